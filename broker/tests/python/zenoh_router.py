"""The plant's zenoh router for broker/tests/bus_router.rs: a zenoh router (eclipse-zenoh
1.10, the same zenoh as zenohd 1.10) running the configuration file it is given, as
zenohd would (`zenohd -c FILE`), then a stranger on that router.

    python3 zenoh_router.py ROUTER_CONFIG ENDPOINT CA CERT KEY

Prints `ready` once the router runs. Then, on "stranger" from stdin, opens a zenoh client
session to ENDPOINT with the certificate CERT/KEY (line-b's, in the test) and tries to
speak for line-a through the router: a put on line-a's data key with a stamp naming
line-a, a registry record and a liveliness token for an invented device of line-a; and,
under its own line's key, a put for line-a's device. Prints `stranger done`. Exits when
stdin closes.
"""

import json
import struct
import sys
import time

import zenoh

CONFIG, ENDPOINT, CA, CERT, KEY = sys.argv[1:6]

router = zenoh.open(zenoh.Config.from_file(CONFIG))
print("ready", flush=True)


def stamp(line, seq):
    return struct.pack(">BBQQ", 1, 1, int(time.time() * 1e6), seq) + line.encode()


def stranger():
    conf = zenoh.Config()
    conf.insert_json5("mode", json.dumps("client"))
    conf.insert_json5("connect/endpoints", json.dumps([ENDPOINT]))
    conf.insert_json5("scouting/multicast/enabled", "false")
    tls = {
        "root_ca_certificate": CA,
        "connect_certificate": CERT,
        "connect_private_key": KEY,
        "enable_mtls": True,
    }
    for key, value in tls.items():
        conf.insert_json5(f"transport/link/tls/{key}", json.dumps(value))
    session = zenoh.open(conf)
    record = {
        "id": "press-7",
        "line": "line-a",
        "status": "online",
        "session": 1,
        "since": "2026-11-25T00:00:00.000Z",
        "last_will_reason": None,
        "interface": {"fbs": {"CONV": {"data_out": {"SPEED": "INT"}}}},
    }
    token = session.liveliness().declare_token("fbbus/@/device/line-a/press-7")
    session.put("fbbus/@/record/line-a/press-7", json.dumps(record))
    for seq in range(1, 6):
        # line-a's own key, stamped line-a: the router must refuse it (line-b's certificate).
        session.put(
            "fbbus/line-a/fb/plc-1/CONV/SPEED", "666", attachment=stamp("line-a", seq)
        )
        # line-b's key, for a device of line-a: through the router, refused by line-a.
        session.put(
            "fbbus/line-b/fb/plc-1/CONV/SPEED", "667", attachment=stamp("line-b", seq)
        )
        time.sleep(0.2)
    time.sleep(1)
    token.undeclare()
    session.close()
    print("stranger done", flush=True)


for line in sys.stdin:
    if line.strip() == "stranger":
        stranger()
router.close()

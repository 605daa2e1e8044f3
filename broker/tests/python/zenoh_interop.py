"""A zenoh application in Python (eclipse-zenoh 1.10) on the fbbus bus, written from
docs/device-contract.md section 7 alone (then fb-bridge/README.md). Run by
broker/tests/bridge.rs against a real line.

Usage: zenoh_interop.py <endpoint> [<bus CA> <certificate> <key>]: with the three files,
over mutual TLS (`tls/` endpoint) as line `line-py` (the certificate's common name).

It joins the bus as a line of its own, `line-py`, with one device `pydev`:
  1. announces the line (a liveliness token) and serves the device's registry record
     (queryable), so fbbus lines know the device, online, and its declared types;
  2. declares interest in everything (`fbbus/@/interest/line-py/fb/%23`) and subscribes
     to `fbbus/*/fb/**`: prints the first fbbus message it sees, with its stamp;
  3. on "put" from stdin, puts pydev's POSITION values 1, 2, "bad", 3 (stamped) on
     `fbbus/line-py/fb/pydev/CONV/POSITION`.

  4. on "query" from stdin, asks every line for its registry records
     (`fbbus/@/record/*/*`) and prints them.

Protocol on stdout, one line each: `ready`, `got <key> <payload> <origin line> <qos>`,
`put`, `records <id@line:status>...`. Every wait is bounded.
"""

import json
import struct
import sys
import threading
import time

import zenoh

ENDPOINT = sys.argv[1]
LINE = "line-py"
DEVICE = "pydev"
INTERFACE = {"fbs": {"CONV": {"type": "CONVEYOR", "data_out": {"POSITION": "INT"}}}}
RECORD = {
    "id": DEVICE,
    "line": LINE,
    "status": "online",
    "session": 1,
    "since": "2026-11-23T00:00:00.000Z",
    "last_will_reason": None,
    "interface": INTERFACE,
}
EPOCH = int(time.time() * 1e6)


def stamp(seq, qos=1, retain=False):
    """docs/device-contract.md section 7: version, flags, epoch, seq (big-endian), line."""
    flags = (qos & 0b11) | (0b100 if retain else 0)
    return struct.pack(">BBQQ", 1, flags, EPOCH, seq) + LINE.encode()


def unstamp(raw):
    """Version 2 (what fbbus puts) has the topic's own number after seq; version 1 not."""
    version, flags, epoch, seq = struct.unpack(">BBQQ", raw[:18])
    assert version in (1, 2), version
    line = raw[26:] if version == 2 else raw[18:]
    return line.decode(), flags & 0b11, seq


def say(*words):
    print(*words, flush=True)


# A zenoh peer linked to the line's endpoint only (no scouting, no listener of its own).
conf = zenoh.Config.from_json5(
    json.dumps(
        {
            "mode": "peer",
            "connect": {"endpoints": [ENDPOINT]},
            "listen": {"endpoints": []},
            "scouting": {"multicast": {"enabled": False}},
        }
    )
)
if len(sys.argv) > 2:
    # The bus between hosts is mutual TLS: the plant's bus CA, and this application's
    # own certificate, whose common name (`line-py`) the lines' [bridge.peers] name.
    ca, cert, key = sys.argv[2:5]
    conf.insert_json5("transport/link/tls/root_ca_certificate", json.dumps(ca))
    conf.insert_json5("transport/link/tls/connect_certificate", json.dumps(cert))
    conf.insert_json5("transport/link/tls/connect_private_key", json.dumps(key))
    conf.insert_json5("transport/link/tls/enable_mtls", "true")
session = zenoh.open(conf)


def answer(query):
    query.reply(f"fbbus/@/record/{LINE}/{DEVICE}", json.dumps(RECORD).encode())


# Records are served before the line is announced: lines query them when they see it.
records = session.declare_queryable(f"fbbus/@/record/{LINE}/*", answer)
tokens = [
    session.liveliness().declare_token(f"fbbus/@/line/{LINE}"),
    session.liveliness().declare_token(f"fbbus/@/interest/{LINE}/fb/%23"),
]

seen = threading.Event()


def on_sample(sample):
    if seen.is_set() or sample.attachment is None:
        return
    origin, qos, _seq = unstamp(sample.attachment.to_bytes())
    seen.set()
    say("got", str(sample.key_expr), sample.payload.to_bytes().decode(), origin, qos)


subscriber = session.declare_subscriber("fbbus/*/fb/**", on_sample)
say("ready")

if not seen.wait(30):
    say("timeout: no fbbus message in 30 s")
    sys.exit(1)

command = sys.stdin.readline().strip()
if command != "put":
    say("unexpected command", command)
    sys.exit(1)
publisher = session.declare_publisher(
    f"fbbus/{LINE}/fb/{DEVICE}/CONV/POSITION",
    congestion_control=zenoh.CongestionControl.BLOCK,
)
for seq, value in enumerate([1, 2, "bad", 3], start=1):
    publisher.put(json.dumps(value).encode(), attachment=stamp(seq))
say("put")

# 4. Registry queries across lines: every line answers for its own devices.
command = sys.stdin.readline().strip()
if command == "query":
    found = []
    for reply in session.get("fbbus/@/record/*/*", timeout=5.0):
        if reply.ok is not None:
            record = json.loads(reply.ok.payload.to_bytes())
            found.append(f"{record['id']}@{record['line']}:{record['status']}")
    say("records", *sorted(found))
    # Keep the tokens up until the test is done with this line.
    sys.stdin.readline()
session.close()

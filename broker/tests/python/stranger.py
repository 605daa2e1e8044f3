"""A stranger on the fbbus bus (issue 22), with Python eclipse-zenoh 1.10: a zenoh peer
that tries to speak for lines and devices that are not its own. Driven by
broker/tests/bus_security.rs, one command a line on stdin, one JSON answer a line on
stdout; the Rust test judges what the lines did with it.

Usage: stranger.py [--ca FILE] [--cert FILE --key FILE] ENDPOINT...
  peer mode, connected to each ENDPOINT, no scouting, no listener of its own. With --ca
  it trusts that CA for the lines' TLS certificates; with --cert/--key it presents that
  certificate (mutual TLS), whose common name is who it is on the bus.

Commands (every wait bounded):
  peers MIN SECS          wait until linked to MIN peers, at most SECS: {"peers": n}
  subscribe KEYEXPR       subscribe, keeping what arrives: {"subscribed": k}
  samples                 what arrived so far: {"samples": n, "keys": [...]}
  alive KEYEXPR           liveliness tokens seen on the bus: {"alive": [...]}
  token KEY / untoken KEY declare / undeclare a liveliness token
  put KEY LINE PAYLOAD    put PAYLOAD on KEY, stamped as a message of LINE
  record LINE DEVICE CLAIMED
                          put a registry record of DEVICE on fbbus/@/record/LINE/DEVICE
                          whose body says it is a device of CLAIMED, with an invented
                          interface (PRESS.STOP: BOOL, PRESS.FORCE: REAL)
  epoch LINE              LINE's epoch, from the stamp of a message of LINE received so
                          far: {"epoch": n or null}
  loss REPORTER ORIGIN N  put a loss report on fbbus/@/loss/REPORTER/ORIGIN: N of
                          ORIGIN's messages (of the epoch `epoch ORIGIN` gives) lost
  play LINE DEVICE        the issue's sequence: declare LINE's liveliness token, put the
                          record of DEVICE, declare DEVICE's token, put STOP true and
                          FORCE 999.5 on fbbus/LINE/fb/DEVICE/PRESS/..., stamped as LINE
  quit
"""

import argparse
import json
import struct
import sys
import threading
import time

import zenoh

PRESS = {
    "fbs": {"PRESS": {"type": "PRESS", "data_out": {"STOP": "BOOL", "FORCE": "REAL"}}}
}
EPOCH = int(time.time() * 1e6)

parser = argparse.ArgumentParser()
parser.add_argument("endpoints", nargs="+")
parser.add_argument("--ca")
parser.add_argument("--cert")
parser.add_argument("--key")
args = parser.parse_args()

conf = zenoh.Config.from_json5(
    json.dumps(
        {
            "mode": "peer",
            "connect": {"endpoints": args.endpoints},
            "listen": {"endpoints": []},
            "scouting": {
                "multicast": {"enabled": False},
                "gossip": {"enabled": False},
            },
        }
    )
)
if args.ca:
    conf.insert_json5("transport/link/tls/root_ca_certificate", json.dumps(args.ca))
if args.cert:
    conf.insert_json5("transport/link/tls/connect_certificate", json.dumps(args.cert))
    conf.insert_json5("transport/link/tls/connect_private_key", json.dumps(args.key))
    conf.insert_json5("transport/link/tls/enable_mtls", "true")
session = zenoh.open(conf)

seq = 0
tokens = {}
subscribers = []
received = []
epochs = {}
lock = threading.Lock()


def stamp(line, qos=1, retain=False):
    """fb-bridge/src/bus/stamp.rs: version, flags, epoch, seq (big-endian), line."""
    global seq
    seq += 1
    flags = (qos & 0b11) | (0b100 if retain else 0)
    return struct.pack(">BBQQ", 1, flags, EPOCH, seq) + line.encode()


def put(key, line, payload):
    session.put(
        key,
        payload.encode(),
        attachment=stamp(line),
        congestion_control=zenoh.CongestionControl.BLOCK,
    )


def record(line, device, claimed):
    body = {
        "id": device,
        "line": claimed,
        "status": "online",
        "session": 1,
        "since": "2026-11-23T00:00:00.000Z",
        "last_will_reason": None,
        "interface": PRESS,
    }
    key = f"fbbus/@/record/{line}/{device}"
    session.put(key, json.dumps(body).encode())
    return key


def token(key):
    tokens[key] = session.liveliness().declare_token(key)


def on_sample(sample):
    stamped = sample.attachment.to_bytes() if sample.attachment is not None else b""
    with lock:
        received.append(str(sample.key_expr))
        # fb-bridge/src/bus/stamp.rs: version 2 is [2, flags, epoch, seq, topic_seq, line].
        if len(stamped) > 26 and stamped[0] == 2:
            epochs[stamped[26:].decode(errors="replace")] = struct.unpack(">Q", stamped[2:10])[0]


def peers():
    return len(list(session.info.peers_zid()))


def run(words):
    command = words[0]
    if command == "peers":
        least, deadline = int(words[1]), time.time() + float(words[2])
        while peers() < least and time.time() < deadline:
            time.sleep(0.05)
        return {"peers": peers()}
    if command == "subscribe":
        subscribers.append(session.declare_subscriber(words[1], on_sample))
        return {"subscribed": words[1]}
    if command == "samples":
        with lock:
            return {"samples": len(received), "keys": sorted(set(received))}
    if command == "alive":
        alive = []
        for reply in session.liveliness().get(words[1], timeout=2.0):
            if reply.ok is not None:
                alive.append(str(reply.ok.key_expr))
        return {"alive": sorted(alive)}
    if command == "token":
        token(words[1])
        return {"token": words[1]}
    if command == "untoken":
        tokens.pop(words[1]).undeclare()
        return {"untoken": words[1]}
    if command == "put":
        put(words[1], words[2], " ".join(words[3:]))
        return {"put": words[1]}
    if command == "record":
        return {"record": record(words[1], words[2], words[3])}
    if command == "epoch":
        with lock:
            return {"epoch": epochs.get(words[1])}
    if command == "loss":
        reporter, origin, lost = words[1], words[2], int(words[3])
        with lock:
            origin_epoch = epochs.get(origin, 0)
        # fb-bridge/src/bus/loss.rs: origin's epoch, the reporter's, the count (big-endian).
        report = struct.pack(">QQQ", origin_epoch, EPOCH, lost)
        session.put(f"fbbus/@/loss/{reporter}/{origin}", report)
        return {"loss": f"fbbus/@/loss/{reporter}/{origin}", "origin_epoch": origin_epoch}
    if command == "play":
        line, device = words[1], words[2]
        token(f"fbbus/@/line/{line}")
        key = record(line, device, line)
        token(f"fbbus/@/device/{line}/{device}")
        put(f"fbbus/{line}/fb/{device}/PRESS/STOP", line, "true")
        put(f"fbbus/{line}/fb/{device}/PRESS/FORCE", line, "999.5")
        return {"played": [f"fbbus/@/line/{line}", key, f"fbbus/@/device/{line}/{device}"]}
    return {"error": f"unknown command {command}"}


for text in sys.stdin:
    words = text.split()
    if not words:
        continue
    if words[0] == "quit":
        break
    try:
        answer = run(words)
    except Exception as e:  # reported, the test decides
        answer = {"error": f"{type(e).__name__}: {e}"}
    print(json.dumps(answer), flush=True)
session.close()

#!/usr/bin/env python3
"""MQTT over WebSockets with Eclipse paho-mqtt 2.x (`transport="websockets"`).

Driven by broker/tests/websocket.rs:

    ws_paho.py --port P [--path /mqtt] [--ca ca.crt] [--protocol 5|311] [--user U --password P]

As device `ws-dev` it declares a panel with a BOOL and an INT output, subscribes to its
own fb/ subtree, publishes BOOL `1` (accepted, delivered as `true`) and, with MQTT 5,
`2` (refused by the typed check, PUBACK reason 0x99). Prints one JSON line of what it
saw and exits 0 when every expectation held. Every wait is bounded (10 s).
"""

import argparse
import json
import queue
import sys

import paho.mqtt.client as mqtt
from paho.mqtt.enums import CallbackAPIVersion

WAIT = 10.0
DEVICE = "ws-dev"
DECLARATION = json.dumps({"fbs": {"PANEL": {
    "data_out": {"ON": "BOOL", "COUNT": "INT"}}}})

p = argparse.ArgumentParser()
p.add_argument("--port", type=int, required=True)
p.add_argument("--path", default="/mqtt")
p.add_argument("--ca")
p.add_argument("--protocol", default="5")
p.add_argument("--user")
p.add_argument("--password")
args = p.parse_args()
v5 = args.protocol == "5"

seen = {}


def fail(why):
    seen["error"] = why
    print(json.dumps(seen), flush=True)
    print(why, file=sys.stderr)
    sys.exit(1)


events = queue.Queue()
client = mqtt.Client(
    CallbackAPIVersion.VERSION2,
    client_id=DEVICE,
    protocol=mqtt.MQTTv5 if v5 else mqtt.MQTTv311,
    transport="websockets",
)
client.ws_set_options(path=args.path)
if args.ca:
    client.tls_set(ca_certs=args.ca)
if args.user:
    client.username_pw_set(args.user, args.password)
client.on_connect = lambda c, u, flags, rc, props: events.put(("connect", rc.value))
client.on_subscribe = lambda c, u, mid, rcs, props: events.put(("suback", [r.value for r in rcs]))
client.on_message = lambda c, u, m: events.put(("message", m.topic, m.payload.decode()))
client.on_publish = lambda c, u, mid, rc, props: events.put(("puback", mid, rc.value))


def wait_for(kind, accept=lambda e: True):
    while True:
        try:
            event = events.get(timeout=WAIT)
        except queue.Empty:
            fail(f"no {kind} within {WAIT} s")
        if event[0] == kind and accept(event):
            return event


client.connect("127.0.0.1", args.port, keepalive=30)
client.loop_start()
try:
    seen["connack"] = wait_for("connect")[1]
    if seen["connack"] != 0:
        fail(f"CONNECT refused: {seen['connack']}")
    client.subscribe([(f"fbbus/diag/{DEVICE}", 1), (f"fb/{DEVICE}/#", 1)])
    seen["suback"] = wait_for("suback")[1]
    client.publish(f"fbbus/declare/{DEVICE}", DECLARATION, qos=1)
    answer = json.loads(wait_for("message", lambda e: e[1] == f"fbbus/diag/{DEVICE}")[2])
    seen["declared"] = answer.get("ok")
    if answer.get("ok") is not True:
        fail(f"declaration refused: {answer}")

    info = client.publish(f"fb/{DEVICE}/PANEL/ON", "1", qos=1)
    seen["bool_puback"] = wait_for("puback", lambda e: e[1] == info.mid)[2]
    topic, payload = wait_for("message", lambda e: e[1].startswith("fb/"))[1:]
    seen["delivered"] = [topic, payload]
    if (topic, payload) != (f"fb/{DEVICE}/PANEL/ON", "true"):
        fail(f"expected true on fb/{DEVICE}/PANEL/ON, got {payload!r} on {topic}")
    if v5:
        info = client.publish(f"fb/{DEVICE}/PANEL/COUNT", '"many"', qos=1)
        seen["refused_puback"] = wait_for("puback", lambda e: e[1] == info.mid)[2]
        if seen["refused_puback"] != 0x99:
            fail(f"expected PUBACK 0x99 for a STRING on an INT port, got {seen['refused_puback']}")
finally:
    client.disconnect()
    client.loop_stop()
print(json.dumps(seen), flush=True)

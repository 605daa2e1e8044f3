#!/usr/bin/env python3
"""A device written from the device contract alone (docs/device-contract.md, then
fb-bridge/README.md), with Eclipse paho-mqtt 2.x (MQTT 5).

    fb_contract.py --port 1883 [--host 127.0.0.1] [--device py-dev]

The device:

1. connects with its id as client id and username (contract section 1) and subscribes to
   its diag topic `fbbus/diag/<id>` before declaring (section 2);
2. declares one FB whose event output MOVED carries WITH data (INT, STRING, TIME,
   ARRAY [3] OF REAL) and checks the `{"kind": "declaration", "ok": true, ...}` answer;
3. subscribes to `fb/<id>/#` and `fbdk/<id>/#` (section 3: subscribe first, the broker
   re-encodes once someone can read the namespace);
4. publishes a valid event without seq/ts (PUBACK reason 0), an ill-typed one (INT 70000:
   PUBACK reason 0x99, read in on_publish, and a `rejected` diag with code 153) and a
   second valid one;
5. checks that fb/ subscribers got exactly the two valid events in canonical JSON with
   seq and ts stamped, and fbdk/ subscribers the bytes computed here from the contract's
   byte layout;
6. reads its retained registry record `fbbus/devices/<id>` and the line's retained online
   count `fbbus/lines/<line>/online` (section 4).

Prints one JSON line with what it observed; exits 0 when every check holds, 1 otherwise
with the failed check on stderr. Every wait is bounded (10 s).

Driven by broker/tests/fb_contract.rs (`python_device_follows_the_readme_contract`).
"""

import argparse
import json
import queue
import struct
import sys
import threading
import time

import paho.mqtt.client as mqtt
from paho.mqtt.enums import CallbackAPIVersion

WAIT = 10.0

# fbdk (contract section 3, "Other encodings of the same ports"): each value is a tag byte
# `0x40 | type number` and a big-endian value. The type numbers are the IEC 61499
# compliance profile's (ASN.1 application tags), spelled out here for the types this
# device uses.
TYPE_NUMBER = {"BOOL": 1, "INT": 3, "REAL": 10, "TIME": 12, "STRING": 16}
ARRAY_TAG = 0x76


def tag(type_name):
    return bytes([0x40 | TYPE_NUMBER[type_name]])


def fbdk_int(n):
    return tag("INT") + struct.pack(">h", n)


def fbdk_string(s):
    raw = s.encode("utf-8")
    return tag("STRING") + struct.pack(">H", len(raw)) + raw


def fbdk_time_us(us):
    # TIME is signed microseconds (8 bytes, like LINT).
    return tag("TIME") + struct.pack(">q", us)


def fbdk_real_array(values):
    # Arrays: 0x76, a 2-byte count, the element tag once, then the bare values.
    return (
        bytes([ARRAY_TAG])
        + struct.pack(">H", len(values))
        + tag("REAL")
        + b"".join(struct.pack(">f", v) for v in values)
    )


class CheckFailed(Exception):
    pass


def check(condition, message):
    if not condition:
        raise CheckFailed(message)


class Device:
    def __init__(self, host, port, device):
        self.device = device
        self.c = mqtt.Client(
            callback_api_version=CallbackAPIVersion.VERSION2,
            client_id=device,
            protocol=mqtt.MQTTv5,
            reconnect_on_failure=False,
        )
        # Contract section 1: the device id as client id and username.
        self.c.username_pw_set(device, None)
        self.connected = threading.Event()
        self.connect_reason = None
        self.messages = {}  # topic -> queue of (payload, retain)
        self.lock = threading.Lock()
        self.acks = {}  # mid -> reason code value
        self.ack_event = threading.Condition()
        self.subacks = queue.Queue()
        self.c.on_connect = self.on_connect
        self.c.on_message = self.on_message
        self.c.on_publish = self.on_publish
        self.c.on_subscribe = self.on_subscribe
        self.c.connect(host, port, keepalive=30)
        self.c.loop_start()
        check(self.connected.wait(WAIT), "no CONNACK")
        check(self.connect_reason == 0, f"CONNECT refused: {self.connect_reason}")

    # paho 2 (CallbackAPIVersion.VERSION2) callbacks
    def on_connect(self, client, userdata, flags, reason_code, properties):
        self.connect_reason = reason_code.value
        self.connected.set()

    def on_message(self, client, userdata, message):
        with self.lock:
            q = self.messages.setdefault(message.topic, queue.Queue())
        q.put((bytes(message.payload), message.retain))

    def on_publish(self, client, userdata, mid, reason_code, properties):
        with self.ack_event:
            self.acks[mid] = reason_code.value
            self.ack_event.notify_all()

    def on_subscribe(self, client, userdata, mid, reason_codes, properties):
        self.subacks.put([rc.value for rc in reason_codes])

    def queue_for(self, topic):
        with self.lock:
            return self.messages.setdefault(topic, queue.Queue())

    def subscribe(self, *filters):
        result, _ = self.c.subscribe([(f, 1) for f in filters])
        check(result == mqtt.MQTT_ERR_SUCCESS, f"SUBSCRIBE {filters}: {result}")
        try:
            codes = self.subacks.get(timeout=WAIT)
        except queue.Empty:
            raise CheckFailed(f"no SUBACK for {filters}")
        check(all(c <= 2 for c in codes), f"SUBACK for {filters}: {codes}")

    def publish(self, topic, payload):
        """Publishes at QoS 1 and returns the PUBACK reason code."""
        info = self.c.publish(topic, payload, qos=1)
        check(info.rc == mqtt.MQTT_ERR_SUCCESS, f"publish {topic}: {info.rc}")
        deadline = time.monotonic() + WAIT
        with self.ack_event:
            while info.mid not in self.acks:
                left = deadline - time.monotonic()
                check(left > 0, f"no PUBACK for {topic}")
                self.ack_event.wait(left)
            return self.acks.pop(info.mid)

    def next(self, topic, what):
        try:
            return self.queue_for(topic).get(timeout=WAIT)[0]
        except queue.Empty:
            raise CheckFailed(f"nothing on {topic} ({what}) within {WAIT} s")

    def next_json(self, topic, what):
        payload = self.next(topic, what)
        try:
            return json.loads(payload)
        except ValueError as e:
            raise CheckFailed(f"{topic} ({what}): not JSON ({e}): {payload!r}")

    def quiet(self, topic, seconds):
        try:
            payload, _ = self.queue_for(topic).get(timeout=seconds)
        except queue.Empty:
            return None
        return payload

    def close(self):
        self.c.disconnect()
        self.c.loop_stop()


def run(args, observed):
    dev = Device(args.host, args.port, args.device)
    d = args.device
    diag = f"fbbus/diag/{d}"
    dev.subscribe(diag)

    declaration = {
        "fbs": {
            "CONV": {
                "type": "CONVEYOR",
                "events_out": {"MOVED": {"with": ["N", "NAME", "CYCLE", "LEVELS"]}},
                "data_out": {
                    "N": "INT",
                    "NAME": "STRING",
                    "CYCLE": "TIME",
                    "LEVELS": "ARRAY [3] OF REAL",
                },
                "events_in": {"START": {"with": ["SPEED"]}},
                "data_in": {"SPEED": "REAL"},
            }
        }
    }
    code = dev.publish(f"fbbus/declare/{d}", json.dumps(declaration))
    observed["declare_puback"] = code
    check(code == 0, f"declaration PUBACK reason {code:#04x}")
    answer = dev.next_json(diag, "declaration answer")
    observed["declaration"] = answer
    check(answer.get("kind") == "declaration", f"diag answer {answer}")
    check(answer.get("ok") is True, f"declaration refused: {answer}")
    session = answer.get("session")
    line = answer.get("line")
    check(isinstance(session, int) and session >= 1, f"session {session!r}")
    check(isinstance(line, str) and line, f"line {line!r}")

    event_topic = f"fb/{d}/CONV/MOVED"
    fbdk_topic = f"fbdk/{d}/CONV/MOVED"
    dev.subscribe(f"fb/{d}/#", f"fbdk/{d}/#")

    valid = {"N": 5, "NAME": "py", "CYCLE": "T#1s500ms", "LEVELS": [0.5, 1.5, -2.25]}
    before_us = time.time_ns() // 1000
    code = dev.publish(event_topic, json.dumps({"data": valid}))
    observed["valid_puback"] = code
    check(code == 0, f"valid event PUBACK reason {code:#04x}")

    invalid = dict(valid, N=70000)
    code = dev.publish(event_topic, json.dumps({"data": invalid}))
    observed["invalid_puback"] = code
    check(code == 0x99, f"ill-typed event PUBACK reason {code:#04x}, expected 0x99")
    rejected = dev.next_json(diag, "rejection")
    observed["rejected"] = rejected
    check(
        rejected.get("kind") == "rejected"
        and rejected.get("code") == 153
        and rejected.get("reason") == "payload_format_invalid"
        and rejected.get("topic") == event_topic,
        f"rejection diag {rejected}",
    )

    second = dict(valid, N=6, NAME="")
    code = dev.publish(event_topic, json.dumps({"data": second}))
    check(code == 0, f"second valid event PUBACK reason {code:#04x}")
    after_us = time.time_ns() // 1000

    # Canonical JSON: exactly the two valid events, in order, with seq and ts stamped.
    got = [dev.next_json(event_topic, "first event"), dev.next_json(event_topic, "second event")]
    observed["fb"] = got
    for message, data in zip(got, [valid, second]):
        check(message.get("data") == data, f"fb/ event {message}, expected data {data}")
        ts = message.get("ts")
        check(
            isinstance(message.get("seq"), int) and isinstance(ts, int),
            f"seq/ts not stamped: {message}",
        )
        check(before_us <= ts <= after_us, f"ts {ts} not within [{before_us}, {after_us}]")
    check(got[1]["seq"] > got[0]["seq"], f"seq does not grow: {got}")
    extra = dev.quiet(event_topic, 0.3)
    check(extra is None, f"an extra message on {event_topic}: {extra!r}")

    # fbdk: the WITH values in WITH order, from the contract's byte layout.
    def fbdk_event(data):
        return (
            fbdk_int(data["N"])
            + fbdk_string(data["NAME"])
            + fbdk_time_us(1_500_000)
            + fbdk_real_array(data["LEVELS"])
        )

    for data, what in [(valid, "first"), (second, "second")]:
        payload = dev.next(fbdk_topic, f"{what} fbdk event")
        expected = fbdk_event(data)
        observed.setdefault("fbdk", []).append(payload.hex())
        check(payload == expected, f"fbdk {what}: {payload.hex()}, expected {expected.hex()}")
    extra = dev.quiet(fbdk_topic, 0.3)
    check(extra is None, f"an extra message on {fbdk_topic}: {extra!r}")

    # The registry, retained.
    record_topic = f"fbbus/devices/{d}"
    count_topic = f"fbbus/lines/{line}/online"
    dev.subscribe(record_topic, count_topic)
    record = dev.next_json(record_topic, "registry record")
    observed["record"] = {k: v for k, v in record.items() if k != "interface"}
    check(record.get("id") == d, f"record {record}")
    check(record.get("status") == "online", f"record status {record.get('status')}")
    check(record.get("session") == session, f"record session {record.get('session')}, declared {session}")
    check(record.get("line") == line, f"record line {record.get('line')}")
    check(record.get("last_will_reason") is None, f"last_will_reason {record.get('last_will_reason')}")
    fbs = record.get("interface", {}).get("fbs", {})
    check(
        fbs.get("CONV", {}).get("events_out", {}).get("MOVED", {}).get("with")
        == ["N", "NAME", "CYCLE", "LEVELS"],
        f"record interface {record.get('interface')}",
    )
    count = dev.next(count_topic, "online count")
    observed["online"] = count.decode(errors="replace")
    check(count == b"1", f"online count {count!r}")

    dev.close()


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--host", default="127.0.0.1")
    parser.add_argument("--port", type=int, required=True)
    parser.add_argument("--device", default="py-dev")
    args = parser.parse_args()
    observed = {}
    try:
        run(args, observed)
    except CheckFailed as e:
        observed["error"] = str(e)
        print(json.dumps(observed))
        print(f"FAILED: {e}", file=sys.stderr)
        return 1
    except Exception as e:  # a connection error, a paho error: still one precise line
        observed["error"] = f"{type(e).__name__}: {e}"
        print(json.dumps(observed))
        print(f"FAILED: unexpected {type(e).__name__}: {e}", file=sys.stderr)
        return 1
    print(json.dumps(observed))
    return 0


if __name__ == "__main__":
    sys.exit(main())

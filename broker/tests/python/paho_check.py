#!/usr/bin/env python3
"""Interoperability checks of fbbus with a third-party client: Eclipse paho-mqtt 2.x.

Runs one scenario against a broker on 127.0.0.1:PORT, prints one JSON line with what it
observed, and exits 0 when the scenario's expectations hold, 1 otherwise (the reason is
in the JSON `error` field and on stderr). Every wait is bounded (at most 10 s).

    paho_check.py --port 1883 --scenario pubsub --protocol 5 [--user U --password P]

Scenarios: pubsub, delivery_qos, bad_password, acl, acl_qos2, will, keepalive0, shutdown5, shutdown311.
`shutdown5`/`shutdown311` print a line `READY` once connected; the caller then stops the
broker (SIGTERM) and the script waits for the connection to end.

Driven by broker/tests/paho.rs; the ACL and password file it sets up are described there.
"""

import argparse
import json
import queue
import sys
import threading
import time

import paho.mqtt
import paho.mqtt.client as mqtt
from paho.mqtt.enums import CallbackAPIVersion
from paho.mqtt.packettypes import PacketTypes
from paho.mqtt.reasoncodes import ReasonCode

HOST = "127.0.0.1"
WAIT = 10.0  # the longest any single wait may take

# paho 2.x maps MQTT 3.1.1 CONNACK return codes to MQTT 5 reason codes in on_connect
# (4 "bad user name or password" arrives as 134); this is the way back, by name.
V311_CONNACK_BY_NAME = {
    "Success": 0,
    "Unsupported protocol version": 1,
    "Client identifier not valid": 2,
    "Server unavailable": 3,
    "Bad user name or password": 4,
    "Not authorized": 5,
}


class CheckFailed(Exception):
    pass


def check(condition, message):
    if not condition:
        raise CheckFailed(message)


class Client:
    """A paho client whose callbacks land in events and queues the scenario can wait on."""

    def __init__(self, args, client_id, user=None, password=None, keepalive=30):
        self.args = args
        self.v5 = args.protocol == "5"
        self.client_id = client_id
        self.keepalive = keepalive
        self.c = mqtt.Client(
            callback_api_version=CallbackAPIVersion.VERSION2,
            client_id=client_id,
            protocol=mqtt.MQTTv5 if self.v5 else mqtt.MQTTv311,
            # A refused CONNECT must not be retried behind the test's back (it would
            # also trip the broker's login throttle).
            reconnect_on_failure=False,
        )
        if user is not None:
            self.c.username_pw_set(user, password)
        self.connected = threading.Event()
        self.connack = None  # the code as the broker sent it (3.1.1 return code or 5 reason)
        self.connack_reason = None  # paho's ReasonCode, as a name
        self.disconnected = threading.Event()
        self.disconnect_reason = None
        self.disconnect_reason_name = None
        self.disconnect_from_server = None
        self.messages = queue.Queue()
        self.lock = threading.Lock()
        self.subacks = {}  # mid -> [reason code values]
        self.subacked = threading.Condition(self.lock)
        self.pubacks = {}  # mid -> reason code value
        self.pubacked = threading.Condition(self.lock)
        self.c.on_connect = self._on_connect
        self.c.on_disconnect = self._on_disconnect
        self.c.on_message = self._on_message
        self.c.on_subscribe = self._on_subscribe
        self.c.on_publish = self._on_publish
        self.loop_running = False
        # paho does not report a PUBREC's reason code (and sends PUBREL even after a
        # refusal); the raw packet is read here, before paho handles it.
        self.pubrecs = {}  # mid -> reason code value (0 when absent)
        handle_pubrec = getattr(self.c, "_handle_pubrec", None)
        if handle_pubrec is not None:
            def _handle_pubrec():
                raw = bytes(self.c._in_packet.get("packet", b""))
                if len(raw) >= 2:
                    with self.lock:
                        self.pubrecs[int.from_bytes(raw[:2], "big")] = raw[2] if len(raw) > 2 else 0
                return handle_pubrec()
            self.c._handle_pubrec = _handle_pubrec

    # Callbacks (paho's network thread).

    def _on_connect(self, client, userdata, flags, reason_code, properties):
        if self.v5:
            self.connack = reason_code.value
        else:
            # The raw CONNACK is still in paho's input buffer while on_connect runs; prefer
            # it, fall back to mapping paho's reason code name back.
            raw = bytes(getattr(client, "_in_packet", {}).get("packet", b""))
            if len(raw) == 2:
                self.connack = raw[1]
            else:
                self.connack = V311_CONNACK_BY_NAME.get(reason_code.getName(), -1)
        self.connack_reason = reason_code.getName()
        self.connected.set()

    def _on_disconnect(self, client, userdata, flags, reason_code, properties):
        self.disconnect_reason = reason_code.value if reason_code is not None else None
        self.disconnect_reason_name = reason_code.getName() if reason_code is not None else None
        self.disconnect_from_server = flags.is_disconnect_packet_from_server
        self.disconnected.set()
        with self.lock:  # wake waiters: what they wait for will not come any more
            self.subacked.notify_all()
            self.pubacked.notify_all()

    def ended(self):
        """Why the connection ended, for messages."""
        source = "DISCONNECT from the broker" if self.disconnect_from_server else "closed"
        return f"connection ended ({source}, reason {self.disconnect_reason} {self.disconnect_reason_name})"

    def _on_message(self, client, userdata, message):
        self.messages.put(
            {
                "topic": message.topic,
                "payload": bytes(message.payload),
                "qos": message.qos,
                "retain": bool(message.retain),
                "at": time.monotonic(),
            }
        )

    def _on_subscribe(self, client, userdata, mid, reason_codes, properties):
        with self.lock:
            self.subacks[mid] = [rc.value for rc in reason_codes]
            self.subacked.notify_all()

    def _on_publish(self, client, userdata, mid, reason_code, properties):
        with self.lock:
            self.pubacks[mid] = reason_code.value
            self.pubacked.notify_all()

    # Operations (the scenario's thread).

    def connect(self, expect_success=True):
        """Connects and waits for CONNACK; returns the broker's code (None: no CONNACK)."""
        self.c.connect(HOST, self.args.port, keepalive=self.keepalive)
        self.c.loop_start()
        self.loop_running = True
        if not self.connected.wait(WAIT):
            if expect_success:
                raise CheckFailed(f"{self.client_id}: no CONNACK within {WAIT} s")
            return None
        if expect_success:
            check(
                self.connack == 0,
                f"{self.client_id}: CONNECT refused with code {self.connack} ({self.connack_reason})",
            )
        return self.connack

    def subscribe(self, topics):
        """Subscribes to [(filter, qos)] in one SUBSCRIBE; returns the SUBACK codes."""
        rc, mid = self.c.subscribe(topics)
        check(rc == mqtt.MQTT_ERR_SUCCESS, f"{self.client_id}: subscribe {topics} failed to send: {rc}")
        with self.lock:
            self.subacked.wait_for(lambda: mid in self.subacks or self.disconnected.is_set(), WAIT)
            if mid not in self.subacks:
                why = self.ended() if self.disconnected.is_set() else f"not within {WAIT} s"
                raise CheckFailed(f"{self.client_id}: no SUBACK for {topics}: {why}")
            return self.subacks[mid]

    def publish(self, topic, payload, qos):
        """Publishes; returns the mid (wait for its acknowledgement with `acked`)."""
        info = self.c.publish(topic, payload, qos=qos)
        check(info.rc == mqtt.MQTT_ERR_SUCCESS, f"{self.client_id}: publish to {topic} failed: {info.rc}")
        return info.mid

    def acked(self, mid):
        """Waits until paho reports the publication done; returns its reason code value."""
        with self.lock:
            self.pubacked.wait_for(lambda: mid in self.pubacks or self.disconnected.is_set(), WAIT)
            if mid not in self.pubacks:
                why = self.ended() if self.disconnected.is_set() else f"not within {WAIT} s"
                raise CheckFailed(f"{self.client_id}: publication mid {mid} not acknowledged: {why}")
            return self.pubacks[mid]

    def next_message(self, timeout=WAIT):
        try:
            return self.messages.get(timeout=min(timeout, WAIT))
        except queue.Empty:
            return None

    def drain(self, quiet):
        """Collects messages until none arrived for `quiet` seconds."""
        got = []
        while True:
            m = self.next_message(quiet)
            if m is None:
                return got
            got.append(m)

    def disconnect(self, reasoncode=None):
        self.c.disconnect(reasoncode=reasoncode)
        if not self.disconnected.wait(WAIT):
            raise CheckFailed(f"{self.client_id}: disconnect() did not complete within {WAIT} s")
        self.stop()

    def stop(self):
        if self.loop_running:
            self.loop_running = False
            self.c.loop_stop()

    def kill_socket(self):
        """Ends the TCP connection without DISCONNECT, as a device losing power would."""
        self.stop()  # paho's thread must not notice and send anything
        sock = self.c.socket()
        check(sock is not None, f"{self.client_id}: no socket to close")
        sock.close()


def message_summary(m):
    return {"topic": m["topic"], "payload": m["payload"].decode("latin-1"), "qos": m["qos"]}


# Scenarios. Each returns a dict of observations and raises CheckFailed when an
# expectation does not hold (the observations so far go into the output).


def payload_for(phase, i, qos):
    # Binary payloads of varying length, with bytes that are not UTF-8.
    return f"{phase}-{i:02d}-q{qos}-".encode() + bytes([0, 0xFF, i]) + bytes(range(i * 7 % 256)) * 3


def receive(sub, count):
    received = []
    deadline = time.monotonic() + WAIT
    while len(received) < count and time.monotonic() < deadline:
        m = sub.next_message(deadline - time.monotonic())
        if m is None:
            break
        received.append(m)
    return received


def scenario_pubsub(args, seen):
    """20 messages at QoS 0, 1, 2 to t/x, subscribed at QoS 1, twice:

    * burst: published back to back; MQTT (4.6.0-6) orders deliveries per topic *and QoS*,
      so each QoS level must arrive in publication order (a QoS 2 message may be routed at
      PUBREL, after later QoS 0/1 messages);
    * sequential: each publication completes before the next is sent, so all 20 must
      arrive in exactly the publication order.
    """
    sub = Client(args, f"paho-sub-{args.protocol}", args.user, args.password)
    pub = Client(args, f"paho-pub-{args.protocol}", args.user, args.password)
    clients = [sub, pub]
    try:
        seen["sub_connack"] = sub.connect()
        seen["pub_connack"] = pub.connect()
        codes = sub.subscribe([("t/#", 1)])
        seen["suback"] = codes
        check(codes == [1], f"SUBACK for t/# at QoS 1 was {codes}, expected [1]")

        for phase in ("burst", "sequential"):
            sent = []
            reasons = []
            mids = []
            for i in range(20):
                qos = i % 3
                payload = payload_for(phase, i, qos)
                mid = pub.publish("t/x", payload, qos)
                sent.append((qos, payload))
                if phase == "sequential":
                    reasons.append(pub.acked(mid))
                else:
                    mids.append(mid)
            reasons += [pub.acked(mid) for mid in mids]
            seen[f"{phase}_publish_reason_codes"] = reasons
            check(all(rc == 0 for rc in reasons), f"{phase}: publications not all acknowledged with success: {reasons}")

            received = receive(sub, len(sent))
            order = [m["payload"].split(b"-q")[0].decode("latin-1") for m in received]
            seen[f"{phase}_received_order"] = order
            check(len(received) == len(sent), f"{phase}: received {len(received)} of {len(sent)} messages: {order}")
            check(all(m["topic"] == "t/x" for m in received), f"{phase}: wrong topics: {[m['topic'] for m in received]}")
            payloads = [m["payload"] for m in received]
            check(sorted(payloads) == sorted(p for _, p in sent), f"{phase}: payloads not received intact: {order}")
            for qos in (0, 1, 2):
                want = [p for q, p in sent if q == qos]
                got = [p for p in payloads if p in want]
                check(got == want, f"{phase}: QoS {qos} messages out of order: {order}")
            if phase == "sequential":
                check(payloads == [p for _, p in sent], f"{phase}: not received in publication order: {order}")
                # Recorded only: the delivery QoS is checked by the `delivery_qos` scenario.
                seen[f"{phase}_delivery_qos"] = [m["qos"] for m in received]
            extra = sub.drain(0.5)
            check(not extra, f"{phase}: {len(extra)} unexpected extra deliveries: {[message_summary(m) for m in extra]}")
        sub.disconnect()
        pub.disconnect()
    finally:
        for c in clients:
            c.stop()


def scenario_delivery_qos(args, seen):
    """MQTT 3.1.1 3.8.4 / MQTT 5 [MQTT-3.8.4-8]: a message is delivered at the minimum of
    its publication QoS and the subscription's granted QoS. Three subscribers (QoS 0, 1, 2)
    each receive one message published at QoS 0, 1 and 2."""
    subs = {q: Client(args, f"paho-dq-sub{q}-{args.protocol}") for q in (0, 1, 2)}
    pub = Client(args, f"paho-dq-pub-{args.protocol}")
    clients = [*subs.values(), pub]
    try:
        for q, sub in subs.items():
            sub.connect()
            codes = sub.subscribe([("q/#", q)])
            check(codes == [q], f"SUBACK for q/# at QoS {q} was {codes}")
        pub.connect()
        for q in (0, 1, 2):
            check(pub.acked(pub.publish(f"q/{q}", f"published-q{q}".encode(), q)) == 0,
                  f"QoS {q} publication not acknowledged")
        matrix = {}  # "sub S, pub P" -> delivered QoS
        wrong = []
        for s, sub in subs.items():
            got = receive(sub, 3)
            check(len(got) == 3, f"QoS {s} subscriber received {len(got)} of 3 messages")
            for m in got:
                p = int(m["topic"].split("/")[1])
                matrix[f"sub{s}_pub{p}"] = m["qos"]
                if m["qos"] != min(s, p):
                    wrong.append(f"published at QoS {p}, subscribed at QoS {s}: delivered at QoS {m['qos']}, expected {min(s, p)}")
        seen["delivered_qos"] = matrix
        check(not wrong, "; ".join(wrong))
        for c in clients:
            c.disconnect()
    finally:
        for c in clients:
            c.stop()


def scenario_bad_password(args, seen):
    check(args.user is not None and args.password is not None, "bad_password needs --user and --password")
    bad = Client(args, f"paho-bad-{args.protocol}", args.user, args.password)
    try:
        code = bad.connect(expect_success=False)
        seen["connack"] = code
        seen["connack_reason"] = bad.connack_reason
        expected = 0x86 if bad.v5 else 4
        check(code is not None, "no CONNACK for the wrong password (connection dropped?)")
        check(code == expected, f"CONNACK code {code} ({bad.connack_reason}), expected {expected}")
        # The broker closes the connection after refusing.
        seen["closed_after_refusal"] = bad.disconnected.wait(WAIT)
        check(seen["closed_after_refusal"], "connection not closed after the refused CONNECT")
    finally:
        bad.stop()
    if args.good_password is not None:
        good = Client(args, f"paho-good-{args.protocol}", args.user, args.good_password)
        try:
            seen["good_connack"] = good.connect()
            good.disconnect()
        finally:
            good.stop()


def scenario_acl(args, seen):
    """User dev1 may write plant/dev1/# and read plant/#; nothing else."""
    check(args.user is not None and args.password is not None, "acl needs --user and --password")
    c = Client(args, f"{args.user}-paho-{args.protocol}", args.user, args.password)
    mixed = Client(args, f"{args.user}-mixed-{args.protocol}", args.user, args.password)
    refused = 0x87 if c.v5 else 0x80
    try:
        seen["connack"] = c.connect()

        codes = c.subscribe([("secret/#", 1)])
        seen["suback_secret"] = codes
        check(codes == [refused], f"SUBACK for secret/# was {codes}, expected [{refused}]")

        codes = c.subscribe([("plant/#", 1)])
        seen["suback_fb"] = codes
        check(codes == [1], f"SUBACK for plant/# was {codes}, expected [1] (granted QoS 1)")

        # One SUBACK with one code per filter, in order, when only some filters are allowed.
        seen["mixed_connack"] = mixed.connect()
        codes = mixed.subscribe([("secret/a", 1), ("plant/dev1/#", 0), ("plant/+/y", 1)])
        seen["suback_mixed"] = codes
        check(codes == [refused, 0, 1], f"SUBACK for [secret/a, plant/dev1/#, plant/+/y] was {codes}, expected [{refused}, 0, 1]")
        mixed.disconnect()

        # Foreign topic, QoS 1: refused (5: PUBACK 0x87; 3.1.1: acknowledged, dropped).
        mid = c.publish("plant/dev2/x", b"foreign-q1", 1)
        seen["puback_foreign"] = rc = c.acked(mid)
        expected = 0x87 if c.v5 else 0
        check(rc == expected, f"PUBACK for plant/dev2/x was {rc}, expected {expected}")

        # Foreign topic, QoS 0: silently dropped.
        c.publish("plant/dev2/z", b"foreign-q0", 0)

        # Own topic: delivered.
        mid = c.publish("plant/dev1/x", b"own", 1)
        seen["puback_own"] = rc = c.acked(mid)
        check(rc == 0, f"PUBACK for plant/dev1/x was {rc}, expected 0")

        got = c.drain(1.5)
        seen["received"] = [message_summary(m) for m in got]
        foreign = [m for m in got if m["topic"].startswith("plant/dev2/")]
        check(not foreign, f"refused publications were delivered: {[message_summary(m) for m in foreign]}")
        own = [m for m in got if m["topic"] == "plant/dev1/x"]
        check(len(own) == 1 and own[0]["payload"] == b"own", f"plant/dev1/x delivered {len(own)} times, expected once")

        # The connection is still usable after the refusals.
        mid = c.publish("plant/dev1/after", b"after", 1)
        check(c.acked(mid) == 0, "publication after the refusals not acknowledged")
        m = c.next_message()
        seen["after"] = message_summary(m) if m else None
        check(m is not None and m["topic"] == "plant/dev1/after", f"plant/dev1/after not delivered: {seen['after']}")
        c.disconnect()
    finally:
        c.stop()
        mixed.stop()


def scenario_acl_qos2(args, seen):
    """A refused QoS 2 publication (same ACL as `acl`): the flow completes, the connection
    stays up, nothing is delivered, and the next QoS 2 publication works.

    3.1.1: PUBREC (success), PUBREL, PUBCOMP, as for any publication (there is no refusal).
    5: PUBREC 0x87 (not authorized). paho 2.x sends PUBREL even after a refused PUBREC (it
    ignores PUBREC reason codes); MQTT 5 (4.3.3-11) has the receiver answer any PUBREL with
    PUBCOMP, 0x92 (packet identifier not found) when it has no state for it.
    """
    check(args.user is not None and args.password is not None, "acl_qos2 needs --user and --password")
    c = Client(args, f"{args.user}-q2-{args.protocol}", args.user, args.password)
    try:
        seen["connack"] = c.connect()
        codes = c.subscribe([("plant/#", 2)])
        seen["suback_fb"] = codes
        check(codes == [2], f"SUBACK for plant/# at QoS 2 was {codes}, expected [2]")

        mid = c.publish("plant/dev2/y", b"foreign-q2", 2)
        try:
            seen["pubcomp_foreign"] = rc = c.acked(mid)
        finally:
            seen["pubrec_foreign"] = c.pubrecs.get(mid)
            seen["disconnected"] = c.disconnected.is_set()
            if c.disconnected.is_set():
                seen["disconnect_reason"] = c.disconnect_reason
                seen["disconnect_reason_name"] = c.disconnect_reason_name
                seen["disconnect_from_server"] = c.disconnect_from_server
        time.sleep(0.2)  # a DISCONNECT right after the PUBCOMP would count too
        check(not c.disconnected.is_set(), f"refused QoS 2 publication: {c.ended()}")
        if c.v5:
            check(seen["pubrec_foreign"] in (None, 0x87), f"PUBREC reason {seen['pubrec_foreign']}, expected 135 (0x87)")
            check(rc in (0, 0x92), f"PUBCOMP reason {rc}, expected 0 or 146 (0x92)")
        else:
            check(rc == 0, f"QoS 2 publication to plant/dev2/y completed with {rc}, expected 0")

        mid = c.publish("plant/dev1/y", b"own-q2", 2)
        seen["pubcomp_own"] = rc = c.acked(mid)
        seen["pubrec_own"] = c.pubrecs.get(mid)
        check(rc == 0, f"own QoS 2 publication completed with {rc}, expected 0")

        got = c.drain(1.5)
        seen["received"] = [message_summary(m) for m in got]
        check([(m["topic"], m["payload"], m["qos"]) for m in got] == [("plant/dev1/y", b"own-q2", 2)],
              f"expected exactly plant/dev1/y at QoS 2, got {seen['received']}")
        c.disconnect()
    finally:
        c.stop()


def scenario_will(args, seen):
    b = Client(args, f"will-b-{args.protocol}")
    a = Client(args, f"will-a-{args.protocol}", keepalive=2)
    a.c.will_set("will/a", b"gone", qos=1)
    c = Client(args, f"will-c-{args.protocol}", keepalive=2)
    c.c.will_set("will/c", b"c-gone", qos=1)
    clients = [a, b, c]
    try:
        seen["b_connack"] = b.connect()
        codes = b.subscribe([("will/#", 1)])
        check(codes == [1], f"SUBACK for will/# was {codes}")
        seen["a_connack"] = a.connect()
        seen["c_connack"] = c.connect()

        # C leaves cleanly: its will must not be published.
        c.disconnect()
        seen["c_disconnected"] = True

        # A's socket is closed without DISCONNECT: its will must arrive within 5 s.
        a.kill_socket()
        closed_at = time.monotonic()
        m = b.next_message(5.0)
        seen["will_a"] = message_summary(m) if m else None
        check(m is not None, "will of A not received within 5 s of its socket closing")
        seen["will_a_after_s"] = round(m["at"] - closed_at, 3)
        check(m["topic"] == "will/a" and m["payload"] == b"gone", f"unexpected message {seen['will_a']}")

        # Two more seconds: nothing else, in particular not C's will.
        extra = b.drain(2.0)
        seen["extra"] = [message_summary(m) for m in extra]
        check(not extra, f"unexpected messages after a clean disconnect: {seen['extra']}")

        if b.v5:
            # MQTT 5: DISCONNECT with reason 0x04 asks the server to publish the will.
            d = Client(args, f"will-d-{args.protocol}")
            clients.append(d)
            d.c.will_set("will/d", b"d-asked", qos=1)
            seen["d_connack"] = d.connect()
            d.disconnect(ReasonCode(PacketTypes.DISCONNECT, "Disconnect with will message"))
            m = b.next_message(5.0)
            seen["will_d"] = message_summary(m) if m else None
            check(m is not None and m["topic"] == "will/d" and m["payload"] == b"d-asked",
                  f"will of D (DISCONNECT 0x04) not received: {seen['will_d']}")
        b.disconnect()
    finally:
        for x in clients:
            x.stop()


def scenario_keepalive0(args, seen):
    c = Client(args, f"paho-ka0-{args.protocol}", args.user, args.password, keepalive=0)
    try:
        seen["connack"] = c.connect()
        codes = c.subscribe([("k/#", 1)])
        seen["suback"] = codes
        check(codes == [1], f"SUBACK for k/# was {codes}")
        mid = c.publish("k/x", b"first", 1)
        check(c.acked(mid) == 0, "first publication not acknowledged")
        m = c.next_message()
        check(m is not None and m["payload"] == b"first", "first message not delivered")
        # Idle for longer than a short keep-alive would allow: no PINGREQ is sent
        # (keep-alive 0 turns the mechanism off) and the connection must stay open.
        time.sleep(3.0)
        check(not c.disconnected.is_set(), f"connection closed while idle (reason {c.disconnect_reason})")
        mid = c.publish("k/x", b"second", 1)
        check(c.acked(mid) == 0, "second publication not acknowledged")
        m = c.next_message()
        check(m is not None and m["payload"] == b"second", "second message not delivered after idling")
        seen["delivered"] = 2
        c.disconnect()
    finally:
        c.stop()


def scenario_shutdown(args, seen):
    c = Client(args, f"paho-shutdown-{args.protocol}", args.user, args.password)
    try:
        seen["connack"] = c.connect()
        check(c.subscribe([("s/#", 1)]) == [1], "SUBACK for s/# refused")
        print("READY", flush=True)
        if not c.disconnected.wait(WAIT):
            raise CheckFailed(f"connection not ended by the broker within {WAIT} s of READY")
        seen["disconnect_reason"] = c.disconnect_reason
        seen["disconnect_from_server"] = c.disconnect_from_server
        if c.v5:
            check(c.disconnect_from_server, "the broker closed the connection without a DISCONNECT packet")
            check(
                c.disconnect_reason == 0x8B,
                f"DISCONNECT reason {c.disconnect_reason}, expected 139 (0x8B server shutting down)",
            )
        else:
            # MQTT 3.1.1 has no server DISCONNECT: the connection just closes.
            check(not c.disconnect_from_server, "a DISCONNECT packet on MQTT 3.1.1")
    finally:
        c.stop()


SCENARIOS = {
    "pubsub": (scenario_pubsub, ("311", "5")),
    "delivery_qos": (scenario_delivery_qos, ("311", "5")),
    "bad_password": (scenario_bad_password, ("311", "5")),
    "acl": (scenario_acl, ("311", "5")),
    "acl_qos2": (scenario_acl_qos2, ("311", "5")),
    "will": (scenario_will, ("311", "5")),
    "keepalive0": (scenario_keepalive0, ("311", "5")),
    "shutdown5": (scenario_shutdown, ("5",)),
    "shutdown311": (scenario_shutdown, ("311",)),
}


def main():
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--port", type=int, required=True)
    p.add_argument("--scenario", required=True, choices=sorted(SCENARIOS))
    p.add_argument("--protocol", choices=["311", "5"])
    p.add_argument("--user")
    p.add_argument("--password")
    p.add_argument("--good-password", help="bad_password: the right password, checked after the refusal")
    args = p.parse_args()
    run, protocols = SCENARIOS[args.scenario]
    if args.protocol is None:
        args.protocol = protocols[-1]
    if args.protocol not in protocols:
        p.error(f"scenario {args.scenario} is for MQTT {' or '.join(protocols)} only")

    seen = {"scenario": args.scenario, "protocol": args.protocol, "paho": paho.mqtt.__version__}
    error = None
    try:
        run(args, seen)
    except CheckFailed as e:
        error = str(e)
    except Exception as e:  # a crash is a failure too, reported the same way
        error = f"{type(e).__name__}: {e}"
    seen["ok"] = error is None
    if error is not None:
        seen["error"] = error
    print(json.dumps(seen, default=str), flush=True)
    if error is not None:
        print(f"paho_check {args.scenario} (MQTT {args.protocol}): FAILED: {error}", file=sys.stderr)
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())

#!/usr/bin/env python3
"""Issue 20, "a device is who its password says", with Eclipse paho-mqtt 2.x.

Runs one scenario against a broker on 127.0.0.1:PORT whose password file has devA/pwA,
devB/pwB and mes/pwM and whose ACL is deploy/acl.example (broker/tests/identity.rs sets
it up), prints one JSON line with what it observed, and exits 0 when the expectations
hold, 1 otherwise. Every wait is bounded (paho_check.WAIT, 10 s).

    identity_check.py --port 1883 --scenario theft_live --protocol 5

Scenarios:
  theft_live    devB is connected (persistent session, subscribed to its commands);
                devA logs in with its own password and client id devB: refused, devB
                stays connected and still receives the MES's command.
  theft_stored  the same with devB away (its session kept): refused; devB comes back
                and receives the command the MES sent while it was away.
"""

import argparse
import json
import os
import sys

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))

import paho.mqtt.client as mqtt  # noqa: E402
from paho.mqtt.enums import CallbackAPIVersion  # noqa: E402
from paho.mqtt.packettypes import PacketTypes  # noqa: E402
from paho.mqtt.properties import Properties  # noqa: E402

from paho_check import CheckFailed, Client, check, message_summary  # noqa: E402

# The CONNACK code for "client identifier not valid": 3.1.1 return code 2, MQTT 5 0x85.
ID_REJECTED = {"311": 2, "5": 0x85}
# A SUBSCRIBE refused by the ACL: 3.1.1 0x80, MQTT 5 0x87 (Not authorized).
SUB_REFUSED = {"311": 0x80, "5": 0x87}
COMMAND = "line1/devB/cmd/stop"


class Persistent(Client):
    """A client whose session outlives its connection: clean session 0 (3.1.1), or Clean
    Start 0 with a Session Expiry Interval (MQTT 5)."""

    def __init__(self, args, client_id, user, password):
        super().__init__(args, client_id, user, password)
        if not self.v5:
            # paho fixes the clean-session flag when the client is made.
            self.c = mqtt.Client(
                callback_api_version=CallbackAPIVersion.VERSION2,
                client_id=client_id,
                protocol=mqtt.MQTTv311,
                clean_session=False,
                reconnect_on_failure=False,
            )
            self.c.username_pw_set(user, password)
            self.c.on_connect = self._on_connect
            self.c.on_disconnect = self._on_disconnect
            self.c.on_message = self._on_message
            self.c.on_subscribe = self._on_subscribe
            self.c.on_publish = self._on_publish

    def connect(self, expect_success=True):
        if not self.v5:
            return super().connect(expect_success)
        props = Properties(PacketTypes.CONNECT)
        props.SessionExpiryInterval = 300
        self.c.connect(
            "127.0.0.1",
            self.args.port,
            keepalive=self.keepalive,
            clean_start=False,
            properties=props,
        )
        self.c.loop_start()
        self.loop_running = True
        if not self.connected.wait(10):
            if expect_success:
                raise CheckFailed(f"{self.client_id}: no CONNACK")
            return None
        if expect_success:
            check(self.connack == 0, f"{self.client_id}: CONNECT refused with code {self.connack}")
        return self.connack


def theft(args, seen, stored):
    p = args.protocol
    dev_b = Persistent(args, "devB", "devB", "pwB")
    dev_a = Client(args, f"devA-{p}", "devA", "pwA")
    thief = Persistent(args, "devB", "devA", "pwA")
    mes = Client(args, f"mes-{p}", "mes", "pwM")
    clients = [dev_b, dev_a, thief, mes]
    try:
        dev_b.connect()
        seen["devB_suback"] = dev_b.subscribe([("line1/devB/cmd/#", 1)])
        check(seen["devB_suback"] == [1], f"devB's own commands: SUBACK {seen['devB_suback']}")
        dev_a.connect()
        seen["devA_suback"] = dev_a.subscribe([("line1/devB/cmd/#", 1)])
        check(
            seen["devA_suback"] == [SUB_REFUSED[p]],
            f"devA subscribing to devB's commands: SUBACK {seen['devA_suback']}",
        )
        if stored:
            dev_b.disconnect()
        seen["thief_connack"] = thief.connect(expect_success=False)
        check(
            seen["thief_connack"] == ID_REJECTED[p],
            f"devA with client id devB: CONNACK {seen['thief_connack']}, expected {ID_REJECTED[p]}",
        )
        mes.connect()
        check(mes.acked(mes.publish(COMMAND, b"stop", 1)) == 0, "the MES's command was refused")
        if stored:
            dev_b = Persistent(args, "devB", "devB", "pwB")
            clients.append(dev_b)
            dev_b.connect()
        got = dev_b.next_message()
        seen["devB_received"] = message_summary(got) if got else None
        check(got is not None and got["topic"] == COMMAND, f"devB did not receive its command: {got}")
        thief_got = thief.drain(0.5)
        seen["thief_received"] = [message_summary(m) for m in thief_got]
        check(not thief_got, "devA received devB's messages")
        check(not dev_b.disconnected.is_set(), f"devB was disconnected: {dev_b.ended()}")
        dev_b.disconnect()
        dev_a.disconnect()
        mes.disconnect()
    finally:
        for c in clients:
            c.stop()


SCENARIOS = {
    "theft_live": lambda args, seen: theft(args, seen, stored=False),
    "theft_stored": lambda args, seen: theft(args, seen, stored=True),
}


def main():
    p = argparse.ArgumentParser()
    p.add_argument("--port", type=int, required=True)
    p.add_argument("--scenario", required=True, choices=sorted(SCENARIOS))
    p.add_argument("--protocol", required=True, choices=["311", "5"])
    args = p.parse_args()
    seen = {"scenario": args.scenario, "protocol": args.protocol}
    try:
        SCENARIOS[args.scenario](args, seen)
    except CheckFailed as e:
        seen["error"] = str(e)
        print(json.dumps(seen, default=str))
        print(f"FAILED: {e}", file=sys.stderr)
        return 1
    print(json.dumps(seen, default=str))
    return 0


if __name__ == "__main__":
    sys.exit(main())

#!/usr/bin/env python3
"""The conveyor line seen through Sparkplug B alone.

A small Sparkplug host application: it connects to the broker, says it is online
(`spBv1.0/STATE/<host_id>`), listens to the group's edge nodes (fbbus publishes one edge
node per line, one device per function-block device) and prints what it learns as a table:

    NODE    DEVICE    STATUS  METRIC
    line1   -         online  Node Control/Rebirth = false (Boolean)
    line1   -         online  bdSeq = 3 (Int64)
    line1   conveyor  online  Belt/SPEED = 12 (Int16)

It knows nothing about fbbus: names, datatypes and values come from the births (NBIRTH,
DBIRTH) and the data (NDATA, DDATA) that follow them, as any Sparkplug host would read
them. So:

* A node it hears data from without having seen its birth (the usual case just after
  starting: births are not retained) is asked for a new one, with an NCMD
  `Node Control/Rebirth` = true, as the Sparkplug spec tells a host to do.
* A birth gives each metric its name, datatype and (optionally) alias; a DATA message may
  name a metric by alias only, and is applied through the birth.
* NDEATH marks the node and its devices dead, but only when its bdSeq is the one of the
  node's NBIRTH (an NDEATH left over from an older session is ignored). DDEATH marks one
  device dead. A dead node's last values stay in the table.

Usage:

    line_view.py --host 127.0.0.1 --port 1883 [--username U --password P]
                 [--group plant] [--host-id line-view] [--once SECONDS]

Without --once it runs until Ctrl-C and reprints the table whenever something changes.
With --once SECONDS it listens that long, prints the table once and exits 0.
`--host-id ''` runs it without STATE (a plain observer; then it is not a primary host).

Needs paho-mqtt 2.x and pysparkplug (pip install 'paho-mqtt>=2' and, as pysparkplug 0.6.1
declares paho-mqtt<2 for a client this script does not use,
pip install --no-deps pysparkplug==0.6.1 protobuf).

A note on signed integers: pysparkplug 0.6.1 reads Int8/Int16/Int32 only in the form it
writes itself (Int8 -1 as 0xFF) and refuses the sign-extended form (0xFFFFFFFF) that the
Sparkplug reference implementation, Eclipse Tahu, and fbbus write. When it refuses, this
script reads the 32-bit value as a signed integer itself.
"""

import argparse
import datetime
import json
import os
import sys
import threading
import time

import paho.mqtt.client as mqtt
from paho.mqtt.enums import CallbackAPIVersion

from pysparkplug import DataType, Metric, NCmd
from pysparkplug._protobuf import DataType as PB_DataType
from pysparkplug._protobuf import Metric as PB_Metric
from pysparkplug._protobuf import Payload as PB_Payload

NAMESPACE = "spBv1.0"
REBIRTH_EVERY = 5.0  # seconds between two Rebirth requests to the same node
SIGNED = {DataType.INT8: 8, DataType.INT16: 16, DataType.INT32: 32}


def now_ms():
    return int(time.time() * 1000)


# ---- decoding ----


def decode_value(pb_metric):
    """A metric's value, by pysparkplug; for Int8/16/32 also from the sign-extended form."""
    try:
        return Metric.from_pb(pb_metric).value
    except OverflowError:
        datatype = DataType(pb_metric.datatype)
        if datatype not in SIGNED or pb_metric.WhichOneof("value") != "int_value":
            raise
        value = pb_metric.int_value
        if value >= 2**31:  # a 32-bit two's complement, sign-extended from the width
            value -= 2**32
        bits = SIGNED[datatype]
        if not -(2 ** (bits - 1)) <= value < 2 ** (bits - 1):
            raise
        return value


def show_value(value, datatype):
    if value is None:
        return "null"
    if isinstance(value, datetime.datetime):
        return value.isoformat(timespec="milliseconds").replace("+00:00", "Z")
    if isinstance(value, bytes):
        return value.hex() or '""'
    if isinstance(value, tuple):
        return "[" + ", ".join(show_value(v, datatype) for v in value) + "]"
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, str):
        return json.dumps(value, ensure_ascii=False)
    return str(value)


def bd_seq_of(payload):
    """The raw bdSeq of an NBIRTH or NDEATH (a number in whichever field it came in)."""
    for m in payload.metrics:
        if m.name == "bdSeq" and m.WhichOneof("value") is not None:
            return getattr(m, m.WhichOneof("value"))
    return None


def datatype_name(datatype_id):
    try:
        return PB_DataType.Name(datatype_id)
    except ValueError:
        return f"datatype {datatype_id}"


# ---- what the host knows ----


class Thing:
    """An edge node (device None) or one of its devices."""

    def __init__(self):
        self.status = "no birth"
        self.metrics = {}  # name -> [datatype id, value shown]
        self.bd_seq = None  # edge nodes: the bdSeq of their NBIRTH


class LineView:
    def __init__(self, args):
        self.args = args
        self.lock = threading.Lock()
        self.nodes = {}  # (group, node) -> Thing
        self.devices = {}  # (group, node, device) -> Thing
        self.aliases = {}  # (group, node) -> {alias: name}; one alias space per node
        self.rebirth_asked = {}  # (group, node) -> time of the last request
        self.changed = threading.Event()
        self.connected = threading.Event()
        self.refused = None
        self.client = mqtt.Client(
            CallbackAPIVersion.VERSION2,
            client_id=args.client_id or f"line-view-{os.getpid()}",
            protocol=mqtt.MQTTv5,
        )
        if args.username is not None:
            self.client.username_pw_set(args.username, args.password)
        self.state_ts = now_ms()
        if args.host_id:
            # If this host goes away without saying so, the broker says it for it.
            self.client.will_set(self.state_topic(), self.state(False), qos=1, retain=True)
        self.client.on_connect = self.on_connect
        self.client.on_message = self.on_message

    # -- Sparkplug host duties --

    def state_topic(self):
        return f"{NAMESPACE}/STATE/{self.args.host_id}"

    def state(self, online):
        return json.dumps({"online": online, "timestamp": self.state_ts})

    def on_connect(self, client, userdata, flags, reason_code, properties):
        if reason_code.is_failure:
            self.refused = str(reason_code)
            self.connected.set()
            return
        group = self.args.group or "+"
        # Subscribe first, then say online: an edge node that waits for this host to be
        # online births right away, and this host must already be listening.
        client.subscribe(f"{NAMESPACE}/{group}/#", qos=1)
        if self.args.host_id:
            client.publish(self.state_topic(), self.state(True), qos=1, retain=True)
        self.connected.set()

    def ask_rebirth(self, group, node):
        """NCMD Node Control/Rebirth = true, at most every REBIRTH_EVERY seconds a node."""
        key = (group, node)
        now = time.monotonic()
        if now - self.rebirth_asked.get(key, -REBIRTH_EVERY) < REBIRTH_EVERY:
            return
        self.rebirth_asked[key] = now
        ts = now_ms()
        rebirth = Metric(timestamp=ts, name="Node Control/Rebirth",
                         datatype=DataType.BOOLEAN, value=True)
        payload = NCmd(timestamp=ts, metrics=(rebirth,)).encode(include_dtypes=True)
        self.client.publish(f"{NAMESPACE}/{group}/NCMD/{node}", payload, qos=0)
        print(f"line_view: no birth seen from {group}/{node}: asked it for a rebirth",
              file=sys.stderr)

    # -- messages --

    def on_message(self, client, userdata, msg):
        parts = msg.topic.split("/")
        if len(parts) < 4 or parts[0] != NAMESPACE or parts[1] == "STATE":
            return
        group, kind, node = parts[1], parts[2], parts[3]
        device = "/".join(parts[4:]) if len(parts) > 4 else None
        if kind in ("NCMD", "DCMD"):
            return
        try:
            payload = PB_Payload.FromString(msg.payload)
        except Exception as exc:
            print(f"line_view: {msg.topic}: not a Sparkplug B payload ({exc})", file=sys.stderr)
            return
        with self.lock:
            if self.handle(group, kind, node, device, payload):
                self.changed.set()

    def handle(self, group, kind, node, device, payload):
        """Applies one message; True when the table changed."""
        node_key = (group, node)
        known = node_key in self.nodes and self.nodes[node_key].status == "online"
        if kind == "NBIRTH":
            thing = self.nodes[node_key] = Thing()
            self.aliases[node_key] = {}
            for key, dev in self.devices.items():  # their DBIRTHs follow the NBIRTH
                if key[:2] == node_key:
                    dev.status = "dead"
            self.apply_birth(node_key, thing, payload)
            thing.bd_seq = bd_seq_of(payload)
            return True
        if kind == "NDEATH":
            if not known:
                return False
            thing = self.nodes[node_key]
            if thing.bd_seq is not None and bd_seq_of(payload) != thing.bd_seq:
                return False  # the death of an older session
            thing.status = "dead"
            for key, dev in self.devices.items():
                if key[:2] == node_key:
                    dev.status = "dead"
            return True
        if not known:
            # NDATA, DBIRTH, DDATA or DDEATH from a node whose birth this host missed.
            self.nodes.setdefault(node_key, Thing())
            if device is not None:
                self.devices.setdefault((group, node, device), Thing())
            self.ask_rebirth(group, node)
            return True
        if kind == "NDATA":
            return self.apply_data(node_key, self.nodes[node_key], payload)
        dev_key = (group, node, device)
        if kind == "DBIRTH":
            thing = self.devices[dev_key] = Thing()
            self.apply_birth(node_key, thing, payload)
            return True
        device_known = dev_key in self.devices and self.devices[dev_key].status == "online"
        if kind == "DDEATH":
            if not device_known:
                return False
            self.devices[dev_key].status = "dead"
            return True
        if kind == "DDATA":
            if not device_known:
                # Data from a device whose birth this host missed, or after its death.
                self.devices.setdefault(dev_key, Thing())
                self.ask_rebirth(group, node)
                return True
            return self.apply_data(node_key, self.devices[dev_key], payload)
        return False

    def value_text(self, pb_metric):
        if pb_metric.is_null or pb_metric.WhichOneof("value") is None:
            return "null"
        try:
            return show_value(decode_value(pb_metric), pb_metric.datatype)
        except Exception as exc:
            field = pb_metric.WhichOneof("value")
            return f"? ({type(exc).__name__}; {field} = {getattr(pb_metric, field)!r})"

    def apply_birth(self, node_key, thing, payload):
        thing.status = "online"
        aliases = self.aliases.setdefault(node_key, {})
        for m in payload.metrics:
            if not m.name:
                continue
            if m.HasField("alias"):
                aliases[m.alias] = m.name
            thing.metrics[m.name] = [m.datatype, self.value_text(m)]

    def apply_data(self, node_key, thing, payload):
        changed = False
        for m in payload.metrics:
            name = m.name or self.aliases.get(node_key, {}).get(m.alias)
            if name is None or name not in thing.metrics:
                print(f"line_view: data for a metric its birth did not declare "
                      f"(name {m.name!r}, alias {m.alias})", file=sys.stderr)
                continue
            filled = PB_Metric()
            filled.CopyFrom(m)
            filled.name = name
            if not filled.datatype:
                filled.datatype = thing.metrics[name][0]
            thing.metrics[name][1] = self.value_text(filled)
            changed = True
        return changed

    # -- the table --

    def table(self):
        with self.lock:
            rows = []
            for (group, node), thing in sorted(self.nodes.items()):
                label = node if self.args.group else f"{group}/{node}"
                rows += self.rows(label, "-", thing)
                for (g, n, device), dev in sorted(self.devices.items()):
                    if (g, n) == (group, node):
                        rows += self.rows(label, device, dev)
        header = ("NODE", "DEVICE", "STATUS", "METRIC")
        widths = [max(len(r[i]) for r in [header] + rows) for i in range(3)]
        lines = []
        for r in [header] + rows:
            lines.append("  ".join(r[i].ljust(widths[i]) for i in range(3)) + "  " + r[3])
        if not rows:
            lines.append("(no Sparkplug edge node heard from yet)")
        return "\n".join(lines)

    @staticmethod
    def rows(node, device, thing):
        if not thing.metrics:
            return [(node, device, thing.status, "-")]
        return [(node, device, thing.status, f"{name} = {value} ({datatype_name(datatype)})")
                for name, (datatype, value) in sorted(thing.metrics.items())]

    # -- running --

    def run(self):
        args = self.args
        try:
            self.client.connect(args.host, args.port, keepalive=30)
        except OSError as exc:
            print(f"line_view: cannot connect to {args.host}:{args.port}: {exc}", file=sys.stderr)
            return 2
        self.client.loop_start()
        if not self.connected.wait(10) or self.refused:
            why = f"refused: {self.refused}" if self.refused else "no answer within 10 s"
            print(f"line_view: cannot connect to {args.host}:{args.port}: {why}", file=sys.stderr)
            self.client.loop_stop()
            return 2
        try:
            if args.once is not None:
                time.sleep(args.once)
                print(self.table(), flush=True)
            else:
                clear = "\x1b[H\x1b[2J" if sys.stdout.isatty() else ""
                print(self.table(), flush=True)
                while True:
                    self.changed.wait()
                    time.sleep(0.2)  # let a burst of messages land, then print once
                    self.changed.clear()
                    stamp = time.strftime("%H:%M:%S")
                    print(f"{clear}\n-- {stamp}\n{self.table()}", flush=True)
        except KeyboardInterrupt:
            pass
        finally:
            if args.host_id:
                # Leaving on purpose: say so (a clean DISCONNECT does not send the will).
                info = self.client.publish(self.state_topic(), self.state(False), qos=1,
                                           retain=True)
                try:
                    info.wait_for_publish(5)
                except (RuntimeError, ValueError):
                    pass
            self.client.disconnect()
            self.client.loop_stop()
        return 0


def main():
    parser = argparse.ArgumentParser(description="Print a line's Sparkplug B view.")
    parser.add_argument("--host", default="127.0.0.1")
    parser.add_argument("--port", type=int, default=1883)
    parser.add_argument("--username")
    parser.add_argument("--password")
    parser.add_argument("--client-id")
    parser.add_argument("--group", help="Sparkplug group id (default: every group)")
    parser.add_argument("--host-id", default="line-view",
                        help="Sparkplug host id for STATE ('' for none)")
    parser.add_argument("--once", type=float, metavar="SECONDS",
                        help="listen this long, print the table once and exit")
    sys.exit(LineView(parser.parse_args()).run())


if __name__ == "__main__":
    main()

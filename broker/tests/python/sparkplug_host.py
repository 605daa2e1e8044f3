#!/usr/bin/env python3
"""A Sparkplug B 3.0 host application for tests, driven over stdin/stdout.

An independent reader of what fbbus publishes as a Sparkplug edge node: payloads are decoded
by pysparkplug (its `Metric` class and `DataType` decoders, the same code its own `Client`
uses), commands are encoded by pysparkplug's `Metric` encoder; MQTT is Eclipse paho-mqtt 2.x.
pysparkplug 0.6.1 declares paho-mqtt<2 but only its client needs that, and this script does
not use its client (.ci/run installs it with --no-deps beside paho-mqtt 2.x).

    sparkplug_host.py --port N [--host 127.0.0.1] [--username U --password P]
                      [--client-id ID] [--host-id ID] [--group G] [--max-seconds 120]

Connects with MQTT 5, clean start. With --host-id it is a Sparkplug 3.0 primary host: its
will is `spBv1.0/STATE/<host_id>` = {"online": false, "timestamp": T} (retained, QoS 1), and
once subscribed it publishes {"online": true, "timestamp": T} there (retained, QoS 1, the
same T). Without --host-id it publishes no STATE at all. It subscribes `spBv1.0/#` (with
--group: `spBv1.0/G/#` and `spBv1.0/STATE/+`) at QoS 1 with No Local set, so it does not
read back its own commands and STATE.

stdout: one JSON object per line, flushed per line:
  {"event": "ready"}                      after the SUBACK and, with --host-id, after
                                          the STATE online's {"event": "puback", "op":
                                          "state", ...} line
  {"event": "state", "topic", "host_id", "retain", "payload": <the JSON, or null>,
   "text": <the payload as text when it is not JSON>}
  {"event": "message", "topic", "type": "NBIRTH"|"NDATA"|..., "group", "node",
   "device": str|null, "qos", "retain", "seq": int|null, "timestamp": int|null,
   "payload_error": null | "<what pysparkplug's whole-payload decode (Payload.decode with
                     the last birth) raised>",
   "metrics": [{"name", "alias", "datatype": "Int16" (Sparkplug name) | null,
                "datatype_id": 2, "value": <decoded>, "is_null", "timestamp",
                "is_historical", "is_transient",
                "raw": {"field": "int_value"|"long_value"|...|null, "value": <raw>},
                ["decode_error": "<why pysparkplug's decoder refused; value is null>"]}],
   "raw_metrics": [... the same metrics as on the wire, before the birth filled in a
                   missing name (from the alias) or datatype (from the name): "name",
                   "alias", "datatype_id" (null when absent), "field", "value" (raw),
                   "is_null", "timestamp"]}
  {"event": "undecodable", "topic", "error"}   a payload that is not a Sparkplug protobuf
  {"event": "sent", "op", "id", "topic", "mid", "qos": 0}      a QoS 0 command was written
  {"event": "puback", "op", "id", "topic", "mid", "reason_code": int}
                                          a QoS 1 command's PUBACK (MQTT 5 reason code:
                                          0 success, 16 no matching subscribers, 0x87 not
                                          authorized, 0x90 topic name invalid, 0x99 payload
                                          format invalid, ...)
  {"event": "error", "op", "id", "error"}   a command that could not be carried out
  {"event": "disconnected", "reason_code": int|null, "reason"}   the connection ended
                                          (reason_code: of the broker's DISCONNECT, null
                                          when it sent none); exit 3

Decoded values are JSON: DateTime as epoch milliseconds, bytes as lowercase hex, arrays as
lists, non-finite floats as the strings "NaN", "inf", "-inf". A name or datatype absent from
a DATA metric is taken from the last NBIRTH/DBIRTH (alias -> name, name -> datatype), as
pysparkplug's Payload.decode does with a birth.

Signed integers: pysparkplug 0.6.1 decodes Int8/Int16/Int32 only from the width-limited
two's complement (Int8 -1 as int_value 0xFF) and raises OverflowError on the sign-extended
form (0xFFFFFFFF) that Eclipse Tahu writes; such a metric gets "value": null and a
"decode_error", and its "raw" field still carries the wire value.

stdin: one JSON command per line ("id" is optional and echoed in the answers; "group"
defaults to --group):
  {"op": "rebirth", "group": G, "node": N, "qos": 0|1}
      NCMD spBv1.0/G/NCMD/N, metric "Node Control/Rebirth" Boolean true (QoS 0 by default,
      as Sparkplug sends commands; qos 1 to see the PUBACK's reason code)
  {"op": "ncmd", "group": G, "node": N, "qos": 0|1, "metrics": [METRIC, ...]}
  {"op": "dcmd", "group": G, "node": N, "device": D, "qos": 0|1, "metrics": [METRIC, ...]}
      METRIC: {"name": "FB/PORT", "datatype": "Int16", "value": 5} encoded by pysparkplug
      (datatype by Sparkplug name, any case; DateTime as epoch ms; Bytes/File as hex; arrays
      as lists); optional "alias", "timestamp" (default now), "is_null": true. Or bypass
      the encoder: {"name": ..., "datatype": "Int8" or "datatype_id": N, "raw": {"field":
      "int_value", "value": 4294967295}} puts that protobuf field as is (bytes_value: hex).
      The payload's timestamp is now; "seq" may be given.
  {"op": "publish", "topic": T, "payload_hex": H, "qos": 0|1, "retain": false}
      publishes arbitrary bytes (malformed payloads, foreign topics)
  {"op": "state", "online": true|false, "timestamp": T}
      publishes STATE again (retained, QoS 1; needs --host-id), then answers with its
      puback; T defaults to the session's (the will's and the first online STATE's)
  {"op": "quit"}
      with --host-id first publishes STATE {"online": false, "timestamp": <the session's>}
      (retained, QoS 1, answered by a puback line with "op": "state"), then disconnects
      cleanly (so the broker drops the will) and exits 0
End of stdin is a quit.

Exit codes: 0 quit; 2 could not connect or subscribe within 10 s (reason on stderr);
3 disconnected by the broker; 4 --max-seconds elapsed.
"""

import argparse
import datetime
import json
import math
import os
import sys
import threading
import time

import paho.mqtt.client as mqtt
from paho.mqtt.enums import CallbackAPIVersion
from paho.mqtt.subscribeoptions import SubscribeOptions

try:
    from pysparkplug import DataType, Metric, MessageType
    from pysparkplug._protobuf import DataType as PB_DataType
    from pysparkplug._protobuf import Metric as PB_Metric
    from pysparkplug._protobuf import Payload as PB_Payload
except ImportError as exc:  # pragma: no cover - environment problem, told plainly
    sys.stderr.write(f"sparkplug_host.py: pysparkplug is not installed ({exc}); run .ci/run\n")
    sys.exit(2)

NAMESPACE = "spBv1.0"
WAIT = 10.0
VALUE_FIELDS = (
    "int_value",
    "long_value",
    "float_value",
    "double_value",
    "boolean_value",
    "string_value",
    "bytes_value",
    "dataset_value",
    "template_value",
    "extension_value",
)

_out_lock = threading.Lock()


def emit(obj):
    line = json.dumps(obj, separators=(",", ":"))
    with _out_lock:
        sys.stdout.write(line + "\n")
        sys.stdout.flush()


def now_ms():
    return int(time.time() * 1000)


def datatype_name(datatype_id):
    """The Sparkplug name of a datatype id ("Int16"), or None for an id outside the enum."""
    try:
        return PB_DataType.Name(datatype_id)
    except ValueError:
        return None


def datatype_by_name(name):
    for candidate in PB_DataType.keys():
        if candidate.lower() == str(name).lower():
            return PB_DataType.Value(candidate)
    raise ValueError(f"unknown Sparkplug datatype {name!r}")


def jsonable(value):
    """A decoded metric value as JSON: DateTime as ms, bytes as hex, tuples as lists."""
    if isinstance(value, datetime.datetime):
        return round(value.timestamp() * 1000)
    if isinstance(value, (bytes, bytearray)):
        return bytes(value).hex()
    if isinstance(value, (tuple, list)):
        return [jsonable(v) for v in value]
    if isinstance(value, float) and not math.isfinite(value):
        return "NaN" if math.isnan(value) else ("inf" if value > 0 else "-inf")
    if isinstance(value, (bool, int, float, str)) or value is None:
        return value
    return str(value)


def raw_value(pb_metric):
    """(field, raw JSON value) of the protobuf value oneof, as on the wire."""
    field = pb_metric.WhichOneof("value")
    if field is None:
        return None, None
    value = getattr(pb_metric, field)
    if field in ("dataset_value", "template_value", "extension_value"):
        from google.protobuf import json_format

        return field, json_format.MessageToDict(value)
    return field, jsonable(value)


def raw_metric_json(pb_metric):
    field, value = raw_value(pb_metric)
    return {
        "name": pb_metric.name if pb_metric.HasField("name") else None,
        "alias": pb_metric.alias if pb_metric.HasField("alias") else None,
        "datatype_id": pb_metric.datatype if pb_metric.HasField("datatype") else None,
        "field": field,
        "value": value,
        "is_null": pb_metric.is_null,
        "timestamp": pb_metric.timestamp if pb_metric.HasField("timestamp") else None,
    }


class Births:
    """The last NBIRTH/DBIRTH metrics of each edge node and device: alias -> name, name ->
    datatype id, and the pysparkplug Birth object (None when it failed to decode)."""

    def __init__(self):
        self.aliases = {}  # (group, node) -> {alias: name}; aliases are per edge node
        self.datatypes = {}  # (group, node, device) -> {name: datatype id}
        self.objects = {}  # (group, node, device) -> pysparkplug Birth or None

    def record(self, group, node, device, pb_payload, birth_obj):
        aliases = self.aliases.setdefault((group, node), {})
        if device is None:
            aliases.clear()
        datatypes = {}
        for m in pb_payload.metrics:
            if m.HasField("name"):
                if m.HasField("alias"):
                    aliases[m.alias] = m.name
                datatypes[m.name] = m.datatype
        self.datatypes[(group, node, device)] = datatypes
        self.objects[(group, node, device)] = birth_obj

    def name(self, group, node, alias):
        return self.aliases.get((group, node), {}).get(alias)

    def datatype(self, group, node, device, name):
        return self.datatypes.get((group, node, device), {}).get(name)

    def obj(self, group, node, device):
        return self.objects.get((group, node, device))


def decode_metric(pb_metric, resolve_name, resolve_datatype):
    """One metric decoded by pysparkplug's Metric.from_pb (its DataType decoders), with a
    missing name/datatype filled in from the birth first, as pysparkplug's Payload.decode
    does. A decoder error is reported in the metric instead of failing the message."""
    filled = PB_Metric()
    filled.CopyFrom(pb_metric)
    if not filled.name and filled.HasField("alias"):
        name = resolve_name(filled.alias)
        if name is not None:
            filled.name = name
    if filled.datatype == 0 and filled.name:
        datatype = resolve_datatype(filled.name)
        if datatype is not None:
            filled.datatype = datatype
    field, raw = raw_value(filled)
    out = {
        "name": filled.name if filled.HasField("name") else None,
        "alias": filled.alias if filled.HasField("alias") else None,
        "datatype": datatype_name(filled.datatype),
        "datatype_id": filled.datatype,
        "value": None,
        "is_null": filled.is_null,
        "timestamp": filled.timestamp if filled.HasField("timestamp") else None,
        "is_historical": filled.is_historical,
        "is_transient": filled.is_transient,
        "raw": {"field": field, "value": raw},
    }
    try:
        metric = Metric.from_pb(filled)
        out["value"] = jsonable(metric.value)
        out["is_null"] = metric.is_null
    except Exception as exc:  # OverflowError, NotImplementedError, ValueError, ...
        out["decode_error"] = f"{type(exc).__name__}: {exc}"
    return out


class Host:
    def __init__(self, args):
        self.args = args
        self.births = Births()
        self.connected = threading.Event()
        self.subscribed = threading.Event()
        self.connack_error = None
        self.suback_error = None
        self.quitting = False
        self.state_ts = now_ms()
        self.lock = threading.Lock()
        self.pending = {}  # mid -> (op, id, topic, qos)
        self.early = {}  # mid -> reason code, acknowledged before publish() returned
        self.state_acked = threading.Event()
        self.ready = False
        self.early_disconnect = None

        client_id = args.client_id or f"spb-host-py-{os.getpid()}"
        self.client = mqtt.Client(
            CallbackAPIVersion.VERSION2,
            client_id=client_id,
            protocol=mqtt.MQTTv5,
            reconnect_on_failure=False,
        )
        if args.username is not None:
            self.client.username_pw_set(args.username, args.password)
        if args.host_id:
            self.client.will_set(
                self.state_topic(),
                self.state_payload(False, self.state_ts),
                qos=1,
                retain=True,
            )
        self.client.on_connect = self.on_connect
        self.client.on_subscribe = self.on_subscribe
        self.client.on_message = self.on_message
        self.client.on_publish = self.on_publish
        self.client.on_disconnect = self.on_disconnect

    def state_topic(self):
        return f"{NAMESPACE}/STATE/{self.args.host_id}"

    @staticmethod
    def state_payload(online, timestamp):
        return json.dumps({"online": online, "timestamp": timestamp})

    # -- paho callbacks (network thread) --

    def on_connect(self, client, userdata, flags, reason_code, properties):
        if reason_code.is_failure:
            self.connack_error = f"CONNACK {reason_code.value} ({reason_code})"
        self.connected.set()

    def on_subscribe(self, client, userdata, mid, reason_codes, properties):
        bad = [rc for rc in reason_codes if rc.is_failure]
        if bad:
            self.suback_error = "SUBACK " + ", ".join(f"{rc.value} ({rc})" for rc in bad)
        self.subscribed.set()

    def on_disconnect(self, client, userdata, flags, reason_code, properties):
        if self.quitting:
            return
        code = reason_code.value if hasattr(reason_code, "value") else int(reason_code)
        if not self.ready:
            # Still starting up: run() reports it as a failure to connect (exit 2).
            self.early_disconnect = f"disconnected while starting: {code} ({reason_code})"
            for event in (self.connected, self.subscribed, self.state_acked):
                event.set()
            return
        # reason_code: the broker's DISCONNECT reason code, null when the connection just
        # ended (no DISCONNECT packet), as the JS host reports it.
        if not flags.is_disconnect_packet_from_server:
            code = None
        emit({"event": "disconnected", "reason_code": code, "reason": str(reason_code)})
        os._exit(3)

    def on_publish(self, client, userdata, mid, reason_code, properties):
        code = reason_code.value if hasattr(reason_code, "value") else int(reason_code)
        with self.lock:
            entry = self.pending.pop(mid, None)
            if entry is None:
                self.early[mid] = code
                return
        self.report_publish(mid, entry, code)

    def report_publish(self, mid, entry, code):
        op, cmd_id, topic, qos = entry
        if op in ("state-birth", "state-quit"):  # STATE of the start or the quit
            emit({"event": "puback", "op": "state", "id": None, "topic": topic, "mid": mid,
                  "reason_code": code})
            self.state_acked.set()
            return
        if qos == 0:
            emit({"event": "sent", "op": op, "id": cmd_id, "topic": topic, "mid": mid, "qos": 0})
        else:
            emit({"event": "puback", "op": op, "id": cmd_id, "topic": topic, "mid": mid,
                  "reason_code": code})

    def on_message(self, client, userdata, msg):
        try:
            self.handle_message(msg)
        except Exception as exc:  # never let one message end the host
            emit({"event": "undecodable", "topic": msg.topic,
                  "error": f"{type(exc).__name__}: {exc}"})

    def handle_message(self, msg):
        parts = msg.topic.split("/")
        if len(parts) < 3 or parts[0] != NAMESPACE:
            return
        if parts[1] == "STATE":
            text = msg.payload.decode("utf-8", "replace")
            try:
                payload, text_out = json.loads(text), None
            except ValueError:
                payload, text_out = None, text
            event = {"event": "state", "topic": msg.topic, "host_id": parts[2],
                     "retain": bool(msg.retain), "payload": payload}
            if text_out is not None:
                event["text"] = text_out
            emit(event)
            return
        if len(parts) < 4:
            emit({"event": "undecodable", "topic": msg.topic, "error": "topic too short"})
            return
        group, mtype, node = parts[1], parts[2], parts[3]
        device = "/".join(parts[4:]) if len(parts) > 4 else None
        try:
            pb = PB_Payload.FromString(msg.payload)
        except Exception as exc:
            emit({"event": "undecodable", "topic": msg.topic,
                  "error": f"{type(exc).__name__}: {exc}"})
            return

        is_birth = mtype in ("NBIRTH", "DBIRTH")
        # pysparkplug's own whole-payload decode, as its Client would do it.
        payload_error = None
        decoded = None
        try:
            birth = None if is_birth else (self.births.obj(group, node, device)
                                           or self.births.obj(group, node, None))
            decoded = MessageType(mtype).payload.decode(msg.payload, birth=birth)
        except Exception as exc:
            payload_error = f"{type(exc).__name__}: {exc}"
        if is_birth:
            self.births.record(group, node, device if mtype == "DBIRTH" else None, pb,
                               decoded if payload_error is None else None)

        def resolve_name(alias):
            return self.births.name(group, node, alias)

        def resolve_datatype(name):
            found = self.births.datatype(group, node, device, name)
            if found is None and device is not None:
                found = self.births.datatype(group, node, None, name)
            return found

        emit({
            "event": "message",
            "topic": msg.topic,
            "type": mtype,
            "group": group,
            "node": node,
            "device": device,
            "qos": msg.qos,
            "retain": bool(msg.retain),
            "seq": pb.seq if pb.HasField("seq") else None,
            "timestamp": pb.timestamp if pb.HasField("timestamp") else None,
            "payload_error": payload_error,
            "metrics": [decode_metric(m, resolve_name, resolve_datatype) for m in pb.metrics],
            "raw_metrics": [raw_metric_json(m) for m in pb.metrics],
        })

    # -- publishing --

    def publish(self, op, cmd_id, topic, payload, qos, retain=False):
        # Not under self.lock: paho calls on_publish holding its own locks.
        info = self.client.publish(topic, payload, qos=qos, retain=retain)
        if info.rc != mqtt.MQTT_ERR_SUCCESS:
            emit({"event": "error", "op": op, "id": cmd_id,
                  "error": f"publish failed: {mqtt.error_string(info.rc)}"})
            return None
        entry = (op, cmd_id, topic, qos)
        with self.lock:
            code = self.early.pop(info.mid, None)
            if code is None:
                self.pending[info.mid] = entry
        if code is not None:
            self.report_publish(info.mid, entry, code)
        return info.mid

    def build_metric(self, spec, timestamp):
        """A protobuf metric from a command's METRIC: pysparkplug's encoder, or raw."""
        if "raw" in spec:
            pb = PB_Metric()
            if spec.get("name") is not None:
                pb.name = spec["name"]
            if spec.get("alias") is not None:
                pb.alias = int(spec["alias"])
            if "datatype_id" in spec:
                pb.datatype = int(spec["datatype_id"])
            elif spec.get("datatype") is not None:
                pb.datatype = datatype_by_name(spec["datatype"])
            if spec.get("timestamp", timestamp) is not None:
                pb.timestamp = int(spec.get("timestamp", timestamp))
            if spec.get("is_null"):
                pb.is_null = True
            raw = spec["raw"]
            field, value = raw["field"], raw["value"]
            if field not in VALUE_FIELDS[:7]:
                raise ValueError(f"raw field must be one of {VALUE_FIELDS[:7]}")
            if field == "bytes_value":
                value = bytes.fromhex(value)
            setattr(pb, field, value)
            return pb
        datatype = DataType(datatype_by_name(spec["datatype"]))
        value = spec.get("value")
        if value is not None:
            value = self.python_value(datatype, value)
        metric = Metric(
            timestamp=spec.get("timestamp", timestamp),
            name=spec.get("name"),
            datatype=datatype,
            value=value,
            alias=spec.get("alias"),
            is_null=bool(spec.get("is_null", False)) or value is None,
        )
        return metric.to_pb(include_dtype=True)

    @staticmethod
    def python_value(datatype, value):
        """A command's JSON value as the Python value pysparkplug's encoder takes."""
        if datatype == DataType.DATETIME:
            return datetime.datetime.fromtimestamp(value / 1000, tz=datetime.timezone.utc)
        if datatype == DataType.DATETIME_ARRAY:
            return tuple(datetime.datetime.fromtimestamp(v / 1000, tz=datetime.timezone.utc)
                         for v in value)
        if datatype in (DataType.BYTES, DataType.FILE):
            return bytes.fromhex(value)
        if isinstance(value, list):
            return tuple(value)
        return value

    def command_payload(self, metrics, seq=None):
        ts = now_ms()
        pb = PB_Payload()
        pb.timestamp = ts
        if seq is not None:
            pb.seq = int(seq)
        for spec in metrics:
            pb.metrics.append(self.build_metric(spec, ts))
        return pb.SerializeToString()

    def handle_command(self, cmd):
        op = cmd.get("op")
        cmd_id = cmd.get("id")
        qos = int(cmd.get("qos", 0))
        group = cmd.get("group", self.args.group)
        if op == "quit":
            return False
        if op in ("rebirth", "ncmd", "dcmd"):
            if group is None or cmd.get("node") is None:
                raise ValueError("group and node are required")
            if op == "rebirth":
                metrics = [{"name": "Node Control/Rebirth", "datatype": "Boolean", "value": True}]
            else:
                metrics = cmd.get("metrics") or []
            if op == "dcmd":
                if cmd.get("device") is None:
                    raise ValueError("device is required")
                topic = f"{NAMESPACE}/{group}/DCMD/{cmd['node']}/{cmd['device']}"
            else:
                topic = f"{NAMESPACE}/{group}/NCMD/{cmd['node']}"
            payload = self.command_payload(metrics, cmd.get("seq"))
            self.publish(op, cmd_id, topic, payload, qos)
        elif op == "publish":
            payload = bytes.fromhex(cmd.get("payload_hex", ""))
            self.publish(op, cmd_id, cmd["topic"], payload, qos, bool(cmd.get("retain", False)))
        elif op == "state":
            if not self.args.host_id:
                raise ValueError("no --host-id: this host has no STATE")
            ts = int(cmd.get("timestamp", self.state_ts))
            payload = self.state_payload(bool(cmd.get("online", True)), ts)
            self.publish(op, cmd_id, self.state_topic(), payload, 1, retain=True)
        else:
            raise ValueError(f"unknown op {op!r}")
        return True

    # -- main --

    def run(self):
        args = self.args
        deadline = time.monotonic() + WAIT
        while True:  # the broker may still be starting: retry until the deadline
            try:
                self.client.connect(args.host, args.port, keepalive=30, clean_start=True)
                break
            except Exception as exc:
                if time.monotonic() + 0.2 >= deadline:
                    fail(f"cannot connect to {args.host}:{args.port} within {WAIT:.0f} s: {exc}")
                time.sleep(0.2)
        self.client.loop_start()
        if not self.connected.wait(max(0.0, deadline - time.monotonic())):
            fail(f"no CONNACK from {args.host}:{args.port} within {WAIT:.0f} s")
        if self.connack_error or self.early_disconnect:
            fail(f"connection refused: {self.connack_error or self.early_disconnect}")

        opts = SubscribeOptions(qos=1, noLocal=True)
        if args.group:
            topics = [(f"{NAMESPACE}/{args.group}/#", opts), (f"{NAMESPACE}/STATE/+", opts)]
        else:
            topics = [(f"{NAMESPACE}/#", opts)]
        rc, _ = self.client.subscribe(topics)
        if rc != mqtt.MQTT_ERR_SUCCESS:
            fail(f"subscribe failed: {mqtt.error_string(rc)}")
        if not self.subscribed.wait(max(0.0, deadline - time.monotonic())):
            fail(f"no SUBACK within {WAIT:.0f} s")
        if self.suback_error or self.early_disconnect:
            fail(f"subscription refused: {self.suback_error or self.early_disconnect}")

        if args.host_id:
            # Sparkplug 3.0: STATE online after subscribing, with the will's timestamp.
            self.publish("state-birth", None, self.state_topic(),
                         self.state_payload(True, self.state_ts), 1, retain=True)
            if not self.state_acked.wait(max(0.0, deadline - time.monotonic())):
                fail(f"no PUBACK for STATE online within {WAIT:.0f} s")
            if self.early_disconnect:
                fail(self.early_disconnect)
        self.ready = True
        emit({"event": "ready"})

        reader = threading.Thread(target=self.read_stdin, daemon=True)
        reader.start()
        reader.join(max(0.0, args.max_seconds - (time.monotonic() - START)))
        if reader.is_alive():
            sys.stderr.write(f"sparkplug_host.py: --max-seconds {args.max_seconds} elapsed\n")
            self.quitting = True
            self.client.disconnect()
            sys.stdout.flush()
            os._exit(4)
        if self.args.host_id:
            # Sparkplug 3.0: a host leaving on purpose says so first (its will would not be
            # sent on a clean DISCONNECT), with the timestamp of its online STATE.
            self.state_acked.clear()
            self.publish("state-quit", None, self.state_topic(),
                         self.state_payload(False, self.state_ts), 1, retain=True)
            self.state_acked.wait(WAIT)
        self.quitting = True
        self.client.disconnect()
        self.client.loop_stop()
        return 0

    def read_stdin(self):
        for line in sys.stdin:
            line = line.strip()
            if not line:
                continue
            try:
                cmd = json.loads(line)
                if not isinstance(cmd, dict):
                    raise ValueError("a command is a JSON object")
            except ValueError as exc:
                emit({"event": "error", "op": None, "id": None, "error": f"bad command: {exc}"})
                continue
            try:
                if not self.handle_command(cmd):
                    return
            except Exception as exc:
                emit({"event": "error", "op": cmd.get("op"), "id": cmd.get("id"),
                      "error": f"{type(exc).__name__}: {exc}"})


def fail(message):
    sys.stderr.write(f"sparkplug_host.py: {message}\n")
    sys.stderr.flush()
    os._exit(2)


START = time.monotonic()


def main():
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--host", default="127.0.0.1")
    parser.add_argument("--port", type=int, required=True)
    parser.add_argument("--username")
    parser.add_argument("--password")
    parser.add_argument("--client-id")
    parser.add_argument("--host-id")
    parser.add_argument("--group")
    parser.add_argument("--max-seconds", type=float, default=120.0)
    args = parser.parse_args()
    sys.exit(Host(args).run())


if __name__ == "__main__":
    main()

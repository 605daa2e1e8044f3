"""DINASORE's own MQTT function blocks, unmodified: MQTT_PUBLISHER and MQTT_SUBSCRIBER of
DIGI2-FEUP/dinasore (resources/function_blocks/MQTT_PUBLISHER.py, MQTT_SUBSCRIBER.py;
master as of 2023-07), driven the way DINASORE's FB thread drives them (core/fb.py).
Their code is copied below as it is; the only differences: `Client()` is paho-mqtt 2.x's
Client with CallbackAPIVersion.VERSION1, which behaves and writes the bytes of the
paho-mqtt 1.x `Client()` DINASORE was written for (see below), wrapped to REPORT what
happens; and one sleep in the subscriber's busy loop (marked).

Usage:
  dinasore_device.py --host 127.0.0.1 --port N
                     [--pub TOPIC:VALUE_NAME]... [--sub TOPIC:VALUE_NAME]...

  Each --pub is one MQTT_PUBLISHER FB, each --sub one MQTT_SUBSCRIBER FB; they are INITed
  in command-line order. Every subscriber FB runs READ again as soon as READ_O came out,
  like an application that loops READ_O back to READ.

Commands on stdin (one a line):
  pub TOPIC VALUE   RUN on the publisher of TOPIC; VALUE is a Python literal (3, 3.0,
                    'abc', True, None...; anything else is taken as a str)
  drop              the network goes away: every socket of the device is shut down (no
                    DISCONNECT); then paho's behaviour: see below
  kill              exit without DISCONNECT (sockets closed by the OS)
  quit              DINASORE's stop: each FB's __del__ (disconnect()), then exit; also
                    on EOF

Lines on stdout:
  connected                every FB's INIT ran (TCP connected, CONNECT written; no FB
                           waits for CONNACK)
  subscribed TOPIC         SUBACK for that subscriber (seen by a hook, no wire effect)
  sent TOPIC PAYLOAD       the publisher's publish() returned MQTT_ERR_SUCCESS (the bytes
                           were handed to the socket)
  lost TOPIC RC            publish() returned an error (DINASORE ignores it: nothing is
                           retried, the value is gone)
  recv TOPIC VALUE         READ_O of the subscriber of TOPIC, VALUE as Python repr (3.0)
  error TOPIC EXC: MSG     the subscriber's schedule() raised: DINASORE's FB thread logs
                           it and stops ("stopping the fb work..."); that FB never outputs
                           again
  disconnected TOPIC RC    a subscriber's paho loop lost its connection (hook)
  reconnected TOPIC        a subscriber's paho loop is connected again (hook)
  error ...                a bad command

What the source does (quoted from the files above):
- Publisher: `self.client = Client()` in __init__; INIT: `self.client.connect(host, port)`,
  nothing else: never loop_start(), never loop(). So: paho 1.x Client() defaults, client
  id "" (paho sends an empty id for MQTT 3.1.1: the broker assigns one), clean session,
  MQTTv311, connect()'s keepalive=60, no username, no will. CONNECT is
  10 0c 00 04 'MQTT' 04 02 00 3c 00 00. No network loop: CONNACK is never read, no
  PINGREQ is ever sent; the broker drops the connection after 1.5 x 60 s without a
  publish, nothing notices, the next publish goes into a dead socket (lost silently) and
  later ones fail (paho: MQTT_ERR_CONN_LOST, then MQTT_ERR_NO_CONN): the publisher never
  reconnects. paho writes a QoS 0 PUBLISH straight to the socket when no loop thread
  runs (`_packet_queue` -> `loop_write()`), so publishing works without the loop.
- RUN: `message_dict = {value_name: str(value)}; message = json.dumps(message_dict);
  self.client.publish(topic, message)`: QoS 0, not retained, the value as a JSON STRING
  of Python's str(): json.dumps' default separators give `{"SPEED": "3"}` for the int 3,
  `{"SPEED": "3.0"}` for the float 3.0, `{"SPEED": "True"}`, `{"SPEED": "None"}`; non-ASCII
  is escaped (\\u00e9). VALUE is declared REAL in MQTT_PUBLISHER.fbt and a REAL parameter
  is converted with float() (core/configuration.py convert_type), so a constant 3 is
  published as "3.0"; a value arriving over a connection is whatever Python object the
  source FB output (an int gives "3").
- Subscriber: the SharedResources object is a CLASS attribute shared by every
  MQTT_SUBSCRIBER of the device; each INIT calls `connect()`, which makes a NEW Client()
  (empty id, clean session, keepalive 60), connect()s, loop_start()s, and the INIT then
  `subscribe(topic)` (QoS 0) on that newest client. An earlier subscriber's client keeps
  running and receiving. SUBSCRIBE is written right after CONNECT, before CONNACK.
  subscribe() is called once, at INIT, not in on_connect: after paho's loop reconnects
  (it does, clean session, backoff 1..120 s) the subscriber receives nothing anymore.
- on_message stores the message in ONE shared slot (topic, payload) and sets an Event;
  READ waits for the Event, and if the slot's topic equals its TOPIC (== on the string:
  a wildcard TOPIC never matches) does `float(json.loads(payload.decode('utf-8'))
  [value_name])`, then clears the Event. A second message before the READ thread ran
  overwrites the first (it is lost). A JSON number or bool is accepted (float(True) is
  1.0), "nan" and "inf" too; invalid UTF-8, invalid JSON, a missing key, null or a
  non-numeric string raise, and the exception ends the FB (core/fb.py FB.run: `except
  Exception ... logging.info('stopping the fb work...'); break`). It raises before
  clearing the Event, so any other subscriber FB of the device then spins (the
  slot's topic is not its own and the Event stays set).
- With the topic not its own the READ loop does not clear the Event and spins at full
  speed until the right FB clears it. Here a 1 ms sleep is added in that case (marked
  in the code) so a test's CPU is not burnt; nothing observable changes.
- Stop (core/fb.py FB.stop -> fb_obj.__del__()): the publisher disconnect()s (DISCONNECT
  written); a subscriber disconnect()s resources.client, i.e. only the newest client.
- paho-mqtt: DINASORE pins no version (requirements.txt has no paho at all). Its bare
  `Client()` works on paho-mqtt 1.x, fails on 2.0.x (callback_api_version required) and
  works again on >= 2.1 (defaults to CallbackAPIVersion.VERSION1 with a
  DeprecationWarning). VERSION1 with the same defaults writes the same CONNECT, SUBSCRIBE,
  PUBLISH and DISCONNECT bytes as paho 1.6.1 and loops/reconnects the same way (checked
  against DINASORE's own files on paho 1.6.1 with a byte-logging listener).
- The publisher never reads its socket, so the CONNACK stays unread in it: when the
  process ends (kill, or after quit's DISCONNECT) the kernel closes that connection with
  a TCP RST, not a FIN.
"""

import argparse
import ast
import json
import os
import socket
import sys
import threading
import time
import warnings
from threading import Event

import paho.mqtt.client as mqtt

# VERSION1 is what reproduces paho 1.x; its deprecation warning is noise on stderr
warnings.filterwarnings("ignore", category=DeprecationWarning)

_out_lock = threading.Lock()


def out(line):
    with _out_lock:
        sys.stdout.write(line + "\n")
        sys.stdout.flush()


class _ReportingClient(mqtt.Client):
    """paho 1.x's `Client()`: client_id "", clean session, MQTTv311, TCP. The overrides
    only report; each calls paho's own method with the same arguments."""

    def __init__(self):
        super().__init__(mqtt.CallbackAPIVersion.VERSION1)
        self._report_subs = {}
        self._report_topic = None
        self._report_sessions = 0
        self.on_subscribe = self._report_subscribe
        self.on_connect = self._report_connect
        self.on_disconnect = self._report_disconnect

    def publish(self, topic, payload=None, qos=0, retain=False, properties=None):
        info = super().publish(topic, payload, qos, retain, properties)
        if info.rc == mqtt.MQTT_ERR_SUCCESS:
            out(f"sent {topic} {payload}")
        else:
            out(f"lost {topic} {mqtt.error_string(info.rc)}")
        return info

    def subscribe(self, topic, qos=0, options=None, properties=None):
        # Known before the SUBSCRIBE is sent: paho's network thread may handle the
        # SUBACK before subscribe() returns its mid (a race CI hit).
        self._report_topic = topic
        rc, mid = super().subscribe(topic, qos, options, properties)
        self._report_subs[mid] = topic
        return rc, mid

    def _report_subscribe(self, client, userdata, mid, granted_qos):
        # Each DINASORE subscriber FB's client subscribes one topic.
        topic = self._report_subs.get(mid, self._report_topic or "?")
        if granted_qos and granted_qos[0] == 0x80:
            out(f"error {topic} SUBACK 0x80")
        else:
            out(f"subscribed {topic}")

    def _report_connect(self, client, userdata, flags, rc):
        self._report_sessions += 1
        if self._report_sessions > 1 and self._report_topic is not None:
            out(f"reconnected {self._report_topic}")

    def _report_disconnect(self, client, userdata, rc):
        if self._report_topic is not None:
            out(f"disconnected {self._report_topic} {rc}")


ALL_CLIENTS = []


def Client():
    client = _ReportingClient()
    ALL_CLIENTS.append(client)
    return client


# ------------------------------------------------------------------------------------
# resources/function_blocks/MQTT_PUBLISHER.py, as it is (imports above)


class MQTT_PUBLISHER:

    def __init__(self):
        self.client = Client()

    def schedule(self, event_name, event_value, topic, host, port, value_name, value):
        if event_name == 'INIT':
            # connects to the broker
            self.client.connect(host, port)
            return [event_value, None]

        elif event_name == 'RUN':
            message_dict = {value_name: str(value)}
            message = json.dumps(message_dict)
            self.client.publish(topic, message)
            return [None, event_value]

    def __del__(self):
        self.client.disconnect()


# ------------------------------------------------------------------------------------
# resources/function_blocks/MQTT_SUBSCRIBER.py, as it is but for the marked sleep


class SharedResources:

    def __init__(self):
        self.client = None
        self.topic = None
        self.message_payload = None
        self.new_message = Event()

    def connect(self, host, port):
        self.client = Client()

        def on_message(client, userdata, message):
            # print('new message: {0}\ntopic: {1}'.format(message.payload, message.topic))
            self.topic = message.topic
            self.message_payload = message.payload
            self.new_message.set()

        self.client.on_message = on_message
        self.client.connect(host, port)
        self.client.loop_start()


class MQTT_SUBSCRIBER:
    resources = SharedResources()

    def __init__(self):
        self.resources.new_message.clear()
        self.stop = Event()

    def schedule(self, event_name, event_value, topic, host, port, value_name):
        if event_name == 'INIT':
            self.resources.connect(host, port)
            self.resources.client.subscribe(topic)
            return [event_value, None, 0.0]

        elif event_name == 'READ':
            # wait for new messages
            while not self.stop.is_set():
                self.resources.new_message.wait()

                # checks if is the right topic
                if self.resources.topic == topic and self.resources.message_payload is not None:
                    # process each message
                    msg = self.resources.message_payload.decode('utf-8')
                    payload_json = json.loads(msg)
                    value = float(payload_json[value_name])
                    # otherwise clears the new message event
                    self.resources.new_message.clear()
                    return [None, event_value, value]
                time.sleep(0.001)  # EMULATOR ONLY: DINASORE spins here at full speed

    def __del__(self):
        self.stop.set()
        self.resources.new_message.clear()
        self.resources.client.disconnect()


# ------------------------------------------------------------------------------------
# the device: core/fb.py's FB thread, reduced to these two FB types


def read_loop(fb, topic, host, port, value_name):
    """FB.run of a subscriber whose READ_O is looped back to READ."""
    while True:
        try:
            outputs = fb.schedule('READ', 1, topic, host, port, value_name)
        except Exception as ex:  # FB.run: logs, 'stopping the fb work...', break
            out(f"error {topic} {type(ex).__name__}: {ex}")
            return
        if outputs is None:  # FB.run: 'Outputs are null', break
            return
        out(f"recv {topic} {outputs[2]!r}")


class Spec(argparse.Action):
    def __call__(self, parser, namespace, value, option_string=None):
        if ":" not in value:
            parser.error(f"{option_string} {value}: TOPIC:VALUE_NAME expected")
        topic, name = value.rsplit(":", 1)
        namespace.fbs.append((option_string.lstrip("-"), topic, name))


def main():
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--host", default="127.0.0.1")
    p.add_argument("--port", type=int, required=True)
    p.add_argument("--pub", action=Spec, dest="fbs_pub")
    p.add_argument("--sub", action=Spec, dest="fbs_sub")
    p.set_defaults(fbs=[])
    args = p.parse_args()

    pubs = {}
    fbs = []
    for kind, topic, name in args.fbs:
        if kind == "pub":
            fb = MQTT_PUBLISHER()
            fb.schedule('INIT', 1, topic, args.host, args.port, name, None)
            pubs.setdefault(topic, (fb, name))
        else:
            fb = MQTT_SUBSCRIBER()
            fb.schedule('INIT', 1, topic, args.host, args.port, name)
            threading.Thread(target=read_loop, args=(fb, topic, args.host, args.port, name),
                             daemon=True).start()
        fbs.append(fb)
    out("connected")

    def stop_all():
        for fb in fbs:  # core/configuration.py stop_work -> FB.stop -> fb_obj.__del__()
            try:
                fb.__del__()
            except Exception:
                pass
        time.sleep(0.2)  # let the subscribers' loop threads write their DISCONNECT
        os._exit(0)

    for line in sys.stdin:
        parts = line.strip().split(None, 2)
        if not parts:
            continue
        cmd = parts[0].lower()
        if cmd == "pub" and len(parts) == 3:
            topic, text = parts[1], parts[2]
            if topic not in pubs:
                out(f"error {topic} no publisher on this topic")
                continue
            try:
                value = ast.literal_eval(text)
            except (ValueError, SyntaxError):
                value = text
            fb, name = pubs[topic]
            fb.schedule('RUN', 1, topic, args.host, args.port, name, value)
        elif cmd == "drop":
            for c in ALL_CLIENTS:
                s = c.socket()
                if s is not None:
                    try:
                        s.shutdown(socket.SHUT_RDWR)
                    except OSError:
                        pass
        elif cmd == "kill":
            os._exit(0)
        elif cmd == "quit":
            stop_all()
        else:
            out(f"error bad command: {line.strip()}")
    stop_all()


if __name__ == "__main__":
    main()

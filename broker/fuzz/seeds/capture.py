#!/usr/bin/env python3
"""Captures real MQTT 3.1.1 and 5 packets as seeds for the `mqtt_decode` fuzz target.

Starts a Mosquitto broker on a free loopback port, and a recording TCP proxy in front of
it; runs Debian's `mosquitto_pub` / `mosquitto_sub` and Python paho-mqtt clients against
the proxy; writes what each client connection sent (`<scenario>.c2s`: CONNECT first, then
everything else, as the broker reads it) and what the broker answered (`<scenario>.s2c`:
CONNACK, SUBACK, deliveries: server-to-client packets the decoders must survive too) to
`seeds/mqtt_decode/`.

Usage (from anywhere; needs mosquitto, mosquitto-clients, python3-paho-mqtt >= 2):

    python3 broker/fuzz/seeds/capture.py            # writes broker/fuzz/seeds/mqtt_decode/
    python3 broker/fuzz/seeds/capture.py --out DIR

Client ids, topics and payloads are fixed, so a rerun writes the same packets (mosquitto's
own answers may differ between versions in their properties).
"""

import argparse
import os
import shutil
import socket
import subprocess
import sys
import tempfile
import threading
import time

HERE = os.path.dirname(os.path.abspath(__file__))


def free_port():
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def wait_port(port, timeout=10.0):
    deadline = time.time() + timeout
    while time.time() < deadline:
        try:
            socket.create_connection(("127.0.0.1", port), timeout=0.2).close()
            return
        except OSError:
            time.sleep(0.05)
    raise RuntimeError(f"nothing listens on {port}")


class Recorder:
    """A TCP proxy that keeps both directions of every connection, in accept order."""

    def __init__(self, upstream_port):
        self.upstream_port = upstream_port
        self.server = socket.socket()
        self.server.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        self.server.bind(("127.0.0.1", 0))
        self.server.listen(16)
        self.port = self.server.getsockname()[1]
        self.lock = threading.Lock()
        self.connections = []  # [c2s bytearray, s2c bytearray, done Event]
        threading.Thread(target=self.accept_loop, daemon=True).start()

    def accept_loop(self):
        while True:
            try:
                client, _ = self.server.accept()
            except OSError:
                return
            upstream = socket.create_connection(("127.0.0.1", self.upstream_port))
            record = [bytearray(), bytearray(), threading.Event(), threading.Event()]
            with self.lock:
                self.connections.append(record)
            threading.Thread(
                target=self.pump, args=(client, upstream, record[0], record[2]), daemon=True
            ).start()
            threading.Thread(
                target=self.pump, args=(upstream, client, record[1], record[3]), daemon=True
            ).start()

    @staticmethod
    def pump(src, dst, keep, done):
        try:
            while True:
                data = src.recv(65536)
                if not data:
                    break
                keep.extend(data)
                dst.sendall(data)
        except OSError:
            pass
        finally:
            for s in (dst, src):
                try:
                    s.shutdown(socket.SHUT_RDWR)
                except OSError:
                    pass
            done.set()

    def take(self, expected, timeout=10.0):
        """Waits for `expected` connections since the last take to close; returns them."""
        deadline = time.time() + timeout
        while time.time() < deadline:
            with self.lock:
                if len(self.connections) >= expected and all(
                    c[2].is_set() and c[3].is_set() for c in self.connections[:expected]
                ):
                    taken = self.connections[:expected]
                    self.connections = self.connections[expected:]
                    return [(bytes(c[0]), bytes(c[1])) for c in taken]
            time.sleep(0.05)
        raise RuntimeError(f"expected {expected} finished connections, have {len(self.connections)}")


def run(cmd, **kw):
    subprocess.run(cmd, check=True, timeout=30, **kw)


def mosquitto_scenarios(port, rec, save):
    pub = ["mosquitto_pub", "-h", "127.0.0.1", "-p", str(port)]
    sub = ["mosquitto_sub", "-h", "127.0.0.1", "-p", str(port)]

    # 3.1.1 QoS 0 on a topic whose first character is multi-byte (issue 14).
    run(pub + ["-i", "pub-311-q0", "-t", "é/x", "-m", "1"])
    save("v311-pub-qos0-multibyte", rec.take(1))

    # 3.1.1 QoS 1, retained, with user, password and a will.
    run(pub + ["-i", "plc-1", "-u", "plc-1", "-P", "s3cret", "-q", "1", "-r",
               "--will-topic", "fbbus/will/plc-1", "--will-payload", "gone",
               "--will-qos", "1", "--will-retain",
               "-t", "Förderband/1", "-m", "Geschwindigkeit 3"])
    save("v311-pub-qos1-will-login", rec.take(1))

    # 3.1.1 QoS 2 (PUBLISH, then PUBREL after PUBREC).
    run(pub + ["-i", "pub-311-q2", "-q", "2", "-t", "日本/ライン/1", "-m", "{\"v\":1}"])
    save("v311-pub-qos2", rec.take(1))

    # MQTT 5 with properties on CONNECT, PUBLISH and the will; QoS 1 and 2.
    v5 = pub + ["-V", "mqttv5"]
    run(v5 + ["-i", "plc-5", "-u", "plc-5", "-P", "pässwort", "-q", "1", "-x", "300",
              "-D", "connect", "user-property", "line", "1",
              "-D", "connect", "receive-maximum", "10",
              "-D", "connect", "maximum-packet-size", "65536",
              "-D", "publish", "user-property", "unit", "m/s",
              "-D", "publish", "content-type", "application/json",
              "-D", "publish", "message-expiry-interval", "60",
              "-D", "publish", "payload-format-indicator", "1",
              "-D", "publish", "response-topic", "fb/plc-5/CONV/REPLY",
              "-D", "publish", "correlation-data", "abc",
              "--will-topic", "fbbus/will/plc-5", "--will-payload", "weg", "--will-qos", "2",
              "-D", "will", "will-delay-interval", "5",
              "-D", "will", "user-property", "why", "crash",
              "-t", "fb/plc-5/CONV/SPEED", "-m", "3"])
    save("v5-pub-qos1-properties-will", rec.take(1))

    run(v5 + ["-i", "plc-5b", "-q", "2", "-D", "publish", "topic-alias", "1",
              "-t", "Förderband/2/é", "-m", "70000"])
    save("v5-pub-qos2-topic-alias", rec.take(1))

    # Subscribers receiving QoS 1 and 2 deliveries (their PUBACK, PUBREC, PUBCOMP), with
    # wildcards, `$` and shared subscriptions, and an UNSUBSCRIBE.
    for version, q, name, extra in [
        ("mqttv311", "1", "v311-sub-qos1-wildcards", []),
        ("mqttv311", "2", "v311-sub-qos2-unsubscribe", ["-U", "fb/+/CONV/#"]),
        ("mqttv5", "2", "v5-sub-qos2-shared", ["-D", "subscribe", "user-property", "k", "v",
                                               "-D", "subscribe", "subscription-identifier", "7"]),
    ]:
        topics = ["-t", "#", "-t", "fb/+/CONV/#", "-t", "$SYS/broker/uptime",
                  "-t", "$share/g1/Förderband/+"]
        proc = subprocess.Popen(sub + ["-V", version, "-i", f"sub-{name}", "-q", q,
                                       "-C", "2", "-W", "8"] + topics + extra,
                                stdout=subprocess.DEVNULL)
        time.sleep(0.5)
        run(pub + ["-i", "pub-for-sub", "-q", q, "-t", "Förderband/1", "-m", "a"])
        run(pub + ["-i", "pub-for-sub2", "-q", q, "-t", "fb/plc-1/CONV/SPEED", "-m", "b"])
        proc.wait(timeout=15)
        conns = rec.take(3)
        save(name, conns[:1])
        # The publishers of the deliveries are ordinary seeds too.
        save(name + "-publisher", conns[1:2])


def paho_scenarios(port, rec, save):
    import paho.mqtt.client as mqtt
    from paho.mqtt.packettypes import PacketTypes
    from paho.mqtt.properties import Properties
    from paho.mqtt.reasoncodes import ReasonCode
    from paho.mqtt.subscribeoptions import SubscribeOptions

    def connect(client, keepalive=30):
        client.connect("127.0.0.1", port, keepalive=keepalive)
        client.loop_start()
        time.sleep(0.3)

    def finish(client, **disconnect):
        time.sleep(0.5)
        client.disconnect(**disconnect)
        time.sleep(0.3)
        client.loop_stop()

    # 3.1.1: will, login, QoS 0/1/2 publications, subscribe, unsubscribe, and PINGREQs
    # (keep-alive 1 s).
    c = mqtt.Client(mqtt.CallbackAPIVersion.VERSION2, client_id="paho-311",
                    protocol=mqtt.MQTTv311, clean_session=False)
    c.username_pw_set("paho-311", "geheim")
    c.will_set("fbbus/will/paho-311", "offline", qos=1, retain=True)
    connect(c, keepalive=1)
    c.subscribe([("é/#", 1), ("+/CONV/+", 2), ("fb/#", 0)])
    for qos in (0, 1, 2):
        c.publish("Förderband/1", f"q{qos}".encode(), qos=qos)
    c.publish("fb/paho-311/CONV/SPEED", b"3", qos=1, retain=True)
    time.sleep(2.5)
    c.unsubscribe(["é/#", "+/CONV/+"])
    finish(c)
    save("paho-v311-session", rec.take(1))

    # 5: properties everywhere, subscription options, DISCONNECT with a reason and
    # properties (0x04: disconnect with will message).
    c = mqtt.Client(mqtt.CallbackAPIVersion.VERSION2, client_id="paho-5", protocol=mqtt.MQTTv5)
    c.username_pw_set("paho-5", "pässwört")
    will = Properties(PacketTypes.WILLMESSAGE)
    will.WillDelayInterval = 10
    will.UserProperty = ("device", "paho-5")
    c.will_set("fbbus/will/paho-5", "tot", qos=2, retain=False, properties=will)
    props = Properties(PacketTypes.CONNECT)
    props.SessionExpiryInterval = 120
    props.ReceiveMaximum = 20
    props.TopicAliasMaximum = 5
    props.UserProperty = ("line", "Förderband")
    c.connect("127.0.0.1", port, keepalive=30, clean_start=True, properties=props)
    c.loop_start()
    time.sleep(0.3)
    sub_props = Properties(PacketTypes.SUBSCRIBE)
    sub_props.SubscriptionIdentifier = 42
    c.subscribe([("fb/#", SubscribeOptions(qos=2, noLocal=True, retainAsPublished=True,
                                           retainHandling=SubscribeOptions.RETAIN_SEND_IF_NEW_SUB)),
                 ("$share/grp/日本/+", SubscribeOptions(qos=1)),
                 ("é/x", SubscribeOptions(qos=0, retainHandling=SubscribeOptions.RETAIN_DO_NOT_SEND))],
                properties=sub_props)
    pub_props = Properties(PacketTypes.PUBLISH)
    pub_props.ContentType = "application/json"
    pub_props.UserProperty = [("a", "1"), ("ü", "ß")]
    pub_props.CorrelationData = b"\x00\x01\x02"
    pub_props.MessageExpiryInterval = 30
    for qos in (0, 1, 2):
        c.publish("日本/ライン/1", b'{"seq":1,"data":{}}', qos=qos, properties=pub_props)
    alias = Properties(PacketTypes.PUBLISH)
    alias.TopicAlias = 2
    c.publish("é/x", b"with alias", qos=1, properties=alias)
    c.publish("", b"alias only", qos=1, properties=alias)
    time.sleep(0.5)
    unsub_props = Properties(PacketTypes.UNSUBSCRIBE)
    unsub_props.UserProperty = ("bye", "now")
    c.unsubscribe(["$share/grp/日本/+", "é/x"], properties=unsub_props)
    disc = Properties(PacketTypes.DISCONNECT)
    disc.ReasonString = "maintenance"
    disc.SessionExpiryInterval = 0
    finish(c, reasoncode=ReasonCode(PacketTypes.DISCONNECT, "Disconnect with will message"),
           properties=disc)
    save("paho-v5-session", rec.take(1))

    # 5: DISCONNECT with a reason code and no properties (remaining length 1 is allowed).
    c = mqtt.Client(mqtt.CallbackAPIVersion.VERSION2, client_id="paho-5-short", protocol=mqtt.MQTTv5)
    connect(c)
    finish(c, reasoncode=ReasonCode(PacketTypes.DISCONNECT, "Disconnect with will message"))
    save("paho-v5-disconnect-reason", rec.take(1))


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", default=os.path.join(HERE, "mqtt_decode"))
    args = parser.parse_args()
    for tool in ("mosquitto", "mosquitto_pub", "mosquitto_sub"):
        if not shutil.which(tool) and not os.path.exists(f"/usr/sbin/{tool}"):
            sys.exit(f"capture.py: {tool} is missing (apt-get install mosquitto mosquitto-clients)")
    try:
        import paho.mqtt  # noqa: F401
    except ImportError:
        sys.exit("capture.py: paho-mqtt is missing (pip install 'paho-mqtt>=2')")

    os.makedirs(args.out, exist_ok=True)
    broker_port = free_port()
    with tempfile.TemporaryDirectory() as tmp:
        conf = os.path.join(tmp, "mosquitto.conf")
        with open(conf, "w") as f:
            f.write(f"listener {broker_port} 127.0.0.1\nallow_anonymous true\n"
                    "persistence false\nlog_dest none\n")
        mosquitto = shutil.which("mosquitto") or "/usr/sbin/mosquitto"
        broker = subprocess.Popen([mosquitto, "-c", conf])
        try:
            wait_port(broker_port)
            rec = Recorder(broker_port)
            written = []

            def save(name, conns):
                for c2s, s2c in conns:
                    for suffix, data in (("c2s", c2s), ("s2c", s2c)):
                        if data:
                            path = os.path.join(args.out, f"{name}.{suffix}")
                            with open(path, "wb") as f:
                                f.write(data)
                            written.append((path, len(data)))

            mosquitto_scenarios(rec.port, rec, save)
            paho_scenarios(rec.port, rec, save)
        finally:
            broker.terminate()
            broker.wait(timeout=10)
    for path, size in written:
        print(f"{size:6d}  {os.path.relpath(path)}")


if __name__ == "__main__":
    main()

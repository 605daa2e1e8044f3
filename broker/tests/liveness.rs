//! "...and is gone when it stops answering" (issue 20): a client that stops reading, or
//! whose link is cut, is closed within its keep-alive bound (or, without keep-alive, the
//! slow-consumer and dead-link bounds), with its will and `offline` in the registry, even
//! while messages flow to it; publishers and the other subscribers go on.
//!
//! - a `mosquitto_sub` stopped with SIGSTOP (its kernel keeps acknowledging with a zero
//!   window, like a hung PLC network stack) while 300 x 60 KB flow to it;
//! - a raw client that stops reading, without keep-alive, with a persistent session: a
//!   slow consumer, whose QoS 1 messages wait for its return;
//! - clients in a network namespace the test creates whose link is cut (a veth pair set
//!   down: packets vanish, as with a pulled cable), with and without keep-alive, with data
//!   in flight and idle. Skipped, with the reason printed, where namespaces cannot be made.

mod common;

use std::process::{Child, Command, Stdio};
use std::time::{Duration, Instant};

use serde_json::Value;

use common::clients::V4;
use common::netns::{lines_of, VethPair};
use common::raw::{self, Connect, RawClient};
use common::{http_get, Broker, Options};

const CONV: &str = r#"{"fbs":{"CONV":{"data_out":{"POSITION":"INT"}}}}"#;

/// Will and registry within this of the stop: 1.5 x keep-alive 5 s, plus 0.5 s.
const KEEP_ALIVE_BOUND: Duration = Duration::from_millis(8_000);

/// A child process, resumed (if stopped), killed and reaped when dropped.
struct Guard(Child);

impl Drop for Guard {
    fn drop(&mut self) {
        let _ = Command::new("kill")
            .args(["-CONT", &self.0.id().to_string()])
            .stderr(Stdio::null())
            .status();
        let _ = self.0.kill();
        let _ = self.0.wait();
    }
}

fn signal(child: &Child, signal: &str) {
    let status = Command::new("kill")
        .args([&format!("-{signal}"), &child.id().to_string()])
        .status()
        .unwrap();
    assert!(status.success(), "kill -{signal}");
}

/// The registry record of `id` on the broker's admin endpoint.
fn record(broker: &Broker, id: &str) -> Option<Value> {
    let (code, body) = http_get(broker.admin, &format!("/api/v1/devices/{id}"))?;
    (code == 200).then(|| serde_json::from_str(&body).ok())?
}

/// Polls `probe` every 50 ms until it returns Some, at most until `deadline`.
fn poll_until<T>(deadline: Instant, mut probe: impl FnMut() -> Option<T>) -> Option<T> {
    loop {
        if let Some(t) = probe() {
            return Some(t);
        }
        if Instant::now() >= deadline {
            return None;
        }
        std::thread::sleep(Duration::from_millis(50));
    }
}

/// Declares `id`'s interface (a registry record for it), as a device does.
fn declare(port: u16, id: &str) {
    let (ok, _, err) = common::run(
        Command::new("mosquitto_pub").args([
            "-h",
            "127.0.0.1",
            "-p",
            &port.to_string(),
            "-i",
            id,
            "-q",
            "1",
            "-t",
            &format!("fbbus/declare/{id}"),
            "-m",
            CONV,
        ]),
        Duration::from_secs(10),
    );
    assert!(ok, "declaring {id}: {err}");
}

/// The payload of the next publication on `topic`, until `deadline`.
async fn will_before(sub: &mut V4, topic: &str, deadline: Instant) -> Option<Vec<u8>> {
    let left = deadline.saturating_duration_since(Instant::now());
    sub.next(left, |p| match p {
        rumqttc::Packet::Publish(p) if p.topic == topic => Some(p.payload.to_vec()),
        _ => None,
    })
    .await
}

/// The issue's reproduction. A `mosquitto_sub` with keep-alive 5 s and a will, stopped with
/// SIGSTOP while 300 messages of 60 KB are published on its topic: its will is delivered
/// and the registry marks it offline within 8 s of the stop, while two healthy subscribers
/// of the same topic get all 300 messages meanwhile.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_frozen_subscriber_is_gone_within_its_keep_alive_while_messages_flow() {
    const MESSAGES: usize = 300;
    const PAYLOAD: usize = 60 * 1024;
    if !common::require("mosquitto_sub") || !common::require("mosquitto_pub") {
        return;
    }
    let broker = Broker::start();
    let port = broker.port().to_string();
    let mut watcher = V4::connect(broker.port(), "watcher", None).await.unwrap();
    watcher.subscribe("will/#").await;
    declare(broker.port(), "frozen");

    let mosquitto_sub = |id: &str, extra: &[&str]| {
        Guard(
            Command::new("mosquitto_sub")
                .args(["-h", "127.0.0.1", "-p", &port, "-i", id, "-t", "flow/data"])
                .args(extra)
                .stdout(Stdio::null())
                .stderr(Stdio::null())
                .spawn()
                .expect("spawn mosquitto_sub"),
        )
    };
    let frozen = mosquitto_sub(
        "frozen",
        &[
            "-k",
            "5",
            "--will-topic",
            "will/frozen",
            "--will-payload",
            "dead",
        ],
    );
    // Healthy subscribers: exit once they have all the messages.
    let count = MESSAGES.to_string();
    let mut healthy: Vec<Guard> = ["healthy-1", "healthy-2"]
        .iter()
        .map(|id| mosquitto_sub(id, &["-C", &count]))
        .collect();
    let online = poll_until(Instant::now() + Duration::from_secs(10), || {
        let online = record(&broker, "frozen").is_some_and(|r| r["status"] == "online");
        (online && broker.metric("fbbus_connections") >= 4.0).then_some(())
    });
    assert!(
        online.is_some(),
        "frozen and the healthy subscribers did not connect: {:?}\n{}",
        record(&broker, "frozen"),
        broker.log_text()
    );

    signal(&frozen.0, "STOP");
    let stopped = Instant::now();
    let publisher = {
        let port = broker.port();
        std::thread::spawn(move || {
            let mut publisher = RawClient::connect(port);
            let connect = Connect {
                client_id: "publisher",
                ..Connect::default()
            };
            assert_eq!(publisher.handshake(&connect), 0);
            let message = raw::publish_qos0("flow/data", &[b'x'; PAYLOAD]);
            for _ in 0..MESSAGES {
                publisher.send(&message);
            }
            let sent = Instant::now();
            publisher.send(&raw::DISCONNECT);
            sent
        })
    };

    // The healthy subscribers get everything, long before the frozen one is closed: it
    // holds nobody up (the router may hold the publisher for `slow_subscriber_hold_ms`,
    // 1 s, once its filter's log is full).
    let publisher_done = publisher.join().expect("publisher");
    for sub in &mut healthy {
        let status = common::wait_until(&mut sub.0, Duration::from_secs(3));
        assert!(
            status.is_some_and(|s| s.success()),
            "a healthy subscriber did not get {MESSAGES} messages within 3 s of the \
             publisher: {status:?}\n{}",
            broker.log_text()
        );
    }
    let healthy_after = stopped.elapsed();

    let will = will_before(&mut watcher, "will/frozen", stopped + KEEP_ALIVE_BOUND).await;
    let will_after = stopped.elapsed();
    assert_eq!(
        will.as_deref(),
        Some(&b"dead"[..]),
        "no will within {KEEP_ALIVE_BOUND:?} of SIGSTOP; log:\n{}",
        broker.log_text()
    );
    let offline = poll_until(stopped + KEEP_ALIVE_BOUND, || {
        record(&broker, "frozen").filter(|r| r["status"] == "offline")
    });
    let offline_after = stopped.elapsed();
    let offline = offline.unwrap_or_else(|| {
        panic!(
            "frozen not offline within {KEEP_ALIVE_BOUND:?}: {:?}\n{}",
            record(&broker, "frozen"),
            broker.log_text()
        )
    });
    let reason = offline["last_will_reason"].as_str().unwrap_or_default();
    assert!(
        ["keep-alive expired", "slow consumer"].contains(&reason),
        "{offline}"
    );
    eprintln!(
        "frozen subscriber: will {will_after:?}, offline ({reason}) {offline_after:?} after \
         SIGSTOP; the publisher sent {MESSAGES} x {PAYLOAD} B in {:?}; the healthy \
         subscribers had them all {healthy_after:?} after SIGSTOP",
        publisher_done - stopped
    );
    // The disconnect is counted at the end of the connection's close, after the will and
    // the offline record seen above.
    let ends = || {
        broker.metric("fbbus_disconnects_total{reason=\"keep_alive\"}")
            + broker.metric("fbbus_disconnects_total{reason=\"slow_consumer\"}")
    };
    let counted = poll_until(Instant::now() + Duration::from_secs(10), || {
        Some(ends()).filter(|n| *n >= 1.0)
    })
    .unwrap_or_else(ends);
    assert_eq!(counted, 1.0, "{}", broker.metrics());
    assert!(broker.metric("fbbus_wills_published_total") >= 1.0);
    drop(frozen);
}

/// MQTT 3.1.1 QoS 1 PUBLISH.
fn publish_qos1(topic: &str, pkid: u16, payload: &[u8]) -> Vec<u8> {
    let mut body = Vec::new();
    body.extend_from_slice(&(topic.len() as u16).to_be_bytes());
    body.extend_from_slice(topic.as_bytes());
    body.extend_from_slice(&pkid.to_be_bytes());
    body.extend_from_slice(payload);
    raw::packet(0x32, &body)
}

/// MQTT 3.1.1 SUBSCRIBE of one filter at `qos`.
fn subscribe_qos(pkid: u16, filter: &str, qos: u8) -> Vec<u8> {
    let mut body = pkid.to_be_bytes().to_vec();
    body.extend_from_slice(&(filter.len() as u16).to_be_bytes());
    body.extend_from_slice(filter.as_bytes());
    body.push(qos);
    raw::packet(0x82, &body)
}

/// A client without keep-alive (so only the write deadline can find it) and with a
/// persistent session stops reading while 8 MB of QoS 0 and 20 QoS 1 messages are sent to
/// it: it is closed as a slow consumer after `slow_consumer_timeout_ms` (1 s here), its
/// will fires, the QoS 0 deliveries it had not taken are counted as dropped, and when it
/// comes back every QoS 1 message is delivered.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_client_that_stops_reading_is_a_slow_consumer_and_keeps_its_qos1_messages() {
    let broker = Broker::start_with(
        Options {
            extra: "slow_consumer_timeout_ms = 1000\n".into(),
            ..Options::default()
        },
        |_| {},
    );
    let mut watcher = V4::connect(broker.port(), "watcher", None).await.unwrap();
    watcher.subscribe("will/#").await;
    let persistent = |will| Connect {
        client_id: "stops-reading",
        keep_alive: 0,
        clean: false,
        will,
        ..Connect::default()
    };
    let mut client = RawClient::connect(broker.port());
    assert_eq!(
        client.handshake(&persistent(Some(("will/stops-reading", b"slow")))),
        0
    );
    client.send(&subscribe_qos(1, "slow/q0", 0));
    assert_eq!(client.read_packet().expect("SUBACK").0, 0x90);
    client.send(&subscribe_qos(2, "slow/q1", 1));
    assert_eq!(client.read_packet().expect("SUBACK").0, 0x90);
    // From here on the client reads nothing.

    let mut publisher = RawClient::connect(broker.port());
    assert_eq!(
        publisher.handshake(&Connect {
            client_id: "pub",
            ..Connect::default()
        }),
        0
    );
    let flood = raw::publish_qos0("slow/q0", &[7u8; 32 * 1024]).repeat(256);
    publisher.send(&flood);
    for seq in 1..=20u16 {
        publisher.send(&publish_qos1("slow/q1", seq, &seq.to_be_bytes()));
    }
    let started = Instant::now();
    let will = will_before(
        &mut watcher,
        "will/stops-reading",
        started + Duration::from_secs(6),
    )
    .await;
    assert_eq!(
        will.as_deref(),
        Some(&b"slow"[..]),
        "no will for the slow consumer; log:\n{}",
        broker.log_text()
    );
    eprintln!(
        "slow consumer closed, will delivered {:?} after the publications",
        started.elapsed()
    );
    // Counted at the end of the close, after the will.
    assert_eq!(
        broker.wait_metric("fbbus_disconnects_total{reason=\"slow_consumer\"}", 1.0),
        1.0,
        "{}",
        broker.metrics()
    );
    let dropped = broker.metric("fbbus_messages_dropped_total{reason=\"slow_consumer\"}");
    assert!(
        dropped > 0.0,
        "unwritten QoS 0 deliveries counted: {}",
        broker.metrics()
    );
    assert!(
        broker.log_text().contains("slow consumer"),
        "the close is logged: {}",
        broker.log_text()
    );
    drop(client);

    // Back, same persistent session: every QoS 1 message arrives (QoS 0 ones may too).
    let mut back = RawClient::connect(broker.port());
    back.send(&persistent(None).bytes());
    let (byte1, body) = back.read_packet().expect("CONNACK");
    assert_eq!((byte1, body[1]), (0x20, 0), "CONNACK");
    assert_eq!(body[0] & 1, 1, "session present");
    back.stream
        .set_read_timeout(Some(Duration::from_secs(3)))
        .unwrap();
    let mut seqs = std::collections::BTreeSet::new();
    let deadline = Instant::now() + Duration::from_secs(20);
    while seqs.len() < 20 && Instant::now() < deadline {
        let Some((byte1, body)) = back.read_packet() else {
            break;
        };
        if byte1 & 0xf0 != 0x30 || (byte1 >> 1) & 3 != 1 {
            continue;
        }
        let topic_len = u16::from_be_bytes([body[0], body[1]]) as usize;
        assert_eq!(&body[2..2 + topic_len], b"slow/q1");
        let pkid = [body[2 + topic_len], body[3 + topic_len]];
        let payload = &body[4 + topic_len..];
        seqs.insert(u16::from_be_bytes([payload[0], payload[1]]));
        back.send(&raw::packet(0x40, &pkid));
    }
    assert_eq!(
        seqs,
        (1..=20).collect(),
        "QoS 1 messages kept for the returning session; log:\n{}",
        broker.log_text()
    );
}

/// The broker's namespace `a` and the devices' namespace `b` (`common::netns`).
struct Net(VethPair);

const BROKER_IP: &str = "10.214.0.1";

impl std::ops::Deref for Net {
    type Target = VethPair;
    fn deref(&self) -> &VethPair {
        &self.0
    }
}

impl Net {
    fn create() -> Result<Net, String> {
        VethPair::create("fbl", "vl", "10.214.0").map(Net)
    }

    /// Pulls the cable on the devices' side: their end goes down, the broker's end loses
    /// its carrier, and whatever the broker sends them vanishes without an error.
    fn cut(&self) {
        self.set_link(&self.b, &self.veth_b, false);
    }

    fn record(&self, id: &str) -> Option<Value> {
        let out = self
            .exec(&self.a, common::fbbus_bin())
            .args(["devices", "--admin", "127.0.0.1:9883", "--json", id])
            .stderr(Stdio::null())
            .output()
            .ok()?;
        serde_json::from_slice(&out.stdout).ok()
    }
}

/// A raw MQTT 3.1.1 client in Python (only the standard library): CONNECT with
/// keep-alive 0 and a will, SUBSCRIBE, then reads whatever comes.
const PY_CLIENT: &str = r#"
import socket, struct, sys
host, user, pw, topic = sys.argv[1:5]
def s(b): return struct.pack('!H', len(b)) + b
def pkt(t, body):
    n, rl = len(body), b''
    while True:
        d, n = n % 128, n // 128
        rl += bytes([d | (128 if n else 0)])
        if not n: return bytes([t]) + rl + body
u = user.encode()
body = s(b'MQTT') + bytes([4, 0xC0 | 0x04 | 0x02]) + struct.pack('!H', 0)
body += s(u) + s(b'will/' + u) + s(b'gone') + s(u) + s(pw.encode())
c = socket.create_connection((host, 1883))
c.sendall(pkt(0x10, body))
c.sendall(pkt(0x82, struct.pack('!H', 1) + s(topic.encode()) + b'\x00'))
while c.recv(65536): pass
"#;

/// A cut link, with data in flight and without: a device with keep-alive 5 s is gone
/// within 8 s (1.5 x keep-alive + 0.5 s), by its keep-alive; devices without keep-alive
/// within the dead-link bound, `dead_link_timeout_s` (8 s here, above the keep-alive
/// bound so each mechanism is seen on its own) + max(1 s, a tenth of it), plus 1 s of
/// slack for the retransmission timer's granularity and the registry: within 10 s.
#[test]
fn a_cut_link_ends_the_session_within_the_keep_alive_or_dead_link_bound() {
    const DEAD_LINK: Duration = Duration::from_secs(8);
    const DEAD_LINK_BOUND: Duration = Duration::from_secs(10);
    if !common::have("mosquitto_pub") || !common::have("mosquitto_sub") || !common::have("python3")
    {
        eprintln!(
            "SKIPPED: mosquitto_pub, mosquitto_sub or python3 missing (.ci/run installs them)"
        );
        return;
    }
    let net = match Net::create() {
        Ok(net) => net,
        Err(e) => {
            eprintln!(
                "SKIPPED: cannot create network namespaces here (needs root or CAP_NET_ADMIN \
                 and iproute2): {e}"
            );
            return;
        }
    };
    let dir = tempfile::tempdir().unwrap();
    let passwd = dir.path().join("passwd");
    let users = ["with-ka", "ka0-busy", "ka0-idle", "watcher", "feeder"];
    for user in users {
        common::add_user(&passwd, user, "pw");
    }
    let config = dir.path().join("fbbus.toml");
    std::fs::write(
        &config,
        format!(
            "[broker]\nline = \"cut\"\ndead_link_timeout_s = {}\nslow_consumer_timeout_ms = 60000\n\
             [auth]\npassword_file = \"{}\"\n\
             [[listener]]\nname = \"main\"\nbind = \"{BROKER_IP}:1883\"\n\
             [admin]\nbind = \"127.0.0.1:9883\"\n[fb]\nregistry_file = \"\"\n",
            DEAD_LINK.as_secs(),
            passwd.display()
        ),
    )
    .unwrap();
    // Killed before `net` deletes the namespaces (dropped first: declared later).
    let mut procs: Vec<Guard> = Vec::new();
    let log_path = dir.path().join("broker.log");
    let broker = net
        .exec(&net.a, common::fbbus_bin())
        .args(["serve", "--config", config.to_str().unwrap()])
        .stdout(Stdio::null())
        .stderr(std::fs::File::create(&log_path).unwrap())
        .spawn()
        .unwrap();
    procs.push(Guard(broker));
    let log = || std::fs::read_to_string(&log_path).unwrap_or_default();
    let ready = poll_until(Instant::now() + Duration::from_secs(20), || {
        net.exec(&net.a, common::fbbus_bin())
            .args(["devices", "--admin", "127.0.0.1:9883", "--json"])
            .stdout(Stdio::null())
            .stderr(Stdio::null())
            .status()
            .is_ok_and(|s| s.success())
            .then_some(())
    });
    assert!(ready.is_some(), "broker not ready: {}", log());

    let mqtt = |ns: &str, program: &str, user: &str| {
        let mut c = net.exec(ns, program);
        c.args(["-h", BROKER_IP, "-u", user, "-P", "pw", "-i", user]);
        c
    };
    for device in ["with-ka", "ka0-busy", "ka0-idle"] {
        let (ok, _, err) = common::run(
            mqtt(&net.b, "mosquitto_pub", device).args([
                "-q",
                "1",
                "-t",
                &format!("fbbus/declare/{device}"),
                "-m",
                CONV,
            ]),
            Duration::from_secs(10),
        );
        assert!(ok, "declaring {device}: {err}\n{}", log());
    }
    // The watcher, next to the broker: prints each will as `topic payload`.
    let mut watcher = mqtt(&net.a, "mosquitto_sub", "watcher")
        .args(["-t", "will/#", "-v"])
        .stdout(Stdio::piped())
        .spawn()
        .unwrap();
    let wills = lines_of(&mut watcher);
    procs.push(Guard(watcher));
    // The devices, across the link.
    let with_ka = mqtt(&net.b, "mosquitto_sub", "with-ka")
        .args(["-k", "5", "-t", "flow/cut", "--will-topic", "will/with-ka"])
        .args(["--will-payload", "gone"])
        .stdout(Stdio::null())
        .stderr(Stdio::null())
        .spawn()
        .unwrap();
    procs.push(Guard(with_ka));
    for (device, topic) in [("ka0-busy", "flow/cut"), ("ka0-idle", "quiet")] {
        let child = net
            .exec(&net.b, "python3")
            .args(["-c", PY_CLIENT, BROKER_IP, device, "pw", topic])
            .stdout(Stdio::null())
            .spawn()
            .unwrap();
        procs.push(Guard(child));
    }
    let online = poll_until(Instant::now() + Duration::from_secs(15), || {
        ["with-ka", "ka0-busy", "ka0-idle"]
            .iter()
            .all(|d| net.record(d).is_some_and(|r| r["status"] == "online"))
            .then_some(())
    });
    assert!(online.is_some(), "devices not online: {}", log());

    // Data in flight: 60 KB messages, 20 a second, to the two busy devices.
    let payload = dir.path().join("payload");
    std::fs::write(&payload, vec![b'x'; 60 * 1024]).unwrap();
    let feeder = mqtt(&net.a, "mosquitto_pub", "feeder")
        .args(["-t", "flow/cut", "-f", payload.to_str().unwrap()])
        .args(["--repeat", "400", "--repeat-delay", "0.05"])
        .stdout(Stdio::null())
        .spawn()
        .unwrap();
    procs.push(Guard(feeder));
    std::thread::sleep(Duration::from_secs(1));

    net.cut();
    let cut = Instant::now();
    let mut gone = std::collections::BTreeMap::new();
    let deadline = cut + KEEP_ALIVE_BOUND.max(DEAD_LINK_BOUND);
    while gone.len() < 3 && Instant::now() < deadline {
        if let Ok(line) = wills.recv_timeout(Duration::from_millis(50)) {
            if let Some(device) = line.strip_prefix("will/").and_then(|l| l.split(' ').next()) {
                gone.entry(device.to_owned()).or_insert(cut.elapsed());
            }
        }
    }
    for (device, bound, reason) in [
        ("with-ka", KEEP_ALIVE_BOUND, "keep-alive expired"),
        ("ka0-busy", DEAD_LINK_BOUND, "connection lost"),
        ("ka0-idle", DEAD_LINK_BOUND, "connection lost"),
    ] {
        let took = gone.get(device).copied();
        assert!(
            took.is_some_and(|t| t <= bound),
            "{device}: will {took:?} after the cut, bound {bound:?}; wills {gone:?}\n{}",
            log()
        );
        let record = net.record(device);
        assert!(
            record
                .as_ref()
                .is_some_and(|r| r["status"] == "offline" && r["last_will_reason"] == reason),
            "{device} not offline with reason {reason}: {record:?}"
        );
        eprintln!(
            "{device}: will {:?} after the cut (bound {bound:?}), offline: {}",
            took.unwrap_or_default(),
            record.unwrap()["last_will_reason"]
        );
    }
}

/// An MQTT 5 client with Receive Maximum 1 that reads but never acknowledges: deliveries
/// wait for its window, and once they hold more than `slow_consumer_max_bytes` it is a
/// slow consumer, told so with DISCONNECT 0x97 (its socket still takes data).
#[test]
fn deliveries_held_for_a_client_that_never_acknowledges_are_bounded() {
    let broker = Broker::start_with(
        Options {
            // The smallest limit: 1 MiB + max_packet_bytes.
            extra: "slow_consumer_max_bytes = 1114112\n".into(),
            ..Options::default()
        },
        |_| {},
    );
    let mut client = RawClient::connect(broker.port());
    let code = client.handshake(&Connect {
        version: 5,
        client_id: "never-acks",
        receive_maximum: Some(1),
        ..Connect::default()
    });
    assert_eq!(code, 0);
    client.send(&raw::subscribe_with_options(1, "held/t", 1));
    assert_eq!(client.read_packet().expect("SUBACK").0, 0x90);

    let mut publisher = RawClient::connect(broker.port());
    assert_eq!(
        publisher.handshake(&Connect {
            client_id: "held-pub",
            ..Connect::default()
        }),
        0
    );
    for pkid in 1..=40u16 {
        publisher.send(&publish_qos1("held/t", pkid, &[1u8; 60 * 1024]));
    }
    // The client reads everything it is sent, acknowledging nothing.
    let mut publishes = 0;
    let disconnect = loop {
        let Some((byte1, body)) = client.read_packet() else {
            panic!("closed without DISCONNECT; log:\n{}", broker.log_text());
        };
        match byte1 & 0xf0 {
            0x30 => publishes += 1,
            0xE0 => break body,
            other => panic!("unexpected packet {other:#04x}"),
        }
    };
    assert_eq!(publishes, 1, "one delivery in the window of 1");
    assert_eq!(disconnect.first(), Some(&0x97), "DISCONNECT Quota exceeded");
    assert_eq!(
        broker.wait_metric("fbbus_disconnects_total{reason=\"slow_consumer\"}", 1.0),
        1.0
    );
}

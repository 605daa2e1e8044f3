//! Read access is enforced at delivery (issue #20): a subscription made under older rules,
//! or by an earlier connection of a resumed session, delivers only what the rules in force
//! let the client read. An ACL reload that revokes a read stops deliveries to existing
//! subscriptions; refused deliveries are acknowledged to the router for the client (its
//! window does not fill up), counted and logged once per session and topic.
//!
//! Real clients: rumqttc (3.1.1 and 5) and mosquitto_sub (3.1.1 and 5).

mod common;

use std::io::{BufRead, BufReader};
use std::process::{Child, Command, Stdio};
use std::sync::mpsc;
use std::time::{Duration, Instant};

use common::clients::{V4, V5, WAIT};
use common::{add_user, require, Broker, Options};

/// Devices publish under their own namespace; everyone reads the plant; the monitor
/// reads everything.
const ACL: &str = "\
pattern write plant/%c/#
pattern read plant/#
user monitor
topic read #
";

/// The same, with dev2's messages no longer readable by the monitor (the line is in the
/// `user monitor` section).
fn revoked() -> String {
    format!("{ACL}topic deny plant/dev2/#\n")
}

/// More refused QoS 1 deliveries than the router lets a session have in flight: if they
/// were not acknowledged for the client, the later allowed delivery could not be sent.
const REFUSED: usize = 150;

fn line_broker() -> Broker {
    Broker::start_with(
        Options {
            extra: "[auth]\npassword_file = \"passwd\"\nacl_file = \"acl\"\nreload_poll_ms = 100\n"
                .into(),
            ..Default::default()
        },
        |dir| {
            for user in ["dev1", "dev2", "monitor"] {
                add_user(&dir.join("passwd"), user, "pw");
            }
            std::fs::write(dir.join("acl"), ACL).unwrap();
        },
    )
}

/// Rewrites the ACL file and waits until the broker has loaded it `reloads` times.
fn rewrite_acl(broker: &Broker, text: &str, reloads: f64) {
    // Whole or not at all, as an editor saves (write, then rename): `fs::write` truncates
    // first, and the 100 ms poll once reloaded the empty file in between (deny all).
    let staged = broker.path("acl.new");
    std::fs::write(&staged, text).unwrap();
    std::fs::rename(&staged, broker.path("acl")).unwrap();
    let series = "fbbus_file_reloads_total{file=\"acl_file\",result=\"ok\"}";
    assert_eq!(
        broker.wait_metric(series, reloads),
        reloads,
        "ACL not reloaded"
    );
}

/// A publisher with its own namespace, waiting for each PUBACK.
struct Device(V4);

impl Device {
    async fn connect(broker: &Broker, id: &str) -> Device {
        Device(
            V4::connect(broker.port(), id, Some((id, "pw")))
                .await
                .unwrap(),
        )
    }

    async fn publish(&mut self, topic: &str, payload: &str, retain: bool) {
        self.0
            .client
            .publish(topic, rumqttc::QoS::AtLeastOnce, retain, payload)
            .await
            .unwrap();
        let ack = self
            .0
            .next(WAIT, |p| {
                matches!(p, rumqttc::Packet::PubAck(_)).then_some(())
            })
            .await;
        assert!(ack.is_some(), "no PUBACK for {topic}");
    }
}

/// mosquitto_sub as a child process, its `-v` lines (`topic payload`) read on a thread.
struct MosquittoSub {
    child: Child,
    lines: mpsc::Receiver<String>,
}

impl MosquittoSub {
    fn start(port: u16, id: &str, extra: &[&str]) -> MosquittoSub {
        let mut child = Command::new("mosquitto_sub")
            .args(["-h", "127.0.0.1", "-p", &port.to_string(), "-i", id])
            .args(["-u", "monitor", "-P", "pw", "-q", "1", "-v", "-W", "60"])
            .args(extra)
            .stdout(Stdio::piped())
            .stderr(Stdio::null())
            .spawn()
            .expect("mosquitto_sub");
        let stdout = child.stdout.take().unwrap();
        let (tx, lines) = mpsc::channel();
        std::thread::spawn(move || {
            for line in BufReader::new(stdout).lines().map_while(Result::ok) {
                if tx.send(line).is_err() {
                    return;
                }
            }
        });
        MosquittoSub { child, lines }
    }

    /// The next line within `within`.
    fn next(&self, within: Duration) -> Option<String> {
        tokio::task::block_in_place(|| self.lines.recv_timeout(within).ok())
    }

    /// Whether mosquitto_sub exited by itself (a lost connection, say).
    fn exited(&mut self) -> bool {
        self.child.try_wait().ok().flatten().is_some()
    }
}

impl Drop for MosquittoSub {
    fn drop(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

/// The subscribers of one test, whatever their client: the next delivery of each.
enum Reader {
    V4(V4),
    V5(V5),
    Mosquitto(MosquittoSub),
}

impl Reader {
    async fn next(&mut self, within: Duration) -> Option<String> {
        match self {
            Reader::V4(c) => c
                .next_publish(within)
                .await
                .map(|p| format!("{} {}", p.topic, String::from_utf8_lossy(&p.payload))),
            Reader::V5(c) => c.next_publish(within).await.map(|p| {
                format!(
                    "{} {}",
                    String::from_utf8_lossy(&p.topic),
                    String::from_utf8_lossy(&p.payload)
                )
            }),
            Reader::Mosquitto(m) => m.next(within),
        }
    }

    fn alive(&mut self) -> bool {
        match self {
            Reader::V4(c) => c.alive(),
            Reader::V5(c) => c.alive(),
            Reader::Mosquitto(m) => !m.exited(),
        }
    }
}

/// Every reader's next delivery is `expected`.
async fn all_get(readers: &mut [(&str, Reader)], expected: &str, broker: &Broker) {
    for (name, reader) in readers.iter_mut() {
        let got = reader.next(WAIT).await;
        assert_eq!(
            got.as_deref(),
            Some(expected),
            "{name}\n--- broker log\n{}",
            broker.log_text()
        );
    }
}

fn deliver_denials(broker: &Broker) -> f64 {
    broker.metric("fbbus_acl_denied_total{action=\"deliver\"}")
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_reload_that_revokes_a_read_stops_deliveries_to_existing_subscriptions() {
    let broker = line_broker();
    let port = broker.port();
    let mut dev1 = Device::connect(&broker, "dev1").await;
    let mut dev2 = Device::connect(&broker, "dev2").await;
    // Retained, so every subscriber (mosquitto_sub included) shows it is subscribed.
    dev1.publish("plant/dev1/ready", "ready", true).await;

    let mut readers: Vec<(&str, Reader)> = Vec::new();
    let mut v4 = V4::connect(port, "mon-v4", Some(("monitor", "pw")))
        .await
        .unwrap();
    assert_eq!(v4.subscribe("plant/#").await.len(), 1);
    readers.push(("rumqttc 3.1.1", Reader::V4(v4)));
    let mut v5 = V5::connect(port, "mon-v5", Some(("monitor", "pw")))
        .await
        .unwrap();
    assert_eq!(v5.subscribe("plant/#").await.len(), 1);
    readers.push(("rumqttc 5", Reader::V5(v5)));
    if require("mosquitto_sub") {
        for (name, id, version) in [
            ("mosquitto_sub 3.1.1", "mon-mosq-v4", "mqttv311"),
            ("mosquitto_sub 5", "mon-mosq-v5", "5"),
        ] {
            let sub = MosquittoSub::start(port, id, &["-V", version, "-t", "plant/#"]);
            readers.push((name, Reader::Mosquitto(sub)));
        }
    }
    all_get(&mut readers, "plant/dev1/ready ready", &broker).await;
    dev2.publish("plant/dev2/x", "before", false).await;
    all_get(&mut readers, "plant/dev2/x before", &broker).await;
    assert_eq!(deliver_denials(&broker), 0.0);

    // Revoked: the existing subscriptions deliver nothing of dev2's any more, and the
    // refused QoS 1 deliveries do not block what is still allowed.
    rewrite_acl(&broker, &revoked(), 1.0);
    for _ in 0..REFUSED {
        dev2.publish("plant/dev2/x", "after the reload", false)
            .await;
    }
    dev1.publish("plant/dev1/x", "still allowed", false).await;
    all_get(&mut readers, "plant/dev1/x still allowed", &broker).await;
    let refused = (REFUSED * readers.len()) as f64;
    assert_eq!(
        broker.wait_metric("fbbus_acl_denied_total{action=\"deliver\"}", refused),
        refused
    );
    let logged = broker
        .log_text()
        .lines()
        .filter(|l| l.contains("denied by ACL") && l.contains("deliver"))
        .filter(|l| l.contains("plant/dev2/x"))
        .count();
    assert_eq!(logged, readers.len(), "one log line per session and topic");

    // Granted again: delivered again, with no reconnect in between.
    rewrite_acl(&broker, ACL, 2.0);
    dev2.publish("plant/dev2/x", "granted again", false).await;
    all_get(&mut readers, "plant/dev2/x granted again", &broker).await;
    for (name, reader) in readers.iter_mut() {
        assert!(reader.alive(), "{name} stayed connected");
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_resumed_sessions_subscriptions_obey_the_rules_in_force() {
    let broker = line_broker();
    let port = broker.port();
    let mut dev1 = Device::connect(&broker, "dev1").await;
    let mut dev2 = Device::connect(&broker, "dev2").await;
    dev1.publish("plant/dev1/ready", "ready", true).await;

    // Sessions that outlive their connections, subscribed under the old rules.
    let mut options = V4::options(port, "mon-persistent", Some(("monitor", "pw")));
    options.set_clean_session(false);
    let mut v4 = V4::connect_with(options.clone()).await.unwrap();
    v4.subscribe("plant/#").await;
    assert!(
        v4.next_publish(WAIT).await.is_some(),
        "the retained message"
    );
    drop(v4);
    let mosquitto = require("mosquitto_sub");
    let persistent = ["-V", "5", "-c", "-x", "300"];
    if mosquitto {
        let args = [&persistent[..], &["-t", "plant/#", "-C", "1"]].concat();
        let mut first = MosquittoSub::start(port, "mon-persistent-v5", &args);
        assert_eq!(first.next(WAIT).as_deref(), Some("plant/dev1/ready ready"));
        let deadline = Instant::now() + WAIT;
        while !first.exited() && Instant::now() < deadline {
            std::thread::sleep(Duration::from_millis(20));
        }
        assert!(first.exited(), "mosquitto_sub -C 1 exits after one message");
    }
    // Let the broker see both connections end before anything is published for them.
    tokio::time::sleep(Duration::from_millis(300)).await;

    // Revoked while they are away; published while they are away: queued for them.
    rewrite_acl(&broker, &revoked(), 1.0);
    dev2.publish("plant/dev2/x", "queued, no longer readable", false)
        .await;
    dev1.publish("plant/dev1/x", "queued", false).await;

    // Resumed without subscribing again (rumqttc) or to an unrelated filter only
    // (mosquitto_sub needs one): the router's old `plant/#` delivers what is readable.
    let mut readers: Vec<(&str, Reader)> = Vec::new();
    let v4 = V4::connect_with(options).await.unwrap();
    readers.push(("rumqttc 3.1.1, resumed", Reader::V4(v4)));
    if mosquitto {
        let args = [&persistent[..], &["-t", "other/nothing"]].concat();
        let sub = MosquittoSub::start(port, "mon-persistent-v5", &args);
        readers.push(("mosquitto_sub 5, resumed", Reader::Mosquitto(sub)));
    }
    all_get(&mut readers, "plant/dev1/x queued", &broker).await;
    dev2.publish("plant/dev2/x", "live, no longer readable", false)
        .await;
    dev1.publish("plant/dev1/x", "live", false).await;
    all_get(&mut readers, "plant/dev1/x live", &broker).await;
    let refused = (2 * readers.len()) as f64;
    assert_eq!(
        broker.wait_metric("fbbus_acl_denied_total{action=\"deliver\"}", refused),
        refused,
        "{}",
        broker.log_text()
    );
}

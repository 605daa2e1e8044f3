//! The last-will contract: when a will fires (abrupt end, keep-alive expiry, takeover,
//! MQTT 5 DISCONNECT 0x04, after the MQTT 5 will delay) and when it must not (clean
//! DISCONNECT, reconnect within the will delay, a will topic outside the ACL).

mod common;

use std::io::{ErrorKind, Read};
use std::net::Shutdown;
use std::process::{Command, Stdio};
use std::time::{Duration, Instant};

use common::clients::{self, V4};
use common::raw::{self, RawClient};
use common::{Broker, Options};

/// A 3.1.1 subscriber on `will/#`.
async fn will_subscriber(broker: &Broker, id: &str) -> V4 {
    let mut sub = V4::connect(broker.port(), id, None)
        .await
        .unwrap_or_else(|e| panic!("subscriber {id} connects: {e}; log: {}", broker.log_text()));
    let codes = sub.subscribe("will/#").await;
    assert!(
        matches!(codes.as_slice(), [rumqttc::SubscribeReasonCode::Success(_)]),
        "SUBACK {codes:?}"
    );
    sub
}

/// The payload of the next publication on `topic` within `within` (others are skipped).
async fn next_on(sub: &mut V4, topic: &str, within: Duration) -> Option<Vec<u8>> {
    sub.next(within, |p| match p {
        rumqttc::Packet::Publish(p) if p.topic == topic => Some(p.payload.to_vec()),
        _ => None,
    })
    .await
}

/// Like `next_on`, until an absolute deadline (None if it has passed).
async fn next_on_before(sub: &mut V4, topic: &str, deadline: Instant) -> Option<Vec<u8>> {
    let left = deadline.saturating_duration_since(Instant::now());
    if left.is_zero() {
        return None;
    }
    next_on(sub, topic, left).await
}

/// Whether the broker closes the raw connection within `within`, skipping any packets it
/// sends first (a reset counts as closed; a read timeout as still open).
fn closed_within(raw: &mut RawClient, within: Duration) -> bool {
    let deadline = Instant::now() + within;
    let mut buf = [0u8; 512];
    let closed = loop {
        let left = deadline.saturating_duration_since(Instant::now());
        if left.is_zero() {
            break false;
        }
        raw.stream.set_read_timeout(Some(left)).unwrap();
        match raw.stream.read(&mut buf) {
            Ok(0) => break true,
            Ok(_) => continue,
            Err(e) if matches!(e.kind(), ErrorKind::WouldBlock | ErrorKind::TimedOut) => {
                break false
            }
            Err(e) if e.kind() == ErrorKind::Interrupted => continue,
            Err(_) => break true,
        }
    };
    raw.stream
        .set_read_timeout(Some(Duration::from_secs(10)))
        .unwrap();
    closed
}

/// Whether the raw connection is still open and silent after `wait`.
fn open_and_silent_for(raw: &mut RawClient, wait: Duration) -> Result<(), String> {
    raw.stream.set_read_timeout(Some(wait)).unwrap();
    let mut b = [0u8; 1];
    let result = match raw.stream.peek(&mut b) {
        Ok(0) => Err("closed by the broker".to_owned()),
        Ok(_) => Err(format!("broker sent a packet (first byte {:#04x})", b[0])),
        Err(e) if matches!(e.kind(), ErrorKind::WouldBlock | ErrorKind::TimedOut) => Ok(()),
        Err(e) => Err(format!("socket error: {e}")),
    };
    raw.stream
        .set_read_timeout(Some(Duration::from_secs(10)))
        .unwrap();
    result
}

/// A QoS 0 PUBLISH for a raw client of `version` (MQTT 5 adds an empty property length).
fn publish_qos0(version: u8, topic: &str, payload: &[u8]) -> Vec<u8> {
    if version != 5 {
        return raw::publish_qos0(topic, payload);
    }
    let mut body = Vec::new();
    body.extend_from_slice(&(topic.len() as u16).to_be_bytes());
    body.extend_from_slice(topic.as_bytes());
    body.push(0);
    body.extend_from_slice(payload);
    raw::packet(0x30, &body)
}

fn disconnects(broker: &Broker, reason: &str) -> f64 {
    broker.metric(&format!("fbbus_disconnects_total{{reason=\"{reason}\"}}"))
}

fn wait_disconnects(broker: &Broker, reason: &str, min: f64) -> f64 {
    broker.wait_metric(
        &format!("fbbus_disconnects_total{{reason=\"{reason}\"}}"),
        min,
    )
}

/// A mosquitto_sub process, killed (SIGKILL) and reaped when dropped.
struct ChildGuard(std::process::Child);

impl Drop for ChildGuard {
    fn drop(&mut self) {
        let _ = self.0.kill();
        let _ = self.0.wait();
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn will_fires_when_client_process_is_killed() {
    if !common::require("mosquitto_sub") {
        return;
    }
    let broker = Broker::start();
    let mut sub = will_subscriber(&broker, "watcher").await;
    assert_eq!(broker.wait_metric("fbbus_connections", 1.0), 1.0);

    let port = broker.port().to_string();
    let mut victim = ChildGuard(
        Command::new("mosquitto_sub")
            .args(["-h", "127.0.0.1", "-p", &port, "-i", "victim", "-k", "60"])
            .args(["--will-topic", "will/victim", "--will-payload", "dead"])
            .args(["-t", "unused"])
            .stdout(Stdio::null())
            .stderr(Stdio::null())
            .spawn()
            .expect("spawn mosquitto_sub"),
    );
    assert!(
        broker.wait_metric("fbbus_connections", 2.0) >= 2.0,
        "mosquitto_sub did not connect; log: {}",
        broker.log_text()
    );
    // Negative: while the victim lives, its will is not published.
    assert_eq!(
        next_on(&mut sub, "will/victim", Duration::from_millis(500)).await,
        None
    );
    assert_eq!(broker.metric("fbbus_wills_published_total"), 0.0);

    victim.0.kill().expect("SIGKILL mosquitto_sub");
    victim.0.wait().unwrap();

    let will = next_on(&mut sub, "will/victim", Duration::from_secs(5)).await;
    assert_eq!(
        will.as_deref(),
        Some(&b"dead"[..]),
        "no will after SIGKILL; log: {}",
        broker.log_text()
    );
    assert!(broker.wait_metric("fbbus_wills_published_total", 1.0) >= 1.0);
    assert!(wait_disconnects(&broker, "abrupt", 1.0) >= 1.0);
    assert_eq!(disconnects(&broker, "client"), 0.0);
    // Exactly one will.
    assert_eq!(
        next_on(&mut sub, "will/victim", Duration::from_millis(500)).await,
        None
    );
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn will_fires_on_keep_alive_expiry() {
    let broker = Broker::start();
    let mut sub = will_subscriber(&broker, "watcher").await;

    for (n, version) in [(1.0, 4u8), (2.0, 5u8)] {
        let topic = format!("will/ka{version}");
        let client_id = format!("silent{version}");
        let mut client = RawClient::connect(broker.port());
        let t0 = Instant::now();
        let code = client.handshake(&raw::Connect {
            version,
            client_id: &client_id,
            keep_alive: 1,
            will: Some((&topic, b"expired")),
            ..Default::default()
        });
        assert_eq!(code, 0, "v{version} CONNECT refused");
        // Silence, socket open. Nothing before ~1 s (the limit is 1.5 x keep-alive).
        assert_eq!(
            next_on_before(&mut sub, &topic, t0 + Duration::from_millis(1000)).await,
            None,
            "v{version}: will before the keep-alive limit"
        );
        let will = next_on_before(&mut sub, &topic, t0 + Duration::from_secs(4)).await;
        let elapsed = t0.elapsed();
        assert_eq!(
            will.as_deref(),
            Some(&b"expired"[..]),
            "v{version}: no will within 4 s of a silent keep-alive-1 client; log: {}",
            broker.log_text()
        );
        assert!(
            elapsed >= Duration::from_millis(1000),
            "v{version}: will after {elapsed:?}"
        );
        assert!(
            wait_disconnects(&broker, "keep_alive", n) >= n,
            "v{version}: keep_alive disconnect not counted"
        );
        if version == 5 {
            let (byte1, body) = client
                .read_packet()
                .expect("v5: a DISCONNECT before the socket closes");
            assert_eq!(byte1, 0xE0, "v5: expected DISCONNECT, got {byte1:#04x}");
            assert_eq!(body.first(), Some(&0x8D), "v5: DISCONNECT reason {body:?}");
        }
        assert!(
            closed_within(&mut client, Duration::from_secs(2)),
            "v{version}: socket still open after keep-alive expiry"
        );
    }
    assert!(broker.metric("fbbus_wills_published_total") >= 2.0);
    assert_eq!(disconnects(&broker, "abrupt"), 0.0);
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn no_will_after_clean_disconnect() {
    let broker = Broker::start();
    let mut sub = will_subscriber(&broker, "watcher").await;

    for (n, version) in [(1.0, 4u8), (2.0, 5u8)] {
        let topic = format!("will/clean{version}");
        let client_id = format!("polite{version}");
        let mut client = RawClient::connect(broker.port());
        let code = client.handshake(&raw::Connect {
            version,
            client_id: &client_id,
            will: Some((&topic, b"should-not-fire")),
            ..Default::default()
        });
        assert_eq!(code, 0, "v{version} CONNECT refused");
        client.send(&raw::DISCONNECT);
        assert!(
            closed_within(&mut client, Duration::from_secs(2)),
            "v{version}: broker kept the connection after DISCONNECT"
        );
        assert_eq!(
            next_on(&mut sub, &topic, Duration::from_secs(2)).await,
            None,
            "v{version}: will published after a clean DISCONNECT; log: {}",
            broker.log_text()
        );
        assert!(wait_disconnects(&broker, "client", n) >= n);
    }
    assert_eq!(broker.metric("fbbus_wills_published_total"), 0.0);

    // The subscriber was listening all along: a publication on will/# does reach it.
    let mut control = RawClient::connect(broker.port());
    assert_eq!(
        control.handshake(&raw::Connect {
            client_id: "control",
            ..Default::default()
        }),
        0
    );
    control.send(&raw::publish_qos0("will/control", b"heard"));
    assert_eq!(
        next_on(&mut sub, "will/control", clients::WAIT)
            .await
            .as_deref(),
        Some(&b"heard"[..])
    );
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn v5_disconnect_with_will_message_fires_will() {
    let broker = Broker::start();
    let mut sub = will_subscriber(&broker, "watcher").await;

    let mut client = RawClient::connect(broker.port());
    let code = client.handshake(&raw::Connect {
        version: 5,
        client_id: "asks-for-will",
        will: Some(("will/asked", b"bye-with-will")),
        ..Default::default()
    });
    assert_eq!(code, 0);
    assert_eq!(
        next_on(&mut sub, "will/asked", Duration::from_millis(300)).await,
        None
    );
    client.send(&[0xE0, 0x01, 0x04]);
    let will = next_on(&mut sub, "will/asked", clients::WAIT).await;
    assert_eq!(
        will.as_deref(),
        Some(&b"bye-with-will"[..]),
        "no will after DISCONNECT 0x04; log: {}",
        broker.log_text()
    );
    assert!(closed_within(&mut client, Duration::from_secs(2)));
    assert!(
        wait_disconnects(&broker, "client_with_will", 1.0) >= 1.0,
        "DISCONNECT 0x04 not counted as client_with_will; metrics: {}; log: {}",
        broker.metrics(),
        broker.log_text()
    );
    assert_eq!(disconnects(&broker, "client"), 0.0);
    assert!(broker.wait_metric("fbbus_wills_published_total", 1.0) >= 1.0);
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn will_fires_on_session_takeover() {
    let broker = Broker::start();
    let mut sub = will_subscriber(&broker, "watcher").await;

    for (n, version) in [(1.0, 4u8), (2.0, 5u8)] {
        let topic = format!("will/dup{version}");
        let client_id = format!("dup{version}");
        let mut a = RawClient::connect(broker.port());
        assert_eq!(
            a.handshake(&raw::Connect {
                version,
                client_id: &client_id,
                will: Some((&topic, b"taken-over")),
                ..Default::default()
            }),
            0,
            "v{version}: A refused"
        );
        // Negative: A's will does not fire while A is connected.
        assert_eq!(
            next_on(&mut sub, &topic, Duration::from_millis(300)).await,
            None
        );

        let mut b = RawClient::connect(broker.port());
        assert_eq!(
            b.handshake(&raw::Connect {
                version,
                client_id: &client_id,
                ..Default::default()
            }),
            0,
            "v{version}: B refused"
        );
        let will = next_on(&mut sub, &topic, clients::WAIT).await;
        assert_eq!(
            will.as_deref(),
            Some(&b"taken-over"[..]),
            "v{version}: no will on takeover; log: {}",
            broker.log_text()
        );
        if version == 5 {
            let (byte1, body) = a
                .read_packet()
                .expect("v5: A gets a DISCONNECT before its socket closes");
            assert_eq!(byte1, 0xE0, "v5: expected DISCONNECT, got {byte1:#04x}");
            assert_eq!(body.first(), Some(&0x8E), "v5: DISCONNECT reason {body:?}");
        }
        assert!(
            closed_within(&mut a, Duration::from_secs(3)),
            "v{version}: A still connected after takeover"
        );
        assert!(
            wait_disconnects(&broker, "takeover", n) >= n,
            "v{version}: takeover not counted; log: {}",
            broker.log_text()
        );

        // B stays connected and works.
        open_and_silent_for(&mut b, Duration::from_millis(500))
            .unwrap_or_else(|e| panic!("v{version}: B after takeover: {e}"));
        let check = format!("will/b-alive{version}");
        b.send(&publish_qos0(version, &check, b"b-works"));
        assert_eq!(
            next_on(&mut sub, &check, clients::WAIT).await.as_deref(),
            Some(&b"b-works"[..]),
            "v{version}: B's publication not delivered; log: {}",
            broker.log_text()
        );
        // One will, not two.
        assert_eq!(
            next_on(&mut sub, &topic, Duration::from_millis(300)).await,
            None
        );
        b.send(&raw::DISCONNECT);
        assert!(closed_within(&mut b, Duration::from_secs(2)));
    }
    assert_eq!(disconnects(&broker, "abrupt"), 0.0);
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn keep_alive_zero_is_accepted() {
    let broker = Broker::start();
    let mut sub = V4::connect(broker.port(), "watcher", None).await.unwrap();
    sub.subscribe("ka0/#").await;

    let mut idle = Vec::new();
    for version in [4u8, 5u8] {
        let mut client = RawClient::connect(broker.port());
        let code = client.handshake(&raw::Connect {
            version,
            client_id: if version == 4 { "idle4" } else { "idle5" },
            keep_alive: 0,
            ..Default::default()
        });
        assert_eq!(
            code,
            0,
            "v{version}: keep-alive 0 refused; log: {}",
            broker.log_text()
        );
        idle.push((version, client));
    }
    // Both idle for 3 s: no keep-alive timeout.
    std::thread::sleep(Duration::from_secs(3));
    for (version, client) in &mut idle {
        open_and_silent_for(client, Duration::from_millis(100)).unwrap_or_else(|e| {
            panic!(
                "v{version}: keep-alive-0 connection after 3 s idle: {e}; log: {}",
                broker.log_text()
            )
        });
    }
    assert_eq!(disconnects(&broker, "keep_alive"), 0.0);
    // Counted once the CONNACK is written: the client may read it first.
    assert_eq!(broker.wait_metric("fbbus_connections", 3.0), 3.0);

    for (version, client) in &mut idle {
        let topic = format!("ka0/v{version}");
        client.send(&publish_qos0(*version, &topic, b"still-here"));
        assert_eq!(
            next_on(&mut sub, &topic, clients::WAIT).await.as_deref(),
            Some(&b"still-here"[..]),
            "v{version}: publication after idling not delivered"
        );
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn v5_will_delay_is_honoured() {
    let broker = Broker::start();
    let mut sub = will_subscriber(&broker, "watcher").await;
    let delayed = |client_id| raw::Connect {
        version: 5,
        client_id,
        clean: false,
        session_expiry: Some(30),
        will: Some(("will/d", b"late")),
        will_delay: Some(2),
        ..Default::default()
    };

    // 1. Abrupt end, no return: the will comes after its 2 s delay.
    let mut client = RawClient::connect(broker.port());
    assert_eq!(client.handshake(&delayed("delayed1")), 0);
    client.stream.shutdown(Shutdown::Both).unwrap();
    drop(client);
    let dropped = Instant::now();
    assert_eq!(
        next_on_before(&mut sub, "will/d", dropped + Duration::from_secs(1)).await,
        None,
        "will published before its delay; log: {}",
        broker.log_text()
    );
    let will = next_on_before(&mut sub, "will/d", dropped + Duration::from_secs(4)).await;
    assert_eq!(
        will.as_deref(),
        Some(&b"late"[..]),
        "no will 4 s after the drop (delay 2 s); log: {}",
        broker.log_text()
    );
    assert!(wait_disconnects(&broker, "abrupt", 1.0) >= 1.0);
    assert!(broker.wait_metric("fbbus_wills_published_total", 1.0) >= 1.0);

    // 2. Abrupt end, back within 1 s with the same client id: the will never comes.
    let mut client = RawClient::connect(broker.port());
    assert_eq!(client.handshake(&delayed("delayed2")), 0);
    client.stream.shutdown(Shutdown::Both).unwrap();
    drop(client);
    assert!(wait_disconnects(&broker, "abrupt", 2.0) >= 2.0);
    std::thread::sleep(Duration::from_millis(300));
    let mut back = RawClient::connect(broker.port());
    assert_eq!(
        back.handshake(&raw::Connect {
            version: 5,
            client_id: "delayed2",
            clean: false,
            session_expiry: Some(30),
            ..Default::default()
        }),
        0
    );
    assert_eq!(
        next_on(&mut sub, "will/d", Duration::from_secs(4)).await,
        None,
        "will published although the client came back within the delay; log: {}",
        broker.log_text()
    );
    assert_eq!(broker.metric("fbbus_wills_published_total"), 1.0);
    open_and_silent_for(&mut back, Duration::from_millis(100))
        .unwrap_or_else(|e| panic!("reconnected client: {e}"));
}

#[test]
fn will_topic_outside_acl_refuses_connect() {
    let broker = Broker::start_with(
        Options {
            extra: "[auth]\npassword_file = \"passwd\"\nacl_file = \"acl\"\n".into(),
            ..Default::default()
        },
        |dir| {
            common::add_user(&dir.join("passwd"), "dev1", "pw");
            std::fs::write(dir.join("acl"), "user dev1\ntopic write plant/dev1/#\n").unwrap();
        },
    );
    let denied = "fbbus_acl_denied_total{action=\"will\"}";

    // 3.1.1: not authorized (5).
    let mut client = RawClient::connect(broker.port());
    let code = client.handshake(&raw::Connect {
        client_id: "dev1-a",
        login: Some(("dev1", "pw")),
        will: Some(("plant/dev2/x", b"forged")),
        ..Default::default()
    });
    assert_eq!(code, 5, "will outside the ACL; log: {}", broker.log_text());
    assert!(closed_within(&mut client, Duration::from_secs(2)));
    assert!(broker.wait_metric(denied, 1.0) >= 1.0);

    // MQTT 5: not authorized (0x87).
    let mut client = RawClient::connect(broker.port());
    let code = client.handshake(&raw::Connect {
        version: 5,
        client_id: "dev1-b",
        login: Some(("dev1", "pw")),
        will: Some(("plant/dev2/x", b"forged")),
        ..Default::default()
    });
    assert_eq!(
        code,
        0x87,
        "v5 will outside the ACL; log: {}",
        broker.log_text()
    );
    assert!(broker.wait_metric(denied, 2.0) >= 2.0);
    assert_eq!(broker.metric("fbbus_connections"), 0.0);

    // Inside the ACL: accepted, and not counted as a denial.
    for version in [4u8, 5u8] {
        let mut client = RawClient::connect(broker.port());
        let code = client.handshake(&raw::Connect {
            version,
            client_id: if version == 4 { "dev1-c" } else { "dev1-d" },
            login: Some(("dev1", "pw")),
            will: Some(("plant/dev1/status", b"offline")),
            ..Default::default()
        });
        assert_eq!(
            code,
            0,
            "v{version}: allowed will topic refused; log: {}",
            broker.log_text()
        );
        open_and_silent_for(&mut client, Duration::from_millis(200))
            .unwrap_or_else(|e| panic!("v{version}: accepted client: {e}"));
    }
    assert_eq!(broker.metric(denied), 2.0);
}

/// A will reaches MQTT 5 subscribers with exactly the User Properties the client set, in
/// order, duplicates kept, and nothing added [MQTT-3.3.2-17] [MQTT-3.3.2-18]: the broker
/// keeps the session number beside the will, not in it.
#[test]
fn will_user_properties_arrive_unaltered() {
    let broker = Broker::start();
    let mut sub = RawClient::connect(broker.port());
    assert_eq!(
        sub.handshake(&raw::Connect {
            version: 5,
            client_id: "props-watcher",
            ..Default::default()
        }),
        0
    );
    sub.send(&raw::subscribe(5, 1, &["will/props"]));
    assert_eq!(sub.read_packet().expect("SUBACK").0, 0x90);

    let user = [("a", "1"), ("a", "2"), ("b", "x")];
    let mut client = RawClient::connect(broker.port());
    assert_eq!(
        client.handshake(&raw::Connect {
            version: 5,
            client_id: "props-will",
            will: Some(("will/props", b"gone")),
            will_user_properties: &user,
            ..Default::default()
        }),
        0
    );
    client.stream.shutdown(Shutdown::Both).unwrap();
    drop(client);

    let (byte1, body) = sub.read_packet().expect("the will");
    assert_eq!(byte1 & 0xF0, 0x30, "a PUBLISH");
    let (topic, _, props, payload) = raw::parse_publish_v5(byte1, &body);
    assert_eq!(
        (&topic[..], &payload[..]),
        (&b"will/props"[..], &b"gone"[..])
    );
    assert_eq!(
        props,
        raw::user_properties(&user),
        "the will's properties, byte for byte"
    );
}

//! Issue 20, "a device is who its password says": a session belongs to the identity that
//! created it. Another user's CONNECT with that client id is refused (MQTT 5 0x85, 3.1.1
//! 0x02) and changes nothing: no takeover, no will, no registry change, no cancelled will
//! delay; the owner still takes its own session over. `[auth] client_id` binds client ids
//! to usernames.
//!
//! The line of the issue: a password file (devA, devB, mes, monitor) and
//! `deploy/acl.example`'s ACL (`pattern read line1/%u/cmd/#`, `user mes` writes
//! `line1/+/cmd/#`). Clients: rumqttc (3.1.1 and 5), hand-built packets, Debian's
//! `mosquitto_sub`/`mosquitto_pub` and Python paho-mqtt (`tests/python/identity_check.py`).

mod common;

use std::net::Shutdown;
use std::process::Command;
use std::time::{Duration, Instant};

use common::clients::{V4, V5, WAIT};
use common::fb::record;
use common::raw::{self, RawClient};
use common::{add_user, Broker, Options};
use rumqttc::QoS;

const ACL: &str = include_str!("../../deploy/acl.example");
const USERS: [(&str, &str); 4] = [
    ("devA", "pwA"),
    ("devB", "pwB"),
    ("mes", "pwM"),
    ("monitor", "pwMon"),
];
const COMMAND: &str = "line1/devB/cmd/stop";
const WILL: &str = "line1/devB/status";
const OWNED: &str = "fbbus_connects_refused_total{reason=\"client_id_owned\"}";
const BINDING: &str = "fbbus_connects_refused_total{reason=\"client_id_binding\"}";
const SCRIPT: &str = concat!(
    env!("CARGO_MANIFEST_DIR"),
    "/tests/python/identity_check.py"
);

/// The line; `auth` is appended to its `[auth]` section.
fn line(auth: &str) -> Broker {
    line_with("", auth)
}

/// [`line`] with `[broker]` keys.
fn line_with(broker: &str, auth: &str) -> Broker {
    Broker::start_with(
        Options {
            extra: format!(
                "{broker}[auth]\npassword_file = \"passwd\"\nacl_file = \"acl\"\n{auth}"
            ),
            ..Default::default()
        },
        |dir| {
            for (user, password) in USERS {
                add_user(&dir.join("passwd"), user, password);
            }
            std::fs::write(dir.join("acl"), ACL).unwrap();
        },
    )
}

fn login(user: &str) -> Option<(&str, &str)> {
    USERS
        .iter()
        .find(|(u, _)| *u == user)
        .map(|(u, p)| (*u, *p))
}

/// devB as the issue has it: MQTT 3.1.1, clean session false, a will, subscribed to its
/// commands.
async fn dev_b(port: u16) -> V4 {
    let mut o = V4::options(port, "devB", login("devB"));
    o.set_clean_session(false);
    o.set_last_will(rumqttc::LastWill::new(
        WILL,
        "devB lost",
        QoS::AtLeastOnce,
        false,
    ));
    let mut dev = V4::connect_with(o).await.expect("devB connects");
    assert_eq!(
        dev.subscribe("line1/devB/cmd/#").await,
        [rumqttc::SubscribeReasonCode::Success(QoS::AtLeastOnce)]
    );
    dev
}

/// devB declares its interface, so the registry has a record of it.
async fn declare(broker: &Broker, dev: &mut V4) {
    dev.client
        .publish(
            "fbbus/declare/devB",
            QoS::AtLeastOnce,
            false,
            common::fb::CONV,
        )
        .await
        .unwrap();
    dev.next(WAIT, |p| {
        matches!(p, rumqttc::Packet::PubAck(_)).then_some(())
    })
    .await
    .expect("declaration acknowledged");
    common::fb::wait_record(broker, "devB", "came online", |r| r["status"] == "online").await;
}

/// The monitor, reading everything: devB's will would come here.
async fn monitor(port: u16) -> V4 {
    let mut m = V4::connect(port, "monitor", login("monitor"))
        .await
        .unwrap();
    assert_eq!(
        m.subscribe("line1/#").await,
        [rumqttc::SubscribeReasonCode::Success(QoS::AtLeastOnce)]
    );
    m
}

async fn mes_sends_command(port: u16) {
    let mes = V4::connect(port, "mes", login("mes")).await.unwrap();
    mes.client
        .publish(COMMAND, QoS::AtLeastOnce, false, "stop")
        .await
        .unwrap();
    // Published once acknowledged; keep the connection until then.
    let mut mes = mes;
    mes.next(WAIT, |p| {
        matches!(p, rumqttc::Packet::PubAck(_)).then_some(())
    })
    .await
    .expect("the MES's command is acknowledged");
}

/// devA (its own password) asks for devB's session, in MQTT 3.1.1 and 5, clean and
/// persistent, through rumqttc: every CONNECT refused with the version's code.
async fn thefts_refused(port: u16) -> usize {
    let mut attempts = 0;
    for clean in [false, true] {
        let mut o = V4::options(port, "devB", login("devA"));
        o.set_clean_session(clean);
        assert_eq!(
            V4::connect_with(o).await.err().as_deref(),
            Some("BadClientId")
        );
        let mut o = V5::options(port, "devB", login("devA"));
        o.set_clean_start(clean);
        let mut props = rumqttc::v5::mqttbytes::v5::ConnectProperties::new();
        props.session_expiry_interval = Some(300);
        o.set_connect_properties(props);
        assert_eq!(
            V5::connect_with(o).await.err().as_deref(),
            Some("ClientIdentifierNotValid")
        );
        attempts += 2;
    }
    attempts
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn another_user_cannot_take_a_live_session() {
    let broker = line("");
    let port = broker.port();
    let mut watch = monitor(port).await;
    let mut dev = dev_b(port).await;
    declare(&broker, &mut dev).await;
    let before = record(&broker, "devB");
    assert!(before.is_some());

    // devA may not read devB's commands...
    let mut dev_a = V4::connect(port, "devA", login("devA")).await.unwrap();
    assert_eq!(
        dev_a.subscribe("line1/devB/cmd/#").await,
        [rumqttc::SubscribeReasonCode::Failure]
    );
    // ...nor get them by taking devB's session.
    let attempts = thefts_refused(port).await;

    mes_sends_command(port).await;
    let got = dev
        .next_publish(WAIT)
        .await
        .expect("devB still receives its commands");
    assert_eq!(got.topic, COMMAND);
    assert!(dev.alive(), "devB was disconnected");
    assert!(
        watch
            .next_publish(Duration::from_millis(500))
            .await
            .map(|p| p.topic)
            != Some(WILL.into()),
        "devB's will was published"
    );
    assert_eq!(broker.metric("fbbus_wills_published_total"), 0.0);
    assert_eq!(
        broker.metric("fbbus_disconnects_total{reason=\"takeover\"}"),
        0.0
    );
    assert_eq!(
        record(&broker, "devB"),
        before,
        "devB's registry record changed"
    );
    assert_eq!(broker.wait_metric(OWNED, attempts as f64), attempts as f64);
    // Logged once per client id and user, not per attempt.
    let log = broker.log_text();
    assert_eq!(
        log.matches("belongs to another identity").count(),
        1,
        "log: {log}"
    );
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn another_user_cannot_resume_a_stored_session_and_its_owner_can() {
    let broker = line("");
    let port = broker.port();
    let mut dev = dev_b(port).await;
    declare(&broker, &mut dev).await;
    dev.client.disconnect().await.unwrap();
    drop(dev);
    common::fb::wait_record(&broker, "devB", "went offline", |r| {
        r["status"] == "offline"
    })
    .await;
    let before = record(&broker, "devB");

    let attempts = thefts_refused(port).await;
    // A refused CONNECT took no session number: the owner's comes next.
    mes_sends_command(port).await;
    assert_eq!(
        record(&broker, "devB"),
        before,
        "devB's registry record changed"
    );

    // devB comes back: its session was kept, with the command the MES sent meanwhile.
    let mut o = V4::options(port, "devB", login("devB"));
    o.set_clean_session(false);
    let mut dev = V4::connect_with(o).await.expect("devB resumes its session");
    let got = dev
        .next_publish(WAIT)
        .await
        .expect("the command queued while away");
    assert_eq!(got.topic, COMMAND);
    assert_eq!(broker.metric(OWNED), attempts as f64);
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn the_owner_takes_its_own_session_over() {
    let broker = line("");
    let port = broker.port();
    let mut watch = monitor(port).await;
    let stale = dev_b(port).await;
    // The device reconnects after a network cut, its old connection not yet noticed.
    let mut o = V4::options(port, "devB", login("devB"));
    o.set_clean_session(false);
    let mut dev = V4::connect_with(o).await.expect("the owner takes over");
    assert_eq!(
        broker.wait_metric("fbbus_disconnects_total{reason=\"takeover\"}", 1.0),
        1.0
    );
    // MQTT: the taken-over connection's will is published.
    let will = watch
        .next_publish(WAIT)
        .await
        .expect("the stale connection's will");
    assert_eq!(will.topic, WILL);
    drop(stale);
    // The session's subscription goes on delivering to the new connection.
    mes_sends_command(port).await;
    assert_eq!(
        dev.next_publish(WAIT).await.expect("command").topic,
        COMMAND
    );
    assert_eq!(broker.metric(OWNED), 0.0);
}

/// devB's will, if it comes before `until`.
async fn next_will(watch: &mut V4, until: Instant) -> Option<bytes::Bytes> {
    let within = until.saturating_duration_since(Instant::now());
    watch
        .next(within, |p| match p {
            rumqttc::Packet::Publish(p) if p.topic == WILL => Some(p.payload),
            _ => None,
        })
        .await
}

/// MQTT 5 will delay: another identity's CONNECT does not cancel it; the owner's does.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_will_delay_is_cancelled_only_by_its_owner() {
    let broker = line("");
    let port = broker.port();
    let mut watch = monitor(port).await;
    let delayed = |client_id, user| raw::Connect {
        version: 5,
        client_id,
        clean: false,
        session_expiry: Some(30),
        will: Some((WILL, b"late")),
        will_delay: Some(2),
        login: login(user),
        ..Default::default()
    };

    // 1. devB dies; devA connects as devB within the delay: refused, the will comes.
    let mut dev = RawClient::connect(port);
    assert_eq!(dev.handshake(&delayed("devB", "devB")), 0);
    dev.stream.shutdown(Shutdown::Both).unwrap();
    drop(dev);
    let died = Instant::now();
    broker.wait_metric("fbbus_disconnects_total{reason=\"abrupt\"}", 1.0);
    let mut thief = RawClient::connect(port);
    let thief_connect = raw::Connect {
        will: None,
        ..delayed("devB", "devA")
    };
    assert_eq!(thief.handshake(&thief_connect), 0x85);
    assert!(thief.closed_by_broker());
    let will = next_will(&mut watch, died + Duration::from_secs(5)).await;
    assert_eq!(
        will.as_deref(),
        Some(&b"late"[..]),
        "another user's CONNECT cancelled devB's will; log: {}",
        broker.log_text()
    );
    assert!(
        died.elapsed() >= Duration::from_millis(1900),
        "the delay was kept"
    );

    // 2. devB dies again and comes back itself within the delay: no will.
    let mut dev = RawClient::connect(port);
    assert_eq!(dev.handshake(&delayed("devB", "devB")), 0);
    dev.stream.shutdown(Shutdown::Both).unwrap();
    drop(dev);
    broker.wait_metric("fbbus_disconnects_total{reason=\"abrupt\"}", 2.0);
    let mut back = RawClient::connect(port);
    assert_eq!(back.handshake(&delayed("devB", "devB")), 0);
    let will = next_will(&mut watch, Instant::now() + Duration::from_secs(4)).await;
    assert_eq!(will, None, "devB's own reconnect did not cancel its will");
    assert_eq!(broker.metric("fbbus_wills_published_total"), 1.0);
    assert_eq!(broker.metric(OWNED), 1.0);
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn binding_client_ids_to_usernames() {
    let broker = line("client_id = \"%u-*\"\n");
    let port = broker.port();
    for id in ["devA", "devA-debug"] {
        V4::connect(port, id, login("devA"))
            .await
            .unwrap_or_else(|e| panic!("{id}: {e}"));
        V5::connect(port, id, login("devA"))
            .await
            .unwrap_or_else(|e| panic!("{id}: {e}"));
    }
    for id in ["devB", "devAx", "dev", "mosq-1234"] {
        assert_eq!(
            V4::connect(port, id, login("devA")).await.err().as_deref(),
            Some("BadClientId"),
            "{id}"
        );
        assert_eq!(
            V5::connect(port, id, login("devA")).await.err().as_deref(),
            Some("ClientIdentifierNotValid"),
            "{id}"
        );
    }
    assert_eq!(broker.wait_metric(BINDING, 8.0), 8.0);
    // Exported at 0 before the first refusal, for alerts.
    assert!(broker.metrics().contains(&format!("{OWNED} 0")));
}

/// `client_id = "%u"` with Debian's Mosquitto clients, MQTT 3.1.1 and 5.
#[test]
fn binding_with_mosquitto_clients() {
    if !common::require("mosquitto_pub") {
        return;
    }
    let broker = line("client_id = \"%u\"\n");
    let port = broker.port().to_string();
    let publish = |id: &str, version: &str| {
        common::run(
            Command::new("mosquitto_pub").args([
                "-h",
                "127.0.0.1",
                "-p",
                &port,
                "-u",
                "devA",
                "-P",
                "pwA",
                "-i",
                id,
                "-V",
                version,
                "-t",
                "line1/devA/x",
                "-m",
                "hello",
                "-q",
                "1",
            ]),
            WAIT,
        )
    };
    for version in ["mqttv311", "mqttv5"] {
        let (ok, _, err) = publish("devA", version);
        assert!(ok, "{version}: devA as devA refused: {err}");
        let (ok, out, err) = publish("devA-debug", version);
        assert!(!ok, "{version}: devA as devA-debug accepted");
        let text = format!("{out}{err}").to_lowercase();
        assert!(
            text.contains("identifier"),
            "{version}: not refused for its client id: {out}{err}"
        );
    }
    assert_eq!(broker.wait_metric(BINDING, 2.0), 2.0);
}

/// The stored-session theft with `mosquitto_sub` as the thief (clean session off, `-c`),
/// MQTT 3.1.1 and 5: refused, and nothing received.
#[test]
fn stored_session_theft_with_mosquitto_sub() {
    if !common::require("mosquitto_sub") {
        return;
    }
    let broker = line("");
    let port = broker.port();
    let rt = tokio::runtime::Runtime::new().unwrap();
    rt.block_on(async {
        let dev = dev_b(port).await;
        dev.client.disconnect().await.unwrap();
        tokio::time::sleep(Duration::from_millis(300)).await;
        mes_sends_command(port).await;
    });
    for (version, expiry) in [("mqttv311", None), ("mqttv5", Some("300"))] {
        let port = port.to_string();
        let mut cmd = Command::new("mosquitto_sub");
        cmd.args([
            "-h",
            "127.0.0.1",
            "-p",
            &port,
            "-u",
            "devA",
            "-P",
            "pwA",
            "-i",
            "devB",
            "-c",
            "-V",
            version,
            "-t",
            "line1/devA/#",
            "-C",
            "1",
            "-W",
            "3",
            "-v",
        ]);
        if let Some(expiry) = expiry {
            cmd.args(["-x", expiry]);
        }
        let (ok, out, err) = common::run(&mut cmd, Duration::from_secs(10));
        assert!(!ok, "{version}: devA got devB's session: {out}");
        assert!(!out.contains(COMMAND), "{version}: devA received {out}");
        assert!(
            err.to_lowercase().contains("identifier"),
            "{version}: not refused for its client id: {err}"
        );
    }
    assert_eq!(broker.wait_metric(OWNED, 2.0), 2.0);
    // devB's session still holds the command for devB.
    rt.block_on(async {
        let mut o = V4::options(port, "devB", login("devB"));
        o.set_clean_session(false);
        let mut dev = V4::connect_with(o).await.expect("devB resumes");
        assert_eq!(
            dev.next_publish(WAIT).await.expect("command").topic,
            COMMAND
        );
    });
}

fn paho(scenario: &str) {
    if !common::require_paho() {
        return;
    }
    for protocol in ["311", "5"] {
        let broker = line("");
        let (ok, out, err) = common::run(
            Command::new("python3").args([
                "-u",
                SCRIPT,
                "--port",
                &broker.port().to_string(),
                "--scenario",
                scenario,
                "--protocol",
                protocol,
            ]),
            Duration::from_secs(60),
        );
        assert!(
            ok,
            "paho {scenario} (MQTT {protocol}) failed\n--- stdout\n{out}\n--- stderr\n{err}\n--- broker log\n{}",
            broker.log_text()
        );
        eprintln!("paho {scenario} (MQTT {protocol}): {}", out.trim());
        assert_eq!(broker.wait_metric(OWNED, 1.0), 1.0);
        assert_eq!(broker.metric("fbbus_wills_published_total"), 0.0);
    }
}

#[test]
fn paho_live_session_theft_is_refused() {
    paho("theft_live");
}

#[test]
fn paho_stored_session_theft_is_refused() {
    paho("theft_stored");
}

/// The session table keeps at most max(max_connections, 4096) offline sessions, as the
/// router does; the oldest dropped beyond takes the router's copy with it. Its client id
/// is then free: whoever connects with it next gets a new, empty session, never the
/// dropped one's subscriptions or messages.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_session_dropped_at_the_limit_is_gone_for_everyone() {
    const LIMIT: usize = 4096;
    // devA holds more sessions than one identity may by default (issue 21).
    let broker = line_with("max_sessions_per_identity = 5000\n", "");
    let port = broker.port();
    let dev = dev_b(port).await;
    dev.client.disconnect().await.unwrap();
    drop(dev);
    broker.wait_metric("fbbus_disconnects_total{reason=\"client\"}", 1.0);

    // devA keeps LIMIT persistent sessions of its own: devB's, the oldest, is dropped.
    let started = Instant::now();
    tokio::task::spawn_blocking(move || {
        for i in 0..LIMIT {
            let id = format!("devA-{i}");
            let mut c = RawClient::connect(port);
            let code = c.handshake(&raw::Connect {
                client_id: &id,
                clean: false,
                login: login("devA"),
                ..Default::default()
            });
            assert_eq!(code, 0, "{id}");
            c.send(&raw::DISCONNECT);
            assert!(c.closed_by_broker());
            assert!(
                started.elapsed() < Duration::from_secs(120),
                "too slow at {i}"
            );
        }
    })
    .await
    .unwrap();
    // The router holds as many: devB's was ended with its table entry (the eviction hook),
    // or dropped by the router itself as its oldest.
    assert_eq!(
        broker.wait_metric("fbbus_router_saved_sessions", LIMIT as f64),
        LIMIT as f64
    );
    mes_sends_command(port).await;

    // devB's session is gone: the id is free again, for devB only (a client id that is a
    // user's name is that user's: issue 33), and devB finds nothing of its old session.
    let mut thief = RawClient::connect(port);
    thief.send(
        &raw::Connect {
            client_id: "devB",
            clean: false,
            login: login("devB"),
            ..Default::default()
        }
        .bytes(),
    );
    let (byte1, body) = thief.read_packet().expect("CONNACK");
    assert_eq!((byte1, body[1]), (0x20, 0), "accepted");
    assert_eq!(
        body[0] & 1,
        0,
        "session present: devB's session was resumed"
    );
    thief.send(&raw::subscribe(4, 1, &["line1/devA/#"]));
    let (byte1, _) = thief.read_packet().expect("SUBACK");
    assert_eq!(
        byte1, 0x90,
        "nothing of devB's session arrives before the SUBACK"
    );
    thief
        .stream
        .set_read_timeout(Some(Duration::from_millis(500)))
        .unwrap();
    assert!(thief.read_packet().is_none(), "devA received something");
}

//! Access control in the packet path: publish and subscribe, MQTT 3.1.1 and 5,
//! per-filter SUBACK codes, reload without disconnects, one log line per client and topic.

mod common;

use std::time::Duration;

use common::clients::{V4, V5, WAIT};
use common::raw::{self, RawClient};
use common::{add_user, Broker, Options};
use rumqttc::v5::mqttbytes::QoS as QoS5;

/// A line: devices publish under their own namespace and read all FB topics.
const ACL: &str = "\
pattern write plant/%c/#
pattern read plant/#
user monitor
topic read #
";

fn line_broker() -> Broker {
    Broker::start_with(
        Options {
            extra: "[auth]\npassword_file = \"passwd\"\nacl_file = \"acl\"\nreload_poll_ms = 200\n"
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

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn v311_subscribe_and_publish_are_authorized() {
    let broker = line_broker();
    let port = broker.port();
    let mut monitor = V4::connect(port, "monitor", Some(("monitor", "pw")))
        .await
        .unwrap();
    assert_eq!(
        monitor.subscribe("#").await,
        [rumqttc::SubscribeReasonCode::Success(
            rumqttc::QoS::AtLeastOnce
        )]
    );

    let mut dev1 = V4::connect(port, "dev1", Some(("dev1", "pw")))
        .await
        .unwrap();
    assert_eq!(
        dev1.subscribe("secret/#").await,
        [rumqttc::SubscribeReasonCode::Failure]
    );
    assert_eq!(
        dev1.subscribe("plant/#").await,
        [rumqttc::SubscribeReasonCode::Success(
            rumqttc::QoS::AtLeastOnce
        )]
    );

    // Foreign namespace: acknowledged (3.1.1 cannot refuse) but never routed.
    dev1.client
        .publish("plant/dev2/x", rumqttc::QoS::AtLeastOnce, false, "forged")
        .await
        .unwrap();
    dev1.client
        .publish("plant/dev1/x", rumqttc::QoS::AtLeastOnce, false, "own")
        .await
        .unwrap();
    let got = monitor
        .next_publish(WAIT)
        .await
        .expect("the allowed message");
    assert_eq!(
        (got.topic.as_str(), &got.payload[..]),
        ("plant/dev1/x", &b"own"[..])
    );
    assert!(monitor
        .next_publish(Duration::from_millis(500))
        .await
        .is_none());
    let puback = dev1
        .next(WAIT, |p| match p {
            rumqttc::Packet::PubAck(a) => Some(a.pkid),
            _ => None,
        })
        .await;
    assert!(
        puback.is_some(),
        "the refused QoS 1 publish is acknowledged on 3.1.1"
    );
    assert_eq!(
        broker.metric("fbbus_acl_denied_total{action=\"publish\"}"),
        1.0
    );
    assert_eq!(
        broker.metric("fbbus_acl_denied_total{action=\"subscribe\"}"),
        1.0
    );
    assert!(dev1.alive(), "a denial does not disconnect");
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn v5_refusals_carry_not_authorized_reason_codes() {
    let broker = line_broker();
    let port = broker.port();
    let mut monitor = V5::connect(port, "monitor", Some(("monitor", "pw")))
        .await
        .unwrap();
    monitor.subscribe("plant/#").await;

    // rumqttc ends its v5 connection on a refusal and reports the reason code.
    let dev1 = V5::connect(port, "dev1", Some(("dev1", "pw")))
        .await
        .unwrap();
    dev1.client
        .subscribe("secret/#", QoS5::AtMostOnce)
        .await
        .unwrap();
    let mut dev1 = dev1;
    let e = dev1.error(WAIT).await.expect("SUBACK refusal");
    assert!(e.contains("SubFail") && e.contains("NotAuthorized"), "{e}");

    let mut dev1 = V5::connect(port, "dev1", Some(("dev1", "pw")))
        .await
        .unwrap();
    dev1.client
        .publish("plant/dev2/x", QoS5::AtLeastOnce, false, "forged")
        .await
        .unwrap();
    let e = dev1.error(WAIT).await.expect("PUBACK refusal");
    assert!(
        e.contains("PubAckFail") && e.contains("NotAuthorized"),
        "{e}"
    );

    let mut dev1 = V5::connect(port, "dev1", Some(("dev1", "pw")))
        .await
        .unwrap();
    dev1.client
        .publish("plant/dev2/y", QoS5::ExactlyOnce, false, "forged")
        .await
        .unwrap();
    let e = dev1.error(WAIT).await.expect("PUBREC refusal");
    assert!(
        e.contains("PubRecFail") && e.contains("NotAuthorized"),
        "{e}"
    );
    assert!(monitor
        .next_publish(Duration::from_millis(500))
        .await
        .is_none());

    let dev1 = V5::connect(port, "dev1", Some(("dev1", "pw")))
        .await
        .unwrap();
    dev1.client
        .publish("plant/dev1/ok", QoS5::AtLeastOnce, false, "own")
        .await
        .unwrap();
    assert_eq!(
        monitor.next_publish(WAIT).await.expect("own topic").payload,
        "own"
    );
    assert_eq!(
        broker.metric("fbbus_acl_denied_total{action=\"publish\"}"),
        2.0
    );
}

#[test]
fn one_subscribe_with_allowed_and_denied_filters_gets_a_code_per_filter() {
    let broker = line_broker();
    let filters = [
        "plant/dev2/#",
        "secret/a",
        "plant/+/x",
        "$SYS/#",
        "bad/#/filter",
    ];
    for (version, expected) in [
        // `$SYS/#`: granted, by the `$SYS` rule for loopback clients (issue 35).
        (4u8, vec![0x00, 0x80, 0x00, 0x00, 0x80]),
        (5u8, vec![0x00, 0x87, 0x00, 0x00, 0x8F]),
    ] {
        let mut c = RawClient::connect(broker.port());
        let connect = raw::Connect {
            version,
            client_id: "dev1",
            login: Some(("dev1", "pw")),
            ..Default::default()
        };
        assert_eq!(c.handshake(&connect), 0);
        c.send(&raw::subscribe(version, 7, &filters));
        let (byte1, body) = c.read_packet().expect("SUBACK");
        assert_eq!(byte1, 0x90);
        assert_eq!(&body[..2], &7u16.to_be_bytes());
        assert_eq!(
            raw::suback_codes(version, &body),
            expected,
            "MQTT {version}"
        );
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn acl_reloads_without_disconnects_and_denials_are_logged_once() {
    let broker = line_broker();
    let port = broker.port();
    let dev1 = V4::connect(port, "dev1", Some(("dev1", "pw")))
        .await
        .unwrap();
    for _ in 0..5 {
        dev1.client
            .publish("cell/7/cmd", rumqttc::QoS::AtMostOnce, false, "x")
            .await
            .unwrap();
    }
    assert_eq!(
        broker.wait_metric("fbbus_acl_denied_total{action=\"publish\"}", 5.0),
        5.0
    );
    let lines = |b: &Broker| {
        b.log_text()
            .lines()
            .filter(|l| l.contains("denied by ACL") && l.contains("cell/7/cmd"))
            .count()
    };
    assert_eq!(lines(&broker), 1, "five denials, one log line");

    let mut monitor = V4::connect(port, "monitor", Some(("monitor", "pw")))
        .await
        .unwrap();
    monitor.subscribe("cell/#").await;
    std::fs::write(
        broker.path("acl"),
        format!("{ACL}user dev1\ntopic write cell/7/#\n"),
    )
    .unwrap();
    broker.wait_metric(
        "fbbus_file_reloads_total{file=\"acl_file\",result=\"ok\"}",
        1.0,
    );
    dev1.client
        .publish("cell/7/cmd", rumqttc::QoS::AtMostOnce, false, "now allowed")
        .await
        .unwrap();
    assert_eq!(
        monitor
            .next_publish(WAIT)
            .await
            .expect("allowed after reload")
            .payload,
        "now allowed"
    );
    assert!(dev1.alive(), "the reload kept dev1 connected");
}

/// A stranger cannot fill the log by reconnecting: each connection's denials are logged
/// once per client and topic, and all of them together at most
/// `logging::OUTSIDE_LINES_PER_MINUTE` (600) lines a minute; every denial is still
/// counted. 700 connections, each denied once on a topic of its own.
#[test]
fn denials_from_a_loop_of_connections_stay_within_the_logs_budget() {
    const CONNECTIONS: usize = 700;
    let broker = line_broker();
    for i in 0..CONNECTIONS {
        let mut c = RawClient::connect(broker.port());
        let client_id = format!("dev1-{i}");
        let connect = raw::Connect {
            client_id: &client_id,
            login: Some(("dev1", "pw")),
            ..Default::default()
        };
        assert_eq!(c.handshake(&connect), 0, "connection {i} refused");
        c.send(&raw::publish_qos0(&format!("cell/{i}/cmd"), b"x"));
        c.send(&raw::packet(0xE0, &[]));
    }
    assert_eq!(
        broker.wait_metric(
            "fbbus_acl_denied_total{action=\"publish\"}",
            CONNECTIONS as f64
        ),
        CONNECTIONS as f64
    );
    broker.assert_within_log_budget("denied by ACL", CONNECTIONS);
    // The broker serves on.
    let mut c = RawClient::connect(broker.port());
    let connect = raw::Connect {
        client_id: "monitor",
        login: Some(("monitor", "pw")),
        ..Default::default()
    };
    assert_eq!(c.handshake(&connect), 0);
}

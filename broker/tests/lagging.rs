//! A subscriber that lags behind its filter's commit log (issue 3). While it reads, the
//! publishers are held back so it loses nothing; once it has not caught up for
//! `slow_subscriber_hold_ms`, it skips what retention drops (QoS 0), never silently.

mod common;

use std::time::{Duration, Instant};

use common::clients::V4;
use common::raw::{self, Connect, RawClient};
use common::{Broker, Options};

const MESSAGES: usize = 20_000;
const PAYLOAD: usize = 1_000;

/// A broker whose filters keep two 4 KiB segments (eight 1,000-byte messages).
fn small_log_broker(hold_ms: u64) -> Broker {
    Broker::start_with(
        Options {
            extra: format!(
                "max_packet_bytes = 4096\nrouter_segment_bytes = 4096\nrouter_segment_count = 2\n\
                 slow_subscriber_hold_ms = {hold_ms}\n"
            ),
            ..Options::default()
        },
        |_| {},
    )
}

/// An MQTT 3.1.1 client, connected; subscribed to `topic` at QoS 0 if one is given.
fn client(port: u16, client_id: &str, topic: Option<&str>) -> RawClient {
    let mut client = RawClient::connect(port);
    let connect = Connect {
        client_id,
        ..Connect::default()
    };
    assert_eq!(client.handshake(&connect), 0);
    if let Some(topic) = topic {
        client.send(&raw::subscribe(4, 1, &[topic]));
        let (suback, _) = client.read_packet().expect("SUBACK");
        assert_eq!(suback, 0x90);
    }
    client
}

/// A subscriber that reads 20 MB more slowly than a publisher sends them (a pause every
/// 50 messages), through a commit log of eight messages; what it received and what the
/// broker counted as skipped.
fn slow_reader_run(broker: &Broker) -> (usize, f64) {
    let mut subscriber = client(broker.port(), "slow-reader", Some("lag/slow"));

    let port = broker.port();
    let publisher = std::thread::spawn(move || {
        let mut publisher = client(port, "burst", None);
        let burst: Vec<u8> = raw::publish_qos0("lag/slow", &[7u8; PAYLOAD]).repeat(1_000);
        for _ in 0..MESSAGES / 1_000 {
            publisher.send(&burst);
        }
        publisher
    });

    subscriber
        .stream
        .set_read_timeout(Some(Duration::from_secs(3)))
        .unwrap();
    let deadline = Instant::now() + Duration::from_secs(60);
    let mut received = 0;
    while received < MESSAGES && Instant::now() < deadline {
        let Some((byte1, _)) = subscriber.read_packet() else {
            break;
        };
        assert_eq!(byte1 & 0xf0, 0x30, "only PUBLISH expected");
        received += 1;
        if received % 50 == 0 {
            std::thread::sleep(Duration::from_millis(1));
        }
    }
    let _publisher = publisher.join().expect("publisher thread");
    (received, broker.metric("fbbus_messages_skipped_total"))
}

/// The subscriber reads all the time, only slower than the burst comes in: the publisher is
/// held back whenever the next message would drop one the subscriber has not read, and every
/// message arrives. Without holding (`slow_subscriber_hold_ms = 0`), the same run loses
/// messages: the control that shows the test can fail.
#[test]
fn a_subscriber_that_reads_slower_than_a_burst_gets_every_message() {
    let broker = small_log_broker(1_000);
    // Both outcomes are exported before anything was held.
    let metrics = broker.metrics();
    for outcome in ["caught_up", "gave_up"] {
        let series = format!("fbbus_publisher_holds_total{{outcome=\"{outcome}\"}} 0");
        assert!(metrics.contains(&series), "{metrics}");
    }
    let (received, skipped) = slow_reader_run(&broker);
    assert_eq!(received, MESSAGES, "{}", broker.log_text());
    assert_eq!(skipped, 0.0);
    let held = broker.metric("fbbus_publisher_holds_total{outcome=\"caught_up\"}");
    assert!(held > 0.0, "the publisher was held: {}", broker.metrics());
    assert_eq!(
        broker.metric("fbbus_publisher_holds_total{outcome=\"gave_up\"}"),
        0.0
    );
    drop(broker);

    let control = small_log_broker(0);
    let (received, skipped) = slow_reader_run(&control);
    assert!(received < MESSAGES, "without holding, messages are skipped");
    assert_eq!(skipped, (MESSAGES - received) as f64);
    assert_eq!(
        control.metric("fbbus_publisher_holds_total{outcome=\"caught_up\"}"),
        0.0
    );
}

/// The subscriber reads nothing while 20 MB are published, far more than the socket
/// buffers and a commit log of eight messages hold, then drains. The publisher is held
/// for `slow_subscriber_hold_ms`, then goes on: the subscriber is slow, and every message
/// it did not get is counted in `fbbus_messages_skipped_total`. Both are warned about
/// once.
#[test]
fn messages_a_lagging_subscriber_skips_are_counted_exactly() {
    let broker = small_log_broker(300);
    let mut subscriber = client(broker.port(), "laggard", Some("lag/t"));
    let mut publisher = client(broker.port(), "fast", None);
    let message = raw::publish_qos0("lag/t", &[7u8; PAYLOAD]);
    let burst: Vec<u8> = message.repeat(1_000);
    let started = Instant::now();
    for _ in 0..MESSAGES / 1_000 {
        publisher.send(&burst);
    }
    let routed = broker.wait_metric("fbbus_messages_received_total", MESSAGES as f64);
    assert_eq!(routed, MESSAGES as f64);
    let gave_up = broker.wait_metric("fbbus_publisher_holds_total{outcome=\"gave_up\"}", 1.0);
    assert!(gave_up >= 1.0, "{}", broker.metrics());
    // Held at least once for the whole 300 ms, and not forever. The milliseconds are
    // added just after the hold's outcome is counted: waited for.
    assert!(broker.wait_metric("fbbus_publisher_hold_milliseconds_total", 300.0) >= 300.0);
    assert!(started.elapsed() < Duration::from_secs(30));

    // Drain: everything still buffered or in the log, until the broker has nothing more.
    subscriber
        .stream
        .set_read_timeout(Some(Duration::from_secs(2)))
        .unwrap();
    let mut received = 0;
    while let Some((byte1, body)) = subscriber.read_packet() {
        assert_eq!(byte1 & 0xf0, 0x30, "only PUBLISH expected");
        assert_eq!(body.len(), 2 + "lag/t".len() + PAYLOAD);
        received += 1;
    }

    let sent = broker.metric("fbbus_messages_sent_total");
    let skipped = broker.metric("fbbus_messages_skipped_total");
    assert_eq!(sent, received as f64);
    assert!(
        received < MESSAGES,
        "the subscriber lagged by more than the commit log holds"
    );
    assert_eq!(skipped, (MESSAGES - received) as f64);
    let log = broker.log_text();
    let warnings = log
        .lines()
        .filter(|l| l.contains("WARN") && l.contains("messages skipped"))
        .count();
    assert_eq!(
        warnings, 1,
        "at most one warning a minute per client:\n{log}"
    );
    let hold_warnings = log
        .lines()
        .filter(|l| l.contains("WARN") && l.contains("did not catch up"))
        .count();
    assert_eq!(hold_warnings, 1, "at most one a minute per filter:\n{log}");
}

/// QoS 1 publications take the same way: a held PUBLISH is acknowledged only once it is
/// routed, so the publisher (rumqttc, 100 in flight) gets every PUBACK and the slow
/// subscriber every message, each once.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn held_qos1_publications_are_acknowledged_and_delivered_once() {
    const QOS1_MESSAGES: usize = 10_000;
    let broker = small_log_broker(1_000);
    let mut subscriber = client(broker.port(), "slow-qos1-reader", Some("lag/qos1"));
    let reader = std::thread::spawn(move || {
        subscriber
            .stream
            .set_read_timeout(Some(Duration::from_secs(3)))
            .unwrap();
        let deadline = Instant::now() + Duration::from_secs(60);
        let mut seqs = Vec::with_capacity(QOS1_MESSAGES);
        while seqs.len() < QOS1_MESSAGES && Instant::now() < deadline {
            let Some((byte1, body)) = subscriber.read_packet() else {
                break;
            };
            assert_eq!(byte1 & 0xf0, 0x30, "only PUBLISH expected");
            let payload = &body[2 + "lag/qos1".len()..];
            seqs.push(u32::from_be_bytes(payload[..4].try_into().unwrap()));
            if seqs.len() % 10 == 0 {
                std::thread::sleep(Duration::from_millis(1));
            }
        }
        seqs
    });

    let mut publisher = V4::connect(broker.port(), "qos1-burst", None)
        .await
        .expect("publisher connects");
    let client = publisher.client.clone();
    let sender = tokio::spawn(async move {
        for seq in 0..QOS1_MESSAGES as u32 {
            let mut payload = vec![7u8; PAYLOAD];
            payload[..4].copy_from_slice(&seq.to_be_bytes());
            client
                .publish("lag/qos1", rumqttc::QoS::AtLeastOnce, false, payload)
                .await
                .unwrap();
        }
    });
    let mut acked = 0;
    while acked < QOS1_MESSAGES {
        let ack = publisher
            .next(Duration::from_secs(20), |p| {
                matches!(p, rumqttc::Packet::PubAck(_)).then_some(())
            })
            .await;
        assert!(ack.is_some(), "{acked} of {QOS1_MESSAGES} PUBACKs");
        acked += 1;
    }
    sender.await.unwrap();

    let seqs = tokio::task::spawn_blocking(move || reader.join().unwrap())
        .await
        .unwrap();
    let expected: Vec<u32> = (0..QOS1_MESSAGES as u32).collect();
    let first_wrong = seqs
        .iter()
        .zip(&expected)
        .position(|(got, want)| got != want);
    assert!(
        seqs == expected,
        "{} of {QOS1_MESSAGES} delivered, in order and once each; first out of place at {first_wrong:?}",
        seqs.len()
    );
    assert_eq!(broker.metric("fbbus_messages_skipped_total"), 0.0);
    let held = broker.metric("fbbus_publisher_holds_total{outcome=\"caught_up\"}");
    assert!(held > 0.0, "the publisher was held: {}", broker.metrics());
}

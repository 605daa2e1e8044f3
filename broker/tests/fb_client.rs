//! The fb-bridge device client against the real broker when its application reads slowly:
//! a subscriber that reads, only slower than a burst comes in, gets every IND (the client
//! stops reading the socket while the subscriber's queue is full, and the broker holds the
//! publisher); one that stops reading is given up on after a short wait, and the device's
//! other subscribers go on.

mod common;

use std::time::{Duration, Instant};

use common::clients::V4;
use common::Broker;
use fb_bridge::client::{Device, DeviceConfig, Subscriber};
use fb_bridge::Value;

/// More than a subscriber's queue holds (1,024).
const BURST: i64 = 5_000;

/// `dev-a`, declared with two INT outputs, as a plain MQTT client that can burst.
async fn declared_publisher(broker: &Broker) -> V4 {
    let mut a = V4::connect(broker.port(), "dev-a", None).await.unwrap();
    a.declare(
        "dev-a",
        r#"{"fbs":{"CONV":{"data_out":{"POSITION":"INT","SPEED":"INT"}}}}"#,
    )
    .await;
    a
}

/// `dev-b`, an fb-bridge device following dev-a's ports.
async fn following_device(broker: &Broker) -> Device {
    let interface = serde_json::from_str(r#"{"fbs":{"MON":{"data_out":{"ALIVE":"BOOL"}}}}"#)
        .expect("interface");
    Device::connect(
        DeviceConfig::new("127.0.0.1", broker.port(), "dev-b"),
        interface,
    )
    .await
    .expect("dev-b connects")
}

async fn burst(a: &V4, port: &str, values: impl Iterator<Item = i64>) {
    for value in values {
        a.client
            .publish(
                format!("fb/dev-a/CONV/{port}"),
                rumqttc::QoS::AtMostOnce,
                false,
                value.to_string(),
            )
            .await
            .unwrap();
    }
}

async fn next_int(subscriber: &mut Subscriber, within: Duration) -> Option<i64> {
    let ind = tokio::time::timeout(within, subscriber.ind())
        .await
        .ok()??;
    match ind.data.as_slice() {
        [Value::Int(v)] => Some(*v as i64),
        other => panic!("not one INT: {other:?}"),
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_subscriber_that_reads_slower_than_a_burst_gets_every_ind() {
    let broker = Broker::start();
    let a = declared_publisher(&broker).await;
    let b = following_device(&broker).await;
    let mut position = b.subscriber("dev-a", "CONV", "POSITION").await.unwrap();

    let sender = tokio::spawn(async move {
        burst(&a, "POSITION", 0..BURST).await;
        a
    });
    let deadline = Instant::now() + Duration::from_secs(60);
    let mut got = Vec::new();
    while got.len() < BURST as usize && Instant::now() < deadline {
        let Some(value) = next_int(&mut position, Duration::from_secs(5)).await else {
            break;
        };
        got.push(value);
        if got.len() % 20 == 0 {
            tokio::time::sleep(Duration::from_millis(1)).await;
        }
    }
    let _a = sender.await.unwrap();
    let first_wrong = got.iter().zip(0..).position(|(v, want)| *v != want);
    assert!(
        got.len() == BURST as usize && first_wrong.is_none(),
        "{} of {BURST} INDs, first out of place at {first_wrong:?}",
        got.len()
    );
    assert_eq!(broker.metric("fbbus_messages_skipped_total"), 0.0);
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_subscriber_that_stops_reading_does_not_hold_up_the_others() {
    let broker = Broker::start();
    let a = declared_publisher(&broker).await;
    let b = following_device(&broker).await;
    let mut position = b.subscriber("dev-a", "CONV", "POSITION").await.unwrap();
    let mut speed = b.subscriber("dev-a", "CONV", "SPEED").await.unwrap();

    // Nobody reads POSITION.
    burst(&a, "POSITION", 0..BURST).await;
    burst(&a, "SPEED", std::iter::once(7)).await;
    let started = Instant::now();
    assert_eq!(next_int(&mut speed, Duration::from_secs(10)).await, Some(7));
    assert!(
        started.elapsed() < Duration::from_secs(5),
        "SPEED arrived after {:?}",
        started.elapsed()
    );
    // The stalled subscriber no longer holds the connection up at all: had each of these
    // 100 INDs waited its 500 ms for room, SPEED would come 50 s later. The bound is the
    // time of ten such waits, not a speed: a loaded CI machine took over 400 ms to carry
    // these 101 messages through a debug build.
    burst(&a, "POSITION", BURST..BURST + 100).await;
    burst(&a, "SPEED", std::iter::once(8)).await;
    assert_eq!(next_int(&mut speed, Duration::from_secs(5)).await, Some(8));
    assert!(b.status().0, "still connected: {:?}", b.status());

    // What POSITION kept: its queue's worth from the start, in order.
    let mut kept = Vec::new();
    while let Some(value) = next_int(&mut position, Duration::from_millis(300)).await {
        kept.push(value);
    }
    assert!(
        kept.len() >= 1_024 && kept.len() < (BURST + 100) as usize,
        "{}",
        kept.len()
    );
    assert!(kept.windows(2).all(|w| w[0] < w[1]), "in order");
    assert_eq!(&kept[..1_024], &(0..1_024).collect::<Vec<i64>>()[..]);
}

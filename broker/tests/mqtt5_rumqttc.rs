//! Issue 17's MQTT 5 rows as a Rust MQTT 5 client library sees them (rumqttc's v5
//! client), beside the byte-level checks in `conformance.rs` and the paho-mqtt rows of
//! `python/conformance.py`: a will's user properties arrive unaltered, overlapping
//! subscriptions give one copy with every Subscription Identifier, and topic aliases the
//! client allowed are resolved by the client to the topics published.

mod common;

use std::time::Duration;

use common::clients::{p5, V5, WAIT};
use common::Broker;
use rumqttc::v5::mqttbytes::QoS;

const QUIET: Duration = Duration::from_millis(700);

async fn drain(c: &mut V5) -> Vec<p5::Publish> {
    let mut got = Vec::new();
    while let Some(p) = c.next_publish(QUIET).await {
        got.push(p);
    }
    got
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_wills_user_properties_arrive_unaltered() {
    let broker = Broker::start();
    let mut watcher = V5::connect(broker.port(), "w-watch", None).await.unwrap();
    watcher.subscribe("wills/#").await;
    let properties = vec![
        ("a".to_owned(), "1".to_owned()),
        ("a".to_owned(), "2".to_owned()),
        ("b".to_owned(), "x".to_owned()),
    ];
    let mut options = V5::options(broker.port(), "w-dev", None);
    options.set_last_will(p5::LastWill::new(
        "wills/dev",
        "gone",
        QoS::AtLeastOnce,
        false,
        Some(p5::LastWillProperties {
            delay_interval: None,
            payload_format_indicator: None,
            message_expiry_interval: None,
            content_type: None,
            response_topic: None,
            correlation_data: None,
            user_properties: properties.clone(),
        }),
    ));
    let device = V5::connect_with(options).await.unwrap();
    // The connection is lost without DISCONNECT: the will goes out.
    drop(device);
    let will = watcher.next_publish(WAIT).await.expect("the will");
    assert_eq!(&will.payload[..], b"gone");
    let got = will
        .properties
        .map(|p| p.user_properties)
        .unwrap_or_default();
    assert_eq!(got, properties, "exactly the client's, in order");
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn overlapping_subscriptions_give_one_copy_with_every_identifier() {
    let broker = Broker::start();
    let mut c = V5::connect(broker.port(), "ids", None).await.unwrap();
    for (filter, id) in [("a/+/c", 1), ("a/#", 2)] {
        c.client
            .subscribe_with_properties(
                filter,
                QoS::AtLeastOnce,
                p5::SubscribeProperties {
                    id: Some(id),
                    user_properties: Vec::new(),
                },
            )
            .await
            .unwrap();
        c.next(WAIT, |p| matches!(p, p5::Packet::SubAck(_)).then_some(()))
            .await
            .expect("SUBACK");
    }
    let publisher = V5::connect(broker.port(), "ids-pub", None).await.unwrap();
    publisher
        .client
        .publish("a/b/c", QoS::AtLeastOnce, false, "one")
        .await
        .unwrap();
    let got = drain(&mut c).await;
    assert_eq!(got.len(), 1, "one copy: {got:?}");
    let mut ids = got[0]
        .properties
        .as_ref()
        .map(|p| p.subscription_identifiers.clone())
        .unwrap_or_default();
    ids.sort_unstable();
    assert_eq!(ids, vec![1, 2]);
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn topic_aliases_the_client_allows_are_used_and_resolved() {
    let broker = Broker::start();
    let mut options = V5::options(broker.port(), "alias", None);
    options.set_topic_alias_max(Some(10));
    let mut c = V5::connect_with(options).await.unwrap();
    c.subscribe("al/#").await;
    let publisher = V5::connect(broker.port(), "alias-pub", None).await.unwrap();
    for i in 0..3 {
        publisher
            .client
            .publish("al/Förderband/1", QoS::AtLeastOnce, false, format!("{i}"))
            .await
            .unwrap();
    }
    let got = drain(&mut c).await;
    assert_eq!(got.len(), 3);
    for (i, p) in got.iter().enumerate() {
        // rumqttc puts the topic back from the alias it learnt on the first delivery.
        assert_eq!(&p.topic[..], "al/Förderband/1".as_bytes(), "delivery {i}");
        assert_eq!(p.payload, i.to_string().as_bytes());
        let alias = p.properties.as_ref().and_then(|p| p.topic_alias);
        assert!(
            alias.is_some_and(|a| (1..=10).contains(&a)),
            "delivery {i}: {alias:?}"
        );
    }
}

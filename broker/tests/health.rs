//! Health that tells the truth: `/readyz` is 200 only while the router routes, a dead
//! router stops the process (non-zero, within a second), and a panic in one client's
//! session closes that connection only, with its will and its gauges.
//!
//! The panics are provoked through the test-only hooks of debug builds
//! (`FBBUS_TEST_ROUTER_PANIC_TOPIC`, `FBBUS_TEST_SESSION_PANIC_TOPIC`, see
//! `broker::supervisor::test_panic_topic`).

mod common;

use std::time::{Duration, Instant};

use common::clients::{self, V4, V5, WAIT};
use common::{http_get, wait_until, Broker, Options};

const KILL_ROUTER: &str = "test/kill-router";
const KILL_SESSION: &str = "test/kill-session";

fn broker_with(var: &'static str, topic: &str) -> Broker {
    Broker::start_with(
        Options {
            env: vec![(var, topic.to_owned())],
            ..Default::default()
        },
        |_| {},
    )
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn readyz_answers_from_a_probe_through_the_router() {
    let broker = Broker::start();
    let (code, body) = http_get(broker.admin, "/readyz").expect("readyz answers");
    assert_eq!((code, body.as_str()), (200, "ready\n"));
    // The probe is the broker's own: a `#` subscriber never sees it.
    let mut all = V4::connect(broker.port(), "all", None).await.unwrap();
    all.subscribe("#").await;
    for _ in 0..5 {
        assert_eq!(http_get(broker.admin, "/readyz").map(|r| r.0), Some(200));
        std::thread::sleep(Duration::from_millis(300));
    }
    assert!(
        all.next_publish(Duration::from_millis(300)).await.is_none(),
        "a client saw the readiness probe"
    );
}

/// `$fbbus/` is the broker's own: a client can neither feed the probe nor flood it.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn clients_may_not_publish_on_the_probe_topic() {
    let broker = Broker::start();
    let mut client = V5::connect(broker.port(), "forger", None).await.unwrap();
    client
        .client
        .publish(
            "$fbbus/probe",
            rumqttc::v5::mqttbytes::QoS::AtLeastOnce,
            false,
            "x",
        )
        .await
        .unwrap();
    let e = client.error(WAIT).await.expect("PUBACK refusal");
    assert!(
        e.contains("PubAckFail") && e.contains("NotAuthorized"),
        "{e}"
    );
    assert_eq!(http_get(broker.admin, "/readyz").map(|r| r.0), Some(200));
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_dead_router_fails_readyz_and_stops_the_process_non_zero() {
    let mut broker = broker_with("FBBUS_TEST_ROUTER_PANIC_TOPIC", KILL_ROUTER);
    assert_eq!(http_get(broker.admin, "/readyz").map(|r| r.0), Some(200));

    let client = V4::connect(broker.port(), "killer", None).await.unwrap();
    client
        .client
        .publish(KILL_ROUTER, rumqttc::QoS::AtMostOnce, false, "x")
        .await
        .unwrap();
    let sent = Instant::now();

    let status = wait_until(&mut broker.child, Duration::from_secs(5))
        .unwrap_or_else(|| panic!("the broker did not exit: {}", broker.log_text()));
    let took = sent.elapsed();
    assert_eq!(
        status.code(),
        Some(70),
        "exit status; log: {}",
        broker.log_text()
    );
    assert!(
        took < Duration::from_secs(1),
        "exited {took:?} after the panic"
    );
    assert_ne!(http_get(broker.admin, "/readyz").map(|r| r.0), Some(200));
    let log = broker.log_text();
    assert!(
        log.contains("panic_on_topic") && log.contains("router"),
        "the panic is in the log: {log}"
    );
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_panic_in_one_session_closes_only_that_connection_with_its_will() {
    let broker = broker_with("FBBUS_TEST_SESSION_PANIC_TOPIC", KILL_SESSION);
    let mut watcher = V4::connect(broker.port(), "watcher", None).await.unwrap();
    watcher.subscribe("will/#").await;
    watcher.subscribe("line/#").await;
    let mut options = V4::options(broker.port(), "victim", None);
    options.set_last_will(rumqttc::LastWill::new(
        "will/victim",
        "gone",
        rumqttc::QoS::AtLeastOnce,
        false,
    ));
    let victim = V4::connect_with(options).await.unwrap();
    let other = V4::connect(broker.port(), "other", None).await.unwrap();
    assert_eq!(broker.wait_metric("fbbus_connections", 3.0), 3.0);

    victim
        .client
        .publish(KILL_SESSION, rumqttc::QoS::AtMostOnce, false, "x")
        .await
        .unwrap();

    let will = watcher.next_publish(Duration::from_secs(5)).await;
    assert_eq!(
        will.map(|p| (p.topic, p.payload.to_vec())),
        Some(("will/victim".to_owned(), b"gone".to_vec())),
        "log: {}",
        broker.log_text()
    );
    assert_eq!(
        broker.wait_metric("fbbus_disconnects_total{reason=\"internal_error\"}", 1.0),
        1.0
    );
    let deadline = Instant::now() + clients::WAIT;
    while broker.metric("fbbus_connections") != 2.0 && Instant::now() < deadline {
        tokio::time::sleep(Duration::from_millis(50)).await;
    }
    assert_eq!(broker.metric("fbbus_connections"), 2.0, "the gauge is back");

    // Everyone else goes on.
    other
        .client
        .publish("line/a", rumqttc::QoS::AtLeastOnce, false, "still")
        .await
        .unwrap();
    let next = watcher.next_publish(Duration::from_secs(5)).await;
    assert_eq!(next.map(|p| p.topic), Some("line/a".to_owned()));
    assert_eq!(http_get(broker.admin, "/readyz").map(|r| r.0), Some(200));
    assert!(V4::connect(broker.port(), "newcomer", None).await.is_ok());
    assert!(broker.log_text().contains("test_panic_topic"));
}

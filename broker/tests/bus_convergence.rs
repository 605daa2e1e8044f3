//! Issue 32: what the bus keeps true when lines forget, die and come back.
//!
//! - A device its line forgets is forgotten on every other line, with its record and the
//!   retained values they held of it.
//! - A subscriber that subscribed on line A while line B was down gets B's devices'
//!   retained values once B is back (B was SIGKILLed and restarted on its store).
//! - QoS 1 messages from the bus are stored for an offline persistent session like local
//!   ones: line A is SIGKILLed while its session is away, and the session gets them.
//!
//! Real `fbbus` processes on a plain loopback bus (`tcp/`), devices as rumqttc clients.

mod common;

use std::io::{Read, Write};
use std::time::{Duration, Instant};

use common::bus::*;
use common::clients::V4;

/// `DELETE /api/v1/devices/<id>` on `line`'s admin endpoint (what `fbbus devices forget`
/// sends); the status code.
fn forget(line: &Line, id: &str) -> u16 {
    let mut s = std::net::TcpStream::connect(line.broker.admin).unwrap();
    write!(
        s,
        "DELETE /api/v1/devices/{id} HTTP/1.0\r\nHost: localhost\r\n\r\n"
    )
    .unwrap();
    let mut answer = String::new();
    let _ = s.read_to_string(&mut answer);
    answer
        .split(' ')
        .nth(1)
        .and_then(|code| code.parse().ok())
        .unwrap_or(0)
}

/// Waits until `check` holds, or panics with `what` after `within`.
async fn eventually(within: Duration, what: &str, mut check: impl FnMut() -> bool) {
    let deadline = Instant::now() + within;
    while !check() {
        assert!(Instant::now() < deadline, "{what} within {within:?}");
        tokio::time::sleep(Duration::from_millis(50)).await;
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_forgotten_device_is_gone_from_every_line() {
    let endpoint = tcp_endpoint();
    let b = Line::start_on("line-b", &endpoint, &[], "", None);
    let a = Line::plain("line-a", &[&endpoint], "");
    let c = Line::plain("line-c", &[&endpoint], "");
    // A subscriber on C holds the device's last value, imported from B.
    let mut watcher = V4::connect(c.port(), "watcher", None).await.unwrap();
    watcher.subscribe("fb/old-plc/CONV/POSITION").await;
    tokio::time::sleep(Duration::from_millis(500)).await;
    let dev = device(&b, "old-plc").await;
    publish(&dev, "fb/old-plc/CONV/POSITION", "7".into(), true).await;
    a.wait_record("old-plc", "online", PROPAGATION);
    c.wait_record("old-plc", "online", PROPAGATION);
    assert!(watcher.next_publish(PROPAGATION).await.is_some());
    dev.client.disconnect().await.unwrap();
    drop(dev);
    c.wait_record("old-plc", "offline", PROPAGATION);

    assert_eq!(forget(&b, "old-plc"), 200);
    for line in [&a, &c] {
        eventually(
            PROPAGATION,
            &format!("{}: old-plc forgotten", line.name),
            || line.record("old-plc").is_none(),
        )
        .await;
        assert_eq!(
            line.broker
                .metric("fbbus_registry_forgotten_total{reason=\"bus\"}"),
            1.0
        );
    }
    // C's retained value is cleared: a new subscriber gets nothing of the device.
    let mut late = V4::connect(c.port(), "late", None).await.unwrap();
    late.subscribe("fb/old-plc/#").await;
    let got = drain(&mut late, Duration::from_millis(700)).await;
    assert!(
        got.iter().all(|p| p.payload.is_empty()),
        "values of a forgotten device: {got:?}"
    );
    // Nothing was refused on the way: the clears C made are not put back on the bus.
    for line in [&a, &b, &c] {
        assert!(
            !line
                .broker
                .metrics()
                .contains("fbbus_bridge_refused_total{"),
            "{}: {}",
            line.name,
            line.broker.metrics()
        );
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_returning_line_brings_its_retained_values_to_subscribers_of_meanwhile() {
    // A listens and B dials it: B links again as soon as it is back, without waiting for
    // zenoh's backoff between A's attempts to reach a dead peer.
    let endpoint = tcp_endpoint();
    let a = Line::start_on("line-a", &endpoint, &[], "", None);
    let mut b = Line::plain("line-b", &[&endpoint], "");
    let dev = device(&b, "press-1").await;
    publish(&dev, "fb/press-1/CONV/POSITION", "42".into(), true).await;
    a.wait_record("press-1", "online", PROPAGATION);
    // In B's store before B dies (written before its acknowledgement).
    b.wait_metric("fbbus_store_retained_messages", 1.0);
    drop(dev);

    b.broker.kill_now();
    a.wait_record("press-1", "unreachable", PROPAGATION);
    // Subscribed while B is away: nothing of B's can come yet.
    let mut hmi = V4::connect(a.port(), "hmi", None).await.unwrap();
    hmi.subscribe("fb/press-1/#").await;
    assert!(hmi.next_publish(Duration::from_millis(500)).await.is_none());

    b.broker.start_again();
    // B starts again (its store, its bridge), links, A asks for its records, then for its
    // retained values: on a loaded 2-core machine this takes seconds.
    let Some(got) = hmi.next_publish(3 * PROPAGATION).await else {
        panic!(
            "B's retained value once B is back\n--- line A\n{}\n--- line B\n{}\n{}",
            a.broker.log_text(),
            b.broker.log_text(),
            a.broker.metrics()
        );
    };
    assert_eq!(got.topic, "fb/press-1/CONV/POSITION");
    assert_eq!(&got.payload[..], b"42");
    // Once, not again with every later requery.
    assert!(drain(&mut hmi, Duration::from_millis(700)).await.is_empty());
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn qos1_messages_from_the_bus_are_stored_for_an_offline_session() {
    let endpoint = tcp_endpoint();
    let b = Line::start_on("line-b", &endpoint, &[], "", None);
    let mut a = Line::plain("line-a", &[&endpoint], "");
    let a_port = a.port();
    let persistent = || {
        let mut options = V4::options(a_port, "historian", None);
        options.set_clean_session(false);
        options
    };
    let mut historian = V4::connect_with(persistent()).await.unwrap();
    historian.subscribe("fb/line-b-plc/#").await;
    let dev = device(&b, "line-b-plc").await;
    a.wait_record("line-b-plc", "online", PROPAGATION);
    // The subscription is imported once B sees A's interest.
    tokio::time::sleep(Duration::from_secs(1)).await;
    drop(historian);
    tokio::time::sleep(Duration::from_millis(300)).await;
    for i in 1..=5 {
        publish(&dev, "fb/line-b-plc/CONV/POSITION", i.to_string(), false).await;
    }
    a.wait_metric("fbbus_store_queued_messages", 5.0);

    a.broker.restart("KILL");
    let mut historian = V4::connect_with(persistent()).await.unwrap();
    let got = drain(&mut historian, Duration::from_secs(2)).await;
    assert_eq!(
        positions(&got, "fb/line-b-plc/CONV/POSITION"),
        [1, 2, 3, 4, 5],
        "every QoS 1 message from the bus survives the crash\n{}",
        a.broker.log_text()
    );
    drop(b);
}

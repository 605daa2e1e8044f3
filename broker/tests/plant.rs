//! Issue 32: a plant, not a pair. Five lines on one bus: lines 1 and 2 are zenoh routers
//! (`mode = "router"`) linked to each other, lines 3 to 5 are zenoh clients of both, as a
//! plant with two redundant routers runs them (here the routers are fbbus lines, as the
//! issue's own attempt did; `zenohd` itself is not installed in CI). Each line has
//! `DEVICES` declared devices.
//!
//! - every line lists every device of the bus online (and says how long it took);
//! - a device of line 3 reaches a subscriber of line 5, every message once and in order;
//! - router line 1 is SIGKILLed: after the lease, lines 3 to 5 still list each other's
//!   devices online (their clients moved to router line 2), and line 3 -> line 5 goes on,
//!   every message once and in order.

mod common;

use std::time::{Duration, Instant};

use common::bus::*;
use common::clients::V4;

const DEVICES: usize = 20;
const LINES: usize = 5;

fn id(line: usize, device: usize) -> String {
    format!("l{line}-dev-{device:02}")
}

/// Waits until `line` lists `want` devices online; returns how long it took.
async fn converged(line: &Line, want: usize, within: Duration) -> Duration {
    let started = Instant::now();
    loop {
        let online = line
            .broker
            .metric("fbbus_registry_devices{status=\"online\"}");
        if online >= want as f64 {
            return started.elapsed();
        }
        assert!(
            started.elapsed() < within,
            "line {} lists {online} of {want} devices online\n{}",
            line.name,
            line.broker.log_text()
        );
        tokio::time::sleep(Duration::from_millis(50)).await;
    }
}

/// Publishes `range` from `dev` and checks `sub` gets each once, in order.
async fn once_in_order(dev: &V4, sub: &mut V4, topic: &str, range: std::ops::RangeInclusive<i64>) {
    for i in range.clone() {
        publish(dev, topic, i.to_string(), false).await;
    }
    let mut got = Vec::new();
    let deadline = Instant::now() + PROPAGATION;
    while got.len() < range.clone().count() && Instant::now() < deadline {
        if let Some(p) = sub.next_publish(Duration::from_millis(200)).await {
            got.push(p);
        }
    }
    got.extend(drain(sub, Duration::from_millis(500)).await);
    let want: Vec<i64> = range.collect();
    assert_eq!(positions(&got, topic), want, "once each, in order");
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn five_lines_two_routers_converge_and_survive_a_router() {
    let (r1, r2) = (tcp_endpoint(), tcp_endpoint());
    let router = "mode = \"router\"\n";
    let client = "mode = \"client\"\n";
    let mut lines = vec![
        Line::start_on("line-1", &r1, &[], router, None),
        Line::start_on("line-2", &r2, &[&r1], router, None),
    ];
    for n in 3..=LINES {
        lines.push(Line::start_on(
            &format!("line-{n}"),
            "",
            &[&r1, &r2],
            client,
            None,
        ));
    }
    let mut devices = Vec::new();
    for (n, line) in lines.iter().enumerate() {
        for d in 0..DEVICES {
            devices.push(device(line, &id(n + 1, d)).await);
        }
    }
    let everyone = LINES * DEVICES;
    let mut slowest = Duration::ZERO;
    for line in &lines {
        slowest = slowest.max(converged(line, everyone, Duration::from_secs(30)).await);
    }
    eprintln!("every line listed all {everyone} devices online within {slowest:?} of the last declaration");

    let topic = format!("fb/{}/CONV/POSITION", id(3, 0));
    let mut sub = V4::connect(lines[4].port(), "hmi-5", None).await.unwrap();
    sub.subscribe(&topic).await;
    // The interest reaches line 3 through a router.
    tokio::time::sleep(Duration::from_secs(1)).await;
    let publisher = &devices[2 * DEVICES];
    once_in_order(publisher, &mut sub, &topic, 1..=20).await;

    lines[0].broker.kill_now();
    let killed = Instant::now();
    // Line 1's devices go unreachable; every other line's devices are online again (or
    // still) once the clients of line 1 moved to router line 2: within the lease and
    // zenoh's reconnection.
    for line in &lines[2..] {
        line.wait_record(&id(1, 0), "unreachable", PROPAGATION);
    }
    for line in &lines[1..] {
        for n in 2..=LINES {
            for d in [0, DEVICES - 1] {
                if line.name != format!("line-{n}") {
                    line.wait_record(&id(n, d), "online", PROPAGATION);
                }
            }
        }
    }
    eprintln!(
        "after router line 1 died, every other line listed the others online again within {:?}",
        killed.elapsed()
    );
    once_in_order(publisher, &mut sub, &topic, 21..=40).await;
    drop(devices);
}

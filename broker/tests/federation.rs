//! Issue 32: a device's record crosses the bus once per change, and a line that joins gets
//! another line's registry in a bounded number of exchanges, not one query per device.
//! Line A holds 300 declared devices; line B joins the bus afterwards: B lists all of
//! them online after one query for line A's records (a device has no liveliness token of
//! its own to ask for more), and a device A declares afterwards reaches B by its record
//! alone.

mod common;

use std::time::{Duration, Instant};

use common::bus::*;

const DEVICES: usize = 300;

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_joining_line_gets_a_whole_registry_in_one_exchange() {
    let endpoint = tcp_endpoint();
    // All of A's devices come from one address: past the default share of 100.
    let a = Line::start_with("line-a", &endpoint, &[], "", |_| {
        "[fb]\nmax_devices_per_identity = 1000\n".into()
    });
    let mut devices = Vec::with_capacity(DEVICES);
    for i in 0..DEVICES {
        devices.push(device(&a, &format!("dev-{i:03}")).await);
    }
    let b = Line::plain("line-b", &[&endpoint], "");
    let deadline = Instant::now() + Duration::from_secs(30);
    loop {
        let online = b.broker.metric("fbbus_registry_devices{status=\"online\"}");
        if online >= DEVICES as f64 {
            break;
        }
        assert!(
            Instant::now() < deadline,
            "line B lists {online} devices online, not {DEVICES}\n{}",
            b.broker.log_text()
        );
        tokio::time::sleep(Duration::from_millis(100)).await;
    }
    for id in ["dev-000", "dev-150", "dev-299"] {
        assert_eq!(b.record(id).expect(id)["status"], "online");
    }
    let queries = |kind: &str| {
        b.broker.metric(&format!(
            "fbbus_bridge_record_queries_total{{kind=\"{kind}\"}}"
        ))
    };
    // Line A's coming up asks once for its registry (once more if the link flapped on a
    // slow machine), never once per device.
    assert!(queries("line") >= 1.0, "{}", b.broker.metrics());
    assert!(
        queries("line") <= 3.0,
        "{} queries for {DEVICES} devices",
        queries("line"),
    );
    let before = queries("line");
    let late = device(&a, "dev-late").await;
    b.wait_record("dev-late", "online", Duration::from_secs(10));
    tokio::time::sleep(Duration::from_millis(300)).await;
    assert_eq!(
        queries("line"),
        before,
        "a record put on the bus needs no query"
    );
    drop((devices, late));
}

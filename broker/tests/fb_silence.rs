//! Silence is a state, end to end against the real `fbbus` binary: a device that stays
//! connected while its periodic output stops — a 4diac FORTE whose Paho publishers died
//! after a failed send — is shown `online, silent` in its record (HTTP and the retained
//! `fbbus/devices/<id>`), by `fbbus devices` and in `fbbus_registry_silent_devices`, and is
//! shown speaking again once it publishes.

mod common;

use std::net::SocketAddr;
use std::path::PathBuf;
use std::process::{Command, Stdio};
use std::time::{Duration, Instant};

use serde_json::Value;

use common::fb::*;
use common::{Broker, Options};

/// The device's period.
const PERIOD: Duration = Duration::from_millis(200);
/// `max(silence_factor 3 × 200 ms, silence_min_s 1 s)` = 1 s, plus the registry's 1 s
/// check interval: the record must turn within this of the last publication.
const BOUND: Duration = Duration::from_secs(2);
/// For a loaded test machine (HTTP polling, process scheduling).
const SLACK: Duration = Duration::from_millis(1500);

fn silent(r: &Value) -> bool {
    r["status"] == "online" && r["silent"] == true
}

fn speaking(r: &Value) -> bool {
    r["status"] == "online" && r["silent"] == false
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_connected_device_whose_publishers_stopped_is_online_silent() {
    let broker = Broker::start_with(
        Options {
            extra: "[fb]\nsilence_min_s = 1\n".into(),
            ..Default::default()
        },
        |_| {},
    );
    let series = "fbbus_registry_silent_devices";
    let mut diag_sub = observer(&broker, "watch", &["fbbus/diag/#"]).await;
    // Like FORTE: MQTT 3.1.1, QoS 0.
    let mut forte = Dev::connect(broker.port(), 4, "forte");
    declare_ok(&mut forte, CONV, &mut diag_sub, &broker).await;

    // 3 s of a 200 ms period: established, and never silent meanwhile.
    let mut last = Instant::now();
    for i in 0..15 {
        forte.publish_qos0("fb/forte/CONV/POSITION", i.to_string().as_bytes());
        last = Instant::now();
        tokio::time::sleep(PERIOD).await;
    }
    let r = record(&broker, "forte").expect("declared");
    assert!(speaking(&r), "{r}");
    assert_eq!(broker.metric(series), 0.0);

    // Its publishers die; the connection stays.
    let mut records = observer(&broker, "records", &["fbbus/devices/forte"]).await;
    let r = wait_record(&broker, "forte", "turned silent", silent).await;
    let took = last.elapsed();
    assert!(
        took <= BOUND + SLACK,
        "silent after {took:?}, bound {BOUND:?}: {r}"
    );
    assert!(took >= Duration::from_secs(1), "silent too early: {took:?}");
    assert!(r["silent_since"].is_string(), "{r}");
    assert_eq!(r["last_will_reason"], Value::Null);
    assert_metric(&broker, series, 1.0);
    // Announced on the bus topic too (the retained record first, then the change).
    let deadline = Instant::now() + Duration::from_secs(5);
    loop {
        let got = json_on(&mut records, "fbbus/devices/forte", &broker).await;
        if silent(&got) {
            break;
        }
        assert!(
            Instant::now() < deadline,
            "no silent record published: {got}"
        );
    }

    let mut cmd = Command::new(common::fbbus_bin());
    cmd.args(["devices", "--admin", &broker.admin.to_string()])
        .stdin(Stdio::null());
    let (ok, out, err) = common::run(&mut cmd, Duration::from_secs(15));
    assert!(ok, "fbbus devices failed: {err}");
    let row = out
        .lines()
        .find(|l| l.starts_with("forte"))
        .unwrap_or_else(|| panic!("{out}"));
    assert!(row.contains("online, silent"), "{out}");
    assert!(out.ends_with("1 devices, 1 online (1 silent)\n"), "{out}");

    // It speaks again: shown speaking within a check interval.
    forte.publish_qos0("fb/forte/CONV/POSITION", b"99");
    let spoke = Instant::now();
    let r = wait_record(&broker, "forte", "spoke again", speaking).await;
    assert!(
        spoke.elapsed() <= Duration::from_secs(1) + SLACK,
        "speaking after {:?}: {r}",
        spoke.elapsed()
    );
    assert_eq!(r["silent_since"], Value::Null);
    let deadline = Instant::now() + Duration::from_secs(5);
    while broker.metric(series) != 0.0 {
        assert!(Instant::now() < deadline, "{series} stayed at 1");
        tokio::time::sleep(Duration::from_millis(25)).await;
    }
}

/// Stops the broker with SIGTERM (it writes its registry) and starts a new one on the same
/// config, directory and ports.
fn restart(mut broker: Broker) -> Broker {
    broker.signal("TERM");
    let status = common::wait_until(&mut broker.child, Duration::from_secs(15));
    assert!(
        status.is_some_and(|s| s.success()),
        "broker exited with {status:?} after SIGTERM\n{}",
        broker.log_text()
    );
    let dir = std::mem::replace(&mut broker.dir, tempfile::tempdir().unwrap());
    let (config, mqtt, admin): (PathBuf, SocketAddr, SocketAddr) =
        (broker.config.clone(), broker.mqtt, broker.admin);
    drop(broker);
    Broker::spawn(dir, config, mqtt, admin)
}

/// FORTE after a broker restart: it reconnects (without declaring again) but its
/// publishers stay dead, so the new broker never sees a publication. The period observed
/// before the restart is kept with the registry, so the device still turns silent, one
/// bound after its connection.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_device_that_reconnects_after_a_restart_and_never_publishes_is_silent() {
    let broker = Broker::start_with(
        Options {
            extra: "[fb]\nsilence_min_s = 1\n".into(),
            ..Default::default()
        },
        |_| {},
    );
    let mut diag_sub = observer(&broker, "watch", &["fbbus/diag/#"]).await;
    let mut forte = Dev::connect(broker.port(), 4, "forte");
    declare_ok(&mut forte, CONV, &mut diag_sub, &broker).await;
    for i in 0..12 {
        forte.publish_qos0("fb/forte/CONV/POSITION", i.to_string().as_bytes());
        tokio::time::sleep(PERIOD).await;
    }
    drop(diag_sub);
    let broker = tokio::task::block_in_place(|| restart(broker));
    drop(forte);

    let _forte = Dev::connect(broker.port(), 4, "forte");
    let connected = Instant::now();
    wait_record(&broker, "forte", "came back", |r| r["status"] == "online").await;
    let r = wait_record(&broker, "forte", "turned silent", silent).await;
    let took = connected.elapsed();
    assert!(
        took <= BOUND + SLACK,
        "silent {took:?} after connecting, bound {BOUND:?}: {r}"
    );
    assert_metric(&broker, "fbbus_registry_silent_devices", 1.0);
}

//! The device registry end to end against the real `fbbus` binary: over MQTT, HTTP and
//! `fbbus devices`; every kind of end marks a device offline with its reason; the registry
//! survives a shutdown and a crash.
//!
//! Each test starts its own broker on free loopback ports; helpers are in
//! `common/fb.rs`.

mod common;

use std::net::SocketAddr;
use std::path::PathBuf;
use std::process::{Command, Stdio};
use std::time::{Duration, Instant};

use serde_json::Value;

use common::clients::{V4, WAIT};
use common::fb::*;
use common::raw;
use common::Broker;

// ---------------------------------------------------------------- 7. registry over HTTP and CLI

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn registry_is_served_over_http_and_by_fbbus_devices() {
    let broker = Broker::start();
    let mut diag_sub = observer(&broker, "watch", &["fbbus/diag/#"]).await;
    let mut a = Dev::connect(broker.port(), 5, "conv-a");
    let session_a = declare_ok(&mut a, CONV, &mut diag_sub, &broker).await;
    let mut b = Dev::connect(broker.port(), 4, "conv-b");
    declare_ok(&mut b, CONV, &mut diag_sub, &broker).await;
    b.disconnect();
    wait_record(&broker, "conv-b", "went offline", |r| {
        r["status"] == "offline"
    })
    .await;

    let (code, all) = http_json(&broker, "/api/v1/devices");
    assert_eq!(code, 200);
    assert_eq!(all["line"], "test");
    let ids: Vec<&str> = all["devices"]
        .as_array()
        .unwrap()
        .iter()
        .map(|d| d["id"].as_str().unwrap())
        .collect();
    assert_eq!(ids, ["conv-a", "conv-b"]);
    let (_, online) = http_json(&broker, "/api/v1/devices?status=online");
    assert_eq!(online["devices"].as_array().unwrap().len(), 1, "{online}");
    assert_eq!(online["devices"][0]["id"], "conv-a");
    let (_, offline) = http_json(&broker, "/api/v1/devices?status=offline");
    assert_eq!(offline["devices"].as_array().unwrap().len(), 1, "{offline}");
    assert_eq!(
        offline["devices"][0]["last_will_reason"],
        "clean disconnect"
    );

    let (code, one) = http_json(&broker, "/api/v1/devices/conv-a");
    assert_eq!(code, 200);
    assert_eq!(one["status"], "online");
    assert_eq!(one["session"], session_a);
    assert_eq!(one["interface"]["fbs"]["CONV"]["data_in"]["SPEED"], "REAL");
    let (code, missing) = http_json(&broker, "/api/v1/devices/nope");
    assert_eq!(code, 404);
    assert!(
        missing["error"]
            .as_str()
            .is_some_and(|e| e.contains("nope")),
        "{missing}"
    );

    // The terminal view.
    let admin = broker.admin.to_string();
    let devices = |args: &[&str]| {
        let mut cmd = Command::new(common::fbbus_bin());
        cmd.arg("devices").args(args).stdin(Stdio::null());
        common::run(&mut cmd, Duration::from_secs(15))
    };
    let (ok, out, err) = devices(&["--admin", &admin]);
    assert!(ok, "fbbus devices failed: {err}");
    let lines: Vec<&str> = out.lines().collect();
    assert!(lines[0].starts_with("ID"), "{out}");
    let row_a = lines
        .iter()
        .find(|l| l.starts_with("conv-a"))
        .unwrap_or_else(|| panic!("{out}"));
    assert!(row_a.contains("online") && row_a.contains("test"), "{out}");
    let row_b = lines
        .iter()
        .find(|l| l.starts_with("conv-b"))
        .unwrap_or_else(|| panic!("{out}"));
    assert!(
        row_b.contains("offline") && row_b.contains("clean disconnect"),
        "{out}"
    );
    assert_eq!(lines.last(), Some(&"2 devices, 1 online"), "{out}");

    let (ok, out, err) = devices(&["--admin", &admin, "--json"]);
    assert!(ok, "fbbus devices --json failed: {err}");
    let parsed: Value = serde_json::from_str(&out).unwrap_or_else(|e| panic!("{e}: {out}"));
    assert_eq!(parsed["devices"][0]["id"], "conv-a");
    assert_eq!(parsed["devices"][0]["status"], "online");

    let (ok, out, err) = devices(&["--admin", &admin, "--json", "conv-b"]);
    assert!(ok, "fbbus devices conv-b failed: {err}");
    assert_eq!(parse(out.as_bytes())["status"], "offline");
    let (ok, out, _) = devices(&["--config", broker.config.to_str().unwrap(), "conv-a"]);
    assert!(
        ok && out.contains("conv-a") && out.ends_with("1 devices, 1 online\n"),
        "{out}"
    );

    let (ok, _, err) = devices(&["--admin", &admin, "nope"]);
    assert!(!ok);
    assert!(err.contains("no device nope"), "{err}");
}

// ---------------------------------------------------------------- 8. ends mark offline

/// Waits until the retained online count of line `test` reads `n`.
async fn wait_count(sub: &mut V4, n: &str, broker: &Broker) {
    let deadline = Instant::now() + Duration::from_secs(10);
    let mut seen = Vec::new();
    loop {
        let left = deadline.saturating_duration_since(Instant::now());
        match next_on(sub, "fbbus/lines/test/online", left).await {
            Some(p) if p == n.as_bytes() => return,
            Some(p) => seen.push(String::from_utf8_lossy(&p).into_owned()),
            None => panic!(
                "online count never {n}; saw {seen:?}\n--- broker log\n{}",
                broker.log_text()
            ),
        }
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn every_kind_of_end_marks_the_device_offline_with_its_reason() {
    let broker = Broker::start();
    let mut diag_sub = observer(&broker, "watch", &["fbbus/diag/#"]).await;
    let mut count = observer(&broker, "count", &["fbbus/lines/test/online"]).await;

    // The TCP connection dropped without DISCONNECT (socket closed).
    let mut dev = Dev::try_connect(
        broker.port(),
        &raw::Connect {
            version: 4,
            client_id: "dev-lost",
            keep_alive: 2,
            ..Default::default()
        },
    )
    .unwrap();
    let session = declare_ok(&mut dev, CONV, &mut diag_sub, &broker).await;
    wait_count(&mut count, "1", &broker).await;
    drop(dev);
    let rec = wait_record(&broker, "dev-lost", "lost its connection", |r| {
        r["status"] == "offline"
    })
    .await;
    assert_eq!(rec["last_will_reason"], "connection lost", "{rec}");
    assert_eq!(rec["session"], session, "{rec}");
    wait_count(&mut count, "0", &broker).await;

    // A rumqttc device whose event loop is aborted (its task and socket gone).
    let rumqtt = V4::connect(broker.port(), "dev-abort", None).await.unwrap();
    rumqtt
        .client
        .publish(
            "fbbus/declare/dev-abort",
            rumqttc::QoS::AtLeastOnce,
            false,
            CONV,
        )
        .await
        .unwrap();
    assert_eq!(
        diag(&mut diag_sub, "dev-abort", "declaration", &broker).await["ok"],
        true
    );
    wait_count(&mut count, "1", &broker).await;
    drop(rumqtt);
    wait_record(
        &broker,
        "dev-abort",
        "lost its connection",
        offline_because("connection lost"),
    )
    .await;
    wait_count(&mut count, "0", &broker).await;

    // Silence on an open socket: keep-alive 1 s expires after 1.5 s.
    let mut dev = Dev::try_connect(
        broker.port(),
        &raw::Connect {
            version: 5,
            client_id: "dev-silent",
            keep_alive: 1,
            ..Default::default()
        },
    )
    .unwrap();
    declare_ok(&mut dev, CONV, &mut diag_sub, &broker).await;
    wait_count(&mut count, "1", &broker).await;
    let silent_since = Instant::now();
    wait_record(
        &broker,
        "dev-silent",
        "expired",
        offline_because("keep-alive expired"),
    )
    .await;
    assert!(
        silent_since.elapsed() >= Duration::from_millis(1000),
        "offline after {:?} of silence",
        silent_since.elapsed()
    );
    wait_count(&mut count, "0", &broker).await;
    drop(dev);

    // A clean DISCONNECT.
    let mut dev = Dev::connect(broker.port(), 5, "dev-clean");
    declare_ok(&mut dev, CONV, &mut diag_sub, &broker).await;
    wait_count(&mut count, "1", &broker).await;
    dev.disconnect();
    wait_record(
        &broker,
        "dev-clean",
        "disconnected",
        offline_because("clean disconnect"),
    )
    .await;
    wait_count(&mut count, "0", &broker).await;

    // And the MQTT 5 DISCONNECT that asks for the will.
    let mut dev = Dev::connect(broker.port(), 5, "dev-will");
    declare_ok(&mut dev, CONV, &mut diag_sub, &broker).await;
    tokio::task::block_in_place(|| dev.raw.send(&[0xE0, 0x01, 0x04]));
    wait_record(
        &broker,
        "dev-will",
        "disconnected",
        offline_because("disconnect with will"),
    )
    .await;
    wait_count(&mut count, "0", &broker).await;
    assert_eq!(
        broker.metric(r#"fbbus_registry_devices{status="offline"}"#),
        5.0
    );
}

// ---------------------------------------------------------------- 10. restarts

/// Stops the broker (SIGTERM, or SIGKILL for a crash) and starts a new one on the same
/// config, directory and ports. The old log is kept as `broker.log.1`.
fn restart(mut broker: Broker, signal: &str) -> Broker {
    broker.signal(signal);
    let status = common::wait_until(&mut broker.child, Duration::from_secs(15));
    if signal == "TERM" {
        assert!(
            status.is_some_and(|s| s.success()),
            "broker exited with {status:?} after SIGTERM\n{}",
            broker.log_text()
        );
    }
    std::fs::copy(&broker.log, broker.path("broker.log.1")).unwrap();
    let dir = std::mem::replace(&mut broker.dir, tempfile::tempdir().unwrap());
    let (config, mqtt, admin): (PathBuf, SocketAddr, SocketAddr) =
        (broker.config.clone(), broker.mqtt, broker.admin);
    drop(broker);
    Broker::spawn(dir, config, mqtt, admin)
}

async fn restart_keeps_the_registry(signal: &str, reason: &str) {
    let broker = Broker::start();
    let mut diag_sub = observer(&broker, "watch", &["fbbus/diag/conv-a"]).await;
    let mut dev = Dev::connect(broker.port(), 5, "conv-a");
    let s1 = declare_ok(&mut dev, CONV, &mut diag_sub, &broker).await;
    if signal == "KILL" {
        // A crash loses at most what was not yet written: wait until it was.
        // The change is appended to the journal beside the snapshot (issue 21).
        let file = broker.path("fbbus-registry.json.log");
        let deadline = Instant::now() + Duration::from_secs(5);
        while !std::fs::read_to_string(&file).is_ok_and(|t| t.contains("conv-a")) {
            assert!(
                Instant::now() < deadline,
                "registry never persisted to {file:?}"
            );
            tokio::time::sleep(Duration::from_millis(20)).await;
        }
    }
    drop(diag_sub);
    let broker = tokio::task::block_in_place(|| restart(broker, signal));
    drop(dev);

    let rec = record(&broker, "conv-a").expect("the record survives the restart");
    assert_eq!(rec["status"], "offline", "{rec}");
    assert_eq!(rec["last_will_reason"], reason, "{rec}");
    assert_eq!(rec["session"], s1, "{rec}");
    assert_eq!(
        rec["interface"]["fbs"]["CONV"]["data_out"]["POSITION"],
        "INT"
    );
    // Retained again on the new broker, with the count.
    let mut late = observer(
        &broker,
        "late",
        &["fbbus/devices/conv-a", "fbbus/lines/test/online"],
    )
    .await;
    assert_eq!(
        json_on(&mut late, "fbbus/devices/conv-a", &broker).await["status"],
        "offline"
    );
    assert_eq!(
        next_on(&mut late, "fbbus/lines/test/online", WAIT)
            .await
            .as_deref(),
        Some(&b"0"[..])
    );

    // The device comes back: a newer session, online, and its redeclaration says so.
    let mut diag_sub = observer(&broker, "watch", &["fbbus/diag/conv-a"]).await;
    let mut dev = Dev::connect(broker.port(), 5, "conv-a");
    let rec = wait_record(&broker, "conv-a", "came back", |r| r["status"] == "online").await;
    let s2 = rec["session"].as_u64().unwrap();
    assert!(s2 > s1, "session {s2} after a restart, was {s1}");
    assert_eq!(declare_ok(&mut dev, CONV, &mut diag_sub, &broker).await, s2);
    wait_count(&mut late, "1", &broker).await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn registry_survives_a_broker_shutdown() {
    restart_keeps_the_registry("TERM", "broker shutdown").await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn registry_survives_a_broker_crash() {
    restart_keeps_the_registry("KILL", "broker restart").await;
}

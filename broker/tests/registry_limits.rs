//! Issue 21, the device registry's bounds, against the real `fbbus` binary: a new device
//! beyond `[fb] max_devices` or `max_devices_per_identity` is refused with its reason on
//! `fbbus/diag/<id>` and counted while the others work on; offline devices expire after
//! `[fb] forget_offline_after_s`; `DELETE /api/v1/devices/{id}` and
//! `fbbus devices forget` remove a device with its retained record and values and its
//! metric series.

mod common;

use std::io::{Read, Write};
use std::net::TcpStream;
use std::process::{Command, Stdio};
use std::time::{Duration, Instant};

use serde_json::Value;

use common::clients::V4;
use common::fb::*;
use common::raw;
use common::{Broker, Options};

const QUOTA_EXCEEDED: u8 = 0x97;

fn broker(fb: &str) -> Broker {
    Broker::start_with(
        Options {
            extra: format!("[fb]\n{fb}\n"),
            ..Options::default()
        },
        |_| {},
    )
}

/// An MQTT 5 device connected from `source` (a loopback address).
fn device_from(broker: &Broker, source: &str, id: &str) -> Dev {
    let connect = raw::Connect {
        version: 5,
        client_id: id,
        ..Default::default()
    };
    Dev::connect_from(broker, source, &connect)
}

/// Asserts a declaration was refused at `limit`: 0x97, and the reason on its diag topic.
async fn refused_at(dev: &mut Dev, limit: &str, diag_sub: &mut V4, broker: &Broker) {
    assert_eq!(dev.declare(CONV), QUOTA_EXCEEDED, "{} not refused", dev.id);
    let answer = diag(diag_sub, &dev.id, "declaration", broker).await;
    assert_eq!(answer["ok"], false, "{answer}");
    assert_eq!(answer["limit"], limit, "{answer}");
    let why = answer["errors"][0]["error"].as_str().unwrap_or_default();
    assert!(why.contains(&format!("max_{limit}")), "{answer}");
}

/// An HTTP/1.0 request to the admin endpoint: (status, JSON body).
fn admin(broker: &Broker, method: &str, path: &str) -> (u16, Value) {
    let mut s = TcpStream::connect_timeout(&broker.admin, Duration::from_secs(2)).unwrap();
    s.set_read_timeout(Some(Duration::from_secs(5))).unwrap();
    write!(s, "{method} {path} HTTP/1.0\r\nHost: localhost\r\n\r\n").unwrap();
    let mut text = String::new();
    s.read_to_string(&mut text).unwrap();
    let code = text.split_whitespace().nth(1).unwrap().parse().unwrap();
    let body = text.split_once("\r\n\r\n").map_or("", |(_, b)| b);
    let json = serde_json::from_str(body).unwrap_or_else(|e| panic!("{e}: {text}"));
    (code, json)
}

fn device_count(broker: &Broker) -> usize {
    let (_, all) = http_json(broker, "/api/v1/devices");
    all["devices"].as_array().map_or(0, Vec::len)
}

/// Retained messages a new subscriber of `filters` gets within a short window.
async fn retained(broker: &Broker, id: &str, filters: &[&str]) -> Vec<(String, Vec<u8>)> {
    let mut late = observer(broker, id, filters).await;
    drain(&mut late, QUIET).await
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn devices_beyond_max_devices_are_refused_and_the_others_work_on() {
    let broker = broker("max_devices = 20\nmax_devices_per_identity = 1000");
    let mut diag_sub = observer(&broker, "watch", &["fbbus/diag/#"]).await;
    // The flood: CONNECT, declare, DISCONNECT, each with a fresh id.
    for i in 0..20 {
        let mut dev = Dev::connect(broker.port(), 5, &format!("dev-{i}"));
        assert_eq!(dev.declare(CONV), 0, "dev-{i}");
        dev.disconnect();
    }
    for i in 20..30 {
        let mut dev = Dev::connect(broker.port(), 5, &format!("dev-{i}"));
        refused_at(&mut dev, "devices", &mut diag_sub, &broker).await;
        // The connection is served on: it is only no device.
        dev.disconnect();
    }
    assert_metric(
        &broker,
        "fbbus_limit_refusals_total{limit=\"devices\"}",
        10.0,
    );
    assert_eq!(
        broker.metric("fbbus_limit_refusals_total{limit=\"devices\"}"),
        10.0
    );
    assert_eq!(device_count(&broker), 20);
    assert!(record(&broker, "dev-25").is_none());
    // Logged, not once per refusal.
    assert_eq!(
        broker.log_text().matches("new device refused").count(),
        1,
        "{}",
        broker.log_text()
    );

    // Known devices go on: one reconnects and publishes on its declared port, another
    // declares again.
    let mut values = observer(&broker, "values", &["fb/dev-3/#"]).await;
    let mut known = Dev::connect(broker.port(), 5, "dev-3");
    wait_record(&broker, "dev-3", "came back", |r| r["status"] == "online").await;
    assert_eq!(known.publish("fb/dev-3/CONV/POSITION", b"7"), 0);
    assert_eq!(
        next_on(
            &mut values,
            "fb/dev-3/CONV/POSITION",
            Duration::from_secs(5)
        )
        .await,
        Some(b"7".to_vec())
    );
    let mut again = Dev::connect(broker.port(), 5, "dev-4");
    declare_ok(&mut again, CONV, &mut diag_sub, &broker).await;
    assert_eq!(device_count(&broker), 20);
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn devices_beyond_max_devices_per_identity_are_refused_per_address() {
    let broker = broker("max_devices_per_identity = 3");
    let mut diag_sub = observer(&broker, "watch", &["fbbus/diag/#"]).await;
    for i in 0..3 {
        let mut dev = device_from(&broker, "127.0.0.1", &format!("one-{i}"));
        declare_ok(&mut dev, CONV, &mut diag_sub, &broker).await;
        dev.disconnect();
    }
    let mut fourth = device_from(&broker, "127.0.0.1", "one-3");
    refused_at(&mut fourth, "devices_per_identity", &mut diag_sub, &broker).await;
    assert_metric(
        &broker,
        "fbbus_limit_refusals_total{limit=\"devices_per_identity\"}",
        1.0,
    );
    assert_eq!(
        broker.metric("fbbus_limit_refusals_total{limit=\"devices\"}"),
        0.0
    );
    // Another address registers its own; a known device declares again from anywhere.
    let mut other = device_from(&broker, "127.0.0.2", "two-0");
    declare_ok(&mut other, CONV, &mut diag_sub, &broker).await;
    let mut moved = device_from(&broker, "127.0.0.2", "one-0");
    declare_ok(&mut moved, CONV, &mut diag_sub, &broker).await;
    // Forgetting one of the first address's devices gives it a place again.
    assert_eq!(admin(&broker, "DELETE", "/api/v1/devices/one-1").0, 200);
    declare_ok(&mut fourth, CONV, &mut diag_sub, &broker).await;
    assert_eq!(device_count(&broker), 4);
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn offline_devices_expire_with_their_retained_record() {
    let broker = broker("forget_offline_after_s = 1");
    let mut diag_sub = observer(&broker, "watch", &["fbbus/diag/#"]).await;
    let mut records = observer(&broker, "records", &["fbbus/devices/#"]).await;
    let mut stays = Dev::connect(broker.port(), 5, "stays");
    declare_ok(&mut stays, CONV, &mut diag_sub, &broker).await;
    let mut leaves = Dev::connect(broker.port(), 5, "leaves");
    declare_ok(&mut leaves, CONV, &mut diag_sub, &broker).await;
    leaves.disconnect();
    let left = Instant::now();

    // The record's topic is cleared (an empty retained message), then the record is gone.
    let deadline = Instant::now() + Duration::from_secs(10);
    loop {
        let remaining = deadline.saturating_duration_since(Instant::now());
        match next_on(&mut records, "fbbus/devices/leaves", remaining).await {
            Some(p) if p.is_empty() => break,
            Some(_) => continue,
            None => panic!("never forgotten\n{}", broker.log_text()),
        }
    }
    // Offline from when the broker saw the end, a moment before the client saw its close.
    assert!(left.elapsed() >= Duration::from_millis(900), "too early");
    assert!(record(&broker, "leaves").is_none());
    assert_metric(
        &broker,
        "fbbus_registry_forgotten_total{reason=\"expired\"}",
        1.0,
    );
    // A new subscriber gets the record of the online device only.
    let topics: Vec<String> = retained(&broker, "late", &["fbbus/devices/#"])
        .await
        .into_iter()
        .map(|(t, _)| t)
        .collect();
    assert_eq!(topics, ["fbbus/devices/stays"]);
    tokio::time::sleep(Duration::from_millis(1500)).await;
    assert_eq!(record(&broker, "stays").unwrap()["status"], "online");
    assert!(broker.log_text().contains("device forgotten"));
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn delete_forgets_an_offline_device_with_its_retained_values_and_series() {
    let broker = broker("");
    let mut diag_sub = observer(&broker, "watch", &["fbbus/diag/#"]).await;
    let mut dev = Dev::connect(broker.port(), 5, "old-plc");
    declare_ok(&mut dev, CONV, &mut diag_sub, &broker).await;
    assert_eq!(dev.publish_retained("fb/old-plc/CONV/POSITION", b"42"), 0);
    // An ill-typed value: a series labelled with the device.
    assert_eq!(dev.publish("fb/old-plc/CONV/POSITION", b"\"x\""), REFUSED);
    let series = rejected_series("old-plc", "CONV.POSITION", "payload_format_invalid");
    assert_metric(&broker, &series, 1.0);
    let mut records = observer(&broker, "records", &["fbbus/devices/old-plc"]).await;
    let before = retained(
        &broker,
        "before",
        &["fbbus/devices/old-plc", "fb/old-plc/#"],
    )
    .await;
    let topics: Vec<&str> = before.iter().map(|(t, _)| t.as_str()).collect();
    assert!(
        topics.contains(&"fbbus/devices/old-plc") && topics.contains(&"fb/old-plc/CONV/POSITION"),
        "{topics:?}"
    );

    let (code, body) = admin(&broker, "DELETE", "/api/v1/devices/old-plc");
    assert_eq!(code, 409, "{body}");
    assert!(body["error"].as_str().unwrap().contains("online"), "{body}");
    let (code, body) = admin(&broker, "DELETE", "/api/v1/devices/nobody");
    assert_eq!(code, 404, "{body}");
    assert!(body["error"].as_str().unwrap().contains("nobody"), "{body}");

    dev.disconnect();
    wait_record(&broker, "old-plc", "went offline", |r| {
        r["status"] == "offline"
    })
    .await;
    let (code, body) = admin(&broker, "DELETE", "/api/v1/devices/old-plc");
    assert_eq!(code, 200, "{body}");
    assert!(record(&broker, "old-plc").is_none());
    // The subscriber of the record topic sees it cleared; a new subscriber gets nothing.
    let deadline = Instant::now() + Duration::from_secs(5);
    loop {
        let remaining = deadline.saturating_duration_since(Instant::now());
        match next_on(&mut records, "fbbus/devices/old-plc", remaining).await {
            Some(p) if p.is_empty() => break,
            Some(_) => continue,
            None => panic!("record topic not cleared\n{}", broker.log_text()),
        }
    }
    let after = retained(&broker, "after", &["fbbus/devices/old-plc", "fb/old-plc/#"]).await;
    assert!(after.is_empty(), "{after:?}");
    let metrics = broker.metrics();
    assert!(!metrics.contains("device=\"old-plc\""), "{metrics}");
    assert_eq!(
        broker.metric("fbbus_registry_forgotten_total{reason=\"admin\"}"),
        1.0
    );
    assert_eq!(
        admin(&broker, "DELETE", "/api/v1/devices/old-plc").0,
        404,
        "forgotten once"
    );
    // It may come back, as a new device.
    let mut back = Dev::connect(broker.port(), 5, "old-plc");
    declare_ok(&mut back, CONV, &mut diag_sub, &broker).await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn fbbus_devices_forget_removes_a_device() {
    let broker = broker("");
    let mut diag_sub = observer(&broker, "watch", &["fbbus/diag/#"]).await;
    let mut on = Dev::connect(broker.port(), 4, "on-line");
    declare_ok(&mut on, CONV, &mut diag_sub, &broker).await;
    let mut off = Dev::connect(broker.port(), 4, "off-line");
    declare_ok(&mut off, CONV, &mut diag_sub, &broker).await;
    off.disconnect();
    wait_record(&broker, "off-line", "went offline", |r| {
        r["status"] == "offline"
    })
    .await;

    let admin = broker.admin.to_string();
    let forget = |id: &str| {
        let mut cmd = Command::new(common::fbbus_bin());
        cmd.args(["devices", "forget", id, "--admin", &admin])
            .stdin(Stdio::null());
        common::run(&mut cmd, Duration::from_secs(15))
    };
    let (ok, out, err) = forget("off-line");
    assert!(ok, "fbbus devices forget failed: {err}");
    assert!(
        out.contains("off-line") && out.contains("forgotten"),
        "{out}"
    );
    assert!(record(&broker, "off-line").is_none());
    let (ok, _, err) = forget("off-line");
    assert!(!ok);
    assert!(err.contains("no device off-line"), "{err}");
    let (ok, _, err) = forget("on-line");
    assert!(!ok);
    assert!(err.contains("online"), "{err}");
    assert!(record(&broker, "on-line").is_some());
    // `fbbus devices ID` still shows one device.
    let mut cmd = Command::new(common::fbbus_bin());
    cmd.args(["devices", "--admin", &admin, "on-line"])
        .stdin(Stdio::null());
    let (ok, out, err) = common::run(&mut cmd, Duration::from_secs(15));
    assert!(ok && out.contains("on-line"), "{out} {err}");
}

/// A FORTE-like device recognised by its client id, and a DINASORE-like one recognised by
/// its topics only (as in `profiles.rs`, smaller).
const FORTE_PROFILE: &str = r#"
device = "conv2"
runtime = "forte"
[speaks]
encoding = "fbdk"
[interface.fbs.CONV.data_out]
POSITION = "INT"
[[topics]]
topic = "line1/conv2/position"
port = "CONV.POSITION"
"#;

const TOPICS_ONLY_PROFILE: &str = r#"
device = "conv3"
runtime = "dinasore"
identity = { topics_only = true }
[speaks]
encoding = "dinasore"
[interface.fbs.CONV.data_out]
SPEED = "REAL"
[[topics]]
topic = "line1/conv3/speed"
port = "CONV.SPEED"
"#;

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn profiled_devices_are_new_devices_too() {
    let broker = Broker::start_with(
        Options {
            extra: "[fb]\nprofiles_dir = \"profiles\"\nmax_devices = 1\n".into(),
            ..Options::default()
        },
        |dir| {
            let profiles = dir.join("profiles");
            std::fs::create_dir(&profiles).unwrap();
            std::fs::write(profiles.join("conv2.toml"), FORTE_PROFILE).unwrap();
            std::fs::write(profiles.join("conv3.toml"), TOPICS_ONLY_PROFILE).unwrap();
        },
    );
    let mut diag_sub = observer(&broker, "watch", &["fbbus/diag/#"]).await;
    let mut plain = Dev::connect(broker.port(), 5, "plain");
    declare_ok(&mut plain, CONV, &mut diag_sub, &broker).await;

    // Recognised at CONNECT: told on its diag topic, and no device on this connection.
    let mut forte = Dev::connect(broker.port(), 5, "conv2");
    let answer = diag(&mut diag_sub, "conv2", "declaration", &broker).await;
    assert_eq!(
        (answer["ok"].clone(), answer["limit"].clone()),
        (false.into(), "devices".into())
    );
    assert!(record(&broker, "conv2").is_none());
    assert_eq!(
        forte.publish("line1/conv2/position", &[0x43, 0, 7]),
        NOT_AUTHORIZED
    );
    forte.disconnect();

    // Recognised by its topics: its first publication is refused at the limit.
    let mut dinasore = Dev::connect(broker.port(), 5, "random-7f3a");
    let speed = br#"{"SPEED": 1.5}"#;
    assert_eq!(dinasore.publish("line1/conv3/speed", speed), QUOTA_EXCEEDED);
    let answer = diag(&mut diag_sub, "conv3", "declaration", &broker).await;
    assert_eq!(answer["limit"], "devices", "{answer}");
    assert!(record(&broker, "conv3").is_none());
    assert_metric(
        &broker,
        "fbbus_limit_refusals_total{limit=\"devices\"}",
        2.0,
    );

    // With a place free, the profiled device is registered at its next CONNECT.
    plain.disconnect();
    wait_record(&broker, "plain", "went offline", |r| {
        r["status"] == "offline"
    })
    .await;
    assert_eq!(admin(&broker, "DELETE", "/api/v1/devices/plain").0, 200);
    let _forte = Dev::connect(broker.port(), 5, "conv2");
    wait_record(&broker, "conv2", "registered", |r| r["status"] == "online").await;
    assert_eq!(dinasore.publish("line1/conv3/speed", speed), QUOTA_EXCEEDED);
}

//! One bus across lines: real `fbbus` brokers linked by their zenoh bridges on loopback.
//!
//! Each test starts two or three line brokers (child processes) with `[bridge]` sections on
//! free loopback ports, devices and observers as real MQTT clients, and checks what the
//! issue promises: location transparency with the device's types, QoS 1 across the hop,
//! retained messages across lines, exactly one delivery in a chain and a full mesh, and
//! remote devices marked unreachable when their line stops and back when it returns.
//! Every wait is bounded; multicast scouting stays off (the default).

mod common;

use std::net::SocketAddr;
use std::time::{Duration, Instant};

use serde_json::{json, Value};

use common::clients::{V4, WAIT};
use common::{free_port, http_get, Broker};

const CONV: &str = r#"{"fbs": {"CONV": {
    "type": "CONVEYOR",
    "events_out": {"MOVED": {"with": ["POSITION"]}},
    "data_out": {"POSITION": "INT", "ID": "STRING"}
}}}"#;

/// How long zenoh has to carry declarations and liveliness between lines on loopback.
const PROPAGATION: Duration = Duration::from_secs(10);

/// A line: its broker and the zenoh endpoint it listens on.
struct Line {
    broker: Broker,
    name: String,
    zenoh: String,
}

impl Line {
    /// Starts line `name`, its bridge listening on a free port and connecting to `connect`.
    fn start(name: &str, connect: &[&str], extra: &str) -> Line {
        let zenoh = format!("tcp/127.0.0.1:{}", free_port());
        Line::start_on(name, &zenoh, connect, extra, None)
    }

    fn start_on(
        name: &str,
        zenoh: &str,
        connect: &[&str],
        extra: &str,
        ports: Option<(SocketAddr, SocketAddr)>,
    ) -> Line {
        let dir = tempfile::tempdir().unwrap();
        let (mqtt, admin) = ports.unwrap_or_else(|| {
            (
                format!("127.0.0.1:{}", free_port()).parse().unwrap(),
                format!("127.0.0.1:{}", free_port()).parse().unwrap(),
            )
        });
        let config = dir.path().join("fbbus.toml");
        std::fs::write(
            &config,
            format!(
                "[broker]\nline = \"{name}\"\n\n\
                 [[listener]]\nname = \"main\"\nbind = \"{mqtt}\"\n\n\
                 [admin]\nbind = \"{admin}\"\n\n\
                 [log]\nlevel = \"info,rumqttd=warn,zenoh=warn\"\n\n\
                 [bridge]\nlisten = [\"{zenoh}\"]\nconnect = {connect:?}\nlease_ms = 1000\n{extra}\n",
            ),
        )
        .unwrap();
        Line {
            broker: Broker::spawn(dir, config, mqtt, admin),
            name: name.to_owned(),
            zenoh: zenoh.to_owned(),
        }
    }

    fn port(&self) -> u16 {
        self.broker.port()
    }

    /// The registry record of `id` as this line's admin endpoint serves it.
    fn record(&self, id: &str) -> Option<Value> {
        let (code, body) = http_get(self.broker.admin, &format!("/api/v1/devices/{id}"))?;
        (code == 200).then(|| serde_json::from_str(&body).unwrap())
    }

    /// Waits until this line's registry shows `id` with `status`; returns the record.
    fn wait_record(&self, id: &str, status: &str, within: Duration) -> Value {
        let deadline = Instant::now() + within;
        loop {
            let record = self.record(id);
            if record.as_ref().is_some_and(|r| r["status"] == status) {
                return record.unwrap();
            }
            if Instant::now() > deadline {
                panic!(
                    "line {}: device {id} not {status} within {within:?}: {record:?}\n{}",
                    self.name,
                    self.broker.log_text()
                );
            }
            std::thread::sleep(Duration::from_millis(50));
        }
    }

    /// Waits until `series` reaches `min` on this line.
    fn wait_metric(&self, series: &str, min: f64) {
        let deadline = Instant::now() + PROPAGATION;
        while self.broker.metric(series) < min {
            assert!(
                Instant::now() < deadline,
                "line {}: {series} < {min}\n{}",
                self.name,
                self.broker.metrics()
            );
            std::thread::sleep(Duration::from_millis(20));
        }
    }
}

/// A device on `line`: connected, interface declared and accepted.
async fn device(line: &Line, id: &str) -> V4 {
    let mut dev = V4::connect(line.port(), id, None).await.unwrap();
    dev.subscribe(&format!("fbbus/diag/{id}")).await;
    dev.client
        .publish(
            format!("fbbus/declare/{id}"),
            rumqttc::QoS::AtLeastOnce,
            false,
            CONV,
        )
        .await
        .unwrap();
    let answer = dev.next_publish(WAIT).await.expect("declaration answer");
    let answer: Value = serde_json::from_slice(&answer.payload).unwrap();
    assert_eq!(answer["ok"], true, "{answer}");
    dev
}

async fn publish(dev: &V4, topic: &str, payload: String, retain: bool) {
    dev.client
        .publish(topic, rumqttc::QoS::AtLeastOnce, retain, payload)
        .await
        .unwrap();
}

/// Subscribes on `line` and waits until every line in `exporters` subscribed for it.
async fn observe(line: &Line, id: &str, filters: &[&str], exporters: &[&Line]) -> V4 {
    let before: Vec<f64> = exporters
        .iter()
        .map(|l| l.broker.metric("fbbus_bridge_remote_subscriptions"))
        .collect();
    let mut obs = V4::connect(line.port(), id, None).await.unwrap();
    for f in filters {
        obs.subscribe(f).await;
    }
    for (l, before) in exporters.iter().zip(before) {
        l.wait_metric("fbbus_bridge_remote_subscriptions", before + 1.0);
    }
    // The exporter's router subscription is in place within a router turn.
    tokio::time::sleep(Duration::from_millis(100)).await;
    obs
}

/// Every publish received until `quiet` passes without one.
async fn drain(obs: &mut V4, quiet: Duration) -> Vec<rumqttc::Publish> {
    let mut out = Vec::new();
    while let Some(p) = obs.next_publish(quiet).await {
        out.push(p);
    }
    out
}

fn positions(received: &[rumqttc::Publish], topic: &str) -> Vec<i64> {
    received
        .iter()
        .filter(|p| p.topic == topic)
        .map(|p| serde_json::from_slice::<Value>(&p.payload).unwrap())
        .map(|v| v.as_i64().unwrap())
        .collect()
}

// ---------------------------------------------------------------- two lines

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_remote_device_is_subscribed_to_as_if_it_were_local() {
    let a = Line::start("line-a", &[], "");
    let b = Line::start("line-b", &[&a.zenoh], "");
    let dev = device(&a, "conv-a").await;

    // Line B's registry learns the device, its line and its interface.
    let record = b.wait_record("conv-a", "online", PROPAGATION);
    assert_eq!(record["line"], "line-a");
    assert_eq!(
        record["interface"]["fbs"]["CONV"]["data_out"]["POSITION"],
        "INT"
    );
    // A retained value published before anyone on B listened.
    publish(&dev, "fb/conv-a/CONV/ID", json!("belt-7").to_string(), true).await;
    tokio::time::sleep(Duration::from_millis(200)).await;

    let mut obs = observe(
        &b,
        "watch-b",
        &["fb/conv-a/CONV/#", "dinasore/conv-a/CONV/MOVED"],
        &[&a],
    )
    .await;
    let retained = obs
        .next_publish(WAIT)
        .await
        .expect("retained value from line A");
    assert_eq!(retained.topic, "fb/conv-a/CONV/ID");
    assert_eq!(&retained.payload[..], b"\"belt-7\"");

    const N: i64 = 200;
    for i in 0..N {
        publish(&dev, "fb/conv-a/CONV/POSITION", i.to_string(), false).await;
        if i % 50 == 0 {
            let event = json!({"seq": i, "ts": 1, "data": {"POSITION": i}});
            publish(&dev, "fb/conv-a/CONV/MOVED", event.to_string(), false).await;
        }
    }
    let received = drain(&mut obs, Duration::from_millis(1500)).await;
    assert!(
        received.iter().all(|p| p.topic != "fb/conv-a/CONV/ID"),
        "the retained value once"
    );
    assert_eq!(
        positions(&received, "fb/conv-a/CONV/POSITION"),
        (0..N).collect::<Vec<_>>(),
        "every value once, in order"
    );
    assert!(received
        .iter()
        .filter(|p| p.topic.contains("POSITION"))
        .all(|p| p.qos == rumqttc::QoS::AtLeastOnce));
    // Typed across the hop: line B re-encodes events for its DINASORE subscriber from the
    // declaration it learned from line A.
    let dinasore: Vec<Value> = received
        .iter()
        .filter(|p| p.topic == "dinasore/conv-a/CONV/MOVED")
        .map(|p| serde_json::from_slice(&p.payload).unwrap())
        .collect();
    assert_eq!(dinasore.len(), 4, "{received:?}");
    assert_eq!(dinasore[1], json!({"POSITION": 50}));
    assert_eq!(
        received
            .iter()
            .filter(|p| p.topic == "fb/conv-a/CONV/MOVED")
            .count(),
        4
    );

    // Exactly what B asked for crossed: the retained value by query, the rest live.
    let exported = a
        .broker
        .metric("fbbus_bridge_messages_total{direction=\"export\"}");
    assert_eq!(exported, (N + 4) as f64, "{}", a.broker.metrics());
    assert_eq!(
        b.broker
            .metric("fbbus_bridge_messages_total{direction=\"import\"}"),
        (N + 4 + 1) as f64
    );
}

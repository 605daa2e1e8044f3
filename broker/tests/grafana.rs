//! Issue 37: the Grafana dashboard in `deploy/grafana/fbbus.json` loads and shows real
//! data. Its JSON has what Grafana's import needs (the data source input, unique panel
//! ids, a grid position within 24 columns, a query and a refId per target), and every
//! metric its queries use is in a real broker's `/metrics`: two lines linked by the bus,
//! with the Sparkplug view on and persistence, driven until each series the board plots
//! exists (a typed refusal, a will, a refused login, ...). No Grafana installs here, so
//! the PromQL itself is not evaluated: the metric names and their labels are.

mod common;

use std::collections::{BTreeMap, BTreeSet};

use common::bus::{self, Line};
use common::clients::V4;
use common::raw::{self, Connect, RawClient};
use serde_json::Value;

fn dashboard() -> Value {
    let path = concat!(env!("CARGO_MANIFEST_DIR"), "/../deploy/grafana/fbbus.json");
    let text = std::fs::read_to_string(path).expect("deploy/grafana/fbbus.json");
    serde_json::from_str(&text).expect("the dashboard is JSON")
}

/// Every `expr` of the dashboard's targets and template variables.
fn queries(dash: &Value) -> Vec<String> {
    let mut out = Vec::new();
    for panel in dash["panels"].as_array().expect("panels") {
        for target in panel["targets"].as_array().into_iter().flatten() {
            out.push(target["expr"].as_str().expect("expr").to_owned());
        }
    }
    for var in dash["templating"]["list"].as_array().into_iter().flatten() {
        out.push(var["definition"].as_str().expect("definition").to_owned());
    }
    out
}

/// The metric names a query uses, and the label names it groups by or matches on.
fn names_and_labels(query: &str) -> (BTreeSet<String>, BTreeSet<String>) {
    let mut names = BTreeSet::new();
    let mut labels = BTreeSet::new();
    let mut i = 0;
    while let Some(at) = query.get(i..).and_then(|rest| rest.find("fbbus_")) {
        let start = i + at;
        let end = query[start..]
            .find(|c: char| !(c.is_ascii_alphanumeric() || c == '_'))
            .map_or(query.len(), |n| start + n);
        names.insert(query[start..end].to_owned());
        i = end;
    }
    // `by (a, b)` and `{a=~"..."}`: label names.
    for (open, close) in [("by (", ")"), ("{", "}")] {
        let mut rest = query;
        while let Some(at) = rest.find(open) {
            let inner = &rest[at + open.len()..];
            let end = inner.find(close).unwrap_or(inner.len());
            for part in inner[..end].split(',') {
                let label: String = part
                    .trim()
                    .chars()
                    .take_while(|c| c.is_ascii_alphanumeric() || *c == '_')
                    .collect();
                if !label.is_empty() {
                    labels.insert(label);
                }
            }
            rest = &inner[end..];
        }
    }
    (names, labels)
}

#[test]
fn the_dashboard_has_what_grafana_imports() {
    let dash = dashboard();
    for key in ["title", "uid"] {
        assert!(dash[key].as_str().is_some_and(|s| !s.is_empty()), "{key}");
    }
    assert!(dash["schemaVersion"].as_u64().is_some_and(|v| v >= 30));
    let inputs: BTreeSet<&str> = dash["__inputs"]
        .as_array()
        .expect("__inputs")
        .iter()
        .filter_map(|i| i["name"].as_str())
        .collect();
    assert!(inputs.contains("DS_PROMETHEUS"), "{inputs:?}");
    let panels = dash["panels"].as_array().expect("panels");
    assert!(panels.len() >= 20, "{} panels", panels.len());
    let mut ids = BTreeSet::new();
    let mut kinds = BTreeSet::new();
    for p in panels {
        let title = p["title"].as_str().expect("a title");
        assert!(
            ids.insert(p["id"].as_u64().expect("an id")),
            "{title}: id twice"
        );
        let kind = p["type"].as_str().expect("a type");
        kinds.insert(kind.to_owned());
        let g = &p["gridPos"];
        let (x, w, h) = (g["x"].as_u64(), g["w"].as_u64(), g["h"].as_u64());
        let (Some(x), Some(w), Some(_), Some(h)) = (x, w, g["y"].as_u64(), h) else {
            panic!("{title}: gridPos {g}");
        };
        assert!(x + w <= 24 && w > 0 && h > 0, "{title}: gridPos {g}");
        if kind == "row" {
            continue;
        }
        assert_eq!(p["datasource"]["uid"], "${DS_PROMETHEUS}", "{title}");
        let targets = p["targets"].as_array().expect("targets");
        assert!(!targets.is_empty(), "{title}: no query");
        let refs: BTreeSet<&str> = targets.iter().filter_map(|t| t["refId"].as_str()).collect();
        assert_eq!(refs.len(), targets.len(), "{title}: refIds");
        for t in targets {
            assert_eq!(t["datasource"]["uid"], "${DS_PROMETHEUS}", "{title}");
            assert!(
                t["expr"].as_str().is_some_and(|e| e.contains("fbbus_")),
                "{title}"
            );
        }
    }
    // Every panel type the board uses is declared in `__requires`.
    let required: BTreeSet<&str> = dash["__requires"]
        .as_array()
        .expect("__requires")
        .iter()
        .filter(|r| r["type"] == "panel")
        .filter_map(|r| r["id"].as_str())
        .collect();
    for kind in &kinds {
        assert!(
            required.contains(kind.as_str()),
            "panel type {kind} not in __requires"
        );
    }
}

/// `name` → the label names its series carry, from a `/metrics` text (histograms as
/// their `_bucket`, `_sum`, `_count` series).
fn series(text: &str) -> BTreeMap<String, BTreeSet<String>> {
    let mut out: BTreeMap<String, BTreeSet<String>> = BTreeMap::new();
    for line in text
        .lines()
        .filter(|l| !l.starts_with('#') && !l.is_empty())
    {
        let name_end = line.find(['{', ' ']).unwrap_or(line.len());
        let labels = out.entry(line[..name_end].to_owned()).or_default();
        if let Some(inner) = line.get(name_end..).and_then(|l| l.strip_prefix('{')) {
            for pair in inner.split("\",") {
                if let Some((k, _)) = pair.split_once('=') {
                    labels.insert(k.trim_start_matches([',', ' ']).to_owned());
                }
            }
        }
    }
    out
}

/// Every metric the board's queries use is a series of a real line, with the labels the
/// queries group by (`instance` is Prometheus's own).
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn every_metric_the_dashboard_uses_is_in_a_real_metrics_page() {
    let a = Line::plain("line-a", &[], "[sparkplug]\nenabled = true\n");
    let b = Line::plain("line-b", &[&a.zenoh], "");
    let broker = &a.broker;

    // A device declared and publishing, one value refused, a will.
    let mut dev = V4::connect(broker.port(), "conv-1", None).await.unwrap();
    dev.declare("conv-1", bus::CONV).await;
    for payload in ["3", "\"three\""] {
        dev.client
            .publish(
                "fb/conv-1/CONV/POSITION",
                rumqttc::QoS::AtLeastOnce,
                false,
                payload,
            )
            .await
            .unwrap();
    }
    // Another line's device, read here: the bus carries it.
    let remote = bus::device_with(&b, "remote-1", bus::CONV).await;
    a.wait_record("remote-1", "online", bus::PROPAGATION);
    let mut reader = V4::connect(broker.port(), "reader", None).await.unwrap();
    reader.subscribe("fb/remote-1/#").await;
    bus::publish(&remote, "fb/remote-1/CONV/POSITION", "5".into(), false).await;
    reader
        .next_publish(bus::PROPAGATION)
        .await
        .expect("the bus carried it");
    // A Sparkplug host reading; a malformed packet. (Counters of a closed set of reasons
    // exist at 0 from the start, so a quiet line's board shows 0, not "no data".)
    let mut host = V4::connect(broker.port(), "scada", None).await.unwrap();
    host.subscribe("spBv1.0/#").await;
    let mut bad = RawClient::connect(broker.port());
    assert_eq!(
        bad.handshake(&Connect {
            version: 4,
            client_id: "bad",
            ..Default::default()
        }),
        0
    );
    bad.send(&raw::packet(0x30, &[0xff]));
    assert!(bad.closed_by_broker());
    drop(dev);
    a.wait_record("conv-1", "offline", bus::PROPAGATION);
    tokio::time::sleep(std::time::Duration::from_millis(500)).await;

    let metrics = broker.metrics();
    let have = series(&metrics);
    let mut missing = Vec::new();
    for query in queries(&dashboard()) {
        let (names, labels) = names_and_labels(&query);
        for name in names {
            let Some(found) = have.get(&name) else {
                missing.push(format!("{name} (in {query})"));
                continue;
            };
            for label in labels.iter().filter(|l| *l != "instance" && *l != "le") {
                if !found.contains(label) {
                    missing.push(format!("{name} has no label {label} (in {query})"));
                }
            }
        }
    }
    assert!(
        missing.is_empty(),
        "the dashboard uses what /metrics does not have:\n{}\n\n{metrics}",
        missing.join("\n")
    );
    drop((remote, reader, host, b));
}

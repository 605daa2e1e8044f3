//! Issue 37: the Grafana dashboard in `deploy/grafana/fbbus.json` loads and shows real
//! data. Its JSON has what Grafana's import needs (the data source input, unique panel
//! ids, a grid position within 24 columns that no other panel overlaps, a query and a
//! refId per target, a unit per panel), and every metric its queries use is in a real
//! broker's `/metrics`: two lines linked by the bus, with the Sparkplug view on and
//! persistence, driven until each series the board plots exists (a typed refusal, a
//! malformed packet, a device of another line, ...). The labels the queries match on,
//! group by and name in their legends are the series' labels, an exact label value
//! (`reason="slow_consumer"`) is one of theirs, counters are only read through `rate` or
//! `increase` and gauges never are. No Grafana installs here, so the PromQL itself is not
//! evaluated: the metric names, types and labels are.

mod common;

use std::collections::{BTreeMap, BTreeSet};
use std::time::{Duration, Instant};

use common::bus::{self, Line};
use common::clients::V4;
use common::raw::{self, Connect, RawClient};
use serde_json::Value;

const DS: &str = "${DS_PROMETHEUS}";

fn dashboard() -> Value {
    let path = concat!(env!("CARGO_MANIFEST_DIR"), "/../deploy/grafana/fbbus.json");
    let text = std::fs::read_to_string(path).expect("deploy/grafana/fbbus.json");
    serde_json::from_str(&text).expect("the dashboard is JSON")
}

/// One query of the board: where it is, its PromQL, the labels its legend names.
struct Query {
    at: String,
    expr: String,
    legend: Vec<String>,
    /// A panel's target (filtered by `$instance`), not a template variable.
    target: bool,
}

/// Every `expr` of the dashboard's targets and every query of its template variables.
fn queries(dash: &Value) -> Vec<Query> {
    let mut out = Vec::new();
    for panel in dash["panels"].as_array().expect("panels") {
        for target in panel["targets"].as_array().into_iter().flatten() {
            let legend = target["legendFormat"].as_str().unwrap_or("");
            out.push(Query {
                at: format!("panel {}/{}", panel["title"], target["refId"]),
                expr: target["expr"].as_str().expect("expr").to_owned(),
                legend: legend
                    .split("{{")
                    .skip(1)
                    .filter_map(|s| s.split_once("}}"))
                    .map(|(label, _)| label.trim().to_owned())
                    .collect(),
                target: true,
            });
        }
    }
    for var in dash["templating"]["list"].as_array().into_iter().flatten() {
        let query = match &var["query"] {
            Value::String(s) => s.as_str(),
            q => q["query"].as_str().unwrap_or(""),
        };
        for expr in [query, var["definition"].as_str().unwrap_or("")] {
            out.push(Query {
                at: format!("variable {}", var["name"]),
                expr: expr.to_owned(),
                legend: Vec::new(),
                target: false,
            });
        }
    }
    out
}

/// `label op "value"` inside a selector's braces.
#[derive(Debug)]
struct Matcher {
    label: String,
    op: String,
    value: String,
}

/// One metric a query reads: its name, its selector's matchers, whether `rate(` or
/// `increase(` reads it.
#[derive(Debug)]
struct Use {
    name: String,
    matchers: Vec<Matcher>,
    as_counter: bool,
}

/// What a query uses: its metrics, the labels of its `by (...)` clauses, whether it
/// aggregates (then only those labels are left for the legend).
struct Parsed {
    uses: Vec<Use>,
    by: BTreeSet<String>,
    aggregates: bool,
}

fn ident(c: char) -> bool {
    c.is_ascii_alphanumeric() || c == '_'
}

fn matchers(inner: &str) -> Vec<Matcher> {
    let mut out = Vec::new();
    let mut rest = inner;
    loop {
        rest = rest.trim_start_matches([',', ' ']);
        if rest.is_empty() {
            return out;
        }
        let label_end = rest.find(|c: char| !ident(c)).unwrap_or(rest.len());
        let label = &rest[..label_end];
        rest = rest[label_end..].trim_start();
        let op_end = rest.find('"').expect("a quoted matcher value");
        let op = rest[..op_end].trim();
        // The closing quote: the first not escaped (`\"` in a label value).
        let mut escaped = false;
        let value_end = op_end
            + 1
            + rest[op_end + 1..]
                .find(|c| {
                    let end = c == '"' && !escaped;
                    escaped = c == '\\' && !escaped;
                    end
                })
                .expect("a closing quote");
        out.push(Matcher {
            label: label.to_owned(),
            op: op.to_owned(),
            value: rest[op_end + 1..value_end].to_owned(),
        });
        rest = &rest[value_end + 1..];
    }
}

fn parse(expr: &str) -> Parsed {
    let mut uses = Vec::new();
    let mut i = 0;
    while let Some(at) = expr[i..].find("fbbus_") {
        let start = i + at;
        let end = expr[start..]
            .find(|c: char| !ident(c))
            .map_or(expr.len(), |n| start + n);
        // A name, not the tail of another identifier.
        if expr[..start].ends_with(ident) {
            i = end;
            continue;
        }
        let before = expr[..start].trim_end();
        let as_counter = before.ends_with("rate(") || before.ends_with("increase(");
        let mut found = Vec::new();
        i = end;
        if let Some(inner) = expr[end..].strip_prefix('{') {
            let close = inner.find('}').expect("a closing brace");
            found = matchers(&inner[..close]);
            i = end + 1 + close + 1;
        }
        uses.push(Use {
            name: expr[start..end].to_owned(),
            matchers: found,
            as_counter,
        });
    }
    let mut by = BTreeSet::new();
    for open in ["by (", "by("] {
        let mut rest = expr;
        while let Some(at) = rest.find(open) {
            let inner = &rest[at + open.len()..];
            let end = inner.find(')').expect("by (...)");
            by.extend(
                inner[..end]
                    .split(',')
                    .map(|l| l.trim().to_owned())
                    .filter(|l| !l.is_empty()),
            );
            rest = &inner[end..];
        }
    }
    let aggregates = [
        "sum",
        "avg",
        "min",
        "max",
        "count",
        "topk",
        "bottomk",
        "histogram_quantile",
    ]
    .iter()
    .any(|f| {
        expr.match_indices(f).any(|(at, _)| {
            !expr[..at].ends_with(ident)
                && expr[at + f.len()..].trim_start().starts_with(['(', 'b'])
        })
    });
    Parsed {
        uses,
        by,
        aggregates,
    }
}

#[test]
fn the_dashboard_has_what_grafana_imports() {
    let dash = dashboard();
    for key in ["title", "uid"] {
        assert!(dash[key].as_str().is_some_and(|s| !s.is_empty()), "{key}");
    }
    assert_eq!(dash["schemaVersion"], 39);

    // Every `${DS_...}` anywhere in the board is an input of a Prometheus data source.
    let inputs: BTreeSet<String> = dash["__inputs"]
        .as_array()
        .expect("__inputs")
        .iter()
        .filter(|i| i["type"] == "datasource" && i["pluginId"] == "prometheus")
        .filter_map(|i| i["name"].as_str().map(|n| format!("${{{n}}}")))
        .collect();
    assert!(inputs.contains(DS), "{inputs:?}");
    fn strings<'a>(v: &'a Value, out: &mut Vec<&'a str>) {
        match v {
            Value::String(s) => out.push(s),
            Value::Array(a) => a.iter().for_each(|v| strings(v, out)),
            Value::Object(o) => o.values().for_each(|v| strings(v, out)),
            _ => {}
        }
    }
    let mut all = Vec::new();
    strings(&dash, &mut all);
    for s in all {
        for (at, _) in s.match_indices("${DS_") {
            let used = &s[at..=at + s[at..].find('}').expect("${DS_...}")];
            assert!(inputs.contains(used), "{used} has no __inputs entry");
        }
    }
    let prometheus = |v: &Value, what: &str| {
        assert_eq!(v["type"], "prometheus", "{what}: datasource {v}");
        assert_eq!(v["uid"], DS, "{what}: datasource {v}");
    };

    // A template variable `instance` from a query of Prometheus.
    let vars = dash["templating"]["list"].as_array().expect("templating");
    let instance = vars
        .iter()
        .find(|v| v["name"] == "instance")
        .expect("a variable `instance`");
    assert_eq!(instance["type"], "query");
    prometheus(&instance["datasource"], "variable instance");
    for var in vars {
        let definition = var["definition"].as_str().unwrap_or("");
        assert!(definition.contains("fbbus_"), "{var}");
    }

    let panels = dash["panels"].as_array().expect("panels");
    assert!(panels.len() >= 20, "{} panels", panels.len());
    let mut ids = BTreeSet::new();
    let mut kinds = BTreeSet::new();
    let mut cells: BTreeMap<(u64, u64), String> = BTreeMap::new();
    for p in panels {
        let title = p["title"].as_str().expect("a title");
        assert!(!title.is_empty());
        assert!(
            ids.insert(p["id"].as_u64().expect("an integer id")),
            "{title}: id twice"
        );
        let kind = p["type"].as_str().expect("a type");
        kinds.insert(kind.to_owned());
        let g = &p["gridPos"];
        let [Some(x), Some(y), Some(w), Some(h)] = ["x", "y", "w", "h"].map(|k| g[k].as_u64())
        else {
            panic!("{title}: gridPos {g}");
        };
        assert!(x + w <= 24 && w > 0 && h > 0, "{title}: gridPos {g}");
        // No two panels on one cell of the grid.
        for cx in x..x + w {
            for cy in y..y + h {
                if let Some(other) = cells.insert((cx, cy), title.to_owned()) {
                    panic!("{title} overlaps {other} at ({cx}, {cy})");
                }
            }
        }
        if kind == "row" {
            assert!(
                p["targets"].as_array().is_none_or(|t| t.is_empty()),
                "{title}"
            );
            continue;
        }
        assert!(["timeseries", "stat"].contains(&kind), "{title}: {kind}");
        prometheus(&p["datasource"], title);
        assert!(
            p["fieldConfig"]["defaults"]["unit"]
                .as_str()
                .is_some_and(|u| !u.is_empty()),
            "{title}: no unit"
        );
        let targets = p["targets"].as_array().expect("targets");
        assert!(!targets.is_empty(), "{title}: no query");
        let mut refs = BTreeSet::new();
        for t in targets {
            let r = t["refId"].as_str().expect("a refId");
            assert!(refs.insert(r), "{title}: refId {r} twice");
            prometheus(&t["datasource"], title);
            assert!(
                t["expr"].as_str().is_some_and(|e| e.contains("fbbus_")),
                "{title}/{r}: no fbbus metric"
            );
        }
    }
    // Every panel type the board uses is declared in `__requires`, with Grafana and the
    // Prometheus data source.
    let requires = dash["__requires"].as_array().expect("__requires");
    let required = |kind: &str| -> BTreeSet<&str> {
        requires
            .iter()
            .filter(|r| r["type"] == kind)
            .filter_map(|r| r["id"].as_str())
            .collect()
    };
    assert!(required("grafana").contains("grafana"));
    assert!(required("datasource").contains("prometheus"));
    for kind in &kinds {
        assert!(
            required("panel").contains(kind.as_str()),
            "panel type {kind} not in __requires"
        );
    }

    // Every metric a target reads is filtered by the `instance` variable.
    for q in queries(&dash).iter().filter(|q| q.target) {
        let uses = parse(&q.expr).uses;
        assert!(!uses.is_empty(), "{}: {}", q.at, q.expr);
        for u in uses {
            assert!(
                u.matchers
                    .iter()
                    .any(|m| m.label == "instance" && m.op == "=~" && m.value == "$instance"),
                "{}: {} not filtered by instance=~\"$instance\"",
                q.at,
                u.name
            );
        }
    }
}

/// A metric family of a `/metrics` page: its `# TYPE` and its series' labels and values.
#[derive(Default, Debug)]
struct Family {
    kind: String,
    labels: BTreeMap<String, BTreeSet<String>>,
    samples: usize,
}

/// The families of a `/metrics` text; a histogram's `_bucket`, `_sum` and `_count`
/// series count for their family.
fn families(text: &str) -> BTreeMap<String, Family> {
    let mut out: BTreeMap<String, Family> = BTreeMap::new();
    for line in text.lines() {
        if let Some(rest) = line.strip_prefix("# TYPE ") {
            let (name, kind) = rest.split_once(' ').expect("# TYPE name kind");
            out.entry(name.to_owned()).or_default().kind = kind.trim().to_owned();
        }
    }
    for line in text
        .lines()
        .filter(|l| !l.starts_with('#') && !l.is_empty())
    {
        let name_end = line.find(['{', ' ']).unwrap_or(line.len());
        let name = family_of(&out, &line[..name_end]);
        let family = out.entry(name).or_default();
        family.samples += 1;
        if let Some(inner) = line[name_end..].strip_prefix('{') {
            let close = inner.rfind('}').expect("a closing brace");
            for m in matchers(&inner[..close]) {
                family.labels.entry(m.label).or_default().insert(m.value);
            }
        }
    }
    out
}

/// `name` itself if it is a family, else the histogram (or summary) it is a series of.
fn family_of(families: &BTreeMap<String, Family>, name: &str) -> String {
    for suffix in ["_bucket", "_sum", "_count"] {
        if let Some(base) = name.strip_suffix(suffix) {
            if families
                .get(base)
                .is_some_and(|f| f.kind == "histogram" || f.kind == "summary")
                && !families.contains_key(name)
            {
                return base.to_owned();
            }
        }
    }
    name.to_owned()
}

/// What the board uses that a `/metrics` page does not have (empty: nothing).
fn missing(dash: &Value, metrics: &str) -> Vec<String> {
    // Prometheus's own target labels.
    const TARGET: [&str; 2] = ["instance", "job"];
    let have = families(metrics);
    let mut out = Vec::new();
    for q in queries(dash) {
        let at = format!("{} ({})", q.at, q.expr);
        let parsed = parse(&q.expr);
        let mut labels: BTreeSet<&str> = BTreeSet::new();
        for u in &parsed.uses {
            let name = family_of(&have, &u.name);
            let Some(family) = have.get(&name).filter(|f| !f.kind.is_empty()) else {
                out.push(format!("{}: no # TYPE {name} in /metrics: {at}", u.name));
                continue;
            };
            if family.samples == 0 {
                out.push(format!("{name}: registered, no series yet: {at}"));
            }
            if family.kind == "histogram" && name == u.name {
                out.push(format!(
                    "{name}: a histogram, read by _bucket, _sum or _count: {at}"
                ));
            }
            let counter = family.kind == "counter" || name != u.name;
            if u.as_counter != counter {
                out.push(format!(
                    "{}: a {} read {} rate/increase: {at}",
                    u.name,
                    family.kind,
                    if u.as_counter { "with" } else { "without" }
                ));
            }
            labels.extend(family.labels.keys().map(String::as_str));
            for m in u.matchers.iter().filter(|m| !TARGET.contains(&&*m.label)) {
                let Some(values) = family.labels.get(&m.label) else {
                    out.push(format!("{name} has no label {}: {at}", m.label));
                    continue;
                };
                if m.op == "=" && !m.value.contains('$') && !values.contains(&m.value) {
                    out.push(format!(
                        "{name} has no series {}=\"{}\" (only {values:?}): {at}",
                        m.label, m.value
                    ));
                }
            }
        }
        for label in parsed.by.iter().filter(|l| !TARGET.contains(&l.as_str())) {
            for u in &parsed.uses {
                let name = family_of(&have, &u.name);
                if have
                    .get(&name)
                    .is_some_and(|f| !f.labels.contains_key(label))
                {
                    out.push(format!("{name} has no label {label} to group by: {at}"));
                }
            }
        }
        // A legend names what the query leaves: the grouping labels, or every label.
        for label in &q.legend {
            let left = match parsed.aggregates {
                true => parsed.by.contains(label),
                false => labels.contains(label.as_str()) || TARGET.contains(&label.as_str()),
            };
            if !left {
                out.push(format!(
                    "legend {{{{{label}}}}} is no label of the result: {at}"
                ));
            }
        }
    }
    out
}

/// Every metric the board's queries use is a series of a real line, with the labels the
/// queries match, group by and show (`instance` is Prometheus's own).
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn every_metric_the_dashboard_uses_is_in_a_real_metrics_page() {
    let a = Line::plain("line-a", &[], "[sparkplug]\nenabled = true\n");
    let b = Line::plain("line-b", &[&a.zenoh], "");
    let broker = &a.broker;

    // A device declared and publishing, one value refused.
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
    // The subscription reaches line b as interest a moment after its SUBACK: a value
    // published before that is not exported (by design), so publish until one arrives.
    let mut carried = false;
    for _ in 0..20 {
        bus::publish(&remote, "fb/remote-1/CONV/POSITION", "5".into(), false).await;
        if reader
            .next_publish(Duration::from_millis(500))
            .await
            .is_some()
        {
            carried = true;
            break;
        }
    }
    assert!(carried, "the bus carried none of 20 values in 10 s");
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

    // The counters are updated asynchronously: wait for the last to appear.
    let dash = dashboard();
    let deadline = Instant::now() + Duration::from_secs(10);
    loop {
        let metrics = broker.metrics();
        let missing = missing(&dash, &metrics);
        if missing.is_empty() {
            break;
        }
        assert!(
            Instant::now() < deadline,
            "the dashboard uses what /metrics does not have:\n{}\n\n{metrics}",
            missing.join("\n")
        );
        tokio::time::sleep(Duration::from_millis(100)).await;
    }
    drop((remote, reader, host, b));
}

/// The checks above catch what they are for: a misspelt metric, a label the series do
/// not have, a counter plotted raw, a legend naming a label the query summed away.
#[test]
fn the_checks_find_what_is_wrong() {
    let metrics = "# HELP fbbus_x_total X\n# TYPE fbbus_x_total counter\n\
                   fbbus_x_total{reason=\"a\"} 1\n\
                   # HELP fbbus_g G\n# TYPE fbbus_g gauge\nfbbus_g 3\n\
                   # HELP fbbus_h_seconds H\n# TYPE fbbus_h_seconds histogram\n\
                   fbbus_h_seconds_bucket{le=\"0.1\"} 1\nfbbus_h_seconds_bucket{le=\"+Inf\"} 1\n\
                   fbbus_h_seconds_sum 0.05\nfbbus_h_seconds_count 1\n";
    let board = |expr: &str, legend: &str| {
        serde_json::json!({"panels": [{"title": "p", "targets": [
            {"refId": "A", "expr": expr, "legendFormat": legend}
        ]}]})
    };
    let i = "instance=~\"$instance\"";
    let good = [
        (
            format!("sum by (reason) (rate(fbbus_x_total{{{i}}}[5m]))"),
            "{{reason}}",
        ),
        (format!("fbbus_g{{{i}}}"), "{{instance}}"),
        (
            format!("sum(rate(fbbus_x_total{{{i},reason=\"a\"}}[5m]))"),
            "a",
        ),
        (
            format!(
                "histogram_quantile(0.99, sum by (le) (rate(fbbus_h_seconds_bucket{{{i}}}[5m])))"
            ),
            "p99",
        ),
        (
            format!("rate(fbbus_h_seconds_count{{{i}}}[5m])"),
            "{{instance}}",
        ),
    ];
    for (expr, legend) in &good {
        assert_eq!(
            missing(&board(expr, legend), metrics),
            Vec::<String>::new(),
            "{expr}"
        );
    }
    let bad = [
        (format!("sum(rate(fbbus_y_total{{{i}}}[5m]))"), ""),
        (
            format!("sum by (result) (rate(fbbus_x_total{{{i}}}[5m]))"),
            "",
        ),
        (
            format!("sum(rate(fbbus_x_total{{{i},reason=\"b\"}}[5m]))"),
            "",
        ),
        (format!("sum(fbbus_x_total{{{i}}})"), ""),
        (format!("sum(rate(fbbus_g{{{i}}}[5m]))"), ""),
        (format!("sum(rate(fbbus_x_total{{{i}}}[5m]))"), "{{reason}}"),
        (format!("rate(fbbus_h_seconds_total{{{i}}}[5m])"), ""),
        (format!("sum(fbbus_h_seconds{{{i}}})"), ""),
    ];
    for (expr, legend) in &bad {
        assert!(!missing(&board(expr, legend), metrics).is_empty(), "{expr}");
    }
}

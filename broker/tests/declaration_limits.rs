//! Issue 21: what one device may declare, how often, and how many diagnostics it is sent
//! (`[fb] max_declaration_bytes`, `max_fbs`, `max_ports`, `declarations_per_minute`,
//! `diag_per_second`, and a port's worst-case message size against
//! `[broker] max_packet_bytes`). Past each limit the declaration is refused (MQTT 5 PUBACK
//! 0x97), the reason is on `fbbus/diag/<device>`, the refusal is counted in
//! `fbbus_limit_refusals_total{limit=...}`, and other devices go on as before.

mod common;

use serde_json::{json, Value};

use common::fb::*;
use common::{Broker, Options};

const QUOTA_EXCEEDED: u8 = 0x97;

fn broker_with(fb: &str) -> Broker {
    Broker::start_with(
        Options {
            extra: format!("[fb]\nregistry_file = \"\"\n{fb}\n"),
            ..Options::default()
        },
        |_| {},
    )
}

fn limit_series(limit: &str) -> String {
    format!("fbbus_limit_refusals_total{{limit=\"{limit}\"}}")
}

/// A declaration of `fbs` FBs with `ports` INT data outputs each.
fn declaration(fbs: usize, ports: usize) -> String {
    let fbs: serde_json::Map<String, Value> = (0..fbs)
        .map(|f| {
            let out: serde_json::Map<String, Value> = (0..ports)
                .map(|p| (format!("P{p}"), json!("INT")))
                .collect();
            (format!("FB{f}"), json!({"data_out": out}))
        })
        .collect();
    json!({ "fbs": fbs }).to_string()
}

/// Declares `text` and returns the PUBACK reason and the device's declaration answer.
async fn declare(
    dev: &mut Dev,
    text: &str,
    sub: &mut common::clients::V4,
    broker: &Broker,
) -> (u8, Value) {
    let code = dev.declare(text);
    let answer = diag(sub, &dev.id.clone(), "declaration", broker).await;
    (code, answer)
}

fn first_error(answer: &Value) -> String {
    answer["errors"][0]["error"]
        .as_str()
        .unwrap_or_default()
        .to_owned()
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn declarations_past_the_size_fb_port_and_encoded_size_limits_are_refused() {
    let broker = broker_with("max_declaration_bytes = 2000\nmax_fbs = 3\nmax_ports = 10");
    let mut sub = observer(&broker, "watch", &["fbbus/diag/#"]).await;
    let mut dev = Dev::connect(broker.port(), 5, "big-a");

    // Bytes: read no further than the limit.
    let long = json!({"fbs": {"A": {"type": "x".repeat(3000)}}}).to_string();
    let (code, answer) = declare(&mut dev, &long, &mut sub, &broker).await;
    assert_eq!(code, QUOTA_EXCEEDED);
    assert_eq!(answer["ok"], false);
    assert_eq!(answer["limit"], "declaration_bytes", "{answer}");
    assert!(first_error(&answer).contains("at most 2000"), "{answer}");
    assert_eq!(broker.metric(&limit_series("declaration_bytes")), 1.0);

    // FBs: 4 of at most 3.
    let (code, answer) = declare(&mut dev, &declaration(4, 1), &mut sub, &broker).await;
    assert_eq!(code, QUOTA_EXCEEDED);
    assert_eq!(answer["limit"], "fbs", "{answer}");
    assert!(first_error(&answer).contains("4 FBs declared; at most 3"));
    assert_eq!(broker.metric(&limit_series("fbs")), 1.0);

    // Ports: 3 FBs of 4 ports, 12 of at most 10, over the device.
    let (code, answer) = declare(&mut dev, &declaration(3, 4), &mut sub, &broker).await;
    assert_eq!(code, QUOTA_EXCEEDED);
    assert_eq!(answer["limit"], "ports", "{answer}");
    assert!(first_error(&answer).contains("12 ports declared; at most 10"));
    assert_eq!(broker.metric(&limit_series("ports")), 1.0);

    // Encoded size: ARRAY [30000] OF TIME takes far more than 64 KiB in every encoding.
    let huge = r#"{"fbs": {"LOG": {"data_out": {"OK": "INT", "TIMES": "ARRAY [30000] OF TIME"}}}}"#;
    let (code, answer) = declare(&mut dev, huge, &mut sub, &broker).await;
    assert_eq!(code, QUOTA_EXCEEDED);
    assert_eq!(answer["limit"], "encoded_size", "{answer}");
    assert_eq!(
        answer["errors"].as_array().map(Vec::len),
        Some(1),
        "{answer}"
    );
    assert_eq!(answer["errors"][0]["fb"], "LOG");
    assert_eq!(answer["errors"][0]["port"], "TIMES");
    let error = first_error(&answer);
    assert!(
        error.contains("bytes on") && error.contains("max_packet_bytes (65536)"),
        "{error}"
    );
    assert_eq!(broker.metric(&limit_series("encoded_size")), 1.0);
    // Nothing of these is in the registry.
    assert_eq!(record(&broker, "big-a"), None);

    // Within every limit: accepted, from this device and from another one.
    let fits = r#"{"fbs": {"LOG": {"data_out": {"OK": "INT", "TIMES": "ARRAY [100] OF TIME"}}}}"#;
    let (code, answer) = declare(&mut dev, fits, &mut sub, &broker).await;
    assert_eq!((code, &answer["ok"]), (0, &json!(true)), "{answer}");
    let mut other = Dev::connect(broker.port(), 5, "small-b");
    declare_ok(&mut other, &declaration(3, 3), &mut sub, &broker).await;
    assert_eq!(
        broker.metric("fbbus_declarations_total{result=\"refused\"}"),
        4.0
    );
    // Refusals at a limit are QoS 1 acknowledged like any refusal: the connection goes on.
    assert_eq!(other.publish("fb/small-b/FB0/P0", b"7"), 0);
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn re_declarations_past_the_rate_are_refused_with_retry_after() {
    let broker = broker_with("declarations_per_minute = 3");
    let mut sub = observer(&broker, "watch", &["fbbus/diag/#"]).await;
    let mut dev = Dev::connect(broker.port(), 5, "loop-a");
    for _ in 0..3 {
        declare_ok(&mut dev, CONV, &mut sub, &broker).await;
    }
    let (code, answer) = declare(&mut dev, CONV, &mut sub, &broker).await;
    assert_eq!(code, QUOTA_EXCEEDED);
    assert_eq!(answer["limit"], "declaration_rate", "{answer}");
    let error = first_error(&answer);
    assert!(error.starts_with("rate limited, retry after "), "{error}");
    // One token a 20 s at 3 a minute.
    let wait: u64 = error["rate limited, retry after ".len()..]
        .split(' ')
        .next()
        .and_then(|n| n.parse().ok())
        .unwrap_or_else(|| panic!("{error}"));
    assert!((1..=20).contains(&wait), "{error}");
    for _ in 0..5 {
        assert_eq!(dev.declare(CONV), QUOTA_EXCEEDED);
    }
    broker.wait_metric(&limit_series("declaration_rate"), 6.0);
    // Logged once, not once per declaration.
    let log = broker.log_text();
    assert_eq!(
        log.matches("over [fb] declarations_per_minute").count(),
        1,
        "{log}"
    );
    // Another device has its own budget.
    let mut other = Dev::connect(broker.port(), 5, "calm-b");
    declare_ok(&mut other, CONV, &mut sub, &broker).await;
    // The declaration in force is the last one accepted; the device publishes on.
    assert_eq!(dev.publish("fb/loop-a/CONV/POSITION", b"3"), 0);
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn diagnostics_past_the_rate_are_dropped_and_counted() {
    let broker = broker_with("diag_per_second = 2.0\ndiag_burst = 3");
    let mut sub = observer(&broker, "watch", &["fbbus/diag/#"]).await;
    let mut noisy = Dev::connect(broker.port(), 5, "noisy-a");
    let mut calm = Dev::connect(broker.port(), 5, "calm-b");
    declare_ok(&mut noisy, CONV, &mut sub, &broker).await;
    declare_ok(&mut calm, CONV, &mut sub, &broker).await;
    // 20 ill-typed values at once: each refused, few explained.
    for _ in 0..20 {
        assert_eq!(noisy.publish("fb/noisy-a/CONV/POSITION", b"70000"), REFUSED);
    }
    let dropped = broker.wait_metric("fbbus_diag_dropped_total", 15.0);
    assert!(dropped <= 20.0, "{dropped}");
    // The other device is explained as before.
    assert_eq!(calm.publish("fb/calm-b/CONV/POSITION", b"70000"), REFUSED);
    let got = diag(&mut sub, "calm-b", "rejected", &broker).await;
    assert_eq!(got["reason"], "payload_format_invalid");
    // What reached the monitor for the noisy device: at most the burst and the refill.
    let seen = drain(&mut sub, QUIET).await;
    let noisy_diags = seen
        .iter()
        .filter(|(t, _)| t == "fbbus/diag/noisy-a")
        .count();
    assert!(noisy_diags <= 6, "{noisy_diags} diagnostics: {seen:?}");
    // Once the budget refills, the next diagnostic is preceded by the count dropped.
    tokio::time::sleep(std::time::Duration::from_millis(1200)).await;
    assert_eq!(noisy.publish("fb/noisy-a/CONV/POSITION", b"70000"), REFUSED);
    let summary = diag(&mut sub, "noisy-a", "diag_dropped", &broker).await;
    assert!(summary["dropped"].as_u64().unwrap_or(0) >= 14, "{summary}");
    let next = diag(&mut sub, "noisy-a", "rejected", &broker).await;
    assert_eq!(next["reason"], "payload_format_invalid");
}

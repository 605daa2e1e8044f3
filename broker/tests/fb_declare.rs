//! Declarations end to end against the real `fbbus` binary (the device contract of
//! `docs/device-contract.md`): an accepted declaration is answered on `fbbus/diag/<id>` and
//! recorded; a refused one lists every error and is not routed.
//!
//! Each test starts its own broker on free loopback ports; helpers are in
//! `common/fb.rs`.

mod common;

use serde_json::{json, Value};

use common::clients::WAIT;
use common::fb::*;
use common::Broker;

// ---------------------------------------------------------------- 1. declaration accepted

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn declaration_is_answered_and_recorded() {
    let broker = Broker::start();
    let mut sub = observer(&broker, "watch", &["fbbus/diag/conv-a"]).await;
    // No device yet: the line's topic space is empty.
    assert_eq!(record(&broker, "conv-a"), None);

    let mut dev = Dev::connect(broker.port(), 5, "conv-a");
    assert_eq!(dev.declare(CONV), 0, "PUBACK of a good declaration");
    let answer = diag(&mut sub, "conv-a", "declaration", &broker).await;
    let session = answer["session"].as_u64().expect("session is a number");
    assert!(session >= 1);
    assert_eq!(
        answer,
        json!({"kind": "declaration", "ok": true, "session": session, "line": "test"})
    );

    // A client arriving later reads the retained record and count.
    let mut late = observer(
        &broker,
        "late",
        &["fbbus/devices/conv-a", "fbbus/lines/test/online"],
    )
    .await;
    let rec = json_on(&mut late, "fbbus/devices/conv-a", &broker).await;
    assert_eq!(rec["id"], "conv-a");
    assert_eq!(rec["line"], "test");
    assert_eq!(rec["status"], "online");
    assert_eq!(rec["session"], session);
    assert_eq!(rec["last_will_reason"], Value::Null);
    assert!(
        rec["since"].as_str().is_some_and(|s| s.ends_with('Z')),
        "{rec}"
    );
    assert_eq!(
        rec["interface"]["fbs"]["CONV"]["data_out"]["POSITION"],
        "INT"
    );
    assert_eq!(
        rec["interface"]["fbs"]["CONV"]["events_out"]["MOVED"]["with"],
        json!(["POSITION", "SENSOR_IN"])
    );
    let online = next_on(&mut late, "fbbus/lines/test/online", WAIT).await;
    assert_eq!(online.as_deref(), Some(&b"1"[..]));
    assert_metric(
        &broker,
        r#"fbbus_declarations_total{result="accepted"}"#,
        1.0,
    );
    assert_metric(&broker, r#"fbbus_registry_devices{status="online"}"#, 1.0);

    // A new declaration replaces the old one, on the same session.
    assert_eq!(
        dev.declare(r#"{"fbs": {"LAMP": {"data_out": {"ON": "BOOL"}}}}"#),
        0
    );
    let again = diag(&mut sub, "conv-a", "declaration", &broker).await;
    assert_eq!(again["session"], session);
    let rec = wait_record(&broker, "conv-a", "redeclared", |r| {
        r["interface"]["fbs"].get("LAMP").is_some()
    })
    .await;
    assert!(rec["interface"]["fbs"].get("CONV").is_none(), "{rec}");
}

// ---------------------------------------------------------------- 2. declaration refused

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn refused_declaration_lists_every_error_and_is_not_routed() {
    let broker = Broker::start();
    let mut sub = observer(&broker, "watch", &["fbbus/diag/conv-b"]).await;
    let mut everything = observer(&broker, "all", &["#"]).await;

    let bad = r#"{"fbs": {"CONV": {
        "events_out": {"MOVED": {"with": ["POSITION", "GHOST"]}},
        "data_out": {"POSITION": "FLOAT", "MOVED": "INT", "OK": "BOOL"}}}}"#;
    let mut dev = Dev::connect(broker.port(), 5, "conv-b");
    assert_eq!(
        dev.declare(bad),
        REFUSED,
        "MQTT 5 PUBACK of a refused declaration"
    );
    let answer = diag(&mut sub, "conv-b", "declaration", &broker).await;
    assert_eq!(answer["ok"], false, "{answer}");
    let errors = answer["errors"].as_array().expect("errors list");
    let has = |port: &str, text: &str| {
        errors.iter().any(|e| {
            e["fb"] == "CONV"
                && e["port"] == port
                && e["error"].as_str().is_some_and(|t| t.contains(text))
        })
    };
    assert!(has("POSITION", "unknown type 'FLOAT'"), "{answer}");
    assert!(has("MOVED", "declared twice"), "{answer}");
    assert!(has("MOVED", "WITH GHOST"), "{answer}");
    assert!(answer.get("session").is_none(), "{answer}");

    // Not JSON at all: one error, without fb or port.
    assert_eq!(dev.declare("{\"fbs\": "), REFUSED);
    let answer = diag(&mut sub, "conv-b", "declaration", &broker).await;
    assert_eq!(answer["ok"], false);
    assert!(
        answer["errors"][0]["error"]
            .as_str()
            .is_some_and(|t| t.contains("not a valid interface declaration")),
        "{answer}"
    );
    assert_metric(
        &broker,
        r#"fbbus_declarations_total{result="refused"}"#,
        2.0,
    );
    // Counted as declarations, not as typed rejections.
    assert_eq!(
        broker.metric(&rejected_series(
            "undeclared",
            "undeclared",
            "payload_format_invalid"
        )),
        0.0
    );

    // MQTT 3.1.1: acknowledged, answered, not recorded.
    let mut sub4 = observer(&broker, "watch4", &["fbbus/diag/conv-c"]).await;
    let mut dev4 = Dev::connect(broker.port(), 4, "conv-c");
    assert_eq!(dev4.declare(bad), 0);
    let answer = diag(&mut sub4, "conv-c", "declaration", &broker).await;
    assert_eq!(answer["ok"], false, "{answer}");

    // No record, no count, and the declarations themselves went to nobody: the `#`
    // subscriber saw only the broker's answers on fbbus/diag/.
    assert_eq!(record(&broker, "conv-b"), None);
    assert_eq!(record(&broker, "conv-c"), None);
    let seen = drain(&mut everything, QUIET).await;
    let topics: Vec<&str> = seen.iter().map(|(t, _)| t.as_str()).collect();
    assert!(
        topics.iter().all(|t| t.starts_with("fbbus/diag/")),
        "a refused declaration led to {topics:?}"
    );
    assert_eq!(
        topics.iter().filter(|t| **t == "fbbus/diag/conv-b").count(),
        2
    );

    // The connection is still usable: a good declaration now succeeds.
    assert_eq!(dev.declare(CONV), 0);
    assert_eq!(
        diag(&mut sub, "conv-b", "declaration", &broker).await["ok"],
        true
    );
    let (topic, _) = next_under(&mut everything, "fbbus/devices/", WAIT)
        .await
        .expect("a record once a declaration is accepted");
    assert_eq!(topic, "fbbus/devices/conv-b");
}

/// Issue 21: a large bad declaration is answered with a summary of at most 4 KiB, not an
/// echo of everything wrong in it (a 64 KB one used to make an 821 KB diagnostic).
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_large_bad_declaration_gets_a_bounded_answer() {
    // Read although larger than the default `[fb] max_declaration_bytes` (16 KiB), to see
    // what its errors make of it.
    let broker = common::Broker::start_with(
        common::Options {
            extra: "[fb]\nmax_declaration_bytes = 65536\n".into(),
            ..Default::default()
        },
        |_| {},
    );
    let mut sub = observer(&broker, "watch", &["fbbus/diag/big"]).await;
    // Each error names the port's type, and every type is a 6,000-character invention.
    let ports: serde_json::Map<String, Value> = (0..10)
        .map(|i| (format!("P{i}"), json!(format!("T{i}{}", "ü".repeat(3000)))))
        .collect();
    let bad = json!({"fbs": {"FB": {"data_out": ports}}}).to_string();
    assert!(bad.len() > 40_000);
    let mut dev = Dev::connect(broker.port(), 5, "big");
    assert_eq!(dev.declare(&bad), REFUSED);
    let topic = "fbbus/diag/big";
    let bytes = common::fb::next_on(&mut sub, topic, WAIT)
        .await
        .expect("the declaration's answer");
    assert!(bytes.len() <= 4096, "answer of {} bytes", bytes.len());
    let answer: Value = serde_json::from_slice(&bytes).unwrap();
    assert_eq!(
        (
            answer["kind"].as_str(),
            answer["ok"].as_bool(),
            answer["truncated"].as_bool()
        ),
        (Some("declaration"), Some(false), Some(true))
    );
    assert!(answer["errors"].as_array().is_some_and(|e| !e.is_empty()));
}

/// Issue 21: a declaration sent at QoS 2 completes with PUBCOMP 0x00 (success), not
/// 0x92 (packet identifier not found): it was consumed, not refused.
#[test]
fn a_qos2_declaration_completes_with_success() {
    use common::raw::{self, Connect, RawClient};
    let broker = Broker::start();
    let mut c = RawClient::connect(broker.port());
    assert_eq!(
        c.handshake(&Connect {
            version: 5,
            client_id: "q2-dev",
            ..Default::default()
        }),
        0
    );
    c.send(&raw::publish_v5(
        "fbbus/declare/q2-dev",
        None,
        2,
        7,
        CONV.as_bytes(),
    ));
    let (b, body) = c.read_packet().expect("PUBREC");
    assert_eq!(b, 0x50);
    assert!(body.len() < 3 || body[2] == 0, "PUBREC reason {body:?}");
    c.send(&raw::packet(0x62, &7u16.to_be_bytes()));
    let (b, body) = c.read_packet().expect("PUBCOMP");
    assert_eq!(b, 0x70);
    assert_eq!(u16::from_be_bytes([body[0], body[1]]), 7);
    assert!(
        body.len() < 3 || body[2] == 0,
        "PUBCOMP reason {:#x}",
        body[2]
    );
}

//! The three encodings end to end against the real `fbbus` binary: every encoding in is
//! delivered in every encoding out, re-encoding starts with the first subscriber that can
//! read it, and `fb/` subscribers always get canonical JSON.
//!
//! Each test starts its own broker on free loopback ports; helpers are in
//! `common/fb.rs`.

mod common;

use serde_json::{json, Value};

use common::clients::{V4, WAIT};
use common::fb::*;
use common::Broker;

// ---------------------------------------------------------------- 5. encodings

/// One observer per namespace, each subscribed to the device's whole subtree.
struct Three {
    fb: V4,
    dinasore: V4,
    fbdk: V4,
}

impl Three {
    async fn new(broker: &Broker, device: &str) -> Three {
        Three {
            fb: observer(broker, "sub-fb", &[&format!("fb/{device}/#")]).await,
            dinasore: observer(broker, "sub-din", &[&format!("dinasore/{device}/#")]).await,
            fbdk: observer(broker, "sub-fbdk", &[&format!("fbdk/{device}/#")]).await,
        }
    }

    /// Asserts the next message on `<ns>/<device>/<port path>` in each namespace. For an
    /// event, `fb` is the expected `data` and seq/ts must be present.
    async fn expect(
        &mut self,
        path: &str,
        fb: Value,
        dinasore: Value,
        fbdk: &[u8],
        broker: &Broker,
    ) {
        let got = json_on(&mut self.fb, &format!("fb/{path}"), broker).await;
        if got.is_object() {
            assert_eq!(got["data"], fb, "fb/{path}: {got}");
            assert!(
                got["seq"].as_u64().is_some() && got["ts"].as_u64().is_some(),
                "fb/{path}: {got}"
            );
        } else {
            assert_eq!(got, fb, "fb/{path}");
        }
        let got = json_on(&mut self.dinasore, &format!("dinasore/{path}"), broker).await;
        assert_eq!(got, dinasore, "dinasore/{path}");
        let got = next_on(&mut self.fbdk, &format!("fbdk/{path}"), WAIT)
            .await
            .unwrap_or_else(|| panic!("nothing on fbdk/{path}\n{}", broker.log_text()));
        assert_eq!(got, fbdk, "fbdk/{path}: {got:02x?}");
    }
}

fn be<const N: usize>(tag: u8, bytes: [u8; N]) -> Vec<u8> {
    let mut v = vec![tag];
    v.extend_from_slice(&bytes);
    v
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn every_encoding_in_is_delivered_in_every_encoding_out() {
    let broker = Broker::start();
    let mut diag_sub = observer(&broker, "watch", &["fbbus/diag/forte"]).await;
    // Subscribe first: the broker re-encodes into dinasore/ and fbdk/ once someone can read them.
    let mut three = Three::new(&broker, "forte").await;
    let mut dev = Dev::connect(broker.port(), 5, "forte");
    declare_ok(&mut dev, FORTE, &mut diag_sub, &broker).await;

    // fbdk in (INT 5: tag 0x43, two big-endian bytes; the device contract's fbdk table).
    assert_eq!(
        dev.publish("fbdk/forte/CONV/POSITION", &[0x43, 0x00, 0x05]),
        0
    );
    three
        .expect(
            "forte/CONV/POSITION",
            json!(5),
            json!({"POSITION": 5}),
            &[0x43, 0, 5],
            &broker,
        )
        .await;
    // DINASORE in.
    assert_eq!(
        dev.publish_json("dinasore/forte/CONV/POSITION", &json!({"POSITION": -2})),
        0
    );
    three
        .expect(
            "forte/CONV/POSITION",
            json!(-2),
            json!({"POSITION": -2}),
            &[0x43, 0xFF, 0xFE],
            &broker,
        )
        .await;
    // Canonical JSON in.
    assert_eq!(dev.publish("fb/forte/CONV/POSITION", b"300"), 0);
    three
        .expect(
            "forte/CONV/POSITION",
            json!(300),
            json!({"POSITION": 300}),
            &[0x43, 0x01, 0x2C],
            &broker,
        )
        .await;

    // An event with WITH (INT, BOOL): fbdk out is the values in WITH order.
    assert_eq!(
        dev.publish_json(
            "fb/forte/CONV/MOVED",
            &json!({"data": {"SENSOR_IN": true, "POSITION": 5}})
        ),
        0
    );
    three
        .expect(
            "forte/CONV/MOVED",
            json!({"POSITION": 5, "SENSOR_IN": true}),
            json!({"POSITION": 5, "SENSOR_IN": true}),
            &[0x43, 0x00, 0x05, 0x41],
            &broker,
        )
        .await;
    assert_eq!(
        dev.publish("fbdk/forte/CONV/MOVED", &[0x43, 0x00, 0x06, 0x40]),
        0
    );
    three
        .expect(
            "forte/CONV/MOVED",
            json!({"POSITION": 6, "SENSOR_IN": false}),
            json!({"POSITION": 6, "SENSOR_IN": false}),
            &[0x43, 0x00, 0x06, 0x40],
            &broker,
        )
        .await;
    assert_eq!(
        dev.publish_json(
            "dinasore/forte/CONV/MOVED",
            &json!({"POSITION": 7, "SENSOR_IN": true})
        ),
        0
    );
    three
        .expect(
            "forte/CONV/MOVED",
            json!({"POSITION": 7, "SENSOR_IN": true}),
            json!({"POSITION": 7, "SENSOR_IN": true}),
            &[0x43, 0x00, 0x07, 0x41],
            &broker,
        )
        .await;
    // An event without data is the single byte 0x05.
    assert_eq!(dev.publish("fbdk/forte/CONV/TICK", &[0x05]), 0);
    three
        .expect("forte/CONV/TICK", json!({}), json!({}), &[0x05], &broker)
        .await;

    // The device contract's layouts (docs/device-contract.md section 3), one per kind of value.
    let layouts: Vec<(&str, Value, Vec<u8>)> = vec![
        ("ID", json!("abc"), vec![0x50, 0x00, 0x03, b'a', b'b', b'c']),
        ("SPEED", json!(1.5), be(0x4A, 1.5f32.to_be_bytes())),
        ("CYCLE", json!("T#1s"), be(0x4C, 1_000_000i64.to_be_bytes())),
        (
            "CYCLE",
            json!("T#-250ms"),
            be(0x4C, (-250_000i64).to_be_bytes()),
        ),
        // Nanoseconds, the default `[fb] fbdk_time_unit` (FORTE 3.x); both units are
        // tested in fbdk_time_unit.rs.
        (
            "DAY",
            json!("D#1970-01-02"),
            be(0x4D, 86_400_000_000_000u64.to_be_bytes()),
        ),
        (
            "LEVELS",
            json!([1, 2, 3]),
            vec![0x76, 0x00, 0x03, 0x43, 0x00, 0x01, 0x00, 0x02, 0x00, 0x03],
        ),
        (
            "FLAGS",
            json!([true, false]),
            vec![0x76, 0x00, 0x02, 0x41, 0x40],
        ),
    ];
    for (port, value, bytes) in &layouts {
        let path = format!("forte/CONV/{port}");
        // JSON in, fbdk out ...
        assert_eq!(
            dev.publish_json(&format!("fb/{path}"), value),
            0,
            "{port} {value}"
        );
        three
            .expect(&path, value.clone(), json!({*port: value}), bytes, &broker)
            .await;
        // ... and fbdk in, JSON out.
        assert_eq!(
            dev.publish(&format!("fbdk/{path}"), bytes),
            0,
            "{port} {bytes:02x?}"
        );
        three
            .expect(&path, value.clone(), json!({*port: value}), bytes, &broker)
            .await;
    }

    // Refused in fbdk and DINASORE: truncated, mistagged, trailing bytes, wrong keys.
    let refused: [(&str, &[u8]); 8] = [
        ("fbdk/forte/CONV/POSITION", &[0x43, 0x00]),
        ("fbdk/forte/CONV/POSITION", &[0x43]),
        ("fbdk/forte/CONV/POSITION", &[]),
        ("fbdk/forte/CONV/POSITION", &[0x44, 0x00, 0x00, 0x00, 0x05]),
        ("fbdk/forte/CONV/POSITION", &[0x43, 0x00, 0x05, 0x00]),
        ("fbdk/forte/CONV/MOVED", &[0x43, 0x00, 0x05]),
        ("dinasore/forte/CONV/POSITION", br#"{"POS": 5}"#),
        ("dinasore/forte/CONV/MOVED", br#"{"POSITION": 5}"#),
    ];
    for (topic, payload) in refused {
        assert_eq!(
            dev.publish(topic, payload),
            REFUSED,
            "{topic} {payload:02x?} was accepted"
        );
        let d = diag(&mut diag_sub, "forte", "rejected", &broker).await;
        assert_eq!(d["topic"], topic);
        assert_eq!(d["code"], 153);
    }
    // None of them reached any namespace: the next message everywhere is this one.
    assert_eq!(dev.publish("fb/forte/CONV/POSITION", b"1"), 0);
    three
        .expect(
            "forte/CONV/POSITION",
            json!(1),
            json!({"POSITION": 1}),
            &[0x43, 0, 1],
            &broker,
        )
        .await;
    assert_metric(
        &broker,
        &rejected_series("forte", "CONV.POSITION", "payload_format_invalid"),
        6.0,
    );
}

/// Before anyone subscribes to dinasore/ or fbdk/, nothing is re-encoded into them. A
/// filter starting with a wildcard (`+/...`, `#`) gets a typed value once, on `fb/`, and
/// turns no re-encoding on (issue 35: mirrors on request); a filter naming `fbdk/` turns
/// that one on, and only it.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn re_encoding_starts_with_the_first_subscriber_that_names_it() {
    let broker = Broker::start();
    let mut diag_sub = observer(&broker, "watch", &["fbbus/diag/forte"]).await;
    let mut dev = Dev::connect(broker.port(), 5, "forte");
    declare_ok(&mut dev, FORTE, &mut diag_sub, &broker).await;
    let mut plus = observer(&broker, "plus", &["+/forte/CONV/POSITION"]).await;
    assert_eq!(
        dev.publish("fbdk/forte/CONV/POSITION", &[0x43, 0x00, 0x05]),
        0
    );
    let got = next_under(&mut plus, "", WAIT)
        .await
        .unwrap_or_else(|| panic!("+/... got nothing\n{}", broker.log_text()));
    assert_eq!(got, ("fb/forte/CONV/POSITION".to_owned(), b"5".to_vec()));
    assert!(drain(&mut plus, QUIET).await.is_empty(), "one copy only");
    assert!(
        !broker
            .log_text()
            .contains("now also published in this encoding"),
        "a wildcard filter turned a re-encoding on\n{}",
        broker.log_text()
    );

    let mut named = observer(&broker, "named", &["fbdk/forte/#"]).await;
    assert_eq!(dev.publish("fb/forte/CONV/POSITION", b"6"), 0);
    let got = next_under(&mut named, "", WAIT)
        .await
        .unwrap_or_else(|| panic!("fbdk/... got nothing\n{}", broker.log_text()));
    assert_eq!(
        got,
        (
            "fbdk/forte/CONV/POSITION".to_owned(),
            vec![0x43, 0x00, 0x06]
        )
    );
    let got = next_under(&mut plus, "", WAIT).await;
    assert_eq!(
        got,
        Some(("fb/forte/CONV/POSITION".to_owned(), b"6".to_vec()))
    );
    assert!(drain(&mut plus, QUIET).await.is_empty(), "one copy only");
    let log = broker.log_text();
    assert!(
        log.contains("namespace=\"fbdk\"") || log.contains("namespace=fbdk"),
        "{log}"
    );
    assert!(
        !log.contains("namespace=\"dinasore\"") && !log.contains("namespace=dinasore"),
        "{log}"
    );
}

/// Device contract section 3: `fb/...` carries canonical JSON, and the type table lists the
/// non-canonical forms a device may publish ("input may also be", "accepted"). A device
/// publishing an accepted non-canonical form on fb/... must not make fb/ subscribers parse
/// every input form: they get the canonical one, as they do when the same value arrives
/// through fbdk/ or DINASORE.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn fb_subscribers_get_canonical_json_whatever_form_was_published() {
    let decl = r#"{"fbs": {"CONV": {
        "events_out": {"MOVED": {"with": ["MASK"]}},
        "data_out": {"MASK": "WORD", "CYCLE": "TIME", "DAY": "DATE", "ON": "BOOL"}}}}"#;
    let broker = Broker::start();
    let mut diag_sub = observer(&broker, "watch", &["fbbus/diag/conv-a"]).await;
    let mut sub = observer(&broker, "sub", &["fb/conv-a/#"]).await;
    let mut dev = Dev::connect(broker.port(), 5, "conv-a");
    declare_ok(&mut dev, decl, &mut diag_sub, &broker).await;
    let cases: [(&str, &str, Value); 8] = [
        // BOOL as PLC code and people write it (issue 35).
        ("ON", "1", json!(true)),
        ("ON", "0", json!(false)),
        ("MASK", r#""16#FF""#, json!(255)),
        ("MASK", r#""2#1010""#, json!(10)),
        ("CYCLE", r#""TIME#1.5s""#, json!("T#1s500ms")),
        ("CYCLE", "1500000", json!("T#1s500ms")),
        ("DAY", r#""d#2026-11-22""#, json!("D#2026-11-22")),
        (
            "MOVED",
            r#"{"seq": 1, "ts": 2, "data": {"MASK": "16#10"}}"#,
            json!({"seq": 1, "ts": 2, "data": {"MASK": 16}}),
        ),
    ];
    let mut wrong = Vec::new();
    for (port, payload, canonical) in &cases {
        let topic = format!("fb/conv-a/CONV/{port}");
        assert_eq!(
            dev.publish(&topic, payload.as_bytes()),
            0,
            "{topic} {payload}"
        );
        let got = json_on(&mut sub, &topic, &broker).await;
        if &got != canonical {
            wrong.push(format!("{payload} arrived as {got}, not {canonical}"));
        }
    }
    assert!(wrong.is_empty(), "non-canonical JSON on fb/: {wrong:#?}");
    // Only 1 and 0: any other integer is still refused.
    assert_eq!(dev.publish("fb/conv-a/CONV/ON", b"2"), REFUSED);
}

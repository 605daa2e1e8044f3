//! The device contract of `docs/device-contract.md`, end to end against the real `fbbus`
//! binary: declarations and their answers on `fbbus/diag/<id>`, typed topics in the three
//! encodings, refusals with their exact MQTT 5 reason codes, lenient mode, the registry
//! over MQTT, HTTP and `fbbus devices`, wills, takeovers, restarts and identity.
//!
//! Each test starts its own broker on free loopback ports. Devices whose PUBACK reason
//! code must be observed exactly are raw MQTT connections (`common::raw`): rumqttc's v5
//! client ends its connection on a refusing PUBACK. Observers are rumqttc clients.
//! Every wait is bounded; the negative checks ("nothing was delivered") either wait for a
//! later valid message on the same subscription (ordered after the refused one) or for a
//! short fixed window when there is nothing valid to follow.

mod common;

use std::net::SocketAddr;
use std::path::PathBuf;
use std::process::{Command, Stdio};
use std::time::{Duration, Instant, SystemTime, UNIX_EPOCH};

use serde_json::{json, Value};

use common::clients::{V4, V5, WAIT};
use common::raw::{self, RawClient};
use common::{Broker, Options};

// ---------------------------------------------------------------- fixtures

/// The reference interface: a conveyor with data and event outputs, and inputs.
const CONV: &str = r#"{"fbs": {"CONV": {
    "type": "CONVEYOR",
    "events_out": {"MOVED": {"with": ["POSITION", "SENSOR_IN"]}, "TICK": {"with": []}},
    "events_in": {"START": {"with": ["SPEED"]}},
    "data_out": {"POSITION": "INT", "SENSOR_IN": "BOOL", "ID": "STRING", "CONNECT": "BOOL"},
    "data_in": {"SPEED": "REAL"}
}}}"#;

/// For the encoding tests: one port per interesting fbdk layout.
const FORTE: &str = r#"{"fbs": {"CONV": {
    "type": "CONVEYOR",
    "events_out": {"MOVED": {"with": ["POSITION", "SENSOR_IN"]}, "TICK": {"with": []}},
    "data_out": {
        "POSITION": "INT", "SENSOR_IN": "BOOL", "ID": "STRING", "SPEED": "REAL",
        "CYCLE": "TIME", "DAY": "DATE", "LEVELS": "ARRAY [3] OF INT",
        "FLAGS": "ARRAY [0..1] OF BOOL"
    }
}}}"#;

const REFUSED: u8 = 0x99;
const NOT_AUTHORIZED: u8 = 0x87;
const TOPIC_INVALID: u8 = 0x90;

/// Long enough for a message the broker would wrongly route to arrive on loopback.
const QUIET: Duration = Duration::from_millis(400);

fn now_us() -> u64 {
    SystemTime::now()
        .duration_since(UNIX_EPOCH)
        .unwrap()
        .as_micros() as u64
}

// ---------------------------------------------------------------- raw devices

/// A device on a raw MQTT connection, publishing at QoS 1 and reading its PUBACKs.
struct Dev {
    raw: RawClient,
    version: u8,
    pkid: u16,
    id: String,
}

/// A QoS 1 PUBLISH in MQTT 3.1.1 framing.
fn publish_v4_qos1(topic: &str, pkid: u16, payload: &[u8]) -> Vec<u8> {
    let mut body = Vec::new();
    body.extend_from_slice(&(topic.len() as u16).to_be_bytes());
    body.extend_from_slice(topic.as_bytes());
    body.extend_from_slice(&pkid.to_be_bytes());
    body.extend_from_slice(payload);
    raw::packet(0x32, &body)
}

impl Dev {
    /// Connects with `connect`; Err carries the CONNACK code of a refusal.
    fn try_connect(port: u16, connect: &raw::Connect) -> Result<Dev, u8> {
        tokio::task::block_in_place(|| {
            let mut raw = RawClient::connect(port);
            let code = raw.handshake(connect);
            if code != 0 {
                return Err(code);
            }
            Ok(Dev {
                raw,
                version: connect.version,
                pkid: 0,
                id: connect.client_id.to_owned(),
            })
        })
    }

    fn connect(port: u16, version: u8, id: &str) -> Dev {
        Dev::try_connect(
            port,
            &raw::Connect {
                version,
                client_id: id,
                ..Default::default()
            },
        )
        .unwrap_or_else(|code| panic!("{id} (v{version}) refused with {code:#04x}"))
    }

    fn next_pkid(&mut self) -> u16 {
        self.pkid = self.pkid % 60_000 + 1;
        self.pkid
    }

    /// Publishes at QoS 1; returns the PUBACK reason code (always 0 on MQTT 3.1.1, which
    /// has none). Panics if the connection ends before the PUBACK.
    fn publish(&mut self, topic: &str, payload: &[u8]) -> u8 {
        let pkid = self.next_pkid();
        let packet = if self.version == 5 {
            raw::publish_v5(topic, None, 1, pkid, payload)
        } else {
            publish_v4_qos1(topic, pkid, payload)
        };
        self.send_for_ack(&packet, pkid, 4, topic)
    }

    /// An MQTT 5 QoS 1 publication with a topic alias (`topic` may be empty to use it).
    fn publish_alias(&mut self, topic: &str, alias: u16, payload: &[u8]) -> u8 {
        let pkid = self.next_pkid();
        let packet = raw::publish_v5(topic, Some(alias), 1, pkid, payload);
        self.send_for_ack(&packet, pkid, 4, topic)
    }

    /// An MQTT 5 QoS 2 publication: returns the PUBREC reason, then completes the flow
    /// (PUBREL, PUBCOMP) whatever the reason.
    fn publish_qos2(&mut self, topic: &str, payload: &[u8]) -> u8 {
        assert_eq!(self.version, 5);
        let pkid = self.next_pkid();
        let packet = raw::publish_v5(topic, None, 2, pkid, payload);
        let reason = self.send_for_ack(&packet, pkid, 5, topic);
        let mut pubrel = pkid.to_be_bytes().to_vec();
        pubrel.push(0);
        self.send_for_ack(&raw::packet(0x62, &pubrel), pkid, 7, topic);
        reason
    }

    /// A QoS 0 publication: no answer.
    fn publish_qos0(&mut self, topic: &str, payload: &[u8]) {
        let mut body = (topic.len() as u16).to_be_bytes().to_vec();
        body.extend_from_slice(topic.as_bytes());
        if self.version == 5 {
            body.push(0);
        }
        body.extend_from_slice(payload);
        tokio::task::block_in_place(|| self.raw.send(&raw::packet(0x30, &body)));
    }

    /// A retained QoS 1 publication; returns the PUBACK reason.
    fn publish_retained(&mut self, topic: &str, payload: &[u8]) -> u8 {
        let pkid = self.next_pkid();
        let mut packet = if self.version == 5 {
            raw::publish_v5(topic, None, 1, pkid, payload)
        } else {
            publish_v4_qos1(topic, pkid, payload)
        };
        packet[0] |= 0x01;
        self.send_for_ack(&packet, pkid, 4, topic)
    }

    /// Sends `packet` and reads until the answer of packet type `kind` (4 PUBACK, 5 PUBREC,
    /// 7 PUBCOMP) for `pkid`; returns its reason code (0 when absent).
    fn send_for_ack(&mut self, packet: &[u8], pkid: u16, kind: u8, topic: &str) -> u8 {
        let id = self.id.clone();
        tokio::task::block_in_place(|| {
            self.raw.send(packet);
            loop {
                let Some((byte1, body)) = self.raw.read_packet() else {
                    panic!("{id}: connection closed before the answer (type {kind}) for {topic}");
                };
                if byte1 >> 4 == kind && body[..2] == pkid.to_be_bytes() {
                    return body.get(2).copied().unwrap_or(0);
                }
                assert_ne!(
                    byte1 >> 4,
                    14,
                    "{id}: the broker sent DISCONNECT {body:?} instead of an answer for {topic}"
                );
            }
        })
    }

    fn publish_json(&mut self, topic: &str, payload: &Value) -> u8 {
        self.publish(topic, payload.to_string().as_bytes())
    }

    fn declare(&mut self, declaration: &str) -> u8 {
        let topic = format!("fbbus/declare/{}", self.id);
        self.publish(&topic, declaration.as_bytes())
    }

    /// A clean DISCONNECT (reason 0 on MQTT 5), then waits for the broker to close.
    fn disconnect(mut self) {
        tokio::task::block_in_place(|| {
            let bytes: &[u8] = if self.version == 5 {
                &[0xE0, 0x01, 0x00]
            } else {
                &raw::DISCONNECT
            };
            self.raw.send(bytes);
            self.raw
                .stream
                .set_read_timeout(Some(Duration::from_secs(5)))
                .unwrap();
            assert!(self.raw.closed_by_broker());
        })
    }
}

// ---------------------------------------------------------------- observers

async fn observer(broker: &Broker, id: &str, filters: &[&str]) -> V4 {
    let mut sub = V4::connect(broker.port(), id, None)
        .await
        .unwrap_or_else(|e| panic!("observer {id}: {e}\n{}", broker.log_text()));
    subscribe_all(&mut sub, filters).await;
    sub
}

/// Subscribes to every filter in one SUBSCRIBE, so no retained message is skipped while
/// waiting for a later SUBACK (the broker sends the SUBACK before retained messages).
async fn subscribe_all(sub: &mut V4, filters: &[&str]) {
    sub.client
        .subscribe_many(
            filters
                .iter()
                .map(|f| rumqttc::SubscribeFilter::new(f.to_string(), rumqttc::QoS::AtLeastOnce)),
        )
        .await
        .unwrap();
    let codes = sub
        .next(WAIT, |p| match p {
            rumqttc::Packet::SubAck(s) => Some(s.return_codes),
            _ => None,
        })
        .await
        .expect("SUBACK");
    assert!(
        codes.len() == filters.len()
            && codes
                .iter()
                .all(|c| matches!(c, rumqttc::SubscribeReasonCode::Success(_))),
        "SUBACK for {filters:?}: {codes:?}"
    );
}

/// One message on each of `topics` (in whatever order they arrive: re-encodings and
/// messages matched by different filters are not ordered with each other).
async fn one_each(sub: &mut V4, topics: &[&str], broker: &Broker) -> Vec<Vec<u8>> {
    let mut got: Vec<Option<Vec<u8>>> = vec![None; topics.len()];
    let deadline = Instant::now() + WAIT;
    while got.iter().any(Option::is_none) {
        let left = deadline.saturating_duration_since(Instant::now());
        let Some((topic, payload)) = next_under(sub, "", left).await else {
            panic!(
                "waiting for {topics:?}, got {got:?}\n--- broker log\n{}",
                broker.log_text()
            );
        };
        if let Some(i) = topics.iter().position(|t| *t == topic) {
            assert!(
                got[i].is_none(),
                "two messages on {topic}: {got:?} and {payload:?}"
            );
            got[i] = Some(payload);
        }
    }
    got.into_iter().flatten().collect()
}

/// The payload of the next publication on `topic` within `within` (others are skipped).
async fn next_on(sub: &mut V4, topic: &str, within: Duration) -> Option<Vec<u8>> {
    sub.next(within, |p| match p {
        rumqttc::Packet::Publish(p) if p.topic == topic => Some(p.payload.to_vec()),
        _ => None,
    })
    .await
}

/// The next publication whose topic starts with `prefix`: (topic, payload).
async fn next_under(sub: &mut V4, prefix: &str, within: Duration) -> Option<(String, Vec<u8>)> {
    sub.next(within, |p| match p {
        rumqttc::Packet::Publish(p) if p.topic.starts_with(prefix) => {
            Some((p.topic.clone(), p.payload.to_vec()))
        }
        _ => None,
    })
    .await
}

/// Every publication received within `within`: (topic, payload).
async fn drain(sub: &mut V4, within: Duration) -> Vec<(String, Vec<u8>)> {
    let mut all = Vec::new();
    let deadline = Instant::now() + within;
    while let Some(left) = deadline.checked_duration_since(Instant::now()) {
        match sub
            .next(left, |p| match p {
                rumqttc::Packet::Publish(p) => Some((p.topic.clone(), p.payload.to_vec())),
                _ => None,
            })
            .await
        {
            Some(m) => all.push(m),
            None => break,
        }
    }
    all
}

fn parse(bytes: &[u8]) -> Value {
    serde_json::from_slice(bytes)
        .unwrap_or_else(|e| panic!("not JSON ({e}): {}", String::from_utf8_lossy(bytes)))
}

/// The next JSON message on `topic`, or a panic naming what was awaited.
async fn json_on(sub: &mut V4, topic: &str, broker: &Broker) -> Value {
    let bytes = next_on(sub, topic, WAIT).await.unwrap_or_else(|| {
        panic!(
            "nothing on {topic} within {WAIT:?}\n--- broker log\n{}",
            broker.log_text()
        )
    });
    parse(&bytes)
}

/// The next diag message of `kind` on `fbbus/diag/<id>`.
async fn diag(sub: &mut V4, id: &str, kind: &str, broker: &Broker) -> Value {
    let topic = format!("fbbus/diag/{id}");
    let deadline = Instant::now() + WAIT;
    loop {
        let left = deadline.saturating_duration_since(Instant::now());
        let Some(bytes) = next_on(sub, &topic, left).await else {
            panic!(
                "no {kind} diag on {topic}\n--- broker log\n{}",
                broker.log_text()
            );
        };
        let v = parse(&bytes);
        if v["kind"] == kind {
            return v;
        }
    }
}

// ---------------------------------------------------------------- registry access

fn http_json(broker: &Broker, path: &str) -> (u16, Value) {
    let (code, body) = common::http_get(broker.admin, path)
        .unwrap_or_else(|| panic!("GET {path}: no answer from {}", broker.admin));
    let json = serde_json::from_str(&body)
        .unwrap_or_else(|e| panic!("GET {path}: {code}, body not JSON ({e}): {body}"));
    (code, json)
}

fn record(broker: &Broker, id: &str) -> Option<Value> {
    let (code, json) = http_json(broker, &format!("/api/v1/devices/{id}"));
    match code {
        200 => Some(json),
        404 => None,
        _ => panic!("GET /api/v1/devices/{id}: {code} {json}"),
    }
}

/// Polls the registry until `id`'s record satisfies `pred` (at most 10 s).
async fn wait_record(
    broker: &Broker,
    id: &str,
    what: &str,
    pred: impl Fn(&Value) -> bool,
) -> Value {
    let deadline = Instant::now() + Duration::from_secs(10);
    loop {
        let r = record(broker, id);
        if let Some(r) = r.as_ref().filter(|r| pred(r)) {
            return r.clone();
        }
        if Instant::now() > deadline {
            panic!(
                "device {id} never {what}; last record: {r:?}\n--- broker log\n{}",
                broker.log_text()
            );
        }
        tokio::time::sleep(Duration::from_millis(25)).await;
    }
}

fn rejected_series(device: &str, port: &str, reason: &str) -> String {
    format!(
        "fbbus_typed_messages_rejected_total{{device=\"{device}\",port=\"{port}\",reason=\"{reason}\"}}"
    )
}

/// Waits for a metric to reach `min` and asserts it did, with everything that helps.
fn assert_metric(broker: &Broker, series: &str, min: f64) -> f64 {
    let v = broker.wait_metric(series, min);
    assert!(
        v >= min,
        "{series} = {v}, expected at least {min}\n--- metrics\n{}\n--- broker log\n{}",
        broker.metrics(),
        broker.log_text()
    );
    v
}

/// Declares `declaration` for `dev` and returns the session the broker answered with.
async fn declare_ok(dev: &mut Dev, declaration: &str, diag_sub: &mut V4, broker: &Broker) -> u64 {
    assert_eq!(
        dev.declare(declaration),
        0,
        "declaration of {} refused",
        dev.id
    );
    let answer = diag(diag_sub, &dev.id, "declaration", broker).await;
    assert_eq!(
        answer["ok"], true,
        "declaration of {} refused: {answer}",
        dev.id
    );
    answer["session"].as_u64().expect("session number")
}

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

// ---------------------------------------------------------------- 3. typed publications

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn typed_publications_are_delivered_and_events_stamped() {
    let broker = Broker::start();
    let mut diag_sub = observer(&broker, "watch", &["fbbus/diag/conv-a"]).await;
    let mut sub = observer(&broker, "sub", &["fb/conv-a/#"]).await;
    // Also an MQTT 5 subscriber, on one port.
    let mut sub5 = V5::connect(broker.port(), "sub5", None).await.unwrap();
    sub5.subscribe("fb/conv-a/CONV/MOVED").await;

    // The device is a real rumqttc MQTT 3.1.1 client.
    let dev = V4::connect(broker.port(), "conv-a", None).await.unwrap();
    let qos1 = rumqttc::QoS::AtLeastOnce;
    dev.client
        .publish("fbbus/declare/conv-a", qos1, false, CONV)
        .await
        .unwrap();
    let answer = diag(&mut diag_sub, "conv-a", "declaration", &broker).await;
    assert_eq!(answer["ok"], true, "{answer}");

    // A data port: the bare value, delivered as published.
    dev.client
        .publish("fb/conv-a/CONV/POSITION", qos1, false, "42")
        .await
        .unwrap();
    let got = next_on(&mut sub, "fb/conv-a/CONV/POSITION", WAIT).await;
    assert_eq!(got.as_deref(), Some(&b"42"[..]));
    dev.client
        .publish("fb/conv-a/CONV/ID", qos1, false, r#""Grüße""#)
        .await
        .unwrap();
    assert_eq!(
        json_on(&mut sub, "fb/conv-a/CONV/ID", &broker).await,
        json!("Grüße")
    );

    // An event without seq and ts: both stamped.
    let before = now_us();
    dev.client
        .publish(
            "fb/conv-a/CONV/MOVED",
            qos1,
            false,
            r#"{"data": {"POSITION": 3, "SENSOR_IN": true}}"#,
        )
        .await
        .unwrap();
    let ev = json_on(&mut sub, "fb/conv-a/CONV/MOVED", &broker).await;
    let after = now_us();
    assert_eq!(
        ev["data"],
        json!({"POSITION": 3, "SENSOR_IN": true}),
        "{ev}"
    );
    assert_eq!(ev["seq"], 1, "{ev}");
    let ts = ev["ts"].as_u64().unwrap_or_else(|| panic!("no ts: {ev}"));
    assert!(
        before <= ts && ts <= after,
        "ts {ts} not within [{before}, {after}]"
    );
    let ev5 = sub5.next_publish(WAIT).await.expect("MQTT 5 subscriber");
    assert_eq!(parse(&ev5.payload), ev);

    // The next one counts on; seq and ts given by the device are kept.
    dev.client
        .publish(
            "fb/conv-a/CONV/MOVED",
            qos1,
            false,
            r#"{"ts": 1763800000123456, "data": {"SENSOR_IN": false, "POSITION": -4}}"#,
        )
        .await
        .unwrap();
    let ev = json_on(&mut sub, "fb/conv-a/CONV/MOVED", &broker).await;
    assert_eq!(ev["seq"], 2, "{ev}");
    assert_eq!(ev["ts"], 1_763_800_000_123_456u64, "{ev}");
    assert_eq!(ev["data"], json!({"POSITION": -4, "SENSOR_IN": false}));
    let given =
        r#"{"seq": 17, "ts": 1763800000123456, "data": {"POSITION": 5, "SENSOR_IN": true}}"#;
    dev.client
        .publish("fb/conv-a/CONV/MOVED", qos1, false, given)
        .await
        .unwrap();
    let got = next_on(&mut sub, "fb/conv-a/CONV/MOVED", WAIT)
        .await
        .unwrap();
    assert_eq!(parse(&got), parse(given.as_bytes()));

    // An event without WITH data: `{}` is enough.
    dev.client
        .publish("fb/conv-a/CONV/TICK", qos1, false, "{}")
        .await
        .unwrap();
    let tick = json_on(&mut sub, "fb/conv-a/CONV/TICK", &broker).await;
    assert_eq!(tick["seq"], 1, "{tick}");
    assert!(tick["ts"].as_u64().is_some(), "{tick}");
    assert!(tick.get("data").is_none_or(|d| d == &json!({})), "{tick}");
    assert_metric(&broker, "fbbus_typed_messages_accepted_total", 6.0);
}

// ---------------------------------------------------------------- 4. refusals

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn refusals_have_their_reason_codes_and_are_never_delivered() {
    let broker = Broker::start();
    let mut diag_sub = observer(&broker, "watch", &["fbbus/diag/conv-a"]).await;
    let mut sub = observer(&broker, "sub", &["fb/#"]).await;
    let mut control = observer(&broker, "control", &["fbbus/devices/x", "fbbus/declare/#"]).await;

    let mut other = Dev::connect(broker.port(), 5, "conv-z");
    let mut other_diag = observer(&broker, "watch-z", &["fbbus/diag/conv-z"]).await;
    declare_ok(&mut other, CONV, &mut other_diag, &broker).await;

    let mut dev = Dev::connect(broker.port(), 5, "conv-a");
    declare_ok(&mut dev, CONV, &mut diag_sub, &broker).await;

    struct Case {
        topic: &'static str,
        payload: &'static str,
        code: u8,
        reason: &'static str,
        /// The `port` label of the rejection counter.
        port: &'static str,
    }
    let cases = [
        Case {
            topic: "fb/conv-a/CONV/POSITION",
            payload: "70000",
            code: REFUSED,
            reason: "payload_format_invalid",
            port: "CONV.POSITION",
        },
        Case {
            topic: "fb/conv-a/CONV/POSITION",
            payload: "3.0",
            code: REFUSED,
            reason: "payload_format_invalid",
            port: "CONV.POSITION",
        },
        // Wrong shape: the WITH data as a bare array, a missing WITH port, an extra one.
        Case {
            topic: "fb/conv-a/CONV/MOVED",
            payload: "[3, true]",
            code: REFUSED,
            reason: "payload_format_invalid",
            port: "CONV.MOVED",
        },
        Case {
            topic: "fb/conv-a/CONV/MOVED",
            payload: r#"{"data": {"POSITION": 3}}"#,
            code: REFUSED,
            reason: "payload_format_invalid",
            port: "CONV.MOVED",
        },
        Case {
            topic: "fb/conv-a/CONV/MOVED",
            payload: r#"{"data": {"POSITION": 3, "SENSOR_IN": true, "ID": "x"}}"#,
            code: REFUSED,
            reason: "payload_format_invalid",
            port: "CONV.MOVED",
        },
        Case {
            topic: "fb/conv-a/CONV/SENSOR_IN",
            payload: "not json",
            code: REFUSED,
            reason: "payload_format_invalid",
            port: "CONV.SENSOR_IN",
        },
        Case {
            topic: "fb/conv-a/CONV/GHOST",
            payload: "1",
            code: TOPIC_INVALID,
            reason: "topic_name_invalid",
            port: "undeclared",
        },
        // Inputs are declared, but the device does not publish them.
        Case {
            topic: "fb/conv-a/CONV/SPEED",
            payload: "1.5",
            code: TOPIC_INVALID,
            reason: "topic_name_invalid",
            port: "undeclared",
        },
        Case {
            topic: "fb/conv-a/CONV",
            payload: "1",
            code: TOPIC_INVALID,
            reason: "topic_name_invalid",
            port: "undeclared",
        },
        Case {
            topic: "fb/conv-z/CONV/POSITION",
            payload: "1",
            code: NOT_AUTHORIZED,
            reason: "not_authorized",
            // conv-a declares CONV.POSITION too, so the label names it.
            port: "CONV.POSITION",
        },
        Case {
            topic: "fbbus/devices/x",
            payload: "{}",
            code: NOT_AUTHORIZED,
            reason: "not_authorized",
            port: "undeclared",
        },
        Case {
            topic: "fbbus/declare/conv-z",
            payload: CONV,
            code: NOT_AUTHORIZED,
            reason: "not_authorized",
            port: "undeclared",
        },
    ];
    let mut details = Vec::new();
    for case in &cases {
        let code = dev.publish(case.topic, case.payload.as_bytes());
        assert_eq!(
            code, case.code,
            "PUBACK for {} {}: {code:#04x}, expected {:#04x}",
            case.topic, case.payload, case.code
        );
        let d = diag(&mut diag_sub, "conv-a", "rejected", &broker).await;
        assert_eq!(d["topic"], case.topic, "{d}");
        assert_eq!(d["reason"], case.reason, "{d}");
        assert_eq!(d["code"], case.code, "{d}");
        assert!(d["detail"].as_str().is_some_and(|s| !s.is_empty()), "{d}");
        details.push(d["detail"].as_str().unwrap_or_default().to_owned());
    }
    assert!(
        details[0].contains("CONV.POSITION")
            && details[0].contains("70000")
            && details[0].contains("INT"),
        "{}",
        details[0]
    );

    // Valid messages after all that: the subscriber of fb/# gets exactly these, in order.
    assert_eq!(dev.publish("fb/conv-a/CONV/POSITION", b"7"), 0);
    assert_eq!(other.publish("fb/conv-z/CONV/POSITION", b"8"), 0);
    assert_eq!(
        dev.publish_json(
            "fb/conv-a/CONV/MOVED",
            &json!({"seq": 1, "ts": 2, "data": {"POSITION": 7, "SENSOR_IN": true}})
        ),
        0
    );
    let mut got = Vec::new();
    while got.len() < 3 {
        let Some(m) = next_under(&mut sub, "fb/", WAIT).await else {
            panic!("only {got:?} delivered\n{}", broker.log_text());
        };
        got.push(m);
    }
    assert_eq!(
        got,
        vec![
            ("fb/conv-a/CONV/POSITION".to_owned(), b"7".to_vec()),
            ("fb/conv-z/CONV/POSITION".to_owned(), b"8".to_vec()),
            (
                "fb/conv-a/CONV/MOVED".to_owned(),
                // Canonical JSON comes through as the publisher wrote it (key order and
                // spacing are not part of the form), so compare it as JSON.
                json!({"seq": 1, "ts": 2, "data": {"POSITION": 7, "SENSOR_IN": true}})
                    .to_string()
                    .into_bytes()
            ),
        ]
    );
    assert!(drain(&mut sub, QUIET).await.is_empty());
    // Nothing reached the broker's own namespace or the other device's declaration.
    assert!(drain(&mut control, QUIET).await.is_empty());
    assert_eq!(
        record(&broker, "conv-z").unwrap()["interface"]["fbs"]["CONV"]["type"],
        "CONVEYOR"
    );

    // Counted per device, port and reason.
    let mut expected = std::collections::BTreeMap::new();
    for case in &cases {
        *expected
            .entry(rejected_series("conv-a", case.port, case.reason))
            .or_insert(0.0) += 1.0;
    }
    for (series, n) in &expected {
        assert_metric(&broker, series, *n);
        assert_eq!(broker.metric(series), *n, "{series}");
    }

    // MQTT 3.1.1: the same ill-typed QoS 1 publication is acknowledged and dropped.
    let mut diag4 = observer(&broker, "watch4", &["fbbus/diag/conv-4"]).await;
    let mut dev4 = Dev::connect(broker.port(), 4, "conv-4");
    declare_ok(&mut dev4, CONV, &mut diag4, &broker).await;
    assert_eq!(dev4.publish("fb/conv-4/CONV/POSITION", b"70000"), 0);
    assert_eq!(
        diag(&mut diag4, "conv-4", "rejected", &broker).await["code"],
        153
    );
    assert_eq!(dev4.publish("fb/conv-4/CONV/GHOST", b"1"), 0);
    assert_eq!(dev4.publish("fb/conv-a/CONV/POSITION", b"1"), 0);
    assert_eq!(dev4.publish("fb/conv-4/CONV/POSITION", b"9"), 0);
    let (topic, payload) = next_under(&mut sub, "fb/", WAIT)
        .await
        .expect("the valid one");
    assert_eq!(
        (topic.as_str(), payload.as_slice()),
        ("fb/conv-4/CONV/POSITION", &b"9"[..])
    );
    assert_metric(
        &broker,
        &rejected_series("conv-4", "CONV.POSITION", "payload_format_invalid"),
        1.0,
    );
    assert_metric(
        &broker,
        &rejected_series("conv-4", "undeclared", "topic_name_invalid"),
        1.0,
    );
}

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

    // fbdk in (INT 5, the README's example).
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

    // The README's layouts, one per kind of value.
    let layouts: Vec<(&str, Value, Vec<u8>)> = vec![
        ("ID", json!("abc"), vec![0x50, 0x00, 0x03, b'a', b'b', b'c']),
        ("SPEED", json!(1.5), be(0x4A, 1.5f32.to_be_bytes())),
        ("CYCLE", json!("T#1s"), be(0x4C, 1_000_000i64.to_be_bytes())),
        (
            "CYCLE",
            json!("T#-250ms"),
            be(0x4C, (-250_000i64).to_be_bytes()),
        ),
        (
            "DAY",
            json!("D#1970-01-02"),
            be(0x4D, 86_400_000u64.to_be_bytes()),
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

/// Before anyone subscribes to dinasore/ or fbdk/, nothing is re-encoded into them; a
/// subscriber to `#` or `+/...` turns both on.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn re_encoding_starts_with_the_first_subscriber_that_can_read_it() {
    let broker = Broker::start();
    let mut diag_sub = observer(&broker, "watch", &["fbbus/diag/forte"]).await;
    let mut dev = Dev::connect(broker.port(), 5, "forte");
    declare_ok(&mut dev, FORTE, &mut diag_sub, &broker).await;
    let mut plus = observer(&broker, "plus", &["+/forte/CONV/POSITION"]).await;
    assert_eq!(
        dev.publish("fbdk/forte/CONV/POSITION", &[0x43, 0x00, 0x05]),
        0
    );
    let mut got = Vec::new();
    while got.len() < 3 {
        let m = next_under(&mut plus, "", WAIT)
            .await
            .unwrap_or_else(|| panic!("+/... got only {got:?}\n{}", broker.log_text()));
        got.push(m);
    }
    got.sort();
    assert_eq!(
        got,
        vec![
            (
                "dinasore/forte/CONV/POSITION".to_owned(),
                br#"{"POSITION":5}"#.to_vec()
            ),
            ("fb/forte/CONV/POSITION".to_owned(), b"5".to_vec()),
            (
                "fbdk/forte/CONV/POSITION".to_owned(),
                vec![0x43, 0x00, 0x05]
            ),
        ]
    );
    assert!(drain(&mut plus, QUIET).await.is_empty());
}

// ---------------------------------------------------------------- 6. lenient mode

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn lenient_mode_passes_undeclared_topics_but_checks_declared_ports() {
    let broker = Broker::start_with(
        Options {
            extra: "[fb]\nundeclared = \"pass\"\n".into(),
            ..Default::default()
        },
        |_| {},
    );
    let mut diag_sub = observer(&broker, "watch", &["fbbus/diag/conv-a"]).await;
    let mut sub = observer(&broker, "sub", &["fb/#", "dinasore/#"]).await;
    let mut dev = Dev::connect(broker.port(), 5, "conv-a");
    declare_ok(&mut dev, CONV, &mut diag_sub, &broker).await;
    let mut legacy = Dev::connect(broker.port(), 5, "legacy");

    // A device that never declared: its typed-namespace topics pass unchecked.
    assert_eq!(legacy.publish("fb/legacy/X/Y", b"anything at all"), 0);
    assert_eq!(
        next_under(&mut sub, "fb/", WAIT).await,
        Some(("fb/legacy/X/Y".to_owned(), b"anything at all".to_vec()))
    );
    assert_eq!(legacy.publish("fb/legacy/short", b"3 levels"), 0);
    assert_eq!(
        next_under(&mut sub, "fb/", WAIT).await,
        Some(("fb/legacy/short".to_owned(), b"3 levels".to_vec()))
    );
    assert_eq!(legacy.publish("dinasore/legacy/X/Y", b"[1]"), 0);
    assert_eq!(
        next_under(&mut sub, "dinasore/", WAIT).await,
        Some(("dinasore/legacy/X/Y".to_owned(), b"[1]".to_vec()))
    );
    // A declared device's undeclared port passes too.
    assert_eq!(dev.publish("fb/conv-a/CONV/GHOST", b"\"boo\""), 0);
    assert_eq!(
        next_under(&mut sub, "fb/", WAIT).await,
        Some(("fb/conv-a/CONV/GHOST".to_owned(), b"\"boo\"".to_vec()))
    );

    // Declared ports are checked: ill-typed is refused and not delivered.
    assert_eq!(dev.publish("fb/conv-a/CONV/POSITION", b"70000"), REFUSED);
    assert_eq!(dev.publish("fb/conv-a/CONV/POSITION", b"true"), REFUSED);
    // Another device's topics are still its own.
    assert_eq!(
        legacy.publish("fb/conv-a/CONV/POSITION", b"1"),
        NOT_AUTHORIZED
    );
    assert_eq!(legacy.publish("fb/conv-a/CONV/GHOST", b"1"), NOT_AUTHORIZED);
    assert_eq!(
        legacy.publish("fbbus/devices/conv-a", b"{}"),
        NOT_AUTHORIZED
    );
    assert_eq!(dev.publish("fb/conv-a/CONV/POSITION", b"12"), 0);
    // Typed and checked, so also re-encoded for the dinasore/# subscriber.
    assert_eq!(
        one_each(
            &mut sub,
            &["fb/conv-a/CONV/POSITION", "dinasore/conv-a/CONV/POSITION"],
            &broker
        )
        .await,
        [b"12".to_vec(), br#"{"POSITION":12}"#.to_vec()]
    );
    assert!(drain(&mut sub, QUIET).await.is_empty());
    assert_metric(
        &broker,
        &rejected_series("conv-a", "CONV.POSITION", "payload_format_invalid"),
        2.0,
    );
    assert_eq!(
        diag(&mut diag_sub, "conv-a", "rejected", &broker).await["code"],
        153
    );
}

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

fn offline_because<'a>(reason: &'a str) -> impl Fn(&Value) -> bool + 'a {
    move |r: &Value| r["status"] == "offline" && r["last_will_reason"] == reason
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

// ---------------------------------------------------------------- 9. stale ends, typed wills

/// Connects a second time with `first`'s client id and waits until the broker has closed
/// `first` (the takeover). Returns the new connection.
fn take_over(first: &mut Dev, port: u16) -> Dev {
    let second = Dev::connect(port, 5, &first.id.clone());
    let closed = tokio::task::block_in_place(|| {
        first.raw.stream.set_read_timeout(Some(WAIT)).unwrap();
        first.raw.closed_by_broker()
    });
    assert!(closed, "the first connection stays open");
    second
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_takeover_leaves_the_device_online_on_the_new_session() {
    let broker = Broker::start();
    let mut diag_sub = observer(&broker, "watch", &["fbbus/diag/conv-a"]).await;
    let mut first = Dev::connect(broker.port(), 5, "conv-a");
    let s1 = declare_ok(&mut first, CONV, &mut diag_sub, &broker).await;

    let mut second = take_over(&mut first, broker.port());
    assert!(broker.wait_metric(r#"fbbus_disconnects_total{reason="takeover"}"#, 1.0) >= 1.0);
    let rec = wait_record(&broker, "conv-a", "moved to the new session", |r| {
        r["session"].as_u64() > Some(s1)
    })
    .await;
    let s2 = rec["session"].as_u64().unwrap();
    assert_eq!(rec["status"], "online", "{rec}");
    assert_eq!(rec["last_will_reason"], Value::Null, "{rec}");

    // The new session has the declared interface without declaring again, and redeclaring
    // answers with its number.
    let mut sub = observer(&broker, "sub", &["fb/conv-a/#"]).await;
    assert_eq!(second.publish("fb/conv-a/CONV/POSITION", b"1"), 0);
    assert_eq!(
        next_on(&mut sub, "fb/conv-a/CONV/POSITION", WAIT)
            .await
            .as_deref(),
        Some(&b"1"[..])
    );
    assert_eq!(
        declare_ok(&mut second, CONV, &mut diag_sub, &broker).await,
        s2
    );
    // Whatever the old connection's end did, it is over: the record is s2's.
    tokio::time::sleep(QUIET).await;
    let rec = record(&broker, "conv-a").unwrap();
    assert_eq!(
        (rec["status"].as_str(), rec["session"].as_u64()),
        (Some("online"), Some(s2)),
        "{rec}"
    );
    second.disconnect();
    let rec = wait_record(
        &broker,
        "conv-a",
        "disconnected",
        offline_because("clean disconnect"),
    )
    .await;
    assert_eq!(rec["session"], s2);
}

/// Device contract section 4: "An end that belongs to an older session (a takeover, a delayed
/// will) never marks a newer session offline." A watcher of the record and of the online
/// count must not see the device go offline while it takes its own client id over.
/// Repeated, because whether the old connection's end lands before or after the new
/// connection reaches the registry is a race: before commit 2c57be9 (the registry learns
/// the new session number before the router link ends the old connection) most takeovers
/// published the device offline and the count at 0.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_takeover_never_shows_the_device_offline() {
    const ROUNDS: u64 = 20;
    let broker = Broker::start();
    let mut diag_sub = observer(&broker, "watch", &["fbbus/diag/conv-a"]).await;
    let mut current = Dev::connect(broker.port(), 5, "conv-a");
    let s1 = declare_ok(&mut current, CONV, &mut diag_sub, &broker).await;
    let mut records = observer(
        &broker,
        "records",
        &["fbbus/devices/conv-a", "fbbus/lines/test/online"],
    )
    .await;
    // The retained record and count first.
    let retained = one_each(
        &mut records,
        &["fbbus/devices/conv-a", "fbbus/lines/test/online"],
        &broker,
    )
    .await;
    assert_eq!(parse(&retained[0])["session"], s1);
    assert_eq!(retained[1], b"1");

    for _ in 0..ROUNDS {
        current = take_over(&mut current, broker.port());
    }
    // The last connection's number, as the device learns it: session numbers come from one
    // counter for all client ids, so it is not s1 + ROUNDS.
    let last = declare_ok(&mut current, CONV, &mut diag_sub, &broker).await;
    assert!(
        last >= s1 + ROUNDS,
        "{last} after {s1} and {ROUNDS} takeovers"
    );
    let rec = wait_record(&broker, "conv-a", "reached the last session", |r| {
        r["session"].as_u64() == Some(last)
    })
    .await;
    assert_eq!(rec["status"], "online");
    let seen: Vec<(String, String)> = drain(&mut records, QUIET)
        .await
        .into_iter()
        .map(|(t, p)| (t, String::from_utf8_lossy(&p).into_owned()))
        .collect();
    let stale = broker.metric("fbbus_registry_stale_ends_total");
    let flaps: Vec<&(String, String)> = seen
        .iter()
        .filter(|(t, p)| {
            if t == "fbbus/lines/test/online" {
                p != "1"
            } else {
                parse(p.as_bytes())["status"] != "online"
            }
        })
        .collect();
    assert!(
        flaps.is_empty() && stale == ROUNDS as f64,
        "{ROUNDS} takeovers: {} published the device offline or the count below 1, \
         fbbus_registry_stale_ends_total = {stale}; first: {:?}",
        flaps.len(),
        flaps.first()
    );
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn typed_wills_are_checked_and_re_encoded() {
    let broker = Broker::start();
    let mut diag_sub = observer(&broker, "watch", &["fbbus/diag/#"]).await;
    let mut wills = observer(
        &broker,
        "wills",
        &["fb/+/CONV/CONNECT", "fbdk/+/CONV/CONNECT"],
    )
    .await;

    // The reference line's CONNECT output: a BOOL data output set to FALSE by the will.
    let connect = |id: &'static str, payload: &'static str| {
        let mut o = V4::options(broker.port(), id, None);
        o.set_last_will(rumqttc::LastWill::new(
            format!("fb/{id}/CONV/CONNECT"),
            payload,
            rumqttc::QoS::AtLeastOnce,
            false,
        ));
        o
    };
    let plc = V4::connect_with(connect("plc", "false")).await.unwrap();
    plc.client
        .publish("fbbus/declare/plc", rumqttc::QoS::AtLeastOnce, false, CONV)
        .await
        .unwrap();
    let answer = diag(&mut diag_sub, "plc", "declaration", &broker).await;
    assert_eq!(answer["ok"], true, "{answer}");
    let session = answer["session"].as_u64().unwrap();
    let mut wills5 = V5::connect(broker.port(), "wills5", None).await.unwrap();
    wills5.subscribe("fb/plc/CONV/CONNECT").await;
    plc.client
        .publish(
            "fb/plc/CONV/CONNECT",
            rumqttc::QoS::AtLeastOnce,
            false,
            "true",
        )
        .await
        .unwrap();
    let pair = ["fb/plc/CONV/CONNECT", "fbdk/plc/CONV/CONNECT"];
    assert_eq!(
        one_each(&mut wills, &pair, &broker).await,
        [b"true".to_vec(), vec![0x41]]
    );
    drop(plc);
    // The will, canonical and re-encoded.
    assert_eq!(
        one_each(&mut wills, &pair, &broker).await,
        [b"false".to_vec(), vec![0x40]]
    );
    // MQTT 5 subscribers see which session the will belongs to.
    let mut will5 = None;
    while let Some(p) = wills5.next_publish(WAIT).await {
        if &p.payload[..] == b"false" {
            will5 = Some(p);
            break;
        }
    }
    let will5 = will5.expect("the will, for the MQTT 5 subscriber");
    let props = will5.properties.unwrap_or_default().user_properties;
    assert!(
        props.contains(&("fbbus-session".to_owned(), session.to_string())),
        "will properties {props:?}, session {session}"
    );
    wait_record(&broker, "plc", "died", offline_because("connection lost")).await;

    // An ill-typed will payload (0 is not a BOOL) is refused like a publication.
    let bad = V4::connect_with(connect("plc-bad", "0")).await.unwrap();
    bad.client
        .publish(
            "fbbus/declare/plc-bad",
            rumqttc::QoS::AtLeastOnce,
            false,
            CONV,
        )
        .await
        .unwrap();
    assert_eq!(
        diag(&mut diag_sub, "plc-bad", "declaration", &broker).await["ok"],
        true
    );
    let wills_before = broker.metric("fbbus_wills_published_total");
    drop(bad);
    wait_record(
        &broker,
        "plc-bad",
        "died",
        offline_because("connection lost"),
    )
    .await;
    assert_metric(
        &broker,
        &rejected_series("plc-bad", "CONV.CONNECT", "payload_format_invalid"),
        1.0,
    );
    let d = diag(&mut diag_sub, "plc-bad", "rejected", &broker).await;
    assert_eq!(d["topic"], "fb/plc-bad/CONV/CONNECT", "{d}");
    let seen = drain(&mut wills, QUIET).await;
    assert!(seen.is_empty(), "an ill-typed will was published: {seen:?}");
    assert_eq!(broker.metric("fbbus_wills_published_total"), wills_before);

    // A will on another device's typed topic is accepted at CONNECT, never published.
    let mut o = V4::options(broker.port(), "intruder", None);
    o.set_last_will(rumqttc::LastWill::new(
        "fb/plc/CONV/CONNECT",
        "true",
        rumqttc::QoS::AtLeastOnce,
        false,
    ));
    let intruder = V4::connect_with(o).await.unwrap();
    drop(intruder);
    assert_metric(
        &broker,
        &rejected_series("undeclared", "undeclared", "not_authorized"),
        1.0,
    );
    assert!(drain(&mut wills, QUIET).await.is_empty());
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
        let file = broker.path("fbbus-registry.json");
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

// ---------------------------------------------------------------- 11. identity

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn with_passwords_only_the_device_itself_speaks_for_it() {
    let broker = Broker::start_with(
        Options {
            extra: "[auth]\npassword_file = \"passwd\"\n".into(),
            ..Default::default()
        },
        |dir| {
            common::add_user(&dir.join("passwd"), "dev1", "pw1");
            common::add_user(&dir.join("passwd"), "dev2", "pw2");
            common::add_user(&dir.join("passwd"), "ops", "pw-ops");
        },
    );
    let ops = |id: &str| {
        let port = broker.port();
        let id = id.to_owned();
        async move {
            V4::connect(port, &id, Some(("ops", "pw-ops")))
                .await
                .unwrap_or_else(|e| panic!("observer {id}: {e}"))
        }
    };
    let mut diag_sub = ops("watch").await;
    diag_sub.subscribe("fbbus/diag/dev1").await;
    let mut sub = ops("sub").await;
    sub.subscribe("fb/#").await;
    let login = |id, user, password| raw::Connect {
        version: 5,
        client_id: id,
        login: Some((user, password)),
        ..Default::default()
    };

    // dev1 itself declares and goes away.
    let mut dev1 = Dev::try_connect(broker.port(), &login("dev1", "dev1", "pw1")).unwrap();
    let s1 = declare_ok(&mut dev1, CONV, &mut diag_sub, &broker).await;
    dev1.disconnect();
    wait_record(
        &broker,
        "dev1",
        "disconnected",
        offline_because("clean disconnect"),
    )
    .await;

    // dev2's credentials with dev1's client id: authenticated, but not dev1.
    let mut impostor = Dev::try_connect(broker.port(), &login("dev1", "dev2", "pw2")).unwrap();
    assert_eq!(impostor.declare(CONV), NOT_AUTHORIZED);
    let d = diag(&mut diag_sub, "dev1", "rejected", &broker).await;
    assert_eq!(d["topic"], "fbbus/declare/dev1");
    assert_eq!(d["code"], 135);
    assert_eq!(
        impostor.publish("fb/dev1/CONV/POSITION", b"1"),
        NOT_AUTHORIZED
    );
    assert_eq!(
        impostor.publish("fbdk/dev1/CONV/POSITION", &[0x43, 0, 1]),
        NOT_AUTHORIZED
    );
    // Nor does its connection bring dev1 online, or change its record.
    let rec = record(&broker, "dev1").unwrap();
    assert_eq!(
        (rec["status"].as_str(), rec["session"].as_u64()),
        (Some("offline"), Some(s1)),
        "{rec}"
    );
    impostor.disconnect();
    assert_metric(
        &broker,
        &rejected_series("undeclared", "undeclared", "not_authorized"),
        3.0,
    );

    // dev2 as itself cannot publish dev1's topics either; on MQTT 3.1.1 they are dropped.
    let mut dev2 = Dev::try_connect(
        broker.port(),
        &raw::Connect {
            version: 4,
            ..login("dev2", "dev2", "pw2")
        },
    )
    .unwrap();
    assert_eq!(dev2.publish("fb/dev1/CONV/POSITION", b"2"), 0);
    assert_eq!(dev2.publish("fbbus/declare/dev1", CONV.as_bytes()), 0);

    // dev1 back: only its own message is delivered.
    let mut dev1 = Dev::try_connect(broker.port(), &login("dev1", "dev1", "pw1")).unwrap();
    assert_eq!(dev1.publish("fb/dev1/CONV/POSITION", b"4"), 0);
    assert_eq!(
        next_under(&mut sub, "fb/", WAIT).await,
        Some(("fb/dev1/CONV/POSITION".to_owned(), b"4".to_vec()))
    );
    assert!(drain(&mut sub, QUIET).await.is_empty());
    let rec = record(&broker, "dev1").unwrap();
    assert_eq!(rec["status"], "online");
    assert!(rec["session"].as_u64() > Some(s1), "{rec}");
    assert_metric(
        &broker,
        &rejected_series("undeclared", "undeclared", "not_authorized"),
        5.0,
    );
}

// ---------------------------------------------------------------- 12. wills on fbbus/

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_will_on_the_broker_namespace_is_refused_at_connect() {
    let broker = Broker::start();
    for (version, refused) in [(4u8, 5u8), (5, 0x87)] {
        for topic in [
            "fbbus/devices/dev1",
            "fbbus/lines/test/online",
            "fbbus/declare/dev1",
            "fbbus/diag/dev1",
        ] {
            let result = Dev::try_connect(
                broker.port(),
                &raw::Connect {
                    version,
                    client_id: "dev1",
                    will: Some((topic, b"{\"status\": \"online\"}")),
                    ..Default::default()
                },
            );
            assert_eq!(result.err(), Some(refused), "v{version} will on {topic}");
        }
    }
    assert_eq!(
        broker.wait_metric(
            r#"fbbus_connects_refused_total{reason="will_not_authorized"}"#,
            8.0
        ),
        8.0
    );
    // A will on the device's own typed topic is fine.
    let dev = Dev::try_connect(
        broker.port(),
        &raw::Connect {
            version: 5,
            client_id: "dev1",
            will: Some(("fb/dev1/CONV/CONNECT", b"false")),
            ..Default::default()
        },
    );
    assert!(dev.is_ok());
}

// ---------------------------------------------------------------- more of section 3

/// QoS 0 and 2, retained messages and topic aliases go through the same check.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn refusals_hold_for_every_qos_retain_and_topic_alias() {
    let broker = Broker::start();
    let mut diag_sub = observer(&broker, "watch", &["fbbus/diag/conv-a"]).await;
    let mut sub = observer(&broker, "sub", &["fb/#"]).await;
    let mut dev = Dev::connect(broker.port(), 5, "conv-a");
    // A declaration at QoS 2 is acknowledged and completed.
    assert_eq!(dev.publish_qos2("fbbus/declare/conv-a", CONV.as_bytes()), 0);
    assert_eq!(
        diag(&mut diag_sub, "conv-a", "declaration", &broker).await["ok"],
        true
    );

    // QoS 2: PUBREC carries the reason and the flow completes.
    assert_eq!(
        dev.publish_qos2("fb/conv-a/CONV/POSITION", b"70000"),
        REFUSED
    );
    assert_eq!(
        dev.publish_qos2("fb/conv-a/CONV/GHOST", b"1"),
        TOPIC_INVALID
    );
    assert_eq!(
        dev.publish_qos2("fb/conv-b/CONV/POSITION", b"1"),
        NOT_AUTHORIZED
    );
    assert_eq!(dev.publish_qos2("fb/conv-a/CONV/POSITION", b"1"), 0);
    // QoS 0: nothing to answer, nothing delivered.
    dev.publish_qos0("fb/conv-a/CONV/POSITION", b"70000");
    dev.publish_qos0("fb/conv-a/CONV/POSITION", b"2");
    // A topic alias: set with a valid message, then used alone.
    assert_eq!(dev.publish_alias("fb/conv-a/CONV/POSITION", 1, b"3"), 0);
    assert_eq!(dev.publish_alias("", 1, b"70000"), REFUSED);
    assert_eq!(dev.publish_alias("", 1, b"4"), 0);
    // Retained: a refused retained message does not replace the retained value.
    assert_eq!(dev.publish_retained("fb/conv-a/CONV/ID", b"\"kept\""), 0);
    assert_eq!(dev.publish_retained("fb/conv-a/CONV/ID", b"17"), REFUSED);
    assert_eq!(
        dev.publish_retained("fbbus/devices/conv-a", b"{}"),
        NOT_AUTHORIZED
    );

    let mut got = Vec::new();
    while got.len() < 5 {
        match next_under(&mut sub, "fb/", WAIT).await {
            Some((t, p)) => got.push((t, String::from_utf8(p).unwrap())),
            None => panic!("only {got:?}\n{}", broker.log_text()),
        }
    }
    let topic = "fb/conv-a/CONV/POSITION".to_owned();
    assert_eq!(
        got,
        [
            (topic.clone(), "1".to_owned()),
            (topic.clone(), "2".to_owned()),
            (topic.clone(), "3".to_owned()),
            (topic, "4".to_owned()),
            ("fb/conv-a/CONV/ID".to_owned(), "\"kept\"".to_owned()),
        ]
    );
    assert!(drain(&mut sub, QUIET).await.is_empty());
    let mut late = observer(
        &broker,
        "late",
        &["fb/conv-a/CONV/ID", "fbbus/devices/conv-a"],
    )
    .await;
    let retained = one_each(
        &mut late,
        &["fb/conv-a/CONV/ID", "fbbus/devices/conv-a"],
        &broker,
    )
    .await;
    assert_eq!(retained[0], b"\"kept\"");
    assert_eq!(parse(&retained[1])["id"], "conv-a");
    assert_metric(
        &broker,
        &rejected_series("conv-a", "CONV.POSITION", "payload_format_invalid"),
        3.0,
    );
    assert_metric(
        &broker,
        &rejected_series("conv-a", "CONV.ID", "payload_format_invalid"),
        1.0,
    );
}

/// A device looping on a bad message gets explanations at a bounded rate: a burst of 20,
/// then 5 per second; every refusal is still counted.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn rejection_diagnostics_are_rate_limited() {
    const SENT: usize = 60;
    let broker = Broker::start();
    let mut diag_sub = observer(&broker, "watch", &["fbbus/diag/conv-a"]).await;
    let mut dev = Dev::connect(broker.port(), 5, "conv-a");
    declare_ok(&mut dev, CONV, &mut diag_sub, &broker).await;
    let start = Instant::now();
    for _ in 0..SENT {
        assert_eq!(dev.publish("fb/conv-a/CONV/POSITION", b"70000"), REFUSED);
    }
    let elapsed = start.elapsed().as_secs_f64();
    assert_metric(
        &broker,
        &rejected_series("conv-a", "CONV.POSITION", "payload_format_invalid"),
        SENT as f64,
    );
    let diags = drain(&mut diag_sub, QUIET).await;
    let allowed = 20 + (elapsed * 5.0).ceil() as usize;
    assert!(
        diags.len() >= 20 && diags.len() <= allowed,
        "{} diagnostics for {SENT} refusals in {elapsed:.2} s (allowed 20..={allowed})",
        diags.len()
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
        "data_out": {"MASK": "WORD", "CYCLE": "TIME", "DAY": "DATE"}}}}"#;
    let broker = Broker::start();
    let mut diag_sub = observer(&broker, "watch", &["fbbus/diag/conv-a"]).await;
    let mut sub = observer(&broker, "sub", &["fb/conv-a/#"]).await;
    let mut dev = Dev::connect(broker.port(), 5, "conv-a");
    declare_ok(&mut dev, decl, &mut diag_sub, &broker).await;
    let cases: [(&str, &str, Value); 6] = [
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
}

// ---------------------------------------------------------------- a device from the README

const CONTRACT_SCRIPT: &str = concat!(env!("CARGO_MANIFEST_DIR"), "/tests/python/fb_contract.py");

/// A paho-mqtt device that knows only docs/device-contract.md declares, publishes, is
/// refused, reads both encodings and the registry (see the script's docstring).
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn python_device_follows_the_readme_contract() {
    if !common::require_paho() {
        return;
    }
    let broker = Broker::start();
    let (ok, out, err) = tokio::task::block_in_place(|| {
        common::run(
            Command::new("python3")
                .arg("-u")
                .arg(CONTRACT_SCRIPT)
                .args(["--port", &broker.port().to_string()]),
            Duration::from_secs(60),
        )
    });
    assert!(
        ok,
        "fb_contract.py failed\n--- stdout\n{out}\n--- stderr\n{err}\n--- broker log\n{}",
        broker.log_text()
    );
    eprintln!("fb_contract.py: {}", out.trim());
    // The broker's side of the same story.
    assert_metric(
        &broker,
        r#"fbbus_declarations_total{result="accepted"}"#,
        1.0,
    );
    assert_eq!(
        broker.wait_metric(
            &rejected_series("py-dev", "CONV.MOVED", "payload_format_invalid"),
            1.0
        ),
        1.0
    );
    assert_metric(&broker, "fbbus_typed_messages_accepted_total", 2.0);
    // It disconnected cleanly at the end.
    wait_record(
        &broker,
        "py-dev",
        "disconnected",
        offline_because("clean disconnect"),
    )
    .await;
}

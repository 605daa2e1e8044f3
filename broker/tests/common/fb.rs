//! Support for the typed-topic tests (`tests/fb_*.rs`): the reference interfaces, raw
//! MQTT devices, observers and the registry's views.
//!
//! Devices whose PUBACK reason code must be observed exactly are raw MQTT connections
//! (`super::raw`): rumqttc's v5 client ends its connection on a refusing PUBACK.
//! Observers are rumqttc clients. Every wait is bounded; the negative checks ("nothing was
//! delivered") either wait for a later valid message on the same subscription (ordered
//! after the refused one) or for a short fixed window when there is nothing valid to
//! follow.

use std::time::{Duration, Instant, SystemTime, UNIX_EPOCH};

use serde_json::Value;

use super::clients::{V4, WAIT};
use super::raw::{self, RawClient};
use super::Broker;

// ---------------------------------------------------------------- fixtures

/// The reference interface: a conveyor with data and event outputs, and inputs.
pub const CONV: &str = r#"{"fbs": {"CONV": {
    "type": "CONVEYOR",
    "events_out": {"MOVED": {"with": ["POSITION", "SENSOR_IN"]}, "TICK": {"with": []}},
    "events_in": {"START": {"with": ["SPEED"]}},
    "data_out": {"POSITION": "INT", "SENSOR_IN": "BOOL", "ID": "STRING", "CONNECT": "BOOL"},
    "data_in": {"SPEED": "REAL"}
}}}"#;

/// For the encoding tests: one port per interesting fbdk layout.
pub const FORTE: &str = r#"{"fbs": {"CONV": {
    "type": "CONVEYOR",
    "events_out": {"MOVED": {"with": ["POSITION", "SENSOR_IN"]}, "TICK": {"with": []}},
    "data_out": {
        "POSITION": "INT", "SENSOR_IN": "BOOL", "ID": "STRING", "SPEED": "REAL",
        "CYCLE": "TIME", "DAY": "DATE", "LEVELS": "ARRAY [3] OF INT",
        "FLAGS": "ARRAY [0..1] OF BOOL"
    }
}}}"#;

pub const REFUSED: u8 = 0x99;
pub const NOT_AUTHORIZED: u8 = 0x87;
pub const TOPIC_INVALID: u8 = 0x90;

/// Long enough for a message the broker would wrongly route to arrive on loopback.
pub const QUIET: Duration = Duration::from_millis(400);

pub fn now_us() -> u64 {
    SystemTime::now()
        .duration_since(UNIX_EPOCH)
        .unwrap()
        .as_micros() as u64
}

// ---------------------------------------------------------------- raw devices

/// A device on a raw MQTT connection, publishing at QoS 1 and reading its PUBACKs.
pub struct Dev {
    pub raw: RawClient,
    pub version: u8,
    pub pkid: u16,
    pub id: String,
}

/// A QoS 1 PUBLISH in MQTT 3.1.1 framing.
pub fn publish_v4_qos1(topic: &str, pkid: u16, payload: &[u8]) -> Vec<u8> {
    let mut body = Vec::new();
    body.extend_from_slice(&(topic.len() as u16).to_be_bytes());
    body.extend_from_slice(topic.as_bytes());
    body.extend_from_slice(&pkid.to_be_bytes());
    body.extend_from_slice(payload);
    raw::packet(0x32, &body)
}

impl Dev {
    /// Connects with `connect`; Err carries the CONNACK code of a refusal.
    pub fn try_connect(port: u16, connect: &raw::Connect) -> Result<Dev, u8> {
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

    /// Connects with `connect` from the loopback address `source`; panics if refused.
    pub fn connect_from(broker: &super::Broker, source: &str, connect: &raw::Connect) -> Dev {
        tokio::task::block_in_place(|| {
            let mut raw = RawClient::connect_from(broker.mqtt, source);
            let code = raw.handshake(connect);
            assert_eq!(code, 0, "{} refused", connect.client_id);
            Dev {
                raw,
                version: connect.version,
                pkid: 0,
                id: connect.client_id.to_owned(),
            }
        })
    }

    pub fn connect(port: u16, version: u8, id: &str) -> Dev {
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

    pub fn next_pkid(&mut self) -> u16 {
        self.pkid = self.pkid % 60_000 + 1;
        self.pkid
    }

    /// Publishes at QoS 1; returns the PUBACK reason code (always 0 on MQTT 3.1.1, which
    /// has none). Panics if the connection ends before the PUBACK.
    pub fn publish(&mut self, topic: &str, payload: &[u8]) -> u8 {
        let pkid = self.next_pkid();
        let packet = if self.version == 5 {
            raw::publish_v5(topic, None, 1, pkid, payload)
        } else {
            publish_v4_qos1(topic, pkid, payload)
        };
        self.send_for_ack(&packet, pkid, 4, topic)
    }

    /// An MQTT 5 QoS 1 publication with a topic alias (`topic` may be empty to use it).
    pub fn publish_alias(&mut self, topic: &str, alias: u16, payload: &[u8]) -> u8 {
        let pkid = self.next_pkid();
        let packet = raw::publish_v5(topic, Some(alias), 1, pkid, payload);
        self.send_for_ack(&packet, pkid, 4, topic)
    }

    /// An MQTT 5 QoS 2 publication: returns the PUBREC reason, then completes the flow
    /// (PUBREL, PUBCOMP) whatever the reason.
    pub fn publish_qos2(&mut self, topic: &str, payload: &[u8]) -> u8 {
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
    pub fn publish_qos0(&mut self, topic: &str, payload: &[u8]) {
        let mut body = (topic.len() as u16).to_be_bytes().to_vec();
        body.extend_from_slice(topic.as_bytes());
        if self.version == 5 {
            body.push(0);
        }
        body.extend_from_slice(payload);
        tokio::task::block_in_place(|| self.raw.send(&raw::packet(0x30, &body)));
    }

    /// A retained QoS 1 publication; returns the PUBACK reason.
    pub fn publish_retained(&mut self, topic: &str, payload: &[u8]) -> u8 {
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
    pub fn send_for_ack(&mut self, packet: &[u8], pkid: u16, kind: u8, topic: &str) -> u8 {
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

    pub fn publish_json(&mut self, topic: &str, payload: &Value) -> u8 {
        self.publish(topic, payload.to_string().as_bytes())
    }

    pub fn declare(&mut self, declaration: &str) -> u8 {
        let topic = format!("fbbus/declare/{}", self.id);
        self.publish(&topic, declaration.as_bytes())
    }

    /// A clean DISCONNECT (reason 0 on MQTT 5), then waits for the broker to close.
    pub fn disconnect(mut self) {
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

pub async fn observer(broker: &Broker, id: &str, filters: &[&str]) -> V4 {
    let mut sub = V4::connect(broker.port(), id, None)
        .await
        .unwrap_or_else(|e| panic!("observer {id}: {e}\n{}", broker.log_text()));
    subscribe_all(&mut sub, filters).await;
    sub
}

/// Subscribes to every filter in one SUBSCRIBE, so no retained message is skipped while
/// waiting for a later SUBACK (the broker sends the SUBACK before retained messages).
pub async fn subscribe_all(sub: &mut V4, filters: &[&str]) {
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
pub async fn one_each(sub: &mut V4, topics: &[&str], broker: &Broker) -> Vec<Vec<u8>> {
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
pub async fn next_on(sub: &mut V4, topic: &str, within: Duration) -> Option<Vec<u8>> {
    sub.next(within, |p| match p {
        rumqttc::Packet::Publish(p) if p.topic == topic => Some(p.payload.to_vec()),
        _ => None,
    })
    .await
}

/// The next publication whose topic starts with `prefix`: (topic, payload).
pub async fn next_under(sub: &mut V4, prefix: &str, within: Duration) -> Option<(String, Vec<u8>)> {
    sub.next(within, |p| match p {
        rumqttc::Packet::Publish(p) if p.topic.starts_with(prefix) => {
            Some((p.topic.clone(), p.payload.to_vec()))
        }
        _ => None,
    })
    .await
}

/// Every publication received within `within`: (topic, payload).
pub async fn drain(sub: &mut V4, within: Duration) -> Vec<(String, Vec<u8>)> {
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

pub fn parse(bytes: &[u8]) -> Value {
    serde_json::from_slice(bytes)
        .unwrap_or_else(|e| panic!("not JSON ({e}): {}", String::from_utf8_lossy(bytes)))
}

/// The next JSON message on `topic`, or a panic naming what was awaited.
pub async fn json_on(sub: &mut V4, topic: &str, broker: &Broker) -> Value {
    let bytes = next_on(sub, topic, WAIT).await.unwrap_or_else(|| {
        panic!(
            "nothing on {topic} within {WAIT:?}\n--- broker log\n{}",
            broker.log_text()
        )
    });
    parse(&bytes)
}

/// The next diag message of `kind` on `fbbus/diag/<id>`.
pub async fn diag(sub: &mut V4, id: &str, kind: &str, broker: &Broker) -> Value {
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

pub fn http_json(broker: &Broker, path: &str) -> (u16, Value) {
    let (code, body) = super::http_get(broker.admin, path)
        .unwrap_or_else(|| panic!("GET {path}: no answer from {}", broker.admin));
    let json = serde_json::from_str(&body)
        .unwrap_or_else(|e| panic!("GET {path}: {code}, body not JSON ({e}): {body}"));
    (code, json)
}

pub fn record(broker: &Broker, id: &str) -> Option<Value> {
    let (code, json) = http_json(broker, &format!("/api/v1/devices/{id}"));
    match code {
        200 => Some(json),
        404 => None,
        _ => panic!("GET /api/v1/devices/{id}: {code} {json}"),
    }
}

/// Polls the registry until `id`'s record satisfies `pred` (at most 10 s).
pub async fn wait_record(
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

pub fn rejected_series(device: &str, port: &str, reason: &str) -> String {
    format!(
        "fbbus_typed_messages_rejected_total{{device=\"{device}\",port=\"{port}\",reason=\"{reason}\"}}"
    )
}

/// Waits for a metric to reach `min` and asserts it did, with everything that helps.
pub fn assert_metric(broker: &Broker, series: &str, min: f64) -> f64 {
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
pub async fn declare_ok(
    dev: &mut Dev,
    declaration: &str,
    diag_sub: &mut V4,
    broker: &Broker,
) -> u64 {
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

pub fn offline_because<'a>(reason: &'a str) -> impl Fn(&Value) -> bool + 'a {
    move |r: &Value| r["status"] == "offline" && r["last_will_reason"] == reason
}

/// Builds the example (a no-op when `cargo test --workspace` already did) and returns it.
pub fn conveyor_example() -> std::path::PathBuf {
    let (ok, _, err) = super::run(
        std::process::Command::new(env!("CARGO")).args([
            "build",
            "-p",
            "fb-bridge",
            "--example",
            "conveyor",
        ]),
        std::time::Duration::from_secs(600),
    );
    assert!(ok, "cannot build the conveyor example: {err}");
    // target/debug/fbbus -> target/debug/examples/conveyor
    std::path::PathBuf::from(env!("CARGO_BIN_EXE_fbbus"))
        .with_file_name("examples")
        .join("conveyor")
}

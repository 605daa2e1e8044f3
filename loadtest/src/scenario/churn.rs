//! `churn`: many short-lived connections (100,000 by default), the way a line's devices,
//! scanners and broken clients come and go, to see what a broker keeps of them.
//!
//! Each connection is one of (weights in %):
//! - `valid` (25): clean CONNECT, SUBSCRIBE `churn/<id>/cmd`, a PUBLISH on
//!   `churn/<id>/state` (QoS 0 or 1; 1 in 20 on `churn/broadcast`), PINGREQ, DISCONNECT,
//!   and waits for the broker to close;
//! - `pipelined` (5): CONNECT, PUBLISH (QoS 1), PINGREQ and DISCONNECT in one write, as a
//!   client that does not wait for the CONNACK (MQTT allows it, 3.1.4); half of them in
//!   under 64 bytes (`short`), half with a SUBSCRIBE and longer names (`long`): the
//!   broker must answer and close within `--read-ms` of the CONNACK
//!   (`pipelined_short_closed`, `pipelined_long_closed`, `pipelined_puback`; else
//!   `pipelined_*_left_open`);
//! - `persistent_random` (15): clean session 0 (MQTT 5: session expiry 1 h) with a client
//!   id never used again, subscribed to `churn/<id>/cmd` and `churn/broadcast` at QoS 1,
//!   then DISCONNECT: every one leaves a saved session (what the router's saved-session
//!   table must bound);
//! - `persistent_recurring` (15): the same with ids from a recurring set of
//!   `--recurring-ids` (devices that come back; concurrent ones take each other over);
//!   DISCONNECT or a reset;
//! - `abrupt` (15): valid CONNECT (some with a will), the CONNACK, perhaps a PUBLISH,
//!   then a reset or a close without DISCONNECT;
//! - `malformed` (10): a first packet that is not valid MQTT (junk, an HTTP request, a TLS
//!   ClientHello, a bad protocol name or level, reserved flags, a 5-byte or 256 MB
//!   remaining length, PUBLISH before CONNECT, invalid UTF-8 client id, ...); waits for
//!   the answer, closes;
//! - `abandoned` (15): part of a CONNECT (possibly nothing), then a reset or close.
//!
//! Half MQTT 3.1.1, half MQTT 5. `--mix persistent_random=1` runs other weights (kinds
//! not named: none), to see what one kind of connection leaves behind. See [`campaign`] for the rounds, the
//! routing probe, memory and the verdict.

use std::sync::Arc;
use std::time::{Duration, Instant};

use serde::Serialize;

use super::campaign::{self, Campaign, Close, Conn, Ctx, Outcome, Start};
use crate::rng::Rng;
use crate::session::Session;
use crate::target::Target;
use crate::wire::{self, prop, Connect, Props, Will, V311, V5};

/// `churn`'s parameters.
#[derive(Debug, Clone, Serialize)]
pub struct Churn {
    #[serde(flatten)]
    pub campaign: Campaign,
    /// Client ids of the `persistent_recurring` connections.
    pub recurring_ids: u64,
    /// Weight of each kind of connection, in the order of [`KIND_NAMES`].
    pub mix: Vec<(String, u32)>,
}

/// The kinds of connection, by name (`--mix valid=1,abrupt=1`).
pub const KIND_NAMES: [&str; 7] = [
    "valid",
    "pipelined",
    "persistent_random",
    "persistent_recurring",
    "abrupt",
    "malformed",
    "abandoned",
];

/// The default mix, in percent.
pub const DEFAULT_MIX: [u32; 7] = [25, 5, 15, 15, 15, 10, 15];

/// Parses `--mix` (`valid=30,abrupt=15`; kinds not named get weight 0); empty: the
/// default mix.
pub fn parse_mix(text: &str) -> Result<Vec<(String, u32)>, String> {
    if text.trim().is_empty() {
        return Ok(KIND_NAMES
            .iter()
            .zip(DEFAULT_MIX)
            .map(|(k, w)| (k.to_string(), w))
            .collect());
    }
    let mut weights = [0u32; 7];
    for part in text.split(',') {
        let (name, weight) = part
            .split_once('=')
            .ok_or_else(|| format!("{part:?}: expected KIND=WEIGHT"))?;
        let k = KIND_NAMES
            .iter()
            .position(|n| *n == name.trim())
            .ok_or_else(|| format!("{name:?}: kinds are {}", KIND_NAMES.join(", ")))?;
        weights[k] = weight
            .trim()
            .parse()
            .map_err(|_| format!("{weight:?}: not a whole number"))?;
    }
    if weights.iter().all(|w| *w == 0) {
        return Err("every weight is 0".into());
    }
    Ok(KIND_NAMES
        .iter()
        .zip(weights)
        .map(|(k, w)| (k.to_string(), w))
        .collect())
}

/// This campaign's generator stream (see [`Rng::for_item`]).
const STREAM: u64 = 2;

#[derive(Debug, Clone, Copy)]
enum Kind {
    Valid,
    Pipelined,
    PersistentRandom,
    PersistentRecurring,
    Abrupt,
    Malformed,
    Abandoned,
}

/// In the order of [`KIND_NAMES`].
const KINDS: [Kind; 7] = [
    Kind::Valid,
    Kind::Pipelined,
    Kind::PersistentRandom,
    Kind::PersistentRecurring,
    Kind::Abrupt,
    Kind::Malformed,
    Kind::Abandoned,
];

impl Kind {
    fn label(self) -> &'static str {
        match self {
            Kind::Valid => "kind_valid",
            Kind::Pipelined => "kind_pipelined",
            Kind::PersistentRandom => "kind_persistent_random",
            Kind::PersistentRecurring => "kind_persistent_recurring",
            Kind::Abrupt => "kind_abrupt",
            Kind::Malformed => "kind_malformed",
            Kind::Abandoned => "kind_abandoned",
        }
    }
}

impl Churn {
    pub fn planned(&self, targets: usize) -> u64 {
        super::mutate::rounds(&self.campaign) * targets as u64
    }

    pub async fn run(&self, s: &mut Session, targets: &[Target], prefix: &str) -> Vec<String> {
        let recurring = self.recurring_ids.max(1);
        let weights: Arc<[u32]> = self.mix.iter().map(|(_, w)| *w).collect();
        campaign::run(
            s,
            targets,
            prefix,
            &self.campaign,
            "churn",
            move |ctx, i| connection(ctx, i, recurring, weights.clone()),
        )
        .await
    }
}

/// Connection `i` of the campaign.
pub async fn connection(ctx: Arc<Ctx>, i: u64, recurring: u64, weights: Arc<[u32]>) -> Outcome {
    let mut rng = Rng::for_item(ctx.seed, STREAM, i);
    let mut o = Outcome::default();
    let kind = KINDS[rng.weighted(&weights).min(KINDS.len() - 1)];
    let level = if rng.chance(0.5) { V5 } else { V311 };
    o.label(kind.label());
    o.label(if level == V5 { "mqtt_5" } else { "mqtt_3_1_1" });
    let prefix = &ctx.prefix;
    let seed = ctx.seed;
    let (user, password) = ctx.login();
    let connect = |id: String, clean: bool| {
        let mut c = Connect::new(level, id);
        c.clean = clean;
        if level == V5 && !clean {
            c.properties = Props::new().u32(prop::SESSION_EXPIRY, 3600);
        }
        (c.username, c.password) = (user.clone(), password.clone());
        c
    };

    let Ok(mut conn) = Conn::open(&ctx, i).await else {
        o.start = Start::TcpFailed;
        return o;
    };
    match kind {
        Kind::Valid | Kind::PersistentRandom | Kind::PersistentRecurring => {
            let (id, clean) = match kind {
                Kind::Valid => (format!("{prefix}-c{seed}-{i}"), true),
                Kind::PersistentRandom => (format!("{prefix}-cr{seed}-{i}"), false),
                _ => (format!("{prefix}-cp-{}", i % recurring), false),
            };
            if !begin(&mut conn, &mut o, &ctx, &connect(id.clone(), clean)).await {
                return o;
            }
            let mut filters = vec![(format!("churn/{id}/cmd").into_bytes(), 1u8)];
            if !clean {
                filters.push((b"churn/broadcast".to_vec(), 1));
            }
            let sub = wire::subscribe(level, campaign::pid(&mut rng), &Props::new(), &filters);
            let qos = rng.below(2) as u8;
            let topic = if rng.chance(0.05) {
                "churn/broadcast".to_owned()
            } else {
                format!("churn/{id}/state")
            };
            let payload = format!("{{\"i\":{i},\"état\":\"läuft\"}}");
            let publ = wire::publish(
                level,
                topic.as_bytes(),
                qos,
                false,
                false,
                campaign::pid(&mut rng),
                &Props::new(),
                payload.as_bytes(),
            );
            for p in [sub, publ, wire::pingreq()] {
                if !conn.packet(&mut o, &p, false).await {
                    break;
                }
            }
            conn.drain(&mut o);
            let how = if matches!(kind, Kind::PersistentRecurring) && rng.chance(0.3) {
                Close::Reset
            } else {
                conn.packet(&mut o, &wire::disconnect(level, None), false)
                    .await;
                Close::Disconnect
            };
            conn.close(&mut o, how, ctx.read).await;
        }
        Kind::Pipelined => {
            // Short: CONNECT, PUBLISH, PINGREQ, DISCONNECT in under 64 bytes, what a small
            // device sends in one segment; long: with a SUBSCRIBE and longer names.
            let short = rng.chance(0.5);
            let id = if short {
                format!("{prefix}-q{i}")
            } else {
                format!("{prefix}-cq{seed}-{i}")
            };
            let mut bytes = connect(id.clone(), true).encode();
            let mut packets = 4;
            let topic = if short {
                "churn/q".to_owned()
            } else {
                let filters = [(format!("churn/{id}/cmd").into_bytes(), 1u8)];
                bytes.extend(wire::subscribe(level, 1, &Props::new(), &filters));
                packets += 1;
                format!("churn/{id}/state")
            };
            let payload: &[u8] = if short { b"1" } else { b"pipelined" };
            let publish = wire::publish(
                level,
                topic.as_bytes(),
                1,
                false,
                false,
                2,
                &Props::new(),
                payload,
            );
            bytes.extend(publish);
            bytes.extend(wire::pingreq());
            bytes.extend(wire::disconnect(level, None));
            o.valid_connect = true;
            let sent = Instant::now();
            if !conn.send(&mut o, &bytes).await {
                o.start = Start::ClosedWithoutAnswer;
                o.closed_by_broker = true;
                return o;
            }
            o.packets += packets;
            conn.await_answer(&mut o, ctx.connack, sent).await;
            if o.start != Start::Accepted {
                o.closed_by_broker = conn.closed;
                return o;
            }
            // Everything the broker answers, until it closes (it must: DISCONNECT).
            conn.read_until(&mut o, ctx.read, |_| false).await;
            if wire::packet_types(&conn.received).contains(&0x40) {
                o.label("pipelined_puback");
            }
            o.label(match (short, conn.closed) {
                (true, true) => "pipelined_short_closed",
                (true, false) => "pipelined_short_left_open",
                (false, true) => "pipelined_long_closed",
                (false, false) => "pipelined_long_left_open",
            });
            o.close = Some(Close::Disconnect);
        }
        Kind::Abrupt => {
            let mut c = connect(format!("{prefix}-ca{seed}-{i}"), rng.chance(0.7));
            if rng.chance(0.3) {
                c.will = Some(Will {
                    topic: format!("churn/will/{}", i % 50).into_bytes(),
                    payload: b"gone".to_vec(),
                    qos: rng.below(2) as u8,
                    retain: false,
                    properties: Props::new(),
                });
            }
            if !begin(&mut conn, &mut o, &ctx, &c).await {
                return o;
            }
            if rng.chance(0.5) {
                let p = wire::publish(
                    level,
                    format!("churn/{prefix}-ca{seed}-{i}/state").as_bytes(),
                    0,
                    false,
                    false,
                    0,
                    &Props::new(),
                    b"1",
                );
                conn.packet(&mut o, &p, false).await;
            }
            let how = if rng.chance(0.6) {
                Close::Reset
            } else {
                Close::Drop
            };
            conn.close(&mut o, how, ctx.read).await;
        }
        Kind::Malformed => {
            let (bytes, label) = malformed(&mut rng, level, &format!("{prefix}-cm{seed}-{i}"));
            o.label(label);
            let sent = Instant::now();
            if !conn.packet(&mut o, &bytes, true).await {
                o.start = Start::ClosedWithoutAnswer;
                o.closed_by_broker = true;
                return o;
            }
            conn.await_answer(&mut o, ctx.read, sent).await;
            if o.start == Start::Accepted {
                // A broker that takes this for a CONNECT: which ones, in the report.
                o.label(&format!("accepted_{label}"));
            }
            conn.close(&mut o, Close::Drop, ctx.read).await;
        }
        Kind::Abandoned => {
            let full = connect(format!("{prefix}-cb{seed}-{i}"), true).encode();
            let cut = rng.below(full.len() as u64) as usize;
            if cut > 0 && conn.send(&mut o, &full[..cut]).await {
                o.partial += 1;
            }
            if rng.chance(0.3) {
                tokio::time::sleep(Duration::from_millis(rng.range(1, 20))).await;
            }
            o.start = Start::NotAwaited;
            let how = if rng.chance(0.5) {
                Close::Reset
            } else {
                Close::Drop
            };
            conn.close(&mut o, how, ctx.read).await;
        }
    }
    o
}

/// Sends a valid CONNECT and waits for the CONNACK; false when the session cannot go on
/// (refused, closed, no answer: the connection is then closed and counted).
async fn begin(conn: &mut Conn, o: &mut Outcome, ctx: &Ctx, c: &Connect) -> bool {
    o.valid_connect = true;
    let sent = Instant::now();
    if !conn.packet(o, &c.encode(), false).await {
        o.start = Start::ClosedWithoutAnswer;
        o.closed_by_broker = true;
        return false;
    }
    conn.await_answer(o, ctx.connack, sent).await;
    if o.start == Start::Accepted && !conn.closed {
        return true;
    }
    if conn.closed {
        o.closed_by_broker = true;
    }
    false
}

/// A first packet that is not a valid CONNECT, and its label.
fn malformed(rng: &mut Rng, level: u8, id: &str) -> (Vec<u8>, &'static str) {
    let valid = Connect::new(level, id);
    let mut bytes = valid.encode();
    let header = wire::header_len(&bytes);
    match rng.below(14) {
        0 => {
            let n = rng.range(1, 64) as usize;
            (rng.bytes(n), "malformed_junk")
        }
        1 => {
            bytes[header + 5] = b'X';
            (bytes, "malformed_protocol_name")
        }
        2 => {
            bytes[header + 6] = *rng.pick(&[0u8, 2, 6, 7, 0x84]);
            (bytes, "malformed_protocol_level")
        }
        3 => {
            bytes[header + 7] |= 0x01;
            (bytes, "malformed_reserved_flag")
        }
        4 => (
            vec![0x10, 0xFF, 0xFF, 0xFF, 0xFF, 0x7F, 0, 4],
            "malformed_varint_overflow",
        ),
        5 => {
            let mut b = vec![0x10];
            b.extend(wire::varint(u64::from(wire::MAX_REMAINING)));
            b.extend_from_slice(&bytes[header..]);
            (b, "malformed_oversized_length")
        }
        6 => (
            wire::publish(
                level,
                "é/x".as_bytes(),
                0,
                false,
                false,
                0,
                &Props::new(),
                b"x",
            ),
            "malformed_publish_first",
        ),
        7 => {
            let mut c = valid.clone();
            c.client_id = b"\xC3\x28".to_vec();
            (c.encode(), "malformed_invalid_utf8_client_id")
        }
        8 => {
            let half = bytes.len() / 2;
            bytes.truncate(half);
            let n = rng.range(8, 64) as usize;
            bytes.extend(rng.bytes(n));
            (bytes, "malformed_truncated_then_garbage")
        }
        9 => {
            let mut c = valid.clone();
            c.will = Some(Will {
                topic: b"churn/will".to_vec(),
                payload: Vec::new(),
                qos: 3,
                retain: false,
                properties: Props::new(),
            });
            (c.encode(), "malformed_will_qos3")
        }
        10 => (
            b"GET / HTTP/1.1\r\nHost: 127.0.0.1\r\n\r\n".to_vec(),
            "malformed_http_request",
        ),
        11 => {
            // The start of a TLS 1.2/1.3 ClientHello: a TLS client on the plain port.
            let mut b = vec![
                0x16, 0x03, 0x01, 0x00, 0xC8, 0x01, 0x00, 0x00, 0xC4, 0x03, 0x03,
            ];
            b.extend(rng.bytes(32));
            (b, "malformed_tls_client_hello")
        }
        12 => (vec![0x10, 0x00], "malformed_empty_connect"),
        _ => {
            // Password flag without username (3.1.1 forbids it).
            bytes[header + 7] = (bytes[header + 7] & !0x80) | 0x40;
            bytes.extend(wire::string(b"pw"));
            let body = bytes[header..].to_vec();
            (
                wire::packet(0x10, &body),
                "malformed_password_without_username",
            )
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn mixes_parse() {
        let default = parse_mix("").unwrap();
        assert_eq!(default.iter().map(|(_, w)| w).sum::<u32>(), 100);
        let only = parse_mix("persistent_random=1, abrupt = 3").unwrap();
        assert_eq!(only[2], ("persistent_random".into(), 1));
        assert_eq!(only[4], ("abrupt".into(), 3));
        let others: u32 = only.iter().map(|(_, w)| w).sum::<u32>() - 4;
        assert_eq!(others, 0);
        assert!(parse_mix("nope=1").is_err());
        assert!(parse_mix("valid").is_err());
        assert!(parse_mix("valid=0").is_err());
    }

    #[test]
    fn malformed_packets_are_not_valid_connects() {
        let mut rng = Rng::new(5);
        let valid = Connect::new(V311, "x").encode();
        for _ in 0..200 {
            let (bytes, label) = malformed(&mut rng, V311, "x");
            assert!(label.starts_with("malformed_"));
            assert_ne!(bytes, valid, "{label}");
        }
    }
}

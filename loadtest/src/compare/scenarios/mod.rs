//! The measurements of `compare`: the earlier broker study's six, and (issue 34) the
//! fan-in at QoS 1 (`fanin1`) and independent publisher/subscriber pairs (`pairs`). Each
//! runs against one freshly started broker, is bounded by a count and a deadline, and
//! returns what it measured as an [`Outcome`] (also after a timeout).
//!
//! The bursts (`fanin`, `fanin1`, `pairs`, `latency`, `msgmem`) write raw PUBLISH packets
//! ([`loadtest::raw_client`]): 200,000 messages into one subscriber are beyond what a
//! client library generates on a shared 2-core machine. The connection scenarios
//! (`idlemem`, `connrate`, `connect1`, `authstorm`) are the harness's own connection wave and
//! idle-memory measurement ([`loadtest::scenario::connections`]).
//!
//! Here: the scenarios, their parameters and outcome, and the figures' formatting; the
//! bursts are in `bursts`, the connection scenarios in `waves`.

use anyhow::{Context as _, Result};
use hdrhistogram::Histogram;

use std::time::Duration;

use loadtest::broker_process::spawn::Running;
use loadtest::raw_client::{self as mqtt};

mod bursts;
mod waves;

use bursts::{latency, message_memory, throughput, Shape};
use waves::{auth_storm, connect_latency, connection_rate, idle_memory};

/// How the storm's devices log in: user `<STORM_USER_PREFIX><i>` for device `i`, all
/// with one password (each user's hash has its own salt, so every login costs the broker
/// a full verification).
#[derive(Clone)]
pub struct Login {
    pub password: String,
}

/// The storm's user names: `plc-0`, `plc-1`, ...
pub const STORM_USER_PREFIX: &str = "plc-";

/// Payload size of every message.
pub const PAYLOAD_BYTES: usize = 32;
/// Time to open one client connection before it counts as failed.
const CONNECT_TIMEOUT: Duration = Duration::from_secs(10);

#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Scenario {
    Fanin,
    /// The fan-in at QoS 1 (publishers and subscriber), whatever the other rows use.
    Fanin1,
    Pairs,
    Latency,
    IdleMem,
    MsgMem,
    ConnRate,
    /// One connection at a time: how long one device waits for its CONNACK.
    Connect1,
    AuthStorm,
}

impl Scenario {
    pub const ALL: [Scenario; 9] = [
        Scenario::Fanin,
        Scenario::Fanin1,
        Scenario::Pairs,
        Scenario::Latency,
        Scenario::IdleMem,
        Scenario::MsgMem,
        Scenario::ConnRate,
        Scenario::Connect1,
        Scenario::AuthStorm,
    ];

    pub fn name(self) -> &'static str {
        match self {
            Scenario::Fanin => "fanin",
            Scenario::Fanin1 => "fanin1",
            Scenario::Pairs => "pairs",
            Scenario::Latency => "latency",
            Scenario::IdleMem => "idlemem",
            Scenario::MsgMem => "msgmem",
            Scenario::ConnRate => "connrate",
            Scenario::Connect1 => "connect1",
            Scenario::AuthStorm => "authstorm",
        }
    }

    pub fn parse(name: &str) -> Option<Scenario> {
        Scenario::ALL.into_iter().find(|s| s.name() == name)
    }

    /// Short title with the exact parameters, used in the header and the ratio line.
    pub fn title(self, p: &Params) -> String {
        match self {
            Scenario::Fanin => format!(
                "burst fan-in ({} x {} x {PAYLOAD_BYTES} B, QoS 0)",
                p.publishers, p.fanin_messages
            ),
            // Not "burst fan-in ...": the QoS 0 row's title is what its line starts with.
            Scenario::Fanin1 => format!(
                "QoS 1 burst fan-in ({} x {} x {PAYLOAD_BYTES} B, {} in flight)",
                p.publishers, p.fanin1_messages, p.inflight
            ),
            Scenario::Pairs => format!(
                "independent pairs ({} pairs x {} x {PAYLOAD_BYTES} B, QoS 0)",
                p.pairs, p.pairs_messages
            ),
            Scenario::Latency => format!(
                "steady latency ({} x {} msg/s x {} s, {PAYLOAD_BYTES} B, QoS 0)",
                p.publishers, p.latency_rate, p.latency_secs
            ),
            Scenario::IdleMem => format!(
                "memory per idle connection ({} clients, keep-alive {})",
                p.idle_connections,
                mqtt::KEEP_ALIVE_SECS
            ),
            Scenario::MsgMem => format!(
                "memory after {} messages ({} x {} x {PAYLOAD_BYTES} B, QoS 0, +2 s)",
                p.publishers * p.msgmem_per_publisher,
                p.publishers,
                p.msgmem_per_publisher
            ),
            Scenario::ConnRate => format!(
                "connections per second ({} anonymous, {} in flight)",
                p.connrate_connections, p.connrate_inflight
            ),
            Scenario::Connect1 => format!(
                "one connection at a time ({} anonymous, each kept open)",
                p.connect1_connections
            ),
            Scenario::AuthStorm => format!(
                "authenticated reconnect storm ({} devices at once, fresh broker)",
                p.storm_devices
            ),
        }
    }

    /// What the scenario does, printed under its header.
    pub fn description(self, p: &Params) -> String {
        let secs = p.deadline.as_secs();
        match self {
            Scenario::Fanin => format!(
                "{} publishers each write {} QoS 0 PUBLISHes of {PAYLOAD_BYTES} B to one topic as fast as possible \
                 (64 KiB buffered writes); one subscriber counts them. msg/s = received / (last receive - first send). \
                 Deadline {secs} s.",
                p.publishers, p.fanin_messages
            ),
            Scenario::Fanin1 => format!(
                "the fan-in at QoS 1: {} publishers each write {} QoS 1 PUBLISHes of {PAYLOAD_BYTES} B to one topic \
                 as fast as the PUBACKs allow (at most {} unacknowledged per publisher, --inflight); one subscriber \
                 (SUBSCRIBE QoS 1) counts them and acknowledges each read's PUBLISHes in one write. \
                 msg/s = received / (last receive - first send). Deadline {secs} s.",
                p.publishers, p.fanin1_messages, p.inflight
            ),
            Scenario::Pairs => format!(
                "{} publisher/subscriber pairs, each on its own topic (bench/pair/<i>); every publisher writes {} \
                 QoS 0 PUBLISHes of {PAYLOAD_BYTES} B at once, as fast as possible (64 KiB buffered writes); each \
                 subscriber counts its own. msg/s = received by all / (last receive anywhere - first send). \
                 Deadline {secs} s.",
                p.pairs, p.pairs_messages
            ),
            Scenario::Latency => format!(
                "{} publishers each send {} msg/s for {} s (one write per message, nodelay) to one subscriber; \
                 the payload carries the send time (ns since a shared Instant). HDR histogram of receive - send; \
                 lost = sent - received after a 2 s drain. tokio's 1 ms timer makes the publishers send together \
                 on each millisecond tick.",
                p.publishers, p.latency_rate, p.latency_secs
            ),
            Scenario::IdleMem => format!(
                "broker VmRSS 1 s after start, then again 1 s after {} clients completed CONNECT/CONNACK \
                 (64 in flight) and stay idle. KB/conn = difference / connected clients.",
                p.idle_connections
            ),
            Scenario::MsgMem => format!(
                "broker VmRSS 1 s after start, then {} publishers x {} messages as fast as possible into one \
                 subscriber that drains them; VmRSS again 2 s after the traffic stopped, clients still connected.",
                p.publishers, p.msgmem_per_publisher
            ),
            Scenario::ConnRate => format!(
                "{} connections, CONNECT -> CONNACK, {} in flight at a time, kept open; \
                 conns/s = connected / (last CONNACK - start); broker CPU/conn = the broker process's \
                 user + system CPU during the wave (/proc, 10 ms ticks) / connected.",
                p.connrate_connections, p.connrate_inflight
            ),
            Scenario::Connect1 => format!(
                "{} connections one after the other, each TCP connect + CONNECT -> CONNACK alone \
                 (the next starts after its CONNACK), all kept open; p50/p99 of one connection's time.",
                p.connect1_connections
            ),
            Scenario::AuthStorm => format!(
                "{} devices with passwords start TCP connect + CONNECT at the same instant against a broker \
                 process started for this scenario; time until the last CONNACK. Password stores: fbbus argon2id \
                 (security::hash_password defaults), mosquitto PBKDF2-SHA512 $7$ (mosquitto_passwd), \
                 rumqttd plaintext static map (no hashing at all), flashmq Mosquitto's file \
                 (mosquitto_password_file). One salted hash per device.",
                p.storm_devices
            ),
        }
    }

    pub fn columns(self) -> &'static [&'static str] {
        match self {
            Scenario::Fanin | Scenario::Fanin1 | Scenario::Pairs => {
                &["msg/s", "delivered", "lost", "send->last recv"]
            }
            Scenario::Latency => &["p50 ms", "p99 ms", "max ms", "received", "lost"],
            Scenario::IdleMem => &["RSS before", "RSS after", "KB/conn", "connected"],
            Scenario::MsgMem => &["RSS before", "RSS after", "delivered", "msg/s"],
            Scenario::ConnRate => &["conns/s", "connected", "time", "broker CPU/conn"],
            Scenario::Connect1 => &["p50 ms", "p99 ms", "connected"],
            Scenario::AuthStorm => &["all CONNACK", "p50", "p99", "connected", "password store"],
        }
    }

    /// Whether a larger key figure is better (decides the wording of the ratio line).
    pub fn higher_is_better(self) -> bool {
        matches!(
            self,
            Scenario::Fanin | Scenario::Fanin1 | Scenario::Pairs | Scenario::ConnRate
        )
    }

    /// The key figures as printed in the ratio line.
    pub fn format_keys(self, keys: &[Option<f64>]) -> String {
        let k = |i: usize| keys.get(i).copied().flatten();
        let or_na = |v: Option<String>| v.unwrap_or_else(|| "n/a".into());
        match self {
            Scenario::Fanin | Scenario::Fanin1 | Scenario::Pairs => {
                or_na(k(0).map(|v| format!("{} msg/s", si(v))))
            }
            Scenario::Latency => match (k(0), k(1), k(2)) {
                (Some(a), Some(b), Some(c)) => format!("p50/p99/max {a:.2}/{b:.2}/{c:.2} ms"),
                _ => "n/a".into(),
            },
            Scenario::IdleMem => or_na(k(0).map(|v| format!("{v:.2} KB/conn"))),
            Scenario::MsgMem => or_na(k(0).map(|v| format!("{v:.1} MB"))),
            Scenario::ConnRate => or_na(k(0).map(|v| format!("{v:.0} conn/s"))),
            Scenario::Connect1 => match (k(0), k(1)) {
                (Some(a), Some(b)) => format!("p50/p99 {a:.3}/{b:.3} ms"),
                _ => "n/a".into(),
            },
            Scenario::AuthStorm => or_na(k(0).map(|v| format!("{v:.2} s"))),
        }
    }

    /// The scenario's row in the summary table: its name and the unit of its figure.
    pub fn summary_label(self) -> &'static str {
        match self {
            Scenario::Fanin => "fanin msg/s",
            Scenario::Fanin1 => "fanin1 msg/s",
            Scenario::Pairs => "pairs msg/s",
            Scenario::Latency => "latency p50/p99/max ms",
            Scenario::IdleMem => "idlemem KB/conn",
            Scenario::MsgMem => "msgmem RSS MB",
            Scenario::ConnRate => "connrate conn/s",
            Scenario::Connect1 => "connect1 p50/p99 ms",
            Scenario::AuthStorm => "authstorm s",
        }
    }

    /// The key figures in a summary-table cell, without the unit (the row has it).
    pub fn summary_figure(self, keys: &[Option<f64>]) -> String {
        let k = |i: usize| keys.get(i).copied().flatten();
        let or_na = |v: Option<String>| v.unwrap_or_else(|| "n/a".into());
        match self {
            Scenario::Fanin | Scenario::Fanin1 | Scenario::Pairs => or_na(k(0).map(si)),
            Scenario::Latency => match (k(0), k(1), k(2)) {
                (Some(a), Some(b), Some(c)) => format!("{a:.2}/{b:.2}/{c:.2}"),
                _ => "n/a".into(),
            },
            Scenario::IdleMem => or_na(k(0).map(|v| format!("{v:.2}"))),
            Scenario::MsgMem => or_na(k(0).map(|v| format!("{v:.1}"))),
            Scenario::ConnRate => or_na(k(0).map(|v| format!("{v:.0}"))),
            Scenario::Connect1 => match (k(0), k(1)) {
                (Some(a), Some(b)) => format!("{a:.3}/{b:.3}"),
                _ => "n/a".into(),
            },
            Scenario::AuthStorm => or_na(k(0).map(|v| format!("{v:.2}"))),
        }
    }

    pub async fn run(self, broker: &Running, p: &Params, storm: Option<&Login>) -> Outcome {
        let result = match self {
            Scenario::Fanin => throughput(broker, p.fanin_shape(0), p).await,
            Scenario::Fanin1 => throughput(broker, p.fanin_shape(1), p).await,
            Scenario::Pairs => throughput(broker, p.pairs_shape(), p).await,
            Scenario::Latency => latency(broker, p).await,
            Scenario::IdleMem => idle_memory(broker, p).await,
            Scenario::MsgMem => message_memory(broker, p).await,
            Scenario::ConnRate => connection_rate(broker, p).await,
            Scenario::Connect1 => connect_latency(broker, p).await,
            Scenario::AuthStorm => match storm {
                Some(login) => auth_storm(broker, p, login).await,
                None => Err(anyhow::anyhow!("no users were prepared")),
            },
        };
        result.unwrap_or_else(|e| Outcome::failed(self, format!("error: {e:#}")))
    }
}

/// Sizes of every scenario.
#[derive(Clone, Debug)]
pub struct Params {
    pub publishers: usize,
    /// Messages per publisher in the QoS 0 fan-in.
    pub fanin_messages: usize,
    /// Messages per publisher in the QoS 1 fan-in (`fanin1`).
    pub fanin1_messages: usize,
    /// QoS 1 PUBLISHes a publisher may have unacknowledged (`--inflight`).
    pub inflight: usize,
    /// Publisher/subscriber pairs of `pairs`, and messages per pair.
    pub pairs: usize,
    pub pairs_messages: usize,
    pub latency_rate: u64,
    pub latency_secs: u64,
    pub idle_connections: usize,
    pub msgmem_per_publisher: usize,
    pub connrate_connections: usize,
    pub connrate_inflight: usize,
    /// Connections of `connect1`, one at a time.
    pub connect1_connections: usize,
    pub storm_devices: usize,
    /// Each scenario's own time limit (the latency scenario adds its duration).
    pub deadline: Duration,
}

impl Params {
    pub fn full() -> Params {
        Params {
            publishers: 10,
            fanin_messages: 20_000,
            fanin1_messages: 10_000,
            inflight: 100,
            pairs: 50,
            pairs_messages: 2_000,
            latency_rate: 1_000,
            latency_secs: 10,
            idle_connections: 1_000,
            msgmem_per_publisher: 100_000,
            connrate_connections: 2_000,
            connrate_inflight: 64,
            connect1_connections: 500,
            storm_devices: 1_045,
            deadline: Duration::from_secs(60),
        }
    }

    pub fn quick() -> Params {
        Params {
            publishers: 10,
            fanin_messages: 2_000,
            fanin1_messages: 1_000,
            inflight: 100,
            pairs: 10,
            pairs_messages: 500,
            latency_rate: 1_000,
            latency_secs: 2,
            idle_connections: 100,
            msgmem_per_publisher: 10_000,
            connrate_connections: 200,
            connrate_inflight: 64,
            connect1_connections: 50,
            storm_devices: 100,
            deadline: Duration::from_secs(20),
        }
    }

    /// The fan-in, 10 publishers into one subscriber, at `qos` (0: `fanin`, 1: `fanin1`).
    fn fanin_shape(&self, qos: u8) -> Shape {
        Shape {
            groups: 1,
            publishers: self.publishers,
            per_publisher: match qos {
                0 => self.fanin_messages,
                _ => self.fanin1_messages,
            },
            qos,
            inflight: self.inflight,
        }
    }

    /// `pairs`: one publisher and one subscriber per topic.
    fn pairs_shape(&self) -> Shape {
        Shape {
            groups: self.pairs,
            publishers: 1,
            per_publisher: self.pairs_messages,
            qos: 0,
            inflight: self.inflight,
        }
    }
}

/// What one scenario measured on one broker: the table cells, the key figures for the ratio
/// line (None: not measured) and a note (timeout, failures, errors).
#[derive(Clone, Debug)]
pub struct Outcome {
    pub cells: Vec<String>,
    pub keys: Vec<Option<f64>>,
    /// Messages sent and not delivered, where the scenario sends messages: shown next to
    /// the throughput in the summary table (a broker that drops part of a burst can show
    /// any rate).
    pub lost: Option<u64>,
    pub note: Option<String>,
    /// The key figures are incomplete (deadline hit): shown as "timeout" in the ratio line.
    pub timed_out: bool,
}

impl Outcome {
    pub fn failed(scenario: Scenario, note: String) -> Outcome {
        Outcome {
            cells: vec!["-".into(); scenario.columns().len()],
            keys: Vec::new(),
            lost: None,
            note: Some(note),
            timed_out: false,
        }
    }
}

fn add_note(note: &mut Option<String>, text: impl Into<String>) {
    let text = text.into();
    *note = Some(match note.take() {
        Some(n) => format!("{n}; {text}"),
        None => text,
    });
}

/// 312400 -> "312.4k".
pub fn si(v: f64) -> String {
    if v >= 1e6 {
        format!("{:.2}M", v / 1e6)
    } else if v >= 1e3 {
        format!("{:.1}k", v / 1e3)
    } else {
        format!("{v:.0}")
    }
}

fn mb(kib: u64) -> String {
    format!("{:.1} MB", kib as f64 / 1024.0)
}

fn rss(broker: &Running) -> Result<u64> {
    broker
        .rss_kib()
        .context("cannot read VmRSS of the broker process")
}

fn delivered(received: u64, expected: u64) -> String {
    format!("{received}/{expected}")
}

/// p50, p99 and max of a histogram of nanoseconds, in milliseconds (None when empty).
pub(super) fn latency_ms(h: &Histogram<u64>) -> (Option<f64>, Option<f64>, Option<f64>) {
    if h.is_empty() {
        return (None, None, None);
    }
    let ms = |ns: u64| ns as f64 / 1e6;
    (
        Some(ms(h.value_at_quantile(0.50))),
        Some(ms(h.value_at_quantile(0.99))),
        Some(ms(h.max())),
    )
}

/// A table cell of milliseconds, `-` without a value.
pub(super) fn ms_cell(v: Option<f64>) -> String {
    v.map(|v| format!("{v:.2}")).unwrap_or_else(|| "-".into())
}

fn lost(received: u64, sent: u64) -> String {
    let lost = sent.saturating_sub(received);
    if sent == 0 {
        "-".into()
    } else {
        format!("{lost} ({:.1}%)", lost as f64 * 100.0 / sent as f64)
    }
}

//! What a run produces: the one data model every output (terminal table, JSON, CSV, JTL,
//! SVG charts) is written from. A scenario fills a [`Report`]; `report::*` only reads it.
//!
//! Times are microseconds unless a field says otherwise; rates are messages per second.

use serde::{Deserialize, Serialize};

/// Everything one invocation measured, with what is needed to trust and repeat it.
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct Report {
    /// `fbbus-loadtest <version>`.
    pub tool: String,
    /// The exact command line, so the run can be repeated.
    pub command: String,
    /// When the run started, RFC 3339 UTC.
    pub started: String,
    pub machine: Machine,
    /// The scenario's name (`stress`, `loss-search`, `perf`, `fan-in`, ...).
    pub scenario: String,
    /// The scenario's parameters, exactly as used (after defaults).
    pub params: serde_json::Value,
    /// The brokers measured: one, or two in compare mode (labels `A`, `B`).
    pub targets: Vec<Target>,
    /// The harness's own ceiling on this machine (the same load against a trivial
    /// in-process sink), when measured.
    pub ceiling: Option<Ceiling>,
    /// Every measured batch, in the order run (compare mode interleaves A B A B).
    pub batches: Vec<Batch>,
    /// Per target: figures over all its batches.
    pub summaries: Vec<Summary>,
    /// Compare mode: B / A for each figure in the summaries.
    pub ratios: Vec<Ratio>,
    /// Things the reader must know to read the numbers right (e.g. "FB subscriber not
    /// used: the broker does not answer fbbus declarations").
    pub notes: Vec<String>,
    /// Why the run failed its verdict (the campaigns `mutate` and `churn`: the broker
    /// stopped routing, crashed, or kept too much memory); empty: it passed. A run with
    /// failures exits 1 after writing its outputs.
    #[serde(default)]
    pub failures: Vec<String>,
}

#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct Machine {
    pub hostname: String,
    pub os: String,
    pub cpu_model: String,
    pub cpus: usize,
    pub memory_mib: u64,
}

/// One broker under test.
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct Target {
    /// `A` or `B` (compare mode), else `A`.
    pub label: String,
    /// `mqtt://127.0.0.1:1883`, `mqtts://line1:8883`.
    pub address: String,
    /// The broker's version string if it told (MQTT `$SYS/broker/version`, fbbus's
    /// `/version`), else `None`.
    pub version: Option<String>,
    /// A short name for tables and chart legends (`fbbus`, `mosquitto`, or the address).
    pub name: String,
}

/// The harness against a trivial sink: the most it can generate and count on this
/// machine, with the scenario's clients and pace. A broker figure near this is the
/// harness's limit, not the broker's.
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct Ceiling {
    /// The batch run through the sink (`burst 20000`, `rate 1000/s`).
    #[serde(default)]
    pub label: String,
    pub messages: u64,
    pub throughput: f64,
    pub latency: Latency,
}

/// One batch: a burst (closed loop) or a constant-rate run (open loop) of `sent`
/// messages, counted at the subscribers. A JMeter "sample" in the JTL.
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct Batch {
    /// Target label (`A`/`B`).
    pub target: String,
    /// What this batch is, for tables and JTL labels: `burst 1280`, `rate 5000/s`,
    /// `connect storm`.
    pub label: String,
    /// The independent variable of the scenario's charts: the burst size (stress,
    /// loss-search, perf), the rate, the number of connections.
    pub x: f64,
    /// 1-based repeat number of this x.
    pub repeat: u32,
    /// Wall clock at the batch's start, milliseconds since 1970 (JTL `timeStamp`).
    pub started_ms: u64,
    /// Messages (or connections, for connection scenarios) attempted.
    pub sent: u64,
    /// Delivered at the raw MQTT subscriber(s): distinct messages received. With several
    /// subscribers (fan-out) each subscriber's copy counts, and `expected` says how many
    /// copies there should be.
    pub delivered: u64,
    /// Copies that should have arrived (`sent` x subscribers).
    pub expected: u64,
    /// Delivered at the subscribing FB (fb-bridge client API, typed INDs); `None` when
    /// no FB subscriber ran.
    pub delivered_fb: Option<u64>,
    /// Messages received more than once (counted once in `delivered`).
    pub duplicates: u64,
    /// Messages that arrived after a later message of the same publisher.
    pub out_of_order: u64,
    /// Time to hand the whole batch to the client library.
    pub send_us: u64,
    /// The study's processing time: first send to last delivery.
    pub processing_us: u64,
    /// Delivered copies per second of processing time.
    pub throughput: f64,
    /// Per-message latency, publish to delivery, of this batch.
    pub latency: Latency,
    /// Whether the batch is a success: everything expected arrived, nothing failed.
    pub ok: bool,
    /// Why not, when `ok` is false (`lost 12 of 1280`, `connect refused: ...`).
    pub error: Option<String>,
}

impl Batch {
    /// Messages lost: expected copies that did not arrive.
    pub fn lost(&self) -> u64 {
        self.expected.saturating_sub(self.delivered)
    }

    /// Delivered / expected, 0..=1 (1 for an empty batch).
    pub fn delivery_rate(&self) -> f64 {
        if self.expected == 0 {
            1.0
        } else {
            self.delivered as f64 / self.expected as f64
        }
    }
}

/// A latency distribution, from an HDR histogram (microsecond resolution, 3 significant
/// digits). In open-loop runs it is corrected for coordinated omission: latency runs from
/// when a message was *due* by the schedule, not from when it was actually sent.
#[derive(Debug, Clone, Default, Serialize, Deserialize)]
pub struct Latency {
    pub count: u64,
    pub mean_us: f64,
    pub p50_us: u64,
    pub p90_us: u64,
    pub p99_us: u64,
    pub p999_us: u64,
    pub max_us: u64,
    /// The percentile curve for charts: (percentile 0..=100, microseconds), ascending.
    pub curve: Vec<(f64, u64)>,
}

/// One target's figures over all its batches.
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct Summary {
    pub target: String,
    pub batches: u64,
    pub sent: u64,
    pub expected: u64,
    pub delivered: u64,
    pub delivered_fb: Option<u64>,
    pub duplicates: u64,
    /// Throughput: the median of the batches' throughputs.
    pub throughput: f64,
    /// All batches' latencies merged.
    pub latency: Latency,
    /// Scenario-specific figures (`largest_lossless` for loss-search, `rss_kib_per_conn`
    /// for idle, `connect_s` for storms), by name.
    pub figures: Vec<Figure>,
}

#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct Figure {
    pub name: String,
    pub value: f64,
    /// `msg/s`, `us`, `KiB`, `s`, `messages`.
    pub unit: String,
}

/// Compare mode: one figure of B divided by the same of A.
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct Ratio {
    pub figure: String,
    pub a: f64,
    pub b: f64,
    /// b / a (0 when a is 0: no ratio).
    pub ratio: f64,
}

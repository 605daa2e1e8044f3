//! What the network campaigns (`mutate`, `churn`) share: raw TCP connections driven by a
//! per-connection script at bounded concurrency, in rounds; between rounds a **routing
//! probe**; the broker's process (alive, resident memory, descriptors) and Prometheus
//! series before, after and after an idle settle; and the verdict.
//!
//! A campaign fails (the run exits 1, after writing its report) when:
//! - the probe fails: a fresh valid subscriber (`fbbus-loadtest/probe/#` and
//!   `+/probe/+/Förderband/#`) does not get a fresh publisher's QoS 1 message on
//!   `fbbus-loadtest/probe/é/Förderband/<n>` within `--probe-timeout-ms` — before the
//!   campaign, after each round of `--probe-every` connections, or after the settle;
//! - the broker's process (found by `--pid` or by the port it listens on) has exited;
//! - its resident memory after the settle is more than `--max-rss-ratio` times what it
//!   was before the campaign.
//!
//! Counts add up: every connection ends in exactly one `result_*` figure, so
//! `connections` = the sum of the `result_*` figures.
//!
//! Each connection's bytes come from its own generator ([`Rng::for_item`]: seed, campaign,
//! connection number), so `--seed` repeats a campaign packet for packet whatever the
//! concurrency and timing.

mod conn;
mod probe;

pub use conn::{Conn, Ctx};
pub use probe::probe;

use std::collections::BTreeMap;
use std::future::Future;
use std::net::{IpAddr, Ipv4Addr, SocketAddr};
use std::sync::Arc;
use std::time::{Duration, Instant};

use serde::Serialize;
use tokio::net::TcpSocket;
use tokio::task::JoinSet;

use crate::model::Batch;
use crate::rng::Rng;
use crate::session::Session;
use crate::target::Target;
use crate::{broker_process, clock, scrape, tally};

/// The parameters both campaigns take.
#[derive(Debug, Clone, Serialize)]
pub struct Campaign {
    /// Connections per broker.
    pub connections: u64,
    /// Connections in progress at once.
    pub concurrency: usize,
    /// The campaign stops starting connections after this long (the report says so).
    pub duration_s: u64,
    pub seed: u64,
    /// A routing probe after every this many connections (0: only before and after).
    pub probe_every: u64,
    /// How long to wait for whatever the broker answers (after a mutated or malformed
    /// packet, and for the end of a connection).
    pub read_ms: u64,
    /// How long to wait for the CONNACK of a valid CONNECT.
    pub connack_ms: u64,
    pub probe_timeout_ms: u64,
    /// Idle time after the campaign before the last memory reading.
    pub settle_s: u64,
    /// Resident memory after the settle may be at most this times the memory before.
    pub max_rss_ratio: f64,
    /// The brokers' processes, per target, when given (`--pid`, `--compare-pid`); else
    /// found by the port they listen on.
    pub pids: Vec<Option<u32>>,
    /// The brokers' Prometheus endpoints, per target (`--metrics`, `--compare-metrics`).
    pub metrics: Vec<Option<String>>,
    /// Campaign connections come from 127.0.0.2-127.0.0.33 (IPv4 loopback targets only),
    /// so their failed logins never throttle the probe's address, 127.0.0.1.
    pub spread_sources: bool,
}

/// How one connection began: every connection ends up in exactly one.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum Start {
    /// No TCP connection (refused, timed out).
    TcpFailed,
    /// The harness gave up on it (its overall bound passed).
    TimedOut,
    /// CONNACK, accepted.
    Accepted,
    /// CONNACK with a refusal code.
    Refused,
    /// The broker's first packet was not a CONNACK.
    OtherAnswer,
    /// The broker closed the connection without sending anything.
    ClosedWithoutAnswer,
    /// Nothing within the deadline, connection still open.
    #[default]
    NoAnswer,
    /// The harness closed it before an answer could come (abandoned mid-CONNECT).
    NotAwaited,
}

impl Start {
    pub const ALL: [Start; 8] = [
        Start::TcpFailed,
        Start::TimedOut,
        Start::Accepted,
        Start::Refused,
        Start::OtherAnswer,
        Start::ClosedWithoutAnswer,
        Start::NoAnswer,
        Start::NotAwaited,
    ];

    pub fn name(self) -> &'static str {
        match self {
            Start::TcpFailed => "tcp_failed",
            Start::TimedOut => "timed_out",
            Start::Accepted => "connack_accepted",
            Start::Refused => "connack_refused",
            Start::OtherAnswer => "other_answer",
            Start::ClosedWithoutAnswer => "closed_without_answer",
            Start::NoAnswer => "no_answer",
            Start::NotAwaited => "not_awaited",
        }
    }
}

/// How the harness ended a connection.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Close {
    /// DISCONNECT, then waits (`--read-ms`) for the broker to close.
    Disconnect,
    /// Close without DISCONNECT (FIN; RST if unread bytes were pending).
    Drop,
    /// RST (SO_LINGER 0): a power cut as the broker sees it.
    Reset,
    /// Part of a packet, then RST or close.
    MidPacket,
}

impl Close {
    pub fn name(self) -> &'static str {
        match self {
            Close::Disconnect => "disconnect",
            Close::Drop => "close",
            Close::Reset => "reset",
            Close::MidPacket => "mid_packet",
        }
    }
}

/// What one connection did.
#[derive(Debug, Default)]
pub struct Outcome {
    pub start: Start,
    /// Its CONNECT was a valid one (not mutated, not malformed, sent whole).
    pub valid_connect: bool,
    /// CONNECT sent to CONNACK received (accepted ones).
    pub connack_us: Option<u64>,
    /// Packets written whole (mutated ones included).
    pub packets: u64,
    pub mutated: u64,
    /// Packets the harness cut off by closing.
    pub partial: u64,
    pub bytes_sent: u64,
    pub bytes_received: u64,
    /// The broker closed the connection before the harness's script ended.
    pub closed_by_broker: bool,
    /// How the harness ended it (None: the broker did, or it never began).
    pub close: Option<Close>,
    /// Labels counted per connection or per packet (`mutation_bit_flip`, `kind_valid`).
    pub labels: Vec<String>,
}

impl Outcome {
    /// Counts `label` once more for this connection.
    pub fn label(&mut self, label: &str) {
        self.labels.push(label.to_owned());
    }
}

/// The sum of many [`Outcome`]s.
#[derive(Debug)]
pub struct Tally {
    pub connections: u64,
    pub counts: BTreeMap<String, u64>,
    pub connack: hdrhistogram::Histogram<u64>,
}

impl Default for Tally {
    fn default() -> Self {
        Tally {
            connections: 0,
            counts: BTreeMap::new(),
            connack: tally::histogram(),
        }
    }
}

impl Tally {
    fn bump(&mut self, name: &str, by: u64) {
        *self.counts.entry(name.to_owned()).or_default() += by;
    }

    pub fn get(&self, name: &str) -> u64 {
        self.counts.get(name).copied().unwrap_or(0)
    }

    pub fn add(&mut self, o: &Outcome) {
        self.connections += 1;
        self.bump(&format!("result_{}", o.start.name()), 1);
        self.bump("packets_sent", o.packets);
        self.bump("packets_mutated", o.mutated);
        self.bump("packets_partial", o.partial);
        self.bump("bytes_sent", o.bytes_sent);
        self.bump("bytes_received", o.bytes_received);
        self.bump("closed_by_broker", u64::from(o.closed_by_broker));
        if o.valid_connect {
            self.bump("valid_connects", 1);
            if o.start == Start::Accepted {
                self.bump("valid_connects_accepted", 1);
            }
        }
        if let Some(c) = o.close {
            self.bump(&format!("ended_{}", c.name()), 1);
        }
        for l in &o.labels {
            self.bump(l, 1);
        }
        if let Some(us) = o.connack_us {
            self.connack.saturating_record(us.max(1));
        }
    }

    fn merge(&mut self, other: &Tally) {
        self.connections += other.connections;
        for (k, v) in &other.counts {
            self.bump(k, *v);
        }
        let _ = self.connack.add(&other.connack);
    }

    /// Connections that ran their script (TCP up, not abandoned by a timeout).
    fn completed(&self) -> u64 {
        self.connections - self.get("result_tcp_failed") - self.get("result_timed_out")
    }
}

/// One reading of the broker's process and metrics.
#[derive(Debug, Clone, Default)]
struct Sample {
    rss: Option<u64>,
    hwm: Option<u64>,
    fds: Option<u64>,
    threads: Option<u64>,
    metrics: Vec<(String, f64)>,
    metrics_error: Option<String>,
}

/// Where to read the broker's state.
struct Watch {
    pid: Option<u32>,
    metrics: Option<String>,
}

impl Watch {
    async fn sample(&self) -> Sample {
        let mut s = Sample::default();
        if let Some(pid) = self.pid {
            s.rss = broker_process::rss_kib(pid);
            s.hwm = broker_process::status_kib(pid, "VmHWM");
            s.fds = broker_process::open_fds(pid);
            s.threads = broker_process::status_number(pid, "Threads");
        }
        if let Some(url) = &self.metrics {
            match scrape::get(url, Duration::from_secs(5)).await {
                Ok(text) => s.metrics = scrape::select(&text, scrape::CAMPAIGN_SERIES),
                Err(e) => s.metrics_error = Some(e),
            }
        }
        s
    }

    fn alive(&self) -> bool {
        self.pid.is_none_or(broker_process::alive)
    }
}

/// One broker's campaign so far.
struct Run {
    ctx: Arc<Ctx>,
    watch: Watch,
    before: Sample,
    after: Sample,
    peak_rss: Option<u64>,
    tally: Tally,
    /// Connections started so far.
    done: u64,
    probes_ok: u64,
    probes_failed: u64,
    probe_us: Vec<u64>,
    /// Stopped after a failure: no more rounds.
    stopped: bool,
    crashed: bool,
}

/// The campaign against every target: rounds of `probe_every` connections, A B A B in
/// compare mode, each followed by a probe; then the settle. Figures go into the session;
/// returns the failures (empty: the campaign passed).
#[allow(clippy::too_many_arguments)]
pub async fn run<F, Fut>(
    s: &mut Session,
    targets: &[Target],
    prefix: &str,
    c: &Campaign,
    scenario: &str,
    script: F,
) -> Vec<String>
where
    F: Fn(Arc<Ctx>, u64) -> Fut,
    Fut: Future<Output = Outcome> + Send + 'static,
{
    let mut failures = Vec::new();
    let probe_wait = Duration::from_millis(c.probe_timeout_ms);
    let mut runs: Vec<Run> = Vec::new();
    for (rig, target) in targets.iter().enumerate() {
        let label = s.labels[rig].clone();
        let addr = match tokio::net::lookup_host((target.host.as_str(), target.port)).await {
            Ok(mut addrs) => addrs.next(),
            Err(_) => None,
        };
        let Some(addr) = addr else {
            failures.push(format!("{label}: cannot resolve {}", target.address));
            continue;
        };
        let pid = c.pids.get(rig).copied().flatten().or_else(|| {
            target
                .is_loopback()
                .then(|| broker_process::pid_listening_on(target.port))
                .flatten()
        });
        match pid {
            Some(pid) => s.notes.push(format!(
                "{label}: broker process {pid} ({})",
                broker_process::name(pid).unwrap_or_else(|| "name unknown".into())
            )),
            None => s.notes.push(format!(
                "{label}: broker process not found (no --pid, and no process listening on port {} is visible on this machine): crashes are seen only as failed probes, memory is not measured",
                target.port
            )),
        }
        let id_prefix = format!("{prefix}-{}", label.to_lowercase());
        let ctx = Ctx {
            target: target.clone(),
            addr,
            sources: sources(addr, c.spread_sources),
            prefix: id_prefix,
            seed: c.seed,
            read: Duration::from_millis(c.read_ms),
            connack: Duration::from_millis(c.connack_ms),
            io: Duration::from_secs(5),
        };
        let watch = Watch {
            pid,
            metrics: c.metrics.get(rig).cloned().flatten(),
        };
        let before = watch.sample().await;
        if let Some(e) = &before.metrics_error {
            s.notes.push(format!("{label}: metrics not read: {e}"));
        }
        let mut run = Run {
            ctx: Arc::new(ctx),
            watch,
            after: before.clone(),
            peak_rss: before.rss,
            before,
            tally: Tally::default(),
            done: 0,
            probes_ok: 0,
            probes_failed: 0,
            probe_us: Vec::new(),
            stopped: false,
            crashed: false,
        };
        match probe(target, &run.ctx.prefix, 0, probe_wait).await {
            Ok(took) => {
                run.probes_ok += 1;
                run.probe_us.push(took.as_micros() as u64);
            }
            Err(e) => {
                run.probes_failed += 1;
                run.stopped = true;
                failures.push(format!(
                    "{label}: the broker did not route before the campaign: {e}"
                ));
            }
        }
        runs.push(run);
    }

    let deadline = Instant::now() + Duration::from_secs(c.duration_s);
    let per_round = match c.probe_every {
        0 => c.connections.max(1),
        n => n,
    };
    let mut start = 0;
    let mut cut_short = false;
    'rounds: while start < c.connections {
        let end = (start + per_round).min(c.connections);
        for (rig, run) in runs.iter_mut().enumerate() {
            if run.stopped {
                continue;
            }
            if Instant::now() >= deadline || s.out_of_time() {
                cut_short = true;
                break 'rounds;
            }
            let label = s.labels[rig].clone();
            let started_ms = clock::now_ms();
            let began = Instant::now();
            let round = round(&run.ctx, start..end, c.concurrency, deadline, &script).await;
            let took = began.elapsed();
            run.done += round.connections;
            let probed = probe(&run.ctx.target, &run.ctx.prefix, run.done, probe_wait).await;
            let sample = run.watch.sample().await;
            run.peak_rss = run.peak_rss.max(sample.rss);
            run.after = sample;
            let mut error = None;
            if !run.watch.alive() {
                run.crashed = true;
                error = Some(format!(
                    "the broker process {} exited (crashed) during connections {}..{}",
                    run.watch.pid.unwrap_or(0),
                    start + 1,
                    start + round.connections
                ));
            } else if let Err(e) = &probed {
                error = Some(format!(
                    "the broker stopped routing during connections {}..{}: {e}",
                    start + 1,
                    start + round.connections
                ));
            }
            match &probed {
                Ok(t) => {
                    run.probes_ok += 1;
                    run.probe_us.push(t.as_micros() as u64);
                }
                Err(_) => run.probes_failed += 1,
            }
            if let Some(e) = &error {
                failures.push(format!("{label}: {e}"));
                run.stopped = true;
            }
            let n = round.connections;
            let completed = round.completed();
            let batch = Batch {
                target: label.clone(),
                label: format!("connections {}", run.done),
                x: run.done as f64,
                repeat: 1,
                started_ms,
                sent: n,
                delivered: completed,
                expected: n,
                delivered_fb: None,
                duplicates: 0,
                out_of_order: 0,
                send_us: took.as_micros() as u64,
                processing_us: took.as_micros() as u64,
                throughput: n as f64 / took.as_secs_f64().max(1e-9),
                latency: tally::summarize(&round.connack),
                ok: error.is_none(),
                error,
            };
            s.record(rig, batch, &round.connack);
            run.tally.merge(&round);
            if run.done < end {
                cut_short = true;
                break 'rounds;
            }
        }
        start = end;
    }
    if cut_short {
        s.notes.push(format!(
            "{scenario} stopped at its --duration ({} s) or the run's --time-limit-s: {}",
            c.duration_s,
            runs.iter()
                .enumerate()
                .map(|(i, r)| format!(
                    "{}: {} of {} connections",
                    s.labels[i], r.done, c.connections
                ))
                .collect::<Vec<_>>()
                .join(", ")
        ));
    }

    // The settle: the broker idle, then memory and routing once more.
    let watched = runs
        .iter()
        .any(|r| !r.crashed && (r.watch.pid.is_some() || r.watch.metrics.is_some()));
    if watched && c.settle_s > 0 {
        s.println(format!("{scenario}: settling {} s", c.settle_s));
        tokio::time::sleep(Duration::from_secs(c.settle_s)).await;
    }
    for (rig, run) in runs.iter_mut().enumerate() {
        let label = s.labels[rig].clone();
        let settled = run.watch.sample().await;
        if !run.crashed && !run.watch.alive() {
            run.crashed = true;
            failures.push(format!(
                "{label}: the broker process {} exited (crashed) after the campaign",
                run.watch.pid.unwrap_or(0)
            ));
        }
        if !run.crashed && !run.stopped {
            match probe(&run.ctx.target, &run.ctx.prefix, run.done + 1, probe_wait).await {
                Ok(t) => {
                    run.probes_ok += 1;
                    run.probe_us.push(t.as_micros() as u64);
                }
                Err(e) => {
                    run.probes_failed += 1;
                    failures.push(format!(
                        "{label}: the broker did not route after the settle: {e}"
                    ));
                }
            }
        }
        figures(s, rig, run, &settled, c, &mut failures, &label);
    }
    failures
}

/// Source addresses for IPv4 loopback targets: 127.0.0.2-127.0.0.33, when they can be
/// bound here.
fn sources(addr: SocketAddr, spread: bool) -> Vec<IpAddr> {
    let loopback_v4 = matches!(addr.ip(), IpAddr::V4(ip) if ip.is_loopback());
    if !spread || !loopback_v4 {
        return Vec::new();
    }
    let candidates: Vec<IpAddr> = (2..=33)
        .map(|d| IpAddr::V4(Ipv4Addr::new(127, 0, 0, d)))
        .collect();
    let bindable = TcpSocket::new_v4()
        .and_then(|s| s.bind(SocketAddr::new(candidates[0], 0)))
        .is_ok();
    if bindable {
        candidates
    } else {
        Vec::new()
    }
}

/// Connections `range` against one broker, at most `concurrency` at once, none started
/// after `deadline`.
async fn round<F, Fut>(
    ctx: &Arc<Ctx>,
    range: std::ops::Range<u64>,
    concurrency: usize,
    deadline: Instant,
    script: &F,
) -> Tally
where
    F: Fn(Arc<Ctx>, u64) -> Fut,
    Fut: Future<Output = Outcome> + Send + 'static,
{
    // Generous: every wait of a script is bounded by itself; this only catches a hang.
    let limit = ctx.connack + 8 * ctx.read + 4 * ctx.io;
    let mut tally = Tally::default();
    let mut set = JoinSet::new();
    let mut next = range.start;
    loop {
        while set.len() < concurrency.max(1) && next < range.end && Instant::now() < deadline {
            let fut = script(ctx.clone(), next);
            set.spawn(async move {
                tokio::time::timeout(limit, fut).await.unwrap_or(Outcome {
                    start: Start::TimedOut,
                    ..Outcome::default()
                })
            });
            next += 1;
        }
        match set.join_next().await {
            Some(Ok(o)) => tally.add(&o),
            Some(Err(_)) => tally.add(&Outcome {
                start: Start::TimedOut,
                ..Outcome::default()
            }),
            None => break,
        }
    }
    tally
}

/// The campaign's figures for one broker, and its memory verdict.
fn figures(
    s: &mut Session,
    rig: usize,
    run: &Run,
    settled: &Sample,
    c: &Campaign,
    failures: &mut Vec<String>,
    label: &str,
) {
    let t = &run.tally;
    let mut fig = |name: &str, value: f64, unit: &str| s.figure(rig, name, value, unit);
    fig("connections", t.connections as f64, "connections");
    for start in Start::ALL {
        let name = format!("result_{}", start.name());
        fig(&name, t.get(&name) as f64, "connections");
    }
    for (name, value) in &t.counts {
        if name.starts_with("result_") {
            continue;
        }
        let unit = if name.starts_with("bytes") {
            "bytes"
        } else if name.starts_with("packets") || name.starts_with("mutation_") {
            "packets"
        } else {
            "connections"
        };
        fig(name, *value as f64, unit);
    }
    fig("probes_ok", run.probes_ok as f64, "probes");
    fig("probes_failed", run.probes_failed as f64, "probes");
    if let Some(max) = run.probe_us.iter().max() {
        fig("probe_max_ms", *max as f64 / 1000.0, "ms");
    }
    if run.watch.pid.is_some() {
        fig("crashes", f64::from(u8::from(run.crashed)), "exits");
    }
    let kib = |v: Option<u64>| v.map(|v| v as f64);
    for (when, sample) in [
        ("before", &run.before),
        ("after", &run.after),
        ("settled", settled),
    ] {
        if let Some(v) = kib(sample.rss) {
            fig(&format!("rss_{when}_kib"), v, "KiB");
        }
        if let Some(v) = sample.fds {
            fig(&format!("fds_{when}"), v as f64, "fds");
        }
        if let Some(v) = sample.threads {
            fig(&format!("threads_{when}"), v as f64, "threads");
        }
    }
    if let Some(v) = kib(run.peak_rss) {
        fig("rss_peak_sampled_kib", v, "KiB");
    }
    if let Some(v) = kib(settled.hwm.or(run.after.hwm)) {
        fig("rss_hwm_kib", v, "KiB");
    }
    if let (Some(b), Some(a)) = (run.before.rss, run.after.rss) {
        fig("rss_after_ratio", a as f64 / b.max(1) as f64, "x");
    }
    if let (Some(b), Some(z)) = (run.before.rss, settled.rss) {
        let ratio = z as f64 / b.max(1) as f64;
        fig("rss_settled_ratio", ratio, "x");
        if ratio > c.max_rss_ratio {
            failures.push(format!(
                "{label}: resident memory after the {} s settle is {z} KiB, {ratio:.2}x the {b} KiB before the campaign (limit --max-rss-ratio {})",
                c.settle_s, c.max_rss_ratio
            ));
        }
    }
    for (when, sample) in [
        ("before", &run.before),
        ("after", &run.after),
        ("settled", settled),
    ] {
        for (series, value) in &sample.metrics {
            fig(&format!("{series} {when}"), *value, "");
        }
    }
}

/// A context for unit tests of the scripts' generators (never connects).
#[cfg(test)]
pub fn test_ctx(seed: u64) -> Ctx {
    Ctx {
        target: Target::parse("mqtt://127.0.0.1:1883").unwrap(),
        addr: "127.0.0.1:1883".parse().unwrap(),
        sources: Vec::new(),
        prefix: "lt-a".into(),
        seed,
        read: Duration::from_millis(100),
        connack: Duration::from_secs(5),
        io: Duration::from_secs(5),
    }
}

/// A random client-chosen packet identifier (never 0 unless asked).
pub fn pid(rng: &mut Rng) -> u16 {
    rng.range(1, u64::from(u16::MAX)) as u16
}

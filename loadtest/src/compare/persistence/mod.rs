//! `fbbus-loadtest compare persistence`: what fbbus's store (issue 17) costs a line's QoS 1
//! traffic and how fast fbbus comes back on it, beside Mosquitto, in one run.
//!
//! Setups, each a freshly started broker per measurement and round:
//!
//! - `fbbus-off`: `[persistence] enabled = false`;
//! - `fbbus-always`, `fbbus-every100ms` (fbbus's default policy), `fbbus-os`: the store on,
//!   in the broker's temporary directory, with `fsync` = `"always"`, `"every 100 ms"`,
//!   `"os"`;
//! - `mosquitto-persist`: `persistence true`, `persistence_location` in its temporary
//!   directory, the default `autosave_interval` (1800 s: Mosquitto writes its database
//!   then and when it stops, not before it acknowledges a message);
//! - `mosquitto-nopersist`: `persistence false`.
//!
//! Both Mosquittos run with `set_tcp_nodelay true` and `max_inflight_messages 512`, the
//! window fbbus keeps towards a subscriber by default (`[broker] max_inflight_out`;
//! Mosquitto's default is 20; until 2026-11-30 both were 100).
//!
//! Measured:
//!
//! 1. **`throughput`**: QoS 1 burst fan-in. A persistent subscriber (MQTT 3.1.1, clean
//!    session 0, QoS 1 subscription, PUBACK for every message) is connected during the
//!    burst, so fbbus stores every publication; N publishers each send M QoS 1
//!    PUBLISHes with up to 100 unacknowledged (fbbus's `max_inflight`). msg/s = delivered
//!    / (last receipt - first send); delivered counts each message once, lost = sent -
//!    delivered.
//! 2. **`latency`**: the same persistent subscriber, N publishers x R QoS 1 msg/s for S
//!    seconds on an absolute schedule, publish -> delivery in an HDR histogram.
//! 3. **`restart`**: a broker with persistence is filled with K retained messages
//!    (QoS 1, acknowledged) and J persistent sessions, each with one QoS 1 subscription
//!    and Q QoS 1 messages queued while it is offline; stopped with SIGTERM; started again
//!    on the same config and store. Restart time = spawn -> a fresh subscriber received
//!    a retained message (the last one published); for fbbus also spawn -> `/readyz` 200,
//!    for Mosquitto spawn -> CONNACK. Also: fbbus's own `store restored ... read_ms=...
//!    put_back_ms=...` log line, the store's size on disk, every retained message back
//!    (a subscriber to all of them) and one session back with its queued messages.
//!
//! Everything on 127.0.0.1; every loop is bounded by a count and a deadline.

mod latency;
mod restart;
mod summary;
mod throughput;

use std::net::SocketAddr;
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicUsize, Ordering};
use std::time::{Duration, Instant};

use anyhow::{bail, Context as _, Result};
use hdrhistogram::Histogram;
use tokio::io::AsyncWriteExt;

use loadtest::broker_process::spawn::{self, Kind, Persistence, Spec};
use loadtest::raw_client::{self as mqtt, PacketReader};

use super::{metric, Transcript};

use self::latency::latency;
use self::restart::restart;
use self::summary::{goals, ratio_lines, table};
use self::throughput::throughput;

/// Payload size of every message: send time (8 bytes), publisher (4), sequence (8), padding.
const PAYLOAD_BYTES: usize = 32;

/// Time to open one client connection before it counts as failed.
const CONNECT_TIMEOUT: Duration = Duration::from_secs(10);

/// The default policy, whose figures the goals are about.
const DEFAULT_POLICY: &str = "fbbus-every100ms";

/// One measurement.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Measure {
    Throughput,
    Latency,
    Restart,
}

impl Measure {
    pub const ALL: [Measure; 3] = [Measure::Throughput, Measure::Latency, Measure::Restart];

    pub fn name(self) -> &'static str {
        match self {
            Measure::Throughput => "throughput",
            Measure::Latency => "latency",
            Measure::Restart => "restart",
        }
    }

    /// `--scenarios` as given, in the canonical order; all when empty.
    pub fn parse_list(names: &[String]) -> Result<Vec<Measure>> {
        let mut chosen = Vec::new();
        for name in names {
            let m = Measure::ALL
                .into_iter()
                .find(|m| m.name() == name.trim())
                .with_context(|| {
                    format!(
                        "unknown scenario `{name}` (known: {})",
                        Measure::ALL.map(|m| m.name()).join(", ")
                    )
                })?;
            chosen.push(m);
        }
        Ok(Measure::ALL
            .into_iter()
            .filter(|m| chosen.is_empty() || chosen.contains(m))
            .collect())
    }

    fn title(self, p: &PersistParams) -> String {
        match self {
            Measure::Throughput => format!(
                "QoS 1 burst fan-in, persistent subscriber ({} x {} x {PAYLOAD_BYTES} B)",
                p.publishers, p.messages
            ),
            Measure::Latency => format!(
                "QoS 1 steady latency, persistent subscriber ({} x {} msg/s x {} s)",
                p.publishers, p.latency_rate, p.latency_secs
            ),
            Measure::Restart => format!(
                "restart with {} retained messages and {} persistent sessions",
                p.retained, p.sessions
            ),
        }
    }

    fn description(self, p: &PersistParams) -> String {
        match self {
            Measure::Throughput => format!(
                "one subscriber with a persistent session (MQTT 3.1.1 clean session 0, QoS 1 subscription, \
                 PUBACK for each message) is connected during the burst; {} publishers each send {} QoS 1 \
                 PUBLISHes as fast as their PUBACKs allow ({} unacknowledged at most). msg/s = delivered / \
                 (last receipt - first send); lost = sent - delivered. fbbus: not stored = \
                 fbbus_store_not_stored_total (over max_queued_messages or max_bytes: routed, not stored); \
                 writes, fsyncs = the store's, with their mean time. broker CPU = the broker's CPU time \
                 over the burst per delivered message (its threads' schedstat), split into the runtime's \
                 workers (sessions), the router and the store's writer thread. Deadline {} s.",
                p.publishers,
                p.messages,
                p.window,
                p.deadline.as_secs()
            ),
            Measure::Latency => format!(
                "the same persistent subscriber; {} publishers each send {} QoS 1 msg/s for {} s on an \
                 absolute schedule (tokio's 1 ms timer: they send together on each tick), reading their \
                 PUBACKs on the side; the payload carries the send time. HDR histogram of receive - send; \
                 lost = sent - delivered after a 2 s drain.",
                p.publishers, p.latency_rate, p.latency_secs
            ),
            Measure::Restart => format!(
                "brokers with persistence only. Fill: {} persistent sessions (clean session 0) each subscribe \
                 at QoS 1 to a topic of their own and disconnect; one client publishes {} retained QoS 1 \
                 messages, then {} QoS 1 messages to each session's topic (queued for it, offline), all \
                 acknowledged. Stop: SIGTERM, until the process exited. Restart: the same config and store; \
                 ready = spawn -> /readyz 200 (fbbus) or CONNACK (mosquitto); restart = spawn -> a fresh \
                 subscriber received the last retained message. read_ms, put_back_ms: fbbus's `store \
                 restored` log line. Then: every retained message back (one subscriber, 500 topics per \
                 SUBSCRIBE, 1 s quiet) and session 0 back (session present, its queued messages).",
                p.sessions, p.retained, p.queued
            ),
        }
    }

    fn columns(self) -> &'static [&'static str] {
        match self {
            Measure::Throughput => &[
                "msg/s",
                "delivered",
                "lost",
                "dup",
                "send->last recv",
                "not stored",
                "writes (mean)",
                "fsyncs (mean)",
                "broker CPU us/msg (workers+router+store)",
            ],
            Measure::Latency => &["p50 ms", "p99 ms", "max ms", "delivered", "lost"],
            Measure::Restart => &[
                "restart s",
                "ready s",
                "read_ms",
                "put_back_ms",
                "store MB",
                "fill s",
                "stop s",
                "restored (log)",
                "retained back",
                "session 0 back",
            ],
        }
    }
}

/// Sizes of the measurements.
pub struct PersistParams {
    pub publishers: usize,
    /// QoS 1 messages per publisher in the burst.
    pub messages: usize,
    /// Unacknowledged QoS 1 PUBLISHes per publisher.
    pub window: usize,
    pub latency_rate: u64,
    pub latency_secs: u64,
    pub retained: usize,
    pub sessions: usize,
    /// QoS 1 messages queued for each offline session.
    pub queued: usize,
    pub rounds: u32,
    pub measures: Vec<Measure>,
    /// Each measurement's own time limit (latency adds its duration, restart its fill).
    pub deadline: Duration,
}

impl PersistParams {
    pub fn full() -> PersistParams {
        PersistParams {
            publishers: 10,
            messages: 10_000,
            window: 100,
            latency_rate: 1_000,
            latency_secs: 10,
            retained: 100_000,
            sessions: 1_000,
            queued: 3,
            rounds: 1,
            measures: Measure::ALL.to_vec(),
            deadline: Duration::from_secs(60),
        }
    }

    pub fn quick() -> PersistParams {
        PersistParams {
            messages: 500,
            latency_secs: 1,
            retained: 2_000,
            sessions: 50,
            deadline: Duration::from_secs(20),
            ..PersistParams::full()
        }
    }
}

/// One broker configuration of the comparison.
struct Setup {
    label: &'static str,
    kind: Kind,
    program: PathBuf,
    persistence: Persistence,
}

impl Setup {
    fn persistent(&self) -> bool {
        matches!(self.persistence, Persistence::On { .. })
    }

    fn describe(&self) -> String {
        match (self.kind, &self.persistence) {
            (Kind::Fbbus, Persistence::Off) => "[persistence] enabled = false".into(),
            (Kind::Fbbus, Persistence::On { fsync }) => format!(
                "[persistence] enabled = true, dir in its temp dir, max_queued_messages = 100000, fsync = \"{}\"{}",
                fsync.as_deref().unwrap_or("every 100 ms"),
                if self.label == DEFAULT_POLICY {
                    " (the default)"
                } else {
                    ""
                }
            ),
            (_, Persistence::On { .. }) => {
                "persistence true, persistence_location in its temp dir, autosave_interval default (1800 s)"
                    .into()
            }
            (_, Persistence::Off) => "persistence false".into(),
        }
    }
}

fn setups(fbbus: &Path, mosquitto: &Path, brokers: &[Kind]) -> Vec<Setup> {
    let mut out = Vec::new();
    if brokers.contains(&Kind::Fbbus) {
        let on = |fsync: &str| Persistence::On {
            fsync: Some(fsync.into()),
        };
        for (label, persistence) in [
            ("fbbus-off", Persistence::Off),
            ("fbbus-always", on("always")),
            (DEFAULT_POLICY, on("every 100 ms")),
            ("fbbus-os", on("os")),
        ] {
            out.push(Setup {
                label,
                kind: Kind::Fbbus,
                program: fbbus.to_path_buf(),
                persistence,
            });
        }
    }
    if brokers.contains(&Kind::Mosquitto) {
        for (label, persistence) in [
            ("mosquitto-persist", Persistence::On { fsync: None }),
            ("mosquitto-nopersist", Persistence::Off),
        ] {
            out.push(Setup {
                label,
                kind: Kind::Mosquitto,
                program: mosquitto.to_path_buf(),
                persistence,
            });
        }
    }
    out
}

/// What one measurement gave on one setup in one round.
struct Figures {
    cells: Vec<String>,
    /// Throughput: msg/s. Latency: p50, p99, max (ms). Restart: restart s, ready s,
    /// read_ms, put_back_ms, store MB.
    keys: Vec<Option<f64>>,
    note: Option<String>,
}

struct Row<'a> {
    setup: &'a Setup,
    round: u32,
    result: std::result::Result<Figures, String>,
}

/// Runs the measurements; the output also goes to `<out>/persistence.txt`.
pub async fn run(
    fbbus: &Path,
    mosquitto: Option<&Path>,
    brokers: &[Kind],
    p: &PersistParams,
    out: &Path,
) -> Result<()> {
    let mosquitto_path = mosquitto.map_or_else(|| PathBuf::from("mosquitto"), Path::to_path_buf);
    let setups = setups(fbbus, &mosquitto_path, brokers);
    let mut t = Transcript::default();
    header(&mut t, fbbus, mosquitto, &setups, p);
    let started = Instant::now();
    let mut summary = Vec::new();
    let mut failed = 0;
    let mut all_rows: Vec<(Measure, Vec<Row>)> = Vec::new();
    for &m in &p.measures {
        t.line("");
        t.line(format!("== {} ==", m.title(p)));
        t.line(format!("   {}", m.description(p)));
        let mut rows = Vec::new();
        for round in 1..=p.rounds {
            for s in &setups {
                if m == Measure::Restart && !s.persistent() {
                    continue;
                }
                eprintln!(
                    "persistence: {} on {} (round {round}/{})...",
                    m.name(),
                    s.label,
                    p.rounds
                );
                let result = one(m, s, mosquitto.is_some(), p).await;
                if let Err(e) = &result {
                    eprintln!("  failed: {e}");
                }
                rows.push(Row {
                    setup: s,
                    round,
                    result,
                });
            }
        }
        failed += rows.iter().filter(|r| r.result.is_err()).count();
        table(&mut t, m, &rows, p.rounds);
        for line in ratio_lines(m, &setups, &rows, p) {
            t.line(&line);
            summary.push(line);
        }
        all_rows.push((m, rows));
    }
    t.line("");
    t.line(format!(
        "== summary ({:.0} s) ==",
        started.elapsed().as_secs_f64()
    ));
    for line in summary {
        t.line(line);
    }
    goals(&mut t, &all_rows, p);
    std::fs::create_dir_all(out).with_context(|| format!("creating --out {}", out.display()))?;
    let file = out.join("persistence.txt");
    std::fs::write(&file, &t.0).with_context(|| format!("writing {}", file.display()))?;
    eprintln!("wrote {}", file.display());
    if failed > 0 {
        bail!("{failed} measurement(s) failed (see their rows)");
    }
    Ok(())
}

fn header(
    t: &mut Transcript,
    fbbus: &Path,
    mosquitto: Option<&Path>,
    setups: &[Setup],
    p: &PersistParams,
) {
    t.machine_lines("persistence");
    t.line(format!(
        "fbbus:     {} ({}; config defaults, [log] level = \"warn\" (+ broker::store=info with the store on), \
         max_connections 10100)",
        spawn::fbbus_version(fbbus),
        fbbus.display()
    ));
    if setups.iter().any(|s| s.kind == Kind::Mosquitto) {
        match mosquitto {
            Some(path) => t.line(format!(
                "mosquitto: {} ({}; set_tcp_nodelay true, max_queued_messages 100000, max_inflight_messages 512)",
                spawn::mosquitto_version(path),
                path.display()
            )),
            None => t.line("mosquitto: not installed (apt-get install -y mosquitto)"),
        }
    }
    for s in setups {
        t.line(format!("  {:<20} {}", s.label, s.describe()));
    }
    t.line(format!(
        "params:    {} round(s), setups alternating, a fresh broker for each measurement; raw MQTT 3.1.1 \
         sockets, nodelay, 127.0.0.1 only; {PAYLOAD_BYTES}-byte payloads",
        p.rounds
    ));
}

/// A fresh broker of `setup` for one measurement; stopped afterwards.
async fn one(
    m: Measure,
    setup: &Setup,
    have_mosquitto: bool,
    p: &PersistParams,
) -> std::result::Result<Figures, String> {
    if setup.kind == Kind::Mosquitto && !have_mosquitto {
        return Err(
            "mosquitto is not installed (apt-get install -y mosquitto, or --mosquitto PATH)".into(),
        );
    }
    let mosquitto_lines: [String; 0] = [];
    let spec = Spec {
        kind: setup.kind,
        program: &setup.program,
        broker_keys: &[],
        tables: "",
        auth: None,
        acl: None,
        persistence: Some(&setup.persistence),
        mosquitto_lines: &mosquitto_lines,
        flashmq_lines: &[],
    };
    let mut broker = match spawn::start(&spec).await {
        Ok(b) => b,
        Err(e) => return Err(format!("failed to start: {e}")),
    };
    // A safety net above the measurement's own deadlines.
    let limit = p.deadline * 4 + Duration::from_secs(p.latency_secs + 60);
    let measured = match m {
        Measure::Throughput => tokio::time::timeout(limit, throughput(&broker, p)).await,
        Measure::Latency => tokio::time::timeout(limit, latency(&broker, p)).await,
        Measure::Restart => tokio::time::timeout(limit, restart(&mut broker, p)).await,
    };
    let mut result = match measured {
        Ok(Ok(f)) => Ok(f),
        Ok(Err(e)) => Err(format!("{e:#}")),
        Err(_) => Err(format!("timeout (no result after {limit:?})")),
    };
    if let Some(exit) = broker.exited() {
        match &mut result {
            Ok(f) => add_note(&mut f.note, exit),
            Err(e) => e.push_str(&format!("; {exit}")),
        }
    }
    result
}

fn add_note(note: &mut Option<String>, text: impl Into<String>) {
    let text = text.into();
    *note = Some(match note.take() {
        Some(n) => format!("{n}; {text}"),
        None => text,
    });
}

async fn connect(addr: SocketAddr, id: &str, clean: bool) -> Result<(PacketReader, bool)> {
    let (stream, present) =
        tokio::time::timeout(CONNECT_TIMEOUT, mqtt::connect_session(addr, id, clean))
            .await
            .with_context(|| format!("{id}: no CONNACK within {CONNECT_TIMEOUT:?}"))?
            .with_context(|| id.to_string())?;
    Ok((PacketReader::new(stream), present))
}

/// The persistent subscriber (clean session 0) on `topic` at QoS 1.
/// The persistent subscriber of `topic` and `n` clean publishers, connected; then a
/// pause, as some brokers apply a subscription after its SUBACK.
async fn subscriber_and_publishers(
    addr: SocketAddr,
    topic: &str,
    n: usize,
) -> Result<(PacketReader, Vec<PacketReader>)> {
    let sub = persistent_subscriber(addr, topic).await?;
    let mut pubs = Vec::with_capacity(n);
    for i in 0..n {
        pubs.push(connect(addr, &format!("bench-pub-{i}"), true).await?.0);
    }
    tokio::time::sleep(Duration::from_millis(200)).await;
    Ok((sub, pubs))
}

async fn persistent_subscriber(addr: SocketAddr, topic: &str) -> Result<PacketReader> {
    let (mut sub, _) = connect(addr, "bench-persist-sub", false).await?;
    let granted = tokio::time::timeout(
        CONNECT_TIMEOUT,
        mqtt::subscribe_qos(sub.get_mut(), topic, 1),
    )
    .await
    .context("no SUBACK")??;
    if granted != 1 {
        bail!("the subscription to {topic} was granted QoS {granted}, not 1");
    }
    Ok(sub)
}

/// The payload of message `seq` of publisher `publisher`, sent at `sent_ns`.
fn payload(sent_ns: u64, publisher: u32, seq: u64) -> [u8; PAYLOAD_BYTES] {
    let mut p = [0u8; PAYLOAD_BYTES];
    p[..8].copy_from_slice(&sent_ns.to_be_bytes());
    p[8..12].copy_from_slice(&publisher.to_be_bytes());
    p[12..20].copy_from_slice(&seq.to_be_bytes());
    p
}

struct Received {
    delivered: u64,
    duplicates: u64,
    last_receive: Option<Instant>,
    latency_ns: Histogram<u64>,
    end: String,
}

/// Reads QoS 1 PUBLISHes on the persistent subscriber, acknowledging each, until every
/// one of `publishers` x `per_publisher` arrived, or the publishers are done and nothing
/// arrived for 2 s, or `end_at`. Each message counts once; latencies from the payload's
/// send time (ns since `epoch`).
async fn receive_acking(
    sub: &mut PacketReader,
    publishers: usize,
    per_publisher: usize,
    publishers_done: &AtomicUsize,
    end_at: Instant,
    epoch: Instant,
) -> Received {
    let expected = (publishers * per_publisher) as u64;
    let mut seen = vec![false; publishers * per_publisher];
    let mut r = Received {
        delivered: 0,
        duplicates: 0,
        last_receive: None,
        latency_ns: Histogram::<u64>::new_with_bounds(1, 120_000_000_000, 3)
            .expect("valid histogram bounds"),
        end: String::new(),
    };
    let idle = Duration::from_secs(2);
    let mut last_activity = Instant::now();
    let mut done_seen: Option<Instant> = None;
    let mut acks = Vec::new();
    let end = loop {
        if r.delivered >= expected {
            break "complete".into();
        }
        let now = Instant::now();
        if now >= end_at {
            break "timeout".into();
        }
        if done_seen.is_none() && publishers_done.load(Ordering::Acquire) >= publishers {
            done_seen = Some(now);
        }
        if let Some(done) = done_seen {
            if now.duration_since(done.max(last_activity)) >= idle {
                break "idle".into();
            }
        }
        match tokio::time::timeout(Duration::from_millis(100), sub.read_more()).await {
            Err(_) => continue,
            Ok(Err(e)) => break format!("subscriber: {e}"),
            Ok(Ok(0)) => break "the broker closed the subscriber".into(),
            Ok(Ok(_)) => {}
        }
        let t = Instant::now();
        last_activity = t;
        let now_ns = t.duration_since(epoch).as_nanos() as u64;
        loop {
            let (header, body) = match sub.next_packet() {
                Ok(Some(packet)) => packet,
                Ok(None) => break,
                Err(e) => {
                    r.end = format!("subscriber: {e}");
                    return r;
                }
            };
            let Some(payload) = mqtt::publish_payload(header, body) else {
                continue;
            };
            if let Some(pid) = mqtt::packet_id(header, body) {
                acks.extend_from_slice(&mqtt::puback_packet(pid));
            }
            let (Some(ts), Some(who), Some(seq)) =
                (payload.get(..8), payload.get(8..12), payload.get(12..20))
            else {
                continue;
            };
            let who = u32::from_be_bytes(who.try_into().expect("4 bytes")) as usize;
            let seq = u64::from_be_bytes(seq.try_into().expect("8 bytes")) as usize;
            if who >= publishers || seq >= per_publisher {
                continue;
            }
            let slot = &mut seen[who * per_publisher + seq];
            if *slot {
                r.duplicates += 1;
                continue;
            }
            *slot = true;
            r.delivered += 1;
            r.last_receive = Some(t);
            let sent = u64::from_be_bytes(ts.try_into().expect("8 bytes"));
            r.latency_ns
                .saturating_record(now_ns.saturating_sub(sent).max(1));
        }
        if !acks.is_empty() {
            if let Err(e) = sub.get_mut().write_all(&acks).await {
                break format!("subscriber: {e}");
            }
            acks.clear();
        }
    };
    r.end = end;
    r
}

fn lost(delivered: u64, sent: u64) -> String {
    let lost = sent.saturating_sub(delivered);
    if sent == 0 {
        "-".into()
    } else {
        format!("{lost} ({:.1}%)", lost as f64 * 100.0 / sent as f64)
    }
}

/// The store's counters on fbbus's `/metrics` that the burst reads before and after.
struct StoreCounters {
    not_stored: f64,
    writes: f64,
    write_seconds: f64,
    fsyncs: f64,
    fsync_seconds: f64,
}

async fn store_counters(admin: SocketAddr) -> StoreCounters {
    StoreCounters {
        not_stored: metric(
            admin,
            "fbbus_store_not_stored_total{reason=\"session_queue_full\"}",
        )
        .await
            + metric(admin, "fbbus_store_not_stored_total{reason=\"store_full\"}").await,
        writes: metric(admin, "fbbus_store_write_seconds_count").await,
        write_seconds: metric(admin, "fbbus_store_write_seconds_sum").await,
        fsyncs: metric(admin, "fbbus_store_fsync_seconds_count").await,
        fsync_seconds: metric(admin, "fbbus_store_fsync_seconds_sum").await,
    }
}

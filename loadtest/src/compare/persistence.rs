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
//! Both Mosquittos run with `set_tcp_nodelay true` and `max_inflight_messages 100`, the
//! window fbbus keeps towards a subscriber (Mosquitto's default is 20).
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

use std::net::SocketAddr;
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicU64, AtomicUsize, Ordering};
use std::sync::Arc;
use std::time::{Duration, Instant};

use anyhow::{bail, Context as _, Result};
use hdrhistogram::Histogram;
use tokio::io::{AsyncReadExt, AsyncWriteExt};
use tokio::sync::watch;

use loadtest::broker_process;
use loadtest::broker_process::spawn::{self, Kind, Persistence, Running, Spec};
use loadtest::raw_client::{self as mqtt, PacketReader};
use loadtest::scrape;

use super::{metric, Transcript};

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
                "mosquitto: {} ({}; set_tcp_nodelay true, max_queued_messages 100000, max_inflight_messages 100)",
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
    let mosquitto_lines = ["max_inflight_messages 100".to_string()];
    let spec = Spec {
        kind: setup.kind,
        program: &setup.program,
        broker_keys: &[],
        tables: "",
        auth: None,
        acl: None,
        persistence: Some(&setup.persistence),
        mosquitto_lines: &mosquitto_lines,
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

/// Sends `count` QoS 1 PUBLISHes, the k-th made by `make(k, packet id, buffer)`, with at
/// most `window` unacknowledged, and reads the PUBACKs; returns when every one is
/// acknowledged. `sent` counts what was written.
async fn publish_acked(
    conn: &mut PacketReader,
    count: usize,
    window: usize,
    sent: &AtomicU64,
    mut make: impl FnMut(usize, u16, &mut Vec<u8>),
) -> std::io::Result<()> {
    let window = window.clamp(1, 65_535);
    let (mut next, mut acked) = (0usize, 0usize);
    let mut buf = Vec::with_capacity(window * 64);
    while acked < count {
        let before = next;
        while next < count && next - acked < window {
            make(next, (next % 65_535) as u16 + 1, &mut buf);
            next += 1;
        }
        if !buf.is_empty() {
            conn.get_mut().write_all(&buf).await?;
            buf.clear();
            sent.fetch_add((next - before) as u64, Ordering::Relaxed);
        }
        if conn.read_more().await? == 0 {
            return Err(std::io::Error::new(
                std::io::ErrorKind::UnexpectedEof,
                format!("the broker closed the connection after {acked} PUBACKs of {count}"),
            ));
        }
        while let Some((header, _)) = conn.next_packet()? {
            if header >> 4 == 4 {
                acked += 1;
            }
        }
    }
    Ok(())
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

fn count_and_mean(count: f64, seconds: f64) -> String {
    if count <= 0.0 {
        "0".into()
    } else {
        format!("{count:.0} ({:.2} ms)", seconds * 1000.0 / count)
    }
}

async fn throughput(broker: &Running, p: &PersistParams) -> Result<Figures> {
    let topic = "bench/persist";
    let addr = broker.addr;
    let (mut sub, pubs) = subscriber_and_publishers(addr, topic, p.publishers).await?;
    let store = match (broker.kind, broker.admin) {
        (Kind::Fbbus, Some(admin)) => Some((admin, store_counters(admin).await)),
        _ => None,
    };
    let epoch = Instant::now();
    let end_at = epoch + p.deadline;
    let (go_tx, go_rx) = watch::channel(false);
    let done = Arc::new(AtomicUsize::new(0));
    let sent = Arc::new(AtomicU64::new(0));
    let mut tasks = Vec::with_capacity(p.publishers);
    for (i, mut conn) in pubs.into_iter().enumerate() {
        let (mut go, done, sent) = (go_rx.clone(), done.clone(), sent.clone());
        let (messages, window) = (p.messages, p.window);
        tasks.push(tokio::spawn(async move {
            let _ = go.wait_for(|go| *go).await;
            let result = tokio::time::timeout_at(
                end_at.into(),
                publish_acked(&mut conn, messages, window, &sent, |k, pid, buf| {
                    let now_ns = epoch.elapsed().as_nanos() as u64;
                    buf.extend(mqtt::publish_qos1_packet(
                        topic,
                        pid,
                        false,
                        &payload(now_ns, i as u32, k as u64),
                    ));
                }),
            )
            .await;
            done.fetch_add(1, Ordering::Release);
            let result = match result {
                Ok(Ok(())) => None,
                Ok(Err(e)) => Some(format!("publisher {i}: {e}")),
                Err(_) => Some("publishers hit the deadline".to_string()),
            };
            (conn, result)
        }));
    }
    let cpu_before = broker_process::cpu_ns_by_thread(broker.pid());
    let first_send = Instant::now();
    go_tx.send(true).ok();
    let received = receive_acking(&mut sub, p.publishers, p.messages, &done, end_at, epoch).await;
    let cpu = cpu_per_message(
        &cpu_before,
        &broker_process::cpu_ns_by_thread(broker.pid()),
        received.delivered,
    );
    let mut note = None;
    let mut conns = Vec::new();
    for task in tasks {
        let (conn, problem) = task.await.context("publisher task")?;
        if let Some(problem) = problem {
            if note.is_none() {
                add_note(&mut note, problem);
            }
        }
        conns.push(conn);
    }
    if received.end != "complete" && received.end != "idle" {
        add_note(&mut note, received.end.clone());
    }
    let sent = sent.load(Ordering::Relaxed);
    let span = received
        .last_receive
        .map(|l| l.duration_since(first_send).as_secs_f64());
    let rate = span
        .filter(|s| *s > 0.0)
        .map(|s| received.delivered as f64 / s);
    let (not_stored, writes, fsyncs) = match store {
        Some((admin, before)) => {
            let after = store_counters(admin).await;
            (
                format!("{:.0}", after.not_stored - before.not_stored),
                count_and_mean(
                    after.writes - before.writes,
                    after.write_seconds - before.write_seconds,
                ),
                count_and_mean(
                    after.fsyncs - before.fsyncs,
                    after.fsync_seconds - before.fsync_seconds,
                ),
            )
        }
        None => ("-".into(), "-".into(), "-".into()),
    };
    drop(conns);
    Ok(Figures {
        cells: vec![
            rate.map(super::scenarios::si).unwrap_or_else(|| "-".into()),
            format!("{}/{}", received.delivered, p.publishers * p.messages),
            lost(received.delivered, sent),
            received.duplicates.to_string(),
            span.map(|s| format!("{s:.3} s"))
                .unwrap_or_else(|| "-".into()),
            not_stored,
            writes,
            fsyncs,
            cpu,
        ],
        keys: vec![rate],
        note,
    })
}

/// The broker's CPU time per delivered message between two readings of
/// [`broker_process::cpu_ns_by_thread`], in microseconds: the total, then the runtime's
/// workers (`fbbus`), the router (`router-*`) and the store's writer (`fbbus-store`). Shows
/// where a setup's extra cost goes; "-" where /proc cannot be read.
fn cpu_per_message(
    before: &std::collections::BTreeMap<String, u64>,
    after: &std::collections::BTreeMap<String, u64>,
    delivered: u64,
) -> String {
    if after.is_empty() || delivered == 0 {
        return "-".into();
    }
    let spent = |pick: &dyn Fn(&str) -> bool| -> f64 {
        let sum = |m: &std::collections::BTreeMap<String, u64>| -> u64 {
            m.iter().filter(|(n, _)| pick(n)).map(|(_, ns)| *ns).sum()
        };
        sum(after).saturating_sub(sum(before)) as f64 / 1000.0 / delivered as f64
    };
    // Another broker (Mosquitto: one thread): the total only.
    if !after.keys().any(|n| n.starts_with("router")) {
        return format!("{:.2}", spent(&|_| true));
    }
    format!(
        "{:.2} ({:.2}+{:.2}+{:.2})",
        spent(&|_| true),
        spent(&|n| n == "fbbus" || n.starts_with("tokio")),
        spent(&|n| n.starts_with("router")),
        spent(&|n| n == "fbbus-store"),
    )
}

async fn latency(broker: &Running, p: &PersistParams) -> Result<Figures> {
    let topic = "bench/persist-latency";
    let addr = broker.addr;
    let (mut sub, pubs) = subscriber_and_publishers(addr, topic, p.publishers).await?;
    let per_publisher = (p.latency_rate * p.latency_secs) as usize;
    let period_ns = 1_000_000_000 / p.latency_rate.max(1);
    let epoch = Instant::now();
    let end_at = epoch + p.deadline + Duration::from_secs(p.latency_secs);
    let start = tokio::time::Instant::now() + Duration::from_millis(100);
    let done = Arc::new(AtomicUsize::new(0));
    let sent = Arc::new(AtomicU64::new(0));
    let mut tasks = Vec::with_capacity(p.publishers);
    for (i, conn) in pubs.into_iter().enumerate() {
        let (done, sent) = (done.clone(), sent.clone());
        let stream = conn.into_inner();
        tasks.push(tokio::spawn(async move {
            let (mut read, mut write) = stream.into_split();
            // The PUBACKs are read on the side and dropped.
            let acks = tokio::spawn(async move {
                let mut buf = vec![0u8; 16 * 1024];
                while matches!(read.read(&mut buf).await, Ok(n) if n > 0) {}
                read
            });
            let send_all = async {
                for k in 0..per_publisher {
                    tokio::time::sleep_until(start + Duration::from_nanos(k as u64 * period_ns))
                        .await;
                    let now_ns = epoch.elapsed().as_nanos() as u64;
                    let packet = mqtt::publish_qos1_packet(
                        topic,
                        (k % 65_535) as u16 + 1,
                        false,
                        &payload(now_ns, i as u32, k as u64),
                    );
                    write.write_all(&packet).await?;
                    sent.fetch_add(1, Ordering::Relaxed);
                }
                Ok::<(), std::io::Error>(())
            };
            let result = tokio::time::timeout_at(end_at.into(), send_all).await;
            done.fetch_add(1, Ordering::Release);
            let problem = match result {
                Ok(Ok(())) => None,
                Ok(Err(e)) => Some(format!("publisher {i}: {e}")),
                Err(_) => Some("publishers hit the deadline".to_string()),
            };
            (write, acks, problem)
        }));
    }
    let received =
        receive_acking(&mut sub, p.publishers, per_publisher, &done, end_at, epoch).await;
    let mut note = None;
    let mut keep = Vec::new();
    for task in tasks {
        let (write, acks, problem) = task.await.context("publisher task")?;
        if let Some(problem) = problem {
            if note.is_none() {
                add_note(&mut note, problem);
            }
        }
        acks.abort();
        keep.push(write);
    }
    if received.end != "complete" && received.end != "idle" {
        add_note(&mut note, received.end.clone());
    }
    let sent = sent.load(Ordering::Relaxed);
    let (p50, p99, max) = super::scenarios::latency_ms(&received.latency_ns);
    drop(keep);
    let f = super::scenarios::ms_cell;
    Ok(Figures {
        cells: vec![
            f(p50),
            f(p99),
            f(max),
            format!("{}/{}", received.delivered, per_publisher * p.publishers),
            lost(received.delivered, sent),
        ],
        keys: vec![p50, p99, max],
        note,
    })
}

/// Retained messages per topic group (`bench/retained/<group>/+`): the check after the
/// restart subscribes group by group, as a burst of retained messages on one SUBSCRIBE
/// beyond fbbus's `router_max_outgoing_packets` (1,000) is cut there.
const RETAINED_GROUP: usize = 500;

fn retained_topic(k: usize) -> String {
    format!(
        "bench/retained/{:04}/{:03}",
        k / RETAINED_GROUP,
        k % RETAINED_GROUP
    )
}

/// Every retained message back: one subscriber, one group at a time (1 s quiet ends a
/// group short of its count).
async fn retained_back(addr: SocketAddr, retained: usize, limit: Duration) -> Result<usize> {
    let (mut conn, _) = connect(addr, "bench-check-all", true).await?;
    let end_at = Instant::now() + limit;
    let mut back = 0;
    for (i, group) in (0..retained).step_by(RETAINED_GROUP).enumerate() {
        let want = RETAINED_GROUP.min(retained - group);
        let filter = format!("bench/retained/{:04}/+", group / RETAINED_GROUP);
        conn.get_mut()
            .write_all(&mqtt::subscribe_qos_packet(
                (i % 65_535) as u16 + 1,
                &filter,
                0,
            ))
            .await?;
        let left = end_at.saturating_duration_since(Instant::now());
        if left.is_zero() {
            break;
        }
        back += count_publishes(&mut conn, want, Duration::from_secs(1), left).await;
    }
    Ok(back)
}

fn session_id(i: usize) -> String {
    format!("bench-session-{i:04}")
}

fn session_topic(i: usize) -> String {
    format!("bench/session/{i:04}")
}

/// Bytes of the files under `dir` (not following links).
fn dir_bytes(dir: &Path) -> u64 {
    let Ok(entries) = std::fs::read_dir(dir) else {
        return 0;
    };
    entries
        .flatten()
        .filter_map(|e| {
            let meta = e.metadata().ok()?;
            Some(if meta.is_dir() {
                dir_bytes(&e.path())
            } else {
                meta.len()
            })
        })
        .sum()
}

/// `key=value` of fbbus's last `store restored` log line.
fn restored_line(log: &str) -> Option<Vec<(String, String)>> {
    let line = log.lines().rev().find(|l| l.contains("store restored"))?;
    Some(
        line.split_whitespace()
            .filter_map(|w| {
                let (k, v) = w.split_once('=')?;
                Some((strip_ansi(k), strip_ansi(v)))
            })
            .collect(),
    )
}

/// Without the colour escapes a terminal-less log may still carry.
fn strip_ansi(s: &str) -> String {
    let mut out = String::new();
    let mut chars = s.chars();
    while let Some(c) = chars.next() {
        if c == '\u{1b}' {
            for c in chars.by_ref() {
                if c.is_ascii_alphabetic() {
                    break;
                }
            }
        } else {
            out.push(c);
        }
    }
    out
}

/// Whether the broker answers: `/readyz` 200 (fbbus) or a CONNACK.
async fn answers(broker: &Running) -> bool {
    match broker.admin {
        Some(admin) => scrape::get(&format!("http://{admin}/readyz"), Duration::from_secs(1))
            .await
            .is_ok(),
        None => tokio::time::timeout(
            Duration::from_secs(1),
            mqtt::connect_session(broker.addr, "bench-probe", true),
        )
        .await
        .is_ok_and(|r| r.is_ok()),
    }
}

/// A fresh subscriber to `topic` receives its retained message within 1 s.
async fn retained_served(addr: SocketAddr, topic: &str) -> bool {
    let attempt = async {
        let (mut conn, _) = connect(addr, "bench-check", true).await.ok()?;
        mqtt::subscribe_qos(conn.get_mut(), topic, 0).await.ok()?;
        loop {
            if conn.read_more().await.ok()? == 0 {
                return None;
            }
            while let Ok(Some((header, body))) = conn.next_packet() {
                if mqtt::publish_payload(header, body).is_some() && (header & 1) == 1 {
                    let _ = conn.get_mut().write_all(&mqtt::DISCONNECT).await;
                    return Some(());
                }
            }
        }
    };
    tokio::time::timeout(Duration::from_secs(1), attempt)
        .await
        .ok()
        .flatten()
        .is_some()
}

/// PUBLISHes on `conn` until `want` arrived or nothing came for `quiet`, each QoS 1 one
/// acknowledged; returns how many arrived (bounded by `limit`).
async fn count_publishes(
    conn: &mut PacketReader,
    want: usize,
    quiet: Duration,
    limit: Duration,
) -> usize {
    let end_at = Instant::now() + limit;
    let mut got = 0;
    let mut acks = Vec::new();
    while got < want && Instant::now() < end_at {
        match tokio::time::timeout(quiet, conn.read_more()).await {
            Ok(Ok(n)) if n > 0 => {}
            _ => break,
        }
        while let Ok(Some((header, body))) = conn.next_packet() {
            if mqtt::publish_payload(header, body).is_some() {
                got += 1;
                if let Some(pid) = mqtt::packet_id(header, body) {
                    acks.extend_from_slice(&mqtt::puback_packet(pid));
                }
            }
        }
        if !acks.is_empty() {
            if conn.get_mut().write_all(&acks).await.is_err() {
                break;
            }
            acks.clear();
        }
    }
    got
}

async fn restart(broker: &mut Running, p: &PersistParams) -> Result<Figures> {
    let addr = broker.addr;
    let fill_started = Instant::now();
    // The sessions first, so that the queued messages are queued for them.
    let slots = Arc::new(tokio::sync::Semaphore::new(64));
    let mut tasks = Vec::with_capacity(p.sessions);
    for i in 0..p.sessions {
        let slots = Arc::clone(&slots);
        tasks.push(tokio::spawn(async move {
            let _slot = slots.acquire().await;
            let (mut conn, _) = connect(addr, &session_id(i), false).await?;
            let granted = tokio::time::timeout(
                CONNECT_TIMEOUT,
                mqtt::subscribe_qos(conn.get_mut(), &session_topic(i), 1),
            )
            .await
            .context("no SUBACK")??;
            if granted != 1 {
                bail!("{}: granted QoS {granted}", session_id(i));
            }
            conn.get_mut().write_all(&mqtt::DISCONNECT).await?;
            // The broker closes the connection after DISCONNECT.
            let _ = tokio::time::timeout(Duration::from_secs(5), conn.read_more()).await;
            anyhow::Ok(())
        }));
    }
    for t in tasks {
        t.await.context("session task")??;
    }
    let (mut publisher, _) = connect(addr, "bench-fill", true).await?;
    let sent = AtomicU64::new(0);
    let body = [0x5a; PAYLOAD_BYTES];
    let fill = async {
        publish_acked(&mut publisher, p.retained, 500, &sent, |k, pid, buf| {
            buf.extend(mqtt::publish_qos1_packet(
                &retained_topic(k),
                pid,
                true,
                &body,
            ));
        })
        .await?;
        let sessions = p.sessions.max(1);
        publish_acked(
            &mut publisher,
            p.sessions * p.queued,
            500,
            &sent,
            |k, pid, buf| {
                buf.extend(mqtt::publish_qos1_packet(
                    &session_topic(k % sessions),
                    pid,
                    false,
                    &body,
                ));
            },
        )
        .await
    };
    tokio::time::timeout(p.deadline * 2, fill)
        .await
        .context("filling the broker: timeout")?
        .context("filling the broker")?;
    publisher.get_mut().write_all(&mqtt::DISCONNECT).await?;
    drop(publisher);
    let fill_s = fill_started.elapsed().as_secs_f64();
    tokio::time::sleep(Duration::from_millis(200)).await;
    let mut note = None;
    if let (Kind::Fbbus, Some(admin)) = (broker.kind, broker.admin) {
        let retained = metric(admin, "fbbus_store_retained_messages").await;
        let sessions = metric(admin, "fbbus_store_sessions").await;
        let queued = metric(admin, "fbbus_store_queued_messages").await;
        if retained as usize != p.retained
            || sessions as usize != p.sessions
            || queued as usize != p.sessions * p.queued
        {
            add_note(
                &mut note,
                format!(
                    "before the stop the store held {retained:.0} retained, {sessions:.0} sessions, \
                     {queued:.0} queued"
                ),
            );
        }
    }

    let stop = broker
        .terminate(Duration::from_secs(60))
        .context("stopping the broker")?;
    let store_dir = broker.dir().join(match broker.kind {
        Kind::Fbbus => "store",
        _ => "mosquitto-store",
    });
    let store_mb = dir_bytes(&store_dir) as f64 / (1024.0 * 1024.0);

    let spawned = Instant::now();
    broker.respawn().context("starting the broker again")?;
    let deadline = spawned + p.deadline;
    let ready = loop {
        if let Some(exit) = broker.exited() {
            bail!("after the restart: {exit}");
        }
        if answers(broker).await {
            break spawned.elapsed();
        }
        if Instant::now() > deadline {
            bail!("not ready {:?} after the restart", p.deadline);
        }
        tokio::time::sleep(Duration::from_millis(2)).await;
    };
    let last = retained_topic(p.retained.saturating_sub(1));
    let served = loop {
        if retained_served(addr, &last).await {
            break spawned.elapsed();
        }
        if let Some(exit) = broker.exited() {
            bail!("after the restart: {exit}");
        }
        if Instant::now() > deadline {
            bail!(
                "the retained message on {last} was not served {:?} after the restart",
                p.deadline
            );
        }
        tokio::time::sleep(Duration::from_millis(2)).await;
    };

    // Not timed: is everything back?
    let retained_back = retained_back(addr, p.retained, p.deadline).await?;
    let (mut session, present) = connect(addr, &session_id(0), false).await?;
    let queued_back = count_publishes(
        &mut session,
        p.queued,
        Duration::from_secs(2),
        Duration::from_secs(10),
    )
    .await;
    drop(session);

    let log = std::fs::read_to_string(broker.log_path()).unwrap_or_default();
    let restored = match broker.kind {
        Kind::Fbbus => restored_line(&log),
        _ => None,
    };
    let field = |k: &str| -> Option<String> {
        restored
            .as_ref()?
            .iter()
            .find(|(key, _)| key == k)
            .map(|(_, v)| v.clone())
    };
    let number = |k: &str| field(k).and_then(|v| v.parse::<f64>().ok());
    let restored_cell = match broker.kind {
        Kind::Fbbus => match (field("retained"), field("sessions"), field("queued")) {
            (Some(r), Some(s), Some(q)) => format!("{r}/{s}/{q}"),
            _ => "no log line".into(),
        },
        _ => "-".into(),
    };
    if retained_back < p.retained {
        add_note(
            &mut note,
            format!(
                "{} retained messages missing after the restart",
                p.retained - retained_back
            ),
        );
    }
    let secs = |d: Duration| format!("{:.3}", d.as_secs_f64());
    let opt = |v: Option<f64>| v.map(|v| format!("{v:.0}")).unwrap_or_else(|| "-".into());
    Ok(Figures {
        cells: vec![
            secs(served),
            secs(ready),
            opt(number("read_ms")),
            opt(number("put_back_ms")),
            format!("{store_mb:.1}"),
            format!("{fill_s:.1}"),
            secs(stop),
            restored_cell,
            format!("{retained_back}/{}", p.retained),
            format!(
                "{}, {queued_back}/{}",
                if present { "present" } else { "NOT present" },
                p.queued
            ),
        ],
        keys: vec![
            Some(served.as_secs_f64()),
            Some(ready.as_secs_f64()),
            number("read_ms"),
            number("put_back_ms"),
            Some(store_mb),
        ],
        note,
    })
}

/// Every row in the order it ran, columns as wide as their widest cell.
fn table(t: &mut Transcript, m: Measure, rows: &[Row], rounds: u32) {
    let mut headers = vec!["setup".to_string()];
    headers.extend(m.columns().iter().map(|c| c.to_string()));
    let mut lines: Vec<(Vec<String>, Option<String>)> = Vec::new();
    for row in rows {
        let name = if rounds > 1 {
            format!("{} #{}", row.setup.label, row.round)
        } else {
            row.setup.label.to_string()
        };
        let mut cells = vec![name];
        match &row.result {
            Ok(f) => {
                cells.extend(f.cells.iter().cloned());
                lines.push((cells, f.note.clone()));
            }
            Err(why) => {
                cells.extend(m.columns().iter().map(|_| "-".to_string()));
                lines.push((cells, Some(why.clone())));
            }
        }
    }
    let rows: Vec<Vec<String>> = lines.iter().map(|(cells, _)| cells.clone()).collect();
    let widths = super::table::column_widths(headers.iter().map(|h| h.chars().count()), &rows);
    let render = |cells: &[String]| super::table::aligned(cells, &widths);
    t.line(format!("   {}", render(&headers)));
    for (cells, note) in &lines {
        let mut text = render(cells);
        if let Some(note) = note {
            text.push_str(&format!("  [{note}]"));
        }
        t.line(format!("   {text}"));
    }
}

fn median(mut v: Vec<f64>) -> Option<f64> {
    v.sort_by(f64::total_cmp);
    match v.len() {
        0 => None,
        n if n % 2 == 1 => Some(v[n / 2]),
        n => Some((v[n / 2 - 1] + v[n / 2]) / 2.0),
    }
}

/// The median of key `i` over the setup's successful rounds.
fn median_key(rows: &[Row], label: &str, i: usize) -> Option<f64> {
    median(
        rows.iter()
            .filter(|r| r.setup.label == label)
            .filter_map(|r| r.result.as_ref().ok())
            .filter_map(|f| f.keys.get(i).copied().flatten())
            .collect(),
    )
}

fn format_keys(m: Measure, rows: &[Row], label: &str) -> String {
    let k = |i| median_key(rows, label, i);
    match m {
        Measure::Throughput => k(0)
            .map(|v| format!("{} msg/s", super::scenarios::si(v)))
            .unwrap_or_else(|| "failed".into()),
        Measure::Latency => match (k(0), k(1), k(2)) {
            (Some(a), Some(b), Some(c)) => format!("p50/p99/max {a:.2}/{b:.2}/{c:.2} ms"),
            _ => "failed".into(),
        },
        Measure::Restart => match k(0) {
            Some(r) => {
                let mut s = format!("{r:.3} s");
                if let (Some(read), Some(put)) = (k(2), k(3)) {
                    s.push_str(&format!(" (read {read:.0} ms, put back {put:.0} ms)"));
                }
                s
            }
            None => "failed".into(),
        },
    }
}

/// `a/b 0.85x` (throughput) or `a/b 1.10x/1.20x/0.90x` (latency p50/p99/max) or `a/b
/// 0.20x` (restart time).
fn ratio(m: Measure, rows: &[Row], a: &str, b: &str) -> Option<String> {
    let n = match m {
        Measure::Latency => 3,
        _ => 1,
    };
    let mut parts = Vec::new();
    for i in 0..n {
        match (median_key(rows, a, i), median_key(rows, b, i)) {
            (Some(x), Some(y)) if y > 0.0 => parts.push(format!("{:.2}x", x / y)),
            _ => parts.push("n/a".into()),
        }
    }
    if parts.iter().all(|p| p == "n/a") {
        return None;
    }
    Some(format!("{a}/{b} {}", parts.join("/")))
}

/// The measurement's medians per setup, then the ratios: each fbbus policy against
/// fbbus-off and against mosquitto-persist, and Mosquitto's persistence against none.
fn ratio_lines(m: Measure, setups: &[Setup], rows: &[Row], p: &PersistParams) -> Vec<String> {
    let mut line = m.title(p);
    if p.rounds > 1 {
        line.push_str(&format!(" [median of {}]", p.rounds));
    }
    let ran: Vec<&Setup> = setups
        .iter()
        .filter(|s| rows.iter().any(|r| r.setup.label == s.label))
        .collect();
    for s in &ran {
        line.push_str(&format!("   {} {}", s.label, format_keys(m, rows, s.label)));
    }
    let mut ratios = Vec::new();
    for s in ran
        .iter()
        .filter(|s| s.kind == Kind::Fbbus && s.persistent())
    {
        for base in ["fbbus-off", "mosquitto-persist"] {
            if let Some(r) = ratio(m, rows, s.label, base) {
                ratios.push(r);
            }
        }
    }
    if let Some(r) = ratio(m, rows, "mosquitto-persist", "mosquitto-nopersist") {
        ratios.push(r);
    }
    let mut out = vec![line];
    if !ratios.is_empty() {
        out.push(format!(
            "   ratios: {}   ({})",
            ratios.join("   "),
            match m {
                Measure::Throughput => "higher is better",
                Measure::Latency => "p50/p99/max, lower is better",
                Measure::Restart => "lower is better",
            }
        ));
    }
    out
}

/// The goals, met or not, from the medians.
fn goals(t: &mut Transcript, all: &[(Measure, Vec<Row>)], p: &PersistParams) {
    let rows_of = |m: Measure| all.iter().find(|(x, _)| *x == m).map(|(_, r)| r);
    let verdict = |ok: bool| if ok { "MET" } else { "NOT MET" };
    t.line("");
    t.line("== goals (issue 17) ==");
    if let Some(rows) = rows_of(Measure::Throughput) {
        let default = median_key(rows, DEFAULT_POLICY, 0);
        for (base, want) in [("fbbus-off", 0.7), ("mosquitto-persist", 1.5)] {
            match (default, median_key(rows, base, 0)) {
                (Some(x), Some(y)) if y > 0.0 => t.line(format!(
                    "QoS 1 throughput, {DEFAULT_POLICY} (default policy) >= {want}x {base}: {:.2}x ({} / {} msg/s)  {}",
                    x / y,
                    super::scenarios::si(x),
                    super::scenarios::si(y),
                    verdict(x / y >= want)
                )),
                _ => t.line(format!(
                    "QoS 1 throughput, {DEFAULT_POLICY} (default policy) >= {want}x {base}: n/a (not measured)"
                )),
            }
        }
    }
    if let Some(rows) = rows_of(Measure::Restart) {
        match median_key(rows, DEFAULT_POLICY, 0) {
            Some(x) => {
                let worst = rows
                    .iter()
                    .filter(|r| r.setup.label == DEFAULT_POLICY)
                    .filter_map(|r| r.result.as_ref().ok()?.keys.first().copied().flatten())
                    .fold(0.0f64, f64::max);
                t.line(format!(
                    "restart of {DEFAULT_POLICY} with {} retained messages and {} sessions < 1 s: {x:.3} s \
                     (slowest round {worst:.3} s)  {}",
                    p.retained,
                    p.sessions,
                    verdict(x < 1.0)
                ))
            }
            None => t.line(format!(
                "restart of {DEFAULT_POLICY} < 1 s: n/a (not measured)"
            )),
        }
    }
}

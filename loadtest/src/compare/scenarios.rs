//! The six measurements of `compare`, the earlier broker study's. Each runs against one
//! freshly started broker, is bounded by a count and a deadline, and returns what it
//! measured as an [`Outcome`] (also after a timeout).
//!
//! The bursts (`fanin`, `latency`, `msgmem`) write raw PUBLISH packets
//! ([`loadtest::raw_client`]): 200,000 messages into one subscriber are beyond what a
//! client library generates on a shared 2-core machine. The connection scenarios
//! (`idlemem`, `connrate`, `authstorm`) are the harness's own connection wave and
//! idle-memory measurement ([`loadtest::scenario::connections`]).

use std::net::SocketAddr;
use std::sync::atomic::{AtomicU64, AtomicUsize, Ordering};
use std::sync::{Arc, Mutex};

use anyhow::{Context as _, Result};
use hdrhistogram::Histogram;
use tokio::io::{AsyncWriteExt, BufWriter};
use tokio::net::TcpStream;
use tokio::sync::watch;

use std::time::{Duration, Instant};

use loadtest::broker_process::spawn::{Kind, Running};
use loadtest::raw_client::{self as mqtt, PacketReader};
use loadtest::scenario::connections::{self, Wave};
use loadtest::target::Target;

/// Keeps the first reason a publisher stopped early (an I/O error or the deadline), for
/// the scenario's note.
fn note_publisher_end(
    first_error: &Mutex<Option<String>>,
    result: std::result::Result<std::io::Result<()>, tokio::time::error::Elapsed>,
) {
    let reason = match result {
        Ok(Ok(())) => return,
        Ok(Err(e)) => format!("publisher: {e}"),
        Err(_) => "publishers hit the deadline".into(),
    };
    if let Ok(mut first) = first_error.lock() {
        first.get_or_insert(reason);
    }
}
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
    Latency,
    IdleMem,
    MsgMem,
    ConnRate,
    AuthStorm,
}

impl Scenario {
    pub const ALL: [Scenario; 6] = [
        Scenario::Fanin,
        Scenario::Latency,
        Scenario::IdleMem,
        Scenario::MsgMem,
        Scenario::ConnRate,
        Scenario::AuthStorm,
    ];

    pub fn name(self) -> &'static str {
        match self {
            Scenario::Fanin => "fanin",
            Scenario::Latency => "latency",
            Scenario::IdleMem => "idlemem",
            Scenario::MsgMem => "msgmem",
            Scenario::ConnRate => "connrate",
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
                 conns/s = connected / (last CONNACK - start).",
                p.connrate_connections, p.connrate_inflight
            ),
            Scenario::AuthStorm => format!(
                "{} devices with passwords start TCP connect + CONNECT at the same instant against a broker \
                 process started for this scenario; time until the last CONNACK. Password stores: fbbus argon2id \
                 (security::hash_password defaults), mosquitto PBKDF2-SHA512 $7$ (mosquitto_passwd), \
                 rumqttd plaintext static map (no hashing at all). One salted hash per device.",
                p.storm_devices
            ),
        }
    }

    pub fn columns(self) -> &'static [&'static str] {
        match self {
            Scenario::Fanin => &["msg/s", "delivered", "lost", "send->last recv"],
            Scenario::Latency => &["p50 ms", "p99 ms", "max ms", "received", "lost"],
            Scenario::IdleMem => &["RSS before", "RSS after", "KB/conn", "connected"],
            Scenario::MsgMem => &["RSS before", "RSS after", "delivered", "msg/s"],
            Scenario::ConnRate => &["conns/s", "connected", "time"],
            Scenario::AuthStorm => &["all CONNACK", "p50", "p99", "connected", "password store"],
        }
    }

    /// Whether a larger key figure is better (decides the wording of the ratio line).
    pub fn higher_is_better(self) -> bool {
        matches!(self, Scenario::Fanin | Scenario::ConnRate)
    }

    /// The key figures as printed in the ratio line.
    pub fn format_keys(self, keys: &[Option<f64>]) -> String {
        let k = |i: usize| keys.get(i).copied().flatten();
        let or_na = |v: Option<String>| v.unwrap_or_else(|| "n/a".into());
        match self {
            Scenario::Fanin => or_na(k(0).map(|v| format!("{} msg/s", si(v)))),
            Scenario::Latency => match (k(0), k(1), k(2)) {
                (Some(a), Some(b), Some(c)) => format!("p50/p99/max {a:.2}/{b:.2}/{c:.2} ms"),
                _ => "n/a".into(),
            },
            Scenario::IdleMem => or_na(k(0).map(|v| format!("{v:.2} KB/conn"))),
            Scenario::MsgMem => or_na(k(0).map(|v| format!("{v:.1} MB"))),
            Scenario::ConnRate => or_na(k(0).map(|v| format!("{v:.0} conn/s"))),
            Scenario::AuthStorm => or_na(k(0).map(|v| format!("{v:.2} s"))),
        }
    }

    pub async fn run(self, broker: &Running, p: &Params, storm: Option<&Login>) -> Outcome {
        let result = match self {
            Scenario::Fanin => fanin(broker, p).await,
            Scenario::Latency => latency(broker, p).await,
            Scenario::IdleMem => idle_memory(broker, p).await,
            Scenario::MsgMem => message_memory(broker, p).await,
            Scenario::ConnRate => connection_rate(broker, p).await,
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
    pub fanin_messages: usize,
    pub latency_rate: u64,
    pub latency_secs: u64,
    pub idle_connections: usize,
    pub msgmem_per_publisher: usize,
    pub connrate_connections: usize,
    pub connrate_inflight: usize,
    pub storm_devices: usize,
    /// Each scenario's own time limit (the latency scenario adds its duration).
    pub deadline: Duration,
}

impl Params {
    pub fn full() -> Params {
        Params {
            publishers: 10,
            fanin_messages: 20_000,
            latency_rate: 1_000,
            latency_secs: 10,
            idle_connections: 1_000,
            msgmem_per_publisher: 100_000,
            connrate_connections: 2_000,
            connrate_inflight: 64,
            storm_devices: 1_045,
            deadline: Duration::from_secs(60),
        }
    }

    pub fn quick() -> Params {
        Params {
            publishers: 10,
            fanin_messages: 2_000,
            latency_rate: 1_000,
            latency_secs: 2,
            idle_connections: 100,
            msgmem_per_publisher: 10_000,
            connrate_connections: 200,
            connrate_inflight: 64,
            storm_devices: 100,
            deadline: Duration::from_secs(20),
        }
    }
}

/// What one scenario measured on one broker: the table cells, the key figures for the ratio
/// line (None: not measured) and a note (timeout, failures, errors).
#[derive(Clone, Debug)]
pub struct Outcome {
    pub cells: Vec<String>,
    pub keys: Vec<Option<f64>>,
    pub note: Option<String>,
    /// The key figures are incomplete (deadline hit): shown as "timeout" in the ratio line.
    pub timed_out: bool,
}

impl Outcome {
    pub fn failed(scenario: Scenario, note: String) -> Outcome {
        Outcome {
            cells: vec!["-".into(); scenario.columns().len()],
            keys: Vec::new(),
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

async fn connect(addr: SocketAddr, id: &str) -> Result<TcpStream> {
    tokio::time::timeout(CONNECT_TIMEOUT, mqtt::connect(addr, id, None))
        .await
        .with_context(|| format!("{id}: no CONNACK within {CONNECT_TIMEOUT:?}"))?
        .with_context(|| id.to_string())
}

/// One subscriber on `topic` plus `publishers` connected publishers.
async fn subscriber_and_publishers(
    addr: SocketAddr,
    topic: &str,
    publishers: usize,
) -> Result<(PacketReader, Vec<TcpStream>)> {
    let mut sub = connect(addr, "bench-sub").await?;
    tokio::time::timeout(CONNECT_TIMEOUT, mqtt::subscribe(&mut sub, topic))
        .await
        .context("no SUBACK")??;
    let mut pubs = Vec::with_capacity(publishers);
    for i in 0..publishers {
        pubs.push(connect(addr, &format!("bench-pub-{i}")).await?);
    }
    // Routers apply a subscription asynchronously to its SUBACK on some brokers.
    tokio::time::sleep(Duration::from_millis(200)).await;
    Ok((PacketReader::new(sub), pubs))
}

#[derive(Debug, PartialEq, Eq)]
enum DrainEnd {
    Complete,
    /// Publishers done and nothing arrived for the idle time: the rest was lost.
    Idle,
    Closed,
    Deadline,
    Error(String),
}

struct Drained {
    reader: PacketReader,
    received: u64,
    last_receive: Option<Instant>,
    end: DrainEnd,
    latency_ns: Option<Histogram<u64>>,
}

/// Counts PUBLISHes until `expected` arrived, the publishers are done and the stream was
/// idle for `idle`, the broker closed the connection, or `end_at`. With `epoch`, the first
/// 8 payload bytes are a send time (ns since `epoch`) and latencies go into a histogram.
async fn drain(
    mut reader: PacketReader,
    expected: u64,
    publishers_done: Arc<AtomicUsize>,
    publishers: usize,
    idle: Duration,
    end_at: Instant,
    epoch: Option<Instant>,
) -> Drained {
    let mut latency_ns = epoch.map(|_| {
        Histogram::<u64>::new_with_bounds(1, 120_000_000_000, 3).expect("valid histogram bounds")
    });
    let mut received = 0u64;
    let mut last_receive = None;
    let mut last_activity = Instant::now();
    let mut done_seen: Option<Instant> = None;
    let end = loop {
        if received >= expected {
            break DrainEnd::Complete;
        }
        let now = Instant::now();
        if now >= end_at {
            break DrainEnd::Deadline;
        }
        if done_seen.is_none() && publishers_done.load(Ordering::Acquire) >= publishers {
            done_seen = Some(now);
        }
        if let Some(done) = done_seen {
            if now.duration_since(done.max(last_activity)) >= idle {
                break DrainEnd::Idle;
            }
        }
        match tokio::time::timeout(Duration::from_millis(100), reader.read_more()).await {
            Err(_) => continue,
            Ok(Err(e)) => break DrainEnd::Error(e.to_string()),
            Ok(Ok(0)) => break DrainEnd::Closed,
            Ok(Ok(_)) => {
                let t = Instant::now();
                last_activity = t;
                let now_ns = epoch.map(|e| t.duration_since(e).as_nanos() as u64);
                let mut got = 0u64;
                loop {
                    match reader.next_packet() {
                        Ok(Some((header, body))) => {
                            if let Some(payload) = mqtt::publish_payload(header, body) {
                                got += 1;
                                if let (Some(h), Some(now_ns), Some(ts)) =
                                    (latency_ns.as_mut(), now_ns, payload.get(..8))
                                {
                                    let sent = u64::from_be_bytes(ts.try_into().expect("8 bytes"));
                                    h.saturating_record(now_ns.saturating_sub(sent).max(1));
                                }
                            }
                        }
                        Ok(None) => break,
                        Err(e) => {
                            return Drained {
                                reader,
                                received: received + got,
                                last_receive,
                                end: DrainEnd::Error(e.to_string()),
                                latency_ns,
                            }
                        }
                    }
                }
                if got > 0 {
                    received += got;
                    last_receive = Some(t);
                }
            }
        }
    };
    Drained {
        reader,
        received,
        last_receive,
        end,
        latency_ns,
    }
}

struct Burst {
    sent: u64,
    expected: u64,
    received: u64,
    first_send: Instant,
    last_receive: Option<Instant>,
    timed_out: bool,
    note: Option<String>,
    /// Every client connection, still open.
    _keep: (PacketReader, Vec<TcpStream>),
}

impl Burst {
    fn rate(&self) -> Option<f64> {
        let last = self.last_receive?;
        let secs = last.duration_since(self.first_send).as_secs_f64();
        (secs > 0.0).then(|| self.received as f64 / secs)
    }
}

/// `publishers` x `per_publisher` QoS 0 messages as fast as possible into one subscriber.
async fn burst(
    addr: SocketAddr,
    publishers: usize,
    per_publisher: usize,
    deadline: Duration,
) -> Result<Burst> {
    let topic = "bench/burst";
    let (reader, pubs) = subscriber_and_publishers(addr, topic, publishers).await?;
    let packet = Arc::new(mqtt::publish_packet(topic, &[0x5a; PAYLOAD_BYTES]));
    let (go_tx, go_rx) = watch::channel(false);
    let done = Arc::new(AtomicUsize::new(0));
    let sent = Arc::new(AtomicU64::new(0));
    let first_error = Arc::new(Mutex::new(None::<String>));
    let end_at = Instant::now() + deadline;
    let mut tasks = Vec::with_capacity(publishers);
    for stream in pubs {
        let (mut go, packet, done, sent, first_error) = (
            go_rx.clone(),
            packet.clone(),
            done.clone(),
            sent.clone(),
            first_error.clone(),
        );
        tasks.push(tokio::spawn(async move {
            let _ = go.wait_for(|go| *go).await;
            let mut writer = BufWriter::with_capacity(64 * 1024, stream);
            let send_all = async {
                for _ in 0..per_publisher {
                    writer.write_all(&packet).await?;
                    sent.fetch_add(1, Ordering::Relaxed);
                }
                writer.flush().await
            };
            note_publisher_end(
                &first_error,
                tokio::time::timeout_at(end_at.into(), send_all).await,
            );
            done.fetch_add(1, Ordering::Release);
            writer.into_inner()
        }));
    }
    let expected = (publishers * per_publisher) as u64;
    let drained = tokio::spawn(drain(
        reader,
        expected,
        done.clone(),
        publishers,
        Duration::from_secs(2),
        end_at,
        None,
    ));
    let first_send = Instant::now();
    go_tx.send(true).ok();
    let mut streams = Vec::with_capacity(publishers);
    for t in tasks {
        streams.push(t.await.context("publisher task")?);
    }
    let drained = drained.await.context("subscriber task")?;
    let mut note = first_error
        .lock()
        .unwrap_or_else(std::sync::PoisonError::into_inner)
        .take();
    let timed_out =
        drained.end == DrainEnd::Deadline || note.as_deref() == Some("publishers hit the deadline");
    match &drained.end {
        DrainEnd::Closed => add_note(&mut note, "broker closed the subscriber"),
        DrainEnd::Error(e) => add_note(&mut note, format!("subscriber: {e}")),
        _ => {}
    }
    if timed_out {
        add_note(&mut note, "timeout");
    }
    Ok(Burst {
        sent: sent.load(Ordering::Relaxed),
        expected,
        received: drained.received,
        first_send,
        last_receive: drained.last_receive,
        timed_out,
        note,
        _keep: (drained.reader, streams),
    })
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

async fn fanin(broker: &Running, p: &Params) -> Result<Outcome> {
    let b = burst(broker.addr, p.publishers, p.fanin_messages, p.deadline).await?;
    let rate = b.rate();
    let span = b
        .last_receive
        .map(|l| format!("{:.3} s", l.duration_since(b.first_send).as_secs_f64()))
        .unwrap_or_else(|| "-".into());
    Ok(Outcome {
        cells: vec![
            rate.map(si).unwrap_or_else(|| "-".into()),
            delivered(b.received, b.expected),
            lost(b.received, b.sent),
            span,
        ],
        keys: vec![rate],
        note: b.note.clone(),
        timed_out: b.timed_out,
    })
}

async fn latency(broker: &Running, p: &Params) -> Result<Outcome> {
    let topic = "bench/latency";
    let (reader, pubs) = subscriber_and_publishers(broker.addr, topic, p.publishers).await?;
    let per_publisher = p.latency_rate * p.latency_secs;
    let period_ns = 1_000_000_000 / p.latency_rate.max(1);
    let epoch = Instant::now();
    let end_at = Instant::now() + p.deadline + Duration::from_secs(p.latency_secs);
    let start = tokio::time::Instant::now() + Duration::from_millis(100);
    let done = Arc::new(AtomicUsize::new(0));
    let sent = Arc::new(AtomicU64::new(0));
    let first_error = Arc::new(Mutex::new(None::<String>));
    let publishers = pubs.len();
    let mut tasks = Vec::with_capacity(publishers);
    for (i, mut stream) in pubs.into_iter().enumerate() {
        let (done, sent, first_error) = (done.clone(), sent.clone(), first_error.clone());
        tasks.push(tokio::spawn(async move {
            let mut packet = mqtt::publish_packet(topic, &[0u8; PAYLOAD_BYTES]);
            let ts_at = packet.len() - PAYLOAD_BYTES;
            packet[ts_at + 8..ts_at + 12].copy_from_slice(&(i as u32).to_be_bytes());
            let send_all = async {
                for k in 0..per_publisher {
                    // An absolute schedule: a late send does not shift the later ones. tokio's
                    // timer has 1 ms resolution, so at 1,000 msg/s the publishers' sends share
                    // each millisecond tick (10 messages at once into the broker).
                    tokio::time::sleep_until(start + Duration::from_nanos(k * period_ns)).await;
                    let now_ns = epoch.elapsed().as_nanos() as u64;
                    packet[ts_at..ts_at + 8].copy_from_slice(&now_ns.to_be_bytes());
                    packet[ts_at + 12..ts_at + 20].copy_from_slice(&k.to_be_bytes());
                    stream.write_all(&packet).await?;
                    sent.fetch_add(1, Ordering::Relaxed);
                }
                Ok::<(), std::io::Error>(())
            };
            note_publisher_end(
                &first_error,
                tokio::time::timeout_at(end_at.into(), send_all).await,
            );
            done.fetch_add(1, Ordering::Release);
            stream
        }));
    }
    let expected = per_publisher * publishers as u64;
    let drained = drain(
        reader,
        expected,
        done.clone(),
        publishers,
        Duration::from_secs(2),
        end_at,
        Some(epoch),
    )
    .await;
    let mut streams = Vec::with_capacity(publishers);
    for t in tasks {
        streams.push(t.await.context("publisher task")?);
    }
    let sent = sent.load(Ordering::Relaxed);
    let mut note = first_error
        .lock()
        .unwrap_or_else(std::sync::PoisonError::into_inner)
        .take();
    let timed_out = drained.end == DrainEnd::Deadline;
    match &drained.end {
        DrainEnd::Closed => add_note(&mut note, "broker closed the subscriber"),
        DrainEnd::Error(e) => add_note(&mut note, format!("subscriber: {e}")),
        _ => {}
    }
    if timed_out {
        add_note(&mut note, "timeout");
    }
    let h = drained.latency_ns.expect("latency histogram");
    let (p50, p99, max) = latency_ms(&h);
    drop(streams);
    Ok(Outcome {
        cells: vec![
            ms_cell(p50),
            ms_cell(p99),
            ms_cell(max),
            delivered(drained.received, expected),
            lost(drained.received, sent),
        ],
        keys: vec![p50, p99, max],
        note,
        timed_out,
    })
}

/// The broker as the harness's client stack addresses it, optionally with a login.
fn target(broker: &Running, login: Option<(&str, &str)>) -> Result<Target> {
    let mut target = Target::parse(&broker.url())?;
    if let Some((user, password)) = login {
        target.username = Some(user.to_owned());
        target.password = Some(password.to_owned());
    }
    Ok(target)
}

/// Failed connections of a wave, for the scenario's note.
fn wave_note(wave: &Wave) -> Option<String> {
    wave.errors
        .first()
        .map(|first| format!("{} of {} failed: {first}", wave.errors.len(), wave.n))
}

/// A wave's clients, dropped without DISCONNECT: the broker is stopped next anyway.
fn close(wave: Wave) {
    for c in wave.clients {
        c.abort();
    }
}

async fn idle_memory(broker: &Running, p: &Params) -> Result<Outcome> {
    let idle = connections::idle_memory(
        &target(broker, None)?,
        Some(broker.pid()),
        "bench-idle",
        p.idle_connections,
        64,
        Duration::from_secs(1),
        Duration::from_secs(1),
        p.deadline,
    )
    .await;
    let before = idle
        .before_kib
        .context("cannot read VmRSS of the broker process")?;
    let after = idle
        .after_kib
        .context("cannot read VmRSS of the broker process")?;
    let n = idle.wave.clients.len();
    // KB as /proc reports it (kB = 1024 bytes), like the reference figures.
    let per_conn = idle.kib_per_connection();
    let note = wave_note(&idle.wave);
    close(idle.wave);
    Ok(Outcome {
        cells: vec![
            mb(before),
            mb(after),
            per_conn
                .map(|v| format!("{v:.2}"))
                .unwrap_or_else(|| "-".into()),
            format!("{n}/{}", p.idle_connections),
        ],
        keys: vec![per_conn],
        note,
        timed_out: false,
    })
}

async fn message_memory(broker: &Running, p: &Params) -> Result<Outcome> {
    tokio::time::sleep(Duration::from_secs(1)).await;
    let before = rss(broker)?;
    let b = burst(
        broker.addr,
        p.publishers,
        p.msgmem_per_publisher,
        p.deadline,
    )
    .await?;
    tokio::time::sleep(Duration::from_secs(2)).await;
    let after = rss(broker)?;
    let rate = b.rate();
    let after_mb = after as f64 / 1024.0;
    Ok(Outcome {
        cells: vec![
            mb(before),
            mb(after),
            delivered(b.received, b.expected),
            rate.map(si).unwrap_or_else(|| "-".into()),
        ],
        keys: vec![Some(after_mb)],
        note: b.note.clone(),
        timed_out: b.timed_out,
    })
}

async fn connection_rate(broker: &Running, p: &Params) -> Result<Outcome> {
    let wave = connections::connect_many(
        &target(broker, None)?,
        "bench-rate",
        p.connrate_connections,
        p.connrate_inflight,
        p.deadline,
    )
    .await;
    let n = wave.clients.len();
    let rate = (n > 0).then(|| wave.rate());
    let took = wave.took;
    let note = wave_note(&wave);
    close(wave);
    Ok(Outcome {
        cells: vec![
            rate.map(|r| format!("{r:.0}"))
                .unwrap_or_else(|| "-".into()),
            format!("{n}/{}", p.connrate_connections),
            format!("{:.3} s", took.as_secs_f64()),
        ],
        keys: vec![rate],
        note,
        timed_out: false,
    })
}

async fn auth_storm(broker: &Running, p: &Params, login: &Login) -> Result<Outcome> {
    let n = p.storm_devices;
    let user = format!("{STORM_USER_PREFIX}{{i}}");
    let target = target(broker, Some((&user, &login.password)))?;
    // Every device at once: as many in flight as there are devices.
    let wave = connections::connect_many(&target, "bench-storm", n, n, p.deadline).await;
    let connected = wave.clients.len();
    let pct = |q: f64| -> Option<Duration> {
        (connected > 0).then(|| Duration::from_micros(wave.latency.value_at_quantile(q)))
    };
    let secs = |d: Option<Duration>| {
        d.map(|d| format!("{:.3} s", d.as_secs_f64()))
            .unwrap_or_else(|| "-".into())
    };
    let all = (connected > 0).then_some(wave.took);
    let store = match broker.kind {
        Kind::Fbbus => "argon2id m=8192 t=1 p=1",
        Kind::Rumqttd => "plaintext map",
        Kind::Mosquitto | Kind::MosquittoDefault => "PBKDF2-SHA512 $7$",
    };
    let mut note = wave_note(&wave);
    // "All have CONNACK" is only true when nobody failed.
    let complete = connected == n;
    if !complete && note.is_none() {
        add_note(&mut note, format!("{} not connected", n - connected));
    }
    let cells = vec![
        secs(all),
        secs(pct(0.50)),
        secs(pct(0.99)),
        format!("{connected}/{n}"),
        store.into(),
    ];
    close(wave);
    Ok(Outcome {
        cells,
        keys: vec![all.filter(|_| complete).map(|d| d.as_secs_f64())],
        note,
        timed_out: false,
    })
}

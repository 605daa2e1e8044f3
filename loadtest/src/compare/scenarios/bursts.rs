//! The bursts (`fanin`, `fanin1`, `pairs`, `latency`, `msgmem`): raw PUBLISH packets from
//! publishers that write as fast as they can (or at a steady rate) into subscribers that
//! drain and count them (and acknowledge them at QoS 1). One burst, [`burst`], for every
//! shape ([`Shape`]): many publishers into one subscriber (fan-in, at QoS 0 or 1), or
//! many independent publisher/subscriber pairs.

use std::net::SocketAddr;
use std::sync::atomic::{AtomicU64, AtomicUsize, Ordering};
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

use anyhow::{Context as _, Result};
use hdrhistogram::Histogram;
use tokio::io::{AsyncWriteExt, BufWriter};
use tokio::net::TcpStream;
use tokio::sync::watch;

use loadtest::broker_process::spawn::Running;
use loadtest::raw_client::{self as mqtt, PacketReader};

use super::{
    add_note, delivered, latency_ms, lost, mb, ms_cell, rss, si, Outcome, Params, CONNECT_TIMEOUT,
    PAYLOAD_BYTES,
};

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

async fn connect(addr: SocketAddr, id: &str) -> Result<TcpStream> {
    tokio::time::timeout(CONNECT_TIMEOUT, mqtt::connect(addr, id, None))
        .await
        .with_context(|| format!("{id}: no CONNACK within {CONNECT_TIMEOUT:?}"))?
        .with_context(|| id.to_string())
}

/// One subscriber on `topic` at `qos` (`<prefix>-sub`) plus `publishers` connected
/// publishers (`<prefix>-pub-<i>`).
async fn group(
    addr: SocketAddr,
    prefix: &str,
    topic: &str,
    publishers: usize,
    qos: u8,
) -> Result<(PacketReader, Vec<TcpStream>)> {
    let id = format!("{prefix}-sub");
    let mut sub = connect(addr, &id).await?;
    let granted = tokio::time::timeout(CONNECT_TIMEOUT, mqtt::subscribe_qos(&mut sub, topic, qos))
        .await
        .with_context(|| format!("{id}: no SUBACK"))??;
    if granted != qos {
        anyhow::bail!("{id}: the subscription to {topic} was granted QoS {granted}, not {qos}");
    }
    let mut pubs = Vec::with_capacity(publishers);
    for i in 0..publishers {
        pubs.push(connect(addr, &format!("{prefix}-pub-{i}")).await?);
    }
    Ok((PacketReader::new(sub), pubs))
}

/// Routers apply a subscription asynchronously to its SUBACK on some brokers: the pause
/// between the last SUBACK and the first PUBLISH.
const SUBSCRIPTION_SETTLE: Duration = Duration::from_millis(200);

/// One QoS 0 subscriber on `topic` plus `publishers` connected publishers, settled.
async fn subscriber_and_publishers(
    addr: SocketAddr,
    topic: &str,
    publishers: usize,
) -> Result<(PacketReader, Vec<TcpStream>)> {
    let clients = group(addr, "bench", topic, publishers, 0).await?;
    tokio::time::sleep(SUBSCRIPTION_SETTLE).await;
    Ok(clients)
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
/// idle for `idle`, the broker closed the connection, or `end_at`; acknowledges QoS 1 ones.
/// With `epoch`, the first 8 payload bytes are a send time (ns since `epoch`) and
/// latencies go into a histogram.
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
    let mut acks = Vec::new();
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
                            if let Some(pid) = mqtt::packet_id(header, body) {
                                acks.extend_from_slice(&mqtt::puback_packet(pid));
                            }
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
                // QoS 1: every PUBLISH of this read acknowledged in one write.
                if !acks.is_empty() {
                    if let Err(e) = reader.get_mut().write_all(&acks).await {
                        break DrainEnd::Error(e.to_string());
                    }
                    acks.clear();
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

/// What a burst sends, and where: `groups` topics, each with one subscriber and
/// `publishers` publishers that write `per_publisher` messages of [`PAYLOAD_BYTES`] at
/// `qos` as fast as they can (QoS 1: at most `inflight` unacknowledged per publisher).
/// Fan-in is one group of 10 publishers; `pairs` is 50 groups of one.
#[derive(Clone, Copy, Debug)]
pub(super) struct Shape {
    pub groups: usize,
    pub publishers: usize,
    pub per_publisher: usize,
    pub qos: u8,
    pub inflight: usize,
}

impl Shape {
    fn expected_per_group(&self) -> u64 {
        (self.publishers * self.per_publisher) as u64
    }

    fn expected(&self) -> u64 {
        self.groups as u64 * self.expected_per_group()
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
    _keep: (Vec<PacketReader>, Vec<TcpStream>),
}

impl Burst {
    fn rate(&self) -> Option<f64> {
        let last = self.last_receive?;
        let secs = last.duration_since(self.first_send).as_secs_f64();
        (secs > 0.0).then(|| self.received as f64 / secs)
    }
}

/// One publisher of a burst: waits for `go`, then writes its messages. QoS 0: 64 KiB
/// buffered writes, nothing to wait for. QoS 1: a window of `inflight` PUBLISHes, each
/// batch written at once, the next ones as PUBACKs come back.
async fn publish_burst(
    stream: TcpStream,
    topic: String,
    shape: Shape,
    sent: &AtomicU64,
    end_at: Instant,
) -> (
    TcpStream,
    std::result::Result<std::io::Result<()>, tokio::time::error::Elapsed>,
) {
    if shape.qos == 0 {
        let packet = mqtt::publish_packet(&topic, &[0x5a; PAYLOAD_BYTES]);
        let mut writer = BufWriter::with_capacity(64 * 1024, stream);
        let send_all = async {
            for _ in 0..shape.per_publisher {
                writer.write_all(&packet).await?;
                sent.fetch_add(1, Ordering::Relaxed);
            }
            writer.flush().await
        };
        let result = tokio::time::timeout_at(end_at.into(), send_all).await;
        (writer.into_inner(), result)
    } else {
        let mut conn = PacketReader::new(stream);
        let send_all = mqtt::publish_acked(
            &mut conn,
            shape.per_publisher,
            shape.inflight,
            sent,
            |_, pid, buf| {
                buf.extend(mqtt::publish_qos1_packet(
                    &topic,
                    pid,
                    false,
                    &[0x5a; PAYLOAD_BYTES],
                ))
            },
        );
        let result = tokio::time::timeout_at(end_at.into(), send_all).await;
        (conn.into_inner(), result)
    }
}

/// A burst of `shape`: every group's clients connected first, then every publisher starts
/// at once; each subscriber drains its own topic. Received and lost are over all groups;
/// the last receive is the latest of any subscriber.
async fn burst(addr: SocketAddr, shape: Shape, deadline: Duration) -> Result<Burst> {
    let mut subs = Vec::with_capacity(shape.groups);
    let mut pubs = Vec::with_capacity(shape.groups * shape.publishers);
    for g in 0..shape.groups {
        // One group keeps the fan-in's topic and client ids of the earlier study.
        let (prefix, topic) = match shape.groups {
            1 => ("bench".to_string(), "bench/burst".to_string()),
            _ => (format!("bench-{g}"), format!("bench/pair/{g}")),
        };
        let (sub, group_pubs) = group(addr, &prefix, &topic, shape.publishers, shape.qos).await?;
        subs.push(sub);
        pubs.extend(group_pubs.into_iter().map(|p| (topic.clone(), p)));
    }
    tokio::time::sleep(SUBSCRIPTION_SETTLE).await;
    let publishers = pubs.len();
    let (go_tx, go_rx) = watch::channel(false);
    let done = Arc::new(AtomicUsize::new(0));
    let sent = Arc::new(AtomicU64::new(0));
    let first_error = Arc::new(Mutex::new(None::<String>));
    let end_at = Instant::now() + deadline;
    let mut tasks = Vec::with_capacity(publishers);
    for (topic, stream) in pubs {
        let (mut go, done, sent, first_error) = (
            go_rx.clone(),
            done.clone(),
            sent.clone(),
            first_error.clone(),
        );
        tasks.push(tokio::spawn(async move {
            let _ = go.wait_for(|go| *go).await;
            let (stream, result) = publish_burst(stream, topic, shape, &sent, end_at).await;
            note_publisher_end(&first_error, result);
            done.fetch_add(1, Ordering::Release);
            stream
        }));
    }
    let drains: Vec<_> = subs
        .into_iter()
        .map(|reader| {
            tokio::spawn(drain(
                reader,
                shape.expected_per_group(),
                done.clone(),
                publishers,
                Duration::from_secs(2),
                end_at,
                None,
            ))
        })
        .collect();
    let first_send = Instant::now();
    go_tx.send(true).ok();
    let mut streams = Vec::with_capacity(publishers);
    for t in tasks {
        streams.push(t.await.context("publisher task")?);
    }
    let mut note = first_error
        .lock()
        .unwrap_or_else(std::sync::PoisonError::into_inner)
        .take();
    let mut timed_out = note.as_deref() == Some("publishers hit the deadline");
    let (mut received, mut last_receive) = (0u64, None::<Instant>);
    let mut readers = Vec::with_capacity(drains.len());
    let mut subscriber_problem = None;
    for d in drains {
        let drained = d.await.context("subscriber task")?;
        received += drained.received;
        last_receive = last_receive.max(drained.last_receive);
        timed_out |= drained.end == DrainEnd::Deadline;
        let problem = match &drained.end {
            DrainEnd::Closed => Some("broker closed the subscriber".to_string()),
            DrainEnd::Error(e) => Some(format!("subscriber: {e}")),
            _ => None,
        };
        subscriber_problem = subscriber_problem.or(problem);
        readers.push(drained.reader);
    }
    if let Some(problem) = subscriber_problem {
        add_note(&mut note, problem);
    }
    if timed_out {
        add_note(&mut note, "timeout");
    }
    Ok(Burst {
        sent: sent.load(Ordering::Relaxed),
        expected: shape.expected(),
        received,
        first_send,
        last_receive,
        timed_out,
        note,
        _keep: (readers, streams),
    })
}

/// `fanin`, `fanin1` and `pairs`: delivered msg/s (first send to last receive) and what
/// was lost, for a burst of `shape`.
pub(super) async fn throughput(broker: &Running, shape: Shape, p: &Params) -> Result<Outcome> {
    let b = burst(broker.addr, shape, p.deadline).await?;
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
        lost: Some(b.sent.saturating_sub(b.received)),
        note: b.note.clone(),
        timed_out: b.timed_out,
    })
}

pub(super) async fn latency(broker: &Running, p: &Params) -> Result<Outcome> {
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
        lost: Some(sent.saturating_sub(drained.received)),
        note,
        timed_out,
    })
}

pub(super) async fn message_memory(broker: &Running, p: &Params) -> Result<Outcome> {
    tokio::time::sleep(Duration::from_secs(1)).await;
    let before = rss(broker)?;
    let shape = Shape {
        groups: 1,
        publishers: p.publishers,
        per_publisher: p.msgmem_per_publisher,
        qos: 0,
        inflight: p.inflight,
    };
    let b = burst(broker.addr, shape, p.deadline).await?;
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
        lost: None,
        note: b.note.clone(),
        timed_out: b.timed_out,
    })
}

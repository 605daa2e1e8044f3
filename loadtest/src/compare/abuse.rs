//! `fbbus-loadtest compare abuse`: the floods of issue 21 against an fbbus it starts
//! itself, with what each costs a well-behaved device.
//!
//! One fbbus child process (its defaults, an admin endpoint on 127.0.0.1) runs through
//! seven phases of `--phase-secs` each, with a settle between two phases:
//!
//! 0. `idle`: only the probe;
//! 1. `registry`: distinct client ids CONNECT, declare a small interface (QoS 1, the PUBACK
//!    awaited) and DISCONNECT, 8 at a time, at most 50,000, from 500 loopback addresses
//!    (127.0.0.2 on, 100 devices each: the per-address limit lets each address fill its
//!    share, so the flood meets the line's `max_devices`);
//! 2. `redeclare`: one client declares the same device again as fast as the broker
//!    acknowledges (QoS 1, one at a time);
//! 3. `admin-poll`: 6 loops GET `/api/v1/devices`, following `next` pages;
//! 4. `slow-headers`: 500 connections to the admin port each send part of a request
//!    header and wait; meanwhile clients CONNECT and DISCONNECT, every one should succeed;
//! 5. `labels`: one device declares an FB with 100 fresh port names per declaration and
//!    publishes a string on each INT port (ill-typed, refused);
//! 6. `retained`: retained QoS 0 publications on distinct topics, at most 100,000.
//!
//! The probe, all along: one client subscribed at QoS 1 to its own topic publishes a QoS
//! 1 message every 10 ms and times each publish -> delivery (HDR histogram); a probe not
//! delivered within 5 s is lost. A sampler reads the broker's VmRSS and counts its
//! `/proc/<pid>/fd` every 100 ms. Per phase: flood operations, refusals (the deltas of
//! `fbbus_limit_refusals_total`, `fbbus_connects_refused_total` and
//! `fbbus_admin_connections_refused_total`), probe p50/p99/max,
//! p99 / idle p99, probes lost, peak RSS and fds, `/metrics` size at the end. Then the
//! goals of the issue, MET or NOT MET.
//!
//! Everything on 127.0.0.1; every loop is bounded by a count and the phase's deadline.

use std::collections::HashMap;
use std::net::SocketAddr;
use std::path::Path;
use std::sync::atomic::{AtomicBool, AtomicU64, AtomicUsize, Ordering};
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

use anyhow::{bail, Context as _, Result};
use hdrhistogram::Histogram;
use tokio::io::AsyncWriteExt;
use tokio::net::TcpStream;

use loadtest::broker_process::{self, spawn};
use loadtest::raw_client::{self as mqtt, PacketReader};
use loadtest::scrape;

use super::table::{aligned, column_widths};
use super::{start_fbbus, Transcript};

/// Probe interval and how long a probe may take before it counts as lost.
const PROBE_EVERY: Duration = Duration::from_millis(10);
const PROBE_LOST_AFTER: Duration = Duration::from_secs(5);
/// Resident memory and descriptors are sampled this often.
const SAMPLE_EVERY: Duration = Duration::from_millis(100);
/// Bounds of the floods.
const MAX_DEVICES: u64 = 50_000;
const MAX_RETAINED: u64 = 100_000;
const REGISTRY_WORKERS: usize = 8;
/// Devices of phase 1 from one source address: fbbus's default `max_devices_per_identity`.
const DEVICES_PER_SOURCE: u64 = 100;

/// The loopback address device `n` of phase 1 connects from: 127.0.0.2 on, a new one
/// every [`DEVICES_PER_SOURCE`] devices (at most 50,000 / 100 = 500 addresses).
fn registry_source(n: u64) -> std::net::IpAddr {
    let k = 2 + n / DEVICES_PER_SOURCE;
    std::net::Ipv4Addr::new(127, 0, (k / 250) as u8, (k % 250) as u8).into()
}
const POLLERS: usize = 6;
const SLOW_HEADERS: usize = 500;
const PORTS_PER_DECLARATION: usize = 100;
/// Fresh port names in the label flood, at most.
const MAX_LABELS: u64 = 100_000;
/// Any one request or acknowledgement awaited.
const WAIT: Duration = Duration::from_secs(5);

/// A small valid interface: one FB with one INT output.
const SMALL_INTERFACE: &str = r#"{"fbs":{"F":{"type":"ABUSE","data_out":{"V":"INT"}}}}"#;

pub struct AbuseParams {
    pub phase: Duration,
    /// Pause between two phases; probes sent then are not counted.
    pub settle: Duration,
    pub max_rss_mb: u64,
    pub quick: bool,
}

impl AbuseParams {
    pub fn full() -> AbuseParams {
        AbuseParams {
            phase: Duration::from_secs(10),
            settle: Duration::from_secs(1),
            max_rss_mb: 256,
            quick: false,
        }
    }

    pub fn quick() -> AbuseParams {
        AbuseParams {
            phase: Duration::from_secs(2),
            settle: Duration::from_millis(500),
            quick: true,
            ..AbuseParams::full()
        }
    }
}

#[derive(Clone, Copy, PartialEq, Eq, Debug)]
enum Phase {
    Idle,
    Registry,
    Redeclare,
    AdminPoll,
    SlowHeaders,
    Labels,
    Retained,
}

impl Phase {
    const ALL: [Phase; 7] = [
        Phase::Idle,
        Phase::Registry,
        Phase::Redeclare,
        Phase::AdminPoll,
        Phase::SlowHeaders,
        Phase::Labels,
        Phase::Retained,
    ];

    fn name(self) -> &'static str {
        match self {
            Phase::Idle => "0 idle",
            Phase::Registry => "1 registry",
            Phase::Redeclare => "2 redeclare",
            Phase::AdminPoll => "3 admin-poll",
            Phase::SlowHeaders => "4 slow-headers",
            Phase::Labels => "5 labels",
            Phase::Retained => "6 retained",
        }
    }

    fn description(self) -> String {
        match self {
            Phase::Idle => "only the probe".into(),
            Phase::Registry => format!(
                "distinct client ids CONNECT, declare {SMALL_INTERFACE} on fbbus/declare/<id> (QoS 1, PUBACK \
                 awaited), DISCONNECT; {REGISTRY_WORKERS} at a time, at most {MAX_DEVICES}, {DEVICES_PER_SOURCE} \
                 from each loopback address 127.0.x.y from 127.0.0.2 on; ops = devices declared"
            ),
            Phase::Redeclare => "one client declares the same device again as soon as the previous declaration \
                 is acknowledged (QoS 1); ops = declarations acknowledged"
                .into(),
            Phase::AdminPoll => format!(
                "{POLLERS} loops GET /api/v1/devices (following `next` pages with ?after=); ops = pages \
                 answered 200"
            ),
            Phase::SlowHeaders => format!(
                "{SLOW_HEADERS} connections to the admin port each send an incomplete request header and wait; \
                 meanwhile one client after the other CONNECTs and DISCONNECTs; ops = MQTT connects that \
                 succeeded / tried"
            ),
            Phase::Labels => format!(
                "one device declares FB L with {PORTS_PER_DECLARATION} INT outputs of fresh names per \
                 declaration, then publishes the string \"x\" on each (QoS 1, ill-typed); ops = ill-typed \
                 publications acknowledged"
            ),
            Phase::Retained => format!(
                "one client publishes retained QoS 0 messages on distinct topics abuse/retained/<n>, at most \
                 {MAX_RETAINED}; ops = publications written"
            ),
        }
    }
}

/// What a flood did.
#[derive(Default)]
struct Flood {
    ops: String,
    note: Option<String>,
}

/// The probe's figures for one phase.
struct ProbeFigures {
    latency_us: Histogram<u64>,
    sent: u64,
    lost: u64,
    reconnects: u64,
}

impl ProbeFigures {
    fn new() -> ProbeFigures {
        ProbeFigures {
            latency_us: Histogram::new_with_bounds(1, 120_000_000, 3).expect("valid bounds"),
            sent: 0,
            lost: 0,
            reconnects: 0,
        }
    }
}

/// The probe's state shared with the phases: the phase its probes count for now
/// (`usize::MAX`: none, settling) and the figures per phase.
struct ProbeShared {
    phase: AtomicUsize,
    figures: Mutex<Vec<ProbeFigures>>,
    stop: AtomicBool,
}

/// Peak resident memory (KiB) and descriptors since the last [`Sampler::take`].
struct Sampler {
    rss_kib: AtomicU64,
    fds: AtomicU64,
    stop: AtomicBool,
}

impl Sampler {
    fn take(&self) -> (u64, u64) {
        (
            self.rss_kib.swap(0, Ordering::Relaxed),
            self.fds.swap(0, Ordering::Relaxed),
        )
    }
}

/// The counters read from `/metrics` at a phase's start and end.
#[derive(Default, Clone, Copy)]
struct Counters {
    limit_refusals: f64,
    connects_refused: f64,
    admin_refused: f64,
    bytes: usize,
}

struct Row {
    phase: Phase,
    flood: std::result::Result<Flood, String>,
    limit_refusals: Option<f64>,
    connects_refused: Option<f64>,
    admin_refused: Option<f64>,
    p50_ms: Option<f64>,
    p99_ms: Option<f64>,
    max_ms: Option<f64>,
    sent: u64,
    lost: u64,
    reconnects: u64,
    peak_rss_kib: u64,
    peak_fds: u64,
    metrics_kb: Option<f64>,
}

pub async fn run(fbbus: &Path, p: &AbuseParams, out: &Path) -> Result<()> {
    let mut t = Transcript::default();
    header(&mut t, fbbus, p);
    let started = Instant::now();
    let mut broker = start_fbbus(fbbus, &[], "")
        .await
        .context("starting fbbus")?;
    let admin = broker.admin.context("fbbus runs with an admin endpoint")?;
    let pid = broker.pid();
    t.line(format!(
        "broker:    pid {pid}, MQTT {}, admin http://{admin}",
        broker.addr
    ));

    let sampler = Arc::new(Sampler {
        rss_kib: AtomicU64::new(0),
        fds: AtomicU64::new(0),
        stop: AtomicBool::new(false),
    });
    let sampling = {
        let sampler = Arc::clone(&sampler);
        std::thread::Builder::new()
            .name("abuse-sampler".into())
            .spawn(move || sample(pid, &sampler))?
    };
    let probe = Arc::new(ProbeShared {
        phase: AtomicUsize::new(usize::MAX),
        figures: Mutex::new(Phase::ALL.iter().map(|_| ProbeFigures::new()).collect()),
        stop: AtomicBool::new(false),
    });
    let probing = spawn_probe(broker.addr, Arc::clone(&probe))?;
    // The re-declaring device is registered before the registry flood fills the address's
    // `max_devices_per_identity`: its flood then meets the declaration rate limit, as a
    // known device's would, not the registry's.
    register_redeclarer(broker.addr).await?;
    // The probe connects and its first round trips settle before the idle phase.
    tokio::time::sleep(p.settle.max(Duration::from_millis(500))).await;

    let mut rows = Vec::new();
    let mut died = None;
    for (i, &phase) in Phase::ALL.iter().enumerate() {
        eprintln!(
            "abuse: phase {} ({} s)...",
            phase.name(),
            p.phase.as_secs_f64()
        );
        let before = counters(admin).await;
        sampler.take();
        probe.phase.store(i, Ordering::Relaxed);
        let deadline = Instant::now() + p.phase;
        // A safety net: a phase that overruns its deadline by far is cut.
        let limit = p.phase + Duration::from_secs(30);
        let flood =
            match tokio::time::timeout(limit, run_phase(phase, broker.addr, admin, deadline)).await
            {
                Ok(Ok(f)) => Ok(f),
                Ok(Err(e)) => Err(format!("{e:#}")),
                Err(_) => Err(format!("no result after {limit:?}")),
            };
        if let Some(wait) = deadline.checked_duration_since(Instant::now()) {
            tokio::time::sleep(wait).await;
        }
        probe.phase.store(usize::MAX, Ordering::Relaxed);
        let (peak_rss_kib, peak_fds) = sampler.take();
        let after = counters(admin).await;
        if let Err(e) = &flood {
            eprintln!("  failed: {e}");
        }
        rows.push(Row {
            phase,
            flood,
            limit_refusals: delta(before, after, |c| c.limit_refusals),
            connects_refused: delta(before, after, |c| c.connects_refused),
            admin_refused: delta(before, after, |c| c.admin_refused),
            p50_ms: None,
            p99_ms: None,
            max_ms: None,
            sent: 0,
            lost: 0,
            reconnects: 0,
            peak_rss_kib,
            peak_fds,
            metrics_kb: after.map(|c| c.bytes as f64 / 1024.0),
        });
        if let Some(exit) = broker.exited() {
            died = Some(exit);
            break;
        }
        tokio::time::sleep(p.settle).await;
    }
    // Probes of the last phase may still be in flight: they are lost after 5 s.
    tokio::time::sleep(PROBE_LOST_AFTER + Duration::from_millis(200)).await;
    probe.stop.store(true, Ordering::Relaxed);
    sampler.stop.store(true, Ordering::Relaxed);
    let _ = tokio::task::spawn_blocking(move || probing.join()).await;
    let _ = tokio::task::spawn_blocking(move || sampling.join()).await;
    {
        let figures = probe.figures.lock().expect("probe figures");
        for (row, f) in rows.iter_mut().zip(figures.iter()) {
            let h = &f.latency_us;
            if !h.is_empty() {
                row.p50_ms = Some(h.value_at_quantile(0.5) as f64 / 1000.0);
                row.p99_ms = Some(h.value_at_quantile(0.99) as f64 / 1000.0);
                row.max_ms = Some(h.max() as f64 / 1000.0);
            }
            row.sent = f.sent;
            row.lost = f.lost;
            row.reconnects = f.reconnects;
        }
    }
    table(&mut t, &rows);
    if let Some(exit) = &died {
        t.line(format!("FAILED: the broker died: {exit}"));
    }
    goals(&mut t, &rows, p);
    t.line(format!(
        "(run took {:.0} s)",
        started.elapsed().as_secs_f64()
    ));
    drop(broker);

    std::fs::create_dir_all(out).with_context(|| format!("creating --out {}", out.display()))?;
    let file = out.join("abuse.txt");
    std::fs::write(&file, &t.0).with_context(|| format!("writing {}", file.display()))?;
    eprintln!("wrote {}", file.display());
    let failed = rows.iter().filter(|r| r.flood.is_err()).count();
    if died.is_some() {
        bail!("the broker died during the run");
    }
    if failed > 0 {
        bail!("{failed} phase(s) failed (see their rows)");
    }
    Ok(())
}

fn header(t: &mut Transcript, fbbus: &Path, p: &AbuseParams) {
    t.machine_lines("abuse");
    t.line(format!(
        "fbbus:     {} ({}; config defaults, [log] level = \"warn\", max_connections 10100, admin on 127.0.0.1)",
        spawn::fbbus_version(fbbus),
        fbbus.display()
    ));
    t.line(format!(
        "params:    {}phases of {:.1} s, {:.1} s settle between phases (probes then not counted); \
         --max-rss-mb {}",
        if p.quick {
            "--quick (smoke-test sizes, not a measurement): "
        } else {
            ""
        },
        p.phase.as_secs_f64(),
        p.settle.as_secs_f64(),
        p.max_rss_mb
    ));
    t.line(format!(
        "probe:     one client (MQTT 3.1.1, raw socket) subscribed at QoS 1 to abuse/probe publishes a QoS 1 \
         message there every {} ms; round trip = publish -> delivery (HDR histogram); lost = not delivered \
         within {} s. RSS (VmRSS) and fds (/proc/<pid>/fd) of the broker sampled every {} ms; refused = \
         the phase's deltas of fbbus_limit_refusals_total (all labels) / fbbus_connects_refused_total / \
         fbbus_admin_connections_refused_total; a phase ends when its flood's last operation after the \
         deadline returns",
        PROBE_EVERY.as_millis(),
        PROBE_LOST_AFTER.as_secs(),
        SAMPLE_EVERY.as_millis()
    ));
    t.line("");
    t.line("phases:");
    for phase in Phase::ALL {
        t.line(format!("  {:<15} {}", phase.name(), phase.description()));
    }
}

async fn run_phase(
    phase: Phase,
    addr: SocketAddr,
    admin: SocketAddr,
    deadline: Instant,
) -> Result<Flood> {
    match phase {
        Phase::Idle => Ok(Flood {
            ops: "-".into(),
            note: None,
        }),
        Phase::Registry => registry_flood(addr, deadline).await,
        Phase::Redeclare => redeclaration_flood(addr, deadline).await,
        Phase::AdminPoll => admin_polling(admin, deadline).await,
        Phase::SlowHeaders => slow_headers(addr, admin, deadline).await,
        Phase::Labels => label_flood(addr, deadline).await,
        Phase::Retained => retained_flood(addr, deadline).await,
    }
}

// ---------------------------------------------------------------------------------------
// The floods
// ---------------------------------------------------------------------------------------

/// 1: distinct devices CONNECT, declare, DISCONNECT.
async fn registry_flood(addr: SocketAddr, deadline: Instant) -> Result<Flood> {
    let next = Arc::new(AtomicU64::new(0));
    let done = Arc::new(AtomicU64::new(0));
    let refused = Arc::new(AtomicU64::new(0));
    let mut workers = Vec::new();
    for _ in 0..REGISTRY_WORKERS {
        let (next, done, refused) = (Arc::clone(&next), Arc::clone(&done), Arc::clone(&refused));
        workers.push(tokio::spawn(async move {
            while Instant::now() < deadline {
                let n = next.fetch_add(1, Ordering::Relaxed);
                if n >= MAX_DEVICES {
                    break;
                }
                let id = format!("abuse-dev-{n:05}");
                let from = registry_source(n);
                let s = match tokio::time::timeout(WAIT, mqtt::connect_from(addr, from, &id)).await
                {
                    Ok(Ok(s)) => s,
                    _ => {
                        refused.fetch_add(1, Ordering::Relaxed);
                        continue;
                    }
                };
                let mut reader = PacketReader::new(s);
                if declare(&mut reader, &id, SMALL_INTERFACE, 1).await.is_ok() {
                    done.fetch_add(1, Ordering::Relaxed);
                }
                let _ = reader.get_mut().write_all(&mqtt::DISCONNECT).await;
            }
        }));
    }
    for w in workers {
        w.await?;
    }
    let (done, refused) = (
        done.load(Ordering::Relaxed),
        refused.load(Ordering::Relaxed),
    );
    Ok(Flood {
        ops: done.to_string(),
        note: (refused > 0).then(|| format!("{refused} connects failed")),
    })
}

/// The device of phase 2.
const REDECLARER: &str = "abuse-redeclare";

/// Declares [`REDECLARER`] once, so it is a known device.
async fn register_redeclarer(addr: SocketAddr) -> Result<()> {
    let s = tokio::time::timeout(WAIT, mqtt::connect(addr, REDECLARER, None))
        .await
        .context("CONNECT timed out")??;
    let mut reader = PacketReader::new(s);
    declare(&mut reader, REDECLARER, SMALL_INTERFACE, 1)
        .await
        .context("the re-declaring device's first declaration")?;
    let _ = reader.get_mut().write_all(&mqtt::DISCONNECT).await;
    Ok(())
}

/// 2: one device declares again as soon as its previous declaration is acknowledged.
async fn redeclaration_flood(addr: SocketAddr, deadline: Instant) -> Result<Flood> {
    let id = REDECLARER;
    let s = tokio::time::timeout(WAIT, mqtt::connect(addr, id, None))
        .await
        .context("CONNECT timed out")??;
    let mut reader = PacketReader::new(s);
    let mut done = 0u64;
    let mut pid = 0u16;
    while Instant::now() < deadline {
        pid = pid % u16::MAX + 1;
        declare(&mut reader, id, SMALL_INTERFACE, pid)
            .await
            .with_context(|| format!("declaration {} not acknowledged", done + 1))?;
        done += 1;
    }
    let _ = reader.get_mut().write_all(&mqtt::DISCONNECT).await;
    Ok(Flood {
        ops: done.to_string(),
        note: None,
    })
}

/// 3: admin loops listing every device, page after page.
async fn admin_polling(admin: SocketAddr, deadline: Instant) -> Result<Flood> {
    let mut loops = Vec::new();
    for _ in 0..POLLERS {
        loops.push(tokio::spawn(async move {
            let (mut pages, mut failed, mut bytes) = (0u64, 0u64, 0usize);
            let mut after: Option<String> = None;
            while Instant::now() < deadline {
                let path = match &after {
                    Some(a) => format!("/api/v1/devices?after={}", percent_encode(a)),
                    None => "/api/v1/devices".to_string(),
                };
                match scrape::get(&format!("http://{admin}{path}"), Duration::from_secs(10)).await {
                    Ok(body) => {
                        pages += 1;
                        bytes = bytes.max(body.len());
                        after = next_page(&body);
                    }
                    Err(_) => {
                        failed += 1;
                        after = None;
                        tokio::time::sleep(Duration::from_millis(10)).await;
                    }
                }
            }
            (pages, failed, bytes)
        }));
    }
    let (mut pages, mut failed, mut largest) = (0, 0, 0);
    for l in loops {
        let (p, f, b) = l.await?;
        pages += p;
        failed += f;
        largest = largest.max(b);
    }
    let mut note = format!("largest page {:.0} KB", largest as f64 / 1024.0);
    if failed > 0 {
        note.push_str(&format!(", {failed} requests failed"));
    }
    Ok(Flood {
        ops: pages.to_string(),
        note: Some(note),
    })
}

/// 4: incomplete request headers held on the admin port while MQTT clients connect.
async fn slow_headers(addr: SocketAddr, admin: SocketAddr, deadline: Instant) -> Result<Flood> {
    let mut opening = Vec::new();
    for _ in 0..SLOW_HEADERS {
        opening.push(tokio::spawn(async move {
            let mut s = tokio::time::timeout(WAIT, TcpStream::connect(admin))
                .await
                .ok()?
                .ok()?;
            s.write_all(b"GET /api/v1/devices HTTP/1.1\r\nHost: 127.0.0.1\r\nX-Slow: ")
                .await
                .ok()?;
            Some(s)
        }));
    }
    let mut held = Vec::new();
    for o in opening {
        if let Some(s) = o.await? {
            held.push(s);
        }
    }
    let opened = held.len();
    let (mut ok, mut tried, mut n) = (0u64, 0u64, 0u64);
    while Instant::now() < deadline {
        tried += 1;
        n += 1;
        let id = format!("abuse-conn-{n}");
        if let Ok(Ok(mut s)) = tokio::time::timeout(WAIT, mqtt::connect(addr, &id, None)).await {
            ok += 1;
            let _ = s.write_all(&mqtt::DISCONNECT).await;
        }
        tokio::time::sleep(Duration::from_millis(5)).await;
    }
    // Which the broker closed (or answered) while they were held.
    let mut closed = 0;
    let mut buf = [0u8; 256];
    for s in &held {
        match s.try_read(&mut buf) {
            Err(e) if e.kind() == std::io::ErrorKind::WouldBlock => {}
            _ => closed += 1,
        }
    }
    drop(held);
    Ok(Flood {
        ops: format!("{ok}/{tried}"),
        note: Some(format!(
            "{opened}/{SLOW_HEADERS} admin connections opened, {closed} closed or answered by the broker by the end"
        )),
    })
}

/// 5: fresh port names, one ill-typed value on each.
async fn label_flood(addr: SocketAddr, deadline: Instant) -> Result<Flood> {
    let id = "abuse-labels";
    let s = tokio::time::timeout(WAIT, mqtt::connect(addr, id, None))
        .await
        .context("CONNECT timed out")??;
    let mut reader = PacketReader::new(s);
    let (mut published, mut declarations, mut generation) = (0u64, 0u64, 0u64);
    while Instant::now() < deadline && published < MAX_LABELS {
        let ports: Vec<String> = (0..PORTS_PER_DECLARATION)
            .map(|i| format!("P{generation}_{i}"))
            .collect();
        generation += 1;
        let data_out: Vec<String> = ports.iter().map(|p| format!("\"{p}\":\"INT\"")).collect();
        let interface = format!(
            r#"{{"fbs":{{"L":{{"type":"ABUSE","data_out":{{{}}}}}}}}}"#,
            data_out.join(",")
        );
        declare(&mut reader, id, &interface, 1)
            .await
            .context("declaration not acknowledged")?;
        declarations += 1;
        let mut batch = Vec::new();
        for (i, port) in ports.iter().enumerate() {
            batch.extend(mqtt::publish_qos1_packet(
                &format!("fb/{id}/L/{port}"),
                i as u16 + 2,
                false,
                b"\"x\"",
            ));
        }
        reader.get_mut().write_all(&batch).await?;
        await_pubacks(&mut reader, ports.len())
            .await
            .context("ill-typed publications not acknowledged")?;
        published += ports.len() as u64;
    }
    let _ = reader.get_mut().write_all(&mqtt::DISCONNECT).await;
    Ok(Flood {
        ops: published.to_string(),
        note: Some(format!("{declarations} declarations")),
    })
}

/// 6: retained messages on distinct topics.
async fn retained_flood(addr: SocketAddr, deadline: Instant) -> Result<Flood> {
    let mut s = tokio::time::timeout(WAIT, mqtt::connect(addr, "abuse-retained", None))
        .await
        .context("CONNECT timed out")??;
    let mut sent = 0u64;
    while Instant::now() < deadline && sent < MAX_RETAINED {
        let mut batch = Vec::new();
        for _ in 0..100.min(MAX_RETAINED - sent) {
            batch.extend(loadtest::wire::publish(
                loadtest::wire::V311,
                format!("abuse/retained/{sent}").as_bytes(),
                0,
                true,
                false,
                0,
                &loadtest::wire::Props::new(),
                b"retained value 16",
            ));
            sent += 1;
        }
        tokio::time::timeout(WAIT, s.write_all(&batch))
            .await
            .context("the broker stopped reading")??;
    }
    let _ = s.write_all(&mqtt::DISCONNECT).await;
    Ok(Flood {
        ops: sent.to_string(),
        note: None,
    })
}

/// Publishes `interface` on `fbbus/declare/<id>` at QoS 1 and waits for its PUBACK.
async fn declare(reader: &mut PacketReader, id: &str, interface: &str, pid: u16) -> Result<()> {
    let packet = mqtt::publish_qos1_packet(
        &format!("fbbus/declare/{id}"),
        pid,
        false,
        interface.as_bytes(),
    );
    reader.get_mut().write_all(&packet).await?;
    await_pubacks(reader, 1).await
}

/// Reads until `n` PUBACKs arrived (within [`WAIT`]); anything else is ignored.
async fn await_pubacks(reader: &mut PacketReader, n: usize) -> Result<()> {
    let until = Instant::now() + WAIT;
    let mut acks = 0;
    while acks < n {
        let left = until
            .checked_duration_since(Instant::now())
            .context("no PUBACK in time")?;
        match tokio::time::timeout(left, reader.read_more()).await {
            Err(_) => bail!("{acks} of {n} PUBACKs within {WAIT:?}"),
            Ok(Ok(0)) => bail!("the broker closed the connection"),
            Ok(Err(e)) => return Err(e.into()),
            Ok(Ok(_)) => {
                while let Some((header, _)) = reader.next_packet()? {
                    if header >> 4 == 4 {
                        acks += 1;
                    }
                }
            }
        }
    }
    Ok(())
}

/// `next` of a device listing (`{"devices": [...], "line": ..., "next": ...}`): the
/// `after` of the next page, absent or null on the last. Only the answer's last key is
/// parsed, not the whole page: parsing megabytes of records in six loops would take the
/// harness's CPU, not the broker's.
fn next_page(body: &str) -> Option<String> {
    let at = body.rfind("\"next\"")?;
    let rest = body[at + "\"next\"".len()..]
        .trim_start()
        .strip_prefix(':')?;
    let mut values = serde_json::Deserializer::from_str(rest).into_iter::<serde_json::Value>();
    let value = values.next()?.ok()?;
    // The top-level key: nothing but the object's end after its value.
    if rest[values.byte_offset()..].trim() != "}" {
        return None;
    }
    match value {
        serde_json::Value::String(s) if !s.is_empty() => Some(s),
        serde_json::Value::Number(n) => Some(n.to_string()),
        _ => None,
    }
}

fn percent_encode(s: &str) -> String {
    s.bytes()
        .map(|b| match b {
            b'A'..=b'Z' | b'a'..=b'z' | b'0'..=b'9' | b'-' | b'_' | b'.' | b'~' => {
                (b as char).to_string()
            }
            _ => format!("%{b:02X}"),
        })
        .collect()
}

// ---------------------------------------------------------------------------------------
// The probe, the sampler, the counters
// ---------------------------------------------------------------------------------------

const PROBE_TOPIC: &str = "abuse/probe";

async fn probe_connect(addr: SocketAddr) -> Result<TcpStream> {
    let connect = async {
        let mut s = mqtt::connect(addr, "abuse-probe", None).await?;
        mqtt::subscribe_qos(&mut s, PROBE_TOPIC, 1).await?;
        anyhow::Ok(s)
    };
    tokio::time::timeout(Duration::from_secs(2), connect)
        .await
        .context("probe connect timed out")?
}

/// The probe on a thread and runtime of its own, so that the floods' clients in this
/// process (megabytes of admin answers, thousands of connects) do not delay its timer or
/// its reads: the round trip it measures is the broker's.
fn spawn_probe(addr: SocketAddr, shared: Arc<ProbeShared>) -> Result<std::thread::JoinHandle<()>> {
    let runtime = tokio::runtime::Builder::new_current_thread()
        .enable_all()
        .build()
        .context("the probe's runtime")?;
    Ok(std::thread::Builder::new()
        .name("abuse-probe".into())
        .spawn(move || runtime.block_on(run_probe(addr, shared)))?)
}

/// The well-behaved device: a QoS 1 publication every [`PROBE_EVERY`] on its own topic,
/// each timed until it comes back; reconnects (counted) if its connection drops.
async fn run_probe(addr: SocketAddr, shared: Arc<ProbeShared>) {
    let mut stream: Option<TcpStream> = None;
    let mut buf = vec![0u8; 64 * 1024];
    let mut pending: Vec<u8> = Vec::new();
    // seq -> (sent at, the phase it counts for)
    let mut outstanding: HashMap<u64, (Instant, usize)> = HashMap::new();
    let mut tick = tokio::time::interval(PROBE_EVERY);
    tick.set_missed_tick_behavior(tokio::time::MissedTickBehavior::Skip);
    let mut seq = 0u64;
    let mut connected_once = false;
    while !shared.stop.load(Ordering::Relaxed) {
        tokio::select! {
            r = read_some(&mut stream, &mut buf) => match r {
                Ok(0) | Err(_) => stream = None,
                Ok(n) => {
                    pending.extend_from_slice(&buf[..n]);
                    let now = Instant::now();
                    let mut acks = Vec::new();
                    while let Some(Ok(total)) = loadtest::wire::frame_len(&pending) {
                        let header = pending[0];
                        let body = &pending[loadtest::wire::header_len(&pending)..total];
                        if let Some(payload) = mqtt::publish_payload(header, body) {
                            if let Some(id) = mqtt::packet_id(header, body) {
                                acks.extend(mqtt::puback_packet(id));
                            }
                            if let Ok(b) = <[u8; 8]>::try_from(payload) {
                                if let Some((sent, phase)) = outstanding.remove(&u64::from_be_bytes(b)) {
                                    if phase != usize::MAX {
                                        let us = now.duration_since(sent).as_micros() as u64;
                                        let mut f = shared.figures.lock().expect("probe figures");
                                        let _ = f[phase].latency_us.record(us.max(1));
                                    }
                                }
                            }
                        }
                        pending.drain(..total);
                    }
                    if !acks.is_empty() {
                        if let Some(s) = stream.as_mut() {
                            if s.write_all(&acks).await.is_err() {
                                stream = None;
                            }
                        }
                    }
                }
            },
            _ = tick.tick() => {
                let now = Instant::now();
                let phase = shared.phase.load(Ordering::Relaxed);
                // Overdue probes are lost.
                let overdue: Vec<u64> = outstanding
                    .iter()
                    .filter(|(_, (sent, _))| now.duration_since(*sent) > PROBE_LOST_AFTER)
                    .map(|(k, _)| *k)
                    .collect();
                for k in overdue {
                    if let Some((_, p)) = outstanding.remove(&k) {
                        if p != usize::MAX {
                            shared.figures.lock().expect("probe figures")[p].lost += 1;
                        }
                    }
                }
                if stream.is_none() {
                    pending.clear();
                    match probe_connect(addr).await {
                        Ok(s) => {
                            if connected_once && phase != usize::MAX {
                                shared.figures.lock().expect("probe figures")[phase].reconnects += 1;
                            }
                            connected_once = true;
                            stream = Some(s);
                        }
                        Err(_) => {
                            if phase != usize::MAX {
                                let mut f = shared.figures.lock().expect("probe figures");
                                f[phase].sent += 1;
                                f[phase].lost += 1;
                            }
                            continue;
                        }
                    }
                }
                seq += 1;
                let packet = mqtt::publish_qos1_packet(
                    PROBE_TOPIC,
                    (seq % u64::from(u16::MAX)) as u16 + 1,
                    false,
                    &seq.to_be_bytes(),
                );
                if phase != usize::MAX {
                    shared.figures.lock().expect("probe figures")[phase].sent += 1;
                }
                outstanding.insert(seq, (Instant::now(), phase));
                if let Some(s) = stream.as_mut() {
                    if s.write_all(&packet).await.is_err() {
                        stream = None;
                    }
                }
            }
        }
    }
    // Whatever is still outstanding at the end is lost.
    let mut f = shared.figures.lock().expect("probe figures");
    for (_, (_, p)) in outstanding {
        if p != usize::MAX {
            f[p].lost += 1;
        }
    }
}

/// One read from the probe's connection; never ready while it has none.
async fn read_some(stream: &mut Option<TcpStream>, buf: &mut [u8]) -> std::io::Result<usize> {
    use tokio::io::AsyncReadExt;
    match stream.as_mut() {
        Some(s) => s.read(buf).await,
        None => std::future::pending().await,
    }
}

/// Peak VmRSS and open descriptors of `pid`, every [`SAMPLE_EVERY`] (on a thread of its
/// own, until told to stop).
fn sample(pid: u32, s: &Sampler) {
    while !s.stop.load(Ordering::Relaxed) {
        if let Some(kib) = broker_process::rss_kib(pid) {
            s.rss_kib.fetch_max(kib, Ordering::Relaxed);
        }
        if let Some(fds) = broker_process::open_fds(pid) {
            s.fds.fetch_max(fds, Ordering::Relaxed);
        }
        std::thread::sleep(SAMPLE_EVERY);
    }
}

/// The refusal counters and the size of `/metrics`; None when the endpoint did not
/// answer within 8 s (the slow-header phase may hold every admin slot until the
/// broker's header timeout).
async fn counters(admin: SocketAddr) -> Option<Counters> {
    let until = Instant::now() + Duration::from_secs(8);
    loop {
        if let Ok(text) =
            scrape::get(&format!("http://{admin}/metrics"), Duration::from_secs(5)).await
        {
            return Some(Counters {
                limit_refusals: sum_series(&text, "fbbus_limit_refusals_total"),
                connects_refused: sum_series(&text, "fbbus_connects_refused_total"),
                admin_refused: sum_series(&text, "fbbus_admin_connections_refused_total"),
                bytes: text.len(),
            });
        }
        if Instant::now() > until {
            return None;
        }
        tokio::time::sleep(Duration::from_millis(200)).await;
    }
}

/// The sum of every series of metric `name`, over its labels.
fn sum_series(text: &str, name: &str) -> f64 {
    text.lines()
        .filter(|l| !l.starts_with('#'))
        .filter_map(|l| {
            let rest = l.strip_prefix(name)?;
            if !(rest.starts_with('{') || rest.starts_with(' ')) {
                return None;
            }
            l.rsplit_once(' ')?.1.trim().parse::<f64>().ok()
        })
        .sum()
}

fn delta(
    before: Option<Counters>,
    after: Option<Counters>,
    f: impl Fn(&Counters) -> f64,
) -> Option<f64> {
    Some(f(&after?) - f(&before?))
}

// ---------------------------------------------------------------------------------------
// The report
// ---------------------------------------------------------------------------------------

fn idle_p99(rows: &[Row]) -> Option<f64> {
    rows.iter()
        .find(|r| r.phase == Phase::Idle)
        .and_then(|r| r.p99_ms)
        .filter(|v| *v > 0.0)
}

fn table(t: &mut Transcript, rows: &[Row]) {
    let headers = [
        "phase",
        "ops",
        "refused (limits/connects/admin)",
        "p50 ms",
        "p99 ms",
        "max ms",
        "p99/idle",
        "lost",
        "peak RSS MB",
        "peak fds",
        "/metrics KB",
    ];
    let idle = idle_p99(rows);
    let num =
        |v: Option<f64>, digits: usize| v.map_or("-".to_string(), |v| format!("{v:.digits$}"));
    let cells: Vec<Vec<String>> = rows
        .iter()
        .map(|r| {
            vec![
                r.phase.name().to_string(),
                match &r.flood {
                    Ok(f) => f.ops.clone(),
                    Err(_) => "FAILED".into(),
                },
                format!(
                    "{}/{}/{}",
                    num(r.limit_refusals, 0),
                    num(r.connects_refused, 0),
                    num(r.admin_refused, 0)
                ),
                num(r.p50_ms, 2),
                num(r.p99_ms, 2),
                num(r.max_ms, 2),
                match (r.p99_ms, idle) {
                    (Some(p), Some(i)) => format!("{:.2}x", p / i),
                    _ => "-".into(),
                },
                format!("{}/{}", r.lost, r.sent),
                format!("{:.1}", r.peak_rss_kib as f64 / 1024.0),
                r.peak_fds.to_string(),
                num(r.metrics_kb, 1),
            ]
        })
        .collect();
    let widths = column_widths(headers.iter().map(|h| h.chars().count()), &cells);
    t.line("");
    t.line("== phases ==");
    let header: Vec<String> = headers.iter().map(|h| h.to_string()).collect();
    t.line(format!("   {}", aligned(&header, &widths)));
    for c in &cells {
        t.line(format!("   {}", aligned(c, &widths)));
    }
    let mut notes = Vec::new();
    for r in rows {
        let mut parts = Vec::new();
        match &r.flood {
            Ok(f) => parts.extend(f.note.clone()),
            Err(e) => parts.push(format!("FAILED: {e}")),
        }
        if r.reconnects > 0 {
            parts.push(format!("probe reconnected {} time(s)", r.reconnects));
        }
        if !parts.is_empty() {
            notes.push(format!("   {}: {}", r.phase.name(), parts.join("; ")));
        }
    }
    if !notes.is_empty() {
        t.line("   notes:");
        for n in notes {
            t.line(n);
        }
    }
}

fn goals(t: &mut Transcript, rows: &[Row], p: &AbuseParams) {
    t.line("");
    t.line("== goals (issue 21) ==");
    let idle = idle_p99(rows);
    for (phase, what) in [
        (Phase::AdminPoll, "during admin polling"),
        (Phase::Redeclare, "during re-declaration"),
    ] {
        let p99 = rows
            .iter()
            .find(|r| r.phase == phase)
            .and_then(|r| r.p99_ms);
        let line = match (p99, idle) {
            (Some(v), Some(i)) => {
                let ratio = v / i;
                format!(
                    "probe p99 within 2x idle {what}: {ratio:.2}x ({v:.2} ms vs {i:.2} ms) {}",
                    if ratio <= 2.0 { "MET" } else { "NOT MET" }
                )
            }
            _ => format!("probe p99 within 2x idle {what}: no figure NOT MET"),
        };
        t.line(line);
    }
    let peak = rows.iter().map(|r| r.peak_rss_kib).max().unwrap_or(0);
    let peak_mb = peak as f64 / 1024.0;
    t.line(format!(
        "resident memory within --max-rss-mb {} MB (the configured limit compared against): peak {:.1} MB {}",
        p.max_rss_mb,
        peak_mb,
        if peak > 0 && peak_mb <= p.max_rss_mb as f64 {
            "MET"
        } else {
            "NOT MET"
        }
    ));
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn sums_series_over_labels_and_reads_next() {
        let text = "# HELP fbbus_limit_refusals_total x\n\
                    fbbus_limit_refusals_total{limit=\"a\"} 3\n\
                    fbbus_limit_refusals_total{limit=\"b\"} 4\n\
                    fbbus_limit_refusals_totalx 100\n\
                    fbbus_connects_refused_total 2\n";
        assert_eq!(sum_series(text, "fbbus_limit_refusals_total"), 7.0);
        assert_eq!(sum_series(text, "fbbus_connects_refused_total"), 2.0);
        assert_eq!(sum_series(text, "fbbus_absent"), 0.0);
        assert_eq!(
            next_page(r#"{"devices":[],"next":"dev-9"}"#),
            Some("dev-9".into())
        );
        assert_eq!(next_page(r#"{"devices":[],"next":null}"#), None);
        assert_eq!(next_page(r#"{"devices":[]}"#), None);
        assert_eq!(
            next_page(r#"{"devices":[{"fbs":{"F":{"data_out":{"next":"INT"}}}}],"line":"l"}"#),
            None,
            "a port named next is not the page's"
        );
        assert_eq!(
            next_page(r#"{"devices":[],"line":"l","next":"a/b" }"#),
            Some("a/b".into())
        );
        assert_eq!(percent_encode("a b/é"), "a%20b%2F%C3%A9");
    }
}

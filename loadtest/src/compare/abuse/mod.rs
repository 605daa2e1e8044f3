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

mod floods;
mod probe;
mod summary;

use std::net::SocketAddr;
use std::path::Path;
use std::sync::atomic::{AtomicBool, AtomicU64, AtomicUsize, Ordering};
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

use anyhow::{bail, Context as _, Result};
use hdrhistogram::Histogram;

use loadtest::broker_process::spawn;

use super::{start_fbbus, Transcript};

use self::floods::{
    admin_polling, label_flood, redeclaration_flood, register_redeclarer, registry_flood,
    retained_flood, slow_headers, DEVICES_PER_SOURCE, MAX_DEVICES, MAX_RETAINED, POLLERS,
    PORTS_PER_DECLARATION, REGISTRY_WORKERS, SLOW_HEADERS, SMALL_INTERFACE,
};
use self::probe::spawn_probe;
use self::summary::{counters, delta, goals, sample, table};

/// Probe interval and how long a probe may take before it counts as lost.
const PROBE_EVERY: Duration = Duration::from_millis(10);

const PROBE_LOST_AFTER: Duration = Duration::from_secs(5);

/// Resident memory and descriptors are sampled this often.
const SAMPLE_EVERY: Duration = Duration::from_millis(100);

/// Any one request or acknowledgement awaited.
const WAIT: Duration = Duration::from_secs(5);

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

#[cfg(test)]
mod tests {
    use super::floods::{next_page, percent_encode};
    use super::summary::sum_series;

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

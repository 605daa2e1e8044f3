//! `fbbus-loadtest compare plant`: a plant on one machine (issue 32). N fbbus lines on
//! one zenoh bus, M devices on each, in one of two topologies:
//!
//! - **routers**: lines 1 and 2 are zenoh routers (`mode = "router"`), line 2 linked to
//!   line 1; lines 3..N are zenoh clients of both (a client uses one router at a time and
//!   moves to the other when it goes), as a plant with two redundant routers runs;
//! - **redundant**: the same, but each client line holds a zenoh session on each router
//!   line at once (`[bridge] session_per_router`), every message arriving once per router
//!   and its copy dropped by the stamp;
//! - **peers**: every line a zenoh peer listening on its own endpoint and connecting to
//!   lines 1 and 2 (zenoh's gossip makes the mesh).
//!
//! Each device is a raw MQTT 3.1.1 client that connects with its id, declares one LINT
//! output (`fb/<id>/FB/OUT`) and stays connected, as the issue's own attempt did. Measured,
//! every loop bounded by a count and a deadline:
//!
//! 1. **convergence**: from the last device's declaration until every line's registry
//!    lists all N x M devices online (`fbbus_registry_devices{status="online"}`);
//! 2. **local delivery while the bus federates**: a device of line 3 publishes every
//!    `probe_period` to a subscriber on line 3 from before the devices connect until
//!    convergence, then as long again on the quiet plant: p50/p99 of each phase (the
//!    goal: during within 2x idle);
//! 3. **traffic matrix**, each pattern for `traffic` seconds, a message every `period` per
//!    publisher, its LINT value the send time (µs): *neighbour* (line i -> line i+1),
//!    *all-to-one* (every other line -> line N), *one-to-all* (line 3 -> every other
//!    line); per pattern sent, delivered, lost, duplicated, latency p50/p99/max, and the CPU
//!    each line's process spent meanwhile;
//! 4. **a router dies**: line 1 is SIGKILLed; the time until every other line lists the
//!    (N-1) x M devices of the living lines online again, and the lowest count seen
//!    meanwhile.
//!
//! Everything on 127.0.0.1, plain `tcp/` bus (no TLS: the hop's cost over mutual TLS is
//! `compare bridge --bus tcp,mtls`).

use std::collections::HashMap;
use std::net::SocketAddr;
use std::path::{Path, PathBuf};
use std::sync::Arc;
use std::time::{Duration, Instant};

use anyhow::{bail, Context as _, Result};
use hdrhistogram::Histogram;
use tokio::io::AsyncWriteExt;
use tokio::net::TcpStream;
use tokio::sync::Mutex;

use super::{metric, start_fbbus, Transcript};
use loadtest::broker_process::spawn::{self, Running};
use loadtest::raw_client::{self as mqtt, PacketReader};

pub struct PlantParams {
    pub lines: usize,
    pub devices: usize,
    pub topologies: Vec<Topology>,
    pub traffic: Duration,
    pub period: Duration,
    /// How often the local probe of line 3 publishes: often enough for a p99 of a storm
    /// that lasts seconds (at the traffic's 20 ms, 65-260 samples: the p99 was the max).
    pub probe_period: Duration,
    /// How long convergence may take before the run says it did not converge.
    pub converge_within: Duration,
    /// The zenohd binary for topology `zenohd`.
    pub zenohd: Option<PathBuf>,
    /// Line 3 on a core of its own, everything else on the others ([`isolate`]).
    pub isolate: bool,
}

impl PlantParams {
    pub fn full() -> PlantParams {
        PlantParams {
            lines: 8,
            devices: 1000,
            topologies: vec![Topology::Alone, Topology::Routers, Topology::Peers],
            traffic: Duration::from_secs(6),
            period: Duration::from_millis(20),
            probe_period: Duration::from_millis(2),
            converge_within: Duration::from_secs(120),
            zenohd: None,
            isolate: false,
        }
    }

    pub fn quick() -> PlantParams {
        PlantParams {
            lines: 5,
            devices: 20,
            traffic: Duration::from_secs(2),
            converge_within: Duration::from_secs(30),
            ..PlantParams::full()
        }
    }
}

#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Topology {
    /// The control: the same lines and device storm without a bus, so that what the
    /// storm itself costs local delivery on a shared machine is not laid at the bus's
    /// door.
    Alone,
    Routers,
    /// As `Routers`, each client line with a session on each router line.
    Redundant,
    Peers,
    /// Every line a zenoh client of two real `zenohd` routers with a session on each
    /// (`session_per_router`), router 2 linked to router 1: the plant of deploy/plant/
    /// (without TLS). Router 1 is what dies. (Before 2026-11-29: one session per line.)
    Zenohd,
}

impl Topology {
    pub const ALL: [Topology; 5] = [
        Topology::Alone,
        Topology::Routers,
        Topology::Redundant,
        Topology::Peers,
        Topology::Zenohd,
    ];

    pub fn name(self) -> &'static str {
        match self {
            Topology::Alone => "alone",
            Topology::Routers => "routers",
            Topology::Redundant => "redundant",
            Topology::Peers => "peers",
            Topology::Zenohd => "zenohd",
        }
    }

    /// `names` (empty: every topology, `zenohd` only `with_zenohd`).
    pub fn parse_list(names: &[String], with_zenohd: bool) -> Result<Vec<Topology>> {
        let mut out = Vec::new();
        for name in names {
            let t = Topology::ALL
                .into_iter()
                .find(|t| t.name() == name.trim())
                .with_context(|| {
                    format!("unknown topology `{name}` (known: alone, routers, redundant, peers, zenohd)")
                })?;
            if !out.contains(&t) {
                out.push(t);
            }
        }
        if out.is_empty() {
            out = Topology::ALL
                .into_iter()
                .filter(|t| with_zenohd || *t != Topology::Zenohd)
                .collect();
        }
        if out.contains(&Topology::Zenohd) && !with_zenohd {
            bail!(
                "topology zenohd needs zenohd 1.10 (--zenohd PATH; `cargo install zenohd \
                 --version 1.10.2 --locked --root target/zenohd`)"
            );
        }
        Ok(out)
    }

    /// Line `n`'s (1-based) `[bridge]` section, `endpoints[i]` being line i+1's.
    fn bridge(self, n: usize, endpoints: &[String]) -> String {
        let (first, second) = (&endpoints[0], &endpoints[1]);
        let (mode, listen, connect): (&str, Vec<&String>, Vec<&String>) = match (self, n) {
            (Topology::Alone, _) => return String::new(),
            (Topology::Routers | Topology::Redundant, 1) => ("router", vec![first], vec![]),
            (Topology::Routers | Topology::Redundant, 2) => ("router", vec![second], vec![first]),
            (Topology::Routers, _) => ("client", vec![], vec![first, second]),
            // Zenohd: the two endpoints are the zenohd routers'.
            (Topology::Redundant | Topology::Zenohd, _) => {
                return format!(
                    "\n[bridge]\nmode = \"client\"\nsession_per_router = true\nconnect = \
                     {:?}\n",
                    [first, second]
                )
            }
            (Topology::Peers, 1) => ("peer", vec![first], vec![]),
            (Topology::Peers, 2) => ("peer", vec![second], vec![first]),
            (Topology::Peers, n) => ("peer", vec![&endpoints[n - 1]], vec![first, second]),
        };
        format!("\n[bridge]\nmode = \"{mode}\"\nlisten = {listen:?}\nconnect = {connect:?}\n")
    }
}

const INTERFACE: &str = r#"{"fbs": {"FB": {"type": "PLANT_DEVICE", "data_out": {"OUT": "LINT"}}}}"#;

fn device_id(line: usize, device: usize) -> String {
    format!("l{line}-d{device:04}")
}

fn topic(line: usize, device: usize) -> String {
    format!("fb/{}/FB/OUT", device_id(line, device))
}

/// Microseconds since `epoch`, the value every measured message carries.
fn micros(epoch: Instant) -> i64 {
    epoch.elapsed().as_micros() as i64
}

pub async fn run(fbbus: &Path, p: &PlantParams, out: &Path) -> Result<()> {
    if p.lines < 3 {
        bail!("a plant needs at least 3 lines (two routers and a client)");
    }
    let mut t = Transcript::default();
    t.machine_lines("plant");
    t.line(format!(
        "plant:     {} lines x {} devices (raw MQTT 3.1.1 clients, one LINT output each), \
         topologies {}; traffic {} s per pattern, one message per {} ms per publisher",
        p.lines,
        p.devices,
        p.topologies
            .iter()
            .map(|t| t.name())
            .collect::<Vec<_>>()
            .join(", "),
        p.traffic.as_secs(),
        p.period.as_millis()
    ));
    t.line(format!("fbbus:     {}", fbbus.display()));
    if p.isolate {
        t.line(
            "isolated:  line 3 and its probe's clients on the last core alone, every other \
             process on the others (--isolate: a line on a host of its own)",
        );
    }
    let mut failed = 0;
    // The control's figures, once `alone` ran.
    let mut alone = None;
    for &topology in &p.topologies {
        t.line(String::new());
        t.line(format!("== topology {} ==", topology.name()));
        match plant(fbbus, topology, p, alone.as_ref(), &mut t).await {
            Ok(control) if topology == Topology::Alone => alone = Some(control),
            Ok(_) => {}
            Err(e) => {
                failed += 1;
                t.line(format!("FAILED: {e:#}"));
            }
        }
    }
    std::fs::create_dir_all(out).with_context(|| format!("creating --out {}", out.display()))?;
    let file = out.join("plant.txt");
    std::fs::write(&file, &t.0).with_context(|| format!("writing {}", file.display()))?;
    eprintln!("wrote {}", file.display());
    if failed > 0 {
        bail!("{failed} topologies failed (see plant.txt)");
    }
    Ok(())
}

/// How much more each line used than the same line in topology `alone`, and the mean.
fn beyond(bus: &[u64], alone: &[u64]) -> (Vec<f64>, f64) {
    let more: Vec<f64> = bus
        .iter()
        .zip(alone)
        .map(|(bus, own)| *bus as f64 - *own as f64)
        .collect();
    let mean = more.iter().sum::<f64>() / more.len().max(1) as f64;
    (more, mean)
}

/// What topology `alone` measured, for the others to be set against.
struct Control {
    /// Line 3's local p99 during the storm.
    p99: u64,
    /// Each line's resident memory on the quiet plant (KiB).
    rss_kib: Vec<u64>,
    /// Each line's CPU from the first connection to convergence (ms).
    storm_cpu_ms: Vec<u64>,
}

/// One topology, from its lines' start to the router's death (`alone`: to the quiet
/// plant). Returns its figures; `alone` is the control's.
async fn plant(
    fbbus: &Path,
    topology: Topology,
    p: &PlantParams,
    alone: Option<&Control>,
    t: &mut Transcript,
) -> Result<Control> {
    let endpoints: Vec<String> = (0..p.lines)
        .map(|_| spawn::free_port().map(|port| format!("tcp/127.0.0.1:{port}")))
        .collect::<std::result::Result<_, _>>()?;
    // Topology zenohd: the routers take the first two endpoints, the lines only connect.
    let mut routers = match (topology, &p.zenohd) {
        (Topology::Zenohd, Some(zenohd)) => {
            Some(ZenohRouters::start(zenohd, &endpoints[0], &endpoints[1]).await?)
        }
        (Topology::Zenohd, None) => bail!("topology zenohd needs --zenohd"),
        _ => None,
    };
    let mut lines = Vec::with_capacity(p.lines);
    for n in 1..=p.lines {
        let tables = format!(
            "\n[fb]\nmax_devices_per_identity = {}\n{}",
            p.devices * 2,
            topology.bridge(n, &endpoints)
        );
        let line = start_fbbus(fbbus, &[format!("line = \"line-{n}\"")], &tables)
            .await
            .with_context(|| format!("line-{n}"))?;
        lines.push(line);
    }
    if p.isolate {
        isolate(&lines, routers.as_ref())?;
    }
    let admins: Vec<SocketAddr> = lines
        .iter()
        .map(|l| l.admin.context("fbbus has an admin endpoint"))
        .collect::<Result<_>>()?;
    let epoch = Instant::now();

    // Local delivery on line 3, through everything that follows until convergence;
    // isolated, its clients run on line 3's core (a few packets every 2 ms), not on the
    // harness's, which the device storm keeps busy.
    let probe_thread = match p.isolate {
        true => Some(ProbeThread::start(online_cores() - 1)?),
        false => None,
    };
    let runtime = probe_thread
        .as_ref()
        .map_or_else(tokio::runtime::Handle::current, |t| t.handle.clone());
    let local = runtime
        .spawn(Probe::start(
            lines[2].addr,
            (3, p.devices),
            vec![lines[2].addr],
            epoch,
            p.probe_period,
        ))
        .await
        .context("the probe's start")??;
    let connecting = Instant::now();
    let cpu_before = cpu(&lines);
    let mut held: HashMap<String, TcpStream> = HashMap::new();
    // Isolated, line 3's own devices come first and settle, and its idle p99 is read with
    // all of them connected, before the other lines' devices (and their records) come:
    // what follows is then the bus's federation alone, as the goal reads ("while the bus
    // federates, within 2x its idle p99").
    let idle_before = if p.isolate {
        held.extend(devices(lines[2].addr, 3, p.devices).await?);
        tokio::time::sleep(SETTLE).await;
        let _ = local.phase();
        tokio::time::sleep(SETTLE).await;
        Some(local.phase())
    } else {
        None
    };
    // The devices, every line at once.
    let mut joins = Vec::new();
    for (i, line) in lines.iter().enumerate() {
        if idle_before.is_some() && i == 2 {
            continue;
        }
        let (addr, m) = (line.addr, p.devices);
        joins.push(tokio::spawn(async move { devices(addr, i + 1, m).await }));
    }
    for j in joins {
        held.extend(j.await.context("device task")??);
    }
    let declared = Instant::now();
    t.line(format!(
        "devices:   {} connected and declared in {:.1} s",
        held.len(),
        (declared - connecting).as_secs_f64()
    ));
    let held = Arc::new(Mutex::new(held));
    let pings = keep_alive(Arc::clone(&held));
    if topology == Topology::Alone {
        t.line("converged: no bus (the control: the same storm, each line on its own)");
    } else {
        // And the local probe's device.
        let everyone = (p.lines * p.devices + 1) as f64;
        let mut per_line = Vec::new();
        for (i, admin) in admins.iter().enumerate() {
            let took = until(*admin, everyone, declared, p.converge_within).await;
            per_line.push(match took {
                Some(d) => format!("line-{}: {:.2} s", i + 1, d.as_secs_f64()),
                None => format!(
                    "line-{}: NOT CONVERGED ({} of {everyone} online)",
                    i + 1,
                    metric(*admin, ONLINE).await
                ),
            });
        }
        t.line(format!(
            "converged: every line lists all {everyone} devices online, after the last declaration: {}",
            per_line.join(", ")
        ));
    }
    let during = local.phase();
    let storm_cpu_ms: Vec<u64> = cpu(&lines)
        .iter()
        .zip(&cpu_before)
        .map(|(a, b)| a.saturating_sub(*b) * 1000 / ticks_per_second())
        .collect();
    // The quiet plant, as long as the federation took (3 to 10 s).
    tokio::time::sleep(
        declared
            .elapsed()
            .clamp(Duration::from_secs(3), Duration::from_secs(10)),
    )
    .await;
    let idle = local.phase();
    local.stop().await;
    t.line(format!(
        "local:     line 3 -> line 3 while the bus federated: {}; quiet plant: {}; p99 ratio {}",
        during.describe(),
        idle.describe(),
        ratio(during.p99(), idle.p99())
    ));
    if let Some(before) = &idle_before {
        t.line(format!(
            "           line 3 idle before the other lines' devices came (its own connected): \
             {}; p99 while the bus federated against it: {}",
            before.describe(),
            ratio(during.p99(), before.p99())
        ));
    }
    if let Some(alone) = alone {
        t.line(format!(
            "           p99 during the storm against the same storm with no bus (topology alone, \
             {} ms): {}",
            ms(alone.p99),
            ratio(during.p99(), alone.p99)
        ));
    }
    let control = Control {
        p99: during.p99(),
        rss_kib: lines.iter().map(|l| l.rss_kib().unwrap_or(0)).collect(),
        storm_cpu_ms,
    };
    let join = |v: &[u64]| v.iter().map(u64::to_string).collect::<Vec<_>>().join(" ");
    t.line(format!(
        "cpu:       ms per line from the first connection to convergence: {}",
        join(&control.storm_cpu_ms)
    ));
    // Remote devices each line holds, for the bus's share per device.
    let remote = ((p.lines - 1) * p.devices).max(1) as f64;
    if let Some(alone) = alone {
        let (_, mean) = beyond(&control.storm_cpu_ms, &alone.storm_cpu_ms);
        t.line(format!(
            "           against topology alone: {:.0} ms more per line on average, {:.1} us \
             per remote device taken",
            mean,
            mean * 1000.0 / remote
        ));
    }
    let mib: Vec<String> = control
        .rss_kib
        .iter()
        .map(|k| format!("{:.1}", *k as f64 / 1024.0))
        .collect();
    t.line(format!(
        "memory:    resident MiB per line on the quiet plant: {}",
        mib.join(" ")
    ));
    if let Some(alone) = alone {
        let (more, mean) = beyond(&control.rss_kib, &alone.rss_kib);
        t.line(format!(
            "           against topology alone: MiB more per line {} (the bus: its zenoh \
             session and the {remote} remote devices each line holds), {:.2} KiB per remote \
             device on average, the session included",
            more.iter()
                .map(|k| format!("{:+.1}", k / 1024.0))
                .collect::<Vec<_>>()
                .join(" "),
            mean / remote
        ));
    }
    if topology == Topology::Alone {
        pings.abort();
        return Ok(control);
    }

    // The traffic matrix.
    t.line(format!(
        "{:<12} {:>8} {:>9} {:>6} {:>5} {:>9} {:>9} {:>9}  cpu ms per line",
        "pattern", "sent", "delivered", "lost", "dup", "p50 ms", "p99 ms", "max ms"
    ));
    let n = p.lines;
    let patterns: Vec<(&str, Vec<Flow>)> = vec![
        (
            "neighbour",
            (1..=n).map(|i| ((i, 0), vec![i % n + 1])).collect(),
        ),
        ("all-to-one", (1..n).map(|i| ((i, 1), vec![n])).collect()),
        (
            "one-to-all",
            vec![((3, 2), (1..=n).filter(|&j| j != 3).collect())],
        ),
    ];
    for (name, flows) in patterns {
        let before = cpu(&lines);
        let figures = matrix(&lines, &held, &flows, epoch, p).await?;
        let after = cpu(&lines);
        let cpu_ms: Vec<String> = before
            .iter()
            .zip(&after)
            .map(|(b, a)| format!("{}", a.saturating_sub(*b) * 1000 / ticks_per_second()))
            .collect();
        let [p50, p99, max] = figures.latencies();
        t.line(format!(
            "{:<12} {:>8} {:>9} {:>6} {:>5} {p50:>9} {p99:>9} {max:>9}  {}",
            name,
            figures.sent,
            figures.delivered,
            figures.lost(),
            figures.duplicated,
            cpu_ms.join(" ")
        ));
    }

    if let Some(routers) = routers.as_mut() {
        // Router 1 dies while the neighbour pattern runs: what was in flight through it is
        // lost, and counted three times: by the harness, by the lines that missed it and
        // by the lines that sent it.
        let lost_before = bus_lost(&admins).await;
        let neighbour: Vec<Flow> = (1..=n).map(|i| ((i, 3), vec![i % n + 1])).collect();
        let (figures, died) = tokio::join!(matrix(&lines, &held, &neighbour, epoch, p), async {
            tokio::time::sleep(Duration::from_millis(500)).await;
            router_dies(routers, &admins, (p.lines * p.devices) as f64, t).await
        });
        died?;
        let figures = figures?;
        // The senders hear of it within a second of the receivers counting it.
        tokio::time::sleep(Duration::from_millis(1500)).await;
        let lost_after = bus_lost(&admins).await;
        let (missed, reported) = (lost_after.0 - lost_before.0, lost_after.1 - lost_before.1);
        let [p50, p99, max] = figures.latencies();
        t.line(format!(
            "neighbour while router 1 dies: sent {}, delivered {}, lost {} (counted by the \
             lines that missed them, fbbus_bridge_lost_total: {missed}; by the lines that \
             sent them, fbbus_bridge_lost_reported_total: {reported}), duplicated {}; \
             p50 / p99 / max {p50} / {p99} / {max} ms",
            figures.sent,
            figures.delivered,
            figures.lost(),
            figures.duplicated,
        ));
        pings.abort();
        return Ok(control);
    }
    // A router (or the first peer) dies.
    let living = ((p.lines - 1) * p.devices) as f64;
    let killed = Instant::now();
    lines[0].kill().context("killing line 1")?;
    let mut lowest = f64::MAX;
    let mut back = Vec::new();
    for (i, admin) in admins.iter().enumerate().skip(1) {
        let (took, low) = reconverged(*admin, living, killed, p.converge_within).await;
        lowest = lowest.min(low);
        back.push(match took {
            Some(d) => format!("line-{}: {:.2} s", i + 1, d.as_secs_f64()),
            None => format!("line-{}: NOT BACK", i + 1),
        });
    }
    t.line(format!(
        "line 1 killed: every other line lists the {living} devices of the living lines \
         online (and line 1's not) after: {}; lowest count seen meanwhile {lowest}",
        back.join(", ")
    ));
    pings.abort();
    Ok(control)
}

const ONLINE: &str = "fbbus_registry_devices{status=\"online\"}";

/// Messages the lines counted as lost on the bus, all lines together: as (counted by the
/// lines that missed them, counted by the lines that sent them from the others' reports).
async fn bus_lost(admins: &[SocketAddr]) -> (f64, f64) {
    let (mut missed, mut sent) = (0.0, 0.0);
    for admin in admins {
        missed += metric(*admin, "fbbus_bridge_lost_total").await;
        sent += metric(*admin, "fbbus_bridge_lost_reported_total").await;
    }
    (missed, sent)
}

/// Topology zenohd: router 1 dies, no line does. Every line is polled every 50 ms for 8 s
/// (the 3 s lease and as much again): whether any listed fewer than `want` devices online,
/// the lowest count, and the last moment one did.
async fn router_dies(
    routers: &mut ZenohRouters,
    admins: &[SocketAddr],
    want: f64,
    t: &mut Transcript,
) -> Result<()> {
    let killed = Instant::now();
    routers.kill_first()?;
    let (mut lowest, mut last_short) = (f64::MAX, None);
    while killed.elapsed() < Duration::from_secs(8) {
        for admin in admins {
            let online = metric(*admin, ONLINE).await;
            lowest = lowest.min(online);
            if online < want {
                last_short = Some(killed.elapsed());
            }
        }
        tokio::time::sleep(Duration::from_millis(50)).await;
    }
    t.line(match last_short {
        None => format!(
            "router 1 (zenohd) killed: no line ever listed fewer than all {want} devices \
             online (every line polled every 50 ms for 8 s)"
        ),
        Some(d) => format!(
            "router 1 (zenohd) killed: every line lists all {want} devices online again \
             {:.2} s after it at the latest; lowest count seen meanwhile {lowest}",
            d.as_secs_f64()
        ),
    });
    Ok(())
}

/// Two zenohd routers on plain tcp/ loopback endpoints, router 2 connecting to router 1,
/// with the lines' lease (3 s); killed on drop.
struct ZenohRouters {
    children: Vec<std::process::Child>,
    _dir: tempfile::TempDir,
}

impl ZenohRouters {
    async fn start(zenohd: &Path, first: &str, second: &str) -> Result<ZenohRouters> {
        let dir = tempfile::tempdir()?;
        let mut routers = ZenohRouters {
            children: Vec::new(),
            _dir: tempfile::tempdir()?,
        };
        for (i, (listen, connect)) in [(first, None), (second, Some(first))]
            .into_iter()
            .enumerate()
        {
            let config = serde_json::json!({
                "mode": "router",
                "listen": {"endpoints": [listen]},
                "connect": {
                    "endpoints": connect.into_iter().collect::<Vec<_>>(),
                    "timeout_ms": -1,
                    "exit_on_failure": false,
                },
                "scouting": {"multicast": {"enabled": false}},
                "transport": {"link": {"tx": {"lease": 3000, "keep_alive": 4}}},
            });
            let file = dir.path().join(format!("router-{}.json5", i + 1));
            std::fs::write(&file, config.to_string())?;
            let log = std::fs::File::create(dir.path().join(format!("router-{}.log", i + 1)))?;
            let child = std::process::Command::new(zenohd)
                .arg("-c")
                .arg(&file)
                .stdout(log.try_clone()?)
                .stderr(log)
                .spawn()
                .with_context(|| format!("starting {}", zenohd.display()))?;
            routers.children.push(child);
            let addr = listen.trim_start_matches("tcp/");
            let deadline = Instant::now() + Duration::from_secs(10);
            while TcpStream::connect(addr).await.is_err() {
                if Instant::now() > deadline {
                    bail!("zenohd did not listen on {listen} within 10 s");
                }
                tokio::time::sleep(Duration::from_millis(50)).await;
            }
        }
        routers._dir = dir;
        Ok(routers)
    }

    fn kill_first(&mut self) -> Result<()> {
        let first = &mut self.children[0];
        first.kill().context("killing zenohd router 1")?;
        first.wait().context("reaping zenohd router 1")?;
        Ok(())
    }
}

impl Drop for ZenohRouters {
    fn drop(&mut self) {
        for child in &mut self.children {
            let _ = child.kill();
            let _ = child.wait();
        }
    }
}

/// Connects and declares `m` devices of line `line`; their connections by id, held open.
async fn devices(addr: SocketAddr, line: usize, m: usize) -> Result<Vec<(String, TcpStream)>> {
    let mut out = Vec::with_capacity(m);
    for d in 0..m {
        let id = device_id(line, d);
        let mut s = tokio::time::timeout(Duration::from_secs(10), mqtt::connect(addr, &id, None))
            .await
            .with_context(|| format!("{id}: CONNECT timed out"))??;
        s.write_all(&mqtt::publish_packet(
            &format!("fbbus/declare/{id}"),
            INTERFACE.as_bytes(),
        ))
        .await?;
        out.push((id, s));
    }
    Ok(out)
}

type Held = Arc<Mutex<HashMap<String, TcpStream>>>;

/// PINGREQ on every held connection every 20 s (their keep-alive is 60 s), until
/// aborted. (The PINGRESPs are never read: 2 bytes each in a socket's buffer.)
fn keep_alive(held: Held) -> tokio::task::JoinHandle<()> {
    tokio::spawn(async move {
        loop {
            tokio::time::sleep(Duration::from_secs(20)).await;
            for s in held.lock().await.values_mut() {
                let _ = s.write_all(&[0xC0, 0x00]).await;
            }
        }
    })
}

/// How long after `from` the line's online count reached `want`, or None by `within`.
async fn until(admin: SocketAddr, want: f64, from: Instant, within: Duration) -> Option<Duration> {
    while from.elapsed() < within {
        if metric(admin, ONLINE).await >= want {
            return Some(from.elapsed());
        }
        tokio::time::sleep(Duration::from_millis(100)).await;
    }
    None
}

/// After a line died: how long until the online count is `want` again (it drops when
/// the dead line's devices go unreachable, and whatever else was cut off with it), and
/// the lowest count seen on the way.
async fn reconverged(
    admin: SocketAddr,
    want: f64,
    from: Instant,
    within: Duration,
) -> (Option<Duration>, f64) {
    let mut lowest = f64::MAX;
    while from.elapsed() < within {
        let now = metric(admin, ONLINE).await;
        lowest = lowest.min(now);
        if now == want {
            return (Some(from.elapsed()), lowest);
        }
        tokio::time::sleep(Duration::from_millis(100)).await;
    }
    (None, lowest)
}

struct Figures {
    sent: u64,
    delivered: u64,
    duplicated: u64,
    latency: Histogram<u64>,
}

impl Figures {
    fn lost(&self) -> u64 {
        self.sent.saturating_sub(self.delivered)
    }

    /// p50, p99 and max, in ms as printed.
    fn latencies(&self) -> [String; 3] {
        let l = &self.latency;
        [
            ms(l.value_at_quantile(0.5)),
            ms(l.value_at_quantile(0.99)),
            ms(l.max()),
        ]
    }
}

/// A publisher (line, device) and the lines whose subscribers read it.
type Flow = ((usize, usize), Vec<usize>);

/// One pattern: each publisher (line, device) sends to subscribers on the listed lines.
async fn matrix(
    lines: &[Running],
    held: &Held,
    flows: &[Flow],
    epoch: Instant,
    p: &PlantParams,
) -> Result<Figures> {
    let figures = Arc::new(Mutex::new(Figures {
        sent: 0,
        delivered: 0,
        duplicated: 0,
        latency: Histogram::new_with_bounds(1, 60_000_000, 3)?,
    }));
    // One subscriber per (flow, receiving line), each counting what it gets once.
    let mut readers = Vec::new();
    let stop = Arc::new(tokio::sync::Notify::new());
    for (f, ((line, device), to)) in flows.iter().enumerate() {
        for &j in to {
            let mut s =
                mqtt::connect(lines[j - 1].addr, &format!("plant-sub-{f}-{j}"), None).await?;
            mqtt::subscribe(&mut s, &topic(*line, *device)).await?;
            readers.push(tokio::spawn(receive(
                PacketReader::new(s),
                epoch,
                Arc::clone(&figures),
                Arc::clone(&stop),
            )));
        }
    }
    // The interests cross the bus before the first message.
    tokio::time::sleep(Duration::from_secs(2)).await;
    let mut publishers = Vec::new();
    for ((line, device), to) in flows {
        // The device publishes on its own connection, taken from the plant for the
        // pattern and given back after.
        let id = device_id(*line, *device);
        let mut s = held
            .lock()
            .await
            .remove(&id)
            .with_context(|| format!("device {id} is not connected"))?;
        let (period, traffic, topic) = (p.period, p.traffic, topic(*line, *device));
        let copies = to.len() as u64;
        let figures = Arc::clone(&figures);
        publishers.push(tokio::spawn(async move {
            let started = Instant::now();
            let mut tick = tokio::time::interval(period);
            let mut sent = 0u64;
            while started.elapsed() < traffic {
                tick.tick().await;
                let value = micros(epoch).to_string();
                if s.write_all(&mqtt::publish_packet(&topic, value.as_bytes()))
                    .await
                    .is_err()
                {
                    break;
                }
                sent += copies;
            }
            figures.lock().await.sent += sent;
            (id, s)
        }));
    }
    for pub_task in publishers {
        let (id, s) = pub_task.await.context("publisher task")?;
        held.lock().await.insert(id, s);
    }
    tokio::time::sleep(Duration::from_secs(2)).await;
    stop.notify_waiters();
    for r in readers {
        let _ = r.await;
    }
    let figures = Arc::try_unwrap(figures)
        .map_err(|_| anyhow::anyhow!("a reader still holds the figures"))?
        .into_inner();
    Ok(figures)
}

/// Reads PUBLISHes until `stop`, counting each value once (a second copy is a duplicate).
async fn receive(
    reader: PacketReader,
    epoch: Instant,
    figures: Arc<Mutex<Figures>>,
    stop: Arc<tokio::sync::Notify>,
) {
    let mut seen = std::collections::HashSet::new();
    let (mut delivered, mut duplicated) = (0u64, 0u64);
    let mut latencies = Vec::new();
    read_values(reader, &stop, |value| {
        if seen.insert(value) {
            delivered += 1;
            latencies.push((micros(epoch) - value).max(1) as u64);
        } else {
            duplicated += 1;
        }
    })
    .await;
    let mut f = figures.lock().await;
    f.delivered += delivered;
    f.duplicated += duplicated;
    for l in latencies {
        let _ = f.latency.record(l);
    }
}

/// Reads PUBLISHes until `stop` or the connection's end, handing each measured value
/// (its send time, [`sent_at`]) to `each`.
async fn read_values(
    mut reader: PacketReader,
    stop: &tokio::sync::Notify,
    mut each: impl FnMut(i64),
) {
    let stopped = stop.notified();
    tokio::pin!(stopped);
    loop {
        tokio::select! {
            _ = &mut stopped => break,
            read = reader.read_more() => {
                if !matches!(read, Ok(n) if n > 0) {
                    break;
                }
                while let Ok(Some((header, body))) = reader.next_packet() {
                    if let Some(value) = sent_at(header, body) {
                        each(value);
                    }
                }
            }
        }
    }
}

/// A device publishing to subscribers, whose latency is read phase by phase.
struct Probe {
    /// A std mutex: held only to record or take, never across an await.
    latency: Arc<std::sync::Mutex<Histogram<u64>>>,
    tasks: Vec<tokio::task::JoinHandle<()>>,
    stop: Arc<tokio::sync::Notify>,
}

struct Phase(Histogram<u64>);

impl Phase {
    fn p99(&self) -> u64 {
        self.0.value_at_quantile(0.99)
    }

    fn describe(&self) -> String {
        format!(
            "{} messages, p50 {} ms, p99 {} ms, max {} ms",
            self.0.len(),
            ms(self.0.value_at_quantile(0.5)),
            ms(self.p99()),
            ms(self.0.max())
        )
    }
}

impl Probe {
    async fn start(
        on: SocketAddr,
        (line, device): (usize, usize),
        to: Vec<SocketAddr>,
        epoch: Instant,
        period: Duration,
    ) -> Result<Probe> {
        let latency = Arc::new(std::sync::Mutex::new(Histogram::new_with_bounds(
            1, 60_000_000, 3,
        )?));
        let stop = Arc::new(tokio::sync::Notify::new());
        let id = device_id(line, device);
        let mut dev = mqtt::connect(on, &id, None).await?;
        dev.write_all(&mqtt::publish_packet(
            &format!("fbbus/declare/{id}"),
            INTERFACE.as_bytes(),
        ))
        .await?;
        let mut tasks = Vec::new();
        for (k, sub) in to.iter().enumerate() {
            let mut s = mqtt::connect(*sub, &format!("plant-probe-{k}"), None).await?;
            mqtt::subscribe(&mut s, &topic(line, device)).await?;
            let (latency, stop) = (Arc::clone(&latency), Arc::clone(&stop));
            tasks.push(tokio::spawn(async move {
                read_values(PacketReader::new(s), &stop, |value| {
                    let _ = latency
                        .lock()
                        .unwrap_or_else(std::sync::PoisonError::into_inner)
                        .record((micros(epoch) - value).max(1) as u64);
                })
                .await;
            }));
        }
        let topic = topic(line, device);
        let stop_pub = Arc::clone(&stop);
        tasks.push(tokio::spawn(async move {
            let mut tick = tokio::time::interval(period);
            let stopped = stop_pub.notified();
            tokio::pin!(stopped);
            // Bounded: at most ten minutes of messages whatever happens.
            for _ in 0..(600_000 / period.as_millis().max(1)) {
                tokio::select! {
                    _ = &mut stopped => break,
                    _ = tick.tick() => {
                        let value = micros(epoch).to_string();
                        if dev.write_all(&mqtt::publish_packet(&topic, value.as_bytes())).await.is_err() {
                            break;
                        }
                    }
                }
            }
        }));
        Ok(Probe {
            latency,
            tasks,
            stop,
        })
    }

    /// The latencies since the last phase, and a fresh start.
    fn phase(&self) -> Phase {
        let mut h = self
            .latency
            .lock()
            .unwrap_or_else(std::sync::PoisonError::into_inner);
        let taken = h.clone();
        h.reset();
        Phase(taken)
    }

    async fn stop(self) {
        self.stop.notify_waiters();
        for t in self.tasks {
            let _ = t.await;
        }
    }
}

/// The send time a measured PUBLISH carries as its LINT value (µs since the run's
/// epoch); None for any other packet.
fn sent_at(header: u8, body: &[u8]) -> Option<i64> {
    mqtt::publish_payload(header, body)
        .and_then(|v| std::str::from_utf8(v).ok())
        .and_then(|v| v.trim().parse::<i64>().ok())
}

fn ms(us: u64) -> String {
    format!("{:.2}", us as f64 / 1000.0)
}

fn ratio(a: u64, b: u64) -> String {
    if b == 0 {
        return "-".into();
    }
    format!("{:.2}x", a as f64 / b as f64)
}

/// Line 3 (the local probe's) on the last core alone; the other lines, the zenohd
/// routers and this harness (its devices and probes) on the others. Every thread of each
/// process is pinned; threads started later inherit their creator's cores.
fn isolate(lines: &[Running], routers: Option<&ZenohRouters>) -> Result<()> {
    let cores = online_cores();
    if cores < 2 {
        bail!("--isolate needs at least 2 cores");
    }
    let own = [cores - 1];
    let rest: Vec<usize> = (0..cores - 1).collect();
    let mut others: Vec<u32> = vec![std::process::id()];
    others.extend(
        routers
            .iter()
            .flat_map(|r| r.children.iter().map(|c| c.id())),
    );
    for (i, line) in lines.iter().enumerate() {
        if i == 2 {
            pin(line.pid(), &own)?;
        } else {
            others.push(line.pid());
        }
    }
    for pid in others {
        pin(pid, &rest)?;
    }
    Ok(())
}

/// How long line 3's own devices settle, and its idle p99 is then read, before the other
/// lines' devices come (`--isolate`).
const SETTLE: Duration = Duration::from_secs(3);

/// The machine's cores (not this process's: once pinned, it has fewer).
fn online_cores() -> usize {
    // SAFETY: sysconf has no preconditions.
    let n = unsafe { libc::sysconf(libc::_SC_NPROCESSORS_ONLN) };
    usize::try_from(n).ok().filter(|n| *n > 0).unwrap_or(1)
}

/// Pins every thread of process `pid` to `cores` (as `taskset -a`).
fn pin(pid: u32, cores: &[usize]) -> Result<()> {
    let tasks = std::fs::read_dir(format!("/proc/{pid}/task"))
        .with_context(|| format!("the threads of process {pid}"))?;
    for task in tasks {
        let Some(tid) = task?
            .file_name()
            .to_str()
            .and_then(|t| t.parse::<i32>().ok())
        else {
            continue;
        };
        pin_thread(tid, cores).with_context(|| format!("a thread of process {pid}"))?;
    }
    Ok(())
}

/// Pins thread `tid` (0: the calling thread) to `cores` (`sched_setaffinity`).
fn pin_thread(tid: i32, cores: &[usize]) -> Result<()> {
    // SAFETY: a zeroed cpu_set_t is an empty set; CPU_SET writes within it for cores
    // below CPU_SETSIZE (checked).
    let mut set: libc::cpu_set_t = unsafe { std::mem::zeroed() };
    for &core in cores {
        if core >= libc::CPU_SETSIZE as usize {
            bail!("core {core} is beyond CPU_SETSIZE");
        }
        unsafe { libc::CPU_SET(core, &mut set) };
    }
    // SAFETY: `set` is a valid cpu_set_t of the size passed.
    let rc = unsafe { libc::sched_setaffinity(tid, std::mem::size_of::<libc::cpu_set_t>(), &set) };
    if rc != 0 {
        bail!("pinning thread {tid}: {}", std::io::Error::last_os_error());
    }
    Ok(())
}

/// A runtime of one thread pinned to one core, for the local probe's clients when line 3
/// is isolated. Stops when dropped.
struct ProbeThread {
    handle: tokio::runtime::Handle,
    stop: Option<tokio::sync::oneshot::Sender<()>>,
}

impl ProbeThread {
    fn start(core: usize) -> Result<ProbeThread> {
        let runtime = tokio::runtime::Builder::new_current_thread()
            .enable_all()
            .build()?;
        let handle = runtime.handle().clone();
        let (stop, stopped) = tokio::sync::oneshot::channel::<()>();
        let (pinned_tx, pinned) = std::sync::mpsc::channel();
        std::thread::Builder::new()
            .name("plant-probe".into())
            .spawn(move || {
                let _ = pinned_tx.send(pin_thread(0, &[core]));
                let _ = runtime.block_on(stopped);
            })?;
        pinned.recv().context("the probe's thread")??;
        Ok(ProbeThread {
            handle,
            stop: Some(stop),
        })
    }
}

impl Drop for ProbeThread {
    fn drop(&mut self) {
        if let Some(stop) = self.stop.take() {
            let _ = stop.send(());
        }
    }
}

/// user + system CPU ticks of each line's process so far.
fn cpu(lines: &[Running]) -> Vec<u64> {
    lines
        .iter()
        .map(|l| super::bridge::cpu_ticks(l.pid()).unwrap_or(0))
        .collect()
}

fn ticks_per_second() -> u64 {
    // SAFETY: sysconf has no preconditions.
    let ticks = unsafe { libc::sysconf(libc::_SC_CLK_TCK) };
    u64::try_from(ticks).ok().filter(|t| *t > 0).unwrap_or(100)
}

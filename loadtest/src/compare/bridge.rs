//! `fbbus-loadtest compare bridge`: what the zenoh hop between two lines costs, side by
//! side in one run, over plain TCP and over mutual TLS with access control.
//!
//! Setups, each with one device publishing the conveyor's STATE event (canonical JSON,
//! QoS 0) on `fb/bench-dev/CONV/STATE` and one subscriber:
//!
//! - **one broker**: fbbus without a bridge, device and subscriber on it;
//! - **line A, local**: line A of a bridged pair, device and subscriber both on A (what a
//!   configured bridge costs traffic that does not cross); on the first bus only;
//! - **A -> B `<bus>`**: the device on line A, the subscriber on line B: MQTT → router →
//!   bridge → zenoh (loopback) → bridge → typed check → router → MQTT; once per bus of
//!   `--bus`:
//!   - `tcp`: `tcp/127.0.0.1` endpoints, no TLS, no access control (a loopback bus as
//!     issue 5 measured it);
//!   - `tls`: `tls/127.0.0.1` endpoints, `[bridge.tls]` with `mutual = false`: only the
//!     listening line shows a certificate, no access control (allowed on loopback only);
//!     what the encryption alone costs;
//!   - `mtls`: `tls/127.0.0.1` endpoints, `[bridge.tls]` with a CA and one certificate
//!     per line made for this run (rcgen; CN = the line's name, SANs localhost and
//!     127.0.0.1, server and client auth), mutual by default, and `[bridge.peers] lines =
//!     [the other line]`, which turns on zenoh's access control (default deny; issue 22).
//!
//! Measured per setup: **latency**, one message at a time (send, wait for it, next),
//! p50/p99/max; **throughput**, a burst of M messages into the subscriber, from the first
//! send to the last receipt, with the messages lost and the CPU time the broker processes
//! spent on it. With `--rounds N` every setup runs N times, alternating (one broker, A ->
//! B tcp, A -> B mtls, one broker, ...), each on freshly started processes, so machine
//! noise hits every setup alike; the summary uses each setup's median. Then the hop's
//! cost, p50(A -> B) − p50(one broker) and msg/s(A -> B) / msg/s(one broker), per bus,
//! and every later bus as a ratio to each earlier one (`mtls/tcp`). Last, the floor under
//! the hop: zenoh alone between two processes, ping-pong at 1,000 msg/s
//! ([`loadtest::zenoh_floor`]), half a round trip being what zenoh itself adds one way.
//! Everything on 127.0.0.1; every loop is bounded by a count and a deadline.

use std::net::SocketAddr;
use std::path::{Path, PathBuf};
use std::time::{Duration, Instant};

use anyhow::{bail, Context as _, Result};
use hdrhistogram::Histogram;
use tokio::io::AsyncWriteExt;

use super::{metric, start_fbbus, Transcript};
use loadtest::broker_process::spawn::{self, Running};
use loadtest::raw_client::{self as mqtt, PacketReader};

pub struct BridgeParams {
    pub samples: usize,
    pub burst: usize,
    pub rounds: u32,
    pub buses: Vec<Bus>,
}

impl BridgeParams {
    pub fn full() -> BridgeParams {
        BridgeParams {
            samples: 5_000,
            burst: 40_000,
            rounds: 1,
            buses: vec![Bus::Tcp],
        }
    }

    pub fn quick() -> BridgeParams {
        BridgeParams {
            samples: 200,
            burst: 2_000,
            ..BridgeParams::full()
        }
    }
}

/// How the two lines' bridges are linked.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Bus {
    /// Plain TCP on loopback, no access control.
    Tcp,
    /// zenoh's TLS, only the listener shows a certificate, no access control.
    Tls,
    /// zenoh's TLS with certificates on both sides and `[bridge.peers]` access control.
    Mtls,
}

impl Bus {
    pub const ALL: [Bus; 3] = [Bus::Tcp, Bus::Tls, Bus::Mtls];

    pub fn name(self) -> &'static str {
        match self {
            Bus::Tcp => "tcp",
            Bus::Tls => "tls",
            Bus::Mtls => "mtls",
        }
    }

    pub fn parse(name: &str) -> Option<Bus> {
        Bus::ALL.into_iter().find(|b| b.name() == name)
    }

    /// `--bus` as given (comma-separated names), in the order given, each once; default tcp.
    pub fn parse_list(names: &[String]) -> Result<Vec<Bus>> {
        let mut buses = Vec::new();
        for name in names {
            let bus = Bus::parse(name.trim()).with_context(|| {
                format!(
                    "unknown bus `{name}` (known: {})",
                    Bus::ALL.map(|b| b.name()).join(", ")
                )
            })?;
            if !buses.contains(&bus) {
                buses.push(bus);
            }
        }
        if buses.is_empty() {
            buses.push(Bus::Tcp);
        }
        Ok(buses)
    }

    fn describe(self) -> &'static str {
        match self {
            Bus::Tcp => "line-a listens on tcp/127.0.0.1:<port>, line-b connects; no TLS, no access control",
            Bus::Tls => {
                "line-a listens on tls/127.0.0.1:<port>, line-b connects; [bridge.tls] root_ca/cert/key with \
                 mutual = false (line-a's certificate only; allowed on loopback only); no access control"
            }
            Bus::Mtls => {
                "line-a listens on tls/127.0.0.1:<port>, line-b connects; [bridge.tls] root_ca/cert/key \
                 (mutual, the default): a CA and one certificate per line made for this run with rcgen \
                 (ECDSA P-256, CN = the line's name, SANs localhost + 127.0.0.1, server + client auth); \
                 [bridge.peers] lines = [the other line]: zenoh access control, default deny"
            }
        }
    }
}

const DEVICE: &str = "bench-dev";
const TOPIC: &str = "fb/bench-dev/CONV/STATE";
const INTERFACE: &str = r#"{"fbs":{"CONV":{"type":"CONVEYOR",
  "events_out":{"STATE":{"with":["ID","CONNECT","SENSOR_IN","SENSOR_OUT","POSITION","SWAP"]}},
  "data_out":{"ID":"STRING","CONNECT":"BOOL","SENSOR_IN":"BOOL","SENSOR_OUT":"BOOL","POSITION":"INT","SWAP":"BOOL"}}}}"#;
const EVENT: &str = r#"{"seq":1,"ts":1763800000000000,"data":{"ID":"conveyor-a","CONNECT":true,"SENSOR_IN":false,"SENSOR_OUT":true,"POSITION":2,"SWAP":false}}"#;
/// The burst's limit: no receipt after this long counts the rest as lost.
const BURST_DEADLINE: Duration = Duration::from_secs(60);
/// The latency samples' limit, all of them together.
const LATENCY_DEADLINE: Duration = Duration::from_secs(120);
/// A safety net around one setup's whole measurement (start-up waits included).
const SETUP_DEADLINE: Duration = Duration::from_secs(300);
/// Linux's USER_HZ: the unit of utime and stime in `/proc/<pid>/stat`.
pub(super) const TICKS_PER_SECOND: f64 = 100.0;

/// What one setup measured in one round.
#[derive(Clone, Debug)]
struct Figures {
    p50_us: f64,
    p99_us: f64,
    max_us: f64,
    rate: f64,
    delivered: usize,
    /// CPU seconds (user + system) the setup's broker processes spent per 100,000
    /// messages of the burst.
    cpu_per_100k: Option<f64>,
    /// For A -> B: the same for line A and line B apart.
    cpu_lines: Option<(f64, f64)>,
}

/// One row of the run: a setup in a round, its figures or why there are none.
struct Row {
    setup: String,
    round: u32,
    result: std::result::Result<Figures, String>,
}

/// Round trips and their rate for the floor under the hop ([`loadtest::zenoh_floor`]).
const FLOOR_ROUND_TRIPS: usize = 2000;
const FLOOR_RATE: u32 = 1000;

pub async fn run(fbbus: &Path, p: &BridgeParams, out: &Path) -> Result<()> {
    let mut t = Transcript::default();
    header(&mut t, fbbus, p);
    // The certificates are made before anything starts (not measured).
    let pki = if p.buses.iter().any(|&b| b != Bus::Tcp) {
        Some(Pki::generate(&["line-a", "line-b"])?)
    } else {
        None
    };

    let started = Instant::now();
    let mut rows: Vec<Row> = Vec::new();
    for round in 1..=p.rounds {
        eprintln!("bridge: round {round}/{}", p.rounds);
        let result = guarded(async {
            let single = start(fbbus, &[], "").await?;
            measure("one broker", &single, &single, None, p).await
        })
        .await;
        rows.push(Row {
            setup: "one broker".into(),
            round,
            result,
        });
        for (i, &bus) in p.buses.iter().enumerate() {
            let pair = match Pair::start(fbbus, bus, pki.as_ref()).await {
                Ok(pair) => pair,
                Err(e) => {
                    let why = format!("lines did not start: {e:#}");
                    if i == 0 {
                        rows.push(Row {
                            setup: "line A, local".into(),
                            round,
                            result: Err(why.clone()),
                        });
                    }
                    rows.push(Row {
                        setup: across(bus),
                        round,
                        result: Err(why),
                    });
                    continue;
                }
            };
            if i == 0 {
                let result = guarded(measure("line A, local", &pair.a, &pair.a, None, p)).await;
                rows.push(Row {
                    setup: "line A, local".into(),
                    round,
                    result,
                });
            }
            let name = across(bus);
            let result = guarded(measure(&name, &pair.a, &pair.b, Some(&pair.a), p)).await;
            let keep = format!("bridge-failed-{}-round{round}", bus.name());
            let result = pair.check(result, out, &keep).await;
            rows.push(Row {
                setup: name,
                round,
                result,
            });
        }
    }

    eprintln!("bridge: zenoh alone");
    let floor = tokio::task::spawn_blocking(|| {
        loadtest::zenoh_floor::measure(FLOOR_ROUND_TRIPS, FLOOR_RATE)
    })
    .await
    .map_err(|e| anyhow::anyhow!("{e}"))
    .and_then(|r| r);
    table(&mut t, &rows, p);
    summary(&mut t, &rows, p, started.elapsed());
    match floor {
        Ok(f) => t.line(format!(
            "zenoh alone (loadtest::zenoh_floor: two processes, peers over loopback TCP, no TLS, \
             {FLOOR_RATE} msg/s, {} round trips): one way p50 {:.0} us, p99 {:.0} us: what zenoh \
             itself adds, the hop's floor here while the bus is zenoh over TCP",
            f.samples, f.p50_us, f.p99_us
        )),
        Err(e) => t.line(format!("zenoh alone: n/a ({e:#})")),
    }
    drop(pki);
    std::fs::create_dir_all(out).with_context(|| format!("creating --out {}", out.display()))?;
    let file = out.join("bridge.txt");
    std::fs::write(&file, &t.0).with_context(|| format!("writing {}", file.display()))?;
    eprintln!("wrote {}", file.display());
    let failed = rows.iter().filter(|r| r.result.is_err()).count();
    if failed > 0 {
        bail!(
            "{failed} of {} measurements failed (see their rows)",
            rows.len()
        );
    }
    Ok(())
}

fn across(bus: Bus) -> String {
    format!("A -> B {}", bus.name())
}

/// A fresh fbbus (see [`start_fbbus`]); tried a second time on fresh ports if it does not
/// start: a port found free can be taken by another process before fbbus binds it.
async fn start(fbbus: &Path, broker_keys: &[String], tables: &str) -> Result<Running> {
    match start_fbbus(fbbus, broker_keys, tables).await {
        Ok(running) => Ok(running),
        Err(e) => {
            eprintln!("bridge: fbbus did not start ({e:#}); trying again on other ports");
            start_fbbus(fbbus, broker_keys, tables).await
        }
    }
}

/// One setup's measurement within [`SETUP_DEADLINE`], its error as text.
async fn guarded(
    measurement: impl std::future::Future<Output = Result<Figures>>,
) -> std::result::Result<Figures, String> {
    match tokio::time::timeout(SETUP_DEADLINE, measurement).await {
        Ok(Ok(f)) => Ok(f),
        Ok(Err(e)) => Err(format!("{e:#}")),
        Err(_) => Err(format!("timeout (no result after {SETUP_DEADLINE:?})")),
    }
}

fn header(t: &mut Transcript, fbbus: &Path, p: &BridgeParams) {
    let m = loadtest::machine::this_machine();
    t.line(format!(
        "fbbus-loadtest compare bridge {}",
        env!("CARGO_PKG_VERSION")
    ));
    t.line(format!(
        "machine:  {} cores, {}, {} MiB RAM, {}",
        m.cpus, m.cpu_model, m.memory_mib, m.os
    ));
    t.line(format!(
        "fbbus:    {} ({}; config defaults, [log] level = \"warn\")",
        spawn::fbbus_version(fbbus),
        fbbus.display()
    ));
    for bus in &p.buses {
        t.line(format!(
            "bus {:<5} {}",
            format!("{}:", bus.name()),
            bus.describe()
        ));
    }
    t.line(format!(
        "params:   {} latency samples (one at a time), bursts of {} ({}-byte STATE events, QoS 0, raw MQTT 3.1.1 \
         sockets, 1,000 messages per write); {} round(s), setups alternating, fresh processes for each; \
         127.0.0.1 only",
        p.samples,
        p.burst,
        EVENT.len(),
        p.rounds
    ));
    t.line(
        "columns:  latency of single messages (p50/p99/max, us); burst msg/s = received / (last receipt - \
         first send); lost = burst - received; cpu s/100k = user + system CPU of the setup's broker \
         processes (both lines for A -> B) during the burst, per 100,000 messages; cpu A, cpu B: of it line A's, \
         line B's",
    );
    t.line("");
}

const COLUMNS: [&str; 9] = [
    "p50 us",
    "p99 us",
    "max us",
    "burst msg/s",
    "delivered",
    "lost",
    "cpu s/100k",
    "cpu A",
    "cpu B",
];

fn table_line(setup: &str, cells: &[String]) -> String {
    let widths = [9, 9, 9, 12, 14, 7, 11, 7, 7];
    let mut line = format!("{setup:<18}");
    for (cell, w) in cells.iter().zip(widths) {
        line.push_str(&format!("{cell:>w$}"));
    }
    line
}

fn header_line(first: &str) -> String {
    let cells: Vec<String> = COLUMNS.iter().map(|c| c.to_string()).collect();
    table_line(first, &cells)
}

fn cpu_cell(cpu: Option<f64>) -> String {
    cpu.map(|c| format!("{c:.2}")).unwrap_or_else(|| "-".into())
}

/// Every row in the order it ran.
fn table(t: &mut Transcript, rows: &[Row], p: &BridgeParams) {
    t.line(header_line("setup"));
    for row in rows {
        let name = if p.rounds > 1 {
            format!("{} #{}", row.setup, row.round)
        } else {
            row.setup.clone()
        };
        match &row.result {
            Ok(f) => t.line(table_line(
                &name,
                &[
                    format!("{:.0}", f.p50_us),
                    format!("{:.0}", f.p99_us),
                    format!("{:.0}", f.max_us),
                    format!("{:.0}", f.rate),
                    format!("{}/{}", f.delivered, p.burst),
                    format!("{}", p.burst.saturating_sub(f.delivered)),
                    cpu_cell(f.cpu_per_100k),
                    cpu_cell(f.cpu_lines.map(|c| c.0)),
                    cpu_cell(f.cpu_lines.map(|c| c.1)),
                ],
            )),
            Err(why) => {
                let mut line = table_line(&name, &vec!["-".to_string(); COLUMNS.len()]);
                line.push_str(&format!("  [{why}]"));
                t.line(line);
            }
        }
    }
}

/// A setup's figures over its rounds: the median of each (rounds that failed left out).
struct Median {
    p50_us: f64,
    p99_us: f64,
    max_us: f64,
    rate: f64,
    cpu_per_100k: Option<f64>,
    cpu_lines: (Option<f64>, Option<f64>),
    /// Burst messages lost over all its rounds, and sent.
    lost: usize,
    sent: usize,
    rounds: usize,
}

fn median(mut v: Vec<f64>) -> Option<f64> {
    v.sort_by(f64::total_cmp);
    match v.len() {
        0 => None,
        n if n % 2 == 1 => Some(v[n / 2]),
        n => Some((v[n / 2 - 1] + v[n / 2]) / 2.0),
    }
}

fn median_of(rows: &[Row], setup: &str, burst: usize) -> Option<Median> {
    let own: Vec<&Figures> = rows
        .iter()
        .filter(|r| r.setup == setup)
        .filter_map(|r| r.result.as_ref().ok())
        .collect();
    let of = |f: fn(&Figures) -> f64| median(own.iter().map(|&x| f(x)).collect());
    Some(Median {
        p50_us: of(|f| f.p50_us)?,
        p99_us: of(|f| f.p99_us)?,
        max_us: of(|f| f.max_us)?,
        rate: of(|f| f.rate)?,
        cpu_per_100k: median(own.iter().filter_map(|f| f.cpu_per_100k).collect()),
        cpu_lines: (
            median(own.iter().filter_map(|f| Some(f.cpu_lines?.0)).collect()),
            median(own.iter().filter_map(|f| Some(f.cpu_lines?.1)).collect()),
        ),
        lost: own.iter().map(|f| burst.saturating_sub(f.delivered)).sum(),
        sent: burst * own.len(),
        rounds: own.len(),
    })
}

fn summary(t: &mut Transcript, rows: &[Row], p: &BridgeParams, took: Duration) {
    let mut setups: Vec<&str> = Vec::new();
    for r in rows {
        if !setups.contains(&r.setup.as_str()) {
            setups.push(&r.setup);
        }
    }
    t.line("");
    if p.rounds > 1 {
        t.line(header_line(&format!("median of {}", p.rounds)));
        for setup in &setups {
            match median_of(rows, setup, p.burst) {
                Some(m) => t.line(table_line(
                    setup,
                    &[
                        format!("{:.0}", m.p50_us),
                        format!("{:.0}", m.p99_us),
                        format!("{:.0}", m.max_us),
                        format!("{:.0}", m.rate),
                        format!("{} rounds", m.rounds),
                        format!("{}", m.lost),
                        cpu_cell(m.cpu_per_100k),
                        cpu_cell(m.cpu_lines.0),
                        cpu_cell(m.cpu_lines.1),
                    ],
                )),
                None => t.line(table_line(setup, &vec!["-".to_string(); COLUMNS.len()])),
            }
        }
        t.line("");
    }
    let one = median_of(rows, "one broker", p.burst);
    for &bus in &p.buses {
        let name = across(bus);
        match (&one, median_of(rows, &name, p.burst)) {
            (Some(one), Some(x)) => t.line(format!(
                "{:<5} hop adds {:.0} us at p50 ({:.0} us at p99); throughput across the bridge = {:.2} x one broker; \
                 lost {} of {}",
                format!("{}:", bus.name()),
                x.p50_us - one.p50_us,
                x.p99_us - one.p99_us,
                x.rate / one.rate,
                x.lost,
                x.sent
            )),
            _ => t.line(format!("{}: n/a (no successful round)", bus.name())),
        }
    }
    for (i, &bus) in p.buses.iter().enumerate() {
        let Some(x) = median_of(rows, &across(bus), p.burst) else {
            continue;
        };
        for &earlier in &p.buses[..i] {
            let Some(base) = median_of(rows, &across(earlier), p.burst) else {
                continue;
            };
            t.line(ratio_line(bus, earlier, &x, &base, p.rounds));
        }
    }
    t.line(format!("({:.0} s)", took.as_secs_f64()));
}

/// `bus/base (A -> B, medians): p50 1.04x  p99 ...`: the figures of `bus` over `base`'s.
fn ratio_line(bus: Bus, base_bus: Bus, x: &Median, base: &Median, rounds: u32) -> String {
    let r = |a: f64, b: f64| {
        if b > 0.0 {
            format!("{:.2}x", a / b)
        } else {
            "n/a".into()
        }
    };
    let cpu = match (x.cpu_per_100k, base.cpu_per_100k) {
        (Some(a), Some(b)) => r(a, b),
        _ => "n/a".into(),
    };
    format!(
        "{}/{} (A -> B{}): p50 {}  p99 {}  max {}  burst msg/s {}  cpu s/100k {}   \
         (latency and CPU: lower is better; msg/s: higher is better)",
        bus.name(),
        base_bus.name(),
        if rounds > 1 { ", medians" } else { "" },
        r(x.p50_us, base.p50_us),
        r(x.p99_us, base.p99_us),
        r(x.max_us, base.max_us),
        r(x.rate, base.rate),
        cpu
    )
}

/// The test PKI of a `tls` or `mtls` bus: a CA and one certificate per line, as PEM files in a
/// temporary directory (removed on drop).
struct Pki {
    dir: tempfile::TempDir,
}

impl Pki {
    fn generate(lines: &[&str]) -> Result<Pki> {
        use rcgen::{
            BasicConstraints, CertificateParams, DnType, ExtendedKeyUsagePurpose, IsCa, KeyPair,
            KeyUsagePurpose,
        };
        let dir = tempfile::Builder::new()
            .prefix("fbbus-loadtest-bus-pki-")
            .tempdir()?;
        let ca_key = KeyPair::generate()?;
        let mut ca_params = CertificateParams::new(Vec::<String>::new())?;
        ca_params.is_ca = IsCa::Ca(BasicConstraints::Unconstrained);
        ca_params
            .distinguished_name
            .push(DnType::CommonName, "fbbus-loadtest bus CA");
        ca_params.key_usages = vec![
            KeyUsagePurpose::KeyCertSign,
            KeyUsagePurpose::DigitalSignature,
        ];
        let ca = ca_params.self_signed(&ca_key)?;
        std::fs::write(dir.path().join("ca.crt"), ca.pem())?;
        for line in lines {
            let key = KeyPair::generate()?;
            let mut params = CertificateParams::new(vec!["localhost".into(), "127.0.0.1".into()])?;
            params.distinguished_name.push(DnType::CommonName, *line);
            params.use_authority_key_identifier_extension = true;
            params.key_usages = vec![KeyUsagePurpose::DigitalSignature];
            params.extended_key_usages = vec![
                ExtendedKeyUsagePurpose::ServerAuth,
                ExtendedKeyUsagePurpose::ClientAuth,
            ];
            let cert = params.signed_by(&key, &ca, &ca_key)?;
            std::fs::write(dir.path().join(format!("{line}.crt")), cert.pem())?;
            std::fs::write(dir.path().join(format!("{line}.key")), key.serialize_pem())?;
        }
        Ok(Pki { dir })
    }

    fn file(&self, name: &str) -> PathBuf {
        self.dir.path().join(name)
    }

    /// `[bridge.tls]` of `line`; with `peer`, mutual TLS and `[bridge.peers]` admitting
    /// that line, else `mutual = false` and no peers.
    fn tables(&self, line: &str, peer: Option<&str>) -> String {
        let mut tables = format!(
            "\n[bridge.tls]\nroot_ca = {:?}\ncert = {:?}\nkey = {:?}\n",
            self.file("ca.crt").display().to_string(),
            self.file(&format!("{line}.crt")).display().to_string(),
            self.file(&format!("{line}.key")).display().to_string(),
        );
        match peer {
            Some(peer) => tables.push_str(&format!("\n[bridge.peers]\nlines = [{peer:?}]\n")),
            None => tables.push_str("mutual = false\n"),
        }
        tables
    }
}

/// Two lines linked by a bus: `line-a` listens, `line-b` connects.
struct Pair {
    a: Running,
    b: Running,
}

impl Pair {
    async fn start(fbbus: &Path, bus: Bus, pki: Option<&Pki>) -> Result<Pair> {
        let port = spawn::free_port()?;
        let (endpoint, a_tls, b_tls) = match bus {
            Bus::Tcp => (
                format!("tcp/127.0.0.1:{port}"),
                String::new(),
                String::new(),
            ),
            Bus::Tls | Bus::Mtls => {
                let pki = pki.context("no certificates were made for the bus")?;
                let mutual = bus == Bus::Mtls;
                (
                    format!("tls/127.0.0.1:{port}"),
                    pki.tables("line-a", mutual.then_some("line-b")),
                    pki.tables("line-b", mutual.then_some("line-a")),
                )
            }
        };
        let a = start(
            fbbus,
            &["line = \"line-a\"".into()],
            &format!("\n[bridge]\nlisten = [\"{endpoint}\"]\n{a_tls}"),
        )
        .await
        .context("line-a")?;
        let b = start(
            fbbus,
            &["line = \"line-b\"".into()],
            &format!("\n[bridge]\nconnect = [\"{endpoint}\"]\n{b_tls}"),
        )
        .await
        .context("line-b")?;
        Ok(Pair { a, b })
    }

    /// A measurement's result, with how a line ended if it did; a failure also with
    /// each line's bridge counters and the end of its log, and both logs copied to
    /// `<out>/<keep>-line-a.log` and `-line-b.log`.
    async fn check(
        mut self,
        result: std::result::Result<Figures, String>,
        out: &Path,
        keep: &str,
    ) -> std::result::Result<Figures, String> {
        let exits: Vec<String> = [("line-a", &mut self.a), ("line-b", &mut self.b)]
            .into_iter()
            .filter_map(|(name, line)| line.exited().map(|e| format!("{name}: {e}")))
            .collect();
        let why = match (result, exits.is_empty()) {
            (r, true) => match r {
                Ok(f) => return Ok(f),
                Err(e) => e,
            },
            (Ok(_), false) => exits.join("; "),
            (Err(e), false) => format!("{e}; {}", exits.join("; ")),
        };
        let mut details = Vec::new();
        for (name, line) in [("line-a", &self.a), ("line-b", &self.b)] {
            let counters = match line.admin {
                Some(admin) => bridge_counters(admin).await,
                None => String::new(),
            };
            details.push(format!("{name}: {counters}; {}", line.log_tail()));
            let copy = out.join(format!("{keep}-{name}.log"));
            let kept = std::fs::create_dir_all(out)
                .and_then(|()| std::fs::copy(line.log_path(), &copy).map(|_| ()));
            if kept.is_ok() {
                details.push(format!("log kept in {}", copy.display()));
            }
        }
        Err(format!("{why} ({})", details.join("; ")))
    }
}

/// The non-zero `fbbus_bridge_*` series of a line's `/metrics`, for a failure's note.
async fn bridge_counters(admin: SocketAddr) -> String {
    let text = loadtest::scrape::get(&format!("http://{admin}/metrics"), Duration::from_secs(5))
        .await
        .unwrap_or_default();
    let series: Vec<&str> = text
        .lines()
        .filter(|l| l.starts_with("fbbus_bridge_"))
        .filter(|l| {
            l.rsplit_once(' ')
                .and_then(|(_, v)| v.parse::<f64>().ok())
                .is_some_and(|v| v != 0.0)
        })
        .collect();
    if series.is_empty() {
        "no bridge counters".into()
    } else {
        series.join(", ")
    }
}

/// user + system CPU ticks of `pid` so far (`/proc/<pid>/stat` fields 14 and 15).
pub(super) fn cpu_ticks(pid: u32) -> Option<u64> {
    let stat = std::fs::read_to_string(format!("/proc/{pid}/stat")).ok()?;
    // The command name (field 2) is in parentheses and may contain spaces.
    let rest = stat.rsplit_once(')')?.1;
    let fields: Vec<&str> = rest.split_whitespace().collect();
    // `rest` starts at field 3 (state): utime is field 14, stime field 15.
    let utime: u64 = fields.get(11)?.parse().ok()?;
    let stime: u64 = fields.get(12)?.parse().ok()?;
    Some(utime + stime)
}

fn cpu_of(brokers: &[&Running]) -> Option<Vec<u64>> {
    brokers.iter().map(|b| cpu_ticks(b.pid())).collect()
}

/// One setup: a device on `publisher`, a subscriber on `subscriber`. With `exporter`, waits
/// until that line's bridge has the subscriber's interest.
async fn measure(
    name: &str,
    publisher: &Running,
    subscriber: &Running,
    exporter: Option<&Running>,
    p: &BridgeParams,
) -> Result<Figures> {
    eprintln!("bridge: {name}");
    let mut dev = mqtt::connect(publisher.addr, DEVICE, None).await?;
    dev.write_all(&mqtt::publish_packet(
        &format!("fbbus/declare/{DEVICE}"),
        INTERFACE.as_bytes(),
    ))
    .await?;
    let admin = publisher.admin.context("fbbus has an admin endpoint")?;
    wait_metric(admin, "fbbus_registry_devices{status=\"online\"}", 1.0).await?;
    let mut sub =
        mqtt::connect(subscriber.addr, &format!("bench-sub-{}", name.len()), None).await?;
    mqtt::subscribe(&mut sub, TOPIC).await?;
    if let Some(exporter) = exporter {
        let admin = exporter.admin.context("fbbus has an admin endpoint")?;
        wait_metric(admin, "fbbus_bridge_remote_subscriptions", 1.0).await?;
    }
    let mut reader = PacketReader::new(sub);
    let packet = mqtt::publish_packet(TOPIC, EVENT.as_bytes());

    // Warm up: until the path delivers (the exporter's router subscription is in place,
    // the importer knows the device from line A's record).
    let warm_deadline = Instant::now() + Duration::from_secs(10);
    loop {
        dev.write_all(&packet).await?;
        if receive(&mut reader, 1, Duration::from_millis(200)).await? == 1 {
            break;
        }
        if Instant::now() > warm_deadline {
            bail!("{name}: nothing delivered in 10 s");
        }
    }
    while receive(&mut reader, 1, Duration::from_millis(200)).await? == 1 {}

    let mut latency = Histogram::<u64>::new(3)?;
    let latency_deadline = Instant::now() + LATENCY_DEADLINE;
    for _ in 0..p.samples {
        let sent = Instant::now();
        dev.write_all(&packet).await?;
        if receive(&mut reader, 1, Duration::from_secs(2)).await? != 1 {
            bail!("{name}: a latency sample was not delivered within 2 s");
        }
        latency.record(sent.elapsed().as_micros() as u64)?;
        if Instant::now() > latency_deadline {
            bail!(
                "{name}: {} latency samples took longer than {LATENCY_DEADLINE:?}",
                p.samples
            );
        }
    }

    let brokers: Vec<&Running> = if std::ptr::eq(publisher, subscriber) {
        vec![publisher]
    } else {
        vec![publisher, subscriber]
    };
    let cpu_before = cpu_of(&brokers);
    let burst: Vec<u8> = packet.repeat(p.burst.min(1_000));
    let first_send = Instant::now();
    let writer = async {
        let mut left = p.burst;
        while left > 0 {
            let n = left.min(1_000);
            dev.write_all(&burst[..n * packet.len()]).await?;
            left -= n;
        }
        Ok::<_, std::io::Error>(dev)
    };
    let (dev, received) = tokio::join!(writer, async {
        let mut got = 0;
        let mut last = first_send;
        let deadline = Instant::now() + BURST_DEADLINE;
        while got < p.burst && Instant::now() < deadline {
            match receive(&mut reader, p.burst - got, Duration::from_secs(2)).await {
                Ok(0) | Err(_) => break,
                Ok(n) => {
                    got += n;
                    last = Instant::now();
                }
            }
        }
        (got, last)
    });
    let cpu_after = cpu_of(&brokers);
    let mut dev = dev?;
    let (delivered, last) = received;
    let _ = dev.write_all(&mqtt::DISCONNECT).await;
    let secs = last.duration_since(first_send).as_secs_f64().max(1e-9);
    // CPU seconds per 100,000 burst messages, per process.
    let cpu: Option<Vec<f64>> = match (cpu_before, cpu_after) {
        (Some(before), Some(after)) if delivered > 0 => Some(
            before
                .iter()
                .zip(&after)
                .map(|(b, a)| {
                    a.saturating_sub(*b) as f64 / TICKS_PER_SECOND * 100_000.0 / p.burst as f64
                })
                .collect(),
        ),
        _ => None,
    };
    let cpu_per_100k = cpu.as_ref().map(|c| c.iter().sum());
    let cpu_lines = match cpu.as_deref() {
        Some(&[a, b]) => Some((a, b)),
        _ => None,
    };
    Ok(Figures {
        p50_us: latency.value_at_quantile(0.5) as f64,
        p99_us: latency.value_at_quantile(0.99) as f64,
        max_us: latency.max() as f64,
        rate: delivered as f64 / secs,
        delivered,
        cpu_per_100k,
        cpu_lines,
    })
}

/// Reads until `want` publications arrived or `quiet` passed without one; returns how many.
async fn receive(reader: &mut PacketReader, want: usize, quiet: Duration) -> Result<usize> {
    let mut got = 0;
    loop {
        while let Some((header, _)) = reader.next_packet()? {
            if header >> 4 == 3 {
                got += 1;
            }
        }
        if got >= want {
            return Ok(got);
        }
        match tokio::time::timeout(quiet, reader.read_more()).await {
            Ok(Ok(0)) => bail!("the broker closed the subscriber"),
            Ok(Ok(_)) => {}
            Ok(Err(e)) => return Err(e.into()),
            Err(_) => return Ok(got),
        }
    }
}

async fn wait_metric(admin: SocketAddr, series: &str, min: f64) -> Result<()> {
    let deadline = Instant::now() + Duration::from_secs(20);
    loop {
        if metric(admin, series).await >= min {
            return Ok(());
        }
        if Instant::now() > deadline {
            bail!("{series} stayed below {min} for 20 s");
        }
        tokio::time::sleep(Duration::from_millis(10)).await;
    }
}

//! `fbbus-loadtest compare`: the earlier broker study's scenarios (and issue 34's QoS 1
//! fan-in and independent pairs) against fbbus, Mosquitto, raw rumqttd and FlashMQ, or
//! against two fbbus builds (before/after a change), in one run, with every figure as a
//! ratio and a summary table (a column per broker, a ratio column per peer). See
//! loadtest/README.md, "compare".
//!
//! Unlike the other scenarios, `compare` starts the brokers itself: every broker is a
//! child process of its own on free 127.0.0.1 ports, freshly started for each scenario
//! ([`loadtest::broker_process::spawn`]; raw rumqttd is this binary re-executed as the
//! hidden `serve-rumqttd` subcommand; FlashMQ its own binary, `--flashmq`), so its resident memory is its own and no scenario
//! inherits another's state. With `--rounds N` each scenario runs N times per broker,
//! alternating (A B A B ...), so machine noise hits every broker alike; the ratios use
//! each broker's median.

mod abuse;
mod auth;
mod bridge;
mod fb;
mod persistence;
mod plant;
mod scenarios;
mod table;

use std::net::SocketAddr;
use std::path::{Path, PathBuf};
use std::time::{Duration, Instant};

use anyhow::{bail, Context as _, Result};
use clap::{Args, Subcommand};

use loadtest::broker_process::spawn::{self, Kind, Running, Spec};
use loadtest::raw_client;
use loadtest::scrape;

use auth::Storm;
use scenarios::{Outcome, Params, Scenario};

/// `fbbus-loadtest compare [fb|bridge] ...`
#[derive(Args)]
#[command(args_conflicts_with_subcommands = true)]
pub struct CompareArgs {
    #[command(subcommand)]
    fbbus_only: Option<FbbusOnly>,
    #[command(flatten)]
    run: RunArgs,
}

#[derive(Subcommand)]
enum FbbusOnly {
    /// fbbus only (issue 21): floods of the registry, re-declarations, admin polling,
    /// slow admin headers, metric labels and retained messages, one phase each, with the
    /// broker's resident memory and descriptors and a well-behaved device's round trip
    /// during each; the goals MET or NOT MET. Writes abuse.txt.
    Abuse {
        /// Short phases (2 s), for a smoke test: the figures are not measurements.
        #[arg(long)]
        quick: bool,
        /// The fbbus binary. Default: `fbbus` next to this binary.
        #[arg(long, value_name = "PATH")]
        fbbus: Option<PathBuf>,
        /// Duration of each phase in seconds (default 10; --quick 2).
        #[arg(long, value_name = "SECONDS")]
        phase_secs: Option<u64>,
        /// The resident-memory goal: the broker's peak VmRSS must stay within this.
        #[arg(long, default_value_t = 256, value_name = "MB")]
        max_rss_mb: u64,
    },
    /// fbbus only: typed-topic validation cost (typed vs untyped burst, A B A B), device
    /// births per second, and registry HTTP query latency with 10,000 devices.
    Fb {
        /// Small sizes (a smoke test, not a measurement).
        #[arg(long)]
        quick: bool,
        /// Devices registered for the births and query measurements (default 10000).
        #[arg(long, value_name = "N")]
        devices: Option<usize>,
        /// The fbbus binary. Default: `fbbus` next to this binary.
        #[arg(long, value_name = "PATH")]
        fbbus: Option<PathBuf>,
    },
    /// fbbus only: the zenoh bridge between two lines: latency p50/p99 and burst
    /// throughput line A -> line B, next to the same on one broker; with `--bus tcp,mtls`
    /// over plain TCP and over mutual TLS with access control, side by side.
    Bridge {
        /// Small sizes (a smoke test, not a measurement).
        #[arg(long)]
        quick: bool,
        /// The fbbus binary. Default: `fbbus` next to this binary.
        #[arg(long, value_name = "PATH")]
        fbbus: Option<PathBuf>,
        /// The bus between the two lines, comma-separated: `tcp` (plain TCP on loopback,
        /// no access control), `tls` (zenoh TLS, `mutual = false`, no access control:
        /// the encryption alone) and `mtls` (zenoh TLS with a certificate on both sides,
        /// CN = the line's name, from a CA made for the run, and `[bridge.peers]` access
        /// control). Each is measured on its own pair of lines; every later one as a ratio
        /// to each earlier one (`mtls/tcp`). Default: tcp.
        #[arg(long, value_delimiter = ',', value_name = "LIST")]
        bus: Vec<String>,
        /// Runs of every setup, alternating setups round by round (one broker, A -> B tcp,
        /// A -> B mtls, one broker, ...); the summary uses each setup's median.
        #[arg(long, default_value_t = 1, value_name = "N")]
        rounds: u32,
        /// Latency samples per setup and round (default 5000; --quick 200).
        #[arg(long, value_name = "N")]
        samples: Option<usize>,
        /// Messages in each burst (default 40000; --quick 2000).
        #[arg(long, value_name = "N")]
        burst: Option<usize>,
    },
    /// fbbus only (issue 32): a plant on one machine: N lines x M devices on one zenoh
    /// bus, two router lines and clients of both (`routers`), a mesh of peers (`peers`),
    /// or clients of two real zenohd routers (`zenohd`), beside the same lines without a
    /// bus (`alone`): registry convergence, a line's local delivery while the bus
    /// federates, a traffic matrix (neighbour, all-to-one, one-to-all: delivered, lost,
    /// latency, CPU per line), and line 1 (zenohd: router 1) killed. Writes plant.txt.
    Plant {
        /// Small sizes (5 lines x 20 devices, 2 s of traffic): a smoke test.
        #[arg(long)]
        quick: bool,
        /// The fbbus binary. Default: `fbbus` next to this binary.
        #[arg(long, value_name = "PATH")]
        fbbus: Option<PathBuf>,
        /// Lines (default 8; --quick 5; at least 3).
        #[arg(long, value_name = "N")]
        lines: Option<usize>,
        /// Devices per line (default 1000; --quick 20).
        #[arg(long, value_name = "M")]
        devices: Option<usize>,
        /// Topologies, comma-separated: alone, routers, redundant, peers, zenohd. Default: all (zenohd
        /// when a zenohd binary is found).
        #[arg(long, value_delimiter = ',', value_name = "LIST")]
        topology: Vec<String>,
        /// Seconds of traffic per pattern (default 6; --quick 2).
        #[arg(long, value_name = "SECONDS")]
        traffic_secs: Option<u64>,
        /// The zenohd binary (1.10) for topology zenohd. Default: target/zenohd/bin/zenohd
        /// (`cargo install zenohd --version 1.10.2 --locked --root target/zenohd`, as
        /// deploy/plant/check.sh does), else `zenohd` on PATH.
        #[arg(long, value_name = "PATH")]
        zenohd: Option<PathBuf>,
        /// Line 3 (the local probe's line) on a core of its own, every other process (the
        /// other lines, the routers, this harness and its devices) on the other cores: a
        /// line on its own host, as in a plant, so that its local p99 shows what its own
        /// share of the bus costs it, not the other lines' work on the same cores.
        #[arg(long)]
        isolate: bool,
    },
    /// fbbus's store (issue 17) beside Mosquitto's persistence: QoS 1 burst throughput and
    /// steady latency into a persistent subscriber with fbbus's persistence off and with
    /// fsync "always", "every 100 ms" (the default) and "os", Mosquitto with persistence
    /// true and false; and the restart time with 100,000 retained messages and 1,000
    /// persistent sessions (SIGTERM, start again on the same store).
    Persistence {
        /// Small sizes (a smoke test, not a measurement).
        #[arg(long)]
        quick: bool,
        /// The fbbus binary. Default: `fbbus` next to this binary.
        #[arg(long, value_name = "PATH")]
        fbbus: Option<PathBuf>,
        /// The mosquitto binary. Default: /usr/sbin/mosquitto, else PATH.
        #[arg(long, value_name = "PATH")]
        mosquitto: Option<PathBuf>,
        /// Brokers to run, comma-separated: fbbus (its four setups), mosquitto (its two).
        /// Default: both.
        #[arg(long, value_delimiter = ',', value_name = "LIST")]
        brokers: Vec<String>,
        /// Measurements, comma-separated: throughput, latency, restart. Default: all.
        #[arg(long, value_delimiter = ',', value_name = "LIST")]
        scenarios: Vec<String>,
        /// Runs of each measurement per setup, alternating setups round by round; the
        /// ratios use each setup's median.
        #[arg(long, default_value_t = 1, value_name = "N")]
        rounds: u32,
        /// QoS 1 messages per publisher in the burst (default 10000; --quick 500).
        #[arg(long, value_name = "N")]
        messages: Option<usize>,
        /// Duration of the steady-rate latency measurement in seconds (default 10; --quick 1).
        #[arg(long, value_name = "SECONDS")]
        latency_secs: Option<u64>,
        /// Retained messages the restart measurement stores (default 100000; --quick 2000).
        #[arg(long, value_name = "N")]
        retained: Option<usize>,
        /// Persistent sessions the restart measurement stores (default 1000; --quick 50).
        #[arg(long, value_name = "N")]
        sessions: Option<usize>,
    },
}

#[derive(Args)]
struct RunArgs {
    /// Scenarios to run, comma-separated: fanin, fanin1, pairs, latency, idlemem, msgmem,
    /// connrate, connect1, authstorm. Default: all.
    #[arg(long, value_delimiter = ',', value_name = "LIST")]
    scenarios: Vec<String>,
    /// Brokers to run, comma-separated: fbbus (every --fbbus binary), mosquitto, rumqttd,
    /// flashmq. Default: all, flashmq only when its binary is found.
    #[arg(long, value_delimiter = ',', value_name = "LIST")]
    brokers: Vec<String>,
    /// Small sizes (a smoke test, not a measurement).
    #[arg(long)]
    quick: bool,
    /// An fbbus binary, optionally named: `--fbbus new=target/release/fbbus`. Repeat it to
    /// compare builds (`--fbbus old=/tmp/fbbus-old --fbbus new=target/release/fbbus`):
    /// the later ones are also reported as ratios to the first. Default: `fbbus` next to
    /// this binary.
    #[arg(long = "fbbus", value_name = "[NAME=]PATH")]
    fbbus: Vec<String>,
    /// The mosquitto binary. Default: /usr/sbin/mosquitto, else PATH.
    #[arg(long, value_name = "PATH")]
    mosquitto: Option<PathBuf>,
    /// The flashmq binary (FlashMQ 1.x, built from github.com/halfgaar/FlashMQ). Default:
    /// `flashmq` on PATH.
    #[arg(long, value_name = "PATH")]
    flashmq: Option<PathBuf>,
    /// Skip the extra Mosquitto run with its shipped `set_tcp_nodelay false` (fanin, latency).
    #[arg(long)]
    no_mosquitto_default: bool,
    /// A line added to FlashMQ's generated `flashmq.conf`, e.g.
    /// `client_max_write_buffer_size 104857600` (its 1 MiB default per client is what makes
    /// it drop most of a QoS 0 fan-in; repeatable).
    #[arg(long = "flashmq-option", value_name = "LINE")]
    flashmq_options: Vec<String>,
    /// Extra `[broker]` key for every fbbus's generated config, e.g.
    /// `router_segment_bytes=1048576` (repeatable; default: fbbus's own defaults).
    #[arg(long = "fbbus-broker-option", value_name = "KEY=VALUE")]
    fbbus_broker_options: Vec<String>,
    /// An ACL file every fbbus serves with (`[auth] acl_file`), to measure the access
    /// checks: it must let the scenarios' anonymous clients use `bench/#`.
    #[arg(long = "fbbus-acl", value_name = "FILE")]
    fbbus_acl: Option<PathBuf>,
    /// Runs of each scenario per broker, alternating brokers round by round (A B A B);
    /// the ratios use each broker's median.
    #[arg(long, default_value_t = 1, value_name = "N")]
    rounds: u32,
    /// Messages per publisher in the fan-in burst (default 20000; --quick 2000).
    #[arg(long, value_name = "N")]
    fanin_messages: Option<usize>,
    /// Messages per publisher in the QoS 1 fan-in, `fanin1` (default 10000; --quick 1000).
    #[arg(long, value_name = "N")]
    fanin1_messages: Option<usize>,
    /// Publisher/subscriber pairs in `pairs` (default 50; --quick 10); the 100,000
    /// messages (--quick 5,000) are shared among them.
    #[arg(long, value_name = "N")]
    pairs: Option<usize>,
    /// Messages per pair in `pairs` (default: the 100,000 shared among the pairs, 2,000
    /// each). 100,000 take 0.1-0.3 s on 2 cores, short enough for one scheduling hiccup
    /// to move a round by 2x; 20,000 per pair (1,000,000) run 1-3 s.
    #[arg(long, value_name = "N")]
    pairs_messages: Option<usize>,
    /// Duration of the steady-rate latency scenario in seconds (default 10; --quick 2).
    #[arg(long, value_name = "SECONDS")]
    latency_secs: Option<u64>,
    /// How the clients reach each broker, comma-separated: tcp (direct), tcp-relay
    /// (through the harness's relay, byte for byte), ws (through the relay, MQTT over
    /// WebSockets to the broker's ws listener). Each broker runs once per transport, as
    /// `<broker>/<transport>`; ws is compared with tcp-relay, which has the same hop
    /// (`loadtest::relay`). Default: tcp.
    #[arg(long, value_delimiter = ',', value_name = "LIST")]
    transport: Vec<String>,
}

/// How a contender's clients reach it (`--transport`).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Transport {
    Tcp,
    TcpRelay,
    WebSocket,
}

impl Transport {
    fn parse(name: &str) -> Result<Transport> {
        Ok(match name.trim() {
            "tcp" => Transport::Tcp,
            "tcp-relay" => Transport::TcpRelay,
            "ws" => Transport::WebSocket,
            other => bail!("unknown transport `{other}` (known: tcp, tcp-relay, ws)"),
        })
    }

    pub fn name(self) -> &'static str {
        match self {
            Transport::Tcp => "tcp",
            Transport::TcpRelay => "tcp-relay",
            Transport::WebSocket => "ws",
        }
    }
}

/// One broker of the comparison: a label in the tables and what to start.
pub struct Contender {
    pub label: String,
    pub kind: Kind,
    pub program: PathBuf,
    /// How its clients reach it; with several transports the label is
    /// `<broker>/<transport>`.
    pub transport: Transport,
    /// Lines added to the peer's own config file (FlashMQ: `--flashmq-option`).
    pub peer_lines: Vec<String>,
}

impl CompareArgs {
    /// The default `--out` directory's last part: `abuse` for `compare abuse`, else
    /// `compare`.
    pub fn scenario_dir(&self) -> &'static str {
        match self.fbbus_only {
            Some(FbbusOnly::Abuse { .. }) => "abuse",
            _ => "compare",
        }
    }
}

/// Runs `compare`; the main comparison's output also goes to `<out>/compare.txt`, `compare
/// bridge`'s to `<out>/bridge.txt`. `inflight` is the global `--inflight`, the QoS 1
/// fan-in's window per publisher.
pub async fn run(args: CompareArgs, out: &Path, inflight: u16) -> Result<()> {
    let harness = std::env::current_exe().context("locating this binary")?;
    let default_fbbus = harness.with_file_name("fbbus");
    match args.fbbus_only {
        Some(FbbusOnly::Abuse {
            quick,
            fbbus,
            phase_secs,
            max_rss_mb,
        }) => {
            let fbbus = existing_fbbus(fbbus.unwrap_or(default_fbbus))?;
            let mut params = if quick {
                abuse::AbuseParams::quick()
            } else {
                abuse::AbuseParams::full()
            };
            if let Some(s) = phase_secs {
                params.phase = Duration::from_secs(s.max(1));
            }
            params.max_rss_mb = max_rss_mb;
            abuse::run(&fbbus, &params, out).await
        }
        Some(FbbusOnly::Fb {
            quick,
            devices,
            fbbus,
        }) => {
            let fbbus = existing_fbbus(fbbus.unwrap_or(default_fbbus))?;
            let mut params = if quick {
                fb::FbParams::quick()
            } else {
                fb::FbParams::full()
            };
            if let Some(n) = devices {
                params.devices = n.max(1);
            }
            fb::run(&fbbus, &params).await
        }
        Some(FbbusOnly::Bridge {
            quick,
            fbbus,
            bus,
            rounds,
            samples,
            burst,
        }) => {
            let buses = bridge::Bus::parse_list(&bus)?;
            let fbbus = existing_fbbus(fbbus.unwrap_or(default_fbbus))?;
            let mut params = if quick {
                bridge::BridgeParams::quick()
            } else {
                bridge::BridgeParams::full()
            };
            params.buses = buses;
            params.rounds = rounds.max(1);
            if let Some(n) = samples {
                params.samples = n.max(1);
            }
            if let Some(n) = burst {
                params.burst = n.max(1);
            }
            bridge::run(&fbbus, &params, out).await
        }
        Some(FbbusOnly::Plant {
            quick,
            fbbus,
            lines,
            devices,
            topology,
            traffic_secs,
            zenohd,
            isolate,
        }) => {
            let fbbus = existing_fbbus(fbbus.unwrap_or(default_fbbus))?;
            let mut params = if quick {
                plant::PlantParams::quick()
            } else {
                plant::PlantParams::full()
            };
            params.zenohd =
                zenohd.or_else(|| spawn::find_program("zenohd", &["target/zenohd/bin/zenohd"]));
            params.topologies = plant::Topology::parse_list(&topology, params.zenohd.is_some())?;
            if let Some(n) = lines {
                params.lines = n;
            }
            if let Some(m) = devices {
                params.devices = m.max(1);
            }
            if let Some(s) = traffic_secs {
                params.traffic = Duration::from_secs(s.max(1));
            }
            params.isolate = isolate;
            plant::run(&fbbus, &params, out).await
        }
        Some(FbbusOnly::Persistence {
            quick,
            fbbus,
            mosquitto,
            brokers,
            scenarios,
            rounds,
            messages,
            latency_secs,
            retained,
            sessions,
        }) => {
            let fbbus = existing_fbbus(fbbus.unwrap_or(default_fbbus))?;
            let mut kinds = Vec::new();
            for name in &brokers {
                let kind = match name.trim() {
                    "fbbus" => Kind::Fbbus,
                    "mosquitto" => Kind::Mosquitto,
                    other => bail!("unknown broker `{other}` (known: fbbus, mosquitto)"),
                };
                if !kinds.contains(&kind) {
                    kinds.push(kind);
                }
            }
            if kinds.is_empty() {
                kinds = vec![Kind::Fbbus, Kind::Mosquitto];
            }
            let mut params = if quick {
                persistence::PersistParams::quick()
            } else {
                persistence::PersistParams::full()
            };
            params.measures = persistence::Measure::parse_list(&scenarios)?;
            params.rounds = rounds.max(1);
            if let Some(n) = messages {
                params.messages = n.max(1);
            }
            if let Some(s) = latency_secs {
                params.latency_secs = s.max(1);
            }
            if let Some(n) = retained {
                params.retained = n.max(1);
            }
            if let Some(n) = sessions {
                params.sessions = n.max(1);
            }
            let mosquitto =
                mosquitto.or_else(|| spawn::find_program("mosquitto", &["/usr/sbin/mosquitto"]));
            persistence::run(&fbbus, mosquitto.as_deref(), &kinds, &params, out).await
        }
        None => compare(args.run, &harness, &default_fbbus, out, inflight).await,
    }
}

fn existing_fbbus(path: PathBuf) -> Result<PathBuf> {
    if !path.is_file() {
        bail!(
            "the fbbus binary is not at {}: build it with `cargo build --release -p broker -p fbbus-loadtest` \
             or pass --fbbus PATH",
            path.display()
        );
    }
    Ok(path)
}

/// Everything printed on stdout, kept for `<out>/compare.txt`.
#[derive(Default)]
struct Transcript(String);

impl Transcript {
    fn line(&mut self, text: impl AsRef<str>) {
        println!("{}", text.as_ref());
        self.0.push_str(text.as_ref());
        self.0.push('\n');
    }

    /// The first lines of a `compare <what>` transcript: the harness, the machine, and the
    /// load it had at the start (other work skews a measurement).
    fn machine_lines(&mut self, what: &str) {
        let m = loadtest::machine::this_machine();
        self.line(format!(
            "fbbus-loadtest compare {what} {}",
            env!("CARGO_PKG_VERSION")
        ));
        self.line(format!(
            "machine:   {} cores, {}, {} MiB RAM, {}",
            m.cpus, m.cpu_model, m.memory_mib, m.os
        ));
        if let Ok(load) = std::fs::read_to_string("/proc/loadavg") {
            let load: Vec<&str> = load.split_whitespace().take(3).collect();
            self.line(format!(
                "load:      {} (1, 5, 15 min, at the start: other work on the machine)",
                load.join(" ")
            ));
        }
    }
}

/// The scenarios asked for, in the canonical order.
fn chosen_scenarios(names: &[String]) -> Result<Vec<Scenario>> {
    if names.is_empty() {
        return Ok(Scenario::ALL.to_vec());
    }
    let mut chosen = Vec::new();
    for name in names {
        let s = Scenario::parse(name.trim()).with_context(|| {
            format!(
                "unknown scenario `{name}` (known: {})",
                Scenario::ALL.map(|s| s.name()).join(", ")
            )
        })?;
        chosen.push(s);
    }
    Ok(Scenario::ALL
        .into_iter()
        .filter(|s| chosen.contains(s))
        .collect())
}

/// `--fbbus [NAME=]PATH` entries as labelled fbbus contenders.
fn fbbus_contenders(entries: &[String], default: &Path) -> Result<Vec<Contender>> {
    if entries.is_empty() {
        return Ok(vec![Contender {
            label: "fbbus".into(),
            kind: Kind::Fbbus,
            program: existing_fbbus(default.to_path_buf())?,
            transport: Transport::Tcp,
            peer_lines: Vec::new(),
        }]);
    }
    let mut out: Vec<Contender> = Vec::new();
    for (i, entry) in entries.iter().enumerate() {
        let (name, path) = match entry.split_once('=') {
            Some((name, path)) if !name.is_empty() && !name.contains('/') => {
                (name.to_owned(), path)
            }
            _ if entries.len() == 1 => ("fbbus".to_owned(), entry.as_str()),
            _ => (format!("fbbus-{}", i + 1), entry.as_str()),
        };
        if ["mosquitto", "rumqttd", "flashmq"].contains(&name.as_str())
            || out.iter().any(|c| c.label == name)
        {
            bail!("--fbbus {entry}: the name `{name}` is taken; give each binary its own name (--fbbus old=PATH --fbbus new=PATH)");
        }
        out.push(Contender {
            label: name,
            kind: Kind::Fbbus,
            program: existing_fbbus(PathBuf::from(path))?,
            transport: Transport::Tcp,
            peer_lines: Vec::new(),
        });
    }
    Ok(out)
}

async fn compare(
    args: RunArgs,
    harness: &Path,
    default_fbbus: &Path,
    out: &Path,
    inflight: u16,
) -> Result<()> {
    let scenarios = chosen_scenarios(&args.scenarios)?;
    let flashmq = args
        .flashmq
        .clone()
        .or_else(|| spawn::find_program("flashmq", &[]));
    let names: Vec<&str> = if args.brokers.is_empty() {
        // FlashMQ is not packaged here (it is built from source): by default it runs
        // where it is found, and the run says when it is not.
        let mut all = vec!["fbbus", "mosquitto", "rumqttd"];
        match &flashmq {
            Some(path) if path.is_file() => all.push("flashmq"),
            Some(path) => eprintln!(
                "flashmq is skipped: {} is not a file (--flashmq PATH)",
                path.display()
            ),
            None => eprintln!(
                "flashmq is skipped: no `flashmq` on PATH (build it, see loadtest/README.md, \
                 and pass --flashmq PATH)"
            ),
        }
        all
    } else {
        args.brokers.iter().map(|b| b.trim()).collect()
    };
    let mut kinds = Vec::new();
    for name in names {
        let kind = match name {
            "fbbus" => Kind::Fbbus,
            "mosquitto" => Kind::Mosquitto,
            "rumqttd" => Kind::Rumqttd,
            "flashmq" => Kind::FlashMq,
            other => {
                bail!("unknown broker `{other}` (known: fbbus, mosquitto, rumqttd, flashmq)")
            }
        };
        if !kinds.contains(&kind) {
            kinds.push(kind);
        }
    }
    for option in &args.fbbus_broker_options {
        let valid = matches!(option.split_once('='), Some((k, v)) if !k.trim().is_empty() && !v.trim().is_empty());
        if !valid {
            bail!("--fbbus-broker-option wants KEY=VALUE, got `{option}`");
        }
    }
    let fbbus_acl = match &args.fbbus_acl {
        Some(file) => Some(
            std::fs::canonicalize(file)
                .with_context(|| format!("--fbbus-acl {}", file.display()))?,
        ),
        None => None,
    };
    let mut params = if args.quick {
        Params::quick()
    } else {
        Params::full()
    };
    if let Some(n) = args.fanin_messages {
        params.fanin_messages = n.max(1);
    }
    if let Some(n) = args.fanin1_messages {
        params.fanin1_messages = n.max(1);
    }
    if let Some(n) = args.pairs {
        // The total stays: `pairs` spreads the same messages over more or fewer pairs.
        let total = params.pairs * params.pairs_messages;
        params.pairs = n.max(1);
        params.pairs_messages = (total / params.pairs).max(1);
    }
    if let Some(n) = args.pairs_messages {
        params.pairs_messages = n.max(1);
    }
    params.inflight = usize::from(inflight.max(1));
    if let Some(s) = args.latency_secs {
        params.latency_secs = s.max(1);
    }
    let rounds = args.rounds.max(1);

    let mosquitto = args
        .mosquitto
        .clone()
        .or_else(|| spawn::find_program("mosquitto", &["/usr/sbin/mosquitto"]));
    let mut contenders = Vec::new();
    for kind in &kinds {
        match kind {
            Kind::Fbbus => contenders.extend(fbbus_contenders(&args.fbbus, default_fbbus)?),
            Kind::Mosquitto => contenders.push(Contender {
                label: "mosquitto".into(),
                kind: Kind::Mosquitto,
                // Missing: every scenario's row says how to install it.
                program: mosquitto
                    .clone()
                    .unwrap_or_else(|| PathBuf::from("mosquitto")),
                transport: Transport::Tcp,
                peer_lines: Vec::new(),
            }),
            Kind::Rumqttd => contenders.push(Contender {
                label: "rumqttd".into(),
                kind: Kind::Rumqttd,
                program: harness.to_path_buf(),
                transport: Transport::Tcp,
                peer_lines: Vec::new(),
            }),
            Kind::FlashMq => contenders.push(Contender {
                label: "flashmq".into(),
                kind: Kind::FlashMq,
                // Missing: every scenario's row says how to get it.
                program: flashmq.clone().unwrap_or_else(|| PathBuf::from("flashmq")),
                transport: Transport::Tcp,
                peer_lines: args.flashmq_options.clone(),
            }),
            Kind::MosquittoDefault => {}
        }
    }
    let transports = match args.transport.is_empty() {
        true => vec![Transport::Tcp],
        false => args
            .transport
            .iter()
            .map(|t| Transport::parse(t))
            .collect::<Result<Vec<_>>>()?,
    };
    if transports != [Transport::Tcp] {
        // One contender per broker and transport, grouped by transport.
        contenders = transports
            .iter()
            .flat_map(|&transport| {
                contenders.iter().map(move |c| Contender {
                    label: format!("{}/{}", c.label, transport.name()),
                    kind: c.kind,
                    program: c.program.clone(),
                    transport,
                    peer_lines: c.peer_lines.clone(),
                })
            })
            .collect();
    }

    let mut t = Transcript::default();
    if let Some(acl) = &fbbus_acl {
        t.line(format!("fbbus serves with the ACL file {}", acl.display()));
    }
    table::header(
        &mut t,
        &contenders,
        mosquitto.as_deref(),
        &scenarios,
        &params,
        args.quick,
        !args.no_mosquitto_default,
        rounds,
    );

    // The storm's password files are made before any broker starts (not measured).
    let mut storm: Option<Storm> = None;
    if scenarios.contains(&Scenario::AuthStorm) {
        let started = Instant::now();
        eprintln!(
            "preparing {} device passwords for the auth storm...",
            params.storm_devices
        );
        storm = Some(auth::prepare(params.storm_devices, &kinds)?);
        eprintln!("  done in {:.1} s", started.elapsed().as_secs_f64());
    }

    let started = Instant::now();
    let mut summary = Vec::new();
    let mut all_rows: Vec<(Scenario, Vec<table::Row>)> = Vec::new();
    let nodelay_off = Contender {
        label: Kind::MosquittoDefault.label().into(),
        kind: Kind::MosquittoDefault,
        program: mosquitto
            .clone()
            .unwrap_or_else(|| PathBuf::from("mosquitto")),
        transport: Transport::Tcp,
        peer_lines: Vec::new(),
    };
    for &scenario in &scenarios {
        let mut runs: Vec<&Contender> = Vec::new();
        for c in &contenders {
            runs.push(c);
            if c.kind == Kind::Mosquitto
                && c.transport == Transport::Tcp
                && !args.no_mosquitto_default
                && matches!(scenario, Scenario::Fanin | Scenario::Latency)
            {
                runs.push(&nodelay_off);
            }
        }
        t.line("");
        t.line(format!("== {} ==", scenario.title(&params)));
        t.line(format!("   {}", scenario.description(&params)));
        let mut rows: Vec<(&Contender, u32, Outcome)> = Vec::new();
        for round in 1..=rounds {
            for &c in &runs {
                eprintln!(
                    "running {} on {} (round {round}/{rounds})...",
                    scenario.name(),
                    c.label
                );
                let outcome = run_one(
                    scenario,
                    c,
                    &args.fbbus_broker_options,
                    fbbus_acl.as_deref(),
                    &params,
                    storm.as_ref(),
                )
                .await;
                rows.push((c, round, outcome));
            }
        }
        table::rows(&mut t, scenario, &rows, rounds);
        let line = table::ratio_line(scenario, &params, &rows, rounds);
        t.line(&line);
        summary.push(line);
        all_rows.push((scenario, rows));
    }
    t.line("");
    t.line(format!(
        "== summary ({:.0} s) ==",
        started.elapsed().as_secs_f64()
    ));
    for line in summary {
        t.line(line);
    }
    t.line("");
    table::summary_table(&mut t, &all_rows, rounds);
    drop(storm);
    std::fs::create_dir_all(out).with_context(|| format!("creating --out {}", out.display()))?;
    let file = out.join("compare.txt");
    std::fs::write(&file, &t.0).with_context(|| format!("writing {}", file.display()))?;
    eprintln!("wrote {}", file.display());
    Ok(())
}

/// A fresh broker for one scenario, stopped afterwards.
async fn run_one(
    scenario: Scenario,
    contender: &Contender,
    fbbus_broker_options: &[String],
    fbbus_acl: Option<&Path>,
    params: &Params,
    storm: Option<&Storm>,
) -> Outcome {
    let auth = match (scenario, storm) {
        (Scenario::AuthStorm, Some(storm)) => Some(storm),
        _ => None,
    };
    if matches!(contender.kind, Kind::Mosquitto | Kind::MosquittoDefault)
        && !contender.program.is_file()
    {
        return Outcome::failed(
            scenario,
            "mosquitto is not installed (apt-get install -y mosquitto, or --mosquitto PATH)".into(),
        );
    }
    if contender.kind == Kind::FlashMq && !contender.program.is_file() {
        return Outcome::failed(
            scenario,
            format!(
                "no flashmq binary at {} (build it, see loadtest/README.md, or --flashmq PATH)",
                contender.program.display()
            ),
        );
    }
    // A WebSocket listener beside the broker's TCP one, for `--transport ws`.
    let ws_port = match contender.transport {
        Transport::WebSocket => match (contender.kind, spawn::free_port()) {
            (Kind::Rumqttd, _) => {
                return Outcome::failed(scenario, "rumqttd is run without websockets".into())
            }
            (Kind::FlashMq, _) => {
                return Outcome::failed(scenario, "flashmq is run without websockets".into())
            }
            (_, Ok(port)) => Some(port),
            (_, Err(e)) => return Outcome::failed(scenario, format!("no free port: {e}")),
        },
        _ => None,
    };
    let ws_table = ws_port.map_or(String::new(), |port| {
        format!("\n[[listener]]\nname = \"ws\"\nkind = \"ws\"\nbind = \"127.0.0.1:{port}\"\n")
    });
    let ws_lines: Vec<String> = ws_port.map_or(Vec::new(), |port| {
        vec![
            format!("listener {port} 127.0.0.1"),
            "protocol websockets".into(),
        ]
    });
    let spec = Spec {
        kind: contender.kind,
        program: &contender.program,
        broker_keys: fbbus_broker_options,
        tables: &ws_table,
        auth: auth.map(|s| &s.files),
        acl: fbbus_acl,
        persistence: None,
        mosquitto_lines: &ws_lines,
        flashmq_lines: &contender.peer_lines,
    };
    let mut broker: Running = match spawn::start(&spec).await {
        Ok(b) => b,
        Err(e) => return Outcome::failed(scenario, format!("failed to start: {e}")),
    };
    // The clients go through the relay: the scenario sees the relay's address.
    let upstream = match (contender.transport, ws_port) {
        (Transport::Tcp, _) => None,
        (Transport::TcpRelay, _) => Some(loadtest::relay::Upstream::Tcp(broker.addr)),
        (Transport::WebSocket, Some(port)) => Some(loadtest::relay::Upstream::WebSocket {
            addr: SocketAddr::from(([127, 0, 0, 1], port)),
            path: "/mqtt".into(),
        }),
        (Transport::WebSocket, None) => None,
    };
    let _relay = match upstream {
        Some(upstream) => match loadtest::relay::start(upstream).await {
            Ok(relay) => {
                broker.addr = relay.addr;
                Some(relay)
            }
            Err(e) => return Outcome::failed(scenario, format!("relay: {e}")),
        },
        None => None,
    };
    // A safety net above the scenario's own deadline.
    let limit = params.deadline * 2 + Duration::from_secs(params.latency_secs + 30);
    let login = auth.map(|s| &s.login);
    let mut outcome = match tokio::time::timeout(limit, scenario.run(&broker, params, login)).await
    {
        Ok(o) => o,
        Err(_) => Outcome::failed(scenario, format!("timeout (no result after {limit:?})")),
    };
    if let Some(exit) = broker.exited() {
        outcome.note = Some(match outcome.note.take() {
            Some(n) => format!("{n}; {exit}"),
            None => exit,
        });
    }
    drop(broker);
    outcome
}

/// The keep-alive every `compare` client announces, for the header.
pub const KEEP_ALIVE_SECS: u16 = raw_client::KEEP_ALIVE_SECS;

/// A fresh fbbus with `broker_keys` in its `[broker]` section and `tables` appended, for
/// the fbbus-only measurements (`compare fb`, `compare bridge`).
async fn start_fbbus(fbbus: &Path, broker_keys: &[String], tables: &str) -> Result<Running> {
    Ok(spawn::start(&Spec {
        kind: Kind::Fbbus,
        program: fbbus,
        broker_keys,
        tables,
        auth: None,
        acl: None,
        persistence: None,
        mosquitto_lines: &[],
        flashmq_lines: &[],
    })
    .await?)
}

/// The value of one Prometheus series on fbbus's admin endpoint (0 when absent or
/// unreadable).
async fn metric(admin: SocketAddr, series: &str) -> f64 {
    let text = scrape::get(&format!("http://{admin}/metrics"), Duration::from_secs(10))
        .await
        .unwrap_or_default();
    series_value(&text, series)
}

/// The value of `series` in a `/metrics` page (0 when it has none).
fn series_value(text: &str, series: &str) -> f64 {
    text.lines()
        .find_map(|l| l.strip_prefix(series)?.trim().parse::<f64>().ok())
        .unwrap_or(0.0)
}

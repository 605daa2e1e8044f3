//! `fbbus-loadtest`: see loadtest/README.md, or `fbbus-loadtest --help`.

mod compare;

use std::path::PathBuf;
use std::process::ExitCode;
use std::time::Duration;

use anyhow::{bail, Context as _, Result};
use clap::{Args, Parser, Subcommand};

use loadtest::rig::RigConfig;
use loadtest::scenario::campaign::Campaign;
use loadtest::scenario::churn::{self, Churn};
use loadtest::scenario::connections::{Idle, Storm};
use loadtest::scenario::conveyor::Conveyor;
use loadtest::scenario::flow::{Flow, FlowKind};
use loadtest::scenario::mutate::Mutate;
use loadtest::scenario::study::{LossSearch, Perf, Stress};
use loadtest::scenario::Scenario;
use loadtest::target::{Mqtt, Target};
use loadtest::{report, Plan};

#[derive(Parser)]
#[command(
    name = "fbbus-loadtest",
    version,
    about = "Throughput, latency and loss of an MQTT broker: the JMeter study's stress, loss-search and perf tests, and more",
    after_help = "The password is read from the environment variable MQTT_PASSWORD or from --password-file, never from the command line.\nExample: fbbus-loadtest --broker mqtt://127.0.0.1:1883 --compare mqtt://127.0.0.1:1884 stress"
)]
struct Cli {
    #[command(flatten)]
    common: Common,
    #[command(subcommand)]
    scenario: Command,
}

#[derive(Args)]
struct Common {
    /// The broker: mqtt://host:port or mqtts://host:port.
    #[arg(
        long,
        global = true,
        default_value = "mqtt://127.0.0.1:1883",
        value_name = "URL"
    )]
    broker: String,
    /// Compare mode: a second broker, run interleaved with the first (A B A B).
    #[arg(long, global = true, value_name = "URL")]
    compare: Option<String>,
    /// Names of the brokers in tables and charts (default: detected).
    #[arg(long, global = true, value_name = "NAME")]
    name: Option<String>,
    #[arg(long, global = true, value_name = "NAME")]
    compare_name: Option<String>,
    /// MQTT username; `{i}` is replaced by the device number in `storm`.
    #[arg(long, global = true)]
    username: Option<String>,
    /// File whose first line is the password (else the MQTT_PASSWORD variable).
    #[arg(long, global = true, value_name = "FILE")]
    password_file: Option<PathBuf>,
    /// CA certificate (PEM) for mqtts:// brokers.
    #[arg(long, global = true, value_name = "FILE")]
    ca: Option<PathBuf>,
    /// MQTT protocol version: 3 (3.1.1) or 5.
    #[arg(long, global = true, default_value_t = 3, value_parser = clap::value_parser!(u8).range(3..=5))]
    mqtt: u8,
    /// QoS of publications and subscriptions.
    #[arg(long, global = true, default_value_t = 0, value_parser = clap::value_parser!(u8).range(0..=2))]
    qos: u8,
    /// Message size in bytes (the study: 30; messages carry seq and a timestamp, so at
    /// least 31).
    #[arg(long, global = true, default_value_t = 30)]
    payload: usize,
    /// QoS 1/2 messages in flight per client.
    #[arg(long, global = true, default_value_t = 100)]
    inflight: u16,
    /// A batch ends after this long without a delivery (ms).
    #[arg(long, global = true, default_value_t = 1000)]
    quiet_ms: u64,
    /// A batch ends after this long in any case (s).
    #[arg(long, global = true, default_value_t = 60)]
    batch_limit_s: u64,
    /// The whole run stops after this long (s); the report says so.
    #[arg(long, global = true, default_value_t = 1800)]
    time_limit_s: u64,
    /// Client ids start with this.
    #[arg(long, global = true, default_value = "lt")]
    prefix: String,
    /// Do not count at an FB subscriber (study tests on fbbus).
    #[arg(long, global = true)]
    no_fb: bool,
    /// Messages for the harness's own ceiling (a trivial in-process sink); 0 skips it.
    #[arg(long, global = true, default_value_t = 20_000)]
    ceiling: u64,
    /// Allow brokers that are not on this machine (not 127.0.0.0/8, ::1, localhost).
    /// Off by default: a load test against a live line's broker can starve its devices.
    #[arg(long, global = true)]
    allow_remote: bool,
    /// Directory for report.json, batches.csv, batches.jtl and the SVG charts (compare:
    /// compare.txt; compare bridge: bridge.txt; compare persistence: persistence.txt;
    /// compare abuse: abuse.txt). Default: `target/loadtest/<scenario>`
    /// (compare abuse: target/loadtest/abuse), outside the source tree.
    #[arg(long, global = true, value_name = "DIR")]
    out: Option<PathBuf>,
}

impl Common {
    /// `--out`, else `target/loadtest/<scenario>` under the working directory.
    fn out_dir(&self, scenario: &str) -> PathBuf {
        self.out
            .clone()
            .unwrap_or_else(|| PathBuf::from("target/loadtest").join(scenario))
    }
}

#[derive(Subcommand)]
enum Command {
    /// The study's stress test: bursts doubling from --start to --max, each --repeats times.
    Stress {
        #[arg(long, default_value_t = 10)]
        start: u64,
        #[arg(long, default_value_t = 5120)]
        max: u64,
        #[arg(long, default_value_t = 5)]
        repeats: u32,
    },
    /// The study's loss mitigation: the largest burst delivered without loss, by search.
    LossSearch {
        #[arg(long, default_value_t = 10)]
        start: u64,
        #[arg(long, default_value_t = 81_920)]
        max: u64,
        #[arg(long, default_value_t = 5)]
        repeats: u32,
        /// Stop when lossless and lossy bursts are this close.
        #[arg(long, default_value_t = 5)]
        resolution: u64,
    },
    /// The study's performance test: batches of 1 .. --max messages, each --repeats times.
    Perf {
        #[arg(long, default_value_t = 1045)]
        max: u64,
        /// How many batch sizes between 1 and --max (evenly spaced).
        #[arg(long, default_value_t = 20)]
        points: u64,
        #[arg(long, default_value_t = 10)]
        repeats: u32,
    },
    /// --clients publishers -> 1 subscriber.
    FanIn(FlowArgs),
    /// 1 publisher -> --clients subscribers.
    FanOut(FlowArgs),
    /// --clients publisher/subscriber pairs, each on its own topic.
    Pairs(FlowArgs),
    /// Publisher on --broker (line A), subscriber on --subscribe-at (line B).
    Bridge {
        #[command(flatten)]
        flow: FlowArgs,
        /// Line B's broker.
        #[arg(long, value_name = "URL")]
        subscribe_at: String,
    },
    /// --connections idle clients (keep-alive 60 s) held for --hold-s; the broker's
    /// memory per connection when it runs on this machine.
    Idle {
        #[arg(long, default_value_t = 1000)]
        connections: usize,
        #[arg(long, default_value_t = 5)]
        hold_s: u64,
        #[arg(long, default_value_t = 1)]
        repeats: u32,
    },
    /// --devices clients connect at once, drop without DISCONNECT and reconnect at once.
    Storm {
        #[arg(long, default_value_t = 1045)]
        devices: usize,
        #[arg(long, default_value_t = 1)]
        repeats: u32,
    },
    /// The simulated conveyor line: --devices fb-bridge devices in a chain pass --parts
    /// parts from the first to the last (fbbus only).
    Conveyor {
        /// Line lengths (comma-separated), each a point on the charts.
        #[arg(long, value_delimiter = ',', default_value = "2,5,10")]
        devices: Vec<usize>,
        #[arg(long, default_value_t = 100)]
        parts: u64,
        /// Parts per second into the first conveyor (default: each after the previous CNF).
        #[arg(long)]
        rate: Option<f64>,
        #[arg(long, default_value_t = 3)]
        repeats: u32,
    },
    /// Random-mutation campaign over the network: --connections connections, each a
    /// CONNECT and a session of packets, every packet mutated with --mutate-prob; the
    /// broker must still route (probe) before, every --probe-every connections and after,
    /// and keep its memory (exit 1 otherwise).
    Mutate {
        #[arg(long, default_value_t = 20_000)]
        connections: u64,
        /// Stop starting connections after this long (e.g. 90s, 5m).
        #[arg(long, default_value = "5m", value_parser = humantime::parse_duration)]
        duration: Duration,
        /// A routing probe after every this many connections (0: before and after only).
        #[arg(long, default_value_t = 5_000)]
        probe_every: u64,
        /// Probability that a packet (CONNECT included) is mutated.
        #[arg(long, default_value_t = 0.15)]
        mutate_prob: f64,
        /// Packets after the CONNECT, at most.
        #[arg(long, default_value_t = 8)]
        max_packets: u64,
        #[command(flatten)]
        campaign: CampaignArgs,
    },
    /// Connection churn: --connections short-lived connections (valid, persistent with new
    /// and recurring ids, abrupt, malformed, abandoned mid-CONNECT; MQTT 3.1.1 and 5); the
    /// broker must still route and keep its memory (exit 1 otherwise).
    Churn {
        #[arg(long, default_value_t = 100_000)]
        connections: u64,
        /// Stop starting connections after this long (e.g. 90s, 10m).
        #[arg(long, default_value = "10m", value_parser = humantime::parse_duration)]
        duration: Duration,
        /// A routing probe after every this many connections (0: before and after only).
        #[arg(long, default_value_t = 10_000)]
        probe_every: u64,
        /// Client ids of the persistent connections that come back.
        #[arg(long, default_value_t = 200)]
        recurring_ids: u64,
        /// Weights of the kinds of connection, e.g. `persistent_random=1` (kinds not named:
        /// 0). Default: valid=25, pipelined=5, persistent_random=15, persistent_recurring=15,
        /// abrupt=15, malformed=10, abandoned=15.
        #[arg(long, default_value = "", hide_default_value = true)]
        mix: String,
        #[command(flatten)]
        campaign: CampaignArgs,
    },
    /// Writes the table, CSV, JTL and charts again from an earlier run's report.json
    /// (into --out, default: the report's own directory).
    Render {
        #[arg(value_name = "REPORT_JSON")]
        report: PathBuf,
    },
    /// fbbus beside Mosquitto, raw rumqttd and FlashMQ, or two fbbus builds, on brokers it
    /// starts
    ///
    /// The earlier broker study's scenarios (fan-in, latency, idle memory, memory after
    /// 1M messages, connection rate, auth storm), the fan-in at QoS 1 and independent
    /// pairs, on brokers this command starts itself on loopback, with ratios and a summary
    /// table (FlashMQ where `--flashmq PATH` or PATH has it). Two builds: `--brokers fbbus --fbbus old=PATH --fbbus
    /// new=PATH --rounds 3` (alternating, ratio new/old). `compare fb` and `compare
    /// bridge`: fbbus's typed topics, registry and bridge (`--bus tcp,mtls`: plain TCP
    /// vs mutual TLS with access control).
    Compare(Box<compare::CompareArgs>),
    /// Internal (`compare bridge`): a zenoh peer on 127.0.0.1:PORT that answers pings,
    /// until standard input closes (`loadtest::zenoh_floor`).
    #[command(hide = true)]
    ZenohPong {
        #[arg(long)]
        port: u16,
    },
    /// Internal (`compare`): run raw rumqttd 0.20 on 127.0.0.1:PORT until killed.
    #[command(hide = true)]
    ServeRumqttd {
        #[arg(long)]
        port: u16,
        /// `user:password` lines for rumqttd's static auth map.
        #[arg(long)]
        auth_file: Option<PathBuf>,
        /// Exit when standard input closes (the harness died).
        #[arg(long)]
        exit_on_stdin_eof: bool,
    },
}

/// What `mutate` and `churn` share.
#[derive(Args)]
struct CampaignArgs {
    /// Connections in progress at once.
    #[arg(long, default_value_t = 64)]
    concurrency: usize,
    /// Seed of every connection's generator: the same seed sends the same packets.
    #[arg(long, default_value_t = 1)]
    seed: u64,
    /// Wait for whatever the broker answers a mutated or malformed packet, and for it to
    /// close after DISCONNECT (ms).
    #[arg(long, default_value_t = 100)]
    read_ms: u64,
    /// Wait for the CONNACK of a valid CONNECT (ms).
    #[arg(long, default_value_t = 5000)]
    connack_ms: u64,
    /// A probe message must arrive within this (ms).
    #[arg(long, default_value_t = 5000)]
    probe_timeout_ms: u64,
    /// Idle time after the campaign before the last memory reading and probe (s).
    #[arg(long, default_value_t = 15)]
    settle_s: u64,
    /// Fail when resident memory after the settle exceeds this times the memory before.
    #[arg(long, default_value_t = 2.0)]
    max_rss_ratio: f64,
    /// The broker's process id (default: the process listening on the broker's port,
    /// when it runs on this machine).
    #[arg(long)]
    pid: Option<u32>,
    /// The second broker's process id (compare mode).
    #[arg(long)]
    compare_pid: Option<u32>,
    /// The broker's Prometheus endpoint, read before, after and after the settle
    /// (e.g. http://127.0.0.1:9883/metrics).
    #[arg(long, value_name = "URL")]
    metrics: Option<String>,
    /// The second broker's Prometheus endpoint (compare mode).
    #[arg(long, value_name = "URL")]
    compare_metrics: Option<String>,
    /// Connect every campaign connection from 127.0.0.1 (by default they come from
    /// 127.0.0.2-127.0.0.33 when the broker is on 127.0.0.1, so their failed logins never
    /// throttle the probe's address).
    #[arg(long)]
    no_spread_sources: bool,
}

impl CampaignArgs {
    fn campaign(&self, connections: u64, duration: Duration, probe_every: u64) -> Campaign {
        Campaign {
            connections,
            concurrency: self.concurrency.max(1),
            duration_s: duration.as_secs().max(1),
            seed: self.seed,
            probe_every,
            read_ms: self.read_ms,
            connack_ms: self.connack_ms,
            probe_timeout_ms: self.probe_timeout_ms,
            settle_s: self.settle_s,
            max_rss_ratio: self.max_rss_ratio,
            pids: vec![self.pid, self.compare_pid],
            metrics: vec![self.metrics.clone(), self.compare_metrics.clone()],
            spread_sources: !self.no_spread_sources,
        }
    }
}

#[derive(Args)]
struct FlowArgs {
    #[arg(long, default_value_t = 10)]
    clients: usize,
    /// Messages per publisher per batch.
    #[arg(long, default_value_t = 10_000)]
    messages: u64,
    /// Open-loop rate(s), messages/s over all publishers (comma-separated); without it
    /// each batch is a closed-loop burst.
    #[arg(long, value_delimiter = ',')]
    rate: Vec<f64>,
    #[arg(long, default_value_t = 3)]
    repeats: u32,
}

fn main() -> ExitCode {
    let cli = Cli::parse();
    if let Command::ServeRumqttd {
        port,
        auth_file,
        exit_on_stdin_eof,
    } = &cli.scenario
    {
        // rumqttd runs its own threads and runtimes: no tokio runtime of ours around it.
        return match loadtest::broker_process::rumqttd::serve(
            *port,
            auth_file.as_deref(),
            *exit_on_stdin_eof,
        ) {
            Ok(()) => ExitCode::SUCCESS,
            Err(e) => {
                eprintln!("fbbus-loadtest serve-rumqttd: {e}");
                ExitCode::FAILURE
            }
        };
    }
    if let Command::ZenohPong { port } = &cli.scenario {
        return match loadtest::zenoh_floor::serve_pong(*port) {
            Ok(()) => ExitCode::SUCCESS,
            Err(e) => {
                eprintln!("fbbus-loadtest zenoh-pong: {e:#}");
                ExitCode::FAILURE
            }
        };
    }
    // mqtts:// targets: one crypto provider for the whole process (see Cargo.toml).
    let _ = rustls::crypto::ring::default_provider().install_default();
    let runtime = tokio::runtime::Builder::new_multi_thread()
        .enable_all()
        .build()
        .expect("a tokio runtime");
    match runtime.block_on(run(cli)) {
        Ok(()) => ExitCode::SUCCESS,
        Err(e) => {
            eprintln!("fbbus-loadtest: {e:#}");
            ExitCode::FAILURE
        }
    }
}

async fn run(cli: Cli) -> Result<()> {
    let c = &cli.common;
    let scenario = match cli.scenario {
        Command::Compare(args) => {
            let out = c.out_dir(args.scenario_dir());
            return compare::run(*args, &out, c.inflight).await;
        }
        other => other,
    };
    if let Command::Render { report: path } = &scenario {
        return render(path, c);
    }
    let password = password(c)?;
    let target = |url: &str| -> Result<Target> {
        let mut t = Target::parse(url)?;
        t.ca = c.ca.clone();
        t.username = c.username.clone();
        t.password = password.clone();
        t.mqtt = if c.mqtt == 5 { Mqtt::V5 } else { Mqtt::V311 };
        Ok(t)
    };
    let mut targets = vec![target(&c.broker)?];
    if let Some(b) = &c.compare {
        targets.push(target(b)?);
    }
    for t in &targets {
        refuse_remote(t, c.allow_remote)?;
    }
    let mut subscribe_at = None;
    let flow = |kind, a: &FlowArgs| {
        Scenario::Flow(Flow {
            kind,
            clients: a.clients,
            messages: a.messages,
            rates: a.rate.clone(),
            repeats: a.repeats,
        })
    };
    let scenario = match &scenario {
        Command::Stress {
            start,
            max,
            repeats,
        } => Scenario::Stress(Stress {
            start: *start,
            max: *max,
            repeats: *repeats,
        }),
        Command::LossSearch {
            start,
            max,
            repeats,
            resolution,
        } => Scenario::LossSearch(LossSearch {
            start: *start,
            max: *max,
            repeats: *repeats,
            resolution: *resolution,
        }),
        Command::Perf {
            max,
            points,
            repeats,
        } => Scenario::Perf(Perf {
            max: *max,
            points: *points,
            repeats: *repeats,
        }),
        Command::FanIn(a) => flow(FlowKind::FanIn, a),
        Command::FanOut(a) => flow(FlowKind::FanOut, a),
        Command::Pairs(a) => flow(FlowKind::Pairs, a),
        Command::Bridge {
            flow: a,
            subscribe_at: b,
        } => {
            if c.compare.is_some() {
                bail!("bridge measures line A -> line B; --compare does not apply");
            }
            let b = target(b)?;
            refuse_remote(&b, c.allow_remote)?;
            subscribe_at = Some(b);
            flow(FlowKind::Bridge, a)
        }
        Command::Idle {
            connections,
            hold_s,
            repeats,
        } => Scenario::Idle(Idle {
            connections: *connections,
            hold_s: *hold_s,
            repeats: *repeats,
        }),
        Command::Storm { devices, repeats } => Scenario::Storm(Storm {
            devices: *devices,
            repeats: *repeats,
        }),
        Command::Mutate {
            connections,
            duration,
            probe_every,
            mutate_prob,
            max_packets,
            campaign,
        } => Scenario::Mutate(Mutate {
            campaign: campaign.campaign(*connections, *duration, *probe_every),
            mutate_prob: mutate_prob.clamp(0.0, 1.0),
            max_packets: *max_packets,
        }),
        Command::Churn {
            connections,
            duration,
            probe_every,
            recurring_ids,
            mix,
            campaign,
        } => Scenario::Churn(Churn {
            campaign: campaign.campaign(*connections, *duration, *probe_every),
            recurring_ids: *recurring_ids,
            mix: churn::parse_mix(mix).map_err(|e| anyhow::anyhow!("--mix {e}"))?,
        }),
        Command::Render { .. }
        | Command::Compare(_)
        | Command::ServeRumqttd { .. }
        | Command::ZenohPong { .. } => {
            unreachable!("handled above")
        }
        Command::Conveyor {
            devices,
            parts,
            rate,
            repeats,
        } => Scenario::Conveyor(Conveyor {
            devices: devices.clone(),
            parts: *parts,
            rate: *rate,
            repeats: *repeats,
        }),
    };
    let message_scenario = !matches!(
        scenario,
        Scenario::Idle(_)
            | Scenario::Storm(_)
            | Scenario::Conveyor(_)
            | Scenario::Mutate(_)
            | Scenario::Churn(_)
    );
    let plan = Plan {
        targets,
        names: vec![c.name.clone(), c.compare_name.clone()],
        subscribe_at,
        scenario,
        rig: RigConfig {
            qos: c.qos,
            payload: c.payload,
            prefix: c.prefix.clone(),
            inflight: c.inflight,
            quiet: Duration::from_millis(c.quiet_ms),
            batch_limit: Duration::from_secs(c.batch_limit_s),
            timeout: Duration::from_secs(10),
        },
        fb: !c.no_fb,
        ceiling_messages: (message_scenario && c.ceiling > 0).then_some(c.ceiling),
        time_limit: Duration::from_secs(c.time_limit_s),
        command: std::env::args().collect::<Vec<_>>().join(" "),
    };
    let out = c.out_dir(&plan.scenario.name());
    let report = loadtest::run(&plan).await?;
    print!("{}", report::table(&report));
    clear_old_outputs(&out);
    let files = report::write_all(&report, &out)?;
    println!("\nwrote {} files to {}", files.len(), out.display());
    if !report.failures.is_empty() {
        bail!(
            "{} failed:\n  {}",
            report.scenario,
            report.failures.join("\n  ")
        );
    }
    Ok(())
}

/// A load test can starve a live line's devices: a broker on another host needs
/// --allow-remote.
fn refuse_remote(t: &Target, allow_remote: bool) -> Result<()> {
    if !t.is_loopback() && !allow_remote {
        bail!(
            "{} is not on this machine: loading a live line's broker can starve its devices; \
             if this broker is yours to load (a test line, a staging broker), add --allow-remote",
            t.address
        );
    }
    Ok(())
}

/// `render`: the outputs of a recorded run, from its report.json.
fn render(path: &std::path::Path, c: &Common) -> Result<()> {
    let text = std::fs::read_to_string(path).with_context(|| format!("{}", path.display()))?;
    let report: loadtest::model::Report = serde_json::from_str(&text)
        .with_context(|| format!("{}: not a fbbus-loadtest report.json", path.display()))?;
    let out = match &c.out {
        Some(out) => out.clone(),
        None => path
            .parent()
            .map_or_else(|| c.out_dir(&report.scenario), |p| p.to_path_buf()),
    };
    print!("{}", report::table(&report));
    clear_old_outputs(&out);
    let files = report::write_all(&report, &out)?;
    println!("\nwrote {} files to {}", files.len(), out.display());
    Ok(())
}

/// Removes an earlier run's outputs from `dir`, so no chart of another scenario is left
/// next to this run's. Only the harness's own files: report.json, batches.*, *.svg.
fn clear_old_outputs(dir: &std::path::Path) {
    let Ok(entries) = std::fs::read_dir(dir) else {
        return;
    };
    for entry in entries.flatten() {
        let name = entry.file_name().to_string_lossy().into_owned();
        let ours = name == report::JSON_FILE
            || name == report::CSV_FILE
            || name == report::JTL_FILE
            || name.ends_with(".svg");
        if ours {
            let _ = std::fs::remove_file(entry.path());
        }
    }
}

/// From --password-file or MQTT_PASSWORD; never from the command line.
fn password(c: &Common) -> Result<Option<String>> {
    if let Some(file) = &c.password_file {
        let text = std::fs::read_to_string(file)
            .with_context(|| format!("--password-file {}", file.display()))?;
        let line = text.lines().next().unwrap_or_default().to_owned();
        if line.is_empty() {
            bail!(
                "--password-file {}: the first line is empty",
                file.display()
            );
        }
        return Ok(Some(line));
    }
    Ok(std::env::var("MQTT_PASSWORD")
        .ok()
        .filter(|p| !p.is_empty()))
}

//! `fbbus-bench`: runs the same load scenarios against fbbus, Mosquitto and raw rumqttd in
//! one run and prints each figure with the ratios fbbus/Mosquitto and fbbus/rumqttd.
//! See bench/README.md.
//!
//! Every broker is a child process of its own on free 127.0.0.1 ports (raw rumqttd is this
//! binary re-executed as the hidden `serve-rumqttd` subcommand); every client is a minimal
//! MQTT 3.1.1 client on this process's multi-thread tokio runtime.

mod bridge;
mod brokers;
mod fb;
mod mqtt;
mod scenarios;

use std::path::{Path, PathBuf};
use std::process::ExitCode;
use std::sync::Arc;
use std::time::{Duration, Instant};

use anyhow::{bail, Context as _, Result};
use clap::{Args, Parser, Subcommand};

use brokers::{AuthFiles, BrokerKind, Programs};
use scenarios::{Outcome, Params, Scenario, Users};

/// The auth storm's users and password files (in a temporary directory).
struct Storm {
    _dir: tempfile::TempDir,
    files: AuthFiles,
    users: Users,
}

#[derive(Parser)]
#[command(
    name = "fbbus-bench",
    version,
    about = "Benchmarks fbbus against Mosquitto and raw rumqttd on this machine (loopback only)",
    args_conflicts_with_subcommands = true
)]
struct Cli {
    #[command(subcommand)]
    command: Option<Command>,
    #[command(flatten)]
    run: RunArgs,
}

#[derive(Subcommand)]
enum Command {
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
    /// throughput line A -> line B, next to the same on one broker.
    Bridge {
        /// Small sizes (a smoke test, not a measurement).
        #[arg(long)]
        quick: bool,
        /// The fbbus binary. Default: `fbbus` next to this binary.
        #[arg(long, value_name = "PATH")]
        fbbus: Option<PathBuf>,
    },
    /// Internal: run raw rumqttd 0.20 on 127.0.0.1:PORT until killed.
    #[command(hide = true)]
    ServeRumqttd {
        #[arg(long)]
        port: u16,
        /// `user:password` lines for rumqttd's static auth map.
        #[arg(long)]
        auth_file: Option<PathBuf>,
        /// Exit when standard input closes (the bench died).
        #[arg(long)]
        exit_on_stdin_eof: bool,
    },
}

#[derive(Args)]
struct RunArgs {
    /// Scenarios to run, comma-separated: fanin, latency, idlemem, msgmem, connrate, authstorm.
    /// Default: all.
    #[arg(long, value_delimiter = ',', value_name = "LIST")]
    scenarios: Vec<String>,
    /// Brokers to run, comma-separated: fbbus, mosquitto, rumqttd. Default: all.
    #[arg(long, value_delimiter = ',', value_name = "LIST")]
    brokers: Vec<String>,
    /// Small sizes (a smoke test, not a measurement).
    #[arg(long)]
    quick: bool,
    /// The fbbus binary. Default: `fbbus` next to this binary.
    #[arg(long, value_name = "PATH")]
    fbbus: Option<PathBuf>,
    /// The mosquitto binary. Default: /usr/sbin/mosquitto, else PATH.
    #[arg(long, value_name = "PATH")]
    mosquitto: Option<PathBuf>,
    /// Skip the extra Mosquitto run with its shipped `set_tcp_nodelay false` (fanin, latency).
    #[arg(long)]
    no_mosquitto_default: bool,
    /// Extra `[broker]` key for fbbus's generated config, e.g. `router_segment_bytes=1048576`
    /// (repeatable; default: fbbus's own defaults).
    #[arg(long = "fbbus-broker-option", value_name = "KEY=VALUE")]
    fbbus_broker_options: Vec<String>,
    /// Messages per publisher in the fan-in burst (default 20000; --quick 2000).
    #[arg(long, value_name = "N")]
    fanin_messages: Option<usize>,
    /// Duration of the steady-rate latency scenario in seconds (default 10; --quick 2).
    #[arg(long, value_name = "SECONDS")]
    latency_secs: Option<u64>,
}

fn main() -> ExitCode {
    let cli = Cli::parse();
    let result = match cli.command {
        Some(Command::ServeRumqttd {
            port,
            auth_file,
            exit_on_stdin_eof,
        }) => brokers::serve_rumqttd(port, auth_file.as_deref(), exit_on_stdin_eof),
        Some(Command::Fb {
            quick,
            devices,
            fbbus,
        }) => tokio::runtime::Builder::new_multi_thread()
            .enable_all()
            .build()
            .context("starting the tokio runtime")
            .and_then(|rt| rt.block_on(run_fb(quick, devices, fbbus))),
        Some(Command::Bridge { quick, fbbus }) => tokio::runtime::Builder::new_multi_thread()
            .enable_all()
            .build()
            .context("starting the tokio runtime")
            .and_then(|rt| rt.block_on(run_bridge(quick, fbbus))),
        None => tokio::runtime::Builder::new_multi_thread()
            .enable_all()
            .build()
            .context("starting the tokio runtime")
            .and_then(|rt| rt.block_on(run(cli.run))),
    };
    match result {
        Ok(()) => ExitCode::SUCCESS,
        Err(e) => {
            eprintln!("fbbus-bench: {e:#}");
            ExitCode::FAILURE
        }
    }
}

async fn run_fb(quick: bool, devices: Option<usize>, fbbus: Option<PathBuf>) -> Result<()> {
    let bench = std::env::current_exe().context("locating this binary")?;
    let fbbus = fbbus.unwrap_or_else(|| bench.with_file_name("fbbus"));
    if !fbbus.is_file() {
        bail!(
            "the fbbus binary is not at {}: build it with `cargo build --release -p broker -p fbbus-bench` or pass --fbbus PATH",
            fbbus.display()
        );
    }
    let mut params = if quick {
        fb::FbParams::quick()
    } else {
        fb::FbParams::full()
    };
    if let Some(n) = devices {
        params.devices = n.max(1);
    }
    let programs = Programs {
        fbbus,
        fbbus_broker_options: Vec::new(),
        mosquitto: None,
        mosquitto_passwd: None,
        bench,
    };
    fb::run(&programs, &params).await
}

async fn run_bridge(quick: bool, fbbus: Option<PathBuf>) -> Result<()> {
    let bench = std::env::current_exe().context("locating this binary")?;
    let fbbus = fbbus.unwrap_or_else(|| bench.with_file_name("fbbus"));
    if !fbbus.is_file() {
        bail!(
            "the fbbus binary is not at {}: build it with `cargo build --release -p broker -p fbbus-bench` or pass --fbbus PATH",
            fbbus.display()
        );
    }
    let params = if quick {
        bridge::BridgeParams::quick()
    } else {
        bridge::BridgeParams::full()
    };
    let programs = Programs {
        fbbus,
        fbbus_broker_options: Vec::new(),
        mosquitto: None,
        mosquitto_passwd: None,
        bench,
    };
    bridge::run(&programs, &params).await
}

/// rumqttd's version as resolved in the workspace's Cargo.lock.
fn rumqttd_version() -> &'static str {
    const LOCK: &str = include_str!("../../Cargo.lock");
    LOCK.split("[[package]]")
        .find(|p| p.contains("\nname = \"rumqttd\"\n"))
        .and_then(|p| p.lines().find_map(|l| l.strip_prefix("version = ")))
        .map(|v| v.trim_matches('"'))
        .unwrap_or("0.20")
}

fn read_first(path: &str, key: Option<&str>) -> String {
    let text = std::fs::read_to_string(path).unwrap_or_default();
    let line = match key {
        Some(key) => text
            .lines()
            .find(|l| l.starts_with(key))
            .and_then(|l| l.split_once(':'))
            .map(|(_, v)| v.trim().to_string()),
        None => text.lines().next().map(|l| l.trim().to_string()),
    };
    line.unwrap_or_else(|| "unknown".into())
}

async fn run(args: RunArgs) -> Result<()> {
    let scenarios: Vec<Scenario> = if args.scenarios.is_empty() {
        Scenario::ALL.to_vec()
    } else {
        let mut chosen = Vec::new();
        for name in &args.scenarios {
            let s = Scenario::parse(name.trim()).with_context(|| {
                format!(
                    "unknown scenario `{name}` (known: {})",
                    Scenario::ALL.map(|s| s.name()).join(", ")
                )
            })?;
            if !chosen.contains(&s) {
                chosen.push(s);
            }
        }
        // Always in the canonical order.
        Scenario::ALL
            .into_iter()
            .filter(|s| chosen.contains(s))
            .collect()
    };
    let mut selected = Vec::new();
    let names: Vec<&str> = if args.brokers.is_empty() {
        vec!["fbbus", "mosquitto", "rumqttd"]
    } else {
        args.brokers.iter().map(|b| b.trim()).collect()
    };
    for name in names {
        let kind = match name {
            "fbbus" => BrokerKind::Fbbus,
            "mosquitto" => BrokerKind::Mosquitto,
            "rumqttd" => BrokerKind::Rumqttd,
            other => bail!("unknown broker `{other}` (known: fbbus, mosquitto, rumqttd)"),
        };
        if !selected.contains(&kind) {
            selected.push(kind);
        }
    }
    let mut params = if args.quick {
        Params::quick()
    } else {
        Params::full()
    };
    if let Some(n) = args.fanin_messages {
        params.fanin_messages = n.max(1);
    }
    if let Some(s) = args.latency_secs {
        params.latency_secs = s.max(1);
    }

    let bench = std::env::current_exe().context("locating this binary")?;
    let fbbus = match &args.fbbus {
        Some(p) => p.clone(),
        None => bench.with_file_name("fbbus"),
    };
    if selected.contains(&BrokerKind::Fbbus) && !fbbus.is_file() {
        bail!(
            "the fbbus binary is not at {}: build it with `cargo build --release -p broker -p fbbus-bench` \
             or pass --fbbus PATH",
            fbbus.display()
        );
    }
    let mosquitto = match &args.mosquitto {
        Some(p) => Some(p.clone()),
        None => brokers::find_program("mosquitto", &["/usr/sbin/mosquitto"]),
    };
    for option in &args.fbbus_broker_options {
        let valid = matches!(option.split_once('='), Some((k, v)) if !k.trim().is_empty() && !v.trim().is_empty());
        if !valid {
            bail!("--fbbus-broker-option wants KEY=VALUE, got `{option}`");
        }
    }
    let programs = Programs {
        fbbus_broker_options: args.fbbus_broker_options.clone(),
        fbbus,
        mosquitto_passwd: brokers::find_program("mosquitto_passwd", &["/usr/bin/mosquitto_passwd"]),
        mosquitto,
        bench,
    };

    print_header(&programs, &selected, &scenarios, &params, &args);

    // The storm's password files are made before any broker starts (not measured).
    let mut storm: Option<Storm> = None;
    if scenarios.contains(&Scenario::AuthStorm) {
        let t = Instant::now();
        eprintln!(
            "preparing {} device passwords for the auth storm...",
            params.storm_devices
        );
        let prepared = prepare_auth(params.storm_devices, &selected, &programs)?;
        eprintln!("  done in {:.1} s", t.elapsed().as_secs_f64());
        storm = Some(prepared);
    }

    let started = Instant::now();
    let mut summary = Vec::new();
    for &scenario in &scenarios {
        let mut kinds = Vec::new();
        for &kind in &selected {
            kinds.push(kind);
            if kind == BrokerKind::Mosquitto
                && !args.no_mosquitto_default
                && matches!(scenario, Scenario::Fanin | Scenario::Latency)
            {
                kinds.push(BrokerKind::MosquittoDefault);
            }
        }
        println!();
        println!("== {} ==", scenario.title(&params));
        println!("   {}", scenario.description(&params));
        let mut rows = Vec::new();
        for &kind in &kinds {
            eprintln!("running {} on {kind}...", scenario.name());
            let auth = match (scenario, &storm) {
                (Scenario::AuthStorm, Some(storm)) => Some((&storm.files, storm.users.clone())),
                _ => None,
            };
            let outcome = run_one(scenario, kind, &programs, &params, auth).await;
            rows.push((kind, outcome));
        }
        print_table(scenario, &rows);
        let line = ratio_line(scenario, &params, &rows);
        println!("{line}");
        summary.push(line);
    }
    println!();
    println!("== summary ({:.0} s) ==", started.elapsed().as_secs_f64());
    for line in summary {
        println!("{line}");
    }
    drop(storm);
    Ok(())
}

/// A fresh broker for one scenario, stopped afterwards.
async fn run_one(
    scenario: Scenario,
    kind: BrokerKind,
    programs: &Programs,
    params: &Params,
    auth: Option<(&AuthFiles, Users)>,
) -> Outcome {
    let mut broker = match brokers::start(kind, programs, auth.as_ref().map(|a| a.0)).await {
        Ok(b) => b,
        Err(e) => return Outcome::failed(scenario, format!("failed to start: {e:#}")),
    };
    // A safety net above the scenario's own deadline.
    let limit = params.deadline * 2 + Duration::from_secs(params.latency_secs + 30);
    let mut outcome =
        match tokio::time::timeout(limit, scenario.run(&broker, params, auth.map(|a| a.1))).await {
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

fn print_header(
    programs: &Programs,
    selected: &[BrokerKind],
    scenarios: &[Scenario],
    p: &Params,
    args: &RunArgs,
) {
    println!("fbbus-bench {}", env!("CARGO_PKG_VERSION"));
    println!(
        "machine:   {} cores, {}, {} RAM",
        std::thread::available_parallelism()
            .map(|n| n.get())
            .unwrap_or(0),
        read_first("/proc/cpuinfo", Some("model name")),
        read_first("/proc/meminfo", Some("MemTotal")),
    );
    println!("kernel:    {}", read_first("/proc/version", None));
    if selected.contains(&BrokerKind::Fbbus) {
        println!(
            "fbbus:     {} ({}; config defaults, [log] level = \"warn\", max_connections 10010{})",
            brokers::fbbus_version(&programs.fbbus),
            programs.fbbus.display(),
            programs
                .fbbus_broker_options
                .iter()
                .map(|o| format!(", {o}"))
                .collect::<String>()
        );
    }
    if selected.contains(&BrokerKind::Mosquitto) {
        match &programs.mosquitto {
            Some(m) => println!(
                "mosquitto: {} ({}; set_tcp_nodelay true, max_queued_messages 100000, persistence false{})",
                brokers::mosquitto_version(m),
                m.display(),
                if args.no_mosquitto_default {
                    ""
                } else {
                    "; fanin and latency also with the shipped set_tcp_nodelay false"
                }
            ),
            None => println!("mosquitto: not installed (apt-get install -y mosquitto)"),
        }
    }
    if selected.contains(&BrokerKind::Rumqttd) {
        println!(
            "rumqttd:   {} raw (library in a child process; rumqttd.toml example values: router max_connections 10010, \
             max_outgoing_packet_count 200, segments 100 MiB x 10; max_inflight_count 100, next_connection_delay_ms 1)",
            rumqttd_version()
        );
    }
    println!(
        "clients:   minimal MQTT 3.1.1 on one tokio multi-thread runtime in this process, nodelay, keep-alive {} s, \
         127.0.0.1 only",
        mqtt::KEEP_ALIVE_SECS
    );
    println!(
        "params:    {}{}; scenarios {}; deadline {} s per scenario and broker",
        if args.quick { "--quick" } else { "full" },
        if args.quick {
            " (smoke-test sizes, not a measurement)"
        } else {
            ""
        },
        scenarios
            .iter()
            .map(|s| s.name())
            .collect::<Vec<_>>()
            .join(","),
        p.deadline.as_secs()
    );
}

fn print_table(scenario: Scenario, rows: &[(BrokerKind, Outcome)]) {
    let mut headers = vec!["broker"];
    headers.extend_from_slice(scenario.columns());
    let mut table: Vec<Vec<String>> = rows
        .iter()
        .map(|(kind, o)| {
            let mut r = vec![kind.label().to_string()];
            r.extend(o.cells.iter().cloned());
            r
        })
        .collect();
    let mut widths: Vec<usize> = headers.iter().map(|h| h.len()).collect();
    for r in &table {
        for (w, c) in widths.iter_mut().zip(r) {
            *w = (*w).max(c.chars().count());
        }
    }
    let line = |cells: &[String]| {
        cells
            .iter()
            .zip(&widths)
            .map(|(c, w)| format!("{c:<w$}"))
            .collect::<Vec<_>>()
            .join("  ")
            .trim_end()
            .to_string()
    };
    let header: Vec<String> = headers.iter().map(|h| h.to_string()).collect();
    println!("   {}", line(&header));
    for (r, (_, o)) in table.iter_mut().zip(rows) {
        let mut text = line(r);
        if let Some(note) = &o.note {
            text.push_str(&format!("  [{note}]"));
        }
        println!("   {text}");
    }
}

fn ratio_line(scenario: Scenario, p: &Params, rows: &[(BrokerKind, Outcome)]) -> String {
    let mut line = scenario.title(p);
    let value = |o: &Outcome| {
        if o.timed_out {
            "timeout".to_string()
        } else if o.keys.iter().all(|k| k.is_none()) {
            "failed".to_string()
        } else {
            scenario.format_keys(&o.keys)
        }
    };
    for (kind, o) in rows {
        line.push_str(&format!("   {} {}", kind.label(), value(o)));
    }
    let fbbus = rows.iter().find(|(k, _)| *k == BrokerKind::Fbbus);
    for other in [BrokerKind::Mosquitto, BrokerKind::Rumqttd] {
        let (Some((_, f)), Some((_, o))) = (fbbus, rows.iter().find(|(k, _)| *k == other)) else {
            continue;
        };
        let ratios: Vec<String> = f
            .keys
            .iter()
            .enumerate()
            .map(|(i, fk)| match (fk, o.keys.get(i).copied().flatten()) {
                (Some(a), Some(b)) if !f.timed_out && !o.timed_out && b > 0.0 => {
                    format!("{:.2}x", a / b)
                }
                _ => "n/a".into(),
            })
            .collect();
        let ratios = if ratios.is_empty() {
            "n/a".to_string()
        } else {
            ratios.join("/")
        };
        line.push_str(&format!("   fbbus/{} {ratios}", other.label()));
    }
    if fbbus.is_some() && rows.len() > 1 {
        line.push_str(if scenario.higher_is_better() {
            "   (higher is better)"
        } else {
            "   (lower is better)"
        });
    }
    line
}

/// Users `plc-0000`... with passwords, and a password file per broker format.
fn prepare_auth(devices: usize, selected: &[BrokerKind], programs: &Programs) -> Result<Storm> {
    let dir = tempfile::Builder::new()
        .prefix("fbbus-bench-auth-")
        .tempdir()?;
    // Readable by Mosquitto after it drops root privileges to its own user.
    brokers::set_mode(dir.path(), 0o755)?;
    let users: Vec<(String, String)> = (0..devices)
        .map(|i| {
            let salt = (i as u64 + 1).wrapping_mul(0x9E37_79B9_7F4A_7C15);
            (format!("plc-{i:04}"), format!("pw-{i:04}-{salt:016x}"))
        })
        .collect();
    let probe = ("bench-probe".to_string(), "probe-secret-7d1f".to_string());
    let mut everyone = users.clone();
    everyone.push(probe.clone());
    let plain: String = everyone.iter().map(|(u, p)| format!("{u}:{p}\n")).collect();

    let rumqttd = dir.path().join("rumqttd-users");
    std::fs::write(&rumqttd, &plain)?;

    let fbbus = if selected.contains(&BrokerKind::Fbbus) {
        let path = dir.path().join("fbbus-passwd");
        write_argon2_file(&path, &everyone)?;
        Some(path)
    } else {
        None
    };

    let mosquitto = if selected.contains(&BrokerKind::Mosquitto) {
        match &programs.mosquitto_passwd {
            Some(tool) => {
                let path = dir.path().join("mosquitto-passwd");
                std::fs::write(&path, &plain)?;
                let status = std::process::Command::new(tool)
                    .arg("-U")
                    .arg(&path)
                    .status()
                    .with_context(|| format!("running {} -U", tool.display()))?;
                if !status.success() {
                    bail!("{} -U {} failed: {status}", tool.display(), path.display());
                }
                brokers::set_mode(&path, 0o644)?;
                Some(path)
            }
            None => {
                eprintln!("  mosquitto_passwd not found: mosquitto will not run the auth storm");
                None
            }
        }
    } else {
        None
    };
    Ok(Storm {
        _dir: dir,
        files: AuthFiles {
            fbbus,
            mosquitto,
            rumqttd,
            probe,
        },
        users: Arc::new(users),
    })
}

/// argon2id hashes with fbbus's defaults, made on every core.
fn write_argon2_file(path: &Path, users: &[(String, String)]) -> Result<()> {
    let params = security::Argon2Params::default();
    let threads = std::thread::available_parallelism()
        .map(|n| n.get())
        .unwrap_or(2);
    let chunk = users.len().div_ceil(threads).max(1);
    let hashes: Vec<Result<Vec<String>>> = std::thread::scope(|s| {
        let handles: Vec<_> = users
            .chunks(chunk)
            .map(|part| {
                s.spawn(move || {
                    part.iter()
                        .map(|(_, pw)| {
                            security::hash_password(pw.as_bytes(), &params)
                                .map_err(|e| anyhow::anyhow!("hashing: {e}"))
                        })
                        .collect::<Result<Vec<String>>>()
                })
            })
            .collect();
        handles
            .into_iter()
            .map(|h| {
                h.join()
                    .unwrap_or_else(|_| bail!("hashing thread panicked"))
            })
            .collect()
    });
    let mut file = security::PasswordFile::default();
    let mut users_iter = users.iter();
    for part in hashes {
        for phc in part? {
            let (user, _) = users_iter.next().context("hash count")?;
            file.set(user, security::StoredHash::parse(&phc)?)?;
        }
    }
    file.save(path)?;
    Ok(())
}

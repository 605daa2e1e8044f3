//! A conveyor line on fbbus: simulated Fischertechnik conveyor modules (the reference
//! line of a 2024 thesis), each a real device with its own connection, in one process.
//!
//! ```text
//! cargo run -p fb-bridge --example conveyor -- --host 127.0.0.1 --port 1883 --count 3
//! ```
//!
//! Needs a running broker (`fbbus serve`). The phases:
//!
//! 1. modules `conveyor-a`, `conveyor-b`, ... start, publish their outputs and follow the
//!    line's online count (no NUM_DEV block);
//! 2. parts travel the line: the first module's SENSOR_IN triggers, each module's
//!    SENSOR_OUT hands over to the next, which learns it from the messages it follows;
//! 3. one more module is plugged in at the end: the count goes up, parts go one further;
//! 4. the second module (or `--unplug ID`) is unplugged abruptly: its will sets
//!    `CONNECT = FALSE`, the count drops (for a contract module within 1.5 x keep-alive),
//!    parts skip it;
//! 5. the first two modules swap places: parts travel in the new order.
//!
//! **Runtimes.** Every module runs the same conveyor logic (`module.rs`); how it talks
//! MQTT is its runtime (`runtime/`). By default each is a `fb_bridge::client` device
//! (declares its interface, typed will, the broker's online count). `--forte ID` makes a
//! module talk as an unmodified 4diac FORTE does (client id = its id, keep-alive 20 s,
//! QoS 0, no will, no declaration; its STATE as `fbdk` on `line1/<id>/state`, its peers
//! read on `fbdk/<peer>/CONV/<PORT>`, the count read as text on
//! `fbbus/lines/<line>/online`); `--dinasore ID` as DINASORE's MQTT FBs do (one
//! connection per published value with an empty client id, `{"POSITION": "2"}` on
//! `line1/<id>/position`, no will, a keep-alive it never honours; its peers read as
//! `float(json[NAME])` on `dinasore/<peer>/CONV/<PORT>`, the count from its peers'
//! CONNECT). Neither declares: the broker needs their profiles, which the example writes:
//!
//! ```text
//! cargo run -p fb-bridge --example conveyor -- --forte conveyor-b --dinasore conveyor-c \
//!     --print-profiles profiles/          # then fbbus serve with [fb] profiles_dir = "profiles"
//! cargo run -p fb-bridge --example conveyor -- --forte conveyor-b --dinasore conveyor-c \
//!     --line line-1 --host 127.0.0.1 --port 1883
//! ```
//!
//! (`--profiles-dir DIR` instead writes them into a running broker's profiles directory
//! and waits 2 s for its reload before starting.) `--line` is the broker's
//! `[broker] line`, which a FORTE module's count topic names.
//!
//! Exits 0 when every phase completed, 1 with the reason when one did not (every wait is
//! bounded by 10 s). `RUST_LOG=fb_bridge=debug` shows the client's own log.

mod line;
mod module;
mod runtime;

use std::path::{Path, PathBuf};
use std::process::ExitCode;
use std::sync::OnceLock;
use std::time::{Duration, Instant};

use clap::Parser;

use line::Line;
use runtime::{Roster, Runtime, Setup};

#[derive(Parser)]
#[command(about = "A simulated conveyor line of fbbus devices")]
struct Args {
    #[arg(long, default_value = "127.0.0.1")]
    host: String,
    #[arg(long, default_value_t = 1883)]
    port: u16,
    /// Modules at the start (one more is plugged in later).
    #[arg(long, default_value_t = 3, value_parser = clap::value_parser!(u8).range(2..=25))]
    count: u8,
    /// Parts sent down the line in each phase.
    #[arg(long, default_value_t = 1, value_parser = clap::value_parser!(u32).range(1..))]
    parts: u32,
    /// MQTT keep-alive of every contract module, in seconds (FORTE's is 20 s,
    /// DINASORE's 60 s).
    #[arg(long, default_value_t = 2, value_parser = clap::value_parser!(u64).range(1..))]
    keep_alive: u64,
    /// Modules that talk as an unmodified 4diac FORTE device (repeat or comma-separate).
    #[arg(long, value_name = "ID", value_delimiter = ',')]
    forte: Vec<String>,
    /// Modules that talk as an unmodified DINASORE device (repeat or comma-separate).
    #[arg(long, value_name = "ID", value_delimiter = ',')]
    dinasore: Vec<String>,
    /// The broker's line name (`[broker] line`): FORTE modules read the online count on
    /// `fbbus/lines/<line>/online`.
    #[arg(long, default_value = "line-1")]
    line: String,
    /// The module unplugged in phase 4 (default: the second on the line).
    #[arg(long, value_name = "ID")]
    unplug: Option<String>,
    /// Write the profiles of the FORTE and DINASORE modules (`<id>.toml`) into DIR, then
    /// exit: for a broker started with `[fb] profiles_dir` = DIR.
    #[arg(long, value_name = "DIR", conflicts_with = "profiles_dir")]
    print_profiles: Option<PathBuf>,
    /// Write the profiles into DIR, a running broker's `[fb] profiles_dir`, and wait 2 s
    /// for it to read them (it polls every `[auth] reload_poll_ms`, 1 s by default).
    #[arg(long, value_name = "DIR")]
    profiles_dir: Option<PathBuf>,
}

static START: OnceLock<Instant> = OnceLock::new();

/// Prints one log line, with the time since the start.
pub fn log(line: impl AsRef<str>) {
    let t = START.get_or_init(Instant::now).elapsed();
    println!("{:>7.3}s  {}", t.as_secs_f64(), line.as_ref());
}

#[tokio::main]
async fn main() -> ExitCode {
    tracing_subscriber::fmt()
        .with_env_filter(
            tracing_subscriber::EnvFilter::try_from_default_env().unwrap_or_else(|_| "warn".into()),
        )
        .with_writer(std::io::stderr)
        .init();
    let args = Args::parse();
    let roster = match roster(&args) {
        Ok(roster) => roster,
        Err(reason) => {
            eprintln!("error: {reason}");
            return ExitCode::from(2);
        }
    };
    if let Some(dir) = &args.print_profiles {
        return match write_profiles(dir, &roster) {
            Ok(()) => ExitCode::SUCCESS,
            Err(reason) => {
                eprintln!("error: {reason}");
                ExitCode::FAILURE
            }
        };
    }
    let runtimes: Vec<String> = roster
        .iter()
        .filter(|(_, r)| **r != Runtime::Contract)
        .map(|(id, r)| format!("{id} {}", r.name()))
        .collect();
    log(format!(
        "conveyor line: {} modules on {}:{}, line {}{}",
        args.count,
        args.host,
        args.port,
        args.line,
        match runtimes.is_empty() {
            true => String::new(),
            false => format!(" ({}; the others contract)", runtimes.join(", ")),
        }
    ));
    if let Some(dir) = &args.profiles_dir {
        if let Err(reason) = write_profiles(dir, &roster) {
            log(format!("FAILED: {reason}"));
            return ExitCode::FAILURE;
        }
        tokio::time::sleep(Duration::from_secs(2)).await;
    }
    match run(&args, roster).await {
        Ok(()) => {
            log("all phases completed");
            ExitCode::SUCCESS
        }
        Err(reason) => {
            log(format!("FAILED: {reason}"));
            ExitCode::FAILURE
        }
    }
}

/// Every module id of the run: `conveyor-a`, `conveyor-b`, ..., one more than `--count`.
fn ids(args: &Args) -> Vec<String> {
    (0..=args.count)
        .map(|i| format!("conveyor-{}", (b'a' + i) as char))
        .collect()
}

/// Each module's runtime, from `--forte` and `--dinasore`.
fn roster(args: &Args) -> Result<Roster, String> {
    let mut roster: Roster = ids(args)
        .into_iter()
        .map(|id| (id, Runtime::Contract))
        .collect();
    for (ids, runtime) in [
        (&args.forte, Runtime::Forte),
        (&args.dinasore, Runtime::Dinasore),
    ] {
        for id in ids {
            match roster.get_mut(id) {
                Some(r) if *r == Runtime::Contract => *r = runtime,
                Some(r) => {
                    return Err(format!(
                        "{id} is given as {} and {}",
                        r.name(),
                        runtime.name()
                    ))
                }
                None => {
                    return Err(format!(
                        "no module {id} in this run (conveyor-a ... with --count)"
                    ))
                }
            }
        }
    }
    if let Some(id) = &args.unplug {
        if !roster.contains_key(id) {
            return Err(format!("--unplug {id}: no such module in this run"));
        }
    }
    Ok(roster)
}

/// Writes the profile of every FORTE and DINASORE module into `dir` (each through a
/// `.`-file the broker ignores, then renamed, so it never reads one half-written).
fn write_profiles(dir: &Path, roster: &Roster) -> Result<(), String> {
    std::fs::create_dir_all(dir).map_err(|e| format!("{}: {e}", dir.display()))?;
    for (id, runtime) in roster {
        let Some(text) = runtime::profile(id, *runtime) else {
            continue;
        };
        let (temporary, path) = (
            dir.join(format!(".{id}.toml")),
            dir.join(format!("{id}.toml")),
        );
        std::fs::write(&temporary, text)
            .and_then(|()| std::fs::rename(&temporary, &path))
            .map_err(|e| format!("{}: {e}", path.display()))?;
        log(format!(
            "profile of {id} ({}): {}",
            runtime.name(),
            path.display()
        ));
    }
    Ok(())
}

async fn run(args: &Args, roster: Roster) -> Result<(), String> {
    let setup = Setup {
        host: args.host.clone(),
        port: args.port,
        keep_alive: Duration::from_secs(args.keep_alive),
        line: args.line.clone(),
    };
    let ids = ids(args);
    let (first, added) = ids.split_at(args.count as usize);
    let parts = args.parts as usize;
    let mut line = Line::new(setup, roster);

    phase(1, "modules start and follow the online count");
    for id in first {
        line.start(id);
        line.settle().await?;
    }
    log(format!("line: {}", line.order().join(" -> ")));

    phase(2, "parts travel the line");
    line.run_parts(parts).await?;

    phase(3, &format!("{} is plugged in while running", added[0]));
    line.start(&added[0]);
    line.settle().await?;
    line.run_parts(parts).await?;

    let victim = match &args.unplug {
        Some(id) => id.clone(),
        None => line.order()[1].clone(),
    };
    let keep_alive = line
        .keep_alive(&victim)
        .ok_or(format!("{victim} is not on the line"))?;
    phase(4, &format!("{victim} is unplugged abruptly"));
    let took = line.unplug(&victim).await?;
    let bound = keep_alive * 3 / 2;
    log(format!(
        "every module saw the count drop after {} ms (bound: 1.5 x keep-alive = {} ms)",
        took.as_millis(),
        bound.as_millis()
    ));
    if took > bound {
        return Err(format!(
            "the count dropped after {took:?}, more than {bound:?}"
        ));
    }
    line.settle().await?;
    line.run_parts(parts).await?;

    let order = line.order();
    let (a, b) = (&order[0], &order[1]);
    phase(5, &format!("{a} and {b} swap places"));
    line.swap(a, b).await?;
    line.settle().await?;
    log(format!("line: {}", line.order().join(" -> ")));
    line.run_parts(parts).await?;

    line.stop().await
}

fn phase(n: u32, what: &str) {
    log(format!("== phase {n}: {what}"));
}

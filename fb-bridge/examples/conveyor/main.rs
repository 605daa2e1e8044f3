//! A conveyor line on fbbus: simulated Fischertechnik conveyor modules (the reference
//! line of a 2024 thesis), each a real device with its own connection, in one process.
//!
//! ```text
//! cargo run -p fb-bridge --example conveyor -- --host 127.0.0.1 --port 1883 --count 3
//! ```
//!
//! Needs a running broker (`fbbus serve`). The phases:
//!
//! 1. modules `conveyor-a`, `conveyor-b`, ... start, declare `CONV`, publish `STATE` and
//!    follow the line's online count (no NUM_DEV block);
//! 2. parts travel the line: the first module's SENSOR_IN triggers, each module's
//!    SENSOR_OUT hands over to the next, which learns it from an IND of its `STATE`;
//! 3. one more module is plugged in at the end: the count goes up, parts go one further;
//! 4. the second module is unplugged abruptly: its will sets `CONNECT = FALSE`, the count
//!    drops within 1.5 x keep-alive, parts skip it;
//! 5. the first two modules swap places: parts travel in the new order.
//!
//! Exits 0 when every phase completed, 1 with the reason when one did not (every wait is
//! bounded by 10 s). `RUST_LOG=fb_bridge=debug` shows the client's own log.

mod line;
mod module;

use std::process::ExitCode;
use std::sync::OnceLock;
use std::time::{Duration, Instant};

use clap::Parser;
use fb_bridge::client::DeviceConfig;

use line::Line;

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
    /// MQTT keep-alive of every module, in seconds.
    #[arg(long, default_value_t = 2, value_parser = clap::value_parser!(u64).range(1..))]
    keep_alive: u64,
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
    log(format!(
        "conveyor line: {} modules on {}:{}",
        args.count, args.host, args.port
    ));
    match run(&args).await {
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

async fn run(args: &Args) -> Result<(), String> {
    let keep_alive = Duration::from_secs(args.keep_alive);
    let mut base = DeviceConfig::new(&args.host, args.port, "");
    base.keep_alive = keep_alive;
    let ids: Vec<String> = (0..=args.count)
        .map(|i| format!("conveyor-{}", (b'a' + i) as char))
        .collect();
    let (first, added) = ids.split_at(args.count as usize);
    let parts = args.parts as usize;
    let mut line = Line::new(base, ids.clone());

    phase(1, "modules start, declare and follow the online count");
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

    let victim = line.order()[1].clone();
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

//! `fbbus zenohd-config`: the configuration of the plant's zenoh router (`zenohd`), built
//! by the same code as a line's bridge, so the router holds every line to the same rules
//! the lines hold each other to.
//!
//! Behind a router, a line only ever talks to the router: each line's traffic reaches the
//! others through it, and the router's own access control is what keeps line C from
//! speaking under line A's keys. The lines list the router under
//! `[bridge.peers] routers`; the router lists the lines here.

use std::io::Write as _;
use std::path::PathBuf;

use anyhow::{Context as _, Result};
use clap::Args;
use fb_bridge::bus::{BusConfig, BusPeers, BusTls, Mode};

#[derive(Args)]
pub struct ZenohdArgs {
    /// The router's name: its certificate's common name, which the lines list under
    /// `[bridge.peers] routers`.
    #[arg(long)]
    name: String,
    /// zenoh endpoints the router listens on, e.g. tls/0.0.0.0:7447.
    #[arg(long, required = true)]
    listen: Vec<String>,
    /// Other routers it connects to (a plant with one router per site).
    #[arg(long)]
    connect: Vec<String>,
    /// The plant's bus CA (PEM), as the router host will see it.
    #[arg(long)]
    root_ca: PathBuf,
    /// The router's certificate and key (PEM; `fbbus bus-cert issue --name <name>`).
    #[arg(long)]
    cert: PathBuf,
    #[arg(long)]
    key: PathBuf,
    /// Lines whose bridges connect to it (certificate CNs = line names), comma-separated.
    #[arg(long, value_delimiter = ',')]
    lines: Vec<String>,
    /// Other routers it exchanges every line's traffic with.
    #[arg(long, value_delimiter = ',')]
    routers: Vec<String>,
    /// Read-only zenoh applications.
    #[arg(long, value_delimiter = ',')]
    readers: Vec<String>,
    /// The lines' `lease_ms`: a line that stops answering is dropped after this long.
    #[arg(long, default_value_t = 3_000)]
    lease_ms: u64,
}

/// Prints the router's configuration (JSON, which zenohd reads as JSON5).
pub fn run(args: ZenohdArgs) -> Result<()> {
    let config = BusConfig {
        mode: Mode::Router,
        listen: args.listen,
        connect: args.connect,
        lease_ms: args.lease_ms,
        tls: Some(BusTls {
            root_ca: args.root_ca,
            cert: args.cert,
            key: args.key,
            mutual: true,
        }),
        peers: Some(BusPeers {
            lines: args.lines,
            routers: args.routers,
            readers: args.readers,
        }),
        ..BusConfig::default()
    };
    config
        .validate(&args.name)
        .map_err(|(key, message)| anyhow::anyhow!("{key}: {message}"))?;
    let json = fb_bridge::bus::link::zenohd_config(&config, &args.name)
        .context("the router's configuration")?;
    let text = serde_json::to_string_pretty(&json).context("printing the configuration")?;
    let mut out = std::io::stdout().lock();
    // A closed pipe (`| head`) ends the command quietly.
    match writeln!(out, "{text}") {
        Err(e) if e.kind() != std::io::ErrorKind::BrokenPipe => Err(e.into()),
        _ => Ok(()),
    }
}

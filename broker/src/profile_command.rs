//! `fbbus declare` and `fbbus profile`: device profiles from the command line.
//!
//! - `fbbus declare FILE` puts a profile into a running broker (its admin endpoint, from
//!   the broker's own host), which checks it against every other profile and writes it
//!   into its profiles directory, in force at once;
//! - `fbbus profile check FILE` validates a profile without a broker: every mistake,
//!   each with its key;
//! - `fbbus profile import FILE [--device NAME]` derives profiles from a 4diac boot file
//!   (`.fboot`): a FORTE boot file, one profile per MQTT client id; or the
//!   `resources/data_model.fboot` of a DINASORE, one profile, of device NAME; and prints
//!   them, with what it could not derive.

use std::net::SocketAddr;
use std::path::Path;

use anyhow::{bail, Context as _, Result};
use fb_bridge::profile::fboot::{self, FbootImport};

/// The device of a DINASORE's profile when `--device` does not name it.
const DINASORE_DEVICE: &str = "dinasore";

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
pub fn import(file: &Path, device: Option<&str>) -> Result<()> {
    let bytes = std::fs::read(file).with_context(|| format!("cannot read {}", file.display()))?;
    let text = String::from_utf8_lossy(&bytes);
    let imported = derive(&text, device);
    print!("{}", render(&imported)?);
    if imported.profiles.is_empty() {
        bail!(
            "{}: no profile derived (no MQTT PUBLISH/SUBSCRIBE FB with an fbdk[].mqtt[...] ID, \
             and no DINASORE MQTT_PUBLISHER/MQTT_SUBSCRIBER FB, that can be mapped)",
            file.display()
        );
    }
    Ok(())
}

/// The profiles of a FORTE boot file or of a DINASORE's configuration: the file is read
/// both ways, and each reading is empty for the other runtime's file, but for FORTE's
/// notes on a DINASORE file (how FORTE would read it), which are left out.
fn derive(text: &str, device: Option<&str>) -> FbootImport {
    let forte = fboot::import(text);
    let dinasore = fboot::import_dinasore(text, device.unwrap_or(DINASORE_DEVICE));
    if dinasore == FbootImport::default() {
        let mut out = forte;
        if let Some(device) = device {
            out.notes.push(
                format!(
                    "--device {device:?} is not used: it names the device of a DINASORE \
                 configuration, and this file has no DINASORE MQTT FB (a FORTE profile's \
                 device is its client id)."
                )
                .into(),
            );
        }
        return out;
    }
    // Both runtimes' FBs in one file: everything is printed.
    let mut out = match forte.profiles.is_empty() {
        true => FbootImport::default(),
        false => forte,
    };
    if device.is_none() && !dinasore.profiles.is_empty() {
        out.notes.push(
            format!(
                "No --device: the DINASORE profile's device is {DINASORE_DEVICE:?}; give each \
             DINASORE its own id, its registry id (fb/<device>/...), with --device NAME."
            )
            .into(),
        );
    }
    out.notes.extend(dinasore.notes);
    out.profiles.extend(dinasore.profiles);
    out
}

/// The import as text: notes first, then each profile, with whether it is complete.
fn render(imported: &FbootImport) -> Result<String> {
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

    fn fixture(name: &str) -> String {
        let path = Path::new(env!("CARGO_MANIFEST_DIR"))
            .join("../fb-bridge/tests/data")
            .join(name);
        std::fs::read_to_string(path).unwrap()
    }

    /// Each profile block parses back into the profile it was printed from, every note is
    /// printed.
    fn reads_back(imported: &FbootImport) -> String {
        let out = render(imported).unwrap();
        let blocks: Vec<&str> = out.split("\n# ---- device ").skip(1).collect();
        assert_eq!(blocks.len(), imported.profiles.len());
        for (block, profile) in blocks.iter().zip(&imported.profiles) {
            let toml_text = block.split_once('\n').map(|(_, t)| t).unwrap_or_default();
            let back: fb_bridge::profile::ProfileFile = toml::from_str(toml_text).unwrap();
            assert_eq!(&back, profile);
        }
        assert_eq!(out.matches("# NOTE: ").count(), imported.notes.len());
        out
    }

    #[test]
    fn the_conveyor_boot_file_imports_into_profiles_that_read_back() {
        let text = fixture("conveyor.fboot");
        let imported = derive(&text, None);
        assert_eq!(imported, fboot::import(&text));
        assert!(!imported.profiles.is_empty());
        reads_back(&imported);
        // --device is DINASORE's: said to be unused.
        let with_device = derive(&text, Some("conv9"));
        assert_eq!(with_device.profiles, imported.profiles);
        assert!(with_device
            .notes
            .last()
            .unwrap()
            .starts_with("--device \"conv9\" is not used"));
    }

    #[test]
    fn a_dinasore_configuration_imports_into_its_profile() {
        let text = fixture("dinasore.fboot");
        let imported = derive(&text, Some("conv3"));
        assert_eq!(imported, fboot::import_dinasore(&text, "conv3"));
        assert_eq!(imported.profiles.len(), 1);
        let out = reads_back(&imported);
        assert!(out.contains("\n# ---- device conv3: incomplete (2 to fix, see the notes)"));
        assert!(out.contains("runtime = \"dinasore\""), "{out}");
        assert!(out.contains("topics_only = true"), "{out}");
        assert!(out.contains("enforce_keep_alive = false"), "{out}");

        // Without --device: "dinasore", and a note saying so first.
        let imported = derive(&text, None);
        assert_eq!(imported.profiles[0].device, DINASORE_DEVICE);
        assert!(
            imported.notes[0].starts_with("No --device"),
            "{:?}",
            imported.notes
        );
        reads_back(&imported);
    }
}

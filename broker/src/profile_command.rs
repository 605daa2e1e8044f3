//! `fbbus declare` and `fbbus profile`: device profiles from the command line.
//!
//! - `fbbus declare FILE` puts a profile into a running broker (its admin endpoint, from
//!   the broker's own host), which checks it against every other profile and writes it
//!   into its profiles directory, in force at once;
//! - `fbbus profile check FILE` validates a profile without a broker: every mistake in one
//!   run, each with its key, and how many;
//! - `fbbus profile import FILE [--device NAME] [--name FB.PORT=NAME]... [--names FILE]`
//!   derives profiles from a 4diac boot file (`.fboot`): a FORTE boot file, one profile
//!   per MQTT client id; or the `resources/data_model.fboot` of a DINASORE, one profile,
//!   of device NAME; and prints them after a summary and the notes on what it could not
//!   derive, those that block `fbbus declare` first. `--name`/`--names` name the ports
//!   the import generates (`P_COUNT.SD_1=COUNT`), so the JSON side reads as the
//!   application means.

use std::net::SocketAddr;
use std::path::{Path, PathBuf};

use anyhow::{bail, Context as _, Result};
use fb_bridge::profile::fboot::{self, FbootImport, NameError, Note, PortNames};
use fb_bridge::profile::ProfileFile;

/// The device of a DINASORE's profile when `--device` does not name it.
const DINASORE_DEVICE: &str = "dinasore";

/// `fbbus profile import`'s arguments.
#[derive(clap::Args)]
pub struct ImportArgs {
    file: PathBuf,
    /// The device id of a DINASORE's profile (nothing in its file names it); default
    /// "dinasore". A FORTE profile's device is its MQTT client id.
    #[arg(long)]
    device: Option<String>,
    /// Name a generated port: FB.PORT=NAME, the FB and port as the import prints them
    /// without names (`P_COUNT.SD_1=COUNT`, `P_COUNT.REQ=COUNTED`). Repeatable.
    #[arg(long = "name", value_name = "FB.PORT=NAME")]
    names: Vec<String>,
    /// A TOML file of port names, one `FB.PORT = "NAME"` a line (or a `[FB]` table of
    /// `PORT = "NAME"`); --name adds to it.
    #[arg(long = "names", value_name = "FILE")]
    names_file: Option<PathBuf>,
}

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

/// Validates a profile file and reports every mistake at once, one a line, with their
/// count (the count `fbbus profile import` gives for the profile it printed).
pub fn check(file: &Path) -> Result<()> {
    let text =
        std::fs::read_to_string(file).with_context(|| format!("cannot read {}", file.display()))?;
    let profile: ProfileFile =
        toml::from_str(&text).map_err(|e| anyhow::anyhow!("{}: {e}", file.display()))?;
    let device = profile.device.clone();
    match profile.validate() {
        Ok(_) => {
            println!("{}: a valid profile of device {device}", file.display());
            Ok(())
        }
        Err(errors) => bail!("{}", problems(&file.display().to_string(), &errors)),
    }
}

/// `FILE: N to fix before `fbbus declare`:` and each error on its own line.
fn problems(file: &str, errors: &[impl std::fmt::Display]) -> String {
    let mut out = format!(
        "{file}: {} to fix before `fbbus declare` takes it:",
        count(errors.len(), "problem")
    );
    for e in errors {
        out.push_str(&format!("\n  {e}"));
    }
    out
}

/// `1 problem`, `2 problems`.
fn count(n: usize, what: &str) -> String {
    match n {
        1 => format!("1 {what}"),
        n => format!("{n} {what}s"),
    }
}

/// Prints the profiles derived from a 4diac boot file as TOML, one block per device,
/// preceded by a summary and the notes (as TOML comments), so the output can be cut into
/// files and completed. Fails if a port name is wrong, or if nothing could be derived.
pub fn import(args: &ImportArgs) -> Result<()> {
    let file = &args.file;
    let mut names = port_names(args)?;
    let bytes = std::fs::read(file).with_context(|| format!("cannot read {}", file.display()))?;
    let text = String::from_utf8_lossy(&bytes);
    let imported = derive(&text, args.device.as_deref(), &mut names);
    if let Err(errors) = names.finish() {
        bail!("{}", name_problems(&errors));
    }
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

fn name_problems(errors: &[NameError]) -> String {
    problems("the port names", errors).replace(" before `fbbus declare` takes it", "")
}

/// The names of `--names FILE` and every `--name`.
fn port_names(args: &ImportArgs) -> Result<PortNames> {
    let mut names = PortNames::new();
    let mut errors = Vec::new();
    if let Some(path) = &args.names_file {
        let text = std::fs::read_to_string(path)
            .with_context(|| format!("cannot read {}", path.display()))?;
        errors.extend(
            names_file(&text, &mut names)
                .map_err(|e| anyhow::anyhow!("{}: {e}", path.display()))?,
        );
    }
    for arg in &args.names {
        if let Err(e) = names.add_arg(arg) {
            errors.push(e);
        }
    }
    if !errors.is_empty() {
        bail!("{}", name_problems(&errors));
    }
    Ok(names)
}

/// Reads a names file: TOML whose keys are `FB.PORT` (dotted, or a `[FB]` table) and whose
/// values are the new names. Err: it is not TOML; the list: names that are wrong.
fn names_file(text: &str, names: &mut PortNames) -> Result<Vec<NameError>> {
    let table: toml::Table = toml::from_str(text).context("not TOML")?;
    let mut errors = Vec::new();
    for (key, value) in &table {
        let pairs: Vec<(String, &toml::Value)> = match value {
            toml::Value::Table(ports) => ports
                .iter()
                .map(|(port, v)| (format!("{key}.{port}"), v))
                .collect(),
            other => vec![(key.clone(), other)],
        };
        for (fb_port, value) in pairs {
            let result = match value.as_str() {
                Some(name) => names.add(&fb_port, name),
                None => Err(NameError::Syntax(format!("{fb_port}={value}"))),
            };
            errors.extend(result.err());
        }
    }
    Ok(errors)
}

/// The profiles of a FORTE boot file or of a DINASORE's configuration: the file is read
/// both ways, and each reading is empty for the other runtime's file, but for FORTE's
/// notes on a DINASORE file (how FORTE would read it), which are left out.
fn derive(text: &str, device: Option<&str>, names: &mut PortNames) -> FbootImport {
    let forte = fboot::import_named(text, &fboot::builtin_types(), names);
    let dinasore = fboot::import_dinasore_named(text, device.unwrap_or(DINASORE_DEVICE), names);
    if dinasore == FbootImport::default() {
        let mut out = forte;
        if let Some(device) = device {
            out.notes.push(Note::from(format!(
                "--device {device:?} is not used: it names the device of a DINASORE \
                 configuration, and this file has no DINASORE MQTT FB (a FORTE profile's \
                 device is its client id)."
            )));
        }
        return out;
    }
    // Both runtimes' FBs in one file: everything is printed.
    let mut out = match forte.profiles.is_empty() {
        true => FbootImport::default(),
        false => forte,
    };
    if device.is_none() && !dinasore.profiles.is_empty() {
        out.notes.push(Note::from(format!(
            "No --device: the DINASORE profile's device is {DINASORE_DEVICE:?}; give each \
             DINASORE its own id, its registry id (fb/<device>/...), with --device NAME."
        )));
    }
    out.notes.extend(dinasore.notes);
    out.profiles.extend(dinasore.profiles);
    out
}

/// The import as text: a summary, the notes (those that block `fbbus declare` first), then
/// each profile, with whether it is complete.
fn render(imported: &FbootImport) -> Result<String> {
    let blocking = imported.blocking();
    let mut out = match imported.notes.len() {
        0 => "# No notes.\n".to_owned(),
        n => format!(
            "# {}: {blocking} block `fbbus declare` (listed first, each naming the profile it \
             blocks), {} advisory.\n",
            count(n, "note"),
            n - blocking
        ),
    };
    for note in imported.notes_blocking_first() {
        match &note.blocks {
            Some(device) => out.push_str(&format!("# NOTE (blocks {device}): {note}\n")),
            None => out.push_str(&format!("# NOTE: {note}\n")),
        }
    }
    for profile in &imported.profiles {
        let toml = toml::to_string(profile).context("a derived profile did not serialize")?;
        let file = format!("{}.toml", profile.device);
        let state = match profile.clone().validate() {
            Ok(_) => format!("complete: save it as {file}"),
            Err(errors) => format!(
                "incomplete ({} to fix, the notes that block {}): save it as {file} once \
                 done; `fbbus profile check {file}` lists them",
                errors.len(),
                profile.device
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

    fn derive_unnamed(text: &str, device: Option<&str>) -> FbootImport {
        let mut names = PortNames::new();
        let out = derive(text, device, &mut names);
        names.finish().unwrap();
        out
    }

    /// Each profile block parses back into the profile it was printed from, every note is
    /// printed, blocking ones first, and the summary counts them.
    fn reads_back(imported: &FbootImport) -> String {
        let out = render(imported).unwrap();
        let blocks: Vec<&str> = out.split("\n# ---- device ").skip(1).collect();
        assert_eq!(blocks.len(), imported.profiles.len());
        for (block, profile) in blocks.iter().zip(&imported.profiles) {
            let toml_text = block.split_once('\n').map(|(_, t)| t).unwrap_or_default();
            let back: fb_bridge::profile::ProfileFile = toml::from_str(toml_text).unwrap();
            assert_eq!(&back, profile);
            let blocking = imported
                .notes
                .iter()
                .filter(|n| n.blocks.as_deref() == Some(profile.device.as_str()))
                .count();
            match profile.clone().validate() {
                Ok(_) => assert_eq!(blocking, 0),
                Err(errors) => assert_eq!(errors.len(), blocking, "{errors:#?}"),
            }
        }
        let notes: Vec<&str> = out.lines().filter(|l| l.starts_with("# NOTE")).collect();
        assert_eq!(notes.len(), imported.notes.len());
        let blocking = imported.blocking();
        assert!(notes[..blocking]
            .iter()
            .all(|l| l.starts_with("# NOTE (blocks ")));
        assert!(notes[blocking..].iter().all(|l| l.starts_with("# NOTE: ")));
        out
    }

    #[test]
    fn the_conveyor_boot_file_imports_into_profiles_that_read_back() {
        let text = fixture("conveyor.fboot");
        let imported = derive_unnamed(&text, None);
        assert_eq!(imported, fboot::import(&text));
        assert!(!imported.profiles.is_empty());
        reads_back(&imported);
        // --device is DINASORE's: said to be unused.
        let with_device = derive_unnamed(&text, Some("conv9"));
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
        let imported = derive_unnamed(&text, Some("conv3"));
        assert_eq!(imported, fboot::import_dinasore(&text, "conv3"));
        assert_eq!(imported.profiles.len(), 1);
        let out = reads_back(&imported);
        assert!(
            out.contains(
                "\n# ---- device conv3: incomplete (2 to fix, the notes that block conv3)"
            ),
            "{out}"
        );
        assert!(out.contains("runtime = \"dinasore\""), "{out}");
        assert!(out.contains("topics_only = true"), "{out}");
        assert!(out.contains("enforce_keep_alive = false"), "{out}");
        // The subscriber's missing `from` is the first thing to fix.
        assert!(
            out.starts_with(
                "# 3 notes: 2 block `fbbus declare` (listed first, each naming the profile it \
             blocks), 1 advisory.\n# NOTE (blocks conv3): MQTT_SUBSCRIBER SUB_POS reads topic"
            ),
            "{out}"
        );

        // Without --device: "dinasore", and a note saying so.
        let imported = derive_unnamed(&text, None);
        assert_eq!(imported.profiles[0].device, DINASORE_DEVICE);
        assert!(
            imported.notes[0].starts_with("No --device"),
            "{:?}",
            imported.notes
        );
        reads_back(&imported);
    }

    #[test]
    fn the_summary_counts_the_notes_and_the_ones_that_block() {
        let imported = derive_unnamed(&fixture("cell.fboot"), None);
        let out = reads_back(&imported);
        let n = imported.notes.len();
        assert!(
            out.starts_with(&format!(
                "# {n} notes: 4 block `fbbus declare` (listed first, each naming the profile \
                 it blocks), {} advisory.\n",
                n - 4
            )),
            "{out}"
        );
        assert!(
            out.contains("# ---- device cell1: incomplete (4 to fix, the notes that block cell1)")
        );
    }

    #[test]
    fn a_names_file_is_toml_keyed_by_fb_and_port() {
        let mut names = PortNames::new();
        let errors = names_file(
            "P_COUNT.SD_1 = \"COUNT\"\n\"P_COUNT.REQ\" = \"COUNTED\"\n[S_MODE]\nRD_2 = \"MODE\"\n",
            &mut names,
        )
        .unwrap();
        assert!(errors.is_empty(), "{errors:?}");
        let imported = derive(&fixture("cell.fboot"), None, &mut names);
        names.finish().unwrap();
        let fbs = &imported.profiles[0].interface.fbs;
        assert_eq!(fbs["P_COUNT"].events_out["COUNTED"].with, ["COUNT"]);
        assert!(fbs["S_MODE"].events_in["IND"]
            .with
            .contains(&"MODE".to_owned()));

        let mut names = PortNames::new();
        let errors = names_file("P_COUNT.SD_1 = 3\nS_MODE.RD_2 = \"2MODE\"\n", &mut names).unwrap();
        assert_eq!(errors.len(), 2, "{errors:?}");
        assert!(names_file("P_COUNT.SD_1 = ", &mut names).is_err());
    }
}

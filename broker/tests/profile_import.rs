//! `fbbus profile import` and `fbbus profile check` through the real binary, on boot files
//! with the cases of issue 30 item 5: the summary counts every note and says how many
//! block `fbbus declare`, those come first, `profile check` reports every problem of the
//! printed profile in one run with the same count, and `--name`/`--names` name the
//! generated ports.

use std::path::{Path, PathBuf};
use std::process::{Command, Output};

fn fixture(name: &str) -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("../fb-bridge/tests/data")
        .join(name)
}

fn fbbus(args: &[&str]) -> Output {
    Command::new(env!("CARGO_BIN_EXE_fbbus"))
        .args(args)
        .output()
        .expect("fbbus runs")
}

fn stdout(out: &Output) -> String {
    String::from_utf8_lossy(&out.stdout).into_owned()
}

fn stderr(out: &Output) -> String {
    String::from_utf8_lossy(&out.stderr).into_owned()
}

/// The TOML of device `device`'s block in an import's output.
fn profile_block(out: &str, device: &str) -> String {
    let start = format!("\n# ---- device {device}: ");
    let block = out.split(&start).nth(1).expect("the device's block");
    let block = block.split("\n# ---- device ").next().unwrap_or_default();
    block
        .split_once('\n')
        .map(|(_, t)| t)
        .unwrap_or_default()
        .to_owned()
}

#[test]
fn import_counts_every_note_blocking_ones_first_and_check_reports_them_in_one_run() {
    let boot = fixture("cell.fboot");
    let out = fbbus(&["profile", "import", boot.to_str().unwrap()]);
    assert!(out.status.success(), "{}", stderr(&out));
    let text = stdout(&out);
    let notes: Vec<&str> = text.lines().filter(|l| l.starts_with("# NOTE")).collect();
    let summary = text.lines().next().unwrap_or_default();
    assert_eq!(
        summary,
        format!(
            "# {} notes: 4 block `fbbus declare` (listed first, each naming the profile it \
             blocks), {} advisory.",
            notes.len(),
            notes.len() - 4
        ),
        "{text}"
    );
    // One input type and three `from`s, first.
    assert!(notes[..4]
        .iter()
        .all(|l| l.starts_with("# NOTE (blocks cell1): ")));
    assert_eq!(
        notes[..4]
            .iter()
            .filter(|l| l.contains("set `from`"))
            .count(),
        3
    );
    assert!(notes[..4]
        .iter()
        .any(|l| l.contains("set data_in.RD_2 of FB S_MODE")));
    assert!(notes[4..].iter().all(|l| l.starts_with("# NOTE: ")));
    // The DINT read as INT: advisory, named.
    assert!(
        notes[4..]
            .iter()
            .any(|l| l.contains("as INT") && l.contains("as DINT")),
        "{text}"
    );
    assert!(
        text.contains("# ---- device cell1: incomplete (4 to fix, the notes that block cell1)"),
        "{text}"
    );
    // Both DT literals typed their port.
    let block = profile_block(&text, "cell1");
    assert_eq!(
        block.matches("RD_1 = \"DATE_AND_TIME\"").count(),
        1,
        "{block}"
    );
    assert_eq!(
        block.matches("SD_1 = \"DATE_AND_TIME\"").count(),
        1,
        "{block}"
    );

    // Saved as printed, `fbbus profile check` lists the same four problems at once.
    let dir = tempfile::tempdir().unwrap();
    let file = dir.path().join("cell1.toml");
    std::fs::write(&file, &block).unwrap();
    let check = fbbus(&["profile", "check", file.to_str().unwrap()]);
    assert!(!check.status.success());
    let err = stderr(&check);
    assert!(
        err.contains("cell1.toml: 4 problems to fix before `fbbus declare` takes it:"),
        "{err}"
    );
    assert_eq!(
        err.lines().filter(|l| l.starts_with("  ")).count(),
        4,
        "{err}"
    );
    assert_eq!(err.matches(".from: ").count(), 3, "{err}");
    assert!(err.contains("WITH RD_2"), "{err}");

    // Done: valid.
    let done = block
        .replace(
            "[interface.fbs.S_MODE.data_in]\n",
            "[interface.fbs.S_MODE.data_in]\nRD_2 = \"USINT\"\n",
        )
        .replace(
            "topic = \"cell0/stamp\"\n",
            "topic = \"cell0/stamp\"\nfrom = \"cell0/CLOCK/STAMP\"\n",
        )
        .replace(
            "topic = \"cell0/speed\"\n",
            "topic = \"cell0/speed\"\nfrom = \"cell0/DRIVE/SPEED\"\n",
        )
        .replace(
            "topic = \"cell0/mode\"\n",
            "topic = \"cell0/mode\"\nfrom = \"cell0/MODE/SET\"\n",
        );
    std::fs::write(&file, &done).unwrap();
    let check = fbbus(&["profile", "check", file.to_str().unwrap()]);
    assert!(check.status.success(), "{}\n{done}", stderr(&check));
    assert!(stdout(&check).contains("a valid profile of device cell1"));
}

#[test]
fn ports_are_named_by_name_and_by_a_names_file() {
    let boot = fixture("cell.fboot");
    let dir = tempfile::tempdir().unwrap();
    let names = dir.path().join("names.toml");
    std::fs::write(&names, "S_MODE.RD_1 = \"AUTO\"\nS_MODE.RD_2 = \"MODE\"\n").unwrap();
    let out = fbbus(&[
        "profile",
        "import",
        boot.to_str().unwrap(),
        "--name",
        "P_COUNT.SD_1=COUNT",
        "--name",
        "P_COUNT.REQ=COUNTED",
        "--names",
        names.to_str().unwrap(),
    ]);
    assert!(out.status.success(), "{}", stderr(&out));
    let text = stdout(&out);
    assert!(text.contains("port = \"P_COUNT.COUNTED\""), "{text}");
    assert!(
        text.contains("[interface.fbs.P_COUNT.events_out.COUNTED]\nwith = [\"COUNT\"]"),
        "{text}"
    );
    assert!(text.contains("with = [\"AUTO\", \"MODE\"]"), "{text}");
    assert!(
        text.contains("set data_in.MODE of FB S_MODE in profile cell1"),
        "{text}"
    );
    assert!(!text.contains("SD_1 = \"DINT\""), "{text}");

    // Names that name no port, are no identifier or collide: an error, nothing printed.
    for (name, says) in [
        (
            "P_COUNT.SD_9=NINE",
            "P_COUNT.SD_9 names no port the import generates",
        ),
        ("P_COUNT.SD_1=1COUNT", "is not an IEC 61131-3 identifier"),
        (
            "P_COUNT.SD_1=REQ",
            "collides with another port of FB P_COUNT",
        ),
        ("P_COUNT", "is not FB.PORT=NAME"),
    ] {
        let out = fbbus(&["profile", "import", boot.to_str().unwrap(), "--name", name]);
        assert!(!out.status.success(), "{name}");
        assert!(stdout(&out).is_empty(), "{name}: {}", stdout(&out));
        assert!(stderr(&out).contains(says), "{name}: {}", stderr(&out));
    }
}

#[test]
fn a_dinasore_subscribers_missing_from_is_the_first_thing_to_fix() {
    let boot = fixture("dinasore.fboot");
    let out = fbbus(&[
        "profile",
        "import",
        boot.to_str().unwrap(),
        "--device",
        "conv3",
    ]);
    assert!(out.status.success(), "{}", stderr(&out));
    let text = stdout(&out);
    let first = text
        .lines()
        .find(|l| l.starts_with("# NOTE"))
        .unwrap_or_default();
    assert!(
        first.starts_with("# NOTE (blocks conv3): MQTT_SUBSCRIBER SUB_POS reads topic"),
        "{text}"
    );
    assert!(
        text.starts_with("# 3 notes: 2 block `fbbus declare`"),
        "{text}"
    );
}

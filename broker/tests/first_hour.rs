//! Issue 35, "the first hour": what a plant engineer new to fbbus meets first. The README's
//! "Try it" commands run as written against the real broker (with Debian's
//! mosquitto-clients), and the mistakes everyone makes once get an answer that says what
//! to do: a broken config file, a missing one, `passwd add` on an existing user,
//! `declare` on a broker without a profiles directory.

mod common;

use std::path::Path;
use std::process::Command;
use std::time::Duration;

use common::{add_user, fbbus_bin, run, Broker};

const LIMIT: Duration = Duration::from_secs(60);

/// `fbbus args...`: (success, stdout, stderr).
fn fbbus(args: &[&str]) -> (bool, String, String) {
    run(Command::new(fbbus_bin()).args(args), LIMIT)
}

fn write(dir: &Path, name: &str, text: &str) -> String {
    let path = dir.join(name);
    std::fs::write(&path, text).unwrap();
    path.to_str().unwrap().to_owned()
}

/// The README's quick-start block that starts with `mosquitto_sub`: its lines, as written.
fn readme_try_it() -> Vec<String> {
    let readme = std::fs::read_to_string(concat!(env!("CARGO_MANIFEST_DIR"), "/../README.md"))
        .expect("README.md");
    let block = readme
        .split("```sh\n")
        .skip(1)
        .filter_map(|b| b.split_once("```").map(|(code, _)| code))
        .find(|code| code.starts_with("mosquitto_sub"))
        .expect("README has a ```sh block starting with mosquitto_sub");
    // Continuation lines joined, as the shell reads them.
    block
        .replace("\\\n", "")
        .lines()
        .map(str::to_owned)
        .collect()
}

/// A shell line without its comment (a `#` after white space, outside single quotes).
fn without_comment(line: &str) -> &str {
    let mut quoted = false;
    let mut after_space = true;
    for (i, c) in line.char_indices() {
        match c {
            '\'' => quoted = !quoted,
            '#' if !quoted && after_space => return line[..i].trim_end(),
            _ => {}
        }
        after_space = c.is_whitespace();
    }
    line.trim_end()
}

/// The README's "Try it", command by command, against a broker of the embedded default's
/// shape on free ports. What the test changes, and only that: the port (mosquitto's
/// clients read `-p` from their per-user option files, `$XDG_CONFIG_HOME/mosquitto_pub`),
/// the admin address (`127.0.0.1:9883` and `fbbus devices` given the test broker's), a
/// pause after each background subscriber so it subscribes before the device publishes,
/// and the subscribers' end (`timeout`).
#[test]
fn the_readmes_try_it_does_what_it_says() {
    if !common::require("mosquitto_sub") || !common::require("curl") {
        return;
    }
    let broker = Broker::start();
    let dir = broker.dir.path();
    let xdg = dir.join("xdg");
    std::fs::create_dir_all(&xdg).unwrap();
    for tool in ["mosquitto_pub", "mosquitto_sub"] {
        std::fs::write(xdg.join(tool), format!("-p {}\n", broker.port())).unwrap();
    }
    let admin = broker.admin.to_string();
    let bin_dir = Path::new(fbbus_bin()).parent().unwrap();
    let mut script = String::from("set -u\n");
    let mut subscribers = 0;
    for line in readme_try_it() {
        let mut line = line
            .replace("127.0.0.1:9883", &admin)
            .replace("fbbus devices", &format!("fbbus devices --admin {admin}"));
        if let Some(command) = without_comment(&line).strip_suffix('&') {
            let command = command.trim();
            subscribers += 1;
            line = format!("timeout 6 {command} > sub{subscribers}.out 2>&1 &\nsleep 1");
        }
        script.push_str(&line);
        script.push('\n');
    }
    script.push_str("wait\n");
    let path = std::env::var("PATH").unwrap_or_default();
    let (_, out, err) = run(
        Command::new("sh")
            .args(["-c", &script])
            .current_dir(dir)
            .env("XDG_CONFIG_HOME", &xdg)
            .env("PATH", format!("{}:{path}", bin_dir.display())),
        LIMIT,
    );
    let sub = |n: u32| std::fs::read_to_string(dir.join(format!("sub{n}.out"))).unwrap_or_default();
    let (json, fbdk) = (sub(1), sub(2));
    let all = format!(
        "--- script\n{script}\n--- stdout\n{out}\n--- stderr\n{err}\n--- sub1\n{json}\n\
         --- sub2\n{fbdk}\n--- broker\n{}",
        broker.log_text()
    );
    assert_eq!(subscribers, 2, "{all}");
    // The value, as JSON on fb/ and as fbdk bytes in hex; each once.
    assert_eq!(json.matches("fb/plc-1/CONV/SPEED 3\n").count(), 1, "{all}");
    assert_eq!(fbdk, "fbdk/plc-1/CONV/SPEED 430003\n", "{all}");
    // The 3.1.1 refusal is on diag, as the README says; the MQTT 5 one is told.
    assert_eq!(
        json.matches(r#"fbbus/diag/plc-1 {"code":153,"detail":"CONV.SPEED: SPEED: 70000 is out of range for INT""#)
            .count(),
        2,
        "{all}"
    );
    assert!(
        !json.contains("70000\n"),
        "a refused value was delivered\n{all}"
    );
    assert!(
        err.contains("Warning: Publish 1 failed: Payload format invalid."),
        "{all}"
    );
    // The registry: offline after the last mosquitto_pub's clean disconnect.
    let row = out
        .lines()
        .find(|l| l.starts_with("plc-1 "))
        .unwrap_or_else(|| panic!("no plc-1 row\n{all}"));
    assert!(
        row.contains("offline") && row.contains("clean disconnect"),
        "{all}"
    );
    assert!(
        out.contains("fbbus_typed_messages_accepted_total 1\n"),
        "{all}"
    );
}

/// A TOML error shows the file, the line and column and toml's caret drawing as toml
/// formats it, over several lines; a syntax error does not claim a key.
#[test]
fn a_broken_config_file_is_shown_where_it_is_broken() {
    let dir = tempfile::tempdir().unwrap();
    let unclosed = write(dir.path(), "unclosed.toml", "[broker\nline = \"a\"\n");
    let (ok, _, err) = fbbus(&["check-config", &unclosed]);
    assert!(!ok);
    assert!(
        err.starts_with(&format!("fbbus: config file {unclosed}: not TOML:\n")),
        "{err}"
    );
    assert!(
        err.contains("TOML parse error at line 1, column 8\n  |\n1 | [broker\n  |        ^\n"),
        "{err}"
    );
    assert!(!err.contains("key `.`"), "{err}");

    let typed = write(
        dir.path(),
        "typed.toml",
        "[broker]\nmax_connections = \"many\"\n",
    );
    let (ok, _, err) = fbbus(&["check-config", &typed]);
    assert!(!ok);
    assert!(
        err.contains(&format!(
            "config file {typed}: key `broker.max_connections`:\nTOML parse error at line 2, column 19\n"
        )),
        "{err}"
    );
    assert!(
        err.contains("2 | max_connections = \"many\"\n  |                   ^^^^^^\n"),
        "{err}"
    );
}

/// A missing config file: the OS error once, for `serve` and `check-config` alike.
#[test]
fn a_missing_config_file_is_said_once() {
    let dir = tempfile::tempdir().unwrap();
    let missing = dir.path().join("nowhere.toml");
    let missing = missing.to_str().unwrap();
    for args in [
        vec!["serve", "--config", missing],
        vec!["check-config", missing],
    ] {
        let (ok, _, err) = fbbus(&args);
        assert!(!ok);
        assert_eq!(
            err.trim_end(),
            format!(
                "fbbus: cannot read config file {missing}: No such file or directory (os error 2)"
            ),
            "{args:?}"
        );
    }
}

/// `passwd add` on a user the file has is refused without `--force` (the file unchanged)
/// and says how; with it the password is replaced, and says so.
#[test]
fn passwd_add_does_not_replace_a_password_without_force() {
    let dir = tempfile::tempdir().unwrap();
    let file = dir.path().join("passwd");
    add_user(&file, "plc-1", "first-secret");
    let before = std::fs::read_to_string(&file).unwrap();
    let add = |force: bool| {
        let mut args = vec!["passwd", file.to_str().unwrap(), "add", "plc-1", "--stdin"];
        if force {
            args.push("--force");
        }
        let mut cmd = Command::new(fbbus_bin());
        cmd.args(&args).stdin(std::process::Stdio::piped());
        let mut child = cmd
            .stdout(std::process::Stdio::piped())
            .stderr(std::process::Stdio::piped())
            .spawn()
            .unwrap();
        use std::io::Write;
        let _ = child.stdin.take().unwrap().write_all(b"second-secret\n");
        let out = child.wait_with_output().unwrap();
        (
            out.status.success(),
            String::from_utf8_lossy(&out.stderr).into_owned(),
        )
    };
    let (ok, err) = add(false);
    assert!(!ok, "{err}");
    assert!(
        err.contains("user `plc-1` already exists; nothing changed"),
        "{err}"
    );
    assert!(err.contains("add plc-1 --force"), "{err}");
    assert!(!err.contains("secret"), "{err}");
    assert_eq!(std::fs::read_to_string(&file).unwrap(), before);
    let (ok, err) = add(true);
    assert!(ok, "{err}");
    assert!(err.contains("user `plc-1` password replaced"), "{err}");
    assert_ne!(std::fs::read_to_string(&file).unwrap(), before);
}

/// `fbbus declare` against a broker without a profiles directory (the embedded default
/// has none) says how to give it one.
#[test]
fn declare_without_a_profiles_directory_says_how_to_set_one() {
    let broker = Broker::start();
    let profile = concat!(
        env!("CARGO_MANIFEST_DIR"),
        "/../deploy/profiles/conv2-forte.toml"
    );
    let admin = broker.admin.to_string();
    let (ok, _, err) = fbbus(&["declare", "--admin", &admin, profile]);
    assert!(!ok);
    assert!(
        err.contains("this broker has no profiles directory"),
        "{err}"
    );
    assert!(err.contains("profiles_dir = \"profiles\""), "{err}");
    assert!(err.contains("fbbus serve --config FILE"), "{err}");
}

//! Child processes with bounds, and the peers `.ci/run` installs (a missing one fails
//! in CI, and skips loudly elsewhere).

use std::io::{Read, Write};
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::time::{Duration, Instant};

use crate::fbbus_bin;

/// Writes `password` for `user` into a password file with `fbbus passwd ... --stdin`.
pub fn add_user(file: &Path, user: &str, password: &str) {
    let mut child = Command::new(fbbus_bin())
        .args(["passwd", file.to_str().unwrap(), "add", user, "--stdin"])
        .stdin(Stdio::piped())
        .stdout(Stdio::null())
        .stderr(Stdio::null())
        .spawn()
        .unwrap();
    child
        .stdin
        .take()
        .unwrap()
        .write_all(format!("{password}\n").as_bytes())
        .unwrap();
    let status = wait_until(&mut child, Duration::from_secs(30)).expect("fbbus passwd hung");
    assert!(status.success(), "fbbus passwd add {user} failed");
}

/// Waits for a child to exit, at most `limit`; kills and reaps it after that (None).
pub fn wait_until(child: &mut Child, limit: Duration) -> Option<std::process::ExitStatus> {
    let deadline = Instant::now() + limit;
    loop {
        if let Some(status) = child.try_wait().unwrap() {
            return Some(status);
        }
        if Instant::now() > deadline {
            let _ = child.kill();
            let _ = child.wait();
            return None;
        }
        std::thread::sleep(Duration::from_millis(20));
    }
}

/// Runs a command to completion with a timeout; returns (exit success, stdout, stderr).
pub fn run(cmd: &mut Command, limit: Duration) -> (bool, String, String) {
    let mut child = cmd
        .stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .spawn()
        .unwrap_or_else(|e| panic!("cannot run {cmd:?}: {e}"));
    let status = wait_until(&mut child, limit);
    let mut out = String::new();
    let mut err = String::new();
    if let Some(mut o) = child.stdout.take() {
        let _ = o.read_to_string(&mut out);
    }
    if let Some(mut e) = child.stderr.take() {
        let _ = e.read_to_string(&mut err);
    }
    match status {
        Some(status) => (status.success(), out, err),
        None => (false, out, format!("timed out; {err}")),
    }
}

/// Whether a program is on PATH (CI installs them; a developer machine may not have them).
pub fn have(program: &str) -> bool {
    Command::new("sh")
        .args(["-c", &format!("command -v {program}")])
        .stdout(Stdio::null())
        .status()
        .map(|s| s.success())
        .unwrap_or(false)
}

/// A file of an npm package `.ci/run` installs (MQTT.js, Node-RED) into `FBBUS_NPM_DIR`,
/// or `~/.cache/fbbus/npm`: `node_modules/<file>`. Missing: a failure in CI, elsewhere
/// None with the test skipped loudly.
pub fn npm_file(file: &str) -> Option<PathBuf> {
    let dir = std::env::var_os("FBBUS_NPM_DIR")
        .map(PathBuf::from)
        .or_else(|| std::env::var_os("HOME").map(|h| Path::new(&h).join(".cache/fbbus/npm")))?;
    let path = dir.join("node_modules").join(file);
    if path.is_file() {
        return Some(path);
    }
    if std::env::var_os("CI").is_some() {
        panic!(
            "{} missing; .ci/run should have installed it",
            path.display()
        );
    }
    eprintln!("SKIPPED: {} missing (run .ci/run)", path.display());
    None
}

/// Requires a program; in CI its absence is a failure, elsewhere the test is skipped loudly.
pub fn require(program: &str) -> bool {
    if have(program) {
        return true;
    }
    if std::env::var_os("CI").is_some() {
        panic!("{program} is not installed; .ci/run should have installed it");
    }
    eprintln!("SKIPPED: {program} not installed (run .ci/run or install it)");
    false
}

/// python3 with paho-mqtt 2.x importable; in CI its absence is a failure (`.ci/run`
/// installs it), elsewhere the test is skipped loudly.
pub fn require_paho() -> bool {
    if !require("python3") {
        return false;
    }
    let ok = Command::new("python3")
        .args([
            "-c",
            "import sys, paho.mqtt, paho.mqtt.client; \
             sys.exit(int(paho.mqtt.__version__.split('.')[0]) < 2)",
        ])
        .stdout(Stdio::null())
        .stderr(Stdio::null())
        .status()
        .is_ok_and(|s| s.success());
    if ok {
        return true;
    }
    if std::env::var_os("CI").is_some() {
        panic!("python3 has no paho-mqtt 2.x; .ci/run should have installed it");
    }
    eprintln!("SKIPPED: python3 has no paho-mqtt 2.x (pip install 'paho-mqtt>=2')");
    false
}

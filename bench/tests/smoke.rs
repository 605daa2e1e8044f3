//! Smoke test: `fbbus-bench --quick --brokers fbbus --scenarios fanin,connrate` runs against
//! the fbbus binary of the same target directory and prints a numeric msg/s figure for fbbus.
//! Skipped (with a message) when that binary has not been built, e.g. with
//! `cargo test -p fbbus-bench` alone; `cargo test --workspace` builds it first.

use std::io::Read;
use std::path::{Path, PathBuf};
use std::process::{Command, Stdio};
use std::time::{Duration, Instant};

fn fbbus_binary() -> Option<PathBuf> {
    let beside_bench = Path::new(env!("CARGO_BIN_EXE_fbbus-bench")).with_file_name("fbbus");
    let default_target = PathBuf::from(concat!(
        env!("CARGO_MANIFEST_DIR"),
        "/../target/debug/fbbus"
    ));
    [beside_bench, default_target]
        .into_iter()
        .find(|p| p.is_file())
}

/// "312.4k" -> 312400.0
fn parse_si(token: &str) -> Option<f64> {
    let (number, factor) = match token.strip_suffix('k') {
        Some(n) => (n, 1e3),
        None => match token.strip_suffix('M') {
            Some(n) => (n, 1e6),
            None => (token, 1.0),
        },
    };
    number.parse::<f64>().ok().map(|v| v * factor)
}

#[test]
fn quick_fanin_and_connrate_against_fbbus() {
    let Some(fbbus) = fbbus_binary() else {
        eprintln!(
            "skipping the fbbus-bench smoke test: no fbbus binary beside {} \
             (run `cargo build -p broker` or `cargo test --workspace`)",
            env!("CARGO_BIN_EXE_fbbus-bench")
        );
        return;
    };
    let started = Instant::now();
    let mut child = Command::new(env!("CARGO_BIN_EXE_fbbus-bench"))
        .args([
            "--quick",
            "--brokers",
            "fbbus",
            "--scenarios",
            "fanin,connrate",
            "--fbbus",
        ])
        .arg(&fbbus)
        .stdin(Stdio::null())
        .stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .spawn()
        .expect("start fbbus-bench");
    let mut stdout = child.stdout.take().expect("stdout");
    let mut stderr = child.stderr.take().expect("stderr");
    let out_reader = std::thread::spawn(move || {
        let mut s = String::new();
        stdout.read_to_string(&mut s).ok();
        s
    });
    let err_reader = std::thread::spawn(move || {
        let mut s = String::new();
        stderr.read_to_string(&mut s).ok();
        s
    });
    let deadline = started + Duration::from_secs(60);
    let status = loop {
        if let Some(status) = child.try_wait().expect("wait for fbbus-bench") {
            break Some(status);
        }
        if Instant::now() > deadline {
            child.kill().ok();
            child.wait().ok();
            break None;
        }
        std::thread::sleep(Duration::from_millis(50));
    };
    let elapsed = started.elapsed();
    let out = out_reader.join().unwrap_or_default();
    let err = err_reader.join().unwrap_or_default();
    let status = status.unwrap_or_else(|| {
        panic!("fbbus-bench did not finish in 60 s\nstdout:\n{out}\nstderr:\n{err}")
    });
    assert!(
        status.success(),
        "fbbus-bench failed: {status}\nstdout:\n{out}\nstderr:\n{err}"
    );

    // The ratio line: `burst fan-in (...)   fbbus 312.4k msg/s ...`
    let line = out
        .lines()
        .find(|l| l.starts_with("burst fan-in"))
        .unwrap_or_else(|| panic!("no fan-in result line in:\n{out}"));
    let tokens: Vec<&str> = line.split_whitespace().collect();
    let at = tokens
        .iter()
        .position(|t| *t == "fbbus")
        .unwrap_or_else(|| panic!("no fbbus figure in {line:?}"));
    let rate = tokens.get(at + 1).and_then(|t| parse_si(t));
    assert!(
        matches!(rate, Some(r) if r > 0.0) && tokens.get(at + 2) == Some(&"msg/s"),
        "fbbus msg/s is not a number in {line:?}\n{out}"
    );
    assert!(
        out.lines()
            .any(|l| l.starts_with("connections per second") && l.contains("conn/s")),
        "no connection-rate figure in:\n{out}"
    );
    assert!(
        elapsed < Duration::from_secs(30),
        "the quick smoke run took {elapsed:?}"
    );
}

/// `fbbus-bench bridge --quick` links two fbbus lines over zenoh and reports the hop.
#[test]
fn quick_bridge_scenario_reports_the_hop() {
    let Some(fbbus) = fbbus_binary() else {
        eprintln!("skipping the bridge smoke test: no fbbus binary built");
        return;
    };
    let mut child = Command::new(env!("CARGO_BIN_EXE_fbbus-bench"))
        .args(["bridge", "--quick", "--fbbus"])
        .arg(&fbbus)
        .stdin(Stdio::null())
        .stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .spawn()
        .expect("start fbbus-bench bridge");
    let mut stdout = child.stdout.take().expect("stdout");
    let started = Instant::now();
    let status = loop {
        if let Some(status) = child.try_wait().unwrap() {
            break status;
        }
        if started.elapsed() > Duration::from_secs(120) {
            let _ = child.kill();
            panic!("fbbus-bench bridge --quick took more than 120 s");
        }
        std::thread::sleep(Duration::from_millis(100));
    };
    let mut out = String::new();
    stdout.read_to_string(&mut out).unwrap();
    let mut err = String::new();
    child
        .stderr
        .take()
        .unwrap()
        .read_to_string(&mut err)
        .unwrap();
    assert!(status.success(), "fbbus-bench bridge failed:\n{out}\n{err}");
    let across = out
        .lines()
        .find(|l| l.starts_with("A -> B"))
        .unwrap_or_else(|| panic!("no A -> B row:\n{out}"));
    assert!(
        across.ends_with("2000/2000"),
        "every burst message crossed: {across}"
    );
    assert!(out.contains("hop adds"), "{out}");
}

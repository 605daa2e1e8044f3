//! Test support of the harness's tests: the shared kit (`fbbus_testkit`: the real
//! `fbbus` binary on free loopback ports, bounded processes), re-exported here, and what
//! only these tests use: Debian's Mosquitto as a peer, the harness binary run to
//! completion with a bound, and readers for its outputs.
#![allow(dead_code, unused_imports)]

use std::io::Read;
use std::net::{SocketAddr, TcpStream};
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::time::{Duration, Instant};

use loadtest::model::Report;

pub use fbbus_testkit::{
    add_user, fbbus_bin, free_port, have, http_get, require, wait_until, Broker as Fbbus, Options,
};

/// Every harness run in these tests is tiny: none should come near this.
pub const RUN_LIMIT: Duration = Duration::from_secs(120);

/// An fbbus line `line` for the harness: `top` (TOML tables after `[broker]`: `[auth]`
/// ...), `listener` (keys of the main listener), `bottom` (tables at the end: `[bridge]`);
/// `prepare` writes files into its directory first. zenoh logs only its warnings.
pub fn fbbus_with(
    line: &str,
    top: &str,
    listener: &str,
    bottom: &str,
    prepare: impl FnOnce(&Path),
) -> Fbbus {
    Fbbus::start_with(
        Options {
            line: line.into(),
            extra: top.into(),
            listener_extra: listener.into(),
            tables: bottom.into(),
            log_level: "info,rumqttd=warn,zenoh=warn".into(),
            ..Options::default()
        },
        prepare,
    )
}

/// Waits (bounded) until something accepts TCP connections on `addr`.
fn wait_listening(addr: SocketAddr, child: &mut Child, what: &str, log: &Path) {
    let deadline = Instant::now() + Duration::from_secs(20);
    loop {
        if let Ok(Some(status)) = child.try_wait() {
            panic!("{what} exited with {status}: {}", read(log));
        }
        if TcpStream::connect_timeout(&addr, Duration::from_millis(200)).is_ok() {
            return;
        }
        assert!(
            Instant::now() < deadline,
            "{what} not listening on {addr} within 20 s: {}",
            read(log)
        );
        std::thread::sleep(Duration::from_millis(30));
    }
}

fn read(path: &Path) -> String {
    std::fs::read_to_string(path).unwrap_or_default()
}

/// Debian's Mosquitto on a free loopback port, anonymous, TCP_NODELAY, killed when
/// dropped. `None` (after a loud SKIPPED) when it is not installed outside CI.
pub struct Mosquitto {
    child: Child,
    pub addr: SocketAddr,
    _dir: tempfile::TempDir,
}

impl Mosquitto {
    pub fn start() -> Option<Mosquitto> {
        // Debian installs it in /usr/sbin, which a non-root PATH may lack.
        let program = if have("mosquitto") {
            PathBuf::from("mosquitto")
        } else if Path::new("/usr/sbin/mosquitto").is_file() {
            PathBuf::from("/usr/sbin/mosquitto")
        } else {
            // Panics in CI, skips loudly elsewhere.
            require("mosquitto");
            return None;
        };
        let dir = tempfile::tempdir().unwrap();
        let port = free_port();
        let config = dir.path().join("mosquitto.conf");
        std::fs::write(
            &config,
            format!("listener {port} 127.0.0.1\nallow_anonymous true\nset_tcp_nodelay true\n"),
        )
        .unwrap();
        let log = dir.path().join("mosquitto.log");
        let mut child = Command::new(&program)
            .arg("-c")
            .arg(&config)
            .current_dir(dir.path())
            .stdout(Stdio::null())
            .stderr(std::fs::File::create(&log).unwrap())
            .spawn()
            .expect("mosquitto starts");
        let addr: SocketAddr = format!("127.0.0.1:{port}").parse().unwrap();
        wait_listening(addr, &mut child, "mosquitto", &log);
        Some(Mosquitto {
            child,
            addr,
            _dir: dir,
        })
    }

    pub fn url(&self) -> String {
        format!("mqtt://{}", self.addr)
    }
}

impl Drop for Mosquitto {
    fn drop(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

/// One finished run of `fbbus-loadtest`, with its output directory.
pub struct Run {
    pub success: bool,
    pub stdout: String,
    pub stderr: String,
    pub out: tempfile::TempDir,
}

impl Run {
    pub fn path(&self, name: &str) -> PathBuf {
        self.out.path().join(name)
    }

    pub fn file(&self, name: &str) -> String {
        std::fs::read_to_string(self.path(name))
            .unwrap_or_else(|e| panic!("{name}: {e}\n{}", self.context()))
    }

    /// `report.json`, parsed into the harness's own model.
    pub fn report(&self) -> Report {
        serde_json::from_str(&self.file("report.json"))
            .unwrap_or_else(|e| panic!("report.json does not parse: {e}"))
    }

    /// `batches.csv` (or the JTL) as rows of named fields; the header must be `header`.
    pub fn table(&self, name: &str, header: &[&str]) -> Vec<Vec<(String, String)>> {
        let rows = parse_csv(&self.file(name));
        assert_eq!(rows[0], header, "{name}: header");
        rows[1..]
            .iter()
            .map(|r| {
                assert_eq!(r.len(), header.len(), "{name}: row {r:?}");
                header
                    .iter()
                    .map(|h| h.to_string())
                    .zip(r.iter().cloned())
                    .collect()
            })
            .collect()
    }

    /// Panics with the run's output: what a failed assertion needs to be read.
    pub fn context(&self) -> String {
        format!(
            "--- stdout ---\n{}\n--- stderr ---\n{}",
            self.stdout, self.stderr
        )
    }

    /// Asserts the run succeeded and returns its report.
    pub fn ok(&self) -> Report {
        assert!(self.success, "fbbus-loadtest failed\n{}", self.context());
        self.report()
    }
}

/// Runs `fbbus-loadtest --out <tempdir> --ceiling 500 --quiet-ms 300 ARGS` with `env`,
/// bounded by [`RUN_LIMIT`].
pub fn loadtest(args: &[&str], env: &[(&str, &str)]) -> Run {
    let out = tempfile::tempdir().unwrap();
    let mut cmd = Command::new(env!("CARGO_BIN_EXE_fbbus-loadtest"));
    cmd.arg("--out")
        .arg(out.path())
        .args(["--ceiling", "500", "--quiet-ms", "300"])
        .args(args)
        .env_remove("MQTT_PASSWORD")
        .envs(env.iter().copied())
        .stdin(Stdio::null())
        .stdout(Stdio::piped())
        .stderr(Stdio::piped());
    let mut child = cmd
        .spawn()
        .unwrap_or_else(|e| panic!("cannot run {cmd:?}: {e}"));
    // Read both pipes on threads so a full pipe never blocks the child.
    let mut so = child.stdout.take().unwrap();
    let mut se = child.stderr.take().unwrap();
    let stdout = std::thread::spawn(move || {
        let mut s = String::new();
        let _ = so.read_to_string(&mut s);
        s
    });
    let stderr = std::thread::spawn(move || {
        let mut s = String::new();
        let _ = se.read_to_string(&mut s);
        s
    });
    let status = wait_until(&mut child, RUN_LIMIT);
    let stdout = stdout.join().unwrap();
    let mut stderr = stderr.join().unwrap();
    if status.is_none() {
        stderr = format!("KILLED after {RUN_LIMIT:?}\n{stderr}");
    }
    Run {
        success: status.is_some_and(|s| s.success()),
        stdout,
        stderr,
        out,
    }
}

/// RFC 4180 records (quoted fields, doubled quotes), `\n` or `\r\n` line ends.
pub fn parse_csv(text: &str) -> Vec<Vec<String>> {
    let mut rows = Vec::new();
    let mut row = Vec::new();
    let mut field = String::new();
    let mut quoted = false;
    let mut chars = text.chars().peekable();
    while let Some(c) = chars.next() {
        match (quoted, c) {
            (true, '"') if chars.peek() == Some(&'"') => {
                chars.next();
                field.push('"');
            }
            (true, '"') => quoted = false,
            (true, c) => field.push(c),
            (false, '"') => quoted = true,
            (false, ',') => row.push(std::mem::take(&mut field)),
            (false, '\r') => {}
            (false, '\n') => {
                row.push(std::mem::take(&mut field));
                rows.push(std::mem::take(&mut row));
            }
            (false, c) => field.push(c),
        }
    }
    if !field.is_empty() || !row.is_empty() {
        row.push(field);
        rows.push(row);
    }
    rows
}

/// The value of column `name` in a row from [`Run::table`].
pub fn col<'a>(row: &'a [(String, String)], name: &str) -> &'a str {
    &row.iter()
        .find(|(h, _)| h == name)
        .unwrap_or_else(|| panic!("no column {name}"))
        .1
}

/// The points of the SVG polyline tagged `data-series="<series>"`, if any.
pub fn svg_series(svg: &str, series: &str) -> Option<Vec<(i64, i64)>> {
    let tag = format!("data-series=\"{series}\"");
    let at = svg.find(&tag)?;
    let element = &svg[at..at + svg[at..].find('>')?];
    let points = element.split("points=\"").nth(1)?.split('"').next()?;
    Some(
        points
            .split_whitespace()
            .map(|p| {
                let (x, y) = p.split_once(',').expect("x,y");
                (x.parse().unwrap(), y.parse().unwrap())
            })
            .collect(),
    )
}

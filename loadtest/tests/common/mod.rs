//! Test support: the real `fbbus` binary and Debian's Mosquitto on free loopback ports,
//! the harness binary run to completion with a bound, and readers for its outputs.
#![allow(dead_code)]

use std::io::{Read, Write};
use std::net::{SocketAddr, TcpStream};
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::sync::OnceLock;
use std::time::{Duration, Instant};

use loadtest::model::Report;

/// Every harness run in these tests is tiny: none should come near this.
pub const RUN_LIMIT: Duration = Duration::from_secs(120);

/// A TCP port on 127.0.0.1 that was free a moment ago, below Linux's ephemeral range
/// (why: [`loadtest::broker_process::spawn::free_port`]).
pub fn free_port() -> u16 {
    loadtest::broker_process::spawn::free_port().expect("a free port on 127.0.0.1")
}

/// The `fbbus` broker binary. It is not a CARGO_BIN_EXE of this package: it sits next to
/// this test executable's profile directory (target/debug/deps/.. -> target/debug/fbbus),
/// where `cargo test --workspace` builds it. If it is missing it is built once.
pub fn fbbus_bin() -> &'static Path {
    static BIN: OnceLock<PathBuf> = OnceLock::new();
    BIN.get_or_init(|| {
        let exe = std::env::current_exe().expect("the test executable's path");
        let profile_dir = exe
            .parent()
            .and_then(Path::parent)
            .expect("the test executable lives in <target>/<profile>/deps");
        let bin = profile_dir.join("fbbus");
        if bin.is_file() {
            return bin;
        }
        eprintln!(
            "{} is missing: building it with `cargo build -p broker --bin fbbus` (once)",
            bin.display()
        );
        let cargo = std::env::var("CARGO").unwrap_or_else(|_| "cargo".into());
        let manifest = Path::new(env!("CARGO_MANIFEST_DIR")).join("../Cargo.toml");
        let mut cmd = Command::new(cargo);
        cmd.args(["build", "-p", "broker", "--bin", "fbbus", "--manifest-path"])
            .arg(&manifest);
        if let Some(target_dir) = profile_dir.parent() {
            cmd.arg("--target-dir").arg(target_dir);
        }
        if profile_dir.file_name().is_some_and(|n| n == "release") {
            cmd.arg("--release");
        }
        let status = cmd
            .status()
            .unwrap_or_else(|e| panic!("cannot run {cmd:?}: {e}"));
        assert!(
            status.success() && bin.is_file(),
            "`cargo build -p broker --bin fbbus` failed ({status}); build the broker first \
             (`cargo build -p broker`) so that {} exists",
            bin.display()
        );
        bin
    })
}

/// Whether a program is on PATH.
pub fn have(program: &str) -> bool {
    Command::new("sh")
        .args(["-c", &format!("command -v {program}")])
        .stdout(Stdio::null())
        .status()
        .map(|s| s.success())
        .unwrap_or(false)
}

/// Requires a program; in CI (.ci/run installs it) its absence is a failure, elsewhere
/// the test is skipped loudly.
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

/// Writes `password` for `user` into a password file with `fbbus passwd FILE add USER
/// --stdin`.
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

/// An `fbbus` broker as a child process, killed when dropped.
pub struct Fbbus {
    child: Child,
    pub mqtt: SocketAddr,
    pub admin: SocketAddr,
    pub dir: tempfile::TempDir,
    log: PathBuf,
}

impl Fbbus {
    /// Anonymous loopback broker.
    pub fn start() -> Fbbus {
        Fbbus::start_with("test", "", "", "", |_| {})
    }

    /// `top`: TOML tables after `[broker]` (`[auth]` ...); `listener`: keys of the main
    /// listener; `bottom`: tables at the end (`[bridge]`). `prepare` may write files into
    /// the broker's directory (its working directory) before it starts.
    pub fn start_with(
        line: &str,
        top: &str,
        listener: &str,
        bottom: &str,
        prepare: impl FnOnce(&Path),
    ) -> Fbbus {
        let dir = tempfile::tempdir().unwrap();
        prepare(dir.path());
        let mqtt: SocketAddr = format!("127.0.0.1:{}", free_port()).parse().unwrap();
        let admin: SocketAddr = format!("127.0.0.1:{}", free_port()).parse().unwrap();
        let config = dir.path().join("fbbus.toml");
        std::fs::write(
            &config,
            format!(
                "[broker]\nline = \"{line}\"\nconnect_timeout_ms = 2000\n{top}\n\
                 [[listener]]\nname = \"main\"\nbind = \"{mqtt}\"\n{listener}\n\
                 [admin]\nbind = \"{admin}\"\n\
                 [log]\nlevel = \"info,rumqttd=warn,zenoh=warn\"\n{bottom}\n"
            ),
        )
        .unwrap();
        let log = dir.path().join("broker.log");
        let child = Command::new(fbbus_bin())
            .args(["serve", "--config", config.to_str().unwrap()])
            .current_dir(dir.path())
            .env_remove("RUST_LOG")
            .stdout(Stdio::null())
            .stderr(std::fs::File::create(&log).unwrap())
            .spawn()
            .unwrap();
        let mut broker = Fbbus {
            child,
            mqtt,
            admin,
            dir,
            log,
        };
        broker.wait_ready();
        broker
    }

    fn wait_ready(&mut self) {
        let deadline = Instant::now() + Duration::from_secs(20);
        loop {
            if let Ok(Some(status)) = self.child.try_wait() {
                panic!("fbbus exited with {status}: {}", self.log_text());
            }
            if http_get(self.admin, "/readyz").is_some_and(|(code, _)| code == 200) {
                return;
            }
            assert!(
                Instant::now() < deadline,
                "fbbus not ready in 20 s: {}",
                self.log_text()
            );
            std::thread::sleep(Duration::from_millis(50));
        }
    }

    pub fn url(&self) -> String {
        format!("mqtt://{}", self.mqtt)
    }

    /// The broker's Prometheus endpoint.
    pub fn metrics_url(&self) -> String {
        format!("http://{}/metrics", self.admin)
    }

    pub fn pid(&self) -> u32 {
        self.child.id()
    }

    /// Kills the broker now (SIGKILL), as a crash would end it; not reaped.
    pub fn kill_now(&self) {
        let _ = Command::new("kill")
            .args(["-KILL", &self.child.id().to_string()])
            .status();
    }

    pub fn log_text(&self) -> String {
        read(&self.log)
    }

    /// The value of one Prometheus series; 0 if absent.
    pub fn metric(&self, series: &str) -> f64 {
        let text = http_get(self.admin, "/metrics")
            .map(|r| r.1)
            .unwrap_or_default();
        text.lines()
            .filter(|l| !l.starts_with('#'))
            .find_map(|l| {
                let (name, value) = l.rsplit_once(' ')?;
                (name == series).then(|| value.parse().ok())?
            })
            .unwrap_or(0.0)
    }

    /// Waits (bounded) until `series` reaches `min`.
    pub fn wait_metric(&self, series: &str, min: f64, within: Duration) {
        let deadline = Instant::now() + within;
        while self.metric(series) < min {
            assert!(
                Instant::now() < deadline,
                "{series} < {min} after {within:?}\n{}",
                self.log_text()
            );
            std::thread::sleep(Duration::from_millis(20));
        }
    }
}

impl Drop for Fbbus {
    fn drop(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
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

/// A minimal HTTP/1.0 GET: (status code, body).
pub fn http_get(addr: SocketAddr, path: &str) -> Option<(u16, String)> {
    let mut s = TcpStream::connect_timeout(&addr, Duration::from_secs(2)).ok()?;
    s.set_read_timeout(Some(Duration::from_secs(5))).ok()?;
    write!(s, "GET {path} HTTP/1.0\r\nHost: localhost\r\n\r\n").ok()?;
    let mut text = String::new();
    s.read_to_string(&mut text).ok()?;
    let code = text.split_whitespace().nth(1)?.parse().ok()?;
    let body = text.split_once("\r\n\r\n").map(|(_, b)| b.to_owned())?;
    Some((code, body))
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

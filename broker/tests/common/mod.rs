//! Test support: the real `fbbus` binary on free loopback ports, and small clients.
#![allow(dead_code)]

pub mod bus;
pub mod clients;
pub mod fb;
pub mod netns;
pub mod pki;
pub mod raw;

use std::io::{Read, Write};
use std::net::{SocketAddr, TcpListener, TcpStream};
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::time::{Duration, Instant};

/// A TCP port on 127.0.0.1 that was free a moment ago, below Linux's ephemeral range.
///
/// Why not `bind(0)`: the kernel hands out ports for outgoing connections (every client a
/// test opens, thousands in the storm tests) from that same ephemeral range (32768-60999
/// by default); a port picked there and released could be taken by a client's connect
/// before the broker bound it, and the broker failed to start with `Address already in
/// use` (seen in CI). Ports 20000-32767 are never handed out that way; they are tried in
/// a pseudo-random order, so parallel tests rarely try the same one.
pub fn free_port() -> u16 {
    use std::sync::atomic::{AtomicU64, Ordering};
    static NEXT: AtomicU64 = AtomicU64::new(0);
    // Never the same port twice in one test process: a port handed out and not bound yet
    // (a test picks its listeners' ports before the broker starts) looks free to the next
    // caller too, and two of them once got one port (CI: `Address already in use`).
    static GIVEN: std::sync::Mutex<Vec<u16>> = std::sync::Mutex::new(Vec::new());
    let mut given = GIVEN
        .lock()
        .unwrap_or_else(std::sync::PoisonError::into_inner);
    let seed = std::time::SystemTime::now()
        .duration_since(std::time::UNIX_EPOCH)
        .map_or(0, |d| d.as_nanos() as u64)
        ^ (u64::from(std::process::id()) << 20);
    for _ in 0..1000 {
        let n = NEXT.fetch_add(0x9E37_79B9_7F4A_7C15, Ordering::Relaxed) ^ seed;
        let port = 20_000 + (n.wrapping_mul(0xBF58_476D_1CE4_E5B9) >> 33) % 12_768;
        let port = port as u16;
        if !given.contains(&port) && TcpListener::bind(("127.0.0.1", port)).is_ok() {
            given.push(port);
            return port;
        }
    }
    TcpListener::bind("127.0.0.1:0")
        .unwrap()
        .local_addr()
        .unwrap()
        .port()
}

pub fn fbbus_bin() -> &'static str {
    env!("CARGO_BIN_EXE_fbbus")
}

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
    assert!(child.wait().unwrap().success(), "fbbus passwd add failed");
}

/// The broker as a child process, killed when dropped.
pub struct Broker {
    pub child: Child,
    pub mqtt: SocketAddr,
    pub admin: SocketAddr,
    pub dir: tempfile::TempDir,
    pub log: PathBuf,
    pub config: PathBuf,
    /// The `Authorization` header value this harness sends to the admin endpoint (its
    /// readiness poll, `metrics`) when the config sets `[admin] password_file`.
    pub admin_authorization: Option<String>,
}

pub struct Options {
    /// TOML appended after `[broker]` and before the listener: `[auth]` sections etc.
    pub extra: String,
    /// Extra keys for the main listener table.
    pub listener_extra: String,
    /// Extra keys for the `[admin]` table.
    pub admin_extra: String,
    pub log_level: String,
    /// `text` or `json`.
    pub log_format: &'static str,
    /// Environment variables for the broker process (the test-only fault hooks).
    pub env: Vec<(&'static str, String)>,
}

impl Default for Options {
    fn default() -> Self {
        Options {
            extra: String::new(),
            listener_extra: String::new(),
            admin_extra: String::new(),
            log_level: "info,rumqttd=warn".into(),
            log_format: "text",
            env: Vec::new(),
        }
    }
}

impl Broker {
    /// Anonymous loopback broker.
    pub fn start() -> Broker {
        Broker::start_with(Options::default(), |_| {})
    }

    /// `prepare` may write files into the broker's directory before it starts.
    pub fn start_with(options: Options, prepare: impl FnOnce(&Path)) -> Broker {
        let dir = tempfile::tempdir().unwrap();
        prepare(dir.path());
        let mqtt: SocketAddr = format!("127.0.0.1:{}", free_port()).parse().unwrap();
        let admin: SocketAddr = format!("127.0.0.1:{}", free_port()).parse().unwrap();
        let config = dir.path().join("fbbus.toml");
        std::fs::write(
            &config,
            format!(
                "[broker]\nline = \"test\"\nconnect_timeout_ms = 2000\n{extra}\n\
                 [[listener]]\nname = \"main\"\nbind = \"{mqtt}\"\n{lextra}\n\
                 [admin]\nbind = \"{admin}\"\n{aextra}\n\
                 [log]\nlevel = \"{level}\"\nformat = \"{format}\"\n",
                extra = options.extra,
                lextra = options.listener_extra,
                aextra = options.admin_extra,
                level = options.log_level,
                format = options.log_format,
            ),
        )
        .unwrap();
        Broker::spawn_with_env(dir, config, mqtt, admin, &options.env)
    }

    /// Starts the broker on a complete config file the caller wrote.
    pub fn spawn(
        dir: tempfile::TempDir,
        config: PathBuf,
        mqtt: SocketAddr,
        admin: SocketAddr,
    ) -> Broker {
        Broker::spawn_with_env(dir, config, mqtt, admin, &[])
    }

    /// [`Broker::spawn`] with environment variables for the broker process.
    pub fn spawn_with_env(
        dir: tempfile::TempDir,
        config: PathBuf,
        mqtt: SocketAddr,
        admin: SocketAddr,
        env: &[(&'static str, String)],
    ) -> Broker {
        Broker::spawn_as(dir, config, mqtt, admin, env, None)
    }

    /// [`Broker::spawn_with_env`] for a config whose admin endpoint wants credentials
    /// (`[admin] password_file`): the harness sends `admin_authorization` (an
    /// `Authorization` header value) to it.
    pub fn spawn_as(
        dir: tempfile::TempDir,
        config: PathBuf,
        mqtt: SocketAddr,
        admin: SocketAddr,
        env: &[(&'static str, String)],
        admin_authorization: Option<String>,
    ) -> Broker {
        let log = dir.path().join("broker.log");
        let child = Command::new(fbbus_bin())
            .args(["serve", "--config", config.to_str().unwrap()])
            .env_remove("RUST_LOG")
            .envs(env.iter().map(|(k, v)| (*k, v.as_str())))
            .stdout(Stdio::null())
            .stderr(std::fs::File::create(&log).unwrap())
            .spawn()
            .unwrap();
        let mut broker = Broker {
            child,
            mqtt,
            admin,
            dir,
            log,
            config,
            admin_authorization,
        };
        broker.wait_ready();
        broker
    }

    fn wait_ready(&mut self) {
        let deadline = Instant::now() + Duration::from_secs(20);
        while Instant::now() < deadline {
            if let Ok(Some(status)) = self.child.try_wait() {
                panic!("broker exited with {status}: {}", self.log_text());
            }
            let auth = self.admin_authorization.as_deref();
            if http_get_as(self.admin, "/readyz", auth).is_some_and(|(code, _)| code == 200) {
                return;
            }
            std::thread::sleep(Duration::from_millis(50));
        }
        panic!("broker not ready in 20 s: {}", self.log_text());
    }

    pub fn port(&self) -> u16 {
        self.mqtt.port()
    }

    pub fn log_text(&self) -> String {
        std::fs::read_to_string(&self.log).unwrap_or_default()
    }

    pub fn metrics(&self) -> String {
        http_get_as(self.admin, "/metrics", self.admin_authorization.as_deref())
            .expect("metrics")
            .1
    }

    /// The value of one series, e.g. `fbbus_acl_denied_total{action="publish"}`; 0 if absent.
    pub fn metric(&self, series: &str) -> f64 {
        metric_value(&self.metrics(), series)
    }

    /// Waits until `series` reaches at least `min` (metrics are updated asynchronously).
    pub fn wait_metric(&self, series: &str, min: f64) -> f64 {
        let deadline = Instant::now() + Duration::from_secs(10);
        loop {
            let v = self.metric(series);
            if v >= min || Instant::now() > deadline {
                return v;
            }
            std::thread::sleep(Duration::from_millis(50));
        }
    }

    pub fn signal(&self, signal: &str) {
        let status = Command::new("kill")
            .args([&format!("-{signal}"), &self.child.id().to_string()])
            .status()
            .unwrap();
        assert!(status.success());
    }

    pub fn path(&self, name: &str) -> PathBuf {
        self.dir.path().join(name)
    }

    /// Stops the broker with `signal` ("TERM", "KILL"), waits until it exited, and starts
    /// it again on the same config, directory and ports; its log goes on in the same file.
    pub fn restart(&mut self, signal: &str) {
        self.signal(signal);
        wait_until(&mut self.child, Duration::from_secs(15)).expect("the broker did not stop");
        self.start_again();
    }

    /// Starts the broker again after it exited, on the same config, directory and ports.
    pub fn start_again(&mut self) {
        let log = std::fs::OpenOptions::new()
            .append(true)
            .open(&self.log)
            .unwrap();
        self.child = Command::new(fbbus_bin())
            .args(["serve", "--config", self.config.to_str().unwrap()])
            .env_remove("RUST_LOG")
            .stdout(Stdio::null())
            .stderr(log)
            .spawn()
            .unwrap();
        self.wait_ready();
    }
}

impl Drop for Broker {
    fn drop(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

pub fn metric_value(text: &str, series: &str) -> f64 {
    text.lines()
        .filter(|l| !l.starts_with('#'))
        .find_map(|l| {
            let (name, value) = l.rsplit_once(' ')?;
            (name == series).then(|| value.parse().ok())?
        })
        .unwrap_or(0.0)
}

/// A minimal HTTP/1.0 GET: (status code, body).
pub fn http_get(addr: SocketAddr, path: &str) -> Option<(u16, String)> {
    http_get_as(addr, path, None)
}

/// [`http_get`] with an `Authorization` header value.
pub fn http_get_as(
    addr: SocketAddr,
    path: &str,
    authorization: Option<&str>,
) -> Option<(u16, String)> {
    let mut s = TcpStream::connect_timeout(&addr, Duration::from_secs(2)).ok()?;
    s.set_read_timeout(Some(Duration::from_secs(5))).ok()?;
    let authorization = authorization
        .map(|a| format!("Authorization: {a}\r\n"))
        .unwrap_or_default();
    write!(
        s,
        "GET {path} HTTP/1.0\r\nHost: localhost\r\n{authorization}\r\n"
    )
    .ok()?;
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

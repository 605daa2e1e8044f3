//! The real broker as a child process on free loopback ports, with a generated config.

use std::net::SocketAddr;
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::time::{Duration, Instant};

use crate::{fbbus_bin, free_port, http_get_as, wait_until};

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

/// What [`Broker::start_with`] writes into the config beside its defaults (loopback
/// listener and admin endpoint on free ports, `connect_timeout_ms = 2000`).
pub struct Options {
    /// `[broker] line` (default `test`).
    pub line: String,
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
    /// TOML tables at the end of the config (`[bridge]`).
    pub tables: String,
    /// The `Authorization` header the harness sends to an admin endpoint that wants
    /// credentials (`admin_extra` with `password_file`): [`basic`].
    pub admin_authorization: Option<String>,
}

/// An HTTP Basic `Authorization` header value.
pub fn basic(user: &str, password: &str) -> String {
    use base64::Engine as _;
    let token = base64::engine::general_purpose::STANDARD.encode(format!("{user}:{password}"));
    format!("Basic {token}")
}

impl Default for Options {
    fn default() -> Self {
        Options {
            line: "test".into(),
            extra: String::new(),
            listener_extra: String::new(),
            admin_extra: String::new(),
            log_level: "info,rumqttd=warn".into(),
            log_format: "text",
            env: Vec::new(),
            tables: String::new(),
            admin_authorization: None,
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
                "[broker]\nline = \"{line}\"\nconnect_timeout_ms = 2000\n{extra}\n\
                 [[listener]]\nname = \"main\"\nbind = \"{mqtt}\"\n{lextra}\n\
                 [admin]\nbind = \"{admin}\"\n{aextra}\n\
                 [log]\nlevel = \"{level}\"\nformat = \"{format}\"\n{tables}\n",
                line = options.line,
                tables = options.tables,
                extra = options.extra,
                lextra = options.listener_extra,
                aextra = options.admin_extra,
                level = options.log_level,
                format = options.log_format,
            ),
        )
        .unwrap();
        Broker::spawn_as(
            dir,
            config,
            mqtt,
            admin,
            &options.env,
            options.admin_authorization,
        )
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
            .current_dir(dir.path())
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

    /// `mqtt://127.0.0.1:<port>`, as the harness's `--broker` takes it.
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
        std::fs::read_to_string(&self.log).unwrap_or_default()
    }

    /// Asserts that `refusals` refusals logged as `line` were held to the broker's budget
    /// for outside input (`logging::OUTSIDE`, 600 lines a minute): 500-600 such lines,
    /// and the line saying the rest were left out.
    pub fn assert_within_log_budget(&self, line: &str, refusals: usize) {
        let log = self.log_text();
        let logged = log.lines().filter(|l| l.contains(line)).count();
        assert!(
            (500..=600).contains(&logged),
            "{logged} lines \"{line}\" for {refusals} refusals"
        );
        assert!(
            log.contains("refusals of outside input this minute"),
            "the log does not say that lines were left out"
        );
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
            .current_dir(self.dir.path())
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

//! Brokers the harness starts itself (`fbbus-loadtest compare`): fbbus, Mosquitto, raw
//! rumqttd and FlashMQ, each a child process of its own on free 127.0.0.1 ports, so its resident
//! memory is its own. [`Running`] kills the process when dropped, also when a scenario
//! panics; raw rumqttd also exits when the harness dies (it watches its stdin). For
//! `compare persistence` a broker can also be stopped with SIGTERM
//! ([`Running::terminate`]) and started again on the same ports, config and store
//! ([`Running::respawn`]).

use std::ffi::OsString;
use std::fmt;
use std::net::{SocketAddr, TcpListener};
use std::path::{Path, PathBuf};
use std::process::{Child, ChildStdin, Command, Stdio};
use std::time::{Duration, Instant};

use tokio::io::AsyncWriteExt;

use crate::{raw_client, scrape, Error};

/// Mosquitto's QoS 1/2 window towards each client (`max_inflight_messages`): fbbus's
/// default (`[broker] max_inflight_out`), so a QoS 1 scenario compares brokers, not
/// windows (Mosquitto's default is 20; until 2026-11-30 the persistence comparison set
/// 100 and the others kept 20).
pub const MOSQUITTO_INFLIGHT: u16 = 512;

/// How long a started broker may take to accept clients.
const READY_WITHIN: Duration = Duration::from_secs(15);

#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Kind {
    Fbbus,
    /// Mosquitto with `set_tcp_nodelay true` (the earlier study's fair configuration).
    Mosquitto,
    /// Mosquitto as shipped: `set_tcp_nodelay false`.
    MosquittoDefault,
    /// Upstream rumqttd 0.20 as a library, in `fbbus-loadtest serve-rumqttd`.
    Rumqttd,
    /// FlashMQ (a C++ broker, one event loop per core), from its own binary.
    FlashMq,
}

impl Kind {
    pub fn label(self) -> &'static str {
        match self {
            Kind::Fbbus => "fbbus",
            Kind::Mosquitto => "mosquitto",
            Kind::MosquittoDefault => "mosquitto (nodelay off)",
            Kind::Rumqttd => "rumqttd",
            Kind::FlashMq => "flashmq",
        }
    }
}

impl fmt::Display for Kind {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(self.label())
    }
}

/// Password files for the authenticated scenario, one per broker's format.
pub struct AuthFiles {
    /// `user:$argon2id$...` made with `security::hash_password`.
    pub fbbus: Option<PathBuf>,
    /// `user:$7$...` made with `mosquitto_passwd -U`; FlashMQ reads the same file
    /// (`mosquitto_password_file`, which takes Mosquitto's PBKDF2-SHA512 `$7$` hashes).
    pub mosquitto: Option<PathBuf>,
    /// `user:password` lines, loaded into rumqttd's static auth map.
    pub rumqttd: PathBuf,
    /// A user outside the storm's devices, for the readiness probe.
    pub probe: (String, String),
}

/// What a broker keeps across a restart (`compare persistence`). Without one
/// ([`Spec::persistence`] `None`), fbbus runs with its defaults (its store on, in the
/// broker's temporary directory) and Mosquitto with `persistence false`.
#[derive(Clone, Debug, PartialEq, Eq)]
pub enum Persistence {
    /// fbbus: `[persistence] enabled = false`; Mosquitto: `persistence false`.
    Off,
    /// fbbus: `[persistence] enabled = true`, `dir` = `store/` in the broker's temporary
    /// directory, this `fsync` policy (`"always"`, `"every 100 ms"`, `"os"`; None: fbbus's
    /// default), and the store's `store restored` line in the log
    /// (`[log] level = "warn,broker::store=info"`). Mosquitto: `persistence true`,
    /// `persistence_location` = `mosquitto-store/` in its temporary directory, the default
    /// `autosave_interval` (the policy does not apply).
    On { fsync: Option<String> },
}

/// What to start.
pub struct Spec<'a> {
    pub kind: Kind,
    /// fbbus, mosquitto or flashmq; for raw rumqttd the harness binary (re-executed as
    /// `serve-rumqttd`).
    pub program: &'a Path,
    /// fbbus: `key = value` lines added to its `[broker]` section.
    pub broker_keys: &'a [String],
    /// fbbus: TOML tables appended to its config (`[bridge]`).
    pub tables: &'a str,
    /// Only the users of these files may connect.
    pub auth: Option<&'a AuthFiles>,
    /// fbbus: its `[auth] acl_file`.
    pub acl: Option<&'a Path>,
    /// fbbus and Mosquitto: what they keep across a restart (None: see [`Persistence`]).
    pub persistence: Option<&'a Persistence>,
    /// Mosquitto: lines added to its `mosquitto.conf` (a second listener).
    pub mosquitto_lines: &'a [String],
    /// FlashMQ: lines added to its `flashmq.conf` (`client_max_write_buffer_size ...`).
    pub flashmq_lines: &'a [String],
}

/// A broker child process; killed and reaped on drop.
pub struct Running {
    pub kind: Kind,
    pub addr: SocketAddr,
    /// fbbus's admin endpoint (HTTP).
    pub admin: Option<SocketAddr>,
    child: Child,
    /// Held open so that `serve-rumqttd` exits by itself if the harness dies.
    _stdin: Option<ChildStdin>,
    log: PathBuf,
    /// What was started, for [`Running::respawn`].
    program: PathBuf,
    args: Vec<OsString>,
    dir: tempfile::TempDir,
}

impl Running {
    pub fn pid(&self) -> u32 {
        self.child.id()
    }

    /// Resident memory (VmRSS) in KiB.
    pub fn rss_kib(&self) -> Option<u64> {
        super::rss_kib(self.pid())
    }

    /// `mqtt://` URL of its listener.
    pub fn url(&self) -> String {
        format!("mqtt://{}", self.addr)
    }

    /// None while running, else how it ended.
    pub fn exited(&mut self) -> Option<String> {
        match self.child.try_wait() {
            Ok(Some(status)) => Some(format!("broker exited ({status}); {}", self.log_tail())),
            Ok(None) => None,
            Err(e) => Some(format!("cannot check broker process: {e}")),
        }
    }

    /// Its log file (stdout and stderr); removed with the process's directory on drop.
    pub fn log_path(&self) -> &Path {
        &self.log
    }

    /// Its temporary directory: config, log and (with [`Persistence::On`]) its store,
    /// `store/` (fbbus) or `mosquitto-store/` (Mosquitto).
    pub fn dir(&self) -> &Path {
        self.dir.path()
    }

    /// Kills the broker now (SIGKILL), as a crash or a power cut ends it, and reaps it.
    pub fn kill(&mut self) -> Result<(), Error> {
        if self.child.try_wait()?.is_none() {
            self.child.kill()?;
            self.child.wait()?;
        }
        Ok(())
    }

    /// Stops the broker with SIGTERM, as systemd does, and waits up to `within` for it to
    /// exit (then kills it). Its directory (config, store, log) stays, for
    /// [`Running::respawn`]. Returns how long it took to exit.
    pub fn terminate(&mut self, within: Duration) -> Result<Duration, Error> {
        let started = Instant::now();
        if self.child.try_wait()?.is_none() {
            let pid = libc::pid_t::try_from(self.child.id())
                .map_err(|_| Error::Process("pid out of range".into()))?;
            // SAFETY: kill(2) on our own child's pid, which is not reaped yet (try_wait
            // said it runs), so the pid cannot have been reused.
            if unsafe { libc::kill(pid, libc::SIGTERM) } != 0 {
                return Err(Error::Process(format!(
                    "SIGTERM to {}: {}",
                    self.kind,
                    std::io::Error::last_os_error()
                )));
            }
        }
        loop {
            if let Some(status) = self.child.try_wait()? {
                if !status.success() && status.code().is_some() {
                    return Err(Error::Process(format!(
                        "{} exited with {status} on SIGTERM; {}",
                        self.kind,
                        self.log_tail()
                    )));
                }
                return Ok(started.elapsed());
            }
            if started.elapsed() > within {
                let _ = self.child.kill();
                let _ = self.child.wait();
                return Err(Error::Process(format!(
                    "{} did not exit within {within:?} of SIGTERM (killed)",
                    self.kind
                )));
            }
            std::thread::sleep(Duration::from_millis(2));
        }
    }

    /// Starts the same program again, with the same config, ports and directory (its
    /// store), after [`Running::terminate`]; returns as soon as the process is spawned:
    /// the caller decides when it is ready. Its log is appended to.
    pub fn respawn(&mut self) -> Result<(), Error> {
        if self.child.try_wait()?.is_none() {
            return Err(Error::Process(format!("{} is still running", self.kind)));
        }
        let log = std::fs::OpenOptions::new().append(true).open(&self.log)?;
        let mut command = Command::new(&self.program);
        command
            .args(&self.args)
            .stdin(if self.kind == Kind::Rumqttd {
                Stdio::piped()
            } else {
                Stdio::null()
            })
            .stdout(log.try_clone()?)
            .stderr(log);
        let mut child = command.spawn().map_err(|e| {
            Error::Process(format!(
                "cannot start {} ({}): {e}",
                self.kind,
                self.program.display()
            ))
        })?;
        self._stdin = child.stdin.take();
        self.child = child;
        Ok(())
    }

    /// The last lines of its log (stdout and stderr), joined with ` | `.
    pub fn log_tail(&self) -> String {
        let text = std::fs::read_to_string(&self.log).unwrap_or_default();
        let lines: Vec<&str> = text.lines().collect();
        let tail = lines[lines.len().saturating_sub(5)..].join(" | ");
        if tail.is_empty() {
            "no log output".into()
        } else {
            format!("log: {tail}")
        }
    }
}

impl Drop for Running {
    fn drop(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

/// A TCP port on 127.0.0.1 that was free a moment ago, below Linux's ephemeral range.
///
/// Why not `bind(0)`: the kernel hands out ports for outgoing connections (every client a
/// test opens, thousands in the storm tests) from that same ephemeral range (32768-60999
/// by default); a port picked there and released could be taken by a client's connect
/// before the broker bound it, and the broker failed to start with `Address already in
/// use` (seen in CI). Ports 20000-32767 are never handed out that way; they are tried in
/// a pseudo-random order, so parallel tests rarely try the same one.
pub fn free_port() -> Result<u16, Error> {
    use std::sync::atomic::{AtomicU64, Ordering};
    static NEXT: AtomicU64 = AtomicU64::new(0);
    let seed = std::time::SystemTime::now()
        .duration_since(std::time::UNIX_EPOCH)
        .map_or(0, |d| d.as_nanos() as u64)
        ^ (u64::from(std::process::id()) << 20);
    for _ in 0..1000 {
        let n = NEXT.fetch_add(0x9E37_79B9_7F4A_7C15, Ordering::Relaxed) ^ seed;
        let port = 20_000 + (n.wrapping_mul(0xBF58_476D_1CE4_E5B9) >> 33) % 12_768;
        if TcpListener::bind(("127.0.0.1", port as u16)).is_ok() {
            return Ok(port as u16);
        }
    }
    Ok(TcpListener::bind("127.0.0.1:0")?.local_addr()?.port())
}

/// A temporary directory the privilege-dropped Mosquitto (user `mosquitto` when started as
/// root) can read.
pub fn readable_tempdir(prefix: &str) -> Result<tempfile::TempDir, Error> {
    let dir = tempfile::Builder::new().prefix(prefix).tempdir()?;
    set_mode(dir.path(), 0o755)?;
    Ok(dir)
}

pub fn set_mode(path: &Path, mode: u32) -> Result<(), Error> {
    use std::os::unix::fs::PermissionsExt;
    std::fs::set_permissions(path, std::fs::Permissions::from_mode(mode))
        .map_err(|e| Error::Process(format!("chmod {}: {e}", path.display())))
}

/// Starts the broker on a fresh port and waits until it accepts MQTT clients.
pub async fn start(spec: &Spec<'_>) -> Result<Running, Error> {
    let kind = spec.kind;
    let dir = readable_tempdir("fbbus-loadtest-broker-")?;
    let port = free_port()?;
    let addr = SocketAddr::from(([127, 0, 0, 1], port));
    let log = dir.path().join("broker.log");
    let log_file = std::fs::File::create(&log)?;
    let mut admin = None;
    let mut command = match kind {
        Kind::Fbbus => {
            let admin_addr = SocketAddr::from(([127, 0, 0, 1], free_port()?));
            admin = Some(admin_addr);
            let path = dir.path().join("fbbus.toml");
            std::fs::write(&path, fbbus_config(spec, dir.path(), addr, admin_addr)?)?;
            let mut c = Command::new(spec.program);
            c.arg("serve").arg("--config").arg(&path);
            c
        }
        Kind::Mosquitto | Kind::MosquittoDefault => {
            let nodelay = kind == Kind::Mosquitto;
            let persist = matches!(spec.persistence, Some(Persistence::On { .. }));
            let mut config = format!(
                "listener {port} 127.0.0.1\n\
                 set_tcp_nodelay {nodelay}\n\
                 max_queued_messages 100000\n\
                 max_inflight_messages {MOSQUITTO_INFLIGHT}\n\
                 persistence {persist}\n\
                 log_dest none\n"
            );
            if persist {
                // Started as root, Mosquitto writes its database as user `mosquitto`.
                let store = dir.path().join("mosquitto-store");
                std::fs::create_dir(&store)?;
                set_mode(&store, 0o777)?;
                config.push_str(&format!("persistence_location {}/\n", store.display()));
            }
            for line in spec.mosquitto_lines {
                config.push_str(line);
                config.push('\n');
            }
            match spec.auth {
                Some(a) => {
                    let file = a.mosquitto.as_ref().ok_or_else(|| {
                        Error::Process(
                            "no mosquitto password file was prepared (is mosquitto_passwd installed?)"
                                .into(),
                        )
                    })?;
                    config.push_str(&format!(
                        "allow_anonymous false\npassword_file {}\n",
                        file.display()
                    ));
                }
                None => config.push_str("allow_anonymous true\n"),
            }
            let path = dir.path().join("mosquitto.conf");
            std::fs::write(&path, config)?;
            set_mode(&path, 0o644)?;
            let mut c = Command::new(spec.program);
            c.arg("-c").arg(&path);
            c
        }
        Kind::FlashMq => {
            let path = dir.path().join("flashmq.conf");
            std::fs::write(&path, flashmq_config(spec, dir.path(), port)?)?;
            let mut c = Command::new(spec.program);
            c.arg("--config-file")
                .arg(&path)
                // A debug build locks `$HOME/.FlashMQ.lock` (one instance per user): each
                // broker gets its own home, so rounds and parallel tests never collide.
                .env("HOME", dir.path());
            c
        }
        Kind::Rumqttd => {
            let mut c = Command::new(spec.program);
            c.arg("serve-rumqttd")
                .arg("--port")
                .arg(port.to_string())
                .arg("--exit-on-stdin-eof");
            if let Some(a) = spec.auth {
                c.arg("--auth-file").arg(&a.rumqttd);
            }
            c
        }
    };
    command
        .stdin(if kind == Kind::Rumqttd {
            Stdio::piped()
        } else {
            Stdio::null()
        })
        .stdout(log_file.try_clone()?)
        .stderr(log_file);
    let mut child = command.spawn().map_err(|e| {
        Error::Process(format!(
            "cannot start {kind} ({}): {e}",
            spec.program.display()
        ))
    })?;
    let stdin = child.stdin.take();
    let mut running = Running {
        kind,
        addr,
        admin,
        child,
        _stdin: stdin,
        log,
        program: spec.program.to_path_buf(),
        args: command.get_args().map(|a| a.to_os_string()).collect(),
        dir,
    };
    let deadline = Instant::now() + READY_WITHIN;
    loop {
        if let Some(why) = running.exited() {
            return Err(Error::Process(format!("{kind} did not start: {why}")));
        }
        let ready = match admin {
            Some(admin) => scrape::get(&format!("http://{admin}/readyz"), Duration::from_secs(2))
                .await
                .is_ok(),
            None => {
                let probe = spec.auth.map(|a| (a.probe.0.as_str(), a.probe.1.as_str()));
                accepts_clients(addr, probe).await
            }
        };
        if ready {
            return Ok(running);
        }
        if Instant::now() > deadline {
            return Err(Error::Process(format!(
                "{kind} not ready after {READY_WITHIN:?}; {}",
                running.log_tail()
            )));
        }
        tokio::time::sleep(Duration::from_millis(50)).await;
    }
}

/// fbbus's generated config: its defaults, one loopback listener, `max_connections`
/// (and `max_sessions_per_identity`: every load client is one loopback identity) above
/// every scenario's count, warnings only in the log.
fn fbbus_config(
    spec: &Spec<'_>,
    dir: &Path,
    addr: SocketAddr,
    admin: SocketAddr,
) -> Result<String, Error> {
    let mut config =
        String::from("[broker]\nmax_connections = 10100\nmax_sessions_per_identity = 20200\n");
    for option in spec.broker_keys {
        config.push_str(option);
        config.push('\n');
    }
    config.push_str(&format!(
        "\n[[listener]]\nname = \"bench\"\nbind = \"{addr}\"\n"
    ));
    let mut auth = String::new();
    match spec.auth {
        Some(a) => {
            let file = a
                .fbbus
                .as_ref()
                .ok_or_else(|| Error::Process("no fbbus password file was prepared".into()))?;
            auth.push_str(&format!("password_file = \"{}\"\n", file.display()));
        }
        None => config.push_str("allow_anonymous = true\n"),
    }
    if let Some(acl) = spec.acl {
        auth.push_str(&format!("acl_file = \"{}\"\n", acl.display()));
    }
    if !auth.is_empty() {
        config.push_str("\n[auth]\n");
        config.push_str(&auth);
    }
    let mut level = "warn";
    match spec.persistence {
        None => {}
        Some(Persistence::Off) => config.push_str("\n[persistence]\nenabled = false\n"),
        Some(Persistence::On { fsync }) => {
            let store = dir.join("store");
            // As many queued messages per session as Mosquitto is given
            // (`max_queued_messages 100000`): a burst into a connected persistent
            // subscriber keeps more than fbbus's default 1,000 unacknowledged, and past
            // the limit messages are routed but not stored, which would measure less work.
            config.push_str(&format!(
                "\n[persistence]\nenabled = true\ndir = \"{}\"\nmax_queued_messages = 100000\n",
                store.display()
            ));
            if let Some(fsync) = fsync {
                config.push_str(&format!("fsync = \"{fsync}\"\n"));
            }
            // The `store restored retained=... read_ms=... put_back_ms=...` line.
            level = "warn,broker::store=info";
        }
    }
    config.push_str(&format!(
        "\n[admin]\nbind = \"{admin}\"\n\n[log]\nlevel = \"{level}\"\n"
    ));
    config.push_str(spec.tables);
    Ok(config)
}

/// FlashMQ's generated `flashmq.conf`: one plain MQTT listener on `port` of 127.0.0.1 with
/// `tcp_nodelay true` (as Mosquitto's `set_tcp_nodelay true`: the clients write small
/// packets and measure latency), `thread_count` = the cores (FlashMQ's own auto-detected
/// default, written out so the header's claim is the config's), warnings only to a log
/// file in `dir` (its packaged config logs to /var/log/flashmq), no `storage_dir` (no
/// persistence; the packaged one uses /var/lib/flashmq). `max_qos_msg_pending_per_client`
/// and `max_qos_bytes_pending_per_client` are raised from 512 messages / 64 KiB to the
/// most the first allows (65,535) and 100 MiB: past them FlashMQ drops QoS 1 messages for a
/// subscriber, and a QoS 1 burst of 100,000 queues more than 512 for the one subscriber;
/// Mosquitto is given `max_queued_messages 100000` for the same reason. `rlimit_nofile`
/// is this process's hard limit: FlashMQ's default (1,000,000) fails without privileges
/// and logs an error. Anonymous clients, or for the auth storm only the users of
/// Mosquitto's password file (`mosquitto_password_file`).
fn flashmq_config(spec: &Spec<'_>, dir: &Path, port: u16) -> Result<String, Error> {
    let threads = std::thread::available_parallelism().map_or(1, |n| n.get());
    let mut config = format!(
        "thread_count {threads}\n\
         log_file {}\n\
         log_level warning\n\
         max_qos_msg_pending_per_client 65535\n\
         max_qos_bytes_pending_per_client 104857600\n",
        dir.join("flashmq.log").display()
    );
    if let Some(limit) = nofile_hard_limit() {
        config.push_str(&format!("rlimit_nofile {limit}\n"));
    }
    for line in spec.flashmq_lines {
        config.push_str(line);
        config.push('\n');
    }
    match spec.auth {
        Some(a) => {
            let file = a.mosquitto.as_ref().ok_or_else(|| {
                Error::Process(
                    "no mosquitto password file was prepared for flashmq (is mosquitto_passwd installed?)"
                        .into(),
                )
            })?;
            config.push_str(&format!(
                "allow_anonymous false\nmosquitto_password_file {}\n",
                file.display()
            ));
        }
        None => config.push_str("allow_anonymous true\n"),
    }
    config.push_str(&format!(
        "listen {{\n  protocol mqtt\n  inet_protocol ip4\n  inet4_bind_address 127.0.0.1\n  \
         port {port}\n  tcp_nodelay true\n}}\n"
    ));
    Ok(config)
}

/// This process's hard limit of open files (inherited by the brokers it starts).
fn nofile_hard_limit() -> Option<libc::rlim_t> {
    let mut limit = libc::rlimit {
        rlim_cur: 0,
        rlim_max: 0,
    };
    // SAFETY: getrlimit(2) writes into the struct we pass and reads nothing else.
    if unsafe { libc::getrlimit(libc::RLIMIT_NOFILE, &mut limit) } != 0 {
        return None;
    }
    (limit.rlim_max != libc::RLIM_INFINITY).then_some(limit.rlim_max)
}

/// An MQTT CONNECT gets a successful CONNACK; the probe then disconnects cleanly.
async fn accepts_clients(addr: SocketAddr, credentials: Option<(&str, &str)>) -> bool {
    let attempt = async {
        let mut s = raw_client::connect(addr, "bench-probe", credentials)
            .await
            .ok()?;
        s.write_all(&raw_client::DISCONNECT).await.ok()?;
        Some(())
    };
    tokio::time::timeout(Duration::from_secs(2), attempt)
        .await
        .ok()
        .flatten()
        .is_some()
}

/// `fbbus --version`, or why not.
pub fn fbbus_version(fbbus: &Path) -> String {
    match Command::new(fbbus).arg("--version").output() {
        Ok(out) => String::from_utf8_lossy(&out.stdout).trim().to_string(),
        Err(e) => format!("unknown ({}: {e})", fbbus.display()),
    }
}

/// The first line of `mosquitto -h`.
pub fn mosquitto_version(mosquitto: &Path) -> String {
    match Command::new(mosquitto).arg("-h").output() {
        Ok(out) => {
            let mut text = String::from_utf8_lossy(&out.stdout).to_string();
            text.push_str(&String::from_utf8_lossy(&out.stderr));
            text.lines().next().unwrap_or("unknown").trim().to_string()
        }
        Err(e) => format!("unknown ({e})"),
    }
}

/// The first line of `flashmq --version`.
pub fn flashmq_version(flashmq: &Path) -> String {
    match Command::new(flashmq).arg("--version").output() {
        Ok(out) => String::from_utf8_lossy(&out.stdout)
            .lines()
            .next()
            .unwrap_or("unknown")
            .trim()
            .to_string(),
        Err(e) => format!("unknown ({}: {e})", flashmq.display()),
    }
}

/// A program in one of `candidates`, or on PATH.
pub fn find_program(name: &str, candidates: &[&str]) -> Option<PathBuf> {
    for c in candidates {
        let p = PathBuf::from(c);
        if p.is_file() {
            return Some(p);
        }
    }
    std::env::var_os("PATH").and_then(|path| {
        std::env::split_paths(&path)
            .map(|d| d.join(name))
            .find(|p| p.is_file())
    })
}

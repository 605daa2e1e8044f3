//! The brokers under test, each a child process of its own on free 127.0.0.1 ports, so its
//! resident memory is its own. [`Running`] kills the process when dropped, also when a
//! scenario panics.

use std::fmt;
use std::net::{SocketAddr, TcpListener};
use std::path::{Path, PathBuf};
use std::process::{Child, ChildStdin, Command, Stdio};
use std::time::{Duration, Instant};

use anyhow::{bail, Context as _, Result};
use tokio::io::{AsyncReadExt, AsyncWriteExt};

use crate::mqtt;

#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum BrokerKind {
    Fbbus,
    /// Mosquitto with `set_tcp_nodelay true` (the study's fair configuration).
    Mosquitto,
    /// Mosquitto as shipped: `set_tcp_nodelay false`.
    MosquittoDefault,
    Rumqttd,
}

impl BrokerKind {
    pub fn label(self) -> &'static str {
        match self {
            BrokerKind::Fbbus => "fbbus",
            BrokerKind::Mosquitto => "mosquitto",
            BrokerKind::MosquittoDefault => "mosquitto (nodelay off)",
            BrokerKind::Rumqttd => "rumqttd",
        }
    }
}

impl fmt::Display for BrokerKind {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(self.label())
    }
}

/// Where the programs are.
pub struct Programs {
    pub fbbus: PathBuf,
    /// `KEY=VALUE` lines added to fbbus's `[broker]` section.
    pub fbbus_broker_options: Vec<String>,
    pub mosquitto: Option<PathBuf>,
    pub mosquitto_passwd: Option<PathBuf>,
    /// This binary, re-executed as `serve-rumqttd`.
    pub bench: PathBuf,
}

/// Password files for the authenticated scenario, one per broker's format.
pub struct AuthFiles {
    /// `user:$argon2id$...` made with `security::hash_password`.
    pub fbbus: Option<PathBuf>,
    /// `user:$7$...` made with `mosquitto_passwd -U`.
    pub mosquitto: Option<PathBuf>,
    /// `user:password` lines, loaded into rumqttd's static auth map.
    pub rumqttd: PathBuf,
    /// A user outside the storm's devices, for the readiness probe.
    pub probe: (String, String),
}

/// A broker child process; killed and reaped on drop.
pub struct Running {
    pub kind: BrokerKind,
    pub addr: SocketAddr,
    /// fbbus's admin endpoint (HTTP).
    pub admin: Option<SocketAddr>,
    child: Child,
    /// Held open so that `serve-rumqttd` exits by itself if the bench dies.
    _stdin: Option<ChildStdin>,
    log: PathBuf,
    _dir: tempfile::TempDir,
}

impl Running {
    pub fn pid(&self) -> u32 {
        self.child.id()
    }

    /// Resident memory (VmRSS) in KiB.
    pub fn rss_kib(&self) -> Option<u64> {
        rss_kib(self.pid())
    }

    /// None while running, else how it ended.
    pub fn exited(&mut self) -> Option<String> {
        match self.child.try_wait() {
            Ok(Some(status)) => Some(format!("broker exited ({status}); {}", self.log_tail())),
            Ok(None) => None,
            Err(e) => Some(format!("cannot check broker process: {e}")),
        }
    }

    fn log_tail(&self) -> String {
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

pub fn rss_kib(pid: u32) -> Option<u64> {
    let status = std::fs::read_to_string(format!("/proc/{pid}/status")).ok()?;
    status
        .lines()
        .find_map(|l| l.strip_prefix("VmRSS:"))
        .and_then(|v| v.trim().trim_end_matches("kB").trim().parse().ok())
}

/// A TCP port on 127.0.0.1 that was free a moment ago, below Linux's ephemeral range.
///
/// Why not `bind(0)`: the kernel hands out ports for outgoing connections (every client a
/// test opens, thousands in the storm tests) from that same ephemeral range (32768-60999
/// by default); a port picked there and released could be taken by a client's connect
/// before the broker bound it, and the broker failed to start with `Address already in
/// use` (seen in CI). Ports 20000-32767 are never handed out that way; they are tried in
/// a pseudo-random order, so parallel tests rarely try the same one.
pub fn free_port() -> Result<u16> {
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
fn readable_tempdir() -> Result<tempfile::TempDir> {
    let dir = tempfile::Builder::new().prefix("fbbus-bench-").tempdir()?;
    set_mode(dir.path(), 0o755)?;
    Ok(dir)
}

pub fn set_mode(path: &Path, mode: u32) -> Result<()> {
    use std::os::unix::fs::PermissionsExt;
    std::fs::set_permissions(path, std::fs::Permissions::from_mode(mode))
        .with_context(|| format!("chmod {}", path.display()))
}

/// Starts `kind` on a fresh port and waits until it accepts MQTT clients.
/// With `auth`, only the users of the password file may connect.
pub async fn start(
    kind: BrokerKind,
    programs: &Programs,
    auth: Option<&AuthFiles>,
) -> Result<Running> {
    start_with(kind, programs, auth, &[], "").await
}

/// [`start`], with fbbus given extra `[broker]` keys and TOML tables appended to its
/// config (the bridge scenario's `line` and `[bridge]`).
pub async fn start_with(
    kind: BrokerKind,
    programs: &Programs,
    auth: Option<&AuthFiles>,
    broker_keys: &[String],
    tables: &str,
) -> Result<Running> {
    let dir = readable_tempdir()?;
    let port = free_port()?;
    let addr = SocketAddr::from(([127, 0, 0, 1], port));
    let log = dir.path().join("broker.log");
    let log_file = std::fs::File::create(&log)?;
    let mut admin = None;
    let mut command = match kind {
        BrokerKind::Fbbus => {
            let admin_addr = SocketAddr::from(([127, 0, 0, 1], free_port()?));
            admin = Some(admin_addr);
            let mut config = String::from("[broker]\nmax_connections = 10100\n");
            for option in programs.fbbus_broker_options.iter().chain(broker_keys) {
                config.push_str(option);
                config.push('\n');
            }
            config.push_str(&format!(
                "\n[[listener]]\nname = \"bench\"\nbind = \"{addr}\"\n"
            ));
            match auth {
                Some(a) => {
                    let file = a
                        .fbbus
                        .as_ref()
                        .context("no fbbus password file was prepared")?;
                    config.push_str(&format!(
                        "\n[auth]\npassword_file = \"{}\"\n",
                        file.display()
                    ));
                }
                None => config.push_str("allow_anonymous = true\n"),
            }
            config.push_str(&format!(
                "\n[admin]\nbind = \"{admin_addr}\"\n\n[log]\nlevel = \"warn\"\n"
            ));
            config.push_str(tables);
            let path = dir.path().join("fbbus.toml");
            std::fs::write(&path, config)?;
            let mut c = Command::new(&programs.fbbus);
            c.arg("serve").arg("--config").arg(&path);
            c
        }
        BrokerKind::Mosquitto | BrokerKind::MosquittoDefault => {
            let program = programs
                .mosquitto
                .as_ref()
                .context("mosquitto is not installed (apt-get install -y mosquitto)")?;
            let nodelay = kind == BrokerKind::Mosquitto;
            let mut config = format!(
                "listener {port} 127.0.0.1\n\
                 set_tcp_nodelay {nodelay}\n\
                 max_queued_messages 100000\n\
                 persistence false\n\
                 log_dest none\n"
            );
            match auth {
                Some(a) => {
                    let file = a
                        .mosquitto
                        .as_ref()
                        .context("no mosquitto password file was prepared")?;
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
            let mut c = Command::new(program);
            c.arg("-c").arg(&path);
            c
        }
        BrokerKind::Rumqttd => {
            let mut c = Command::new(&programs.bench);
            c.arg("serve-rumqttd")
                .arg("--port")
                .arg(port.to_string())
                .arg("--exit-on-stdin-eof");
            if let Some(a) = auth {
                c.arg("--auth-file").arg(&a.rumqttd);
            }
            c
        }
    };
    command
        .stdin(if kind == BrokerKind::Rumqttd {
            Stdio::piped()
        } else {
            Stdio::null()
        })
        .stdout(log_file.try_clone()?)
        .stderr(log_file);
    let mut child = command
        .spawn()
        .with_context(|| format!("starting {kind} ({:?})", command.get_program()))?;
    let stdin = child.stdin.take();
    let mut running = Running {
        kind,
        addr,
        admin,
        child,
        _stdin: stdin,
        log,
        _dir: dir,
    };
    let deadline = Instant::now() + Duration::from_secs(15);
    loop {
        if let Some(why) = running.exited() {
            bail!("{kind} did not start: {why}");
        }
        let ready = match admin {
            Some(admin) => readyz(admin).await,
            None => probe(addr, auth.map(|a| (a.probe.0.as_str(), a.probe.1.as_str()))).await,
        };
        if ready {
            break;
        }
        if Instant::now() > deadline {
            bail!("{kind} not ready after 15 s; {}", running.log_tail());
        }
        tokio::time::sleep(Duration::from_millis(50)).await;
    }
    Ok(running)
}

/// `GET /readyz` answered 200.
async fn readyz(admin: SocketAddr) -> bool {
    matches!(http_get(admin, "/readyz").await, Some((200, _)))
}

/// One HTTP/1.0 GET to fbbus's admin endpoint: (status, body), None on any failure or
/// after 10 s.
pub async fn http_get(admin: SocketAddr, path: &str) -> Option<(u16, Vec<u8>)> {
    let attempt = async {
        let mut s = tokio::net::TcpStream::connect(admin).await.ok()?;
        s.write_all(format!("GET {path} HTTP/1.0\r\nHost: 127.0.0.1\r\n\r\n").as_bytes())
            .await
            .ok()?;
        let mut response = Vec::new();
        s.read_to_end(&mut response).await.ok()?;
        let split = response.windows(4).position(|w| w == b"\r\n\r\n")?;
        let status = std::str::from_utf8(&response[..split])
            .ok()?
            .split_whitespace()
            .nth(1)?
            .parse()
            .ok()?;
        Some((status, response[split + 4..].to_vec()))
    };
    tokio::time::timeout(Duration::from_secs(10), attempt)
        .await
        .ok()
        .flatten()
}

/// An MQTT CONNECT gets a successful CONNACK; the probe then disconnects cleanly.
async fn probe(addr: SocketAddr, credentials: Option<(&str, &str)>) -> bool {
    let attempt = async {
        let mut s = mqtt::connect(addr, "bench-probe", credentials).await.ok()?;
        s.write_all(&mqtt::DISCONNECT).await.ok()?;
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

/// rumqttd 0.20 as its `rumqttd.toml` example ships it: one v4 listener on 127.0.0.1:`port`.
pub fn rumqttd_config(
    port: u16,
    auth: Option<std::collections::HashMap<String, String>>,
) -> rumqttd::Config {
    let router = rumqttd::RouterConfig {
        max_connections: 10010,
        max_outgoing_packet_count: 200,
        max_segment_size: 104_857_600,
        max_segment_count: 10,
        ..Default::default()
    };
    let connections = rumqttd::ConnectionSettings {
        connection_timeout_ms: 60_000,
        max_payload_size: 20_480,
        max_inflight_count: 100,
        auth,
        external_auth: None,
        dynamic_filters: true,
    };
    let server = rumqttd::ServerSettings {
        name: "v4-1".into(),
        listen: SocketAddr::from(([127, 0, 0, 1], port)),
        tls: None,
        // rumqttd's shipped pause between two accepts.
        next_connection_delay_ms: 1,
        connections,
    };
    rumqttd::Config {
        id: 0,
        router,
        v4: Some([("1".to_string(), server)].into_iter().collect()),
        ..Default::default()
    }
}

/// The hidden `serve-rumqttd` subcommand: raw rumqttd in this process until killed.
pub fn serve_rumqttd(port: u16, auth_file: Option<&Path>, exit_on_stdin_eof: bool) -> Result<()> {
    if exit_on_stdin_eof {
        std::thread::spawn(|| {
            let mut sink = Vec::new();
            let _ = std::io::Read::read_to_end(&mut std::io::stdin(), &mut sink);
            std::process::exit(0);
        });
    }
    let auth = match auth_file {
        Some(path) => {
            let text = std::fs::read_to_string(path)
                .with_context(|| format!("reading {}", path.display()))?;
            let map = text
                .lines()
                .filter_map(|l| l.split_once(':'))
                .map(|(u, p)| (u.to_string(), p.to_string()))
                .collect();
            Some(map)
        }
        None => None,
    };
    let mut broker = rumqttd::Broker::new(rumqttd_config(port, auth));
    broker.start().map_err(|e| anyhow::anyhow!("rumqttd: {e}"))
}

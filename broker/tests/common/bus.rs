//! Lines of the bus for the tests that link brokers (`bridge.rs`, `bus_security.rs`):
//! real `fbbus` processes with `[bridge]` sections on free loopback ports, devices as
//! real MQTT clients, and Python eclipse-zenoh programs driven line by line.
//!
//! A line's bus is mutual TLS with access control by default, as between hosts: its
//! certificate (common name = its line name) comes from the test process's PKI
//! ([`super::pki::bus`]) and its `[bridge.peers]` names every line the tests use. A line
//! whose endpoints are `tcp/` ([`Line::plain`]) runs the plain loopback bus: no TLS, no
//! access control.

use std::io::{BufRead, Write};
use std::net::SocketAddr;
use std::process::{Child, ChildStdin, Command, Stdio};
use std::sync::mpsc;
use std::time::{Duration, Instant};

use serde_json::Value;

use super::clients::V4;
use super::{free_port, http_get, Broker};

/// How long zenoh has to carry declarations and liveliness between lines on loopback.
pub const PROPAGATION: Duration = Duration::from_secs(10);

pub const CONV: &str = r#"{"fbs": {"CONV": {
    "type": "CONVEYOR",
    "events_out": {"MOVED": {"with": ["POSITION"]}},
    "data_out": {"POSITION": "INT", "ID": "STRING"}
}}}"#;

/// A free loopback endpoint for a mutual-TLS bus.
pub fn tls_endpoint() -> String {
    format!("tls/127.0.0.1:{}", free_port())
}

/// A free loopback endpoint for a plain bus (no TLS, no access control).
pub fn tcp_endpoint() -> String {
    format!("tcp/127.0.0.1:{}", free_port())
}

/// A line: its broker and the zenoh endpoint it listens on.
pub struct Line {
    pub broker: Broker,
    pub name: String,
    pub zenoh: String,
}

impl Line {
    /// Starts line `name` on the mutual-TLS bus, its bridge listening on a free port and
    /// connecting to `connect`.
    pub fn start(name: &str, connect: &[&str], extra: &str) -> Line {
        Line::start_on(name, &tls_endpoint(), connect, extra, None)
    }

    /// Starts line `name` on the plain loopback bus (`tcp/`: no TLS, no access control).
    pub fn plain(name: &str, connect: &[&str], extra: &str) -> Line {
        Line::start_on(name, &tcp_endpoint(), connect, extra, None)
    }

    /// `zenoh` empty: the bridge does not listen (zenoh client mode).
    pub fn start_on(
        name: &str,
        zenoh: &str,
        connect: &[&str],
        extra: &str,
        ports: Option<(SocketAddr, SocketAddr)>,
    ) -> Line {
        Line::start_full(name, zenoh, connect, extra, ports, |_| String::new())
    }

    /// `prepare` writes files into the broker's directory and returns TOML tables for
    /// the top of the config (`[auth]`, ...).
    pub fn start_with(
        name: &str,
        zenoh: &str,
        connect: &[&str],
        extra: &str,
        prepare: impl FnOnce(&std::path::Path) -> String,
    ) -> Line {
        Line::start_full(name, zenoh, connect, extra, None, prepare)
    }

    /// The line's bus is mutual TLS (with the test PKI's certificate for `name` and
    /// `[bridge.peers]`) when one of its endpoints is `tls/`.
    pub fn start_full(
        name: &str,
        zenoh: &str,
        connect: &[&str],
        extra: &str,
        ports: Option<(SocketAddr, SocketAddr)>,
        prepare: impl FnOnce(&std::path::Path) -> String,
    ) -> Line {
        let listen: Vec<&str> = [zenoh].into_iter().filter(|z| !z.is_empty()).collect();
        let dir = tempfile::tempdir().unwrap();
        let top = prepare(dir.path());
        let tls = listen.iter().chain(connect).any(|e| e.starts_with("tls/"));
        let security = match tls {
            true => super::pki::bus_tables(dir.path(), name),
            false => String::new(),
        };
        let (mqtt, admin) = ports.unwrap_or_else(|| {
            (
                format!("127.0.0.1:{}", free_port()).parse().unwrap(),
                format!("127.0.0.1:{}", free_port()).parse().unwrap(),
            )
        });
        // The product's default lease (3 s) unless a test asks for a shorter one: on a busy
        // 2-core machine a 1 s lease expired between lines that were both up, and the
        // messages in flight were lost (a chain through a router lost some of 100).
        let lease = match extra.contains("lease_ms") {
            true => "",
            false => "lease_ms = 3000\n",
        };
        let config = dir.path().join("fbbus.toml");
        std::fs::write(
            &config,
            format!(
                "[broker]\nline = \"{name}\"\n\n{top}\n\
                 [[listener]]\nname = \"main\"\nbind = \"{mqtt}\"\n\n\
                 [admin]\nbind = \"{admin}\"\n\n\
                 [log]\nlevel = \"info,rumqttd=warn,zenoh=warn\"\n\n\
                 [bridge]\nlisten = {listen:?}\nconnect = {connect:?}\n{lease}{extra}\n\n\
                 {security}",
            ),
        )
        .unwrap();
        Line {
            broker: Broker::spawn(dir, config, mqtt, admin),
            name: name.to_owned(),
            zenoh: zenoh.to_owned(),
        }
    }

    pub fn port(&self) -> u16 {
        self.broker.port()
    }

    /// The registry record of `id` as this line's admin endpoint serves it.
    pub fn record(&self, id: &str) -> Option<Value> {
        let (code, body) = http_get(self.broker.admin, &format!("/api/v1/devices/{id}"))?;
        (code == 200).then(|| serde_json::from_str(&body).unwrap())
    }

    /// Waits until this line's registry shows `id` with `status`; returns the record.
    pub fn wait_record(&self, id: &str, status: &str, within: Duration) -> Value {
        self.poll_record(id, status, within)
            .unwrap_or_else(|failure| {
                panic!("{failure}\n{}", self.broker.log_text());
            })
    }

    /// [`Line::wait_record`] for a caller that shows more than this line's log when it
    /// fails: the record, or what the line showed instead.
    pub fn poll_record(&self, id: &str, status: &str, within: Duration) -> Result<Value, String> {
        let deadline = Instant::now() + within;
        loop {
            let record = self.record(id);
            if record.as_ref().is_some_and(|r| r["status"] == status) {
                return Ok(record.unwrap());
            }
            if Instant::now() > deadline {
                return Err(format!(
                    "line {}: device {id} not {status} within {within:?}: {record:?}",
                    self.name
                ));
            }
            std::thread::sleep(Duration::from_millis(50));
        }
    }

    /// Waits until `series` reaches `min` on this line.
    pub fn wait_metric(&self, series: &str, min: f64) {
        let deadline = Instant::now() + PROPAGATION;
        while self.broker.metric(series) < min {
            assert!(
                Instant::now() < deadline,
                "line {}: {series} < {min}\n{}\n{}",
                self.name,
                self.broker.metrics(),
                self.broker.log_text()
            );
            std::thread::sleep(Duration::from_millis(20));
        }
    }
}

/// A device on `line` declaring the conveyor interface [`CONV`].
pub async fn device(line: &Line, id: &str) -> V4 {
    device_with(line, id, CONV).await
}

/// A device on `line`: connected, `interface` declared and accepted, subscribed to its
/// own diagnostics (`fbbus/diag/<id>`).
pub async fn device_with(line: &Line, id: &str, interface: &str) -> V4 {
    let mut dev = V4::connect(line.port(), id, None).await.unwrap();
    dev.declare(id, interface).await;
    dev
}

pub async fn publish(dev: &V4, topic: &str, payload: String, retain: bool) {
    dev.client
        .publish(topic, rumqttc::QoS::AtLeastOnce, retain, payload)
        .await
        .unwrap();
}

/// Every publish received until `quiet` passes without one.
pub async fn drain(obs: &mut V4, quiet: Duration) -> Vec<rumqttc::Publish> {
    let mut out = Vec::new();
    while let Some(p) = obs.next_publish(quiet).await {
        out.push(p);
    }
    out
}

pub fn positions(received: &[rumqttc::Publish], topic: &str) -> Vec<i64> {
    received
        .iter()
        .filter(|p| p.topic == topic)
        .map(|p| serde_json::from_slice::<Value>(&p.payload).unwrap())
        .map(|v| v.as_i64().unwrap())
        .collect()
}

/// Whether Python's `eclipse-zenoh` is importable (`.ci/run` installs it); without it the
/// test is skipped loudly, or fails where `CI` is set.
pub fn python_zenoh() -> bool {
    let ok = Command::new("python3")
        .args(["-c", "import zenoh"])
        .stdout(Stdio::null())
        .stderr(Stdio::null())
        .status()
        .is_ok_and(|s| s.success());
    if !ok {
        assert!(
            std::env::var_os("CI").is_none(),
            "Python eclipse-zenoh is not installed; .ci/run should have installed it"
        );
        eprintln!("SKIPPED: Python eclipse-zenoh is not installed (pip install eclipse-zenoh==1.10.2; .ci/run does)");
    }
    ok
}

/// A Python program of `broker/tests/python/` talking line by line on stdin/stdout;
/// killed when dropped.
pub struct Python {
    child: Child,
    stdin: ChildStdin,
    lines: mpsc::Receiver<String>,
    name: String,
}

impl Python {
    pub fn spawn(script: &str, args: &[&str]) -> Python {
        Python::spawn_in(None, script, args)
    }

    /// The script run in network namespace `netns` (`ip netns exec`, which becomes the
    /// Python process), or in the test's own.
    pub fn spawn_in(netns: Option<&str>, script: &str, args: &[&str]) -> Python {
        let path = format!("{}/tests/python/{script}", env!("CARGO_MANIFEST_DIR"));
        let mut command = match netns {
            Some(ns) => {
                let mut c = Command::new("ip");
                c.args(["netns", "exec", ns, "python3"]);
                c
            }
            None => Command::new("python3"),
        };
        let mut child = command
            .arg(&path)
            .args(args)
            .stdin(Stdio::piped())
            .stdout(Stdio::piped())
            .stderr(Stdio::inherit())
            .spawn()
            .unwrap_or_else(|e| panic!("cannot run {path}: {e}"));
        let stdin = child.stdin.take().unwrap();
        let stdout = child.stdout.take().unwrap();
        let (tx, lines) = mpsc::channel();
        std::thread::spawn(move || {
            for line in std::io::BufReader::new(stdout)
                .lines()
                .map_while(Result::ok)
            {
                if tx.send(line).is_err() {
                    return;
                }
            }
        });
        Python {
            child,
            stdin,
            lines,
            name: script.to_owned(),
        }
    }

    /// Sends the program a signal (`STOP`, `CONT`, ...) with kill(1): a frozen runtime.
    pub fn signal(&self, signal: &str) {
        let pid = self.child.id().to_string();
        let ok = Command::new("kill")
            .args([&format!("-{signal}"), &pid])
            .status()
            .is_ok_and(|s| s.success());
        assert!(ok, "kill -{signal} {pid} failed");
    }

    /// Writes one line to the program.
    pub fn send(&mut self, line: &str) {
        writeln!(self.stdin, "{line}").unwrap();
        self.stdin.flush().unwrap();
    }

    /// Waits up to `within` for the program to exit by itself (a browser script quits its
    /// browser first: killed, it would leave Chromium and its driver running); whether
    /// it did. Dropping kills it in any case.
    pub fn wait_exit(&mut self, within: Duration) -> bool {
        let deadline = std::time::Instant::now() + within;
        while std::time::Instant::now() < deadline {
            if let Ok(Some(_)) = self.child.try_wait() {
                return true;
            }
            std::thread::sleep(Duration::from_millis(50));
        }
        false
    }

    /// The program's next line, if one comes within `within`.
    pub fn next_line(&self, within: Duration) -> Option<String> {
        self.lines.recv_timeout(within).ok()
    }

    /// Sends `command` and returns the program's answer, one JSON line (20 s at most).
    pub fn ask(&mut self, command: &str) -> Value {
        self.send(command);
        self.answer(command)
    }

    /// The program's answer to `command`, sent before ([`Python::send`]): programs asked
    /// one after the other answer meanwhile.
    pub fn answer(&mut self, command: &str) -> Value {
        let line = self
            .next_line(Duration::from_secs(20))
            .unwrap_or_else(|| panic!("{}: no answer to `{command}` in 20 s", self.name));
        let answer: Value = serde_json::from_str(&line)
            .unwrap_or_else(|e| panic!("{}: `{command}` answered {line:?}: {e}", self.name));
        assert!(
            answer.get("error").is_none(),
            "{}: `{command}` failed: {answer}",
            self.name
        );
        answer
    }
}

impl Drop for Python {
    fn drop(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

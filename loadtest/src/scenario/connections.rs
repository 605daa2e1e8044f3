//! Connection scenarios: many idle connections (with the broker's resident memory when
//! it runs on this machine) and connect/reconnect storms with authentication.
//!
//! The harness's one connection wave ([`connect_many`]) and one idle-memory measurement
//! ([`idle_memory`]) live here; `compare`'s `idlemem`, `connrate` and `authstorm` run
//! them too, against the brokers it starts.
//!
//! Their batches count connections, not messages: `sent` is connections attempted,
//! `delivered` connections up, latency is the time from the wave's start (when every
//! device wanted to connect) to each connection's CONNACK.

use std::sync::Arc;
use std::time::{Duration, Instant};

use serde::Serialize;
use tokio::sync::Semaphore;

use crate::client::{Client, ClientConfig};
use crate::model::Batch;
use crate::session::Session;
use crate::target::Target;
use crate::{broker_process, clock, tally};

/// `idle`: `connections` clients connect (keep-alive 60 s) and stay idle for `hold`.
#[derive(Debug, Clone, Serialize)]
pub struct Idle {
    pub connections: usize,
    pub hold_s: u64,
    pub repeats: u32,
}

/// `storm`: `devices` clients connect at once, then all drop without DISCONNECT (power
/// cut) and reconnect at once. With `--username`, device `i` logs in as the user of the
/// same name with `{i}` replaced (`dev-{i}`), all with the one password given.
#[derive(Debug, Clone, Serialize)]
pub struct Storm {
    pub devices: usize,
    pub repeats: u32,
}

/// Connections opened at once, at most, by `idle` and `storm`: the harness's own
/// file-descriptor budget.
pub const CONCURRENT_CONNECTS: usize = 512;

/// One wave of concurrent connects and what came of it.
pub struct Wave {
    pub n: usize,
    pub clients: Vec<Client>,
    pub errors: Vec<String>,
    /// Start of each connection to its CONNACK.
    pub latency: hdrhistogram::Histogram<u64>,
    /// First connect started to last CONNACK.
    pub took: Duration,
    pub started_ms: u64,
}

/// Connects `n` clients concurrently, at most `in_flight` in progress, each bounded by
/// `timeout`. Client `i` is `<prefix>-<i>`; a `{i}` in the target's username becomes `i`.
pub async fn connect_many(
    target: &Target,
    prefix: &str,
    n: usize,
    in_flight: usize,
    timeout: Duration,
) -> Wave {
    let gate = Arc::new(Semaphore::new(in_flight.max(1)));
    let started_ms = clock::now_ms();
    let start = Instant::now();
    let mut tasks = Vec::with_capacity(n);
    for i in 0..n {
        let mut target = target.clone();
        if let Some(user) = &target.username {
            target.username = Some(user.replace("{i}", &i.to_string()));
        }
        let gate = gate.clone();
        let id = format!("{prefix}-{i}");
        tasks.push(tokio::spawn(async move {
            let _permit = gate.acquire_owned().await;
            let mut config = ClientConfig::new(id);
            config.timeout = timeout;
            // From the wave's start, not the permit: every device wanted to connect then,
            // and waiting for a permit is part of its wait.
            Client::connect(&target, &config, None)
                .await
                .map(|c| (c, start.elapsed()))
        }));
    }
    let mut wave = Wave {
        n,
        clients: Vec::new(),
        errors: Vec::new(),
        latency: tally::histogram(),
        took: Duration::ZERO,
        started_ms,
    };
    for task in tasks {
        match task.await {
            Ok(Ok((client, took))) => {
                wave.latency
                    .saturating_record((took.as_micros() as u64).max(1));
                wave.clients.push(client);
            }
            Ok(Err(e)) => wave.errors.push(e.to_string()),
            Err(e) => wave.errors.push(e.to_string()),
        }
    }
    wave.took = start.elapsed();
    wave
}

impl Wave {
    /// Connections up per second of the wave (up / first connect to last CONNACK).
    pub fn rate(&self) -> f64 {
        self.clients.len() as f64 / self.took.as_secs_f64().max(1e-9)
    }

    /// The wave as a batch: `up` connections counted as delivered.
    fn batch(&self, target: &str, label: String, up: usize, repeat: u32) -> Batch {
        let n = self.n;
        let error = self.errors.first().map(|first| {
            format!(
                "{} of {n} connections failed; first: {first}",
                self.errors.len()
            )
        });
        Batch {
            target: target.to_owned(),
            label,
            x: n as f64,
            repeat,
            started_ms: self.started_ms,
            sent: n as u64,
            delivered: up as u64,
            expected: n as u64,
            delivered_fb: None,
            duplicates: 0,
            out_of_order: 0,
            send_us: self.took.as_micros() as u64,
            processing_us: self.took.as_micros() as u64,
            throughput: up as f64 / self.took.as_secs_f64().max(1e-9),
            latency: tally::summarize(&self.latency),
            ok: error.is_none(),
            error,
        }
    }
}

/// The broker's resident memory before and after a wave of idle connections.
pub struct IdleMemory {
    pub wave: Wave,
    pub before_kib: Option<u64>,
    pub after_kib: Option<u64>,
}

impl IdleMemory {
    /// The growth per connection that came up, in KiB (/proc's kB), when both readings
    /// exist.
    pub fn kib_per_connection(&self) -> Option<f64> {
        let (b, a) = (self.before_kib?, self.after_kib?);
        let up = self.wave.clients.len();
        (up > 0).then(|| (a as f64 - b as f64) / up as f64)
    }
}

/// Reads the resident memory of `pid` after `settle`, connects `n` idle clients
/// (keep-alive 60 s, at most `in_flight` connecting at once), holds them for `hold` and
/// reads it again. Without a pid only the wave is measured.
#[allow(clippy::too_many_arguments)]
pub async fn idle_memory(
    target: &Target,
    pid: Option<u32>,
    prefix: &str,
    n: usize,
    in_flight: usize,
    settle: Duration,
    hold: Duration,
    timeout: Duration,
) -> IdleMemory {
    tokio::time::sleep(settle).await;
    let before_kib = pid.and_then(broker_process::rss_kib);
    let wave = connect_many(target, prefix, n, in_flight, timeout).await;
    tokio::time::sleep(hold).await;
    let after_kib = pid.and_then(broker_process::rss_kib);
    IdleMemory {
        wave,
        before_kib,
        after_kib,
    }
}

impl Idle {
    pub fn planned(&self, targets: usize) -> u64 {
        (self.repeats as usize * targets) as u64
    }

    pub async fn run(&self, s: &mut Session, targets: &[Target], prefix: &str, timeout: Duration) {
        for repeat in 1..=self.repeats {
            for (rig, target) in targets.iter().enumerate() {
                if s.out_of_time() {
                    return;
                }
                let label = s.labels[rig].clone();
                let pid = target
                    .is_loopback()
                    .then(|| broker_process::pid_listening_on(target.port))
                    .flatten();
                let id_prefix = format!("{prefix}-{}-idle{repeat}", label.to_lowercase());
                let idle = idle_memory(
                    target,
                    pid,
                    &id_prefix,
                    self.connections,
                    CONCURRENT_CONNECTS,
                    Duration::ZERO,
                    Duration::from_secs(self.hold_s),
                    timeout,
                )
                .await;
                let (per_connection, after) = (idle.kib_per_connection(), idle.after_kib);
                let wave = idle.wave;
                let still_up = wave.clients.iter().filter(|c| c.alive()).count();
                let mut batch = wave.batch(
                    &label,
                    format!("idle {}", self.connections),
                    still_up,
                    repeat,
                );
                if still_up < wave.clients.len() && batch.error.is_none() {
                    batch.ok = false;
                    batch.error = Some(format!(
                        "{} connections dropped while idle",
                        wave.clients.len() - still_up
                    ));
                }
                s.record(rig, batch, &wave.latency);
                s.figure(rig, "connects_per_s", wave.rate(), "conn/s");
                match (per_connection, after) {
                    (Some(per), Some(a)) => {
                        s.figure(rig, "rss_kib_per_idle_connection", per, "KiB");
                        s.figure(rig, "broker_rss_kib", a as f64, "KiB");
                    }
                    _ if repeat == 1 => s.notes.push(format!(
                        "{label}: broker memory not measured: no process listening on port {} is visible on this machine",
                        target.port
                    )),
                    _ => {}
                }
                for c in wave.clients {
                    c.disconnect().await;
                }
            }
        }
    }
}

impl Storm {
    pub fn planned(&self, targets: usize) -> u64 {
        (2 * self.repeats as usize * targets) as u64
    }

    pub async fn run(&self, s: &mut Session, targets: &[Target], prefix: &str, timeout: Duration) {
        for repeat in 1..=self.repeats {
            for (rig, target) in targets.iter().enumerate() {
                if s.out_of_time() {
                    return;
                }
                let label = s.labels[rig].clone();
                let id_prefix = format!("{prefix}-{}-dev", label.to_lowercase());
                // All connect at once; then a power cut: every device drops without
                // DISCONNECT, and all come back at once.
                let mut up: Vec<Client> = Vec::new();
                for kind in ["connect", "reconnect"] {
                    for c in up.drain(..) {
                        c.abort();
                    }
                    let wave = connect_many(
                        target,
                        &id_prefix,
                        self.devices,
                        CONCURRENT_CONNECTS,
                        timeout,
                    )
                    .await;
                    let name = format!("{kind} storm {}", self.devices);
                    let batch = wave.batch(&label, name, wave.clients.len(), repeat);
                    s.record(rig, batch, &wave.latency);
                    s.figure(
                        rig,
                        &format!("{kind}_storm_s"),
                        wave.took.as_secs_f64(),
                        "s",
                    );
                    up = wave.clients;
                }
                for c in up {
                    c.disconnect().await;
                }
            }
        }
    }
}

//! The connection scenarios (`idlemem`, `connrate`, `connect1`, `authstorm`): the
//! harness's own connection wave and idle-memory measurement
//! ([`loadtest::scenario::connections`]).

use std::time::{Duration, Instant};

use anyhow::{Context as _, Result};

use loadtest::broker_process::spawn::{Kind, Running};
use loadtest::scenario::connections::{self, Wave};
use loadtest::target::Target;

use super::{add_note, mb, Login, Outcome, Params, STORM_USER_PREFIX};
use crate::compare::bridge::{cpu_ticks, TICKS_PER_SECOND};

/// The broker as the harness's client stack addresses it, optionally with a login.
fn target(broker: &Running, login: Option<(&str, &str)>) -> Result<Target> {
    let mut target = Target::parse(&broker.url())?;
    if let Some((user, password)) = login {
        target.username = Some(user.to_owned());
        target.password = Some(password.to_owned());
    }
    Ok(target)
}

/// Failed connections of a wave, for the scenario's note.
fn wave_note(wave: &Wave) -> Option<String> {
    wave.errors
        .first()
        .map(|first| format!("{} of {} failed: {first}", wave.errors.len(), wave.n))
}

/// A wave's clients, dropped without DISCONNECT: the broker is stopped next anyway.
fn close(wave: Wave) {
    for c in wave.clients {
        c.abort();
    }
}

pub(super) async fn idle_memory(broker: &Running, p: &Params) -> Result<Outcome> {
    let idle = connections::idle_memory(
        &target(broker, None)?,
        Some(broker.pid()),
        "bench-idle",
        p.idle_connections,
        64,
        Duration::from_secs(1),
        Duration::from_secs(1),
        p.deadline,
    )
    .await;
    let before = idle
        .before_kib
        .context("cannot read VmRSS of the broker process")?;
    let after = idle
        .after_kib
        .context("cannot read VmRSS of the broker process")?;
    let n = idle.wave.clients.len();
    // KB as /proc reports it (kB = 1024 bytes), like the reference figures.
    let per_conn = idle.kib_per_connection();
    let note = wave_note(&idle.wave);
    close(idle.wave);
    Ok(Outcome {
        cells: vec![
            mb(before),
            mb(after),
            per_conn
                .map(|v| format!("{v:.2}"))
                .unwrap_or_else(|| "-".into()),
            format!("{n}/{}", p.idle_connections),
        ],
        keys: vec![per_conn],
        lost: None,
        note,
        timed_out: false,
    })
}

pub(super) async fn connection_rate(broker: &Running, p: &Params) -> Result<Outcome> {
    let cpu_before = cpu_ticks(broker.pid());
    let wave = connections::connect_many(
        &target(broker, None)?,
        "bench-rate",
        p.connrate_connections,
        p.connrate_inflight,
        p.deadline,
    )
    .await;
    let cpu_after = cpu_ticks(broker.pid());
    let n = wave.clients.len();
    let rate = (n > 0).then(|| wave.rate());
    let took = wave.took;
    let note = wave_note(&wave);
    close(wave);
    // The broker's own CPU per connection: steadier than the rate on a machine the harness
    // shares, where the rate also measures how the two split the cores.
    let cpu_per_connection = match (cpu_before, cpu_after) {
        (Some(before), Some(after)) if n > 0 => {
            let us = (after - before) as f64 * 1e6 / TICKS_PER_SECOND / n as f64;
            format!("{us:.0} us")
        }
        _ => "-".into(),
    };
    Ok(Outcome {
        cells: vec![
            rate.map(|r| format!("{r:.0}"))
                .unwrap_or_else(|| "-".into()),
            format!("{n}/{}", p.connrate_connections),
            format!("{:.3} s", took.as_secs_f64()),
            cpu_per_connection,
        ],
        keys: vec![rate],
        lost: None,
        note,
        timed_out: false,
    })
}

/// `connect1`: one device connecting at a time, as a line's devices come back one by one
/// after a power cut or a cable is plugged back. A wave of one connection per step, so the
/// time is TCP connect + CONNECT -> CONNACK of that one connection; every connection stays
/// open to the end, like the devices.
pub(super) async fn connect_latency(broker: &Running, p: &Params) -> Result<Outcome> {
    let target = target(broker, None)?;
    // Bounded like every latency of the harness: `saturating_record` into an
    // auto-resizing histogram clamps instead of growing, and gave 2 us for rumqttd's 2 ms.
    let mut latency = loadtest::tally::histogram();
    let mut waves = Vec::with_capacity(p.connect1_connections);
    let mut failed = Vec::new();
    let start = Instant::now();
    let mut timed_out = false;
    for i in 0..p.connect1_connections {
        if start.elapsed() > p.deadline {
            timed_out = true;
            break;
        }
        let wave =
            connections::connect_many(&target, &format!("bench-one-{i}"), 1, 1, p.deadline).await;
        if wave.clients.is_empty() {
            failed.extend(wave.errors.first().cloned());
        } else {
            latency.saturating_record((wave.took.as_micros() as u64).max(1));
        }
        waves.push(wave);
    }
    let connected = latency.len() as usize;
    waves.into_iter().for_each(close);
    let ms = |q: f64| (connected > 0).then(|| latency.value_at_quantile(q) as f64 / 1000.0);
    let cell = |v: Option<f64>| v.map(|v| format!("{v:.3}")).unwrap_or_else(|| "-".into());
    let (p50, p99) = (ms(0.5), ms(0.99));
    Ok(Outcome {
        cells: vec![
            cell(p50),
            cell(p99),
            format!("{connected}/{}", p.connect1_connections),
        ],
        keys: vec![p50, p99],
        lost: None,
        note: failed
            .first()
            .map(|first| format!("{} failed: {first}", failed.len())),
        timed_out,
    })
}

pub(super) async fn auth_storm(broker: &Running, p: &Params, login: &Login) -> Result<Outcome> {
    let n = p.storm_devices;
    let user = format!("{STORM_USER_PREFIX}{{i}}");
    let target = target(broker, Some((&user, &login.password)))?;
    // Every device at once: as many in flight as there are devices.
    let wave = connections::connect_many(&target, "bench-storm", n, n, p.deadline).await;
    let connected = wave.clients.len();
    let pct = |q: f64| -> Option<Duration> {
        (connected > 0).then(|| Duration::from_micros(wave.latency.value_at_quantile(q)))
    };
    let secs = |d: Option<Duration>| {
        d.map(|d| format!("{:.3} s", d.as_secs_f64()))
            .unwrap_or_else(|| "-".into())
    };
    let all = (connected > 0).then_some(wave.took);
    let store = match broker.kind {
        Kind::Fbbus => "argon2id m=8192 t=1 p=1",
        Kind::Rumqttd => "plaintext map",
        Kind::Mosquitto | Kind::MosquittoDefault => "PBKDF2-SHA512 $7$",
        // The same file as Mosquitto's (`mosquitto_password_file`).
        Kind::FlashMq => "PBKDF2-SHA512 $7$ (mosquitto_passwd file)",
    };
    let mut note = wave_note(&wave);
    // "All have CONNACK" is only true when nobody failed.
    let complete = connected == n;
    if !complete && note.is_none() {
        add_note(&mut note, format!("{} not connected", n - connected));
    }
    let cells = vec![
        secs(all),
        secs(pct(0.50)),
        secs(pct(0.99)),
        format!("{connected}/{n}"),
        store.into(),
    ];
    close(wave);
    Ok(Outcome {
        cells,
        keys: vec![all.filter(|_| complete).map(|d| d.as_secs_f64())],
        lost: None,
        note,
        timed_out: false,
    })
}

//! `restart`: a broker filled with retained messages and persistent sessions with queued
//! messages, stopped and started again on its store: how long until it serves them, and
//! whether everything came back.

use std::net::SocketAddr;
use std::path::Path;
use std::sync::atomic::AtomicU64;
use std::sync::Arc;
use std::time::{Duration, Instant};

use anyhow::{bail, Context as _, Result};
use loadtest::broker_process::spawn::{Kind, Running};
use loadtest::raw_client::{self as mqtt, publish_acked, PacketReader};
use loadtest::scrape;
use tokio::io::AsyncWriteExt;

use super::metric;
use super::{add_note, connect, Figures, PersistParams, CONNECT_TIMEOUT, PAYLOAD_BYTES};

/// Retained messages per topic group (`bench/retained/<group>/+`): the check after the
/// restart subscribes group by group, as a burst of retained messages on one SUBSCRIBE
/// beyond fbbus's `router_max_outgoing_packets` (1,000) is cut there.
pub(super) const RETAINED_GROUP: usize = 500;

pub(super) fn retained_topic(k: usize) -> String {
    format!(
        "bench/retained/{:04}/{:03}",
        k / RETAINED_GROUP,
        k % RETAINED_GROUP
    )
}

/// Every retained message back: one subscriber, one group at a time (1 s quiet ends a
/// group short of its count).
pub(super) async fn retained_back(
    addr: SocketAddr,
    retained: usize,
    limit: Duration,
) -> Result<usize> {
    let (mut conn, _) = connect(addr, "bench-check-all", true).await?;
    let end_at = Instant::now() + limit;
    let mut back = 0;
    for (i, group) in (0..retained).step_by(RETAINED_GROUP).enumerate() {
        let want = RETAINED_GROUP.min(retained - group);
        let filter = format!("bench/retained/{:04}/+", group / RETAINED_GROUP);
        conn.get_mut()
            .write_all(&mqtt::subscribe_qos_packet(
                (i % 65_535) as u16 + 1,
                &filter,
                0,
            ))
            .await?;
        let left = end_at.saturating_duration_since(Instant::now());
        if left.is_zero() {
            break;
        }
        back += count_publishes(&mut conn, want, Duration::from_secs(1), left).await;
    }
    Ok(back)
}

pub(super) fn session_id(i: usize) -> String {
    format!("bench-session-{i:04}")
}

pub(super) fn session_topic(i: usize) -> String {
    format!("bench/session/{i:04}")
}

/// Bytes of the files under `dir` (not following links).
pub(super) fn dir_bytes(dir: &Path) -> u64 {
    let Ok(entries) = std::fs::read_dir(dir) else {
        return 0;
    };
    entries
        .flatten()
        .filter_map(|e| {
            let meta = e.metadata().ok()?;
            Some(if meta.is_dir() {
                dir_bytes(&e.path())
            } else {
                meta.len()
            })
        })
        .sum()
}

/// `key=value` of fbbus's last `store restored` log line.
pub(super) fn restored_line(log: &str) -> Option<Vec<(String, String)>> {
    let line = log.lines().rev().find(|l| l.contains("store restored"))?;
    Some(
        line.split_whitespace()
            .filter_map(|w| {
                let (k, v) = w.split_once('=')?;
                Some((strip_ansi(k), strip_ansi(v)))
            })
            .collect(),
    )
}

/// Without the colour escapes a terminal-less log may still carry.
pub(super) fn strip_ansi(s: &str) -> String {
    let mut out = String::new();
    let mut chars = s.chars();
    while let Some(c) = chars.next() {
        if c == '\u{1b}' {
            for c in chars.by_ref() {
                if c.is_ascii_alphabetic() {
                    break;
                }
            }
        } else {
            out.push(c);
        }
    }
    out
}

/// Whether the broker answers: `/readyz` 200 (fbbus) or a CONNACK.
pub(super) async fn answers(broker: &Running) -> bool {
    match broker.admin {
        Some(admin) => scrape::get(&format!("http://{admin}/readyz"), Duration::from_secs(1))
            .await
            .is_ok(),
        None => tokio::time::timeout(
            Duration::from_secs(1),
            mqtt::connect_session(broker.addr, "bench-probe", true),
        )
        .await
        .is_ok_and(|r| r.is_ok()),
    }
}

/// A fresh subscriber to `topic` receives its retained message within 1 s.
pub(super) async fn retained_served(addr: SocketAddr, topic: &str) -> bool {
    let attempt = async {
        let (mut conn, _) = connect(addr, "bench-check", true).await.ok()?;
        mqtt::subscribe_qos(conn.get_mut(), topic, 0).await.ok()?;
        loop {
            if conn.read_more().await.ok()? == 0 {
                return None;
            }
            while let Ok(Some((header, body))) = conn.next_packet() {
                if mqtt::publish_payload(header, body).is_some() && (header & 1) == 1 {
                    let _ = conn.get_mut().write_all(&mqtt::DISCONNECT).await;
                    return Some(());
                }
            }
        }
    };
    tokio::time::timeout(Duration::from_secs(1), attempt)
        .await
        .ok()
        .flatten()
        .is_some()
}

/// PUBLISHes on `conn` until `want` arrived or nothing came for `quiet`, each QoS 1 one
/// acknowledged; returns how many arrived (bounded by `limit`).
pub(super) async fn count_publishes(
    conn: &mut PacketReader,
    want: usize,
    quiet: Duration,
    limit: Duration,
) -> usize {
    let end_at = Instant::now() + limit;
    let mut got = 0;
    let mut acks = Vec::new();
    while got < want && Instant::now() < end_at {
        match tokio::time::timeout(quiet, conn.read_more()).await {
            Ok(Ok(n)) if n > 0 => {}
            _ => break,
        }
        while let Ok(Some((header, body))) = conn.next_packet() {
            if mqtt::publish_payload(header, body).is_some() {
                got += 1;
                if let Some(pid) = mqtt::packet_id(header, body) {
                    acks.extend_from_slice(&mqtt::puback_packet(pid));
                }
            }
        }
        if !acks.is_empty() {
            if conn.get_mut().write_all(&acks).await.is_err() {
                break;
            }
            acks.clear();
        }
    }
    got
}

pub(super) async fn restart(broker: &mut Running, p: &PersistParams) -> Result<Figures> {
    let addr = broker.addr;
    let fill_started = Instant::now();
    // The sessions first, so that the queued messages are queued for them.
    let slots = Arc::new(tokio::sync::Semaphore::new(64));
    let mut tasks = Vec::with_capacity(p.sessions);
    for i in 0..p.sessions {
        let slots = Arc::clone(&slots);
        tasks.push(tokio::spawn(async move {
            let _slot = slots.acquire().await;
            let (mut conn, _) = connect(addr, &session_id(i), false).await?;
            let granted = tokio::time::timeout(
                CONNECT_TIMEOUT,
                mqtt::subscribe_qos(conn.get_mut(), &session_topic(i), 1),
            )
            .await
            .context("no SUBACK")??;
            if granted != 1 {
                bail!("{}: granted QoS {granted}", session_id(i));
            }
            conn.get_mut().write_all(&mqtt::DISCONNECT).await?;
            // The broker closes the connection after DISCONNECT.
            let _ = tokio::time::timeout(Duration::from_secs(5), conn.read_more()).await;
            anyhow::Ok(())
        }));
    }
    for t in tasks {
        t.await.context("session task")??;
    }
    let (mut publisher, _) = connect(addr, "bench-fill", true).await?;
    let sent = AtomicU64::new(0);
    let body = [0x5a; PAYLOAD_BYTES];
    let fill = async {
        publish_acked(&mut publisher, p.retained, 500, &sent, |k, pid, buf| {
            buf.extend(mqtt::publish_qos1_packet(
                &retained_topic(k),
                pid,
                true,
                &body,
            ));
        })
        .await?;
        let sessions = p.sessions.max(1);
        publish_acked(
            &mut publisher,
            p.sessions * p.queued,
            500,
            &sent,
            |k, pid, buf| {
                buf.extend(mqtt::publish_qos1_packet(
                    &session_topic(k % sessions),
                    pid,
                    false,
                    &body,
                ));
            },
        )
        .await
    };
    tokio::time::timeout(p.deadline * 2, fill)
        .await
        .context("filling the broker: timeout")?
        .context("filling the broker")?;
    publisher.get_mut().write_all(&mqtt::DISCONNECT).await?;
    drop(publisher);
    let fill_s = fill_started.elapsed().as_secs_f64();
    tokio::time::sleep(Duration::from_millis(200)).await;
    let mut note = None;
    if let (Kind::Fbbus, Some(admin)) = (broker.kind, broker.admin) {
        let retained = metric(admin, "fbbus_store_retained_messages").await;
        let sessions = metric(admin, "fbbus_store_sessions").await;
        let queued = metric(admin, "fbbus_store_queued_messages").await;
        if retained as usize != p.retained
            || sessions as usize != p.sessions
            || queued as usize != p.sessions * p.queued
        {
            add_note(
                &mut note,
                format!(
                    "before the stop the store held {retained:.0} retained, {sessions:.0} sessions, \
                     {queued:.0} queued"
                ),
            );
        }
    }

    let stop = broker
        .terminate(Duration::from_secs(60))
        .context("stopping the broker")?;
    let store_dir = broker.dir().join(match broker.kind {
        Kind::Fbbus => "store",
        _ => "mosquitto-store",
    });
    let store_mb = dir_bytes(&store_dir) as f64 / (1024.0 * 1024.0);

    let spawned = Instant::now();
    broker.respawn().context("starting the broker again")?;
    let deadline = spawned + p.deadline;
    let ready = loop {
        if let Some(exit) = broker.exited() {
            bail!("after the restart: {exit}");
        }
        if answers(broker).await {
            break spawned.elapsed();
        }
        if Instant::now() > deadline {
            bail!("not ready {:?} after the restart", p.deadline);
        }
        tokio::time::sleep(Duration::from_millis(2)).await;
    };
    let last = retained_topic(p.retained.saturating_sub(1));
    let served = loop {
        if retained_served(addr, &last).await {
            break spawned.elapsed();
        }
        if let Some(exit) = broker.exited() {
            bail!("after the restart: {exit}");
        }
        if Instant::now() > deadline {
            bail!(
                "the retained message on {last} was not served {:?} after the restart",
                p.deadline
            );
        }
        tokio::time::sleep(Duration::from_millis(2)).await;
    };

    // Not timed: is everything back?
    let retained_back = retained_back(addr, p.retained, p.deadline).await?;
    let (mut session, present) = connect(addr, &session_id(0), false).await?;
    let queued_back = count_publishes(
        &mut session,
        p.queued,
        Duration::from_secs(2),
        Duration::from_secs(10),
    )
    .await;
    drop(session);

    let log = std::fs::read_to_string(broker.log_path()).unwrap_or_default();
    let restored = match broker.kind {
        Kind::Fbbus => restored_line(&log),
        _ => None,
    };
    let field = |k: &str| -> Option<String> {
        restored
            .as_ref()?
            .iter()
            .find(|(key, _)| key == k)
            .map(|(_, v)| v.clone())
    };
    let number = |k: &str| field(k).and_then(|v| v.parse::<f64>().ok());
    let restored_cell = match broker.kind {
        Kind::Fbbus => match (field("retained"), field("sessions"), field("queued")) {
            (Some(r), Some(s), Some(q)) => format!("{r}/{s}/{q}"),
            _ => "no log line".into(),
        },
        _ => "-".into(),
    };
    if retained_back < p.retained {
        add_note(
            &mut note,
            format!(
                "{} retained messages missing after the restart",
                p.retained - retained_back
            ),
        );
    }
    let secs = |d: Duration| format!("{:.3}", d.as_secs_f64());
    let opt = |v: Option<f64>| v.map(|v| format!("{v:.0}")).unwrap_or_else(|| "-".into());
    Ok(Figures {
        cells: vec![
            secs(served),
            secs(ready),
            opt(number("read_ms")),
            opt(number("put_back_ms")),
            format!("{store_mb:.1}"),
            format!("{fill_s:.1}"),
            secs(stop),
            restored_cell,
            format!("{retained_back}/{}", p.retained),
            format!(
                "{}, {queued_back}/{}",
                if present { "present" } else { "NOT present" },
                p.queued
            ),
        ],
        keys: vec![
            Some(served.as_secs_f64()),
            Some(ready.as_secs_f64()),
            number("read_ms"),
            number("put_back_ms"),
            Some(store_mb),
        ],
        note,
    })
}

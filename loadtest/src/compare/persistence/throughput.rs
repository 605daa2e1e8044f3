//! `throughput`: the QoS 1 burst fan-in to a persistent subscriber, and the broker's CPU
//! per message it took.

use std::sync::atomic::{AtomicU64, AtomicUsize, Ordering};
use std::sync::Arc;
use std::time::Instant;

use anyhow::{Context as _, Result};
use loadtest::broker_process;
use loadtest::broker_process::spawn::{Kind, Running};
use loadtest::raw_client::{self as mqtt, publish_acked};
use tokio::sync::watch;

use super::{
    add_note, lost, payload, receive_acking, store_counters, subscriber_and_publishers, Figures,
    PersistParams,
};

pub(super) fn count_and_mean(count: f64, seconds: f64) -> String {
    if count <= 0.0 {
        "0".into()
    } else {
        format!("{count:.0} ({:.2} ms)", seconds * 1000.0 / count)
    }
}

pub(super) async fn throughput(broker: &Running, p: &PersistParams) -> Result<Figures> {
    let topic = "bench/persist";
    let addr = broker.addr;
    let (mut sub, pubs) = subscriber_and_publishers(addr, topic, p.publishers).await?;
    let store = match (broker.kind, broker.admin) {
        (Kind::Fbbus, Some(admin)) => Some((admin, store_counters(admin).await)),
        _ => None,
    };
    let epoch = Instant::now();
    let end_at = epoch + p.deadline;
    let (go_tx, go_rx) = watch::channel(false);
    let done = Arc::new(AtomicUsize::new(0));
    let sent = Arc::new(AtomicU64::new(0));
    let mut tasks = Vec::with_capacity(p.publishers);
    for (i, mut conn) in pubs.into_iter().enumerate() {
        let (mut go, done, sent) = (go_rx.clone(), done.clone(), sent.clone());
        let (messages, window) = (p.messages, p.window);
        tasks.push(tokio::spawn(async move {
            let _ = go.wait_for(|go| *go).await;
            let result = tokio::time::timeout_at(
                end_at.into(),
                publish_acked(&mut conn, messages, window, &sent, |k, pid, buf| {
                    let now_ns = epoch.elapsed().as_nanos() as u64;
                    buf.extend(mqtt::publish_qos1_packet(
                        topic,
                        pid,
                        false,
                        &payload(now_ns, i as u32, k as u64),
                    ));
                }),
            )
            .await;
            done.fetch_add(1, Ordering::Release);
            let result = match result {
                Ok(Ok(())) => None,
                Ok(Err(e)) => Some(format!("publisher {i}: {e}")),
                Err(_) => Some("publishers hit the deadline".to_string()),
            };
            (conn, result)
        }));
    }
    let cpu_before = broker_process::cpu_ns_by_thread(broker.pid());
    let first_send = Instant::now();
    go_tx.send(true).ok();
    let received = receive_acking(&mut sub, p.publishers, p.messages, &done, end_at, epoch).await;
    let cpu = cpu_per_message(
        &cpu_before,
        &broker_process::cpu_ns_by_thread(broker.pid()),
        received.delivered,
    );
    let mut note = None;
    let mut conns = Vec::new();
    for task in tasks {
        let (conn, problem) = task.await.context("publisher task")?;
        if let Some(problem) = problem {
            if note.is_none() {
                add_note(&mut note, problem);
            }
        }
        conns.push(conn);
    }
    if received.end != "complete" && received.end != "idle" {
        add_note(&mut note, received.end.clone());
    }
    let sent = sent.load(Ordering::Relaxed);
    let span = received
        .last_receive
        .map(|l| l.duration_since(first_send).as_secs_f64());
    let rate = span
        .filter(|s| *s > 0.0)
        .map(|s| received.delivered as f64 / s);
    let (not_stored, writes, fsyncs) = match store {
        Some((admin, before)) => {
            let after = store_counters(admin).await;
            (
                format!("{:.0}", after.not_stored - before.not_stored),
                count_and_mean(
                    after.writes - before.writes,
                    after.write_seconds - before.write_seconds,
                ),
                count_and_mean(
                    after.fsyncs - before.fsyncs,
                    after.fsync_seconds - before.fsync_seconds,
                ),
            )
        }
        None => ("-".into(), "-".into(), "-".into()),
    };
    drop(conns);
    Ok(Figures {
        cells: vec![
            rate.map(crate::compare::scenarios::si)
                .unwrap_or_else(|| "-".into()),
            format!("{}/{}", received.delivered, p.publishers * p.messages),
            lost(received.delivered, sent),
            received.duplicates.to_string(),
            span.map(|s| format!("{s:.3} s"))
                .unwrap_or_else(|| "-".into()),
            not_stored,
            writes,
            fsyncs,
            cpu,
        ],
        keys: vec![rate],
        note,
    })
}

/// The broker's CPU time per delivered message between two readings of
/// [`broker_process::cpu_ns_by_thread`], in microseconds: the total, then the runtime's
/// workers (`fbbus`), the router (`router-*`) and the store's writer (`fbbus-store`). Shows
/// where a setup's extra cost goes; "-" where /proc cannot be read.
pub(super) fn cpu_per_message(
    before: &std::collections::BTreeMap<String, u64>,
    after: &std::collections::BTreeMap<String, u64>,
    delivered: u64,
) -> String {
    if after.is_empty() || delivered == 0 {
        return "-".into();
    }
    let spent = |pick: &dyn Fn(&str) -> bool| -> f64 {
        let sum = |m: &std::collections::BTreeMap<String, u64>| -> u64 {
            m.iter().filter(|(n, _)| pick(n)).map(|(_, ns)| *ns).sum()
        };
        sum(after).saturating_sub(sum(before)) as f64 / 1000.0 / delivered as f64
    };
    // Another broker (Mosquitto: one thread): the total only.
    if !after.keys().any(|n| n.starts_with("router")) {
        return format!("{:.2}", spent(&|_| true));
    }
    format!(
        "{:.2} ({:.2}+{:.2}+{:.2})",
        spent(&|_| true),
        spent(&|n| n == "fbbus" || n.starts_with("tokio")),
        spent(&|n| n.starts_with("router")),
        spent(&|n| n == "fbbus-store"),
    )
}

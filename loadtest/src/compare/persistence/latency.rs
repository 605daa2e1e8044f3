//! `latency`: publish -> delivery to a persistent subscriber under a steady QoS 1 load on
//! an absolute schedule, in an HDR histogram.

use std::sync::atomic::{AtomicU64, AtomicUsize, Ordering};
use std::sync::Arc;
use std::time::{Duration, Instant};

use anyhow::{Context as _, Result};
use loadtest::broker_process::spawn::Running;
use loadtest::raw_client::{self as mqtt};
use tokio::io::{AsyncReadExt, AsyncWriteExt};

use super::{
    add_note, lost, payload, receive_acking, subscriber_and_publishers, Figures, PersistParams,
};

pub(super) async fn latency(broker: &Running, p: &PersistParams) -> Result<Figures> {
    let topic = "bench/persist-latency";
    let addr = broker.addr;
    let (mut sub, pubs) = subscriber_and_publishers(addr, topic, p.publishers).await?;
    let per_publisher = (p.latency_rate * p.latency_secs) as usize;
    let period_ns = 1_000_000_000 / p.latency_rate.max(1);
    let epoch = Instant::now();
    let end_at = epoch + p.deadline + Duration::from_secs(p.latency_secs);
    let start = tokio::time::Instant::now() + Duration::from_millis(100);
    let done = Arc::new(AtomicUsize::new(0));
    let sent = Arc::new(AtomicU64::new(0));
    let mut tasks = Vec::with_capacity(p.publishers);
    for (i, conn) in pubs.into_iter().enumerate() {
        let (done, sent) = (done.clone(), sent.clone());
        let stream = conn.into_inner();
        tasks.push(tokio::spawn(async move {
            let (mut read, mut write) = stream.into_split();
            // The PUBACKs are read on the side and dropped.
            let acks = tokio::spawn(async move {
                let mut buf = vec![0u8; 16 * 1024];
                while matches!(read.read(&mut buf).await, Ok(n) if n > 0) {}
                read
            });
            let send_all = async {
                for k in 0..per_publisher {
                    tokio::time::sleep_until(start + Duration::from_nanos(k as u64 * period_ns))
                        .await;
                    let now_ns = epoch.elapsed().as_nanos() as u64;
                    let packet = mqtt::publish_qos1_packet(
                        topic,
                        (k % 65_535) as u16 + 1,
                        false,
                        &payload(now_ns, i as u32, k as u64),
                    );
                    write.write_all(&packet).await?;
                    sent.fetch_add(1, Ordering::Relaxed);
                }
                Ok::<(), std::io::Error>(())
            };
            let result = tokio::time::timeout_at(end_at.into(), send_all).await;
            done.fetch_add(1, Ordering::Release);
            let problem = match result {
                Ok(Ok(())) => None,
                Ok(Err(e)) => Some(format!("publisher {i}: {e}")),
                Err(_) => Some("publishers hit the deadline".to_string()),
            };
            (write, acks, problem)
        }));
    }
    let received =
        receive_acking(&mut sub, p.publishers, per_publisher, &done, end_at, epoch).await;
    let mut note = None;
    let mut keep = Vec::new();
    for task in tasks {
        let (write, acks, problem) = task.await.context("publisher task")?;
        if let Some(problem) = problem {
            if note.is_none() {
                add_note(&mut note, problem);
            }
        }
        acks.abort();
        keep.push(write);
    }
    if received.end != "complete" && received.end != "idle" {
        add_note(&mut note, received.end.clone());
    }
    let sent = sent.load(Ordering::Relaxed);
    let (p50, p99, max) = crate::compare::scenarios::latency_ms(&received.latency_ns);
    drop(keep);
    let f = crate::compare::scenarios::ms_cell;
    Ok(Figures {
        cells: vec![
            f(p50),
            f(p99),
            f(max),
            format!("{}/{}", received.delivered, per_publisher * p.publishers),
            lost(received.delivered, sent),
        ],
        keys: vec![p50, p99, max],
        note,
    })
}

//! The probe: a device that publishes and reads its own message back every
//! `PROBE_EVERY` on a thread of its own, through every phase, so a flood's cost to the
//! line is a latency and a loss, not a guess.

use std::collections::HashMap;
use std::net::SocketAddr;
use std::sync::atomic::Ordering;
use std::sync::Arc;
use std::time::{Duration, Instant};

use anyhow::{Context as _, Result};
use loadtest::raw_client::{self as mqtt};
use tokio::io::AsyncWriteExt;
use tokio::net::TcpStream;

use super::{ProbeShared, PROBE_EVERY, PROBE_LOST_AFTER};

// ---------------------------------------------------------------------------------------
// The probe, the sampler, the counters
// ---------------------------------------------------------------------------------------
pub(super) const PROBE_TOPIC: &str = "abuse/probe";

pub(super) async fn probe_connect(addr: SocketAddr) -> Result<TcpStream> {
    let connect = async {
        let mut s = mqtt::connect(addr, "abuse-probe", None).await?;
        mqtt::subscribe_qos(&mut s, PROBE_TOPIC, 1).await?;
        anyhow::Ok(s)
    };
    tokio::time::timeout(Duration::from_secs(2), connect)
        .await
        .context("probe connect timed out")?
}

/// The probe on a thread and runtime of its own, so that the floods' clients in this
/// process (megabytes of admin answers, thousands of connects) do not delay its timer or
/// its reads: the round trip it measures is the broker's.
pub(super) fn spawn_probe(
    addr: SocketAddr,
    shared: Arc<ProbeShared>,
) -> Result<std::thread::JoinHandle<()>> {
    let runtime = tokio::runtime::Builder::new_current_thread()
        .enable_all()
        .build()
        .context("the probe's runtime")?;
    Ok(std::thread::Builder::new()
        .name("abuse-probe".into())
        .spawn(move || runtime.block_on(run_probe(addr, shared)))?)
}

/// The well-behaved device: a QoS 1 publication every [`PROBE_EVERY`] on its own topic,
/// each timed until it comes back; reconnects (counted) if its connection drops.
pub(super) async fn run_probe(addr: SocketAddr, shared: Arc<ProbeShared>) {
    let mut stream: Option<TcpStream> = None;
    let mut buf = vec![0u8; 64 * 1024];
    let mut pending: Vec<u8> = Vec::new();
    // seq -> (sent at, the phase it counts for)
    let mut outstanding: HashMap<u64, (Instant, usize)> = HashMap::new();
    let mut tick = tokio::time::interval(PROBE_EVERY);
    tick.set_missed_tick_behavior(tokio::time::MissedTickBehavior::Skip);
    let mut seq = 0u64;
    let mut connected_once = false;
    while !shared.stop.load(Ordering::Relaxed) {
        tokio::select! {
            r = read_some(&mut stream, &mut buf) => match r {
                Ok(0) | Err(_) => stream = None,
                Ok(n) => {
                    pending.extend_from_slice(&buf[..n]);
                    let now = Instant::now();
                    let mut acks = Vec::new();
                    while let Some(Ok(total)) = loadtest::wire::frame_len(&pending) {
                        let header = pending[0];
                        let body = &pending[loadtest::wire::header_len(&pending)..total];
                        if let Some(payload) = mqtt::publish_payload(header, body) {
                            if let Some(id) = mqtt::packet_id(header, body) {
                                acks.extend(mqtt::puback_packet(id));
                            }
                            if let Ok(b) = <[u8; 8]>::try_from(payload) {
                                if let Some((sent, phase)) = outstanding.remove(&u64::from_be_bytes(b)) {
                                    if phase != usize::MAX {
                                        let us = now.duration_since(sent).as_micros() as u64;
                                        let mut f = shared.figures.lock().expect("probe figures");
                                        let _ = f[phase].latency_us.record(us.max(1));
                                    }
                                }
                            }
                        }
                        pending.drain(..total);
                    }
                    if !acks.is_empty() {
                        if let Some(s) = stream.as_mut() {
                            if s.write_all(&acks).await.is_err() {
                                stream = None;
                            }
                        }
                    }
                }
            },
            _ = tick.tick() => {
                let now = Instant::now();
                let phase = shared.phase.load(Ordering::Relaxed);
                // Overdue probes are lost.
                let overdue: Vec<u64> = outstanding
                    .iter()
                    .filter(|(_, (sent, _))| now.duration_since(*sent) > PROBE_LOST_AFTER)
                    .map(|(k, _)| *k)
                    .collect();
                for k in overdue {
                    if let Some((_, p)) = outstanding.remove(&k) {
                        if p != usize::MAX {
                            shared.figures.lock().expect("probe figures")[p].lost += 1;
                        }
                    }
                }
                if stream.is_none() {
                    pending.clear();
                    match probe_connect(addr).await {
                        Ok(s) => {
                            if connected_once && phase != usize::MAX {
                                shared.figures.lock().expect("probe figures")[phase].reconnects += 1;
                            }
                            connected_once = true;
                            stream = Some(s);
                        }
                        Err(_) => {
                            if phase != usize::MAX {
                                let mut f = shared.figures.lock().expect("probe figures");
                                f[phase].sent += 1;
                                f[phase].lost += 1;
                            }
                            continue;
                        }
                    }
                }
                seq += 1;
                let packet = mqtt::publish_qos1_packet(
                    PROBE_TOPIC,
                    (seq % u64::from(u16::MAX)) as u16 + 1,
                    false,
                    &seq.to_be_bytes(),
                );
                if phase != usize::MAX {
                    shared.figures.lock().expect("probe figures")[phase].sent += 1;
                }
                outstanding.insert(seq, (Instant::now(), phase));
                if let Some(s) = stream.as_mut() {
                    if s.write_all(&packet).await.is_err() {
                        stream = None;
                    }
                }
            }
        }
    }
    // Whatever is still outstanding at the end is lost.
    let mut f = shared.figures.lock().expect("probe figures");
    for (_, (_, p)) in outstanding {
        if p != usize::MAX {
            f[p].lost += 1;
        }
    }
}

/// One read from the probe's connection; never ready while it has none.
pub(super) async fn read_some(
    stream: &mut Option<TcpStream>,
    buf: &mut [u8],
) -> std::io::Result<usize> {
    use tokio::io::AsyncReadExt;
    match stream.as_mut() {
        Some(s) => s.read(buf).await,
        None => std::future::pending().await,
    }
}

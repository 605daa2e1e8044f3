//! The floods, one a phase: a registry of new devices, re-declarations, admin polling,
//! slow admin headers, invented port labels, retained messages. Each runs until its
//! phase's deadline and says how much it sent and how much was refused.

use std::net::SocketAddr;
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::Arc;
use std::time::{Duration, Instant};

use anyhow::{bail, Context as _, Result};
use loadtest::raw_client::{self as mqtt, PacketReader};
use loadtest::scrape;
use tokio::io::AsyncWriteExt;
use tokio::net::TcpStream;

use super::{Flood, WAIT};

/// Bounds of the floods.
pub(super) const MAX_DEVICES: u64 = 50_000;

pub(super) const MAX_RETAINED: u64 = 100_000;

pub(super) const REGISTRY_WORKERS: usize = 8;

/// Devices of phase 1 from one source address: fbbus's default `max_devices_per_identity`.
pub(super) const DEVICES_PER_SOURCE: u64 = 100;

/// The loopback address device `n` of phase 1 connects from: 127.0.0.2 on, a new one
/// every [`DEVICES_PER_SOURCE`] devices (at most 50,000 / 100 = 500 addresses).
pub(super) fn registry_source(n: u64) -> std::net::IpAddr {
    let k = 2 + n / DEVICES_PER_SOURCE;
    std::net::Ipv4Addr::new(127, 0, (k / 250) as u8, (k % 250) as u8).into()
}

pub(super) const POLLERS: usize = 6;

pub(super) const SLOW_HEADERS: usize = 500;

pub(super) const PORTS_PER_DECLARATION: usize = 100;

/// Fresh port names in the label flood, at most.
pub(super) const MAX_LABELS: u64 = 100_000;

/// A small valid interface: one FB with one INT output.
pub(super) const SMALL_INTERFACE: &str = r#"{"fbs":{"F":{"type":"ABUSE","data_out":{"V":"INT"}}}}"#;

// ---------------------------------------------------------------------------------------
// The floods
// ---------------------------------------------------------------------------------------
/// 1: distinct devices CONNECT, declare, DISCONNECT.
pub(super) async fn registry_flood(addr: SocketAddr, deadline: Instant) -> Result<Flood> {
    let next = Arc::new(AtomicU64::new(0));
    let done = Arc::new(AtomicU64::new(0));
    let refused = Arc::new(AtomicU64::new(0));
    let mut workers = Vec::new();
    for _ in 0..REGISTRY_WORKERS {
        let (next, done, refused) = (Arc::clone(&next), Arc::clone(&done), Arc::clone(&refused));
        workers.push(tokio::spawn(async move {
            while Instant::now() < deadline {
                let n = next.fetch_add(1, Ordering::Relaxed);
                if n >= MAX_DEVICES {
                    break;
                }
                let id = format!("abuse-dev-{n:05}");
                let from = registry_source(n);
                let s = match tokio::time::timeout(WAIT, mqtt::connect_from(addr, from, &id)).await
                {
                    Ok(Ok(s)) => s,
                    _ => {
                        refused.fetch_add(1, Ordering::Relaxed);
                        continue;
                    }
                };
                let mut reader = PacketReader::new(s);
                if declare(&mut reader, &id, SMALL_INTERFACE, 1).await.is_ok() {
                    done.fetch_add(1, Ordering::Relaxed);
                }
                let _ = reader.get_mut().write_all(&mqtt::DISCONNECT).await;
            }
        }));
    }
    for w in workers {
        w.await?;
    }
    let (done, refused) = (
        done.load(Ordering::Relaxed),
        refused.load(Ordering::Relaxed),
    );
    Ok(Flood {
        ops: done.to_string(),
        note: (refused > 0).then(|| format!("{refused} connects failed")),
    })
}

/// The device of phase 2.
pub(super) const REDECLARER: &str = "abuse-redeclare";

/// Declares [`REDECLARER`] once, so it is a known device.
pub(super) async fn register_redeclarer(addr: SocketAddr) -> Result<()> {
    let s = tokio::time::timeout(WAIT, mqtt::connect(addr, REDECLARER, None))
        .await
        .context("CONNECT timed out")??;
    let mut reader = PacketReader::new(s);
    declare(&mut reader, REDECLARER, SMALL_INTERFACE, 1)
        .await
        .context("the re-declaring device's first declaration")?;
    let _ = reader.get_mut().write_all(&mqtt::DISCONNECT).await;
    Ok(())
}

/// 2: one device declares again as soon as its previous declaration is acknowledged.
pub(super) async fn redeclaration_flood(addr: SocketAddr, deadline: Instant) -> Result<Flood> {
    let id = REDECLARER;
    let s = tokio::time::timeout(WAIT, mqtt::connect(addr, id, None))
        .await
        .context("CONNECT timed out")??;
    let mut reader = PacketReader::new(s);
    let mut done = 0u64;
    let mut pid = 0u16;
    while Instant::now() < deadline {
        pid = pid % u16::MAX + 1;
        declare(&mut reader, id, SMALL_INTERFACE, pid)
            .await
            .with_context(|| format!("declaration {} not acknowledged", done + 1))?;
        done += 1;
    }
    let _ = reader.get_mut().write_all(&mqtt::DISCONNECT).await;
    Ok(Flood {
        ops: done.to_string(),
        note: None,
    })
}

/// 3: admin loops listing every device, page after page.
pub(super) async fn admin_polling(admin: SocketAddr, deadline: Instant) -> Result<Flood> {
    let mut loops = Vec::new();
    for _ in 0..POLLERS {
        loops.push(tokio::spawn(async move {
            let (mut pages, mut failed, mut bytes) = (0u64, 0u64, 0usize);
            let mut after: Option<String> = None;
            while Instant::now() < deadline {
                let path = match &after {
                    Some(a) => format!("/api/v1/devices?after={}", percent_encode(a)),
                    None => "/api/v1/devices".to_string(),
                };
                match scrape::get(&format!("http://{admin}{path}"), Duration::from_secs(10)).await {
                    Ok(body) => {
                        pages += 1;
                        bytes = bytes.max(body.len());
                        after = next_page(&body);
                    }
                    Err(_) => {
                        failed += 1;
                        after = None;
                        tokio::time::sleep(Duration::from_millis(10)).await;
                    }
                }
            }
            (pages, failed, bytes)
        }));
    }
    let (mut pages, mut failed, mut largest) = (0, 0, 0);
    for l in loops {
        let (p, f, b) = l.await?;
        pages += p;
        failed += f;
        largest = largest.max(b);
    }
    let mut note = format!("largest page {:.0} KB", largest as f64 / 1024.0);
    if failed > 0 {
        note.push_str(&format!(", {failed} requests failed"));
    }
    Ok(Flood {
        ops: pages.to_string(),
        note: Some(note),
    })
}

/// 4: incomplete request headers held on the admin port while MQTT clients connect.
pub(super) async fn slow_headers(
    addr: SocketAddr,
    admin: SocketAddr,
    deadline: Instant,
) -> Result<Flood> {
    let mut opening = Vec::new();
    for _ in 0..SLOW_HEADERS {
        opening.push(tokio::spawn(async move {
            let mut s = tokio::time::timeout(WAIT, TcpStream::connect(admin))
                .await
                .ok()?
                .ok()?;
            s.write_all(b"GET /api/v1/devices HTTP/1.1\r\nHost: 127.0.0.1\r\nX-Slow: ")
                .await
                .ok()?;
            Some(s)
        }));
    }
    let mut held = Vec::new();
    for o in opening {
        if let Some(s) = o.await? {
            held.push(s);
        }
    }
    let opened = held.len();
    let (mut ok, mut tried, mut n) = (0u64, 0u64, 0u64);
    while Instant::now() < deadline {
        tried += 1;
        n += 1;
        let id = format!("abuse-conn-{n}");
        if let Ok(Ok(mut s)) = tokio::time::timeout(WAIT, mqtt::connect(addr, &id, None)).await {
            ok += 1;
            let _ = s.write_all(&mqtt::DISCONNECT).await;
        }
        tokio::time::sleep(Duration::from_millis(5)).await;
    }
    // Which the broker closed (or answered) while they were held.
    let mut closed = 0;
    let mut buf = [0u8; 256];
    for s in &held {
        match s.try_read(&mut buf) {
            Err(e) if e.kind() == std::io::ErrorKind::WouldBlock => {}
            _ => closed += 1,
        }
    }
    drop(held);
    Ok(Flood {
        ops: format!("{ok}/{tried}"),
        note: Some(format!(
            "{opened}/{SLOW_HEADERS} admin connections opened, {closed} closed or answered by the broker by the end"
        )),
    })
}

/// 5: fresh port names, one ill-typed value on each.
pub(super) async fn label_flood(addr: SocketAddr, deadline: Instant) -> Result<Flood> {
    let id = "abuse-labels";
    let s = tokio::time::timeout(WAIT, mqtt::connect(addr, id, None))
        .await
        .context("CONNECT timed out")??;
    let mut reader = PacketReader::new(s);
    let (mut published, mut declarations, mut generation) = (0u64, 0u64, 0u64);
    while Instant::now() < deadline && published < MAX_LABELS {
        let ports: Vec<String> = (0..PORTS_PER_DECLARATION)
            .map(|i| format!("P{generation}_{i}"))
            .collect();
        generation += 1;
        let data_out: Vec<String> = ports.iter().map(|p| format!("\"{p}\":\"INT\"")).collect();
        let interface = format!(
            r#"{{"fbs":{{"L":{{"type":"ABUSE","data_out":{{{}}}}}}}}}"#,
            data_out.join(",")
        );
        declare(&mut reader, id, &interface, 1)
            .await
            .context("declaration not acknowledged")?;
        declarations += 1;
        let mut batch = Vec::new();
        for (i, port) in ports.iter().enumerate() {
            batch.extend(mqtt::publish_qos1_packet(
                &format!("fb/{id}/L/{port}"),
                i as u16 + 2,
                false,
                b"\"x\"",
            ));
        }
        reader.get_mut().write_all(&batch).await?;
        await_pubacks(&mut reader, ports.len())
            .await
            .context("ill-typed publications not acknowledged")?;
        published += ports.len() as u64;
    }
    let _ = reader.get_mut().write_all(&mqtt::DISCONNECT).await;
    Ok(Flood {
        ops: published.to_string(),
        note: Some(format!("{declarations} declarations")),
    })
}

/// 6: retained messages on distinct topics.
pub(super) async fn retained_flood(addr: SocketAddr, deadline: Instant) -> Result<Flood> {
    let mut s = tokio::time::timeout(WAIT, mqtt::connect(addr, "abuse-retained", None))
        .await
        .context("CONNECT timed out")??;
    let mut sent = 0u64;
    while Instant::now() < deadline && sent < MAX_RETAINED {
        let mut batch = Vec::new();
        for _ in 0..100.min(MAX_RETAINED - sent) {
            batch.extend(loadtest::wire::publish(
                loadtest::wire::V311,
                format!("abuse/retained/{sent}").as_bytes(),
                0,
                true,
                false,
                0,
                &loadtest::wire::Props::new(),
                b"retained value 16",
            ));
            sent += 1;
        }
        tokio::time::timeout(WAIT, s.write_all(&batch))
            .await
            .context("the broker stopped reading")??;
    }
    let _ = s.write_all(&mqtt::DISCONNECT).await;
    Ok(Flood {
        ops: sent.to_string(),
        note: None,
    })
}

/// Publishes `interface` on `fbbus/declare/<id>` at QoS 1 and waits for its PUBACK.
pub(super) async fn declare(
    reader: &mut PacketReader,
    id: &str,
    interface: &str,
    pid: u16,
) -> Result<()> {
    let packet = mqtt::publish_qos1_packet(
        &format!("fbbus/declare/{id}"),
        pid,
        false,
        interface.as_bytes(),
    );
    reader.get_mut().write_all(&packet).await?;
    await_pubacks(reader, 1).await
}

/// Reads until `n` PUBACKs arrived (within [`WAIT`]); anything else is ignored.
pub(super) async fn await_pubacks(reader: &mut PacketReader, n: usize) -> Result<()> {
    let until = Instant::now() + WAIT;
    let mut acks = 0;
    while acks < n {
        let left = until
            .checked_duration_since(Instant::now())
            .context("no PUBACK in time")?;
        match tokio::time::timeout(left, reader.read_more()).await {
            Err(_) => bail!("{acks} of {n} PUBACKs within {WAIT:?}"),
            Ok(Ok(0)) => bail!("the broker closed the connection"),
            Ok(Err(e)) => return Err(e.into()),
            Ok(Ok(_)) => {
                while let Some((header, _)) = reader.next_packet()? {
                    if header >> 4 == 4 {
                        acks += 1;
                    }
                }
            }
        }
    }
    Ok(())
}

/// `next` of a device listing (`{"devices": [...], "line": ..., "next": ...}`): the
/// `after` of the next page, absent or null on the last. Only the answer's last key is
/// parsed, not the whole page: parsing megabytes of records in six loops would take the
/// harness's CPU, not the broker's.
pub(super) fn next_page(body: &str) -> Option<String> {
    let at = body.rfind("\"next\"")?;
    let rest = body[at + "\"next\"".len()..]
        .trim_start()
        .strip_prefix(':')?;
    let mut values = serde_json::Deserializer::from_str(rest).into_iter::<serde_json::Value>();
    let value = values.next()?.ok()?;
    // The top-level key: nothing but the object's end after its value.
    if rest[values.byte_offset()..].trim() != "}" {
        return None;
    }
    match value {
        serde_json::Value::String(s) if !s.is_empty() => Some(s),
        serde_json::Value::Number(n) => Some(n.to_string()),
        _ => None,
    }
}

pub(super) fn percent_encode(s: &str) -> String {
    s.bytes()
        .map(|b| match b {
            b'A'..=b'Z' | b'a'..=b'z' | b'0'..=b'9' | b'-' | b'_' | b'.' | b'~' => {
                (b as char).to_string()
            }
            _ => format!("%{b:02X}"),
        })
        .collect()
}

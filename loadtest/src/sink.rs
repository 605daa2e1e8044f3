//! The ceiling's sink: the least an MQTT broker can do, so the harness can measure
//! itself. It accepts MQTT 3.1.1 and 5 connections, grants every subscription (exact
//! topics only, at QoS 0), answers PINGREQ, acknowledges QoS 1 publications and forwards
//! each PUBLISH as QoS 0 to the connections subscribed to its exact topic. No sessions,
//! no retained messages, no wildcards, no authentication: not a broker, a yardstick.
//!
//! It runs in the harness's process on 127.0.0.1. When a broker's figures come close to
//! the sink's, the load generator, not the broker, is the limit.

use std::collections::HashMap;
use std::io;
use std::net::SocketAddr;
use std::sync::{Arc, Mutex};

use tokio::io::{AsyncReadExt, AsyncWriteExt, BufReader};
use tokio::net::{TcpListener, TcpStream};
use tokio::sync::mpsc;
use tokio::task::JoinHandle;

/// Exact topic -> (subscriber's writer, whether it speaks MQTT 5).
type Subscribers = Arc<Mutex<HashMap<Vec<u8>, Vec<(mpsc::UnboundedSender<Arc<Vec<u8>>>, bool)>>>>;

/// A running sink; stops when dropped.
pub struct Sink {
    pub addr: SocketAddr,
    task: JoinHandle<()>,
}

impl Drop for Sink {
    fn drop(&mut self) {
        self.task.abort();
    }
}

impl Sink {
    pub async fn start() -> io::Result<Sink> {
        let listener = TcpListener::bind("127.0.0.1:0").await?;
        let addr = listener.local_addr()?;
        let subscribers: Subscribers = Arc::default();
        let task = tokio::spawn(async move {
            let mut connections = Vec::new();
            while let Ok((stream, _)) = listener.accept().await {
                let _ = stream.set_nodelay(true);
                connections.push(AbortOnDrop(tokio::spawn(serve(
                    stream,
                    subscribers.clone(),
                ))));
            }
        });
        Ok(Sink { addr, task })
    }
}

struct AbortOnDrop(JoinHandle<io::Result<()>>);

impl Drop for AbortOnDrop {
    fn drop(&mut self) {
        self.0.abort();
    }
}

/// Reads one packet: (first header byte, body).
async fn read_packet(r: &mut (impl AsyncReadExt + Unpin)) -> io::Result<(u8, Vec<u8>)> {
    let header = r.read_u8().await?;
    let mut len = 0usize;
    for shift in (0..28).step_by(7) {
        let b = r.read_u8().await?;
        len |= ((b & 0x7f) as usize) << shift;
        if b & 0x80 == 0 {
            let mut body = vec![0; len];
            r.read_exact(&mut body).await?;
            return Ok((header, body));
        }
    }
    Err(io::Error::new(
        io::ErrorKind::InvalidData,
        "bad remaining length",
    ))
}

fn packet(header: u8, body: &[u8]) -> Vec<u8> {
    let mut out = vec![header];
    let mut len = body.len();
    loop {
        let mut b = (len % 128) as u8;
        len /= 128;
        if len > 0 {
            b |= 0x80;
        }
        out.push(b);
        if len == 0 {
            break;
        }
    }
    out.extend_from_slice(body);
    out
}

/// `body[from..to]`, or an error that ends the connection: a malformed packet must not
/// panic the sink.
fn part(body: &[u8], from: usize, to: usize) -> io::Result<&[u8]> {
    body.get(from..to)
        .ok_or_else(|| io::Error::new(io::ErrorKind::InvalidData, "packet shorter than its fields"))
}

/// The big-endian u16 at `at`.
fn u16_at(body: &[u8], at: usize) -> io::Result<usize> {
    let b = part(body, at, at + 2)?;
    Ok(u16::from_be_bytes([b[0], b[1]]) as usize)
}

/// Length of an MQTT 5 property block at `at` (its variable-byte length + the block).
fn properties_len(body: &[u8], at: usize) -> usize {
    let mut len = 0usize;
    for (i, shift) in (0..28).step_by(7).enumerate() {
        let Some(&b) = body.get(at + i) else { return i };
        len |= ((b & 0x7f) as usize) << shift;
        if b & 0x80 == 0 {
            return i + 1 + len;
        }
    }
    0
}

async fn serve(stream: TcpStream, subscribers: Subscribers) -> io::Result<()> {
    let (rd, mut wr) = stream.into_split();
    // Buffered both ways: one read and one write system call per batch of packets, not
    // per packet (let alone per byte), as a broker would.
    let mut rd = BufReader::with_capacity(64 * 1024, rd);
    let (tx, mut rx) = mpsc::unbounded_channel::<Arc<Vec<u8>>>();
    let writer = AbortOnDrop(tokio::spawn(async move {
        let mut out = Vec::with_capacity(64 * 1024);
        while let Some(bytes) = rx.recv().await {
            out.extend_from_slice(&bytes);
            while out.len() < 64 * 1024 {
                match rx.try_recv() {
                    Ok(more) => out.extend_from_slice(&more),
                    Err(_) => break,
                }
            }
            wr.write_all(&out).await?;
            out.clear();
        }
        Ok(())
    }));
    let mut v5 = false;
    loop {
        let (header, body) = read_packet(&mut rd).await?;
        match header >> 4 {
            1 => {
                // CONNECT: protocol level after the protocol name "MQTT".
                v5 = body.get(6) == Some(&5);
                let ack = if v5 { vec![0, 0, 0] } else { vec![0, 0] };
                let _ = tx.send(Arc::new(packet(0x20, &ack)));
            }
            3 => {
                let qos = (header >> 1) & 3;
                let topic_len = u16_at(&body, 0)?;
                let topic = part(&body, 2, 2 + topic_len)?.to_vec();
                let mut at = 2 + topic_len;
                if qos > 0 {
                    let id = part(&body, at, at + 2)?.to_vec();
                    at += 2;
                    let ack = if qos == 1 { 0x40 } else { 0x50 };
                    let _ = tx.send(Arc::new(packet(ack, &id)));
                }
                let props = if v5 { properties_len(&body, at) } else { 0 };
                let payload = part(&body, at + props, body.len())?;
                let mut out_body = Vec::with_capacity(2 + topic_len + 1 + payload.len());
                out_body.extend_from_slice(part(&body, 0, 2 + topic_len)?);
                let forwarded_v5 = packet(0x30, &[&out_body[..], &[0], payload].concat());
                out_body.extend_from_slice(payload);
                let forwarded = Arc::new(packet(0x30, &out_body));
                let forwarded_v5 = Arc::new(forwarded_v5);
                let subs = subscribers.lock().unwrap_or_else(|p| p.into_inner());
                for (s, s_v5) in subs.get(&topic).into_iter().flatten() {
                    // An MQTT 5 PUBLISH carries a (here empty) property block.
                    let _ = s.send(if *s_v5 {
                        forwarded_v5.clone()
                    } else {
                        forwarded.clone()
                    });
                }
            }
            6 => {
                // PUBREL -> PUBCOMP
                let _ = tx.send(Arc::new(packet(0x70, part(&body, 0, 2)?)));
            }
            8 => {
                let id = part(&body, 0, 2)?.to_vec();
                let mut at = 2;
                if v5 {
                    at += properties_len(&body, at);
                }
                let mut granted = Vec::new();
                while at + 2 <= body.len() {
                    let len = u16_at(&body, at)?;
                    let filter = part(&body, at + 2, at + 2 + len)?.to_vec();
                    at += 2 + len + 1;
                    subscribers
                        .lock()
                        .unwrap_or_else(|p| p.into_inner())
                        .entry(filter)
                        .or_default()
                        .push((tx.clone(), v5));
                    granted.push(0u8);
                }
                let mut ack = id.to_vec();
                if v5 {
                    ack.push(0);
                }
                ack.extend(granted);
                let _ = tx.send(Arc::new(packet(0x90, &ack)));
            }
            12 => {
                let _ = tx.send(Arc::new(packet(0xD0, &[])));
            }
            14 => break,
            _ => {}
        }
    }
    drop(writer);
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A malformed packet ends its own connection, not the sink.
    #[tokio::test]
    async fn a_malformed_packet_closes_only_its_connection() {
        let sink = Sink::start().await.unwrap();
        let connect = packet(0x10, b"\x00\x04MQTT\x04\x02\x00\x3c\x00\x01x");
        let mut bad = TcpStream::connect(sink.addr).await.unwrap();
        bad.write_all(&connect).await.unwrap();
        let mut ack = [0u8; 4];
        bad.read_exact(&mut ack).await.unwrap();
        // A PUBLISH whose topic length points past its end.
        bad.write_all(&packet(0x30, &[0x00, 0x09, b'a']))
            .await
            .unwrap();
        let mut rest = Vec::new();
        let closed = tokio::time::timeout(
            std::time::Duration::from_secs(5),
            bad.read_to_end(&mut rest),
        )
        .await;
        assert!(matches!(closed, Ok(Ok(0))), "{closed:?}");

        let mut good = TcpStream::connect(sink.addr).await.unwrap();
        good.write_all(&connect).await.unwrap();
        good.read_exact(&mut ack).await.unwrap();
        assert_eq!(ack, [0x20, 2, 0, 0]);
    }
}

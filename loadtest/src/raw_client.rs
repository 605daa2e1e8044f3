//! A minimal MQTT 3.1.1 client on a plain tokio `TcpStream`, for the rates a client
//! library does not reach: `compare`'s bursts of 200,000 messages into one subscriber,
//! and readiness probes of the brokers it starts.
//!
//! The packets are [`wire`]'s (the campaigns' byte-level encoder); this module only
//! adds the waits (CONNACK, SUBACK) and a reader that hands out whole packets from one
//! reusable buffer. QoS 0, and for `compare persistence` the pieces of QoS 1 (persistent
//! sessions, PUBLISH with a packet id, PUBACK); nothing here retries or reconnects: a drop
//! is a result.

use std::io;
use std::net::SocketAddr;
use std::sync::atomic::{AtomicU64, Ordering};

use tokio::io::{AsyncReadExt, AsyncWriteExt};
use tokio::net::TcpStream;

use crate::wire::{self, Props};
use crate::Error;

/// Keep-alive every client announces (rumqttd 0.20 refuses 0).
pub const KEEP_ALIVE_SECS: u16 = 60;

/// CONNECT, MQTT 3.1.1, clean session, optional username and password.
pub fn connect_packet(client_id: &str, credentials: Option<(&str, &str)>) -> Vec<u8> {
    let mut c = wire::Connect::new(wire::V311, client_id.as_bytes());
    c.keep_alive = KEEP_ALIVE_SECS;
    if let Some((user, password)) = credentials {
        c.username = Some(user.as_bytes().to_vec());
        c.password = Some(password.as_bytes().to_vec());
    }
    c.encode()
}

/// CONNECT, MQTT 3.1.1, anonymous, with clean session `clean` (false: a persistent
/// session, kept by the broker after the connection ends).
pub fn connect_session_packet(client_id: &str, clean: bool) -> Vec<u8> {
    let mut c = wire::Connect::new(wire::V311, client_id.as_bytes());
    c.keep_alive = KEEP_ALIVE_SECS;
    c.clean = clean;
    c.encode()
}

/// SUBSCRIBE to one filter at QoS 0.
pub fn subscribe_packet(packet_id: u16, filter: &str) -> Vec<u8> {
    subscribe_qos_packet(packet_id, filter, 0)
}

/// SUBSCRIBE to one filter at `qos`.
pub fn subscribe_qos_packet(packet_id: u16, filter: &str, qos: u8) -> Vec<u8> {
    wire::subscribe(
        wire::V311,
        packet_id,
        &Props::new(),
        &[(filter.as_bytes().to_vec(), qos)],
    )
}

/// PUBLISH at QoS 1 with packet id `pid` (not 0), optionally retained; the payload is
/// the packet's tail, as in [`publish_packet`].
pub fn publish_qos1_packet(topic: &str, pid: u16, retain: bool, payload: &[u8]) -> Vec<u8> {
    wire::publish(
        wire::V311,
        topic.as_bytes(),
        1,
        retain,
        false,
        pid,
        &Props::new(),
        payload,
    )
}

/// PUBACK for packet id `pid`.
pub fn puback_packet(pid: u16) -> [u8; 4] {
    let [hi, lo] = pid.to_be_bytes();
    [0x40, 0x02, hi, lo]
}

/// The packet id of a QoS 1/2 PUBLISH or of a PUBACK; None for anything else.
pub fn packet_id(header: u8, body: &[u8]) -> Option<u16> {
    match header >> 4 {
        3 if (header >> 1) & 3 > 0 => {
            let topic_len = u16::from_be_bytes([*body.first()?, *body.get(1)?]) as usize;
            let at = 2 + topic_len;
            Some(u16::from_be_bytes([*body.get(at)?, *body.get(at + 1)?]))
        }
        4 => Some(u16::from_be_bytes([*body.first()?, *body.get(1)?])),
        _ => None,
    }
}

/// PUBLISH at QoS 0, no retain. The payload is the packet's tail, so callers can rewrite
/// `packet[packet.len() - payload.len()..]` in place (timestamps).
pub fn publish_packet(topic: &str, payload: &[u8]) -> Vec<u8> {
    wire::publish(
        wire::V311,
        topic.as_bytes(),
        0,
        false,
        false,
        0,
        &Props::new(),
        payload,
    )
}

/// DISCONNECT (MQTT 3.1.1).
pub const DISCONNECT: [u8; 2] = [0xE0, 0x00];

/// Opens a TCP connection (nodelay), sends CONNECT and waits for a successful CONNACK.
/// The caller bounds the time with `tokio::time::timeout`.
pub async fn connect(
    addr: SocketAddr,
    client_id: &str,
    credentials: Option<(&str, &str)>,
) -> Result<TcpStream, Error> {
    let packet = connect_packet(client_id, credentials);
    Ok(connect_with(addr, client_id, &packet).await?.0)
}

/// Like [`connect`], anonymous, from the local address `source` (one of the loopback
/// addresses 127.0.0.0/8 when the broker is on 127.0.0.1: a broker that limits per
/// address then sees many hosts).
pub async fn connect_from(
    addr: SocketAddr,
    source: std::net::IpAddr,
    client_id: &str,
) -> Result<TcpStream, Error> {
    let packet = connect_packet(client_id, None);
    Ok(connect_on(addr, Some(source), client_id, &packet).await?.0)
}

/// Like [`connect`], anonymous, with clean session `clean`; also returns the CONNACK's
/// session-present flag (a persistent session the broker kept).
pub async fn connect_session(
    addr: SocketAddr,
    client_id: &str,
    clean: bool,
) -> Result<(TcpStream, bool), Error> {
    connect_with(addr, client_id, &connect_session_packet(client_id, clean)).await
}

async fn connect_with(
    addr: SocketAddr,
    client_id: &str,
    packet: &[u8],
) -> Result<(TcpStream, bool), Error> {
    connect_on(addr, None, client_id, packet).await
}

async fn connect_on(
    addr: SocketAddr,
    source: Option<std::net::IpAddr>,
    client_id: &str,
    packet: &[u8],
) -> Result<(TcpStream, bool), Error> {
    let connect_error = |reason: String| Error::Connect {
        id: client_id.to_owned(),
        address: addr.to_string(),
        reason,
    };
    let stream = match source {
        None => TcpStream::connect(addr).await,
        Some(source) => {
            let socket = if source.is_ipv4() {
                tokio::net::TcpSocket::new_v4()?
            } else {
                tokio::net::TcpSocket::new_v6()?
            };
            socket.bind(SocketAddr::new(source, 0))?;
            socket.connect(addr).await
        }
    };
    let mut stream = stream.map_err(|e| connect_error(e.to_string()))?;
    stream.set_nodelay(true)?;
    stream
        .write_all(packet)
        .await
        .map_err(|e| connect_error(format!("sending CONNECT: {e}")))?;
    let mut ack = [0u8; 4];
    stream
        .read_exact(&mut ack)
        .await
        .map_err(|e| connect_error(format!("waiting for CONNACK: {e}")))?;
    if ack[0] != 0x20 || ack[1] != 2 {
        return Err(connect_error(format!(
            "expected CONNACK, got {:02x} {:02x}",
            ack[0], ack[1]
        )));
    }
    if ack[3] != 0 {
        return Err(Error::Refused {
            id: client_id.to_owned(),
            address: addr.to_string(),
            reason: format!("CONNACK return code {}", ack[3]),
        });
    }
    Ok((stream, ack[2] & 1 == 1))
}

/// Subscribes to `filter` at QoS 0 and waits for a SUBACK that grants it.
pub async fn subscribe(stream: &mut TcpStream, filter: &str) -> Result<(), Error> {
    subscribe_qos(stream, filter, 0).await.map(|_| ())
}

/// Subscribes to `filter` at `qos` and waits for a SUBACK that grants it; returns the
/// QoS granted.
pub async fn subscribe_qos(stream: &mut TcpStream, filter: &str, qos: u8) -> Result<u8, Error> {
    stream
        .write_all(&subscribe_qos_packet(1, filter, qos))
        .await?;
    let mut ack = [0u8; 5];
    stream.read_exact(&mut ack).await?;
    let refused = |reason: String| Error::Refused {
        id: "subscriber".into(),
        address: stream
            .peer_addr()
            .map_or_else(|_| "?".into(), |a| a.to_string()),
        reason,
    };
    if ack[0] != 0x90 || ack[1] != 3 || ack[2..4] != [0, 1] {
        return Err(refused(format!(
            "expected SUBACK for packet 1, got {ack:02x?}"
        )));
    }
    if ack[4] == 0x80 {
        return Err(refused(format!(
            "SUBACK refused the subscription to {filter} (check the broker's access rules)"
        )));
    }
    Ok(ack[4])
}

/// Reads whole MQTT packets from a stream with one reusable buffer: one `read` syscall per
/// `read_more`, then `next_packet` hands out every complete packet in it without copying.
pub struct PacketReader {
    stream: TcpStream,
    buf: Vec<u8>,
    start: usize,
    end: usize,
}

impl PacketReader {
    pub fn new(stream: TcpStream) -> PacketReader {
        PacketReader {
            stream,
            buf: vec![0; 256 * 1024],
            start: 0,
            end: 0,
        }
    }

    /// The connection back; whatever was read and not handed out is dropped.
    pub fn into_inner(self) -> TcpStream {
        self.stream
    }

    /// The connection, to write on it between reads (acknowledgements).
    pub fn get_mut(&mut self) -> &mut TcpStream {
        &mut self.stream
    }

    /// One read from the socket; 0 means the peer closed it. Cancel-safe.
    pub async fn read_more(&mut self) -> io::Result<usize> {
        if self.start == self.end {
            self.start = 0;
            self.end = 0;
        } else if self.start > 0 && self.buf.len() - self.end < 64 * 1024 {
            self.buf.copy_within(self.start..self.end, 0);
            self.end -= self.start;
            self.start = 0;
        }
        if self.end == self.buf.len() {
            let doubled = self.buf.len() * 2;
            self.buf.resize(doubled, 0);
        }
        let n = self.stream.read(&mut self.buf[self.end..]).await?;
        self.end += n;
        Ok(n)
    }

    /// The next complete packet already read: (first byte of the fixed header, body).
    pub fn next_packet(&mut self) -> io::Result<Option<(u8, &[u8])>> {
        let avail = &self.buf[self.start..self.end];
        let total = match wire::frame_len(avail) {
            None => return Ok(None),
            Some(Err(())) => {
                return Err(io::Error::new(
                    io::ErrorKind::InvalidData,
                    "malformed remaining length",
                ))
            }
            Some(Ok(total)) => total,
        };
        let header = avail[0];
        let body_start = self.start + wire::header_len(avail);
        self.start += total;
        Ok(Some((header, &self.buf[body_start..self.start])))
    }
}

/// The payload of a PUBLISH packet, or None for any other packet.
pub fn publish_payload(header: u8, body: &[u8]) -> Option<&[u8]> {
    if header >> 4 != 3 || body.len() < 2 {
        return None;
    }
    let qos = (header >> 1) & 3;
    let topic_len = u16::from_be_bytes([body[0], body[1]]) as usize;
    let start = 2 + topic_len + if qos > 0 { 2 } else { 0 };
    body.get(start..)
}

/// Sends `count` QoS 1 PUBLISHes, the k-th made by `make(k, packet id, buffer)`, with at
/// most `window` unacknowledged, and reads the PUBACKs; returns when every one is
/// acknowledged. `sent` counts what was written. (`compare persistence`'s bursts and
/// retained store, `compare`'s QoS 1 fan-in.)
pub async fn publish_acked(
    conn: &mut PacketReader,
    count: usize,
    window: usize,
    sent: &AtomicU64,
    mut make: impl FnMut(usize, u16, &mut Vec<u8>),
) -> io::Result<()> {
    let window = window.clamp(1, 65_535);
    let (mut next, mut acked) = (0usize, 0usize);
    let mut buf = Vec::with_capacity(window * 64);
    while acked < count {
        let before = next;
        while next < count && next - acked < window {
            make(next, (next % 65_535) as u16 + 1, &mut buf);
            next += 1;
        }
        if !buf.is_empty() {
            conn.get_mut().write_all(&buf).await?;
            buf.clear();
            sent.fetch_add((next - before) as u64, Ordering::Relaxed);
        }
        if conn.read_more().await? == 0 {
            return Err(io::Error::new(
                io::ErrorKind::UnexpectedEof,
                format!("the broker closed the connection after {acked} PUBACKs of {count}"),
            ));
        }
        while let Some((header, _)) = conn.next_packet()? {
            if header >> 4 == 4 {
                acked += 1;
            }
        }
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn packets_round_trip_through_the_parser_shapes() {
        let p = publish_packet("bench/t", &[7u8; 32]);
        assert_eq!(p[0], 0x30);
        assert_eq!(p[1] as usize, 2 + 7 + 32);
        assert_eq!(publish_payload(p[0], &p[2..]), Some(&[7u8; 32][..]));
        let c = connect_packet("id", Some(("u", "p")));
        assert_eq!(c[0], 0x10);
        assert_eq!(c[1] as usize, c.len() - 2);
        assert_eq!(c[9], 0xC2, "username, password, clean session");
        assert_eq!(
            u16::from_be_bytes([c[10], c[11]]),
            KEEP_ALIVE_SECS,
            "keep-alive"
        );
        assert_eq!(wire::varint(321), vec![0xC1, 0x02]);
        let q = publish_qos1_packet("bench/t", 513, true, &[7u8; 32]);
        assert_eq!(q[0], 0x33, "QoS 1, retain");
        assert_eq!(packet_id(q[0], &q[2..]), Some(513));
        assert_eq!(publish_payload(q[0], &q[2..]), Some(&[7u8; 32][..]));
        let a = puback_packet(513);
        assert_eq!(packet_id(a[0], &a[2..]), Some(513));
        assert_eq!(packet_id(p[0], &p[2..]), None, "QoS 0 has no packet id");
        assert_eq!(
            connect_session_packet("id", false)[9],
            0x00,
            "no clean session"
        );
    }
}

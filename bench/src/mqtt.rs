//! A minimal MQTT 3.1.1 client on a tokio `TcpStream`: CONNECT/CONNACK, SUBSCRIBE/SUBACK at
//! QoS 0, PUBLISH at QoS 0 and a packet reader for the receive side. Just enough to be a cheap
//! and precise load generator; nothing here retries or reconnects.

use std::io;
use std::net::SocketAddr;

use anyhow::{bail, Context as _, Result};
use tokio::io::{AsyncReadExt, AsyncWriteExt};
use tokio::net::TcpStream;

/// Keep-alive every bench client announces (rumqttd 0.20 refuses 0).
pub const KEEP_ALIVE_SECS: u16 = 60;

fn put_remaining_length(out: &mut Vec<u8>, mut len: usize) {
    loop {
        let mut byte = (len % 128) as u8;
        len /= 128;
        if len > 0 {
            byte |= 0x80;
        }
        out.push(byte);
        if len == 0 {
            break;
        }
    }
}

fn put_string(out: &mut Vec<u8>, s: &[u8]) {
    out.extend_from_slice(&(s.len() as u16).to_be_bytes());
    out.extend_from_slice(s);
}

/// CONNECT, protocol level 4 (3.1.1), clean session, optional username and password.
pub fn connect_packet(client_id: &str, credentials: Option<(&str, &str)>) -> Vec<u8> {
    let mut body = Vec::with_capacity(64);
    put_string(&mut body, b"MQTT");
    body.push(4);
    body.push(if credentials.is_some() { 0xC2 } else { 0x02 });
    body.extend_from_slice(&KEEP_ALIVE_SECS.to_be_bytes());
    put_string(&mut body, client_id.as_bytes());
    if let Some((user, password)) = credentials {
        put_string(&mut body, user.as_bytes());
        put_string(&mut body, password.as_bytes());
    }
    let mut packet = vec![0x10];
    put_remaining_length(&mut packet, body.len());
    packet.extend_from_slice(&body);
    packet
}

/// SUBSCRIBE to one filter at QoS 0.
pub fn subscribe_packet(packet_id: u16, filter: &str) -> Vec<u8> {
    let mut body = Vec::with_capacity(filter.len() + 5);
    body.extend_from_slice(&packet_id.to_be_bytes());
    put_string(&mut body, filter.as_bytes());
    body.push(0);
    let mut packet = vec![0x82];
    put_remaining_length(&mut packet, body.len());
    packet.extend_from_slice(&body);
    packet
}

/// PUBLISH at QoS 0, no retain. The payload is the packet's tail, so callers can rewrite
/// `packet[packet.len() - payload.len()..]` in place (timestamps).
pub fn publish_packet(topic: &str, payload: &[u8]) -> Vec<u8> {
    let mut packet = vec![0x30];
    put_remaining_length(&mut packet, 2 + topic.len() + payload.len());
    put_string(&mut packet, topic.as_bytes());
    packet.extend_from_slice(payload);
    packet
}

pub const DISCONNECT: [u8; 2] = [0xE0, 0x00];

/// Opens a TCP connection (nodelay), sends CONNECT and waits for a successful CONNACK.
/// The caller bounds the time with `tokio::time::timeout`.
pub async fn connect(
    addr: SocketAddr,
    client_id: &str,
    credentials: Option<(&str, &str)>,
) -> Result<TcpStream> {
    let mut stream = TcpStream::connect(addr)
        .await
        .with_context(|| format!("TCP connect to {addr}"))?;
    stream.set_nodelay(true)?;
    stream
        .write_all(&connect_packet(client_id, credentials))
        .await
        .context("sending CONNECT")?;
    let mut ack = [0u8; 4];
    stream
        .read_exact(&mut ack)
        .await
        .context("waiting for CONNACK")?;
    if ack[0] != 0x20 || ack[1] != 2 {
        bail!("expected CONNACK, got {:02x} {:02x}", ack[0], ack[1]);
    }
    if ack[3] != 0 {
        bail!("CONNACK refused the connection: return code {}", ack[3]);
    }
    Ok(stream)
}

/// Subscribes to `filter` at QoS 0 and waits for a SUBACK that grants it.
pub async fn subscribe(stream: &mut TcpStream, filter: &str) -> Result<()> {
    stream.write_all(&subscribe_packet(1, filter)).await?;
    let mut ack = [0u8; 5];
    stream
        .read_exact(&mut ack)
        .await
        .context("waiting for SUBACK")?;
    if ack[0] != 0x90 || ack[1] != 3 || ack[2..4] != [0, 1] {
        bail!("expected SUBACK for packet 1, got {ack:02x?}");
    }
    if ack[4] == 0x80 {
        bail!("SUBACK refused the subscription to {filter}");
    }
    Ok(())
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
        if avail.len() < 2 {
            return Ok(None);
        }
        let mut len = 0usize;
        let mut multiplier = 1usize;
        let mut i = 1;
        loop {
            let Some(&byte) = avail.get(i) else {
                return Ok(None);
            };
            len += (byte & 0x7f) as usize * multiplier;
            i += 1;
            if byte & 0x80 == 0 {
                break;
            }
            multiplier *= 128;
            if i > 4 {
                return Err(io::Error::new(
                    io::ErrorKind::InvalidData,
                    "malformed remaining length",
                ));
            }
        }
        if avail.len() < i + len {
            return Ok(None);
        }
        let header = avail[0];
        let body_start = self.start + i;
        self.start = body_start + len;
        Ok(Some((header, &self.buf[body_start..body_start + len])))
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
        let mut long = Vec::new();
        put_remaining_length(&mut long, 321);
        assert_eq!(long, vec![0xC1, 0x02]);
    }
}

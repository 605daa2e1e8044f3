//! The client's socket with its read and write buffers: bytes in, packets out, and back.
//!
//! Reading is cancel-safe (bytes read stay in the buffer), so the connection loop can
//! select on it. Buffers start small, because most of a line's devices are idle most of
//! the time, grow with the traffic, and are let go of once they are empty again: a device
//! that sent one burst must not keep a burst-sized buffer for the rest of the shift.
//!
//! Writing is cancel-safe too ([`Io::poll_write_out`] removes from the buffer what the
//! socket took), so the session can wait for a slow socket and for its other deadlines at
//! once (`session::write`). Every write has a deadline: [`Io::flush`] gives up after the
//! write timeout (`broker.slow_consumer_timeout_ms`); a peer that takes nothing must not
//! hold a task, its buffers and its will forever.

use std::future::poll_fn;
use std::io::ErrorKind;
use std::net::SocketAddr;
use std::pin::Pin;
use std::task::{Context, Poll};
use std::time::Duration;

use bytes::BytesMut;
use rumqttd::protocol::{ConnectReturnCode, Packet};
use tokio::io::{AsyncRead, AsyncReadExt, AsyncWrite};

use crate::metrics::Metrics;
use crate::wire::codec::{decode_frame, Codec, ReadError, Version};
use crate::wire::frame::{self, FrameError};

/// A byte stream a client connected over: TCP or TLS over TCP.
pub trait Stream: AsyncRead + AsyncWrite + Send + Unpin {}
impl<T: AsyncRead + AsyncWrite + Send + Unpin> Stream for T {}

/// A CONNECT that could not be read, with the CONNACK to answer it (if any).
pub struct Refusal {
    pub reason: &'static str,
    pub detail: String,
    pub connack: Option<ConnectReturnCode>,
}

impl Refusal {
    pub fn report(&self, metrics: &Metrics, peer: SocketAddr) {
        metrics.refused(self.reason);
        match self.reason {
            "malformed" => metrics.malformed_packets.inc(),
            "oversized" => metrics.oversized_packets.inc(),
            _ => {}
        }
        tracing::info!(%peer, reason = self.reason, detail = %self.detail, "CONNECT refused");
    }
}

/// Why the first bytes of a connection are not an MQTT CONNECT: (reason, log detail). An
/// HTTP request is most likely a WebSocket client at a plain MQTT port (Node-RED with
/// `ws://host:1883/mqtt`), a TLS hello an `mqtts://` client at a port without TLS.
fn not_mqtt(first: &[u8]) -> (&'static str, &'static str) {
    if first.starts_with(b"GET ") || b"GET ".starts_with(first) {
        (
            "websocket_on_mqtt",
            "an HTTP request (a WebSocket handshake?) reached a plain MQTT listener: \
             MQTT over WebSockets needs a [[listener]] with kind = \"ws\"",
        )
    } else if first[0] == 0x16 {
        (
            "tls_on_plain",
            "a TLS hello reached a listener without TLS: connect without TLS, or to a \
             listener with [listener.tls]",
        )
    } else {
        ("malformed", "first packet is not an MQTT CONNECT")
    }
}

/// Free room below which a read first reserves `BUSY_READ_RESERVE` more.
const MIN_READ_ROOM: usize = 256;

/// Room a read gets once a packet is underway: a batch of small packets per system call.
const BUSY_READ_RESERVE: usize = 4 * 1024;

/// A write buffer larger than this is freed after it was written out, not kept.
const KEPT_WRITE_CAPACITY: usize = 1024;

/// The deadline of a write when the broker's configuration did not give one.
pub const DEFAULT_WRITE_TIMEOUT: Duration = Duration::from_secs(10);

/// The socket with its read and write buffers.
pub struct Io {
    pub stream: Box<dyn Stream>,
    pub read: BytesMut,
    pub write: BytesMut,
    pub codec: Codec,
    max_packet: usize,
    /// How long [`Io::flush`] waits for the socket to take the write buffer.
    pub write_timeout: Duration,
    /// Bytes at the start of `write` the socket already took (a write that waits): kept
    /// as an offset, not advanced past, so the buffer's allocation is still known when it
    /// is empty again (a burst-sized one is let go of).
    written: usize,
}

impl Io {
    pub fn new(stream: Box<dyn Stream>, max_packet: usize) -> Io {
        Io {
            stream,
            // Empty to start: an idle device should cost little; busy ones grow on demand.
            read: BytesMut::new(),
            write: BytesMut::new(),
            codec: Codec(Version::V311),
            max_packet,
            write_timeout: DEFAULT_WRITE_TIMEOUT,
            written: 0,
        }
    }

    /// The same, with writes given up after `write_timeout`.
    pub fn with_write_timeout(mut self, write_timeout: Duration) -> Io {
        self.write_timeout = write_timeout;
        self
    }

    /// Reads more bytes from the socket. Cancel-safe: bytes read stay in the buffer.
    pub async fn fill(&mut self) -> Result<usize, ReadError> {
        if self.read.is_empty() {
            // Everything read was decoded: let go of the last batch's buffer (packets that
            // still point into it keep it alive only as long as they live). Reading into an
            // empty `BytesMut` reserves 64 bytes: enough for a device's usual packet, and
            // the next read of a longer one reserves more.
            if self.read.capacity() > 0 {
                self.read = BytesMut::new();
            }
        } else if self.read.capacity() - self.read.len() < MIN_READ_ROOM {
            self.read.reserve(BUSY_READ_RESERVE);
        }
        match self.stream.read_buf(&mut self.read).await {
            Ok(0) | Err(_) => Err(ReadError::Closed),
            Ok(n) => Ok(n),
        }
    }

    /// The header of the next buffered packet, if it is complete.
    pub fn next_frame(&self) -> Result<Option<frame::FixedHeader>, ReadError> {
        match frame::check(&self.read, self.max_packet) {
            Ok(header) => Ok(Some(header)),
            Err(FrameError::Incomplete(_)) => Ok(None),
            Err(FrameError::MalformedLength) => Err(ReadError::Malformed(
                "remaining length longer than 4 bytes".into(),
            )),
            Err(FrameError::TooLarge { size, max }) => Err(ReadError::Oversized { size, max }),
        }
    }

    /// Decodes the buffered packet whose header was just checked.
    ///
    /// A PUBLISH is decoded from a copy of its own frame. Its topic and payload are
    /// slices of the buffer it is decoded from, and the router keeps them for as long as
    /// a commit log holds the message: decoded from the read buffer, a 100-byte message
    /// kept the whole 4 KiB read batch alive, ~4.5 KiB per stored message (found by
    /// `fbbus-loadtest mutate`; the router's log limits count topic and payload only).
    pub fn decode(&mut self, header: &frame::FixedHeader) -> Result<Packet, ReadError> {
        const PUBLISH: u8 = 3;
        if header.packet_type() == PUBLISH {
            let Some(frame) = self.read.get(..header.frame_len()) else {
                return Err(ReadError::Malformed("incomplete frame".into()));
            };
            let mut own = BytesMut::from(frame);
            let _ = self.read.split_to(header.frame_len());
            return decode_frame(&self.codec, &mut own, header, self.max_packet);
        }
        decode_frame(&self.codec, &mut self.read, header, self.max_packet)
    }

    /// Reads the first packet, which must be CONNECT, and picks the codec from it.
    pub async fn read_connect(&mut self) -> Result<Packet, Refusal> {
        let refusal = |reason, detail: String, connack| Refusal {
            reason,
            detail,
            connack,
        };
        let header = loop {
            // The first byte of a session must be CONNECT's; anything else (an HTTP
            // request, a TLS hello on a plain port) is refused without waiting for more,
            // saying what it was when it is a protocol of another kind of listener.
            if self.read.first().is_some_and(|b| *b != 0x10) {
                let (reason, detail) = not_mqtt(&self.read);
                return Err(refusal(reason, detail.into(), None));
            }
            match self.next_frame() {
                Ok(Some(header)) => break header,
                Ok(None) => {
                    self.fill()
                        .await
                        .map_err(|_| refusal("closed_before_connect", String::new(), None))?;
                }
                Err(ReadError::Oversized { size, max }) => {
                    return Err(refusal(
                        "oversized",
                        format!("CONNECT of {size} bytes, limit {max}"),
                        None,
                    ))
                }
                Err(e) => return Err(refusal("malformed", e.to_string(), None)),
            }
        };
        match frame::connect_protocol_level(&self.read, &header) {
            Some(4) => self.codec = Codec(Version::V311),
            Some(5) => self.codec = Codec(Version::V5),
            Some(level) => {
                return Err(refusal(
                    "unsupported_protocol",
                    format!("protocol level {level}; fbbus speaks MQTT 3.1.1 (4) and 5"),
                    Some(ConnectReturnCode::RefusedProtocolVersion),
                ))
            }
            None => {
                return Err(refusal(
                    "malformed",
                    "first packet is not an MQTT CONNECT".into(),
                    None,
                ))
            }
        }
        match self.decode(&header) {
            Ok(packet @ Packet::Connect(..)) => Ok(packet),
            Ok(_) => Err(refusal(
                "malformed",
                "first packet is not an MQTT CONNECT".into(),
                None,
            )),
            Err(e) => Err(refusal("malformed", e.to_string(), None)),
        }
    }

    /// Encodes a packet into the write buffer.
    pub fn queue(&mut self, packet: Packet) {
        if let Err(e) = self.codec.write(packet, &mut self.write) {
            tracing::error!(error = %e, "could not encode a packet for a client; dropped");
        }
    }

    /// Writes the write buffer out within the write timeout; returns the bytes written.
    /// On a timeout (`ErrorKind::TimedOut`) what the socket did not take stays buffered.
    pub async fn flush(&mut self) -> std::io::Result<usize> {
        if self.unwritten() == 0 {
            return Ok(0);
        }
        let n = self.unwritten();
        // First without a timer: the socket nearly always takes it at once.
        match poll_fn(|cx| Poll::Ready(self.poll_write_out(cx))).await {
            Poll::Ready(Ok(())) => return Ok(n),
            Poll::Ready(Err(e)) => return Err(e),
            Poll::Pending => {}
        }
        match tokio::time::timeout(self.write_timeout, poll_fn(|cx| self.poll_write_out(cx))).await
        {
            Ok(Ok(())) => Ok(n),
            Ok(Err(e)) => Err(e),
            Err(_) => Err(ErrorKind::TimedOut.into()),
        }
    }

    /// Writes as much of the write buffer as the socket takes, then flushes the stream
    /// (TLS keeps records of its own); Ready(Ok) once everything is out. Cancel-safe: what
    /// the socket took is gone from the buffer, what it did not stays.
    pub fn poll_write_out(&mut self, cx: &mut Context<'_>) -> Poll<std::io::Result<()>> {
        while self.written < self.write.len() {
            let rest = &self.write[self.written..];
            match Pin::new(&mut self.stream).poll_write(cx, rest) {
                Poll::Ready(Ok(0)) => return Poll::Ready(Err(ErrorKind::WriteZero.into())),
                Poll::Ready(Ok(n)) => self.written += n,
                Poll::Ready(Err(e)) => return Poll::Ready(Err(e)),
                Poll::Pending => return Poll::Pending,
            }
        }
        self.written = 0;
        if self.write.capacity() > KEPT_WRITE_CAPACITY {
            self.write = BytesMut::new();
        } else {
            self.write.clear();
        }
        Pin::new(&mut self.stream).poll_flush(cx)
    }

    /// Bytes in the write buffer the socket has not taken yet.
    pub fn unwritten(&self) -> usize {
        self.write.len() - self.written
    }

    /// Reads what the socket has into the read buffer without waiting, at most until it
    /// holds `limit` bytes: Ready(Ok(n)) with the bytes read (0: none, the buffer is full
    /// to `limit`), Ready(Err) when the connection closed, Pending when nothing is there.
    /// Used while a write waits (`session::write`): a client that is heard is alive.
    pub fn poll_fill_up_to(
        &mut self,
        cx: &mut Context<'_>,
        limit: usize,
    ) -> Poll<Result<usize, ReadError>> {
        if self.read.len() >= limit {
            return Poll::Ready(Ok(0));
        }
        // Through a small stack buffer: this path only runs while a write waits, and
        // carries a client's PINGREQs and acknowledgements, not its bulk traffic.
        let mut chunk = [0u8; 1024];
        let room = chunk.len().min(limit - self.read.len());
        let mut buf = tokio::io::ReadBuf::new(&mut chunk[..room]);
        match Pin::new(&mut self.stream).poll_read(cx, &mut buf) {
            Poll::Ready(Ok(())) => {
                let filled = buf.filled();
                if filled.is_empty() {
                    return Poll::Ready(Err(ReadError::Closed));
                }
                self.read.extend_from_slice(filled);
                Poll::Ready(Ok(filled.len()))
            }
            Poll::Ready(Err(_)) => Poll::Ready(Err(ReadError::Closed)),
            Poll::Pending => Poll::Pending,
        }
    }

    pub async fn send(&mut self, packet: Packet) -> std::io::Result<usize> {
        self.queue(packet);
        self.flush().await
    }
}

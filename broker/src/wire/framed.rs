//! The client's socket with its read and write buffers: bytes in, packets out, and back.
//!
//! Reading is cancel-safe (bytes read stay in the buffer), so the connection loop can
//! select on it. Buffers start small, because most of a line's devices are idle most of
//! the time, grow with the traffic, and are let go of once they are empty again: a device
//! that sent one burst must not keep a burst-sized buffer for the rest of the shift.

use std::net::SocketAddr;

use bytes::BytesMut;
use rumqttd::protocol::{ConnectReturnCode, Packet};
use tokio::io::{AsyncRead, AsyncReadExt, AsyncWrite, AsyncWriteExt};

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

/// Free room below which a read first reserves `BUSY_READ_RESERVE` more.
const MIN_READ_ROOM: usize = 256;

/// Room a read gets once a packet is underway: a batch of small packets per system call.
const BUSY_READ_RESERVE: usize = 4 * 1024;

/// A write buffer larger than this is freed after it was written out, not kept.
const KEPT_WRITE_CAPACITY: usize = 1024;

/// The socket with its read and write buffers.
pub struct Io {
    pub stream: Box<dyn Stream>,
    pub read: BytesMut,
    pub write: BytesMut,
    pub codec: Codec,
    max_packet: usize,
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
        }
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
            // request, a TLS hello on a plain port) is refused without waiting for more.
            if self.read.first().is_some_and(|b| *b != 0x10) {
                return Err(refusal(
                    "malformed",
                    "first packet is not an MQTT CONNECT".into(),
                    None,
                ));
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

    /// Writes the write buffer out; returns the bytes written.
    pub async fn flush(&mut self) -> std::io::Result<usize> {
        if self.write.is_empty() {
            return Ok(0);
        }
        self.stream.write_all(&self.write).await?;
        let n = self.write.len();
        if self.write.capacity() > KEPT_WRITE_CAPACITY {
            self.write = BytesMut::new();
        } else {
            self.write.clear();
        }
        Ok(n)
    }

    pub async fn send(&mut self, packet: Packet) -> std::io::Result<usize> {
        self.queue(packet);
        self.flush().await
    }
}

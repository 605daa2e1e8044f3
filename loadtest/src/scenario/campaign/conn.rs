//! One connection of a campaign: where to connect, from which source address, and the
//! raw TCP connection its script drives (bounded writes and reads, bytes kept to parse).

use crate::target::{Mqtt, Target};
use crate::wire::{self, Answer};

use super::{Close, Outcome, Start};
use std::net::{IpAddr, SocketAddr};
use std::time::{Duration, Instant};
use tokio::io::{AsyncReadExt, AsyncWriteExt};
use tokio::net::{TcpSocket, TcpStream};

/// What a connection's script knows: where to connect and how long to wait.
pub struct Ctx {
    pub target: Target,
    pub addr: SocketAddr,
    pub(super) sources: Vec<IpAddr>,
    /// Client ids start with this (`lt-a`).
    pub prefix: String,
    pub seed: u64,
    pub read: Duration,
    pub connack: Duration,
    /// Bound on a TCP connect and on each write.
    pub io: Duration,
}

impl Ctx {
    /// The harness's --username and password, for valid CONNECTs.
    pub fn login(&self) -> (Option<Vec<u8>>, Option<Vec<u8>>) {
        (
            self.target
                .username
                .as_ref()
                .map(|u| u.replace("{i}", "0").into_bytes()),
            self.target
                .password
                .as_ref()
                .map(|p| p.clone().into_bytes()),
        )
    }

    /// The protocol level the harness's own clients speak (`--mqtt`).
    pub fn level(&self) -> u8 {
        match self.target.mqtt {
            Mqtt::V5 => wire::V5,
            Mqtt::V311 => wire::V311,
        }
    }
}

/// Received bytes kept for parsing; beyond this they are only counted.
const KEEP: usize = 64 * 1024;

/// One raw TCP connection to the broker.
pub struct Conn {
    stream: TcpStream,
    pub received: Vec<u8>,
    /// The broker closed (EOF, reset, a failed write).
    pub closed: bool,
    io: Duration,
}

impl Conn {
    /// Connects connection `i` (from its source address, when spread).
    pub async fn open(ctx: &Ctx, i: u64) -> std::io::Result<Conn> {
        let connect = async {
            match ctx.sources.get(i as usize % ctx.sources.len().max(1)) {
                Some(source) => {
                    let socket = TcpSocket::new_v4()?;
                    socket.bind(SocketAddr::new(*source, 0))?;
                    socket.connect(ctx.addr).await
                }
                None => TcpStream::connect(ctx.addr).await,
            }
        };
        let stream = tokio::time::timeout(ctx.io, connect)
            .await
            .map_err(|_| std::io::Error::new(std::io::ErrorKind::TimedOut, "connect"))??;
        let _ = stream.set_nodelay(true);
        Ok(Conn {
            stream,
            received: Vec::new(),
            closed: false,
            io: ctx.io,
        })
    }

    /// Writes `bytes` whole; false (and `closed`) if the broker closed or stopped reading.
    pub async fn send(&mut self, o: &mut Outcome, bytes: &[u8]) -> bool {
        if self.closed {
            return false;
        }
        match tokio::time::timeout(self.io, self.stream.write_all(bytes)).await {
            Ok(Ok(())) => {
                o.bytes_sent += bytes.len() as u64;
                true
            }
            _ => {
                self.closed = true;
                false
            }
        }
    }

    /// Sends one whole packet, counting it.
    pub async fn packet(&mut self, o: &mut Outcome, bytes: &[u8], mutated: bool) -> bool {
        let sent = self.send(o, bytes).await;
        if sent {
            o.packets += 1;
            o.mutated += u64::from(mutated);
        }
        sent
    }

    fn take(&mut self, o: &mut Outcome, buf: &[u8]) {
        o.bytes_received += buf.len() as u64;
        let room = KEEP.saturating_sub(self.received.len());
        self.received.extend_from_slice(&buf[..buf.len().min(room)]);
    }

    /// Reads until `done(received)`, the broker closes, or `wait` passes.
    pub async fn read_until(&mut self, o: &mut Outcome, wait: Duration, done: fn(&[u8]) -> bool) {
        let deadline = tokio::time::Instant::now() + wait;
        let mut buf = [0u8; 4096];
        while !self.closed && !done(&self.received) {
            match tokio::time::timeout_at(deadline, self.stream.read(&mut buf)).await {
                Ok(Ok(0)) | Ok(Err(_)) => self.closed = true,
                Ok(Ok(n)) => self.take(o, &buf[..n]),
                Err(_) => return,
            }
        }
    }

    /// Reads what has already arrived, without waiting.
    pub fn drain(&mut self, o: &mut Outcome) {
        let mut buf = [0u8; 4096];
        while !self.closed {
            match self.stream.try_read(&mut buf) {
                Ok(0) => self.closed = true,
                Ok(n) => self.take(o, &buf[..n]),
                Err(e) if e.kind() == std::io::ErrorKind::WouldBlock => return,
                Err(_) => self.closed = true,
            }
        }
    }

    /// Waits (up to `wait`) for the broker's first packet and records how the connection
    /// began. `sent` is when the CONNECT went out; `awaited` false: the harness does not
    /// wait (the CONNECT was never completed).
    pub async fn await_answer(&mut self, o: &mut Outcome, wait: Duration, sent: Instant) {
        self.read_until(o, wait, |b| wire::first_answer(b).is_some())
            .await;
        o.start = match wire::first_answer(&self.received) {
            Some(Answer::Connack(0)) => {
                o.connack_us = Some(sent.elapsed().as_micros() as u64);
                Start::Accepted
            }
            Some(Answer::Connack(_)) => Start::Refused,
            Some(Answer::Other(_)) => Start::OtherAnswer,
            None if self.closed => Start::ClosedWithoutAnswer,
            None => Start::NoAnswer,
        };
    }

    /// Ends the connection the harness's way (unless the broker already closed it).
    /// Returns whether the broker closed it (for `Close::Disconnect`: within `read`, as it
    /// should after a DISCONNECT).
    pub async fn close(mut self, o: &mut Outcome, how: Close, read: Duration) -> bool {
        if self.closed {
            o.closed_by_broker = true;
            return true;
        }
        match how {
            Close::Disconnect => {
                // Waits for the broker to close: the DISCONNECT was processed.
                self.read_until(o, read, |_| false).await;
            }
            Close::Drop => {
                self.drain(o);
                let _ = self.stream.shutdown().await;
            }
            Close::Reset | Close::MidPacket => {
                let _ = self.stream.set_zero_linger();
            }
        }
        o.close = Some(how);
        self.closed
    }
}

//! Writing to the client, with its deadlines: liveness does not depend on the client
//! reading.
//!
//! A client that stops reading (a process stopped with SIGSTOP, a hung PLC network stack:
//! the kernel keeps acknowledging with a zero window) would otherwise hold a write forever,
//! and with it the connection's task: no keep-alive check, no will, `online` in the
//! registry for as long as it stays stopped (issue 20). So a write that cannot complete at
//! once waits for, whichever comes first:
//!
//! - the socket taking everything: done;
//! - `broker.slow_consumer_timeout_ms` (the write deadline): the client is a **slow
//!   consumer** ([`End::SlowConsumer`]);
//! - the keep-alive deadline (1.5 x keep-alive after the client was last heard): the
//!   client is read meanwhile, so a live client that sends PINGREQ or acknowledgements is
//!   heard while its write waits ([`End::KeepAlive`] otherwise);
//! - the broker shutting down.
//!
//! And a connection whose queued outgoing bytes are more than
//! `broker.slow_consumer_max_bytes` is a slow consumer at once: what the socket has not
//! taken of the write buffer (at most a `deliver` batch, 1 MiB, plus one packet) and the
//! deliveries held for its MQTT 5 Receive Maximum (a client that reads but does not
//! acknowledge); the most one connection may hold of the broker's memory.
//!
//! The socket is tried once first without any timer: a client that keeps up (nearly all
//! writes) costs what it did before.

use std::future::{poll_fn, Future};
use std::pin::pin;
use std::task::Poll;

use tokio::time::{sleep, sleep_until, Instant};

use super::close::End;
use super::Session;

/// Bytes read from the client while a write waits for it, at most; their packets are
/// handled once the write is done. Plenty for the PINGREQs and acknowledgements of a live
/// client; a client that sends more without reading is not read further (TCP slows it)
/// and is left to the write deadline.
const READ_WHILE_WRITING: usize = 64 * 1024;

impl Session {
    /// Writes the write buffer out under the deadlines above; counts the bytes.
    pub(super) async fn write_out(&mut self) -> Result<(), End> {
        let queued = self.io.unwritten();
        if queued > 0 {
            let first = poll_fn(|cx| Poll::Ready(self.io.poll_write_out(cx))).await;
            match first {
                Poll::Ready(Ok(())) => {}
                Poll::Ready(Err(_)) => return Err(End::Abrupt),
                Poll::Pending => self.wait_for_socket().await?,
            }
            self.qos0_unwritten = 0;
            self.ctx.metrics.bytes_out.inc_by(queued as u64);
        }
        // A client that reads but does not acknowledge: its held deliveries alone pass
        // the limit (checked once per write, not per message).
        if self.held_bytes > self.ctx.max_queued_bytes {
            self.over_quota(self.held_bytes);
            return Err(End::SlowConsumer);
        }
        Ok(())
    }

    fn over_quota(&self, queued: usize) {
        if crate::logging::OUTSIDE.allow() {
            tracing::warn!(
                client_id = &*self.client.client_id,
                queued,
                held = self.held_bytes,
                limit = self.ctx.max_queued_bytes,
                "slow consumer: more outgoing data queued than broker.slow_consumer_max_bytes; \
                 connection closed"
            );
        }
    }

    /// The slow path of [`Session::write_out`]: the socket did not take everything.
    async fn wait_for_socket(&mut self) -> Result<(), End> {
        let queued = self.io.unwritten() + self.held_bytes;
        if queued > self.ctx.max_queued_bytes {
            self.over_quota(queued);
            return Err(End::SlowConsumer);
        }
        let started = Instant::now();
        let mut write_deadline = pin!(sleep(self.ctx.write_timeout));
        let mut keep_alive = pin!(sleep_until(self.alive_until));
        let mut shutdown = self.ctx.shutdown.clone();
        let mut shutdown = pin!(shutdown.changed());
        let with_keep_alive = self.keep_alive.is_some();
        let waited = poll_fn(|cx| {
            match self.io.poll_write_out(cx) {
                Poll::Ready(Ok(())) => return Poll::Ready(Ok(())),
                Poll::Ready(Err(_)) => return Poll::Ready(Err(End::Abrupt)),
                Poll::Pending => {}
            }
            // Hear the client while its write waits: bytes read are handled afterwards.
            loop {
                match self.io.poll_fill_up_to(cx, READ_WHILE_WRITING) {
                    Poll::Ready(Ok(0)) | Poll::Pending => break,
                    Poll::Ready(Ok(n)) => {
                        self.ctx.metrics.bytes_in.inc_by(n as u64);
                        self.unhandled_read = true;
                        self.heard();
                        keep_alive.as_mut().reset(self.alive_until);
                    }
                    Poll::Ready(Err(_)) => return Poll::Ready(Err(End::Abrupt)),
                }
            }
            if with_keep_alive && keep_alive.as_mut().poll(cx).is_ready() {
                return Poll::Ready(Err(End::KeepAlive));
            }
            if write_deadline.as_mut().poll(cx).is_ready() {
                return Poll::Ready(Err(End::SlowConsumer));
            }
            if shutdown.as_mut().poll(cx).is_ready() {
                return Poll::Ready(Err(End::Shutdown));
            }
            Poll::Pending
        })
        .await;
        if let Err(end) = waited {
            let unwritten = self.io.unwritten();
            match end {
                End::SlowConsumer if crate::logging::OUTSIDE.allow() => tracing::warn!(
                    client_id = &*self.client.client_id,
                    unwritten,
                    waited_ms = started.elapsed().as_millis() as u64,
                    "slow consumer: outgoing data not taken within \
                     broker.slow_consumer_timeout_ms; connection closed"
                ),
                End::KeepAlive => tracing::info!(
                    client_id = &*self.client.client_id,
                    unwritten,
                    "keep-alive expired while a write to the client waited"
                ),
                _ => {}
            }
        }
        waited
    }
}

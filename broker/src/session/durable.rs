//! A session's bookkeeping with the store ([`persist`](super::persist)), allocated the
//! first time it needs any: most connections never store or receive a stored message.
//!
//! - **Stored messages on their way to the client** (`stored_out`), by the router's packet
//!   id: what the client's acknowledgement of a delivery is written as.
//! - **Acknowledgements that wait for the store.** A publication the store keeps is handed
//!   to the router at once, in the same batch as always; only the client's PUBACK/PUBREC
//!   for it waits until the writer confirms the write ([`Durable::pass`]). What fbbus has
//!   acknowledged therefore survives a restart, and the router's batches are as large as
//!   without the store. A subscriber may get the message before it is written; if the
//!   broker dies in between, the publisher, which got no acknowledgement, sends it again
//!   (QoS 1: a duplicate, as MQTT allows).
//!
//! Writes are confirmed in the order they were handed over (one writer, one queue), and
//! acknowledgements leave in the order the router gave them: one that waits holds back
//! those after it (MQTT 4.6: PUBACKs in the order of the PUBLISHes).

use std::collections::{HashMap, VecDeque};

/// A map keyed by packet id. foldhash, not SipHash: five hashes per stored message, and
/// its keys are bounded by the in-flight window, so a flood of colliding ids costs nothing.
pub(super) type ByPkid<V> = HashMap<u16, V, foldhash::fast::RandomState>;

use rumqttd::protocol::Packet;
use tokio::sync::oneshot;

#[derive(Default)]
pub(super) struct Durable {
    /// Stored messages on their way to the client: router packet id -> (message number,
    /// client packet id). Bounded by the in-flight window.
    pub stored_out: ByPkid<(u64, u16)>,
    /// Writes not confirmed yet, oldest first: their number and the writer's answer.
    pending: VecDeque<(u64, oneshot::Receiver<()>)>,
    /// Client packet ids of stored publications -> the number of the write that has them.
    /// Bounded by the Receive Maximum fbbus announces (the client cannot have more
    /// publications unacknowledged).
    unwritten: ByPkid<u64>,
    /// Acknowledgements from the router that wait for a write, and those behind them.
    held: VecDeque<Packet>,
    /// Writes handed over, and the last one confirmed (all before it are too).
    submitted: u64,
    written: u64,
}

impl Durable {
    /// A write that has the publications the client sent under `pkids` was handed to the
    /// store; `written` answers when it is written.
    pub fn submitted(&mut self, pkids: &[u16], written: oneshot::Receiver<()>) {
        self.submitted += 1;
        for pkid in pkids {
            self.unwritten.insert(*pkid, self.submitted);
        }
        self.pending.push_back((self.submitted, written));
    }

    /// Whether a write is awaited.
    #[cfg(test)]
    pub fn awaiting(&self) -> bool {
        !self.pending.is_empty()
    }

    /// Waits until the oldest awaited write is confirmed (forever if none is awaited).
    /// Cancel-safe: nothing changes until [`Durable::confirmed`].
    pub async fn next_written(durable: &mut Option<Box<Durable>>) {
        match durable.as_mut().and_then(|d| d.pending.front_mut()) {
            // A writer that is gone answers too (the broker is stopping).
            // Never polled again once it answered (tokio's receiver panics then): an
            // answered write is ready until `confirmed` takes it.
            Some((_, written)) if written.is_terminated() => {}
            Some((_, written)) => {
                let _ = written.await;
            }
            None => std::future::pending().await,
        }
    }

    /// Takes note of every write confirmed by now, and moves the acknowledgements that no
    /// longer wait to `out`, in order.
    pub fn confirmed(&mut self, out: &mut Vec<Packet>) {
        while let Some((number, written)) = self.pending.front_mut() {
            match written.try_recv() {
                Err(oneshot::error::TryRecvError::Empty) => break,
                _ => {
                    self.written = *number;
                    self.pending.pop_front();
                }
            }
        }
        while let Some(packet) = self.held.front() {
            if self.waits(packet) {
                break;
            }
            if let Some(packet) = self.held.pop_front() {
                self.forget(&packet);
                out.push(packet);
            }
        }
    }

    /// An answer from the router on its way to the client: given back if it may leave now,
    /// kept (and given back by [`Durable::confirmed`]) if it waits for the store.
    pub fn pass(&mut self, packet: Packet) -> Option<Packet> {
        if self.held.is_empty() && !self.waits(&packet) {
            self.forget(&packet);
            return Some(packet);
        }
        self.held.push_back(packet);
        None
    }

    fn waits(&self, packet: &Packet) -> bool {
        ack_pkid(packet)
            .and_then(|pkid| self.unwritten.get(&pkid))
            .is_some_and(|number| *number > self.written)
    }

    fn forget(&mut self, packet: &Packet) {
        if let Some(pkid) = ack_pkid(packet) {
            self.unwritten.remove(&pkid);
        }
    }
}

/// The packet id of an acknowledgement that may wait for the store.
fn ack_pkid(packet: &Packet) -> Option<u16> {
    match packet {
        Packet::PubAck(ack, _) => Some(ack.pkid),
        Packet::PubRec(rec, _) => Some(rec.pkid),
        _ => None,
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use rumqttd::protocol::{PingResp, PubAck, PubAckReason};

    fn puback(pkid: u16) -> Packet {
        Packet::PubAck(
            PubAck {
                pkid,
                reason: PubAckReason::Success,
            },
            None,
        )
    }

    fn ids(packets: &[Packet]) -> Vec<u16> {
        packets.iter().filter_map(ack_pkid).collect()
    }

    #[test]
    fn acknowledgements_wait_for_their_write_and_keep_their_order() {
        let mut d = Durable::default();
        let (first_done, first) = oneshot::channel();
        let (second_done, second) = oneshot::channel();
        d.submitted(&[1, 2], first);
        d.submitted(&[3], second);
        // Not stored: passes while nothing is held.
        assert!(d.pass(puback(9)).is_some());
        assert!(d.pass(puback(1)).is_none());
        // Behind a held one, even a publication that was not stored waits.
        assert!(d.pass(Packet::PingResp(PingResp)).is_none());
        assert!(d.pass(puback(2)).is_none());
        assert!(d.pass(puback(3)).is_none());
        let mut out = Vec::new();
        d.confirmed(&mut out);
        assert!(out.is_empty(), "nothing written yet");
        second_done.send(()).unwrap();
        d.confirmed(&mut out);
        assert!(
            out.is_empty(),
            "the first write is not confirmed: order holds"
        );
        first_done.send(()).unwrap();
        d.confirmed(&mut out);
        assert_eq!(ids(&out), [1, 2, 3]);
        assert_eq!(out.len(), 4, "the PINGRESP behind them too");
        assert!(!d.awaiting());
        // Written before the router answers: passes at once, and the id is forgotten.
        let (done, rx) = oneshot::channel();
        d.submitted(&[4], rx);
        done.send(()).unwrap();
        d.confirmed(&mut out);
        assert!(d.pass(puback(4)).is_some());
        assert!(d.unwritten.is_empty());
    }

    #[tokio::test]
    async fn an_answered_write_is_ready_until_confirmed() {
        let mut d = Some(Box::<Durable>::default());
        let (done, rx) = oneshot::channel();
        d.as_mut().unwrap().submitted(&[1], rx);
        done.send(()).unwrap();
        Durable::next_written(&mut d).await;
        // Again before `confirmed` took it: ready, not a second poll of the receiver.
        Durable::next_written(&mut d).await;
        let mut out = Vec::new();
        d.as_mut().unwrap().confirmed(&mut out);
        assert!(!d.as_ref().unwrap().awaiting());
    }

    #[test]
    fn a_gone_writer_releases_what_waits() {
        let mut d = Durable::default();
        let (done, rx) = oneshot::channel::<()>();
        d.submitted(&[1], rx);
        assert!(d.pass(puback(1)).is_none());
        drop(done);
        let mut out = Vec::new();
        d.confirmed(&mut out);
        assert_eq!(ids(&out), [1]);
    }
}

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

use rumqttd::protocol::{Packet, PubAckReason, PubRecReason};
use tokio::sync::oneshot;

use crate::store::Refusals;

/// A write handed to the store: its number, and the writer's answer once it came.
struct Pending {
    number: u64,
    written: oneshot::Receiver<Refusals>,
    /// Some once the writer answered (or is gone: no refusals).
    answer: Option<Refusals>,
}

#[derive(Default)]
pub(super) struct Durable {
    /// Stored messages on their way to the client: router packet id -> (message number,
    /// client packet id). Bounded by the in-flight window.
    pub stored_out: ByPkid<(u64, u16)>,
    /// Writes not confirmed yet, oldest first.
    pending: VecDeque<Pending>,
    /// Client packet ids of stored publications -> the number of the write that has them
    /// and the publication's message number. Bounded by the Receive Maximum fbbus
    /// announces (the client cannot have more publications unacknowledged).
    unwritten: ByPkid<(u64, u64)>,
    /// Client packet ids of publications the client is told were not kept (MQTT 5 0x97
    /// Quota exceeded): by the store (`store::Refusals`, true) or as retained messages
    /// (`retained_share`, false). Bounded as `unwritten`.
    refused: ByPkid<bool>,
    /// Acknowledgements that said 0x97, not yet counted by the session.
    pub refusals_sent: u32,
    /// The identity whose store share this session's publications spend, set once.
    pub share: Option<std::sync::Arc<str>>,
    /// Acknowledgements from the router that wait for a write, and those behind them.
    held: VecDeque<Packet>,
    /// Writes handed over, and the last one confirmed (all before it are too).
    submitted: u64,
    written: u64,
}

impl Durable {
    /// A write that has the publications the client sent under these packet ids, with
    /// these message numbers, was handed to the store; `written` answers when it is
    /// written, with the numbers the store did not keep.
    pub fn submitted(&mut self, published: &[(u16, u64)], written: oneshot::Receiver<Refusals>) {
        self.submitted += 1;
        for (pkid, seq) in published {
            self.unwritten.insert(*pkid, (self.submitted, *seq));
        }
        self.pending.push_back(Pending {
            number: self.submitted,
            written,
            answer: None,
        });
    }

    /// Whether a write is awaited.
    #[cfg(test)]
    pub fn awaiting(&self) -> bool {
        !self.pending.is_empty()
    }

    /// Waits until the oldest awaited write is answered (forever if none is awaited).
    /// Cancel-safe: the answer is kept until [`Durable::confirmed`] takes it.
    pub async fn next_written(durable: &mut Option<Box<Durable>>) {
        match durable.as_mut().and_then(|d| d.pending.front_mut()) {
            // Never polled again once it answered (tokio's receiver panics then).
            Some(p) if p.answer.is_some() => {}
            // A writer that is gone answers too (the broker is stopping): no refusals.
            Some(p) => p.answer = Some((&mut p.written).await.unwrap_or_default()),
            None => std::future::pending().await,
        }
    }

    /// Takes note of every write confirmed by now, and moves the acknowledgements that no
    /// longer wait to `out`, in order.
    pub fn confirmed(&mut self, out: &mut Vec<Packet>) {
        while let Some(p) = self.pending.front_mut() {
            if p.answer.is_none() {
                match p.written.try_recv() {
                    Err(oneshot::error::TryRecvError::Empty) => break,
                    answer => p.answer = Some(answer.unwrap_or_default()),
                }
            }
            let number = p.number;
            let refusals = p.answer.take().unwrap_or_default();
            self.pending.pop_front();
            self.written = number;
            self.note_refusals(number, &refusals);
        }
        while let Some(packet) = self.held.front() {
            if self.waits(packet) {
                break;
            }
            if let Some(packet) = self.held.pop_front() {
                let packet = self.forget(packet);
                out.push(packet);
            }
        }
    }

    /// Marks the publications of write `number` whose message numbers are in `refusals`.
    fn note_refusals(&mut self, number: u64, refusals: &[u64]) {
        if refusals.is_empty() {
            return;
        }
        for (pkid, (write, seq)) in &self.unwritten {
            if *write == number && refusals.binary_search(seq).is_ok() {
                self.refused.insert(*pkid, true);
            }
        }
    }

    /// An answer from the router on its way to the client: given back if it may leave now,
    /// kept (and given back by [`Durable::confirmed`]) if it waits for the store.
    pub fn pass(&mut self, packet: Packet) -> Option<Packet> {
        if self.held.is_empty() && !self.waits(&packet) {
            return Some(self.forget(packet));
        }
        self.held.push_back(packet);
        None
    }

    fn waits(&self, packet: &Packet) -> bool {
        ack_pkid(packet)
            .and_then(|pkid| self.unwritten.get(&pkid))
            .is_some_and(|(number, _)| *number > self.written)
    }

    /// The publication the client sent under `pkid` is routed but not retained
    /// (`retained_share`): its acknowledgement says 0x97.
    pub fn refuse_retained(&mut self, pkid: u16) {
        self.refused.insert(pkid, false);
    }

    /// The acknowledgement as it leaves: 0x97 if its publication was not kept.
    fn forget(&mut self, mut packet: Packet) -> Packet {
        let Some(pkid) = ack_pkid(&packet) else {
            return packet;
        };
        self.unwritten.remove(&pkid);
        let Some(by_store) = self.refused.remove(&pkid) else {
            return packet;
        };
        let refused = match &mut packet {
            Packet::PubAck(ack, _) if ack.reason == PubAckReason::Success => {
                ack.reason = PubAckReason::QuotaExceeded;
                true
            }
            Packet::PubRec(rec, _) if rec.reason == PubRecReason::Success => {
                rec.reason = PubRecReason::QuotaExceeded;
                true
            }
            _ => false,
        };
        self.refusals_sent += (refused && by_store) as u32;
        packet
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
        d.submitted(&[(1, 11), (2, 12)], first);
        d.submitted(&[(3, 13)], second);
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
        second_done.send(Vec::new()).unwrap();
        d.confirmed(&mut out);
        assert!(
            out.is_empty(),
            "the first write is not confirmed: order holds"
        );
        first_done.send(Vec::new()).unwrap();
        d.confirmed(&mut out);
        assert_eq!(ids(&out), [1, 2, 3]);
        assert_eq!(out.len(), 4, "the PINGRESP behind them too");
        assert!(!d.awaiting());
        // Written before the router answers: passes at once, and the id is forgotten.
        let (done, rx) = oneshot::channel();
        d.submitted(&[(4, 14)], rx);
        done.send(Vec::new()).unwrap();
        d.confirmed(&mut out);
        assert!(d.pass(puback(4)).is_some());
        assert!(d.unwritten.is_empty());
    }

    #[tokio::test]
    async fn an_answered_write_is_ready_until_confirmed() {
        let mut d = Some(Box::<Durable>::default());
        let (done, rx) = oneshot::channel();
        d.as_mut().unwrap().submitted(&[(1, 11)], rx);
        done.send(Vec::new()).unwrap();
        Durable::next_written(&mut d).await;
        // Again before `confirmed` took it: ready, not a second poll of the receiver.
        Durable::next_written(&mut d).await;
        assert!(d.as_ref().unwrap().awaiting());
        let mut out = Vec::new();
        d.as_mut().unwrap().confirmed(&mut out);
        assert!(!d.as_ref().unwrap().awaiting());
    }

    /// The refusals of a write the session awaited are not lost with the wait.
    #[tokio::test]
    async fn an_awaited_write_keeps_its_refusals() {
        let mut d = Some(Box::<Durable>::default());
        let (done, rx) = oneshot::channel();
        d.as_mut().unwrap().submitted(&[(1, 11)], rx);
        done.send(vec![11]).unwrap();
        Durable::next_written(&mut d).await;
        let d = d.as_mut().unwrap();
        let mut out = Vec::new();
        d.confirmed(&mut out);
        let Some(Packet::PubAck(ack, _)) = d.pass(puback(1)) else {
            panic!("the PUBACK waits for nothing");
        };
        assert_eq!(ack.reason, PubAckReason::QuotaExceeded);
    }

    #[test]
    fn a_gone_writer_releases_what_waits() {
        let mut d = Durable::default();
        let (done, rx) = oneshot::channel::<Refusals>();
        d.submitted(&[(1, 11)], rx);
        assert!(d.pass(puback(1)).is_none());
        drop(done);
        let mut out = Vec::new();
        d.confirmed(&mut out);
        assert_eq!(ids(&out), [1]);
    }

    /// Issue 33: a publication the store did not keep is answered 0x97, the others of the
    /// same write succeed, and a later publication under the same packet id is not
    /// marked by the earlier refusal.
    #[test]
    fn what_the_store_did_not_keep_is_answered_quota_exceeded() {
        let reason = |p: &Packet| match p {
            Packet::PubAck(ack, _) => ack.reason,
            _ => panic!("not a PUBACK"),
        };
        let mut d = Durable::default();
        let (done, rx) = oneshot::channel();
        d.submitted(&[(1, 11), (2, 12), (3, 13)], rx);
        assert!(d.pass(puback(1)).is_none());
        assert!(d.pass(puback(2)).is_none());
        done.send(vec![12]).unwrap();
        let mut out = Vec::new();
        d.confirmed(&mut out);
        assert_eq!(ids(&out), [1, 2]);
        assert_eq!(reason(&out[0]), PubAckReason::Success);
        assert_eq!(reason(&out[1]), PubAckReason::QuotaExceeded);
        assert_eq!(reason(&d.pass(puback(3)).unwrap()), PubAckReason::Success);
        assert_eq!(d.refusals_sent, 1);
        let (done, rx) = oneshot::channel();
        d.submitted(&[(2, 20)], rx);
        done.send(Vec::new()).unwrap();
        out.clear();
        d.confirmed(&mut out);
        assert_eq!(reason(&d.pass(puback(2)).unwrap()), PubAckReason::Success);
        assert!(d.refused.is_empty() && d.unwritten.is_empty());
    }
}

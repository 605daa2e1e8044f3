//! Matching the broker's PUBACKs and SUBACKs to the calls waiting for them.
//!
//! rumqttc assigns packet ids inside its event loop and reports them as events:
//! `Outgoing::Publish(pkid)` when a request is written, `Incoming::PubAck(pkid)` when it is
//! acknowledged. Requests reach the event loop through one FIFO channel and are written in
//! that order, so each call that hands a request to rumqttc queues a waiter at the same
//! time (under one lock), and the n-th `Outgoing` event of a kind belongs to the n-th
//! waiter. From then on the waiter is found by packet id, so acknowledgements may come in
//! any order.
//!
//! Two rumqttc behaviours shape this:
//!
//! - After a reconnect rumqttc resends unacknowledged publishes **with their packet ids**:
//!   an `Outgoing::Publish` for an id that already has a waiter is a resend, not a new
//!   request. Subscribes are never resent (the client re-subscribes after a reconnect), so
//!   their waiters are dropped when the connection is lost.
//! - When a packet id is still in flight rumqttc reports `Outgoing::AwaitAck(pkid)`, holds
//!   the request back and writes it (with that id) while handling the PUBACK for the
//!   older one, reporting the write *before* the PUBACK. The held-back waiter is parked
//!   until that PUBACK.

use std::collections::{HashMap, VecDeque};

use tokio::sync::oneshot;

/// Waiters for one kind of acknowledgement, carrying a `T`.
#[derive(Debug)]
pub(super) struct Pending<T> {
    /// Whether rumqttc resends this kind of packet after a reconnect, keeping its id.
    resent: bool,
    /// Handed to rumqttc, not yet written: no packet id yet. In request order.
    queued: VecDeque<oneshot::Sender<T>>,
    /// Written with this packet id, waiting for its acknowledgement.
    written: HashMap<u16, oneshot::Sender<T>>,
    /// Held back by rumqttc until the id's previous holder is acknowledged.
    collided: Option<(u16, oneshot::Sender<T>)>,
}

impl<T> Pending<T> {
    pub(super) fn new(resent: bool) -> Pending<T> {
        Pending {
            resent,
            queued: VecDeque::new(),
            written: HashMap::new(),
            collided: None,
        }
    }

    /// A request is being handed to rumqttc: the receiver gets its acknowledgement.
    pub(super) fn queue(&mut self) -> oneshot::Receiver<T> {
        let (tx, rx) = oneshot::channel();
        self.queued.push_back(tx);
        rx
    }

    /// The request just queued could not be handed over after all.
    pub(super) fn unqueue(&mut self) {
        self.queued.pop_back();
    }

    /// rumqttc wrote a packet with id `pkid`.
    pub(super) fn written(&mut self, pkid: u16) {
        if self.resent && self.written.contains_key(&pkid) {
            return; // a resend after a reconnect, or the held-back request (see `acked`)
        }
        if let Some(waiter) = self.queued.pop_front() {
            self.written.insert(pkid, waiter);
        }
    }

    /// rumqttc holds the next request back until `pkid` is acknowledged.
    pub(super) fn collided(&mut self, pkid: u16) {
        if let Some(waiter) = self.queued.pop_front() {
            self.collided = Some((pkid, waiter));
        }
    }

    /// The broker acknowledged `pkid`.
    pub(super) fn acked(&mut self, pkid: u16, value: T) {
        if let Some(waiter) = self.written.remove(&pkid) {
            // The caller may have stopped waiting (timeout); nothing to do then.
            let _ = waiter.send(value);
        }
        if self.collided.as_ref().is_some_and(|(id, _)| *id == pkid) {
            let (id, waiter) = self.collided.take().expect("checked above");
            self.written.insert(id, waiter);
        }
    }

    /// The connection was lost: packets rumqttc does not resend will never be
    /// acknowledged, so their waiters learn it now.
    pub(super) fn connection_lost(&mut self) {
        if !self.resent {
            self.written.clear();
        }
    }
}

/// Every acknowledgement the client waits for.
#[derive(Debug)]
pub(super) struct Acks {
    /// QoS 1 publishes: PUBACK carries nothing on MQTT 3.1.1.
    pub(super) publishes: Pending<()>,
    /// Subscribes: the SUBACK return codes (`Failure` is a refusal).
    pub(super) subscribes: Pending<Vec<rumqttc::SubscribeReasonCode>>,
}

impl Default for Acks {
    fn default() -> Acks {
        Acks {
            publishes: Pending::new(true),
            subscribes: Pending::new(false),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use tokio::sync::oneshot::error::TryRecvError;

    fn got(rx: &mut oneshot::Receiver<u8>) -> Option<u8> {
        rx.try_recv().ok()
    }

    #[test]
    fn acknowledgements_find_their_request_in_any_order() {
        let mut p = Pending::new(true);
        let (mut a, mut b) = (p.queue(), p.queue());
        p.written(1);
        p.written(2);
        p.acked(2, 20);
        assert_eq!(got(&mut a), None);
        assert_eq!(got(&mut b), Some(20));
        p.acked(1, 10);
        assert_eq!(got(&mut a), Some(10));
    }

    #[test]
    fn a_request_that_was_not_handed_over_leaves_no_waiter() {
        let mut p = Pending::new(true);
        let mut a = p.queue();
        let _failed = p.queue();
        p.unqueue();
        let mut c = p.queue();
        p.written(1);
        p.written(2);
        p.acked(2, 2);
        p.acked(1, 1);
        assert_eq!((got(&mut a), got(&mut c)), (Some(1), Some(2)));
    }

    #[test]
    fn publishes_resent_after_a_reconnect_keep_their_waiter() {
        let mut p = Pending::new(true);
        let (mut a, mut b) = (p.queue(), p.queue());
        p.written(1);
        p.connection_lost();
        // Reconnected: rumqttc resends 1 with its id, then writes the next request.
        p.written(1);
        p.written(2);
        p.acked(1, 1);
        p.acked(2, 2);
        assert_eq!((got(&mut a), got(&mut b)), (Some(1), Some(2)));
    }

    #[test]
    fn subscribes_lost_with_the_connection_fail_and_ids_are_reused() {
        let mut p = Pending::new(false);
        let mut a = p.queue();
        p.written(1);
        p.connection_lost();
        assert_eq!(a.try_recv(), Err(TryRecvError::Closed));
        let mut b = p.queue();
        p.written(1);
        p.acked(1, 7);
        assert_eq!(got(&mut b), Some(7));
    }

    #[test]
    fn a_held_back_publish_is_acknowledged_after_its_ids_previous_holder() {
        let mut p = Pending::new(true);
        let (mut a, mut b) = (p.queue(), p.queue());
        p.written(1);
        p.collided(1);
        // rumqttc writes the held-back request, then reports the PUBACK that freed the id.
        p.written(1);
        p.acked(1, 1);
        assert_eq!((got(&mut a), got(&mut b)), (Some(1), None));
        p.acked(1, 2);
        assert_eq!(got(&mut b), Some(2));
    }
}

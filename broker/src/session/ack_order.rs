//! Acknowledgements towards the router, in the order the router requires.
//!
//! rumqttd 0.20's router accepts PUBACK/PUBREC for its deliveries only in the order it sent
//! them, and PUBCOMP only in the order of its PUBRELs; anything else ends the connection
//! ("out of order ack"). A client answers in order by itself (MQTT 4.6). But the packet
//! path sometimes answers for the client: a delivery sent at a lower QoS than the router
//! used, or not sent at all because it exceeds the client's Maximum Packet Size. Those
//! answers are interleaved with the client's here: each delivery takes a place in line
//! when it is sent, and acknowledgements leave in line order as soon as the head is
//! answered.
//!
//! **Small per delivery.** A line holds one entry per delivery in flight, up to
//! `[broker] max_inflight_out` (512) for a client that does not acknowledge. An entry is a
//! packet id and, only for an answer that came ahead of its turn, the answer boxed: 16
//! bytes. It held the answer inline before, `Option<Packet>`, 400 bytes whether answered
//! or not: 200 KB per connection at a window of 512.

use std::collections::VecDeque;

use rumqttd::protocol::Packet;

/// One line of outstanding acknowledgements (PUBACK/PUBREC, or PUBCOMP).
#[derive(Default)]
struct Line {
    waiting: VecDeque<(u16, Option<Box<Packet>>)>,
}

impl Line {
    fn enqueue(&mut self, pkid: u16) {
        self.waiting.push_back((pkid, None));
    }

    /// Records the answer for `pkid`: at the head of the line (a client answering in
    /// order) it goes to `out` at once; further back it waits, boxed. One for a `pkid` not
    /// waiting here goes to `out` too.
    fn answer(&mut self, pkid: u16, packet: Packet, out: &mut Vec<Packet>) {
        if self
            .waiting
            .front()
            .is_some_and(|(id, answer)| *id == pkid && answer.is_none())
        {
            self.waiting.pop_front();
            out.push(packet);
            return;
        }
        match self
            .waiting
            .iter_mut()
            .find(|(id, answer)| *id == pkid && answer.is_none())
        {
            Some(slot) => slot.1 = Some(Box::new(packet)),
            None => out.push(packet),
        }
    }

    /// Moves answered acknowledgements from the head of the line to `out`.
    fn release(&mut self, out: &mut Vec<Packet>) {
        while self.waiting.front().is_some_and(|(_, a)| a.is_some()) {
            if let Some((_, Some(packet))) = self.waiting.pop_front() {
                out.push(*packet);
            }
        }
    }
}

/// The two lines of one connection.
#[derive(Default)]
pub struct AckOrder {
    acks: Line,
    completions: Line,
}

impl AckOrder {
    /// A QoS 1/2 delivery with this packet id left for the client (or was answered for it).
    pub fn delivered(&mut self, pkid: u16) {
        self.acks.enqueue(pkid);
    }

    /// The router sent PUBREL for this packet id.
    pub fn released(&mut self, pkid: u16) {
        self.completions.enqueue(pkid);
    }

    /// A PUBACK or PUBREC for a delivery, from the client or on its behalf. Acknowledgements
    /// that may now go to the router are appended to `out`; one for a delivery this
    /// connection did not send (a session resumed from an earlier connection) goes straight
    /// through, as before.
    pub fn ack(&mut self, pkid: u16, packet: Packet, out: &mut Vec<Packet>) {
        self.acks.answer(pkid, packet, out);
        self.acks.release(out);
    }

    /// A PUBCOMP, from the client or on its behalf.
    pub fn complete(&mut self, pkid: u16, packet: Packet, out: &mut Vec<Packet>) {
        self.completions.answer(pkid, packet, out);
        self.completions.release(out);
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use rumqttd::protocol::{PubAck, PubAckReason};

    fn puback(pkid: u16) -> Packet {
        Packet::PubAck(
            PubAck {
                pkid,
                reason: PubAckReason::Success,
            },
            None,
        )
    }

    fn ids(out: &[Packet]) -> Vec<u16> {
        out.iter()
            .map(|p| match p {
                Packet::PubAck(a, _) => a.pkid,
                _ => 0,
            })
            .collect()
    }

    #[test]
    fn an_early_answer_waits_for_the_ones_before_it() {
        let mut order = AckOrder::default();
        let mut out = Vec::new();
        for pkid in [1, 2, 3] {
            order.delivered(pkid);
        }
        order.ack(2, puback(2), &mut out); // answered for the client, ahead of 1
        assert!(out.is_empty());
        order.ack(1, puback(1), &mut out); // the client's own
        assert_eq!(ids(&out), [1, 2]);
        order.ack(3, puback(3), &mut out);
        assert_eq!(ids(&out), [1, 2, 3]);
    }

    /// What a delivery in flight costs while its client has not answered.
    #[test]
    fn an_entry_is_an_id_and_a_pointer() {
        assert_eq!(std::mem::size_of::<(u16, Option<Box<Packet>>)>(), 16);
    }

    #[test]
    fn in_order_answers_leave_at_once_and_ids_answered_twice_pass_through() {
        let mut order = AckOrder::default();
        let mut out = Vec::new();
        for pkid in [1, 2, 1] {
            order.delivered(pkid); // ids wrap: 1 is in line twice
        }
        order.ack(1, puback(1), &mut out);
        assert_eq!(ids(&out), [1]);
        order.ack(1, puback(1), &mut out); // the second 1 waits behind 2
        assert_eq!(ids(&out), [1]);
        order.ack(2, puback(2), &mut out);
        assert_eq!(ids(&out), [1, 2, 1]);
        assert!(order.acks.waiting.is_empty());
    }

    #[test]
    fn unknown_ids_pass_through() {
        let mut order = AckOrder::default();
        let mut out = Vec::new();
        order.ack(9, puback(9), &mut out);
        assert_eq!(ids(&out), [9]);
    }
}

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

use std::collections::VecDeque;

use rumqttd::protocol::Packet;

/// One line of outstanding acknowledgements (PUBACK/PUBREC, or PUBCOMP).
#[derive(Default)]
struct Line {
    waiting: VecDeque<(u16, Option<Packet>)>,
}

impl Line {
    fn enqueue(&mut self, pkid: u16) {
        self.waiting.push_back((pkid, None));
    }

    /// Records the answer for `pkid`; gives the packet back when `pkid` is not waiting here.
    fn answer(&mut self, pkid: u16, packet: Packet) -> Option<Packet> {
        match self
            .waiting
            .iter_mut()
            .find(|(id, answer)| *id == pkid && answer.is_none())
        {
            Some(slot) => {
                slot.1 = Some(packet);
                None
            }
            None => Some(packet),
        }
    }

    /// Moves answered acknowledgements from the head of the line to `out`.
    fn release(&mut self, out: &mut Vec<Packet>) {
        while self.waiting.front().is_some_and(|(_, a)| a.is_some()) {
            if let Some((_, Some(packet))) = self.waiting.pop_front() {
                out.push(packet);
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
        if let Some(packet) = self.acks.answer(pkid, packet) {
            out.push(packet);
        }
        self.acks.release(out);
    }

    /// A PUBCOMP, from the client or on its behalf.
    pub fn complete(&mut self, pkid: u16, packet: Packet, out: &mut Vec<Packet>) {
        if let Some(packet) = self.completions.answer(pkid, packet) {
            out.push(packet);
        }
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

    #[test]
    fn unknown_ids_pass_through() {
        let mut order = AckOrder::default();
        let mut out = Vec::new();
        order.ack(9, puback(9), &mut out);
        assert_eq!(ids(&out), [9]);
    }
}

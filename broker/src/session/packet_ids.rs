//! Packet ids of deliveries as the client sees them, apart from the router's.
//!
//! rumqttd's router numbers each connection's QoS 1/2 deliveries itself, from 1 on every
//! new connection and wrapping at its in-flight window (`[broker] max_inflight_out`). A session needs more of its packet ids than that:
//!
//! - a delivery re-sent when the session resumes keeps its original id [MQTT-4.4.0-1];
//!   with a fresh count it would not, and a QoS 2 receiver could not tell it had the
//!   message already;
//! - an id stays taken until its exchange is complete, PUBACK or PUBCOMP [MQTT-2.2.1-3]:
//!   after a resume the fresh count hands out the id of a QoS 2 message whose PUBREL is
//!   still pending, and the client drops the new message as a duplicate of that one.
//!
//! So the connection numbers deliveries for the client itself and translates at the
//! edges: [`PacketIds::deliver`] gives a delivery its id as it leaves,
//! [`PacketIds::in_router_ids`] maps the client's PUBACK/PUBREC/PUBCOMP back to the router's
//! id as they arrive, [`PacketIds::release`] maps the router's PUBREL as it leaves. Between
//! the edges the packet path (ack order, QoS 2 answered on the client's behalf) works with
//! the router's ids. An id the table does not know passes through unchanged, as it did
//! before fbbus numbered deliveries.
//!
//! When a connection ends with its session kept, [`PacketIds::into_resume`] is what the
//! next connection of the client id starts from ([`PacketIds::resumed`], handed over by
//! `redelivery`): the deliveries the client never acknowledged, by fingerprint and id,
//! and the QoS 2 exchanges waiting for PUBREL or PUBCOMP, by both ids.

use std::collections::VecDeque;

use rumqttd::protocol::Packet;

/// The open exchanges of one connection.
#[derive(Default)]
pub struct PacketIds {
    /// Exchanges not yet complete, in the order they started. Bounded by the router's
    /// in-flight window (`max_inflight_out`) plus the QoS 2 exchanges waiting for PUBCOMP.
    open: VecDeque<Exchange>,
    /// The last id handed out.
    last: u16,
    /// Exchanges still `Unsent` (a resumed session's): while there are none, a delivery
    /// need not be looked up as a re-send.
    unsent: u16,
    /// An open exchange may hold `last + 1` or a later id: it came from an earlier
    /// connection, or the ids wrapped. While false, `last + 1` is free without a search:
    /// every open exchange took its id from this counter, at or below `last`.
    may_collide: bool,
}

/// What a resumed session starts from (see the module doc), and the subscriptions the
/// previous connection made when some use an option the router ignores (No Local, Retain
/// As Published, Retain Handling): the delivery path applies them from the session's own
/// table, which a resumed connection would otherwise start empty.
#[derive(Debug, Default, PartialEq)]
pub struct Resume {
    exchanges: Vec<Exchange>,
    pub subscriptions: std::collections::BTreeMap<String, rumqttd::protocol::Filter>,
}

impl Resume {
    /// Only subscriptions (a session put back from the store at start).
    pub fn with_subscriptions(
        subscriptions: std::collections::BTreeMap<String, rumqttd::protocol::Filter>,
    ) -> Resume {
        Resume {
            exchanges: Vec::new(),
            subscriptions,
        }
    }

    pub fn is_empty(&self) -> bool {
        self.exchanges.is_empty() && self.subscriptions.is_empty()
    }
}

#[derive(Clone, Copy, Debug, PartialEq)]
struct Exchange {
    /// The id the client sees.
    client: u16,
    /// The router's id (meaningless while `Unsent`).
    router: u16,
    stage: Stage,
    /// The message's fingerprint (`redelivery::fingerprint`), to recognise a re-send.
    print: u64,
}

#[derive(Clone, Copy, Debug, PartialEq)]
enum Stage {
    /// Left unacknowledged by an earlier connection; the router re-sends it on resume.
    Unsent,
    /// Sent, no PUBACK or PUBREC yet.
    Sent,
    /// PUBREC received; the router's PUBREL has not left yet.
    Received,
    /// PUBREL sent; waiting for PUBCOMP.
    Released,
}

/// A delivery's id for the client, and whether it is a re-send (DUP=1 [MQTT-3.3.1-1]).
#[derive(Debug, PartialEq)]
pub struct Delivery {
    pub id: u16,
    pub dup: bool,
}

impl PacketIds {
    /// A connection resuming a session that an earlier connection left as `resume`.
    pub fn resumed(resume: Resume) -> PacketIds {
        let open: VecDeque<Exchange> = resume.exchanges.into();
        PacketIds {
            unsent: open.iter().filter(|e| e.stage == Stage::Unsent).count() as u16,
            may_collide: !open.is_empty(),
            open,
            last: 0,
        }
    }

    /// A QoS 1/2 delivery the router numbered `router` leaves for the client. A message
    /// the previous connection left unacknowledged gets its original id back; anything
    /// else gets the next id no open exchange holds.
    pub fn deliver(&mut self, router: u16, print: u64) -> Delivery {
        let resent = (self.unsent > 0)
            .then(|| {
                self.open
                    .iter_mut()
                    .find(|e| e.stage == Stage::Unsent && e.print == print)
            })
            .flatten();
        if let Some(e) = resent {
            self.unsent -= 1;
            e.router = router;
            e.stage = Stage::Sent;
            return Delivery {
                id: e.client,
                dup: true,
            };
        }
        let id = self.free_id();
        self.open.push_back(Exchange {
            client: id,
            router,
            stage: Stage::Sent,
            print,
        });
        Delivery { id, dup: false }
    }

    /// An id for a delivery the router never had (a restored session's backlog,
    /// `persist`): held until [`PacketIds::finish_local`]. Its router id is 0, which the
    /// router never uses.
    pub fn local(&mut self) -> u16 {
        let id = self.free_id();
        self.open.push_back(Exchange {
            client: id,
            router: 0,
            stage: Stage::Sent,
            print: 0,
        });
        id
    }

    /// Holds `id` for a backlog delivery that must keep it (a QoS 2 exchange resumed
    /// after a restart); false when an open exchange already holds it.
    pub fn reserve(&mut self, id: u16) -> bool {
        if id == 0 || self.open.iter().any(|e| e.client == id) {
            return false;
        }
        self.may_collide = true;
        self.open.push_back(Exchange {
            client: id,
            router: 0,
            stage: Stage::Sent,
            print: 0,
        });
        true
    }

    /// The backlog delivery under `id` is complete.
    pub fn finish_local(&mut self, id: u16) {
        if let Some(i) = self
            .open
            .iter()
            .position(|e| e.client == id && e.router == 0)
        {
            self.open.remove(i);
        }
    }

    /// A delivery given an id by [`PacketIds::deliver`] was not sent after all (the packet
    /// path acknowledged it to the router for the client).
    pub fn withdraw(&mut self, id: u16) {
        if let Some(i) = self.position(id, &[Stage::Sent]) {
            self.open.remove(i);
        }
    }

    /// The client's PUBACK, PUBREC or PUBCOMP, with the router's id in place of the
    /// client's. Other packets are returned as they are.
    pub fn in_router_ids(&mut self, mut packet: Packet) -> Packet {
        match &mut packet {
            Packet::PubAck(ack, _) => {
                if let Some(i) = self.position(ack.pkid, &[Stage::Sent]) {
                    ack.pkid = self.open.remove(i).map_or(ack.pkid, |e| e.router);
                }
            }
            Packet::PubRec(rec, _) => {
                if let Some(i) = self.position(rec.pkid, &[Stage::Sent]) {
                    let e = &mut self.open[i];
                    e.stage = Stage::Received;
                    rec.pkid = e.router;
                }
            }
            Packet::PubComp(comp, _) => {
                if let Some(i) = self.position(comp.pkid, &[Stage::Released, Stage::Received]) {
                    comp.pkid = self.open.remove(i).map_or(comp.pkid, |e| e.router);
                }
            }
            _ => {}
        }
        packet
    }

    /// The id the client knows for the router's PUBREL `router`. The router releases in
    /// the order the client's PUBRECs arrived, so it is the oldest exchange at that stage.
    pub fn release(&mut self, router: u16) -> u16 {
        match self
            .open
            .iter_mut()
            .find(|e| e.stage == Stage::Received && e.router == router)
        {
            Some(e) => {
                e.stage = Stage::Released;
                e.client
            }
            None => router,
        }
    }

    /// What the next connection of this session starts from: every delivery without
    /// PUBACK or PUBREC is re-sent by the router, and every PUBREL is sent again [MQTT-4.4.0-1].
    ///
    /// An exchange still `Unsent` here was expected from the router and never came, although
    /// this connection went on to new deliveries (`last > 0`): its message is gone (a
    /// retained message sent at subscribe time, which the router does not re-send, or a
    /// dropped commit-log segment). It is not handed on, or such entries would pile up over
    /// the session's connections, each holding a packet id.
    pub fn into_resume(self) -> Resume {
        let went_on = self.last > 0;
        let exchanges = self
            .open
            .into_iter()
            .filter(|e| !(went_on && e.stage == Stage::Unsent))
            // Backlog deliveries go back to the store, not to the router's re-sends.
            .filter(|e| e.router != 0 || e.stage == Stage::Unsent)
            .map(|mut e| {
                e.stage = match e.stage {
                    Stage::Unsent | Stage::Sent => Stage::Unsent,
                    Stage::Received | Stage::Released => Stage::Received,
                };
                e
            })
            .collect();
        Resume {
            exchanges,
            subscriptions: Default::default(),
        }
    }

    fn position(&self, client: u16, stages: &[Stage]) -> Option<usize> {
        self.open
            .iter()
            .position(|e| e.client == client && stages.contains(&e.stage))
    }

    /// The next id after the last one that no open exchange holds. Ids are 1..=65535
    /// [MQTT-2.2.1-2]; at most a few hundred are open, so the search ends quickly.
    fn free_id(&mut self) -> u16 {
        if self.open.is_empty() {
            self.may_collide = false;
        }
        loop {
            self.last = match self.last.checked_add(1) {
                Some(id) => id,
                None => {
                    self.may_collide = true;
                    1
                }
            };
            let id = self.last;
            if !self.may_collide || !self.open.iter().any(|e| e.client == id) {
                return id;
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use rumqttd::protocol::{PubAck, PubAckReason, PubComp, PubCompReason, PubRec, PubRecReason};

    use super::*;

    fn puback(pkid: u16) -> Packet {
        Packet::PubAck(
            PubAck {
                pkid,
                reason: PubAckReason::Success,
            },
            None,
        )
    }

    fn pubrec(pkid: u16) -> Packet {
        Packet::PubRec(
            PubRec {
                pkid,
                reason: PubRecReason::Success,
            },
            None,
        )
    }

    fn pubcomp(pkid: u16) -> Packet {
        Packet::PubComp(
            PubComp {
                pkid,
                reason: PubCompReason::Success,
            },
            None,
        )
    }

    fn id_of(packet: &Packet) -> u16 {
        match packet {
            Packet::PubAck(a, _) => a.pkid,
            Packet::PubRec(r, _) => r.pkid,
            Packet::PubComp(c, _) => c.pkid,
            _ => unreachable!(),
        }
    }

    #[test]
    fn a_resumed_session_keeps_its_ids_and_the_router_its_own() {
        // First connection: three QoS 1 deliveries, the first acknowledged.
        let mut ids = PacketIds::default();
        for (router, print) in [(1, 10), (2, 20), (3, 30)] {
            assert_eq!(ids.deliver(router, print).id, router);
        }
        assert_eq!(id_of(&ids.in_router_ids(puback(1))), 1);
        let resume = ids.into_resume();

        // The router numbers its re-sends from 1 again; the client sees 2 and 3, with DUP.
        let mut ids = PacketIds::resumed(resume);
        assert_eq!(ids.deliver(1, 20), Delivery { id: 2, dup: true });
        assert_eq!(ids.deliver(2, 30), Delivery { id: 3, dup: true });
        // A new message takes an id no open exchange holds.
        assert_eq!(ids.deliver(3, 40), Delivery { id: 1, dup: false });
        assert_eq!(ids.deliver(4, 50), Delivery { id: 4, dup: false });
        // The client's acknowledgements reach the router with the router's ids.
        for (client, router) in [(2, 1), (3, 2), (1, 3), (4, 4)] {
            assert_eq!(id_of(&ids.in_router_ids(puback(client))), router);
        }
        assert!(ids.into_resume().is_empty());
    }

    #[test]
    fn a_pending_pubrel_keeps_its_id_and_holds_it_across_a_resume() {
        let mut ids = PacketIds::default();
        assert_eq!(ids.deliver(1, 10).id, 1);
        assert_eq!(ids.deliver(2, 20).id, 2);
        // QoS 2: the first is received, released, never completed; the second not received.
        assert_eq!(id_of(&ids.in_router_ids(pubrec(1))), 1);
        assert_eq!(ids.release(1), 1);
        let mut ids = PacketIds::resumed(ids.into_resume());

        // The router sends PUBREL for its id 1 again and re-sends the second message as
        // its id 1 too: the client sees PUBREL 1 and PUBLISH 2.
        assert_eq!(ids.deliver(1, 20), Delivery { id: 2, dup: true });
        assert_eq!(ids.release(1), 1);
        // Id 1 is still held by the exchange that waits for PUBCOMP.
        assert_eq!(ids.deliver(2, 30).id, 3);
        assert_eq!(id_of(&ids.in_router_ids(pubcomp(1))), 1);
        assert_eq!(id_of(&ids.in_router_ids(pubrec(2))), 1);
        assert_eq!(ids.release(1), 2);
        assert_eq!(id_of(&ids.in_router_ids(pubcomp(2))), 1);
        assert_eq!(id_of(&ids.in_router_ids(puback(3))), 2);
        assert!(ids.into_resume().is_empty());
    }

    #[test]
    fn a_resend_that_never_came_is_not_handed_on_once_new_deliveries_went_out() {
        let mut ids = PacketIds::default();
        ids.deliver(1, 10);
        ids.deliver(2, 20);
        // Closed before the router re-sent anything: both are still expected.
        let mut ids = PacketIds::resumed(PacketIds::resumed(ids.into_resume()).into_resume());
        // The router re-sends only the first, then something new.
        assert_eq!(ids.deliver(1, 10), Delivery { id: 1, dup: true });
        assert_eq!(ids.deliver(2, 30), Delivery { id: 3, dup: false });
        let mut ids = PacketIds::resumed(ids.into_resume());
        // 10 and 30 are expected again; 20 is not, and its id is free.
        assert_eq!(ids.deliver(1, 20), Delivery { id: 2, dup: false });
        assert_eq!(ids.deliver(2, 10), Delivery { id: 1, dup: true });
        assert_eq!(ids.deliver(3, 30), Delivery { id: 3, dup: true });
    }

    #[test]
    fn ids_wrap_past_65535_to_1_and_skip_open_ones() {
        let mut ids = PacketIds::default();
        assert_eq!(ids.deliver(1, 1).id, 1);
        ids.last = u16::MAX - 1;
        assert_eq!(ids.deliver(2, 2).id, u16::MAX);
        assert_eq!(ids.deliver(3, 3).id, 2, "1 is still open");
    }

    #[test]
    fn unknown_ids_and_withdrawn_deliveries_pass_through() {
        let mut ids = PacketIds::default();
        assert_eq!(id_of(&ids.in_router_ids(puback(9))), 9);
        assert_eq!(ids.release(7), 7);
        let d = ids.deliver(5, 1);
        ids.withdraw(d.id);
        assert!(ids.into_resume().is_empty());
    }
}

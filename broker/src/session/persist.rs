//! What a session tells the store (`store`), and the backlog a restored session sends
//! first.
//!
//! - **Before routing** ([`Session::store_batch`]): the batch's retained publications and,
//!   while a persistent session subscribes to anything, its QoS 1/2 ones are numbered
//!   (`Origin::stored`) and handed to the store's writer; the router gets them at once,
//!   the client its PUBACK/PUBREC only once they are written ([`durable`](super::durable)).
//! - **A persistent session's** SUBSCRIBE/UNSUBSCRIBE, the start and end of its
//!   connection, and what becomes of each stored message delivered to it: `Done` at the
//!   client's PUBACK/PUBCOMP or when fbbus does not send it (No Local, access rules,
//!   Maximum Packet Size), the QoS 2 step at PUBLISH and PUBREC. These records wait in
//!   `journal` and go out with the next batch.
//! - **The backlog**: what was queued for this session when the broker last stopped. Sent
//!   before anything the router delivers, within the client's Receive Maximum, and
//!   answered here (the router never had it): QoS 2 exchanges resume at the step they had
//!   reached, under their packet ids (a PUBREC'd one gets PUBREL, a sent one is sent
//!   again with DUP=1). What the client has not acknowledged when the connection ends is
//!   handed back to the store for its next connection.

use std::sync::Arc;

use rumqttd::protocol::{
    Filter, Packet, PubRel, PubRelReason, PublishProperties, QoS, RetainForwardRule,
};

use super::durable::Durable;
use super::Session;
use crate::broker_publisher::publish_packet;
use crate::store::{Backlogged, Options, Qos2, Record};

impl Session {
    /// Hands the batch's stored publications and the session's waiting records to the
    /// store, before the batch goes to the router; the client's acknowledgements of those
    /// publications wait for the write ([`durable`](super::durable)).
    pub(super) async fn store_batch(&mut self) {
        let Some(store) = self.ctx.store.clone() else {
            return;
        };
        // The client's packet ids of the stored QoS 1/2 publications: their PUBACK/PUBREC
        // waits for this write.
        let mut acknowledged = Vec::new();
        // `on_publish` worked the share out when it admitted a retained publication.
        let share = self.durable.as_ref().and_then(|d| d.share.as_deref());
        store.record_publications(
            &mut self.to_router,
            &mut self.journal,
            |journal, publish, pkid, seq, rest| {
                if let Some(pkid) = pkid {
                    if acknowledged.capacity() == 0 {
                        acknowledged.reserve(rest);
                    }
                    acknowledged.push((pkid, seq));
                }
                // Whom the retained message is charged to, for a restart (`retained_share`).
                if let (true, false, Some(share)) =
                    (publish.retain, publish.payload.is_empty(), share)
                {
                    if let Ok(topic) = std::str::from_utf8(&publish.topic) {
                        journal.push(Record::RetainedBy {
                            topic: topic.to_owned(),
                            share: share.to_owned(),
                        });
                    }
                }
            },
        );
        let wait = !acknowledged.is_empty();
        let share = wait.then(|| self.share());
        let answer = store.submit(
            &self.client.client_id,
            share.as_ref(),
            &mut self.journal,
            wait,
        );
        if let Some(written) = answer.await {
            self.durable().submitted(&acknowledged, written);
        }
    }

    /// Counts (and logs, once a minute for the broker) the acknowledgements that said
    /// 0x97 because the store did not keep their publication ([`Durable`]).
    pub(super) fn count_refusals(&mut self) {
        let Some(durable) = self.durable.as_mut() else {
            return;
        };
        let n = std::mem::take(&mut durable.refusals_sent);
        if n == 0 {
            return;
        }
        self.ctx
            .metrics
            .limit_refusals
            .with_label_values(&["stored_publications"])
            .inc_by(n.into());
        static LOGGED: crate::logging::OnceAMinute = crate::logging::OnceAMinute::new();
        if LOGGED.due() {
            tracing::warn!(
                client_id = %self.client.client_id,
                share = durable.share.as_deref().unwrap_or_default(),
                refused = n,
                "the store did not keep publications for persistent sessions (its \
                 [persistence] max_bytes, or this identity's max_bytes_per_identity or \
                 max_messages_per_identity, is reached): MQTT 5 publishers are answered 0x97 \
                 Quota exceeded, MQTT 3.1.1 ones cannot be told; see \
                 fbbus_store_not_stored_total (logged once a minute)"
            );
        }
    }

    /// The identity whose store share this session's publications spend, worked out once.
    pub(super) fn share(&mut self) -> Arc<str> {
        if let Some(share) = self.durable.as_ref().and_then(|d| d.share.clone()) {
            return share;
        }
        let owner = self.ctx.identity.owner(self.client.username.as_deref());
        let share: Arc<str> = self
            .ctx
            .identity
            .share(&owner, self.client.address.ip())
            .into();
        self.durable().share = Some(Arc::clone(&share));
        share
    }

    /// The session's store bookkeeping, allocated on first use.
    pub(super) fn durable(&mut self) -> &mut Durable {
        self.durable.get_or_insert_with(Box::default)
    }

    /// Sends the acknowledgements whose publications are written by now.
    pub(super) fn release_written(&mut self) {
        let mut released = Vec::new();
        if let Some(durable) = self.durable.as_mut() {
            durable.confirmed(&mut released);
        }
        self.count_refusals();
        for packet in released {
            self.answer(packet);
        }
    }

    /// Records the filters a persistent session subscribed to.
    pub(super) fn store_subscribed(&mut self, filters: &[&Filter], id: Option<usize>) {
        if !self.persistent {
            return;
        }
        for f in filters {
            self.journal.push(Record::Subscribe {
                client: Arc::clone(&self.client.client_id),
                filter: f.path.clone(),
                options: Options {
                    qos: match f.qos {
                        QoS::AtMostOnce => 0,
                        QoS::AtLeastOnce => 1,
                        QoS::ExactlyOnce => 2,
                    },
                    no_local: f.nolocal,
                    retain_as_published: f.preserve_retain,
                    retain_handling: match f.retain_forward_rule {
                        RetainForwardRule::OnEverySubscribe => 0,
                        RetainForwardRule::OnNewSubscribe => 1,
                        RetainForwardRule::Never => 2,
                    },
                    id: id.unwrap_or(0).min(u32::MAX as usize) as u32,
                },
            });
        }
    }

    pub(super) fn store_unsubscribed(&mut self, filters: &[String]) {
        if !self.persistent {
            return;
        }
        for f in filters {
            self.journal.push(Record::Unsubscribe {
                client: Arc::clone(&self.client.client_id),
                filter: f.clone(),
            });
        }
    }

    /// A stored message (`seq`) the router delivered as `router_pkid` is on its way to the
    /// client as `client_pkid` at `qos` (0: it is not sent after all).
    pub(super) fn store_delivering(&mut self, seq: u64, router_pkid: u16, client_pkid: u16) {
        if self.persistent && seq != 0 {
            self.durable()
                .stored_out
                .insert(router_pkid, (seq, client_pkid));
        }
    }

    /// The delivery `router_pkid` went out at QoS 2.
    pub(super) fn store_sent_qos2(&mut self, router_pkid: u16) {
        let sent = self
            .durable
            .as_ref()
            .and_then(|d| d.stored_out.get(&router_pkid));
        if let Some((seq, client_pkid)) = sent {
            self.journal.push(Record::Qos2 {
                client: Arc::clone(&self.client.client_id),
                seq: *seq,
                state: Qos2::Sent(*client_pkid),
            });
        }
    }

    /// Delivery `router_pkid` is acknowledged towards the router: `done` (PUBACK, PUBCOMP,
    /// or not sent), or PUBREC.
    pub(super) fn store_acked(&mut self, router_pkid: u16, done: bool) {
        let Some(stored_out) = self
            .durable
            .as_mut()
            .map(|d| &mut d.stored_out)
            .filter(|s| !s.is_empty())
        else {
            return;
        };
        if done {
            if let Some((seq, _)) = stored_out.remove(&router_pkid) {
                self.journal.done(seq);
            }
        } else if let Some((seq, client_pkid)) = stored_out.get(&router_pkid) {
            self.journal.push(Record::Qos2 {
                client: Arc::clone(&self.client.client_id),
                seq: *seq,
                state: Qos2::Received(*client_pkid),
            });
        }
    }

    /// Takes a restored session's backlog from the store (a resumed session only).
    pub(super) fn take_backlog(&mut self) {
        let Some(store) = self.ctx.store.clone() else {
            return;
        };
        let backlog = store.take_backlog(&self.client.client_id);
        if backlog.is_empty() {
            return;
        }
        tracing::info!(
            client_id = &*self.client.client_id,
            messages = backlog.len(),
            "sending what was queued for this session before the broker restarted"
        );
        self.rare().backlog.extend(backlog);
    }

    /// Whether backlog messages are still to be sent (router deliveries wait behind them).
    pub(super) fn backlog_waiting(&self) -> bool {
        self.rare.as_ref().is_some_and(|r| !r.backlog.is_empty())
    }

    /// Sends backlog messages while the client's Receive Maximum allows.
    pub(super) fn release_backlog(&mut self) {
        while self.outstanding_out < self.client_receive_max {
            let Some(b) = self.rare.as_mut().and_then(|r| r.backlog.pop_front()) else {
                return;
            };
            let client_pkid = match b.qos2 {
                Some(Qos2::Sent(pkid)) | Some(Qos2::Received(pkid)) => {
                    if !self.ids.reserve(pkid) {
                        // The id is taken by a delivery of this connection: a new one.
                        self.ids.local()
                    } else {
                        pkid
                    }
                }
                None => self.ids.local(),
            };
            match b.qos2 {
                Some(Qos2::Received(_)) => {
                    self.io.queue(Packet::PubRel(
                        PubRel {
                            pkid: client_pkid,
                            reason: PubRelReason::Success,
                        },
                        None,
                    ));
                }
                _ => {
                    let m = &b.message;
                    let publish = publish_packet(
                        m.topic.clone(),
                        m.payload.clone(),
                        b.qos,
                        false,
                        client_pkid,
                    );
                    let properties: Option<Box<PublishProperties>> = m.properties.clone();
                    let before = self.io.write.len();
                    self.io.queue(Packet::Publish(publish, properties));
                    if b.qos2.is_some() && self.io.write.len() > before {
                        // Sent before the restart: DUP=1 [MQTT-3.3.1-1].
                        self.io.write[before] |= 0b0000_1000;
                    }
                    if b.qos == 2 && b.qos2.is_none() {
                        self.journal.push(Record::Qos2 {
                            client: Arc::clone(&self.client.client_id),
                            seq: b.seq,
                            state: Qos2::Sent(client_pkid),
                        });
                    }
                    self.ctx.metrics.messages_out.inc();
                    self.client.sent();
                }
            }
            self.outstanding_out = self.outstanding_out.saturating_add(1);
            let mut b = b;
            if b.qos == 2 && b.qos2.is_none() {
                b.qos2 = Some(Qos2::Sent(client_pkid));
            }
            self.rare().backlog_out.insert(client_pkid, b);
        }
    }

    /// The client's acknowledgement of a backlog message, answered here; false for any
    /// other packet.
    pub(super) fn backlog_ack(&mut self, packet: &Packet) -> bool {
        let Some(rare) = self.rare.as_mut().filter(|r| !r.backlog_out.is_empty()) else {
            return false;
        };
        let client = Arc::clone(&self.client.client_id);
        match packet {
            Packet::PubAck(ack, _) => {
                let Some(b) = rare.backlog_out.remove(&ack.pkid) else {
                    return false;
                };
                self.journal.done(b.seq);
                self.ids.finish_local(ack.pkid);
                self.outstanding_out = self.outstanding_out.saturating_sub(1);
            }
            Packet::PubRec(rec, _) => {
                let Some(b) = rare.backlog_out.get_mut(&rec.pkid) else {
                    return false;
                };
                b.qos2 = Some(Qos2::Received(rec.pkid));
                self.journal.push(Record::Qos2 {
                    client,
                    seq: b.seq,
                    state: Qos2::Received(rec.pkid),
                });
                self.io.queue(Packet::PubRel(
                    PubRel {
                        pkid: rec.pkid,
                        reason: PubRelReason::Success,
                    },
                    None,
                ));
            }
            Packet::PubComp(comp, _) => {
                let Some(b) = rare.backlog_out.remove(&comp.pkid) else {
                    return false;
                };
                self.journal.done(b.seq);
                self.ids.finish_local(comp.pkid);
                self.outstanding_out = self.outstanding_out.saturating_sub(1);
            }
            _ => return false,
        }
        true
    }

    /// The connection ends: what the client has not acknowledged of the backlog goes back
    /// to the store for the session's next connection (a kept session only).
    pub(super) fn return_backlog(&mut self, kept: bool) {
        let (Some(store), Some(rare)) = (self.ctx.store.clone(), self.rare.as_mut()) else {
            return;
        };
        let mut rest: Vec<Backlogged> = std::mem::take(&mut rare.backlog_out)
            .into_values()
            .collect();
        rest.extend(std::mem::take(&mut rare.backlog));
        if kept && !rest.is_empty() {
            rest.sort_by_key(|b| b.seq);
            store.give_back(&self.client.client_id, rest);
        }
    }
}

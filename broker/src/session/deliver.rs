//! Packets from the router to the client: deliveries with the MQTT rules rumqttd's router
//! leaves out and the access rules in force, SUBACKs completed for refused filters,
//! acknowledgements kept in order.

use fb_bridge::topic::filter;
use rumqttd::local::LinkError;
use rumqttd::protocol::{
    Filter, Packet, PubAck, PubAckReason, PubComp, PubCompReason, PubRec, PubRecReason, Publish,
    PublishProperties, RetainForwardRule, SubscribeReasonCode,
};
use rumqttd::Notification;

use super::aliases::{Alias, OutAliases};
use super::close::End;
use super::redelivery::{self};
use super::{Session, HOLD_LIMIT};

/// Encoded bytes after which `deliver` writes out before it encodes more
/// (`broker.slow_consumer_max_bytes` must leave room for one batch and a packet).
pub const WRITE_BATCH: usize = 1024 * 1024;
use crate::policy::origin;
use crate::wire::codec::Version;

impl Session {
    /// Writes what the router delivered, draining everything it has queued.
    ///
    /// What it encodes is written out whenever [`WRITE_BATCH`] bytes are waiting, not only
    /// at the end: one router batch (up to `router_max_outgoing_packets` messages, 64 MB of
    /// large ones) is never copied into one buffer, and each write's deadline
    /// (`session::write`) is for at most a batch, which any client that reads takes in
    /// time. Small messages (a line's usual traffic) still go out in one write per batch.
    pub(super) async fn deliver(&mut self) -> Result<(), End> {
        // Writes the store confirmed since the last wake: the acknowledgements in this
        // batch that waited only for them leave now, not after another wake.
        self.release_written();
        let mut unscheduled = false;
        // With overlapping subscriptions the router's batch is read whole first, so the
        // copies of one message are all known before one is chosen (`copies`).
        let mut batch = Vec::new();
        // A deadline already passed: take what is there, never wait. Read once, not per
        // notification (the clock was 3 % of the worker's samples in a QoS 1 fan-in).
        let now = std::time::Instant::now();
        loop {
            match self.link_rx.recv_deadline(now) {
                Ok(Some(Notification::Unschedule)) => unscheduled = true,
                Ok(Some(notification)) if self.overlapping => batch.push(notification),
                Ok(Some(notification)) => {
                    self.outbound(notification);
                    if self.io.write.len() >= WRITE_BATCH {
                        self.route().await?;
                        self.write_out().await?;
                    }
                }
                Ok(None) => {}
                Err(LinkError::RecvTimeout(_)) => break,
                Err(_) => return Err(self.router_dropped().await),
            }
        }
        for notification in &batch {
            if let Notification::Forward(forward) = notification {
                self.announce_copy(&forward.publish);
            }
        }
        for notification in batch {
            self.outbound(notification);
            if self.io.write.len() >= WRITE_BATCH {
                self.route().await?;
                self.write_out().await?;
            }
        }
        self.route().await?;
        self.write_out().await?;
        if unscheduled {
            if self.held.len() < HOLD_LIMIT {
                self.link_rx.wake().await.map_err(|_| End::Router)?;
            } else {
                self.wake_pending = true;
            }
        }
        Ok(())
    }

    /// The router dropped this link: either a newer connection took the client id over,
    /// or the router refused something this client sent.
    pub(super) async fn router_dropped(&mut self) -> End {
        // What was queued before the drop, briefly: the connection is ending anyway.
        let _ = tokio::time::timeout(std::time::Duration::from_secs(1), self.io.flush()).await;
        if self
            .ctx
            .sessions
            .is_current(&self.client.client_id, self.session)
        {
            tracing::warn!(
                client_id = &*self.client.client_id,
                "the router ended the connection"
            );
            End::Router
        } else {
            End::Takeover
        }
    }

    /// Sends held deliveries while the client's Receive Maximum allows.
    pub(super) fn release_held(&mut self) {
        if self.backlog_waiting() {
            self.release_backlog();
            if self.backlog_waiting() {
                return;
            }
        }
        while self.outstanding_out < self.client_receive_max {
            let Some((publish, properties)) = self.held.pop_front() else {
                break;
            };
            self.held_bytes = self.held_bytes.saturating_sub(held_size(&publish));
            self.deliver_publish(publish, properties);
        }
    }

    /// One packet from the router to the client.
    pub(super) fn outbound(&mut self, notification: Notification) {
        let packet: Option<Packet> = notification.into();
        match packet {
            Some(Packet::SubAck(mut suback, properties)) => {
                let refused = self
                    .rare
                    .as_mut()
                    .and_then(|r| r.partial_subscribes.remove(&suback.pkid));
                if let Some(refused) = refused {
                    let mut granted = suback.return_codes.into_iter();
                    suback.return_codes = refused
                        .into_iter()
                        .map(|r| {
                            r.or_else(|| granted.next())
                                .unwrap_or(SubscribeReasonCode::Unspecified)
                        })
                        .collect();
                }
                self.io.queue(Packet::SubAck(suback, properties));
            }
            Some(Packet::Publish(publish, properties)) => {
                // Order is kept: once something is held, everything after it waits too.
                if self.held.is_empty()
                    && self.outstanding_out < self.client_receive_max
                    && !self.backlog_waiting()
                {
                    self.deliver_publish(publish, properties);
                } else {
                    self.held_bytes += held_size(&publish);
                    self.held.push_back((publish, properties));
                }
            }
            Some(Packet::PubRel(mut pubrel, properties)) => {
                self.ack_order.released(pubrel.pkid);
                if self
                    .rare
                    .as_mut()
                    .is_some_and(|r| r.dropped_qos2.remove(&pubrel.pkid))
                {
                    let complete = Packet::PubComp(
                        PubComp {
                            pkid: pubrel.pkid,
                            reason: PubCompReason::Success,
                        },
                        None,
                    );
                    self.ack_order
                        .complete(pubrel.pkid, complete, &mut self.to_router);
                } else {
                    pubrel.pkid = self.ids.release(pubrel.pkid);
                    self.io.queue(Packet::PubRel(pubrel, properties));
                }
            }
            // An acknowledgement of a stored publication may wait for the store.
            Some(packet) => match self.durable.as_mut() {
                Some(durable) => {
                    if let Some(packet) = durable.pass(packet) {
                        self.count_refusals();
                        self.answer(packet);
                    }
                }
                None => self.answer(packet),
            },
            None => {}
        }
    }

    /// An answer from the router (PUBACK, PUBREC, PUBCOMP, UNSUBACK, PINGRESP) goes to
    /// the client.
    pub(super) fn answer(&mut self, packet: Packet) {
        let ends = match &packet {
            Packet::PubAck(..) | Packet::PubComp(..) => true,
            // An MQTT 5 PUBREC with an error code ends the exchange: no PUBREL follows
            // (a 3.1.1 client sees no code and goes on to PUBREL and PUBCOMP).
            Packet::PubRec(rec, _) if self.version == Version::V5 => {
                let failed = rec.reason != PubRecReason::Success
                    && rec.reason != PubRecReason::NoMatchingSubscribers;
                if failed {
                    if let Some(rare) = self.rare.as_mut() {
                        rare.qos2_routed.remove(&rec.pkid);
                    }
                }
                failed
            }
            _ => false,
        };
        if ends {
            self.inflight_in = self.inflight_in.saturating_sub(1);
        }
        self.io.queue(packet)
    }

    /// Encodes one delivery, applying the MQTT rules rumqttd 0.20's router leaves out, in
    /// this order:
    /// - the subscriptions' options ([`Session::subscription_options`]): No Local and
    ///   Retain Handling 2 may drop the delivery, Retain As Published restores RETAIN;
    /// - the delivery QoS is min(publication QoS, subscription QoS) [MQTT-3.8.4-8]: the
    ///   router sends at the subscription's QoS, so a lower publication QoS is restored from
    ///   the message's `origin`;
    /// - the access rules in force must let the client read the topic
    ///   ([`Session::may_read`]), whichever subscription, however old, matched it;
    /// - a packet over the client's Maximum Packet Size is not sent [MQTT-3.1.2-25].
    ///
    /// A QoS 1/2 delivery goes out under the packet id the client sees (`PacketIds`):
    /// the original id and DUP=1 when it re-sends what an earlier connection of the session
    /// left unacknowledged [MQTT-4.4.0-1] [MQTT-3.3.1-1]. Whatever the client is not sent at
    /// the router's QoS is acknowledged to the router for it ([`Session::ack_for_client`]).
    pub(super) fn deliver_publish(
        &mut self,
        mut publish: Publish,
        properties: Option<Box<PublishProperties>>,
    ) {
        let origin = origin::take(&mut publish);
        let published = origin.as_ref().map(|o| o.qos);
        let stored = origin.as_ref().map_or(0, |o| o.stored);
        let (mut deliver, retain_as_published) =
            self.subscription_options(&publish, origin.as_ref());
        // Whatever subscription matched, and whenever it was made: the rules in force now.
        if deliver && !self.may_read(&publish.topic) {
            deliver = false;
        }
        // Overlapping subscriptions: one copy, with every matching subscription's id.
        let mut properties = properties;
        if let Some(ids) = self.one_copy(&publish, origin.as_ref()) {
            match ids {
                Some(ids) if deliver => {
                    // MQTT 3.1.1 has no identifiers (nor properties to carry them).
                    if self.version == crate::wire::codec::Version::V5 {
                        properties
                            .get_or_insert_with(Default::default)
                            .subscription_identifiers = ids;
                    }
                }
                _ => deliver = false,
            }
        }
        if retain_as_published {
            publish.retain = true;
        }
        // `pkid` stays the router's; the client sees `client_pkid`.
        let (routed_qos, pkid) = publish.qos_and_pkid();
        let (client_pkid, dup) = if routed_qos > 0 {
            let print = redelivery::fingerprint(&publish.topic, &publish.payload);
            let delivery = self.ids.deliver(pkid, print);
            publish.set_pkid(delivery.id);
            (delivery.id, delivery.dup)
        } else {
            (0, false)
        };
        // Topic aliases, for deliveries that are sent (`aliases`).
        let alias_topic = publish.topic.clone();
        let alias = if deliver && self.client_alias_max > 0 {
            self.topic_alias(&mut publish, &mut properties)
        } else {
            None
        };
        let (topic, payload, retain) = (
            publish.topic.clone(),
            publish.payload.clone(),
            publish.retain,
        );
        let may_lower = routed_qos > 0 && matches!(published, Some(0 | 1));
        let kept_properties = if may_lower { properties.clone() } else { None };

        let before = self.io.write.len();
        self.io.queue(Packet::Publish(publish, properties));

        if routed_qos > 0 {
            self.ack_order.delivered(pkid);
            self.store_delivering(stored, pkid, client_pkid);
        }
        if !deliver {
            self.io.write.truncate(before);
            self.ids.withdraw(client_pkid);
            self.ack_for_client(routed_qos, pkid);
            return;
        }
        let qos = published.map_or(routed_qos, |q| q.min(routed_qos));
        if may_lower && qos < routed_qos {
            self.io.write.truncate(before);
            let lower_pkid = if qos == 0 { 0 } else { client_pkid };
            let lower = crate::broker_publisher::publish_packet(
                topic.clone(),
                payload.clone(),
                qos,
                retain,
                lower_pkid,
            );
            self.io.queue(Packet::Publish(lower, kept_properties));
            if qos == 0 {
                self.ids.withdraw(client_pkid);
                self.ack_for_client(routed_qos, pkid);
            } else {
                self.rare().qos2_sent_as_qos1.insert(pkid);
            }
        }

        let size = self.io.write.len() - before;
        match self.client_max_packet {
            Some(max) if size > max => {
                self.io.write.truncate(before);
                if let (Some(Alias::Set(_)), Some(aliases)) = (alias, self.aliases_out.as_mut()) {
                    aliases.forget_last(&alias_topic);
                }
                if let Some(rare) = self.rare.as_mut() {
                    rare.qos2_sent_as_qos1.remove(&pkid);
                }
                if qos > 0 {
                    self.ids.withdraw(client_pkid);
                    self.ack_for_client(routed_qos, pkid);
                }
                self.ctx
                    .metrics
                    .messages_dropped
                    .with_label_values(&["client_max_packet_size"])
                    .inc();
                tracing::debug!(
                    client_id = &*self.client.client_id,
                    size,
                    max,
                    "delivery larger than the client's maximum packet size; dropped"
                );
            }
            _ => {
                self.ctx.metrics.messages_out.inc();
                self.client.sent();
                if qos == 0 {
                    self.qos0_unwritten = self.qos0_unwritten.saturating_add(1);
                } else {
                    self.outstanding_out = self.outstanding_out.saturating_add(1);
                    if dup {
                        self.io.write[before] |= 0b0000_1000;
                    }
                    if qos == 2 {
                        self.store_sent_qos2(pkid);
                    }
                }
            }
        }
    }

    /// The non-shared subscriptions matching `topic` when there are at least two (a
    /// message the router sends once per match): how many, and the identifiers of those
    /// that take it (No Local ones do not take the client's `own` messages). None with
    /// fewer than two, or without overlapping subscriptions.
    fn matching_copies(&self, topic: &[u8], own: bool) -> Option<(usize, Vec<usize>)> {
        if !self.overlapping {
            return None;
        }
        let topic = std::str::from_utf8(topic).ok()?;
        let (mut copies, mut ids) = (0, Vec::new());
        for (path, f) in &self.subscriptions {
            if filter::is_shared(path) || !filter::filter_matches(path, topic) {
                continue;
            }
            copies += 1;
            if own && f.nolocal {
                continue;
            }
            if let Some(id) = self
                .rare
                .as_ref()
                .and_then(|r| r.subscription_ids.get(path))
            {
                ids.push(*id);
            }
        }
        ids.sort_unstable();
        (copies >= 2).then_some((copies, ids))
    }

    /// A copy of a live message is in the router batch being read (`deliver`).
    fn announce_copy(&mut self, publish: &Publish) {
        let Some(origin) = publish.origin.as_ref().filter(|_| !publish.retain) else {
            return;
        };
        let own = origin.publisher == self.client.client_id;
        if let Some((copies, _)) = self.matching_copies(&publish.topic, own) {
            let (routed, _) = publish.qos_and_pkid();
            let seq = origin.seq;
            self.rare()
                .copies
                .announce(seq, &publish.topic, copies, routed);
        }
    }

    /// For a live message matching several overlapping subscriptions: Some(Some(ids))
    /// to send this copy with those Subscription Identifiers, Some(None) to drop it
    /// (another copy carries the message). None: not such a message ([`super::copies`]).
    fn one_copy(
        &mut self,
        publish: &Publish,
        origin: Option<&origin::Origin>,
    ) -> Option<Option<Vec<usize>>> {
        let origin = origin.filter(|_| !publish.retain)?;
        let own = origin.publisher == self.client.client_id;
        let (copies, ids) = self.matching_copies(&publish.topic, own)?;
        let (routed, _) = publish.qos_and_pkid();
        let send =
            self.rare()
                .copies
                .decide(origin.seq, &publish.topic, copies, routed, origin.qos);
        Some(send.then_some(ids))
    }

    /// Puts this connection's topic alias on a delivery the client announced a Topic
    /// Alias Maximum for (policy in [`super::aliases`]): a new alias goes with the topic,
    /// a known one replaces it.
    fn topic_alias(
        &mut self,
        publish: &mut Publish,
        properties: &mut Option<Box<PublishProperties>>,
    ) -> Option<Alias> {
        let max = self.client_alias_max;
        let aliases = match &mut self.aliases_out {
            Some(a) => a,
            none => none.insert(Box::new(OutAliases::new(max)?)),
        };
        let alias = aliases.alias(&publish.topic)?;
        let (Alias::Set(n) | Alias::Use(n)) = alias;
        properties.get_or_insert_with(Default::default).topic_alias = Some(n);
        if let Alias::Use(_) = alias {
            publish.topic = bytes::Bytes::new();
        }
        Some(alias)
    }

    /// What the client's subscription options say about one delivery: whether to send it
    /// (No Local [MQTT-3.8.3-3], Retain Handling 2 [MQTT-3.3.1-11]) and whether to set RETAIN
    /// as published [MQTT-3.3.1-12]. rumqttd's router ignores these options; a delivery
    /// with RETAIN set is a retained message sent at subscribe time (the router clears
    /// RETAIN on live deliveries). When several subscriptions match, the delivery is sent
    /// unless every matching one excludes it.
    pub(super) fn subscription_options(
        &self,
        publish: &Publish,
        origin: Option<&origin::Origin>,
    ) -> (bool, bool) {
        if !self.special_subscriptions {
            return (true, false);
        }
        let Ok(topic) = std::str::from_utf8(&publish.topic) else {
            return (true, false);
        };
        let matching: Vec<&Filter> = self
            .subscriptions
            .iter()
            .filter(|(path, _)| filter::filter_matches(path, topic))
            .map(|(_, f)| f)
            .collect();
        if matching.is_empty() {
            return (true, false);
        }
        let own = origin.is_some_and(|o| o.publisher == self.client.client_id);
        if own && matching.iter().all(|f| f.nolocal) {
            return (false, false);
        }
        if publish.retain
            && matching
                .iter()
                .all(|f| matches!(f.retain_forward_rule, RetainForwardRule::Never))
        {
            return (false, false);
        }
        let retained_origin = origin.is_some_and(|o| o.retain);
        let rap = !publish.retain && retained_origin && matching.iter().any(|f| f.preserve_retain);
        (true, rap)
    }

    /// Acknowledges a delivery to the router on the client's behalf (the client was not
    /// sent it at the router's QoS), so the session's in-flight window does not leak.
    /// At QoS 2 the router answers with PUBREL, which `outbound` completes with PUBCOMP.
    pub(super) fn ack_for_client(&mut self, routed_qos: u8, pkid: u16) {
        self.store_acked(pkid, true);
        let ack = match routed_qos {
            1 => Packet::PubAck(
                PubAck {
                    pkid,
                    reason: PubAckReason::Success,
                },
                None,
            ),
            2 => {
                self.rare().dropped_qos2.insert(pkid);
                Packet::PubRec(
                    PubRec {
                        pkid,
                        reason: PubRecReason::Success,
                    },
                    None,
                )
            }
            _ => return,
        };
        self.ack_order.ack(pkid, ack, &mut self.to_router);
    }
}

/// What a held delivery counts towards the connection's queued bytes
/// (`broker.slow_consumer_max_bytes`): its topic and payload, which it keeps alive.
fn held_size(publish: &Publish) -> usize {
    publish.topic.len() + publish.payload.len()
}

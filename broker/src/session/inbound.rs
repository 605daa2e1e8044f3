//! Packets from the client: one dispatch per packet type (`Session::inbound`), then the
//! PUBLISH and SUBSCRIBE handlers.

use std::borrow::Cow;

use fb_bridge::topic::filter;
use rumqttd::protocol::{
    DisconnectReasonCode, Filter, Packet, PingResp, PubAck, PubAckReason, PubComp, PubCompReason,
    PubRec, PubRecReason, Publish, PublishProperties, RetainForwardRule, SubAck, Subscribe,
    SubscribeProperties, SubscribeReasonCode,
};
use security::Identity;

use super::close::End;
use super::{copies, Session, MAX_LOGGED_DENIALS};
use crate::policy::origin;
use crate::policy::typed::Refusal;
use crate::policy::{Admission, Door, Publication, Stage};
use crate::wire::codec::Version;

/// The Topic Alias Maximum rumqttd's router announces in CONNACK.
const TOPIC_ALIAS_MAX: u16 = 4096;

impl Session {
    /// The packet path for one packet from the client (see the module doc).
    pub(super) fn inbound(&mut self, packet: Packet) -> Result<(), End> {
        // A restored session's backlog is answered here, never by the router (`persist`).
        if self.backlog_ack(&packet) {
            return Ok(());
        }
        // Acknowledgements of deliveries carry the client's packet ids; from here on the
        // packet path works with the router's (`packet_ids`).
        let packet = self.ids.in_router_ids(packet);
        match packet {
            Packet::Publish(publish, properties) => {
                let (qos, pkid) = publish.qos_and_pkid();
                self.on_publish(publish, properties, qos, pkid)
            }
            Packet::Subscribe(subscribe, properties) => {
                self.on_subscribe(subscribe, properties);
                Ok(())
            }
            Packet::PubRel(pubrel, _) => {
                // The router knows only the QoS 2 publications this connection routed: a
                // PUBREL for another (refused, consumed, or one an earlier connection or an
                // earlier run of fbbus already routed and answered with PUBREC) ends here;
                // the router drops a connection that releases a packet id it never saw.
                let routed = self
                    .rare
                    .as_mut()
                    .is_some_and(|r| r.qos2_routed.remove(&pubrel.pkid));
                let refused = self
                    .rare
                    .as_mut()
                    .is_some_and(|r| r.refused_qos2.remove(&pubrel.pkid));
                if !routed {
                    // A refused QoS 2 exchange ends here with "not found" (MQTT 5); one an
                    // earlier connection routed (before a reconnect or a restart) with
                    // success: the message went on when its PUBREC was sent.
                    let reason = match self.version {
                        Version::V5 if refused => PubCompReason::PacketIdentifierNotFound,
                        _ => PubCompReason::Success,
                    };
                    self.io.queue(Packet::PubComp(
                        PubComp {
                            pkid: pubrel.pkid,
                            reason,
                        },
                        None,
                    ));
                } else {
                    // rumqttd 0.20 ignores a PUBREL carrying MQTT 5 properties (reason
                    // string, user properties), which mean nothing to the router anyway.
                    self.to_router.push(Packet::PubRel(pubrel, None));
                }
                Ok(())
            }
            Packet::PubAck(ack, _)
                if self
                    .rare
                    .as_mut()
                    .is_some_and(|r| r.qos2_sent_as_qos1.remove(&ack.pkid)) =>
            {
                self.outstanding_out = self.outstanding_out.saturating_sub(1);
                self.ack_for_client(2, ack.pkid);
                Ok(())
            }
            Packet::PubAck(ack, properties) => {
                self.outstanding_out = self.outstanding_out.saturating_sub(1);
                let pkid = ack.pkid;
                self.store_acked(pkid, true);
                let packet = Packet::PubAck(ack, properties);
                self.ack_order.ack(pkid, packet, &mut self.to_router);
                Ok(())
            }
            Packet::PubRec(rec, properties) => {
                let pkid = rec.pkid;
                self.store_acked(pkid, false);
                let packet = Packet::PubRec(rec, properties);
                self.ack_order.ack(pkid, packet, &mut self.to_router);
                Ok(())
            }
            Packet::PubComp(comp, properties) => {
                self.outstanding_out = self.outstanding_out.saturating_sub(1);
                let pkid = comp.pkid;
                self.store_acked(pkid, true);
                let packet = Packet::PubComp(comp, properties);
                self.ack_order.complete(pkid, packet, &mut self.to_router);
                Ok(())
            }
            Packet::Unsubscribe(unsubscribe, properties) => {
                for f in &unsubscribe.filters {
                    if self.subscriptions.contains_key(f) {
                        self.ctx.observers.unsubscribed(f);
                    }
                }
                self.remember_subscriptions(std::iter::empty(), &unsubscribe.filters);
                self.store_unsubscribed(&unsubscribe.filters);
                self.to_router
                    .push(Packet::Unsubscribe(unsubscribe, properties));
                Ok(())
            }
            Packet::PingReq(_) => {
                self.io.queue(Packet::PingResp(PingResp));
                Ok(())
            }
            Packet::Disconnect(disconnect, properties) => {
                let expiry = properties.and_then(|p| p.session_expiry_interval);
                if let Some(expiry) = expiry.filter(|_| self.version == Version::V5) {
                    let Some(lifetime) = self.lifetime.on_disconnect(expiry) else {
                        if crate::logging::OUTSIDE.allow() {
                            tracing::warn!(
                                client_id = &*self.client.client_id,
                                session_expiry = expiry,
                                "DISCONNECT sets a Session Expiry Interval after CONNECT's 0; \
                                 protocol error"
                            );
                        }
                        return Err(End::ProtocolError(DisconnectReasonCode::ProtocolError));
                    };
                    self.lifetime = lifetime;
                    if let Some(will) = self.will.as_mut() {
                        will.set_session_expiry(expiry);
                    }
                }
                Err(End::Client {
                    with_will: disconnect.reason_code
                        == DisconnectReasonCode::DisconnectWithWillMessage,
                })
            }
            Packet::Connect(..) => {
                if crate::logging::OUTSIDE.allow() {
                    tracing::warn!(
                        client_id = &*self.client.client_id,
                        "second CONNECT; connection closed"
                    );
                }
                Err(End::ProtocolError(DisconnectReasonCode::ProtocolError))
            }
            // Server-only types never get here: `decode_frame` refuses them.
            _ => Err(End::ProtocolError(DisconnectReasonCode::ProtocolError)),
        }
    }

    pub(super) fn on_publish(
        &mut self,
        publish: Publish,
        properties: Option<Box<PublishProperties>>,
        qos: u8,
        pkid: u16,
    ) -> Result<(), End> {
        // The topic is read in place: only an alias makes a new string.
        let mut publish = publish;
        let raw = std::mem::take(&mut publish.topic);
        let topic = self.resolve_topic(&raw, properties.as_deref())?;
        if self.ctx.test_panic_topic.as_deref() == Some(&*topic) {
            panic!(
                "test_panic_topic: {} published on {topic}",
                self.client.client_id
            );
        }

        // The publish policy: access, typed check, origin mark (`policy`).
        let publication = Publication {
            topic: &topic,
            payload: &publish.payload,
            qos,
            retain: publish.retain,
        };
        let admission = self.ctx.policy.admit(
            Door::Client,
            &mut self.fb,
            &self.client.client_id,
            publication,
        );
        // A publication may have made this connection a profiled device's (topics-only).
        if self.keep_alive.is_some() {
            self.relax_keep_alive();
        }
        let (origin, routes) = match admission {
            Admission::Route { origin, routes } => (origin, routes),
            Admission::Consumed => {
                self.acknowledge_consumed(qos, pkid);
                return Ok(());
            }
            Admission::Refused { stage, refusal } => {
                if stage == Stage::Access {
                    self.log_denial("publish", &topic);
                }
                self.refuse_publish(qos, pkid, refusal);
                return Ok(());
            }
        };

        // Route and meter. The router gets the full topic, never an alias.
        if qos > 0 {
            self.inflight_in = self.inflight_in.saturating_add(1);
            if self.version == Version::V5 && self.inflight_in > self.ctx.max_inflight {
                if crate::logging::OUTSIDE.allow() {
                    tracing::warn!(client_id = &*self.client.client_id, receive_maximum = self.ctx.max_inflight,
                        "more unacknowledged QoS 1/2 publications than the Receive Maximum; connection closed");
                }
                return Err(End::ProtocolError(
                    DisconnectReasonCode::ReceiveMaximumExceeded,
                ));
            }
        }
        let mut properties = properties;
        if publish.retain {
            // Charged to the publisher's share as the message subscribers will get: the
            // canonical encoding of a typed message.
            let (retained_topic, payload_len) = match routes.as_ref().and_then(|r| r.first()) {
                Some((t, p)) => (t.as_str(), p.len()),
                None => (&*topic, publish.payload.len()),
            };
            let size = retained_topic.len() + payload_len;
            let clear = publish.payload.is_empty();
            if !self.retained_admitted(retained_topic, size, clear, qos, pkid) {
                publish.retain = false;
            }
        }
        if let Some(p) = properties.as_mut() {
            p.topic_alias = None;
        }
        publish.topic = match topic {
            Cow::Borrowed(_) => raw,
            Cow::Owned(aliased) => aliased.into(),
        };
        let retain = publish.retain;
        self.ctx.metrics.messages_in.inc();
        self.client.received();
        let mut routes = routes.unwrap_or_default().into_iter();
        if let Some((topic, payload)) = routes.next() {
            // A typed message: the canonical encoding travels at the publication's QoS and
            // packet id (the router acknowledges it), the re-encodings as QoS 0 copies
            // carrying the same origin, so subscribers get them at the same delivery QoS.
            for (topic, payload) in routes {
                let mut copy =
                    crate::broker_publisher::publish_packet(topic, payload, 0, retain, 0);
                origin::mark(&mut copy, origin.clone());
                self.to_router
                    .push(Packet::Publish(copy, properties.clone()));
            }
            publish.topic = topic.into();
            publish.payload = payload;
        }
        origin::mark(&mut publish, origin);
        self.to_router.push(Packet::Publish(publish, properties));
        if qos == 2 {
            self.rare().qos2_routed.insert(pkid);
        }
        Ok(())
    }

    /// Whether the publisher's share lets this retained publication be retained
    /// (`retained_share`). If not, it is routed without RETAIN, its MQTT 5 acknowledgement
    /// says 0x97, and the refusal is counted and logged once a minute.
    fn retained_admitted(
        &mut self,
        topic: &str,
        size: usize,
        clear: bool,
        qos: u8,
        pkid: u16,
    ) -> bool {
        let share = self.share();
        if self.ctx.retained_shares.admit(&share, topic, size, clear) {
            return true;
        }
        if qos > 0 {
            self.durable().refuse_retained(pkid);
        }
        self.ctx
            .metrics
            .limit_refusals
            .with_label_values(&["retained_per_identity"])
            .inc();
        static LOGGED: crate::logging::OnceAMinute = crate::logging::OnceAMinute::new();
        if LOGGED.due() {
            tracing::warn!(
                client_id = &*self.client.client_id,
                share = &*share,
                "a retained publication was delivered but not retained: its identity holds \
                 [broker] max_retained_messages_per_identity or max_retained_bytes_per_identity \
                 (MQTT 5: 0x97 Quota exceeded); see fbbus_limit_refusals_total \
                 (logged once a minute)"
            );
        }
        false
    }

    /// Acknowledges a publication the broker consumed (a declaration).
    pub(super) fn acknowledge_consumed(&mut self, qos: u8, pkid: u16) {
        match qos {
            1 => self.io.queue(Packet::PubAck(
                PubAck {
                    pkid,
                    reason: PubAckReason::Success,
                },
                None,
            )),
            2 => {
                self.io.queue(Packet::PubRec(
                    PubRec {
                        pkid,
                        reason: PubRecReason::Success,
                    },
                    None,
                ));
                // Its PUBREL is answered here with success (`inbound`, PubRel): the router
                // never saw it, and it is not a refused one.
            }
            _ => {}
        }
    }

    /// The topic a PUBLISH goes to, following MQTT 5 topic aliases.
    pub(super) fn resolve_topic<'t>(
        &mut self,
        raw: &'t [u8],
        properties: Option<&PublishProperties>,
    ) -> Result<Cow<'t, str>, End> {
        let Ok(topic) = std::str::from_utf8(raw) else {
            return Err(End::Malformed);
        };
        let alias = properties.and_then(|p| p.topic_alias);
        let topic = match (topic.is_empty(), alias) {
            (_, Some(alias)) if alias == 0 || alias > TOPIC_ALIAS_MAX => {
                return Err(End::ProtocolError(DisconnectReasonCode::TopicAliasInvalid))
            }
            (false, Some(alias)) => {
                self.rare().topic_aliases.insert(alias, topic.to_owned());
                Cow::Borrowed(topic)
            }
            (false, None) => Cow::Borrowed(topic),
            (true, Some(alias)) => {
                match self.rare.as_ref().and_then(|r| r.topic_aliases.get(&alias)) {
                    Some(t) => Cow::Owned(t.clone()),
                    None => {
                        return Err(End::ProtocolError(DisconnectReasonCode::TopicAliasInvalid))
                    }
                }
            }
            (true, None) => return Err(End::ProtocolError(DisconnectReasonCode::TopicNameInvalid)),
        };
        if !filter::valid_topic(&topic) {
            if crate::logging::OUTSIDE.allow() {
                tracing::warn!(
                    client_id = &*self.client.client_id,
                    ?topic,
                    "invalid topic name in PUBLISH; connection closed"
                );
            }
            return Err(End::ProtocolError(DisconnectReasonCode::TopicNameInvalid));
        }
        Ok(topic)
    }

    /// Answers a refused publication. MQTT 5 says "not authorized"; MQTT 3.1.1 has no way
    /// to refuse a PUBLISH, so like Mosquitto it is acknowledged and dropped — otherwise
    /// the device's in-flight window would fill with retries that can never succeed.
    pub(super) fn refuse_publish(&mut self, qos: u8, pkid: u16, refusal: Refusal) {
        let v5 = self.version == Version::V5;
        let (ack, rec) = match (v5, refusal) {
            (false, _) => (PubAckReason::Success, PubRecReason::Success),
            (true, Refusal::NotAuthorized) => {
                (PubAckReason::NotAuthorized, PubRecReason::NotAuthorized)
            }
            (true, Refusal::TopicNameInvalid) => (
                PubAckReason::TopicNameInvalid,
                PubRecReason::TopicNameInvalid,
            ),
            (true, Refusal::PayloadFormatInvalid) => (
                PubAckReason::PayloadFormatInvalid,
                PubRecReason::PayloadFormatInvalid,
            ),
            (true, Refusal::QuotaExceeded) => {
                (PubAckReason::QuotaExceeded, PubRecReason::QuotaExceeded)
            }
        };
        match qos {
            1 => self
                .io
                .queue(Packet::PubAck(PubAck { pkid, reason: ack }, None)),
            2 => {
                self.io
                    .queue(Packet::PubRec(PubRec { pkid, reason: rec }, None));
                // MQTT 5 clients should not send PUBREL after a refusing PUBREC; some
                // (paho 2.2) do, so the id is remembered for both versions.
                self.rare().refused_qos2.insert(pkid);
            }
            _ => {}
        }
    }

    pub(super) fn on_subscribe(
        &mut self,
        subscribe: Subscribe,
        properties: Option<SubscribeProperties>,
    ) {
        let v5 = self.version == Version::V5;
        let mut refused = Vec::with_capacity(subscribe.filters.len());
        let mut held = self.subscriptions.len();
        for filter in &subscribe.filters {
            let verdict = if !filter::valid_filter(&filter.path) {
                Some(if v5 {
                    SubscribeReasonCode::TopicFilterInvalid
                } else {
                    SubscribeReasonCode::Failure
                })
            } else if !self.may_subscribe(&filter.path) {
                self.ctx
                    .metrics
                    .acl_denied
                    .with_label_values(&["subscribe"])
                    .inc();
                self.log_denial("subscribe", &filter.path);
                Some(if v5 {
                    SubscribeReasonCode::NotAuthorized
                } else {
                    SubscribeReasonCode::Failure
                })
            } else if !self.subscriptions.contains_key(&filter.path)
                && held >= self.ctx.max_subscriptions
            {
                self.ctx
                    .metrics
                    .limit_refusals
                    .with_label_values(&["subscriptions_per_client"])
                    .inc();
                let first = self
                    .rare()
                    .logged_denials
                    .insert(("max_subscriptions_per_client", String::new()));
                if first && crate::logging::OUTSIDE.allow() {
                    tracing::warn!(
                        client_id = &*self.client.client_id,
                        limit = self.ctx.max_subscriptions,
                        "SUBSCRIBE beyond [broker] max_subscriptions_per_client refused \
                         (logged once per connection; fbbus_limit_refusals_total)"
                    );
                }
                Some(if v5 {
                    SubscribeReasonCode::QuotaExceeded
                } else {
                    SubscribeReasonCode::Failure
                })
            } else if filter::is_dollar(&filter.path)
                && !filter::is_shared(&filter.path)
                && !security::acl::is_sys(&filter.path)
            {
                // fbbus publishes nothing under `$` topics but `$SYS/`, and rumqttd's router
                // drops a connection that subscribes to another: refuse the filter, keep the
                // client.
                Some(if v5 {
                    SubscribeReasonCode::ImplementationSpecific
                } else {
                    SubscribeReasonCode::Failure
                })
            } else {
                None
            };
            if verdict.is_none() && !self.subscriptions.contains_key(&filter.path) {
                held += 1;
            }
            refused.push(verdict);
        }

        let granted = subscribe
            .filters
            .iter()
            .zip(&refused)
            .filter(|(_, r)| r.is_none())
            .map(|(f, _)| f);
        let granted: Vec<&Filter> = granted.collect();
        for filter in &granted {
            if !self.subscriptions.contains_key(&filter.path) {
                self.ctx.observers.subscribed(&filter.path);
            }
            // A topics-only device's input topic: this connection may be that device.
            self.fb.granted_subscription(&self.ctx.fb, &filter.path);
        }
        self.store_subscribed(&granted, properties.as_ref().and_then(|p| p.id));
        let id = properties.as_ref().and_then(|p| p.id);
        if id.is_some()
            || self
                .rare
                .as_ref()
                .is_some_and(|r| !r.subscription_ids.is_empty())
        {
            let ids = &mut self.rare().subscription_ids;
            for filter in &granted {
                match id {
                    Some(id) => ids.insert(filter.path.clone(), id),
                    None => ids.remove(&filter.path),
                };
            }
        }
        self.remember_subscriptions(granted.into_iter(), &[]);
        if refused.iter().all(Option::is_none) {
            self.to_router
                .push(Packet::Subscribe(subscribe, properties));
            return;
        }
        if refused.iter().all(Option::is_some) {
            let return_codes = refused.into_iter().flatten().collect();
            self.io.queue(Packet::SubAck(
                SubAck {
                    pkid: subscribe.pkid,
                    return_codes,
                },
                None,
            ));
            return;
        }
        // Some filters allowed: the router gets those, and its SUBACK is completed with the
        // refusals in `outbound` so the client sees one code per filter, in order.
        let allowed = subscribe
            .filters
            .into_iter()
            .zip(&refused)
            .filter(|(_, r)| r.is_none())
            .map(|(f, _)| f)
            .collect();
        self.rare()
            .partial_subscribes
            .insert(subscribe.pkid, refused);
        self.to_router.push(Packet::Subscribe(
            Subscribe {
                pkid: subscribe.pkid,
                filters: allowed,
            },
            properties,
        ));
    }

    /// Records the client's subscriptions and whether any uses an option the router ignores.
    pub(super) fn remember_subscriptions<'a>(
        &mut self,
        added: impl Iterator<Item = &'a Filter>,
        removed: &[String],
    ) {
        for f in added {
            self.subscriptions.insert(f.path.clone(), f.clone());
        }
        for path in removed {
            self.subscriptions.remove(path);
            if let Some(rare) = self.rare.as_mut() {
                rare.subscription_ids.remove(path);
            }
        }
        self.client.set_subscriptions(self.subscriptions.len());
        let own: Vec<&str> = self
            .subscriptions
            .keys()
            .map(String::as_str)
            .filter(|f| !filter::is_shared(f))
            .collect();
        // Pairwise for the usual few filters; a client with hundreds is assumed to overlap.
        self.overlapping = own.len() > 256
            || own
                .iter()
                .enumerate()
                .any(|(i, a)| own[i + 1..].iter().any(|b| copies::filters_overlap(a, b)));
        self.special_subscriptions = self.subscriptions.values().any(|f| {
            f.nolocal
                || f.preserve_retain
                || matches!(f.retain_forward_rule, RetainForwardRule::Never)
        });
    }

    pub(super) fn identity(&self) -> Identity<'_> {
        Identity {
            username: self.client.username.as_deref(),
            client_id: &self.client.client_id,
        }
    }

    pub(super) fn may_subscribe(&self, filter: &str) -> bool {
        let access = self.ctx.policy.access();
        if security::acl::is_sys(filter) {
            return access.can_subscribe_sys(self.identity(), self.on_loopback(), filter);
        }
        access.can_subscribe(self.identity(), filter)
    }

    /// Whether this client connected from the broker's own host (the `$SYS` rule).
    pub(super) fn on_loopback(&self) -> bool {
        self.client.address.ip().to_canonical().is_loopback()
    }

    pub(super) fn log_denial(&mut self, action: &'static str, topic: &str) {
        let logged = &mut self.rare().logged_denials;
        if logged.len() >= MAX_LOGGED_DENIALS {
            return;
        }
        if logged.insert((action, topic.to_owned())) && crate::logging::OUTSIDE.allow() {
            tracing::warn!(
                client_id = &*self.client.client_id,
                username = self.client.username.as_deref().unwrap_or(""),
                action,
                topic = ?topic,
                "denied by ACL (logged once per client and topic)"
            );
        }
    }
}

//! Export: what other lines are interested in leaves this line through the router's
//! export link, stamped, one hop only.
//!
//! Another line's interest is a filter it subscribed to (its liveliness token). Each
//! exported message is matched against every filter held, so how many are held is the
//! export path's cost and a peer's way to grow this line: one line holds at most
//! `[bridge] max_remote_filters_per_line` here, all lines together `max_remote_filters`
//! ([`Shares`]). A filter beyond them is not honoured (that line's clients do not get this
//! line's messages through it) until the line declares it again, counted in
//! `fbbus_limit_refusals_total{limit="remote_subscriptions_per_line"|"remote_subscriptions"}`.

use std::collections::HashMap;
use std::sync::Arc;

use fb_bridge::bus::{keys, BusConfig};
use fb_bridge::interface::OutputPort;
use fb_bridge::topic::{filter, TypedTopic};
use rumqttd::local::{LinkRx, LinkTx};
use rumqttd::protocol::{
    Filter, Packet, PubAck, PubAckReason, QoS, RetainForwardRule, Subscribe, Unsubscribe,
};
use tokio::sync::mpsc;

use super::{EXPORT_FILTER, IMPORT_CLIENT_ID};
use crate::broker_publisher;
use crate::link;
use crate::logging::OnceAMinute;
use crate::policy::origin;
use crate::session::Context;

/// Subscribes to what other lines want, and puts what this line's clients publish there.
pub(super) async fn export_loop(
    exporter: fb_bridge::bus::link::Exporter,
    (mut tx, mut rx): (LinkTx, LinkRx),
    mut remote: mpsc::UnboundedReceiver<(bool, String, String)>,
    ctx: Arc<Context>,
    shares: Shares,
) {
    let mut exports = Exports {
        exporter,
        interest: HashMap::new(),
        per_line: HashMap::new(),
        held: 0,
        is_event: HashMap::new(),
        shares,
        exported: ctx.metrics.bridge_messages.with_label_values(&["export"]),
        ctx,
    };
    let mut forwards = Vec::new();
    loop {
        tokio::select! {
            change = remote.recv() => {
                let Some((added, line, filter)) = change else { return };
                if let Some(packet) = exports.interest_changed(added, line, filter) {
                    if tx.send(packet).await.is_err() {
                        return;
                    }
                }
            }
            notification = rx.next() => {
                let Ok(first) = notification else { return };
                // Everything the router delivered at once is exported, then acknowledged
                // in one go: one router wake-up per batch, not one per message.
                let taken = link::take_batch(&mut rx, first, |f| forwards.push(f));
                let mut acks = Vec::new();
                for forward in forwards.drain(..) {
                    acks.extend(exports.forward(forward).await);
                }
                let Ok(paused) = taken else { return };
                if let Some(last) = acks.pop() {
                    tx.buffer().extend(acks);
                    if tx.send(last).await.is_err() {
                        return;
                    }
                }
                if paused.resume(&rx).await.is_err() {
                    return;
                }
            }
        }
    }
}

/// What may leave (`[bridge] export`), and how many filters the other lines may hold.
pub(super) struct Shares {
    pub export: Vec<String>,
    /// `[bridge] max_remote_filters_per_line`
    pub per_line: usize,
    /// `[bridge] max_remote_filters`
    pub all: usize,
}

/// The exporting side's state: what the other lines want, and which topics are events.
struct Exports {
    exporter: fb_bridge::bus::link::Exporter,
    /// filter -> lines interested in it
    interest: HashMap<String, std::collections::HashSet<String>>,
    /// line -> how many filters it holds (only lines holding some)
    per_line: HashMap<String, usize>,
    /// (line, filter) pairs held
    held: usize,
    is_event: HashMap<String, bool>,
    shares: Shares,
    /// `fbbus_bridge_messages_total{direction="export"}`, looked up once.
    exported: prometheus::IntCounter,
    ctx: Arc<Context>,
}

impl Exports {
    /// Another line's interest in `filter` came or went; returns the router subscription
    /// change, if any.
    fn interest_changed(&mut self, added: bool, line: String, filter: String) -> Option<Packet> {
        if !keys::bridgeable_filter(&filter) {
            return None;
        }
        let held = self
            .interest
            .get(&filter)
            .is_some_and(|lines| lines.contains(&line));
        if added == held {
            return None;
        }
        if added && !self.within_shares(&line, &filter) {
            return None;
        }
        let was_empty = self.interest.is_empty();
        let lines = self.interest.entry(filter.clone()).or_default();
        let of_line = self.per_line.entry(line.clone()).or_default();
        if added {
            lines.insert(line);
            *of_line += 1;
            self.held += 1;
        } else {
            lines.remove(&line);
            *of_line -= 1;
            self.held -= 1;
            if *of_line == 0 {
                self.per_line.remove(&line);
            }
        }
        if lines.is_empty() {
            self.interest.remove(&filter);
        }
        self.ctx
            .metrics
            .bridge_remote_subscriptions
            .add(if added { 1 } else { -1 });
        // One router subscription to the whole typed namespace while anyone is
        // interested: one filter cannot deliver a message twice, which overlapping
        // per-interest filters would. What leaves is decided per message against the
        // interest set ([`Exports::forward`]), and zenoh sends each put only to the lines
        // whose subscribers match.
        if was_empty && !self.interest.is_empty() {
            Some(Packet::Subscribe(
                Subscribe {
                    pkid: 0,
                    filters: vec![Filter {
                        path: EXPORT_FILTER.to_owned(),
                        qos: QoS::AtLeastOnce,
                        nolocal: false,
                        preserve_retain: true,
                        retain_forward_rule: RetainForwardRule::Never,
                    }],
                },
                None,
            ))
        } else if !was_empty && self.interest.is_empty() {
            Some(Packet::Unsubscribe(
                Unsubscribe {
                    pkid: 0,
                    filters: vec![EXPORT_FILTER.to_owned()],
                },
                None,
            ))
        } else {
            None
        }
    }

    /// Whether `line` may hold one more filter here; counts and logs a refusal.
    fn within_shares(&self, line: &str, filter: &str) -> bool {
        static LOGGED: OnceAMinute = OnceAMinute::new();
        let of_line = self.per_line.get(line).copied().unwrap_or(0);
        let (limit, value) = if of_line >= self.shares.per_line {
            ("remote_subscriptions_per_line", self.shares.per_line)
        } else if self.held >= self.shares.all {
            ("remote_subscriptions", self.shares.all)
        } else {
            return true;
        };
        self.ctx
            .metrics
            .limit_refusals
            .with_label_values(&[limit])
            .inc();
        if LOGGED.due() {
            tracing::warn!(
                line,
                filter,
                limit,
                "another line's subscription not honoured: [bridge] max_{} = {value} \
                 reached; its clients do not get this line's messages through it \
                 (logged at most once a minute; fbbus_limit_refusals_total)",
                limit.replace("subscriptions", "filters")
            );
        }
        false
    }

    /// Puts one delivery of the router on the bus if another line wants it; returns the
    /// acknowledgement the router expects (a QoS 1 delivery), sent once zenoh took it.
    async fn forward(&mut self, forward: rumqttd::Forward) -> Option<Packet> {
        let mut publish = forward.publish;
        let origin = origin::take(&mut publish);
        let (routed_qos, pkid) = broker_publisher::qos_and_pkid(&publish);
        let from_bus = origin
            .as_ref()
            .is_some_and(|o| &*o.publisher == IMPORT_CLIENT_ID);
        // A forgotten device's values, cleared by its registry: every line forgets the
        // device and clears them itself when it hears of it (`federation`).
        let forgotten_clear = publish.payload.is_empty()
            && origin
                .as_ref()
                .is_some_and(|o| o.retain && &*o.publisher == broker_publisher::INTERNAL_CLIENT_ID);
        let topic = String::from_utf8_lossy(&publish.topic).into_owned();
        // rumqttd replays retained messages on every subscribe (it ignores Retain
        // Handling): those reach other lines by query, not here.
        let replay = publish.retain;
        let wanted = !from_bus
            && !forgotten_clear
            && !replay
            && BusConfig::allows(&self.shares.export, &topic)
            && self.interest.keys().any(|f| filter::matches(f, &topic));
        if wanted {
            let ctx = &self.ctx;
            let event = match self.is_event.get(&topic) {
                Some(&event) => event,
                None => {
                    let event = event_port(ctx, &topic);
                    self.is_event.insert(topic.clone(), event);
                    event
                }
            };
            let qos = origin
                .as_ref()
                .map_or(routed_qos, |o| o.qos.min(routed_qos));
            let retain = origin.as_ref().is_some_and(|o| o.retain);
            let payload = std::mem::take(&mut publish.payload);
            let metrics = &self.ctx.metrics;
            match self
                .exporter
                .export(&topic, payload, qos, retain, event)
                .await
            {
                Ok(true) => self.exported.inc(),
                Ok(false) => metrics
                    .bridge_dropped
                    .with_label_values(&["unbridgeable"])
                    .inc(),
                Err(e) => {
                    metrics
                        .bridge_dropped
                        .with_label_values(&["zenoh_error"])
                        .inc();
                    tracing::warn!(topic, error = %e, "not exported");
                }
            }
        }
        if self.is_event.len() > 100_000 {
            self.is_event.clear();
        }
        (routed_qos > 0).then(|| {
            Packet::PubAck(
                PubAck {
                    pkid,
                    reason: PubAckReason::Success,
                },
                None,
            )
        })
    }
}

/// Whether `topic` is an event output of a local device (events travel at a higher
/// priority than data).
pub(super) fn event_port(ctx: &Context, topic: &str) -> bool {
    let Some(typed) = TypedTopic::parse(topic) else {
        return false;
    };
    ctx.fb.registry.get(typed.device).is_some_and(|r| {
        matches!(
            r.interface.output(typed.fb, typed.port),
            Some(OutputPort::Event(_))
        )
    })
}

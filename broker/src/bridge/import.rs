//! Import: what local clients subscribe to is imported from the other lines, and what
//! arrives passes the publish policy (`Door::Bus`) before it enters the router.

use std::collections::HashMap;
use std::sync::Arc;
use std::time::{Duration, Instant};

use bytes::Bytes;
use fb_bridge::bus::link::{Import, Inbound, Inbox, Link, RouteKeys};
use fb_bridge::bus::{BusConfig, Dedup, Gaps};
use fb_bridge::topic::TypedTopic;
use rumqttd::local::{LinkRx, LinkTx};
use rumqttd::protocol::Packet;
use tokio::sync::mpsc;

use super::{Interest, IMPORT_CLIENT_ID};
use crate::broker_publisher::{self, Message as BrokerMessage};
use crate::link;
use crate::policy::origin;
use crate::policy::typed::FbSession;
use crate::policy::{Admission, Door, Publication, Stage};
use crate::session::Context;

/// Keeps one zenoh import per filter local clients subscribed to, counted.
pub(super) async fn imports(
    link: Arc<Link>,
    mut interest: mpsc::UnboundedReceiver<Interest>,
    ctx: Arc<Context>,
) {
    let mut active: HashMap<String, (usize, Import)> = HashMap::new();
    while let Some(change) = interest.recv().await {
        match change {
            Interest::Add(filter) => {
                if let Some((count, _)) = active.get_mut(&filter) {
                    *count += 1;
                    continue;
                }
                match link.import(&filter).await {
                    Ok(import) => {
                        tracing::debug!(filter, "importing from the other lines");
                        active.insert(filter.clone(), (1, import));
                        ctx.metrics.bridge_imports.set(active.len() as i64);
                        // Retained messages of the other lines, published before this
                        // line was listening.
                        match link.query_retained(&filter).await {
                            Ok(retained) => {
                                for message in retained {
                                    ctx.metrics.bridge_retained_replayed.inc();
                                    link.requeue(message).await;
                                }
                            }
                            Err(e) => {
                                tracing::warn!(filter, error = %e, "retained messages of other lines not fetched")
                            }
                        }
                    }
                    Err(e) => {
                        tracing::error!(filter, error = %e, "cannot import from the other lines")
                    }
                }
            }
            Interest::Requery(line) => {
                for filter in active.keys() {
                    requery(&link, &ctx, &line, filter).await;
                }
            }
            Interest::Remove(filter) => {
                if let Some((count, _)) = active.get_mut(&filter) {
                    *count -= 1;
                    if *count == 0 {
                        active.remove(&filter);
                        ctx.metrics.bridge_imports.set(active.len() as i64);
                    }
                }
            }
        }
    }
}

/// Asks `line` again for its retained messages matching `filter` and requeues those this
/// line's router does not hold as they are: a value it missed, not a repeat of one its
/// subscribers have.
async fn requery(link: &Link, ctx: &Context, line: &str, filter: &str) {
    let answer = match link.query_retained_of(Some(line), filter).await {
        Ok(answer) => answer,
        Err(e) => {
            return tracing::warn!(line, filter, error = %e, "retained messages of a returning line not fetched")
        }
    };
    if answer.is_empty() {
        return;
    }
    let held = super::retained::held(ctx, filter).await;
    for message in answer {
        if held.get(&message.topic) != Some(&message.payload) {
            ctx.metrics.bridge_retained_replayed.inc();
            link.requeue(message).await;
        }
    }
}

/// Messages from the bus into the router, checked like local publications, through the
/// import link. Whatever the inbox holds is taken at once (up to [`INJECT_BATCH`]) and
/// handed to the router in one go: one router wake-up per batch, not per message.
pub(super) async fn inject_loop(
    (link, inbox): (Arc<Link>, Inbox<Inbound>),
    ctx: Arc<Context>,
    (mut tx, rx): (LinkTx, LinkRx),
    import: Vec<String>,
) {
    // The router acknowledges QoS 1 messages to this link; nothing waits for them.
    tokio::spawn(link::discard(rx));
    let mut injector = Injector {
        dedup: Dedup::default(),
        gaps: Gaps::default(),
        route_keys: link.route_keys(),
        link,
        publisher: IMPORT_CLIENT_ID.into(),
        devices: HashMap::new(),
        origin: Origins::default(),
        import,
        pkid: 0,
        packets: Vec::new(),
        imported: ctx.metrics.bridge_messages.with_label_values(&["import"]),
    };
    while let Some(first) = inbox.recv().await {
        injector.take(&ctx, first);
        let mut taken = 1;
        for message in inbox.try_iter().take(INJECT_BATCH) {
            injector.take(&ctx, message);
            taken += 1;
        }
        // QoS 1 and retained messages from the bus are stored like local ones: a
        // persistent session offline now gets them when it returns (issue 32).
        if let Some(store) = &ctx.store {
            let mut journal = crate::store::Journal::default();
            store.record_publications(&mut injector.packets, &mut journal, |_, _, _, _, _| {});
            // Nobody waits for it: the other line's exporter has its answer from zenoh.
            let _ = store
                .submit(&injector.publisher, None, &mut journal, false)
                .await;
        }
        if let Some(last) = injector.packets.pop() {
            tx.buffer().extend(injector.packets.drain(..));
            if tx.send(last).await.is_err() {
                tracing::error!("router gone: the bridge stops importing");
                return;
            }
        }
        // A full batch: more is waiting. The inbox (flume), unlike tokio's channels, never
        // makes a task yield, so a bus that keeps it full would hold the worker thread and
        // every local session would wait behind it (issue 32). One batch is at most a
        // millisecond of work.
        if taken > INJECT_BATCH {
            tokio::task::yield_now().await;
        }
    }
}

/// Messages taken from the inbox at once before the router is woken.
const INJECT_BATCH: usize = 256;

/// The importing side's state: what it has seen, and each remote device's typed check.
struct Injector {
    dedup: Dedup,
    /// Messages of other lines lost on the way (`fbbus_bridge_lost_total`).
    gaps: Gaps,
    /// Counts them for their origins too ([`Link::count_lost`]).
    link: Arc<Link>,
    route_keys: RouteKeys,
    /// The origin's publisher of every message from the bus: the import link.
    publisher: Arc<str>,
    /// Per remote device: the interface its session checks against.
    devices: HashMap<String, (Arc<fb_bridge::Interface>, FbSession)>,
    origin: Origins,
    import: Vec<String>,
    pkid: u16,
    packets: Vec<Packet>,
    /// `fbbus_bridge_messages_total{direction="import"}`, looked up once.
    imported: prometheus::IntCounter,
}

impl Injector {
    fn take(&mut self, ctx: &Context, message: Inbound) {
        let dropped = |reason: &str| {
            ctx.metrics
                .bridge_dropped
                .with_label_values(&[reason])
                .inc()
        };
        self.route_keys.note(&message.line, &message.topic);
        if !BusConfig::allows(&self.import, &message.topic) {
            return dropped("filter");
        }
        let Some(typed) = TypedTopic::parse(&message.topic) else {
            return dropped("unbridgeable");
        };
        let device = typed.device;
        // Authentication: the message is of a device its line declared. Then the device's
        // typed-topic state, checked against that declaration like a local device's.
        let interface = match self.origin.authenticate(ctx, &message, device) {
            Ok(interface) => interface,
            Err(()) => return,
        };
        // Only an authenticated message counts in its line's window of sequence numbers:
        // a forged stamp would move another line's window ahead and have all its
        // messages dropped as old (issue 22: line C silencing line A on line B with one
        // message), and each line a stranger invents would take a window.
        if !self.dedup.first_time(&message.stamp) {
            return dropped("duplicate");
        }
        // A message that came the long way (through a second router) after a newer one of
        // its topic: dropped, so each topic keeps its order.
        let Some(missing) = self.gaps.missing(&message.stamp, &message.topic) else {
            return dropped("late");
        };
        if missing > 0 {
            ctx.metrics.bridge_lost.inc_by(missing);
            let origin = &message.stamp;
            if !self.link.count_lost(&origin.line, origin.epoch, missing) {
                tracing::debug!(
                    line = origin.line,
                    "lost messages not reported: too many lines"
                );
            }
            static LOGGED: crate::logging::OnceAMinute = crate::logging::OnceAMinute::new();
            if LOGGED.due() {
                tracing::warn!(
                    line = message.stamp.line,
                    topic = message.topic,
                    missing,
                    "messages of another line lost on the bus (a router or link failed \
                     with them in flight; fbbus_bridge_lost_total, logged at most once a \
                     minute)"
                );
            }
        }
        let entry = self.devices.entry(device.to_owned()).or_insert_with(|| {
            (
                Arc::clone(&interface),
                FbSession::new(&ctx.fb, device, Some(device), 0),
            )
        });
        if !Arc::ptr_eq(&entry.0, &interface) || entry.1.interface().is_none() {
            entry.0 = Arc::clone(&interface);
            entry.1.set_interface(Some(interface));
        }
        let publisher = &mut entry.1;
        let payload = Bytes::from(message.payload);
        let publication = Publication {
            topic: &message.topic,
            payload: &payload,
            qos: message.stamp.qos.min(1),
            retain: message.stamp.retain,
        };
        let admission = ctx
            .policy
            .admit(Door::Bus, publisher, &self.publisher, publication);
        // The device's diagnostics are its own line's to publish.
        drop(publisher.take_outbox());
        let (origin, routes) = match admission {
            Admission::Route { origin, routes } => (origin, routes),
            Admission::Refused {
                stage: Stage::Access,
                ..
            } => {
                tracing::debug!(
                    topic = message.topic,
                    line = message.stamp.line,
                    "message from another line refused by this line's ACL"
                );
                return;
            }
            // Counted by the policy (`bridge_dropped{reason="type"}`); a declaration is
            // never a bridged topic, but would not be routed either.
            Admission::Refused { .. } => return,
            Admission::Consumed => return dropped("type"),
        };
        let routes = routes.unwrap_or_else(|| vec![(message.topic, payload)]);
        self.imported.inc();
        let qos = message.stamp.qos.min(1);
        for (topic, payload) in routes {
            let pkid = if qos > 0 {
                self.pkid = self.pkid % u16::MAX + 1;
                self.pkid
            } else {
                0
            };
            let mut publish =
                broker_publisher::publish_packet(topic, payload, qos, message.stamp.retain, pkid);
            origin::mark(&mut publish, origin.clone());
            self.packets.push(Packet::Publish(publish, None));
        }
    }
}

/// The bus door's authentication: a message from another line is imported only if it
/// comes from where it claims.
///
/// - Its stamp names the line whose key it came on. On a mutual-TLS bus zenoh's access
///   control let only that line (or a router forwarding it) put there, so the key's line
///   is the authenticated sender.
/// - Its device is a device of that line: the registry holds the device's record as that
///   line's own record put it. A line cannot speak for a device of this line, of a third
///   line, or for a device it never announced.
///
/// Refusals are counted per origin line (`fbbus_bridge_refused_total`), logged once per
/// line and reason, and described on the device's `fbbus/diag/<device>` at most once a
/// second per line.
#[derive(Default)]
struct Origins {
    /// When each origin line's refusals were last described on a diag topic.
    described: HashMap<String, Option<Instant>>,
    logged: std::collections::HashSet<(String, &'static str)>,
}

/// Origin lines whose refusals are logged and described separately; past this many
/// (an unauthenticated loopback peer writes any line on its keys) they are only counted.
const ORIGINS: usize = crate::metrics::REFUSED_LINE_LABELS;

impl Origins {
    fn authenticate(
        &mut self,
        ctx: &Context,
        message: &Inbound,
        device: &str,
    ) -> Result<Arc<fb_bridge::Interface>, ()> {
        let refusal = if message.stamp.line != message.line {
            "forged_origin"
        } else {
            match ctx.fb.registry.remote_interface(device, &message.line) {
                Ok(interface) => return Ok(interface),
                Err(not_of_line) => not_of_line.as_str(),
            }
        };
        self.refuse(ctx, message, device, refusal);
        Err(())
    }

    fn refuse(&mut self, ctx: &Context, message: &Inbound, device: &str, reason: &'static str) {
        ctx.metrics.bus_refused(&message.line, reason);
        let line = &message.line;
        let known = self.described.contains_key(line) || self.described.len() < ORIGINS;
        if !known {
            return;
        }
        if self.logged.insert((line.clone(), reason)) {
            tracing::warn!(
                line = %message.line,
                stamp_line = %message.stamp.line,
                device,
                topic = message.topic,
                reason,
                "message from the bus refused: it does not come from where it claims \
                 (logged once per line and reason; counted in fbbus_bridge_refused_total)"
            );
        }
        let last = self.described.entry(line.clone()).or_default();
        if last.is_some_and(|t| t.elapsed() < DESCRIBE_EVERY) {
            return;
        }
        *last = Some(Instant::now());
        ctx.fb.publish(vec![BrokerMessage::broker(
            fb_bridge::topic::diag(device),
            serde_json::json!({
                "kind": "bus_refused",
                "reason": reason,
                "line": message.line,
                "stamp_line": message.stamp.line,
                "topic": message.topic,
            })
            .to_string(),
            false,
        )]);
    }
}

/// At most one diagnostic a second per origin line.
const DESCRIBE_EVERY: Duration = Duration::from_secs(1);

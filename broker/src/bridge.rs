//! The line's end of the bus: fbbus's router on one side, zenoh (`fb_bridge::bus`) on
//! the other. Runs inside `fbbus serve` when the configuration has a `[bridge]` section.
//!
//! ```text
//!  local client SUBSCRIBE fb/X/..  ──► Bridge::subscribed ──► import: zenoh subscriber
//!                                                               + interest token
//!  other line's interest token ──► export: router link `fbbus:bridge-out` subscribes
//!  local PUBLISH fb/<local>/.. ──► router ──► export ──► zenoh put (stamped)
//!  zenoh sample ──► dedup ─► ACL ─► typed check ─► router link `fbbus:bridge-in`
//! ```
//!
//! **Subscription-driven.** Nothing leaves a line unless another line's client subscribed
//! to it: a subscription here declares a zenoh subscriber and a liveliness token naming
//! the filter; the other lines' bridges see the token, put only the messages matching
//! some line's interest, and zenoh sends each only to the lines whose subscribers match.
//! While no other line is interested in anything, the exporter is not even subscribed on
//! its router.
//!
//! **One hop, never more.** The exporter skips every message whose origin (the marker
//! the packet path attaches, `origin`) is the import link: what came from the bus is
//! never put back on it. With each line exporting only what its own clients published,
//! no topology can loop or duplicate; the per-origin sequence numbers in each message's
//! stamp ([`fb_bridge::bus::Dedup`]) drop the copies zenoh delivers once per overlapping
//! import filter.
//!
//! **Same rules as local traffic.** A message from the bus enters the router only after
//! this line's ACL allows its device (as username and client id) to publish on its topic
//! and, once the registry knows the device's declared interface, after the same typed
//! check as a local publication (which also re-encodes it for `dinasore/` and `fbdk/`
//! subscribers). A line exports only topics its `export` filters allow and imports only
//! what its `import` filters allow.
//!
//! **Delivery.** zenoh links are reliable and every put uses blocking congestion control:
//! a slow link or a slow remote line slows the exporter down (and, behind it, the router's
//! queue for the export link), it does not drop; a line that takes nothing for 5 s
//! (zenoh's blocking limit) has its link closed, is marked unreachable and reconnects. Event ports travel at a higher zenoh
//! priority than data ports, so events overtake queued data; each topic keeps its order.
//! An MQTT QoS 1 message is acknowledged to the router only after zenoh took it, and is
//! injected on the other line at QoS 1. What holds across failures: while both bridges
//! and the link are up, every message reaches every subscribed line once, in order; a
//! message in flight when a bridge or the link goes down may be lost (zenoh keeps no
//! end-to-end acknowledgement), and nothing published while a line is cut off is queued
//! for it. Retained messages are fetched again when a line (re)starts importing a filter,
//! so retained state converges after a restart or a partition.
//!
//! **Starting alone.** A line never waits for the bus: a peer or router starts with its
//! peers down and links when they answer; a zenoh client (`mode = "client"`), whose zenoh
//! `open` waits for its router, opens in the background (`start`), serves its own devices
//! meanwhile, and imports the subscriptions its clients made once it is linked.
//!
//! **Registry federation.** The line announces itself and each online local device with
//! liveliness tokens and puts every local record change on the bus; the other lines'
//! records arrive the same way. A device whose token disappears without its line saying
//! it went offline, and every device of a line whose token disappears, is marked
//! unreachable (within the zenoh lease, `bridge.lease_ms`); they are online again when
//! their tokens come back.

use std::collections::HashMap;
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::{Arc, Mutex, OnceLock};
use std::time::Duration;

use bytes::Bytes;
use fb_bridge::bus::link::{
    DeviceToken, Event, Import, Inbound, Inbox, Link, LinkError, RetainedQueries, RouteKeys,
};
use fb_bridge::bus::{keys, BusConfig, Dedup, Mode};
use fb_bridge::interface::OutputPort;
use fb_bridge::topic::{filter, TypedTopic};
use rumqttd::local::{LinkRx, LinkTx};
use rumqttd::protocol::{
    Filter, Packet, PubAck, PubAckReason, QoS, RetainForwardRule, Subscribe, Unsubscribe,
};
use rumqttd::Notification;
use security::Identity;
use tokio::sync::mpsc;
use tokio::task::JoinHandle;

use crate::broker_publisher;
use crate::context::Context;
use crate::policy::origin;
use crate::policy::typed::FbSession;
use crate::policy::{Admission, Door, Publication, Stage};
use crate::registry::{Record, Status};

/// The router link messages from the bus enter through.
pub const IMPORT_CLIENT_ID: &str = "fbbus:bridge-in";
/// The router link the exporter subscribes with.
pub const EXPORT_CLIENT_ID: &str = "fbbus:bridge-out";
/// What the exporter subscribes to while another line is interested in anything.
const EXPORT_FILTER: &str = "fb/#";

#[derive(Debug, thiserror::Error)]
pub enum BridgeError {
    #[error("bridge: {0}")]
    Link(#[from] LinkError),
    #[error("bridge: router: {0}")]
    Router(String),
}

/// What connections tell the bridge.
enum Interest {
    Add(String),
    Remove(String),
}

/// The handle connections hold: local subscriptions become imports.
pub struct Bridge {
    import_filters: Vec<String>,
    interest: mpsc::UnboundedSender<Interest>,
    /// Set once zenoh is open: at start, or for a zenoh client, once its router answers.
    link: OnceLock<Arc<Link>>,
    tasks: Mutex<Vec<JoinHandle<()>>>,
}

/// Local subscriptions become imports.
impl crate::session::SubscriptionObserver for Bridge {
    /// A local client was granted `filter`.
    fn subscribed(&self, filter: &str) {
        for f in self.imports_for(filter) {
            let _ = self.interest.send(Interest::Add(f));
        }
    }

    /// A local client dropped `filter` (UNSUBSCRIBE, or its clean session ended).
    fn unsubscribed(&self, filter: &str) {
        for f in self.imports_for(filter) {
            let _ = self.interest.send(Interest::Remove(f));
        }
    }
}

impl Bridge {
    /// The filters to import for a local subscription to `filter`: the typed namespace
    /// in the canonical `fb/` form (`dinasore/` and `fbdk/` are re-encoded here), narrowed
    /// to the configured import filters.
    fn imports_for(&self, filter: &str) -> Vec<String> {
        let filter = filter::unshared(filter);
        let canonical = match filter.split_once('/') {
            Some(("dinasore" | "fbdk", rest)) => format!("fb/{rest}"),
            _ => filter.to_owned(),
        };
        let mut out = Vec::new();
        for allowed in &self.import_filters {
            if filter::covers(allowed, &canonical) {
                if keys::bridgeable_filter(&canonical) {
                    out.push(canonical);
                }
                return out;
            }
        }
        for allowed in &self.import_filters {
            if filter::covers(&canonical, allowed) {
                out.push(allowed.clone());
            }
        }
        out
    }

    /// The bridge's tasks (a list of handles, valid after any panic of another holder).
    fn tasks(&self) -> std::sync::MutexGuard<'_, Vec<JoinHandle<()>>> {
        self.tasks
            .lock()
            .unwrap_or_else(std::sync::PoisonError::into_inner)
    }

    /// Closes the zenoh session (other lines see this line go at once) and stops the
    /// bridge's tasks.
    pub async fn close(&self) {
        if let Some(link) = self.link.get() {
            link.close().await;
        }
        for task in self.tasks().drain(..) {
            task.abort();
        }
    }
}

/// How long a zenoh client waits for its router before the line says it serves alone.
const ROUTER_PATIENCE: Duration = Duration::from_secs(2);

/// Starts the bridge. A peer or router opens zenoh here (its listeners bind, its peers
/// are tried in the background); a client (`mode = "client"`) opens it in the background,
/// because zenoh's `open` waits for the client's router: the line must serve its own
/// devices while the plant's router is down, and link up when it answers. Local
/// subscriptions made meanwhile are imported then.
pub async fn start(config: &BusConfig, ctx: Arc<Context>) -> Result<Arc<Bridge>, BridgeError> {
    // A bad `[bridge]` section fails the start whatever the mode.
    fb_bridge::bus::link::validate(config)?;
    let (interest, interest_rx) = mpsc::unbounded_channel();
    let bridge = Arc::new(Bridge {
        import_filters: config.import.clone(),
        interest,
        link: OnceLock::new(),
        tasks: Mutex::new(Vec::new()),
    });
    let line = ctx.fb.registry.line().to_owned();
    if config.mode != Mode::Client {
        let opened = Link::open(config, &line).await?;
        run(&bridge, opened, config, ctx, interest_rx).await?;
        return Ok(bridge);
    }
    let (config, weak) = (config.clone(), Arc::downgrade(&bridge));
    let opener = tokio::spawn(async move {
        let opening = Link::open(&config, &line);
        tokio::pin!(opening);
        let opened = match tokio::time::timeout(ROUTER_PATIENCE, &mut opening).await {
            Ok(opened) => opened,
            Err(_) => {
                tracing::warn!(connect = ?config.connect,
                    "zenoh router not reachable: the line serves its own devices and links to the other lines once it answers");
                opening.await
            }
        };
        let started = match (opened, weak.upgrade()) {
            (Ok(opened), Some(bridge)) => run(&bridge, opened, &config, ctx, interest_rx).await,
            (Ok(_), None) => Ok(()),
            (Err(e), _) => Err(e.into()),
        };
        if let Err(e) = started {
            tracing::error!(error = %e, "bridge to the other lines not started");
        }
    });
    bridge.tasks().push(opener);
    Ok(bridge)
}

/// The bridge's work once zenoh is open: its router links, registry federation, retained
/// queries, and the import, export and event tasks.
async fn run(
    bridge: &Bridge,
    (link, inbox, events): (Link, Inbox<Inbound>, Inbox<Event>),
    config: &BusConfig,
    ctx: Arc<Context>,
    interest_rx: mpsc::UnboundedReceiver<Interest>,
) -> Result<(), BridgeError> {
    let line = link.line().to_owned();
    let link = Arc::new(link);
    let metrics = Arc::clone(&ctx.metrics);

    let router = &ctx.router;
    let router_link = |id: &'static str| async move {
        router
            .link(id, true, 0)
            .await
            .map_err(|e| BridgeError::Router(e.to_string()))
    };
    let import_link = router_link(IMPORT_CLIENT_ID).await?;
    let export_link = router_link(EXPORT_CLIENT_ID).await?;

    let (remote_interest, remote_interest_rx) = mpsc::unbounded_channel();
    let (local_records, local_records_rx) = mpsc::unbounded_channel();
    let local_now = ctx.fb.registry.observe(local_records);

    let registry = Arc::clone(&ctx.fb.registry);
    link.serve_records(move || {
        registry
            .local()
            .into_iter()
            .map(|r| {
                (
                    r.id.clone(),
                    serde_json::to_vec(&r).expect("records serialize"),
                )
            })
            .collect()
    })
    .await?;
    let retained_queries = link.retained_queries().await?;
    link.announce_line().await?;

    let tasks = [
        tokio::spawn(imports(Arc::clone(&link), interest_rx, Arc::clone(&ctx))),
        tokio::spawn(inject_loop(
            inbox,
            link.route_keys(),
            Arc::clone(&ctx),
            (import_link.0, import_link.1),
            config.import.clone(),
        )),
        tokio::spawn(export_loop(
            link.exporter(),
            (export_link.0, export_link.1),
            remote_interest_rx,
            Arc::clone(&ctx),
            config.export.clone(),
        )),
        tokio::spawn(bus_events(
            Arc::clone(&link),
            events,
            remote_interest,
            Arc::clone(&ctx),
        )),
        tokio::spawn(announce_local(
            Arc::clone(&link),
            local_now,
            local_records_rx,
        )),
        tokio::spawn(serve_retained(
            Arc::clone(&link),
            retained_queries,
            Arc::clone(&ctx),
            config.export.clone(),
        )),
    ];
    bridge.tasks().extend(tasks);
    let _ = bridge.link.set(link);
    tracing::info!(line, mode = config.mode.as_str(), listen = ?config.listen, connect = ?config.connect,
        "bridge to the other lines started (zenoh)");
    metrics.bridge_imports.set(0);
    Ok(())
}

/// Keeps one zenoh import per filter local clients subscribed to, counted.
async fn imports(
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

/// Messages from the bus into the router, checked like local publications, through the
/// import link. Whatever the inbox holds is taken at once (up to [`INJECT_BATCH`]) and
/// handed to the router in one go: one router wake-up per batch, not per message.
async fn inject_loop(
    inbox: Inbox<Inbound>,
    route_keys: RouteKeys,
    ctx: Arc<Context>,
    (mut tx, mut rx): (LinkTx, LinkRx),
    import: Vec<String>,
) {
    // The router acknowledges QoS 1 messages to this link; nothing waits for them.
    tokio::spawn(async move {
        while let Ok(notification) = rx.next().await {
            if matches!(notification, Some(Notification::Unschedule)) {
                let _ = rx.wake().await;
            }
        }
    });
    let mut injector = Injector {
        dedup: Dedup::default(),
        route_keys,
        publisher: IMPORT_CLIENT_ID.into(),
        devices: HashMap::new(),
        import,
        pkid: 0,
        packets: Vec::new(),
    };
    while let Some(first) = inbox.recv().await {
        injector.take(&ctx, first);
        for message in inbox.try_iter().take(INJECT_BATCH) {
            injector.take(&ctx, message);
        }
        if let Some(last) = injector.packets.pop() {
            tx.buffer().extend(injector.packets.drain(..));
            if tx.send(last).await.is_err() {
                tracing::error!("router gone: the bridge stops importing");
                return;
            }
        }
    }
}

/// Messages taken from the inbox at once before the router is woken.
const INJECT_BATCH: usize = 256;

/// The importing side's state: what it has seen, and each remote device's typed check.
struct Injector {
    dedup: Dedup,
    route_keys: RouteKeys,
    /// The origin's publisher of every message from the bus: the import link.
    publisher: Arc<str>,
    /// Per remote device: the interface its session checks against.
    devices: HashMap<String, (Arc<fb_bridge::Interface>, FbSession)>,
    import: Vec<String>,
    pkid: u16,
    packets: Vec<Packet>,
}

impl Injector {
    fn take(&mut self, ctx: &Context, message: Inbound) {
        let dropped = |reason: &str| {
            ctx.metrics
                .bridge_dropped
                .with_label_values(&[reason])
                .inc()
        };
        if !self.dedup.first_time(&message.stamp) {
            return dropped("duplicate");
        }
        self.route_keys.note(&message.stamp.line, &message.topic);
        if !BusConfig::allows(&self.import, &message.topic) {
            return dropped("filter");
        }
        let Some(typed) = TypedTopic::parse(&message.topic) else {
            return dropped("unbridgeable");
        };
        let device = typed.device;
        // The device's typed-topic state: its declared interface once the registry has its
        // record from the other line, none until then (see `PublishPolicy::admit`).
        let interface = ctx.fb.registry.remote_interface(device, &message.stamp.line);
        let mut unknown;
        let publisher = match interface {
            Some(interface) => {
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
                &mut entry.1
            }
            None => {
                unknown = FbSession::new(&ctx.fb, device, Some(device), 0);
                &mut unknown
            }
        };
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
        ctx.metrics
            .bridge_messages
            .with_label_values(&["import"])
            .inc();
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

/// Subscribes to what other lines want, and puts what this line's clients publish there.
async fn export_loop(
    exporter: fb_bridge::bus::link::Exporter,
    (mut tx, mut rx): (LinkTx, LinkRx),
    mut remote: mpsc::UnboundedReceiver<(bool, String, String)>,
    ctx: Arc<Context>,
    export: Vec<String>,
) {
    let mut exports = Exports {
        exporter,
        interest: HashMap::new(),
        is_event: HashMap::new(),
        export,
        ctx,
    };
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
                let Ok(mut next) = notification else { return };
                // Everything the router delivered at once is exported, then acknowledged
                // in one go: one router wake-up per batch, not one per message.
                let mut acks = Vec::new();
                let mut unscheduled = false;
                loop {
                    match next {
                        Some(Notification::Forward(forward)) => {
                            acks.extend(exports.forward(forward).await);
                        }
                        Some(Notification::Unschedule) => unscheduled = true,
                        _ => {}
                    }
                    next = match rx.recv_deadline(std::time::Instant::now()) {
                        Ok(n) => n,
                        Err(rumqttd::local::LinkError::RecvTimeout(_)) => break,
                        Err(_) => return,
                    };
                }
                if let Some(last) = acks.pop() {
                    tx.buffer().extend(acks);
                    if tx.send(last).await.is_err() {
                        return;
                    }
                }
                if unscheduled && rx.wake().await.is_err() {
                    return;
                }
            }
        }
    }
}

/// The exporting side's state: what the other lines want, and which topics are events.
struct Exports {
    exporter: fb_bridge::bus::link::Exporter,
    /// filter -> lines interested in it
    interest: HashMap<String, std::collections::HashSet<String>>,
    is_event: HashMap<String, bool>,
    export: Vec<String>,
    ctx: Arc<Context>,
}

impl Exports {
    /// Another line's interest in `filter` came or went; returns the router subscription
    /// change, if any.
    fn interest_changed(&mut self, added: bool, line: String, filter: String) -> Option<Packet> {
        if !keys::bridgeable_filter(&filter) {
            return None;
        }
        let was_empty = self.interest.is_empty();
        let lines = self.interest.entry(filter.clone()).or_default();
        let changed = if added {
            lines.insert(line)
        } else {
            lines.remove(&line)
        };
        if lines.is_empty() {
            self.interest.remove(&filter);
        }
        if changed {
            self.ctx
                .metrics
                .bridge_remote_subscriptions
                .add(if added { 1 } else { -1 });
        }
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

    /// Puts one delivery of the router on the bus if another line wants it; returns the
    /// acknowledgement the router expects (a QoS 1 delivery), sent once zenoh took it.
    async fn forward(&mut self, forward: rumqttd::Forward) -> Option<Packet> {
        let mut publish = forward.publish;
        let origin = origin::take(&mut publish);
        let (routed_qos, pkid) = broker_publisher::qos_and_pkid(&publish);
        let from_bus = origin
            .as_ref()
            .is_some_and(|o| &*o.publisher == IMPORT_CLIENT_ID);
        let topic = String::from_utf8_lossy(&publish.topic).into_owned();
        // rumqttd replays retained messages on every subscribe (it ignores Retain
        // Handling): those reach other lines by query, not here.
        let replay = publish.retain;
        let wanted = !from_bus
            && !replay
            && BusConfig::allows(&self.export, &topic)
            && self.interest.keys().any(|f| filter::matches(f, &topic));
        if wanted {
            let ctx = &self.ctx;
            let event = *self
                .is_event
                .entry(topic.clone())
                .or_insert_with(|| event_port(ctx, &topic));
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
                Ok(true) => metrics.bridge_messages.with_label_values(&["export"]).inc(),
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
fn event_port(ctx: &Context, topic: &str) -> bool {
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

/// Liveliness and records of the other lines: the registry, and the exporter's interest.
async fn bus_events(
    link: Arc<Link>,
    events: Inbox<Event>,
    remote_interest: mpsc::UnboundedSender<(bool, String, String)>,
    ctx: Arc<Context>,
) {
    let registry = &ctx.fb.registry;
    let liveliness = |kind: &str| {
        ctx.metrics
            .bridge_liveliness
            .with_label_values(&[kind])
            .inc()
    };
    while let Some(event) = events.recv().await {
        match event {
            Event::InterestAdded { line, filter } => {
                let _ = remote_interest.send((true, line, filter));
            }
            Event::InterestRemoved { line, filter } => {
                let _ = remote_interest.send((false, line, filter));
            }
            Event::LineUp(line) => {
                liveliness("line_up");
                tracing::info!(line, "line reachable");
                // Every record of the line, online or not, in the background: the
                // events keep flowing meanwhile.
                let (link, ctx) = (Arc::clone(&link), Arc::clone(&ctx));
                tokio::spawn(async move {
                    match link.query_records(&line).await {
                        Ok(records) => {
                            for (_, _, json) in records {
                                apply_record(&ctx, &json);
                            }
                        }
                        Err(e) => tracing::warn!(line, error = %e, "registry query failed"),
                    }
                });
            }
            Event::LineDown(line) => {
                liveliness("line_down");
                tracing::warn!(line, "line unreachable: its devices are marked unreachable");
                registry.line_unreachable(&line);
            }
            Event::DeviceUp { line, device } => {
                liveliness("device_up");
                if registry.get(&device).is_some_and(|r| r.line == line) {
                    registry.remote_status(&line, &device, Status::Online);
                } else {
                    let (link, ctx) = (Arc::clone(&link), Arc::clone(&ctx));
                    tokio::spawn(async move {
                        if let Ok(records) = link.query_records(&line).await {
                            for (_, d, json) in records {
                                if d == device {
                                    apply_record(&ctx, &json);
                                }
                            }
                        }
                    });
                }
            }
            Event::DeviceDown { line, device } => {
                liveliness("device_down");
                // Gone offline (its line put the record first) or cut off: a record that
                // still says online means this line lost sight of it.
                if registry
                    .get(&device)
                    .is_some_and(|r| r.line == line && r.status == Status::Online)
                {
                    registry.remote_status(&line, &device, Status::Unreachable);
                }
            }
            Event::Record { json, .. } => apply_record(&ctx, &json),
        }
    }
}

fn apply_record(ctx: &Context, json: &[u8]) {
    match serde_json::from_slice::<Record>(json) {
        Ok(record) => ctx.fb.registry.remote_record(record),
        Err(e) => tracing::warn!(error = %e, "unreadable registry record from another line"),
    }
}

/// Puts each local record change on the bus and keeps a liveliness token per online
/// local device.
async fn announce_local(
    link: Arc<Link>,
    now: Vec<Record>,
    mut changes: mpsc::UnboundedReceiver<Record>,
) {
    let mut tokens: HashMap<String, DeviceToken> = HashMap::new();
    for record in now {
        announce(&link, &mut tokens, record).await;
    }
    while let Some(record) = changes.recv().await {
        announce(&link, &mut tokens, record).await;
    }
}

async fn announce(link: &Link, tokens: &mut HashMap<String, DeviceToken>, record: Record) {
    {
        let json = serde_json::to_vec(&record).expect("records serialize");
        // The record first: a line that sees the token go finds the device offline already.
        if let Err(e) = link.put_record(&record.id, json).await {
            tracing::warn!(device = record.id, error = %e, "record not put on the bus");
        }
        match record.status {
            Status::Online if !tokens.contains_key(&record.id) => {
                match link.device_online(&record.id).await {
                    Ok(token) => {
                        tokens.insert(record.id.clone(), token);
                    }
                    Err(e) => {
                        tracing::warn!(device = record.id, error = %e, "liveliness token not declared")
                    }
                }
            }
            Status::Online => {}
            _ => {
                tokens.remove(&record.id);
            }
        }
    }
}

static RETAINED_LINKS: AtomicU64 = AtomicU64::new(0);

/// Answers other lines' queries for this line's retained messages: a short-lived router
/// link subscribes to the filter and collects what the router replays as retained.
async fn serve_retained(
    link: Arc<Link>,
    queries: RetainedQueries,
    ctx: Arc<Context>,
    export: Vec<String>,
) {
    while let Some(query) = queries.recv().await {
        let messages = retained(&ctx, query.filter(), &export).await;
        link.reply_retained(&query, messages).await;
    }
}

async fn retained(ctx: &Context, filter: &str, export: &[String]) -> Vec<(String, Vec<u8>)> {
    let id = format!(
        "fbbus:bridge-retained-{}",
        RETAINED_LINKS.fetch_add(1, Ordering::Relaxed)
    );
    let Ok((mut tx, mut rx, _)) = ctx.router.link(&id, true, 0).await else {
        return Vec::new();
    };
    let subscribe = Packet::Subscribe(
        Subscribe {
            pkid: 1,
            filters: vec![Filter {
                path: filter.to_owned(),
                qos: QoS::AtMostOnce,
                nolocal: false,
                preserve_retain: false,
                retain_forward_rule: RetainForwardRule::OnEverySubscribe,
            }],
        },
        None,
    );
    let mut out = Vec::new();
    if tx.send(subscribe).await.is_ok() {
        // The router replays retained messages right after the SUBACK; stop once it has
        // been quiet for a moment.
        let mut quiet = Duration::from_millis(500);
        while let Ok(Ok(n)) = tokio::time::timeout(quiet, rx.next()).await {
            match n {
                Some(Notification::Forward(forward)) => {
                    quiet = Duration::from_millis(50);
                    let mut publish = forward.publish;
                    let origin = origin::take(&mut publish);
                    let own = origin.is_none_or(|o| o.retain && &*o.publisher != IMPORT_CLIENT_ID);
                    let topic = String::from_utf8_lossy(&publish.topic).into_owned();
                    if own && BusConfig::allows(export, &topic) {
                        out.push((topic, publish.payload.to_vec()));
                    }
                }
                Some(Notification::Unschedule) => {
                    let _ = rx.wake().await;
                }
                Some(_) => quiet = Duration::from_millis(50),
                None => {}
            }
        }
    }
    let _ = crate::router::unlink(tx).await;
    out
}

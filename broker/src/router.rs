//! rumqttd's router, the part of rumqttd fbbus keeps: subscriptions, retained messages,
//! per-filter commit logs and QoS bookkeeping, on its own thread.
//!
//! Connections reach it through links (`LinkTx` towards the router, `LinkRx` back).
//! rumqttd does not export the type of the router's event channel, so the channel is
//! captured in a closure here and the rest of the broker only sees [`RouterHandle::link`].
//!
//! fbbus runs a vendored rumqttd (`vendor/rumqttd`, changes in its `FBBUS-CHANGES.md`)
//! that holds publishers back for lagging subscribers and reports three things back
//! through [`RouterHooks`]:
//! - **held publishers**: when a filter's commit log (`router_segment_count` x
//!   `router_segment_bytes`) is full and its next message would drop messages a subscriber
//!   has not read, the router stops taking the publishers' packets until the subscriber
//!   has read them, so TCP slows the publishers down instead of the subscriber losing
//!   messages (a burst is delivered whole to a subscriber that reads, only slower). At most
//!   for `slow_subscriber_hold_ms`, though: one stalled device must not stop a line. A
//!   subscriber still behind then is slow, skips (below) and holds nobody back until it
//!   has caught up. Counted in `fbbus_publisher_holds_total{outcome}` and
//!   `fbbus_publisher_hold_milliseconds_total`; a hold that gave up is warned about, at
//!   most once per filter per [`SKIP_WARNING_INTERVAL`].
//! - **skipped messages**: what retention dropped before a slow subscriber read it is
//!   lost. MQTT allows that for QoS 0, but never silently here:
//!   `fbbus_messages_skipped_total` counts every such message and one warning is logged
//!   per episode (until the subscriber catches up again), at most one per client per
//!   [`SKIP_WARNING_INTERVAL`]: a device that keeps falling behind catches up briefly
//!   between bursts, and must not flood the log.
//! - **released**: the router has freed the commit-log data every reader has read and the
//!   empty per-connection queues, after [`IDLE_AFTER`] without any event, and every
//!   [`RELEASE_EVERY`] while traffic never pauses that long (a line with steady telemetry,
//!   the registry publishing after a reconnect storm); the broker then asks the allocator
//!   to give freed memory back to the OS ([`crate::memory`]).

use std::collections::HashMap;
use std::sync::Arc;
use std::time::{Duration, Instant};

use rumqttd::local::{LinkBuilder, LinkError, LinkRx, LinkTx};
use rumqttd::protocol::{Disconnect, DisconnectReasonCode, Packet};
use rumqttd::{Held, Notification, Router, RouterConfig, RouterHooks, Skipped};

use crate::health::Health;
use crate::metrics::Metrics;

/// What the router may hold: `[broker]`'s router keys, which the configuration's reader
/// hands over (`config::BrokerSection::router`). The router owns their meaning, not the
/// file they come from.
#[derive(Debug, Clone, Copy)]
pub struct Settings {
    /// Client connections at once (`max_connections`); the router gets
    /// [`INTERNAL_LINKS`] slots more, for the broker's own links.
    pub max_connections: usize,
    /// Messages queued towards one connection before the router pauses delivery to it.
    pub max_outgoing_packets: u64,
    /// Commit-log segment size and segments kept, per subscribed filter.
    pub segment_bytes: usize,
    pub segment_count: usize,
    /// Retained messages clients can make the router keep, and their bytes.
    pub max_retained_messages: usize,
    pub max_retained_bytes: usize,
    /// Longest time publishers are held back for a lagging subscriber; zero: never.
    pub slow_subscriber_hold: Duration,
    /// QoS 1/2 deliveries in flight to one connection at most (`max_inflight_out`).
    pub max_inflight_out: u16,
}

/// Router connections beyond `max_connections` for the broker's own links: its publisher,
/// the readiness probe, the console's and the Sparkplug view's observers, the bus
/// bridge's, and the short-lived ones (a retained query over the bus, a session purged
/// before its client's link). With one slot, as before, a full line refused its last
/// clients in the router, each with an error line, instead of at the listener, counted
/// under `max_connections` and logged once.
pub const INTERNAL_LINKS: usize = 64;

/// Offline persistent sessions kept at most, by the router and by the broker's session
/// table alike (the oldest closed is dropped beyond): every client that can be connected
/// at once (`max_connections`) may also be away.
pub fn saved_sessions_limit(max_connections: usize) -> usize {
    max_connections.max(rumqttd::DEFAULT_MAX_SAVED_SESSIONS)
}

/// Topics whose retained messages are outside `max_retained_messages` and
/// `max_retained_bytes`: the broker's own (`fbbus/`: device records, line counts;
/// `$fbbus/`: the readiness probe). Clients cannot publish there (the policy refuses
/// every `fbbus/` topic but their own declaration, which is never routed).
pub const RETAINED_UNCOUNTED: [&str; 3] = ["fbbus/", "$fbbus/", "$SYS/"];

/// How long the router must be quiet before it releases memory.
pub const IDLE_AFTER: Duration = Duration::from_millis(500);

/// How often the router releases memory while it is never quiet that long.
pub const RELEASE_EVERY: Duration = Duration::from_secs(10);

/// At most one skipped-messages warning per client in this time.
pub const SKIP_WARNING_INTERVAL: Duration = Duration::from_secs(60);

type Builder = dyn for<'a> Fn(&'a str) -> LinkBuilder<'a> + Send + Sync;

/// The router did not register a link (it is gone, or full).
#[derive(Debug, thiserror::Error)]
#[error("the router refused the connection: {0}")]
pub struct LinkRefused(String);

type Linked = Result<(LinkTx, LinkRx, Notification), LinkRefused>;

/// Links connections to the router; clones link to the same router.
#[derive(Clone)]
pub struct RouterHandle {
    builder: Arc<Builder>,
}

impl RouterHandle {
    /// Starts the router thread with the line's memory bounds. If the router ever stops
    /// (a panic, or its loop ending), `health` is told: the broker is dead without it.
    pub fn spawn(settings: &Settings, metrics: Arc<Metrics>, health: &Arc<Health>) -> RouterHandle {
        let config = RouterConfig {
            max_connections: settings.max_connections + INTERNAL_LINKS,
            max_outgoing_packet_count: settings.max_outgoing_packets,
            max_segment_size: settings.segment_bytes,
            max_segment_count: settings.segment_count,
            custom_segment: None,
            initialized_filters: None,
            shared_subscriptions_strategy: Default::default(),
            max_saved_sessions: saved_sessions_limit(settings.max_connections),
            max_retained_messages: settings.max_retained_messages,
            max_retained_bytes: settings.max_retained_bytes,
            // The broker's own retained messages (registry records, line counts) are
            // bounded by the registry, not by what clients retain: a flood of clients'
            // retained messages must never keep a device's record from being retained.
            retained_uncounted_prefixes: RETAINED_UNCOUNTED.iter().map(|p| p.to_string()).collect(),
            // A `#` subscriber gets each typed value once, on `fb/` (issue 35).
            wildcard_hidden_prefixes: fb_bridge::topic::MIRROR_PREFIXES
                .iter()
                .map(|p| p.to_string())
                .collect(),
        };
        let mut warned = SkipWarnings::default();
        let mut warned_holds = SkipWarnings::default();
        let held_metrics = metrics.clone();
        let hooks = RouterHooks {
            // Exported as fbbus_router_saved_sessions{,_dropped_total}.
            saved_sessions: Arc::clone(&metrics.router_sessions),
            // Exported as fbbus_retained_{messages,bytes} and, refused,
            // fbbus_limit_refusals_total{limit="retained_messages"|"retained_bytes"}.
            retained: Arc::clone(&metrics.router_retained),
            hold_limit: settings.slow_subscriber_hold,
            held: Some(Box::new(move |held: &Held<'_>| {
                let outcome = if held.gave_up { "gave_up" } else { "caught_up" };
                held_metrics
                    .publisher_holds
                    .with_label_values(&[outcome])
                    .inc();
                held_metrics
                    .publisher_hold_ms
                    .inc_by(held.waited.as_millis() as u64);
                if held.gave_up && warned_holds.may_warn(held.filter) {
                    tracing::warn!(
                        filter = held.filter,
                        publishers = held.publishers,
                        waited_ms = held.waited.as_millis() as u64,
                        "a subscriber of this filter did not catch up while its publishers \
                         were held (slow_subscriber_hold_ms); it now skips what it cannot \
                         keep up with (fbbus_messages_skipped_total; logged at most once a \
                         minute per filter)"
                    );
                }
            })),
            skipped: Some(Box::new(move |skipped: &Skipped<'_>| {
                metrics.messages_skipped.inc_by(skipped.count);
                if skipped.first_in_episode && warned.may_warn(skipped.client_id) {
                    tracing::warn!(
                        client_id = skipped.client_id,
                        filter = skipped.filter,
                        skipped = skipped.count,
                        "subscriber lagged behind the commit log; messages skipped \
                         (all counted in fbbus_messages_skipped_total; logged once per \
                         episode and at most once a minute per client)"
                    );
                }
            })),
            released: Some(std::sync::Arc::new(crate::memory::release_freed)),
            idle_after: IDLE_AFTER,
            release_every: RELEASE_EVERY,
            exited: Some(Box::new({
                let health = Arc::clone(health);
                move |reason| health.fatal(reason)
            })),
            panic_on_topic: crate::supervisor::test_panic_topic("FBBUS_TEST_ROUTER_PANIC_TOPIC"),
        };
        let router = Router::new(0, config).with_hooks(hooks);
        let ids = router.connection_ids();
        let router_tx = router.spawn();
        let max_inflight = settings.max_inflight_out;
        RouterHandle {
            builder: Arc::new(move |client_id| {
                LinkBuilder::new(client_id, router_tx.clone(), ids.clone())
                    .max_inflight(max_inflight)
            }),
        }
    }

    /// Registers a connection with the router. A connection with the same client id is
    /// dropped by the router (its `LinkRx` fails), which is how takeover reaches it.
    ///
    /// A clean session's link is ready at once: its connection id comes from the pool the
    /// router shares with its links, and what it sends next reaches the router after its
    /// Connect. A session the router may hold waits (without blocking the thread) for the
    /// router's answer, within its next event loop turn: whether the session was there,
    /// and its pending PUBRELs.
    pub async fn link(&self, client_id: &str, clean_session: bool, topic_alias_max: u16) -> Linked {
        self.builder(client_id, clean_session, topic_alias_max)
            .build_linked()
            .await
            .map_err(|e| LinkRefused(e.to_string()))
    }

    /// A link for one of the broker's observers (the line console): clean, and its lag
    /// never holds publishers back (`slow_subscriber_hold_ms` does not apply); what its
    /// filters' logs drop before it reads it, it skips. The devices never wait for it.
    pub async fn observer_link(&self, client_id: &str) -> Linked {
        self.builder(client_id, true, 0)
            .holds_publishers(false)
            .build_async()
            .await
            .map_err(|e| LinkRefused(e.to_string()))
    }

    /// [`RouterHandle::link`] for callers that must link while holding a lock: blocks the
    /// thread (and tells tokio so) until the router answers.
    pub fn link_blocking(&self, client_id: &str, clean_session: bool) -> Linked {
        let builder = self.builder(client_id, clean_session, 0);
        tokio::task::block_in_place(|| builder.build().map_err(|e| LinkRefused(e.to_string())))
    }

    fn builder<'a>(
        &self,
        client_id: &'a str,
        clean_session: bool,
        topic_alias_max: u16,
    ) -> LinkBuilder<'a> {
        (self.builder)(client_id)
            .clean_session(clean_session)
            .dynamic_filters(true)
            .topic_alias_max(topic_alias_max)
    }
}

/// When each client (or filter) was last warned about (router thread only).
#[derive(Default)]
struct SkipWarnings {
    last: HashMap<String, Instant>,
}

impl SkipWarnings {
    /// Whether `client_id` (or a filter) may be warned about now; records it if so.
    fn may_warn(&mut self, client_id: &str) -> bool {
        let now = Instant::now();
        if self
            .last
            .get(client_id)
            .is_some_and(|at| now.duration_since(*at) < SKIP_WARNING_INTERVAL)
        {
            return false;
        }
        if self.last.len() >= 1024 {
            self.last
                .retain(|_, at| now.duration_since(*at) < SKIP_WARNING_INTERVAL);
        }
        self.last.insert(client_id.to_owned(), now);
        true
    }
}

/// Tells the router a link ended: it drops the link and, for a clean session, its state.
pub async fn unlink(mut link_tx: LinkTx) -> Result<usize, LinkError> {
    link_tx
        .send(Packet::Disconnect(
            Disconnect {
                reason_code: DisconnectReasonCode::NormalDisconnection,
            },
            None,
        ))
        .await
}

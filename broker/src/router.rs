//! rumqttd's router, the part of rumqttd fbbus keeps: subscriptions, retained messages,
//! per-filter commit logs and QoS bookkeeping, on its own thread.
//!
//! Connections reach it through links (`LinkTx` towards the router, `LinkRx` back).
//! rumqttd does not export the type of the router's event channel, so the channel is
//! captured in a closure here and the rest of the broker only sees [`RouterHandle::link`].
//!
//! fbbus runs a vendored rumqttd (`vendor/rumqttd`, changes in its `FBBUS-CHANGES.md`)
//! that reports two things back through [`RouterHooks`]:
//! - **skipped messages**: a subscriber that lags by more than a filter's commit log holds
//!   (`router_segment_count` x `router_segment_bytes`) reads on from the oldest message
//!   still there, and what retention dropped unread is lost. MQTT allows that for QoS 0,
//!   but never silently here: `fbbus_messages_skipped_total` counts every such message
//!   and one warning is logged per episode (until the subscriber catches up again), at
//!   most one per client per [`SKIP_WARNING_INTERVAL`]: a device that keeps falling behind
//!   catches up briefly between bursts, and must not flood the log.
//!   Publishers are not slowed down for a slow subscriber: one stalled device must not
//!   stop a line.
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
use rumqttd::{Notification, Router, RouterConfig, RouterHooks, Skipped};

use crate::config::BrokerSection;
use crate::metrics::Metrics;

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

pub struct RouterHandle {
    builder: Box<Builder>,
}

impl RouterHandle {
    /// Starts the router thread with the line's memory bounds.
    pub fn spawn(broker: &BrokerSection, metrics: Arc<Metrics>) -> RouterHandle {
        let config = RouterConfig {
            // One extra for the broker's internal link.
            max_connections: broker.max_connections + 1,
            max_outgoing_packet_count: broker.router_max_outgoing_packets,
            max_segment_size: broker.router_segment_bytes,
            max_segment_count: broker.router_segment_count,
            custom_segment: None,
            initialized_filters: None,
            shared_subscriptions_strategy: Default::default(),
        };
        let mut warned = SkipWarnings::default();
        let hooks = RouterHooks {
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
        };
        let router_tx = Router::new(0, config).with_hooks(hooks).spawn();
        RouterHandle {
            builder: Box::new(move |client_id| LinkBuilder::new(client_id, router_tx.clone())),
        }
    }

    /// Registers a connection with the router. A connection with the same client id is
    /// dropped by the router (its `LinkRx` fails), which is how takeover reaches it.
    /// Waits (without blocking the thread) until the router answers, within its next
    /// event loop turn.
    pub async fn link(&self, client_id: &str, clean_session: bool, topic_alias_max: u16) -> Linked {
        self.builder(client_id, clean_session, topic_alias_max)
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

/// When each client was last warned about skipped messages (router thread only).
#[derive(Default)]
struct SkipWarnings {
    last: HashMap<String, Instant>,
}

impl SkipWarnings {
    /// Whether `client_id` may be warned about now; records it if so.
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

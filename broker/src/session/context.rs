//! What every connection shares, built once at start-up by `server`.
//!
//! The session layer reads it; nothing in it belongs to one connection. Kept apart from the
//! session code so the bridge and the session-expiry task can use it without reaching into
//! a connection's internals.

use std::sync::Arc;
use std::time::Duration;

use tokio::sync::watch;

use super::redelivery::Redeliveries;
use super::table::SessionTable;
use super::takeover::Takeovers;
use crate::authenticator::Authenticator;
use crate::identity::Identities;
use crate::metrics::Metrics;
use crate::observer::Observers;
use crate::policy::typed::FbTopics;
use crate::policy::PublishPolicy;
use crate::router::RouterHandle;
use crate::wills::Wills;

/// Everything connections share, built once by `server`.
pub struct Context {
    pub router: RouterHandle,
    pub authenticator: Arc<Authenticator>,
    /// Who owns a session, which client ids a user may use (`identity`).
    pub identity: Identities,
    /// What every publication passes, whichever way it came in: access, typed check,
    /// origin mark (`policy`).
    pub policy: PublishPolicy,
    pub wills: Arc<Wills>,
    /// Typed topics and the device registry, shared with the policy's typed stage.
    pub fb: Arc<FbTopics>,
    pub sessions: SessionTable,
    /// The connected clients, for the admin plane's list.
    pub clients: Arc<crate::clients::Clients>,
    pub redeliveries: Redeliveries,
    /// New connections waiting for their client id's old connection to finish reading.
    pub takeovers: Takeovers,
    /// What survives a restart; None with `[persistence] enabled = false`.
    pub store: Option<Arc<crate::store::Store>>,
    /// Each identity's share of the retained messages.
    pub retained_shares: Arc<crate::retained_share::RetainedShares>,
    pub metrics: Arc<Metrics>,
    pub max_packet: usize,
    pub max_inflight: u16,
    /// `[broker] max_subscriptions_per_client`.
    pub max_subscriptions: usize,
    /// `[broker] max_sessions_per_identity`.
    pub max_sessions_per_identity: usize,
    /// `broker.max_keep_alive_s` (see `session::connect::keep_alive`).
    pub max_keep_alive: u16,
    pub connect_timeout: Duration,
    /// Connections before CONNECT, per source address (`[broker] max_pending_per_address`).
    pub pending: Arc<crate::pending::Pending>,
    /// `broker.slow_consumer_timeout_ms`: the deadline of every write to a client.
    pub write_timeout: Duration,
    /// `broker.slow_consumer_max_bytes`: outgoing bytes queued for one connection at most.
    pub max_queued_bytes: usize,
    /// `broker.dead_link_timeout_s`: TCP keep-alive and `TCP_USER_TIMEOUT` (`listener`).
    pub dead_link: Option<Duration>,
    /// Becomes true when the broker shuts down.
    pub shutdown: watch::Receiver<bool>,
    /// Tests only: a publication on this topic makes its session panic (`supervisor`).
    pub test_panic_topic: Option<String>,
    /// Told of what clients subscribe to: typed-topic re-encoding, the bus bridge.
    pub observers: Observers,
}

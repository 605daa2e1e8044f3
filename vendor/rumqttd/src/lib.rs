//! # rumqttd (fbbus's fork of rumqttd 0.20)
//!
//! **It owns** the router (topic matching, retained messages, per-filter commit logs,
//! QoS 1/2 state, shared subscriptions), its local links, and the MQTT 3.1.1 and 5
//! codecs. **It must not know** fbbus's policy: who may publish where, typed topics,
//! wills, the registry or the bus; the broker puts those in front of it. Every change
//! from upstream is listed in `FBBUS-CHANGES.md`, so a rebase stays possible.

// fbbus: the router, its local links and the MQTT codecs of rumqttd 0.20, as the fbbus
// broker embeds them. Upstream's server (listeners, TLS, websockets), console, cluster
// replicator, bridge, metrics exporter and `rumqttd` binary are removed
// (FBBUS-CHANGES.md, "Removed from upstream").

use std::collections::HashMap;

use serde::{Deserialize, Serialize};

pub use link::local;
pub use router::{
    Forward, Held, Notification, RetainLimit, RetainedStats, Router, RouterHooks, SavedSessions,
    Skipped, DEFAULT_MAX_SAVED_SESSIONS,
};
use segments::Storage;

pub use self::router::ids::ConnectionIds; // fbbus
pub use self::router::shared_subs::Strategy;

mod freer; // fbbus
mod link;
pub mod protocol;
mod router;
mod segments;

pub type ConnectionId = usize;
pub type RouterId = usize;
pub type Topic = String;
pub type Filter = String;
pub type Offset = (u64, u64);
pub type Cursor = (u64, u64);

// fbbus: `Default` is written out for `max_saved_sessions`.
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct RouterConfig {
    pub max_connections: usize,
    pub max_outgoing_packet_count: u64,
    pub max_segment_size: usize,
    pub max_segment_count: usize,
    pub custom_segment: Option<HashMap<String, SegmentConfig>>,
    pub initialized_filters: Option<Vec<Filter>>,
    // defaults to Round Robin
    #[serde(default)]
    pub shared_subscriptions_strategy: Strategy,
    /// fbbus: at most this many offline persistent sessions are kept; saving one more
    /// drops the oldest saved (counted in `RouterHooks::saved_sessions`). Default
    /// [`DEFAULT_MAX_SAVED_SESSIONS`]; upstream kept every one forever.
    #[serde(default = "default_max_saved_sessions")]
    pub max_saved_sessions: usize,
    /// fbbus: a retained publication on a topic without a retained message is not kept
    /// when this many are kept, or when its topic and payload would take the retained
    /// bytes beyond `max_retained_bytes` (counted in `RouterHooks::retained`). Replacing
    /// or clearing one always works. Default: no bound (upstream).
    #[serde(default = "unbounded")]
    pub max_retained_messages: usize,
    #[serde(default = "unbounded")]
    pub max_retained_bytes: usize,
    /// fbbus: retained messages on topics starting with one of these are neither counted
    /// nor refused: the embedder's own, which it bounds itself.
    #[serde(default)]
    pub retained_uncounted_prefixes: Vec<String>,
    /// fbbus: topics starting with one of these are, like `$` topics [MQTT-4.7.2-1],
    /// matched only by filters that name their first level: a filter starting with `#`
    /// or `+` does not match them (the embedder's re-encoded copies of its own topics,
    /// which a generic `#` subscriber would otherwise see once per encoding).
    #[serde(default)]
    pub wildcard_hidden_prefixes: Vec<String>,
}

// fbbus
fn unbounded() -> usize {
    usize::MAX
}

// fbbus
fn default_max_saved_sessions() -> usize {
    DEFAULT_MAX_SAVED_SESSIONS
}

impl Default for RouterConfig {
    fn default() -> Self {
        RouterConfig {
            max_connections: 0,
            max_outgoing_packet_count: 0,
            max_segment_size: 0,
            max_segment_count: 0,
            custom_segment: None,
            initialized_filters: None,
            shared_subscriptions_strategy: Strategy::default(),
            max_saved_sessions: DEFAULT_MAX_SAVED_SESSIONS,
            max_retained_messages: usize::MAX,
            max_retained_bytes: usize::MAX,
            retained_uncounted_prefixes: Vec::new(),
            wildcard_hidden_prefixes: Vec::new(),
        }
    }
}

#[derive(Debug, Default, Clone, Serialize, Deserialize)]
pub struct SegmentConfig {
    pub max_segment_size: usize,
    pub max_segment_count: usize,
}

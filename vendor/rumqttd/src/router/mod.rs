use std::collections::VecDeque;

use bytes::Bytes;
use serde::{Deserialize, Serialize};

use crate::{
    protocol::{
        ConnAck, ConnAckProperties, Disconnect, DisconnectProperties, Packet, PingResp, PubAck,
        PubAckProperties, PubComp, PubCompProperties, PubRec, PubRecProperties, PubRel,
        PubRelProperties, Publish, PublishProperties, SubAck, SubAckProperties, UnsubAck,
    },
    ConnectionId, Filter,
};

mod connection;
mod graveyard;
mod holds;
pub mod ids; // fbbus
pub mod iobufs;
mod logs;
mod retained; // fbbus
mod routing;
mod scheduler;
pub(crate) mod shared_subs;
mod waiters;
pub(crate) mod wakeup; // fbbus

pub use connection::Connection;
pub use graveyard::{SavedSessions, DEFAULT_MAX_SAVED_SESSIONS};
pub use retained::{RetainLimit, RetainedStats};
pub use routing::Router;
pub(crate) use routing::TOPIC_ALIAS_MAX; // fbbus: `LinkBuilder::build_linked`
pub use waiters::Waiters;

/// fbbus: called for every skip (`RouterHooks::skipped`).
pub type SkipHook = Box<dyn FnMut(&Skipped<'_>) + Send>;
/// fbbus: called for every released hold (`RouterHooks::held`).
pub type HeldHook = Box<dyn FnMut(&Held<'_>) + Send>;

/// fbbus: what the router tells the broker embedding it. The callbacks run on the router
/// thread, between two events: they must be quick and must not wait on the router.
pub struct RouterHooks {
    /// A subscriber read past messages the filter's commit log no longer held: it lagged
    /// by more than `max_segment_count` segments and retention dropped them unread.
    pub skipped: Option<SkipHook>,
    /// The offline persistent sessions the router keeps, and how many it dropped at
    /// `RouterConfig::max_saved_sessions`: the router updates the counters, the embedder
    /// reads them (keep a clone of the `Arc`).
    pub saved_sessions: std::sync::Arc<SavedSessions>,
    /// The retained messages the router keeps, and the retained publications it did not
    /// keep at `RouterConfig::max_retained_messages` / `max_retained_bytes` (`retained`):
    /// updated by the router, read by the embedder (keep a clone of the `Arc`).
    pub retained: std::sync::Arc<RetainedStats>,
    /// Called after the router released the memory no reader needs any more (read
    /// commit-log segments, empty per-connection queues): once it had no event for
    /// `idle_after`, and while events keep coming, at most every `release_every`.
    /// Without it the router never releases memory early (upstream behaviour). It runs on
    /// the thread that frees the released segments (`freer`), after they are freed.
    pub released: Option<std::sync::Arc<dyn Fn() + Send + Sync>>,
    pub idle_after: std::time::Duration,
    pub release_every: std::time::Duration,
    /// Longest time a publisher is held back for a reader that would otherwise lose
    /// messages it has not read (`holds`). Zero: never held (upstream behaviour: the reader
    /// skips what retention drops).
    pub hold_limit: std::time::Duration,
    /// Called when publishers held for a filter are let go.
    pub held: Option<HeldHook>,
    /// Called on the router thread when the router stops for good: its loop returned
    /// (`RouterError`, e.g. every link gone) or it panicked (the panic's message). Nothing
    /// is routed after this: the embedder must stop serving (fbbus exits non-zero).
    pub exited: Option<Box<dyn FnOnce(String) + Send>>,
    /// Tests only: the router panics when it routes a publication on exactly this topic,
    /// so the embedder's handling of a dead router can be tested. fbbus sets it only in
    /// debug builds, from an environment variable.
    pub panic_on_topic: Option<String>,
}

impl Default for RouterHooks {
    fn default() -> Self {
        RouterHooks {
            skipped: None,
            saved_sessions: Default::default(),
            retained: Default::default(),
            released: None,
            idle_after: std::time::Duration::from_millis(500),
            release_every: std::time::Duration::from_secs(10),
            hold_limit: std::time::Duration::ZERO,
            held: None,
            exited: None,
            panic_on_topic: None,
        }
    }
}

/// fbbus: publishers were held back on a filter because one of its readers was about to
/// lose messages it had not read (`holds`), and are now let go.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Held<'a> {
    pub filter: &'a str,
    /// Connections that were held (each once, however many publishes it had queued).
    pub publishers: usize,
    pub waited: std::time::Duration,
    /// The readers did not catch up within `hold_limit`: the ones still behind now skip.
    pub gave_up: bool,
}

/// fbbus: messages one subscriber did not get because the commit log had dropped them.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Skipped<'a> {
    pub client_id: &'a str,
    pub filter: &'a str,
    /// Messages skipped by this read.
    pub count: u64,
    /// True for the first skip since this subscription last caught up with its filter.
    pub first_in_episode: bool,
}

pub const MAX_SCHEDULE_ITERATIONS: usize = 100;
pub const MAX_CHANNEL_CAPACITY: usize = 200;

pub(crate) type FilterIdx = usize;

#[derive(Debug)]
// TODO: Fix this
#[allow(clippy::large_enum_variant)]
pub enum Event {
    /// Client id and connection handle
    Connect {
        connection: connection::Connection,
        incoming: iobufs::Incoming,
        outgoing: iobufs::Outgoing,
    },
    /// Connection ready to receive more data
    Ready,
    /// Data for native commitlog
    DeviceData,
    /// Disconnection request
    Disconnect,
    /// Shadow
    Shadow(ShadowRequest),
    /// Publish Will message
    PublishWill((String, Option<String>)),
}

/// Notification from router to connection
#[derive(Debug, Clone)]
pub enum Notification {
    /// Data reply
    Forward(Forward),
    /// Acks reply for connection data
    DeviceAck(Ack),
    /// Data reply
    ReplicaData {
        cursor: (u64, u64),
        size: usize,
        payload: Bytes,
    },
    /// Acks reply for replication data
    ReplicaAcks {
        offset: (u64, u64),
        payload: Bytes,
    },
    /// Shadow
    Shadow(ShadowReply),
    Unschedule,
    Disconnect(Disconnect, Option<DisconnectProperties>),
}

type MaybePacket = Option<Packet>;

// We either get a Packet to write to buffer or we unschedule which is represented as `None`
impl From<Notification> for MaybePacket {
    fn from(notification: Notification) -> Self {
        let packet: Packet = match notification {
            Notification::Forward(forward) => Packet::Publish(forward.publish, forward.properties),
            Notification::DeviceAck(ack) => ack.into(),
            Notification::Unschedule => return None,
            Notification::Disconnect(disconnect, props) => Packet::Disconnect(disconnect, props),
            v => {
                tracing::error!("Unexpected notification here, it cannot be converted into Packet, Notification: {:?}", v);
                return None;
            }
        };
        Some(packet)
    }
}

#[derive(Debug, Clone)]
pub struct Forward {
    pub cursor: Option<(u64, u64)>,
    pub size: usize,
    pub publish: Publish,
    pub properties: Option<Box<PublishProperties>>,
}

#[derive(Debug, Clone)]
#[allow(clippy::enum_variant_names)]
pub enum Ack {
    ConnAck(ConnectionId, ConnAck, Option<Box<ConnAckProperties>>),
    // NOTE: using Option may be a better choice than new variant
    // ConnAckWithProperties(ConnectionId, ConnAck, ConnAckProperties),
    // TODO: merge the other variants as well using the same pattern
    PubAck(PubAck),
    PubAckWithProperties(PubAck, PubAckProperties),
    SubAck(SubAck),
    SubAckWithProperties(SubAck, SubAckProperties),
    PubRec(PubRec),
    PubRecWithProperties(PubRec, PubRecProperties),
    PubRel(PubRel),
    PubRelWithProperties(PubRel, PubRelProperties),
    PubComp(PubComp),
    PubCompWithProperties(PubComp, PubCompProperties),
    UnsubAck(UnsubAck),
    PingResp(PingResp),
}

impl From<Ack> for Packet {
    fn from(value: Ack) -> Self {
        match value {
            Ack::ConnAck(_id, connack, props) => Packet::ConnAck(connack, props),
            Ack::PubAck(puback) => Packet::PubAck(puback, None),
            Ack::PubAckWithProperties(puback, prop) => Packet::PubAck(puback, Some(prop)),
            Ack::SubAck(suback) => Packet::SubAck(suback, None),
            Ack::SubAckWithProperties(suback, prop) => Packet::SubAck(suback, Some(prop)),
            Ack::PubRec(pubrec) => Packet::PubRec(pubrec, None),
            Ack::PubRecWithProperties(pubrec, prop) => Packet::PubRec(pubrec, Some(prop)),
            Ack::PubRel(pubrel) => Packet::PubRel(pubrel, None),
            Ack::PubRelWithProperties(pubrel, prop) => Packet::PubRel(pubrel, Some(prop)),
            Ack::PubComp(pubcomp) => Packet::PubComp(pubcomp, None),
            Ack::PubCompWithProperties(pubcomp, prop) => Packet::PubComp(pubcomp, Some(prop)),
            Ack::UnsubAck(unsuback) => Packet::UnsubAck(unsuback, None),
            Ack::PingResp(pingresp) => Packet::PingResp(pingresp),
        }
    }
}

fn packetid(ack: &Ack) -> u16 {
    match ack {
        Ack::ConnAck(..) => 0,
        Ack::PubAck(puback) => puback.pkid,
        Ack::PubAckWithProperties(puback, _) => puback.pkid,
        Ack::SubAck(suback) => suback.pkid,
        Ack::SubAckWithProperties(suback, _) => suback.pkid,
        Ack::PubRel(pubrel) => pubrel.pkid,
        Ack::PubRelWithProperties(pubrel, _) => pubrel.pkid,
        Ack::PubRec(pubrec) => pubrec.pkid,
        Ack::PubRecWithProperties(pubrec, _) => pubrec.pkid,
        Ack::PubComp(pubcomp) => pubcomp.pkid,
        Ack::PubCompWithProperties(pubcomp, _) => pubcomp.pkid,
        Ack::UnsubAck(unsuback) => unsuback.pkid,
        Ack::PingResp(_) => 0,
    }
}

/// Request that connection/linker makes to extract data from commitlog
/// NOTE Connection can make one sweep request to get data from multiple topics
/// but we'll keep it simple for now as multiple requests in one message can
/// makes constant extraction size harder
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
pub struct DataRequest {
    /// Commitlog this request is pulling data from
    pub filter: Filter,
    pub filter_idx: FilterIdx,
    /// Qos of the outgoing data
    pub qos: u8,
    /// (segment, offset) tuples per replica (1 native and 2 replicas)
    pub cursor: (u64, u64),
    /// number of messages read from subscription
    pub read_count: usize,
    /// Maximum count of payload buffer per replica
    max_count: usize,
    pub(crate) forward_retained: bool,
    /// fbbus: repeated SUBSCRIBEs that asked for the retained messages again while a
    /// sending of them was still pending: each gets its own copy, one read after another.
    #[serde(default)]
    pub(crate) retained_again: u8,
    pub(crate) group: Option<String>,
    /// fbbus: the last read skipped messages and the reader has not caught up since.
    #[serde(default)]
    pub(crate) skipping: bool,
    /// fbbus: publishers were held for this reader for `hold_limit` and it was still
    /// behind: until it catches up it no longer holds them back (`holds`).
    #[serde(default)]
    pub(crate) slow: bool,
    /// fbbus: the retained messages of this SUBSCRIBE still to send, read once and sent a
    /// window at a time. Upstream read them all on every round and dropped what did not
    /// fit the window (`max_outgoing_packet_count`): a subscriber of a line with more
    /// than 1,000 retained messages got 1,000 of them.
    #[serde(skip)]
    pub(crate) retained_pending: RetainedPending,
}

/// fbbus: retained messages still to send for a request ([`DataRequest::retained_pending`]).
/// Compared by length only: a request's identity is its filter and cursor.
#[derive(Debug, Clone, Default)]
#[allow(clippy::type_complexity)]
pub struct RetainedPending(
    pub(crate)  Option<
        Box<
            std::collections::VecDeque<(
                crate::protocol::Publish,
                Option<Box<crate::protocol::PublishProperties>>,
            )>,
        >,
    >,
);

impl PartialEq for RetainedPending {
    fn eq(&self, other: &Self) -> bool {
        self.0.as_ref().map(|p| p.len()) == other.0.as_ref().map(|p| p.len())
    }
}

impl Eq for RetainedPending {}

#[derive(Debug, Clone)]
pub struct ShadowRequest {
    pub filter: String,
}

#[derive(Debug, Clone)]
pub struct ShadowReply {
    pub topic: Bytes,
    pub payload: Bytes,
}

#[derive(Debug, Default, Clone, Serialize, Deserialize)]
pub struct ConnectionEvents {
    events: VecDeque<String>,
}

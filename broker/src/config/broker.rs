//! `[broker]`: the line's name and the bounds of its connections, packets, router and
//! clients, the section no single module owns (the router takes its share through
//! [`BrokerSection::router`]).

use std::time::Duration;

use serde::Deserialize;

/// Most connections `broker.max_connections` may allow. The router reserves a slot per
/// connection when it starts, and the connection semaphore counts at most
/// `tokio::sync::Semaphore::MAX_PERMITS`: before this bound, a typo such as
/// `max_connections = 9000000000000000000` validated and then panicked at startup
/// (found with broker/fuzz `config_load`).
pub const MAX_CONNECTIONS: usize = 1_000_000;
const _: () = assert!(MAX_CONNECTIONS < tokio::sync::Semaphore::MAX_PERMITS);

/// `broker.slow_consumer_max_bytes` is at least this more than `max_packet_bytes`: the
/// size of the batches `session::deliver` writes, which the session layer sets.
pub const MIN_QUEUED_BYTES: usize = crate::session::WRITE_BATCH;

#[derive(Debug, Clone, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct BrokerSection {
    /// Name of the production line this broker serves.
    pub line: String,
    /// Connections accepted at once, over all listeners.
    pub max_connections: usize,
    /// Largest MQTT packet accepted, in bytes (fixed header included).
    pub max_packet_bytes: usize,
    /// Packets read from one connection before they are handed to the router as a batch;
    /// also the MQTT 5 receive maximum the broker announces.
    pub max_inflight: u16,
    /// QoS 1/2 deliveries sent to one connection before the broker waits for its
    /// acknowledgements (the router's window towards each subscriber).
    pub max_inflight_out: u16,
    /// Subscriptions one connection holds at most; a SUBSCRIBE beyond is refused for the
    /// filters over the limit (MQTT 5: 0x97 Quota exceeded; 3.1.1: 0x80).
    pub max_subscriptions_per_client: usize,
    /// Retained messages clients can make the broker keep, and their bytes (topic and
    /// payload). A retained publication on a topic without a retained message beyond
    /// either is not retained (it is still delivered to the subscribers of the moment;
    /// MQTT 5 QoS 1: PUBACK 0x97 Quota exceeded); replacing or clearing a retained message
    /// always works. The broker's own `fbbus/` topics are not counted.
    pub max_retained_messages: usize,
    pub max_retained_bytes: usize,
    /// What one identity (as `max_sessions_per_identity`) holds of them (issue 33: shares,
    /// not one pool): beyond, its new retained topics are refused the same way, while
    /// every other identity keeps its own share (`retained_share`).
    pub max_retained_messages_per_identity: usize,
    pub max_retained_bytes_per_identity: usize,
    /// Connections and persistent sessions one identity holds at most (the username; the
    /// peer IP address where there is no password file); a CONNECT beyond is refused
    /// (MQTT 5: 0x97 Quota exceeded; 3.1.1: 0x05 Not authorized).
    pub max_sessions_per_identity: usize,
    /// Time a new TCP connection has to send CONNECT.
    pub connect_timeout_ms: u64,
    /// Connections one source address may have open before their CONNECT (`pending`).
    pub max_pending_per_address: usize,
    /// Longest keep-alive an MQTT 5 client may use; one asking for more, or for none, is
    /// told this value as Server Keep Alive. 0: no maximum.
    pub max_keep_alive_s: u16,
    /// Router commit-log segment size per subscribed filter.
    pub router_segment_bytes: usize,
    /// Segments kept per filter: memory per filter is at most size x count. It is also how
    /// far a subscriber may fall behind on that filter before it skips messages: the
    /// defaults (4 MiB x 4) keep the reference study's largest burst (81,920 messages)
    /// lossless for a subscriber that cannot keep up.
    pub router_segment_count: usize,
    /// Messages queued towards one connection before the router pauses delivery to it.
    pub router_max_outgoing_packets: u64,
    /// Longest time the publishers of a filter are held back for a subscriber that would
    /// otherwise lose messages it has not read (the filter's commit log is full); 0: never
    /// held, a lagging subscriber skips.
    pub slow_subscriber_hold_ms: u64,
    /// Longest time a write to a client (at most 1 MiB and a packet) may wait for its
    /// socket: a write that has not completed by then closes the connection as a slow
    /// consumer (its will is published). Every socket write has this deadline.
    pub slow_consumer_timeout_ms: u64,
    /// Most outgoing bytes queued for one connection (unwritten, and held for its MQTT 5
    /// Receive Maximum); a connection with more is closed as a slow consumer at once.
    pub slow_consumer_max_bytes: usize,
    /// TCP keep-alive and `TCP_USER_TIMEOUT` on every accepted socket: a peer that
    /// vanished (power cut, pulled cable) is noticed by the kernel within about this long,
    /// whatever the client's MQTT keep-alive (0 included). 0: the kernel's defaults.
    pub dead_link_timeout_s: u64,
    /// How often the broker publishes its `$SYS/` status topics (Mosquitto's
    /// `sys_interval`); 0: never.
    pub sys_interval_s: u64,
    /// Threads that run the connections (tokio's workers). 0: one fewer than the cores,
    /// at least one ([`BrokerSection::workers`]).
    pub worker_threads: usize,
}

/// Most `broker.worker_threads`: more threads than this are contention, not capacity.
pub const MAX_WORKER_THREADS: usize = 256;

impl BrokerSection {
    /// The connections' threads: `worker_threads`, or for 0 one fewer than `cores`, at
    /// least one.
    ///
    /// Why one fewer: every message passes the router's thread (`docs/architecture.md`,
    /// "Threads and hand-offs"), which is busy whenever the line is, so a worker per core
    /// besides it only makes three threads take turns on two cores. Measured on 2 cores
    /// (`fbbus-loadtest compare`, one worker against two, alternating, two runs of 4 and 5
    /// rounds): burst fan-in 1.12-1.13x, independent pairs 1.04-1.37x, QoS 1 fan-in
    /// 0.98-1.02x, steady latency p50 0.89-0.97x, connections per second 0.91-1.14x. On one
    /// core: one worker.
    pub fn workers(&self, cores: usize) -> usize {
        match self.worker_threads {
            0 => cores.saturating_sub(1).max(1),
            n => n,
        }
    }

    /// The router's share of `[broker]`.
    pub(crate) fn router(&self) -> crate::router::Settings {
        crate::router::Settings {
            max_connections: self.max_connections,
            max_outgoing_packets: self.router_max_outgoing_packets,
            segment_bytes: self.router_segment_bytes,
            segment_count: self.router_segment_count,
            max_retained_messages: self.max_retained_messages,
            max_retained_bytes: self.max_retained_bytes,
            slow_subscriber_hold: Duration::from_millis(self.slow_subscriber_hold_ms),
            max_inflight_out: self.max_inflight_out,
        }
    }
}

impl Default for BrokerSection {
    fn default() -> Self {
        BrokerSection {
            line: "line-1".into(),
            max_connections: 4096,
            max_packet_bytes: 64 * 1024,
            max_inflight: 100,
            // FlashMQ's default queue of unacknowledged QoS messages per client. At 100
            // (rumqttd's), one subscriber taking a line's QoS 1 traffic waited on its
            // acknowledgements: 2.3-3.2x fewer msg/s in the QoS 1 fan-in (docs/performance.md).
            max_inflight_out: 512,
            max_subscriptions_per_client: 1000,
            max_retained_messages: 100_000,
            max_retained_bytes: 64 * 1024 * 1024,
            // A tenth of the messages and an eighth of the bytes: a device's last values
            // many times over, and ten identities, not one, to fill the router.
            max_retained_messages_per_identity: 10_000,
            max_retained_bytes_per_identity: 8 * 1024 * 1024,
            max_sessions_per_identity: 1000,
            connect_timeout_ms: 5_000,
            max_pending_per_address: 512,
            max_keep_alive_s: 65_535,
            router_segment_bytes: 4 * 1024 * 1024,
            router_segment_count: 4,
            router_max_outgoing_packets: 1_000,
            slow_subscriber_hold_ms: 1_000,
            slow_consumer_timeout_ms: 10_000,
            slow_consumer_max_bytes: 64 * 1024 * 1024,
            dead_link_timeout_s: 20,
            sys_interval_s: 10,
            worker_threads: 0,
        }
    }
}

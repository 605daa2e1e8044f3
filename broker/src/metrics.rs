//! Prometheus metrics, served as text at `/metrics` on the admin port.
//!
//! Labels are low-cardinality on purpose (reasons, actions, files), never client ids,
//! user names or topics: a line of a thousand devices must not become a thousand series,
//! and a metric must never carry a secret. Per-client detail goes to the log, once.

use prometheus::{
    Encoder, Histogram, HistogramOpts, IntCounter, IntCounterVec, IntGauge, IntGaugeVec, Opts,
    Registry, TextEncoder,
};
use rumqttd::SavedSessions;
use std::sync::{Arc, Mutex, PoisonError};

/// Why a connection ended; the `reason` label of `fbbus_disconnects_total`.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum DisconnectReason {
    /// The client sent DISCONNECT.
    Client,
    /// MQTT 5 DISCONNECT with reason 0x04: the client asked for its will.
    ClientWithWill,
    /// The TCP connection closed or reset without DISCONNECT.
    Abrupt,
    /// Nothing received for 1.5 x keep-alive.
    KeepAlive,
    /// The client did not take its outgoing data in time (`broker.slow_consumer_timeout_ms`)
    /// or let too much of it queue (`broker.slow_consumer_max_bytes`).
    SlowConsumer,
    /// Another connection with the same client id took the session over.
    Takeover,
    /// The client sent bytes that are not MQTT.
    Malformed,
    /// The client sent a packet larger than `max_packet_bytes`.
    Oversized,
    /// The client broke a protocol rule (e.g. a second CONNECT, a wildcard in a topic).
    ProtocolError,
    /// The router ended the connection.
    Router,
    /// The broker is shutting down.
    Shutdown,
    /// fbbus failed while serving this connection (a panic in its task, logged): the
    /// connection is closed as if it had been lost, the rest of the line goes on.
    Internal,
}

impl DisconnectReason {
    pub fn label(self) -> &'static str {
        match self {
            DisconnectReason::Client => "client",
            DisconnectReason::ClientWithWill => "client_with_will",
            DisconnectReason::Abrupt => "abrupt",
            DisconnectReason::KeepAlive => "keep_alive",
            DisconnectReason::SlowConsumer => "slow_consumer",
            DisconnectReason::Takeover => "takeover",
            DisconnectReason::Malformed => "malformed",
            DisconnectReason::Oversized => "oversized",
            DisconnectReason::ProtocolError => "protocol_error",
            DisconnectReason::Router => "router",
            DisconnectReason::Shutdown => "shutdown",
            DisconnectReason::Internal => "internal_error",
        }
    }

    /// Words for people: the device registry's `last_will_reason`.
    pub fn description(self) -> &'static str {
        match self {
            DisconnectReason::Client => "clean disconnect",
            DisconnectReason::ClientWithWill => "disconnect with will",
            DisconnectReason::Abrupt => "connection lost",
            DisconnectReason::KeepAlive => "keep-alive expired",
            DisconnectReason::SlowConsumer => "slow consumer",
            DisconnectReason::Takeover => "taken over by a new connection",
            DisconnectReason::Malformed => "malformed packet",
            DisconnectReason::Oversized => "packet too large",
            DisconnectReason::ProtocolError => "protocol error",
            DisconnectReason::Router => "dropped by the router",
            DisconnectReason::Shutdown => "broker shutdown",
            DisconnectReason::Internal => "broker internal error",
        }
    }
}

/// Every metric the broker exports.
pub struct Metrics {
    registry: Registry,
    pub connections: IntGauge,
    /// The most connections open at once since start (`$SYS/broker/clients/maximum`).
    connections_peak: std::sync::atomic::AtomicI64,
    /// Connections open and accepted per listener (after TLS and, for `ws`, the WebSocket
    /// handshake), labelled `listener` and `transport` (mqtt, mqtts, ws, wss).
    pub listener_connections: IntGaugeVec,
    pub listener_accepted: IntCounterVec,
    pub connects: IntCounter,
    pub connects_refused: IntCounterVec,
    pub disconnects: IntCounterVec,
    pub auth_failures: IntCounterVec,
    pub logins_throttled: IntCounter,
    pub auth_cache_hits: IntCounter,
    pub auth_verify_seconds: Histogram,
    pub passwords_rehashed: IntCounter,
    pub acl_denied: IntCounterVec,
    pub messages_in: IntCounter,
    pub messages_out: IntCounter,
    pub bytes_in: IntCounter,
    pub bytes_out: IntCounter,
    pub wills_published: IntCounter,
    pub messages_dropped: IntCounterVec,
    pub messages_skipped: IntCounter,
    pub publisher_holds: IntCounterVec,
    pub publisher_hold_ms: IntCounter,
    pub malformed_packets: IntCounter,
    pub oversized_packets: IntCounter,
    /// Takeovers whose old connection did not finish reading in time (`session::takeover`).
    pub takeovers_unfinished: IntCounter,
    /// Kept sessions an operator dropped (`session::control`).
    pub sessions_dropped: IntCounter,
    pub reloads: IntCounterVec,
    pub typed_accepted: IntCounter,
    pub typed_rejected: IntCounterVec,
    /// Every typed publication refused, whatever its labels (the console's rates: the
    /// labelled series would have to be summed).
    pub typed_refused_all: std::sync::atomic::AtomicU64,
    pub typed_not_reencoded: IntCounterVec,
    pub declarations: IntCounterVec,
    /// Diagnostics not published on `fbbus/diag/<device>`: over `[fb] diag_per_second`.
    pub diag_dropped: IntCounter,
    pub registry_devices: IntGaugeVec,
    /// Online devices whose periodic outputs stopped (`silence`), included in
    /// `registry_devices{status="online"}`.
    pub registry_silent_devices: IntGauge,
    pub registry_stale_ends: IntCounter,
    pub registry_silence_offline: IntCounter,
    /// Devices forgotten, by reason (`expired`, `admin`).
    pub registry_forgotten: IntCounterVec,
    /// The zenoh bridge between lines (`bridge`): all zero without a `[bridge]` section.
    pub bridge_messages: IntCounterVec,
    pub bridge_dropped: IntCounterVec,
    bridge_refused: IntCounterVec,
    /// Origin lines with a `bridge_refused` label of their own (see [`Metrics::bus_refused`]).
    refused_lines: Mutex<std::collections::HashSet<String>>,
    /// (device, port) pairs with `typed_rejected` series of their own ([`Metrics::typed_refused`]).
    typed_ports: Mutex<std::collections::HashSet<(String, String)>>,
    pub bridge_remote_subscriptions: IntGauge,
    pub bridge_imports: IntGauge,
    /// With `[bridge] session_per_router`: the line's sessions, and those whose router is
    /// there (0 and 0 otherwise).
    pub bridge_router_sessions: IntGauge,
    pub bridge_router_sessions_up: IntGauge,
    pub bridge_liveliness: IntCounterVec,
    /// Registry queries this line sent other lines (`bridge::federation`).
    pub bridge_record_queries: IntCounterVec,
    pub bridge_retained_replayed: IntCounter,
    /// Messages of other lines that never arrived (gaps in a topic's numbering).
    pub bridge_lost: IntCounter,
    pub bridge_lost_reported: IntCounter,
    /// Requests refused at a limit, by limit (`subscriptions_per_client`, ...).
    pub limit_refusals: IntCounterVec,
    /// Admin HTTP connections open now, and those closed at `[admin] max_connections`.
    pub admin_connections: IntGauge,
    /// MQTT connections the listeners accept at once: `[broker] max_connections`, or less
    /// if the open-file limit is lower (`fd_budget`).
    pub connection_limit: IntGauge,
    pub admin_refused: IntCounter,
    /// Admin requests refused for their credentials (`[admin] password_file`), by reason:
    /// missing, invalid, throttled.
    pub admin_auth_failures: IntCounterVec,
    pub admin_writes_refused: IntCounterVec,
    /// The router's offline persistent sessions, which it updates itself
    /// (`RouterHooks::saved_sessions`); copied into the two metrics below at each scrape.
    pub router_sessions: Arc<SavedSessions>,
    saved_sessions: IntGauge,
    saved_sessions_dropped: IntCounter,
    /// The router's retained store (`RouterHooks::retained`): copied into the gauges below
    /// and, its refusals, into `limit_refusals` at each scrape.
    pub router_retained: Arc<rumqttd::RetainedStats>,
    retained_messages: IntGauge,
    retained_bytes: IntGauge,
    /// Serializes the copy into the counter above (two scrapes at once would add twice).
    scrape: Mutex<()>,
}

impl Metrics {
    pub fn new() -> Metrics {
        let registry = Registry::new();
        let counter = |name: &str, help: &str| {
            let c = IntCounter::new(name, help).expect("valid metric");
            registry
                .register(Box::new(c.clone()))
                .expect("unique metric");
            c
        };
        let counter_vec = |name: &str, help: &str, labels: &[&str]| {
            let c = IntCounterVec::new(Opts::new(name, help), labels).expect("valid metric");
            registry
                .register(Box::new(c.clone()))
                .expect("unique metric");
            c
        };
        let connections =
            IntGauge::new("fbbus_connections", "MQTT connections currently open").expect("valid");
        registry
            .register(Box::new(connections.clone()))
            .expect("unique metric");
        let auth_verify_seconds = Histogram::with_opts(
            HistogramOpts::new(
                "fbbus_auth_verify_seconds",
                "Time to verify a password, queueing included (cache hits are not observed)",
            )
            .buckets(vec![
                0.001, 0.002, 0.005, 0.01, 0.02, 0.05, 0.1, 0.25, 0.5, 1.0, 2.5, 5.0,
            ]),
        )
        .expect("valid");
        registry
            .register(Box::new(auth_verify_seconds.clone()))
            .expect("unique metric");

        let registry_devices = IntGaugeVec::new(
            Opts::new(
                "fbbus_registry_devices",
                "Devices in the registry, by status",
            ),
            &["status"],
        )
        .expect("valid");
        registry
            .register(Box::new(registry_devices.clone()))
            .expect("unique metric");

        let gauge = |name: &str, help: &str| {
            let g = IntGauge::new(name, help).expect("valid metric");
            registry
                .register(Box::new(g.clone()))
                .expect("unique metric");
            g
        };

        let listener_connections = IntGaugeVec::new(
            Opts::new(
                "fbbus_listener_connections",
                "Connections open per listener, by transport (mqtt, mqtts, ws, wss); \
                 CONNECT not necessarily read yet",
            ),
            &["listener", "transport"],
        )
        .expect("valid");
        registry
            .register(Box::new(listener_connections.clone()))
            .expect("unique metric");

        Metrics {
            connections_peak: Default::default(),
            listener_connections,
            listener_accepted: counter_vec(
                "fbbus_listener_accepted_total",
                "Connections accepted per listener, by transport, once TLS and the WebSocket \
                 handshake (ws, wss) completed",
                &["listener", "transport"],
            ),
            bridge_messages: counter_vec(
                "fbbus_bridge_messages_total",
                "Messages carried by the zenoh bridge, by direction (export: to other lines, import: from them)",
                &["direction"],
            ),
            // Exported from the start at 0, like every closed set of reasons a dashboard
            // plots (deploy/grafana/fbbus.json): a quiet line shows 0, not "no data".
            bridge_dropped: with_series(
                counter_vec(
                    "fbbus_bridge_dropped_total",
                    "Bridged messages not delivered, by reason (duplicate: a copy, one per router path with session_per_router; late: older than one of its topic taken already; acl, type, filter, unbridgeable, zenoh_error)",
                    &["reason"],
                ),
                &[
                    &["duplicate"],
                    &["late"],
                    &["acl"],
                    &["type"],
                    &["filter"],
                    &["unbridgeable"],
                    &["zenoh_error"],
                ],
            ),
            bridge_refused: counter_vec(
                "fbbus_bridge_refused_total",
                "Messages from other lines refused because they did not come from where they \
                 claim, by origin line (at most 64 lines, then `other`) and reason \
                 (forged_origin, unknown_device, local_device, other_line_device; for registry records: \
                 forged_record, local_device, claimed_device, line_share, remote_full)",
                &["line", "reason"],
            ),
            bridge_remote_subscriptions: gauge(
                "fbbus_bridge_remote_subscriptions",
                "(line, filter) pairs other lines subscribed to on this line",
            ),
            bridge_imports: gauge(
                "fbbus_bridge_imports",
                "Filters this line imports from other lines (its clients subscribed to them)",
            ),
            bridge_router_sessions: gauge(
                "fbbus_bridge_router_sessions",
                "With [bridge] session_per_router: this line's zenoh sessions, one per router (0 otherwise)",
            ),
            bridge_router_sessions_up: gauge(
                "fbbus_bridge_router_sessions_up",
                "With [bridge] session_per_router: the sessions whose router is there now (below fbbus_bridge_router_sessions: the line is on fewer routers than it should be)",
            ),
            bridge_liveliness: counter_vec(
                "fbbus_bridge_liveliness_changes_total",
                "Liveliness changes seen on the bus, by kind (line_up, line_down, device_up, device_down; forgotten: another line forgot its device, and so did this line)",
                &["kind"],
            ),
            bridge_record_queries: counter_vec(
                "fbbus_bridge_record_queries_total",
                "Registry queries sent to other lines for records missed: one device's, or a whole line's (kind device, line)",
                &["kind"],
            ),
            bridge_retained_replayed: counter(
                "fbbus_bridge_retained_replayed_total",
                "Retained messages fetched from other lines when this line started importing a filter",
            ),
            bridge_lost: counter(
                "fbbus_bridge_lost_total",
                "Messages of other lines that never reached this line: gaps in the numbering \
                 each line gives every topic it puts on the bus (a router that died with \
                 messages queued, a cut link); see docs/device-contract.md, the bus",
            ),
            bridge_lost_reported: counter(
                "fbbus_bridge_lost_reported_total",
                "Messages this line put on the bus that other lines reported never reached \
                 them (the sum of their fbbus_bridge_lost_total for this line, reported \
                 within about a second)",
            ),
            connections,
            limit_refusals: counter_vec(
                "fbbus_limit_refusals_total",
                "Requests refused because a configured limit was reached, by limit \
                 (subscriptions_per_client, retained_messages, retained_bytes, \
                 sessions_per_identity, devices, devices_per_identity, declaration_bytes, fbs, \
                 ports, encoded_size, declaration_rate, stored_publications: a QoS 1/2 \
                 publication the store did not keep for a persistent session, its store full \
                 or the publisher's own share spent, answered 0x97 to MQTT 5 publishers; \
                 remote_subscriptions_per_line, remote_subscriptions: another line's \
                 subscription not honoured)",
                &["limit"],
            ),
            connection_limit: gauge(
                "fbbus_connection_limit",
                "MQTT connections accepted at once: [broker] max_connections, or less if the \
                 process's open-file limit (RLIMIT_NOFILE) cannot hold it beside the admin \
                 endpoint's share (logged at start)",
            ),
            admin_connections: gauge(
                "fbbus_admin_connections",
                "Admin HTTP connections open now ([admin] max_connections)",
            ),
            admin_refused: counter(
                "fbbus_admin_connections_refused_total",
                "Admin HTTP connections closed at once because [admin] max_connections were open",
            ),
            admin_auth_failures: with_series(
                counter_vec(
                    "fbbus_admin_auth_failures_total",
                    "Admin HTTP requests refused for their credentials ([admin] password_file), \
                     by reason (missing: no HTTP Basic credentials, 401; invalid: unknown user, \
                     wrong password or a malformed header, 401; throttled: too many recent \
                     failures from the address, 429)",
                    &["reason"],
                ),
                &[&["missing"], &["invalid"], &["throttled"]],
            ),
            admin_writes_refused: with_series(
                counter_vec(
                    "fbbus_admin_writes_refused_total",
                    "Admin writes (PUT a profile, DELETE a device) refused with 403, by reason \
                     (remote: not from the broker's host; host, origin: the Host or Origin \
                     header names neither an IP address, localhost nor [admin] allowed_hosts)",
                    &["reason"],
                ),
                &[&["remote"], &["host"], &["origin"]],
            ),
            typed_accepted: counter(
                "fbbus_typed_messages_accepted_total",
                "Publications on typed FB topics that matched their declaration and were routed",
            ),
            typed_rejected: counter_vec(
                "fbbus_typed_messages_rejected_total",
                "Publications on typed FB topics refused, by device, port (fb.port) and reason",
                &["device", "port", "reason"],
            ),
            typed_refused_all: Default::default(),
            typed_not_reencoded: counter_vec(
                "fbbus_typed_messages_not_reencoded_total",
                "Accepted typed publications not delivered in one encoding because it cannot \
                 carry a value (fbdk nanoseconds end in 2554), by namespace (the device and port \
                 are in its fbbus/diag message: client-chosen names make no labels)",
                &["namespace"],
            ),
            declarations: counter_vec(
                "fbbus_declarations_total",
                "Interface declarations, by result (accepted, refused)",
                &["result"],
            ),
            diag_dropped: counter(
                "fbbus_diag_dropped_total",
                "Diagnostics for a device dropped over its rate ([fb] diag_per_second)",
            ),
            registry_devices,
            registry_silent_devices: gauge(
                "fbbus_registry_silent_devices",
                "Online devices whose periodic outputs stopped publishing (also counted as online)",
            ),
            registry_forgotten: with_series(
                counter_vec(
                    "fbbus_registry_forgotten_total",
                    "Devices removed from the registry with their retained record and values, \
                     by reason (expired: offline longer than [fb] forget_offline_after_s; \
                     admin: DELETE /api/v1/devices/{id}, fbbus devices forget)",
                    &["reason"],
                ),
                &[&["expired"], &["admin"]],
            ),
            registry_stale_ends: counter(
                "fbbus_registry_stale_ends_total",
                "Connection ends ignored by the registry because the device is on a newer session",
            ),
            registry_silence_offline: counter(
                "fbbus_registry_silence_offline_total",
                "Devices marked offline because their periodic outputs were silent longer than \
                 their profile's liveness.offline_after_silent_s (their connections stay open)",
            ),
            connects: counter("fbbus_connects_total", "CONNECTs accepted"),
            // The identity refusals (issue 20) exist at 0, so an alert on their first
            // increase sees it.
            connects_refused: with_series(
                counter_vec(
                    "fbbus_connects_refused_total",
                    "CONNECTs refused, by reason",
                    &["reason"],
                ),
                &[
                    &["client_id_owned"],
                    &["client_id_binding"],
                    &["client_id_reserved"],
                ],
            ),
            disconnects: counter_vec(
                "fbbus_disconnects_total",
                "Connections ended, by reason",
                &["reason"],
            ),
            auth_failures: with_series(
                counter_vec(
                    "fbbus_auth_failures_total",
                    "Failed logins: bad_credentials (wrong password or unknown user) or missing_credentials",
                    &["reason"],
                ),
                &[&["bad_credentials"], &["missing_credentials"]],
            ),
            logins_throttled: counter(
                "fbbus_logins_throttled_total",
                "CONNECTs refused because their address failed too often recently",
            ),
            auth_cache_hits: counter(
                "fbbus_auth_cache_hits_total",
                "Logins verified from the verified-credential cache (argon2 skipped)",
            ),
            auth_verify_seconds,
            passwords_rehashed: counter(
                "fbbus_passwords_rehashed_total",
                "Mosquitto password entries rewritten as argon2id after a successful login",
            ),
            acl_denied: with_series(
                counter_vec(
                    "fbbus_acl_denied_total",
                    "Operations refused by the access rules, by action (publish, subscribe, will, deliver)",
                    &["action"],
                ),
                &[&["publish"], &["subscribe"], &["will"], &["deliver"]],
            ),
            messages_in: counter("fbbus_messages_received_total", "PUBLISH packets received"),
            messages_out: counter("fbbus_messages_sent_total", "PUBLISH packets sent"),
            bytes_in: counter("fbbus_bytes_received_total", "MQTT bytes received"),
            bytes_out: counter("fbbus_bytes_sent_total", "MQTT bytes sent"),
            wills_published: counter("fbbus_wills_published_total", "Will messages published"),
            // Exported from the start at 0, so an alert on slow consumers has its series.
            messages_dropped: with_series(
                counter_vec(
                "fbbus_messages_dropped_total",
                "Deliveries not sent, by reason (client_max_packet_size; slow_consumer: QoS 0 \
                 deliveries a connection closed as a slow consumer, or at keep-alive expiry \
                 while a write waited, had not taken; connection_closed: the same at \
                 another end)",
                    &["reason"],
                ),
                &[&["client_max_packet_size"], &["slow_consumer"]],
            ),
            messages_skipped: counter(
                "fbbus_messages_skipped_total",
                "Messages a lagging subscriber never got: the router's commit log for its \
                 filter had dropped them before it read them (router_segment_count x \
                 router_segment_bytes per filter)",
            ),
            // Both outcomes are exported from the start, at 0: an alert on gave_up needs
            // the series before the first hold.
            publisher_holds: with_series(
                counter_vec(
                    "fbbus_publisher_holds_total",
                    "Times the publishers of a filter were held back because a subscriber \
                     would otherwise have lost messages it had not read, by outcome \
                     (caught_up: it read them; gave_up: held for slow_subscriber_hold_ms, \
                     it skips)",
                    &["outcome"],
                ),
                &[&["caught_up"], &["gave_up"]],
            ),
            publisher_hold_ms: counter(
                "fbbus_publisher_hold_milliseconds_total",
                "Time the publishers of filters were held back for lagging subscribers",
            ),
            malformed_packets: counter(
                "fbbus_malformed_packets_total",
                "Connections closed for bytes that are not valid MQTT",
            ),
            oversized_packets: counter(
                "fbbus_oversized_packets_total",
                "Connections closed for a packet over broker.max_packet_bytes",
            ),
            takeovers_unfinished: counter(
                "fbbus_takeovers_unfinished_total",
                "Takeovers that linked before the old connection read what its client had sent (it did not answer within 200 ms): those packets may be lost",
            ),
            sessions_dropped: counter(
                "fbbus_sessions_dropped_total",
                "Kept offline sessions dropped by an operator (admin API DELETE /api/v1/sessions/ID)",
            ),
            reloads: counter_vec(
                "fbbus_file_reloads_total",
                "Password file, ACL file and profiles directory reloads, by file and result",
                &["file", "result"],
            ),
            router_sessions: Arc::default(),
            saved_sessions: gauge(
                "fbbus_router_saved_sessions",
                "Offline persistent sessions (clean session 0) the router keeps for their \
                 clients; at most max(broker.max_connections, 4096)",
            ),
            saved_sessions_dropped: counter(
                "fbbus_router_saved_sessions_dropped_total",
                "Saved persistent sessions dropped, the oldest first, because the router \
                 kept as many as it may",
            ),
            router_retained: Arc::default(),
            retained_messages: gauge(
                "fbbus_retained_messages",
                "Retained messages the router keeps for clients (broker.max_retained_messages; \
                 the broker's own fbbus/ topics are not counted)",
            ),
            retained_bytes: gauge(
                "fbbus_retained_bytes",
                "Topic and payload bytes of those retained messages (broker.max_retained_bytes)",
            ),
            scrape: Mutex::new(()),
            refused_lines: Mutex::new(Default::default()),
            typed_ports: Mutex::new(Default::default()),
            registry,
        }
    }

    pub fn disconnected(&self, reason: DisconnectReason) {
        self.disconnects.with_label_values(&[reason.label()]).inc();
    }

    /// Records the connections open now as the peak if they are more than any before.
    pub fn note_connections_peak(&self) {
        self.connections_peak
            .fetch_max(self.connections.get(), std::sync::atomic::Ordering::Relaxed);
    }

    /// The most connections open at once since start.
    pub fn connections_peak(&self) -> i64 {
        self.connections_peak
            .load(std::sync::atomic::Ordering::Relaxed)
    }

    pub fn refused(&self, reason: &str) {
        self.connects_refused.with_label_values(&[reason]).inc();
    }

    /// Registers metrics kept by another part of the broker (`store`).
    pub fn register(&self, collector: Box<dyn prometheus::core::Collector>) {
        self.registry.register(collector).expect("unique metric");
    }

    /// The Prometheus text exposition of every metric.
    pub fn render(&self) -> String {
        self.copy_router_sessions();
        let mut out = Vec::new();
        TextEncoder::new()
            .encode(&self.registry.gather(), &mut out)
            .expect("text encoding to a Vec cannot fail");
        String::from_utf8(out).expect("prometheus text is UTF-8")
    }
}

/// Origin lines with a `fbbus_bridge_refused_total` label of their own; past this many
/// they share `other`: the line of a key is whatever an unauthenticated peer of a
/// loopback bus writes there.
pub const REFUSED_LINE_LABELS: usize = 64;

/// (device, port) pairs of `fbbus_typed_messages_rejected_total` with series of their own.
pub const TYPED_PORT_LABELS: usize = 1024;
/// Of those, the most one device's ports take: one device declaring or inventing port
/// names cannot take the series every other device's refusals need (issue 33). Its
/// further ports are counted under its own `port="other"`.
pub const TYPED_PORT_LABELS_PER_DEVICE: usize = 16;

impl Metrics {
    /// Counts a message or record from the bus refused because it does not come from
    /// where it claims (`line`: the line whose key it came on).
    pub fn bus_refused(&self, line: &str, reason: &str) {
        let mut lines = self
            .refused_lines
            .lock()
            .unwrap_or_else(PoisonError::into_inner);
        if !lines.contains(line) && lines.len() < REFUSED_LINE_LABELS {
            lines.insert(line.to_owned());
        }
        let label = if lines.contains(line) { line } else { "other" };
        self.bridge_refused
            .with_label_values(&[label, reason])
            .inc();
    }

    /// One typed publication refused, by device, port and reason. Device and port names are
    /// the clients' (a device may declare fresh port names without end): at most
    /// [`TYPED_PORT_LABELS`] (device, port) pairs get series of their own, at most
    /// [`TYPED_PORT_LABELS_PER_DEVICE`] of them one device's: a device's further ports are
    /// counted under its `port="other"`, and beyond the whole bound under device and port
    /// `other` (issue 21: 25,000 invented port names took `/metrics` from 7.5 KB to
    /// 3.6 MB; issue 33: one device must not take every series).
    pub fn typed_refused(&self, device: &str, port: &str, reason: &str) {
        let mut ports = self
            .typed_ports
            .lock()
            .unwrap_or_else(PoisonError::into_inner);
        let mut key = (device.to_owned(), port.to_owned());
        if !ports.contains(&key) {
            let own = ports.iter().filter(|(d, _)| d == device).count();
            if own >= TYPED_PORT_LABELS_PER_DEVICE {
                key.1 = "other".to_owned();
            }
            if !ports.contains(&key) && ports.len() < TYPED_PORT_LABELS {
                ports.insert(key.clone());
            }
        }
        let (device, port) = match ports.contains(&key) {
            true => (device, key.1.as_str()),
            false => ("other", "other"),
        };
        self.typed_rejected
            .with_label_values(&[device, port, reason])
            .inc();
        self.typed_refused_all
            .fetch_add(1, std::sync::atomic::Ordering::Relaxed);
    }

    /// Removes the series labelled with the forgotten device `device`: its
    /// `fbbus_typed_messages_rejected_total` series, whatever the port and reason (a
    /// device's series must not outlive it, or forgetting would not bound `/metrics`).
    pub fn forget_device(&self, device: &str) {
        let mut ports = self
            .typed_ports
            .lock()
            .unwrap_or_else(PoisonError::into_inner);
        let gone: std::collections::HashSet<(String, String)> =
            ports.iter().filter(|(d, _)| d == device).cloned().collect();
        if gone.is_empty() {
            return;
        }
        // Each reason one of its ports was refused for is a series of the vector: read
        // them from it, so that metrics need not know the policy's reasons.
        use prometheus::core::Collector as _;
        for family in self.typed_rejected.collect() {
            for metric in family.get_metric() {
                let label = |name: &str| {
                    metric
                        .get_label()
                        .iter()
                        .find(|l| l.get_name() == name)
                        .map_or("", |l| l.get_value())
                };
                let (device, port) = (label("device"), label("port"));
                if gone.contains(&(device.to_owned(), port.to_owned())) {
                    let _ =
                        self.typed_rejected
                            .remove_label_values(&[device, port, label("reason")]);
                }
            }
        }
        for key in gone {
            ports.remove(&key);
        }
    }

    /// The router's saved-session counters into their metrics.
    fn copy_router_sessions(&self) {
        let _one_at_a_time = self.scrape.lock().unwrap_or_else(PoisonError::into_inner);
        let sessions = &self.router_sessions;
        self.saved_sessions
            .set(i64::try_from(sessions.saved()).unwrap_or(i64::MAX));
        let dropped = sessions.dropped();
        let counted = self.saved_sessions_dropped.get();
        if dropped > counted {
            self.saved_sessions_dropped.inc_by(dropped - counted);
        }
        let retained = &self.router_retained;
        self.retained_messages
            .set(i64::try_from(retained.messages()).unwrap_or(i64::MAX));
        self.retained_bytes
            .set(i64::try_from(retained.bytes()).unwrap_or(i64::MAX));
        for (limit, label) in [
            (rumqttd::RetainLimit::Messages, "retained_messages"),
            (rumqttd::RetainLimit::Bytes, "retained_bytes"),
        ] {
            let refused = retained.refused(limit);
            let counter = self.limit_refusals.with_label_values(&[label]);
            let counted = counter.get();
            if refused > counted {
                counter.inc_by(refused - counted);
            }
        }
    }
}

impl Default for Metrics {
    fn default() -> Self {
        Metrics::new()
    }
}

/// The counter family with these label values created, so their series are exported at 0
/// before anything is counted.
fn with_series(counters: IntCounterVec, series: &[&[&str]]) -> IntCounterVec {
    for labels in series {
        counters.with_label_values(labels);
    }
    counters
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn typed_refusal_labels_are_bounded() {
        let m = Metrics::new();
        for i in 0..TYPED_PORT_LABELS + 500 {
            let device = format!("dev{}", i / 4);
            m.typed_refused(&device, &format!("FB.P{i}"), "payload_format_invalid");
        }
        // A known pair keeps its series.
        m.typed_refused("dev0", "FB.P0", "payload_format_invalid");
        let text = m.render();
        let series = text
            .lines()
            .filter(|l| l.starts_with("fbbus_typed_messages_rejected_total{"))
            .count();
        assert_eq!(
            series,
            TYPED_PORT_LABELS + 1,
            "own series, then one `other`"
        );
        assert_eq!(
            crate::metrics::tests::value(
                &text,
                "fbbus_typed_messages_rejected_total{device=\"other\",port=\"other\",reason=\"payload_format_invalid\"}"
            ),
            500.0
        );
    }

    /// One device inventing ports takes its share, then counts under its own `other`;
    /// another device still gets series of its own.
    #[test]
    fn one_device_takes_only_its_share_of_refusal_series() {
        let m = Metrics::new();
        for i in 0..5_000 {
            m.typed_refused("flood", &format!("FB.P{i}"), "payload_format_invalid");
        }
        m.typed_refused("plc-1", "CONV.SPEED", "payload_format_invalid");
        let text = m.render();
        let series = |device: &str| {
            text.lines()
                .filter(|l| l.starts_with("fbbus_typed_messages_rejected_total{"))
                .filter(|l| l.contains(&format!("device=\"{device}\"")))
                .count()
        };
        assert_eq!(series("flood"), TYPED_PORT_LABELS_PER_DEVICE + 1);
        assert_eq!(
            value(
                &text,
                "fbbus_typed_messages_rejected_total{device=\"flood\",port=\"other\",reason=\"payload_format_invalid\"}"
            ),
            (5_000 - TYPED_PORT_LABELS_PER_DEVICE) as f64
        );
        assert_eq!(
            value(
                &text,
                "fbbus_typed_messages_rejected_total{device=\"plc-1\",port=\"CONV.SPEED\",reason=\"payload_format_invalid\"}"
            ),
            1.0
        );
    }

    /// Forgetting a device removes its series, whatever the reasons its ports were
    /// refused for, and only its own.
    #[test]
    fn forgetting_a_device_removes_its_refusal_series() {
        let m = Metrics::new();
        m.typed_refused("devA", "FB.P1", "payload_format_invalid");
        m.typed_refused("devA", "FB.P1", "not_authorized");
        m.typed_refused("devA", "FB.P2", "quota_exceeded");
        m.typed_refused("devB", "FB.P1", "payload_format_invalid");
        m.forget_device("devA");
        let text = m.render();
        let series: Vec<&str> = text
            .lines()
            .filter(|l| l.starts_with("fbbus_typed_messages_rejected_total{"))
            .collect();
        assert_eq!(series.len(), 1, "{series:?}");
        assert!(series[0].contains("device=\"devB\""), "{series:?}");
    }

    fn value(text: &str, series: &str) -> f64 {
        text.lines()
            .find_map(|l| l.strip_prefix(series))
            .and_then(|v| v.trim().parse().ok())
            .unwrap_or(0.0)
    }
}

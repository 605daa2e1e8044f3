//! The broker's configuration: one TOML file, validated completely before anything binds.
//!
//! Every option is documented in `deploy/fbbus.example.toml`. The embedded default
//! ([`DEFAULT_CONFIG`]) is what `fbbus serve` runs with no `--config`: a loopback-only line
//! broker with anonymous access, so the first command of the README works on a fresh machine.
//!
//! Validation refuses a file with the file name, the key and what is wrong. The security
//! rules live here because they are configuration facts: a listener that is reachable from
//! the network must require a password, anonymous access is a loopback-only privilege, and
//! an admin endpoint reachable from the network must require credentials of its own
//! (`[admin] password_file`, never the devices' `[auth] password_file`).

use std::path::{Path, PathBuf};
use std::time::Duration;

use serde::Deserialize;

// Each section's type lives with the module it configures, which owns its defaults; this
// reader only assembles them (and is imported by none of them).
pub use crate::admin::AdminSection;
pub use crate::authenticator::{AuthSection, ThrottleSection};
pub use crate::console::ConsoleSection;
pub use crate::listener::ListenerSection;
pub use crate::logging::{LogFormat, LogSection};
pub use crate::store::PersistenceSection;
pub use crate::tls::TlsSection;

/// The configuration `fbbus serve` uses when no `--config` is given.
pub const DEFAULT_CONFIG: &str = r#"
[broker]
line = "line-1"

[[listener]]
name = "mqtt-loopback"
bind = "127.0.0.1:1883"
allow_anonymous = true

[admin]
bind = "127.0.0.1:9883"

# Retained messages and persistent sessions survive a restart, next to the registry.
[persistence]
dir = "fbbus-store"
"#;

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

#[derive(Debug, thiserror::Error)]
pub enum ConfigError {
    #[error("cannot read config file {path}: {source}")]
    Read {
        path: PathBuf,
        source: std::io::Error,
    },
    #[error("config file {file}: key `{key}`: {message}")]
    Invalid {
        file: String,
        key: String,
        message: String,
    },
}

#[derive(Debug, Clone, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Config {
    #[serde(default)]
    pub broker: BrokerSection,
    #[serde(default)]
    pub auth: AuthSection,
    #[serde(default, rename = "listener")]
    pub listeners: Vec<ListenerSection>,
    #[serde(default)]
    pub admin: AdminSection,
    #[serde(default)]
    pub log: LogSection,
    /// The line console on the admin endpoint (`console`).
    #[serde(default)]
    pub console: ConsoleSection,
    #[serde(default)]
    pub fb: FbSection,
    /// What survives a restart (`store`).
    #[serde(default)]
    pub persistence: PersistenceSection,
    /// Present: link this line to the other lines' brokers over zenoh (`bridge`).
    pub bridge: Option<fb_bridge::bus::BusConfig>,
}

#[derive(Debug, Clone, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct FbSection {
    /// Where the device registry is persisted (written atomically); relative to the
    /// config file's directory, or to the working directory for the embedded default.
    /// Empty: not persisted.
    pub registry_file: PathBuf,
    /// Typed-namespace topics (fb/, dinasore/, fbdk/) no device declared: "reject" them
    /// (MQTT 5: 0x90), or "pass" them unchecked while migrating an untyped line.
    /// Declared ports are checked in both modes.
    pub undeclared: crate::policy::typed::Undeclared,
    /// A directory of device profiles (`*.toml`, one per device): the declaration the
    /// broker holds for a runtime that cannot send one (`profiles`). Relative to the
    /// config file's directory. Empty: none. Reloaded when it changes.
    pub profiles_dir: PathBuf,
    /// The unit of DATE, TIME_OF_DAY and DATE_AND_TIME in `fbdk/` payloads, read and
    /// written: "ns" (4diac FORTE 3.x) or "ms" (FORTE 2.0.x). A device's profile sets its
    /// own unit on its own topics.
    pub fbdk_time_unit: fb_bridge::codec::fbdk::TimeUnit,
    /// The largest `fbdk/` payload delivered, in bytes: 4diac FORTE's MQTT layer copies a
    /// received message into a 255-byte buffer per subscription, and a longer one
    /// corrupts that subscription's stream. 0: no limit. A device's profile sets its
    /// own limit on its own input topics (`speaks.max_payload`).
    pub fbdk_max_payload: usize,
    /// An online device is `silent` when none of its periodic outputs published for
    /// `silence_factor` times its period (observed), and at least `silence_min_s`
    /// seconds. 0 turns the judgement off.
    pub silence_factor: f64,
    pub silence_min_s: f64,
    /// Devices of this line the registry holds at most: a new device beyond is refused
    /// (its declaration answered on `fbbus/diag/<id>`, MQTT 5: 0x97), known devices go on.
    pub max_devices: usize,
    /// Devices one identity registers at most (the verified username where a password
    /// file exists, else the client's address): a new device beyond is refused likewise.
    pub max_devices_per_identity: usize,
    /// A device of this line offline this long is forgotten, with its retained record and
    /// values, as `fbbus devices forget` does. 0: never (a device away for maintenance
    /// keeps its record until it is forgotten by hand).
    pub forget_offline_after_s: u64,
    /// The largest declaration payload read, in bytes; a longer one is refused unread
    /// (`fbbus_limit_refusals_total{limit="declaration_bytes"}`).
    pub max_declaration_bytes: usize,
    /// Most FB instances one device declares (`limit="fbs"`).
    pub max_fbs: usize,
    /// Most ports (event and data, inputs and outputs) one device declares, over all
    /// its FBs (`limit="ports"`).
    pub max_ports: usize,
    /// Declarations one connected device may send per minute, in a burst of as many
    /// (a token bucket per connection); beyond, refused with "rate limited, retry after
    /// N s" (`limit="declaration_rate"`).
    pub declarations_per_minute: u32,
    /// Diagnostics on `fbbus/diag/<device>` per device and second, beyond a burst of
    /// `diag_burst`; beyond, dropped and counted (`fbbus_diag_dropped_total`).
    pub diag_per_second: f64,
    pub diag_burst: u32,
}

impl FbSection {
    /// How long a periodic output may be quiet.
    pub fn silence_bound(&self) -> crate::silence::Bound {
        crate::silence::Bound {
            factor: self.silence_factor,
            floor: std::time::Duration::from_secs_f64(self.silence_min_s),
        }
    }

    /// What one device may declare, and how often it may declare and be answered.
    pub(crate) fn declaration_limits(&self) -> crate::policy::typed::Limits {
        crate::policy::typed::Limits {
            max_declaration_bytes: self.max_declaration_bytes,
            max_fbs: self.max_fbs,
            max_ports: self.max_ports,
            declarations_per_minute: self.declarations_per_minute,
            diag_per_second: self.diag_per_second,
            diag_burst: self.diag_burst,
        }
    }

    /// What the device registry holds at most.
    pub(crate) fn registry_limits(&self) -> crate::registry::Limits {
        crate::registry::Limits {
            max_devices: self.max_devices,
            max_per_identity: self.max_devices_per_identity,
            forget_offline_after: (self.forget_offline_after_s > 0)
                .then(|| std::time::Duration::from_secs(self.forget_offline_after_s)),
        }
    }
}

impl Default for FbSection {
    /// The defaults of the modules `[fb]` configures, from the one place each sets them.
    fn default() -> Self {
        let silence = crate::silence::Bound::DEFAULT;
        let declarations = crate::policy::typed::Limits::default();
        let registry = crate::registry::Limits::default();
        FbSection {
            registry_file: PathBuf::from("fbbus-registry.json"),
            profiles_dir: PathBuf::new(),
            undeclared: Default::default(),
            fbdk_time_unit: Default::default(),
            fbdk_max_payload: crate::policy::typed::FORTE_RECEIVE_BUFFER,
            silence_factor: silence.factor,
            silence_min_s: silence.floor.as_secs_f64(),
            max_devices: registry.max_devices,
            max_devices_per_identity: registry.max_per_identity,
            forget_offline_after_s: registry.forget_offline_after.map_or(0, |d| d.as_secs()),
            max_declaration_bytes: declarations.max_declaration_bytes,
            max_fbs: declarations.max_fbs,
            max_ports: declarations.max_ports,
            declarations_per_minute: declarations.declarations_per_minute,
            diag_per_second: declarations.diag_per_second,
            diag_burst: declarations.diag_burst,
        }
    }
}

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
    /// Connections and persistent sessions one identity holds at most (the username; the
    /// peer IP address where there is no password file); a CONNECT beyond is refused
    /// (MQTT 5: 0x97 Quota exceeded; 3.1.1: 0x05 Not authorized).
    pub max_sessions_per_identity: usize,
    /// Time a new TCP connection has to send CONNECT.
    pub connect_timeout_ms: u64,
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
}

impl BrokerSection {
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
            max_subscriptions_per_client: 1000,
            max_retained_messages: 100_000,
            max_retained_bytes: 64 * 1024 * 1024,
            max_sessions_per_identity: 1000,
            connect_timeout_ms: 5_000,
            max_keep_alive_s: 65_535,
            router_segment_bytes: 4 * 1024 * 1024,
            router_segment_count: 4,
            router_max_outgoing_packets: 1_000,
            slow_subscriber_hold_ms: 1_000,
            slow_consumer_timeout_ms: 10_000,
            slow_consumer_max_bytes: 64 * 1024 * 1024,
            dead_link_timeout_s: 20,
            sys_interval_s: 10,
        }
    }
}

impl Config {
    /// The embedded default configuration.
    pub fn embedded_default() -> Config {
        Config::parse(DEFAULT_CONFIG, "<embedded default>")
            .expect("the embedded default configuration is valid")
    }

    /// Reads and validates a configuration file.
    pub fn load(path: &Path) -> Result<Config, ConfigError> {
        let text = std::fs::read_to_string(path).map_err(|source| ConfigError::Read {
            path: path.to_owned(),
            source,
        })?;
        let mut config = Config::parse(&text, &path.display().to_string())?;
        config.resolve_paths(path.parent().unwrap_or(Path::new(".")));
        config.validate_files(&path.display().to_string())?;
        Ok(config)
    }

    /// Parses and validates configuration text; `file` names it in errors.
    pub fn parse(text: &str, file: &str) -> Result<Config, ConfigError> {
        let deserializer = toml::Deserializer::new(text);
        let config: Config = serde_path_to_error::deserialize(deserializer).map_err(|e| {
            let key = e.path().to_string();
            // toml's own message carries the line and column; keep only its first line
            // plus the pointer lines so the error stays readable in a journal.
            let message = e.into_inner().to_string().trim().replace('\n', " ");
            invalid(file, &key, message)
        })?;
        config.validate(file)?;
        Ok(config)
    }

    /// Relative paths in a config file are relative to the file's directory.
    fn resolve_paths(&mut self, base: &Path) {
        let fix = |p: &mut PathBuf| {
            if p.is_relative() {
                *p = base.join(&*p);
            }
        };
        if let Some(p) = self.auth.password_file.as_mut() {
            fix(p)
        }
        if let Some(p) = self.auth.acl_file.as_mut() {
            fix(p)
        }
        if let Some(p) = self.admin.password_file.as_mut() {
            fix(p)
        }
        if !self.fb.registry_file.as_os_str().is_empty() {
            fix(&mut self.fb.registry_file);
        }
        if !self.fb.profiles_dir.as_os_str().is_empty() {
            fix(&mut self.fb.profiles_dir);
        }
        fix(&mut self.persistence.dir);
        if let Some(tls) = self.bridge.as_mut().and_then(|b| b.tls.as_mut()) {
            fix(&mut tls.root_ca);
            fix(&mut tls.cert);
            fix(&mut tls.key);
        }
        for l in &mut self.listeners {
            if let Some(tls) = l.tls.as_mut() {
                fix(&mut tls.cert);
                fix(&mut tls.key);
                if let Some(ca) = tls.client_ca.as_mut() {
                    fix(ca)
                }
            }
        }
    }

    fn validate(&self, file: &str) -> Result<(), ConfigError> {
        let b = &self.broker;
        if b.line.trim().is_empty() || b.line.contains(['/', '+', '#']) {
            return Err(invalid(
                file,
                "broker.line",
                "must be a non-empty name without `/`, `+` or `#`",
            ));
        }
        if !(1..=MAX_CONNECTIONS).contains(&b.max_connections) {
            return Err(invalid(
                file,
                "broker.max_connections",
                format!("must be between 1 and {MAX_CONNECTIONS}"),
            ));
        }
        if !(64..=268_435_455).contains(&b.max_packet_bytes) {
            return Err(invalid(
                file,
                "broker.max_packet_bytes",
                "must be between 64 and 268435455 (the MQTT maximum)",
            ));
        }
        let a = &self.admin;
        if !(1..=4096).contains(&a.max_connections) {
            return Err(invalid(
                file,
                "admin.max_connections",
                "must be between 1 and 4096",
            ));
        }
        if a.header_timeout_ms == 0 || a.connection_timeout_ms < a.header_timeout_ms {
            return Err(invalid(
                file,
                "admin.header_timeout_ms",
                "must be at least 1 and at most admin.connection_timeout_ms",
            ));
        }
        if !a.bind.ip().to_canonical().is_loopback() && a.password_file.is_none() {
            return Err(invalid(
                file,
                "admin.bind",
                format!(
                    "{} is not a loopback address, so the admin endpoint must require \
                     credentials: set [admin] password_file (create one with \
                     `fbbus passwd FILE add USER`; a file of its own, not [auth] password_file), \
                     or bind to 127.0.0.1",
                    a.bind
                ),
            ));
        }
        let p = &self.persistence;
        if p.max_queued_messages == 0 {
            return Err(invalid(
                file,
                "persistence.max_queued_messages",
                "must be at least 1",
            ));
        }
        if p.enabled && p.dir.as_os_str().is_empty() {
            return Err(invalid(
                file,
                "persistence.dir",
                "must name a directory (or set persistence.enabled = false)",
            ));
        }
        if b.max_retained_messages == 0 || b.max_retained_bytes == 0 {
            return Err(invalid(
                file,
                "broker.max_retained_messages",
                "max_retained_messages and max_retained_bytes must be at least 1",
            ));
        }
        if b.max_sessions_per_identity == 0 {
            return Err(invalid(
                file,
                "broker.max_sessions_per_identity",
                "must be at least 1",
            ));
        }
        if b.max_subscriptions_per_client == 0 {
            return Err(invalid(
                file,
                "broker.max_subscriptions_per_client",
                "must be at least 1",
            ));
        }
        if b.max_inflight == 0 {
            return Err(invalid(file, "broker.max_inflight", "must be at least 1"));
        }
        // A day bounds both: beyond it the judgement means nothing, and the durations
        // they make cannot overflow.
        for (key, value) in [
            ("fb.silence_factor", self.fb.silence_factor),
            ("fb.silence_min_s", self.fb.silence_min_s),
        ] {
            if !(0.0..=86_400.0).contains(&value) {
                return Err(invalid(file, key, "must be between 0 and 86400"));
            }
        }
        for (key, value) in [
            ("fb.max_devices", self.fb.max_devices),
            (
                "fb.max_devices_per_identity",
                self.fb.max_devices_per_identity,
            ),
        ] {
            if value == 0 {
                return Err(invalid(file, key, "must be at least 1"));
            }
        }
        let fb = &self.fb;
        for (key, value, most) in [
            (
                "fb.max_declaration_bytes",
                fb.max_declaration_bytes,
                16 << 20,
            ),
            ("fb.max_fbs", fb.max_fbs, fb_bridge::interface::MAX_FBS),
            ("fb.max_ports", fb.max_ports, 1 << 20),
            (
                "fb.declarations_per_minute",
                fb.declarations_per_minute as usize,
                1 << 20,
            ),
            ("fb.diag_burst", fb.diag_burst as usize, 1 << 20),
        ] {
            if !(1..=most).contains(&value) {
                return Err(invalid(file, key, format!("must be between 1 and {most}")));
            }
        }
        if !(fb.diag_per_second > 0.0 && fb.diag_per_second <= 1e6) {
            return Err(invalid(
                file,
                "fb.diag_per_second",
                "must be more than 0 (and at most 1000000)",
            ));
        }
        if b.connect_timeout_ms == 0 {
            return Err(invalid(
                file,
                "broker.connect_timeout_ms",
                "must be at least 1",
            ));
        }
        if b.router_segment_bytes < b.max_packet_bytes.max(1024) {
            return Err(invalid(
                file,
                "broker.router_segment_bytes",
                "must be at least 1024 (rumqttd's minimum) and at least broker.max_packet_bytes, \
                 or the largest message could not be stored",
            ));
        }
        if b.router_segment_count < 1 {
            return Err(invalid(
                file,
                "broker.router_segment_count",
                "must be at least 1",
            ));
        }
        if b.router_max_outgoing_packets == 0 {
            return Err(invalid(
                file,
                "broker.router_max_outgoing_packets",
                "must be at least 1",
            ));
        }
        if b.slow_subscriber_hold_ms > 60_000 {
            return Err(invalid(
                file,
                "broker.slow_subscriber_hold_ms",
                "must be at most 60000: a stalled subscriber would stop its filter's publishers \
                 that long",
            ));
        }
        if !(100..=600_000).contains(&b.slow_consumer_timeout_ms) {
            return Err(invalid(
                file,
                "broker.slow_consumer_timeout_ms",
                "must be between 100 and 600000: every write to a client needs a deadline",
            ));
        }
        if b.slow_consumer_max_bytes < MIN_QUEUED_BYTES + b.max_packet_bytes {
            return Err(invalid(
                file,
                "broker.slow_consumer_max_bytes",
                "must be at least 1 MiB (1048576) more than broker.max_packet_bytes: the broker \
                 writes to a client in batches of up to 1 MiB, and a healthy client may have one \
                 batch and a message waiting",
            ));
        }
        if b.dead_link_timeout_s > 3_600 {
            return Err(invalid(
                file,
                "broker.dead_link_timeout_s",
                "must be at most 3600 (0: the kernel's defaults)",
            ));
        }
        // A day at most: figures older than that are no status.
        if b.sys_interval_s > 86_400 {
            return Err(invalid(
                file,
                "broker.sys_interval_s",
                "must be at most 86400 (0: no $SYS topics)",
            ));
        }
        if self.auth.verify_concurrency == 0 {
            return Err(invalid(
                file,
                "auth.verify_concurrency",
                "must be at least 1",
            ));
        }
        if self.auth.reload_poll_ms < 100 {
            return Err(invalid(file, "auth.reload_poll_ms", "must be at least 100"));
        }
        if self.auth.client_id != crate::identity::ClientIdRule::Any
            && self.auth.password_file.is_none()
        {
            return Err(invalid(
                file,
                "auth.client_id",
                "binds client ids to verified usernames, so it needs [auth] password_file; \
                 without one nobody's username is checked",
            ));
        }
        let t = &self.auth.throttle;
        if t.base_delay_ms == 0 || t.max_delay_ms < t.base_delay_ms {
            return Err(invalid(
                file,
                "auth.throttle",
                "base_delay_ms must be at least 1 and max_delay_ms at least base_delay_ms",
            ));
        }
        if let Some(bridge) = &self.bridge {
            if !cfg!(feature = "bridge") {
                return Err(invalid(
                    file,
                    "bridge",
                    "this fbbus was built without the `bridge` cargo feature (the zenoh bus); \
                     remove the [bridge] section or use a build with it",
                ));
            }
            bridge
                .validate(&b.line)
                .map_err(|(key, message)| invalid(file, &key, message))?;
        }
        if self.listeners.is_empty() {
            return Err(invalid(
                file,
                "listener",
                "at least one [[listener]] is needed, e.g. bind = \"127.0.0.1:1883\"",
            ));
        }
        for (i, l) in self.listeners.iter().enumerate() {
            let key = |k: &str| format!("listener[{i}].{k}");
            if l.name.trim().is_empty() {
                return Err(invalid(file, &key("name"), "must not be empty"));
            }
            if self.listeners[..i].iter().any(|o| o.name == l.name) {
                return Err(invalid(file, &key("name"), "is used by another listener"));
            }
            l.validate_kind()
                .map_err(|(k, message)| invalid(file, &key(k), message))?;
            let loopback = l.bind.ip().is_loopback();
            let anonymous = l.anonymous(&self.auth);
            if !loopback && self.auth.password_file.is_none() {
                return Err(invalid(
                    file,
                    &key("bind"),
                    format!(
                        "{} is not a loopback address, so this listener must require authentication: \
                         set [auth] password_file (create one with `fbbus passwd FILE add USER`), \
                         or bind to 127.0.0.1",
                        l.bind
                    ),
                ));
            }
            if !loopback && anonymous {
                return Err(invalid(
                    file,
                    &key("allow_anonymous"),
                    "anonymous access is only allowed on loopback listeners",
                ));
            }
            if !anonymous && self.auth.password_file.is_none() {
                return Err(invalid(
                    file,
                    &key("allow_anonymous"),
                    "is false but there is no [auth] password_file: nobody could connect",
                ));
            }
        }
        Ok(())
    }

    /// Checks that the files the config names exist, so a typo fails at start, not at first use.
    fn validate_files(&self, file: &str) -> Result<(), ConfigError> {
        let check = |key: String, p: &Path| -> Result<(), ConfigError> {
            if p.is_file() {
                Ok(())
            } else {
                Err(invalid(
                    file,
                    &key,
                    format!("{} does not exist or is not a file", p.display()),
                ))
            }
        };
        if let Some(p) = &self.auth.password_file {
            check("auth.password_file".into(), p)?;
        }
        if let Some(p) = &self.auth.acl_file {
            check("auth.acl_file".into(), p)?;
        }
        if let Some(p) = &self.admin.password_file {
            check("admin.password_file".into(), p)?;
            let same = |a: &Path, b: &Path| match (a.canonicalize(), b.canonicalize()) {
                (Ok(a), Ok(b)) => a == b,
                _ => a == b,
            };
            if self
                .auth
                .password_file
                .as_deref()
                .is_some_and(|m| same(m, p))
            {
                return Err(invalid(
                    file,
                    "admin.password_file",
                    "is also [auth] password_file: every device's MQTT password would open the \
                     admin plane; give the admin endpoint a file of its own \
                     (`fbbus passwd FILE add USER`)",
                ));
            }
        }
        if let Some(tls) = self.bridge.as_ref().and_then(|b| b.tls.as_ref()) {
            check("bridge.tls.root_ca".into(), &tls.root_ca)?;
            check("bridge.tls.cert".into(), &tls.cert)?;
            check("bridge.tls.key".into(), &tls.key)?;
        }
        for (i, l) in self.listeners.iter().enumerate() {
            if let Some(tls) = &l.tls {
                check(format!("listener[{i}].tls.cert"), &tls.cert)?;
                check(format!("listener[{i}].tls.key"), &tls.key)?;
                if let Some(ca) = &tls.client_ca {
                    check(format!("listener[{i}].tls.client_ca"), ca)?;
                }
            }
        }
        Ok(())
    }

    pub fn connect_timeout(&self) -> Duration {
        Duration::from_millis(self.broker.connect_timeout_ms)
    }

    /// `broker.dead_link_timeout_s`; None when it is 0 (kernel defaults).
    pub fn dead_link_timeout(&self) -> Option<Duration> {
        (self.broker.dead_link_timeout_s > 0)
            .then(|| Duration::from_secs(self.broker.dead_link_timeout_s))
    }
}

fn invalid(file: &str, key: &str, message: impl Into<String>) -> ConfigError {
    ConfigError::Invalid {
        file: file.to_owned(),
        key: key.to_owned(),
        message: message.into(),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn embedded_default_is_loopback_and_anonymous() {
        let c = Config::embedded_default();
        assert_eq!(c.listeners.len(), 1);
        assert!(c.listeners[0].bind.ip().is_loopback());
        assert!(c.listeners[0].anonymous(&c.auth));
        assert!(c.admin.bind.ip().is_loopback());
    }

    #[test]
    fn non_loopback_without_password_file_is_refused() {
        let err = Config::parse(
            "[[listener]]\nname = \"a\"\nbind = \"0.0.0.0:1883\"\n",
            "line.toml",
        )
        .unwrap_err()
        .to_string();
        assert!(err.contains("line.toml"), "{err}");
        assert!(err.contains("listener[0].bind"), "{err}");
        assert!(err.contains("password_file"), "{err}");
    }

    /// Issue 18: an admin endpoint off loopback needs its own password file; the MQTT
    /// password file does not count (a device's password must not open the admin plane).
    #[test]
    fn non_loopback_admin_needs_an_admin_password_file() {
        let listener = "[[listener]]\nname=\"a\"\nbind=\"127.0.0.1:1\"\n";
        for bind in [
            "0.0.0.0:9883",
            "10.1.0.5:9883",
            "[::]:9883",
            "[::ffff:10.1.0.5]:9883",
        ] {
            for auth in ["", "[auth]\npassword_file = \"p\"\n"] {
                let err = Config::parse(
                    &format!("{auth}{listener}[admin]\nbind = \"{bind}\"\n"),
                    "line.toml",
                )
                .unwrap_err()
                .to_string();
                for part in [
                    "line.toml",
                    "admin.bind",
                    "[admin] password_file",
                    "fbbus passwd",
                ] {
                    assert!(err.contains(part), "{bind} {auth}: {err}");
                }
            }
            let c = Config::parse(
                &format!("{listener}[admin]\nbind = \"{bind}\"\npassword_file = \"admin\"\n"),
                "f",
            )
            .unwrap();
            assert_eq!(c.admin.password_file, Some(PathBuf::from("admin")));
        }
        for bind in [
            "127.0.0.1:9883",
            "127.0.0.2:9883",
            "[::1]:9883",
            "[::ffff:127.0.0.1]:9883",
        ] {
            let c = Config::parse(&format!("{listener}[admin]\nbind = \"{bind}\"\n"), "f").unwrap();
            assert_eq!(c.admin.password_file, None);
        }
    }

    /// The admin password file is not the MQTT one, and it must exist.
    #[test]
    fn admin_password_file_is_its_own_and_exists() {
        let dir = tempfile::tempdir().unwrap();
        std::fs::write(dir.path().join("passwd"), "").unwrap();
        std::fs::write(dir.path().join("admin-passwd"), "").unwrap();
        let load = |auth: &str, admin: &str| {
            let path = dir.path().join("line.toml");
            std::fs::write(
                &path,
                format!(
                    "[auth]\npassword_file = \"{auth}\"\n[[listener]]\nname=\"a\"\n\
                     bind=\"127.0.0.1:1\"\n[admin]\nbind=\"0.0.0.0:0\"\npassword_file = \"{admin}\"\n"
                ),
            )
            .unwrap();
            Config::load(&path).map_err(|e| e.to_string())
        };
        let c = load("passwd", "admin-passwd").unwrap();
        assert_eq!(c.admin.password_file, Some(dir.path().join("admin-passwd")));
        let err = load("passwd", "./passwd").unwrap_err();
        assert!(err.contains("admin.password_file"), "{err}");
        assert!(err.contains("[auth] password_file"), "{err}");
        let err = load("passwd", "missing").unwrap_err();
        assert!(err.contains("admin.password_file"), "{err}");
        assert!(err.contains("does not exist"), "{err}");
    }

    #[test]
    fn anonymous_on_non_loopback_is_refused() {
        let err = Config::parse(
            "[auth]\npassword_file = \"p\"\n[[listener]]\nname = \"a\"\nbind = \"0.0.0.0:1883\"\nallow_anonymous = true\n",
            "f",
        )
        .unwrap_err()
        .to_string();
        assert!(err.contains("listener[0].allow_anonymous"), "{err}");
    }

    #[test]
    fn unknown_key_names_the_key() {
        let err = Config::parse("[broker]\nmax_conections = 3\n", "f")
            .unwrap_err()
            .to_string();
        assert!(err.contains("max_conections"), "{err}");
        assert!(err.contains("broker"), "{err}");
    }

    #[test]
    fn wrong_type_names_the_key() {
        let err = Config::parse(
            "[broker]\nmax_connections = \"many\"\n[[listener]]\nname=\"a\"\nbind=\"127.0.0.1:1\"\n",
            "f",
        )
        .unwrap_err()
        .to_string();
        assert!(err.contains("broker.max_connections"), "{err}");
    }

    #[test]
    fn client_id_binding_needs_a_password_file() {
        let listener = "[[listener]]\nname=\"a\"\nbind=\"127.0.0.1:1\"\n";
        let err = Config::parse(&format!("[auth]\nclient_id = \"%u\"\n{listener}"), "f")
            .unwrap_err()
            .to_string();
        assert!(err.contains("auth.client_id"), "{err}");
        let err = Config::parse(&format!("[auth]\nclient_id = \"%c\"\n{listener}"), "f")
            .unwrap_err()
            .to_string();
        assert!(err.contains("auth.client_id"), "{err}");
        let c = Config::parse(
            &format!("[auth]\npassword_file = \"p\"\nclient_id = \"%u-*\"\n{listener}"),
            "f",
        )
        .unwrap();
        assert_eq!(
            c.auth.client_id,
            crate::identity::ClientIdRule::UsernamePrefix
        );
        assert_eq!(
            Config::embedded_default().auth.client_id,
            crate::identity::ClientIdRule::Any
        );
    }

    #[test]
    fn fbdk_time_unit_is_ns_unless_ms_is_said() {
        use fb_bridge::codec::fbdk::TimeUnit;
        let listener = "[[listener]]\nname=\"a\"\nbind=\"127.0.0.1:1\"\n";
        let unit = |fb: &str| {
            Config::parse(&format!("[fb]\n{fb}\n{listener}"), "f")
                .map(|c| c.fb.fbdk_time_unit)
                .map_err(|e| e.to_string())
        };
        assert_eq!(unit(""), Ok(TimeUnit::Nanoseconds));
        assert_eq!(
            Config::embedded_default().fb.fbdk_time_unit,
            TimeUnit::Nanoseconds
        );
        assert_eq!(unit("fbdk_time_unit = \"ns\""), Ok(TimeUnit::Nanoseconds));
        assert_eq!(unit("fbdk_time_unit = \"ms\""), Ok(TimeUnit::Milliseconds));
        let err = unit("fbdk_time_unit = \"us\"").unwrap_err();
        assert!(err.contains("fb.fbdk_time_unit"), "{err}");
        assert!(err.contains("`ns` or `ms`"), "{err}");
    }

    /// The registry's bounds: 10,000 devices, 100 per identity, never forgotten by age;
    /// a limit of 0 would refuse every device and is refused instead.
    #[test]
    fn registry_limits_default_and_are_at_least_1() {
        let listener = "[[listener]]\nname=\"a\"\nbind=\"127.0.0.1:1\"\n";
        let limits = |fb: &str| {
            Config::parse(&format!("[fb]\n{fb}\n{listener}"), "f")
                .map(|c| c.fb.registry_limits())
                .map_err(|e| e.to_string())
        };
        let default = limits("").unwrap();
        assert_eq!(
            default,
            crate::registry::Limits {
                max_devices: 10_000,
                max_per_identity: 100,
                forget_offline_after: None,
            }
        );
        let set = limits("max_devices = 20\nforget_offline_after_s = 3600").unwrap();
        assert_eq!(set.max_devices, 20);
        assert_eq!(
            set.forget_offline_after,
            Some(std::time::Duration::from_secs(3600))
        );
        for (bad, key) in [
            ("max_devices = 0", "fb.max_devices"),
            (
                "max_devices_per_identity = 0",
                "fb.max_devices_per_identity",
            ),
        ] {
            let err = limits(bad).unwrap_err();
            assert!(err.contains(key), "{bad}: {err}");
        }
    }

    /// The silence keys become durations: a value no duration can hold (negative, NaN,
    /// huge) is refused here, never reaches `Duration::from_secs_f64`.
    #[test]
    fn silence_keys_default_to_3_and_5_s_and_are_bounded() {
        let listener = "[[listener]]\nname=\"a\"\nbind=\"127.0.0.1:1\"\n";
        let bound = |fb: &str| {
            Config::parse(&format!("[fb]\n{fb}\n{listener}"), "f")
                .map(|c| c.fb.silence_bound())
                .map_err(|e| e.to_string())
        };
        let default = bound("").unwrap();
        assert_eq!(default.factor, 3.0);
        assert_eq!(default.floor, std::time::Duration::from_secs(5));
        assert!(!bound("silence_factor = 0").unwrap().enabled());
        assert_eq!(
            bound("silence_min_s = 0.5").unwrap().floor,
            std::time::Duration::from_millis(500)
        );
        for bad in [
            "silence_factor = -1",
            "silence_factor = nan",
            "silence_min_s = 1e300",
            "silence_min_s = -0.1",
        ] {
            let err = bound(bad).unwrap_err();
            assert!(err.contains("fb.silence_"), "{bad}: {err}");
        }
    }

    /// Regression (broker/fuzz/regressions/config_load): a max_connections the broker
    /// cannot start with is refused when the file is read.
    #[test]
    fn max_connections_is_bounded() {
        let config = |n: u64| {
            Config::parse(
                &format!(
                    "[broker]\nmax_connections = {n}\n[[listener]]\nname=\"a\"\nbind=\"127.0.0.1:1\"\n"
                ),
                "f",
            )
        };
        for n in [0, MAX_CONNECTIONS as u64 + 1, 9_000_000_000_000_000_000] {
            let err = config(n).unwrap_err().to_string();
            assert!(err.contains("broker.max_connections"), "{n}: {err}");
        }
        assert!(config(MAX_CONNECTIONS as u64).is_ok());
    }

    #[test]
    fn liveness_limits_are_bounded() {
        let config = |keys: &str| {
            Config::parse(
                &format!("[broker]\n{keys}\n[[listener]]\nname=\"a\"\nbind=\"127.0.0.1:1\"\n"),
                "f",
            )
        };
        let c = config("").unwrap();
        assert_eq!(c.broker.slow_consumer_timeout_ms, 10_000);
        assert_eq!(c.dead_link_timeout(), Some(Duration::from_secs(20)));
        for (keys, key) in [
            (
                "slow_consumer_timeout_ms = 0",
                "broker.slow_consumer_timeout_ms",
            ),
            (
                "slow_consumer_timeout_ms = 600001",
                "broker.slow_consumer_timeout_ms",
            ),
            (
                "slow_consumer_max_bytes = 1000",
                "broker.slow_consumer_max_bytes",
            ),
            ("dead_link_timeout_s = 3601", "broker.dead_link_timeout_s"),
            ("sys_interval_s = 86401", "broker.sys_interval_s"),
        ] {
            let err = config(keys).unwrap_err().to_string();
            assert!(err.contains(key), "{keys}: {err}");
        }
        assert_eq!(
            config("dead_link_timeout_s = 0")
                .unwrap()
                .dead_link_timeout(),
            None
        );
    }

    #[test]
    fn websocket_listener_keys_are_checked() {
        let listener = |keys: &str| {
            Config::parse(
                &format!("[[listener]]\nname=\"a\"\nbind=\"127.0.0.1:1\"\n{keys}"),
                "f",
            )
        };
        let ws = listener("kind = \"ws\"\npath = \"/line/mqtt\"\nallowed_origins = [\"https://hmi.example:8443\"]\n")
            .unwrap();
        let handshake = ws.listeners[0].websocket().expect("a ws listener");
        assert_eq!(handshake.path, "/line/mqtt");
        assert!(listener("").unwrap().listeners[0].websocket().is_none());
        assert_eq!(
            listener("kind = \"ws\"\n").unwrap().listeners[0]
                .websocket()
                .unwrap()
                .path,
            "/mqtt"
        );
        for (keys, key) in [
            ("kind = \"wss\"\n", "listener[0].tls"),
            ("path = \"/mqtt\"\n", "listener[0].path"),
            ("allowed_origins = []\n", "listener[0].allowed_origins"),
            ("kind = \"ws\"\npath = \"mqtt\"\n", "listener[0].path"),
            ("kind = \"ws\"\npath = \"/mqtt?x\"\n", "listener[0].path"),
            (
                "kind = \"ws\"\nallowed_origins = [\"hmi.example\"]\n",
                "listener[0].allowed_origins",
            ),
            ("kind = \"websocket\"\n", "listener[0].kind"),
        ] {
            let err = listener(keys).unwrap_err().to_string();
            assert!(err.contains(key), "{keys}: {err}");
        }
    }
}

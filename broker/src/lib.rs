//! # fbbus broker
//!
//! The MQTT 3.1.1 + 5 broker a production line runs. It keeps rumqttd's router (topic
//! matching, retained messages, per-filter commit logs, QoS state) and puts fbbus's own
//! listeners and connection loop in front of it, because that is where line policy lives:
//!
//! ```text
//!   TCP/TLS ─► listener ─► connection (the packet path) ──LinkTx──► rumqttd router
//!                          1 authenticate (CONNECT)                      │
//!                          2 authorize (ACL)                             │
//!                          3 check (typed FB topics, declarations)       │
//!                          4 route ───────────────────────────────────────┘
//!                          5 meter (Prometheus)     ◄──LinkRx── deliveries, acks
//! ```
//!
//! - [`connection`]: one client's session; its module doc is the packet path, in order.
//!   Around it: [`wire`] (the socket, framing, and rumqttd's MQTT codecs
//!   with the guards in front of them),
//!   [`ack_order`], [`origin`], [`packet_ids`] and [`redelivery`] (delivery rules the
//!   router leaves out),
//!   [`session_table`] and [`session_lifetime`] (session numbers, MQTT 5 session expiry).
//! - [`authenticator`]: throttle → anonymous → verified-credential cache → argon2id, the
//!   last on the [`verifier`]'s threads.
//! - [`wills`]: last wills, published by fbbus (abrupt close, keep-alive expiry, takeover,
//!   MQTT 5 will delay), never after a clean DISCONNECT.
//! - [`fb_topics`] and [`registry`]: typed FB topics checked against each device's
//!   declared interface (`fb-bridge` crate), and the device registry (online/offline by
//!   session number, persisted, published retained, served on `/api/v1/devices`).
//! - [`broker_publisher`]: the one queue through which the broker publishes its own
//!   messages (wills, registry records, diagnostics).
//! - [`config`]: the TOML file, its embedded default and the secure-by-default rules.
//! - [`server`]: assembly, reload of password and ACL files, graceful shutdown.
//! - [`bridge`]: one bus across lines: the zenoh bridge to the other lines' brokers
//!   (`[bridge]` section), its imports, exports and registry federation.
//! - [`admin`] and [`metrics`]: `/metrics`, `/healthz`, `/readyz`; [`health`]: what
//!   `/readyz` answers (a probe publication through the router) and what is fatal;
//!   [`supervisor`]: a panic in a core task or thread is fatal, one in a connection's
//!   task closes that connection only.
//! - [`router`] and [`memory`]: the vendored rumqttd router's thread, its reports
//!   (skipped messages, idle), and giving freed memory back to the OS.
//!
//! Password files, access rules and throttling are the `security` crate's.

mod admin;
mod authenticator;
#[cfg(feature = "bridge")]
mod bridge;
mod broker_publisher;
pub mod config;
mod context;
mod health;
mod listener;
mod logging;
mod memory;
mod metrics;
mod policy;
mod registry;
mod router;
mod server;
mod session;
mod supervisor;
mod tls;
mod watched_file;
mod wills;

// For the fuzz targets (`broker/fuzz`) and the tests of the password verifier's memory:
// not part of the broker's API.
#[doc(hidden)]
pub mod verifier;
#[doc(hidden)]
pub mod wire;

pub use config::{Config, ConfigError, DEFAULT_CONFIG};
pub use logging::init as init_logging;
pub use memory::{configure as configure_memory, JEMALLOC_CONF};
pub use server::{check as check_config, Broker, StartError};
pub use supervisor::install_panic_hook;

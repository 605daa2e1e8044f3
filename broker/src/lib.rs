//! # fbbus broker
//!
//! The MQTT 3.1.1 + 5 broker a production line runs. It keeps rumqttd's router (topic
//! matching, retained messages, per-filter commit logs, QoS state; the fork in
//! `vendor/rumqttd`) and puts fbbus's own listeners, sessions and policy in front of it,
//! because that is where the line's rules live:
//!
//! ```text
//!   TCP/TLS ─► listener ─► wire ─► session ──────────────────LinkTx──► rumqttd router
//!                                  1 authenticate (connect)               │
//!                                  2 authorize ┐ policy::PublishPolicy    │
//!                                  3 check     ┘ (also wills, bus import) │
//!                                  4 route ───────────────────────────────┘
//!                                  5 meter (metrics) ◄──LinkRx── deliveries, acks
//! ```
//!
//! **What it owns:** the listeners (MQTT over TCP, TLS and WebSockets: `listener`,
//! `websocket`) and the connection loop (`session`, over `wire`),
//! the publish policy every publication passes whatever its door (`policy`: access
//! rules, typed FB topics, origin mark), last wills (`wills`), the device registry
//! (`registry`), the broker's own publications (`broker_publisher`, its `$SYS/` status in
//! `sys`), the bus bridge
//! to other lines (`bridge`, feature `bridge`), the line as a Sparkplug B edge node for
//! SCADA (`sparkplug`), health, metrics and the admin endpoint
//! (`health`, `metrics`, `admin`), the tasks it runs and what a panic does
//! (`supervisor`), and assembly from a [`Config`] (`server`).
//!
//! **What it must not know:** how passwords are hashed or access rules parsed (the
//! `security` crate), how FB values are encoded or what a declaration may contain
//! (`fb-bridge`), or how zenoh carries the bus (`fb_bridge::bus`). The router is reached
//! only through its link API (`router`).
//!
//! **Its API** is what the `fbbus` binary and the tests need: [`Broker`] (start, wait
//! for death, shut down), [`Config`] and [`check_config`], and the process set-up
//! helpers. `docs/architecture.md` walks through the packet path and the module map.

mod admin;
mod admin_auth;
mod admin_writes;
mod authenticator;
#[cfg(feature = "bridge")]
mod bridge;
mod broker_publisher;
mod clients;
pub mod config;
mod console;
mod fd_budget;
mod health;
mod identity;
mod link;
mod listener;
mod logging;
mod memory;
mod metrics;
mod observer;
mod pending;
mod policy;
pub mod profiles;
mod registry;
mod retained_share;
mod router;
mod server;
mod session;
mod silence;
mod sparkplug;
pub mod store;
mod supervisor;
mod sys;
mod tls;
mod watched_file;
mod websocket;
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

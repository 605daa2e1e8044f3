//! One bus across lines: the zenoh bridge between line brokers.
//!
//! Each production line runs its own fbbus broker. The bridge links them over zenoh so an
//! FB connection can cross lines: a device on line B subscribes to
//! `fb/<device>/<fb>/<port>` as if the device were local, and if the device lives on line
//! A, the two bridges carry the messages. This module holds what both ends of a hop must
//! agree on and what can be reasoned about without a network:
//!
//! - [`keys`]: the zenoh key expressions (`fbbus/<line>/fb/<device>/<fb>/<port>` for data,
//!   `fbbus/@/...` for the bridges' own control plane);
//! - [`Stamp`]: the attachment each bridged message carries (origin line, origin epoch,
//!   per-origin sequence, MQTT QoS and RETAIN), and [`Dedup`], which drops a message
//!   already seen from that origin;
//! - [`BusConfig`]: the `[bridge]` section of the broker's configuration, and [`access`]:
//!   zenoh's access control built from its `[bridge.peers]` (who may speak for which line);
//! - [`LossTally`] and [`Reported`]: messages lost on the way, counted by the line that
//!   missed them and reported back to the line that sent them.
//!
//! The zenoh session itself is [`link`] (cargo feature `zenoh`).
//!
//! **No loops, no duplicates, by construction.** A bridge exports only messages its own
//! broker accepted from a local client; a message that came from zenoh is never exported
//! again. So every message crosses exactly one hop, from its origin line to each line that
//! subscribed, whatever the topology (chain, mesh, routers in between). [`Dedup`] is the
//! second line of defence: zenoh delivers a sample once per matching subscriber, so two
//! overlapping import filters of one line would otherwise inject it twice.

pub mod access;
mod config;
#[cfg(feature = "zenoh")]
mod error;
#[cfg(feature = "zenoh")]
mod event;
pub mod keys;
#[cfg(feature = "zenoh")]
pub mod link;
mod loss;
#[cfg(feature = "zenoh")]
mod presence;
#[cfg(feature = "zenoh")]
mod sessions;
mod stamp;

pub use config::{loopback_endpoint, BusConfig, BusPeers, BusTls, Mode, MAX_ROUTER_SESSIONS};
pub use loss::{LossReport, LossTally, Reported, LOSS_LINES};
pub use stamp::{Dedup, Gaps, Stamp, DEDUP_ORIGINS, DEDUP_WINDOW, GAP_TOPICS};

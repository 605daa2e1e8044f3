//! # fb-bridge: the FB side of fbbus
//!
//! IEC 61499 devices connect event and data outputs of function blocks on one device to
//! inputs on another. This crate is the model both ends of that connection share, and
//! the two ways of reaching the broker that are not the broker itself.
//!
//! ## What it owns
//!
//! The **FB model and codecs** (always compiled; what the broker uses):
//!
//! - [`types`] and [`value`]: the IEC 61131-3 elementary types, `ARRAY [n] OF` them, and
//!   typed Rust values with their ranges;
//! - [`interface`]: the FB interface a device declares at birth, validated with errors
//!   that name the FB and the port;
//! - [`topic`]: the typed topics (`fb/<device>/<fb>/<port>`) and fbbus's control topics,
//!   and [`topic::filter`], the one MQTT topic/filter grammar (validity, `$share/`,
//!   matching, coverage) that the ACL, the bus and the broker all use;
//! - [`profile`]: device profiles, the declaration the broker holds for a runtime that
//!   cannot send one (4diac FORTE, DINASORE), with its own topics mapped onto its ports;
//! - [`codec`]: canonical JSON, DINASORE JSON and 4diac's `fbdk` bytes, all decoded to
//!   and encoded from one [`codec::Message`];
//! - [`sparkplug`]: Sparkplug B 3.0 payloads (the protobuf types of Eclipse Tahu's
//!   `sparkplug_b.proto`) and the mapping of port types and values onto their metrics.
//!
//! The **device client API**, [`client`] (cargo feature `client`, on by default, the only
//! user of `rumqttc`): IEC 61499 PUBLISH/SUBSCRIBE semantics (INIT, REQ→CNF, IND) over an
//! MQTT 3.1.1 connection that declares, reconnects and re-declares by itself. The broker
//! builds without it.
//!
//! The **bus**, [`bus`]: one bus across lines. Its key expressions, stamps, dedup window
//! and `[bridge]` configuration are always compiled; the zenoh session, `bus::link`, is
//! behind the cargo feature `zenoh`, and no zenoh or flume type appears in its public API.
//!
//! ## What it must not know
//!
//! - **The broker**: its sessions, its router (rumqttd), its registry, its metrics. The
//!   broker depends on this crate, never the reverse; `bus::link` hands the broker fbbus
//!   types and leaves routing to it.
//! - **Who may do what**: passwords, hashes and access rules are the `security` crate's.
//!   (`security` uses [`topic::filter`], not the other way round.)
//! - **MQTT sessions beyond a device's own**: the client API is one device's connection.
//!
//! The broker uses this crate to check every publication on a typed topic; device
//! software uses the same types through the client API. The device contract (topics,
//! encodings, registry) is written down in this crate's README.

pub mod bus;
#[cfg(feature = "client")]
pub mod client;
pub mod codec;
pub mod interface;
pub mod profile;
pub mod sparkplug;
pub mod topic;
pub mod types;
pub mod value;

pub use codec::{CodecError, Encoding, EventMessage, Message};
pub use interface::{Declaration, DeclarationError, Interface, OutputPort};
pub use topic::TypedTopic;
pub use types::{DataType, ElementaryType};
pub use value::{TypeError, Value};

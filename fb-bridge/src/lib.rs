//! # fb-bridge: the FB side of fbbus
//!
//! IEC 61499 devices connect event and data outputs of function blocks on one device to
//! inputs on another. This crate is the model both ends of that connection share:
//!
//! - [`types`] and [`value`]: the IEC 61131-3 elementary types, `ARRAY [n] OF` them, and
//!   typed Rust values with their ranges;
//! - [`interface`]: the FB interface a device declares at birth, validated with errors
//!   that name the FB and the port;
//! - [`topic`]: the typed topics (`fb/<device>/<fb>/<port>`) and fbbus's control topics;
//! - [`codec`]: canonical JSON, DINASORE JSON and 4diac's `fbdk` bytes, all decoded to
//!   and encoded from one [`codec::Message`];
//! - [`client`]: the device client API, IEC 61499 PUBLISH/SUBSCRIBE semantics (INIT,
//!   REQ→CNF, IND) over an MQTT 3.1.1 connection that declares, reconnects and
//!   re-declares by itself.
//!
//! - [`bus`]: one bus across lines: the zenoh bridge between line brokers (the
//!   network half behind the cargo feature `zenoh`).
//!
//! The broker uses this crate to check every publication on a typed topic; device
//! software uses the same types through the client API. The device contract (topics,
//! encodings, registry) is written down in the repository's `docs/device-contract.md`.

pub mod bus;
#[cfg(feature = "client")]
pub mod client;
pub mod codec;
pub mod interface;
pub mod topic;
pub mod types;
pub mod value;

pub use codec::{CodecError, Encoding, EventMessage, Message};
pub use interface::{Declaration, DeclarationError, Interface, OutputPort};
pub use topic::TypedTopic;
pub use types::{DataType, ElementaryType};
pub use value::{TypeError, Value};

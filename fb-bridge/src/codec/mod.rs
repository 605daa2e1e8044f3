//! Payload codecs: one typed message, three encodings on the wire.
//!
//! | encoding | topic namespace | who speaks it |
//! |---|---|---|
//! | [`Encoding::Json`] (canonical) | `fb/<device>/<fb>/<port>` | fbbus clients, anything with a JSON parser |
//! | [`Encoding::Dinasore`] | `dinasore/<device>/<fb>/<port>` | DINASORE's Python FBs: `{"VALUE_NAME": value}` |
//! | [`Encoding::Fbdk`] | `fbdk/<device>/<fb>/<port>` | 4diac FORTE's `fbdk[]` layer (IEC 61499 compliance profile, ASN.1 style) |
//!
//! A publication in any of them is decoded against the port's declaration into a
//! [`Message`]; each subscriber gets it re-encoded in the namespace it subscribed to.
//! Decoding never panics: truncated, mistagged or ill-typed input is a [`CodecError`].

pub mod dinasore;
pub mod fbdk;
pub mod json;
pub mod worst;

use crate::interface::OutputPort;
use crate::value::{TypeError, Value};

/// A payload encoding, named by its topic namespace.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub enum Encoding {
    Json,
    Dinasore,
    Fbdk,
}

impl Encoding {
    pub const ALL: [Encoding; 3] = [Encoding::Json, Encoding::Dinasore, Encoding::Fbdk];

    /// The first topic level of this encoding's typed topics.
    pub fn namespace(self) -> &'static str {
        match self {
            Encoding::Json => "fb",
            Encoding::Dinasore => "dinasore",
            Encoding::Fbdk => "fbdk",
        }
    }

    pub fn from_namespace(level: &str) -> Option<Encoding> {
        Self::ALL.into_iter().find(|e| e.namespace() == level)
    }
}

/// One typed publication on an output port.
#[derive(Debug, Clone, PartialEq)]
pub enum Message {
    /// An event with its WITH data, atomically.
    Event(EventMessage),
    /// A data output's value.
    Data(Value),
}

/// An event occurrence. `seq` and `ts_us` are optional on input (DINASORE and `fbdk` carry
/// neither); the broker stamps missing ones before delivery, so every canonical event a
/// subscriber receives has both.
#[derive(Debug, Clone, PartialEq)]
pub struct EventMessage {
    /// Counts the occurrences of this event output, per publisher session.
    pub seq: Option<u64>,
    /// When the event occurred: microseconds since 1970-01-01 UTC.
    pub ts_us: Option<u64>,
    /// The WITH data values, in WITH order.
    pub data: Vec<Value>,
}

/// Why a payload is not a valid message for its port.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum CodecError {
    /// Not parseable at all in this encoding (bad JSON, not an object, ...).
    #[error("malformed payload: {0}")]
    Malformed(String),
    /// A value does not fit its port's type (`port` is the data port's name).
    #[error("{port}: {error}")]
    Type { port: String, error: TypeError },
    /// A WITH data port is missing from an event.
    #[error("{0}: missing (the event carries every WITH data port)")]
    Missing(String),
    /// A field the port does not declare.
    #[error("{0}: not declared for this port")]
    Unexpected(String),
    /// `fbdk`: the payload ends in the middle of a value.
    #[error("truncated: {needed} more bytes needed at offset {offset}")]
    Truncated { offset: usize, needed: usize },
    /// `fbdk`: a tag byte that is not the declared type's.
    #[error("tag 0x{tag:02x} at offset {offset}, expected {expected}")]
    Tag {
        offset: usize,
        tag: u8,
        expected: String,
    },
    /// `fbdk`: bytes left after the last declared value.
    #[error("{0} unexpected bytes after the last value")]
    Trailing(usize),
}

/// Decodes `payload` in `encoding` as a message on `port` (named `port_name`);
/// `fbdk_unit` is the unit of `fbdk` dates and times ([`fbdk::TimeUnit`]).
pub fn decode(
    encoding: Encoding,
    payload: &[u8],
    port_name: &str,
    port: &OutputPort<'_>,
    fbdk_unit: fbdk::TimeUnit,
) -> Result<Message, CodecError> {
    match encoding {
        Encoding::Json => json::decode_named(payload, port_name, port),
        Encoding::Dinasore => dinasore::decode(payload, port_name, port),
        Encoding::Fbdk => fbdk::decode(payload, port, fbdk_unit),
    }
}

/// Encodes a message that [`decode`] accepted for `port` (named `port_name`);
/// `fbdk_unit` is the unit of `fbdk` dates and times ([`fbdk::TimeUnit`]).
///
/// JSON and DINASORE encode every such message. `fbdk` in nanoseconds refuses a DATE or
/// DATE_AND_TIME later than 64-bit nanoseconds reach (2554-07-21), as [`CodecError::Type`].
pub fn encode(
    encoding: Encoding,
    message: &Message,
    port_name: &str,
    port: &OutputPort<'_>,
    fbdk_unit: fbdk::TimeUnit,
) -> Result<Vec<u8>, CodecError> {
    match encoding {
        Encoding::Json => Ok(json::encode(message, port)),
        Encoding::Dinasore => Ok(dinasore::encode(message, port_name, port)),
        Encoding::Fbdk => fbdk::encode(message, port, fbdk_unit),
    }
}

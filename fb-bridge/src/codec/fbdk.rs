//! 4diac FORTE's `fbdk[]` payloads: the IEC 61499 compliance-profile encoding (ISO/IEC
//! 8825 ASN.1 style) that FORTE's `fbdk` communication layer writes for the SD_1..SD_n
//! inputs of a publisher.
//!
//! # Wire format
//!
//! A message is its values one after the other, in port order (an event's WITH order).
//! Each value is a tag byte `0x40 | type number` ([`ElementaryType::number`]) followed by
//! the value, big-endian:
//!
//! | type | value after the tag |
//! |---|---|
//! | `BOOL` | none: the tag is the value, `0x41` TRUE, `0x40` FALSE |
//! | `SINT`, `USINT`, `BYTE` | 1 byte |
//! | `INT`, `UINT`, `WORD` | 2 bytes |
//! | `DINT`, `UDINT`, `DWORD`, `REAL` (IEEE 754 single) | 4 bytes |
//! | `LINT`, `ULINT`, `LWORD`, `LREAL` (IEEE 754 double) | 8 bytes |
//! | `TIME` | 8 bytes, signed microseconds |
//! | `DATE`, `TIME_OF_DAY`, `DATE_AND_TIME` | 8 bytes, unsigned, in the [`TimeUnit`] of FORTE's version |
//! | `STRING` | 2-byte length in bytes, then the bytes |
//! | `WSTRING` | 2-byte length in UTF-16 units, then the units, big-endian |
//! | `ARRAY [n] OF t` | tag `0x76`, 2-byte element count, then the elements (below) |
//!
//! An array's elements share one tag: the element type's tag follows the count once and
//! the elements follow it bare. `BOOL` elements are the exception, since a BOOL's value is
//! its tag: each element is its own `0x40`/`0x41` byte. A message with no values (an
//! event without WITH data) is the single byte `0x05`, ASN.1's NULL.
//!
//! # fbbus's choices
//!
//! - **Units of DATE, TIME_OF_DAY and DATE_AND_TIME** (since the epoch at midnight, since
//!   midnight, since the epoch): the format fixes only their width, and FORTE's versions put
//!   different units in it, so every function here takes the [`TimeUnit`] of the device's
//!   FORTE: [`TimeUnit::Nanoseconds`] for FORTE 3.x, [`TimeUnit::Milliseconds`] for 2.0.x.
//!   [`Value`] holds them in milliseconds whatever the wire unit; see [`TimeUnit`] for how
//!   nanoseconds are read and written. `TIME` is signed microseconds in both versions.
//! - **STRING text**: IEC 61131-3 STRING is a single-byte string without a stated
//!   character set, while [`Value::String`] holds Rust text. Decoding takes the bytes as
//!   UTF-8 when they are valid UTF-8 and as Latin-1 (ISO 8859-1, one byte one character)
//!   otherwise, so no payload is refused for its characters. Encoding writes UTF-8, which
//!   round-trips every string exactly. The cost: Latin-1 text that happens to be valid
//!   UTF-8 reads as UTF-8, and Latin-1 input comes back as UTF-8 bytes. A Latin-1 string
//!   whose UTF-8 form exceeds 65,535 bytes is refused as too long, since it could not be
//!   forwarded in this encoding.
//! - **WSTRING**: unpaired surrogates are [`CodecError::Malformed`]: Rust text cannot hold
//!   them.
//! - **Port names in errors**: [`decode`] names an event's WITH ports by their names; a
//!   data port, whose name `decode` is not given, is named `value`; [`decode_values`]
//!   names its ports `SD_1`, `SD_2`, ... like 4diac's publisher inputs.
//! - **Every decoded value is [`Value::check`]ed**, so NaN and infinite REAL/LREAL, a
//!   TIME_OF_DAY of a day or more and a DATE off midnight are refused as
//!   [`CodecError::Type`] even though the bytes parse.
//! - **Truncation** is reported as [`CodecError::Truncated`] with the offset where the
//!   incomplete field (tag, length, count or value) starts and how many bytes past the end
//!   of the payload it still needs.
//! - **Event metadata**: the format has no place for an event's `seq` and `ts_us`, so
//!   [`encode`] drops them and [`decode`] leaves them `None` for the broker to stamp.

//!
//! # Modules
//!
//! This file holds the wire's tags and the entry points; `decode` reads a payload,
//! `encode` writes one, and `time` converts DATE, TIME_OF_DAY and DATE_AND_TIME between
//! the wire's [`TimeUnit`] and the milliseconds [`Value`] holds, which both directions
//! need.

use super::{CodecError, EventMessage, Message};
use crate::interface::OutputPort;
use crate::types::{DataType, ElementaryType};
use crate::value::Value;

mod decode;
mod encode;
mod time;

#[cfg(test)]
use decode::array_capacity;
use decode::{decode_ports, read_port, Reader};
use encode::encode_named;
#[cfg(test)]
use {
    crate::types::MAX_ARRAY_LEN,
    crate::value::{TypeError, MAX_STRING_LEN},
};

/// Tag bits of an ASN.1 application-class tag; `| type number` gives a primitive's tag.
pub(super) const APPLICATION: u8 = 0x40;
/// Constructed-encoding bit, set on the array tag.
pub(super) const CONSTRUCTED: u8 = 0x20;
/// Compliance-profile type number of `ARRAY`.
pub(super) const ARRAY_NUMBER: u8 = 22;
/// The array tag, `0x76`.
pub(super) const ARRAY_TAG: u8 = APPLICATION | CONSTRUCTED | ARRAY_NUMBER;
/// A BOOL TRUE: the BOOL tag itself.
pub(super) const TRUE_TAG: u8 = APPLICATION | 1;
/// A BOOL FALSE: the application tag with type number 0.
pub(super) const FALSE_TAG: u8 = APPLICATION;
/// ASN.1 NULL: the whole of a message without values.
pub(super) const EMPTY: u8 = 0x05;

/// The tag of a non-array value of `ty` (for BOOL, the TRUE tag).
fn tag_of(ty: ElementaryType) -> u8 {
    APPLICATION | ty.number()
}

/// How [`decode`] names a data port in [`CodecError::Type`]: it is not told the real name.
pub const DATA_PORT_NAME: &str = "value";

/// The unit of `DATE`, `TIME_OF_DAY` and `DATE_AND_TIME` values on the wire: 8 unsigned
/// bytes whose unit the compliance profile leaves open and FORTE's versions fill
/// differently. A device's FORTE version decides it; every function of this module takes it.
///
/// | unit | FORTE | DATE | TIME_OF_DAY | DATE_AND_TIME |
/// |---|---|---|---|---|
/// | [`Nanoseconds`](TimeUnit::Nanoseconds) (the default) | 3.x: the develop line since its nanosecond time base (December 2022, Eclipse bug 581136) | ns since 1970-01-01 at midnight UTC | ns since midnight | ns since 1970-01-01 UTC |
/// | [`Milliseconds`](TimeUnit::Milliseconds) | 2.0.x and earlier | ms, likewise | ms | ms |
///
/// From FORTE's source (eclipse-4diac/4diac-forte, the develop branch as of October 2024
/// and the 2.0.x branch): its `fbdk` layer writes these three types as the raw 64-bit
/// value FORTE holds them in (`src/core/cominfra/fbdkasn1layer.cpp`, `serializeValue`,
/// line 345 on develop, handing them to `serializeValueSimpleDataType`). That value is
/// unsigned (`src/core/datatypes/forte_any_date.h`, line 24), and `setDateAndTime` stores
/// seconds and milliseconds scaled to nanoseconds on develop
/// (`src/core/datatypes/forte_any_date.cpp`, line 48; `forte_time_of_day.cpp`, line 93,
/// the same since midnight), to milliseconds on 2.0.x (`forte_any_date.cpp`, line 47).
/// `TIME` goes through `serializeValueTime`, in microseconds in both, so it does not
/// depend on the unit.
///
/// **Reading nanoseconds.** [`Value`] holds these types in milliseconds, the resolution of
/// the canonical JSON form on `fb/`. A `TIME_OF_DAY` or `DATE_AND_TIME` with a
/// sub-millisecond part is **truncated** to the millisecond (towards the past), not
/// refused, because that is what the engineer of a FORTE 3.x device expects to happen to
/// it:
///
/// - FORTE 3.x's `NOW()` is the system clock to the nanosecond
///   (`src/core/iec61131_functions.cpp`, line 413, `func_NOW`), so nearly every timestamp
///   an unmodified application publishes has digits below the millisecond. Refusing them would refuse the whole publication, an event with all
///   its WITH data, for digits that nothing on `fb/` or in DINASORE can show.
/// - FORTE itself shows a `DATE_AND_TIME` to the millisecond, cutting the same way
///   (`CIEC_DATE_AND_TIME::toString`, `src/core/datatypes/forte_date_and_time.cpp`, line
///   118), so `fb/` shows the value its engineer sees in 4diac's monitoring.
/// - Nothing is lost that another kind of device could have sent: JSON, DINASORE and
///   FORTE 2.x carry milliseconds, which read back exactly. The broker passes an `fbdk`
///   publisher's bytes to `fbdk` subscribers as they came, nanoseconds included; only the
///   other encodings see the millisecond. The device contract (`docs/device-contract.md`)
///   states it.
///
/// A `DATE` has no time of day to truncate: one that is not midnight to the nanosecond is
/// refused, as a `DATE` off midnight is in every encoding.
///
/// **Writing nanoseconds** multiplies by 1,000,000 and cannot overflow silently: 64 bits of
/// nanoseconds end at 2554-07-21 23:34:33.709 UTC, and a later `DATE` or `DATE_AND_TIME`
/// (the IEC range goes to 9999) is refused with [`CodecError::Type`], since no FORTE 3.x
/// device can hold it. Every `TIME_OF_DAY` fits.
#[derive(
    Debug, Clone, Copy, Default, PartialEq, Eq, Hash, serde::Deserialize, serde::Serialize,
)]
pub enum TimeUnit {
    /// FORTE 3.x; the name `ns` in configuration.
    #[default]
    #[serde(rename = "ns")]
    Nanoseconds,
    /// FORTE 2.0.x; the name `ms` in configuration.
    #[serde(rename = "ms")]
    Milliseconds,
}

/// Decodes an `fbdk` payload published on `port`, with DATE, TIME_OF_DAY and
/// DATE_AND_TIME in `unit`.
///
/// A data port carries exactly one value of its type; an event carries the values of its
/// WITH ports in WITH order (`0x05`, or an empty payload, when it has none).
pub fn decode(
    payload: &[u8],
    port: &OutputPort<'_>,
    unit: TimeUnit,
) -> Result<Message, CodecError> {
    match port {
        OutputPort::Data(ty) => {
            let mut reader = Reader::new(payload, unit);
            let value = read_port(&mut reader, DATA_PORT_NAME, *ty)?;
            reader.finish()?;
            Ok(Message::Data(value))
        }
        OutputPort::Event(with) => Ok(Message::Event(EventMessage {
            seq: None,
            ts_us: None,
            data: decode_ports(payload, with, unit)?,
        })),
    }
}

/// Encodes a message for `port` with DATE, TIME_OF_DAY and DATE_AND_TIME in `unit`; an
/// event's `seq` and `ts_us` have no place in this format and are dropped.
///
/// Fails only for a DATE or DATE_AND_TIME that does not fit 64 bits of nanoseconds
/// ([`TimeUnit`]), as [`CodecError::Type`] naming the port as [`decode`] does (an event's
/// WITH port by its name in `port`).
pub fn encode(
    message: &Message,
    port: &OutputPort<'_>,
    unit: TimeUnit,
) -> Result<Vec<u8>, CodecError> {
    match (message, port) {
        (Message::Data(value), _) => {
            encode_named(std::slice::from_ref(value), |_| DATA_PORT_NAME.into(), unit)
        }
        (Message::Event(event), OutputPort::Event(with)) => encode_named(
            &event.data,
            |i| {
                with.get(i)
                    .map_or_else(|| sd_name(i), |(n, _)| (*n).to_owned())
            },
            unit,
        ),
        (Message::Event(event), OutputPort::Data(_)) => encode_named(&event.data, sd_name, unit),
    }
}

/// Encodes values in order, as a 4diac publisher sends its SD_1..SD_n, with DATE,
/// TIME_OF_DAY and DATE_AND_TIME in `unit`; no values is `[0x05]`.
///
/// The values are expected to pass [`Value::check`] for their types, as every decoded
/// value does. Values that do not are written as far as the format allows (strings and
/// arrays beyond the two-byte length limits are cut at the limit, an array nested in an
/// array is written as nothing) and may not decode again. The one error is a DATE or
/// DATE_AND_TIME after the end of 64-bit nanoseconds ([`TimeUnit`]), naming its port
/// `SD_1`, `SD_2`, ...
pub fn encode_values(values: &[Value], unit: TimeUnit) -> Result<Vec<u8>, CodecError> {
    encode_named(values, sd_name, unit)
}

/// Decodes what a 4diac publisher sends from its SD_1..SD_n inputs, typed `types` in
/// order, with DATE, TIME_OF_DAY and DATE_AND_TIME in `unit`; errors name the ports
/// `SD_1`, `SD_2`, ... by position.
pub fn decode_values(
    bytes: &[u8],
    types: &[DataType],
    unit: TimeUnit,
) -> Result<Vec<Value>, CodecError> {
    let ports: Vec<(String, DataType)> = types
        .iter()
        .enumerate()
        .map(|(i, ty)| (sd_name(i), *ty))
        .collect();
    decode_ports(bytes, &ports, unit)
}

/// The name 4diac gives the publisher input of the value at `index`.
pub(super) fn sd_name(index: usize) -> String {
    format!("SD_{}", index + 1)
}

#[cfg(test)]
mod tests;

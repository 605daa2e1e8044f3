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

use super::{CodecError, EventMessage, Message};
use crate::interface::OutputPort;
use crate::types::{DataType, ElementaryType, MAX_ARRAY_LEN};
use crate::value::{TypeError, Value, MAX_STRING_LEN, MS_PER_DAY};

/// Tag bits of an ASN.1 application-class tag; `| type number` gives a primitive's tag.
const APPLICATION: u8 = 0x40;
/// Constructed-encoding bit, set on the array tag.
const CONSTRUCTED: u8 = 0x20;
/// Compliance-profile type number of `ARRAY`.
const ARRAY_NUMBER: u8 = 22;
/// The array tag, `0x76`.
const ARRAY_TAG: u8 = APPLICATION | CONSTRUCTED | ARRAY_NUMBER;
/// A BOOL TRUE: the BOOL tag itself.
const TRUE_TAG: u8 = APPLICATION | 1;
/// A BOOL FALSE: the application tag with type number 0.
const FALSE_TAG: u8 = APPLICATION;
/// ASN.1 NULL: the whole of a message without values.
const EMPTY: u8 = 0x05;

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
fn sd_name(index: usize) -> String {
    format!("SD_{}", index + 1)
}

// ---------------------------------------------------------------------------------------
// Decoding

/// Decodes one value per (name, type) port, then requires the payload to be used up.
fn decode_ports<N: AsRef<str>>(
    bytes: &[u8],
    ports: &[(N, DataType)],
    unit: TimeUnit,
) -> Result<Vec<Value>, CodecError> {
    if ports.is_empty() {
        return decode_empty(bytes).map(|()| Vec::new());
    }
    let mut reader = Reader::new(bytes, unit);
    let values = ports
        .iter()
        .map(|(name, ty)| read_port(&mut reader, name.as_ref(), *ty))
        .collect::<Result<Vec<_>, _>>()?;
    reader.finish()?;
    Ok(values)
}

/// A message without values is `0x05`; an empty payload is accepted too, since it says
/// the same and some publishers send it.
fn decode_empty(bytes: &[u8]) -> Result<(), CodecError> {
    match bytes {
        [] | [EMPTY] => Ok(()),
        [EMPTY, rest @ ..] => Err(CodecError::Trailing(rest.len())),
        other => Err(CodecError::Trailing(other.len())),
    }
}

/// Reads the value of port `name`, brings its times from the wire unit to milliseconds,
/// and checks it against the port's type: the bytes fix the representation, not the
/// ranges (NaN, a TIME_OF_DAY past midnight, ...).
fn read_port(reader: &mut Reader<'_>, name: &str, ty: DataType) -> Result<Value, CodecError> {
    let type_error = |error| CodecError::Type {
        port: name.to_owned(),
        error,
    };
    let value = match ty {
        DataType::Elementary(t) => read_scalar(reader, t)?,
        DataType::Array(t, n) => read_array(reader, t, n).map_err(|e| match e {
            ArrayError::Codec(e) => e,
            ArrayError::Length(e) => type_error(e),
        })?,
    };
    let value = from_wire_unit(value, reader.unit).map_err(type_error)?;
    value.check(ty).map_err(type_error)?;
    Ok(value)
}

/// Nanoseconds in a millisecond.
const NS_PER_MS: u64 = 1_000_000;

/// A value as read (DATE, TIME_OF_DAY and DATE_AND_TIME in `unit`) to the milliseconds
/// [`Value`] holds: see [`TimeUnit`] for why a sub-millisecond time is truncated and a
/// DATE off midnight refused.
fn from_wire_unit(value: Value, unit: TimeUnit) -> Result<Value, TypeError> {
    if unit == TimeUnit::Milliseconds {
        return Ok(value);
    }
    let out_of_range = |ty: ElementaryType, ns: u64, why: &str| TypeError::OutOfRange {
        ty,
        value: format!("{ns} ns ({why})"),
    };
    Ok(match value {
        Value::Date(ns) if ns % (MS_PER_DAY * NS_PER_MS) != 0 => {
            return Err(out_of_range(ElementaryType::Date, ns, "not midnight"))
        }
        // Reported in the unit it came in, rather than as its truncated milliseconds.
        Value::TimeOfDay(ns) if ns / NS_PER_MS >= MS_PER_DAY => {
            return Err(out_of_range(
                ElementaryType::TimeOfDay,
                ns,
                "a day or more after midnight",
            ))
        }
        Value::Date(ns) => Value::Date(ns / NS_PER_MS),
        Value::TimeOfDay(ns) => Value::TimeOfDay(ns / NS_PER_MS),
        Value::DateAndTime(ns) => Value::DateAndTime(ns / NS_PER_MS),
        Value::Array(ty, items) => Value::Array(
            ty,
            items
                .into_iter()
                .enumerate()
                .map(|(index, item)| {
                    from_wire_unit(item, unit).map_err(|error| TypeError::Element {
                        index,
                        error: Box::new(error),
                    })
                })
                .collect::<Result<_, _>>()?,
        ),
        other => other,
    })
}

/// A DATE, TIME_OF_DAY or DATE_AND_TIME of `ms` milliseconds in `unit`; a value whose
/// nanoseconds do not fit 64 bits is refused (see [`TimeUnit`]).
fn to_wire_unit(value: &Value, ms: u64, unit: TimeUnit) -> Result<u64, TypeError> {
    match unit {
        TimeUnit::Milliseconds => Ok(ms),
        TimeUnit::Nanoseconds => ms.checked_mul(NS_PER_MS).ok_or_else(|| {
            let shown = match crate::codec::json::value_to_json(value) {
                serde_json::Value::String(literal) => literal,
                other => other.to_string(),
            };
            TypeError::OutOfRange {
                ty: value.elementary_type(),
                value: format!(
                    "{shown} (fbdk's 64-bit nanoseconds end at DT#2554-07-21-23:34:33.709)"
                ),
            }
        }),
    }
}

/// Reads a tagged scalar. A BOOL's tag is its whole encoding, so it is read as a body.
fn read_scalar(reader: &mut Reader<'_>, ty: ElementaryType) -> Result<Value, CodecError> {
    if ty != ElementaryType::Bool {
        reader.expect_tag(tag_of(ty), ty.name())?;
    }
    read_body(reader, ty)
}

/// Why an array could not be read: a wire problem, or a count other than the declared one
/// (a type error, which the caller names after the port).
enum ArrayError {
    Codec(CodecError),
    Length(TypeError),
}

impl From<CodecError> for ArrayError {
    fn from(e: CodecError) -> Self {
        ArrayError::Codec(e)
    }
}

/// Reads `ARRAY [n] OF ty`: the array tag, the count, then the elements, which share one
/// tag unless they are BOOLs.
///
/// The count is compared with the declaration before anything is allocated, and the
/// vector's capacity is bounded by the bytes left, so a forged count cannot make the
/// decoder reserve memory the payload does not back.
fn read_array(reader: &mut Reader<'_>, ty: ElementaryType, n: u16) -> Result<Value, ArrayError> {
    reader.expect_tag(ARRAY_TAG, &DataType::Array(ty, n).to_string())?;
    let count = usize::from(u16::from_be_bytes(reader.take_array()?));
    if count != usize::from(n) {
        return Err(ArrayError::Length(TypeError::ArrayLength {
            expected: usize::from(n),
            got: count,
        }));
    }
    if ty != ElementaryType::Bool {
        reader.expect_tag(tag_of(ty), ty.name())?;
    }
    let mut items = Vec::with_capacity(array_capacity(count, reader.remaining()));
    for _ in 0..count {
        items.push(read_body(reader, ty)?);
    }
    Ok(Value::Array(ty, items))
}

/// Capacity to reserve for `count` elements with `remaining` bytes left: every element
/// takes at least one byte, so no more than `remaining` of them can be there.
fn array_capacity(count: usize, remaining: usize) -> usize {
    count.min(remaining)
}

/// Reads the bytes after a tag: the value of a `ty` in its fixed width or with its length.
/// A BOOL has no bytes after its tag, so its "body" is the tag byte itself; this is also
/// how each element of a BOOL array is written.
fn read_body(reader: &mut Reader<'_>, ty: ElementaryType) -> Result<Value, CodecError> {
    use ElementaryType as T;
    Ok(match ty {
        T::Bool => Value::Bool(read_bool(reader)?),
        T::Sint => Value::Sint(i8::from_be_bytes(reader.take_array()?)),
        T::Int => Value::Int(i16::from_be_bytes(reader.take_array()?)),
        T::Dint => Value::Dint(i32::from_be_bytes(reader.take_array()?)),
        T::Lint => Value::Lint(i64::from_be_bytes(reader.take_array()?)),
        T::Usint => Value::Usint(u8::from_be_bytes(reader.take_array()?)),
        T::Uint => Value::Uint(u16::from_be_bytes(reader.take_array()?)),
        T::Udint => Value::Udint(u32::from_be_bytes(reader.take_array()?)),
        T::Ulint => Value::Ulint(u64::from_be_bytes(reader.take_array()?)),
        T::Real => Value::Real(f32::from_be_bytes(reader.take_array()?)),
        T::Lreal => Value::Lreal(f64::from_be_bytes(reader.take_array()?)),
        T::Byte => Value::Byte(u8::from_be_bytes(reader.take_array()?)),
        T::Word => Value::Word(u16::from_be_bytes(reader.take_array()?)),
        T::Dword => Value::Dword(u32::from_be_bytes(reader.take_array()?)),
        T::Lword => Value::Lword(u64::from_be_bytes(reader.take_array()?)),
        T::Time => Value::Time(i64::from_be_bytes(reader.take_array()?)),
        T::Date => Value::Date(u64::from_be_bytes(reader.take_array()?)),
        T::TimeOfDay => Value::TimeOfDay(u64::from_be_bytes(reader.take_array()?)),
        T::DateAndTime => Value::DateAndTime(u64::from_be_bytes(reader.take_array()?)),
        T::String => Value::String(read_string(reader)?),
        T::WString => Value::WString(read_wstring(reader)?),
    })
}

/// A BOOL: `0x41` TRUE, `0x40` FALSE; any other byte is a wrong tag.
fn read_bool(reader: &mut Reader<'_>) -> Result<bool, CodecError> {
    let offset = reader.pos;
    match reader.take_array::<1>()? {
        [TRUE_TAG] => Ok(true),
        [FALSE_TAG] => Ok(false),
        [tag] => Err(tag_error(offset, tag, ElementaryType::Bool.name())),
    }
}

/// A STRING: UTF-8 when the bytes are UTF-8, Latin-1 otherwise (see the module doc).
fn read_string(reader: &mut Reader<'_>) -> Result<String, CodecError> {
    let len = usize::from(u16::from_be_bytes(reader.take_array()?));
    let bytes = reader.take(len)?;
    Ok(match std::str::from_utf8(bytes) {
        Ok(text) => text.to_owned(),
        Err(_) => bytes.iter().map(|&b| char::from(b)).collect(),
    })
}

/// A WSTRING: big-endian UTF-16 units; an unpaired surrogate is malformed.
fn read_wstring(reader: &mut Reader<'_>) -> Result<String, CodecError> {
    let units = usize::from(u16::from_be_bytes(reader.take_array()?));
    let offset = reader.pos;
    let bytes = reader.take(units * 2)?;
    let units = bytes
        .chunks_exact(2)
        .map(|pair| u16::from_be_bytes([pair[0], pair[1]]));
    char::decode_utf16(units)
        .collect::<Result<String, _>>()
        .map_err(|e| {
            CodecError::Malformed(format!(
                "WSTRING at offset {offset}: unpaired UTF-16 surrogate 0x{:04x}",
                e.unpaired_surrogate()
            ))
        })
}

fn tag_error(offset: usize, tag: u8, expected: &str) -> CodecError {
    CodecError::Tag {
        offset,
        tag,
        expected: expected.to_owned(),
    }
}

/// A cursor over the payload whose every read is bounds-checked: running out of bytes is
/// a [`CodecError::Truncated`], never a panic.
struct Reader<'a> {
    bytes: &'a [u8],
    /// Offset of the next unread byte; never beyond `bytes.len()`.
    pos: usize,
    /// The unit DATE, TIME_OF_DAY and DATE_AND_TIME are read in.
    unit: TimeUnit,
}

impl<'a> Reader<'a> {
    fn new(bytes: &'a [u8], unit: TimeUnit) -> Self {
        Reader {
            bytes,
            pos: 0,
            unit,
        }
    }

    fn remaining(&self) -> usize {
        self.bytes.len() - self.pos
    }

    /// The next `n` bytes, or how many are missing.
    fn take(&mut self, n: usize) -> Result<&'a [u8], CodecError> {
        let rest = self.bytes.get(self.pos..).unwrap_or_default();
        match rest.get(..n) {
            Some(taken) => {
                self.pos += n;
                Ok(taken)
            }
            None => Err(CodecError::Truncated {
                offset: self.pos,
                needed: n - rest.len(),
            }),
        }
    }

    /// The next `N` bytes as an array, for `from_be_bytes`.
    fn take_array<const N: usize>(&mut self) -> Result<[u8; N], CodecError> {
        let mut out = [0; N];
        // `take` returns exactly N bytes or an error, so the lengths match.
        out.copy_from_slice(self.take(N)?);
        Ok(out)
    }

    /// Reads a tag byte that must be `tag`; `expected` names the type in the error.
    fn expect_tag(&mut self, tag: u8, expected: &str) -> Result<(), CodecError> {
        let offset = self.pos;
        match self.take_array::<1>()? {
            [found] if found == tag => Ok(()),
            [found] => Err(tag_error(offset, found, expected)),
        }
    }

    /// Every byte must have been read.
    fn finish(self) -> Result<(), CodecError> {
        match self.remaining() {
            0 => Ok(()),
            n => Err(CodecError::Trailing(n)),
        }
    }
}

// ---------------------------------------------------------------------------------------
// Encoding

/// The tag of a non-array value of `ty` (for BOOL, the TRUE tag).
fn tag_of(ty: ElementaryType) -> u8 {
    APPLICATION | ty.number()
}

/// Encodes `values` in order, naming the value at index `i` `name(i)` in an error.
fn encode_named(
    values: &[Value],
    name: impl Fn(usize) -> String,
    unit: TimeUnit,
) -> Result<Vec<u8>, CodecError> {
    if values.is_empty() {
        return Ok(vec![EMPTY]);
    }
    let mut out = Vec::new();
    for (i, value) in values.iter().enumerate() {
        write_value(value, unit, &mut out).map_err(|error| CodecError::Type {
            port: name(i),
            error,
        })?;
    }
    Ok(out)
}

/// Writes one tagged value. A BOOL is written by its body alone, which is its tag.
fn write_value(value: &Value, unit: TimeUnit, out: &mut Vec<u8>) -> Result<(), TypeError> {
    match value {
        Value::Array(ty, items) => write_array(*ty, items, unit, out),
        Value::Bool(_) => write_body(value, unit, out),
        scalar => {
            out.push(tag_of(scalar.elementary_type()));
            write_body(scalar, unit, out)
        }
    }
}

/// Writes an array: tag, count, then the elements under one shared tag, or each with its
/// own tag when they are BOOLs.
fn write_array(
    ty: ElementaryType,
    items: &[Value],
    unit: TimeUnit,
    out: &mut Vec<u8>,
) -> Result<(), TypeError> {
    let items = &items[..items.len().min(MAX_ARRAY_LEN)];
    out.push(ARRAY_TAG);
    write_len(items.len(), out);
    if ty != ElementaryType::Bool {
        out.push(tag_of(ty));
    }
    for (index, item) in items.iter().enumerate() {
        write_body(item, unit, out).map_err(|error| TypeError::Element {
            index,
            error: Box::new(error),
        })?;
    }
    Ok(())
}

/// Writes what follows a value's tag (for a BOOL, the tag itself), DATE, TIME_OF_DAY and
/// DATE_AND_TIME in `unit`.
fn write_body(value: &Value, unit: TimeUnit, out: &mut Vec<u8>) -> Result<(), TypeError> {
    match value {
        Value::Bool(b) => out.push(if *b { TRUE_TAG } else { FALSE_TAG }),
        Value::Sint(x) => out.extend_from_slice(&x.to_be_bytes()),
        Value::Int(x) => out.extend_from_slice(&x.to_be_bytes()),
        Value::Dint(x) => out.extend_from_slice(&x.to_be_bytes()),
        Value::Lint(x) | Value::Time(x) => out.extend_from_slice(&x.to_be_bytes()),
        Value::Usint(x) | Value::Byte(x) => out.push(*x),
        Value::Uint(x) | Value::Word(x) => out.extend_from_slice(&x.to_be_bytes()),
        Value::Udint(x) | Value::Dword(x) => out.extend_from_slice(&x.to_be_bytes()),
        Value::Ulint(x) | Value::Lword(x) => out.extend_from_slice(&x.to_be_bytes()),
        Value::Date(ms) | Value::TimeOfDay(ms) | Value::DateAndTime(ms) => {
            out.extend_from_slice(&to_wire_unit(value, *ms, unit)?.to_be_bytes())
        }
        Value::Real(x) => out.extend_from_slice(&x.to_be_bytes()),
        Value::Lreal(x) => out.extend_from_slice(&x.to_be_bytes()),
        Value::String(s) => write_string(s, out),
        Value::WString(s) => write_wstring(s, out),
        // Arrays do not nest in IEC 61499 ports; see `encode_values`.
        Value::Array(..) => {}
    }
    Ok(())
}

/// A STRING as its UTF-8 bytes, cut at [`MAX_STRING_LEN`] bytes.
fn write_string(s: &str, out: &mut Vec<u8>) {
    let bytes = &s.as_bytes()[..s.len().min(MAX_STRING_LEN)];
    write_len(bytes.len(), out);
    out.extend_from_slice(bytes);
}

/// A WSTRING as big-endian UTF-16 units, cut at [`MAX_STRING_LEN`] units.
fn write_wstring(s: &str, out: &mut Vec<u8>) {
    let units: Vec<u16> = s.encode_utf16().take(MAX_STRING_LEN).collect();
    write_len(units.len(), out);
    for unit in units {
        out.extend_from_slice(&unit.to_be_bytes());
    }
}

/// A two-byte length or count; callers cut what they count to 65,535 first.
fn write_len(len: usize, out: &mut Vec<u8>) {
    let len = u16::try_from(len).unwrap_or(u16::MAX);
    out.extend_from_slice(&len.to_be_bytes());
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::value::MS_PER_DAY;
    use ElementaryType as T;

    fn el(t: ElementaryType) -> DataType {
        DataType::Elementary(t)
    }

    const NS: TimeUnit = TimeUnit::Nanoseconds;
    const MS: TimeUnit = TimeUnit::Milliseconds;
    const UNITS: [TimeUnit; 2] = [NS, MS];

    /// Whether the wire unit matters for values of `ty`.
    fn is_dated(ty: DataType) -> bool {
        let t = match ty {
            DataType::Elementary(t) | DataType::Array(t, _) => t,
        };
        matches!(t, T::Date | T::TimeOfDay | T::DateAndTime)
    }

    /// Decodes `bytes` in `unit` as one value of `ty`, asserts it is `value`, and that
    /// encoding `value` in `unit` gives `bytes` back.
    fn assert_wire_in(unit: TimeUnit, bytes: &[u8], ty: DataType, value: Value) {
        assert_eq!(
            decode(bytes, &OutputPort::Data(ty), unit),
            Ok(Message::Data(value.clone())),
            "decoding {bytes:02x?} as {ty} in {unit:?}"
        );
        assert_eq!(
            encode(&Message::Data(value.clone()), &OutputPort::Data(ty), unit),
            Ok(bytes.to_vec()),
            "encoding {value:?} in {unit:?}"
        );
    }

    /// [`assert_wire_in`] in both units, for a type the unit does not concern.
    fn assert_wire(bytes: &[u8], ty: DataType, value: Value) {
        assert!(!is_dated(ty), "{ty}: say which unit");
        for unit in UNITS {
            assert_wire_in(unit, bytes, ty, value.clone());
        }
    }

    /// An 8-byte DATE, TIME_OF_DAY or DATE_AND_TIME (`tag`) on the wire.
    fn dated(tag: u8, raw: u64) -> Vec<u8> {
        let mut bytes = vec![tag];
        bytes.extend(raw.to_be_bytes());
        bytes
    }

    #[test]
    fn hand_written_bytes_decode_and_encode() {
        assert_wire(&[0x41], el(T::Bool), Value::Bool(true));
        assert_wire(&[0x40], el(T::Bool), Value::Bool(false));
        assert_wire(&[0x42, 0x80], el(T::Sint), Value::Sint(-128));
        assert_wire(&[0x43, 0xFF, 0xFE], el(T::Int), Value::Int(-2));
        assert_wire(&[0x44, 0, 0, 0, 1], el(T::Dint), Value::Dint(1));
        assert_wire(
            &[0x45, 0xFF, 0xFF, 0xFF, 0xFF, 0xFF, 0xFF, 0xFF, 0xFF],
            el(T::Lint),
            Value::Lint(-1),
        );
        assert_wire(&[0x46, 0xFF], el(T::Usint), Value::Usint(255));
        assert_wire(&[0x47, 0x12, 0x34], el(T::Uint), Value::Uint(0x1234));
        assert_wire(&[0x48, 0, 0, 1, 0], el(T::Udint), Value::Udint(256));
        assert_wire(
            &[0x49, 0, 0, 0, 0, 0, 0, 0, 7],
            el(T::Ulint),
            Value::Ulint(7),
        );
        assert_wire(
            &[0x4A, 0x3F, 0x80, 0x00, 0x00],
            el(T::Real),
            Value::Real(1.0),
        );
        assert_wire(
            &[0x4B, 0xC0, 0x00, 0, 0, 0, 0, 0, 0],
            el(T::Lreal),
            Value::Lreal(-2.0),
        );
        assert_wire(
            &[0x4C, 0, 0, 0, 0, 0, 0x0F, 0x42, 0x40],
            el(T::Time),
            Value::Time(1_000_000),
        );
        // FORTE 2.x: 1970-01-02 is 86,400,000 ms = 0x05265C00.
        assert_wire_in(
            MS,
            &[0x4D, 0, 0, 0, 0, 0x05, 0x26, 0x5C, 0x00],
            el(T::Date),
            Value::Date(MS_PER_DAY),
        );
        assert_wire_in(
            MS,
            &[0x4E, 0, 0, 0, 0, 0, 0, 0x03, 0xE8],
            el(T::TimeOfDay),
            Value::TimeOfDay(1000),
        );
        assert_wire_in(
            MS,
            &[0x4F, 0, 0, 0, 0, 0, 0, 0, 0x2A],
            el(T::DateAndTime),
            Value::DateAndTime(42),
        );
        // FORTE 3.x: 1970-01-02 is 86,400,000,000,000 ns = 0x4E94914F0000.
        assert_wire_in(
            NS,
            &[0x4D, 0, 0, 0x4E, 0x94, 0x91, 0x4F, 0x00, 0x00],
            el(T::Date),
            Value::Date(MS_PER_DAY),
        );
        // One second: 1,000,000,000 ns = 0x3B9ACA00.
        assert_wire_in(
            NS,
            &[0x4E, 0, 0, 0, 0, 0x3B, 0x9A, 0xCA, 0x00],
            el(T::TimeOfDay),
            Value::TimeOfDay(1000),
        );
        // 42 ms: 42,000,000 ns = 0x0280DE80.
        assert_wire_in(
            NS,
            &[0x4F, 0, 0, 0, 0, 0x02, 0x80, 0xDE, 0x80],
            el(T::DateAndTime),
            Value::DateAndTime(42),
        );
        assert_wire(
            &[0x50, 0x00, 0x02, 0x41, 0x42],
            el(T::String),
            Value::String("AB".into()),
        );
        assert_wire(&[0x51, 0xAB], el(T::Byte), Value::Byte(0xAB));
        assert_wire(&[0x52, 0xBE, 0xEF], el(T::Word), Value::Word(0xBEEF));
        assert_wire(
            &[0x53, 0xDE, 0xAD, 0xBE, 0xEF],
            el(T::Dword),
            Value::Dword(0xDEAD_BEEF),
        );
        assert_wire(
            &[0x54, 1, 2, 3, 4, 5, 6, 7, 8],
            el(T::Lword),
            Value::Lword(0x0102_0304_0506_0708),
        );
        assert_wire(
            &[0x55, 0x00, 0x01, 0x00, 0xE9],
            el(T::WString),
            Value::WString("é".into()),
        );
        assert_wire(
            &[0x76, 0x00, 0x03, 0x43, 0, 1, 0, 2, 0, 3],
            DataType::Array(T::Int, 3),
            Value::Array(T::Int, vec![Value::Int(1), Value::Int(2), Value::Int(3)]),
        );
        assert_wire(
            &[0x76, 0x00, 0x02, 0x41, 0x40],
            DataType::Array(T::Bool, 2),
            Value::Array(T::Bool, vec![Value::Bool(true), Value::Bool(false)]),
        );
    }

    #[test]
    fn events_are_their_with_values_concatenated() {
        let port = OutputPort::Event(vec![("POS", el(T::Int)), ("OK", el(T::Bool))]);
        let bytes = [0x43, 0xFF, 0xFE, 0x41];
        let message = Message::Event(EventMessage {
            seq: None,
            ts_us: None,
            data: vec![Value::Int(-2), Value::Bool(true)],
        });
        assert_eq!(decode(&bytes, &port, MS), Ok(message.clone()));
        assert_eq!(encode(&message, &port, MS).unwrap(), bytes);
        // seq and ts_us have no place on the wire.
        let stamped = Message::Event(EventMessage {
            seq: Some(9),
            ts_us: Some(1),
            data: vec![Value::Int(-2), Value::Bool(true)],
        });
        assert_eq!(encode(&stamped, &port, MS).unwrap(), bytes);
    }

    #[test]
    fn an_event_without_data_is_0x05() {
        let port = OutputPort::Event(vec![]);
        let empty = Message::Event(EventMessage {
            seq: None,
            ts_us: None,
            data: vec![],
        });
        assert_eq!(decode(&[0x05], &port, MS), Ok(empty.clone()));
        assert_eq!(decode(&[], &port, MS), Ok(empty.clone()));
        assert_eq!(encode(&empty, &port, MS).unwrap(), [0x05]);
        assert_eq!(
            decode(&[0x05, 0x00], &port, MS),
            Err(CodecError::Trailing(1))
        );
        assert_eq!(decode(&[0x41], &port, MS), Err(CodecError::Trailing(1)));
        assert_eq!(encode_values(&[], MS).unwrap(), [0x05]);
        assert_eq!(decode_values(&[0x05], &[], MS), Ok(vec![]));
    }

    #[test]
    fn strings_that_are_not_utf8_are_latin1() {
        assert_wire(
            &[0x50, 0x00, 0x00],
            el(T::String),
            Value::String(String::new()),
        );
        assert_eq!(
            decode_values(&[0x50, 0x00, 0x02, 0xE9, 0x41], &[el(T::String)], MS),
            Ok(vec![Value::String("éA".into())])
        );
        assert_wire(
            &[0x50, 0x00, 0x02, 0xC3, 0xA9],
            el(T::String),
            Value::String("é".into()),
        );
        // 40,000 Latin-1 bytes are 80,000 UTF-8 bytes: too long to forward.
        let mut long = vec![0x50, 0x9C, 0x40];
        long.resize(long.len() + 40_000, 0xE9);
        assert!(matches!(
            decode_values(&long, &[el(T::String)], MS),
            Err(CodecError::Type {
                error: TypeError::TooLong(T::String),
                ..
            })
        ));
    }

    /// Values of every elementary type, with the extremes of each.
    fn samples() -> Vec<Value> {
        vec![
            Value::Bool(true),
            Value::Bool(false),
            Value::Sint(i8::MIN),
            Value::Sint(i8::MAX),
            Value::Int(i16::MIN),
            Value::Int(i16::MAX),
            Value::Dint(i32::MIN),
            Value::Dint(i32::MAX),
            Value::Lint(i64::MIN),
            Value::Lint(i64::MAX),
            Value::Usint(0),
            Value::Usint(u8::MAX),
            Value::Uint(0),
            Value::Uint(u16::MAX),
            Value::Udint(0),
            Value::Udint(u32::MAX),
            Value::Ulint(0),
            Value::Ulint(u64::MAX),
            Value::Real(f32::MAX),
            Value::Real(f32::MIN),
            Value::Real(f32::MIN_POSITIVE),
            Value::Real(-0.5),
            Value::Lreal(f64::MAX),
            Value::Lreal(f64::MIN),
            Value::Lreal(f64::EPSILON),
            Value::Byte(0),
            Value::Byte(u8::MAX),
            Value::Word(0),
            Value::Word(u16::MAX),
            Value::Dword(0),
            Value::Dword(u32::MAX),
            Value::Lword(0),
            Value::Lword(u64::MAX),
            Value::String(String::new()),
            Value::String("Förderband 𝄞".into()),
            Value::String("x".repeat(MAX_STRING_LEN)),
            Value::WString(String::new()),
            Value::WString("𝄞".into()),
            Value::WString("Grüße, 世界 𝄞".into()),
            Value::WString("é".repeat(MAX_STRING_LEN)),
            Value::Time(i64::MIN),
            Value::Time(i64::MAX),
            Value::Time(0),
            Value::Date(0),
            Value::Date(
                crate::value::MAX_DATE_AND_TIME_MS
                    - crate::value::MAX_DATE_AND_TIME_MS % MS_PER_DAY,
            ),
            Value::TimeOfDay(0),
            Value::TimeOfDay(MS_PER_DAY - 1),
            Value::DateAndTime(0),
            Value::DateAndTime(crate::value::MAX_DATE_AND_TIME_MS),
            // The last ones 64-bit nanoseconds hold (FORTE 3.x).
            Value::Date(LAST_NS_MS - LAST_NS_MS % MS_PER_DAY),
            Value::DateAndTime(LAST_NS_MS),
        ]
    }

    /// One array per elementary type, holding every sample of that type.
    fn array_samples() -> Vec<Value> {
        array_samples_in(MS)
    }

    /// One array per elementary type, holding every sample of that type `unit` can write.
    fn array_samples_in(unit: TimeUnit) -> Vec<Value> {
        ElementaryType::ALL
            .into_iter()
            .map(|t| {
                let items = samples()
                    .into_iter()
                    .filter(|v| v.elementary_type() == t)
                    .collect();
                Value::Array(t, writable_in(unit, items))
            })
            .collect()
    }

    /// The last DATE_AND_TIME (in ms) whose nanoseconds fit 64 bits: 2554-07-21-23:34:33.709.
    const LAST_NS_MS: u64 = u64::MAX / 1_000_000;

    /// Whether `value` can be written in nanoseconds (every value can in milliseconds).
    fn fits_ns(value: &Value) -> bool {
        match value {
            Value::Date(ms) | Value::DateAndTime(ms) => *ms <= LAST_NS_MS,
            Value::Array(_, items) => items.iter().all(fits_ns),
            _ => true,
        }
    }

    /// `values` without what cannot be written in `unit` (array elements included).
    fn writable_in(unit: TimeUnit, values: Vec<Value>) -> Vec<Value> {
        if unit == MS {
            return values;
        }
        values.into_iter().filter(fits_ns).collect()
    }

    fn assert_round_trip(value: &Value, unit: TimeUnit) {
        let ty = value.data_type();
        let bytes = encode_values(std::slice::from_ref(value), unit).unwrap();
        assert_eq!(
            decode_values(&bytes, &[ty], unit),
            Ok(vec![value.clone()]),
            "{ty} in {unit:?}"
        );
    }

    #[test]
    fn every_type_round_trips() {
        for t in ElementaryType::ALL {
            assert!(
                samples().iter().any(|v| v.elementary_type() == t),
                "no sample of {t}"
            );
        }
        for unit in UNITS {
            let values = writable_in(
                unit,
                samples()
                    .into_iter()
                    .chain(array_samples_in(unit))
                    .collect(),
            );
            for value in &values {
                assert_round_trip(value, unit);
            }
            assert_round_trip(
                &Value::Array(T::Lint, vec![Value::Lint(0); MAX_ARRAY_LEN]),
                unit,
            );
            // All of them in one message, as an event and as SD_1..SD_n.
            let types: Vec<DataType> = values.iter().map(Value::data_type).collect();
            let bytes = encode_values(&values, unit).unwrap();
            assert_eq!(decode_values(&bytes, &types, unit), Ok(values.clone()));
            let names: Vec<String> = (0..values.len()).map(|i| format!("P{i}")).collect();
            let port = OutputPort::Event(
                names
                    .iter()
                    .map(String::as_str)
                    .zip(types.iter().copied())
                    .collect(),
            );
            let message = Message::Event(EventMessage {
                seq: None,
                ts_us: None,
                data: values,
            });
            assert_eq!(
                decode(&encode(&message, &port, unit).unwrap(), &port, unit),
                Ok(message)
            );
        }
    }

    #[test]
    fn every_truncation_is_reported() {
        let values = vec![
            Value::Bool(false),
            Value::Int(7),
            Value::String("abc".into()),
            Value::WString("𝄞".into()),
            Value::Array(T::Bool, vec![Value::Bool(true); 3]),
            Value::Array(T::Lreal, vec![Value::Lreal(0.25); 2]),
            Value::Time(-5),
            Value::DateAndTime(1_795_350_615_250),
        ];
        let types: Vec<DataType> = values.iter().map(Value::data_type).collect();
        for unit in UNITS {
            let bytes = encode_values(&values, unit).unwrap();
            for len in 0..bytes.len() {
                match decode_values(&bytes[..len], &types, unit) {
                    Err(CodecError::Truncated { offset, needed }) => {
                        assert!(
                            offset <= len && needed > 0,
                            "prefix {len}: {offset} {needed}"
                        );
                        assert!(offset + needed <= bytes.len(), "prefix {len}");
                    }
                    other => panic!("prefix of {len} bytes in {unit:?}: {other:?}"),
                }
            }
            assert_eq!(decode_values(&bytes, &types, unit), Ok(values.clone()));
        }
        assert_eq!(
            decode(&[0x43, 0x00], &OutputPort::Data(el(T::Int)), MS),
            Err(CodecError::Truncated {
                offset: 1,
                needed: 1
            })
        );
        assert_eq!(
            decode(&[], &OutputPort::Data(el(T::Bool)), MS),
            Err(CodecError::Truncated {
                offset: 0,
                needed: 1
            })
        );
    }

    #[test]
    fn wrong_tags_are_reported_with_the_expected_type() {
        let tag = |offset, tag, expected: &str| {
            Err(CodecError::Tag {
                offset,
                tag,
                expected: expected.into(),
            })
        };
        assert_eq!(
            decode_values(&[0x44, 0, 0, 0, 1], &[el(T::Int)], MS),
            tag(0, 0x44, "INT")
        );
        assert_eq!(
            decode_values(&[0x42], &[el(T::Bool)], MS),
            tag(0, 0x42, "BOOL")
        );
        // FALSE's tag is not INT's.
        assert_eq!(
            decode_values(&[0x40], &[el(T::Int)], MS),
            tag(0, 0x40, "INT")
        );
        assert_eq!(
            decode_values(&[0x41, 0x43, 0, 1], &[el(T::Bool), el(T::Dint)], MS),
            tag(1, 0x43, "DINT")
        );
        let array = DataType::Array(T::Int, 2);
        assert_eq!(
            decode_values(&[0x43, 0, 1], &[array], MS),
            tag(0, 0x43, "ARRAY [2] OF INT")
        );
        assert_eq!(
            decode_values(&[0x76, 0, 2, 0x44, 0, 1, 0, 2], &[array], MS),
            tag(3, 0x44, "INT")
        );
        assert_eq!(
            decode_values(
                &[0x76, 0, 2, 0x41, 0x43],
                &[DataType::Array(T::Bool, 2)],
                MS
            ),
            tag(4, 0x43, "BOOL")
        );
        // A scalar port does not take an array.
        assert_eq!(
            decode_values(&[0x76, 0, 1, 0x43, 0, 1], &[el(T::Int)], MS),
            tag(0, 0x76, "INT")
        );
    }

    #[test]
    fn trailing_bytes_are_refused() {
        assert_eq!(
            decode(&[0x43, 0, 1, 0x00], &OutputPort::Data(el(T::Int)), MS),
            Err(CodecError::Trailing(1))
        );
        assert_eq!(
            decode_values(&[0x41, 0x40, 0x41], &[el(T::Bool), el(T::Bool)], MS),
            Err(CodecError::Trailing(1))
        );
    }

    #[test]
    fn array_counts_must_match_the_declaration() {
        assert_eq!(
            decode_values(
                &[0x76, 0, 2, 0x43, 0, 1, 0, 2],
                &[DataType::Array(T::Int, 3)],
                MS
            ),
            Err(CodecError::Type {
                port: "SD_1".into(),
                error: TypeError::ArrayLength {
                    expected: 3,
                    got: 2
                }
            })
        );
        // A forged count is refused before anything is allocated for it.
        assert!(matches!(
            decode_values(
                &[0x76, 0xFF, 0xFF, 0x43, 0, 1],
                &[DataType::Array(T::Int, 3)],
                MS
            ),
            Err(CodecError::Type {
                error: TypeError::ArrayLength { got: 65_535, .. },
                ..
            })
        ));
    }

    #[test]
    fn a_huge_declared_array_with_a_short_payload_is_truncated() {
        let ty = DataType::Array(T::Lint, u16::MAX);
        assert_eq!(
            decode_values(&[0x76, 0xFF, 0xFF, 0x45, 0, 0, 0], &[ty], MS),
            Err(CodecError::Truncated {
                offset: 4,
                needed: 5
            })
        );
        let ty = DataType::Array(T::Bool, u16::MAX);
        assert_eq!(
            decode_values(&[0x76, 0xFF, 0xFF], &[ty], MS),
            Err(CodecError::Truncated {
                offset: 3,
                needed: 1
            })
        );
        // What is reserved for the elements is bounded by the bytes that are there.
        assert_eq!(array_capacity(65_535, 3), 3);
        assert_eq!(array_capacity(2, 100), 2);
    }

    #[test]
    fn unpaired_surrogates_are_malformed() {
        for units in [
            [0xD8, 0x34, 0x00, 0x41], // high surrogate, then 'A'
            [0xDD, 0x1E, 0x00, 0x41], // low surrogate first
        ] {
            let mut bytes = vec![0x55, 0x00, 0x02];
            bytes.extend(units);
            assert!(
                matches!(
                    decode_values(&bytes, &[el(T::WString)], MS),
                    Err(CodecError::Malformed(_))
                ),
                "{bytes:02x?}"
            );
        }
        assert!(matches!(
            decode_values(&[0x55, 0x00, 0x01, 0xD8, 0x34], &[el(T::WString)], MS),
            Err(CodecError::Malformed(_))
        ));
    }

    #[test]
    fn values_out_of_range_are_type_errors_named_after_the_port() {
        let nan = [0x4A, 0x7F, 0xC0, 0x00, 0x00];
        assert!(matches!(
            decode(&nan, &OutputPort::Data(el(T::Real)), MS),
            Err(CodecError::Type { port, error: TypeError::OutOfRange { .. } }) if port == DATA_PORT_NAME
        ));
        let port = OutputPort::Event(vec![("POS", el(T::Int)), ("AT", el(T::TimeOfDay))]);
        let mut bytes = vec![0x43, 0, 1, 0x4E];
        bytes.extend(MS_PER_DAY.to_be_bytes());
        assert!(matches!(
            decode(&bytes, &port, MS),
            Err(CodecError::Type { port, error: TypeError::OutOfRange { .. } }) if port == "AT"
        ));
        assert!(matches!(
            decode_values(&[0x41, 0x4D, 0, 0, 0, 0, 0, 0, 0, 1], &[el(T::Bool), el(T::Date)], MS),
            Err(CodecError::Type { port, .. }) if port == "SD_2"
        ));
        let mut inf_element = vec![0x76, 0, 2, 0x4B];
        inf_element.extend(0.0f64.to_be_bytes());
        inf_element.extend(f64::INFINITY.to_be_bytes());
        assert!(matches!(
            decode_values(&inf_element, &[DataType::Array(T::Lreal, 2)], MS),
            Err(CodecError::Type {
                error: TypeError::Element { index: 1, .. },
                ..
            })
        ));
    }

    /// DT#2026-11-22-12:30:15.250 in milliseconds since the epoch.
    const DT_MS: u64 = 1_795_350_615_250;

    #[test]
    fn forte_3_sends_dates_and_times_in_nanoseconds() {
        // The issue's example as FORTE 3.x writes it: 1,795,350,615,250,000,000 ns.
        let dt = [0x4F, 0x18, 0xEA, 0x5D, 0xDF, 0x55, 0x41, 0x58, 0x80];
        assert_eq!(dated(0x4F, DT_MS * 1_000_000), dt);
        assert_wire_in(NS, &dt, el(T::DateAndTime), Value::DateAndTime(DT_MS));
        // TOD#12:30:15.250 and D#2026-11-22.
        let tod_ms = DT_MS % MS_PER_DAY;
        assert_eq!(tod_ms, 45_015_250);
        assert_wire_in(
            NS,
            &dated(0x4E, 45_015_250_000_000),
            el(T::TimeOfDay),
            Value::TimeOfDay(tod_ms),
        );
        let day_ms = DT_MS - tod_ms;
        assert_wire_in(
            NS,
            &dated(0x4D, day_ms * 1_000_000),
            el(T::Date),
            Value::Date(day_ms),
        );
        // The same value in FORTE 2.x's milliseconds.
        assert_wire_in(
            MS,
            &dated(0x4F, DT_MS),
            el(T::DateAndTime),
            Value::DateAndTime(DT_MS),
        );

        // The wrong unit: FORTE 3.x's nanoseconds read as milliseconds are after 9999 and
        // refused; milliseconds read as nanoseconds are the issue's misreading, the first
        // half hour of 1970 (DT#1970-01-01-00:29:55.350).
        assert!(matches!(
            decode(&dt, &OutputPort::Data(el(T::DateAndTime)), MS),
            Err(CodecError::Type {
                error: TypeError::OutOfRange { .. },
                ..
            })
        ));
        assert_eq!(
            decode(
                &dated(0x4F, DT_MS),
                &OutputPort::Data(el(T::DateAndTime)),
                NS
            ),
            Ok(Message::Data(Value::DateAndTime(1_795_350)))
        );
        assert_eq!(TimeUnit::default(), NS);
    }

    #[test]
    fn sub_millisecond_nanoseconds_are_truncated_to_the_millisecond() {
        let port = |t| OutputPort::Data(el(t));
        let data = |v| Ok(Message::Data(v));
        // DT#2026-11-22-12:30:15.250999999 reads as .250, and writes back as .250000000.
        let ns = DT_MS * 1_000_000 + 999_999;
        assert_eq!(
            decode(&dated(0x4F, ns), &port(T::DateAndTime), NS),
            data(Value::DateAndTime(DT_MS))
        );
        assert_eq!(
            encode_values(&[Value::DateAndTime(DT_MS)], NS),
            Ok(dated(0x4F, DT_MS * 1_000_000))
        );
        assert_eq!(
            decode(&dated(0x4F, 1), &port(T::DateAndTime), NS),
            data(Value::DateAndTime(0))
        );
        // The last nanosecond of a day is the last millisecond of it.
        assert_eq!(
            decode(&dated(0x4E, 86_399_999_999_999), &port(T::TimeOfDay), NS),
            data(Value::TimeOfDay(MS_PER_DAY - 1))
        );
        assert_eq!(
            decode(&dated(0x4E, 999_999), &port(T::TimeOfDay), NS),
            data(Value::TimeOfDay(0))
        );
        // The last nanosecond 64 bits hold: DT#2554-07-21-23:34:33.709551615.
        assert_eq!(
            decode(&dated(0x4F, u64::MAX), &port(T::DateAndTime), NS),
            data(Value::DateAndTime(LAST_NS_MS))
        );
        // Elements of an array, and WITH values of an event, the same way.
        let mut bytes = vec![0x76, 0, 2, 0x4E];
        bytes.extend(1_000_000_001u64.to_be_bytes());
        bytes.extend(2_999_999u64.to_be_bytes());
        assert_eq!(
            decode(
                &bytes,
                &OutputPort::Data(DataType::Array(T::TimeOfDay, 2)),
                NS
            ),
            data(Value::Array(
                T::TimeOfDay,
                vec![Value::TimeOfDay(1_000), Value::TimeOfDay(2)]
            ))
        );
        let event = OutputPort::Event(vec![("POS", el(T::Int)), ("AT", el(T::DateAndTime))]);
        let mut bytes = vec![0x43, 0, 7];
        bytes.extend(dated(0x4F, ns));
        assert_eq!(
            decode(&bytes, &event, NS),
            Ok(Message::Event(EventMessage {
                seq: None,
                ts_us: None,
                data: vec![Value::Int(7), Value::DateAndTime(DT_MS)],
            }))
        );
        // Milliseconds are exact: there is nothing below them on the wire.
        assert_eq!(
            decode(&dated(0x4F, DT_MS + 1), &port(T::DateAndTime), MS),
            data(Value::DateAndTime(DT_MS + 1))
        );
    }

    #[test]
    fn a_date_off_midnight_or_a_time_of_day_past_it_is_refused_in_nanoseconds() {
        let refused = |bytes: &[u8], ty: DataType, unit: TimeUnit| -> String {
            match decode(bytes, &OutputPort::Data(ty), unit) {
                Err(CodecError::Type { port, error }) => {
                    assert_eq!(port, DATA_PORT_NAME);
                    error.to_string()
                }
                other => panic!("{bytes:02x?} as {ty} in {unit:?}: {other:?}"),
            }
        };
        let day_ns = MS_PER_DAY * 1_000_000;
        // A nanosecond, or a millisecond, past midnight is no DATE.
        for off in [1, 1_000_000] {
            let e = refused(&dated(0x4D, day_ns + off), el(T::Date), NS);
            assert!(
                e.contains(&format!("{} ns (not midnight)", day_ns + off)),
                "{e}"
            );
        }
        assert!(refused(&dated(0x4D, 1), el(T::Date), MS).contains("not midnight"));
        // A TIME_OF_DAY of a day or more, reported in the nanoseconds that came.
        for ns in [day_ns, day_ns + 5, u64::MAX] {
            let e = refused(&dated(0x4E, ns), el(T::TimeOfDay), NS);
            assert!(e.contains(&format!("{ns} ns")), "{e}");
        }
        // In an array, the element is named.
        let mut bytes = vec![0x76, 0, 2, 0x4D];
        bytes.extend(0u64.to_be_bytes());
        bytes.extend((day_ns + 1).to_be_bytes());
        assert!(matches!(
            decode(&bytes, &OutputPort::Data(DataType::Array(T::Date, 2)), NS),
            Err(CodecError::Type {
                error: TypeError::Element { index: 1, .. },
                ..
            })
        ));
    }

    #[test]
    fn dates_after_2554_do_not_fit_nanoseconds_and_are_refused_not_wrapped() {
        let last = Value::DateAndTime(LAST_NS_MS);
        assert_eq!(
            encode_values(std::slice::from_ref(&last), NS),
            Ok(dated(0x4F, LAST_NS_MS * 1_000_000))
        );
        let after = [
            Value::DateAndTime(LAST_NS_MS + 1),
            Value::DateAndTime(crate::value::MAX_DATE_AND_TIME_MS),
            Value::Date(LAST_NS_MS - LAST_NS_MS % MS_PER_DAY + MS_PER_DAY),
            Value::DateAndTime(u64::MAX),
            // Not a valid TIME_OF_DAY, but encoding must not panic on it either.
            Value::TimeOfDay(u64::MAX),
        ];
        for value in &after {
            let ty = value.elementary_type();
            match encode_values(&[Value::Bool(true), value.clone()], NS) {
                Err(CodecError::Type {
                    port,
                    error:
                        TypeError::OutOfRange {
                            ty: got,
                            value: text,
                        },
                }) => {
                    assert_eq!((port.as_str(), got), ("SD_2", ty));
                    assert!(text.contains("DT#2554-07-21-23:34:33.709"), "{text}");
                }
                other => panic!("{value:?}: {other:?}"),
            }
            // Milliseconds hold them all.
            let mut expected = vec![0x41];
            expected.extend(dated(
                0x40 | ty.number(),
                match value {
                    Value::Date(ms) | Value::TimeOfDay(ms) | Value::DateAndTime(ms) => *ms,
                    _ => unreachable!(),
                },
            ));
            assert_eq!(
                encode_values(&[Value::Bool(true), value.clone()], MS),
                Ok(expected)
            );
        }
        let e = encode_values(
            &[Value::Date(
                crate::value::MAX_DATE_AND_TIME_MS
                    - crate::value::MAX_DATE_AND_TIME_MS % MS_PER_DAY,
            )],
            NS,
        )
        .unwrap_err()
        .to_string();
        assert!(e.starts_with("SD_1: D#9999-12-31 ("), "{e}");
        // The largest TIME_OF_DAY fits.
        assert!(encode_values(&[Value::TimeOfDay(MS_PER_DAY - 1)], NS).is_ok());
        // Named after the WITH port, the data port, the array element.
        let event = OutputPort::Event(vec![("POS", el(T::Int)), ("AT", el(T::DateAndTime))]);
        let message = Message::Event(EventMessage {
            seq: None,
            ts_us: None,
            data: vec![Value::Int(1), Value::DateAndTime(LAST_NS_MS + 1)],
        });
        assert!(
            matches!(encode(&message, &event, NS), Err(CodecError::Type { port, .. }) if port == "AT")
        );
        assert!(encode(&message, &event, MS).is_ok());
        let data = OutputPort::Data(el(T::DateAndTime));
        let message = Message::Data(Value::DateAndTime(LAST_NS_MS + 1));
        assert!(
            matches!(encode(&message, &data, NS), Err(CodecError::Type { port, .. }) if port == DATA_PORT_NAME)
        );
        let array = Value::Array(
            T::Date,
            vec![Value::Date(0), Value::Date(MS_PER_DAY * 300_000)],
        );
        assert!(matches!(
            encode_values(&[array], NS),
            Err(CodecError::Type {
                error: TypeError::Element { index: 1, .. },
                ..
            })
        ));
    }

    #[test]
    fn time_units_are_named_ns_and_ms() {
        let unit = |text: &str| serde_json::from_str::<TimeUnit>(text).map_err(|e| e.to_string());
        assert_eq!(unit(r#""ns""#), Ok(NS));
        assert_eq!(unit(r#""ms""#), Ok(MS));
        assert!(unit(r#""us""#)
            .unwrap_err()
            .contains("expected `ns` or `ms`"));
    }

    /// A tiny xorshift64 generator: reproducible noise without a new dependency.
    struct XorShift(u64);

    impl XorShift {
        fn next(&mut self) -> u64 {
            self.0 ^= self.0 << 13;
            self.0 ^= self.0 >> 7;
            self.0 ^= self.0 << 17;
            self.0
        }

        fn below(&mut self, n: usize) -> usize {
            (self.next() % n as u64) as usize
        }
    }

    #[test]
    fn random_bytes_never_panic() {
        let shapes = [
            OutputPort::Data(el(T::Bool)),
            OutputPort::Data(el(T::Lint)),
            OutputPort::Data(el(T::String)),
            OutputPort::Data(el(T::WString)),
            OutputPort::Data(DataType::Array(T::Int, 3)),
            OutputPort::Data(DataType::Array(T::Bool, u16::MAX)),
            OutputPort::Data(DataType::Array(T::WString, 2)),
            OutputPort::Event(vec![]),
            OutputPort::Event(vec![
                ("A", el(T::Bool)),
                ("B", el(T::Real)),
                ("C", el(T::String)),
                ("D", DataType::Array(T::TimeOfDay, 2)),
            ]),
            OutputPort::Data(el(T::DateAndTime)),
            OutputPort::Data(el(T::Date)),
            OutputPort::Data(DataType::Array(T::DateAndTime, 2)),
        ];
        // Valid messages to mutate, so the noise also reaches past the first tag.
        let seeds: Vec<Vec<u8>> = array_samples()
            .iter()
            .chain(&samples()[..20])
            .map(|v| encode_values(std::slice::from_ref(v), MS).unwrap())
            .chain([dated(0x4F, 1_795_350_615_250_123_456), dated(0x4D, 0)])
            .collect();
        // Bytes that are tags or small lengths more often than chance would make them.
        let interesting = [
            0x00, 0x01, 0x05, 0x40, 0x41, 0x43, 0x4D, 0x4E, 0x4F, 0x50, 0x55, 0x76, 0xD8, 0xFF,
        ];
        let mut rng = XorShift(0x9E37_79B9_7F4A_7C15);
        let mut accepted = 0;
        for round in 0..5_000 {
            let mut bytes = if round % 2 == 0 {
                seeds[rng.below(seeds.len())].clone()
            } else {
                Vec::new()
            };
            bytes.truncate(rng.below(bytes.len() + 1));
            for _ in 0..rng.below(24) {
                let byte = if rng.below(2) == 0 {
                    interesting[rng.below(interesting.len())]
                } else {
                    rng.next() as u8
                };
                if !bytes.is_empty() && rng.below(3) == 0 {
                    let at = rng.below(bytes.len());
                    bytes[at] = byte;
                } else {
                    bytes.push(byte);
                }
            }
            for (shape, unit) in shapes.iter().flat_map(|s| UNITS.map(|u| (s, u))) {
                if let Ok(message) = decode(&bytes, shape, unit) {
                    accepted += 1;
                    // Whatever is accepted re-encodes to something accepted the same way, in
                    // its own unit and in the other one when it fits there.
                    for to in UNITS {
                        match encode(&message, shape, to) {
                            Ok(again) => assert_eq!(decode(&again, shape, to), Ok(message.clone())),
                            Err(e) => {
                                assert_eq!(to, NS, "{e}");
                                assert_ne!(unit, NS, "{e}");
                            }
                        }
                    }
                }
            }
        }
        // The mutated seeds keep some inputs valid, so the accepting paths are exercised too.
        assert!(accepted > 50, "only {accepted} inputs decoded");
    }
}

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
//! | `DATE`, `TIME_OF_DAY`, `DATE_AND_TIME` | 8 bytes, unsigned milliseconds |
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
//! - **Units of DATE, TIME_OF_DAY and DATE_AND_TIME**: milliseconds (since the epoch, since
//!   midnight, since the epoch), the units [`Value`] holds them in; `TIME` is microseconds.
//!   FORTE versions differ in the resolution they put on the wire, so this is fbbus's
//!   documented choice rather than something the format itself says.
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
use crate::value::{TypeError, Value, MAX_STRING_LEN};

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

/// Decodes an `fbdk` payload published on `port`.
///
/// A data port carries exactly one value of its type; an event carries the values of its
/// WITH ports in WITH order (`0x05`, or an empty payload, when it has none).
pub fn decode(payload: &[u8], port: &OutputPort<'_>) -> Result<Message, CodecError> {
    match port {
        OutputPort::Data(ty) => {
            let mut reader = Reader::new(payload);
            let value = read_port(&mut reader, DATA_PORT_NAME, *ty)?;
            reader.finish()?;
            Ok(Message::Data(value))
        }
        OutputPort::Event(with) => Ok(Message::Event(EventMessage {
            seq: None,
            ts_us: None,
            data: decode_ports(payload, with)?,
        })),
    }
}

/// Encodes a message [`decode`] accepted; an event's `seq` and `ts_us` have no place in
/// this format and are dropped.
pub fn encode(message: &Message) -> Vec<u8> {
    match message {
        Message::Data(value) => encode_values(std::slice::from_ref(value)),
        Message::Event(event) => encode_values(&event.data),
    }
}

/// Encodes values in order, as a 4diac publisher sends its SD_1..SD_n; no values is
/// `[0x05]`.
///
/// The values are expected to pass [`Value::check`] for their types, as every decoded
/// value does. Encoding cannot fail, so values that do not are written as far as the
/// format allows (strings and arrays beyond the two-byte length limits are cut at the
/// limit, an array nested in an array is written as nothing) and may not decode again.
pub fn encode_values(values: &[Value]) -> Vec<u8> {
    if values.is_empty() {
        return vec![EMPTY];
    }
    let mut out = Vec::new();
    for value in values {
        write_value(value, &mut out);
    }
    out
}

/// Decodes what a 4diac publisher sends from its SD_1..SD_n inputs, typed `types` in
/// order; errors name the ports `SD_1`, `SD_2`, ... by position.
pub fn decode_values(bytes: &[u8], types: &[DataType]) -> Result<Vec<Value>, CodecError> {
    let ports: Vec<(String, DataType)> = types
        .iter()
        .enumerate()
        .map(|(i, ty)| (format!("SD_{}", i + 1), *ty))
        .collect();
    decode_ports(bytes, &ports)
}

// ---------------------------------------------------------------------------------------
// Decoding

/// Decodes one value per (name, type) port, then requires the payload to be used up.
fn decode_ports<N: AsRef<str>>(
    bytes: &[u8],
    ports: &[(N, DataType)],
) -> Result<Vec<Value>, CodecError> {
    if ports.is_empty() {
        return decode_empty(bytes).map(|()| Vec::new());
    }
    let mut reader = Reader::new(bytes);
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

/// Reads the value of port `name` and checks it against the port's type: the bytes fix
/// the representation, not the ranges (NaN, a TIME_OF_DAY past midnight, ...).
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
    value.check(ty).map_err(type_error)?;
    Ok(value)
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
}

impl<'a> Reader<'a> {
    fn new(bytes: &'a [u8]) -> Self {
        Reader { bytes, pos: 0 }
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

/// Writes one tagged value. A BOOL is written by its body alone, which is its tag.
fn write_value(value: &Value, out: &mut Vec<u8>) {
    match value {
        Value::Array(ty, items) => write_array(*ty, items, out),
        Value::Bool(_) => write_body(value, out),
        scalar => {
            out.push(tag_of(scalar.elementary_type()));
            write_body(scalar, out);
        }
    }
}

/// Writes an array: tag, count, then the elements under one shared tag, or each with its
/// own tag when they are BOOLs.
fn write_array(ty: ElementaryType, items: &[Value], out: &mut Vec<u8>) {
    let items = &items[..items.len().min(MAX_ARRAY_LEN)];
    out.push(ARRAY_TAG);
    write_len(items.len(), out);
    if ty != ElementaryType::Bool {
        out.push(tag_of(ty));
    }
    for item in items {
        write_body(item, out);
    }
}

/// Writes what follows a value's tag (for a BOOL, the tag itself).
fn write_body(value: &Value, out: &mut Vec<u8>) {
    match value {
        Value::Bool(b) => out.push(if *b { TRUE_TAG } else { FALSE_TAG }),
        Value::Sint(x) => out.extend_from_slice(&x.to_be_bytes()),
        Value::Int(x) => out.extend_from_slice(&x.to_be_bytes()),
        Value::Dint(x) => out.extend_from_slice(&x.to_be_bytes()),
        Value::Lint(x) | Value::Time(x) => out.extend_from_slice(&x.to_be_bytes()),
        Value::Usint(x) | Value::Byte(x) => out.push(*x),
        Value::Uint(x) | Value::Word(x) => out.extend_from_slice(&x.to_be_bytes()),
        Value::Udint(x) | Value::Dword(x) => out.extend_from_slice(&x.to_be_bytes()),
        Value::Ulint(x)
        | Value::Lword(x)
        | Value::Date(x)
        | Value::TimeOfDay(x)
        | Value::DateAndTime(x) => out.extend_from_slice(&x.to_be_bytes()),
        Value::Real(x) => out.extend_from_slice(&x.to_be_bytes()),
        Value::Lreal(x) => out.extend_from_slice(&x.to_be_bytes()),
        Value::String(s) => write_string(s, out),
        Value::WString(s) => write_wstring(s, out),
        // Arrays do not nest in IEC 61499 ports; see `encode_values`.
        Value::Array(..) => {}
    }
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

    /// Decodes `bytes` as one value of `ty`, asserts it is `value`, and that encoding
    /// `value` gives `bytes` back.
    fn assert_wire(bytes: &[u8], ty: DataType, value: Value) {
        assert_eq!(
            decode(bytes, &OutputPort::Data(ty)),
            Ok(Message::Data(value.clone())),
            "decoding {bytes:02x?} as {ty}"
        );
        assert_eq!(
            encode(&Message::Data(value.clone())),
            bytes,
            "encoding {value:?}"
        );
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
        // 1970-01-02: 86,400,000 ms = 0x05265C00.
        assert_wire(
            &[0x4D, 0, 0, 0, 0, 0x05, 0x26, 0x5C, 0x00],
            el(T::Date),
            Value::Date(MS_PER_DAY),
        );
        assert_wire(
            &[0x4E, 0, 0, 0, 0, 0, 0, 0x03, 0xE8],
            el(T::TimeOfDay),
            Value::TimeOfDay(1000),
        );
        assert_wire(
            &[0x4F, 0, 0, 0, 0, 0, 0, 0, 0x2A],
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
        assert_eq!(decode(&bytes, &port), Ok(message.clone()));
        assert_eq!(encode(&message), bytes);
        // seq and ts_us have no place on the wire.
        let stamped = Message::Event(EventMessage {
            seq: Some(9),
            ts_us: Some(1),
            data: vec![Value::Int(-2), Value::Bool(true)],
        });
        assert_eq!(encode(&stamped), bytes);
    }

    #[test]
    fn an_event_without_data_is_0x05() {
        let port = OutputPort::Event(vec![]);
        let empty = Message::Event(EventMessage {
            seq: None,
            ts_us: None,
            data: vec![],
        });
        assert_eq!(decode(&[0x05], &port), Ok(empty.clone()));
        assert_eq!(decode(&[], &port), Ok(empty.clone()));
        assert_eq!(encode(&empty), [0x05]);
        assert_eq!(decode(&[0x05, 0x00], &port), Err(CodecError::Trailing(1)));
        assert_eq!(decode(&[0x41], &port), Err(CodecError::Trailing(1)));
        assert_eq!(encode_values(&[]), [0x05]);
        assert_eq!(decode_values(&[0x05], &[]), Ok(vec![]));
    }

    #[test]
    fn strings_that_are_not_utf8_are_latin1() {
        assert_wire(
            &[0x50, 0x00, 0x00],
            el(T::String),
            Value::String(String::new()),
        );
        assert_eq!(
            decode_values(&[0x50, 0x00, 0x02, 0xE9, 0x41], &[el(T::String)]),
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
            decode_values(&long, &[el(T::String)]),
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
        ]
    }

    /// One array per elementary type, holding every sample of that type.
    fn array_samples() -> Vec<Value> {
        ElementaryType::ALL
            .into_iter()
            .map(|t| {
                let items = samples()
                    .into_iter()
                    .filter(|v| v.elementary_type() == t)
                    .collect();
                Value::Array(t, items)
            })
            .collect()
    }

    fn assert_round_trip(value: &Value) {
        let ty = value.data_type();
        let bytes = encode_values(std::slice::from_ref(value));
        assert_eq!(
            decode_values(&bytes, &[ty]),
            Ok(vec![value.clone()]),
            "{ty}"
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
        for value in samples().iter().chain(&array_samples()) {
            assert_round_trip(value);
        }
        assert_round_trip(&Value::Array(T::Lint, vec![Value::Lint(0); MAX_ARRAY_LEN]));
        // All of them in one message, as an event and as SD_1..SD_n.
        let values: Vec<Value> = samples().into_iter().chain(array_samples()).collect();
        let types: Vec<DataType> = values.iter().map(Value::data_type).collect();
        let bytes = encode_values(&values);
        assert_eq!(decode_values(&bytes, &types), Ok(values.clone()));
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
        assert_eq!(decode(&encode(&message), &port), Ok(message));
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
        ];
        let types: Vec<DataType> = values.iter().map(Value::data_type).collect();
        let bytes = encode_values(&values);
        for len in 0..bytes.len() {
            match decode_values(&bytes[..len], &types) {
                Err(CodecError::Truncated { offset, needed }) => {
                    assert!(
                        offset <= len && needed > 0,
                        "prefix {len}: {offset} {needed}"
                    );
                    assert!(offset + needed <= bytes.len(), "prefix {len}");
                }
                other => panic!("prefix of {len} bytes: {other:?}"),
            }
        }
        assert_eq!(decode_values(&bytes, &types), Ok(values));
        assert_eq!(
            decode(&[0x43, 0x00], &OutputPort::Data(el(T::Int))),
            Err(CodecError::Truncated {
                offset: 1,
                needed: 1
            })
        );
        assert_eq!(
            decode(&[], &OutputPort::Data(el(T::Bool))),
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
            decode_values(&[0x44, 0, 0, 0, 1], &[el(T::Int)]),
            tag(0, 0x44, "INT")
        );
        assert_eq!(decode_values(&[0x42], &[el(T::Bool)]), tag(0, 0x42, "BOOL"));
        // FALSE's tag is not INT's.
        assert_eq!(decode_values(&[0x40], &[el(T::Int)]), tag(0, 0x40, "INT"));
        assert_eq!(
            decode_values(&[0x41, 0x43, 0, 1], &[el(T::Bool), el(T::Dint)]),
            tag(1, 0x43, "DINT")
        );
        let array = DataType::Array(T::Int, 2);
        assert_eq!(
            decode_values(&[0x43, 0, 1], &[array]),
            tag(0, 0x43, "ARRAY [2] OF INT")
        );
        assert_eq!(
            decode_values(&[0x76, 0, 2, 0x44, 0, 1, 0, 2], &[array]),
            tag(3, 0x44, "INT")
        );
        assert_eq!(
            decode_values(&[0x76, 0, 2, 0x41, 0x43], &[DataType::Array(T::Bool, 2)]),
            tag(4, 0x43, "BOOL")
        );
        // A scalar port does not take an array.
        assert_eq!(
            decode_values(&[0x76, 0, 1, 0x43, 0, 1], &[el(T::Int)]),
            tag(0, 0x76, "INT")
        );
    }

    #[test]
    fn trailing_bytes_are_refused() {
        assert_eq!(
            decode(&[0x43, 0, 1, 0x00], &OutputPort::Data(el(T::Int))),
            Err(CodecError::Trailing(1))
        );
        assert_eq!(
            decode_values(&[0x41, 0x40, 0x41], &[el(T::Bool), el(T::Bool)]),
            Err(CodecError::Trailing(1))
        );
    }

    #[test]
    fn array_counts_must_match_the_declaration() {
        assert_eq!(
            decode_values(
                &[0x76, 0, 2, 0x43, 0, 1, 0, 2],
                &[DataType::Array(T::Int, 3)]
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
                &[DataType::Array(T::Int, 3)]
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
            decode_values(&[0x76, 0xFF, 0xFF, 0x45, 0, 0, 0], &[ty]),
            Err(CodecError::Truncated {
                offset: 4,
                needed: 5
            })
        );
        let ty = DataType::Array(T::Bool, u16::MAX);
        assert_eq!(
            decode_values(&[0x76, 0xFF, 0xFF], &[ty]),
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
                    decode_values(&bytes, &[el(T::WString)]),
                    Err(CodecError::Malformed(_))
                ),
                "{bytes:02x?}"
            );
        }
        assert!(matches!(
            decode_values(&[0x55, 0x00, 0x01, 0xD8, 0x34], &[el(T::WString)]),
            Err(CodecError::Malformed(_))
        ));
    }

    #[test]
    fn values_out_of_range_are_type_errors_named_after_the_port() {
        let nan = [0x4A, 0x7F, 0xC0, 0x00, 0x00];
        assert!(matches!(
            decode(&nan, &OutputPort::Data(el(T::Real))),
            Err(CodecError::Type { port, error: TypeError::OutOfRange { .. } }) if port == DATA_PORT_NAME
        ));
        let port = OutputPort::Event(vec![("POS", el(T::Int)), ("AT", el(T::TimeOfDay))]);
        let mut bytes = vec![0x43, 0, 1, 0x4E];
        bytes.extend(MS_PER_DAY.to_be_bytes());
        assert!(matches!(
            decode(&bytes, &port),
            Err(CodecError::Type { port, error: TypeError::OutOfRange { .. } }) if port == "AT"
        ));
        assert!(matches!(
            decode_values(&[0x41, 0x4D, 0, 0, 0, 0, 0, 0, 0, 1], &[el(T::Bool), el(T::Date)]),
            Err(CodecError::Type { port, .. }) if port == "SD_2"
        ));
        let mut inf_element = vec![0x76, 0, 2, 0x4B];
        inf_element.extend(0.0f64.to_be_bytes());
        inf_element.extend(f64::INFINITY.to_be_bytes());
        assert!(matches!(
            decode_values(&inf_element, &[DataType::Array(T::Lreal, 2)]),
            Err(CodecError::Type {
                error: TypeError::Element { index: 1, .. },
                ..
            })
        ));
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
        ];
        // Valid messages to mutate, so the noise also reaches past the first tag.
        let seeds: Vec<Vec<u8>> = array_samples()
            .iter()
            .chain(&samples()[..20])
            .map(|v| encode_values(std::slice::from_ref(v)))
            .collect();
        // Bytes that are tags or small lengths more often than chance would make them.
        let interesting = [
            0x00, 0x01, 0x05, 0x40, 0x41, 0x43, 0x4E, 0x50, 0x55, 0x76, 0xD8, 0xFF,
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
            for shape in &shapes {
                if let Ok(message) = decode(&bytes, shape) {
                    accepted += 1;
                    // Whatever is accepted re-encodes to something accepted the same way.
                    assert_eq!(decode(&encode(&message), shape), Ok(message));
                }
            }
        }
        // The mutated seeds keep some inputs valid, so the accepting paths are exercised too.
        assert!(accepted > 50, "only {accepted} inputs decoded");
    }
}

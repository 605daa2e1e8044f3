//! Writing an `fbdk` payload: each value's tag and body, arrays under one shared tag,
//! strings and arrays cut at the format's two-byte lengths.

use super::time::to_wire_unit;
use super::{tag_of, TimeUnit, ARRAY_TAG, EMPTY, FALSE_TAG, TRUE_TAG};
use crate::codec::CodecError;
use crate::types::{ElementaryType, MAX_ARRAY_LEN};
use crate::value::{TypeError, Value, MAX_STRING_LEN};

/// Encodes `values` in order, naming the value at index `i` `name(i)` in an error.
pub(super) fn encode_named(
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
pub(super) fn write_value(
    value: &Value,
    unit: TimeUnit,
    out: &mut Vec<u8>,
) -> Result<(), TypeError> {
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
pub(super) fn write_array(
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
pub(super) fn write_body(
    value: &Value,
    unit: TimeUnit,
    out: &mut Vec<u8>,
) -> Result<(), TypeError> {
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
pub(super) fn write_string(s: &str, out: &mut Vec<u8>) {
    let bytes = &s.as_bytes()[..s.len().min(MAX_STRING_LEN)];
    write_len(bytes.len(), out);
    out.extend_from_slice(bytes);
}

/// A WSTRING as big-endian UTF-16 units, cut at [`MAX_STRING_LEN`] units.
pub(super) fn write_wstring(s: &str, out: &mut Vec<u8>) {
    let units: Vec<u16> = s.encode_utf16().take(MAX_STRING_LEN).collect();
    write_len(units.len(), out);
    for unit in units {
        out.extend_from_slice(&unit.to_be_bytes());
    }
}

/// A two-byte length or count; callers cut what they count to 65,535 first.
pub(super) fn write_len(len: usize, out: &mut Vec<u8>) {
    let len = u16::try_from(len).unwrap_or(u16::MAX);
    out.extend_from_slice(&len.to_be_bytes());
}

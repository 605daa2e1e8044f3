//! Sparkplug B 3.0 payloads for FB values: which Sparkplug datatype an IEC 61131-3 port
//! type becomes, and how its [`Value`] is written into, and read back from, a metric.
//!
//! Sparkplug B (Eclipse Sparkplug 3.0) carries typed values over MQTT as protobuf
//! [`proto::Payload`]s: each [`proto::payload::Metric`] has a `datatype` number and its
//! value in one field of a `oneof` (`int_value`, `long_value`, `float_value`,
//! `double_value`, `boolean_value`, `string_value`, `bytes_value`, ...). This module is the
//! one place that decides how fbbus's FB model meets that: [`datatype`] (port type to
//! Sparkplug datatype), [`metric_value`] (value to metric field), [`metric`] (a whole
//! metric), and [`value_of`] (a metric a Sparkplug host wrote, a DCMD, back to a value of
//! the port's type, checked). It knows nothing of topics, births or sequence numbers.
//!
//! ## The mapping
//!
//! | IEC 61131-3 | Sparkplug datatype | field | value |
//! |---|---|---|---|
//! | `BOOL` | `Boolean` (11) | `boolean_value` | |
//! | `SINT` | `Int8` (1) | `int_value` | sign-extended to 32 bits: -1 is `0xFFFFFFFF` |
//! | `INT` | `Int16` (2) | `int_value` | sign-extended to 32 bits |
//! | `DINT` | `Int32` (3) | `int_value` | two's complement |
//! | `LINT` | `Int64` (4) | `long_value` | two's complement |
//! | `USINT`, `BYTE` | `UInt8` (5) | `int_value` | |
//! | `UINT`, `WORD` | `UInt16` (6) | `int_value` | |
//! | `UDINT`, `DWORD` | `UInt32` (7) | `long_value` | as Tahu writes it (`int_value` also read) |
//! | `ULINT`, `LWORD` | `UInt64` (8) | `long_value` | |
//! | `REAL` | `Float` (9) | `float_value` | |
//! | `LREAL` | `Double` (10) | `double_value` | |
//! | `STRING`, `WSTRING` | `String` (12) | `string_value` | UTF-8 |
//! | `TIME` | `Int64` (4) | `long_value` | signed **microseconds**, two's complement |
//! | `DATE` | `DateTime` (13) | `long_value` | ms since 1970-01-01 UTC, at midnight |
//! | `DATE_AND_TIME` | `DateTime` (13) | `long_value` | ms since 1970-01-01 UTC |
//! | `TIME_OF_DAY` | `UInt32` (7) | `long_value` | ms since midnight (`int_value` also read) |
//! | `ARRAY [n] OF t` | the array type of `t`'s datatype | `bytes_value` | see below |
//!
//! Why these:
//!
//! - **Integers keep their width and signedness.** Each IEC integer has a Sparkplug
//!   integer of the same range, so a host shows and range-checks the tag as the FB
//!   declares it. The bit strings (`BYTE` .. `LWORD`) are unsigned integers of their width:
//!   Sparkplug has no bit-string type, and an unsigned number is what a host can display
//!   and write back.
//! - **`TIME` is `Int64` microseconds**, the unit every fbbus codec uses for `TIME`
//!   ([`crate::value`]): Sparkplug has no duration type, and a signed 64-bit count holds
//!   every `TIME` exactly. A host sees a plain number; the tag's unit is microseconds.
//! - **`DATE` and `DATE_AND_TIME` are `DateTime`**, Sparkplug's ms-since-epoch UTC type,
//!   which is exactly fbbus's unit for both; a `DATE` is one at midnight UTC, and
//!   [`value_of`] refuses a `DATE` that is not.
//! - **`TIME_OF_DAY` is `UInt32` milliseconds since midnight**: Sparkplug has no
//!   time-of-day type; a day has fewer than 2^32 ms; `DateTime` would suggest a date.
//! - **`WSTRING` is `String`**: Sparkplug strings are UTF-8 and fbbus holds WSTRING as
//!   Unicode text, so only the limit differs (65,535 UTF-16 units rather than bytes).
//!
//! Sparkplug's `Text`, `UUID`, `Bytes`, `File`, `DataSet`, `Template` and the property
//! types have no IEC counterpart here and are never produced, nor accepted.
//!
//! ### Arrays (Sparkplug 3.0 array types)
//!
//! `ARRAY [n] OF t` maps to `Int8Array` .. `UInt64Array`, `FloatArray`, `DoubleArray`,
//! `BooleanArray`, `StringArray` or `DateTimeArray` after `t`'s scalar datatype (so
//! `ARRAY OF TIME` is `Int64Array` of microseconds, `ARRAY OF TIME_OF_DAY` is
//! `UInt32Array`, `ARRAY OF DATE` is `DateTimeArray`). The value is in `bytes_value`:
//!
//! - numeric arrays: the elements packed little-endian, 1, 2, 4 or 8 bytes each (`Float`
//!   4, `Double` 8, `DateTime` an 8-byte unsigned ms count). `INT [1, -2]` is
//!   `01 00 FE FF`;
//! - `BooleanArray`: the element count as 4 bytes little-endian, then the elements one bit
//!   each, the first in the most significant bit of the first byte, the last byte padded
//!   with zeros. `[TRUE, FALSE, TRUE]` is `03 00 00 00 A0`;
//! - `StringArray`: each string's UTF-8 bytes followed by a NUL byte. `['a', 'bc']` is
//!   `61 00 62 63 00`. (So an element cannot hold NUL, which fbbus refuses in every
//!   string anyway.)
//!
//! These are the encodings of the Tahu Java reference implementation and of pysparkplug.
//!
//! ## Where hosts disagree, and what [`value_of`] accepts
//!
//! The Sparkplug 3.0 specification names a protobuf type per datatype but not always
//! how a value is put in it, and real implementations differ. fbbus writes one form
//! (the table above) and reads every form a host in use is known to write, as long as it
//! means one value:
//!
//! - **`Int8`/`Int16` in `int_value`.** Tahu Java writes a negative value sign-extended
//!   (`setIntValue((byte) -1)` is `0xFFFFFFFF`), and Tahu JS reads it back as a signed
//!   32-bit number, so fbbus writes that. pysparkplug (0.6.1) writes the two's complement
//!   of the datatype's width instead (`Int8` -1 is `0xFF`, `Int16` -1 is `0xFFFF`).
//!   [`value_of`] accepts both: a value in the type's range read as a signed 32-bit
//!   number, or a value below 2^8 (2^16) read as a signed 8-bit (16-bit) number. Anything
//!   else (`0x100` for `Int8`) is out of range. The two forms never overlap on a
//!   different value. (pysparkplug 0.6.1 refuses the sign-extended form when it reads:
//!   such a host sees a negative `SINT` or `INT` as an error.)
//! - **`UInt32` in `long_value` or `int_value`.** The Sparkplug 3.0 text names `uint32`
//!   (`int_value`), and pysparkplug writes it there; Tahu Java, the reference
//!   implementation Ignition uses, writes `long_value` and reads either; Tahu JS
//!   (`sparkplug-payload` 1.x) reads only `long_value` (eclipse-tahu/tahu#76). fbbus
//!   writes `long_value`, the one field every one of them reads (pysparkplug reads
//!   whichever is set), and [`value_of`] reads either, refusing a `long_value` above
//!   2^32 - 1. The same goes for `TIME_OF_DAY`, which is a `UInt32`.
//! - **`datatype` may be absent** on a command's metric (hosts often send only the alias
//!   and the value); when present it must be the port's datatype exactly.
//!
//! Everything else is strict: the value must be in the datatype's field, an array must
//! have exactly the port's `n` elements and exactly the bytes they take (a
//! `BooleanArray`'s padding bits are ignored, as Tahu and pysparkplug do), strings must be
//! valid UTF-8, and the value must pass [`Value::check`] for the port's type (ranges,
//! `STRING` at most 65,535 bytes, `WSTRING` at most 65,535 UTF-16 units, no NUL, finite
//! reals, a `DATE` at midnight, a `TIME_OF_DAY` below 24 h). A null metric (`is_null`, no
//! value) is an error: a port always holds a value. [`value_of`] never panics, whatever
//! the metric (fuzzed by `broker/fuzz` target `sparkplug_metric`, from payloads fbbus,
//! pysparkplug 0.6.1 and Tahu JS 1.0.3 wrote).

pub mod proto;
#[cfg(test)]
mod tests;

use crate::types::{DataType, ElementaryType};
use crate::value::{TypeError, Value};

use proto::payload::metric::Value as MetricValue;
use proto::payload::Metric;
use proto::DataType as SpType;

/// The first level of every Sparkplug B topic (`spBv1.0/<group>/<type>/<node>[/<device>]`).
pub const NAMESPACE: &str = "spBv1.0";

/// Why a metric is not a value of a port's type. Each message names what was expected.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum MetricError {
    /// The metric's `datatype` is not the port type's Sparkplug datatype.
    #[error("datatype {got}, expected {expected} for {ty}")]
    Datatype {
        ty: DataType,
        expected: &'static str,
        got: String,
    },
    /// No value: a null metric, or none of the `oneof` fields set.
    #[error("no value (a null metric), expected {expected} for {ty}")]
    Null {
        ty: DataType,
        expected: &'static str,
    },
    /// The value is in another field of the `oneof` than the datatype's.
    #[error("value in {got}, expected {expected} for {ty}")]
    Field {
        ty: DataType,
        expected: &'static str,
        got: &'static str,
    },
    /// An integer outside the IEC type's range.
    #[error("value out of range for {ty}: {value}")]
    OutOfRange { ty: ElementaryType, value: u64 },
    /// An array with another number of elements than the port's `n`.
    #[error("array of {got} elements, {ty} expects {expected}")]
    ArrayLength {
        ty: DataType,
        expected: usize,
        got: usize,
    },
    /// `bytes_value` of a length no array of the datatype has.
    #[error("{datatype} of {len} bytes: {why}, for {ty}")]
    ArrayBytes {
        ty: DataType,
        datatype: &'static str,
        len: usize,
        why: String,
    },
    /// A `StringArray` element that is not UTF-8.
    #[error("StringArray element {index} is not valid UTF-8, for {ty}")]
    Utf8 { ty: DataType, index: usize },
    /// Decoded, but not a valid value of the type ([`Value::check`]).
    #[error("not a valid {ty}: {error}")]
    Invalid { ty: DataType, error: TypeError },
}

/// The Sparkplug scalar datatype of an elementary type (the table in the module doc).
fn scalar_datatype(t: ElementaryType) -> SpType {
    use ElementaryType as T;
    match t {
        T::Bool => SpType::Boolean,
        T::Sint => SpType::Int8,
        T::Int => SpType::Int16,
        T::Dint => SpType::Int32,
        T::Lint | T::Time => SpType::Int64,
        T::Usint | T::Byte => SpType::UInt8,
        T::Uint | T::Word => SpType::UInt16,
        T::Udint | T::Dword | T::TimeOfDay => SpType::UInt32,
        T::Ulint | T::Lword => SpType::UInt64,
        T::Real => SpType::Float,
        T::Lreal => SpType::Double,
        T::String | T::WString => SpType::String,
        T::Date | T::DateAndTime => SpType::DateTime,
    }
}

/// The Sparkplug 3.0 array datatype whose elements are `scalar`s.
fn array_datatype(scalar: SpType) -> SpType {
    match scalar {
        SpType::Int8 => SpType::Int8Array,
        SpType::Int16 => SpType::Int16Array,
        SpType::Int32 => SpType::Int32Array,
        SpType::Int64 => SpType::Int64Array,
        SpType::UInt8 => SpType::UInt8Array,
        SpType::UInt16 => SpType::UInt16Array,
        SpType::UInt32 => SpType::UInt32Array,
        SpType::UInt64 => SpType::UInt64Array,
        SpType::Float => SpType::FloatArray,
        SpType::Double => SpType::DoubleArray,
        SpType::Boolean => SpType::BooleanArray,
        SpType::String => SpType::StringArray,
        SpType::DateTime => SpType::DateTimeArray,
        // `scalar_datatype` gives none of the others.
        other => other,
    }
}

/// The Sparkplug datatype of a port type: the table in the [module doc](self). Store it in
/// a metric's `datatype` as `datatype(ty) as u32`.
pub fn datatype(ty: DataType) -> SpType {
    match ty {
        DataType::Elementary(t) => scalar_datatype(t),
        DataType::Array(t, _) => array_datatype(scalar_datatype(t)),
    }
}

/// The metric value of `value`, in the field and form of the [module doc](self)'s table.
///
/// `value` should be a checked value ([`Value::check`]); for one that is not (a
/// `TIME_OF_DAY` past 2^32 ms, an array whose elements are not all of its element type),
/// the result is unspecified, but this never panics.
pub fn metric_value(value: &Value) -> MetricValue {
    match value {
        Value::Bool(b) => MetricValue::BooleanValue(*b),
        // Sign-extended to 32 bits, as Tahu Java writes them (module doc).
        Value::Sint(v) => MetricValue::IntValue(i32::from(*v) as u32),
        Value::Int(v) => MetricValue::IntValue(i32::from(*v) as u32),
        Value::Dint(v) => MetricValue::IntValue(*v as u32),
        Value::Lint(v) | Value::Time(v) => MetricValue::LongValue(*v as u64),
        Value::Usint(v) | Value::Byte(v) => MetricValue::IntValue(u32::from(*v)),
        Value::Uint(v) | Value::Word(v) => MetricValue::IntValue(u32::from(*v)),
        // `long_value`, as Tahu writes it (module doc).
        Value::Udint(v) | Value::Dword(v) => MetricValue::LongValue(u64::from(*v)),
        Value::TimeOfDay(ms) => {
            MetricValue::LongValue(u64::from(u32::try_from(*ms).unwrap_or(u32::MAX)))
        }
        Value::Ulint(v) | Value::Lword(v) | Value::Date(v) | Value::DateAndTime(v) => {
            MetricValue::LongValue(*v)
        }
        Value::Real(x) => MetricValue::FloatValue(*x),
        Value::Lreal(x) => MetricValue::DoubleValue(*x),
        Value::String(s) | Value::WString(s) => MetricValue::StringValue(s.clone()),
        Value::Array(t, items) => MetricValue::BytesValue(array_bytes(*t, items)),
    }
}

/// A metric carrying `value`: its `datatype` ([`datatype`] of the value's type) and value
/// ([`metric_value`]), with the given name (births), alias and timestamp (ms since the
/// epoch); every other field unset.
pub fn metric(
    name: Option<String>,
    alias: Option<u64>,
    timestamp_ms: Option<u64>,
    value: &Value,
) -> Metric {
    Metric {
        name,
        alias,
        timestamp: timestamp_ms,
        datatype: Some(datatype(value.data_type()) as u32),
        value: Some(metric_value(value)),
        ..Default::default()
    }
}

/// The value a metric written by a Sparkplug host (a command) holds for a port of type
/// `ty`: `datatype` and `value` are the metric's fields of those names.
///
/// The datatype, when present, must be [`datatype`]`(ty)`; the value must be in that
/// datatype's field, of that datatype's form, and a valid value of `ty`. What is accepted
/// beyond the form fbbus writes (sign-extended or width-limited `Int8`/`Int16`, `UInt32`
/// in `long_value`) is listed in the [module doc](self). Never panics.
pub fn value_of(
    ty: DataType,
    datatype: Option<u32>,
    value: Option<&MetricValue>,
) -> Result<Value, MetricError> {
    let expected = self::datatype(ty);
    if let Some(got) = datatype {
        if got != expected as u32 {
            return Err(MetricError::Datatype {
                ty,
                expected: expected.as_str_name(),
                got: datatype_name(got),
            });
        }
    }
    let Some(value) = value else {
        return Err(MetricError::Null {
            ty,
            expected: expected.as_str_name(),
        });
    };
    let decoded = match ty {
        DataType::Elementary(t) => scalar(ty, t, value)?,
        DataType::Array(t, n) => {
            let MetricValue::BytesValue(bytes) = value else {
                return Err(wrong_field(ty, "bytes_value", value));
            };
            let items = array(ty, t, usize::from(n), bytes)?;
            Value::Array(t, items)
        }
    };
    decoded
        .check(ty)
        .map_err(|error| MetricError::Invalid { ty, error })?;
    Ok(decoded)
}

/// [`value_of`] for a whole metric, which also refuses one marked `is_null` whatever its
/// value field says.
pub fn value_of_metric(ty: DataType, metric: &Metric) -> Result<Value, MetricError> {
    if metric.is_null == Some(true) {
        return Err(MetricError::Null {
            ty,
            expected: datatype(ty).as_str_name(),
        });
    }
    value_of(ty, metric.datatype, metric.value.as_ref())
}

/// A datatype number as the proto names it, or as a number if it names none.
fn datatype_name(n: u32) -> String {
    i32::try_from(n)
        .ok()
        .and_then(|n| SpType::try_from(n).ok())
        .map_or_else(
            || format!("{n} (no such datatype)"),
            |d| d.as_str_name().to_owned(),
        )
}

/// The proto name of the field a metric value is in.
fn field_name(value: &MetricValue) -> &'static str {
    match value {
        MetricValue::IntValue(_) => "int_value",
        MetricValue::LongValue(_) => "long_value",
        MetricValue::FloatValue(_) => "float_value",
        MetricValue::DoubleValue(_) => "double_value",
        MetricValue::BooleanValue(_) => "boolean_value",
        MetricValue::StringValue(_) => "string_value",
        MetricValue::BytesValue(_) => "bytes_value",
        MetricValue::DatasetValue(_) => "dataset_value",
        MetricValue::TemplateValue(_) => "template_value",
        MetricValue::ExtensionValue(_) => "extension_value",
    }
}

fn wrong_field(ty: DataType, expected: &'static str, value: &MetricValue) -> MetricError {
    MetricError::Field {
        ty,
        expected,
        got: field_name(value),
    }
}

/// An `int_value` of a signed datatype `bits` wide, in either form hosts write (module
/// doc): sign-extended to 32 bits, or the two's complement of `bits` bits.
fn signed_int(raw: u32, bits: u32) -> Option<i32> {
    let as_i32 = raw as i32;
    let max = (1i64 << (bits - 1)) - 1;
    let min = -(1i64 << (bits - 1));
    if (min..=max).contains(&i64::from(as_i32)) {
        Some(as_i32)
    } else if bits < 32 && raw < (1u32 << bits) {
        // Shift the width's sign bit up to bit 31 and back: sign extension.
        Some(((raw << (32 - bits)) as i32) >> (32 - bits))
    } else {
        None
    }
}

/// A scalar metric value as the elementary type `t` (`ty` is `t`, for errors).
fn scalar(ty: DataType, t: ElementaryType, value: &MetricValue) -> Result<Value, MetricError> {
    use ElementaryType as T;
    use MetricValue as M;
    let out_of_range = |value: u64| MetricError::OutOfRange { ty: t, value };
    let expected_field = match scalar_datatype(t) {
        SpType::Int64 | SpType::UInt64 | SpType::DateTime => "long_value",
        SpType::UInt32 => "int_value or long_value",
        SpType::Float => "float_value",
        SpType::Double => "double_value",
        SpType::Boolean => "boolean_value",
        SpType::String => "string_value",
        _ => "int_value",
    };
    // `UInt32` either way (module doc): `int_value`, or a `long_value` that fits.
    let uint32 = |value: &MetricValue| match value {
        M::IntValue(v) => Ok(Some(*v)),
        M::LongValue(v) => u32::try_from(*v).map(Some).map_err(|_| out_of_range(*v)),
        _ => Ok(None),
    };
    let decoded = match (t, value) {
        (T::Bool, M::BooleanValue(b)) => Some(Value::Bool(*b)),
        (T::Sint, M::IntValue(v)) => Some(Value::Sint(
            signed_int(*v, 8)
                .and_then(|v| i8::try_from(v).ok())
                .ok_or_else(|| out_of_range(u64::from(*v)))?,
        )),
        (T::Int, M::IntValue(v)) => Some(Value::Int(
            signed_int(*v, 16)
                .and_then(|v| i16::try_from(v).ok())
                .ok_or_else(|| out_of_range(u64::from(*v)))?,
        )),
        (T::Dint, M::IntValue(v)) => Some(Value::Dint(*v as i32)),
        (T::Lint, M::LongValue(v)) => Some(Value::Lint(*v as i64)),
        (T::Time, M::LongValue(v)) => Some(Value::Time(*v as i64)),
        (T::Usint | T::Byte, M::IntValue(v)) => {
            let v = u8::try_from(*v).map_err(|_| out_of_range(u64::from(*v)))?;
            Some(if t == T::Usint {
                Value::Usint(v)
            } else {
                Value::Byte(v)
            })
        }
        (T::Uint | T::Word, M::IntValue(v)) => {
            let v = u16::try_from(*v).map_err(|_| out_of_range(u64::from(*v)))?;
            Some(if t == T::Uint {
                Value::Uint(v)
            } else {
                Value::Word(v)
            })
        }
        (T::Udint, v) => uint32(v)?.map(Value::Udint),
        (T::Dword, v) => uint32(v)?.map(Value::Dword),
        (T::TimeOfDay, v) => uint32(v)?.map(|ms| Value::TimeOfDay(u64::from(ms))),
        (T::Ulint, M::LongValue(v)) => Some(Value::Ulint(*v)),
        (T::Lword, M::LongValue(v)) => Some(Value::Lword(*v)),
        (T::Date, M::LongValue(v)) => Some(Value::Date(*v)),
        (T::DateAndTime, M::LongValue(v)) => Some(Value::DateAndTime(*v)),
        (T::Real, M::FloatValue(x)) => Some(Value::Real(*x)),
        (T::Lreal, M::DoubleValue(x)) => Some(Value::Lreal(*x)),
        (T::String, M::StringValue(s)) => Some(Value::String(s.clone())),
        (T::WString, M::StringValue(s)) => Some(Value::WString(s.clone())),
        _ => None,
    };
    decoded.ok_or_else(|| wrong_field(ty, expected_field, value))
}

/// Bytes per element of a fixed-width array of `t` (`None`: BOOL and the strings).
fn element_width(t: ElementaryType) -> Option<usize> {
    match scalar_datatype(t) {
        SpType::Int8 | SpType::UInt8 => Some(1),
        SpType::Int16 | SpType::UInt16 => Some(2),
        SpType::Int32 | SpType::UInt32 | SpType::Float => Some(4),
        SpType::Int64 | SpType::UInt64 | SpType::Double | SpType::DateTime => Some(8),
        _ => None,
    }
}

/// `bytes_value` for `ARRAY OF t` (module doc).
fn array_bytes(t: ElementaryType, items: &[Value]) -> Vec<u8> {
    let mut out = Vec::new();
    match t {
        ElementaryType::Bool => {
            let count = u32::try_from(items.len()).unwrap_or(u32::MAX);
            out.extend_from_slice(&count.to_le_bytes());
            for byte in items.chunks(8) {
                let mut packed = 0u8;
                for (bit, item) in byte.iter().enumerate() {
                    if matches!(item, Value::Bool(true)) {
                        packed |= 0x80 >> bit;
                    }
                }
                out.push(packed);
            }
        }
        ElementaryType::String | ElementaryType::WString => {
            for item in items {
                if let Value::String(s) | Value::WString(s) = item {
                    out.extend_from_slice(s.as_bytes());
                }
                out.push(0);
            }
        }
        _ => {
            let width = element_width(t).unwrap_or(8);
            out.reserve(width * items.len());
            for item in items {
                let bits = element_bits(item).to_le_bytes();
                out.extend_from_slice(&bits[..width]);
            }
        }
    }
    out
}

/// A fixed-width element's bits, little-endian in the low bytes of a `u64` (its width's
/// two's complement for a signed integer, IEEE 754 for the reals).
fn element_bits(item: &Value) -> u64 {
    match item {
        Value::Bool(b) => u64::from(*b),
        Value::Sint(v) => u64::from(*v as u8),
        Value::Int(v) => u64::from(*v as u16),
        Value::Dint(v) => u64::from(*v as u32),
        Value::Lint(v) | Value::Time(v) => *v as u64,
        Value::Usint(v) | Value::Byte(v) => u64::from(*v),
        Value::Uint(v) | Value::Word(v) => u64::from(*v),
        Value::Udint(v) | Value::Dword(v) => u64::from(*v),
        // A `UInt32Array` element: saturated, as in `metric_value`.
        Value::TimeOfDay(ms) => u64::from(u32::try_from(*ms).unwrap_or(u32::MAX)),
        Value::Ulint(v) | Value::Lword(v) | Value::Date(v) | Value::DateAndTime(v) => *v,
        Value::Real(x) => u64::from(x.to_bits()),
        Value::Lreal(x) => x.to_bits(),
        Value::String(_) | Value::WString(_) | Value::Array(..) => 0,
    }
}

/// The `n` elements of `ARRAY [n] OF t` in `bytes` (`ty` is the array type, for errors).
fn array(
    ty: DataType,
    t: ElementaryType,
    n: usize,
    bytes: &[u8],
) -> Result<Vec<Value>, MetricError> {
    let sp = datatype(ty).as_str_name();
    let bad_bytes = |why: String| MetricError::ArrayBytes {
        ty,
        datatype: sp,
        len: bytes.len(),
        why,
    };
    let wrong_length = |got: usize| MetricError::ArrayLength {
        ty,
        expected: n,
        got,
    };
    match t {
        ElementaryType::Bool => {
            let Some((count, bits)) = bytes.split_first_chunk::<4>() else {
                return Err(bad_bytes("shorter than its 4-byte element count".into()));
            };
            let count = u32::from_le_bytes(*count);
            let count = usize::try_from(count).unwrap_or(usize::MAX);
            if count != n {
                return Err(wrong_length(count));
            }
            let expected = n.div_ceil(8);
            if bits.len() != expected {
                return Err(bad_bytes(format!("{n} elements take 4 + {expected} bytes")));
            }
            // Padding bits past the last element are ignored, as Tahu and pysparkplug do.
            Ok((0..n)
                .map(|i| Value::Bool(bits[i / 8] & (0x80 >> (i % 8)) != 0))
                .collect())
        }
        ElementaryType::String | ElementaryType::WString => {
            let strings: Vec<&[u8]> = match bytes.split_last() {
                None => Vec::new(),
                Some((0, body)) => body.split(|b| *b == 0).collect(),
                Some(_) => return Err(bad_bytes("the last string is not NUL-terminated".into())),
            };
            if strings.len() != n {
                return Err(wrong_length(strings.len()));
            }
            strings
                .into_iter()
                .enumerate()
                .map(|(index, s)| {
                    let s = std::str::from_utf8(s).map_err(|_| MetricError::Utf8 { ty, index })?;
                    Ok(if t == ElementaryType::String {
                        Value::String(s.to_owned())
                    } else {
                        Value::WString(s.to_owned())
                    })
                })
                .collect()
        }
        _ => {
            let Some(width) = element_width(t) else {
                // Every other elementary type has a width (`element_width`).
                return Err(bad_bytes("no array encoding".into()));
            };
            if !bytes.len().is_multiple_of(width) {
                return Err(bad_bytes(format!(
                    "not a whole number of {width}-byte elements"
                )));
            }
            if bytes.len() / width != n {
                return Err(wrong_length(bytes.len() / width));
            }
            Ok(bytes
                .chunks_exact(width)
                .map(|chunk| {
                    let mut le = [0u8; 8];
                    le[..width].copy_from_slice(chunk);
                    element(t, u64::from_le_bytes(le))
                })
                .collect())
        }
    }
}

/// A fixed-width array element of type `t` from its `width` bytes, little-endian, in the
/// low bytes of `bits` (the inverse of [`element_bits`]).
fn element(t: ElementaryType, bits: u64) -> Value {
    use ElementaryType as T;
    match t {
        T::Sint => Value::Sint(bits as u8 as i8),
        T::Int => Value::Int(bits as u16 as i16),
        T::Dint => Value::Dint(bits as u32 as i32),
        T::Lint => Value::Lint(bits as i64),
        T::Time => Value::Time(bits as i64),
        T::Usint => Value::Usint(bits as u8),
        T::Byte => Value::Byte(bits as u8),
        T::Uint => Value::Uint(bits as u16),
        T::Word => Value::Word(bits as u16),
        T::Udint => Value::Udint(bits as u32),
        T::Dword => Value::Dword(bits as u32),
        T::TimeOfDay => Value::TimeOfDay(bits & 0xFFFF_FFFF),
        T::Ulint => Value::Ulint(bits),
        T::Lword => Value::Lword(bits),
        T::Date => Value::Date(bits),
        T::DateAndTime => Value::DateAndTime(bits),
        T::Real => Value::Real(f32::from_bits(bits as u32)),
        T::Lreal => Value::Lreal(f64::from_bits(bits)),
        // Not fixed-width (`array` decodes them itself).
        T::Bool => Value::Bool(bits != 0),
        T::String => Value::String(String::new()),
        T::WString => Value::WString(String::new()),
    }
}

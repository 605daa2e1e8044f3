//! Canonical JSON: fbbus's own wire format, on topics `fb/<device>/<fb>/<port>`.
//!
//! A **data port** carries its bare value: `42`, `true`, `"T#1s"`, `[1,2,3]`.
//!
//! An **event port** carries an object with the event's WITH data, atomically:
//!
//! ```json
//! {"seq": 17, "ts": 1763797200123456, "data": {"POSITION": 3, "SENSOR_IN": true}}
//! ```
//!
//! - `seq` (unsigned integer) counts the occurrences of this event; optional on input.
//! - `ts` (unsigned integer) is when the event occurred, in microseconds since
//!   1970-01-01 UTC; optional on input. The broker stamps both before delivery.
//! - `data` holds exactly the WITH data ports, each by name. It may be left out when the
//!   WITH list is empty. A missing WITH port, an undeclared key in `data` and any
//!   top-level key other than these three are refused.
//!
//! Decoding is strict so that a device learns about a mistake the first time it makes
//! it, rather than having a value silently converted. Each value is written as follows:
//!
//! | type | JSON | examples |
//! |---|---|---|
//! | `BOOL` | `true` / `false` only (not `0`/`1`) | `true` |
//! | `SINT` `INT` `DINT` `LINT` `USINT` `UINT` `UDINT` `ULINT` | an integer within the type's range; `3.0`, `1e3` are refused | `-128`, `18446744073709551615` |
//! | `BYTE` `WORD` `DWORD` `LWORD` | an integer within range, or a string with an IEC base-2/8/16 literal (accepted on input, never written) | `255`, `"16#FF"`, `"2#1010"`, `"8#17"`, `"16#FFFF_FFFF"` |
//! | `REAL` | a number that rounds to a finite 32-bit float (integers too) | `0.1`, `3.4028235e38` |
//! | `LREAL` | a number (JSON has no NaN or infinity) | `-1.5`, `1e300` |
//! | `STRING` `WSTRING` | a string (at most 65,535 bytes or UTF-16 units) | `"Grüße"` |
//! | `TIME` | an IEC literal `T#`/`TIME#`, units `d h m s ms us ns` from largest to smallest, `_` between digits or units, a fraction on the last unit; or an integer number of microseconds (input only) | `"T#1h2m3s4ms5us"`, `"T#-250ms"`, `"TIME#1.5s"`, `"t#1h_30m"`, `1500000` |
//! | `DATE` | `D#`/`DATE#YYYY-MM-DD`, years 1970 to 9999 | `"D#2026-11-22"` |
//! | `TIME_OF_DAY` | `TOD#`/`TIME_OF_DAY#HH:MM:SS`, optionally `.f` to `.fff` (milliseconds) | `"TOD#12:30:15.250"` |
//! | `DATE_AND_TIME` | `DT#`/`DATE_AND_TIME#YYYY-MM-DD-HH:MM:SS[.fff]`, UTC | `"DT#2026-11-22-12:30:15.250"` |
//! | `ARRAY [n] OF t` | an array of exactly `n` elements, each as `t` | `[1, 2, 3]` |
//!
//! Prefixes, units and hex digits may be upper or lower case. Durations in `ns` must add
//! up to whole microseconds (TIME's unit). fbbus always writes the canonical form: plain
//! integers for bit strings, `T#` with the non-zero units from days down (`T#0s` for
//! zero), `D#YYYY-MM-DD`, `TOD#HH:MM:SS` and `DT#YYYY-MM-DD-HH:MM:SS` with `.mmm` only
//! when the milliseconds are not zero, and the shortest decimal that reads back as the
//! same `REAL`/`LREAL`.

mod de;
/// The tree-building reference the streaming decoder is checked against (tests, fuzzing).
#[cfg(any(test, feature = "reference-decoder"))]
#[doc(hidden)]
pub mod tree;

use serde::{Serialize, Serializer};
use serde_json::{Map, Number, Value as Json};

use super::{CodecError, EventMessage, Message};
use crate::interface::OutputPort;
use crate::types::{DataType, ElementaryType};
use crate::value::{TypeError, Value, MS_PER_DAY};

/// Decodes a canonical JSON payload published on `port`.
///
/// An ill-typed data port value is reported as [`CodecError::Type`] with an empty `port`,
/// since this signature does not know the port's name; [`decode_named`] fills it in.
pub fn decode(payload: &[u8], port: &OutputPort<'_>) -> Result<Message, CodecError> {
    decode_named(payload, "", port)
}

/// [`decode`], naming a data port `port_name` in [`CodecError::Type`].
///
/// Reads the payload in one pass, straight into typed values (see the `de` submodule),
/// with the results of parsing it into a `serde_json::Value` and reading that with
/// [`value_from_json`].
pub fn decode_named(
    payload: &[u8],
    port_name: &str,
    port: &OutputPort<'_>,
) -> Result<Message, CodecError> {
    match port {
        OutputPort::Data(ty) => de::parse_value(payload, de::Typed(*ty))?
            .map(Message::Data)
            .map_err(|error| CodecError::Type {
                port: port_name.to_owned(),
                error,
            }),
        OutputPort::Event(with) => {
            de::parse_object(payload, de::Any(de::Event(with)))?.map(Message::Event)
        }
    }
}

/// Encodes a message for `port` in canonical JSON.
///
/// An event's `data` keys are written in WITH order. `port` only supplies those names; a
/// message that does not fit its port (which [`decode`] never returns) is written as far
/// as the names go rather than panicking.
pub fn encode(message: &Message, port: &OutputPort<'_>) -> Vec<u8> {
    let mut out = Vec::with_capacity(128);
    match message {
        Message::Data(value) => write_json(&mut out, &Canonical(value)),
        Message::Event(event) => encode_event(&mut out, event, port),
    }
    out
}

/// A value in its canonical JSON form (the table in this module's documentation).
///
/// A non-finite `REAL`/`LREAL`, which [`Value::check`] refuses, becomes `null`.
pub fn value_to_json(v: &Value) -> Json {
    match v {
        Value::Bool(b) => Json::Bool(*b),
        Value::Sint(n) => (*n).into(),
        Value::Int(n) => (*n).into(),
        Value::Dint(n) => (*n).into(),
        Value::Lint(n) => (*n).into(),
        Value::Usint(n) | Value::Byte(n) => (*n).into(),
        Value::Uint(n) | Value::Word(n) => (*n).into(),
        Value::Udint(n) | Value::Dword(n) => (*n).into(),
        Value::Ulint(n) | Value::Lword(n) => (*n).into(),
        Value::Real(x) => real_to_json(*x),
        Value::Lreal(x) => Number::from_f64(*x).map_or(Json::Null, Json::Number),
        Value::String(s) | Value::WString(s) => Json::String(s.clone()),
        Value::Time(us) => Json::String(iec::format_time(*us)),
        Value::Date(ms) => Json::String(format!("D#{}", iec::format_date(*ms / MS_PER_DAY))),
        Value::TimeOfDay(ms) => Json::String(format!("TOD#{}", iec::format_tod(*ms))),
        Value::DateAndTime(ms) => Json::String(format!(
            "DT#{}-{}",
            iec::format_date(*ms / MS_PER_DAY),
            iec::format_tod(*ms % MS_PER_DAY)
        )),
        Value::Array(_, items) => Json::Array(items.iter().map(value_to_json).collect()),
    }
}

/// Reads a value of type `ty` from its JSON form (the table in this module's
/// documentation), then checks it with [`Value::check`].
pub fn value_from_json(j: &Json, ty: DataType) -> Result<Value, TypeError> {
    let value = match ty {
        DataType::Elementary(t) => scalar_from_token(Token::of(j), t)?,
        DataType::Array(t, n) => array_from_json(j, t, n)?,
    };
    value.check(ty)?;
    Ok(value)
}

/// Reads a payload that is a JSON object of exactly the named, typed `fields`, in their
/// order: every DINASORE payload. A payload that is JSON but not an object is refused
/// with `not_object(its description)`.
///
/// Structural mistakes are reported before value mistakes: a missing field first (in
/// field order), then a key that is not a field, then the first ill-typed value.
pub(super) fn decode_object(
    payload: &[u8],
    fields: &[(&str, DataType)],
    not_object: impl FnOnce(&str) -> CodecError,
) -> Result<Vec<Value>, CodecError> {
    de::parse_object(payload, de::Any(de::Fields(fields)))?.map_err(not_object)?
}

/// Reads exactly the named, typed `fields` from a JSON object, in their order: what
/// `de` does for an object whose fields do not all have distinct names.
///
/// Structural mistakes are reported before value mistakes: a missing field first (in
/// field order), then a key that is not a field, then the first ill-typed value.
fn object_fields(
    object: &Map<String, Json>,
    fields: &[(&str, DataType)],
) -> Result<Vec<Value>, CodecError> {
    if let Some((name, _)) = fields.iter().find(|(name, _)| !object.contains_key(*name)) {
        return Err(CodecError::Missing((*name).to_owned()));
    }
    if let Some(key) = object
        .keys()
        .find(|key| !fields.iter().any(|(name, _)| name == key))
    {
        return Err(CodecError::Unexpected(key.clone()));
    }
    fields
        .iter()
        .map(|(name, ty)| {
            let value = object.get(*name).unwrap_or(&Json::Null);
            value_from_json(value, *ty).map_err(|error| CodecError::Type {
                port: (*name).to_owned(),
                error,
            })
        })
        .collect()
}

/// Writes a JSON object with its keys in the given order (`serde_json`'s map would sort
/// them), each value in its canonical form.
pub(super) fn write_object<'a>(
    out: &mut Vec<u8>,
    fields: impl IntoIterator<Item = (&'a str, &'a Value)>,
) {
    out.push(b'{');
    for (i, (name, value)) in fields.into_iter().enumerate() {
        if i > 0 {
            out.push(b',');
        }
        write_json(out, name);
        out.push(b':');
        write_json(out, &Canonical(value));
    }
    out.push(b'}');
}

/// The WITH names of an event port, in order; none for a data port.
pub(super) fn with_names<'p>(port: &'p OutputPort<'_>) -> impl Iterator<Item = &'p str> {
    let with: &'p [(&'p str, DataType)] = match port {
        OutputPort::Event(with) => with,
        OutputPort::Data(_) => &[],
    };
    with.iter().map(|(name, _)| *name)
}

fn encode_event(out: &mut Vec<u8>, event: &EventMessage, port: &OutputPort<'_>) {
    out.push(b'{');
    for (key, stamp) in [(&b"\"seq\":"[..], event.seq), (b"\"ts\":", event.ts_us)] {
        if let Some(n) = stamp {
            out.extend_from_slice(key);
            write_json(out, &n);
            out.push(b',');
        }
    }
    out.extend_from_slice(b"\"data\":");
    write_object(out, with_names(port).zip(&event.data));
    out.push(b'}');
}

/// Appends `value` as compact JSON.
fn write_json(out: &mut Vec<u8>, value: &(impl Serialize + ?Sized)) {
    // Writing to a Vec cannot fail, and neither can serializing strings, numbers or
    // `Canonical`.
    let _ = serde_json::to_writer(out, value);
}

/// A value serialized in its canonical JSON form: the text of [`value_to_json`]'s tree,
/// written without building the tree.
struct Canonical<'a>(&'a Value);

impl Serialize for Canonical<'_> {
    fn serialize<S: Serializer>(&self, s: S) -> Result<S::Ok, S::Error> {
        match self.0 {
            Value::Bool(b) => s.serialize_bool(*b),
            Value::Sint(n) => s.serialize_i8(*n),
            Value::Int(n) => s.serialize_i16(*n),
            Value::Dint(n) => s.serialize_i32(*n),
            Value::Lint(n) => s.serialize_i64(*n),
            Value::Usint(n) | Value::Byte(n) => s.serialize_u8(*n),
            Value::Uint(n) | Value::Word(n) => s.serialize_u16(*n),
            Value::Udint(n) | Value::Dword(n) => s.serialize_u32(*n),
            Value::Ulint(n) | Value::Lword(n) => s.serialize_u64(*n),
            // `serde_json` writes a non-finite number as `null`.
            Value::Real(x) => s.serialize_f64(shortest_f64(*x)),
            Value::Lreal(x) => s.serialize_f64(*x),
            Value::String(text) | Value::WString(text) => s.serialize_str(text),
            Value::Time(us) => s.serialize_str(&iec::format_time(*us)),
            Value::Date(ms) => {
                s.collect_str(&format_args!("D#{}", iec::format_date(*ms / MS_PER_DAY)))
            }
            Value::TimeOfDay(ms) => s.collect_str(&format_args!("TOD#{}", iec::format_tod(*ms))),
            Value::DateAndTime(ms) => s.collect_str(&format_args!(
                "DT#{}-{}",
                iec::format_date(*ms / MS_PER_DAY),
                iec::format_tod(*ms % MS_PER_DAY)
            )),
            Value::Array(_, items) => s.collect_seq(items.iter().map(Canonical)),
        }
    }
}

/// A `REAL` as the shortest decimal that reads back as the same `f32` (`0.1`, not the
/// `0.10000000149011612` its widening to `f64` would print).
fn shortest_f64(x: f32) -> f64 {
    x.to_string().parse::<f64>().unwrap_or(f64::from(x))
}

fn real_to_json(x: f32) -> Json {
    Number::from_f64(shortest_f64(x)).map_or(Json::Null, Json::Number)
}

/// One JSON value as the value readers see it: a scalar with its content, an array or
/// an object by kind only. Both decoders, the tree ([`value_from_json`]) and the stream
/// (`de`), hand values over as tokens, so they read them identically.
#[derive(Debug, Clone, Copy)]
enum Token<'a> {
    Null,
    Bool(bool),
    /// An integer that `serde_json` read exactly: it fits `i64` or `u64`.
    Int(i128),
    /// Any other number: it has a fraction or an exponent, or is an integer beyond 64
    /// bits.
    Float(f64),
    Str(&'a str),
    Array,
    Object,
}

impl<'a> Token<'a> {
    fn of(j: &'a Json) -> Token<'a> {
        match j {
            Json::Null => Token::Null,
            Json::Bool(b) => Token::Bool(*b),
            Json::Number(n) => match (n.as_i64(), n.as_u64()) {
                (Some(i), _) => Token::Int(i.into()),
                (None, Some(u)) => Token::Int(u.into()),
                (None, None) => Token::Float(n.as_f64().unwrap_or(f64::NAN)),
            },
            Json::String(s) => Token::Str(s),
            Json::Array(_) => Token::Array,
            Json::Object(_) => Token::Object,
        }
    }

    /// What kind of JSON value this is, for error messages ("expected INT, got a JSON
    /// string").
    fn describe(self) -> &'static str {
        match self {
            Token::Null => "null",
            Token::Bool(_) => "a JSON boolean",
            Token::Int(_) => "a JSON integer",
            Token::Float(x) if x.fract() != 0.0 => "a JSON number with a fraction",
            Token::Float(_) => "a JSON number with a fraction or exponent",
            Token::Str(_) => "a JSON string",
            Token::Array => "a JSON array",
            Token::Object => "a JSON object",
        }
    }

    /// A number as `serde_json` writes it.
    fn number_text(self) -> String {
        match self {
            Token::Int(n) => n.to_string(),
            Token::Float(x) => Json::from(x).to_string(),
            other => other.describe().to_owned(),
        }
    }
}

fn mismatch(token: Token<'_>, expected: DataType) -> TypeError {
    TypeError::Mismatch {
        expected,
        got: token.describe().to_owned(),
    }
}

fn scalar_mismatch(token: Token<'_>, t: ElementaryType) -> TypeError {
    mismatch(token, DataType::Elementary(t))
}

fn array_from_json(j: &Json, t: ElementaryType, n: u16) -> Result<Value, TypeError> {
    let Some(items) = j.as_array() else {
        return Err(mismatch(Token::of(j), DataType::Array(t, n)));
    };
    if items.len() != usize::from(n) {
        return Err(TypeError::ArrayLength {
            expected: usize::from(n),
            got: items.len(),
        });
    }
    let elements = items
        .iter()
        .enumerate()
        .map(|(index, item)| {
            scalar_from_token(Token::of(item), t).map_err(|error| TypeError::Element {
                index,
                error: Box::new(error),
            })
        })
        .collect::<Result<Vec<_>, _>>()?;
    Ok(Value::Array(t, elements))
}

/// Reads an elementary value of type `t` (not yet [checked](Value::check)).
fn scalar_from_token(token: Token<'_>, t: ElementaryType) -> Result<Value, TypeError> {
    use ElementaryType as T;
    Ok(match t {
        T::Bool => match token {
            Token::Bool(b) => Value::Bool(b),
            _ => return Err(scalar_mismatch(token, t)),
        },
        T::Sint => Value::Sint(fit(integer(token, t)?, t)?),
        T::Int => Value::Int(fit(integer(token, t)?, t)?),
        T::Dint => Value::Dint(fit(integer(token, t)?, t)?),
        T::Lint => Value::Lint(fit(integer(token, t)?, t)?),
        T::Usint => Value::Usint(fit(integer(token, t)?, t)?),
        T::Uint => Value::Uint(fit(integer(token, t)?, t)?),
        T::Udint => Value::Udint(fit(integer(token, t)?, t)?),
        T::Ulint => Value::Ulint(fit(integer(token, t)?, t)?),
        T::Byte => Value::Byte(fit(bit_string(token, t)?, t)?),
        T::Word => Value::Word(fit(bit_string(token, t)?, t)?),
        T::Dword => Value::Dword(fit(bit_string(token, t)?, t)?),
        T::Lword => Value::Lword(fit(bit_string(token, t)?, t)?),
        T::Real => Value::Real(real(token)?),
        T::Lreal => Value::Lreal(number(token, t)?),
        T::String => Value::String(string(token, t)?),
        T::WString => Value::WString(string(token, t)?),
        T::Time => Value::Time(time(token)?),
        T::Date => Value::Date(literal(token, t, iec::parse_date)?),
        T::TimeOfDay => Value::TimeOfDay(literal(token, t, iec::parse_tod)?),
        T::DateAndTime => Value::DateAndTime(literal(token, t, iec::parse_date_and_time)?),
    })
}

/// A JSON integer, exactly. `serde_json` keeps integers that fit `i64` or `u64` as such;
/// anything else it reads is an `f64`: a fraction, an exponent, or an integer too large
/// for 64 bits (that last one is out of range rather than of the wrong kind).
fn integer(token: Token<'_>, t: ElementaryType) -> Result<i128, TypeError> {
    match token {
        Token::Int(n) => Ok(n),
        Token::Float(x) => {
            // Integers just below i64::MIN round to exactly -2^63, so that counts as beyond.
            let beyond_64_bits = x <= -(2f64.powi(63)) || x >= 2f64.powi(64);
            if x.fract() == 0.0 && beyond_64_bits {
                return Err(TypeError::OutOfRange {
                    ty: t,
                    value: token.number_text(),
                });
            }
            Err(scalar_mismatch(token, t))
        }
        _ => Err(scalar_mismatch(token, t)),
    }
}

/// Narrows an integer to the Rust type of `t`'s values.
fn fit<N: TryFrom<i128>>(n: i128, t: ElementaryType) -> Result<N, TypeError> {
    N::try_from(n).map_err(|_| TypeError::OutOfRange {
        ty: t,
        value: n.to_string(),
    })
}

/// A bit string (`BYTE` .. `LWORD`): an integer, or an IEC literal such as `"16#FF"`.
fn bit_string(token: Token<'_>, t: ElementaryType) -> Result<i128, TypeError> {
    match token {
        Token::Str(s) => literal_str(s, t, iec::parse_bit_string),
        _ => integer(token, t),
    }
}

fn number(token: Token<'_>, t: ElementaryType) -> Result<f64, TypeError> {
    match token {
        // Rounds to nearest, as `serde_json::Number::as_f64` does.
        Token::Int(n) => Ok(n as f64),
        Token::Float(x) => Ok(x),
        _ => Err(scalar_mismatch(token, t)),
    }
}

/// A `REAL`: any number that rounds to a finite `f32`. Rounding rather than comparing
/// with `f32::MAX` accepts `3.4028235e38`, the shortest decimal for `f32::MAX`, which is
/// a little larger than it.
fn real(token: Token<'_>) -> Result<f32, TypeError> {
    let x = number(token, ElementaryType::Real)?;
    let narrowed = x as f32;
    if narrowed.is_finite() {
        Ok(narrowed)
    } else {
        Err(TypeError::OutOfRange {
            ty: ElementaryType::Real,
            value: token.number_text(),
        })
    }
}

fn string(token: Token<'_>, t: ElementaryType) -> Result<String, TypeError> {
    match token {
        Token::Str(s) => Ok(s.to_owned()),
        _ => Err(scalar_mismatch(token, t)),
    }
}

/// A `TIME`: an IEC literal, or an integer number of microseconds.
fn time(token: Token<'_>) -> Result<i64, TypeError> {
    let t = ElementaryType::Time;
    match token {
        Token::Str(s) => literal_str(s, t, iec::parse_time),
        _ => fit(integer(token, t)?, t),
    }
}

/// A JSON string holding an IEC literal of type `t`, read by `parse`.
fn literal<V>(
    token: Token<'_>,
    t: ElementaryType,
    parse: impl Fn(&str) -> Result<V, iec::LiteralError>,
) -> Result<V, TypeError> {
    match token {
        Token::Str(s) => literal_str(s, t, parse),
        _ => Err(scalar_mismatch(token, t)),
    }
}

/// An IEC literal of type `t` in `s`, read by `parse`.
fn literal_str<V>(
    s: &str,
    t: ElementaryType,
    parse: impl Fn(&str) -> Result<V, iec::LiteralError>,
) -> Result<V, TypeError> {
    parse(s).map_err(|e| match e {
        iec::LiteralError::Syntax(why) => TypeError::Mismatch {
            expected: DataType::Elementary(t),
            got: format!("the string {} ({why})", Json::from(excerpt(s))),
        },
        iec::LiteralError::Range => TypeError::OutOfRange {
            ty: t,
            value: excerpt(s),
        },
    })
}

/// At most 40 characters of `s`: error messages go back to devices and into logs, and a
/// 64 KiB string does not belong in either.
fn excerpt(s: &str) -> String {
    const MAX: usize = 40;
    match s.char_indices().nth(MAX) {
        Some((cut, _)) => format!("{}...", &s[..cut]),
        None => s.to_owned(),
    }
}

/// IEC 61131-3 literals: durations, dates, times of day and based bit strings.
mod iec {
    use std::borrow::Cow;
    use std::fmt::Write;

    use super::excerpt;
    use crate::value::MS_PER_DAY;

    /// Why a string is not a valid literal: its form, or a value beyond the type's range.
    #[derive(Debug, PartialEq)]
    pub enum LiteralError {
        Syntax(String),
        Range,
    }

    use LiteralError::{Range, Syntax};

    fn syntax(why: impl Into<String>) -> LiteralError {
        Syntax(why.into())
    }

    /// `s` without the first of `prefixes` it starts with, compared case-insensitively.
    fn strip_prefix<'a>(s: &'a str, prefixes: &[&str]) -> Option<&'a str> {
        prefixes.iter().find_map(|p| {
            s.get(..p.len())
                .filter(|head| head.eq_ignore_ascii_case(p))
                .map(|_| &s[p.len()..])
        })
    }

    /// Splits a run of digits in `radix` off the front of `s`, skipping single `_`
    /// between digits (IEC 61131-3 allows `1_000_000`, `16#FF_FF`). `None` when `s`
    /// does not start with a digit.
    fn take_digits(s: &str, radix: u32) -> Option<(Cow<'_, str>, &str)> {
        let bytes = s.as_bytes();
        let is_digit = |b: Option<&u8>| b.is_some_and(|b| char::from(*b).is_digit(radix));
        if !is_digit(bytes.first()) {
            return None;
        }
        let mut end = 0;
        let mut separated = false;
        while end < bytes.len() {
            match bytes[end] {
                b if is_digit(Some(&b)) => {}
                b'_' if is_digit(bytes.get(end + 1)) => separated = true,
                _ => break,
            }
            end += 1;
        }
        // Only ASCII bytes were consumed, so `end` is a character boundary.
        let (run, rest) = s.split_at(end);
        // Only copied when there are `_` to drop.
        let digits = if separated {
            Cow::Owned(run.replace('_', ""))
        } else {
            Cow::Borrowed(run)
        };
        Some((digits, rest))
    }

    /// A based literal `16#FF`, `8#17` or `2#1010`.
    pub fn parse_bit_string(s: &str) -> Result<i128, LiteralError> {
        let expected = "expected 16#.., 8#.. or 2#..";
        let (base, rest) = s.split_once('#').ok_or_else(|| syntax(expected))?;
        let radix = match base {
            "16" => 16,
            "8" => 8,
            "2" => 2,
            _ => return Err(syntax(expected)),
        };
        let (digits, rest) =
            take_digits(rest, radix).ok_or_else(|| syntax(format!("no base-{radix} digits")))?;
        if !rest.is_empty() {
            return Err(syntax(format!(
                "not a base-{radix} digit at {:?}",
                excerpt(rest)
            )));
        }
        // The digits are valid, so this fails only when the number overflows.
        let n = u128::from_str_radix(&digits, radix).map_err(|_| Range)?;
        i128::try_from(n).map_err(|_| Range)
    }

    /// Duration units, largest first, with their length in nanoseconds.
    const TIME_UNITS: [(&str, u128); 7] = [
        ("d", 86_400_000_000_000),
        ("h", 3_600_000_000_000),
        ("m", 60_000_000_000),
        ("s", 1_000_000_000),
        ("ms", 1_000_000),
        ("us", 1_000),
        ("ns", 1),
    ];

    /// A duration `T#1h2m3s4ms5us`, `TIME#-1.5s`, `t#1h_30m` in microseconds.
    ///
    /// Sums in `u128` nanoseconds, so any literal that fits `TIME` is computed exactly
    /// and anything larger is [`Range`] rather than an overflow.
    pub fn parse_time(s: &str) -> Result<i64, LiteralError> {
        let body = strip_prefix(s, &["TIME#", "T#"]).ok_or_else(|| syntax("expected T#.."))?;
        let (negative, mut rest) = match body.strip_prefix('-') {
            Some(rest) => (true, rest),
            None => (false, body),
        };
        if rest.is_empty() {
            return Err(syntax("no duration"));
        }
        let mut total_ns: u128 = 0;
        let mut previous_unit = None;
        let mut had_fraction = false;
        while !rest.is_empty() {
            if had_fraction {
                return Err(syntax("only the last unit may have a fraction"));
            }
            let (whole, after) = take_digits(rest, 10)
                .ok_or_else(|| syntax(format!("expected a number at {:?}", excerpt(rest))))?;
            let (fraction, after) = match after.strip_prefix('.') {
                Some(f) => {
                    let (digits, after) =
                        take_digits(f, 10).ok_or_else(|| syntax("expected digits after '.'"))?;
                    (Some(digits), after)
                }
                None => (None, after),
            };
            let unit_end = after
                .find(|c: char| !c.is_ascii_alphabetic())
                .unwrap_or(after.len());
            let (unit, after) = after.split_at(unit_end);
            let index = unit_index(unit)?;
            if previous_unit.is_some_and(|p| index <= p) {
                return Err(syntax("units go from largest to smallest, each once"));
            }
            previous_unit = Some(index);
            let ns = component_ns(&whole, fraction.as_deref(), TIME_UNITS[index].1)?;
            total_ns = total_ns.checked_add(ns).ok_or(Range)?;
            had_fraction = fraction.is_some();
            rest = match after.strip_prefix('_') {
                Some(next) if next.starts_with(|c: char| c.is_ascii_digit()) => next,
                _ => after,
            };
        }
        // (Remainders rather than `is_multiple_of`, which needs Rust 1.87.)
        let (us, leftover_ns) = (total_ns / 1_000, total_ns % 1_000);
        if leftover_ns != 0 {
            return Err(syntax("not a whole number of microseconds"));
        }
        let us = i128::try_from(us).map_err(|_| Range)?;
        i64::try_from(if negative { -us } else { us }).map_err(|_| Range)
    }

    fn unit_index(unit: &str) -> Result<usize, LiteralError> {
        if unit.is_empty() {
            return Err(syntax("a number without a unit"));
        }
        TIME_UNITS
            .iter()
            .position(|(name, _)| name.eq_ignore_ascii_case(unit))
            .ok_or_else(|| {
                syntax(format!(
                    "unknown unit {:?}: expected d, h, m, s, ms, us or ns",
                    excerpt(unit)
                ))
            })
    }

    /// `whole.fraction` units of `unit_ns` nanoseconds each, exactly.
    fn component_ns(
        whole: &str,
        fraction: Option<&str>,
        unit_ns: u128,
    ) -> Result<u128, LiteralError> {
        // Only digits, so parsing fails only on overflow.
        let whole: u128 = whole.parse().map_err(|_| Range)?;
        let mut ns = whole.checked_mul(unit_ns).ok_or(Range)?;
        let fraction = fraction.unwrap_or("").trim_end_matches('0');
        if !fraction.is_empty() {
            // A day is 864 * 10^11 ns, so more than 16 significant fraction digits can
            // never be whole nanoseconds; the cap also keeps the product below 10^32.
            let finer = || syntax("finer than a nanosecond");
            if fraction.len() > 18 {
                return Err(finer());
            }
            let scale = 10u128.pow(fraction.len() as u32);
            let scaled = fraction.parse::<u128>().map_err(|_| Range)? * unit_ns;
            let (fraction_ns, leftover) = (scaled / scale, scaled % scale);
            if leftover != 0 {
                return Err(finer());
            }
            ns = ns.checked_add(fraction_ns).ok_or(Range)?;
        }
        Ok(ns)
    }

    /// `T#` and the non-zero units from days down: `T#1h2m3s4ms5us`, `T#-1s`, `T#0s`.
    pub fn format_time(us: i64) -> String {
        if us == 0 {
            return "T#0s".to_owned();
        }
        let mut out = String::from(if us < 0 { "T#-" } else { "T#" });
        let mut rest = u128::from(us.unsigned_abs()) * 1_000;
        for (name, unit_ns) in &TIME_UNITS[..6] {
            let n = rest / unit_ns;
            rest %= unit_ns;
            if n > 0 {
                let _ = write!(out, "{n}{name}");
            }
        }
        out
    }

    /// A date `D#2026-11-22` or `DATE#2026-11-22` in milliseconds since the epoch.
    pub fn parse_date(s: &str) -> Result<u64, LiteralError> {
        let body = strip_prefix(s, &["DATE#", "D#"]).ok_or_else(|| syntax("expected D#.."))?;
        date_body(body).map(|days| days * MS_PER_DAY)
    }

    /// A time of day `TOD#12:30:15.250` or `TIME_OF_DAY#..` in milliseconds since midnight.
    pub fn parse_tod(s: &str) -> Result<u64, LiteralError> {
        let body =
            strip_prefix(s, &["TIME_OF_DAY#", "TOD#"]).ok_or_else(|| syntax("expected TOD#.."))?;
        tod_body(body)
    }

    /// A date and time `DT#2026-11-22-12:30:15.250` or `DATE_AND_TIME#..` (UTC) in
    /// milliseconds since the epoch.
    pub fn parse_date_and_time(s: &str) -> Result<u64, LiteralError> {
        let body =
            strip_prefix(s, &["DATE_AND_TIME#", "DT#"]).ok_or_else(|| syntax("expected DT#.."))?;
        // The date has two dashes; the third separates it from the time of day.
        let (cut, _) = body
            .match_indices('-')
            .nth(2)
            .ok_or_else(|| syntax("expected YYYY-MM-DD-HH:MM:SS"))?;
        Ok(date_body(&body[..cut])? * MS_PER_DAY + tod_body(&body[cut + 1..])?)
    }

    /// `YYYY-MM-DD` as days since 1970-01-01, for years 1970 to 9999.
    fn date_body(s: &str) -> Result<u64, LiteralError> {
        let mut parts = s.split('-');
        let (Some(year), Some(month), Some(day), None) =
            (parts.next(), parts.next(), parts.next(), parts.next())
        else {
            return Err(syntax("expected YYYY-MM-DD"));
        };
        let year = field(year, 4, 4, "YYYY-MM-DD")?;
        let month = field(month, 1, 2, "YYYY-MM-DD")?;
        let day = field(day, 1, 2, "YYYY-MM-DD")?;
        if !(1970..=9999).contains(&year)
            || !(1..=12).contains(&month)
            || !(1..=days_in_month(year, month)).contains(&day)
        {
            return Err(Range);
        }
        // At or after 1970-01-01, so not negative.
        u64::try_from(days_from_civil(year, month, day)).map_err(|_| Range)
    }

    /// `HH:MM:SS` with an optional `.f`, `.ff` or `.fff`, as milliseconds.
    fn tod_body(s: &str) -> Result<u64, LiteralError> {
        const FORM: &str = "HH:MM:SS.fff";
        let (hms, fraction) = match s.split_once('.') {
            Some((hms, fraction)) => (hms, Some(fraction)),
            None => (s, None),
        };
        let mut parts = hms.split(':');
        let (Some(hours), Some(minutes), Some(seconds), None) =
            (parts.next(), parts.next(), parts.next(), parts.next())
        else {
            return Err(syntax(format!("expected {FORM}")));
        };
        let hours = field(hours, 1, 2, FORM)?;
        let minutes = field(minutes, 1, 2, FORM)?;
        let seconds = field(seconds, 1, 2, FORM)?;
        let ms = match fraction {
            Some(f) => {
                let digits = field(f, 1, 3, FORM)?;
                // ".250" and ".25" are 250 ms, ".2" is 200 ms.
                digits * 10i64.pow(3 - f.len() as u32)
            }
            None => 0,
        };
        if hours >= 24 || minutes >= 60 || seconds >= 60 {
            return Err(Range);
        }
        let ms = ((hours * 60 + minutes) * 60 + seconds) * 1_000 + ms;
        u64::try_from(ms).map_err(|_| Range)
    }

    /// A field of `min..=max` decimal digits (no sign, no `_`).
    fn field(s: &str, min: usize, max: usize, form: &str) -> Result<i64, LiteralError> {
        if !(min..=max).contains(&s.len()) || !s.bytes().all(|b| b.is_ascii_digit()) {
            return Err(syntax(format!("expected {form}")));
        }
        s.parse().map_err(|_| syntax(format!("expected {form}")))
    }

    /// `YYYY-MM-DD` for a day number (days since 1970-01-01).
    pub fn format_date(days: u64) -> String {
        // Days fit i64 for every u64 millisecond count.
        let (y, m, d) = civil_from_days(days as i64);
        format!("{y:04}-{m:02}-{d:02}")
    }

    /// `HH:MM:SS`, and `.mmm` when the milliseconds are not zero.
    pub fn format_tod(ms: u64) -> String {
        let (seconds, millis) = (ms / 1_000, ms % 1_000);
        let hms = format!(
            "{:02}:{:02}:{:02}",
            seconds / 3_600,
            seconds / 60 % 60,
            seconds % 60
        );
        if millis == 0 {
            hms
        } else {
            format!("{hms}.{millis:03}")
        }
    }

    fn days_in_month(year: i64, month: i64) -> i64 {
        let leap = year % 4 == 0 && (year % 100 != 0 || year % 400 == 0);
        match month {
            2 if leap => 29,
            2 => 28,
            4 | 6 | 9 | 11 => 30,
            _ => 31,
        }
    }

    /// Days since 1970-01-01 of a proleptic Gregorian date (Howard Hinnant,
    /// "chrono-Compatible Low-Level Date Algorithms"). Years start in March so that the
    /// leap day is the last day of a year.
    pub(super) fn days_from_civil(year: i64, month: i64, day: i64) -> i64 {
        let y = if month <= 2 { year - 1 } else { year };
        let era = y.div_euclid(400);
        let year_of_era = y - era * 400;
        let month_from_march = (month + 9) % 12;
        let day_of_year = (153 * month_from_march + 2) / 5 + day - 1;
        let day_of_era = year_of_era * 365 + year_of_era / 4 - year_of_era / 100 + day_of_year;
        era * 146_097 + day_of_era - 719_468
    }

    /// The inverse of [`days_from_civil`]: (year, month, day).
    pub(super) fn civil_from_days(days: i64) -> (i64, i64, i64) {
        let z = days + 719_468;
        let era = z.div_euclid(146_097);
        let day_of_era = z - era * 146_097;
        let year_of_era =
            (day_of_era - day_of_era / 1_460 + day_of_era / 36_524 - day_of_era / 146_096) / 365;
        let day_of_year = day_of_era - (365 * year_of_era + year_of_era / 4 - year_of_era / 100);
        let month_from_march = (5 * day_of_year + 2) / 153;
        let day = day_of_year - (153 * month_from_march + 2) / 5 + 1;
        let month = if month_from_march < 10 {
            month_from_march + 3
        } else {
            month_from_march - 9
        };
        let year = year_of_era + era * 400 + i64::from(month <= 2);
        (year, month, day)
    }
}

#[cfg(test)]
pub(crate) mod tests {
    use super::*;
    use ElementaryType as T;

    /// Valid values of every elementary type, with their canonical JSON text, extremes
    /// included. Shared with the DINASORE tests.
    pub(crate) fn samples() -> Vec<(ElementaryType, Vec<(Value, &'static str)>)> {
        vec![
            (
                T::Bool,
                vec![(Value::Bool(true), "true"), (Value::Bool(false), "false")],
            ),
            (
                T::Sint,
                vec![
                    (Value::Sint(i8::MIN), "-128"),
                    (Value::Sint(i8::MAX), "127"),
                ],
            ),
            (
                T::Int,
                vec![
                    (Value::Int(i16::MIN), "-32768"),
                    (Value::Int(i16::MAX), "32767"),
                ],
            ),
            (
                T::Dint,
                vec![
                    (Value::Dint(i32::MIN), "-2147483648"),
                    (Value::Dint(i32::MAX), "2147483647"),
                ],
            ),
            (
                T::Lint,
                vec![
                    (Value::Lint(i64::MIN), "-9223372036854775808"),
                    (Value::Lint(i64::MAX), "9223372036854775807"),
                    (Value::Lint(0), "0"),
                ],
            ),
            (
                T::Usint,
                vec![(Value::Usint(0), "0"), (Value::Usint(u8::MAX), "255")],
            ),
            (
                T::Uint,
                vec![(Value::Uint(0), "0"), (Value::Uint(u16::MAX), "65535")],
            ),
            (T::Udint, vec![(Value::Udint(u32::MAX), "4294967295")]),
            (
                T::Ulint,
                vec![
                    (Value::Ulint(0), "0"),
                    (Value::Ulint(u64::MAX), "18446744073709551615"),
                ],
            ),
            (
                T::Real,
                vec![
                    (Value::Real(0.1), "0.1"),
                    (Value::Real(-1.5), "-1.5"),
                    (Value::Real(3.0), "3.0"),
                    (Value::Real(f32::MAX), "3.4028235e+38"),
                    (Value::Real(f32::MIN), "-3.4028235e+38"),
                    (Value::Real(f32::MIN_POSITIVE), "1.1754944e-38"),
                    (Value::Real(1e-45), "1e-45"),
                ],
            ),
            (
                T::Lreal,
                vec![
                    (Value::Lreal(0.1), "0.1"),
                    (Value::Lreal(f64::MAX), "1.7976931348623157e+308"),
                    (Value::Lreal(f64::MIN_POSITIVE), "2.2250738585072014e-308"),
                ],
            ),
            (
                T::Byte,
                vec![(Value::Byte(0), "0"), (Value::Byte(255), "255")],
            ),
            (T::Word, vec![(Value::Word(u16::MAX), "65535")]),
            (T::Dword, vec![(Value::Dword(u32::MAX), "4294967295")]),
            (
                T::Lword,
                vec![(Value::Lword(u64::MAX), "18446744073709551615")],
            ),
            (
                T::String,
                vec![
                    (Value::String(String::new()), r#""""#),
                    (Value::String("say \"hi\"\n".into()), r#""say \"hi\"\n""#),
                ],
            ),
            (
                T::WString,
                vec![
                    (Value::WString(String::new()), r#""""#),
                    (Value::WString("Grüße 日本 🌍".into()), r#""Grüße 日本 🌍""#),
                ],
            ),
            (
                T::Time,
                vec![
                    (Value::Time(0), r#""T#0s""#),
                    (Value::Time(-1_000_000), r#""T#-1s""#),
                    (Value::Time(-250_000), r#""T#-250ms""#),
                    (Value::Time(3_723_004_005), r#""T#1h2m3s4ms5us""#),
                    (Value::Time(86_400_000_000), r#""T#1d""#),
                    (Value::Time(i64::MAX), r#""T#106751991d4h54s775ms807us""#),
                    (Value::Time(i64::MIN), r#""T#-106751991d4h54s775ms808us""#),
                ],
            ),
            (
                T::Date,
                vec![
                    (Value::Date(0), r#""D#1970-01-01""#),
                    (Value::Date(20_779 * MS_PER_DAY), r#""D#2026-11-22""#),
                    (Value::Date(19_782 * MS_PER_DAY), r#""D#2024-02-29""#),
                    (Value::Date(2_932_896 * MS_PER_DAY), r#""D#9999-12-31""#),
                ],
            ),
            (
                T::TimeOfDay,
                vec![
                    (Value::TimeOfDay(0), r#""TOD#00:00:00""#),
                    (Value::TimeOfDay(45_015_250), r#""TOD#12:30:15.250""#),
                    (Value::TimeOfDay(MS_PER_DAY - 1), r#""TOD#23:59:59.999""#),
                ],
            ),
            (
                T::DateAndTime,
                vec![
                    (Value::DateAndTime(0), r#""DT#1970-01-01-00:00:00""#),
                    (
                        Value::DateAndTime(1_795_350_615_250),
                        r#""DT#2026-11-22-12:30:15.250""#,
                    ),
                ],
            ),
        ]
    }

    fn data(ty: DataType) -> OutputPort<'static> {
        OutputPort::Data(ty)
    }

    fn decode_text(text: &str, ty: DataType) -> Result<Message, CodecError> {
        decode(text.as_bytes(), &data(ty))
    }

    /// The [`TypeError`] of decoding `text` on a data port of type `ty`.
    fn type_error(text: &str, ty: impl Into<Ty>) -> TypeError {
        match decode_text(text, ty.into().0) {
            Err(CodecError::Type { port, error }) => {
                assert_eq!(port, "");
                error
            }
            other => panic!("{text}: expected a type error, got {other:?}"),
        }
    }

    /// Lets tests write `T::Int` or a `DataType`.
    struct Ty(DataType);

    impl From<ElementaryType> for Ty {
        fn from(t: ElementaryType) -> Ty {
            Ty(DataType::Elementary(t))
        }
    }

    impl From<DataType> for Ty {
        fn from(t: DataType) -> Ty {
            Ty(t)
        }
    }

    fn decoded(text: &str, t: ElementaryType) -> Value {
        match decode_text(text, DataType::Elementary(t)) {
            Ok(Message::Data(v)) => v,
            other => panic!("{text}: {other:?}"),
        }
    }

    fn out_of_range(ty: ElementaryType, value: &str) -> TypeError {
        TypeError::OutOfRange {
            ty,
            value: value.into(),
        }
    }

    fn is_mismatch(e: &TypeError) -> bool {
        matches!(e, TypeError::Mismatch { .. })
    }

    #[test]
    fn every_elementary_type_round_trips_in_canonical_form() {
        for (t, cases) in samples() {
            let ty = DataType::Elementary(t);
            for (value, text) in cases {
                let encoded = encode(&Message::Data(value.clone()), &data(ty));
                assert_eq!(String::from_utf8_lossy(&encoded), text, "{t}");
                assert_eq!(decode(&encoded, &data(ty)), Ok(Message::Data(value)), "{t}");
            }
        }
    }

    #[test]
    fn an_array_of_every_elementary_type_round_trips() {
        for (t, cases) in samples() {
            let values: Vec<Value> = cases.into_iter().map(|(v, _)| v).collect();
            let ty = DataType::Array(t, values.len() as u16);
            let message = Message::Data(Value::Array(t, values));
            let encoded = encode(&message, &data(ty));
            assert!(encoded.starts_with(b"["), "{t}");
            assert_eq!(decode(&encoded, &data(ty)), Ok(message), "{t}");
        }
    }

    #[test]
    fn encoding_writes_the_text_of_value_to_json() {
        let mut values: Vec<Value> = Vec::new();
        for (t, cases) in samples() {
            let scalars: Vec<Value> = cases.into_iter().map(|(v, _)| v).collect();
            values.extend(scalars.iter().cloned());
            values.push(Value::Array(t, scalars));
        }
        values.extend([
            Value::Real(f32::NAN),
            Value::Real(f32::INFINITY),
            Value::Real(-0.0),
            Value::Real(16_777_217.0),
            Value::Lreal(f64::NEG_INFINITY),
            Value::Lreal(-0.0),
            Value::Lreal(1e300),
            Value::String("\u{0}\u{1f}\"\\/\u{7f}\u{2028}".into()),
            Value::Date(MS_PER_DAY / 2),
            Value::Array(T::Real, vec![Value::Real(f32::NAN), Value::Real(0.1)]),
        ]);
        for value in &values {
            let encoded = encode(&Message::Data(value.clone()), &data(value.data_type()));
            assert_eq!(
                String::from_utf8_lossy(&encoded),
                value_to_json(value).to_string(),
                "{value:?}"
            );
        }
        // Events, against building the text from `value_to_json`.
        let port = OutputPort::Event(vec![
            ("A", DataType::Elementary(T::Real)),
            ("B\"\\", DataType::Elementary(T::String)),
            ("C", DataType::Elementary(T::Time)),
        ]);
        for (seq, ts_us, data) in [
            (Some(0), Some(u64::MAX), values[..3].to_vec()),
            (None, Some(1), values[3..5].to_vec()),
            (Some(7), None, values[5..9].to_vec()),
            (None, None, vec![]),
        ] {
            let members: Vec<String> = seq
                .map(|n| format!(r#""seq":{n}"#))
                .into_iter()
                .chain(ts_us.map(|n| format!(r#""ts":{n}"#)))
                .chain([format!(
                    r#""data":{{{}}}"#,
                    with_names(&port)
                        .zip(&data)
                        .map(|(name, v)| format!("{}:{}", Json::from(name), value_to_json(v)))
                        .collect::<Vec<_>>()
                        .join(",")
                )])
                .collect();
            let event = Message::Event(EventMessage { seq, ts_us, data });
            assert_eq!(
                String::from_utf8_lossy(&encode(&event, &port)),
                format!("{{{}}}", members.join(","))
            );
        }
    }

    #[test]
    fn events_round_trip_with_data_in_with_order() {
        let port = OutputPort::Event(vec![
            ("POSITION", DataType::Elementary(T::Int)),
            ("SENSOR_IN", DataType::Elementary(T::Bool)),
            ("AT", DataType::Elementary(T::DateAndTime)),
        ]);
        let event = Message::Event(EventMessage {
            seq: Some(17),
            ts_us: Some(1_763_797_200_123_456),
            data: vec![Value::Int(3), Value::Bool(true), Value::DateAndTime(0)],
        });
        let encoded = encode(&event, &port);
        assert_eq!(
            String::from_utf8_lossy(&encoded),
            r#"{"seq":17,"ts":1763797200123456,"data":{"POSITION":3,"SENSOR_IN":true,"AT":"DT#1970-01-01-00:00:00"}}"#
        );
        assert_eq!(decode(&encoded, &port), Ok(event));

        let unstamped = Message::Event(EventMessage {
            seq: None,
            ts_us: None,
            data: vec![
                Value::Int(-1),
                Value::Bool(false),
                Value::DateAndTime(1_000),
            ],
        });
        let encoded = encode(&unstamped, &port);
        assert!(encoded.starts_with(br#"{"data":{"POSITION""#));
        assert_eq!(decode(&encoded, &port), Ok(unstamped));
    }

    #[test]
    fn an_event_without_with_data_may_omit_data() {
        let port = OutputPort::Event(vec![]);
        let bare = Message::Event(EventMessage {
            seq: None,
            ts_us: None,
            data: vec![],
        });
        assert_eq!(decode(b"{}", &port), Ok(bare.clone()));
        assert_eq!(decode(br#"{"data":{}}"#, &port), Ok(bare.clone()));
        assert_eq!(encode(&bare, &port), br#"{"data":{}}"#);
        assert_eq!(
            decode(br#"{"seq":0,"ts":5}"#, &port),
            Ok(Message::Event(EventMessage {
                seq: Some(0),
                ts_us: Some(5),
                data: vec![],
            }))
        );
    }

    #[test]
    fn event_shape_mistakes_name_the_port_or_key() {
        let port = OutputPort::Event(vec![
            ("POSITION", DataType::Elementary(T::Int)),
            ("SENSOR_IN", DataType::Elementary(T::Bool)),
        ]);
        let dec = |text: &str| decode(text.as_bytes(), &port);
        assert_eq!(
            dec(r#"{"data":{"POSITION":3}}"#),
            Err(CodecError::Missing("SENSOR_IN".into()))
        );
        assert_eq!(
            dec(r#"{"seq":1}"#),
            Err(CodecError::Missing("POSITION".into()))
        );
        assert_eq!(
            dec(r#"{"data":{"POSITION":3,"SENSOR_IN":true,"X":1}}"#),
            Err(CodecError::Unexpected("X".into()))
        );
        assert_eq!(
            dec(r#"{"data":{"POSITION":3,"SENSOR_IN":true},"extra":1}"#),
            Err(CodecError::Unexpected("extra".into()))
        );
        assert_eq!(
            dec(r#"{"data":{"POSITION":"3","SENSOR_IN":true}}"#),
            Err(CodecError::Type {
                port: "POSITION".into(),
                error: TypeError::Mismatch {
                    expected: DataType::Elementary(T::Int),
                    got: "a JSON string".into()
                }
            })
        );
        for bad in [
            "[1,2]",
            "3",
            r#"{"data":[3,true]}"#,
            r#"{"data":null,"seq":1}"#,
            r#"{"seq":-1,"data":{"POSITION":3,"SENSOR_IN":true}}"#,
            r#"{"ts":1.5,"data":{"POSITION":3,"SENSOR_IN":true}}"#,
            r#"{"seq":"1","data":{"POSITION":3,"SENSOR_IN":true}}"#,
        ] {
            assert!(matches!(dec(bad), Err(CodecError::Malformed(_))), "{bad}");
        }
    }

    #[test]
    fn payloads_that_are_not_json_are_malformed() {
        let ty = DataType::Elementary(T::Int);
        for bad in [
            &b""[..],
            b"{",
            b"42 43",
            b"\xff\xfe",
            b"NaN",
            b"'a'",
            b"1e999",
        ] {
            assert!(
                matches!(decode(bad, &data(ty)), Err(CodecError::Malformed(_))),
                "{}",
                String::from_utf8_lossy(bad)
            );
        }
        assert_eq!(
            decode(b" 42\n", &data(ty)),
            Ok(Message::Data(Value::Int(42)))
        );
    }

    #[test]
    fn integers_are_strict_about_range_and_kind() {
        assert_eq!(type_error("128", T::Sint), out_of_range(T::Sint, "128"));
        assert_eq!(type_error("300", T::Sint), out_of_range(T::Sint, "300"));
        assert_eq!(type_error("-1", T::Usint), out_of_range(T::Usint, "-1"));
        assert_eq!(type_error("256", T::Byte), out_of_range(T::Byte, "256"));
        assert_eq!(
            type_error("-9223372036854775809", T::Lint),
            out_of_range(T::Lint, "-9.223372036854776e+18")
        );
        assert!(matches!(
            type_error("18446744073709551616", T::Ulint),
            TypeError::OutOfRange { ty: T::Ulint, .. }
        ));
        assert_eq!(
            type_error(r#""5""#, T::Int),
            TypeError::Mismatch {
                expected: DataType::Elementary(T::Int),
                got: "a JSON string".into()
            }
        );
        assert_eq!(
            type_error("1.5", T::Dint),
            TypeError::Mismatch {
                expected: DataType::Elementary(T::Dint),
                got: "a JSON number with a fraction".into()
            }
        );
        for (text, t) in [
            ("3.0", T::Int),
            ("1e3", T::Uint),
            ("null", T::Lint),
            ("true", T::Sint),
            ("[1]", T::Ulint),
            ("{}", T::Udint),
            ("1", T::Bool),
            ("0", T::Bool),
            (r#""true""#, T::Bool),
        ] {
            assert!(is_mismatch(&type_error(text, t)), "{text} as {t}");
        }
    }

    #[test]
    fn bit_strings_accept_iec_based_literals() {
        assert_eq!(decoded(r#""16#FF""#, T::Byte), Value::Byte(255));
        assert_eq!(decoded(r#""16#ff""#, T::Byte), Value::Byte(255));
        assert_eq!(decoded(r#""2#1010""#, T::Byte), Value::Byte(10));
        assert_eq!(decoded(r#""8#17""#, T::Word), Value::Word(15));
        assert_eq!(
            decoded(r#""16#FFFF_FFFF""#, T::Dword),
            Value::Dword(u32::MAX)
        );
        assert_eq!(
            decoded(r#""16#FFFF_FFFF_FFFF_FFFF""#, T::Lword),
            Value::Lword(u64::MAX)
        );
        assert_eq!(decoded("65535", T::Word), Value::Word(65535));
        assert_eq!(
            type_error(r#""16#100""#, T::Byte),
            out_of_range(T::Byte, "256")
        );
        assert_eq!(
            type_error(r#""16#1_0000_0000_0000_0000""#, T::Lword),
            out_of_range(T::Lword, "18446744073709551616")
        );
        let beyond_u128 = format!("16#{}", "F".repeat(33));
        assert_eq!(
            type_error(&format!("{beyond_u128:?}"), T::Lword),
            out_of_range(T::Lword, &beyond_u128)
        );
        for bad in [
            r#""FF""#,
            r#""16#""#,
            r#""16#FG""#,
            r#""16#_FF""#,
            r#""16#F__F""#,
            r#""2#102""#,
            r#""10#5""#,
            r#""-16#1""#,
            r#""255""#,
        ] {
            assert!(is_mismatch(&type_error(bad, T::Byte)), "{bad}");
        }
        // Only bit strings take based literals.
        assert!(is_mismatch(&type_error(r#""16#FF""#, T::Usint)));
    }

    #[test]
    fn reals_must_fit_their_width() {
        assert_eq!(decoded("1", T::Real), Value::Real(1.0));
        assert_eq!(decoded("-7", T::Lreal), Value::Lreal(-7.0));
        assert_eq!(
            decoded("18446744073709551615", T::Lreal),
            Value::Lreal(1.8446744073709552e19)
        );
        assert_eq!(decoded("1e-60", T::Real), Value::Real(0.0));
        assert_eq!(type_error("1e39", T::Real), out_of_range(T::Real, "1e+39"));
        assert_eq!(
            type_error("-3.5e38", T::Real),
            out_of_range(T::Real, "-3.5e+38")
        );
        assert!(is_mismatch(&type_error(r#""1.0""#, T::Lreal)));
        assert!(is_mismatch(&type_error("null", T::Real)));
    }

    #[test]
    fn strings_are_json_strings_within_their_length() {
        assert!(is_mismatch(&type_error("5", T::String)));
        assert!(is_mismatch(&type_error("null", T::WString)));
        let long = Json::from("x".repeat(65_536)).to_string();
        assert_eq!(type_error(&long, T::String), TypeError::TooLong(T::String));
    }

    fn time(text: &str) -> i64 {
        match decoded(&format!("{text:?}"), T::Time) {
            Value::Time(us) => us,
            other => panic!("{other:?}"),
        }
    }

    #[test]
    fn time_literals_in_every_iec_spelling() {
        assert_eq!(time("T#1h2m3s4ms5us"), 3_723_004_005);
        assert_eq!(time("T#-250ms"), -250_000);
        assert_eq!(time("TIME#1.5s"), 1_500_000);
        assert_eq!(time("time#1.5S"), 1_500_000);
        assert_eq!(time("t#1d"), 86_400_000_000);
        assert_eq!(time("T#1H_30M"), 5_400_000_000);
        assert_eq!(time("T#1_000ms"), 1_000_000);
        assert_eq!(time("T#90m"), 5_400_000_000);
        assert_eq!(time("T#2000ns"), 2);
        assert_eq!(time("T#1s1000ns"), 1_000_001);
        assert_eq!(time("T#0.5d"), 43_200_000_000);
        assert_eq!(time("T#1.250000ms"), 1_250);
        assert_eq!(time("T#0s"), 0);
        assert_eq!(time("T#-0s"), 0);
        assert_eq!(decoded("-42", T::Time), Value::Time(-42));
        assert_eq!(decoded("1500000", T::Time), Value::Time(1_500_000));
    }

    #[test]
    fn bad_time_literals_are_refused() {
        for bad in [
            "T#5x",
            "T#",
            "T#-",
            "5s",
            "T#5",
            "T#1s1h",
            "T#1s1s",
            "T#1.5s2ms",
            "T#1500ns",
            "T#1.0000001us",
            "T#.5s",
            "T#5.s",
            "T#1h__2m",
            "T#1h_",
            "T#_1h",
            "T#+1s",
            "T#1 s",
            "TOD#1s",
            "T#1s ",
        ] {
            let e = type_error(&format!("{bad:?}"), T::Time);
            assert!(is_mismatch(&e), "{bad}: {e:?}");
        }
        assert_eq!(
            type_error(r#""T#106751992d""#, T::Time),
            out_of_range(T::Time, "T#106751992d")
        );
        assert!(matches!(
            type_error(&format!("\"T#{}d\"", "9".repeat(60)), T::Time),
            TypeError::OutOfRange { .. }
        ));
        assert!(matches!(
            type_error("9223372036854775808", T::Time),
            TypeError::OutOfRange { .. }
        ));
        assert!(is_mismatch(&type_error("1.5", T::Time)));
    }

    #[test]
    fn date_and_time_literals_are_validated() {
        let day = |d: u64| d * MS_PER_DAY;
        assert_eq!(
            decoded(r#""DATE#2026-11-22""#, T::Date),
            Value::Date(day(20_779))
        );
        assert_eq!(
            decoded(r#""d#2026-11-22""#, T::Date),
            Value::Date(day(20_779))
        );
        assert_eq!(
            decoded(r#""D#2000-3-1""#, T::Date),
            Value::Date(day(11_017))
        );
        assert_eq!(
            decoded(r#""TIME_OF_DAY#12:30:15.25""#, T::TimeOfDay),
            Value::TimeOfDay(45_015_250)
        );
        assert_eq!(
            decoded(r#""tod#1:2:3.4""#, T::TimeOfDay),
            Value::TimeOfDay(3_723_400)
        );
        assert_eq!(
            decoded(r#""DATE_AND_TIME#2026-11-22-12:30:15""#, T::DateAndTime),
            Value::DateAndTime(1_795_350_615_000)
        );
        for (bad, t) in [
            ("D#2026-13-01", T::Date),
            ("D#2026-00-01", T::Date),
            ("D#2026-02-30", T::Date),
            ("D#2023-02-29", T::Date),
            ("D#2100-02-29", T::Date),
            ("D#2026-04-31", T::Date),
            ("D#1969-12-31", T::Date),
            ("D#0000-01-01", T::Date),
            ("TOD#24:00:00", T::TimeOfDay),
            ("TOD#12:60:00", T::TimeOfDay),
            ("TOD#12:00:60", T::TimeOfDay),
            ("DT#2026-11-22-25:00:00", T::DateAndTime),
            ("DT#2026-02-29-00:00:00", T::DateAndTime),
        ] {
            assert_eq!(
                type_error(&format!("{bad:?}"), t),
                out_of_range(t, bad),
                "{bad}"
            );
        }
        for (bad, t) in [
            ("2026-11-22", T::Date),
            ("D#26-11-22", T::Date),
            ("D#10000-01-01", T::Date),
            ("D#2026-11", T::Date),
            ("D#2026-11-22-", T::Date),
            ("D#2026-11-+2", T::Date),
            ("D#2026/11/22", T::Date),
            ("DT#2026-11-22", T::Date),
            ("TOD#12:30", T::TimeOfDay),
            ("TOD#12:30:15.2500", T::TimeOfDay),
            ("TOD#12:30:15.", T::TimeOfDay),
            ("TOD#123:00:00", T::TimeOfDay),
            ("TOD#-1:00:00", T::TimeOfDay),
            ("TOD#12:30:15.2.5", T::TimeOfDay),
            ("T#12:30:15", T::TimeOfDay),
            ("DT#2026-11-22", T::DateAndTime),
            ("DT#2026-11-22T12:30:15", T::DateAndTime),
            ("DT#2026-11-22 12:30:15", T::DateAndTime),
            ("DT#2026-11-22--12:30:15", T::DateAndTime),
        ] {
            let e = type_error(&format!("{bad:?}"), t);
            assert!(is_mismatch(&e), "{bad}: {e:?}");
        }
        for t in [T::Date, T::TimeOfDay, T::DateAndTime] {
            assert!(is_mismatch(&type_error("0", t)), "{t}");
        }
    }

    #[test]
    fn civil_date_conversion_agrees_on_every_day() {
        let mut expected = (1970, 1, 1);
        for days in 0..=iec::days_from_civil(9999, 12, 31) {
            assert_eq!(iec::civil_from_days(days), expected);
            assert_eq!(
                iec::days_from_civil(expected.0, expected.1, expected.2),
                days
            );
            let (y, m, d) = expected;
            let leap = y % 4 == 0 && (y % 100 != 0 || y % 400 == 0);
            let month_len = [
                31,
                if leap { 29 } else { 28 },
                31,
                30,
                31,
                30,
                31,
                31,
                30,
                31,
                30,
                31,
            ];
            expected = if d < month_len[m as usize - 1] {
                (y, m, d + 1)
            } else if m < 12 {
                (y, m + 1, 1)
            } else {
                (y + 1, 1, 1)
            };
        }
    }

    #[test]
    fn arrays_need_their_exact_length_and_element_type() {
        let ty = DataType::Array(T::Int, 3);
        assert_eq!(
            type_error("[1,2]", ty),
            TypeError::ArrayLength {
                expected: 3,
                got: 2
            }
        );
        assert_eq!(
            type_error("[1,2,3,4]", ty),
            TypeError::ArrayLength {
                expected: 3,
                got: 4
            }
        );
        assert_eq!(
            type_error("[1,40000,3]", ty),
            TypeError::Element {
                index: 1,
                error: Box::new(out_of_range(T::Int, "40000"))
            }
        );
        assert!(is_mismatch(&type_error("5", ty)));
        assert!(is_mismatch(&type_error(r#"{"0":1}"#, ty)));
        assert!(is_mismatch(&type_error("[1,2,3]", T::Int)));
        assert!(matches!(
            type_error(r#"["T#1s","T#1y"]"#, DataType::Array(T::Time, 2)),
            TypeError::Element { index: 1, .. }
        ));
    }

    #[test]
    fn long_strings_are_shortened_in_errors() {
        let text = format!("\"T#{}\"", "x".repeat(1_000));
        let message = type_error(&text, T::Time).to_string();
        assert!(message.len() < 200, "{message}");
    }

    /// Regression (broker/fuzz/regressions/typed_codec): numbers are read correctly
    /// rounded (`serde_json`'s `float_roundtrip`), so an LREAL keeps its value through
    /// every hop between encodings. Without it `-4.5e300` read as the next double, and
    /// each re-encoding moved it one more.
    #[test]
    fn lreal_and_real_read_exactly_and_round_trip() {
        let port = data(DataType::Elementary(T::Lreal));
        let message = decode(b"-4.5e300", &port).unwrap();
        assert_eq!(message, Message::Data(Value::Lreal(-4.5e300)));
        assert_eq!(decode(&encode(&message, &port), &port), Ok(message));
        let port = data(DataType::Elementary(T::Real));
        let message = decode(b"3.4028235e38", &port).unwrap();
        assert_eq!(message, Message::Data(Value::Real(f32::MAX)));
        assert_eq!(decode(&encode(&message, &port), &port), Ok(message));
    }

    #[test]
    fn decode_named_names_the_data_port() {
        let port = data(DataType::Elementary(T::Bool));
        assert!(matches!(
            decode_named(b"1", "SENSOR_IN", &port),
            Err(CodecError::Type { port, .. }) if port == "SENSOR_IN"
        ));
    }

    /// xorshift64: deterministic pseudo-random numbers without a crate.
    pub(crate) struct XorShift(pub(crate) u64);

    impl XorShift {
        pub(crate) fn next(&mut self) -> u64 {
            self.0 ^= self.0 << 13;
            self.0 ^= self.0 >> 7;
            self.0 ^= self.0 << 17;
            self.0
        }

        pub(crate) fn below(&mut self, n: usize) -> usize {
            (self.next() % n as u64) as usize
        }
    }

    /// Random payloads: raw bytes, and soups of JSON and literal fragments that get
    /// further into the decoder than raw bytes do.
    pub(crate) fn random_payloads(count: usize) -> Vec<Vec<u8>> {
        const PIECES: [&str; 32] = [
            "{",
            "}",
            "[",
            "]",
            "\"",
            ":",
            ",",
            "-",
            ".",
            "_",
            "#",
            "0",
            "1",
            "9",
            "e",
            "true",
            "null",
            "T#",
            "D#",
            "TOD#",
            "DT#",
            "16#",
            "2#",
            "ms",
            "h",
            "d",
            "s",
            "\"data\"",
            "\"seq\"",
            "\"A\"",
            "\"B\"",
            "18446744073709551616",
        ];
        let mut rng = XorShift(0x9E37_79B9_7F4A_7C15);
        (0..count)
            .map(|i| {
                let len = rng.below(24);
                if i % 2 == 0 {
                    (0..len).map(|_| rng.next() as u8).collect()
                } else {
                    (0..len)
                        .map(|_| PIECES[rng.below(PIECES.len())])
                        .collect::<String>()
                        .into_bytes()
                }
            })
            .collect()
    }

    /// Ports of several shapes for the random-input tests.
    pub(crate) fn fuzz_ports() -> Vec<OutputPort<'static>> {
        let mut ports: Vec<OutputPort<'static>> = [
            T::Bool,
            T::Sint,
            T::Ulint,
            T::Real,
            T::Byte,
            T::String,
            T::Time,
            T::Date,
            T::TimeOfDay,
            T::DateAndTime,
        ]
        .into_iter()
        .map(|t| OutputPort::Data(DataType::Elementary(t)))
        .collect();
        ports.push(OutputPort::Data(DataType::Array(T::Int, 2)));
        ports.push(OutputPort::Event(vec![]));
        ports.push(OutputPort::Event(vec![
            ("A", DataType::Elementary(T::Int)),
            ("B", DataType::Array(T::Time, 1)),
        ]));
        ports
    }

    #[test]
    fn random_payloads_never_panic_and_accepted_ones_round_trip() {
        let ports = fuzz_ports();
        let mut accepted = 0;
        for payload in random_payloads(2_000) {
            for port in &ports {
                if let Ok(message) = decode(&payload, port) {
                    accepted += 1;
                    let again = encode(&message, port);
                    assert_eq!(decode(&again, port), Ok(message));
                }
            }
        }
        assert!(
            accepted > 0,
            "no random payload was valid: the generator is too weak"
        );
    }

    /// A valid literal with up to three random one-character edits: inputs right at
    /// the border between valid and invalid, where the literal parsers do their work.
    fn mutated_literal(rng: &mut XorShift) -> String {
        const SEEDS: [&str; 14] = [
            "T#1h2m3s4ms5us",
            "T#-250ms",
            "TIME#1.5s",
            "t#1h_30m",
            "T#2000ns",
            "D#2026-11-22",
            "DATE#2024-02-29",
            "TOD#23:59:59.999",
            "TIME_OF_DAY#12:30:15.25",
            "DT#2026-11-22-12:30:15.250",
            "16#FF",
            "2#1010",
            "8#17",
            "16#FFFF_FFFF",
        ];
        const CHARS: &[u8] = b"0123456789-:._#TtDdOoHhMmSsUuNnFfx ";
        let mut bytes = SEEDS[rng.below(SEEDS.len())].as_bytes().to_vec();
        for _ in 0..rng.below(4) {
            let at = rng.below(bytes.len() + 1);
            let c = CHARS[rng.below(CHARS.len())];
            match rng.below(3) {
                0 if at < bytes.len() => bytes[at] = c,
                1 if at < bytes.len() => {
                    bytes.remove(at);
                }
                _ => bytes.insert(at, c),
            }
        }
        String::from_utf8_lossy(&bytes).into_owned()
    }

    #[test]
    fn mutated_literals_never_panic_and_accepted_ones_round_trip() {
        let mut rng = XorShift(42);
        let ports = fuzz_ports();
        let mut accepted = 0;
        for _ in 0..2_000 {
            let text = Json::from(mutated_literal(&mut rng)).to_string();
            for port in &ports {
                if let Ok(message) = decode(text.as_bytes(), port) {
                    // Any string is a STRING; count only what a literal parser accepted.
                    if !matches!(message, Message::Data(Value::String(_))) {
                        accepted += 1;
                    }
                    let again = encode(&message, port);
                    assert_eq!(decode(&again, port), Ok(message), "{text}");
                }
            }
        }
        assert!(
            accepted > 100,
            "only {accepted} mutated literals were valid"
        );
    }
}

//! The streaming decoder: reads a payload straight into [`Value`]s with `serde_json`'s
//! [`Deserializer`](serde_json::Deserializer), without building a `serde_json::Value`
//! tree first. The broker decodes every publication on a typed topic, so this is the
//! cost of type checking.
//!
//! It accepts and refuses exactly what parsing into a tree and then reading the tree
//! would ([`super::value_from_json`] for values), with the same errors:
//!
//! - A JSON syntax error anywhere wins over everything else, as when the whole payload
//!   is parsed first: the visitors here never fail, they return what they found as
//!   values, so only the parser stops early.
//! - Every value is read with `deserialize_any`, as the tree is, so syntax errors and
//!   the nesting limit are reported at the same places with the same messages. (An
//!   object payload is checked for UTF-8 once, then parsed as `&str`: the same parser,
//!   without a check per key; one that is not UTF-8 is parsed as bytes for its error.)
//! - Findings are reported in the tree decoder's order rather than the payload's (see
//!   [`Fields`] and [`Event`]).
//! - Of duplicate keys the last one counts, as in a `serde_json::Map`.

use std::fmt;

use serde::de::{DeserializeSeed, Deserializer, MapAccess, SeqAccess, Visitor};
use serde_json::Map;

use super::read::{mismatch, object_fields, scalar_from_token, Token};
use crate::codec::{CodecError, EventMessage};
use crate::types::{DataType, ElementaryType};
use crate::value::{TypeError, Value};

/// Parses all of `payload`, a JSON object, with `seed`; invalid JSON or anything after
/// the value is [`CodecError::Malformed`].
pub(super) fn parse_object<'de, S: DeserializeSeed<'de>>(
    payload: &'de [u8],
    seed: S,
) -> Result<S::Value, CodecError> {
    // Checking all of the payload at once spares the parser checking each key.
    match std::str::from_utf8(payload) {
        Ok(text) => parse(serde_json::Deserializer::from_str(text), seed),
        // Always an error (JSON outside strings is ASCII), found where it always was.
        Err(_) => parse(serde_json::Deserializer::from_slice(payload), seed),
    }
}

/// [`parse_object`] for a bare value: one string at most, checked as it is read.
pub(super) fn parse_value<'de, S: DeserializeSeed<'de>>(
    payload: &'de [u8],
    seed: S,
) -> Result<S::Value, CodecError> {
    parse(serde_json::Deserializer::from_slice(payload), seed)
}

fn parse<'de, R, S>(mut de: serde_json::Deserializer<R>, seed: S) -> Result<S::Value, CodecError>
where
    R: serde_json::de::Read<'de>,
    S: DeserializeSeed<'de>,
{
    let not_json = |e: serde_json::Error| CodecError::Malformed(format!("not JSON: {e}"));
    let value = seed.deserialize(&mut de).map_err(not_json)?;
    de.end().map_err(not_json)?;
    Ok(value)
}

/// What to make of one JSON value, by kind. [`Any`] parses the value and hands it over;
/// the arrays and objects a shape does not read are parsed to their end and given to
/// [`Shape::scalar`] as [`Token::Array`] or [`Token::Object`].
pub(super) trait Shape<'de>: Sized {
    type Out;

    fn scalar(self, token: Token<'_>) -> Self::Out;

    fn seq<A: SeqAccess<'de>>(self, mut seq: A) -> Result<Self::Out, A::Error> {
        while seq.next_element_seed(Any(Skip))?.is_some() {}
        Ok(self.scalar(Token::Array))
    }

    fn map<A: MapAccess<'de>>(self, mut map: A) -> Result<Self::Out, A::Error> {
        while map.next_key_seed(Any(Skip))?.is_some() {
            map.next_value_seed(Any(Skip))?;
        }
        Ok(self.scalar(Token::Object))
    }
}

/// Reads one JSON value of any kind into the shape `S`.
pub(super) struct Any<S>(pub(super) S);

impl<'de, S: Shape<'de>> DeserializeSeed<'de> for Any<S> {
    type Value = S::Out;

    fn deserialize<D: Deserializer<'de>>(self, d: D) -> Result<S::Out, D::Error> {
        d.deserialize_any(self)
    }
}

impl<'de, S: Shape<'de>> Visitor<'de> for Any<S> {
    type Value = S::Out;

    fn expecting(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str("any JSON value")
    }

    fn visit_unit<E>(self) -> Result<S::Out, E> {
        Ok(self.0.scalar(Token::Null))
    }

    fn visit_bool<E>(self, b: bool) -> Result<S::Out, E> {
        Ok(self.0.scalar(Token::Bool(b)))
    }

    fn visit_i64<E>(self, n: i64) -> Result<S::Out, E> {
        Ok(self.0.scalar(Token::Int(n.into())))
    }

    fn visit_u64<E>(self, n: u64) -> Result<S::Out, E> {
        Ok(self.0.scalar(Token::Int(n.into())))
    }

    fn visit_f64<E>(self, x: f64) -> Result<S::Out, E> {
        Ok(self.0.scalar(Token::Float(x)))
    }

    // Borrowed and owned strings come here too.
    fn visit_str<E>(self, s: &str) -> Result<S::Out, E> {
        Ok(self.0.scalar(Token::Str(s)))
    }

    fn visit_seq<A: SeqAccess<'de>>(self, seq: A) -> Result<S::Out, A::Error> {
        self.0.seq(seq)
    }

    fn visit_map<A: MapAccess<'de>>(self, map: A) -> Result<S::Out, A::Error> {
        self.0.map(map)
    }
}

/// Any JSON value, parsed and dropped.
struct Skip;

impl Shape<'_> for Skip {
    type Out = ();

    fn scalar(self, _: Token<'_>) {}
}

/// One elementary value (an array element: [`Typed`] checks the whole value).
struct Scalar(ElementaryType);

impl Shape<'_> for Scalar {
    type Out = Result<Value, TypeError>;

    fn scalar(self, token: Token<'_>) -> Self::Out {
        scalar_from_token(token, self.0)
    }
}

/// Arrays preallocate at most this many elements: the declared length may be large
/// (65,535) for a payload that is not.
const MAX_PREALLOCATED: usize = 256;

/// `ARRAY [n] OF t`. A wrong length is reported before an ill-typed element (as the
/// tree decoder does), so elements are counted to the end.
struct Array(ElementaryType, u16);

impl<'de> Shape<'de> for Array {
    type Out = Result<Value, TypeError>;

    fn scalar(self, token: Token<'_>) -> Self::Out {
        Err(mismatch(token, DataType::Array(self.0, self.1)))
    }

    fn seq<A: SeqAccess<'de>>(self, mut seq: A) -> Result<Self::Out, A::Error> {
        let Array(t, n) = self;
        let expected = usize::from(n);
        let mut items = Vec::with_capacity(expected.min(MAX_PREALLOCATED));
        let mut got = 0;
        let mut first_error = None;
        loop {
            // Past the first bad element or the declared length, only the count matters.
            let more = if got < expected && first_error.is_none() {
                match seq.next_element_seed(Any(Scalar(t)))? {
                    None => false,
                    Some(Ok(item)) => {
                        items.push(item);
                        true
                    }
                    Some(Err(error)) => {
                        first_error = Some(TypeError::Element {
                            index: got,
                            error: Box::new(error),
                        });
                        true
                    }
                }
            } else {
                seq.next_element_seed(Any(Skip))?.is_some()
            };
            if !more {
                break;
            }
            got += 1;
        }
        Ok(if got != expected {
            Err(TypeError::ArrayLength { expected, got })
        } else if let Some(error) = first_error {
            Err(error)
        } else {
            Ok(Value::Array(t, items))
        })
    }
}

/// A value of a port's type, checked with [`Value::check`].
pub(super) struct Typed(pub(super) DataType);

impl<'de> DeserializeSeed<'de> for Typed {
    type Value = Result<Value, TypeError>;

    fn deserialize<D: Deserializer<'de>>(self, d: D) -> Result<Self::Value, D::Error> {
        let value = match self.0 {
            DataType::Elementary(t) => Any(Scalar(t)).deserialize(d)?,
            DataType::Array(t, n) => Any(Array(t, n)).deserialize(d)?,
        };
        Ok(value.and_then(|value| {
            value.check(self.0)?;
            Ok(value)
        }))
    }
}

/// Exactly the named, typed fields of a JSON object, in field order: the shape of an
/// event's `data` and of every DINASORE payload. Anything but an object is `Err` with
/// its description ("a JSON array").
///
/// Structural mistakes are reported before value mistakes, whatever the payload's
/// order: a missing field first (in field order), then a key that is not a field (the
/// least in byte order, which is the one a `serde_json::Map` lists first), then the
/// first ill-typed value in field order.
pub(super) struct Fields<'a>(pub(super) &'a [(&'a str, DataType)]);

/// What [`Fields`] reads: the values, or the first mistake in the object; `Err` for a
/// value that is not an object.
pub(super) type FieldsOut = Result<Result<Vec<Value>, CodecError>, &'static str>;

impl<'de> Shape<'de> for Fields<'_> {
    type Out = FieldsOut;

    fn scalar(self, token: Token<'_>) -> Self::Out {
        Err(token.describe())
    }

    fn map<A: MapAccess<'de>>(self, mut map: A) -> Result<Self::Out, A::Error> {
        let fields = self.0;
        let names = Names::new(fields);
        if names.repeat() {
            // Fields sharing a name each take that key's value: rare enough (a validated
            // interface never lists a WITH port twice) to read the object as a tree.
            let mut object = Map::new();
            while let Some(key) = map.next_key::<String>()? {
                object.insert(key, map.next_value::<serde_json::Value>()?);
            }
            return Ok(Ok(object_fields(&object, fields)));
        }
        let mut values = Collected::InOrder(Vec::with_capacity(fields.len()));
        // Per field, the error of its (last) value if that is ill-typed; allocated at
        // the first error.
        let mut errors: Vec<Option<TypeError>> = Vec::new();
        let mut undeclared = None;
        let mut next = 0;
        loop {
            let key = FieldKey {
                names: &names,
                next,
                undeclared: &mut undeclared,
            };
            let Some(found) = map.next_key_seed(key)? else {
                break;
            };
            let Some((index, &(_, ty))) = found.and_then(|i| Some((i, fields.get(i)?))) else {
                map.next_value_seed(Any(Skip))?;
                continue;
            };
            next = index + 1;
            let value = match map.next_value_seed(Typed(ty))? {
                Ok(value) => {
                    if let Some(error) = errors.get_mut(index) {
                        *error = None;
                    }
                    value
                }
                Err(error) => {
                    if errors.is_empty() {
                        errors.resize_with(fields.len(), || None);
                    }
                    if let Some(slot) = errors.get_mut(index) {
                        *slot = Some(error);
                    }
                    // Marks the field present; never returned.
                    Value::Bool(false)
                }
            };
            values.set(index, value, fields.len());
        }
        Ok(Ok(self.finish(values, undeclared, errors)))
    }
}

impl Fields<'_> {
    fn finish(
        self,
        values: Collected,
        undeclared: Option<String>,
        errors: Vec<Option<TypeError>>,
    ) -> Result<Vec<Value>, CodecError> {
        let name = |index: usize| self.0.get(index).map_or("", |(name, _)| name).to_owned();
        if let Some(missing) = values.first_missing(self.0.len()) {
            return Err(CodecError::Missing(name(missing)));
        }
        if let Some(key) = undeclared {
            return Err(CodecError::Unexpected(key));
        }
        let first_error = errors
            .into_iter()
            .enumerate()
            .find_map(|(i, e)| Some((i, e?)));
        if let Some((index, error)) = first_error {
            return Err(CodecError::Type {
                port: name(index),
                error,
            });
        }
        Ok(values.into_values())
    }
}

/// The field values read so far.
enum Collected {
    /// The first `len()` fields: the keys have come in field order so far, the usual case.
    InOrder(Vec<Value>),
    /// By field index, once a key came out of order or twice.
    Scattered(Vec<Option<Value>>),
}

impl Collected {
    /// Sets field `index` of `len`.
    fn set(&mut self, index: usize, value: Value, len: usize) {
        match self {
            Collected::InOrder(values) if index == values.len() => values.push(value),
            Collected::InOrder(values) => {
                let mut slots: Vec<Option<Value>> =
                    std::mem::take(values).into_iter().map(Some).collect();
                slots.resize_with(len, || None);
                if let Some(slot) = slots.get_mut(index) {
                    *slot = Some(value);
                }
                *self = Collected::Scattered(slots);
            }
            Collected::Scattered(slots) => {
                if let Some(slot) = slots.get_mut(index) {
                    *slot = Some(value);
                }
            }
        }
    }

    /// The first of `len` fields without a value.
    fn first_missing(&self, len: usize) -> Option<usize> {
        match self {
            Collected::InOrder(values) => (values.len() < len).then_some(values.len()),
            Collected::Scattered(slots) => slots.iter().position(Option::is_none),
        }
    }

    /// The values in field order, once none is missing.
    fn into_values(self) -> Vec<Value> {
        match self {
            Collected::InOrder(values) => values,
            Collected::Scattered(slots) => slots.into_iter().flatten().collect(),
        }
    }
}

/// Finds fields by name.
struct Names<'a> {
    fields: &'a [(&'a str, DataType)],
    /// Field indices in name order, for a long list; empty for a short one.
    sorted: Vec<usize>,
}

impl<'a> Names<'a> {
    /// Longer lists get a sorted index, so that no key costs a scan of every name (a
    /// payload may repeat a key many times).
    const SHORT: usize = 16;

    fn new(fields: &'a [(&'a str, DataType)]) -> Names<'a> {
        let mut sorted = Vec::new();
        if fields.len() > Self::SHORT {
            sorted.extend(0..fields.len());
            sorted.sort_unstable_by_key(|&i| fields.get(i).map(|(name, _)| *name));
        }
        Names { fields, sorted }
    }

    fn name(&self, index: usize) -> Option<&'a str> {
        self.fields.get(index).map(|(name, _)| *name)
    }

    /// Whether two fields share a name.
    fn repeat(&self) -> bool {
        let fields = self.fields;
        if self.sorted.is_empty() {
            fields.iter().enumerate().any(|(i, (name, _))| {
                fields
                    .get(..i)
                    .is_some_and(|before| before.iter().any(|(n, _)| n == name))
            })
        } else {
            self.sorted
                .windows(2)
                .any(|pair| self.name(pair[0]) == self.name(pair[1]))
        }
    }

    /// The field named `key`, trying `next` first: keys usually come in field order.
    fn find(&self, key: &str, next: usize) -> Option<usize> {
        if self.name(next) == Some(key) {
            return Some(next);
        }
        if self.sorted.is_empty() {
            self.fields.iter().position(|(name, _)| *name == key)
        } else {
            let at = self
                .sorted
                .binary_search_by(|&i| self.name(i).unwrap_or("").cmp(key))
                .ok()?;
            self.sorted.get(at).copied()
        }
    }
}

/// A key of a [`Fields`] object: the index of its field, or `None` for an undeclared
/// key (kept in `undeclared` if it is the least so far).
struct FieldKey<'n, 'a, 'u> {
    names: &'n Names<'a>,
    /// The field after the previous key's.
    next: usize,
    undeclared: &'u mut Option<String>,
}

impl<'de> DeserializeSeed<'de> for FieldKey<'_, '_, '_> {
    type Value = Option<usize>;

    fn deserialize<D: Deserializer<'de>>(self, d: D) -> Result<Self::Value, D::Error> {
        d.deserialize_str(self)
    }
}

impl Visitor<'_> for FieldKey<'_, '_, '_> {
    type Value = Option<usize>;

    fn expecting(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str("a data port name")
    }

    fn visit_str<E>(self, key: &str) -> Result<Option<usize>, E> {
        let index = self.names.find(key, self.next);
        if index.is_none() {
            note_undeclared(self.undeclared, key);
        }
        Ok(index)
    }
}

/// Keeps the least undeclared key, allocating only for a new least one.
fn note_undeclared(least: &mut Option<String>, key: &str) {
    let is_less = match least {
        Some(least) => key < least.as_str(),
        None => true,
    };
    if is_less {
        *least = Some(key.to_owned());
    }
}

/// A canonical event `{"seq":..,"ts":..,"data":{..}}` for an event port with these WITH
/// data ports.
///
/// Reported first: an undeclared top-level key (the least), then whatever is wrong
/// with `data` (see [`Fields`]), then a bad `seq`, then a bad `ts`.
pub(super) struct Event<'a>(pub(super) &'a [(&'a str, DataType)]);

impl<'de> Shape<'de> for Event<'_> {
    type Out = Result<EventMessage, CodecError>;

    fn scalar(self, token: Token<'_>) -> Self::Out {
        Err(CodecError::Malformed(format!(
            r#"an event is a JSON object {{"seq":..,"ts":..,"data":{{..}}}}, got {}"#,
            token.describe()
        )))
    }

    fn map<A: MapAccess<'de>>(self, mut map: A) -> Result<Self::Out, A::Error> {
        let with = self.0;
        let mut undeclared = None;
        let (mut seq, mut ts, mut data) = (None, None, None);
        while let Some(key) = map.next_key_seed(EventKey(&mut undeclared))? {
            match key {
                Some(EventField::Seq) => seq = Some(map.next_value_seed(Any(Unsigned))?),
                Some(EventField::Ts) => ts = Some(map.next_value_seed(Any(Unsigned))?),
                Some(EventField::Data) => data = Some(map.next_value_seed(Any(Fields(with)))?),
                None => map.next_value_seed(Any(Skip))?,
            }
        }
        Ok(self.finish(undeclared, seq, ts, data))
    }
}

/// What an event's value for `seq` or `ts` turned out to be.
type Stamp = Option<Result<u64, &'static str>>;

impl Event<'_> {
    fn finish(
        self,
        undeclared: Option<String>,
        seq: Stamp,
        ts: Stamp,
        data: Option<FieldsOut>,
    ) -> Result<EventMessage, CodecError> {
        if let Some(key) = undeclared {
            return Err(CodecError::Unexpected(key));
        }
        let data = match data {
            Some(Ok(values)) => values?,
            // Without `data`, an event with WITH ports reports the first one as missing.
            None => match self.0.first() {
                Some((name, _)) => return Err(CodecError::Missing((*name).to_owned())),
                None => Vec::new(),
            },
            Some(Err(got)) => {
                return Err(CodecError::Malformed(format!(
                    "data: expected a JSON object of the WITH data ports, got {got}"
                )))
            }
        };
        Ok(EventMessage {
            seq: stamp(seq, "seq")?,
            ts_us: stamp(ts, "ts")?,
            data,
        })
    }
}

/// `seq` or `ts`: absent, or an unsigned integer.
fn stamp(value: Stamp, key: &str) -> Result<Option<u64>, CodecError> {
    value.transpose().map_err(|got| {
        CodecError::Malformed(format!("{key}: expected an unsigned integer, got {got}"))
    })
}

/// An unsigned 64-bit integer, or the description of what is there instead.
struct Unsigned;

impl Shape<'_> for Unsigned {
    type Out = Result<u64, &'static str>;

    fn scalar(self, token: Token<'_>) -> Self::Out {
        match token {
            Token::Int(n) => u64::try_from(n).map_err(|_| token.describe()),
            _ => Err(token.describe()),
        }
    }
}

enum EventField {
    Seq,
    Ts,
    Data,
}

/// A top-level key of an event: `None` for an undeclared one, kept in the `Option` if
/// it is the least so far.
struct EventKey<'u>(&'u mut Option<String>);

impl<'de> DeserializeSeed<'de> for EventKey<'_> {
    type Value = Option<EventField>;

    fn deserialize<D: Deserializer<'de>>(self, d: D) -> Result<Self::Value, D::Error> {
        d.deserialize_str(self)
    }
}

impl Visitor<'_> for EventKey<'_> {
    type Value = Option<EventField>;

    fn expecting(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(r#""seq", "ts" or "data""#)
    }

    fn visit_str<E>(self, key: &str) -> Result<Self::Value, E> {
        Ok(match key {
            "seq" => Some(EventField::Seq),
            "ts" => Some(EventField::Ts),
            "data" => Some(EventField::Data),
            _ => {
                note_undeclared(self.0, key);
                None
            }
        })
    }
}

#[cfg(test)]
mod tests {
    use super::super::tests::{fuzz_ports, random_payloads, XorShift};
    use super::super::tree;
    use crate::codec::{dinasore, json};
    use crate::interface::OutputPort;
    use crate::types::{DataType, ElementaryType as T};

    fn pick<'a>(rng: &mut XorShift, items: &[&'a str]) -> &'a str {
        items[rng.below(items.len())]
    }

    fn random_value(rng: &mut XorShift, depth: usize) -> String {
        const SCALARS: [&str; 24] = [
            "0",
            "-1",
            "1.5",
            "1e3",
            "-0",
            "128",
            "40000",
            "18446744073709551616",
            "-9223372036854775809",
            "true",
            "false",
            "null",
            r#""T#1s""#,
            r#""T#5x""#,
            r#""x""#,
            r#""16#FF""#,
            r#""T#1\u0073""#,
            "[]",
            r#"["T#1s"]"#,
            r#"["T#1s","T#2s"]"#,
            r#"["T#1y"]"#,
            "[1]",
            "{}",
            r#"{"A":1}"#,
        ];
        match rng.below(if depth > 3 { 1 } else { 5 }) {
            0 | 1 => pick(rng, &SCALARS).to_owned(),
            2 => format!("[{}]", random_value(rng, depth + 1)),
            3 => random_object(rng, depth + 1),
            _ => format!(
                "[{},{}]",
                random_value(rng, depth + 1),
                random_value(rng, depth + 1)
            ),
        }
    }

    fn random_object(rng: &mut XorShift, depth: usize) -> String {
        const KEYS: [&str; 11] = [
            r#""A""#,
            r#""B""#,
            r#""C""#,
            r#""\u0041""#,
            r#""a""#,
            r#""""#,
            r#""seq""#,
            r#""ts""#,
            r#""data""#,
            r#""x""#,
            r#""Z""#,
        ];
        let entries: Vec<String> = (0..rng.below(5))
            .map(|_| {
                let key = pick(rng, &KEYS);
                let value = if key == r#""data""# && rng.below(4) > 0 {
                    random_object(rng, depth + 1)
                } else if matches!(key, r#""seq""# | r#""ts""#) && rng.below(2) > 0 {
                    pick(rng, &["0", "17", "-1", "1.0", "18446744073709551615"]).to_owned()
                } else {
                    random_value(rng, depth + 1)
                };
                format!("{key}:{value}")
            })
            .collect();
        format!("{{{}}}", entries.join(","))
    }

    /// Event-shaped payloads, a few of them broken.
    fn event_payloads(count: usize) -> Vec<Vec<u8>> {
        let mut rng = XorShift(0x5EED);
        (0..count)
            .map(|_| {
                let mut bytes = if rng.below(3) == 0 {
                    random_value(&mut rng, 0)
                } else {
                    random_object(&mut rng, 0)
                }
                .into_bytes();
                match rng.below(10) {
                    0 => bytes.truncate(rng.below(bytes.len() + 1)),
                    1 => {
                        let at = rng.below(bytes.len() + 1);
                        let c = b"{}[],:\"\\x 1\xff"[rng.below(12)];
                        bytes.insert(at, c);
                    }
                    2 => bytes.extend_from_slice(b" x"),
                    _ => {}
                }
                bytes
            })
            .collect()
    }

    fn ports() -> Vec<OutputPort<'static>> {
        let mut ports = fuzz_ports();
        ports.push(OutputPort::Event(vec![
            ("A", DataType::Elementary(T::Int)),
            ("B", DataType::Array(T::Time, 1)),
            ("C", DataType::Elementary(T::String)),
        ]));
        ports.push(OutputPort::Event(vec![(
            "A",
            DataType::Elementary(T::Bool),
        )]));
        ports.push(OutputPort::Data(DataType::Array(T::Time, 2)));
        // Not from a validated interface: a WITH name listed twice.
        ports.push(OutputPort::Event(vec![
            ("A", DataType::Elementary(T::Int)),
            ("B", DataType::Array(T::Time, 1)),
            ("A", DataType::Elementary(T::Int)),
        ]));
        ports
    }

    const LONG: [&str; 20] = [
        "N00", "N01", "N02", "N03", "N04", "N05", "N06", "N07", "N08", "N09", "N10", "N11", "N12",
        "N13", "N14", "N15", "N16", "N17", "N18", "N19",
    ];

    /// Ports with more WITH names than [`Names::SHORT`](super::Names), one of them with
    /// a name listed twice.
    fn long_ports() -> Vec<OutputPort<'static>> {
        let ty = |i: usize| DataType::Elementary([T::Bool, T::Int][i % 2]);
        let long: Vec<_> = LONG.iter().enumerate().map(|(i, n)| (*n, ty(i))).collect();
        let mut repeated = long.clone();
        repeated[19] = ("N05", ty(5));
        vec![OutputPort::Event(long), OutputPort::Event(repeated)]
    }

    /// Objects of the long ports' names: shuffled, some missing, repeated or undeclared,
    /// some values ill-typed; bare (DINASORE) or as an event's `data`.
    fn long_payloads(count: usize) -> Vec<Vec<u8>> {
        let mut rng = XorShift(0x10_4E);
        (0..count)
            .map(|_| {
                let mut order: Vec<usize> = (0..LONG.len()).collect();
                for i in (1..order.len()).rev() {
                    order.swap(i, rng.below(i + 1));
                }
                // Half of them are valid, for either the plain or the repeating port.
                let valid = rng.below(2) == 0;
                if !valid && rng.below(3) == 0 {
                    order.truncate(order.len() - 1 - rng.below(3));
                }
                let mut entries: Vec<String> = order
                    .iter()
                    .map(|&i| {
                        let value = match (i % 2, if valid { 2 } else { rng.below(12) }) {
                            (_, 0) => r#""x""#,
                            (0, 1) => "1",
                            (1, 1) => "40000",
                            (0, _) => pick(&mut rng, &["true", "false"]),
                            _ => pick(&mut rng, &["0", "-7", "32767"]),
                        };
                        format!(r#""{}":{value}"#, LONG[i])
                    })
                    .collect();
                for _ in 0..if valid { 0 } else { rng.below(3) } {
                    let at = rng.below(entries.len() + 1);
                    let entry = match rng.below(3) {
                        0 => format!(r#""N{:02}":true"#, rng.below(25)),
                        1 => format!(r#""N{:02}":3"#, rng.below(25)),
                        _ => r#""M":null"#.to_owned(),
                    };
                    entries.insert(at, entry);
                }
                let object = format!("{{{}}}", entries.join(","));
                if rng.below(2) == 0 {
                    object
                } else {
                    format!(r#"{{"seq":1,"data":{object}}}"#)
                }
                .into_bytes()
            })
            .collect()
    }

    fn explicit_payloads() -> Vec<Vec<u8>> {
        let deep = |open: &str, close: &str, n: usize| open.repeat(n) + &close.repeat(n);
        let mut payloads: Vec<String> = vec![
            r#"{"data":{"A":"bad","A":1,"B":["T#1s"],"C":""}}"#.into(),
            r#"{"data":{"A":1,"B":["T#1s"],"C":"","A":"bad"}}"#.into(),
            r#"{"data":{"C":"","B":["T#1s"],"A":1}}"#.into(),
            r#"{"data":{"A":1,"B":["T#1s"],"C":""},"data":5}"#.into(),
            r#"{"data":5,"data":{"A":1,"B":["T#1s"],"C":""}}"#.into(),
            r#"{"zz":1,"extra":2,"data":{}}"#.into(),
            r#"{"data":{"Z":1,"Y":2}}"#.into(),
            r#"{"data":{"Z":1,"A":"x","Y":2,"B":[],"C":3}}"#.into(),
            r#"{"seq":-1,"ts":1.5,"data":{"A":"x"}}"#.into(),
            r#"{"seq":-1,"ts":1.5,"data":{"A":1,"B":["T#1s"],"C":""}}"#.into(),
            r#"{"ts":1.5,"seq":-1,"data":{"A":1,"B":["T#1s"],"C":""}}"#.into(),
            r#"{"data":{"A":1,"B":["T#1s",[[[]]],3],"C":""}}"#.into(),
            r#"{"data":{"\u0041":1,"B":["T#1s"],"C":"\ud83c\udf0d"}}"#.into(),
            r#"{"data":{"A":1,"B":["T#1s"],"C":"\ud800"}}"#.into(),
            r#"{"data":{"A":1,"B":["T#1s"],"C":"x"},}"#.into(),
            r#"[1,40000,3]"#.into(),
            r#"[1,2,"x",4]"#.into(),
            deep("[", "]", 127),
            deep("[", "]", 128),
            deep("[", "]", 300),
            format!(r#"{{"data":{{"A":{}}}}}"#, deep("[", "]", 200)),
            format!(r#"{{"data":{{"A":{}}}}}"#, deep(r#"{"k":"#, "}", 126)),
            format!(r#"{{"data":{{"A":{}}}}}"#, deep(r#"{"k":"#, "}", 127)),
        ];
        payloads.push(format!("[{}]", vec!["1"; 70_000].join(",")));
        let mut bytes: Vec<Vec<u8>> = payloads.into_iter().map(String::into_bytes).collect();
        bytes.push(b"{\"data\":{\"A\":1,\"B\":[\"T#1s\"],\"C\":\"\xff\"}}".to_vec());
        bytes.push(b"{\"data\":{\"A\":1,\"B\":[\"T#1s\"],\"C\":\"\"}}\xff".to_vec());
        bytes.push(b"{\"data\xc3\x28\":1}".to_vec());
        bytes
    }

    #[test]
    fn streaming_decodes_exactly_as_the_tree_decoder() {
        let mut ports = ports();
        ports.extend(long_ports());
        let payloads = explicit_payloads()
            .into_iter()
            .chain(event_payloads(4_000))
            .chain(random_payloads(2_000))
            .chain(long_payloads(2_000));
        let (mut accepted, mut refused) = (0, 0);
        for payload in payloads {
            let text = String::from_utf8_lossy(&payload);
            for port in &ports {
                let streamed = json::decode_named(&payload, "P", port);
                assert_eq!(streamed, tree::decode_json(&payload, "P", port), "{text}");
                if streamed.is_ok() {
                    accepted += 1;
                } else {
                    refused += 1;
                }
                let streamed = dinasore::decode(&payload, "A", port);
                assert_eq!(
                    streamed,
                    tree::decode_dinasore(&payload, "A", port),
                    "{text}"
                );
                if streamed.is_ok() {
                    accepted += 1;
                }
            }
        }
        assert!(accepted > 500 && refused > 500, "{accepted} {refused}");
    }
}

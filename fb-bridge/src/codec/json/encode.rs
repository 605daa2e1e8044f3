//! Writing canonical JSON. Two encoders that must write the same text: [`encode`]
//! streams a message straight into bytes (the broker re-encodes every typed publication
//! with it), and [`value_to_json`] builds the `serde_json::Value` tree of one value (for
//! callers that want a tree, and as the reference the streaming writer is tested against).

use serde::{Serialize, Serializer};
use serde_json::{Number, Value as Json};

use super::iec;
use crate::codec::{EventMessage, Message};
use crate::interface::OutputPort;
use crate::types::DataType;
use crate::value::{Value, MS_PER_DAY};

/// Encodes a message for `port` in canonical JSON.
///
/// An event's `data` keys are written in WITH order. `port` only supplies those names; a
/// message that does not fit its port (which [`decode`](super::decode) never returns) is written as far
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

/// Writes a JSON object with its keys in the given order (`serde_json`'s map would sort
/// them), each value in its canonical form.
pub(crate) fn write_object<'a>(
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
pub(crate) fn with_names<'p>(port: &'p OutputPort<'_>) -> impl Iterator<Item = &'p str> {
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

#[cfg(test)]
mod tests {
    use super::super::decode;
    use super::super::tests::{data, samples};
    use super::*;
    use crate::types::ElementaryType as T;

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
}

//! DINASORE JSON, on topics `dinasore/<device>/<fb>/<port>`.
//!
//! DINASORE's MQTT publisher FB sends `{"<VALUE_NAME>": value}` and its subscriber reads
//! `json[VALUE_NAME]`, so every payload here is a JSON object keyed by data port names:
//!
//! - a **data port** `POSITION`: `{"POSITION": 3}`, that one key and no other;
//! - an **event port** with WITH `POSITION, SENSOR_IN`:
//!   `{"POSITION": 3, "SENSOR_IN": true}`, exactly its WITH names (`{}` for none).
//!
//! Values are written as in canonical JSON (see [`super::json`]). DINASORE has no place
//! for an event's `seq` and `ts`: they are absent after decoding (the broker stamps them)
//! and dropped when encoding.

use super::json::{decode_object, with_names, write_object};
use super::{CodecError, EventMessage, Message};
use crate::interface::OutputPort;

/// Decodes a DINASORE payload published on `port`, named `port_name`.
pub fn decode(
    payload: &[u8],
    port_name: &str,
    port: &OutputPort<'_>,
) -> Result<Message, CodecError> {
    let not_object = |got: &str| {
        CodecError::Malformed(format!(
            "a DINASORE payload is a JSON object keyed by data port names, got {got}"
        ))
    };
    match port {
        // A data port reads like an event carrying just that port.
        OutputPort::Data(ty) => {
            let mut values = decode_object(payload, &[(port_name, *ty)], not_object)?;
            Ok(Message::Data(values.remove(0)))
        }
        OutputPort::Event(with) => Ok(Message::Event(EventMessage {
            seq: None,
            ts_us: None,
            data: decode_object(payload, with, not_object)?,
        })),
    }
}

/// Encodes a message for `port`, named `port_name`, the way DINASORE writes it.
///
/// An event's keys follow WITH order; its `seq` and `ts` are dropped.
pub fn encode(message: &Message, port_name: &str, port: &OutputPort<'_>) -> Vec<u8> {
    let mut out = Vec::with_capacity(128);
    match message {
        Message::Data(value) => write_object(&mut out, [(port_name, value)]),
        Message::Event(event) => write_object(&mut out, with_names(port).zip(&event.data)),
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::codec::json::tests::{fuzz_ports, random_payloads, samples};
    use crate::types::{DataType, ElementaryType as T};
    use crate::value::{TypeError, Value};

    fn data_port(t: T) -> OutputPort<'static> {
        OutputPort::Data(DataType::Elementary(t))
    }

    fn text(bytes: &[u8]) -> String {
        String::from_utf8_lossy(bytes).into_owned()
    }

    #[test]
    fn bool_strings_one_and_zero_read_as_dinasore_writes_them() {
        // DINASORE's publisher writes str(value); with `string_numbers` the profile turns
        // "1"/"0" back into numbers, which a BOOL port reads as true/false (issue 35).
        let port = OutputPort::Event(vec![
            ("ON", DataType::Elementary(T::Bool)),
            ("OFF", DataType::Elementary(T::Bool)),
        ]);
        let payload =
            crate::profile::unstring_numbers(br#"{"ON": "1", "OFF": "0"}"#, "EV", &port).unwrap();
        let Ok(Message::Event(event)) = decode(&payload, "EV", &port) else {
            panic!("{}", text(&payload));
        };
        assert_eq!(event.data, vec![Value::Bool(true), Value::Bool(false)]);
        let payload =
            crate::profile::unstring_numbers(br#"{"ON": "2", "OFF": "0"}"#, "EV", &port).unwrap();
        assert!(matches!(
            decode(&payload, "EV", &port),
            Err(CodecError::Type { port, error: TypeError::OutOfRange { .. } }) if port == "ON"
        ));
    }

    #[test]
    fn every_elementary_type_and_array_round_trips() {
        for (t, cases) in samples() {
            let port = data_port(t);
            let mut values = Vec::new();
            for (value, canonical) in cases {
                let message = Message::Data(value.clone());
                let encoded = encode(&message, "OUT", &port);
                assert_eq!(text(&encoded), format!(r#"{{"OUT":{canonical}}}"#));
                assert_eq!(decode(&encoded, "OUT", &port), Ok(message), "{t}");
                values.push(value);
            }
            let port = OutputPort::Data(DataType::Array(t, values.len() as u16));
            let message = Message::Data(Value::Array(t, values));
            let encoded = encode(&message, "OUT", &port);
            assert_eq!(decode(&encoded, "OUT", &port), Ok(message), "{t}");
        }
    }

    #[test]
    fn events_are_objects_of_their_with_names_without_seq_or_ts() {
        let port = OutputPort::Event(vec![
            ("SENSOR_IN", DataType::Elementary(T::Bool)),
            ("POSITION", DataType::Elementary(T::Int)),
        ]);
        let stamped = Message::Event(EventMessage {
            seq: Some(3),
            ts_us: Some(4),
            data: vec![Value::Bool(true), Value::Int(-7)],
        });
        let encoded = encode(&stamped, "MOVED", &port);
        assert_eq!(text(&encoded), r#"{"SENSOR_IN":true,"POSITION":-7}"#);
        assert_eq!(
            decode(&encoded, "MOVED", &port),
            Ok(Message::Event(EventMessage {
                seq: None,
                ts_us: None,
                data: vec![Value::Bool(true), Value::Int(-7)],
            }))
        );

        let bare = OutputPort::Event(vec![]);
        let empty = Message::Event(EventMessage {
            seq: None,
            ts_us: None,
            data: vec![],
        });
        assert_eq!(encode(&empty, "TICK", &bare), b"{}");
        assert_eq!(decode(b"{}", "TICK", &bare), Ok(empty));
    }

    #[test]
    fn mistakes_name_the_missing_or_extra_key() {
        let port = data_port(T::Sint);
        assert_eq!(
            decode(br#"{"OTHER":1}"#, "OUT", &port),
            Err(CodecError::Missing("OUT".into()))
        );
        assert_eq!(
            decode(br#"{}"#, "OUT", &port),
            Err(CodecError::Missing("OUT".into()))
        );
        assert_eq!(
            decode(br#"{"OUT":1,"seq":2}"#, "OUT", &port),
            Err(CodecError::Unexpected("seq".into()))
        );
        assert_eq!(
            decode(br#"{"OUT":128}"#, "OUT", &port),
            Err(CodecError::Type {
                port: "OUT".into(),
                error: TypeError::OutOfRange {
                    ty: T::Sint,
                    value: "128".into()
                }
            })
        );
        let event = OutputPort::Event(vec![
            ("A", DataType::Elementary(T::Time)),
            ("B", DataType::Array(T::Bool, 2)),
        ]);
        assert_eq!(
            decode(br#"{"A":"T#1s"}"#, "E", &event),
            Err(CodecError::Missing("B".into()))
        );
        assert_eq!(
            decode(br#"{"A":"T#1s","B":[true,false],"C":0}"#, "E", &event),
            Err(CodecError::Unexpected("C".into()))
        );
        assert_eq!(
            decode(br#"{"A":"T#5x","B":[true,false]}"#, "E", &event),
            Err(CodecError::Type {
                port: "A".into(),
                error: TypeError::Mismatch {
                    expected: DataType::Elementary(T::Time),
                    got:
                        r#"the string "T#5x" (unknown unit "x": expected d, h, m, s, ms, us or ns)"#
                            .into()
                }
            })
        );
        assert!(matches!(
            decode(br#"{"A":"T#1s","B":[true]}"#, "E", &event),
            Err(CodecError::Type {
                error: TypeError::ArrayLength {
                    expected: 2,
                    got: 1
                },
                ..
            })
        ));
        // The canonical event shape is not DINASORE's.
        assert_eq!(
            decode(br#"{"data":{"A":"T#1s","B":[true,false]}}"#, "E", &event),
            Err(CodecError::Missing("A".into()))
        );
    }

    #[test]
    fn payloads_that_are_not_objects_are_malformed() {
        for bad in [
            &b"42"[..],
            b"[1]",
            b"\"OUT\"",
            b"null",
            b"{",
            b"",
            b"\xc3\x28",
        ] {
            assert!(
                matches!(
                    decode(bad, "OUT", &data_port(T::Int)),
                    Err(CodecError::Malformed(_))
                ),
                "{}",
                text(bad)
            );
        }
    }

    #[test]
    fn random_payloads_never_panic_and_accepted_ones_round_trip() {
        let ports = fuzz_ports();
        let mut accepted = 0;
        for fragment in random_payloads(2_000) {
            let mut wrapped = br#"{"A":"#.to_vec();
            wrapped.extend_from_slice(&fragment);
            wrapped.push(b'}');
            for (payload, port) in [fragment, wrapped]
                .iter()
                .flat_map(|p| ports.iter().map(move |port| (p, port)))
            {
                // Wrapped fragments reach the value decoders through the key "A".
                if let Ok(message) = decode(payload, "A", port) {
                    accepted += 1;
                    let again = encode(&message, "A", port);
                    assert_eq!(decode(&again, "A", port), Ok(message));
                }
            }
        }
        assert!(
            accepted > 0,
            "no random payload was valid: the generator is too weak"
        );
    }
}

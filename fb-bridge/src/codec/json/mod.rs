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
//! | `BOOL` | `true` / `false`, or the integers `1` / `0` (accepted on input, never written) | `true`, `1` |
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
//!
//! ## Where things are
//!
//! | file | concept |
//! |---|---|
//! | this one | the entry points: [`decode`], [`decode_named`], [`encode`] |
//! | `encode.rs` | writing canonical JSON: the streaming writer and the [`value_to_json`] tree, which must agree |
//! | `read.rs` | what one JSON value means as an IEC type ([`value_from_json`]), shared by both decoders |
//! | `iec.rs` | IEC 61131-3 literals (`T#`, `D#`, `TOD#`, `DT#`, `16#`): parsing and canonical formatting |
//! | `de.rs` | the streaming decoder: payload bytes straight into typed values |
//! | `tree.rs` | the reference decoder through a `serde_json::Value` tree (tests and fuzzing only) |

mod de;
mod encode;
mod iec;
mod read;
/// The tree-building reference the streaming decoder is checked against (tests, fuzzing).
#[cfg(any(test, feature = "reference-decoder"))]
#[doc(hidden)]
pub mod tree;

#[cfg(test)]
pub(crate) mod tests;

use super::{CodecError, Message};
use crate::interface::OutputPort;
use crate::types::DataType;
use crate::value::Value;

pub use encode::{encode, value_to_json};
pub(super) use encode::{with_names, write_object};
pub use read::value_from_json;

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

#[cfg(test)]
mod payload_tests {
    //! Whole payloads: the shape of events, what is not JSON, and random input.

    use super::tests::{data, fuzz_ports, random_payloads};
    use super::*;
    use crate::types::ElementaryType as T;
    use crate::value::TypeError;

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
    fn decode_named_names_the_data_port() {
        let port = data(DataType::Elementary(T::Bool));
        assert!(matches!(
            decode_named(b"2", "SENSOR_IN", &port),
            Err(CodecError::Type { port, .. }) if port == "SENSOR_IN"
        ));
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
}

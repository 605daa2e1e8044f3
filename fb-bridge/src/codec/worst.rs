//! The worst-case size of one message on a port, in each encoding: what a declaration
//! commits the broker to carry (issue 21: a 60 KB publication on an
//! `ARRAY [30000] OF TIME` went out as 240 KB on `fbdk/`).
//!
//! The rule (docs/device-contract.md, "Message sizes"):
//!
//! - every fixed-size type is counted at its **widest value**, encoded by the codecs
//!   themselves (`T#-106751990d23h59m59s999ms999us` for TIME in JSON, 9 bytes in `fbdk`, ...),
//!   so the figure is the bytes the broker would really write;
//! - an event's `seq` and `ts` are counted at their widest (20 digits each);
//! - a STRING or WSTRING is counted **empty**: its characters come from the publication
//!   that carries them, which is itself at most `max_packet_bytes`; a re-encoded copy
//!   that still grows past the limit (JSON escapes) is not delivered, per message;
//! - an array of `n` elements is the one-element message plus `n - 1` times the
//!   encoding's per-element size (every encoding is linear in the element count).

use super::{encode, fbdk::TimeUnit, Encoding, EventMessage, Message};
use crate::interface::OutputPort;
use crate::types::{DataType, ElementaryType as T};
use crate::value::{Value, MAX_DATE_AND_TIME_MS, MS_PER_DAY};

/// The widest value of an elementary type in any encoding (STRING: empty).
fn widest(t: T) -> Value {
    match t {
        T::Bool => Value::Bool(false),
        T::Sint => Value::Sint(i8::MIN),
        T::Int => Value::Int(i16::MIN),
        T::Dint => Value::Dint(i32::MIN),
        T::Lint => Value::Lint(i64::MIN),
        T::Usint => Value::Usint(u8::MAX),
        T::Uint => Value::Uint(u16::MAX),
        T::Udint => Value::Udint(u32::MAX),
        T::Ulint => Value::Ulint(u64::MAX),
        // The longest shortest-round-trip texts: 9 and 17 significant digits, sign and a
        // two- or three-digit negative exponent.
        T::Real => Value::Real(-1.175_494_3e-38),
        T::Lreal => Value::Lreal(-2.225_073_858_507_201_4e-308),
        T::Byte => Value::Byte(u8::MAX),
        T::Word => Value::Word(u16::MAX),
        T::Dword => Value::Dword(u32::MAX),
        T::Lword => Value::Lword(u64::MAX),
        T::String => Value::String(String::new()),
        T::WString => Value::WString(String::new()),
        // Every unit at its widest: `T#-106751990d23h59m59s999ms999us` (i64::MIN has
        // one-digit hours and no minutes).
        T::Time => Value::Time(-(106_751_990 * 86_400_000_000 + 86_399_999_999)),
        T::Date => Value::Date(MAX_DATE_AND_TIME_MS / MS_PER_DAY * MS_PER_DAY),
        T::TimeOfDay => Value::TimeOfDay(MS_PER_DAY - 1),
        T::DateAndTime => Value::DateAndTime(MAX_DATE_AND_TIME_MS),
    }
}

/// `ty` with `n` widest elements (arrays), or its widest value.
fn value(ty: DataType, n: usize) -> Value {
    match ty {
        DataType::Elementary(t) => widest(t),
        DataType::Array(t, _) => Value::Array(t, vec![widest(t); n]),
    }
}

fn size(encoding: Encoding, port_name: &str, port: &OutputPort<'_>, n: usize) -> usize {
    let message = match port {
        OutputPort::Data(ty) => Message::Data(value(*ty, n)),
        OutputPort::Event(with) => Message::Event(EventMessage {
            seq: Some(u64::MAX),
            ts_us: Some(u64::MAX),
            data: with.iter().map(|(_, ty)| value(*ty, n)).collect(),
        }),
    };
    // Milliseconds: every date the types hold is encodable (the size is the same in ns).
    encode(encoding, &message, port_name, port, TimeUnit::Milliseconds).map_or(0, |b| b.len())
}

/// The largest message a port can carry in `encoding`, in bytes, by the rule above.
pub fn worst_case_size(encoding: Encoding, port_name: &str, port: &OutputPort<'_>) -> usize {
    let one = size(encoding, port_name, port, 1);
    let extra: usize = port
        .value_types()
        .into_iter()
        .map(|ty| match ty {
            DataType::Array(t, n) => {
                let single = OutputPort::Data(DataType::Array(t, 1));
                let per = size(encoding, port_name, &single, 2)
                    .saturating_sub(size(encoding, port_name, &single, 1));
                per.saturating_mul(usize::from(n).saturating_sub(1))
            }
            DataType::Elementary(_) => 0,
        })
        .fold(0, usize::saturating_add);
    one.saturating_add(extra)
}

/// The encoding in which a port's messages are largest, and that size.
pub fn largest(port_name: &str, port: &OutputPort<'_>) -> (Encoding, usize) {
    Encoding::ALL
        .into_iter()
        .map(|e| (e, worst_case_size(e, port_name, port)))
        .max_by_key(|(_, size)| *size)
        .unwrap_or((Encoding::Json, 0))
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The formula for arrays agrees with encoding the whole widest array.
    #[test]
    fn arrays_are_counted_as_if_encoded_whole() {
        for t in T::ALL {
            let ty = DataType::Array(t, 300);
            let port = OutputPort::Data(ty);
            for e in Encoding::ALL {
                assert_eq!(
                    worst_case_size(e, "OUT", &port),
                    size(e, "OUT", &port, 300),
                    "{t} in {e:?}"
                );
            }
        }
    }

    /// Issue 21's case: ARRAY [30000] OF TIME is far over 64 KiB in every encoding.
    #[test]
    fn a_large_time_array_is_large_everywhere() {
        let port = OutputPort::Data(DataType::Array(T::Time, 30000));
        for e in Encoding::ALL {
            assert!(worst_case_size(e, "V", &port) > 200_000, "{e:?}");
        }
        assert!(largest("V", &port).1 >= worst_case_size(Encoding::Json, "V", &port));
        let small = OutputPort::Data(DataType::Elementary(T::Int));
        assert!(largest("SPEED", &small).1 < 32);
    }

    /// No candidate value of a type is wider than the one counted.
    #[test]
    fn the_widest_values_are_the_widest() {
        let others: Vec<(T, Value)> = vec![
            (T::Real, Value::Real(-f32::MAX)),
            (T::Real, Value::Real(-1.234_567_9e-30)),
            (T::Real, Value::Real(-f32::MIN_POSITIVE)),
            (T::Lreal, Value::Lreal(-f64::MAX)),
            (T::Lreal, Value::Lreal(-1.234_567_890_123_456_7e-300)),
            (T::Time, Value::Time(i64::MAX)),
            (T::Time, Value::Time(i64::MIN)),
            (
                T::Time,
                Value::Time(-86_399_999_999 - 106_750 * 86_400_000_000),
            ),
            (T::Lint, Value::Lint(i64::MAX)),
        ];
        for (t, v) in others {
            let port = OutputPort::Data(DataType::Elementary(t));
            for e in Encoding::ALL {
                let other = encode(
                    e,
                    &Message::Data(v.clone()),
                    "P",
                    &port,
                    TimeUnit::Milliseconds,
                )
                .unwrap()
                .len();
                let counted = worst_case_size(e, "P", &port);
                assert!(other <= counted, "{v:?} in {e:?}: {other} > {counted}");
            }
        }
    }
}

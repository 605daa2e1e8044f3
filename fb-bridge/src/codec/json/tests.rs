//! Test support shared by the JSON tests and the DINASORE ones: sample values with
//! their canonical text, decoding helpers, and deterministic random input.

use super::decode;
use crate::codec::{CodecError, Message};
use crate::interface::OutputPort;
use crate::types::{DataType, ElementaryType};
use crate::value::{TypeError, Value, MS_PER_DAY};
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

pub(crate) fn data(ty: DataType) -> OutputPort<'static> {
    OutputPort::Data(ty)
}

pub(crate) fn decode_text(text: &str, ty: DataType) -> Result<Message, CodecError> {
    decode(text.as_bytes(), &data(ty))
}

/// The [`TypeError`] of decoding `text` on a data port of type `ty`.
pub(crate) fn type_error(text: &str, ty: impl Into<Ty>) -> TypeError {
    match decode_text(text, ty.into().0) {
        Err(CodecError::Type { port, error }) => {
            assert_eq!(port, "");
            error
        }
        other => panic!("{text}: expected a type error, got {other:?}"),
    }
}

/// Lets tests write `T::Int` or a `DataType`.
pub(crate) struct Ty(pub(crate) DataType);

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

pub(crate) fn decoded(text: &str, t: ElementaryType) -> Value {
    match decode_text(text, DataType::Elementary(t)) {
        Ok(Message::Data(v)) => v,
        other => panic!("{text}: {other:?}"),
    }
}

pub(crate) fn out_of_range(ty: ElementaryType, value: &str) -> TypeError {
    TypeError::OutOfRange {
        ty,
        value: value.into(),
    }
}

pub(crate) fn is_mismatch(e: &TypeError) -> bool {
    matches!(e, TypeError::Mismatch { .. })
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

use super::*;
use crate::value::MS_PER_DAY;
use ElementaryType as T;

fn el(t: ElementaryType) -> DataType {
    DataType::Elementary(t)
}

const NS: TimeUnit = TimeUnit::Nanoseconds;
const MS: TimeUnit = TimeUnit::Milliseconds;
const UNITS: [TimeUnit; 2] = [NS, MS];

/// Whether the wire unit matters for values of `ty`.
fn is_dated(ty: DataType) -> bool {
    let t = match ty {
        DataType::Elementary(t) | DataType::Array(t, _) => t,
    };
    matches!(t, T::Date | T::TimeOfDay | T::DateAndTime)
}

/// Decodes `bytes` in `unit` as one value of `ty`, asserts it is `value`, and that
/// encoding `value` in `unit` gives `bytes` back.
fn assert_wire_in(unit: TimeUnit, bytes: &[u8], ty: DataType, value: Value) {
    assert_eq!(
        decode(bytes, &OutputPort::Data(ty), unit),
        Ok(Message::Data(value.clone())),
        "decoding {bytes:02x?} as {ty} in {unit:?}"
    );
    assert_eq!(
        encode(&Message::Data(value.clone()), &OutputPort::Data(ty), unit),
        Ok(bytes.to_vec()),
        "encoding {value:?} in {unit:?}"
    );
}

/// [`assert_wire_in`] in both units, for a type the unit does not concern.
fn assert_wire(bytes: &[u8], ty: DataType, value: Value) {
    assert!(!is_dated(ty), "{ty}: say which unit");
    for unit in UNITS {
        assert_wire_in(unit, bytes, ty, value.clone());
    }
}

/// An 8-byte DATE, TIME_OF_DAY or DATE_AND_TIME (`tag`) on the wire.
fn dated(tag: u8, raw: u64) -> Vec<u8> {
    let mut bytes = vec![tag];
    bytes.extend(raw.to_be_bytes());
    bytes
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
    // FORTE 2.x: 1970-01-02 is 86,400,000 ms = 0x05265C00.
    assert_wire_in(
        MS,
        &[0x4D, 0, 0, 0, 0, 0x05, 0x26, 0x5C, 0x00],
        el(T::Date),
        Value::Date(MS_PER_DAY),
    );
    assert_wire_in(
        MS,
        &[0x4E, 0, 0, 0, 0, 0, 0, 0x03, 0xE8],
        el(T::TimeOfDay),
        Value::TimeOfDay(1000),
    );
    assert_wire_in(
        MS,
        &[0x4F, 0, 0, 0, 0, 0, 0, 0, 0x2A],
        el(T::DateAndTime),
        Value::DateAndTime(42),
    );
    // FORTE 3.x: 1970-01-02 is 86,400,000,000,000 ns = 0x4E94914F0000.
    assert_wire_in(
        NS,
        &[0x4D, 0, 0, 0x4E, 0x94, 0x91, 0x4F, 0x00, 0x00],
        el(T::Date),
        Value::Date(MS_PER_DAY),
    );
    // One second: 1,000,000,000 ns = 0x3B9ACA00.
    assert_wire_in(
        NS,
        &[0x4E, 0, 0, 0, 0, 0x3B, 0x9A, 0xCA, 0x00],
        el(T::TimeOfDay),
        Value::TimeOfDay(1000),
    );
    // 42 ms: 42,000,000 ns = 0x0280DE80.
    assert_wire_in(
        NS,
        &[0x4F, 0, 0, 0, 0, 0x02, 0x80, 0xDE, 0x80],
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
    assert_eq!(decode(&bytes, &port, MS), Ok(message.clone()));
    assert_eq!(encode(&message, &port, MS).unwrap(), bytes);
    // seq and ts_us have no place on the wire.
    let stamped = Message::Event(EventMessage {
        seq: Some(9),
        ts_us: Some(1),
        data: vec![Value::Int(-2), Value::Bool(true)],
    });
    assert_eq!(encode(&stamped, &port, MS).unwrap(), bytes);
}

#[test]
fn an_event_without_data_is_0x05() {
    let port = OutputPort::Event(vec![]);
    let empty = Message::Event(EventMessage {
        seq: None,
        ts_us: None,
        data: vec![],
    });
    assert_eq!(decode(&[0x05], &port, MS), Ok(empty.clone()));
    assert_eq!(decode(&[], &port, MS), Ok(empty.clone()));
    assert_eq!(encode(&empty, &port, MS).unwrap(), [0x05]);
    assert_eq!(
        decode(&[0x05, 0x00], &port, MS),
        Err(CodecError::Trailing(1))
    );
    assert_eq!(decode(&[0x41], &port, MS), Err(CodecError::Trailing(1)));
    assert_eq!(encode_values(&[], MS).unwrap(), [0x05]);
    assert_eq!(decode_values(&[0x05], &[], MS), Ok(vec![]));
}

#[test]
fn strings_that_are_not_utf8_are_latin1() {
    assert_wire(
        &[0x50, 0x00, 0x00],
        el(T::String),
        Value::String(String::new()),
    );
    assert_eq!(
        decode_values(&[0x50, 0x00, 0x02, 0xE9, 0x41], &[el(T::String)], MS),
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
        decode_values(&long, &[el(T::String)], MS),
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
            crate::value::MAX_DATE_AND_TIME_MS - crate::value::MAX_DATE_AND_TIME_MS % MS_PER_DAY,
        ),
        Value::TimeOfDay(0),
        Value::TimeOfDay(MS_PER_DAY - 1),
        Value::DateAndTime(0),
        Value::DateAndTime(crate::value::MAX_DATE_AND_TIME_MS),
        // The last ones 64-bit nanoseconds hold (FORTE 3.x).
        Value::Date(LAST_NS_MS - LAST_NS_MS % MS_PER_DAY),
        Value::DateAndTime(LAST_NS_MS),
    ]
}

/// One array per elementary type, holding every sample of that type.
fn array_samples() -> Vec<Value> {
    array_samples_in(MS)
}

/// One array per elementary type, holding every sample of that type `unit` can write.
fn array_samples_in(unit: TimeUnit) -> Vec<Value> {
    ElementaryType::ALL
        .into_iter()
        .map(|t| {
            let items = samples()
                .into_iter()
                .filter(|v| v.elementary_type() == t)
                .collect();
            Value::Array(t, writable_in(unit, items))
        })
        .collect()
}

/// The last DATE_AND_TIME (in ms) whose nanoseconds fit 64 bits: 2554-07-21-23:34:33.709.
const LAST_NS_MS: u64 = u64::MAX / 1_000_000;

/// Whether `value` can be written in nanoseconds (every value can in milliseconds).
fn fits_ns(value: &Value) -> bool {
    match value {
        Value::Date(ms) | Value::DateAndTime(ms) => *ms <= LAST_NS_MS,
        Value::Array(_, items) => items.iter().all(fits_ns),
        _ => true,
    }
}

/// `values` without what cannot be written in `unit` (array elements included).
fn writable_in(unit: TimeUnit, values: Vec<Value>) -> Vec<Value> {
    if unit == MS {
        return values;
    }
    values.into_iter().filter(fits_ns).collect()
}

fn assert_round_trip(value: &Value, unit: TimeUnit) {
    let ty = value.data_type();
    let bytes = encode_values(std::slice::from_ref(value), unit).unwrap();
    assert_eq!(
        decode_values(&bytes, &[ty], unit),
        Ok(vec![value.clone()]),
        "{ty} in {unit:?}"
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
    for unit in UNITS {
        let values = writable_in(
            unit,
            samples()
                .into_iter()
                .chain(array_samples_in(unit))
                .collect(),
        );
        for value in &values {
            assert_round_trip(value, unit);
        }
        assert_round_trip(
            &Value::Array(T::Lint, vec![Value::Lint(0); MAX_ARRAY_LEN]),
            unit,
        );
        // All of them in one message, as an event and as SD_1..SD_n.
        let types: Vec<DataType> = values.iter().map(Value::data_type).collect();
        let bytes = encode_values(&values, unit).unwrap();
        assert_eq!(decode_values(&bytes, &types, unit), Ok(values.clone()));
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
        assert_eq!(
            decode(&encode(&message, &port, unit).unwrap(), &port, unit),
            Ok(message)
        );
    }
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
        Value::DateAndTime(1_795_350_615_250),
    ];
    let types: Vec<DataType> = values.iter().map(Value::data_type).collect();
    for unit in UNITS {
        let bytes = encode_values(&values, unit).unwrap();
        for len in 0..bytes.len() {
            match decode_values(&bytes[..len], &types, unit) {
                Err(CodecError::Truncated { offset, needed }) => {
                    assert!(
                        offset <= len && needed > 0,
                        "prefix {len}: {offset} {needed}"
                    );
                    assert!(offset + needed <= bytes.len(), "prefix {len}");
                }
                other => panic!("prefix of {len} bytes in {unit:?}: {other:?}"),
            }
        }
        assert_eq!(decode_values(&bytes, &types, unit), Ok(values.clone()));
    }
    assert_eq!(
        decode(&[0x43, 0x00], &OutputPort::Data(el(T::Int)), MS),
        Err(CodecError::Truncated {
            offset: 1,
            needed: 1
        })
    );
    assert_eq!(
        decode(&[], &OutputPort::Data(el(T::Bool)), MS),
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
        decode_values(&[0x44, 0, 0, 0, 1], &[el(T::Int)], MS),
        tag(0, 0x44, "INT")
    );
    assert_eq!(
        decode_values(&[0x42], &[el(T::Bool)], MS),
        tag(0, 0x42, "BOOL")
    );
    // FALSE's tag is not INT's.
    assert_eq!(
        decode_values(&[0x40], &[el(T::Int)], MS),
        tag(0, 0x40, "INT")
    );
    assert_eq!(
        decode_values(&[0x41, 0x43, 0, 1], &[el(T::Bool), el(T::Dint)], MS),
        tag(1, 0x43, "DINT")
    );
    let array = DataType::Array(T::Int, 2);
    assert_eq!(
        decode_values(&[0x43, 0, 1], &[array], MS),
        tag(0, 0x43, "ARRAY [2] OF INT")
    );
    assert_eq!(
        decode_values(&[0x76, 0, 2, 0x44, 0, 1, 0, 2], &[array], MS),
        tag(3, 0x44, "INT")
    );
    assert_eq!(
        decode_values(
            &[0x76, 0, 2, 0x41, 0x43],
            &[DataType::Array(T::Bool, 2)],
            MS
        ),
        tag(4, 0x43, "BOOL")
    );
    // A scalar port does not take an array.
    assert_eq!(
        decode_values(&[0x76, 0, 1, 0x43, 0, 1], &[el(T::Int)], MS),
        tag(0, 0x76, "INT")
    );
}

#[test]
fn trailing_bytes_are_refused() {
    assert_eq!(
        decode(&[0x43, 0, 1, 0x00], &OutputPort::Data(el(T::Int)), MS),
        Err(CodecError::Trailing(1))
    );
    assert_eq!(
        decode_values(&[0x41, 0x40, 0x41], &[el(T::Bool), el(T::Bool)], MS),
        Err(CodecError::Trailing(1))
    );
}

#[test]
fn array_counts_must_match_the_declaration() {
    assert_eq!(
        decode_values(
            &[0x76, 0, 2, 0x43, 0, 1, 0, 2],
            &[DataType::Array(T::Int, 3)],
            MS
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
            &[DataType::Array(T::Int, 3)],
            MS
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
        decode_values(&[0x76, 0xFF, 0xFF, 0x45, 0, 0, 0], &[ty], MS),
        Err(CodecError::Truncated {
            offset: 4,
            needed: 5
        })
    );
    let ty = DataType::Array(T::Bool, u16::MAX);
    assert_eq!(
        decode_values(&[0x76, 0xFF, 0xFF], &[ty], MS),
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
                decode_values(&bytes, &[el(T::WString)], MS),
                Err(CodecError::Malformed(_))
            ),
            "{bytes:02x?}"
        );
    }
    assert!(matches!(
        decode_values(&[0x55, 0x00, 0x01, 0xD8, 0x34], &[el(T::WString)], MS),
        Err(CodecError::Malformed(_))
    ));
}

#[test]
fn values_out_of_range_are_type_errors_named_after_the_port() {
    let nan = [0x4A, 0x7F, 0xC0, 0x00, 0x00];
    assert!(matches!(
        decode(&nan, &OutputPort::Data(el(T::Real)), MS),
        Err(CodecError::Type { port, error: TypeError::OutOfRange { .. } }) if port == DATA_PORT_NAME
    ));
    let port = OutputPort::Event(vec![("POS", el(T::Int)), ("AT", el(T::TimeOfDay))]);
    let mut bytes = vec![0x43, 0, 1, 0x4E];
    bytes.extend(MS_PER_DAY.to_be_bytes());
    assert!(matches!(
        decode(&bytes, &port, MS),
        Err(CodecError::Type { port, error: TypeError::OutOfRange { .. } }) if port == "AT"
    ));
    assert!(matches!(
        decode_values(&[0x41, 0x4D, 0, 0, 0, 0, 0, 0, 0, 1], &[el(T::Bool), el(T::Date)], MS),
        Err(CodecError::Type { port, .. }) if port == "SD_2"
    ));
    let mut inf_element = vec![0x76, 0, 2, 0x4B];
    inf_element.extend(0.0f64.to_be_bytes());
    inf_element.extend(f64::INFINITY.to_be_bytes());
    assert!(matches!(
        decode_values(&inf_element, &[DataType::Array(T::Lreal, 2)], MS),
        Err(CodecError::Type {
            error: TypeError::Element { index: 1, .. },
            ..
        })
    ));
}

/// DT#2026-11-22-12:30:15.250 in milliseconds since the epoch.
const DT_MS: u64 = 1_795_350_615_250;

#[test]
fn forte_3_sends_dates_and_times_in_nanoseconds() {
    // The issue's example as FORTE 3.x writes it: 1,795,350,615,250,000,000 ns.
    let dt = [0x4F, 0x18, 0xEA, 0x5D, 0xDF, 0x55, 0x41, 0x58, 0x80];
    assert_eq!(dated(0x4F, DT_MS * 1_000_000), dt);
    assert_wire_in(NS, &dt, el(T::DateAndTime), Value::DateAndTime(DT_MS));
    // TOD#12:30:15.250 and D#2026-11-22.
    let tod_ms = DT_MS % MS_PER_DAY;
    assert_eq!(tod_ms, 45_015_250);
    assert_wire_in(
        NS,
        &dated(0x4E, 45_015_250_000_000),
        el(T::TimeOfDay),
        Value::TimeOfDay(tod_ms),
    );
    let day_ms = DT_MS - tod_ms;
    assert_wire_in(
        NS,
        &dated(0x4D, day_ms * 1_000_000),
        el(T::Date),
        Value::Date(day_ms),
    );
    // The same value in FORTE 2.x's milliseconds.
    assert_wire_in(
        MS,
        &dated(0x4F, DT_MS),
        el(T::DateAndTime),
        Value::DateAndTime(DT_MS),
    );

    // The wrong unit: FORTE 3.x's nanoseconds read as milliseconds are after 9999 and
    // refused; milliseconds read as nanoseconds are the issue's misreading, the first
    // half hour of 1970 (DT#1970-01-01-00:29:55.350).
    assert!(matches!(
        decode(&dt, &OutputPort::Data(el(T::DateAndTime)), MS),
        Err(CodecError::Type {
            error: TypeError::OutOfRange { .. },
            ..
        })
    ));
    assert_eq!(
        decode(
            &dated(0x4F, DT_MS),
            &OutputPort::Data(el(T::DateAndTime)),
            NS
        ),
        Ok(Message::Data(Value::DateAndTime(1_795_350)))
    );
    assert_eq!(TimeUnit::default(), NS);
}

#[test]
fn sub_millisecond_nanoseconds_are_truncated_to_the_millisecond() {
    let port = |t| OutputPort::Data(el(t));
    let data = |v| Ok(Message::Data(v));
    // DT#2026-11-22-12:30:15.250999999 reads as .250, and writes back as .250000000.
    let ns = DT_MS * 1_000_000 + 999_999;
    assert_eq!(
        decode(&dated(0x4F, ns), &port(T::DateAndTime), NS),
        data(Value::DateAndTime(DT_MS))
    );
    assert_eq!(
        encode_values(&[Value::DateAndTime(DT_MS)], NS),
        Ok(dated(0x4F, DT_MS * 1_000_000))
    );
    assert_eq!(
        decode(&dated(0x4F, 1), &port(T::DateAndTime), NS),
        data(Value::DateAndTime(0))
    );
    // The last nanosecond of a day is the last millisecond of it.
    assert_eq!(
        decode(&dated(0x4E, 86_399_999_999_999), &port(T::TimeOfDay), NS),
        data(Value::TimeOfDay(MS_PER_DAY - 1))
    );
    assert_eq!(
        decode(&dated(0x4E, 999_999), &port(T::TimeOfDay), NS),
        data(Value::TimeOfDay(0))
    );
    // The last nanosecond 64 bits hold: DT#2554-07-21-23:34:33.709551615.
    assert_eq!(
        decode(&dated(0x4F, u64::MAX), &port(T::DateAndTime), NS),
        data(Value::DateAndTime(LAST_NS_MS))
    );
    // Elements of an array, and WITH values of an event, the same way.
    let mut bytes = vec![0x76, 0, 2, 0x4E];
    bytes.extend(1_000_000_001u64.to_be_bytes());
    bytes.extend(2_999_999u64.to_be_bytes());
    assert_eq!(
        decode(
            &bytes,
            &OutputPort::Data(DataType::Array(T::TimeOfDay, 2)),
            NS
        ),
        data(Value::Array(
            T::TimeOfDay,
            vec![Value::TimeOfDay(1_000), Value::TimeOfDay(2)]
        ))
    );
    let event = OutputPort::Event(vec![("POS", el(T::Int)), ("AT", el(T::DateAndTime))]);
    let mut bytes = vec![0x43, 0, 7];
    bytes.extend(dated(0x4F, ns));
    assert_eq!(
        decode(&bytes, &event, NS),
        Ok(Message::Event(EventMessage {
            seq: None,
            ts_us: None,
            data: vec![Value::Int(7), Value::DateAndTime(DT_MS)],
        }))
    );
    // Milliseconds are exact: there is nothing below them on the wire.
    assert_eq!(
        decode(&dated(0x4F, DT_MS + 1), &port(T::DateAndTime), MS),
        data(Value::DateAndTime(DT_MS + 1))
    );
}

#[test]
fn a_date_off_midnight_or_a_time_of_day_past_it_is_refused_in_nanoseconds() {
    let refused = |bytes: &[u8], ty: DataType, unit: TimeUnit| -> String {
        match decode(bytes, &OutputPort::Data(ty), unit) {
            Err(CodecError::Type { port, error }) => {
                assert_eq!(port, DATA_PORT_NAME);
                error.to_string()
            }
            other => panic!("{bytes:02x?} as {ty} in {unit:?}: {other:?}"),
        }
    };
    let day_ns = MS_PER_DAY * 1_000_000;
    // A nanosecond, or a millisecond, past midnight is no DATE.
    for off in [1, 1_000_000] {
        let e = refused(&dated(0x4D, day_ns + off), el(T::Date), NS);
        assert!(
            e.contains(&format!("{} ns (not midnight)", day_ns + off)),
            "{e}"
        );
    }
    assert!(refused(&dated(0x4D, 1), el(T::Date), MS).contains("not midnight"));
    // A TIME_OF_DAY of a day or more, reported in the nanoseconds that came.
    for ns in [day_ns, day_ns + 5, u64::MAX] {
        let e = refused(&dated(0x4E, ns), el(T::TimeOfDay), NS);
        assert!(e.contains(&format!("{ns} ns")), "{e}");
    }
    // In an array, the element is named.
    let mut bytes = vec![0x76, 0, 2, 0x4D];
    bytes.extend(0u64.to_be_bytes());
    bytes.extend((day_ns + 1).to_be_bytes());
    assert!(matches!(
        decode(&bytes, &OutputPort::Data(DataType::Array(T::Date, 2)), NS),
        Err(CodecError::Type {
            error: TypeError::Element { index: 1, .. },
            ..
        })
    ));
}

#[test]
fn dates_after_2554_do_not_fit_nanoseconds_and_are_refused_not_wrapped() {
    let last = Value::DateAndTime(LAST_NS_MS);
    assert_eq!(
        encode_values(std::slice::from_ref(&last), NS),
        Ok(dated(0x4F, LAST_NS_MS * 1_000_000))
    );
    let after = [
        Value::DateAndTime(LAST_NS_MS + 1),
        Value::DateAndTime(crate::value::MAX_DATE_AND_TIME_MS),
        Value::Date(LAST_NS_MS - LAST_NS_MS % MS_PER_DAY + MS_PER_DAY),
        Value::DateAndTime(u64::MAX),
        // Not a valid TIME_OF_DAY, but encoding must not panic on it either.
        Value::TimeOfDay(u64::MAX),
    ];
    for value in &after {
        let ty = value.elementary_type();
        match encode_values(&[Value::Bool(true), value.clone()], NS) {
            Err(CodecError::Type {
                port,
                error:
                    TypeError::OutOfRange {
                        ty: got,
                        value: text,
                    },
            }) => {
                assert_eq!((port.as_str(), got), ("SD_2", ty));
                assert!(text.contains("DT#2554-07-21-23:34:33.709"), "{text}");
            }
            other => panic!("{value:?}: {other:?}"),
        }
        // Milliseconds hold them all.
        let mut expected = vec![0x41];
        expected.extend(dated(
            0x40 | ty.number(),
            match value {
                Value::Date(ms) | Value::TimeOfDay(ms) | Value::DateAndTime(ms) => *ms,
                _ => unreachable!(),
            },
        ));
        assert_eq!(
            encode_values(&[Value::Bool(true), value.clone()], MS),
            Ok(expected)
        );
    }
    let e = encode_values(
        &[Value::Date(
            crate::value::MAX_DATE_AND_TIME_MS - crate::value::MAX_DATE_AND_TIME_MS % MS_PER_DAY,
        )],
        NS,
    )
    .unwrap_err()
    .to_string();
    assert!(e.starts_with("SD_1: D#9999-12-31 ("), "{e}");
    // The largest TIME_OF_DAY fits.
    assert!(encode_values(&[Value::TimeOfDay(MS_PER_DAY - 1)], NS).is_ok());
    // Named after the WITH port, the data port, the array element.
    let event = OutputPort::Event(vec![("POS", el(T::Int)), ("AT", el(T::DateAndTime))]);
    let message = Message::Event(EventMessage {
        seq: None,
        ts_us: None,
        data: vec![Value::Int(1), Value::DateAndTime(LAST_NS_MS + 1)],
    });
    assert!(
        matches!(encode(&message, &event, NS), Err(CodecError::Type { port, .. }) if port == "AT")
    );
    assert!(encode(&message, &event, MS).is_ok());
    let data = OutputPort::Data(el(T::DateAndTime));
    let message = Message::Data(Value::DateAndTime(LAST_NS_MS + 1));
    assert!(
        matches!(encode(&message, &data, NS), Err(CodecError::Type { port, .. }) if port == DATA_PORT_NAME)
    );
    let array = Value::Array(
        T::Date,
        vec![Value::Date(0), Value::Date(MS_PER_DAY * 300_000)],
    );
    assert!(matches!(
        encode_values(&[array], NS),
        Err(CodecError::Type {
            error: TypeError::Element { index: 1, .. },
            ..
        })
    ));
}

#[test]
fn time_units_are_named_ns_and_ms() {
    let unit = |text: &str| serde_json::from_str::<TimeUnit>(text).map_err(|e| e.to_string());
    assert_eq!(unit(r#""ns""#), Ok(NS));
    assert_eq!(unit(r#""ms""#), Ok(MS));
    assert!(unit(r#""us""#)
        .unwrap_err()
        .contains("expected `ns` or `ms`"));
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
        OutputPort::Data(el(T::DateAndTime)),
        OutputPort::Data(el(T::Date)),
        OutputPort::Data(DataType::Array(T::DateAndTime, 2)),
    ];
    // Valid messages to mutate, so the noise also reaches past the first tag.
    let seeds: Vec<Vec<u8>> = array_samples()
        .iter()
        .chain(&samples()[..20])
        .map(|v| encode_values(std::slice::from_ref(v), MS).unwrap())
        .chain([dated(0x4F, 1_795_350_615_250_123_456), dated(0x4D, 0)])
        .collect();
    // Bytes that are tags or small lengths more often than chance would make them.
    let interesting = [
        0x00, 0x01, 0x05, 0x40, 0x41, 0x43, 0x4D, 0x4E, 0x4F, 0x50, 0x55, 0x76, 0xD8, 0xFF,
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
        for (shape, unit) in shapes.iter().flat_map(|s| UNITS.map(|u| (s, u))) {
            if let Ok(message) = decode(&bytes, shape, unit) {
                accepted += 1;
                // Whatever is accepted re-encodes to something accepted the same way, in
                // its own unit and in the other one when it fits there.
                for to in UNITS {
                    match encode(&message, shape, to) {
                        Ok(again) => assert_eq!(decode(&again, shape, to), Ok(message.clone())),
                        Err(e) => {
                            assert_eq!(to, NS, "{e}");
                            assert_ne!(unit, NS, "{e}");
                        }
                    }
                }
            }
        }
    }
    // The mutated seeds keep some inputs valid, so the accepting paths are exercised too.
    assert!(accepted > 50, "only {accepted} inputs decoded");
}

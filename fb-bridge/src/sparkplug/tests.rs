use prost::Message as _;

use super::*;
use crate::value::{MAX_DATE_AND_TIME_MS, MAX_STRING_LEN, MS_PER_DAY};
use ElementaryType as T;

fn scalar_ty(t: ElementaryType) -> DataType {
    DataType::Elementary(t)
}

/// `value` through `metric_value` and back through `value_of`, with and without the
/// datatype, as the port type of the value itself.
fn round_trip(value: &Value) -> Value {
    let ty = value.data_type();
    let encoded = metric_value(value);
    let back = value_of(ty, Some(datatype(ty) as u32), Some(&encoded))
        .unwrap_or_else(|e| panic!("{value:?} as {ty}: {e}"));
    assert_eq!(value_of(ty, None, Some(&encoded)), Ok(back.clone()));
    back
}

/// A few values of each elementary type: its extremes, zero, -1 where signed.
fn samples(t: ElementaryType) -> Vec<Value> {
    match t {
        T::Bool => vec![Value::Bool(false), Value::Bool(true)],
        T::Sint => [i8::MIN, -1, 0, 1, i8::MAX].map(Value::Sint).to_vec(),
        T::Int => [i16::MIN, -1, 0, 1, i16::MAX].map(Value::Int).to_vec(),
        T::Dint => [i32::MIN, -1, 0, 1, i32::MAX].map(Value::Dint).to_vec(),
        T::Lint => [i64::MIN, -1, 0, 1, i64::MAX].map(Value::Lint).to_vec(),
        T::Usint => [0, 1, u8::MAX].map(Value::Usint).to_vec(),
        T::Byte => [0, 0x5A, u8::MAX].map(Value::Byte).to_vec(),
        T::Uint => [0, 1, u16::MAX].map(Value::Uint).to_vec(),
        T::Word => [0, 0xA55A, u16::MAX].map(Value::Word).to_vec(),
        T::Udint => [0, 1, u32::MAX].map(Value::Udint).to_vec(),
        T::Dword => [0, 0xDEAD_BEEF, u32::MAX].map(Value::Dword).to_vec(),
        T::Ulint => [0, 1, u64::MAX].map(Value::Ulint).to_vec(),
        T::Lword => [0, 0xDEAD_BEEF_0BAD_F00D, u64::MAX]
            .map(Value::Lword)
            .to_vec(),
        T::Real => [f32::MIN, -1.5, -0.0, 0.0, f32::MIN_POSITIVE, f32::MAX]
            .map(Value::Real)
            .to_vec(),
        T::Lreal => [f64::MIN, -4.5e300, -0.0, 0.0, 1e-308, f64::MAX]
            .map(Value::Lreal)
            .to_vec(),
        T::Time => [i64::MIN, -1, 0, 1, i64::MAX].map(Value::Time).to_vec(),
        T::Date => [0, MS_PER_DAY, MAX_DATE_AND_TIME_MS + 1 - MS_PER_DAY]
            .map(Value::Date)
            .to_vec(),
        T::TimeOfDay => [0, 1, MS_PER_DAY - 1].map(Value::TimeOfDay).to_vec(),
        T::DateAndTime => [0, 1_700_000_000_123, MAX_DATE_AND_TIME_MS]
            .map(Value::DateAndTime)
            .to_vec(),
        T::String => vec![
            Value::String(String::new()),
            Value::String("Förderband 1".into()),
            Value::String("x".repeat(MAX_STRING_LEN)),
        ],
        T::WString => vec![
            Value::WString(String::new()),
            Value::WString("日本/ライン 🏭".into()),
            Value::WString("ü".repeat(MAX_STRING_LEN)),
        ],
    }
}

#[test]
fn datatypes_follow_the_table() {
    use SpType as S;
    let table = [
        (T::Bool, S::Boolean, S::BooleanArray),
        (T::Sint, S::Int8, S::Int8Array),
        (T::Int, S::Int16, S::Int16Array),
        (T::Dint, S::Int32, S::Int32Array),
        (T::Lint, S::Int64, S::Int64Array),
        (T::Usint, S::UInt8, S::UInt8Array),
        (T::Byte, S::UInt8, S::UInt8Array),
        (T::Uint, S::UInt16, S::UInt16Array),
        (T::Word, S::UInt16, S::UInt16Array),
        (T::Udint, S::UInt32, S::UInt32Array),
        (T::Dword, S::UInt32, S::UInt32Array),
        (T::Ulint, S::UInt64, S::UInt64Array),
        (T::Lword, S::UInt64, S::UInt64Array),
        (T::Real, S::Float, S::FloatArray),
        (T::Lreal, S::Double, S::DoubleArray),
        (T::String, S::String, S::StringArray),
        (T::WString, S::String, S::StringArray),
        (T::Time, S::Int64, S::Int64Array),
        (T::Date, S::DateTime, S::DateTimeArray),
        (T::DateAndTime, S::DateTime, S::DateTimeArray),
        (T::TimeOfDay, S::UInt32, S::UInt32Array),
    ];
    assert_eq!(table.len(), ElementaryType::ALL.len());
    for (t, scalar, array) in table {
        assert_eq!(datatype(scalar_ty(t)), scalar, "{t}");
        assert_eq!(datatype(DataType::Array(t, 3)), array, "ARRAY OF {t}");
    }
    // The numbers hosts see (Sparkplug 3.0, 6.4.16).
    assert_eq!(datatype(scalar_ty(T::Int)) as u32, 2);
    assert_eq!(datatype(DataType::Array(T::DateAndTime, 1)) as u32, 34);
}

#[test]
fn every_elementary_type_round_trips_at_its_extremes() {
    for t in ElementaryType::ALL {
        for value in samples(t) {
            let back = round_trip(&value);
            // Bit for bit: -0.0 stays -0.0.
            match (&value, &back) {
                (Value::Real(a), Value::Real(b)) => assert_eq!(a.to_bits(), b.to_bits()),
                (Value::Lreal(a), Value::Lreal(b)) => assert_eq!(a.to_bits(), b.to_bits()),
                _ => assert_eq!(back, value),
            }
        }
    }
}

#[test]
fn arrays_of_every_element_type_round_trip() {
    for t in ElementaryType::ALL {
        let items = samples(t);
        let value = Value::Array(t, items.clone());
        assert_eq!(round_trip(&value), value, "ARRAY OF {t}");
        // One element, and more than one byte of booleans.
        let one = Value::Array(t, items[..1].to_vec());
        assert_eq!(round_trip(&one), one, "ARRAY [1] OF {t}");
        let many: Vec<Value> = items.iter().cycle().take(19).cloned().collect();
        let many = Value::Array(t, many);
        assert_eq!(round_trip(&many), many, "ARRAY [19] OF {t}");
    }
}

fn bytes_of(value: &Value) -> Vec<u8> {
    match metric_value(value) {
        MetricValue::BytesValue(b) => b,
        other => panic!("{value:?} in {}", field_name(&other)),
    }
}

#[test]
fn array_bytes_are_the_sparkplug_3_encodings() {
    assert_eq!(
        bytes_of(&Value::Array(T::Int, vec![Value::Int(1), Value::Int(-2)])),
        [0x01, 0x00, 0xFE, 0xFF]
    );
    assert_eq!(
        bytes_of(&Value::Array(
            T::Bool,
            vec![Value::Bool(true), Value::Bool(false), Value::Bool(true)]
        )),
        [0x03, 0x00, 0x00, 0x00, 0xA0]
    );
    assert_eq!(
        bytes_of(&Value::Array(
            T::String,
            vec![Value::String("a".into()), Value::String("bc".into())]
        )),
        [0x61, 0x00, 0x62, 0x63, 0x00]
    );
    assert_eq!(
        bytes_of(&Value::Array(
            T::Sint,
            vec![Value::Sint(-1), Value::Sint(2)]
        )),
        [0xFF, 0x02]
    );
    assert_eq!(
        bytes_of(&Value::Array(T::Real, vec![Value::Real(1.0)])),
        [0x00, 0x00, 0x80, 0x3F]
    );
    assert_eq!(
        bytes_of(&Value::Array(
            T::DateAndTime,
            vec![Value::DateAndTime(0x0102)]
        )),
        [0x02, 0x01, 0, 0, 0, 0, 0, 0]
    );
    assert_eq!(
        bytes_of(&Value::Array(T::TimeOfDay, vec![Value::TimeOfDay(1000)])),
        [0xE8, 0x03, 0, 0]
    );
    // Nine booleans: two bytes, the second holding the ninth in its top bit.
    let nine = Value::Array(T::Bool, (0..9).map(|i| Value::Bool(i == 8)).collect());
    assert_eq!(bytes_of(&nine), [9, 0, 0, 0, 0x00, 0x80]);
}

#[test]
fn signed_scalars_are_sign_extended_and_read_in_both_forms() {
    assert_eq!(
        metric_value(&Value::Sint(-1)),
        MetricValue::IntValue(0xFFFF_FFFF)
    );
    assert_eq!(
        metric_value(&Value::Int(-2)),
        MetricValue::IntValue(0xFFFF_FFFE)
    );
    assert_eq!(
        metric_value(&Value::Dint(i32::MIN)),
        MetricValue::IntValue(0x8000_0000)
    );
    assert_eq!(
        metric_value(&Value::Lint(-1)),
        MetricValue::LongValue(u64::MAX)
    );
    let sint = scalar_ty(T::Sint);
    let int = scalar_ty(T::Int);
    let read = |ty, raw| value_of(ty, None, Some(&MetricValue::IntValue(raw)));
    // pysparkplug's width-limited form.
    assert_eq!(read(sint, 0xFF), Ok(Value::Sint(-1)));
    assert_eq!(read(sint, 0x80), Ok(Value::Sint(i8::MIN)));
    assert_eq!(read(sint, 0x7F), Ok(Value::Sint(i8::MAX)));
    assert_eq!(read(int, 0xFFFF), Ok(Value::Int(-1)));
    assert_eq!(read(int, 0x8000), Ok(Value::Int(i16::MIN)));
    // Tahu's sign-extended form.
    assert_eq!(read(sint, 0xFFFF_FF80), Ok(Value::Sint(i8::MIN)));
    assert_eq!(read(int, 0xFFFF_8000), Ok(Value::Int(i16::MIN)));
    // Neither.
    for (ty, raw) in [
        (sint, 0x100),
        (sint, 0xFFFF_FF7F),
        (sint, 0xFFFF),
        (int, 0x1_0000),
        (int, 0xFFFF_7FFF),
        (int, 0x8000_0000),
    ] {
        assert_eq!(
            read(ty, raw),
            Err(MetricError::OutOfRange {
                ty: ty.element(),
                value: u64::from(raw)
            }),
            "{ty} {raw:#x}"
        );
    }
}

#[test]
fn uint32_is_written_in_long_value_and_read_from_int_value_too() {
    let udint = scalar_ty(T::Udint);
    assert_eq!(
        metric_value(&Value::Udint(u32::MAX)),
        MetricValue::LongValue(u64::from(u32::MAX))
    );
    assert_eq!(
        value_of(udint, Some(7), Some(&MetricValue::IntValue(u32::MAX))),
        Ok(Value::Udint(u32::MAX))
    );
    assert_eq!(
        value_of(
            udint,
            Some(7),
            Some(&MetricValue::LongValue(u64::from(u32::MAX)))
        ),
        Ok(Value::Udint(u32::MAX))
    );
    assert_eq!(
        value_of(udint, Some(7), Some(&MetricValue::LongValue(1 << 32))),
        Err(MetricError::OutOfRange {
            ty: T::Udint,
            value: 1 << 32
        })
    );
    assert_eq!(
        value_of(
            scalar_ty(T::TimeOfDay),
            None,
            Some(&MetricValue::LongValue(1000))
        ),
        Ok(Value::TimeOfDay(1000))
    );
    assert_eq!(
        value_of(
            scalar_ty(T::Dword),
            None,
            Some(&MetricValue::LongValue(0xFFFF))
        ),
        Ok(Value::Dword(0xFFFF))
    );
}

#[test]
fn a_wrong_datatype_is_refused_and_named() {
    let err = value_of(
        scalar_ty(T::Int),
        Some(SpType::Int32 as u32),
        Some(&MetricValue::IntValue(1)),
    )
    .unwrap_err();
    assert_eq!(err.to_string(), "datatype Int32, expected Int16 for INT");
    let err = value_of(scalar_ty(T::Int), Some(99), Some(&MetricValue::IntValue(1))).unwrap_err();
    assert_eq!(
        err.to_string(),
        "datatype 99 (no such datatype), expected Int16 for INT"
    );
    assert!(value_of(
        scalar_ty(T::Int),
        Some(u32::MAX),
        Some(&MetricValue::IntValue(1))
    )
    .is_err());
    // The scalar type for an array port.
    let err = value_of(
        DataType::Array(T::Int, 2),
        Some(SpType::Int16 as u32),
        Some(&MetricValue::BytesValue(vec![0; 4])),
    )
    .unwrap_err();
    assert_eq!(
        err.to_string(),
        "datatype Int16, expected Int16Array for ARRAY [2] OF INT"
    );
}

#[test]
fn a_value_in_the_wrong_field_is_refused() {
    let cases = [
        (
            scalar_ty(T::Int),
            MetricValue::LongValue(1),
            "value in long_value, expected int_value for INT",
        ),
        (
            scalar_ty(T::Lint),
            MetricValue::IntValue(1),
            "value in int_value, expected long_value for LINT",
        ),
        (
            scalar_ty(T::Udint),
            MetricValue::FloatValue(1.0),
            "value in float_value, expected int_value or long_value for UDINT",
        ),
        (
            scalar_ty(T::Real),
            MetricValue::DoubleValue(1.0),
            "value in double_value, expected float_value for REAL",
        ),
        (
            scalar_ty(T::Bool),
            MetricValue::IntValue(1),
            "value in int_value, expected boolean_value for BOOL",
        ),
        (
            scalar_ty(T::String),
            MetricValue::BytesValue(b"a".to_vec()),
            "value in bytes_value, expected string_value for STRING",
        ),
        (
            scalar_ty(T::DateAndTime),
            MetricValue::StringValue("x".into()),
            "value in string_value, expected long_value for DATE_AND_TIME",
        ),
        (
            DataType::Array(T::Int, 1),
            MetricValue::IntValue(1),
            "value in int_value, expected bytes_value for ARRAY [1] OF INT",
        ),
        (
            scalar_ty(T::Int),
            MetricValue::DatasetValue(Default::default()),
            "value in dataset_value, expected int_value for INT",
        ),
    ];
    for (ty, value, message) in cases {
        let err = value_of(ty, None, Some(&value)).unwrap_err();
        assert!(matches!(err, MetricError::Field { .. }), "{err:?}");
        assert_eq!(err.to_string(), message);
    }
}

#[test]
fn values_out_of_the_iec_range_are_refused() {
    let err = value_of(scalar_ty(T::Usint), None, Some(&MetricValue::IntValue(300))).unwrap_err();
    assert_eq!(err.to_string(), "value out of range for USINT: 300");
    for (t, raw) in [(T::Byte, 256), (T::Uint, 65_536), (T::Word, u32::MAX)] {
        assert!(matches!(
            value_of(scalar_ty(t), None, Some(&MetricValue::IntValue(raw))),
            Err(MetricError::OutOfRange { .. })
        ));
    }
    // What `Value::check` refuses.
    let invalid = [
        (
            scalar_ty(T::TimeOfDay),
            MetricValue::IntValue(MS_PER_DAY as u32),
        ),
        (scalar_ty(T::Date), MetricValue::LongValue(MS_PER_DAY + 1)),
        (
            scalar_ty(T::DateAndTime),
            MetricValue::LongValue(MAX_DATE_AND_TIME_MS + 1),
        ),
        (scalar_ty(T::Real), MetricValue::FloatValue(f32::NAN)),
        (scalar_ty(T::Lreal), MetricValue::DoubleValue(f64::INFINITY)),
        (
            scalar_ty(T::String),
            MetricValue::StringValue("a\0b".into()),
        ),
        (
            scalar_ty(T::String),
            MetricValue::StringValue("x".repeat(MAX_STRING_LEN + 1)),
        ),
        // 65,535 UTF-8 bytes would do for STRING; as WSTRING, 32,768 surrogate pairs are
        // 65,536 UTF-16 units.
        (
            scalar_ty(T::WString),
            MetricValue::StringValue("🏭".repeat(32_768)),
        ),
    ];
    for (ty, value) in invalid {
        let err = value_of(ty, None, Some(&value)).unwrap_err();
        assert!(matches!(err, MetricError::Invalid { .. }), "{ty}: {err:?}");
    }
    assert_eq!(
        value_of(
            scalar_ty(T::TimeOfDay),
            None,
            Some(&MetricValue::IntValue(86_400_000))
        )
        .unwrap_err()
        .to_string(),
        "not a valid TIME_OF_DAY: 86400000 ms is out of range for TIME_OF_DAY"
    );
    // An element, inside an array.
    let nan = f32::NAN.to_le_bytes();
    let err = value_of(
        DataType::Array(T::Real, 2),
        None,
        Some(&MetricValue::BytesValue([[0; 4], nan].concat())),
    )
    .unwrap_err();
    assert!(err.to_string().contains("element 1"), "{err}");
}

#[test]
fn arrays_of_the_wrong_length_or_bytes_are_refused() {
    let int4 = DataType::Array(T::Int, 4);
    let err = value_of(int4, None, Some(&MetricValue::BytesValue(vec![0; 6]))).unwrap_err();
    assert_eq!(
        err.to_string(),
        "array of 3 elements, ARRAY [4] OF INT expects 4"
    );
    let err = value_of(int4, None, Some(&MetricValue::BytesValue(vec![0; 7]))).unwrap_err();
    assert_eq!(
        err.to_string(),
        "Int16Array of 7 bytes: not a whole number of 2-byte elements, for ARRAY [4] OF INT"
    );
    assert!(value_of(int4, None, Some(&MetricValue::BytesValue(vec![]))).is_err());
    assert!(value_of(int4, None, Some(&MetricValue::BytesValue(vec![0; 10]))).is_err());
    assert!(value_of(
        DataType::Array(T::Lreal, 1),
        None,
        Some(&MetricValue::BytesValue(vec![0; 7]))
    )
    .is_err());

    let bool3 = DataType::Array(T::Bool, 3);
    let bools = |b: &[u8]| value_of(bool3, None, Some(&MetricValue::BytesValue(b.to_vec())));
    assert_eq!(
        bools(&[3, 0, 0, 0, 0xA0]),
        Ok(Value::Array(
            T::Bool,
            vec![Value::Bool(true), Value::Bool(false), Value::Bool(true)]
        ))
    );
    // Padding bits are ignored.
    assert!(bools(&[3, 0, 0, 0, 0xBF]).is_ok());
    for truncated in [&[][..], &[3, 0, 0], &[3, 0, 0, 0]] {
        assert!(
            matches!(bools(truncated), Err(MetricError::ArrayBytes { .. })),
            "{truncated:?}"
        );
    }
    assert!(matches!(
        bools(&[3, 0, 0, 0, 0xA0, 0]),
        Err(MetricError::ArrayBytes { .. })
    ));
    assert_eq!(
        bools(&[4, 0, 0, 0, 0xA0]),
        Err(MetricError::ArrayLength {
            ty: bool3,
            expected: 3,
            got: 4
        })
    );
    assert!(bools(&[0xFF, 0xFF, 0xFF, 0xFF, 0xA0]).is_err());

    let str2 = DataType::Array(T::String, 2);
    let strings = |b: &[u8]| value_of(str2, None, Some(&MetricValue::BytesValue(b.to_vec())));
    assert_eq!(
        strings(b"a\0bc\0"),
        Ok(Value::Array(
            T::String,
            vec![Value::String("a".into()), Value::String("bc".into())]
        ))
    );
    assert_eq!(
        strings(b"\0\0"),
        Ok(Value::Array(
            T::String,
            vec![Value::String(String::new()), Value::String(String::new())]
        ))
    );
    assert!(matches!(
        strings(b"a\0bc"),
        Err(MetricError::ArrayBytes { .. })
    ));
    assert!(matches!(
        strings(b"a\0"),
        Err(MetricError::ArrayLength { got: 1, .. })
    ));
    assert!(matches!(
        strings(b"a\0b\0c\0"),
        Err(MetricError::ArrayLength { got: 3, .. })
    ));
    assert!(matches!(
        strings(b""),
        Err(MetricError::ArrayLength { got: 0, .. })
    ));
    assert_eq!(
        strings(b"a\0\xFF\xFE\0"),
        Err(MetricError::Utf8 { ty: str2, index: 1 })
    );
    assert_eq!(
        strings(b"a\0\xFF\xFE\0").unwrap_err().to_string(),
        "StringArray element 1 is not valid UTF-8, for ARRAY [2] OF STRING"
    );
}

#[test]
fn a_null_metric_is_refused() {
    let ty = scalar_ty(T::Int);
    assert_eq!(
        value_of(ty, Some(2), None).unwrap_err().to_string(),
        "no value (a null metric), expected Int16 for INT"
    );
    let null = Metric {
        datatype: Some(2),
        is_null: Some(true),
        ..Default::default()
    };
    assert!(matches!(
        value_of_metric(ty, &null),
        Err(MetricError::Null { .. })
    ));
    // is_null wins over a value that should not be there.
    let contradictory = Metric {
        value: Some(MetricValue::IntValue(1)),
        ..null
    };
    assert!(matches!(
        value_of_metric(ty, &contradictory),
        Err(MetricError::Null { .. })
    ));
    let plain = metric(None, Some(4), None, &Value::Int(-7));
    assert_eq!(value_of_metric(ty, &plain), Ok(Value::Int(-7)));
}

#[test]
fn metric_sets_datatype_and_value_and_a_payload_survives_prost() {
    let values = [
        Value::Int(-2),
        Value::Udint(u32::MAX),
        Value::DateAndTime(1_700_000_000_123),
        Value::String("Förderband".into()),
        Value::Array(T::Bool, vec![Value::Bool(true), Value::Bool(false)]),
        Value::Array(T::Time, vec![Value::Time(-1), Value::Time(i64::MAX)]),
    ];
    let metrics: Vec<Metric> = values
        .iter()
        .enumerate()
        .map(|(i, v)| {
            metric(
                Some(format!("FB1/OUT{i}")),
                Some(i as u64),
                Some(1_700_000_000_000),
                v,
            )
        })
        .collect();
    assert_eq!(metrics[0].datatype, Some(SpType::Int16 as u32));
    assert_eq!(metrics[0].value, Some(MetricValue::IntValue(0xFFFF_FFFE)));
    assert_eq!(metrics[0].name.as_deref(), Some("FB1/OUT0"));
    assert_eq!(metrics[0].alias, Some(0));
    assert_eq!(metrics[0].timestamp, Some(1_700_000_000_000));
    assert_eq!(metrics[0].is_null, None);
    assert_eq!(metrics[4].datatype, Some(SpType::BooleanArray as u32));
    let payload = proto::Payload {
        timestamp: Some(1_700_000_000_001),
        seq: Some(0),
        metrics,
        ..Default::default()
    };
    let wire = payload.encode_to_vec();
    let decoded = proto::Payload::decode(wire.as_slice()).unwrap();
    assert_eq!(decoded, payload);
    for (m, v) in decoded.metrics.iter().zip(&values) {
        assert_eq!(value_of_metric(v.data_type(), m).as_ref(), Ok(v));
    }
    // The first metric on the wire: field 2 (metrics), then name, alias, timestamp,
    // datatype 2 and int_value as a 5-byte varint of 0xFFFFFFFE.
    let first = decoded.metrics[0].encode_to_vec();
    assert!(
        first.ends_with(&[0x20, 0x02, 0x50, 0xFE, 0xFF, 0xFF, 0xFF, 0x0F]),
        "{first:02X?}"
    );
}

#[test]
fn value_of_never_panics_on_short_or_odd_bytes() {
    // Every array type against every short byte string: errors, never a panic.
    for t in ElementaryType::ALL {
        for n in [1u16, 2, 3, 8, 9] {
            let ty = DataType::Array(t, n);
            for len in 0..80usize {
                let bytes: Vec<u8> = (0..len).map(|i| (i as u8).wrapping_mul(37)).collect();
                let _ = value_of(
                    ty,
                    Some(datatype(ty) as u32),
                    Some(&MetricValue::BytesValue(bytes)),
                );
            }
        }
    }
}

#[test]
fn namespace_is_sparkplug_b_v1() {
    assert_eq!(NAMESPACE, "spBv1.0");
}

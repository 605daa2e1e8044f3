//! Sparkplug B payloads from a host: arbitrary bytes decoded as a protobuf
//! `fb_bridge::sparkplug::proto::Payload` (prost), and every metric in it read with
//! `fb_bridge::sparkplug::value_of` as a value of each elementary port type and of arrays
//! of each (what the broker's Sparkplug view does with a DCMD's metrics,
//! `broker/src/sparkplug/command.rs`).
//!
//! Input: the payload's protobuf bytes, as a host publishes them. Seeds are payloads
//! fbbus, pysparkplug 0.6.1 and Tahu JS (`sparkplug-payload` 1.0.3) wrote, with every
//! datatype fbbus maps, in every form each writes.
//!
//! Arrays are tried with 3 elements and with the element count the metric's bytes hold
//! for that element type (bytes / element width, a `BooleanArray`'s count, a
//! `StringArray`'s NULs), so the fuzzer reaches accepted arrays without guessing `n`.
//!
//! Checks:
//! - decoding and `value_of` never panic, whatever the bytes (prost's recursion limit
//!   bounds nested templates and data sets);
//! - an accepted value passes `Value::check` for the port type, and is of its type;
//! - an accepted value written again (`sparkplug::metric`) is read back, through prost's
//!   encoding, as the same value (so what fbbus publishes for a value, a host reading it as
//!   fbbus does gets that value), and its datatype is the port's;
//! - the metric as a whole (`value_of_metric`) gives the same answer unless it is marked
//!   `is_null`, which is always refused.
#![no_main]

use fb_bridge::sparkplug::proto::payload::metric::Value as MetricValue;
use fb_bridge::sparkplug::proto::{self, payload::Metric};
use fb_bridge::sparkplug::{self, value_of, value_of_metric};
use fb_bridge::types::{DataType, ElementaryType, MAX_ARRAY_LEN};
use libfuzzer_sys::fuzz_target;
use prost::Message as _;

/// More would only slow each input down: every metric is read the same way.
const MAX_METRICS: usize = 16;

fuzz_target!(|data: &[u8]| {
    let Ok(payload) = proto::Payload::decode(data) else {
        return;
    };
    for metric in payload.metrics.iter().take(MAX_METRICS) {
        for t in ElementaryType::ALL {
            read(DataType::Elementary(t), metric);
            read(DataType::Array(t, 3), metric);
            if let Some(n) = natural_len(t, metric) {
                if n != 3 {
                    read(DataType::Array(t, n), metric);
                }
            }
        }
    }
});

/// Reads `metric` as a value of `ty` and checks what is accepted.
fn read(ty: DataType, metric: &Metric) {
    let result = value_of(ty, metric.datatype, metric.value.as_ref());
    let whole = value_of_metric(ty, metric);
    if metric.is_null == Some(true) {
        assert!(
            matches!(whole, Err(sparkplug::MetricError::Null { .. })),
            "{ty}: is_null accepted as {whole:?}"
        );
    } else {
        assert_eq!(whole, result, "{ty}: value_of_metric and value_of differ");
    }
    let Ok(value) = result else {
        return;
    };
    if let Err(e) = value.check(ty) {
        panic!("{ty}: accepted {value:?}, which fails its check: {e}");
    }
    assert_eq!(value.data_type(), ty, "accepted {value:?}");

    // Written again, through the wire, read back the same.
    let written = sparkplug::metric(None, Some(1), None, &value);
    assert_eq!(written.datatype, Some(sparkplug::datatype(ty) as u32));
    let wire = written.encode_to_vec();
    let decoded = Metric::decode(wire.as_slice()).expect("a written metric decodes");
    let again = value_of(ty, decoded.datatype, decoded.value.as_ref())
        .unwrap_or_else(|e| panic!("{ty}: {value:?} written as {written:?} is refused: {e}"));
    assert_eq!(again, value, "{ty}: changed when written and read again");
    // And the form fbbus writes is a fixed point: writing the value read back gives the
    // same bytes (compared as bytes, so the reals too: -0.0 stays -0.0).
    let rewritten = sparkplug::metric(None, Some(1), None, &again).encode_to_vec();
    assert_eq!(rewritten, wire, "{ty}: {value:?} written twice differs");
}

/// The element count `metric`'s bytes hold as an array of `t`, if any is plausible.
fn natural_len(t: ElementaryType, metric: &Metric) -> Option<u16> {
    let Some(MetricValue::BytesValue(bytes)) = &metric.value else {
        return None;
    };
    use ElementaryType as T;
    let n = match t {
        T::Bool => {
            let count: [u8; 4] = bytes.get(..4)?.try_into().ok()?;
            usize::try_from(u32::from_le_bytes(count)).ok()?
        }
        T::String | T::WString => bytes.iter().filter(|b| **b == 0).count(),
        T::Sint | T::Usint | T::Byte => bytes.len(),
        T::Int | T::Uint | T::Word => bytes.len() / 2,
        T::Dint | T::Udint | T::Dword | T::Real | T::TimeOfDay => bytes.len() / 4,
        _ => bytes.len() / 8,
    };
    if (1..=MAX_ARRAY_LEN).contains(&n) {
        u16::try_from(n).ok()
    } else {
        None
    }
}

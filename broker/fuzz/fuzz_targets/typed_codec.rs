//! The typed-topic payload codecs (canonical JSON, DINASORE, 4diac `fbdk`) decoding
//! arbitrary bytes against arbitrary port declarations, as the broker does for every
//! publication on `fb/`, `dinasore/` and `fbdk/` (`broker/src/policy/typed.rs`).
//!
//! Input: one header line naming the encoding, the port and its type(s), then the payload
//! (any bytes), so seeds are readable and libFuzzer mutates types as well as payloads:
//!
//! ```text
//! fb SPEED data INT
//! 42
//! ```
//! ```text
//! fbdk MOVED event POSITION=INT;SENSOR_IN=BOOL;TRACE=ARRAY [2] OF TIME
//! <fbdk bytes>
//! ```
//!
//! Types are read with `DataType::from_str`, the parser declarations use. Checks:
//! - decoding never panics, and what it accepts passes `Value::check` for the port;
//! - the streaming JSON decoder (`json::decode_named`, `dinasore::decode`) gives exactly
//!   the result, errors included, of parsing into a `serde_json::Value` tree and reading
//!   that (the reference decoder `fb-bridge`'s own tests keep, copied below);
//! - a decoded message re-encoded in each of the three encodings (what the broker sends
//!   each namespace's subscribers) decodes back to the same message (without `seq`/`ts`
//!   where the encoding has no place for them);
//! - `json::encode` of a data value writes exactly the text of `json::value_to_json`;
//! - `fbdk::decode_values` agrees with `fbdk::decode` of an event with SD_1..SD_n.
//!
//! `fbdk` runs in both time units (`fbdk::TimeUnit`: nanoseconds as FORTE 3.x, milliseconds
//! as FORTE 2.x) on every input, decoding and re-encoding: encoding may fail only in
//! nanoseconds, only for a DATE or DATE_AND_TIME past 64-bit nanoseconds (2554), and only
//! as a type error; nothing may panic or wrap.
#![no_main]

use fb_bridge::codec::fbdk::TimeUnit;
use fb_bridge::codec::{self, dinasore, fbdk, json, CodecError, Encoding, EventMessage, Message};
use fb_bridge::interface::OutputPort;
use fb_bridge::types::DataType;
use fb_bridge::value::{TypeError, Value};

const UNITS: [TimeUnit; 2] = [TimeUnit::Nanoseconds, TimeUnit::Milliseconds];

/// The last DATE_AND_TIME, in ms, whose nanoseconds fit 64 bits (2554-07-21-23:34:33.709).
const LAST_NS_MS: u64 = u64::MAX / 1_000_000;
use libfuzzer_sys::fuzz_target;

struct Header<'a> {
    encoding: Encoding,
    port_name: &'a str,
    port: OutputPort<'a>,
}

/// `<fb|dinasore|fbdk> <port name> data <TYPE>` or
/// `<fb|dinasore|fbdk> <port name> event [NAME=TYPE[;NAME=TYPE]...]`.
fn header(line: &str) -> Option<Header<'_>> {
    let mut parts = line.splitn(4, ' ');
    let encoding = Encoding::from_namespace(parts.next()?)?;
    let port_name = parts.next()?;
    let kind = parts.next()?;
    let rest = parts.next().unwrap_or("");
    let port = match kind {
        "data" => OutputPort::Data(rest.parse().ok()?),
        "event" => {
            let mut with = Vec::new();
            for item in rest.split(';').filter(|i| !i.is_empty()) {
                let (name, ty) = item.split_once('=')?;
                with.push((name, ty.parse::<DataType>().ok()?));
            }
            // More WITH ports than a declaration allows only make the input slower.
            if with.len() > fb_bridge::interface::MAX_PORTS {
                return None;
            }
            OutputPort::Event(with)
        }
        _ => return None,
    };
    Some(Header {
        encoding,
        port_name,
        port,
    })
}

fuzz_target!(|data: &[u8]| {
    let Some(newline) = data.iter().position(|b| *b == b'\n') else {
        return;
    };
    let Ok(line) = std::str::from_utf8(&data[..newline]) else {
        return;
    };
    let payload = &data[newline + 1..];
    let Some(Header {
        encoding,
        port_name,
        port,
    }) = header(line)
    else {
        return;
    };

    // Every decoder on the payload, whatever the header's encoding says: a publisher can
    // put any bytes on any typed topic.
    let json_result = json::decode_named(payload, port_name, &port);
    assert_eq!(
        json_result,
        fb_bridge::codec::json::tree::decode_json(payload, port_name, &port),
        "streaming and tree JSON decoders differ"
    );
    let dinasore_result = dinasore::decode(payload, port_name, &port);
    assert_eq!(
        dinasore_result,
        fb_bridge::codec::json::tree::decode_dinasore(payload, port_name, &port),
        "streaming and tree DINASORE decoders differ"
    );
    let fbdk_results = UNITS.map(|unit| fbdk::decode(payload, &port, unit));
    for unit in UNITS {
        fbdk_values(payload, &port, unit);
    }

    let decoded = match encoding {
        Encoding::Json => [json_result.clone(), json_result],
        Encoding::Dinasore => [dinasore_result.clone(), dinasore_result],
        Encoding::Fbdk => fbdk_results,
    };
    for (result, unit) in decoded.iter().zip(UNITS) {
        assert_eq!(
            result,
            &codec::decode(encoding, payload, port_name, &port, unit),
            "codec::decode is not its encoding's decoder ({unit:?})"
        );
    }
    // Each unit's message once (JSON and DINASORE have no unit: the same message twice).
    let [by_ns, by_ms] = decoded;
    let messages = match (by_ns, by_ms) {
        (Ok(a), Ok(b)) if a == b => vec![(a, None)],
        (a, b) => [
            a.ok().map(|m| (m, Some(UNITS[0]))),
            b.ok().map(|m| (m, Some(UNITS[1]))),
        ]
        .into_iter()
        .flatten()
        .collect(),
    };
    for (message, from) in messages {
        round_trips(&message, from, port_name, &port);
    }
});

/// What one decoder accepted: it fits the port, its canonical JSON is `value_to_json`'s,
/// and it survives re-encoding in every encoding and unit that can carry it. `from` is
/// the `fbdk` unit it was read in, if it was read in one.
fn round_trips(message: &Message, from: Option<TimeUnit>, port_name: &str, port: &OutputPort<'_>) {
    checked(message, port);
    if let Message::Data(value) = message {
        let text = json::encode(message, port);
        let tree = serde_json::to_vec(&json::value_to_json(value)).unwrap();
        assert_eq!(
            String::from_utf8_lossy(&text),
            String::from_utf8_lossy(&tree),
            "canonical JSON of {value:?}"
        );
    }
    // A validated interface never lists a WITH port twice; objects keyed by repeated
    // names cannot round-trip, so those ports are only decoded.
    if let OutputPort::Event(with) = port {
        let mut names: Vec<&str> = with.iter().map(|(n, _)| *n).collect();
        names.sort_unstable();
        if names.windows(2).any(|w| w[0] == w[1]) {
            return;
        }
    }
    for (target, unit) in Encoding::ALL
        .into_iter()
        .flat_map(|e| UNITS.map(|u| (e, u)))
    {
        let bytes = match codec::encode(target, message, port_name, port, unit) {
            Ok(bytes) => bytes,
            Err(error) => {
                // Only a date past 64-bit nanoseconds, which a nanosecond read cannot give.
                assert!(
                    target == Encoding::Fbdk
                        && unit == TimeUnit::Nanoseconds
                        && from != Some(TimeUnit::Nanoseconds)
                        && !fits_ns(message)
                        && matches!(
                            &error,
                            CodecError::Type {
                                error: TypeError::OutOfRange { .. } | TypeError::Element { .. },
                                ..
                            }
                        ),
                    "{target:?} in {unit:?} refused {message:?}: {error}"
                );
                continue;
            }
        };
        assert!(
            target != Encoding::Fbdk || unit != TimeUnit::Nanoseconds || fits_ns(message),
            "{message:?} written in nanoseconds past 2554: {bytes:02x?}"
        );
        let again = codec::decode(target, &bytes, port_name, port, unit);
        assert_eq!(
            again,
            Ok(without_stamps(message, target)),
            "{from:?} -> {target:?} in {unit:?}: round trip of {message:?} via {:?}",
            String::from_utf8_lossy(&bytes)
        );
    }
}

/// Whether every DATE and DATE_AND_TIME of `message` fits 64-bit nanoseconds.
fn fits_ns(message: &Message) -> bool {
    fn fits(value: &Value) -> bool {
        match value {
            Value::Date(ms) | Value::DateAndTime(ms) => *ms <= LAST_NS_MS,
            Value::Array(_, items) => items.iter().all(fits),
            _ => true,
        }
    }
    match message {
        Message::Data(value) => fits(value),
        Message::Event(event) => event.data.iter().all(fits),
    }
}

/// What a decoder accepted fits the port.
fn checked(message: &Message, port: &OutputPort<'_>) {
    match (message, port) {
        (Message::Data(value), OutputPort::Data(ty)) => {
            value.check(*ty).expect("a decoded value fits its port");
        }
        (Message::Event(event), OutputPort::Event(with)) => {
            assert_eq!(event.data.len(), with.len());
            for (value, (_, ty)) in event.data.iter().zip(with) {
                value
                    .check(*ty)
                    .expect("a decoded WITH value fits its port");
            }
        }
        _ => panic!("{message:?} is not the kind of message {port:?} carries"),
    }
}

/// DINASORE and `fbdk` have no place for an event's `seq` and `ts`.
fn without_stamps(message: &Message, encoding: Encoding) -> Message {
    match (message, encoding) {
        (Message::Event(e), Encoding::Dinasore | Encoding::Fbdk) => Message::Event(EventMessage {
            seq: None,
            ts_us: None,
            data: e.data.clone(),
        }),
        (m, _) => m.clone(),
    }
}

/// `fbdk::decode_values` is `fbdk::decode` of an event whose WITH ports are SD_1..SD_n.
fn fbdk_values(payload: &[u8], port: &OutputPort<'_>, unit: TimeUnit) {
    let types: Vec<DataType> = match port {
        OutputPort::Data(ty) => vec![*ty],
        OutputPort::Event(with) => with.iter().map(|(_, t)| *t).collect(),
    };
    let names: Vec<String> = (1..=types.len()).map(|i| format!("SD_{i}")).collect();
    let event = OutputPort::Event(
        names
            .iter()
            .map(String::as_str)
            .zip(types.iter().copied())
            .collect(),
    );
    let values = fbdk::decode_values(payload, &types, unit);
    let via_event = fbdk::decode(payload, &event, unit).map(|m| match m {
        Message::Event(e) => e.data,
        Message::Data(_) => unreachable!("an event port decodes to an event"),
    });
    assert_eq!(values, via_event, "decode_values and decode differ");
    if let Ok(values) = values {
        // Read in `unit`, so it fits `unit`.
        let bytes = fbdk::encode_values(&values, unit).expect("what was read is written");
        assert_eq!(
            fbdk::decode_values(&bytes, &types, unit),
            Ok(values),
            "fbdk values round trip in {unit:?}"
        );
    }
}

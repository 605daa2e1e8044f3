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
#![no_main]

use fb_bridge::codec::{self, dinasore, fbdk, json, Encoding, EventMessage, Message};
use fb_bridge::interface::OutputPort;
use fb_bridge::types::DataType;
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
    let fbdk_result = fbdk::decode(payload, &port);
    fbdk_values(payload, &port);

    let decoded = match encoding {
        Encoding::Json => json_result,
        Encoding::Dinasore => dinasore_result,
        Encoding::Fbdk => fbdk_result,
    };
    assert_eq!(
        decoded,
        codec::decode(encoding, payload, port_name, &port),
        "codec::decode is not its encoding's decoder"
    );
    let Ok(message) = decoded else {
        return;
    };
    checked(&message, &port);
    if let Message::Data(value) = &message {
        let text = json::encode(&message, &port);
        let tree = serde_json::to_vec(&json::value_to_json(value)).unwrap();
        assert_eq!(
            String::from_utf8_lossy(&text),
            String::from_utf8_lossy(&tree),
            "canonical JSON of {value:?}"
        );
    }
    // A validated interface never lists a WITH port twice; objects keyed by repeated
    // names cannot round-trip, so those ports are only decoded.
    if let OutputPort::Event(with) = &port {
        let mut names: Vec<&str> = with.iter().map(|(n, _)| *n).collect();
        names.sort_unstable();
        if names.windows(2).any(|w| w[0] == w[1]) {
            return;
        }
    }
    for target in Encoding::ALL {
        let bytes = codec::encode(target, &message, port_name, &port);
        let again = codec::decode(target, &bytes, port_name, &port);
        assert_eq!(
            again,
            Ok(without_stamps(&message, target)),
            "{encoding:?} -> {target:?} round trip of {message:?} via {:?}",
            String::from_utf8_lossy(&bytes)
        );
    }
});

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
fn fbdk_values(payload: &[u8], port: &OutputPort<'_>) {
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
    let values = fbdk::decode_values(payload, &types);
    let via_event = fbdk::decode(payload, &event).map(|m| match m {
        Message::Event(e) => e.data,
        Message::Data(_) => unreachable!("an event port decodes to an event"),
    });
    assert_eq!(values, via_event, "decode_values and decode differ");
    if let Ok(values) = values {
        assert_eq!(
            fbdk::decode_values(&fbdk::encode_values(&values), &types),
            Ok(values),
            "fbdk values round trip"
        );
    }
}


//! The JSON and DINASORE decoders as they were before streaming: parse the payload into a
//! `serde_json::Value` tree, then read the tree. The streaming decoder (`de`) promises the
//! same results, errors included; this reference checks it, in fb-bridge's tests and in
//! the `typed_codec` fuzz target (`broker/fuzz`, feature `reference-decoder`). Not for
//! production use: it builds the tree the streaming decoder avoids.

use serde_json::{Map, Value as Json};

use super::value_from_json;
use crate::codec::{CodecError, EventMessage, Message};
use crate::interface::OutputPort;
use crate::types::DataType;
use crate::value::Value;

fn parse(payload: &[u8]) -> Result<Json, CodecError> {
    serde_json::from_slice(payload).map_err(|e| CodecError::Malformed(format!("not JSON: {e}")))
}

fn describe(j: &Json) -> &'static str {
    match j {
        Json::Null => "null",
        Json::Bool(_) => "a JSON boolean",
        Json::Number(n) if n.is_i64() || n.is_u64() => "a JSON integer",
        Json::Number(n) if n.as_f64().is_some_and(|x| x.fract() != 0.0) => {
            "a JSON number with a fraction"
        }
        Json::Number(_) => "a JSON number with a fraction or exponent",
        Json::String(_) => "a JSON string",
        Json::Array(_) => "a JSON array",
        Json::Object(_) => "a JSON object",
    }
}

fn object_fields(
    object: &Map<String, Json>,
    fields: &[(&str, DataType)],
) -> Result<Vec<Value>, CodecError> {
    if let Some((name, _)) = fields.iter().find(|(name, _)| !object.contains_key(*name)) {
        return Err(CodecError::Missing((*name).to_owned()));
    }
    if let Some(key) = object
        .keys()
        .find(|key| !fields.iter().any(|(name, _)| name == key))
    {
        return Err(CodecError::Unexpected(key.clone()));
    }
    fields
        .iter()
        .map(|(name, ty)| {
            value_from_json(&object[*name], *ty).map_err(|error| CodecError::Type {
                port: (*name).to_owned(),
                error,
            })
        })
        .collect()
}

fn optional_u64(object: &Map<String, Json>, key: &str) -> Result<Option<u64>, CodecError> {
    match object.get(key) {
        None => Ok(None),
        Some(j) => j.as_u64().map(Some).ok_or_else(|| {
            CodecError::Malformed(format!(
                "{key}: expected an unsigned integer, got {}",
                describe(j)
            ))
        }),
    }
}

fn decode_event(json: Json, with: &[(&str, DataType)]) -> Result<EventMessage, CodecError> {
    let Json::Object(object) = json else {
        return Err(CodecError::Malformed(format!(
            r#"an event is a JSON object {{"seq":..,"ts":..,"data":{{..}}}}, got {}"#,
            describe(&json)
        )));
    };
    if let Some(key) = object
        .keys()
        .find(|key| !matches!(key.as_str(), "seq" | "ts" | "data"))
    {
        return Err(CodecError::Unexpected(key.clone()));
    }
    let data = match object.get("data") {
        Some(Json::Object(data)) => object_fields(data, with)?,
        None => object_fields(&Map::new(), with)?,
        Some(other) => {
            return Err(CodecError::Malformed(format!(
                "data: expected a JSON object of the WITH data ports, got {}",
                describe(other)
            )))
        }
    };
    Ok(EventMessage {
        seq: optional_u64(&object, "seq")?,
        ts_us: optional_u64(&object, "ts")?,
        data,
    })
}

pub fn decode_json(
    payload: &[u8],
    port_name: &str,
    port: &OutputPort<'_>,
) -> Result<Message, CodecError> {
    let json = parse(payload)?;
    match port {
        OutputPort::Data(ty) => value_from_json(&json, *ty)
            .map(Message::Data)
            .map_err(|error| CodecError::Type {
                port: port_name.to_owned(),
                error,
            }),
        OutputPort::Event(with) => decode_event(json, with).map(Message::Event),
    }
}

pub fn decode_dinasore(
    payload: &[u8],
    port_name: &str,
    port: &OutputPort<'_>,
) -> Result<Message, CodecError> {
    let json = parse(payload)?;
    let Some(object) = json.as_object() else {
        return Err(CodecError::Malformed(format!(
            "a DINASORE payload is a JSON object keyed by data port names, got {}",
            describe(&json)
        )));
    };
    match port {
        OutputPort::Data(ty) => {
            let mut values = object_fields(object, &[(port_name, *ty)])?;
            Ok(Message::Data(values.remove(0)))
        }
        OutputPort::Event(with) => Ok(Message::Event(EventMessage {
            seq: None,
            ts_us: None,
            data: object_fields(object, with)?,
        })),
    }
}

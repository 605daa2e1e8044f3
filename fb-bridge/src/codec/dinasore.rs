//! DINASORE JSON (helper fills this in).
use super::{CodecError, Message};
use crate::interface::OutputPort;

pub fn decode(
    _payload: &[u8],
    _port_name: &str,
    _port: &OutputPort<'_>,
) -> Result<Message, CodecError> {
    Err(CodecError::Malformed("not implemented".into()))
}

pub fn encode(_message: &Message, _port_name: &str, _port: &OutputPort<'_>) -> Vec<u8> {
    Vec::new()
}

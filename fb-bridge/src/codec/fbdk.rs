//! 4diac fbdk (helper fills this in).
use super::{CodecError, Message};
use crate::interface::OutputPort;

pub fn decode(_payload: &[u8], _port: &OutputPort<'_>) -> Result<Message, CodecError> {
    Err(CodecError::Malformed("not implemented".into()))
}

pub fn encode(_message: &Message) -> Vec<u8> {
    Vec::new()
}

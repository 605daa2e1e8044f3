//! The wire: bytes on a client's socket to MQTT packets and back.
//!
//! - [`framed`]: the socket with its read and write buffers; reads whole packets, writes
//!   with a deadline.
//! - [`frame`]: the few bytes fbbus reads itself before a packet is decoded (is it whole,
//!   is it too large, which protocol level does CONNECT ask for).
//! - [`codec`]: rumqttd's MQTT 3.1.1 and 5 codecs behind one type, with the guards fbbus
//!   puts in front of them.
//!
//! Nothing here knows about sessions, policy or the router: a packet leaves this module
//! decoded, or as a precise [`codec::ReadError`].

pub mod codec;
pub mod frame;
pub mod framed;

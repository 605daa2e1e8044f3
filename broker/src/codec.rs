//! MQTT packets to and from bytes: rumqttd 0.20's codecs, behind one type, with the
//! guards fbbus puts in front of them.
//!
//! - MQTT 3.1.1 and 5 share a port; the version is chosen from CONNECT ([`Version`]).
//! - rumqttd's 3.1.1 writer panics on packets carrying MQTT 5 properties and on CONNACK
//!   codes 3.1.1 does not have: [`Codec::write`] strips and maps them.
//! - rumqttd's decoders panic on some input: [`decode_frame`] refuses packet types only
//!   servers send before decoding, and catches what panics remain.

use bytes::BytesMut;
use rumqttd::protocol::{
    v4::V4, v5::V5, ConnAck, ConnAckProperties, ConnectReturnCode, Packet, Protocol,
};

use crate::frame;

/// MQTT version of a connection, chosen from CONNECT's protocol level.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Version {
    V311,
    V5,
}

/// rumqttd's codecs, behind one type. The 3.1.1 codec panics on packets with MQTT 5
/// properties, so they are stripped here: a v5 publisher's properties do not exist for a
/// v3.1.1 subscriber.
pub struct Codec(pub Version);

impl Codec {
    pub fn read(&self, buf: &mut BytesMut, max: usize) -> Result<Packet, rumqttd::protocol::Error> {
        match self.0 {
            Version::V311 => V4.read_mut(buf, max),
            Version::V5 => V5.read_mut(buf, max),
        }
    }

    pub fn write(
        &self,
        packet: Packet,
        buf: &mut BytesMut,
    ) -> Result<usize, rumqttd::protocol::Error> {
        match self.0 {
            Version::V5 => V5.write(packet, buf),
            Version::V311 => V4.write(strip_properties(packet), buf),
        }
    }
}

fn strip_properties(packet: Packet) -> Packet {
    match packet {
        Packet::ConnAck(ack, _) => Packet::ConnAck(v311_connack(ack), None),
        Packet::Publish(p, _) => Packet::Publish(p, None),
        Packet::PubAck(p, _) => Packet::PubAck(p, None),
        Packet::PubRec(p, _) => Packet::PubRec(p, None),
        Packet::PubRel(p, _) => Packet::PubRel(p, None),
        Packet::PubComp(p, _) => Packet::PubComp(p, None),
        Packet::SubAck(p, _) => Packet::SubAck(p, None),
        Packet::UnsubAck(p, _) => Packet::UnsubAck(p, None),
        Packet::Disconnect(p, _) => Packet::Disconnect(p, None),
        other => other,
    }
}

/// MQTT 3.1.1 has six CONNACK codes; rumqttd's 3.1.1 writer panics on the others.
fn v311_connack(mut ack: ConnAck) -> ConnAck {
    use ConnectReturnCode::*;
    ack.code = match ack.code {
        Success
        | RefusedProtocolVersion
        | ClientIdentifierNotValid
        | ServiceUnavailable
        | BadUserNamePassword
        | NotAuthorized => ack.code,
        UnsupportedProtocolVersion => RefusedProtocolVersion,
        ConnectionRateExceeded | ServerBusy | ServerUnavailable => ServiceUnavailable,
        _ => NotAuthorized,
    };
    ack
}

pub fn connack(code: ConnectReturnCode, properties: Option<ConnAckProperties>) -> Packet {
    Packet::ConnAck(
        ConnAck {
            session_present: false,
            code,
        },
        properties,
    )
}

/// Packet types a client may send: CONNECT, PUBLISH, PUBACK, PUBREC, PUBREL, PUBCOMP,
/// SUBSCRIBE, UNSUBSCRIBE, PINGREQ, DISCONNECT. (AUTH, 15, is not supported.)
const FROM_CLIENTS: [u8; 10] = [1, 3, 4, 5, 6, 7, 8, 10, 12, 14];

/// Decodes the complete frame at the start of `buf` (its header already checked).
///
/// rumqttd 0.20's decoders panic on some input (a v5 CONNACK-typed packet with a body
/// reaches an `unreachable!`), and a panic would end the connection task without telling
/// the router or firing the will. Server-only packet types are refused before decoding;
/// a panic that remains is caught and reported as a malformed packet.
pub fn decode_frame(
    codec: &Codec,
    buf: &mut BytesMut,
    header: &frame::FixedHeader,
    max_packet: usize,
) -> Result<Packet, ReadError> {
    std::panic::catch_unwind(std::panic::AssertUnwindSafe(|| {
        decode_unguarded(codec, buf, header, max_packet)
    }))
    .unwrap_or_else(|_| {
        let _ = buf.split_to(header.frame_len().min(buf.len()));
        Err(ReadError::Malformed("the decoder panicked".into()))
    })
}

pub fn decode_unguarded(
    codec: &Codec,
    buf: &mut BytesMut,
    header: &frame::FixedHeader,
    max_packet: usize,
) -> Result<Packet, ReadError> {
    if !FROM_CLIENTS.contains(&header.packet_type()) {
        return Err(ReadError::ServerOnlyType(header.packet_type()));
    }
    // MQTT 5 3.14.2.2: a DISCONNECT may end after its reason code, meaning "no
    // properties"; rumqttd 0.20 expects the property length. Decode a copy with it.
    if codec.0 == Version::V5 && header.packet_type() == 14 && header.remaining_len == 1 {
        let mut padded = BytesMut::from(&buf[..header.frame_len()]);
        padded[1] = 2;
        padded.extend_from_slice(&[0]);
        let _ = buf.split_to(header.frame_len());
        return codec
            .read(&mut padded, max_packet)
            .map_err(|e| ReadError::Malformed(e.to_string()));
    }
    codec
        .read(buf, max_packet)
        .map_err(|e| ReadError::Malformed(e.to_string()))
}

/// Something wrong with the bytes a client sent.
#[derive(Debug)]
pub enum ReadError {
    Closed,
    Malformed(String),
    /// A packet type only servers send (e.g. CONNACK): a protocol error.
    ServerOnlyType(u8),
    Oversized {
        size: usize,
        max: usize,
    },
}

impl std::fmt::Display for ReadError {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            ReadError::Closed => f.write_str("connection closed"),
            ReadError::Malformed(why) => write!(f, "malformed packet: {why}"),
            ReadError::ServerOnlyType(t) => write!(f, "packet type {t} is not sent by clients"),
            ReadError::Oversized { size, max } => write!(f, "packet of {size} bytes, limit {max}"),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Random and mutated packets through both codecs must never panic: a panic would end
    /// the connection task without telling the router or firing the will.
    #[test]
    fn codecs_survive_random_and_mutated_packets() {
        let seeds: [&[u8]; 6] = [
            &[0x10, 12, 0, 4, b'M', b'Q', b'T', b'T', 5, 2, 0, 60, 0, 0],
            &[0x30, 8, 0, 3, b'a', b'/', b'b', 0, b'h', b'i'],
            &[0x32, 9, 0, 1, b't', 0, 7, 0, b'x', b'y', b'z'],
            &[0x82, 7, 0, 1, 0, 0, 2, b'a', 1],
            &[0xA2, 6, 0, 2, 0, 0, 1, b'a'],
            &[0xE0, 2, 0x04, 0],
        ];
        let mut state = 0x2545_f491_4f6c_dd1du64;
        let mut next = || {
            state ^= state << 13;
            state ^= state >> 7;
            state ^= state << 17;
            state
        };
        for round in 0..200_000u32 {
            let mut bytes = seeds[round as usize % seeds.len()].to_vec();
            for _ in 0..(next() % 4) {
                let at = (next() as usize) % bytes.len();
                bytes[at] = next() as u8;
            }
            if next() % 3 == 0 {
                bytes.truncate((next() as usize) % (bytes.len() + 1));
            }
            if next() % 5 == 0 {
                bytes.extend((0..next() % 8).map(|_| next() as u8));
            }
            for version in [Version::V311, Version::V5] {
                let mut buf = BytesMut::from(&bytes[..]);
                let Ok(header) = frame::check(&buf, 1024) else {
                    continue;
                };
                // The unguarded path: this test is what keeps the guard a last resort.
                let result = std::panic::catch_unwind(std::panic::AssertUnwindSafe(|| {
                    decode_unguarded(&Codec(version), &mut buf, &header, 1024)
                }));
                assert!(result.is_ok(), "{version:?} codec panicked on {bytes:02x?}");
            }
        }
    }
}

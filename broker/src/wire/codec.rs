//! MQTT packets to and from bytes: rumqttd 0.20's codecs, behind one type, with the
//! guards fbbus puts in front of them.
//!
//! - MQTT 3.1.1 and 5 share a port; the version is chosen from CONNECT ([`Version`]).
//! - rumqttd's writers refuse (with an error) what a version cannot carry: MQTT 5
//!   properties and CONNACK codes on 3.1.1, 3.1.1-only CONNACK codes on 5.
//!   [`Codec::write`] strips and maps them, so a client is always answered.
//! - [`decode_frame`] refuses packet types only servers send before decoding. rumqttd's
//!   decoders themselves do not panic on any input: the panics they had were fixed at the
//!   source (`vendor/rumqttd/FBBUS-CHANGES.md`), and the `mqtt_decode` fuzz target
//!   (`broker/fuzz`, `docs/fuzzing.md`) keeps it so, without a `catch_unwind` here.

use bytes::BytesMut;
use rumqttd::protocol::{
    v4::V4, v5::V5, ConnAck, ConnAckProperties, ConnectReturnCode, Packet, Protocol,
};

use crate::wire::frame;

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
        properties.map(Box::new),
    )
}

/// Packet types a client may send: CONNECT, PUBLISH, PUBACK, PUBREC, PUBREL, PUBCOMP,
/// SUBSCRIBE, UNSUBSCRIBE, PINGREQ, DISCONNECT. (AUTH, 15, is not supported.)
const FROM_CLIENTS: [u8; 10] = [1, 3, 4, 5, 6, 7, 8, 10, 12, 14];

/// Decodes the complete frame at the start of `buf` (its header already checked), and
/// takes it out of `buf`.
///
/// Server-only packet types are refused before decoding (a protocol error, not a
/// malformed packet). No `catch_unwind`: rumqttd's decoders return errors for every
/// input (fbbus fixed the panics they had, and `broker/fuzz` checks it).
pub fn decode_frame(
    codec: &Codec,
    buf: &mut BytesMut,
    header: &frame::FixedHeader,
    max_packet: usize,
) -> Result<Packet, ReadError> {
    if !FROM_CLIENTS.contains(&header.packet_type()) {
        return Err(ReadError::ServerOnlyType(header.packet_type()));
    }
    // MQTT 5 3.14.2.2: a DISCONNECT may end after its reason code, meaning "no
    // properties"; rumqttd 0.20 expects the property length. Decode it with one.
    if codec.0 == Version::V5 && header.packet_type() == 14 && header.remaining_len == 1 {
        let reason = buf[header.header_len];
        let mut padded = BytesMut::from(&[header.byte1, 2, reason, 0][..]);
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

    /// The packet path reads a client PUBLISH's QoS and packet id from the decoded packet
    /// (rumqttd's `Publish::qos_and_pkid`), not from the raw bytes.
    #[test]
    fn decoded_publish_carries_its_qos_and_packet_id() {
        let cases: [(Version, &[u8], (u8, u16)); 3] = [
            (
                Version::V311,
                &[0x32, 7, 0, 1, b'a', 0x12, 0x34, b'x', b'y'],
                (1, 0x1234),
            ),
            // MQTT 5: an empty property length after the packet id.
            (
                Version::V5,
                &[0x34, 8, 0, 1, b'a', 0xAB, 0xCD, 0, b'x', b'y'],
                (2, 0xABCD),
            ),
            (Version::V311, &[0x30, 5, 0, 1, b'a', b'x', b'y'], (0, 0)),
        ];
        for (version, bytes, expected) in cases {
            let mut buf = BytesMut::from(bytes);
            let header = frame::check(&buf, 1024).unwrap();
            match decode_frame(&Codec(version), &mut buf, &header, 1024) {
                Ok(Packet::Publish(publish, _)) => {
                    assert_eq!(publish.qos_and_pkid(), expected, "{version:?} {bytes:x?}")
                }
                other => panic!("{version:?} {bytes:x?}: {other:?}"),
            }
        }
    }

    /// Random and mutated packets through both codecs must never panic: a panic would end
    /// the connection task without telling the router or firing the will. (Bounded; the
    /// `mqtt_decode` fuzz target in broker/fuzz does this coverage-guided.)
    #[test]
    fn codecs_survive_random_and_mutated_packets() {
        let seeds: [&[u8]; 8] = [
            &[0x10, 12, 0, 4, b'M', b'Q', b'T', b'T', 5, 2, 0, 60, 0, 0],
            &[0x30, 8, 0, 3, b'a', b'/', b'b', 0, b'h', b'i'],
            &[0x32, 9, 0, 1, b't', 0, 7, 0, b'x', b'y', b'z'],
            &[0x82, 7, 0, 1, 0, 0, 2, b'a', 1],
            &[0xA2, 6, 0, 2, 0, 0, 1, b'a'],
            &[0xE0, 2, 0x04, 0],
            &[0x20, 3, 0, 0, 0],
            &[0xB0, 4, 0, 1, 0, 0],
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
                let Ok(header) = frame::check(&bytes, 1024) else {
                    continue;
                };
                // The broker's decoder, and rumqttd's own, server-only types included.
                let _ = decode_frame(
                    &Codec(version),
                    &mut BytesMut::from(&bytes[..]),
                    &header,
                    1024,
                );
                let _ = Codec(version).read(&mut BytesMut::from(&bytes[..]), 1024);
            }
        }
    }

    /// Regression (broker/fuzz/regressions/mqtt_decode/v5-connack, v5-unsuback): rumqttd's
    /// MQTT 5 decoder reached an `unreachable!()` on CONNACK and UNSUBACK, which is why
    /// `decode_frame` once caught panics.
    #[test]
    fn v5_connack_and_unsuback_decode() {
        let mut connack = BytesMut::from(&[0x20, 3, 1, 0x87, 0][..]);
        assert!(matches!(
            Codec(Version::V5).read(&mut connack, 1024),
            Ok(Packet::ConnAck(ack, None))
                if ack.session_present && ack.code == ConnectReturnCode::NotAuthorized
        ));
        let mut unsuback = BytesMut::from(&[0xB0, 4, 0, 1, 0, 0][..]);
        assert!(matches!(
            Codec(Version::V5).read(&mut unsuback, 1024),
            Ok(Packet::UnsubAck(ack, None)) if ack.pkid == 1
        ));
        // From a client they are still refused, before decoding.
        let header = frame::check(&[0x20, 3, 1, 0x87, 0], 1024).unwrap();
        assert!(matches!(
            decode_frame(
                &Codec(Version::V5),
                &mut BytesMut::from(&[0x20, 3, 1, 0x87, 0][..]),
                &header,
                1024
            ),
            Err(ReadError::ServerOnlyType(2))
        ));
    }

    /// Regression (broker/fuzz/regressions/mqtt_decode/v5-disconnect-reason-without-
    /// properties): a v5 DISCONNECT with a reason code and no properties announced a
    /// remaining length of 1 and wrote 2 bytes, so the client read a stray 0x00 packet.
    /// fbbus sends exactly these (0x8B server shutting down, 0x8E session taken over, ...).
    #[test]
    fn v5_disconnect_with_a_reason_is_one_whole_frame() {
        use rumqttd::protocol::{Disconnect, DisconnectReasonCode};
        for reason_code in [
            DisconnectReasonCode::ServerShuttingDown,
            DisconnectReasonCode::SessionTakenOver,
            DisconnectReasonCode::KeepAliveTimeout,
            DisconnectReasonCode::NormalDisconnection,
        ] {
            let packet = Packet::Disconnect(Disconnect { reason_code }, None);
            let mut out = BytesMut::new();
            Codec(Version::V5).write(packet.clone(), &mut out).unwrap();
            let header = frame::check(&out, 1024).unwrap();
            assert_eq!(header.frame_len(), out.len(), "{reason_code:?}: {out:02x?}");
            let decoded = decode_frame(&Codec(Version::V5), &mut out, &header, 1024).unwrap();
            assert_eq!(decoded, packet);
            assert!(out.is_empty());
        }
        // As a client sends it, reason code only (remaining length 1).
        let bytes = [0xE0, 1, 0x04];
        let header = frame::check(&bytes, 1024).unwrap();
        assert_eq!(
            decode_frame(
                &Codec(Version::V5),
                &mut BytesMut::from(&bytes[..]),
                &header,
                1024
            )
            .unwrap(),
            Packet::Disconnect(
                Disconnect {
                    reason_code: DisconnectReasonCode::DisconnectWithWillMessage
                },
                None
            )
        );
    }

    /// Regression (broker/fuzz/regressions/mqtt_decode/v5-publish-repeated-subscription-
    /// identifiers): rumqttd counted a subscription identifier's property byte twice, so
    /// after several identifiers it stopped reading properties early and the rest became
    /// payload (a SUBSCRIBE's, topic filters).
    #[test]
    fn v5_subscription_identifiers_are_counted_once() {
        let mut properties = vec![0x02, 0, 0, 0, 11];
        for _ in 0..14 {
            properties.extend_from_slice(&[0x0B, 11]);
        }
        let mut bytes = vec![0x30, 0, 0, 1, b't', properties.len() as u8];
        bytes.extend_from_slice(&properties);
        bytes.extend_from_slice(b"payload");
        bytes[1] = (bytes.len() - 2) as u8;
        let Ok(Packet::Publish(publish, Some(p))) =
            Codec(Version::V5).read(&mut BytesMut::from(&bytes[..]), 1024)
        else {
            panic!("not a PUBLISH with properties");
        };
        assert_eq!(p.subscription_identifiers, vec![11; 14]);
        assert_eq!(&publish.payload[..], b"payload");
    }
}

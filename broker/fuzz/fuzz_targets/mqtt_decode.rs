//! MQTT 3.1.1 and 5 decoding as the broker does it, and encoding what decoded.
//!
//! The input is the byte stream a client sends on a TCP connection. It goes through:
//!
//! 1. **The session path**: `broker::wire::framed::Io` over an in-memory stream: `read_connect`
//!    (first-byte check, framing, the CONNECT's protocol level choosing the 3.1.1 or 5
//!    codec, decoding), then `next_frame` / `decode` for every following packet, as
//!    the session (`broker/src/session/mod.rs`) reads them, until the stream ends or a packet is refused (which
//!    closes a real connection). A decoded PUBLISH's QoS (`Publish::qos_and_pkid`, which
//!    the packet path acknowledges with) must be the one its fixed header announces.
//! 2. **Every frame with both codecs**, without a CONNECT first: `frame::check` and
//!    `codec::decode_frame` (the broker's guarded decoder), and rumqttd's decoder itself
//!    (`Codec::read`, no guard: it must not panic on any packet type either).
//!
//! Whatever decodes is encoded again with the broker's `Codec::write` in the same version
//! and, for the packets the broker writes to clients (PUBLISH, the acks, DISCONNECT), in
//! the other version too (a 3.1.1 publisher's message goes to 5 subscribers and back).
//! What was written must be exactly one well-formed frame (`frame::check` reads the same
//! length that was written) and decode back to the same packet (minus the properties
//! 3.1.1 cannot carry).
#![no_main]

use std::future::Future;
use std::io::Cursor;
use std::pin::pin;
use std::task::{Context, Poll, Waker};

use broker::wire::codec::{decode_frame, Codec, ReadError, Version};
use broker::wire::frame;
use broker::wire::framed::Io;
use bytes::BytesMut;
use libfuzzer_sys::fuzz_target;
use rumqttd::protocol::Packet;

/// The broker's default `max_packet_bytes`.
const SESSION_MAX_PACKET: usize = 64 * 1024;
/// Smaller for the direct decode, so the size limit is reached by inputs libFuzzer makes.
const DIRECT_MAX_PACKET: usize = 2048;

fuzz_target!(|data: &[u8]| {
    session(data);
    for version in [Version::V311, Version::V5] {
        direct(data, version);
    }
});

/// Runs a future that never waits (the stream is in memory) to completion.
fn run<F: Future>(future: F) -> F::Output {
    let mut future = pin!(future);
    let mut cx = Context::from_waker(Waker::noop());
    match future.as_mut().poll(&mut cx) {
        Poll::Ready(output) => output,
        Poll::Pending => panic!("an in-memory read waited"),
    }
}

/// The bytes as one client connection: CONNECT first, then packets until one is refused.
fn session(data: &[u8]) {
    let stream = Box::new(Cursor::new(data.to_vec()));
    let mut io = Io::new(stream, SESSION_MAX_PACKET);
    let Ok(connect) = run(io.read_connect()) else {
        return;
    };
    assert!(
        matches!(connect, Packet::Connect(..)),
        "read_connect returned {connect:?}"
    );
    let version = io.codec.0;
    reencode(version, &connect);
    loop {
        let header = match io.next_frame() {
            Ok(Some(header)) => header,
            Ok(None) => match run(io.fill()) {
                Ok(_) => continue,
                Err(_) => return,
            },
            Err(_) => return,
        };
        let _ = frame::connect_protocol_level(&io.read, &header);
        let before = io.read.len();
        match io.decode(&header) {
            Ok(packet) => {
                assert_eq!(
                    before - io.read.len(),
                    header.frame_len(),
                    "a decoded packet must consume exactly its frame"
                );
                check_publish_qos(&header, &packet);
                reencode(version, &packet);
            }
            Err(_) => return,
        }
    }
}

/// A decoded PUBLISH has the QoS its fixed header's flags announce, and a packet id only
/// when that QoS is 1 or 2.
fn check_publish_qos(header: &frame::FixedHeader, packet: &Packet) {
    if let Packet::Publish(publish, _) = packet {
        let (qos, pkid) = publish.qos_and_pkid();
        assert_eq!(qos, (header.byte1 >> 1) & 0b11, "QoS of {publish:?}");
        if qos == 0 {
            assert_eq!(pkid, 0, "packet id of a QoS 0 {publish:?}");
        }
    }
}

/// Frame after frame with one codec, through the broker's guarded decoder and rumqttd's
/// unguarded one.
fn direct(data: &[u8], version: Version) {
    let codec = Codec(version);
    let mut buf = BytesMut::from(data);
    loop {
        let header = match frame::check(&buf, DIRECT_MAX_PACKET) {
            Ok(header) => header,
            Err(_) => return,
        };
        let _ = frame::connect_protocol_level(&buf, &header);

        // rumqttd's decoder on its own, every packet type included.
        let mut raw = BytesMut::from(&buf[..header.frame_len()]);
        if let Ok(packet) = codec.read(&mut raw, DIRECT_MAX_PACKET) {
            reencode(version, &packet);
        }

        let before = buf.len();
        match decode_frame(&codec, &mut buf, &header, DIRECT_MAX_PACKET) {
            Ok(packet) => {
                assert_eq!(before - buf.len(), header.frame_len());
                check_publish_qos(&header, &packet);
                reencode(version, &packet);
            }
            Err(ReadError::ServerOnlyType(t)) => {
                assert!(
                    matches!(t, 0 | 2 | 9 | 11 | 13 | 15),
                    "type {t} is sent by clients"
                );
                return;
            }
            Err(_) => return,
        }
    }
}

/// Packets the broker writes to a client of either version with content that may come
/// from the other version: forwarded PUBLISHes, and acks and DISCONNECTs, which
/// `Codec::write` strips down for 3.1.1. (SUBACK and CONNACK codes are chosen per version
/// by the connection, so they are only written in the version they were read in.)
fn cross_version(packet: &Packet) -> bool {
    matches!(
        packet,
        Packet::Publish(..)
            | Packet::PubAck(..)
            | Packet::PubRec(..)
            | Packet::PubRel(..)
            | Packet::PubComp(..)
            | Packet::PingResp(..)
            | Packet::Disconnect(..)
    )
}

fn reencode(version: Version, packet: &Packet) {
    write_and_read_back(version, packet);
    if cross_version(packet) {
        let other = match version {
            Version::V311 => Version::V5,
            Version::V5 => Version::V311,
        };
        write_and_read_back(other, packet);
    }
}

/// Writes `packet` with the broker's codec for `version`; what was written must frame and
/// decode back to `packet` as that version sees it.
fn write_and_read_back(version: Version, packet: &Packet) {
    let codec = Codec(version);
    let mut out = BytesMut::new();
    if codec.write(packet.clone(), &mut out).is_err() {
        return;
    }
    let header = frame::check(&out, usize::MAX).unwrap_or_else(|e| {
        panic!("{version:?} wrote an unframeable {out:02x?} ({e:?}) for {packet:?}")
    });
    assert_eq!(
        header.frame_len(),
        out.len(),
        "{version:?} wrote a frame whose length is not what it wrote: {out:02x?} for {packet:?}"
    );
    let written = out.clone();
    let again = codec.read(&mut out, usize::MAX).unwrap_or_else(|e| {
        panic!("{version:?} cannot read back {written:02x?} ({e}) for {packet:?}")
    });
    assert!(out.is_empty());
    let expected = as_written(version, packet.clone());
    assert_eq!(
        again, expected,
        "{version:?} round trip changed the packet (wrote {written:02x?})"
    );
}

/// What `packet` is once written in `version` and read back: 3.1.1 has no properties and
/// no reason codes on acks, UNSUBACK and DISCONNECT.
fn as_written(version: Version, packet: Packet) -> Packet {
    use rumqttd::protocol::*;
    if version == Version::V5 {
        return packet;
    }
    match packet {
        Packet::Publish(p, _) => Packet::Publish(p, None),
        Packet::PubAck(p, _) => Packet::PubAck(
            PubAck {
                reason: PubAckReason::Success,
                ..p
            },
            None,
        ),
        Packet::PubRec(p, _) => Packet::PubRec(
            PubRec {
                reason: PubRecReason::Success,
                ..p
            },
            None,
        ),
        Packet::PubRel(p, _) => Packet::PubRel(
            PubRel {
                reason: PubRelReason::Success,
                ..p
            },
            None,
        ),
        Packet::PubComp(p, _) => Packet::PubComp(
            PubComp {
                reason: PubCompReason::Success,
                ..p
            },
            None,
        ),
        Packet::Disconnect(_, _) => Packet::Disconnect(
            Disconnect {
                reason_code: DisconnectReasonCode::NormalDisconnection,
            },
            None,
        ),
        Packet::UnsubAck(p, _) => Packet::UnsubAck(
            UnsubAck {
                reasons: vec![],
                ..p
            },
            None,
        ),
        other => other,
    }
}

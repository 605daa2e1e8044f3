//! MQTT framing: the few bytes fbbus reads itself before rumqttd's codec decodes a packet.
//!
//! Two facts are needed from the raw bytes:
//! - whether a whole packet is buffered, and whether it is over the size limit
//!   (so an oversized packet is refused before it is decoded);
//! - the protocol level in CONNECT, so MQTT 3.1.1 and 5 share one port.
//!
//! A PUBLISH's QoS and packet id come from the decoded packet
//! (`rumqttd::protocol::Publish::qos_and_pkid`).

use bytes::BytesMut;

/// The fixed header of one MQTT packet.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct FixedHeader {
    /// The first byte: packet type in the high nibble, flags in the low one.
    pub byte1: u8,
    /// Length of the fixed header (1 + the remaining-length bytes).
    pub header_len: usize,
    /// Length of everything after the fixed header.
    pub remaining_len: usize,
}

impl FixedHeader {
    pub fn frame_len(&self) -> usize {
        self.header_len + self.remaining_len
    }

    pub fn packet_type(&self) -> u8 {
        self.byte1 >> 4
    }
}

#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum FrameError {
    /// Not enough bytes yet; at least this many more are needed.
    Incomplete(usize),
    /// The remaining-length field is longer than 4 bytes.
    MalformedLength,
    /// The packet is larger than the configured maximum.
    TooLarge { size: usize, max: usize },
}

/// Parses the fixed header at the start of `buf`, and checks the whole frame is buffered.
pub fn check(buf: &[u8], max_packet: usize) -> Result<FixedHeader, FrameError> {
    if buf.len() < 2 {
        return Err(FrameError::Incomplete(2 - buf.len()));
    }
    let mut remaining_len = 0usize;
    for (i, byte) in buf[1..].iter().enumerate() {
        if i == 4 {
            return Err(FrameError::MalformedLength);
        }
        remaining_len |= ((byte & 0x7f) as usize) << (7 * i);
        if byte & 0x80 == 0 {
            let header = FixedHeader {
                byte1: buf[0],
                header_len: i + 2,
                remaining_len,
            };
            if header.frame_len() > max_packet {
                return Err(FrameError::TooLarge {
                    size: header.frame_len(),
                    max: max_packet,
                });
            }
            if buf.len() < header.frame_len() {
                return Err(FrameError::Incomplete(header.frame_len() - buf.len()));
            }
            return Ok(header);
        }
    }
    if buf.len() >= 5 {
        return Err(FrameError::MalformedLength);
    }
    Err(FrameError::Incomplete(1))
}

/// The protocol level of a buffered CONNECT frame (4 = MQTT 3.1.1, 5 = MQTT 5,
/// 3 = MQTT 3.1), or None when the frame is not a CONNECT with a readable protocol name.
pub fn connect_protocol_level(buf: &BytesMut, header: &FixedHeader) -> Option<u8> {
    if header.packet_type() != 1 {
        return None;
    }
    let body = &buf[header.header_len..header.frame_len()];
    let name_len = u16::from_be_bytes([*body.first()?, *body.get(1)?]) as usize;
    let name = body.get(2..2 + name_len)?;
    if name != b"MQTT" && name != b"MQIsdp" {
        return None;
    }
    body.get(2 + name_len).copied()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn single_byte_length() {
        let h = check(&[0x30, 3, 0, 1, b'a'], 100).unwrap();
        assert_eq!(h.header_len, 2);
        assert_eq!(h.remaining_len, 3);
        assert_eq!(h.packet_type(), 3);
    }

    #[test]
    fn multi_byte_length_incomplete() {
        // 321 = 0xC1 0x02
        assert_eq!(
            check(&[0x30, 0xC1, 0x02, 0], 1000),
            Err(FrameError::Incomplete(321 + 3 - 4))
        );
        assert_eq!(check(&[0x30, 0xC1], 1000), Err(FrameError::Incomplete(1)));
    }

    #[test]
    fn too_large_before_the_body_arrives() {
        assert_eq!(
            check(&[0x30, 0xC1, 0x02], 100),
            Err(FrameError::TooLarge {
                size: 324,
                max: 100
            })
        );
    }

    #[test]
    fn five_length_bytes_are_malformed() {
        assert_eq!(
            check(&[0x30, 0xff, 0xff, 0xff, 0xff, 0x01], usize::MAX),
            Err(FrameError::MalformedLength)
        );
    }

    #[test]
    fn connect_level() {
        let connect = [0x10, 10, 0, 4, b'M', b'Q', b'T', b'T', 5, 2, 0, 60];
        let buf = BytesMut::from(&connect[..]);
        let h = check(&buf, 100).unwrap();
        assert_eq!(connect_protocol_level(&buf, &h), Some(5));
    }
}

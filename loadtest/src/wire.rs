//! MQTT 3.1.1 and 5 packets as raw bytes, and the byte-level mutations of the `mutate`
//! and `churn` campaigns.
//!
//! The campaigns must send what no MQTT client library would: a CONNECT whose remaining
//! length says 256 MB, a topic with a lone UTF-8 continuation byte, a PUBLISH cut off
//! in the middle. So they build every packet here, byte by byte, from the specifications
//! (MQTT 3.1.1 section 3, MQTT 5.0 section 3), and [`mutate`] corrupts the bytes.

use crate::rng::Rng;

/// Protocol levels of the CONNECT packet.
pub const V311: u8 = 4;
pub const V5: u8 = 5;

/// The largest remaining length MQTT can encode (4 varint bytes).
pub const MAX_REMAINING: u32 = 268_435_455;

/// A variable byte integer (remaining length, property lengths); values above
/// [`MAX_REMAINING`] are encoded anyway, in more than 4 bytes (which is malformed).
pub fn varint(mut n: u64) -> Vec<u8> {
    let mut out = Vec::with_capacity(4);
    loop {
        let mut byte = (n % 128) as u8;
        n /= 128;
        if n > 0 {
            byte |= 0x80;
        }
        out.push(byte);
        if n == 0 {
            return out;
        }
    }
}

/// A UTF-8 string or binary data field: a two-byte length, then the bytes (longer input
/// is cut at 65,535 bytes).
pub fn string(s: &[u8]) -> Vec<u8> {
    let s = &s[..s.len().min(u16::MAX as usize)];
    let mut out = Vec::with_capacity(2 + s.len());
    out.extend_from_slice(&(s.len() as u16).to_be_bytes());
    out.extend_from_slice(s);
    out
}

/// Fixed header (`first` byte, remaining length) + body.
pub fn packet(first: u8, body: &[u8]) -> Vec<u8> {
    let mut out = Vec::with_capacity(5 + body.len());
    out.push(first);
    out.extend(varint(body.len() as u64));
    out.extend_from_slice(body);
    out
}

/// MQTT 5 properties, encoded in the order added (duplicates and properties not allowed in
/// the packet are the caller's choice: the campaigns send both on purpose).
#[derive(Debug, Clone, Default)]
pub struct Props(Vec<u8>);

impl Props {
    pub fn new() -> Props {
        Props::default()
    }
    pub fn is_empty(&self) -> bool {
        self.0.is_empty()
    }
    pub fn byte(mut self, id: u8, v: u8) -> Props {
        self.0.extend([id, v]);
        self
    }
    pub fn u16(mut self, id: u8, v: u16) -> Props {
        self.0.push(id);
        self.0.extend(v.to_be_bytes());
        self
    }
    pub fn u32(mut self, id: u8, v: u32) -> Props {
        self.0.push(id);
        self.0.extend(v.to_be_bytes());
        self
    }
    pub fn varint(mut self, id: u8, v: u64) -> Props {
        self.0.push(id);
        self.0.extend(varint(v));
        self
    }
    pub fn string(mut self, id: u8, s: &[u8]) -> Props {
        self.0.push(id);
        self.0.extend(string(s));
        self
    }
    pub fn pair(mut self, id: u8, k: &[u8], v: &[u8]) -> Props {
        self.0.push(id);
        self.0.extend(string(k));
        self.0.extend(string(v));
        self
    }
    /// Raw bytes (a random property id, a truncated value).
    pub fn raw(mut self, bytes: &[u8]) -> Props {
        self.0.extend_from_slice(bytes);
        self
    }
    /// Property length + properties, as they appear in a packet.
    pub fn encode(&self) -> Vec<u8> {
        let mut out = varint(self.0.len() as u64);
        out.extend_from_slice(&self.0);
        out
    }
}

/// MQTT 5 property identifiers used by the campaigns.
pub mod prop {
    pub const PAYLOAD_FORMAT: u8 = 0x01;
    pub const MESSAGE_EXPIRY: u8 = 0x02;
    pub const CONTENT_TYPE: u8 = 0x03;
    pub const RESPONSE_TOPIC: u8 = 0x08;
    pub const CORRELATION_DATA: u8 = 0x09;
    pub const SUBSCRIPTION_ID: u8 = 0x0B;
    pub const SESSION_EXPIRY: u8 = 0x11;
    pub const AUTH_METHOD: u8 = 0x15;
    pub const REQUEST_PROBLEM_INFO: u8 = 0x17;
    pub const WILL_DELAY: u8 = 0x18;
    pub const RECEIVE_MAXIMUM: u8 = 0x21;
    pub const TOPIC_ALIAS_MAXIMUM: u8 = 0x22;
    pub const TOPIC_ALIAS: u8 = 0x23;
    pub const USER_PROPERTY: u8 = 0x26;
    pub const MAX_PACKET_SIZE: u8 = 0x27;
}

/// A last will.
#[derive(Debug, Clone)]
pub struct Will {
    pub topic: Vec<u8>,
    pub payload: Vec<u8>,
    pub qos: u8,
    pub retain: bool,
    /// MQTT 5 only.
    pub properties: Props,
}

/// A CONNECT packet.
#[derive(Debug, Clone)]
pub struct Connect {
    /// 4 (3.1.1) or 5; anything else is sent as given.
    pub level: u8,
    pub client_id: Vec<u8>,
    pub clean: bool,
    pub keep_alive: u16,
    pub will: Option<Will>,
    pub username: Option<Vec<u8>>,
    pub password: Option<Vec<u8>>,
    /// MQTT 5 only.
    pub properties: Props,
}

impl Connect {
    /// A plain clean CONNECT: `client_id`, keep-alive 60 s, no will, no login.
    pub fn new(level: u8, client_id: impl Into<Vec<u8>>) -> Connect {
        Connect {
            level,
            client_id: client_id.into(),
            clean: true,
            keep_alive: 60,
            will: None,
            username: None,
            password: None,
            properties: Props::new(),
        }
    }

    pub fn encode(&self) -> Vec<u8> {
        let v5 = self.level == V5;
        let mut flags = 0u8;
        if self.clean {
            flags |= 0x02;
        }
        if let Some(w) = &self.will {
            flags |= 0x04 | ((w.qos & 3) << 3);
            if w.retain {
                flags |= 0x20;
            }
        }
        if self.password.is_some() {
            flags |= 0x40;
        }
        if self.username.is_some() {
            flags |= 0x80;
        }
        let mut body = string(b"MQTT");
        body.push(self.level);
        body.push(flags);
        body.extend(self.keep_alive.to_be_bytes());
        if v5 {
            body.extend(self.properties.encode());
        }
        body.extend(string(&self.client_id));
        if let Some(w) = &self.will {
            if v5 {
                body.extend(w.properties.encode());
            }
            body.extend(string(&w.topic));
            body.extend(string(&w.payload));
        }
        if let Some(u) = &self.username {
            body.extend(string(u));
        }
        if let Some(p) = &self.password {
            body.extend(string(p));
        }
        packet(0x10, &body)
    }
}

/// PUBLISH; `pid` is written only for QoS > 0 (QoS 3 is sent as asked: malformed).
#[allow(clippy::too_many_arguments)]
pub fn publish(
    level: u8,
    topic: &[u8],
    qos: u8,
    retain: bool,
    dup: bool,
    pid: u16,
    props: &Props,
    payload: &[u8],
) -> Vec<u8> {
    let first = 0x30 | (u8::from(dup) << 3) | ((qos & 3) << 1) | u8::from(retain);
    let mut body = string(topic);
    if qos > 0 {
        body.extend(pid.to_be_bytes());
    }
    if level == V5 {
        body.extend(props.encode());
    }
    body.extend_from_slice(payload);
    packet(first, &body)
}

/// SUBSCRIBE with (filter, options) pairs; options are the QoS in 3.1.1, QoS | no-local
/// << 2 | retain-as-published << 3 | retain handling << 4 in 5.
pub fn subscribe(level: u8, pid: u16, props: &Props, filters: &[(Vec<u8>, u8)]) -> Vec<u8> {
    let mut body = pid.to_be_bytes().to_vec();
    if level == V5 {
        body.extend(props.encode());
    }
    for (f, options) in filters {
        body.extend(string(f));
        body.push(*options);
    }
    packet(0x82, &body)
}

pub fn unsubscribe(level: u8, pid: u16, props: &Props, filters: &[Vec<u8>]) -> Vec<u8> {
    let mut body = pid.to_be_bytes().to_vec();
    if level == V5 {
        body.extend(props.encode());
    }
    for f in filters {
        body.extend(string(f));
    }
    packet(0xA2, &body)
}

/// PUBACK (0x40), PUBREC (0x50), PUBREL (0x62) or PUBCOMP (0x70); in MQTT 5 with a
/// reason code when given.
pub fn ack(first: u8, level: u8, pid: u16, reason: Option<u8>) -> Vec<u8> {
    let mut body = pid.to_be_bytes().to_vec();
    if let (V5, Some(r)) = (level, reason) {
        body.push(r);
    }
    packet(first, &body)
}

pub fn pingreq() -> Vec<u8> {
    vec![0xC0, 0x00]
}

/// DISCONNECT; MQTT 5 with a reason code when given.
pub fn disconnect(level: u8, reason: Option<u8>) -> Vec<u8> {
    match (level, reason) {
        (V5, Some(r)) => packet(0xE0, &[r, 0]),
        _ => vec![0xE0, 0x00],
    }
}

/// MQTT 5 AUTH.
pub fn auth(reason: u8, props: &Props) -> Vec<u8> {
    let mut body = vec![reason];
    body.extend(props.encode());
    packet(0xF0, &body)
}

/// The length of the first complete packet in `buf`: `Some(Ok(n))`, `None` while
/// incomplete, `Some(Err(()))` if its remaining length is malformed.
pub fn frame_len(buf: &[u8]) -> Option<Result<usize, ()>> {
    let mut len: usize = 0;
    for i in 0..4 {
        let byte = *buf.get(1 + i)?;
        len |= usize::from(byte & 0x7F) << (7 * i);
        if byte & 0x80 == 0 {
            let total = 2 + i + len;
            return (buf.len() >= total).then_some(Ok(total));
        }
    }
    Some(Err(()))
}

/// The first bytes (type and flags) of the complete packets at the start of `buf`, in
/// order, up to the first incomplete or malformed one.
pub fn packet_types(buf: &[u8]) -> Vec<u8> {
    let mut types = Vec::new();
    let mut rest = buf;
    while let Some(Ok(len)) = frame_len(rest) {
        types.push(rest[0]);
        rest = &rest[len..];
    }
    types
}

/// The broker's first packet on a connection, as far as the campaigns care.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Answer {
    /// CONNACK with its return code (3.1.1) or reason code (5): 0 accepted.
    Connack(u8),
    /// Another packet type (its first byte), or a malformed one.
    Other(u8),
}

/// The first complete packet of `buf`, if there is one.
pub fn first_answer(buf: &[u8]) -> Option<Answer> {
    let first = *buf.first()?;
    match frame_len(buf)? {
        Err(()) => Some(Answer::Other(first)),
        Ok(total) => {
            let header = total - remaining_of(buf);
            if first == 0x20 && total >= header + 2 {
                Some(Answer::Connack(buf[header + 1]))
            } else {
                Some(Answer::Other(first))
            }
        }
    }
}

/// The remaining length of a complete packet at the start of `buf` (0 if malformed).
fn remaining_of(buf: &[u8]) -> usize {
    let mut len = 0usize;
    for i in 0..4 {
        let Some(byte) = buf.get(1 + i) else { return 0 };
        len |= usize::from(byte & 0x7F) << (7 * i);
        if byte & 0x80 == 0 {
            return len;
        }
    }
    0
}

/// Bytes of the fixed header of `pkt` (1 + the remaining length's bytes; 2 when it
/// cannot be read).
pub fn header_len(pkt: &[u8]) -> usize {
    for i in 0..4 {
        match pkt.get(1 + i) {
            Some(b) if b & 0x80 == 0 => return 2 + i,
            Some(_) => {}
            None => return pkt.len().clamp(1, 2),
        }
    }
    2
}

/// The byte-level mutations.
#[derive(Debug, Clone, Copy, PartialEq, Eq, PartialOrd, Ord)]
pub enum Mutation {
    /// 1-4 random bits flipped anywhere.
    BitFlip,
    /// 1-8 random bytes inserted at a random position.
    InsertBytes,
    /// 1-8 bytes removed at a random position.
    DeleteBytes,
    /// Cut at a random length: the rest of the stream is read as this packet's body.
    Truncate,
    /// The remaining length rewritten to another plausible value (0, ±1, double, random).
    LengthField,
    /// The remaining length as a variable byte integer of 5 or more bytes.
    VarintOverflow,
    /// The remaining length set to MQTT's maximum (256 MB) or to 1 MiB, the body unchanged.
    OversizedLength,
    /// A random first byte: any packet type (0 and 15 included) with any flags.
    PacketType,
    /// The fixed header's flag bits flipped (reserved flags, QoS 3, DUP on QoS 0).
    Flags,
    /// The first string's two-byte length (protocol name, topic, first filter; in MQTT 5
    /// SUBSCRIBE and UNSUBSCRIBE the property length and what follows) set to 0, 65,535 or
    /// a random value.
    StringLength,
    /// The packet sent twice in a row (for CONNECT: a second CONNECT).
    Duplicate,
}

impl Mutation {
    pub const ALL: [Mutation; 11] = [
        Mutation::BitFlip,
        Mutation::InsertBytes,
        Mutation::DeleteBytes,
        Mutation::Truncate,
        Mutation::LengthField,
        Mutation::VarintOverflow,
        Mutation::OversizedLength,
        Mutation::PacketType,
        Mutation::Flags,
        Mutation::StringLength,
        Mutation::Duplicate,
    ];

    pub fn name(self) -> &'static str {
        match self {
            Mutation::BitFlip => "bit_flip",
            Mutation::InsertBytes => "insert_bytes",
            Mutation::DeleteBytes => "delete_bytes",
            Mutation::Truncate => "truncate",
            Mutation::LengthField => "length_field",
            Mutation::VarintOverflow => "varint_overflow",
            Mutation::OversizedLength => "oversized_length",
            Mutation::PacketType => "packet_type",
            Mutation::Flags => "flags",
            Mutation::StringLength => "string_length",
            Mutation::Duplicate => "duplicate",
        }
    }
}

/// Applies one random mutation to `pkt` and says which.
pub fn mutate(rng: &mut Rng, pkt: &mut Vec<u8>) -> Mutation {
    let m = *rng.pick(&Mutation::ALL);
    apply(rng, pkt, m);
    m
}

/// Applies mutation `m` to `pkt`.
pub fn apply(rng: &mut Rng, pkt: &mut Vec<u8>, m: Mutation) {
    if pkt.is_empty() {
        pkt.push(rng.byte());
        return;
    }
    let header = header_len(pkt).min(pkt.len());
    let body_len = pkt.len() - header;
    let set_header = |pkt: &mut Vec<u8>, remaining: Vec<u8>| {
        let first = pkt[0];
        let body = pkt[header..].to_vec();
        pkt.clear();
        pkt.push(first);
        pkt.extend(remaining);
        pkt.extend(body);
    };
    match m {
        Mutation::BitFlip => {
            for _ in 0..rng.range(1, 4) {
                let at = rng.index(pkt.len());
                pkt[at] ^= 1 << rng.below(8);
            }
        }
        Mutation::InsertBytes => {
            let at = rng.index(pkt.len() + 1);
            let n = rng.range(1, 8) as usize;
            let bytes = rng.bytes(n);
            pkt.splice(at..at, bytes);
        }
        Mutation::DeleteBytes => {
            let at = rng.index(pkt.len());
            let n = (rng.range(1, 8) as usize).min(pkt.len() - at);
            pkt.drain(at..at + n);
        }
        Mutation::Truncate => {
            let keep = if pkt.len() > 1 {
                rng.range(1, pkt.len() as u64 - 1) as usize
            } else {
                0
            };
            pkt.truncate(keep);
        }
        Mutation::LengthField => {
            let n = body_len as u64;
            let new = match rng.below(6) {
                0 => 0,
                1 => n.saturating_sub(1),
                2 => n + 1,
                3 => n * 2 + 1,
                4 => n + rng.range(2, 64),
                _ => rng.below(1 << 14),
            };
            set_header(pkt, varint(new));
        }
        Mutation::VarintOverflow => {
            let remaining = match rng.below(3) {
                0 => vec![0xFF, 0xFF, 0xFF, 0xFF, 0x7F],
                1 => vec![0x80; 5],
                _ => vec![0xFF, 0xFF, 0xFF, 0xFF, 0xFF, 0xFF, 0x01],
            };
            set_header(pkt, remaining);
        }
        Mutation::OversizedLength => {
            let remaining = if rng.chance(0.5) {
                varint(u64::from(MAX_REMAINING))
            } else {
                varint(1 << 20)
            };
            set_header(pkt, remaining);
        }
        Mutation::PacketType => pkt[0] = rng.byte(),
        Mutation::Flags => pkt[0] ^= rng.range(1, 15) as u8,
        Mutation::StringLength => {
            // CONNECT and PUBLISH start their body with a string; SUBSCRIBE and
            // UNSUBSCRIBE with a packet identifier, then (3.1.1) the first filter.
            let at = match pkt[0] >> 4 {
                8 | 10 => header + 2,
                _ => header,
            };
            if at + 2 <= pkt.len() {
                let old = u16::from_be_bytes([pkt[at], pkt[at + 1]]);
                let mut len: u16 = match rng.below(3) {
                    0 => 0,
                    1 => u16::MAX,
                    _ => rng.next_u64() as u16,
                };
                if len == old {
                    len = !old;
                }
                pkt[at..at + 2].copy_from_slice(&len.to_be_bytes());
            } else {
                let at = rng.index(pkt.len());
                pkt[at] ^= 0xFF;
            }
        }
        Mutation::Duplicate => {
            let copy = pkt.clone();
            pkt.extend(copy);
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn connect_3_1_1_matches_the_spec_example() {
        // MQTT 3.1.1 section 3.1: "MQTT", level 4, clean session, keep-alive 60, id "a".
        let c = Connect::new(V311, "a");
        assert_eq!(
            c.encode(),
            [0x10, 13, 0, 4, b'M', b'Q', b'T', b'T', 4, 0x02, 0, 60, 0, 1, b'a']
        );
        let mut c = Connect::new(V5, "a");
        c.username = Some(b"u".to_vec());
        c.password = Some(b"p".to_vec());
        c.properties = Props::new().u32(prop::SESSION_EXPIRY, 10);
        let bytes = c.encode();
        assert_eq!(bytes[9], 0xC2, "username, password and clean start flags");
        assert_eq!(&bytes[12..18], &[5, 0x11, 0, 0, 0, 10], "properties");
        assert_eq!(frame_len(&bytes), Some(Ok(bytes.len())));
    }

    #[test]
    fn varints_and_frames() {
        assert_eq!(varint(0), [0]);
        assert_eq!(varint(127), [0x7F]);
        assert_eq!(varint(128), [0x80, 0x01]);
        assert_eq!(varint(u64::from(MAX_REMAINING)), [0xFF, 0xFF, 0xFF, 0x7F]);
        assert_eq!(varint(u64::from(MAX_REMAINING) + 1).len(), 5);
        let p = publish(
            V311,
            "é/x".as_bytes(),
            1,
            false,
            false,
            7,
            &Props::new(),
            b"hi",
        );
        assert_eq!(p[0], 0x32);
        assert_eq!(frame_len(&p), Some(Ok(p.len())));
        assert_eq!(frame_len(&p[..p.len() - 1]), None);
        assert_eq!(
            frame_len(&[0x30, 0xFF, 0xFF, 0xFF, 0xFF, 0x7F]),
            Some(Err(()))
        );
        assert_eq!(first_answer(&[0x20, 2, 0, 0]), Some(Answer::Connack(0)));
        assert_eq!(
            first_answer(&[0x20, 3, 0, 0x87, 0]),
            Some(Answer::Connack(0x87))
        );
        assert_eq!(first_answer(&[0x20, 2, 0]), None);
        assert_eq!(first_answer(&[0xD0, 0]), Some(Answer::Other(0xD0)));
        assert_eq!(
            packet_types(&[0x20, 2, 0, 0, 0x40, 2, 0, 1, 0xD0, 0, 0x90]),
            [0x20, 0x40, 0xD0]
        );
    }

    #[test]
    fn every_mutation_changes_the_bytes_and_never_panics() {
        let mut rng = Rng::new(1);
        let packets = [
            Connect::new(V5, "client").encode(),
            publish(V311, b"a/b", 0, false, false, 0, &Props::new(), b""),
            subscribe(V5, 1, &Props::new(), &[(b"#".to_vec(), 1)]),
            pingreq(),
            vec![0x30],
        ];
        for m in Mutation::ALL {
            for p in &packets {
                for _ in 0..50 {
                    let mut q = p.clone();
                    apply(&mut rng, &mut q, m);
                    if !matches!(
                        m,
                        Mutation::BitFlip | Mutation::Flags | Mutation::PacketType
                    ) && p.len() > 2
                    {
                        assert_ne!(&q, p, "{m:?} left {p:?} unchanged");
                    }
                }
            }
        }
        let mut q = pingreq();
        apply(&mut rng, &mut q, Mutation::VarintOverflow);
        assert!(matches!(frame_len(&q), Some(Err(()))), "{q:?}");
    }
}

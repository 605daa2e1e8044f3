//! The store's records: what is appended to the log, one change each, and their bytes.
//!
//! A record is a tag byte and its fields. Strings are a `u16` length and UTF-8 bytes, byte
//! strings a `u32` length; numbers are little-endian. A stored message is its MQTT 5
//! PUBLISH packet, written and read by rumqttd's v5 codec (the one the listeners use and
//! the fuzzers attack): topic, payload, QoS, RETAIN and properties in one tested encoding,
//! and a publisher's id beside it. Reading never trusts a length: every field is
//! bounds-checked, and a record that does not parse is corrupt, never a panic.

use std::sync::Arc;

use bytes::{Bytes, BytesMut};
use rumqttd::protocol::{v5::V5, Packet, Protocol, Publish, PublishProperties};

/// One stored message: a publication as it entered the router.
#[derive(Debug, Clone, PartialEq)]
pub struct Message {
    pub topic: Bytes,
    pub payload: Bytes,
    pub qos: u8,
    pub retain: bool,
    /// MQTT 5 properties as published (no topic alias, no subscription identifiers: those
    /// belong to one connection or one delivery).
    /// Boxed: most publications have none, and a message travels by value to the writer.
    pub properties: Option<Box<PublishProperties>>,
    /// The publishing client's id (No Local; retained messages keep their publisher).
    pub publisher: Arc<str>,
}

impl Message {
    /// The bytes this message keeps in the store's budget (`max_bytes`).
    pub fn size(&self) -> usize {
        self.topic.len() + self.payload.len() + self.publisher.len() + 16
    }
}

/// A subscription's options, as the client asked (MQTT 5 3.8.3.1).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Options {
    pub qos: u8,
    pub no_local: bool,
    pub retain_as_published: bool,
    /// Retain Handling 0, 1 or 2.
    pub retain_handling: u8,
    /// The Subscription Identifier (0: none).
    pub id: u32,
}

/// Where a QoS 2 delivery stands with the client.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Qos2 {
    /// PUBLISH sent under this packet id, no PUBREC yet.
    Sent(u16),
    /// PUBREC received for this packet id: PUBREL is what the client gets next.
    Received(u16),
}

/// A session's client id in records: shared with the session that writes them, so the
/// records of every acknowledgement do not each copy it.
pub type ClientId = Arc<str>;

#[derive(Debug, Clone, PartialEq)]
pub enum Record {
    /// A persistent session connected: `fresh` when it starts empty (no session was
    /// resumed). `expiry`: seconds it outlives its connection, None for never.
    Session {
        client: ClientId,
        owner: String,
        /// The identity whose store share its queue spends (`user:<name>`, or
        /// `address:<ip>` for a client without a verified username). Written last, so a
        /// record of an fbbus before it reads as the owner's (`share_of_owner`).
        share: String,
        v5: bool,
        expiry: Option<u32>,
        fresh: bool,
    },
    /// Its connection ended and the session is kept: offline since `at` (Unix seconds).
    Offline {
        client: ClientId,
        at: u64,
        expiry: Option<u32>,
    },
    /// The session is gone (clean connection, expiry, eviction): with its queue.
    Ended {
        client: ClientId,
    },
    Subscribe {
        client: ClientId,
        filter: String,
        options: Options,
    },
    Unsubscribe {
        client: ClientId,
        filter: String,
    },
    /// A publication: retained if `message.retain`, queued for every persistent session
    /// whose subscriptions match it at QoS 1 or 2.
    Publish {
        seq: u64,
        message: Message,
    },
    /// A message queued for exactly these sessions (written by compaction).
    Queued {
        seq: u64,
        message: Message,
        targets: Vec<Target>,
    },
    /// The client acknowledged (PUBACK, PUBCOMP) or was not to be sent message `seq`.
    Done {
        client: ClientId,
        seq: u64,
    },
    /// A QoS 2 delivery of message `seq` moved on.
    Qos2 {
        client: ClientId,
        seq: u64,
        state: Qos2,
    },
    /// A will with a delay, due at `due` (Unix milliseconds).
    Will {
        client: ClientId,
        due: u64,
        message: Message,
    },
    /// That will was published or cancelled.
    WillDone {
        client: ClientId,
    },
    /// The retained message on `topic` (the `Publish` before it) is charged to `share`
    /// (`retained_share`), so a restart charges it to the same identity.
    RetainedBy {
        topic: String,
        share: String,
    },
}

/// One session a `Queued` message waits for.
#[derive(Debug, Clone, PartialEq)]
pub struct Target {
    pub client: ClientId,
    pub qos: u8,
    pub qos2: Option<Qos2>,
}

/// A record that does not parse.
#[derive(Debug, thiserror::Error)]
#[error("{0}")]
pub struct Corrupt(pub &'static str);

const SESSION: u8 = 1;
const OFFLINE: u8 = 2;
const ENDED: u8 = 3;
const SUBSCRIBE: u8 = 4;
const UNSUBSCRIBE: u8 = 5;
const PUBLISH: u8 = 6;
const QUEUED: u8 = 7;
const DONE: u8 = 8;
const QOS2: u8 = 9;
const WILL: u8 = 10;
const WILL_DONE: u8 = 11;
const RETAINED_BY: u8 = 12;

/// The largest stored message: MQTT's own packet limit.
const MAX_MESSAGE: usize = 268_435_455 + 5;

impl Record {
    /// Appends the record's bytes to `out`.
    pub fn encode(&self, out: &mut Vec<u8>) {
        let mut w = Writer(out);
        match self {
            Record::Session {
                client,
                owner,
                share,
                v5,
                expiry,
                fresh,
            } => {
                w.u8(SESSION);
                w.str(client);
                w.str(owner);
                w.u8(*v5 as u8 | (*fresh as u8) << 1);
                w.expiry(*expiry);
                w.str(share);
            }
            Record::Offline { client, at, expiry } => {
                w.u8(OFFLINE);
                w.str(client);
                w.u64(*at);
                w.expiry(*expiry);
            }
            Record::Ended { client } => {
                w.u8(ENDED);
                w.str(client);
            }
            Record::Subscribe {
                client,
                filter,
                options,
            } => {
                w.u8(SUBSCRIBE);
                w.str(client);
                w.str(filter);
                w.u8(options.qos);
                w.u8(options.no_local as u8
                    | (options.retain_as_published as u8) << 1
                    | (options.retain_handling & 3) << 2);
                w.u32(options.id);
            }
            Record::Unsubscribe { client, filter } => {
                w.u8(UNSUBSCRIBE);
                w.str(client);
                w.str(filter);
            }
            Record::Publish { seq, message } => {
                w.u8(PUBLISH);
                w.u64(*seq);
                w.message(message);
            }
            Record::Queued {
                seq,
                message,
                targets,
            } => {
                w.u8(QUEUED);
                w.u64(*seq);
                w.message(message);
                w.u32(targets.len() as u32);
                for t in targets {
                    w.str(&t.client);
                    w.u8(t.qos);
                    w.qos2(t.qos2);
                }
            }
            Record::Done { client, seq } => encode_done(client, *seq, w.0),
            Record::Qos2 { client, seq, state } => {
                w.u8(QOS2);
                w.str(client);
                w.u64(*seq);
                w.qos2(Some(*state));
            }
            Record::Will {
                client,
                due,
                message,
            } => {
                w.u8(WILL);
                w.str(client);
                w.u64(*due);
                w.message(message);
            }
            Record::WillDone { client } => {
                w.u8(WILL_DONE);
                w.str(client);
            }
            Record::RetainedBy { topic, share } => {
                w.u8(RETAINED_BY);
                w.str(topic);
                w.str(share);
            }
        }
    }

    /// Reads one record from exactly `bytes`.
    pub fn decode(bytes: &[u8]) -> Result<Record, Corrupt> {
        let mut r = Reader(bytes);
        let record = match r.u8()? {
            SESSION => {
                let client: ClientId = r.str()?.into();
                let owner = r.str()?;
                let flags = r.u8()?;
                let expiry = r.expiry()?;
                let share = match r.0.is_empty() {
                    true => share_of_owner(&owner),
                    false => r.str()?,
                };
                Record::Session {
                    client,
                    owner,
                    share,
                    v5: flags & 1 != 0,
                    fresh: flags & 2 != 0,
                    expiry,
                }
            }
            OFFLINE => Record::Offline {
                client: r.str()?.into(),
                at: r.u64()?,
                expiry: r.expiry()?,
            },
            ENDED => Record::Ended {
                client: r.str()?.into(),
            },
            SUBSCRIBE => {
                let client: ClientId = r.str()?.into();
                let filter = r.str()?;
                let qos = r.u8()?;
                let flags = r.u8()?;
                Record::Subscribe {
                    client,
                    filter,
                    options: Options {
                        qos: qos.min(2),
                        no_local: flags & 1 != 0,
                        retain_as_published: flags & 2 != 0,
                        retain_handling: (flags >> 2) & 3,
                        id: r.u32()?,
                    },
                }
            }
            UNSUBSCRIBE => Record::Unsubscribe {
                client: r.str()?.into(),
                filter: r.str()?,
            },
            PUBLISH => Record::Publish {
                seq: r.u64()?,
                message: r.message()?,
            },
            QUEUED => {
                let seq = r.u64()?;
                let message = r.message()?;
                let n = r.u32()? as usize;
                // Each target takes at least 4 bytes: a count beyond the record is corrupt.
                if n > r.0.len() / 4 {
                    return Err(Corrupt("target count beyond the record"));
                }
                let mut targets = Vec::with_capacity(n);
                for _ in 0..n {
                    targets.push(Target {
                        client: r.str()?.into(),
                        qos: r.u8()?.min(2),
                        qos2: r.qos2()?,
                    });
                }
                Record::Queued {
                    seq,
                    message,
                    targets,
                }
            }
            DONE => Record::Done {
                client: r.str()?.into(),
                seq: r.u64()?,
            },
            QOS2 => {
                let client: ClientId = r.str()?.into();
                let seq = r.u64()?;
                let state = r.qos2()?.ok_or(Corrupt("QoS 2 record without a state"))?;
                Record::Qos2 { client, seq, state }
            }
            WILL => Record::Will {
                client: r.str()?.into(),
                due: r.u64()?,
                message: r.message()?,
            },
            WILL_DONE => Record::WillDone {
                client: r.str()?.into(),
            },
            RETAINED_BY => Record::RetainedBy {
                topic: r.str()?,
                share: r.str()?,
            },
            _ => return Err(Corrupt("unknown record type")),
        };
        if !r.0.is_empty() {
            return Err(Corrupt("bytes after the record"));
        }
        Ok(record)
    }
}

/// The share of a session recorded before shares were (issue 33): its owner's, and one
/// for every anonymous session.
pub fn share_of_owner(owner: &str) -> String {
    match owner {
        "" => "anonymous".to_owned(),
        user => format!("user:{user}"),
    }
}

/// A `Done` record's body, written without building a [`Record`] (the writer writes one
/// for every delivered stored message, from the numbers in a session's journal).
pub fn encode_done(client: &str, seq: u64, out: &mut Vec<u8>) {
    let mut w = Writer(out);
    w.u8(DONE);
    w.str(client);
    w.u64(seq);
}

struct Writer<'a>(&'a mut Vec<u8>);

impl Writer<'_> {
    fn u8(&mut self, v: u8) {
        self.0.push(v);
    }
    fn u32(&mut self, v: u32) {
        self.0.extend_from_slice(&v.to_le_bytes());
    }
    fn u64(&mut self, v: u64) {
        self.0.extend_from_slice(&v.to_le_bytes());
    }
    /// Strings the store writes are client ids, usernames and topic filters, which MQTT
    /// limits to 65,535 bytes; a longer one is cut at a character boundary.
    fn str(&mut self, s: &str) {
        let mut end = s.len().min(u16::MAX as usize);
        while !s.is_char_boundary(end) {
            end -= 1;
        }
        self.0.extend_from_slice(&(end as u16).to_le_bytes());
        self.0.extend_from_slice(&s.as_bytes()[..end]);
    }
    fn bytes(&mut self, b: &[u8]) {
        self.u32(b.len() as u32);
        self.0.extend_from_slice(b);
    }
    fn expiry(&mut self, e: Option<u32>) {
        match e {
            None => self.u8(0),
            Some(secs) => {
                self.u8(1);
                self.u32(secs);
            }
        }
    }
    fn qos2(&mut self, q: Option<Qos2>) {
        match q {
            None => self.u8(0),
            Some(Qos2::Sent(pkid)) => {
                self.u8(1);
                self.0.extend_from_slice(&pkid.to_le_bytes());
            }
            Some(Qos2::Received(pkid)) => {
                self.u8(2);
                self.0.extend_from_slice(&pkid.to_le_bytes());
            }
        }
    }
    /// A message as the v5 PUBLISH packet MQTT would carry (packet id 1 for QoS 1/2: it
    /// means nothing here), then its publisher.
    fn message(&mut self, m: &Message) {
        if m.properties.is_some() || !self.plain_publish(m) {
            self.publish_with_properties(m);
        }
        self.str(&m.publisher);
    }

    /// The common case, a PUBLISH without properties, written straight into the record:
    /// the same bytes rumqttd writes (`plain_publish_is_what_rumqttd_writes`), without its
    /// intermediate buffer and reference-counted copies. False (nothing written) for sizes
    /// MQTT cannot carry.
    fn plain_publish(&mut self, m: &Message) -> bool {
        let qos = m.qos.min(2);
        let remaining = 2 + m.topic.len() + if qos > 0 { 2 } else { 0 } + 1 + m.payload.len();
        if m.topic.len() > u16::MAX as usize || remaining > MAX_REMAINING_LENGTH {
            return false;
        }
        let mut length = [0u8; 4];
        let mut n = 0;
        let mut rest = remaining;
        loop {
            let mut byte = (rest % 128) as u8;
            rest /= 128;
            if rest > 0 {
                byte |= 0x80;
            }
            length[n] = byte;
            n += 1;
            if rest == 0 {
                break;
            }
        }
        self.u32((1 + n + remaining) as u32);
        self.u8(0b0011_0000 | u8::from(m.retain) | (qos << 1));
        self.0.extend_from_slice(&length[..n]);
        self.0
            .extend_from_slice(&(m.topic.len() as u16).to_be_bytes());
        self.0.extend_from_slice(&m.topic);
        if qos > 0 {
            self.0.extend_from_slice(&1u16.to_be_bytes());
        }
        // No properties: their length, 0.
        self.u8(0);
        self.0.extend_from_slice(&m.payload);
        true
    }

    fn publish_with_properties(&mut self, m: &Message) {
        let mut publish = Publish::with_qos(
            m.topic.clone(),
            m.payload.clone(),
            m.qos.min(2),
            m.retain,
            // A QoS 1/2 PUBLISH needs a packet id on the wire; it means nothing here.
            u16::from(m.qos > 0),
        );
        publish.origin = None;
        let properties = m.properties.clone().map(|mut p| {
            p.topic_alias = None;
            p.subscription_identifiers.clear();
            p
        });
        let mut packet = BytesMut::with_capacity(m.topic.len() + m.payload.len() + 64);
        // Writing a PUBLISH fails only for sizes MQTT cannot carry, which nothing that
        // entered through a listener has; such a message is stored without properties.
        let (topic, payload) = (publish.topic.clone(), publish.payload.clone());
        if V5
            .write(Packet::Publish(publish, properties), &mut packet)
            .is_err()
        {
            packet.clear();
            let publish =
                Publish::with_qos(topic, payload, m.qos.min(2), m.retain, u16::from(m.qos > 0));
            let _ = V5.write(Packet::Publish(publish, None), &mut packet);
        }
        self.bytes(&packet);
    }
}

/// The largest Remaining Length MQTT can encode (four bytes of 7 bits).
const MAX_REMAINING_LENGTH: usize = 268_435_455;

struct Reader<'a>(&'a [u8]);

impl Reader<'_> {
    fn take(&mut self, n: usize) -> Result<&[u8], Corrupt> {
        if n > self.0.len() {
            return Err(Corrupt("field beyond the record"));
        }
        let (head, rest) = self.0.split_at(n);
        self.0 = rest;
        Ok(head)
    }
    fn u8(&mut self) -> Result<u8, Corrupt> {
        Ok(self.take(1)?[0])
    }
    fn u16(&mut self) -> Result<u16, Corrupt> {
        let b = self.take(2)?;
        Ok(u16::from_le_bytes([b[0], b[1]]))
    }
    fn u32(&mut self) -> Result<u32, Corrupt> {
        let b = self.take(4)?;
        Ok(u32::from_le_bytes([b[0], b[1], b[2], b[3]]))
    }
    fn u64(&mut self) -> Result<u64, Corrupt> {
        let b = self.take(8)?;
        let mut a = [0u8; 8];
        a.copy_from_slice(b);
        Ok(u64::from_le_bytes(a))
    }
    fn str(&mut self) -> Result<String, Corrupt> {
        let n = self.u16()? as usize;
        let b = self.take(n)?;
        String::from_utf8(b.to_vec()).map_err(|_| Corrupt("string not UTF-8"))
    }
    fn expiry(&mut self) -> Result<Option<u32>, Corrupt> {
        match self.u8()? {
            0 => Ok(None),
            1 => Ok(Some(self.u32()?)),
            _ => Err(Corrupt("bad expiry")),
        }
    }
    fn qos2(&mut self) -> Result<Option<Qos2>, Corrupt> {
        match self.u8()? {
            0 => Ok(None),
            1 => Ok(Some(Qos2::Sent(self.u16()?))),
            2 => Ok(Some(Qos2::Received(self.u16()?))),
            _ => Err(Corrupt("bad QoS 2 state")),
        }
    }
    fn message(&mut self) -> Result<Message, Corrupt> {
        let n = self.u32()? as usize;
        if n > MAX_MESSAGE {
            return Err(Corrupt("message larger than MQTT allows"));
        }
        let mut packet = BytesMut::from(self.take(n)?);
        let (publish, properties) = match V5.read_mut(&mut packet, MAX_MESSAGE) {
            Ok(Packet::Publish(publish, properties)) => (publish, properties),
            _ => return Err(Corrupt("stored message is not a PUBLISH")),
        };
        let publisher: Arc<str> = self.str()?.into();
        let (qos, _) = publish.qos_and_pkid();
        Ok(Message {
            topic: publish.topic,
            payload: publish.payload,
            qos,
            retain: publish.retain,
            properties,
            publisher,
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn message() -> Message {
        Message {
            topic: Bytes::from_static("Förderband/1/é".as_bytes()),
            payload: Bytes::from_static(b"\x00\xffpayload"),
            qos: 2,
            retain: true,
            properties: Some(Box::new(PublishProperties {
                user_properties: vec![("a".into(), "1".into()), ("a".into(), "2".into())],
                content_type: Some("application/json".into()),
                message_expiry_interval: Some(60),
                ..Default::default()
            })),
            publisher: "plc-1".into(),
        }
    }

    #[test]
    fn plain_publish_is_what_rumqttd_writes() {
        // Sizes around each step of the Remaining Length (1, 2 and 3 bytes), each QoS.
        for payload_len in [0, 1, 120, 127, 128, 16_380, 16_384, 70_000] {
            for qos in 0..=2 {
                for retain in [false, true] {
                    let m = Message {
                        topic: Bytes::from_static("Förderband/1/é".as_bytes()),
                        payload: Bytes::from(vec![0xa5; payload_len]),
                        qos,
                        retain,
                        properties: None,
                        publisher: "plc-1".into(),
                    };
                    let (mut fast, mut slow) = (Vec::new(), Vec::new());
                    assert!(Writer(&mut fast).plain_publish(&m));
                    Writer(&mut slow).publish_with_properties(&m);
                    assert_eq!(
                        fast, slow,
                        "{payload_len} bytes, QoS {qos}, retain {retain}"
                    );
                }
            }
        }
    }

    #[test]
    fn every_record_reads_back_as_written() {
        let records = vec![
            Record::Session {
                client: "plc-1".into(),
                owner: "alice".into(),
                share: "user:alice".into(),
                v5: true,
                expiry: Some(300),
                fresh: true,
            },
            Record::Offline {
                client: "plc-1".into(),
                at: 1_700_000_000,
                expiry: None,
            },
            Record::Ended {
                client: "plc-1".into(),
            },
            Record::Subscribe {
                client: "plc-1".into(),
                filter: "fb/+/é/#".into(),
                options: Options {
                    qos: 2,
                    no_local: true,
                    retain_as_published: true,
                    retain_handling: 2,
                    id: 268_435_455,
                },
            },
            Record::Unsubscribe {
                client: "plc-1".into(),
                filter: "a".into(),
            },
            Record::Publish {
                seq: 7,
                message: message(),
            },
            Record::Queued {
                seq: 8,
                message: Message {
                    qos: 0,
                    properties: None,
                    ..message()
                },
                targets: vec![
                    Target {
                        client: "a".into(),
                        qos: 1,
                        qos2: None,
                    },
                    Target {
                        client: "b".into(),
                        qos: 2,
                        qos2: Some(Qos2::Received(65535)),
                    },
                ],
            },
            Record::Done {
                client: "a".into(),
                seq: u64::MAX,
            },
            Record::Qos2 {
                client: "a".into(),
                seq: 1,
                state: Qos2::Sent(1),
            },
            Record::Will {
                client: "a".into(),
                due: 5,
                message: message(),
            },
            Record::WillDone { client: "a".into() },
            Record::RetainedBy {
                topic: "fb/plc-1/CONV/Geschwindigkeit/é".into(),
                share: "user:plc-1".into(),
            },
        ];
        for record in records {
            let mut bytes = Vec::new();
            record.encode(&mut bytes);
            assert_eq!(Record::decode(&bytes).unwrap(), record);
            // Every strict prefix is corrupt, never a panic; except a session record cut
            // before its share, which is how fbbus wrote it before shares.
            for cut in 0..bytes.len() {
                if let Record::Session { owner, share, .. } = &record {
                    if cut == bytes.len() - 2 - share.len() {
                        let Ok(Record::Session { share: read, .. }) = Record::decode(&bytes[..cut])
                        else {
                            panic!("a session record without its share does not read");
                        };
                        assert_eq!(read, share_of_owner(owner));
                        continue;
                    }
                }
                assert!(
                    Record::decode(&bytes[..cut]).is_err(),
                    "{record:?} cut at {cut}"
                );
            }
        }
    }

    #[test]
    fn lengths_beyond_the_record_are_corrupt() {
        let mut bytes = vec![QUEUED];
        bytes.extend_from_slice(&1u64.to_le_bytes());
        bytes.extend_from_slice(&u32::MAX.to_le_bytes());
        assert!(Record::decode(&bytes).is_err());
        assert!(Record::decode(&[SESSION, 0xff, 0xff]).is_err());
        assert!(Record::decode(&[200]).is_err());
    }
}

//! What each bridged message carries, and how a receiving line drops the copies zenoh
//! delivers more than once.

use std::collections::{HashMap, HashSet, VecDeque};

/// What travels with every bridged message as its zenoh attachment.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Stamp {
    /// The line whose broker accepted the message from its publisher.
    pub line: String,
    /// The origin bridge's start time (µs): a restarted bridge counts from 1 again.
    pub epoch: u64,
    /// Per origin bridge, 1, 2, 3, ...; 0 for replies to a retained-message query.
    pub seq: u64,
    /// Per origin bridge and topic, 1, 2, 3, ...: every line that takes a topic takes
    /// all of its messages, so a gap is a message lost on the way ([`Gaps`]). 0: not
    /// numbered (a retained-message reply, or a stamp of version 1).
    pub topic_seq: u64,
    pub qos: u8,
    pub retain: bool,
}

/// Version 2 added `topic_seq`; version 1 stamps are still read.
const STAMP_VERSION: u8 = 2;

impl Stamp {
    /// `[version, flags, epoch (8, BE), seq (8, BE), topic_seq (8, BE), line (UTF-8)]`;
    /// flags: bits 0-1 QoS, bit 2 RETAIN. Version 1 had no `topic_seq`.
    pub fn encode(&self) -> Vec<u8> {
        let mut out = Vec::with_capacity(26 + self.line.len());
        out.push(STAMP_VERSION);
        out.push(self.qos.min(2) | (self.retain as u8) << 2);
        out.extend_from_slice(&self.epoch.to_be_bytes());
        out.extend_from_slice(&self.seq.to_be_bytes());
        out.extend_from_slice(&self.topic_seq.to_be_bytes());
        out.extend_from_slice(self.line.as_bytes());
        out
    }

    pub fn decode(bytes: &[u8]) -> Option<Stamp> {
        let (topic_seq, line) = match bytes.first() {
            Some(1) if bytes.len() >= 18 => (0, &bytes[18..]),
            Some(2) if bytes.len() >= 26 => (
                u64::from_be_bytes(bytes[18..26].try_into().ok()?),
                &bytes[26..],
            ),
            _ => return None,
        };
        let flags = bytes[1];
        // MQTT has no QoS 3: not a stamp a line writes.
        if flags & 0b11 == 3 {
            return None;
        }
        Some(Stamp {
            qos: flags & 0b11,
            retain: flags & 0b100 != 0,
            epoch: u64::from_be_bytes(bytes[2..10].try_into().ok()?),
            seq: u64::from_be_bytes(bytes[10..18].try_into().ok()?),
            topic_seq,
            line: std::str::from_utf8(line).ok()?.to_owned(),
        })
    }
}

/// How many sequence numbers per origin [`Dedup`] remembers.
pub const DEDUP_WINDOW: u64 = 4096;

/// Origin lines [`Dedup`] keeps windows for; past this many it starts over. A plant has
/// tens of lines; the broker feeds it only messages of devices their line declared, so
/// reaching this takes a bus of more lines than any plant has, or a stranger on an
/// unauthenticated loopback bus. Starting over may let one repeat in flight through.
pub const DEDUP_ORIGINS: usize = 1024;

/// Drops messages already seen, per origin line: a sliding window of sequence numbers
/// (at most [`DEDUP_WINDOW`] per origin, [`DEDUP_ORIGINS`] origins).
#[derive(Debug, Default)]
pub struct Dedup {
    origins: HashMap<String, Window>,
}

#[derive(Debug, Default)]
struct Window {
    epoch: u64,
    highest: u64,
    seen: HashSet<u64>,
    order: VecDeque<u64>,
}

impl Dedup {
    /// Whether the message is new (and now remembered). A new epoch of an origin (its
    /// bridge restarted) starts a new window.
    pub fn first_time(&mut self, stamp: &Stamp) -> bool {
        if stamp.seq == 0 {
            return true;
        }
        if !self.origins.contains_key(&stamp.line) {
            if self.origins.len() >= DEDUP_ORIGINS {
                self.origins.clear();
            }
            self.origins.insert(stamp.line.clone(), Window::default());
        }
        let w = self
            .origins
            .get_mut(&stamp.line)
            .expect("inserted just above");
        if stamp.epoch != w.epoch {
            if stamp.epoch < w.epoch {
                // A message of an older incarnation still in flight: its seq space is gone.
                return false;
            }
            *w = Window {
                epoch: stamp.epoch,
                ..Window::default()
            };
        }
        if w.highest.saturating_sub(stamp.seq) >= DEDUP_WINDOW || !w.seen.insert(stamp.seq) {
            return false;
        }
        w.highest = w.highest.max(stamp.seq);
        w.order.push_back(stamp.seq);
        while w.order.len() as u64 > DEDUP_WINDOW {
            if let Some(old) = w.order.pop_front() {
                w.seen.remove(&old);
            }
        }
        true
    }
}

/// Topics [`Gaps`] follows; past this many it starts over (and misses the gaps of
/// messages in flight at that moment).
pub const GAP_TOPICS: usize = 10_000;

/// Messages of other lines that never arrived: per origin line and topic, the gaps in
/// [`Stamp::topic_seq`] (a zenoh router that died with messages queued, a link cut).
///
/// Counted from the second message of a topic on (the first only starts the count), and
/// again from scratch when the origin restarts (a new epoch) or numbers the topic anew
/// (its bridge's cache of topics started over). A gap is also counted when this line's
/// own interest in the topic lapsed and came back, since the origin went on numbering
/// for the other lines meanwhile.
///
/// It also keeps each topic's order: a message older than one already taken of its
/// topic (it came the long way, through a second router, and the copy of a newer one
/// overtook it) is late, and dropped.
#[derive(Debug, Default)]
pub struct Gaps {
    /// origin line -> topic -> the last message taken; looked up without allocating.
    last: HashMap<String, HashMap<String, Last>>,
    topics: usize,
}

/// The last message of a topic [`Gaps`] took: its origin's epoch, its `topic_seq` and
/// its `seq`.
#[derive(Debug, Clone, Copy)]
struct Last {
    epoch: u64,
    topic_seq: u64,
    seq: u64,
}

impl Gaps {
    /// The messages missing before this one (0 if none), or `None` if it is late (an
    /// older message of its topic than one taken already: drop it). Call once per
    /// message after [`Dedup::first_time`].
    pub fn missing(&mut self, stamp: &Stamp, topic: &str) -> Option<u64> {
        if stamp.topic_seq == 0 {
            return Some(0);
        }
        let now = Last {
            epoch: stamp.epoch,
            topic_seq: stamp.topic_seq,
            seq: stamp.seq,
        };
        let known = self
            .last
            .get_mut(&stamp.line)
            .and_then(|t| t.get_mut(topic));
        if let Some(last) = known {
            if last.epoch == stamp.epoch {
                if stamp.topic_seq > last.topic_seq {
                    let missing = stamp.topic_seq - last.topic_seq - 1;
                    *last = now;
                    return Some(missing);
                }
                if stamp.seq < last.seq {
                    return None;
                }
            }
            // The origin restarted, or numbers the topic anew (a later message with a
            // lower number): the count starts again.
            *last = now;
            return Some(0);
        }
        if self.topics >= GAP_TOPICS {
            self.last.clear();
            self.topics = 0;
        }
        self.topics += 1;
        self.last
            .entry(stamp.line.clone())
            .or_default()
            .insert(topic.to_owned(), now);
        Some(0)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn stamp(line: &str, epoch: u64, seq: u64) -> Stamp {
        Stamp {
            line: line.into(),
            epoch,
            seq,
            topic_seq: seq,
            qos: 1,
            retain: true,
        }
    }

    #[test]
    fn stamps_round_trip() {
        let s = stamp("line-a", 17, 99);
        assert_eq!(Stamp::decode(&s.encode()), Some(s));
        assert_eq!(Stamp::decode(b"short"), None);
        // Version 1 (no topic_seq) is still read; a version 2 cut short is not.
        let mut v1 = vec![1, 0b101];
        v1.extend_from_slice(&17u64.to_be_bytes());
        v1.extend_from_slice(&99u64.to_be_bytes());
        v1.extend_from_slice("line-ä".as_bytes());
        let old = Stamp::decode(&v1).unwrap();
        assert_eq!(
            (old.seq, old.topic_seq, old.qos, old.retain),
            (99, 0, 1, true)
        );
        assert_eq!(old.line, "line-ä");
        assert_eq!(Stamp::decode(&stamp("a", 1, 1).encode()[..25]), None);
        assert_eq!(Stamp::decode(&[3; 40]), None);
        let mut qos3 = stamp("a", 1, 1).encode();
        qos3[1] |= 0b11;
        assert_eq!(Stamp::decode(&qos3), None, "QoS 3");
    }

    #[test]
    fn gaps_count_what_never_came_per_origin_and_topic() {
        let mut g = Gaps::default();
        // One topic per origin here, so seq = topic_seq, except where said.
        let at = |epoch, topic_seq| Stamp {
            topic_seq,
            ..stamp("a", epoch, topic_seq)
        };
        assert_eq!(
            g.missing(&at(1, 5), "t"),
            Some(0),
            "the first starts the count"
        );
        assert_eq!(g.missing(&at(1, 6), "t"), Some(0));
        assert_eq!(g.missing(&at(1, 9), "t"), Some(2), "7 and 8");
        assert_eq!(g.missing(&at(1, 1), "u"), Some(0), "another topic");
        assert_eq!(
            g.missing(&at(1, 8), "t"),
            None,
            "late: dropped, the gap stays"
        );
        assert_eq!(g.missing(&at(1, 10), "t"), Some(0));
        let renumbered = Stamp {
            seq: 11,
            ..at(1, 1)
        };
        assert_eq!(g.missing(&renumbered, "t"), Some(0), "numbered anew");
        assert_eq!(
            g.missing(
                &Stamp {
                    seq: 13,
                    ..at(1, 3)
                },
                "t"
            ),
            Some(1)
        );
        assert_eq!(g.missing(&at(2, 1), "t"), Some(0), "the origin restarted");
        assert_eq!(g.missing(&at(2, 3), "t"), Some(1));
        assert_eq!(g.missing(&at(2, 0), "t"), Some(0), "not numbered");
        // Numbers near the end of u64 (a hostile line's) do not overflow.
        assert_eq!(g.missing(&at(2, u64::MAX - 1), "t"), Some(u64::MAX - 5));
        assert_eq!(g.missing(&at(2, 3), "t"), None, "far behind: late");
        let mut d = Dedup::default();
        assert!(d.first_time(&stamp("a", 1, u64::MAX)));
        assert!(d.first_time(&stamp("a", 1, u64::MAX - 1)));
        for i in 0..GAP_TOPICS * 2 {
            g.missing(&at(2, 1), &format!("t{i}"));
            assert!(g.topics <= GAP_TOPICS);
            assert!(g.last.values().map(HashMap::len).sum::<usize>() <= GAP_TOPICS);
        }
    }

    #[test]
    fn dedup_drops_repeats_per_origin_and_resets_on_a_new_epoch() {
        let mut d = Dedup::default();
        assert!(d.first_time(&stamp("a", 1, 1)));
        assert!(d.first_time(&stamp("a", 1, 3)));
        assert!(d.first_time(&stamp("a", 1, 2)), "out of order but new");
        assert!(!d.first_time(&stamp("a", 1, 3)));
        assert!(d.first_time(&stamp("b", 1, 3)), "another origin");
        assert!(d.first_time(&stamp("a", 2, 1)), "the origin restarted");
        assert!(
            !d.first_time(&stamp("a", 1, 4)),
            "the old incarnation is gone"
        );
        for seq in 2..=DEDUP_WINDOW + 10 {
            assert!(d.first_time(&stamp("a", 2, seq)));
        }
        assert!(!d.first_time(&stamp("a", 2, 5)), "older than the window");
    }

    #[test]
    fn dedup_holds_a_bounded_number_of_origins() {
        let mut d = Dedup::default();
        for i in 0..DEDUP_ORIGINS * 3 {
            assert!(d.first_time(&stamp(&format!("line-{i}"), 1, 1)));
            assert!(d.origins.len() <= DEDUP_ORIGINS);
        }
        assert!(!d.first_time(&stamp(&format!("line-{}", DEDUP_ORIGINS * 3 - 1), 1, 1)));
    }
}

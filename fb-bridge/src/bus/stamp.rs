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
    pub qos: u8,
    pub retain: bool,
}

const STAMP_VERSION: u8 = 1;

impl Stamp {
    /// `[version, flags, epoch (8, BE), seq (8, BE), line (UTF-8)]`; flags: bits 0-1 QoS,
    /// bit 2 RETAIN.
    pub fn encode(&self) -> Vec<u8> {
        let mut out = Vec::with_capacity(18 + self.line.len());
        out.push(STAMP_VERSION);
        out.push(self.qos.min(2) | (self.retain as u8) << 2);
        out.extend_from_slice(&self.epoch.to_be_bytes());
        out.extend_from_slice(&self.seq.to_be_bytes());
        out.extend_from_slice(self.line.as_bytes());
        out
    }

    pub fn decode(bytes: &[u8]) -> Option<Stamp> {
        if bytes.len() < 18 || bytes[0] != STAMP_VERSION {
            return None;
        }
        let flags = bytes[1];
        Some(Stamp {
            qos: flags & 0b11,
            retain: flags & 0b100 != 0,
            epoch: u64::from_be_bytes(bytes[2..10].try_into().ok()?),
            seq: u64::from_be_bytes(bytes[10..18].try_into().ok()?),
            line: std::str::from_utf8(&bytes[18..]).ok()?.to_owned(),
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
        if stamp.seq + DEDUP_WINDOW <= w.highest || !w.seen.insert(stamp.seq) {
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

#[cfg(test)]
mod tests {
    use super::*;

    fn stamp(line: &str, epoch: u64, seq: u64) -> Stamp {
        Stamp {
            line: line.into(),
            epoch,
            seq,
            qos: 1,
            retain: true,
        }
    }

    #[test]
    fn stamps_round_trip() {
        let s = stamp("line-a", 17, 99);
        assert_eq!(Stamp::decode(&s.encode()), Some(s));
        assert_eq!(Stamp::decode(b"short"), None);
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

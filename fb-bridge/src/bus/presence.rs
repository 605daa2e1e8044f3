//! One line seen through several zenoh sessions ([`super::BusConfig::session_per_router`]):
//! what every session reports is merged into one view, so the broker sees each line come
//! and go once, and each device's record change once, in order.
//!
//! With one session per router, every token and record of another line arrives once per
//! router that reaches it, and each session loses what it knew when its router goes. A
//! line is there while any session sees it ([`Presence`]); a record is taken only if it
//! is newer than the last one taken of its device ([`RecordOrder`]), since the copies of
//! two changes can arrive through two routers in either order. With one session, zenoh
//! already delivers each once, in order: [`Presence`] then passes every change on, and
//! the link keeps no [`RecordOrder`].

use std::collections::hash_map::RandomState;
use std::collections::HashMap;
use std::hash::{BuildHasher, Hash};
use std::sync::{Mutex, PoisonError};

/// Which sessions see each key (a line's token, a line's interest in a filter).
///
/// Holds one entry per key that at least one session sees now, so its size is that of
/// the tokens zenoh itself holds; an entry goes when the last session loses it.
pub(crate) struct Presence<K> {
    seen_by: Mutex<HashMap<K, u8>>,
}

impl<K: Eq + Hash> Presence<K> {
    pub(crate) fn new() -> Self {
        Presence {
            seen_by: Mutex::new(HashMap::new()),
        }
    }

    /// Session `session` (below 8) saw `key` appear (`up`) or go. Returns `Some(true)`
    /// when the first session sees it, `Some(false)` when the last one lost it, `None`
    /// when nothing changed for the line as a whole.
    pub(crate) fn seen(&self, key: K, session: usize, up: bool) -> Option<bool> {
        let bit = 1u8 << (session % 8);
        let mut seen_by = self.seen_by.lock().unwrap_or_else(PoisonError::into_inner);
        if up {
            let sessions = seen_by.entry(key).or_insert(0);
            let first = *sessions == 0;
            *sessions |= bit;
            return first.then_some(true);
        }
        let sessions = seen_by.get_mut(&key)?;
        if *sessions & bit == 0 {
            return None;
        }
        *sessions &= !bit;
        if *sessions != 0 {
            return None;
        }
        seen_by.remove(&key);
        Some(false)
    }
}

/// Devices [`RecordOrder`] remembers; past this many it starts over (and may then take
/// one late copy of a record in flight at that moment). The registry refuses remote
/// devices beyond its own limit long before a plant reaches this.
pub(crate) const RECORD_ORDER_DEVICES: usize = 200_000;

/// The version of the last record taken per (line, device): the origin bridge's epoch
/// and its count of record changes, carried as the record's attachment
/// ([`encode_version`]).
///
/// Keyed by a keyed 64-bit hash of (line, device), not the names: an entry is about 40
/// bytes whatever names another line sends (10 MB at [`RECORD_ORDER_DEVICES`]), and
/// two devices sharing a hash by chance is a 1 in 2^64 event per pair.
pub(crate) struct RecordOrder {
    last: Mutex<HashMap<u64, (u64, u64)>>,
    hasher: RandomState,
}

impl RecordOrder {
    pub(crate) fn new() -> Self {
        RecordOrder {
            last: Mutex::new(HashMap::new()),
            hasher: RandomState::new(),
        }
    }

    /// Whether a record change (put or forget) of `device` of `line` at `version` is
    /// newer than every one taken before: the first copy of each change is, its later
    /// copies and any older change arriving late are not. A change without a version
    /// (a bridge before issue 32's second pass) is always taken.
    pub(crate) fn newer(&self, line: &str, device: &str, version: Option<(u64, u64)>) -> bool {
        let Some(version) = version else {
            return true;
        };
        let key = self.hasher.hash_one((line, device));
        let mut last = self.last.lock().unwrap_or_else(PoisonError::into_inner);
        match last.get_mut(&key) {
            Some(taken) if *taken >= version => false,
            Some(taken) => {
                *taken = version;
                true
            }
            None => {
                if last.len() >= RECORD_ORDER_DEVICES {
                    last.clear();
                }
                last.insert(key, version);
                true
            }
        }
    }
}

/// A record change's version as its attachment: epoch and count, 8 bytes each, big-endian.
pub(crate) fn encode_version(epoch: u64, count: u64) -> Vec<u8> {
    let mut out = Vec::with_capacity(16);
    out.extend_from_slice(&epoch.to_be_bytes());
    out.extend_from_slice(&count.to_be_bytes());
    out
}

/// [`encode_version`]'s inverse; `None` for anything else.
pub(crate) fn decode_version(bytes: &[u8]) -> Option<(u64, u64)> {
    let epoch = bytes.get(..8)?.try_into().ok()?;
    let count = bytes.get(8..16)?.try_into().ok()?;
    (bytes.len() == 16).then(|| (u64::from_be_bytes(epoch), u64::from_be_bytes(count)))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_line_is_there_while_any_session_sees_it() {
        let p = Presence::new();
        assert_eq!(p.seen("a", 0, true), Some(true));
        assert_eq!(p.seen("a", 1, true), None, "seen through a second router");
        assert_eq!(p.seen("a", 0, true), None, "a repeat");
        assert_eq!(
            p.seen("a", 0, false),
            None,
            "router 1 gone, router 2 still sees it"
        );
        assert_eq!(p.seen("a", 0, false), None, "a repeat");
        assert_eq!(p.seen("a", 1, false), Some(false), "gone from both");
        assert_eq!(p.seen("a", 1, false), None, "already gone");
        assert_eq!(p.seen("b", 1, false), None, "never seen");
        assert!(
            p.seen_by.lock().unwrap().is_empty(),
            "nothing kept of what is gone"
        );
        assert_eq!(p.seen("a", 1, true), Some(true), "back");
    }

    #[test]
    fn only_a_newer_record_change_is_taken() {
        let o = RecordOrder::new();
        assert!(o.newer("l", "d", Some((5, 1))));
        assert!(
            !o.newer("l", "d", Some((5, 1))),
            "the copy through the other router"
        );
        assert!(o.newer("l", "d", Some((5, 3))));
        assert!(
            !o.newer("l", "d", Some((5, 2))),
            "an older change arriving late"
        );
        assert!(o.newer("l", "e", Some((5, 2))), "per device");
        assert!(o.newer("m", "d", Some((1, 1))), "per line");
        assert!(o.newer("l", "d", Some((6, 1))), "the origin restarted");
        assert!(!o.newer("l", "d", Some((5, 9))), "its previous run");
        assert!(o.newer("l", "d", None), "no version: taken");
        for i in 0..RECORD_ORDER_DEVICES as u64 + 10 {
            o.newer("l", &i.to_string(), Some((1, 1)));
        }
        assert!(o.last.lock().unwrap().len() <= RECORD_ORDER_DEVICES);
    }

    #[test]
    fn versions_round_trip_and_nothing_else_reads_as_one() {
        assert_eq!(decode_version(&encode_version(7, 9)), Some((7, 9)));
        assert_eq!(decode_version(&[0; 15]), None);
        assert_eq!(decode_version(&[0; 17]), None);
        assert_eq!(decode_version(b""), None);
    }
}

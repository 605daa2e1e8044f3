//! fbbus: publishers held back while a reader of their filter would lose messages.
//!
//! rumqttd keeps each filter's messages in a commit log of `max_segment_count` segments.
//! When the log is full, the next append drops the oldest segment, and a reader still in
//! it skips what it had not read (`Skipped`). That is right for a reader that stopped, and
//! wrong for one that reads, only slower than a burst comes in: in `fbbus-bench`'s burst
//! of a million messages (now `fbbus-loadtest compare --scenarios msgmem`) the one
//! subscriber lost about 70% of them, where Mosquitto delivers them all (it buffers
//! without bound).
//!
//! So when a publish would make a log drop messages that a live reader has not read, the
//! router stops taking that publisher's packets. The publish and everything after it go
//! back into the connection's input buffer (`Incoming::put_back`); fbbus's connection loop
//! stops reading the socket once that buffer is full, and TCP slows the device down.
//! The router lets a filter's held publishers go, in the order they were held, as soon as
//! its readers have read past the boundary, and at the latest after `hold_limit`. A reader
//! still behind then is marked slow: it skips, as before, and holds nobody back again
//! until it has caught up. One stalled subscriber therefore delays the publishers of its
//! filter by at most `hold_limit` per episode; it never stops a line.
//!
//! Only live readers hold publishers: the subscriptions of connected clients, shared
//! groups at their group's cursor. An offline persistent session never does (it would stop
//! the line for as long as it is away), nor do the unacknowledged deliveries kept for a
//! resumed session.

use std::collections::HashMap;
use std::time::{Duration, Instant};

use crate::router::FilterIdx;
use crate::ConnectionId;

/// How often, at most, the router checks whether held publishers may go on: each check
/// looks at every reader of the held filters.
const CHECK_EVERY: Duration = Duration::from_micros(200);

/// One filter's publishers are held until its readers are past `boundary`.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(crate) struct FilterHold {
    /// Offsets below this are dropped by the filter's next append.
    pub boundary: u64,
    pub since: Instant,
}

#[derive(Debug)]
pub(crate) struct Holds {
    limit: Duration,
    /// Held connections, in the order they were held, with the filter each waits for.
    held: Vec<(ConnectionId, FilterIdx)>,
    filters: HashMap<FilterIdx, FilterHold>,
    last_check: Instant,
}

impl Holds {
    /// `limit` zero: nothing is ever held.
    pub fn new(limit: Duration) -> Holds {
        Holds {
            limit,
            held: Vec::new(),
            filters: HashMap::new(),
            last_check: Instant::now(),
        }
    }

    pub fn enabled(&self) -> bool {
        !self.limit.is_zero()
    }

    pub fn is_empty(&self) -> bool {
        self.held.is_empty()
    }

    pub fn is_held(&self, id: ConnectionId) -> bool {
        self.held.iter().any(|&(held, _)| held == id)
    }

    /// Publishers of `filter` are already held for this boundary.
    pub fn holds(&self, filter: FilterIdx, boundary: u64) -> bool {
        self.filters
            .get(&filter)
            .is_some_and(|hold| hold.boundary == boundary)
    }

    pub fn hold(&mut self, id: ConnectionId, filter: FilterIdx, boundary: u64) {
        let hold = FilterHold {
            boundary,
            since: Instant::now(),
        };
        let entry = self.filters.entry(filter).or_insert(hold);
        if entry.boundary != boundary {
            *entry = hold;
        }
        self.held.push((id, filter));
    }

    /// A held connection ended: its packets are gone with it. fbbus: so is the hold of a
    /// filter none of whose publishers is held any more. Left in place, it outlived its
    /// publishers, and the next publisher held for that boundary found it already expired:
    /// held for no time, and the filter's readers marked slow at once.
    pub fn forget(&mut self, id: ConnectionId) {
        self.held.retain(|&(held, _)| held != id);
        let held = &self.held;
        self.filters
            .retain(|filter, _| held.iter().any(|&(_, held_on)| held_on == *filter));
    }

    /// fbbus: the filters of the holds (`DataLog::remove_unused` keeps their logs).
    pub fn filters(&self) -> impl Iterator<Item = FilterIdx> + '_ {
        self.filters
            .keys()
            .copied()
            .chain(self.held.iter().map(|&(_, filter)| filter))
    }

    /// Whether the router should check the held filters now (at most every
    /// [`CHECK_EVERY`]); the filters to check.
    pub fn due(&mut self) -> Option<Vec<(FilterIdx, FilterHold)>> {
        if self.held.is_empty() || self.last_check.elapsed() < CHECK_EVERY {
            return None;
        }
        self.last_check = Instant::now();
        Some(self.filters.iter().map(|(&f, &h)| (f, h)).collect())
    }

    /// The hold has lasted `hold_limit`.
    pub fn expired(&self, hold: &FilterHold) -> bool {
        hold.since.elapsed() >= self.limit
    }

    /// Lets the publishers held on `filter` go: their connections, in the order they were
    /// held.
    pub fn release(&mut self, filter: FilterIdx) -> Vec<ConnectionId> {
        self.filters.remove(&filter);
        let mut released = Vec::new();
        self.held.retain(|&(id, held_on)| {
            let go = held_on == filter;
            if go {
                released.push(id);
            }
            !go
        });
        released
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn publishers_go_in_the_order_they_were_held_per_filter() {
        let mut holds = Holds::new(Duration::from_secs(1));
        assert!(holds.enabled() && holds.is_empty());
        holds.hold(7, 1, 100);
        holds.hold(3, 2, 50);
        holds.hold(5, 1, 100);
        assert!(holds.holds(1, 100) && !holds.holds(1, 101) && holds.is_held(5));
        assert_eq!(holds.release(1), vec![7, 5]);
        assert!(!holds.is_held(7) && holds.is_held(3));
        holds.forget(3);
        assert!(holds.is_empty());
    }

    #[test]
    fn a_new_boundary_restarts_the_filters_hold() {
        let mut holds = Holds::new(Duration::from_secs(1));
        holds.hold(1, 4, 10);
        let first = holds.filters[&4];
        std::thread::sleep(Duration::from_millis(2));
        holds.hold(2, 4, 10);
        assert_eq!(holds.filters[&4], first);
        holds.hold(3, 4, 20);
        assert_eq!(holds.filters[&4].boundary, 20);
        assert!(holds.filters[&4].since > first.since);
    }

    /// fbbus: a filter's hold ends with the last of its held publishers, however they went.
    #[test]
    fn a_hold_whose_publishers_all_ended_is_gone() {
        let mut holds = Holds::new(Duration::from_secs(1));
        holds.hold(1, 4, 10);
        holds.hold(2, 4, 10);
        holds.hold(3, 5, 7);
        holds.forget(1);
        assert!(holds.holds(4, 10));
        holds.forget(2);
        assert!(!holds.holds(4, 10) && holds.holds(5, 7));
        assert_eq!(holds.filters().collect::<Vec<_>>(), vec![5, 5]);
        holds.forget(3);
        assert!(holds.filters.is_empty() && holds.is_empty());
    }

    #[test]
    fn no_limit_holds_nothing() {
        assert!(!Holds::new(Duration::ZERO).enabled());
    }
}

//! Each identity's share of the retained messages (issue 33, 4: one client retained 101,000
//! messages in 3 s and every other client's new retained topic, a new device's `fb/` last
//! values included, was refused).
//!
//! The router bounds retained messages in all (`[broker] max_retained_messages`,
//! `max_retained_bytes`); this table bounds what one identity holds of them
//! (`max_retained_messages_per_identity`, `max_retained_bytes_per_identity`). A session
//! asks it before routing a retained publication: within the publisher's share (or a
//! replacement no larger than what it replaces), the topic is charged to the publisher and
//! the publication routed as always; beyond, the publication is still delivered to the
//! subscribers of the moment but not retained, and an MQTT 5 publisher hears 0x97 Quota
//! exceeded, as for the router's own bounds. Clearing (an empty payload) always works and
//! gives the share back; a topic retained by another identity moves to the new publisher.
//!
//! Only retained publications come here (a lock per retained publication, none for the
//! rest). The broker's own topics are not charged (`router::RETAINED_UNCOUNTED`). The
//! table holds at most the router's `max_retained_messages` topics: a new topic beyond is
//! left to the router, which refuses it. At start the store's retained messages are
//! charged back to the identities that published them ([`RetainedShares::restore`]).

use std::collections::{BTreeMap, HashMap};
use std::sync::{Arc, Mutex, PoisonError};
use std::time::SystemTime;

use serde::Serialize;

/// What one identity holds.
#[derive(Debug, Default, Clone, Copy, PartialEq, Eq)]
struct Usage {
    messages: usize,
    bytes: usize,
}

#[derive(Default)]
struct Table {
    /// Topic -> the identity it is charged to, its size (topic and payload bytes) and
    /// when it was retained; in topic order, for the admin plane's listing ([`list`]).
    ///
    /// [`list`]: RetainedShares::list
    topics: BTreeMap<Box<str>, Charged>,
    usage: HashMap<Arc<str>, Usage>,
}

/// One retained topic's charge.
#[derive(Debug, Clone)]
struct Charged {
    owner: Arc<str>,
    size: usize,
    at: SystemTime,
}

/// Topics [`RetainedShares::list`] looks at per request at most: the table's lock is
/// what retained publications take, so a listing holds it for a bounded time.
pub const LIST_SCAN: usize = 10_000;

/// One retained topic as the admin plane lists it.
#[derive(Debug, Clone, Serialize)]
pub struct Listed {
    pub topic: String,
    /// Topic and payload bytes.
    pub bytes: usize,
    /// The identity it is charged to (a username, or an anonymous client's address).
    pub owner: String,
    /// RFC 3339, UTC.
    pub retained_at: String,
    pub age_s: u64,
}

/// The retained shares of the line's identities.
pub struct RetainedShares {
    max_messages: usize,
    max_bytes: usize,
    /// The router's bound on retained topics: the table never holds more.
    max_topics: usize,
    table: Mutex<Table>,
}

impl RetainedShares {
    pub fn new(max_messages: usize, max_bytes: usize, max_topics: usize) -> RetainedShares {
        RetainedShares {
            max_messages,
            max_bytes,
            max_topics,
            table: Mutex::default(),
        }
    }

    /// Whether `share`'s retained publication on `topic` of `size` bytes (topic and
    /// payload; an empty payload clears) may be retained. If so, the topic is charged to
    /// `share` now.
    pub fn admit(&self, share: &Arc<str>, topic: &str, size: usize, clear: bool) -> bool {
        if crate::router::RETAINED_UNCOUNTED
            .iter()
            .any(|prefix| topic.starts_with(prefix))
        {
            return true;
        }
        let mut table = self.table.lock().unwrap_or_else(PoisonError::into_inner);
        let old = table
            .topics
            .get(topic)
            .map(|c| (Arc::clone(&c.owner), c.size));
        if clear {
            if let Some((owner, old_size)) = old {
                table.topics.remove(topic);
                table.release(&owner, old_size);
            }
            return true;
        }
        let spent = table.usage.get(share).copied().unwrap_or_default();
        let fits = match &old {
            Some((owner, old_size)) if owner == share => {
                size <= *old_size || spent.bytes - old_size + size <= self.max_bytes
            }
            _ => spent.messages < self.max_messages && spent.bytes + size <= self.max_bytes,
        };
        if !fits {
            return false;
        }
        if old.is_none() && table.topics.len() >= self.max_topics {
            // The router refuses it by its own bound, and answers for it.
            return true;
        }
        if let Some((owner, old_size)) = old {
            table.release(&owner, old_size);
        }
        let share = table.key(share);
        let u = table.usage.entry(Arc::clone(&share)).or_default();
        u.messages += 1;
        u.bytes += size;
        table.topics.insert(
            topic.into(),
            Charged {
                owner: share,
                size,
                at: SystemTime::now(),
            },
        );
        true
    }

    /// The retained topics matching `filter` that sort after `after`, at most `limit`, in
    /// topic order; and the topic to continue after, when the page is full or the scan
    /// stopped at [`LIST_SCAN`] topics. Only the topics of the literal prefix of `filter`
    /// (before its first wildcard) are scanned. The broker's own retained topics
    /// (`fbbus/...`) are not charged, so not listed.
    pub fn list(&self, filter: &str, after: &str, limit: usize) -> (Vec<Listed>, Option<String>) {
        let prefix = filter
            .find(['+', '#'])
            .map_or(filter, |at| filter.get(..at).unwrap_or(""));
        let start = if after >= prefix { after } else { prefix };
        let now = SystemTime::now();
        let table = self.table.lock().unwrap_or_else(PoisonError::into_inner);
        let mut page = Vec::new();
        let mut last = None;
        let range = table.topics.range::<str, _>((
            if start == after && !after.is_empty() {
                std::ops::Bound::Excluded(start)
            } else {
                std::ops::Bound::Included(start)
            },
            std::ops::Bound::Unbounded,
        ));
        for (scanned, (topic, charged)) in range.enumerate() {
            if !topic.starts_with(prefix) {
                return (page, None);
            }
            if scanned == LIST_SCAN || page.len() == limit {
                return (page, last);
            }
            last = Some(topic.to_string());
            if fb_bridge::topic::filter::matches(filter, topic) {
                page.push(Listed {
                    topic: topic.to_string(),
                    bytes: charged.size,
                    owner: charged.owner.to_string(),
                    retained_at: humantime::format_rfc3339_millis(charged.at).to_string(),
                    age_s: now.duration_since(charged.at).map_or(0, |d| d.as_secs()),
                });
            }
        }
        (page, None)
    }

    /// Retained topics charged, in all.
    pub fn len(&self) -> usize {
        self.table
            .lock()
            .unwrap_or_else(PoisonError::into_inner)
            .topics
            .len()
    }

    /// Charges the retained messages the store brought back to their identities, as they
    /// were charged when the broker stopped (`store::Restore`), within the same bounds.
    pub fn restore<'a>(&self, retained: impl Iterator<Item = (&'a str, &'a str, usize)>) {
        for (share, topic, size) in retained {
            self.admit(&share.into(), topic, size, false);
        }
    }

    /// Topics charged to `share` and their bytes.
    #[cfg(test)]
    pub fn usage(&self, share: &str) -> (usize, usize) {
        let table = self.table.lock().unwrap_or_else(PoisonError::into_inner);
        let u = table.usage.get(share).copied().unwrap_or_default();
        (u.messages, u.bytes)
    }
}

impl Table {
    /// The table's own copy of a share's name, shared by its topics.
    fn key(&self, share: &Arc<str>) -> Arc<str> {
        match self.usage.get_key_value(share) {
            Some((k, _)) => Arc::clone(k),
            None => Arc::clone(share),
        }
    }

    fn release(&mut self, owner: &Arc<str>, size: usize) {
        if let Some(u) = self.usage.get_mut(owner) {
            u.messages = u.messages.saturating_sub(1);
            u.bytes = u.bytes.saturating_sub(size);
            if u.messages == 0 {
                self.usage.remove(owner);
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn one_identity_cannot_take_the_retained_messages_others_need() {
        let shares = RetainedShares::new(3, 100, 1000);
        let flood: Arc<str> = "address:127.0.0.9".into();
        let device: Arc<str> = "user:plc-2".into();
        for i in 0..3 {
            assert!(shares.admit(&flood, &format!("f/{i}"), 10, false));
        }
        assert!(!shares.admit(&flood, "f/3", 10, false), "beyond its share");
        assert!(
            shares.admit(&device, "fb/plc-2/CONV/SPEED", 10, false),
            "another identity keeps its share"
        );
        // A replacement no larger always; a larger one within the bytes.
        assert!(shares.admit(&flood, "f/0", 5, false));
        assert!(shares.admit(&flood, "f/0", 70, false));
        assert!(!shares.admit(&flood, "f/1", 80, false), "over its bytes");
        assert_eq!(shares.usage("address:127.0.0.9"), (3, 90));
        // Clearing gives the share back.
        assert!(shares.admit(&flood, "f/0", 0, true));
        assert_eq!(shares.usage("address:127.0.0.9"), (2, 20));
        assert!(shares.admit(&flood, "f/4", 10, false));
        // Another identity's topic moves to its new publisher.
        assert!(shares.admit(&device, "f/4", 10, false));
        assert_eq!(shares.usage("address:127.0.0.9"), (2, 20));
        assert_eq!(shares.usage("user:plc-2"), (2, 20));
        // The broker's own topics are not charged.
        for i in 0..10 {
            assert!(shares.admit(&flood, &format!("fbbus/devices/{i}"), 10, false));
        }
        assert_eq!(shares.usage("address:127.0.0.9"), (2, 20));
    }

    #[test]
    fn the_table_holds_no_more_topics_than_the_router() {
        let shares = RetainedShares::new(100, 10_000, 4);
        let a: Arc<str> = "user:a".into();
        for i in 0..10 {
            // Beyond the router's bound: left to the router (which refuses it).
            assert!(shares.admit(&a, &format!("t/{i}"), 1, false));
        }
        assert_eq!(shares.usage("user:a"), (4, 4));
        shares.restore([("user:b", "t/0", 1), ("user:b", "u/0", 1)].into_iter());
        assert_eq!(
            shares.usage("user:b"),
            (1, 1),
            "t/0 moved; u/0 is over the bound"
        );
    }
}

//! fbbus: connection ids, handed out by the link and kept by the router.
//!
//! Upstream's router chose a connection's id when it registered the connection (the next
//! free key of its slabs) and told the link in the ConnAck, so every link waited a round
//! trip through the router thread before its connection could say or hear anything. The
//! id now comes from [`ConnectionIds`], shared by the router and its links: a link takes
//! one, sends its Connect under it and can go on at once (`LinkBuilder::build_linked`);
//! the router gives it back when the connection is gone. The router's per-connection
//! tables are [`IdTable`]s, filled at the id the link chose.
//!
//! Ids are reused last-freed first, as the slabs did, so the tables stay as dense as the
//! number of connections at once.

use std::sync::Arc;

use parking_lot::Mutex;

use crate::ConnectionId;

/// The pool of connection ids: at most `max` in use at once.
#[derive(Clone)]
pub struct ConnectionIds {
    inner: Arc<Mutex<Pool>>,
}

struct Pool {
    /// Ids given back, the last one first out.
    free: Vec<ConnectionId>,
    /// Ids below this were handed out at least once.
    next: ConnectionId,
    in_use: usize,
    max: usize,
}

impl ConnectionIds {
    pub fn new(max: usize) -> ConnectionIds {
        ConnectionIds {
            inner: Arc::new(Mutex::new(Pool {
                free: Vec::new(),
                next: 0,
                in_use: 0,
                max,
            })),
        }
    }

    /// An id for a new connection; None when `max` connections hold one.
    pub fn take(&self) -> Option<ConnectionId> {
        let mut pool = self.inner.lock();
        if pool.in_use >= pool.max {
            return None;
        }
        pool.in_use += 1;
        Some(match pool.free.pop() {
            Some(id) => id,
            None => {
                pool.next += 1;
                pool.next - 1
            }
        })
    }

    /// A connection's id is free again: the router removed the connection from every
    /// table, or never registered it.
    pub fn give_back(&self, id: ConnectionId) {
        let mut pool = self.inner.lock();
        debug_assert!(
            id < pool.next && !pool.free.contains(&id),
            "id {id} given back twice"
        );
        pool.in_use = pool.in_use.saturating_sub(1);
        pool.free.push(id);
    }
}

/// A router table with one entry per connection, at the connection's id.
pub(crate) struct IdTable<T> {
    entries: Vec<Option<T>>,
    len: usize,
}

impl<T> IdTable<T> {
    pub fn with_capacity(capacity: usize) -> IdTable<T> {
        IdTable {
            entries: Vec::with_capacity(capacity),
            len: 0,
        }
    }

    /// Puts `value` at `id`; the entry there before, if any (none while ids are taken
    /// from one [`ConnectionIds`]).
    pub fn insert_at(&mut self, id: ConnectionId, value: T) -> Option<T> {
        if id >= self.entries.len() {
            self.entries.resize_with(id + 1, || None);
        }
        let previous = self.entries[id].replace(value);
        if previous.is_none() {
            self.len += 1;
        }
        previous
    }

    pub fn remove(&mut self, id: ConnectionId) -> Option<T> {
        let removed = self.entries.get_mut(id)?.take();
        if removed.is_some() {
            self.len -= 1;
        }
        removed
    }

    pub fn get(&self, id: ConnectionId) -> Option<&T> {
        self.entries.get(id)?.as_ref()
    }

    pub fn get_mut(&mut self, id: ConnectionId) -> Option<&mut T> {
        self.entries.get_mut(id)?.as_mut()
    }

    pub fn contains(&self, id: ConnectionId) -> bool {
        self.get(id).is_some()
    }

    /// Connections in the table.
    pub fn len(&self) -> usize {
        self.len
    }

    pub fn iter(&self) -> impl Iterator<Item = (ConnectionId, &T)> {
        self.entries
            .iter()
            .enumerate()
            .filter_map(|(id, entry)| Some((id, entry.as_ref()?)))
    }

    pub fn iter_mut(&mut self) -> impl Iterator<Item = (ConnectionId, &mut T)> {
        self.entries
            .iter_mut()
            .enumerate()
            .filter_map(|(id, entry)| Some((id, entry.as_mut()?)))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn ids_are_bounded_and_reused_last_freed_first() {
        let ids = ConnectionIds::new(3);
        assert_eq!(
            (ids.take(), ids.take(), ids.take()),
            (Some(0), Some(1), Some(2))
        );
        assert_eq!(ids.take(), None, "three in use of three");
        ids.give_back(0);
        ids.give_back(2);
        assert_eq!((ids.take(), ids.take()), (Some(2), Some(0)));
        assert_eq!(ids.take(), None);
    }

    #[test]
    fn a_table_holds_entries_at_their_ids() {
        let mut table = IdTable::with_capacity(0);
        assert_eq!(table.insert_at(5, "five"), None);
        assert_eq!(table.insert_at(1, "one"), None);
        assert_eq!(table.len(), 2);
        assert_eq!(table.get(5), Some(&"five"));
        assert_eq!(table.get(4), None);
        assert_eq!(table.get(100), None);
        assert_eq!(table.remove(5), Some("five"));
        assert_eq!(table.remove(5), None);
        assert_eq!(table.len(), 1);
        let ids: Vec<_> = table.iter_mut().map(|(id, _)| id).collect();
        assert_eq!(ids, vec![1]);
    }
}

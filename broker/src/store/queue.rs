//! The messages queued for one persistent session, in message-number order.
//!
//! Numbers arrive almost in order (sessions number their publications as they read them,
//! and their batches reach the writer nearly in that order) and leave almost in order
//! (deliveries are acknowledged as they were sent). So the queue is a deque of slots in
//! number order: a message joins at the back (a binary search and a short shift for the
//! rare late one), leaves by becoming an empty slot, and the empty slots at the front go
//! at once. A `BTreeMap` did the same at several times the cost; inserting and removing
//! were an eighth of the writer thread's time in the QoS 1 burst (`docs/performance.md`).
//!
//! Bounded: empty slots behind a message that stays (a QoS 2 exchange its client never
//! completes) are swept out once they outnumber the messages, so the slots are at most
//! about twice the messages, and the messages at most `max_queued_messages`.

use std::collections::VecDeque;
use std::sync::Arc;

use super::record::{Message, Qos2};

/// A message waiting in a session's queue, and how it is delivered.
#[derive(Debug, Clone)]
pub struct Queued {
    pub message: Arc<Message>,
    /// The QoS it is delivered at.
    pub qos: u8,
    pub qos2: Option<Qos2>,
}

#[derive(Debug, Clone, Default)]
pub struct Queue {
    /// In increasing number order; `None`: the message left.
    slots: VecDeque<(u64, Option<Queued>)>,
    len: usize,
}

impl Queue {
    /// Messages queued.
    pub fn len(&self) -> usize {
        self.len
    }

    #[cfg(test)]
    pub fn is_empty(&self) -> bool {
        self.len == 0
    }

    /// Queues `q` as message `seq`; false (and nothing changes) if it is queued already.
    pub fn insert(&mut self, seq: u64, q: Queued) -> bool {
        match self.slots.back() {
            Some((last, _)) if *last >= seq => {}
            _ => {
                self.slots.push_back((seq, Some(q)));
                self.len += 1;
                return true;
            }
        }
        match self.slots.binary_search_by_key(&seq, |(s, _)| *s) {
            Ok(i) => match &mut self.slots[i].1 {
                Some(_) => false,
                empty => {
                    *empty = Some(q);
                    self.len += 1;
                    true
                }
            },
            Err(i) => {
                self.slots.insert(i, (seq, Some(q)));
                self.len += 1;
                true
            }
        }
    }

    /// Takes message `seq` off the queue.
    pub fn remove(&mut self, seq: u64) -> Option<Queued> {
        let i = self.slots.binary_search_by_key(&seq, |(s, _)| *s).ok()?;
        let q = self.slots[i].1.take()?;
        self.len -= 1;
        while matches!(self.slots.front(), Some((_, None))) {
            self.slots.pop_front();
        }
        if self.slots.len() > 2 * self.len + 64 {
            self.slots.retain(|(_, q)| q.is_some());
        }
        Some(q)
    }

    pub fn get_mut(&mut self, seq: u64) -> Option<&mut Queued> {
        let i = self.slots.binary_search_by_key(&seq, |(s, _)| *s).ok()?;
        self.slots[i].1.as_mut()
    }

    /// The queued messages in number order.
    pub fn iter(&self) -> impl Iterator<Item = (u64, &Queued)> {
        self.slots
            .iter()
            .filter_map(|(seq, q)| q.as_ref().map(|q| (*seq, q)))
    }
}

#[cfg(test)]
mod tests {
    use std::collections::BTreeMap;
    use std::sync::Arc;

    use super::*;
    use crate::store::record::Message;

    fn queued(qos: u8) -> Queued {
        Queued {
            message: Arc::new(Message {
                topic: bytes::Bytes::from_static(b"t"),
                payload: bytes::Bytes::new(),
                qos,
                retain: false,
                properties: None,
                publisher: "p".into(),
            }),
            qos,
            qos2: None,
        }
    }

    /// The queue against a `BTreeMap` under a random mix of in-order, late and repeated
    /// inserts and removals: the same messages, in the same order, and the slots bounded.
    #[test]
    fn behaves_as_an_ordered_map() {
        let mut rng = 0x9e37_79b9_7f4a_7c15u64;
        let mut next = || {
            rng ^= rng << 13;
            rng ^= rng >> 7;
            rng ^= rng << 17;
            rng
        };
        let mut queue = Queue::default();
        let mut model: BTreeMap<u64, u8> = BTreeMap::new();
        let mut seq = 0u64;
        // One message that never leaves, as a QoS 2 exchange a client never completes.
        assert!(queue.insert(0, queued(2)));
        model.insert(0, 2);
        for _ in 0..20_000 {
            match next() % 8 {
                0..=3 => {
                    seq += 1 + next() % 3;
                    // Now and then a little late: a number below the last.
                    let s = if next() % 5 == 0 {
                        seq.saturating_sub(next() % 4)
                    } else {
                        seq
                    };
                    let qos = (next() % 3) as u8;
                    let fresh = !model.contains_key(&s);
                    assert_eq!(queue.insert(s, queued(qos)), fresh);
                    model.entry(s).or_insert(qos);
                }
                4..=6 => {
                    let Some(&s) = model.keys().nth((next() % 8) as usize) else {
                        continue;
                    };
                    if s == 0 {
                        continue;
                    }
                    assert_eq!(queue.remove(s).map(|q| q.qos), model.remove(&s));
                    assert!(queue.remove(s).is_none(), "removed twice");
                }
                _ => {
                    let s = seq.saturating_sub(next() % 16);
                    if let Some(q) = queue.get_mut(s) {
                        q.qos2 = Some(crate::store::record::Qos2::Received(1));
                    }
                    assert_eq!(queue.get_mut(s).is_some(), model.contains_key(&s));
                }
            }
            assert_eq!(queue.len(), model.len());
            assert!(queue.slots.len() <= 2 * queue.len() + 65);
        }
        let got: Vec<(u64, u8)> = queue.iter().map(|(s, q)| (s, q.qos)).collect();
        let want: Vec<(u64, u8)> = model.into_iter().collect();
        assert_eq!(got, want);
        assert!(!queue.is_empty());
    }
}

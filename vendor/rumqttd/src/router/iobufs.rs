use std::{
    collections::{HashMap, VecDeque},
    sync::Arc,
};

use parking_lot::Mutex;
use tracing::{error, warn};

use crate::{protocol::Packet, router::FilterIdx, Cursor, Notification};

use super::wakeup::{wakeup, WakeRx, WakeTx};
use super::Forward;

/// QoS 1/2 deliveries to one connection unacknowledged at once, unless its link says
/// otherwise (fbbus: `LinkBuilder::max_inflight`; upstream's fixed window).
pub const DEFAULT_MAX_INFLIGHT: u16 = 100;

#[derive(Debug)]
pub struct Incoming {
    /// Identifier associated with connected client
    pub(crate) client_id: String,
    /// Recv buffer
    pub(crate) buffer: Arc<Mutex<VecDeque<Packet>>>,
    // fbbus: no `IncomingMeter` (112 bytes per connection, a String per subscription):
    // nothing read it once the per-topic publish meter was gone (see routing.rs).
}

impl Incoming {
    #[inline]
    pub(crate) fn new(client_id: String) -> Self {
        Self {
            // fbbus: allocated on first use; most devices are idle most of the time.
            buffer: Arc::new(Mutex::new(VecDeque::new())),
            client_id,
        }
    }

    #[inline]
    pub(crate) fn buffer(&self) -> Arc<Mutex<VecDeque<Packet>>> {
        self.buffer.clone()
    }

    /// Takes what the connection sent. fbbus: the connection is left with an unallocated
    /// buffer (upstream swapped in the router's cache, so every connection that ever sent a
    /// batch kept a batch-sized buffer while idle).
    #[inline]
    pub(crate) fn take(&mut self) -> VecDeque<Packet> {
        std::mem::take(&mut *self.buffer.lock())
    }

    /// fbbus: gives back packets taken but not handled (a held publisher's, see
    /// `router::holds`), in front of what the connection sent since.
    pub(crate) fn put_back(&self, mut taken: VecDeque<Packet>) {
        let mut buffer = self.buffer.lock();
        taken.append(&mut buffer);
        *buffer = taken;
    }
}

#[derive(Debug)]
pub struct Outgoing {
    /// Identifier associated with connected client
    pub(crate) client_id: String,
    /// Send buffer
    pub(crate) data_buffer: Arc<Mutex<VecDeque<Notification>>>,
    /// Handle which is given to router to allow router to communicate with this connection
    /// (fbbus: a flag and a waiter, not a channel of tokens: `wakeup`)
    pub(crate) handle: WakeTx,
    /// The buffer to keep track of inflight packets.
    inflight_buffer: VecDeque<(u16, FilterIdx, Option<Cursor>)>,
    /// PubRels waiting for PubComp
    pub(crate) unacked_pubrels: VecDeque<u16>,
    /// Last packet id
    last_pkid: u16,
    /// fbbus: deliveries in flight at most, and the highest packet id (ids wrap after it).
    max_inflight: u16,
}

impl Outgoing {
    #[inline]
    pub(crate) fn new(client_id: String, max_inflight: u16) -> (Self, WakeRx) {
        let (handle, rx) = wakeup();
        // fbbus: no buffer is preallocated (upstream reserved 200 notifications and 2 x 100
        // inflight entries per connection, ~40 KB for an idle device); they grow on use and
        // `compact` gives the memory back once they are empty again.
        let data_buffer = VecDeque::new();
        let inflight_buffer = VecDeque::new();
        let unacked_pubrels = VecDeque::new();

        let outgoing = Self {
            client_id,
            data_buffer: Arc::new(Mutex::new(data_buffer)),
            inflight_buffer,
            unacked_pubrels,
            handle,
            last_pkid: 0,
            max_inflight: max_inflight.max(1),
        };

        (outgoing, rx)
    }

    #[inline]
    pub(crate) fn buffer(&self) -> Arc<Mutex<VecDeque<Notification>>> {
        self.data_buffer.clone()
    }

    /// fbbus: releases the memory of empty buffers (called when the router is idle).
    pub(crate) fn compact(&mut self) {
        shrink_if_empty(&mut self.inflight_buffer);
        shrink_if_empty(&mut self.unacked_pubrels);
        shrink_if_empty(&mut self.data_buffer.lock());
    }

    pub fn free_slots(&self) -> usize {
        // fbbus: saturating. `forward_device_data` never reads more QoS 1/2 messages than
        // there are free slots, so this cannot underflow; upstream's `push_forwards` warns
        // when it would have, and a warning must not turn into a panic here.
        usize::from(self.max_inflight).saturating_sub(self.inflight_buffer.len())
    }

    pub fn push_notification(&mut self, notification: Notification) -> usize {
        let mut buffer = self.data_buffer.lock();
        buffer.push_back(notification);
        buffer.len()
    }

    /// Push packets to the outgoing buffer.
    ///
    /// fbbus: into `buffer`, the connection's buffer, which the router holds locked for
    /// a whole scheduling round (`Router::consume`). Returns the number of notifications
    /// in the buffer and the number in flight.
    pub fn push_forwards(
        &mut self,
        publishes: impl Iterator<Item = Forward>,
        qos: u8,
        filter_idx: usize,
        buffer: &mut VecDeque<Notification>,
    ) -> (usize, usize) {
        if qos == 0 {
            for p in publishes {
                buffer.push_back(Notification::Forward(p));
            }

            let buffer_count = buffer.len();
            let inflight_count = self.inflight_buffer.len();
            return (buffer_count, inflight_count);
        }

        for mut p in publishes {
            // Index and pkid of current outgoing packet
            self.last_pkid += 1;
            p.publish.pkid = self.last_pkid;

            self.inflight_buffer
                .push_back((self.last_pkid, filter_idx, p.cursor));

            // Place max pkid packet at index 0
            if self.last_pkid == self.max_inflight {
                self.last_pkid = 0;
            }

            buffer.push_back(Notification::Forward(p));
        }

        let buffer_count = buffer.len();
        let inflight_count = self.inflight_buffer.len();

        if inflight_count > usize::from(self.max_inflight) {
            warn!(
                "More inflight publishes than max allowed, inflight count = {}, max allowed = {}",
                inflight_count, self.max_inflight
            );
        }

        (buffer_count, inflight_count)
    }

    // Returns (unsolicited, outoforder) flags
    // Return: Out of order or unsolicited acks
    pub fn register_ack(&mut self, pkid: u16) -> Option<()> {
        let (head, _filter_idx, _cursor) = self.inflight_buffer.pop_front()?;

        // We don't support out of order acks
        if pkid != head {
            error!(pkid, head, "out of order ack.");
            return None;
        }

        Some(())
    }

    pub fn register_pubrec(&mut self, pkid: u16) {
        // NOTE: we can return true of false
        // to indicate whether this is duplicate or not
        self.unacked_pubrels.push_back(pkid);
    }

    // OASIS standards don't specify anything about ordering of PubComp
    // https://docs.oasis-open.org/mqtt/mqtt/v5.0/os/mqtt-v5.0-os.html#_Toc3901240
    // But we don't support out of order / unsolicited pubcomps
    // to be consistent with the behaviour with other acks
    pub fn register_pubcomp(&mut self, pkid: u16) -> Option<()> {
        let id = self.unacked_pubrels.pop_front()?;

        // out of order acks
        if pkid != id {
            error!(pkid, id, "out of order ack.");
            return None;
        }

        Some(())
    }

    // Here we are assuming that the first unique filter_idx we find while iterating will have the
    // least corresponding cursor because of the way we insert into the inflight_buffer
    pub fn retransmission_map(&self) -> HashMap<FilterIdx, Cursor> {
        let mut o = HashMap::new();
        for (_, filter_idx, cursor) in self.inflight_buffer.iter() {
            // if cursor in None, it means it was a retained publish
            if let (false, Some(cursor)) = (o.contains_key(filter_idx), cursor) {
                o.insert(*filter_idx, *cursor);
            }
        }

        o
    }
}

/// fbbus: frees the allocation of an empty queue.
pub(crate) fn shrink_if_empty<T>(queue: &mut VecDeque<T>) {
    if queue.is_empty() && queue.capacity() > 0 {
        *queue = VecDeque::new();
    }
}

#[cfg(test)]
mod test {
    use super::*;

    #[test]
    fn retransmission_map_is_calculated_accurately() {
        let (mut outgoing, _) =
            Outgoing::new("retransmission-test".to_string(), DEFAULT_MAX_INFLIGHT);
        let mut result = HashMap::new();

        result.insert(0, (0, 8));
        result.insert(1, (0, 1));
        result.insert(2, (1, 1));
        result.insert(3, (1, 0));

        let buf = vec![
            (1, 0, Some((0, 8))),
            (1, 0, Some((0, 10))),
            (1, 1, Some((0, 1))),
            (3, 1, Some((0, 4))),
            (2, 2, Some((1, 1))),
            (1, 2, Some((2, 6))),
            (1, 2, Some((2, 1))),
            (1, 3, Some((1, 0))),
            (1, 3, Some((1, 1))),
            (1, 3, Some((1, 3))),
            (1, 3, Some((1, 3))),
        ];

        outgoing.inflight_buffer.extend(buf);
        assert_eq!(outgoing.retransmission_map(), result);
    }

    // use super::{Outgoing, MAX_INFLIGHT};
    // use crate::protocol::{Publish, QoS};
    // use crate::router::Forward;
    // use crate::Notification;
    //
    // fn publishes(count: usize) -> impl Iterator<Item = Forward> {
    //     (1..=count).map(|v| {
    //         let publish = Publish {
    //             dup: false,
    //             retain: false,
    //             pkid: 0,
    //             qos: QoS::AtLeastOnce,
    //             topic: "hello/world".into(),
    //             payload: vec![1, 2, 3].into(),
    //         };
    //
    //         Forward {
    //             cursor: (0, v as u64),
    //             publish,
    //             size: 0,
    //         }
    //     })
    // }
    //
    // #[test]
    // fn inflight_ring_buffer_pushes_correctly() {
    //     let count = MAX_INFLIGHT as usize;
    //     let (mut outgoing, _rx) = Outgoing::new("hello".to_owned());
    //     outgoing.push_forwards(publishes(count), 1, 3);
    //
    //     // Index 1 = (0, 1), Index 99 = (0, 99), Index 0 = (0, 100)
    //     assert_eq!(outgoing.inflight_buffer[0].unwrap().1, (0, count as u64));
    //     for i in 1..count {
    //         assert_eq!(outgoing.inflight_buffer[i].unwrap().1, (0, i as u64));
    //     }
    //
    //     // Outgoing publish pkids are as expected
    //     for (i, o) in outgoing.data_buffer.lock().iter().enumerate() {
    //         let pkid = match &o {
    //             Notification::Forward(f) => f.publish.pkid,
    //             _ => unreachable!(),
    //         };
    //
    //         assert_eq!(pkid, i as u16 + 1);
    //     }
    // }
    //
    // #[test]
    // fn inflight_ring_buffer_pops_correctly() {
    //     let (mut outgoing, _rx) = Outgoing::new("hello".to_owned());
    //     outgoing.push_forwards(publishes(MAX_INFLIGHT as usize), 1, 3);
    //
    //     for pkid in 1..=MAX_INFLIGHT {
    //         let (unsolicited, outoforder) = outgoing.register_ack(pkid);
    //         assert_eq!(unsolicited, false);
    //         assert_eq!(outoforder, false);
    //     }
    // }
}

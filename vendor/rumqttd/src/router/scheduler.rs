use std::collections::{HashSet, VecDeque};

use serde::{Deserialize, Serialize};
use tracing::{debug, trace};

use super::ids::IdTable;
use super::DataRequest;
use crate::{ConnectionId, Filter};

/// fbbus: the invariant behind the tracker lookups that cannot fail: the router calls them
/// only for a connection it holds (registered in every per-connection slab together).
const LIVE_CONNECTION: &str = "invariant: only a registered connection is tracked or paused";

pub struct Scheduler {
    /// Subscriptions and matching topics maintained per connection
    pub trackers: IdTable<Tracker>,
    /// Connections with more pending requests and ready to make progress
    pub readyqueue: VecDeque<ConnectionId>,
}

impl Scheduler {
    pub fn with_capacity(capacity: usize) -> Scheduler {
        Scheduler {
            trackers: IdTable::with_capacity(capacity),
            readyqueue: VecDeque::with_capacity(capacity),
        }
    }

    /// fbbus: at the connection's id, which its link chose (`ids`).
    pub fn add(&mut self, id: ConnectionId, tracker: Tracker) {
        self.trackers.insert_at(id, tracker);
    }

    pub fn remove(&mut self, id: ConnectionId) -> Option<Tracker> {
        self.trackers.remove(id)
    }

    /// Next connection which is ready to make progress
    pub fn poll(&mut self) -> Option<(ConnectionId, VecDeque<DataRequest>)> {
        // fbbus: ids of connections that are gone are skipped (the router leaves them in
        // the queue, see `handle_disconnection`). Upstream returned `None` for one, as if
        // nobody were ready, and the router then waited for the next event while the
        // connections behind it in the queue had data to send.
        let (id, tracker) = loop {
            let id = self.readyqueue.pop_front()?;
            if let Some(tracker) = self.trackers.get_mut(id) {
                break (id, tracker);
            }
        };

        // drain will clear all DataRequest but will keep the allocated memory of our VecDeque.
        let data_requests = tracker.data_requests.drain(..).collect();

        // Implicitly reschedule the connection. Router will take care of explicitly pausing if
        // required (it has the state necessary to determine if pausing is required)
        self.readyqueue.push_back(id);
        Some((id, data_requests))
    }

    pub fn track(&mut self, id: ConnectionId, request: DataRequest) {
        let tracker = self.trackers.get_mut(id).expect(LIVE_CONNECTION);
        tracker.register_data_request(request);
    }

    pub fn untrack(&mut self, id: ConnectionId, filter: &Filter) {
        let tracker = self.trackers.get_mut(id).expect(LIVE_CONNECTION);
        tracker.unregister_data_request(filter.clone());
    }

    pub fn trackv(&mut self, id: ConnectionId, requests: VecDeque<DataRequest>) {
        let tracker = self.trackers.get_mut(id).expect(LIVE_CONNECTION);
        tracker.data_requests.extend(requests);
    }

    pub fn reschedule(&mut self, id: ConnectionId, reason: ScheduleReason) {
        // fbbus: a connection that is gone is not scheduled. `Event::Ready` comes from a
        // link (`LinkRx::wake`) and may arrive after the router dropped its connection
        // (a taken-over client id, an ack the router refused): upstream unwrapped the
        // tracker here and the router thread panicked.
        let Some(tracker) = self.trackers.get_mut(id) else {
            debug!(id, ?reason, "not scheduled: the connection is gone");
            return;
        };
        if let Some(v) = tracker.try_ready(reason) {
            trace!(tracker_id = tracker.id, "reschedule {:?} -> Ready", v);
            self.readyqueue.push_back(id);
        }
    }

    pub fn pause(&mut self, id: ConnectionId, reason: PauseReason) {
        assert_eq!(
            self.readyqueue.pop_back(),
            Some(id),
            "invariant: the router pauses only the connection it polled last, which `poll` \
             put back at the end of the ready queue"
        );
        let tracker = self.trackers.get_mut(id).expect(LIVE_CONNECTION);

        trace!(
            tracker_id = tracker.id,
            "pause {:?} -> {:?}",
            tracker.status,
            reason
        );
        tracker.pause(reason);
    }
}

/// Used to register a new connection with the router
/// Connection messages encompasses a handle for router to
/// communicate with this connection
/// TODO: Don't expose tracker to the outside world
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct Tracker {
    pub id: String,
    /// Data requests of all the subscriptions of this connection
    pub data_requests: VecDeque<DataRequest>,
    /// State machine
    pub status: Status,
}

#[derive(Debug, Copy, Clone, PartialEq, Eq, Serialize, Deserialize)]
pub enum Status {
    Ready,
    Paused(PauseReason),
}

#[derive(Debug, Copy, Clone, PartialEq, Eq, Serialize, Deserialize)]
pub enum ScheduleReason {
    Init,
    NewFilter,
    FreshData,
    IncomingAck,
    Ready,
}

#[derive(Debug, Copy, Clone, PartialEq, Eq, Serialize, Deserialize)]
pub enum PauseReason {
    Caughtup,
    InflightFull,
    Busy,
}

impl Tracker {
    pub fn new(client_id: String) -> Tracker {
        // fbbus: allocated on the first subscription.
        let requests = VecDeque::new();
        Tracker {
            id: client_id,
            data_requests: requests,
            status: Status::Paused(PauseReason::Busy),
        }
    }

    pub fn _reset(&mut self) {
        self.data_requests.clear();
        self.status = Status::Paused(PauseReason::Busy);
    }

    /// Sets the state to ready if correct event to bring out of paused state
    /// is received.
    ///
    /// Doesn't change the state to ready if counter event is not received or
    /// if already in ready state
    ///
    /// Returns Some(previous state) if status is changed to ready.
    /// None return implies either the connection is already ready of the
    /// state cannot be changed to ready
    pub fn try_ready(&mut self, reason: ScheduleReason) -> Option<PauseReason> {
        let previous = match self.status {
            Status::Ready => return None,
            Status::Paused(p) => p,
        };

        match reason {
            ScheduleReason::Init => {
                debug_assert!(
                    self.status == Status::Paused(PauseReason::Busy),
                    "invariant: a connection starts with a new tracker or a saved one, both \
                     paused Busy (`Tracker::new`, `Graveyard::save_state`)"
                );
                self.status = Status::Ready;
                Some(previous)
            }
            ScheduleReason::NewFilter if previous == PauseReason::Caughtup => {
                self.status = Status::Ready;
                Some(previous)
            }
            ScheduleReason::FreshData if previous == PauseReason::Caughtup => {
                self.status = Status::Ready;
                Some(previous)
            }
            // There might be a case where we got IncomingAck but our inflight wasn't full
            // In case of QoS2, we need to send back PubRel ASAP,
            // So we set status to Ready in case of IncomingAck unless reason in Busy
            ScheduleReason::IncomingAck if previous != PauseReason::Busy => {
                self.status = Status::Ready;
                Some(previous)
            }
            // fbbus: only a connection paused because its buffer was full waits for its
            // link's `Ready` (`Notification::Unschedule`). A `Ready` found in another state
            // is stale: its link's connection was replaced by a new one under the same id
            // (slab ids are reused). Upstream asserted Busy (a panic in debug builds) and
            // scheduled whatever it found.
            ScheduleReason::Ready if previous == PauseReason::Busy => {
                self.status = Status::Ready;
                Some(previous)
            }
            _ => None,
        }
    }

    pub fn pause(&mut self, reason: PauseReason) {
        self.status = Status::Paused(reason);
    }

    pub fn _is_empty(&self) -> bool {
        self.data_requests.is_empty()
    }

    pub fn get_data_requests(&self) -> &VecDeque<DataRequest> {
        &self.data_requests
    }

    pub fn register_data_request(&mut self, request: DataRequest) {
        self.data_requests.push_back(request);
    }

    pub fn unregister_data_request(&mut self, filter: Filter) {
        self.data_requests
            .retain(|data_req| data_req.filter != filter);
    }
}

// Methods to check duplicates in trackers and schedulers
impl Scheduler {
    // Return a `Some` if duplicate were found, otherwise `None`
    pub fn check_readyqueue_duplicates(&self) -> Option<&VecDeque<ConnectionId>> {
        let readyqueue = &self.readyqueue;
        // In _worst_ case where all elements are unique, the size of uniq will be same as len of readyqueue
        let mut uniq = HashSet::with_capacity(readyqueue.len());

        let all_uniq = readyqueue.iter().all(|x| uniq.insert(x));

        if !all_uniq {
            Some(readyqueue)
        } else {
            None
        }
    }

    // Return a `Some` if duplicate were found, otherwise `None`
    pub fn check_tracker_duplicates(&self, id: ConnectionId) -> Option<&VecDeque<DataRequest>> {
        let tracker = self.trackers.get(id).expect(LIVE_CONNECTION);
        let tracker_data_req = tracker.get_data_requests();
        let mut uniq = HashSet::with_capacity(tracker_data_req.len());

        // fbbus: one request per subscription, not per log: `x` and `$share/g/x` read the
        // same log (one filter index). Upstream compared indices, and a client subscribing
        // both (one SUBSCRIBE is enough) failed the router's debug assertion.
        let all_uniq = tracker_data_req.iter().all(|x| uniq.insert(&x.filter));

        if !all_uniq {
            Some(&tracker.data_requests)
        } else {
            None
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn busy_connection(scheduler: &mut Scheduler, client_id: &str) -> ConnectionId {
        let id = scheduler.trackers.len();
        scheduler.add(id, Tracker::new(client_id.to_owned()));
        scheduler.reschedule(id, ScheduleReason::Init);
        id
    }

    /// fbbus: a link's `Ready` for a connection the router dropped must not panic.
    #[test]
    fn scheduling_a_connection_that_is_gone_does_nothing() {
        let mut scheduler = Scheduler::with_capacity(0);
        let id = busy_connection(&mut scheduler, "a");
        scheduler.remove(id);
        scheduler.reschedule(id, ScheduleReason::Ready);
        scheduler.reschedule(id + 1, ScheduleReason::FreshData);
        assert_eq!(scheduler.readyqueue, [id]);
    }

    /// fbbus: `Ready` only ends a pause for a full buffer; a stale one (its connection was
    /// replaced under the same id) changes nothing.
    #[test]
    fn a_stale_ready_leaves_a_caught_up_connection_paused() {
        let mut scheduler = Scheduler::with_capacity(0);
        let id = busy_connection(&mut scheduler, "a");
        assert_eq!(scheduler.poll().map(|(polled, _)| polled), Some(id));
        scheduler.pause(id, PauseReason::Caughtup);
        scheduler.reschedule(id, ScheduleReason::Ready);
        assert!(scheduler.readyqueue.is_empty());
        assert_eq!(
            scheduler.trackers.get(id).unwrap().status,
            Status::Paused(PauseReason::Caughtup)
        );

        assert_eq!(scheduler.poll(), None);
        scheduler
            .trackers
            .get_mut(id)
            .unwrap()
            .pause(PauseReason::Busy);
        scheduler.reschedule(id, ScheduleReason::Ready);
        assert_eq!(scheduler.readyqueue, [id]);
    }

    /// fbbus: a gone connection's id left in the ready queue does not hide the ones after it.
    #[test]
    fn polling_skips_connections_that_are_gone() {
        let mut scheduler = Scheduler::with_capacity(0);
        let gone = busy_connection(&mut scheduler, "gone");
        let live = busy_connection(&mut scheduler, "live");
        scheduler.remove(gone);
        assert_eq!(scheduler.poll().map(|(id, _)| id), Some(live));
        assert_eq!(scheduler.readyqueue, [live]);
    }
}

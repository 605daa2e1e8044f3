use std::collections::{BTreeMap, BTreeSet, HashMap, VecDeque};
use std::sync::atomic::{AtomicU64, AtomicUsize, Ordering};
use std::sync::Arc;

use tracing::{debug, warn};

use super::{
    scheduler::{PauseReason, Tracker},
    ConnectionEvents, DataRequest,
};

/// fbbus: the default of `RouterConfig::max_saved_sessions`. As many offline persistent
/// sessions as fbbus's default `max_connections`: every client that can be connected at
/// once can also be away with its session saved (a line of ~1,000 devices with persistent
/// sessions fits four times over). A saved session costs its client id, subscriptions
/// and read cursors, well under 1 KB for a device with a few subscriptions: a few MB at
/// the cap. Without a cap, every client id ever seen with a persistent session stayed
/// forever (an MQTT 3.1.1 session never expires).
pub const DEFAULT_MAX_SAVED_SESSIONS: usize = 4096;

/// fbbus: the saved persistent sessions, for the embedder's metrics (`RouterHooks`).
/// Updated by the router thread whenever a session is saved, resumed or dropped.
#[derive(Debug, Default)]
pub struct SavedSessions {
    saved: AtomicUsize,
    dropped: AtomicU64,
}

impl SavedSessions {
    /// Offline persistent sessions the router keeps now.
    pub fn saved(&self) -> usize {
        self.saved.load(Ordering::Relaxed)
    }

    /// Saved sessions dropped so far because `max_saved_sessions` were kept (the oldest
    /// saved goes first). Its client finds no session when it comes back.
    pub fn dropped(&self) -> u64 {
        self.dropped.load(Ordering::Relaxed)
    }
}

pub struct Graveyard {
    /// fbbus: each saved session with its save number (its age, see `by_age`).
    connections: HashMap<String, (u64, SavedState)>,
    /// fbbus: client ids of the saved sessions by save number, oldest first.
    by_age: BTreeMap<u64, String>,
    next_save: u64,
    /// fbbus: at most this many sessions are kept (`RouterConfig::max_saved_sessions`).
    max_saved: usize,
    stats: Arc<SavedSessions>,
    /// fbbus: the first drop at the cap was warned about.
    warned: bool,
}

impl Graveyard {
    pub fn new(max_saved: usize) -> Graveyard {
        Graveyard {
            connections: HashMap::new(),
            by_age: BTreeMap::new(),
            next_save: 0,
            max_saved,
            stats: Arc::default(),
            warned: false,
        }
    }

    /// fbbus: the counters the embedder reads (`RouterHooks::saved_sessions`).
    pub fn report_to(&mut self, stats: Arc<SavedSessions>) {
        stats.saved.store(self.connections.len(), Ordering::Relaxed);
        self.stats = stats;
    }

    /// Add a new connection.
    /// Return tracker of previous connection if connection id already exists
    pub fn retrieve(&mut self, id: &str) -> Option<SavedState> {
        let (age, saved) = self.connections.remove(id)?;
        self.by_age.remove(&age);
        self.count();
        Some(saved)
    }

    /// fbbus: the saved session of `id`, left in place (for tests; upstream's
    /// `print_status`, removed with the console, used `retrieve`, which ended the session).
    #[cfg(test)]
    pub fn get(&self, id: &str) -> Option<&SavedState> {
        self.connections.get(id).map(|(_, saved)| saved)
    }

    /// Save connection tracker
    pub fn save_state(
        &mut self,
        mut tracker: Tracker,
        subscriptions: BTreeSet<String>,
        metrics: ConnectionEvents,
        unacked_pubrels: VecDeque<u16>,
    ) {
        tracker.pause(PauseReason::Busy);
        let id = tracker.id.clone();

        let session_state = SessionState {
            tracker,
            subscriptions,
            unacked_pubrels,
        };

        let saved = SavedState {
            session_state: Some(session_state),
            metrics,
        };
        // fbbus: kept in the order saved; at the cap the oldest saved session is dropped.
        let age = self.next_save;
        self.next_save += 1;
        if let Some((previous, _)) = self.connections.insert(id.clone(), (age, saved)) {
            self.by_age.remove(&previous);
        }
        self.by_age.insert(age, id);
        while self.connections.len() > self.max_saved {
            let Some((_, oldest)) = self.by_age.pop_first() else {
                break;
            };
            self.connections.remove(&oldest);
            self.stats.dropped.fetch_add(1, Ordering::Relaxed);
            if !self.warned {
                self.warned = true;
                warn!(
                    client_id = %oldest,
                    max_saved_sessions = self.max_saved,
                    "saved-session limit reached: the oldest saved persistent session was \
                     dropped (further drops are only counted, and logged at debug level)"
                );
            } else {
                debug!(client_id = %oldest, "saved-session limit: oldest session dropped");
            }
        }
        self.count();
    }

    /// fbbus: the read requests of the saved sessions (their subscriptions' cursors).
    pub fn data_requests(&self) -> impl Iterator<Item = &DataRequest> {
        self.connections
            .values()
            .filter_map(|(_, saved)| saved.session_state.as_ref())
            .flat_map(|state| state.tracker.data_requests.iter())
    }

    /// fbbus: the subscriptions of the saved sessions.
    pub fn subscriptions(&self) -> impl Iterator<Item = &String> {
        self.connections
            .values()
            .filter_map(|(_, saved)| saved.session_state.as_ref())
            .flat_map(|state| state.subscriptions.iter())
    }

    /// fbbus: sessions saved now.
    #[cfg(test)]
    pub fn len(&self) -> usize {
        self.connections.len()
    }

    fn count(&self) {
        self.stats
            .saved
            .store(self.connections.len(), Ordering::Relaxed);
    }
}

#[derive(Debug)]
pub struct SavedState {
    pub session_state: Option<SessionState>,
    pub metrics: ConnectionEvents,
}

#[derive(Debug)]
pub struct SessionState {
    pub tracker: Tracker,
    pub subscriptions: BTreeSet<String>,
    // used for pubrel in qos2
    pub unacked_pubrels: VecDeque<u16>,
}

#[cfg(test)]
mod tests {
    use super::*;

    fn save(graveyard: &mut Graveyard, client_id: &str) {
        let mut subscriptions = BTreeSet::new();
        subscriptions.insert(format!("{client_id}/cmd"));
        graveyard.save_state(
            Tracker::new(client_id.to_owned()),
            subscriptions,
            ConnectionEvents::default(),
            VecDeque::new(),
        );
    }

    #[test]
    fn at_the_cap_the_oldest_saved_session_is_dropped_and_counted() {
        let stats = Arc::new(SavedSessions::default());
        let mut graveyard = Graveyard::new(3);
        graveyard.report_to(stats.clone());
        for id in ["a", "b", "c"] {
            save(&mut graveyard, id);
        }
        assert_eq!((stats.saved(), stats.dropped()), (3, 0));

        // "a" comes back and leaves again: it is the newest now, "b" the oldest.
        assert!(graveyard.retrieve("a").is_some());
        assert_eq!(stats.saved(), 2);
        save(&mut graveyard, "a");
        save(&mut graveyard, "d");
        assert_eq!((stats.saved(), stats.dropped()), (3, 1));
        assert!(graveyard.get("b").is_none());
        for id in ["c", "a", "d"] {
            assert!(graveyard.get(id).is_some(), "{id} is kept");
        }

        for id in 0..1000 {
            save(&mut graveyard, &format!("churn-{id}"));
        }
        assert_eq!(graveyard.len(), 3);
        assert_eq!(graveyard.by_age.len(), 3);
        assert_eq!((stats.saved(), stats.dropped()), (3, 1001));
        assert!(graveyard.retrieve("churn-999").is_some());
        assert!(graveyard.retrieve("a").is_none());
    }

    #[test]
    fn a_cap_of_zero_keeps_nothing() {
        let mut graveyard = Graveyard::new(0);
        save(&mut graveyard, "a");
        assert_eq!(graveyard.len(), 0);
        assert!(graveyard.by_age.is_empty());
        assert_eq!(graveyard.stats.dropped(), 1);
    }

    #[test]
    fn saving_a_session_twice_keeps_one_entry() {
        let mut graveyard = Graveyard::new(10);
        save(&mut graveyard, "a");
        save(&mut graveyard, "a");
        assert_eq!((graveyard.len(), graveyard.by_age.len()), (1, 1));
        assert!(graveyard.retrieve("a").is_some());
        assert!(graveyard.by_age.is_empty());
    }
}

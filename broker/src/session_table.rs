//! Which connection owns each client id, and each client's session number.
//!
//! Every accepted CONNECT gets the next session number of its client id. When rumqttd's
//! router drops a link, the connection compares its number with the current one: a newer
//! number means another connection took the client id over (MQTT session takeover);
//! the same number means the router itself ended the link. The number is the Sparkplug
//! `bdSeq` idea: the device registry uses it so that a late will from an old session never
//! marks a newer session offline.
//!
//! The number also makes MQTT 5 session expiry simple: when a session's expiry is due,
//! it is ended only if its number is still the newest and nobody is connected with it
//! ([`SessionTable::with_idle`]); a client that came back in time has a newer number.

use std::collections::HashMap;
use std::sync::{Mutex, PoisonError};

#[derive(Default)]
pub struct SessionTable {
    /// client id -> (latest session number, whether that session is connected)
    sessions: Mutex<HashMap<String, (u64, bool)>>,
}

impl SessionTable {
    /// Registers a new connection for `client_id`; returns its session number, and whether
    /// the previous connection of that client id is still running (has not closed yet).
    pub fn open(&self, client_id: &str) -> (u64, bool) {
        let mut sessions = self.sessions.lock().unwrap_or_else(PoisonError::into_inner);
        let entry = sessions.entry(client_id.to_owned()).or_insert((0, false));
        let previous_running = entry.1;
        entry.0 += 1;
        entry.1 = true;
        (entry.0, previous_running)
    }

    /// Continues `client_id`'s numbering after `session` (from the persisted registry).
    pub fn seed(&self, client_id: &str, session: u64) {
        let mut sessions = self.sessions.lock().unwrap_or_else(PoisonError::into_inner);
        let entry = sessions.entry(client_id.to_owned()).or_insert((0, false));
        entry.0 = entry.0.max(session);
    }

    /// Whether `session` is still the newest session of `client_id`.
    pub fn is_current(&self, client_id: &str, session: u64) -> bool {
        self.sessions
            .lock()
            .unwrap_or_else(PoisonError::into_inner)
            .get(client_id)
            .is_some_and(|(latest, _)| *latest == session)
    }

    /// Runs `f` if `session` is the newest session of `client_id` and not connected, with
    /// the table held, so no connection of that client id starts while `f` runs.
    pub fn with_idle<R>(&self, client_id: &str, session: u64, f: impl FnOnce() -> R) -> Option<R> {
        let sessions = self.sessions.lock().unwrap_or_else(PoisonError::into_inner);
        match sessions.get(client_id) {
            Some((latest, false)) if *latest == session => Some(f()),
            _ => None,
        }
    }

    /// The connection of `session` ended; the number is kept so the next one is higher.
    pub fn close(&self, client_id: &str, session: u64) {
        self.close_with(client_id, session, |_| ());
    }

    /// [`SessionTable::close`], running `f(superseded)` with the table held: `superseded`
    /// says a newer connection of `client_id` has started. No connection of the client id
    /// starts while `f` runs, so what `f` hands over is either there before the newer
    /// connection's [`SessionTable::open`] (which then reports no running predecessor), or
    /// handed over knowing it is awaited (`redelivery`).
    pub fn close_with<R>(&self, client_id: &str, session: u64, f: impl FnOnce(bool) -> R) -> R {
        let mut sessions = self.sessions.lock().unwrap_or_else(PoisonError::into_inner);
        let entry = sessions.get_mut(client_id);
        let superseded = entry.as_ref().is_some_and(|(latest, _)| *latest != session);
        if let Some(entry) = entry {
            if entry.0 == session {
                entry.1 = false;
            }
        }
        f(superseded)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_newer_session_makes_the_older_one_stale() {
        let t = SessionTable::default();
        let (a, running) = t.open("plc");
        assert!(!running);
        assert!(t.is_current("plc", a));
        let (b, running) = t.open("plc");
        assert!(b > a);
        assert!(running, "a has not closed");
        assert!(!t.is_current("plc", a));
        t.close("plc", a);
        assert!(t.is_current("plc", b));
        assert_eq!(t.with_idle("plc", b, || ()), None, "connected");
        t.close("plc", b);
        assert_eq!(t.with_idle("plc", b, || 7), Some(7));
        assert_eq!(t.with_idle("plc", a, || 7), None, "stale");
        assert!(
            t.close_with("plc", a, |superseded| superseded),
            "b is newer"
        );
        assert_eq!(t.open("plc"), (b + 1, false));
    }
}

//! Redelivery: what a resumed session gets again, and under which packet ids.
//!
//! When a persistent session resumes, rumqttd's router sends the QoS 1 and 2 deliveries
//! the client never acknowledged again — it rewinds the filter's commit-log cursor and
//! reads them as new forwards — with DUP=0 and packet ids from a fresh per-connection
//! counter, and it sends the pending PUBRELs again. MQTT says a re-sent PUBLISH carries
//! DUP=1 [MQTT-3.3.1-1] and its original packet id [MQTT-4.4.0-1]. The router does not
//! know which deliveries reached the old connection, nor which ids the client saw; the
//! connection does (`packet_ids`). So a connection that ends with its session kept hands
//! its open exchanges over here ([`Resume`]), and the next connection of that client id
//! recognises each re-sent message by its fingerprint (topic and payload) and sends it
//! with DUP=1 under its original id.
//!
//! The handover has to beat the next connection. A client that drops and reconnects at
//! once can have its new connection linked before the old one has closed, so the new one
//! waits for the handover when its predecessor was still running ([`Redeliveries::take`]),
//! at most [`HANDOVER_WAIT`]. The predecessor hands over inside `SessionTable::close_with`,
//! so it knows whether a newer connection is waiting, and then leaves a mark even when it
//! has nothing to hand over.
//!
//! Fingerprints, because the router's re-send is a new forward with nothing else that
//! ties it to the first delivery. The router re-sends before anything new, so a new
//! message with the same topic and payload cannot take a re-sent one's place.
//!
//! Bounded: at most as many handovers as the router keeps sessions
//! (`router::saved_sessions_limit`); beyond, the one of the oldest session (lowest session
//! number, numbers are global) is dropped: its client, if it ever comes back, gets the
//! router's re-sends with DUP=0 and new packet ids, as before fbbus tracked them.

use std::collections::{BTreeMap, HashMap};
use std::hash::{Hash, Hasher};
use std::sync::Mutex;
use std::time::Duration;

use crate::session::packet_ids::Resume;

/// A delivery's fingerprint: a hash of its topic and payload.
pub fn fingerprint(topic: &[u8], payload: &[u8]) -> u64 {
    let mut h = std::collections::hash_map::DefaultHasher::new();
    topic.hash(&mut h);
    payload.hash(&mut h);
    h.finish()
}

/// How long a connection waits for its still-running predecessor's handover.
pub const HANDOVER_WAIT: Duration = Duration::from_secs(1);

pub struct Redeliveries {
    pending: Mutex<Pending>,
    /// Handovers kept at most.
    limit: usize,
}

#[derive(Default)]
struct Pending {
    by_client: HashMap<String, Handover>,
    /// Client ids by the session number of their handover, oldest first.
    by_session: BTreeMap<u64, String>,
}

impl Pending {
    fn insert(&mut self, client_id: &str, handover: Handover, limit: usize) {
        self.by_session
            .insert(handover.session, client_id.to_owned());
        if let Some(old) = self.by_client.insert(client_id.to_owned(), handover) {
            self.by_session.remove(&old.session);
        }
        while self.by_client.len() > limit {
            let Some((_, oldest)) = self.by_session.pop_first() else {
                break;
            };
            self.by_client.remove(&oldest);
        }
    }

    fn remove(&mut self, client_id: &str) -> Option<Handover> {
        let handover = self.by_client.remove(client_id)?;
        self.by_session.remove(&handover.session);
        Some(handover)
    }
}

/// What the connection with session number `session` handed over.
struct Handover {
    session: u64,
    resume: Resume,
}

impl Redeliveries {
    /// A table keeping at most `limit` handovers.
    pub fn new(limit: usize) -> Redeliveries {
        Redeliveries {
            pending: Mutex::default(),
            limit,
        }
    }

    /// The connection `session` of `client_id` ended with these exchanges open (empty for
    /// a clean session). `superseded`: a newer connection of the client id has started and
    /// waits for this, so even nothing is handed over as a mark.
    pub fn save(&self, client_id: &str, session: u64, resume: Resume, superseded: bool) {
        let mut pending = self.pending();
        if resume.is_empty() && !superseded {
            pending.remove(client_id);
        } else {
            pending.insert(client_id, Handover { session, resume }, self.limit);
        }
    }

    /// The connection `session` of `client_id` ended before it took its own handover (its
    /// CONNACK could not be sent): what an earlier connection handed over stays for the
    /// next one; a newer connection waiting for this one gets a mark.
    pub fn abandoned(&self, client_id: &str, session: u64, superseded: bool) {
        let mut pending = self.pending();
        if superseded && !pending.by_client.contains_key(client_id) {
            let mark = Handover {
                session,
                resume: Resume::default(),
            };
            pending.insert(client_id, mark, self.limit);
        }
    }

    /// What the resuming connection `session` of `client_id` starts from. When its
    /// predecessor was still running at its start (`SessionTable::open`), it waits for
    /// that one's handover, at most [`HANDOVER_WAIT`].
    pub async fn take(&self, client_id: &str, session: u64, predecessor_running: bool) -> Resume {
        let deadline = tokio::time::Instant::now() + HANDOVER_WAIT;
        loop {
            {
                let mut pending = self.pending();
                if pending
                    .by_client
                    .get(client_id)
                    .is_some_and(|h| h.session < session)
                {
                    return pending
                        .remove(client_id)
                        .map(|h| h.resume)
                        .unwrap_or_default();
                }
            }
            if !predecessor_running || tokio::time::Instant::now() >= deadline {
                return Resume::default();
            }
            tokio::time::sleep(Duration::from_millis(2)).await;
        }
    }

    /// The session of `client_id` ended: nothing will be re-sent.
    pub fn forget(&self, client_id: &str) {
        self.pending().remove(client_id);
    }

    /// The table, also after a panic elsewhere left the lock poisoned: every update is a
    /// single insert or remove, so it is never half done.
    fn pending(&self) -> std::sync::MutexGuard<'_, Pending> {
        self.pending
            .lock()
            .unwrap_or_else(std::sync::PoisonError::into_inner)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::session::packet_ids::PacketIds;

    fn open_exchange(print: u64) -> Resume {
        let mut ids = PacketIds::default();
        ids.deliver(1, print);
        ids.into_resume()
    }

    #[tokio::test]
    async fn open_exchanges_are_handed_over_once() {
        let r = Redeliveries::new(10);
        let a = fingerprint(b"t", b"one");
        assert_ne!(a, fingerprint(b"t", b"two"));
        assert_ne!(a, fingerprint(b"to", b"ne"));
        r.save("plc", 1, open_exchange(a), false);
        assert_eq!(r.take("plc", 2, false).await, open_exchange(a));
        assert!(r.take("plc", 3, false).await.is_empty());
        r.save("plc", 3, open_exchange(a), false);
        r.forget("plc");
        assert!(r.take("plc", 4, false).await.is_empty());
    }

    #[tokio::test]
    async fn a_connection_waits_for_its_running_predecessor() {
        let r = std::sync::Arc::new(Redeliveries::new(10));
        let a = fingerprint(b"t", b"one");
        let late = r.clone();
        tokio::spawn(async move {
            tokio::time::sleep(Duration::from_millis(50)).await;
            late.save("plc", 1, open_exchange(a), true);
        });
        assert_eq!(r.take("plc", 2, true).await, open_exchange(a));

        // A predecessor with nothing to hand over leaves a mark, so the wait is short.
        let late = r.clone();
        tokio::spawn(async move {
            tokio::time::sleep(Duration::from_millis(50)).await;
            late.save("plc", 2, Resume::default(), true);
        });
        let started = std::time::Instant::now();
        assert!(r.take("plc", 3, true).await.is_empty());
        assert!(
            started.elapsed() < HANDOVER_WAIT,
            "waited for the mark, not the limit"
        );
    }

    /// Issue 14: at most `limit` handovers, the oldest session's dropped first.
    #[tokio::test]
    async fn handovers_are_bounded() {
        let r = Redeliveries::new(2);
        let a = fingerprint(b"t", b"one");
        for (session, id) in [(1, "a"), (2, "b"), (3, "c")] {
            r.save(id, session, open_exchange(a), false);
        }
        assert!(r.take("a", 10, false).await.is_empty(), "dropped");
        assert_eq!(r.take("b", 11, false).await, open_exchange(a));
        assert_eq!(r.take("c", 12, false).await, open_exchange(a));
        let pending = r.pending();
        assert!(pending.by_client.is_empty() && pending.by_session.is_empty());
    }
}

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

use std::collections::HashMap;
use std::hash::{Hash, Hasher};
use std::sync::Mutex;
use std::time::Duration;

use crate::packet_ids::Resume;

/// A delivery's fingerprint: a hash of its topic and payload.
pub fn fingerprint(topic: &[u8], payload: &[u8]) -> u64 {
    let mut h = std::collections::hash_map::DefaultHasher::new();
    topic.hash(&mut h);
    payload.hash(&mut h);
    h.finish()
}

/// How long a connection waits for its still-running predecessor's handover.
pub const HANDOVER_WAIT: Duration = Duration::from_secs(1);

#[derive(Default)]
pub struct Redeliveries {
    pending: Mutex<HashMap<String, Handover>>,
}

/// What the connection with session number `session` handed over.
struct Handover {
    session: u64,
    resume: Resume,
}

impl Redeliveries {
    /// The connection `session` of `client_id` ended with these exchanges open (empty for
    /// a clean session). `superseded`: a newer connection of the client id has started and
    /// waits for this, so even nothing is handed over as a mark.
    pub fn save(&self, client_id: &str, session: u64, resume: Resume, superseded: bool) {
        let mut pending = self.pending();
        if resume.is_empty() && !superseded {
            pending.remove(client_id);
        } else {
            pending.insert(client_id.to_owned(), Handover { session, resume });
        }
    }

    /// The connection `session` of `client_id` ended before it took its own handover (its
    /// CONNACK could not be sent): what an earlier connection handed over stays for the
    /// next one; a newer connection waiting for this one gets a mark.
    pub fn abandoned(&self, client_id: &str, session: u64, superseded: bool) {
        if superseded {
            self.pending()
                .entry(client_id.to_owned())
                .or_insert(Handover {
                    session,
                    resume: Resume::default(),
                });
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
                if pending.get(client_id).is_some_and(|h| h.session < session) {
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
    fn pending(&self) -> std::sync::MutexGuard<'_, HashMap<String, Handover>> {
        self.pending.lock().unwrap_or_else(|e| e.into_inner())
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::packet_ids::PacketIds;

    fn open_exchange(print: u64) -> Resume {
        let mut ids = PacketIds::default();
        ids.deliver(1, print);
        ids.into_resume()
    }

    #[tokio::test]
    async fn open_exchanges_are_handed_over_once() {
        let r = Redeliveries::default();
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
        let r = std::sync::Arc::new(Redeliveries::default());
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
}

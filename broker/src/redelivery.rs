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
//! Fingerprints, because the router's re-send is a new forward with nothing else that
//! ties it to the first delivery. The router re-sends before anything new, so a new
//! message with the same topic and payload cannot take a re-sent one's place.

use std::collections::HashMap;
use std::hash::{Hash, Hasher};
use std::sync::Mutex;

use crate::packet_ids::Resume;

/// A delivery's fingerprint: a hash of its topic and payload.
pub fn fingerprint(topic: &[u8], payload: &[u8]) -> u64 {
    let mut h = std::collections::hash_map::DefaultHasher::new();
    topic.hash(&mut h);
    payload.hash(&mut h);
    h.finish()
}

#[derive(Default)]
pub struct Redeliveries {
    pending: Mutex<HashMap<String, Resume>>,
}

impl Redeliveries {
    /// A connection with a kept session ended with these exchanges open.
    pub fn save(&self, client_id: &str, open: Resume) {
        let mut pending = self.pending();
        if open.is_empty() {
            pending.remove(client_id);
        } else {
            pending.insert(client_id.to_owned(), open);
        }
    }

    /// What a resuming connection of `client_id` starts from.
    pub fn take(&self, client_id: &str) -> Resume {
        self.pending().remove(client_id).unwrap_or_default()
    }

    /// The session of `client_id` ended: nothing will be re-sent.
    pub fn forget(&self, client_id: &str) {
        self.pending().remove(client_id);
    }

    /// The table, also after a panic elsewhere left the lock poisoned: every update is a
    /// single insert or remove, so it is never half done.
    fn pending(&self) -> std::sync::MutexGuard<'_, HashMap<String, Resume>> {
        self.pending.lock().unwrap_or_else(|e| e.into_inner())
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::packet_ids::PacketIds;

    #[test]
    fn open_exchanges_are_handed_over_once() {
        let r = Redeliveries::default();
        let a = fingerprint(b"t", b"one");
        assert_ne!(a, fingerprint(b"t", b"two"));
        assert_ne!(a, fingerprint(b"to", b"ne"));
        let open = || {
            let mut ids = PacketIds::default();
            ids.deliver(1, a);
            ids.into_resume()
        };
        r.save("plc", open());
        assert_eq!(r.take("plc"), open());
        assert!(r.take("plc").is_empty());
        r.save("plc", open());
        r.forget("plc");
        assert!(r.take("plc").is_empty());
    }
}

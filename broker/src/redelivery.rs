//! DUP on redelivery: which deliveries a resumed session gets again.
//!
//! When a persistent session resumes, rumqttd's router sends the QoS 1 and 2 deliveries
//! the client never acknowledged again — it rewinds the filter's commit-log cursor and
//! reads them as new forwards — with DUP=0 and packet ids from a fresh per-connection
//! counter. MQTT says a re-sent PUBLISH carries DUP=1 [MQTT-3.3.1-1], so a client can
//! suspect a duplicate. The router does not know which deliveries reached the old
//! connection; the connection does. So each connection remembers a fingerprint (topic
//! and payload) of every delivery the client did not acknowledge (PUBACK, or PUBREC for
//! QoS 2), hands them over here when it ends with its session kept, and the next
//! connection of that client id marks the delivery with a remembered fingerprint DUP=1.
//!
//! Fingerprints rather than packet ids, because the router renumbers: the re-sent
//! message's packet id is the original one only when the numbering happens to coincide
//! (see docs/conformance.md, 17a/b). The router re-sends before anything new, so a new
//! message with the same topic and payload cannot take a re-sent one's mark.

use std::collections::HashMap;
use std::hash::{Hash, Hasher};
use std::sync::Mutex;

/// A delivery's fingerprint: a hash of its topic and payload.
pub fn fingerprint(topic: &[u8], payload: &[u8]) -> u64 {
    let mut h = std::collections::hash_map::DefaultHasher::new();
    topic.hash(&mut h);
    payload.hash(&mut h);
    h.finish()
}

#[derive(Default)]
pub struct Redeliveries {
    pending: Mutex<HashMap<String, Vec<u64>>>,
}

impl Redeliveries {
    /// A connection with a kept session ended with these deliveries unacknowledged.
    pub fn save(&self, client_id: &str, unacked: Vec<u64>) {
        let mut pending = self.pending.lock().expect("lock poisoned");
        if unacked.is_empty() {
            pending.remove(client_id);
        } else {
            pending.insert(client_id.to_owned(), unacked);
        }
    }

    /// The deliveries a resuming connection of `client_id` will see again.
    pub fn take(&self, client_id: &str) -> Vec<u64> {
        self.pending
            .lock()
            .expect("lock poisoned")
            .remove(client_id)
            .unwrap_or_default()
    }

    /// The session of `client_id` ended: nothing will be re-sent.
    pub fn forget(&self, client_id: &str) {
        self.pending
            .lock()
            .expect("lock poisoned")
            .remove(client_id);
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn fingerprints_are_handed_over_once() {
        let r = Redeliveries::default();
        let a = fingerprint(b"t", b"one");
        assert_ne!(a, fingerprint(b"t", b"two"));
        assert_ne!(a, fingerprint(b"to", b"ne"));
        r.save("plc", vec![a]);
        assert_eq!(r.take("plc"), vec![a]);
        assert!(r.take("plc").is_empty());
        r.save("plc", vec![a]);
        r.forget("plc");
        assert!(r.take("plc").is_empty());
    }
}

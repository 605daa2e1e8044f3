//! One copy of a message for a client whose subscriptions overlap.
//!
//! rumqttd's router keeps a commit log per filter, so a message on `a/b/c` reaches a
//! client subscribed to `a/+/c` and `a/#` twice, each copy at its own subscription's QoS
//! and with its own Subscription Identifier. MQTT 5 allows that [MQTT-3.3.4-5], but
//! clients expect one copy carrying every matching subscription's identifier
//! [MQTT-3.3.4-3] [MQTT-3.3.4-4], at the maximum QoS of the matching subscriptions
//! (min'd with the publication's) [MQTT-3.3.4-2]. The session sends one:
//!
//! - every publication carries a number ([`rumqttd::protocol::Origin::seq`], given by
//!   `policy::origin::new`), the same on each copy the router makes of it;
//! - a session whose non-shared subscriptions overlap ([`filters_overlap`]) counts, for a
//!   delivery on a topic matching k >= 2 of them, the k copies the router will send, and
//!   sends the first copy whose QoS is the delivery QoS with the identifiers of all the
//!   matching subscriptions; the others are acknowledged to the router for the client
//!   and dropped. Copies of one router batch are announced before any is sent, so a
//!   lower-QoS copy read first gives way to the higher one behind it. The router hands a
//!   connection everything one scheduling round read, for all its filters, in one batch
//!   (`Router::consume` in the router fork), so the copies of a message arrive
//!   together. If the higher copy comes in a later batch (its filter's in-flight window
//!   was full, or the connection's buffer), the lower one was already sent; the higher
//!   one is then sent too, so a copy at the maximum QoS always arrives (two copies, as
//!   before, in that case only);
//! - options that differ between the matching subscriptions: No Local excludes a
//!   subscription from the identifiers and the QoS of the client's own messages (the copy
//!   is dropped only when every matching one has No Local); Retain As Published is
//!   applied if any matching subscription asks for it (`Session::subscription_options`);
//! - retained messages sent at SUBSCRIBE (RETAIN set by the router) come from the new
//!   subscription only and pass unchanged with its identifier; shared subscriptions
//!   (`$share/...`) never match here, so a group member gets its copies as before.
//!
//! Limits: the session knows the subscriptions its own connection made (as for No
//! Local); a resumed session's older subscriptions are not known, and its overlapping
//! ones give one copy each, as before. A copy that never comes (a subscription made while
//! the message was between the router's logs) leaves an entry, and at most
//! [`MAX_PENDING`] are kept, oldest dropped first.

use std::collections::BTreeMap;

use bytes::Bytes;

/// Publications whose copies are still expected, at most.
pub const MAX_PENDING: usize = 1024;

/// Whether some topic matches both filters (neither shared).
pub fn filters_overlap(a: &str, b: &str) -> bool {
    let (mut a, mut b) = (a.split('/'), b.split('/'));
    loop {
        match (a.next(), b.next()) {
            (Some("#"), _) | (_, Some("#")) => return true,
            (None, None) => return true,
            (None, Some(_)) | (Some(_), None) => return false,
            (Some(x), Some(y)) => {
                if x != "+" && y != "+" && x != y {
                    return false;
                }
            }
        }
    }
}

/// One publication's copies for this connection.
#[derive(Debug)]
struct Pending {
    /// Copies the router has still to deliver (or the session to decide).
    remaining: usize,
    /// The QoS of the copy sent, if one was.
    sent: Option<u8>,
    /// Copies announced and not decided yet, by the router's QoS (0, 1, 2).
    coming: [u16; 3],
}

/// The copies of the current connection, by publication and topic (a typed message's
/// re-encodings share their publication's number, on other topics).
#[derive(Debug, Default)]
pub struct Copies {
    pending: BTreeMap<(u64, Bytes), Pending>,
}

impl Copies {
    fn entry(&mut self, seq: u64, topic: &Bytes, copies: usize) -> &mut Pending {
        let key = (seq, topic.clone());
        if !self.pending.contains_key(&key) {
            if self.pending.len() >= MAX_PENDING {
                self.pending.pop_first();
            }
            // A copy of the topic: the key must not keep a delivery's buffer alive.
            let pending = Pending {
                remaining: copies,
                sent: None,
                coming: [0; 3],
            };
            self.pending
                .insert((seq, Bytes::copy_from_slice(topic)), pending);
        }
        self.pending.get_mut(&key).expect("inserted above")
    }

    /// A copy at the router's QoS `routed` is in this batch, not decided yet.
    pub fn announce(&mut self, seq: u64, topic: &Bytes, copies: usize, routed: u8) {
        let e = self.entry(seq, topic, copies);
        e.coming[routed.min(2) as usize] += 1;
    }

    /// Whether to send this copy (router QoS `routed`) of publication `seq` (published
    /// at `published`), one of `copies`, when the delivery QoS is `target`.
    pub fn decide(
        &mut self,
        seq: u64,
        topic: &Bytes,
        copies: usize,
        routed: u8,
        published: u8,
    ) -> bool {
        let routed = routed.min(2);
        let e = self.entry(seq, topic, copies);
        let c = &mut e.coming[routed as usize];
        *c = c.saturating_sub(1);
        let qos = published.min(routed);
        let better_coming = (0..3u8).any(|q| e.coming[q as usize] > 0 && published.min(q) > qos);
        let send = match e.sent {
            Some(sent) => qos > sent && !better_coming,
            None => !better_coming,
        };
        if send {
            e.sent = Some(qos);
        }
        e.remaining = e.remaining.saturating_sub(1);
        if e.remaining == 0 && e.coming.iter().all(|c| *c == 0) {
            self.pending.remove(&(seq, topic.clone()));
        }
        send
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn overlap_follows_the_filter_grammar() {
        assert!(filters_overlap("a/+/c", "a/#"));
        assert!(filters_overlap("a/b", "+/b"));
        assert!(filters_overlap("a", "a/#"));
        assert!(filters_overlap("#", "x/y"));
        assert!(!filters_overlap("a/+/c", "a/+/d"));
        assert!(!filters_overlap("a/b", "a/b/c"));
        assert!(!filters_overlap("a/+", "b/#"));
    }

    #[test]
    fn one_copy_at_the_highest_qos() {
        let t = Bytes::from("a/b/c");
        let mut c = Copies::default();
        // Same QoS: the first is sent, the second dropped, the entry gone.
        assert!(c.decide(1, &t, 2, 1, 1));
        assert!(!c.decide(1, &t, 2, 1, 1));
        assert!(c.pending.is_empty());
        // QoS 0 copy first, QoS 1 copy behind it in the batch: only the QoS 1 one.
        c.announce(2, &t, 2, 0);
        c.announce(2, &t, 2, 1);
        assert!(!c.decide(2, &t, 2, 0, 1));
        assert!(c.decide(2, &t, 2, 1, 1));
        assert!(c.pending.is_empty());
        // Published at QoS 0: both copies are QoS 0, the first goes.
        c.announce(3, &t, 2, 0);
        c.announce(3, &t, 2, 1);
        assert!(c.decide(3, &t, 2, 0, 0));
        assert!(!c.decide(3, &t, 2, 1, 0));
        // The higher copy in a later batch: sent as well.
        assert!(c.decide(4, &t, 2, 0, 2));
        assert!(c.decide(4, &t, 2, 2, 2));
        // Another topic of the same publication (a typed re-encoding) is its own entry.
        assert!(c.decide(5, &t, 2, 1, 1));
        assert!(c.decide(5, &Bytes::from("x/b/c"), 2, 1, 1));
    }

    #[test]
    fn pending_entries_are_bounded() {
        let mut c = Copies::default();
        let t = Bytes::from("t");
        for seq in 0..(MAX_PENDING as u64 + 10) {
            c.decide(seq, &t, 3, 1, 1);
        }
        assert_eq!(c.pending.len(), MAX_PENDING);
    }
}

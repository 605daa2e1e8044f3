//! Topic aliases the broker sets on its PUBLISH packets to one client (MQTT 5 3.3.2.3.4).
//!
//! A client that announces a Topic Alias Maximum > 0 in CONNECT lets the server replace
//! a topic it has already sent by a two-byte number. The policy, per connection and keyed
//! by topic name:
//! - the first delivery on a topic takes the next free alias (1, 2, ...) and is sent with
//!   its topic and the alias; later deliveries on that topic are sent with an empty topic
//!   and the alias;
//! - once every alias is taken (the client's maximum, at most [`MAX_ALIASES`]), the
//!   assigned ones are kept, and deliveries on other topics carry their full topic and no
//!   alias: no eviction, so a client never has to follow an alias that changes meaning
//!   (a line's devices publish a fixed set of topics, which the first aliases cover);
//! - a client that announced 0 or nothing is never sent an alias [MQTT-3.3.2-9]; aliases
//!   start over with every connection, resumed sessions included [MQTT-3.3.2-10].
//!
//! The session assigns an alias only for a delivery it sends, and takes a fresh
//! assignment back ([`OutAliases::forget_last`]) when that packet is not sent after all
//! (over the client's Maximum Packet Size).

use std::collections::HashMap;

use bytes::Bytes;

/// Aliases kept per connection at most, whatever the client allows: memory is bounded
/// by this many topics (copied, so no delivery's buffer is kept alive).
pub const MAX_ALIASES: u16 = 1024;

/// The aliases of one connection, allocated at its first aliased delivery.
#[derive(Debug)]
pub struct OutAliases {
    max: u16,
    by_topic: HashMap<Bytes, u16>,
}

/// What to put on one delivery.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Alias {
    /// A new alias: send the topic and the alias.
    Set(u16),
    /// An alias the client knows: send an empty topic and the alias.
    Use(u16),
}

impl OutAliases {
    /// For a client whose Topic Alias Maximum is `client_max`; None when it is 0.
    pub fn new(client_max: u16) -> Option<OutAliases> {
        (client_max > 0).then(|| OutAliases {
            max: client_max.min(MAX_ALIASES),
            by_topic: HashMap::new(),
        })
    }

    /// The alias for a delivery on `topic`, assigning the next free one if there is one.
    pub fn alias(&mut self, topic: &Bytes) -> Option<Alias> {
        if topic.is_empty() {
            return None;
        }
        if let Some(&alias) = self.by_topic.get(topic) {
            return Some(Alias::Use(alias));
        }
        let used = self.by_topic.len() as u16;
        if used >= self.max {
            return None;
        }
        let alias = used + 1;
        self.by_topic.insert(Bytes::copy_from_slice(topic), alias);
        Some(Alias::Set(alias))
    }

    /// The delivery that was just given `Alias::Set` for `topic` was not sent: the alias
    /// is free again (it is the last one assigned, so the next is still `len + 1`).
    pub fn forget_last(&mut self, topic: &Bytes) {
        self.by_topic.remove(topic);
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn first_delivery_sets_later_ones_use_and_full_topics_once_all_are_taken() {
        assert!(OutAliases::new(0).is_none());
        let mut a = OutAliases::new(2).unwrap();
        let (x, y, z) = (Bytes::from("x"), Bytes::from("y"), Bytes::from("z"));
        assert_eq!(a.alias(&x), Some(Alias::Set(1)));
        assert_eq!(a.alias(&x), Some(Alias::Use(1)));
        assert_eq!(a.alias(&y), Some(Alias::Set(2)));
        assert_eq!(a.alias(&z), None, "all taken: full topic");
        assert_eq!(a.alias(&y), Some(Alias::Use(2)), "kept, not evicted");
        assert_eq!(a.alias(&x), Some(Alias::Use(1)));
    }

    #[test]
    fn an_unsent_assignment_is_taken_back_and_memory_is_capped() {
        let mut a = OutAliases::new(u16::MAX).unwrap();
        let big = Bytes::from("big");
        assert_eq!(a.alias(&big), Some(Alias::Set(1)));
        a.forget_last(&big);
        assert_eq!(a.alias(&Bytes::from("small")), Some(Alias::Set(1)));
        for i in 0..2000 {
            a.alias(&Bytes::from(format!("t/{i}")));
        }
        assert_eq!(a.by_topic.len(), MAX_ALIASES as usize);
    }
}

//! A cache of recently verified credentials, so that a device reconnecting
//! (network blip, keep-alive timeout, gateway restart) skips argon2.
//!
//! The cache never holds a password. For each user it holds one tag:
//!
//! ```text
//! HMAC-SHA256(key, username ‖ 0x00 ‖ password ‖ 0x00 ‖ stored_hash.phc())
//! ```
//!
//! where `key` is 32 random bytes made when the cache is created; it lives
//! only in this process, so the cache is empty after a broker restart and
//! the first login of every device pays the full argon2 cost. Someone who
//! can read the process memory gets the key too and could test password
//! guesses for cached users at HMAC speed rather than argon2 speed; they
//! could equally read passwords from memory as clients log in, so this is no
//! new exposure worth the cost of argon2 on every reconnect.
//!
//! Because the tag covers the stored hash string, changing or deleting a
//! user's password-file entry makes old tags miss by themselves; no
//! invalidation hook is needed for correctness (`remove` and `clear` just
//! free memory sooner). The concatenation is unambiguous because the user
//! name is the lookup key and the stored hash is the current one, which
//! fixes where the password starts and ends.
//!
//! The cache is bounded: when full, the entry inserted longest ago goes.

use std::collections::HashMap;
use std::fmt;
use std::sync::{Mutex, MutexGuard, PoisonError};

use hmac::{Hmac, Mac as _};
use rand::RngCore as _;
use sha2::Sha256;
use subtle::ConstantTimeEq as _;

use crate::hash::StoredHash;

type Tag = [u8; 32];

/// Verified credentials, keyed by user name. `Send + Sync`.
pub struct CredentialCache {
    key: [u8; 32],
    capacity: usize,
    state: Mutex<State>,
}

#[derive(Default)]
struct State {
    entries: HashMap<String, Entry>,
    /// Insertion counter, to find the oldest entry.
    next_seq: u64,
}

struct Entry {
    tag: Tag,
    seq: u64,
}

impl CredentialCache {
    /// A cache for up to `capacity` users (0 disables caching), with a
    /// fresh random key.
    pub fn new(capacity: usize) -> CredentialCache {
        let mut key = [0u8; 32];
        rand::rngs::OsRng.fill_bytes(&mut key);
        CredentialCache {
            key,
            capacity,
            state: Mutex::new(State::default()),
        }
    }

    /// Did `user` recently log in with exactly this `password` against
    /// exactly this `stored` hash?
    pub fn hit(&self, user: &str, password: &[u8], stored: &StoredHash) -> bool {
        let tag = self.tag(user, password, stored);
        match self.lock().entries.get(user) {
            Some(entry) => bool::from(entry.tag.ct_eq(&tag)),
            None => false,
        }
    }

    /// Remembers a successful verification. Call only after `stored`
    /// accepted `password`.
    pub fn insert(&self, user: &str, password: &[u8], stored: &StoredHash) {
        if self.capacity == 0 {
            return;
        }
        let tag = self.tag(user, password, stored);
        let mut state = self.lock();
        if !state.entries.contains_key(user) && state.entries.len() >= self.capacity {
            let oldest = state
                .entries
                .iter()
                .min_by_key(|(_, entry)| entry.seq)
                .map(|(user, _)| user.clone());
            if let Some(oldest) = oldest {
                state.entries.remove(&oldest);
            }
        }
        let seq = state.next_seq;
        state.next_seq += 1;
        state.entries.insert(user.to_owned(), Entry { tag, seq });
    }

    /// Forgets `user`, e.g. after their password was changed or removed.
    pub fn remove(&self, user: &str) {
        self.lock().entries.remove(user);
    }

    /// Forgets everyone, e.g. after the password file was reloaded.
    pub fn clear(&self) {
        self.lock().entries.clear();
    }

    pub fn len(&self) -> usize {
        self.lock().entries.len()
    }

    pub fn is_empty(&self) -> bool {
        self.lock().entries.is_empty()
    }

    fn tag(&self, user: &str, password: &[u8], stored: &StoredHash) -> Tag {
        let mut mac =
            <Hmac<Sha256>>::new_from_slice(&self.key).expect("HMAC accepts keys of any length");
        mac.update(user.as_bytes());
        mac.update(&[0]);
        mac.update(password);
        mac.update(&[0]);
        mac.update(stored.phc().as_bytes());
        mac.finalize().into_bytes().into()
    }

    fn lock(&self) -> MutexGuard<'_, State> {
        // The map is valid after any panic mid-update, so poisoning is moot.
        self.state.lock().unwrap_or_else(PoisonError::into_inner)
    }
}

impl fmt::Debug for CredentialCache {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.debug_struct("CredentialCache")
            .field("len", &self.len())
            .field("capacity", &self.capacity)
            .finish_non_exhaustive()
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::hash::{hash_password, Argon2Params};

    const FAST: Argon2Params = Argon2Params {
        memory_kib: 64,
        iterations: 1,
        parallelism: 1,
    };

    fn stored(password: &str) -> StoredHash {
        StoredHash::parse(&hash_password(password.as_bytes(), &FAST).unwrap()).unwrap()
    }

    #[test]
    fn hit_after_insert_only_with_the_same_password() {
        let cache = CredentialCache::new(10);
        let hash = stored("pw");
        assert!(!cache.hit("alice", b"pw", &hash));
        cache.insert("alice", b"pw", &hash);
        assert!(cache.hit("alice", b"pw", &hash));
        assert!(!cache.hit("alice", b"pw2", &hash));
        assert!(!cache.hit("alice", b"", &hash));
        assert!(!cache.hit("bob", b"pw", &hash));
    }

    #[test]
    fn miss_when_the_stored_hash_changes() {
        let cache = CredentialCache::new(10);
        let old = stored("pw");
        cache.insert("alice", b"pw", &old);
        // Same password re-hashed (new salt), e.g. after `passwd` or a
        // legacy-hash upgrade: the old tag no longer applies.
        let new = stored("pw");
        assert!(!cache.hit("alice", b"pw", &new));
        assert!(cache.hit("alice", b"pw", &old));
    }

    #[test]
    fn separate_caches_use_separate_keys() {
        let hash = stored("pw");
        let a = CredentialCache::new(1);
        let b = CredentialCache::new(1);
        assert_ne!(a.tag("u", b"pw", &hash), b.tag("u", b"pw", &hash));
    }

    #[test]
    fn bounded_evicting_the_oldest_insertion() {
        let cache = CredentialCache::new(2);
        let hash = stored("pw");
        cache.insert("a", b"pw", &hash);
        cache.insert("b", b"pw", &hash);
        cache.insert("c", b"pw", &hash);
        assert_eq!(cache.len(), 2);
        assert!(!cache.hit("a", b"pw", &hash));
        assert!(cache.hit("b", b"pw", &hash));
        assert!(cache.hit("c", b"pw", &hash));
        // Re-inserting an existing user evicts nobody.
        cache.insert("b", b"pw", &hash);
        assert_eq!(cache.len(), 2);
        assert!(cache.hit("c", b"pw", &hash));
        // ... and makes "c" the oldest.
        cache.insert("d", b"pw", &hash);
        assert!(!cache.hit("c", b"pw", &hash));
        assert!(cache.hit("b", b"pw", &hash));
    }

    #[test]
    fn remove_clear_and_zero_capacity() {
        let hash = stored("pw");
        let cache = CredentialCache::new(10);
        cache.insert("a", b"pw", &hash);
        cache.insert("b", b"pw", &hash);
        cache.remove("a");
        assert!(!cache.hit("a", b"pw", &hash));
        assert_eq!(cache.len(), 1);
        cache.clear();
        assert!(cache.is_empty());

        let disabled = CredentialCache::new(0);
        disabled.insert("a", b"pw", &hash);
        assert!(!disabled.hit("a", b"pw", &hash));
        assert_eq!(disabled.len(), 0);
    }

    #[test]
    fn debug_shows_no_tags() {
        let cache = CredentialCache::new(10);
        cache.insert("alice", b"pw", &stored("pw"));
        let debug = format!("{cache:?}");
        assert_eq!(debug, "CredentialCache { len: 1, capacity: 10, .. }");
    }

    #[test]
    fn is_send_and_sync() {
        fn assert_send_sync<T: Send + Sync>() {}
        assert_send_sync::<CredentialCache>();
    }
}

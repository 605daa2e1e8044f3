//! Rate budgets that outlive connections: declarations (`[fb] declarations_per_minute`)
//! and diagnostics (`[fb] diag_per_second`), one per device and the identity that
//! registers it (the verified username with a password file, else the peer's address).
//!
//! Why not per connection: a budget a connection owns starts full on every CONNECT, so a
//! client that reconnects gets a fresh one each time (issue 33 measured 91 declarations a
//! second that way against a limit of 60 a minute). Keyed by device as well as identity,
//! so that the devices behind one address (a gateway, a loopback test line) do not share
//! one budget; a client that invents device ids meets the registry's
//! `max_devices_per_identity` and this table's bound.
//!
//! Bounded: at most [`MAX_IDENTITIES`] identities have buckets of their own. When the
//! table is full, buckets that have filled up again (their identity idle long enough to
//! have its whole budget back, so forgetting them changes nothing) are dropped; if none
//! has, a new identity shares one overflow bucket with every other newcomer, so a flood
//! of addresses cannot grow the table or get fresh budgets.

use std::collections::HashMap;
use std::sync::{Mutex, PoisonError};
use std::time::Instant;

/// Identities with buckets of their own, per kind.
pub const MAX_IDENTITIES: usize = 10_000;

/// What a budget is for.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub enum Kind {
    Declarations,
    Diagnostics,
}

/// A token bucket: `rate` tokens a second, at most `burst` held.
#[derive(Debug)]
struct Bucket {
    tokens: f64,
    at: Instant,
}

impl Bucket {
    fn full(burst: f64, now: Instant) -> Bucket {
        Bucket {
            tokens: burst,
            at: now,
        }
    }

    fn refill(&mut self, rate: f64, burst: f64, now: Instant) {
        let elapsed = now.saturating_duration_since(self.at).as_secs_f64();
        self.tokens = (self.tokens + elapsed * rate).min(burst);
        self.at = now;
    }

    /// Takes a token, or says in how many seconds one will be there.
    fn take(&mut self, rate: f64, burst: f64, now: Instant) -> Result<(), f64> {
        self.refill(rate, burst, now);
        if self.tokens >= 1.0 {
            self.tokens -= 1.0;
            Ok(())
        } else {
            Err((1.0 - self.tokens) / rate)
        }
    }
}

/// Every identity's buckets, shared by the line's connections.
#[derive(Debug, Default)]
pub struct Budgets {
    buckets: Mutex<HashMap<(Kind, String), Bucket>>,
}

/// The key every newcomer shares once the table is full.
const OVERFLOW: &str = "";

impl Budgets {
    /// Takes one token of `identity`'s `kind` budget (`rate` a second, `burst` at most),
    /// or says in how many seconds one will be there.
    pub fn take(&self, kind: Kind, identity: &str, rate: f64, burst: f64) -> Result<(), f64> {
        let now = Instant::now();
        let mut buckets = self.buckets.lock().unwrap_or_else(PoisonError::into_inner);
        let key = (kind, identity.to_owned());
        if !buckets.contains_key(&key) && buckets.len() >= MAX_IDENTITIES {
            buckets.retain(|(k, _), b| {
                *k != kind || {
                    b.refill(rate, burst, now);
                    b.tokens < burst
                }
            });
        }
        let key = match buckets.contains_key(&key) || buckets.len() < MAX_IDENTITIES {
            true => key,
            false => (kind, OVERFLOW.to_owned()),
        };
        buckets
            .entry(key)
            .or_insert_with(|| Bucket::full(burst, now))
            .take(rate, burst, now)
    }

    /// Identities with buckets now (for tests).
    #[cfg(test)]
    fn len(&self) -> usize {
        self.buckets
            .lock()
            .unwrap_or_else(PoisonError::into_inner)
            .len()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn an_identitys_connections_share_one_budget() {
        let budgets = Budgets::default();
        for _ in 0..3 {
            assert!(budgets
                .take(Kind::Declarations, "user:a", 0.05, 3.0)
                .is_ok());
        }
        // A fourth declaration, from whichever connection: refused.
        assert!(budgets
            .take(Kind::Declarations, "user:a", 0.05, 3.0)
            .is_err());
        // Another identity, and another kind, are apart.
        assert!(budgets
            .take(Kind::Declarations, "user:b", 0.05, 3.0)
            .is_ok());
        assert!(budgets.take(Kind::Diagnostics, "user:a", 0.05, 3.0).is_ok());
    }

    #[test]
    fn a_flood_of_identities_shares_the_overflow_bucket() {
        let budgets = Budgets::default();
        for i in 0..MAX_IDENTITIES {
            let _ = budgets.take(Kind::Declarations, &format!("address:{i}"), 0.0001, 1.0);
        }
        assert_eq!(budgets.len(), MAX_IDENTITIES);
        // Full table, none refilled: newcomers share one bucket of one token.
        assert!(budgets
            .take(Kind::Declarations, "address:new-1", 0.0001, 1.0)
            .is_ok());
        assert!(budgets
            .take(Kind::Declarations, "address:new-2", 0.0001, 1.0)
            .is_err());
        assert_eq!(budgets.len(), MAX_IDENTITIES + 1);
    }
}

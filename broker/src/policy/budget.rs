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
//! Bounded: each kind holds at most its capacity of buckets: the registry's `[fb]
//! max_devices` (every registered device may have one) plus [`MAX_NEWCOMERS`], ~100 bytes
//! each. When a kind is full, buckets that have filled up again (their device idle long
//! enough to have its whole budget back, so forgetting them changes nothing) are dropped,
//! at most once a second; if none has, a newcomer shares one overflow bucket with every
//! other newcomer, so a flood of invented ids cannot grow the table or get fresh budgets.
//! Until 2026-11-29 both kinds shared one table of 10,000: a device's declaration and its
//! answer take a bucket of each, so from 5,000 devices on, new devices from one gateway
//! (or one loopback test line) shared the overflow bucket and 837 of 10,000 devices
//! declaring at once were refused as "rate limited" (`fbbus-loadtest compare fb`).

use std::collections::HashMap;
use std::sync::{Mutex, PoisonError};
use std::time::{Duration, Instant};

/// Buckets beyond the registry's `max_devices`, per kind: devices not registered (yet).
pub const MAX_NEWCOMERS: usize = 10_000;
/// Sweeps of a full table at most this often.
const SWEEP_EVERY: Duration = Duration::from_secs(1);

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

/// One kind's buckets.
#[derive(Debug, Default)]
struct Table {
    buckets: HashMap<String, Bucket>,
    /// When the full table was last swept.
    swept: Option<Instant>,
}

/// Every identity's buckets, shared by the line's connections.
#[derive(Debug)]
pub struct Budgets {
    /// Buckets per kind at most (besides the overflow one).
    capacity: usize,
    declarations: Mutex<Table>,
    diagnostics: Mutex<Table>,
}

/// The key every newcomer shares once the table is full.
const OVERFLOW: &str = "";

impl Budgets {
    /// Room for a bucket per kind for each of `max_devices` devices, and
    /// [`MAX_NEWCOMERS`] more.
    pub fn new(max_devices: usize) -> Budgets {
        Budgets {
            capacity: max_devices.saturating_add(MAX_NEWCOMERS),
            declarations: Mutex::default(),
            diagnostics: Mutex::default(),
        }
    }

    /// Takes one token of `identity`'s `kind` budget (`rate` a second, `burst` at most),
    /// or says in how many seconds one will be there.
    pub fn take(&self, kind: Kind, identity: &str, rate: f64, burst: f64) -> Result<(), f64> {
        let now = Instant::now();
        let table = match kind {
            Kind::Declarations => &self.declarations,
            Kind::Diagnostics => &self.diagnostics,
        };
        let mut table = table.lock().unwrap_or_else(PoisonError::into_inner);
        if let Some(bucket) = table.buckets.get_mut(identity) {
            return bucket.take(rate, burst, now);
        }
        let due = table
            .swept
            .is_none_or(|at| now.duration_since(at) >= SWEEP_EVERY);
        if table.buckets.len() >= self.capacity && due {
            table.swept = Some(now);
            table.buckets.retain(|_, b| {
                b.refill(rate, burst, now);
                b.tokens < burst
            });
        }
        let key = match table.buckets.len() < self.capacity {
            true => identity,
            false => OVERFLOW,
        };
        table
            .buckets
            .entry(key.to_owned())
            .or_insert_with(|| Bucket::full(burst, now))
            .take(rate, burst, now)
    }

    /// Buckets of `kind` now (for tests).
    #[cfg(test)]
    fn len(&self, kind: Kind) -> usize {
        let table = match kind {
            Kind::Declarations => &self.declarations,
            Kind::Diagnostics => &self.diagnostics,
        };
        table
            .lock()
            .unwrap_or_else(PoisonError::into_inner)
            .buckets
            .len()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn an_identitys_connections_share_one_budget() {
        let budgets = Budgets::new(10);
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
    fn every_device_of_a_full_registry_has_its_own_budgets() {
        // Each device declares once and is answered once: a bucket of each kind.
        let budgets = Budgets::new(20_000);
        for i in 0..20_000 {
            let key = format!("address:127.0.0.1/dev-{i}");
            assert!(budgets.take(Kind::Declarations, &key, 0.5, 30.0).is_ok());
            assert!(budgets.take(Kind::Diagnostics, &key, 10.0, 20.0).is_ok());
        }
        assert_eq!(budgets.len(Kind::Declarations), 20_000);
        assert_eq!(budgets.len(Kind::Diagnostics), 20_000);
    }

    #[test]
    fn a_flood_of_identities_shares_the_overflow_bucket() {
        let budgets = Budgets::new(0);
        for i in 0..MAX_NEWCOMERS {
            let _ = budgets.take(Kind::Declarations, &format!("address:{i}"), 0.0001, 1.0);
        }
        assert_eq!(budgets.len(Kind::Declarations), MAX_NEWCOMERS);
        // Full table, none refilled: newcomers share one bucket of one token.
        assert!(budgets
            .take(Kind::Declarations, "address:new-1", 0.0001, 1.0)
            .is_ok());
        assert!(budgets
            .take(Kind::Declarations, "address:new-2", 0.0001, 1.0)
            .is_err());
        assert_eq!(budgets.len(Kind::Declarations), MAX_NEWCOMERS + 1);
        // The other kind is a table of its own.
        assert!(budgets
            .take(Kind::Diagnostics, "address:new-2", 0.0001, 1.0)
            .is_ok());
    }
}

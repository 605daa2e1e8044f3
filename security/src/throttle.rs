//! Login throttling with exponential backoff, per client address (or per user, or for a
//! whole endpoint: [`ThrottleKey`]).
//!
//! Password hashing makes each guess expensive for the attacker, but also
//! for us: without a throttle, one client looping over passwords keeps a
//! core busy with argon2. So after a few failures in a row, an address is
//! blocked for a time that doubles with every further failure.
//!
//! The formula, with `n` the number of consecutive failures so far:
//!
//! ```text
//! block(n) = 0                                               if n <= free_failures
//! block(n) = min(base_delay * 2^(n - free_failures - 1), max_delay)  otherwise
//! ```
//!
//! With the defaults (5 free failures, 1 s base, 60 s max) failures 1–5 are
//! free and failures 6, 7, 8, … block for 1, 2, 4, 8, 16, 32, 60, 60, … s.
//! A misconfigured device retrying once per second is therefore slowed to
//! one attempt a minute rather than locked out for good, and it recovers by
//! itself once the password is fixed. A success clears the address; an
//! address with no failure for `forget_after` starts again from zero.
//!
//! IPv4-mapped IPv6 addresses (`::ffff:a.b.c.d`, as seen on dual-stack
//! sockets) count as the IPv4 address. Other IPv6 addresses are tracked
//! individually, not per /64, because on a plant network a /64 is often
//! one LAN segment full of devices.
//!
//! The table holds at most `max_tracked` addresses, so an attacker rotating
//! through addresses cannot grow it without bound. When it is full, entries
//! idle for `forget_after` (and no longer blocked) are dropped first, then
//! the one whose last failure is oldest.
//!
//! The same rule can count failures by another key ([`ThrottleKey`]): per user name
//! (guesses at one account from many addresses) or for a whole endpoint (`()`: every
//! guess, whoever and whatever it targets).
//!
//! The caller passes the current time in, so tests need no sleeping.

use std::collections::HashMap;
use std::hash::Hash;
use std::net::IpAddr;
use std::sync::{Mutex, MutexGuard, PoisonError};
use std::time::{Duration, Instant};

/// Tuning for [`LoginThrottle`]; see the module docs for the formula.
#[derive(Debug, Clone)]
pub struct ThrottleConfig {
    /// Consecutive failures allowed before blocking starts.
    pub free_failures: u32,
    /// Block after the first non-free failure; doubles from there.
    pub base_delay: Duration,
    /// Upper bound on a single block.
    pub max_delay: Duration,
    /// An address with no failure for this long starts again from zero.
    pub forget_after: Duration,
    /// Most addresses remembered at once; 0 disables throttling.
    pub max_tracked: usize,
}

impl Default for ThrottleConfig {
    fn default() -> Self {
        ThrottleConfig {
            free_failures: 5,
            base_delay: Duration::from_secs(1),
            max_delay: Duration::from_secs(60),
            forget_after: Duration::from_secs(10 * 60),
            max_tracked: 100_000,
        }
    }
}

impl ThrottleConfig {
    /// How long the `failures`-th consecutive failure blocks for.
    fn block_for(&self, failures: u32) -> Duration {
        if failures <= self.free_failures {
            return Duration::ZERO;
        }
        // Beyond 2^31 the delay is certainly capped anyway.
        let doublings = (failures - self.free_failures - 1).min(31);
        self.base_delay
            .saturating_mul(1u32 << doublings)
            .min(self.max_delay)
    }
}

/// What failures are counted by. An address counts as its canonical form (an
/// IPv4-mapped IPv6 address as the IPv4 address).
pub trait ThrottleKey: Hash + Eq + Clone {
    fn canonical(self) -> Self;
}

impl ThrottleKey for IpAddr {
    fn canonical(self) -> IpAddr {
        self.to_canonical()
    }
}

/// A user name.
impl ThrottleKey for String {
    fn canonical(self) -> String {
        self
    }
}

/// The whole endpoint: one count for every failure.
impl ThrottleKey for () {
    fn canonical(self) {}
}

/// Tracks failed logins per client address (or per another [`ThrottleKey`]). Shared
/// between connection tasks (`Send + Sync`).
#[derive(Debug)]
pub struct LoginThrottle<K: ThrottleKey = IpAddr> {
    config: ThrottleConfig,
    addresses: Mutex<HashMap<K, Failures>>,
}

#[derive(Debug, Clone, Copy)]
struct Failures {
    consecutive: u32,
    last: Instant,
    /// Blocked until `last + blocked_for`.
    blocked_for: Duration,
}

impl Failures {
    fn remaining_block(&self, now: Instant) -> Option<Duration> {
        let since = now.saturating_duration_since(self.last);
        (since < self.blocked_for).then(|| self.blocked_for - since)
    }

    fn is_forgotten(&self, now: Instant, forget_after: Duration) -> bool {
        now.saturating_duration_since(self.last) >= forget_after
            && self.remaining_block(now).is_none()
    }
}

impl<K: ThrottleKey> LoginThrottle<K> {
    pub fn new(config: ThrottleConfig) -> LoginThrottle<K> {
        LoginThrottle {
            config,
            addresses: Mutex::new(HashMap::new()),
        }
    }

    /// `Err(retry_after)` while `addr` is blocked. Call before verifying a
    /// password, and refuse the login without verifying if blocked.
    pub fn check(&self, addr: K, now: Instant) -> Result<(), Duration> {
        let addr = addr.canonical();
        let mut addresses = self.lock();
        let Some(failures) = addresses.get(&addr) else {
            return Ok(());
        };
        if let Some(remaining) = failures.remaining_block(now) {
            return Err(remaining);
        }
        if failures.is_forgotten(now, self.config.forget_after) {
            addresses.remove(&addr);
        }
        Ok(())
    }

    /// Records a wrong password from `addr`. Returns how long the address
    /// is now blocked for, if this failure blocks it.
    pub fn record_failure(&self, addr: K, now: Instant) -> Option<Duration> {
        if self.config.max_tracked == 0 {
            return None;
        }
        let addr = addr.canonical();
        let mut addresses = self.lock();
        if !addresses.contains_key(&addr) && addresses.len() >= self.config.max_tracked {
            self.make_room(&mut addresses, now);
        }
        let failures = addresses.entry(addr).or_insert(Failures {
            consecutive: 0,
            last: now,
            blocked_for: Duration::ZERO,
        });
        if failures.is_forgotten(now, self.config.forget_after) {
            failures.consecutive = 0;
        }
        failures.consecutive = failures.consecutive.saturating_add(1);
        failures.last = now;
        failures.blocked_for = self.config.block_for(failures.consecutive);
        (!failures.blocked_for.is_zero()).then_some(failures.blocked_for)
    }

    /// Records a successful login from `addr`, clearing its failures.
    pub fn record_success(&self, addr: K) {
        self.lock().remove(&addr.canonical());
    }

    /// Number of addresses currently remembered (for metrics).
    pub fn tracked(&self) -> usize {
        self.lock().len()
    }

    /// Frees at least one slot: forgotten entries first, then the oldest.
    fn make_room(&self, addresses: &mut HashMap<K, Failures>, now: Instant) {
        addresses.retain(|_, failures| !failures.is_forgotten(now, self.config.forget_after));
        while addresses.len() >= self.config.max_tracked {
            let Some(oldest) = addresses
                .iter()
                .min_by_key(|(_, failures)| failures.last)
                .map(|(addr, _)| addr.clone())
            else {
                return;
            };
            addresses.remove(&oldest);
        }
    }

    fn lock(&self) -> MutexGuard<'_, HashMap<K, Failures>> {
        // The map is valid after any panic mid-update, so poisoning is moot.
        self.addresses
            .lock()
            .unwrap_or_else(PoisonError::into_inner)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::net::{Ipv4Addr, Ipv6Addr};

    const A: IpAddr = IpAddr::V4(Ipv4Addr::new(10, 0, 0, 1));
    const B: IpAddr = IpAddr::V4(Ipv4Addr::new(10, 0, 0, 2));

    fn secs(s: u64) -> Duration {
        Duration::from_secs(s)
    }

    #[test]
    fn backoff_sequence_with_defaults() {
        let throttle = LoginThrottle::new(ThrottleConfig::default());
        let now = Instant::now();
        let blocks: Vec<Option<u64>> = (0..14)
            .map(|_| throttle.record_failure(A, now).map(|d| d.as_secs()))
            .collect();
        let expected = [
            None,
            None,
            None,
            None,
            None,
            Some(1),
            Some(2),
            Some(4),
            Some(8),
            Some(16),
            Some(32),
            Some(60),
            Some(60),
            Some(60),
        ];
        assert_eq!(blocks, expected);
    }

    #[test]
    fn formula_saturates_for_huge_counts() {
        let config = ThrottleConfig::default();
        assert_eq!(config.block_for(5), Duration::ZERO);
        assert_eq!(config.block_for(6), secs(1));
        assert_eq!(config.block_for(u32::MAX), secs(60));
        let uncapped = ThrottleConfig {
            max_delay: Duration::MAX,
            ..ThrottleConfig::default()
        };
        assert_eq!(uncapped.block_for(6 + 31), secs(1 << 31));
        assert_eq!(uncapped.block_for(u32::MAX), secs(1 << 31));
    }

    #[test]
    fn check_reports_the_remaining_block() {
        let throttle = LoginThrottle::new(ThrottleConfig::default());
        let t0 = Instant::now();
        for _ in 0..5 {
            throttle.record_failure(A, t0);
            assert_eq!(throttle.check(A, t0), Ok(()));
        }
        assert_eq!(throttle.record_failure(A, t0), Some(secs(1)));
        assert_eq!(throttle.check(A, t0), Err(secs(1)));
        assert_eq!(
            throttle.check(A, t0 + Duration::from_millis(400)),
            Err(Duration::from_millis(600))
        );
        assert_eq!(throttle.check(A, t0 + secs(1)), Ok(()));
        // Other addresses are unaffected.
        assert_eq!(throttle.check(B, t0), Ok(()));

        let t1 = t0 + secs(1);
        assert_eq!(throttle.record_failure(A, t1), Some(secs(2)));
        assert_eq!(throttle.check(A, t1 + secs(1)), Err(secs(1)));
        assert_eq!(throttle.check(A, t1 + secs(2)), Ok(()));
    }

    #[test]
    fn success_resets() {
        let throttle = LoginThrottle::new(ThrottleConfig::default());
        let now = Instant::now();
        for _ in 0..7 {
            throttle.record_failure(A, now);
        }
        assert!(throttle.check(A, now).is_err());
        throttle.record_success(A);
        assert_eq!(throttle.check(A, now), Ok(()));
        assert_eq!(throttle.tracked(), 0);
        for _ in 0..5 {
            assert_eq!(throttle.record_failure(A, now), None);
        }
        assert_eq!(throttle.record_failure(A, now), Some(secs(1)));
    }

    #[test]
    fn failures_are_forgotten_after_idle_time() {
        let throttle = LoginThrottle::new(ThrottleConfig::default());
        let t0 = Instant::now();
        for _ in 0..8 {
            throttle.record_failure(A, t0);
        }
        let later = t0 + secs(10 * 60);
        assert_eq!(throttle.check(A, later), Ok(()));
        assert_eq!(throttle.tracked(), 0);

        for _ in 0..8 {
            throttle.record_failure(B, t0);
        }
        // Without a `check` in between, the next failure also starts over.
        assert_eq!(throttle.record_failure(B, later), None);
    }

    #[test]
    fn ipv4_mapped_ipv6_counts_as_ipv4() {
        let throttle = LoginThrottle::new(ThrottleConfig {
            free_failures: 0,
            ..ThrottleConfig::default()
        });
        let now = Instant::now();
        let mapped = IpAddr::V6(Ipv4Addr::new(10, 0, 0, 1).to_ipv6_mapped());
        throttle.record_failure(mapped, now);
        assert!(throttle.check(A, now).is_err());
        throttle.record_success(A);
        assert!(throttle.check(mapped, now).is_ok());

        let v6 = IpAddr::V6(Ipv6Addr::new(0xfd00, 0, 0, 0, 0, 0, 0, 1));
        let neighbour = IpAddr::V6(Ipv6Addr::new(0xfd00, 0, 0, 0, 0, 0, 0, 2));
        throttle.record_failure(v6, now);
        assert!(throttle.check(v6, now).is_err());
        assert!(throttle.check(neighbour, now).is_ok());
    }

    #[test]
    fn tracked_addresses_are_bounded_oldest_first() {
        let throttle = LoginThrottle::new(ThrottleConfig {
            max_tracked: 3,
            free_failures: 0,
            base_delay: secs(60),
            ..ThrottleConfig::default()
        });
        let t0 = Instant::now();
        let addr = |i: u8| IpAddr::V4(Ipv4Addr::new(192, 168, 0, i));
        for i in 0..3 {
            throttle.record_failure(addr(i), t0 + secs(u64::from(i)));
        }
        assert_eq!(throttle.tracked(), 3);
        throttle.record_failure(addr(3), t0 + secs(3));
        assert_eq!(throttle.tracked(), 3);
        // The oldest (address 0) was dropped; the others are still blocked.
        assert!(throttle.check(addr(0), t0 + secs(3)).is_ok());
        assert!(throttle.check(addr(1), t0 + secs(3)).is_err());
        assert!(throttle.check(addr(3), t0 + secs(3)).is_err());
        // A known address never evicts anyone.
        throttle.record_failure(addr(3), t0 + secs(4));
        assert_eq!(throttle.tracked(), 3);
    }

    #[test]
    fn idle_entries_are_pruned_before_the_oldest() {
        let throttle = LoginThrottle::new(ThrottleConfig {
            max_tracked: 3,
            ..ThrottleConfig::default()
        });
        let t0 = Instant::now();
        let addr = |i: u8| IpAddr::V4(Ipv4Addr::new(192, 168, 0, i));
        throttle.record_failure(addr(0), t0);
        throttle.record_failure(addr(1), t0 + secs(1));
        throttle.record_failure(addr(2), t0 + secs(11 * 60));
        throttle.record_failure(addr(3), t0 + secs(11 * 60));
        // 0 and 1 were idle for over 10 minutes and both went.
        assert_eq!(throttle.tracked(), 2);
    }

    #[test]
    fn zero_capacity_disables_throttling() {
        let throttle = LoginThrottle::new(ThrottleConfig {
            max_tracked: 0,
            ..ThrottleConfig::default()
        });
        let now = Instant::now();
        for _ in 0..20 {
            assert_eq!(throttle.record_failure(A, now), None);
        }
        assert_eq!(throttle.check(A, now), Ok(()));
    }

    #[test]
    fn is_send_and_sync() {
        fn assert_send_sync<T: Send + Sync>() {}
        assert_send_sync::<LoginThrottle>();
    }
}

//! One clock for publisher and subscriber: this process's.
//!
//! Latency is "delivered at" minus "published at". Both ends run in this process, so
//! both read this clock: wall-clock microseconds since 1970 (the fbbus event contract's
//! `ts` unit) taken once at start, advanced by the monotonic clock. It cannot jump
//! when NTP adjusts the system clock during a run, and two processes are never
//! compared. (To measure across machines, run the harness where both clients can be
//! placed in one process: e.g. publish to line A and subscribe at line B from one host.)

use std::sync::OnceLock;
use std::time::{Instant, SystemTime, UNIX_EPOCH};

fn epoch() -> &'static (Instant, u64) {
    static EPOCH: OnceLock<(Instant, u64)> = OnceLock::new();
    EPOCH.get_or_init(|| {
        let wall = SystemTime::now()
            .duration_since(UNIX_EPOCH)
            .map(|d| d.as_micros() as u64)
            .unwrap_or(0);
        (Instant::now(), wall)
    })
}

/// Microseconds since 1970, monotonic within this process.
pub fn now_us() -> u64 {
    at_us(Instant::now())
}

/// [`now_us`] of an `Instant` (a schedule's due time, say).
pub fn at_us(instant: Instant) -> u64 {
    let (start, wall) = *epoch();
    wall + instant.saturating_duration_since(start).as_micros() as u64
}

/// Milliseconds since 1970 (JTL timestamps).
pub fn now_ms() -> u64 {
    now_us() / 1000
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn never_goes_backwards_and_tracks_the_wall_clock() {
        let a = now_us();
        let b = now_us();
        assert!(b >= a);
        let wall = SystemTime::now()
            .duration_since(UNIX_EPOCH)
            .unwrap()
            .as_micros() as u64;
        // Started within this test: at most a few seconds apart.
        assert!(wall.abs_diff(b) < 5_000_000, "{wall} vs {b}");
    }
}

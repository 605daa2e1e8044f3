//! Connections that have not completed their CONNECT yet, counted per source address.
//!
//! Until a client has sent CONNECT and logged in, nobody knows who it is, yet its socket
//! holds one of `[broker] max_connections` slots for up to `connect_timeout_ms`. One
//! stranger that opens thousands of sockets, sends half a CONNECT on each and reopens
//! every one the broker closes would hold every slot: devices already connected go on,
//! but a device that drops can never come back while it lasts (issue 33 measured 16 of
//! 18 real CONNECTs refused). So each source address may have at most
//! `[broker] max_pending_per_address` connections before CONNECT; one more is closed at
//! accept, counted in `fbbus_connects_refused_total{reason="pending_per_address"}` and
//! logged at most once a minute. A device reconnects through one socket at a time, so
//! the bound only meets floods; devices behind one NAT address that all reconnect at once
//! (after a power cut) are let in that many at a time and retry for the rest.
//!
//! The admin endpoint counts its connections per address with the same table (`admin`:
//! a quarter of `[admin] max_connections` each), for the same reason: its probes.
//!
//! IPv6 addresses count one by one (like the login throttle): on a plant network a /64 is
//! often one LAN segment full of devices. The table holds only addresses with a pending
//! connection, so it is bounded by `max_connections`.

use std::collections::HashMap;
use std::net::IpAddr;
use std::sync::{Arc, Mutex, PoisonError};

/// The per-address counts, shared by every listener.
#[derive(Debug)]
pub struct Pending {
    max_per_address: usize,
    counts: Mutex<HashMap<IpAddr, usize>>,
}

impl Pending {
    pub fn new(max_per_address: usize) -> Arc<Pending> {
        Arc::new(Pending {
            max_per_address,
            counts: Mutex::default(),
        })
    }

    /// A connection from `peer` was accepted: its place until it completes CONNECT (the
    /// guard is dropped), or None if `peer` has `max_per_address` places already.
    pub fn enter(self: &Arc<Self>, peer: IpAddr) -> Option<PendingGuard> {
        let peer = peer.to_canonical();
        let mut counts = self.counts.lock().unwrap_or_else(PoisonError::into_inner);
        let count = counts.entry(peer).or_insert(0);
        if *count >= self.max_per_address {
            return None;
        }
        *count += 1;
        Some(PendingGuard {
            pending: Arc::clone(self),
            peer,
        })
    }

    /// Connections of `peer` before CONNECT now.
    #[cfg(test)]
    fn of(&self, peer: IpAddr) -> usize {
        let counts = self.counts.lock().unwrap_or_else(PoisonError::into_inner);
        counts.get(&peer.to_canonical()).copied().unwrap_or(0)
    }
}

/// One connection's place before CONNECT; given back when dropped.
#[derive(Debug)]
pub struct PendingGuard {
    pending: Arc<Pending>,
    peer: IpAddr,
}

impl Drop for PendingGuard {
    fn drop(&mut self) {
        let mut counts = self
            .pending
            .counts
            .lock()
            .unwrap_or_else(PoisonError::into_inner);
        if let Some(count) = counts.get_mut(&self.peer) {
            *count = count.saturating_sub(1);
            if *count == 0 {
                counts.remove(&self.peer);
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn an_address_has_its_places_and_gets_them_back() {
        let pending = Pending::new(2);
        let a: IpAddr = "10.0.0.1".parse().unwrap();
        let mapped: IpAddr = "::ffff:10.0.0.1".parse().unwrap();
        let b: IpAddr = "10.0.0.2".parse().unwrap();
        let first = pending.enter(a).expect("first");
        let second = pending.enter(mapped).expect("second, the same address");
        assert!(pending.enter(a).is_none());
        assert!(pending.enter(b).is_some(), "another address has its own");
        drop(first);
        assert_eq!(pending.of(a), 1);
        assert!(pending.enter(a).is_some());
        drop(second);
        assert_eq!(pending.of(b), 0, "a dropped guard gives its place back");
    }
}

//! Reading what the router delivers to one of the broker's own links, a batch at a time.
//!
//! The router delivers in bursts, and a link's receiver hands notifications over one at a
//! time. A reader that woke for the first of a burst takes every one already queued
//! behind it without waiting ([`take_batch`]), handles them together (one lock, one
//! acknowledgement write), and only then tells the router it may go on: when the router
//! found the link's queue full it paused the link (`Unschedule`), and the link stays
//! paused until it is woken ([`Paused::resume`]). Forgetting that wake-up stalls the link
//! for good, which is why there is one place that does it.
//!
//! Three readers share it: the readiness probe (`health`), the bus export
//! (`bridge::export`) and the console's activity (`console::activity`). The first
//! notification is awaited by the caller (`LinkRx::next`, often in a `select!`, where it
//! is cancel-safe); what follows it here never waits.

use std::time::Instant;

use rumqttd::local::{LinkError, LinkRx};
use rumqttd::{Forward, Notification};

/// The router dropped the link: it is gone, or linked the client id again.
#[derive(Debug, thiserror::Error)]
#[error("the router closed the link")]
pub struct LinkClosed;

/// Whether the router paused the link during a batch; it must be resumed once the batch
/// is handled.
#[must_use = "a paused link stays paused until it is resumed"]
#[derive(Debug)]
pub struct Paused(bool);

impl Paused {
    /// Wakes the link if the router paused it.
    pub async fn resume(self, rx: &LinkRx) -> Result<(), LinkClosed> {
        if self.0 {
            rx.wake().await.map_err(|_| LinkClosed)?;
        }
        Ok(())
    }
}

/// Takes `first` (the notification the caller awaited) and every notification already
/// queued behind it, without waiting, handing each delivered publication to `forward` in
/// order; acknowledgements and the like are passed over. Says whether the link was
/// paused.
pub fn take_batch(
    rx: &mut LinkRx,
    first: Option<Notification>,
    mut forward: impl FnMut(Forward),
) -> Result<Paused, LinkClosed> {
    let mut paused = false;
    let mut next = first;
    loop {
        match next {
            Some(Notification::Forward(f)) => forward(f),
            Some(Notification::Unschedule) => paused = true,
            _ => {}
        }
        next = match rx.recv_deadline(Instant::now()) {
            Ok(n) => n,
            Err(LinkError::RecvTimeout(_)) => return Ok(Paused(paused)),
            Err(_) => return Err(LinkClosed),
        };
    }
}

/// Reads a link whose deliveries nobody waits for (the router's acknowledgements of the
/// broker's own QoS 1 publications) until the router closes it, keeping it awake.
pub async fn discard(mut rx: LinkRx) {
    while let Ok(first) = rx.next().await {
        let Ok(paused) = take_batch(&mut rx, first, drop) else {
            return;
        };
        if paused.resume(&rx).await.is_err() {
            return;
        }
    }
}

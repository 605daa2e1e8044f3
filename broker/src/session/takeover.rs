//! A takeover lets the old connection finish reading first.
//!
//! A device that publishes, disconnects and is back at once with the same client id (a
//! `mosquitto_pub -i` in a shell loop, a runtime that restarts) has its last packets in the
//! broker's socket when its next CONNECT arrives. rumqttd's router drops the old link as
//! soon as the new one links (MQTT session takeover), and whatever the old connection had
//! not read by then was lost: 303 and 332 of 400 such rounds in `tests/fb_sessions.rs`,
//! where the old connection's task had not run yet; the README's try-it lost a value this
//! way once in CI.
//!
//! So a new connection whose client id is still connected does not link at once. It asks
//! the old connection, through the old link's [`Nudge`] (the wake-up the old connection
//! waits on anyway: no memory per connection), to read what its socket holds now and route
//! it; it links once the old connection said so or ended, at most [`FINISH_WAIT`]. An old
//! connection that waits for its client answers at once (an empty read); one busy in a
//! write to a client that does not read, up to `slow_consumer_timeout_ms`, is not waited
//! for beyond [`FINISH_WAIT`]: counted in `fbbus_takeovers_unfinished_total`, and what it
//! had not read may be lost as before. What the old connection reads is bounded by
//! [`FINISH_READS`] reads, so a publisher that never stops cannot hold it.
//!
//! Routed first, the old connection's packets reach the router before the new link, in
//! the order the client sent them; its DISCONNECT, if it sent one, ends it as a clean
//! disconnect (no will), as it would have without the new connection.

use std::collections::HashMap;
use std::sync::{Mutex, PoisonError};
use std::time::Duration;

use rumqttd::local::Nudge;
use tokio::sync::oneshot;

/// How long a new connection waits for its client id's old connection to finish reading.
pub const FINISH_WAIT: Duration = Duration::from_millis(200);

/// Socket reads the old connection makes for a takeover at most (each up to the read
/// buffer's room, 4 KiB and more).
pub const FINISH_READS: usize = 16;

/// New connections waiting for an old connection to finish, by the old one's session
/// number. At most one entry per connection in its login (`max_connections`), removed
/// when it goes on.
#[derive(Default)]
pub struct Takeovers {
    waiting: Mutex<HashMap<u64, oneshot::Sender<()>>>,
}

/// Whether the old connection finished before the new one linked.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Finished {
    /// It read and routed what its socket held, or ended.
    InTime,
    /// It did not answer within [`FINISH_WAIT`].
    TimedOut,
}

impl Takeovers {
    fn waiting(&self) -> std::sync::MutexGuard<'_, HashMap<u64, oneshot::Sender<()>>> {
        self.waiting.lock().unwrap_or_else(PoisonError::into_inner)
    }

    /// Asks the connection `old` (through `nudge`) to read and route what its client sent,
    /// and waits until it did or ended, at most [`FINISH_WAIT`].
    pub async fn finish(&self, old: u64, nudge: &Nudge) -> Finished {
        let (told, done) = oneshot::channel();
        self.waiting().insert(old, told);
        nudge.nudge();
        // A dropped sender (the old connection ended) also means it is done.
        let in_time = tokio::time::timeout(FINISH_WAIT, done).await.is_ok();
        self.waiting().remove(&old);
        if in_time {
            Finished::InTime
        } else {
            Finished::TimedOut
        }
    }

    /// The connection `session` read and routed what its client had sent (or is ending):
    /// a newer connection waiting for that goes on.
    pub fn finished(&self, session: u64) {
        if let Some(told) = self.waiting().remove(&session) {
            let _ = told.send(());
        }
    }

    /// Connections waiting now.
    #[cfg(test)]
    fn len(&self) -> usize {
        self.waiting().len()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A link of a real router, and its nudge.
    async fn nudge_of_a_link() -> (Nudge, rumqttd::local::LinkRx) {
        let settings = crate::config::BrokerSection::default().router();
        let metrics = std::sync::Arc::new(crate::metrics::Metrics::new());
        let router =
            crate::router::RouterHandle::spawn(&settings, metrics, &crate::health::Health::new());
        let (_tx, rx, _ack) = router.link("old", true, 0).await.unwrap();
        (rx.nudge(), rx)
    }

    #[tokio::test]
    async fn the_new_connection_goes_on_once_the_old_one_finished() {
        let takeovers = std::sync::Arc::new(Takeovers::default());
        let (nudge, mut old) = nudge_of_a_link().await;
        let answering = std::sync::Arc::clone(&takeovers);
        tokio::spawn(async move {
            // The old connection, waiting for its router, is woken and sees why.
            old.wait().await.unwrap();
            assert!(old.nudged());
            assert!(!old.nudged(), "taken once");
            answering.finished(7);
        });
        assert_eq!(takeovers.finish(7, &nudge).await, Finished::InTime);
        assert_eq!(takeovers.len(), 0);
    }

    #[tokio::test]
    async fn an_old_connection_that_does_not_answer_is_not_waited_for_long() {
        let takeovers = Takeovers::default();
        let (nudge, _old) = nudge_of_a_link().await;
        let started = tokio::time::Instant::now();
        assert_eq!(takeovers.finish(7, &nudge).await, Finished::TimedOut);
        assert!(started.elapsed() >= FINISH_WAIT);
        assert_eq!(takeovers.len(), 0, "nothing left behind");
        // Finishing late, or a session nobody waits for, changes nothing.
        takeovers.finished(7);
        takeovers.finished(8);
        assert_eq!(takeovers.len(), 0);
    }
}

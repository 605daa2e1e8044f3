//! fbbus: how the router tells a link that its buffer has something: one flag and one
//! waiter, not a channel.
//!
//! Upstream gave every connection a flume channel of 200 `()` tokens for this. Every idle
//! connection then held the channel (about 150 bytes), the queue of its waiters and, while
//! it waited, a waiter allocated anew on every wait: about 280 bytes of the 4 KB an idle
//! connection costs, and an allocation per wake-up on the delivery path. A token per wake
//! also made a link that had already taken the whole buffer wake again for each token the
//! router had sent meanwhile, to find nothing. The link only needs to know *that* there is
//! something, and whether the router dropped it: a flag, the waiting task's waker (or a
//! blocked thread), and "closed" when the router's side goes away.
//!
//! Order: the router fills the buffer, then [`WakeTx::wake`]; the link clears the flag,
//! then takes the buffer. A wake that lands between the two makes one empty wake-up
//! later, never a lost one.
//!
//! A [`Nudge`] wakes the link from outside the router, with nothing in its buffer and a
//! flag of its own: fbbus asks a connection that is about to be taken over to read what
//! its client sent first (`session::takeover`), through the wait the link does anyway.

use std::future::poll_fn;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::Arc;
use std::task::{Poll, Waker};
use std::time::Instant;

use flume::{RecvError, RecvTimeoutError};
use parking_lot::{Condvar, Mutex};

/// Makes the router's side and the link's side of one connection's wake-up.
pub(crate) fn wakeup() -> (WakeTx, WakeRx) {
    let shared = Arc::new(Shared {
        state: Mutex::new(State {
            woken: false,
            closed: false,
            waker: None,
        }),
        blocked: Condvar::new(),
        nudged: AtomicBool::new(false),
    });
    (
        WakeTx {
            shared: Arc::clone(&shared),
        },
        WakeRx { shared },
    )
}

struct Shared {
    state: Mutex<State>,
    /// A thread blocked in [`WakeRx::recv`] or [`WakeRx::recv_deadline`].
    blocked: Condvar,
    /// A [`Nudge`] came and the link has not taken it yet.
    nudged: AtomicBool,
}

struct State {
    woken: bool,
    /// The router dropped its side: the connection is gone from the router.
    closed: bool,
    /// The task waiting in [`WakeRx::recv_async`].
    waker: Option<Waker>,
}

/// The router's side, in the connection's `Outgoing`. Dropping it closes the link.
pub(crate) struct WakeTx {
    shared: Arc<Shared>,
}

impl std::fmt::Debug for WakeTx {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str("WakeTx")
    }
}

impl WakeTx {
    /// The link's buffer has something new.
    pub(crate) fn wake(&self) {
        self.shared.wake();
    }
}

impl Shared {
    fn wake(&self) {
        let waker = {
            let mut state = self.state.lock();
            state.woken = true;
            state.waker.take()
        };
        if let Some(waker) = waker {
            waker.wake();
        }
        self.blocked.notify_one();
    }
}

/// Wakes a link without the router, flagged so the link can tell
/// ([`crate::local::LinkRx::nudged`]). Holding one keeps nothing of the connection alive
/// in the router.
#[derive(Clone)]
pub struct Nudge {
    shared: Arc<Shared>,
}

impl std::fmt::Debug for Nudge {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str("Nudge")
    }
}

impl Nudge {
    pub fn nudge(&self) {
        self.shared.nudged.store(true, Ordering::Release);
        self.shared.wake();
    }
}

impl Drop for WakeTx {
    fn drop(&mut self) {
        let waker = {
            let mut state = self.shared.state.lock();
            state.closed = true;
            state.waker.take()
        };
        if let Some(waker) = waker {
            waker.wake();
        }
        self.shared.blocked.notify_all();
    }
}

/// The link's side. A wake-up the router sent is returned before the close that followed
/// it, so the link reads what the router left in its buffer (a Disconnect) first.
pub(crate) struct WakeRx {
    shared: Arc<Shared>,
}

impl std::fmt::Debug for WakeRx {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str("WakeRx")
    }
}

impl WakeRx {
    /// A handle that wakes this link flagged as nudged.
    pub(crate) fn nudge(&self) -> Nudge {
        Nudge {
            shared: Arc::clone(&self.shared),
        }
    }

    /// Takes the nudge flag: true once per [`Nudge::nudge`] (several before the link looked
    /// count once). A relaxed load first, so the usual wake-up writes nothing.
    pub(crate) fn take_nudge(&self) -> bool {
        self.shared.nudged.load(Ordering::Relaxed)
            && self.shared.nudged.swap(false, Ordering::Acquire)
    }

    /// Waits for a wake-up; `Err` once the router dropped its side.
    pub(crate) async fn recv_async(&self) -> Result<(), RecvError> {
        poll_fn(|cx| {
            let mut state = self.shared.state.lock();
            if std::mem::take(&mut state.woken) {
                return Poll::Ready(Ok(()));
            }
            if state.closed {
                return Poll::Ready(Err(RecvError::Disconnected));
            }
            match &mut state.waker {
                Some(waker) if waker.will_wake(cx.waker()) => {}
                slot => *slot = Some(cx.waker().clone()),
            }
            Poll::Pending
        })
        .await
    }

    /// Blocks the thread until a wake-up; `Err` once the router dropped its side.
    pub(crate) fn recv(&self) -> Result<(), RecvError> {
        let mut state = self.shared.state.lock();
        loop {
            if std::mem::take(&mut state.woken) {
                return Ok(());
            }
            if state.closed {
                return Err(RecvError::Disconnected);
            }
            self.shared.blocked.wait(&mut state);
        }
    }

    /// [`WakeRx::recv`] until `deadline` (a deadline already past: a look without waiting).
    pub(crate) fn recv_deadline(&self, deadline: Instant) -> Result<(), RecvTimeoutError> {
        let mut state = self.shared.state.lock();
        loop {
            if std::mem::take(&mut state.woken) {
                return Ok(());
            }
            if state.closed {
                return Err(RecvTimeoutError::Disconnected);
            }
            if self
                .shared
                .blocked
                .wait_until(&mut state, deadline)
                .timed_out()
            {
                return match (std::mem::take(&mut state.woken), state.closed) {
                    (true, _) => Ok(()),
                    (false, true) => Err(RecvTimeoutError::Disconnected),
                    (false, false) => Err(RecvTimeoutError::Timeout),
                };
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::time::Duration;

    #[test]
    fn wake_ups_coalesce_and_the_close_comes_after_them() {
        let (tx, rx) = wakeup();
        let now = Instant::now;
        assert_eq!(rx.recv_deadline(now()), Err(RecvTimeoutError::Timeout));
        tx.wake();
        tx.wake();
        assert_eq!(rx.recv_deadline(now()), Ok(()));
        assert_eq!(rx.recv_deadline(now()), Err(RecvTimeoutError::Timeout));
        tx.wake();
        drop(tx);
        assert_eq!(rx.recv(), Ok(()), "the wake-up before the close first");
        assert_eq!(rx.recv(), Err(RecvError::Disconnected));
        assert_eq!(rx.recv_deadline(now()), Err(RecvTimeoutError::Disconnected));
    }

    #[test]
    fn a_nudge_wakes_flagged_once_and_keeps_nothing_open() {
        let (tx, rx) = wakeup();
        let nudge = rx.nudge();
        let now = Instant::now;
        tx.wake();
        assert_eq!(rx.recv_deadline(now()), Ok(()));
        assert!(!rx.take_nudge(), "the router's wake-up is no nudge");
        nudge.nudge();
        nudge.nudge();
        assert_eq!(rx.recv_deadline(now()), Ok(()), "a nudge wakes");
        assert!(rx.take_nudge());
        assert!(!rx.take_nudge(), "taken once");
        drop(tx);
        assert_eq!(
            rx.recv(),
            Err(RecvError::Disconnected),
            "a nudge handle does not keep the link open"
        );
        nudge.nudge();
    }

    #[test]
    fn a_blocked_thread_is_woken_and_a_deadline_passes() {
        let (tx, rx) = wakeup();
        let started = Instant::now();
        let deadline = started + Duration::from_millis(50);
        assert_eq!(rx.recv_deadline(deadline), Err(RecvTimeoutError::Timeout));
        assert!(started.elapsed() >= Duration::from_millis(50));
        let waker = std::thread::spawn(move || {
            std::thread::sleep(Duration::from_millis(20));
            tx.wake();
            tx
        });
        assert_eq!(rx.recv(), Ok(()));
        drop(waker.join().unwrap());
        assert_eq!(rx.recv(), Err(RecvError::Disconnected));
    }

    #[tokio::test]
    async fn a_waiting_task_is_woken_by_a_wake_up_and_by_the_close() {
        let (tx, rx) = wakeup();
        let waiting = tokio::spawn(async move {
            rx.recv_async().await.unwrap();
            rx.recv_async().await
        });
        tokio::time::sleep(Duration::from_millis(20)).await;
        tx.wake();
        tokio::time::sleep(Duration::from_millis(20)).await;
        drop(tx);
        let closed = tokio::time::timeout(Duration::from_secs(5), waiting).await;
        assert_eq!(closed.unwrap().unwrap(), Err(RecvError::Disconnected));
    }
}

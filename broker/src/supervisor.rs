//! What happens when code panics anyway.
//!
//! No panic should be reachable from the network or from stored state: input is checked
//! where it enters (`wire`, the router's protocol codecs, the typed codecs), and
//! the fuzz targets in `broker/fuzz` keep it so. This module is the last line, and it
//! does not pretend a panic did not happen:
//!
//! - a task the whole line depends on ([`Tasks::core`]; the router thread reports its own
//!   end, see `router`) that panics is **fatal**: [`Health::fatal`] makes `/readyz` fail at
//!   once and `fbbus serve` exits non-zero, so the service manager restarts a broker that
//!   is whole again;
//! - a panic in one connection's task ends that connection only: the session is closed as
//!   for any other abnormal end (router unlinked, will published, gauges and registry
//!   updated), see `session::serve`, which wraps the session in [`CatchPanic`].
//!
//! A panic is logged where it happens by the panic hook [`install_panic_hook`] installs
//! (thread, location, message), whatever caught it.

use std::any::Any;
use std::future::Future;
use std::panic::{catch_unwind, AssertUnwindSafe};
use std::pin::Pin;
use std::sync::Arc;
use std::sync::{Mutex, MutexGuard, PoisonError};
use std::task::{Context, Poll};

use tokio::task::{AbortHandle, JoinSet};

use crate::health::Health;

/// A future whose panics come out as `Err(message)` instead of unwinding further.
///
/// The future is not polled again after it panicked: its state may be half-updated, so
/// whoever gets the `Err` must only clean up with what it owns outside the future.
pub struct CatchPanic<F> {
    inner: Option<Pin<Box<F>>>,
}

impl<F: Future> CatchPanic<F> {
    pub fn new(future: F) -> CatchPanic<F> {
        CatchPanic {
            inner: Some(Box::pin(future)),
        }
    }
}

impl<F: Future> Future for CatchPanic<F> {
    type Output = Result<F::Output, String>;

    fn poll(mut self: Pin<&mut Self>, cx: &mut Context<'_>) -> Poll<Self::Output> {
        let Some(inner) = self.inner.as_mut() else {
            return Poll::Pending;
        };
        match catch_unwind(AssertUnwindSafe(|| inner.as_mut().poll(cx))) {
            Ok(Poll::Pending) => Poll::Pending,
            Ok(Poll::Ready(output)) => {
                self.inner = None;
                Poll::Ready(Ok(output))
            }
            Err(panic) => {
                self.inner = None;
                Poll::Ready(Err(panic_message(panic.as_ref()).to_owned()))
            }
        }
    }
}

/// The broker's own tasks: everything it spawns besides connections (which end with their
/// clients, see `session::serve`) goes through one `Tasks`, so shutdown can finish them
/// all ([`Tasks::finish`]) before the last registry write, and none outlives the broker.
///
/// Finished tasks are reaped as new ones start, so short-lived ones (delayed wills) do not
/// accumulate: the set holds the tasks still running. Dropping the last clone aborts them
/// (the `Broker` holds one while it runs).
#[derive(Clone)]
pub struct Tasks {
    set: Arc<Mutex<JoinSet<()>>>,
    health: Arc<Health>,
}

impl Tasks {
    pub fn new(health: &Arc<Health>) -> Tasks {
        Tasks {
            set: Arc::default(),
            health: Arc::clone(health),
        }
    }

    /// Spawns a task the line depends on: if it panics, the broker is not whole any more.
    pub fn core<F>(&self, name: &'static str, task: F) -> AbortHandle
    where
        F: Future<Output = ()> + Send + 'static,
    {
        let health = Arc::clone(&self.health);
        self.spawn(async move {
            if let Err(message) = CatchPanic::new(task).await {
                health.fatal(format!("task `{name}` panicked: {message}"));
            }
        })
    }

    /// Spawns a task the broker owns; a panic in it is logged (the panic hook) and ends
    /// that task only.
    pub fn spawn<F>(&self, task: F) -> AbortHandle
    where
        F: Future<Output = ()> + Send + 'static,
    {
        let mut set = self.lock();
        while set.try_join_next().is_some() {}
        set.spawn(task)
    }

    /// Stops every task and waits until each has finished: after this, no task of the
    /// broker runs, writes a file or publishes.
    pub async fn finish(&self) {
        let mut set = std::mem::take(&mut *self.lock());
        set.abort_all();
        while set.join_next().await.is_some() {}
    }

    /// The one rule for poisoned locks, here as everywhere in fbbus: a panic while the lock
    /// was held left the data consistent (every critical section is a short update), so
    /// the lock is taken anyway.
    fn lock(&self) -> MutexGuard<'_, JoinSet<()>> {
        self.set.lock().unwrap_or_else(PoisonError::into_inner)
    }
}

/// Runs `task` on a thread and a current-thread runtime of its own, named `name`: work
/// that reads every accepted typed message and would otherwise take turns with the
/// sessions on the workers' runtime (the Sparkplug view, the console's activity and
/// history). Logged if the thread or its runtime cannot start.
pub fn spawn_apart<F>(name: &str, task: F)
where
    F: Future<Output = ()> + Send + 'static,
{
    let label = name.to_owned();
    let thread = std::thread::Builder::new()
        .name(name.to_owned())
        .spawn(move || {
            match tokio::runtime::Builder::new_current_thread()
                .enable_all()
                .build()
            {
                Ok(runtime) => runtime.block_on(task),
                Err(e) => tracing::error!(error = %e, thread = label, "cannot start its runtime"),
            }
        });
    if let Err(e) = thread {
        tracing::error!(error = %e, thread = name, "cannot start its thread");
    }
}

/// The message of a panic payload (`panic!` makes a `&str` or a `String`).
pub fn panic_message(panic: &(dyn Any + Send)) -> &str {
    panic
        .downcast_ref::<&str>()
        .copied()
        .or_else(|| panic.downcast_ref::<String>().map(String::as_str))
        .unwrap_or("(no message)")
}

/// Debug builds only (the tests' binary): the topic the environment variable `var` names,
/// whose publication makes a part of the broker panic on purpose, so tests can check what
/// a panic does (`FBBUS_TEST_ROUTER_PANIC_TOPIC`: the router thread;
/// `FBBUS_TEST_SESSION_PANIC_TOPIC`: the publishing client's session). A release build
/// ignores them.
pub fn test_panic_topic(var: &str) -> Option<String> {
    if cfg!(debug_assertions) {
        std::env::var(var).ok().filter(|t| !t.is_empty())
    } else {
        None
    }
}

/// Logs every panic through `tracing` (thread, location, message), so it reaches the
/// broker's log in its format (JSON included), not only standard error.
pub fn install_panic_hook() {
    std::panic::set_hook(Box::new(|info| {
        let thread = std::thread::current();
        let location = info
            .location()
            .map(|l| format!("{}:{}:{}", l.file(), l.line(), l.column()))
            .unwrap_or_default();
        tracing::error!(
            thread = thread.name().unwrap_or("(unnamed)"),
            location,
            message = panic_message(info.payload()),
            "panic"
        );
    }));
}

#[cfg(test)]
mod tests {
    use super::*;

    #[tokio::test]
    async fn a_panicking_future_comes_out_as_its_message() {
        let caught = CatchPanic::new(async {
            tokio::task::yield_now().await;
            panic!("boom at {}", 7);
        })
        .await;
        assert_eq!(caught, Err("boom at 7".to_owned()));
        assert_eq!(CatchPanic::new(async { 5 }).await, Ok(5));
    }

    #[tokio::test]
    async fn a_panicking_core_task_is_fatal() {
        let health = Health::new();
        assert!(health.fatal_reason().is_none());
        // Dropping the last `Tasks` aborts its tasks: keep it for the test.
        let tasks = Tasks::new(&health);
        tasks.core("test", async { panic!("core broke") });
        let reason = tokio::time::timeout(std::time::Duration::from_secs(1), health.died())
            .await
            .expect("died() resolves");
        assert!(
            reason.contains("test") && reason.contains("core broke"),
            "{reason}"
        );
        assert!(health.ready().await.is_err());
    }
}

//! fbbus: frees large garbage off the router thread.
//!
//! A full commit-log segment holds tens of thousands of messages, each with its own topic
//! and payload buffers. Dropping one (retention in `CommitLog::append`, or
//! `CommitLog::release_read`) took 6-19 ms on the router thread at 10,000 msg/s, and every
//! delivery of every connection waited meanwhile: the steady-rate latency maximum was that
//! drop. [`dispose`] hands such garbage to one thread of its own, which drops it in the
//! order it came and then runs the job's follow-up (the router's `released` hook, so the
//! embedder returns memory to the OS after it was actually freed).

use std::sync::mpsc::{self, Sender};
use std::sync::{Arc, OnceLock};

/// Runs after the garbage handed over with it (and everything handed over before) is freed.
pub type Then = Arc<dyn Fn() + Send + Sync>;

struct Job {
    garbage: Box<dyn Send>,
    then: Option<Then>,
}

impl Job {
    fn run(self) {
        drop(self.garbage);
        if let Some(then) = self.then {
            then();
        }
    }
}

/// The freeing thread's queue; `None` if the thread could not be started (then garbage is
/// dropped where it is disposed of, as upstream does).
static FREER: OnceLock<Option<Sender<Job>>> = OnceLock::new();

/// Drops `garbage` on the freeing thread, then runs `then`.
pub(crate) fn dispose(garbage: Box<dyn Send>, then: Option<Then>) {
    let freer = FREER.get_or_init(|| {
        let (tx, rx) = mpsc::channel::<Job>();
        std::thread::Builder::new()
            .name("router-free".into())
            .spawn(move || rx.into_iter().for_each(Job::run))
            .ok()
            .map(|_| tx)
    });
    let job = Job { garbage, then };
    match freer {
        Some(tx) => {
            if let Err(mpsc::SendError(job)) = tx.send(job) {
                job.run();
            }
        }
        None => job.run(),
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::sync::atomic::{AtomicUsize, Ordering};

    struct Counted(Arc<AtomicUsize>);
    impl Drop for Counted {
        fn drop(&mut self) {
            self.0.fetch_add(1, Ordering::SeqCst);
        }
    }

    #[test]
    fn garbage_is_dropped_before_the_follow_up_runs() {
        let dropped = Arc::new(AtomicUsize::new(0));
        let (tx, rx) = mpsc::channel();
        for _ in 0..3 {
            dispose(Box::new(Counted(dropped.clone())), None);
        }
        let seen = dropped.clone();
        let tx = std::sync::Mutex::new(tx);
        dispose(
            Box::new(()),
            Some(Arc::new(move || {
                let _ = tx.lock().unwrap().send(seen.load(Ordering::SeqCst));
            })),
        );
        let at_follow_up = rx.recv_timeout(std::time::Duration::from_secs(5)).unwrap();
        assert_eq!(at_follow_up, 3);
    }
}

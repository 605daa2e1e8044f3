//! The password-verification threads: where a login's argon2id check runs.
//!
//! A fixed set of threads (`auth.verify_concurrency`, the number of cores by default)
//! takes verifications from one first-come-first-served queue. A reconnect storm queues
//! here instead of starving the connections already serving traffic, and the logins are
//! verified in the order they arrived.
//!
//! **Why our own threads and not tokio's blocking pool behind a semaphore.** That was the
//! first version. Between two verifications a slot then went through the async side: the
//! blocking thread finished, a runtime worker woke the login's task, the task released its
//! permit, the next task woke, and only then was the next verification handed to a blocking
//! thread. With the workers busy with the storm's connections, the cores sat idle for about
//! a quarter of a 1,045-device cold storm (`/proc/stat` during the storm: 28% idle with a
//! thousand logins queued), and the storm took 2.1 s on the 2-core development machine.
//! Here a thread that finishes a verification takes the next from the queue at once.
//!
//! A login whose client went away while it was queued is skipped, not verified.
//!
//! **Memory.** argon2id works in `m` KiB (8 MiB by default) that `security::hash` keeps
//! between verifications, so a storm does not page-fault it in again for every login. When
//! a thread finds the queue empty after a verification, it frees that memory: idle, the
//! broker keeps none of it.

use std::future::Future;
use std::io;
use std::thread;

use tokio::sync::oneshot;

type Job = Box<dyn FnOnce() + Send>;

/// The queue and its threads. The threads end when the `Verifier` is dropped (after the
/// verifications still queued have run or been skipped).
pub struct Verifier {
    jobs: flume::Sender<Job>,
}

impl Verifier {
    /// Starts `threads` verification threads, named `fbbus-verify`.
    pub fn start(threads: usize) -> io::Result<Verifier> {
        let (jobs, queue) = flume::unbounded::<Job>();
        for _ in 0..threads.max(1) {
            let queue = queue.clone();
            thread::Builder::new()
                .name("fbbus-verify".into())
                .spawn(move || work(queue))?;
        }
        Ok(Verifier { jobs })
    }

    /// Runs `check` on a verification thread, after the checks queued before it, and
    /// returns its result. `None` if the threads are gone (they never stop while the
    /// `Verifier` lives) or `check` panicked.
    ///
    /// Dropping the returned future while it waits (the client disconnected) withdraws the
    /// check: it is not run.
    pub fn run<T, F>(&self, check: F) -> impl Future<Output = Option<T>> + Send + 'static
    where
        T: Send + 'static,
        F: FnOnce() -> T + Send + 'static,
    {
        let jobs = self.jobs.clone();
        async move {
            let (reply, result) = oneshot::channel();
            let job: Job = Box::new(move || {
                if reply.is_closed() {
                    return;
                }
                let _ = reply.send(check());
            });
            jobs.send(job).ok()?;
            result.await.ok()
        }
    }
}

fn work(queue: flume::Receiver<Job>) {
    while let Ok(job) = queue.recv() {
        // A panicking check loses only its own login (its reply is dropped: rejected).
        let _ = std::panic::catch_unwind(std::panic::AssertUnwindSafe(job));
        if queue.is_empty() {
            security::hash::release_verify_buffers();
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::sync::atomic::{AtomicUsize, Ordering};
    use std::sync::{Arc, Barrier};

    #[tokio::test]
    async fn checks_run_on_the_threads_and_return_their_result() {
        let verifier = Verifier::start(2).unwrap();
        let name = verifier
            .run(|| thread::current().name().map(str::to_owned))
            .await;
        assert_eq!(name, Some(Some("fbbus-verify".to_string())));
    }

    #[tokio::test]
    async fn a_withdrawn_check_is_not_run() {
        let verifier = Verifier::start(1).unwrap();
        // Hold the only thread so the next check stays queued.
        let gate = Arc::new(Barrier::new(2));
        let mut busy = Box::pin(verifier.run({
            let gate = Arc::clone(&gate);
            move || {
                gate.wait();
            }
        }));
        poll_once(busy.as_mut()).await;
        let ran = Arc::new(AtomicUsize::new(0));
        let mut queued = Box::pin({
            let ran = Arc::clone(&ran);
            verifier.run(move || ran.fetch_add(1, Ordering::SeqCst))
        });
        poll_once(queued.as_mut()).await;
        drop(queued); // the client went away
        gate.wait();
        assert_eq!(busy.await, Some(()));
        // A later check runs after the withdrawn one would have.
        assert_eq!(verifier.run(|| 7).await, Some(7));
        assert_eq!(ran.load(Ordering::SeqCst), 0, "the withdrawn check ran");
    }

    /// Polls `future` once (so a check is queued), expecting it to be still waiting.
    async fn poll_once<F: std::future::Future>(future: std::pin::Pin<&mut F>) {
        tokio::select! {
            biased;
            _ = future => panic!("the check cannot have finished yet"),
            _ = tokio::task::yield_now() => {}
        }
    }

    #[tokio::test]
    async fn a_panicking_check_loses_only_itself() {
        let verifier = Verifier::start(1).unwrap();
        assert_eq!(verifier.run(|| -> u8 { panic!("boom") }).await, None);
        assert_eq!(verifier.run(|| 1).await, Some(1));
    }
}

//! The writer thread: the only owner of the log and of the state it mirrors. It takes
//! every batch the sessions handed over, writes them with one `write` and, by policy, one
//! `fsync` (group commit), tells each batch's waiter, and compacts the log when it has
//! grown. After a busy turn it pauses ([`GATHER`]) so that its next turn gathers more.

use std::sync::atomic::{AtomicUsize, Ordering};
use std::sync::Arc;
use std::time::{Duration, Instant};

use tokio::sync::oneshot;

use super::log;
use super::record::{ClientId, Record};
use super::settings::Fsync;
use super::state::{Drops, Limits, Refused, State};
use super::StoreMetrics;

/// The message numbers of a batch's publications that were not kept and whose publisher
/// is told so (MQTT 5 0x97): the store is full, or the publisher's own identity's share
/// is spent (`state::Refused`). Empty (no allocation) in the common case.
pub type Refusals = Vec<u64>;

/// One record batch for the writer, and who waits for it.
pub(super) struct Batch {
    pub(super) records: Vec<Record>,
    /// A session's `Done` records by message number ([`Journal`]), written after `records`.
    pub(super) done: Option<(ClientId, Vec<u64>)>,
    /// Answered once the batch is written and applied, with its [`Refusals`].
    pub(super) written: Option<oneshot::Sender<Refusals>>,
    /// The share (identity) of the session that publishes the batch's publications.
    pub(super) sender: Option<Arc<str>>,
    /// Force the log to the disk after this batch, whatever the policy (shutdown).
    pub(super) sync: bool,
}

/// The writer thread: the only owner of the log and of the state it mirrors.
pub(super) struct Writer {
    pub(super) log: log::Log,
    pub(super) state: State,
    pub(super) limits: Limits,
    pub(super) fsync: Fsync,
    pub(super) compact_min: u64,
    pub(super) metrics: Arc<StoreMetrics>,
    pub(super) subscribed: Arc<AtomicUsize>,
    pub(super) subscribing: Arc<AtomicUsize>,
}

/// Batches taken in one write at most.
const GROUP: usize = 1024;

/// After a busy turn (more than one batch was waiting), the writer pauses this long before
/// taking the next. Meanwhile sessions hand batches over without waking it (in the QoS 1
/// burst, waking the writer once per batch cost about 6% of the broker's CPU), and its next
/// turn writes them together. Adds at most this much to an acknowledgement's wait, only
/// under load, and nothing to routing, which never waits for the store.
const GATHER: Duration = Duration::from_micros(100);

/// The numbers in `refused` (emptied) that `sender` is told of: every one the store had
/// no room for, and those its own identity's share had no room for; in order, once each.
fn refusals(refused: &mut Vec<(u64, Refused)>, sender: Option<&str>) -> Refusals {
    let mut out = Refusals::new();
    for (seq, why) in refused.drain(..) {
        let told = match why {
            Refused::StoreFull => true,
            Refused::Share(share) => sender == Some(&*share),
        };
        if told {
            out.push(seq);
        }
    }
    // Sorted for the session's lookups; a publication refused for several sessions once.
    out.sort_unstable();
    out.dedup();
    out
}

impl Writer {
    pub(super) fn run(mut self, batches: flume::Receiver<Batch>) {
        let mut buffer = Vec::with_capacity(64 * 1024);
        let mut unsynced = false;
        let mut last_sync = Instant::now();
        let mut failing = false;
        self.maybe_compact();
        loop {
            let first = match self.fsync {
                Fsync::Every(every) if unsynced => {
                    let left = every.saturating_sub(last_sync.elapsed());
                    match batches.recv_timeout(left) {
                        Ok(b) => Some(b),
                        Err(flume::RecvTimeoutError::Timeout) => None,
                        Err(flume::RecvTimeoutError::Disconnected) => break,
                    }
                }
                _ => match batches.recv() {
                    Ok(b) => Some(b),
                    Err(_) => break,
                },
            };
            let mut group: Vec<Batch> = first.into_iter().collect();
            while group.len() < GROUP {
                match batches.try_recv() {
                    Ok(b) => group.push(b),
                    Err(_) => break,
                }
            }
            let busy = group.len() > 1;
            buffer.clear();
            let mut sync = self.fsync == Fsync::Always;
            let framer = self.log.framer();
            for b in &group {
                for r in &b.records {
                    framer.frame(r, &mut buffer);
                }
                if let Some((client, seqs)) = &b.done {
                    for seq in seqs {
                        framer.frame_done(client, *seq, &mut buffer);
                    }
                }
                sync |= b.sync;
            }
            if !buffer.is_empty() {
                let t = Instant::now();
                let written = self.log.append(&buffer);
                self.metrics
                    .write_seconds
                    .observe(t.elapsed().as_secs_f64());
                self.report(written, &mut failing);
                unsynced = true;
            }
            let due = matches!(self.fsync, Fsync::Every(every) if last_sync.elapsed() >= every);
            if unsynced && (sync || due) {
                let t = Instant::now();
                let synced = self.log.sync();
                self.metrics
                    .fsync_seconds
                    .observe(t.elapsed().as_secs_f64());
                self.report(synced, &mut failing);
                unsynced = false;
                last_sync = Instant::now();
            }
            let mut drops = Drops::default();
            let mut subscribes = 0;
            for b in group {
                for r in b.records {
                    subscribes += matches!(r, Record::Subscribe { .. }) as usize;
                    self.state.apply(r, self.limits, &mut drops);
                }
                if let Some((client, seqs)) = &b.done {
                    self.state.done(client, seqs);
                }
                // Applied before answering, so the answer says what was not kept.
                let refusals = refusals(&mut drops.refused, b.sender.as_deref());
                if let Some(w) = b.written {
                    let _ = w.send(refusals);
                }
            }
            self.subscribed
                .store(self.state.subscribed, Ordering::Release);
            if subscribes > 0 {
                self.subscribing.fetch_sub(subscribes, Ordering::AcqRel);
            }
            self.count(drops);
            self.maybe_compact();
            self.metrics.show(&self.state, self.log.length());
            if busy {
                std::thread::sleep(GATHER);
            }
        }
        if unsynced {
            let _ = self.log.sync();
        }
    }

    fn report(&self, result: std::io::Result<()>, failing: &mut bool) {
        match result {
            Ok(()) => {
                if *failing {
                    tracing::info!(store = %self.log.path().display(), "the store writes again");
                    *failing = false;
                }
            }
            Err(e) => {
                self.metrics.write_errors.inc();
                if !*failing {
                    tracing::error!(
                        store = %self.log.path().display(),
                        error = %e,
                        "cannot write the store: what is acknowledged now may not survive a \
                         restart (free disk space or fix the disk; the line goes on)"
                    );
                    *failing = true;
                }
            }
        }
    }

    fn count(&self, drops: Drops) {
        for (reason, n) in [
            ("session_queue_full", drops.session_queue_full),
            ("store_full", drops.store_full),
            ("identity_share", drops.identity_share),
            ("retained_limit", drops.retained_limit),
        ] {
            if n > 0 {
                let counter = self.metrics.not_stored.with_label_values(&[reason]);
                if counter.get() == 0 {
                    tracing::warn!(
                        store = %self.log.path().display(),
                        reason,
                        "a message was not stored (it is still routed, but lost if the \
                         broker restarts before it is delivered); see \
                         fbbus_store_not_stored_total"
                    );
                }
                counter.inc_by(n);
            }
        }
    }

    /// Rewrites the log once it is over `compact_min_bytes` and four times what is live.
    fn maybe_compact(&mut self) {
        let live = self.state.bytes as u64 + 256 * self.state.sessions.len() as u64 + 4096;
        if self.log.length() < self.compact_min.max(live.saturating_mul(4)) {
            return;
        }
        let t = Instant::now();
        let before = self.log.length();
        match self.log.compact(self.state.snapshot().into_iter()) {
            Ok(()) => {
                self.metrics.compactions.inc();
                tracing::info!(
                    store = %self.log.path().display(),
                    before,
                    after = self.log.length(),
                    ms = t.elapsed().as_millis() as u64,
                    "store compacted"
                );
            }
            Err(e) => {
                self.metrics.write_errors.inc();
                tracing::error!(error = %e, "store compaction failed; the log is kept as it was");
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A publisher hears of a full store, and of its own identity's spent share, not of
    /// another identity's; each number once, sorted.
    #[test]
    fn a_publisher_is_told_of_the_store_and_of_its_own_share_only() {
        let own: Arc<str> = "user:filler".into();
        let other: Arc<str> = "user:hmi".into();
        let mut refused = vec![
            (7, Refused::Share(Arc::clone(&own))),
            (5, Refused::Share(Arc::clone(&other))),
            (6, Refused::StoreFull),
            (7, Refused::Share(Arc::clone(&own))),
        ];
        assert_eq!(refusals(&mut refused.clone(), Some("user:filler")), [6, 7]);
        assert_eq!(refusals(&mut refused.clone(), Some("user:hmi")), [5, 6]);
        assert_eq!(refusals(&mut refused, None), [6]);
        assert!(refused.is_empty());
    }
}

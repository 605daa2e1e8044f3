//! What survives the broker (issue 17): retained messages, persistent MQTT sessions (their
//! subscriptions with options, the QoS 1/2 messages queued for them, QoS 2 exchanges in
//! flight) and delayed wills, in one append-only log (`log`) under `[persistence] dir`.
//!
//! **The write path.** A session hands its network read's accepted publications to the
//! router as one batch (`Session::route`). Before it does, the retained ones and, while
//! some persistent session subscribes to anything, the QoS 1/2 ones are numbered
//! (`Origin::stored`) and sent to the writer thread as one batch. The router gets them at
//! once; the router's PUBACK/PUBREC for them waits in the session until the writer has
//! written the batch (`fsync = "always"`: written and synced; `session/durable.rs`): a
//! publication fbbus acknowledged is in the log. Being handed over before routing, a
//! publication's record always precedes the `Done` of its deliveries (until 2026-11-26
//! the session waited for the write before routing: docs/performance.md has both). The
//! writer thread takes every batch waiting and writes them with one `write` (and, by
//! policy, one `fsync`): group commit, so a line of publishers shares the cost of each
//! sync. After a busy turn it pauses 100 µs (`GATHER`) so the next turn gathers more.
//! A session's `Done` records travel as bare message numbers ([`Journal`]).
//!
//! **What is queued for whom** is not decided on the packet path: the log records
//! subscriptions and publications, and the writer's copy of the state (`state`) works out
//! which persistent session each publication is queued for, as a replay would. A
//! delivery carries its number out of the router, and the client's PUBACK/PUBCOMP (or the
//! broker's decision not to send it) is recorded as `Done`.
//!
//! **At start** the log is replayed: retained messages go back into the router, each
//! persistent session is linked to the router again with its subscriptions (so messages
//! published before its client returns are queued for it as before), and what was queued
//! for it when the broker stopped is its backlog, which its next connection sends first
//! (`Session::release_backlog`, `session/persist.rs`), QoS 2 exchanges at the step they had
//! reached.
//!
//! **Bounded**: `max_queued_messages` per session, `max_bytes_per_identity` and
//! `max_messages_per_identity` for the sessions of one identity (issue 33: shares, not one
//! pool), and `max_bytes` in all; a message over any of them is not stored (it is still
//! routed), counted in `fbbus_store_not_stored_total`. The writer answers each batch with
//! the publications its publisher must hear of ([`Refusals`]: the store was full, or the
//! sessions were the publisher's own identity's and its share spent), and their MQTT 5
//! acknowledgement says 0x97 Quota exceeded instead of success (`session/durable.rs`).

mod journal;
mod log;
mod queue;
pub mod record;
mod settings;
mod state;
mod writer;

use std::collections::{HashMap, HashSet};
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicU64, AtomicUsize, Ordering};
use std::sync::{Arc, Mutex, PoisonError};
use std::time::{Duration, Instant, SystemTime, UNIX_EPOCH};

use prometheus::{Histogram, HistogramOpts, IntCounter, IntCounterVec, IntGauge, Opts};
use tokio::sync::oneshot;

pub use self::journal::Journal;
pub use self::log::LogError;
pub use self::record::{ClientId, Message, Options, Qos2, Record};
pub use self::settings::{Fsync, PersistenceSection};
use self::state::{Drops, Limits, State, StoredSession};
pub use self::writer::Refusals;
use self::writer::{Batch, Writer};

/// A queued message a restored session's next connection sends first.
#[derive(Debug, Clone)]
pub struct Backlogged {
    pub seq: u64,
    pub message: Arc<Message>,
    /// The QoS it is delivered at.
    pub qos: u8,
    pub qos2: Option<Qos2>,
}

/// A session the log held at start.
#[derive(Debug, Clone)]
pub struct RestoredSession {
    pub client: String,
    pub owner: String,
    pub v5: bool,
    /// How long it has left offline (None: never expires).
    pub expires_in: Option<Duration>,
    pub subscriptions: Vec<(String, Options)>,
}

/// What the log held at start, for the broker to put back.
#[derive(Default)]
pub struct Restore {
    pub retained: Vec<Arc<Message>>,
    /// The identity each retained message was charged to, its topic and its size (topic
    /// and payload bytes), for `retained_share`.
    pub retained_shares: Vec<(String, String, usize)>,
    pub sessions: Vec<RestoredSession>,
    /// Delayed wills: client id, seconds from now (0: overdue), message.
    pub wills: Vec<(String, Duration, Arc<Message>)>,
    pub queued: usize,
    pub took: Duration,
}

#[derive(Debug, thiserror::Error)]
pub enum StoreError {
    #[error(transparent)]
    Log(#[from] LogError),
    #[error("store {path}: cannot start its writer thread: {source}")]
    Thread {
        path: PathBuf,
        source: std::io::Error,
    },
}

/// The store's handle, shared by every session.
pub struct Store {
    queue: flume::Sender<Batch>,
    next_seq: AtomicU64,
    /// Persistent sessions with at least one subscription, after the writer's last batch.
    subscribed: Arc<AtomicUsize>,
    /// Subscribe records sent and not yet applied by the writer: while there are any,
    /// publications are stored as if a session subscribed (no window where a new
    /// subscription's messages are routed but not stored).
    subscribing: Arc<AtomicUsize>,
    /// Client ids with a stored session (so a clean connection ends one).
    persistent: Mutex<HashSet<String>>,
    /// Restored sessions' queued messages, taken by their next connection.
    backlogs: Mutex<HashMap<String, Vec<Backlogged>>>,
    thread: Mutex<Option<std::thread::JoinHandle<()>>>,
}

/// Metrics of the store (`fbbus_store_*`).
pub struct StoreMetrics {
    retained: IntGauge,
    sessions: IntGauge,
    queued: IntGauge,
    bytes: IntGauge,
    file_bytes: IntGauge,
    write_seconds: Histogram,
    fsync_seconds: Histogram,
    not_stored: IntCounterVec,
    write_errors: IntCounter,
    compactions: IntCounter,
    skipped_bytes: IntCounterVec,
    skipped_records: IntCounterVec,
}

impl StoreMetrics {
    fn new(metrics: &crate::metrics::Metrics) -> StoreMetrics {
        let gauge = |name: &str, help: &str| {
            let g = IntGauge::new(name, help).expect("valid metric");
            metrics.register(Box::new(g.clone()));
            g
        };
        let histogram = |name: &str, help: &str| {
            let h = Histogram::with_opts(HistogramOpts::new(name, help).buckets(vec![
                0.00005, 0.0001, 0.00025, 0.0005, 0.001, 0.0025, 0.005, 0.01, 0.025, 0.05, 0.1, 0.5,
            ]))
            .expect("valid metric");
            metrics.register(Box::new(h.clone()));
            h
        };
        let not_stored = IntCounterVec::new(
            Opts::new(
                "fbbus_store_not_stored_total",
                "Messages not stored (still routed) by reason: session_queue_full \
                 (max_queued_messages), store_full (max_bytes), retained_limit (a retained \
                 message on a new topic beyond [broker] max_retained_messages or \
                 max_retained_bytes, which the router does not retain either)",
            ),
            &["reason"],
        )
        .expect("valid metric");
        // At 0 from the start, for the dashboards.
        for reason in ["session_queue_full", "store_full", "retained_limit"] {
            not_stored.with_label_values(&[reason]);
        }
        metrics.register(Box::new(not_stored.clone()));
        let by_reason = |name: &str, help: &str| {
            let c = IntCounterVec::new(Opts::new(name, help), &["reason"]).expect("valid metric");
            metrics.register(Box::new(c.clone()));
            c
        };
        let skipped_bytes = by_reason(
            "fbbus_store_skipped_bytes_total",
            "Bytes of the store's log not restored at start, by reason: damaged (records \
             that failed their checksum, skipped; what follows them was restored), torn (an \
             incomplete tail, cut and kept beside the log)",
        );
        let skipped_records = by_reason(
            "fbbus_store_skipped_records_total",
            "Records of the store's log not restored at start (estimated from the record \
             marks in the bytes), by reason as fbbus_store_skipped_bytes_total",
        );
        let counter = |name: &str, help: &str| {
            let c = IntCounter::new(name, help).expect("valid metric");
            metrics.register(Box::new(c.clone()));
            c
        };
        StoreMetrics {
            retained: gauge("fbbus_store_retained_messages", "Retained messages stored"),
            sessions: gauge(
                "fbbus_store_sessions",
                "Persistent sessions stored (connected and offline)",
            ),
            queued: gauge(
                "fbbus_store_queued_messages",
                "Messages stored for persistent sessions, not yet acknowledged",
            ),
            bytes: gauge(
                "fbbus_store_message_bytes",
                "Bytes of retained and queued messages the store holds (max_bytes)",
            ),
            file_bytes: gauge("fbbus_store_file_bytes", "Size of the store's log on disk"),
            write_seconds: histogram(
                "fbbus_store_write_seconds",
                "Time of one batch's write to the log",
            ),
            fsync_seconds: histogram("fbbus_store_fsync_seconds", "Time of one fsync of the log"),
            not_stored,
            write_errors: counter(
                "fbbus_store_write_errors_total",
                "Failed writes or syncs of the log (the disk is full or failing)",
            ),
            compactions: counter("fbbus_store_compactions_total", "Compactions of the log"),
            skipped_bytes,
            skipped_records,
        }
    }

    /// What replay did not restore.
    fn skipped(&self, skipped: &[log::Skip], torn: Option<&(PathBuf, u64, u64)>) {
        for s in skipped {
            self.skipped_bytes
                .with_label_values(&["damaged"])
                .inc_by(s.bytes);
            self.skipped_records
                .with_label_values(&["damaged"])
                .inc_by(s.records);
        }
        if let Some((_, bytes, records)) = torn {
            self.skipped_bytes
                .with_label_values(&["torn"])
                .inc_by(*bytes);
            self.skipped_records
                .with_label_values(&["torn"])
                .inc_by(*records);
        }
        // Both reasons are there from the start, at 0.
        for reason in ["damaged", "torn"] {
            self.skipped_bytes.with_label_values(&[reason]);
            self.skipped_records.with_label_values(&[reason]);
        }
    }

    fn show(&self, state: &State, file: u64) {
        self.retained.set(state.retained.len() as i64);
        self.sessions.set(state.sessions.len() as i64);
        self.queued.set(state.queued as i64);
        self.bytes.set(state.bytes as i64);
        self.file_bytes.set(file as i64);
    }
}

/// Batches waiting for the writer at most: beyond, sessions wait to hand theirs over
/// (and, not reading their sockets meanwhile, slow their publishers by TCP).
const QUEUE: usize = 4096;

fn unix_now() -> u64 {
    SystemTime::now()
        .duration_since(UNIX_EPOCH)
        .map(|d| d.as_secs())
        .unwrap_or(0)
}

impl Store {
    /// Opens the store in `section.dir`, replays it, and starts its writer thread.
    /// `retained`: the router's bounds on retained messages (count, bytes), which the
    /// store applies too.
    pub fn open(
        section: &PersistenceSection,
        retained: (usize, usize),
        metrics: &crate::metrics::Metrics,
    ) -> Result<(Arc<Store>, Restore), StoreError> {
        let started = Instant::now();
        let path = section.dir.join("store.log");
        let (mut log, replay) = log::Log::open(&path)?;
        if let Some((torn, bytes, _)) = &replay.torn {
            tracing::warn!(
                store = %path.display(),
                kept_in = %torn.display(),
                bytes,
                "the store's last records were torn or corrupt (a crash or power cut while \
                 writing): recovered up to the last intact record; the rest is kept aside"
            );
        }
        if let Some(first) = replay.skipped.first() {
            let bytes: u64 = replay.skipped.iter().map(|s| s.bytes).sum();
            let records: u64 = replay.skipped.iter().map(|s| s.records).sum();
            let offsets: Vec<String> = replay
                .skipped
                .iter()
                .take(16)
                .map(|s| format!("{}+{}", s.offset, s.bytes))
                .collect();
            tracing::warn!(
                store = %path.display(),
                kept_in = %replay.damaged.as_ref().map(|p| p.display().to_string()).unwrap_or_default(),
                offset = first.offset,
                stretches = replay.skipped.len(),
                offsets = %offsets.join(" "),
                bytes,
                records,
                "the store has damaged records (a disk or memory error, an edit): they were \
                 skipped and everything else restored; the records are estimated, their bytes \
                 kept aside, and the store is rewritten without them; see \
                 fbbus_store_skipped_bytes_total"
            );
        }
        let limits = Limits {
            max_bytes: section.max_bytes,
            max_queued: section.max_queued_messages.max(1),
            max_retained: retained.0,
            max_retained_bytes: retained.1,
            share_bytes: section.max_bytes_per_identity.max(1),
            share_messages: section.max_messages_per_identity.max(1),
        };
        let mut state = State::default();
        let mut drops = Drops::default();
        let (rewrite, version) = (replay.rewrite(), replay.version);
        for record in replay.records {
            state.apply(record, limits, &mut drops);
        }
        // Sessions whose expiry passed while the broker was down end now.
        let now = unix_now();
        let expired: Vec<ClientId> = state
            .sessions
            .iter()
            .filter(|(_, s)| match (s.offline_at, s.expiry) {
                (Some(at), Some(e)) => at.saturating_add(e as u64) <= now,
                _ => false,
            })
            .map(|(c, _)| c.clone())
            .collect();
        let mut ended = Vec::new();
        for client in expired {
            let record = Record::Ended { client };
            ended.push(record.clone());
            state.apply(record, limits, &mut drops);
        }
        let mut restore = Restore::default();
        let mut backlogs = HashMap::new();
        let mut persistent = HashSet::new();
        for (client, s) in &state.sessions {
            persistent.insert(client.to_string());
            restore.sessions.push(restored_session(client, s, now));
            let backlog: Vec<Backlogged> = s
                .queue
                .iter()
                .map(|(seq, q)| Backlogged {
                    seq,
                    message: Arc::clone(&q.message),
                    qos: q.qos,
                    qos2: q.qos2,
                })
                .collect();
            restore.queued += backlog.len();
            if !backlog.is_empty() {
                backlogs.insert(client.to_string(), backlog);
            }
        }
        restore.retained = state.retained.values().cloned().collect();
        restore.retained_shares = state
            .retained_by
            .iter()
            .filter_map(|(topic, share)| {
                let message = state.retained.get(topic)?;
                let topic = std::str::from_utf8(topic).ok()?;
                let size = topic.len() + message.payload.len();
                Some((share.clone(), topic.to_owned(), size))
            })
            .collect();
        for (client, wills) in &state.wills {
            let now_ms = now_ms();
            for (due, message) in wills {
                let left = Duration::from_millis(due.saturating_sub(now_ms));
                restore
                    .wills
                    .push((client.to_string(), left, Arc::clone(message)));
            }
        }
        let store_metrics = Arc::new(StoreMetrics::new(metrics));
        store_metrics.skipped(&replay.skipped, replay.torn.as_ref());
        let mut rewritten = false;
        if rewrite {
            // Format 1 (which this fbbus does not append to) or damage met: the store is
            // rewritten now, from what was restored.
            match log.compact(state.snapshot().into_iter()) {
                Ok(()) => {
                    store_metrics.compactions.inc();
                    rewritten = true;
                    tracing::info!(
                        store = %path.display(),
                        format = version,
                        bytes = log.length(),
                        "store rewritten in format {}", self::log::VERSION
                    );
                }
                Err(e) if version < log::VERSION => return Err(e.into()),
                Err(e) => {
                    store_metrics.write_errors.inc();
                    tracing::error!(
                        error = %e,
                        "cannot rewrite the store without its damaged records; it goes on \
                         with them (skipped again at the next start)"
                    );
                }
            }
        }
        if !ended.is_empty() && !rewritten {
            let mut bytes = Vec::new();
            let framer = log.framer();
            for r in &ended {
                framer.frame(r, &mut bytes);
            }
            if let Err(e) = log.append(&bytes) {
                tracing::error!(store = %path.display(), error = %e, "cannot write to the store");
            }
        }
        store_metrics.show(&state, log.length());
        let subscribed = Arc::new(AtomicUsize::new(state.subscribed));
        let subscribing = Arc::new(AtomicUsize::new(0));
        let (queue, batches) = flume::bounded(QUEUE);
        let writer = Writer {
            log,
            state,
            limits,
            fsync: section.fsync,
            compact_min: section.compact_min_bytes,
            metrics: Arc::clone(&store_metrics),
            subscribed: Arc::clone(&subscribed),
            subscribing: Arc::clone(&subscribing),
        };
        let next_seq = AtomicU64::new(writer.state.last_seq + 1);
        let thread = std::thread::Builder::new()
            .name("fbbus-store".into())
            .spawn(move || writer.run(batches))
            .map_err(|source| StoreError::Thread {
                path: path.clone(),
                source,
            })?;
        restore.took = started.elapsed();
        let store = Store {
            queue,
            next_seq,
            subscribed,
            subscribing,
            persistent: Mutex::new(persistent),
            backlogs: Mutex::new(backlogs),
            thread: Mutex::new(Some(thread)),
        };
        Ok((Arc::new(store), restore))
    }

    /// Whether a publication at `qos` with `retain` is stored.
    pub fn stores(&self, qos: u8, retain: bool) -> bool {
        retain
            || (qos > 0
                && (self.subscribed.load(Ordering::Acquire) > 0
                    || self.subscribing.load(Ordering::Acquire) > 0))
    }

    /// The next message number.
    pub fn number(&self) -> u64 {
        self.next_seq.fetch_add(1, Ordering::Relaxed)
    }

    /// Numbers the publications among `packets` the store keeps (retained ones and, while
    /// a persistent session subscribes to anything, QoS 1/2 ones: `Origin::stored`) and
    /// records each in `journal`, before the packets go to the router. `recorded` is
    /// called after each record with the journal, the publication, its packet id if it is
    /// QoS 1/2 on the wire, its number, and how many packets are left from it on (room to
    /// reserve). Used by a client's session and by the bus's import alike.
    pub fn record_publications(
        &self,
        packets: &mut [rumqttd::protocol::Packet],
        journal: &mut Journal,
        mut recorded: impl FnMut(&mut Journal, &rumqttd::protocol::Publish, Option<u16>, u64, usize),
    ) {
        let batch = packets.len();
        let mut reserved = false;
        for (i, packet) in packets.iter_mut().enumerate() {
            let rumqttd::protocol::Packet::Publish(publish, properties) = packet else {
                continue;
            };
            // The publication's QoS, from its origin: a typed message's re-encodings
            // travel as QoS 0 copies and are delivered at the publication's QoS.
            let (wire_qos, pkid) = publish.qos_and_pkid();
            let Some(origin) = publish.origin.as_mut() else {
                continue;
            };
            let qos = origin.qos;
            if !self.stores(qos, publish.retain) {
                continue;
            }
            let seq = self.number();
            origin.stored = seq;
            // Room for the rest of the batch at the first stored publication: one
            // allocation, none for a batch that stores nothing.
            if !reserved {
                journal.reserve(batch - i);
                reserved = true;
            }
            journal.push(Record::Publish {
                seq,
                message: Message {
                    topic: publish.topic.clone(),
                    payload: publish.payload.clone(),
                    qos,
                    retain: publish.retain,
                    properties: properties.clone(),
                    publisher: Arc::clone(&origin.publisher),
                },
            });
            recorded(
                journal,
                publish,
                (wire_qos > 0).then_some(pkid),
                seq,
                batch - i,
            );
        }
    }

    /// Hands `records` to the writer; with `wait`, returns once they are written (and
    /// synced under `fsync = "always"`).
    pub async fn write(&self, records: Vec<Record>, wait: bool) {
        if let Some(written) = self.hand_over(records, None, None, wait).await {
            let _ = written.await;
        }
    }

    /// Hands what `client`'s session recorded to the writer (waiting only while its queue
    /// is full), leaving `journal` empty; with `wait`, the receiver answers once it is
    /// written (and synced under `fsync = "always"`) with the [`Refusals`] its publisher
    /// (of identity `share`) is told of, or when the writer is gone.
    pub async fn submit(
        &self,
        client: &ClientId,
        share: Option<&Arc<str>>,
        journal: &mut Journal,
        wait: bool,
    ) -> Option<oneshot::Receiver<Refusals>> {
        let (records, done) = journal.take(client);
        self.hand_over(records, done, share, wait).await
    }

    async fn hand_over(
        &self,
        records: Vec<Record>,
        done: Option<(ClientId, Vec<u64>)>,
        sender: Option<&Arc<str>>,
        wait: bool,
    ) -> Option<oneshot::Receiver<Refusals>> {
        if records.is_empty() && done.is_none() {
            return None;
        }
        let subscribes = records
            .iter()
            .filter(|r| matches!(r, Record::Subscribe { .. }))
            .count();
        if subscribes > 0 {
            self.subscribing.fetch_add(subscribes, Ordering::AcqRel);
        }
        let (written, answer) = if wait {
            let (tx, rx) = oneshot::channel();
            (Some(tx), Some(rx))
        } else {
            (None, None)
        };
        let batch = Batch {
            records,
            done,
            written,
            sender: sender.filter(|_| wait).cloned(),
            sync: false,
        };
        // A writer that is gone drops the sender: the receiver answers at once.
        let _ = self.queue.send_async(batch).await;
        answer
    }

    /// Hands `records` to the writer from code that cannot wait (wills): in order with
    /// everything handed over before, unless the writer's queue is full, when they go on
    /// a task of their own after it.
    pub fn write_now(&self, records: Vec<Record>) {
        self.hand_over_now(records, None);
    }

    /// [`Store::submit`] from code that cannot wait (a connection's end), as
    /// [`Store::write_now`].
    pub fn submit_now(&self, client: &ClientId, journal: &mut Journal) {
        let (records, done) = journal.take(client);
        self.hand_over_now(records, done);
    }

    fn hand_over_now(&self, records: Vec<Record>, done: Option<(ClientId, Vec<u64>)>) {
        if records.is_empty() && done.is_none() {
            return;
        }
        let batch = Batch {
            records,
            done,
            written: None,
            sender: None,
            sync: false,
        };
        if let Err(flume::TrySendError::Full(batch)) = self.queue.try_send(batch) {
            let queue = self.queue.clone();
            tokio::spawn(async move {
                let _ = queue.send_async(batch).await;
            });
        }
    }

    /// Writes and syncs everything handed over so far (shutdown), then stops the writer.
    pub async fn close(&self) {
        let (tx, rx) = oneshot::channel();
        let batch = Batch {
            records: Vec::new(),
            done: None,
            written: Some(tx),
            sender: None,
            sync: true,
        };
        if self.queue.send_async(batch).await.is_ok() {
            let _ = rx.await;
        }
        let thread = self
            .thread
            .lock()
            .unwrap_or_else(PoisonError::into_inner)
            .take();
        // The writer ends when the last sender is gone; it has nothing left to write.
        drop(thread);
    }

    /// Whether `client` has a stored session.
    pub fn has_session(&self, client: &str) -> bool {
        self.persistent
            .lock()
            .unwrap_or_else(PoisonError::into_inner)
            .contains(client)
    }

    /// Notes that `client` has (true) or no longer has (false) a stored session.
    pub fn set_session(&self, client: &str, stored: bool) {
        let mut set = self
            .persistent
            .lock()
            .unwrap_or_else(PoisonError::into_inner);
        if stored {
            if !set.contains(client) {
                set.insert(client.to_owned());
            }
        } else {
            set.remove(client);
            drop(set);
            self.backlogs
                .lock()
                .unwrap_or_else(PoisonError::into_inner)
                .remove(client);
        }
    }

    /// The queued messages a restored session's next connection sends first.
    pub fn take_backlog(&self, client: &str) -> Vec<Backlogged> {
        self.backlogs
            .lock()
            .unwrap_or_else(PoisonError::into_inner)
            .remove(client)
            .unwrap_or_default()
    }

    /// What a connection did not get through of its backlog, for the session's next one.
    pub fn give_back(&self, client: &str, backlog: Vec<Backlogged>) {
        if self.has_session(client) {
            self.backlogs
                .lock()
                .unwrap_or_else(PoisonError::into_inner)
                .insert(client.to_owned(), backlog);
        }
    }
}

fn restored_session(client: &str, s: &StoredSession, now: u64) -> RestoredSession {
    let expires_in = match (s.offline_at, s.expiry) {
        (_, None) => None,
        (Some(at), Some(e)) => Some(Duration::from_secs(
            at.saturating_add(e as u64).saturating_sub(now),
        )),
        // Connected when the broker stopped: offline from now on.
        (None, Some(e)) => Some(Duration::from_secs(e as u64)),
    };
    RestoredSession {
        client: client.to_owned(),
        owner: s.owner.clone(),
        v5: s.v5,
        expires_in,
        subscriptions: s
            .subscriptions
            .iter()
            .map(|(f, o)| (f.clone(), *o))
            .collect(),
    }
}

/// For the fuzzer (`broker/fuzz`, target `store_replay`): reads `bytes` as a store log
/// (a header, then records; format 1 or 2) into a state under small limits, checks what
/// the state promises, and that a compaction of it rebuilds the same state. Returns how
/// many records were intact. A file on disk is outside input: nothing here may panic on
/// it, and replay, skipping damage, never reads more than was there.
#[doc(hidden)]
pub fn replay_for_fuzzing(bytes: &[u8]) -> usize {
    let parsed = log::parse(bytes);
    let end = parsed.end;
    assert!(end <= bytes.len().max(log::HEADER));
    // Skipped stretches lie before the end, in order, apart; every record took at least a
    // frame and a byte of what was not skipped.
    let mut last = 0;
    for s in &parsed.skipped {
        assert!(s.offset >= last && s.bytes > 0 && s.records > 0);
        last = s.offset + s.bytes;
    }
    assert!(last <= end as u64);
    let skipped: u64 = parsed.skipped.iter().map(|s| s.bytes).sum();
    assert!(parsed.records.len() as u64 * 9 <= (end as u64).saturating_sub(skipped));
    let records = parsed.records;
    let limits = Limits {
        max_bytes: 1 << 16,
        max_queued: 16,
        max_retained: 64,
        max_retained_bytes: 1 << 14,
        share_bytes: 1 << 15,
        share_messages: 24,
    };
    let mut state = State::default();
    let mut drops = Drops::default();
    let n = records.len();
    for r in records {
        // Every record that was read writes back as the same bytes.
        let mut bytes = Vec::new();
        r.encode(&mut bytes);
        assert_eq!(Record::decode(&bytes).ok().as_ref(), Some(&r));
        state.apply(r, limits, &mut drops);
    }
    assert!(state.bytes <= limits.max_bytes);
    assert!(state
        .sessions
        .values()
        .all(|s| s.queue.len() <= limits.max_queued));
    let mut again = State::default();
    for r in state.snapshot() {
        again.apply(r, limits, &mut drops);
    }
    assert_eq!(
        (
            again.retained.len(),
            again.sessions.len(),
            again.queued,
            again.bytes
        ),
        (
            state.retained.len(),
            state.sessions.len(),
            state.queued,
            state.bytes
        ),
        "a compaction does not rebuild the state"
    );
    n
}

/// Unix seconds now (records' times).
pub fn now() -> u64 {
    unix_now()
}

/// Unix milliseconds now (a delayed will's due time).
pub fn now_ms() -> u64 {
    SystemTime::now()
        .duration_since(UNIX_EPOCH)
        .map(|d| d.as_millis() as u64)
        .unwrap_or(0)
}

/// The store's log file in `dir` (named in errors).
pub fn log_path(dir: &Path) -> PathBuf {
    dir.join("store.log")
}

#[cfg(test)]
mod tests {
    use super::*;

    fn message(topic: &'static str) -> Message {
        Message {
            topic: bytes::Bytes::from_static(topic.as_bytes()),
            payload: bytes::Bytes::from_static(b"v"),
            qos: 2,
            retain: false,
            properties: None,
            publisher: "press-1".into(),
        }
    }

    /// Hands `journal` over and waits until it is written.
    async fn written(store: &Store, client: &ClientId, journal: &mut Journal) {
        let answer = store
            .submit(client, Some(&"anonymous".into()), journal, true)
            .await;
        answer
            .expect("a journal with records is handed over")
            .await
            .unwrap();
    }

    /// A journal's `Done` numbers are written after its records, and a restart finds what
    /// they left: the QoS 2 step recorded before a `Done` in the same journal does not
    /// bring the message back, and what has no `Done` is still queued.
    #[tokio::test]
    async fn done_numbers_follow_their_journals_records_across_a_restart() {
        let dir = tempfile::tempdir().unwrap();
        let section = PersistenceSection {
            dir: dir.path().to_path_buf(),
            fsync: Fsync::Always,
            ..PersistenceSection::default()
        };
        let open = || Store::open(&section, (1000, 1 << 20), &crate::metrics::Metrics::new());
        let (store, _) = open().unwrap();
        let client: ClientId = "hmi-1".into();
        let mut journal = Journal::default();
        journal.push(Record::Session {
            client: client.clone(),
            owner: String::new(),
            share: "anonymous".into(),
            v5: false,
            expiry: None,
            fresh: true,
        });
        journal.push(Record::Subscribe {
            client: client.clone(),
            filter: "line/#".into(),
            options: Options {
                qos: 2,
                no_local: false,
                retain_as_published: false,
                retain_handling: 0,
                id: 0,
            },
        });
        written(&store, &client, &mut journal).await;
        let publications = (1..=3)
            .map(|seq| Record::Publish {
                seq,
                message: message("line/press"),
            })
            .collect();
        store.write(publications, true).await;
        // Message 1: PUBREC then PUBCOMP in one read; message 2: a PUBACK.
        journal.push(Record::Qos2 {
            client: client.clone(),
            seq: 1,
            state: Qos2::Received(7),
        });
        journal.done(1);
        journal.done(2);
        assert!(!journal.is_empty());
        written(&store, &client, &mut journal).await;
        assert!(journal.is_empty(), "submit takes everything");
        store.close().await;
        drop(store);
        let (store, restore) = open().unwrap();
        assert_eq!(restore.queued, 1);
        let backlog: Vec<u64> = store.take_backlog("hmi-1").iter().map(|b| b.seq).collect();
        assert_eq!(backlog, [3]);
    }

    const WIDE: Limits = Limits {
        max_bytes: 1 << 30,
        max_queued: 1 << 20,
        max_retained: 1 << 20,
        max_retained_bytes: 1 << 30,
        share_bytes: 1 << 30,
        share_messages: 1 << 20,
    };

    /// What a state holds, comparable: each session's queue (number, QoS, QoS 2 step),
    /// offline time and subscriptions; retained topics and payloads; the counters.
    type Summary = (
        Vec<(
            String,
            Option<u64>,
            Vec<String>,
            Vec<(u64, u8, Option<Qos2>)>,
        )>,
        Vec<(Vec<u8>, Vec<u8>)>,
        (u64, usize, usize),
    );

    fn summary(s: &State) -> Summary {
        let mut sessions: Vec<_> = s
            .sessions
            .iter()
            .map(|(c, s)| {
                (
                    c.to_string(),
                    s.offline_at,
                    s.subscriptions.keys().cloned().collect(),
                    s.queue
                        .iter()
                        .map(|(seq, q)| (seq, q.qos, q.qos2))
                        .collect(),
                )
            })
            .collect();
        sessions.sort_by(|a, b| a.0.cmp(&b.0));
        let retained = s
            .retained
            .iter()
            .map(|(t, m)| (t.clone(), m.payload.to_vec()))
            .collect();
        (sessions, retained, (s.last_seq, s.queued, s.bytes))
    }

    fn replayed(records: Vec<Record>) -> State {
        let mut state = State::default();
        let mut drops = Drops::default();
        for r in records {
            state.apply(r, WIDE, &mut drops);
        }
        state
    }

    /// Two persistent sessions, QoS 1 and 2 publications (some retained) and every step of
    /// their deliveries, interleaved as a broker writes them.
    fn history() -> Vec<Record> {
        let options = |qos| Options {
            qos,
            no_local: false,
            retain_as_published: false,
            retain_handling: 0,
            id: 0,
        };
        let session = |c: &str| Record::Session {
            client: c.into(),
            owner: String::new(),
            share: "anonymous".into(),
            v5: true,
            expiry: None,
            fresh: true,
        };
        let mut h = vec![
            session("q2"),
            Record::Subscribe {
                client: "q2".into(),
                filter: "line/#".into(),
                options: options(2),
            },
            session("q1"),
            Record::Subscribe {
                client: "q1".into(),
                filter: "line/+".into(),
                options: options(1),
            },
        ];
        for seq in 1..=24u64 {
            let mut m = message("line/press");
            m.qos = if seq % 3 == 0 { 1 } else { 2 };
            m.retain = seq % 5 == 0;
            m.payload = bytes::Bytes::from(format!("m{seq}"));
            h.push(Record::Publish { seq, message: m });
            // The deliveries of the message two before: q2 goes through QoS 2's steps,
            // q1 acknowledges; one of q2's is left at PUBREC, one at PUBLISH.
            if seq > 2 {
                let d = seq - 2;
                let pkid = d as u16;
                if d % 3 != 0 {
                    h.push(Record::Qos2 {
                        client: "q2".into(),
                        seq: d,
                        state: Qos2::Sent(pkid),
                    });
                }
                if d % 3 != 0 && d != 7 {
                    h.push(Record::Qos2 {
                        client: "q2".into(),
                        seq: d,
                        state: Qos2::Received(pkid),
                    });
                }
                if d != 7 && d != 11 {
                    h.push(Record::Done {
                        client: "q2".into(),
                        seq: d,
                    });
                }
                h.push(Record::Done {
                    client: "q1".into(),
                    seq: d,
                });
            }
            if seq == 12 {
                h.push(Record::Offline {
                    client: "q1".into(),
                    at: 1_700_000_000,
                    expiry: None,
                });
            }
        }
        h
    }

    /// Issue 33: a log cut anywhere (a lost tail, a file cut in half) restores the store
    /// exactly as it was after the last whole record before the cut: a state it had, never
    /// a mix, never more. So for QoS 2: a delivery whose PUBREC was recorded before the cut
    /// resumes with PUBREL (never a second PUBLISH); one whose PUBCOMP (`Done`) was, never
    /// comes back; one at PUBLISH is sent again under its packet id, DUP=1.
    #[test]
    fn every_cut_restores_an_earlier_state_exactly() {
        let records = history();
        let (bytes, ends) = log::log_of(&records);
        // The state after each whole record, as the writer had it.
        let mut states = vec![summary(&State::default())];
        let mut state = State::default();
        let mut drops = Drops::default();
        for r in &records {
            state.apply(r.clone(), WIDE, &mut drops);
            states.push(summary(&state));
        }
        for cut in 0..=bytes.len() {
            let parsed = log::parse(&bytes[..cut]);
            let whole = ends.iter().filter(|e| **e <= cut).count();
            assert_eq!(parsed.records.len(), whole, "cut at {cut}");
            let restored = replayed(parsed.records);
            assert_eq!(summary(&restored), states[whole], "cut at {cut}");
            // QoS 2, said record by record.
            let before = &records[..whole];
            let Some(q2) = restored.sessions.get("q2") else {
                continue;
            };
            for (seq, q) in q2.queue.iter() {
                let recorded = |want: fn(&Qos2) -> bool| {
                    before.iter().any(|r| {
                        matches!(r, Record::Qos2 { client, seq: s, state }
                            if &**client == "q2" && *s == seq && want(state))
                    })
                };
                let done = before.iter().any(
                    |r| matches!(r, Record::Done { client, seq: s } if &**client == "q2" && *s == seq),
                );
                assert!(!done, "cut at {cut}: message {seq} was done");
                if recorded(|s| matches!(s, Qos2::Received(_))) {
                    assert!(matches!(q.qos2, Some(Qos2::Received(p)) if p as u64 == seq));
                } else if recorded(|s| matches!(s, Qos2::Sent(_))) {
                    assert!(matches!(q.qos2, Some(Qos2::Sent(p)) if p as u64 == seq));
                } else {
                    assert_eq!(q.qos2, None);
                }
            }
        }
    }

    /// A compacted log cut anywhere restores part of what was live, as it was: nothing
    /// that was not live, no QoS 2 delivery at an earlier step.
    #[test]
    fn a_cut_compacted_log_restores_nothing_that_was_not_live() {
        let full = replayed(history());
        let live = summary(&full);
        let (bytes, _) = log::log_of(&full.snapshot());
        for cut in 0..=bytes.len() {
            let restored = summary(&replayed(log::parse(&bytes[..cut]).records));
            for (client, _, subscriptions, queue) in &restored.0 {
                let (_, _, all, queued) = live.0.iter().find(|s| &s.0 == client).unwrap();
                assert!(
                    subscriptions.iter().all(|f| all.contains(f)),
                    "cut at {cut}"
                );
                assert!(queue.iter().all(|q| queued.contains(q)), "cut at {cut}");
            }
            assert!(
                restored.1.iter().all(|r| live.1.contains(r)),
                "cut at {cut}"
            );
        }
    }

    /// Issue 33 through the store: a damaged record in the middle of the log is skipped,
    /// everything after it restored, the skip counted, and the store rewritten without it.
    #[tokio::test]
    async fn a_damaged_record_is_skipped_counted_and_rewritten_away() {
        let dir = tempfile::tempdir().unwrap();
        let section = PersistenceSection {
            dir: dir.path().to_path_buf(),
            ..PersistenceSection::default()
        };
        let records = history();
        let (mut bytes, ends) = log::log_of(&records);
        // A bit of the Publish of message 1, whose deliveries are all done by the end;
        // and one of message 24, which nothing acknowledged.
        let publish = |seq| {
            records
                .iter()
                .position(|r| matches!(r, Record::Publish { seq: s, .. } if *s == seq))
                .unwrap()
        };
        let damaged = [publish(1), publish(24)];
        for i in damaged {
            bytes[ends[i] - 3] ^= 0x08;
        }
        std::fs::create_dir_all(dir.path()).unwrap();
        std::fs::write(dir.path().join("store.log"), &bytes).unwrap();
        let metrics = crate::metrics::Metrics::new();
        let (store, restore) = Store::open(&section, (1000, 1 << 20), &metrics).unwrap();
        let kept: Vec<Record> = (0..records.len())
            .filter(|i| !damaged.contains(i))
            .map(|i| records[i].clone())
            .collect();
        let want = replayed(kept);
        assert_eq!(restore.queued, want.queued);
        let q2: Vec<u64> = store.take_backlog("q2").iter().map(|b| b.seq).collect();
        assert_eq!(q2, [7, 11, 23], "message 24 is lost, the rest as written");
        let text = metrics.render();
        let lost: usize = [damaged[0], damaged[1]]
            .iter()
            .map(|i| ends[*i] - if *i == 0 { log::HEADER } else { ends[*i - 1] })
            .sum();
        assert!(
            text.contains(&format!(
                "fbbus_store_skipped_bytes_total{{reason=\"damaged\"}} {lost}"
            )),
            "{text}"
        );
        assert!(text.contains("fbbus_store_skipped_records_total{reason=\"damaged\"} 2"));
        assert!(text.contains("fbbus_store_skipped_bytes_total{reason=\"torn\"} 0"));
        store.close().await;
        drop(store);
        // Rewritten: the next start meets no damage.
        let metrics = crate::metrics::Metrics::new();
        let (store, restore) = Store::open(&section, (1000, 1 << 20), &metrics).unwrap();
        assert_eq!(restore.queued, want.queued);
        assert!(metrics
            .render()
            .contains("fbbus_store_skipped_bytes_total{reason=\"damaged\"} 0"));
        store.close().await;
    }

    /// A store written in format 1 (before issue 33) restores, and is rewritten in format 2.
    #[tokio::test]
    async fn a_format_1_store_restores_and_is_rewritten() {
        let dir = tempfile::tempdir().unwrap();
        let section = PersistenceSection {
            dir: dir.path().to_path_buf(),
            ..PersistenceSection::default()
        };
        let records = history();
        let mut old = b"FBBUSLOG".to_vec();
        old.extend_from_slice(&1u32.to_le_bytes());
        for r in &records {
            let mut body = Vec::new();
            r.encode(&mut body);
            old.extend_from_slice(&(body.len() as u32).to_le_bytes());
            old.extend_from_slice(&crc32fast::hash(&body).to_le_bytes());
            old.extend_from_slice(&body);
        }
        let path = dir.path().join("store.log");
        std::fs::write(&path, &old).unwrap();
        let want = summary(&replayed(records));
        let (store, restore) =
            Store::open(&section, (1000, 1 << 20), &crate::metrics::Metrics::new()).unwrap();
        assert_eq!(restore.queued, want.2 .1);
        assert_eq!(restore.retained.len(), want.1.len());
        let q2: Vec<u64> = store.take_backlog("q2").iter().map(|b| b.seq).collect();
        assert_eq!(q2, [7, 11, 23, 24]);
        store.close().await;
        drop(store);
        let bytes = std::fs::read(&path).unwrap();
        assert_eq!(&bytes[8..12], &log::VERSION.to_le_bytes(), "rewritten");
        let restored = summary(&replayed(log::parse(&bytes).records));
        assert_eq!(restored.0, want.0);
        assert_eq!(restored.1, want.1);
    }

    #[test]
    fn fsync_policies_parse() {
        assert_eq!("always".parse(), Ok(Fsync::Always));
        assert_eq!("os".parse(), Ok(Fsync::Os));
        assert_eq!(
            "every 100 ms".parse(),
            Ok(Fsync::Every(Duration::from_millis(100)))
        );
        assert_eq!(
            "every 5ms".parse(),
            Ok(Fsync::Every(Duration::from_millis(5)))
        );
        for bad in ["every 0 ms", "every ms", "sometimes", "every 100 s", ""] {
            assert!(bad.parse::<Fsync>().is_err(), "{bad}");
        }
    }
}

//! The zenoh sessions of one link, and what each of them carries.
//!
//! A link holds one session, or with [`BusConfig::session_per_router`] one per router,
//! each connecting to its own router only. A zenoh client's `open` waits for its router,
//! and one that loses its router waits for that router to come back: so a session per
//! router stays on its router, and the line is on every router that is up. The sessions
//! open side by side; the link is up once the first is, and each later one is *attached*:
//! given everything the link declared so far (the watchers of the other lines, the
//! queryables, the line's token, every import), under the same lock that declaring on
//! all sessions takes, so no session misses a declaration.
//!
//! Puts and queries go through one session, the *active* one: the first that has a
//! router, checked every [`ACTIVE_EVERY`].
//!
//! [`BusConfig::session_per_router`]: super::BusConfig::session_per_router

use std::collections::HashMap;
use std::sync::atomic::{AtomicBool, AtomicU64, AtomicUsize, Ordering};
use std::sync::{Arc, Mutex, PoisonError, RwLock};
use std::time::Duration;

use zenoh::key_expr::KeyExpr;
use zenoh::liveliness::LivelinessToken;
use zenoh::pubsub::Subscriber;
use zenoh::query::Query;
use zenoh::sample::SampleKind;
use zenoh::{Session, Wait};

use super::error::{zerr, LinkError};
use super::event::{Event, Inbound};
use super::presence::{decode_version, Presence, RecordOrder};
use super::{keys, LossReport, Reported, Stamp};

/// How often a link with a session per router checks which sessions have a router: the
/// longest a put can go to a session whose router was just killed.
pub(super) const ACTIVE_EVERY: Duration = Duration::from_millis(50);

/// What answers registry queries: (device id, record JSON) of one device or all.
pub(super) type Records = Arc<dyn Fn(Option<&str>) -> Vec<(String, Vec<u8>)> + Send + Sync>;

/// A link's sessions (cheap to clone: one shared state).
#[derive(Clone)]
pub(super) struct Sessions(Arc<Shared>);

struct Shared {
    line: String,
    /// Slot `i` is the session on router `i` once it opened.
    slots: RwLock<Vec<Option<Session>>>,
    /// Bumped at each attachment: caches of per-session handles start over.
    generation: AtomicU64,
    active: AtomicUsize,
    /// Sessions that had a router at the last check ([`Sessions::routers`]).
    reached: AtomicUsize,
    closed: AtomicBool,
    declared: Mutex<Declared>,
    events: flume::Sender<Event>,
    inbox: flume::Sender<Inbound>,
    lines: Presence<String>,
    interests: Presence<(String, String)>,
    /// With more than one session only: one delivers each change once, in order.
    records: Option<RecordOrder>,
    /// What the other lines reported of this line's messages lost on the way.
    reported: Mutex<Reported>,
    /// Messages this line put on the bus in this run: no line can have lost more of them.
    exported: AtomicU64,
}

/// Everything a newly attached session must declare too.
#[derive(Default)]
struct Declared {
    /// The line's tokens, once announced ([`Sessions::announce`]).
    announced: Option<Vec<LivelinessToken>>,
    records: Option<Records>,
    retained: Option<flume::Sender<Query>>,
    imports: HashMap<u64, Imported>,
    next_import: u64,
}

/// One import ([`Sessions::import`]): its key and filter, and its subscriber and interest
/// token on each session.
struct Imported {
    key: String,
    filter: String,
    held: Vec<(Subscriber<()>, LivelinessToken)>,
}

impl Sessions {
    /// Opens a session per configuration, side by side, and returns once the first is up
    /// (attached); the others are attached as they open. Fails only if every one failed.
    pub(super) async fn open(
        configs: Vec<zenoh::Config>,
        (line, epoch): (&str, u64),
        events: flume::Sender<Event>,
        inbox: flume::Sender<Inbound>,
    ) -> Result<Sessions, LinkError> {
        let count = configs.len();
        let sessions = Sessions(Arc::new(Shared {
            line: line.to_owned(),
            slots: RwLock::new((0..count).map(|_| None).collect()),
            generation: AtomicU64::new(0),
            active: AtomicUsize::new(0),
            reached: AtomicUsize::new(0),
            closed: AtomicBool::new(false),
            declared: Mutex::default(),
            events,
            inbox,
            lines: Presence::new(),
            interests: Presence::new(),
            records: (count > 1).then(RecordOrder::new),
            reported: Mutex::new(Reported::new(epoch)),
            exported: AtomicU64::new(0),
        }));
        let (opened_tx, mut opened) = tokio::sync::mpsc::channel(count.max(1));
        for (slot, config) in configs.into_iter().enumerate() {
            // Weak: a session whose router answers only after the link is gone (dropped
            // without `close`, say when the bridge failed to start) is closed, not kept.
            let (sessions, opened_tx) = (Arc::downgrade(&sessions.0), opened_tx.clone());
            tokio::spawn(async move {
                // zenoh's `open` blocks its thread until the session is up (a client's:
                // until its router answers), even when awaited: off the async workers.
                let open = tokio::task::spawn_blocking(move || zenoh::open(config).wait());
                let attached = match open.await.map_err(zerr).and_then(|r| r.map_err(zerr)) {
                    Ok(session) => match sessions.upgrade() {
                        Some(shared) => Sessions(shared).attach(slot, session),
                        None => {
                            let _ = session.close().await;
                            return;
                        }
                    },
                    Err(e) => Err(e),
                };
                if let (Err(e), true) = (&attached, slot > 0) {
                    tracing::warn!(slot, error = %e, "bus: a session to a router failed to open");
                }
                let _ = opened_tx.send(attached).await;
            });
        }
        drop(opened_tx);
        let mut first_error = None;
        while let Some(attached) = opened.recv().await {
            match attached {
                Ok(()) => {
                    if count > 1 {
                        sessions.follow();
                    }
                    return Ok(sessions);
                }
                Err(e) => {
                    first_error.get_or_insert(e);
                }
            }
        }
        Err(first_error.unwrap_or_else(|| LinkError::Zenoh("no session opened".into())))
    }

    /// Gives `session` everything declared so far, then puts it in slot `slot`.
    fn attach(&self, slot: usize, session: Session) -> Result<(), LinkError> {
        let shared = &self.0;
        let mut declared = shared
            .declared
            .lock()
            .unwrap_or_else(PoisonError::into_inner);
        if shared.closed.load(Ordering::SeqCst) {
            let _ = session.close().wait();
            return Ok(());
        }
        self.watch(&session, slot)?;
        if let Some(records) = &declared.records {
            self.serve_records_on(&session, Arc::clone(records))?;
        }
        if let Some(tx) = &declared.retained {
            serve_retained_on(&session, &shared.line, tx.clone())?;
        }
        for imported in declared.imports.values_mut() {
            let held = self.import_on(&session, &imported.key, &imported.filter)?;
            imported.held.push(held);
        }
        if let Some(tokens) = &mut declared.announced {
            tokens.push(line_token_on(&session, &shared.line)?);
        }
        shared.slots.write().unwrap_or_else(PoisonError::into_inner)[slot] = Some(session);
        shared.generation.fetch_add(1, Ordering::SeqCst);
        Ok(())
    }

    /// Every session open now.
    pub(super) fn each(&self) -> Vec<Session> {
        let slots = self.0.slots.read().unwrap_or_else(PoisonError::into_inner);
        slots.iter().flatten().cloned().collect()
    }

    /// The session puts and queries go through; an error once the link is closed.
    pub(super) fn active(&self) -> Result<Session, LinkError> {
        let slots = self.0.slots.read().unwrap_or_else(PoisonError::into_inner);
        let want = self.0.active.load(Ordering::Relaxed);
        slots
            .get(want)
            .cloned()
            .flatten()
            .or_else(|| slots.iter().flatten().next().cloned())
            .ok_or_else(|| LinkError::Zenoh("the link is closed".into()))
    }

    /// The exporter put its `count`-th message of this run.
    pub(super) fn exported(&self, count: u64) {
        self.0.exported.store(count, Ordering::Relaxed);
    }

    /// Changes when the active session or the set of sessions changed: a cache of handles
    /// declared on the active session is stale once this differs from when it was built.
    pub(super) fn version(&self) -> (usize, u64) {
        (
            self.0.active.load(Ordering::Relaxed),
            self.0.generation.load(Ordering::SeqCst),
        )
    }

    /// With a session per router: (sessions that have their router, sessions), as of the
    /// last check; `None` with one session.
    pub(super) fn routers(&self) -> Option<(usize, usize)> {
        let total = self
            .0
            .slots
            .read()
            .unwrap_or_else(PoisonError::into_inner)
            .len();
        (total > 1).then(|| (self.0.reached.load(Ordering::Relaxed), total))
    }

    /// Declares the line's liveliness token on every session, now and attached later.
    pub(super) fn announce(&self) -> Result<(), LinkError> {
        let mut declared = self.lock();
        let mut tokens = Vec::new();
        for session in self.each() {
            tokens.push(line_token_on(&session, &self.0.line)?);
        }
        declared.announced = Some(tokens);
        Ok(())
    }

    /// Answers registry queries with `records` on every session.
    pub(super) fn serve_records(&self, records: Records) -> Result<(), LinkError> {
        let mut declared = self.lock();
        for session in self.each() {
            self.serve_records_on(&session, Arc::clone(&records))?;
        }
        declared.records = Some(records);
        Ok(())
    }

    /// Hands other lines' retained-message queries, from every session, to `tx`.
    pub(super) fn serve_retained(&self, tx: flume::Sender<Query>) -> Result<(), LinkError> {
        let mut declared = self.lock();
        for session in self.each() {
            serve_retained_on(&session, &self.0.line, tx.clone())?;
        }
        declared.retained = Some(tx);
        Ok(())
    }

    /// Declares interest in `filter` (zenoh key `key`) on every session; returns the
    /// number [`Sessions::forget_import`] takes.
    pub(super) fn import(&self, key: String, filter: &str) -> Result<u64, LinkError> {
        let mut declared = self.lock();
        let mut held = Vec::new();
        for session in self.each() {
            held.push(self.import_on(&session, &key, filter)?);
        }
        let id = declared.next_import;
        declared.next_import += 1;
        declared.imports.insert(
            id,
            Imported {
                key,
                filter: filter.to_owned(),
                held,
            },
        );
        Ok(id)
    }

    /// Undeclares import `id` on every session.
    pub(super) fn forget_import(&self, id: u64) {
        let removed = self.lock().imports.remove(&id);
        drop(removed);
    }

    /// Closes every session; one that opens later is closed at once.
    pub(super) async fn close(&self) {
        let (slots, declared) = {
            let mut declared = self.lock();
            self.0.closed.store(true, Ordering::SeqCst);
            let mut slots = self.0.slots.write().unwrap_or_else(PoisonError::into_inner);
            let slots: Vec<_> = slots.iter_mut().filter_map(Option::take).collect();
            // Dropped outside the lock: the imports' handles, and the retained queries'
            // sender, whose receiver then ends.
            (slots, std::mem::take(&mut *declared))
        };
        drop(declared);
        for session in slots {
            let _ = session.close().await;
        }
    }

    fn lock(&self) -> std::sync::MutexGuard<'_, Declared> {
        self.0
            .declared
            .lock()
            .unwrap_or_else(PoisonError::into_inner)
    }

    /// Follows the sessions until the link closes: the first with a router is active.
    fn follow(&self) {
        let sessions = Arc::downgrade(&self.0);
        tokio::spawn(async move {
            loop {
                tokio::time::sleep(ACTIVE_EVERY).await;
                let Some(shared) = sessions.upgrade() else {
                    return;
                };
                if shared.closed.load(Ordering::SeqCst) {
                    return;
                }
                let with_router: Vec<bool> = {
                    let slots = shared.slots.read().unwrap_or_else(PoisonError::into_inner);
                    slots
                        .iter()
                        .map(|s| {
                            s.as_ref()
                                .is_some_and(|s| s.info().routers_zid().wait().next().is_some())
                        })
                        .collect()
                };
                let reached = with_router.iter().filter(|&&r| r).count();
                shared.reached.store(reached, Ordering::Relaxed);
                if let Some(slot) = with_router.iter().position(|&r| r) {
                    let was = shared.active.swap(slot, Ordering::Relaxed);
                    if was != slot {
                        tracing::info!(
                            from = was,
                            to = slot,
                            "bus: puts go through the session on another router"
                        );
                    }
                }
            }
        });
    }

    /// Watches `session` (in slot `slot`) for the other lines' liveliness, interests and
    /// record changes, merged with what the other sessions see.
    fn watch(&self, session: &Session, slot: usize) -> Result<(), LinkError> {
        let shared = Arc::downgrade(&self.0);
        let on_line = move |sample: zenoh::sample::Sample| {
            let Some(s) = shared.upgrade() else { return };
            let Some(l) = keys::parse_line_token(sample.key_expr().as_str()) else {
                return;
            };
            if l == s.line {
                return;
            }
            let up = sample.kind() == SampleKind::Put;
            let _ = match s.lines.seen(l.to_owned(), slot, up) {
                Some(true) => s.events.send(Event::LineUp(l.to_owned())),
                Some(false) => s.events.send(Event::LineDown(l.to_owned())),
                None => Ok(()),
            };
        };
        session
            .liveliness()
            .declare_subscriber(format!("{}/line/*", keys::CONTROL))
            .history(true)
            .callback(on_line)
            .background()
            .wait()
            .map_err(zerr)?;
        let shared = Arc::downgrade(&self.0);
        let on_interest = move |sample: zenoh::sample::Sample| {
            let Some(s) = shared.upgrade() else { return };
            let Some((l, filter)) = keys::parse_interest(sample.key_expr().as_str()) else {
                return;
            };
            if l == s.line {
                return;
            }
            let up = sample.kind() == SampleKind::Put;
            let line = l.to_owned();
            let _ = match s.interests.seen((line.clone(), filter.clone()), slot, up) {
                Some(true) => s.events.send(Event::InterestAdded { line, filter }),
                Some(false) => s.events.send(Event::InterestRemoved { line, filter }),
                None => Ok(()),
            };
        };
        session
            .liveliness()
            .declare_subscriber(format!("{}/interest/**", keys::CONTROL))
            .history(true)
            .callback(on_interest)
            .background()
            .wait()
            .map_err(zerr)?;
        let shared = Arc::downgrade(&self.0);
        let on_record = move |sample: zenoh::sample::Sample| {
            let Some(s) = shared.upgrade() else { return };
            let Some((l, device)) = keys::parse_line_item("record", sample.key_expr().as_str())
            else {
                return;
            };
            if l == s.line {
                return;
            }
            let version = sample
                .attachment()
                .and_then(|a| decode_version(&a.to_bytes()));
            if s.records
                .as_ref()
                .is_some_and(|r| !r.newer(l, device, version))
            {
                return;
            }
            let _ = s.events.send(match sample.kind() {
                SampleKind::Put => Event::Record {
                    line: l.to_owned(),
                    device: device.to_owned(),
                    json: sample.payload().to_bytes().into_owned(),
                },
                SampleKind::Delete => Event::Forgotten {
                    line: l.to_owned(),
                    device: device.to_owned(),
                },
            });
        };
        session
            .declare_subscriber(format!("{}/record/**", keys::CONTROL))
            .callback(on_record)
            .background()
            .wait()
            .map_err(zerr)?;
        let shared = Arc::downgrade(&self.0);
        let on_loss = move |sample: zenoh::sample::Sample| {
            let Some(s) = shared.upgrade() else { return };
            let Some((receiver, origin)) =
                keys::parse_line_item("loss", sample.key_expr().as_str())
            else {
                return;
            };
            let Some(report) = LossReport::decode(&sample.payload().to_bytes()) else {
                return;
            };
            if origin != s.line || receiver == s.line {
                return;
            }
            let lost = s
                .reported
                .lock()
                .unwrap_or_else(PoisonError::into_inner)
                .take(receiver, report, s.exported.load(Ordering::Relaxed));
            if lost > 0 {
                let line = receiver.to_owned();
                let _ = s.events.send(Event::LossReported { line, lost });
            }
        };
        session
            .declare_subscriber(keys::loss_key("*", &self.0.line))
            .callback(on_loss)
            .background()
            .wait()
            .map_err(zerr)
    }

    fn serve_records_on(&self, session: &Session, records: Records) -> Result<(), LinkError> {
        let line = self.0.line.clone();
        session
            .declare_queryable(format!("{}/record/{line}/*", keys::CONTROL))
            .callback(move |query: Query| {
                let asked = keys::parse_line_item("record", query.key_expr().as_str())
                    .map(|(_, device)| device)
                    .filter(|device| !device.contains(['*', '$']));
                for (device, json) in records(asked) {
                    let Ok(k) = KeyExpr::try_from(keys::record_key(&line, &device)) else {
                        continue;
                    };
                    if query.key_expr().intersects(&k) {
                        let _ = query.reply(k, json).wait();
                    }
                }
            })
            .background()
            .wait()
            .map_err(zerr)
    }

    /// A subscriber to `key` whose samples go to the link's inbox, and the interest token
    /// for `filter`, on `session`.
    fn import_on(
        &self,
        session: &Session,
        key: &str,
        filter: &str,
    ) -> Result<(Subscriber<()>, LivelinessToken), LinkError> {
        let (inbox, own) = (self.0.inbox.clone(), self.0.line.clone());
        let subscriber = session
            .declare_subscriber(key.to_owned())
            .callback(move |sample| {
                let Some((line, topic)) = keys::parse_data_key(sample.key_expr().as_str()) else {
                    return;
                };
                let Some(stamp) = sample
                    .attachment()
                    .and_then(|a| Stamp::decode(&a.to_bytes()))
                else {
                    tracing::debug!(key = %sample.key_expr(), "bus sample without an fbbus stamp; ignored");
                    return;
                };
                // The stamp naming another line than the key is refused (and counted) by
                // the importing broker, which also drops the copies that came through
                // another router (`Dedup`).
                if line == own {
                    return;
                }
                let _ = inbox.send(Inbound {
                    line: line.to_owned(),
                    stamp,
                    topic: topic.to_owned(),
                    payload: sample.payload().to_bytes().into_owned(),
                });
            })
            .wait()
            .map_err(zerr)?;
        let token = session
            .liveliness()
            .declare_token(keys::interest_token(&self.0.line, filter))
            .wait()
            .map_err(zerr)?;
        Ok((subscriber, token))
    }
}

fn line_token_on(session: &Session, line: &str) -> Result<LivelinessToken, LinkError> {
    session
        .liveliness()
        .declare_token(keys::line_token(line))
        .wait()
        .map_err(zerr)
}

/// Other lines' queries for `line`'s retained messages, on `session`, into `tx`. A full
/// queue blocks zenoh's receive path, as zenoh's own channel handler would.
fn serve_retained_on(
    session: &Session,
    line: &str,
    tx: flume::Sender<Query>,
) -> Result<(), LinkError> {
    session
        .declare_queryable(keys::retained_queryable(line))
        .callback(move |query| {
            let _ = tx.send(query);
        })
        .background()
        .wait()
        .map_err(zerr)
}

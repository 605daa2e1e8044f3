//! Which connection owns each client id, and each client's session number.
//!
//! Every accepted CONNECT gets the next session number of its client id. When rumqttd's
//! router drops a link, the connection compares its number with the current one: a newer
//! number means another connection took the client id over (MQTT session takeover);
//! the same number means the router itself ended the link. The number is the Sparkplug
//! `bdSeq` idea: the device registry uses it so that a late will from an old session never
//! marks a newer session offline.
//!
//! The number also makes MQTT 5 session expiry simple: when a session's expiry is due,
//! it is ended only if its number is still the newest and nobody is connected with it
//! ([`SessionTable::with_idle`]); a client that came back in time has a newer number.
//!
//! **Bounded.** Numbers come from one counter for all client ids, so a client id needs no
//! entry to be numbered above its past sessions: the table holds only the connected
//! clients (at most `max_connections`) and the offline sessions the router keeps, at most
//! `limit` of them, the oldest closed dropped first, as the router drops its saved
//! sessions (`router::saved_sessions_limit`). A clean session leaves nothing. The expiry
//! deadlines of the offline sessions live here too, served by one task
//! ([`SessionTable::due`]) instead of a sleeping task per session. Before, every client
//! id ever seen stayed (~350 bytes each, found by `fbbus-loadtest churn`), and every MQTT
//! 5 session with an expiry left a task asleep for that long.
//!
//! **Owned** (issue 20). Each entry records the identity that created the session
//! ([`Owner`]), connected or kept offline, and [`SessionTable::open`] refuses a client id
//! whose entry belongs to another identity, atomically with taking the session number:
//! two CONNECTs racing for one client id cannot both pass. A refused CONNECT changes
//! nothing here. An offline entry dropped at the limit takes the router's saved session
//! with it (the eviction hook, [`SessionTable::evicting`], run with the table held): the
//! router drops its oldest saved session by its own order, which may differ, and a
//! session the router kept without an owner here could be resumed by anyone.
//!
//! **Per identity** (issue 21). Each entry may name the identity it is counted for (the
//! username, or the peer address of an anonymous client: `connect.rs`), and
//! [`SessionTable::open_counted`] refuses a CONNECT that would give that identity more
//! than `[broker] max_sessions_per_identity` entries, connected and kept offline,
//! atomically with the rest of `open`. Taking over or resuming one's own session adds
//! nothing.
//!
//! **Linked.** Each connected entry keeps its link's [`Nudge`] once linked
//! ([`SessionTable::linked`]), and `open` returns the one of the connection it supersedes:
//! the new connection asks the old one to finish reading before it links (`takeover`).

use std::collections::{BTreeMap, HashMap};
use std::sync::{Arc, Mutex, PoisonError};
use std::time::Duration;

use rumqttd::local::Nudge;
use tokio::time::Instant;

use crate::identity::Owner;

/// What is done with a client id whose offline session left the table at the limit.
type Evict = Box<dyn Fn(&str) + Send + Sync>;

pub struct SessionTable {
    inner: Mutex<Inner>,
    /// Offline sessions kept at most.
    limit: usize,
    evicted: Evict,
}

#[derive(Default)]
struct Inner {
    /// The last session number given out, to any client id.
    last: u64,
    clients: HashMap<String, Client>,
    /// The offline sessions, by the order they closed (oldest first).
    offline: BTreeMap<u64, String>,
    closes: u64,
    /// The offline sessions' expiry deadlines.
    expiries: BTreeMap<(Instant, u64), String>,
    /// Entries (connected and offline) by the identity they are counted for.
    per_identity: HashMap<Arc<str>, usize>,
}

struct Client {
    /// Who created the session: only this identity may connect with the client id.
    owner: Owner,
    /// The client id's latest session number.
    latest: u64,
    /// Whether that session is connected.
    connected: bool,
    /// While offline: its place in `offline`, and in `expiries` if it expires.
    closed: Option<(u64, Option<Instant>)>,
    /// The identity this entry counts for (`per_identity`), if any.
    counted: Option<Arc<str>>,
    /// The connected session's link, once linked (`takeover`).
    nudge: Option<Nudge>,
}

/// The connection a new one supersedes, still running when the new one opened.
#[derive(Debug)]
pub struct Running {
    /// Its session number.
    pub session: u64,
    /// Its link, if it was linked yet: to ask it to finish reading (`takeover`).
    pub nudge: Option<Nudge>,
}

/// Why [`SessionTable::open_counted`] refused a CONNECT.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum Refusal {
    /// The client id's session belongs to another identity.
    Owned(Owned),
    /// The identity holds `max_sessions_per_identity` sessions already.
    Quota,
}

/// A CONNECT's client id belongs to another identity's session.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Owned {
    /// That session is connected (else it is kept offline).
    pub connected: bool,
}

/// One session as [`SessionTable::list`] shows it.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Listed {
    pub client_id: String,
    pub owner: Owner,
    pub session: u64,
    pub connected: bool,
    /// A kept session's time left, if it expires.
    pub expires_in: Option<Duration>,
}

/// What remains of a session once its connection ended.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Remains {
    /// Nothing: a clean session, or one the router refused.
    Nothing,
    /// The router keeps it, forever (`None`) or until it expires.
    Kept(Option<Duration>),
}

impl SessionTable {
    /// A table keeping at most `limit` offline sessions.
    pub fn new(limit: usize) -> SessionTable {
        SessionTable {
            inner: Mutex::default(),
            limit,
            evicted: Box::new(|_| ()),
        }
    }

    /// Runs `hook` with each client id whose offline session is dropped at the limit,
    /// with the table held: no connection of that client id starts before it returns.
    pub fn evicting(mut self, hook: impl Fn(&str) + Send + Sync + 'static) -> SessionTable {
        self.evicted = Box::new(hook);
        self
    }

    /// The table, also after a panic elsewhere left the lock poisoned: every update below
    /// leaves it consistent before it could panic.
    fn inner(&self) -> std::sync::MutexGuard<'_, Inner> {
        self.inner.lock().unwrap_or_else(PoisonError::into_inner)
    }

    /// Registers a new connection of `owner` for `client_id`; returns its session number,
    /// and the previous connection of that client id if it is still running (has not
    /// closed yet). Refused, changing nothing, when the client id's connected or kept
    /// session belongs to another identity.
    /// (Not counted for any identity: never `Refusal::Quota`.)
    pub fn open(&self, client_id: &str, owner: &Owner) -> Result<(u64, Option<Running>), Refusal> {
        self.open_counted(client_id, owner, None, None)
    }

    /// [`SessionTable::open`], the entry counted for `identity`; with `max`, also refused
    /// when it would give `identity` more than `max` entries (taking over or resuming an
    /// entry already counted for it adds none). Refused, changing nothing.
    pub fn open_counted(
        &self,
        client_id: &str,
        owner: &Owner,
        identity: Option<&str>,
        max: Option<usize>,
    ) -> Result<(u64, Option<Running>), Refusal> {
        let mut inner = self.inner();
        let existing = inner.clients.get(client_id);
        if let Some(other) = existing.filter(|c| c.owner != *owner) {
            return Err(Refusal::Owned(Owned {
                connected: other.connected,
            }));
        }
        if let (Some(identity), Some(max)) = (identity, max) {
            let adds = existing.is_none_or(|c| c.counted.as_deref() != Some(identity));
            let held = inner.per_identity.get(identity).copied().unwrap_or(0);
            if adds && held >= max {
                return Err(Refusal::Quota);
            }
        }
        inner.last += 1;
        let session = inner.last;
        let counted: Option<Arc<str>> = identity.map(Arc::from);
        if let Some(identity) = &counted {
            *inner.per_identity.entry(Arc::clone(identity)).or_default() += 1;
        }
        let previous = inner.clients.insert(
            client_id.to_owned(),
            Client {
                owner: owner.clone(),
                latest: session,
                connected: true,
                closed: None,
                counted,
                nudge: None,
            },
        );
        let running = previous.as_ref().filter(|c| c.connected).map(|c| Running {
            session: c.latest,
            nudge: c.nudge.clone(),
        });
        if let Some(previous) = previous {
            inner.forget(&previous);
        }
        Ok((session, running))
    }

    /// The connection `session` of `client_id` is linked: a connection that takes it over
    /// nudges it through `nudge`. Nothing when a newer connection took the entry already.
    pub fn linked(&self, client_id: &str, session: u64, nudge: Nudge) {
        if let Some(client) = self
            .inner()
            .clients
            .get_mut(client_id)
            .filter(|c| c.latest == session)
        {
            client.nudge = Some(nudge);
        }
    }

    /// `client_id`'s newest session number, whether it is connected, and its owner.
    pub fn state(&self, client_id: &str) -> Option<(u64, bool, Owner)> {
        self.inner()
            .clients
            .get(client_id)
            .map(|c| (c.latest, c.connected, c.owner.clone()))
    }

    /// The sessions whose client ids sort after `after`, at most `limit`, in client id
    /// order; and how many sessions the table holds. For the operator (`control`): the
    /// table is held only to copy the entries after `after`, sorted once released.
    pub fn list(&self, after: &str, limit: usize) -> (Vec<Listed>, usize) {
        let now = Instant::now();
        let (mut listed, total) = {
            let inner = self.inner();
            let listed: Vec<Listed> = inner
                .clients
                .iter()
                .filter(|(id, _)| id.as_str() > after)
                .map(|(id, c)| Listed {
                    client_id: id.clone(),
                    owner: c.owner.clone(),
                    session: c.latest,
                    connected: c.connected,
                    expires_in: c
                        .closed
                        .and_then(|(_, at)| at)
                        .map(|at| at.saturating_duration_since(now)),
                })
                .collect();
            (listed, inner.clients.len())
        };
        listed.sort_unstable_by(|a, b| a.client_id.cmp(&b.client_id));
        listed.truncate(limit);
        (listed, total)
    }

    /// Whether `client_id` has a session, connected or kept.
    pub fn holds(&self, client_id: &str) -> bool {
        self.inner().clients.contains_key(client_id)
    }

    /// Entries counted for `identity` now.
    #[cfg(test)]
    pub fn held_by(&self, identity: &str) -> usize {
        self.inner()
            .per_identity
            .get(identity)
            .copied()
            .unwrap_or(0)
    }

    /// Numbers sessions above `session` from now on (from the persisted registry).
    pub fn seed(&self, session: u64) {
        let mut inner = self.inner();
        inner.last = inner.last.max(session);
    }

    /// Whether `session` is still the newest session of `client_id`.
    pub fn is_current(&self, client_id: &str, session: u64) -> bool {
        self.inner()
            .clients
            .get(client_id)
            .is_some_and(|c| c.latest == session)
    }

    /// Runs `f` if `session` is the newest session of `client_id` and not connected, with
    /// the table held, so no connection of that client id starts while `f` runs; the
    /// session is then ended (`f` ends it in the router) and leaves the table.
    pub fn with_idle<R>(&self, client_id: &str, session: u64, f: impl FnOnce() -> R) -> Option<R> {
        let mut inner = self.inner();
        match inner.clients.get(client_id) {
            Some(c) if c.latest == session && !c.connected => {}
            _ => return None,
        }
        let result = f();
        if let Some(ended) = inner.clients.remove(client_id) {
            inner.forget(&ended);
        }
        Some(result)
    }

    /// The connection of `session` ended, leaving what `remains`.
    pub fn close(&self, client_id: &str, session: u64, remains: Remains) {
        self.close_with(client_id, session, remains, |_| ());
    }

    /// `SessionTable::close`, running `f(superseded)` with the table held: `superseded`
    /// says a newer connection of `client_id` has started. No connection of the client id
    /// starts while `f` runs, so what `f` hands over is either there before the newer
    /// connection's [`SessionTable::open`] (which then reports no running predecessor), or
    /// handed over knowing it is awaited (`redelivery`).
    pub fn close_with<R>(
        &self,
        client_id: &str,
        session: u64,
        remains: Remains,
        f: impl FnOnce(bool) -> R,
    ) -> R {
        let mut inner = self.inner();
        let superseded = match inner.clients.get(client_id) {
            Some(c) => c.latest != session,
            None => true,
        };
        if !superseded {
            match remains {
                Remains::Nothing => {
                    if let Some(ended) = inner.clients.remove(client_id) {
                        inner.forget(&ended);
                    }
                }
                Remains::Kept(expires_after) => {
                    inner.keep(client_id, expires_after, self.limit, &self.evicted)
                }
            }
        }
        f(superseded)
    }

    /// Sessions whose expiry is due at `now`: (client id, session) to end with
    /// `lifetime::end_idle_session`. They stay in the table until then.
    pub fn due(&self, now: Instant) -> Vec<(String, u64)> {
        let mut inner = self.inner();
        let mut due = Vec::new();
        while let Some(entry) = inner.expiries.first_entry() {
            if entry.key().0 > now {
                break;
            }
            let ((_, session), client_id) = entry.remove_entry();
            due.push((client_id, session));
        }
        due
    }

    /// (connected, offline) sessions in the table.
    #[cfg(test)]
    pub fn len(&self) -> (usize, usize) {
        let inner = self.inner();
        let offline = inner.offline.len();
        (inner.clients.len() - offline, offline)
    }
}

impl Inner {
    /// `client_id`'s current session went offline and is kept.
    fn keep(
        &mut self,
        client_id: &str,
        expires_after: Option<Duration>,
        limit: usize,
        evicted: &Evict,
    ) {
        self.closes += 1;
        let order = self.closes;
        let Some(client) = self.clients.get_mut(client_id) else {
            return;
        };
        let expiry = expires_after.map(|after| Instant::now() + after);
        client.connected = false;
        client.closed = Some((order, expiry));
        let session = client.latest;
        self.offline.insert(order, client_id.to_owned());
        if let Some(at) = expiry {
            self.expiries.insert((at, session), client_id.to_owned());
        }
        while self.offline.len() > limit {
            let Some((_, oldest)) = self.offline.pop_first() else {
                break;
            };
            if let Some(dropped) = self.clients.remove(&oldest) {
                self.forget(&dropped);
            }
            evicted(&oldest);
        }
    }

    /// `client` left the table: its count, and its offline places.
    fn forget(&mut self, client: &Client) {
        if let Some(identity) = &client.counted {
            if let Some(held) = self.per_identity.get_mut(identity) {
                *held = held.saturating_sub(1);
                if *held == 0 {
                    self.per_identity.remove(identity);
                }
            }
        }
        self.forget_closed(client);
    }

    /// The places of `client`'s offline session in `offline` and `expiries`, if it had
    /// one, are gone (it left the table).
    fn forget_closed(&mut self, client: &Client) {
        if let Some((order, expiry)) = client.closed {
            self.offline.remove(&order);
            if let Some(at) = expiry {
                self.expiries.remove(&(at, client.latest));
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn open(t: &SessionTable, client_id: &str) -> (u64, bool) {
        let (session, running) = t
            .open(client_id, &Owner::Anonymous)
            .expect("anonymous owns these");
        (session, running.is_some())
    }

    #[test]
    fn sessions_are_listed_in_pages_by_client_id() {
        let t = SessionTable::new(10);
        let user = Owner::User(Arc::from("devA"));
        let (b, _) = t.open("devB", &user).unwrap();
        t.close("devB", b, Remains::Kept(Some(Duration::from_secs(60))));
        open(&t, "a-plc");
        open(&t, "c-plc");
        let (page, total) = t.list("", 2);
        assert_eq!(total, 3);
        let ids: Vec<&str> = page.iter().map(|l| l.client_id.as_str()).collect();
        assert_eq!(ids, ["a-plc", "c-plc"]);
        assert!(page[0].connected && page[0].expires_in.is_none());
        let (rest, _) = t.list("c-plc", 2);
        assert_eq!(rest.len(), 1);
        assert_eq!(rest[0].client_id, "devB");
        assert_eq!(rest[0].owner, user);
        assert!(!rest[0].connected);
        assert!(rest[0]
            .expires_in
            .is_some_and(|d| d <= Duration::from_secs(60)));
        assert_eq!(t.state("devB"), Some((b, false, user)));
        assert_eq!(t.state("nobody"), None);
    }

    #[test]
    fn a_newer_session_makes_the_older_one_stale() {
        let t = SessionTable::new(10);
        let kept = Remains::Kept(None);
        let (a, running) = open(&t, "plc");
        assert!(!running);
        assert!(t.is_current("plc", a));
        let (b, running) = open(&t, "plc");
        assert!(b > a);
        assert!(running, "a has not closed");
        assert!(!t.is_current("plc", a));
        t.close("plc", a, kept);
        assert!(t.is_current("plc", b));
        assert_eq!(t.with_idle("plc", b, || ()), None, "connected");
        t.close("plc", b, kept);
        assert_eq!(t.with_idle("plc", a, || 7), None, "stale");
        assert!(
            t.close_with("plc", a, kept, |superseded| superseded),
            "b is newer"
        );
        assert_eq!(t.with_idle("plc", b, || 7), Some(7));
        assert_eq!(t.len(), (0, 0), "an ended session leaves the table");
        let (c, running) = open(&t, "plc");
        assert!(c > b && !running);
    }

    /// Issue 21: at most `max` entries per identity, connected and kept offline; one's own
    /// takeover adds none; an entry leaving gives its place back.
    #[test]
    fn sessions_per_identity_are_bounded() {
        let t = SessionTable::new(10);
        let open = |id: &str, who: &str| {
            t.open_counted(id, &Owner::Anonymous, Some(who), Some(2))
                .map(|(session, running)| (session, running.is_some()))
        };
        let (a, _) = open("a", "10.0.0.1").unwrap();
        let (b, _) = open("b", "10.0.0.1").unwrap();
        assert_eq!(open("c", "10.0.0.1"), Err(Refusal::Quota));
        assert_eq!(t.held_by("10.0.0.1"), 2);
        // Another identity, and a takeover of one's own client id, are not refused.
        assert!(open("c", "10.0.0.2").is_ok());
        let (a2, running) = open("a", "10.0.0.1").unwrap();
        assert!(running);
        assert_eq!(t.held_by("10.0.0.1"), 2);
        t.close("a", a, Remains::Nothing);
        // A kept session still counts; a clean one's end gives its place back.
        t.close("a", a2, Remains::Kept(None));
        assert_eq!(open("c2", "10.0.0.1"), Err(Refusal::Quota));
        t.close("b", b, Remains::Nothing);
        assert_eq!(t.held_by("10.0.0.1"), 1);
        assert!(open("c2", "10.0.0.1").is_ok());
        // Taking a client id counted for another identity adds one: refused at the limit.
        assert_eq!(open("c", "10.0.0.1"), Err(Refusal::Quota));
        assert_eq!(t.held_by("10.0.0.2"), 1);
    }

    /// Issue 14: a clean session leaves nothing, and numbers still grow per client id.
    #[test]
    fn clean_sessions_leave_nothing() {
        let t = SessionTable::new(10);
        let mut last = 0;
        for i in 0..1000 {
            let id = format!("client-{}", i % 7);
            let (session, _) = open(&t, &id);
            assert!(session > last);
            last = session;
            t.close(&id, session, Remains::Nothing);
        }
        assert_eq!(t.len(), (0, 0));
        t.seed(5000);
        assert_eq!(open(&t, "x").0, 5001);
    }

    /// Issue 14: at most `limit` offline sessions, the oldest closed dropped first, with
    /// their expiries.
    #[tokio::test(start_paused = true)]
    async fn offline_sessions_are_bounded_oldest_first() {
        let t = SessionTable::new(3);
        let mut sessions = Vec::new();
        for id in ["a", "b", "c", "d"] {
            let (s, _) = open(&t, id);
            sessions.push(s);
            t.close(id, s, Remains::Kept(Some(Duration::from_secs(60))));
        }
        assert_eq!(t.len(), (0, 3));
        assert!(
            !t.is_current("a", sessions[0]),
            "a, the oldest, was dropped"
        );
        assert!(t.is_current("d", sessions[3]));
        // "b" comes back: connected, no longer offline, its expiry gone.
        let (b2, running) = open(&t, "b");
        assert!(!running);
        assert_eq!(t.len(), (1, 2));
        tokio::time::advance(Duration::from_secs(61)).await;
        let mut due = t.due(Instant::now());
        due.sort();
        assert_eq!(
            due,
            vec![("c".to_owned(), sessions[2]), ("d".to_owned(), sessions[3])]
        );
        assert!(t.due(Instant::now()).is_empty());
        assert_eq!(t.with_idle("c", sessions[2], || ()), Some(()));
        assert_eq!(t.len(), (1, 1));
        t.close("b", b2, Remains::Nothing);
        assert_eq!(t.len(), (0, 1));
    }

    /// Issue 20: a client id's session, connected or kept, belongs to its identity.
    #[test]
    fn another_identity_is_refused_and_changes_nothing() {
        let t = SessionTable::new(10);
        let dev_b = Owner::User("devB".into());
        let dev_a = Owner::User("devA".into());
        let (b1, _) = t.open("devB", &dev_b).unwrap();
        assert_eq!(
            t.open("devB", &dev_a).err(),
            Some(Refusal::Owned(Owned { connected: true }))
        );
        assert_eq!(
            t.open("devB", &Owner::Anonymous).err(),
            Some(Refusal::Owned(Owned { connected: true }))
        );
        assert!(
            t.is_current("devB", b1),
            "the refusal took no session number"
        );
        t.close("devB", b1, Remains::Kept(None));
        assert_eq!(
            t.open("devB", &dev_a).err(),
            Some(Refusal::Owned(Owned { connected: false }))
        );
        assert_eq!(t.len(), (0, 1), "the kept session is still there");
        // The owner itself takes its session back.
        let (b2, running) = t.open("devB", &dev_b).unwrap();
        assert!(b2 > b1 && running.is_none());
        // A clean session leaves nothing: the client id is free again.
        t.close("devB", b2, Remains::Nothing);
        assert!(t.open("devB", &dev_a).is_ok());
    }

    /// Issue 20: an offline entry dropped at the limit is handed to the eviction hook (which
    /// ends the router's saved session), with the table held.
    #[test]
    fn evicted_sessions_are_reported() {
        let evicted = std::sync::Arc::new(Mutex::new(Vec::new()));
        let t = SessionTable::new(2).evicting({
            let evicted = evicted.clone();
            move |id| evicted.lock().unwrap().push(id.to_owned())
        });
        for id in ["a", "b", "c", "d"] {
            let (s, _) = open(&t, id);
            t.close(id, s, Remains::Kept(None));
        }
        assert_eq!(*evicted.lock().unwrap(), ["a", "b"]);
        assert_eq!(t.len(), (0, 2));
    }
}

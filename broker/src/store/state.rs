//! What the store holds, rebuilt from the log's records: retained messages, persistent
//! sessions with their subscriptions and queued messages, delayed wills.
//!
//! The same [`State::apply`] replays the log at start and follows the writer thread as it
//! appends, so compaction writes what replay would rebuild. Queues are computed here, off
//! the packet path: a `Publish` record names no session; it is queued for every persistent
//! session whose subscriptions match it at that point of the log, at the delivery QoS
//! (min of the publication's and the best matching subscription's), unless every matching
//! subscription is No Local and the session published it. A `Done` takes it off again.
//!
//! Bounded: at most `max_queued` messages per session, `share_bytes` and `share_messages`
//! queued for the sessions of one identity (issue 33: shares, not one pool), and
//! `max_bytes` of messages in all (a message queued for n sessions counts n times); beyond
//! any of them, a message is not stored for that session (or, for a retained message, not
//! stored), and counted. What a publisher must hear of ([`Refused`]) is listed by message
//! number in [`Drops::refused`].

use std::collections::{BTreeMap, HashMap};
use std::sync::Arc;

use super::queue::{Queue, Queued};
use super::record::{ClientId, Message, Options, Qos2, Record, Target};

/// Limits on what the store keeps.
#[derive(Debug, Clone, Copy)]
pub struct Limits {
    pub max_bytes: usize,
    pub max_queued: usize,
    /// The router's bounds on retained messages (`[broker] max_retained_messages`,
    /// `max_retained_bytes`), applied here the same way, so the store keeps what the
    /// router keeps and a restart brings back the same set: a retained message on a new
    /// topic beyond either is not stored; replacing and clearing always work; the broker's
    /// own topics are not counted.
    pub max_retained: usize,
    pub max_retained_bytes: usize,
    /// Bytes and messages queued for the persistent sessions of one identity at most
    /// (`[persistence] max_bytes_per_identity`, `max_messages_per_identity`).
    pub share_bytes: usize,
    pub share_messages: usize,
}

/// What the persistent sessions of one identity hold in the store.
#[derive(Debug, Default, Clone, Copy, PartialEq, Eq)]
pub struct Usage {
    pub bytes: usize,
    pub messages: usize,
}

#[derive(Debug, Clone)]
pub struct StoredSession {
    pub owner: String,
    /// The identity whose share its queue spends (`Record::Session`'s `share`).
    pub share: Arc<str>,
    pub v5: bool,
    pub expiry: Option<u32>,
    /// Unix seconds since it is offline; None while connected.
    pub offline_at: Option<u64>,
    pub subscriptions: BTreeMap<String, Options>,
    pub queue: Queue,
}

impl StoredSession {
    /// What its queue spends of its identity's share.
    fn usage(&self) -> Usage {
        Usage {
            bytes: self.queue.iter().map(|(_, q)| q.message.size()).sum(),
            messages: self.queue.len(),
        }
    }
}

/// Why a message was not stored.
#[derive(Debug, Default, Clone, PartialEq, Eq)]
pub struct Drops {
    pub session_queue_full: u64,
    pub store_full: u64,
    pub identity_share: u64,
    pub retained_limit: u64,
    /// Stored publications not kept for some session, by message number, in the order
    /// met: what the writer tells their publishers (`writer`).
    pub refused: Vec<(u64, Refused)>,
}

/// Why a publication was not kept where a publisher may have to hear of it.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum Refused {
    /// `max_bytes`: the store is full. Every publisher hears of it.
    StoreFull,
    /// The share of this identity, whose session it was for, is spent. Only a publisher
    /// of that identity hears of it: another identity's full sessions are their loss, as
    /// a session over `max_queued` is, not the publisher's.
    Share(Arc<str>),
}

/// Which persistent sessions subscribe to what, as a tree of topic levels, so that finding
/// the sessions a publication is queued for costs its levels and the sessions that match,
/// not every subscription of every session. Each entry carries what queueing needs of the
/// subscription's options, so a match is final: no filter is matched twice.
#[derive(Default)]
struct Subscribers {
    /// Sessions whose filter ends at this node.
    here: BTreeMap<ClientId, Wanted>,
    /// Sessions with `#` below this node (it matches this level too).
    rest: BTreeMap<ClientId, Wanted>,
    plus: Option<Box<Subscribers>>,
    /// foldhash, not SipHash: looked up for every level of every stored publication. Its
    /// keys are the levels of persistent sessions' filters, which `max_subscriptions` and
    /// the session limits bound, and its seed is random: no flood of colliding names.
    levels: HashMap<String, Subscribers, foldhash::fast::RandomState>,
}

/// What a session's matching subscriptions ask of a publication: the best QoS among them,
/// and whether all of them are No Local.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
struct Wanted {
    qos: u8,
    no_local: bool,
}

impl Wanted {
    fn and(self, other: Wanted) -> Wanted {
        Wanted {
            qos: self.qos.max(other.qos),
            no_local: self.no_local && other.no_local,
        }
    }
}

impl Subscribers {
    fn node(&mut self, filter: &str) -> (&mut Subscribers, bool) {
        let mut node = self;
        let mut levels = filter.split('/').peekable();
        while let Some(level) = levels.next() {
            if level == "#" && levels.peek().is_none() {
                return (node, true);
            }
            node = match level {
                "+" => node.plus.get_or_insert_with(Box::default),
                _ => node.levels.entry(level.to_owned()).or_default(),
            };
        }
        (node, false)
    }

    /// Adds or replaces (a SUBSCRIBE to a filter the session has) the session's entry.
    fn insert(&mut self, filter: &str, client: &ClientId, options: &Options) {
        let (node, rest) = self.node(filter);
        let wanted = Wanted {
            qos: options.qos,
            no_local: options.no_local,
        };
        match rest {
            true => node.rest.insert(Arc::clone(client), wanted),
            false => node.here.insert(Arc::clone(client), wanted),
        };
    }

    /// Removes the entry (empty nodes stay: a session's filters are few and bounded).
    fn remove(&mut self, filter: &str, client: &str) {
        let (node, rest) = self.node(filter);
        match rest {
            true => node.rest.remove(client),
            false => node.here.remove(client),
        };
    }

    /// The sessions with a filter matching `topic`, with what their matching filters ask
    /// together (MQTT 4.7: a filter starting with a wildcard does not match a topic
    /// starting with `$`), into `out`. In client id order: replay decides as the writer did.
    fn matching(&self, topic: &str, out: &mut Vec<(ClientId, Wanted)>) {
        out.clear();
        let mut levels = topic.split('/');
        // `$` topics and the re-encoded copies: not for filters starting with a wildcard.
        let hidden = topic.starts_with('$') || fb_bridge::topic::is_mirror(topic);
        self.walk(&mut levels, hidden, out);
        if out.len() > 1 {
            out.sort_by(|a, b| a.0.cmp(&b.0));
            // One entry per session: its matching filters together.
            out.dedup_by(|later, kept| {
                let same = later.0 == kept.0;
                if same {
                    kept.1 = kept.1.and(later.1);
                }
                same
            });
        }
    }

    fn walk<'t>(
        &self,
        levels: &mut (impl Iterator<Item = &'t str> + Clone),
        dollar: bool,
        out: &mut Vec<(ClientId, Wanted)>,
    ) {
        if !dollar {
            add(out, &self.rest);
        }
        let Some(first) = levels.next() else {
            add(out, &self.here);
            return;
        };
        if let (Some(plus), false) = (&self.plus, dollar) {
            plus.walk(&mut levels.clone(), false, out);
        }
        if let Some(next) = self.levels.get(first) {
            next.walk(levels, false, out);
        }
    }
}

fn add(out: &mut Vec<(ClientId, Wanted)>, entries: &BTreeMap<ClientId, Wanted>) {
    out.extend(entries.iter().map(|(c, w)| (Arc::clone(c), *w)));
}

#[derive(Default)]
pub struct State {
    pub retained: BTreeMap<Vec<u8>, Arc<Message>>,
    pub sessions: HashMap<ClientId, StoredSession>,
    /// Sessions with at least one subscription.
    pub subscribed: usize,
    /// Delayed wills by client id (several when a typed will goes out in several encodings).
    pub wills: BTreeMap<ClientId, Vec<(u64, Arc<Message>)>>,
    /// Bytes of retained and queued messages (see the module doc).
    pub bytes: usize,
    /// The highest message number seen.
    pub last_seq: u64,
    /// Queued messages in all sessions.
    pub queued: usize,
    /// What each identity's sessions hold (entries with nothing queued are removed).
    pub shares: HashMap<Arc<str>, Usage>,
    /// The identity each retained message is charged to (`Record::RetainedBy`); only
    /// topics in `retained`, so bounded as it is.
    pub retained_by: HashMap<Vec<u8>, String>,
    /// Retained messages under the router's bounds, and their topic and payload bytes.
    retained_counted: usize,
    retained_counted_bytes: usize,
    subscribers: Subscribers,
    /// The sessions one publication matches, kept between publications (no allocation
    /// per message on the writer's path).
    matches: Vec<(ClientId, Wanted)>,
}

impl State {
    pub fn apply(&mut self, record: Record, limits: Limits, drops: &mut Drops) {
        match record {
            Record::Session {
                client,
                owner,
                share,
                v5,
                expiry,
                fresh,
            } => {
                if fresh {
                    self.end(&client);
                }
                // A kept session that comes back under another identity (the ownership
                // rule allows it only for the same owner) moves its queue along.
                if let Some(s) = self.sessions.get(&*client) {
                    if *s.share != *share {
                        let usage = s.usage();
                        let old = Arc::clone(&s.share);
                        self.unspend(&old, usage);
                        self.spend(&share, usage);
                    }
                }
                let share = self.share_key(&share);
                let s = self
                    .sessions
                    .entry(client)
                    .or_insert_with(|| StoredSession {
                        owner: String::new(),
                        share: Arc::clone(&share),
                        v5,
                        expiry,
                        offline_at: None,
                        subscriptions: BTreeMap::new(),
                        queue: Queue::default(),
                    });
                s.owner = owner;
                s.share = share;
                s.v5 = v5;
                s.expiry = expiry;
                s.offline_at = None;
            }
            Record::Offline { client, at, expiry } => {
                if let Some(s) = self.sessions.get_mut(&*client) {
                    s.offline_at = Some(at);
                    s.expiry = expiry;
                }
            }
            Record::Ended { client } => self.end(&client),
            Record::Subscribe {
                client,
                filter,
                options,
            } => {
                // The tree holds the state's own copy of the client id (the key of its
                // session), not the record's, which the session's task shares: the
                // writer clones it for every publication that matches.
                let Some(own) = self
                    .sessions
                    .get_key_value(&*client)
                    .map(|(k, _)| k.clone())
                else {
                    return;
                };
                if let Some(s) = self.sessions.get_mut(&*client) {
                    if !filter.starts_with("$share/") {
                        self.subscribers.insert(&filter, &own, &options);
                    }
                    self.subscribed += s.subscriptions.is_empty() as usize;
                    s.subscriptions.insert(filter, options);
                }
            }
            Record::Unsubscribe { client, filter } => {
                if let Some(s) = self.sessions.get_mut(&*client) {
                    if s.subscriptions.remove(&filter).is_some() {
                        self.subscribers.remove(&filter, &client);
                        self.subscribed -= s.subscriptions.is_empty() as usize;
                    }
                }
            }
            Record::Publish { seq, message } => {
                self.last_seq = self.last_seq.max(seq);
                let message = Arc::new(message);
                if message.retain {
                    self.retain(seq, &message, limits, drops);
                }
                if message.qos > 0 {
                    self.queue_for_subscribers(seq, &message, limits, drops);
                }
            }
            Record::Queued {
                seq,
                message,
                targets,
            } => {
                self.last_seq = self.last_seq.max(seq);
                let message = Arc::new(message);
                if message.retain && targets.is_empty() {
                    self.retain(0, &message, limits, drops);
                }
                for t in targets {
                    self.enqueue(&t.client, seq, &message, t.qos, t.qos2, limits, drops);
                }
            }
            Record::Done { client, seq } => self.done(&client, &[seq]),
            Record::Qos2 { client, seq, state } => {
                if let Some(q) = self
                    .sessions
                    .get_mut(&*client)
                    .and_then(|s| s.queue.get_mut(seq))
                {
                    q.qos2 = Some(state);
                }
            }
            Record::Will {
                client,
                due,
                message,
            } => {
                self.wills
                    .entry(client)
                    .or_default()
                    .push((due, Arc::new(message)));
            }
            Record::WillDone { client } => {
                self.wills.remove(&*client);
            }
            Record::RetainedBy { topic, share } => {
                if self.retained.contains_key(topic.as_bytes()) {
                    self.retained_by.insert(topic.into_bytes(), share);
                }
            }
        }
    }

    /// `client` is done with the stored messages `seqs` (its `Done` records).
    pub fn done(&mut self, client: &str, seqs: &[u64]) {
        let Some(s) = self.sessions.get_mut(client) else {
            return;
        };
        let (mut bytes, mut count) = (0, 0);
        for seq in seqs {
            if let Some(q) = s.queue.remove(*seq) {
                bytes += q.message.size();
                count += 1;
            }
        }
        self.bytes = self.bytes.saturating_sub(bytes);
        self.queued = self.queued.saturating_sub(count);
        let share = Arc::clone(&s.share);
        self.unspend(
            &share,
            Usage {
                bytes,
                messages: count,
            },
        );
    }

    /// The state's own copy of a share's name, shared by its sessions.
    fn share_key(&self, share: &str) -> Arc<str> {
        match self.shares.get_key_value(share) {
            Some((k, _)) => Arc::clone(k),
            None => share.into(),
        }
    }

    fn spend(&mut self, share: &str, usage: Usage) {
        if usage == Usage::default() {
            return;
        }
        let key = self.share_key(share);
        let u = self.shares.entry(key).or_default();
        u.bytes += usage.bytes;
        u.messages += usage.messages;
    }

    fn unspend(&mut self, share: &str, usage: Usage) {
        if let Some(u) = self.shares.get_mut(share) {
            u.bytes = u.bytes.saturating_sub(usage.bytes);
            u.messages = u.messages.saturating_sub(usage.messages);
            if u.messages == 0 {
                self.shares.remove(share);
            }
        }
    }

    fn end(&mut self, client: &str) {
        if let Some(s) = self.sessions.remove(client) {
            self.subscribed -= !s.subscriptions.is_empty() as usize;
            for f in s.subscriptions.keys() {
                self.subscribers.remove(f, client);
            }
            let usage = s.usage();
            self.bytes = self.bytes.saturating_sub(usage.bytes);
            self.queued = self.queued.saturating_sub(usage.messages);
            self.unspend(&s.share, usage);
        }
    }

    /// `seq`: the publication's number (0: restored from a snapshot, nobody to tell).
    fn retain(&mut self, seq: u64, message: &Arc<Message>, limits: Limits, drops: &mut Drops) {
        let counted = !crate::router::RETAINED_UNCOUNTED
            .iter()
            .any(|prefix| message.topic.starts_with(prefix.as_bytes()));
        let router_size = |m: &Message| m.topic.len() + m.payload.len();
        let old = self.retained.remove(message.topic.as_ref());
        self.retained_by.remove(message.topic.as_ref());
        if let Some(old) = &old {
            self.bytes = self.bytes.saturating_sub(old.size());
            if counted {
                self.retained_counted -= 1;
                self.retained_counted_bytes -= router_size(old);
            }
        }
        if message.payload.is_empty() {
            return;
        }
        // The router's rule (rumqttd `retain_refusal`): a new topic within the count and
        // the bytes; a replacement no larger always; a larger one within the bytes. A
        // refused replacement leaves the old value cleared, as in the router.
        let size = router_size(message);
        let over_bytes = self.retained_counted_bytes + size > limits.max_retained_bytes;
        let refused = match &old {
            Some(old) => size > router_size(old) && over_bytes,
            None => self.retained_counted >= limits.max_retained || over_bytes,
        };
        if counted && refused {
            drops.retained_limit += 1;
            return;
        }
        if self.bytes + message.size() > limits.max_bytes {
            drops.store_full += 1;
            if seq > 0 {
                drops.refused.push((seq, Refused::StoreFull));
            }
            return;
        }
        self.bytes += message.size();
        if counted {
            self.retained_counted += 1;
            self.retained_counted_bytes += router_size(message);
        }
        self.retained
            .insert(message.topic.to_vec(), Arc::clone(message));
    }

    fn queue_for_subscribers(
        &mut self,
        seq: u64,
        message: &Arc<Message>,
        limits: Limits,
        drops: &mut Drops,
    ) {
        let Ok(topic) = std::str::from_utf8(&message.topic) else {
            return;
        };
        let mut matches = std::mem::take(&mut self.matches);
        self.subscribers.matching(topic, &mut matches);
        for (client, wanted) in matches.drain(..) {
            if wanted.no_local && *message.publisher == *client {
                continue;
            }
            let qos = wanted.qos.min(message.qos);
            if qos > 0 {
                self.enqueue(&client, seq, message, qos, None, limits, drops);
            }
        }
        self.matches = matches;
    }

    #[allow(clippy::too_many_arguments)]
    fn enqueue(
        &mut self,
        client: &str,
        seq: u64,
        message: &Arc<Message>,
        qos: u8,
        qos2: Option<Qos2>,
        limits: Limits,
        drops: &mut Drops,
    ) {
        let Some(s) = self.sessions.get_mut(client) else {
            return;
        };
        if s.queue.len() >= limits.max_queued {
            drops.session_queue_full += 1;
            return;
        }
        let size = message.size();
        let spent = self.shares.get(&*s.share).copied().unwrap_or_default();
        if spent.bytes + size > limits.share_bytes || spent.messages >= limits.share_messages {
            drops.identity_share += 1;
            drops
                .refused
                .push((seq, Refused::Share(Arc::clone(&s.share))));
            return;
        }
        if self.bytes + size > limits.max_bytes {
            drops.store_full += 1;
            drops.refused.push((seq, Refused::StoreFull));
            return;
        }
        let queued = Queued {
            message: Arc::clone(message),
            qos,
            qos2,
        };
        if s.queue.insert(seq, queued) {
            self.bytes += size;
            self.queued += 1;
            let share = Arc::clone(&s.share);
            self.spend(
                &share,
                Usage {
                    bytes: size,
                    messages: 1,
                },
            );
        }
    }

    /// Records that rebuild this state: what compaction writes.
    pub fn snapshot(&self) -> Vec<Record> {
        let mut out = Vec::new();
        for (client, s) in &self.sessions {
            out.push(Record::Session {
                client: client.clone(),
                owner: s.owner.clone(),
                share: s.share.to_string(),
                v5: s.v5,
                expiry: s.expiry,
                fresh: true,
            });
            if let Some(at) = s.offline_at {
                out.push(Record::Offline {
                    client: client.clone(),
                    at,
                    expiry: s.expiry,
                });
            }
            for (f, o) in &s.subscriptions {
                out.push(Record::Subscribe {
                    client: client.clone(),
                    filter: f.clone(),
                    options: *o,
                });
            }
        }
        for m in self.retained.values() {
            out.push(Record::Queued {
                seq: 0,
                message: (**m).clone(),
                targets: Vec::new(),
            });
            if let (Some(share), Ok(topic)) = (
                self.retained_by.get(m.topic.as_ref()),
                std::str::from_utf8(&m.topic),
            ) {
                out.push(Record::RetainedBy {
                    topic: topic.to_owned(),
                    share: share.clone(),
                });
            }
        }
        let mut by_seq: BTreeMap<u64, (Arc<Message>, Vec<Target>)> = BTreeMap::new();
        for (client, s) in &self.sessions {
            for (seq, q) in s.queue.iter() {
                by_seq
                    .entry(seq)
                    .or_insert_with(|| (Arc::clone(&q.message), Vec::new()))
                    .1
                    .push(Target {
                        client: client.clone(),
                        qos: q.qos,
                        qos2: q.qos2,
                    });
            }
        }
        for (seq, (message, targets)) in by_seq {
            let mut message = (*message).clone();
            message.retain = false;
            out.push(Record::Queued {
                seq,
                message,
                targets,
            });
        }
        for (client, wills) in &self.wills {
            for (due, message) in wills {
                out.push(Record::Will {
                    client: client.clone(),
                    due: *due,
                    message: (**message).clone(),
                });
            }
        }
        out
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use bytes::Bytes;
    use fb_bridge::topic::filter;
    use std::collections::BTreeSet;

    const LIMITS: Limits = Limits {
        max_bytes: 1 << 20,
        max_queued: 3,
        max_retained: 4,
        max_retained_bytes: 1 << 20,
        share_bytes: 1 << 20,
        share_messages: 1 << 20,
    };

    fn session(client: &str) -> Record {
        Record::Session {
            client: client.into(),
            owner: String::new(),
            share: "anonymous".into(),
            v5: false,
            expiry: None,
            fresh: true,
        }
    }

    fn subscribe(client: &str, filter: &str, qos: u8, no_local: bool) -> Record {
        Record::Subscribe {
            client: client.into(),
            filter: filter.into(),
            options: Options {
                qos,
                no_local,
                retain_as_published: false,
                retain_handling: 0,
                id: 0,
            },
        }
    }

    fn publish(seq: u64, topic: &str, qos: u8, retain: bool, payload: &str) -> Record {
        Record::Publish {
            seq,
            message: Message {
                topic: Bytes::copy_from_slice(topic.as_bytes()),
                payload: Bytes::copy_from_slice(payload.as_bytes()),
                qos,
                retain,
                properties: None,
                publisher: "pub".into(),
            },
        }
    }

    fn state(records: Vec<Record>) -> (State, Drops) {
        let mut s = State::default();
        let mut d = Drops::default();
        for r in records {
            s.apply(r, LIMITS, &mut d);
        }
        (s, d)
    }

    fn queue(s: &State, client: &str) -> Vec<(u64, u8)> {
        s.sessions[client]
            .queue
            .iter()
            .map(|(seq, q)| (seq, q.qos))
            .collect()
    }

    #[test]
    fn messages_queue_at_the_delivery_qos_until_done() {
        let (s, _) = state(vec![
            session("a"),
            subscribe("a", "x/+", 1, false),
            subscribe("a", "x/#", 2, false),
            session("b"),
            subscribe("b", "x/1", 0, false),
            publish(1, "x/1", 2, false, "p"),
            publish(2, "x/1", 1, false, "p"),
            publish(3, "y", 1, false, "p"),
            publish(4, "x/1", 0, false, "p"),
            Record::Done {
                client: "a".into(),
                seq: 2,
            },
        ]);
        assert_eq!(queue(&s, "a"), vec![(1, 2)]);
        // A QoS 0 subscription queues nothing.
        assert!(queue(&s, "b").is_empty());
        assert_eq!(s.queued, 1);
    }

    #[test]
    fn limits_and_no_local_and_retained() {
        let (s, d) = state(vec![
            session("pub"),
            subscribe("pub", "#", 1, true),
            session("a"),
            subscribe("a", "#", 1, false),
            publish(1, "t", 1, true, "1"),
            publish(2, "t", 1, false, "2"),
            publish(3, "t", 1, false, "3"),
            publish(4, "t", 1, false, "4"),
        ]);
        assert!(queue(&s, "pub").is_empty(), "No Local");
        assert_eq!(queue(&s, "a"), vec![(1, 1), (2, 1), (3, 1)]);
        assert_eq!(d.session_queue_full, 1);
        assert_eq!(s.retained.len(), 1);
        // An empty retained publication clears it; a fresh session starts empty.
        let (s, _) = state(vec![
            session("a"),
            subscribe("a", "#", 1, false),
            publish(1, "t", 0, true, "1"),
            publish(2, "t", 0, true, ""),
            publish(3, "t", 1, false, "x"),
            session("a"),
        ]);
        assert!(s.retained.is_empty());
        assert!(queue(&s, "a").is_empty());
        assert_eq!((s.bytes, s.queued), (0, 0));
    }

    fn session_of(client: &str, share: &str) -> Record {
        Record::Session {
            client: client.into(),
            owner: String::new(),
            share: share.into(),
            v5: true,
            expiry: None,
            fresh: true,
        }
    }

    /// Issue 33, 3: one identity's sessions stop at its share; another identity's session
    /// is still queued for; the refusals name the share; acknowledging and ending give the
    /// share back; the store's own cap refuses everyone.
    #[test]
    fn each_identity_has_a_share_of_the_store() {
        // 16 + "t" + "pub" + 4-byte payloads: 24 bytes a message.
        let limits = Limits {
            share_bytes: 24 * 4,
            share_messages: 3,
            max_queued: 100,
            ..LIMITS
        };
        let mut s = State::default();
        let mut d = Drops::default();
        for r in [
            session_of("a1", "user:a"),
            subscribe("a1", "#", 1, false),
            session_of("a2", "user:a"),
            subscribe("a2", "#", 1, false),
            session_of("b", "user:b"),
            subscribe("b", "#", 1, false),
        ] {
            s.apply(r, limits, &mut d);
        }
        for seq in 1..=3 {
            s.apply(publish(seq, "t", 1, false, "1234"), limits, &mut d);
        }
        // a1 and a2 share three messages; b has its own.
        assert_eq!(queue(&s, "a1").len() + queue(&s, "a2").len(), 3);
        assert_eq!(queue(&s, "b").len(), 3);
        assert_eq!(d.identity_share, 3);
        assert_eq!(
            s.shares.get("user:a").copied(),
            Some(Usage {
                bytes: 72,
                messages: 3
            })
        );
        let a: Arc<str> = "user:a".into();
        assert_eq!(
            d.refused,
            vec![
                (2, Refused::Share(a.clone())),
                (3, Refused::Share(a.clone())),
                (3, Refused::Share(a))
            ]
        );
        // Acknowledged: room again for the next one.
        s.done("a1", &[1]);
        d = Drops::default();
        s.apply(publish(4, "t", 1, false, "1234"), limits, &mut d);
        // One of a1 and a2 gets it; b's share (three messages) is spent.
        assert_eq!(d.identity_share, 2);
        assert_eq!(s.shares["user:a"].messages, 3);
        // Ended: the share is free; nothing is left of it.
        s.apply(
            Record::Ended {
                client: "a1".into(),
            },
            limits,
            &mut d,
        );
        s.apply(
            Record::Ended {
                client: "a2".into(),
            },
            limits,
            &mut d,
        );
        assert!(!s.shares.contains_key("user:a"));
        // The store's own cap: everyone is refused, and told.
        let tight = Limits {
            max_bytes: s.bytes + 10,
            ..limits
        };
        d = Drops::default();
        s.apply(session_of("c", "user:c"), tight, &mut d);
        s.apply(subscribe("c", "#", 1, false), tight, &mut d);
        s.apply(publish(5, "t", 1, false, "1234"), tight, &mut d);
        assert_eq!(d.store_full, 1, "b's share is spent first, then the store");
        assert!(d.refused.contains(&(5, Refused::StoreFull)));
    }

    /// A kept session that comes back under another share moves its queue's usage along.
    #[test]
    fn a_session_resumed_under_another_share_moves_its_usage() {
        let (mut s, mut d) = state(vec![
            session_of("a", "address:127.0.0.2"),
            subscribe("a", "#", 1, false),
            publish(1, "t", 1, false, "1234"),
        ]);
        let mut resumed = session_of("a", "user:alice");
        if let Record::Session { fresh, .. } = &mut resumed {
            *fresh = false;
        }
        s.apply(resumed, LIMITS, &mut d);
        assert!(!s.shares.contains_key("address:127.0.0.2"));
        assert_eq!(s.shares["user:alice"].messages, 1);
        s.done("a", &[1]);
        assert!(s.shares.is_empty());
    }

    #[test]
    fn retained_messages_follow_the_routers_bounds() {
        // LIMITS: 4 retained messages; the broker's own topics are not counted.
        let mut records: Vec<Record> = (1..=6)
            .map(|i| publish(i, &format!("r/{i}"), 0, true, "v"))
            .collect();
        records.push(publish(7, "fbbus/devices/x", 0, true, "own"));
        records.push(publish(8, "r/1", 0, true, "replaced, and longer"));
        records.push(publish(9, "r/2", 0, true, ""));
        records.push(publish(10, "r/9", 0, true, "room again"));
        let (s, d) = state(records);
        assert_eq!(d.retained_limit, 2, "r/5 and r/6");
        let topics: Vec<&[u8]> = s.retained.keys().map(|k| k.as_slice()).collect();
        let want: [&[u8]; 5] = [b"fbbus/devices/x", b"r/1", b"r/3", b"r/4", b"r/9"];
        assert_eq!(topics, want);
        assert_eq!(
            &s.retained[b"r/1".as_slice()].payload[..],
            b"replaced, and longer"
        );
        // Bytes: topic and payload, as the router counts them.
        let tight = Limits {
            max_retained_bytes: 10,
            ..LIMITS
        };
        let mut s = State::default();
        let mut d = Drops::default();
        for r in [
            publish(1, "a", 0, true, "123456789"),
            publish(2, "b", 0, true, "1"),
        ] {
            s.apply(r, tight, &mut d);
        }
        assert_eq!((s.retained.len(), d.retained_limit), (1, 1));
        // As the router: a smaller replacement is kept; a larger one beyond the bytes is
        // refused and clears the old value.
        s.apply(publish(3, "a", 0, true, "1234"), tight, &mut d);
        assert_eq!(&s.retained[b"a".as_slice()].payload[..], b"1234");
        s.apply(publish(4, "a", 0, true, "1234567890"), tight, &mut d);
        assert!(s.retained.is_empty(), "the stale value is cleared");
        assert_eq!(d.retained_limit, 2);
    }

    #[test]
    fn the_subscriber_tree_matches_as_mqtt_does() {
        let filters = [
            "a/b", "a/+", "a/#", "#", "+/b", "+", "a/+/c", "$SYS/#", "+/+/#", "a/b/c/#", "é/ü/+",
        ];
        let topics = [
            "a", "a/b", "a/b/c", "a/b/c/d", "b", "b/b", "$SYS/x", "$SYS", "/", "a//c", "é/ü/ß", "",
        ];
        let options = |qos, no_local| Options {
            qos,
            no_local,
            retain_as_published: false,
            retain_handling: 0,
            id: 0,
        };
        let mut tree = Subscribers::default();
        for f in filters {
            tree.insert(f, &ClientId::from(f), &options(1, false));
        }
        let got = |tree: &Subscribers, t: &str| -> BTreeSet<String> {
            let mut out = Vec::new();
            tree.matching(t, &mut out);
            let names: Vec<String> = out.iter().map(|(c, _)| c.to_string()).collect();
            // One entry per session, in client id order.
            assert!(names.windows(2).all(|w| w[0] < w[1]), "{names:?}");
            names.into_iter().collect()
        };
        for t in topics {
            let want: BTreeSet<String> = filters
                .iter()
                .filter(|f| filter::filter_matches(f, t))
                .map(|f| f.to_string())
                .collect();
            assert_eq!(got(&tree, t), want, "topic {t:?}");
        }
        tree.remove("a/#", "a/#");
        assert!(!got(&tree, "a/b/c").contains("a/#"));
        // One session's matching filters together: the best QoS; No Local only if all are.
        let m = ClientId::from("m");
        tree.insert("m/+", &m, &options(1, true));
        tree.insert("m/#", &m, &options(2, false));
        tree.insert("m/x", &m, &options(0, true));
        let wanted = |tree: &Subscribers, t| {
            let mut out = Vec::new();
            tree.matching(t, &mut out);
            assert!(
                out.iter().filter(|(c, _)| &**c == "m").count() <= 1,
                "one entry per session"
            );
            out.iter().find(|(c, _)| &**c == "m").map(|(_, w)| *w)
        };
        assert_eq!(
            wanted(&tree, "m/x"),
            Some(Wanted {
                qos: 2,
                no_local: false
            })
        );
        tree.insert("m/#", &m, &options(0, true));
        assert_eq!(
            wanted(&tree, "m/x"),
            Some(Wanted {
                qos: 1,
                no_local: true
            })
        );
        assert_eq!(
            wanted(&tree, "m"),
            Some(Wanted {
                qos: 0,
                no_local: true
            })
        );
        tree.remove("m/#", "m");
        assert_eq!(wanted(&tree, "m"), None);
    }

    #[test]
    fn a_snapshot_rebuilds_the_same_state() {
        let (s, _) = state(vec![
            session("a"),
            subscribe("a", "x/#", 2, false),
            session("b"),
            subscribe("b", "x/1", 1, false),
            Record::Offline {
                client: "b".into(),
                at: 9,
                expiry: Some(60),
            },
            publish(1, "x/1", 2, true, "p"),
            Record::Qos2 {
                client: "a".into(),
                seq: 1,
                state: Qos2::Received(4),
            },
            publish(2, "x/2", 1, false, "q"),
        ]);
        let (t, _) = state(s.snapshot());
        assert_eq!(queue(&t, "a"), queue(&s, "a"));
        assert_eq!(queue(&t, "b"), queue(&s, "b"));
        assert_eq!(
            t.sessions["a"]
                .queue
                .iter()
                .find(|(seq, _)| *seq == 1)
                .unwrap()
                .1
                .qos2,
            Some(Qos2::Received(4))
        );
        assert_eq!(t.sessions["b"].offline_at, Some(9));
        assert_eq!(t.retained.len(), 1);
        assert_eq!(
            (t.bytes, t.queued, t.last_seq),
            (s.bytes, s.queued, s.last_seq)
        );
    }
}

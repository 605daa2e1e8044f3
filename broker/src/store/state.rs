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
//! Bounded: at most `max_queued` messages per session and `max_bytes` of messages in all
//! (a message queued for n sessions counts n times); beyond either, a message is not
//! stored for that session (or, for a retained message, not stored), and counted.

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
}

#[derive(Debug, Clone)]
pub struct StoredSession {
    pub owner: String,
    pub v5: bool,
    pub expiry: Option<u32>,
    /// Unix seconds since it is offline; None while connected.
    pub offline_at: Option<u64>,
    pub subscriptions: BTreeMap<String, Options>,
    pub queue: Queue,
}

/// Why a message was not stored.
#[derive(Debug, Default, Clone, Copy, PartialEq, Eq)]
pub struct Drops {
    pub session_queue_full: u64,
    pub store_full: u64,
    pub retained_limit: u64,
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
                v5,
                expiry,
                fresh,
            } => {
                if fresh {
                    self.end(&client);
                }
                let s = self
                    .sessions
                    .entry(client)
                    .or_insert_with(|| StoredSession {
                        owner: String::new(),
                        v5,
                        expiry,
                        offline_at: None,
                        subscriptions: BTreeMap::new(),
                        queue: Queue::default(),
                    });
                s.owner = owner;
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
                    self.retain(&message, limits, drops);
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
                    self.retain(&message, limits, drops);
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
    }

    fn end(&mut self, client: &str) {
        if let Some(s) = self.sessions.remove(client) {
            self.subscribed -= !s.subscriptions.is_empty() as usize;
            for f in s.subscriptions.keys() {
                self.subscribers.remove(f, client);
            }
            for (_, q) in s.queue.iter() {
                self.bytes = self.bytes.saturating_sub(q.message.size());
            }
            self.queued = self.queued.saturating_sub(s.queue.len());
        }
    }

    fn retain(&mut self, message: &Arc<Message>, limits: Limits, drops: &mut Drops) {
        let counted = !crate::router::RETAINED_UNCOUNTED
            .iter()
            .any(|prefix| message.topic.starts_with(prefix.as_bytes()));
        let router_size = |m: &Message| m.topic.len() + m.payload.len();
        let old = self.retained.remove(message.topic.as_ref());
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
        if self.bytes + message.size() > limits.max_bytes {
            drops.store_full += 1;
            return;
        }
        let queued = Queued {
            message: Arc::clone(message),
            qos,
            qos2,
        };
        if s.queue.insert(seq, queued) {
            self.bytes += message.size();
            self.queued += 1;
        }
    }

    /// Records that rebuild this state: what compaction writes.
    pub fn snapshot(&self) -> Vec<Record> {
        let mut out = Vec::new();
        for (client, s) in &self.sessions {
            out.push(Record::Session {
                client: client.clone(),
                owner: s.owner.clone(),
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
    };

    fn session(client: &str) -> Record {
        Record::Session {
            client: client.into(),
            owner: String::new(),
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

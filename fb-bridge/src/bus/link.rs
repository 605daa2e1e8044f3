//! The zenoh session of one line's bridge: everything that touches the network.
//!
//! The broker drives it (`broker/src/bridge/`); this module knows zenoh, not MQTT
//! routers. What it offers:
//!
//! - [`Exporter::export`]: put one local message on its data key, stamped, reliable and
//!   with blocking congestion control (a full link slows the exporter down, it never drops
//!   a message); zenoh sends it only to lines that declared a matching subscriber;
//! - [`Link::import`]: declare interest in an MQTT filter: a zenoh subscriber whose
//!   samples arrive on the inbox, and a liveliness token that tells the exporting lines to
//!   subscribe locally to the filter (nothing leaves a line nobody asked for);
//! - liveliness of lines ([`Event`]), registry records (put on every change, queried
//!   when a line comes up) and retained messages (queried when a line starts importing a
//!   filter). A device's state travels in its record, not as a liveliness token of its
//!   own: zenoh's routing tables match every new token against all the others, and 8,000
//!   device tokens made each router spend tens of seconds of CPU doing so (issue 32).
//!
//! A client line with [`BusConfig::session_per_router`] holds one session per router
//! (module `sessions`): every subscription, queryable and token is declared on each,
//! puts and queries go through the first that has a router, and what the sessions
//! report is merged (module `presence`) so the broker sees one bus.
//!
//! No zenoh or flume type appears in this module's public API: the broker sees fbbus
//! types ([`Inbox`], [`RetainedQueries`], [`LinkError`]), so it does not depend on zenoh's
//! version or on the channel crate zenoh's handlers happen to use.

use std::collections::HashMap;
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::{Arc, Mutex, PoisonError};
use std::time::{Duration, SystemTime, UNIX_EPOCH};

use zenoh::key_expr::KeyExpr;
use zenoh::pubsub::Publisher;
use zenoh::qos::{CongestionControl, Priority};
use zenoh::query::Query;
use zenoh::Session;

use super::presence::encode_version;
use super::sessions::Sessions;
use super::{keys, BusConfig, LossTally, Stamp};

use super::error::zerr;
pub use super::error::LinkError;
pub use super::event::{Event, Inbound};

/// Samples and events, in arrival order, bounded: a full inbox blocks zenoh's receive
/// path, which backs the link up to the sender (blocking congestion control) instead of
/// dropping.
pub(crate) const INBOX: usize = 8_192;

/// The receiving end of what the link hands the broker, in arrival order: the messages
/// of imported filters ([`Inbound`]) or the bus's events ([`Event`]).
pub struct Inbox<T>(flume::Receiver<T>);

impl<T> Inbox<T> {
    /// The next item; `None` once the link is gone and everything was taken.
    ///
    /// Each item counts against the task's tokio budget, as an item of tokio's own
    /// channels does: a loop over an inbox that the bus keeps full yields every 128 items
    /// instead of holding its worker thread, so the line's own sessions never wait behind
    /// a burst from the bus (issue 32: a line of 1,000 devices coming up puts 1,000
    /// records on every other line at once). flume alone never yields while it has items.
    pub async fn recv(&self) -> Option<T> {
        let item = self.0.recv_async().await.ok()?;
        tokio::task::consume_budget().await;
        Some(item)
    }

    /// The next item if one is waiting.
    pub fn try_recv(&self) -> Option<T> {
        self.0.try_recv().ok()
    }

    /// Every item waiting now, without waiting for more.
    pub fn try_iter(&self) -> impl Iterator<Item = T> + '_ {
        self.0.try_iter()
    }
}

/// Other lines' queries for this line's retained messages; they end when the link closes.
pub struct RetainedQueries {
    queries: flume::Receiver<Query>,
}

impl RetainedQueries {
    /// The next query with a filter this line can answer (others are skipped); `None`
    /// once the link is closed.
    pub async fn recv(&self) -> Option<RetainedQuery> {
        loop {
            let query = self.queries.recv_async().await.ok()?;
            if let Some((_, filter)) = keys::parse_retained_query(query.key_expr().as_str()) {
                return Some(RetainedQuery { query, filter });
            }
        }
    }
}

/// One other line's query for this line's retained messages matching an MQTT filter;
/// answered with [`Link::reply_retained`].
pub struct RetainedQuery {
    query: Query,
    filter: String,
}

impl RetainedQuery {
    /// The MQTT filter (within `fb/#`) the other line imports.
    pub fn filter(&self) -> &str {
        &self.filter
    }
}

pub struct Link {
    /// One session, or one per router ([`BusConfig::session_per_router`]).
    sessions: Sessions,
    line: String,
    epoch: u64,
    inbox: flume::Sender<Inbound>,
    /// Record changes put so far: with the epoch, each change's version.
    record_changes: AtomicU64,
    /// Other lines' messages this line counted as lost, to be reported to them.
    losses: Mutex<LossTally>,
}

/// The interest of this line in one MQTT filter; dropping it undeclares its subscriber
/// and its token on every session.
pub struct Import {
    sessions: Sessions,
    id: u64,
}

impl Drop for Import {
    fn drop(&mut self) {
        self.sessions.forget_import(self.id);
    }
}

/// Checks that the `[bridge]` section makes a zenoh configuration, and that the line's
/// certificate names `line`, without opening anything: a bad section fails the broker's
/// start (and `fbbus check-config`) whatever the mode.
pub fn validate(config: &BusConfig, line: &str) -> Result<(), LinkError> {
    if let Some(tls) = &config.tls {
        let name = common_name(&tls.cert)?;
        if name != line {
            return Err(LinkError::Identity {
                cert: tls.cert.display().to_string(),
                name,
                line: line.to_owned(),
            });
        }
    }
    session_configs(config).map(drop)
}

/// The common name of the first certificate of a PEM file.
fn common_name(path: &std::path::Path) -> Result<String, LinkError> {
    let failed = |message: String| LinkError::Certificate {
        cert: path.display().to_string(),
        message,
    };
    let bytes = std::fs::read(path).map_err(|e| failed(e.to_string()))?;
    let (_, pem) = x509_parser::pem::parse_x509_pem(&bytes)
        .map_err(|e| failed(format!("not a PEM certificate ({e})")))?;
    let cert = pem
        .parse_x509()
        .map_err(|e| failed(format!("not an X.509 certificate ({e})")))?;
    let name = cert
        .subject()
        .iter_common_name()
        .next()
        .and_then(|cn| cn.as_str().ok())
        .ok_or_else(|| failed("has no common name (CN): it names the line".into()))?;
    Ok(name.to_owned())
}

/// zenoh's configuration of each session the link opens: one, or with a session per
/// router one per router, each connecting to its own router only (a client whose router
/// went waits for it to come back, so each session stays on its router).
fn session_configs(config: &BusConfig) -> Result<Vec<zenoh::Config>, LinkError> {
    if !config.session_per_router {
        return Ok(vec![zenoh_config(config)?]);
    }
    config
        .connect
        .iter()
        .map(|router| {
            zenoh_config(&BusConfig {
                connect: vec![router.clone()],
                ..config.clone()
            })
        })
        .collect()
}

/// Builds zenoh's configuration from the `[bridge]` section.
fn zenoh_config(config: &BusConfig) -> Result<zenoh::Config, LinkError> {
    let mut c = zenoh::Config::default();
    for (key, value) in settings(config) {
        c.insert_json5(key, &value.to_string())
            .map_err(|e| LinkError::Config {
                key: key.to_owned(),
                message: e.to_string(),
            })?;
    }
    Ok(c)
}

/// The plant's zenoh router configured like a line's bridge would be with `config`
/// (`mode = "router"`): its endpoints, TLS and access control, as one JSON document for
/// `zenohd -c`. `name` is the router's name, which its certificate must carry and the
/// lines list under `[bridge.peers] routers`.
pub fn zenohd_config(config: &BusConfig, name: &str) -> Result<serde_json::Value, LinkError> {
    validate(config, name)?;
    let mut root = serde_json::Value::Object(Default::default());
    for (key, value) in settings(config) {
        let mut node = &mut root;
        for part in key.split('/') {
            node = &mut node[part];
        }
        *node = value;
    }
    Ok(root)
}

/// What fbbus sets in zenoh's configuration, as (key path, value).
fn settings(config: &BusConfig) -> Vec<(&'static str, serde_json::Value)> {
    use serde_json::json;
    let mut out = vec![
        ("mode", json!(config.mode.as_str())),
        ("listen/endpoints", json!(config.listen)),
        ("connect/endpoints", json!(config.connect)),
        // Peers that are down are tried again in the background (a zero timeout would try
        // once and give up). A client's `open` returns once its router answered (zenoh
        // retries every 1 to 4 s), which is why the broker opens a client in the
        // background; a client reconnects to its router by itself later.
        ("connect/timeout_ms", json!(-1)),
    ];
    if config.mode != super::Mode::Client {
        out.push(("connect/exit_on_failure", json!(false)));
    }
    if config.session_per_router {
        // A session waits for its own router when it is gone: try it every second (zenoh
        // backs off to every 4 s), so the line is back on both routers within about a
        // second of the router's return.
        out.push(("connect/retry", json!({ "period_max_ms": 1_000 })));
    }
    out.extend([
        (
            "scouting/multicast/enabled",
            json!(config.multicast_scouting),
        ),
        ("transport/link/tx/lease", json!(config.lease_ms)),
        ("transport/link/tx/keep_alive", json!(4)),
        // zenoh holds a batch that is still being written to for up to `time_limit` ms (1
        // by default) to fill it: at a steady 10,000 msg/s every message waited for the
        // next. Send what is there whenever the link is free instead; under a burst the
        // batches fill anyway while the link is busy.
        ("transport/link/tx/queue/batching/time_limit", json!(0)),
    ]);
    if let Some(tls) = &config.tls {
        let path = |p: &std::path::Path| json!(p.display().to_string());
        out.extend([
            ("transport/link/tls/root_ca_certificate", path(&tls.root_ca)),
            ("transport/link/tls/listen_certificate", path(&tls.cert)),
            ("transport/link/tls/listen_private_key", path(&tls.key)),
        ]);
        if tls.mutual {
            out.extend([
                ("transport/link/tls/enable_mtls", json!(true)),
                ("transport/link/tls/connect_certificate", path(&tls.cert)),
                ("transport/link/tls/connect_private_key", path(&tls.key)),
            ]);
        }
    }
    // On a mutual-TLS bus every peer is known by its certificate: zenoh lets each do only
    // what `[bridge.peers]` grants it (`super::access`), default deny.
    if let (Some(peers), true) = (&config.peers, config.mutual_tls()) {
        out.push(("access_control", super::access::access_control(peers)));
    }
    out
}

impl Link {
    /// Opens the session (or one per router: the link is up once the first is) and starts
    /// watching the bus (the line is announced separately, [`Link::announce_line`]).
    /// Returns the link, its inbox (messages of imported filters) and the liveliness
    /// events.
    pub async fn open(
        config: &BusConfig,
        line: &str,
    ) -> Result<(Link, Inbox<Inbound>, Inbox<Event>), LinkError> {
        let configs = session_configs(config)?;
        let epoch = SystemTime::now()
            .duration_since(UNIX_EPOCH)
            .map_or(1, |d| d.as_micros() as u64);
        let (inbox, inbox_rx) = flume::bounded(INBOX);
        let (events, events_rx) = flume::unbounded();
        let sessions = Sessions::open(configs, (line, epoch), events, inbox.clone()).await?;
        Ok((
            Link {
                sessions,
                line: line.to_owned(),
                epoch,
                inbox,
                record_changes: AtomicU64::new(0),
                losses: Mutex::new(LossTally::default()),
            },
            Inbox(inbox_rx),
            Inbox(events_rx),
        ))
    }

    /// Tells the other lines this line is up. Call it once the records are served
    /// ([`Link::serve_records`]): other lines query them as soon as they see the token.
    pub async fn announce_line(&self) -> Result<(), LinkError> {
        self.sessions.announce()
    }

    pub fn line(&self) -> &str {
        &self.line
    }

    /// With [`BusConfig::session_per_router`]: (sessions whose router is there,
    /// sessions), checked every 50 ms. `None` with one session.
    pub fn routers(&self) -> Option<(usize, usize)> {
        self.sessions.routers()
    }

    /// The exporting half (owned by one task: it numbers the messages it sends).
    pub fn exporter(&self) -> Exporter {
        Exporter {
            sessions: self.sessions.clone(),
            declared_for: None,
            line: self.line.clone(),
            epoch: self.epoch,
            seq: 0,
            publishers: HashMap::new(),
            topic_seqs: HashMap::new(),
        }
    }

    /// The importing half's key cache (owned by the task that takes the inbox).
    pub fn route_keys(&self) -> RouteKeys {
        RouteKeys {
            sessions: self.sessions.clone(),
            declared_for: None,
            keys: HashMap::new(),
            len: 0,
        }
    }

    /// Puts a message (a retained reply) into the inbox, behind what is already there.
    pub async fn requeue(&self, message: Inbound) {
        let _ = self.inbox.send_async(message).await;
    }

    /// Declares this line's interest in `filter` (an MQTT filter within `fb/#`).
    pub async fn import(&self, filter: &str) -> Result<Import, LinkError> {
        let key = keys::import_key(filter).ok_or_else(|| LinkError::Config {
            key: "filter".into(),
            message: format!("`{filter}` cannot cross lines"),
        })?;
        let id = self.sessions.import(key, filter)?;
        Ok(Import {
            sessions: self.sessions.clone(),
            id,
        })
    }

    /// The version the next record change of this line carries.
    fn next_record_version(&self) -> Vec<u8> {
        let count = self.record_changes.fetch_add(1, Ordering::Relaxed) + 1;
        encode_version(self.epoch, count)
    }

    /// Publishes a local device's registry record to the other lines.
    pub async fn put_record(&self, device: &str, json: Vec<u8>) -> Result<(), LinkError> {
        self.sessions
            .active()?
            .put(keys::record_key(&self.line, device), json)
            .attachment(self.next_record_version())
            .congestion_control(CongestionControl::Block)
            .await
            .map_err(zerr)
    }

    /// Tells the other lines this line forgot its device (`fbbus devices forget`, or
    /// `[fb] forget_offline_after_s`): a delete of the device's record key.
    pub async fn forget_record(&self, device: &str) -> Result<(), LinkError> {
        self.sessions
            .active()?
            .delete(keys::record_key(&self.line, device))
            .attachment(self.next_record_version())
            .await
            .map_err(zerr)
    }

    /// `lost` messages of `origin`'s run `epoch` never reached this line (the gaps
    /// [`super::Gaps`] found): counted, to be told to `origin` by
    /// [`Link::report_losses`]. False if the count has no room for one more origin
    /// ([`super::LOSS_LINES`]).
    pub fn count_lost(&self, origin: &str, epoch: u64, lost: u64) -> bool {
        self.losses
            .lock()
            .unwrap_or_else(PoisonError::into_inner)
            .add(origin, epoch, lost)
    }

    /// Tells each origin line how many of its messages this line counted as lost: the
    /// counts that moved since the last call, or all of them (`everything`). Returns the
    /// reports put.
    pub async fn report_losses(&self, everything: bool) -> Result<usize, LinkError> {
        let reports = self
            .losses
            .lock()
            .unwrap_or_else(PoisonError::into_inner)
            .reports(self.epoch, everything);
        if reports.is_empty() {
            return Ok(0);
        }
        let session = self.sessions.active()?;
        for (origin, report) in &reports {
            session
                .put(keys::loss_key(&self.line, origin), report.encode())
                .congestion_control(CongestionControl::Block)
                .await
                .map_err(zerr)?;
        }
        Ok(reports.len())
    }

    /// Answers registry queries (`fbbus/@/record/<line>/<device or *>`) with `records`'
    /// answer: (device id, record JSON) of the one local device a query names
    /// (`records(Some(id))`), or of every local device (`records(None)`, a wildcard): a
    /// query for one device does not cost the whole registry (issue 32).
    pub async fn serve_records(
        &self,
        records: impl Fn(Option<&str>) -> Vec<(String, Vec<u8>)> + Send + Sync + 'static,
    ) -> Result<(), LinkError> {
        self.sessions.serve_records(Arc::new(records))
    }

    /// The records `line` (`*`: every line) serves, as (line, device, JSON): of `device`
    /// only, or (None) all of them.
    pub async fn query_records(
        &self,
        line: &str,
        device: Option<&str>,
    ) -> Result<Vec<(String, String, Vec<u8>)>, LinkError> {
        let replies = self
            .sessions
            .active()?
            .get(format!(
                "{}/record/{line}/{}",
                keys::CONTROL,
                device.unwrap_or("*")
            ))
            .timeout(Duration::from_secs(2))
            .await
            .map_err(zerr)?;
        let mut out = Vec::new();
        while let Ok(reply) = replies.recv_async().await {
            if let Ok(sample) = reply.result() {
                if let Some((l, d)) = keys::parse_line_item("record", sample.key_expr().as_str()) {
                    if l != self.line {
                        out.push((
                            l.to_owned(),
                            d.to_owned(),
                            sample.payload().to_bytes().into_owned(),
                        ));
                    }
                }
            }
        }
        Ok(out)
    }

    /// The queries other lines ask for this line's retained messages.
    pub async fn retained_queries(&self) -> Result<RetainedQueries, LinkError> {
        let (tx, queries) = flume::bounded(64);
        self.sessions.serve_retained(tx)?;
        Ok(RetainedQueries { queries })
    }
    /// Retained messages of other lines matching `filter`.
    pub async fn query_retained(&self, filter: &str) -> Result<Vec<Inbound>, LinkError> {
        self.query_retained_of(None, filter).await
    }

    /// [`Link::query_retained`] of one line only (`Some`), or of every line.
    pub async fn query_retained_of(
        &self,
        line: Option<&str>,
        filter: &str,
    ) -> Result<Vec<Inbound>, LinkError> {
        let Some(key) = keys::retained_query_of(line, filter) else {
            return Ok(Vec::new());
        };
        let replies = self
            .sessions
            .active()?
            .get(key)
            .timeout(Duration::from_secs(2))
            .await
            .map_err(zerr)?;
        let mut out = Vec::new();
        while let Ok(reply) = replies.recv_async().await {
            let Ok(sample) = reply.result() else { continue };
            let Some((line, topic)) = keys::parse_retained_reply(sample.key_expr().as_str()) else {
                continue;
            };
            let Some(stamp) = sample
                .attachment()
                .and_then(|a| Stamp::decode(&a.to_bytes()))
            else {
                continue;
            };
            if line != self.line {
                out.push(Inbound {
                    line: line.to_owned(),
                    stamp,
                    topic: topic.to_owned(),
                    payload: sample.payload().to_bytes().into_owned(),
                });
            }
        }
        Ok(out)
    }

    /// Answers one retained-message query with `messages` (topic, payload).
    pub async fn reply_retained(&self, query: &RetainedQuery, messages: Vec<(String, Vec<u8>)>) {
        let query = &query.query;
        for (topic, payload) in messages {
            let Some(key) = keys::retained_reply(&self.line, &topic) else {
                continue;
            };
            let stamp = Stamp {
                line: self.line.clone(),
                epoch: self.epoch,
                seq: 0,
                topic_seq: 0,
                qos: 1,
                retain: true,
            };
            let _ = query.reply(key, payload).attachment(stamp.encode()).await;
        }
    }

    /// Closes the sessions: other lines see this line's tokens go at once.
    pub async fn close(&self) {
        self.sessions.close().await;
    }
}

/// Publishes local messages on the bus, numbered per origin.
pub struct Exporter {
    sessions: Sessions,
    /// What the publishers were declared on ([`Sessions::version`]); they are declared
    /// again when the active session changes.
    declared_for: Option<(usize, u64)>,
    line: String,
    epoch: u64,
    seq: u64,
    /// Per topic, its publisher on the active session.
    publishers: HashMap<String, Publisher<'static>>,
    /// Per topic, the last `topic_seq` it put (kept across a change of session).
    topic_seqs: HashMap<String, u64>,
}

/// Publishers kept for repeated topics; past this many the cache starts over.
const PUBLISHER_CACHE: usize = 10_000;

impl Exporter {
    /// Puts one message of this line; `event` ports travel at a higher priority than data
    /// ports (events overtake queued data, each topic keeps its order). Returns false for
    /// a topic that cannot cross (see [`keys::data_key`]).
    pub async fn export(
        &mut self,
        topic: &str,
        payload: bytes::Bytes,
        qos: u8,
        retain: bool,
        event: bool,
    ) -> Result<bool, LinkError> {
        let version = self.sessions.version();
        if self.declared_for != Some(version) {
            self.publishers.clear();
            self.declared_for = Some(version);
        }
        if !self.publishers.contains_key(topic) {
            let Some(key) = keys::data_key(&self.line, topic) else {
                return Ok(false);
            };
            if self.publishers.len() >= PUBLISHER_CACHE {
                self.publishers.clear();
            }
            if self.topic_seqs.len() >= PUBLISHER_CACHE {
                self.topic_seqs.clear();
            }
            let publisher = self
                .sessions
                .active()?
                .declare_publisher(key)
                .congestion_control(CongestionControl::Block)
                .priority(if event {
                    Priority::DataHigh
                } else {
                    Priority::Data
                })
                .await
                .map_err(zerr)?;
            self.publishers.insert(topic.to_owned(), publisher);
        }
        let Some(publisher) = self.publishers.get(topic) else {
            return Ok(false);
        };
        let topic_seq = match self.topic_seqs.get_mut(topic) {
            Some(n) => {
                *n += 1;
                *n
            }
            None => {
                self.topic_seqs.insert(topic.to_owned(), 1);
                1
            }
        };
        self.seq += 1;
        // What other lines may report lost of this run is at most this (see `Reported`).
        self.sessions.exported(self.seq);
        let stamp = Stamp {
            line: self.line.clone(),
            epoch: self.epoch,
            seq: self.seq,
            topic_seq,
            qos,
            retain,
        };
        publisher
            .put(payload)
            .attachment(stamp.encode())
            .await
            .map_err(zerr)?;
        Ok(true)
    }
}

/// The data keys of the other lines' topics this line receives, declared to zenoh.
///
/// Why: zenoh caches a sample's route (which subscribers get it) only on a resource its
/// tables hold. A sample on a key nobody declared has its route computed from scratch,
/// its key matched against every subscription, and is matched once more against the
/// session's subscribers: in a profile of an importing line during a 100,000-message
/// burst that was about a quarter of the line's CPU. Declaring each key once, as the
/// first message on it arrives, turns both into lookups.
pub struct RouteKeys {
    sessions: Sessions,
    /// The sessions' generation the keys were declared for ([`Sessions::version`]).
    declared_for: Option<u64>,
    /// line -> topic -> the key, declared on each session
    keys: HashMap<String, HashMap<String, Vec<(Session, KeyExpr<'static>)>>>,
    len: usize,
}

/// Keys declared for received topics; past this many the cache starts over.
const ROUTE_KEYS: usize = 10_000;

impl RouteKeys {
    /// Declares the key of `topic` of `line` unless it is already.
    pub fn note(&mut self, line: &str, topic: &str) {
        let generation = self.sessions.version().1;
        let stale = self.declared_for.is_some_and(|g| g != generation);
        if self.keys.get(line).is_some_and(|t| t.contains_key(topic)) && !stale {
            return;
        }
        if self.len >= ROUTE_KEYS || stale {
            for (session, key) in self
                .keys
                .drain()
                .flat_map(|(_, t)| t.into_values())
                .flatten()
            {
                let _ = zenoh::Wait::wait(session.undeclare(key));
            }
            self.len = 0;
        }
        self.declared_for = Some(generation);
        let Some(key) = keys::data_key(line, topic) else {
            return;
        };
        let mut declared = Vec::new();
        for session in self.sessions.each() {
            match zenoh::Wait::wait(session.declare_keyexpr(key.clone())) {
                Ok(k) => declared.push((session, k)),
                Err(e) => tracing::debug!(line, topic, error = %e, "key not declared"),
            }
        }
        self.keys
            .entry(line.to_owned())
            .or_default()
            .insert(topic.to_owned(), declared);
        self.len += 1;
    }
}

#[cfg(test)]
mod tests {
    use std::sync::atomic::{AtomicUsize, Ordering};
    use std::sync::Arc;

    use super::{session_configs, Inbox, INBOX};
    use crate::bus::{BusConfig, Mode};

    /// One zenoh configuration per router, each naming its own router only, and each one
    /// zenoh accepts (a key zenoh does not know fails here, not at a plant's start).
    #[test]
    fn a_session_per_router_is_configured_for_its_router_alone() {
        let routers = vec![
            "tcp/127.0.0.1:7447".to_owned(),
            "tcp/127.0.0.1:7448".to_owned(),
        ];
        let config = BusConfig {
            mode: Mode::Client,
            connect: routers.clone(),
            session_per_router: true,
            ..BusConfig::default()
        };
        let configs = session_configs(&config).expect("zenoh takes them");
        assert_eq!(configs.len(), 2);
        for (config, router) in configs.iter().zip(&routers) {
            let connect = config.get_json("connect/endpoints").unwrap();
            assert_eq!(connect, format!("[\"{router}\"]"));
            assert!(config.get_json("connect/retry").unwrap().contains("1000"));
        }
        let one = BusConfig {
            session_per_router: false,
            ..config
        };
        assert_eq!(session_configs(&one).unwrap().len(), 1);
    }

    /// A loop over a full inbox gives its thread back: another task on the same thread
    /// runs before the loop has taken more than a budget's worth (128) of items. Without
    /// the budget, the loop takes all 8,192 first.
    #[tokio::test(flavor = "current_thread")]
    async fn a_loop_over_a_full_inbox_lets_the_other_tasks_run() {
        let (tx, rx) = flume::bounded(INBOX);
        for i in 0..INBOX {
            tx.send(i).expect("room for it");
        }
        drop(tx);
        let inbox = Inbox(rx);
        let taken = Arc::new(AtomicUsize::new(0));
        let seen = {
            let taken = Arc::clone(&taken);
            tokio::spawn(async move { taken.load(Ordering::SeqCst) })
        };
        while inbox.recv().await.is_some() {
            taken.fetch_add(1, Ordering::SeqCst);
        }
        let when = seen.await.expect("the other task ran");
        assert!(
            when <= 128,
            "the other task ran only after {when} items of {INBOX}"
        );
    }
}

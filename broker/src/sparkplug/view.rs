//! The view's task: its router link in, the registry's changes in, Sparkplug out.

use std::collections::VecDeque;
use std::sync::Arc;
use std::time::Duration;

use bytes::Bytes;
use fb_bridge::sparkplug::proto;
use prometheus::{IntCounterVec, Opts};
use prost::Message as _;
use rumqttd::local::{LinkRx, LinkTx};
use rumqttd::protocol::{Filter, Packet, QoS, RetainForwardRule, Subscribe};
use serde::Deserialize;
use tokio::sync::{broadcast, mpsc, oneshot};
use tokio::time::Instant;

use super::bdseq::BdSeqs;
use super::node::{AliasBook, Nodes, Out, REBIRTH_METRIC};
use super::{Kind, SparkplugSection, Topic, CLIENT_ID, NAMESPACE};
use crate::broker_publisher::publish_packet;
use crate::link;
use crate::metrics::Metrics;
use crate::policy::origin;
use crate::registry::{Change, Registry};

/// How long a registry change waits before the view applies it: the values of a will
/// (the device's, or its profile's broker-side will) are routed before the registry marks
/// the device offline, but reach the view through the router, which may take longer than
/// the registry's channel. Held back this long, they are the device's last DDATA before
/// its DDEATH, as a host expects.
const RECORD_DELAY: Duration = Duration::from_millis(100);

/// How long after the first reader's SUBSCRIBE the view publishes every birth: the
/// session tells the view before the router has the subscription, and births published
/// before it is in force would not reach that reader.
const READER_GRACE: Duration = Duration::from_millis(250);

/// Registry changes held back at most; beyond, the view reads the registry again.
const HELD_CHANGES: usize = crate::registry::CHANGES_CAPACITY;

/// How long a clean shutdown waits for the line's NDEATH to be handed to the router, and
/// then for the router to deliver it, before the clients' connections close.
const DEATH_GRACE: Duration = Duration::from_millis(300);

/// The running view: what the packet path's command stage and the shutdown need of it.
pub struct View {
    aliases: Arc<AliasBook>,
    stop: mpsc::Sender<oneshot::Sender<()>>,
    /// `fbbus_sparkplug_commands_total{result}`.
    pub commands: IntCounterVec,
    readers: Arc<super::Readers>,
}

impl View {
    /// Told of subscriptions: the view reads the line's values once a client reads
    /// Sparkplug.
    pub fn readers(&self) -> Arc<super::Readers> {
        Arc::clone(&self.readers)
    }

    /// The aliases of the line's born devices' metrics.
    pub fn aliases(&self) -> &Arc<AliasBook> {
        &self.aliases
    }

    /// Publishes the line's NDEATH and gives it [`DEATH_GRACE`] to reach the hosts,
    /// before the broker closes their connections.
    pub async fn shutdown(&self) {
        let (done, wait) = oneshot::channel();
        if self.stop.send(done).await.is_ok() {
            let _ = tokio::time::timeout(DEATH_GRACE, wait).await;
            tokio::time::sleep(DEATH_GRACE).await;
        }
    }
}

/// Starts the view of the line `config` describes on its router `link` (`fbbus:sparkplug`).
pub fn start(
    config: &crate::Config,
    registry: Arc<Registry>,
    metrics: &Metrics,
    link: (LinkTx, LinkRx),
) -> Arc<View> {
    let readers = Arc::new(super::Readers::default());
    let persistence = &config.persistence;
    let persistence = persistence.enabled.then_some(persistence.dir.as_path());
    let line = config.broker.line.as_str();
    let max_packet = config.broker.max_packet_bytes;
    let config = &config.sparkplug;
    let published = IntCounterVec::new(
        Opts::new(
            "fbbus_sparkplug_messages_total",
            "Sparkplug B messages the line's view published, by kind (NBIRTH, DDATA, ...)",
        ),
        &["kind"],
    )
    .expect("valid metric");
    let commands = IntCounterVec::new(
        Opts::new(
            "fbbus_sparkplug_commands_total",
            "Sparkplug DCMD commands of hosts, by result: delivered, or why refused \
             (not_authorized, port, type, device, malformed, off)",
        ),
        &["result"],
    )
    .expect("valid metric");
    for kind in ["NBIRTH", "NDEATH", "DBIRTH", "DDATA", "DDEATH"] {
        published.with_label_values(&[kind]);
    }
    for result in [
        "delivered",
        "not_authorized",
        "port",
        "type",
        "device",
        "malformed",
        "off",
    ] {
        commands.with_label_values(&[result]);
    }
    metrics.register(Box::new(published.clone()));
    metrics.register(Box::new(commands.clone()));
    let aliases = Arc::new(AliasBook::default());
    let nodes = Nodes::new(
        &config.group,
        line,
        config.remote_lines,
        BdSeqs::open(persistence),
        Arc::clone(&aliases),
    )
    .with_max_payload(max_packet);
    let (stop, stops) = mpsc::channel(1);
    // A thread of its own: the view decodes every accepted typed message and encodes
    // Sparkplug, work that on the workers' runtime would take turns with the sessions.
    let task = run(
        nodes,
        config.clone(),
        registry,
        link,
        stops,
        published,
        Arc::clone(&readers),
    );
    crate::supervisor::spawn_apart("fbbus-sparkplug", task);
    Arc::new(View {
        aliases,
        stop,
        commands,
        readers,
    })
}

/// A host application's `spBv1.0/STATE/<id>` (Sparkplug 3.0: JSON).
#[derive(Deserialize)]
struct State {
    online: bool,
    timestamp: u64,
}

async fn run(
    mut nodes: Nodes,
    config: SparkplugSection,
    registry: Arc<Registry>,
    link: (LinkTx, LinkRx),
    mut stops: mpsc::Receiver<oneshot::Sender<()>>,
    published: IntCounterVec,
    readers: Arc<super::Readers>,
) {
    let (mut tx, mut rx) = link;
    let mut changes = registry.changes();
    let filter = |path: String, rule| Filter {
        path,
        qos: QoS::AtMostOnce,
        nolocal: false,
        preserve_retain: false,
        retain_forward_rule: rule,
    };
    let mut filters = vec![filter(
        format!("{NAMESPACE}/{}/NCMD/+", config.group),
        RetainForwardRule::Never,
    )];
    if !config.primary_host.is_empty() {
        filters.push(filter(
            format!("{NAMESPACE}/STATE/{}", config.primary_host),
            RetainForwardRule::OnEverySubscribe,
        ));
    }
    let subscribe = Packet::Subscribe(Subscribe { pkid: 0, filters }, None);
    if tx.send(subscribe).await.is_err() {
        return;
    }
    let publisher: Arc<str> = CLIENT_ID.into();
    let mut send = Sender {
        tx,
        publisher,
        published,
    };
    let records = registry.list();
    if !send.all(nodes.start(records)).await {
        return;
    }
    let state_topic = format!("{NAMESPACE}/STATE/{}", config.primary_host);
    let mut primary_seen: Option<u64> = None;
    // Registry changes in order, each with when it may be applied (RECORD_DELAY).
    let mut held: VecDeque<(Instant, Change)> = VecDeque::new();
    let mut resync = false;
    let mut reading = false;
    let mut births_due: Option<Instant> = None;
    loop {
        let next_due = held.front().map(|(due, _)| *due);
        let out = tokio::select! {
            _ = sleep_until(births_due), if births_due.is_some() => {
                births_due = None;
                nodes.rebirth(None)
            },
            // The first Sparkplug reader: take the line's values from now on (the last ones
            // come as the retained `fb/` messages), and give the reader every birth.
            _ = readers.arrived(), if !reading => {
                reading = true;
                let subscribe = Packet::Subscribe(
                    Subscribe {
                        pkid: 0,
                        filters: vec![filter("fb/#".to_owned(), RetainForwardRule::OnEverySubscribe)],
                    },
                    None,
                );
                if send.tx.send(subscribe).await.is_err() {
                    return;
                }
                births_due = Some(Instant::now() + READER_GRACE);
                continue;
            },
            change = changes.recv() => match change {
                Ok(change) if held.len() < HELD_CHANGES => {
                    held.push_back((Instant::now() + RECORD_DELAY, change));
                    continue;
                }
                Ok(_) | Err(broadcast::error::RecvError::Lagged(_)) => {
                    resync = true;
                    continue;
                }
                Err(broadcast::error::RecvError::Closed) => return,
            },
            _ = sleep_until(next_due), if next_due.is_some() || resync => {
                let mut out = Out::new();
                let now = Instant::now();
                while held.front().is_some_and(|(due, _)| *due <= now) {
                    match held.pop_front() {
                        Some((_, Change::Record(record, _))) => out.extend(nodes.record(&record)),
                        Some((_, Change::Removed(id))) => out.extend(nodes.removed(&id)),
                        None => {}
                    }
                }
                // Fell behind: what is held is applied, then the registry as it is now.
                if resync && held.is_empty() {
                    resync = false;
                    for record in registry.list() {
                        out.extend(nodes.record(&record));
                    }
                }
                out
            },
            notification = rx.next() => {
                let Ok(first) = notification else { return };
                let mut batch = Vec::new();
                let Ok(paused) = link::take_batch(&mut rx, first, |forward| {
                    batch.push((forward.publish.topic, forward.publish.payload));
                }) else {
                    return;
                };
                let mut out = Out::new();
                let values = batch.iter().filter_map(|(topic, payload)| {
                    let topic = std::str::from_utf8(topic).ok()?;
                    topic.starts_with("fb/").then_some((topic, payload.as_ref()))
                });
                let data = nodes.values(values);
                // Until the first reader's births, values are only kept: they are in the
                // births, and data before them would be data of the births at start.
                if births_due.is_none() {
                    out.extend(data);
                }
                for (topic, payload) in &batch {
                    let Ok(topic) = std::str::from_utf8(topic) else { continue };
                    if topic.starts_with("fb/") {
                        continue;
                    } else if topic == state_topic {
                        // A primary host that comes online (again) gets every birth.
                        let Ok(state) = serde_json::from_slice::<State>(payload) else {
                            continue;
                        };
                        if state.online && primary_seen.is_none_or(|t| state.timestamp > t) {
                            primary_seen = Some(state.timestamp);
                            out.extend(nodes.rebirth(None));
                        }
                    } else if let Some(node) = rebirth_request(topic, payload, &config.group) {
                        out.extend(nodes.rebirth(Some(&node)));
                    }
                }
                if !send.all(out).await || paused.resume(&rx).await.is_err() {
                    return;
                }
                continue;
            }
            stop = stops.recv() => {
                let out = nodes.shutdown();
                let sent = send.all(out).await;
                if let Some(done) = stop {
                    let _ = done.send(());
                }
                if !sent {
                    return;
                }
                continue;
            }
        };
        if !send.all(out).await {
            return;
        }
    }
}

/// Sleeps until `due`; None: now (a resync waits for nothing).
async fn sleep_until(due: Option<Instant>) {
    if let Some(due) = due {
        tokio::time::sleep_until(due).await;
    }
}

/// The node an `NCMD` asks to be born again (`Node Control/Rebirth` = true, by name or
/// by its alias 1), if it is one.
fn rebirth_request(topic: &str, payload: &[u8], group: &str) -> Option<String> {
    let topic = Topic::parse(topic)?;
    if topic.kind != Kind::NCmd || topic.group != group {
        return None;
    }
    let payload = proto::Payload::decode(payload).ok()?;
    let asked = payload.metrics.iter().any(|m| {
        let named =
            m.name.as_deref() == Some(REBIRTH_METRIC) || (m.name.is_none() && m.alias == Some(1));
        named && m.value == Some(proto::payload::metric::Value::BooleanValue(true))
    });
    asked.then(|| topic.node.to_owned())
}

/// Publishes through the view's own link, at QoS 0 (Sparkplug's QoS for all of these).
struct Sender {
    tx: LinkTx,
    publisher: Arc<str>,
    published: IntCounterVec,
}

impl Sender {
    /// False when the router is gone.
    async fn all(&mut self, out: Out) -> bool {
        for (topic, payload) in out {
            if let Some(t) = Topic::parse(&topic) {
                self.published.with_label_values(&[t.kind.as_str()]).inc();
            }
            let mut publish = publish_packet(Bytes::from(topic), payload, 0, false, 0);
            origin::mark(&mut publish, origin::new(0, false, &self.publisher));
            if self.tx.send(Packet::Publish(publish, None)).await.is_err() {
                return false;
            }
        }
        true
    }
}

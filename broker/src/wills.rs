//! Last-will messages: kept by the connection, published by fbbus, not by rumqttd.
//!
//! rumqttd 0.20 publishes wills only from its own connection loop and gets several cases
//! wrong for a line (no will on keep-alive expiry of a keep-alive-0 client, none on
//! takeover, MQTT 5 will delay measured from the wrong moment). fbbus therefore never hands
//! the will to the router: the connection remembers it, decides at the end of the
//! connection whether it fires (see `connection::End::fires_will`), and this module
//! publishes it into the router through an internal link, immediately or after the
//! MQTT 5 will delay. A new connection with the same client id cancels a delayed will,
//! as MQTT 5 section 3.1.3.2.2 requires, if it is of the same identity (`identity`): the
//! session table refuses another identity's CONNECT before it gets here, and a delayed
//! will also remembers its owner, so it holds even once the session left the table.
//!
//! The will topic is checked against the ACL when the client connects, so a client
//! cannot use its will to publish where it may not publish itself.
//!
//! A will is published as the client set it: its user properties and every other
//! property reach subscribers unaltered [MQTT-3.3.2-17] [MQTT-3.3.2-18]. The session
//! number of the connection it belongs to (Sparkplug's `bdSeq` idea) is kept beside the
//! will, never in it: in the delayed wills' bookkeeping here, the "will published" log
//! line, and the device's registry record (`session`, `registry/`), which says which
//! session went offline. (Wills used to carry it as a `fbbus-session` user property,
//! which altered the application message.)

use std::collections::HashMap;
use std::sync::{Arc, Mutex, OnceLock, PoisonError};
use std::time::Duration;

use bytes::Bytes;
use rumqttd::protocol::{LastWill, LastWillProperties, PublishProperties};
use tokio::task::AbortHandle;

use crate::supervisor::Tasks;

use crate::broker_publisher::{BrokerPublisher, Message};
use crate::identity::Owner;
use crate::metrics::Metrics;
use crate::store::Store;

/// A will as the connection holds it.
#[derive(Debug, Clone)]
pub struct Will {
    pub topic: Bytes,
    pub payload: Bytes,
    pub qos: u8,
    pub retain: bool,
    pub properties: Option<LastWillProperties>,
    /// MQTT 5: min(will delay interval, session expiry interval); zero on 3.1.1.
    pub delay: Duration,
}

impl Will {
    pub fn from_connect(
        will: LastWill,
        properties: Option<LastWillProperties>,
        session_expiry: u32,
    ) -> Will {
        let delay = properties
            .as_ref()
            .and_then(|p| p.delay_interval)
            .unwrap_or(0)
            .min(session_expiry);
        Will {
            topic: will.topic,
            payload: will.message,
            qos: will.qos as u8,
            retain: will.retain,
            properties,
            delay: Duration::from_secs(delay as u64),
        }
    }

    /// The client's DISCONNECT set a new Session Expiry Interval: the delay is again
    /// min(will delay interval, session expiry) (MQTT 5 3.1.3.2.2, 3.14.2.2.2).
    pub fn set_session_expiry(&mut self, session_expiry: u32) {
        let interval = self
            .properties
            .as_ref()
            .and_then(|p| p.delay_interval)
            .unwrap_or(0);
        self.delay = Duration::from_secs(interval.min(session_expiry) as u64);
    }
}

/// A will waiting for its delay.
struct Delayed {
    owner: Owner,
    /// The session number of the connection whose will it is (`session::table`).
    session: u64,
    task: AbortHandle,
}

/// A connection's will as the line console shows it ([`Wills::armed`]): text cut to
/// [`ArmedWill::MAX_CHARS`] characters, so the table costs at most a few hundred bytes per
/// connection.
#[derive(Debug, Clone, serde::Serialize)]
pub struct ArmedWill {
    pub topic: String,
    pub payload: String,
    /// The topic or the payload was cut.
    pub truncated: bool,
    pub qos: u8,
    pub retain: bool,
    /// MQTT 5 will delay (0: at once).
    pub delay_s: u64,
}

impl ArmedWill {
    pub const MAX_CHARS: usize = 200;

    fn of(will: &Will) -> ArmedWill {
        let (topic, cut_topic) = excerpt(&will.topic);
        let (payload, cut_payload) = excerpt(&will.payload);
        ArmedWill {
            topic,
            payload,
            truncated: cut_topic || cut_payload,
            qos: will.qos,
            retain: will.retain,
            delay_s: will.delay.as_secs(),
        }
    }
}

/// At most [`ArmedWill::MAX_CHARS`] characters of `bytes` as lossy UTF-8, cut at a
/// character boundary; whether it was cut.
fn excerpt(bytes: &[u8]) -> (String, bool) {
    let text = String::from_utf8_lossy(bytes);
    match text.char_indices().nth(ArmedWill::MAX_CHARS) {
        Some((at, _)) => (text[..at].to_owned(), true),
        None => (text.into_owned(), false),
    }
}

/// Publishes wills and keeps the delayed ones until they are due.
pub struct Wills {
    publisher: Arc<BrokerPublisher>,
    /// By client id: the will each connection holds now, with the connection's session
    /// number (a takeover's new connection arms before the old one disarms). One entry per
    /// connection: bounded by `[broker] max_connections`.
    armed: Mutex<HashMap<String, (u64, ArmedWill)>>,
    /// By client id: the delayed wills' tasks, with whose identity and connection
    /// (session number) they are.
    delayed: Mutex<HashMap<String, Vec<Delayed>>>,
    metrics: Arc<Metrics>,
    /// Where delayed wills wait: finished (not fired) when the broker shuts down.
    tasks: Tasks,
    /// Where delayed wills and retained or queued wills are kept across a restart.
    store: OnceLock<Arc<Store>>,
}

impl Wills {
    pub fn new(publisher: Arc<BrokerPublisher>, metrics: Arc<Metrics>, tasks: Tasks) -> Arc<Wills> {
        Arc::new(Wills {
            publisher,
            armed: Mutex::new(HashMap::new()),
            delayed: Mutex::new(HashMap::new()),
            metrics,
            tasks,
            store: OnceLock::new(),
        })
    }

    /// Connection `session` of `client_id` holds `will` (the line console shows it).
    pub fn arm(&self, client_id: &str, session: u64, will: &Will) {
        self.armed
            .lock()
            .unwrap_or_else(PoisonError::into_inner)
            .insert(client_id.to_owned(), (session, ArmedWill::of(will)));
    }

    /// Connection `session` of `client_id` ended or dropped its will; a newer
    /// connection's will stays.
    pub fn disarm(&self, client_id: &str, session: u64) {
        let mut armed = self.armed.lock().unwrap_or_else(PoisonError::into_inner);
        if armed.get(client_id).is_some_and(|(s, _)| *s == session) {
            armed.remove(client_id);
        }
    }

    /// The will the connection of `client_id` holds now, if any.
    pub fn armed(&self, client_id: &str) -> Option<ArmedWill> {
        self.armed
            .lock()
            .unwrap_or_else(PoisonError::into_inner)
            .get(client_id)
            .map(|(_, will)| will.clone())
    }

    /// Keeps delayed wills, and wills that are retained or queued for persistent
    /// sessions, in `store` from now on.
    pub fn set_store(&self, store: Arc<Store>) {
        let _ = self.store.set(store);
    }

    /// Schedules the delayed wills the store held at start: each is published when what
    /// was left of its delay has passed, unless its client comes back first.
    pub fn restore(
        self: &Arc<Self>,
        owners: &HashMap<String, Owner>,
        wills: Vec<(String, Duration, Arc<crate::store::Message>)>,
    ) {
        for (client_id, left, m) in wills {
            let owner = owners.get(&client_id).cloned().unwrap_or(Owner::Anonymous);
            let will = Will {
                topic: m.topic.clone(),
                payload: m.payload.clone(),
                qos: m.qos,
                retain: m.retain,
                properties: m
                    .properties
                    .as_deref()
                    .cloned()
                    .map(|p| LastWillProperties {
                        delay_interval: None,
                        payload_format_indicator: p.payload_format_indicator,
                        message_expiry_interval: p.message_expiry_interval,
                        content_type: p.content_type,
                        response_topic: p.response_topic,
                        correlation_data: p.correlation_data,
                        user_properties: p.user_properties,
                    }),
                delay: left.max(Duration::from_millis(1)),
            };
            // Already in the store: scheduled without writing it again.
            self.schedule(&client_id, 0, &owner, will);
        }
    }

    /// `owner` connected with this client id: its wills still waiting for their delay
    /// are dropped. Another identity's are not.
    pub fn cancel_delayed(&self, client_id: &str, owner: &Owner) {
        let mut delayed = self.delayed.lock().unwrap_or_else(PoisonError::into_inner);
        let Some(tasks) = delayed.get_mut(client_id) else {
            return;
        };
        let waiting = tasks.len();
        tasks.retain(|d| {
            if &d.owner == owner {
                d.task.abort();
                tracing::debug!(
                    client_id,
                    session = d.session,
                    "delayed will cancelled by reconnect"
                );
            }
            &d.owner != owner
        });
        if tasks.len() < waiting {
            if let Some(store) = self.store.get() {
                store.write_now(vec![crate::store::Record::WillDone {
                    client: client_id.into(),
                }]);
            }
        }
        if tasks.is_empty() {
            delayed.remove(client_id);
        }
    }

    /// Publishes `will` of `client_id`'s session `session`, which `owner` created, now, or
    /// after its delay unless the client comes back first.
    pub fn fire(self: &Arc<Self>, client_id: &str, session: u64, owner: &Owner, will: Will) {
        if will.delay.is_zero() {
            self.publish(client_id, session, will);
            return;
        }
        if let Some(store) = self.store.get() {
            store.write_now(vec![crate::store::Record::Will {
                client: client_id.into(),
                due: crate::store::now_ms() + will.delay.as_millis() as u64,
                message: stored_will(client_id, &will),
            }]);
        }
        self.schedule(client_id, session, owner, will);
    }

    fn schedule(self: &Arc<Self>, client_id: &str, session: u64, owner: &Owner, will: Will) {
        let this = Arc::clone(self);
        let id = client_id.to_owned();
        let task = self.tasks.spawn(async move {
            tokio::time::sleep(will.delay).await;
            this.forget(&id, tokio::task::id());
            if let Some(store) = this.store.get() {
                store.write_now(vec![crate::store::Record::WillDone {
                    client: id.as_str().into(),
                }]);
            }
            this.publish(&id, session, will);
        });
        // Several when a typed will is published in several encodings.
        self.delayed
            .lock()
            .unwrap_or_else(PoisonError::into_inner)
            .entry(client_id.to_owned())
            .or_default()
            .push(Delayed {
                owner: owner.clone(),
                session,
                task,
            });
    }

    /// The delayed will `task` of `client_id` is due: it can no longer be cancelled.
    fn forget(&self, client_id: &str, task: tokio::task::Id) {
        let mut delayed = self.delayed.lock().unwrap_or_else(PoisonError::into_inner);
        if let Some(tasks) = delayed.get_mut(client_id) {
            tasks.retain(|d| d.task.id() != task);
            if tasks.is_empty() {
                delayed.remove(client_id);
            }
        }
    }

    fn publish(&self, client_id: &str, session: u64, will: Will) {
        tracing::info!(client_id, session, topic = ?String::from_utf8_lossy(&will.topic), "will published");
        self.metrics.wills_published.inc();
        let qos = will.qos.min(1);
        // A retained will, or one persistent sessions subscribe to, is stored as a
        // client's publication is (`store`), before the router has it.
        let seq = match self.store.get().filter(|s| s.stores(qos, will.retain)) {
            Some(store) => {
                let seq = store.number();
                let mut message = stored_will(client_id, &will);
                message.qos = qos;
                store.write_now(vec![crate::store::Record::Publish { seq, message }]);
                seq
            }
            None => 0,
        };
        // Exactly the client's properties: nothing added, nothing reordered.
        let properties = will.properties.map(|p| Box::new(publish_properties(p)));
        self.publisher.publish(Message {
            topic: will.topic,
            payload: will.payload,
            // QoS 2 would need a PUBREL exchange on the internal link; QoS 1 already gives
            // subscribers at-least-once delivery of the will, which is what a will needs.
            qos,
            retain: will.retain,
            properties,
            publisher: client_id.to_owned(),
            stored: seq,
        });
    }
}

/// A will as the store keeps it.
fn stored_will(client_id: &str, will: &Will) -> crate::store::Message {
    crate::store::Message {
        topic: will.topic.clone(),
        payload: will.payload.clone(),
        qos: will.qos,
        retain: will.retain,
        properties: will
            .properties
            .clone()
            .map(publish_properties)
            .map(Box::new),
        publisher: client_id.into(),
    }
}

/// A will's properties as the PUBLISH that carries it has them (no delay, no alias).
fn publish_properties(p: LastWillProperties) -> PublishProperties {
    PublishProperties {
        payload_format_indicator: p.payload_format_indicator,
        message_expiry_interval: p.message_expiry_interval,
        topic_alias: None,
        response_topic: p.response_topic,
        correlation_data: p.correlation_data,
        user_properties: p.user_properties,
        subscription_identifiers: Vec::new(),
        content_type: p.content_type,
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A will's text as the console shows it: cut at a character boundary, multi-byte and
    /// invalid UTF-8 included, never a panic.
    #[test]
    fn a_will_excerpt_is_cut_at_a_character_boundary() {
        let long = "ü€".repeat(300);
        let (text, cut) = excerpt(long.as_bytes());
        assert!(cut);
        assert_eq!(text.chars().count(), ArmedWill::MAX_CHARS);
        let (text, cut) = excerpt(&[0xff, 0xfe, b'a']);
        assert!(!cut);
        assert_eq!(text, "\u{fffd}\u{fffd}a");
        assert_eq!(excerpt(b""), (String::new(), false));
    }
}

//! Last-will messages: kept by the connection, published by fbbus, not by rumqttd.
//!
//! rumqttd 0.20 publishes wills only from its own connection loop and gets several cases
//! wrong for a line (no will on keep-alive expiry of a keep-alive-0 client, none on
//! takeover, MQTT 5 will delay measured from the wrong moment). fbbus therefore never hands
//! the will to the router: the connection remembers it, decides at the end of the
//! connection whether it fires (see `connection::End::fires_will`), and this module
//! publishes it into the router through an internal link, immediately or after the
//! MQTT 5 will delay. A new connection with the same client id cancels a delayed will,
//! as MQTT 5 section 3.1.3.2.2 requires.
//!
//! The will topic is checked against the ACL when the client connects, so a client
//! cannot use its will to publish where it may not publish itself.

use std::collections::HashMap;
use std::sync::{Arc, Mutex};
use std::time::Duration;

use bytes::{BufMut, Bytes, BytesMut};
use rumqttd::local::{LinkRx, LinkTx};
use rumqttd::protocol::{LastWill, LastWillProperties, Packet, Publish, PublishProperties};
use tokio::task::JoinHandle;

use crate::metrics::Metrics;

/// The client id of the broker's own router link; clients may not use it.
pub const INTERNAL_CLIENT_ID: &str = "fbbus:internal";

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
}

/// Publishes wills into the router and keeps the delayed ones until they are due.
pub struct Wills {
    link: tokio::sync::Mutex<(LinkTx, u16)>,
    delayed: Mutex<HashMap<String, JoinHandle<()>>>,
    metrics: Arc<Metrics>,
}

impl Wills {
    /// `link` is the broker's internal router link; its acknowledgements are drained here.
    pub fn new(link: (LinkTx, LinkRx), metrics: Arc<Metrics>) -> Arc<Wills> {
        let (tx, mut rx) = link;
        tokio::spawn(async move {
            // The router acknowledges QoS 1 wills to this link; nothing waits for them.
            while let Ok(notification) = rx.next().await {
                if matches!(notification, Some(rumqttd::Notification::Unschedule)) {
                    let _ = rx.wake().await;
                }
            }
        });
        Arc::new(Wills {
            link: tokio::sync::Mutex::new((tx, 0)),
            delayed: Mutex::new(HashMap::new()),
            metrics,
        })
    }

    /// A client with this id connected: a will still waiting for its delay is dropped.
    pub fn cancel_delayed(&self, client_id: &str) {
        if let Some(task) = self
            .delayed
            .lock()
            .expect("lock poisoned")
            .remove(client_id)
        {
            task.abort();
            tracing::debug!(client_id, "delayed will cancelled by reconnect");
        }
    }

    /// Publishes `will` now, or after its delay unless the client comes back first.
    pub fn fire(self: &Arc<Self>, client_id: &str, will: Will) {
        if will.delay.is_zero() {
            let this = Arc::clone(self);
            let client_id = client_id.to_owned();
            tokio::spawn(async move { this.publish(&client_id, will).await });
            return;
        }
        let this = Arc::clone(self);
        let id = client_id.to_owned();
        let task = tokio::spawn(async move {
            tokio::time::sleep(will.delay).await;
            this.delayed.lock().expect("lock poisoned").remove(&id);
            this.publish(&id, will).await;
        });
        if let Some(old) = self
            .delayed
            .lock()
            .expect("lock poisoned")
            .insert(client_id.to_owned(), task)
        {
            old.abort();
        }
    }

    async fn publish(&self, client_id: &str, will: Will) {
        let mut link = self.link.lock().await;
        // QoS 2 would need a PUBREL exchange on the internal link; QoS 1 already gives
        // subscribers at-least-once delivery of the will, which is what a will needs.
        let qos = will.qos.min(1);
        link.1 = link.1 % u16::MAX + 1;
        let publish = publish_packet(&will.topic, &will.payload, qos, will.retain, link.1);
        let mut properties = will.properties.map(|p| PublishProperties {
            payload_format_indicator: p.payload_format_indicator,
            message_expiry_interval: p.message_expiry_interval,
            topic_alias: None,
            response_topic: p.response_topic,
            correlation_data: p.correlation_data,
            user_properties: p.user_properties,
            subscription_identifiers: Vec::new(),
            content_type: p.content_type,
        });
        crate::origin::mark(
            &mut properties,
            &crate::origin::Origin {
                qos,
                retain: will.retain,
                publisher: client_id.to_owned(),
            },
        );
        match link.0.send(Packet::Publish(publish, properties)).await {
            Ok(_) => {
                self.metrics.wills_published.inc();
                tracing::info!(client_id, topic = %String::from_utf8_lossy(&will.topic), "will published");
            }
            Err(e) => tracing::error!(client_id, error = %e, "could not publish will: router gone"),
        }
    }
}

/// Builds a `Publish` with a QoS and packet id. rumqttd keeps those fields crate-private;
/// its public, stable serialisation format is the way to set them.
pub fn publish_packet(topic: &[u8], payload: &[u8], qos: u8, retain: bool, pkid: u16) -> Publish {
    let mut raw = BytesMut::with_capacity(5 + topic.len() + payload.len());
    raw.put_u8(0b0011_0000 | (qos << 1) | retain as u8);
    raw.put_u16(pkid);
    raw.put_u16(topic.len() as u16);
    raw.extend_from_slice(topic);
    raw.extend_from_slice(payload);
    Publish::deserialize(raw.freeze())
}

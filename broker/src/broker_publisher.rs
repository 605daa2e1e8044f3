//! The broker's own publications: wills, registry records, diagnostics.
//!
//! Everything fbbus publishes itself goes through one internal router link
//! (`fbbus:internal`), fed by one task from a queue. One queue keeps the broker's messages
//! in the order they were decided — a device's retained registry record must never be
//! overwritten by an older one — and lets any code publish without awaiting the router.

use std::sync::Arc;

use bytes::Bytes;
use rumqttd::local::{LinkRx, LinkTx};
use rumqttd::protocol::{Packet, Publish, PublishProperties};
use tokio::sync::mpsc;

use crate::link;
use crate::policy::origin;
use crate::supervisor::Tasks;

/// The client id of the broker's own router link; clients may not use it.
pub const INTERNAL_CLIENT_ID: &str = "fbbus:internal";

/// The publisher of what came from the bus (the bridge's import link): the exporter never
/// puts a message of this publisher back on the bus.
pub const BUS_CLIENT_ID: &str = "fbbus:bridge-in";

/// Client ids starting with this are the broker's own router links (its publisher, the
/// readiness probe, the bus bridge's links): a client may not take one.
pub const RESERVED_CLIENT_ID_PREFIX: &str = "fbbus:";

/// Whether `id` is one of the broker's own client ids.
pub fn is_reserved_client_id(id: &str) -> bool {
    id.starts_with(RESERVED_CLIENT_ID_PREFIX)
}

/// One message the broker publishes.
#[derive(Debug)]
pub struct Message {
    pub topic: Bytes,
    pub payload: Bytes,
    /// 0 or 1: QoS 2 would need a PUBREL exchange on the internal link for no gain.
    pub qos: u8,
    pub retain: bool,
    pub properties: Option<Box<PublishProperties>>,
    /// The client the message is published for (a will's owner), or the broker itself.
    pub publisher: String,
    /// Its number in the store (`store`), 0 when it is not stored.
    pub stored: u64,
}

impl Message {
    /// A message from the broker itself, at QoS 1.
    pub fn broker(topic: impl Into<Bytes>, payload: impl Into<Bytes>, retain: bool) -> Message {
        Message {
            topic: topic.into(),
            payload: payload.into(),
            qos: 1,
            retain,
            properties: None,
            publisher: INTERNAL_CLIENT_ID.to_owned(),
            stored: 0,
        }
    }
}

/// Hands messages to the internal link's task.
#[derive(Clone)]
pub struct BrokerPublisher {
    queue: mpsc::UnboundedSender<Message>,
    /// Where the broker's retained messages are kept across a restart, as a client's are
    /// (`store`): the clearing of a retyped port's retained value, a retained will. Not
    /// its own `fbbus/` records: the registry is their source and publishes them again at
    /// start (a stored copy put back after it would bring back a stale status).
    store: Arc<std::sync::OnceLock<Arc<crate::store::Store>>>,
}

impl BrokerPublisher {
    /// Starts the tasks that own the internal link `(tx, rx)`: core tasks (`supervisor`),
    /// since wills and registry records stop without them.
    pub fn start(link: (LinkTx, LinkRx), tasks: &Tasks) -> Arc<BrokerPublisher> {
        let (mut tx, rx) = link;
        let (queue, mut messages) = mpsc::unbounded_channel::<Message>();
        tasks.core("broker publisher (acknowledgements)", async move {
            // The router acknowledges QoS 1 messages to this link; nothing waits for them.
            link::discard(rx).await;
        });
        tasks.core("broker publisher", async move {
            let mut pkid: u16 = 0;
            while let Some(message) = messages.recv().await {
                pkid = pkid % u16::MAX + 1;
                let topic = String::from_utf8_lossy(&message.topic).into_owned();
                let qos = message.qos.min(1);
                let mut publish =
                    publish_packet(message.topic, message.payload, qos, message.retain, pkid);
                let properties = message.properties;
                let mut mark = origin::new(qos, message.retain, &message.publisher.into());
                mark.stored = message.stored;
                origin::mark(&mut publish, mark);
                if let Err(e) = tx.send(Packet::Publish(publish, properties)).await {
                    tracing::error!(topic, error = %e, "router gone: broker message not published");
                    return;
                }
            }
        });
        Arc::new(BrokerPublisher {
            queue,
            store: Arc::default(),
        })
    }

    /// Stores the broker's retained messages in `store` from now on.
    pub fn set_store(&self, store: Arc<crate::store::Store>) {
        let _ = self.store.set(store);
    }

    /// A publisher whose messages go to the returned queue instead of a router (tests).
    #[cfg(test)]
    pub fn detached() -> (Arc<BrokerPublisher>, mpsc::UnboundedReceiver<Message>) {
        let (queue, messages) = mpsc::unbounded_channel();
        let publisher = BrokerPublisher {
            queue,
            store: Arc::default(),
        };
        (Arc::new(publisher), messages)
    }

    /// Queues `message`; it is published after every message queued before it.
    pub fn publish(&self, mut message: Message) {
        if let Some(store) = self.store.get() {
            // `$SYS/` is the broker's status of the moment: published afresh at start.
            let own = message
                .topic
                .starts_with(fb_bridge::topic::BROKER_NAMESPACE.as_bytes())
                || message
                    .topic
                    .starts_with(security::acl::SYS_PREFIX.as_bytes());
            if message.retain && message.stored == 0 && !own {
                let seq = store.number();
                message.stored = seq;
                store.write_now(vec![crate::store::Record::Publish {
                    seq,
                    message: crate::store::Message {
                        topic: message.topic.clone(),
                        payload: message.payload.clone(),
                        qos: message.qos.min(1),
                        retain: true,
                        properties: message.properties.clone(),
                        publisher: message.publisher.as_str().into(),
                    },
                }]);
            }
        }
        // Fails only once the task ended with the router, when nothing can be published.
        let _ = self.queue.send(message);
    }
}

/// The QoS (0, 1, 2) and packet id of a `Publish`.
#[cfg_attr(not(feature = "bridge"), allow(dead_code))]
pub fn qos_and_pkid(publish: &Publish) -> (u8, u16) {
    publish.qos_and_pkid()
}

/// Builds a `Publish` with a QoS and packet id (no copy of topic or payload).
pub fn publish_packet(
    topic: impl Into<Bytes>,
    payload: impl Into<Bytes>,
    qos: u8,
    retain: bool,
    pkid: u16,
) -> Publish {
    Publish::with_qos(topic.into(), payload.into(), qos, retain, pkid)
}

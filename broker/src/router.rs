//! rumqttd's router, the part of rumqttd fbbus keeps: subscriptions, retained messages,
//! per-filter commit logs and QoS bookkeeping, on its own thread.
//!
//! Connections reach it through links (`LinkTx` towards the router, `LinkRx` back).
//! rumqttd does not export the type of the router's event channel, so the channel is
//! captured in a closure here and the rest of the broker only sees [`RouterHandle::link`].

use rumqttd::local::{LinkBuilder, LinkError, LinkRx, LinkTx};
use rumqttd::protocol::{Disconnect, DisconnectReasonCode, Packet};
use rumqttd::{Notification, Router, RouterConfig};

use crate::config::BrokerSection;

type Connect =
    dyn Fn(&str, bool, u16) -> Result<(LinkTx, LinkRx, Notification), LinkRefused> + Send + Sync;

/// The router did not register a link (it is gone, or full).
#[derive(Debug, thiserror::Error)]
#[error("the router refused the connection: {0}")]
pub struct LinkRefused(String);

pub struct RouterHandle {
    connect: Box<Connect>,
}

impl RouterHandle {
    /// Starts the router thread with the line's memory bounds.
    pub fn spawn(broker: &BrokerSection) -> RouterHandle {
        let config = RouterConfig {
            // One extra for the broker's internal link.
            max_connections: broker.max_connections + 1,
            max_outgoing_packet_count: broker.router_max_outgoing_packets,
            max_segment_size: broker.router_segment_bytes,
            max_segment_count: broker.router_segment_count,
            custom_segment: None,
            initialized_filters: None,
            shared_subscriptions_strategy: Default::default(),
        };
        let router_tx = Router::new(0, config).spawn();
        RouterHandle {
            connect: Box::new(move |client_id, clean_session, topic_alias_max| {
                LinkBuilder::new(client_id, router_tx.clone())
                    .clean_session(clean_session)
                    .dynamic_filters(true)
                    .topic_alias_max(topic_alias_max)
                    .build()
                    .map_err(|e| LinkRefused(e.to_string()))
            }),
        }
    }

    /// Registers a connection with the router. A connection with the same client id is
    /// dropped by the router (its `LinkRx` fails), which is how takeover reaches it.
    /// Blocks until the router answers, which it does within its next event loop turn.
    pub fn link(
        &self,
        client_id: &str,
        clean_session: bool,
        topic_alias_max: u16,
    ) -> Result<(LinkTx, LinkRx, Notification), LinkRefused> {
        (self.connect)(client_id, clean_session, topic_alias_max)
    }
}

/// Tells the router a link ended: it drops the link and, for a clean session, its state.
pub async fn unlink(mut link_tx: LinkTx) -> Result<usize, LinkError> {
    link_tx
        .send(Packet::Disconnect(
            Disconnect {
                reason_code: DisconnectReasonCode::NormalDisconnection,
            },
            None,
        ))
        .await
}

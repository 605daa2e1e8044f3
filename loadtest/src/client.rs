//! The harness's MQTT client: rumqttc, MQTT 3.1.1 or 5, plain or TLS, behind one small
//! API the scenarios share.
//!
//! Received messages go to a callback run on the connection's own task, with no queue in
//! between: the subscriber stamps the arrival time the moment rumqttc hands the packet
//! over. A connection that drops is not re-established: in a load test a drop is a
//! result to report, not something to hide.

use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::Arc;
use std::time::Duration;

use rumqttc::v5 as r5;
use rumqttc::{QoS, TlsConfiguration, Transport};
use tokio::sync::{mpsc, oneshot};
use tokio::task::JoinHandle;

use crate::target::{Mqtt, Target};
use crate::Error;

/// Called with (topic, payload) for every PUBLISH received.
pub type OnPublish = Arc<dyn Fn(&[u8], &[u8]) + Send + Sync>;

/// Requests rumqttc may queue before `publish` waits: enough to keep the socket busy.
const REQUEST_QUEUE: usize = 4096;

/// Per-connection settings.
#[derive(Debug, Clone)]
pub struct ClientConfig {
    pub id: String,
    pub keep_alive: Duration,
    pub clean: bool,
    /// QoS 1/2 messages in flight before the client waits for acknowledgements.
    pub inflight: u16,
    /// Bound on connecting and on every acknowledgement.
    pub timeout: Duration,
}

impl ClientConfig {
    pub fn new(id: impl Into<String>) -> ClientConfig {
        ClientConfig {
            id: id.into(),
            keep_alive: Duration::from_secs(60),
            clean: true,
            inflight: 100,
            timeout: Duration::from_secs(10),
        }
    }
}

/// `0`, `1`, `2` as rumqttc's QoS.
pub fn qos(level: u8) -> QoS {
    match level {
        0 => QoS::AtMostOnce,
        1 => QoS::AtLeastOnce,
        _ => QoS::ExactlyOnce,
    }
}

enum Handle {
    V4(rumqttc::AsyncClient),
    V5(r5::AsyncClient),
}

/// What the connection task reports back.
enum Ack {
    /// A SUBACK: whether every filter was granted.
    Sub(bool),
}

/// One connected client.
pub struct Client {
    handle: Handle,
    id: String,
    address: String,
    timeout: Duration,
    acks: mpsc::UnboundedReceiver<Ack>,
    alive: Arc<AtomicBool>,
    task: JoinHandle<()>,
}

impl Client {
    /// Connects and waits for the CONNACK. Refusals (bad password, not authorized) are
    /// [`Error::Refused`]; everything else that keeps the connection from coming up is
    /// [`Error::Connect`].
    pub async fn connect(
        target: &Target,
        config: &ClientConfig,
        on_publish: Option<OnPublish>,
    ) -> Result<Client, Error> {
        let transport = transport(target)?;
        let (ack_tx, acks) = mpsc::unbounded_channel();
        let (first_tx, first_rx) = oneshot::channel();
        let alive = Arc::new(AtomicBool::new(true));
        let events = Events {
            on_publish,
            acks: ack_tx,
            first: Some(first_tx),
            alive: alive.clone(),
        };
        let (handle, task) = match target.mqtt {
            Mqtt::V311 => {
                let mut o = rumqttc::MqttOptions::new(&config.id, &target.host, target.port);
                o.set_keep_alive(config.keep_alive)
                    .set_clean_session(config.clean)
                    .set_inflight(config.inflight.max(1))
                    .set_max_packet_size(1 << 20, 1 << 20)
                    .set_transport(transport);
                if let (Some(u), Some(p)) = (&target.username, &target.password) {
                    o.set_credentials(u, p);
                }
                let (client, mut eventloop) = rumqttc::AsyncClient::new(o, REQUEST_QUEUE);
                eventloop.network_options.set_tcp_nodelay(true);
                eventloop
                    .network_options
                    .set_connection_timeout(config.timeout.as_secs().max(1));
                (Handle::V4(client), tokio::spawn(run_v4(eventloop, events)))
            }
            Mqtt::V5 => {
                let mut o = r5::MqttOptions::new(&config.id, &target.host, target.port);
                o.set_keep_alive(config.keep_alive)
                    .set_clean_start(config.clean)
                    .set_outgoing_inflight_upper_limit(config.inflight.max(1))
                    .set_max_packet_size(Some(1 << 20))
                    .set_connection_timeout(config.timeout.as_secs().max(1))
                    .set_transport(transport);
                if let (Some(u), Some(p)) = (&target.username, &target.password) {
                    o.set_credentials(u, p);
                }
                let mut network = rumqttc::NetworkOptions::new();
                network.set_tcp_nodelay(true);
                network.set_connection_timeout(config.timeout.as_secs().max(1));
                o.set_network_options(network);
                let (client, eventloop) = r5::AsyncClient::new(o, REQUEST_QUEUE);
                (Handle::V5(client), tokio::spawn(run_v5(eventloop, events)))
            }
        };
        let client = Client {
            handle,
            id: config.id.clone(),
            address: target.address.clone(),
            timeout: config.timeout,
            acks,
            alive,
            task,
        };
        let connect_error = |reason: String| Error::Connect {
            id: config.id.clone(),
            address: target.address.clone(),
            reason,
        };
        match tokio::time::timeout(config.timeout, first_rx).await {
            Ok(Ok(Ok(()))) => Ok(client),
            Ok(Ok(Err(Failure::Refused(reason)))) => {
                client.abort();
                Err(Error::Refused {
                    id: config.id.clone(),
                    address: target.address.clone(),
                    reason,
                })
            }
            Ok(Ok(Err(Failure::Other(reason)))) => {
                client.abort();
                Err(connect_error(reason))
            }
            Ok(Err(_)) => Err(connect_error("the connection task ended".into())),
            Err(_) => {
                client.abort();
                Err(connect_error(format!(
                    "no CONNACK within {:?}",
                    config.timeout
                )))
            }
        }
    }

    pub fn id(&self) -> &str {
        &self.id
    }

    /// Whether the connection is still up.
    pub fn alive(&self) -> bool {
        self.alive.load(Ordering::Relaxed)
    }

    /// Hands one PUBLISH to the client (waits only when its request queue is full).
    pub async fn publish(&self, topic: &str, qos: QoS, payload: Vec<u8>) -> Result<(), Error> {
        let sent = match &self.handle {
            Handle::V4(c) => c.publish(topic, qos, false, payload).await.is_ok(),
            Handle::V5(c) => c.publish(topic, v5_qos(qos), false, payload).await.is_ok(),
        };
        if sent {
            Ok(())
        } else {
            Err(self.closed("publishing"))
        }
    }

    /// Subscribes to `filters` and waits for the SUBACK granting all of them.
    pub async fn subscribe(&mut self, filters: &[String], qos: QoS) -> Result<(), Error> {
        let sent = match &self.handle {
            Handle::V4(c) => c
                .subscribe_many(
                    filters
                        .iter()
                        .map(|f| rumqttc::SubscribeFilter::new(f.clone(), qos)),
                )
                .await
                .is_ok(),
            Handle::V5(c) => c
                .subscribe_many(
                    filters
                        .iter()
                        .map(|f| r5::mqttbytes::v5::Filter::new(f.clone(), v5_qos(qos))),
                )
                .await
                .is_ok(),
        };
        if !sent {
            return Err(self.closed("subscribing"));
        }
        match tokio::time::timeout(self.timeout, self.acks.recv()).await {
            Ok(Some(Ack::Sub(true))) => Ok(()),
            Ok(Some(Ack::Sub(false))) => Err(Error::Refused {
                id: self.id.clone(),
                address: self.address.clone(),
                reason: format!("SUBACK refused {filters:?} (check the broker's access rules)"),
            }),
            Ok(None) => Err(self.closed("waiting for SUBACK")),
            Err(_) => Err(Error::Timeout {
                waited: self.timeout,
                what: format!("SUBACK for {} ({})", filters.join(" "), self.id),
            }),
        }
    }

    /// A clean DISCONNECT, then waits (bounded) for the connection to end.
    pub async fn disconnect(self) {
        let sent = match &self.handle {
            Handle::V4(c) => c.disconnect().await.is_ok(),
            Handle::V5(c) => c.disconnect().await.is_ok(),
        };
        let mut task = self.task;
        if !sent
            || tokio::time::timeout(Duration::from_secs(2), &mut task)
                .await
                .is_err()
        {
            task.abort();
        }
    }

    /// Drops the connection without DISCONNECT (the broker sees a lost client).
    pub fn abort(self) {
        self.task.abort();
    }

    fn closed(&self, doing: &str) -> Error {
        Error::Closed {
            id: self.id.clone(),
            address: self.address.clone(),
            reason: format!("connection lost while {doing}"),
        }
    }
}

fn v5_qos(qos: QoS) -> r5::mqttbytes::QoS {
    match qos {
        QoS::AtMostOnce => r5::mqttbytes::QoS::AtMostOnce,
        QoS::AtLeastOnce => r5::mqttbytes::QoS::AtLeastOnce,
        QoS::ExactlyOnce => r5::mqttbytes::QoS::ExactlyOnce,
    }
}

fn transport(target: &Target) -> Result<Transport, Error> {
    if !target.tls {
        return Ok(Transport::Tcp);
    }
    let Some(ca) = &target.ca else {
        return Err(Error::Target(format!(
            "{} is TLS: give the CA certificate that signed the broker's with --ca FILE",
            target.address
        )));
    };
    let ca = std::fs::read(ca).map_err(|e| Error::Target(format!("--ca {}: {e}", ca.display())))?;
    Ok(Transport::tls_with_config(TlsConfiguration::Simple {
        ca,
        alpn: None,
        client_auth: None,
    }))
}

enum Failure {
    Refused(String),
    Other(String),
}

/// The connection task's outputs.
struct Events {
    on_publish: Option<OnPublish>,
    acks: mpsc::UnboundedSender<Ack>,
    first: Option<oneshot::Sender<Result<(), Failure>>>,
    alive: Arc<AtomicBool>,
}

impl Events {
    fn connected(&mut self) {
        if let Some(first) = self.first.take() {
            let _ = first.send(Ok(()));
        }
    }

    fn publish(&self, topic: &[u8], payload: &[u8]) {
        if let Some(f) = &self.on_publish {
            f(topic, payload);
        }
    }

    /// The connection ended; the first error is the connect's result if it never came up.
    fn ended(&mut self, failure: Failure) {
        self.alive.store(false, Ordering::Relaxed);
        if let Some(first) = self.first.take() {
            let _ = first.send(Err(failure));
        }
    }
}

async fn run_v4(mut eventloop: rumqttc::EventLoop, mut events: Events) {
    use rumqttc::{ConnectionError, Event, Packet, SubscribeReasonCode};
    loop {
        match eventloop.poll().await {
            Ok(Event::Incoming(Packet::ConnAck(_))) => events.connected(),
            Ok(Event::Incoming(Packet::Publish(p))) => {
                events.publish(p.topic.as_bytes(), &p.payload)
            }
            Ok(Event::Incoming(Packet::SubAck(s))) => {
                let ok = s
                    .return_codes
                    .iter()
                    .all(|c| *c != SubscribeReasonCode::Failure);
                let _ = events.acks.send(Ack::Sub(ok));
            }
            Ok(_) => {}
            Err(ConnectionError::ConnectionRefused(code)) => {
                return events.ended(Failure::Refused(format!("{code:?}")));
            }
            Err(e) => return events.ended(Failure::Other(e.to_string())),
        }
    }
}

async fn run_v5(mut eventloop: r5::EventLoop, mut events: Events) {
    use r5::mqttbytes::v5::{Packet, SubscribeReasonCode};
    use r5::{ConnectionError, Event};
    loop {
        match eventloop.poll().await {
            Ok(Event::Incoming(Packet::ConnAck(_))) => events.connected(),
            Ok(Event::Incoming(Packet::Publish(p))) => events.publish(&p.topic, &p.payload),
            Ok(Event::Incoming(Packet::SubAck(s))) => {
                let ok = s
                    .return_codes
                    .iter()
                    .all(|c| matches!(c, SubscribeReasonCode::Success(_)));
                let _ = events.acks.send(Ack::Sub(ok));
            }
            Ok(_) => {}
            Err(ConnectionError::ConnectionRefused(code)) => {
                return events.ended(Failure::Refused(format!("{code:?}")));
            }
            Err(e) => return events.ended(Failure::Other(e.to_string())),
        }
    }
}

//! A module as an unmodified 4diac FORTE device: what FORTE's `fbdk[].mqtt[]` layer does
//! on the wire (`broker/tests/python/forte_device.py` documents it from FORTE's and Paho
//! C's source). One MQTT 3.1.1 connection shared by every PUBLISH/SUBSCRIBE FB, client id
//! = the module id, clean session, keep-alive 20 s, QoS 0, no will, no declaration.
//!
//! - PUBLISH_6 on `line1/<id>/state`: the STATE event's WITH values in `fbdk`, in order;
//!   PUBLISH_1 on `line1/<id>/connect`: CONNECT. The module's profile maps both topics
//!   onto `CONV.STATE` and `CONV.CONNECT`, and holds its will (`CONV.CONNECT = FALSE`).
//! - SUBSCRIBE FBs on the peers' typed topics `fbdk/<peer>/CONV/<PORT>` (no mapping
//!   needed: the broker re-encodes every typed port into `fbdk`), one topic each, exact
//!   names (FORTE compares topics with `strcmp`: no wildcards).
//! - The line's online count: a `raw[].mqtt[]` SUBSCRIBE_1 with a STRING on
//!   `fbbus/lines/<line>/online`, which the broker publishes retained as a plain decimal
//!   number, so the retained count arrives at SUBACK and every change after it.

use std::collections::HashMap;
use std::time::Duration;

use fb_bridge::codec::fbdk::{self, TimeUnit};
use fb_bridge::types::DataType;
use fb_bridge::Value;
use rumqttc::{AsyncClient, Event, EventLoop, MqttOptions, Outgoing, Packet, QoS};
use tokio::sync::{mpsc, watch};
use tokio::task::JoinSet;

use super::{
    followed_ports, interface, own_topic_name, Heard, Outputs, PeerUpdate, Runtime, Setup,
    CLOSE_WAIT, TIMEOUT,
};
use crate::log;

/// FORTE's keep-alive (MQTTHandler / MQTTClient.h: 20 s, hard-coded).
pub const KEEP_ALIVE: Duration = Duration::from_secs(20);
/// FORTE's receive buffer per subscription (MQTTComLayer.h `mBufferSize = 255`); the
/// rest of a longer message is discarded.
const RECEIVE_BUFFER: usize = 255;
/// FORTE 3.x writes DATE, TIME_OF_DAY and DATE_AND_TIME in nanoseconds.
const TIME_UNIT: TimeUnit = TimeUnit::Nanoseconds;

/// What one SUBSCRIBE FB reads.
enum Sub {
    /// The line's online count, raw text.
    Online,
    /// A peer's typed port in `fbdk`, its RD types in order.
    Port {
        peer: String,
        port: &'static str,
        types: Vec<DataType>,
    },
}

pub struct Link {
    client: AsyncClient,
    state_topic: String,
    connect_topic: String,
    connected: watch::Receiver<bool>,
    /// A REQ while not connected fails with SEND_FAILED, after which FORTE's PUBLISH FBs
    /// stay dead until they are INITed again (`commfb.cpp`: the com stack is deleted).
    dead: bool,
    /// The connection task; dropping it (the module unplugged) closes the socket without
    /// DISCONNECT, as a FORTE process that dies.
    tasks: JoinSet<()>,
}

impl Link {
    pub async fn open(
        id: &str,
        setup: &Setup,
        peers: &[(String, Runtime)],
        heard: mpsc::Sender<Heard>,
    ) -> Result<Link, String> {
        let mut options = MqttOptions::new(id, &setup.host, setup.port);
        options.set_keep_alive(KEEP_ALIVE);
        options.set_clean_session(true);
        // FORTE sets no will and, without a -mc file, no username or password.
        let (client, mut eventloop) = AsyncClient::new(options, 256);
        // Paho C sets TCP_NODELAY on its sockets.
        eventloop.network_options.set_tcp_nodelay(true);
        eventloop
            .network_options
            .set_connection_timeout(TIMEOUT.as_secs());

        let mut subs = HashMap::new();
        subs.insert(format!("fbbus/lines/{}/online", setup.line), Sub::Online);
        for (peer, runtime) in peers {
            let shape = interface(*runtime);
            for &port in followed_ports(*runtime) {
                let Some(output) = shape.output("CONV", port) else {
                    continue;
                };
                subs.insert(
                    format!("fbdk/{peer}/CONV/{port}"),
                    Sub::Port {
                        peer: peer.clone(),
                        port,
                        types: output.value_types(),
                    },
                );
            }
        }

        let (connected_tx, mut connected) = watch::channel(false);
        let mut tasks = JoinSet::new();
        tasks.spawn(connection(
            id.to_owned(),
            eventloop,
            client.clone(),
            subs,
            heard,
            connected_tx,
        ));
        tokio::time::timeout(TIMEOUT, connected.wait_for(|up| *up))
            .await
            .map_err(|_| format!("no CONNACK within {TIMEOUT:?}"))?
            .map_err(|_| "the connection task ended".to_owned())?;
        log(format!(
            "{id}: connected (FORTE: client id {id}, keep-alive {} s, no will, no declaration)",
            KEEP_ALIVE.as_secs()
        ));
        Ok(Link {
            client,
            state_topic: own_topic_name(id, "STATE"),
            connect_topic: own_topic_name(id, "CONNECT"),
            connected,
            dead: false,
            tasks,
        })
    }

    /// REQ of the CONNECT and STATE publishers: QoS 0, `fbdk`.
    pub async fn publish(&mut self, id: &str, out: &Outputs) -> Result<(), String> {
        if self.dead {
            return Ok(());
        }
        if !*self.connected.borrow() {
            self.dead = true;
            log(format!(
                "{id}: REQ while not connected: SEND_FAILED; FORTE's PUBLISH FBs stay dead \
                 until INIT"
            ));
            return Ok(());
        }
        let connect =
            fbdk::encode_values(&[Value::Bool(true)], TIME_UNIT).map_err(|e| e.to_string())?;
        let state = fbdk::encode_values(
            &[
                Value::String(id.to_owned()),
                Value::Bool(true),
                Value::Bool(out.sensor_in),
                Value::Bool(out.sensor_out),
                Value::Int(out.position),
                Value::Bool(out.swap),
            ],
            TIME_UNIT,
        )
        .map_err(|e| e.to_string())?;
        for (topic, payload) in [(&self.connect_topic, connect), (&self.state_topic, state)] {
            tokio::time::timeout(
                TIMEOUT,
                self.client
                    .publish(topic.as_str(), QoS::AtMostOnce, false, payload),
            )
            .await
            .map_err(|_| format!("publish on {topic} not taken within {TIMEOUT:?}"))?
            .map_err(|e| e.to_string())?;
        }
        Ok(())
    }

    /// FORTE's stop (the MQTTHandler's destructor): DISCONNECT.
    pub async fn close(&mut self) {
        let sent = tokio::time::timeout(CLOSE_WAIT, self.client.disconnect()).await;
        if matches!(sent, Ok(Ok(()))) {
            let _ = tokio::time::timeout(CLOSE_WAIT, self.tasks.join_next()).await;
        }
        self.tasks.shutdown().await;
    }
}

/// The Paho client's thread: connects, subscribes every SUBSCRIBE FB after each CONNACK,
/// delivers what arrives, and reconnects at once when the connection is lost.
async fn connection(
    id: String,
    mut eventloop: EventLoop,
    client: AsyncClient,
    subs: HashMap<String, Sub>,
    heard: mpsc::Sender<Heard>,
    connected: watch::Sender<bool>,
) {
    loop {
        match eventloop.poll().await {
            Ok(Event::Incoming(Packet::ConnAck(_))) => {
                connected.send_replace(true);
                // FORTE subscribes one FB after the other (each after the previous
                // SUBACK); here they are queued at once, the broker answers in order.
                for topic in subs.keys() {
                    if let Err(e) = client.try_subscribe(topic, QoS::AtMostOnce) {
                        log(format!("{id}: cannot subscribe {topic}: {e}"));
                    }
                }
            }
            Ok(Event::Incoming(Packet::Publish(publish))) => {
                // FORTE hands a message to the FB whose topic is strcmp-equal to it.
                let Some(sub) = subs.get(&publish.topic) else {
                    continue;
                };
                let bytes = &publish.payload[..publish.payload.len().min(RECEIVE_BUFFER)];
                let message = match sub {
                    Sub::Online => match std::str::from_utf8(bytes)
                        .ok()
                        .and_then(|text| text.trim().parse::<u64>().ok())
                    {
                        Some(count) => Heard::Count(count),
                        None => {
                            log(format!("{id}: not a count on {}", publish.topic));
                            continue;
                        }
                    },
                    Sub::Port { peer, port, types } => {
                        match fbdk::decode_values(bytes, types, TIME_UNIT) {
                            Ok(values) => {
                                Heard::Peer(peer.clone(), PeerUpdate::from_values(port, &values))
                            }
                            Err(e) => {
                                // IND with QO = FALSE, STATUS DATA_TYPE_ERROR.
                                log(format!("{id}: {}: DATA_TYPE_ERROR: {e}", publish.topic));
                                continue;
                            }
                        }
                    }
                };
                if heard.send(message).await.is_err() {
                    return;
                }
            }
            Ok(Event::Outgoing(Outgoing::Disconnect)) => return,
            Ok(_) => {}
            Err(e) => {
                if connected.send_replace(false) {
                    log(format!("{id}: connection lost: {e}"));
                }
                // FORTE reconnects at once; a tenth of a second keeps a broker that is
                // down from being hammered by the example.
                tokio::time::sleep(Duration::from_millis(100)).await;
            }
        }
    }
}

//! A module as an unmodified DINASORE device: what its MQTT_PUBLISHER and MQTT_SUBSCRIBER
//! FBs do on the wire (`broker/tests/python/dinasore_device.py` documents it from
//! DINASORE's source, on paho-mqtt 1.x).
//!
//! - **One MQTT_PUBLISHER FB per output**, each with its own connection: MQTT 3.1.1, an
//!   empty client id (the broker assigns one), clean session, keep-alive 60 s, no
//!   username, no will. The FB never runs paho's network loop: after CONNECT it only
//!   writes PUBLISHes (QoS 0) and never reads its socket, so it sends no PINGREQ and
//!   never reconnects (a failed write loses the value, silently). It publishes
//!   `{"<PORT>": "<str(value)>"}` (a BOOL as `"True"`/`"False"`) on `line1/<id>/<port>`,
//!   which the module's profile maps onto the data output `CONV.<PORT>`
//!   (`topics_only`, `string_numbers`, `enforce_keep_alive = false`, and its will).
//! - **One MQTT_SUBSCRIBER FB per value read**, each with its own paho connection (empty
//!   client id, keep-alive 60 s with paho's loop, subscribed once at INIT, QoS 0) on a
//!   peer's typed topic `dinasore/<peer>/CONV/<PORT>`, reading `float(json[NAME])`; any
//!   exception stops that FB for good. (DINASORE's subscriber FBs also share one slot for
//!   the last message, so one of two messages arriving together is lost; that is not
//!   reproduced here.)
//! - It cannot read the broker's online count: `fbbus/lines/<line>/online` is a bare
//!   number, and `float(3[NAME])` raises. The module counts its peers' CONNECT instead.

use std::time::Duration;

use rumqttc::{AsyncClient, Event, MqttOptions, Outgoing, Packet, QoS};
use tokio::io::AsyncWriteExt;
use tokio::net::TcpStream;
use tokio::sync::mpsc;
use tokio::task::JoinSet;

use super::{
    own_topic_name, Heard, Outputs, PeerUpdate, Runtime, Setup, CLOSE_WAIT, DATA_PORTS, TIMEOUT,
};
use crate::log;

/// paho's `connect()` default, which the publisher FBs never honour.
pub const KEEP_ALIVE: Duration = Duration::from_secs(60);

/// paho-mqtt 1.x's CONNECT from `Client()` + `connect(host, port)`: "MQTT" level 4, clean
/// session, keep-alive 60, empty client id.
const CONNECT: [u8; 14] = [
    0x10, 0x0c, 0x00, 0x04, b'M', b'Q', b'T', b'T', 0x04, 0x02, 0x00, 0x3c, 0x00, 0x00,
];
const DISCONNECT: [u8; 2] = [0xe0, 0x00];

/// One MQTT_PUBLISHER FB.
struct Publisher {
    port: &'static str,
    topic: String,
    /// `None` once a write failed: DINASORE's publisher never reconnects.
    stream: Option<TcpStream>,
}

pub struct Link {
    id: String,
    publishers: Vec<Publisher>,
    subscribers: Vec<AsyncClient>,
    /// The subscribers' paho loops; dropping them (the module unplugged) closes their
    /// sockets without DISCONNECT, as the publishers' are when `publishers` is dropped.
    tasks: JoinSet<()>,
}

impl Link {
    pub async fn open(
        id: &str,
        setup: &Setup,
        peers: &[(String, Runtime)],
        heard: mpsc::Sender<Heard>,
    ) -> Result<Link, String> {
        let mut publishers = Vec::new();
        for port in DATA_PORTS {
            let mut stream = tokio::time::timeout(
                TIMEOUT,
                TcpStream::connect((setup.host.as_str(), setup.port)),
            )
            .await
            .map_err(|_| format!("no TCP connection within {TIMEOUT:?}"))?
            .map_err(|e| format!("cannot connect: {e}"))?;
            // paho sets TCP_NODELAY on its socket.
            let _ = stream.set_nodelay(true);
            write(&mut stream, &CONNECT).await?;
            publishers.push(Publisher {
                port,
                topic: own_topic_name(id, port),
                stream: Some(stream),
            });
        }
        let mut subscribers = Vec::new();
        let mut tasks = JoinSet::new();
        for (peer, runtime) in peers {
            for (port, name) in read_values(*runtime) {
                let topic = format!("dinasore/{peer}/CONV/{port}");
                let mut options = MqttOptions::new("", &setup.host, setup.port);
                options.set_keep_alive(KEEP_ALIVE);
                options.set_clean_session(true);
                let (client, mut eventloop) = AsyncClient::new(options, 10);
                eventloop.network_options.set_tcp_nodelay(true);
                // INIT: subscribe once; after a reconnect paho does not subscribe again.
                client
                    .try_subscribe(topic.clone(), QoS::AtMostOnce)
                    .map_err(|e| e.to_string())?;
                let (id, peer, heard) = (id.to_owned(), peer.clone(), heard.clone());
                tasks.spawn(async move {
                    let mut stopped = false;
                    loop {
                        match eventloop.poll().await {
                            Ok(Event::Incoming(Packet::Publish(p)))
                                if !stopped && p.topic == topic =>
                            {
                                match python_float(&p.payload, name) {
                                    Ok(value) => {
                                        let update = update(name, value);
                                        if heard.send(Heard::Peer(peer.clone(), update)).await.is_err() {
                                            return;
                                        }
                                    }
                                    Err(e) => {
                                        // DINASORE's FB thread: "stopping the fb work...".
                                        log(format!(
                                            "{id}: MQTT_SUBSCRIBER {topic} [{name}]: {e}: the FB stops"
                                        ));
                                        stopped = true;
                                    }
                                }
                            }
                            Ok(Event::Outgoing(Outgoing::Disconnect)) => return,
                            Ok(_) => {}
                            // paho's loop reconnects, from 1 s on.
                            Err(_) => tokio::time::sleep(Duration::from_secs(1)).await,
                        }
                    }
                });
                subscribers.push(client);
            }
        }
        log(format!(
            "{id}: connected (DINASORE: {} publisher and {} subscriber connections, empty \
             client ids, keep-alive {} s never honoured by the publishers, no will)",
            publishers.len(),
            subscribers.len(),
            KEEP_ALIVE.as_secs()
        ));
        Ok(Link {
            id: id.to_owned(),
            publishers,
            subscribers,
            tasks,
        })
    }

    /// RUN of every publisher FB: `{"<PORT>": "<str(value)>"}`, QoS 0, written straight
    /// to its socket.
    pub async fn publish(&mut self, out: &Outputs) -> Result<(), String> {
        for publisher in &mut self.publishers {
            let value = match publisher.port {
                "CONNECT" => python_bool(true),
                "SENSOR_IN" => python_bool(out.sensor_in),
                "SENSOR_OUT" => python_bool(out.sensor_out),
                "POSITION" => out.position.to_string(),
                _ => python_bool(out.swap),
            };
            // json.dumps({name: str(value)}) with its default separators.
            let payload = format!(
                "{{{}: {}}}",
                serde_json::Value::from(publisher.port),
                serde_json::Value::from(value)
            );
            let Some(stream) = publisher.stream.as_mut() else {
                continue;
            };
            if let Err(e) = write(
                stream,
                &publish_packet(&publisher.topic, payload.as_bytes()),
            )
            .await
            {
                // paho returns an error code, DINASORE ignores it: the value is gone.
                log(format!(
                    "{}: {} lost ({e}); the publisher never reconnects",
                    self.id, publisher.topic
                ));
                publisher.stream = None;
            }
        }
        Ok(())
    }

    /// DINASORE's stop: each FB's `__del__` disconnects its client.
    pub async fn close(&mut self) {
        for publisher in &mut self.publishers {
            if let Some(mut stream) = publisher.stream.take() {
                let _ = write(&mut stream, &DISCONNECT).await;
            }
        }
        for client in &self.subscribers {
            let _ = client.try_disconnect();
        }
        let _ = tokio::time::timeout(CLOSE_WAIT, async {
            while self.tasks.join_next().await.is_some() {}
        })
        .await;
        self.tasks.shutdown().await;
    }
}

/// The values a DINASORE module reads of a peer, one subscriber FB each: (port, value
/// name). A STATE is a JSON object of all its WITH values, so each FB picks its own.
/// (SWAP only makes a log line: not read.)
fn read_values(runtime: Runtime) -> [(&'static str, &'static str); 3] {
    match runtime.publishes_state() {
        true => [
            ("STATE", "POSITION"),
            ("STATE", "SENSOR_OUT"),
            ("CONNECT", "CONNECT"),
        ],
        false => [
            ("POSITION", "POSITION"),
            ("SENSOR_OUT", "SENSOR_OUT"),
            ("CONNECT", "CONNECT"),
        ],
    }
}

/// What the float read for `name` says about the peer.
fn update(name: &str, value: f64) -> PeerUpdate {
    let flag = Some(value != 0.0);
    match name {
        "POSITION" => PeerUpdate {
            position: (value.is_finite()
                && value.fract() == 0.0
                && (f64::from(i16::MIN)..=f64::from(i16::MAX)).contains(&value))
            .then_some(value as i16),
            ..PeerUpdate::default()
        },
        "SENSOR_OUT" => PeerUpdate {
            sensor_out: flag,
            ..PeerUpdate::default()
        },
        "CONNECT" => PeerUpdate {
            connect: flag,
            ..PeerUpdate::default()
        },
        _ => PeerUpdate::default(),
    }
}

/// `float(json.loads(payload.decode('utf-8'))[name])`, with Python's exception on failure.
fn python_float(payload: &[u8], name: &str) -> Result<f64, String> {
    use serde_json::Value as J;
    let text = std::str::from_utf8(payload).map_err(|e| format!("UnicodeDecodeError: {e}"))?;
    let json: J = serde_json::from_str(text).map_err(|e| format!("JSONDecodeError: {e}"))?;
    let value = match &json {
        J::Object(map) => map.get(name).ok_or_else(|| format!("KeyError: '{name}'"))?,
        _ => return Err("TypeError: object is not subscriptable".into()),
    };
    match value {
        J::Number(n) => n.as_f64().ok_or_else(|| format!("OverflowError: {n}")),
        J::Bool(b) => Ok(f64::from(u8::from(*b))),
        J::String(s) => s
            .trim()
            .parse::<f64>()
            .map_err(|_| format!("ValueError: could not convert string to float: '{s}'")),
        J::Null => Err(
            "TypeError: float() argument must be a string or a real number, not 'NoneType'".into(),
        ),
        J::Array(_) | J::Object(_) => {
            Err("TypeError: float() argument must be a string or a real number".into())
        }
    }
}

/// Python's `str()` of a bool.
fn python_bool(b: bool) -> String {
    match b {
        true => "True".into(),
        false => "False".into(),
    }
}

/// A QoS 0 PUBLISH, not retained.
fn publish_packet(topic: &str, payload: &[u8]) -> Vec<u8> {
    let mut remaining = 2 + topic.len() + payload.len();
    let mut packet = vec![0x30];
    loop {
        let mut byte = (remaining % 128) as u8;
        remaining /= 128;
        if remaining > 0 {
            byte |= 0x80;
        }
        packet.push(byte);
        if remaining == 0 {
            break;
        }
    }
    packet.extend((topic.len() as u16).to_be_bytes());
    packet.extend(topic.as_bytes());
    packet.extend(payload);
    packet
}

/// A bounded write of a whole packet.
async fn write(stream: &mut TcpStream, bytes: &[u8]) -> Result<(), String> {
    tokio::time::timeout(TIMEOUT, stream.write_all(bytes))
        .await
        .map_err(|_| format!("write not taken within {TIMEOUT:?}"))?
        .map_err(|e| e.to_string())
}

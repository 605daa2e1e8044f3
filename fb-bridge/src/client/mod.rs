//! The device client: IEC 61499 communication service-interface FBs over fbbus.
//!
//! A [`Device`] is one MQTT 3.1.1 connection speaking the device contract
//! (`docs/device-contract.md` in the repository): it declares its FB interface, publishes
//! its output ports on typed topics and subscribes to other devices' output ports with the
//! types the registry holds for them.
//! Its handles follow the PUBLISH_n / SUBSCRIBE_n service primitives:
//!
//! | IEC 61499 | here |
//! |---|---|
//! | device INIT+ / INITO | [`Device::connect`]: connect, declare, wait for the broker's answer; `Ok` is QO = TRUE. [`Device::status`] is (QO, STATUS) from then on |
//! | device INIT- | [`Device::disconnect`]: clean DISCONNECT, no will |
//! | PUBLISH INIT+ | [`Device::publisher`]: the port must be a declared output of this device |
//! | PUBLISH REQ → CNF | [`Publisher::req`]: values type-checked locally, sent QoS 1, `Ok(Cnf)` after the PUBACK (QO = TRUE); `Err` is QO = FALSE with the error as STATUS, and an ill-typed REQ sends nothing |
//! | SUBSCRIBE INIT+ | [`Device::subscriber`]: the port's types come from the remote device's registry record |
//! | SUBSCRIBE IND | [`Subscriber::ind`]: the next typed message |
//! | NUM_DEV | [`Device::online_count`]: the broker's retained count of online devices of a line |
//!
//! Every wait is bounded by [`DeviceConfig::timeout`]. A CNF is matched to its PUBACK by
//! packet id (rumqttc reports the id it gave each request), so REQs of several publishers
//! may be in flight at once and acknowledged in any order.
//!
//! **Reconnection is built in.** When the connection drops, the device reconnects every
//! 500 ms; meanwhile its status is QO = FALSE, `reconnecting: ...`. The session is clean:
//! after every connect the device subscribes to everything its subscribers and watchers
//! need and declares its interface again, and becomes QO = TRUE with the broker's answer.
//! Messages published to it while it was away are not delivered; QoS 1 publications it
//! had not seen acknowledged are resent, so a REQ may be delivered twice across a
//! reconnect (its `seq` tells them apart).
//!
//! **A slow application loses no IND; a stalled one does not stop the device.** Each
//! [`Subscriber`] has a queue of 1,024 INDs. When it is full, the connection waits for the
//! application to take one, for at most 500 ms (a quarter of the keep-alive if that is
//! shorter): meanwhile the socket is not read, TCP slows the broker down, and the broker
//! holds the publishers back. A subscriber read more slowly than a burst arrives thus
//! gets every IND. One not read at all for that long is stalled: its new INDs are
//! dropped without waiting (warned about once, with the count when it reads again), so
//! the device's other subscribers, its CNFs and its keep-alive go on.
//!
//! **Refusals show on the diag topic.** On MQTT 3.1.1 a PUBACK cannot say no: the broker
//! acknowledges a publication it refuses (another device's topic, an undeclared port, a
//! payload of the wrong type) and drops it. This client checks types before sending, so a
//! refusal means the broker disagrees with the device (for instance after a
//! re-declaration elsewhere); it is logged and delivered as a [`Diagnostic::Rejected`] to
//! [`Device::diagnostics`] receivers and kept in [`Device::recent_diagnostics`].
//!
//! **Dropping a [`Device`] without [`Device::disconnect`] is a crash**: the connection
//! is closed without DISCONNECT, so the broker publishes the device's will and the
//! registry records `connection lost`, as when a real device loses power.
//!
//! # Example
//!
//! A conveyor that publishes its `STATE` event, follows the upstream conveyor's `STATE`
//! and watches how many devices of its line are online:
//!
//! ```no_run
//! use fb_bridge::client::{Device, DeviceConfig, WillSpec};
//! use fb_bridge::{Interface, Value};
//!
//! # async fn run() -> Result<(), Box<dyn std::error::Error>> {
//! let interface: Interface = serde_json::from_str(
//!     r#"{"fbs": {"CONV": {
//!         "events_out": {"STATE": {"with": ["CONNECT", "POSITION"]}},
//!         "data_out": {"CONNECT": "BOOL", "POSITION": "INT"}}}}"#,
//! )?;
//! let mut config = DeviceConfig::new("127.0.0.1", 1883, "conveyor-b");
//! // If this device dies, the broker publishes CONV.CONNECT = FALSE for it.
//! config.will = Some(WillSpec::new("CONV", "CONNECT", Value::Bool(false)));
//!
//! let device = Device::connect(config, interface).await?; // INIT+ -> INITO, QO = TRUE
//! println!("session {} on line {}", device.session(), device.line());
//!
//! let mut state = device.publisher("CONV", "STATE")?;
//! let cnf = state.req(vec![Value::Bool(true), Value::Int(2)]).await?; // REQ -> CNF
//! println!("STATE #{:?} acknowledged", cnf.seq);
//!
//! let mut upstream = device.subscriber("conveyor-a", "CONV", "STATE").await?;
//! let mut online = device.online_count(&device.line()).await?;
//! println!("{} devices online", *online.borrow());
//! tokio::select! {
//!     Some(ind) = upstream.ind() => println!("conveyor-a STATE: {:?}", ind.data),
//!     Ok(()) = online.changed() => println!("{} devices online", *online.borrow()),
//! }
//! device.disconnect().await; // INIT-: no will
//! # Ok(())
//! # }
//! ```

mod acks;
mod connection;
mod device;
mod diag;
mod publisher;
mod subscriber;

use std::time::Duration;

use crate::interface::OutputPort;
use crate::types::DataType;
use crate::value::TypeError;

pub use device::{Device, DeviceConfig, WillSpec};
pub use diag::Diagnostic;
pub use publisher::{Cnf, Publisher};
pub use subscriber::{Ind, Subscriber};

/// Why a client call failed: the STATUS of an INITO or CNF with QO = FALSE.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum ClientError {
    /// The configuration cannot work (bad device id, keep-alive, will).
    #[error("invalid configuration: {0}")]
    InvalidConfig(String),
    /// The first connection attempt failed (refused, unreachable, bad credentials).
    #[error("cannot connect: {0}")]
    Connect(String),
    /// The broker refused the interface declaration; every mistake, `; `-separated.
    #[error("declaration refused: {0}")]
    Declaration(String),
    /// A bounded wait ran out.
    #[error("no {what} within {waited:?}")]
    Timeout {
        waited: Duration,
        what: &'static str,
    },
    /// The connection dropped before the broker answered; the device is reconnecting.
    #[error("connection lost before the broker answered (reconnecting)")]
    ConnectionLost,
    /// The device was disconnected or dropped.
    #[error("the device is disconnected")]
    Closed,
    /// rumqttc's request queue is full (the broker is unreachable or slower than the
    /// device): nothing was sent.
    #[error("too many requests waiting for the connection; nothing sent")]
    Busy,
    /// The port is not a declared output (event or data) of the device.
    #[error("{fb}.{port} is not an output of device {device}")]
    NotAnOutput {
        device: String,
        fb: String,
        port: String,
    },
    /// No registry record for the device arrived in time: it never declared.
    #[error("device {0} is not in the registry (it has never declared an interface)")]
    UnknownDevice(String),
    /// The broker refused a subscription (an ACL, usually).
    #[error("subscription to {0} refused by the broker")]
    SubscribeRefused(String),
    /// A REQ with the wrong number of values; nothing was sent.
    #[error("{port}: expected {expected} value(s), got {got}; nothing sent")]
    Arity {
        port: String,
        expected: usize,
        got: usize,
    },
    /// A REQ value that does not fit its port's type; nothing was sent.
    #[error("{port}: {error}; nothing sent")]
    Type { port: String, error: TypeError },
}

/// An output port's types, owned: publishers and subscribers outlive the interface they
/// were resolved from.
#[derive(Debug, Clone, PartialEq)]
enum PortTypes {
    /// An event output and its WITH data ports, in order.
    Event(Vec<(String, DataType)>),
    Data(DataType),
}

impl PortTypes {
    fn of(port: &OutputPort<'_>) -> PortTypes {
        match port {
            OutputPort::Event(with) => {
                PortTypes::Event(with.iter().map(|(n, t)| ((*n).to_owned(), *t)).collect())
            }
            OutputPort::Data(ty) => PortTypes::Data(*ty),
        }
    }

    fn as_output(&self) -> OutputPort<'_> {
        match self {
            PortTypes::Event(with) => {
                OutputPort::Event(with.iter().map(|(n, t)| (n.as_str(), *t)).collect())
            }
            PortTypes::Data(ty) => OutputPort::Data(*ty),
        }
    }
}

/// A device id is an MQTT client id and a topic level.
fn valid_device_id(id: &str) -> bool {
    !id.is_empty() && !id.contains(['/', '+', '#', '$'])
}

//! SUBSCRIBE: IND for another device's output port.

use rumqttc::Publish;
use tokio::sync::mpsc;

use super::connection::Route;
use super::PortTypes;
use crate::codec::{json, Message};
use crate::interface::OutputPort;
use crate::value::Value;

/// A SUBSCRIBE FB on another device's output port (`fb/<device>/<fb>/<port>`, QoS 1).
/// Made by [`super::Device::subscriber`]; dropping it unsubscribes.
pub struct Subscriber {
    topic: String,
    types: PortTypes,
    rx: mpsc::Receiver<Publish>,
    _route: Route,
}

/// IND: one message on the port.
#[derive(Debug, Clone, PartialEq)]
pub struct Ind {
    /// The event's occurrence number; `None` for a data port. The broker stamps events
    /// published without one, so every event has it.
    pub seq: Option<u64>,
    /// When the event occurred, µs since 1970-01-01 UTC; `None` for a data port.
    pub ts_us: Option<u64>,
    /// An event's WITH values in WITH order; a data port's one value.
    pub data: Vec<Value>,
}

impl Subscriber {
    pub(super) fn new(
        topic: String,
        types: PortTypes,
        route: Route,
        rx: mpsc::Receiver<Publish>,
    ) -> Subscriber {
        Subscriber {
            topic,
            types,
            rx,
            _route: route,
        }
    }

    pub fn topic(&self) -> &str {
        &self.topic
    }

    /// The port's types as the registry declared them at INIT: an event's WITH ports (in
    /// the order of [`Ind::data`]) or a data port's type.
    pub fn port(&self) -> OutputPort<'_> {
        self.types.as_output()
    }

    /// The next IND. Waits as long as it takes (across reconnects); `None` once the device
    /// is disconnected or dropped.
    ///
    /// A message that does not decode against the port's types is dropped with a warning:
    /// the broker checked it against the publisher's declaration, so this only happens if
    /// that declaration changed after this subscriber's INIT.
    pub async fn ind(&mut self) -> Option<Ind> {
        loop {
            let publish = self.rx.recv().await?;
            match decode(&publish.payload, &self.types) {
                Ok(ind) => return Some(ind),
                Err(error) => {
                    tracing::warn!(topic = self.topic, %error, "undecodable message dropped")
                }
            }
        }
    }
}

fn decode(payload: &[u8], types: &PortTypes) -> Result<Ind, crate::CodecError> {
    Ok(match json::decode(payload, &types.as_output())? {
        Message::Event(event) => Ind {
            seq: event.seq,
            ts_us: event.ts_us,
            data: event.data,
        },
        Message::Data(value) => Ind {
            seq: None,
            ts_us: None,
            data: vec![value],
        },
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::types::{DataType, ElementaryType as T};

    #[test]
    fn events_and_data_ports_decode_to_inds() {
        let state = PortTypes::Event(vec![
            ("CONNECT".into(), DataType::Elementary(T::Bool)),
            ("POSITION".into(), DataType::Elementary(T::Int)),
        ]);
        assert_eq!(
            decode(
                br#"{"seq":4,"ts":17,"data":{"POSITION":3,"CONNECT":true}}"#,
                &state
            ),
            Ok(Ind {
                seq: Some(4),
                ts_us: Some(17),
                data: vec![Value::Bool(true), Value::Int(3)]
            })
        );
        assert!(decode(br#"{"data":{"POSITION":3}}"#, &state).is_err());
        let connect = PortTypes::Data(DataType::Elementary(T::Bool));
        assert_eq!(
            decode(b"false", &connect).map(|ind| ind.data),
            Ok(vec![Value::Bool(false)])
        );
    }
}

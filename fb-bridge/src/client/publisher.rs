//! PUBLISH: REQ → CNF on one of the device's output ports.

use std::sync::Arc;
use std::time::SystemTime;

use super::connection::Shared;
use super::{ClientError, PortTypes};
use crate::codec::{json, EventMessage, Message};
use crate::value::Value;

/// A PUBLISH FB on one output port of the device: `fb/<id>/<fb>/<port>`, canonical JSON,
/// QoS 1. Made by [`super::Device::publisher`].
pub struct Publisher {
    shared: Arc<Shared>,
    fb: String,
    port: String,
    topic: String,
    types: PortTypes,
    /// The last `seq` handed to the connection (events only).
    seq: u64,
}

/// CNF: the publication was acknowledged by the broker (QO = TRUE).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Cnf {
    /// The event's occurrence number (from 1, per publisher); `None` for a data port.
    pub seq: Option<u64>,
    /// The event's timestamp, µs since 1970-01-01 UTC; `None` for a data port.
    pub ts_us: Option<u64>,
}

impl Publisher {
    pub(super) fn new(shared: Arc<Shared>, fb: &str, port: &str, types: PortTypes) -> Publisher {
        Publisher {
            topic: format!("fb/{}/{fb}/{port}", shared.id),
            shared,
            fb: fb.to_owned(),
            port: port.to_owned(),
            types,
            seq: 0,
        }
    }

    pub fn topic(&self) -> &str {
        &self.topic
    }

    /// REQ: publishes `data` and returns the CNF once the broker has acknowledged it.
    ///
    /// For an event output `data` holds the WITH values in WITH order; for a data output,
    /// exactly one value. Values are checked against the declared types first: a REQ
    /// that does not fit ([`ClientError::Arity`], [`ClientError::Type`], naming the port)
    /// sends nothing and does not use up a `seq`.
    ///
    /// MQTT 3.1.1 acknowledges even a publication the broker refuses; refusals arrive on
    /// [`super::Device::diagnostics`] (they should not happen for a checked REQ).
    ///
    /// A [`ClientError::Timeout`] (no PUBACK in time, e.g. while the device reconnects)
    /// means "not confirmed", not "not delivered": the publication stays queued and is
    /// resent once the connection is back, so it may still arrive (subscribers tell
    /// repeats apart by `seq`).
    pub async fn req(&mut self, data: Vec<Value>) -> Result<Cnf, ClientError> {
        let (cnf, payload) = self.payload(data, now_us())?;
        let ack = self.shared.publish(&self.topic, payload)?;
        if let Some(seq) = cnf.seq {
            self.seq = seq;
        }
        self.shared.wait(ack, "PUBACK").await?;
        Ok(cnf)
    }

    /// Checks `data` and writes the canonical JSON payload.
    fn payload(&self, data: Vec<Value>, ts_us: u64) -> Result<(Cnf, Vec<u8>), ClientError> {
        let name = format!("{}.{}", self.fb, self.port);
        let arity = |expected: usize| ClientError::Arity {
            port: name.clone(),
            expected,
            got: data.len(),
        };
        match &self.types {
            PortTypes::Data(ty) => {
                let [value] = <[Value; 1]>::try_from(data.clone()).map_err(|_| arity(1))?;
                value
                    .check(*ty)
                    .map_err(|error| ClientError::Type { port: name, error })?;
                let payload = json::encode(&Message::Data(value), &self.types.as_output());
                Ok((
                    Cnf {
                        seq: None,
                        ts_us: None,
                    },
                    payload,
                ))
            }
            PortTypes::Event(with) => {
                if data.len() != with.len() {
                    return Err(arity(with.len()));
                }
                for ((port, ty), value) in with.iter().zip(&data) {
                    value.check(*ty).map_err(|error| ClientError::Type {
                        port: format!("{name} WITH {port}"),
                        error,
                    })?;
                }
                let seq = self.seq + 1;
                let event = EventMessage {
                    seq: Some(seq),
                    ts_us: Some(ts_us),
                    data,
                };
                let payload = json::encode(&Message::Event(event), &self.types.as_output());
                let cnf = Cnf {
                    seq: Some(seq),
                    ts_us: Some(ts_us),
                };
                Ok((cnf, payload))
            }
        }
    }
}

fn now_us() -> u64 {
    SystemTime::now()
        .duration_since(SystemTime::UNIX_EPOCH)
        .map_or(0, |d| d.as_micros() as u64)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::types::{DataType, ElementaryType as T};
    use crate::value::TypeError;
    use rumqttc::{AsyncClient, EventLoop, MqttOptions};
    use std::time::Duration;

    /// A publisher whose connection never runs, and the event loop holding what it sent.
    fn publisher_and_queue(port: &str, types: PortTypes) -> (Publisher, EventLoop) {
        let options = MqttOptions::new("conveyor-a", "localhost", 1883);
        let (client, eventloop) = AsyncClient::new(options, 8);
        let shared = Shared::new(
            "conveyor-a".into(),
            client,
            Duration::from_millis(100),
            Duration::from_millis(100),
            Vec::new(),
        );
        (
            Publisher::new(Arc::new(shared), "CONV", port, types),
            eventloop,
        )
    }

    fn publisher(port: &str, types: PortTypes) -> Publisher {
        publisher_and_queue(port, types).0
    }

    fn state() -> PortTypes {
        PortTypes::Event(vec![
            ("ID".into(), DataType::Elementary(T::String)),
            ("POSITION".into(), DataType::Elementary(T::Int)),
        ])
    }

    #[test]
    fn an_event_is_canonical_json_with_seq_ts_and_its_with_data_in_order() {
        let mut p = publisher("STATE", state());
        assert_eq!(p.topic(), "fb/conveyor-a/CONV/STATE");
        let (cnf, payload) = p
            .payload(
                vec![Value::String("a".into()), Value::Int(2)],
                1_700_000_000_000_000,
            )
            .unwrap();
        assert_eq!(
            String::from_utf8(payload).unwrap(),
            r#"{"seq":1,"ts":1700000000000000,"data":{"ID":"a","POSITION":2}}"#
        );
        assert_eq!(
            cnf,
            Cnf {
                seq: Some(1),
                ts_us: Some(1_700_000_000_000_000)
            }
        );
        p.seq = 1;
        let (cnf, _) = p
            .payload(vec![Value::String("a".into()), Value::Int(3)], 5)
            .unwrap();
        assert_eq!(cnf.seq, Some(2));
    }

    #[test]
    fn a_data_port_carries_its_bare_value() {
        let p = publisher("POSITION", PortTypes::Data(DataType::Elementary(T::Int)));
        let (cnf, payload) = p.payload(vec![Value::Int(-7)], 5).unwrap();
        assert_eq!(payload, b"-7");
        assert_eq!(
            cnf,
            Cnf {
                seq: None,
                ts_us: None
            }
        );
    }

    #[test]
    fn ill_typed_reqs_are_refused_before_sending_naming_the_port() {
        let p = publisher("STATE", state());
        assert_eq!(
            p.payload(vec![Value::String("a".into()), Value::Dint(2)], 5)
                .unwrap_err(),
            ClientError::Type {
                port: "CONV.STATE WITH POSITION".into(),
                error: TypeError::Mismatch {
                    expected: DataType::Elementary(T::Int),
                    got: "DINT".into()
                }
            }
        );
        let error = p.payload(vec![Value::Int(2)], 5).unwrap_err();
        assert_eq!(
            error.to_string(),
            "CONV.STATE: expected 2 value(s), got 1; nothing sent"
        );

        let p = publisher("POSITION", PortTypes::Data(DataType::Elementary(T::Int)));
        assert!(matches!(
            p.payload(vec![Value::Int(1), Value::Int(2)], 5),
            Err(ClientError::Arity {
                expected: 1,
                got: 2,
                ..
            })
        ));
        let error = p.payload(vec![Value::Bool(true)], 5).unwrap_err();
        assert_eq!(
            error.to_string(),
            "CONV.POSITION: expected INT, got BOOL; nothing sent"
        );
    }

    #[tokio::test]
    async fn an_ill_typed_req_sends_nothing_and_keeps_seq() {
        let (mut p, mut eventloop) = publisher_and_queue("STATE", state());
        let cnf = p.req(vec![Value::Bool(true), Value::Int(1)]).await;
        assert!(matches!(cnf, Err(ClientError::Type { .. })));
        assert_eq!(p.seq, 0);
        eventloop.clean(); // moves every request handed to rumqttc into `pending`
        assert!(eventloop.pending.is_empty());

        // A good REQ is handed over (and waits for a PUBACK that never comes).
        let cnf = p.req(vec![Value::String("a".into()), Value::Int(1)]).await;
        assert!(
            matches!(cnf, Err(ClientError::Timeout { what: "PUBACK", .. })),
            "{cnf:?}"
        );
        assert_eq!(p.seq, 1);
        eventloop.clean();
        assert_eq!(eventloop.pending.len(), 1);
    }
}

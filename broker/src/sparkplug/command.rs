//! A host's commands, on the packet path: the publish policy's Sparkplug stage.
//!
//! With the view on, the Sparkplug group (`spBv1.0/<group>/`) is the broker's: clients
//! publish only commands there (`NCMD`, `DCMD`); a birth, data or death of a client is
//! refused as not authorized, so no client can speak for the line's node or devices.
//!
//! A `DCMD` writes input ports of a device of this line (`spBv1.0/<group>/DCMD/<line>/<device>`),
//! and is decided here, where its publisher's identity is known, in the order every
//! publication is decided: the host's identity must be allowed by the ACL to publish the
//! port's typed topic (`fb/<device>/<fb>/<port>`) — authorization; each metric must name
//! an input port (by name `FB/PORT`, or by the alias of the device's last DBIRTH) and carry
//! a value of its type ([`fb_bridge::sparkplug::value_of`]) — the typed check. Then the
//! command is routed as it came (other hosts see it), and each value is delivered the way
//! the device reads: for a declared device on `fb/<device>/<fb>/<port>` in canonical JSON
//! (and on `dinasore/` and `fbdk/` once someone reads those), for a profiled device on its
//! profile's input topics for that port, in their encoding. An event input port (a UInt64
//! metric) fires the event, with its WITH data taken from the same command. A command is
//! all or nothing: one refused metric refuses it, with the MQTT 5 reason code of the first
//! refusal, counted in `fbbus_sparkplug_commands_total{result}` and logged once per host
//! and reason.

use std::collections::{BTreeMap, HashSet};
use std::sync::{Arc, Mutex, PoisonError};

use bytes::Bytes;
use fb_bridge::codec::{self, Encoding, EventMessage, Message};
use fb_bridge::sparkplug::{self as sp, proto};
use fb_bridge::{OutputPort, Value};
use prost::Message as _;

use super::{Kind, Topic, View, NAMESPACE};
use crate::policy::access::Access;
use crate::policy::typed::{FbSession, FbTopics, Refusal};

/// Refusals logged at most, per (publisher, reason); beyond, they are only counted.
const LOGGED_MAX: usize = 1024;

/// The Sparkplug stage of the publish policy.
pub struct Commands {
    group_prefix: String,
    line: String,
    enabled: bool,
    view: Arc<View>,
    logged: Mutex<HashSet<(String, &'static str)>>,
}

/// Why a command was refused: its metric label, its reason code, and what to tell.
struct Refused {
    result: &'static str,
    refusal: Refusal,
    detail: String,
}

fn refused(result: &'static str, refusal: Refusal, detail: impl Into<String>) -> Refused {
    Refused {
        result,
        refusal,
        detail: detail.into(),
    }
}

impl Commands {
    pub fn new(group: &str, line: &str, enabled: bool, view: Arc<View>) -> Commands {
        Commands {
            group_prefix: format!("{NAMESPACE}/{group}/"),
            line: line.to_owned(),
            enabled,
            view,
            logged: Mutex::default(),
        }
    }

    /// None: `topic` is not in the group (the other stages decide). Some(Ok(routes)): route
    /// the publication as it came (`routes` empty) or as `routes` (the command first, then
    /// its deliveries). Some(Err): refused.
    pub fn check(
        &self,
        access: &Access,
        publisher: &FbSession,
        fb: &FbTopics,
        topic: &str,
        payload: &Bytes,
    ) -> Option<Result<Vec<(String, Bytes)>, Refusal>> {
        if !topic.starts_with(&self.group_prefix) {
            return None;
        }
        let decided = match Topic::parse(topic) {
            Some(t) if t.kind == Kind::NCmd => Ok(Vec::new()),
            Some(t) if t.kind == Kind::DCmd => self.command(access, publisher, fb, &t, payload),
            Some(_) => Err(refused(
                "not_authorized",
                Refusal::NotAuthorized,
                "the Sparkplug group is the broker's: clients publish only NCMD and DCMD there",
            )),
            None => Err(refused(
                "malformed",
                Refusal::TopicNameInvalid,
                "not a Sparkplug topic: spBv1.0/<group>/<NCMD|DCMD>/<node>[/<device>]",
            )),
        };
        Some(match decided {
            Ok(routes) => Ok(routes),
            Err(r) => {
                self.view.commands.with_label_values(&[r.result]).inc();
                self.log(publisher, topic, &r);
                Err(r.refusal)
            }
        })
    }

    fn command(
        &self,
        access: &Access,
        publisher: &FbSession,
        fb: &FbTopics,
        topic: &Topic<'_>,
        payload: &Bytes,
    ) -> Result<Vec<(String, Bytes)>, Refused> {
        if !self.enabled {
            return Err(refused(
                "off",
                Refusal::NotAuthorized,
                "commands are off on this line ([sparkplug] commands = false)",
            ));
        }
        let device = topic.device.unwrap_or_default();
        let record = fb
            .registry
            .get(device)
            .filter(|r| topic.node == self.line && r.line == self.line)
            .ok_or_else(|| {
                refused(
                    "device",
                    Refusal::TopicNameInvalid,
                    format!(
                        "no device {device} on line {}: commands reach this line's own devices",
                        self.line
                    ),
                )
            })?;
        let decoded = proto::Payload::decode(payload.as_ref()).map_err(|e| {
            refused(
                "malformed",
                Refusal::PayloadFormatInvalid,
                format!("not a Sparkplug B payload: {e}"),
            )
        })?;
        let interface = &record.interface;
        let identity = publisher.identity();
        // Authorize every metric's port, then check every value: nothing is delivered
        // unless all of it may be.
        let mut ports = Vec::with_capacity(decoded.metrics.len());
        for metric in &decoded.metrics {
            let name = match (&metric.name, metric.alias) {
                (Some(name), _) => name.clone(),
                (None, Some(alias)) => match self.view.aliases().resolve(alias) {
                    Some((d, name)) if d == device => name,
                    _ => {
                        return Err(refused(
                            "port",
                            Refusal::TopicNameInvalid,
                            format!("alias {alias} is no metric of {device}"),
                        ))
                    }
                },
                (None, None) => {
                    return Err(refused(
                        "malformed",
                        Refusal::PayloadFormatInvalid,
                        "a metric without name or alias",
                    ))
                }
            };
            let Some((fb_name, port)) = name.split_once('/') else {
                return Err(refused(
                    "port",
                    Refusal::TopicNameInvalid,
                    format!("{name}: not an FB/PORT metric"),
                ));
            };
            let Some(shape) = interface.input(fb_name, port) else {
                let why = match interface.output(fb_name, port) {
                    Some(_) => (
                        Refusal::NotAuthorized,
                        format!("{name} is an output: only the device itself sets it"),
                    ),
                    None => (
                        Refusal::TopicNameInvalid,
                        format!("{name}: no such input port of {device}"),
                    ),
                };
                return Err(refused("port", why.0, why.1));
            };
            let typed_topic = format!("fb/{device}/{fb_name}/{port}");
            if !access.can_publish(identity, &typed_topic) {
                return Err(refused(
                    "not_authorized",
                    Refusal::NotAuthorized,
                    format!("the ACL does not let this host write {typed_topic}"),
                ));
            }
            ports.push((
                fb_name.to_owned(),
                port.to_owned(),
                shape_is_event(&shape),
                metric,
            ));
        }
        // The typed check.
        let mut values: BTreeMap<(String, String), Value> = BTreeMap::new();
        for (fb_name, port, is_event, metric) in &ports {
            let ty = if *is_event {
                fb_bridge::DataType::Elementary(fb_bridge::types::ElementaryType::Ulint)
            } else {
                match interface.fbs.get(fb_name).and_then(|f| f.data_in.get(port)) {
                    Some(ty) => *ty,
                    None => continue,
                }
            };
            let value = sp::value_of_metric(ty, metric).map_err(|e| {
                refused(
                    "type",
                    Refusal::PayloadFormatInvalid,
                    format!("{fb_name}/{port}: {e}"),
                )
            })?;
            values.insert((fb_name.clone(), port.clone()), value);
        }
        // Events take their WITH data from the command; the other values are data.
        let mut messages: Vec<(String, String, Message)> = Vec::new();
        let mut carried = HashSet::new();
        for (fb_name, port, is_event, _) in &ports {
            if !is_event {
                continue;
            }
            let Some(OutputPort::Event(with)) = interface.input(fb_name, port) else {
                continue;
            };
            let mut data = Vec::with_capacity(with.len());
            for (w, _) in &with {
                let key = (fb_name.clone(), (*w).to_owned());
                let Some(value) = values.get(&key) else {
                    return Err(refused(
                        "type",
                        Refusal::PayloadFormatInvalid,
                        format!("{fb_name}/{port}: the event carries {fb_name}/{w}, missing from the command"),
                    ));
                };
                data.push(value.clone());
                carried.insert(key);
            }
            let seq = match values.get(&(fb_name.clone(), port.clone())) {
                Some(Value::Ulint(seq)) => Some(*seq),
                _ => None,
            };
            messages.push((
                fb_name.clone(),
                port.clone(),
                Message::Event(EventMessage {
                    seq,
                    ts_us: Some(now_us()),
                    data,
                }),
            ));
        }
        for (fb_name, port, is_event, _) in &ports {
            let key = (fb_name.clone(), port.clone());
            if *is_event || carried.contains(&key) {
                continue;
            }
            if let Some(value) = values.get(&key) {
                messages.push((fb_name.clone(), port.clone(), Message::Data(value.clone())));
            }
        }
        let mut routes = vec![(topic.to_topic(), payload.clone())];
        for (fb_name, port, message) in &messages {
            routes.extend(deliveries(fb, device, fb_name, port, message, interface)?);
        }
        self.view.commands.with_label_values(&["delivered"]).inc();
        Ok(routes)
    }

    fn log(&self, publisher: &FbSession, topic: &str, r: &Refused) {
        let who = publisher.identity();
        let key = (who.username.unwrap_or(who.client_id).to_owned(), r.result);
        let mut logged = self.logged.lock().unwrap_or_else(PoisonError::into_inner);
        if logged.len() < LOGGED_MAX && logged.insert(key) {
            tracing::warn!(
                client_id = who.client_id,
                username = who.username,
                topic,
                reason = r.result,
                detail = r.detail,
                "Sparkplug command refused (logged once per host and reason)"
            );
        }
    }
}

fn shape_is_event(shape: &OutputPort<'_>) -> bool {
    matches!(shape, OutputPort::Event(_))
}

/// Where and how `device` reads its input `fb_name.port`.
fn deliveries(
    fb: &FbTopics,
    device: &str,
    fb_name: &str,
    port: &str,
    message: &Message,
    interface: &fb_bridge::Interface,
) -> Result<Vec<(String, Bytes)>, Refused> {
    let Some(shape) = interface.input(fb_name, port) else {
        return Ok(Vec::new());
    };
    let encode = |e: Encoding, unit| {
        codec::encode(e, message, port, &shape, unit).map_err(|error| {
            refused(
                "type",
                Refusal::PayloadFormatInvalid,
                format!("{fb_name}/{port}: {error}"),
            )
        })
    };
    let profiles = fb.profiles.get();
    if let Some(profile) = profiles.get(device) {
        let mut routes = Vec::new();
        for input in profile
            .inputs
            .iter()
            .filter(|i| i.own.fb == fb_name && i.own.port == port)
        {
            let bytes = encode(input.own.encoding, profile.fbdk_time_unit)?;
            routes.push((input.own.topic.clone(), Bytes::from(bytes)));
        }
        // A runtime reads a data input as the one WITH value of an event input (4diac's
        // SUBSCRIBE_1: IND with RD_1), as the profile's feeds deliver it.
        if let (true, Message::Data(value)) = (routes.is_empty(), message) {
            for input in profile.inputs.iter().filter(|i| i.own.fb == fb_name) {
                let Some(shape) = interface.input(fb_name, &input.own.port) else {
                    continue;
                };
                let OutputPort::Event(with) = &shape else {
                    continue;
                };
                if with.len() != 1 || with[0].0 != port {
                    continue;
                }
                let event = Message::Event(EventMessage {
                    seq: None,
                    ts_us: Some(now_us()),
                    data: vec![value.clone()],
                });
                let bytes = codec::encode(
                    input.own.encoding,
                    &event,
                    &input.own.port,
                    &shape,
                    profile.fbdk_time_unit,
                )
                .map_err(|error| {
                    refused(
                        "type",
                        Refusal::PayloadFormatInvalid,
                        format!("{fb_name}/{port}: {error}"),
                    )
                })?;
                routes.push((input.own.topic.clone(), Bytes::from(bytes)));
            }
        }
        if routes.is_empty() {
            return Err(refused(
                "port",
                Refusal::TopicNameInvalid,
                format!("{fb_name}/{port}: the profile of {device} maps no input topic to it"),
            ));
        }
        return Ok(routes);
    }
    let mut routes = Vec::new();
    for e in Encoding::ALL.into_iter().filter(|e| fb.mirrored(*e)) {
        let bytes = encode(e, fb.fbdk_unit)?;
        routes.push((
            format!("{}/{device}/{fb_name}/{port}", e.namespace()),
            Bytes::from(bytes),
        ));
    }
    Ok(routes)
}

fn now_us() -> u64 {
    std::time::SystemTime::now()
        .duration_since(std::time::UNIX_EPOCH)
        .map(|d| d.as_micros() as u64)
        .unwrap_or(0)
}

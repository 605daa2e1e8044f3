//! The edge nodes the view speaks for and their devices, as Sparkplug states: what is
//! born, the sequence numbers, the aliases, the last values. No I/O: each event in
//! (a registry record, an accepted value, a host's request) gives the messages out.
//!
//! The rules kept here (Sparkplug B 3.0):
//! - NBIRTH carries `seq` 0, `bdSeq` and `Node Control/Rebirth`; every later message of
//!   the node but NDEATH carries the next `seq`, 0-255 wrapping; NDEATH carries `bdSeq`
//!   and no `seq`.
//! - A device is born (DBIRTH) only while its node is born and it is online; DDATA is sent
//!   only for a born device; DDEATH ends it. A node's NDEATH ends its devices with it.
//! - Births declare every metric with its name, alias and datatype, and its last value
//!   (or null); DDATA names metrics by alias only.
//! - Metrics are `FB/PORT` for every port of the interface, inputs included (a host
//!   writes those with DCMD); an event port is a UInt64 metric, the event's `seq`, and
//!   its WITH data are the data ports' metrics in the same DDATA, at the event's `ts`.
//!   `fbbus/silent` (Boolean) says the device is online but its periodic outputs stopped.

use std::collections::{BTreeMap, HashMap};
use std::sync::{Arc, Mutex, PoisonError};

use bytes::Bytes;
use fb_bridge::codec::{self, Encoding, Message};
use fb_bridge::sparkplug::{self as sp, proto};
use fb_bridge::topic::TypedTopic;
use fb_bridge::{Interface, Value};
use prost::Message as _;

use super::bdseq::BdSeqs;
use super::{now_ms, Kind, Topic};
use crate::registry::{Record, Status};

/// The metric that says a device is online but silent.
pub const SILENT_METRIC: &str = "fbbus/silent";
/// The node metric a host sets to ask for births again.
pub const REBIRTH_METRIC: &str = "Node Control/Rebirth";
/// The node metric pairing a birth with its death.
pub const BDSEQ_METRIC: &str = "bdSeq";

/// One message to publish: (topic, payload).
pub type Out = Vec<(String, Bytes)>;

/// Which metric of which device of the line an alias names, for the commands of hosts
/// that write by alias. Written at each DBIRTH of the line's own devices, read by
/// [`super::command`] for a DCMD; never touched by routing.
#[derive(Debug, Default)]
pub struct AliasBook(Mutex<HashMap<u64, (String, String)>>);

impl AliasBook {
    /// The (device, metric name) of `alias`.
    pub fn resolve(&self, alias: u64) -> Option<(String, String)> {
        self.0
            .lock()
            .unwrap_or_else(PoisonError::into_inner)
            .get(&alias)
            .cloned()
    }

    fn set(&self, device: &str, aliases: &HashMap<String, u64>) {
        let mut book = self.0.lock().unwrap_or_else(PoisonError::into_inner);
        book.retain(|_, (d, _)| d != device);
        for (name, alias) in aliases {
            book.insert(*alias, (device.to_owned(), name.clone()));
        }
    }

    fn clear(&self, device: &str) {
        let mut book = self.0.lock().unwrap_or_else(PoisonError::into_inner);
        book.retain(|_, (d, _)| d != device);
    }
}

struct Node {
    bd_seq: u8,
    /// The next message's `seq`.
    seq: u8,
    born: bool,
    next_alias: u64,
}

struct Device {
    line: String,
    interface: Arc<Interface>,
    online: bool,
    silent: bool,
    /// By metric name (`FB/PORT`): the last value and when (ms). Bounded by the
    /// declaration's ports.
    values: HashMap<String, (Value, u64)>,
    /// While born: the alias of each metric.
    aliases: Option<HashMap<String, u64>>,
}

/// The nodes and devices the view speaks for.
pub struct Nodes {
    group: String,
    line: String,
    remote_lines: bool,
    nodes: BTreeMap<String, Node>,
    devices: HashMap<String, Device>,
    bdseqs: BdSeqs,
    aliases: Arc<AliasBook>,
    /// The largest birth payload: `[broker] max_packet_bytes`, as for any message a host
    /// could be sent. A birth whose last values would be larger names the rest null.
    max_payload: usize,
}

impl Nodes {
    pub fn new(
        group: &str,
        line: &str,
        remote_lines: bool,
        bdseqs: BdSeqs,
        aliases: Arc<AliasBook>,
    ) -> Nodes {
        Nodes {
            group: group.to_owned(),
            line: line.to_owned(),
            remote_lines,
            nodes: BTreeMap::new(),
            devices: HashMap::new(),
            bdseqs,
            aliases,
            max_payload: 65536,
        }
    }

    /// Births larger than `bytes` carry null in place of the values that do not fit.
    pub fn with_max_payload(mut self, bytes: usize) -> Nodes {
        self.max_payload = bytes;
        self
    }

    /// At start: the line's previous session's death, if one was kept, then the births of
    /// every node and online device in `records`.
    pub fn start(&mut self, records: Vec<Record>) -> Out {
        let mut out = Out::new();
        if let Some(previous) = self.bdseqs.previous(&self.line) {
            out.push(self.death(&self.line.clone(), previous));
        }
        for record in records {
            self.remember(&record);
        }
        let line = self.line.clone();
        self.node_birth(&line, true, &mut out);
        out
    }

    /// Every node born again (a host asked, or the primary host came online); `only`:
    /// that node alone. The `bdSeq`s stay: the nodes' sessions did not end.
    pub fn rebirth(&mut self, only: Option<&str>) -> Out {
        let mut out = Out::new();
        let names: Vec<String> = self
            .nodes
            .iter()
            .filter(|(name, node)| node.born && only.is_none_or(|o| o == name.as_str()))
            .map(|(name, _)| name.clone())
            .collect();
        for name in names {
            self.node_birth(&name, false, &mut out);
        }
        out
    }

    /// The line shuts down: its node's death.
    pub fn shutdown(&mut self) -> Out {
        let line = self.line.clone();
        match self.nodes.get_mut(&line) {
            Some(node) if node.born => {
                node.born = false;
                let bd = node.bd_seq;
                vec![self.death(&line, bd)]
            }
            _ => Vec::new(),
        }
    }

    /// A device's record changed.
    pub fn record(&mut self, record: &Record) -> Out {
        let mut out = Out::new();
        let line = record.line.clone();
        if line != self.line && !self.remote_lines {
            return out;
        }
        let known_interface = self
            .devices
            .get(&record.id)
            .map(|d| Arc::clone(&d.interface));
        self.remember(record);
        if line != self.line {
            let born = self.nodes.get(&line).is_some_and(|n| n.born);
            match (record.status, born) {
                // The bus lost the line: its node dies, and its devices with it.
                (Status::Unreachable, true) => {
                    self.node_died(&line, &mut out);
                    return out;
                }
                (Status::Unreachable, false) => return out,
                (_, false) => {
                    self.node_birth(&line, true, &mut out);
                    return out;
                }
                (_, true) => {}
            }
        }
        let Some(device) = self.devices.get(&record.id) else {
            return out;
        };
        let born = device.aliases.is_some();
        let retyped = known_interface.is_some_and(|i| i != device.interface);
        match (device.online, born) {
            (true, false) => self.device_birth(&record.id, &mut out),
            (true, true) if retyped => self.device_birth(&record.id, &mut out),
            (true, true) => self.silent_changed(&record.id, &mut out),
            (false, true) => self.device_death(&record.id, &mut out),
            (false, false) => {}
        }
        out
    }

    /// A device was forgotten.
    pub fn removed(&mut self, id: &str) -> Out {
        let mut out = Out::new();
        if self.devices.get(id).is_some_and(|d| d.aliases.is_some()) {
            self.device_death(id, &mut out);
        }
        self.devices.remove(id);
        out
    }

    /// An accepted typed publication, in canonical JSON on `fb/...` (the tests' one at a time).
    #[cfg(test)]
    pub fn value(&mut self, topic: &str, payload: &[u8]) -> Out {
        self.values([(topic, payload)])
    }

    /// Accepted typed publications (what the router delivered at once): each value is
    /// kept, and each born device that had some gets one DDATA with all of them, in
    /// order (split where a packet would be full). A burst of a device's messages costs
    /// the router one DDATA per batch, not one per message.
    pub fn values<'a>(&mut self, batch: impl IntoIterator<Item = (&'a str, &'a [u8])>) -> Out {
        let mut out = Out::new();
        let mut order: Vec<(String, Vec<proto::payload::Metric>)> = Vec::new();
        let mut index: HashMap<String, usize> = HashMap::new();
        for (topic, payload) in batch {
            let Some((device, metrics)) = self.metrics_of(topic, payload) else {
                continue;
            };
            match index.get(&device) {
                Some(&i) => order[i].1.extend(metrics),
                None => {
                    index.insert(device.clone(), order.len());
                    order.push((device, metrics));
                }
            }
        }
        for (device, metrics) in order {
            let Some(line) = self.devices.get(&device).map(|d| d.line.clone()) else {
                continue;
            };
            let room = self.max_payload.saturating_sub(1024).max(1);
            let mut chunk = Vec::new();
            let mut size = 0;
            for metric in metrics {
                let len = metric.encoded_len() + 4;
                if size + len > room && !chunk.is_empty() {
                    self.publish(
                        &line,
                        Kind::DData,
                        Some(&device),
                        std::mem::take(&mut chunk),
                        &mut out,
                    );
                    size = 0;
                }
                size += len;
                chunk.push(metric);
            }
            if !chunk.is_empty() {
                self.publish(&line, Kind::DData, Some(&device), chunk, &mut out);
            }
        }
        out
    }

    /// Keeps the values of one accepted publication; the DDATA metrics for them when its
    /// device is born.
    fn metrics_of(
        &mut self,
        topic: &str,
        payload: &[u8],
    ) -> Option<(String, Vec<proto::payload::Metric>)> {
        let typed = TypedTopic::parse(topic)?;
        if typed.encoding != Encoding::Json {
            return None;
        }
        let device = self.devices.get_mut(typed.device)?;
        let port = device.interface.output(typed.fb, typed.port)?;
        let message = codec::decode(
            Encoding::Json,
            payload,
            typed.port,
            &port,
            codec::fbdk::TimeUnit::default(),
        )
        .ok()?;
        let now = now_ms();
        let mut changed: Vec<(&str, Value, u64)> = Vec::new();
        match message {
            Message::Data(value) => changed.push((typed.port, value, now)),
            Message::Event(event) => {
                let at = event.ts_us.map_or(now, |us| us / 1000);
                changed.push((typed.port, Value::Ulint(event.seq.unwrap_or(0)), at));
                if let fb_bridge::OutputPort::Event(with) = &port {
                    for ((name, _), value) in with.iter().zip(event.data) {
                        changed.push((name, value, at));
                    }
                }
            }
        }
        // One name buffer for every metric of the message: `FB/PORT` is looked up, and
        // allocated only for a port's first value.
        let mut name = String::with_capacity(typed.fb.len() + 1 + 64);
        let mut metrics = Vec::with_capacity(changed.len());
        for (port, value, at) in changed {
            name.clear();
            name.push_str(typed.fb);
            name.push('/');
            name.push_str(port);
            if let Some(alias) = device.aliases.as_ref().and_then(|a| a.get(name.as_str())) {
                metrics.push(sp::metric(None, Some(*alias), Some(at), &value));
            }
            match device.values.get_mut(name.as_str()) {
                Some(kept) => *kept = (value, at),
                None => {
                    device.values.insert(name.clone(), (value, at));
                }
            }
        }
        (!metrics.is_empty()).then(|| (typed.device.to_owned(), metrics))
    }

    fn remember(&mut self, record: &Record) {
        let device = self
            .devices
            .entry(record.id.clone())
            .or_insert_with(|| Device {
                line: record.line.clone(),
                interface: Arc::clone(&record.interface),
                online: false,
                silent: false,
                values: HashMap::new(),
                aliases: None,
            });
        if device.interface != record.interface {
            // Values of ports the new declaration dropped or retyped go.
            let interface = &record.interface;
            device.values.retain(|name, (value, _)| {
                port_type(interface, name).is_some_and(|ty| value.check(ty).is_ok())
            });
            device.interface = Arc::clone(&record.interface);
        }
        device.line = record.line.clone();
        device.online = record.status == Status::Online;
        device.silent = record.silent;
    }

    /// NBIRTH of `line`'s node, then DBIRTH of each of its online devices. `new_session`:
    /// a new `bdSeq` (a start, or the line came back on the bus), else a rebirth.
    fn node_birth(&mut self, line: &str, new_session: bool, out: &mut Out) {
        if !self.nodes.contains_key(line) && self.nodes.len() >= super::bdseq::MAX_NODES {
            return;
        }
        let bd_seq = match (new_session, self.nodes.get(line)) {
            (false, Some(node)) => node.bd_seq,
            _ => self.bdseqs.next(line),
        };
        let node = self.nodes.entry(line.to_owned()).or_insert(Node {
            bd_seq,
            seq: 0,
            born: false,
            next_alias: 0,
        });
        node.bd_seq = bd_seq;
        node.seq = 0;
        node.born = true;
        node.next_alias = 2;
        let now = now_ms();
        let metrics = vec![
            sp::metric(
                Some(BDSEQ_METRIC.to_owned()),
                None,
                Some(now),
                &Value::Lint(bd_seq.into()),
            ),
            sp::metric(
                Some(REBIRTH_METRIC.to_owned()),
                Some(1),
                Some(now),
                &Value::Bool(false),
            ),
        ];
        self.publish(line, Kind::NBirth, None, metrics, out);
        let mut ids: Vec<String> = self
            .devices
            .iter()
            .filter(|(_, d)| d.line == line)
            .map(|(id, _)| id.clone())
            .collect();
        ids.sort();
        for id in ids {
            if let Some(device) = self.devices.get_mut(&id) {
                device.aliases = None;
                if device.online {
                    self.device_birth(&id, out);
                }
            }
        }
    }

    /// The node of `line` died (the bus lost it): NDEATH, and its devices are unborn.
    fn node_died(&mut self, line: &str, out: &mut Out) {
        let Some(node) = self.nodes.get_mut(line) else {
            return;
        };
        node.born = false;
        let bd = node.bd_seq;
        out.push(self.death(line, bd));
        for device in self.devices.values_mut().filter(|d| d.line == line) {
            device.aliases = None;
        }
    }

    fn death(&self, line: &str, bd_seq: u8) -> (String, Bytes) {
        let payload = proto::Payload {
            timestamp: Some(now_ms()),
            metrics: vec![sp::metric(
                Some(BDSEQ_METRIC.to_owned()),
                None,
                Some(now_ms()),
                &Value::Lint(bd_seq.into()),
            )],
            seq: None,
            uuid: None,
            body: None,
        };
        let topic = Topic {
            group: &self.group,
            kind: Kind::NDeath,
            node: line,
            device: None,
        };
        (topic.to_topic(), Bytes::from(payload.encode_to_vec()))
    }

    fn device_birth(&mut self, id: &str, out: &mut Out) {
        let Some(device) = self.devices.get(id) else {
            return;
        };
        let line = device.line.clone();
        let Some(node) = self.nodes.get_mut(&line).filter(|n| n.born) else {
            return;
        };
        let now = now_ms();
        let mut aliases = HashMap::new();
        let mut metrics = Vec::new();
        // Names, aliases and types always fit (a declaration is bounded); values only
        // while the birth stays within a packet (STRINGs of 64 KiB on 512 ports do not).
        let mut room = self.max_payload.saturating_sub(1024);
        for (name, ty) in metric_types(&device.interface) {
            let alias = node.next_alias;
            node.next_alias += 1;
            let null = proto::payload::Metric {
                name: Some(name.clone()),
                alias: Some(alias),
                timestamp: Some(now),
                datatype: Some(sp::datatype(ty) as u32),
                is_null: Some(true),
                ..Default::default()
            };
            room = room.saturating_sub(null.encoded_len());
            let metric = match device.values.get(&name) {
                Some((value, at)) => {
                    let metric = sp::metric(Some(name.clone()), Some(alias), Some(*at), value);
                    match metric.encoded_len() <= room {
                        true => {
                            room -= metric.encoded_len();
                            metric
                        }
                        false => null,
                    }
                }
                None => null,
            };
            metrics.push(metric);
            aliases.insert(name, alias);
        }
        let alias = node.next_alias;
        node.next_alias += 1;
        metrics.push(sp::metric(
            Some(SILENT_METRIC.to_owned()),
            Some(alias),
            Some(now),
            &Value::Bool(device.silent),
        ));
        aliases.insert(SILENT_METRIC.to_owned(), alias);
        if line == self.line {
            self.aliases.set(id, &aliases);
        }
        if let Some(device) = self.devices.get_mut(id) {
            device.aliases = Some(aliases);
        }
        self.publish(&line, Kind::DBirth, Some(id), metrics, out);
    }

    fn device_death(&mut self, id: &str, out: &mut Out) {
        let Some(device) = self.devices.get_mut(id) else {
            return;
        };
        if device.aliases.take().is_none() {
            return;
        }
        let line = device.line.clone();
        if line == self.line {
            self.aliases.clear(id);
        }
        self.publish(&line, Kind::DDeath, Some(id), Vec::new(), out);
    }

    fn silent_changed(&mut self, id: &str, out: &mut Out) {
        let Some(device) = self.devices.get(id) else {
            return;
        };
        let Some(alias) = device
            .aliases
            .as_ref()
            .and_then(|a| a.get(SILENT_METRIC))
            .copied()
        else {
            return;
        };
        let metric = sp::metric(
            None,
            Some(alias),
            Some(now_ms()),
            &Value::Bool(device.silent),
        );
        let line = device.line.clone();
        // Only a change is data: a record changes for many reasons.
        let previous = device
            .values
            .get(SILENT_METRIC)
            .map(|(v, _)| v == &Value::Bool(device.silent));
        if previous == Some(true) {
            return;
        }
        let silent = device.silent;
        if let Some(device) = self.devices.get_mut(id) {
            device
                .values
                .insert(SILENT_METRIC.to_owned(), (Value::Bool(silent), now_ms()));
        }
        if previous.is_none() && !silent {
            // Born not silent, and still not: nothing changed.
            return;
        }
        self.publish(&line, Kind::DData, Some(id), vec![metric], out);
    }

    /// A message of `line`'s node with the node's next `seq` (NBIRTH: 0).
    fn publish(
        &mut self,
        line: &str,
        kind: Kind,
        device: Option<&str>,
        metrics: Vec<proto::payload::Metric>,
        out: &mut Out,
    ) {
        let Some(node) = self.nodes.get_mut(line).filter(|n| n.born) else {
            return;
        };
        let seq = node.seq;
        node.seq = node.seq.wrapping_add(1);
        let payload = proto::Payload {
            timestamp: Some(now_ms()),
            metrics,
            seq: Some(seq.into()),
            uuid: None,
            body: None,
        };
        let topic = Topic {
            group: &self.group,
            kind,
            node: line,
            device,
        };
        out.push((topic.to_topic(), Bytes::from(payload.encode_to_vec())));
    }
}

/// `FB/PORT`.
pub fn metric_name(fb: &str, port: &str) -> String {
    format!("{fb}/{port}")
}

/// Every port's metric and its datatype: data ports their type, event ports UInt64
/// (the occurrence's `seq`), in FB then port order, outputs then inputs.
fn metric_types(interface: &Interface) -> Vec<(String, fb_bridge::DataType)> {
    let seq = fb_bridge::DataType::Elementary(fb_bridge::types::ElementaryType::Ulint);
    let mut metrics = Vec::new();
    for (fb, i) in &interface.fbs {
        for (port, ty) in i.data_out.iter().chain(&i.data_in) {
            metrics.push((metric_name(fb, port), *ty));
        }
        for port in i.events_out.keys().chain(i.events_in.keys()) {
            metrics.push((metric_name(fb, port), seq));
        }
    }
    metrics
}

/// The datatype of the metric `name` in `interface`, if it has one.
fn port_type(interface: &Interface, name: &str) -> Option<fb_bridge::DataType> {
    if name == SILENT_METRIC {
        return Some(fb_bridge::DataType::Elementary(
            fb_bridge::types::ElementaryType::Bool,
        ));
    }
    metric_types(interface)
        .into_iter()
        .find(|(n, _)| n == name)
        .map(|(_, ty)| ty)
}

#[cfg(test)]
mod tests;

//! What the console shows of a device beyond its record: the last value and time of each
//! declared output port, its recent refusals (`fbbus/diag/<device>`), and when it last
//! went offline and why.
//!
//! **Off the packet path.** The admin plane never holds what routing needs. The values
//! come from the broker's own router link `fbbus:console` ([`CLIENT_ID`]), subscribed at
//! QoS 0 to `fb/#` (every accepted typed publication, canonical JSON whatever the
//! device's encoding) and `fbbus/diag/#` (the broker's own diagnostics), and read by one
//! task ([`run`]) on a thread of its own (`fbbus-console`): since it decodes values for
//! the trends ([`super::history`]), it does not take turns with the sessions. Tapping the typed stage instead would have cost a lock or a queue per
//! accepted publication on the sessions' threads; the link costs the router one more
//! subscriber, and when this task falls behind the router pauses the link (it is woken
//! again, the way the health probe's link is) — the devices never wait for the console.
//! The declared interfaces are followed from the registry's change channel, so no
//! message takes the registry's lock here either.
//!
//! **Bounded; hostile input.** Topics and payloads are whatever a device sent: values
//! are kept only for declared output ports of registered devices, as lossy UTF-8 cut to
//! [`VALUE_MAX_CHARS`] characters (at a character boundary), at most
//! `[console] max_port_values` in all; refusals at most [`REFUSALS_PER_DEVICE`] per
//! device and `[console] max_refusals` in all, each cut to [`REFUSAL_MAX_CHARS`]; offline
//! times at most [`OFFLINE_PER_DEVICE`] per device. What is not kept is counted
//! (`fbbus_console_dropped_total`). A forgotten device's entries are freed with it, and
//! a port a new declaration removes loses its value.
//!
//! **One value per port and read.** Of the messages one read of the link takes, only the
//! newest of each typed topic is decoded and kept (`Newest`): a burst costs the console
//! one decode per port, not one per message. Refusals are each kept.
//!
//! **Live.** A page viewing a device asks for its port changes ([`Activity::watch`]);
//! changes of watched devices are coalesced and sent every [`FLUSH`] (a 10 ms port
//! makes 4 events a second, not 100); refusals are sent as they come.

use std::collections::{BTreeMap, HashMap, VecDeque};
use std::sync::{Arc, Mutex, PoisonError};
use std::time::{Duration, SystemTime};

use bytes::Bytes;
use fb_bridge::codec::json;
use fb_bridge::topic::{self, TypedTopic};
use fb_bridge::{DataType, Interface, Message, OutputPort};
use prometheus::{IntCounterVec, IntGauge, IntGaugeVec, Opts};
use rumqttd::local::{LinkRx, LinkTx};
use rumqttd::protocol::{Filter, Packet, QoS, RetainForwardRule, Subscribe};
use serde::Serialize;
use tokio::sync::broadcast;

use super::history::{self, History, Kind, Point, Pushed};
use crate::link;
use crate::metrics::Metrics;
use crate::registry::{Change, Registry, Status};

/// The console's router link; clients may not take it (`fbbus:` prefix).
pub const CLIENT_ID: &str = "fbbus:console";
/// The longest value text kept per port, in characters.
pub const VALUE_MAX_CHARS: usize = 200;
/// Refusals kept per device, the newest.
pub const REFUSALS_PER_DEVICE: usize = 20;
/// The longest refusal text (reason and detail) kept, in characters.
pub const REFUSAL_MAX_CHARS: usize = 512;
/// Offline times kept per device, the newest.
pub const OFFLINE_PER_DEVICE: usize = 10;
/// How often the changed ports of watched devices are sent.
pub const FLUSH: Duration = Duration::from_millis(250);
/// Port and refusal events the feeds' channel holds; a feed further behind resyncs.
pub const EVENTS_CAPACITY: usize = 1024;

/// `[console]` limits.
#[derive(Debug, Clone, Copy)]
pub struct Limits {
    pub max_port_values: usize,
    pub max_refusals: usize,
    pub history: history::Limits,
}

/// Points of one port a live feed event carries at most, and of all its ports: a device
/// of 512 ports each publishing fast would otherwise make every 250 ms event megabytes,
/// and the feeds' channel holds up to [`EVENTS_CAPACITY`] of them for a lagging page.
/// Beyond, the event says `points_cut` and the page reads the history again.
pub const FEED_POINTS: usize = 256;
pub const FEED_POINTS_PER_EVENT: usize = 2048;
/// How often points older than the history's window are dropped from every series.
pub const EXPIRE_EVERY: Duration = Duration::from_secs(10);

/// The `what` of `fbbus_console_entries`.
const ENTRIES: [&str; 4] = [
    "port_values",
    "refusals",
    "history_points",
    "history_series",
];

/// One output port's last value.
#[derive(Debug, Clone, Serialize)]
pub struct PortValue {
    /// The canonical JSON payload as text, cut to [`VALUE_MAX_CHARS`].
    pub value: String,
    pub truncated: bool,
    /// When the console received it.
    #[serde(serialize_with = "rfc3339")]
    pub at: SystemTime,
    /// A retained value delivered when the console subscribed: `at` is then the
    /// console's start, not the publication's time.
    pub retained: bool,
}

/// One diagnostic of `fbbus/diag/<device>` other than an accepted declaration.
#[derive(Debug, Clone, Serialize)]
pub struct Refusal {
    #[serde(serialize_with = "rfc3339")]
    pub at: SystemTime,
    /// `rejected`, `declaration`, `diag_dropped`, `not_reencoded`, ...
    pub kind: String,
    pub topic: Option<String>,
    pub reason: Option<String>,
    pub code: Option<u64>,
    /// What was wrong, cut to [`REFUSAL_MAX_CHARS`].
    pub detail: String,
}

/// A time the device went offline (or unreachable), and why.
#[derive(Debug, Clone, Serialize)]
pub struct Offline {
    pub since: String,
    pub status: Status,
    pub reason: Option<String>,
}

/// An event for the feeds: one device's changed ports, or a refusal.
#[derive(Debug, Clone)]
pub enum Event {
    Ports { device: Arc<str>, json: Bytes },
    Refusal { json: Bytes },
}

/// What `/api/v1/devices/{id}/activity` answers.
#[derive(Debug, Serialize)]
pub struct DeviceActivity {
    /// By `FB.PORT`.
    pub ports: BTreeMap<String, PortValue>,
    pub refusals: Vec<Refusal>,
    pub offline: Vec<Offline>,
}

#[derive(Default)]
struct Device {
    /// By FB, then port: looked up without allocating.
    ports: HashMap<String, HashMap<String, PortValue>>,
    /// Newest last.
    refusals: VecDeque<Refusal>,
    offline: VecDeque<Offline>,
    /// The last status seen, to note the changes to offline.
    status: Option<Status>,
}

struct State {
    /// Every registered device's declared interface, from the registry's changes.
    interfaces: HashMap<String, Arc<Interface>>,
    devices: HashMap<String, Device>,
    port_values: usize,
    refusals: usize,
    /// Devices some page views, with how many pages.
    watched: HashMap<String, usize>,
    /// Changed ports of watched devices since the last flush: device -> (FB, PORT) ->
    /// the points its series had been given before the first change.
    pending: HashMap<String, BTreeMap<(String, String), u64>>,
    history: History,
}

/// The console's view of device activity, shared by its task and the admin routes.
pub struct Activity {
    state: Mutex<State>,
    events: broadcast::Sender<Event>,
    limits: Limits,
    /// `fbbus_console_entries` by [`ENTRIES`], looked up once: set after every read.
    counts: [IntGauge; 4],
    dropped: IntCounterVec,
    history_bytes: IntGauge,
}

impl Activity {
    pub fn new(limits: Limits, metrics: &Metrics) -> Arc<Activity> {
        let entries = IntGaugeVec::new(
            Opts::new(
                "fbbus_console_entries",
                "What the line console keeps: port_values, refusals, history_points, history_series",
            ),
            &["what"],
        )
        .expect("valid metric");
        let dropped = IntCounterVec::new(
            Opts::new(
                "fbbus_console_dropped_total",
                "Port values, refusals and port histories the line console did not keep ([console] limits)",
            ),
            &["what"],
        )
        .expect("valid metric");
        let counts = ENTRIES.map(|what| entries.with_label_values(&[what]));
        for what in ["port_values", "refusals", "history_ports"] {
            dropped.with_label_values(&[what]);
        }
        let history_bytes = IntGauge::new(
            "fbbus_console_history_bytes",
            "Memory of the line console's port history: its points' buffers ([console] history_max_points)",
        )
        .expect("valid metric");
        metrics.register(Box::new(history_bytes.clone()));
        metrics.register(Box::new(entries.clone()));
        metrics.register(Box::new(dropped.clone()));
        Arc::new(Activity {
            state: Mutex::new(State {
                interfaces: HashMap::new(),
                devices: HashMap::new(),
                port_values: 0,
                refusals: 0,
                watched: HashMap::new(),
                pending: HashMap::new(),
                history: History::new(limits.history),
            }),
            events: broadcast::channel(EVENTS_CAPACITY).0,
            limits,
            counts,
            dropped,
            history_bytes,
        })
    }

    fn lock(&self) -> std::sync::MutexGuard<'_, State> {
        self.state.lock().unwrap_or_else(PoisonError::into_inner)
    }

    /// Port and refusal events from now on.
    pub fn events(&self) -> broadcast::Receiver<Event> {
        self.events.subscribe()
    }

    /// A page views `device`: its port changes are sent until the returned guard drops.
    pub fn watch(self: &Arc<Self>, device: &str) -> Watch {
        *self.lock().watched.entry(device.to_owned()).or_default() += 1;
        Watch {
            activity: Arc::clone(self),
            device: device.to_owned(),
        }
    }

    /// The device's last port values, refusals and offline times; None if the console
    /// knows nothing of it.
    pub fn device(&self, id: &str) -> Option<DeviceActivity> {
        let state = self.lock();
        let device = state.devices.get(id)?;
        let ports = device
            .ports
            .iter()
            .flat_map(|(fb, ports)| {
                ports
                    .iter()
                    .map(move |(port, value)| (format!("{fb}.{port}"), value.clone()))
            })
            .collect();
        Some(DeviceActivity {
            ports,
            refusals: device.refusals.iter().cloned().collect(),
            offline: device.offline.iter().cloned().collect(),
        })
    }

    /// A registry change: the device's interface (a removed port loses its value), its
    /// offline times; a forgotten device's entries are freed.
    fn changed(&self, change: &Change) {
        let mut state = self.lock();
        match change {
            Change::Removed(id) => {
                state.interfaces.remove(&**id);
                state.pending.remove(&**id);
                state.history.remove(id, |_, _, _| true);
                if let Some(device) = state.devices.remove(&**id) {
                    state.port_values -= device.ports.values().map(HashMap::len).sum::<usize>();
                    state.refusals -= device.refusals.len();
                }
            }
            Change::Record(record, _) => {
                let state = &mut *state;
                let new_interface = state
                    .interfaces
                    .get(&record.id)
                    .is_none_or(|i| !Arc::ptr_eq(i, &record.interface));
                if new_interface {
                    state
                        .interfaces
                        .insert(record.id.clone(), Arc::clone(&record.interface));
                }
                let device = state.devices.entry(record.id.clone()).or_default();
                if new_interface {
                    let interface = &record.interface;
                    let mut removed = 0;
                    device.ports.retain(|fb, ports| {
                        let before = ports.len();
                        ports.retain(|port, _| interface.output(fb, port).is_some());
                        removed += before - ports.len();
                        !ports.is_empty()
                    });
                    state.port_values -= removed;
                    // A series whose port is gone or has another kind or type now.
                    state.history.remove(&record.id, |fb, port, series| {
                        !series.fits(interface.output(fb, port))
                    });
                }
                let offline = matches!(record.status, Status::Offline | Status::Unreachable);
                if offline && device.status != Some(record.status) {
                    if device.offline.len() == OFFLINE_PER_DEVICE {
                        device.offline.pop_front();
                    }
                    device.offline.push_back(Offline {
                        since: record.since.clone(),
                        status: record.status,
                        reason: record.last_will_reason.clone(),
                    });
                }
                device.status = Some(record.status);
            }
        }
        self.count(&state);
    }

    /// Reads every record again (the change channel lagged): devices no longer in the
    /// registry are freed, the others' interfaces are taken.
    fn resync(&self, registry: &Registry) {
        let records = registry.list();
        let ids: std::collections::HashSet<&str> = records.iter().map(|r| r.id.as_str()).collect();
        let gone: Vec<String> = self
            .lock()
            .interfaces
            .keys()
            .filter(|id| !ids.contains(id.as_str()))
            .cloned()
            .collect();
        for id in gone {
            self.changed(&Change::Removed(id.into()));
        }
        for record in records {
            self.changed(&Change::Record(Arc::new(record), Bytes::new()));
        }
    }

    fn count(&self, state: &State) {
        let [values, refusals, points, series] = &self.counts;
        values.set(state.port_values as i64);
        refusals.set(state.refusals as i64);
        points.set(state.history.points() as i64);
        series.set(state.history.series_count() as i64);
        self.history_bytes.set(state.history.bytes() as i64);
    }

    /// One publication the console link received.
    fn received(&self, state: &mut State, topic: &[u8], payload: &[u8], retained: bool) {
        let Ok(topic) = std::str::from_utf8(topic) else {
            return;
        };
        if let Some(device) = topic.strip_prefix(topic::DIAG) {
            self.refused(state, device, payload);
        } else if let Some(t) = TypedTopic::parse(topic) {
            self.port(state, t, payload, retained);
        }
    }

    /// A value on a typed topic: the port's last value and, for a plottable port, a
    /// point of its history; an event's WITH data are the last values (and points) of
    /// their data ports.
    fn port(&self, state: &mut State, t: TypedTopic<'_>, payload: &[u8], retained: bool) {
        let Some(interface) = state.interfaces.get(t.device).map(Arc::clone) else {
            return;
        };
        let Some(output) = interface.output(t.fb, t.port) else {
            return;
        };
        let at = SystemTime::now();
        self.set_value(state, t.device, t.fb, t.port, payload, at, retained);
        let ms = now_ms();
        match &output {
            OutputPort::Data(ty) if !retained && history::plottable(*ty) => {
                if let Ok(Message::Data(value)) = json::decode(payload, &output) {
                    if let Some(x) = history::number(&value) {
                        let point = Point(ms, x);
                        let kind = history::data_kind(&interface, t.fb, t.port);
                        self.point(state, &t, t.port, kind, Some(*ty), point);
                    }
                }
            }
            OutputPort::Event(with) => {
                let Ok(Message::Event(event)) = json::decode(payload, &output) else {
                    return;
                };
                if !retained {
                    let seq = Point(ms, event.seq.unwrap_or(0) as f64);
                    self.point(state, &t, t.port, Kind::Event, None, seq);
                }
                for ((name, ty), value) in with.iter().zip(&event.data) {
                    let text = json::value_to_json(value).to_string();
                    self.set_value(state, t.device, t.fb, name, text.as_bytes(), at, retained);
                    if let Some(x) = history::number(value).filter(|_| !retained) {
                        // A WITH port is one series, whichever way its values come.
                        let kind = history::data_kind(&interface, t.fb, name);
                        self.point(state, &t, name, kind, Some(*ty), Point(ms, x));
                    }
                }
            }
            OutputPort::Data(_) => {}
        }
    }

    /// Adds a point to the port's history.
    fn point(
        &self,
        state: &mut State,
        t: &TypedTopic<'_>,
        port: &str,
        kind: Kind,
        ty: Option<DataType>,
        point: Point,
    ) {
        if state.history.push(t.device, t.fb, port, kind, ty, point) == Pushed::NoRoom {
            self.dropped.with_label_values(&["history_ports"]).inc();
        }
    }

    /// The port's last value := `payload` (text); noted for the page watching the device.
    #[allow(clippy::too_many_arguments)]
    fn set_value(
        &self,
        state: &mut State,
        device_id: &str,
        fb: &str,
        port: &str,
        payload: &[u8],
        at: SystemTime,
        retained: bool,
    ) {
        let State {
            devices,
            port_values,
            watched,
            pending,
            history,
            ..
        } = state;
        if !devices.contains_key(device_id) {
            devices.insert(device_id.to_owned(), Device::default());
        }
        let Some(device) = devices.get_mut(device_id) else {
            return;
        };
        let existing = device
            .ports
            .get_mut(fb)
            .and_then(|ports| ports.get_mut(port));
        match existing {
            Some(value) => {
                value.truncated = set_text(&mut value.value, payload, VALUE_MAX_CHARS);
                value.at = at;
                value.retained = retained;
            }
            None if *port_values >= self.limits.max_port_values => {
                self.dropped.with_label_values(&["port_values"]).inc();
                return;
            }
            None => {
                let mut value = String::new();
                let truncated = set_text(&mut value, payload, VALUE_MAX_CHARS);
                device.ports.entry(fb.to_owned()).or_default().insert(
                    port.to_owned(),
                    PortValue {
                        value,
                        truncated,
                        at,
                        retained,
                    },
                );
                *port_values += 1;
            }
        }
        if watched.contains_key(device_id) {
            let seen = history
                .get(device_id, fb, port)
                .map_or(0, history::Series::pushed);
            pending
                .entry(device_id.to_owned())
                .or_default()
                .entry((fb.to_owned(), port.to_owned()))
                .or_insert(seen);
        }
    }

    fn refused(&self, state: &mut State, device: &str, payload: &[u8]) {
        if !state.interfaces.contains_key(device) {
            // Not a registered device (a refused first declaration): nothing to show it
            // under, and nothing that bounds the ids.
            return;
        }
        let Ok(body) = serde_json::from_slice::<serde_json::Value>(payload) else {
            return;
        };
        let field = |k: &str| body.get(k).and_then(|v| v.as_str()).map(str::to_owned);
        let kind = field("kind").unwrap_or_else(|| "unknown".into());
        if kind == "declaration" && body.get("ok").and_then(|v| v.as_bool()) == Some(true) {
            return;
        }
        let detail = match body.get("detail").and_then(|v| v.as_str()) {
            Some(d) => d.to_owned(),
            // A refused declaration carries its errors, a limit.
            None => body
                .get("errors")
                .or_else(|| body.get("limit"))
                .map(|v| v.to_string())
                .unwrap_or_default(),
        };
        let mut cut = String::new();
        set_text(&mut cut, detail.as_bytes(), REFUSAL_MAX_CHARS);
        let short = |s: Option<String>| {
            s.map(|s| {
                let mut out = String::new();
                set_text(&mut out, s.as_bytes(), REFUSAL_MAX_CHARS);
                out
            })
        };
        let refusal = Refusal {
            at: SystemTime::now(),
            kind: short(Some(kind)).unwrap_or_default(),
            topic: short(field("topic")),
            reason: short(field("reason").or_else(|| field("limit"))),
            code: body.get("code").and_then(|v| v.as_u64()),
            detail: cut,
        };
        let entry = state.devices.entry(device.to_owned()).or_default();
        if entry.refusals.len() == REFUSALS_PER_DEVICE {
            entry.refusals.pop_front();
            state.refusals -= 1;
        } else if state.refusals >= self.limits.max_refusals {
            self.dropped.with_label_values(&["refusals"]).inc();
            return;
        }
        let json = serde_json::to_vec(&serde_json::json!({"device": device, "refusal": &refusal}))
            .map(Bytes::from)
            .unwrap_or_default();
        entry.refusals.push_back(refusal);
        state.refusals += 1;
        let _ = self.events.send(Event::Refusal { json });
    }

    /// Sends the changed ports of the watched devices, with the points their series
    /// were given since the last flush.
    fn flush(&self) {
        let mut state = self.lock();
        if state.pending.is_empty() {
            return;
        }
        let pending = std::mem::take(&mut state.pending);
        for (id, ports) in pending {
            let Some(device) = state.devices.get(&id) else {
                continue;
            };
            let mut values = BTreeMap::new();
            let mut points = BTreeMap::new();
            let (mut left, mut cut) = (FEED_POINTS_PER_EVENT, false);
            for ((fb, port), seen) in &ports {
                let name = format!("{fb}.{port}");
                if let Some(series) = state.history.get(&id, fb, port) {
                    let new: Vec<&Point> = series.after(*seen, FEED_POINTS.min(left)).collect();
                    cut |= series.pushed().saturating_sub(*seen) > new.len() as u64;
                    left -= new.len();
                    if !new.is_empty() {
                        points.insert(name.clone(), new);
                    }
                }
                if let Some(value) = device.ports.get(fb).and_then(|p| p.get(port)) {
                    values.insert(name, value);
                }
            }
            let body = serde_json::json!({
                "device": id,
                "ports": values,
                "points": points,
                "points_cut": cut,
            });
            let Ok(json) = serde_json::to_vec(&body) else {
                continue;
            };
            let _ = self.events.send(Event::Ports {
                device: id.as_str().into(),
                json: json.into(),
            });
        }
        self.count(&state);
    }

    /// Drops the history's points older than its window.
    fn expire(&self) {
        let mut state = self.lock();
        state.history.expire(now_ms());
        self.count(&state);
    }

    /// The history's window, in seconds.
    pub fn history_window_s(&self) -> u64 {
        self.limits.history.window_ms / 1000
    }

    /// The port's history within `[from, to]` (ms since 1970), the newest `limit` points;
    /// None when the port has no series (not declared, not plottable, or no value yet).
    pub fn history(
        &self,
        device: &str,
        fb: &str,
        port: &str,
        from: u64,
        to: u64,
        limit: usize,
    ) -> Option<HistoryAnswer> {
        let state = self.lock();
        let series = state.history.get(device, fb, port)?;
        Some(HistoryAnswer {
            kind: series.kind,
            capacity: state.history.capacity(),
            points: series.range(from, to, limit),
        })
    }
}

/// A port's history, as `/api/v1/devices/{id}/ports/{FB.PORT}/history` answers it.
#[derive(Debug, Serialize)]
pub struct HistoryAnswer {
    pub kind: Kind,
    /// Points the series may hold now (its share of `history_max_points`).
    pub capacity: usize,
    pub points: Vec<Point>,
}

/// Now, in ms since 1970 UTC.
pub fn now_ms() -> u64 {
    SystemTime::now()
        .duration_since(SystemTime::UNIX_EPOCH)
        .map_or(0, |d| u64::try_from(d.as_millis()).unwrap_or(u64::MAX))
}

/// A page's interest in one device's ports; dropping it ends the interest.
pub struct Watch {
    activity: Arc<Activity>,
    device: String,
}

impl Watch {
    pub fn device(&self) -> &str {
        &self.device
    }
}

impl Drop for Watch {
    fn drop(&mut self) {
        let mut state = self.activity.lock();
        if let Some(n) = state.watched.get_mut(&self.device) {
            *n -= 1;
            if *n == 0 {
                state.watched.remove(&self.device);
                state.pending.remove(&self.device);
            }
        }
    }
}

/// `text` := `bytes` as lossy UTF-8, at most `max` characters (cut at a character
/// boundary); returns whether it was cut. Reuses `text`'s allocation.
pub fn set_text(text: &mut String, bytes: &[u8], max: usize) -> bool {
    // No character is longer than 4 bytes: what lies beyond cannot be shown.
    let limit = bytes.len().min(max.saturating_mul(4));
    let lossy = String::from_utf8_lossy(&bytes[..limit]);
    text.clear();
    let cut = match lossy.char_indices().nth(max) {
        Some((at, _)) => {
            text.push_str(&lossy[..at]);
            true
        }
        None => {
            text.push_str(&lossy);
            false
        }
    };
    cut || limit < bytes.len()
}

fn rfc3339<S: serde::Serializer>(at: &SystemTime, s: S) -> Result<S::Ok, S::Error> {
    s.collect_str(&humantime::format_rfc3339_millis(*at))
}

/// The console's task: follows the registry's interfaces, reads the console link, sends
/// the watched devices' port changes every [`FLUSH`]. Ends when the router is gone.
/// The newest publication of each typed topic in one read of the console's link.
///
/// Why: under a burst the router hands the console hundreds of messages at once, mostly
/// on a few topics, all received within the same millisecond. Each would have been
/// decoded, looked up and added to its port's series at the same time as its neighbours:
/// in a profile of a 40,000-message typed burst across the bus the console's thread took
/// a fifth of the machine's samples. A port's value, and its history point, are now those
/// of the newest message of each read; at a line's usual rates a read holds one message
/// per port, and every value is a point as before. A port faster than the console reads
/// (several values within a millisecond or two of each other) keeps one point per read.
#[derive(Default)]
struct Newest {
    /// Topic -> index in `order`.
    at: HashMap<Bytes, usize, foldhash::fast::RandomState>,
    order: Vec<(Bytes, Bytes, bool)>,
}

impl Newest {
    fn note(&mut self, topic: Bytes, payload: Bytes, retained: bool) {
        match self.at.get(&topic) {
            Some(&i) => self.order[i] = (topic, payload, retained),
            None => {
                self.at.insert(topic.clone(), self.order.len());
                self.order.push((topic, payload, retained));
            }
        }
    }

    /// The newest of each topic, in the order the topics first came.
    fn drain(&mut self) -> std::vec::Drain<'_, (Bytes, Bytes, bool)> {
        self.at.clear();
        self.order.drain(..)
    }
}

pub async fn run(activity: Arc<Activity>, registry: Arc<Registry>, link: (LinkTx, LinkRx)) {
    let (mut tx, mut rx) = link;
    let mut changes = registry.changes();
    activity.resync(&registry);
    let filter = |path: &str| Filter {
        path: path.to_owned(),
        qos: QoS::AtMostOnce,
        nolocal: false,
        // Retain flag set only on what the subscription itself delivers.
        preserve_retain: false,
        // The retained values are the last values known before the console started.
        retain_forward_rule: RetainForwardRule::OnEverySubscribe,
    };
    let subscribe = Packet::Subscribe(
        Subscribe {
            pkid: 0,
            filters: vec![filter("fb/#"), filter("fbbus/diag/#")],
        },
        None,
    );
    if tx.send(subscribe).await.is_err() {
        return;
    }
    let mut tick = tokio::time::interval(FLUSH);
    tick.set_missed_tick_behavior(tokio::time::MissedTickBehavior::Delay);
    let mut expire = tokio::time::interval(EXPIRE_EVERY);
    expire.set_missed_tick_behavior(tokio::time::MissedTickBehavior::Delay);
    let mut newest = Newest::default();
    loop {
        tokio::select! {
            change = changes.recv() => match change {
                Ok(change) => activity.changed(&change),
                Err(broadcast::error::RecvError::Lagged(_)) => activity.resync(&registry),
                Err(broadcast::error::RecvError::Closed) => return,
            },
            notification = rx.next() => {
                let Ok(first) = notification else { return };
                // Everything the router delivered at once, under one lock; of a topic,
                // only its newest value (`Newest`).
                let taken = {
                    let mut state = activity.lock();
                    let taken = link::take_batch(&mut rx, first, |forward| {
                        let p = forward.publish;
                        if p.topic.starts_with(topic::DIAG.as_bytes()) {
                            // Every refusal is one to show.
                            activity.received(&mut state, &p.topic, &p.payload, p.retain);
                        } else {
                            newest.note(p.topic, p.payload, p.retain);
                        }
                    });
                    for (topic, payload, retain) in newest.drain() {
                        activity.received(&mut state, &topic, &payload, retain);
                    }
                    activity.count(&state);
                    taken
                };
                let Ok(paused) = taken else { return };
                // The router paused the link (its queue for it was full): wake it.
                if paused.resume(&rx).await.is_err() {
                    return;
                }
            }
            _ = tick.tick() => activity.flush(),
            _ = expire.tick() => activity.expire(),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// What the feed sends a page watching a device: every new point of a slow device, and
    /// no more than [`FEED_POINTS_PER_EVENT`] of a fast one, saying so.
    #[test]
    fn a_feed_event_carries_a_bounded_number_of_points() {
        let limits = Limits {
            max_port_values: 1000,
            max_refusals: 10,
            history: history::Limits {
                window_ms: 3_600_000,
                points_per_port: 3600,
                max_points: 1_000_000,
            },
        };
        let activity = Activity::new(limits, &Metrics::new());
        let ports: Vec<String> = (0..20).map(|p| format!("\"P{p}\":\"INT\"")).collect();
        let declaration = format!(
            "{{\"fbs\":{{\"F\":{{\"data_out\":{{{}}}}}}}}}",
            ports.join(",")
        );
        let interface = fb_bridge::Declaration::from_json(declaration.as_bytes())
            .unwrap()
            .validate()
            .unwrap();
        activity
            .lock()
            .interfaces
            .insert("d".into(), Arc::new(interface));
        let _watch = activity.watch("d");
        let mut events = activity.events();
        let mut feed = |ports: usize, values: usize| {
            {
                let mut state = activity.lock();
                for v in 0..values {
                    for p in 0..ports {
                        let topic = format!("fb/d/F/P{p}");
                        activity.received(
                            &mut state,
                            topic.as_bytes(),
                            v.to_string().as_bytes(),
                            false,
                        );
                    }
                }
            }
            activity.flush();
            let Ok(Event::Ports { json, .. }) = events.try_recv() else {
                panic!("no ports event");
            };
            let body: serde_json::Value = serde_json::from_slice(&json).unwrap();
            let n: usize = body["points"]
                .as_object()
                .unwrap()
                .values()
                .map(|p| p.as_array().unwrap().len())
                .sum();
            (n, body["points_cut"] == true)
        };
        assert_eq!(feed(2, 10), (20, false));
        let (n, cut) = feed(20, 200);
        assert_eq!((n, cut), (FEED_POINTS_PER_EVENT, true));
    }

    #[test]
    fn of_one_read_the_newest_value_of_each_topic_is_kept_in_first_come_order() {
        let mut newest = Newest::default();
        for (topic, value) in [("fb/a/F/X", "1"), ("fb/b/F/Y", "2"), ("fb/a/F/X", "3")] {
            newest.note(Bytes::from(topic), Bytes::from(value), false);
        }
        newest.note(Bytes::from("fb/b/F/Y"), Bytes::from("4"), true);
        let got: Vec<_> = newest.drain().collect();
        assert_eq!(
            got,
            [
                (Bytes::from("fb/a/F/X"), Bytes::from("3"), false),
                (Bytes::from("fb/b/F/Y"), Bytes::from("4"), true),
            ]
        );
        // Drained: the next read starts empty.
        newest.note(Bytes::from("fb/c/F/Z"), Bytes::from("5"), false);
        assert_eq!(newest.drain().count(), 1);
    }

    #[test]
    fn text_is_cut_at_a_character_boundary() {
        let mut t = String::new();
        assert!(!set_text(&mut t, b"42", 200));
        assert_eq!(t, "42");
        let long = "é".repeat(300);
        assert!(set_text(&mut t, long.as_bytes(), 200));
        assert_eq!(t.chars().count(), 200);
        // Invalid UTF-8, a multi-byte character split by the byte limit.
        let mut bytes = vec![0xff, 0xfe];
        bytes.extend("€".repeat(10).as_bytes());
        assert!(set_text(&mut t, &bytes, 3));
        assert_eq!(t.chars().count(), 3);
        assert!(set_text(&mut t, "€€€€".as_bytes(), 1));
        assert_eq!(t, "€");
        assert!(!set_text(&mut t, b"", 0));
    }
}

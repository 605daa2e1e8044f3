//! The device registry: every device of the line, its interface and whether it is online.
//!
//! A device enters the registry when it declares its FB interface (`fbbus/declare/<id>`).
//! From then on the registry follows its connections: online while a connection with its
//! client id is open, offline when that connection ends — with the reason its will fired
//! for (abrupt close, keep-alive expiry, takeover) or `clean disconnect`.
//!
//! **Session numbers decide, not arrival order.** Every connection has a session number
//! (see `session::table`), the Sparkplug `bdSeq` idea: an end is applied only if it belongs
//! to the device's current session, so the late death of an old connection — a takeover,
//! a delayed will — never marks a newer session offline. Numbers keep growing across
//! broker restarts because the table is seeded from the persisted registry.
//!
//! **Readable three ways.** Each change republishes the device's record, retained, on
//! `fbbus/devices/<id>`, and the line's online count on `fbbus/lines/<line>/online`
//! (so a device needs no NUM_DEV block: it subscribes to the count); the admin endpoint
//! serves `/api/v1/devices`; `fbbus devices` prints it.
//!
//! **Online but silent.** A local online device whose periodic outputs stopped publishing
//! is `silent` (see `silence` for the rule): its connection times each accepted
//! publication on a declared output in the device's [`Activity`], without this lock, and a
//! task judges every device each [`SILENCE_CHECK`], republishing a record only when it
//! turns silent or speaks again. Remote devices are judged by their own line.
//!
//! **Persisted incrementally, never half-written.** Every change of a local record marks
//! its id (`Devices::insert` and `update*`, the only writers). A task appends the marked
//! records, one JSON line each, to a journal beside the snapshot (`registry.json.log`)
//! at most every [`PERSIST_INTERVAL`], and syncs it: one declaration costs one line, not
//! a rewrite of every device (issue 21). When the journal outgrows the snapshot
//! ([`Journal::needs_compaction`]) the whole registry is written to a temporary file,
//! synced and renamed over the snapshot, and the journal is emptied. Loading is the
//! snapshot, then the journal's lines newer than it (each line and the snapshot carry a
//! sequence number), a torn last line cut off with a warning. After a restart every
//! device is offline (reason `broker restart`) until it reconnects.
//!
//! **Bounded.** A device of this line enters the registry in one place,
//! [`Registry::declare`] (a declaration, or a profile that recognised a connection), which
//! admits a new device only within `[fb] max_devices` devices of the line and
//! `[fb] max_devices_per_identity` devices registered by one identity (the verified
//! username where a password file exists, else the peer's address); a known device is
//! always admitted again. A refusal is counted (`fbbus_limit_refusals_total`), logged at
//! most once a minute per limit, and answered by the caller on `fbbus/diag/<id>`.
//! [`Registry::forget`] removes an offline device with its retained record and typed
//! values (the admin API, `fbbus devices forget`), and so does `[fb] forget_offline_after_s`
//! for devices offline longer than that.
//!
//! **Other lines' devices.** With a `[bridge]`, the registry also holds the devices of the
//! other lines on the bus (their `line` says where they live), learned from the bus
//! (`bridge`): online and offline as their own line says, and **unreachable** while their
//! line cannot be reached — a fact about the link, not the device, so it never overwrites
//! the device's own last will reason. Remote records are never persisted: they are
//! learned again from the bus after a restart. Local changes are handed to the bridge
//! through [`Registry::observe`].
//!
//! **Watched by the line console.** Every change of any record, local or remote, and
//! every removal is also sent on a bounded broadcast channel ([`Registry::changes`],
//! [`CHANGES_CAPACITY`] changes): the console's live feed (`console::feed`) sends each
//! to the open pages. A page that lags behind by more than the capacity is told to
//! reload the list (the channel drops the oldest changes, never blocks a writer); the
//! bridge's own observer stays the unbounded one above.
//!
//! [`SILENCE_CHECK`]: status::SILENCE_CHECK
//! [`PERSIST_INTERVAL`]: journal::PERSIST_INTERVAL
//! [`Journal::needs_compaction`]: journal::Journal::needs_compaction

mod federation;
mod feed;
mod journal;
mod limits;
mod page;
mod records;
mod status;
#[cfg(test)]
mod tests;

use std::collections::{BTreeMap, HashMap};
use std::path::{Path, PathBuf};
use std::sync::{Arc, Mutex, PoisonError};
use std::time::{Instant, SystemTime};

use fb_bridge::codec::Encoding;
use fb_bridge::Interface;
use tokio::sync::Notify;

use self::journal::{load, Journal};
use self::records::Devices;
use crate::broker_publisher::{BrokerPublisher, Message};
use crate::metrics::Metrics;
use crate::silence::{Activity, Bound};

pub use self::federation::LineState;
#[cfg(any(feature = "bridge", test))]
pub use self::federation::RecordRefused;
pub use self::feed::{Change, LocalChange, CHANGES_CAPACITY};
pub use self::journal::LoadError;
pub use self::limits::{ForgetError, ForgetReason, Full, Limits};
pub use self::records::{Record, Status};

pub struct Registry {
    line: String,
    devices: Mutex<Devices>,
    publisher: Arc<BrokerPublisher>,
    metrics: Arc<Metrics>,
    /// How long a periodic output may be quiet (`[fb] silence_*`).
    bound: Bound,
    limits: Limits,
    file: Option<PathBuf>,
    dirty: Notify,
    /// The journal, held while the files are written: the writer task's append (on a
    /// blocking thread, which aborting the task does not stop) and the last write at
    /// shutdown never overlap.
    journal: Mutex<Journal>,
    /// Receives every change of a local device's record (the bridge announces them).
    observer: std::sync::OnceLock<tokio::sync::mpsc::UnboundedSender<LocalChange>>,
    /// Every change of any record, for the console ([`Registry::changes`]).
    changes: tokio::sync::broadcast::Sender<Change>,
    /// The online count last published on `fbbus/lines/<line>/online` (-1: none yet):
    /// another line's record does not change it, and 7,000 of them arriving at once
    /// republished it 7,000 times through the router (issue 32's plant).
    announced_online: std::sync::atomic::AtomicI64,
    /// The other lines on the bus and whether they are reachable, as the bridge last
    /// saw them ([`Registry::lines`]).
    lines: Mutex<BTreeMap<String, LineState>>,
}

impl Registry {
    /// Loads the registry from `file` (if it exists) with every device offline, publishes
    /// the records, and starts persisting changes to `file`.
    pub fn open(
        line: &str,
        file: Option<&Path>,
        publisher: Arc<BrokerPublisher>,
        metrics: Arc<Metrics>,
        bound: Bound,
        limits: Limits,
        tasks: &crate::supervisor::Tasks,
    ) -> Result<Arc<Registry>, LoadError> {
        let mut devices = BTreeMap::new();
        let mut remembered = HashMap::new();
        let mut registrants = BTreeMap::new();
        let mut journal = Journal::default();
        if let Some(path) = file {
            let (records, periods, registered, opened) = load(path)?;
            journal = opened;
            remembered.extend(periods);
            registrants = registered;
            for mut record in records {
                if record.status == Status::Online {
                    record.status = Status::Offline;
                    record.last_will_reason = Some("broker restart".into());
                    record.since = now();
                }
                record.silent = false;
                record.silent_since = None;
                devices.insert(record.id.clone(), record);
            }
        }
        let mut devices = Devices {
            remembered,
            changed: file.map(|_| Default::default()),
            ..Devices::new(line, devices)
        };
        let wall = SystemTime::now();
        let ids: Vec<String> = devices.keys().cloned().collect();
        for id in ids {
            if let Some(registrant) = registrants.remove(&id) {
                devices.register(&id, &registrant);
            }
            // Offline since its record says (a restart does not make it younger).
            let since = humantime::parse_rfc3339_weak(&devices[&id].since).unwrap_or(wall);
            if devices[&id].status == Status::Offline {
                devices.offline_since.insert(id, since.min(wall));
            }
        }
        // Exported at 0 from the start: an alert on the first refusal has its series.
        for limit in ["devices", "devices_per_identity"] {
            metrics.limit_refusals.with_label_values(&[limit]);
        }
        let registry = Arc::new(Registry {
            line: line.to_owned(),
            devices: Mutex::new(devices),
            publisher,
            metrics,
            bound,
            limits,
            file: file.map(Path::to_owned),
            dirty: Notify::new(),
            journal: Mutex::new(journal),
            observer: std::sync::OnceLock::new(),
            changes: tokio::sync::broadcast::channel(CHANGES_CAPACITY).0,
            announced_online: std::sync::atomic::AtomicI64::new(-1),
            lines: Mutex::new(BTreeMap::new()),
        });
        {
            let devices = registry
                .devices
                .lock()
                .unwrap_or_else(PoisonError::into_inner);
            for record in devices.values() {
                registry.announce(record);
            }
            // A line without devices publishes nothing, so a fresh broker's topic space
            // stays empty; the count appears with the first declaration.
            if !devices.is_empty() {
                registry.announce_count(&devices);
            }
        }
        if registry.file.is_some() {
            tasks.core("registry writer", Arc::clone(&registry).persist_loop());
        }
        Ok(registry)
    }

    pub fn line(&self) -> &str {
        &self.line
    }

    /// How long a periodic output may be quiet.
    pub fn silence_bound(&self) -> &Bound {
        &self.bound
    }

    /// The output activity of the local device `id`, which its connection updates.
    pub fn activity(&self, id: &str) -> Option<Arc<Activity>> {
        let devices = self.devices.lock().unwrap_or_else(PoisonError::into_inner);
        devices.activity.get(id).cloned()
    }

    /// Each known device's latest session number, to seed the session table.
    pub fn sessions(&self) -> Vec<(String, u64)> {
        let devices = self.devices.lock().unwrap_or_else(PoisonError::into_inner);
        devices
            .values()
            .map(|r| (r.id.clone(), r.session))
            .collect()
    }

    /// A device declared its interface on its connection `session` (or a profile declared
    /// it for the connection): it is online with it. `registrant` is who declares
    /// ([`Registry::admit`]); a new device beyond the limits is refused.
    pub fn declare(
        &self,
        id: &str,
        session: u64,
        interface: Interface,
        registrant: &str,
    ) -> Result<Arc<Interface>, Full> {
        let mut devices = self.devices.lock().unwrap_or_else(PoisonError::into_inner);
        self.admit(&mut devices, id, registrant)?;
        let interface = Arc::new(interface);
        let record = Record {
            id: id.to_owned(),
            line: self.line.clone(),
            status: Status::Online,
            session,
            since: now(),
            last_will_reason: None,
            silent: false,
            silent_since: None,
            interface: Arc::clone(&interface),
        };
        // A new interface may have other ports: their timing starts afresh, with the
        // periods its ports had under the old one.
        let activity = Activity::new(&interface, Instant::now());
        activity.remember(&devices.periods(id));
        devices.activity.insert(id.to_owned(), Arc::new(activity));
        self.announce(&record);
        devices.insert(record);
        self.announce_count(&devices);
        self.dirty.notify_one();
        Ok(interface)
    }

    pub fn get(&self, id: &str) -> Option<Record> {
        self.devices
            .lock()
            .unwrap_or_else(PoisonError::into_inner)
            .get(id)
            .cloned()
    }
}

/// Empty retained messages that clear what `device` retained on its output `ports`, in
/// every typed namespace (MQTT 3.3.1.3): a port a re-declaration removes or retypes, or
/// every port of a forgotten device, must not hand a new subscriber an old value.
pub fn retained_clears<'a>(
    device: &'a str,
    ports: impl IntoIterator<Item = (&'a str, &'a str)> + 'a,
) -> impl Iterator<Item = Message> + 'a {
    ports.into_iter().flat_map(move |(fb, port)| {
        Encoding::ALL.into_iter().map(move |e| {
            let topic = format!("{}/{device}/{fb}/{port}", e.namespace());
            Message::broker(topic, Vec::new(), true)
        })
    })
}

/// The current time, RFC 3339 with milliseconds.
pub fn now() -> String {
    humantime::format_rfc3339_millis(SystemTime::now()).to_string()
}

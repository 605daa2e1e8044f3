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

use std::collections::{BTreeMap, HashMap};
use std::path::{Path, PathBuf};
use std::sync::{Arc, Mutex, PoisonError};
use std::time::{Duration, Instant, SystemTime};

use fb_bridge::codec::Encoding;
use fb_bridge::topic;
use fb_bridge::Interface;
use serde::{Deserialize, Serialize};
use tokio::sync::Notify;

use crate::broker_publisher::{BrokerPublisher, Message};
use crate::metrics::Metrics;
use crate::silence::{Activity, Bound, Periods, Verdict};

/// Record changes the console's broadcast channel holds ([`Registry::changes`]): a
/// receiver further behind than this is told it lagged and reloads. 4,096 covers a
/// line of 1,000 devices all changing at once (a broker restart) with room to spare;
/// each slot is an `Arc` and the record's JSON, shared by every receiver.
pub const CHANGES_CAPACITY: usize = 4096;

/// One change of the registry, as the console's live feed sends it.
#[derive(Debug, Clone)]
pub enum Change {
    /// A device's record as it is now, with its JSON (the one published on
    /// `fbbus/devices/<id>`, serialized once for every receiver).
    Record(Arc<Record>, bytes::Bytes),
    /// A device was forgotten.
    Removed(Arc<str>),
}

/// The longest a change waits before it is on disk.
pub const PERSIST_INTERVAL: Duration = Duration::from_millis(200);

/// How often local devices are judged for silence: a silent device is shown within its
/// bound plus this.
pub const SILENCE_CHECK: Duration = Duration::from_secs(1);

/// The longest silence between two log lines about refusals at one registry limit.
const LIMIT_LOG_INTERVAL: Duration = Duration::from_secs(60);

/// How often the observed output periods are written, when nothing else changes: a
/// crash loses at most this much of what was learned.
const PERIODS_PERSIST: u32 = 60;

/// How much the registry holds (`[fb] max_devices`, `max_devices_per_identity`,
/// `forget_offline_after_s`).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Limits {
    /// Devices of this line, at most.
    pub max_devices: usize,
    /// Devices one identity registered, at most.
    pub max_per_identity: usize,
    /// A local device offline this long is forgotten; None: never.
    pub forget_offline_after: Option<Duration>,
}

impl Default for Limits {
    /// `[fb]`'s defaults: 10,000 devices, 100 per identity, never forgotten by age.
    fn default() -> Limits {
        Limits {
            max_devices: 10_000,
            max_per_identity: 100,
            forget_offline_after: None,
        }
    }
}

impl Limits {
    /// No limit (the unit tests).
    #[cfg(test)]
    pub const NONE: Limits = Limits {
        max_devices: usize::MAX,
        max_per_identity: usize::MAX,
        forget_offline_after: None,
    };
}

/// Why a new device was not admitted into the registry.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum Full {
    #[error(
        "the registry holds [fb] max_devices = {0} devices of this line: a new device is \
         refused until one is forgotten (fbbus devices forget)"
    )]
    Devices(usize),
    #[error(
        "this client's identity (its username, or without a password file its address) \
         registered [fb] max_devices_per_identity = {0} devices: a new device is refused \
         until one of them is forgotten (fbbus devices forget)"
    )]
    PerIdentity(usize),
}

impl Full {
    /// The `limit` label of `fbbus_limit_refusals_total`.
    pub fn limit(&self) -> &'static str {
        match self {
            Full::Devices(_) => "devices",
            Full::PerIdentity(_) => "devices_per_identity",
        }
    }
}

/// Why a device was forgotten: the `reason` label of `fbbus_registry_forgotten_total`.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum ForgetReason {
    /// Offline longer than `[fb] forget_offline_after_s`.
    Expired,
    /// `DELETE /api/v1/devices/{id}` (`fbbus devices forget`).
    Admin,
}

impl ForgetReason {
    pub fn label(self) -> &'static str {
        match self {
            ForgetReason::Expired => "expired",
            ForgetReason::Admin => "admin",
        }
    }
}

/// Why a device cannot be forgotten.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum ForgetError {
    #[error("no device {0} in the registry")]
    Unknown(String),
    #[error(
        "device {0} is online: an online device is not forgotten (it would be registered \
         again at its next declaration); disconnect it first"
    )]
    Online(String),
    #[error("device {0} is a device of line {1}: it is forgotten on its own line")]
    OtherLine(String, String),
}

#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum Status {
    Online,
    Offline,
    /// The device's line cannot be reached (set by the zenoh bridge for remote devices).
    Unreachable,
}

impl Status {
    pub fn label(self) -> &'static str {
        match self {
            Status::Online => "online",
            Status::Offline => "offline",
            Status::Unreachable => "unreachable",
        }
    }
}

/// One device, as the registry publishes and persists it.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Record {
    pub id: String,
    pub line: String,
    pub status: Status,
    /// The session number of the device's latest connection.
    pub session: u64,
    /// When the status last changed (RFC 3339, UTC).
    pub since: String,
    /// Why the device went offline last; null while online.
    pub last_will_reason: Option<String>,
    /// Online, but its periodic outputs stopped publishing (`silence`); false otherwise.
    #[serde(default)]
    pub silent: bool,
    /// While silent: the last publication of its periodic outputs, or the start of its
    /// connection if later. Null otherwise.
    #[serde(default)]
    pub silent_since: Option<String>,
    pub interface: Arc<Interface>,
}

#[derive(Serialize, Deserialize)]
struct File {
    version: u32,
    /// The journal's last sequence number when this snapshot was written: the journal
    /// lines up to it are in the snapshot already (0: none).
    #[serde(default)]
    seq: u64,
    devices: Vec<Record>,
    /// The observed output periods of the local devices, by device (`silence`): a
    /// device whose publishers died at a restart is still judged.
    #[serde(default, skip_serializing_if = "BTreeMap::is_empty")]
    periods: BTreeMap<String, Periods>,
    /// Who registered each local device (`[fb] max_devices_per_identity`), by device.
    #[serde(default, skip_serializing_if = "BTreeMap::is_empty")]
    registrants: BTreeMap<String, String>,
}

/// The records, with their counts kept up to date by every change: announcing the
/// counts after a change is O(1), not a walk over every device (a walk per birth made a
/// line's births quadratic: 10,000 declarations at once took seconds).
struct Devices {
    /// In id order: a page of the admin listing is a range walk, O(page), not a scan of
    /// every device under the lock (issue 21: 50,000 devices, polled).
    records: BTreeMap<String, Record>,
    /// This line's name (`Counts::online_here`).
    line: String,
    counts: Counts,
    /// The output activity of the local devices declared or connected since start-up.
    activity: HashMap<String, Arc<Activity>>,
    /// Periods read from the registry file, for devices not connected since.
    remembered: HashMap<String, Periods>,
    /// Live records taken from other lines, counted; and for each remote device the
    /// count when its last live record came. A query's answer was made before the live
    /// records that came after it was sent, so it must not replace them
    /// (`Registry::queried_record`). One entry per remote record: the records' bound.
    live_taken: u64,
    live: HashMap<String, u64>,
    /// When each offline local device went offline (`[fb] forget_offline_after_s`): the
    /// wall clock, as the record's `since` shows it.
    offline_since: HashMap<String, SystemTime>,
    /// Who registered each local device, and how many devices each registrant holds.
    registrants: HashMap<String, Arc<str>>,
    registered: HashMap<Arc<str>, usize>,
    /// The refusals at each limit since its last log line (logged at most once a minute).
    refusals_unlogged: HashMap<&'static str, (Option<Instant>, u64)>,
    /// Local records changed since the journal's last append (`Registry::append`);
    /// None when the registry is not persisted (nothing would empty it).
    changed: Option<std::collections::HashSet<String>>,
}

/// Devices by status (every line), and this line's online devices.
#[derive(Debug, Default, Clone, Copy, PartialEq, Eq)]
struct Counts {
    by_status: [i64; 3],
    /// This line's devices (`[fb] max_devices`).
    local: i64,
    online_here: i64,
    /// Online and silent, every line.
    silent: i64,
}

impl Counts {
    /// Adds (`sign` 1) or removes (-1) one record.
    fn tally(&mut self, record: &Record, line: &str, sign: i64) {
        self.by_status[record.status as usize] += sign;
        if record.line == line {
            self.local += sign;
        }
        if record.status == Status::Online && record.line == line {
            self.online_here += sign;
        }
        if record.status == Status::Online && record.silent {
            self.silent += sign;
        }
    }
}

impl Devices {
    fn new(line: &str, records: BTreeMap<String, Record>) -> Devices {
        let mut counts = Counts::default();
        for record in records.values() {
            counts.tally(record, line, 1);
        }
        Devices {
            records,
            line: line.to_owned(),
            counts,
            activity: HashMap::new(),
            remembered: HashMap::new(),
            live_taken: 0,
            live: HashMap::new(),
            offline_since: HashMap::new(),
            registrants: HashMap::new(),
            registered: HashMap::new(),
            refusals_unlogged: HashMap::new(),
            changed: None,
        }
    }

    /// Marks `record` for the journal if it is a local device's.
    fn mark(changed: &mut Option<std::collections::HashSet<String>>, line: &str, record: &Record) {
        if let Some(changed) = changed.as_mut().filter(|_| record.line == line) {
            if !changed.contains(&record.id) {
                changed.insert(record.id.clone());
            }
        }
    }

    fn insert(&mut self, record: Record) {
        Self::mark(&mut self.changed, &self.line, &record);
        self.counts.tally(&record, &self.line, 1);
        let id = record.id.clone();
        if let Some(old) = self.records.insert(record.id.clone(), record) {
            self.counts.tally(&old, &self.line, -1);
        }
        self.note_offline(&id);
    }

    /// Removes every trace of `id`: its record, timing, registrant and offline time.
    fn remove(&mut self, id: &str) -> Option<Record> {
        let record = self.records.remove(id)?;
        // A removed local device is journaled as removed (`Registry::append`).
        Self::mark(&mut self.changed, &self.line, &record);
        self.counts.tally(&record, &self.line, -1);
        self.activity.remove(id);
        self.remembered.remove(id);
        self.live.remove(id);
        self.offline_since.remove(id);
        if let Some(registrant) = self.registrants.remove(id) {
            if let Some(n) = self.registered.get_mut(&registrant) {
                *n -= 1;
                if *n == 0 {
                    self.registered.remove(&registrant);
                }
            }
        }
        Some(record)
    }

    /// `registrant` registered the new device `id`.
    fn register(&mut self, id: &str, registrant: &str) {
        let registrant: Arc<str> = match self.registered.get_key_value(registrant) {
            Some((held, _)) => Arc::clone(held),
            None => registrant.into(),
        };
        *self.registered.entry(Arc::clone(&registrant)).or_default() += 1;
        if let Some(old) = self.registrants.insert(id.to_owned(), registrant) {
            // Not reached: a device is registered once. Kept consistent anyway.
            if let Some(n) = self.registered.get_mut(&old) {
                *n = n.saturating_sub(1);
            }
        }
    }

    /// Keeps `offline_since` in step with the record of `id`: the time it went offline,
    /// for a local offline device.
    fn note_offline(&mut self, id: &str) {
        let offline = self
            .records
            .get(id)
            .is_some_and(|r| r.line == self.line && r.status == Status::Offline);
        if !offline {
            self.offline_since.remove(id);
        } else if !self.offline_since.contains_key(id) {
            self.offline_since.insert(id.to_owned(), SystemTime::now());
        }
    }

    /// Changes the record of `id` with `change`, if there is one and `which` selects it;
    /// returns the changed record.
    fn update(
        &mut self,
        id: &str,
        which: impl FnOnce(&Record) -> bool,
        change: impl FnOnce(&mut Record),
    ) -> Option<&Record> {
        let record = self.records.get_mut(id).filter(|r| which(r))?;
        self.counts.tally(record, &self.line, -1);
        change(record);
        self.counts.tally(record, &self.line, 1);
        Self::mark(&mut self.changed, &self.line, record);
        self.note_offline(id);
        self.records.get(id)
    }

    /// The output periods of `id`, observed in this run or read from the file.
    fn periods(&self, id: &str) -> Periods {
        match self.activity.get(id) {
            Some(activity) => activity.periods(),
            None => self.remembered.get(id).cloned().unwrap_or_default(),
        }
    }

    /// Changes every record `which` selects with `change`.
    fn update_all(&mut self, which: impl Fn(&Record) -> bool, mut change: impl FnMut(&mut Record)) {
        for record in self.records.values_mut().filter(|r| which(r)) {
            self.counts.tally(record, &self.line, -1);
            change(record);
            self.counts.tally(record, &self.line, 1);
            Self::mark(&mut self.changed, &self.line, record);
        }
    }
}

impl std::ops::Deref for Devices {
    type Target = BTreeMap<String, Record>;

    /// Read access; every change goes through `insert` and `update*` (the counts).
    fn deref(&self) -> &Self::Target {
        &self.records
    }
}

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
    observer: std::sync::OnceLock<tokio::sync::mpsc::UnboundedSender<Record>>,
    /// Every change of any record, for the console ([`Registry::changes`]).
    changes: tokio::sync::broadcast::Sender<Change>,
    /// The other lines on the bus and whether they are reachable, as the bridge last
    /// saw them ([`Registry::lines`]).
    lines: Mutex<BTreeMap<String, LineState>>,
}

/// Another line of the bus as the bridge sees it.
#[derive(Debug, Clone, PartialEq, Eq, Serialize)]
pub struct LineState {
    pub reachable: bool,
    /// When it last changed (RFC 3339, UTC).
    pub since: String,
}

/// Other lines remembered in [`Registry::lines`] at most: a line's name comes from a bus
/// key, which any peer of an unauthenticated bus may write.
pub const MAX_LINES: usize = 256;

#[derive(Debug, thiserror::Error)]
#[error("registry file {path}: {message}")]
pub struct LoadError {
    pub path: String,
    pub message: String,
}

/// Why a registry record from another line was not taken.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum RecordRefused {
    /// The record names another line than the one that sent it.
    ForgedLine,
    /// It is a device of this line.
    LocalDevice,
    /// The device is online on a third line.
    HeldByAnotherLine,
}

impl RecordRefused {
    /// The metric label.
    pub fn as_str(self) -> &'static str {
        match self {
            RecordRefused::ForgedLine => "forged_record",
            RecordRefused::LocalDevice => "local_device",
            RecordRefused::HeldByAnotherLine => "claimed_device",
        }
    }
}

/// Why a device is not a device of the line a bus message claims it for.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum NotOfLine {
    /// No record of it: its line never announced it.
    Unknown,
    /// It is a device of this line: nobody else speaks for it.
    Local,
    /// Its record names a third line.
    OtherLine,
}

impl NotOfLine {
    /// The metric label and the diagnostic's word.
    pub fn as_str(self) -> &'static str {
        match self {
            NotOfLine::Unknown => "unknown_device",
            NotOfLine::Local => "local_device",
            NotOfLine::OtherLine => "other_line_device",
        }
    }
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

    /// The one place a device of this line enters the registry. A device it holds already
    /// is admitted again (a re-declaration, a profiled device's reconnection); a new one
    /// only while the line has fewer than `[fb] max_devices` devices and `registrant`
    /// (the verified username, or the peer's address) registered fewer than
    /// `[fb] max_devices_per_identity`. A refusal is counted and logged (at most once a
    /// minute per limit, with the number refused since); the caller answers the device.
    fn admit(&self, devices: &mut Devices, id: &str, registrant: &str) -> Result<(), Full> {
        if devices.get(id).is_some_and(|r| r.line == self.line) {
            return Ok(());
        }
        let line_full =
            usize::try_from(devices.counts.local).is_ok_and(|n| n >= self.limits.max_devices);
        let held = devices.registered.get(registrant).copied().unwrap_or(0);
        let full = if line_full {
            Full::Devices(self.limits.max_devices)
        } else if held >= self.limits.max_per_identity {
            Full::PerIdentity(self.limits.max_per_identity)
        } else {
            devices.register(id, registrant);
            return Ok(());
        };
        self.metrics
            .limit_refusals
            .with_label_values(&[full.limit()])
            .inc();
        let now = Instant::now();
        let (last, unlogged) = devices.refusals_unlogged.entry(full.limit()).or_default();
        *unlogged += 1;
        if last.is_none_or(|t| now.duration_since(t) >= LIMIT_LOG_INTERVAL) {
            tracing::warn!(
                device = id,
                registrant,
                limit = full.limit(),
                refused_since_last_line = *unlogged,
                "new device refused: {full} (logged at most once a minute per limit; \
                 fbbus_limit_refusals_total)"
            );
            *last = Some(now);
            *unlogged = 0;
        }
        Err(full)
    }

    /// Forgets the offline device `id` of this line: its record, its retained record on
    /// `fbbus/devices/<id>` and its ports' retained values (cleared with empty retained
    /// messages), its output timing and its metric series. Returns the record it had.
    pub fn forget(&self, id: &str, reason: ForgetReason) -> Result<Record, ForgetError> {
        let mut devices = self.devices.lock().unwrap_or_else(PoisonError::into_inner);
        match devices.get(id) {
            None => return Err(ForgetError::Unknown(id.to_owned())),
            Some(r) if r.line != self.line => {
                return Err(ForgetError::OtherLine(id.to_owned(), r.line.clone()))
            }
            Some(r) if r.status == Status::Online => {
                return Err(ForgetError::Online(id.to_owned()))
            }
            Some(_) => {}
        }
        let record = self.remove(&mut devices, id, reason);
        self.announce_count(&devices);
        record.ok_or_else(|| ForgetError::Unknown(id.to_owned()))
    }

    /// Forgets the local devices offline for `after` or longer at `now`.
    fn expire(&self, now: SystemTime, after: Duration) {
        let mut devices = self.devices.lock().unwrap_or_else(PoisonError::into_inner);
        let expired: Vec<String> = devices
            .offline_since
            .iter()
            .filter(|(_, since)| now.duration_since(**since).is_ok_and(|d| d >= after))
            .map(|(id, _)| id.clone())
            .collect();
        if expired.is_empty() {
            return;
        }
        for id in &expired {
            self.remove(&mut devices, id, ForgetReason::Expired);
        }
        self.announce_count(&devices);
    }

    /// Removes `id` (checked by the caller), clears what it retained, and tells.
    fn remove(&self, devices: &mut Devices, id: &str, reason: ForgetReason) -> Option<Record> {
        let record = devices.remove(id)?;
        let _ = self.changes.send(Change::Removed(id.into()));
        // The values first, the record last: one ordered queue, so whoever sees the
        // record cleared knows the values are cleared too (a new subscriber gets none).
        for clear in retained_clears(id, record.interface.outputs()) {
            self.publisher.publish(clear);
        }
        self.publisher
            .publish(Message::broker(topic::device_record(id), Vec::new(), true));
        self.metrics.forget_device(id);
        self.metrics
            .registry_forgotten
            .with_label_values(&[reason.label()])
            .inc();
        self.dirty.notify_one();
        tracing::info!(
            device = id,
            reason = reason.label(),
            offline_since = record.since,
            "device forgotten: its record and retained values are cleared"
        );
        Some(record)
    }

    /// A connection of `id` took session number `session` and is about to end any older
    /// connection of that id (takeover). Recording the number first is what makes the old
    /// connection's end stale, whichever of the two finishes first.
    pub fn session_started(&self, id: &str, session: u64) {
        let mut devices = self.devices.lock().unwrap_or_else(PoisonError::into_inner);
        devices.update(
            id,
            |_| true,
            |record| record.session = record.session.max(session),
        );
    }

    /// A client connected with session `session`. A known device is online again (with
    /// its declared interface, returned) until it declares a new one.
    pub fn connected(&self, id: &str, session: u64) -> Option<Arc<Interface>> {
        let mut devices = self.devices.lock().unwrap_or_else(PoisonError::into_inner);
        let record = devices.update(
            id,
            |record| session >= record.session,
            |record| {
                record.status = Status::Online;
                record.session = session;
                record.since = now();
                record.last_will_reason = None;
                record.silent = false;
                record.silent_since = None;
            },
        )?;
        let interface = Arc::clone(&record.interface);
        let record = record.clone();
        let at = Instant::now();
        match devices.activity.get(id) {
            Some(activity) => activity.reconnected(at),
            None => {
                let activity = Activity::new(&interface, at);
                activity.remember(&devices.periods(id));
                devices.activity.insert(id.to_owned(), Arc::new(activity));
            }
        }
        self.announce(&record);
        self.announce_count(&devices);
        self.dirty.notify_one();
        Some(interface)
    }

    /// The connection `session` of `id` ended for `reason`. Applied only if it is the
    /// device's current session; returns whether it was.
    pub fn disconnected(&self, id: &str, session: u64, reason: &str) -> bool {
        let mut devices = self.devices.lock().unwrap_or_else(PoisonError::into_inner);
        let Some(record) = devices.get(id) else {
            return false;
        };
        if record.session == session && record.status == Status::Offline {
            // Ended already, for its silence (`end_for_silence`): its will went then.
            return false;
        }
        if record.session != session || record.status != Status::Online {
            self.metrics.registry_stale_ends.inc();
            tracing::debug!(
                device = id,
                session,
                current = record.session,
                reason,
                "end of an older session ignored: the device is on a newer one"
            );
            return false;
        }
        let record = devices.update(
            id,
            |_| true,
            |record| {
                record.status = Status::Offline;
                record.since = now();
                record.last_will_reason = Some(reason.to_owned());
                record.silent = false;
                record.silent_since = None;
            },
        );
        if let Some(record) = record {
            self.announce(record);
        }
        self.announce_count(&devices);
        self.dirty.notify_one();
        true
    }

    pub fn get(&self, id: &str) -> Option<Record> {
        self.devices
            .lock()
            .unwrap_or_else(PoisonError::into_inner)
            .get(id)
            .cloned()
    }

    /// The declared interface of `id` if it is a device of the other line `line`, as
    /// `line`'s own record declared it: the bridge imports a message of `id` from `line`
    /// only then, and checks it against this interface (no record is cloned).
    pub fn remote_interface(&self, id: &str, line: &str) -> Result<Arc<Interface>, NotOfLine> {
        let devices = self.devices.lock().unwrap_or_else(PoisonError::into_inner);
        match devices.get(id) {
            None => Err(NotOfLine::Unknown),
            Some(r) if r.line == self.line => Err(NotOfLine::Local),
            Some(r) if r.line != line => Err(NotOfLine::OtherLine),
            Some(r) => Ok(Arc::clone(&r.interface)),
        }
    }

    /// Every device, by id.
    pub fn list(&self) -> Vec<Record> {
        self.devices
            .lock()
            .unwrap_or_else(PoisonError::into_inner)
            .values()
            .cloned()
            .collect()
    }

    /// One page of the devices `which` selects, in id order: the first `limit` with an id
    /// after `after`, and whether more follow. A range walk of the ordered records: only
    /// the page's records (and those `which` skips) are visited and copied under the lock,
    /// whatever the registry's size; the admin API's listing must not hold what sessions
    /// need while it serializes.
    pub fn page(
        &self,
        after: Option<&str>,
        limit: usize,
        which: impl Fn(&Record) -> bool,
    ) -> (Vec<Record>, bool) {
        use std::ops::Bound::{Excluded, Unbounded};
        let devices = self.devices.lock().unwrap_or_else(PoisonError::into_inner);
        let from = after.map_or(Unbounded, Excluded);
        let mut matching = devices
            .range::<str, _>((from, Unbounded))
            .map(|(_, record)| record)
            .filter(|record| which(record));
        let page: Vec<Record> = matching.by_ref().take(limit).cloned().collect();
        let more = matching.next().is_some();
        (page, more)
    }

    /// Every change of a local device's record from now on is sent to `observer`.
    /// Returns the local records as they are now.
    pub fn observe(&self, observer: tokio::sync::mpsc::UnboundedSender<Record>) -> Vec<Record> {
        let devices = self.devices.lock().unwrap_or_else(PoisonError::into_inner);
        let _ = self.observer.set(observer);
        devices
            .values()
            .filter(|r| r.line == self.line)
            .cloned()
            .collect()
    }

    /// The local devices' records.
    pub fn local(&self) -> Vec<Record> {
        self.list()
            .into_iter()
            .filter(|r| r.line == self.line)
            .collect()
    }

    /// Line `from` says this is its device's record (`from` is the line whose key it came
    /// on: on a mutual-TLS bus, the line zenoh authenticated). A device id is unique on
    /// the bus: a line speaks only for its own devices, a local device of the same id
    /// wins, and a device online on another line is not taken over (a device that moved
    /// is taken once its old line has it offline or unreachable).
    pub fn remote_record(&self, from: &str, record: Record) -> Result<(), RecordRefused> {
        self.take_remote(from, record, None)
    }

    /// Where live records stand now: pass it to [`Registry::queried_record`] for the
    /// answers of a query sent after this.
    pub fn live_mark(&self) -> u64 {
        self.devices
            .lock()
            .unwrap_or_else(PoisonError::into_inner)
            .live_taken
    }

    /// A record from the answer to a query of line `from`'s registry, sent at `mark`
    /// ([`Registry::live_mark`]). The answer is older than any live record of the device
    /// that came after the query was sent: such a record is kept, and the answer dropped
    /// (that is not a refusal). Else taken as [`Registry::remote_record`] takes it.
    pub fn queried_record(
        &self,
        from: &str,
        record: Record,
        mark: u64,
    ) -> Result<(), RecordRefused> {
        self.take_remote(from, record, Some(mark))
    }

    fn take_remote(
        &self,
        from: &str,
        record: Record,
        queried_at: Option<u64>,
    ) -> Result<(), RecordRefused> {
        if record.line != from || from == self.line {
            return Err(RecordRefused::ForgedLine);
        }
        let mut devices = self.devices.lock().unwrap_or_else(PoisonError::into_inner);
        match devices.get(&record.id) {
            Some(held) if held.line == self.line => return Err(RecordRefused::LocalDevice),
            Some(held) if held.line != record.line && held.status == Status::Online => {
                return Err(RecordRefused::HeldByAnotherLine)
            }
            _ => {}
        }
        match queried_at {
            Some(mark) if devices.live.get(&record.id).is_some_and(|&at| at > mark) => {
                return Ok(());
            }
            Some(_) => {}
            None => {
                devices.live_taken += 1;
                let at = devices.live_taken;
                devices.live.insert(record.id.clone(), at);
            }
        }
        if devices.get(&record.id).is_some_and(|held| *held == record) {
            return Ok(());
        }
        self.announce(&record);
        devices.insert(record);
        self.announce_count(&devices);
        Ok(())
    }

    /// A remote device's status changed as seen from here (`Unreachable`, or back `Online`
    /// when its liveliness token reappears).
    pub fn remote_status(&self, line: &str, id: &str, status: Status) {
        let mut devices = self.devices.lock().unwrap_or_else(PoisonError::into_inner);
        let changed = devices.update(
            id,
            |r| r.line == line && r.status != status,
            |record| {
                record.status = status;
                record.since = now();
            },
        );
        let Some(record) = changed else {
            return;
        };
        self.announce(record);
        self.announce_count(&devices);
    }

    /// Every change of a record (local or remote) and every removal from now on, on a
    /// channel of [`CHANGES_CAPACITY`]: a receiver that falls further behind gets
    /// `Lagged` and must read the registry again.
    pub fn changes(&self) -> tokio::sync::broadcast::Receiver<Change> {
        self.changes.subscribe()
    }

    /// This line's online devices now (O(1): the counts follow every change).
    pub fn line_online(&self) -> i64 {
        self.devices
            .lock()
            .unwrap_or_else(PoisonError::into_inner)
            .counts
            .online_here
    }

    /// The other lines the bridge has seen, by name, and whether they are reachable.
    pub fn lines(&self) -> BTreeMap<String, LineState> {
        self.lines
            .lock()
            .unwrap_or_else(PoisonError::into_inner)
            .clone()
    }

    /// The bridge reached `line` (its liveliness token appeared).
    pub fn line_reachable(&self, line: &str) {
        self.note_line(line, true);
    }

    fn note_line(&self, line: &str, reachable: bool) {
        if line == self.line {
            return;
        }
        let mut lines = self.lines.lock().unwrap_or_else(PoisonError::into_inner);
        if let Some(state) = lines.get_mut(line) {
            if state.reachable != reachable {
                *state = LineState {
                    reachable,
                    since: now(),
                };
            }
        } else if lines.len() < MAX_LINES {
            lines.insert(
                line.to_owned(),
                LineState {
                    reachable,
                    since: now(),
                },
            );
        }
    }

    /// `line` cannot be reached: every device of it is unreachable.
    pub fn line_unreachable(&self, line: &str) {
        if line == self.line {
            return;
        }
        self.note_line(line, false);
        let mut devices = self.devices.lock().unwrap_or_else(PoisonError::into_inner);
        let mut changed = Vec::new();
        devices.update_all(
            |r| r.line == line && r.status != Status::Unreachable,
            |record| {
                record.status = Status::Unreachable;
                record.since = now();
                changed.push(record.clone());
            },
        );
        for record in &changed {
            self.announce(record);
        }
        if !changed.is_empty() {
            self.announce_count(&devices);
        }
    }

    /// Writes the whole registry now and empties the journal (at shutdown).
    pub fn flush(&self) {
        if let Some(path) = &self.file {
            if let Err(e) = self.append(path, true) {
                tracing::error!(path = %path.display(), error = %e, "cannot persist the device registry");
            }
        }
    }

    fn announce(&self, record: &Record) {
        if record.line == self.line {
            if let Some(observer) = self.observer.get() {
                let _ = observer.send(record.clone());
            }
        }
        let payload = bytes::Bytes::from(serde_json::to_vec(record).expect("a record serializes"));
        // Without a receiver (no console) nothing is cloned.
        if self.changes.receiver_count() > 0 {
            let _ = self
                .changes
                .send(Change::Record(Arc::new(record.clone()), payload.clone()));
        }
        self.publisher.publish(Message::broker(
            topic::device_record(&record.id),
            payload,
            true,
        ));
    }

    fn announce_count(&self, devices: &Devices) {
        let Counts {
            by_status,
            online_here,
            silent,
            local: _,
        } = devices.counts;
        self.metrics.registry_silent_devices.set(silent);
        for (status, count) in [Status::Online, Status::Offline, Status::Unreachable]
            .into_iter()
            .zip(by_status)
        {
            self.metrics
                .registry_devices
                .with_label_values(&[status.label()])
                .set(count);
        }
        self.publisher.publish(Message::broker(
            topic::line_online(&self.line),
            online_here.to_string(),
            true,
        ));
    }

    /// Starts the registry's periodic checks, every [`SILENCE_CHECK`]: the local
    /// devices' silence, unless the judgement is off (`silence_factor = 0`), and the
    /// expiry of offline devices, if `[fb] forget_offline_after_s` is set.
    pub fn start_periodic_checks(self: &Arc<Self>, tasks: &crate::supervisor::Tasks) {
        if self.bound.enabled() || self.limits.forget_offline_after.is_some() {
            tasks.core("registry checks", Arc::clone(self).check_loop());
        }
    }

    async fn check_loop(self: Arc<Self>) {
        let mut tick = tokio::time::interval(SILENCE_CHECK);
        tick.set_missed_tick_behavior(tokio::time::MissedTickBehavior::Delay);
        for n in 1u32.. {
            tick.tick().await;
            if let Some(after) = self.limits.forget_offline_after {
                self.expire(SystemTime::now(), after);
            }
            if !self.bound.enabled() {
                continue;
            }
            self.judge_silence(Instant::now());
            if n % PERIODS_PERSIST == 0 {
                self.dirty.notify_one();
            }
        }
    }

    /// Judges every local online device at `now` and announces those that turned silent
    /// or spoke again.
    fn judge_silence(&self, now: Instant) {
        let mut devices = self.devices.lock().unwrap_or_else(PoisonError::into_inner);
        let mut turned = Vec::new();
        let mut ended = Vec::new();
        for (id, activity) in &devices.activity {
            let Some(record) = devices.get(id) else {
                continue;
            };
            if record.line != self.line || record.status != Status::Online {
                continue;
            }
            let since = match activity.judge(now, &self.bound) {
                Verdict::Silent { since } => Some(since),
                Verdict::Speaking | Verdict::NoPeriod => None,
            };
            if let Some(since) = since.filter(|s| activity.end_if_silent_for(now, *s)) {
                ended.push((id.clone(), now.saturating_duration_since(since)));
            } else if since.is_some() != record.silent {
                turned.push((id.clone(), since));
            }
        }
        for (id, quiet) in ended {
            self.end_for_silence(&mut devices, &id, quiet);
        }
        if turned.is_empty() {
            self.announce_count(&devices);
            return;
        }
        let wall = SystemTime::now();
        for (id, since) in turned {
            let since = since.map(|s| {
                let ago = now.saturating_duration_since(s);
                humantime::format_rfc3339_millis(wall.checked_sub(ago).unwrap_or(wall)).to_string()
            });
            let changed = devices.update(
                &id,
                |_| true,
                |record| {
                    record.silent = since.is_some();
                    record.silent_since = since;
                },
            );
            if let Some(record) = changed {
                tracing::info!(
                    device = record.id,
                    silent = record.silent,
                    since = record.silent_since,
                    "device output activity changed"
                );
                self.announce(record);
            }
        }
        self.announce_count(&devices);
    }

    /// `id` has been silent for `quiet`, longer than its profile allows
    /// (`liveness.offline_after_silent_s`): offline, with that reason. Its connections
    /// stay open, and one of them publishes its will (`Activity::take_will_due`).
    fn end_for_silence(&self, devices: &mut Devices, id: &str, quiet: Duration) {
        let reason = format!(
            "silent: no periodic output for {} s (liveness.offline_after_silent_s)",
            quiet.as_secs()
        );
        let changed = devices.update(
            id,
            |r| r.status == Status::Online,
            |record| {
                record.status = Status::Offline;
                record.since = now();
                record.last_will_reason = Some(reason.clone());
                record.silent = false;
                record.silent_since = None;
            },
        );
        if let Some(record) = changed {
            self.metrics.registry_silence_offline.inc();
            tracing::warn!(
                device = record.id,
                reason,
                "device offline for its silence; its will is published"
            );
            self.announce(record);
            self.dirty.notify_one();
        }
    }

    /// A device the registry ended for its silence published again on its connection
    /// `session`: online again.
    pub fn spoke_again(&self, id: &str, session: u64) {
        let mut devices = self.devices.lock().unwrap_or_else(PoisonError::into_inner);
        let changed = devices.update(
            id,
            |r| r.status == Status::Offline,
            |record| {
                record.status = Status::Online;
                record.session = record.session.max(session);
                record.since = now();
                record.last_will_reason = None;
            },
        );
        if let Some(record) = changed {
            tracing::info!(
                device = record.id,
                "device speaks again after its silence: online"
            );
            self.announce(record);
            self.announce_count(&devices);
            self.dirty.notify_one();
        }
    }

    async fn persist_loop(self: Arc<Self>) {
        let path = self.file.clone().expect("persisting needs a file");
        loop {
            self.dirty.notified().await;
            let this = Arc::clone(&self);
            let p = path.clone();
            let result = tokio::task::spawn_blocking(move || this.append(&p, false)).await;
            if let Ok(Err(e)) = result {
                tracing::error!(path = %path.display(), error = %e, "cannot persist the device registry; retrying on the next change");
                // What was taken is marked again: nothing is lost by a failed write.
                self.dirty.notify_one();
            }
            tokio::time::sleep(PERSIST_INTERVAL).await;
        }
    }

    /// Appends the records changed since the last append to the journal and syncs it;
    /// then, if the journal outgrew the snapshot (or `compact`), writes the snapshot and
    /// empties the journal. Periods alone (the silence loop's periodic wake) are
    /// journaled for the devices whose periods changed since they were last written.
    fn append(&self, path: &Path, compact: bool) -> std::io::Result<()> {
        let mut journal = self.journal.lock().unwrap_or_else(PoisonError::into_inner);
        let seq = journal.seq + 1;
        let entries: Vec<Entry> = {
            let mut devices = self.devices.lock().unwrap_or_else(PoisonError::into_inner);
            let mut changed = devices
                .changed
                .as_mut()
                .map(std::mem::take)
                .unwrap_or_default();
            // Periods change with every publication: looked at once in a while only.
            let every = SILENCE_CHECK * PERIODS_PERSIST;
            if journal.periods_at.is_none_or(|at| at.elapsed() >= every) {
                journal.periods_at = Some(Instant::now());
                for (id, activity) in &devices.activity {
                    let periods = activity.periods();
                    if journal.periods.get(id) != Some(&periods) && !periods.is_empty() {
                        changed.insert(id.clone());
                    }
                }
            }
            changed
                .into_iter()
                .map(|id| match devices.get(&id) {
                    Some(record) if record.line == self.line => Entry::Device {
                        seq,
                        periods: devices.periods(&id),
                        registrant: devices.registrants.get(&id).map(|r| r.to_string()),
                        record: record.clone(),
                    },
                    _ => Entry::Removed { seq, id },
                })
                .collect()
        };
        let mut bytes = Vec::with_capacity(entries.len() * 512);
        for entry in &entries {
            serde_json::to_writer(&mut bytes, entry).expect("a registry entry serializes");
            bytes.push(b'\n');
        }
        let written = match journal.write(path, &bytes) {
            Ok(()) => Ok(()),
            Err(e) => {
                // Marked again for the next try.
                let mut devices = self.devices.lock().unwrap_or_else(PoisonError::into_inner);
                if let Some(changed) = devices.changed.as_mut() {
                    changed.extend(entries.iter().map(|e| e.id().to_owned()));
                }
                Err(e)
            }
        };
        written?;
        if !entries.is_empty() {
            journal.seq = seq;
        }
        for entry in entries {
            match entry {
                Entry::Device {
                    record, periods, ..
                } => {
                    journal.periods.insert(record.id, periods);
                }
                Entry::Removed { id, .. } => {
                    journal.periods.remove(&id);
                }
            }
        }
        if compact || journal.needs_compaction() {
            self.write(path, &mut journal)?;
        }
        Ok(())
    }

    /// Writes a snapshot atomically (temporary file, fsync, rename, fsync of the
    /// directory), then empties the journal, whose lines it holds.
    fn write(&self, path: &Path, journal: &mut Journal) -> std::io::Result<()> {
        let devices = self.local();
        let (periods, registrants) = {
            let held = self.devices.lock().unwrap_or_else(PoisonError::into_inner);
            let periods = devices
                .iter()
                .map(|r| (r.id.clone(), held.periods(&r.id)))
                .filter(|(_, p)| !p.is_empty())
                .collect();
            let registrants = held
                .registrants
                .iter()
                .map(|(id, who)| (id.clone(), who.to_string()))
                .collect();
            (periods, registrants)
        };
        let snapshot = File {
            version: 1,
            seq: journal.seq,
            devices,
            periods,
            registrants,
        };
        let bytes = serde_json::to_vec_pretty(&snapshot).expect("the registry serializes");
        let tmp = path.with_extension("tmp");
        {
            use std::io::Write;
            let mut f = std::fs::File::create(&tmp)?;
            f.write_all(&bytes)?;
            f.sync_all()?;
        }
        std::fs::rename(&tmp, path)?;
        if let Some(dir) = path.parent().filter(|d| !d.as_os_str().is_empty()) {
            std::fs::File::open(dir)?.sync_all()?;
        }
        journal.snapshot_bytes = bytes.len() as u64;
        // A crash before this leaves lines the snapshot's `seq` already covers: skipped.
        journal.truncate(path)?;
        tracing::debug!(
            path = %path.display(),
            bytes = bytes.len(),
            "registry snapshot written, journal emptied"
        );
        Ok(())
    }
}

/// What a registry file holds, with its journal replayed: the records, the observed
/// periods, the registrants, and the journal as the writer goes on with it.
type Loaded = (
    Vec<Record>,
    BTreeMap<String, Periods>,
    BTreeMap<String, String>,
    Journal,
);

/// One line of the registry's journal: a local device's record as it is now, or its
/// removal.
#[derive(Debug, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
enum Entry {
    Device {
        seq: u64,
        record: Record,
        #[serde(default, skip_serializing_if = "BTreeMap::is_empty")]
        periods: Periods,
        /// Who registered it (`[fb] max_devices_per_identity`).
        #[serde(default, skip_serializing_if = "Option::is_none")]
        registrant: Option<String>,
    },
    Removed {
        seq: u64,
        id: String,
    },
}

impl Entry {
    fn id(&self) -> &str {
        match self {
            Entry::Device { record, .. } => &record.id,
            Entry::Removed { id, .. } => id,
        }
    }

    fn seq(&self) -> u64 {
        match self {
            Entry::Device { seq, .. } | Entry::Removed { seq, .. } => *seq,
        }
    }
}

/// The journal beside the snapshot (`<registry file>.log`), as the writer keeps it.
#[derive(Default)]
struct Journal {
    /// Open for appending, once the first line is written.
    file: Option<std::fs::File>,
    bytes: u64,
    snapshot_bytes: u64,
    /// The last sequence number written (a batch of lines shares one).
    seq: u64,
    /// The periods last written per device, so unchanged ones are not written again.
    periods: HashMap<String, Periods>,
    /// When the periods were last compared with what was written.
    periods_at: Option<Instant>,
}

/// The journal is compacted once it is larger than this many times the snapshot (so a
/// compaction's rewrite costs at most a quarter of what was appended since the last)...
const COMPACT_RATIO: u64 = 4;
/// ... and at least this (small registries are not rewritten for every few changes) ...
const COMPACT_FLOOR: u64 = 64 * 1024;
/// ... or once it is larger than this, whatever the snapshot (bounds replay at start).
const COMPACT_CEILING: u64 = 8 * 1024 * 1024;

fn journal_path(path: &Path) -> PathBuf {
    let mut name = path.as_os_str().to_owned();
    name.push(".log");
    PathBuf::from(name)
}

impl Journal {
    fn needs_compaction(&self) -> bool {
        self.bytes > COMPACT_CEILING
            || self.bytes > (COMPACT_RATIO * self.snapshot_bytes).max(COMPACT_FLOOR)
    }

    /// Appends `bytes` (whole lines) and syncs them.
    fn write(&mut self, path: &Path, bytes: &[u8]) -> std::io::Result<()> {
        use std::io::Write;
        if bytes.is_empty() {
            return Ok(());
        }
        let file = self.open(path)?;
        file.write_all(bytes)?;
        file.sync_data()?;
        self.bytes += bytes.len() as u64;
        Ok(())
    }

    /// The journal file, opened (created, for appending) on first use.
    fn open(&mut self, path: &Path) -> std::io::Result<&mut std::fs::File> {
        if self.file.is_none() {
            self.file = Some(
                std::fs::OpenOptions::new()
                    .create(true)
                    .append(true)
                    .open(journal_path(path))?,
            );
        }
        self.file
            .as_mut()
            .ok_or_else(|| std::io::Error::other("the registry journal is not open"))
    }

    fn truncate(&mut self, path: &Path) -> std::io::Result<()> {
        let file = self.open(path)?;
        file.set_len(0)?;
        file.sync_all()?;
        self.bytes = 0;
        Ok(())
    }
}

/// The snapshot, then the journal's lines newer than it.
fn load(path: &Path) -> Result<Loaded, LoadError> {
    let error = |message: String| LoadError {
        path: path.display().to_string(),
        message,
    };
    let mut journal = Journal::default();
    let file = match std::fs::read(path) {
        Ok(text) => {
            journal.snapshot_bytes = text.len() as u64;
            let file: File = serde_json::from_slice(&text)
                .map_err(|e| error(format!("{e}; move it away to start with an empty registry")))?;
            if file.version != 1 {
                return Err(error(format!("version {} is not supported", file.version)));
            }
            file
        }
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => File {
            version: 1,
            seq: 0,
            devices: Vec::new(),
            periods: BTreeMap::new(),
            registrants: BTreeMap::new(),
        },
        Err(e) => return Err(error(e.to_string())),
    };
    journal.seq = file.seq;
    let mut records: HashMap<String, Record> = file
        .devices
        .into_iter()
        .map(|r| (r.id.clone(), r))
        .collect();
    let mut periods = file.periods;
    let mut registrants = file.registrants;
    let log = journal_path(path);
    let log_error = |message: String| LoadError {
        path: log.display().to_string(),
        message,
    };
    let bytes = match std::fs::read(&log) {
        Ok(bytes) => bytes,
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => Vec::new(),
        Err(e) => return Err(log_error(e.to_string())),
    };
    let mut good = 0;
    for line in bytes.split_inclusive(|b| *b == b'\n') {
        let Some(text) = line.strip_suffix(b"\n") else {
            break;
        };
        let Ok(entry) = serde_json::from_slice::<Entry>(text) else {
            break;
        };
        good += line.len();
        if entry.seq() <= file.seq {
            continue;
        }
        journal.seq = journal.seq.max(entry.seq());
        match entry {
            Entry::Device {
                record,
                periods: p,
                registrant,
                ..
            } => {
                match p.is_empty() {
                    true => periods.remove(&record.id),
                    false => periods.insert(record.id.clone(), p),
                };
                match registrant {
                    Some(who) => registrants.insert(record.id.clone(), who),
                    None => registrants.remove(&record.id),
                };
                records.insert(record.id.clone(), record);
            }
            Entry::Removed { id, .. } => {
                periods.remove(&id);
                registrants.remove(&id);
                records.remove(&id);
            }
        }
    }
    if good < bytes.len() {
        // A crash mid-append: the last line is cut (or, after a disk fault, a line is
        // not JSON). What follows the last good line is kept beside the journal and cut
        // off it, so appends go on after whole lines.
        let at = SystemTime::now()
            .duration_since(SystemTime::UNIX_EPOCH)
            .map(|d| d.as_secs())
            .unwrap_or(0);
        let mut torn = log.as_os_str().to_owned();
        torn.push(format!(".torn-{at}"));
        let torn = PathBuf::from(torn);
        std::fs::write(&torn, &bytes[good..]).map_err(|e| log_error(e.to_string()))?;
        let file = std::fs::OpenOptions::new()
            .write(true)
            .open(&log)
            .map_err(|e| log_error(e.to_string()))?;
        file.set_len(good as u64)
            .and_then(|()| file.sync_all())
            .map_err(|e| log_error(e.to_string()))?;
        tracing::warn!(
            journal = %log.display(),
            torn = %torn.display(),
            bytes = bytes.len() - good,
            "registry journal: a torn or unreadable tail was moved aside; the registry is \
             recovered up to the last whole line"
        );
    }
    journal.bytes = good as u64;
    Ok((
        records.into_values().collect(),
        periods,
        registrants,
        journal,
    ))
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

#[cfg(test)]
mod tests {
    use super::*;

    fn interface() -> Interface {
        Interface {
            fbs: Default::default(),
        }
    }

    /// Journal lines the snapshot already holds (a crash between the snapshot's rename
    /// and the journal's truncation) are skipped: an older line never overrides it.
    #[test]
    fn journal_lines_older_than_the_snapshot_are_skipped() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("registry.json");
        let at = |session: u64| Record {
            session,
            ..remote("d1", "a", Status::Offline)
        };
        let snapshot = File {
            version: 1,
            seq: 5,
            devices: vec![at(50)],
            periods: BTreeMap::new(),
            registrants: BTreeMap::from([("d1".to_owned(), "127.0.0.1".to_owned())]),
        };
        std::fs::write(&path, serde_json::to_vec(&snapshot).unwrap()).unwrap();
        let mut journal = Vec::new();
        for (seq, session) in [(4, 40), (6, 60)] {
            let entry = Entry::Device {
                seq,
                record: at(session),
                periods: Periods::new(),
                registrant: Some(format!("user-{seq}")),
            };
            serde_json::to_writer(&mut journal, &entry).unwrap();
            journal.push(b'\n');
        }
        let removed = Entry::Removed {
            seq: 3,
            id: "d1".into(),
        };
        serde_json::to_writer(&mut journal, &removed).unwrap();
        journal.push(b'\n');
        std::fs::write(journal_path(&path), &journal).unwrap();
        let (records, _, registrants, state) = load(&path).unwrap();
        assert_eq!(records.len(), 1);
        assert_eq!(records[0].session, 60);
        // The registrant too comes from the newer line, not the older one or the snapshot.
        assert_eq!(registrants["d1"], "user-6");
        assert_eq!(state.seq, 6);
        assert_eq!(state.bytes, journal.len() as u64);
    }

    fn remote(id: &str, line: &str, status: Status) -> Record {
        Record {
            id: id.into(),
            line: line.into(),
            status,
            session: 1,
            since: now(),
            last_will_reason: None,
            silent: false,
            silent_since: None,
            interface: Arc::new(interface()),
        }
    }

    fn registry(
        metrics: &Arc<Metrics>,
    ) -> (Arc<Registry>, tokio::sync::mpsc::UnboundedReceiver<Message>) {
        let (publisher, published) = BrokerPublisher::detached();
        let bound = Bound {
            factor: 3.0,
            floor: Duration::from_secs(1),
        };
        let health = crate::health::Health::new();
        let tasks = crate::supervisor::Tasks::new(&health);
        let registry = Registry::open(
            "a",
            None,
            publisher,
            Arc::clone(metrics),
            bound,
            Limits::NONE,
            &tasks,
        );
        (registry.unwrap(), published)
    }

    /// The observed periods survive a restart: a device that reconnects and never
    /// publishes (a FORTE whose publishers died) is still judged.
    #[tokio::test]
    async fn periods_are_persisted_and_given_back_on_connect() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("registry.json");
        let open = || {
            let (publisher, _) = BrokerPublisher::detached();
            let health = crate::health::Health::new();
            let bound = crate::silence::Bound::DEFAULT;
            let tasks = crate::supervisor::Tasks::new(&health);
            let metrics = Arc::new(Metrics::new());
            Registry::open(
                "a",
                Some(&path),
                publisher,
                metrics,
                bound,
                Limits::NONE,
                &tasks,
            )
            .unwrap()
        };
        let speed: Interface = serde_json::from_value(serde_json::json!({"fbs": {"CONV": {
            "data_out": {"SPEED": "REAL"},
        }}}))
        .unwrap();
        let first = open();
        first.declare("d1", 1, speed, "test").unwrap();
        let activity = first.activity("d1").unwrap();
        let t0 = Instant::now();
        for i in 0..10 {
            let at = t0 + Duration::from_millis(200) * i;
            activity.published("CONV", "SPEED", at, first.silence_bound());
        }
        first.flush();
        drop(first);

        let second = open();
        assert!(second.activity("d1").is_none());
        assert!(second.connected("d1", 2).is_some());
        let periods = second.activity("d1").unwrap().periods();
        assert!(
            (periods["CONV"]["SPEED"] - 0.2).abs() < 0.001,
            "{periods:?}"
        );
    }

    /// A local device whose periodic output stops turns silent once, is counted, and
    /// speaks again once; going offline ends the silence.
    #[test]
    fn silence_is_announced_once_each_way() {
        let metrics = Arc::new(Metrics::new());
        let (registry, mut published) = registry(&metrics);
        let speed: Interface = serde_json::from_value(serde_json::json!({"fbs": {"CONV": {
            "data_out": {"SPEED": "REAL"},
        }}}))
        .unwrap();
        registry.declare("d1", 1, speed, "test").unwrap();
        registry.declare("quiet", 2, interface(), "test").unwrap();
        let activity = registry.activity("d1").unwrap();
        let bound = *registry.silence_bound();
        let t0 = Instant::now();
        let mut last = t0;
        for i in 0..20 {
            last = t0 + Duration::from_millis(200) * i;
            activity.published("CONV", "SPEED", last, &bound);
        }
        let mut records = || {
            let mut out = Vec::new();
            while let Ok(m) = published.try_recv() {
                if m.topic == topic::device_record("d1") {
                    out.push(serde_json::from_slice::<Record>(&m.payload).unwrap());
                }
            }
            out
        };
        records();
        let silent = || metrics.registry_silent_devices.get();

        registry.judge_silence(last + Duration::from_millis(1000));
        assert!(records().is_empty(), "within the bound");
        registry.judge_silence(last + Duration::from_millis(1001));
        let turned = records();
        assert_eq!(turned.len(), 1);
        assert!(turned[0].silent && turned[0].silent_since.is_some());
        assert_eq!(turned[0].status, Status::Online);
        assert_eq!(silent(), 1);
        registry.judge_silence(last + Duration::from_millis(5000));
        assert!(records().is_empty(), "announced once");
        assert!(!registry.get("quiet").unwrap().silent, "no periodic port");

        let back = last + Duration::from_millis(6000);
        activity.published("CONV", "SPEED", back, &bound);
        registry.judge_silence(back);
        let turned = records();
        assert_eq!(turned.len(), 1);
        assert!(!turned[0].silent && turned[0].silent_since.is_none());
        assert_eq!(silent(), 0);

        registry.judge_silence(back + Duration::from_millis(1001));
        assert_eq!(silent(), 1);
        assert!(registry.disconnected("d1", 1, "keep-alive"));
        let record = registry.get("d1").unwrap();
        assert!(!record.silent && record.status == Status::Offline);
        assert_eq!(silent(), 0);
    }

    /// The counts announced after every change (gauges and the line's online count) are
    /// the counts of the records, whatever the change: they are kept with each change
    /// instead of recounted from every record (which made births quadratic).
    #[test]
    fn announced_counts_follow_every_change() {
        let (publisher, mut published) = BrokerPublisher::detached();
        let metrics = Arc::new(Metrics::new());
        let health = crate::health::Health::new();
        let registry = Registry::open(
            "a",
            None,
            publisher,
            Arc::clone(&metrics),
            crate::silence::Bound::DEFAULT,
            Limits::NONE,
            &crate::supervisor::Tasks::new(&health),
        )
        .unwrap();
        let mut line_online = None;
        let mut check = |step: &str| {
            let records = registry.list();
            let count = |status| records.iter().filter(|r| r.status == status).count() as i64;
            for status in [Status::Online, Status::Offline, Status::Unreachable] {
                let gauge = metrics
                    .registry_devices
                    .with_label_values(&[status.label()])
                    .get();
                assert_eq!(gauge, count(status), "{step}: {} devices", status.label());
            }
            while let Ok(m) = published.try_recv() {
                if m.topic == topic::line_online("a") {
                    line_online = Some(String::from_utf8(m.payload.to_vec()).unwrap());
                }
            }
            let here = records
                .iter()
                .filter(|r| r.line == "a" && r.status == Status::Online)
                .count();
            assert_eq!(line_online, Some(here.to_string()), "{step}: line online");
        };

        for (i, id) in ["d1", "d2", "d3"].into_iter().enumerate() {
            registry
                .declare(id, i as u64 + 1, interface(), "test")
                .unwrap();
        }
        check("declared");
        assert!(registry.disconnected("d1", 1, "clean disconnect"));
        check("d1 offline");
        assert!(registry.connected("d1", 4).is_some());
        check("d1 back");
        assert!(!registry.disconnected("d1", 1, "stale"));
        check("stale end ignored");
        registry.session_started("d2", 5);
        registry.declare("d2", 5, interface(), "test").unwrap();
        check("d2 declared again");
        assert_eq!(
            registry.remote_record("b", remote("r1", "b", Status::Online)),
            Ok(())
        );
        assert_eq!(
            registry.remote_record("b", remote("r2", "b", Status::Offline)),
            Ok(())
        );
        assert_eq!(
            registry.remote_record("b", remote("d3", "b", Status::Offline)),
            Err(RecordRefused::LocalDevice)
        );
        // A line speaks only for its own devices, and does not take one online elsewhere.
        assert_eq!(
            registry.remote_record("c", remote("r9", "b", Status::Online)),
            Err(RecordRefused::ForgedLine)
        );
        assert_eq!(
            registry.remote_record("c", remote("r1", "c", Status::Online)),
            Err(RecordRefused::HeldByAnotherLine)
        );
        check("remote records");
        registry.remote_status("b", "r1", Status::Unreachable);
        check("r1 unreachable");
        registry.remote_status("b", "r1", Status::Online);
        assert_eq!(
            registry.remote_record("b", remote("r1", "b", Status::Offline)),
            Ok(())
        );
        check("r1 replaced");
        // Offline on its line, r1 may move to line c.
        assert_eq!(
            registry.remote_record("c", remote("r1", "c", Status::Online)),
            Ok(())
        );
        assert_eq!(
            registry.remote_record("b", remote("r1", "b", Status::Offline)),
            Err(RecordRefused::HeldByAnotherLine)
        );
        assert_eq!(
            registry.remote_record("c", remote("r1", "c", Status::Offline)),
            Ok(())
        );
        assert_eq!(
            registry.remote_record("b", remote("r1", "b", Status::Offline)),
            Ok(())
        );
        check("r1 moved and back");
        // A query answered before a live record came does not undo it.
        let mark = registry.live_mark();
        let mut newer = remote("r2", "b", Status::Online);
        newer.session = 2;
        assert_eq!(registry.remote_record("b", newer.clone()), Ok(()));
        assert_eq!(
            registry.queried_record("b", remote("r2", "b", Status::Offline), mark),
            Ok(())
        );
        assert_eq!(registry.get("r2"), Some(newer));
        let mark = registry.live_mark();
        assert_eq!(
            registry.queried_record("b", remote("r2", "b", Status::Offline), mark),
            Ok(())
        );
        assert_eq!(registry.get("r2").unwrap().status, Status::Offline);
        check("queried records");
        registry.line_unreachable("b");
        check("line b unreachable");
        assert!(registry.disconnected("d3", 3, "keep-alive"));
        check("d3 offline");
    }

    fn limited(limits: Limits, file: Option<&Path>) -> (Arc<Registry>, Arc<Metrics>) {
        let (publisher, _) = BrokerPublisher::detached();
        let metrics = Arc::new(Metrics::new());
        let health = crate::health::Health::new();
        let registry = Registry::open(
            "a",
            file,
            publisher,
            Arc::clone(&metrics),
            crate::silence::Bound::DEFAULT,
            limits,
            &crate::supervisor::Tasks::new(&health),
        )
        .unwrap();
        (registry, metrics)
    }

    /// A new device beyond either limit is refused and counted; a known device declares
    /// again whoever it is; other lines' devices do not count; a forgotten device frees
    /// its place, and who registered what survives a restart.
    #[tokio::test]
    async fn new_devices_are_admitted_within_the_limits() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("registry.json");
        let limits = Limits {
            max_devices: 3,
            max_per_identity: 2,
            forget_offline_after: None,
        };
        let (registry, metrics) = limited(limits, Some(&path));
        let refusals = |limit: &str| metrics.limit_refusals.with_label_values(&[limit]).get();
        assert!(registry.declare("d1", 1, interface(), "a").is_ok());
        assert!(registry.declare("d2", 2, interface(), "a").is_ok());
        assert_eq!(
            registry.declare("d3", 3, interface(), "a"),
            Err(Full::PerIdentity(2))
        );
        assert_eq!(
            registry.remote_record("b", remote("r1", "b", Status::Online)),
            Ok(())
        );
        assert!(registry.declare("d3", 3, interface(), "b").is_ok());
        assert_eq!(
            registry.declare("d4", 4, interface(), "c"),
            Err(Full::Devices(3))
        );
        assert!(registry.get("d4").is_none());
        assert!(registry.declare("d1", 5, interface(), "c").is_ok(), "known");
        assert_eq!(
            (refusals("devices"), refusals("devices_per_identity")),
            (1, 1)
        );

        assert!(registry.disconnected("d1", 5, "clean disconnect"));
        registry.forget("d1", ForgetReason::Admin).unwrap();
        assert!(
            registry.declare("d4", 6, interface(), "a").is_ok(),
            "d1's place"
        );
        assert_eq!(
            registry.declare("d5", 7, interface(), "c"),
            Err(Full::Devices(3))
        );
        registry.flush();
        drop(registry);

        let (reopened, _) = limited(
            Limits {
                max_devices: 10,
                ..limits
            },
            Some(&path),
        );
        assert_eq!(
            reopened.declare("d6", 8, interface(), "a"),
            Err(Full::PerIdentity(2)),
            "a registered d2 and d4 before the restart"
        );
        assert!(reopened.declare("d6", 8, interface(), "b").is_ok());
    }

    /// Forgetting: refused for an unknown, online or remote device; an offline one goes
    /// with its retained record and port values (empty retained messages), its counts
    /// and its metric series.
    #[test]
    fn forgetting_clears_the_record_its_retained_values_and_series() {
        let metrics = Arc::new(Metrics::new());
        let (registry, mut published) = registry(&metrics);
        let speed: Interface = serde_json::from_value(serde_json::json!({"fbs": {"CONV": {
            "data_out": {"SPEED": "REAL"}, "data_in": {"SET": "REAL"},
        }}}))
        .unwrap();
        registry.declare("d1", 1, speed, "a").unwrap();
        assert_eq!(
            registry.remote_record("b", remote("r1", "b", Status::Offline)),
            Ok(())
        );
        assert_eq!(
            registry.forget("nope", ForgetReason::Admin),
            Err(ForgetError::Unknown("nope".into()))
        );
        assert_eq!(
            registry.forget("d1", ForgetReason::Admin),
            Err(ForgetError::Online("d1".into()))
        );
        assert_eq!(
            registry.forget("r1", ForgetReason::Admin),
            Err(ForgetError::OtherLine("r1".into(), "b".into()))
        );
        metrics.typed_refused("d1", "CONV.SPEED", "payload_format_invalid");
        metrics.typed_refused("d1", "undeclared", "topic_name_invalid");
        metrics.typed_refused("d2", "CONV.SPEED", "payload_format_invalid");
        assert!(registry.disconnected("d1", 1, "clean disconnect"));
        while published.try_recv().is_ok() {}

        registry.forget("d1", ForgetReason::Admin).unwrap();
        assert!(registry.get("d1").is_none());
        let mut cleared = Vec::new();
        while let Ok(m) = published.try_recv() {
            if m.payload.is_empty() {
                assert!(m.retain);
                cleared.push(String::from_utf8(m.topic.to_vec()).unwrap());
            }
        }
        cleared.sort();
        assert_eq!(
            cleared,
            [
                "dinasore/d1/CONV/SPEED",
                "fb/d1/CONV/SPEED",
                "fbbus/devices/d1",
                "fbdk/d1/CONV/SPEED"
            ]
        );
        let offline = metrics
            .registry_devices
            .with_label_values(&["offline"])
            .get();
        assert_eq!(offline, 1, "r1 only");
        let forgotten = metrics
            .registry_forgotten
            .with_label_values(&["admin"])
            .get();
        assert_eq!(forgotten, 1);
        let text = metrics.render();
        assert!(!text.contains("device=\"d1\""), "{text}");
        assert!(text.contains("device=\"d2\""), "{text}");
        assert_eq!(
            registry.forget("d1", ForgetReason::Admin),
            Err(ForgetError::Unknown("d1".into()))
        );
    }

    /// Local devices offline for the configured time are forgotten; online ones, those
    /// offline for less, and other lines' devices are not.
    #[test]
    fn offline_devices_expire() {
        let metrics = Arc::new(Metrics::new());
        let (registry, _published) = registry(&metrics);
        for (i, id) in ["gone", "online", "back"].into_iter().enumerate() {
            registry
                .declare(id, i as u64 + 1, interface(), "a")
                .unwrap();
        }
        assert_eq!(
            registry.remote_record("b", remote("r1", "b", Status::Offline)),
            Ok(())
        );
        assert!(registry.disconnected("gone", 1, "keep-alive"));
        assert!(registry.disconnected("back", 3, "keep-alive"));
        assert!(registry.connected("back", 4).is_some());
        let after = Duration::from_secs(5);
        registry.expire(SystemTime::now() + Duration::from_secs(1), after);
        assert!(registry.get("gone").is_some(), "offline for less");
        registry.expire(SystemTime::now() + Duration::from_secs(6), after);
        assert!(registry.get("gone").is_none());
        for id in ["online", "back", "r1"] {
            assert!(registry.get(id).is_some(), "{id}");
        }
        let expired = metrics
            .registry_forgotten
            .with_label_values(&["expired"])
            .get();
        assert_eq!(expired, 1);
    }
}

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
//! **Other lines' devices.** With a `[bridge]`, the registry also holds the devices of the
//! other lines on the bus (their `line` says where they live), learned from the bus
//! (`bridge`): online and offline as their own line says, and **unreachable** while their
//! line cannot be reached — a fact about the link, not the device, so it never overwrites
//! the device's own last will reason. Remote records are never persisted: they are
//! learned again from the bus after a restart. Local changes are handed to the bridge
//! through [`Registry::observe`].

use std::collections::{BTreeMap, HashMap};
use std::path::{Path, PathBuf};
use std::sync::{Arc, Mutex, PoisonError};
use std::time::{Duration, Instant, SystemTime};

use fb_bridge::topic;
use fb_bridge::Interface;
use serde::{Deserialize, Serialize};
use tokio::sync::Notify;

use crate::broker_publisher::{BrokerPublisher, Message};
use crate::metrics::Metrics;
use crate::silence::{Activity, Bound, Periods, Verdict};

/// The longest a change waits before it is on disk.
pub const PERSIST_INTERVAL: Duration = Duration::from_millis(200);

/// How often local devices are judged for silence: a silent device is shown within its
/// bound plus this.
pub const SILENCE_CHECK: Duration = Duration::from_secs(1);

/// How often the observed output periods are written, when nothing else changes: a
/// crash loses at most this much of what was learned.
const PERIODS_PERSIST: u32 = 60;

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
}

/// The records, with their counts kept up to date by every change: announcing the
/// counts after a change is O(1), not a walk over every device (a walk per birth made a
/// line's births quadratic: 10,000 declarations at once took seconds).
struct Devices {
    records: HashMap<String, Record>,
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
    /// Local records changed since the journal's last append (`Registry::append`);
    /// None when the registry is not persisted (nothing would empty it).
    changed: Option<std::collections::HashSet<String>>,
}

/// Devices by status (every line), and this line's online devices.
#[derive(Debug, Default, Clone, Copy, PartialEq, Eq)]
struct Counts {
    by_status: [i64; 3],
    online_here: i64,
    /// Online and silent, every line.
    silent: i64,
}

impl Counts {
    /// Adds (`sign` 1) or removes (-1) one record.
    fn tally(&mut self, record: &Record, line: &str, sign: i64) {
        self.by_status[record.status as usize] += sign;
        if record.status == Status::Online && record.line == line {
            self.online_here += sign;
        }
        if record.status == Status::Online && record.silent {
            self.silent += sign;
        }
    }
}

impl Devices {
    fn new(line: &str, records: HashMap<String, Record>) -> Devices {
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
        if let Some(old) = self.records.insert(record.id.clone(), record) {
            self.counts.tally(&old, &self.line, -1);
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
        Some(record)
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
    type Target = HashMap<String, Record>;

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
    file: Option<PathBuf>,
    dirty: Notify,
    /// The journal, held while the files are written: the writer task's append (on a
    /// blocking thread, which aborting the task does not stop) and the last write at
    /// shutdown never overlap.
    journal: Mutex<Journal>,
    /// Receives every change of a local device's record (the bridge announces them).
    observer: std::sync::OnceLock<tokio::sync::mpsc::UnboundedSender<Record>>,
}

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
        tasks: &crate::supervisor::Tasks,
    ) -> Result<Arc<Registry>, LoadError> {
        let mut devices = HashMap::new();
        let mut remembered = HashMap::new();
        let mut journal = Journal::default();
        if let Some(path) = file {
            let (records, periods, opened) = load(path)?;
            journal = opened;
            remembered.extend(periods);
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
        let registry = Arc::new(Registry {
            line: line.to_owned(),
            devices: Mutex::new(Devices {
                remembered,
                changed: file.map(|_| Default::default()),
                ..Devices::new(line, devices)
            }),
            publisher,
            metrics,
            bound,
            file: file.map(Path::to_owned),
            dirty: Notify::new(),
            journal: Mutex::new(journal),
            observer: std::sync::OnceLock::new(),
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

    /// A device declared its interface on its connection `session`: it is online with it.
    pub fn declare(&self, id: &str, session: u64, interface: Interface) -> Arc<Interface> {
        let interface = Arc::new(interface);
        let mut devices = self.devices.lock().unwrap_or_else(PoisonError::into_inner);
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
        interface
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
        let mut all: Vec<Record> = self
            .devices
            .lock()
            .unwrap_or_else(PoisonError::into_inner)
            .values()
            .cloned()
            .collect();
        all.sort_by(|a, b| a.id.cmp(&b.id));
        all
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

    /// `line` cannot be reached: every device of it is unreachable.
    pub fn line_unreachable(&self, line: &str) {
        if line == self.line {
            return;
        }
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
        let payload = serde_json::to_vec(record).expect("a record serializes");
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

    /// Starts judging the local devices' silence every [`SILENCE_CHECK`], unless the
    /// judgement is off (`silence_factor = 0`).
    pub fn start_silence_check(self: &Arc<Self>, tasks: &crate::supervisor::Tasks) {
        if self.bound.enabled() {
            tasks.core("registry silence check", Arc::clone(self).silence_loop());
        }
    }

    async fn silence_loop(self: Arc<Self>) {
        let mut tick = tokio::time::interval(SILENCE_CHECK);
        tick.set_missed_tick_behavior(tokio::time::MissedTickBehavior::Delay);
        for n in 1u32.. {
            tick.tick().await;
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
            if since.is_some() != record.silent {
                turned.push((id.clone(), since));
            }
        }
        if turned.is_empty() {
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
        let periods = {
            let held = self.devices.lock().unwrap_or_else(PoisonError::into_inner);
            devices
                .iter()
                .map(|r| (r.id.clone(), held.periods(&r.id)))
                .filter(|(_, p)| !p.is_empty())
                .collect()
        };
        let snapshot = File {
            version: 1,
            seq: journal.seq,
            devices,
            periods,
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
        let file = match &mut self.file {
            Some(file) => file,
            None => self.file.insert(
                std::fs::OpenOptions::new()
                    .create(true)
                    .append(true)
                    .open(journal_path(path))?,
            ),
        };
        file.write_all(bytes)?;
        file.sync_data()?;
        self.bytes += bytes.len() as u64;
        Ok(())
    }

    fn truncate(&mut self, path: &Path) -> std::io::Result<()> {
        let file = match &mut self.file {
            Some(file) => file,
            None => self.file.insert(
                std::fs::OpenOptions::new()
                    .create(true)
                    .append(true)
                    .open(journal_path(path))?,
            ),
        };
        file.set_len(0)?;
        file.sync_all()?;
        self.bytes = 0;
        Ok(())
    }
}

type Loaded = (Vec<Record>, BTreeMap<String, Periods>, Journal);

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
                record, periods: p, ..
            } => {
                match p.is_empty() {
                    true => periods.remove(&record.id),
                    false => periods.insert(record.id.clone(), p),
                };
                records.insert(record.id.clone(), record);
            }
            Entry::Removed { id, .. } => {
                periods.remove(&id);
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
    Ok((records.into_values().collect(), periods, journal))
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
        };
        std::fs::write(&path, serde_json::to_vec(&snapshot).unwrap()).unwrap();
        let mut journal = Vec::new();
        for (seq, session) in [(4, 40), (6, 60)] {
            let entry = Entry::Device {
                seq,
                record: at(session),
                periods: Periods::new(),
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
        let (records, _, state) = load(&path).unwrap();
        assert_eq!(records.len(), 1);
        assert_eq!(records[0].session, 60);
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
        let registry = Registry::open("a", None, publisher, Arc::clone(metrics), bound, &tasks);
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
            let bound = crate::config::FbSection::default().silence_bound();
            let tasks = crate::supervisor::Tasks::new(&health);
            let metrics = Arc::new(Metrics::new());
            Registry::open("a", Some(&path), publisher, metrics, bound, &tasks).unwrap()
        };
        let speed: Interface = serde_json::from_value(serde_json::json!({"fbs": {"CONV": {
            "data_out": {"SPEED": "REAL"},
        }}}))
        .unwrap();
        let first = open();
        first.declare("d1", 1, speed);
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
        registry.declare("d1", 1, speed);
        registry.declare("quiet", 2, interface());
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
            crate::config::FbSection::default().silence_bound(),
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
            registry.declare(id, i as u64 + 1, interface());
        }
        check("declared");
        assert!(registry.disconnected("d1", 1, "clean disconnect"));
        check("d1 offline");
        assert!(registry.connected("d1", 4).is_some());
        check("d1 back");
        assert!(!registry.disconnected("d1", 1, "stale"));
        check("stale end ignored");
        registry.session_started("d2", 5);
        registry.declare("d2", 5, interface());
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
}

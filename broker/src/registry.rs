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
//! **Persisted, never half-written.** Changes mark the registry dirty; a task writes the
//! whole registry at most every [`PERSIST_INTERVAL`] to a temporary file, syncs it and
//! renames it over the old one, so a crash leaves either the old or the new file. After a
//! restart every device is offline (reason `broker restart`) until it reconnects.
//!
//! **Other lines' devices.** With a `[bridge]`, the registry also holds the devices of the
//! other lines on the bus (their `line` says where they live), learned from the bus
//! (`bridge`): online and offline as their own line says, and **unreachable** while their
//! line cannot be reached — a fact about the link, not the device, so it never overwrites
//! the device's own last will reason. Remote records are never persisted: they are
//! learned again from the bus after a restart. Local changes are handed to the bridge
//! through [`Registry::observe`].

use std::collections::HashMap;
use std::path::{Path, PathBuf};
use std::sync::{Arc, Mutex, PoisonError};
use std::time::{Duration, SystemTime};

use fb_bridge::topic;
use fb_bridge::Interface;
use serde::{Deserialize, Serialize};
use tokio::sync::Notify;

use crate::broker_publisher::{BrokerPublisher, Message};
use crate::metrics::Metrics;

/// The longest a change waits before it is on disk.
pub const PERSIST_INTERVAL: Duration = Duration::from_millis(200);

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
    pub interface: Arc<Interface>,
}

#[derive(Serialize, Deserialize)]
struct File {
    version: u32,
    devices: Vec<Record>,
}

/// The records, with their counts kept up to date by every change: announcing the
/// counts after a change is O(1), not a walk over every device (a walk per birth made a
/// line's births quadratic: 10,000 declarations at once took seconds).
struct Devices {
    records: HashMap<String, Record>,
    /// This line's name (`Counts::online_here`).
    line: String,
    counts: Counts,
}

/// Devices by status (every line), and this line's online devices.
#[derive(Debug, Default, Clone, Copy, PartialEq, Eq)]
struct Counts {
    by_status: [i64; 3],
    online_here: i64,
}

impl Counts {
    /// Adds (`sign` 1) or removes (-1) one record.
    fn tally(&mut self, record: &Record, line: &str, sign: i64) {
        self.by_status[record.status as usize] += sign;
        if record.status == Status::Online && record.line == line {
            self.online_here += sign;
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
        }
    }

    fn insert(&mut self, record: Record) {
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
        Some(record)
    }

    /// Changes every record `which` selects with `change`.
    fn update_all(&mut self, which: impl Fn(&Record) -> bool, mut change: impl FnMut(&mut Record)) {
        for record in self.records.values_mut().filter(|r| which(r)) {
            self.counts.tally(record, &self.line, -1);
            change(record);
            self.counts.tally(record, &self.line, 1);
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
    file: Option<PathBuf>,
    dirty: Notify,
    /// Held while the file is written: the writer task's write (on a blocking thread,
    /// which aborting the task does not stop) and the last write at shutdown never overlap
    /// on the temporary file.
    writing: Mutex<()>,
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
        tasks: &crate::supervisor::Tasks,
    ) -> Result<Arc<Registry>, LoadError> {
        let mut devices = HashMap::new();
        if let Some(path) = file {
            for mut record in load(path)? {
                if record.status == Status::Online {
                    record.status = Status::Offline;
                    record.last_will_reason = Some("broker restart".into());
                    record.since = now();
                }
                devices.insert(record.id.clone(), record);
            }
        }
        let registry = Arc::new(Registry {
            line: line.to_owned(),
            devices: Mutex::new(Devices::new(line, devices)),
            publisher,
            metrics,
            file: file.map(Path::to_owned),
            dirty: Notify::new(),
            writing: Mutex::new(()),
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
            interface: Arc::clone(&interface),
        };
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
            },
        )?;
        let interface = Arc::clone(&record.interface);
        self.announce(record);
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
        if record.line != from || from == self.line {
            return Err(RecordRefused::ForgedLine);
        }
        let mut devices = self.devices.lock().unwrap_or_else(PoisonError::into_inner);
        match devices.get(&record.id) {
            Some(held) if held.line == self.line => return Err(RecordRefused::LocalDevice),
            Some(held) if held.line != record.line && held.status == Status::Online => {
                return Err(RecordRefused::HeldByAnotherLine)
            }
            Some(held) if *held == record => return Ok(()),
            _ => {}
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

    /// Writes the registry now (at shutdown).
    pub fn flush(&self) {
        if let Some(path) = &self.file {
            if let Err(e) = self.write(path) {
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
        } = devices.counts;
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

    async fn persist_loop(self: Arc<Self>) {
        let path = self.file.clone().expect("persisting needs a file");
        loop {
            self.dirty.notified().await;
            let this = Arc::clone(&self);
            let p = path.clone();
            let result = tokio::task::spawn_blocking(move || this.write(&p)).await;
            if let Ok(Err(e)) = result {
                tracing::error!(path = %path.display(), error = %e, "cannot persist the device registry; retrying on the next change");
            }
            tokio::time::sleep(PERSIST_INTERVAL).await;
        }
    }

    /// Writes a snapshot atomically: temporary file, fsync, rename, fsync of the directory.
    fn write(&self, path: &Path) -> std::io::Result<()> {
        let _one_writer = self.writing.lock().unwrap_or_else(PoisonError::into_inner);
        let snapshot = File {
            version: 1,
            devices: self.local(),
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
        Ok(())
    }
}

fn load(path: &Path) -> Result<Vec<Record>, LoadError> {
    let error = |message: String| LoadError {
        path: path.display().to_string(),
        message,
    };
    let text = match std::fs::read(path) {
        Ok(t) => t,
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => return Ok(Vec::new()),
        Err(e) => return Err(error(e.to_string())),
    };
    let file: File = serde_json::from_slice(&text)
        .map_err(|e| error(format!("{e}; move it away to start with an empty registry")))?;
    if file.version != 1 {
        return Err(error(format!("version {} is not supported", file.version)));
    }
    Ok(file.devices)
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

    fn remote(id: &str, line: &str, status: Status) -> Record {
        Record {
            id: id.into(),
            line: line.into(),
            status,
            session: 1,
            since: now(),
            last_will_reason: None,
            interface: Arc::new(interface()),
        }
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
        registry.line_unreachable("b");
        check("line b unreachable");
        assert!(registry.disconnected("d3", 3, "keep-alive"));
        check("d3 offline");
    }
}

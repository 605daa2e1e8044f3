//! The device registry: every device of the line, its interface and whether it is online.
//!
//! A device enters the registry when it declares its FB interface (`fbbus/declare/<id>`).
//! From then on the registry follows its connections: online while a connection with its
//! client id is open, offline when that connection ends — with the reason its will fired
//! for (abrupt close, keep-alive expiry, takeover) or `clean disconnect`.
//!
//! **Session numbers decide, not arrival order.** Every connection has a session number
//! (see `session_table`), the Sparkplug `bdSeq` idea: an end is applied only if it belongs
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
use std::sync::{Arc, Mutex};
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

pub struct Registry {
    line: String,
    devices: Mutex<HashMap<String, Record>>,
    publisher: Arc<BrokerPublisher>,
    metrics: Arc<Metrics>,
    file: Option<PathBuf>,
    dirty: Notify,
    /// Receives every change of a local device's record (the bridge announces them).
    observer: std::sync::OnceLock<tokio::sync::mpsc::UnboundedSender<Record>>,
}

#[derive(Debug, thiserror::Error)]
#[error("registry file {path}: {message}")]
pub struct LoadError {
    pub path: String,
    pub message: String,
}

impl Registry {
    /// Loads the registry from `file` (if it exists) with every device offline, publishes
    /// the records, and starts persisting changes to `file`.
    pub fn open(
        line: &str,
        file: Option<&Path>,
        publisher: Arc<BrokerPublisher>,
        metrics: Arc<Metrics>,
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
            devices: Mutex::new(devices),
            publisher,
            metrics,
            file: file.map(Path::to_owned),
            dirty: Notify::new(),
            observer: std::sync::OnceLock::new(),
        });
        {
            let devices = registry.devices.lock().expect("lock poisoned");
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
            tokio::spawn(Arc::clone(&registry).persist_loop());
        }
        Ok(registry)
    }

    pub fn line(&self) -> &str {
        &self.line
    }

    /// Each known device's latest session number, to seed the session table.
    pub fn sessions(&self) -> Vec<(String, u64)> {
        let devices = self.devices.lock().expect("lock poisoned");
        devices
            .values()
            .map(|r| (r.id.clone(), r.session))
            .collect()
    }

    /// A device declared its interface on its connection `session`: it is online with it.
    pub fn declare(&self, id: &str, session: u64, interface: Interface) -> Arc<Interface> {
        let interface = Arc::new(interface);
        let mut devices = self.devices.lock().expect("lock poisoned");
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
        devices.insert(id.to_owned(), record);
        self.announce_count(&devices);
        self.dirty.notify_one();
        interface
    }

    /// A connection of `id` took session number `session` and is about to end any older
    /// connection of that id (takeover). Recording the number first is what makes the old
    /// connection's end stale, whichever of the two finishes first.
    pub fn session_started(&self, id: &str, session: u64) {
        let mut devices = self.devices.lock().expect("lock poisoned");
        if let Some(record) = devices.get_mut(id) {
            record.session = record.session.max(session);
        }
    }

    /// A client connected with session `session`. A known device is online again (with
    /// its declared interface, returned) until it declares a new one.
    pub fn connected(&self, id: &str, session: u64) -> Option<Arc<Interface>> {
        let mut devices = self.devices.lock().expect("lock poisoned");
        let record = devices.get_mut(id)?;
        if session < record.session {
            return None;
        }
        record.status = Status::Online;
        record.session = session;
        record.since = now();
        record.last_will_reason = None;
        let interface = Arc::clone(&record.interface);
        self.announce(record);
        self.announce_count(&devices);
        self.dirty.notify_one();
        Some(interface)
    }

    /// The connection `session` of `id` ended for `reason`. Applied only if it is the
    /// device's current session; returns whether it was.
    pub fn disconnected(&self, id: &str, session: u64, reason: &str) -> bool {
        let mut devices = self.devices.lock().expect("lock poisoned");
        let Some(record) = devices.get_mut(id) else {
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
        record.status = Status::Offline;
        record.since = now();
        record.last_will_reason = Some(reason.to_owned());
        self.announce(record);
        self.announce_count(&devices);
        self.dirty.notify_one();
        true
    }

    pub fn get(&self, id: &str) -> Option<Record> {
        self.devices.lock().expect("lock poisoned").get(id).cloned()
    }

    /// The declared interface of `id` if it is a device of `line` (the bridge's typed
    /// check of messages from that line: no record is cloned).
    pub fn remote_interface(&self, id: &str, line: &str) -> Option<Arc<Interface>> {
        let devices = self.devices.lock().expect("lock poisoned");
        devices
            .get(id)
            .filter(|r| r.line == line)
            .map(|r| Arc::clone(&r.interface))
    }

    /// Every device, by id.
    pub fn list(&self) -> Vec<Record> {
        let mut all: Vec<Record> = self
            .devices
            .lock()
            .expect("lock poisoned")
            .values()
            .cloned()
            .collect();
        all.sort_by(|a, b| a.id.cmp(&b.id));
        all
    }

    /// Every change of a local device's record from now on is sent to `observer`.
    /// Returns the local records as they are now.
    pub fn observe(&self, observer: tokio::sync::mpsc::UnboundedSender<Record>) -> Vec<Record> {
        let devices = self.devices.lock().expect("lock poisoned");
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

    /// Another line says this is its device's record. A device id is unique on the bus:
    /// a local device of the same id wins.
    pub fn remote_record(&self, record: Record) {
        if record.line == self.line {
            return;
        }
        let mut devices = self.devices.lock().expect("lock poisoned");
        if devices.get(&record.id).is_some_and(|r| r.line == self.line) {
            tracing::warn!(
                device = record.id,
                line = record.line,
                "a device of this id lives on this line; the other line's record is ignored"
            );
            return;
        }
        if devices.get(&record.id) == Some(&record) {
            return;
        }
        self.announce(&record);
        devices.insert(record.id.clone(), record);
        self.announce_count(&devices);
    }

    /// A remote device's status changed as seen from here (`Unreachable`, or back `Online`
    /// when its liveliness token reappears).
    pub fn remote_status(&self, line: &str, id: &str, status: Status) {
        let mut devices = self.devices.lock().expect("lock poisoned");
        let Some(record) = devices.get_mut(id).filter(|r| r.line == line) else {
            return;
        };
        if record.status == status {
            return;
        }
        record.status = status;
        record.since = now();
        let record = record.clone();
        self.announce(&record);
        self.announce_count(&devices);
    }

    /// `line` cannot be reached: every device of it is unreachable.
    pub fn line_unreachable(&self, line: &str) {
        if line == self.line {
            return;
        }
        let mut devices = self.devices.lock().expect("lock poisoned");
        let mut changed = Vec::new();
        for record in devices.values_mut().filter(|r| r.line == line) {
            if record.status != Status::Unreachable {
                record.status = Status::Unreachable;
                record.since = now();
                changed.push(record.clone());
            }
        }
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

    fn announce_count(&self, devices: &HashMap<String, Record>) {
        let mut counts = [0i64; 3];
        let mut online_here = 0;
        for r in devices.values() {
            counts[r.status as usize] += 1;
            if r.line == self.line && r.status == Status::Online {
                online_here += 1;
            }
        }
        for (status, count) in [Status::Online, Status::Offline, Status::Unreachable]
            .into_iter()
            .zip(counts)
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

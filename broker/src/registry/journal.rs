//! Persisted incrementally, never half-written: the snapshot (`registry.json`), the
//! journal of changed records beside it (`registry.json.log`), compaction, and loading
//! both back with a torn last line cut off.

use std::collections::{BTreeMap, HashMap};
use std::path::{Path, PathBuf};
use std::sync::{Arc, PoisonError};
use std::time::{Duration, Instant, SystemTime};

use serde::{Deserialize, Serialize};

use super::records::Record;
use super::status::{PERIODS_PERSIST, SILENCE_CHECK};
use super::Registry;
use crate::silence::Periods;

/// The longest a change waits before it is on disk.
pub const PERSIST_INTERVAL: Duration = Duration::from_millis(200);

#[derive(Serialize, Deserialize)]
pub(super) struct File {
    pub(super) version: u32,
    /// The journal's last sequence number when this snapshot was written: the journal
    /// lines up to it are in the snapshot already (0: none).
    #[serde(default)]
    pub(super) seq: u64,
    pub(super) devices: Vec<Record>,
    /// The observed output periods of the local devices, by device (`silence`): a
    /// device whose publishers died at a restart is still judged.
    #[serde(default, skip_serializing_if = "BTreeMap::is_empty")]
    pub(super) periods: BTreeMap<String, Periods>,
    /// Who registered each local device (`[fb] max_devices_per_identity`), by device.
    #[serde(default, skip_serializing_if = "BTreeMap::is_empty")]
    pub(super) registrants: BTreeMap<String, String>,
}

#[derive(Debug, thiserror::Error)]
#[error("registry file {path}: {message}")]
pub struct LoadError {
    pub path: String,
    pub message: String,
}

/// What a registry file holds, with its journal replayed: the records, the observed
/// periods, the registrants, and the journal as the writer goes on with it.
pub(super) type Loaded = (
    Vec<Record>,
    BTreeMap<String, Periods>,
    BTreeMap<String, String>,
    Journal,
);

/// One line of the registry's journal: a local device's record as it is now, or its
/// removal.
#[derive(Debug, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub(super) enum Entry {
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
    pub(super) fn id(&self) -> &str {
        match self {
            Entry::Device { record, .. } => &record.id,
            Entry::Removed { id, .. } => id,
        }
    }

    pub(super) fn seq(&self) -> u64 {
        match self {
            Entry::Device { seq, .. } | Entry::Removed { seq, .. } => *seq,
        }
    }
}

/// The journal beside the snapshot (`<registry file>.log`), as the writer keeps it.
#[derive(Default)]
pub(super) struct Journal {
    /// Open for appending, once the first line is written.
    pub(super) file: Option<std::fs::File>,
    pub(super) bytes: u64,
    pub(super) snapshot_bytes: u64,
    /// The last sequence number written (a batch of lines shares one).
    pub(super) seq: u64,
    /// The periods last written per device, so unchanged ones are not written again.
    pub(super) periods: HashMap<String, Periods>,
    /// When the periods were last compared with what was written.
    pub(super) periods_at: Option<Instant>,
}

/// The journal is compacted once it is larger than this many times the snapshot (so a
/// compaction's rewrite costs at most a quarter of what was appended since the last)...
pub(super) const COMPACT_RATIO: u64 = 4;

/// ... and at least this (small registries are not rewritten for every few changes) ...
pub(super) const COMPACT_FLOOR: u64 = 64 * 1024;

/// ... or once it is larger than this, whatever the snapshot (bounds replay at start).
pub(super) const COMPACT_CEILING: u64 = 8 * 1024 * 1024;

pub(super) fn journal_path(path: &Path) -> PathBuf {
    let mut name = path.as_os_str().to_owned();
    name.push(".log");
    PathBuf::from(name)
}

impl Journal {
    pub(super) fn needs_compaction(&self) -> bool {
        self.bytes > COMPACT_CEILING
            || self.bytes > (COMPACT_RATIO * self.snapshot_bytes).max(COMPACT_FLOOR)
    }

    /// Appends `bytes` (whole lines) and syncs them.
    pub(super) fn write(&mut self, path: &Path, bytes: &[u8]) -> std::io::Result<()> {
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
    pub(super) fn open(&mut self, path: &Path) -> std::io::Result<&mut std::fs::File> {
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

    pub(super) fn truncate(&mut self, path: &Path) -> std::io::Result<()> {
        let file = self.open(path)?;
        file.set_len(0)?;
        file.sync_all()?;
        self.bytes = 0;
        Ok(())
    }
}

/// The snapshot, then the journal's lines newer than it.
pub(super) fn load(path: &Path) -> Result<Loaded, LoadError> {
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

impl Registry {
    /// Writes the whole registry now and empties the journal (at shutdown).
    pub fn flush(&self) {
        if let Some(path) = &self.file {
            if let Err(e) = self.append(path, true) {
                tracing::error!(path = %path.display(), error = %e, "cannot persist the device registry");
            }
        }
    }

    pub(super) async fn persist_loop(self: Arc<Self>) {
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
    pub(super) fn append(&self, path: &Path, compact: bool) -> std::io::Result<()> {
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
    pub(super) fn write(&self, path: &Path, journal: &mut Journal) -> std::io::Result<()> {
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

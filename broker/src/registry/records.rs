//! A device's record and status, and the records of the line with their counts kept up
//! to date by every change (the only writers are `Devices::insert` and `update*`).

use std::collections::{BTreeMap, HashMap};
use std::sync::Arc;
use std::time::{Instant, SystemTime};

use fb_bridge::Interface;
use serde::{Deserialize, Serialize};

use crate::silence::{Activity, Periods};

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

/// The records, with their counts kept up to date by every change: announcing the
/// counts after a change is O(1), not a walk over every device (a walk per birth made a
/// line's births quadratic: 10,000 declarations at once took seconds).
pub(super) struct Devices {
    /// In id order: a page of the admin listing is a range walk, O(page), not a scan of
    /// every device under the lock (issue 21: 50,000 devices, polled).
    pub(super) records: BTreeMap<String, Record>,
    /// This line's name (`Counts::online_here`).
    pub(super) line: String,
    pub(super) counts: Counts,
    /// The output activity of the local devices declared or connected since start-up.
    pub(super) activity: HashMap<String, Arc<Activity>>,
    /// Periods read from the registry file, for devices not connected since.
    pub(super) remembered: HashMap<String, Periods>,
    /// Live records taken from other lines, counted; and for each remote device the
    /// count when its last live record came. A query's answer was made before the live
    /// records that came after it was sent, so it must not replace them
    /// (`Registry::queried_record`). One entry per remote record: the records' bound.
    #[cfg_attr(not(feature = "bridge"), allow(dead_code))]
    pub(super) live_taken: u64,
    pub(super) live: HashMap<String, u64>,
    /// When each offline local device went offline (`[fb] forget_offline_after_s`): the
    /// wall clock, as the record's `since` shows it.
    pub(super) offline_since: HashMap<String, SystemTime>,
    /// Who registered each local device, and how many devices each registrant holds.
    pub(super) registrants: HashMap<String, Arc<str>>,
    pub(super) registered: HashMap<Arc<str>, usize>,
    /// The refusals at each limit since its last log line (logged at most once a minute).
    pub(super) refusals_unlogged: HashMap<&'static str, (Option<Instant>, u64)>,
    /// Local records changed since the journal's last append (`Registry::append`);
    /// None when the registry is not persisted (nothing would empty it).
    pub(super) changed: Option<std::collections::HashSet<String>>,
}

/// Devices by status (every line), and this line's online devices.
#[derive(Debug, Default, Clone, PartialEq, Eq)]
pub(super) struct Counts {
    pub(super) by_status: [i64; 3],
    /// This line's devices (`[fb] max_devices`).
    pub(super) local: i64,
    pub(super) online_here: i64,
    /// Online and silent, every line.
    pub(super) silent: i64,
    /// Other lines' devices, by line (`Limits::max_remote_per_line`), and in all.
    pub(super) remote_by_line: HashMap<String, i64>,
    pub(super) remote: i64,
}

impl Counts {
    /// Adds (`sign` 1) or removes (-1) one record.
    pub(super) fn tally(&mut self, record: &Record, line: &str, sign: i64) {
        self.by_status[record.status as usize] += sign;
        if record.line == line {
            self.local += sign;
        } else {
            self.remote += sign;
            let held = self.remote_by_line.entry(record.line.clone()).or_default();
            *held += sign;
            if *held <= 0 {
                self.remote_by_line.remove(&record.line);
            }
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
    pub(super) fn new(line: &str, records: BTreeMap<String, Record>) -> Devices {
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
    pub(super) fn mark(
        changed: &mut Option<std::collections::HashSet<String>>,
        line: &str,
        record: &Record,
    ) {
        if let Some(changed) = changed.as_mut().filter(|_| record.line == line) {
            if !changed.contains(&record.id) {
                changed.insert(record.id.clone());
            }
        }
    }

    pub(super) fn insert(&mut self, record: Record) {
        Self::mark(&mut self.changed, &self.line, &record);
        self.counts.tally(&record, &self.line, 1);
        let id = record.id.clone();
        if let Some(old) = self.records.insert(record.id.clone(), record) {
            self.counts.tally(&old, &self.line, -1);
        }
        self.note_offline(&id);
    }

    /// Removes every trace of `id`: its record, timing, registrant and offline time.
    pub(super) fn remove(&mut self, id: &str) -> Option<Record> {
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
    pub(super) fn register(&mut self, id: &str, registrant: &str) {
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
    pub(super) fn note_offline(&mut self, id: &str) {
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
    pub(super) fn update(
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
    pub(super) fn periods(&self, id: &str) -> Periods {
        match self.activity.get(id) {
            Some(activity) => activity.periods(),
            None => self.remembered.get(id).cloned().unwrap_or_default(),
        }
    }

    /// Changes every record `which` selects with `change`.
    #[cfg_attr(not(feature = "bridge"), allow(dead_code))]
    pub(super) fn update_all(
        &mut self,
        which: impl Fn(&Record) -> bool,
        mut change: impl FnMut(&mut Record),
    ) {
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

//! Other lines' devices, learned from the bus (`bridge`): their records as their own line
//! says, never persisted, and whether their line can be reached, a fact about the link
//! that never overwrites a device's own last will reason.
//!
//! Only the bus bridge feeds it: a broker built without the `bridge` feature never calls
//! most of it.
#![cfg_attr(not(feature = "bridge"), allow(dead_code))]

use std::collections::BTreeMap;
use std::sync::{Arc, PoisonError};

use fb_bridge::Interface;
use serde::Serialize;

use super::records::{Record, Status};
use super::{now, Registry};

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

/// Why a registry record from another line was not taken.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum RecordRefused {
    /// The record names another line than the one that sent it.
    ForgedLine,
    /// It is a device of this line.
    LocalDevice,
    /// The device is online on a third line.
    HeldByAnotherLine,
    /// A new device of a line that has `[fb] max_remote_devices_per_line` here already.
    LineShare,
    /// A new device of another line while `[fb] max_remote_devices` are held.
    RemoteFull,
}

impl RecordRefused {
    /// The metric label.
    pub fn as_str(self) -> &'static str {
        match self {
            RecordRefused::ForgedLine => "forged_record",
            RecordRefused::LocalDevice => "local_device",
            RecordRefused::HeldByAnotherLine => "claimed_device",
            RecordRefused::LineShare => "line_share",
            RecordRefused::RemoteFull => "remote_full",
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

    /// Line `from` says this is its device's record (`from` is the line whose key it came
    /// on: on a mutual-TLS bus, the line zenoh authenticated). A device id is unique on
    /// the bus: a line speaks only for its own devices, a local device of the same id
    /// wins, and a device online on another line is not taken over (a device that moved
    /// is taken once its old line has it offline or unreachable).
    pub fn remote_record(&self, from: &str, record: Record) -> Result<(), RecordRefused> {
        self.take_remote(from, record, None)
    }

    /// Line `from` forgot its device `id` (by hand or by age): forgotten here too, with
    /// its record and the retained values this line holds of it, if it is `from`'s
    /// device here. False if it is not (unknown, local, another line's).
    pub fn remote_forgotten(&self, from: &str, id: &str) -> bool {
        let mut devices = self.devices.lock().unwrap_or_else(PoisonError::into_inner);
        if devices
            .get(id)
            .is_none_or(|r| r.line != from || from == self.line)
        {
            return false;
        }
        let removed = self.remove(&mut devices, id, super::ForgetReason::Bus);
        self.announce_count(&devices);
        removed.is_some()
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

    pub(super) fn take_remote(
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
            // Already this line's: a change, never refused for a share.
            Some(held) if held.line == record.line => {}
            // New to this line here: within its share and the whole.
            _ => {
                let counts = &devices.counts;
                let of_line = counts.remote_by_line.get(from).copied().unwrap_or(0);
                let at = |held: i64, max: usize| usize::try_from(held).is_ok_and(|n| n >= max);
                let refused = if at(of_line, self.limits.max_remote_per_line) {
                    Some(RecordRefused::LineShare)
                } else if at(counts.remote, self.limits.max_remote) {
                    Some(RecordRefused::RemoteFull)
                } else {
                    None
                };
                if let Some(refused) = refused {
                    let (limit, value) = match refused {
                        RecordRefused::LineShare => {
                            ("remote_devices_per_line", self.limits.max_remote_per_line)
                        }
                        _ => ("remote_devices", self.limits.max_remote),
                    };
                    self.refused_at_limit(&mut devices, limit, |since| {
                        tracing::warn!(
                            line = from,
                            device = record.id,
                            limit,
                            refused_since_last_line = since,
                            "a new device of another line not taken from the bus: [fb] \
                             max_{limit} = {value} reached; its line's other devices are kept \
                             (logged at most once a minute; fbbus_limit_refusals_total)"
                        )
                    });
                    return Err(refused);
                }
            }
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

    pub(super) fn note_line(&self, line: &str, reachable: bool) {
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
}

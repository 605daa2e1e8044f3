//! A local device's life: online while its current session lasts (session numbers decide,
//! not arrival order), offline with the reason its connection ended, silent while its
//! periodic outputs are quiet, judged every [`SILENCE_CHECK`]; and the periodic task that
//! judges silence and expires devices.

use std::sync::{Arc, PoisonError};
use std::time::{Duration, Instant, SystemTime};

use fb_bridge::Interface;

use super::records::{Devices, Status};
use super::{now, Registry};
use crate::silence::{Activity, Verdict};

/// How often local devices are judged for silence: a silent device is shown within its
/// bound plus this.
pub const SILENCE_CHECK: Duration = Duration::from_secs(1);

/// How often the observed output periods are written, when nothing else changes: a
/// crash loses at most this much of what was learned.
pub(super) const PERIODS_PERSIST: u32 = 60;

impl Registry {
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

    /// Starts the registry's periodic checks, every [`SILENCE_CHECK`]: the local
    /// devices' silence, unless the judgement is off (`silence_factor = 0`), and the
    /// expiry of offline devices, if `[fb] forget_offline_after_s` is set.
    pub fn start_periodic_checks(self: &Arc<Self>, tasks: &crate::supervisor::Tasks) {
        if self.bound.enabled() || self.limits.forget_offline_after.is_some() {
            tasks.core("registry checks", Arc::clone(self).check_loop());
        }
    }

    pub(super) async fn check_loop(self: Arc<Self>) {
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
    pub(super) fn judge_silence(&self, now: Instant) {
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
        let any_ended = !ended.is_empty();
        for (id, quiet) in ended {
            self.end_for_silence(&mut devices, &id, quiet);
        }
        if turned.is_empty() {
            if any_ended {
                self.announce_count(&devices);
            }
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
    pub(super) fn end_for_silence(&self, devices: &mut Devices, id: &str, quiet: Duration) {
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
}

//! How much the registry holds, and how devices leave it: the admission of a new device
//! within `[fb] max_devices` and `max_devices_per_identity`, forgetting by hand, and
//! expiry after `[fb] forget_offline_after_s`.

use std::sync::PoisonError;
use std::time::{Duration, Instant, SystemTime};

use fb_bridge::topic;

use super::feed::Change;
use super::records::{Devices, Record, Status};
use super::{retained_clears, Registry};
use crate::broker_publisher::Message;

/// The longest silence between two log lines about refusals at one registry limit.
pub(super) const LIMIT_LOG_INTERVAL: Duration = Duration::from_secs(60);

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
    /// Devices of one other line taken from the bus, at most (issue 33: a line's share):
    /// a line that announces more gets the rest refused, and no other line loses its
    /// place.
    pub max_remote_per_line: usize,
    /// Devices of all other lines together, at most.
    pub max_remote: usize,
}

impl Default for Limits {
    /// `[fb]`'s defaults: 10,000 devices, 100 per identity, never forgotten by age; of
    /// other lines 5,000 a line (a line of about 1,000 devices, five times over) and
    /// 40,000 in all (a plant of eight such lines, five times over).
    fn default() -> Limits {
        Limits {
            max_devices: 10_000,
            max_per_identity: 100,
            forget_offline_after: None,
            max_remote_per_line: 5_000,
            max_remote: 40_000,
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
        max_remote_per_line: usize::MAX,
        max_remote: usize::MAX,
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
    /// Another line's device, forgotten by its own line (the bus).
    Bus,
}

impl ForgetReason {
    pub fn label(self) -> &'static str {
        match self {
            ForgetReason::Expired => "expired",
            ForgetReason::Admin => "admin",
            ForgetReason::Bus => "bus",
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

impl Registry {
    /// The one place a device of this line enters the registry. A device it holds already
    /// is admitted again (a re-declaration, a profiled device's reconnection); a new one
    /// only while the line has fewer than `[fb] max_devices` devices and `registrant`
    /// (the verified username, or the peer's address) registered fewer than
    /// `[fb] max_devices_per_identity`. A refusal is counted and logged (at most once a
    /// minute per limit, with the number refused since); the caller answers the device.
    pub(super) fn admit(
        &self,
        devices: &mut Devices,
        id: &str,
        registrant: &str,
    ) -> Result<(), Full> {
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
        self.refused_at_limit(devices, full.limit(), |since| {
            tracing::warn!(
                device = id,
                registrant,
                limit = full.limit(),
                refused_since_last_line = since,
                "new device refused: {full} (logged at most once a minute per limit; \
                 fbbus_limit_refusals_total)"
            )
        });
        Err(full)
    }

    /// A refusal at registry limit `limit`: counted in `fbbus_limit_refusals_total`, and
    /// `log` called with the number refused since its last call, at most once a minute
    /// per limit.
    pub(super) fn refused_at_limit(
        &self,
        devices: &mut Devices,
        limit: &'static str,
        log: impl FnOnce(u64),
    ) {
        self.metrics
            .limit_refusals
            .with_label_values(&[limit])
            .inc();
        let now = Instant::now();
        let (last, unlogged) = devices.refusals_unlogged.entry(limit).or_default();
        *unlogged += 1;
        if last.is_none_or(|t| now.duration_since(t) >= LIMIT_LOG_INTERVAL) {
            log(*unlogged);
            *last = Some(now);
            *unlogged = 0;
        }
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
    pub(super) fn expire(&self, now: SystemTime, after: Duration) {
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
    pub(super) fn remove(
        &self,
        devices: &mut Devices,
        id: &str,
        reason: ForgetReason,
    ) -> Option<Record> {
        let record = devices.remove(id)?;
        let _ = self.changes.send(Change::Removed(id.into()));
        if record.line == self.line {
            if let Some(observer) = self.observer.get() {
                let _ = observer.send(super::feed::LocalChange::Forgotten(id.to_owned()));
            }
        }
        // The values first, the record last: one ordered queue, so whoever sees the
        // record cleared knows the values are cleared too (a new subscriber gets none).
        // Another line's device: its values here came from the bus, and so do their
        // clears, which are not put back on it (its own line cleared them there).
        let remote = record.line != self.line;
        for mut clear in retained_clears(id, record.interface.outputs()) {
            if remote {
                clear.publisher = crate::broker_publisher::BUS_CLIENT_ID.to_owned();
            }
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
}

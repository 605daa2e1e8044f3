//! `[fb]`: the typed FB topics, the device registry, profiles and silence. Its defaults are
//! those of the modules it configures, from the one place each sets them.

use std::path::PathBuf;

use serde::Deserialize;

#[derive(Debug, Clone, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct FbSection {
    /// Where the device registry is persisted (written atomically); relative to the
    /// config file's directory, or to the working directory for the embedded default.
    /// Empty: not persisted.
    pub registry_file: PathBuf,
    /// Typed-namespace topics (fb/, dinasore/, fbdk/) no device declared: "reject" them
    /// (MQTT 5: 0x90), or "pass" them unchecked while migrating an untyped line.
    /// Declared ports are checked in both modes.
    pub undeclared: crate::policy::typed::Undeclared,
    /// A directory of device profiles (`*.toml`, one per device): the declaration the
    /// broker holds for a runtime that cannot send one (`profiles`). Relative to the
    /// config file's directory. Empty: none. Reloaded when it changes.
    pub profiles_dir: PathBuf,
    /// The unit of DATE, TIME_OF_DAY and DATE_AND_TIME in `fbdk/` payloads, read and
    /// written: "ns" (4diac FORTE 3.x) or "ms" (FORTE 2.0.x). A device's profile sets its
    /// own unit on its own topics.
    pub fbdk_time_unit: fb_bridge::codec::fbdk::TimeUnit,
    /// The largest `fbdk/` payload delivered, in bytes: 4diac FORTE's MQTT layer copies a
    /// received message into a 255-byte buffer per subscription, and a longer one
    /// corrupts that subscription's stream. 0: no limit. A device's profile sets its
    /// own limit on its own input topics (`speaks.max_payload`).
    pub fbdk_max_payload: usize,
    /// An online device is `silent` when none of its periodic outputs published for
    /// `silence_factor` times its period (observed), and at least `silence_min_s`
    /// seconds. 0 turns the judgement off.
    pub silence_factor: f64,
    pub silence_min_s: f64,
    /// Devices of this line the registry holds at most: a new device beyond is refused
    /// (its declaration answered on `fbbus/diag/<id>`, MQTT 5: 0x97), known devices go on.
    pub max_devices: usize,
    /// Devices one identity registers at most (the verified username where a password
    /// file exists, else the client's address): a new device beyond is refused likewise.
    pub max_devices_per_identity: usize,
    /// A device of this line offline this long is forgotten, with its retained record and
    /// values, as `fbbus devices forget` does. 0: never (a device away for maintenance
    /// keeps its record until it is forgotten by hand).
    pub forget_offline_after_s: u64,
    /// Devices of one other line of the bus this line takes (their records, their typed
    /// values): a line announcing more gets the rest refused
    /// (`fbbus_limit_refusals_total{limit="remote_devices_per_line"}`), no other line's
    /// place is taken.
    pub max_remote_devices_per_line: usize,
    /// Devices of all other lines together (`limit="remote_devices"`).
    pub max_remote_devices: usize,
    /// The largest declaration payload read, in bytes; a longer one is refused unread
    /// (`fbbus_limit_refusals_total{limit="declaration_bytes"}`).
    pub max_declaration_bytes: usize,
    /// Most FB instances one device declares (`limit="fbs"`).
    pub max_fbs: usize,
    /// Most ports (event and data, inputs and outputs) one device declares, over all
    /// its FBs (`limit="ports"`).
    pub max_ports: usize,
    /// Declarations one connected device may send per minute, in a burst of as many
    /// (a token bucket per connection); beyond, refused with "rate limited, retry after
    /// N s" (`limit="declaration_rate"`).
    pub declarations_per_minute: u32,
    /// Diagnostics on `fbbus/diag/<device>` per device and second, beyond a burst of
    /// `diag_burst`; beyond, dropped and counted (`fbbus_diag_dropped_total`).
    pub diag_per_second: f64,
    pub diag_burst: u32,
}

impl FbSection {
    /// How long a periodic output may be quiet.
    pub fn silence_bound(&self) -> crate::silence::Bound {
        crate::silence::Bound {
            factor: self.silence_factor,
            floor: std::time::Duration::from_secs_f64(self.silence_min_s),
        }
    }

    /// What one device may declare, and how often it may declare and be answered.
    pub(crate) fn declaration_limits(&self) -> crate::policy::typed::Limits {
        crate::policy::typed::Limits {
            max_declaration_bytes: self.max_declaration_bytes,
            max_fbs: self.max_fbs,
            max_ports: self.max_ports,
            declarations_per_minute: self.declarations_per_minute,
            diag_per_second: self.diag_per_second,
            diag_burst: self.diag_burst,
        }
    }

    /// What the device registry holds at most.
    pub(crate) fn registry_limits(&self) -> crate::registry::Limits {
        crate::registry::Limits {
            max_devices: self.max_devices,
            max_per_identity: self.max_devices_per_identity,
            forget_offline_after: (self.forget_offline_after_s > 0)
                .then(|| std::time::Duration::from_secs(self.forget_offline_after_s)),
            max_remote_per_line: self.max_remote_devices_per_line,
            max_remote: self.max_remote_devices,
        }
    }
}

impl Default for FbSection {
    /// The defaults of the modules `[fb]` configures, from the one place each sets them.
    fn default() -> Self {
        let silence = crate::silence::Bound::DEFAULT;
        let declarations = crate::policy::typed::Limits::default();
        let registry = crate::registry::Limits::default();
        FbSection {
            registry_file: PathBuf::from("fbbus-registry.json"),
            profiles_dir: PathBuf::new(),
            undeclared: Default::default(),
            fbdk_time_unit: Default::default(),
            fbdk_max_payload: crate::policy::typed::FORTE_RECEIVE_BUFFER,
            silence_factor: silence.factor,
            silence_min_s: silence.floor.as_secs_f64(),
            max_devices: registry.max_devices,
            max_devices_per_identity: registry.max_per_identity,
            forget_offline_after_s: registry.forget_offline_after.map_or(0, |d| d.as_secs()),
            max_remote_devices_per_line: registry.max_remote_per_line,
            max_remote_devices: registry.max_remote,
            max_declaration_bytes: declarations.max_declaration_bytes,
            max_fbs: declarations.max_fbs,
            max_ports: declarations.max_ports,
            declarations_per_minute: declarations.declarations_per_minute,
            diag_per_second: declarations.diag_per_second,
            diag_burst: declarations.diag_burst,
        }
    }
}

//! The device profiles the broker holds: `[fb] profiles_dir`, one TOML file per device.
//!
//! A profile ([`fb_bridge::profile`]) stands in for the declaration a 4diac FORTE or
//! DINASORE runtime cannot send. The broker uses it at three points of the packet path:
//!
//! - **CONNECT** (`session::connect`): a connection its identity matches *is* the device:
//!   typed topics under the profile's device id, the profile's interface, registry online.
//!   A declaration the device sends anyway must equal its profile's interface.
//! - **the typed check** (`policy::typed`): a publication on one of the profile's own
//!   output topics is decoded the way the device speaks, checked against the port, and
//!   routed on its own topic and on the typed topics; an accepted message on a typed
//!   output that feeds a profile's input topic is also sent there, encoded for that device.
//! - **the end of the connection** (`session::close`): the profile's broker-side will.
//!
//! **Loading.** Every `*.toml` in the directory is read and validated at start (an error
//! stops the broker, naming the file and the key) and again whenever the directory's
//! listing or a file's size, time or inode changes, polled like the password file; a
//! reload that fails keeps the last good set, with the error logged and counted
//! (`fbbus_file_reloads_total{file="profiles_dir"}`), because one half-written file must
//! not untype a whole line. Profiles apply to connections from their next CONNECT.
//!
//! **Bounds.** At most [`MAX_PROFILES`] files of at most [`MAX_FILE_BYTES`] each, and
//! [`fb_bridge::profile::MAX_TOPICS`] topics per profile: the operator fills this table,
//! not clients, but a stray directory must not exhaust the broker either.
//!
//! **One owner per topic and per device.** Two profiles with the same device id or the
//! same own topic refuse the whole set: a topic that two devices could publish would let
//! one speak for the other (the stolen-topic rule, `docs/runtimes.md`).

use std::collections::{BTreeMap, HashMap};
use std::path::{Path, PathBuf};
use std::sync::{Arc, Mutex, PoisonError, RwLock};
use std::time::SystemTime;

use fb_bridge::profile::{Profile, ProfileFile, Source};

use crate::metrics::Metrics;

/// Most profile files read from the directory.
pub const MAX_PROFILES: usize = 10_000;
/// Largest profile file read, in bytes.
pub const MAX_FILE_BYTES: u64 = 1 << 20;

/// The profiles in force, indexed the ways the packet path asks.
#[derive(Debug, Default)]
pub struct ProfileSet {
    by_device: HashMap<String, Arc<Profile>>,
    /// Own output topic → (profile, index in `outputs`).
    outputs: HashMap<String, (Arc<Profile>, usize)>,
    /// By the device of the typed output: (that output, the profile whose input topic it
    /// feeds, the index in its `inputs`). Keyed by device so that the packet path looks
    /// it up without building a key.
    feeds: HashMap<String, Vec<(Source, Arc<Profile>, usize)>>,
    /// Every input topic, with the profile it is an input of.
    inputs: HashMap<String, Arc<Profile>>,
}

impl ProfileSet {
    /// Indexes `profiles` (by file name, for errors); refuses duplicates.
    pub fn new(profiles: Vec<(String, Profile)>) -> Result<ProfileSet, String> {
        let mut set = ProfileSet::default();
        let mut files: HashMap<String, String> = HashMap::new();
        for (file, profile) in profiles {
            let profile = Arc::new(profile);
            if let Some(other) = files.insert(profile.device.clone(), file.clone()) {
                return Err(format!(
                    "{file}: device {} already has a profile in {other}",
                    profile.device
                ));
            }
            for (i, out) in profile.outputs.iter().enumerate() {
                let owner = (Arc::clone(&profile), i);
                if let Some((other, _)) = set.outputs.insert(out.topic.clone(), owner) {
                    // Both named: which of the two came first is only the order read.
                    let other_file = files.get(&other.device).map_or("?", String::as_str);
                    return Err(format!(
                        "topic {} is an output of device {} ({file}) and of device {} \
                         ({other_file}): one device per topic",
                        out.topic, profile.device, other.device
                    ));
                }
            }
            for (i, input) in profile.inputs.iter().enumerate() {
                set.inputs
                    .insert(input.own.topic.clone(), Arc::clone(&profile));
                set.feeds
                    .entry(input.from.device.clone())
                    .or_default()
                    .push((input.from.clone(), Arc::clone(&profile), i));
            }
            set.by_device.insert(profile.device.clone(), profile);
        }
        // An input topic is the broker's to publish: no device may also publish it. An
        // input fed by a profiled device's output reads the values that output sends.
        for feeds in set.feeds.values() {
            for (source, profile, i) in feeds {
                let input = &profile.inputs[*i];
                let topic = &input.own.topic;
                if let Some(from) = set.by_device.get(&source.device) {
                    let types = |p: &Profile, fb: &str, port: &str, output: bool| {
                        let shape = match output {
                            true => p.interface.output(fb, port),
                            false => p.interface.input(fb, port),
                        };
                        shape.map(|s| s.value_types())
                    };
                    let sent = types(from, &source.fb, &source.port, true);
                    let read = types(profile, &input.own.fb, &input.own.port, false);
                    if sent.is_none() || sent != read {
                        return Err(format!(
                            "{topic}: input {}.{} of device {} is fed from {}/{}/{}, which {}",
                            input.own.fb,
                            input.own.port,
                            profile.device,
                            source.device,
                            source.fb,
                            source.port,
                            match sent {
                                None => "is not an output of that device's profile",
                                Some(_) => "sends other types",
                            }
                        ));
                    }
                }
                if let Some((other, _)) = set.outputs.get(topic) {
                    return Err(format!(
                        "topic {topic} is an input of device {} and an output of device {}",
                        profile.device, other.device
                    ));
                }
            }
        }
        Ok(set)
    }

    pub fn len(&self) -> usize {
        self.by_device.len()
    }

    pub fn is_empty(&self) -> bool {
        self.by_device.is_empty()
    }

    pub fn get(&self, device: &str) -> Option<&Arc<Profile>> {
        self.by_device.get(device)
    }

    /// Every profile, in no order.
    pub fn devices(&self) -> impl Iterator<Item = &Arc<Profile>> {
        self.by_device.values()
    }

    /// The profile a connection with this client id and verified username is, if any.
    ///
    /// A client-id identity is as strong as the listener that let the client in; a
    /// client logged in as another device's username is that device, never this one.
    pub fn identify(&self, client_id: &str, username: Option<&str>) -> Option<&Arc<Profile>> {
        use fb_bridge::profile::Identity;
        // The common case, a FORTE device whose client id is its device id, in O(1).
        let exact = self
            .by_device
            .get(client_id)
            .filter(|p| p.identity == Identity::ClientId(client_id.to_owned()));
        let profile = exact.or_else(|| {
            self.by_device
                .values()
                .find(|p| p.identity.matches(client_id, username))
        })?;
        let claimed = match &profile.identity {
            Identity::Username(_) => true,
            Identity::ClientId(_) | Identity::ClientIdPrefix(_) => {
                username.is_none_or(|u| u == profile.device)
            }
            Identity::TopicsOnly => false,
        };
        claimed.then_some(profile)
    }

    /// The device and port whose own output topic `topic` is.
    pub fn output(&self, topic: &str) -> Option<(&Arc<Profile>, usize)> {
        self.outputs.get(topic).map(|(p, i)| (p, *i))
    }

    /// The input topics fed by the typed output `device/fb/port`.
    pub fn feeds<'a>(
        &'a self,
        device: &str,
        fb: &'a str,
        port: &'a str,
    ) -> impl Iterator<Item = (&'a Arc<Profile>, usize)> + 'a {
        self.feeds
            .get(device)
            .into_iter()
            .flatten()
            .filter(move |(s, _, _)| s.fb == fb && s.port == port)
            .map(|(_, p, i)| (p, *i))
    }

    /// Whether `topic` is some profile's input topic (the broker publishes it).
    pub fn is_input_topic(&self, topic: &str) -> bool {
        self.inputs.contains_key(topic)
    }

    /// The profile `topic` is an input topic of.
    pub fn input(&self, topic: &str) -> Option<&Arc<Profile>> {
        self.inputs.get(topic)
    }

    /// The typed topics (`fb/<device>/<FB>/<PORT>`) that feed an input topic: a line must
    /// ask the bus for them, or another line's device would feed nothing here.
    pub fn fed_outputs(&self) -> std::collections::BTreeSet<String> {
        self.feeds
            .values()
            .flatten()
            .map(|(s, _, _)| format!("fb/{}/{}/{}", s.device, s.fb, s.port))
            .collect()
    }

    /// Whether any profile maps own topics (the typed check looks them up only then).
    pub fn maps_topics(&self) -> bool {
        !self.outputs.is_empty() || !self.feeds.is_empty()
    }
}

/// Reads and validates one profile file.
pub fn read_file(path: &Path) -> Result<Profile, String> {
    let name = path.display();
    let len = std::fs::metadata(path)
        .map_err(|e| format!("{name}: {e}"))?
        .len();
    if len > MAX_FILE_BYTES {
        return Err(format!(
            "{name}: {len} bytes; a profile is at most {MAX_FILE_BYTES}"
        ));
    }
    let text = std::fs::read_to_string(path).map_err(|e| format!("{name}: {e}"))?;
    parse(&text).map_err(|e| format!("{name}: {e}"))
}

/// Parses and validates a profile written in TOML; the error lists every mistake.
pub fn parse(text: &str) -> Result<Profile, String> {
    let file: ProfileFile = toml::from_str(text).map_err(|e| e.to_string())?;
    file.validate().map_err(|errors| {
        errors
            .iter()
            .map(ToString::to_string)
            .collect::<Vec<_>>()
            .join("; ")
    })
}

/// Reads every `*.toml` of `dir`, in name order.
pub fn read_dir(dir: &Path) -> Result<ProfileSet, String> {
    let mut profiles = Vec::new();
    for path in profile_files(dir)? {
        let name = path
            .file_name()
            .map(|n| n.to_string_lossy().into_owned())
            .unwrap_or_default();
        profiles.push((name, read_file(&path)?));
    }
    ProfileSet::new(profiles)
}

fn profile_files(dir: &Path) -> Result<Vec<PathBuf>, String> {
    let entries = std::fs::read_dir(dir).map_err(|e| format!("{}: {e}", dir.display()))?;
    let mut files = Vec::new();
    for entry in entries.flatten() {
        let path = entry.path();
        let toml = path.extension().is_some_and(|e| e == "toml");
        // Editors' and `fbbus declare`'s temporary files start with a dot.
        let hidden = entry.file_name().to_string_lossy().starts_with('.');
        if toml && !hidden && path.is_file() {
            files.push(path);
            if files.len() > MAX_PROFILES {
                return Err(format!(
                    "{}: more than {MAX_PROFILES} profile files",
                    dir.display()
                ));
            }
        }
    }
    files.sort();
    Ok(files)
}

/// What tells a changed directory from an unchanged one without reading its files.
type DirStamp = BTreeMap<PathBuf, (Option<SystemTime>, u64, u64)>;

fn dir_stamp(dir: &Path) -> Option<DirStamp> {
    let files = profile_files(dir).ok()?;
    Some(
        files
            .into_iter()
            .filter_map(|path| {
                let meta = std::fs::metadata(&path).ok()?;
                #[cfg(unix)]
                let inode = std::os::unix::fs::MetadataExt::ino(&meta);
                #[cfg(not(unix))]
                let inode = 0;
                Some((path, (meta.modified().ok(), meta.len(), inode)))
            })
            .collect(),
    )
}

/// The connections speaking for each topics-only device. DINASORE opens one connection
/// per MQTT FB, each with a random client id, so such a device is online while any of
/// them lives: the first to publish on its topics brings it online, the last to end
/// takes it offline. One entry per connection (bounded by `[broker] max_connections`);
/// a device's entry goes with its last connection.
#[derive(Debug, Default)]
pub struct Speakers {
    devices: Mutex<HashMap<String, std::collections::BTreeSet<u64>>>,
}

impl Speakers {
    /// Connection `session` speaks for `device` from now; true if it is the only one.
    pub fn join(&self, device: &str, session: u64) -> bool {
        let mut devices = self.devices.lock().unwrap_or_else(PoisonError::into_inner);
        let sessions = devices.entry(device.to_owned()).or_default();
        sessions.insert(session);
        sessions.len() == 1
    }

    /// Connection `session` of `device` ended; true if it was the last.
    pub fn leave(&self, device: &str, session: u64) -> bool {
        let mut devices = self.devices.lock().unwrap_or_else(PoisonError::into_inner);
        let Some(sessions) = devices.get_mut(device) else {
            return false;
        };
        sessions.remove(&session);
        let last = sessions.is_empty();
        if last {
            devices.remove(device);
        }
        last
    }
}

/// Why [`Profiles::put`] did not put a profile.
#[derive(Debug, thiserror::Error)]
pub enum PutError {
    #[error(
        "this broker has no profiles directory (the embedded default configuration has \
         none). Give it one: in its config file, under [fb], `profiles_dir = \"profiles\"` \
         (relative to the file), then restart it with `fbbus serve --config FILE` and \
         declare again"
    )]
    NoDirectory,
    #[error("{0}")]
    Invalid(String),
    #[error("{0}")]
    Io(String),
}

/// Told of every new set in force: (the set before, the set now).
type OnChange = Box<dyn Fn(&ProfileSet, &ProfileSet) + Send + Sync>;

/// The profiles in force, reloaded from their directory when it changes.
pub struct Profiles {
    dir: Option<PathBuf>,
    current: RwLock<Arc<ProfileSet>>,
    stamp: Mutex<Option<DirStamp>>,
    on_change: std::sync::OnceLock<OnChange>,
}

impl Profiles {
    /// No profiles: every device declares itself.
    pub fn none() -> Profiles {
        Profiles {
            dir: None,
            current: RwLock::default(),
            stamp: Mutex::default(),
            on_change: std::sync::OnceLock::new(),
        }
    }

    /// Loads `dir` once; an error here stops the broker from starting.
    pub fn load(dir: &Path) -> Result<Profiles, String> {
        let stamp = dir_stamp(dir);
        let set = read_dir(dir)?;
        tracing::info!(dir = %dir.display(), profiles = set.len(), "device profiles loaded");
        Ok(Profiles {
            dir: Some(dir.to_owned()),
            current: RwLock::new(Arc::new(set)),
            stamp: Mutex::new(stamp),
            on_change: std::sync::OnceLock::new(),
        })
    }

    pub fn dir(&self) -> Option<&Path> {
        self.dir.as_deref()
    }

    /// Calls `hook` with the set in force now (as both sets), and with every later change
    /// (the set before, the set after). Set once, by the server, which keeps the bus's
    /// interest in the outputs that feed input topics.
    pub fn on_change(&self, hook: impl Fn(&ProfileSet, &ProfileSet) + Send + Sync + 'static) {
        let now = self.get();
        hook(&ProfileSet::default(), &now);
        let _ = self.on_change.set(Box::new(hook));
    }

    fn install(&self, set: ProfileSet) {
        let set = Arc::new(set);
        let before = std::mem::replace(
            &mut *self.current.write().unwrap_or_else(PoisonError::into_inner),
            Arc::clone(&set),
        );
        if let Some(hook) = self.on_change.get() {
            hook(&before, &set);
        }
    }

    /// The profiles now.
    pub fn get(&self) -> Arc<ProfileSet> {
        self.current
            .read()
            .unwrap_or_else(PoisonError::into_inner)
            .clone()
    }

    /// Puts the profile `text` (TOML) for `device` into the directory: validated alone
    /// and with every other profile (one owner per topic), then written whole (a
    /// temporary file renamed over the old one, so no reader sees half of it) and in
    /// force at once. The admin API's `PUT /api/v1/profiles/{device}`, `fbbus declare`.
    pub fn put(&self, device: &str, text: &str, metrics: &Metrics) -> Result<(), PutError> {
        let Some(dir) = &self.dir else {
            return Err(PutError::NoDirectory);
        };
        if text.len() as u64 > MAX_FILE_BYTES {
            return Err(PutError::Invalid(format!(
                "{} bytes; a profile is at most {MAX_FILE_BYTES}",
                text.len()
            )));
        }
        let profile = parse(text).map_err(PutError::Invalid)?;
        if profile.device != device {
            return Err(PutError::Invalid(format!(
                "the profile is device {}'s, not {device}'s",
                profile.device
            )));
        }
        // Hidden files are not read (editors' temporary files): such a profile would be
        // written and then ignored by the next reload.
        if device.starts_with('.') {
            return Err(PutError::Invalid(format!(
                "device id {device:?} starts with '.', which the profiles directory ignores"
            )));
        }
        let name = format!("{device}.toml");
        let path = dir.join(&name);
        // The whole set as it would be: this profile in place of the device's file.
        let mut profiles = vec![(name.clone(), profile)];
        for other in profile_files(dir).map_err(PutError::Io)? {
            if other != path {
                let file = other
                    .file_name()
                    .map(|n| n.to_string_lossy().into_owned())
                    .unwrap_or_default();
                profiles.push((file, read_file(&other).map_err(PutError::Invalid)?));
            }
        }
        let set = ProfileSet::new(profiles).map_err(PutError::Invalid)?;
        let tmp = dir.join(format!(".{name}.tmp"));
        std::fs::write(&tmp, text)
            .and_then(|()| std::fs::rename(&tmp, &path))
            .map_err(|e| PutError::Io(format!("{}: {e}", path.display())))?;
        *self.stamp.lock().unwrap_or_else(PoisonError::into_inner) = dir_stamp(dir);
        self.install(set);
        metrics
            .reloads
            .with_label_values(&["profiles_dir", "ok"])
            .inc();
        tracing::info!(device, file = %path.display(), "device profile put");
        Ok(())
    }

    /// Reloads if the directory changed (`force`: anyway). Returns whether a new set is
    /// in force.
    pub fn reload(&self, force: bool, metrics: &Metrics) -> bool {
        let Some(dir) = &self.dir else {
            return false;
        };
        let now = dir_stamp(dir);
        {
            let mut stamp = self.stamp.lock().unwrap_or_else(PoisonError::into_inner);
            if !force && *stamp == now {
                return false;
            }
            *stamp = now;
        }
        match read_dir(dir) {
            Ok(set) => {
                let count = set.len();
                self.install(set);
                metrics
                    .reloads
                    .with_label_values(&["profiles_dir", "ok"])
                    .inc();
                tracing::info!(dir = %dir.display(), profiles = count, "device profiles reloaded");
                true
            }
            Err(e) => {
                metrics
                    .reloads
                    .with_label_values(&["profiles_dir", "error"])
                    .inc();
                tracing::error!(
                    dir = %dir.display(),
                    error = %e,
                    "device profiles not reloaded; keeping the previous set"
                );
                false
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    const FORTE: &str = r#"
device = "conv2"
runtime = "forte"
[speaks]
encoding = "fbdk"
max_payload = 255
[interface.fbs.CONV.data_out]
POSITION = "INT"
CONNECT = "BOOL"
[interface.fbs.CONV.data_in]
SPEED = "REAL"
[[topics]]
topic = "line1/conv2/position"
port = "CONV.POSITION"
[[topics]]
topic = "line1/conv2/speed"
port = "CONV.SPEED"
from = "conv1/CONV/SPEED"
[will]
"CONV.CONNECT" = false
"#;

    fn write(dir: &Path, name: &str, text: &str) {
        let tmp = dir.join(format!(".{name}"));
        std::fs::write(&tmp, text).unwrap();
        std::fs::rename(tmp, dir.join(name)).unwrap();
    }

    #[test]
    fn a_directory_loads_indexes_and_reloads() {
        let dir = tempfile::tempdir().unwrap();
        write(dir.path(), "conv2.toml", FORTE);
        std::fs::write(dir.path().join("notes.txt"), "not a profile").unwrap();
        let profiles = Profiles::load(dir.path()).expect("loads");
        let set = profiles.get();
        assert_eq!(set.len(), 1);
        assert_eq!(set.identify("conv2", None).unwrap().device, "conv2");
        assert_eq!(
            set.identify("conv2", Some("conv2")).unwrap().device,
            "conv2"
        );
        // Logged in as another device: not this one.
        assert!(set.identify("conv2", Some("conv3")).is_none());
        assert!(set.identify("conv3", None).is_none());
        assert_eq!(set.output("line1/conv2/position").unwrap().1, 0);
        assert_eq!(set.feeds("conv1", "CONV", "SPEED").count(), 1);
        assert_eq!(set.feeds("conv1", "CONV", "POSITION").count(), 0);

        let metrics = Metrics::new();
        assert!(!profiles.reload(false, &metrics), "unchanged");
        // A second device mapping the same topic: refused, the first set stays.
        write(
            dir.path(),
            "thief.toml",
            &FORTE.replace("\"conv2\"", "\"thief\""),
        );
        assert!(!profiles.reload(false, &metrics));
        assert_eq!(profiles.get().len(), 1);
        // Fixed: taken.
        write(
            dir.path(),
            "thief.toml",
            &FORTE
                .replace("\"conv2\"", "\"conv3\"")
                .replace("line1/conv2/", "line1/conv3/"),
        );
        assert!(profiles.reload(false, &metrics));
        assert_eq!(profiles.get().len(), 2);
    }

    /// Issue 35: a profile put beside another that publishes the same topic is refused
    /// with both devices and their files named (it named the new device as the owner).
    #[test]
    fn a_conflicting_put_names_both_devices() {
        let dir = tempfile::tempdir().unwrap();
        write(dir.path(), "conv2.toml", FORTE);
        let profiles = Profiles::load(dir.path()).expect("loads");
        let thief = FORTE.replace("\"conv2\"", "\"thief\"");
        let err = profiles
            .put("thief", &thief, &Metrics::new())
            .unwrap_err()
            .to_string();
        assert_eq!(
            err,
            "topic line1/conv2/position is an output of device conv2 (conv2.toml) and of \
             device thief (thief.toml): one device per topic"
        );
        assert!(!dir.path().join("thief.toml").exists());
    }

    #[test]
    fn own_topics_in_any_utf8_are_owned_and_found() {
        let profile = parse(
            &FORTE
                .replace("line1/conv2/position", "Förderband/1/Position")
                .replace("line1/conv2/speed", "ライン/速度"),
        )
        .unwrap();
        let set = ProfileSet::new(vec![("conv2.toml".into(), profile)]).unwrap();
        assert_eq!(
            set.output("Förderband/1/Position").unwrap().0.device,
            "conv2"
        );
        assert!(set.output("Förderband/1/position").is_none());
        assert!(set.is_input_topic("ライン/速度"));
        // Wildcards and the broker's namespaces are not own topics, in any script.
        for bad in [
            "Förderband/+",
            "fb/conv2/CONV/POSITION",
            "fbbus/x",
            "$SYS/é",
        ] {
            let text = FORTE.replace("line1/conv2/position", bad);
            assert!(parse(&text).is_err(), "{bad} accepted");
        }
    }

    #[test]
    fn the_deploy_examples_load_together() {
        let dir = Path::new(env!("CARGO_MANIFEST_DIR")).join("../deploy/profiles");
        let set = read_dir(&dir).expect("deploy/profiles loads");
        assert_eq!(set.len(), 2);
        assert!(set.output("line1/conv3/speed").is_some());
        assert!(set.is_input_topic("line1/conv2/speed"));
    }

    #[test]
    fn an_input_fed_other_types_is_refused() {
        let feeder = parse(
            &FORTE
                .replace("\"conv2\"", "\"conv1\"")
                .replace("line1/conv2/", "line1/conv1/")
                .replace("conv1/CONV/SPEED", "conv9/CONV/SPEED"),
        )
        .unwrap();
        // conv2's SPEED (REAL) fed from conv1's POSITION (INT).
        let fed = parse(&FORTE.replace("conv1/CONV/SPEED", "conv1/CONV/POSITION")).unwrap();
        let error = ProfileSet::new(vec![
            ("conv1.toml".into(), feeder),
            ("conv2.toml".into(), fed),
        ])
        .expect_err("refused");
        assert!(error.contains("sends other types"), "{error}");
    }

    #[test]
    fn a_bad_file_names_itself_and_its_key() {
        let dir = tempfile::tempdir().unwrap();
        write(
            dir.path(),
            "bad.toml",
            &FORTE.replace("\"INT\"", "\"INTEGER\""),
        );
        let error = Profiles::load(dir.path()).err().expect("refused");
        assert!(
            error.contains("bad.toml") && error.contains("INTEGER"),
            "{error}"
        );
        write(dir.path(), "bad.toml", "device = ");
        let error = Profiles::load(dir.path()).err().expect("refused");
        assert!(error.contains("bad.toml"), "{error}");
    }
}

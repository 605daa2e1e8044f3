//! Device profiles: a typed, registered device that never declares anything.
//!
//! A 4diac FORTE or DINASORE runtime as it is published cannot send the declaration of
//! the device contract, sets no will and publishes on whatever topic its application
//! names. A profile, held by the broker, says instead of the device:
//!
//! - **who it is**: the registry id, and how its connection is recognised (its client
//!   id, a client-id prefix, or its verified username);
//! - **its FB interface**, as a declaration gives it;
//! - **how it speaks**: the encoding of each of its own topics, the unit of its `fbdk`
//!   dates and times, the largest message it can receive, whether its numbers arrive as
//!   JSON strings, the QoS of what it is sent;
//! - **its own topics**, each mapped onto one of its ports: an output topic is where the
//!   device publishes that port; an input topic is where it reads a port, fed from
//!   another device's typed output (`from`);
//! - **its broker-side will**: values the broker publishes on its typed output ports when
//!   it goes offline, for runtimes that cannot set a will.
//!
//! [`ProfileFile`] is the text as written (TOML on disk, JSON on the admin API);
//! [`ProfileFile::validate`] resolves it into a [`Profile`] or lists every mistake, each
//! located, as [`Declaration::validate`] does for a declaration.

use std::collections::{BTreeMap, BTreeSet};

use serde::{Deserialize, Serialize};

use crate::codec::fbdk::TimeUnit;
use crate::codec::Encoding;
use crate::interface::{is_identifier, Declaration, Interface, OutputPort};
use crate::topic::{self, filter};
use crate::types::{DataType, ElementaryType};

/// Most own topics one profile maps: bounds the broker's topic index per profile.
pub const MAX_TOPICS: usize = 1024;

/// A profile as written. Unknown keys are errors, so a misspelt key is not ignored.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ProfileFile {
    /// The registry id: typed topics are `fb/<device>/...`.
    pub device: String,
    /// Informative: `forte`, `dinasore`, or anything the line uses.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub runtime: Option<String>,
    #[serde(default)]
    pub identity: IdentityFile,
    #[serde(default)]
    pub speaks: Speaks,
    pub interface: Declaration,
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub topics: Vec<TopicFile>,
    /// Port (`FB.PORT`) → value, published by the broker when the device goes offline.
    /// A data port takes its value; an event port takes a table of its WITH values.
    #[serde(default, skip_serializing_if = "BTreeMap::is_empty")]
    pub will: BTreeMap<String, serde_json::Value>,
    /// Output port (`FB.PORT`) → the period it publishes at, in milliseconds: the device
    /// is `online, silent` once such a port has been quiet for `[fb] silence_factor`
    /// periods, from its first connection (no period to observe first).
    #[serde(default, skip_serializing_if = "BTreeMap::is_empty")]
    pub periods: BTreeMap<String, u64>,
    /// When the device counts as gone besides its connections ending badly.
    #[serde(default, skip_serializing_if = "LivenessFile::is_default")]
    pub liveness: LivenessFile,
}

/// When the device counts as gone (`[liveness]`), for the broker-side `[will]` and the
/// registry.
#[derive(Debug, Clone, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct LivenessFile {
    /// Publish the `[will]` values also when the device's last connection ends with a
    /// clean DISCONNECT (or the broker shuts down). False by default: an MQTT will fires
    /// only when a connection ends without one, and a tool that says goodbye is no
    /// failure. The reference line's CONNECT/NUM_DEV logic counts every departure, so its
    /// profiles set this.
    #[serde(default, skip_serializing_if = "std::ops::Not::not")]
    pub will_on_clean_disconnect: bool,
    /// Seconds the device's periodic outputs (stated in `[periods]` or observed) may all
    /// be quiet before the registry marks it offline, with its will, while its connection
    /// stays open: a frozen runtime that never pings is noticed. 0 turns it off. Default:
    /// 90 for `runtime = "dinasore"` (what MQTT's keep-alive would have allowed its
    /// publisher's 60 s, which its profile waives), off otherwise (a runtime that pings is
    /// ended by its keep-alive).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub offline_after_silent_s: Option<u64>,
}

impl LivenessFile {
    fn is_default(&self) -> bool {
        *self == LivenessFile::default()
    }
}

/// [`LivenessFile::offline_after_silent_s`] of a DINASORE profile that does not set it.
pub const DINASORE_OFFLINE_AFTER_SILENT_S: u64 = 90;

/// How the device's connection is recognised. With none given, its client id is the
/// device id.
#[derive(Debug, Clone, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct IdentityFile {
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub client_id: Option<String>,
    /// Any client id that starts with this (a runtime that adds a random suffix).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub client_id_prefix: Option<String>,
    /// The verified username (for a client id chosen at random, or left empty).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub username: Option<String>,
    /// Recognised by its own output topics only: a runtime with a random or empty client
    /// id and no username (DINASORE's MQTT FBs). A publication on one of its output topics
    /// is the device's when the access rules let the client publish there and the client
    /// is not recognised as another device.
    #[serde(default, skip_serializing_if = "std::ops::Not::not")]
    pub topics_only: bool,
    /// With `topics_only`: the source addresses or networks (`10.1.2.7`, `10.1.2.0/24`,
    /// IPv6 alike) whose clients may speak for the device. Empty: any address.
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub speakers_from: Vec<String>,
    /// With `topics_only`: the verified username a client must have logged in with to
    /// speak for the device. None: no username, or the device id as username.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub speaker_username: Option<String>,
}

/// How the device speaks on its own topics.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Speaks {
    /// The encoding of its own topics unless a topic says otherwise: `fbdk`, `dinasore`,
    /// `fb`.
    #[serde(default = "Speaks::default_encoding")]
    pub encoding: String,
    /// The unit of DATE, TIME_OF_DAY, DATE_AND_TIME in its `fbdk`: `ns` (FORTE 3.x) or
    /// `ms` (FORTE 2.x).
    #[serde(default)]
    pub fbdk_time_unit: TimeUnit,
    /// The largest message it can receive on its own topics, in bytes; 0: no limit.
    #[serde(default)]
    pub max_payload: usize,
    /// Its JSON values arrive as strings (`{"SPEED": "3"}`): DINASORE's publisher FB.
    #[serde(default)]
    pub string_numbers: bool,
    /// QoS of what the broker sends it on its own input topics.
    #[serde(default)]
    pub qos: u8,
    /// Hold its connections to the MQTT keep-alive they ask for (the default). False for
    /// a runtime that asks for one and never pings (DINASORE's publisher FB runs no
    /// network loop): the broker then does not end it for silence; the kernel's dead-link
    /// probes (`[broker] dead_link_timeout_s`) still end a connection whose peer vanished.
    #[serde(default = "yes", skip_serializing_if = "is_yes")]
    pub enforce_keep_alive: bool,
}

fn yes() -> bool {
    true
}

fn is_yes(b: &bool) -> bool {
    *b
}

impl Speaks {
    fn default_encoding() -> String {
        "fb".into()
    }
}

impl Default for Speaks {
    fn default() -> Speaks {
        Speaks {
            encoding: Speaks::default_encoding(),
            fbdk_time_unit: TimeUnit::default(),
            max_payload: 0,
            string_numbers: false,
            qos: 0,
            enforce_keep_alive: true,
        }
    }
}

/// One of the device's own topics.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct TopicFile {
    pub topic: String,
    /// `FB.PORT` of this device: an output (it publishes here) or an input (it reads here).
    pub port: String,
    /// For an input: the typed output that feeds it, `<device>/<FB>/<PORT>`.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub from: Option<String>,
    /// This topic's encoding, if not the profile's.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub encoding: Option<String>,
}

/// A resolved profile.
#[derive(Debug, Clone, PartialEq)]
pub struct Profile {
    pub device: String,
    pub identity: Identity,
    pub interface: Interface,
    pub fbdk_time_unit: TimeUnit,
    pub max_payload: usize,
    pub string_numbers: bool,
    pub qos: u8,
    pub enforce_keep_alive: bool,
    pub outputs: Vec<OwnTopic>,
    pub inputs: Vec<InputTopic>,
    /// (FB, port, payload in canonical JSON) for each broker-side will value.
    pub will: Vec<(String, String, String)>,
    /// (FB, output port, period) for each stated period.
    pub periods: Vec<(String, String, std::time::Duration)>,
    /// [`LivenessFile::will_on_clean_disconnect`].
    pub will_on_clean_disconnect: bool,
    /// [`LivenessFile::offline_after_silent_s`], resolved: None when off.
    pub offline_after_silent: Option<std::time::Duration>,
    /// Who may speak for a `topics_only` device (default for the others: unused).
    pub speakers: Speakers,
}

/// Who may speak for a `topics_only` device ([`IdentityFile::speakers_from`],
/// [`IdentityFile::speaker_username`]): any client is recognised by the topics it
/// publishes on, so a profile can narrow it to the runtime's host and user.
#[derive(Debug, Clone, Default, PartialEq, Eq)]
pub struct Speakers {
    /// Source networks; empty: any address.
    pub networks: Vec<ipnet::IpNet>,
    /// The one username that may speak; None: no username, or the device id.
    pub username: Option<String>,
}

impl Speakers {
    /// Whether a client from `peer` (None: not a network client) logged in as `username`
    /// may speak for `device`.
    pub fn admit(
        &self,
        device: &str,
        peer: Option<std::net::IpAddr>,
        username: Option<&str>,
    ) -> bool {
        let user_ok = match &self.username {
            Some(wanted) => username == Some(wanted.as_str()),
            None => username.is_none_or(|u| u == device),
        };
        // An IPv4 client on an IPv6 socket arrives as ::ffff:a.b.c.d.
        let from_ok = self.networks.is_empty()
            || peer.is_some_and(|p| {
                let p = p.to_canonical();
                self.networks.iter().any(|n| n.contains(&p))
            });
        user_ok && from_ok
    }

    /// What the profile allows, for an operator reading a refusal.
    pub fn describe(&self) -> String {
        let from = match self.networks.is_empty() {
            true => "any address".to_owned(),
            false => self
                .networks
                .iter()
                .map(ToString::to_string)
                .collect::<Vec<_>>()
                .join(", "),
        };
        let user = match &self.username {
            Some(u) => format!("user {u}"),
            None => "no username or the device id as username".to_owned(),
        };
        format!("from {from}, {user}")
    }
}

/// How a connection is recognised as the device.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum Identity {
    ClientId(String),
    ClientIdPrefix(String),
    Username(String),
    /// See [`IdentityFile::topics_only`]: no connection is the device.
    TopicsOnly,
}

impl Identity {
    /// Whether a connection with this client id and verified username is the device.
    pub fn matches(&self, client_id: &str, username: Option<&str>) -> bool {
        match self {
            Identity::ClientId(id) => client_id == id,
            Identity::ClientIdPrefix(prefix) => client_id.starts_with(prefix.as_str()),
            Identity::Username(user) => username == Some(user.as_str()),
            Identity::TopicsOnly => false,
        }
    }
}

/// An output topic: the device publishes `fb.port` on `topic` in `encoding`.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct OwnTopic {
    pub topic: String,
    pub fb: String,
    pub port: String,
    pub encoding: Encoding,
}

/// An input topic: the device reads `fb.port` on `topic`, in `encoding`, fed by the typed
/// output `from`.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct InputTopic {
    pub own: OwnTopic,
    pub from: Source,
}

/// A typed output port of some device.
#[derive(Debug, Clone, PartialEq, Eq, PartialOrd, Ord, Hash)]
pub struct Source {
    pub device: String,
    pub fb: String,
    pub port: String,
}

/// One mistake in a profile, with where it is.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, thiserror::Error)]
#[error("{at}: {error}")]
pub struct ProfileError {
    /// The key or section (`topics[2].port`, `interface: FB CONV: port X`).
    pub at: String,
    pub error: String,
}

fn err(at: impl Into<String>, error: impl Into<String>) -> ProfileError {
    ProfileError {
        at: at.into(),
        error: error.into(),
    }
}

fn encoding(name: &str, at: &str) -> Result<Encoding, ProfileError> {
    Encoding::from_namespace(name).ok_or_else(|| {
        err(
            at,
            format!("unknown encoding {name:?}: one of \"fb\", \"dinasore\", \"fbdk\""),
        )
    })
}

/// `FB.PORT`, both identifiers.
fn fb_port(text: &str) -> Option<(&str, &str)> {
    let (fb, port) = text.split_once('.')?;
    (is_identifier(fb) && is_identifier(port)).then_some((fb, port))
}

impl ProfileFile {
    /// Checks every key and returns the resolved profile, or every mistake found.
    pub fn validate(self) -> Result<Profile, Vec<ProfileError>> {
        let mut errors = Vec::new();
        if !topic::is_device_id(&self.device) {
            errors.push(err(
                "device",
                "not a usable device id (1-128 characters, none of / + # $, no control characters)",
            ));
        }
        let identity = match (
            self.identity.client_id,
            self.identity.client_id_prefix,
            self.identity.username,
            self.identity.topics_only,
        ) {
            (None, None, None, false) => Identity::ClientId(self.device.clone()),
            (Some(id), None, None, false) => Identity::ClientId(id),
            (None, Some(prefix), None, false) if !prefix.is_empty() => {
                Identity::ClientIdPrefix(prefix)
            }
            (None, None, Some(user), false) if !user.is_empty() => Identity::Username(user),
            (None, None, None, true) => Identity::TopicsOnly,
            _ => {
                errors.push(err(
                    "identity",
                    "give one of client_id, client_id_prefix (not empty), username (not empty) \
                     or topics_only = true",
                ));
                Identity::ClientId(self.device.clone())
            }
        };
        let mut speakers = Speakers {
            networks: Vec::new(),
            username: self.identity.speaker_username.clone(),
        };
        for (i, text) in self.identity.speakers_from.iter().enumerate() {
            let net = text
                .parse::<ipnet::IpNet>()
                .or_else(|_| text.parse::<std::net::IpAddr>().map(ipnet::IpNet::from));
            match net {
                // `10.1.2.7/24` means its network.
                Ok(net) => speakers.networks.push(net.trunc()),
                Err(_) => errors.push(err(
                    format!("identity.speakers_from[{i}]"),
                    format!(
                        "{text:?} is not an address or network (10.1.2.7, 10.1.2.0/24, fd00::/64)"
                    ),
                )),
            }
        }
        if speakers.username.as_deref() == Some("") {
            errors.push(err("identity.speaker_username", "not empty"));
        }
        if identity != Identity::TopicsOnly && speakers != Speakers::default() {
            errors.push(err(
                "identity",
                "speakers_from and speaker_username are for topics_only devices (the others \
                 are recognised by client id or username)",
            ));
        }
        let default_encoding = match encoding(&self.speaks.encoding, "speaks.encoding") {
            Ok(e) => e,
            Err(e) => {
                errors.push(e);
                Encoding::Json
            }
        };
        if self.speaks.qos > 2 {
            errors.push(err("speaks.qos", "0, 1 or 2"));
        }
        // Every port as written: one whose FB or type is wrong has its own error, and
        // what refers to it is not blamed again for its absence from `interface`.
        let written: BTreeSet<(String, String)> = self
            .interface
            .fbs
            .iter()
            .flat_map(|(fb, f)| {
                f.events_out
                    .keys()
                    .chain(f.events_in.keys())
                    .chain(f.data_out.keys())
                    .chain(f.data_in.keys())
                    .map(move |port| (fb.clone(), port.clone()))
            })
            .collect();
        // The rest is checked against the interface's right part, so one run reports
        // every mistake (a port without a type and a topic without from alike).
        let (interface, found) = match self.interface.validate_partly() {
            Ok(checked) => checked,
            Err(found) => {
                errors.extend(found.into_iter().map(|e| err("interface", e.to_string())));
                return Err(errors);
            }
        };
        let faulty: BTreeSet<String> = found.iter().filter_map(|e| e.fb.clone()).collect();
        // A port written but left out of `interface` for its own error.
        let dropped = |interface: &Interface, fb: &str, port: &str| {
            written.contains(&(fb.to_owned(), port.to_owned()))
                && interface.output(fb, port).is_none()
                && interface.input(fb, port).is_none()
        };
        errors.extend(found.into_iter().map(|e| err("interface", e.to_string())));

        if self.topics.len() > MAX_TOPICS {
            errors.push(err(
                "topics",
                format!("{} topics; at most {MAX_TOPICS}", self.topics.len()),
            ));
        }
        let dinasore = self.runtime.as_deref() == Some("dinasore");
        let mut outputs = Vec::new();
        let mut inputs = Vec::new();
        let mut seen = std::collections::BTreeSet::new();
        for (i, t) in self.topics.iter().enumerate().take(MAX_TOPICS) {
            let at = |key: &str| format!("topics[{i}].{key}");
            if !filter::valid_topic(&t.topic) || t.topic.starts_with('$') {
                errors.push(err(
                    at("topic"),
                    "not a topic name (no wildcards, not $...)",
                ));
                continue;
            }
            if topic::is_typed_namespace(&t.topic) || t.topic.starts_with(topic::BROKER_NAMESPACE) {
                errors.push(err(
                    at("topic"),
                    "fb/, dinasore/, fbdk/ and fbbus/ are fbbus's own: a device's own topic is outside them",
                ));
                continue;
            }
            if !seen.insert(t.topic.as_str()) {
                errors.push(err(at("topic"), "mapped twice"));
                continue;
            }
            let enc = match t.encoding.as_deref().map(|e| encoding(e, &at("encoding"))) {
                None => default_encoding,
                Some(Ok(e)) => e,
                Some(Err(e)) => {
                    errors.push(e);
                    continue;
                }
            };
            let Some((fb, port)) = fb_port(&t.port) else {
                errors.push(err(at("port"), "FB.PORT, both IEC 61131-3 identifiers"));
                continue;
            };
            let own = OwnTopic {
                topic: t.topic.clone(),
                fb: fb.to_owned(),
                port: port.to_owned(),
                encoding: enc,
            };
            let is_output = interface.output(fb, port).is_some();
            let is_input = interface.input(fb, port).is_some();
            match (&t.from, is_output, is_input) {
                (None, true, _) => outputs.push(own),
                (None, false, true) => errors.push(err(
                    at("from"),
                    format!("{fb}.{port} is an input: name the typed output that feeds it, <device>/<FB>/<PORT>"),
                )),
                (Some(_), true, _) => errors.push(err(
                    at("from"),
                    format!("{fb}.{port} is an output: only an input topic has a from"),
                )),
                (Some(from), false, true) => match parse_source(from) {
                    Some(_) if dinasore && enc == Encoding::Dinasore && !faulty.contains(fb) && !floats(&interface, fb, port) => {
                        errors.push(err(
                            at("port"),
                            format!(
                                "{fb}.{port}: a DINASORE subscriber FB reads float(value), \
                                 and this port has no value float() can read (only STRING, \
                                 TIME, dates, arrays, or no data): that stops the FB for good"
                            ),
                        ))
                    }
                    Some(from) => inputs.push(InputTopic { own, from }),
                    None => errors.push(err(at("from"), "<device>/<FB>/<PORT>")),
                },
                (_, false, false) if dropped(&interface, fb, port) => {}
                (_, false, false) => errors.push(err(
                    at("port"),
                    format!("{fb}.{port} is not a port of the profile's interface"),
                )),
            }
        }

        let mut will = Vec::new();
        for (port_text, value) in &self.will {
            let at = format!("will.{port_text}");
            let Some((fb, port)) = fb_port(port_text) else {
                errors.push(err(at, "FB.PORT, both IEC 61131-3 identifiers"));
                continue;
            };
            let Some(out) = interface.output(fb, port) else {
                if dropped(&interface, fb, port) {
                    continue;
                }
                errors.push(err(
                    at,
                    format!("{fb}.{port} is not an output of the interface"),
                ));
                continue;
            };
            let payload = match (&out, value) {
                (OutputPort::Data(_), v) => v.clone(),
                (OutputPort::Event(_), v @ serde_json::Value::Object(_)) => {
                    serde_json::json!({ "data": v })
                }
                (OutputPort::Event(_), _) => {
                    errors.push(err(
                        at,
                        "an event port's will is a table of its WITH values",
                    ));
                    continue;
                }
            };
            let payload = payload.to_string();
            if faulty.contains(fb) {
                // Its WITH types may be missing: the FB's own errors come first.
                continue;
            }
            match crate::codec::json::decode_named(payload.as_bytes(), port, &out) {
                Ok(_) => will.push((fb.to_owned(), port.to_owned(), payload)),
                Err(e) => errors.push(err(at, e.to_string())),
            }
        }

        let mut periods = Vec::new();
        for (port_text, ms) in &self.periods {
            let at = format!("periods.{port_text}");
            match fb_port(port_text) {
                Some((fb, port)) if interface.output(fb, port).is_some() => {
                    if *ms == 0 || *ms > 86_400_000 {
                        errors.push(err(at, "a period from 1 ms to one day (86400000)"));
                    } else {
                        periods.push((
                            fb.to_owned(),
                            port.to_owned(),
                            std::time::Duration::from_millis(*ms),
                        ));
                    }
                }
                Some((fb, port)) if dropped(&interface, fb, port) => {}
                _ => errors.push(err(at, "FB.PORT of an output of the interface")),
            }
        }

        let offline_after_silent = match self.liveness.offline_after_silent_s {
            Some(s) if s > 86_400 => {
                errors.push(err(
                    "liveness.offline_after_silent_s",
                    "seconds from 0 (off) to one day (86400)",
                ));
                None
            }
            Some(0) => None,
            Some(s) => Some(std::time::Duration::from_secs(s)),
            None if dinasore => Some(std::time::Duration::from_secs(
                DINASORE_OFFLINE_AFTER_SILENT_S,
            )),
            None => None,
        };

        if !errors.is_empty() {
            return Err(errors);
        }
        Ok(Profile {
            device: self.device,
            identity,
            interface,
            fbdk_time_unit: self.speaks.fbdk_time_unit,
            max_payload: self.speaks.max_payload,
            string_numbers: self.speaks.string_numbers,
            qos: self.speaks.qos,
            enforce_keep_alive: self.speaks.enforce_keep_alive,
            outputs,
            inputs,
            will,
            periods,
            will_on_clean_disconnect: self.liveness.will_on_clean_disconnect,
            offline_after_silent,
            speakers,
        })
    }
}

/// Whether input `fb.port` carries a value DINASORE's subscriber FB can read with
/// `float()` (a number, or a BOOL: `float(true)` is 1.0). Its FB reads only the key its
/// VALUE_NAME names, so an event whose other values are strings is fine; a port with no
/// such value at all would stop it on every message.
fn floats(interface: &Interface, fb: &str, port: &str) -> bool {
    let Some(shape) = interface.input(fb, port) else {
        return false;
    };
    shape.value_types().iter().any(|t| match t {
        DataType::Elementary(e) => e.reads_as_number(),
        DataType::Array(..) => false,
    })
}

/// `<device>/<FB>/<PORT>`.
fn parse_source(text: &str) -> Option<Source> {
    let mut levels = text.split('/');
    let (device, fb, port) = (levels.next()?, levels.next()?, levels.next()?);
    (levels.next().is_none()
        && topic::is_device_id(device)
        && is_identifier(fb)
        && is_identifier(port))
    .then(|| Source {
        device: device.to_owned(),
        fb: fb.to_owned(),
        port: port.to_owned(),
    })
}

/// A DINASORE payload whose values were written as strings, the way DINASORE's
/// publisher FB writes them (`{"SPEED": "3"}`, `str(value)`, so `"True"` for a BOOL),
/// with each value of a numeric or BOOL port turned back into a JSON number or boolean
/// where its string reads as one, so the ordinary decoder checks it. Values of other types
/// (STRING, TIME, dates) and strings that read as no number are left as they are, for the
/// decoder to accept or refuse. None if the payload is not a JSON object.
pub fn unstring_numbers(payload: &[u8], port_name: &str, port: &OutputPort<'_>) -> Option<Vec<u8>> {
    use serde_json::Value as J;
    let J::Object(mut object) = serde_json::from_slice::<J>(payload).ok()? else {
        return None;
    };
    let types: Vec<(&str, DataType)> = match port {
        OutputPort::Data(t) => vec![(port_name, *t)],
        OutputPort::Event(with) => with.clone(),
    };
    for (name, ty) in types {
        let DataType::Elementary(t) = ty else {
            continue;
        };
        let numeric = !matches!(
            t,
            ElementaryType::String
                | ElementaryType::WString
                | ElementaryType::Time
                | ElementaryType::Date
                | ElementaryType::TimeOfDay
                | ElementaryType::DateAndTime
        );
        let Some(J::String(text)) = object.get(name) else {
            continue;
        };
        let integer = !matches!(t, ElementaryType::Real | ElementaryType::Lreal);
        let number = match text.trim() {
            "True" | "TRUE" | "true" if t == ElementaryType::Bool => Some(J::Bool(true)),
            "False" | "FALSE" | "false" if t == ElementaryType::Bool => Some(J::Bool(false)),
            trimmed if numeric => serde_json::from_str::<serde_json::Number>(trimmed)
                .ok()
                .map(|n| match integer {
                    // DINASORE's VALUE is a REAL: an integer port's 3 arrives as "3.0".
                    // A whole number is that integer; anything else stays as it is, for
                    // the decoder to refuse.
                    true => whole(&n).unwrap_or(n),
                    false => n,
                })
                .map(J::Number),
            _ => None,
        };
        if let Some(number) = number {
            object.insert(name.to_owned(), number);
        }
    }
    serde_json::to_vec(&J::Object(object)).ok()
}

pub mod fboot;
/// `n` as an integer when it is a whole number written with a fraction (`3.0`, `-2e0`)
/// within 64 bits.
fn whole(n: &serde_json::Number) -> Option<serde_json::Number> {
    if n.is_i64() || n.is_u64() {
        return None;
    }
    let f = n.as_f64()?;
    if f.fract() != 0.0 || !f.is_finite() {
        return None;
    }
    if (i64::MIN as f64..=i64::MAX as f64).contains(&f) && f < 9.2e18 {
        return Some((f as i64).into());
    }
    if (0.0..1.8e19).contains(&f) {
        return Some((f as u64).into());
    }
    None
}

#[cfg(test)]
mod tests;

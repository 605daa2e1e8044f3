//! The profile of a DINASORE device, derived from the configuration 4diac IDE deployed to
//! it (`resources/data_model.fboot`).
//!
//! DINASORE (DIGI2-FEUP/dinasore) runs IEC 61499 applications of Python FBs. 4diac IDE
//! deploys to it with the same management requests as to FORTE; DINASORE keeps them and,
//! at the resource's `START`, writes them into `resources/data_model.fboot` and builds its
//! FBs from that file (it builds them from it again at every start). Its MQTT traffic is
//! written down there: the instances of its MQTT FB types and their parameters.
//! [`import_dinasore`] reads the file and writes the device's profile, with a note for
//! everything the file does not tell.
//!
//! # The file, and how DINASORE reads it
//!
//! The syntax is a FORTE boot file's, one request a line, `<resource>;<request>`
//! (`UaManagerFboot.save_fboot`): the first line `;` and the resource's `CREATE`, every
//! other line the resource's name, `;`, and the request exactly as 4diac IDE sent it, in
//! the order it came since the last `START`, that `START` last; watches are left out. A
//! parameter is a `WRITE` whose `Source` is the value as typed in 4diac IDE, with `"`,
//! `'`, `<` and `>` escaped and `&` left as it is (the IDE's `encodeXMLChars`):
//!
//! ```text
//! ;<Request ID="1" Action="CREATE"><FB Name="EMB_RES" Type="EMB_RES" /></Request>
//! EMB_RES;<Request ID="4" Action="CREATE"><FB Name="PUB_SPEED" Type="MQTT_PUBLISHER" /></Request>
//! EMB_RES;<Request ID="8" Action="WRITE"><Connection Source="line1/conv3/speed" Destination="PUB_SPEED.TOPIC" /></Request>
//! EMB_RES;<Request ID="30" Action="START"/>
//! ```
//!
//! DINASORE reads it differently from FORTE (`UaManagerFboot.parse_fboot`,
//! `core/configuration.py`), and the importer reads it as DINASORE does, so the profile
//! describes what the device runs:
//!
//! - every line is one request: Python's `readlines()` (universal newlines), each line
//!   split at *every* `;` into exactly two parts, the resource name ignored. A line that
//!   is not makes the file invalid and DINASORE runs nothing of it: a blank line, a `;`
//!   in a parameter, and so **any XML escape**: 4diac IDE writes a parameter's `'`, `"`,
//!   `<`, `>` as `&apos;`, `&quot;`, `&lt;`, `&gt;`. A STRING parameter written with
//!   quotes, as IEC 61131-3 writes a STRING literal (`'line1/a'`), is one: DINASORE's
//!   parameters are written bare (`line1/a`), as in its own example files
//!   (`Source="hello_world"`);
//! - each request is parsed by Python's ElementTree, which refuses what is not XML: a
//!   bare `&` (4diac IDE writes a parameter's `&` as it is), an unclosed element, two
//!   elements. DINASORE does not catch that error, so it runs nothing of the file
//!   either;
//! - it creates every FB first (`CREATE` of an `FB`, a later one of the same name
//!   replacing the earlier, `EMB_RES` itself skipped), then connects and sets parameters
//!   (`CREATE` and `WRITE` of a `Connection`); `DELETE` and the other actions are not
//!   read. `FB.PORT` is split at the first dot. A `WRITE` to an FB that does not exist, a
//!   connection from one, or an MQTT FB's `PORT` that `int()` cannot read (`VALUE` that
//!   `float()` cannot) raises while it builds them: nothing runs;
//! - a STRING parameter is taken as it is written (`convert_type`); an unset input is
//!   None.
//!
//! Where the file is one DINASORE does not run, no profile is derived, and a note says
//! which line and why. Not every refusal of ElementTree is checked (the requests 4diac
//! IDE writes are checked; a comment or a processing instruction is not read).
//!
//! # One profile per file
//!
//! DINASORE is one device, and nothing in the file names it (the resource is usually
//! `EMB_RES` on every device), nor does its traffic: each MQTT FB connects on its own with
//! an empty client id and no username. So the device id comes from the caller, and the
//! profile is recognised by its own topics only (`identity.topics_only`). How it speaks
//! is what its FBs do: `dinasore` payloads with string values (`{"SPEED": "3.0"}`,
//! `string_numbers`), no keep-alive kept by the publisher (`enforce_keep_alive = false`),
//! no size limit, QoS 0.
//!
//! # The MQTT FBs
//!
//! Their types are DINASORE's `resources/function_blocks/MQTT_*.fbt` and `.py`. Each has
//! `TOPIC`, `HOST`, `PORT` and one or two `VALUE_NAME` parameters. A DINASORE payload's
//! keys are the `VALUE_NAME`s, and the `dinasore` codec reads a payload's keys as the
//! port names of the profile, so a `VALUE_NAME` becomes the port's name (and must be an
//! IEC 61131-3 identifier: else the FB is left out, with a note). Every value is REAL,
//! the type of `VALUE` in the `.fbt`.
//!
//! - `MQTT_PUBLISHER` `X` sends `{"<VALUE_NAME>": str(VALUE)}` on `TOPIC` at `RUN`: the
//!   FB `X` with `data_out: { <VALUE_NAME>: REAL }`, its topic mapped onto that data port
//!   (the message is that one value, named);
//! - `MQTT_PUBLISHER_2` `X` sends both values in one object: `events_out: { RUN: { with:
//!   [<VALUE_NAME_1>, <VALUE_NAME_2>] } }`, both REAL, its topic mapped onto `X.RUN`;
//! - `MQTT_SUBSCRIBER` `Y` reads `float(payload[VALUE_NAME])` from `TOPIC`: `data_in: {
//!   <VALUE_NAME>: REAL }`, its topic mapped onto that port as an input;
//! - `MQTT_SUBSCRIBER_2` `Y` reads both: `events_in: { READ_O: { with: [<VALUE_NAME_1>,
//!   <VALUE_NAME_2>] } }`, both REAL, its topic mapped onto `Y.READ_O`.
//!
//! The event names are the FBs' own, the ones whose WITH carries the values in the
//! `.fbt`, as the FORTE import keeps `REQ` and `IND`: the publisher sends at its event
//! input `RUN` (`With VALUE_1, VALUE_2`), the subscriber delivers at its event output
//! `READ_O` (its `READ` only waits for a message and carries nothing). A `VALUE_NAME`
//! that is that name too gets the event renamed (`RUN_2`), with a note. Two equal
//! `VALUE_NAME`s of one FB make a one-key object: a data port, with a note.
//!
//! An input's `from` is not in the file: it is left out, so the profile does not pass
//! [`ProfileFile::validate`](crate::profile::ProfileFile::validate) until it is set, and
//! a note says so. A subscriber of a topic that a publisher of the same file publishes is
//! not mapped (DINASORE reaches itself through the broker as before). HOST and PORT are
//! not part of a profile: a note says when the FBs name more than one broker, and an FB
//! whose connection cannot succeed (no HOST, a PORT that is no TCP port) is left out.
//!
//! # DINASORE sources read
//!
//! DIGI2-FEUP/dinasore at d428b74c (July 2023): `data_model_fboot/ua_manager.py`
//! (`save_fboot`, `parse_fboot`, `generate_function_blocks`, `generate_connections`),
//! `core/manager.py` (which requests are kept), `core/configuration.py` (`create_fb`,
//! `create_connection`, `write_connection`, `convert_type`), `core/fb_interface.py`
//! (inputs start as None), `communication/client_thread.py`, the example files
//! `tests/configurations/*.fboot`, and `resources/function_blocks/MQTT_PUBLISHER{,_2}`
//! and `MQTT_SUBSCRIBER{,_2}` (`.fbt`, `.py`); and eclipse-4diac/4diac-ide's
//! `DeploymentExecutor.java` (the requests and `encodeXMLChars`).

use std::collections::BTreeMap;

use super::draft::{
    dollar_input, input, mappable_topic, output, sanitized_device, topic_kind, unique,
    unmapped_input, Draft, Endpoint, Shape, TopicKind, ValuePort,
};
use super::names::PortNames;
use super::note::Notes;
use super::resource::{PortRef, Resource};
use super::typing::Derived;
use super::FbootImport;
use crate::codec::Encoding;
use crate::interface::{is_identifier, Interface};
use crate::profile::{IdentityFile, ProfileFile, Speaks};
use crate::topic::{self, TypedTopic};
use crate::types::{DataType, ElementaryType};
use read::{mqtt_type, python_int, read, Role};
#[cfg(test)]
use read::{python_float, python_lines};

mod read;

/// The device id when nothing is left of the caller's once made usable.
const FALLBACK_DEVICE: &str = "dinasore";

/// Derives the profile of the DINASORE device `device` from its `data_model.fboot`.
///
/// Empty (no profile, no note) when the file has no DINASORE MQTT FB: it is no DINASORE
/// configuration with MQTT traffic (a FORTE boot file, say). Otherwise one profile, or
/// none and the notes saying why.
pub fn import_dinasore(text: &str, device: &str) -> FbootImport {
    import_dinasore_named(text, device, &mut PortNames::new())
}

/// [`import_dinasore`], with the generated event ports named as `names` says (a data
/// port's name is its payload key, which no name changes); what is wrong with the names is
/// in [`PortNames::finish`] afterwards.
pub fn import_dinasore_named(text: &str, device: &str, names: &mut PortNames) -> FbootImport {
    let config = read(text);
    let mut fbs: Vec<(&String, &(usize, String))> = config.resource.fbs.iter().collect();
    fbs.sort_by_key(|(_, (order, _))| *order);
    let mqtt: Vec<MqttFb<'_>> = fbs
        .into_iter()
        .filter_map(|(instance, (_, fb_type))| {
            let (role, two) = mqtt_type(fb_type)?;
            Some(MqttFb {
                instance,
                fb_type,
                role,
                two,
            })
        })
        .collect();
    if mqtt.is_empty() {
        return FbootImport::default();
    }
    let mut notes = Notes::default();
    if let Some(why) = config.refusal {
        notes.push(why);
        return FbootImport {
            profiles: Vec::new(),
            notes: notes.into_vec(),
        };
    }
    let device = if topic::is_device_id(device) {
        device.to_owned()
    } else {
        let usable = sanitized_device(device, FALLBACK_DEVICE);
        notes.push(format!(
            "The device id {device:?} is not usable (1-{} bytes, none of / + # $, no control \
             characters): the profile's device is {usable:?}.",
            topic::MAX_DEVICE_ID
        ));
        usable
    };
    let resource = &config.resource;
    broker_note(resource, &mqtt, &mut notes);
    // Every topic a publisher of the file publishes on, mapped or not.
    let mut published: BTreeMap<&str, &str> = BTreeMap::new();
    for fb in mqtt.iter().filter(|fb| fb.role == Role::Publisher) {
        if let Param::Written(t) = param(resource, fb.instance, "TOPIC") {
            published.entry(t).or_insert(fb.instance);
        }
    }
    let mut draft = Draft::new(device, names);
    for fb in &mqtt {
        derive(fb, resource, &published, &mut draft, &mut notes);
    }
    if draft.fbs.is_empty() {
        notes.push(format!(
            "None of its MQTT FBs can be mapped, so device {} has no profile.",
            draft.device
        ));
        return FbootImport {
            profiles: Vec::new(),
            notes: notes.into_vec(),
        };
    }
    let profile = ProfileFile {
        device: draft.device,
        runtime: Some("dinasore".into()),
        identity: IdentityFile {
            topics_only: true,
            ..IdentityFile::default()
        },
        speaks: Speaks {
            encoding: Encoding::Dinasore.namespace().into(),
            string_numbers: true,
            enforce_keep_alive: false,
            ..Speaks::default()
        },
        interface: Interface { fbs: draft.fbs },
        topics: draft.topics,
        will: BTreeMap::new(),
        periods: BTreeMap::new(),
        liveness: Default::default(),
    };
    FbootImport {
        profiles: vec![profile],
        notes: notes.into_vec(),
    }
}

// ---------------------------------------------------------------------------------------
// The MQTT FBs.

/// (VALUE_NAME parameter, the REAL port of its value) of each value the FB carries.
fn value_ports(two: bool) -> &'static [(&'static str, &'static str)] {
    if two {
        &[("VALUE_NAME_1", "VALUE_1"), ("VALUE_NAME_2", "VALUE_2")]
    } else {
        &[("VALUE_NAME", "VALUE")]
    }
}

struct MqttFb<'a> {
    instance: &'a str,
    fb_type: &'a str,
    role: Role,
    two: bool,
}

impl MqttFb<'_> {
    /// How notes name it: `MQTT_PUBLISHER PUB_SPEED`.
    fn what(&self) -> String {
        format!("{} {}", self.fb_type, self.instance)
    }
}

/// Where an input of an FB gets its value.
enum Param<'a> {
    Written(&'a str),
    /// Connected: from this output, at run time.
    Wired(&'a PortRef),
    /// Neither: None in DINASORE.
    Missing,
}

/// A connection wins over a parameter: it sets the input whenever its source runs.
fn param<'a>(resource: &'a Resource, fb: &str, port: &str) -> Param<'a> {
    if let Some(source) = resource.sources_of(fb, port).first() {
        return Param::Wired(source);
    }
    match resource.params.get(&(fb.to_owned(), port.to_owned())) {
        Some(value) => Param::Written(value),
        None => Param::Missing,
    }
}

/// The note on brokers: DINASORE connects each MQTT FB to its own HOST and PORT.
fn broker_note(resource: &Resource, mqtt: &[MqttFb<'_>], notes: &mut Notes) {
    let mut brokers: Vec<(String, Vec<&str>)> = Vec::new();
    for fb in mqtt {
        let (Param::Written(host), Param::Written(port)) = (
            param(resource, fb.instance, "HOST"),
            param(resource, fb.instance, "PORT"),
        ) else {
            continue;
        };
        // Those that cannot connect have their own note.
        let Some(port) = python_int(port).filter(|p| (1..=65_535).contains(p)) else {
            continue;
        };
        if host.is_empty() {
            continue;
        }
        let address = format!("{host}:{port}");
        match brokers.iter_mut().find(|(a, _)| *a == address) {
            Some((_, fbs)) => fbs.push(fb.instance),
            None => brokers.push((address, vec![fb.instance])),
        }
    }
    if brokers.len() > 1 {
        let list: Vec<String> = brokers
            .iter()
            .map(|(address, fbs)| format!("{address} ({})", fbs.join(", ")))
            .collect();
        notes.push(format!(
            "The MQTT FBs connect to {} brokers: {}. DINASORE connects each FB to its own \
             HOST and PORT, and the profile describes the device on one broker, fbbus's: \
             point every FB's HOST and PORT at it (two addresses of the same broker are \
             fine).",
            brokers.len(),
            list.join(", ")
        ));
    }
}

/// A STRING parameter the FB cannot do without; None (and a note) if it has none.
fn string_param<'a>(
    resource: &'a Resource,
    fb: &MqttFb<'_>,
    port: &str,
    notes: &mut Notes,
) -> Option<&'a str> {
    let what = fb.what();
    match param(resource, fb.instance, port) {
        Param::Written(value) => Some(value),
        Param::Wired((source_fb, source_port)) => {
            notes.push(format!(
                "{what}: its {port} comes from {source_fb}.{source_port} at run time, which the \
                 file does not say; skipped: map it by hand."
            ));
            None
        }
        Param::Missing => {
            notes.push(format!(
                "{what}: it has no {port} parameter, so {port} is None in DINASORE and the FB \
                 fails on it; skipped: set it in 4diac IDE."
            ));
            None
        }
    }
}

/// Whether the FB's connection can succeed: HOST and PORT given and usable (a note
/// otherwise, or when they come from another FB).
fn connects(resource: &Resource, fb: &MqttFb<'_>, notes: &mut Notes) -> bool {
    let what = fb.what();
    let fails = "so paho's connect() raises at its INIT and the FB stops; skipped";
    for port in ["HOST", "PORT"] {
        match param(resource, fb.instance, port) {
            Param::Missing => {
                notes.push(format!(
                    "{what}: it has no {port} parameter, {fails}: set HOST and PORT in 4diac \
                     IDE."
                ));
                return false;
            }
            Param::Wired((source_fb, source_port)) => notes.push(format!(
                "{what}: its {port} comes from {source_fb}.{source_port} at run time: make \
                 sure it names fbbus's broker."
            )),
            Param::Written(host) if port == "HOST" => {
                if host.is_empty() {
                    notes.push(format!(
                        "{what}: its HOST is empty, {fails}: write the broker's address."
                    ));
                    return false;
                }
            }
            Param::Written(number) => {
                if !python_int(number).is_some_and(|p| (1..=65_535).contains(&p)) {
                    notes.push(format!(
                        "{what}: its PORT {number:?} is no TCP port, {fails}: write the \
                         broker's port."
                    ));
                    return false;
                }
            }
        }
    }
    true
}

/// One MQTT FB: its parameters, then its part of the profile.
fn derive(
    fb: &MqttFb<'_>,
    resource: &Resource,
    published: &BTreeMap<&str, &str>,
    draft: &mut Draft<'_>,
    notes: &mut Notes,
) {
    let what = fb.what();
    if fb.instance.contains('.') {
        notes.push(format!(
            "{what}: its name has a '.' (an FB inside a subapplication), and DINASORE splits \
             FB.PORT at the first '.', so none of its parameters reaches it; skipped: put it \
             at the top level of the application."
        ));
        return;
    }
    if !connects(resource, fb, notes) {
        return;
    }
    let Some(topic) = string_param(resource, fb, "TOPIC", notes) else {
        return;
    };
    let mut names: Vec<&str> = Vec::new();
    for (name_port, _) in value_ports(fb.two) {
        let Some(name) = string_param(resource, fb, name_port, notes) else {
            return;
        };
        if !is_identifier(name) {
            notes.push(format!(
                "{what}: its {name_port} {name:?} is a payload key, which is a port name in \
                 the profile and must be an IEC 61131-3 identifier; skipped: rename it in \
                 4diac IDE, in every FB that uses it."
            ));
            return;
        }
        names.push(name);
    }
    match fb.role {
        Role::Publisher => publisher(fb, resource, topic, &names, draft, notes),
        Role::Subscriber => subscriber(fb, topic, &names, published, draft, notes),
    }
}

/// The key of a DINASORE payload is the port's name: a port named otherwise would not
/// read the device's messages.
const KEY_NAMED: &str = "a DINASORE payload's key is its port's name, the FB's VALUE_NAME: \
                         rename the VALUE_NAME in 4diac IDE, in every FB that uses it";

/// The FB as the profile's builders take it: data ports named by `names`, REAL, and for
/// two distinct names an event `event` (or a free variant of it) carrying both; one name
/// (or the same twice) is the data port itself.
fn endpoint<'a>(
    fb: &'a MqttFb<'a>,
    what: &'a str,
    names: &[&str],
    event: &str,
    device: &str,
    notes: &mut Notes,
) -> Endpoint<'a> {
    let shape = match names {
        [first, second] if first != second => {
            let event_name = unique(event.to_owned(), |e| names.contains(&e), 64);
            if event_name != event {
                notes.push(format!(
                    "{what}: one of its VALUE_NAMEs is {event}, the name of its event, so the \
                     event is {event_name} in profile {device}."
                ));
            }
            Shape::Event(event_name)
        }
        _ => {
            let key = names.first().copied().unwrap_or_default();
            if names.len() == 2 {
                let carried = match fb.role {
                    Role::Publisher => "its message {\"KEY\": ...} carries only VALUE_2",
                    Role::Subscriber => "it reads that one key into both VALUE_1 and VALUE_2",
                }
                .replace("KEY", key);
                notes.push(format!(
                    "{what}: VALUE_NAME_1 and VALUE_NAME_2 are both {key:?}: {carried}, so its \
                     FB in profile {device} has the one data port {key}."
                ));
            }
            Shape::Data
        }
    };
    let mut values: Vec<ValuePort> = Vec::new();
    for name in names {
        if values.iter().all(|v| v.name != *name) {
            values.push(ValuePort {
                name: (*name).to_owned(),
                ty: Ok(Derived {
                    ty: DataType::Elementary(ElementaryType::Real),
                    mismatch: None,
                }),
                fixed: Some(KEY_NAMED),
            });
        }
    }
    Endpoint {
        what,
        instance: fb.instance,
        fb_type: fb.fb_type,
        shape,
        values,
    }
}

/// An MQTT_PUBLISHER(_2): an output of the profile.
fn publisher(
    fb: &MqttFb<'_>,
    resource: &Resource,
    t: &str,
    names: &[&str],
    draft: &mut Draft<'_>,
    notes: &mut Notes,
) {
    let what = fb.what();
    match topic_kind(t) {
        TopicKind::NotAFilter | TopicKind::Wildcard => {
            notes.push(format!(
                "{what}: its TOPIC {t:?} is not a topic one can publish on (empty or a \
                 wildcard), so paho raises at its first RUN and the FB stops; skipped: fix \
                 TOPIC in 4diac IDE."
            ));
            return;
        }
        TopicKind::Dollar => {
            notes.push(format!(
                "{what}: its TOPIC {t:?} starts with $, which brokers keep for themselves; \
                 skipped: use a topic of its own."
            ));
            return;
        }
        TopicKind::Typed => {
            notes.push(format!(
                "{what}: its TOPIC {t:?} is in a typed namespace, where a publication is typed \
                 by the interface of the device the topic names and DINASORE's string values \
                 (\"3.0\") are refused; skipped: publish on a topic of its own, which the \
                 profile maps."
            ));
            return;
        }
        TopicKind::Own => {}
    }
    if !mappable_topic(&what, t, draft, notes) {
        return;
    }
    for (_, value) in value_ports(fb.two) {
        if matches!(param(resource, fb.instance, value), Param::Missing) {
            notes.push(format!(
                "{what}: {}.{value} is neither connected nor given a value, so it publishes \
                 \"None\" for it, which the broker refuses as a REAL: connect it in 4diac IDE.",
                fb.instance
            ));
        }
    }
    let endpoint = endpoint(fb, &what, names, "RUN", &draft.device, notes);
    output(draft, &endpoint, t, notes);
}

/// An MQTT_SUBSCRIBER(_2): an input of the profile.
fn subscriber(
    fb: &MqttFb<'_>,
    t: &str,
    names: &[&str],
    published: &BTreeMap<&str, &str>,
    draft: &mut Draft<'_>,
    notes: &mut Notes,
) {
    let what = fb.what();
    let refused = match topic_kind(t) {
        TopicKind::NotAFilter => Some(format!(
            "{what}: its TOPIC {t:?} is not a topic filter, so paho raises at its INIT and \
             the FB stops; skipped: fix TOPIC in 4diac IDE."
        )),
        TopicKind::Wildcard => Some(format!(
            "{what}: its TOPIC {t:?} is a wildcard filter: it is subscribed, but the FB \
             compares each message's topic with TOPIC as a string, so it reads nothing; \
             skipped: one topic per FB."
        )),
        TopicKind::Dollar => Some(dollar_input(&what, t)),
        TopicKind::Typed => Some(match TypedTopic::parse(t) {
            Some(typed) if typed.encoding == Encoding::Dinasore => format!(
                "{what}: it reads the typed topic {t:?} directly, typed by the interface of \
                 device {:?}: nothing to map (its VALUE_NAMEs must be {} or, for an event, \
                 names of its WITH data).",
                typed.device, typed.port
            ),
            Some(typed) => format!(
                "{what}: it reads {t:?}, whose {} payloads are not the JSON objects it \
                 reads, so the FB fails on the first one; skipped: read {:?} instead.",
                typed.encoding.namespace(),
                typed.in_encoding(Encoding::Dinasore)
            ),
            None => format!(
                "{what}: its TOPIC {t:?} is in a typed namespace but is not \
                 <namespace>/<device>/<FB>/<PORT>, so nothing is published there; skipped."
            ),
        }),
        TopicKind::Own => None,
    };
    if let Some(note) = refused {
        notes.push(note);
        return;
    }
    let Some(publisher) = published.get(t) else {
        if !mappable_topic(&what, t, draft, notes) {
            return;
        }
        let endpoint = endpoint(fb, &what, names, "READ_O", &draft.device, notes);
        input(draft, &endpoint, t, notes);
        return;
    };
    let endpoint = endpoint(fb, &what, names, "READ_O", &draft.device, notes);
    unmapped_input(draft, &endpoint, notes);
    // The device's own output: mapping it as an input too would make one topic both, which
    // a profile refuses, and keep its own publisher off it.
    notes.push(format!(
        "{what} reads topic {t:?}, which {publisher} of the same file publishes: DINASORE \
         reaches itself through the broker as before, so the topic is not mapped as an input \
         (its port stays in the interface)."
    ));
}

#[cfg(test)]
mod tests;

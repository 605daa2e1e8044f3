//! The profile being built for one device, shared by both importers: the names of its
//! device, FBs and ports, the checks a topic passes before it is mapped, and the one
//! function per direction that puts an MQTT FB into it: [`output`] for what the device
//! publishes, [`input`] for what it reads. A FORTE `PUBLISH_n` and a DINASORE
//! `MQTT_PUBLISHER` differ in how they are read, not in what they become, so what they
//! become is written once, here.

use std::collections::{BTreeMap, BTreeSet};

use super::names::PortNames;
use super::note::Notes;
use super::typing::Derived;
use crate::interface::{is_identifier, Event, FbInterface};
use crate::profile::TopicFile;
use crate::topic::{self, filter};

/// The profile being built for one device.
pub(super) struct Draft<'n> {
    pub(super) device: String,
    pub(super) fbs: BTreeMap<String, FbInterface<String>>,
    /// FBs named by a typed topic, not by an instance.
    pub(super) typed_fbs: BTreeSet<String>,
    pub(super) topics: Vec<TopicFile>,
    /// Topic → the port it is mapped onto.
    mapped: BTreeMap<String, String>,
    /// The user's names for generated ports.
    pub(super) names: &'n mut PortNames,
}

impl<'n> Draft<'n> {
    pub(super) fn new(device: String, names: &'n mut PortNames) -> Draft<'n> {
        Draft {
            device,
            fbs: BTreeMap::new(),
            typed_fbs: BTreeSet::new(),
            topics: Vec::new(),
            mapped: BTreeMap::new(),
            names,
        }
    }

    pub(super) fn has_topic(&self, topic: &str) -> Option<&str> {
        self.mapped.get(topic).map(String::as_str)
    }

    pub(super) fn map_topic(&mut self, topic: &str, port: String, from: Option<String>) {
        self.mapped.insert(topic.to_owned(), port.clone());
        self.topics.push(TopicFile {
            topic: topic.to_owned(),
            port,
            from,
            encoding: None,
        });
    }
}

/// A usable device id for a name (a client id): forbidden characters (`/ + # $`,
/// controls) become `_`, and it is cut to the longest id; `fallback` if nothing is left.
pub(super) fn sanitized_device(name: &str, fallback: &str) -> String {
    let mut out = String::new();
    for c in name.chars() {
        let c = if c.is_control() || "/+#$".contains(c) {
            '_'
        } else {
            c
        };
        if out.len() + c.len_utf8() > topic::MAX_DEVICE_ID {
            break;
        }
        out.push(c);
    }
    if out.is_empty() {
        out.push_str(fallback);
    }
    out
}

/// An IEC 61131-3 identifier for a name: other characters become `_`, a leading digit gets
/// a `_` before it, and it is cut to `max` bytes.
pub(super) fn sanitized_identifier(name: &str, max: usize) -> String {
    let mut out: String = name
        .chars()
        .map(|c| if c.is_ascii_alphanumeric() { c } else { '_' })
        .collect();
    if !out.starts_with(|c: char| c.is_ascii_alphabetic() || c == '_') {
        out.insert(0, '_');
    }
    truncate(&mut out, max);
    out
}

/// Cuts `text` to at most `max` bytes, at a character boundary.
pub(super) fn truncate(text: &mut String, max: usize) {
    let mut at = max.min(text.len());
    while !text.is_char_boundary(at) {
        at -= 1;
    }
    text.truncate(at);
}

/// `name`, or `name_2`, `name_3`, ... : the first not in `taken`.
pub(super) fn unique(name: String, taken: impl Fn(&str) -> bool, max: usize) -> String {
    if !taken(&name) {
        return name;
    }
    let mut base = name;
    truncate(&mut base, max.saturating_sub(12));
    (2..)
        .map(|k| format!("{base}_{k}"))
        .find(|candidate| !taken(candidate))
        .unwrap_or(base)
}

/// Every port name of an FB interface.
pub(super) fn has_port(fb: &FbInterface<String>, port: &str) -> bool {
    fb.events_out.contains_key(port)
        || fb.events_in.contains_key(port)
        || fb.data_out.contains_key(port)
        || fb.data_in.contains_key(port)
}

/// The interface name of an instance (`what` names it in notes): the instance name if it
/// is an identifier not yet taken, else a sanitized or numbered one, with a note.
pub(super) fn instance_name(
    what: &str,
    instance: &str,
    draft: &Draft<'_>,
    notes: &mut Notes,
) -> String {
    const MAX: usize = 64;
    let name = if is_identifier(instance) {
        instance.to_owned()
    } else {
        sanitized_identifier(instance, MAX)
    };
    let unique_name = unique(name.clone(), |n| draft.fbs.contains_key(n), MAX);
    if name != instance {
        notes.push(format!(
            "{what}: its name is not an IEC 61131-3 identifier, so its FB in profile {} is \
             {unique_name}.",
            draft.device
        ));
    } else if unique_name != name {
        notes.push(format!(
            "{what}: another FB of profile {} already has its name (one from another resource \
             or named by a typed topic), so its FB there is {unique_name}.",
            draft.device
        ));
    }
    unique_name
}

/// Whether topic `t` of the FB `what` may be mapped at all; notes why not.
pub(super) fn mappable_topic(what: &str, t: &str, draft: &Draft<'_>, notes: &mut Notes) -> bool {
    if t.starts_with(topic::BROKER_NAMESPACE) {
        notes.push(format!(
            "{what}: its topic {t:?} is in fbbus/, the broker's own namespace; skipped: use \
             a topic of its own."
        ));
        return false;
    }
    if let Some(port) = draft.has_topic(t) {
        notes.push(format!(
            "{what}: its topic {t:?} is already mapped onto {port} in profile {}; a topic \
             maps onto one port; skipped: map it by hand if it is another.",
            draft.device
        ));
        return false;
    }
    true
}

/// What a topic of an MQTT FB is, by the checks both runtimes make in this order; each
/// runtime says in its own words what its FB does with one it cannot map.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(super) enum TopicKind {
    /// Not even a topic filter: subscribing and publishing both fail.
    NotAFilter,
    /// A filter with wildcards: no topic name to publish on or to map.
    Wildcard,
    /// `$...`: the broker's, not typed data.
    Dollar,
    /// In a typed namespace (`fb/`, `dinasore/`, `fbdk/`): typed by the broker already.
    Typed,
    /// A topic of the device's own, to map (if [`mappable_topic`] agrees).
    Own,
}

pub(super) fn topic_kind(t: &str) -> TopicKind {
    if !filter::valid_filter(t) {
        TopicKind::NotAFilter
    } else if !filter::valid_topic(t) {
        TopicKind::Wildcard
    } else if filter::is_dollar(t) {
        TopicKind::Dollar
    } else if topic::is_typed_namespace(t) {
        TopicKind::Typed
    } else {
        TopicKind::Own
    }
}

/// The note on an FB that reads a `$` topic, whichever runtime.
pub(super) fn dollar_input(what: &str, t: &str) -> String {
    format!("{what}: it reads {t:?}, a $ topic, not typed data; skipped.")
}

/// Whether an FB's message is an event carrying its values as WITH data (the event's
/// generated name) or, for one value, the data port itself.
pub(super) enum Shape {
    Event(String),
    Data,
}

/// One value port of an MQTT FB as generated: its name, its type (or why the boot file
/// does not tell it), and, when the wire fixes its name, why it cannot be renamed.
pub(super) struct ValuePort {
    pub(super) name: String,
    pub(super) ty: Result<Derived, String>,
    pub(super) fixed: Option<&'static str>,
}

/// An MQTT FB to put into the profile: `what` names it in notes.
pub(super) struct Endpoint<'a> {
    pub(super) what: &'a str,
    pub(super) instance: &'a str,
    pub(super) fb_type: &'a str,
    pub(super) shape: Shape,
    pub(super) values: Vec<ValuePort>,
}

/// Where an FB went in the profile: its FB name, the port its topic maps onto, and its
/// value ports' names and types (None: untyped) in order.
pub(super) struct Added {
    pub(super) fb: String,
    pub(super) port: String,
    pub(super) values: Vec<(String, Option<crate::types::DataType>)>,
}

#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Direction {
    Output,
    Input,
}

/// An FB whose messages the device publishes on `t`: an output of the profile, its topic
/// mapped onto its event (or its one data port).
pub(super) fn output(
    draft: &mut Draft<'_>,
    fb: &Endpoint<'_>,
    t: &str,
    notes: &mut Notes,
) -> Added {
    let added = add_fb(draft, fb, Direction::Output, notes);
    draft.map_topic(t, added.port.clone(), None);
    added
}

/// An FB that reads `t`: an input of the profile, its topic mapped onto its event (or its
/// one data port), with the blocking note asking for the `from` no boot file says. The
/// index of that note comes back with the FB, for an importer that learns later that the
/// topic is its own.
pub(super) fn input(
    draft: &mut Draft<'_>,
    fb: &Endpoint<'_>,
    t: &str,
    notes: &mut Notes,
) -> (Added, usize) {
    let added = add_fb(draft, fb, Direction::Input, notes);
    let note = notes.blocking(
        &draft.device,
        format!(
            "{} reads topic {t:?}: set `from` of that topic in profile {} to the typed \
             output that feeds it (<device>/<FB>/<PORT>).",
            fb.what, draft.device
        ),
    );
    draft.map_topic(t, added.port.clone(), None);
    (added, note)
}

/// An FB that reads a topic the same import publishes: its ports stay in the interface,
/// its topic is not mapped (one topic is not both a device's output and an input).
pub(super) fn unmapped_input(draft: &mut Draft<'_>, fb: &Endpoint<'_>, notes: &mut Notes) -> Added {
    add_fb(draft, fb, Direction::Input, notes)
}

/// Puts the FB into the interface under its instance's name, its ports named as the user
/// asks, a blocking note for each value port without a type (it stays in the WITH list,
/// so the profile is refused until its type is written) and an advisory one for each
/// whose wired pins disagree on the type.
fn add_fb(
    draft: &mut Draft<'_>,
    fb: &Endpoint<'_>,
    direction: Direction,
    notes: &mut Notes,
) -> Added {
    let name = instance_name(fb.what, fb.instance, draft, notes);
    let mut named: Vec<(String, String)> = Vec::new();
    for value in &fb.values {
        let new = match value.fixed {
            Some(why) => {
                draft.names.fixed(&name, &value.name, why);
                value.name.clone()
            }
            None => draft.names.name(&name, &value.name),
        };
        named.push((value.name.clone(), new));
    }
    let event = match &fb.shape {
        Shape::Event(event) => {
            let new = draft.names.name(&name, event);
            named.push((event.clone(), new.clone()));
            Some(new)
        }
        Shape::Data => None,
    };
    draft.names.check_fb(&draft.device, &name, &named);
    let data_key = match direction {
        Direction::Output => "data_out",
        Direction::Input => "data_in",
    };
    let mut data = BTreeMap::new();
    let mut values = Vec::new();
    for (value, (_, port)) in fb.values.iter().zip(&named) {
        match &value.ty {
            Ok(derived) => {
                if let Some(mismatch) = &derived.mismatch {
                    notes.push(format!(
                        "{}: {mismatch}; the profile keeps {}, the type of the data's \
                         source: check the width the application means.",
                        fb.what, derived.ty
                    ));
                }
                data.insert(port.clone(), derived.ty.to_string());
                values.push((port.clone(), Some(derived.ty)));
            }
            Err(why) => {
                notes.blocking(
                    &draft.device,
                    untyped_note(
                        fb.what,
                        fb.instance,
                        &value.name,
                        why,
                        &format!(
                            "set {data_key}.{port} of FB {name} in profile {}",
                            draft.device
                        ),
                    ),
                );
                values.push((port.clone(), None));
            }
        }
    }
    let ports: Vec<String> = values.iter().map(|(p, _)| p.clone()).collect();
    let (events, mapped_port) = match event {
        Some(event) => {
            let port = format!("{name}.{event}");
            (BTreeMap::from([(event, Event { with: ports })]), port)
        }
        None => {
            let first = ports.first().cloned().unwrap_or_default();
            (BTreeMap::new(), format!("{name}.{first}"))
        }
    };
    let mut interface = FbInterface {
        fb_type: Some(fb.fb_type.to_owned()),
        events_out: BTreeMap::new(),
        events_in: BTreeMap::new(),
        data_out: BTreeMap::new(),
        data_in: BTreeMap::new(),
    };
    match direction {
        Direction::Output => (interface.events_out, interface.data_out) = (events, data),
        Direction::Input => (interface.events_in, interface.data_in) = (events, data),
    }
    draft.fbs.insert(name.clone(), interface);
    Added {
        fb: name,
        port: mapped_port,
        values,
    }
}

/// The note on a port whose type is not derivable; `fix` says what to write where.
pub(super) fn untyped_note(what: &str, instance: &str, port: &str, why: &str, fix: &str) -> String {
    format!(
        "{what}: the type of {instance}.{port} is not derivable from the boot file ({why}); \
         {fix}."
    )
}

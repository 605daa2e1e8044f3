//! FORTE's side of the import: the communication FBs grouped by MQTT client id, one
//! profile per group, each `PUBLISH_n` an output and each `SUBSCRIBE_n` an input (through
//! the builders of `draft`, which DINASORE's importer shares), and the notes on what FORTE
//! will not connect as the file asks.

use std::collections::{BTreeMap, BTreeSet};

use super::comm::{CommFb, Service};
use super::draft::{
    dollar_input, has_port, input, mappable_topic, output, sanitized_device, topic_kind, unique,
    unmapped_input, untyped_note, Draft, Endpoint, Shape, TopicKind, ValuePort,
};
use super::names::PortNames;
use super::note::Notes;
use super::resource::Resource;
use super::typing::{receiving_type, sending_type, Derived};
use super::{TypeTable, FORTE_MAX_PAYLOAD};
use crate::codec::Encoding;
use crate::interface::{is_identifier, Event, FbInterface, Interface};
use crate::profile::{IdentityFile, ProfileFile, Speaks};
use crate::topic::{self, TypedTopic};
use crate::types::{DataType, ElementaryType};

/// A topic a `PUBLISH_n` of the import publishes: its typed output and value ports.
struct Published {
    /// `device/FB/PORT`.
    source: String,
    what: String,
    values: Vec<(String, Option<DataType>)>,
}

/// An input topic whose `from` the user must set, and the note that says so.
struct PendingFrom {
    note: usize,
    topic: String,
    what: String,
    device: String,
    fb: String,
    values: Vec<(String, Option<DataType>)>,
}

/// The profiles of the communication FBs, one per client id.
pub(super) fn build_profiles(
    comm: &[CommFb<'_>],
    types: &TypeTable,
    notes: &mut Notes,
    names: &mut PortNames,
) -> Vec<ProfileFile> {
    // Client ids in the order they first appear.
    let mut groups: Vec<(&str, Vec<&CommFb<'_>>)> = Vec::new();
    let mut group_of: BTreeMap<&str, usize> = BTreeMap::new();
    for fb in comm {
        let at = *group_of.entry(fb.client_id.as_str()).or_insert_with(|| {
            groups.push((fb.client_id.as_str(), Vec::new()));
            groups.len() - 1
        });
        if let Some((_, fbs)) = groups.get_mut(at) {
            fbs.push(fb);
        }
    }
    connection_notes(&groups, notes);

    let mut devices: BTreeSet<String> = BTreeSet::new();
    let mut pending: Vec<PendingFrom> = Vec::new();
    // Own output topics, for the notes on input topics.
    let mut published: BTreeMap<String, Published> = BTreeMap::new();
    let mut profiles = Vec::new();
    for (client_id, fbs) in &groups {
        if fbs.iter().all(|fb| fb.skipped.is_some()) {
            for note in fbs.iter().filter_map(|fb| fb.skipped.clone()) {
                notes.push(note);
            }
            notes.push(format!(
                "Client id {client_id:?}: none of its FBs can be mapped, so it has no profile."
            ));
            continue;
        }
        let usable = topic::is_device_id(client_id);
        let device = if usable && !devices.contains(*client_id) {
            (*client_id).to_owned()
        } else {
            let base = sanitized_device(client_id, "forte");
            let device = unique(base, |d| devices.contains(d), topic::MAX_DEVICE_ID);
            let why = if usable {
                "is the device id of another profile of this import".to_owned()
            } else {
                format!(
                    "is not a usable device id (1-{} bytes, none of / + # $, no control \
                     characters)",
                    topic::MAX_DEVICE_ID
                )
            };
            let then = match usable {
                true => "rename the device if you like",
                // The broker refuses such a client id at CONNECT (identifier rejected):
                // a client id becomes topic levels and log fields.
                false => {
                    "but fbbus refuses this client id at CONNECT, so change it in the \
                     FBs' ID parameters (and in identity.client_id) before the device \
                     can connect"
                }
            };
            notes.push(format!(
                "Client id {client_id:?} {why}: its profile's device is {device:?}, with the \
                 client id as identity.client_id; {then}."
            ));
            device
        };
        devices.insert(device.clone());
        let mut draft = Draft::new(device, names);
        for fb in fbs {
            match (&fb.skipped, fb.service) {
                (Some(note), _) => notes.push(note.clone()),
                (None, Service::Publish) => publish(fb, &mut draft, types, notes, &mut published),
                (None, Service::Subscribe) => {
                    subscribe(fb, &mut draft, types, notes, &published, &mut pending)
                }
            }
        }
        if draft.fbs.is_empty() {
            notes.push(format!(
                "Client id {client_id:?}: none of its FBs can be mapped, so it has no profile."
            ));
            continue;
        }
        let time_units = draft.fbs.values().any(|fb| {
            fb.data_out.values().chain(fb.data_in.values()).any(|t| {
                t.parse::<DataType>().is_ok_and(|t| {
                    let (DataType::Elementary(e) | DataType::Array(e, _)) = t;
                    matches!(
                        e,
                        ElementaryType::Date
                            | ElementaryType::TimeOfDay
                            | ElementaryType::DateAndTime
                    )
                })
            })
        });
        if time_units {
            notes.push(format!(
                "Profile {}: it has DATE, TIME_OF_DAY or DATE_AND_TIME ports, read in FORTE \
                 3.x's nanoseconds; set speaks.fbdk_time_unit = \"ms\" if the device runs \
                 FORTE 2.0.x.",
                draft.device
            ));
        }
        profiles.push(ProfileFile {
            device: draft.device.clone(),
            runtime: Some("forte".into()),
            identity: IdentityFile {
                client_id: Some((*client_id).to_owned()),
                ..IdentityFile::default()
            },
            speaks: Speaks {
                encoding: Encoding::Fbdk.namespace().into(),
                max_payload: FORTE_MAX_PAYLOAD,
                qos: 0,
                ..Speaks::default()
            },
            interface: Interface { fbs: draft.fbs },
            topics: draft.topics,
            will: BTreeMap::new(),
            periods: BTreeMap::new(),
            liveness: Default::default(),
        });
    }
    for pending in pending {
        let Some(source) = published.get(&pending.topic) else {
            continue;
        };
        own_topic(&pending, source, &mut profiles, notes);
    }
    profiles
}

/// Notes on client ids FORTE will not connect as the file asks.
fn connection_notes(groups: &[(&str, Vec<&CommFb<'_>>)], notes: &mut Notes) {
    if groups.len() > 1 {
        const LISTED: usize = 8;
        let mut ids: Vec<String> = groups
            .iter()
            .take(LISTED)
            .map(|(id, _)| format!("{id:?}"))
            .collect();
        if groups.len() > LISTED {
            ids.push("...".into());
        }
        notes.push(format!(
            "The boot file uses {} MQTT client ids ({}): FORTE 2.0.x keeps one MQTT client \
             per runtime and fails the INIT of FBs with another, FORTE 3.x one per broker \
             address; a profile is derived for each.",
            groups.len(),
            ids.join(", ")
        ));
    }
    let mut by_address: BTreeMap<&str, &str> = BTreeMap::new();
    for (client_id, fbs) in groups {
        let addresses: BTreeSet<&str> = fbs.iter().map(|fb| fb.address.as_str()).collect();
        if addresses.len() > 1 {
            notes.push(format!(
                "Client id {client_id:?} connects to {} broker addresses ({}): a profile \
                 describes its connection to fbbus's broker; remove the FBs that use another \
                 broker from its profile.",
                addresses.len(),
                addresses.iter().copied().collect::<Vec<_>>().join(", ")
            ));
        }
        for address in addresses {
            match by_address.get(address) {
                Some(first) if first != client_id => notes.push(format!(
                    "Client ids {first:?} and {client_id:?} use the same broker address \
                     {address}: FORTE 3.x connects one client per broker address, so the \
                     INIT of the FBs of {client_id:?} fails; give them one client id."
                )),
                Some(_) => {}
                None => {
                    by_address.insert(address, client_id);
                }
            }
        }
    }
}

/// A `SUBSCRIBE_n` reading a topic a `PUBLISH_n` of the same import publishes: FORTE to
/// FORTE through the broker as before, so its input topic is not mapped (mapping it
/// would make one topic both a device's output and another's input, which a profile set
/// refuses) and its note no longer blocks. Where the two disagree on a value's type, the
/// subscriber's port takes the publisher's (the bytes on the wire are the publisher's),
/// with a note naming both.
fn own_topic(
    pending: &PendingFrom,
    source: &Published,
    profiles: &mut [ProfileFile],
    notes: &mut Notes,
) {
    let topic = &pending.topic;
    if let Some(note) = notes.get_mut(pending.note) {
        note.text = format!(
            "{} reads topic {topic:?}, which {} publishes in this boot file: FORTE to FORTE \
             through the broker as before, so the topic is not mapped as an input (its port \
             stays in the interface).",
            pending.what, source.source
        );
        note.blocks = None;
    }
    for profile in profiles.iter_mut() {
        let fbs = &profile.interface.fbs;
        profile.topics.retain(|t| {
            let input = t.port.split_once('.').is_some_and(|(fb, port)| {
                fbs.get(fb)
                    .is_some_and(|f| f.events_in.contains_key(port) || f.data_in.contains_key(port))
            });
            !(t.topic == *topic && input)
        });
    }
    let Some(profile) = profiles.iter_mut().find(|p| p.device == pending.device) else {
        return;
    };
    let Some(fb) = profile.interface.fbs.get_mut(&pending.fb) else {
        return;
    };
    for ((port, read), (sent_port, sent)) in pending.values.iter().zip(&source.values) {
        let (Some(read), Some(sent)) = (read, sent) else {
            continue;
        };
        if read == sent {
            continue;
        }
        fb.data_in.insert(port.clone(), sent.to_string());
        notes.push(format!(
            "{} reads topic {topic:?} into {}.{port} as {read} (the type of what it is wired \
             to), where {} sends {sent_port} as {sent}: the profile keeps {sent}, the type of \
             the data's source; check the width the application means.",
            pending.what, pending.fb, source.what
        ));
    }
}

/// A PUBLISH_n: an output of the profile.
fn publish(
    fb: &CommFb<'_>,
    draft: &mut Draft<'_>,
    types: &TypeTable,
    notes: &mut Notes,
    published: &mut BTreeMap<String, Published>,
) {
    let what = fb.what();
    let t = fb.topic.as_str();
    match topic_kind(t) {
        TopicKind::NotAFilter | TopicKind::Wildcard | TopicKind::Dollar => {
            notes.push(format!(
                "{what}: its topic {t:?} is not a topic name one can publish on (empty, a \
                 wildcard, or $...), so its publications fail; skipped: fix the ID in 4diac \
                 IDE."
            ));
            return;
        }
        TopicKind::Typed => {
            publish_typed(fb, draft, types, notes);
            return;
        }
        TopicKind::Own => {}
    }
    if !mappable_topic(&what, t, draft, notes) {
        return;
    }
    let endpoint = endpoint(fb, &what, types);
    let added = output(draft, &endpoint, t, notes);
    published.entry(t.to_owned()).or_insert_with(|| Published {
        source: format!("{}/{}", draft.device, added.port.replace('.', "/")),
        what,
        values: added.values,
    });
}

/// A PUBLISH_n or SUBSCRIBE_n as the profile's builders take it: the event `REQ` with
/// `SD_1..SD_n` (`IND` with `RD_1..RD_n`), each typed by what it is wired to.
fn endpoint<'a>(fb: &'a CommFb<'a>, what: &'a str, types: &TypeTable) -> Endpoint<'a> {
    type Derive = fn(&Resource, &str, &str, &TypeTable) -> Result<Derived, String>;
    let (event, prefix, derive): (&str, &str, Derive) = match fb.service {
        Service::Publish => ("REQ", "SD", sending_type),
        Service::Subscribe => ("IND", "RD", receiving_type),
    };
    let values = (1..=fb.ports)
        .map(|i| {
            let name = format!("{prefix}_{i}");
            let ty = derive(fb.resource, fb.instance, &name, types);
            ValuePort {
                name,
                ty,
                fixed: None,
            }
        })
        .collect();
    Endpoint {
        what,
        instance: fb.instance,
        fb_type: fb.fb_type,
        shape: Shape::Event(event.to_owned()),
        values,
    }
}

/// A PUBLISH_n on a typed topic: not mapped, but its port must be in the interface.
fn publish_typed(fb: &CommFb<'_>, draft: &mut Draft<'_>, types: &TypeTable, notes: &mut Notes) {
    let what = fb.what();
    let t = fb.topic.as_str();
    let Some(typed) = TypedTopic::parse(t) else {
        notes.push(format!(
            "{what}: its topic {t:?} is in a typed namespace but is not \
             <namespace>/<device>/<FB>/<PORT>, so the broker refuses it; skipped: fix the \
             ID in 4diac IDE."
        ));
        return;
    };
    let fbdk_topic = typed.in_encoding(Encoding::Fbdk);
    if typed.encoding != Encoding::Fbdk {
        notes.push(format!(
            "{what}: it publishes fbdk[] bytes on {t:?}, which the broker reads as {} and \
             refuses; skipped: publish on {fbdk_topic:?} instead.",
            typed.encoding.namespace()
        ));
        return;
    }
    if typed.device != draft.device {
        notes.push(format!(
            "{what}: it publishes on {t:?}, in the namespace of device {:?}, not its own \
             ({:?}), which the broker refuses; skipped: publish in its own namespace.",
            typed.device, draft.device
        ));
        return;
    }
    if !is_identifier(typed.fb) || !is_identifier(typed.port) {
        notes.push(format!(
            "{what}: its typed topic {t:?} names an FB or port that is not an IEC 61131-3 \
             identifier, so no interface can have it; skipped."
        ));
        return;
    }
    let (fb_name, port) = (typed.fb.to_owned(), typed.port.to_owned());
    if draft.fbs.contains_key(&fb_name) && !draft.typed_fbs.contains(&fb_name) {
        notes.push(format!(
            "{what}: its typed topic {t:?} names FB {fb_name}, which is already another FB's \
             name in profile {}; skipped: rename one in 4diac IDE.",
            draft.device
        ));
        return;
    }
    let sd: Vec<String> = (1..=fb.ports).map(|i| format!("SD_{i}")).collect();
    // A PUBLISH_1's message is its one value: the data port itself.
    let new_ports: Vec<&String> = if fb.ports == 1 {
        vec![&port]
    } else {
        std::iter::once(&port).chain(&sd).collect()
    };
    let existing = draft.fbs.get(&fb_name);
    if let Some(taken) = new_ports
        .iter()
        .find(|p| existing.is_some_and(|e| has_port(e, p)))
    {
        notes.push(format!(
            "{what}: its typed topic {t:?} needs port {fb_name}.{taken}, which another FB \
             already gave profile {}; skipped: map it by hand.",
            draft.device
        ));
        return;
    }
    draft.typed_fbs.insert(fb_name.clone());
    notes.push(format!(
        "{what}: it publishes on the typed topic {t:?} itself, so no topic is mapped; the \
         interface of profile {} gets {fb_name}.{port}, the port that topic names.",
        draft.device
    ));
    let mut typed_ports = Vec::new();
    if fb.ports == 1 {
        match sending_type(fb.resource, fb.instance, "SD_1", types) {
            Ok(Derived { ty, .. }) => typed_ports.push((port.clone(), ty)),
            Err(why) => notes.push(untyped_note(
                &what,
                fb.instance,
                "SD_1",
                &why,
                &format!(
                    "add data_out.{port} of FB {fb_name} in profile {}, or the broker \
                     refuses its publications",
                    draft.device
                ),
            )),
        }
    } else {
        for p in &sd {
            match sending_type(fb.resource, fb.instance, p, types) {
                Ok(Derived { ty, .. }) => typed_ports.push((p.clone(), ty)),
                Err(why) => notes.push(untyped_note(
                    &what,
                    fb.instance,
                    p,
                    &why,
                    &format!(
                        "set data_out.{p} of FB {fb_name} in profile {}",
                        draft.device
                    ),
                )),
            }
        }
    }
    let entry = draft.fbs.entry(fb_name).or_insert_with(|| FbInterface {
        fb_type: None,
        events_out: BTreeMap::new(),
        events_in: BTreeMap::new(),
        data_out: BTreeMap::new(),
        data_in: BTreeMap::new(),
    });
    if fb.ports != 1 {
        entry.events_out.insert(port, Event { with: sd });
    }
    for (p, ty) in typed_ports {
        entry.data_out.insert(p, ty.to_string());
    }
}

/// A SUBSCRIBE_n: an input of the profile.
fn subscribe(
    fb: &CommFb<'_>,
    draft: &mut Draft<'_>,
    types: &TypeTable,
    notes: &mut Notes,
    published: &BTreeMap<String, Published>,
    pending: &mut Vec<PendingFrom>,
) {
    let what = fb.what();
    let t = fb.topic.as_str();
    let refused = match topic_kind(t) {
        TopicKind::NotAFilter => Some(format!(
            "{what}: its topic {t:?} is not a topic filter, so its subscription fails; \
             skipped: fix the ID in 4diac IDE."
        )),
        TopicKind::Wildcard => Some(format!(
            "{what}: it subscribes to the filter {t:?}; a profile maps topic names, one \
             port each; skipped: subscribe to one topic per FB."
        )),
        TopicKind::Dollar => Some(dollar_input(&what, t)),
        TopicKind::Typed => Some(match TypedTopic::parse(t) {
            Some(typed) if typed.encoding == Encoding::Fbdk => format!(
                "{what}: it reads the typed topic {t:?} directly, typed by the interface \
                 of device {:?}: nothing to map.",
                typed.device
            ),
            Some(typed) => format!(
                "{what}: it reads {t:?}, which carries {} payloads its fbdk[] layer \
                 cannot decode; skipped: read {:?} instead.",
                typed.encoding.namespace(),
                typed.in_encoding(Encoding::Fbdk)
            ),
            None => format!(
                "{what}: its topic {t:?} is in a typed namespace but is not \
                 <namespace>/<device>/<FB>/<PORT>, so nothing is published there; \
                 skipped."
            ),
        }),
        TopicKind::Own => None,
    };
    if let Some(note) = refused {
        notes.push(note);
        return;
    }
    let endpoint = endpoint(fb, &what, types);
    let (added, note) = if published.contains_key(t) && draft.has_topic(t).is_some() {
        // Its own profile publishes the topic: read back through the broker, as a reader
        // in another profile of the import is (`own_topic` says so and compares types).
        let added = unmapped_input(draft, &endpoint, notes);
        let note = notes.len();
        notes.push(format!(
            "{what} reads topic {t:?}, its own profile's output."
        ));
        (added, note)
    } else if mappable_topic(&what, t, draft, notes) {
        input(draft, &endpoint, t, notes)
    } else {
        return;
    };
    pending.push(PendingFrom {
        note,
        topic: t.to_owned(),
        what: what.clone(),
        device: draft.device.clone(),
        fb: added.fb,
        values: added.values,
    });
}

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

use std::collections::{BTreeMap, BTreeSet};

use super::{
    instance_name, mappable_topic, sanitized_device, unique, xml_items, Draft, FbootImport,
    PortRef, Resource, Tag, XmlItem,
};
use crate::codec::Encoding;
use crate::interface::{is_identifier, Event, FbInterface, Interface};
use crate::profile::{IdentityFile, ProfileFile, Speaks};
use crate::topic::{self, filter, TypedTopic};

/// The device id when nothing is left of the caller's once made usable.
const FALLBACK_DEVICE: &str = "dinasore";

/// Derives the profile of the DINASORE device `device` from its `data_model.fboot`.
///
/// Empty (no profile, no note) when the file has no DINASORE MQTT FB: it is no DINASORE
/// configuration with MQTT traffic (a FORTE boot file, say). Otherwise one profile, or
/// none and the notes saying why.
pub fn import_dinasore(text: &str, device: &str) -> FbootImport {
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
    let mut notes = Vec::new();
    if let Some(why) = config.refusal {
        notes.push(why);
        return FbootImport {
            profiles: Vec::new(),
            notes,
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
    let mut draft = Draft {
        device,
        fbs: BTreeMap::new(),
        typed_fbs: BTreeSet::new(),
        topics: Vec::new(),
        mapped: BTreeMap::new(),
    };
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
            notes,
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
        notes,
    }
}

// ---------------------------------------------------------------------------------------
// Reading the file as DINASORE reads it.

/// The FBs, parameters and connections DINASORE builds from the file, and the first
/// reason it runs none of them.
struct Config {
    resource: Resource,
    refusal: Option<String>,
}

/// Python's `readlines()` of a file opened as text: lines split after `\n`, `\r\n` or
/// `\r`, without their ends; a last line without an end is a line, an empty text none.
fn python_lines(text: &str) -> Vec<&str> {
    let mut lines = Vec::new();
    let mut rest = text;
    while !rest.is_empty() {
        let Some(at) = rest.find(['\r', '\n']) else {
            lines.push(rest);
            break;
        };
        let (line, end) = rest.split_at(at);
        lines.push(line);
        rest = end
            .strip_prefix("\r\n")
            .or_else(|| end.get(1..))
            .unwrap_or("");
    }
    lines
}

/// The first XML escape in a line (`&apos;`, `&#47;`), if any.
fn escape(line: &str) -> Option<&str> {
    line.match_indices('&').find_map(|(at, _)| {
        let rest = line.get(at..)?;
        let end = rest.find(';')?;
        let name = rest.get(1..end)?;
        let is_name = |c: char| c.is_ascii_alphanumeric() || c == '#';
        (!name.is_empty() && name.chars().all(is_name))
            .then(|| rest.get(..=end))
            .flatten()
    })
}

/// An attribute value as expat (ElementTree's parser) reads it, in a line DINASORE
/// splits into two parts: a literal tab read as a space. Such a line has no `;` but the
/// resource's, so no XML escape (`&apos;`, `&#47;`): an `&` there starts none, and expat
/// refuses it, as it refuses a `<`.
fn expat_value(raw: &str) -> Result<String, String> {
    if raw.contains('&') {
        return Err(
            "it has an '&' that starts no XML escape (4diac IDE writes an '&' of a parameter \
             as it is)"
                .into(),
        );
    }
    if raw.contains('<') {
        return Err("it has a '<'".into());
    }
    Ok(raw.replace('\t', " "))
}

/// One request as ElementTree parses it: its root element and the root's children, or
/// ElementTree's reason to refuse it.
fn element_tree(request: &str) -> Result<(Tag, Vec<Tag>), String> {
    let xml = request.trim_matches(|c| matches!(c, ' ' | '\t' | '\n' | '\r'));
    if !xml.starts_with('<') || !xml.ends_with('>') {
        return Err("there is text around the request".into());
    }
    let mut open: Vec<String> = Vec::new();
    let mut root = None;
    let mut children = Vec::new();
    for item in xml_items(xml, expat_value)? {
        match item {
            XmlItem::Start { tag, empty } => {
                let name = tag.name.clone();
                match (open.len(), &root) {
                    (0, Some(_)) => return Err("it has more than one root element".into()),
                    (0, None) => root = Some(tag),
                    (1, _) => children.push(tag),
                    _ => {}
                }
                if !empty {
                    open.push(name);
                }
            }
            XmlItem::End(name) => match open.pop() {
                Some(opened) if opened == name => {}
                Some(opened) => return Err(format!("<{opened}> is closed by </{name}>")),
                None => return Err(format!("</{name}> closes nothing")),
            },
        }
    }
    if let Some(unclosed) = open.last() {
        return Err(format!("<{unclosed}> is not closed"));
    }
    root.map(|root| (root, children))
        .ok_or_else(|| "it has no element".into())
}

/// `FB.PORT` as DINASORE splits it: at every dot, the first two parts.
fn dinasore_port(text: &str) -> Option<PortRef> {
    let mut parts = text.split('.');
    let (fb, port) = (parts.next()?, parts.next()?);
    Some((fb.to_owned(), port.to_owned()))
}

/// Builds DINASORE's configuration from the file in its two passes: every line's FBs
/// first, then every line's connections and parameters.
fn read(text: &str) -> Config {
    // One configuration, whatever the resource is called.
    let mut resource = Resource::default();
    let mut refusal = None;
    let mut requests = Vec::new();
    for (i, line) in python_lines(text).into_iter().enumerate() {
        let number = i + 1;
        let parts: Vec<&str> = line.split(';').collect();
        let [_, request] = parts.as_slice() else {
            refusal.get_or_insert_with(|| {
                let why = match escape(line) {
                    Some(escape) => format!(
                        "has the XML escape {escape} in a parameter (4diac IDE writes ' \" \
                         < > of a parameter so: a STRING written with quotes, 'line1/a', \
                         is &apos;line1/a&apos;), and DINASORE splits every line at each ';'"
                    ),
                    None => format!(
                        "has {} ';'-separated parts, not the 2 DINASORE splits every line \
                         into (a blank line, or a ';' in a parameter)",
                        parts.len()
                    ),
                };
                format!(
                    "Line {number} {why}: it finds the file in an invalid state and runs \
                     nothing of it (\"Awaiting deployment\"), so no profile is derived; write \
                     the parameters without those characters in 4diac IDE."
                )
            });
            continue;
        };
        match element_tree(request) {
            Ok((root, children)) => requests.push((number, root, children)),
            Err(why) => {
                refusal.get_or_insert_with(|| {
                    format!(
                        "Line {number} is not XML that DINASORE's parser (Python's ElementTree) \
                         reads: {why}. It does not catch that error, so it runs nothing of the \
                         file, and no profile is derived."
                    )
                });
            }
        }
    }
    // Pass 1: the FBs.
    for (order, (_, root, children)) in requests.iter().enumerate() {
        if root.attr("Action") != Some("CREATE") {
            continue;
        }
        for child in children.iter().filter(|c| c.name == "FB") {
            if let (Some(name), Some(fb_type)) = (child.attr("Name"), child.attr("Type")) {
                if fb_type != "EMB_RES" {
                    resource
                        .fbs
                        .insert(name.to_owned(), (order, fb_type.to_owned()));
                }
            }
        }
    }
    // Pass 2: connections and parameters, each a reason to stop if DINASORE raises on it.
    let mut raised = None;
    for (number, root, children) in &requests {
        let action = root.attr("Action");
        if !matches!(action, Some("CREATE" | "WRITE")) {
            continue;
        }
        for child in children.iter().filter(|c| c.name == "Connection") {
            if let Err(why) = apply(&mut resource, action == Some("WRITE"), child) {
                raised.get_or_insert_with(|| {
                    format!(
                        "Line {number}: {why}; DINASORE raises there while it builds its FBs \
                         from the file, so it runs nothing of it, and no profile is derived."
                    )
                });
            }
        }
    }
    Config {
        resource,
        refusal: refusal.or(raised),
    }
}

/// Applies a connection (`write`: a parameter) as DINASORE does; Err: why it raises.
fn apply(resource: &mut Resource, write: bool, connection: &Tag) -> Result<(), String> {
    let (Some(source), Some(destination)) =
        (connection.attr("Source"), connection.attr("Destination"))
    else {
        return Err("the connection lacks its Source or Destination".into());
    };
    let exists = |resource: &Resource, fb: &str| fb == "START" || resource.fbs.contains_key(fb);
    let to = dinasore_port(destination)
        .ok_or_else(|| format!("the Destination {destination:?} is not FB.PORT"))?;
    if !write {
        let from =
            dinasore_port(source).ok_or_else(|| format!("the Source {source:?} is not FB.PORT"))?;
        if !exists(resource, &from.0) {
            return Err(format!(
                "the connection comes from {}, an FB it does not have",
                from.0
            ));
        }
        resource.connect(from, to);
        return Ok(());
    }
    if !exists(resource, &to.0) {
        return Err(format!(
            "the WRITE goes to {}, an FB it does not have",
            to.0
        ));
    }
    if source == "$e" {
        // An event triggered from 4diac IDE, not a parameter.
        return Ok(());
    }
    if let Some((_, two)) = resource.fb_type(&to.0).and_then(mqtt_type) {
        let port = to.1.as_str();
        if port == "PORT" && python_int(source).is_none() {
            return Err(format!(
                "{}.PORT is {source:?}, which its int() cannot read (the port is a UINT)",
                to.0
            ));
        }
        let value_port = match two {
            false => port == "VALUE",
            true => port == "VALUE_1" || port == "VALUE_2",
        };
        // A publisher's VALUE is an input, a subscriber's an output: both REAL.
        if value_port && python_float(source).is_none() {
            return Err(format!(
                "{}.{port} is {source:?}, which its float() cannot read (the value is a REAL)",
                to.0
            ));
        }
    }
    resource.params.insert(to, source.to_owned());
    Ok(())
}

/// Python's `int()` of a text, saturated: None where it raises.
fn python_int(text: &str) -> Option<i128> {
    let t = text.trim();
    let (negative, digits) = match t.strip_prefix('-') {
        Some(d) => (true, d),
        None => (false, t.strip_prefix('+').unwrap_or(t)),
    };
    if !underscored_digits(digits) {
        return None;
    }
    let value = digits
        .bytes()
        .filter(u8::is_ascii_digit)
        .fold(0i128, |n, d| {
            n.saturating_mul(10).saturating_add(i128::from(d - b'0'))
        });
    Some(if negative { -value } else { value })
}

/// Python's `float()` of a text: None where it raises.
fn python_float(text: &str) -> Option<f64> {
    let t = text.trim();
    if t.contains('_') {
        // Underscores only between digits.
        let ok = t
            .split(|c: char| !c.is_ascii_digit() && c != '_')
            .all(|run| run.is_empty() || underscored_digits(run));
        if !ok {
            return None;
        }
        return t.replace('_', "").parse().ok();
    }
    t.parse().ok()
}

/// ASCII digits, with single underscores between them.
fn underscored_digits(text: &str) -> bool {
    !text.is_empty()
        && text
            .split('_')
            .all(|group| !group.is_empty() && group.bytes().all(|b| b.is_ascii_digit()))
}

// ---------------------------------------------------------------------------------------
// The MQTT FBs.

#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Role {
    Publisher,
    Subscriber,
}

/// DINASORE finds an FB type by its file name, exactly.
fn mqtt_type(fb_type: &str) -> Option<(Role, bool)> {
    match fb_type {
        "MQTT_PUBLISHER" => Some((Role::Publisher, false)),
        "MQTT_PUBLISHER_2" => Some((Role::Publisher, true)),
        "MQTT_SUBSCRIBER" => Some((Role::Subscriber, false)),
        "MQTT_SUBSCRIBER_2" => Some((Role::Subscriber, true)),
        _ => None,
    }
}

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
fn broker_note(resource: &Resource, mqtt: &[MqttFb<'_>], notes: &mut Vec<String>) {
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
    notes: &mut Vec<String>,
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
fn connects(resource: &Resource, fb: &MqttFb<'_>, notes: &mut Vec<String>) -> bool {
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
    draft: &mut Draft,
    notes: &mut Vec<String>,
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

/// The FB's ports: data ports named by `names`, REAL, and for two distinct names an
/// event `event` (or a free variant of it) with both; the port its topic maps onto.
fn ports(
    fb: &MqttFb<'_>,
    name: &str,
    names: &[&str],
    event: &str,
    draft: &Draft,
    notes: &mut Vec<String>,
) -> (BTreeMap<String, Event>, BTreeMap<String, String>, String) {
    let what = fb.what();
    let data: BTreeMap<String, String> = names
        .iter()
        .map(|n| ((*n).to_owned(), "REAL".to_owned()))
        .collect();
    match names {
        [first, second] if first != second => {
            let event_name = unique(event.to_owned(), |e| names.contains(&e), 64);
            if event_name != event {
                notes.push(format!(
                    "{what}: one of its VALUE_NAMEs is {event}, the name of its event, so the \
                     event is {event_name} in profile {}.",
                    draft.device
                ));
            }
            let with = names.iter().map(|n| (*n).to_owned()).collect();
            let events = BTreeMap::from([(event_name.clone(), Event { with })]);
            (events, data, format!("{name}.{event_name}"))
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
                     FB in profile {} has the one data port {key}.",
                    draft.device
                ));
            }
            (BTreeMap::new(), data, format!("{name}.{key}"))
        }
    }
}

/// An MQTT_PUBLISHER(_2): an output of the profile.
fn publisher(
    fb: &MqttFb<'_>,
    resource: &Resource,
    t: &str,
    names: &[&str],
    draft: &mut Draft,
    notes: &mut Vec<String>,
) {
    let what = fb.what();
    if !filter::valid_topic(t) {
        notes.push(format!(
            "{what}: its TOPIC {t:?} is not a topic one can publish on (empty or a \
             wildcard), so paho raises at its first RUN and the FB stops; skipped: fix TOPIC \
             in 4diac IDE."
        ));
        return;
    }
    if filter::is_dollar(t) {
        notes.push(format!(
            "{what}: its TOPIC {t:?} starts with $, which brokers keep for themselves; \
             skipped: use a topic of its own."
        ));
        return;
    }
    if topic::is_typed_namespace(t) {
        notes.push(format!(
            "{what}: its TOPIC {t:?} is in a typed namespace, where a publication is typed \
             by the interface of the device the topic names and DINASORE's string values \
             (\"3.0\") are refused; skipped: publish on a topic of its own, which the profile \
             maps."
        ));
        return;
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
    let name = instance_name(&what, fb.instance, draft, notes);
    let (events_out, data_out, port) = ports(fb, &name, names, "RUN", draft, notes);
    draft.fbs.insert(
        name,
        FbInterface {
            fb_type: Some(fb.fb_type.to_owned()),
            events_out,
            events_in: BTreeMap::new(),
            data_out,
            data_in: BTreeMap::new(),
        },
    );
    draft.map_topic(t, port, None);
}

/// An MQTT_SUBSCRIBER(_2): an input of the profile.
fn subscriber(
    fb: &MqttFb<'_>,
    t: &str,
    names: &[&str],
    published: &BTreeMap<&str, &str>,
    draft: &mut Draft,
    notes: &mut Vec<String>,
) {
    let what = fb.what();
    if !filter::valid_filter(t) {
        notes.push(format!(
            "{what}: its TOPIC {t:?} is not a topic filter, so paho raises at its INIT and the \
             FB stops; skipped: fix TOPIC in 4diac IDE."
        ));
        return;
    }
    if !filter::valid_topic(t) {
        notes.push(format!(
            "{what}: its TOPIC {t:?} is a wildcard filter: it is subscribed, but the FB \
             compares each message's topic with TOPIC as a string, so it reads nothing; \
             skipped: one topic per FB."
        ));
        return;
    }
    if filter::is_dollar(t) {
        notes.push(format!(
            "{what}: it reads {t:?}, a $ topic, not typed data; skipped."
        ));
        return;
    }
    if topic::is_typed_namespace(t) {
        match TypedTopic::parse(t) {
            Some(typed) if typed.encoding == Encoding::Dinasore => notes.push(format!(
                "{what}: it reads the typed topic {t:?} directly, typed by the interface of \
                 device {:?}: nothing to map (its VALUE_NAMEs must be {} or, for an event, \
                 names of its WITH data).",
                typed.device, typed.port
            )),
            Some(typed) => notes.push(format!(
                "{what}: it reads {t:?}, whose {} payloads are not the JSON objects it reads, \
                 so the FB fails on the first one; skipped: read {:?} instead.",
                typed.encoding.namespace(),
                typed.in_encoding(Encoding::Dinasore)
            )),
            None => notes.push(format!(
                "{what}: its TOPIC {t:?} is in a typed namespace but is not \
                 <namespace>/<device>/<FB>/<PORT>, so nothing is published there; skipped."
            )),
        }
        return;
    }
    let Some(publisher) = published.get(t) else {
        if !mappable_topic(&what, t, draft, notes) {
            return;
        }
        let port = add_subscriber(fb, names, draft, notes);
        notes.push(format!(
            "{what} reads topic {t:?}: set `from` of that topic in profile {} to the typed \
             output that feeds it (<device>/<FB>/<PORT>).",
            draft.device
        ));
        draft.map_topic(t, port, None);
        return;
    };
    add_subscriber(fb, names, draft, notes);
    // The device's own output: mapping it as an input too would make one topic both, which
    // a profile refuses, and keep its own publisher off it.
    notes.push(format!(
        "{what} reads topic {t:?}, which {publisher} of the same file publishes: DINASORE \
         reaches itself through the broker as before, so the topic is not mapped as an input \
         (its port stays in the interface)."
    ));
}

/// Puts a subscriber's FB into the interface; the port its topic maps onto.
fn add_subscriber(
    fb: &MqttFb<'_>,
    names: &[&str],
    draft: &mut Draft,
    notes: &mut Vec<String>,
) -> String {
    let what = fb.what();
    let name = instance_name(&what, fb.instance, draft, notes);
    let (events_in, data_in, port) = ports(fb, &name, names, "READ_O", draft, notes);
    draft.fbs.insert(
        name,
        FbInterface {
            fb_type: Some(fb.fb_type.to_owned()),
            events_out: BTreeMap::new(),
            events_in,
            data_out: BTreeMap::new(),
            data_in,
        },
    );
    port
}

#[cfg(test)]
mod tests;

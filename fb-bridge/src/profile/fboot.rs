//! Device profiles derived from a 4diac FORTE boot file (`.fboot`).
//!
//! A FORTE device's MQTT traffic is written down nowhere but in its application: the
//! `PUBLISH_n` and `SUBSCRIBE_n` FBs, their `ID` parameters (`fbdk[].mqtt[broker, client
//! id, topic]`) and what is wired to their data ports. 4diac IDE deploys that application
//! as management commands, and the boot file is those commands saved, the form in which a
//! FORTE device starts by itself. [`import`] reads one and writes the profiles
//! ([`ProfileFile`]) that say for the device what it cannot declare, with a note for
//! everything the file does not tell.
//!
//! DINASORE keeps what 4diac IDE deploys to it in the same syntax
//! (`resources/data_model.fboot`), but reads it otherwise, has MQTT FBs of its own and no
//! client ids: [`import_dinasore`] derives its profile from that file (its module,
//! `fboot/dinasore.rs`, says how), with the parsing below.
//!
//! # The boot file
//!
//! One command per line, `<resource>;<request>`: the resource the request goes to (empty
//! for the device itself), a `;`, then one management request in XML:
//!
//! ```text
//! ;<Request ID="1" Action="CREATE"><FB Name="EMB_RES" Type="EMB_RES" /></Request>
//! EMB_RES;<Request ID="2" Action="CREATE"><FB Name="PUB_POS" Type="PUBLISH_1" /></Request>
//! EMB_RES;<Request ID="3" Action="WRITE"><Connection Source="fbdk[].mqtt[tcp://10.0.0.5:1883, conv1, line1/conv1/position]" Destination="PUB_POS.ID" /></Request>
//! EMB_RES;<Request ID="4" Action="CREATE"><Connection Source="POS2REAL.OUT" Destination="PUB_POS.SD_1" /></Request>
//! EMB_RES;<Request ID="5" Action="START"/>
//! ```
//!
//! `CREATE` with an `FB` makes an FB instance, with a `Connection` a connection between two
//! ports; `WRITE` with a `Connection` sets a parameter (its `Source` is the value, XML
//! escaped); `DELETE` undoes a `CREATE`; the rest (`START`, ...) changes nothing here. The
//! file is read the way FORTE reads it, and where FORTE is strict the importer is too, so
//! a profile describes the application the device really runs:
//!
//! - a command may continue over several lines, up to a line that ends in `</Request>` or
//!   `/>`; the first `;` ends the resource name;
//! - FORTE stops loading at the first command it cannot execute, so at a line without `;`
//!   or a request it cannot parse the import stops too, with a note; nothing after it
//!   exists on the device;
//! - a parameter's XML escapes are the five FORTE decodes (`&quot;`, `&apos;`, `&amp;`,
//!   `&lt;`, `&gt;`); any other `&` stays as it is, as it does in FORTE;
//! - the `ID` is a STRING or WSTRING value: a `WSTRING#`/`STRING#` prefix is dropped, a
//!   quoted literal (`"..."`, `'...'`) is unquoted with its `$` escapes; its layers are
//!   split at unescaped `[` and `]` (`\` escapes them), and the `mqtt[]` layer takes
//!   exactly three comma-separated parameters with the spaces around them trimmed;
//! - lines ending in CRLF are read as lines, with a note: FORTE finds the end of a command
//!   only before a bare LF (but on Windows, where reading the file as text drops the CR).
//!
//! # One profile per MQTT client id
//!
//! The broker recognises a device by its connection, and every MQTT FB of a FORTE device
//! names the connection it uses by client id, so the FBs are grouped by client id and each
//! group is one profile: `device` is the client id when it is a usable device id (else a
//! sanitized one, with a note), `identity.client_id` is the client id as FORTE sends it.
//! FORTE 2.0.x keeps one MQTT client per runtime and 3.x one per broker address, so a file
//! with more client ids than that gets a note saying which FBs fail to initialise.
//!
//! How the device speaks is what FORTE's MQTT layer does: `fbdk` payloads (the `fbdk[]`
//! layer), a largest receivable message of 255 bytes (`MQTTComLayer`'s receive buffer: a
//! longer message is cut there), QoS 0 (the layer publishes and subscribes at QoS 0), and
//! DATE/TIME_OF_DAY/DATE_AND_TIME in nanoseconds, FORTE 3.x's unit: the boot file does
//! not say the version, so a profile with such a port gets a note to set `ms` for 2.0.x.
//!
//! # PUBLISH is an output, SUBSCRIBE an input
//!
//! A profile describes the device as the bus sees it, and what a `PUBLISH_n` FB sends is
//! what the device publishes, so the FB becomes an **output** of the profile, whatever
//! its ports are called inside the device. An instance `X` of `PUBLISH_n` becomes the FB
//! `X` with
//!
//! ```text
//! events_out: { REQ: { with: [SD_1, ..., SD_n] } }
//! data_out:   { SD_1: <type of SD_1>, ..., SD_n: <type of SD_n> }
//! ```
//!
//! and its topic maps onto `X.REQ`. The names stay the ones the engineer sees on the FB
//! in 4diac IDE: the message on the topic is what `X` sends at `REQ`. The topic maps onto
//! the event, not onto a data port, because FORTE sends SD_1..SD_n of one `REQ` together
//! as one `fbdk` message, which is exactly an event with that WITH list in that order (a
//! `PUBLISH_0` sends an event without data, `0x05`). An instance `Y` of `SUBSCRIBE_n` is
//! the same the other way round, an **input**: the FB `Y` with `events_in: { IND: { with:
//! [RD_1, ...] } }` and `data_in: { RD_1: ..., ... }`, its topic mapped onto `Y.IND`.
//!
//! An input topic needs `from`, the typed output that feeds it, and which device feeds a
//! topic is not in one device's boot file: it is left out, so the profile does not pass
//! [`ProfileFile::validate`] until it is set, and a note says so. When a PUBLISH of the
//! same import publishes that topic, it is not mapped at all: FORTE reaches FORTE on
//! that topic through the broker as it always did, and a topic that is one device's
//! output cannot also be another's input.
//!
//! A topic already in a typed namespace (`fbdk/<device>/<FB>/<PORT>`) is not mapped: the
//! broker types it already. A SUBSCRIBE reading one needs nothing; a PUBLISH writing one
//! in its own device's namespace needs its port in the interface, so the FB `<FB>` gets
//! `<PORT>`: the data port itself for a `PUBLISH_1` (its message is that one value), an
//! event with WITH `SD_1..SD_n` otherwise.
//!
//! # Data types
//!
//! A `PUBLISH_n`'s SD ports are of type ANY: their type is the type of what is wired to
//! them, and that type belongs to the FB type at the other end, whose interface the boot
//! file does not contain. It is derived, in this order, from
//!
//! 1. the connection into `X.SD_i` (or out of `Y.RD_i`): the other end's port type when
//!    the type table knows its FB type. [`import`] uses [`builtin_types`]: the IEC 61131-3
//!    conversions (`F_INT_TO_REAL`: `IN` INT, `OUT` REAL), FORTE's `INT2INT`-style data
//!    FBs, its event FBs with data (`E_CTU`, `E_SWITCH`, `E_CYCLE`, ...), the IEC 61131-3
//!    FBs (`FB_TON`, `FB_CTU`, ...) and the process-image FBs (`IX`, `QW`, ...), each read
//!    from FORTE's own type. [`import_with_types`] takes another table, for a caller who
//!    has the application's own `.fbt` files;
//! 2. a parameter written to `X.SD_i` (a constant): a typed literal (`INT#3`, `T#1s`,
//!    `'text'`, `TRUE`) gives its type; an untyped one (`3`, `1.5`) does not (and FORTE
//!    2.0.x refuses it: an ANY input takes only `<TYPE>#<value>`);
//! 3. otherwise nothing: the port is left out of the profile, with a note.
//!
//! A port left out stays in its event's WITH list, so [`ProfileFile::validate`] refuses
//! the profile ("WITH SD_2: no data output of that name") until its type is written in:
//! a profile that loads must decode the device's messages right, and one with a WITH
//! value missing would misread every message (there is no `ANY` to put instead; the
//! `fbdk` codec needs each value's type). A SUBSCRIBE's RD port wired to several inputs
//! takes their type when all that are known agree.
//!
//! # Not imported
//!
//! Each with a note naming the FB and what to do: a `raw[]` layer (its payload is the
//! bytes of one STRING, with no type to check), `CLIENT_n_m`/`SERVER_n_m` FBs (fbbus has
//! no request/response mapping, and FORTE's MQTT layer does not implement them either),
//! FBs that do not use MQTT, an `ID` that is not a parameter or is malformed, wildcard
//! subscriptions, topics in the broker's own `fbbus/` namespace, and topics mapped twice.
//!
//! # Untrusted input
//!
//! A boot file comes from outside: the importer never panics, whatever the text (no
//! indexing; text is only split at the characters it looks for, and cut at character
//! boundaries), and every lookup goes through an ordered map, so a hostile file costs
//! time in proportion to its size, not to its square.
//!
//! # FORTE sources read
//!
//! eclipse-4diac/4diac-forte (snapshot b70b4b7f, December 2021, 2.0.x merged), for the
//! format and its reading: `src/stdfblib/ita/ForteBootFileLoader.cpp` (lines, `;`,
//! command ends, stopping), `src/stdfblib/ita/DEV_MGR.cpp` (the requests),
//! `src/core/utils/string_utils.{h,cpp}` (XML escapes, `\` escapes),
//! `src/core/cominfra/basecommfb.cpp` (layers of an ID, the default `fbdk[].ip[]`),
//! `src/core/cominfra/commfb.cpp` (`PUBLISH_n`/`SUBSCRIBE_n` ports, WSTRING `ID`),
//! `src/core/datatypes/forte_wstring.cpp`, `forte_string.cpp`, `forte_any_string.cpp`
//! (the literal of an ID), `forte_any.cpp` (`fromString` of an ANY input), `src/core/utils/parameterParser.cpp` (the three parameters),
//! `src/com/mqtt_paho/MQTTComLayer.{h,cpp}` (255-byte buffer, QoS 0, client/server not
//! implemented), `src/com/mqtt_paho/MQTTHandler.cpp` (2.0.x: one client per runtime; the
//! 3.x version, one client per broker address, from its 2023 source), and the port types
//! of the FBs in [`builtin_types`] from their sources under `src/modules/IEC61131-3`,
//! `src/modules/convert`, `src/stdfblib/events`, `src/stdfblib/io` and
//! `src/stdfblib/timedfb.cpp`.

use std::collections::{BTreeMap, BTreeSet};

use super::{IdentityFile, ProfileFile, Speaks, TopicFile};
use crate::codec::Encoding;
use crate::interface::{is_identifier, Event, FbInterface, Interface};
use crate::topic::{self, filter, TypedTopic};
use crate::types::{DataType, ElementaryType};

/// FB type name → port name → IEC 61131-3 type name, as in the FB type's interface.
pub type TypeTable = BTreeMap<String, BTreeMap<String, String>>;

/// The largest message FORTE's MQTT layer receives: its buffer (`MQTTComLayer`,
/// `mBufferSize`) cuts longer ones.
pub const FORTE_MAX_PAYLOAD: usize = 255;

/// What a boot file gives: one profile per MQTT client id ([`import`]; one for the file with
/// [`import_dinasore`]), and a sentence for each thing it could not derive, naming the FB
/// and what to do.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct FbootImport {
    pub profiles: Vec<ProfileFile>,
    pub notes: Vec<String>,
}

/// Derives profiles from a boot file's text, with FB port types from [`builtin_types`].
pub fn import(text: &str) -> FbootImport {
    import_with_types(text, &builtin_types())
}

/// Derives profiles from a boot file's text, with FB port types from `types` (only: merge
/// [`builtin_types`] in to keep them).
pub fn import_with_types(text: &str, types: &TypeTable) -> FbootImport {
    let mut notes = Vec::new();
    let resources = load(text, &mut notes);
    let comm = find_comm_fbs(&resources, &mut notes);
    let profiles = build_profiles(&comm, types, &mut notes);
    FbootImport { profiles, notes }
}

// ---------------------------------------------------------------------------------------
// Reading the file: commands, requests, and the resources they build.

/// `(FB instance, port)`; an instance inside a subapplication keeps its dotted path.
type PortRef = (String, String);

/// One resource's application as the commands leave it.
#[derive(Debug, Default)]
struct Resource {
    name: String,
    /// Instance → (creation order, FB type).
    fbs: BTreeMap<String, (usize, String)>,
    /// Parameters (`WRITE`): port → value, XML escapes decoded.
    params: BTreeMap<PortRef, String>,
    /// Connections by destination: what feeds each input, in creation order.
    sources: BTreeMap<PortRef, Vec<PortRef>>,
    /// Connections by source: what each output feeds, in creation order.
    destinations: BTreeMap<PortRef, Vec<PortRef>>,
}

impl Resource {
    fn fb_type(&self, fb: &str) -> Option<&str> {
        self.fbs.get(fb).map(|(_, t)| t.as_str())
    }

    fn sources_of(&self, fb: &str, port: &str) -> &[PortRef] {
        self.sources
            .get(&(fb.to_owned(), port.to_owned()))
            .map_or(&[], Vec::as_slice)
    }

    fn destinations_of(&self, fb: &str, port: &str) -> &[PortRef] {
        self.destinations
            .get(&(fb.to_owned(), port.to_owned()))
            .map_or(&[], Vec::as_slice)
    }

    fn connect(&mut self, source: PortRef, destination: PortRef) {
        self.destinations
            .entry(source.clone())
            .or_default()
            .push(destination.clone());
        self.sources.entry(destination).or_default().push(source);
    }

    fn disconnect(&mut self, source: &PortRef, destination: &PortRef) {
        if let Some(list) = self.destinations.get_mut(source) {
            list.retain(|d| d != destination);
        }
        if let Some(list) = self.sources.get_mut(destination) {
            list.retain(|s| s != source);
        }
    }

    /// Forgets an FB: its parameters and the connections at its ports (a connection's
    /// other end keeps a dangling entry, which reads as an FB that is not there).
    fn delete(&mut self, fb: &str) {
        self.fbs.remove(fb);
        for map in [&mut self.sources, &mut self.destinations] {
            let ports: Vec<PortRef> = map
                .range((fb.to_owned(), String::new())..)
                .take_while(|((f, _), _)| f == fb)
                .map(|(k, _)| k.clone())
                .collect();
            for port in ports {
                map.remove(&port);
            }
        }
        let params: Vec<PortRef> = self
            .params
            .range((fb.to_owned(), String::new())..)
            .take_while(|((f, _), _)| f == fb)
            .map(|(k, _)| k.clone())
            .collect();
        for port in params {
            self.params.remove(&port);
        }
    }
}

/// One command: the line it starts on, and its text.
struct Command {
    line: usize,
    text: String,
}

/// Splits the file into commands as FORTE's loader does: a command goes on over lines
/// until one ends in `</Request>` or `/>`. Blank lines between commands are skipped. The
/// flag says whether any line ended in CRLF.
fn split_commands(text: &str) -> (Vec<Command>, bool) {
    let mut commands = Vec::new();
    let mut crlf = false;
    let mut buf = String::new();
    let mut start = 0;
    for (i, raw) in text.split_inclusive('\n').enumerate() {
        let line = raw.strip_suffix('\n').unwrap_or(raw);
        let line = match line.strip_suffix('\r') {
            Some(line) => {
                crlf = true;
                line
            }
            None => line,
        };
        if buf.is_empty() {
            if line.trim().is_empty() {
                continue;
            }
            start = i + 1;
        } else {
            buf.push('\n');
        }
        buf.push_str(line);
        let end = buf.trim_end();
        if end.ends_with("</Request>") || end.ends_with("/>") {
            commands.push(Command {
                line: start,
                text: std::mem::take(&mut buf),
            });
        }
    }
    if !buf.trim().is_empty() {
        commands.push(Command {
            line: start,
            text: buf,
        });
    }
    (commands, crlf)
}

/// An XML start tag: its name and attributes, values unescaped.
#[derive(Debug)]
struct Tag {
    name: String,
    attrs: Vec<(String, String)>,
}

impl Tag {
    fn attr(&self, key: &str) -> Option<&str> {
        self.attrs
            .iter()
            .find(|(k, _)| k == key)
            .map(|(_, v)| v.as_str())
    }
}

/// The start tags of a request, in order, read the way FORTE reads them; end tags are
/// skipped.
fn start_tags(text: &str) -> Result<Vec<Tag>, String> {
    Ok(xml_items(text, |value| Ok(decode_entities(value)))?
        .into_iter()
        .filter_map(|item| match item {
            XmlItem::Start { tag, .. } => Some(tag),
            XmlItem::End(_) => None,
        })
        .collect())
}

/// A tag of a request: a start tag (`empty` if it closes itself, `<FB ... />`) or an end
/// tag, with its name.
#[derive(Debug)]
enum XmlItem {
    Start { tag: Tag, empty: bool },
    End(String),
}

/// The tags of a request, in order, attribute values decoded by `decode` (Err: why the
/// value is not one the reader takes); text between tags is skipped.
fn xml_items(
    text: &str,
    decode: impl Fn(&str) -> Result<String, String>,
) -> Result<Vec<XmlItem>, String> {
    let mut items = Vec::new();
    let mut rest = text;
    while let Some((_, after)) = rest.split_once('<') {
        if let Some(end_tag) = after.strip_prefix('/') {
            let (name, after) = end_tag
                .split_once('>')
                .ok_or("an end tag is not closed with '>'")?;
            items.push(XmlItem::End(name.trim().to_owned()));
            rest = after;
            continue;
        }
        let (tag, empty, after) = start_tag(after, &decode)?;
        items.push(XmlItem::Start { tag, empty });
        rest = after;
    }
    Ok(items)
}

/// One start tag after its `<`, whether it closes itself, and the text after it.
fn start_tag<'t>(
    text: &'t str,
    decode: &impl Fn(&str) -> Result<String, String>,
) -> Result<(Tag, bool, &'t str), String> {
    let name_end = text
        .find(|c: char| c.is_whitespace() || c == '/' || c == '>')
        .ok_or("a tag is not closed")?;
    let (name, mut rest) = text.split_at_checked(name_end).ok_or("a tag is cut")?;
    if name.is_empty() {
        return Err("a tag has no name".into());
    }
    let mut attrs = Vec::new();
    loop {
        rest = rest.trim_start();
        let closed = match rest.strip_prefix("/>") {
            Some(after) => Some((true, after)),
            None => rest.strip_prefix('>').map(|after| (false, after)),
        };
        if let Some((empty, after)) = closed {
            let tag = Tag {
                name: name.to_owned(),
                attrs,
            };
            return Ok((tag, empty, after));
        }
        let (key, after) = rest
            .split_once('=')
            .ok_or_else(|| format!("tag <{name}> is cut or has an attribute without a value"))?;
        let key = key.trim();
        if key.is_empty() || key.contains(|c: char| c.is_whitespace() || "<>/\"'".contains(c)) {
            return Err(format!("tag <{name}> has a malformed attribute"));
        }
        let after = after.trim_start();
        let quote = match after.chars().next() {
            Some(q @ ('"' | '\'')) => q,
            _ => return Err(format!("attribute {key} of <{name}> is not quoted")),
        };
        let (value, after) = after
            .strip_prefix(quote)
            .and_then(|v| v.split_once(quote))
            .ok_or_else(|| format!("attribute {key} of <{name}> has no closing quote"))?;
        let value = decode(value).map_err(|why| format!("attribute {key} of <{name}>: {why}"))?;
        attrs.push((key.to_owned(), value));
        rest = after;
    }
}

/// The five XML escapes FORTE decodes in a parameter; any other `&` is kept.
fn decode_entities(text: &str) -> String {
    const ENTITIES: [(&str, char); 5] = [
        ("&quot;", '"'),
        ("&apos;", '\''),
        ("&amp;", '&'),
        ("&lt;", '<'),
        ("&gt;", '>'),
    ];
    let mut out = String::with_capacity(text.len());
    let mut rest = text;
    while let Some((before, after)) = rest.split_once('&') {
        out.push_str(before);
        let with_amp = rest.get(before.len()..).unwrap_or("");
        match ENTITIES.iter().find(|(e, _)| with_amp.starts_with(e)) {
            Some((entity, c)) => {
                out.push(*c);
                rest = with_amp.get(entity.len()..).unwrap_or("");
            }
            None => {
                out.push('&');
                rest = after;
            }
        }
    }
    out.push_str(rest);
    out
}

/// `FB.PORT` (the FB may be a dotted path): split at the last dot.
fn port_ref(text: &str) -> Option<PortRef> {
    let (fb, port) = text.trim().rsplit_once('.')?;
    (!fb.is_empty() && !port.is_empty()).then(|| (fb.to_owned(), port.to_owned()))
}

/// Executes the boot file's commands on a model of its resources, in the order the
/// resources first appear.
fn load(text: &str, notes: &mut Vec<String>) -> Vec<Resource> {
    let (commands, crlf) = split_commands(text);
    if crlf {
        notes.push(
            "The boot file has CRLF line ends: FORTE off Windows finds the end of a command \
             only before a bare LF, so it would read the whole file as one command and run \
             only the first request; it is read here line by line, but save it with LF line \
             ends for the device."
                .into(),
        );
    }
    let mut resources: Vec<Resource> = Vec::new();
    let mut index: BTreeMap<String, usize> = BTreeMap::new();
    for (order, command) in commands.iter().enumerate() {
        let stop = |notes: &mut Vec<String>, why: &str| {
            notes.push(format!(
                "Line {}: {why}; FORTE stops loading the boot file at a command it cannot \
                 execute, so nothing from this line on is imported.",
                command.line
            ));
        };
        let Some((destination, request)) = command.text.split_once(';') else {
            stop(
                notes,
                "the line has no ';' between the resource and the request",
            );
            break;
        };
        let tags = match start_tags(request) {
            Ok(tags) => tags,
            Err(why) => {
                stop(
                    notes,
                    &format!("the request is not well-formed XML ({why})"),
                );
                break;
            }
        };
        let mut tags = tags.into_iter();
        let Some(action) = tags
            .next()
            .filter(|t| t.name == "Request")
            .and_then(|t| t.attr("Action").map(str::to_owned))
        else {
            stop(notes, "it is not a <Request> with an Action");
            break;
        };
        let child = tags.next();
        let destination = destination.trim();
        match apply(
            &mut resources,
            &mut index,
            destination,
            &action,
            child.as_ref(),
            order,
        ) {
            Ok(()) => {}
            Err(why) => {
                stop(notes, &why);
                break;
            }
        }
    }
    resources
}

/// Applies one request to the resource `destination` (the device itself if empty).
fn apply(
    resources: &mut Vec<Resource>,
    index: &mut BTreeMap<String, usize>,
    destination: &str,
    action: &str,
    child: Option<&Tag>,
    order: usize,
) -> Result<(), String> {
    const KNOWN: [&str; 9] = [
        "CREATE", "DELETE", "START", "STOP", "KILL", "RESET", "READ", "WRITE", "QUERY",
    ];
    if !KNOWN.contains(&action) {
        return Err(format!("the action {action:?} is not a management command"));
    }
    if !matches!(action, "CREATE" | "DELETE" | "WRITE") {
        return Ok(());
    }
    let child = child.ok_or_else(|| format!("the {action} request names nothing to act on"))?;
    let fb = |tag: &Tag| -> Result<(String, String), String> {
        match (tag.attr("Name"), tag.attr("Type")) {
            (Some(name), Some(fb_type)) if !name.is_empty() => {
                Ok((name.trim().to_owned(), fb_type.trim().to_owned()))
            }
            _ => Err(format!("the {action} of an FB lacks its Name or Type")),
        }
    };
    let connection = |tag: &Tag| -> Result<(String, PortRef), String> {
        match (
            tag.attr("Source"),
            tag.attr("Destination").and_then(port_ref),
        ) {
            (Some(source), Some(destination)) => Ok((source.to_owned(), destination)),
            _ => Err(format!(
                "the {action} of a connection lacks its Source or a Destination FB.PORT"
            )),
        }
    };
    if destination.is_empty() {
        // The device itself: creating a resource, or setting a device parameter. A
        // resource exists here once something is created in it.
        return match (action, child.name.as_str()) {
            ("CREATE" | "DELETE", "FB") => fb(child).map(|_| ()),
            ("WRITE", "Connection") => connection(child).map(|_| ()),
            _ => Ok(()),
        };
    }
    let at = *index.entry(destination.to_owned()).or_insert_with(|| {
        resources.push(Resource {
            name: destination.to_owned(),
            ..Resource::default()
        });
        resources.len() - 1
    });
    let Some(resource) = resources.get_mut(at) else {
        return Ok(());
    };
    match (action, child.name.as_str()) {
        ("CREATE", "FB") => {
            let (name, fb_type) = fb(child)?;
            if resource.fbs.contains_key(&name) {
                return Err(format!(
                    "an FB named {name} already exists in resource {destination}"
                ));
            }
            resource.fbs.insert(name, (order, fb_type));
        }
        ("DELETE", "FB") => {
            let (name, _) = fb(child)?;
            resource.delete(&name);
        }
        ("CREATE", "Connection") => {
            let (source, destination) = connection(child)?;
            let source = port_ref(&source)
                .ok_or_else(|| format!("the connection's Source {source:?} is not FB.PORT"))?;
            resource.connect(source, destination);
        }
        ("DELETE", "Connection") => {
            let (source, destination) = connection(child)?;
            if let Some(source) = port_ref(&source) {
                resource.disconnect(&source, &destination);
            }
        }
        ("WRITE", "Connection") => {
            let (value, destination) = connection(child)?;
            resource.params.insert(destination, value);
        }
        ("WRITE", other) => {
            return Err(format!("a WRITE takes a <Connection>, not <{other}>"));
        }
        // Adapter and FB types, watches: nothing to derive from.
        _ => {}
    }
    Ok(())
}

// ---------------------------------------------------------------------------------------
// The communication FBs and their IDs.

#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Service {
    Publish,
    Subscribe,
}

/// What an FB type name says about it.
enum CommType {
    PubSub(Service, u8),
    /// `PUBLISH_`/`SUBSCRIBE_` with more ports than a profile FB holds.
    TooLarge,
    ClientServer,
    Other,
}

/// The type name without a package (`iec61499::net::PUBLISH_1`).
fn base_type(fb_type: &str) -> &str {
    fb_type.rsplit("::").next().unwrap_or(fb_type)
}

fn comm_type(fb_type: &str) -> CommType {
    let base = base_type(fb_type);
    let digits = |s: &str| !s.is_empty() && s.bytes().all(|b| b.is_ascii_digit());
    for (prefix, service) in [
        ("PUBLISH_", Service::Publish),
        ("SUBSCRIBE_", Service::Subscribe),
    ] {
        if let Some(n) = base.strip_prefix(prefix).filter(|n| digits(n)) {
            return match n.parse::<u8>() {
                Ok(n) => CommType::PubSub(service, n),
                Err(_) => CommType::TooLarge,
            };
        }
    }
    let client_server = ["CLIENT_", "SERVER_"].iter().any(|prefix| {
        base.strip_prefix(prefix)
            .is_some_and(|rest| rest.split('_').all(digits))
    });
    if client_server {
        CommType::ClientServer
    } else {
        CommType::Other
    }
}

/// A communication FB with an MQTT client id: mapped if `skipped` is None.
#[derive(Debug)]
struct CommFb<'a> {
    resource: &'a Resource,
    instance: &'a str,
    fb_type: &'a str,
    service: Service,
    ports: u8,
    address: String,
    client_id: String,
    topic: String,
    /// Why it is not mapped, a note.
    skipped: Option<String>,
}

impl CommFb<'_> {
    /// How notes name it: `PUBLISH_2 PUB_STATUS in resource EMB_RES`.
    fn what(&self) -> String {
        what(self.fb_type, self.instance, &self.resource.name)
    }
}

fn what(fb_type: &str, instance: &str, resource: &str) -> String {
    format!("{fb_type} {instance} in resource {resource}")
}

/// The value of a STRING or WSTRING parameter: a `WSTRING#`/`STRING#` prefix dropped, a
/// quoted literal unquoted with its `$` escapes, anything else as written.
fn string_value(text: &str) -> Result<String, String> {
    let text = text
        .strip_prefix("WSTRING#")
        .or_else(|| text.strip_prefix("STRING#"))
        .unwrap_or(text);
    let mut chars = text.chars();
    let quote = match chars.next() {
        Some(q @ ('"' | '\'')) => q,
        _ => return Ok(text.to_owned()),
    };
    // $xx in a STRING ('), $xxxx in a WSTRING (").
    let hex_digits = if quote == '"' { 4 } else { 2 };
    let mut out = String::new();
    while let Some(c) = chars.next() {
        if c == quote {
            return Ok(out);
        }
        if c != '$' {
            out.push(c);
            continue;
        }
        let escaped = chars.next().ok_or("it ends in a lone $")?;
        match escaped {
            '$' | '\'' | '"' => out.push(escaped),
            'L' | 'l' | 'N' | 'n' => out.push('\n'),
            'P' | 'p' => out.push('\u{c}'),
            'R' | 'r' => out.push('\r'),
            'T' | 't' => out.push('\t'),
            first => {
                let mut code = first.to_digit(16).ok_or("it has an unknown $ escape")?;
                for _ in 1..hex_digits {
                    let digit = chars
                        .next()
                        .and_then(|c| c.to_digit(16))
                        .ok_or("it has a malformed $ escape")?;
                    code = code * 16 + digit;
                }
                out.push(char::from_u32(code).ok_or("it has a $ escape that is no character")?);
            }
        }
    }
    Err("its quoted literal is not closed".into())
}

/// Up to the first `delimiter` not escaped by an odd number of `\` (whose last one is
/// dropped), and the text after it.
fn until_unescaped(text: &str, delimiter: char) -> Option<(String, &str)> {
    let mut out = String::new();
    for (i, c) in text.char_indices() {
        if c == delimiter {
            let backslashes = out.chars().rev().take_while(|&c| c == '\\').count();
            if backslashes % 2 == 1 {
                out.pop();
                out.push(c);
                continue;
            }
            return Some((out, text.get(i + c.len_utf8()..).unwrap_or("")));
        }
        out.push(c);
    }
    None
}

/// An ID's layers, `name[params].name[params]...`, split as FORTE splits them.
fn layers(id: &str) -> Result<Vec<(String, String)>, &'static str> {
    let mut layers = Vec::new();
    let mut rest = id;
    while !rest.is_empty() {
        let (name, after) = until_unescaped(rest, '[').ok_or("a layer has no '['")?;
        let (params, after) = until_unescaped(after, ']').ok_or("a layer has no ']'")?;
        if name.is_empty() {
            return Err("a layer has no name");
        }
        layers.push((name, params.replace("\\\\", "\\")));
        // The separator after `]`, whatever it is.
        let mut after = after.chars();
        after.next();
        rest = after.as_str();
    }
    Ok(layers)
}

/// C's `isspace`, which FORTE trims parameters with.
fn c_space(c: char) -> bool {
    matches!(c, ' ' | '\t' | '\n' | '\u{b}' | '\u{c}' | '\r')
}

/// Finds every communication FB and reads its ID. Those with an MQTT client id are
/// returned, to be grouped by it (with the reason when one cannot be mapped); for the
/// others a note says why they are left out.
fn find_comm_fbs<'a>(resources: &'a [Resource], notes: &mut Vec<String>) -> Vec<CommFb<'a>> {
    let mut found = Vec::new();
    for resource in resources {
        let mut fbs: Vec<(&String, &(usize, String))> = resource.fbs.iter().collect();
        fbs.sort_by_key(|(_, (order, _))| *order);
        for (instance, (_, fb_type)) in fbs {
            let comm = comm_type(fb_type);
            if matches!(comm, CommType::Other) {
                continue;
            }
            let what = what(fb_type, instance, &resource.name);
            let mqtt = match mqtt_params(resource, instance) {
                Ok(mqtt) => mqtt,
                Err(why) => {
                    notes.push(format!("{what}: {why}"));
                    continue;
                }
            };
            let Mqtt {
                top,
                address,
                client_id,
                topic,
            } = mqtt;
            if client_id.is_empty() {
                notes.push(format!(
                    "{what}: its client id is empty, so the broker picks one at random and no \
                     profile can recognise its connection by client id; skipped: set a \
                     client id in the ID, or write the profile by hand with \
                     identity.username."
                ));
                continue;
            }
            let (service, ports, mut skipped) = match comm {
                CommType::PubSub(service, ports) => (service, ports, None),
                CommType::TooLarge => (
                    Service::Publish,
                    0,
                    Some(format!(
                        "{what}: it has more data ports than a profile FB holds (255 at \
                         most); skipped: map it by hand or split it."
                    )),
                ),
                _ => (
                    Service::Publish,
                    0,
                    Some(format!(
                        "{what}: client/server FBs have no mapping onto the bus (FORTE's \
                         MQTT layer does not implement them either); skipped: use \
                         PUBLISH/SUBSCRIBE pairs."
                    )),
                ),
            };
            if skipped.is_none() {
                skipped = match top.as_str() {
                    "fbdk" => None,
                    "raw" => Some(format!(
                        "{what}: it sends raw[] payloads on {topic:?} (the bytes of a \
                         STRING, with no type to check), which cannot be typed; skipped: use \
                         fbdk[].mqtt[...] to put it on the bus typed."
                    )),
                    other => Some(format!(
                        "{what}: its layer {other}[] over MQTT is not an encoding fbbus \
                         types; skipped: use fbdk[].mqtt[...]."
                    )),
                };
            }
            found.push(CommFb {
                resource,
                instance,
                fb_type,
                service,
                ports,
                address,
                client_id,
                topic,
                skipped,
            });
        }
    }
    found
}

/// The parameters of an `<encoding>[].mqtt[broker, client id, topic]` ID.
struct Mqtt {
    top: String,
    address: String,
    client_id: String,
    topic: String,
}

/// Reads the ID of a communication FB as FORTE does; Err: why it is not MQTT or not
/// usable, the rest of a note.
fn mqtt_params(resource: &Resource, instance: &str) -> Result<Mqtt, String> {
    let id_port = (instance.to_owned(), "ID".to_owned());
    let Some(id) = resource.params.get(&id_port) else {
        return Err(match resource.sources_of(instance, "ID").first() {
            Some((fb, port)) => format!(
                "its ID comes from {fb}.{port} at run time, not from a parameter, so the \
                 boot file does not say its broker, client id or topic; skipped: map it by \
                 hand."
            ),
            None => "it has no ID parameter, so it never connects; skipped.".into(),
        });
    };
    let id = string_value(id).map_err(|why| {
        format!(
            "its ID {id:?} is not a string FORTE reads ({why}); skipped: fix the ID in 4diac \
             IDE."
        )
    })?;
    if !id.contains(']') {
        return Err(format!(
            "its ID {id:?} has no layers, which FORTE reads as fbdk[].ip[{id}], not MQTT; \
             skipped: not an FB of the bus."
        ));
    }
    let stack = layers(&id).map_err(|why| {
        format!(
            "its ID {id:?} is malformed ({why}), so FORTE refuses it at INIT; skipped: fix \
             the ID in 4diac IDE."
        )
    })?;
    let (top, params) = match stack.as_slice() {
        [(top, _), (mqtt, params)] if mqtt == "mqtt" => (top, params),
        _ if stack.iter().any(|(layer, _)| layer == "mqtt") => {
            return Err(format!(
                "its ID {id:?} is not <encoding>[].mqtt[...]; skipped: fbbus types FORTE's \
                 MQTT traffic in the fbdk[] encoding only."
            ))
        }
        _ => {
            return Err(format!(
                "its ID {id:?} does not use MQTT; skipped: not an FB of the bus."
            ))
        }
    };
    let params: Vec<&str> = params.split(',').map(|p| p.trim_matches(c_space)).collect();
    let [address, client_id, topic] = params.as_slice() else {
        return Err(format!(
            "its mqtt[] layer has {} parameters, not the three FORTE takes (broker, client \
             id, topic), so it fails at INIT; skipped: fix the ID in 4diac IDE.",
            params.len()
        ));
    };
    Ok(Mqtt {
        top: top.clone(),
        address: (*address).to_owned(),
        client_id: (*client_id).to_owned(),
        topic: (*topic).to_owned(),
    })
}

// ---------------------------------------------------------------------------------------
// Types of data ports.

/// The type of a parameter's literal, or why it has none.
fn literal_type(literal: &str) -> Result<DataType, String> {
    let text = literal.trim();
    let untyped = || {
        format!(
            "it is given the untyped value {text:?}, which FORTE 2.0.x even refuses on an \
             ANY input; a typed literal such as INT#3 or REAL#1.5 says its type"
        )
    };
    if text.starts_with('[') {
        return Err(format!(
            "it is given the array {text:?}, whose element type and length the literal does \
             not fix"
        ));
    }
    if text.eq_ignore_ascii_case("TRUE") || text.eq_ignore_ascii_case("FALSE") {
        return Ok(DataType::Elementary(ElementaryType::Bool));
    }
    if text.starts_with('\'') {
        return Ok(DataType::Elementary(ElementaryType::String));
    }
    if text.starts_with('"') {
        return Ok(DataType::Elementary(ElementaryType::WString));
    }
    let Some((prefix, _)) = text.split_once('#') else {
        return Err(untyped());
    };
    let upper = prefix.trim().to_ascii_uppercase();
    let name = match upper.as_str() {
        "T" => "TIME",
        "D" => "DATE",
        base if base.bytes().all(|b| b.is_ascii_digit()) => return Err(untyped()),
        other => other,
    };
    name.parse::<ElementaryType>()
        .map(DataType::Elementary)
        .map_err(|_| {
            format!("it is given {text:?}, a {prefix} literal, a type fbbus does not carry")
        })
}

/// The type of port `port` of the FB `fb` in `resource`, from the type table.
fn port_type(
    resource: &Resource,
    (fb, port): &PortRef,
    types: &TypeTable,
) -> Result<DataType, String> {
    let fb_type = resource.fb_type(fb).ok_or_else(|| {
        format!(
            "{fb}.{port}, and {fb} is not an FB of resource {}",
            resource.name
        )
    })?;
    let known = types
        .get(fb_type)
        .or_else(|| types.get(base_type(fb_type)))
        .and_then(|ports| ports.get(port));
    let Some(type_name) = known else {
        return Err(format!(
            "{fb}.{port}, a port of {fb_type}, whose interface the boot file does not contain"
        ));
    };
    type_name
        .parse::<DataType>()
        .map_err(|_| format!("{fb}.{port}, of type {type_name}, which fbbus does not carry"))
}

/// The type of `SD_i` of a PUBLISH: what is connected to it, else its parameter.
fn publish_port_type(fb: &CommFb<'_>, port: &str, types: &TypeTable) -> Result<DataType, String> {
    let resource = fb.resource;
    if let Some(source) = resource.sources_of(fb.instance, port).first() {
        return port_type(resource, source, types).map_err(|why| format!("it is fed by {why}"));
    }
    match resource
        .params
        .get(&(fb.instance.to_owned(), port.to_owned()))
    {
        Some(literal) => literal_type(literal),
        None => Err("it is neither connected nor given a value".into()),
    }
}

/// The type of `RD_i` of a SUBSCRIBE: that of the inputs it feeds, when those known agree.
fn subscribe_port_type(fb: &CommFb<'_>, port: &str, types: &TypeTable) -> Result<DataType, String> {
    let resource = fb.resource;
    let mut known: Vec<(&PortRef, DataType)> = Vec::new();
    let mut unknown = Vec::new();
    for destination in resource.destinations_of(fb.instance, port) {
        match port_type(resource, destination, types) {
            Ok(t) => known.push((destination, t)),
            Err(why) => unknown.push(why),
        }
    }
    match known.first() {
        Some((_, first)) if known.iter().all(|(_, t)| t == first) => Ok(*first),
        Some(_) => Err(format!(
            "it feeds ports of different types ({})",
            known
                .iter()
                .map(|((fb, port), t)| format!("{fb}.{port} {t}"))
                .collect::<Vec<_>>()
                .join(", ")
        )),
        None if unknown.is_empty() => Err("it is connected to nothing".into()),
        None => Err(format!("it feeds only {}", unknown.join("; and "))),
    }
}

// ---------------------------------------------------------------------------------------
// Profiles.

/// A usable device id for a name (a client id): forbidden characters (`/ + # $`,
/// controls) become `_`, and it is cut to the longest id; `fallback` if nothing is left.
fn sanitized_device(name: &str, fallback: &str) -> String {
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
fn sanitized_identifier(name: &str, max: usize) -> String {
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
fn truncate(text: &mut String, max: usize) {
    let mut at = max.min(text.len());
    while !text.is_char_boundary(at) {
        at -= 1;
    }
    text.truncate(at);
}

/// `name`, or `name_2`, `name_3`, ... : the first not in `taken`.
fn unique(name: String, taken: impl Fn(&str) -> bool, max: usize) -> String {
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

/// The profile being built for one client id.
struct Draft {
    device: String,
    fbs: BTreeMap<String, FbInterface<String>>,
    /// FBs named by a typed topic, not by an instance.
    typed_fbs: BTreeSet<String>,
    topics: Vec<TopicFile>,
    /// Topic → the port it is mapped onto.
    mapped: BTreeMap<String, String>,
}

impl Draft {
    fn has_topic(&self, topic: &str) -> Option<&str> {
        self.mapped.get(topic).map(String::as_str)
    }

    fn map_topic(&mut self, topic: &str, port: String, from: Option<String>) {
        self.mapped.insert(topic.to_owned(), port.clone());
        self.topics.push(TopicFile {
            topic: topic.to_owned(),
            port,
            from,
            encoding: None,
        });
    }
}

/// Every port name of an FB interface.
fn has_port(fb: &FbInterface<String>, port: &str) -> bool {
    fb.events_out.contains_key(port)
        || fb.events_in.contains_key(port)
        || fb.data_out.contains_key(port)
        || fb.data_in.contains_key(port)
}

/// An input topic whose `from` the user must set, and the note that says so.
struct PendingFrom {
    note: usize,
    topic: String,
}

fn build_profiles(
    comm: &[CommFb<'_>],
    types: &TypeTable,
    notes: &mut Vec<String>,
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
    // Own output topic → `device/FB/PORT`, for the notes on input topics.
    let mut published: BTreeMap<String, String> = BTreeMap::new();
    let mut profiles = Vec::new();
    for (client_id, fbs) in &groups {
        if fbs.iter().all(|fb| fb.skipped.is_some()) {
            notes.extend(fbs.iter().filter_map(|fb| fb.skipped.clone()));
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
        let mut draft = Draft {
            device,
            fbs: BTreeMap::new(),
            typed_fbs: BTreeSet::new(),
            topics: Vec::new(),
            mapped: BTreeMap::new(),
        };
        for fb in fbs {
            match (&fb.skipped, fb.service) {
                (Some(note), _) => notes.push(note.clone()),
                (None, Service::Publish) => publish(fb, &mut draft, types, notes, &mut published),
                (None, Service::Subscribe) => subscribe(fb, &mut draft, types, notes, &mut pending),
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
    for PendingFrom { note, topic } in pending {
        let (Some(text), Some(source)) = (notes.get_mut(note), published.get(&topic)) else {
            continue;
        };
        // FORTE to FORTE on one topic, both fbdk: the broker routes the publisher's own
        // topic to the subscriber as it always did. Mapping it as an input too would
        // make one topic both a device's output and another's input, which a profile
        // set refuses.
        *text = format!(
            "{} reads topic {topic:?}, which {source} publishes in this boot file: \
             FORTE to FORTE through the broker as before, so the topic is not mapped as \
             an input (its port stays in the interface).",
            text.split(" reads topic ").next().unwrap_or_default()
        );
        for profile in &mut profiles {
            let fbs = &profile.interface.fbs;
            profile.topics.retain(|t| {
                let input = t.port.split_once('.').is_some_and(|(fb, port)| {
                    fbs.get(fb).is_some_and(|f| {
                        f.events_in.contains_key(port) || f.data_in.contains_key(port)
                    })
                });
                !(t.topic == topic && input)
            });
        }
    }
    profiles
}

/// Notes on client ids FORTE will not connect as the file asks.
fn connection_notes(groups: &[(&str, Vec<&CommFb<'_>>)], notes: &mut Vec<String>) {
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

/// The interface name of an instance (`what` names it in notes): the instance name if it
/// is an identifier not yet taken, else a sanitized or numbered one, with a note.
fn instance_name(what: &str, instance: &str, draft: &Draft, notes: &mut Vec<String>) -> String {
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
fn mappable_topic(what: &str, t: &str, draft: &Draft, notes: &mut Vec<String>) -> bool {
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

/// A PUBLISH_n: an output of the profile.
fn publish(
    fb: &CommFb<'_>,
    draft: &mut Draft,
    types: &TypeTable,
    notes: &mut Vec<String>,
    published: &mut BTreeMap<String, String>,
) {
    let what = fb.what();
    let t = fb.topic.as_str();
    if !filter::valid_topic(t) || filter::is_dollar(t) {
        notes.push(format!(
            "{what}: its topic {t:?} is not a topic name one can publish on (empty, a \
             wildcard, or $...), so its publications fail; skipped: fix the ID in 4diac IDE."
        ));
        return;
    }
    if topic::is_typed_namespace(t) {
        publish_typed(fb, draft, types, notes);
        return;
    }
    if !mappable_topic(&what, t, draft, notes) {
        return;
    }
    let name = instance_name(&what, fb.instance, draft, notes);
    let ports: Vec<String> = (1..=fb.ports).map(|i| format!("SD_{i}")).collect();
    let mut data_out = BTreeMap::new();
    for port in &ports {
        match publish_port_type(fb, port, types) {
            Ok(ty) => {
                data_out.insert(port.clone(), ty.to_string());
            }
            Err(why) => notes.push(untyped_note(
                &what,
                fb.instance,
                port,
                &why,
                &format!(
                    "set data_out.{port} of FB {name} in profile {}",
                    draft.device
                ),
            )),
        }
    }
    let interface = FbInterface {
        fb_type: Some(fb.fb_type.to_owned()),
        events_out: BTreeMap::from([("REQ".to_owned(), Event { with: ports })]),
        events_in: BTreeMap::new(),
        data_out,
        data_in: BTreeMap::new(),
    };
    draft.fbs.insert(name.clone(), interface);
    published
        .entry(t.to_owned())
        .or_insert_with(|| format!("{}/{name}/REQ", draft.device));
    draft.map_topic(t, format!("{name}.REQ"), None);
}

/// The note on a port whose type is not derivable; `fix` says what to write where.
fn untyped_note(what: &str, instance: &str, port: &str, why: &str, fix: &str) -> String {
    format!(
        "{what}: the type of {instance}.{port} is not derivable from the boot file ({why}); \
         {fix}."
    )
}

/// A PUBLISH_n on a typed topic: not mapped, but its port must be in the interface.
fn publish_typed(fb: &CommFb<'_>, draft: &mut Draft, types: &TypeTable, notes: &mut Vec<String>) {
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
        match publish_port_type(fb, "SD_1", types) {
            Ok(ty) => typed_ports.push((port.clone(), ty)),
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
            match publish_port_type(fb, p, types) {
                Ok(ty) => typed_ports.push((p.clone(), ty)),
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
    draft: &mut Draft,
    types: &TypeTable,
    notes: &mut Vec<String>,
    pending: &mut Vec<PendingFrom>,
) {
    let what = fb.what();
    let t = fb.topic.as_str();
    if !filter::valid_filter(t) {
        notes.push(format!(
            "{what}: its topic {t:?} is not a topic filter, so its subscription fails; \
             skipped: fix the ID in 4diac IDE."
        ));
        return;
    }
    if !filter::valid_topic(t) {
        notes.push(format!(
            "{what}: it subscribes to the filter {t:?}; a profile maps topic names, one \
             port each; skipped: subscribe to one topic per FB."
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
            Some(typed) if typed.encoding == Encoding::Fbdk => notes.push(format!(
                "{what}: it reads the typed topic {t:?} directly, typed by the interface of \
                 device {:?}: nothing to map.",
                typed.device
            )),
            Some(typed) => notes.push(format!(
                "{what}: it reads {t:?}, which carries {} payloads its fbdk[] layer cannot \
                 decode; skipped: read {:?} instead.",
                typed.encoding.namespace(),
                typed.in_encoding(Encoding::Fbdk)
            )),
            None => notes.push(format!(
                "{what}: its topic {t:?} is in a typed namespace but is not \
                 <namespace>/<device>/<FB>/<PORT>, so nothing is published there; skipped."
            )),
        }
        return;
    }
    if !mappable_topic(&what, t, draft, notes) {
        return;
    }
    let name = instance_name(&what, fb.instance, draft, notes);
    let ports: Vec<String> = (1..=fb.ports).map(|i| format!("RD_{i}")).collect();
    let mut data_in = BTreeMap::new();
    for port in &ports {
        match subscribe_port_type(fb, port, types) {
            Ok(ty) => {
                data_in.insert(port.clone(), ty.to_string());
            }
            Err(why) => notes.push(untyped_note(
                &what,
                fb.instance,
                port,
                &why,
                &format!(
                    "set data_in.{port} of FB {name} in profile {}",
                    draft.device
                ),
            )),
        }
    }
    let interface = FbInterface {
        fb_type: Some(fb.fb_type.to_owned()),
        events_out: BTreeMap::new(),
        events_in: BTreeMap::from([("IND".to_owned(), Event { with: ports })]),
        data_out: BTreeMap::new(),
        data_in,
    };
    draft.fbs.insert(name.clone(), interface);
    pending.push(PendingFrom {
        note: notes.len(),
        topic: t.to_owned(),
    });
    notes.push(format!(
        "{what} reads topic {t:?}: set `from` of that topic in profile {} to the typed \
         output that feeds it (<device>/<FB>/<PORT>).",
        draft.device
    ));
    draft.map_topic(t, format!("{name}.IND"), None);
}

// ---------------------------------------------------------------------------------------
// The built-in type table.

/// Port types of the FB types whose interface is fixed by their name or by the standard
/// library FORTE ships, each read from FORTE's source:
///
/// - the IEC 61131-3 conversions `F_<A>_TO_<B>` (`IN`: A, `OUT`: B) for every pair of
///   elementary types (also `TOD`, `DT`), the BCD ones (`F_BYTE_BCD_TO_USINT`,
///   `F_USINT_TO_BCD_BYTE`, ...) and `F_TIME_IN_<unit>_TO_<B>` (`IN`: TIME);
/// - FORTE's data FBs `<T>2<T>` (`INT2INT`: `IN`, `OUT` INT);
/// - its event FBs with data: `E_CTU`/`E_CTD`/`E_CTUD` (`PV`, `CV` UINT, `Q`/`QU`/`QD`
///   BOOL), `E_CYCLE`, `E_DELAY`, `E_RDELAY` (`DT` TIME), `E_TRAIN` (`DT` TIME, `N`, `CV`
///   UINT), `E_DEMUX` (`K` UINT), `E_SWITCH`/`E_SELECT` (`G`), `E_PERMIT` (`PERMIT`),
///   `E_R_TRIG`/`E_F_TRIG` (`QI`), `E_D_FF` (`D`, `Q`), `E_SR`, `E_RS`, `E_T_FF` (`Q`),
///   all BOOL where not said;
/// - the IEC 61131-3 FBs: `FB_TON`/`FB_TOF`/`FB_TP`, `FB_CTU`/`FB_CTD`/`FB_CTUD` and
///   their `_DINT`, `_LINT`, `_UDINT`, `_ULINT` forms, `FB_R_TRIG`/`FB_F_TRIG`,
///   `FB_SR`/`FB_RS`;
/// - the process image: `IX`, `IB`, `IW`, `ID`, `IL` (`IN`: BOOL, BYTE, WORD, DWORD,
///   LWORD) and `QX` ... `QL` (`OUT`).
pub fn builtin_types() -> TypeTable {
    let mut table = TypeTable::new();
    let mut add = |fb_type: String, ports: &[(&str, &str)]| {
        let entry = table.entry(fb_type).or_default();
        for (port, ty) in ports {
            entry.insert((*port).to_owned(), (*ty).to_owned());
        }
    };
    let mut names: Vec<&str> = ElementaryType::ALL.iter().map(|t| t.name()).collect();
    names.extend(["TOD", "DT"]);
    for a in &names {
        for b in &names {
            if a != b {
                add(format!("F_{a}_TO_{b}"), &[("IN", a), ("OUT", b)]);
            }
        }
    }
    for (bits, unsigned) in [
        ("BYTE", "USINT"),
        ("WORD", "UINT"),
        ("DWORD", "UDINT"),
        ("LWORD", "ULINT"),
    ] {
        add(
            format!("F_{bits}_BCD_TO_{unsigned}"),
            &[("IN", bits), ("OUT", unsigned)],
        );
        add(
            format!("F_{unsigned}_TO_BCD_{bits}"),
            &[("IN", unsigned), ("OUT", bits)],
        );
    }
    for unit in ["S", "MS", "US", "NS"] {
        for out in ["LINT", "ULINT", "LREAL"] {
            add(
                format!("F_TIME_IN_{unit}_TO_{out}"),
                &[("IN", "TIME"), ("OUT", out)],
            );
        }
    }
    for t in ElementaryType::ALL {
        let t = t.name();
        add(format!("{t}2{t}"), &[("IN", t), ("OUT", t)]);
    }
    let fixed: &[(&str, &[(&str, &str)])] = &[
        ("E_CTU", &[("PV", "UINT"), ("Q", "BOOL"), ("CV", "UINT")]),
        ("E_CTD", &[("PV", "UINT"), ("Q", "BOOL"), ("CV", "UINT")]),
        (
            "E_CTUD",
            &[
                ("PV", "UINT"),
                ("QU", "BOOL"),
                ("QD", "BOOL"),
                ("CV", "UINT"),
            ],
        ),
        ("E_CYCLE", &[("DT", "TIME")]),
        ("E_DELAY", &[("DT", "TIME")]),
        ("E_RDELAY", &[("DT", "TIME")]),
        ("E_TRAIN", &[("DT", "TIME"), ("N", "UINT"), ("CV", "UINT")]),
        ("E_DEMUX", &[("K", "UINT")]),
        ("E_SWITCH", &[("G", "BOOL")]),
        ("E_SELECT", &[("G", "BOOL")]),
        ("E_PERMIT", &[("PERMIT", "BOOL")]),
        ("E_R_TRIG", &[("QI", "BOOL")]),
        ("E_F_TRIG", &[("QI", "BOOL")]),
        ("E_D_FF", &[("D", "BOOL"), ("Q", "BOOL")]),
        ("E_SR", &[("Q", "BOOL")]),
        ("E_RS", &[("Q", "BOOL")]),
        ("E_T_FF", &[("Q", "BOOL")]),
        ("FB_R_TRIG", &[("CLK", "BOOL"), ("Q", "BOOL")]),
        ("FB_F_TRIG", &[("CLK", "BOOL"), ("Q", "BOOL")]),
        ("FB_SR", &[("S1", "BOOL"), ("R", "BOOL"), ("Q1", "BOOL")]),
        ("FB_RS", &[("S", "BOOL"), ("R1", "BOOL"), ("Q1", "BOOL")]),
    ];
    for (fb_type, ports) in fixed {
        add((*fb_type).to_owned(), ports);
    }
    for timer in ["FB_TON", "FB_TOF", "FB_TP"] {
        add(
            timer.to_owned(),
            &[
                ("IN", "BOOL"),
                ("PT", "TIME"),
                ("Q", "BOOL"),
                ("ET", "TIME"),
            ],
        );
    }
    for (suffix, count) in [
        ("", "INT"),
        ("_DINT", "DINT"),
        ("_LINT", "LINT"),
        ("_UDINT", "UDINT"),
        ("_ULINT", "ULINT"),
    ] {
        add(
            format!("FB_CTU{suffix}"),
            &[
                ("CU", "BOOL"),
                ("R", "BOOL"),
                ("PV", count),
                ("Q", "BOOL"),
                ("CV", count),
            ],
        );
        add(
            format!("FB_CTD{suffix}"),
            &[
                ("CD", "BOOL"),
                ("LD", "BOOL"),
                ("PV", count),
                ("Q", "BOOL"),
                ("CV", count),
            ],
        );
        // FORTE has no FB_CTUD_UDINT.
        if suffix != "_UDINT" {
            add(
                format!("FB_CTUD{suffix}"),
                &[
                    ("CU", "BOOL"),
                    ("CD", "BOOL"),
                    ("R", "BOOL"),
                    ("LD", "BOOL"),
                    ("PV", count),
                    ("QU", "BOOL"),
                    ("QD", "BOOL"),
                    ("CV", count),
                ],
            );
        }
    }
    for (letter, ty) in [
        ("X", "BOOL"),
        ("B", "BYTE"),
        ("W", "WORD"),
        ("D", "DWORD"),
        ("L", "LWORD"),
    ] {
        add(format!("I{letter}"), &[("IN", ty)]);
        add(format!("Q{letter}"), &[("OUT", ty)]);
    }
    table
}

mod dinasore;
pub use dinasore::import_dinasore;

#[cfg(test)]
mod tests;

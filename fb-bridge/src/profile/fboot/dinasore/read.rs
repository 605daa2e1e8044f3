//! A DINASORE configuration read as DINASORE reads it (`UaManagerFboot.parse_fboot`,
//! `core/configuration.py`): Python's lines, a split at every `;`, ElementTree's XML, FBs
//! first and then connections and parameters, and the first reason it would run none of
//! it. The module `dinasore` says what it reads and why.

use super::super::resource::{PortRef, Resource};
use super::super::xml::{xml_items, Tag, XmlItem};

#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(super) enum Role {
    Publisher,
    Subscriber,
}

/// DINASORE finds an FB type by its file name, exactly.
pub(super) fn mqtt_type(fb_type: &str) -> Option<(Role, bool)> {
    match fb_type {
        "MQTT_PUBLISHER" => Some((Role::Publisher, false)),
        "MQTT_PUBLISHER_2" => Some((Role::Publisher, true)),
        "MQTT_SUBSCRIBER" => Some((Role::Subscriber, false)),
        "MQTT_SUBSCRIBER_2" => Some((Role::Subscriber, true)),
        _ => None,
    }
}

/// The FBs, parameters and connections DINASORE builds from the file, and the first
/// reason it runs none of them.
pub(super) struct Config {
    pub(super) resource: Resource,
    pub(super) refusal: Option<String>,
}

/// Python's `readlines()` of a file opened as text: lines split after `\n`, `\r\n` or
/// `\r`, without their ends; a last line without an end is a line, an empty text none.
pub(super) fn python_lines(text: &str) -> Vec<&str> {
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
pub(super) fn escape(line: &str) -> Option<&str> {
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
pub(super) fn expat_value(raw: &str) -> Result<String, String> {
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
pub(super) fn element_tree(request: &str) -> Result<(Tag, Vec<Tag>), String> {
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
pub(super) fn dinasore_port(text: &str) -> Option<PortRef> {
    let mut parts = text.split('.');
    let (fb, port) = (parts.next()?, parts.next()?);
    Some((fb.to_owned(), port.to_owned()))
}

/// Builds DINASORE's configuration from the file in its two passes: every line's FBs
/// first, then every line's connections and parameters.
pub(super) fn read(text: &str) -> Config {
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
pub(super) fn apply(resource: &mut Resource, write: bool, connection: &Tag) -> Result<(), String> {
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
pub(super) fn python_int(text: &str) -> Option<i128> {
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
pub(super) fn python_float(text: &str) -> Option<f64> {
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
pub(super) fn underscored_digits(text: &str) -> bool {
    !text.is_empty()
        && text
            .split('_')
            .all(|group| !group.is_empty() && group.bytes().all(|b| b.is_ascii_digit()))
}

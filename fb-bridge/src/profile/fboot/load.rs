//! The boot file as FORTE's loader reads it: lines into commands, each command a
//! `<resource>;<request>` executed on the model of its resource ([`Resource`]), stopping
//! where FORTE stops (see the module `fboot` for the rules and the FORTE sources).

use std::collections::BTreeMap;

use super::note::Notes;
use super::resource::{PortRef, Resource};
use super::xml::{start_tags, Tag};

/// One command: the line it starts on, and its text.
pub(super) struct Command {
    pub(super) line: usize,
    pub(super) text: String,
}

/// Splits the file into commands as FORTE's loader does: a command goes on over lines
/// until one ends in `</Request>` or `/>`. Blank lines between commands are skipped. The
/// flag says whether any line ended in CRLF.
pub(super) fn split_commands(text: &str) -> (Vec<Command>, bool) {
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

/// `FB.PORT` (the FB may be a dotted path): split at the last dot.
pub(super) fn port_ref(text: &str) -> Option<PortRef> {
    let (fb, port) = text.trim().rsplit_once('.')?;
    (!fb.is_empty() && !port.is_empty()).then(|| (fb.to_owned(), port.to_owned()))
}

/// Executes the boot file's commands on a model of its resources, in the order the
/// resources first appear.
pub(super) fn load(text: &str, notes: &mut Notes) -> Vec<Resource> {
    let (commands, crlf) = split_commands(text);
    if crlf {
        notes.push(
            "The boot file has CRLF line ends: FORTE off Windows finds the end of a command \
             only before a bare LF, so it would read the whole file as one command and run \
             only the first request; it is read here line by line, but save it with LF line \
             ends for the device.",
        );
    }
    let mut resources: Vec<Resource> = Vec::new();
    let mut index: BTreeMap<String, usize> = BTreeMap::new();
    for (order, command) in commands.iter().enumerate() {
        let stop = |notes: &mut Notes, why: &str| {
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
pub(super) fn apply(
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

//! The communication FBs of a FORTE application and their `ID`s: which FB types publish
//! or subscribe, and the broker, client id and topic of an `fbdk[].mqtt[...]` ID, read
//! as FORTE reads a STRING/WSTRING parameter and splits its layers.

use super::note::Notes;
use super::resource::Resource;

#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(super) enum Service {
    Publish,
    Subscribe,
}

/// What an FB type name says about it.
pub(super) enum CommType {
    PubSub(Service, u8),
    /// `PUBLISH_`/`SUBSCRIBE_` with more ports than a profile FB holds.
    TooLarge,
    ClientServer,
    Other,
}

/// The type name without a package (`iec61499::net::PUBLISH_1`).
pub(super) fn base_type(fb_type: &str) -> &str {
    fb_type.rsplit("::").next().unwrap_or(fb_type)
}

pub(super) fn comm_type(fb_type: &str) -> CommType {
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
pub(super) struct CommFb<'a> {
    pub(super) resource: &'a Resource,
    pub(super) instance: &'a str,
    pub(super) fb_type: &'a str,
    pub(super) service: Service,
    pub(super) ports: u8,
    pub(super) address: String,
    pub(super) client_id: String,
    pub(super) topic: String,
    /// Why it is not mapped, a note.
    pub(super) skipped: Option<String>,
}

impl CommFb<'_> {
    /// How notes name it: `PUBLISH_2 PUB_STATUS in resource EMB_RES`.
    pub(super) fn what(&self) -> String {
        what(self.fb_type, self.instance, &self.resource.name)
    }
}

pub(super) fn what(fb_type: &str, instance: &str, resource: &str) -> String {
    format!("{fb_type} {instance} in resource {resource}")
}

/// The value of a STRING or WSTRING parameter: a `WSTRING#`/`STRING#` prefix dropped, a
/// quoted literal unquoted with its `$` escapes, anything else as written.
pub(super) fn string_value(text: &str) -> Result<String, String> {
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
pub(super) fn until_unescaped(text: &str, delimiter: char) -> Option<(String, &str)> {
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
pub(super) fn layers(id: &str) -> Result<Vec<(String, String)>, &'static str> {
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
pub(super) fn c_space(c: char) -> bool {
    matches!(c, ' ' | '\t' | '\n' | '\u{b}' | '\u{c}' | '\r')
}

/// Finds every communication FB and reads its ID. Those with an MQTT client id are
/// returned, to be grouped by it (with the reason when one cannot be mapped); for the
/// others a note says why they are left out.
pub(super) fn find_comm_fbs<'a>(resources: &'a [Resource], notes: &mut Notes) -> Vec<CommFb<'a>> {
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
pub(super) struct Mqtt {
    pub(super) top: String,
    pub(super) address: String,
    pub(super) client_id: String,
    pub(super) topic: String,
}

/// Reads the ID of a communication FB as FORTE does; Err: why it is not MQTT or not
/// usable, the rest of a note.
pub(super) fn mqtt_params(resource: &Resource, instance: &str) -> Result<Mqtt, String> {
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

//! The topics fbbus gives meaning to.
//!
//! | topic | who publishes | what |
//! |---|---|---|
//! | `fb/<device>/<fb>/<port>` | the device owning the output port | canonical JSON ([`crate::codec::json`]) |
//! | `dinasore/<device>/<fb>/<port>` | same | DINASORE JSON |
//! | `fbdk/<device>/<fb>/<port>` | same | 4diac `fbdk` bytes |
//! | `fbbus/declare/<device>` | the device | its interface declaration (birth) |
//! | `fbbus/diag/<device>` | the broker | answers to the declaration, rejected publications |
//! | `fbbus/devices/<device>` | the broker, retained | the device's registry record |
//! | `fbbus/lines/<line>/online` | the broker, retained | how many devices of the line are online |
//!
//! The MQTT grammar underneath every topic (validity, wildcards, `$share/`, matching and
//! coverage) is [`filter`], shared with the ACL and the bus.

pub mod filter;

use crate::codec::Encoding;

/// Control-topic prefixes.
pub const DECLARE: &str = "fbbus/declare/";
pub const DIAG: &str = "fbbus/diag/";
pub const DEVICES: &str = "fbbus/devices/";
pub const LINES: &str = "fbbus/lines/";
/// Everything under `fbbus/` belongs to the broker, except declarations.
pub const BROKER_NAMESPACE: &str = "fbbus/";

/// A typed topic, parsed.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct TypedTopic<'a> {
    pub encoding: Encoding,
    pub device: &'a str,
    pub fb: &'a str,
    pub port: &'a str,
}

impl<'a> TypedTopic<'a> {
    /// Parses `<namespace>/<device>/<fb>/<port>`; None for any other topic, including a
    /// typed namespace with the wrong number of levels (see [`is_typed_namespace`]).
    pub fn parse(topic: &'a str) -> Option<TypedTopic<'a>> {
        let mut levels = topic.split('/');
        let encoding = Encoding::from_namespace(levels.next()?)?;
        let device = levels.next()?;
        let fb = levels.next()?;
        let port = levels.next()?;
        if levels.next().is_some() || device.is_empty() || fb.is_empty() || port.is_empty() {
            return None;
        }
        Some(TypedTopic {
            encoding,
            device,
            fb,
            port,
        })
    }

    /// The same port's topic in another encoding.
    pub fn in_encoding(&self, encoding: Encoding) -> String {
        format!(
            "{}/{}/{}/{}",
            encoding.namespace(),
            self.device,
            self.fb,
            self.port
        )
    }
}

/// Whether `topic` is in one of the typed namespaces (`fb/`, `dinasore/`, `fbdk/`).
pub fn is_typed_namespace(topic: &str) -> bool {
    topic
        .split_once('/')
        .is_some_and(|(ns, _)| Encoding::from_namespace(ns).is_some())
}

/// The namespaces of the re-encoded copies (`dinasore/`, `fbdk/`) with their slash: a
/// filter starting with a wildcard does not match them, as it does not match `$` topics
/// ([`filter::matches`]). A typed value is one value: a generic tool subscribed to `#`
/// sees it once, canonically on `fb/`, not again as DINASORE's string and FORTE's bytes;
/// a runtime that reads a copy names its namespace (`fbdk/#`, `dinasore/plc-1/...`).
pub const MIRROR_PREFIXES: [&str; 2] = ["dinasore/", "fbdk/"];

/// Whether `topic` is in a re-encoded copy's namespace ([`MIRROR_PREFIXES`]).
pub fn is_mirror(topic: &str) -> bool {
    MIRROR_PREFIXES.iter().any(|p| topic.starts_with(p))
}

/// Longest device id, in bytes.
pub const MAX_DEVICE_ID: usize = 256;

/// Whether `id` can name a device: a client id fbbus accepts (not empty, none of
/// `/ + # $`, no control characters), at most [`MAX_DEVICE_ID`] bytes.
pub fn is_device_id(id: &str) -> bool {
    !id.is_empty()
        && id.len() <= MAX_DEVICE_ID
        && !id.contains(['+', '#', '/', '$'])
        && !id.chars().any(char::is_control)
}

/// The device whose namespace `topic` is in: the second level of any topic in a typed
/// namespace, at any depth (`fb/<device>`, `fbdk/<device>/a/b/c`, ...), None outside the
/// typed namespaces. Only that device may publish there, whatever shape the topic has:
/// a topic that is not a typed port (lenient mode routes those unchecked) is still the
/// device's. The device may be empty (`fb/`, `fb//x`): a namespace no device owns.
pub fn namespace_owner(topic: &str) -> Option<(Encoding, &str)> {
    let (namespace, rest) = topic.split_once('/')?;
    let encoding = Encoding::from_namespace(namespace)?;
    let device = rest.split_once('/').map_or(rest, |(device, _)| device);
    Some((encoding, device))
}

pub fn declare(device: &str) -> String {
    format!("{DECLARE}{device}")
}

pub fn diag(device: &str) -> String {
    format!("{DIAG}{device}")
}

pub fn device_record(device: &str) -> String {
    format!("{DEVICES}{device}")
}

pub fn line_online(line: &str) -> String {
    format!("{LINES}{line}/online")
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_namespace_owner_is_the_second_level_at_any_depth() {
        for (topic, owner) in [
            ("fb/dev-b", Some((Encoding::Json, "dev-b"))),
            ("fb/dev-b/CONV", Some((Encoding::Json, "dev-b"))),
            ("fbdk/dev-b/CONV/SPEED", Some((Encoding::Fbdk, "dev-b"))),
            (
                "dinasore/dév-ß/CONV/SPEED/x/y",
                Some((Encoding::Dinasore, "dév-ß")),
            ),
            ("fb/", Some((Encoding::Json, ""))),
            ("fb//x", Some((Encoding::Json, ""))),
            ("fb", None),
            ("fbx/dev-b/CONV/SPEED", None),
            ("fbbus/declare/dev-b", None),
            ("a/fb/dev-b", None),
        ] {
            assert_eq!(namespace_owner(topic), owner, "{topic}");
        }
    }

    #[test]
    fn typed_topics_parse_in_every_namespace() {
        let t = TypedTopic::parse("fbdk/conv-a/CONV/MOVED").unwrap();
        assert_eq!(
            (t.encoding, t.device, t.fb, t.port),
            (Encoding::Fbdk, "conv-a", "CONV", "MOVED")
        );
        assert_eq!(t.in_encoding(Encoding::Json), "fb/conv-a/CONV/MOVED");
        assert!(TypedTopic::parse("fb/a/b").is_none());
        assert!(TypedTopic::parse("fb/a/b/c/d").is_none());
        assert!(TypedTopic::parse("fb//b/c").is_none());
        assert!(TypedTopic::parse("plant/a/b/c").is_none());
        assert!(is_typed_namespace("fb/a/b"));
        assert!(!is_typed_namespace("fbx/a/b/c"));
    }
}

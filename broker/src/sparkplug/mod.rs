//! The line as a Sparkplug B 3.0 edge node, for SCADA and historians (issue 36).
//!
//! A Sparkplug host application (Ignition, any historian speaking Sparkplug) reads a
//! plant through `spBv1.0/` topics: births that declare every metric with its datatype,
//! data by alias, deaths, and commands. FB devices never speak Sparkplug, but the broker
//! knows everything a host needs about them: each device's declared (or profiled) FB
//! interface with its IEC 61131-3 types, whether it is online, silent, offline or
//! unreachable, and each port's accepted values. With `[sparkplug] enabled`, the broker
//! publishes that as Sparkplug itself:
//!
//! | Sparkplug | fbbus |
//! |---|---|
//! | edge node `spBv1.0/<group>/NBIRTH\|NDEATH/<line>` | the line (and, with `remote_lines`, each other line on the bus, under its own name) |
//! | device `DBIRTH/<line>/<device>` | a registered device while it is online: one metric per port, `FB/PORT` |
//! | `DDATA` | a port's value accepted by the typed check (`fb/` canonical JSON) |
//! | `DDEATH` | the registry marks the device offline (its will, a profile's broker-side will, liveness) or unreachable, or forgets it |
//! | `NDEATH` | the line shuts down; another line's node when the bus loses it |
//! | `DCMD` | a host writes a device's input port ([`command`]): authorized by the ACL, typed, delivered in the device's own encoding |
//! | `NCMD` `Node Control/Rebirth`, `STATE` of the primary host | NBIRTH and every DBIRTH again |
//!
//! **Off the packet path.** Like the console, the view reads the router through a link
//! of its own, `fbbus:sparkplug` ([`CLIENT_ID`]), subscribed to `fb/#` (every accepted
//! typed publication, canonical JSON) and to the host topics it obeys; it follows the
//! registry's change channel for births and deaths. A device never waits for it: when the
//! view falls behind, the router pauses its link. It publishes through the same link,
//! so what it sends is bounded by what the router takes. The one part on the packet path
//! is a host's `DCMD`, which must be authorized as its publisher ([`command`]).
//!
//! **Free until someone reads it.** As the typed stage re-encodes into `dinasore/` only
//! once someone reads it, the view takes the line's values only once a client subscribed
//! to a filter under `spBv1.0/` ([`Readers`]; a filter starting with a wildcard, `#`, does
//! not count): until then it publishes births and deaths but reads no `fb/` message and
//! costs the packet path nothing. When the first reader comes, the view subscribes to
//! `fb/#` (whose retained messages bring the last values) and every node is born again,
//! so the new host has every birth. The flag is never cleared.
//!
//! **When the line dies.** Sparkplug's NDEATH is normally the edge node's MQTT will; the
//! view is inside the broker, so its death is the broker's:
//! - a clean shutdown publishes NDEATH before any client connection is closed;
//! - after a crash (SIGKILL), a host on this broker loses its own connection, which the
//!   Sparkplug host rules say marks every node of that server offline; a host on another
//!   line's broker gets NDEATH for this line from that broker when the bus loses the line
//!   (`remote_lines`); and at restart the line first publishes NDEATH with the previous
//!   `bdSeq`, then NBIRTH with the next one.
//!
//! **bdSeq** (0-255) is kept across restarts in `<[persistence] dir>/sparkplug-bdseq.json`
//! ([`bdseq`]); without a persistence directory it starts at 0 at every start.

use std::sync::atomic::{AtomicBool, Ordering};

use tokio::sync::Notify;

pub mod bdseq;
pub mod command;
mod node;
mod view;

use serde::Deserialize;

pub use view::{start, View};

/// The view's router link; clients may not take it (`fbbus:` prefix).
pub const CLIENT_ID: &str = "fbbus:sparkplug";

/// The Sparkplug B topic namespace.
pub const NAMESPACE: &str = "spBv1.0";

/// `[sparkplug]`.
#[derive(Debug, Clone, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct SparkplugSection {
    /// Publish the Sparkplug view. Off by default.
    pub enabled: bool,
    /// The Sparkplug group id: the line's edge node is `spBv1.0/<group>/.../<line>`. The
    /// group is fbbus's: clients may not publish births, data or deaths in it.
    pub group: String,
    /// The primary host application's id: when its `spBv1.0/STATE/<id>` says online
    /// (with a newer timestamp than last seen), every node is born again. Empty: none.
    pub primary_host: String,
    /// Accept `DCMD` writes of devices' input ports (authorized by `[auth] acl_file`,
    /// which is then required).
    pub commands: bool,
    /// Show the other lines on the bus as edge nodes of their own, with their devices.
    pub remote_lines: bool,
}

impl Default for SparkplugSection {
    fn default() -> Self {
        SparkplugSection {
            enabled: false,
            group: "fbbus".to_owned(),
            primary_host: String::new(),
            commands: false,
            remote_lines: true,
        }
    }
}

/// Whether any client reads Sparkplug: told of every subscription (`observer`), set by the
/// first filter under `spBv1.0/`, never cleared.
#[derive(Default)]
pub struct Readers {
    some: AtomicBool,
    first: Notify,
}

impl Readers {
    /// Resolves once some client reads under `spBv1.0/` (at once if one already did).
    async fn arrived(&self) {
        if !self.some.load(Ordering::Relaxed) {
            self.first.notified().await;
        }
    }
}

impl crate::observer::SubscriptionObserver for Readers {
    fn subscribed(&self, filter: &str) {
        let filter = fb_bridge::topic::filter::unshared(filter);
        if filter.split('/').next() == Some(NAMESPACE) && !self.some.swap(true, Ordering::Relaxed) {
            tracing::info!("first Sparkplug reader: the view now publishes the line's values");
            self.first.notify_one();
        }
    }

    fn unsubscribed(&self, _filter: &str) {}
}

/// Whether `id` can be a Sparkplug group, edge node or device id: a topic level that is
/// not empty and holds none of `/ + #`.
pub fn valid_id(id: &str) -> bool {
    !id.is_empty() && !id.contains(['/', '+', '#'])
}

/// The kinds of Sparkplug message the view publishes and obeys.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Kind {
    NBirth,
    NData,
    NDeath,
    NCmd,
    DBirth,
    DData,
    DDeath,
    DCmd,
}

impl Kind {
    pub fn as_str(self) -> &'static str {
        match self {
            Kind::NBirth => "NBIRTH",
            Kind::NData => "NDATA",
            Kind::NDeath => "NDEATH",
            Kind::NCmd => "NCMD",
            Kind::DBirth => "DBIRTH",
            Kind::DData => "DDATA",
            Kind::DDeath => "DDEATH",
            Kind::DCmd => "DCMD",
        }
    }

    fn parse(s: &str) -> Option<Kind> {
        [
            Kind::NBirth,
            Kind::NData,
            Kind::NDeath,
            Kind::NCmd,
            Kind::DBirth,
            Kind::DData,
            Kind::DDeath,
            Kind::DCmd,
        ]
        .into_iter()
        .find(|k| k.as_str() == s)
    }
}

/// A topic of a Sparkplug edge node or device: `spBv1.0/<group>/<kind>/<node>[/<device>]`.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Topic<'a> {
    pub group: &'a str,
    pub kind: Kind,
    pub node: &'a str,
    pub device: Option<&'a str>,
}

impl<'a> Topic<'a> {
    /// Parses a topic; None when it is not a node or device topic (`STATE`, anything else).
    pub fn parse(topic: &'a str) -> Option<Topic<'a>> {
        let rest = topic.strip_prefix(NAMESPACE)?.strip_prefix('/')?;
        let mut levels = rest.split('/');
        let group = levels.next()?;
        let kind = Kind::parse(levels.next()?)?;
        let node = levels.next()?;
        let device = levels.next();
        if levels.next().is_some() || !valid_id(group) || !valid_id(node) {
            return None;
        }
        let is_device = matches!(kind, Kind::DBirth | Kind::DData | Kind::DDeath | Kind::DCmd);
        match device {
            Some(d) if is_device && valid_id(d) => {}
            None if !is_device => {}
            _ => return None,
        }
        Some(Topic {
            group,
            kind,
            node,
            device,
        })
    }

    pub fn to_topic(self) -> String {
        match self.device {
            Some(d) => format!(
                "{NAMESPACE}/{}/{}/{}/{d}",
                self.group,
                self.kind.as_str(),
                self.node
            ),
            None => format!(
                "{NAMESPACE}/{}/{}/{}",
                self.group,
                self.kind.as_str(),
                self.node
            ),
        }
    }
}

/// Milliseconds since the epoch, now.
fn now_ms() -> u64 {
    std::time::SystemTime::now()
        .duration_since(std::time::UNIX_EPOCH)
        .map(|d| d.as_millis() as u64)
        .unwrap_or(0)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn topics_parse_and_print() {
        let t = Topic::parse("spBv1.0/fbbus/DCMD/line-1/conv").unwrap();
        assert_eq!(t.kind, Kind::DCmd);
        assert_eq!(
            (t.group, t.node, t.device),
            ("fbbus", "line-1", Some("conv"))
        );
        assert_eq!(t.to_topic(), "spBv1.0/fbbus/DCMD/line-1/conv");
        let n = Topic::parse("spBv1.0/g/NCMD/l").unwrap();
        assert_eq!((n.kind, n.device), (Kind::NCmd, None));
        for bad in [
            "spBv1.0/g/NCMD/l/d",
            "spBv1.0/g/DCMD/l",
            "spBv1.0/g/XCMD/l",
            "spBv1.0/STATE/host",
            "spBv1.0//NCMD/l",
            "spBv1.0/g/DDATA/l/d/e",
            "spBv1.0",
            "fb/x/y/z",
            "spBv1.0/g/DCMD/l/ü€/x",
        ] {
            assert_eq!(Topic::parse(bad), None, "{bad}");
        }
        // Multi-byte ids are ids.
        assert!(Topic::parse("spBv1.0/g/DCMD/lïne/ü€").is_some());
    }
}

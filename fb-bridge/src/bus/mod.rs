//! One bus across lines: the zenoh bridge between line brokers.
//!
//! Each production line runs its own fbbus broker. The bridge links them over zenoh so an
//! FB connection can cross lines: a device on line B subscribes to
//! `fb/<device>/<fb>/<port>` as if the device were local, and if the device lives on line
//! A, the two bridges carry the messages. This module holds what both ends of a hop must
//! agree on and what can be reasoned about without a network:
//!
//! - [`keys`]: the zenoh key expressions (`fbbus/<line>/fb/<device>/<fb>/<port>` for data,
//!   `fbbus/@/...` for the bridges' own control plane);
//! - [`Stamp`]: the attachment each bridged message carries (origin line, origin epoch,
//!   per-origin sequence, MQTT QoS and RETAIN), and [`Dedup`], which drops a message
//!   already seen from that origin;
//! - [`BusConfig`]: the `[bridge]` section of the broker's configuration.
//!
//! The zenoh session itself is [`link`] (cargo feature `zenoh`).
//!
//! **No loops, no duplicates, by construction.** A bridge exports only messages its own
//! broker accepted from a local client; a message that came from zenoh is never exported
//! again. So every message crosses exactly one hop, from its origin line to each line that
//! subscribed, whatever the topology (chain, mesh, routers in between). [`Dedup`] is the
//! second line of defence: zenoh delivers a sample once per matching subscriber, so two
//! overlapping import filters of one line would otherwise inject it twice.

#[cfg(feature = "zenoh")]
pub mod link;

pub mod keys;

use std::collections::{HashMap, HashSet, VecDeque};

use serde::Deserialize;

/// zenoh's role for this bridge.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum Mode {
    /// Talks directly to the bridges it connects to or that connect to it (default).
    #[default]
    Peer,
    /// Talks only through the zenoh router it connects to (`zenohd`).
    Client,
    /// Routes for others too: the middle of a chain of lines.
    Router,
}

impl Mode {
    pub fn as_str(self) -> &'static str {
        match self {
            Mode::Peer => "peer",
            Mode::Client => "client",
            Mode::Router => "router",
        }
    }
}

/// The `[bridge]` section: present means `fbbus serve` links its line to the bus.
#[derive(Debug, Clone, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct BusConfig {
    pub mode: Mode,
    /// zenoh endpoints this bridge listens on, e.g. `tcp/127.0.0.1:7447`, `tls/0.0.0.0:7447`.
    pub listen: Vec<String>,
    /// zenoh endpoints this bridge connects to (other lines' bridges, or `zenohd`).
    pub connect: Vec<String>,
    /// UDP multicast scouting (finding peers on the LAN without endpoints). Off: a line
    /// links only to what its configuration names.
    pub multicast_scouting: bool,
    /// MQTT filters (within `fb/#`) of this line's messages other lines may receive.
    pub export: Vec<String>,
    /// MQTT filters (within `fb/#`) of other lines' messages this line takes in.
    pub import: Vec<String>,
    /// How long a silent link stays up (zenoh lease). A line that stops answering is
    /// marked unreachable after at most this long.
    pub lease_ms: u64,
    /// zenoh's own TLS for `tls/...` endpoints; off unless set.
    pub tls: Option<BusTls>,
}

impl Default for BusConfig {
    fn default() -> Self {
        BusConfig {
            mode: Mode::Peer,
            listen: Vec::new(),
            connect: Vec::new(),
            multicast_scouting: false,
            export: vec!["fb/#".into()],
            import: vec!["fb/#".into()],
            lease_ms: 3_000,
            tls: None,
        }
    }
}

/// TLS for the zenoh link (PEM files).
#[derive(Debug, Clone, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct BusTls {
    /// CA bundle the other side's certificate must chain to.
    pub root_ca: std::path::PathBuf,
    /// This bridge's certificate and key (listening side; also presented when connecting
    /// if `mutual` is set).
    pub cert: std::path::PathBuf,
    pub key: std::path::PathBuf,
    /// Both sides present certificates.
    #[serde(default)]
    pub mutual: bool,
}

impl BusConfig {
    /// Checks what serde cannot; returns (key, message) for the first problem.
    pub fn validate(&self, line: &str) -> Result<(), (String, String)> {
        if !keys::valid_line(line) {
            return Err((
                "broker.line".into(),
                format!(
                    "`{line}` cannot name a line on the bus: use letters, digits, `-`, `_`, `.`"
                ),
            ));
        }
        for (key, filters) in [
            ("bridge.export", &self.export),
            ("bridge.import", &self.import),
        ] {
            for f in filters {
                if !keys::bridgeable_filter(f) {
                    return Err((
                        key.into(),
                        format!("`{f}`: filters must be valid MQTT filters within fb/#"),
                    ));
                }
            }
        }
        for (key, endpoints) in [
            ("bridge.listen", &self.listen),
            ("bridge.connect", &self.connect),
        ] {
            for e in endpoints {
                if !(e.starts_with("tcp/") || e.starts_with("tls/")) {
                    return Err((
                        key.into(),
                        format!("`{e}`: endpoints are tcp/<host>:<port> or tls/<host>:<port>"),
                    ));
                }
                if e.starts_with("tls/") && self.tls.is_none() {
                    return Err((key.into(), format!("`{e}` needs a [bridge.tls] section")));
                }
            }
        }
        if self.lease_ms < 500 {
            return Err(("bridge.lease_ms".into(), "at least 500".into()));
        }
        Ok(())
    }

    /// Whether `topic` matches one of `filters`.
    pub fn allows(filters: &[String], topic: &str) -> bool {
        filters.iter().any(|f| keys::filter_matches(f, topic))
    }
}

/// What travels with every bridged message as its zenoh attachment.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Stamp {
    /// The line whose broker accepted the message from its publisher.
    pub line: String,
    /// The origin bridge's start time (µs): a restarted bridge counts from 1 again.
    pub epoch: u64,
    /// Per origin bridge, 1, 2, 3, ...; 0 for replies to a retained-message query.
    pub seq: u64,
    pub qos: u8,
    pub retain: bool,
}

const STAMP_VERSION: u8 = 1;

impl Stamp {
    /// `[version, flags, epoch (8, BE), seq (8, BE), line (UTF-8)]`; flags: bits 0-1 QoS,
    /// bit 2 RETAIN.
    pub fn encode(&self) -> Vec<u8> {
        let mut out = Vec::with_capacity(18 + self.line.len());
        out.push(STAMP_VERSION);
        out.push(self.qos.min(2) | (self.retain as u8) << 2);
        out.extend_from_slice(&self.epoch.to_be_bytes());
        out.extend_from_slice(&self.seq.to_be_bytes());
        out.extend_from_slice(self.line.as_bytes());
        out
    }

    pub fn decode(bytes: &[u8]) -> Option<Stamp> {
        if bytes.len() < 18 || bytes[0] != STAMP_VERSION {
            return None;
        }
        let flags = bytes[1];
        Some(Stamp {
            qos: flags & 0b11,
            retain: flags & 0b100 != 0,
            epoch: u64::from_be_bytes(bytes[2..10].try_into().ok()?),
            seq: u64::from_be_bytes(bytes[10..18].try_into().ok()?),
            line: std::str::from_utf8(&bytes[18..]).ok()?.to_owned(),
        })
    }
}

/// How many sequence numbers per origin [`Dedup`] remembers.
pub const DEDUP_WINDOW: u64 = 4096;

/// Drops messages already seen, per origin line: a sliding window of sequence numbers.
#[derive(Debug, Default)]
pub struct Dedup {
    origins: HashMap<String, Window>,
}

#[derive(Debug, Default)]
struct Window {
    epoch: u64,
    highest: u64,
    seen: HashSet<u64>,
    order: VecDeque<u64>,
}

impl Dedup {
    /// Whether the message is new (and now remembered). A new epoch of an origin (its
    /// bridge restarted) starts a new window.
    pub fn first_time(&mut self, stamp: &Stamp) -> bool {
        if stamp.seq == 0 {
            return true;
        }
        if !self.origins.contains_key(&stamp.line) {
            self.origins.insert(stamp.line.clone(), Window::default());
        }
        let w = self
            .origins
            .get_mut(&stamp.line)
            .expect("inserted just above");
        if stamp.epoch != w.epoch {
            if stamp.epoch < w.epoch {
                // A message of an older incarnation still in flight: its seq space is gone.
                return false;
            }
            *w = Window {
                epoch: stamp.epoch,
                ..Window::default()
            };
        }
        if stamp.seq + DEDUP_WINDOW <= w.highest || !w.seen.insert(stamp.seq) {
            return false;
        }
        w.highest = w.highest.max(stamp.seq);
        w.order.push_back(stamp.seq);
        while w.order.len() as u64 > DEDUP_WINDOW {
            if let Some(old) = w.order.pop_front() {
                w.seen.remove(&old);
            }
        }
        true
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn stamp(line: &str, epoch: u64, seq: u64) -> Stamp {
        Stamp {
            line: line.into(),
            epoch,
            seq,
            qos: 1,
            retain: true,
        }
    }

    #[test]
    fn stamps_round_trip() {
        let s = stamp("line-a", 17, 99);
        assert_eq!(Stamp::decode(&s.encode()), Some(s));
        assert_eq!(Stamp::decode(b"short"), None);
    }

    #[test]
    fn dedup_drops_repeats_per_origin_and_resets_on_a_new_epoch() {
        let mut d = Dedup::default();
        assert!(d.first_time(&stamp("a", 1, 1)));
        assert!(d.first_time(&stamp("a", 1, 3)));
        assert!(d.first_time(&stamp("a", 1, 2)), "out of order but new");
        assert!(!d.first_time(&stamp("a", 1, 3)));
        assert!(d.first_time(&stamp("b", 1, 3)), "another origin");
        assert!(d.first_time(&stamp("a", 2, 1)), "the origin restarted");
        assert!(
            !d.first_time(&stamp("a", 1, 4)),
            "the old incarnation is gone"
        );
        for seq in 2..=DEDUP_WINDOW + 10 {
            assert!(d.first_time(&stamp("a", 2, seq)));
        }
        assert!(!d.first_time(&stamp("a", 2, 5)), "older than the window");
    }

    #[test]
    fn config_defaults_are_valid_and_loopback_quiet() {
        let c = BusConfig::default();
        assert!(!c.multicast_scouting);
        assert!(c.validate("line-a").is_ok());
        assert!(c.validate("line/a").is_err());
        let bad = BusConfig {
            export: vec!["plant/#".into()],
            ..BusConfig::default()
        };
        assert!(bad.validate("a").is_err());
    }
}

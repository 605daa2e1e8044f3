//! The `[bridge]` section of the broker's configuration: how this line joins the bus,
//! and which of its messages may leave and enter.

use serde::Deserialize;

use super::keys;
use crate::topic::filter;

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
        filters.iter().any(|f| filter::matches(f, topic))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

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

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
    /// zenoh's own TLS for `tls/...` endpoints; off unless set. Required, mutual, for an
    /// endpoint that is not loopback.
    pub tls: Option<BusTls>,
    /// Who may talk to this line over a mutual-TLS bus, by certificate common name.
    pub peers: Option<BusPeers>,
    /// Filters one other line may subscribe to here (its interest tokens). Each is
    /// matched against every exported message, so their number is the export path's
    /// cost; beyond it a line's new filter is not honoured.
    pub max_remote_filters_per_line: usize,
    /// Filters all other lines together may subscribe to here.
    pub max_remote_filters: usize,
    /// `mode = "client"` only: one zenoh session per router in `connect` instead of one
    /// session on the first router that answers. A zenoh client is on one router at a
    /// time, so lines that prefer different routers are split when the link between the
    /// routers is cut; with a session on each, every line meets every other on every
    /// router, and stays on the bus while any one of them reaches it (issue 32). Each
    /// message then arrives once per router path: the copies are dropped by their stamp.
    pub session_per_router: bool,
}

/// The most sessions [`BusConfig::session_per_router`] opens: a plant runs two routers,
/// sometimes three.
pub const MAX_ROUTER_SESSIONS: usize = 4;

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
            peers: None,
            max_remote_filters_per_line: 1_000,
            max_remote_filters: 10_000,
            session_per_router: false,
        }
    }
}

/// TLS for the zenoh link (PEM files).
#[derive(Debug, Clone, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct BusTls {
    /// CA bundle the other side's certificate must chain to (the plant's bus CA; old and
    /// new CA during a CA rotation).
    pub root_ca: std::path::PathBuf,
    /// This line's certificate and key, presented when listening and when connecting.
    /// The certificate's common name is the line's identity: it must be `[broker] line`.
    pub cert: std::path::PathBuf,
    pub key: std::path::PathBuf,
    /// Both sides present certificates (default). `false` (the other side is not
    /// identified, so no access control) is only accepted on a loopback-only bus.
    #[serde(default = "yes")]
    pub mutual: bool,
}

fn yes() -> bool {
    true
}

/// `[bridge.peers]`: who may talk to this line over a mutual-TLS bus, by the common name
/// of the certificate they present. Anyone else is refused by zenoh's access control
/// (default deny); see [`super::access`] for exactly what each may do.
#[derive(Debug, Clone, Default, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct BusPeers {
    /// Other lines (certificate CN = line name): may publish, announce and answer only
    /// under their own line's keys.
    pub lines: Vec<String>,
    /// zenoh routers (`zenohd`, router-mode lines) that forward every line's traffic.
    /// Trusted with every line's keys: a router certificate is a plant-wide secret.
    pub routers: Vec<String>,
    /// zenoh applications that may read the bus (subscribe, query) and nothing else.
    pub readers: Vec<String>,
}

impl BusPeers {
    fn names(&self) -> impl Iterator<Item = (&'static str, &String)> {
        let tag = |key: &'static str| move |name| (key, name);
        (self.lines.iter().map(tag("bridge.peers.lines")))
            .chain(self.routers.iter().map(tag("bridge.peers.routers")))
            .chain(self.readers.iter().map(tag("bridge.peers.readers")))
    }
}

/// Whether a zenoh endpoint (`tcp/127.0.0.1:7447`, `tls/[::1]:7447#iface=lo`) is on
/// loopback: 127.0.0.0/8, `::1` or `localhost`. Anything else, `0.0.0.0` and host names
/// included, can be reached from (or reaches) another host.
pub fn loopback_endpoint(endpoint: &str) -> bool {
    let Some((_, address)) = endpoint.split_once('/') else {
        return false;
    };
    let address = address.split(['?', '#']).next().unwrap_or_default();
    let Some((host, _port)) = address.rsplit_once(':') else {
        return false;
    };
    let host = host
        .strip_prefix('[')
        .and_then(|h| h.strip_suffix(']'))
        .unwrap_or(host);
    match host.parse::<std::net::IpAddr>() {
        Ok(ip) => ip.is_loopback(),
        Err(_) => host.eq_ignore_ascii_case("localhost"),
    }
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
        for (key, value) in [
            (
                "bridge.max_remote_filters_per_line",
                self.max_remote_filters_per_line,
            ),
            ("bridge.max_remote_filters", self.max_remote_filters),
        ] {
            if value == 0 {
                return Err((
                    key.into(),
                    "must be at least 1 (another line's subscriptions are how it receives \
                     this line's messages)"
                        .into(),
                ));
            }
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
                if self.mutual_tls() && !e.starts_with("tls/") {
                    return Err((
                        key.into(),
                        format!(
                            "`{e}`: with mutual TLS every endpoint is tls/: a tcp/ peer has \
                             no certificate, and the access control would refuse all it sends"
                        ),
                    ));
                }
                let secure = e.starts_with("tls/") && self.mutual_tls();
                if !(secure || loopback_endpoint(e)) {
                    let tls = e.replacen("tcp/", "tls/", 1);
                    return Err((
                        key.into(),
                        format!(
                            "`{e}` is not loopback: a bus endpoint between hosts needs mutual \
                             TLS, or any host that reaches it could speak for every line. Use \
                             `{tls}` with [bridge.tls] (root_ca, cert, key: the certificate's \
                             common name is this line's name; `fbbus bus-cert`) and \
                             [bridge.peers] naming the lines and routers it accepts \
                             (docs/bus-security.md)"
                        ),
                    ));
                }
            }
        }
        if self.session_per_router
            && (self.mode != Mode::Client
                || !(2..=MAX_ROUTER_SESSIONS).contains(&self.connect.len()))
        {
            return Err((
                "bridge.session_per_router".into(),
                format!(
                    "takes mode = \"client\" and 2 to {MAX_ROUTER_SESSIONS} routers in \
                     `connect`: it opens one zenoh session per router (this is mode = \"{}\" \
                     with {} endpoint(s))",
                    self.mode.as_str(),
                    self.connect.len()
                ),
            ));
        }
        if self.lease_ms < 500 {
            return Err(("bridge.lease_ms".into(), "at least 500".into()));
        }
        match (&self.peers, self.mutual_tls()) {
            (Some(_), false) => {
                return Err((
                    "bridge.peers".into(),
                    "needs [bridge.tls] with mutual = true: a peer is known by its certificate"
                        .into(),
                ))
            }
            (None, true) => {
                return Err((
                    "bridge.peers".into(),
                    "a mutual-TLS bus needs [bridge.peers]: name the lines (lines = [...]), \
                     zenoh routers (routers = [...]) and read-only applications \
                     (readers = [...]) it accepts, by certificate common name"
                        .into(),
                ))
            }
            _ => {}
        }
        if let Some(peers) = &self.peers {
            if peers.names().next().is_none() {
                return Err((
                    "bridge.peers".into(),
                    "names nobody: list at least one line, router or reader".into(),
                ));
            }
            for (key, name) in peers.names() {
                if !keys::valid_line(name) {
                    return Err((
                        key.into(),
                        format!(
                            "`{name}` cannot be a certificate name on the bus: use letters, \
                             digits, `-`, `_`, `.`"
                        ),
                    ));
                }
            }
        }
        Ok(())
    }

    /// Said once when the bridge starts: a peer that connects somewhere but does not
    /// listen can be reached only by the bridges it connects to itself. That is right for
    /// the second of two lines; but zenoh routers do not pass messages between peers, so
    /// through a router such a line federates with nothing but the router (issue 32,
    /// `tests/plant.rs`), and nothing else says so.
    pub fn reach_note(&self) -> Option<&'static str> {
        (self.mode == Mode::Peer && self.listen.is_empty() && !self.connect.is_empty()).then_some(
            "[bridge] mode = \"peer\" without `listen`: only the bridges this line connects to \
             can reach it. zenoh routers do not pass messages between peers: behind zenoh \
             routers, use mode = \"client\", or give the line a `listen` endpoint the other \
             lines can reach (they then link to it directly)",
        )
    }

    /// Whether both sides of every TLS link present certificates, which is what zenoh's
    /// access control identifies peers by.
    pub fn mutual_tls(&self) -> bool {
        self.tls.as_ref().is_some_and(|t| t.mutual)
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
    fn a_peer_that_does_not_listen_is_told_how_it_is_reached() {
        let connect = vec!["tcp/127.0.0.1:7447".to_owned()];
        let peer = BusConfig {
            connect: connect.clone(),
            ..BusConfig::default()
        };
        assert!(peer.reach_note().is_some());
        let listening = BusConfig {
            listen: vec!["tcp/127.0.0.1:7448".into()],
            ..peer.clone()
        };
        assert!(listening.reach_note().is_none());
        let client = BusConfig {
            mode: Mode::Client,
            ..peer
        };
        assert!(client.reach_note().is_none());
        assert!(BusConfig::default().reach_note().is_none());
    }

    #[test]
    fn a_session_per_router_takes_a_client_and_two_to_four_routers() {
        let routers = |n: usize| {
            (0..n)
                .map(|i| format!("tcp/127.0.0.1:{}", 7447 + i))
                .collect()
        };
        let at = |mode, n| BusConfig {
            mode,
            connect: routers(n),
            session_per_router: true,
            ..BusConfig::default()
        };
        assert!(at(Mode::Client, 2).validate("line-a").is_ok());
        assert!(at(Mode::Client, MAX_ROUTER_SESSIONS)
            .validate("line-a")
            .is_ok());
        for bad in [
            at(Mode::Client, 1),
            at(Mode::Client, MAX_ROUTER_SESSIONS + 1),
            at(Mode::Peer, 2),
            at(Mode::Router, 2),
        ] {
            let (key, message) = bad.validate("line-a").unwrap_err();
            assert_eq!(key, "bridge.session_per_router");
            assert!(message.contains("mode = \"client\""), "{message}");
        }
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

    #[test]
    fn remote_filter_shares_are_at_least_one() {
        for (per_line, all, key) in [
            (0, 10, Some("bridge.max_remote_filters_per_line")),
            (5, 0, Some("bridge.max_remote_filters")),
            (1, 1, None),
        ] {
            let config = BusConfig {
                max_remote_filters_per_line: per_line,
                max_remote_filters: all,
                ..BusConfig::default()
            };
            assert_eq!(
                config.validate("line-a").err().map(|(k, _)| k),
                key.map(String::from)
            );
        }
    }

    #[test]
    fn loopback_endpoints_are_told_apart_from_the_rest() {
        for e in [
            "tcp/127.0.0.1:7447",
            "tls/127.0.0.5:7447",
            "tcp/[::1]:7447",
            "tls/localhost:7447",
            "tcp/127.0.0.1:7447#iface=lo",
        ] {
            assert!(loopback_endpoint(e), "{e}");
        }
        for e in [
            "tcp/0.0.0.0:7447",
            "tls/[::]:7447",
            "tls/10.0.2.1:7447",
            "tls/line-b.plant:7447",
            "tcp/127.0.0.1",
            "garbage",
            "tcp/ü:1",
        ] {
            assert!(!loopback_endpoint(e), "{e}");
        }
    }

    fn tls(mutual: bool) -> Option<BusTls> {
        Some(BusTls {
            root_ca: "ca.crt".into(),
            cert: "a.crt".into(),
            key: "a.key".into(),
            mutual,
        })
    }

    #[test]
    fn a_bus_between_hosts_needs_mutual_tls_and_named_peers() {
        let peers = Some(BusPeers {
            lines: vec!["line-b".into()],
            ..BusPeers::default()
        });
        let plain = BusConfig {
            listen: vec!["tcp/0.0.0.0:7447".into()],
            ..BusConfig::default()
        };
        let (key, message) = plain.validate("line-a").unwrap_err();
        assert_eq!(key, "bridge.listen");
        assert!(message.contains("tls/0.0.0.0:7447"), "{message}");
        assert!(message.contains("[bridge.peers]"), "{message}");
        let one_way = BusConfig {
            connect: vec!["tls/10.0.0.2:7447".into()],
            tls: tls(false),
            ..BusConfig::default()
        };
        assert_eq!(one_way.validate("line-a").unwrap_err().0, "bridge.connect");
        let unnamed = BusConfig {
            connect: vec!["tls/10.0.0.2:7447".into()],
            tls: tls(true),
            ..BusConfig::default()
        };
        assert_eq!(unnamed.validate("line-a").unwrap_err().0, "bridge.peers");
        let secure = BusConfig {
            peers: peers.clone(),
            ..unnamed.clone()
        };
        assert_eq!(secure.validate("line-a"), Ok(()));
        let bad_name = BusConfig {
            peers: Some(BusPeers {
                readers: vec!["his torian".into()],
                ..BusPeers::default()
            }),
            ..unnamed
        };
        assert_eq!(
            bad_name.validate("line-a").unwrap_err().0,
            "bridge.peers.readers"
        );
        // Loopback stays simple; peers without mutual TLS name nobody zenoh could know.
        let local = BusConfig {
            listen: vec!["tcp/127.0.0.1:7447".into()],
            ..BusConfig::default()
        };
        assert_eq!(local.validate("line-a"), Ok(()));
        let unknowable = BusConfig {
            peers: peers.clone(),
            ..local.clone()
        };
        assert_eq!(unknowable.validate("line-a").unwrap_err().0, "bridge.peers");
        // With mutual TLS a plain tcp/ link could only be refused: say so at start.
        let mixed = BusConfig {
            listen: vec!["tls/127.0.0.1:7447".into()],
            connect: vec!["tcp/127.0.0.1:7448".into()],
            tls: tls(true),
            peers,
            ..local
        };
        assert_eq!(mixed.validate("line-a").unwrap_err().0, "bridge.connect");
    }
}

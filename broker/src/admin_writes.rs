//! Who may change the line through the admin endpoint: [`LocalWrite`], the one extractor
//! every write route (putting a profile, forgetting a device) takes, credentials or not.
//!
//! Two rules, for two attacks:
//!
//! - **From the broker's own host.** The peer must be a loopback address: an admin bound
//!   to a plant network for Prometheus must not let that network retype or remove the
//!   line's devices.
//! - **Addressed as the broker's host (DNS rebinding).** A web page on any site can make
//!   a browser on the broker's host send requests to `127.0.0.1`: it lets its own name
//!   resolve to 127.0.0.1 a moment after the page loaded, and the browser, which sees the
//!   same name, lets the page read and write. The peer is then loopback, so the first
//!   rule passes; what gives it away is the name: the `Host` header (and `Origin`, which
//!   a browser sends with every write) says `evil.example`, not an address of the
//!   broker. So a write is accepted only when `Host` and, if present, `Origin` name an IP
//!   address, `localhost`, or a name in `[admin] allowed_hosts`. `fbbus declare`,
//!   `fbbus devices forget` and curl address the broker by IP and send no `Origin`. The
//!   console only reads.
//!
//! Refusals are 403, counted in `fbbus_admin_writes_refused_total{reason}` (remote, host,
//! origin) and logged at most once a minute per reason.

use std::net::{IpAddr, SocketAddr};
use std::sync::{Arc, Mutex, PoisonError};
use std::time::{Duration, Instant};

use axum::extract::{ConnectInfo, FromRequestParts};
use axum::http::request::Parts;
use axum::http::{header, HeaderMap, StatusCode};
use axum::response::{IntoResponse, Response};

use crate::metrics::Metrics;

/// The longest time between two log lines about refused writes, per reason.
const LOG_INTERVAL: Duration = Duration::from_secs(60);

/// Why a write was refused: the label of `fbbus_admin_writes_refused_total`.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Refusal {
    /// The peer is not on the broker's host.
    Remote,
    /// `Host` names something that is not the broker.
    Host,
    /// `Origin` names something that is not the broker.
    Origin,
}

impl Refusal {
    pub const ALL: [Refusal; 3] = [Refusal::Remote, Refusal::Host, Refusal::Origin];

    pub fn label(self) -> &'static str {
        match self {
            Refusal::Remote => "remote",
            Refusal::Host => "host",
            Refusal::Origin => "origin",
        }
    }

    fn message(self) -> &'static str {
        match self {
            Refusal::Remote => {
                "admin writes are accepted from the broker's own host only (fbbus declare, \
                 fbbus devices forget); remote admin writes are refused"
            }
            Refusal::Host | Refusal::Origin => {
                "admin writes must address the broker by IP address, localhost or a name in \
                 [admin] allowed_hosts (Host and Origin headers): a page that rebinds its \
                 own name to this host may not write"
            }
        }
    }
}

/// The names under which the broker accepts writes (`[admin] allowed_hosts`), and the
/// refusals' log budget. Shared by every request.
pub struct WriteRules {
    /// Lower-case host names, besides IP addresses and `localhost`.
    names: Vec<String>,
    metrics: Arc<Metrics>,
    last_logged: Mutex<[Option<Instant>; 3]>,
}

impl WriteRules {
    pub fn new(names: &[String], metrics: Arc<Metrics>) -> WriteRules {
        WriteRules {
            names: names.iter().map(|n| n.to_ascii_lowercase()).collect(),
            metrics,
            last_logged: Mutex::default(),
        }
    }

    /// Whether `host` (a header's host, without port) is the broker.
    fn is_ours(&self, host: &str) -> bool {
        let bare = host
            .strip_prefix('[')
            .and_then(|h| h.strip_suffix(']'))
            .unwrap_or(host);
        bare.parse::<IpAddr>().is_ok()
            || host.eq_ignore_ascii_case("localhost")
            || self.names.iter().any(|n| n.eq_ignore_ascii_case(host))
    }

    /// The rule for one request: peer, then `Host`, then `Origin`.
    pub fn check(&self, peer: Option<IpAddr>, headers: &HeaderMap) -> Result<(), Refusal> {
        if !peer.is_some_and(|ip| ip.to_canonical().is_loopback()) {
            return Err(Refusal::Remote);
        }
        if let Some(host) = headers.get(header::HOST) {
            let host = host.to_str().ok().map(strip_port);
            if !host.is_some_and(|h| self.is_ours(h)) {
                return Err(Refusal::Host);
            }
        }
        if let Some(origin) = headers.get(header::ORIGIN) {
            let host = origin
                .to_str()
                .ok()
                .and_then(|o| o.split_once("://"))
                .map(|(_, rest)| strip_port(rest.split('/').next().unwrap_or("")));
            if !host.is_some_and(|h| self.is_ours(h)) {
                return Err(Refusal::Origin);
            }
        }
        Ok(())
    }

    /// Counts, logs (at most once a minute per reason) and answers a refusal.
    fn refuse(&self, refusal: Refusal, peer: Option<IpAddr>) -> Response {
        self.metrics
            .admin_writes_refused
            .with_label_values(&[refusal.label()])
            .inc();
        let due = {
            let mut last = self
                .last_logged
                .lock()
                .unwrap_or_else(PoisonError::into_inner);
            let index = Refusal::ALL.iter().position(|r| *r == refusal).unwrap_or(0);
            let due = last[index].is_none_or(|t| t.elapsed() >= LOG_INTERVAL);
            if due {
                last[index] = Some(Instant::now());
            }
            due
        };
        if due {
            let peer = peer.map_or_else(|| "unknown".to_owned(), |p| p.to_string());
            tracing::warn!(
                %peer,
                reason = refusal.label(),
                "admin write refused (403); further refusals this minute are only counted \
                 (fbbus_admin_writes_refused_total)"
            );
        }
        (
            StatusCode::FORBIDDEN,
            axum::Json(serde_json::json!({"error": refusal.message()})),
        )
            .into_response()
    }
}

/// `host[:port]` or `[v6]:port` → the host.
fn strip_port(authority: &str) -> &str {
    if authority.starts_with('[') {
        return authority
            .find(']')
            .and_then(|end| authority.get(..=end))
            .unwrap_or(authority);
    }
    match authority.rsplit_once(':') {
        // One colon: a port. More: a bare IPv6 address (not valid in Host; kept whole).
        Some((host, _)) if !host.contains(':') => host,
        _ => authority,
    }
}

/// A write request that passed [`WriteRules::check`]: the admin state's rules, taken by
/// every route that changes something, so the rule is in one place.
pub struct LocalWrite;

/// What [`LocalWrite`] needs of the router's state.
pub trait HasWriteRules {
    fn write_rules(&self) -> &WriteRules;
}

#[axum::async_trait]
impl<S: HasWriteRules + Send + Sync> FromRequestParts<S> for LocalWrite {
    type Rejection = Response;

    async fn from_request_parts(parts: &mut Parts, state: &S) -> Result<Self, Self::Rejection> {
        let peer = parts
            .extensions
            .get::<ConnectInfo<SocketAddr>>()
            .map(|ConnectInfo(peer)| peer.ip().to_canonical());
        let rules = state.write_rules();
        match rules.check(peer, &parts.headers) {
            Ok(()) => Ok(LocalWrite),
            Err(refusal) => Err(rules.refuse(refusal, peer)),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn rules() -> WriteRules {
        WriteRules::new(&["Line1-Broker".into()], Arc::new(Metrics::new()))
    }

    fn check(peer: Option<&str>, host: Option<&str>, origin: Option<&str>) -> Result<(), Refusal> {
        let mut headers = HeaderMap::new();
        if let Some(h) = host {
            headers.insert(header::HOST, h.parse().unwrap());
        }
        if let Some(o) = origin {
            headers.insert(header::ORIGIN, o.parse().unwrap());
        }
        let peer = peer.map(|p| p.parse::<SocketAddr>().unwrap().ip());
        rules().check(peer, &headers)
    }

    /// Admin writes are answered to the broker's own host only, IPv4-mapped loopback
    /// included; a request whose peer is unknown is refused too.
    #[test]
    fn admin_writes_are_loopback_only() {
        for peer in [
            "127.0.0.1:5000",
            "127.0.0.2:5000",
            "[::1]:5000",
            "[::ffff:127.0.0.1]:5000",
        ] {
            assert_eq!(check(Some(peer), None, None), Ok(()), "{peer}");
        }
        for peer in [
            Some("10.0.0.7:5000"),
            Some("[::ffff:10.0.0.7]:5000"),
            Some("[fe80::1]:5000"),
            None,
        ] {
            assert_eq!(check(peer, None, None), Err(Refusal::Remote), "{peer:?}");
        }
    }

    /// A rebinding page names itself in Host and Origin: refused; the broker's own names
    /// (addresses, localhost, the configured ones) are accepted, with or without a port.
    #[test]
    fn a_page_that_rebinds_its_name_may_not_write() {
        let local = Some("127.0.0.1:4000");
        for host in [
            "127.0.0.1:9883",
            "127.0.0.1",
            "[::1]:9883",
            "localhost:9883",
            "LOCALHOST",
            "line1-broker:9883",
        ] {
            assert_eq!(check(local, Some(host), None), Ok(()), "{host}");
        }
        for host in [
            "evil.example",
            "evil.example:9883",
            "127.0.0.1.evil.example",
            "",
        ] {
            assert_eq!(check(local, Some(host), None), Err(Refusal::Host), "{host}");
        }
        assert_eq!(
            check(local, Some("127.0.0.1:9883"), Some("http://127.0.0.1:9883")),
            Ok(())
        );
        assert_eq!(
            check(
                local,
                Some("localhost:9883"),
                Some("https://line1-broker:9883/")
            ),
            Ok(())
        );
        for origin in [
            "http://evil.example",
            "http://evil.example:9883",
            "null",
            "evil",
        ] {
            assert_eq!(
                check(local, Some("127.0.0.1:9883"), Some(origin)),
                Err(Refusal::Origin),
                "{origin}"
            );
        }
    }
}

//! Where the broker is and how to log in: `mqtt://host:port` or `mqtts://host:port`, MQTT
//! 3.1.1 or 5, username and password, a CA for TLS.
//!
//! The password never comes from the command line (it would sit in shell history, `ps`
//! and the report's recorded command): it is read from an environment variable or a file,
//! and [`Target`]'s `Debug` prints `<redacted>`.

use std::fmt;
use std::path::PathBuf;

use crate::Error;

/// The MQTT protocol version the harness speaks.
#[derive(Debug, Clone, Copy, PartialEq, Eq, serde::Serialize)]
pub enum Mqtt {
    V311,
    V5,
}

/// One broker to load.
#[derive(Clone)]
pub struct Target {
    /// As given: `mqtt://127.0.0.1:1883`.
    pub address: String,
    pub host: String,
    pub port: u16,
    pub tls: bool,
    /// PEM CA certificate(s) for `mqtts://`; without it, TLS fails (no system roots).
    pub ca: Option<PathBuf>,
    pub username: Option<String>,
    pub password: Option<String>,
    pub mqtt: Mqtt,
}

impl fmt::Debug for Target {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.debug_struct("Target")
            .field("address", &self.address)
            .field("mqtt", &self.mqtt)
            .field("username", &self.username)
            .field("password", &self.password.as_ref().map(|_| "<redacted>"))
            .finish_non_exhaustive()
    }
}

impl Target {
    /// Parses `mqtt://host[:port]` (default port 1883) or `mqtts://host[:port]` (8883).
    /// A bare `host:port` means `mqtt://`.
    pub fn parse(address: &str) -> Result<Target, Error> {
        let bad = |why: &str| {
            Error::Target(format!(
                "{address:?}: {why} (expected mqtt://host:port or mqtts://host:port)"
            ))
        };
        let (tls, rest) = if let Some(rest) = address.strip_prefix("mqtts://") {
            (true, rest)
        } else if let Some(rest) = address.strip_prefix("mqtt://") {
            (false, rest)
        } else if address.contains("://") {
            return Err(bad("unknown scheme"));
        } else {
            (false, address)
        };
        let rest = rest.trim_end_matches('/');
        let (host, port) = match rest.rsplit_once(':') {
            // `[::1]:1883`
            Some((host, port)) if !host.contains(':') || host.ends_with(']') => (
                host,
                port.parse::<u16>()
                    .map_err(|_| bad("port is not a number 1-65535"))?,
            ),
            _ => (rest, if tls { 8883 } else { 1883 }),
        };
        let host = host.trim_start_matches('[').trim_end_matches(']');
        if host.is_empty() {
            return Err(bad("no host"));
        }
        Ok(Target {
            address: address.to_owned(),
            host: host.to_owned(),
            port,
            tls,
            ca: None,
            username: None,
            password: None,
            mqtt: Mqtt::V311,
        })
    }

    /// Whether the host is this machine (127.0.0.0/8, ::1, `localhost`): the harness can
    /// then find the broker's process and read its resident memory.
    pub fn is_loopback(&self) -> bool {
        self.host == "localhost"
            || self
                .host
                .parse::<std::net::IpAddr>()
                .is_ok_and(|ip| ip.is_loopback())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn parses_addresses_with_defaults() {
        let t = Target::parse("mqtt://127.0.0.1:1884").unwrap();
        assert_eq!((t.host.as_str(), t.port, t.tls), ("127.0.0.1", 1884, false));
        let t = Target::parse("mqtts://line1").unwrap();
        assert_eq!((t.host.as_str(), t.port, t.tls), ("line1", 8883, true));
        let t = Target::parse("[::1]:1999").unwrap();
        assert_eq!((t.host.as_str(), t.port), ("::1", 1999));
        assert!(t.is_loopback());
        assert!(!Target::parse("mqtt://10.0.0.5").unwrap().is_loopback());
        assert!(Target::parse("http://x").is_err());
        assert!(Target::parse("mqtt://x:99999").is_err());
    }

    #[test]
    fn debug_never_shows_the_password() {
        let mut t = Target::parse("mqtt://127.0.0.1").unwrap();
        t.password = Some("s3cret-pw".into());
        assert!(!format!("{t:?}").contains("s3cret"));
    }
}

//! The broker's configuration: one TOML file, validated completely before anything binds.
//!
//! Every option is documented in `deploy/fbbus.example.toml`. The embedded default
//! ([`DEFAULT_CONFIG`]) is what `fbbus serve` runs with no `--config`: a loopback-only line
//! broker with anonymous access, so the first command of the README works on a fresh machine.
//!
//! Validation refuses a file with the file name, the key and what is wrong. The security
//! rules live here because they are configuration facts: a listener that is reachable from
//! the network must require a password, anonymous access is a loopback-only privilege, and
//! an admin endpoint reachable from the network must require credentials of its own
//! (`[admin] password_file`, never the devices' `[auth] password_file`).

use std::path::{Path, PathBuf};
use std::time::Duration;

use serde::Deserialize;

// Each section's type lives with the module it configures, which owns its defaults; this
// reader only assembles them (and is imported by none of them).
pub use crate::admin::AdminSection;
pub use crate::authenticator::{AuthSection, ThrottleSection};
pub use crate::console::ConsoleSection;
pub use crate::listener::ListenerSection;
pub use crate::logging::{LogFormat, LogSection};
pub use crate::sparkplug::SparkplugSection;
pub use crate::store::PersistenceSection;
pub use crate::tls::TlsSection;

pub use self::broker::{BrokerSection, MAX_CONNECTIONS, MAX_WORKER_THREADS, MIN_QUEUED_BYTES};
pub use self::fb::FbSection;

mod broker;
mod fb;
#[cfg(test)]
mod tests;
mod validate;

/// The configuration `fbbus serve` uses when no `--config` is given.
pub const DEFAULT_CONFIG: &str = r#"
[broker]
line = "line-1"

[[listener]]
name = "mqtt-loopback"
bind = "127.0.0.1:1883"
allow_anonymous = true

[admin]
bind = "127.0.0.1:9883"

# Retained messages and persistent sessions survive a restart, next to the registry.
[persistence]
dir = "fbbus-store"
"#;

#[derive(Debug, thiserror::Error)]
pub enum ConfigError {
    /// The OS error is the source, not part of this message: `fbbus: {e:#}` prints the
    /// chain, and printed it twice when it was both.
    #[error("cannot read config file {path}")]
    Read {
        path: PathBuf,
        #[source]
        source: std::io::Error,
    },
    /// The file is not TOML, or a value has the wrong type: toml's own message, which
    /// names the line and column and draws a caret under the place over several lines,
    /// kept as it is; the key when there is one (a syntax error has none).
    #[error("config file {file}: {}\n{message}", key_part(.key))]
    Parse {
        file: String,
        key: String,
        message: String,
    },
    #[error("config file {file}: key `{key}`: {message}")]
    Invalid {
        file: String,
        key: String,
        message: String,
    },
}

/// `key `a.b`:` before a parse error's message, or nothing where serde had no key yet
/// (`.`: a syntax error before any value).
fn key_part(key: &str) -> String {
    match key {
        "" | "." => "not TOML:".to_owned(),
        key => format!("key `{key}`:"),
    }
}

#[derive(Debug, Clone, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Config {
    #[serde(default)]
    pub broker: BrokerSection,
    #[serde(default)]
    pub auth: AuthSection,
    #[serde(default, rename = "listener")]
    pub listeners: Vec<ListenerSection>,
    #[serde(default)]
    pub admin: AdminSection,
    #[serde(default)]
    pub log: LogSection,
    /// The line console on the admin endpoint (`console`).
    #[serde(default)]
    pub console: ConsoleSection,
    #[serde(default)]
    pub fb: FbSection,
    /// What survives a restart (`store`).
    #[serde(default)]
    pub persistence: PersistenceSection,
    /// Present: link this line to the other lines' brokers over zenoh (`bridge`).
    pub bridge: Option<fb_bridge::bus::BusConfig>,
    /// The line as a Sparkplug B edge node (`sparkplug`); off by default.
    #[serde(default)]
    pub sparkplug: SparkplugSection,
}

impl Config {
    /// The embedded default configuration.
    pub fn embedded_default() -> Config {
        Config::parse(DEFAULT_CONFIG, "<embedded default>")
            .expect("the embedded default configuration is valid")
    }

    /// Reads and validates a configuration file.
    pub fn load(path: &Path) -> Result<Config, ConfigError> {
        let text = std::fs::read_to_string(path).map_err(|source| ConfigError::Read {
            path: path.to_owned(),
            source,
        })?;
        let mut config = Config::parse(&text, &path.display().to_string())?;
        config.resolve_paths(path.parent().unwrap_or(Path::new(".")));
        config.validate_files(&path.display().to_string())?;
        Ok(config)
    }

    /// Parses and validates configuration text; `file` names it in errors.
    pub fn parse(text: &str, file: &str) -> Result<Config, ConfigError> {
        let deserializer = toml::Deserializer::new(text);
        let config: Config =
            serde_path_to_error::deserialize(deserializer).map_err(|e| ConfigError::Parse {
                file: file.to_owned(),
                key: e.path().to_string(),
                message: e.into_inner().to_string().trim_end().to_owned(),
            })?;
        config.validate(file)?;
        Ok(config)
    }

    /// Relative paths in a config file are relative to the file's directory.
    fn resolve_paths(&mut self, base: &Path) {
        let fix = |p: &mut PathBuf| {
            if p.is_relative() {
                *p = base.join(&*p);
            }
        };
        if let Some(p) = self.auth.password_file.as_mut() {
            fix(p)
        }
        if let Some(p) = self.auth.acl_file.as_mut() {
            fix(p)
        }
        if let Some(p) = self.admin.password_file.as_mut() {
            fix(p)
        }
        if !self.fb.registry_file.as_os_str().is_empty() {
            fix(&mut self.fb.registry_file);
        }
        if !self.fb.profiles_dir.as_os_str().is_empty() {
            fix(&mut self.fb.profiles_dir);
        }
        fix(&mut self.persistence.dir);
        if let Some(tls) = self.bridge.as_mut().and_then(|b| b.tls.as_mut()) {
            fix(&mut tls.root_ca);
            fix(&mut tls.cert);
            fix(&mut tls.key);
        }
        for l in &mut self.listeners {
            if let Some(tls) = l.tls.as_mut() {
                fix(&mut tls.cert);
                fix(&mut tls.key);
                if let Some(ca) = tls.client_ca.as_mut() {
                    fix(ca)
                }
            }
        }
    }

    pub fn connect_timeout(&self) -> Duration {
        Duration::from_millis(self.broker.connect_timeout_ms)
    }

    /// `broker.dead_link_timeout_s`; None when it is 0 (kernel defaults).
    pub fn dead_link_timeout(&self) -> Option<Duration> {
        (self.broker.dead_link_timeout_s > 0)
            .then(|| Duration::from_secs(self.broker.dead_link_timeout_s))
    }
}

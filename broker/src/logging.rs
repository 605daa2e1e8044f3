//! `tracing` set-up: a level filter from the config (RUST_LOG wins when set), text or JSON.
//!
//! What is logged is chosen at the call sites: client ids, user names, topics, peers and
//! reasons, never a password, a hash or a packet dump (a CONNECT's Debug output would
//! contain the password).

use serde::Deserialize;
use tracing_subscriber::EnvFilter;

#[derive(Debug, Clone, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct LogSection {
    /// A tracing filter: `info`, `debug`, `warn,broker=debug`. RUST_LOG overrides it.
    /// The default keeps rumqttd's router (per-subscription chatter) at warn.
    pub level: String,
    pub format: LogFormat,
}

impl Default for LogSection {
    fn default() -> Self {
        LogSection {
            level: "info,rumqttd=warn".into(),
            format: LogFormat::Text,
        }
    }
}

#[derive(Debug, Clone, Copy, Deserialize, PartialEq, Eq)]
#[serde(rename_all = "lowercase")]
pub enum LogFormat {
    Text,
    Json,
}

pub fn init(log: &LogSection) -> Result<(), String> {
    let filter = match std::env::var("RUST_LOG") {
        Ok(env) if !env.is_empty() => EnvFilter::try_new(env),
        _ => EnvFilter::try_new(&log.level),
    }
    .map_err(|e| format!("log level `{}`: {e}", log.level))?;
    // Colours only on a terminal: a journal or a log file gets plain text.
    let builder = tracing_subscriber::fmt()
        .with_env_filter(filter)
        .with_ansi(std::io::IsTerminal::is_terminal(&std::io::stderr()))
        .with_writer(std::io::stderr);
    let result = match log.format {
        LogFormat::Text => builder.try_init(),
        LogFormat::Json => builder.json().flatten_event(true).try_init(),
    };
    result.map_err(|e| e.to_string())
}

/// A warning logged at most once a minute for the whole broker, however often its cause
/// recurs (the count is in a metric): `static LOGGED: OnceAMinute = OnceAMinute::new();`
/// and `if LOGGED.due() { tracing::warn!(...) }`.
pub struct OnceAMinute(std::sync::Mutex<Option<std::time::Instant>>);

impl OnceAMinute {
    pub const fn new() -> OnceAMinute {
        OnceAMinute(std::sync::Mutex::new(None))
    }

    /// Whether a minute passed since the last time this said yes (yes the first time).
    pub fn due(&self) -> bool {
        let mut last = self
            .0
            .lock()
            .unwrap_or_else(std::sync::PoisonError::into_inner);
        let due = last.is_none_or(|at| at.elapsed() >= std::time::Duration::from_secs(60));
        if due {
            *last = Some(std::time::Instant::now());
        }
        due
    }
}

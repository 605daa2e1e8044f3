//! `tracing` set-up: a level filter from the config (RUST_LOG wins when set), text or JSON.
//!
//! What is logged is chosen at the call sites: client ids, user names, topics, peers and
//! reasons, never a password, a hash or a packet dump (a CONNECT's Debug output would
//! contain the password). How often is bounded too: [`OnceAMinute`] for a cause that
//! recurs, and [`OUTSIDE`] for what a stranger can multiply (connections, topics).

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

/// Warnings and notes that outside input causes "once per connection", "per topic" or
/// "per client id" (a refused CONNECT, an ACL denial, a refused typed publication, a
/// connection closed for a malformed packet or as a slow consumer). Each
/// site logs once where it says, but a stranger opens connections in a loop and invents
/// topics, so once per connection is not once: a loop of refused CONNECTs logged a line
/// each, and each connection up to 1,024 refused topics. These sites share one budget for
/// the whole broker, [`OUTSIDE_LINES_PER_MINUTE`] lines a minute; past it the rest of the
/// minute's are left out (every refusal is still counted in its metric), one line says
/// so when it happens, and the next minute's first call says how many were left out.
pub static OUTSIDE: LogBudget = LogBudget::new(OUTSIDE_LINES_PER_MINUTE);

/// Lines a minute for [`OUTSIDE`]: 10 a second, about 100 KB a minute of log at most.
pub const OUTSIDE_LINES_PER_MINUTE: u32 = 600;

/// At most a number of lines a minute, shared by every call site that asks it; see
/// [`OUTSIDE`].
pub struct LogBudget {
    per_minute: u32,
    window: std::sync::Mutex<Window>,
}

struct Window {
    start: Option<std::time::Instant>,
    used: u32,
    left_out: u64,
}

impl LogBudget {
    pub const fn new(per_minute: u32) -> LogBudget {
        LogBudget {
            per_minute,
            window: std::sync::Mutex::new(Window {
                start: None,
                used: 0,
                left_out: 0,
            }),
        }
    }

    /// Whether one more line may be logged now; a no is counted as left out.
    pub fn allow(&self) -> bool {
        self.allow_at(std::time::Instant::now())
    }

    fn allow_at(&self, now: std::time::Instant) -> bool {
        let mut window = self
            .window
            .lock()
            .unwrap_or_else(std::sync::PoisonError::into_inner);
        let minute = std::time::Duration::from_secs(60);
        if window
            .start
            .is_none_or(|start| now.saturating_duration_since(start) >= minute)
        {
            if window.left_out > 0 {
                tracing::warn!(
                    left_out = window.left_out,
                    "refusals of outside input not logged in the last minute (over the log's \
                     budget of {} lines a minute; their metrics count every one)",
                    self.per_minute
                );
            }
            *window = Window {
                start: Some(now),
                used: 0,
                left_out: 0,
            };
        }
        if window.used < self.per_minute {
            window.used += 1;
            return true;
        }
        if window.left_out == 0 {
            tracing::warn!(
                "more than {} refusals of outside input this minute: the rest of the \
                 minute's are not logged (their metrics count every one)",
                self.per_minute
            );
        }
        window.left_out += 1;
        false
    }
}

#[cfg(test)]
mod tests {
    use std::time::{Duration, Instant};

    use super::LogBudget;

    /// The budget is shared: past it nothing is logged until the minute is over, and the
    /// next minute starts with a full budget.
    #[test]
    fn a_budget_lets_so_many_lines_a_minute_through() {
        let budget = LogBudget::new(3);
        let start = Instant::now();
        let allowed = |at: Duration| budget.allow_at(start + at);
        assert!(allowed(Duration::ZERO));
        assert!(allowed(Duration::from_secs(1)));
        assert!(allowed(Duration::from_secs(2)));
        for s in 3..60 {
            assert!(!allowed(Duration::from_secs(s)), "allowed at {s} s");
        }
        assert_eq!(budget.window.lock().unwrap().left_out, 57);
        assert!(allowed(Duration::from_secs(60)));
        assert_eq!(budget.window.lock().unwrap().left_out, 0);
        assert!(allowed(Duration::from_secs(61)));
        assert!(allowed(Duration::from_secs(62)));
        assert!(!allowed(Duration::from_secs(63)));
    }
}

//! `[persistence]`: whether the store runs, where, how often it syncs, and its bounds.

use std::path::PathBuf;
use std::time::Duration;

use serde::Deserialize;

/// `[persistence]` in the configuration.
#[derive(Debug, Clone, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct PersistenceSection {
    pub enabled: bool,
    /// The store's directory; relative to the config file's directory, or to the working
    /// directory for the embedded default.
    pub dir: PathBuf,
    /// `"always"`, `"every <N> ms"` or `"os"` (see `deploy/fbbus.example.toml`).
    pub fsync: Fsync,
    /// Bytes of retained and queued messages the store keeps at most.
    pub max_bytes: usize,
    /// Messages queued for one session at most.
    pub max_queued_messages: usize,
    /// Bytes and messages queued for the persistent sessions of one identity at most
    /// (issue 33): one user's sessions cannot take the store another user's need.
    pub max_bytes_per_identity: usize,
    pub max_messages_per_identity: usize,
    /// The log is compacted once it is this large and four times what is live.
    pub compact_min_bytes: u64,
}

impl Default for PersistenceSection {
    fn default() -> Self {
        PersistenceSection {
            enabled: true,
            dir: PathBuf::from("fbbus-store"),
            fsync: Fsync::Every(Duration::from_millis(100)),
            max_bytes: 256 * 1024 * 1024,
            max_queued_messages: 1000,
            // An eighth of the store: eight identities, not one, to fill it.
            max_bytes_per_identity: 32 * 1024 * 1024,
            // A hundred sessions' full queues.
            max_messages_per_identity: 100_000,
            compact_min_bytes: 64 * 1024 * 1024,
        }
    }
}

/// When the log is forced to the disk.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Fsync {
    /// Before every acknowledgement: survives a power cut.
    Always,
    /// Written before every acknowledgement, synced at most this long after: survives a
    /// crash of fbbus; a power cut loses at most this much.
    Every(Duration),
    /// Written before every acknowledgement, synced when the OS decides.
    Os,
}

impl<'de> Deserialize<'de> for Fsync {
    fn deserialize<D: serde::Deserializer<'de>>(d: D) -> Result<Fsync, D::Error> {
        let text = String::deserialize(d)?;
        text.parse().map_err(serde::de::Error::custom)
    }
}

impl std::str::FromStr for Fsync {
    type Err = String;
    fn from_str(text: &str) -> Result<Fsync, String> {
        let t = text.trim();
        match t {
            "always" => return Ok(Fsync::Always),
            "os" => return Ok(Fsync::Os),
            _ => {}
        }
        let ms = t
            .strip_prefix("every")
            .and_then(|rest| rest.trim().strip_suffix("ms"))
            .and_then(|n| n.trim().parse::<u64>().ok())
            .filter(|n| (1..=60_000).contains(n));
        match ms {
            Some(ms) => Ok(Fsync::Every(Duration::from_millis(ms))),
            None => Err(format!(
                "`{text}`: expected \"always\", \"os\" or \"every <N> ms\" with N from 1 to 60000"
            )),
        }
    }
}

//! The birth/death sequence numbers (`bdSeq`) of the edge nodes the view speaks for, kept
//! across restarts.
//!
//! Sparkplug pairs every NBIRTH with the NDEATH of the same MQTT session by `bdSeq`
//! (0-255, one more at each new session): a host ignores an NDEATH whose `bdSeq` is not
//! the one of the birth it holds, so a late death of an old session never kills a newer
//! one. The broker's "session" is its process, so the number must survive the process:
//! it is read at start, the next one is written (synced, renamed over the file) before
//! the NBIRTH that carries it is published, and a file that cannot be read is reported
//! and replaced, never trusted in part.
//!
//! One file, `sparkplug-bdseq.json` in the persistence directory: `{"line-1": 7, ...}`,
//! the line's own node and the other lines' nodes this broker announces, at most
//! [`MAX_NODES`] of them.

use std::collections::BTreeMap;
use std::io::Write;
use std::path::{Path, PathBuf};

/// Nodes whose `bdSeq` the file keeps at most: this line and the other lines of the bus
/// (the registry keeps at most `registry::federation::MAX_LINES` of those).
pub const MAX_NODES: usize = 1024;

/// The file's name in the persistence directory.
pub const FILE_NAME: &str = "sparkplug-bdseq.json";

/// The largest file read: `MAX_NODES` entries of a 256-byte name and a number.
const MAX_FILE_BYTES: u64 = 300 * 1024;

/// The numbers, and where they are kept (None: not kept).
#[derive(Debug, Default)]
pub struct BdSeqs {
    file: Option<PathBuf>,
    numbers: BTreeMap<String, u8>,
}

impl BdSeqs {
    /// Reads the numbers kept in `dir` (None: none kept). A missing file is a first
    /// start; a file that is not what this module writes is logged and ignored.
    pub fn open(dir: Option<&Path>) -> BdSeqs {
        let Some(dir) = dir else {
            return BdSeqs::default();
        };
        let file = dir.join(FILE_NAME);
        let numbers = match read(&file) {
            Ok(numbers) => numbers,
            Err(error) => {
                if file.exists() {
                    tracing::warn!(file = %file.display(), error,
                        "Sparkplug bdSeq file not readable: numbering starts again at 0");
                }
                BTreeMap::new()
            }
        };
        BdSeqs {
            file: Some(file),
            numbers,
        }
    }

    /// The `bdSeq` of `node`'s previous session, if one was kept.
    pub fn previous(&self, node: &str) -> Option<u8> {
        self.numbers.get(node).copied()
    }

    /// Starts a new session of `node`: its next `bdSeq` (0 for a node never seen), kept
    /// before it is returned.
    pub fn next(&mut self, node: &str) -> u8 {
        let next = self.numbers.get(node).map_or(0, |n| n.wrapping_add(1));
        if self.numbers.len() < MAX_NODES || self.numbers.contains_key(node) {
            self.numbers.insert(node.to_owned(), next);
            self.write();
        }
        next
    }

    fn write(&self) {
        let Some(file) = &self.file else { return };
        let text = serde_json::to_vec(&self.numbers).unwrap_or_default();
        let tmp = file.with_extension("json.tmp");
        let written = std::fs::File::create(&tmp)
            .and_then(|mut f| f.write_all(&text).and_then(|()| f.sync_all()))
            .and_then(|()| std::fs::rename(&tmp, file));
        if let Err(e) = written {
            tracing::warn!(file = %file.display(), error = %e,
                "Sparkplug bdSeq not kept: after a restart a host may pair an old death with a new birth");
        }
    }
}

fn read(file: &Path) -> Result<BTreeMap<String, u8>, String> {
    let meta = std::fs::metadata(file).map_err(|e| e.to_string())?;
    if meta.len() > MAX_FILE_BYTES {
        return Err(format!("{} bytes, more than {MAX_FILE_BYTES}", meta.len()));
    }
    let bytes = std::fs::read(file).map_err(|e| e.to_string())?;
    let numbers: BTreeMap<String, u8> =
        serde_json::from_slice(&bytes).map_err(|e| e.to_string())?;
    if numbers.len() > MAX_NODES {
        return Err(format!("{} nodes, more than {MAX_NODES}", numbers.len()));
    }
    Ok(numbers)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn numbers_survive_a_restart_and_wrap() {
        let dir = tempfile::tempdir().unwrap();
        let mut seqs = BdSeqs::open(Some(dir.path()));
        assert_eq!(seqs.previous("line-1"), None);
        assert_eq!(seqs.next("line-1"), 0);
        assert_eq!(seqs.next("line-1"), 1);
        let mut again = BdSeqs::open(Some(dir.path()));
        assert_eq!(again.previous("line-1"), Some(1));
        assert_eq!(again.next("line-1"), 2);
        std::fs::write(dir.path().join(FILE_NAME), r#"{"line-1": 255}"#).unwrap();
        assert_eq!(BdSeqs::open(Some(dir.path())).next("line-1"), 0);
    }

    #[test]
    fn a_hostile_file_is_ignored() {
        let dir = tempfile::tempdir().unwrap();
        for text in [
            "",
            "[1]",
            r#"{"a": 256}"#,
            r#"{"a": -1}"#,
            "{\"a\": 1",
            "\u{0}",
        ] {
            std::fs::write(dir.path().join(FILE_NAME), text).unwrap();
            let mut seqs = BdSeqs::open(Some(dir.path()));
            assert_eq!(seqs.previous("a"), None, "{text:?}");
            assert_eq!(seqs.next("a"), 0);
        }
        let mut none = BdSeqs::open(None);
        assert_eq!((none.next("a"), none.next("a")), (0, 1));
    }
}

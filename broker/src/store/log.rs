//! The store's file: a header, then records appended one after the other.
//!
//! ```text
//! "FBBUSLOG" | version u32 LE | { length u32 LE | CRC-32 of the body u32 LE | body }*
//! ```
//!
//! Why a log: a QoS 1 publication is acknowledged only once it is written, so the cost
//! that matters is the write path's, and an append of a few records per network read
//! (group-committed by the writer thread, `store::writer`) is the cheapest durable write
//! there is: no index, no page rewritten, one `write` per batch and, by policy, one
//! `fsync`. The price is replay at start (a sequential read) and compaction, which
//! rewrites what is live into a new file and renames it over the old one.
//!
//! A crash can leave the last record torn (a power cut mid-write). Reading stops at the
//! first record whose length runs past the end or whose checksum does not match; what
//! follows is moved to a file beside the log (`store.log.torn-<unix seconds>`) with a
//! warning that names both files, and the log is cut there: recovered up to the last
//! intact record, nothing silently discarded. A log written by a newer fbbus (a higher
//! version) is refused with an error, never half-read.

use std::fs::{File, OpenOptions};
use std::io::{Read, Seek, SeekFrom, Write};
use std::path::{Path, PathBuf};

use super::record::Record;

const MAGIC: &[u8; 8] = b"FBBUSLOG";
/// The format this fbbus writes and reads.
pub const VERSION: u32 = 1;
pub(super) const HEADER: usize = 12;
/// A record longer than this is taken as corruption (a stored message is at most MQTT's
/// 256 MB packet, and a compaction's `Queued` record adds its targets).
const MAX_RECORD: usize = 512 * 1024 * 1024;

#[derive(Debug, thiserror::Error)]
pub enum LogError {
    #[error("store {path}: {source}")]
    Io {
        path: PathBuf,
        source: std::io::Error,
    },
    #[error(
        "store {path} was written by a newer fbbus (format {found}, this fbbus reads {VERSION}): \
         run the newer fbbus, or move the directory away to start with an empty store"
    )]
    Newer { path: PathBuf, found: u32 },
    #[error(
        "store {path} is not an fbbus store (no FBBUSLOG header): move it away, or set \
         [persistence] dir to another directory"
    )]
    Foreign { path: PathBuf },
}

/// What reading the log found.
pub struct Replay {
    pub records: Vec<Record>,
    /// Where a torn or corrupt tail was moved, and how many bytes it had.
    pub torn: Option<(PathBuf, u64)>,
}

/// The open log, appended to by the writer thread only.
pub struct Log {
    path: PathBuf,
    file: File,
    length: u64,
}

fn io_error(path: &Path) -> impl FnOnce(std::io::Error) -> LogError + '_ {
    move |source| LogError::Io {
        path: path.to_owned(),
        source,
    }
}

impl Log {
    /// Opens (or creates) the log at `path` and reads every intact record in it.
    pub fn open(path: &Path) -> Result<(Log, Replay), LogError> {
        let err = io_error(path);
        if let Some(dir) = path.parent() {
            std::fs::create_dir_all(dir).map_err(io_error(path))?;
        }
        let mut file = OpenOptions::new()
            .read(true)
            .append(true)
            .create(true)
            .open(path)
            .map_err(io_error(path))?;
        let mut bytes = Vec::new();
        file.read_to_end(&mut bytes).map_err(io_error(path))?;
        if bytes.is_empty() {
            let mut header = Vec::with_capacity(HEADER);
            header.extend_from_slice(MAGIC);
            header.extend_from_slice(&VERSION.to_le_bytes());
            file.write_all(&header).map_err(io_error(path))?;
            file.sync_all().map_err(io_error(path))?;
            sync_dir(path);
            let log = Log {
                path: path.to_owned(),
                file,
                length: HEADER as u64,
            };
            let replay = Replay {
                records: Vec::new(),
                torn: None,
            };
            return Ok((log, replay));
        }
        if bytes.len() < HEADER || &bytes[..8] != MAGIC {
            // A file shorter than its header was cut while being created: nothing in it.
            if bytes.len() < HEADER && MAGIC.starts_with(&bytes[..bytes.len().min(8)]) {
                drop(file);
                std::fs::remove_file(path).map_err(err)?;
                return Log::open(path);
            }
            return Err(LogError::Foreign {
                path: path.to_owned(),
            });
        }
        let found = u32::from_le_bytes([bytes[8], bytes[9], bytes[10], bytes[11]]);
        if found > VERSION {
            return Err(LogError::Newer {
                path: path.to_owned(),
                found,
            });
        }
        let (records, good) = parse(&bytes);
        let mut torn = None;
        if good < bytes.len() {
            let tail = &bytes[good..];
            let at = std::time::SystemTime::now()
                .duration_since(std::time::UNIX_EPOCH)
                .map(|d| d.as_secs())
                .unwrap_or(0);
            let torn_path = path.with_extension(format!("log.torn-{at}"));
            std::fs::write(&torn_path, tail).map_err(io_error(&torn_path))?;
            file.set_len(good as u64).map_err(io_error(path))?;
            file.sync_all().map_err(io_error(path))?;
            torn = Some((torn_path, tail.len() as u64));
        }
        file.seek(SeekFrom::End(0)).map_err(io_error(path))?;
        let log = Log {
            path: path.to_owned(),
            file,
            length: good as u64,
        };
        Ok((log, Replay { records, torn }))
    }

    /// Appends encoded records (`frame` output).
    pub fn append(&mut self, framed: &[u8]) -> std::io::Result<()> {
        self.file.write_all(framed)?;
        self.length += framed.len() as u64;
        Ok(())
    }

    /// Forces what was appended to the disk.
    pub fn sync(&mut self) -> std::io::Result<()> {
        self.file.sync_data()
    }

    pub fn length(&self) -> u64 {
        self.length
    }

    pub fn path(&self) -> &Path {
        &self.path
    }

    /// Replaces the log with `records` (what is live): written to a new file, synced,
    /// renamed over the log. A crash at any point leaves either the old log or the new.
    pub fn compact(&mut self, records: impl Iterator<Item = Record>) -> Result<(), LogError> {
        let tmp = self.path.with_extension("log.compacting");
        let err = io_error(&tmp);
        let mut file = File::create(&tmp).map_err(err)?;
        let mut buffer = Vec::with_capacity(1 << 20);
        buffer.extend_from_slice(MAGIC);
        buffer.extend_from_slice(&VERSION.to_le_bytes());
        let mut length = 0u64;
        for record in records {
            frame(&record, &mut buffer);
            if buffer.len() >= 1 << 20 {
                file.write_all(&buffer).map_err(io_error(&tmp))?;
                length += buffer.len() as u64;
                buffer.clear();
            }
        }
        file.write_all(&buffer).map_err(io_error(&tmp))?;
        length += buffer.len() as u64;
        file.sync_all().map_err(io_error(&tmp))?;
        std::fs::rename(&tmp, &self.path).map_err(io_error(&self.path))?;
        sync_dir(&self.path);
        let mut file = OpenOptions::new()
            .append(true)
            .open(&self.path)
            .map_err(io_error(&self.path))?;
        file.seek(SeekFrom::End(0)).map_err(io_error(&self.path))?;
        self.file = file;
        self.length = length;
        Ok(())
    }
}

/// Appends `record` to `out` as the log stores it.
pub fn frame(record: &Record, out: &mut Vec<u8>) {
    frame_body(out, |out| record.encode(out));
}

/// A `Done` record, framed ([`super::record::encode_done`]).
pub fn frame_done(client: &str, seq: u64, out: &mut Vec<u8>) {
    frame_body(out, |out| super::record::encode_done(client, seq, out));
}

fn frame_body(out: &mut Vec<u8>, body: impl FnOnce(&mut Vec<u8>)) {
    let start = out.len();
    out.extend_from_slice(&[0; 8]);
    body(out);
    let body = &out[start + 8..];
    let length = body.len() as u32;
    let crc = crc32fast::hash(body);
    out[start..start + 4].copy_from_slice(&length.to_le_bytes());
    out[start + 4..start + 8].copy_from_slice(&crc.to_le_bytes());
}

/// The intact records after the header, and where they end.
pub(super) fn parse(bytes: &[u8]) -> (Vec<Record>, usize) {
    let mut records = Vec::new();
    let mut at = HEADER;
    while let Some(head) = bytes.get(at..at + 8) {
        let length = u32::from_le_bytes([head[0], head[1], head[2], head[3]]) as usize;
        let crc = u32::from_le_bytes([head[4], head[5], head[6], head[7]]);
        if length > MAX_RECORD {
            break;
        }
        let Some(body) = bytes.get(at + 8..at + 8 + length) else {
            break;
        };
        if crc32fast::hash(body) != crc {
            break;
        }
        match Record::decode(body) {
            Ok(record) => records.push(record),
            Err(_) => break,
        }
        at += 8 + length;
    }
    (records, at)
}

/// Makes a rename or a creation in the log's directory durable (best effort: some
/// filesystems cannot sync a directory).
fn sync_dir(path: &Path) {
    if let Some(dir) = path.parent() {
        if let Ok(d) = File::open(dir) {
            let _ = d.sync_all();
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn ended(i: usize) -> Record {
        Record::Ended {
            client: format!("c{i}").into(),
        }
    }

    #[test]
    fn records_survive_reopening_and_a_torn_tail_is_cut_and_kept() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("store.log");
        let (mut log, replay) = Log::open(&path).unwrap();
        assert!(replay.records.is_empty());
        let mut bytes = Vec::new();
        for i in 0..3 {
            frame(&ended(i), &mut bytes);
        }
        log.append(&bytes).unwrap();
        drop(log);
        let (_, replay) = Log::open(&path).unwrap();
        assert_eq!(replay.records, (0..3).map(ended).collect::<Vec<_>>());
        assert!(replay.torn.is_none());

        // Every cut inside the last record: the first two survive, the rest is kept aside.
        let whole = std::fs::read(&path).unwrap();
        let last = {
            let mut b = Vec::new();
            frame(&ended(2), &mut b);
            b.len()
        };
        for cut in 1..last {
            std::fs::write(&path, &whole[..whole.len() - cut]).unwrap();
            let (_, replay) = Log::open(&path).unwrap();
            assert_eq!(replay.records, (0..2).map(ended).collect::<Vec<_>>());
            let (torn, n) = replay.torn.expect("the torn tail is reported");
            assert_eq!(n as usize, last - cut);
            assert_eq!(
                std::fs::read(&torn).unwrap(),
                whole[whole.len() - last..][..last - cut]
            );
            assert_eq!(
                std::fs::metadata(&path).unwrap().len() as usize,
                whole.len() - last
            );
        }
    }

    #[test]
    fn a_flipped_byte_stops_the_replay_there() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("store.log");
        let (mut log, _) = Log::open(&path).unwrap();
        let mut bytes = Vec::new();
        for i in 0..3 {
            frame(&ended(i), &mut bytes);
        }
        log.append(&bytes).unwrap();
        drop(log);
        let mut whole = std::fs::read(&path).unwrap();
        let n = whole.len();
        whole[n - 2] ^= 0x40;
        std::fs::write(&path, &whole).unwrap();
        let (_, replay) = Log::open(&path).unwrap();
        assert_eq!(replay.records.len(), 2);
        assert!(replay.torn.is_some());
    }

    #[test]
    fn a_newer_or_foreign_file_is_refused() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("store.log");
        let mut newer = MAGIC.to_vec();
        newer.extend_from_slice(&(VERSION + 1).to_le_bytes());
        std::fs::write(&path, &newer).unwrap();
        let e = Log::open(&path).err().unwrap().to_string();
        assert!(e.contains("newer fbbus") && e.contains("store.log"), "{e}");
        std::fs::write(&path, b"{\"json\": true}").unwrap();
        let e = Log::open(&path).err().unwrap().to_string();
        assert!(e.contains("not an fbbus store"), "{e}");
        // Untouched: the operator decides.
        assert_eq!(std::fs::read(&path).unwrap(), b"{\"json\": true}");
    }

    #[test]
    fn compaction_replaces_the_log() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("store.log");
        let (mut log, _) = Log::open(&path).unwrap();
        let mut bytes = Vec::new();
        for i in 0..100 {
            frame(&ended(i), &mut bytes);
        }
        log.append(&bytes).unwrap();
        log.compact([ended(7)].into_iter()).unwrap();
        let mut more = Vec::new();
        frame(&ended(8), &mut more);
        log.append(&more).unwrap();
        drop(log);
        let (_, replay) = Log::open(&path).unwrap();
        assert_eq!(replay.records, vec![ended(7), ended(8)]);
    }
}

//! The store's file: a header, then records appended one after the other.
//!
//! ```text
//! header:  "FBBUSLOG" | version u32 LE (2) | mark [4] | CRC-32 of the 16 bytes before
//! record:  mark [4] | length u32 LE | CRC-32 of mark, length and body, u32 LE | body
//! ```
//!
//! Why a log: a QoS 1 publication is acknowledged only once it is written, so the cost
//! that matters is the write path's, and an append of a few records per network read
//! (group-committed by the writer thread, `store::writer`) is the cheapest durable write
//! there is: no index, no page rewritten, one `write` per batch and, by policy, one
//! `fsync`. The price is replay at start (a sequential read) and compaction, which
//! rewrites what is live into a new file and renames it over the old one.
//!
//! **Damage.** Every record starts with the file's *mark*, four random bytes chosen when
//! the file is created (each compaction creates a new one), and carries a CRC-32 (crc32fast)
//! over its mark, length and body. A record that does not check out (a flipped bit, a
//! zeroed block, an impossible length) is skipped, not everything after it: replay looks
//! for the next position where a whole record starts (the mark, a length that fits, its
//! checksum and a body that decodes) and goes on from there. What it skipped is counted
//! (`fbbus_store_skipped_bytes_total{reason="damaged"}`, `..._records_total`, an estimate
//! from the marks in it), logged with its offset, copied beside the log as
//! `store.log.damaged-<unix seconds>`, and the log is compacted at once, so the damage is
//! not met again. The mark is random per file so that no message payload can carry a
//! record that replay would take for one of the store's own: to be considered at all a
//! position must start with four bytes no client knows, then pass the checksum that
//! covers them.
//!
//! **A torn tail.** A crash can leave the last record torn (a power cut mid-write): bytes
//! after which no whole record follows. They are moved to a file beside the log
//! (`store.log.torn-<unix seconds>`) with a warning that names both files, counted under
//! `reason="torn"`, and the log is cut there: recovered up to the last intact record,
//! nothing silently discarded.
//!
//! **A cut log restores a past state.** Records are appended in the order the writer
//! applied them and replay applies them in that order, so a log cut anywhere restores the
//! store exactly as it was after the last whole record before the cut: never a mix of
//! states, never a message that was not written, never one a `Done` before the cut took
//! away (`every_cut_restores_an_earlier_state_exactly`). What that means for QoS 1 and 2:
//! README.md, "Damage and truncation".
//!
//! **Versions.** Format 1 (until 2026-12: `length | CRC-32 of the body | body`, no mark,
//! a 12-byte header) is still read, the old way (stopping at the first bad record), and
//! rewritten as format 2 by a compaction at start. A log written by a newer fbbus (a
//! higher version) is refused with an error, never half-read.

use std::fs::{File, OpenOptions};
use std::io::{Read, Seek, SeekFrom, Write};
use std::path::{Path, PathBuf};

use super::record::Record;

const MAGIC: &[u8; 8] = b"FBBUSLOG";
/// The format this fbbus writes; it reads this one and format 1.
pub const VERSION: u32 = 2;
/// Format 1's header: magic and version.
const V1_HEADER: usize = 12;
/// Format 2's header: magic, version, mark, checksum.
pub(super) const HEADER: usize = 20;
/// A record's frame before its body: mark, length, checksum.
const FRAME: usize = 12;
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

/// A damaged stretch of the log that replay skipped.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Skip {
    /// Its offset in the file.
    pub offset: u64,
    pub bytes: u64,
    /// Records it held, estimated from the marks in it (at least 1).
    pub records: u64,
}

/// What reading the log found.
pub struct Replay {
    pub records: Vec<Record>,
    /// Where a torn tail was moved, how many bytes it had, and records (estimated).
    pub torn: Option<(PathBuf, u64, u64)>,
    /// Damaged stretches skipped, and where their bytes were copied.
    pub skipped: Vec<Skip>,
    pub damaged: Option<PathBuf>,
    /// The format the file was in.
    pub version: u32,
}

impl Replay {
    /// Whether the log is to be rewritten at once (compacted): it is in an older format
    /// (which this fbbus does not append to), or it has damage replay skipped.
    pub fn rewrite(&self) -> bool {
        self.version < VERSION || !self.skipped.is_empty()
    }
}

/// Frames records for one log file (its mark).
#[derive(Debug, Clone, Copy)]
pub struct Framer {
    mark: [u8; 4],
}

impl Framer {
    /// Appends `record` to `out` as the log stores it.
    pub fn frame(&self, record: &Record, out: &mut Vec<u8>) {
        self.frame_body(out, |out| record.encode(out));
    }

    /// A `Done` record, framed ([`super::record::encode_done`]).
    pub fn frame_done(&self, client: &str, seq: u64, out: &mut Vec<u8>) {
        self.frame_body(out, |out| super::record::encode_done(client, seq, out));
    }

    fn frame_body(&self, out: &mut Vec<u8>, body: impl FnOnce(&mut Vec<u8>)) {
        let start = out.len();
        out.extend_from_slice(&self.mark);
        out.extend_from_slice(&[0; 8]);
        body(out);
        let length = (out.len() - start - FRAME) as u32;
        out[start + 4..start + 8].copy_from_slice(&length.to_le_bytes());
        let crc = checksum(&out[start..start + 8], &out[start + FRAME..]);
        out[start + 8..start + FRAME].copy_from_slice(&crc.to_le_bytes());
    }
}

fn checksum(head: &[u8], body: &[u8]) -> u32 {
    let mut h = crc32fast::Hasher::new();
    h.update(head);
    h.update(body);
    h.finalize()
}

/// The open log, appended to by the writer thread only.
pub struct Log {
    path: PathBuf,
    file: File,
    length: u64,
    framer: Framer,
}

fn io_error(path: &Path) -> impl FnOnce(std::io::Error) -> LogError + '_ {
    move |source| LogError::Io {
        path: path.to_owned(),
        source,
    }
}

fn unix_secs() -> u64 {
    std::time::SystemTime::now()
        .duration_since(std::time::UNIX_EPOCH)
        .map(|d| d.as_secs())
        .unwrap_or(0)
}

/// A new file's mark: four random bytes, all different and none 0x00 or 0xFF (so neither
/// a zeroed block nor a run of one byte holds one).
fn new_mark() -> [u8; 4] {
    use std::hash::BuildHasher;
    // std's RandomState is keyed from the OS's random source.
    let random = std::collections::hash_map::RandomState::new();
    let mut n = 0u64;
    loop {
        let m = (random.hash_one((n, std::process::id(), unix_secs())) as u32).to_le_bytes();
        let distinct = (0..4).all(|i| (i + 1..4).all(|j| m[i] != m[j]));
        if distinct && !m.iter().any(|b| *b == 0 || *b == 0xff) {
            return m;
        }
        n += 1;
    }
}

fn header(mark: [u8; 4], out: &mut Vec<u8>) {
    let start = out.len();
    out.extend_from_slice(MAGIC);
    out.extend_from_slice(&VERSION.to_le_bytes());
    out.extend_from_slice(&mark);
    let crc = crc32fast::hash(&out[start..]);
    out.extend_from_slice(&crc.to_le_bytes());
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
            let mark = new_mark();
            let mut head = Vec::with_capacity(HEADER);
            header(mark, &mut head);
            file.write_all(&head).map_err(io_error(path))?;
            file.sync_all().map_err(io_error(path))?;
            sync_dir(path);
            let log = Log {
                path: path.to_owned(),
                file,
                length: HEADER as u64,
                framer: Framer { mark },
            };
            let replay = Replay {
                records: Vec::new(),
                torn: None,
                skipped: Vec::new(),
                damaged: None,
                version: VERSION,
            };
            return Ok((log, replay));
        }
        let found = match bytes.get(..V1_HEADER) {
            Some(head) if &head[..8] == MAGIC => {
                u32::from_le_bytes([head[8], head[9], head[10], head[11]])
            }
            _ => 0,
        };
        // A file shorter than its header was cut while being created: nothing in it.
        let created = match found {
            0 => bytes.len() < V1_HEADER && MAGIC.starts_with(&bytes[..bytes.len().min(8)]),
            VERSION => bytes.len() < HEADER,
            _ => false,
        };
        if created {
            drop(file);
            std::fs::remove_file(path).map_err(err)?;
            return Log::open(path);
        }
        if found == 0 {
            return Err(LogError::Foreign {
                path: path.to_owned(),
            });
        }
        if found > VERSION {
            return Err(LogError::Newer {
                path: path.to_owned(),
                found,
            });
        }
        let parsed = parse(&bytes);
        let at = unix_secs();
        let mut torn = None;
        let end = parsed.end;
        if end < bytes.len() {
            let tail = &bytes[end..];
            let torn_path = path.with_extension(format!("log.torn-{at}"));
            std::fs::write(&torn_path, tail).map_err(io_error(&torn_path))?;
            file.set_len(end as u64).map_err(io_error(path))?;
            file.sync_all().map_err(io_error(path))?;
            torn = Some((torn_path, tail.len() as u64, marks(tail, parsed.mark)));
        }
        let mut damaged = None;
        if !parsed.skipped.is_empty() {
            let damaged_path = path.with_extension(format!("log.damaged-{at}"));
            let mut kept = Vec::new();
            for s in &parsed.skipped {
                kept.extend_from_slice(&bytes[s.offset as usize..(s.offset + s.bytes) as usize]);
            }
            std::fs::write(&damaged_path, kept).map_err(io_error(&damaged_path))?;
            damaged = Some(damaged_path);
        }
        file.seek(SeekFrom::End(0)).map_err(io_error(path))?;
        let log = Log {
            path: path.to_owned(),
            file,
            length: end as u64,
            // A format 1 log is compacted before anything is appended (`Replay::rewrite`).
            framer: Framer { mark: parsed.mark },
        };
        let replay = Replay {
            records: parsed.records,
            torn,
            skipped: parsed.skipped,
            damaged,
            version: found,
        };
        Ok((log, replay))
    }

    /// How records are framed for this file (its mark changes at each compaction).
    pub fn framer(&self) -> Framer {
        self.framer
    }

    /// Appends framed records ([`Framer`] output).
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

    /// Replaces the log with `records` (what is live): written to a new file (in this
    /// fbbus's format, with a new mark), synced, renamed over the log. A crash at any point
    /// leaves either the old log or the new.
    pub fn compact(&mut self, records: impl Iterator<Item = Record>) -> Result<(), LogError> {
        let tmp = self.path.with_extension("log.compacting");
        let err = io_error(&tmp);
        let mut file = File::create(&tmp).map_err(err)?;
        let framer = Framer { mark: new_mark() };
        let mut buffer = Vec::with_capacity(1 << 20);
        header(framer.mark, &mut buffer);
        let mut length = 0u64;
        for record in records {
            framer.frame(&record, &mut buffer);
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
        self.framer = framer;
        Ok(())
    }
}

/// What the bytes of a log hold.
pub(super) struct Parsed {
    pub records: Vec<Record>,
    /// Where the intact part ends: what follows is a torn tail.
    pub end: usize,
    /// Damaged stretches skipped before `end`.
    pub skipped: Vec<Skip>,
    /// The file's format (0: no header of a known format, nothing read).
    pub version: u32,
    pub mark: [u8; 4],
}

/// Reads the records of a log (header included): every whole record, skipping damaged
/// stretches, up to a torn tail.
pub(super) fn parse(bytes: &[u8]) -> Parsed {
    let mut p = Parsed {
        records: Vec::new(),
        end: bytes.len().min(HEADER),
        skipped: Vec::new(),
        version: 0,
        mark: [0; 4],
    };
    let Some(head) = bytes.get(..V1_HEADER).filter(|h| &h[..8] == MAGIC) else {
        return p;
    };
    match u32::from_le_bytes([head[8], head[9], head[10], head[11]]) {
        1 => {
            p.version = 1;
            // Its records are rewritten with a mark of their own.
            p.mark = new_mark();
            parse_v1(bytes, &mut p);
        }
        2 if bytes.len() >= HEADER => {
            p.version = 2;
            p.mark = header_mark(bytes);
            parse_v2(bytes, &mut p);
        }
        _ => {}
    }
    p
}

/// The mark in a format 2 header; if the header fails its checksum, the first record's,
/// when that is a whole record.
fn header_mark(bytes: &[u8]) -> [u8; 4] {
    let mark = [bytes[12], bytes[13], bytes[14], bytes[15]];
    let crc = u32::from_le_bytes([bytes[16], bytes[17], bytes[18], bytes[19]]);
    if crc32fast::hash(&bytes[..16]) == crc {
        return mark;
    }
    match bytes.get(HEADER..HEADER + 4) {
        Some(m) => {
            let first = [m[0], m[1], m[2], m[3]];
            match record_at(bytes, HEADER, first) {
                Some(_) => first,
                None => mark,
            }
        }
        None => mark,
    }
}

/// The whole, valid record at `at`, and where it ends.
fn record_at(bytes: &[u8], at: usize, mark: [u8; 4]) -> Option<(Record, usize)> {
    let head = bytes.get(at..at.checked_add(FRAME)?)?;
    if head[..4] != mark {
        return None;
    }
    let length = u32::from_le_bytes([head[4], head[5], head[6], head[7]]) as usize;
    if length > MAX_RECORD {
        return None;
    }
    let end = at + FRAME + length;
    let body = bytes.get(at + FRAME..end)?;
    let crc = u32::from_le_bytes([head[8], head[9], head[10], head[11]]);
    if checksum(&head[..8], body) != crc {
        return None;
    }
    Record::decode(body).ok().map(|r| (r, end))
}

/// How many times `mark` occurs in `bytes`, at least 1: the records a damaged stretch held.
fn marks(bytes: &[u8], mark: [u8; 4]) -> u64 {
    (bytes.windows(4).filter(|w| *w == mark).count() as u64).max(1)
}

fn parse_v2(bytes: &[u8], p: &mut Parsed) {
    let mark = p.mark;
    let mut at = HEADER;
    while at < bytes.len() {
        if let Some((record, next)) = record_at(bytes, at, mark) {
            p.records.push(record);
            at = next;
            continue;
        }
        // Damaged or torn: the next position where a whole record starts.
        let mut next = None;
        let mut from = at + 1;
        while let Some(i) = bytes
            .get(from..)
            .and_then(|rest| rest.windows(4).position(|w| w == mark))
        {
            let candidate = from + i;
            if let Some(found) = record_at(bytes, candidate, mark) {
                next = Some((candidate, found));
                break;
            }
            from = candidate + 1;
        }
        let Some((candidate, (record, after))) = next else {
            break;
        };
        p.skipped.push(Skip {
            offset: at as u64,
            bytes: (candidate - at) as u64,
            records: marks(&bytes[at..candidate], mark),
        });
        p.records.push(record);
        at = after;
    }
    p.end = at;
}

/// Format 1: `length | CRC-32 of the body | body`, read up to the first bad record.
fn parse_v1(bytes: &[u8], p: &mut Parsed) {
    let mut at = V1_HEADER;
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
            Ok(record) => p.records.push(record),
            Err(_) => break,
        }
        at += 8 + length;
    }
    p.end = at;
}

/// A format 2 log of `records` and where each record ends (tests elsewhere in the store).
#[cfg(test)]
pub(super) fn log_of(records: &[Record]) -> (Vec<u8>, Vec<usize>) {
    let framer = Framer { mark: new_mark() };
    let mut bytes = Vec::new();
    header(framer.mark, &mut bytes);
    let mut ends = Vec::new();
    for r in records {
        framer.frame(r, &mut bytes);
        ends.push(bytes.len());
    }
    (bytes, ends)
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
    use crate::store::record::Message;

    fn ended(i: usize) -> Record {
        Record::Ended {
            client: format!("c{i}").into(),
        }
    }

    /// Records of different types and sizes.
    fn mixed(i: usize) -> Record {
        match i % 3 {
            0 => ended(i),
            1 => Record::Done {
                client: "hmi".into(),
                seq: i as u64,
            },
            _ => Record::Publish {
                seq: i as u64,
                message: Message {
                    topic: bytes::Bytes::from(format!("line/{i}")),
                    payload: bytes::Bytes::from(vec![i as u8; i % 40]),
                    qos: 2,
                    retain: false,
                    properties: None,
                    publisher: "press".into(),
                },
            },
        }
    }

    /// A log's bytes with `records`, and where each record starts and ends.
    fn log_bytes(records: &[Record]) -> (Vec<u8>, Vec<(usize, usize)>) {
        let framer = Framer { mark: new_mark() };
        let mut bytes = Vec::new();
        header(framer.mark, &mut bytes);
        let mut spans = Vec::new();
        for r in records {
            let start = bytes.len();
            framer.frame(r, &mut bytes);
            spans.push((start, bytes.len()));
        }
        (bytes, spans)
    }

    /// Format 1, as fbbus wrote it until format 2.
    fn log_bytes_v1(records: &[Record]) -> Vec<u8> {
        let mut bytes = MAGIC.to_vec();
        bytes.extend_from_slice(&1u32.to_le_bytes());
        for r in records {
            let mut body = Vec::new();
            r.encode(&mut body);
            bytes.extend_from_slice(&(body.len() as u32).to_le_bytes());
            bytes.extend_from_slice(&crc32fast::hash(&body).to_le_bytes());
            bytes.extend_from_slice(&body);
        }
        bytes
    }

    #[test]
    fn records_survive_reopening_and_a_torn_tail_is_cut_and_kept() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("store.log");
        let (mut log, replay) = Log::open(&path).unwrap();
        assert!(replay.records.is_empty());
        let mut bytes = Vec::new();
        for i in 0..3 {
            log.framer().frame(&ended(i), &mut bytes);
        }
        log.append(&bytes).unwrap();
        drop(log);
        let (_, replay) = Log::open(&path).unwrap();
        assert_eq!(replay.records, (0..3).map(ended).collect::<Vec<_>>());
        assert!(replay.torn.is_none() && replay.skipped.is_empty() && !replay.rewrite());

        // Every cut inside the last record: the first two survive, the rest is kept aside.
        let whole = std::fs::read(&path).unwrap();
        let last = {
            let mut b = Vec::new();
            Framer { mark: [1; 4] }.frame(&ended(2), &mut b);
            b.len()
        };
        for cut in 1..last {
            std::fs::write(&path, &whole[..whole.len() - cut]).unwrap();
            let (_, replay) = Log::open(&path).unwrap();
            assert_eq!(replay.records, (0..2).map(ended).collect::<Vec<_>>());
            assert!(replay.skipped.is_empty(), "a torn tail is not a skip");
            let (torn, n, records) = replay.torn.expect("the torn tail is reported");
            assert_eq!((n as usize, records), (last - cut, 1));
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

    /// Issue 33: one flipped bit anywhere in a record (its mark, length, checksum or body)
    /// loses that record and no other; in the last record, it is a torn tail.
    #[test]
    fn every_flipped_bit_loses_only_its_record() {
        let records: Vec<Record> = (0..12).map(mixed).collect();
        let (bytes, spans) = log_bytes(&records);
        for (i, &(start, end)) in spans.iter().enumerate() {
            for bit in start * 8..end * 8 {
                let mut damaged = bytes.clone();
                damaged[bit / 8] ^= 1 << (bit % 8);
                let p = parse(&damaged);
                let mut want = records.clone();
                want.remove(i);
                assert_eq!(p.records, want, "record {i}, bit {bit}");
                if i + 1 == spans.len() {
                    assert_eq!(p.end, start, "torn tail");
                    assert!(p.skipped.is_empty());
                } else {
                    assert_eq!(p.end, bytes.len());
                    assert_eq!(
                        p.skipped,
                        [Skip {
                            offset: start as u64,
                            bytes: (end - start) as u64,
                            records: 1,
                        }],
                        "record {i}, bit {bit}"
                    );
                }
            }
        }
    }

    /// Issue 33, the report: a damaged byte in the middle of a large log. Everything else
    /// is restored; the skip is reported with its offset and its bytes kept aside.
    #[test]
    fn a_damaged_byte_in_the_middle_skips_one_record_not_the_rest() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("store.log");
        let (mut log, _) = Log::open(&path).unwrap();
        let records: Vec<Record> = (0..20_000).map(mixed).collect();
        let mut bytes = Vec::new();
        let mut spans = Vec::new();
        for r in &records {
            let start = log.length() as usize + bytes.len();
            log.framer().frame(r, &mut bytes);
            spans.push((start, log.length() as usize + bytes.len()));
        }
        log.append(&bytes).unwrap();
        drop(log);
        let mut whole = std::fs::read(&path).unwrap();
        let (start, end) = spans[10_001];
        let at = (start + end) / 2;
        whole[at] ^= 0x10;
        std::fs::write(&path, &whole).unwrap();
        let (_, replay) = Log::open(&path).unwrap();
        let mut want = records.clone();
        want.remove(10_001);
        assert_eq!(replay.records.len(), want.len());
        assert!(replay.records == want);
        assert!(replay.torn.is_none(), "nothing after the damage is lost");
        assert_eq!(
            replay.skipped,
            [Skip {
                offset: start as u64,
                bytes: (end - start) as u64,
                records: 1
            }]
        );
        assert!(
            replay.rewrite(),
            "compacted at once, so the damage is not met again"
        );
        let kept = std::fs::read(replay.damaged.expect("the damaged bytes are kept")).unwrap();
        assert_eq!(kept, whole[start..end]);
        // The log itself is left as it is (the store compacts it).
        assert_eq!(std::fs::read(&path).unwrap(), whole);
    }

    /// A log cut at any point restores exactly the records before the cut: never one that
    /// was not whole, never more than were written.
    #[test]
    fn every_cut_restores_the_whole_records_before_it() {
        let records: Vec<Record> = (0..30).map(mixed).collect();
        let (bytes, spans) = log_bytes(&records);
        for cut in 0..=bytes.len() {
            let p = parse(&bytes[..cut]);
            let whole = spans.iter().filter(|(_, end)| *end <= cut).count();
            assert_eq!(p.records, records[..whole], "cut at {cut}");
            assert!(p.skipped.is_empty(), "cut at {cut}: a cut is a torn tail");
            assert_eq!(
                p.end,
                spans[..whole].last().map_or(HEADER.min(cut), |s| s.1)
            );
        }
        // Several damaged stretches and a cut: what is whole and undamaged, in order.
        let mut damaged = bytes.clone();
        for i in [3, 4, 9, 20] {
            damaged[spans[i].0 + 5] ^= 0x80;
        }
        for cut in (spans[15].0..=bytes.len()).step_by(7) {
            let p = parse(&damaged[..cut]);
            let want: Vec<Record> = (0..records.len())
                .filter(|i| ![3, 4, 9, 20].contains(i) && spans[*i].1 <= cut)
                .map(|i| records[i].clone())
                .collect();
            assert_eq!(p.records, want, "cut at {cut}");
            // Records 3 and 4 are one stretch; 20 is a torn tail until a record follows it.
            let stretches = 2 + usize::from(cut >= spans[21].1);
            assert_eq!(p.skipped.len(), stretches, "cut at {cut}");
            assert_eq!(p.skipped[0].records, 2);
        }
    }

    /// A message's payload that carries what looks like records (framed with a mark of
    /// the sender's choosing) is never read as the store's own, even when the record that
    /// carries it is damaged and replay searches through it.
    #[test]
    fn records_in_a_payload_are_not_taken_for_the_stores() {
        let mut forged = Vec::new();
        let guess = Framer { mark: *b"FBBU" };
        for i in 0..50 {
            guess.frame(&ended(i), &mut forged);
        }
        let carrier = Record::Publish {
            seq: 1,
            message: Message {
                topic: bytes::Bytes::from_static(b"x"),
                payload: bytes::Bytes::from(forged),
                qos: 1,
                retain: true,
                properties: None,
                publisher: "p".into(),
            },
        };
        let records = vec![ended(900), carrier, ended(901)];
        let (mut bytes, spans) = log_bytes(&records);
        bytes[spans[1].0 + 4] ^= 0x01; // the carrier's length
        let p = parse(&bytes);
        assert_eq!(p.records, [ended(900), ended(901)]);
    }

    #[test]
    fn a_damaged_header_mark_is_taken_from_the_first_record() {
        let records: Vec<Record> = (0..5).map(mixed).collect();
        let (mut bytes, _) = log_bytes(&records);
        bytes[13] ^= 0x04;
        assert_eq!(parse(&bytes).records, records);
    }

    #[test]
    fn a_format_1_log_is_read_and_marked_for_rewriting() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("store.log");
        let records: Vec<Record> = (0..30).map(mixed).collect();
        std::fs::write(&path, log_bytes_v1(&records)).unwrap();
        let (mut log, replay) = Log::open(&path).unwrap();
        assert_eq!(replay.version, 1);
        assert_eq!(replay.records, records);
        assert!(replay.rewrite());
        // Rewritten (what the store does at once), it is format 2.
        log.compact(replay.records.into_iter()).unwrap();
        drop(log);
        let (_, replay) = Log::open(&path).unwrap();
        assert_eq!((replay.version, replay.records), (VERSION, records));
        // Format 1 as it was: stops at a bad record.
        let mut old = log_bytes_v1(&[ended(1), ended(2), ended(3)]);
        let n = old.len();
        old[n - 2] ^= 0x40;
        std::fs::write(&path, &old).unwrap();
        let (_, replay) = Log::open(&path).unwrap();
        assert_eq!(replay.records, [ended(1), ended(2)]);
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
        // A header cut while it was created: an empty log.
        let (_, replay) = {
            let mut head = Vec::new();
            header([1, 2, 3, 4], &mut head);
            std::fs::write(&path, &head[..15]).unwrap();
            Log::open(&path).unwrap()
        };
        assert!(replay.records.is_empty() && replay.torn.is_none());
        assert_eq!(std::fs::metadata(&path).unwrap().len(), HEADER as u64);
    }

    /// The `store_replay` fuzz target's seeds (broker/fuzz/seeds/store_log.py) are what
    /// their names say: each damaged one loses one record, the cut ones a tail.
    #[test]
    fn the_fuzz_seeds_are_whole_damaged_and_cut_logs() {
        let dir = Path::new(env!("CARGO_MANIFEST_DIR")).join("fuzz/seeds/store_replay");
        let read = |name: &str| parse(&std::fs::read(dir.join(name)).unwrap());
        let whole = read("v2-whole.store");
        assert!(whole.records.len() > 40 && whole.skipped.is_empty());
        assert_eq!(read("v1-whole.store").records, whole.records);
        for name in [
            "v2-damaged-byte.store",
            "v2-damaged-length.store",
            "v2-zeroed-block.store",
        ] {
            let p = read(name);
            assert_eq!(p.skipped.len(), 1, "{name}");
            assert!(p.records.len() < whole.records.len(), "{name}");
            assert!(p.records.len() + 4 > whole.records.len(), "{name}");
            assert!(p.records.iter().all(|r| whole.records.contains(r)));
        }
        assert_eq!(read("v2-damaged-header-mark.store").records, whole.records);
        for name in ["v2-cut-in-half.store", "v1-cut-in-half.store"] {
            let p = read(name);
            let n = p.records.len();
            assert!(n > 0 && n < whole.records.len(), "{name}");
            assert_eq!(p.records, whole.records[..n], "{name}");
        }
        let bytes = std::fs::read(dir.join("v2-damaged-and-cut.store")).unwrap();
        let p = parse(&bytes);
        assert_eq!(p.skipped.len(), 1);
        assert!(p.end < bytes.len(), "a torn tail");
        assert!(p.records.len() + 2 < whole.records.len());
        assert!(p.records.iter().all(|r| whole.records.contains(r)));
    }

    #[test]
    fn compaction_replaces_the_log() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("store.log");
        let (mut log, _) = Log::open(&path).unwrap();
        let mut bytes = Vec::new();
        for i in 0..100 {
            log.framer().frame(&ended(i), &mut bytes);
        }
        log.append(&bytes).unwrap();
        let before = log.framer().mark;
        log.compact([ended(7)].into_iter()).unwrap();
        assert_ne!(log.framer().mark, before, "a new file, a new mark");
        let mut more = Vec::new();
        log.framer().frame(&ended(8), &mut more);
        log.append(&more).unwrap();
        drop(log);
        let (_, replay) = Log::open(&path).unwrap();
        assert_eq!(replay.records, vec![ended(7), ended(8)]);
    }
}

//! The password file: one `user:HASH` line per user.
//!
//! The format is Mosquitto's, so a Mosquitto password file loads as it is
//! and fbbus files stay readable by people who know Mosquitto. Lines are
//! `user:HASH`; blank lines and lines starting with `#` are ignored. A user
//! name is non-empty and contains no `:`, whitespace or control characters.
//!
//! Load errors name the file, the 1-based line and the problem, and quote
//! the user name only once it has been validated: a line without `:` might
//! be a pasted password, and the hash text is never quoted at all.
//!
//! [`PasswordFile::save`] writes a temporary file next to the target, syncs
//! it and renames it over the target, so a crash or full disk never leaves a
//! half-written file that would lock every device out. The new file is
//! created with mode 0600. Comments are not preserved by `save`.

use std::collections::HashMap;
use std::fmt;
use std::fs;
use std::io::{self, Write as _};
use std::path::{Path, PathBuf};

use rand::Rng as _;

use crate::hash::{dummy_verify, HashError, StoredHash};

/// The outcome of checking a user's password.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Verification {
    /// The password is right. `legacy` is true when the stored hash is a
    /// Mosquitto format that should be replaced with argon2id.
    Accepted { legacy: bool },
    /// Unknown user or wrong password (deliberately indistinguishable).
    Rejected,
}

/// Why a password file could not be loaded or saved, or an entry not set.
#[derive(Debug, thiserror::Error)]
pub enum PasswordFileError {
    #[error("cannot read password file {}: {io}", path.display())]
    Read { path: PathBuf, io: io::Error },
    #[error("cannot write password file {}: {io}", path.display())]
    Write { path: PathBuf, io: io::Error },
    #[error("{}line {line}: {problem}", display_path(path))]
    Line {
        /// The file, when loaded from one.
        path: Option<PathBuf>,
        /// 1-based line number.
        line: usize,
        problem: LineProblem,
    },
    #[error(
        "invalid user name: it must be non-empty and contain no `:`, whitespace \
         or control characters"
    )]
    InvalidUserName,
}

fn display_path(path: &Option<PathBuf>) -> String {
    match path {
        Some(path) => format!("{}: ", path.display()),
        None => String::new(),
    }
}

/// What is wrong with one line of a password file.
#[derive(Debug, thiserror::Error)]
pub enum LineProblem {
    #[error("expected `user:hash` but there is no `:`")]
    MissingColon,
    #[error(
        "the user name is empty or contains whitespace or control characters; \
         user names must be non-empty and contain no `:`, whitespace or control characters"
    )]
    InvalidUserName,
    #[error("user `{user}`: {problem}")]
    InvalidHash { user: String, problem: HashError },
    #[error("user `{user}` is already defined on line {first_line}; remove one of the two lines")]
    DuplicateUser { user: String, first_line: usize },
}

/// A loaded password file: users and their hashes, in file order.
#[derive(Clone, Default)]
pub struct PasswordFile {
    entries: Vec<(String, StoredHash)>,
    /// User name → index into `entries`.
    index: HashMap<String, usize>,
}

impl PasswordFile {
    /// Reads and parses the password file at `path`.
    pub fn load(path: &Path) -> Result<PasswordFile, PasswordFileError> {
        let text = fs::read_to_string(path).map_err(|io| PasswordFileError::Read {
            path: path.to_owned(),
            io,
        })?;
        PasswordFile::parse(&text).map_err(|err| match err {
            PasswordFileError::Line { line, problem, .. } => PasswordFileError::Line {
                path: Some(path.to_owned()),
                line,
                problem,
            },
            other => other,
        })
    }

    /// Parses password-file text.
    pub fn parse(text: &str) -> Result<PasswordFile, PasswordFileError> {
        let mut file = PasswordFile::default();
        let mut first_seen: HashMap<&str, usize> = HashMap::new();
        for (number, line) in (1..).zip(text.lines()) {
            let at = |problem| PasswordFileError::Line {
                path: None,
                line: number,
                problem,
            };
            let line = line.trim();
            if line.is_empty() || line.starts_with('#') {
                continue;
            }
            let (user, hash) = line.split_once(':').ok_or(at(LineProblem::MissingColon))?;
            if !valid_user_name(user) {
                return Err(at(LineProblem::InvalidUserName));
            }
            if let Some(&first_line) = first_seen.get(user) {
                return Err(at(LineProblem::DuplicateUser {
                    user: user.to_owned(),
                    first_line,
                }));
            }
            let hash = StoredHash::parse(hash).map_err(|problem| {
                at(LineProblem::InvalidHash {
                    user: user.to_owned(),
                    problem,
                })
            })?;
            first_seen.insert(user, number);
            file.insert(user, hash);
        }
        Ok(file)
    }

    /// Writes the file atomically (temporary file in the same directory,
    /// fsync, rename over `path`) with Unix mode 0600.
    pub fn save(&self, path: &Path) -> Result<(), PasswordFileError> {
        let write_error = |io| PasswordFileError::Write {
            path: path.to_owned(),
            io,
        };
        let mut text = String::new();
        for (user, hash) in &self.entries {
            text.push_str(user);
            text.push(':');
            text.push_str(&hash.phc());
            text.push('\n');
        }
        write_atomically(path, text.as_bytes()).map_err(write_error)
    }

    /// The stored hash for `user`, if any.
    pub fn get(&self, user: &str) -> Option<&StoredHash> {
        self.index.get(user).map(|&i| &self.entries[i].1)
    }

    /// Adds `user` or replaces their hash (keeping their position).
    pub fn set(&mut self, user: &str, hash: StoredHash) -> Result<(), PasswordFileError> {
        if !valid_user_name(user) {
            return Err(PasswordFileError::InvalidUserName);
        }
        self.insert(user, hash);
        Ok(())
    }

    /// Removes `user`; returns whether they existed.
    pub fn remove(&mut self, user: &str) -> bool {
        let Some(removed) = self.index.remove(user) else {
            return false;
        };
        self.entries.remove(removed);
        for i in self.index.values_mut() {
            if *i > removed {
                *i -= 1;
            }
        }
        true
    }

    /// User names in file order.
    pub fn users(&self) -> impl Iterator<Item = &str> {
        self.entries.iter().map(|(user, _)| user.as_str())
    }

    pub fn len(&self) -> usize {
        self.entries.len()
    }

    pub fn is_empty(&self) -> bool {
        self.entries.is_empty()
    }

    /// Checks `user`'s password. An unknown user costs as much time as a
    /// wrong password (see [`dummy_verify`]).
    pub fn verify(&self, user: &str, password: &[u8]) -> Verification {
        match self.get(user) {
            Some(hash) if hash.verify(password) => Verification::Accepted {
                legacy: hash.is_legacy(),
            },
            Some(_) => Verification::Rejected,
            None => {
                dummy_verify(password);
                Verification::Rejected
            }
        }
    }

    /// Copies `other`'s entries into this file, e.g. to import a Mosquitto
    /// password file. Users already present are replaced if `overwrite`,
    /// otherwise left alone. Returns `(added, skipped)`, where `added`
    /// counts new and replaced users.
    pub fn merge_from(&mut self, other: &PasswordFile, overwrite: bool) -> (usize, usize) {
        let (mut added, mut skipped) = (0, 0);
        for (user, hash) in &other.entries {
            if self.index.contains_key(user) && !overwrite {
                skipped += 1;
            } else {
                self.insert(user, hash.clone());
                added += 1;
            }
        }
        (added, skipped)
    }

    /// Adds or replaces an entry; `user` must already be validated.
    fn insert(&mut self, user: &str, hash: StoredHash) {
        match self.index.get(user) {
            Some(&i) => self.entries[i].1 = hash,
            None => {
                self.index.insert(user.to_owned(), self.entries.len());
                self.entries.push((user.to_owned(), hash));
            }
        }
    }
}

impl fmt::Debug for PasswordFile {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.debug_struct("PasswordFile")
            .field("users", &self.users().collect::<Vec<_>>())
            .finish()
    }
}

fn valid_user_name(user: &str) -> bool {
    !user.is_empty()
        && !user
            .chars()
            .any(|c| c == ':' || c.is_whitespace() || c.is_control())
}

/// Replaces `path` with `contents` so that readers see either the old or
/// the new file, never a partial one.
fn write_atomically(path: &Path, contents: &[u8]) -> io::Result<()> {
    let dir = match path.parent() {
        Some(dir) if !dir.as_os_str().is_empty() => dir,
        _ => Path::new("."),
    };
    let file_name = path
        .file_name()
        .ok_or_else(|| io::Error::new(io::ErrorKind::InvalidInput, "path does not name a file"))?;
    let mut temp_name = std::ffi::OsString::from(".");
    temp_name.push(file_name);
    temp_name.push(format!(".tmp-{:016x}", rand::thread_rng().gen::<u64>()));
    let temp_path = dir.join(temp_name);

    let result = (|| {
        let mut options = fs::OpenOptions::new();
        options.write(true).create_new(true);
        #[cfg(unix)]
        std::os::unix::fs::OpenOptionsExt::mode(&mut options, 0o600);
        let mut file = options.open(&temp_path)?;
        file.write_all(contents)?;
        file.sync_all()?;
        fs::rename(&temp_path, path)?;
        // Make the rename itself durable.
        #[cfg(unix)]
        fs::File::open(dir)?.sync_all()?;
        Ok(())
    })();
    if result.is_err() {
        // Best effort; the temp file may not exist or may already be renamed.
        let _ = fs::remove_file(&temp_path);
    }
    result
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::hash::{hash_password, Argon2Params};

    const FAST: Argon2Params = Argon2Params {
        memory_kib: 64,
        iterations: 1,
        parallelism: 1,
    };

    // From `mosquitto_passwd` (see hash.rs): alice / s3cret-Pass and
    // bob / hunter2.
    const MOSQUITTO_FILE: &str = "\
alice:$7$101$XXL0YIyxs2JprT79$MxDyesxhMmF70J6YJvhWjXQYLpmeuEbKERSayqm9Xvsry/e0H+CddGMWveVVU1K3+bfQkHo3A2U15DQeLqC2+w==
bob:$6$HsJ3sJwAvg7yQbZl$p+p8NvEK2Dl29AhQ1P/srI3art/6N+ktbG/NMUh5O5UGhgvs4Tl6zi6b1ZZJp9uhty8qdyEfUMz7a2IHVW3MDw==
";

    fn argon(password: &str) -> StoredHash {
        StoredHash::parse(&hash_password(password.as_bytes(), &FAST).unwrap()).unwrap()
    }

    #[test]
    fn mosquitto_file_loads_and_verifies() {
        let file = PasswordFile::parse(MOSQUITTO_FILE).unwrap();
        assert_eq!(file.users().collect::<Vec<_>>(), ["alice", "bob"]);
        assert_eq!(
            file.verify("alice", b"s3cret-Pass"),
            Verification::Accepted { legacy: true }
        );
        assert_eq!(
            file.verify("bob", b"hunter2"),
            Verification::Accepted { legacy: true }
        );
        assert_eq!(file.verify("bob", b"hunter3"), Verification::Rejected);
        assert_eq!(file.verify("mallory", b"hunter2"), Verification::Rejected);
    }

    #[test]
    fn comments_blank_lines_and_crlf_are_accepted() {
        let text = format!(
            "# devices\r\n\r\n  \n{}\r\n   # indented comment\n",
            MOSQUITTO_FILE.lines().next().unwrap()
        );
        let file = PasswordFile::parse(&text).unwrap();
        assert_eq!(file.len(), 1);
        assert!(file.get("alice").is_some());
    }

    #[test]
    fn argon2id_entries_verify_as_not_legacy() {
        let mut file = PasswordFile::default();
        file.set("plc-7", argon("secret")).unwrap();
        assert_eq!(
            file.verify("plc-7", b"secret"),
            Verification::Accepted { legacy: false }
        );
        assert_eq!(file.verify("plc-7", b"Secret"), Verification::Rejected);
    }

    fn line_error(text: &str) -> (usize, String) {
        match PasswordFile::parse(text) {
            Err(err @ PasswordFileError::Line { line, .. }) => (line, err.to_string()),
            other => panic!("expected a line error, got {other:?}"),
        }
    }

    #[test]
    fn parse_errors_carry_the_line_and_not_the_hash() {
        let (line, msg) = line_error("# c\nalice:$6$abc\n");
        assert_eq!(line, 2);
        assert!(msg.starts_with("line 2: user `alice`:"), "{msg}");
        assert!(!msg.contains("abc"), "{msg}");

        let (line, msg) = line_error("\n\nbob:$5$notahash\n");
        assert_eq!(line, 3);
        assert_eq!(
            msg,
            "line 3: user `bob`: hash is not a recognised format \
             (expected $argon2id$…, $7$… or $6$…)"
        );

        // A line without `:` may be a pasted password: not quoted.
        let (line, msg) = line_error("alice:$6$x\nhunter2\n");
        assert_eq!(line, 1); // the first bad line wins
        assert!(!msg.contains("$x"));
        let (line, msg) = line_error("hunter2\n");
        assert_eq!(line, 1);
        assert!(!msg.contains("hunter2"), "{msg}");

        let (line, msg) = line_error("al ice:$6$x\n");
        assert_eq!(line, 1);
        assert!(!msg.contains("al ice"), "{msg}");
        let (_, msg) = line_error(":$6$x\n");
        assert!(msg.contains("user name"), "{msg}");
    }

    #[test]
    fn duplicate_users_are_an_error() {
        let text = format!("{MOSQUITTO_FILE}\nalice:$6$whatever\n");
        let (line, msg) = line_error(&text);
        assert_eq!(line, 4);
        assert!(msg.contains("already defined on line 1"), "{msg}");
    }

    #[test]
    fn load_errors_name_the_file() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("passwd");
        fs::write(&path, "alice:nope\n").unwrap();
        let msg = PasswordFile::load(&path).unwrap_err().to_string();
        assert!(
            msg.starts_with(&format!("{}: line 1: user `alice`", path.display())),
            "{msg}"
        );
        assert!(!msg.contains("nope"), "{msg}");

        let missing = dir.path().join("missing");
        let err = PasswordFile::load(&missing).unwrap_err();
        assert!(matches!(err, PasswordFileError::Read { .. }));
        assert!(err.to_string().contains("missing"));
    }

    #[test]
    fn set_validates_user_names() {
        let mut file = PasswordFile::default();
        for bad in ["", "a:b", "a b", "a\tb", "a\u{7}b"] {
            assert!(matches!(
                file.set(bad, argon("x")),
                Err(PasswordFileError::InvalidUserName)
            ));
        }
        assert!(file.is_empty());
        file.set("ünïcode-ok", argon("x")).unwrap();
        assert_eq!(file.len(), 1);
    }

    #[test]
    fn set_remove_keep_order() {
        let mut file = PasswordFile::parse(MOSQUITTO_FILE).unwrap();
        file.set("carol", argon("c")).unwrap();
        file.set("alice", argon("new")).unwrap(); // replaced in place
        assert_eq!(file.users().collect::<Vec<_>>(), ["alice", "bob", "carol"]);
        assert_eq!(
            file.verify("alice", b"new"),
            Verification::Accepted { legacy: false }
        );
        assert!(file.remove("alice"));
        assert!(!file.remove("alice"));
        assert_eq!(file.users().collect::<Vec<_>>(), ["bob", "carol"]);
        assert!(file.get("carol").is_some());
        assert_eq!(
            file.verify("carol", b"c"),
            Verification::Accepted { legacy: false }
        );
        assert_eq!(file.len(), 2);
    }

    #[test]
    fn save_load_round_trip() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("passwd");
        let mut file = PasswordFile::parse(MOSQUITTO_FILE).unwrap();
        file.set("plc-7", argon("s")).unwrap();
        file.save(&path).unwrap();
        let loaded = PasswordFile::load(&path).unwrap();
        assert_eq!(
            loaded.users().collect::<Vec<_>>(),
            ["alice", "bob", "plc-7"]
        );
        for user in ["alice", "bob", "plc-7"] {
            assert_eq!(loaded.get(user), file.get(user));
        }
        // Mosquitto entries are written back byte for byte.
        let text = fs::read_to_string(&path).unwrap();
        assert!(text.starts_with(MOSQUITTO_FILE), "{text}");
    }

    #[cfg(unix)]
    #[test]
    fn save_replaces_the_file_atomically_with_mode_0600() {
        use std::os::unix::fs::PermissionsExt as _;

        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("passwd");
        fs::write(&path, "old contents\n").unwrap();
        fs::set_permissions(&path, fs::Permissions::from_mode(0o644)).unwrap();
        // A hard link keeps the old inode reachable: if save wrote in place,
        // the link would see the new contents.
        let old_inode = dir.path().join("old");
        fs::hard_link(&path, &old_inode).unwrap();

        PasswordFile::parse(MOSQUITTO_FILE)
            .unwrap()
            .save(&path)
            .unwrap();

        assert_eq!(fs::read_to_string(&old_inode).unwrap(), "old contents\n");
        assert_eq!(fs::read_to_string(&path).unwrap(), MOSQUITTO_FILE);
        let mode = fs::metadata(&path).unwrap().permissions().mode() & 0o777;
        assert_eq!(mode, 0o600);
        // No temporary file is left behind.
        let mut names: Vec<_> = fs::read_dir(dir.path())
            .unwrap()
            .map(|e| e.unwrap().file_name())
            .collect();
        names.sort();
        assert_eq!(names, ["old", "passwd"]);
    }

    #[test]
    fn save_to_a_missing_directory_fails_cleanly() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("no/such/dir/passwd");
        let err = PasswordFile::default().save(&path).unwrap_err();
        assert!(matches!(err, PasswordFileError::Write { .. }));
        assert!(err.to_string().contains("no/such/dir/passwd"));
    }

    #[test]
    fn merge_from_counts_added_and_skipped() {
        let mosquitto = PasswordFile::parse(MOSQUITTO_FILE).unwrap();
        let mut ours = PasswordFile::default();
        ours.set("alice", argon("mine")).unwrap();

        let mut keep = ours.clone();
        assert_eq!(keep.merge_from(&mosquitto, false), (1, 1));
        assert_eq!(
            keep.verify("alice", b"mine"),
            Verification::Accepted { legacy: false }
        );
        assert_eq!(keep.users().collect::<Vec<_>>(), ["alice", "bob"]);

        let mut replace = ours.clone();
        assert_eq!(replace.merge_from(&mosquitto, true), (2, 0));
        assert_eq!(
            replace.verify("alice", b"s3cret-Pass"),
            Verification::Accepted { legacy: true }
        );
    }

    #[test]
    fn debug_lists_only_user_names() {
        let file = PasswordFile::parse(MOSQUITTO_FILE).unwrap();
        let debug = format!("{file:?}");
        assert_eq!(debug, r#"PasswordFile { users: ["alice", "bob"] }"#);
    }
}

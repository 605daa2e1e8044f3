//! The password file parser (`security::password_file::PasswordFile::parse`) and the hash
//! formats in it (`StoredHash::parse`: argon2id PHC strings, Mosquitto `$7$` PBKDF2 and
//! `$6$` SHA-512).
//!
//! Input: the file's text, then optionally a NUL byte and a password to check against
//! every entry whose hash is cheap to verify (SHA-512 always, PBKDF2 up to 16 iterations,
//! argon2id up to 64 KiB, 2 passes, 4 lanes: real costs would make the fuzzer crawl).
//!
//! Checks: nothing panics; a parse error names a line of the text and never quotes a hash;
//! every parsed user is found, with a hash that prints (`phc`) to text that parses to the
//! same hash; the file as `save` writes it parses to the same users and hashes; `Debug`
//! shows no hash.
#![no_main]

use argon2::password_hash::PasswordHash;
use argon2::Params;
use libfuzzer_sys::fuzz_target;
use security::{PasswordFile, PasswordFileError, StoredHash};

fuzz_target!(|data: &[u8]| {
    let (file_bytes, password) = match data.iter().position(|b| *b == 0) {
        Some(at) => (&data[..at], &data[at + 1..]),
        None => (data, &[][..]),
    };
    let Ok(text) = std::str::from_utf8(file_bytes) else {
        return;
    };
    // Each line's hash part on its own, and the whole text as one hash.
    let _ = StoredHash::parse(text);
    for line in text.lines().take(32) {
        if let Some((_, hash)) = line.trim().split_once(':') {
            if let Ok(parsed) = StoredHash::parse(hash) {
                round_trip(&parsed);
            }
        }
    }

    let file = match PasswordFile::parse(text) {
        Ok(file) => file,
        Err(e) => {
            parse_error(text, &e);
            return;
        }
    };
    let users: Vec<&str> = file.users().collect();
    assert_eq!(users.len(), file.len());
    let mut saved = String::new();
    let debug = format!("{file:?}");
    for user in &users {
        let hash = file.get(user).expect("a listed user is found");
        round_trip(hash);
        let phc = hash.phc();
        // (Unless a user name holds the text: names are what Debug shows.)
        assert!(
            phc.len() < 12 || users.iter().any(|u| u.contains(&phc)) || !debug.contains(&phc),
            "Debug shows a hash: {debug}"
        );
        assert!(
            !format!("{hash:?}").contains(&phc),
            "StoredHash Debug shows the hash"
        );
        saved.push_str(&format!("{user}:{phc}\n"));
        if cheap(hash) {
            let _ = hash.verify(password);
        }
    }
    // What `save` writes (without the file system) reads back the same.
    let again = PasswordFile::parse(&saved).expect("a saved file parses");
    assert_eq!(again.users().collect::<Vec<_>>(), users);
    for user in &users {
        assert!(
            again.get(user) == file.get(user),
            "{user}'s hash changed on save"
        );
    }
});

fn round_trip(hash: &StoredHash) {
    let phc = hash.phc();
    assert_eq!(hash.to_string(), phc);
    let again = StoredHash::parse(&phc).expect("phc() text parses");
    assert!(again == *hash, "phc() round trip changed the hash");
    assert_eq!(again.is_legacy(), hash.is_legacy());
}

/// Whether verifying against `hash` costs at most a few hundred microseconds.
fn cheap(hash: &StoredHash) -> bool {
    match hash {
        StoredHash::MosquittoSha512 { .. } => true,
        StoredHash::MosquittoPbkdf2 { iterations, .. } => *iterations <= 16,
        StoredHash::Argon2id(phc) => PasswordHash::new(phc)
            .ok()
            .and_then(|p| Params::try_from(&p).ok())
            .is_some_and(|p| p.m_cost() <= 64 && p.t_cost() <= 2 && p.p_cost() <= 4),
    }
}

/// A parse error names a line that exists and quotes no hash.
fn parse_error(text: &str, e: &PasswordFileError) {
    let PasswordFileError::Line { line, .. } = e else {
        panic!("parse returned a non-line error: {e}");
    };
    let lines: Vec<&str> = text.lines().collect();
    assert!(
        *line >= 1 && *line <= lines.len(),
        "error on line {line} of {}",
        lines.len()
    );
    let message = e.to_string();
    let Some((user, hash)) = lines[*line - 1].trim().split_once(':') else {
        return;
    };
    // Salts and hashes are base64: no run of 16 or more base64 characters from the hash
    // field may appear in the message (unless the user name, which errors may quote once
    // it is valid, holds it too). The messages' own words are shorter.
    let base64 = |c: char| c.is_ascii_alphanumeric() || matches!(c, '+' | '/' | '=');
    for run in hash.split(|c: char| !base64(c)).filter(|r| r.len() >= 16) {
        if !user.contains(run) {
            assert!(
                !message.contains(run),
                "the error quotes the hash: {message}"
            );
        }
    }
}

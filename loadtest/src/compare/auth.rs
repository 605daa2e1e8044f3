//! The auth storm's users and their password files, one per broker's format, made before
//! any broker starts (not timed): fbbus argon2id with fbbus's own defaults
//! (`security::hash_password`), Mosquitto PBKDF2-SHA512 (`mosquitto_passwd -U`; FlashMQ
//! reads the same file), rumqttd a plaintext `user:password` list for its static map.

use std::path::Path;

use anyhow::{bail, Context as _, Result};

use loadtest::broker_process::spawn::{self, AuthFiles, Kind};

use super::scenarios::{Login, STORM_USER_PREFIX};

/// The storm's files (in a temporary directory, removed on drop) and the login.
pub struct Storm {
    _dir: tempfile::TempDir,
    pub files: AuthFiles,
    pub login: Login,
}

/// Users `plc-0` ... `plc-<devices - 1>` and a probe user, in every selected broker's
/// format.
pub fn prepare(devices: usize, kinds: &[Kind]) -> Result<Storm> {
    // Readable by Mosquitto after it drops root privileges to its own user.
    let dir = spawn::readable_tempdir("fbbus-loadtest-auth-")?;
    let seed = std::time::SystemTime::now()
        .duration_since(std::time::UNIX_EPOCH)
        .map_or(0, |d| d.as_nanos() as u64);
    let password = format!("storm-{:016x}", seed.wrapping_mul(0x9E37_79B9_7F4A_7C15));
    let mut everyone: Vec<(String, String)> = (0..devices)
        .map(|i| (format!("{STORM_USER_PREFIX}{i}"), password.clone()))
        .collect();
    let probe = ("bench-probe".to_string(), "probe-secret-7d1f".to_string());
    everyone.push(probe.clone());
    let plain: String = everyone.iter().map(|(u, p)| format!("{u}:{p}\n")).collect();

    let rumqttd = dir.path().join("rumqttd-users");
    std::fs::write(&rumqttd, &plain)?;

    let fbbus = if kinds.contains(&Kind::Fbbus) {
        let path = dir.path().join("fbbus-passwd");
        write_argon2_file(&path, &everyone)?;
        Some(path)
    } else {
        None
    };

    // FlashMQ reads Mosquitto's file (`mosquitto_password_file`, `$7$` hashes).
    let mosquitto = if kinds.contains(&Kind::Mosquitto) || kinds.contains(&Kind::FlashMq) {
        match spawn::find_program("mosquitto_passwd", &["/usr/bin/mosquitto_passwd"]) {
            Some(tool) => {
                let path = dir.path().join("mosquitto-passwd");
                std::fs::write(&path, &plain)?;
                let status = std::process::Command::new(&tool)
                    .arg("-U")
                    .arg(&path)
                    .status()
                    .with_context(|| format!("running {} -U", tool.display()))?;
                if !status.success() {
                    bail!("{} -U {} failed: {status}", tool.display(), path.display());
                }
                spawn::set_mode(&path, 0o644)?;
                Some(path)
            }
            None => {
                eprintln!("  mosquitto_passwd not found: mosquitto and flashmq will not run the auth storm (apt-get install -y mosquitto)");
                None
            }
        }
    } else {
        None
    };
    Ok(Storm {
        _dir: dir,
        files: AuthFiles {
            fbbus,
            mosquitto,
            rumqttd,
            probe,
        },
        login: Login { password },
    })
}

/// argon2id hashes with fbbus's defaults, one salt per user, made on every core.
fn write_argon2_file(path: &Path, users: &[(String, String)]) -> Result<()> {
    let params = security::Argon2Params::default();
    let threads = std::thread::available_parallelism()
        .map(|n| n.get())
        .unwrap_or(2);
    let chunk = users.len().div_ceil(threads).max(1);
    let hashes: Vec<Result<Vec<String>>> = std::thread::scope(|s| {
        let handles: Vec<_> = users
            .chunks(chunk)
            .map(|part| {
                s.spawn(move || {
                    part.iter()
                        .map(|(_, pw)| {
                            security::hash_password(pw.as_bytes(), &params)
                                .map_err(|e| anyhow::anyhow!("hashing: {e}"))
                        })
                        .collect::<Result<Vec<String>>>()
                })
            })
            .collect();
        handles
            .into_iter()
            .map(|h| {
                h.join()
                    .unwrap_or_else(|_| bail!("hashing thread panicked"))
            })
            .collect()
    });
    let mut file = security::PasswordFile::default();
    let mut users_iter = users.iter();
    for part in hashes {
        for phc in part? {
            let (user, _) = users_iter.next().context("hash count")?;
            file.set(user, security::StoredHash::parse(&phc)?)?;
        }
    }
    file.save(path)?;
    Ok(())
}

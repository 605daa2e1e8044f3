//! Login: the first step of the packet path, run once per connection at CONNECT.
//!
//! The order is chosen so that the expensive step comes last and is bounded:
//! 1. throttle: an address that failed too often recently is refused at once, no hashing;
//! 2. anonymous: a CONNECT without a username is let in only where the listener allows it;
//! 3. cache: a device that already proved this exact password against this exact
//!    password-file entry is let in without argon2 (the cache keeps keyed MACs, not passwords);
//! 4. argon2id (or a Mosquitto legacy hash), queued for the [`Verifier`]'s threads
//!    (`verify_concurrency` of them), so a reconnect storm queues instead of starving the
//!    connections already serving traffic.
//!
//! An unknown user costs one dummy argon2 verification, exactly like a wrong password, so
//! response time does not reveal which user names exist.

use std::io;
use std::net::IpAddr;
use std::path::PathBuf;
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

use security::{CredentialCache, LoginThrottle, PasswordFile, StoredHash, Verification};
use serde::Deserialize;

use crate::metrics::Metrics;
use crate::verifier::Verifier;
use crate::watched_file::WatchedFile;

#[derive(Debug, Clone, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct AuthSection {
    /// `user:PHC` lines (argon2id), or a Mosquitto password file.
    pub password_file: Option<PathBuf>,
    /// Access rules; without one every authenticated client may do everything.
    pub acl_file: Option<PathBuf>,
    /// Which client ids a client that logs in with a username may use: "any", "%u" (the
    /// username) or "%u-*" (the username, or the username, `-` and anything).
    pub client_id: crate::identity::ClientIdRule,
    /// Rewrite a Mosquitto `$7$`/`$6$` entry as argon2id after its next successful login.
    pub rehash_legacy: bool,
    /// Password verifications run at once (argon2 is CPU-bound: more than the cores only queues).
    pub verify_concurrency: usize,
    /// Verified credentials remembered (as keyed MACs, never passwords) to skip argon2 on reconnect.
    pub cache_capacity: usize,
    /// How often the password and ACL files are checked for changes (SIGHUP reloads at once).
    pub reload_poll_ms: u64,
    pub throttle: ThrottleSection,
}

impl Default for AuthSection {
    fn default() -> Self {
        AuthSection {
            password_file: None,
            acl_file: None,
            client_id: Default::default(),
            rehash_legacy: true,
            verify_concurrency: std::thread::available_parallelism()
                .map(|n| n.get())
                .unwrap_or(2),
            cache_capacity: 100_000,
            reload_poll_ms: 1_000,
            throttle: ThrottleSection::default(),
        }
    }
}

#[derive(Debug, Clone, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct ThrottleSection {
    /// Failed logins from one address before backoff starts.
    pub free_failures: u32,
    pub base_delay_ms: u64,
    pub max_delay_ms: u64,
}

impl ThrottleSection {
    /// The login throttle these settings make: the MQTT logins' and the admin endpoint's
    /// (each has a throttle of its own, tuned alike).
    pub fn throttle_config(&self) -> security::ThrottleConfig {
        security::ThrottleConfig {
            free_failures: self.free_failures,
            base_delay: Duration::from_millis(self.base_delay_ms),
            max_delay: Duration::from_millis(self.max_delay_ms),
            ..security::ThrottleConfig::default()
        }
    }
}

impl Default for ThrottleSection {
    fn default() -> Self {
        ThrottleSection {
            free_failures: 5,
            base_delay_ms: 1_000,
            max_delay_ms: 60_000,
        }
    }
}

/// The result of a login attempt.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Outcome {
    Accepted,
    /// Wrong password or unknown user (deliberately indistinguishable).
    BadCredentials,
    /// No username, on a listener that requires one.
    MissingCredentials,
    /// Too many recent failures from this address; retry after this long.
    Throttled(Duration),
}

pub struct Authenticator {
    passwords: Option<Arc<WatchedFile<PasswordFile>>>,
    cache: CredentialCache,
    throttle: LoginThrottle,
    verifier: Verifier,
    rehash_legacy: bool,
    /// Serialises rewrites of the password file by the broker itself.
    rewrite: Mutex<()>,
    metrics: Arc<Metrics>,
}

impl Authenticator {
    pub fn new(
        auth: &AuthSection,
        passwords: Option<Arc<WatchedFile<PasswordFile>>>,
        metrics: Arc<Metrics>,
    ) -> io::Result<Authenticator> {
        let throttle = auth.throttle.throttle_config();
        Ok(Authenticator {
            passwords,
            cache: CredentialCache::new(auth.cache_capacity),
            throttle: LoginThrottle::new(throttle),
            verifier: Verifier::start(auth.verify_concurrency)?,
            rehash_legacy: auth.rehash_legacy,
            rewrite: Mutex::new(()),
            metrics,
        })
    }

    /// Checks a CONNECT's credentials. `login` is (username, password) when the packet had a
    /// username. The password is dropped when this returns; it is never logged or stored.
    pub async fn authenticate(
        self: &Arc<Self>,
        peer: IpAddr,
        login: Option<(String, String)>,
        anonymous_allowed: bool,
    ) -> Outcome {
        if let Err(retry_after) = self.throttle.check(peer, Instant::now()) {
            self.metrics.logins_throttled.inc();
            return Outcome::Throttled(retry_after);
        }
        let Some((user, password)) = login else {
            return if anonymous_allowed {
                Outcome::Accepted
            } else {
                self.metrics
                    .auth_failures
                    .with_label_values(&["missing_credentials"])
                    .inc();
                Outcome::MissingCredentials
            };
        };
        let Some(passwords) = &self.passwords else {
            // No password file: only loopback listeners exist (config validation), and
            // like Mosquitto without a password file, credentials are not checked.
            return if anonymous_allowed {
                Outcome::Accepted
            } else {
                Outcome::BadCredentials
            };
        };

        let file = passwords.get();
        if let Some(stored) = file.get(&user) {
            if self.cache.hit(&user, password.as_bytes(), stored) {
                self.metrics.auth_cache_hits.inc();
                self.throttle.record_success(peer);
                return Outcome::Accepted;
            }
        }

        let started = Instant::now();
        let this = Arc::clone(self);
        let verdict = self
            .verifier
            .run(move || {
                let verdict = file.verify(&user, password.as_bytes());
                if let Verification::Accepted { legacy } = verdict {
                    if let Some(stored) = file.get(&user) {
                        this.cache.insert(&user, password.as_bytes(), stored);
                        if legacy && this.rehash_legacy {
                            this.rehash(&user, stored, password.as_bytes());
                        }
                    }
                }
                verdict
            })
            .await
            .unwrap_or(Verification::Rejected);
        self.metrics
            .auth_verify_seconds
            .observe(started.elapsed().as_secs_f64());

        match verdict {
            Verification::Accepted { .. } => {
                self.throttle.record_success(peer);
                Outcome::Accepted
            }
            Verification::Rejected => {
                self.metrics
                    .auth_failures
                    .with_label_values(&["bad_credentials"])
                    .inc();
                if let Some(blocked) = self.throttle.record_failure(peer, Instant::now()) {
                    tracing::warn!(%peer, blocked_for = ?blocked, "too many failed logins; address throttled");
                }
                Outcome::BadCredentials
            }
        }
    }

    /// Rewrites one Mosquitto-format entry as argon2id, after that password was just proven.
    /// The file is re-read first, so an edit made since the last reload is not lost, and the
    /// entry is only replaced if it is still the legacy hash that was verified.
    fn rehash(&self, user: &str, verified: &StoredHash, password: &[u8]) {
        let Some(watched) = &self.passwords else {
            return;
        };
        let result = (|| -> Result<bool, String> {
            let _guard = self
                .rewrite
                .lock()
                .unwrap_or_else(std::sync::PoisonError::into_inner);
            let mut file = PasswordFile::load(watched.path()).map_err(|e| e.to_string())?;
            if file.get(user).map(|h| h.phc()) != Some(verified.phc()) {
                return Ok(false);
            }
            let phc = security::hash_password(password, &security::Argon2Params::default())
                .map_err(|e| e.to_string())?;
            let stored = StoredHash::parse(&phc).map_err(|e| e.to_string())?;
            file.set(user, stored).map_err(|e| e.to_string())?;
            file.save(watched.path()).map_err(|e| e.to_string())?;
            watched.replace(file);
            Ok(true)
        })();
        match result {
            Ok(true) => {
                self.metrics.passwords_rehashed.inc();
                tracing::info!(user, file = %watched.path().display(), "legacy password hash rewritten as argon2id");
            }
            Ok(false) => {}
            Err(e) => tracing::warn!(user, error = %e, "could not rewrite legacy password hash"),
        }
    }
}

impl Authenticator {
    /// Whether `name` is a user of the password file (none without one). A client id that
    /// is a user's name is that user's (`session::connect`).
    pub fn is_user(&self, name: &str) -> bool {
        self.passwords
            .as_ref()
            .is_some_and(|p| p.get().get(name).is_some())
    }
}

//! The admin endpoint's credential check: with `[admin] password_file` set, every admin
//! request (every route, and a path no route serves) must carry HTTP Basic credentials
//! that verify against that file, or it is answered 401 (429 while its address is
//! throttled) before any route sees it.
//!
//! Why a file of its own, not `[auth] password_file`: the MQTT password file holds a
//! password per device, and a device's password (on the device, in its configuration,
//! in a runtime's boot file) must not open the admin plane, which reads every device's
//! record and, from the broker's host, forgets devices and puts profiles. The file has
//! the same format and the same tool (`fbbus passwd FILE add USER`), and it reloads the
//! same way (when it changes, and on SIGHUP).
//!
//! Why one layer ([`require`], wrapped around the whole router in `admin::routes`): a
//! route added later is covered without anyone remembering to check, and the check runs
//! before the route's extractors read anything.
//!
//! The cost of a check, and abuse:
//! - argon2id takes milliseconds to tens of milliseconds, so it runs on a blocking thread,
//!   at most [`MAX_VERIFICATIONS`] at once, never on a runtime worker the MQTT sessions
//!   share;
//! - a browser or Prometheus sends the same credentials with every request: a
//!   [`CredentialCache`] (keyed MACs, never passwords) lets them skip argon2 after the
//!   first success;
//! - a [`LoginThrottle`] per peer address (tuned by `[auth.throttle]`, like the MQTT
//!   logins, but counting apart from them) answers 429 with `Retry-After`, without
//!   verifying anything, to an address that failed too often; while it is throttled even
//!   the right password is refused, as on the MQTT side; failures also count per user of
//!   the file (guesses at one account from many addresses, or from an IPv6 /64, meet
//!   the same block) and for the whole endpoint, with [`OVERALL_FACTOR`] times the free
//!   failures (guesses at names that are no user). Neither of those two blocks a
//!   credential the cache already verified, so a scraper with the right password goes on
//!   while someone else guesses;
//! - every refusal is counted in `fbbus_admin_auth_failures_total{reason}` (missing,
//!   invalid, throttled) and logged at most once a minute per reason, with the peer's
//!   address and never a user name or password (a password typed into the user field
//!   would otherwise land in the log).
//!
//! An unknown user and a wrong password get the same answer and cost the same time (an
//! unknown user costs a dummy argon2 verification, [`PasswordFile::verify`]).

use std::net::{IpAddr, SocketAddr};
use std::sync::{Arc, Mutex, PoisonError};
use std::time::{Duration, Instant};

use axum::extract::{ConnectInfo, Request, State};
use axum::http::{header, HeaderMap, HeaderValue, StatusCode};
use axum::middleware::Next;
use axum::response::{IntoResponse, Response};
use base64::Engine as _;
use security::{CredentialCache, LoginThrottle, PasswordFile, ThrottleConfig, Verification};
use tokio::sync::Semaphore;

use crate::authenticator::ThrottleSection;
use crate::metrics::Metrics;
use crate::watched_file::WatchedFile;

/// The challenge of a 401: HTTP Basic, user names and passwords in UTF-8 (RFC 7617).
pub const CHALLENGE: &str = r#"Basic realm="fbbus admin", charset="UTF-8""#;

/// Admin password verifications (argon2id) running at once at most; more wait. The admin
/// plane must not take the cores the MQTT logins need.
pub const MAX_VERIFICATIONS: usize = 2;

/// Admin users whose last good credentials are remembered (as keyed MACs).
const CACHE_CAPACITY: usize = 256;

/// An `Authorization` header longer than this is refused unread: a user name and a
/// password, in base64, with room to spare.
pub const MAX_AUTHORIZATION_BYTES: usize = 1024;

/// The whole endpoint's throttle allows this many times the free failures of an address.
pub const OVERALL_FACTOR: u32 = 10;

/// A refusal is logged at most this often per reason; every one is counted.
const WARNING_INTERVAL: Duration = Duration::from_secs(60);

/// What to do, said in every refusal.
const HOW: &str = "send HTTP Basic credentials of a user of the broker's [admin] password_file \
                   (curl -u USER, Prometheus basic_auth, or FBBUS_ADMIN_USER and \
                   FBBUS_ADMIN_PASSWORD for the fbbus commands)";

/// Checks admin requests against `[admin] password_file`. `Send + Sync`.
pub struct AdminAuth {
    passwords: Arc<WatchedFile<PasswordFile>>,
    cache: CredentialCache,
    throttle: LoginThrottle,
    /// Failures per user of the file (unknown names are not tracked: they count overall).
    per_user: LoginThrottle<String>,
    /// Every failure, whoever and whatever it targets.
    overall: LoginThrottle<()>,
    verifications: Semaphore,
    metrics: Arc<Metrics>,
    /// When each [`Refusal`] was last logged.
    last_warning: Mutex<[Option<Instant>; 3]>,
}

/// Why a request was refused: the `reason` label of `fbbus_admin_auth_failures_total`.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Refusal {
    /// No `Authorization` header.
    Missing,
    /// Unknown user, wrong password, or a header that is not HTTP Basic (deliberately
    /// one answer).
    Invalid,
    /// Too many recent failures from this address; retry after this long.
    Throttled(Duration, Scope),
}

/// Whose failures a throttled request met.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Scope {
    Address,
    User,
    Endpoint,
}

impl Scope {
    fn describe(self) -> &'static str {
        match self {
            Scope::Address => "from this address",
            Scope::User => "for this user",
            Scope::Endpoint => "on this endpoint",
        }
    }
}

impl Refusal {
    fn label(self) -> &'static str {
        match self {
            Refusal::Missing => "missing",
            Refusal::Invalid => "invalid",
            Refusal::Throttled(..) => "throttled",
        }
    }

    fn index(self) -> usize {
        match self {
            Refusal::Missing => 0,
            Refusal::Invalid => 1,
            Refusal::Throttled(..) => 2,
        }
    }
}

/// The layer: answers the request itself (401, 429) unless its credentials verify.
pub async fn require(State(auth): State<Arc<AdminAuth>>, request: Request, next: Next) -> Response {
    let peer = request
        .extensions()
        .get::<ConnectInfo<SocketAddr>>()
        .map(|ConnectInfo(peer)| peer.ip().to_canonical());
    match auth.check(peer, request.headers()).await {
        Ok(()) => next.run(request).await,
        Err(refusal) => auth.refuse(refusal, peer),
    }
}

impl AdminAuth {
    pub fn new(
        passwords: Arc<WatchedFile<PasswordFile>>,
        throttle: &ThrottleSection,
        metrics: Arc<Metrics>,
    ) -> AdminAuth {
        let config = throttle.throttle_config();
        AdminAuth {
            passwords,
            cache: CredentialCache::new(CACHE_CAPACITY),
            per_user: LoginThrottle::new(config.clone()),
            overall: LoginThrottle::new(ThrottleConfig {
                free_failures: config.free_failures.saturating_mul(OVERALL_FACTOR),
                ..config.clone()
            }),
            throttle: LoginThrottle::new(config),
            verifications: Semaphore::new(MAX_VERIFICATIONS),
            metrics,
            last_warning: Mutex::new([None; 3]),
        }
    }

    /// Whether `headers` carry credentials of a user of the file. `peer` is the client's
    /// address (None only where no connection exists, in tests: then nothing is throttled).
    async fn check(
        self: &Arc<Self>,
        peer: Option<IpAddr>,
        headers: &HeaderMap,
    ) -> Result<(), Refusal> {
        if let Some(peer) = peer {
            if let Err(retry_after) = self.throttle.check(peer, Instant::now()) {
                return Err(Refusal::Throttled(retry_after, Scope::Address));
            }
        }
        let mut values = headers.get_all(header::AUTHORIZATION).iter();
        let (Some(value), None) = (values.next(), values.next()) else {
            // Two Authorization headers: which one would count? Neither.
            return if headers.contains_key(header::AUTHORIZATION) {
                Err(self.failed(peer, None))
            } else {
                Err(Refusal::Missing)
            };
        };
        let Some(Credentials { user, password }) = Credentials::parse(value) else {
            return Err(self.failed(peer, None));
        };

        let file = self.passwords.get();
        let known = file.get(&user).is_some();
        if let Some(stored) = file.get(&user) {
            if self.cache.hit(&user, password.as_bytes(), stored) {
                self.succeeded(peer, &user);
                return Ok(());
            }
        }
        // Not verified before: a guess, as far as the user's and the endpoint's counts go.
        let now = Instant::now();
        if known {
            if let Err(retry_after) = self.per_user.check(user.clone(), now) {
                return Err(Refusal::Throttled(retry_after, Scope::User));
            }
        }
        if let Err(retry_after) = self.overall.check((), now) {
            return Err(Refusal::Throttled(retry_after, Scope::Endpoint));
        }
        let accepted = {
            // Never closed, so acquiring only waits.
            let _permit = self.verifications.acquire().await;
            let this = Arc::clone(self);
            let name = user.clone();
            tokio::task::spawn_blocking(move || {
                let accepted = matches!(
                    file.verify(&name, password.as_bytes()),
                    Verification::Accepted { .. }
                );
                if accepted {
                    if let Some(stored) = file.get(&name) {
                        this.cache.insert(&name, password.as_bytes(), stored);
                    }
                }
                accepted
            })
            .await
            .unwrap_or(false)
        };
        if accepted {
            self.succeeded(peer, &user);
            Ok(())
        } else {
            Err(self.failed(peer, known.then_some(user)))
        }
    }

    /// A verified login clears its address's and its user's failures (not the
    /// endpoint's: a scraper's successes must not reset someone else's guessing).
    fn succeeded(&self, peer: Option<IpAddr>, user: &str) {
        if let Some(peer) = peer {
            self.throttle.record_success(peer);
        }
        self.per_user.record_success(user.to_owned());
    }

    /// A failed login counts for its address, for `user` (a user of the file it named),
    /// and for the endpoint.
    fn failed(&self, peer: Option<IpAddr>, user: Option<String>) -> Refusal {
        let now = Instant::now();
        if let Some(peer) = peer {
            self.throttle.record_failure(peer, now);
        }
        if let Some(user) = user {
            self.per_user.record_failure(user, now);
        }
        self.overall.record_failure((), now);
        Refusal::Invalid
    }

    /// Counts and (at most once a minute per reason) logs a refusal, and answers it.
    fn refuse(&self, refusal: Refusal, peer: Option<IpAddr>) -> Response {
        self.metrics
            .admin_auth_failures
            .with_label_values(&[refusal.label()])
            .inc();
        let log = {
            let mut last = self
                .last_warning
                .lock()
                .unwrap_or_else(PoisonError::into_inner);
            let last = &mut last[refusal.index()];
            let due = last.is_none_or(|t| t.elapsed() >= WARNING_INTERVAL);
            if due {
                *last = Some(Instant::now());
            }
            due
        };
        if log {
            let peer = peer.map_or_else(|| "unknown".to_owned(), |p| p.to_string());
            let reason = refusal.label();
            match refusal {
                // A browser asks without credentials first: not worth a warning.
                Refusal::Missing => tracing::info!(
                    %peer,
                    reason,
                    "admin endpoint: request without credentials refused (401); further \
                     refusals this minute are only counted (fbbus_admin_auth_failures_total)"
                ),
                Refusal::Invalid => tracing::warn!(
                    %peer,
                    reason,
                    "admin endpoint: request with wrong credentials refused (401); further \
                     refusals this minute are only counted (fbbus_admin_auth_failures_total)"
                ),
                Refusal::Throttled(retry_after, scope) => tracing::warn!(
                    %peer,
                    reason,
                    ?retry_after,
                    "admin endpoint: too many failed logins {}, refused (429); further \
                     refusals this minute are only counted (fbbus_admin_auth_failures_total)",
                    scope.describe()
                ),
            }
        }
        match refusal {
            Refusal::Missing | Refusal::Invalid => {
                let message = match refusal {
                    Refusal::Missing => format!("credentials required: {HOW}"),
                    _ => format!("credentials refused: {HOW}"),
                };
                (
                    StatusCode::UNAUTHORIZED,
                    [(
                        header::WWW_AUTHENTICATE,
                        HeaderValue::from_static(CHALLENGE),
                    )],
                    axum::Json(serde_json::json!({ "error": message })),
                )
                    .into_response()
            }
            Refusal::Throttled(retry_after, scope) => {
                // Whole seconds, rounded up: retrying at the announced time is not too early.
                let seconds = retry_after.as_secs() + u64::from(retry_after.subsec_nanos() > 0);
                let seconds = seconds.max(1);
                (
                    StatusCode::TOO_MANY_REQUESTS,
                    [(header::RETRY_AFTER, HeaderValue::from(seconds))],
                    axum::Json(serde_json::json!({
                        "error": format!(
                            "too many failed logins {}; retry after {seconds} s",
                            scope.describe()
                        )
                    })),
                )
                    .into_response()
            }
        }
    }
}

/// A user name and password from an `Authorization: Basic` header (RFC 7617). Its `Debug`
/// shows neither.
struct Credentials {
    user: String,
    password: String,
}

impl std::fmt::Debug for Credentials {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str("Credentials { .. }")
    }
}

impl Credentials {
    /// `Basic base64(user:password)`, the scheme in any case, the user and password in
    /// UTF-8, the user non-empty (the password is split at the first `:`, so it may hold
    /// one). Anything else is None: not base64, no `:`, not UTF-8, another scheme, a value
    /// longer than [`MAX_AUTHORIZATION_BYTES`].
    fn parse(value: &HeaderValue) -> Option<Credentials> {
        let value = value.as_bytes();
        if value.len() > MAX_AUTHORIZATION_BYTES {
            return None;
        }
        let value = std::str::from_utf8(value).ok()?.trim();
        let (scheme, token) = value.split_once(' ')?;
        if !scheme.eq_ignore_ascii_case("basic") {
            return None;
        }
        let decoded = base64::engine::general_purpose::STANDARD
            .decode(token.trim_start())
            .ok()?;
        let decoded = String::from_utf8(decoded).ok()?;
        let (user, password) = decoded.split_once(':')?;
        if user.is_empty() || password.is_empty() {
            return None;
        }
        Some(Credentials {
            user: user.to_owned(),
            password: password.to_owned(),
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn parse(value: &[u8]) -> Option<(String, String)> {
        let value = HeaderValue::from_bytes(value).ok()?;
        Credentials::parse(&value).map(|c| (c.user, c.password))
    }

    fn basic(raw: &[u8]) -> Vec<u8> {
        let mut value = b"Basic ".to_vec();
        value.extend(
            base64::engine::general_purpose::STANDARD
                .encode(raw)
                .bytes(),
        );
        value
    }

    #[test]
    fn basic_credentials_are_read() {
        let ok = |u: &str, p: &str| Some((u.to_owned(), p.to_owned()));
        assert_eq!(parse(&basic(b"admin:s3cret")), ok("admin", "s3cret"));
        // The password is split at the first colon only.
        assert_eq!(parse(&basic(b"admin:a:b:")), ok("admin", "a:b:"));
        // The scheme in any case; spaces around.
        assert_eq!(parse(b"basic YWRtaW46eA=="), ok("admin", "x"));
        assert_eq!(parse(b"BASIC   YWRtaW46eA==  "), ok("admin", "x"));
        // Multi-byte UTF-8 user names and passwords are what they are.
        assert_eq!(
            parse(&basic("bediener-ü:pässwort-✓".as_bytes())),
            ok("bediener-ü", "pässwort-✓")
        );
    }

    /// Hostile input: refused, never a panic.
    #[test]
    fn anything_else_is_refused() {
        let huge = basic(&vec![b'a'; 64 * 1024]);
        let long_enough = basic(&[b'u', b':'].repeat(MAX_AUTHORIZATION_BYTES));
        let hostile: Vec<Vec<u8>> = vec![
            b"".to_vec(),
            b"Basic".to_vec(),
            b"Basic ".to_vec(),
            b"Basic !!!not-base64!!!".to_vec(),
            b"Basic YWRtaW46eA".to_vec(),    // missing padding
            b"Basic YWRtaW46eA===".to_vec(), // too much padding
            b"Bearer YWRtaW46eA==".to_vec(),
            b"Digest username=\"admin\"".to_vec(),
            b"YWRtaW46eA==".to_vec(),
            basic(b"no-colon"),
            basic(b":password-without-user"),
            basic(b"user-without-password:"),
            basic(b":"),
            basic(b""),
            basic(b"\xff\xfe:password"),        // not UTF-8
            basic(b"admin:\xc3\x28"),           // invalid UTF-8 in the password
            b"Basic \xc3\xa4\xc3\xa4".to_vec(), // not ASCII at all
            b"\xff\xff\xff\xff".to_vec(),
            huge,
            long_enough,
        ];
        for value in hostile {
            assert_eq!(parse(&value), None, "{:?}", String::from_utf8_lossy(&value));
        }
    }

    #[test]
    fn credentials_debug_shows_nothing() {
        let c = Credentials {
            user: "admin".into(),
            password: "s3cret".into(),
        };
        assert_eq!(format!("{c:?}"), "Credentials { .. }");
    }

    /// A check against a file of `users` (cheap argon2 parameters), three free failures
    /// then a minute's block; the directory holds the file.
    fn checker(users: &[(&str, &str)]) -> (tempfile::TempDir, Arc<AdminAuth>) {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("admin-passwd");
        let params = security::Argon2Params {
            memory_kib: 64,
            iterations: 1,
            parallelism: 1,
        };
        let mut file = PasswordFile::default();
        for (user, password) in users {
            let phc = security::hash_password(password.as_bytes(), &params).unwrap();
            file.set(user, security::StoredHash::parse(&phc).unwrap())
                .unwrap();
        }
        file.save(&path).unwrap();
        let watched = WatchedFile::load("admin_password_file", &path, |p| {
            PasswordFile::load(p).map_err(|e| e.to_string())
        })
        .unwrap();
        let throttle = ThrottleSection {
            free_failures: 3,
            base_delay_ms: 60_000,
            max_delay_ms: 60_000,
        };
        let auth = AdminAuth::new(Arc::new(watched), &throttle, Arc::new(Metrics::new()));
        (dir, Arc::new(auth))
    }

    fn headers(value: &[u8]) -> HeaderMap {
        let mut h = HeaderMap::new();
        h.insert(
            header::AUTHORIZATION,
            HeaderValue::from_bytes(value).unwrap(),
        );
        h
    }

    /// The whole check against a real password file: the right user and password pass
    /// (the second time from the cache), anything else is one refusal, and a throttled
    /// address is refused even the right password.
    #[tokio::test]
    async fn the_check_accepts_only_a_user_of_the_file() {
        let (_dir, auth) = checker(&[("admin", "s3cret"), ("bediener-ü", "pässwort")]);
        let peer = Some(IpAddr::from([10, 0, 0, 7]));
        let right = headers(&basic(b"admin:s3cret"));
        assert_eq!(auth.check(peer, &right).await, Ok(()));
        assert_eq!(auth.cache.len(), 1);
        assert_eq!(auth.check(peer, &right).await, Ok(()));
        assert_eq!(
            auth.check(peer, &headers(&basic("bediener-ü:pässwort".as_bytes())))
                .await,
            Ok(())
        );
        assert_eq!(
            auth.check(peer, &HeaderMap::new()).await,
            Err(Refusal::Missing)
        );
        let mut twice = right.clone();
        twice.append(
            header::AUTHORIZATION,
            HeaderValue::from_static("Basic eDp5"),
        );
        for wrong in [
            headers(&basic(b"admin:S3cret")),
            headers(&basic(b"nobody:s3cret")),
            headers(&basic("bediener-ü:passwort".as_bytes())),
            headers(b"Basic !!"),
            twice,
        ] {
            assert_eq!(
                auth.check(None, &wrong).await,
                Err(Refusal::Invalid),
                "{wrong:?}"
            );
        }
        // From one address: three free failures, the fourth blocks it. (Guesses at a name
        // that is no user: only the address and the endpoint count them.)
        for _ in 0..4 {
            let wrong = headers(&basic(b"guesser:guess"));
            assert_eq!(auth.check(peer, &wrong).await, Err(Refusal::Invalid));
        }
        assert!(matches!(
            auth.check(peer, &right).await,
            Err(Refusal::Throttled(..))
        ));
        // Another address is not.
        assert_eq!(
            auth.check(Some(IpAddr::from([10, 0, 0, 8])), &right).await,
            Ok(())
        );
        let refused = auth.refuse(
            Refusal::Throttled(Duration::from_millis(1500), Scope::Address),
            peer,
        );
        assert_eq!(refused.status(), StatusCode::TOO_MANY_REQUESTS);
        assert_eq!(refused.headers()[header::RETRY_AFTER], "2");
        let refused = auth.refuse(Refusal::Invalid, peer);
        assert_eq!(refused.status(), StatusCode::UNAUTHORIZED);
        assert_eq!(refused.headers()[header::WWW_AUTHENTICATE], CHALLENGE);
    }

    /// Guesses at one user from many addresses meet that user's block (an IPv6 /64 or a
    /// pool of addresses gains nothing); a credential the cache verified still passes;
    /// guesses at names that are no user meet the endpoint's block after
    /// `OVERALL_FACTOR` times the free failures.
    #[tokio::test]
    async fn guesses_count_per_user_and_for_the_endpoint_too() {
        let (_dir, auth) = checker(&[("admin", "s3cret")]);
        let right = headers(&basic(b"admin:s3cret"));
        let scraper = Some(IpAddr::from([10, 0, 0, 1]));
        assert_eq!(auth.check(scraper, &right).await, Ok(()));
        let wrong = headers(&basic(b"admin:guess"));
        for i in 0..4u8 {
            let from = Some(IpAddr::from([10, 0, 1, i]));
            assert_eq!(auth.check(from, &wrong).await, Err(Refusal::Invalid), "{i}");
        }
        assert!(matches!(
            auth.check(Some(IpAddr::from([10, 0, 1, 9])), &wrong).await,
            Err(Refusal::Throttled(_, Scope::User))
        ));
        assert_eq!(auth.check(scraper, &right).await, Ok(()), "cached");
        let nobody = headers(&basic(b"nobody:guess"));
        // 30 failures are free (4 made above); the 31st blocks.
        let free = 3 * OVERALL_FACTOR - 4 + 1;
        for i in 0..free {
            let from = Some(IpAddr::from([10, 1, (i / 200) as u8, (i % 200) as u8]));
            assert_eq!(
                auth.check(from, &nobody).await,
                Err(Refusal::Invalid),
                "{i}"
            );
        }
        assert!(matches!(
            auth.check(Some(IpAddr::from([10, 2, 0, 1])), &nobody).await,
            Err(Refusal::Throttled(_, Scope::Endpoint))
        ));
        assert_eq!(auth.check(scraper, &right).await, Ok(()), "cached");
    }
}

//! # fbbus security
//!
//! Everything fbbus decides about *who* may connect and *what* they may do,
//! kept apart from the network code so it can be read, tested and reviewed
//! on its own. The broker uses it to check passwords on CONNECT, to check
//! every PUBLISH and SUBSCRIBE against access rules, and to slow down
//! password guessing. The `fbbus passwd` command uses it to edit password
//! files.
//!
//! **It owns** password hashes and files, access rules, login throttling
//! and the credential cache. **It must not know** MQTT sessions, packets or
//! the network (it is handed a user name, a client id, a topic or filter,
//! and a peer address), nor the FB model: of `fb-bridge` it uses only the
//! MQTT topic/filter grammar, `fb_bridge::topic::filter`, so that the ACL
//! judges topics exactly as the broker and the bus route them.
//!
//! | module | concept |
//! |---|---|
//! | [`hash`] | password hashes: new argon2id ones, and verifying Mosquitto's |
//! | [`password_file`] | the `user:HASH` file: load, edit, save atomically, verify |
//! | [`acl`] | access rules (Mosquitto `acl_file` syntax), judged with `fb_bridge::topic::filter` |
//! | [`throttle`] | per-address exponential backoff after failed logins |
//! | [`credential_cache`] | skip argon2 for devices that just verified |
//!
//! ## Password file
//!
//! ```text
//! # comments and blank lines are ignored
//! plc-7:$argon2id$v=19$m=8192,t=1,p=1$<salt>$<hash>
//! alice:$7$101$<base64 salt>$<base64 hash>      # from Mosquitto 2.x
//! bob:$6$<base64 salt>$<base64 hash>            # from Mosquitto 1.x
//! ```
//!
//! One user per line; user names are non-empty with no `:`, whitespace or
//! control characters. A Mosquitto password file loads as it is. fbbus
//! writes argon2id only; a Mosquitto entry reports
//! [`Verification::Accepted { legacy: true }`](Verification::Accepted) so
//! the broker can re-hash it with the password it has just seen. Saving is
//! atomic (temporary file, fsync, rename) and the file gets mode 0600.
//!
//! ## ACL file
//!
//! ```text
//! topic read $SYS/#            # before any section: applies to every client
//! user alice                   # following `topic` lines apply to user alice
//! topic readwrite line1/alice/#
//! client plc-7                 # following `topic` lines apply to client id plc-7
//! topic write cell/7/#
//! pattern write fb/%c/#        # `pattern` applies to every client
//! topic deny secrets/#         # `deny` beats any grant
//! ```
//!
//! Without an ACL file everything is allowed ([`AclRules::allow_all`]);
//! with one, everything not granted is denied. See [`acl`] for `%u`/`%c`
//! substitution and how subscriptions are checked.
//!
//! ## Defaults and why
//!
//! * **argon2id, 8 MiB, 1 iteration, 1 lane** ([`Argon2Params`]): about
//!   2.5 ms of CPU per check in release on a 2-core machine, so after a
//!   broker restart 1,045 devices reconnecting at once are all verified in
//!   about 1.5 s (the broker's `reconnect_storm` example). Device secrets should be random high-entropy strings, for which
//!   this is ample; operators with human passwords should raise the cost
//!   (`fbbus passwd … --memory-kib/--iterations`).
//! * **Unknown users cost a full argon2 check** ([`hash::dummy_verify`]), so
//!   timing does not reveal which user names exist.
//! * **Throttle: 5 free failures, then 1 s doubling to 60 s, forgotten after
//!   10 minutes idle, at most 100,000 addresses** ([`ThrottleConfig`]): a
//!   device with a wrong password keeps trying once a minute and recovers
//!   by itself once fixed; a guesser gets about 60 tries an hour per
//!   address.
//! * **Credential cache** ([`CredentialCache`]): stores a keyed HMAC of the
//!   credentials and the stored hash, never the password; a changed
//!   password-file entry misses automatically.
//!
//! Passwords and hash strings never appear in errors, `Debug` output or
//! logs produced by this crate.

pub mod acl;
pub mod credential_cache;
pub mod hash;
pub mod password_file;
pub mod throttle;

pub use acl::{AclError, AclRules, Identity};
pub use credential_cache::CredentialCache;
pub use hash::{hash_password, Argon2Params, HashError, StoredHash};
pub use password_file::{PasswordFile, PasswordFileError, Verification};
pub use throttle::{LoginThrottle, ThrottleConfig, ThrottleKey};

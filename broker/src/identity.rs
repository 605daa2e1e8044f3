//! Who a session belongs to, and which client ids a user may connect with (issue 20: "a
//! device is who its password says").
//!
//! **The owner.** A session belongs to the identity that created it: the username the
//! password file verified. A connection with another identity never resumes, reads from
//! or takes over that session: its CONNECT is refused (MQTT 5 0x85, 3.1.1 0x02,
//! `fbbus_connects_refused_total{reason="client_id_owned"}`) before anything of the
//! session is touched (no will cancelled, no takeover, no registry change). There is no
//! setting that lets another identity in: two machines that must share a session share a
//! user. Clients without a username (a loopback listener with `allow_anonymous`) are
//! all one identity, [`Owner::Anonymous`], and so are all clients of a broker without a
//! password file, whose usernames nobody verifies.
//!
//! **The binding.** `[auth] client_id` ([`ClientIdRule`]) can in addition tie the client id
//! to the username, as Mosquitto's `use_username_as_clientid` does, so that a user cannot
//! even occupy another device's client id while that device has no session. It applies to
//! clients that log in with a username; anonymous clients keep any client id.
//!
//! The owner is kept per client id in the session table (`session::table`), for connected
//! and for kept offline sessions, and with delayed wills (`wills`).

use std::collections::HashMap;
use std::fmt;
use std::sync::{Arc, Mutex, PoisonError};
use std::time::{Duration, Instant};

use serde::Deserialize;

/// The identity a session belongs to.
#[derive(Debug, Clone, PartialEq, Eq, Hash)]
pub enum Owner {
    /// No verified username: every anonymous client, or every client of a broker without
    /// a password file.
    Anonymous,
    /// The username the password file verified.
    User(Arc<str>),
}

impl fmt::Display for Owner {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            Owner::Anonymous => f.write_str("(anonymous)"),
            Owner::User(user) => f.write_str(user),
        }
    }
}

/// `[auth] client_id`: which client ids a client that logs in with a username may use.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, Deserialize)]
pub enum ClientIdRule {
    /// Any client id (the ownership rule still holds).
    #[default]
    #[serde(rename = "any")]
    Any,
    /// The client id is the username.
    #[serde(rename = "%u")]
    Username,
    /// The client id is the username, or the username, `-` and anything
    /// (`plc-1`, `plc-1-debug`).
    #[serde(rename = "%u-*")]
    UsernamePrefix,
}

impl ClientIdRule {
    /// Whether a client logged in as `username` (None: anonymous) may use `client_id`.
    pub fn allows(self, client_id: &str, username: Option<&str>) -> bool {
        let Some(user) = username else {
            return true;
        };
        match self {
            ClientIdRule::Any => true,
            ClientIdRule::Username => client_id == user,
            ClientIdRule::UsernamePrefix => client_id
                .strip_prefix(user)
                .is_some_and(|rest| rest.is_empty() || rest.starts_with('-')),
        }
    }
}

/// Refusals remembered to be logged at most once per (client id, identity) in this time.
pub const REFUSAL_LOG_INTERVAL: Duration = Duration::from_secs(60);

/// (client id, identity) pairs remembered for [`REFUSAL_LOG_INTERVAL`] at most.
const REFUSAL_LOG_KEYS: usize = 1024;

/// The identity rules of the line: who owns what, which client ids are bound.
pub struct Identities {
    /// Usernames are verified (there is a password file).
    verified: bool,
    rule: ClientIdRule,
    logged: Mutex<HashMap<(String, Owner), Instant>>,
}

impl Identities {
    pub fn new(verified: bool, rule: ClientIdRule) -> Identities {
        Identities {
            verified,
            rule,
            logged: Mutex::default(),
        }
    }

    /// The identity of a client that logged in with `username`.
    pub fn owner(&self, username: Option<&str>) -> Owner {
        match username {
            Some(user) if self.verified => Owner::User(user.into()),
            _ => Owner::Anonymous,
        }
    }

    /// Whose shares a client of `owner` from `ip` spends (issue 33: the store's bytes and
    /// messages, retained messages): its verified username, or, without one, its address
    /// (client ids are free to choose, an address is not).
    pub fn share(&self, owner: &Owner, ip: std::net::IpAddr) -> String {
        match owner {
            Owner::User(user) => format!("user:{user}"),
            Owner::Anonymous => format!("address:{}", ip.to_canonical()),
        }
    }

    /// Whether `[auth] client_id` lets `username` use `client_id`.
    pub fn bound(&self, client_id: &str, username: Option<&str>) -> bool {
        self.rule.allows(client_id, username)
    }

    /// Whether a refusal of `client_id` for `owner` is to be logged now: once per pair
    /// per [`REFUSAL_LOG_INTERVAL`], at most [`REFUSAL_LOG_KEYS`] pairs remembered (the
    /// rest only counted), so a client retrying in a loop cannot flood the log or grow
    /// this memory.
    pub fn may_log(&self, client_id: &str, owner: &Owner) -> bool {
        let now = Instant::now();
        let mut logged = self.logged.lock().unwrap_or_else(PoisonError::into_inner);
        let key = (client_id.to_owned(), owner.clone());
        if logged
            .get(&key)
            .is_some_and(|at| now.duration_since(*at) < REFUSAL_LOG_INTERVAL)
        {
            return false;
        }
        if logged.len() >= REFUSAL_LOG_KEYS {
            logged.retain(|_, at| now.duration_since(*at) < REFUSAL_LOG_INTERVAL);
            if logged.len() >= REFUSAL_LOG_KEYS {
                return false;
            }
        }
        logged.insert(key, now);
        true
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn usernames_are_identities_only_when_verified() {
        let verified = Identities::new(true, ClientIdRule::Any);
        assert_eq!(verified.owner(Some("plc-1")), Owner::User("plc-1".into()));
        assert_eq!(verified.owner(None), Owner::Anonymous);
        let unverified = Identities::new(false, ClientIdRule::Any);
        assert_eq!(unverified.owner(Some("plc-1")), Owner::Anonymous);
    }

    #[test]
    fn binding_rules() {
        use ClientIdRule::*;
        let cases = [
            (Any, "anything", Some("plc-1"), true),
            (Username, "plc-1", Some("plc-1"), true),
            (Username, "plc-10", Some("plc-1"), false),
            (Username, "plc-1-debug", Some("plc-1"), false),
            (UsernamePrefix, "plc-1", Some("plc-1"), true),
            (UsernamePrefix, "plc-1-debug", Some("plc-1"), true),
            (UsernamePrefix, "plc-10", Some("plc-1"), false),
            (UsernamePrefix, "plc", Some("plc-1"), false),
            // Any UTF-8: the prefix is compared as a string, never sliced by bytes.
            (UsernamePrefix, "Förderband-ä", Some("Förderband"), true),
            (UsernamePrefix, "Förderbandä", Some("Förderband"), false),
            // Anonymous clients are not bound (loopback listeners only).
            (Username, "dinasore-4711", None, true),
        ];
        for (rule, client_id, user, allowed) in cases {
            assert_eq!(
                rule.allows(client_id, user),
                allowed,
                "{rule:?} {client_id} {user:?}"
            );
        }
    }

    #[test]
    fn refusals_are_logged_once_per_pair_and_bounded() {
        let ids = Identities::new(true, ClientIdRule::Any);
        let owner = Owner::User("devA".into());
        assert!(ids.may_log("devB", &owner));
        assert!(!ids.may_log("devB", &owner), "once per interval");
        assert!(ids.may_log("devC", &owner));
        assert!(ids.may_log("devB", &Owner::Anonymous));
        for i in 0..2 * REFUSAL_LOG_KEYS {
            ids.may_log(&format!("churn-{i}"), &owner);
        }
        let logged = ids.logged.lock().unwrap();
        assert!(logged.len() <= REFUSAL_LOG_KEYS);
    }

    #[test]
    fn the_rule_reads_from_toml() {
        #[derive(Deserialize)]
        struct T {
            client_id: ClientIdRule,
        }
        let read =
            |s: &str| toml::from_str::<T>(&format!("client_id = \"{s}\"")).map(|t| t.client_id);
        assert_eq!(read("any").unwrap(), ClientIdRule::Any);
        assert_eq!(read("%u").unwrap(), ClientIdRule::Username);
        assert_eq!(read("%u-*").unwrap(), ClientIdRule::UsernamePrefix);
        assert!(read("%c").is_err());
    }
}

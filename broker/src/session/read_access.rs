//! Read access at delivery: a client is sent only what the access rules in force let it
//! read, whatever subscription the router matched.
//!
//! SUBSCRIBE is checked when made (`inbound`), but that alone is not enough: the ACL file
//! is reloaded while subscriptions stay in the router, and a resumed session's
//! subscriptions were made by an earlier connection (the router keeps them; this
//! connection's `Session::subscriptions` has only its own). So every delivery's topic is
//! checked against the rules in force ([`Access::can_read`], the same answer
//! `can_subscribe` gives for that topic). A grant revoked by a reload stops deliveries
//! from the next one on.
//!
//! Cost: without an ACL file nothing is looked up (one match on [`Access::AllowAll`]).
//! With rules, each session remembers its verdicts per topic ([`ReadVerdicts`]) under the
//! rules' generation, which a reload changes; a device stream repeats few topics, so most
//! deliveries cost one hash lookup. The memo is bounded per session in entries and bytes,
//! and started afresh when full.
//!
//! A refused delivery is not sent; the router is acknowledged on the client's behalf
//! (`deliver_publish`), it is counted in `fbbus_acl_denied_total{action="deliver"}` and
//! logged once per session and topic (`Session::log_denial`).

use std::collections::HashMap;

use security::Identity;

use super::Session;
use crate::policy::access::Access;

/// Topics remembered per session at most.
const MAX_VERDICTS: usize = 128;
/// Bytes of topic names remembered per session at most; longer topics are not remembered.
const MAX_VERDICT_BYTES: usize = 8 * 1024;

/// One session's read verdicts under one generation of the rules.
#[derive(Default)]
pub(super) struct ReadVerdicts {
    generation: u64,
    bytes: usize,
    verdicts: HashMap<Box<str>, bool>,
}

impl ReadVerdicts {
    /// May `who` read `topic` under `access`? Remembered while `access` stays at the
    /// same generation.
    fn check(&mut self, access: &Access, generation: u64, who: Identity<'_>, topic: &str) -> bool {
        if self.generation != generation {
            self.forget();
            self.generation = generation;
        }
        if let Some(&verdict) = self.verdicts.get(topic) {
            return verdict;
        }
        // `generation` was read before the rules are: a verdict is never older than the
        // generation it is remembered under.
        let verdict = access.can_read(who, topic);
        if topic.len() <= MAX_VERDICT_BYTES {
            if self.verdicts.len() >= MAX_VERDICTS || self.bytes + topic.len() > MAX_VERDICT_BYTES {
                self.forget();
            }
            self.bytes += topic.len();
            self.verdicts.insert(topic.into(), verdict);
        }
        verdict
    }

    fn forget(&mut self) {
        self.verdicts.clear();
        self.bytes = 0;
    }
}

impl Session {
    /// May this client be sent a message published on `topic`? Counts and logs a refusal.
    pub(super) fn may_read(&mut self, topic: &[u8]) -> bool {
        let access = self.ctx.policy.access();
        // `$SYS/` has a rule of its own (loopback, or granted), with or without an ACL
        // file; its deliveries are a few per `sys_interval_s`, not worth remembering.
        if topic.starts_with(security::acl::SYS_PREFIX.as_bytes()) {
            let readable = std::str::from_utf8(topic)
                .is_ok_and(|topic| access.can_read_sys(self.identity(), self.on_loopback(), topic));
            if !readable {
                self.ctx
                    .metrics
                    .acl_denied
                    .with_label_values(&["deliver"])
                    .inc();
                self.log_denial("deliver", &String::from_utf8_lossy(topic));
            }
            return readable;
        }
        let Some(generation) = access.generation() else {
            return true;
        };
        // Topics are checked UTF-8 when published; anything else is not readable.
        let readable = std::str::from_utf8(topic).is_ok_and(|topic| {
            let who = Identity {
                username: self.client.username.as_deref(),
                client_id: &self.client.client_id,
            };
            self.read_verdicts
                .get_or_insert_with(Box::default)
                .check(access, generation, who, topic)
        });
        if !readable {
            self.ctx
                .metrics
                .acl_denied
                .with_label_values(&["deliver"])
                .inc();
            self.log_denial("deliver", &String::from_utf8_lossy(topic));
        }
        readable
    }
}

#[cfg(test)]
mod tests {
    use std::io::Write;
    use std::sync::Arc;

    use security::AclRules;

    use super::*;
    use crate::metrics::Metrics;
    use crate::watched_file::WatchedFile;

    fn who() -> Identity<'static> {
        Identity {
            username: Some("reader"),
            client_id: "reader",
        }
    }

    #[test]
    fn verdicts_follow_the_rules_across_a_reload_and_stay_bounded() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("acl");
        let write = |text: &str| {
            std::fs::File::create(&path)
                .unwrap()
                .write_all(text.as_bytes())
                .unwrap()
        };
        write("user reader\ntopic read fb/#\n");
        let file = Arc::new(
            WatchedFile::load("acl_file", &path, |p| {
                AclRules::load(p).map_err(|e| e.to_string())
            })
            .unwrap(),
        );
        let access = Access::new(Some(Arc::clone(&file)));
        let mut memo = ReadVerdicts::default();
        let generation = access.generation().unwrap();
        assert!(memo.check(&access, generation, who(), "fb/dev-a/CONV/SPEED"));
        assert!(!memo.check(&access, generation, who(), "other/x"));

        // Revoked by a reload: the next check under the new generation refuses.
        write("user reader\ntopic read other/#\n");
        assert!(file.reload(true, &Metrics::new()));
        let next = access.generation().unwrap();
        assert_ne!(next, generation);
        assert!(!memo.check(&access, next, who(), "fb/dev-a/CONV/SPEED"));
        assert!(memo.check(&access, next, who(), "other/x"));

        // Bounded in entries and bytes, multi-byte topics included.
        for i in 0..10 * MAX_VERDICTS {
            memo.check(&access, next, who(), &format!("other/ß{i}"));
            assert!(memo.verdicts.len() <= MAX_VERDICTS);
            assert!(memo.bytes <= MAX_VERDICT_BYTES);
        }
        let long = format!("other/{}", "é".repeat(MAX_VERDICT_BYTES));
        assert!(memo.check(&access, next, who(), &long));
        assert!(memo.bytes <= MAX_VERDICT_BYTES);
    }

    #[test]
    fn without_an_acl_file_there_is_no_generation() {
        assert_eq!(Access::AllowAll.generation(), None);
        assert!(Access::AllowAll.can_read(who(), "anything/at/all"));
    }
}

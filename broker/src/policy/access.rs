//! Stage 1 of the publish policy, and the rule for subscriptions: the access rules.
//!
//! A broker without an ACL file lets every authenticated client publish and subscribe
//! anywhere (fbbus's own namespaces aside, which the typed stage guards). That is one of
//! the two values of [`Access`], not an `Option` every caller has to remember to check.

use std::sync::Arc;

use security::{AclRules, Identity};

use crate::watched_file::WatchedFile;

/// The access rules the broker serves with.
pub enum Access {
    /// No ACL file configured.
    AllowAll,
    /// `[auth] acl_file`, reloaded when it changes.
    Rules(Arc<WatchedFile<AclRules>>),
}

impl Access {
    pub fn new(file: Option<Arc<WatchedFile<AclRules>>>) -> Access {
        file.map_or(Access::AllowAll, Access::Rules)
    }

    /// May `who` publish on `topic`? Never on `$SYS/`, the broker's status topics.
    pub fn can_publish(&self, who: Identity<'_>, topic: &str) -> bool {
        match self {
            Access::AllowAll => !security::acl::is_sys(topic),
            Access::Rules(rules) => rules.get().can_publish(who, topic),
        }
    }

    /// May `who` be sent a message published on `topic`? Asked at delivery
    /// (`session::read_access`), so subscriptions the rules no longer allow (made before
    /// a reload, or by an earlier connection of the session) deliver nothing they refuse.
    pub fn can_read(&self, who: Identity<'_>, topic: &str) -> bool {
        match self {
            Access::AllowAll => true,
            Access::Rules(rules) => rules.get().can_read(who, topic),
        }
    }

    /// Which version of the rules is in force: None without an ACL file (nothing ever
    /// changes), otherwise a number that changes with each reload. Verdicts remembered
    /// under one number hold until it changes; read it before asking.
    pub fn generation(&self) -> Option<u64> {
        match self {
            Access::AllowAll => None,
            Access::Rules(rules) => Some(rules.generation()),
        }
    }

    /// May `who`, connected from loopback or not, subscribe to the `$SYS/` filter
    /// `filter`? Loopback clients may, and others an ACL rule grants it to
    /// ([`AclRules::can_subscribe_sys`]).
    pub fn can_subscribe_sys(&self, who: Identity<'_>, loopback: bool, filter: &str) -> bool {
        match self {
            Access::AllowAll => AclRules::allow_all().can_subscribe_sys(who, loopback, filter),
            Access::Rules(rules) => rules.get().can_subscribe_sys(who, loopback, filter),
        }
    }

    /// May `who` be sent the `$SYS/` topic `topic`? As [`Access::can_subscribe_sys`].
    pub fn can_read_sys(&self, who: Identity<'_>, loopback: bool, topic: &str) -> bool {
        match self {
            Access::AllowAll => AclRules::allow_all().can_read_sys(who, loopback, topic),
            Access::Rules(rules) => rules.get().can_read_sys(who, loopback, topic),
        }
    }

    /// May `who` subscribe to `filter`?
    pub fn can_subscribe(&self, who: Identity<'_>, filter: &str) -> bool {
        match self {
            Access::AllowAll => true,
            Access::Rules(rules) => rules.get().can_subscribe(who, filter),
        }
    }
}

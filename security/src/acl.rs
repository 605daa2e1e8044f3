//! Access rules: which client may publish to and subscribe to which topics.
//!
//! The syntax is Mosquitto's `acl_file` plus a `client` section, so existing
//! Mosquitto ACLs mostly load unchanged:
//!
//! ```text
//! # comment
//! topic read $SYS/#            # before any section: applies to every client
//! user alice                   # following `topic` lines apply to username alice
//! topic readwrite line1/alice/#
//! client plc-7                 # following `topic` lines apply to client id plc-7
//! topic write cell/7/#
//! pattern write fb/%c/#        # `pattern` applies to every client wherever it appears
//! pattern read fb/#
//! topic deny secrets/#         # `deny` overrides any grant
//! ```
//!
//! Differences from Mosquitto:
//!
//! * `topic` lines before the first section apply to **every** client.
//!   Mosquitto applies them to anonymous clients only, so review such lines
//!   when importing a Mosquitto ACL: they grant more here.
//! * A filter is one whitespace-free word and may be followed by a `#`
//!   comment (Mosquitto takes the rest of the line, spaces included).
//! * `%u` and `%c` work in `topic` lines too.
//!
//! Once any rules exist, everything not granted is denied, and a `deny`
//! rule that applies to the client beats every grant. The substitutions
//! `%u` (user name) and `%c` (client id) are made per client. A rule that
//! uses `%u` does not apply to a client without a user name. If a
//! substituted value contains `+`, `#` or `/` or starts with `$`, a
//! granting rule does not match and a `deny` rule denies everything to
//! that client, so a crafted client id or user name can never widen access.
//!
//! Subscriptions are checked when made: a filter is allowed only if every
//! topic it could match is readable, i.e. it is a subset of a granted read
//! filter and shares no topic with an applicable deny filter. Rules change
//! (the file is reloaded) and sessions outlive connections, so the broker
//! also checks each delivered topic ([`AclRules::can_read`]); for a topic
//! the two checks agree.
//!
//! `$SYS/` topics are the broker's status (Mosquitto's names): only the broker publishes
//! there, and who may read them has a default rule of its own ([`AclRules::can_read_sys`]):
//! clients on loopback (the line's own tools on the broker's host) and clients an ACL rule
//! grants read of them (`topic read $SYS/#`), a deny rule beating both.
//!
//! What a topic or filter is, what matches, covers and overlaps what, and
//! how `$share/<group>/` is split off, is MQTT's grammar, decided in
//! `fb_bridge::topic::filter` for the ACL, the bus and the broker alike.

use std::borrow::Cow;
use std::fs;
use std::io;
use std::path::{Path, PathBuf};

use fb_bridge::topic::filter::{covers, overlaps, strip_share};
/// The MQTT grammar lives in `fb_bridge::topic::filter`; these stay here because the
/// broker checks its topics and filters through `security::acl`.
pub use fb_bridge::topic::filter::{filter_matches, valid_filter, valid_topic};

/// The prefix of the broker's status topics (`$SYS/broker/uptime`, ...).
pub const SYS_PREFIX: &str = "$SYS/";

/// Whether a topic or filter (a `$share/<group>/` prefix aside) is under `$SYS/`.
pub fn is_sys(name: &str) -> bool {
    strip_share(name).is_some_and(|f| f.starts_with(SYS_PREFIX))
}

/// Who is asking: the authenticated user name (if any) and the client id.
#[derive(Debug, Clone, Copy)]
pub struct Identity<'a> {
    pub username: Option<&'a str>,
    pub client_id: &'a str,
}

/// A parsed ACL file, or "allow everything" when no file is configured.
#[derive(Debug, Clone)]
pub struct AclRules {
    allow_all: bool,
    rules: Vec<Rule>,
}

#[derive(Debug, Clone)]
struct Rule {
    scope: Scope,
    access: Access,
    /// A valid MQTT filter, possibly containing `%u` / `%c`.
    filter: String,
}

impl Rule {
    fn in_scope(&self, who: Identity) -> bool {
        match &self.scope {
            Scope::Everyone => true,
            Scope::User(user) => who.username == Some(user.as_str()),
            Scope::Client(id) => who.client_id == id,
        }
    }
}

/// Which clients a rule applies to.
#[derive(Debug, Clone, PartialEq, Eq)]
enum Scope {
    Everyone,
    User(String),
    Client(String),
}

#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Access {
    Read,
    Write,
    ReadWrite,
    Deny,
}

impl Access {
    fn from_word(word: &str) -> Option<Access> {
        match word {
            "read" => Some(Access::Read),
            "write" => Some(Access::Write),
            "readwrite" => Some(Access::ReadWrite),
            "deny" => Some(Access::Deny),
            _ => None,
        }
    }

    fn grants_read(self) -> bool {
        matches!(self, Access::Read | Access::ReadWrite)
    }

    fn grants_write(self) -> bool {
        matches!(self, Access::Write | Access::ReadWrite)
    }
}

/// Why an ACL file could not be loaded.
#[derive(Debug, thiserror::Error)]
pub enum AclError {
    #[error("cannot read ACL file {}: {io}", path.display())]
    Read { path: PathBuf, io: io::Error },
    #[error("{}line {line}: {problem}", display_path(path))]
    Line {
        /// The file, when loaded from one.
        path: Option<PathBuf>,
        /// 1-based line number.
        line: usize,
        problem: AclLineProblem,
    },
}

fn display_path(path: &Option<PathBuf>) -> String {
    match path {
        Some(path) => format!("{}: ", path.display()),
        None => String::new(),
    }
}

/// What is wrong with one line of an ACL file.
#[derive(Debug, thiserror::Error)]
pub enum AclLineProblem {
    #[error("unknown keyword `{0}` (expected topic, pattern, user or client)")]
    UnknownKeyword(String),
    #[error("unknown access word `{0}` (expected read, write, readwrite or deny)")]
    UnknownAccess(String),
    #[error("`{0}` needs a topic filter, e.g. `{0} read sensors/#`")]
    MissingFilter(&'static str),
    #[error("`{0}` needs a name, e.g. `{0} plc-7`")]
    MissingName(&'static str),
    #[error(
        "`{0}` is not a valid MQTT topic filter (`+` and `#` must fill a whole level \
         and `#` must be the last level)"
    )]
    InvalidFilter(String),
    #[error(
        "unexpected `{0}` at the end of the line (filters and names cannot contain \
         spaces; start comments with `#`)"
    )]
    TrailingText(String),
}

impl AclRules {
    /// Rules that allow every valid publish and subscription; used when no
    /// ACL file is configured.
    pub fn allow_all() -> AclRules {
        AclRules {
            allow_all: true,
            rules: Vec::new(),
        }
    }

    pub fn is_allow_all(&self) -> bool {
        self.allow_all
    }

    /// Reads and parses the ACL file at `path`.
    pub fn load(path: &Path) -> Result<AclRules, AclError> {
        let text = fs::read_to_string(path).map_err(|io| AclError::Read {
            path: path.to_owned(),
            io,
        })?;
        AclRules::parse(&text).map_err(|err| match err {
            AclError::Line { line, problem, .. } => AclError::Line {
                path: Some(path.to_owned()),
                line,
                problem,
            },
            other => other,
        })
    }

    /// Parses ACL text. A file with no rules denies everything.
    pub fn parse(text: &str) -> Result<AclRules, AclError> {
        let mut rules = Vec::new();
        let mut section = Scope::Everyone;
        for (number, line) in (1..).zip(text.lines()) {
            let at = |problem| AclError::Line {
                path: None,
                line: number,
                problem,
            };
            let words: Vec<&str> = line.split_whitespace().collect();
            let Some((&keyword, words)) = words.split_first() else {
                continue;
            };
            match keyword {
                _ if keyword.starts_with('#') => {}
                "user" => section = Scope::User(parse_name("user", words).map_err(at)?),
                "client" => section = Scope::Client(parse_name("client", words).map_err(at)?),
                "topic" => {
                    let (access, filter) = parse_rule("topic", words).map_err(at)?;
                    rules.push(Rule {
                        scope: section.clone(),
                        access,
                        filter,
                    });
                }
                "pattern" => {
                    let (access, filter) = parse_rule("pattern", words).map_err(at)?;
                    rules.push(Rule {
                        scope: Scope::Everyone,
                        access,
                        filter,
                    });
                }
                other => return Err(at(AclLineProblem::UnknownKeyword(other.to_owned()))),
            }
        }
        Ok(AclRules {
            allow_all: false,
            rules,
        })
    }

    /// May `who` publish to `topic`? True iff some applicable write rule
    /// matches the topic and no applicable deny rule does. Never under `$SYS/`: the
    /// broker's status is the broker's alone, whatever a rule grants.
    pub fn can_publish(&self, who: Identity, topic: &str) -> bool {
        if !valid_topic(topic) || is_sys(topic) {
            return false;
        }
        if self.allow_all {
            return true;
        }
        // A topic is a filter that matches exactly itself.
        self.decide(who, |access, rule_filter| match access {
            Access::Deny => covers(rule_filter, topic),
            _ => access.grants_write() && covers(rule_filter, topic),
        })
    }

    /// May `who` subscribe to `filter`? A `$share/<group>/` prefix is
    /// ignored. True iff the filter is a subset of some applicable read
    /// rule's filter and overlaps no applicable deny rule's filter.
    pub fn can_subscribe(&self, who: Identity, filter: &str) -> bool {
        let Some(filter) = strip_share(filter) else {
            return false;
        };
        if !valid_filter(filter) {
            return false;
        }
        if self.allow_all {
            return true;
        }
        self.decide(who, |access, rule_filter| match access {
            Access::Deny => overlaps(filter, rule_filter),
            _ => access.grants_read() && covers(rule_filter, filter),
        })
    }

    /// May `who` read `topic`, i.e. be sent a message published on it? True iff some
    /// applicable read rule matches the topic and no applicable deny rule does: exactly
    /// when `can_subscribe(who, topic)` would be, so every topic of an allowed
    /// subscription is readable. The broker asks at delivery, so a subscription made
    /// under older rules (or by an earlier connection of the session) delivers only what
    /// the rules in force allow.
    pub fn can_read(&self, who: Identity, topic: &str) -> bool {
        if !valid_topic(topic) {
            return false;
        }
        if self.allow_all {
            return true;
        }
        self.decide(who, |access, rule_filter| match access {
            Access::Deny => covers(rule_filter, topic),
            _ => access.grants_read() && covers(rule_filter, topic),
        })
    }

    /// May `who` subscribe to the `$SYS/` filter `filter`? From loopback: unless a deny
    /// rule overlaps it. From elsewhere: only where a read rule grants it, as for any
    /// filter ([`AclRules::can_subscribe`]); without an ACL file, nobody.
    pub fn can_subscribe_sys(&self, who: Identity, loopback: bool, filter: &str) -> bool {
        let Some(filter) = strip_share(filter) else {
            return false;
        };
        if !valid_filter(filter) || !filter.starts_with(SYS_PREFIX) {
            return false;
        }
        match (loopback, self.allow_all) {
            (true, _) => !self.denies(who, |rule_filter| overlaps(filter, rule_filter)),
            (false, true) => false,
            (false, false) => self.can_subscribe(who, filter),
        }
    }

    /// May `who` be sent the `$SYS/` topic `topic`? Exactly when
    /// [`AclRules::can_subscribe_sys`] would allow a subscription to it.
    pub fn can_read_sys(&self, who: Identity, loopback: bool, topic: &str) -> bool {
        if !valid_topic(topic) || !topic.starts_with(SYS_PREFIX) {
            return false;
        }
        match (loopback, self.allow_all) {
            (true, _) => !self.denies(who, |rule_filter| covers(rule_filter, topic)),
            (false, true) => false,
            (false, false) => self.can_read(who, topic),
        }
    }

    /// Whether a deny rule that applies to `who` matches (`applies` on its filter). A
    /// deny rule whose substitution is unsafe denies.
    fn denies(&self, who: Identity, applies: impl Fn(&str) -> bool) -> bool {
        self.rules
            .iter()
            .filter(|rule| rule.access == Access::Deny && rule.in_scope(who))
            .any(|rule| match substitute(&rule.filter, who) {
                Substituted::Filter(filter) => applies(&filter),
                Substituted::NoUser => false,
                Substituted::Unsafe => true,
            })
    }

    /// Runs `applies(access, effective_filter)` over the rules that apply
    /// to `who`: allowed iff it is true for some grant and for no deny.
    fn decide(&self, who: Identity, applies: impl Fn(Access, &str) -> bool) -> bool {
        let mut granted = false;
        for rule in &self.rules {
            if !rule.in_scope(who) {
                continue;
            }
            let filter = match substitute(&rule.filter, who) {
                Substituted::Filter(filter) => filter,
                Substituted::NoUser => continue,
                // Fail closed: skipping a deny would widen access.
                Substituted::Unsafe if rule.access == Access::Deny => return false,
                Substituted::Unsafe => continue,
            };
            if applies(rule.access, &filter) {
                if rule.access == Access::Deny {
                    return false;
                }
                granted = true;
            }
        }
        granted
    }
}

/// Parses the words after `user`/`client`: `name [# comment]`.
fn parse_name(keyword: &'static str, words: &[&str]) -> Result<String, AclLineProblem> {
    match words {
        [] => Err(AclLineProblem::MissingName(keyword)),
        [name, ..] if name.starts_with('#') => Err(AclLineProblem::MissingName(keyword)),
        [_, extra, ..] if !extra.starts_with('#') => {
            Err(AclLineProblem::TrailingText((*extra).to_owned()))
        }
        [name, ..] => Ok((*name).to_owned()),
    }
}

/// Parses the words after `topic`/`pattern`: `[access] filter [# comment]`.
/// The filter itself may be `#`, so a comment is only recognised after it.
fn parse_rule(keyword: &'static str, words: &[&str]) -> Result<(Access, String), AclLineProblem> {
    let (access, filter_at) = match words.first().and_then(|w| Access::from_word(w)) {
        Some(access) => (access, 1),
        None => (Access::ReadWrite, 0),
    };
    let filter = words
        .get(filter_at)
        .ok_or(AclLineProblem::MissingFilter(keyword))?;
    if let Some(extra) = words.get(filter_at + 1).filter(|w| !w.starts_with('#')) {
        // `topic reed a/b`: the first word was meant as an access word.
        return Err(if filter_at == 0 {
            AclLineProblem::UnknownAccess((*filter).to_owned())
        } else {
            AclLineProblem::TrailingText((*extra).to_owned())
        });
    }
    if !valid_filter(filter) {
        return Err(AclLineProblem::InvalidFilter((*filter).to_owned()));
    }
    Ok((access, (*filter).to_owned()))
}

/// The outcome of replacing `%u` and `%c` in a rule's filter.
enum Substituted<'a> {
    /// Borrowed when the filter has nothing to substitute: no allocation for most rules,
    /// which are checked at every publication and delivery.
    Filter(Cow<'a, str>),
    /// `%u` is used and the client has no user name: the rule is about
    /// users, so it does not apply (as in Mosquitto).
    NoUser,
    /// A value contains `+`, `#` or `/`, which would change the filter's
    /// structure, or starts with `$`, which could reach `$SYS` topics via
    /// `%c/#`. Grants do not match; denies match everything.
    Unsafe,
}

fn substitute<'a>(filter: &'a str, who: Identity) -> Substituted<'a> {
    if !filter.contains('%') {
        return Substituted::Filter(Cow::Borrowed(filter));
    }
    let mut out = String::with_capacity(filter.len());
    let mut rest = filter;
    while let Some(at) = rest.find('%') {
        out.push_str(&rest[..at]);
        let after = &rest[at + 1..];
        let value = match after.as_bytes().first() {
            Some(b'u') => match who.username {
                Some(user) => user,
                None => return Substituted::NoUser,
            },
            Some(b'c') => who.client_id,
            _ => {
                out.push('%');
                rest = after;
                continue;
            }
        };
        if value.contains(['+', '#', '/']) || value.starts_with('$') {
            return Substituted::Unsafe;
        }
        out.push_str(value);
        rest = &after[1..];
    }
    out.push_str(rest);
    Substituted::Filter(Cow::Owned(out))
}

#[cfg(test)]
mod tests {
    use super::*;

    const EXAMPLE: &str = "\
# comment
topic read $SYS/#            # before any section: applies to every client
user alice                   # following `topic` lines apply to username alice
topic readwrite line1/alice/#
client plc-7                 # following `topic` lines apply to client id plc-7
topic write cell/7/#
pattern write fb/%c/#        # `pattern` applies to every client wherever it appears
pattern read fb/#
topic deny secrets/#         # `deny` (Mosquitto style) overrides any grant
";

    fn who<'a>(username: Option<&'a str>, client_id: &'a str) -> Identity<'a> {
        Identity {
            username,
            client_id,
        }
    }

    fn rules(text: &str) -> AclRules {
        AclRules::parse(text).unwrap()
    }

    fn problem(text: &str) -> (usize, AclLineProblem) {
        match AclRules::parse(text) {
            Err(AclError::Line { line, problem, .. }) => (line, problem),
            other => panic!("expected a line error, got {other:?}"),
        }
    }

    #[test]
    fn sys_is_read_from_loopback_or_where_granted_and_a_deny_beats_both() {
        let alice = Identity {
            username: Some("alice"),
            client_id: "a",
        };
        let bob = Identity {
            username: Some("bob"),
            client_id: "b",
        };
        let open = AclRules::allow_all();
        assert!(open.can_subscribe_sys(bob, true, "$SYS/#"));
        assert!(open.can_read_sys(bob, true, "$SYS/broker/uptime"));
        assert!(!open.can_subscribe_sys(bob, false, "$SYS/#"));
        assert!(!open.can_read_sys(bob, false, "$SYS/broker/uptime"));
        assert!(
            !open.can_subscribe_sys(bob, true, "fb/#"),
            "not a $SYS filter"
        );

        let rules = AclRules::parse(
            "user alice\ntopic read $SYS/#\nuser bob\ntopic read fb/#\n\
             topic deny $SYS/broker/clients/#\n",
        )
        .unwrap();
        assert!(rules.can_subscribe_sys(alice, false, "$SYS/#"));
        assert!(rules.can_subscribe_sys(alice, false, "$share/g/$SYS/broker/+"));
        assert!(!rules.can_subscribe_sys(bob, false, "$SYS/#"));
        assert!(rules.can_subscribe_sys(bob, true, "$SYS/broker/uptime"));
        assert!(
            !rules.can_subscribe_sys(bob, true, "$SYS/#"),
            "overlaps bob's deny"
        );
        assert!(rules.can_read_sys(bob, true, "$SYS/broker/uptime"));
        assert!(!rules.can_read_sys(bob, true, "$SYS/broker/clients/connected"));
        assert!(is_sys("$SYS/broker/version") && is_sys("$share/g/$SYS/#"));
        assert!(!is_sys("$SYS") && !is_sys("fb/$SYS/x"));
        // Nobody publishes $SYS, not even with a grant.
        let writer = AclRules::parse("topic readwrite #\ntopic write $SYS/#\n").unwrap();
        assert!(!writer.can_publish(alice, "$SYS/broker/uptime"));
        assert!(!open.can_publish(alice, "$SYS/broker/uptime"));
        assert!(open.can_publish(alice, "fb/x"));
    }

    #[test]
    fn example_file() {
        let acl = rules(EXAMPLE);
        assert!(!acl.is_allow_all());
        let alice = who(Some("alice"), "alice-laptop");
        let plc7 = who(None, "plc-7");
        let plc8 = who(Some("bob"), "plc-8");

        // General section applies to everyone.
        for c in [alice, plc7, plc8] {
            assert!(acl.can_subscribe(c, "$SYS/broker/uptime"));
            assert!(!acl.can_publish(c, "$SYS/broker/uptime"));
        }
        // User section.
        assert!(acl.can_publish(alice, "line1/alice/temp"));
        assert!(acl.can_subscribe(alice, "line1/alice/#"));
        assert!(!acl.can_publish(plc8, "line1/alice/temp"));
        assert!(!acl.can_subscribe(plc8, "line1/alice/#"));
        // Client section: write only.
        assert!(acl.can_publish(plc7, "cell/7/state"));
        assert!(!acl.can_subscribe(plc7, "cell/7/state"));
        assert!(!acl.can_publish(plc8, "cell/7/state"));
        // Patterns apply to everyone, with %c substituted.
        assert!(acl.can_publish(plc8, "fb/plc-8/status"));
        assert!(!acl.can_publish(plc8, "fb/plc-7/status"));
        assert!(acl.can_subscribe(plc8, "fb/+/status"));
        assert!(acl.can_subscribe(alice, "fb/#"));
        // `topic deny` in the plc-7 section applies to plc-7 only.
        assert!(!acl.can_publish(plc7, "secrets/x"));
        // Deny by default.
        assert!(!acl.can_publish(alice, "other/topic"));
        assert!(!acl.can_subscribe(alice, "#"));
    }

    #[test]
    fn can_read_agrees_with_can_subscribe_on_topics() {
        let acl = rules(EXAMPLE);
        let ids = [
            who(Some("alice"), "x"),
            who(None, "plc-7"),
            who(None, "plc-8"),
            who(Some("dév-ß"), "dév-ß"),
            who(None, "a/b"),
            who(None, "$x"),
        ];
        let topics = [
            "$SYS/broker/uptime",
            "line1/alice/x",
            "cell/7/state",
            "fb/plc-8/CONV/SPEED",
            "fb/dév-ß/CONV",
            "secrets/a",
            "other",
            "fb",
        ];
        for c in ids {
            for t in topics {
                assert_eq!(acl.can_read(c, t), acl.can_subscribe(c, t), "{c:?} {t}");
            }
        }
        assert!(acl.can_read(who(None, "plc-8"), "fb/plc-8/x"));
        assert!(!acl.can_read(who(None, "plc-7"), "cell/7/state"));
        assert!(!acl.can_read(who(Some("alice"), "x"), "secrets/fb"));
        // Not topics: never readable, with or without rules.
        for t in ["fb/+", "fb/#", ""] {
            assert!(!acl.can_read(who(Some("alice"), "x"), t), "{t}");
            assert!(!AclRules::allow_all().can_read(who(None, "x"), t), "{t}");
        }
        assert!(AclRules::allow_all().can_read(who(None, "x"), "secrets/a"));
    }

    #[test]
    fn deny_overrides_grants() {
        let acl = rules("topic readwrite a/#\ntopic deny a/secret/#\n");
        let c = who(None, "c");
        assert!(acl.can_publish(c, "a/open"));
        assert!(!acl.can_publish(c, "a/secret"));
        assert!(!acl.can_publish(c, "a/secret/x"));
        assert!(acl.can_subscribe(c, "a/open/#"));
        // Overlapping a denied area denies the whole subscription.
        assert!(!acl.can_subscribe(c, "a/#"));
        assert!(!acl.can_subscribe(c, "a/+/x"));
        assert!(!acl.can_subscribe(c, "a/secret/deep/+"));
        // Deny applies whatever the order.
        let acl = rules("topic deny a/secret\ntopic readwrite a/#\n");
        assert!(!acl.can_publish(c, "a/secret"));
        assert!(acl.can_publish(c, "a/other"));
    }

    #[test]
    fn access_words_and_default() {
        let acl = rules("topic r/1\ntopic read r/2\ntopic write r/3\ntopic readwrite r/4\n");
        let c = who(None, "c");
        let can = |t: &str| (acl.can_subscribe(c, t), acl.can_publish(c, t));
        assert_eq!(can("r/1"), (true, true));
        assert_eq!(can("r/2"), (true, false));
        assert_eq!(can("r/3"), (false, true));
        assert_eq!(can("r/4"), (true, true));
        assert_eq!(can("r/5"), (false, false));
    }

    #[test]
    fn hash_filter_and_comments() {
        let acl = rules("topic #\ntopic read # # everything\n  # indented comment\n\n");
        let c = who(None, "c");
        assert!(acl.can_publish(c, "x/y"));
        assert!(acl.can_subscribe(c, "#"));
        // `#` never covers `$` topics.
        assert!(!acl.can_publish(c, "$SYS/x"));
        assert!(!acl.can_subscribe(c, "$SYS/#"));
    }

    #[test]
    fn user_substitution() {
        let acl = rules("pattern readwrite users/%u/#\ntopic read shared/%u/+/%c\n");
        let alice = who(Some("alice"), "dev1");
        assert!(acl.can_publish(alice, "users/alice/x"));
        assert!(acl.can_publish(alice, "users/alice"));
        assert!(!acl.can_publish(alice, "users/bob/x"));
        assert!(acl.can_subscribe(alice, "shared/alice/q/dev1"));
        assert!(!acl.can_subscribe(alice, "shared/alice/q/dev2"));
        // No user name: %u rules do not apply.
        let anon = who(None, "dev1");
        assert!(!acl.can_publish(anon, "users//x"));
        assert!(!acl.can_publish(anon, "users/%u/x"));
        // A `%` not followed by u or c is literal.
        let acl = rules("topic a/100%/%x\n");
        assert!(acl.can_publish(anon, "a/100%/%x"));
    }

    #[test]
    fn crafted_ids_do_not_widen_grants() {
        let acl = rules("pattern readwrite fb/%c/#\npattern readwrite home/%u\n");
        for id in ["+", "#", "a/b", "x/#", "a+b"] {
            let c = who(None, id);
            assert!(!acl.can_publish(c, "fb/a/b"), "{id}");
            assert!(!acl.can_subscribe(c, "fb/#"), "{id}");
            assert!(!acl.can_subscribe(c, "fb/+/x"), "{id}");
        }
        let sys = who(None, "$SYS");
        let acl_sys = rules("pattern read %c/#\n");
        assert!(!acl_sys.can_subscribe(sys, "$SYS/#"));
        assert!(acl_sys.can_subscribe(who(None, "dev"), "dev/#"));
        let sneaky = who(Some("+"), "ok");
        assert!(!acl.can_subscribe(sneaky, "home/+"));
        assert!(!acl.can_publish(sneaky, "home/bob"));
        assert!(acl.can_publish(sneaky, "fb/ok/x"));
    }

    #[test]
    fn crafted_ids_fail_closed_on_deny_patterns() {
        let acl = rules("topic readwrite fb/#\npattern deny fb/%c/secret\n");
        assert!(!acl.can_publish(who(None, "a"), "fb/a/secret"));
        assert!(acl.can_publish(who(None, "a"), "fb/a/open"));
        // With id `a/b`, the deny cannot be applied precisely, so it denies all.
        let crafted = who(None, "a/b");
        assert!(!acl.can_publish(crafted, "fb/a/b/secret"));
        assert!(!acl.can_publish(crafted, "fb/open"));
        // A %u deny does not apply to clients without a user name.
        let acl = rules("topic readwrite fb/#\npattern deny fb/%u/secret\n");
        assert!(acl.can_publish(who(None, "a"), "fb/x/secret"));
        assert!(!acl.can_publish(who(Some("x"), "a"), "fb/x/secret"));
    }

    #[test]
    fn sys_topics() {
        let acl = rules("topic read $SYS/#\ntopic readwrite +/status\n");
        let c = who(None, "c");
        assert!(acl.can_subscribe(c, "$SYS/#"));
        assert!(acl.can_subscribe(c, "$SYS/broker/+"));
        assert!(!acl.can_publish(c, "$SYS/x"));
        assert!(!acl.can_publish(c, "$SYS/status"));
        assert!(acl.can_publish(c, "dev/status"));
        assert!(!acl.can_subscribe(c, "#"));
    }

    #[test]
    fn shared_subscriptions() {
        let acl = rules("topic read jobs/#\n");
        let c = who(None, "c");
        assert!(acl.can_subscribe(c, "$share/workers/jobs/#"));
        assert!(acl.can_subscribe(c, "$share/workers/jobs/+/new"));
        assert!(!acl.can_subscribe(c, "$share/workers/other/#"));
        assert!(!acl.can_subscribe(c, "$share/workers"));
        assert!(!acl.can_subscribe(c, "$share//jobs/#"));
        assert!(!acl.can_subscribe(c, "$share/w+/jobs/#"));
        assert!(!acl.can_subscribe(c, "$share/w/"));
    }

    #[test]
    fn empty_file_denies_everything_and_allow_all_allows() {
        let none = rules("# nothing here\n");
        let c = who(Some("alice"), "c");
        assert!(!none.is_allow_all());
        assert!(!none.can_publish(c, "a"));
        assert!(!none.can_subscribe(c, "#"));

        let all = AclRules::allow_all();
        assert!(all.is_allow_all());
        assert!(all.can_publish(c, "a/b"));
        assert!(!all.can_publish(c, "$SYS/x"), "the broker's own, even so");
        assert!(all.can_subscribe(c, "#"));
        assert!(all.can_subscribe(c, "$share/g/#"));
        // Malformed requests are refused even so.
        assert!(!all.can_publish(c, "a/+"));
        assert!(!all.can_publish(c, ""));
        assert!(!all.can_subscribe(c, "a/#/b"));
    }

    #[test]
    fn invalid_requests_are_refused() {
        let acl = rules("topic #\n");
        let c = who(None, "c");
        assert!(!acl.can_publish(c, "a/#"));
        assert!(!acl.can_publish(c, "a/+/b"));
        assert!(!acl.can_subscribe(c, "a/b#"));
        assert!(!acl.can_subscribe(c, ""));
    }

    #[test]
    fn parse_errors() {
        let (line, p) = problem("# c\ntopic reed a/b\n");
        assert_eq!(line, 2);
        assert!(matches!(p, AclLineProblem::UnknownAccess(w) if w == "reed"));
        let (line, p) = problem("\n\ntopic read a/#/b\n");
        assert_eq!(line, 3);
        assert!(matches!(p, AclLineProblem::InvalidFilter(f) if f == "a/#/b"));
        assert!(matches!(
            problem("topic\n").1,
            AclLineProblem::MissingFilter("topic")
        ));
        assert!(matches!(
            problem("pattern read # just a comment? no\n").1,
            AclLineProblem::TrailingText(_)
        ));
        assert!(matches!(
            problem("topic write\n").1,
            AclLineProblem::MissingFilter("topic")
        ));
        assert!(matches!(
            problem("topic read a/b c\n").1,
            AclLineProblem::TrailingText(w) if w == "c"
        ));
        assert!(matches!(
            problem("user\n").1,
            AclLineProblem::MissingName("user")
        ));
        assert!(matches!(
            problem("client # no name\n").1,
            AclLineProblem::MissingName("client")
        ));
        assert!(matches!(
            problem("user alice bob\n").1,
            AclLineProblem::TrailingText(_)
        ));
        assert!(matches!(
            problem("topics read a\n").1,
            AclLineProblem::UnknownKeyword(w) if w == "topics"
        ));
        assert!(matches!(
            problem("topic read a+/b\n").1,
            AclLineProblem::InvalidFilter(_)
        ));
        let msg = AclRules::parse("x\n").unwrap_err().to_string();
        assert!(msg.starts_with("line 1: unknown keyword `x`"), "{msg}");
    }

    #[test]
    fn load_names_the_file() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("acl");
        fs::write(&path, "topic read a\ntopic bogus a b\n").unwrap();
        let msg = AclRules::load(&path).unwrap_err().to_string();
        let expected = format!("{}: line 2: unknown access word `bogus`", path.display());
        assert!(msg.starts_with(&expected), "{msg}");
        fs::write(&path, EXAMPLE).unwrap();
        assert!(AclRules::load(&path).is_ok());
        assert!(matches!(
            AclRules::load(&dir.path().join("missing")),
            Err(AclError::Read { .. })
        ));
    }
}

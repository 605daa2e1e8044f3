//! The ACL file parser (`security::acl::AclRules::parse`, Mosquitto `acl_file` syntax
//! plus `client` sections) and the decisions made with what parsed: `can_publish` and
//! `can_subscribe` for arbitrary identities, topics and filters, `%u` / `%c` substitution
//! with crafted user names and client ids included.
//!
//! Input: the ACL text, then optionally a NUL byte and query lines
//! `<username or -> <client id> <topic or filter>`. Every rule's own filter is queried
//! too, and specialisations of each granted subscription.
//!
//! Checks: nothing panics; a parse error names a line of the text; only valid topics and
//! filters are ever allowed; a granted subscription grants every narrower one (a subset of
//! a readable filter is readable: that is what lets the broker check a subscription once);
//! `pattern deny #` added at the end denies every topic and filter outside `$`.
#![no_main]

use libfuzzer_sys::fuzz_target;
use security::acl::{self, AclError, AclRules, Identity};

fuzz_target!(|data: &[u8]| {
    let (acl_bytes, queries) = match data.iter().position(|b| *b == 0) {
        Some(at) => (&data[..at], &data[at + 1..]),
        None => (data, &[][..]),
    };
    let Ok(text) = std::str::from_utf8(acl_bytes) else {
        return;
    };
    let rules = match AclRules::parse(text) {
        Ok(rules) => rules,
        Err(e) => {
            let AclError::Line { line, .. } = &e else {
                panic!("parse returned a non-line error: {e}");
            };
            assert!(
                *line >= 1 && *line <= text.lines().count(),
                "error on line {line} of {} lines",
                text.lines().count()
            );
            let _ = e.to_string();
            return;
        }
    };
    assert!(!rules.is_allow_all());

    let mut asks: Vec<(Option<String>, String, String)> = Vec::new();
    for line in String::from_utf8_lossy(queries).lines().take(16) {
        let mut words = line.splitn(3, ' ');
        let (Some(user), Some(client), Some(topic)) = (words.next(), words.next(), words.next())
        else {
            continue;
        };
        let user = (user != "-").then(|| user.to_owned());
        asks.push((user, client.to_owned(), topic.to_owned()));
    }
    // The rules' own filters, asked by the identities of the queries and a plain one.
    let mut identities: Vec<(Option<String>, String)> = asks
        .iter()
        .map(|(u, c, _)| (u.clone(), c.clone()))
        .collect();
    identities.push((Some("alice".into()), "plc-7".into()));
    identities.truncate(4);
    for filter in rule_filters(text).into_iter().take(16) {
        for (user, client) in &identities {
            let substituted = filter
                .replace("%u", user.as_deref().unwrap_or("nobody"))
                .replace("%c", client);
            asks.push((user.clone(), client.clone(), substituted));
        }
    }

    let deny_all = AclRules::parse(&format!("{text}\npattern deny #\n"))
        .expect("an ACL that parsed still parses with one more valid line");
    for (user, client, q) in &asks {
        let who = Identity {
            username: user.as_deref(),
            client_id: client,
        };
        let publish = rules.can_publish(who, q);
        let subscribe = rules.can_subscribe(who, q);
        if publish {
            assert!(acl::valid_topic(q), "published to invalid topic {q:?}");
        }
        if subscribe {
            narrower(&rules, who, q);
        }
        if !q.starts_with('$') {
            assert!(
                !deny_all.can_publish(who, q),
                "`pattern deny #` let {q:?} be published"
            );
            assert!(
                !deny_all.can_subscribe(who, q),
                "`pattern deny #` let {q:?} be subscribed"
            );
        }
    }
});

/// The filter word of every `topic` and `pattern` line.
fn rule_filters(text: &str) -> Vec<String> {
    let mut filters = Vec::new();
    for line in text.lines() {
        let words: Vec<&str> = line.split_whitespace().collect();
        let rest = match words.first() {
            Some(&"topic") | Some(&"pattern") => &words[1..],
            _ => continue,
        };
        let filter = match rest {
            [access, filter, ..] if matches!(*access, "read" | "write" | "readwrite" | "deny") => {
                filter
            }
            [filter, ..] => filter,
            [] => continue,
        };
        filters.push((*filter).to_owned());
    }
    filters
}

/// Every filter narrower than a granted one is granted too: each `+` made one concrete
/// level, a trailing `#` made the parent level, one level or two.
fn narrower(rules: &AclRules, who: Identity<'_>, filter: &str) {
    let bare = match filter.strip_prefix("$share/") {
        Some(rest) => match rest.split_once('/') {
            Some((_, f)) => f,
            None => panic!("subscription to {filter:?} allowed"),
        },
        None => filter,
    };
    assert!(
        acl::valid_filter(bare),
        "subscription to invalid {filter:?} allowed"
    );
    let levels: Vec<&str> = bare.split('/').collect();
    let mut candidates = Vec::new();
    for (i, level) in levels.iter().enumerate() {
        let with = |replacement: &[&str]| {
            let mut l: Vec<&str> = levels[..i].to_vec();
            l.extend_from_slice(replacement);
            l.extend_from_slice(&levels[i + 1..]);
            l.join("/")
        };
        match *level {
            "+" => candidates.push(with(&["x"])),
            "#" => {
                if i > 0 {
                    candidates.push(levels[..i].join("/"));
                }
                candidates.push(with(&["x"]));
                candidates.push(with(&["x", "y"]));
                candidates.push(with(&["+", "#"]));
            }
            _ => {}
        }
    }
    for narrow in candidates {
        if acl::valid_filter(&narrow) {
            assert!(
                rules.can_subscribe(who, &narrow),
                "{filter:?} is allowed but the narrower {narrow:?} is not"
            );
        }
    }
}

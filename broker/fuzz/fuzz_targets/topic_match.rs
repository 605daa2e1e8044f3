//! Topic and filter validation and matching, on arbitrary UTF-8 (multi-byte characters,
//! `$` topics, empty levels) against arbitrary filters.
//!
//! Four implementations of MQTT matching live in fbbus, and a fifth is written here:
//!
//! - `rumqttd::protocol::{valid_topic, valid_filter, matches}`: the router's, used for
//!   every delivery (a panic here killed the router thread: issue 14, `é/x`);
//! - `security::acl::{valid_topic, valid_filter, filter_matches}` and the ACL's subset and
//!   overlap logic behind `can_subscribe` / `can_publish`;
//! - `fb_bridge::bus::keys::{filter_matches, covers, bridgeable_filter}`: the bus's, for
//!   `fb/` filters only (no `$` rule: `fb/` topics never start with `$`);
//! - `reference` below: the MQTT 3.1.1/5 rules, level by level, as plainly as possible.
//!
//! Where their contracts agree they must give the same answer: validity of a non-empty
//! filter or topic without NUL and within 65,535 bytes; matching of a valid topic against
//! a valid filter (not `$share/`); the bus matcher on topics not starting with `$`; the
//! ACL's subset test (a one-rule ACL `topic read F`) and overlap test (a deny rule).
//! The bus's key expressions must also round-trip (interest tokens, data keys, retained
//! queries), and typed topics must parse back from every encoding's namespace.
#![no_main]

use arbitrary::Arbitrary;
use fb_bridge::bus::keys;
use fb_bridge::codec::Encoding;
use fb_bridge::topic::{is_typed_namespace, TypedTopic};
use libfuzzer_sys::fuzz_target;
use security::acl::{self, AclRules, Identity};

/// Words with multi-byte characters, spelled out so they are common in the input.
const WORDS: [&str; 16] = [
    "é",
    "Förderband",
    "日本",
    "ライン",
    "€",
    "😀",
    "Ü",
    "ß",
    "\u{200b}",
    "\u{feff}",
    "a\u{301}",
    "fb",
    "fbbus",
    "$SYS",
    "$share",
    "$fbbus",
];

#[derive(Arbitrary, Debug)]
enum Level {
    Text(String),
    Word(u8),
    Plus,
    Hash,
    Empty,
    Dollar(String),
}

#[derive(Arbitrary, Debug)]
struct Input {
    topic: Vec<Level>,
    filter: Vec<Level>,
    raw_topic: String,
    raw_filter: String,
    /// Which topic levels become `+` in a filter made from the topic, and where `#` cuts.
    wildcard_mask: u64,
    hash_at: Option<u8>,
    line: String,
    share_group: Option<String>,
}

fn level_text(level: &Level) -> String {
    match level {
        Level::Text(s) => s.clone(),
        Level::Word(i) => WORDS[*i as usize % WORDS.len()].to_owned(),
        Level::Plus => "+".into(),
        Level::Hash => "#".into(),
        Level::Empty => String::new(),
        Level::Dollar(s) => format!("${s}"),
    }
}

fn join(levels: &[Level]) -> String {
    levels.iter().map(level_text).collect::<Vec<_>>().join("/")
}

/// A filter that matches `topic` by construction: some levels become `+`, and from some
/// level on everything becomes `#`. Wildcards in the first level never match `$` topics,
/// so those keep their first level.
fn filter_from_topic(topic: &str, mask: u64, hash_at: Option<u8>) -> String {
    let levels: Vec<&str> = topic.split('/').collect();
    let mut out = Vec::new();
    for (i, level) in levels.iter().enumerate() {
        let keep_first = i == 0 && topic.starts_with('$');
        if !keep_first && hash_at.is_some_and(|h| h as usize == i) {
            out.push("#");
            break;
        }
        if !keep_first && mask & (1 << (i % 64)) != 0 {
            out.push("+");
        } else {
            out.push(level);
        }
    }
    out.join("/")
}

mod reference {
    //! MQTT matching as the specification words it (MQTT 5 4.7, 3.1.1 4.7).

    fn wildcard(level: &str) -> bool {
        level == "+" || level == "#"
    }

    pub fn first_is_wildcard(filter: &str) -> bool {
        wildcard(filter.split('/').next().unwrap_or(""))
    }

    /// A valid topic name: at least one character, no wildcard characters, no NUL.
    pub fn valid_topic(t: &str) -> bool {
        !t.is_empty() && t.len() <= 65_535 && !t.contains(['+', '#', '\0'])
    }

    /// A valid filter: `+` fills a whole level, `#` fills the last level.
    pub fn valid_filter(f: &str) -> bool {
        if f.is_empty() || f.len() > 65_535 || f.contains('\0') {
            return false;
        }
        let levels: Vec<&str> = f.split('/').collect();
        levels.iter().enumerate().all(|(i, l)| match *l {
            "+" => true,
            "#" => i == levels.len() - 1,
            l => !l.contains(['+', '#']),
        })
    }

    fn levels_match(t: &[&str], f: &[&str]) -> bool {
        match (t, f) {
            (_, ["#"]) => true,
            ([], []) => true,
            ([t0, t_rest @ ..], [f0, f_rest @ ..]) => {
                (*f0 == "+" || f0 == t0) && levels_match(t_rest, f_rest)
            }
            _ => false,
        }
    }

    /// Does valid filter `f` match valid topic `t`? `#` also matches the parent level
    /// (`a/#` matches `a`); a filter starting with a wildcard matches no `$` topic.
    pub fn matches(t: &str, f: &str) -> bool {
        if t.starts_with('$') && first_is_wildcard(f) {
            return false;
        }
        let t: Vec<&str> = t.split('/').collect();
        let f: Vec<&str> = f.split('/').collect();
        levels_match(&t, &f)
    }

    fn levels_cover(o: &[&str], i: &[&str]) -> bool {
        match (o, i) {
            (["#", ..], _) => true,
            ([], []) => true,
            ([o0, o_rest @ ..], [i0, i_rest @ ..]) => {
                let ok = match *i0 {
                    "#" => false,
                    "+" => *o0 == "+",
                    lit => *o0 == "+" || *o0 == lit,
                };
                ok && levels_cover(o_rest, i_rest)
            }
            _ => false,
        }
    }

    /// Every topic `inner` matches is matched by `outer`, ignoring the `$` rule.
    pub fn covers_plain(outer: &str, inner: &str) -> bool {
        let o: Vec<&str> = outer.split('/').collect();
        let i: Vec<&str> = inner.split('/').collect();
        levels_cover(&o, &i)
    }

    /// [`covers_plain`] with the `$` rule: `$` topics are only matched by filters that
    /// do not start with a wildcard.
    pub fn covers(outer: &str, inner: &str) -> bool {
        if inner.starts_with('$') && first_is_wildcard(outer) {
            return false;
        }
        covers_plain(outer, inner)
    }

    fn levels_overlap(a: &[&str], b: &[&str]) -> bool {
        match (a, b) {
            (["#", ..], _) | (_, ["#", ..]) => true,
            ([], []) => true,
            ([a0, a_rest @ ..], [b0, b_rest @ ..]) => {
                (*a0 == "+" || *b0 == "+" || a0 == b0) && levels_overlap(a_rest, b_rest)
            }
            _ => false,
        }
    }

    /// Some topic is matched by both filters.
    pub fn overlaps(a: &str, b: &str) -> bool {
        if (first_is_wildcard(a) && b.starts_with('$'))
            || (first_is_wildcard(b) && a.starts_with('$'))
        {
            return false;
        }
        let a: Vec<&str> = a.split('/').collect();
        let b: Vec<&str> = b.split('/').collect();
        levels_overlap(&a, &b)
    }
}

fuzz_target!(|input: Input| {
    let built_topic = join(&input.topic);
    let built_filter = join(&input.filter);
    let topics = [built_topic.as_str(), input.raw_topic.as_str()];
    let made: Vec<String> = topics
        .iter()
        .map(|t| filter_from_topic(t, input.wildcard_mask, input.hash_at))
        .collect();
    let mut filters = vec![built_filter.as_str(), input.raw_filter.as_str()];
    filters.extend(made.iter().map(String::as_str));
    let shared = input
        .share_group
        .as_ref()
        .map(|g| format!("$share/{g}/{built_filter}"));

    for s in topics.iter().chain(&filters) {
        validity(s);
    }
    for t in topics {
        typed_topic(t);
        for f in &filters {
            matching(t, f);
        }
        if let Some(shared) = &shared {
            // The ACL's matcher ignores a well-formed `$share/<group>/` prefix.
            let _ = acl::filter_matches(shared, t);
        }
    }
    for (topic, filter) in topics.iter().zip(&made) {
        if reference::valid_topic(topic) && reference::valid_filter(filter) {
            assert!(
                reference::matches(topic, filter),
                "made {filter:?} from {topic:?}"
            );
        }
    }
    for outer in &filters {
        for inner in &filters {
            subsets(outer, inner);
        }
    }
    bus_keys(&input.line, &topics, &filters);
});

/// Validity: rumqttd's and the ACL's rules agree with the specification's wherever
/// rumqttd's contract covers the string (it leaves empty, NUL and length to its caller).
fn validity(s: &str) {
    let in_contract = !s.is_empty() && !s.contains('\0') && s.len() <= 65_535;
    let (r_topic, r_filter) = (
        rumqttd::protocol::valid_topic(s),
        rumqttd::protocol::valid_filter(s),
    );
    let (a_topic, a_filter) = (acl::valid_topic(s), acl::valid_filter(s));
    let _ = rumqttd::protocol::has_wildcards(s);
    assert_eq!(
        a_topic,
        reference::valid_topic(s),
        "acl::valid_topic({s:?})"
    );
    assert_eq!(
        a_filter,
        reference::valid_filter(s),
        "acl::valid_filter({s:?})"
    );
    if in_contract {
        assert_eq!(
            r_topic, a_topic,
            "valid_topic({s:?}): rumqttd {r_topic}, acl {a_topic}"
        );
        assert_eq!(
            r_filter, a_filter,
            "valid_filter({s:?}): rumqttd {r_filter}, acl {a_filter}"
        );
    }
}

fn matching(t: &str, f: &str) {
    // Never panic, valid or not.
    let router = rumqttd::protocol::matches(t, f);
    let acl_says = acl::filter_matches(f, t);
    let bus = keys::filter_matches(f, t);
    if !(reference::valid_topic(t) && reference::valid_filter(f)) || f.starts_with("$share/") {
        return;
    }
    let expected = reference::matches(t, f);
    assert_eq!(router, expected, "rumqttd matches({t:?}, {f:?})");
    // fbbus routes as MQTT does, except that a filter starting with a wildcard does not
    // reach the re-encoded copies (`dinasore/`, `fbdk/`; issue 35): the router gets
    // those prefixes in its config, the typed-topic model applies them itself.
    let routed = expected && !(fb_bridge::topic::is_mirror(t) && reference::first_is_wildcard(f));
    assert_eq!(acl_says, routed, "acl filter_matches({f:?}, {t:?})");
    if !t.starts_with('$') {
        assert_eq!(bus, routed, "bus filter_matches({f:?}, {t:?})");
    }
    // A one-rule ACL granting write on `f` lets exactly the matching topics be published,
    // except the broker's own `$SYS/` topics, which nobody publishes (issue 35).
    if let Some(rules) = one_rule("write", f) {
        assert_eq!(
            rules.can_publish(who(), t),
            expected && !t.starts_with(acl::SYS_PREFIX),
            "`topic write {f}` and publish {t:?}"
        );
    }
}

const NOBODY: Identity<'static> = Identity {
    username: None,
    client_id: "fuzz",
};

fn who() -> Identity<'static> {
    NOBODY
}

/// `topic <access> <filter>` as an ACL, when the filter can be written in one (one word,
/// no `%` substitutions, not read as a comment).
fn one_rule(access: &str, filter: &str) -> Option<AclRules> {
    if filter.contains(char::is_whitespace) || filter.contains('%') || !acl::valid_filter(filter) {
        return None;
    }
    let rules = AclRules::parse(&format!("topic {access} {filter}\n"))
        .unwrap_or_else(|e| panic!("`topic {access} {filter}` did not parse: {e}"));
    Some(rules)
}

/// The ACL's subset and overlap logic, and the bus's `covers`, against the reference.
fn subsets(outer: &str, inner: &str) {
    let _ = keys::covers(outer, inner);
    if !(reference::valid_filter(outer) && reference::valid_filter(inner))
        || inner.starts_with("$share/")
    {
        return;
    }
    if !inner.starts_with('$') && !outer.starts_with('$') {
        assert_eq!(
            keys::covers(outer, inner),
            reference::covers_plain(outer, inner),
            "bus covers({outer:?}, {inner:?})"
        );
    }
    if let Some(rules) = one_rule("read", outer) {
        assert_eq!(
            rules.can_subscribe(who(), inner),
            reference::covers(outer, inner),
            "`topic read {outer}` and subscribe {inner:?}"
        );
    }
    if outer.contains(char::is_whitespace) || outer.contains('%') {
        return;
    }
    let rules = AclRules::parse(&format!("topic read #\ntopic deny {outer}\n")).unwrap();
    assert_eq!(
        rules.can_subscribe(who(), inner),
        reference::covers("#", inner) && !reference::overlaps(inner, outer),
        "`topic read #`, `topic deny {outer}` and subscribe {inner:?}"
    );
}

fn typed_topic(t: &str) {
    let namespace = is_typed_namespace(t);
    if let Some(typed) = TypedTopic::parse(t) {
        assert!(
            namespace,
            "{t:?} parsed as typed but is not in a typed namespace"
        );
        for e in Encoding::ALL {
            let other = typed.in_encoding(e);
            let back = TypedTopic::parse(&other).expect("a typed topic in another encoding");
            assert_eq!(
                (back.encoding, back.device, back.fb, back.port),
                (e, typed.device, typed.fb, typed.port)
            );
        }
    }
}

/// The bus's key expressions: what is built from a valid line, topic or filter parses
/// back to it.
fn bus_keys(line: &str, topics: &[&str], filters: &[&str]) {
    let line_ok = keys::valid_line(line);
    if line_ok {
        let _ = keys::line_token(line);
        assert_eq!(keys::parse_line_token(&keys::line_token(line)), Some(line));
    }
    for f in filters {
        let bridgeable = keys::bridgeable_filter(f);
        let import = keys::import_key(f);
        assert_eq!(import.is_some(), bridgeable, "import_key({f:?})");
        if bridgeable {
            assert!(
                acl::valid_filter(f) || f.len() > 65_535,
                "bridgeable {f:?} is not a valid filter"
            );
            let query = keys::retained_query(f).expect("a retained query for a bridgeable filter");
            assert_eq!(
                keys::parse_retained_query(&query),
                Some(("*", (*f).to_owned())),
                "retained query {query:?} of {f:?}"
            );
        }
        if line_ok {
            let token = keys::interest_token(line, f);
            assert_eq!(
                keys::parse_interest(&token),
                Some((line, (*f).to_owned())),
                "interest token {token:?}"
            );
        }
    }
    for t in topics {
        let _ = keys::parse_data_key(t);
        let _ = keys::parse_retained_reply(t);
        let _ = keys::parse_interest(t);
        let _ = keys::parse_line_item("device", t);
        if !line_ok {
            continue;
        }
        if let Some(key) = keys::data_key(line, t) {
            assert!(
                acl::valid_topic(t) || t.len() > 65_535,
                "data_key of invalid topic {t:?}"
            );
            assert_eq!(
                keys::parse_data_key(&key),
                Some((line, *t)),
                "data key {key:?}"
            );
            let reply = keys::retained_reply(line, t).expect("a reply key for a data topic");
            assert_eq!(keys::parse_retained_reply(&reply), Some((line, *t)));
            // Every bridgeable filter that matches the topic imports it: the import key
            // is `fbbus/*/<filter>`, the data key `fbbus/<line>/<topic>`.
            for f in filters {
                if keys::bridgeable_filter(f) {
                    assert_eq!(
                        keys::filter_matches(f, t),
                        reference::matches(t, f),
                        "bus filter_matches({f:?}, {t:?})"
                    );
                }
            }
        }
    }
}

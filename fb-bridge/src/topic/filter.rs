//! The MQTT topic and topic-filter grammar: the one copy fbbus has.
//!
//! The ACL (`security::acl`), the bus ([`crate::bus`]) and the broker all decide what a
//! topic or a filter is, what a filter matches and whether one filter's topics are all
//! another's. They decide it here, so a subscription cannot be allowed by one reading of
//! the grammar and routed by another.
//!
//! The rules (MQTT 3.1.1 section 4.7, MQTT 5 section 4.7):
//!
//! - A **topic name** is non-empty, at most 65,535 bytes, with no `+`, `#` or NUL. Levels
//!   are separated by `/` and may be empty (`a//b`, `/x`).
//! - A **filter** is non-empty, at most 65,535 bytes, with no NUL; `+` and `#` fill a
//!   whole level, and `#` only the last one.
//! - `+` **matches** exactly one level, `#` the remaining levels including none (`a/#`
//!   matches `a`); other levels match only themselves.
//! - A filter whose first level is a wildcard does not match a topic that starts with
//!   `$` ([MQTT-4.7.2-1]): `#` never delivers `$SYS/...`.
//! - A **shared subscription** `$share/<group>/<filter>` matches with `<filter>`; the
//!   group is non-empty and has no `+` or `#`.
//!
//! Everything here works on `&str` with `split`, `strip_prefix` and `split_once` on ASCII
//! separators, so any UTF-8 topic is handled without slicing inside a character and no
//! input can panic.

/// Maximum length of an MQTT topic or filter in bytes.
pub const MAX_LEN: usize = 65_535;

/// The prefix of a shared subscription, `$share/<group>/<filter>`.
pub const SHARE_PREFIX: &str = "$share/";

/// Is `t` a valid topic name to publish to: non-empty, at most 65,535 bytes, no
/// wildcards and no NUL?
pub fn valid_topic(t: &str) -> bool {
    !t.is_empty() && t.len() <= MAX_LEN && !t.contains(['+', '#', '\0'])
}

/// Is `f` a valid subscription filter: non-empty, at most 65,535 bytes, no NUL, `+` and
/// `#` only as whole levels and `#` only as the last level?
///
/// A `$share/<group>/` prefix is not special here (its levels are plain ones); see
/// [`strip_share`] for checking a shared subscription.
pub fn valid_filter(f: &str) -> bool {
    if f.is_empty() || f.len() > MAX_LEN || f.contains('\0') {
        return false;
    }
    let mut levels = f.split('/').peekable();
    while let Some(level) = levels.next() {
        let is_last = levels.peek().is_none();
        let ok = match level {
            "#" => is_last,
            "+" => true,
            _ => !level.contains(['+', '#']),
        };
        if !ok {
            return false;
        }
    }
    true
}

/// Whether `filter` is a shared subscription (starts with `$share/`), well-formed or not.
pub fn is_shared(filter: &str) -> bool {
    filter.starts_with(SHARE_PREFIX)
}

/// Splits `$share/<group>/<filter>` into `(group, filter)`, judging neither: `None` for a
/// filter that does not start with `$share/`. Without a `/` after the group the filter is
/// empty (`$share/g` gives `("g", "")`), which no check accepts.
pub fn split_share(filter: &str) -> Option<(&str, &str)> {
    let rest = filter.strip_prefix(SHARE_PREFIX)?;
    Some(rest.split_once('/').unwrap_or((rest, "")))
}

/// Whether `group` can name a shared subscription's group: non-empty, no `+` or `#`.
pub fn valid_share_group(group: &str) -> bool {
    !group.is_empty() && !group.contains(['+', '#'])
}

/// The filter a subscription matches with, strictly: `filter` itself, or what follows a
/// well-formed `$share/<group>/`. `None` for a malformed shared subscription (empty group
/// or a wildcard in it). The result still needs [`valid_filter`]; `$share/g` gives an empty
/// filter, which fails it.
pub fn strip_share(filter: &str) -> Option<&str> {
    match split_share(filter) {
        None => Some(filter),
        Some((group, filter)) => valid_share_group(group).then_some(filter),
    }
}

/// The filter a subscription the broker already granted matches with: `filter` itself,
/// or the part after `$share/<group>/`, the group unchecked (`$share/g` gives `""`).
///
/// For code that only needs to know which topics a granted subscription reaches; checks
/// use [`strip_share`], which refuses a malformed group.
pub fn unshared(filter: &str) -> &str {
    split_share(filter).map_or(filter, |(_, filter)| filter)
}

/// Whether a topic name or filter starts with `$` (`$SYS/...`): such topics are the
/// server's, and a filter starting with a wildcard does not match them.
pub fn is_dollar(name: &str) -> bool {
    name.starts_with('$')
}

/// Whether the first level of `filter` is `+` or `#`.
fn starts_with_wildcard(filter: &str) -> bool {
    matches!(filter.split('/').next(), Some("+" | "#"))
}

/// Does plain `filter` (no `$share/` prefix) match topic name `topic`?
///
/// As MQTT's, except that a filter starting with a wildcard does not match the re-encoded
/// copies' namespaces ([`super::is_mirror`]), as it does not match `$` topics: the rule
/// fbbus's router routes by. Access rules do not use it ([`covers`]: a grant of `#`
/// still covers `fbdk/#`).
///
/// Does not check validity: callers check their filters once ([`valid_filter`]), not at
/// every message. [`filter_matches`] is the checked form for a subscription as a client
/// sent it.
pub fn matches(filter: &str, topic: &str) -> bool {
    if starts_with_wildcard(filter) && super::is_mirror(topic) {
        return false;
    }
    // A topic name is a filter that matches exactly itself.
    covers(filter, topic)
}

/// Does subscription `filter` (possibly `$share/<group>/...`) match `topic`? False for a
/// malformed shared subscription or an invalid filter.
pub fn filter_matches(filter: &str, topic: &str) -> bool {
    strip_share(filter).is_some_and(|f| valid_filter(f) && matches(f, topic))
}

/// Does every topic matched by filter `inner` also match filter `outer`?
///
/// Both should be valid plain filters; a topic name is a filter that matches only
/// itself, so `covers(filter, topic)` is "does `filter` match `topic`" ([`matches()`]).
/// `+` covers one level (but not `#`), `#` covers the remaining levels including none (`x/#`
/// covers `x`), and a filter starting with a wildcard never covers one starting with `$`.
pub fn covers(outer: &str, inner: &str) -> bool {
    if is_dollar(inner) && starts_with_wildcard(outer) {
        return false;
    }
    let (mut inner_levels, mut outer_levels) = (inner.split('/'), outer.split('/'));
    loop {
        match (inner_levels.next(), outer_levels.next()) {
            // `outer` matches everything below this point, parent level included.
            (_, Some("#")) => return true,
            (None, None) => return true,
            // One filter needs more levels than the other can provide.
            (None, Some(_)) | (Some(_), None) => return false,
            // Only `#` (handled above) covers `#`, only `+` or `#` covers `+`.
            (Some("#"), Some(_)) => return false,
            (Some("+"), Some(o)) if o != "+" => return false,
            (Some(i), Some(o)) if o != "+" && i != o => return false,
            _ => {}
        }
    }
}

/// Is there a topic that both filters match?
pub fn overlaps(a: &str, b: &str) -> bool {
    // A first-level wildcard never matches a `$` topic, and those are the only topics a
    // filter starting with `$` can match.
    if (is_dollar(a) && starts_with_wildcard(b)) || (is_dollar(b) && starts_with_wildcard(a)) {
        return false;
    }
    let (mut a_levels, mut b_levels) = (a.split('/'), b.split('/'));
    loop {
        match (a_levels.next(), b_levels.next()) {
            (Some("#"), _) | (_, Some("#")) | (None, None) => return true,
            (None, Some(_)) | (Some(_), None) => return false,
            (Some(a), Some(b)) if a != "+" && b != "+" && a != b => return false,
            _ => {}
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn filters_match_topics() {
        assert!(filter_matches("a/+/c", "a/b/c"));
        assert!(filter_matches("a/#", "a"));
        assert!(filter_matches("$share/g/a/#", "a/b"));
        assert!(!filter_matches("#", "$SYS/x"));
        assert!(filter_matches("$SYS/#", "$SYS/x"));
        assert!(!filter_matches("a/+", "a/b/c"));
        // Malformed shared subscriptions and invalid filters match nothing.
        assert!(!filter_matches("$share//a/#", "a/b"));
        assert!(!filter_matches("$share/g+/a/#", "a/b"));
        assert!(!filter_matches("$share/g", "g"));
        assert!(!filter_matches("a/#/b", "a/x/b"));
    }

    /// The bus's cases (formerly `bus::keys::filter_matches`).
    #[test]
    fn mqtt_matching() {
        assert!(matches("fb/#", "fb/a/b/c"));
        assert!(matches("fb/+/b/c", "fb/a/b/c"));
        assert!(!matches("fb/+/b", "fb/a/b/c"));
        assert!(matches("fb/a/b/c", "fb/a/b/c"));
        assert!(!matches("fb/a/b/d", "fb/a/b/c"));
        assert!(matches("fb/#", "fb"));
        assert!(matches("a//b", "a//b"));
        assert!(matches("a/+/b", "a//b"));
        assert!(!matches("+/x", "$SYS/x"));
        assert!(matches("$SYS/+", "$SYS/x"));
        // The re-encoded copies go to filters that name their namespace only.
        for copy in ["fbdk/plc/F/P", "dinasore/plc/F/P"] {
            assert!(!matches("#", copy) && !matches("+/plc/#", copy), "{copy}");
            assert!(!filter_matches("$share/g/#", copy), "{copy}");
            let namespace = copy.split('/').next().unwrap();
            assert!(matches(&format!("{namespace}/#"), copy), "{copy}");
            assert!(covers("#", copy), "access rules are not routing");
        }
        assert!(matches("#", "fb/plc/F/P") && matches("#", "fbdkx/a"));
    }

    #[test]
    fn filter_and_topic_validity() {
        for f in [
            "#", "+", "a", "a/b", "a/+", "a/#", "+/+/#", "/", "a//b", "$SYS/#", "a/%c",
        ] {
            assert!(valid_filter(f), "{f}");
        }
        for f in ["", "a/#/b", "a#", "#/a", "a/b+", "++", "a/\0"] {
            assert!(!valid_filter(f), "{f:?}");
        }
        for t in ["a", "a/b", "/", "$SYS/x", "a b/c"] {
            assert!(valid_topic(t), "{t}");
        }
        for t in ["", "a/+", "#", "a/#", "a\0b"] {
            assert!(!valid_topic(t), "{t:?}");
        }
        assert!(!valid_topic(&"a".repeat(65_536)));
        assert!(valid_topic(&"a".repeat(65_535)));
        assert!(!valid_filter(&"a".repeat(65_536)));
        assert!(valid_filter(&"a".repeat(65_535)));
    }

    #[test]
    fn shared_subscriptions_split() {
        assert_eq!(split_share("a/b"), None);
        assert_eq!(split_share("$share"), None);
        assert_eq!(split_share("$share/g/a/#"), Some(("g", "a/#")));
        assert_eq!(split_share("$share/g"), Some(("g", "")));
        assert_eq!(split_share("$share/g/"), Some(("g", "")));
        assert_eq!(split_share("$share//a"), Some(("", "a")));
        assert_eq!(split_share("$share/"), Some(("", "")));
        assert!(is_shared("$share/g/a") && is_shared("$share/") && !is_shared("$share"));

        assert_eq!(strip_share("jobs/#"), Some("jobs/#"));
        assert_eq!(strip_share("$SYS/#"), Some("$SYS/#"));
        assert_eq!(strip_share("$share/workers/jobs/#"), Some("jobs/#"));
        assert_eq!(strip_share("$share/workers/$SYS/#"), Some("$SYS/#"));
        assert_eq!(strip_share("$share/workers"), Some(""));
        assert_eq!(strip_share("$share/w/"), Some(""));
        assert_eq!(strip_share("$share//jobs/#"), None);
        assert_eq!(strip_share("$share/w+/jobs/#"), None);
        assert_eq!(strip_share("$share/w#/jobs/#"), None);
        assert_eq!(strip_share("$share/"), None);

        // Granted subscriptions: the group is not judged again.
        assert_eq!(unshared("fb/#"), "fb/#");
        assert_eq!(unshared("$share/g/fbdk/+/C/P"), "fbdk/+/C/P");
        assert_eq!(unshared("$share//fb/#"), "fb/#");
        assert_eq!(unshared("$share/g"), "");
        assert_eq!(unshared("$share"), "$share");
    }

    #[test]
    fn multi_byte_topics_and_nul() {
        let topic = "fb/Förderband/日本/🌍";
        assert!(valid_topic(topic));
        assert!(valid_filter("fb/Förderband/+/🌍"));
        assert!(matches("fb/Förderband/+/🌍", topic));
        assert!(matches("fb/+/日本/#", topic));
        assert!(!matches("fb/Förderband/日/🌍", topic));
        assert!(filter_matches("$share/gruppe-ü/fb/#", topic));
        assert_eq!(split_share("$share/ü/é"), Some(("ü", "é")));
        assert_eq!(split_share("$share/üé"), Some(("üé", "")));
        assert!(covers("fb/#", "fb/ö/+"));
        assert!(overlaps("fb/ö/+", "fb/+/ü"));
        assert!(!valid_topic("fb/\0/x") && !valid_filter("fb/\0/#"));
        assert!(!filter_matches("fb/\0/#", "fb/\0/x"));
    }

    /// `covers(outer, inner)`: every topic `inner` matches, `outer` matches.
    #[test]
    fn coverage() {
        let yes = [
            ("a/b", "a/b"),
            ("a/b", "a/+"),
            ("a/b", "a/#"),
            ("a", "a/#"),
            ("a/+", "a/#"),
            ("a/+", "a/+"),
            ("a/#", "a/#"),
            ("a/b/#", "a/#"),
            ("a/b/#", "a/+/#"),
            ("+/b", "+/+"),
            ("+/b", "#"),
            ("a/b/c", "#"),
            ("#", "#"),
            ("+", "#"),
            ("$SYS/x", "$SYS/#"),
            ("$SYS/x", "$SYS/+"),
            ("$SYS", "$SYS/#"),
            ("a//b", "a/+/b"),
            ("/x", "+/x"),
        ];
        for (inner, outer) in yes {
            assert!(covers(outer, inner), "{outer} should cover {inner}");
        }
        let no = [
            ("a/#", "a/+"),
            ("a/+", "a/b"),
            ("#", "a/#"),
            ("a/#", "a/b/#"),
            ("a", "a/+"),
            ("a/b", "a"),
            ("a/b", "b/#"),
            ("+/+", "+/b"),
            ("a/+/c", "a/+"),
            ("$SYS/x", "#"),
            ("$SYS/x", "+/x"),
            ("$SYS/x", "+/+"),
            ("#", "$SYS/#"),
            ("+/x", "$SYS/x"),
            ("a/#", "a"),
            ("+", "a"),
        ];
        for (inner, outer) in no {
            assert!(!covers(outer, inner), "{outer} should not cover {inner}");
        }
    }

    /// The bus's cases (formerly `bus::keys::covers`).
    #[test]
    fn filter_coverage() {
        assert!(covers("fb/#", "fb/a/+/c"));
        assert!(covers("fb/#", "fb/#"));
        assert!(covers("fb/+/b/c", "fb/x/b/c"));
        assert!(!covers("fb/+/b/c", "fb/#"));
        assert!(!covers("fb/a/#", "fb/+/b/c"));
        assert!(covers("#", "fb/#"));
        assert!(covers("+/#", "fb/a"));
        assert!(!covers("fb/a", "fb/+"));
        // [MQTT-4.7.2-1]: `#` does not reach `$` topics, so it does not cover them.
        assert!(!covers("#", "$SYS/#"));
    }

    #[test]
    fn overlap() {
        let yes = [
            ("a/b", "a/b"),
            ("a/+", "a/b"),
            ("a/#", "a"),
            ("a", "a/#"),
            ("#", "a/b/c"),
            ("+/b", "a/+"),
            ("a/+/c", "a/b/+"),
            ("a/#", "+/x/y"),
            ("+", "#"),
            ("$SYS/#", "$SYS/x"),
            ("$SYS/+", "$SYS/#"),
        ];
        for (a, b) in yes {
            assert!(overlaps(a, b), "{a} should overlap {b}");
            assert!(overlaps(b, a), "{b} should overlap {a}");
        }
        let no = [
            ("a/b", "a/c"),
            ("a/+", "a"),
            ("a/+", "a/b/c"),
            ("+/+", "a/b/c"),
            ("a/b/#", "a/c/#"),
            ("#", "$SYS/x"),
            ("+/x", "$SYS/x"),
            ("#", "$SYS/#"),
            ("$SYS/#", "$other/#"),
        ];
        for (a, b) in no {
            assert!(!overlaps(a, b), "{a} should not overlap {b}");
            assert!(!overlaps(b, a), "{b} should not overlap {a}");
        }
    }
}

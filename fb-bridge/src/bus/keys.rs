//! zenoh key expressions of the bus.
//!
//! | key expression | what |
//! |---|---|
//! | `fbbus/<line>/fb/<device>/<fb>/<port>` | a typed message of `<device>` on `<line>`, canonical JSON |
//! | `fbbus/@/line/<line>` | liveliness token: the line's bridge is up |
//! | `fbbus/@/record/<line>/<device>` | the device's registry record, its state included (put on change; queryable) |
//! | `fbbus/@/interest/<line>/<filter>` | liveliness token: a client of `<line>` subscribed to `<filter>` (escaped) |
//! | `fbbus/@/retained/<line>/...` | queryable: retained messages of `<line>` matching a filter |
//! | `fbbus/@/loss/<line>/<origin>` | `<origin>`'s messages `<line>` counted as lost ([`super::LossReport`]) |
//!
//! The `@` chunk is verbatim in zenoh: `fbbus/*/fb/**` never matches the control plane.
//! Only the `fb/` namespace crosses lines: `dinasore/` and `fbdk/` are re-encoded from it
//! by the receiving broker, which knows the device's declared types.
//!
//! What an MQTT filter matches and covers is not decided here but by the one grammar in
//! [`crate::topic::filter`]; this module only maps filters and topics to keys and back.

/// Prefix of every key of the bus.
pub const ROOT: &str = "fbbus";
pub const CONTROL: &str = "fbbus/@";

/// A line name is one zenoh chunk without special characters.
pub fn valid_line(line: &str) -> bool {
    !line.is_empty()
        && line.len() <= 64
        && line
            .chars()
            .all(|c| c.is_ascii_alphanumeric() || matches!(c, '-' | '_' | '.'))
}

/// A topic level can be a zenoh chunk as it is. (No NUL either: MQTT forbids it in topics
/// and filters, and a `[bridge]` filter with one validated; found by broker/fuzz
/// `topic_match`.)
fn plain_level(level: &str) -> bool {
    !level.is_empty() && !level.contains(['*', '$', '?', '#', '+', '@', '\0'])
}

/// `fbbus/<line>/<topic>`, or None for a topic that cannot cross (outside `fb/`, or with
/// characters zenoh reserves).
pub fn data_key(line: &str, topic: &str) -> Option<String> {
    if !topic.starts_with("fb/") || !topic.split('/').all(plain_level) {
        return None;
    }
    Some(format!("{ROOT}/{line}/{topic}"))
}

/// Splits a data key into (line, topic).
pub fn parse_data_key(key: &str) -> Option<(&str, &str)> {
    let rest = key.strip_prefix("fbbus/")?;
    let (line, topic) = rest.split_once('/')?;
    (topic.starts_with("fb/") && !line.starts_with('@')).then_some((line, topic))
}

/// Whether `filter` is a valid MQTT filter inside `fb/#` the bus can carry.
pub fn bridgeable_filter(filter: &str) -> bool {
    let mut levels = filter.split('/').peekable();
    if levels.next() != Some("fb") {
        return false;
    }
    while let Some(level) = levels.next() {
        let ok = match level {
            "+" => true,
            "#" => levels.peek().is_none(),
            l => plain_level(l),
        };
        if !ok {
            return false;
        }
    }
    true
}

/// The key expression matching `filter`'s messages on every line: `fbbus/*/<filter>` with
/// `+` as `*` and `#` as `**`. None if the filter cannot cross.
pub fn import_key(filter: &str) -> Option<String> {
    if !bridgeable_filter(filter) {
        return None;
    }
    let levels: Vec<&str> = filter
        .split('/')
        .map(|l| match l {
            "+" => "*",
            "#" => "**",
            l => l,
        })
        .collect();
    Some(format!("{ROOT}/*/{}", levels.join("/")))
}

/// The key expression of every line's retained messages matching `filter`.
pub fn retained_query(filter: &str) -> Option<String> {
    retained_query_of(None, filter)
}

/// The key expression of `line`'s retained messages matching `filter` (None: every
/// line's).
pub fn retained_query_of(line: Option<&str>, filter: &str) -> Option<String> {
    if line.is_some_and(|l| !valid_line(l)) {
        return None;
    }
    let k = import_key(filter)?;
    // `fbbus/*/<filter>`: the line's chunk after the root.
    let levels = k.strip_prefix("fbbus/*/")?;
    Some(format!(
        "{CONTROL}/retained/{}/{levels}",
        line.unwrap_or("*")
    ))
}

/// The (line, topic filter) of a retained-message query, from its key expression.
pub fn parse_retained_query(key: &str) -> Option<(&str, String)> {
    let rest = key.strip_prefix("fbbus/@/retained/")?;
    let (line, filter) = rest.split_once('/')?;
    let filter: Vec<&str> = filter
        .split('/')
        .map(|l| match l {
            "*" => "+",
            "**" => "#",
            l => l,
        })
        .collect();
    Some((line, filter.join("/")))
}

/// The key a retained message of `line` is returned under (replies must match the query).
pub fn retained_reply(line: &str, topic: &str) -> Option<String> {
    data_key(line, topic).map(|k| format!("{CONTROL}/retained/{}", &k["fbbus/".len()..]))
}

/// (line, topic) of a retained-message reply.
pub fn parse_retained_reply(key: &str) -> Option<(&str, &str)> {
    let rest = key.strip_prefix("fbbus/@/retained/")?;
    let (line, topic) = rest.split_once('/')?;
    topic.starts_with("fb/").then_some((line, topic))
}

/// Where a line's bridge answers retained-message queries.
pub fn retained_queryable(line: &str) -> String {
    format!("{CONTROL}/retained/{line}/fb/**")
}

pub fn line_token(line: &str) -> String {
    format!("{CONTROL}/line/{line}")
}

pub fn record_key(line: &str, device: &str) -> String {
    format!("{CONTROL}/record/{line}/{device}")
}

/// Where `receiver` reports the messages of `origin` it counted as lost.
pub fn loss_key(receiver: &str, origin: &str) -> String {
    format!("{CONTROL}/loss/{receiver}/{origin}")
}

/// The liveliness token announcing that a client of `line` subscribed to `filter`.
pub fn interest_token(line: &str, filter: &str) -> String {
    let escaped = filter
        .replace('%', "%25")
        .replace('+', "%2B")
        .replace('#', "%23");
    format!("{CONTROL}/interest/{line}/{escaped}")
}

/// (line, filter) of an interest token.
pub fn parse_interest(key: &str) -> Option<(&str, String)> {
    let rest = key.strip_prefix("fbbus/@/interest/")?;
    let (line, escaped) = rest.split_once('/')?;
    let filter = escaped
        .replace("%2B", "+")
        .replace("%23", "#")
        .replace("%25", "%");
    Some((line, filter))
}

/// The (line, last chunk) of `fbbus/@/<kind>/<line>/<id>` keys.
pub fn parse_line_item<'a>(kind: &str, key: &'a str) -> Option<(&'a str, &'a str)> {
    let rest = key.strip_prefix(CONTROL)?.strip_prefix('/')?;
    let rest = rest.strip_prefix(kind)?.strip_prefix('/')?;
    rest.split_once('/')
}

/// The line of a line token.
pub fn parse_line_token(key: &str) -> Option<&str> {
    key.strip_prefix("fbbus/@/line/")
}

/// The MQTT grammar's matching and coverage, under the names the `topic_match` fuzz
/// target (`broker/fuzz`) calls them by; the bus itself uses [`crate::topic::filter`].
pub use crate::topic::filter::{covers, matches as filter_matches};

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn typed_topics_and_filters_map_to_key_expressions() {
        assert_eq!(
            data_key("line-a", "fb/conv/CONV/MOVED").as_deref(),
            Some("fbbus/line-a/fb/conv/CONV/MOVED")
        );
        assert_eq!(data_key("a", "plant/x"), None);
        assert_eq!(data_key("a", "fb/x*/F/P"), None);
        assert_eq!(
            parse_data_key("fbbus/line-a/fb/conv/CONV/MOVED"),
            Some(("line-a", "fb/conv/CONV/MOVED"))
        );
        assert_eq!(parse_data_key("fbbus/@/line/a"), None);
        assert_eq!(
            import_key("fb/conv/#").as_deref(),
            Some("fbbus/*/fb/conv/**")
        );
        assert_eq!(
            import_key("fb/+/CONV/MOVED").as_deref(),
            Some("fbbus/*/fb/*/CONV/MOVED")
        );
        assert_eq!(import_key("#"), None);
        assert_eq!(import_key("fb/#/x"), None);
        assert_eq!(
            retained_query("fb/conv/+/P").as_deref(),
            Some("fbbus/@/retained/*/fb/conv/*/P")
        );
        // One line's only (a line that came back, issue 32); a line name that is not one
        // chunk asks nothing.
        assert_eq!(
            retained_query_of(Some("line-b"), "fb/conv/+/P").as_deref(),
            Some("fbbus/@/retained/line-b/fb/conv/*/P")
        );
        assert_eq!(retained_query_of(Some("a/b"), "fb/#"), None);
        assert_eq!(retained_query_of(Some("**"), "fb/#"), None);
        let reply = retained_reply("line-a", "fb/conv/CONV/ID").unwrap();
        assert_eq!(reply, "fbbus/@/retained/line-a/fb/conv/CONV/ID");
        assert_eq!(
            parse_retained_reply(&reply),
            Some(("line-a", "fb/conv/CONV/ID"))
        );
        assert_eq!(
            parse_retained_query("fbbus/@/retained/line-a/fb/conv/*/**"),
            Some(("line-a", "fb/conv/+/#".to_string()))
        );
    }

    #[test]
    fn interest_tokens_escape_mqtt_wildcards() {
        let key = interest_token("line-b", "fb/+/CONV/#");
        assert_eq!(key, "fbbus/@/interest/line-b/fb/%2B/CONV/%23");
        assert_eq!(parse_interest(&key), Some(("line-b", "fb/+/CONV/#".into())));
        assert_eq!(
            parse_line_item("record", "fbbus/@/record/line-a/conv-1"),
            Some(("line-a", "conv-1"))
        );
        assert_eq!(parse_line_token("fbbus/@/line/line-a"), Some("line-a"));
    }

    /// Regression (broker/fuzz/regressions/topic_match): a NUL is not allowed in an MQTT
    /// topic or filter, so it cannot be in a bridged one.
    #[test]
    fn filters_and_topics_with_nul_do_not_cross() {
        assert!(bridgeable_filter("fb/plc/+/#"));
        assert!(!bridgeable_filter("fb/p\0c-/+/+"));
        assert_eq!(import_key("fb/p\0c/#"), None);
        assert_eq!(data_key("line-1", "fb/p\0c/CONV/SPEED"), None);
        assert!(data_key("line-1", "fb/plc/CONV/SPEED").is_some());
    }
}

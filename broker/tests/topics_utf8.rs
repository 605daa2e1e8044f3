//! Topics are any UTF-8 (issue 14). One publication on `é/x` with a `#` subscriber present
//! used to kill the router thread (`topic[..1]` sliced inside the multi-byte `é`); from
//! then on every new connection was refused ("Connection Refused: broker unavailable")
//! while `/readyz` still said 200.
//!
//! These tests run the real broker on its embedded default configuration (only the two
//! ports moved to free loopback ones) with real clients: rumqttc (MQTT 3.1.1 and 5) and
//! Debian's `mosquitto_pub`/`mosquitto_sub`. A generated set of topics puts 2-, 3- and
//! 4-byte characters and combining marks at every level and position; every publication
//! must reach the `#` subscribers exactly once with its topic byte for byte, and reach the
//! `+`-filter subscribers whose filters match it; afterwards the broker must still accept
//! a new connection and route, and `/readyz` must still answer 200.

mod common;

use std::collections::HashMap;
use std::io::{BufRead, BufReader};
use std::net::SocketAddr;
use std::process::{Child, Command, Stdio};
use std::sync::mpsc;
use std::time::{Duration, Instant};

use common::clients::{p5, V4, V5, WAIT};
use common::{free_port, http_get, Broker};

/// Multi-byte text placed at every position of the generated topics: 2-byte (`é`, `Ü`,
/// `ö` inside a word), 3-byte (`€`, CJK), 4-byte (emoji), combining marks (a 2-byte one
/// after a base letter and one *starting* a level, a 3-byte one), and widths mixed.
const WORDS: [&str; 10] = [
    "é",
    "Ü",
    "Förderband",
    "€",
    "日本",
    "😀",
    "e\u{301}",
    "\u{301}x",
    "1\u{20e3}",
    "ä€😀",
];

/// Levels of the deep topic.
const DEEP_LEVELS: usize = 40;

/// How long to wait for the last deliveries once everything is published.
const DELIVERY_WAIT: Duration = Duration::from_secs(10);

/// The broker on `broker::DEFAULT_CONFIG`, the configuration `fbbus serve` runs
/// without `--config`, with its MQTT and admin ports moved to free loopback ports (so
/// tests can run side by side). Its registry file then lands next to the config, in the
/// test's own directory.
fn start_default_broker() -> Broker {
    let default = broker::DEFAULT_CONFIG;
    let mqtt: SocketAddr = format!("127.0.0.1:{}", free_port()).parse().unwrap();
    let admin: SocketAddr = format!("127.0.0.1:{}", free_port()).parse().unwrap();
    let text = default
        .replace("127.0.0.1:1883", &mqtt.to_string())
        .replace("127.0.0.1:9883", &admin.to_string());
    assert!(
        text.contains(&mqtt.to_string()) && text.contains(&admin.to_string()),
        "the embedded default config no longer binds 127.0.0.1:1883 and :9883; update this test:\n{default}"
    );
    let dir = tempfile::tempdir().unwrap();
    let config = dir.path().join("fbbus.toml");
    std::fs::write(&config, text).unwrap();
    Broker::spawn(dir, config, mqtt, admin)
}

/// Every topic shape for one word: first character of the first level, last character of
/// the last level, alone in a level, in the middle of a level, with empty levels around
/// it, one to several levels, and a deep topic.
fn shapes(w: &str) -> Vec<String> {
    let deep: Vec<String> = (0..DEEP_LEVELS)
        .map(|i| {
            if i % 2 == 0 {
                w.to_owned()
            } else {
                i.to_string()
            }
        })
        .collect();
    vec![
        w.to_owned(),
        format!("{w}/x"),
        format!("{w}tail/x"),
        format!("x/{w}"),
        format!("x/head{w}"),
        format!("a/{w}/b"),
        format!("a/mid{w}dle/b"),
        format!("/{w}"),
        format!("{w}/"),
        format!("//{w}//"),
        format!("{w}//x"),
        format!("{w}/{w}"),
        format!("a/{w}/{w}/{w}/z"),
        deep.join("/"),
    ]
}

/// The generated topics, each once, in a fixed order.
fn topics() -> Vec<String> {
    let mut all: Vec<String> = Vec::new();
    for w in WORDS {
        for t in shapes(w) {
            if !all.contains(&t) {
                all.push(t);
            }
        }
    }
    all
}

/// Whether `filter` matches `topic`, written from MQTT 3.1.1 section 4.7 (independently
/// of the broker's own matcher, which is what is under test): `+` is one whole level,
/// `#` the rest including the parent level itself, topics starting with `$` are not
/// matched by a leading wildcard.
fn mqtt_matches(filter: &str, topic: &str) -> bool {
    if topic.starts_with('$') && (filter.starts_with('+') || filter.starts_with('#')) {
        return false;
    }
    let mut topic_levels = topic.split('/');
    for f in filter.split('/') {
        if f == "#" {
            return true;
        }
        match topic_levels.next() {
            Some(t) if f == "+" || f == t => {}
            _ => return false,
        }
    }
    topic_levels.next().is_none()
}

/// The topic with every level that holds a non-ASCII character replaced by `+`: the
/// wildcard must match a multi-byte level.
fn wildcard_for_multibyte(topic: &str) -> String {
    let levels: Vec<&str> = topic
        .split('/')
        .map(|l| if l.is_ascii() { l } else { "+" })
        .collect();
    levels.join("/")
}

/// The topic with every ASCII level (empty ones included) replaced by `+`: the multi-byte
/// levels must match literally next to wildcards.
fn wildcard_for_ascii(topic: &str) -> String {
    let levels: Vec<&str> = topic
        .split('/')
        .map(|l| if l.is_ascii() { "+" } else { l })
        .collect();
    levels.join("/")
}

/// Distinct filters, in first-seen order.
fn distinct(filters: impl Iterator<Item = String>) -> Vec<String> {
    let mut out: Vec<String> = Vec::new();
    for f in filters {
        if !out.contains(&f) {
            out.push(f);
        }
    }
    out
}

/// One publication: a unique payload says which.
#[derive(Debug, Clone)]
struct Publication {
    topic: String,
    payload: String,
    qos: u8,
    by: &'static str,
}

/// What a subscriber received: (topic bytes, payload).
type Received = Vec<(Vec<u8>, String)>;

/// `mosquitto_sub` with its output lines on a channel (`-v`: "topic payload"; payloads
/// here have no spaces, so the last space splits them). Killed when dropped.
struct MosquittoSub {
    child: Child,
    lines: mpsc::Receiver<String>,
}

impl MosquittoSub {
    fn start(port: u16, filter: &str) -> MosquittoSub {
        let mut child = Command::new("mosquitto_sub")
            .args(["-h", "127.0.0.1", "-p", &port.to_string(), "-q", "1", "-v"])
            .args(["-t", filter])
            .stdout(Stdio::piped())
            .stderr(Stdio::null())
            .spawn()
            .expect("mosquitto_sub starts");
        let stdout = child.stdout.take().unwrap();
        let (tx, lines) = mpsc::channel();
        std::thread::spawn(move || {
            for line in BufReader::new(stdout).lines() {
                let Ok(line) = line else { return };
                if tx.send(line).is_err() {
                    return;
                }
            }
        });
        MosquittoSub { child, lines }
    }

    /// Waits until the subscription is in place: publishes `topic` (QoS 1) with `probe`
    /// until mosquitto_sub prints it. Lines seen meanwhile are returned.
    async fn wait_subscribed(&mut self, publisher: &V4, topic: &str) -> Vec<String> {
        let deadline = Instant::now() + Duration::from_secs(10);
        let mut early = Vec::new();
        loop {
            publisher
                .client
                .publish(topic, rumqttc::QoS::AtLeastOnce, false, "probe")
                .await
                .unwrap();
            tokio::time::sleep(Duration::from_millis(100)).await;
            while let Ok(line) = self.lines.try_recv() {
                if line == format!("{topic} probe") {
                    return early;
                }
                early.push(line);
            }
            assert!(
                Instant::now() < deadline,
                "mosquitto_sub never received the probe on {topic}"
            );
        }
    }

    /// Lines until `n` matched `keep` or `within` passed.
    fn collect(&self, n: usize, within: Duration, keep: impl Fn(&str) -> bool) -> Vec<String> {
        let deadline = Instant::now() + within;
        let mut out = Vec::new();
        while out.len() < n {
            let left = deadline.saturating_duration_since(Instant::now());
            match self.lines.recv_timeout(left) {
                Ok(line) if keep(&line) => out.push(line),
                Ok(_) => {}
                Err(_) => break,
            }
        }
        out
    }
}

impl Drop for MosquittoSub {
    fn drop(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

/// `mosquitto_pub` one message; Err carries its stderr (e.g. "Connection Refused: broker
/// unavailable").
fn mosquitto_pub(port: u16, topic: &str, payload: &str, qos: u8) -> Result<(), String> {
    let (ok, _, err) = common::run(
        Command::new("mosquitto_pub")
            .args(["-h", "127.0.0.1", "-p", &port.to_string()])
            .args(["-q", &qos.to_string(), "-t", topic, "-m", payload]),
        Duration::from_secs(10),
    );
    if ok {
        Ok(())
    } else {
        Err(format!("mosquitto_pub -t {topic:?} -m {payload}: {err}"))
    }
}

fn assert_ready(broker: &Broker, when: &str) {
    let code = http_get(broker.admin, "/readyz").map(|r| r.0);
    assert_eq!(
        code,
        Some(200),
        "/readyz {when}; broker log:\n{}",
        broker.log_text()
    );
}

/// Collects publications from a rumqttc 3.1.1 subscriber until `n` arrived or nothing
/// came for [`DELIVERY_WAIT`].
async fn drain_v4(sub: &mut V4, n: usize) -> Received {
    let mut got = Vec::new();
    while got.len() < n {
        let Some(p) = sub.next_publish(DELIVERY_WAIT).await else {
            break;
        };
        got.push((
            p.topic.as_bytes().to_vec(),
            String::from_utf8_lossy(&p.payload).into_owned(),
        ));
    }
    got
}

async fn drain_v5(sub: &mut V5, n: usize) -> Received {
    let mut got = Vec::new();
    while got.len() < n {
        let Some(p) = sub.next_publish(DELIVERY_WAIT).await else {
            break;
        };
        got.push((
            p.topic.to_vec(),
            String::from_utf8_lossy(&p.payload).into_owned(),
        ));
    }
    got
}

/// `#` subscriber `who` received every publication exactly once, topic byte for byte,
/// and nothing else.
fn assert_exactly_once(who: &str, sent: &[Publication], got: &Received, log: &str) {
    let by_payload: HashMap<&str, &Publication> =
        sent.iter().map(|p| (p.payload.as_str(), p)).collect();
    let mut seen: HashMap<&str, usize> = HashMap::new();
    for (topic, payload) in got {
        let p = by_payload
            .get(payload.as_str())
            .unwrap_or_else(|| panic!("{who} received an unknown publication {payload:?}"));
        assert_eq!(
            topic,
            p.topic.as_bytes(),
            "{who}: {payload} arrived on {:?}, sent on {:?}",
            String::from_utf8_lossy(topic),
            p.topic
        );
        *seen.entry(payload.as_str()).or_default() += 1;
    }
    let missing: Vec<&Publication> = sent
        .iter()
        .filter(|p| !seen.contains_key(p.payload.as_str()))
        .collect();
    assert!(
        missing.is_empty(),
        "{who} missed {} of {} publications, first ones: {:?}\nbroker log:\n{log}",
        missing.len(),
        sent.len(),
        &missing[..missing.len().min(5)]
    );
    let twice: Vec<_> = seen.iter().filter(|(_, n)| **n > 1).collect();
    assert!(twice.is_empty(), "{who} received duplicates: {twice:?}");
}

fn matching_filters(filters: &[String], topic: &str) -> usize {
    filters.iter().filter(|f| mqtt_matches(f, topic)).count()
}

/// The most copies a subscriber to `filters` may receive of `sent`: one per matching
/// filter of each publication.
fn most_copies(filters: &[String], sent: &[Publication]) -> usize {
    sent.iter()
        .map(|p| matching_filters(filters, &p.topic))
        .sum()
}

/// A subscriber to `filters` received each matching publication, topic byte for byte, at
/// least once and at most once per matching filter (MQTT lets a broker send one copy per
/// matching subscription), and none that matches no filter.
fn assert_matching(who: &str, filters: &[String], sent: &[Publication], got: &Received) {
    let matching = |topic: &str| matching_filters(filters, topic);
    let mut seen: HashMap<&str, usize> = HashMap::new();
    for (topic, payload) in got {
        let p = sent
            .iter()
            .find(|p| &p.payload == payload)
            .unwrap_or_else(|| panic!("{who} received an unknown publication {payload:?}"));
        assert_eq!(topic, p.topic.as_bytes(), "{who}: {payload} topic changed");
        assert!(
            matching(&p.topic) > 0,
            "{who} received {:?}, which matches none of its filters",
            p.topic
        );
        *seen.entry(p.payload.as_str()).or_default() += 1;
    }
    for p in sent {
        let n = matching(&p.topic);
        let copies = seen.get(p.payload.as_str()).copied().unwrap_or(0);
        assert!(
            (n == 0 && copies == 0) || (1..=n).contains(&copies),
            "{who}: {:?} ({} QoS {}) matches {n} filter(s), received {copies} times",
            p.topic,
            p.by,
            p.qos
        );
    }
}

/// After everything: a brand-new connection is accepted and a publication is routed, on
/// an ASCII topic and on one starting with a multi-byte character.
async fn assert_still_routes(broker: &Broker) {
    let mut sub = V4::connect(broker.port(), "after-sub", None)
        .await
        .unwrap_or_else(|e| {
            panic!(
                "a new connection after the campaign was refused: {e}\n{}",
                broker.log_text()
            )
        });
    sub.subscribe("after/#").await;
    sub.subscribe("après/#").await;
    let publisher = V4::connect(broker.port(), "after-pub", None)
        .await
        .expect("a new publisher connects");
    for topic in ["after/x", "après/x"] {
        publisher
            .client
            .publish(topic, rumqttc::QoS::AtLeastOnce, false, "alive")
            .await
            .unwrap();
        let p = sub
            .next_publish(WAIT)
            .await
            .unwrap_or_else(|| panic!("{topic} was not routed afterwards"));
        assert_eq!((p.topic.as_str(), &p.payload[..]), (topic, &b"alive"[..]));
    }
    assert_ready(broker, "after the campaign");
}

/// The reproduction of issue 14, command for command.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn issue_14_reproduction_delivers_e_acute_and_keeps_serving() {
    if !common::require("mosquitto_sub") || !common::require("mosquitto_pub") {
        return;
    }
    let broker = start_default_broker();
    let port = broker.port();
    let mut all = MosquittoSub::start(port, "#");
    let prober = V4::connect(port, "prober", None).await.unwrap();
    all.wait_subscribed(&prober, "ready/probe").await;
    drop(prober);

    let first = mosquitto_pub(port, "é/x", "1", 0);
    let second = mosquitto_pub(port, "after/x", "alive", 0);
    let got = all.collect(2, DELIVERY_WAIT, |l| !l.starts_with("ready/"));
    assert_eq!(
        (first, second, got),
        (
            Ok(()),
            Ok(()),
            vec!["é/x 1".to_owned(), "after/x alive".to_owned()]
        ),
        "broker log:\n{}",
        broker.log_text()
    );
    assert_ready(&broker, "after the reproduction");
}

/// The generated topics, published at QoS 0 and 1 by rumqttc (3.1.1 and 5) and by
/// `mosquitto_pub`, reach `#` subscribers (rumqttc 3.1.1 and 5, `mosquitto_sub`) exactly
/// as sent and `+`-filter subscribers whose filters match.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn generated_multibyte_topics_reach_every_matching_subscriber_exactly_as_sent() {
    let mosquitto = common::require("mosquitto_sub") && common::require("mosquitto_pub");
    let broker = start_default_broker();
    let port = broker.port();
    let topics = topics();
    assert!(topics.len() > 100, "{} topics", topics.len());
    assert!(
        topics.iter().any(|t| t.split('/').count() == DEEP_LEVELS),
        "a deep topic"
    );

    let mut hash4 = V4::connect(port, "hash-v311", None).await.unwrap();
    hash4.subscribe("#").await;
    let mut hash5 = V5::connect(port, "hash-v5", None).await.unwrap();
    assert!(matches!(
        hash5.subscribe("#").await[..],
        [p5::SubscribeReasonCode::Success(_)]
    ));
    let publisher4 = V4::connect(port, "pub-v311", None).await.unwrap();
    let mut mosquitto_all = if mosquitto {
        let mut sub = MosquittoSub::start(port, "#");
        let early = sub.wait_subscribed(&publisher4, "ready/probe").await;
        assert!(early.iter().all(|l| l.starts_with("ready/")), "{early:?}");
        Some(sub)
    } else {
        None
    };
    // The probes reached the rumqttc `#` subscribers too: skip them.
    while hash4
        .next_publish(Duration::from_millis(300))
        .await
        .is_some()
    {}
    while hash5
        .next_publish(Duration::from_millis(300))
        .await
        .is_some()
    {}
    // The `+` subscribers subscribe after the probes, which some of their filters match
    // (`+/+`).
    let multibyte_wild = distinct(topics.iter().map(|t| wildcard_for_multibyte(t)));
    let ascii_wild = distinct(topics.iter().map(|t| wildcard_for_ascii(t)));
    let mut plus_multibyte = V4::connect(port, "plus-multibyte", None).await.unwrap();
    for f in &multibyte_wild {
        let codes = plus_multibyte.subscribe(f).await;
        assert!(
            matches!(codes[..], [rumqttc::SubscribeReasonCode::Success(_)]),
            "{f:?}: {codes:?}"
        );
    }
    let mut plus_ascii = V5::connect(port, "plus-ascii", None).await.unwrap();
    for f in &ascii_wild {
        let codes = plus_ascii.subscribe(f).await;
        assert!(
            matches!(codes[..], [p5::SubscribeReasonCode::Success(_)]),
            "{f:?}: {codes:?}"
        );
    }
    assert_ready(&broker, "before publishing");

    let mut sent: Vec<Publication> = Vec::new();
    let mut publication = |topic: &str, qos: u8, by: &'static str| {
        let p = Publication {
            topic: topic.to_owned(),
            payload: format!("m{}-{by}-q{qos}", sent.len()),
            qos,
            by,
        };
        sent.push(p.clone());
        p
    };

    let publisher5 = V5::connect(port, "pub-v5", None).await.unwrap();
    for topic in &topics {
        for qos in [0u8, 1] {
            let p = publication(topic, qos, "rumqttc-v311");
            let q = if qos == 0 {
                rumqttc::QoS::AtMostOnce
            } else {
                rumqttc::QoS::AtLeastOnce
            };
            publisher4
                .client
                .publish(&p.topic, q, false, p.payload.clone())
                .await
                .unwrap();
        }
        let p = publication(topic, 1, "rumqttc-v5");
        publisher5
            .client
            .publish(
                &p.topic,
                rumqttc::v5::mqttbytes::QoS::AtLeastOnce,
                false,
                p.payload.clone(),
            )
            .await
            .unwrap();
    }
    if mosquitto {
        let batch: Vec<Publication> = topics
            .iter()
            .flat_map(|t| [0u8, 1].map(|qos| (t, qos)))
            .map(|(t, qos)| publication(t, qos, "mosquitto_pub"))
            .collect();
        let failures = tokio::task::spawn_blocking(move || {
            batch
                .iter()
                .filter_map(|p| mosquitto_pub(port, &p.topic, &p.payload, p.qos).err())
                .collect::<Vec<_>>()
        })
        .await
        .unwrap();
        assert!(
            failures.is_empty(),
            "{} mosquitto_pub runs failed, first: {}\nbroker log:\n{}",
            failures.len(),
            failures[0],
            broker.log_text()
        );
    }

    let n = sent.len();
    let log = || broker.log_text();
    let got = drain_v4(&mut hash4, n).await;
    assert_exactly_once("rumqttc 3.1.1 `#`", &sent, &got, &log());
    let got = drain_v5(&mut hash5, n).await;
    assert_exactly_once("rumqttc 5 `#`", &sent, &got, &log());
    if let Some(sub) = mosquitto_all.as_mut() {
        let lines = sub.collect(n, DELIVERY_WAIT, |_| true);
        let got: Received = lines
            .iter()
            .map(|l| {
                let (topic, payload) = l.rsplit_once(' ').expect("-v prints topic payload");
                (topic.as_bytes().to_vec(), payload.to_owned())
            })
            .collect();
        assert_exactly_once("mosquitto_sub `#`", &sent, &got, &log());
    }
    let got = drain_v4(&mut plus_multibyte, most_copies(&multibyte_wild, &sent)).await;
    assert_matching("`+` for multi-byte levels", &multibyte_wild, &sent, &got);
    let got = drain_v5(&mut plus_ascii, most_copies(&ascii_wild, &sent)).await;
    assert_matching("`+` for ASCII levels", &ascii_wild, &sent, &got);

    assert_still_routes(&broker).await;
}

/// The test's own helpers must be right for the assertions above to mean anything.
#[test]
fn the_generated_topics_cover_every_position_and_the_matcher_follows_the_spec() {
    let topics = topics();
    for w in WORDS {
        assert!(topics.iter().any(|t| t.starts_with(w)), "{w} first");
        assert!(topics.iter().any(|t| t.ends_with(w)), "{w} last");
        assert!(
            topics.iter().any(|t| t.split('/').any(|l| l == w)),
            "{w} alone in a level"
        );
        assert!(
            topics.contains(&format!("//{w}//")),
            "{w} between empty levels"
        );
    }
    for width in 2..=4 {
        assert!(
            topics
                .iter()
                .any(|t| t.chars().any(|c| c.len_utf8() == width)),
            "{width}-byte characters"
        );
    }
    assert!(
        topics.iter().any(|t| t.contains('\u{301}')),
        "combining marks"
    );
    assert!(topics
        .iter()
        .all(|t| !t.contains(['+', '#']) && !t.starts_with('$')));

    assert!(mqtt_matches("#", "é/x"));
    assert!(mqtt_matches("+/x", "é/x"));
    assert!(mqtt_matches("é/#", "é"));
    assert!(mqtt_matches("+/+", "/"));
    assert!(!mqtt_matches("+", "/"));
    assert!(!mqtt_matches("e/x", "é/x"));
    assert!(!mqtt_matches("#", "$SYS/x"));
    assert!(!mqtt_matches("é/+", "é/x/y"));
    assert_eq!(wildcard_for_multibyte("a/é/b€"), "a/+/+");
    assert_eq!(wildcard_for_ascii("a//é/b€"), "+/+/é/b€");
}

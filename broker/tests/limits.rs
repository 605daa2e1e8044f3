//! Issue 21: what a client can make the broker hold has a limit, and past it the request
//! is refused with its reason and counted, while everything else goes on.

mod common;

use common::raw::{self, Connect, RawClient};
use common::{Broker, Options};

#[test]
fn subscriptions_beyond_the_per_client_limit_are_refused_with_quota_exceeded() {
    let broker = Broker::start_with(
        Options {
            extra: "max_subscriptions_per_client = 3\n".into(),
            ..Options::default()
        },
        |_| {},
    );
    for (version, over) in [(5u8, 0x97u8), (4, 0x80)] {
        let mut c = RawClient::connect(broker.port());
        let id = format!("subs-{version}");
        assert_eq!(
            c.handshake(&Connect {
                version,
                client_id: &id,
                ..Default::default()
            }),
            0
        );
        c.send(&raw::subscribe(
            version,
            1,
            &["a/1", "a/2", "a/3", "a/4", "a/#"],
        ));
        let (b, body) = c.read_packet().expect("SUBACK");
        assert_eq!(b, 0x90);
        assert_eq!(
            raw::suback_codes(version, &body),
            vec![0, 0, 0, over, over],
            "v{version}"
        );
        // A filter already held is replaced, not added: allowed at the limit.
        c.send(&raw::subscribe(version, 2, &["a/2"]));
        let (_, body) = c.read_packet().expect("SUBACK");
        assert_eq!(raw::suback_codes(version, &body), vec![0], "v{version}");
        // The connection is served on.
        c.send(&raw::PINGREQ);
        assert_eq!(c.read_packet().expect("PINGRESP").0, 0xD0);
    }
    assert_eq!(
        broker.metric("fbbus_limit_refusals_total{limit=\"subscriptions_per_client\"}"),
        4.0
    );
}

/// An MQTT 5 client (`id`) connected to `broker`.
fn v5(broker: &Broker, id: &str) -> RawClient {
    let mut c = RawClient::connect(broker.port());
    assert_eq!(
        c.handshake(&Connect {
            version: 5,
            client_id: id,
            ..Default::default()
        }),
        0,
        "{id}"
    );
    c
}

/// A retained QoS 1 publication (MQTT `version`); the PUBACK's reason (0 on 3.1.1).
fn retain(c: &mut RawClient, version: u8, pkid: u16, topic: &str, payload: &[u8]) -> u8 {
    let mut packet = if version == 5 {
        raw::publish_v5(topic, None, 1, pkid, payload)
    } else {
        let mut body = Vec::new();
        body.extend_from_slice(&(topic.len() as u16).to_be_bytes());
        body.extend_from_slice(topic.as_bytes());
        body.extend_from_slice(&pkid.to_be_bytes());
        body.extend_from_slice(payload);
        raw::packet(0x32, &body)
    };
    packet[0] |= 0x01;
    c.send(&packet);
    loop {
        let (byte1, body) = c.read_packet().expect("PUBACK");
        if byte1 >> 4 == 4 && body[..2] == pkid.to_be_bytes() {
            return body.get(2).copied().unwrap_or(0);
        }
    }
}

/// The retained messages a new subscription of `filter` gets: (topic, payload), sorted.
fn retained(broker: &Broker, filter: &str) -> Vec<(String, Vec<u8>)> {
    let mut c = RawClient::connect(broker.port());
    assert_eq!(
        c.handshake(&Connect {
            client_id: "retained-reader",
            ..Default::default()
        }),
        0
    );
    c.send(&raw::subscribe(4, 1, &[filter]));
    assert_eq!(c.read_packet().expect("SUBACK").0, 0x90);
    c.stream
        .set_read_timeout(Some(std::time::Duration::from_millis(700)))
        .unwrap();
    let mut got = Vec::new();
    while let Some((byte1, body)) = c.read_packet() {
        if byte1 >> 4 == 3 {
            let len = u16::from_be_bytes([body[0], body[1]]) as usize;
            let topic = String::from_utf8(body[2..2 + len].to_vec()).unwrap();
            let at = 2 + len + if byte1 & 0x06 != 0 { 2 } else { 0 };
            got.push((topic, body[at..].to_vec()));
        }
    }
    got.sort();
    got
}

/// Issue 21: a flood of retained messages on new topics stops at `max_retained_messages`
/// (and `max_retained_bytes`): past it a new topic's retained publication is delivered to
/// the subscribers of the moment but not retained, MQTT 5 QoS 1 publishers get PUBACK
/// 0x97, every refusal is counted; existing ones stay replaceable and clearable, and the
/// broker's own `fbbus/` records are still retained.
#[test]
fn retained_messages_beyond_the_limits_are_not_retained_and_counted() {
    const MAX: usize = 10;
    let broker = Broker::start_with(
        Options {
            extra: format!("max_retained_messages = {MAX}\nmax_retained_bytes = 2000\n"),
            ..Options::default()
        },
        |_| {},
    );
    let mut live = RawClient::connect(broker.port());
    assert_eq!(
        live.handshake(&Connect {
            client_id: "live",
            ..Default::default()
        }),
        0
    );
    live.send(&raw::subscribe(4, 1, &["flood/#"]));
    assert_eq!(live.read_packet().expect("SUBACK").0, 0x90);

    let mut p = v5(&broker, "flooder");
    let payload = [b'v'; 100];
    for i in 0..2 * MAX {
        let expected = if i < MAX { 0 } else { 0x97 };
        assert_eq!(
            retain(&mut p, 5, i as u16 + 1, &format!("flood/{i:02}"), &payload),
            expected,
            "flood/{i:02}"
        );
    }
    // Each was delivered to the subscriber of the moment.
    let mut delivered = 0;
    while delivered < 2 * MAX {
        let (byte1, _) = live.read_packet().expect("live delivery");
        if byte1 >> 4 == 3 {
            delivered += 1;
        }
    }
    drop(live);
    // Replacing and clearing work at the limit; a cleared place can be taken.
    assert_eq!(retain(&mut p, 5, 100, "flood/03", b"replaced"), 0);
    assert_eq!(retain(&mut p, 5, 101, "flood/04", b""), 0);
    assert_eq!(retain(&mut p, 5, 102, "flood/new", &payload), 0);
    assert_eq!(retain(&mut p, 5, 103, "flood/newer", &payload), 0x97);
    // MQTT 3.1.1 has no reason code: acknowledged, not retained, counted.
    let mut v4 = RawClient::connect(broker.port());
    assert_eq!(
        v4.handshake(&Connect {
            client_id: "flooder-4",
            ..Default::default()
        }),
        0
    );
    assert_eq!(retain(&mut v4, 4, 1, "flood/v4", &payload), 0);

    let mut expected: Vec<(String, Vec<u8>)> = (0..MAX)
        .filter(|&i| i != 4)
        .map(|i| (format!("flood/{i:02}"), payload.to_vec()))
        .chain([("flood/new".to_owned(), payload.to_vec())])
        .collect();
    expected[3].1 = b"replaced".to_vec();
    expected.sort();
    assert_eq!(retained(&broker, "flood/#"), expected);
    assert_eq!(broker.metric("fbbus_retained_messages"), MAX as f64);
    let refused = r#"fbbus_limit_refusals_total{limit="retained_messages"}"#;
    assert_eq!(broker.metric(refused), (MAX + 2) as f64);

    // Bytes: with a place free, a publication that would take the bytes past
    // max_retained_bytes is refused too.
    assert_eq!(retain(&mut p, 5, 104, "flood/new", b""), 0);
    let big = [b'b'; 1500];
    assert_eq!(retain(&mut p, 5, 105, "flood/big", &big), 0x97);
    assert_eq!(
        broker.metric(r#"fbbus_limit_refusals_total{limit="retained_bytes"}"#),
        1.0
    );
    assert_eq!(retain(&mut p, 5, 106, "flood/small", b"s"), 0);

    // A QoS 0 flood of 2,000 new topics: the store stays at its limit.
    for i in 0..2000 {
        let mut packet = raw::publish_v5(&format!("flood/q0/{i}"), None, 0, 0, &payload);
        packet[0] |= 0x01;
        p.send(&packet);
    }
    p.send(&raw::PINGREQ);
    while p.read_packet().expect("PINGRESP").0 != 0xD0 {}
    assert_eq!(
        broker.wait_metric(refused, (MAX + 2 + 2000) as f64),
        (MAX + 2 + 2000) as f64
    );
    assert_eq!(broker.metric("fbbus_retained_messages"), MAX as f64);
    let bytes = broker.metric("fbbus_retained_bytes");
    assert!(bytes > 0.0 && bytes <= 2000.0, "retained bytes {bytes}");

    // The broker's own records are outside the clients' limit: a device declared now
    // still has its retained record.
    let mut dev = v5(&broker, "dev-late");
    p.send(&raw::DISCONNECT);
    let declaration = r#"{"fbs": {"F": {"type": "T", "data_out": {"X": "INT"}}}}"#;
    dev.send(&raw::publish_v5(
        "fbbus/declare/dev-late",
        None,
        1,
        1,
        declaration.as_bytes(),
    ));
    loop {
        let (byte1, body) = dev.read_packet().expect("PUBACK");
        if byte1 >> 4 == 4 {
            assert_eq!(body.get(2).copied().unwrap_or(0), 0);
            break;
        }
    }
    let deadline = std::time::Instant::now() + std::time::Duration::from_secs(5);
    loop {
        let record = retained(&broker, "fbbus/devices/dev-late");
        if record.len() == 1 {
            break;
        }
        assert!(
            std::time::Instant::now() < deadline,
            "no retained record for dev-late"
        );
    }
    assert_eq!(broker.metric("fbbus_retained_messages"), MAX as f64);
    assert!(broker
        .log_text()
        .contains("retained publication not retained"));

    // A larger replacement beyond max_retained_bytes: refused (0x97), and the old value
    // is cleared, not left stale; a smaller replacement always works.
    let mut p = v5(&broker, "replacer");
    assert_eq!(retain(&mut p, 5, 1, "flood/00", &big), 0x97);
    assert!(
        !retained(&broker, "flood/#")
            .iter()
            .any(|(t, _)| t == "flood/00"),
        "the replaced value is cleared"
    );
    assert_eq!(broker.metric("fbbus_retained_messages"), (MAX - 1) as f64);
    assert_eq!(retain(&mut p, 5, 2, "flood/01", b"tiny"), 0);
    assert!(retained(&broker, "flood/#").contains(&("flood/01".to_owned(), b"tiny".to_vec())));
}

/// Issue 21: one identity (here the peer address: no password file) holds at most
/// `max_sessions_per_identity` connections and persistent sessions; beyond, CONNECT is
/// refused (MQTT 5 0x97, 3.1.1 0x05) and counted; a takeover or resume of its own
/// session is not refused, and a session that ends gives its place back.
#[test]
fn sessions_beyond_the_per_identity_limit_are_refused() {
    let broker = Broker::start_with(
        Options {
            extra: "max_sessions_per_identity = 3\n".into(),
            ..Options::default()
        },
        |_| {},
    );
    let connect = |version: u8, id: &str, clean: bool| {
        let mut c = RawClient::connect(broker.port());
        let code = c.handshake(&Connect {
            version,
            client_id: id,
            clean,
            session_expiry: (version == 5 && !clean).then_some(3600),
            ..Default::default()
        });
        (c, code)
    };
    let (a, code) = connect(4, "a", true);
    assert_eq!(code, 0);
    let (_b, code) = connect(5, "b", true);
    assert_eq!(code, 0);
    // A persistent session kept offline still counts.
    let (mut kept, code) = connect(4, "kept", false);
    assert_eq!(code, 0);
    kept.send(&raw::DISCONNECT);
    assert!(kept.closed_by_broker());
    broker.wait_metric("fbbus_disconnects_total{reason=\"client\"}", 1.0);
    assert_eq!(connect(5, "d", true).1, 0x97, "MQTT 5: Quota exceeded");
    assert_eq!(connect(4, "d", true).1, 0x05, "MQTT 3.1.1: Not authorized");
    // Its own sessions: a takeover and a resume.
    let (_a2, code) = connect(4, "a", true);
    assert_eq!(code, 0, "takeover");
    drop(a);
    let (mut kept, code) = connect(4, "kept", false);
    assert_eq!(code, 0, "resume");
    // The kept session ended for good (clean): its place is free.
    kept.send(&raw::DISCONNECT);
    assert!(kept.closed_by_broker());
    let (mut kept, code) = connect(4, "kept", true);
    assert_eq!(code, 0);
    kept.send(&raw::DISCONNECT);
    assert!(kept.closed_by_broker());
    broker.wait_metric("fbbus_disconnects_total{reason=\"client\"}", 3.0);
    assert_eq!(connect(5, "e", true).1, 0);
    assert_eq!(
        broker.metric(r#"fbbus_limit_refusals_total{limit="sessions_per_identity"}"#),
        2.0
    );
    assert!(broker.log_text().contains("max_sessions_per_identity"));
}

/// With a password file the identity is the username: one user's sessions do not take
/// another's places, even from the same address.
#[test]
fn sessions_are_counted_per_username() {
    let broker = Broker::start_with(
        Options {
            extra: "max_sessions_per_identity = 2\n[auth]\npassword_file = \"passwd\"\n".into(),
            ..Options::default()
        },
        |dir| {
            common::add_user(&dir.join("passwd"), "alice", "alice-pw");
            common::add_user(&dir.join("passwd"), "bob", "bob-pw");
        },
    );
    let connect = |user: &str, id: &str| {
        let mut c = RawClient::connect(broker.port());
        let password = format!("{user}-pw");
        let code = c.handshake(&Connect {
            version: 5,
            client_id: id,
            login: Some((user, &password)),
            ..Default::default()
        });
        (c, code)
    };
    let held: Vec<_> = ["a1", "a2"]
        .iter()
        .map(|id| {
            let (c, code) = connect("alice", id);
            assert_eq!(code, 0, "{id}");
            c
        })
        .collect();
    assert_eq!(connect("alice", "a3").1, 0x97);
    assert_eq!(connect("bob", "b1").1, 0);
    assert_eq!(
        broker.metric(r#"fbbus_limit_refusals_total{limit="sessions_per_identity"}"#),
        1.0
    );
    drop(held);
}

/// `max_connections` clients all get in, however many router links the broker holds for
/// itself (its publisher, the readiness probe, the console's observer): the next one is
/// closed at the listener, counted under `max_connections`. With one router slot beyond
/// `max_connections`, as before, the last clients were refused in the router instead,
/// each with an error line and no count.
#[test]
fn max_connections_clients_all_get_in_and_the_next_is_refused_at_the_listener() {
    const MAX: usize = 12;
    let broker = Broker::start_with(
        Options {
            extra: format!("max_connections = {MAX}\n"),
            ..Options::default()
        },
        |_| {},
    );
    let clients: Vec<RawClient> = (0..MAX)
        .map(|i| {
            let mut c = RawClient::connect(broker.port());
            let id = format!("c{i:02}");
            let code = c.handshake(&Connect {
                client_id: &id,
                ..Default::default()
            });
            assert_eq!(code, 0, "{id}, one of the {MAX} allowed");
            c
        })
        .collect();
    let mut extra = RawClient::connect(broker.port());
    assert!(extra.closed_by_broker(), "client {} is closed", MAX + 1);
    broker.wait_metric(
        r#"fbbus_connects_refused_total{reason="max_connections"}"#,
        1.0,
    );
    assert!(
        !broker.log_text().contains("router refused"),
        "no client was refused in the router"
    );
    drop(clients);
}

//! Sessions and identity of typed devices end to end against the real `fbbus` binary:
//! takeovers never show a device offline, typed wills are checked and re-encoded, with
//! passwords only the device itself speaks for it, and a will on `fbbus/` is refused.
//!
//! Each test starts its own broker on free loopback ports; helpers are in
//! `common/fb.rs`.

mod common;

use serde_json::Value;

use common::clients::{V4, V5, WAIT};
use common::fb::*;
use common::raw;
use common::{Broker, Options};

// ---------------------------------------------------------------- 9. stale ends, typed wills

/// Connects a second time with `first`'s client id and waits until the broker has closed
/// `first` (the takeover). Returns the new connection.
fn take_over(first: &mut Dev, port: u16) -> Dev {
    let second = Dev::connect(port, 5, &first.id.clone());
    let closed = tokio::task::block_in_place(|| {
        first.raw.stream.set_read_timeout(Some(WAIT)).unwrap();
        first.raw.closed_by_broker()
    });
    assert!(closed, "the first connection stays open");
    second
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_takeover_leaves_the_device_online_on_the_new_session() {
    let broker = Broker::start();
    let mut diag_sub = observer(&broker, "watch", &["fbbus/diag/conv-a"]).await;
    let mut first = Dev::connect(broker.port(), 5, "conv-a");
    let s1 = declare_ok(&mut first, CONV, &mut diag_sub, &broker).await;

    let mut second = take_over(&mut first, broker.port());
    assert!(broker.wait_metric(r#"fbbus_disconnects_total{reason="takeover"}"#, 1.0) >= 1.0);
    let rec = wait_record(&broker, "conv-a", "moved to the new session", |r| {
        r["session"].as_u64() > Some(s1)
    })
    .await;
    let s2 = rec["session"].as_u64().unwrap();
    assert_eq!(rec["status"], "online", "{rec}");
    assert_eq!(rec["last_will_reason"], Value::Null, "{rec}");

    // The new session has the declared interface without declaring again, and redeclaring
    // answers with its number.
    let mut sub = observer(&broker, "sub", &["fb/conv-a/#"]).await;
    assert_eq!(second.publish("fb/conv-a/CONV/POSITION", b"1"), 0);
    assert_eq!(
        next_on(&mut sub, "fb/conv-a/CONV/POSITION", WAIT)
            .await
            .as_deref(),
        Some(&b"1"[..])
    );
    assert_eq!(
        declare_ok(&mut second, CONV, &mut diag_sub, &broker).await,
        s2
    );
    // Whatever the old connection's end did, it is over: the record is s2's.
    tokio::time::sleep(QUIET).await;
    let rec = record(&broker, "conv-a").unwrap();
    assert_eq!(
        (rec["status"].as_str(), rec["session"].as_u64()),
        (Some("online"), Some(s2)),
        "{rec}"
    );
    second.disconnect();
    let rec = wait_record(
        &broker,
        "conv-a",
        "disconnected",
        offline_because("clean disconnect"),
    )
    .await;
    assert_eq!(rec["session"], s2);
}

/// Device contract section 4: "An end that belongs to an older session (a takeover, a delayed
/// will) never marks a newer session offline." A watcher of the record and of the online
/// count must not see the device go offline while it takes its own client id over.
/// Repeated, because whether the old connection's end lands before or after the new
/// connection reaches the registry is a race: before commit 2c57be9 (the registry learns
/// the new session number before the router link ends the old connection) most takeovers
/// published the device offline and the count at 0.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_takeover_never_shows_the_device_offline() {
    const ROUNDS: u64 = 20;
    let broker = Broker::start();
    let mut diag_sub = observer(&broker, "watch", &["fbbus/diag/conv-a"]).await;
    let mut current = Dev::connect(broker.port(), 5, "conv-a");
    let s1 = declare_ok(&mut current, CONV, &mut diag_sub, &broker).await;
    let mut records = observer(
        &broker,
        "records",
        &["fbbus/devices/conv-a", "fbbus/lines/test/online"],
    )
    .await;
    // The retained record and count first.
    let retained = one_each(
        &mut records,
        &["fbbus/devices/conv-a", "fbbus/lines/test/online"],
        &broker,
    )
    .await;
    assert_eq!(parse(&retained[0])["session"], s1);
    assert_eq!(retained[1], b"1");

    for _ in 0..ROUNDS {
        current = take_over(&mut current, broker.port());
    }
    // The last connection's number, as the device learns it: session numbers come from one
    // counter for all client ids, so it is not s1 + ROUNDS.
    let last = declare_ok(&mut current, CONV, &mut diag_sub, &broker).await;
    assert!(
        last >= s1 + ROUNDS,
        "{last} after {s1} and {ROUNDS} takeovers"
    );
    let rec = wait_record(&broker, "conv-a", "reached the last session", |r| {
        r["session"].as_u64() == Some(last)
    })
    .await;
    assert_eq!(rec["status"], "online");
    let seen: Vec<(String, String)> = drain(&mut records, QUIET)
        .await
        .into_iter()
        .map(|(t, p)| (t, String::from_utf8_lossy(&p).into_owned()))
        .collect();
    // An old connection's end reaches the registry after its socket closed (what
    // `take_over` saw), so the last one may still be on its way.
    let stale = broker.wait_metric("fbbus_registry_stale_ends_total", ROUNDS as f64);
    let flaps: Vec<&(String, String)> = seen
        .iter()
        .filter(|(t, p)| {
            if t == "fbbus/lines/test/online" {
                p != "1"
            } else {
                parse(p.as_bytes())["status"] != "online"
            }
        })
        .collect();
    assert!(
        flaps.is_empty() && stale == ROUNDS as f64,
        "{ROUNDS} takeovers: {} published the device offline or the count below 1, \
         fbbus_registry_stale_ends_total = {stale}; first: {:?}",
        flaps.len(),
        flaps.first()
    );
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn typed_wills_are_checked_and_re_encoded() {
    let broker = Broker::start();
    let mut diag_sub = observer(&broker, "watch", &["fbbus/diag/#"]).await;
    let mut wills = observer(
        &broker,
        "wills",
        &["fb/+/CONV/CONNECT", "fbdk/+/CONV/CONNECT"],
    )
    .await;

    // The reference line's CONNECT output: a BOOL data output set to FALSE by the will.
    let connect = |id: &'static str, payload: &'static str| {
        let mut o = V4::options(broker.port(), id, None);
        o.set_last_will(rumqttc::LastWill::new(
            format!("fb/{id}/CONV/CONNECT"),
            payload,
            rumqttc::QoS::AtLeastOnce,
            false,
        ));
        o
    };
    let plc = V4::connect_with(connect("plc", "false")).await.unwrap();
    plc.client
        .publish("fbbus/declare/plc", rumqttc::QoS::AtLeastOnce, false, CONV)
        .await
        .unwrap();
    let answer = diag(&mut diag_sub, "plc", "declaration", &broker).await;
    assert_eq!(answer["ok"], true, "{answer}");
    let session = answer["session"].as_u64().unwrap();
    let mut wills5 = V5::connect(broker.port(), "wills5", None).await.unwrap();
    wills5.subscribe("fb/plc/CONV/CONNECT").await;
    plc.client
        .publish(
            "fb/plc/CONV/CONNECT",
            rumqttc::QoS::AtLeastOnce,
            false,
            "true",
        )
        .await
        .unwrap();
    let pair = ["fb/plc/CONV/CONNECT", "fbdk/plc/CONV/CONNECT"];
    assert_eq!(
        one_each(&mut wills, &pair, &broker).await,
        [b"true".to_vec(), vec![0x41]]
    );
    drop(plc);
    // The will, canonical and re-encoded.
    assert_eq!(
        one_each(&mut wills, &pair, &broker).await,
        [b"false".to_vec(), vec![0x40]]
    );
    // MQTT 5 subscribers get the will exactly as set: the broker adds no user property
    // [MQTT-3.3.2-17]; the session number is the registry record's.
    let mut will5 = None;
    while let Some(p) = wills5.next_publish(WAIT).await {
        if &p.payload[..] == b"false" {
            will5 = Some(p);
            break;
        }
    }
    let will5 = will5.expect("the will, for the MQTT 5 subscriber");
    let props = will5.properties.unwrap_or_default().user_properties;
    assert!(props.is_empty(), "will user properties {props:?}");
    let died = wait_record(&broker, "plc", "died", offline_because("connection lost")).await;
    assert_eq!(died["session"].as_u64(), Some(session), "{died}");

    // An ill-typed will payload (2 is not a BOOL; 0 and 1 are) is refused like a
    // publication.
    let bad = V4::connect_with(connect("plc-bad", "2")).await.unwrap();
    bad.client
        .publish(
            "fbbus/declare/plc-bad",
            rumqttc::QoS::AtLeastOnce,
            false,
            CONV,
        )
        .await
        .unwrap();
    assert_eq!(
        diag(&mut diag_sub, "plc-bad", "declaration", &broker).await["ok"],
        true
    );
    let wills_before = broker.metric("fbbus_wills_published_total");
    drop(bad);
    wait_record(
        &broker,
        "plc-bad",
        "died",
        offline_because("connection lost"),
    )
    .await;
    assert_metric(
        &broker,
        &rejected_series("plc-bad", "CONV.CONNECT", "payload_format_invalid"),
        1.0,
    );
    let d = diag(&mut diag_sub, "plc-bad", "rejected", &broker).await;
    assert_eq!(d["topic"], "fb/plc-bad/CONV/CONNECT", "{d}");
    let seen = drain(&mut wills, QUIET).await;
    assert!(seen.is_empty(), "an ill-typed will was published: {seen:?}");
    assert_eq!(broker.metric("fbbus_wills_published_total"), wills_before);

    // A will on another device's typed topic is accepted at CONNECT, never published.
    let mut o = V4::options(broker.port(), "intruder", None);
    o.set_last_will(rumqttc::LastWill::new(
        "fb/plc/CONV/CONNECT",
        "true",
        rumqttc::QoS::AtLeastOnce,
        false,
    ));
    let intruder = V4::connect_with(o).await.unwrap();
    drop(intruder);
    assert_metric(
        &broker,
        &rejected_series("undeclared", "undeclared", "not_authorized"),
        1.0,
    );
    assert!(drain(&mut wills, QUIET).await.is_empty());
}

// ---------------------------------------------------------------- 11. identity

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn with_passwords_only_the_device_itself_speaks_for_it() {
    let broker = Broker::start_with(
        Options {
            extra: "[auth]\npassword_file = \"passwd\"\n".into(),
            ..Default::default()
        },
        |dir| {
            common::add_user(&dir.join("passwd"), "dev1", "pw1");
            common::add_user(&dir.join("passwd"), "dev2", "pw2");
            common::add_user(&dir.join("passwd"), "ops", "pw-ops");
        },
    );
    let ops = |id: &str| {
        let port = broker.port();
        let id = id.to_owned();
        async move {
            V4::connect(port, &id, Some(("ops", "pw-ops")))
                .await
                .unwrap_or_else(|e| panic!("observer {id}: {e}"))
        }
    };
    let mut diag_sub = ops("watch").await;
    diag_sub.subscribe("fbbus/diag/dev1").await;
    let mut sub = ops("sub").await;
    sub.subscribe("fb/#").await;
    let login = |id, user, password| raw::Connect {
        version: 5,
        client_id: id,
        login: Some((user, password)),
        ..Default::default()
    };

    // dev1 itself declares and goes away.
    let mut dev1 = Dev::try_connect(broker.port(), &login("dev1", "dev1", "pw1")).unwrap();
    let s1 = declare_ok(&mut dev1, CONV, &mut diag_sub, &broker).await;
    dev1.disconnect();
    wait_record(
        &broker,
        "dev1",
        "disconnected",
        offline_because("clean disconnect"),
    )
    .await;

    // dev2's credentials with dev1's client id: refused at CONNECT (issue 33: a client id
    // that is a user's name is that user's), before it could try to speak for dev1.
    let impostor = Dev::try_connect(broker.port(), &login("dev1", "dev2", "pw2"));
    assert_eq!(
        impostor.err(),
        Some(0x85),
        "dev2 connected with dev1's client id"
    );
    // Nor does the attempt bring dev1 online, or change its record.
    let rec = record(&broker, "dev1").unwrap();
    assert_eq!(
        (rec["status"].as_str(), rec["session"].as_u64()),
        (Some("offline"), Some(s1)),
        "{rec}"
    );
    assert_metric(
        &broker,
        "fbbus_connects_refused_total{reason=\"client_id_reserved\"}",
        1.0,
    );

    // dev2 as itself cannot publish dev1's topics either; on MQTT 3.1.1 they are dropped.
    let mut dev2 = Dev::try_connect(
        broker.port(),
        &raw::Connect {
            version: 4,
            ..login("dev2", "dev2", "pw2")
        },
    )
    .unwrap();
    assert_eq!(dev2.publish("fb/dev1/CONV/POSITION", b"2"), 0);
    assert_eq!(dev2.publish("fbbus/declare/dev1", CONV.as_bytes()), 0);

    // dev1 back: only its own message is delivered.
    let mut dev1 = Dev::try_connect(broker.port(), &login("dev1", "dev1", "pw1")).unwrap();
    assert_eq!(dev1.publish("fb/dev1/CONV/POSITION", b"4"), 0);
    assert_eq!(
        next_under(&mut sub, "fb/", WAIT).await,
        Some(("fb/dev1/CONV/POSITION".to_owned(), b"4".to_vec()))
    );
    assert!(drain(&mut sub, QUIET).await.is_empty());
    let rec = record(&broker, "dev1").unwrap();
    assert_eq!(rec["status"], "online");
    assert!(rec["session"].as_u64() > Some(s1), "{rec}");
    assert_metric(
        &broker,
        &rejected_series("undeclared", "undeclared", "not_authorized"),
        2.0,
    );
}

// ---------------------------------------------------------------- 12. wills on fbbus/

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_will_on_the_broker_namespace_is_refused_at_connect() {
    let broker = Broker::start();
    for (version, refused) in [(4u8, 5u8), (5, 0x87)] {
        for topic in [
            "fbbus/devices/dev1",
            "fbbus/lines/test/online",
            "fbbus/declare/dev1",
            "fbbus/diag/dev1",
        ] {
            let result = Dev::try_connect(
                broker.port(),
                &raw::Connect {
                    version,
                    client_id: "dev1",
                    will: Some((topic, b"{\"status\": \"online\"}")),
                    ..Default::default()
                },
            );
            assert_eq!(result.err(), Some(refused), "v{version} will on {topic}");
        }
    }
    assert_eq!(
        broker.wait_metric(
            r#"fbbus_connects_refused_total{reason="will_not_authorized"}"#,
            8.0
        ),
        8.0
    );
    // A will on the device's own typed topic is fine.
    let dev = Dev::try_connect(
        broker.port(),
        &raw::Connect {
            version: 5,
            client_id: "dev1",
            will: Some(("fb/dev1/CONV/CONNECT", b"false")),
            ..Default::default()
        },
    );
    assert!(dev.is_ok());
}

// ---------------------------------------------------------------- last words before a takeover

/// A device that publishes, disconnects (or just closes) and is back at once with the same
/// client id (a `mosquitto_pub -i` in a shell loop, a runtime restarting) loses nothing: what it sent
/// before it left was already in the broker's socket when the new connection took its
/// client id over, and is routed first. Before, the router dropped the old link at the
/// new CONNECT, and whatever its connection had not read yet was gone (seen once in CI:
/// the README's try-it lost a `mosquitto_pub`'s value).
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn what_a_device_sent_before_its_next_connection_is_delivered() {
    const ROUNDS: usize = 400;
    let broker = Broker::start();
    let mut sub = observer(&broker, "watch", &["line/seq"]).await;
    tokio::task::block_in_place(|| {
        for i in 0..ROUNDS {
            let mut dev = raw::RawClient::connect(broker.port());
            let connect = raw::Connect {
                client_id: "plc-quick",
                ..Default::default()
            };
            assert_eq!(dev.handshake(&connect), 0, "round {i}");
            let mut last_words = raw::publish_qos0("line/seq", i.to_string().as_bytes());
            // Every other device leaves with a DISCONNECT; the rest just close.
            if i % 2 == 0 {
                last_words.extend_from_slice(&[0xe0, 0x00]);
            }
            dev.send(&last_words);
        }
    });
    let mut seen = Vec::new();
    while let Some(payload) = next_on(&mut sub, "line/seq", WAIT).await {
        seen.push(
            String::from_utf8(payload)
                .unwrap()
                .parse::<usize>()
                .unwrap(),
        );
        if seen.len() == ROUNDS {
            break;
        }
    }
    let missing: Vec<usize> = (0..ROUNDS).filter(|i| !seen.contains(i)).collect();
    assert!(
        missing.is_empty(),
        "{} of {ROUNDS} lost: {missing:?}; takeovers: {}\n{}",
        missing.len(),
        broker.metric(r#"fbbus_disconnects_total{reason="takeover"}"#),
        broker.log_text()
    );
    assert_eq!(seen, (0..ROUNDS).collect::<Vec<_>>(), "out of order");
}

//! MQTT 5 behaviours fbbus enforces in its own packet path (the rest of the conformance
//! work is listed in docs/conformance.md).

mod common;

use std::time::Duration;

use common::clients::{p5, V4, V5, WAIT};
use common::raw::{self, RawClient};
use common::{Broker, Options};

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn client_topic_aliases_are_resolved_before_routing() {
    let broker = Broker::start();
    let mut sub = V4::connect(broker.port(), "sub", None).await.unwrap();
    sub.subscribe("plant/plc-1/#").await;
    let mut c = RawClient::connect(broker.port());
    assert_eq!(
        c.handshake(&raw::Connect {
            version: 5,
            client_id: "aliaser",
            ..Default::default()
        }),
        0
    );
    c.send(&raw::publish_v5(
        "plant/plc-1/speed",
        Some(7),
        0,
        0,
        b"first",
    ));
    c.send(&raw::publish_v5("", Some(7), 1, 1, b"second"));
    for expected in ["first", "second"] {
        let m = sub.next_publish(WAIT).await.expect("delivery");
        assert_eq!(
            (m.topic.as_str(), &m.payload[..]),
            ("plant/plc-1/speed", expected.as_bytes())
        );
    }
    // An alias never set is a protocol error (DISCONNECT 0x94).
    c.send(&raw::publish_v5("", Some(8), 0, 0, b"unknown"));
    let (byte1, body) = loop {
        let p = c.read_packet().expect("DISCONNECT");
        if p.0 == 0xE0 {
            break p;
        }
    };
    assert_eq!((byte1, body[0]), (0xE0, 0x94));
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn deliveries_over_the_clients_maximum_packet_size_are_dropped() {
    let broker = Broker::start();
    let mut small = RawClient::connect(broker.port());
    let connect = raw::Connect {
        version: 5,
        client_id: "small",
        max_packet_size: Some(100),
        ..Default::default()
    };
    assert_eq!(small.handshake(&connect), 0);
    small.send(&raw::subscribe(5, 1, &["t"]));
    assert_eq!(small.read_packet().expect("SUBACK").0, 0x90);

    let publisher = V4::connect(broker.port(), "pub", None).await.unwrap();
    for (qos, payload) in [
        (1, vec![b'x'; 500]),
        (1, b"fits".to_vec()),
        (0, vec![b'y'; 500]),
        (0, b"fits too".to_vec()),
    ] {
        let qos = if qos == 1 {
            rumqttc::QoS::AtLeastOnce
        } else {
            rumqttc::QoS::AtMostOnce
        };
        publisher
            .client
            .publish("t", qos, false, payload)
            .await
            .unwrap();
    }
    let mut received = Vec::new();
    small
        .stream
        .set_read_timeout(Some(Duration::from_secs(2)))
        .unwrap();
    while let Some((byte1, body)) = small.read_packet() {
        assert!(
            body.len() + 2 <= 100,
            "a packet over the client's maximum arrived"
        );
        if byte1 & 0xF0 == 0x30 {
            let qos = (byte1 >> 1) & 3;
            let topic_len = u16::from_be_bytes([body[0], body[1]]) as usize;
            let mut at = 2 + topic_len;
            if qos > 0 {
                let pkid = [body[at], body[at + 1]];
                small.send(&[0x40, 0x02, pkid[0], pkid[1]]); // PUBACK
                at += 2;
            }
            let props = body[at] as usize;
            received.push(String::from_utf8_lossy(&body[at + 1 + props..]).into_owned());
        }
        if received.len() == 2 {
            break;
        }
    }
    assert_eq!(received, ["fits", "fits too"]);
    assert_eq!(
        broker.metric("fbbus_messages_dropped_total{reason=\"client_max_packet_size\"}"),
        2.0
    );
    // The dropped QoS 1 delivery was acknowledged for the client: the session still flows.
    publisher
        .client
        .publish("t", rumqttc::QoS::AtLeastOnce, false, "after")
        .await
        .unwrap();
    let (byte1, _) = small.read_packet().expect("later deliveries still arrive");
    assert_eq!(byte1 & 0xF0, 0x30);
}

#[test]
fn more_unacknowledged_publications_than_the_receive_maximum_disconnect() {
    let broker = Broker::start_with(
        common::Options {
            extra: "max_inflight = 5\n".into(),
            ..Default::default()
        },
        |_| {},
    );
    let mut c = RawClient::connect(broker.port());
    assert_eq!(
        c.handshake(&raw::Connect {
            version: 5,
            client_id: "greedy",
            ..Default::default()
        }),
        0
    );
    // Twenty QoS 1 publications in one write: the broker cannot have acknowledged them.
    let burst: Vec<u8> = (1..=20u16)
        .flat_map(|pkid| raw::publish_v5("t", None, 1, pkid, b"x"))
        .collect();
    c.send(&burst);
    let disconnect = loop {
        match c.read_packet() {
            Some((0xE0, body)) => break body[0],
            Some(_) => continue,
            None => panic!("closed without DISCONNECT 0x93"),
        }
    };
    assert_eq!(disconnect, 0x93, "receive maximum exceeded");

    // Within the limit, nothing happens.
    let mut ok = RawClient::connect(broker.port());
    assert_eq!(
        ok.handshake(&raw::Connect {
            version: 5,
            client_id: "polite",
            ..Default::default()
        }),
        0
    );
    let burst: Vec<u8> = (1..=5u16)
        .flat_map(|pkid| raw::publish_v5("t", None, 1, pkid, b"x"))
        .collect();
    ok.send(&burst);
    for _ in 0..5 {
        assert_eq!(ok.read_packet().expect("PUBACK").0, 0x40);
    }
}

/// The Receive Maximum fbbus announced in CONNACK, exceeded with QoS 2 publications
/// that stay in flight (never released): the client reads DISCONNECT 0x93 before the
/// connection closes [MQTT-3.3.4-7], even though it kept sending and a PINGRESP was
/// still queued when the broker decided to close.
#[test]
fn the_receive_maximum_disconnect_reaches_the_client_before_the_close() {
    let broker = Broker::start();
    let mut c = RawClient::connect(broker.port());
    c.send(
        &raw::Connect {
            version: 5,
            client_id: "flooder",
            ..Default::default()
        }
        .bytes(),
    );
    let (byte1, body) = c.read_packet().expect("CONNACK");
    assert_eq!((byte1, body[1]), (0x20, 0));
    // CONNACK properties: find Receive Maximum (0x21).
    let (mut at, end) = (3, 3 + body[2] as usize);
    let mut receive_max = 65535u16;
    while at < end {
        let id = body[at];
        at += 1;
        match id {
            0x21 => {
                receive_max = u16::from_be_bytes([body[at], body[at + 1]]);
                break;
            }
            0x13 | 0x22 => at += 2,
            0x24 | 0x25 | 0x28 | 0x29 | 0x2A => at += 1,
            0x11 | 0x27 => at += 4,
            0x12 | 0x1A | 0x1C | 0x1F => {
                at += 2 + u16::from_be_bytes([body[at], body[at + 1]]) as usize
            }
            other => panic!("CONNACK property {other:#x}"),
        }
    }
    assert!(
        receive_max < 1000,
        "Receive Maximum {receive_max} announced"
    );
    // PINGREQ, then one QoS 2 PUBLISH more than allowed, all in one write, no PUBREL.
    let mut burst = raw::PINGREQ.to_vec();
    for pkid in 1..=receive_max + 1 {
        burst.extend(raw::publish_v5("flood", None, 2, pkid, b"x"));
    }
    c.send(&burst);
    let mut seen = Vec::new();
    let disconnect = loop {
        match c.read_packet() {
            Some((0xE0, body)) => break body,
            Some((byte1, _)) => seen.push(byte1),
            None => panic!("closed without DISCONNECT; read {seen:x?}"),
        }
    };
    assert_eq!(disconnect[0], 0x93, "Receive Maximum exceeded");
    assert!(
        c.closed_by_broker(),
        "the broker closes after the DISCONNECT"
    );
    // The disconnect is counted when the connection task ends, which may be just after
    // the client sees the close.
    assert_eq!(
        broker.wait_metric("fbbus_disconnects_total{reason=\"protocol_error\"}", 1.0),
        1.0
    );
}

/// Lower-QoS deliveries are acknowledged to the router on the client's behalf: many more
/// than the router's in-flight window (`max_inflight_out`, 50 here) must flow through a
/// QoS 2 subscription.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn delivery_qos_is_the_lower_of_publication_and_subscription() {
    let broker = Broker::start_with(
        common::Options {
            extra: "max_inflight_out = 50\n".into(),
            ..Default::default()
        },
        |_| {},
    );
    let mut sub = V4::connect(broker.port(), "sub2", None).await.unwrap();
    sub.client
        .subscribe("q/#", rumqttc::QoS::ExactlyOnce)
        .await
        .unwrap();
    sub.next(WAIT, |p| {
        matches!(p, rumqttc::Packet::SubAck(_)).then_some(())
    })
    .await
    .unwrap();
    let publisher = V4::connect(broker.port(), "pub", None).await.unwrap();
    for (topic, qos) in [
        ("q/0", rumqttc::QoS::AtMostOnce),
        ("q/1", rumqttc::QoS::AtLeastOnce),
        ("q/2", rumqttc::QoS::ExactlyOnce),
    ] {
        for i in 0..300u32 {
            publisher
                .client
                .publish(topic, qos, false, i.to_be_bytes().to_vec())
                .await
                .unwrap();
        }
        for i in 0..300u32 {
            let m = sub
                .next_publish(Duration::from_secs(10))
                .await
                .unwrap_or_else(|| {
                    panic!(
                        "{topic}: delivery {i} of 300 missing; log: {}",
                        broker.log_text()
                    )
                });
            assert_eq!(m.topic, topic);
            assert_eq!(m.qos, qos, "{topic}: delivered at the publication's QoS");
            assert_eq!(m.payload[..], i.to_be_bytes(), "{topic}: in order");
        }
    }
}

/// [MQTT-3.3.4-9]: no more unacknowledged QoS 1/2 deliveries than the client's Receive
/// Maximum; the rest wait, in order, and follow as the client acknowledges.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn deliveries_respect_the_clients_receive_maximum() {
    let broker = Broker::start();
    let connect = raw::Connect {
        version: 5,
        client_id: "slow",
        receive_maximum: Some(2),
        ..Default::default()
    };
    let (mut c, _publisher) = subscribed_with_ten_waiting(&broker, &connect, "rm").await;
    assert_eq!(
        acknowledge_in_turn(&mut c, 2, 10, "a third delivery before any PUBACK"),
        (0..10).collect::<Vec<u8>>()
    );
}

/// A raw client connected with `connect` and subscribed to `topic` at QoS 1, with ten QoS 1
/// messages (payloads 0..10) published to it by another client, which is returned too: it
/// must live on, its messages go out from its event loop.
async fn subscribed_with_ten_waiting(
    broker: &Broker,
    connect: &raw::Connect<'_>,
    topic: &str,
) -> (RawClient, V4) {
    let mut c = RawClient::connect(broker.port());
    assert_eq!(c.handshake(connect), 0);
    let mut sub = raw::subscribe(connect.version, 1, &[topic]);
    *sub.last_mut().unwrap() = 1; // QoS 1
    c.send(&sub);
    assert_eq!(c.read_packet().expect("SUBACK").0, 0x90);
    let publisher = V4::connect(broker.port(), "pub", None).await.unwrap();
    for i in 0..10u8 {
        publisher
            .client
            .publish(topic, rumqttc::QoS::AtLeastOnce, false, vec![i])
            .await
            .unwrap();
    }
    (c, publisher)
}

/// Reads a QoS 1 PUBLISH (MQTT 3.1.1 or 5): its packet id and one-byte payload; None when
/// nothing comes within the read timeout.
fn read_qos1_publish(c: &mut RawClient) -> Option<(u16, u8)> {
    let (byte1, body) = c.read_packet()?;
    assert_eq!(byte1 & 0xF0, 0x30);
    let topic_len = u16::from_be_bytes([body[0], body[1]]) as usize;
    let pkid = u16::from_be_bytes([body[2 + topic_len], body[3 + topic_len]]);
    Some((pkid, *body.last().unwrap()))
}

/// Reads `window` deliveries, checks that no more come before a PUBACK (else fails with
/// `beyond`), then acknowledges each in turn, reading the next, until `total` came.
/// Returns their payloads in the order they came.
fn acknowledge_in_turn(c: &mut RawClient, window: usize, total: usize, beyond: &str) -> Vec<u8> {
    c.stream
        .set_read_timeout(Some(Duration::from_millis(700)))
        .unwrap();
    let mut in_flight: Vec<(u16, u8)> = (0..window)
        .map(|i| read_qos1_publish(c).unwrap_or_else(|| panic!("delivery {i} of the window")))
        .collect();
    assert!(read_qos1_publish(c).is_none(), "{beyond}");
    let mut payloads = Vec::new();
    while let Some((pkid, payload)) = in_flight.first().copied() {
        in_flight.remove(0);
        payloads.push(payload);
        let [hi, lo] = pkid.to_be_bytes();
        c.send(&[0x40, 0x02, hi, lo]);
        if payloads.len() + in_flight.len() < total {
            in_flight.push(read_qos1_publish(c).expect("the next delivery after a PUBACK"));
        }
    }
    payloads
}

/// `[broker] max_inflight_out`: an MQTT 3.1.1 client, which has no Receive Maximum, gets
/// that many unacknowledged QoS 1 deliveries at most; the rest wait, in order, and follow
/// as it acknowledges.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn deliveries_in_flight_to_a_connection_are_bounded() {
    const WINDOW: usize = 3;
    let broker = Broker::start_with(
        common::Options {
            extra: format!("max_inflight_out = {WINDOW}\n"),
            ..Default::default()
        },
        |_| {},
    );
    let connect = raw::Connect {
        client_id: "historian",
        ..Default::default()
    };
    let (mut c, _publisher) = subscribed_with_ten_waiting(&broker, &connect, "w").await;
    let beyond = "a delivery beyond max_inflight_out before any PUBACK";
    assert_eq!(
        acknowledge_in_turn(&mut c, WINDOW, 10, beyond),
        (0..10).collect::<Vec<u8>>()
    );
}

/// Connects, returns (session present, the client).
fn connect_v5(port: u16, id: &str, clean: bool, expiry: u32) -> (bool, RawClient) {
    let mut c = RawClient::connect(port);
    c.send(
        &raw::Connect {
            version: 5,
            client_id: id,
            clean,
            session_expiry: Some(expiry),
            ..Default::default()
        }
        .bytes(),
    );
    let (byte1, body) = c.read_packet().expect("CONNACK");
    assert_eq!((byte1, body[1]), (0x20, 0), "CONNACK success");
    (body[0] & 1 == 1, c)
}

/// Subscribes at QoS 1, disconnects cleanly, and has another client publish while offline.
async fn leave_a_message_behind(broker: &Broker, c: RawClient, topic: &str) {
    leave_a_message_behind_with(broker, c, topic, &raw::DISCONNECT).await
}

/// An MQTT 5 DISCONNECT (reason 0) with a Session Expiry Interval.
fn disconnect_with_expiry(expiry: u32) -> Vec<u8> {
    let mut body = vec![0x00, 0x05, 0x11];
    body.extend_from_slice(&expiry.to_be_bytes());
    raw::packet(0xE0, &body)
}

/// `leave_a_message_behind`, ending the connection with `disconnect`.
async fn leave_a_message_behind_with(
    broker: &Broker,
    mut c: RawClient,
    topic: &str,
    disconnect: &[u8],
) {
    let mut sub = raw::subscribe(5, 1, &[topic]);
    *sub.last_mut().unwrap() = 1;
    c.send(&sub);
    assert_eq!(c.read_packet().expect("SUBACK").0, 0x90);
    c.send(disconnect);
    assert!(c.closed_by_broker());
    let publisher = V4::connect(
        broker.port(),
        &format!("pub-{}", topic.replace('/', "-")),
        None,
    )
    .await
    .unwrap();
    publisher
        .client
        .publish(topic, rumqttc::QoS::AtLeastOnce, false, "while offline")
        .await
        .unwrap();
    tokio::time::sleep(Duration::from_millis(300)).await;
}

fn next_publish_payload(c: &mut RawClient) -> Option<Vec<u8>> {
    c.stream
        .set_read_timeout(Some(Duration::from_millis(800)))
        .unwrap();
    let (byte1, body) = c.read_packet()?;
    (byte1 & 0xF0 == 0x30).then_some(body)
}

/// MQTT 5 3.1.2.11.2: the session lives as long as the Session Expiry Interval says,
/// independently of Clean Start (rumqttd alone applies the MQTT 3.1.1 clean-session rule).
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn mqtt5_session_expiry_decides_how_long_a_session_lives() {
    let broker = Broker::start();
    let port = broker.port();

    // Clean Start 0, expiry 0: the session ends with the connection.
    let (_, c) = connect_v5(port, "se-zero", false, 0);
    leave_a_message_behind(&broker, c, "se/zero").await;
    let (present, mut c) = connect_v5(port, "se-zero", false, 0);
    assert!(!present, "expiry 0: no session after the connection ended");
    assert!(
        next_publish_payload(&mut c).is_none(),
        "expiry 0: nothing was queued"
    );

    // Clean Start 1, expiry 300: a fresh session that outlives the connection.
    let (present, c) = connect_v5(port, "se-long", true, 300);
    assert!(!present);
    leave_a_message_behind(&broker, c, "se/long").await;
    let (present, mut c) = connect_v5(port, "se-long", false, 300);
    assert!(present, "expiry 300: the session is resumed");
    assert!(
        next_publish_payload(&mut c).is_some(),
        "the offline message is delivered"
    );

    // Expiry 1 s: gone after 2.5 s offline.
    let (_, c) = connect_v5(port, "se-short", false, 1);
    leave_a_message_behind(&broker, c, "se/short").await;
    tokio::time::sleep(Duration::from_millis(2500)).await;
    let (present, mut c) = connect_v5(port, "se-short", false, 1);
    assert!(!present, "expired session resumed");
    assert!(next_publish_payload(&mut c).is_none());
}

/// MQTT 5 3.14.2.2.2: the Session Expiry Interval of DISCONNECT replaces CONNECT's; after
/// a CONNECT with 0 a non-zero one is a Protocol Error [MQTT-3.14.2-2] (DISCONNECT 0x82).
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn disconnect_replaces_the_session_expiry() {
    let broker = Broker::start();
    let port = broker.port();

    // CONNECT 1 s, DISCONNECT 5 s: still there after 3 s, with what was published.
    let (_, c) = connect_v5(port, "se-longer", false, 1);
    leave_a_message_behind_with(&broker, c, "se/longer", &disconnect_with_expiry(5)).await;
    tokio::time::sleep(Duration::from_millis(2700)).await;
    let (present, mut c) = connect_v5(port, "se-longer", false, 1);
    assert!(present, "DISCONNECT's 5 s replaced CONNECT's 1 s");
    let body = next_publish_payload(&mut c).expect("the message published while offline");
    assert!(body.ends_with(b"while offline"));
    c.send(&disconnect_with_expiry(0));
    assert!(c.closed_by_broker());

    // CONNECT 300 s, DISCONNECT 0: the session ends with the connection.
    let (_, c) = connect_v5(port, "se-shorter", false, 300);
    leave_a_message_behind_with(&broker, c, "se/shorter", &disconnect_with_expiry(0)).await;
    let (present, mut c) = connect_v5(port, "se-shorter", false, 300);
    assert!(!present, "DISCONNECT's 0 ended the session at once");
    assert!(next_publish_payload(&mut c).is_none(), "nothing was queued");

    // CONNECT 0, DISCONNECT 5: a protocol error, answered with DISCONNECT 0x82, and the
    // session still ends with the connection.
    for clean in [true, false] {
        let (_, mut c) = connect_v5(port, "se-zero-then-five", clean, 0);
        c.send(&disconnect_with_expiry(5));
        let (byte1, body) = c.read_packet().expect("DISCONNECT from the server");
        assert_eq!((byte1, body[0]), (0xE0, 0x82), "Protocol Error");
        assert!(c.closed_by_broker());
        let (present, _c) = connect_v5(port, "se-zero-then-five", false, 0);
        assert!(!present, "no session kept after CONNECT's expiry 0");
    }
}

/// Reads PUBLISH packets for `within`: (RETAIN flag, payload) of each.
fn publishes_within(c: &mut RawClient, within: Duration) -> Vec<(bool, Vec<u8>)> {
    c.stream.set_read_timeout(Some(within)).unwrap();
    let mut got = Vec::new();
    while let Some((byte1, body)) = c.read_packet() {
        if byte1 & 0xF0 != 0x30 {
            continue;
        }
        let topic_len = u16::from_be_bytes([body[0], body[1]]) as usize;
        let mut at = 2 + topic_len;
        if (byte1 >> 1) & 3 > 0 {
            let [hi, lo] = [body[at], body[at + 1]];
            c.send(&[0x40, 0x02, hi, lo]);
            at += 2;
        }
        let props = body[at] as usize;
        got.push((byte1 & 1 == 1, body[at + 1 + props..].to_vec()));
    }
    got
}

/// No Local [MQTT-3.8.3-3], Retain As Published [MQTT-3.3.1-12] and Retain Handling 2
/// [MQTT-3.3.1-11]: subscription options rumqttd's router ignores, applied by fbbus.
#[test]
fn mqtt5_subscription_options_are_honoured() {
    let broker = Broker::start();
    let port = broker.port();
    // A retained message is already there.
    let mut retainer = RawClient::connect(port);
    assert_eq!(
        retainer.handshake(&raw::Connect {
            version: 5,
            client_id: "retainer",
            ..Default::default()
        }),
        0
    );
    let mut retained = raw::publish_v5("opt/t", None, 0, 0, b"kept");
    retained[0] |= 1; // RETAIN
    retainer.send(&retained);
    // Routed before anyone subscribes: the router answers a connection's PINGREQ after
    // the packets it sent before.
    retainer.send(&raw::packet(0xC0, &[]));
    assert_eq!(retainer.read_packet().expect("PINGRESP").0, 0xD0);

    let (_, mut c) = connect_v5(port, "options", true, 0);
    // No Local + Retain As Published + Retain Handling 2 on one filter.
    // Retain Handling 2 (bits 4-5), Retain As Published (bit 3), No Local (bit 2), QoS 0.
    c.send(&raw::subscribe_with_options(1, "opt/#", 0b0010_1100));
    assert_eq!(c.read_packet().expect("SUBACK").0, 0x90);
    c.send(&raw::publish_v5("opt/own", None, 0, 0, b"mine"));
    let mut live = raw::publish_v5("opt/t", None, 0, 0, b"live retained");
    live[0] |= 1;
    retainer.send(&live);
    retainer.send(&raw::publish_v5("opt/t", None, 0, 0, b"live plain"));

    let got = publishes_within(&mut c, Duration::from_millis(800));
    let payloads: Vec<&[u8]> = got.iter().map(|(_, p)| &p[..]).collect();
    assert!(
        !payloads.contains(&&b"kept"[..]),
        "Retain Handling 2: no retained message at subscribe"
    );
    assert!(
        !payloads.contains(&&b"mine"[..]),
        "No Local: own publication came back"
    );
    assert_eq!(
        got,
        [
            (true, b"live retained".to_vec()),
            (false, b"live plain".to_vec())
        ],
        "Retain As Published keeps RETAIN on a live delivery, and only where it was set"
    );
}

/// [MQTT-3.3.1-1] [MQTT-4.4.0-1]: a QoS 1 delivery the client never acknowledged is sent
/// again when the session resumes, with DUP=1; a new delivery after it has DUP=0.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn unacknowledged_deliveries_are_resent_with_dup_on_resume() {
    let broker = Broker::start();
    let port = broker.port();
    let (_, mut c) = connect_v5(port, "dup-sub", false, 300);
    let mut sub = raw::subscribe(5, 1, &["dup/t"]);
    *sub.last_mut().unwrap() = 1;
    c.send(&sub);
    assert_eq!(c.read_packet().expect("SUBACK").0, 0x90);
    let publisher = V4::connect(port, "dup-pub", None).await.unwrap();
    publisher
        .client
        .publish("dup/t", rumqttc::QoS::AtLeastOnce, false, "once")
        .await
        .unwrap();
    c.stream
        .set_read_timeout(Some(Duration::from_secs(5)))
        .unwrap();
    let (first, body) = c.read_packet().expect("the delivery");
    assert_eq!(first & 0xF6, 0x32, "a QoS 1 PUBLISH");
    assert_eq!(first & 0x08, 0, "first delivery with DUP=0");
    assert!(publish_pkid(&body) > 0);
    // Gone without acknowledging it.
    c.send(&raw::DISCONNECT);
    assert!(c.closed_by_broker());

    let (present, mut c) = connect_v5(port, "dup-sub", false, 300);
    assert!(present, "session present");
    c.stream
        .set_read_timeout(Some(Duration::from_secs(5)))
        .unwrap();
    let (again, body) = c.read_packet().expect("the redelivery");
    assert_eq!(again & 0xF0, 0x30);
    assert_eq!(again & 0x08, 0x08, "re-sent with DUP=1");
    assert_eq!(&body[2..7], b"dup/t");
    let id = publish_pkid(&body);
    c.send(&raw::packet(0x40, &id.to_be_bytes()));
    publisher
        .client
        .publish("dup/t", rumqttc::QoS::AtLeastOnce, false, "new")
        .await
        .unwrap();
    let (fresh, _) = c.read_packet().expect("a new delivery");
    assert_eq!(fresh & 0x08, 0, "a new delivery has DUP=0");
    // End the session.
    c.send(&raw::DISCONNECT);
    connect_v5(port, "dup-sub", true, 0);
}

/// The packet id of a PUBLISH at QoS 1 or 2, from its body.
fn publish_pkid(body: &[u8]) -> u16 {
    let topic_len = u16::from_be_bytes([body[0], body[1]]) as usize;
    u16::from_be_bytes([body[2 + topic_len], body[3 + topic_len]])
}

/// An MQTT 5 PUBLISH at QoS 1 or 2 on `topic`: (DUP, packet id, payload).
fn delivery(byte1: u8, body: &[u8], topic: &str) -> (bool, u16, Vec<u8>) {
    assert_eq!(byte1 & 0xF0, 0x30, "a PUBLISH, got {byte1:#04x}");
    let topic_len = u16::from_be_bytes([body[0], body[1]]) as usize;
    assert_eq!(&body[2..2 + topic_len], topic.as_bytes());
    let props_at = 4 + topic_len;
    let props_len = body[props_at] as usize; // below 128 here: one varint byte
    let payload = body[props_at + 1 + props_len..].to_vec();
    (byte1 & 0x08 != 0, publish_pkid(body), payload)
}

/// The next packet, which must be a PUBLISH on `topic`: (DUP, packet id, payload).
fn read_delivery(c: &mut RawClient, topic: &str) -> (bool, u16, Vec<u8>) {
    let (byte1, body) = c.read_packet().expect("a delivery");
    delivery(byte1, &body, topic)
}

/// Answers a QoS 2 delivery: PUBREC, the broker's PUBREL for the same id, PUBCOMP.
fn complete_qos2(c: &mut RawClient, pkid: u16) {
    c.send(&raw::packet(0x50, &pkid.to_be_bytes()));
    let (byte1, body) = c.read_packet().expect("PUBREL");
    assert_eq!(
        (byte1, &body[..2]),
        (0x62, &pkid.to_be_bytes()[..]),
        "PUBREL {pkid}"
    );
    c.send(&raw::packet(0x70, &pkid.to_be_bytes()));
}

/// [MQTT-4.4.0-1] [MQTT-2.2.1-3]: re-sent deliveries keep their original packet ids even
/// when the client acknowledged earlier ones (rumqttd's router numbers every connection's
/// deliveries from 1 again), a pending PUBREL is re-sent under its id, and no new delivery
/// takes an id whose exchange is still open.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn resent_deliveries_keep_their_packet_ids_and_open_ids_stay_taken() {
    let broker = Broker::start();
    let port = broker.port();
    let (_, mut c) = connect_v5(port, "ids-sub", false, 300);
    c.stream
        .set_read_timeout(Some(Duration::from_secs(5)))
        .unwrap();
    let mut sub = raw::subscribe(5, 1, &["ids/t"]);
    *sub.last_mut().unwrap() = 2;
    c.send(&sub);
    assert_eq!(c.read_packet().expect("SUBACK").0, 0x90);
    let publisher = V4::connect(port, "ids-pub", None).await.unwrap();
    let publish = |payload: &'static str| {
        let client = publisher.client.clone();
        async move {
            client
                .publish("ids/t", rumqttc::QoS::ExactlyOnce, false, payload)
                .await
                .unwrap()
        }
    };
    for p in ["a", "b", "c"] {
        publish(p).await;
    }
    let mut first = Vec::new();
    for _ in 0..3 {
        first.push(read_delivery(&mut c, "ids/t"));
    }
    let ids: Vec<u16> = first.iter().map(|d| d.1).collect();
    assert_eq!(first[0].2, b"a");
    // "a" is received (PUBREC) and released (PUBREL), never completed; "b" and "c" are
    // not even received.
    c.send(&raw::packet(0x50, &ids[0].to_be_bytes()));
    let (byte1, body) = c.read_packet().expect("PUBREL");
    assert_eq!((byte1, &body[..2]), (0x62, &ids[0].to_be_bytes()[..]));
    c.send(&raw::DISCONNECT);
    assert!(c.closed_by_broker());

    let (present, mut c) = connect_v5(port, "ids-sub", false, 300);
    assert!(present, "session present");
    c.stream
        .set_read_timeout(Some(Duration::from_secs(5)))
        .unwrap();
    let mut pubrels = Vec::new();
    let mut resent = Vec::new();
    while pubrels.len() + resent.len() < 3 {
        let (byte1, body) = c.read_packet().expect("the resumed session's packets");
        if byte1 == 0x62 {
            pubrels.push(u16::from_be_bytes([body[0], body[1]]));
        } else {
            resent.push(delivery(byte1, &body, "ids/t"));
        }
    }
    assert_eq!(pubrels, [ids[0]], "the PUBREL again, under its id");
    assert_eq!(
        resent,
        [(true, ids[1], b"b".to_vec()), (true, ids[2], b"c".to_vec())],
        "b and c again, with DUP=1 and their original ids"
    );

    // A new message while all three exchanges are open takes none of their ids.
    publish("d").await;
    let (dup, d_id, payload) = read_delivery(&mut c, "ids/t");
    assert_eq!((dup, payload.as_slice()), (false, &b"d"[..]));
    assert!(
        !ids.contains(&d_id),
        "{d_id} is one of the open ids {ids:?}"
    );

    // Every exchange completes under the client's ids, and the session goes on.
    c.send(&raw::packet(0x70, &ids[0].to_be_bytes()));
    for id in [ids[1], ids[2], d_id] {
        complete_qos2(&mut c, id);
    }
    publish("e").await;
    let (dup, e_id, payload) = read_delivery(&mut c, "ids/t");
    assert_eq!((dup, payload.as_slice()), (false, &b"e"[..]));
    complete_qos2(&mut c, e_id);
    // End the session.
    c.send(&raw::DISCONNECT);
    connect_v5(port, "ids-sub", true, 0);
}

/// Retained PUBLISHes arriving within `within` (payloads), after a SUBSCRIBE.
async fn retained_within(c: &mut V5, within: Duration) -> Vec<Vec<u8>> {
    let deadline = tokio::time::Instant::now() + within;
    let mut got = Vec::new();
    while let Some(p) = c.next_publish(deadline - tokio::time::Instant::now()).await {
        if p.retain {
            got.push(p.payload.to_vec());
        }
    }
    got
}

/// Subscribes `c` to `filter` with a Retain Handling, waiting for the SUBACK.
async fn subscribe_rh(c: &mut V5, filter: &str, rule: p5::RetainForwardRule) {
    let mut f = p5::Filter::new(filter, rumqttc::v5::mqttbytes::QoS::AtLeastOnce);
    f.retain_forward_rule = rule;
    c.client.subscribe_many([f]).await.unwrap();
    c.next(WAIT, |p| match p {
        p5::Packet::SubAck(s) => Some(s.return_codes),
        _ => None,
    })
    .await
    .expect("SUBACK");
}

/// Retain Handling [MQTT-3.3.1-9..11], [MQTT-3.8.4-4]: 0 sends the retained messages on
/// every SUBSCRIBE, a repeated one of an existing filter too (conformance row 7a); 1 only
/// when the subscription is new (7b); 2 never (7c). Replacing the subscription loses no
/// live message.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn retain_handling_decides_the_retained_messages_of_every_subscribe() {
    use p5::RetainForwardRule::{Never, OnEverySubscribe, OnNewSubscribe};
    let broker = Broker::start();
    let port = broker.port();
    let publisher = V5::connect(port, "rh-publisher", None).await.unwrap();
    publisher
        .client
        .publish(
            "rh/t",
            rumqttc::v5::mqttbytes::QoS::AtLeastOnce,
            true,
            "kept",
        )
        .await
        .unwrap();
    // The retained message is stored once a new subscriber gets it.
    let mut probe = V5::connect(port, "rh-probe", None).await.unwrap();
    subscribe_rh(&mut probe, "rh/#", OnEverySubscribe).await;
    let stored = probe
        .next_publish(WAIT)
        .await
        .expect("the retained message");
    assert!(stored.retain && &stored.payload[..] == b"kept");

    let window = Duration::from_millis(800);
    for (rule, expected) in [
        (OnEverySubscribe, (1, 1)),
        (OnNewSubscribe, (1, 0)),
        (Never, (0, 0)),
    ] {
        let mut c = V5::connect(port, &format!("rh-{rule:?}"), None)
            .await
            .unwrap();
        subscribe_rh(&mut c, "rh/#", rule.clone()).await;
        let first = retained_within(&mut c, window).await.len();
        subscribe_rh(&mut c, "rh/#", rule.clone()).await;
        let second = retained_within(&mut c, window).await.len();
        assert_eq!(
            (first, second),
            expected,
            "{rule:?}: retained copies on the first/second SUBSCRIBE"
        );
        // The subscription was replaced, not lost: live messages still arrive, once.
        let live = format!("live {rule:?}");
        publisher
            .client
            .publish(
                "rh/live",
                rumqttc::v5::mqttbytes::QoS::AtLeastOnce,
                false,
                live.clone(),
            )
            .await
            .unwrap();
        let mut got = Vec::new();
        while let Some(p) = c.next_publish(window).await {
            got.push(String::from_utf8_lossy(&p.payload).into_owned());
        }
        assert_eq!(
            got,
            [live],
            "{rule:?}: live delivery after the repeated SUBSCRIBE"
        );
    }
}

/// MQTT 3.1.1 [MQTT-3.8.4-3]: a repeated SUBSCRIBE re-sends the retained messages.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn mqtt311_repeated_subscribe_resends_retained_messages() {
    let broker = Broker::start();
    let port = broker.port();
    let mut publisher = V4::connect(port, "rs-publisher", None).await.unwrap();
    publisher
        .client
        .publish("rs/t", rumqttc::QoS::AtLeastOnce, true, "kept")
        .await
        .unwrap();
    // Retained once acknowledged (with persistence on, the PUBACK follows the store's write).
    publisher
        .next(WAIT, |p| {
            matches!(p, rumqttc::Packet::PubAck(_)).then_some(())
        })
        .await
        .expect("PUBACK");
    let mut c = V4::connect(port, "rs-sub", None).await.unwrap();
    for round in ["first", "second"] {
        c.subscribe("rs/#").await;
        let m = c.next_publish(WAIT).await;
        assert!(
            m.as_ref()
                .is_some_and(|m| m.retain && &m.payload[..] == b"kept"),
            "{round} SUBSCRIBE: retained message not sent ({m:?})"
        );
    }
}

/// [MQTT-3.8.4-3]: a repeated SUBSCRIBE of the same filter replaces the subscription, its
/// maximum QoS included (rumqttd 0.20 kept the first one's).
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_repeated_subscribe_replaces_the_maximum_qos() {
    use rumqttc::QoS::{AtLeastOnce, AtMostOnce, ExactlyOnce};
    let broker = Broker::start();
    let mut sub = V4::connect(broker.port(), "resub", None).await.unwrap();
    let publisher = V4::connect(broker.port(), "resub-pub", None).await.unwrap();
    for (round, qos) in [AtMostOnce, AtLeastOnce, ExactlyOnce, AtMostOnce]
        .into_iter()
        .enumerate()
    {
        sub.client.subscribe("rq/t", qos).await.unwrap();
        sub.next(WAIT, |p| {
            matches!(p, rumqttc::Packet::SubAck(_)).then_some(())
        })
        .await
        .unwrap();
        publisher
            .client
            .publish("rq/t", ExactlyOnce, false, format!("{round}"))
            .await
            .unwrap();
        let m = sub
            .next_publish(WAIT)
            .await
            .unwrap_or_else(|| panic!("round {round}: nothing delivered"));
        assert_eq!(m.payload[..], *format!("{round}").as_bytes());
        assert_eq!(
            m.qos, qos,
            "round {round}: delivered at the latest subscription's QoS"
        );
        assert!(sub.next_publish(Duration::from_millis(300)).await.is_none());
    }
}

/// [MQTT-3.8.4-3] (3.1.1), [MQTT-3.3.1-9] (5, Retain Handling 0): every SUBSCRIBE gets
/// the retained messages, also a second one that arrives (here: in the same TCP write)
/// before the broker sent the first one's.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn back_to_back_subscribes_each_get_the_retained_messages() {
    let broker = Broker::start();
    let publisher = V4::connect(broker.port(), "bb-publisher", None)
        .await
        .unwrap();
    publisher
        .client
        .publish("bb/t", rumqttc::QoS::AtLeastOnce, true, "kept")
        .await
        .unwrap();
    // Routed (acknowledged) before anyone subscribes, else it is delivered live.
    let mut publisher = publisher;
    publisher
        .next(WAIT, |p| {
            matches!(p, rumqttc::Packet::PubAck(_)).then_some(())
        })
        .await
        .expect("PUBACK");
    // Stored once a subscriber got it.
    let mut probe = V4::connect(broker.port(), "bb-probe", None).await.unwrap();
    probe.subscribe("bb/#").await;
    assert!(probe.next_publish(WAIT).await.is_some_and(|m| m.retain));

    let mut c = RawClient::connect(broker.port());
    assert_eq!(
        c.handshake(&raw::Connect {
            client_id: "bb-sub",
            ..Default::default()
        }),
        0
    );
    c.stream
        .set_read_timeout(Some(Duration::from_millis(800)))
        .unwrap();
    let twice = [
        raw::subscribe(4, 1, &["bb/#"]),
        raw::subscribe(4, 2, &["bb/#"]),
    ]
    .concat();
    c.send(&twice);
    let (mut subacks, mut retained) = (0, 0);
    while let Some((byte1, body)) = c.read_packet() {
        match byte1 & 0xF0 {
            0x90 => subacks += 1,
            0x30 if byte1 & 0x01 == 1 && body.ends_with(b"kept") => retained += 1,
            _ => {}
        }
    }
    assert_eq!((subacks, retained), (2, 2), "(SUBACKs, retained copies)");
}

/// The Server Keep Alive property of a CONNACK body, if any (MQTT 5, 3.2.2.3).
fn server_keep_alive(connack: &[u8]) -> Option<u16> {
    let mut i = 2;
    let (mut len, mut shift) = (0usize, 0);
    loop {
        let b = connack[i];
        i += 1;
        len |= ((b & 0x7f) as usize) << shift;
        shift += 7;
        if b & 0x80 == 0 {
            break;
        }
    }
    let end = i + len;
    let u16_at = |at: usize| u16::from_be_bytes([connack[at], connack[at + 1]]);
    while i < end {
        let id = connack[i];
        i += 1;
        let size = match id {
            0x13 => return Some(u16_at(i)),
            0x24 | 0x25 | 0x28 | 0x29 | 0x2A => 1,
            0x21 | 0x22 => 2,
            0x11 | 0x27 => 4,
            0x12 | 0x1A | 0x1C | 0x1F | 0x15 | 0x16 => 2 + u16_at(i) as usize,
            0x26 => {
                let key = 2 + u16_at(i) as usize;
                key + 2 + u16_at(i + key) as usize
            }
            other => panic!("unexpected CONNACK property {other:#x}"),
        };
        i += size;
    }
    None
}

/// `max_keep_alive_s`: an MQTT 5 client that asks for no keep-alive, or a longer one, is
/// told the maximum as Server Keep Alive and is disconnected after 1.5 x that of silence
/// [MQTT-3.2.2-21]; one within the maximum keeps its own. An MQTT 3.1.1 client cannot be
/// told, so its keep-alive 0 still means none.
#[test]
fn mqtt5_clients_are_held_to_the_maximum_keep_alive() {
    let broker = Broker::start_with(
        Options {
            extra: "max_keep_alive_s = 1\n".into(),
            ..Options::default()
        },
        |_| {},
    );
    let connect = |version: u8, id: &str, keep_alive: u16| {
        let mut c = RawClient::connect(broker.port());
        c.send(
            &raw::Connect {
                version,
                client_id: id,
                keep_alive,
                ..Default::default()
            }
            .bytes(),
        );
        let (byte1, body) = c.read_packet().expect("CONNACK");
        assert_eq!((byte1, body[1]), (0x20, 0), "CONNACK success");
        (c, body)
    };
    let (mut silent_v5, connack) = connect(5, "ka-v5-zero", 0);
    assert_eq!(server_keep_alive(&connack), Some(1));
    let (_, connack) = connect(5, "ka-v5-long", 600);
    assert_eq!(server_keep_alive(&connack), Some(1));
    let (_, connack) = connect(5, "ka-v5-within", 1);
    assert_eq!(server_keep_alive(&connack), None);
    let (mut silent_v4, _) = connect(4, "ka-v4-zero", 0);

    let started = std::time::Instant::now();
    silent_v5
        .stream
        .set_read_timeout(Some(Duration::from_secs(5)))
        .unwrap();
    assert!(silent_v5.closed_by_broker());
    let closed_after = started.elapsed();
    assert!(
        closed_after >= Duration::from_millis(1_200) && closed_after < Duration::from_secs(4),
        "closed after {closed_after:?}"
    );
    // The 3.1.1 client, silent just as long, is still served.
    silent_v4.send(&raw::PINGREQ);
    assert_eq!(silent_v4.read_packet().expect("PINGRESP").0, 0xD0);
}

/// A client need not wait for CONNACK [MQTT-3.1.4-5 allows sending before it]: packets in
/// the same write as CONNECT are handled at once. They used to wait for the socket's
/// next bytes, so CONNECT + PUBLISH + DISCONNECT in one write delivered nothing and the
/// connection hung until keep-alive (found by `fbbus-loadtest churn`, kind `pipelined`).
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn packets_sent_with_connect_are_handled_at_once() {
    let broker = Broker::start();
    let mut sub = V4::connect(broker.port(), "pipe-sub", None).await.unwrap();
    sub.subscribe("pipe/#").await;

    let mut c = RawClient::connect(broker.port());
    let mut bytes = raw::Connect {
        client_id: "pipe-pub",
        ..Default::default()
    }
    .bytes();
    bytes.extend(raw::publish_qos0("pipe/t", b"with connect"));
    bytes.extend(raw::packet(0xE0, &[])); // DISCONNECT
    c.send(&bytes);

    let m = sub.next_publish(WAIT).await.expect("the pipelined PUBLISH");
    assert_eq!(&m.payload[..], b"with connect");
    // DISCONNECT handled too: the broker closes at once (a read timeout would also end
    // `closed_by_broker`, hence the clock: keep-alive is 60 s).
    let started = std::time::Instant::now();
    c.stream
        .set_read_timeout(Some(Duration::from_secs(20)))
        .unwrap();
    assert!(c.closed_by_broker());
    assert!(
        started.elapsed() < Duration::from_secs(10),
        "the connection stayed open"
    );
}

/// [MQTT-3.1.2-3]: a CONNECT with the reserved flag set is refused: the connection is
/// closed without CONNACK and counted as malformed (found by `fbbus-loadtest mutate`: 676
/// of 681 were accepted).
#[test]
fn a_connect_with_the_reserved_flag_set_is_refused() {
    let broker = Broker::start();
    for version in [4, 5] {
        let mut bytes = raw::Connect {
            version,
            client_id: "reserved",
            ..Default::default()
        }
        .bytes();
        // Fixed header (2 bytes), protocol name (6), level (1), then the flags.
        assert_eq!(&bytes[2..8], b"\0\x04MQTT");
        bytes[9] |= 1;
        let mut c = RawClient::connect(broker.port());
        c.send(&bytes);
        assert_eq!(c.read_packet(), None, "v{version}: no CONNACK, closed");
    }
    assert!(broker.wait_metric(r#"fbbus_connects_refused_total{reason="malformed"}"#, 2.0) >= 2.0);
    // A well-formed one still connects.
    let mut c = RawClient::connect(broker.port());
    assert_eq!(
        c.handshake(&raw::Connect {
            client_id: "fine",
            ..Default::default()
        }),
        0
    );
}

/// Client ids that would forge a topic level, a `$` name, the broker's own links
/// (`fbbus:`) or control characters in the log are refused with CONNACK 2 (identifier
/// rejected); an ordinary one, multi-byte included, is accepted.
#[test]
fn unusable_client_ids_are_refused() {
    let broker = Broker::start();
    let handshake = |client_id: &str| {
        RawClient::connect(broker.port()).handshake(&raw::Connect {
            client_id,
            ..Default::default()
        })
    };
    for bad in [
        "a/b",
        "a+",
        "#",
        "$SYS",
        "fbbus:probe",
        "line\nbreak",
        "nul\0",
        "bell\u{7}",
    ] {
        assert_eq!(handshake(bad), 2, "{bad:?}");
    }
    for good in ["plc-1", "Förderband_1", "日本"] {
        assert_eq!(handshake(good), 0, "{good:?}");
    }
}

/// Server-to-client topic aliases (MQTT 5 3.3.2.3.4, policy in `session/aliases.rs`): a
/// client announcing Topic Alias Maximum 2 gets topic + alias on a topic's first delivery,
/// an empty topic + the alias after; a third topic goes with its full name and no alias;
/// a client that announced none never sees an alias; a new connection starts over.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn deliveries_use_topic_aliases_the_client_allows() {
    let broker = Broker::start();
    let port = broker.port();
    let subscriber = |id: &'static str, alias_max: Option<u16>| {
        let mut c = RawClient::connect(port);
        assert_eq!(
            c.handshake(&raw::Connect {
                version: 5,
                client_id: id,
                clean: false,
                session_expiry: Some(60),
                topic_alias_max: alias_max,
                ..Default::default()
            }),
            0
        );
        c
    };
    let mut aliased = subscriber("aliased", Some(2));
    let mut plain = subscriber("plain", None);
    for c in [&mut aliased, &mut plain] {
        c.send(&raw::subscribe(5, 1, &["ta/#"]));
        assert_eq!(c.read_packet().expect("SUBACK").0, 0x90);
    }
    let publisher = V4::connect(port, "ta-pub", None).await.unwrap();
    let sends = ["ta/a", "ta/a", "ta/b", "ta/c", "ta/b", "ta/a"];
    for (i, topic) in sends.iter().enumerate() {
        publisher
            .client
            .publish(*topic, rumqttc::QoS::AtMostOnce, false, vec![i as u8])
            .await
            .unwrap();
    }
    let alias = |n: u16| {
        let mut p = vec![0x23];
        p.extend_from_slice(&n.to_be_bytes());
        p
    };
    let expected: Vec<(&[u8], Vec<u8>)> = vec![
        (b"ta/a", alias(1)),
        (b"", alias(1)),
        (b"ta/b", alias(2)),
        (b"ta/c", vec![]),
        (b"", alias(2)),
        (b"", alias(1)),
    ];
    for (i, (topic, props)) in expected.iter().enumerate() {
        let (byte1, body) = aliased.read_packet().expect("delivery");
        let (t, _, p, payload) = raw::parse_publish_v5(byte1, &body);
        assert_eq!(
            (&t[..], &p, &payload[..]),
            (*topic, props, &[i as u8][..]),
            "delivery {i}"
        );
        let (byte1, body) = plain.read_packet().expect("delivery");
        let (t, _, p, _) = raw::parse_publish_v5(byte1, &body);
        assert_eq!((&t[..], &p[..]), (sends[i].as_bytes(), &[][..]), "no alias");
    }
    // Resumed session, new connection: aliases start over.
    drop(aliased);
    tokio::time::sleep(Duration::from_millis(200)).await;
    let mut again = subscriber("aliased", Some(2));
    publisher
        .client
        .publish("ta/b", rumqttc::QoS::AtMostOnce, false, vec![9])
        .await
        .unwrap();
    let (byte1, body) = again.read_packet().expect("delivery after reconnect");
    let (t, _, p, _) = raw::parse_publish_v5(byte1, &body);
    assert_eq!((&t[..], p), (&b"ta/b"[..], alias(1)));
}

/// MQTT 5 SUBSCRIBE of one filter with a Subscription Identifier.
fn subscribe_with_id(pkid: u16, filter: &str, qos: u8, id: u8) -> Vec<u8> {
    let mut body = pkid.to_be_bytes().to_vec();
    body.extend_from_slice(&[2, 0x0B, id]);
    body.extend_from_slice(&(filter.len() as u16).to_be_bytes());
    body.extend_from_slice(filter.as_bytes());
    body.push(qos);
    raw::packet(0x82, &body)
}

/// A client whose subscriptions overlap gets one copy of a message matching several,
/// with every matching subscription's identifier [MQTT-3.3.4-3] [MQTT-3.3.4-4], at the
/// highest QoS [MQTT-3.3.4-2] (`session/copies.rs`).
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn overlapping_subscriptions_get_one_copy_with_every_identifier() {
    let broker = Broker::start();
    let mut c = RawClient::connect(broker.port());
    assert_eq!(
        c.handshake(&raw::Connect {
            version: 5,
            client_id: "overlap",
            ..Default::default()
        }),
        0
    );
    for (pkid, filter, qos, id) in [
        (1, "a/+/c", 1, 1),
        (2, "a/#", 1, 2),
        (3, "q/+", 0, 3),
        (4, "q/#", 1, 4),
    ] {
        c.send(&subscribe_with_id(pkid, filter, qos, id));
        assert_eq!(c.read_packet().expect("SUBACK").0, 0x90);
    }
    let publisher = V4::connect(broker.port(), "overlap-pub", None)
        .await
        .unwrap();
    for topic in ["a/b/c", "q/x", "a/x"] {
        publisher
            .client
            .publish(topic, rumqttc::QoS::AtLeastOnce, false, topic)
            .await
            .unwrap();
    }
    let mut got = Vec::new();
    c.stream
        .set_read_timeout(Some(Duration::from_millis(800)))
        .unwrap();
    while let Some((byte1, body)) = c.read_packet() {
        if byte1 & 0xF0 != 0x30 {
            continue;
        }
        let (topic, pkid, props, _) = raw::parse_publish_v5(byte1, &body);
        if pkid > 0 {
            c.send(&[0x40, 0x02, (pkid >> 8) as u8, pkid as u8]);
        }
        got.push((String::from_utf8(topic).unwrap(), (byte1 >> 1) & 3, props));
    }
    assert_eq!(
        got,
        [
            ("a/b/c".to_owned(), 1, vec![0x0B, 1, 0x0B, 2]),
            ("q/x".to_owned(), 1, vec![0x0B, 3, 0x0B, 4]),
            ("a/x".to_owned(), 1, vec![0x0B, 2]),
        ],
        "one copy each, every matching subscription's identifier, the highest QoS"
    );

    // The router hands over the copies of one message together (`Router::consume`),
    // so a lower-QoS copy never goes out ahead of the higher one: CI once saw q/x's QoS 0
    // copy from `q/+` sent, then its QoS 1 copy from `q/#`, when the router announced
    // each filter's forwards on their own. One message at a time keeps the in-flight
    // window (the one documented exception) out of it.
    const ROUNDS: usize = 1000;
    c.stream
        .set_read_timeout(Some(Duration::from_secs(5)))
        .unwrap();
    let mut lower = 0;
    for round in 0..ROUNDS {
        let payload = format!("{round}");
        publisher
            .client
            .publish("q/x", rumqttc::QoS::AtLeastOnce, false, payload.clone())
            .await
            .unwrap();
        loop {
            let (byte1, body) = c.read_packet().expect("a copy of each message");
            if byte1 & 0xF0 != 0x30 {
                continue;
            }
            let (_, pkid, _, data) = raw::parse_publish_v5(byte1, &body);
            if pkid > 0 {
                c.send(&[0x40, 0x02, (pkid >> 8) as u8, pkid as u8]);
            }
            if (byte1 >> 1) & 3 == 0 {
                lower += 1;
            } else if data == payload.as_bytes() {
                break;
            }
        }
    }
    assert_eq!(lower, 0, "QoS 0 copies sent beside {ROUNDS} QoS 1 ones");
}

/// A new subscription gets every retained message it matches, not only as many as the
/// router sends in one round (`router_max_outgoing_packets`, 1,000): a dashboard of a line
/// with several thousand retained FB values used to get the first 1,000.
#[test]
fn a_new_subscription_gets_every_retained_message_not_only_a_window() {
    use common::raw::{self, Connect, RawClient};
    const N: usize = 2500;
    let broker = Broker::start();
    let mut p = RawClient::connect(broker.port());
    assert_eq!(
        p.handshake(&Connect {
            client_id: "many-pub",
            ..Default::default()
        }),
        0
    );
    let mut burst = Vec::new();
    for i in 0..N {
        let mut packet = raw::publish_qos0(&format!("many/{i}"), b"v");
        packet[0] |= 0x01;
        burst.extend_from_slice(&packet);
    }
    p.send(&burst);
    // A round trip on the publisher's connection: everything before it was taken.
    p.send(&raw::PINGREQ);
    assert_eq!(p.read_packet().expect("PINGRESP").0, 0xD0);
    std::thread::sleep(std::time::Duration::from_millis(300));
    let mut s = RawClient::connect(broker.port());
    assert_eq!(
        s.handshake(&Connect {
            client_id: "many-sub",
            ..Default::default()
        }),
        0
    );
    s.send(&raw::subscribe(4, 1, &["many/#"]));
    s.stream
        .set_read_timeout(Some(std::time::Duration::from_secs(2)))
        .unwrap();
    let mut retained = std::collections::BTreeSet::new();
    while let Some((b, body)) = s.read_packet() {
        if b & 0xF0 == 0x30 && b & 0x01 == 1 {
            let n = u16::from_be_bytes([body[0], body[1]]) as usize;
            retained.insert(String::from_utf8_lossy(&body[2..2 + n]).into_owned());
        }
    }
    assert_eq!(retained.len(), N, "every retained message, once");
}

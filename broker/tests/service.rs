//! The broker as a service: one port for MQTT 3.1.1 and 5, real peers, bad input,
//! metrics, configuration refusal, graceful shutdown.

mod common;

use std::process::Command;
use std::time::Duration;

use common::clients::{self, V4, V5, WAIT};
use common::raw::{self, RawClient};
use common::{Broker, Options};

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn v311_and_v5_clients_share_one_port() {
    let broker = Broker::start();
    let mut sub4 = V4::connect(broker.port(), "sub4", None).await.unwrap();
    let mut sub5 = V5::connect(broker.port(), "sub5", None).await.unwrap();
    sub4.subscribe("line/#").await;
    sub5.subscribe("line/#").await;

    let pub5 = V5::connect(broker.port(), "pub5", None).await.unwrap();
    pub5.client
        .publish(
            "line/a",
            rumqttc::v5::mqttbytes::QoS::AtLeastOnce,
            false,
            "from-v5",
        )
        .await
        .unwrap();
    let pub4 = V4::connect(broker.port(), "pub4", None).await.unwrap();
    pub4.client
        .publish("line/b", rumqttc::QoS::AtLeastOnce, false, "from-v4")
        .await
        .unwrap();

    // Two publishers: MQTT orders messages per publisher, not across them.
    let mut got4 = Vec::new();
    let mut got5 = Vec::new();
    for _ in 0..2 {
        let m = sub4.next_publish(WAIT).await.expect("v3.1.1 subscriber");
        got4.push(String::from_utf8(m.payload.to_vec()).unwrap());
        let m = sub5.next_publish(WAIT).await.expect("v5 subscriber");
        got5.push(String::from_utf8(m.payload.to_vec()).unwrap());
    }
    got4.sort();
    got5.sort();
    assert_eq!(got4, ["from-v4", "from-v5"]);
    assert_eq!(got5, ["from-v4", "from-v5"]);
    assert!(broker.metric("fbbus_messages_received_total") >= 2.0);
    assert!(broker.wait_metric("fbbus_messages_sent_total", 4.0) >= 4.0);
    assert!(broker.metric("fbbus_bytes_received_total") > 0.0);
    assert!(broker.metric("fbbus_bytes_sent_total") > 0.0);
    assert_eq!(broker.metric("fbbus_connections"), 4.0);
}

#[test]
fn mosquitto_clients_interoperate_on_both_versions() {
    if !common::require("mosquitto_sub") {
        return;
    }
    let broker = Broker::start();
    let port = broker.port().to_string();
    let publish = |version: &str, topic: &str, qos: &str, message: &str| {
        let (ok, _, err) = common::run(
            Command::new("mosquitto_pub")
                .args(["-h", "127.0.0.1", "-p", &port, "-V", version])
                .args(["-t", topic, "-q", qos, "-m", message]),
            Duration::from_secs(10),
        );
        assert!(ok, "mosquitto_pub {version}: {err}");
    };
    for version in ["mqttv311", "mqttv5"] {
        let mut sub = Command::new("mosquitto_sub")
            .args(["-h", "127.0.0.1", "-p", &port, "-V", version])
            .args(["-t", "cell/#", "-W", "20", "-v"])
            .stdout(std::process::Stdio::piped())
            .spawn()
            .unwrap();
        let lines = std::io::BufRead::lines(std::io::BufReader::new(sub.stdout.take().unwrap()));
        let (tx, rx) = std::sync::mpsc::channel();
        std::thread::spawn(move || lines.map_while(Result::ok).for_each(|l| drop(tx.send(l))));

        // Probe until the subscription is in place: then order is defined.
        let subscribed = (0..50).any(|_| {
            publish(version, "cell/probe", "0", "probe");
            rx.recv_timeout(Duration::from_millis(200)).is_ok()
        });
        assert!(
            subscribed,
            "mosquitto_sub never received; log: {}",
            broker.log_text()
        );
        for (topic, qos) in [("cell/1", "0"), ("cell/2", "2")] {
            publish(version, topic, qos, &format!("{version}-{topic}"));
        }
        let received: Vec<String> = rx
            .iter()
            .filter(|l| !l.starts_with("cell/probe"))
            .take(2)
            .collect();
        let _ = sub.kill();
        let _ = sub.wait();
        assert_eq!(
            received,
            [
                format!("cell/1 {version}-cell/1"),
                format!("cell/2 {version}-cell/2")
            ],
            "log: {}",
            broker.log_text()
        );
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn publish_then_disconnect_in_one_write_is_delivered() {
    let broker = Broker::start();
    let mut sub = V4::connect(broker.port(), "sub", None).await.unwrap();
    sub.subscribe("burst").await;
    for i in 0..5 {
        let mut c = RawClient::connect(broker.port());
        assert_eq!(
            c.handshake(&raw::Connect {
                client_id: &format!("burst-{i}"),
                ..Default::default()
            }),
            0
        );
        let mut bytes = raw::publish_qos0("burst", b"last words");
        bytes.extend_from_slice(&raw::DISCONNECT);
        c.send(&bytes);
        let m = sub
            .next_publish(WAIT)
            .await
            .expect("the PUBLISH before DISCONNECT");
        assert_eq!(m.payload, "last words");
    }
    // A normal disconnect logs no error. The router gets the publication's batch and the
    // connection's end as two events and handled both on the first; it logged the second
    // as an ERROR ("no-connection id N is already gone"). Once the disconnects are
    // counted, both events were sent to the router; the SUBACK of a later SUBSCRIBE comes
    // after the router handled them.
    broker.wait_metric("fbbus_disconnects_total{reason=\"client\"}", 5.0);
    sub.subscribe("after").await;
    let log = broker.log_text();
    assert!(
        !log.lines().any(|l| l.contains(" ERROR ")),
        "a normal disconnect logged an error:\n{log}"
    );
}

/// A stranger who connects in a loop and sends each time a malformed packet cannot fill
/// the log: the "malformed packet; connection closed" lines share the broker's budget for
/// what outside input causes (`logging::OUTSIDE`, 600 lines a minute), and every one is
/// still counted. Found attacking the broker with random MQTT 5 properties: a line each.
#[test]
fn malformed_packets_from_a_loop_of_connections_stay_within_the_logs_budget() {
    const CONNECTIONS: usize = 700;
    let broker = Broker::start();
    for i in 0..CONNECTIONS {
        let mut c = RawClient::connect(broker.port());
        let client_id = format!("stranger-{i}");
        let connect = raw::Connect {
            client_id: &client_id,
            ..Default::default()
        };
        assert_eq!(c.handshake(&connect), 0, "connection {i} refused");
        // A SUBSCRIBE whose topic length runs past the end of the packet.
        c.send(&[0x82, 0x05, 0x00, 0x01, 0x00, 0x40, b'a']);
    }
    let series = "fbbus_malformed_packets_total";
    assert_eq!(
        broker.wait_metric(series, CONNECTIONS as f64),
        CONNECTIONS as f64
    );
    broker.assert_within_log_budget("malformed packet; connection closed", CONNECTIONS);
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn malformed_packet_closes_only_that_connection() {
    let broker = Broker::start();
    let mut sub = V4::connect(broker.port(), "bystander", None).await.unwrap();
    sub.subscribe("ok").await;

    let mut bad = RawClient::connect(broker.port());
    assert_eq!(
        bad.handshake(&raw::Connect {
            client_id: "bad",
            ..Default::default()
        }),
        0
    );
    // A SUBSCRIBE whose topic length runs past the end of the packet.
    bad.send(&[0x82, 0x05, 0x00, 0x01, 0x00, 0x40, b'a']);
    assert!(bad.closed_by_broker());
    assert_eq!(
        broker.wait_metric("fbbus_malformed_packets_total", 1.0),
        1.0
    );
    assert_eq!(
        broker.wait_metric("fbbus_disconnects_total{reason=\"malformed\"}", 1.0),
        1.0
    );

    // Not MQTT at all, before CONNECT: an HTTP request is named as the WebSocket
    // client it likely is (issue 35), anything else is malformed.
    let mut http = RawClient::connect(broker.port());
    http.send(b"GET / HTTP/1.1\r\nHost: x\r\n\r\n");
    assert!(http.closed_by_broker());
    let series = "fbbus_connects_refused_total{reason=\"websocket_on_mqtt\"}";
    assert!(broker.wait_metric(series, 1.0) >= 1.0);
    let mut noise = RawClient::connect(broker.port());
    noise.send(b"\x01\x02\x03");
    assert!(noise.closed_by_broker());
    assert!(broker.wait_metric("fbbus_connects_refused_total{reason=\"malformed\"}", 1.0) >= 1.0);

    // Everyone else is still served.
    let p = V4::connect(broker.port(), "pub", None).await.unwrap();
    p.client
        .publish("ok", rumqttc::QoS::AtMostOnce, false, "still here")
        .await
        .unwrap();
    assert_eq!(
        sub.next_publish(WAIT).await.expect("delivery").payload,
        "still here"
    );
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn oversized_packet_closes_that_connection_and_is_counted() {
    let broker = Broker::start_with(
        Options {
            extra: "max_packet_bytes = 1024\n".into(),
            ..Default::default()
        },
        |_| {},
    );
    let mut sub = V4::connect(broker.port(), "bystander", None).await.unwrap();
    sub.subscribe("big").await;

    let mut c = RawClient::connect(broker.port());
    assert_eq!(c.handshake(&raw::Connect::default()), 0);
    c.send(&raw::publish_qos0("big", &[7u8; 4096]));
    assert!(c.closed_by_broker());
    assert_eq!(
        broker.wait_metric("fbbus_oversized_packets_total", 1.0),
        1.0
    );
    assert!(sub.next_publish(Duration::from_millis(500)).await.is_none());

    // MQTT 5: the client is told why (DISCONNECT 0x95, packet too large).
    let mut c5 = RawClient::connect(broker.port());
    assert_eq!(
        c5.handshake(&raw::Connect {
            version: 5,
            client_id: "c5",
            ..Default::default()
        }),
        0
    );
    c5.send(&raw::publish_qos0("big", &[7u8; 4096]));
    let (byte1, body) = c5.read_packet().expect("DISCONNECT");
    assert_eq!((byte1, body[0]), (0xE0, 0x95));

    // A packet just under the limit goes through.
    let p = V4::connect(broker.port(), "pub", None).await.unwrap();
    p.client
        .publish("big", rumqttc::QoS::AtMostOnce, false, vec![1u8; 900])
        .await
        .unwrap();
    assert_eq!(
        sub.next_publish(WAIT)
            .await
            .expect("delivery")
            .payload
            .len(),
        900
    );
}

#[test]
fn unsafe_config_is_refused_with_file_key_and_reason() {
    let dir = tempfile::tempdir().unwrap();
    let config = dir.path().join("line.toml");
    std::fs::write(
        &config,
        "[[listener]]\nname = \"plant\"\nbind = \"0.0.0.0:18830\"\n",
    )
    .unwrap();
    for args in [
        vec!["serve", "--config", config.to_str().unwrap()],
        vec!["check-config", config.to_str().unwrap()],
    ] {
        let (ok, _, err) = common::run(
            Command::new(common::fbbus_bin()).args(&args),
            Duration::from_secs(10),
        );
        assert!(
            !ok,
            "{args:?} must refuse a non-loopback listener without passwords"
        );
        assert!(err.contains("line.toml"), "{err}");
        assert!(err.contains("listener[0].bind"), "{err}");
        assert!(err.contains("password_file"), "{err}");
    }

    std::fs::write(&config, "[broker]\nmax_conections = 10\n").unwrap();
    let (ok, _, err) = common::run(
        Command::new(common::fbbus_bin()).args(["check-config", config.to_str().unwrap()]),
        Duration::from_secs(10),
    );
    assert!(!ok);
    assert!(err.contains("max_conections"), "{err}");
}

/// Issue 15: an error about a file names the file. A corrupt registry stops the start with
/// its path and what to do, instead of a bare parse error.
#[test]
fn a_corrupt_registry_file_is_named_when_the_broker_refuses_to_start() {
    let dir = tempfile::tempdir().unwrap();
    let registry = dir.path().join("line-registry.json");
    std::fs::write(&registry, "{\"version\":1,\"devices\":[{\"id\":").unwrap();
    let config = dir.path().join("line.toml");
    std::fs::write(
        &config,
        format!(
            "[fb]\nregistry_file = {:?}\n[[listener]]\nname = \"l\"\nbind = \"127.0.0.1:0\"\n\
             [admin]\nbind = \"127.0.0.1:0\"\n",
            registry.to_str().unwrap()
        ),
    )
    .unwrap();
    let (ok, _, err) = common::run(
        Command::new(common::fbbus_bin()).args(["serve", "--config", config.to_str().unwrap()]),
        Duration::from_secs(10),
    );
    assert!(!ok, "a corrupt registry must stop the start");
    assert!(err.contains(registry.to_str().unwrap()), "{err}");
    assert!(err.contains("move it away"), "{err}");
}

#[test]
fn health_and_readiness() {
    let broker = Broker::start();
    assert_eq!(common::http_get(broker.admin, "/healthz").unwrap().0, 200);
    assert_eq!(common::http_get(broker.admin, "/readyz").unwrap().0, 200);
    let metrics = broker.metrics();
    for name in [
        "fbbus_connections",
        "fbbus_connects_total",
        "fbbus_messages_received_total",
        "fbbus_wills_published_total",
    ] {
        assert!(metrics.contains(name), "{name} missing from /metrics");
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn sigterm_disconnects_clients_cleanly_and_exits_zero() {
    let mut broker = Broker::start();
    let mut c5 = RawClient::connect(broker.port());
    assert_eq!(
        c5.handshake(&raw::Connect {
            version: 5,
            client_id: "v5",
            ..Default::default()
        }),
        0
    );
    let mut watcher = V4::connect(broker.port(), "watcher", None).await.unwrap();
    watcher.subscribe("will/#").await;
    let mut c4 = RawClient::connect(broker.port());
    assert_eq!(
        c4.handshake(&raw::Connect {
            client_id: "v4",
            will: Some(("will/v4", b"gone")),
            ..Default::default()
        }),
        0
    );

    broker.signal("TERM");
    let (byte1, body) = c5.read_packet().expect("DISCONNECT before close");
    assert_eq!((byte1, body[0]), (0xE0, 0x8B), "server shutting down");
    assert!(c4.closed_by_broker());
    let status = (0..100)
        .find_map(|_| {
            std::thread::sleep(Duration::from_millis(100));
            broker.child.try_wait().unwrap()
        })
        .expect("broker exits within 10 s");
    assert!(status.success(), "exit status {status}");
    // A broker shutdown is not a device failure: no will.
    assert!(watcher
        .next_publish(Duration::from_millis(300))
        .await
        .is_none());
    let _ = clients::WAIT;
}

#[test]
fn dollar_filters_are_refused_without_dropping_the_client() {
    let broker = Broker::start();
    for (version, code) in [(4u8, 0x80u8), (5, 0x83)] {
        let mut c = RawClient::connect(broker.port());
        assert_eq!(
            c.handshake(&raw::Connect {
                version,
                ..Default::default()
            }),
            0
        );
        // (`$SYS/` is the broker's status, readable from loopback: tests/sys.rs.)
        c.send(&raw::subscribe(version, 3, &["$other/#", "plain/#"]));
        let (byte1, body) = c.read_packet().expect("SUBACK");
        assert_eq!(byte1, 0x90);
        assert_eq!(
            raw::suback_codes(version, &body),
            [code, 0x00],
            "MQTT {version}"
        );
        c.send(&[0xC0, 0x00]); // PINGREQ: the connection is still served
        assert_eq!(c.read_packet().expect("PINGRESP").0, 0xD0);
    }
}

/// The annotated example in deploy/ is what operators copy: it must stay a valid config
/// whose files load, as the config grows.
#[test]
fn deploy_example_config_passes_check_config() {
    let root = concat!(env!("CARGO_MANIFEST_DIR"), "/..");
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    std::fs::create_dir(d.join("tls")).unwrap();
    common::add_user(&d.join("passwd"), "plc-1", "pw");
    std::fs::copy(format!("{root}/deploy/acl.example"), d.join("acl")).unwrap();
    let cert = rcgen::generate_simple_self_signed(vec!["localhost".into()]).unwrap();
    std::fs::write(d.join("tls/server.crt"), cert.cert.pem()).unwrap();
    std::fs::write(d.join("tls/server.key"), cert.key_pair.serialize_pem()).unwrap();
    std::fs::write(d.join("tls/ca.crt"), cert.cert.pem()).unwrap();
    let example = std::fs::read_to_string(format!("{root}/deploy/fbbus.example.toml")).unwrap();
    let config = d.join("fbbus.toml");
    std::fs::write(
        &config,
        example.replace("/etc/fbbus/", &format!("{}/", d.display())),
    )
    .unwrap();

    let (ok, out, err) = common::run(
        Command::new(common::fbbus_bin()).args(["check-config", config.to_str().unwrap()]),
        Duration::from_secs(10),
    );
    assert!(
        ok,
        "deploy/fbbus.example.toml no longer passes check-config: {err}"
    );
    assert!(out.contains(": ok"), "{out}");

    // check-config parses the named files: a broken ACL fails it.
    std::fs::write(d.join("acl"), "topic sometimes plant/#\n").unwrap();
    let (ok, _, err) = common::run(
        Command::new(common::fbbus_bin()).args(["check-config", config.to_str().unwrap()]),
        Duration::from_secs(10),
    );
    assert!(!ok);
    assert!(err.contains("line 1") && err.contains("sometimes"), "{err}");
}

#[test]
fn json_logs_are_one_object_per_line() {
    let broker = Broker::start_with(
        Options {
            log_format: "json",
            ..Default::default()
        },
        |_| {},
    );
    let mut c = RawClient::connect(broker.port());
    assert_eq!(
        c.handshake(&raw::Connect {
            client_id: "json-dev",
            ..Default::default()
        }),
        0
    );
    c.send(&raw::DISCONNECT);
    assert!(c.closed_by_broker());
    broker.wait_metric("fbbus_disconnects_total{reason=\"client\"}", 1.0);
    let log = broker.log_text();
    let events: Vec<serde_json::Value> = log
        .lines()
        .map(|l| serde_json::from_str(l).unwrap_or_else(|e| panic!("not JSON ({e}): {l}")))
        .collect();
    assert!(events
        .iter()
        .any(|e| e["message"] == "client connected" && e["client_id"] == "json-dev"));
}

/// A publisher that writes faster than the router takes its messages is slowed by TCP
/// backpressure, and a burst larger than the backlog still arrives complete and in order.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_burst_larger_than_the_backlog_arrives_complete_and_in_order() {
    let broker = Broker::start();
    let mut sub = V4::connect(broker.port(), "sink", None).await.unwrap();
    sub.subscribe("burst/#").await;
    let mut c = RawClient::connect(broker.port());
    assert_eq!(
        c.handshake(&raw::Connect {
            client_id: "firehose",
            ..Default::default()
        }),
        0
    );
    const N: u32 = 20_000;
    let burst: Vec<u8> = (0..N)
        .flat_map(|i| raw::publish_qos0("burst/x", &i.to_be_bytes()))
        .collect();
    let writer = std::thread::spawn(move || {
        c.send(&burst);
        c
    });
    for i in 0..N {
        let m = sub
            .next_publish(Duration::from_secs(10))
            .await
            .unwrap_or_else(|| panic!("message {i} of {N} missing"));
        assert_eq!(m.payload[..], i.to_be_bytes());
    }
    drop(writer.join().unwrap());
}

/// A packet type only servers send (here a CONNACK with a body, which rumqttd 0.20's v5
/// decoder would panic on) ends that connection as a protocol error, with the usual
/// clean-up: its will fires and the connection count comes back down.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn server_only_packet_types_end_the_connection_cleanly() {
    let broker = Broker::start();
    let mut watcher = V4::connect(broker.port(), "watcher", None).await.unwrap();
    watcher.subscribe("will/#").await;
    let mut c = RawClient::connect(broker.port());
    let connect = raw::Connect {
        version: 5,
        client_id: "confused",
        will: Some(("will/confused", b"gone")),
        ..Default::default()
    };
    assert_eq!(c.handshake(&connect), 0);
    // The gauge counts a connection once its CONNACK is written: the client may read the
    // CONNACK before the broker has counted it.
    assert_eq!(broker.wait_metric("fbbus_connections", 2.0), 2.0);
    c.send(&[0x2d, 0x02, 0x04, 0x1f]);
    let (byte1, body) = c.read_packet().expect("DISCONNECT");
    assert_eq!((byte1, body[0]), (0xE0, 0x82), "protocol error");
    assert!(c.closed_by_broker());
    let will = watcher.next_publish(WAIT).await.expect("the will fires");
    assert_eq!(will.payload, "gone");
    assert_eq!(
        broker.wait_metric("fbbus_disconnects_total{reason=\"protocol_error\"}", 1.0),
        1.0
    );
    assert_eq!(broker.metric("fbbus_connections"), 1.0);
}

/// The `fbbus` binary runs on jemalloc with the options `broker::JEMALLOC_CONF`
/// names (the idle-memory figures depend on them). jemalloc reads them from an exported
/// symbol before `main`; if the symbol were lost (renamed, stripped by a build change),
/// jemalloc would silently run on its defaults. `background_thread:true` is the option
/// visible from outside: a thread named `jemalloc_bg_thd`.
#[test]
#[cfg(all(target_os = "linux", feature = "jemalloc"))]
fn the_broker_runs_on_jemalloc_with_its_options() {
    assert!(
        std::str::from_utf8(broker::JEMALLOC_CONF)
            .unwrap()
            .contains("background_thread:true"),
        "this test looks for the background thread"
    );
    let broker = Broker::start();
    let tasks = format!("/proc/{}/task", broker.child.id());
    let deadline = std::time::Instant::now() + Duration::from_secs(5);
    loop {
        let names: Vec<String> = std::fs::read_dir(&tasks)
            .unwrap()
            .filter_map(|t| std::fs::read_to_string(t.ok()?.path().join("comm")).ok())
            .map(|n| n.trim().to_owned())
            .collect();
        if names.iter().any(|n| n == "jemalloc_bg_thd") {
            break;
        }
        assert!(
            std::time::Instant::now() < deadline,
            "no jemalloc background thread among {names:?}"
        );
        std::thread::sleep(Duration::from_millis(50));
    }
}

//! A device's namespace is its own on every topic shape (issue #20): in lenient mode
//! (`[fb] undeclared = "pass"`), topics that are not typed ports are routed unchecked,
//! and before the fix a device could publish `fb/devB`, `fb/devB/CONV` or
//! `fbdk/devB/CONV/SPEED/x` in devB's name. Real clients: rumqttc (3.1.1), a raw MQTT 5
//! connection (to read the PUBACK reason code) and mosquitto_pub (3.1.1 and 5).

mod common;

use std::process::Command;
use std::time::Duration;

use common::clients::{V4, WAIT};
use common::fb::{rejected_series, subscribe_all, Dev, NOT_AUTHORIZED};
use common::raw;
use common::{add_user, require, run, Broker, Options};

/// Every shape under devB's namespace that is not a typed port of four levels, and one
/// that is, in every encoding.
fn foreign_topics() -> Vec<String> {
    let mut topics = Vec::new();
    for ns in ["fb", "fbdk", "dinasore"] {
        for rest in [
            "",
            "/CONV",
            "/CONV/SPEED",
            "/CONV/SPEED/x",
            "/CONV/SPEED/x/ÿ€",
        ] {
            topics.push(format!("{ns}/devB{rest}"));
        }
    }
    topics
}

/// The next delivery in a typed namespace; the broker's explanations to devA on
/// `fbbus/diag/devA`, which the `#` subscriber also gets, are skipped.
async fn next_typed(watch: &mut V4, within: Duration) -> Option<(String, Vec<u8>)> {
    watch
        .next(within, |p| match p {
            rumqttc::Packet::Publish(p) if !p.topic.starts_with("fbbus/") => {
                Some((p.topic.clone(), p.payload.to_vec()))
            }
            _ => None,
        })
        .await
}

fn lenient_line() -> Broker {
    Broker::start_with(
        Options {
            extra: "[auth]\npassword_file = \"passwd\"\n[fb]\nundeclared = \"pass\"\n".into(),
            ..Default::default()
        },
        |dir| {
            for user in ["devA", "devB", "watch"] {
                add_user(&dir.join("passwd"), user, "pw");
            }
        },
    )
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn another_devices_namespace_is_refused_at_every_depth_in_lenient_mode() {
    let broker = lenient_line();
    let port = broker.port();
    let mut watch = V4::connect(port, "watch", Some(("watch", "pw")))
        .await
        .unwrap();
    // `#` does not reach the re-encoded copies (issue 35): they are named too.
    subscribe_all(&mut watch, &["#", "dinasore/#", "fbdk/#"]).await;

    // rumqttc, MQTT 3.1.1: a refusal cannot be told (PUBACK has no reason), it is dropped.
    let mut dev_a = V4::connect(port, "devA", Some(("devA", "pw")))
        .await
        .unwrap();
    let topics = foreign_topics();
    for topic in &topics {
        dev_a
            .client
            .publish(topic, rumqttc::QoS::AtLeastOnce, false, "forged by devA")
            .await
            .unwrap();
    }
    // Every one acknowledged (3.1.1 cannot refuse) before devA's next connection takes
    // the client id over.
    for topic in &topics {
        let ack = dev_a
            .next(WAIT, |p| {
                matches!(p, rumqttc::Packet::PubAck(_)).then_some(())
            })
            .await;
        assert!(ack.is_some(), "no PUBACK for {topic}");
    }
    drop(dev_a);
    // A raw MQTT 5 connection reads the reason: 0x87 at every depth and encoding.
    let mut dev_a5 = Dev::try_connect(
        port,
        &raw::Connect {
            version: 5,
            client_id: "devA",
            login: Some(("devA", "pw")),
            ..Default::default()
        },
    )
    .expect("devA logs in");
    for topic in &topics {
        assert_eq!(
            dev_a5.publish(topic, b"forged by devA, v5"),
            NOT_AUTHORIZED,
            "{topic}"
        );
    }
    // mosquitto_pub, both versions, one after the other under devA's id (each waits for
    // its PUBACK before it disconnects, so each refusal is counted when it returns).
    let mosquitto = require("mosquitto_pub");
    if mosquitto {
        for (version, topic) in [
            ("mqttv311", "fb/devB"),
            ("mqttv311", "fbdk/devB/CONV/SPEED/x"),
            ("5", "dinasore/devB/CONV"),
            ("5", "fb/devB/CONV/SPEED/x/y"),
        ] {
            // Not asserted: mosquitto_pub exits non-zero on a refusing MQTT 5 PUBACK.
            let _ = tokio::task::block_in_place(|| {
                run(
                    Command::new("mosquitto_pub").args([
                        "-h",
                        "127.0.0.1",
                        "-p",
                        &port.to_string(),
                        "-V",
                        version,
                        "-i",
                        "devA",
                        "-u",
                        "devA",
                        "-P",
                        "pw",
                        "-q",
                        "1",
                        "-t",
                        topic,
                        "-m",
                        "forged by mosquitto_pub",
                    ]),
                    Duration::from_secs(10),
                )
            });
        }
    }

    // devB itself, on a typed port: delivered, and the first thing the watcher sees, so
    // nothing forged was routed before it on the same subscription.
    let dev_b = V4::connect(port, "devB", Some(("devB", "pw")))
        .await
        .unwrap();
    dev_b
        .client
        .publish(
            "fb/devB/CONV/SPEED",
            rumqttc::QoS::AtLeastOnce,
            false,
            "1.5",
        )
        .await
        .unwrap();
    assert_eq!(
        next_typed(&mut watch, WAIT).await,
        Some(("fb/devB/CONV/SPEED".to_owned(), b"1.5".to_vec())),
        "{}",
        broker.log_text()
    );
    assert_eq!(
        next_typed(&mut watch, Duration::from_millis(400)).await,
        None,
        "a forged message was delivered"
    );

    // Counted: devA has not declared, so its refusals carry the bounded labels.
    let forged = 2 * topics.len() + if mosquitto { 4 } else { 0 };
    let series = rejected_series("undeclared", "undeclared", "not_authorized");
    assert_eq!(
        broker.wait_metric(&series, forged as f64),
        forged as f64,
        "{}",
        broker.metrics()
    );
    assert!(dev_b.alive());
}

//! Interoperability with a third-party client: Eclipse paho-mqtt 2.x (Python), MQTT 3.1.1
//! and 5, against the real `fbbus` binary.
//!
//! Each test starts its own broker and runs one scenario of `tests/python/paho_check.py`,
//! which prints one JSON line of what paho observed and exits 0 when the expectations hold.
//! The broker's side is checked here through its metrics. Without python3 and paho-mqtt
//! the tests are skipped (and fail in CI, where `.ci/run` installs them).

mod common;

use std::io::{BufRead, BufReader, Read};
use std::path::Path;
use std::process::{Command, Stdio};
use std::sync::mpsc;
use std::time::{Duration, Instant};

use common::{Broker, Options};

const SCRIPT: &str = concat!(env!("CARGO_MANIFEST_DIR"), "/tests/python/paho_check.py");
const LIMIT: Duration = Duration::from_secs(30);

/// The script's command line for one scenario.
fn script(broker: &Broker, scenario: &str, protocol: &str, extra: &[&str]) -> Command {
    let mut cmd = Command::new("python3");
    cmd.arg("-u")
        .arg(SCRIPT)
        .args(["--port", &broker.port().to_string()])
        .args(["--scenario", scenario, "--protocol", protocol])
        .args(extra);
    cmd
}

/// Runs a scenario to completion and fails the test with everything that helps if it failed.
fn run_scenario(broker: &Broker, scenario: &str, protocol: &str, extra: &[&str]) -> String {
    let (ok, out, err) = common::run(&mut script(broker, scenario, protocol, extra), LIMIT);
    assert!(
        ok,
        "paho scenario {scenario} (MQTT {protocol}) failed\n--- stdout\n{out}\n--- stderr\n{err}\n--- broker log\n{}",
        broker.log_text()
    );
    // What paho observed, for `--nocapture` runs.
    eprintln!("paho {scenario} (MQTT {protocol}): {}", out.trim());
    out
}

/// Asserts a metric reached at least `min` (waiting, since metrics move asynchronously).
fn assert_metric_at_least(broker: &Broker, series: &str, min: f64) -> f64 {
    let v = broker.wait_metric(series, min);
    assert!(
        v >= min,
        "{series} = {v}, expected at least {min}\n--- metrics\n{}\n--- broker log\n{}",
        broker.metrics(),
        broker.log_text()
    );
    v
}

fn anonymous_broker() -> Broker {
    Broker::start()
}

/// A broker with a password file (dev1 / pw1) and, optionally, an ACL file.
fn auth_broker(acl: Option<&str>) -> Broker {
    let mut extra = String::from("[auth]\npassword_file = \"passwd\"\n");
    if acl.is_some() {
        extra.push_str("acl_file = \"acl\"\n");
    }
    Broker::start_with(
        Options {
            extra,
            ..Default::default()
        },
        |dir: &Path| {
            common::add_user(&dir.join("passwd"), "dev1", "pw1");
            if let Some(acl) = acl {
                std::fs::write(dir.join("acl"), acl).unwrap();
            }
        },
    )
}

/// dev1 may publish only under plant/dev1/ and read all of plant/.
const DEV1_ACL: &str = "\
user dev1
topic write plant/dev1/#
topic read plant/#
";

// ---------------------------------------------------------------- pubsub

fn pubsub(protocol: &str) {
    if !common::require_paho() {
        return;
    }
    let broker = anonymous_broker();
    run_scenario(&broker, "pubsub", protocol, &[]);
    // Two rounds of 20 (burst, then one at a time).
    assert_metric_at_least(&broker, "fbbus_messages_received_total", 40.0);
    assert_metric_at_least(&broker, "fbbus_messages_sent_total", 40.0);
}

#[test]
fn paho_pubsub_v311() {
    pubsub("311");
}

#[test]
fn paho_pubsub_v5() {
    pubsub("5");
}

/// Delivery QoS is min(publication QoS, granted subscription QoS) [MQTT-3.8.4-8].
/// rumqttd's router delivers at the subscription's QoS; fbbus's packet path restores it.
fn delivery_qos(protocol: &str) {
    if !common::require_paho() {
        return;
    }
    let broker = anonymous_broker();
    run_scenario(&broker, "delivery_qos", protocol, &[]);
    assert_metric_at_least(&broker, "fbbus_messages_sent_total", 9.0);
}

#[test]
fn paho_delivery_qos_v311() {
    delivery_qos("311");
}

#[test]
fn paho_delivery_qos_v5() {
    delivery_qos("5");
}

fn pubsub_authenticated(protocol: &str) {
    if !common::require_paho() {
        return;
    }
    let broker = auth_broker(None);
    run_scenario(
        &broker,
        "pubsub",
        protocol,
        &["--user", "dev1", "--password", "pw1"],
    );
    assert_metric_at_least(&broker, "fbbus_connects_total", 2.0);
    assert_metric_at_least(&broker, "fbbus_messages_received_total", 40.0);
    assert_eq!(
        broker.metric(r#"fbbus_auth_failures_total{reason="bad_credentials"}"#),
        0.0
    );
}

#[test]
fn paho_pubsub_authenticated_v311() {
    pubsub_authenticated("311");
}

#[test]
fn paho_pubsub_authenticated_v5() {
    pubsub_authenticated("5");
}

// ---------------------------------------------------------------- bad_password

fn bad_password(protocol: &str) {
    if !common::require_paho() {
        return;
    }
    let broker = auth_broker(None);
    let args = [
        "--user",
        "dev1",
        "--password",
        "wrong",
        "--good-password",
        "pw1",
    ];
    run_scenario(&broker, "bad_password", protocol, &args);
    assert_metric_at_least(
        &broker,
        r#"fbbus_auth_failures_total{reason="bad_credentials"}"#,
        1.0,
    );
    assert_metric_at_least(
        &broker,
        r#"fbbus_connects_refused_total{reason="bad_credentials"}"#,
        1.0,
    );
    // The right password afterwards was accepted.
    assert_metric_at_least(&broker, "fbbus_connects_total", 1.0);
}

#[test]
fn paho_bad_password_v311() {
    bad_password("311");
}

#[test]
fn paho_bad_password_v5() {
    bad_password("5");
}

// ---------------------------------------------------------------- acl

fn acl(protocol: &str) {
    if !common::require_paho() {
        return;
    }
    let broker = auth_broker(Some(DEV1_ACL));
    run_scenario(
        &broker,
        "acl",
        protocol,
        &["--user", "dev1", "--password", "pw1"],
    );
    // The QoS 1 and QoS 0 publications to plant/dev2/.
    assert_metric_at_least(&broker, r#"fbbus_acl_denied_total{action="publish"}"#, 2.0);
    // secret/# and secret/a.
    assert_metric_at_least(
        &broker,
        r#"fbbus_acl_denied_total{action="subscribe"}"#,
        2.0,
    );
    // Only plant/dev1/x and plant/dev1/after were routed.
    assert_eq!(broker.metric("fbbus_messages_received_total"), 2.0);
}

#[test]
fn paho_acl_v311() {
    acl("311");
}

#[test]
fn paho_acl_v5() {
    acl("5");
}

/// A refused QoS 2 publication completes its flow and leaves the connection up.
fn acl_qos2(protocol: &str) {
    if !common::require_paho() {
        return;
    }
    let broker = auth_broker(Some(DEV1_ACL));
    run_scenario(
        &broker,
        "acl_qos2",
        protocol,
        &["--user", "dev1", "--password", "pw1"],
    );
    assert_metric_at_least(&broker, r#"fbbus_acl_denied_total{action="publish"}"#, 1.0);
    assert_eq!(broker.metric("fbbus_messages_received_total"), 1.0);
    // Nothing else ever held this client id.
    assert_eq!(
        broker.metric(r#"fbbus_disconnects_total{reason="takeover"}"#),
        0.0
    );
}

#[test]
fn paho_acl_qos2_v311() {
    acl_qos2("311");
}

#[test]
fn paho_acl_qos2_v5() {
    acl_qos2("5");
}

// ---------------------------------------------------------------- will

fn will(protocol: &str) {
    if !common::require_paho() {
        return;
    }
    let broker = anonymous_broker();
    run_scenario(&broker, "will", protocol, &[]);
    // A's will (abrupt close); on 5 also D's (DISCONNECT 0x04); never C's (clean DISCONNECT).
    let wills = if protocol == "5" { 2.0 } else { 1.0 };
    assert_metric_at_least(&broker, "fbbus_wills_published_total", wills);
    assert_eq!(
        broker.metric("fbbus_wills_published_total"),
        wills,
        "a will was published for a clean disconnect\n{}",
        broker.log_text()
    );
    assert_metric_at_least(&broker, r#"fbbus_disconnects_total{reason="abrupt"}"#, 1.0);
    assert_metric_at_least(&broker, r#"fbbus_disconnects_total{reason="client"}"#, 2.0);
}

#[test]
fn paho_will_v311() {
    will("311");
}

#[test]
fn paho_will_v5() {
    will("5");
}

// ---------------------------------------------------------------- keepalive0

fn keepalive0(protocol: &str) {
    if !common::require_paho() {
        return;
    }
    let broker = anonymous_broker();
    run_scenario(&broker, "keepalive0", protocol, &[]);
    assert_metric_at_least(&broker, "fbbus_connects_total", 1.0);
    assert_metric_at_least(&broker, "fbbus_messages_received_total", 2.0);
    assert_eq!(
        broker.metric(r#"fbbus_disconnects_total{reason="keep_alive"}"#),
        0.0
    );
}

#[test]
fn paho_keepalive0_v311() {
    keepalive0("311");
}

#[test]
fn paho_keepalive0_v5() {
    keepalive0("5");
}

// ---------------------------------------------------------------- shutdown

/// The script connects and prints READY; then the broker gets SIGTERM. The script must see
/// the connection end (MQTT 5: DISCONNECT 0x8B) and the broker must exit 0 within 10 s.
fn shutdown(scenario: &str, protocol: &str) {
    if !common::require_paho() {
        return;
    }
    let mut broker = anonymous_broker();
    let mut child = script(&broker, scenario, protocol, &[])
        .stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .spawn()
        .expect("cannot run python3");

    // Stdout is read on a thread, line by line, so waiting for READY has a deadline.
    let (tx, lines) = mpsc::channel::<String>();
    let stdout = child.stdout.take().unwrap();
    let reader = std::thread::spawn(move || {
        for line in BufReader::new(stdout).lines() {
            let Ok(line) = line else { break };
            if tx.send(line).is_err() {
                break;
            }
        }
    });
    let mut stderr = child.stderr.take().unwrap();
    let stderr_reader = std::thread::spawn(move || {
        let mut s = String::new();
        let _ = stderr.read_to_string(&mut s);
        s
    });

    let mut out = Vec::new();
    let ready = loop {
        match lines.recv_timeout(LIMIT) {
            Ok(line) => {
                let done = line == "READY";
                out.push(line);
                if done {
                    break true;
                }
            }
            Err(_) => break false,
        }
    };
    if !ready {
        let _ = child.kill();
        let _ = child.wait();
        panic!(
            "script never printed READY\n--- stdout\n{}\n--- stderr\n{}\n--- broker log\n{}",
            out.join("\n"),
            stderr_reader.join().unwrap(),
            broker.log_text()
        );
    }

    broker.signal("TERM");
    let signalled = Instant::now();

    // The script ends by itself (it waits at most 10 s for the disconnect).
    let status = common::wait_until(&mut child, LIMIT);
    reader.join().unwrap();
    out.extend(lines.try_iter());
    let err = stderr_reader.join().unwrap();

    // The broker exits, with status 0, within 10 s of SIGTERM.
    let exit = loop {
        if let Some(exit) = broker.child.try_wait().unwrap() {
            break Some(exit);
        }
        if signalled.elapsed() > Duration::from_secs(10) {
            break None;
        }
        std::thread::sleep(Duration::from_millis(20));
    };
    let report = format!(
        "--- stdout\n{}\n--- stderr\n{err}\n--- broker log\n{}",
        out.join("\n"),
        broker.log_text()
    );
    eprintln!("paho {scenario} (MQTT {protocol}): {}", out.join(" | "));
    assert!(
        status.is_some_and(|s| s.success()),
        "paho scenario {scenario} failed ({status:?})\n{report}"
    );
    match exit {
        Some(exit) => assert!(
            exit.success(),
            "broker exited with {exit} after SIGTERM\n{report}"
        ),
        None => panic!("broker still running 10 s after SIGTERM\n{report}"),
    }
    assert!(
        broker.log_text().contains("broker stopped"),
        "no `broker stopped` in the log\n{report}"
    );
}

#[test]
fn paho_shutdown_v5() {
    shutdown("shutdown5", "5");
}

#[test]
fn paho_shutdown_v311() {
    shutdown("shutdown311", "311");
}

//! `$SYS/` (issue 35): the broker's status under Mosquitto's names, read with Mosquitto's
//! own client (`mosquitto_sub -t '$SYS/#'`) from loopback; refused where an ACL rule
//! denies it; never published by a client; never matched by `#`; off with
//! `sys_interval_s = 0`. (Who may read it from elsewhere, the rule's other half, is
//! checked in security's ACL tests: tests here run on loopback only.)

mod common;

use std::collections::BTreeMap;
use std::process::Command;
use std::time::{Duration, Instant};

use common::{Broker, Options};

/// The topics README.md documents, as published at start.
const TOPICS: [&str; 26] = [
    "$SYS/broker/version",
    "$SYS/broker/uptime",
    "$SYS/broker/clients/connected",
    "$SYS/broker/clients/disconnected",
    "$SYS/broker/clients/total",
    "$SYS/broker/clients/maximum",
    "$SYS/broker/publish/messages/received",
    "$SYS/broker/publish/messages/sent",
    "$SYS/broker/bytes/received",
    "$SYS/broker/bytes/sent",
    "$SYS/broker/retained messages/count",
    "$SYS/broker/load/publish/received/1min",
    "$SYS/broker/load/publish/received/5min",
    "$SYS/broker/load/publish/received/15min",
    "$SYS/broker/load/publish/sent/1min",
    "$SYS/broker/load/publish/sent/5min",
    "$SYS/broker/load/publish/sent/15min",
    "$SYS/broker/load/bytes/received/1min",
    "$SYS/broker/load/bytes/received/5min",
    "$SYS/broker/load/bytes/received/15min",
    "$SYS/broker/load/bytes/sent/1min",
    "$SYS/broker/load/bytes/sent/5min",
    "$SYS/broker/load/bytes/sent/15min",
    "$SYS/broker/load/connections/1min",
    "$SYS/broker/load/connections/5min",
    "$SYS/broker/load/connections/15min",
];

const ACL: &str = "user tool\ntopic read fb/#\n\
                   user nosy\ntopic read #\ntopic deny $SYS/#\n";

fn broker_with_users() -> Broker {
    Broker::start_with(
        Options {
            extra: "sys_interval_s = 1\n[auth]\npassword_file = \"passwd\"\nacl_file = \"acl\"\n"
                .into(),
            ..Default::default()
        },
        |dir| {
            common::add_user(&dir.join("passwd"), "tool", "tool-pass-1");
            common::add_user(&dir.join("passwd"), "nosy", "nosy-pass-1");
            std::fs::write(dir.join("acl"), ACL).unwrap();
        },
    )
}

/// `mosquitto_sub -v` as `user` (None: anonymous) with `args`; (exited 0, stdout, stderr).
fn sub(broker: &Broker, user: Option<&str>, args: &[&str]) -> (bool, String, String) {
    let mut cmd = Command::new("mosquitto_sub");
    cmd.args(["-h", "127.0.0.1", "-p", &broker.port().to_string(), "-v"]);
    if let Some(user) = user {
        cmd.args(["-u", user, "-P", &format!("{user}-pass-1")]);
    }
    cmd.args(args);
    common::run(&mut cmd, Duration::from_secs(20))
}

/// `topic payload` lines of `mosquitto_sub -v` as a map (the last payload per topic).
/// Topics with a space (`retained messages/count`) are matched against `TOPICS`.
fn by_topic(out: &str) -> BTreeMap<String, String> {
    out.lines()
        .map(|line| {
            let topic = TOPICS
                .iter()
                .find(|t| line.starts_with(&format!("{t} ")))
                .map(|t| t.to_string())
                .unwrap_or_else(|| line.split(' ').next().unwrap_or("").to_owned());
            let payload = line[topic.len()..].trim().to_owned();
            (topic, payload)
        })
        .collect()
}

#[test]
fn mosquitto_sub_reads_sys_from_loopback_under_mosquittos_names() {
    if !common::require("mosquitto_sub") {
        return;
    }
    let broker = broker_with_users();
    // Retained: a subscriber arriving later gets every topic at once.
    let n = TOPICS.len().to_string();
    let (ok, out, err) = sub(
        &broker,
        Some("tool"),
        &["-t", "$SYS/#", "-C", &n, "-W", "10"],
    );
    assert!(ok, "{out}\n{err}\n{}", broker.log_text());
    let got = by_topic(&out);
    for topic in TOPICS {
        assert!(got.contains_key(topic), "{topic} missing from\n{out}");
    }
    assert!(
        got["$SYS/broker/version"].starts_with("fbbus version "),
        "{out}"
    );
    let uptime = &got["$SYS/broker/uptime"];
    assert!(
        uptime.ends_with(" seconds") && uptime.trim_end_matches(" seconds").parse::<u64>().is_ok(),
        "{uptime}"
    );

    // The figures follow the broker: two more clients held open show up within a few
    // intervals in clients/connected and clients/maximum (0 or 1 before).
    let hold = |user: &str| {
        Command::new("mosquitto_sub")
            .args(["-h", "127.0.0.1", "-p", &broker.port().to_string()])
            .args([
                "-u",
                user,
                "-P",
                &format!("{user}-pass-1"),
                "-t",
                "fb/x",
                "-W",
                "15",
            ])
            .stdout(std::process::Stdio::null())
            .spawn()
            .unwrap()
    };
    let mut held = [hold("tool"), hold("tool")];
    let deadline = Instant::now() + Duration::from_secs(10);
    loop {
        let (_, out, _) = sub(
            &broker,
            Some("tool"),
            &["-t", "$SYS/broker/clients/+", "-C", "4", "-W", "5"],
        );
        let got = by_topic(&out);
        // The figures of the last interval: the two held (this reader may come after it).
        let at_least_2 = |t: &str| got.get(t).and_then(|v| v.parse::<u64>().ok()) >= Some(2);
        if at_least_2("$SYS/broker/clients/connected") && at_least_2("$SYS/broker/clients/maximum")
        {
            break;
        }
        assert!(Instant::now() < deadline, "clients not counted:\n{out}");
        std::thread::sleep(Duration::from_millis(300));
    }
    for child in &mut held {
        let _ = child.kill();
        let _ = child.wait();
    }

    // `#` never matches a `$` topic (MQTT 4.7.2): nosy reads `#` and gets no $SYS.
    let (_, out, _) = sub(&broker, Some("nosy"), &["-t", "#", "-W", "3"]);
    assert!(!out.contains("$SYS"), "{out}");
}

#[test]
fn sys_is_refused_where_the_acl_denies_it_and_nobody_publishes_there() {
    if !common::require("mosquitto_sub") || !common::require("mosquitto_pub") {
        return;
    }
    let broker = broker_with_users();
    // nosy's `topic deny $SYS/#` beats the loopback default.
    // (mosquitto_sub 2.0 says so on stderr and ends.)
    let (_, out, err) = sub(&broker, Some("nosy"), &["-t", "$SYS/#", "-W", "5"]);
    assert!(!out.contains("$SYS"), "{out}");
    assert!(err.contains("denied"), "{err}\n{}", broker.log_text());
    assert!(
        broker.wait_metric(r#"fbbus_acl_denied_total{action="subscribe"}"#, 1.0) >= 1.0,
        "{}",
        broker.metrics()
    );
    // A client publishing under $SYS is refused (MQTT 5: PUBACK 0x87), whatever its ACL.
    let (_, out, err) = common::run(
        Command::new("mosquitto_pub")
            .args(["-h", "127.0.0.1", "-p", &broker.port().to_string()])
            .args(["-u", "nosy", "-P", "nosy-pass-1", "-V", "5", "-q", "1"])
            .args(["-t", "$SYS/broker/uptime", "-m", "0 seconds"]),
        Duration::from_secs(10),
    );
    assert!(
        format!("{out}{err}").contains("Not authorized"),
        "{out}\n{err}"
    );
}

#[test]
fn sys_interval_zero_publishes_nothing() {
    if !common::require("mosquitto_sub") {
        return;
    }
    let broker = Broker::start_with(
        Options {
            extra: "sys_interval_s = 0\n".into(),
            ..Default::default()
        },
        |_| {},
    );
    let (ok, out, _) = sub(&broker, None, &["-t", "$SYS/#", "-W", "2"]);
    assert!(!ok && out.is_empty(), "{out}");
    // The same subscription on a broker with $SYS on gets it at once.
    let broker = Broker::start();
    let (ok, out, _) = sub(
        &broker,
        None,
        &["-t", "$SYS/broker/version", "-C", "1", "-W", "5"],
    );
    assert!(ok && out.contains("fbbus version"), "{out}");
}

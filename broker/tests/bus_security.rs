//! Issue 22: one bus, no strangers. The stranger sequence of the issue, played by a Python
//! eclipse-zenoh peer (`python/stranger.py`) against real `fbbus` lines on loopback:
//!
//! - a line whose bus endpoint is not loopback and not mutual TLS does not start (and
//!   `fbbus check-config` says why): the stranger has nothing to talk to;
//! - on a mutual-TLS bus, a peer without a certificate, or with one of another CA, gets no
//!   session; a peer with another line's certificate (line-c) cannot speak for line-a
//!   (its data keys, its liveliness tokens, its records), and what it puts under its own
//!   keys for devices it does not have is refused by the importing line's registry check,
//!   counted per origin line and described on `fbbus/diag/<device>`; a zenoh application
//!   with a reader's certificate reads the bus and nothing it puts goes anywhere;
//! - on a mutual-TLS bus a line reports messages it lost only as itself (`fbbus/@/loss/`),
//!   and a reader not at all;
//! - on the plain loopback bus (no TLS, no access control) the registry check still holds:
//!   nobody speaks for a device of this line, or for a device no line announced.
//!
//! Every wait is bounded; what "did not happen" is checked after the same bounded quiet
//! period the positive checks of the same step needed, and once more at the end.

mod common;

use std::time::Duration;

use serde_json::{json, Value};

use common::bus::{
    device_with, drain, publish, python_zenoh, tcp_endpoint, Line, Python, PROPAGATION,
};
use common::clients::{V4, WAIT};
use common::pki::{self, Pki};

const PRESS: &str = r#"{"fbs": {"PRESS": {
    "type": "PRESS",
    "data_out": {"STOP": "BOOL", "FORCE": "REAL"}
}}}"#;

/// How long a refused or ignored message gets to show an effect before the test says it
/// had none (loopback: milliseconds in practice).
const QUIET: Duration = Duration::from_millis(1500);

/// What line A counts of its messages other lines reported lost.
const LOST_REPORTED: &str = "fbbus_bridge_lost_reported_total";

fn refused(line: &Line, origin: &str, reason: &str) -> f64 {
    line.broker.metric(&format!(
        "fbbus_bridge_refused_total{{line=\"{origin}\",reason=\"{reason}\"}}"
    ))
}

/// Every refusal `line` counted for messages on `origin`'s keys, whatever the reason.
fn refused_any(line: &Line, origin: &str) -> f64 {
    let prefix = format!("fbbus_bridge_refused_total{{line=\"{origin}\",");
    line.broker
        .metrics()
        .lines()
        .filter(|l| l.starts_with(&prefix))
        .filter_map(|l| l.rsplit_once(' ')?.1.parse::<f64>().ok())
        .sum()
}

fn liveliness(line: &Line, kind: &str) -> f64 {
    line.broker.metric(&format!(
        "fbbus_bridge_liveliness_changes_total{{kind=\"{kind}\"}}"
    ))
}

/// The stranger program: a zenoh peer connected to `endpoints` with `identity` (its TLS
/// arguments: none, `--ca` alone, or [`identity`]).
fn stranger(endpoints: &[&str], identity: &[String]) -> Python {
    let mut args: Vec<&str> = identity.iter().map(String::as_str).collect();
    args.extend(endpoints);
    Python::spawn("stranger.py", &args)
}

/// `--ca`, `--cert`, `--key` of `name` in `pki`, the lines' CA trusted (`ca`).
fn identity(dir: &std::path::Path, pki: &Pki, name: &str, ca: &std::path::Path) -> Vec<String> {
    let sub = dir.join(name);
    std::fs::create_dir_all(&sub).unwrap();
    let files = pki.write(&sub, name);
    vec![
        "--ca".into(),
        ca.display().to_string(),
        "--cert".into(),
        files.cert.display().to_string(),
        "--key".into(),
        files.key.display().to_string(),
    ]
}

/// Everything `obs` received within `quiet`, as (topic, payload).
async fn received(obs: &mut V4, quiet: Duration) -> Vec<(String, String)> {
    drain(obs, quiet)
        .await
        .into_iter()
        .map(|p| (p.topic, String::from_utf8_lossy(&p.payload).into_owned()))
        .collect()
}

/// What an observer may see in the mutual-TLS scenario: press-8's own FORCE values (and,
/// on line A, the refusals' diagnostics of press-8). Everything the strangers put is on
/// STOP ports, dev-b's POSITION or devices that do not exist.
fn only_press_8_force(seen: &[(String, String)], at: &str) {
    for (topic, payload) in seen {
        assert!(
            topic == "fb/press-8/PRESS/FORCE" || topic == "fbbus/diag/press-8",
            "observer on {at} received {topic} {payload}: a stranger's message was delivered"
        );
    }
}

// ---------------------------------------------------------------- (a) no mutual TLS, no start

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_bus_endpoint_between_hosts_without_mutual_tls_does_not_start() {
    let dir = tempfile::tempdir().unwrap();
    let port = common::free_port();
    let config = |name: &str, bridge: &str| {
        let path = dir.path().join(format!("{name}.toml"));
        std::fs::write(
            &path,
            format!(
                "[broker]\nline = \"line-a\"\n[[listener]]\nname = \"main\"\n\
                 bind = \"127.0.0.1:{}\"\n[admin]\nbind = \"127.0.0.1:{}\"\n\
                 [bridge]\n{bridge}\n",
                common::free_port(),
                common::free_port()
            ),
        )
        .unwrap();
        path
    };
    let fbbus = |args: &[&str]| {
        common::run(
            std::process::Command::new(common::fbbus_bin()).args(args),
            Duration::from_secs(20),
        )
    };

    // What deploy/fbbus.example.toml used to suggest: plain TCP on every interface.
    let open = config("open", &format!("listen = [\"tcp/0.0.0.0:{port}\"]"));
    let (ok, out, err) = fbbus(&["check-config", open.to_str().unwrap()]);
    assert!(
        !ok,
        "check-config accepted a plain bus on 0.0.0.0: {out}{err}"
    );
    let said = format!("{out}{err}");
    assert!(
        said.contains("bridge.listen") && said.contains("mutual TLS"),
        "check-config does not say what to configure: {said}"
    );
    let (ok, out, err) = fbbus(&["serve", "--config", open.to_str().unwrap()]);
    assert!(
        !ok,
        "fbbus serve started a plain bus on 0.0.0.0: {out}{err}"
    );
    assert!(
        err.contains("bridge.listen") && err.contains("mutual TLS"),
        "fbbus serve does not say what to configure: {err}"
    );
    assert!(
        std::net::TcpStream::connect(("127.0.0.1", port)).is_err(),
        "something listens on the bus port"
    );

    // TLS that does not identify the other side (mutual = false) is no better, and a
    // line's certificate must name the line.
    let bus = pki::bus();
    let files = bus.write(dir.path(), "line-a");
    let tls = |cert: &std::path::Path, key: &std::path::Path, mutual: bool| {
        format!(
            "listen = [\"tls/0.0.0.0:{port}\"]\n[bridge.tls]\nroot_ca = {:?}\ncert = {:?}\n\
             key = {:?}\nmutual = {mutual}\n",
            files.ca.display().to_string(),
            cert.display().to_string(),
            key.display().to_string(),
        )
    };
    let one_way = config("one-way", &tls(&files.cert, &files.key, false));
    let (ok, out, err) = fbbus(&["check-config", one_way.to_str().unwrap()]);
    assert!(
        !ok,
        "check-config accepted one-way TLS on 0.0.0.0: {out}{err}"
    );
    assert!(
        format!("{out}{err}").contains("bridge.listen"),
        "{out}{err}"
    );
    let other = bus.write(dir.path(), "line-b");
    let peers = "[bridge.peers]\nlines = [\"line-b\"]\n";
    let impostor = config("impostor", &(tls(&other.cert, &other.key, true) + peers));
    let (ok, out, err) = fbbus(&["check-config", impostor.to_str().unwrap()]);
    assert!(!ok, "line-a started with line-b's certificate: {out}{err}");
    assert!(
        format!("{out}{err}").contains("names `line-b`, but this bridge is `line-a`"),
        "{out}{err}"
    );
    let secure = config("secure", &(tls(&files.cert, &files.key, true) + peers));
    let (ok, out, err) = fbbus(&["check-config", secure.to_str().unwrap()]);
    assert!(ok, "the secure setup is refused: {out}{err}");

    if !python_zenoh() {
        return;
    }
    // The stranger finds nothing to talk to.
    let mut s = stranger(&[&format!("tcp/127.0.0.1:{port}")], &[]);
    assert_eq!(s.ask("peers 1 2"), json!({"peers": 0}));
    s.send("quit");

    // Control: the same stranger without a certificate does link to a TLS endpoint that
    // is not mutual (accepted on loopback, with neither peers nor access control). What
    // keeps it off the mutual-TLS bus (`on_a_mutual_tls_bus_a_peer_speaks_only_for_itself`)
    // is that it has no certificate to show.
    let own = tempfile::tempdir().unwrap();
    let files = bus.write(own.path(), "line-a");
    let endpoint = common::bus::tls_endpoint();
    let mqtt = format!("127.0.0.1:{}", common::free_port())
        .parse()
        .unwrap();
    let admin = format!("127.0.0.1:{}", common::free_port())
        .parse()
        .unwrap();
    let config = own.path().join("fbbus.toml");
    std::fs::write(
        &config,
        format!(
            "[broker]\nline = \"line-a\"\n[[listener]]\nname = \"main\"\nbind = \"{mqtt}\"\n\
             [admin]\nbind = \"{admin}\"\n[bridge]\nlisten = [\"{endpoint}\"]\n\
             [bridge.tls]\nroot_ca = {:?}\ncert = {:?}\nkey = {:?}\nmutual = false\n",
            files.ca.display().to_string(),
            files.cert.display().to_string(),
            files.key.display().to_string(),
        ),
    )
    .unwrap();
    let _line = common::Broker::spawn(own, config, mqtt, admin);
    let mut s = stranger(
        &[&endpoint],
        &["--ca".into(), files.ca.display().to_string()],
    );
    assert_eq!(s.ask("peers 1 10"), json!({"peers": 1}));
    s.send("quit");
}

// ---------------------------------------------------------------- (b), (c) a mutual-TLS bus

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn on_a_mutual_tls_bus_a_peer_speaks_only_for_itself() {
    if !python_zenoh() {
        return;
    }
    // zenoh's default lease: nothing here waits for a line to be seen gone.
    let a = Line::start("line-a", &[], "lease_ms = 3000");
    let b = Line::start("line-b", &[&a.zenoh], "lease_ms = 3000");
    let press = device_with(&a, "press-8", PRESS).await;
    let _dev_b = device_with(&b, "dev-b", common::bus::CONV).await;
    let mut obs_a = V4::connect(a.port(), "watch-a", None).await.unwrap();
    obs_a.subscribe("fb/#").await;
    obs_a.subscribe("fbbus/diag/press-8").await;
    let mut obs_b = V4::connect(b.port(), "watch-b", None).await.unwrap();
    obs_b.subscribe("fb/#").await;
    a.wait_metric("fbbus_bridge_remote_subscriptions", 1.0);
    b.wait_metric("fbbus_bridge_remote_subscriptions", 1.0);
    b.wait_record("press-8", "online", PROPAGATION);
    a.wait_record("dev-b", "online", PROPAGATION);
    tokio::time::sleep(Duration::from_millis(300)).await;
    let force = |i: i32| format!("{i}.5");
    // press-8's values cross to line B (the bus works) before anyone else tries anything.
    publish(&press, "fb/press-8/PRESS/FORCE", force(0), false).await;
    let mut crossed = false;
    for _ in 0..50 {
        if let Some(p) = obs_b.next_publish(Duration::from_millis(200)).await {
            assert_eq!(p.topic, "fb/press-8/PRESS/FORCE");
            crossed = true;
            break;
        }
    }
    assert!(crossed, "press-8's value did not cross to line B");
    let dir = tempfile::tempdir().unwrap();
    let ca = pki::bus().write(dir.path(), "line-c").ca;
    let endpoints = [a.zenoh.as_str(), b.zenoh.as_str()];
    // Line A's record may reach line B (and its values cross) before B counted line A's
    // token: the baseline waits for it.
    b.wait_metric(
        "fbbus_bridge_liveliness_changes_total{kind=\"line_up\"}",
        1.0,
    );
    let line_downs = liveliness(&b, "line_down");

    // 1. No certificate, or a certificate (named line-c) of another CA: no session, so
    //    nothing received, and the issue's sequence goes nowhere.
    let foreign = Pki::generate("a stranger's CA", &["line-c"], &["localhost", "127.0.0.1"]);
    let mut nobody = stranger(&endpoints, &["--ca".into(), ca.display().to_string()]);
    let mut forger = stranger(&endpoints, &identity(dir.path(), &foreign, "line-c", &ca));
    for s in [&mut nobody, &mut forger] {
        s.ask("subscribe fbbus/**");
    }
    for i in 1..=5 {
        publish(&press, "fb/press-8/PRESS/FORCE", force(i), false).await;
    }
    nobody.send("peers 1 3");
    forger.send("peers 1 3");
    for (name, s) in [("no certificate", &mut nobody), ("another CA", &mut forger)] {
        assert_eq!(s.answer("peers 1 3"), json!({"peers": 0}), "{name}");
        let samples = s.ask("samples");
        eprintln!("stranger with {name}: {samples}");
        assert_eq!(samples["samples"], 0, "{name}: {samples}");
        assert_eq!(s.ask("alive fbbus/@/**")["alive"], json!([]), "{name}");
        s.ask("play line-a press-7");
    }

    // 2. Line C's certificate: a session (it is a line of the plant), but only line C's
    //    keys. The issue's sequence for line A, and line A's local device.
    let mut c = stranger(&endpoints, &identity(dir.path(), pki::bus(), "line-c", &ca));
    assert_eq!(c.ask("peers 2 10"), json!({"peers": 2}), "line-c linked");
    let played = c.ask("play line-a press-7");
    c.ask("put fbbus/line-a/fb/press-8/PRESS/STOP line-a true");
    c.ask("record line-a press-8 line-c");
    c.ask("token fbbus/@/device/line-a/press-8");
    // A record under its own key whose body says it is line A's device.
    c.ask("record line-c press-9 line-a");
    eprintln!("line-c played {played}");
    tokio::time::sleep(QUIET).await;
    for line in [&a, &b] {
        assert_eq!(line.record("press-7"), None, "line {}", line.name);
    }
    assert_eq!(
        b.record("press-9").map(|r| r["line"].clone()),
        None,
        "line B took line C's record claiming a device of line A"
    );
    // The tokens go: line B's view of line A and press-8 did not waver (a device has no
    // token of its own any more, its state is in its record: the forged device token
    // is refused by zenoh's access control like any key no line speaks for).
    for key in [
        "fbbus/@/line/line-a",
        "fbbus/@/device/line-a/press-7",
        "fbbus/@/device/line-a/press-8",
    ] {
        c.ask(&format!("untoken {key}"));
    }
    tokio::time::sleep(QUIET).await;
    if liveliness(&b, "line_down") > line_downs {
        eprintln!("(line B lost its link to line A meanwhile: a slow machine?)");
    }
    let record = b.record("press-8").unwrap();
    assert_eq!(
        (&record["status"], &record["line"]),
        (&json!("online"), &json!("line-a"))
    );
    assert_eq!(
        record["interface"]["fbs"]["PRESS"]["type"], "PRESS",
        "{record}"
    );
    // zenoh's access control stopped all of it before the bridges: nothing was even
    // refused as line A's.
    for line in [&a, &b] {
        assert_eq!(refused_any(line, "line-a"), 0.0, "line {}", line.name);
    }
    only_press_8_force(
        &received(&mut obs_a, Duration::from_millis(300)).await,
        "line-a",
    );
    only_press_8_force(
        &received(&mut obs_b, Duration::from_millis(300)).await,
        "line-b",
    );

    // 3. Under its own keys, for devices that are not line C's: refused by the importing
    //    line's registry check, counted as line C's, described on the device's diag.
    c.ask("put fbbus/line-c/fb/press-8/PRESS/STOP line-c true");
    a.wait_metric(
        "fbbus_bridge_refused_total{line=\"line-c\",reason=\"local_device\"}",
        1.0,
    );
    let diag = loop {
        let p = obs_a
            .next_publish(WAIT)
            .await
            .expect("a diagnostic on line A");
        if p.topic == "fbbus/diag/press-8" {
            break p;
        }
        only_press_8_force(&[(p.topic.clone(), String::new())], "line-a");
    };
    let diag: Value = serde_json::from_slice(&diag.payload).unwrap();
    assert_eq!(
        diag,
        json!({"kind": "bus_refused", "reason": "local_device", "line": "line-c",
               "stamp_line": "line-c", "topic": "fb/press-8/PRESS/STOP"})
    );
    b.wait_metric(
        "fbbus_bridge_refused_total{line=\"line-c\",reason=\"other_line_device\"}",
        1.0,
    );
    c.ask("put fbbus/line-c/fb/dev-b/CONV/POSITION line-c 7");
    a.wait_metric(
        "fbbus_bridge_refused_total{line=\"line-c\",reason=\"other_line_device\"}",
        1.0,
    );
    b.wait_metric(
        "fbbus_bridge_refused_total{line=\"line-c\",reason=\"local_device\"}",
        1.0,
    );
    c.ask("put fbbus/line-c/fb/press-7/PRESS/STOP line-c true");
    for line in [&a, &b] {
        line.wait_metric(
            "fbbus_bridge_refused_total{line=\"line-c\",reason=\"unknown_device\"}",
            1.0,
        );
    }
    // A stamp naming line A on line C's key: a forged origin. Line B keeps taking line A's
    // own messages after it (the forged stamp must not count as line A's).
    c.ask("put fbbus/line-c/fb/dev-b/CONV/POSITION line-a 8");
    for line in [&a, &b] {
        line.wait_metric(
            "fbbus_bridge_refused_total{line=\"line-c\",reason=\"forged_origin\"}",
            1.0,
        );
    }
    for i in 10..15 {
        publish(&press, "fb/press-8/PRESS/FORCE", force(i), false).await;
    }
    let seen = received(&mut obs_b, QUIET).await;
    only_press_8_force(&seen, "line-b");
    let values: Vec<&str> = seen.iter().map(|(_, v)| v.as_str()).collect();
    assert_eq!(
        values,
        ["10.5", "11.5", "12.5", "13.5", "14.5"],
        "line A's values on line B after line C's forged stamp"
    );
    only_press_8_force(
        &received(&mut obs_a, Duration::from_millis(300)).await,
        "line-a",
    );
    for (line, local, other) in [(&a, "press-8", "dev-b"), (&b, "dev-b", "press-8")] {
        assert_eq!(
            (
                refused(line, "line-c", "local_device"),
                refused(line, "line-c", "other_line_device"),
                refused(line, "line-c", "unknown_device"),
                refused(line, "line-c", "forged_origin"),
            ),
            (1.0, 1.0, 1.0, 1.0),
            "line {}: one refusal each (local {local}, other line's {other}, unknown press-7, \
             forged)\n{}",
            line.name,
            line.broker.metrics()
        );
    }
    // A record under its own key whose body names line A was refused as forged.
    for line in [&a, &b] {
        line.wait_metric(
            "fbbus_bridge_refused_total{line=\"line-c\",reason=\"forged_record\"}",
            1.0,
        );
    }
    // Line C's own record of dev-b, a device online on line B: line A does not move dev-b
    // to line C (it would then take line C's messages as dev-b's), line B keeps its own.
    c.ask("record line-c dev-b line-c");
    a.wait_metric(
        "fbbus_bridge_refused_total{line=\"line-c\",reason=\"claimed_device\"}",
        1.0,
    );
    b.wait_metric(
        "fbbus_bridge_refused_total{line=\"line-c\",reason=\"local_device\"}",
        2.0,
    );
    assert_eq!(a.record("dev-b").unwrap()["line"], "line-b");
    c.ask("put fbbus/line-c/fb/dev-b/CONV/POSITION line-c 9");
    a.wait_metric(
        "fbbus_bridge_refused_total{line=\"line-c\",reason=\"other_line_device\"}",
        2.0,
    );
    let leaked: Vec<_> = received(&mut obs_a, Duration::from_millis(300))
        .await
        .into_iter()
        .filter(|(topic, _)| topic.starts_with("fb/dev-b/"))
        .collect();
    assert!(
        leaked.is_empty(),
        "line C spoke for dev-b on line A: {leaked:?}"
    );
    // Loss reports: line C may tell line A what it missed of line A's (under its own key),
    // not as line B. It learns line A's run (epoch) from a stamp of line A's messages: a
    // report about another run of line A would be ignored whoever sent it.
    c.ask("subscribe fbbus/line-a/**");
    tokio::time::sleep(Duration::from_millis(300)).await;
    let mut epoch = json!(null);
    for i in 15..35 {
        publish(&press, "fb/press-8/PRESS/FORCE", force(i), false).await;
        epoch = c.ask("epoch line-a")["epoch"].clone();
        if !epoch.is_null() {
            break;
        }
        tokio::time::sleep(Duration::from_millis(100)).await;
    }
    assert!(epoch.is_u64(), "line C never saw a message of line A");
    assert_eq!(a.broker.metric(LOST_REPORTED), 0.0);
    c.ask("loss line-b line-a 7");
    c.ask("loss line-c line-a 5");
    a.wait_metric(LOST_REPORTED, 5.0);
    tokio::time::sleep(QUIET).await;
    assert_eq!(
        a.broker.metric(LOST_REPORTED),
        5.0,
        "line C's report as line B was taken"
    );
    received(&mut obs_a, Duration::from_millis(300)).await;
    received(&mut obs_b, Duration::from_millis(300)).await;
    c.send("quit");

    // 4. A zenoh application with a reader's certificate: reads line A's messages (and the
    //    bus's liveliness), and nothing it puts or declares goes anywhere.
    let mut historian = stranger(
        &endpoints,
        &identity(dir.path(), pki::bus(), "historian", &ca),
    );
    assert_eq!(historian.ask("peers 2 10"), json!({"peers": 2}));
    historian.ask("subscribe fbbus/**");
    tokio::time::sleep(Duration::from_millis(300)).await;
    let mut samples = json!(null);
    for i in 20..40 {
        publish(&press, "fb/press-8/PRESS/FORCE", force(i), false).await;
        samples = historian.ask("samples");
        if samples["samples"].as_u64() > Some(0) {
            break;
        }
        tokio::time::sleep(Duration::from_millis(100)).await;
    }
    assert_eq!(
        samples["keys"],
        json!(["fbbus/line-a/fb/press-8/PRESS/FORCE"]),
        "the reader receives line A's messages: {samples}"
    );
    assert_eq!(
        historian.ask("alive fbbus/@/line/*")["alive"],
        json!(["fbbus/@/line/line-a", "fbbus/@/line/line-b"])
    );
    historian.ask("play line-a press-7");
    historian.ask("put fbbus/historian/fb/press-8/PRESS/STOP historian true");
    historian.ask("record historian hist-1 historian");
    historian.ask("token fbbus/@/line/historian");
    historian.ask("token fbbus/@/device/historian/hist-1");
    historian.ask("put fbbus/historian/fb/hist-1/PRESS/STOP historian true");
    // Its loss report, about line A's current run (it read line A's messages above).
    assert!(historian.ask("epoch line-a")["epoch"].is_u64());
    historian.ask("loss historian line-a 3");
    tokio::time::sleep(QUIET).await;
    assert_eq!(
        a.broker.metric(LOST_REPORTED),
        5.0,
        "a reader's loss report was taken"
    );
    for line in [&a, &b] {
        assert_eq!(line.record("hist-1"), None, "line {}", line.name);
        assert_eq!(refused_any(line, "historian"), 0.0, "line {}", line.name);
    }
    historian.send("quit");

    // At the end, once more: nothing of the strangers was delivered, registered, or
    // counted as line A's, and line B's view of line A never wavered.
    only_press_8_force(
        &received(&mut obs_a, Duration::from_millis(300)).await,
        "line-a",
    );
    only_press_8_force(
        &received(&mut obs_b, Duration::from_millis(300)).await,
        "line-b",
    );
    for line in [&a, &b] {
        assert_eq!(line.record("press-7"), None, "line {}", line.name);
        assert_eq!(refused_any(line, "line-a"), 0.0, "line {}", line.name);
    }
    assert_eq!(
        b.record("press-8").map(|r| r["status"].clone()),
        Some(json!("online")),
        "line B's view of press-8 wavered"
    );
    nobody.send("quit");
    forger.send("quit");
}

// ---------------------------------------------------------------- the plain loopback bus

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn on_the_plain_loopback_bus_nobody_speaks_for_a_local_or_unannounced_device() {
    if !python_zenoh() {
        return;
    }
    let a = Line::start_on("line-a", &tcp_endpoint(), &[], "", None);
    let press = device_with(&a, "press-8", PRESS).await;
    let mut obs = V4::connect(a.port(), "watch-a", None).await.unwrap();
    obs.subscribe("fb/#").await;
    obs.subscribe("fbbus/diag/press-8").await;

    // No TLS, no access control: anyone on this host can open a session.
    let mut s = stranger(&[&a.zenoh], &[]);
    assert_eq!(s.ask("peers 1 10"), json!({"peers": 1}));
    // The issue's sequence for line A itself: a line takes nothing of its own from the bus.
    s.ask("play line-a press-7");
    s.ask("put fbbus/line-a/fb/press-8/PRESS/STOP line-a true");
    // A line of its own (`line-s`), speaking for line A's local device, for a device no
    // line announced, and with a stamp naming line A.
    s.ask("put fbbus/line-s/fb/press-8/PRESS/STOP line-s true");
    a.wait_metric(
        "fbbus_bridge_refused_total{line=\"line-s\",reason=\"local_device\"}",
        1.0,
    );
    s.ask("put fbbus/line-s/fb/press-7/PRESS/STOP line-s true");
    a.wait_metric(
        "fbbus_bridge_refused_total{line=\"line-s\",reason=\"unknown_device\"}",
        1.0,
    );
    s.ask("put fbbus/line-s/fb/press-8/PRESS/STOP line-a true");
    a.wait_metric(
        "fbbus_bridge_refused_total{line=\"line-s\",reason=\"forged_origin\"}",
        1.0,
    );
    publish(&press, "fb/press-8/PRESS/FORCE", "1.5".into(), false).await;
    let seen = received(&mut obs, QUIET).await;
    only_press_8_force(&seen, "line-a");
    assert!(
        seen.iter().any(|(topic, _)| topic == "fbbus/diag/press-8"),
        "no diagnostic of the refusal: {seen:?}"
    );
    assert!(seen.contains(&("fb/press-8/PRESS/FORCE".into(), "1.5".into())));
    assert_eq!(a.record("press-7"), None);
    assert_eq!(refused_any(&a, "line-a"), 0.0);
    assert_eq!(
        (
            refused(&a, "line-s", "local_device"),
            refused(&a, "line-s", "unknown_device"),
            refused(&a, "line-s", "forged_origin"),
        ),
        (1.0, 1.0, 1.0)
    );
    s.send("quit");
}

/// Issue 32, bounded: another line's subscriptions (its interest tokens) are held up to
/// `[bridge] max_remote_filters_per_line` per line and `max_remote_filters` in all; what
/// is beyond is counted and not honoured, a real line's subscription keeps working, and a
/// share given back can be taken again.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn another_lines_subscriptions_are_bounded_per_line_and_in_all() {
    if !python_zenoh() {
        return;
    }
    let endpoint = tcp_endpoint();
    let a = Line::start_on(
        "line-a",
        &endpoint,
        &[],
        "max_remote_filters_per_line = 5\nmax_remote_filters = 8\n",
        None,
    );
    let b = Line::plain("line-b", &[&endpoint], "");
    let press = device_with(&a, "press-8", PRESS).await;
    // Line B's client subscribes: line B holds one filter at line A.
    let mut obs_b = V4::connect(b.port(), "watch-b", None).await.unwrap();
    obs_b.subscribe("fb/press-8/#").await;
    let held = "fbbus_bridge_remote_subscriptions";
    assert_eq!(a.broker.wait_metric(held, 1.0), 1.0);

    let mut s = stranger(&[&a.zenoh], &[]);
    assert_eq!(s.ask("peers 1 10")["peers"], 1);
    let interest = |line: &str, i: usize| format!("fbbus/@/interest/{line}/fb/x{i}/%23");
    // line-s: 7 filters, 5 held (its share), 2 refused.
    for i in 0..7 {
        s.ask(&format!("token {}", interest("line-s", i)));
    }
    assert_eq!(a.broker.wait_metric(held, 6.0), 6.0);
    let refusals = |limit: &str| {
        a.broker
            .metric(&format!("fbbus_limit_refusals_total{{limit=\"{limit}\"}}"))
    };
    let per_line = a.broker.wait_metric(
        "fbbus_limit_refusals_total{limit=\"remote_subscriptions_per_line\"}",
        2.0,
    );
    assert_eq!(per_line, 2.0);
    // line-t: 5 filters, 2 held (8 in all), 3 refused.
    for i in 0..5 {
        s.ask(&format!("token {}", interest("line-t", i)));
    }
    let all = a.broker.wait_metric(
        "fbbus_limit_refusals_total{limit=\"remote_subscriptions\"}",
        3.0,
    );
    assert_eq!(all, 3.0);
    tokio::time::sleep(Duration::from_millis(300)).await;
    assert_eq!(a.broker.metric(held), 8.0);
    assert_eq!(refusals("remote_subscriptions_per_line"), 2.0);

    // Line B's subscription still works.
    drain(&mut obs_b, Duration::from_millis(200)).await;
    publish(&press, "fb/press-8/PRESS/FORCE", "2.5".into(), false).await;
    let mut got = None;
    for _ in 0..25 {
        if let Some(p) = obs_b.next_publish(Duration::from_millis(200)).await {
            got = Some(p.topic);
            break;
        }
    }
    assert_eq!(got.as_deref(), Some("fb/press-8/PRESS/FORCE"));

    // line-s gives three back: a new filter of line-t is held again.
    for i in 0..3 {
        s.ask(&format!("untoken {}", interest("line-s", i)));
    }
    let deadline = std::time::Instant::now() + Duration::from_secs(10);
    while a.broker.metric(held) > 5.0 && std::time::Instant::now() < deadline {
        tokio::time::sleep(Duration::from_millis(50)).await;
    }
    assert_eq!(a.broker.metric(held), 5.0);
    s.ask(&format!("token {}", interest("line-t", 9)));
    assert_eq!(a.broker.wait_metric(held, 6.0), 6.0);
    assert_eq!(refusals("remote_subscriptions"), 3.0);
    s.send("quit");
}

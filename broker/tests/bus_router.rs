//! The plant's zenoh router as `deploy/multi-line/` configures it: the example's files,
//! run as they are (ports and paths moved to a temporary directory).
//!
//! - `make-certs.sh` creates the bus certificates with `fbbus bus-cert`;
//! - `zenohd.json5`, from `fbbus zenohd-config`, runs in a zenoh router (Python
//!   `eclipse-zenoh` 1.10, the zenoh of zenohd 1.10: CI cannot install zenohd itself);
//! - `line-a.toml` and `line-b.toml` start two fbbus lines, clients of that router over
//!   mutual TLS.
//!
//! A device of line A reaches a subscriber of line B through the router; a stranger
//! holding line B's certificate cannot speak for line A through it (the router's access
//! control), and what it puts under its own line's keys for a device of line A is refused
//! by line A's registry check.

mod common;

use std::io::{BufRead, Write};
use std::path::Path;
use std::process::{Command, Stdio};
use std::time::{Duration, Instant};

use common::clients::V4;
use common::{fbbus_bin, free_port, http_get, Broker};

const WITHIN: Duration = Duration::from_secs(20);

fn deploy(file: &str) -> String {
    let path = format!("{}/../deploy/multi-line/{file}", env!("CARGO_MANIFEST_DIR"));
    std::fs::read_to_string(&path).unwrap_or_else(|e| panic!("{path}: {e}"))
}

/// A line of the example: its file with the ports and the registry moved.
fn line(dir: &Path, name: &str, router: u16) -> Broker {
    let (mqtt, admin) = (free_port(), free_port());
    let (default_mqtt, default_admin) = match name {
        "line-a" => ("127.0.0.1:1883", "127.0.0.1:9883"),
        _ => ("127.0.0.1:1884", "127.0.0.1:9884"),
    };
    let text = deploy(&format!("{name}.toml"))
        .replace("/var/lib/fbbus/", &format!("{}/", dir.display()))
        .replace(default_mqtt, &format!("127.0.0.1:{mqtt}"))
        .replace(default_admin, &format!("127.0.0.1:{admin}"))
        .replace("127.0.0.1:7447", &format!("127.0.0.1:{router}"));
    let line_dir = tempfile::tempdir_in(dir).unwrap();
    std::os::unix::fs::symlink(dir.join("tls"), line_dir.path().join("tls")).unwrap();
    let config = line_dir.path().join("fbbus.toml");
    std::fs::write(&config, text).unwrap();
    Broker::spawn(
        line_dir,
        config,
        format!("127.0.0.1:{mqtt}").parse().unwrap(),
        format!("127.0.0.1:{admin}").parse().unwrap(),
    )
}

/// `fbbus check-config` passes on both line files as they are, next to the certificates
/// `make-certs.sh` made, and fails on line A's file with line B's certificate.
fn check_config(dir: &Path) {
    let check = |file: &Path| {
        common::run(
            Command::new(fbbus_bin()).args(["check-config", file.to_str().unwrap()]),
            Duration::from_secs(10),
        )
    };
    for name in ["line-a", "line-b"] {
        let file = dir.join(format!("{name}.toml"));
        std::fs::write(&file, deploy(&format!("{name}.toml"))).unwrap();
        let (ok, out, err) = check(&file);
        assert!(ok, "deploy/multi-line/{name}.toml: {out}{err}");
    }
    let wrong = dir.join("wrong.toml");
    std::fs::write(
        &wrong,
        deploy("line-a.toml").replace("tls/line-a.", "tls/line-b."),
    )
    .unwrap();
    let (ok, _, err) = check(&wrong);
    assert!(!ok && err.contains("names `line-b`"), "{err}");
}

/// `zenohd.json5` is `fbbus zenohd-config`'s output for the example (paths aside), so
/// the router applies exactly the rules the lines apply.
fn the_router_file_is_what_zenohd_config_prints(tls: &Path) {
    let file = |name: &str| tls.join(name).to_str().unwrap().to_owned();
    let (ok, out, err) = common::run(
        Command::new(fbbus_bin()).args([
            "zenohd-config",
            "--name",
            "zenohd",
            "--listen",
            "tls/127.0.0.1:7447",
            "--root-ca",
            &file("bus-ca.crt"),
            "--cert",
            &file("zenohd.crt"),
            "--key",
            &file("zenohd.key"),
            "--lines",
            "line-a,line-b",
        ]),
        Duration::from_secs(10),
    );
    assert!(ok, "fbbus zenohd-config: {err}");
    let printed: serde_json::Value =
        serde_json::from_str(&out.replace(&format!("{}/", tls.display()), "/etc/zenoh/tls/"))
            .unwrap();
    let committed: String = deploy("zenohd.json5")
        .lines()
        .filter(|l| !l.trim_start().starts_with("//"))
        .collect::<Vec<_>>()
        .join("\n");
    let committed: serde_json::Value = serde_json::from_str(&committed).unwrap();
    assert_eq!(
        committed, printed,
        "deploy/multi-line/zenohd.json5 differs from `fbbus zenohd-config` (regenerate it \
         with the command in its header)"
    );
}

fn status_on(line: &Broker, id: &str) -> Option<String> {
    let (code, body) = http_get(line.admin, &format!("/api/v1/devices/{id}"))?;
    let record: serde_json::Value = (code == 200).then(|| serde_json::from_str(&body).ok())??;
    Some(format!("{} {}", record["line"], record["status"]))
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn the_example_router_holds_each_line_to_its_own_keys() {
    if !common::bus::python_zenoh() {
        return;
    }
    let dir = tempfile::tempdir().unwrap();
    let tls = dir.path().join("tls");
    let script = format!(
        "{}/../deploy/multi-line/make-certs.sh",
        env!("CARGO_MANIFEST_DIR")
    );
    let (ok, out, err) = common::run(
        Command::new("bash").args([&script, tls.to_str().unwrap(), fbbus_bin()]),
        Duration::from_secs(30),
    );
    assert!(ok, "make-certs.sh: {out}{err}");
    let ca = tls.join("bus-ca.crt");
    for name in ["line-a", "line-b", "zenohd"] {
        assert!(tls.join(format!("{name}.crt")).is_file(), "{name}: {out}");
    }
    check_config(dir.path());
    the_router_file_is_what_zenohd_config_prints(&tls);

    // The router, on the example's configuration with its port and paths moved.
    let port = free_port();
    let router_config = dir.path().join("zenohd.json5");
    std::fs::write(
        &router_config,
        deploy("zenohd.json5")
            .replace("/etc/zenoh/tls/", &format!("{}/", tls.display()))
            .replace("127.0.0.1:7447", &format!("127.0.0.1:{port}")),
    )
    .unwrap();
    let endpoint = format!("tls/127.0.0.1:{port}");
    let script = format!(
        "{}/tests/python/zenoh_router.py",
        env!("CARGO_MANIFEST_DIR")
    );
    let path = |p: &Path| p.to_str().unwrap().to_owned();
    let mut router = Command::new("python3")
        .args([
            script,
            path(&router_config),
            endpoint,
            path(&ca),
            path(&tls.join("line-b.crt")),
            path(&tls.join("line-b.key")),
        ])
        .stdin(Stdio::piped())
        .stdout(Stdio::piped())
        .spawn()
        .unwrap();
    let mut stdin = router.stdin.take().unwrap();
    let (lines_tx, lines) = std::sync::mpsc::channel::<String>();
    let stdout = router.stdout.take().unwrap();
    std::thread::spawn(move || {
        for line in std::io::BufReader::new(stdout)
            .lines()
            .map_while(Result::ok)
        {
            let _ = lines_tx.send(line);
        }
    });
    let _kill = KillOnDrop(router);
    assert_eq!(lines.recv_timeout(WITHIN).ok().as_deref(), Some("ready"));

    let a = line(dir.path(), "line-a", port);
    let b = line(dir.path(), "line-b", port);

    // plc-1 on line A, declared; a subscriber of its ports on line B and one on line A
    // (line A imports fb/# from the bus only while a local client subscribes to it).
    let mut plc = V4::connect(a.port(), "plc-1", None).await.unwrap();
    plc.subscribe("fbbus/diag/plc-1").await;
    publish(
        &plc,
        "fbbus/declare/plc-1",
        r#"{"fbs":{"CONV":{"data_out":{"SPEED":"INT"}}}}"#,
    )
    .await;
    let answer = plc.next_publish(WITHIN).await.expect("declaration answer");
    assert!(
        String::from_utf8_lossy(&answer.payload).contains("\"ok\":true"),
        "{answer:?}"
    );
    let mut on_a = V4::connect(a.port(), "watch-a", None).await.unwrap();
    on_a.subscribe("fb/#").await;
    let mut on_b = V4::connect(b.port(), "watch-b", None).await.unwrap();
    on_b.subscribe("fb/plc-1/#").await;
    let deadline = Instant::now() + WITHIN;
    while status_on(&b, "plc-1").as_deref() != Some("\"line-a\" \"online\"") {
        assert!(
            Instant::now() < deadline,
            "line B never listed plc-1 of line-a:\n{}",
            b.log_text()
        );
        tokio::time::sleep(Duration::from_millis(100)).await;
    }
    b.wait_metric("fbbus_bridge_imports", 1.0);
    a.wait_metric("fbbus_bridge_remote_subscriptions", 1.0);

    // Through the router: plc-1's messages reach line B.
    let mut got = None;
    for i in 0..50 {
        publish(&plc, "fb/plc-1/CONV/SPEED", &i.to_string()).await;
        if let Some(p) = on_b.next_publish(Duration::from_millis(200)).await {
            got = Some(p);
            break;
        }
    }
    let got = got.expect("line B got nothing of plc-1 through the router");
    assert_eq!(got.topic, "fb/plc-1/CONV/SPEED");

    // The stranger, with line B's certificate, through the same router.
    writeln!(stdin, "stranger").unwrap();
    assert_eq!(
        lines.recv_timeout(WITHIN).ok().as_deref(),
        Some("stranger done")
    );
    tokio::time::sleep(Duration::from_millis(500)).await;
    let mut forged = Vec::new();
    while let Some(p) = on_b.next_publish(Duration::from_millis(300)).await {
        if p.payload.as_ref() == b"666" || p.payload.as_ref() == b"667" {
            forged.push(p);
        }
    }
    while let Some(p) = on_a.next_publish(Duration::from_millis(300)).await {
        if p.payload.as_ref() == b"666" || p.payload.as_ref() == b"667" {
            forged.push(p);
        }
    }
    assert!(
        forged.is_empty(),
        "the stranger's messages were delivered: {forged:?}"
    );
    assert_eq!(
        status_on(&b, "press-7"),
        None,
        "line B lists the invented press-7"
    );
    // What it put under its own line's key for line A's device reached line A through
    // the router, and was refused there.
    a.wait_metric(
        "fbbus_bridge_refused_total{line=\"line-b\",reason=\"local_device\"}",
        1.0,
    );
    drop(stdin);
}

async fn publish(client: &V4, topic: &str, payload: &str) {
    client
        .client
        .publish(topic, rumqttc::QoS::AtLeastOnce, false, payload.to_owned())
        .await
        .unwrap();
}

struct KillOnDrop(std::process::Child);

impl Drop for KillOnDrop {
    fn drop(&mut self) {
        let _ = self.0.kill();
        let _ = self.0.wait();
    }
}

//! Authentication: argon2id password files, refusals, throttling, reload without
//! disconnects, Mosquitto password import and re-hashing, and secrets kept out of logs.

mod common;

use std::process::{Command, Stdio};
use std::time::Duration;

use common::clients::{V4, V5, WAIT};
use common::{add_user, Broker, Options};

const AUTH: &str = "[auth]\npassword_file = \"passwd\"\nreload_poll_ms = 200\n";

fn broker_with_users(extra: &str, users: &[(&str, &str)]) -> Broker {
    Broker::start_with(
        Options {
            extra: format!("{AUTH}{extra}"),
            ..Default::default()
        },
        |dir| {
            for (u, p) in users {
                add_user(&dir.join("passwd"), u, p);
            }
        },
    )
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn login_ok_wrong_password_unknown_user_and_anonymous() {
    let broker = broker_with_users("", &[("plc-1", "s3cret-1")]);
    let port = broker.port();

    V4::connect(port, "plc-1", Some(("plc-1", "s3cret-1")))
        .await
        .unwrap();
    V5::connect(port, "plc-1b", Some(("plc-1", "s3cret-1")))
        .await
        .unwrap();

    assert_eq!(
        V4::connect(port, "x", Some(("plc-1", "wrong")))
            .await
            .err()
            .unwrap(),
        "BadUserNamePassword"
    );
    assert_eq!(
        V5::connect(port, "x", Some(("plc-1", "wrong")))
            .await
            .err()
            .unwrap(),
        "BadUserNamePassword"
    );
    // An unknown user gets exactly the same answer as a wrong password.
    assert_eq!(
        V4::connect(port, "x", Some(("nobody", "s3cret-1")))
            .await
            .err()
            .unwrap(),
        "BadUserNamePassword"
    );
    // With a password file, anonymous access is off by default.
    assert_eq!(
        V4::connect(port, "anon", None).await.err().unwrap(),
        "NotAuthorized"
    );
    assert_eq!(
        broker.metric("fbbus_auth_failures_total{reason=\"bad_credentials\"}"),
        3.0
    );
    assert_eq!(
        broker.metric("fbbus_auth_failures_total{reason=\"missing_credentials\"}"),
        1.0
    );
    // Counted once the CONNACK is written: the client may read it first.
    assert_eq!(broker.wait_metric("fbbus_connects_total", 2.0), 2.0);
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn failed_logins_are_throttled_per_address() {
    let broker = broker_with_users(
        "[auth.throttle]\nfree_failures = 2\nbase_delay_ms = 3000\nmax_delay_ms = 3000\n",
        &[("plc-1", "right")],
    );
    let port = broker.port();
    for _ in 0..3 {
        assert_eq!(
            V4::connect(port, "x", Some(("plc-1", "guess")))
                .await
                .err()
                .unwrap(),
            "BadUserNamePassword"
        );
    }
    // Blocked now: even the right password is refused, at once, without hashing.
    assert_eq!(
        V5::connect(port, "x", Some(("plc-1", "right")))
            .await
            .err()
            .unwrap(),
        "ConnectionRateExceeded"
    );
    assert_eq!(
        V4::connect(port, "x", Some(("plc-1", "right")))
            .await
            .err()
            .unwrap(),
        "ServiceUnavailable"
    );
    assert_eq!(broker.metric("fbbus_logins_throttled_total"), 2.0);
    tokio::time::sleep(Duration::from_millis(3200)).await;
    V4::connect(port, "x", Some(("plc-1", "right")))
        .await
        .expect("allowed again after the backoff");
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn password_file_reloads_without_dropping_devices() {
    let broker = broker_with_users("", &[("plc-1", "pw-1")]);
    let port = broker.port();
    let mut dev = V4::connect(port, "plc-1", Some(("plc-1", "pw-1")))
        .await
        .unwrap();
    dev.subscribe("line/#").await;
    assert!(V4::connect(port, "plc-2", Some(("plc-2", "pw-2")))
        .await
        .is_err());

    // Edit the file: add plc-2, remove plc-1. The poll picks it up.
    let passwd = broker.path("passwd");
    add_user(&passwd, "plc-2", "pw-2");
    let (ok, _, err) = common::run(
        Command::new(common::fbbus_bin()).args([
            "passwd",
            passwd.to_str().unwrap(),
            "delete",
            "plc-1",
        ]),
        WAIT,
    );
    assert!(ok, "{err}");
    broker.wait_metric(
        "fbbus_file_reloads_total{file=\"password_file\",result=\"ok\"}",
        1.0,
    );
    let p2 = loop_connect(port, "plc-2", ("plc-2", "pw-2")).await;

    // plc-1 is still connected and served; it just cannot log in again.
    p2.client
        .publish("line/x", rumqttc::QoS::AtLeastOnce, false, "after reload")
        .await
        .unwrap();
    assert_eq!(
        dev.next_publish(WAIT).await.expect("still served").payload,
        "after reload"
    );
    assert!(dev.alive());
    // The two edits may be seen by different polls: wait until the deletion is in force.
    let mut refused = false;
    for _ in 0..50 {
        if V4::connect(port, "plc-1b", Some(("plc-1", "pw-1")))
            .await
            .is_err()
        {
            refused = true;
            break;
        }
        tokio::time::sleep(Duration::from_millis(100)).await;
    }
    assert!(refused, "plc-1 can still log in after its deletion");
    assert!(
        dev.alive(),
        "deleting plc-1 from the file did not disconnect it"
    );

    // A broken file is refused on reload; the previous users keep working.
    std::fs::write(&passwd, "this line has no colon\n").unwrap();
    broker.signal("HUP");
    broker.wait_metric(
        "fbbus_file_reloads_total{file=\"password_file\",result=\"error\"}",
        1.0,
    );
    V4::connect(port, "plc-2b", Some(("plc-2", "pw-2")))
        .await
        .expect("the last good password file stays in force");
    assert!(broker.log_text().contains("keeping the previous version"));
}

/// Connects, retrying briefly: a reload is seen within one poll interval.
async fn loop_connect(port: u16, id: &str, login: (&str, &str)) -> V4 {
    for _ in 0..50 {
        if let Ok(c) = V4::connect(port, id, Some(login)).await {
            return c;
        }
        tokio::time::sleep(Duration::from_millis(100)).await;
    }
    panic!("{id} could not log in after the reload");
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn mosquitto_password_files_work_and_are_rehashed_to_argon2id() {
    if !common::require("mosquitto_passwd") {
        return;
    }
    let broker = Broker::start_with(
        Options {
            extra: AUTH.into(),
            ..Default::default()
        },
        |dir| {
            let file = dir.join("passwd");
            let file = file.to_str().unwrap();
            // $7$: PBKDF2-SHA512, Mosquitto 2's default. $6$: salted SHA-512 (-H sha512).
            let status = Command::new("mosquitto_passwd")
                .args(["-c", "-b", file, "pbkdf2-dev", "pw-seven"])
                .status()
                .unwrap();
            assert!(status.success());
            let status = Command::new("mosquitto_passwd")
                .args(["-H", "sha512", "-b", file, "sha-dev", "pw-six"])
                .status()
                .unwrap();
            assert!(status.success());
            let text = std::fs::read_to_string(file).unwrap();
            assert!(
                text.contains("pbkdf2-dev:$7$") && text.contains("sha-dev:$6$"),
                "{text}"
            );
        },
    );
    let port = broker.port();
    assert!(V4::connect(port, "a", Some(("pbkdf2-dev", "wrong")))
        .await
        .is_err());
    V4::connect(port, "a", Some(("pbkdf2-dev", "pw-seven")))
        .await
        .unwrap();
    V5::connect(port, "b", Some(("sha-dev", "pw-six")))
        .await
        .unwrap();

    // Both entries were rewritten as argon2id after their successful login.
    assert_eq!(
        broker.wait_metric("fbbus_passwords_rehashed_total", 2.0),
        2.0
    );
    let text = std::fs::read_to_string(broker.path("passwd")).unwrap();
    assert!(text.contains("pbkdf2-dev:$argon2id$v=19$"), "{text}");
    assert!(text.contains("sha-dev:$argon2id$v=19$"), "{text}");
    assert!(!text.contains("$7$") && !text.contains("$6$"), "{text}");
    // And the same passwords still work against the new hashes.
    V4::connect(port, "c", Some(("pbkdf2-dev", "pw-seven")))
        .await
        .unwrap();
    V4::connect(port, "d", Some(("sha-dev", "pw-six")))
        .await
        .unwrap();
    assert!(V4::connect(port, "e", Some(("sha-dev", "pw-seven")))
        .await
        .is_err());
}

#[test]
fn passwd_cli_manages_argon2id_entries_and_imports_mosquitto_files() {
    let dir = tempfile::tempdir().unwrap();
    let file = dir.path().join("passwd");
    let f = file.to_str().unwrap();
    add_user(&file, "plc-1", "first-password");
    add_user(&file, "plc-2", "second-password");
    let text = std::fs::read_to_string(&file).unwrap();
    assert_eq!(
        text.lines()
            .filter(|l| l.contains(":$argon2id$v=19$m=8192,t=1,p=1$"))
            .count(),
        2
    );
    assert!(!text.contains("first-password"));
    #[cfg(unix)]
    {
        use std::os::unix::fs::PermissionsExt;
        let mode = std::fs::metadata(&file).unwrap().permissions().mode() & 0o777;
        assert_eq!(mode, 0o600);
    }

    let (ok, out, _) = common::run(
        Command::new(common::fbbus_bin()).args(["passwd", f, "list"]),
        WAIT,
    );
    assert!(ok);
    assert_eq!(out.lines().count(), 2);
    assert!(
        out.contains("plc-1\targon2id") && !out.contains('$'),
        "{out}"
    );

    let (ok, _, _) = common::run(
        Command::new(common::fbbus_bin()).args(["passwd", f, "delete", "plc-1"]),
        WAIT,
    );
    assert!(ok);
    let (ok, _, err) = common::run(
        Command::new(common::fbbus_bin()).args(["passwd", f, "delete", "plc-1"]),
        WAIT,
    );
    assert!(!ok && err.contains("no user `plc-1`"), "{err}");

    // An empty password from --stdin is refused and changes nothing.
    let before = std::fs::read_to_string(&file).unwrap();
    let mut child = Command::new(common::fbbus_bin())
        .args(["passwd", f, "add", "plc-3", "--stdin"])
        .stdin(Stdio::piped())
        .stderr(Stdio::null())
        .spawn()
        .unwrap();
    drop(child.stdin.take());
    assert!(!child.wait().unwrap().success());
    assert_eq!(std::fs::read_to_string(&file).unwrap(), before);

    if common::require("mosquitto_passwd") {
        let mosq = dir.path().join("mosquitto.passwd");
        let status = Command::new("mosquitto_passwd")
            .args(["-c", "-b", mosq.to_str().unwrap(), "old-plc", "legacy"])
            .status()
            .unwrap();
        assert!(status.success());
        let (ok, _, err) = common::run(
            Command::new(common::fbbus_bin()).args(["passwd", f, "import", mosq.to_str().unwrap()]),
            WAIT,
        );
        assert!(ok, "{err}");
        let (_, out, _) = common::run(
            Command::new(common::fbbus_bin()).args(["passwd", f, "list"]),
            WAIT,
        );
        assert!(out.contains("old-plc\tmosquitto"), "{out}");
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn passwords_and_hashes_never_reach_the_log() {
    let broker = Broker::start_with(
        Options {
            extra: AUTH.into(),
            log_level: "trace".into(),
            ..Default::default()
        },
        |dir| add_user(&dir.join("passwd"), "plc-1", "Tr0ub4dor-secret"),
    );
    let port = broker.port();
    V4::connect(port, "plc-1", Some(("plc-1", "Tr0ub4dor-secret")))
        .await
        .unwrap();
    let _ = V5::connect(port, "plc-x", Some(("plc-1", "Wr0ng-secret-guess"))).await;
    let hash_line = std::fs::read_to_string(broker.path("passwd")).unwrap();
    let salt_and_hash = hash_line.trim().rsplit('$').take(2).collect::<Vec<_>>();
    tokio::time::sleep(Duration::from_millis(300)).await;
    let log = broker.log_text();
    assert!(
        log.contains("client connected"),
        "trace log is being written"
    );
    for secret in ["Tr0ub4dor-secret", "Wr0ng-secret-guess", "$argon2id$"]
        .into_iter()
        .chain(salt_and_hash)
    {
        assert!(!log.contains(secret), "`{secret}` appears in the log");
        assert!(
            !broker.metrics().contains(secret),
            "`{secret}` appears in /metrics"
        );
    }
}

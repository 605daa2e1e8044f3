//! Issue 18, the admin endpoint's credentials: off loopback it needs `[admin]
//! password_file`, or the broker refuses to start (and `fbbus check-config` says why);
//! with the file set, every admin request (page, API and metrics alike, and a path no
//! route serves) needs HTTP Basic credentials of a user of that file, checked once per
//! peer address against a throttle. The `fbbus` commands send them from
//! `FBBUS_ADMIN_USER` and `FBBUS_ADMIN_PASSWORD`.
//!
//! The protected brokers here bind the admin endpoint to 127.0.0.1 with the file set (the
//! check applies whenever the file is set): nothing is served on a reachable address.

mod common;

use std::io::{Read, Write};
use std::net::{IpAddr, SocketAddr, TcpStream};
use std::process::Command;
use std::time::{Duration, Instant};

use common::{basic, Broker, Options};

const USER: &str = "ops";
/// Distinctive enough that finding it in a log or a metric cannot be a coincidence.
const PASSWORD: &str = "Zq7-admin-secret-Pw41";

/// One HTTP/1.0 request from `from` (a loopback address of the test's choice, so that a
/// throttled address does not lock the harness out): (status, head, body).
fn request(
    admin: SocketAddr,
    from: IpAddr,
    method: &str,
    path: &str,
    authorization: Option<&str>,
) -> (u16, String, String) {
    let socket = socket2::Socket::new(socket2::Domain::IPV4, socket2::Type::STREAM, None).unwrap();
    socket.bind(&SocketAddr::new(from, 0).into()).unwrap();
    socket
        .connect_timeout(&admin.into(), Duration::from_secs(2))
        .unwrap();
    let mut s = TcpStream::from(socket);
    s.set_read_timeout(Some(Duration::from_secs(10))).unwrap();
    let authorization = authorization
        .map(|a| format!("Authorization: {a}\r\n"))
        .unwrap_or_default();
    write!(
        s,
        "{method} {path} HTTP/1.0\r\nHost: localhost\r\n{authorization}Content-Length: 0\r\n\r\n"
    )
    .unwrap();
    let mut text = String::new();
    s.read_to_string(&mut text).unwrap();
    let (head, body) = text.split_once("\r\n\r\n").expect("an HTTP answer");
    let code = head.split_whitespace().nth(1).unwrap().parse().unwrap();
    (code, head.to_ascii_lowercase(), body.to_owned())
}

const LOCAL: IpAddr = IpAddr::V4(std::net::Ipv4Addr::LOCALHOST);

fn get(broker: &Broker, path: &str, authorization: Option<&str>) -> (u16, String, String) {
    request(broker.admin, LOCAL, "GET", path, authorization)
}

/// A broker whose admin endpoint (on 127.0.0.1) wants a user of `admin-passwd`: `ops`
/// with [`PASSWORD`]. `extra`: more TOML before the listener.
fn protected(extra: &str) -> Broker {
    Broker::start_with(
        Options {
            extra: extra.into(),
            admin_extra: "password_file = \"admin-passwd\"\n".into(),
            log_level: "debug,rumqttd=warn".into(),
            admin_authorization: Some(basic(USER, PASSWORD)),
            ..Options::default()
        },
        |dir| common::add_user(&dir.join("admin-passwd"), USER, PASSWORD),
    )
}

#[test]
fn a_non_loopback_admin_bind_without_credentials_refuses_to_start() {
    let dir = tempfile::tempdir().unwrap();
    let config = dir.path().join("line.toml");
    let mqtt = common::free_port();
    let write = |auth: &str, admin: &str| {
        std::fs::write(
            &config,
            format!(
                "{auth}[[listener]]\nname = \"main\"\nbind = \"127.0.0.1:{mqtt}\"\n\
                 [admin]\nbind = \"0.0.0.0:0\"\n{admin}"
            ),
        )
        .unwrap()
    };
    common::add_user(&dir.path().join("passwd"), "plc-1", "device-password");
    // Without any password file, and with the MQTT one only: a device's password must
    // not open the admin plane.
    for auth in ["", "[auth]\npassword_file = \"passwd\"\n"] {
        write(auth, "");
        for args in [
            vec!["serve", "--config", config.to_str().unwrap()],
            vec!["check-config", config.to_str().unwrap()],
        ] {
            let (ok, _, err) = common::run(
                Command::new(common::fbbus_bin()).args(&args),
                Duration::from_secs(20),
            );
            assert!(
                !ok,
                "{args:?} {auth:?} must refuse a non-loopback admin without credentials"
            );
            for part in [
                "line.toml",
                "admin.bind",
                "0.0.0.0:0",
                "[admin] password_file",
                "fbbus passwd",
                "127.0.0.1",
            ] {
                assert!(
                    err.contains(part),
                    "{args:?} {auth:?}: `{part}` not in {err}"
                );
            }
        }
    }
    // The MQTT password file as the admin's: refused, with the reason.
    write(
        "[auth]\npassword_file = \"passwd\"\n",
        "password_file = \"passwd\"\n",
    );
    let (ok, _, err) = common::run(
        Command::new(common::fbbus_bin()).args(["check-config", config.to_str().unwrap()]),
        Duration::from_secs(20),
    );
    assert!(!ok);
    assert!(err.contains("admin.password_file"), "{err}");
    // An admin password file of its own: the config is good (checked, not served).
    common::add_user(&dir.path().join("admin-passwd"), USER, PASSWORD);
    write("", "password_file = \"admin-passwd\"\n");
    let (ok, out, err) = common::run(
        Command::new(common::fbbus_bin()).args(["check-config", config.to_str().unwrap()]),
        Duration::from_secs(20),
    );
    assert!(ok, "{out}{err}");
    assert!(out.contains(": ok"), "{out}");
    // check-config loads the file: a broken one is named.
    std::fs::write(dir.path().join("admin-passwd"), "ops:not-a-hash\n").unwrap();
    let (ok, _, err) = common::run(
        Command::new(common::fbbus_bin()).args(["check-config", config.to_str().unwrap()]),
        Duration::from_secs(20),
    );
    assert!(!ok);
    assert!(err.contains("admin password file"), "{err}");
    assert!(err.contains("admin-passwd"), "{err}");
}

#[test]
fn requests_without_the_right_credentials_are_refused_on_every_route() {
    let broker = protected("[auth]\nreload_poll_ms = 100\n");

    // No credentials: 401 with the challenge, wherever.
    for (method, path) in [
        ("GET", "/metrics"),
        ("GET", "/healthz"),
        ("GET", "/readyz"),
        ("GET", "/api/v1/devices"),
        ("GET", "/api/v1/devices/plc-1"),
        ("GET", "/api/v1/profiles"),
        ("GET", "/"),
        ("GET", "/no/such/path"),
        ("PUT", "/api/v1/profiles/plc-1"),
        ("DELETE", "/api/v1/devices/plc-1"),
        ("POST", "/metrics"),
    ] {
        let (code, head, body) = request(broker.admin, LOCAL, method, path, None);
        assert_eq!(code, 401, "{method} {path}: {head}\n{body}");
        assert!(
            head.contains("www-authenticate: basic realm=\"fbbus admin\""),
            "{method} {path}: {head}"
        );
        assert!(body.contains("[admin] password_file"), "{body}");
        assert!(!body.contains("fbbus_"), "{method} {path} leaked: {body}");
    }
    let missing = broker.metric("fbbus_admin_auth_failures_total{reason=\"missing\"}");
    assert!(missing >= 11.0, "missing {missing}");

    // Wrong password and unknown user: one answer, counted.
    let wrong = get(&broker, "/api/v1/devices", Some(&basic(USER, "wrong")));
    let unknown = get(&broker, "/api/v1/devices", Some(&basic("nobody", PASSWORD)));
    let garbage = get(&broker, "/api/v1/devices", Some("Basic !!!"));
    for (code, head, _) in [&wrong, &unknown, &garbage] {
        assert_eq!(*code, 401);
        assert!(head.contains("www-authenticate: basic"), "{head}");
    }
    assert_eq!(wrong.2, unknown.2, "unknown user and wrong password differ");
    assert_eq!(wrong.2, garbage.2);
    assert!(
        !wrong.2.contains("wrong") && !wrong.2.contains("nobody"),
        "{}",
        wrong.2
    );
    assert_eq!(
        broker.metric("fbbus_admin_auth_failures_total{reason=\"invalid\"}"),
        3.0
    );

    // The right credentials: every route answers as without the check.
    let right = basic(USER, PASSWORD);
    let (code, _, body) = get(&broker, "/metrics", Some(&right));
    assert_eq!(code, 200);
    assert!(
        body.contains("fbbus_admin_auth_failures_total{reason=\"missing\"}"),
        "{body}"
    );
    assert!(body.contains("fbbus_connections"), "{body}");
    let (code, _, body) = get(&broker, "/api/v1/devices", Some(&right));
    assert_eq!(code, 200, "{body}");
    let devices: serde_json::Value = serde_json::from_str(&body).unwrap();
    assert_eq!(devices["line"], "test");
    assert_eq!(devices["devices"], serde_json::json!([]));
    assert_eq!(get(&broker, "/readyz", Some(&right)).0, 200);
    assert_eq!(get(&broker, "/healthz", Some(&right)).2, "ok\n");
    assert_eq!(get(&broker, "/no/such/path", Some(&right)).0, 404);
    // A write passes both gates from the host: the device is unknown, 404 (not 401/403).
    let (code, _, body) = request(
        broker.admin,
        LOCAL,
        "DELETE",
        "/api/v1/devices/plc-1",
        Some(&right),
    );
    assert_eq!(code, 404, "{body}");
    // Again: from the credential cache, the same answers.
    for _ in 0..20 {
        assert_eq!(get(&broker, "/readyz", Some(&right)).0, 200);
    }

    // The admin password file reloads: a user added while the broker runs gets in.
    let second = basic("ops-2", "second-password");
    assert_eq!(get(&broker, "/readyz", Some(&second)).0, 401);
    common::add_user(&broker.path("admin-passwd"), "ops-2", "second-password");
    let deadline = Instant::now() + Duration::from_secs(10);
    while get(&broker, "/readyz", Some(&second)).0 != 200 {
        assert!(
            Instant::now() < deadline,
            "the added admin user was not let in"
        );
        std::thread::sleep(Duration::from_millis(100));
    }
    assert!(
        broker.metric("fbbus_file_reloads_total{file=\"admin_password_file\",result=\"ok\"}")
            >= 1.0
    );

    // No secret anywhere: not the password, not the header that carries it.
    let metrics = broker.metrics();
    let log = broker.log_text();
    for secret in [PASSWORD, &right["Basic ".len()..], "second-password"] {
        assert!(!metrics.contains(secret), "a secret in /metrics");
        assert!(!log.contains(secret), "a secret in the log:\n{log}");
    }
    // The refusals were logged (at most once a minute per reason), the peer named.
    assert!(
        log.contains("admin endpoint: request with wrong credentials refused"),
        "{log}"
    );
    assert_eq!(
        log.matches("admin endpoint: request with wrong credentials refused")
            .count(),
        1,
        "{log}"
    );
}

#[test]
fn repeated_wrong_passwords_throttle_the_address() {
    // Two free failures, then a minute.
    let broker = protected(
        "[auth.throttle]\nfree_failures = 2\nbase_delay_ms = 60000\nmax_delay_ms = 60000\n",
    );
    let guesser: IpAddr = "127.0.0.2".parse().unwrap();
    let right = basic(USER, PASSWORD);
    let wrong = basic(USER, "guess");
    for i in 0..3 {
        let (code, _, _) = request(broker.admin, guesser, "GET", "/metrics", Some(&wrong));
        assert_eq!(code, 401, "failure {i}");
    }
    // Throttled: refused without a check, the right password too.
    for authorization in [&wrong, &right] {
        let (code, head, body) = request(
            broker.admin,
            guesser,
            "GET",
            "/metrics",
            Some(authorization),
        );
        assert_eq!(code, 429, "{head}\n{body}");
        let retry: u64 = head
            .lines()
            .find_map(|l| l.strip_prefix("retry-after:"))
            .expect("Retry-After")
            .trim()
            .parse()
            .unwrap();
        assert!((1..=60).contains(&retry), "retry after {retry}");
        assert!(body.contains("too many failed logins"), "{body}");
        assert!(!body.contains("fbbus_"), "{body}");
    }
    // Another address is not throttled.
    let (code, _, body) = get(&broker, "/metrics", Some(&right));
    assert_eq!(code, 200);
    assert_eq!(
        common::metric_value(
            &body,
            "fbbus_admin_auth_failures_total{reason=\"throttled\"}"
        ),
        2.0
    );
    assert_eq!(
        common::metric_value(&body, "fbbus_admin_auth_failures_total{reason=\"invalid\"}"),
        3.0
    );
    // The MQTT logins count apart: the admin throttle did not block the address there.
    assert_eq!(
        common::metric_value(&body, "fbbus_logins_throttled_total"),
        0.0
    );
    assert!(broker
        .log_text()
        .contains("too many failed logins from this address"));
}

#[test]
fn fbbus_commands_send_the_credentials_from_the_environment() {
    let broker = protected("");
    let admin = broker.admin.to_string();
    let devices = |env: &[(&str, &str)]| {
        let mut cmd = Command::new(common::fbbus_bin());
        cmd.args(["devices", "--admin", &admin, "--json"])
            .env_remove("FBBUS_ADMIN_USER")
            .env_remove("FBBUS_ADMIN_PASSWORD");
        for (k, v) in env {
            cmd.env(k, v);
        }
        common::run(&mut cmd, Duration::from_secs(20))
    };

    let (ok, _, err) = devices(&[]);
    assert!(!ok);
    assert!(
        err.contains("FBBUS_ADMIN_USER") && err.contains("FBBUS_ADMIN_PASSWORD"),
        "{err}"
    );
    assert!(err.contains("requires credentials"), "{err}");

    let (ok, _, err) = devices(&[
        ("FBBUS_ADMIN_USER", USER),
        ("FBBUS_ADMIN_PASSWORD", "wrong"),
    ]);
    assert!(!ok);
    assert!(err.contains("refused the credentials"), "{err}");
    assert!(!err.contains("wrong"), "the password echoed: {err}");

    let (ok, _, err) = devices(&[("FBBUS_ADMIN_USER", USER)]);
    assert!(!ok);
    assert!(err.contains("FBBUS_ADMIN_PASSWORD"), "{err}");

    let (ok, out, err) = devices(&[
        ("FBBUS_ADMIN_USER", USER),
        ("FBBUS_ADMIN_PASSWORD", PASSWORD),
    ]);
    assert!(ok, "{out}{err}");
    assert!(!out.contains(PASSWORD) && !err.contains(PASSWORD));

    // A write (DELETE) sends them too: the unknown device is the answer, not 401.
    let (ok, _, err) = common::run(
        Command::new(common::fbbus_bin())
            .args(["devices", "forget", "plc-9", "--admin", &admin])
            .env("FBBUS_ADMIN_USER", USER)
            .env("FBBUS_ADMIN_PASSWORD", PASSWORD),
        Duration::from_secs(20),
    );
    assert!(!ok);
    assert!(err.contains("plc-9"), "{err}");
    assert!(!err.contains("FBBUS_ADMIN"), "{err}");
}

//! Issue 33, "Fair shares": what one client can spend of what others need, each attack
//! run as a stranger would against the real `fbbus` on loopback, with the outcome the
//! broker's rule gives.

mod common;

use std::io::{Read, Write};
use std::net::{SocketAddr, TcpStream};
use std::time::Duration;

use common::{Broker, Options};

const PROFILE: &str = r#"device = "rebind"
[interface.fbs.CONV]
data_out = { SPEED = "REAL" }
"#;

/// One HTTP/1.1 request with `headers`; the status code.
fn request(admin: SocketAddr, head: &str, body: &str) -> u16 {
    let mut s = TcpStream::connect_timeout(&admin, Duration::from_secs(2)).unwrap();
    s.set_read_timeout(Some(Duration::from_secs(5))).unwrap();
    write!(
        s,
        "{head}\r\nConnection: close\r\nContent-Length: {}\r\n\r\n{body}",
        body.len()
    )
    .unwrap();
    let mut text = String::new();
    let _ = s.read_to_string(&mut text);
    text.split_whitespace()
        .nth(1)
        .and_then(|c| c.parse().ok())
        .unwrap_or_else(|| panic!("no HTTP answer: {text:?}"))
}

/// DNS rebinding: a page on `evil.example` that rebinds its name to 127.0.0.1 makes the
/// browser on the broker's host send `PUT /api/v1/profiles/rebind` from loopback with
/// `Host: evil.example` and `Origin: http://evil.example`. Refused (403), counted, and
/// no profile is written; the same request addressed to the broker's IP (as
/// `fbbus declare` sends it), or to a name in `[admin] allowed_hosts`, is accepted.
#[test]
fn admin_writes_refuse_a_rebound_name() {
    let broker = Broker::start_with(
        Options {
            extra: "[fb]\nprofiles_dir = \"profiles\"\n".into(),
            admin_extra: "allowed_hosts = [\"line1-broker\"]".into(),
            ..Default::default()
        },
        |dir| std::fs::create_dir(dir.join("profiles")).unwrap(),
    );
    let written = || broker.path("profiles/rebind.toml").exists();
    let put = |headers: &str| {
        request(
            broker.admin,
            &format!("PUT /api/v1/profiles/rebind HTTP/1.1\r\n{headers}"),
            PROFILE,
        )
    };
    let delete = |headers: &str| {
        request(
            broker.admin,
            &format!("DELETE /api/v1/devices/rebind HTTP/1.1\r\n{headers}"),
            "",
        )
    };

    assert_eq!(
        put("Host: evil.example\r\nOrigin: http://evil.example"),
        403
    );
    assert_eq!(put("Host: evil.example:9883"), 403);
    assert_eq!(
        put("Host: 127.0.0.1\r\nOrigin: http://evil.example:9883"),
        403
    );
    assert_eq!(delete("Host: evil.example"), 403);
    assert!(!written(), "a rebound page wrote a profile");
    assert_eq!(
        broker.metric("fbbus_admin_writes_refused_total{reason=\"host\"}"),
        3.0
    );
    assert_eq!(
        broker.metric("fbbus_admin_writes_refused_total{reason=\"origin\"}"),
        1.0
    );
    assert_eq!(
        broker
            .log_text()
            .matches("admin write refused (403)")
            .count(),
        2,
        "logged once a minute per reason:\n{}",
        broker.log_text()
    );

    let addr = broker.admin.to_string();
    assert_eq!(put(&format!("Host: {addr}")), 200);
    assert!(written());
    assert_eq!(
        put("Host: line1-broker:9883\r\nOrigin: http://line1-broker:9883"),
        200
    );
    assert_eq!(put("Host: localhost"), 200);
    // The console's own reads are not writes: answered whatever the name.
    assert_eq!(
        request(
            broker.admin,
            "GET /api/v1/profiles HTTP/1.1\r\nHost: 127.0.0.1",
            ""
        ),
        200
    );
}

/// A device locked out for good (issue 33, 1): with the default `[auth] client_id =
/// "any"`, user devA connects with client id `devB` and clean session 0 while devB has no
/// session, then leaves; the real devB was then refused its own id forever (the kept
/// session was devA's). A client id that is a user's name is that user's: devA (and an
/// anonymous client) is refused it (0x02, `client_id_reserved`), devB gets in; other
/// client ids stay free for any user.
#[test]
fn a_users_name_is_not_anothers_client_id() {
    use common::raw::{Connect, RawClient};
    let broker = Broker::start_with(
        Options {
            extra: "[auth]\npassword_file = \"passwd\"\n".into(),
            listener_extra: "allow_anonymous = true\n".into(),
            ..Default::default()
        },
        |dir| {
            common::add_user(&dir.join("passwd"), "devA", "pwA");
            common::add_user(&dir.join("passwd"), "devB", "pwB");
        },
    );
    let connect = |client_id: &str, login: Option<(&str, &str)>| {
        let mut raw = RawClient::connect(broker.port());
        let code = raw.handshake(&Connect {
            version: 4,
            client_id,
            keep_alive: 30,
            clean: false,
            login,
            ..Default::default()
        });
        (code, raw)
    };
    let (code, _) = connect("devB", Some(("devA", "pwA")));
    assert_eq!(code, 0x02, "devA opened a session under devB's name");
    let (code, _) = connect("devB", None);
    assert_eq!(
        code, 0x02,
        "an anonymous client opened a session under devB's name"
    );
    assert_eq!(
        broker.metric("fbbus_connects_refused_total{reason=\"client_id_reserved\"}"),
        2.0
    );
    let (code, devb) = connect("devB", Some(("devB", "pwB")));
    assert_eq!(code, 0x00, "devB refused its own id");
    drop(devb);
    // Any other client id stays free under client_id = "any".
    let (code, _) = connect("devA-tool", Some(("devA", "pwA")));
    assert_eq!(code, 0x00);
    let (code, _) = connect("hmi-1", Some(("devB", "pwB")));
    assert_eq!(code, 0x00);
}

/// Admin passwords guessed from many addresses (issue 33, 5: 100 of 100 guesses were
/// checked from 20 loopback addresses, each under its address's free failures): the
/// user's own count blocks them after `[auth.throttle] free_failures`, whatever the
/// address, while the scraper whose credentials the broker verified before goes on.
#[test]
fn admin_guesses_from_many_addresses_meet_the_users_block() {
    let basic = common::basic;
    let right = basic("ops", "Right-Pw-1");
    let broker = Broker::start_with(
        common::Options {
            admin_extra: "password_file = \"admin-passwd\"\n".into(),
            admin_authorization: Some(right.clone()),
            ..Default::default()
        },
        |dir| common::add_user(&dir.join("admin-passwd"), "ops", "Right-Pw-1"),
    );
    let admin = broker.admin;
    let from = |last: u8, authorization: &str| -> u16 {
        let socket =
            socket2::Socket::new(socket2::Domain::IPV4, socket2::Type::STREAM, None).unwrap();
        let ip = std::net::IpAddr::from([127, 0, 0, last]);
        socket.bind(&SocketAddr::new(ip, 0).into()).unwrap();
        socket
            .connect_timeout(&admin.into(), Duration::from_secs(2))
            .unwrap();
        let mut s = TcpStream::from(socket);
        s.set_read_timeout(Some(Duration::from_secs(10))).unwrap();
        write!(
            s,
            "GET /metrics HTTP/1.0\r\nHost: 127.0.0.1\r\nAuthorization: {authorization}\r\n\r\n"
        )
        .unwrap();
        let mut text = String::new();
        let _ = s.read_to_string(&mut text);
        text.split_whitespace().nth(1).unwrap().parse().unwrap()
    };
    let (mut checked, mut throttled) = (0, 0);
    for round in 0..5u8 {
        for address in 0..20u8 {
            match from(
                10 + address,
                &basic("ops", &format!("guess-{round}-{address}")),
            ) {
                401 => checked += 1,
                429 => throttled += 1,
                code => panic!("answered {code}"),
            }
        }
    }
    assert_eq!(checked + throttled, 100);
    assert!(checked <= 6, "{checked} of 100 guesses were checked");
    assert_eq!(from(1, &right), 200, "the verified scraper was blocked");
    assert!(broker
        .log_text()
        .contains("too many failed logins for this user"));
}

/// Budgets reset on reconnect (issue 33, 5): a device that reconnects before each
/// declaration got a fresh `declarations_per_minute` every time (91 declarations a second
/// against 60 a minute). The budget is its device's now: 3 a minute are accepted over 10
/// connections, the rest refused 0x97; another device has its own.
#[test]
fn a_reconnecting_device_keeps_its_declaration_budget() {
    use common::fb::Dev;
    const DECLARATION: &str = r#"{"fbs":{"CONV":{"data_out":{"POSITION":"INT"}}}}"#;
    let broker = Broker::start_with(
        Options {
            extra: "[fb]\nregistry_file = \"\"\ndeclarations_per_minute = 3\n".into(),
            ..Default::default()
        },
        |_| {},
    );
    let mut codes = Vec::new();
    for _ in 0..10 {
        let mut dev = Dev::connect(broker.port(), 5, "looper");
        codes.push(dev.declare(DECLARATION));
        dev.disconnect();
    }
    assert_eq!(codes.iter().filter(|c| **c == 0).count(), 3, "{codes:?}");
    assert_eq!(codes.iter().filter(|c| **c == 0x97).count(), 7, "{codes:?}");
    let mut other = Dev::connect(broker.port(), 5, "calm");
    assert_eq!(other.declare(DECLARATION), 0);
}

/// Reconnection starved before CONNECT (issue 33, 2): a stranger on one address keeps
/// 200 sockets that sent half a CONNECT (with `max_connections = 100`, every slot); a
/// device that then reconnects from another address got in 2 times in 18. Now one
/// address has at most `max_pending_per_address` connections before CONNECT: the rest are
/// closed at accept and counted, and 18 of 18 devices get in while the flood lasts.
#[test]
fn half_connects_from_one_address_cannot_starve_reconnection() {
    use common::raw::{Connect, RawClient};
    let broker = Broker::start_with(
        Options {
            extra: "max_connections = 100\nmax_pending_per_address = 16\n".into(),
            ..Default::default()
        },
        |_| {},
    );
    let mqtt = SocketAddr::from(([127, 0, 0, 1], broker.port()));
    let stranger = std::net::IpAddr::from([127, 0, 0, 77]);
    let mut held = Vec::new();
    for _ in 0..200 {
        let socket =
            socket2::Socket::new(socket2::Domain::IPV4, socket2::Type::STREAM, None).unwrap();
        socket.bind(&SocketAddr::new(stranger, 0).into()).unwrap();
        socket
            .connect_timeout(&mqtt.into(), Duration::from_secs(2))
            .unwrap();
        let mut s = TcpStream::from(socket);
        // The fixed header and half of a CONNECT's variable header, then nothing.
        let _ = s.write_all(&[0x10, 0x10, 0x00, 0x04, b'M', b'Q']);
        held.push(s);
    }
    // Let the broker accept them all.
    std::thread::sleep(Duration::from_millis(500));
    let refused = broker.metric("fbbus_connects_refused_total{reason=\"pending_per_address\"}");
    assert!(refused >= 180.0, "{refused} refused at accept");
    let mut got_in = 0;
    for i in 0..18 {
        let id = format!("device-{i}");
        let mut raw = RawClient::connect(broker.port());
        let code = raw.handshake(&Connect {
            version: 4,
            client_id: &id,
            keep_alive: 30,
            clean: true,
            ..Default::default()
        });
        if code == 0 {
            got_in += 1;
        }
    }
    assert_eq!(
        got_in, 18,
        "devices got in while the flood held its sockets"
    );
    assert_eq!(
        broker
            .log_text()
            .matches("have not sent CONNECT ([broker] max_pending_per_address)")
            .count(),
        1,
        "logged once a minute"
    );
    drop(held);
}

/// The admin plane starved (issue 33, 2): 64 admin connections held with unfinished
/// headers, and `/healthz` answered 0 of 18 probes in 20 s (a liveness probe would
/// restart the broker). One address now holds at most a quarter of the admin slots, so
/// an orchestrator's probes from another address are answered.
#[test]
fn unfinished_admin_requests_from_one_address_cannot_fail_the_probes() {
    let broker = Broker::start();
    let stranger = std::net::IpAddr::from([127, 0, 0, 88]);
    let mut held = Vec::new();
    for _ in 0..100 {
        let socket =
            socket2::Socket::new(socket2::Domain::IPV4, socket2::Type::STREAM, None).unwrap();
        socket.bind(&SocketAddr::new(stranger, 0).into()).unwrap();
        socket
            .connect_timeout(&broker.admin.into(), Duration::from_secs(2))
            .unwrap();
        let mut s = TcpStream::from(socket);
        let _ = s.write_all(b"GET /healthz HTTP/1.1\r\nHost: 127.0.0.1\r\nX-Slow: ");
        held.push(s);
    }
    std::thread::sleep(Duration::from_millis(300));
    let answered = (0..18)
        .filter(|_| common::http_get(broker.admin, "/healthz").is_some_and(|(code, _)| code == 200))
        .count();
    assert_eq!(
        answered, 18,
        "probes answered while a stranger held admin slots"
    );
    assert!(broker.metric("fbbus_admin_connections_refused_total") >= 80.0);
    drop(held);
}

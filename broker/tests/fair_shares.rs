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
    use base64::Engine;
    let dir = tempfile::tempdir().unwrap();
    common::add_user(&dir.path().join("admin-passwd"), "ops", "Right-Pw-1");
    let mqtt: SocketAddr = format!("127.0.0.1:{}", common::free_port())
        .parse()
        .unwrap();
    let admin: SocketAddr = format!("127.0.0.1:{}", common::free_port())
        .parse()
        .unwrap();
    let config = dir.path().join("fbbus.toml");
    std::fs::write(
        &config,
        format!(
            "[broker]\nline = \"test\"\n[[listener]]\nname = \"main\"\nbind = \"{mqtt}\"\n\
             [admin]\nbind = \"{admin}\"\npassword_file = \"admin-passwd\"\n"
        ),
    )
    .unwrap();
    let basic = |user: &str, pw: &str| {
        let token = base64::engine::general_purpose::STANDARD.encode(format!("{user}:{pw}"));
        format!("Basic {token}")
    };
    let right = basic("ops", "Right-Pw-1");
    let broker = Broker::spawn_as(dir, config, mqtt, admin, &[], Some(right.clone()));
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

//! MQTT over WebSockets (issue 35): `kind = "ws"` listeners, with and without TLS, against
//! real clients: Eclipse paho-mqtt's `transport="websockets"` (`python/ws_paho.py`) and
//! MQTT.js, the npm package's browser build, in headless Chromium (`js/ws_hmi.html`,
//! driven by `python/ws_browser.py` over WebDriver, the page and library served by this
//! test on loopback). Also: the handshake's checks (path, subprotocol, origin), a
//! non-loopback `ws` listener without authentication refusing to start, and the log line
//! naming the protocol when a WebSocket client reaches a plain MQTT port or the other way
//! round.

mod common;

use std::io::{Read, Write};
use std::net::{SocketAddr, TcpListener, TcpStream};
use std::path::{Path, PathBuf};
use std::process::Command;
use std::time::{Duration, Instant};

use common::pki::Pki;
use common::raw::{self, RawClient};
use common::{Broker, Options};
use serde_json::Value;

const PAHO: &str = concat!(env!("CARGO_MANIFEST_DIR"), "/tests/python/ws_paho.py");
const BROWSER: &str = concat!(env!("CARGO_MANIFEST_DIR"), "/tests/python/ws_browser.py");
const PAGE: &str = include_str!("js/ws_hmi.html");
const LIMIT: Duration = Duration::from_secs(60);

/// A broker whose main listener speaks MQTT over WebSockets (`extra_keys` added to it).
fn ws_broker(extra_keys: &str, prepare: impl FnOnce(&Path)) -> Broker {
    Broker::start_with(
        Options {
            listener_extra: format!("kind = \"ws\"\n{extra_keys}"),
            ..Default::default()
        },
        prepare,
    )
}

/// A wss broker: the test CA's certificate for localhost and 127.0.0.1.
fn wss_broker() -> Broker {
    let pki = Pki::generate(
        "fbbus ws test CA",
        &["localhost"],
        &["localhost", "127.0.0.1"],
    );
    // The CA is written as bus-ca.crt, the server's as localhost.crt and .key.
    ws_broker(
        "[listener.tls]\ncert = \"localhost.crt\"\nkey = \"localhost.key\"\n",
        |dir| {
            pki.write(dir, "localhost");
        },
    )
}

fn paho(broker: &Broker, extra: &[&str]) -> Value {
    let mut cmd = Command::new("python3");
    cmd.arg("-u")
        .arg(PAHO)
        .args(["--port", &broker.port().to_string()])
        .args(extra);
    let (ok, out, err) = common::run(&mut cmd, LIMIT);
    assert!(
        ok,
        "ws_paho.py {extra:?} failed\n--- stdout\n{out}\n--- stderr\n{err}\n--- broker log\n{}",
        broker.log_text()
    );
    serde_json::from_str(out.trim()).unwrap_or_else(|e| panic!("{e}: {out}"))
}

fn assert_accepted(broker: &Broker, transport: &str, min: f64) {
    let series =
        format!(r#"fbbus_listener_accepted_total{{listener="main",transport="{transport}"}}"#);
    let got = broker.wait_metric(&series, min);
    assert!(got >= min, "{series} = {got}\n{}", broker.metrics());
}

#[test]
fn paho_over_websockets_publishes_typed_values_and_gets_refusals() {
    if !common::require_paho() {
        return;
    }
    let broker = ws_broker("", |_| {});
    let seen = paho(&broker, &["--protocol", "5"]);
    assert_eq!(seen["bool_puback"], 0, "{seen}");
    assert_eq!(seen["delivered"][1], "true", "{seen}");
    assert_eq!(seen["refused_puback"], 0x99, "{seen}");
    let seen = paho(&broker, &["--protocol", "311"]);
    assert_eq!(seen["delivered"][1], "true", "{seen}");
    assert_accepted(&broker, "ws", 2.0);
    // The typed refusal is the ordinary one, counted as on TCP.
    let series = r#"fbbus_typed_messages_rejected_total{device="ws-dev",port="PANEL.COUNT",reason="payload_format_invalid"}"#;
    assert_eq!(broker.wait_metric(series, 1.0), 1.0, "{}", broker.metrics());
    let log = broker.log_text();
    assert!(
        log.contains("transport=\"ws\"") || log.contains("transport=ws"),
        "{log}"
    );
}

#[test]
fn paho_over_wss_with_the_test_ca() {
    if !common::require_paho() {
        return;
    }
    let broker = wss_broker();
    let ca = broker.path("bus-ca.crt");
    let seen = paho(&broker, &["--ca", ca.to_str().unwrap()]);
    assert_eq!(seen["delivered"][1], "true", "{seen}");
    assert_eq!(seen["refused_puback"], 0x99, "{seen}");
    assert_accepted(&broker, "wss", 1.0);
}

#[test]
fn paho_with_a_password_on_a_ws_listener_that_wants_one() {
    if !common::require_paho() {
        return;
    }
    let broker = Broker::start_with(
        Options {
            extra: "[auth]\npassword_file = \"passwd\"\n".into(),
            listener_extra: "kind = \"ws\"\n".into(),
            ..Default::default()
        },
        |dir| common::add_user(&dir.join("passwd"), "ws-dev", "s3cret-pass"),
    );
    let seen = paho(&broker, &["--user", "ws-dev", "--password", "s3cret-pass"]);
    assert_eq!(seen["delivered"][1], "true", "{seen}");
    // Without credentials: refused as on TCP.
    let mut cmd = Command::new("python3");
    cmd.arg("-u")
        .arg(PAHO)
        .args(["--port", &broker.port().to_string()]);
    let (ok, out, _) = common::run(&mut cmd, LIMIT);
    assert!(!ok && out.contains("CONNECT refused"), "{out}");
}

/// Writes a config with one `ws` listener on `bind` and no `[auth]`.
fn config_with_ws_on(dir: &Path, bind: &str) -> PathBuf {
    let admin = common::free_port();
    let path = dir.join("fbbus.toml");
    std::fs::write(
        &path,
        format!(
            "[broker]\nline = \"t\"\n[[listener]]\nname = \"hmi\"\nkind = \"ws\"\nbind = \"{bind}\"\n\
             [admin]\nbind = \"127.0.0.1:{admin}\"\n"
        ),
    )
    .unwrap();
    path
}

#[test]
fn a_non_loopback_ws_listener_without_authentication_refuses_to_start() {
    let dir = tempfile::tempdir().unwrap();
    let config = config_with_ws_on(dir.path(), &format!("0.0.0.0:{}", common::free_port()));
    let (ok, _, err) = common::run(
        Command::new(common::fbbus_bin()).args(["serve", "--config", config.to_str().unwrap()]),
        Duration::from_secs(10),
    );
    assert!(!ok, "started: {err}");
    assert!(
        err.contains("listener[0].bind") && err.contains("must require authentication"),
        "{err}"
    );
    // The same listener on loopback starts (the check is the bind address, not the kind).
    let config = config_with_ws_on(dir.path(), &format!("127.0.0.1:{}", common::free_port()));
    let (ok, _, err) = common::run(
        Command::new(common::fbbus_bin()).args(["check-config", config.to_str().unwrap()]),
        Duration::from_secs(10),
    );
    assert!(ok, "{err}");
    // WebSocket keys on a plain listener are a mistake, said so.
    std::fs::write(
        &config,
        "[[listener]]\nname = \"a\"\nbind = \"127.0.0.1:1\"\npath = \"/mqtt\"\n",
    )
    .unwrap();
    let (ok, _, err) = common::run(
        Command::new(common::fbbus_bin()).args(["check-config", config.to_str().unwrap()]),
        Duration::from_secs(10),
    );
    assert!(!ok && err.contains("listener[0].path"), "{err}");
}

/// The status line and head of one raw HTTP upgrade request to `addr`.
fn upgrade(addr: SocketAddr, path: &str, headers: &str) -> (u16, String) {
    let mut s = TcpStream::connect_timeout(&addr, Duration::from_secs(2)).unwrap();
    s.set_read_timeout(Some(Duration::from_secs(5))).unwrap();
    let request = format!(
        "GET {path} HTTP/1.1\r\nHost: 127.0.0.1\r\nConnection: Upgrade\r\nUpgrade: websocket\r\n\
         Sec-WebSocket-Version: 13\r\nSec-WebSocket-Key: dGhlIHNhbXBsZSBub25jZQ==\r\n{headers}\r\n"
    );
    // A plain MQTT listener closes at the request's first bytes: the rest of the write
    // can then meet a closed socket (EPIPE), which is that listener's answer too.
    if let Err(e) = s.write_all(request.as_bytes()) {
        assert!(
            matches!(
                e.kind(),
                std::io::ErrorKind::BrokenPipe | std::io::ErrorKind::ConnectionReset
            ),
            "{e}"
        );
        return (0, String::new());
    }
    let mut head = Vec::new();
    let mut byte = [0u8; 1];
    while !head.ends_with(b"\r\n\r\n") && head.len() < 4096 {
        match s.read(&mut byte) {
            Ok(1) => head.push(byte[0]),
            _ => break,
        }
    }
    let head = String::from_utf8_lossy(&head).to_ascii_lowercase();
    let code = head
        .split_whitespace()
        .nth(1)
        .and_then(|c| c.parse().ok())
        .unwrap_or(0);
    (code, head)
}

#[test]
fn the_handshake_checks_path_subprotocol_and_origin() {
    let broker = ws_broker(
        "path = \"/line/mqtt\"\nallowed_origins = [\"https://hmi.example\"]\n",
        |_| {},
    );
    let (code, head) = upgrade(
        broker.mqtt,
        "/line/mqtt",
        "Sec-WebSocket-Protocol: mqtt\r\n",
    );
    assert_eq!(code, 101, "{head}");
    assert!(head.contains("sec-websocket-protocol: mqtt\r\n"), "{head}");
    let (code, head) = upgrade(
        broker.mqtt,
        "/line/mqtt",
        "Sec-WebSocket-Protocol: mqttv3.1\r\nOrigin: https://hmi.example\r\n",
    );
    assert_eq!(code, 101, "{head}");
    assert!(
        head.contains("sec-websocket-protocol: mqttv3.1\r\n"),
        "{head}"
    );
    for (path, headers, status, reason) in [
        ("/mqtt", "Sec-WebSocket-Protocol: mqtt\r\n", 404, "ws_path"),
        ("/line/mqtt", "", 400, "ws_subprotocol"),
        (
            "/line/mqtt",
            "Sec-WebSocket-Protocol: mqtt\r\nOrigin: https://evil.example\r\n",
            403,
            "ws_origin",
        ),
    ] {
        let (code, head) = upgrade(broker.mqtt, path, headers);
        assert_eq!(code, status, "{path} {headers:?}: {head}");
        assert!(head.contains("content-type: text/plain"), "{head}");
        let series = format!(r#"fbbus_connects_refused_total{{reason="{reason}"}}"#);
        assert_eq!(broker.wait_metric(&series, 1.0), 1.0, "{series}");
    }
    assert!(
        broker.log_text().contains("WebSocket connection refused"),
        "{}",
        broker.log_text()
    );
}

#[test]
fn a_protocol_at_the_wrong_kind_of_listener_is_named_in_the_log() {
    let ws_port = common::free_port();
    let broker = Broker::start_with(
        Options {
            extra: format!(
                "[[listener]]\nname = \"web\"\nkind = \"ws\"\nbind = \"127.0.0.1:{ws_port}\"\n"
            ),
            ..Default::default()
        },
        |_| {},
    );
    // Node-RED's `ws://host:1883/mqtt` at the plain MQTT port.
    let (code, _) = upgrade(broker.mqtt, "/mqtt", "Sec-WebSocket-Protocol: mqtt\r\n");
    assert_eq!(code, 0, "a plain MQTT port answers no HTTP");
    // An MQTT client at the WebSocket port.
    let ws: SocketAddr = format!("127.0.0.1:{ws_port}").parse().unwrap();
    let mut c = RawClient::connect(ws.port());
    c.send(&raw::Connect::default().bytes());
    assert_eq!(
        c.read_packet(),
        None,
        "no CONNACK from a WebSocket listener"
    );
    let deadline = Instant::now() + Duration::from_secs(10);
    let wanted = [
        "an HTTP request (a WebSocket handshake?) reached a plain MQTT listener",
        "an MQTT CONNECT reached a WebSocket listener",
    ];
    while Instant::now() < deadline && !wanted.iter().all(|w| broker.log_text().contains(w)) {
        std::thread::sleep(Duration::from_millis(50));
    }
    let log = broker.log_text();
    for w in wanted {
        assert!(log.contains(w), "{w} missing from\n{log}");
    }
    for reason in ["websocket_on_mqtt", "mqtt_on_websocket"] {
        let series = format!(r#"fbbus_connects_refused_total{{reason="{reason}"}}"#);
        assert_eq!(broker.wait_metric(&series, 1.0), 1.0, "{series}");
    }
}

/// A client frame: binary, final, masked (RFC 6455 5.3: every client frame is).
fn ws_frame(payload: &[u8]) -> Vec<u8> {
    let mask = [0x5a, 0x17, 0xc3, 0x08];
    let mut frame = vec![0x82];
    match payload.len() {
        n if n < 126 => frame.push(0x80 | n as u8),
        n => {
            frame.push(0x80 | 126);
            frame.extend_from_slice(&(n as u16).to_be_bytes());
        }
    }
    frame.extend_from_slice(&mask);
    frame.extend(payload.iter().enumerate().map(|(i, b)| b ^ mask[i % 4]));
    frame
}

/// The payload of the next (small, unmasked) server frame.
fn read_ws_frame(s: &mut TcpStream) -> Vec<u8> {
    let mut head = [0u8; 2];
    s.read_exact(&mut head).unwrap();
    assert_eq!(head[0], 0x82, "a final binary frame");
    assert!(head[1] < 126, "a small frame");
    let mut payload = vec![0u8; usize::from(head[1])];
    s.read_exact(&mut payload).unwrap();
    payload
}

/// A WebSocket client that stops reading is closed by the write deadline, as on TCP: its
/// connection is a byte stream under the same session, so a flood it does not take ends
/// it as a slow consumer after `slow_consumer_timeout_ms`. Also: a CONNECT and a
/// SUBSCRIBE in one WebSocket message are two packets, as MQTT 5.0 section 6 says.
#[test]
fn a_websocket_client_that_stops_reading_is_a_slow_consumer() {
    let ws_port = common::free_port();
    let broker = Broker::start_with(
        Options {
            extra: format!(
                "slow_consumer_timeout_ms = 1000\n\
                 [[listener]]\nname = \"web\"\nkind = \"ws\"\nbind = \"127.0.0.1:{ws_port}\"\n"
            ),
            ..Default::default()
        },
        |_| {},
    );
    let ws: SocketAddr = format!("127.0.0.1:{ws_port}").parse().unwrap();
    let mut s = TcpStream::connect_timeout(&ws, Duration::from_secs(2)).unwrap();
    s.set_read_timeout(Some(Duration::from_secs(5))).unwrap();
    write!(
        s,
        "GET /mqtt HTTP/1.1\r\nHost: 127.0.0.1\r\nConnection: Upgrade\r\nUpgrade: websocket\r\n\
         Sec-WebSocket-Version: 13\r\nSec-WebSocket-Key: dGhlIHNhbXBsZSBub25jZQ==\r\n\
         Sec-WebSocket-Protocol: mqtt\r\n\r\n"
    )
    .unwrap();
    let mut head = Vec::new();
    let mut byte = [0u8; 1];
    while !head.ends_with(b"\r\n\r\n") {
        s.read_exact(&mut byte).unwrap();
        head.push(byte[0]);
    }
    assert!(
        head.starts_with(b"HTTP/1.1 101"),
        "{}",
        String::from_utf8_lossy(&head)
    );
    let mut packets = raw::Connect {
        client_id: "ws-slow",
        keep_alive: 0,
        ..Default::default()
    }
    .bytes();
    packets.extend(raw::subscribe(4, 1, &["slow/q0"]));
    s.write_all(&ws_frame(&packets)).unwrap();
    assert_eq!(read_ws_frame(&mut s)[0], 0x20, "CONNACK");
    assert_eq!(read_ws_frame(&mut s)[0], 0x90, "SUBACK");
    // From here on the client reads nothing.

    let mut publisher = RawClient::connect(broker.port());
    assert_eq!(
        publisher.handshake(&raw::Connect {
            client_id: "pub",
            ..Default::default()
        }),
        0
    );
    publisher.send(&raw::publish_qos0("slow/q0", &[7u8; 32 * 1024]).repeat(256));
    let series = r#"fbbus_disconnects_total{reason="slow_consumer"}"#;
    let deadline = Instant::now() + Duration::from_secs(10);
    while broker.metric(series) < 1.0 && Instant::now() < deadline {
        std::thread::sleep(Duration::from_millis(100));
    }
    assert_eq!(
        broker.metric(series),
        1.0,
        "{}\n{}",
        broker.metrics(),
        broker.log_text()
    );
    // The connection is gone from its listener's count too.
    let open = r#"fbbus_listener_connections{listener="web",transport="ws"}"#;
    let deadline = Instant::now() + Duration::from_secs(5);
    while broker.metric(open) > 0.0 && Instant::now() < deadline {
        std::thread::sleep(Duration::from_millis(50));
    }
    assert_eq!(broker.metric(open), 0.0, "{}", broker.metrics());
    drop(s);
}

// ------------------------------------------------------------ MQTT.js in Chromium

/// MQTT.js's browser build, from the npm package `.ci/run` installs.
fn mqtt_js() -> Option<PathBuf> {
    common::npm_file("mqtt/dist/mqtt.min.js")
}

fn require_browser() -> bool {
    if !common::require("chromium") || !common::require("chromedriver") {
        return false;
    }
    let ok = Command::new("python3")
        .args(["-c", "import selenium"])
        .status()
        .is_ok_and(|s| s.success());
    if !ok && std::env::var_os("CI").is_some() {
        panic!("python3 has no selenium; .ci/run should have installed it");
    }
    ok
}

/// Serves the HMI page (any path but the library's) and `/mqtt.min.js` on loopback, on a
/// thread that ends with the test process. Each request is read with a deadline.
fn serve_page(library: Vec<u8>) -> SocketAddr {
    let listener = TcpListener::bind("127.0.0.1:0").unwrap();
    let addr = listener.local_addr().unwrap();
    std::thread::spawn(move || {
        for conn in listener.incoming() {
            let Ok(mut conn) = conn else { continue };
            let _ = conn.set_read_timeout(Some(Duration::from_secs(5)));
            let mut head = Vec::new();
            let mut buf = [0u8; 1024];
            while !head.windows(4).any(|w| w == b"\r\n\r\n") && head.len() < 16 * 1024 {
                match conn.read(&mut buf) {
                    Ok(0) | Err(_) => break,
                    Ok(n) => head.extend_from_slice(&buf[..n]),
                }
            }
            let line = String::from_utf8_lossy(&head);
            let path = line.split_whitespace().nth(1).unwrap_or("/");
            let (status, kind, body): (&str, &str, &[u8]) = if path == "/mqtt.min.js" {
                ("200 OK", "text/javascript", &library)
            } else if path == "/" || path.starts_with("/?") {
                ("200 OK", "text/html; charset=utf-8", PAGE.as_bytes())
            } else {
                ("404 Not Found", "text/plain", b"not here")
            };
            let _ = write!(
                conn,
                "HTTP/1.1 {status}\r\nContent-Type: {kind}\r\nContent-Length: {}\r\nConnection: close\r\n\r\n",
                body.len()
            );
            let _ = conn.write_all(body);
        }
    });
    addr
}

fn browser(broker: &Broker, scheme: &str, device: &str) -> Option<Value> {
    let library = mqtt_js()?;
    if !require_browser() {
        return None;
    }
    let page = serve_page(std::fs::read(library).unwrap());
    let url = format!(
        "http://{page}/?broker={scheme}://127.0.0.1:{}/mqtt&device={device}",
        broker.port()
    );
    let mut cmd = Command::new("python3");
    cmd.arg("-u").arg(BROWSER).arg(&url);
    if scheme == "wss" {
        cmd.arg("--insecure");
    }
    let (ok, out, err) = common::run(&mut cmd, LIMIT);
    assert!(
        ok,
        "ws_browser.py failed\n--- stdout\n{out}\n--- stderr\n{err}\n--- broker log\n{}",
        broker.log_text()
    );
    let seen: Value = serde_json::from_str(out.trim()).unwrap_or_else(|e| panic!("{e}: {out}"));
    eprintln!("browser ({scheme}): {seen}");
    Some(seen)
}

fn assert_hmi_outcome(seen: &Value, broker: &Broker) {
    assert_eq!(seen["error"], Value::Null, "{seen}\n{}", broker.log_text());
    assert_eq!(seen["library"], "mqtt.js", "{seen}");
    assert_eq!(seen["declared"], true, "{seen}");
    assert_eq!(seen["bool_error"], Value::Null, "{seen}");
    assert_eq!(
        seen["delivered"], "true",
        "BOOL 1 arrives as true on fb/: {seen}"
    );
    assert_eq!(seen["refused"]["code"], 0x99, "{seen}");
}

#[test]
fn mqtt_js_in_headless_chromium_over_ws() {
    let broker = ws_broker("", |_| {});
    let Some(seen) = browser(&broker, "ws", "hmi-ws") else {
        return;
    };
    assert_hmi_outcome(&seen, &broker);
    assert_accepted(&broker, "ws", 1.0);
}

#[test]
fn mqtt_js_in_headless_chromium_over_wss() {
    let broker = wss_broker();
    let Some(seen) = browser(&broker, "wss", "hmi-wss") else {
        return;
    };
    assert_hmi_outcome(&seen, &broker);
    assert_accepted(&broker, "wss", 1.0);
}

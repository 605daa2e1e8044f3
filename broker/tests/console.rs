//! The line console (issue 18): its routes on the real broker (assets and their headers,
//! the line summary, a device's activity, the live feed), and what a person sees in
//! headless Chromium (`python/console_browser.py`, driven over WebDriver): the devices and
//! their statuses, a killed device turning offline with its reason without a reload, a
//! refusal with its reason, the FB box with its ports and last values, and another
//! line's device turning unreachable when that line stops; the trends, clients and
//! retained views and the layout at 400 px (issue 37; their API: `console_history.rs`).

mod common;

use std::io::{Read, Write};
use std::net::{SocketAddr, TcpStream};
use std::time::{Duration, Instant};

use common::bus::{self, Line, Python};
use common::clients::V4;
use common::Broker;
use serde_json::Value;

/// A conveyor with an event carrying data (WITH), an event input and data both ways.
const CONV: &str = r#"{"fbs": {"CONV": {
    "type": "CONVEYOR",
    "events_out": {"MOVED": {"with": ["POSITION", "SENSOR_IN"]}, "TICK": {"with": []}},
    "events_in": {"START": {"with": ["SPEED"]}},
    "data_out": {"POSITION": "INT", "SENSOR_IN": "BOOL", "ID": "STRING"},
    "data_in": {"SPEED": "REAL"}
}}}"#;

/// An oven whose zone temperature only it has (search by port name).
const OVEN: &str = r#"{"fbs": {"OVEN": {
    "type": "OVEN_CTRL",
    "data_out": {"T_ZONE1": "REAL"}
}}}"#;

/// (status code, head, body) of one HTTP/1.0 request.
fn request(addr: SocketAddr, path: &str, headers: &str) -> (u16, String, String) {
    let mut s = TcpStream::connect_timeout(&addr, Duration::from_secs(2)).unwrap();
    s.set_read_timeout(Some(Duration::from_secs(5))).unwrap();
    write!(s, "GET {path} HTTP/1.0\r\nHost: localhost\r\n{headers}\r\n").unwrap();
    let mut text = String::new();
    s.read_to_string(&mut text).unwrap();
    let (head, body) = text.split_once("\r\n\r\n").unwrap();
    let code = head.split_whitespace().nth(1).unwrap().parse().unwrap();
    (code, head.to_ascii_lowercase(), body.to_owned())
}

fn json(addr: SocketAddr, path: &str) -> Value {
    let (code, _, body) = request(addr, path, "");
    assert_eq!(code, 200, "{path}: {body}");
    serde_json::from_str(&body).unwrap()
}

/// A device connected, subscribed to its diagnostics, its interface declared.
async fn declared(port: u16, id: &str, will: bool) -> V4 {
    let mut options = V4::options(port, id, None);
    if will {
        options.set_last_will(rumqttc::LastWill::new(
            format!("plant/{id}/will"),
            "gone",
            rumqttc::QoS::AtLeastOnce,
            false,
        ));
    }
    let mut dev = V4::connect_with(options).await.unwrap();
    dev.declare(id, CONV).await;
    dev
}

async fn publish(dev: &V4, topic: &str, payload: &str) {
    dev.client
        .publish(topic, rumqttc::QoS::AtLeastOnce, false, payload.to_owned())
        .await
        .unwrap();
}

/// Waits (bounded) until `check` holds for the JSON at `path`; returns it.
fn wait_json(addr: SocketAddr, path: &str, check: impl Fn(&Value) -> bool) -> Value {
    let deadline = Instant::now() + Duration::from_secs(10);
    loop {
        let v = json(addr, path);
        if check(&v) {
            return v;
        }
        assert!(Instant::now() < deadline, "{path}: {v}");
        std::thread::sleep(Duration::from_millis(50));
    }
}

/// A live feed read as raw server-sent events.
struct Feed {
    stream: TcpStream,
    text: String,
}

impl Feed {
    fn open(addr: SocketAddr, path: &str) -> Feed {
        let mut stream = TcpStream::connect_timeout(&addr, Duration::from_secs(2)).unwrap();
        write!(stream, "GET {path} HTTP/1.0\r\nHost: localhost\r\n\r\n").unwrap();
        Feed {
            stream,
            text: String::new(),
        }
    }

    /// Reads until an event `name` whose data contains every one of `needles` arrives
    /// (bounded by `within`); returns its data.
    fn until(&mut self, name: &str, needles: &[&str], within: Duration) -> String {
        let deadline = Instant::now() + within;
        let mut buf = [0u8; 8192];
        loop {
            // Complete events only; the one found is taken out, the others stay.
            let complete = self.text.rfind("\n\n").map_or(0, |at| at + 2);
            let mut found = None;
            let mut offset = 0;
            for block in self.text[..complete].split_inclusive("\n\n") {
                let start = offset;
                offset += block.len();
                if !block
                    .lines()
                    .any(|l| l.strip_prefix("event: ") == Some(name))
                {
                    continue;
                }
                let data = block
                    .lines()
                    .find_map(|l| l.strip_prefix("data: "))
                    .unwrap_or("");
                if needles.iter().all(|n| data.contains(n)) {
                    found = Some((start..offset, data.to_owned()));
                    break;
                }
            }
            if let Some((range, data)) = found {
                self.text.drain(range);
                return data;
            }
            let left = deadline.saturating_duration_since(Instant::now());
            assert!(
                !left.is_zero(),
                "no `{name}` event with {needles:?} within {within:?}: {}",
                self.text
            );
            self.stream.set_read_timeout(Some(left)).unwrap();
            match self.stream.read(&mut buf) {
                Ok(0) => panic!("the feed closed: {}", self.text),
                Ok(n) => self.text.push_str(&String::from_utf8_lossy(&buf[..n])),
                Err(e)
                    if matches!(
                        e.kind(),
                        std::io::ErrorKind::WouldBlock | std::io::ErrorKind::TimedOut
                    ) =>
                {
                    panic!(
                        "no `{name}` event with {needles:?} within {within:?}: {}",
                        self.text
                    )
                }
                Err(e) => panic!("feed read: {e}: {}", self.text),
            }
        }
    }
}

/// The routes: the page and its assets with their headers; the line summary; a device's
/// last values and refusals (hostile ones included); the live feed's events.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn console_routes_serve_the_page_the_summary_the_activity_and_the_feed() {
    let broker = Broker::start();
    let admin = broker.admin;

    // The page and its assets, embedded, with their types and the security policy.
    let (code, head, body) = request(admin, "/", "");
    assert_eq!(code, 200);
    assert!(head.contains("content-type: text/html"), "{head}");
    assert!(
        head.contains("content-security-policy: default-src 'self'"),
        "{head}"
    );
    assert!(body.contains("/console/console.js"), "{body}");
    for (asset, kind) in [
        ("console.js", "text/javascript"),
        ("console.css", "text/css"),
        ("icon.svg", "image/svg+xml"),
    ] {
        let (code, head, _) = request(admin, &format!("/console/{asset}"), "");
        assert_eq!(code, 200, "{asset}");
        assert!(head.contains(&format!("content-type: {kind}")), "{head}");
        assert!(head.contains("x-content-type-options: nosniff"), "{head}");
        let etag = head
            .lines()
            .find_map(|l| l.strip_prefix("etag: "))
            .expect("an etag")
            .to_owned();
        let (code, _, body) = request(
            admin,
            &format!("/console/{asset}"),
            &format!("If-None-Match: {etag}\r\n"),
        );
        assert_eq!((code, body.as_str()), (304, ""), "{asset}");
    }
    assert_eq!(request(admin, "/console/nothing.js", "").0, 404);
    assert_eq!(request(admin, "/console/..%2fCargo.toml", "").0, 404);

    // A feed open before anything happens, watching the device.
    let mut feed = Feed::open(admin, "/api/v1/events?device=belt-1");
    let hello = feed.until("hello", &["\"line\":\"test\""], Duration::from_secs(5));
    assert!(hello.contains("\"version\""), "{hello}");
    feed.until("stats", &["\"sample\""], Duration::from_secs(3));

    let dev = declared(broker.port(), "belt-1", true).await;
    feed.until(
        "device",
        &["\"id\":\"belt-1\"", "\"status\":\"online\""],
        Duration::from_secs(2),
    );
    publish(&dev, "fb/belt-1/CONV/POSITION", "42").await;
    // Hostile text: multi-byte characters past the value cap.
    let long = format!("\"{}\"", "ü€".repeat(400));
    publish(&dev, "fb/belt-1/CONV/ID", &long).await;
    // Ill-typed: refused, with its reason on fbbus/diag/belt-1.
    publish(&dev, "fb/belt-1/CONV/POSITION", "\"not a number\"").await;
    let ports = feed.until(
        "ports",
        &["\"device\":\"belt-1\"", "CONV.POSITION"],
        Duration::from_secs(2),
    );
    assert!(ports.contains("\"value\":\"42\""), "{ports}");
    let refusal = feed.until("refusal", &["belt-1"], Duration::from_secs(2));
    assert!(refusal.contains("payload_format_invalid"), "{refusal}");

    let activity = wait_json(admin, "/api/v1/devices/belt-1/activity", |a| {
        a["ports"]["CONV.ID"].is_object() && a["refusals"].as_array().is_some_and(|r| !r.is_empty())
    });
    assert_eq!(
        activity["ports"]["CONV.POSITION"]["value"], "42",
        "{activity}"
    );
    let id = &activity["ports"]["CONV.ID"];
    assert_eq!(id["truncated"], true, "{id}");
    assert_eq!(id["value"].as_str().unwrap().chars().count(), 200, "{id}");
    // The will its connection holds.
    assert_eq!(activity["will"]["topic"], "plant/belt-1/will", "{activity}");
    assert_eq!(activity["will"]["payload"], "gone", "{activity}");
    assert_eq!(activity["will"]["qos"], 1, "{activity}");
    let refused = &activity["refusals"][0];
    assert_eq!(refused["kind"], "rejected", "{refused}");
    assert_eq!(refused["reason"], "payload_format_invalid", "{refused}");
    assert_eq!(refused["topic"], "fb/belt-1/CONV/POSITION", "{refused}");
    assert!(
        activity["silence"]["factor"].as_f64().is_some(),
        "{activity}"
    );

    // An undeclared port and another device's topic leave nothing behind.
    publish(&dev, "fb/belt-1/CONV/NOPE", "1").await;
    assert_eq!(request(admin, "/api/v1/devices/nobody/activity", "").0, 404);

    // The device killed without DISCONNECT: offline, with its reason, on the feed; the
    // activity keeps the offline time and why.
    drop(dev);
    let offline = feed.until(
        "device",
        &["\"id\":\"belt-1\"", "\"status\":\"offline\""],
        Duration::from_secs(3),
    );
    assert!(offline.contains("connection lost"), "{offline}");
    let activity = wait_json(admin, "/api/v1/devices/belt-1/activity", |a| {
        a["offline"].as_array().is_some_and(|o| !o.is_empty())
    });
    assert_eq!(
        activity["offline"][0]["reason"], "connection lost",
        "{activity}"
    );
    // Its will fired with the connection: none is held any more.
    assert!(activity["will"].is_null(), "{activity}");

    // The line summary: name, version, the rates' history, no bridge.
    let line = wait_json(admin, "/api/v1/line", |l| {
        l["history"].as_array().is_some_and(|h| h.len() >= 2)
    });
    assert_eq!(line["line"], "test");
    assert_eq!(line["bridge"], false);
    let last = line["history"].as_array().unwrap().last().unwrap().clone();
    assert_eq!(last["offline"], 1, "{last}");

    // A forgotten device's activity is gone with it, and the feed says so.
    let mut s = TcpStream::connect(admin).unwrap();
    write!(
        s,
        "DELETE /api/v1/devices/belt-1 HTTP/1.0\r\nHost: localhost\r\n\r\n"
    )
    .unwrap();
    let mut answer = String::new();
    s.read_to_string(&mut answer).unwrap();
    assert!(answer.starts_with("HTTP/1.0 200"), "{answer}");
    feed.until("removed", &["belt-1"], Duration::from_secs(2));
    assert_eq!(request(admin, "/api/v1/devices/belt-1/activity", "").0, 404);
    let metrics = broker.metrics();
    assert!(
        metrics.contains("fbbus_console_entries{what=\"port_values\"} 0"),
        "{metrics}"
    );
    assert!(metrics.contains("fbbus_console_feeds 1"), "{metrics}");
}

/// Whether headless Chromium, its WebDriver and Python's selenium are here; in CI their
/// absence is a failure (`.ci/run` installs them), elsewhere the test skips itself loudly.
fn have_browser() -> bool {
    let missing: Vec<&str> = [
        (
            "/usr/bin/chromium",
            std::path::Path::new("/usr/bin/chromium").exists(),
        ),
        (
            "/usr/bin/chromedriver",
            std::path::Path::new("/usr/bin/chromedriver").exists(),
        ),
        (
            "python3 selenium",
            std::process::Command::new("python3")
                .args(["-c", "import selenium"])
                .stdout(std::process::Stdio::null())
                .stderr(std::process::Stdio::null())
                .status()
                .is_ok_and(|s| s.success()),
        ),
    ]
    .into_iter()
    .filter(|(_, ok)| !ok)
    .map(|(what, _)| what)
    .collect();
    if missing.is_empty() {
        return true;
    }
    assert!(
        std::env::var_os("CI").is_none(),
        "{missing:?} missing; .ci/run should have installed chromium, chromium-driver, selenium"
    );
    eprintln!("SKIPPED: {missing:?} missing (apt-get install chromium chromium-driver; pip install selenium; .ci/run does)");
    false
}

/// Waits for the browser script's line `want` (its failures end the test with its words).
fn expect(python: &Python, want: &str, within: Duration) {
    let deadline = Instant::now() + within;
    loop {
        let left = deadline.saturating_duration_since(Instant::now());
        let line = python
            .next_line(left)
            .unwrap_or_else(|| panic!("the browser script did not say `{want}` within {within:?}"));
        if line == want {
            return;
        }
        assert!(!line.starts_with("FAIL"), "browser: {line}");
        eprintln!("browser: {line}");
    }
}

/// What a person sees, in headless Chromium: two lines on the bus, devices declared and
/// publishing on line A, one killed (its will fires), one refused, one on line B; then
/// line B stops; and (issue 37) the trends: a sparkline and a chart that grow, a port put
/// on the chart by a click on its sparkline, an event's WITH data and its seq and ts in
/// local time, the CSV export (content and file name), search by port, the clients and
/// retained views, the layout at 400 px (no sideways scroll, text drawn at a readable
/// size). Screenshots of each view with `FBBUS_CONSOLE_SCREENSHOTS=<dir>`.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn the_console_in_a_browser_shows_the_line_live() {
    if !have_browser() {
        return;
    }
    let a = Line::plain("line-a", &[], "");
    let b = Line::plain("line-b", &[&a.zenoh], "");

    let press = declared(a.port(), "press-1", false).await;
    let doomed = declared(a.port(), "press-2", true).await;
    let bad = declared(a.port(), "bad-1", false).await;
    let mut oven = V4::connect(a.port(), "oven-1", None).await.unwrap();
    oven.declare("oven-1", OVEN).await;
    publish(&oven, "fb/oven-1/OVEN/T_ZONE1", "182.5").await;
    // A retained topic for the retained view: "plant/line-a/shift" and "B", 19 bytes.
    oven.client
        .publish("plant/line-a/shift", rumqttc::QoS::AtLeastOnce, true, "B")
        .await
        .unwrap();
    let remote = bus::device_with(&b, "remote-1", CONV).await;
    a.wait_record("remote-1", "online", bus::PROPAGATION);
    publish(&bad, "fb/bad-1/CONV/POSITION", "7").await;
    publish(&bad, "fb/bad-1/CONV/POSITION", "\"seven\"").await;
    publish(&doomed, "fb/press-2/CONV/POSITION", "3").await;
    // press-1 publishes every 200 ms for as long as the test runs.
    let client = press.client.clone();
    let publisher = tokio::spawn(async move {
        for i in 0u64.. {
            let _ = client
                .publish(
                    "fb/press-1/CONV/POSITION",
                    rumqttc::QoS::AtMostOnce,
                    false,
                    (100 + i % 900).to_string(),
                )
                .await;
            if i % 5 == 0 {
                let _ = client
                    .publish(
                        "fb/press-1/CONV/MOVED",
                        rumqttc::QoS::AtMostOnce,
                        false,
                        // The device's own occurrence number and time (µs).
                        format!(
                            r#"{{"seq": {}, "ts": {}, "data": {{"POSITION": {}, "SENSOR_IN": true}}}}"#,
                            i / 5 + 1,
                            std::time::SystemTime::now()
                                .duration_since(std::time::UNIX_EPOCH)
                                .unwrap()
                                .as_micros(),
                            100 + i % 900
                        ),
                    )
                    .await;
            }
            tokio::time::sleep(Duration::from_millis(200)).await;
        }
    });

    let shots = std::env::var("FBBUS_CONSOLE_SCREENSHOTS").unwrap_or_default();
    let shots = match shots.as_str() {
        "" => String::new(),
        dir if std::path::Path::new(dir).is_absolute() => dir.to_owned(),
        dir => format!("{}/../{dir}", env!("CARGO_MANIFEST_DIR")),
    };
    let url = format!("http://{}", a.broker.admin);
    let mut python = Python::spawn("console_browser.py", &[&url, &shots]);
    let outcome = tokio::task::block_in_place(|| {
        std::panic::catch_unwind(std::panic::AssertUnwindSafe(|| {
            expect(&python, "ready-for-kill", Duration::from_secs(90));
            drop(doomed);
            python.send("killed");
            expect(&python, "ready-for-stop", Duration::from_secs(90));
            drop(b);
            python.send("stopped");
            expect(&python, "done", Duration::from_secs(90));
        }))
    });
    // The script quits Chromium and its driver when it is done or has failed; killing it
    // first would leave both running.
    let exited = python.wait_exit(Duration::from_secs(30));
    publisher.abort();
    drop((press, bad, remote, oven));
    if let Err(panic) = outcome {
        eprintln!("line A's log:\n{}", a.broker.log_text());
        std::panic::resume_unwind(panic);
    }
    assert!(exited, "the browser script did not exit after `done`");
}

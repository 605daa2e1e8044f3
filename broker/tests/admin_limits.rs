//! Issue 21, the admin plane: a stranger who opens admin connections and sends half a
//! request header holds at most `[admin] max_connections` of them, each for at most
//! `header_timeout_ms`; the rest are closed at once and counted, and MQTT clients keep
//! connecting meanwhile. Before, 21,000 such connections held every file descriptor of
//! the process and MQTT clients got "Too many open files".
//!
//! The device listing is paginated, and polling it does not stall the packet path; request
//! bodies are size-limited and cut when they come too slowly.

mod common;

use std::collections::BTreeSet;
use std::io::{Read, Write};
use std::net::{SocketAddr, TcpStream};
use std::sync::atomic::{AtomicBool, AtomicUsize, Ordering};
use std::sync::Arc;
use std::time::{Duration, Instant};

use common::raw::{self, Connect, RawClient};
use common::{Broker, Options};

const MAX: usize = 8;

/// Whether the server closed `s` within `within` (EOF, a reset, or an HTTP error answer
/// followed by EOF).
fn closed_within(s: &mut TcpStream, within: Duration) -> bool {
    s.set_read_timeout(Some(within)).unwrap();
    let mut buf = [0u8; 512];
    loop {
        match s.read(&mut buf) {
            Ok(0) => return true,
            // An answer (408 Request Timeout): the close follows.
            Ok(_) => continue,
            Err(e)
                if matches!(
                    e.kind(),
                    std::io::ErrorKind::WouldBlock | std::io::ErrorKind::TimedOut
                ) =>
            {
                return false
            }
            // Reset by the server.
            Err(_) => return true,
        }
    }
}

fn open_fds(pid: u32) -> usize {
    std::fs::read_dir(format!("/proc/{pid}/fd"))
        .map(|d| d.count())
        .unwrap_or(0)
}

#[test]
fn slow_admin_clients_are_capped_and_timed_out_while_mqtt_keeps_accepting() {
    let dir = tempfile::tempdir().unwrap();
    let mqtt: std::net::SocketAddr = format!("127.0.0.1:{}", common::free_port())
        .parse()
        .unwrap();
    let admin: std::net::SocketAddr = format!("127.0.0.1:{}", common::free_port())
        .parse()
        .unwrap();
    let config = dir.path().join("fbbus.toml");
    std::fs::write(
        &config,
        format!(
            "[broker]\nline = \"t\"\n[[listener]]\nname = \"main\"\nbind = \"{mqtt}\"\n\
             [admin]\nbind = \"{admin}\"\nmax_connections = {MAX}\nheader_timeout_ms = 700\n\
             connection_timeout_ms = 5000\n"
        ),
    )
    .unwrap();
    let broker = Broker::spawn(dir, config, mqtt, admin);
    let pid = broker.child.id();
    let fds_before = open_fds(pid);

    // The stranger: half a header on each connection, never the rest.
    let mut slow = Vec::new();
    for _ in 0..MAX {
        let mut s = TcpStream::connect(admin).unwrap();
        s.write_all(b"GET /metrics HTTP/1.1\r\nHost: x\r\n")
            .unwrap();
        slow.push(s);
    }
    std::thread::sleep(Duration::from_millis(100));
    // Beyond the cap: closed at once.
    let started = Instant::now();
    for i in 0..200 {
        let mut s = TcpStream::connect(admin).unwrap();
        let _ = s.write_all(b"GET /metrics HTTP/1.1\r\nHost: x\r\n");
        assert!(
            closed_within(&mut s, Duration::from_millis(500)),
            "connection {i} over the cap was not closed"
        );
    }
    assert!(started.elapsed() < Duration::from_secs(20));
    // MQTT clients connect meanwhile.
    for i in 0..20 {
        let mut c = RawClient::connect(broker.port());
        let id = format!("dev-{i}");
        assert_eq!(
            c.handshake(&Connect {
                client_id: &id,
                ..Default::default()
            }),
            0,
            "MQTT CONNECT {i} while the admin port is flooded"
        );
    }
    // The broker's file descriptors stay bounded by the cap (+ the MQTT clients above,
    // closed by now or closing).
    let fds_flooded = open_fds(pid);
    assert!(
        fds_flooded <= fds_before + MAX + 25,
        "file descriptors {fds_before} -> {fds_flooded}"
    );
    // The half headers time out; then the admin endpoint answers again.
    for (i, s) in slow.iter_mut().enumerate() {
        assert!(
            closed_within(s, Duration::from_secs(3)),
            "slow connection {i} was held past the header timeout"
        );
    }
    // A closed connection gives its slot back a moment after its client sees the close:
    // the endpoint answers again within a second.
    let deadline = std::time::Instant::now() + Duration::from_secs(1);
    let ready = loop {
        let code = common::http_get(admin, "/readyz").map(|(code, _)| code);
        if code == Some(200) || std::time::Instant::now() > deadline {
            break code;
        }
        std::thread::sleep(Duration::from_millis(20));
    };
    assert_eq!(ready, Some(200), "the admin endpoint answers again");
    let refused = broker.metric("fbbus_admin_connections_refused_total");
    assert!(refused >= 200.0, "refused {refused}");
}

const DECLARATION: &str = r#"{"fbs": {"F": {"type": "T", "data_out": {"X": "INT"}}}}"#;

/// A broker that lets one address register more than the 100 devices
/// `max_devices_per_identity` allows by default: the test's devices all come from 127.0.0.1.
fn many_devices_broker() -> Broker {
    Broker::start_with(
        Options {
            extra: "[fb]\nmax_devices_per_identity = 10000\n".into(),
            ..Options::default()
        },
        |_| {},
    )
}

/// Registers devices `dev-00000` .. `dev-{n-1}` the way devices do (CONNECT, a QoS 1
/// declaration, DISCONNECT), from four threads.
fn register(broker: &Broker, n: usize) {
    let port = broker.port();
    let threads: Vec<_> = (0..4)
        .map(|t| {
            std::thread::spawn(move || {
                for i in (t..n).step_by(4) {
                    let id = format!("dev-{i:05}");
                    let mut c = RawClient::connect(port);
                    assert_eq!(
                        c.handshake(&Connect {
                            version: 5,
                            client_id: &id,
                            ..Default::default()
                        }),
                        0
                    );
                    assert_eq!(declare(&mut c, &id), 0, "declaration of {id}");
                    c.send(&[0xE0, 0x01, 0x00]);
                    assert!(c.closed_by_broker());
                }
            })
        })
        .collect();
    for t in threads {
        t.join().unwrap();
    }
}

/// Declares `id`'s interface at QoS 1 (MQTT 5); the PUBACK's reason.
fn declare(c: &mut RawClient, id: &str) -> u8 {
    c.send(&raw::publish_v5(
        &format!("fbbus/declare/{id}"),
        None,
        1,
        1,
        DECLARATION.as_bytes(),
    ));
    loop {
        let (byte1, body) = c.read_packet().expect("PUBACK of the declaration");
        if byte1 >> 4 == 4 {
            return body.get(2).copied().unwrap_or(0);
        }
    }
}

fn get_json(admin: SocketAddr, path: &str) -> (u16, serde_json::Value) {
    let (code, body) = common::http_get(admin, path).unwrap_or_else(|| panic!("GET {path}"));
    let json = serde_json::from_str(&body).unwrap_or(serde_json::Value::Null);
    (code, json)
}

/// Follows the pages of the listing with `limit` (and `query`, e.g. `&status=online`):
/// every id in order, and the number of pages.
fn every_id(admin: SocketAddr, limit: usize, query: &str) -> (Vec<String>, usize) {
    let mut ids = Vec::new();
    let mut after: Option<String> = None;
    let mut pages = 0;
    loop {
        let mut path = format!("/api/v1/devices?limit={limit}{query}");
        if let Some(after) = &after {
            path.push_str(&format!("&after={after}"));
        }
        let (code, page) = get_json(admin, &path);
        assert_eq!(code, 200, "GET {path}: {page}");
        pages += 1;
        let devices = page["devices"].as_array().expect("devices");
        assert!(
            devices.len() <= limit.min(10_000),
            "page of {}",
            devices.len()
        );
        ids.extend(devices.iter().map(|d| d["id"].as_str().unwrap().to_owned()));
        match &page["next"] {
            serde_json::Value::Null => return (ids, pages),
            serde_json::Value::String(next) => {
                assert_eq!(Some(next), ids.last(), "next names the page's last id");
                after = Some(next.clone());
            }
            other => panic!("next: {other}"),
        }
    }
}

#[test]
fn the_device_listing_is_paginated_and_every_device_is_seen_once() {
    const N: usize = 2_500;
    let broker = many_devices_broker();
    register(&broker, N);
    // Three devices stay online.
    let mut online = Vec::new();
    for i in 0..3 {
        let id = format!("live-{i}");
        let mut c = RawClient::connect(broker.port());
        assert_eq!(
            c.handshake(&Connect {
                version: 5,
                client_id: &id,
                ..Default::default()
            }),
            0
        );
        assert_eq!(declare(&mut c, &id), 0);
        online.push(c);
    }
    let expected: Vec<String> = (0..N)
        .map(|i| format!("dev-{i:05}"))
        .chain((0..3).map(|i| format!("live-{i}")))
        .collect::<BTreeSet<_>>()
        .into_iter()
        .collect();

    // The default page: 1,000.
    let (code, first) = get_json(broker.admin, "/api/v1/devices");
    assert_eq!(code, 200);
    assert_eq!(first["line"], "test");
    assert_eq!(first["devices"].as_array().unwrap().len(), 1000);
    assert_eq!(first["next"], expected[999].as_str());

    for limit in [1000, 7, 10_000, 50_000] {
        let (ids, pages) = every_id(broker.admin, limit, "");
        assert_eq!(ids, expected, "limit {limit}: every id once, in order");
        assert_eq!(
            pages,
            expected.len().div_ceil(limit.min(10_000)),
            "limit {limit}"
        );
    }
    // `?status=` filters before the page is cut.
    let (ids, pages) = every_id(broker.admin, 2, "&status=online");
    assert_eq!(ids, ["live-0", "live-1", "live-2"]);
    assert_eq!(pages, 2);
    let (ids, _) = every_id(broker.admin, 1000, "&status=offline");
    assert_eq!(ids.len(), N);
    // After the last id: an empty last page.
    let (code, page) = get_json(broker.admin, "/api/v1/devices?after=zzz");
    assert_eq!(code, 200);
    assert_eq!(page["devices"].as_array().unwrap().len(), 0);
    assert!(page["next"].is_null());
    // A limit of 0 or not a number is refused.
    assert_eq!(get_json(broker.admin, "/api/v1/devices?limit=0").0, 400);
    assert_eq!(get_json(broker.admin, "/api/v1/devices?limit=x").0, 400);

    // `fbbus devices` follows the pages.
    // (Read while it writes: its output is larger than a pipe holds.)
    let output = std::process::Command::new(common::fbbus_bin())
        .args(["devices", "--json", "--admin", &broker.admin.to_string()])
        .output()
        .unwrap();
    let (out, err) = (
        String::from_utf8_lossy(&output.stdout),
        String::from_utf8_lossy(&output.stderr),
    );
    assert!(output.status.success(), "fbbus devices: {err}");
    let all: serde_json::Value = serde_json::from_str(&out).unwrap();
    let ids: Vec<&str> = all["devices"]
        .as_array()
        .unwrap()
        .iter()
        .map(|d| d["id"].as_str().unwrap())
        .collect();
    assert_eq!(ids, expected, "fbbus devices lists every device once");
    drop(online);
}

#[test]
fn polling_the_device_listing_does_not_stall_a_well_behaved_client() {
    const N: usize = 2_500;
    let broker = many_devices_broker();
    register(&broker, N);
    let admin = broker.admin;
    let stop = Arc::new(AtomicBool::new(false));
    let listings = Arc::new(AtomicUsize::new(0));
    // Two loops polling the whole listing: one in default pages, one in the largest.
    let pollers: Vec<_> = [1000usize, 10_000]
        .into_iter()
        .map(|limit| {
            let (stop, listings) = (Arc::clone(&stop), Arc::clone(&listings));
            std::thread::spawn(move || {
                while !stop.load(Ordering::Relaxed) {
                    let (ids, _) = every_id(admin, limit, "");
                    assert_eq!(ids.len(), N);
                    listings.fetch_add(1, Ordering::Relaxed);
                }
            })
        })
        .collect();

    // The well-behaved client: publish -> own subscription, each probe must come back.
    let mut c = RawClient::connect(broker.port());
    c.stream
        .set_read_timeout(Some(Duration::from_secs(5)))
        .unwrap();
    assert_eq!(
        c.handshake(&Connect {
            client_id: "probe",
            ..Default::default()
        }),
        0
    );
    c.send(&raw::subscribe(4, 1, &["probe/rt"]));
    assert_eq!(c.read_packet().expect("SUBACK").0, 0x90);
    let started = Instant::now();
    let mut probes = 0u32;
    while probes < 200
        || (listings.load(Ordering::Relaxed) < 4 && started.elapsed() < Duration::from_secs(60))
    {
        let payload = probes.to_be_bytes();
        c.send(&raw::publish_qos0("probe/rt", &payload));
        loop {
            let (byte1, body) = c.read_packet().unwrap_or_else(|| {
                panic!("probe {probes} not delivered within 5 s while the listing is polled")
            });
            if byte1 >> 4 == 3 && body.ends_with(&payload) {
                break;
            }
        }
        probes += 1;
    }
    stop.store(true, Ordering::Relaxed);
    for p in pollers {
        p.join().expect("poller");
    }
    assert!(
        listings.load(Ordering::Relaxed) >= 4,
        "the probes ran while the listing was polled"
    );
}

/// A broker whose admin connections live at most `connection_ms`.
fn broker_with_admin(connection_ms: u64) -> Broker {
    Broker::start_with(
        common::Options {
            admin_extra: format!(
                "header_timeout_ms = 500\nconnection_timeout_ms = {connection_ms}\n"
            ),
            ..Default::default()
        },
        |_| {},
    )
}

/// The status code of the answer to `head` + `body`.
fn answer(admin: SocketAddr, head: &str, body: &[u8]) -> Option<u16> {
    let mut s = TcpStream::connect(admin).unwrap();
    s.set_read_timeout(Some(Duration::from_secs(5))).unwrap();
    s.write_all(head.as_bytes()).unwrap();
    // The broker may answer (and close) before the whole body is sent.
    let _ = s.write_all(body);
    let mut text = Vec::new();
    let _ = s.read_to_end(&mut text);
    String::from_utf8_lossy(&text)
        .split_whitespace()
        .nth(1)?
        .parse()
        .ok()
}

#[test]
fn request_bodies_are_size_limited_and_a_slow_body_is_cut() {
    let broker = broker_with_admin(1_500);
    let put = |len: usize| {
        format!(
            "PUT /api/v1/profiles/dev-a HTTP/1.1\r\nHost: 127.0.0.1\r\nConnection: close\r\n\
             Content-Length: {len}\r\n\r\n"
        )
    };
    // Over 1 MiB (the largest profile): 413, before the handler.
    let big = vec![b'#'; (1 << 20) + 1];
    assert_eq!(answer(broker.admin, &put(big.len()), &big), Some(413));
    // Within it: the handler answers (no profiles directory here: 409).
    let small = b"# a profile\n";
    assert_eq!(answer(broker.admin, &put(small.len()), small), Some(409));

    // A body announced and never sent is cut at connection_timeout_ms.
    let mut s = TcpStream::connect(broker.admin).unwrap();
    s.write_all(put(1000).as_bytes()).unwrap();
    s.write_all(b"# a few").unwrap();
    assert!(
        closed_within(&mut s, Duration::from_secs(5)),
        "a slow body was held past the connection timeout"
    );
    // The endpoint is served on.
    assert_eq!(
        common::http_get(broker.admin, "/healthz").map(|a| a.0),
        Some(200)
    );
}

/// Each of `pid`'s threads: its name and its nice value (Linux: `/proc/<pid>/task`).
fn thread_nice(pid: u32) -> Vec<(String, i64)> {
    let mut threads = Vec::new();
    for task in std::fs::read_dir(format!("/proc/{pid}/task")).expect("/proc") {
        let task = task.expect("task").path();
        let comm = std::fs::read_to_string(task.join("comm")).unwrap_or_default();
        let stat = std::fs::read_to_string(task.join("stat")).unwrap_or_default();
        // Field 19 is the nice value; the fields after the `(comm)` start at field 3.
        if let Some((_, after_comm)) = stat.rsplit_once(") ") {
            if let Some(n) = after_comm.split(' ').nth(16) {
                threads.push((comm.trim_end().to_owned(), n.parse().expect("nice")));
            }
        }
    }
    threads
}

/// The admin endpoint answers from a thread of its own, at a lower scheduling priority
/// than the packet path's (issue 21: admin polling must not take the sessions' CPU).
#[test]
fn the_admin_endpoint_runs_on_its_own_lower_priority_thread() {
    let broker = Broker::start();
    // A listing: it is served on the admin thread.
    assert_eq!(
        common::http_get(broker.admin, "/api/v1/devices").map(|(code, _)| code),
        Some(200)
    );
    let threads = thread_nice(broker.child.id());
    let (admin, others): (Vec<_>, Vec<_>) = threads
        .into_iter()
        .partition(|(name, _)| name == "fbbus-admin");
    assert!(
        !admin.is_empty() && admin.iter().all(|(_, nice)| *nice == 10),
        "the admin thread (and any blocking thread of its runtime), nice 10: {admin:?}"
    );
    assert!(
        others.len() >= 3 && others.iter().all(|(_, nice)| *nice == 0),
        "the router, the runtime's workers and the store keep the normal priority: {others:?}"
    );
}

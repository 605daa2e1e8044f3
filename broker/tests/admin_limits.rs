//! Issue 21, the admin plane: a stranger who opens admin connections and sends half a
//! request header holds at most `[admin] max_connections` of them, each for at most
//! `header_timeout_ms`; the rest are closed at once and counted, and MQTT clients keep
//! connecting meanwhile. Before, 21,000 such connections held every file descriptor of
//! the process and MQTT clients got "Too many open files".

mod common;

use std::io::{Read, Write};
use std::net::TcpStream;
use std::time::{Duration, Instant};

use common::raw::{Connect, RawClient};
use common::Broker;

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

//! Issue 21: each plane its share of the process's file descriptors. Under an open-file
//! limit (RLIMIT_NOFILE) too low for `[broker] max_connections`, the broker cuts the MQTT
//! share to what the limit leaves beside the admin endpoint's share and a reserve, says so
//! at start and in `fbbus_connection_limit`, and refuses the connection past it itself —
//! cleanly, counted — instead of failing accepts with "Too many open files"; the admin
//! endpoint, at its own cap, still answers.
//!
//! One test in this binary: it lowers the test process's own hard limit (inherited by the
//! broker it starts), which cannot be raised again.

mod common;

use std::io::Write;
use std::net::TcpStream;
use std::time::Duration;

use common::raw::{Connect, RawClient};
use common::{Broker, Options};

const LIMIT: u64 = 400;
/// `fd_budget::RESERVE`.
const RESERVE: u64 = 128;
const ADMIN: u64 = 64;

#[test]
fn the_mqtt_share_is_cut_to_the_open_file_limit_and_refused_cleanly() {
    let rl = libc::rlimit {
        rlim_cur: LIMIT as libc::rlim_t,
        rlim_max: LIMIT as libc::rlim_t,
    };
    // SAFETY: setrlimit reads one rlimit we own.
    assert_eq!(unsafe { libc::setrlimit(libc::RLIMIT_NOFILE, &rl) }, 0);
    let broker = Broker::start_with(
        Options {
            extra: "max_connections = 4096\n".into(),
            ..Options::default()
        },
        |_| {},
    );
    let share = (LIMIT - ADMIN - RESERVE) as usize;
    assert_eq!(broker.metric("fbbus_connection_limit"), share as f64);
    assert!(
        broker
            .log_text()
            .contains("MQTT connections are limited to"),
        "the cut is said at start: {}",
        broker.log_text()
    );

    // The admin endpoint's share, used up by connections that never finish a request.
    let held: Vec<TcpStream> = (0..ADMIN)
        .map(|_| {
            let mut s = TcpStream::connect(broker.admin).expect("admin connection");
            s.write_all(b"GET /metrics HTTP/1.1\r\n").unwrap();
            s
        })
        .collect();

    // The MQTT share, every connection accepted.
    let clients: Vec<RawClient> = (0..share)
        .map(|i| {
            let mut c = RawClient::connect(broker.port());
            let id = format!("c{i:03}");
            assert_eq!(
                c.handshake(&Connect {
                    client_id: &id,
                    ..Default::default()
                }),
                0,
                "{id} within the share"
            );
            c
        })
        .collect();

    // One more: closed by the broker at once, counted as max_connections.
    let mut extra = RawClient::connect(broker.port());
    extra
        .stream
        .set_read_timeout(Some(Duration::from_secs(5)))
        .unwrap();
    assert!(
        extra.closed_by_broker(),
        "the connection past the share is closed"
    );
    // The admin endpoint answers again once the broker has seen its slots given back.
    drop(held);
    let deadline = std::time::Instant::now() + Duration::from_secs(10);
    while common::http_get(broker.admin, "/healthz").is_none() {
        assert!(std::time::Instant::now() < deadline, "admin answers again");
        std::thread::sleep(Duration::from_millis(50));
    }
    let refused = r#"fbbus_connects_refused_total{reason="max_connections"}"#;
    assert!(broker.wait_metric(refused, 1.0) >= 1.0);

    // The places given back are taken again, once the broker has seen them closed.
    drop(clients);
    let mut admitted = wait_for_connack(&broker, "again");
    admitted.send(&common::raw::DISCONNECT);
    let log = broker.log_text();
    assert!(
        !log.contains("accept failed"),
        "no accept failed for want of descriptors: {log}"
    );
    assert_eq!(
        log.matches("connection limit reached (fbbus_connection_limit")
            .count(),
        1,
        "the refusal is logged once"
    );
}

/// Connects as `id` until a CONNACK comes (at most 10 s): a place is free again only once
/// the broker has seen a connection close.
fn wait_for_connack(broker: &Broker, id: &str) -> RawClient {
    let deadline = std::time::Instant::now() + Duration::from_secs(10);
    loop {
        let mut c = RawClient::connect(broker.port());
        c.stream
            .set_read_timeout(Some(Duration::from_secs(2)))
            .unwrap();
        let code = std::panic::catch_unwind(std::panic::AssertUnwindSafe(|| {
            c.handshake(&Connect {
                client_id: id,
                ..Default::default()
            })
        }));
        if code.ok() == Some(0) {
            return c;
        }
        assert!(
            std::time::Instant::now() < deadline,
            "{id}: no place given back within 10 s"
        );
        std::thread::sleep(Duration::from_millis(50));
    }
}

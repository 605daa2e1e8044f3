//! Raw rumqttd, the reference broker of `compare`: upstream rumqttd 0.20 from crates.io
//! (not fbbus's vendored fork) as its `rumqttd.toml` example ships it, run by the hidden
//! `fbbus-loadtest serve-rumqttd` subcommand in a process of its own so that its memory
//! can be read like any other broker's.

use std::collections::HashMap;
use std::net::SocketAddr;
use std::path::Path;

use crate::Error;

/// rumqttd 0.20 as its `rumqttd.toml` example ships it: one v4 listener on 127.0.0.1:`port`.
pub fn config(port: u16, auth: Option<HashMap<String, String>>) -> rumqttd::Config {
    let router = rumqttd::RouterConfig {
        max_connections: 10010,
        max_outgoing_packet_count: 200,
        max_segment_size: 104_857_600,
        max_segment_count: 10,
        ..Default::default()
    };
    let connections = rumqttd::ConnectionSettings {
        connection_timeout_ms: 60_000,
        max_payload_size: 20_480,
        max_inflight_count: 100,
        auth,
        external_auth: None,
        dynamic_filters: true,
    };
    let server = rumqttd::ServerSettings {
        name: "v4-1".into(),
        listen: SocketAddr::from(([127, 0, 0, 1], port)),
        tls: None,
        // rumqttd's shipped pause between two accepts.
        next_connection_delay_ms: 1,
        connections,
    };
    rumqttd::Config {
        id: 0,
        router,
        v4: Some([("1".to_string(), server)].into_iter().collect()),
        ..Default::default()
    }
}

/// Runs raw rumqttd in this process until killed. `auth_file` holds `user:password`
/// lines for its static auth map; with `exit_on_stdin_eof` the process ends when its
/// standard input closes (the harness that started it died).
pub fn serve(port: u16, auth_file: Option<&Path>, exit_on_stdin_eof: bool) -> Result<(), Error> {
    if exit_on_stdin_eof {
        std::thread::spawn(|| {
            let mut sink = Vec::new();
            let _ = std::io::Read::read_to_end(&mut std::io::stdin(), &mut sink);
            std::process::exit(0);
        });
    }
    let auth = match auth_file {
        Some(path) => {
            let text = std::fs::read_to_string(path)
                .map_err(|e| Error::Process(format!("reading {}: {e}", path.display())))?;
            let map = text
                .lines()
                .filter_map(|l| l.split_once(':'))
                .map(|(u, p)| (u.to_string(), p.to_string()))
                .collect();
            Some(map)
        }
        None => None,
    };
    let mut broker = rumqttd::Broker::new(config(port, auth));
    broker
        .start()
        .map_err(|e| Error::Process(format!("rumqttd on 127.0.0.1:{port}: {e}")))
}

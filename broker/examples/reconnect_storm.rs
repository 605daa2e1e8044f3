//! Reconnect storm: N argon2id-authenticated devices connect at the same instant, as a
//! line does after a broker restart. Prints how long until every device had its CONNACK.
//!
//! ```text
//! cargo run --release -p broker --example reconnect_storm -- [DEVICES] [ROUNDS]
//! ```
//!
//! Round 1 runs against a freshly started broker (empty verified-credential cache: every
//! login pays argon2id, the case the issue names); the following rounds reconnect the same
//! devices to the same broker (cache warm). The broker runs in this process on its own
//! 2-thread runtime; the devices are raw MQTT 3.1.1 clients on a separate 1-thread runtime,
//! so both share this machine's cores as they would on a line controller. Traffic stays on
//! 127.0.0.1; every wait is bounded by a 30 s deadline.

use std::time::{Duration, Instant};

use tokio::io::{AsyncReadExt, AsyncWriteExt};
use tokio::net::TcpStream;

fn connect_packet(user: &str, password: &str) -> Vec<u8> {
    let mut body = Vec::new();
    let string = |s: &[u8], out: &mut Vec<u8>| {
        out.extend_from_slice(&(s.len() as u16).to_be_bytes());
        out.extend_from_slice(s);
    };
    string(b"MQTT", &mut body);
    body.extend_from_slice(&[4, 0xC2, 0, 60]); // 3.1.1, user+password+clean, keep-alive 60
    string(user.as_bytes(), &mut body);
    string(user.as_bytes(), &mut body);
    string(password.as_bytes(), &mut body);
    let mut packet = vec![0x10];
    let mut len = body.len();
    loop {
        let mut byte = (len % 128) as u8;
        len /= 128;
        if len > 0 {
            byte |= 0x80;
        }
        packet.push(byte);
        if len == 0 {
            break;
        }
    }
    packet.extend_from_slice(&body);
    packet
}

/// Connects every device at once; returns (wall time, per-device latencies, failures).
async fn storm(port: u16, devices: usize) -> (Duration, Vec<Duration>, usize, Vec<TcpStream>) {
    let start = Instant::now();
    let tasks: Vec<_> = (0..devices)
        .map(|i| {
            tokio::spawn(async move {
                let user = format!("plc-{i:04}");
                let t0 = Instant::now();
                let mut s = TcpStream::connect(("127.0.0.1", port)).await.ok()?;
                s.set_nodelay(true).ok()?;
                s.write_all(&connect_packet(&user, &format!("secret-{i:04}")))
                    .await
                    .ok()?;
                let mut ack = [0u8; 4];
                tokio::time::timeout(Duration::from_secs(30), s.read_exact(&mut ack))
                    .await
                    .ok()?
                    .ok()?;
                (ack[0] == 0x20 && ack[3] == 0).then(|| (t0.elapsed(), s))
            })
        })
        .collect();
    let mut latencies = Vec::new();
    let mut streams = Vec::new();
    let mut failures = 0;
    for t in tasks {
        match t.await.ok().flatten() {
            Some((latency, stream)) => {
                latencies.push(latency);
                streams.push(stream);
            }
            None => failures += 1,
        }
    }
    let wall = start.elapsed();
    latencies.sort();
    (wall, latencies, failures, streams)
}

fn main() -> anyhow::Result<()> {
    let mut args = std::env::args().skip(1);
    let devices: usize = args.next().map(|a| a.parse()).transpose()?.unwrap_or(1045);
    let rounds: usize = args.next().map(|a| a.parse()).transpose()?.unwrap_or(2);

    let dir = tempfile::tempdir()?;
    let passwd = dir.path().join("passwd");
    eprintln!("hashing {devices} argon2id passwords (default parameters)...");
    let mut file = security::PasswordFile::default();
    let params = security::Argon2Params::default();
    for i in 0..devices {
        let phc = security::hash_password(format!("secret-{i:04}").as_bytes(), &params)?;
        file.set(&format!("plc-{i:04}"), security::StoredHash::parse(&phc)?)?;
    }
    file.save(&passwd)?;

    let port = std::net::TcpListener::bind("127.0.0.1:0")?
        .local_addr()?
        .port();
    let admin = std::net::TcpListener::bind("127.0.0.1:0")?
        .local_addr()?
        .port();
    let config = broker::Config::parse(
        &format!(
            "[broker]\nmax_connections = {}\n[auth]\npassword_file = \"{}\"\n\
             [fb]\nregistry_file = \"{}\"\n\
             [[listener]]\nname = \"storm\"\nbind = \"127.0.0.1:{port}\"\n\
             [admin]\nbind = \"127.0.0.1:{admin}\"\n",
            devices + 16,
            passwd.display(),
            dir.path().join("registry.json").display()
        ),
        "<reconnect_storm>",
    )?;

    let broker_rt = tokio::runtime::Builder::new_multi_thread()
        .worker_threads(2)
        .enable_all()
        .build()?;
    let broker = broker_rt.block_on(broker::Broker::start(config))?;
    let clients_rt = tokio::runtime::Builder::new_multi_thread()
        .worker_threads(1)
        .enable_all()
        .build()?;

    println!(
        "reconnect storm: {devices} devices, argon2id m={} KiB t={} p={}, {} cores",
        params.memory_kib,
        params.iterations,
        params.parallelism,
        std::thread::available_parallelism()
            .map(|n| n.get())
            .unwrap_or(0)
    );
    for round in 1..=rounds {
        let (wall, lat, failures, streams) = clients_rt.block_on(storm(port, devices));
        let pct = |p: f64| {
            lat.get(((lat.len() as f64 * p) as usize).min(lat.len().saturating_sub(1)))
                .copied()
                .unwrap_or_default()
        };
        println!(
            "round {round} ({}): all {} connected in {:.3} s, failed {failures}; CONNACK latency p50 {:.0} ms, p99 {:.0} ms, max {:.0} ms",
            if round == 1 { "fresh broker, cold cache" } else { "same broker, warm cache" },
            lat.len(),
            wall.as_secs_f64(),
            pct(0.50).as_secs_f64() * 1e3,
            pct(0.99).as_secs_f64() * 1e3,
            lat.last().copied().unwrap_or_default().as_secs_f64() * 1e3,
        );
        drop(streams);
        // Let the broker see every close before the next round.
        let deadline = Instant::now() + Duration::from_secs(30);
        while broker.metrics.connections.get() > 0 && Instant::now() < deadline {
            std::thread::sleep(Duration::from_millis(20));
        }
    }
    println!(
        "cache hits: {}, argon2 verifications observed: {}",
        broker.metrics.auth_cache_hits.get(),
        broker.metrics.auth_verify_seconds.get_sample_count()
    );
    broker_rt.block_on(broker.shutdown(Duration::from_secs(2)));
    Ok(())
}

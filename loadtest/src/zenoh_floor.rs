//! The floor under the bus hop: zenoh alone between two processes on this machine.
//!
//! `compare bridge` reports what the hop between two fbbus lines adds to one broker's
//! latency. Part of that is zenoh's own: a put crosses zenoh's transmit task, the socket
//! and zenoh's receive task before fbbus sees it. This measures that part by itself, the
//! way the bus runs zenoh (two peers over loopback TCP, blocking congestion control):
//! this process puts a 32-byte sample on `fbbus-floor/ping` at a steady rate, a second
//! process (`fbbus-loadtest zenoh-pong`, [`serve_pong`]) puts it back on
//! `fbbus-floor/pong` from its subscriber's callback, and half of each round trip is one
//! way. No TLS, no fbbus code: what the hop could cost at best here.

use std::io::{BufRead, BufReader, Read};
use std::process::{Command, Stdio};
use std::sync::mpsc;
use std::time::{Duration, Instant};

use anyhow::{anyhow, bail, Context, Result};
use zenoh::qos::CongestionControl;
use zenoh::Wait;

const PING: &str = "fbbus-floor/ping";
const PONG: &str = "fbbus-floor/pong";

/// Round trips before the measured ones (sessions and caches warm).
const WARMUP: usize = 200;

/// Half of the measured round trips: zenoh's one-way latency.
#[derive(Debug, Clone, Copy)]
pub struct Floor {
    pub p50_us: f64,
    pub p99_us: f64,
    pub samples: usize,
}

fn config(listen: Option<u16>, connect: Option<u16>) -> Result<zenoh::Config> {
    let mut c = zenoh::Config::default();
    let set = |c: &mut zenoh::Config, key: &str, value: String| {
        c.insert_json5(key, &value)
            .map_err(|e| anyhow!("zenoh config {key}: {e}"))
    };
    set(&mut c, "mode", "\"peer\"".into())?;
    set(&mut c, "scouting/multicast/enabled", "false".into())?;
    if let Some(port) = listen {
        set(
            &mut c,
            "listen/endpoints",
            format!("[\"tcp/127.0.0.1:{port}\"]"),
        )?;
    }
    if let Some(port) = connect {
        set(
            &mut c,
            "connect/endpoints",
            format!("[\"tcp/127.0.0.1:{port}\"]"),
        )?;
    }
    Ok(c)
}

/// `fbbus-loadtest zenoh-pong --port PORT`: a zenoh peer on 127.0.0.1:PORT that puts back
/// every ping; prints `ready`, exits when standard input closes (the harness is gone).
pub fn serve_pong(port: u16) -> Result<()> {
    let session = zenoh::open(config(Some(port), None)?)
        .wait()
        .map_err(|e| anyhow!("zenoh: {e}"))?;
    let publisher = session
        .declare_publisher(PONG)
        .congestion_control(CongestionControl::Block)
        .wait()
        .map_err(|e| anyhow!("zenoh: {e}"))?;
    let _subscriber = session
        .declare_subscriber(PING)
        .callback(move |sample| {
            let _ = publisher.put(sample.payload().clone()).wait();
        })
        .wait()
        .map_err(|e| anyhow!("zenoh: {e}"))?;
    println!("ready");
    let _ = std::io::stdin().read_to_end(&mut Vec::new());
    Ok(())
}

/// `count` round trips at `rate` per second against a `zenoh-pong` this starts; bounded:
/// at most 2 s per round trip, 20 s for the other process to start.
pub fn measure(count: usize, rate: u32) -> Result<Floor> {
    let port = std::net::TcpListener::bind("127.0.0.1:0")?
        .local_addr()?
        .port();
    let exe = std::env::current_exe().context("finding fbbus-loadtest itself")?;
    let mut pong = Command::new(exe)
        .args(["zenoh-pong", "--port", &port.to_string()])
        .stdin(Stdio::piped())
        .stdout(Stdio::piped())
        .stderr(Stdio::null())
        .spawn()
        .context("starting zenoh-pong")?;
    let result = ping(&mut pong, port, count, rate);
    let _ = pong.kill();
    let _ = pong.wait();
    result
}

fn ping(pong: &mut std::process::Child, port: u16, count: usize, rate: u32) -> Result<Floor> {
    let stdout = pong.stdout.take().context("zenoh-pong's stdout")?;
    let (ready_tx, ready) = mpsc::channel();
    std::thread::spawn(move || {
        let mut line = String::new();
        let _ = BufReader::new(stdout).read_line(&mut line);
        let _ = ready_tx.send(line);
    });
    match ready.recv_timeout(Duration::from_secs(20)) {
        Ok(line) if line.trim() == "ready" => {}
        Ok(line) => bail!("zenoh-pong did not start: {line:?}"),
        Err(_) => bail!("zenoh-pong did not start within 20 s"),
    }
    let session = zenoh::open(config(None, Some(port))?)
        .wait()
        .map_err(|e| anyhow!("zenoh: {e}"))?;
    let (back_tx, back) = mpsc::channel();
    let _subscriber = session
        .declare_subscriber(PONG)
        .callback(move |_| {
            let _ = back_tx.send(Instant::now());
        })
        .wait()
        .map_err(|e| anyhow!("zenoh: {e}"))?;
    let publisher = session
        .declare_publisher(PING)
        .congestion_control(CongestionControl::Block)
        .wait()
        .map_err(|e| anyhow!("zenoh: {e}"))?;
    // Until the other side's subscriber is known here: the first ping that comes back.
    let linked = Instant::now();
    loop {
        publisher
            .put(vec![0u8; 32])
            .wait()
            .map_err(|e| anyhow!("zenoh: {e}"))?;
        if back.recv_timeout(Duration::from_millis(100)).is_ok() {
            break;
        }
        if linked.elapsed() > Duration::from_secs(10) {
            bail!("no answer from zenoh-pong within 10 s");
        }
    }
    let gap = Duration::from_secs(1) / rate.max(1);
    let mut round_trips = Vec::with_capacity(count);
    for i in 0..count + WARMUP {
        // Late answers of an earlier ping would be taken for this one's.
        while back.try_recv().is_ok() {}
        let sent = Instant::now();
        publisher
            .put(vec![0u8; 32])
            .wait()
            .map_err(|e| anyhow!("zenoh: {e}"))?;
        let came = back
            .recv_timeout(Duration::from_secs(2))
            .map_err(|_| anyhow!("a ping got no answer within 2 s"))?;
        if i >= WARMUP {
            round_trips.push(came.duration_since(sent));
        }
        std::thread::sleep(gap.saturating_sub(sent.elapsed()));
    }
    round_trips.sort();
    let half_us = |q: f64| {
        let i = ((round_trips.len() - 1) as f64 * q).round() as usize;
        round_trips[i].as_secs_f64() * 1e6 / 2.0
    };
    Ok(Floor {
        p50_us: half_us(0.5),
        p99_us: half_us(0.99),
        samples: round_trips.len(),
    })
}

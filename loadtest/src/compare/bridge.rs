//! `fbbus-loadtest compare bridge`: what the zenoh hop between two lines costs, side by side in one run.
//!
//! Three setups, each with one device publishing the conveyor's STATE event (canonical
//! JSON, QoS 0) on `fb/bench-dev/CONV/STATE` and one subscriber:
//!
//! - **one broker**: fbbus without a bridge, device and subscriber on it;
//! - **line A, local**: line A of a bridged pair, device and subscriber both on A (what a
//!   configured bridge costs traffic that does not cross);
//! - **A → B**: the device on line A, the subscriber on line B: MQTT → router → bridge →
//!   zenoh (loopback TCP) → bridge → typed check → router → MQTT.
//!
//! Measured per setup: **latency**, one message at a time (send, wait for it, next),
//! p50/p99/max; **throughput**, a burst of M messages into the subscriber, from the first
//! send to the last receipt. Then the hop's cost: p50(A → B) − p50(one broker), and
//! msg/s(A → B) / msg/s(one broker). Everything on 127.0.0.1; every loop is bounded.

use std::net::SocketAddr;
use std::path::Path;
use std::time::{Duration, Instant};

use anyhow::{bail, Context as _, Result};
use hdrhistogram::Histogram;
use tokio::io::AsyncWriteExt;

use super::{metric, start_fbbus as start};
use loadtest::broker_process::spawn::{self, Running};
use loadtest::raw_client::{self as mqtt, PacketReader};

pub struct BridgeParams {
    pub samples: usize,
    pub burst: usize,
}

impl BridgeParams {
    pub fn full() -> BridgeParams {
        BridgeParams {
            samples: 5_000,
            burst: 40_000,
        }
    }

    pub fn quick() -> BridgeParams {
        BridgeParams {
            samples: 200,
            burst: 2_000,
        }
    }
}

const DEVICE: &str = "bench-dev";
const TOPIC: &str = "fb/bench-dev/CONV/STATE";
const INTERFACE: &str = r#"{"fbs":{"CONV":{"type":"CONVEYOR",
  "events_out":{"STATE":{"with":["ID","CONNECT","SENSOR_IN","SENSOR_OUT","POSITION","SWAP"]}},
  "data_out":{"ID":"STRING","CONNECT":"BOOL","SENSOR_IN":"BOOL","SENSOR_OUT":"BOOL","POSITION":"INT","SWAP":"BOOL"}}}}"#;
const EVENT: &str = r#"{"seq":1,"ts":1763800000000000,"data":{"ID":"conveyor-a","CONNECT":true,"SENSOR_IN":false,"SENSOR_OUT":true,"POSITION":2,"SWAP":false}}"#;
const DEADLINE: Duration = Duration::from_secs(60);

struct Figures {
    p50_us: f64,
    p99_us: f64,
    max_us: f64,
    rate: f64,
    delivered: usize,
}

pub async fn run(fbbus: &Path, p: &BridgeParams) -> Result<()> {
    let zenoh_port = spawn::free_port()?;
    let endpoint = format!("tcp/127.0.0.1:{zenoh_port}");
    println!(
        "fbbus {}: the zenoh hop between two lines vs one broker; {} latency samples, bursts of {} (QoS 0, {}-byte STATE events)\n",
        spawn::fbbus_version(fbbus),
        p.samples,
        p.burst,
        EVENT.len()
    );
    let single = start(fbbus, &[], "").await?;
    let a = start(
        fbbus,
        &["line = \"line-a\"".into()],
        &format!("\n[bridge]\nlisten = [\"{endpoint}\"]\n"),
    )
    .await?;
    let b = start(
        fbbus,
        &["line = \"line-b\"".into()],
        &format!("\n[bridge]\nconnect = [\"{endpoint}\"]\n"),
    )
    .await?;

    let one = measure("one broker", &single, &single, None, p).await?;
    let local = measure("line A, local", &a, &a, None, p).await?;
    let across = measure("A -> B", &a, &b, Some(&a), p).await?;

    println!(
        "{:<16} {:>9} {:>9} {:>9} {:>12} {:>12}",
        "setup", "p50 us", "p99 us", "max us", "burst msg/s", "delivered"
    );
    for (name, f) in [
        ("one broker", &one),
        ("line A, local", &local),
        ("A -> B", &across),
    ] {
        println!(
            "{:<16} {:>9.0} {:>9.0} {:>9.0} {:>12.0} {:>6}/{}",
            name, f.p50_us, f.p99_us, f.max_us, f.rate, f.delivered, p.burst
        );
    }
    println!(
        "\nhop adds {:.0} us at p50 ({:.0} us at p99); throughput across the bridge = {:.2} x one broker",
        across.p50_us - one.p50_us,
        across.p99_us - one.p99_us,
        across.rate / one.rate
    );
    Ok(())
}

/// One setup: a device on `publisher`, a subscriber on `subscriber`. With `exporter`, waits
/// until that line's bridge has the subscriber's interest.
async fn measure(
    name: &str,
    publisher: &Running,
    subscriber: &Running,
    exporter: Option<&Running>,
    p: &BridgeParams,
) -> Result<Figures> {
    eprintln!("bridge: {name}");
    let mut dev = mqtt::connect(publisher.addr, DEVICE, None).await?;
    dev.write_all(&mqtt::publish_packet(
        &format!("fbbus/declare/{DEVICE}"),
        INTERFACE.as_bytes(),
    ))
    .await?;
    let admin = publisher.admin.context("fbbus has an admin endpoint")?;
    wait_metric(admin, "fbbus_registry_devices{status=\"online\"}", 1.0).await?;
    let mut sub =
        mqtt::connect(subscriber.addr, &format!("bench-sub-{}", name.len()), None).await?;
    mqtt::subscribe(&mut sub, TOPIC).await?;
    if let Some(exporter) = exporter {
        let admin = exporter.admin.context("fbbus has an admin endpoint")?;
        wait_metric(admin, "fbbus_bridge_remote_subscriptions", 1.0).await?;
    }
    let mut reader = PacketReader::new(sub);
    let packet = mqtt::publish_packet(TOPIC, EVENT.as_bytes());

    // Warm up: until the path delivers (the exporter's router subscription is in place).
    let warm_deadline = Instant::now() + Duration::from_secs(10);
    loop {
        dev.write_all(&packet).await?;
        if receive(&mut reader, 1, Duration::from_millis(200)).await? == 1 {
            break;
        }
        if Instant::now() > warm_deadline {
            bail!("{name}: nothing delivered in 10 s");
        }
    }
    while receive(&mut reader, 1, Duration::from_millis(200)).await? == 1 {}

    let mut latency = Histogram::<u64>::new(3)?;
    for _ in 0..p.samples {
        let sent = Instant::now();
        dev.write_all(&packet).await?;
        if receive(&mut reader, 1, Duration::from_secs(2)).await? != 1 {
            bail!("{name}: a latency sample was not delivered within 2 s");
        }
        latency.record(sent.elapsed().as_micros() as u64)?;
    }

    let burst: Vec<u8> = packet.repeat(p.burst.min(1_000));
    let first_send = Instant::now();
    let writer = async {
        let mut left = p.burst;
        while left > 0 {
            let n = left.min(1_000);
            dev.write_all(&burst[..n * packet.len()]).await?;
            left -= n;
        }
        Ok::<_, std::io::Error>(dev)
    };
    let (dev, received) = tokio::join!(writer, async {
        let mut got = 0;
        let mut last = first_send;
        let deadline = Instant::now() + DEADLINE;
        while got < p.burst && Instant::now() < deadline {
            match receive(&mut reader, p.burst - got, Duration::from_secs(2)).await {
                Ok(0) | Err(_) => break,
                Ok(n) => {
                    got += n;
                    last = Instant::now();
                }
            }
        }
        (got, last)
    });
    let mut dev = dev?;
    let (delivered, last) = received;
    let _ = dev.write_all(&mqtt::DISCONNECT).await;
    let secs = last.duration_since(first_send).as_secs_f64().max(1e-9);
    Ok(Figures {
        p50_us: latency.value_at_quantile(0.5) as f64,
        p99_us: latency.value_at_quantile(0.99) as f64,
        max_us: latency.max() as f64,
        rate: delivered as f64 / secs,
        delivered,
    })
}

/// Reads until `want` publications arrived or `quiet` passed without one; returns how many.
async fn receive(reader: &mut PacketReader, want: usize, quiet: Duration) -> Result<usize> {
    let mut got = 0;
    loop {
        while let Some((header, _)) = reader.next_packet()? {
            if header >> 4 == 3 {
                got += 1;
            }
        }
        if got >= want {
            return Ok(got);
        }
        match tokio::time::timeout(quiet, reader.read_more()).await {
            Ok(Ok(0)) => bail!("the broker closed the subscriber"),
            Ok(Ok(_)) => {}
            Ok(Err(e)) => return Err(e.into()),
            Err(_) => return Ok(got),
        }
    }
}

async fn wait_metric(admin: SocketAddr, series: &str, min: f64) -> Result<()> {
    let deadline = Instant::now() + Duration::from_secs(20);
    loop {
        if metric(admin, series).await >= min {
            return Ok(());
        }
        if Instant::now() > deadline {
            bail!("{series} stayed below {min} for 20 s");
        }
        tokio::time::sleep(Duration::from_millis(10)).await;
    }
}

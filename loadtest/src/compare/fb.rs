//! `fbbus-loadtest compare fb`: what fbbus's typed FB topics and device registry cost, on fbbus alone.
//!
//! 1. **Validation and mapping cost.** Ten devices with a conveyor interface burst the
//!    same event message into one subscriber, in turn on an untyped topic
//!    (`plant/<dev>/CONV/STATE`, routed as is), on the typed topic
//!    (`fb/<dev>/CONV/STATE`, decoded and checked against the declaration) and on the
//!    device's own topic (`line/<dev>/state`, mapped onto `CONV.STATE` by its device
//!    profile: decoded, checked, routed there as is and re-encoded onto
//!    `fb/<dev>/CONV/STATE`, which the subscriber reads), A B C A B C in one broker
//!    process. Reported: each round's msg/s, the medians, typed/untyped and
//!    mapped/typed.
//! 2. **Births.** N devices (default 10,000) connect, then all declare at once; reported:
//!    declarations per second until the registry shows every device online (polled on
//!    `/metrics`), which includes each record's retained publication.
//! 3. **Registry queries.** With those N devices registered: latency of
//!    `GET /api/v1/devices/<id>` (1,000 sequential requests, random ids) and of the full
//!    `GET /api/v1/devices` list (20 requests), p50/p99/max.
//!
//! 4. **The Sparkplug view's cost** (issue 36; run after section 1): two fbbus processes of the same binary,
//!    one with `[sparkplug] enabled = true`, both running, each with the same publishers
//!    declared, and on the "on" broker a Sparkplug host subscribed to `spBv1.0/#` reading
//!    everything; the typed burst of section 1 in rounds off, on, off, on, ... Reported:
//!    each round's msg/s, the medians and on/off against the goal (at least 0.90), and
//!    the view's DDATA count on the "on" broker (it must have published one per message:
//!    a binary without the view fails the section).
//!
//! Everything runs on 127.0.0.1 against an fbbus child process; every loop is bounded
//! by a count and a deadline.

use std::net::SocketAddr;
use std::path::Path;
use std::sync::atomic::{AtomicUsize, Ordering};
use std::sync::Arc;
use std::time::{Duration, Instant};

use anyhow::{bail, Context as _, Result};
use hdrhistogram::Histogram;
use tokio::io::{AsyncReadExt, AsyncWriteExt};
use tokio::net::TcpStream;

use loadtest::broker_process::spawn::{self, Running};
use loadtest::raw_client::{self as mqtt, PacketReader};
use loadtest::scrape;

use super::{metric, series_value, start_fbbus as start};

pub struct FbParams {
    pub devices: usize,
    pub publishers: usize,
    pub messages: usize,
    pub rounds: usize,
}

impl FbParams {
    pub fn full() -> FbParams {
        FbParams {
            devices: 10_000,
            publishers: 10,
            // 40,000 messages of ~180 bytes stay within the router's default commit-log
            // window per filter (4 x 4 MiB); a larger burst into one slow subscriber loses
            // messages in rumqttd's router (see the issue-3 notes in README.md).
            messages: 4_000,
            rounds: 5,
        }
    }

    pub fn quick() -> FbParams {
        FbParams {
            devices: 200,
            publishers: 2,
            messages: 500,
            rounds: 1,
        }
    }
}

const DEADLINE: Duration = Duration::from_secs(120);

/// The conveyor module interface of the reference line (one FB, one event with six data).
const INTERFACE: &str = r#"{"fbs":{"CONV":{"type":"CONVEYOR",
  "events_out":{"STATE":{"with":["ID","CONNECT","SENSOR_IN","SENSOR_OUT","POSITION","SWAP"]}},
  "data_out":{"ID":"STRING","CONNECT":"BOOL","SENSOR_IN":"BOOL","SENSOR_OUT":"BOOL","POSITION":"INT","SWAP":"BOOL"}}}}"#;

/// One STATE event, with sequence number and timestamp (so fbbus routes the bytes as sent).
const EVENT: &str = r#"{"seq":1,"ts":1763800000000000,"data":{"ID":"conveyor-a","CONNECT":true,"SENSOR_IN":false,"SENSOR_OUT":true,"POSITION":2,"SWAP":false}}"#;

pub async fn run(fbbus: &Path, p: &FbParams) -> Result<()> {
    // The publishers' profiles: the interface they declare, and their own topic.
    let profiles = tempfile::tempdir()?;
    for i in 0..p.publishers {
        std::fs::write(
            profiles.path().join(format!("bench-pub-{i}.toml")),
            profile(&format!("bench-pub-{i}")),
        )?;
    }
    // Every device of the run comes from one loopback address: the registry's per-identity
    // limit (issue 21) raised above the births' count, as `max_sessions_per_identity` is.
    let tables = format!(
        "\n[fb]\nprofiles_dir = \"{}\"\nmax_devices = 20200\nmax_devices_per_identity = 20200\n",
        profiles.path().display()
    );
    let broker = start(fbbus, &[], &tables).await?;
    let admin = broker.admin.context("fbbus runs with an admin endpoint")?;
    println!(
        "fbbus {} at {} (admin {admin}); {} publishers x {} messages, {} rounds; {} devices\n",
        spawn::fbbus_version(fbbus),
        broker.addr,
        p.publishers,
        p.messages,
        p.rounds,
        p.devices
    );

    validation_cost(&broker, admin, p).await?;
    sparkplug_cost(fbbus, &tables, p).await?;
    let _devices = births(&broker, admin, p).await?;
    registry_queries(admin, p).await?;
    if let Some(kib) = broker.rss_kib() {
        println!(
            "\nbroker resident memory with {} devices connected and registered: {:.1} MB\n",
            p.devices + p.publishers,
            kib as f64 / 1024.0
        );
    }
    Ok(())
}

async fn validation_cost(broker: &Running, admin: SocketAddr, p: &FbParams) -> Result<()> {
    let (mut reader, mut pubs) = publishers(broker, admin, p).await?;

    println!("1. validation and mapping cost: the same STATE event, untyped vs typed vs the device's own (profile-mapped) topic (QoS 0 burst, 1 subscriber)");
    println!(
        "   {:<7} {:>14} {:>14} {:>14}",
        "round", "untyped msg/s", "typed msg/s", "mapped msg/s"
    );
    let mut rates: [Vec<f64>; 3] = Default::default();
    for round in 1..=p.rounds {
        let mut this = [0.0; 3];
        for (k, topic) in [Topic::Untyped, Topic::Typed, Topic::Mapped]
            .into_iter()
            .enumerate()
        {
            let (rate, lost) = burst(&mut reader, &mut pubs, topic, p.messages).await?;
            if lost > 0 {
                bail!("{topic:?} round {round}: {lost} messages lost");
            }
            this[k] = rate;
            rates[k].push(rate);
        }
        println!(
            "   {round:<7} {:>14.0} {:>14.0} {:>14.0}",
            this[0], this[1], this[2]
        );
    }
    let [u, t, m] = rates.map(|mut r| median(&mut r));
    println!(
        "   median  {u:>14.0} {t:>14.0} {m:>14.0}   typed/untyped = {:.3} (validation costs {:.1} %), mapped/typed = {:.3}\n",
        t / u,
        (1.0 - t / u) * 100.0,
        m / t
    );
    Ok(())
}

/// One subscriber of every burst's topics, and `p.publishers` devices declared and online.
async fn publishers(
    broker: &Running,
    admin: SocketAddr,
    p: &FbParams,
) -> Result<(PacketReader, Vec<(String, TcpStream)>)> {
    let mut sub = mqtt::connect(broker.addr, "bench-sub", None).await?;
    subscribe_all(&mut sub, &["fb/+/CONV/STATE", "plant/+/CONV/STATE"]).await?;
    // (`line/+/state` is not read: a mapped message reaches the subscriber once, on fb/.)
    let reader = PacketReader::new(sub);
    let mut pubs = Vec::new();
    for i in 0..p.publishers {
        let id = format!("bench-pub-{i}");
        let mut s = mqtt::connect(broker.addr, &id, None).await?;
        s.write_all(&mqtt::publish_packet(
            &format!("fbbus/declare/{id}"),
            INTERFACE.as_bytes(),
        ))
        .await?;
        pubs.push((id, s));
    }
    wait_online(admin, p.publishers).await?;
    tokio::time::sleep(Duration::from_millis(200)).await;
    Ok((reader, pubs))
}

/// Section 4: the typed burst with the Sparkplug view off and on, alternating.
async fn sparkplug_cost(fbbus: &Path, tables: &str, p: &FbParams) -> Result<()> {
    println!("4. the Sparkplug view's cost: the typed burst of section 1, view off and on with a Sparkplug host reading (two brokers of one binary, rounds alternating)");
    let off = start(fbbus, &[], tables).await?;
    let on = start(
        fbbus,
        &[],
        &format!("{tables}\n[sparkplug]\nenabled = true\n"),
    )
    .await?;
    let mut lines = Vec::new();
    for broker in [&off, &on] {
        let admin = broker.admin.context("fbbus runs with an admin endpoint")?;
        lines.push((publishers(broker, admin, p).await?, admin));
    }
    // A Sparkplug host reading everything the view publishes (the view reads the line's
    // values only once someone reads Sparkplug), draining its socket until the end.
    let mut host = mqtt::connect(on.addr, "bench-scada", None).await?;
    subscribe_all(&mut host, &["spBv1.0/#"]).await?;
    let sparkplug_bytes = Arc::new(AtomicUsize::new(0));
    let drain = tokio::spawn({
        let read = Arc::clone(&sparkplug_bytes);
        async move {
            let mut buf = vec![0u8; 1 << 16];
            while let Ok(n @ 1..) = host.read(&mut buf).await {
                read.fetch_add(n, Ordering::Relaxed);
            }
        }
    });
    println!("   {:<7} {:>14} {:>14}", "round", "off msg/s", "on msg/s");
    let mut rates: [Vec<f64>; 2] = Default::default();
    for round in 1..=p.rounds.max(3) {
        let mut this = [0.0; 2];
        for (k, ((reader, pubs), _)) in lines.iter_mut().enumerate() {
            let (rate, lost) = burst(reader, pubs, Topic::Typed, p.messages).await?;
            if lost > 0 {
                bail!(
                    "Sparkplug view {} round {round}: {lost} messages lost",
                    ["off", "on"][k]
                );
            }
            this[k] = rate;
            rates[k].push(rate);
        }
        println!("   {round:<7} {:>14.0} {:>14.0}", this[0], this[1]);
    }
    let [off_rate, on_rate] = rates.map(|mut r| median(&mut r));
    let ratio = on_rate / off_rate;
    println!(
        "   median  {off_rate:>14.0} {on_rate:>14.0}   on/off = {ratio:.3} (goal: at least 0.90: {})",
        if ratio >= 0.90 { "met" } else { "NOT met" }
    );
    let ddata = metric(lines[1].1, "fbbus_sparkplug_messages_total{kind=\"DDATA\"}").await;
    if ddata < 1.0 {
        bail!("the \"on\" broker published no Sparkplug DDATA: this fbbus has no Sparkplug view");
    }
    drain.abort();
    println!(
        "   the view published {ddata:.0} DDATA on the \"on\" broker; its host read {:.1} MB\n",
        sparkplug_bytes.load(Ordering::Relaxed) as f64 / 1e6
    );
    Ok(())
}

/// Where a burst is published.
#[derive(Debug, Clone, Copy)]
enum Topic {
    /// `plant/<id>/CONV/STATE`: no meaning to fbbus, routed as is.
    Untyped,
    /// `fb/<id>/CONV/STATE`: checked against the declared interface.
    Typed,
    /// `line/<id>/state`: the device's own topic, mapped by its profile.
    Mapped,
}

impl Topic {
    fn of(self, id: &str) -> String {
        match self {
            Topic::Untyped => format!("plant/{id}/CONV/STATE"),
            Topic::Typed => format!("fb/{id}/CONV/STATE"),
            Topic::Mapped => format!("line/{id}/state"),
        }
    }
}

/// A publisher's device profile: [`INTERFACE`], and `line/<id>/state` as its own topic
/// for `CONV.STATE` in canonical JSON.
fn profile(id: &str) -> String {
    format!(
        r#"device = "{id}"
[interface.fbs.CONV]
type = "CONVEYOR"
events_out = {{ STATE = {{ with = ["ID", "CONNECT", "SENSOR_IN", "SENSOR_OUT", "POSITION", "SWAP"] }} }}
data_out = {{ ID = "STRING", CONNECT = "BOOL", SENSOR_IN = "BOOL", SENSOR_OUT = "BOOL", POSITION = "INT", SWAP = "BOOL" }}
[[topics]]
topic = "line/{id}/state"
port = "CONV.STATE"
"#
    )
}

/// Every publisher sends `messages` PUBLISHes on its `topic` at once; returns the
/// subscriber's receive rate and the messages that never arrived.
async fn burst(
    reader: &mut PacketReader,
    pubs: &mut Vec<(String, TcpStream)>,
    topic: Topic,
    messages: usize,
) -> Result<(f64, u64)> {
    let expected = (pubs.len() * messages) as u64;
    let start = Instant::now();
    let mut tasks = Vec::new();
    for (id, mut stream) in std::mem::take(pubs) {
        let packet = mqtt::publish_packet(&topic.of(&id), EVENT.as_bytes());
        // 64 messages per write: the publishers are cheaper than the broker.
        let batch: Vec<u8> = packet.repeat(64);
        tasks.push(tokio::spawn(async move {
            let mut left = messages;
            while left > 0 {
                let n = left.min(64);
                stream.write_all(&batch[..packet.len() * n]).await?;
                left -= n;
            }
            anyhow::Ok((id, stream))
        }));
    }
    let mut received = 0u64;
    let mut last = start;
    let deadline = start + DEADLINE;
    while received < expected && Instant::now() < deadline {
        match tokio::time::timeout(Duration::from_secs(2), reader.read_more()).await {
            Ok(Ok(0)) | Ok(Err(_)) => bail!("the subscriber's connection closed"),
            Err(_) => break,
            Ok(Ok(_)) => {
                while let Some((header, body)) = reader.next_packet()? {
                    if mqtt::publish_payload(header, body).is_some() {
                        received += 1;
                    }
                }
                last = Instant::now();
            }
        }
    }
    for t in tasks {
        pubs.push(t.await??);
    }
    Ok((
        received as f64 / last.duration_since(start).as_secs_f64(),
        expected - received.min(expected),
    ))
}

async fn births(broker: &Running, admin: SocketAddr, p: &FbParams) -> Result<Vec<TcpStream>> {
    println!(
        "2. births: {} devices connect, then declare at once",
        p.devices
    );
    let connected = Arc::new(AtomicUsize::new(0));
    let slots = Arc::new(tokio::sync::Semaphore::new(256));
    let mut tasks = Vec::with_capacity(p.devices);
    for i in 0..p.devices {
        let (addr, slots, connected) = (broker.addr, Arc::clone(&slots), Arc::clone(&connected));
        tasks.push(tokio::spawn(async move {
            let _slot = slots.acquire().await;
            let s = mqtt::connect(addr, &device_id(i), None).await?;
            connected.fetch_add(1, Ordering::Relaxed);
            anyhow::Ok(s)
        }));
    }
    let mut streams = Vec::with_capacity(p.devices);
    for t in tasks {
        streams.push(t.await??);
    }
    let start = Instant::now();
    for (i, s) in streams.iter_mut().enumerate() {
        s.write_all(&mqtt::publish_packet(
            &format!("fbbus/declare/{}", device_id(i)),
            INTERFACE.as_bytes(),
        ))
        .await?;
    }
    let written = start.elapsed();
    wait_online(admin, p.devices).await?;
    let elapsed = start.elapsed();
    println!(
        "   {} declarations written in {:.3} s; all online in the registry after {:.3} s: {:.0} births/s\n",
        p.devices,
        written.as_secs_f64(),
        elapsed.as_secs_f64(),
        p.devices as f64 / elapsed.as_secs_f64()
    );
    Ok(streams)
}

async fn registry_queries(admin: SocketAddr, p: &FbParams) -> Result<()> {
    println!(
        "3. registry over HTTP with {} devices",
        p.devices + p.publishers
    );
    let mut one = Histogram::<u64>::new(3)?;
    let mut rng = 0x9E37_79B9_7F4A_7C15u64;
    for _ in 0..1000 {
        rng ^= rng << 13;
        rng ^= rng >> 7;
        rng ^= rng << 17;
        let id = device_id((rng % p.devices as u64) as usize);
        let t = Instant::now();
        match get(admin, &format!("/api/v1/devices/{id}")).await {
            Ok(_) => one.record(t.elapsed().as_micros() as u64)?,
            Err(e) => bail!("GET /api/v1/devices/{id}: {e}"),
        }
    }
    let mut all = Histogram::<u64>::new(3)?;
    let mut size = 0;
    for _ in 0..20 {
        let t = Instant::now();
        match get(admin, "/api/v1/devices").await {
            Ok(body) => {
                all.record(t.elapsed().as_micros() as u64)?;
                size = body.len();
            }
            Err(e) => bail!("GET /api/v1/devices: {e}"),
        }
    }
    let ms = |h: &Histogram<u64>, q: f64| h.value_at_quantile(q) as f64 / 1000.0;
    println!(
        "   GET /api/v1/devices/<id>  x1000: p50 {:.2} ms  p99 {:.2} ms  max {:.2} ms",
        ms(&one, 0.5),
        ms(&one, 0.99),
        one.max() as f64 / 1000.0
    );
    println!(
        "   GET /api/v1/devices       x20:   p50 {:.1} ms  p99 {:.1} ms  max {:.1} ms  ({:.1} MB of JSON)",
        ms(&all, 0.5),
        ms(&all, 0.99),
        all.max() as f64 / 1000.0,
        size as f64 / 1e6
    );
    Ok(())
}

fn device_id(i: usize) -> String {
    format!("bench-dev-{i:05}")
}

/// Subscribes to every filter at QoS 0 on one connection.
async fn subscribe_all(stream: &mut TcpStream, filters: &[&str]) -> Result<()> {
    for (i, filter) in filters.iter().enumerate() {
        stream
            .write_all(&mqtt::subscribe_packet(i as u16 + 1, filter))
            .await?;
    }
    let mut acks = vec![0u8; 5 * filters.len()];
    tokio::time::timeout(Duration::from_secs(5), stream.read_exact(&mut acks))
        .await
        .context("no SUBACK")??;
    if acks.chunks(5).any(|a| a[0] != 0x90 || a[4] == 0x80) {
        bail!("a subscription was refused: {acks:02x?}");
    }
    Ok(())
}

/// Polls `/metrics` until the registry counts `n` devices online. A page that could not
/// be read says so: with 10,000 of the harness's own sockets open, a failed request once
/// read as "0 online" while the broker had 9,163.
async fn wait_online(admin: SocketAddr, n: usize) -> Result<()> {
    let deadline = Instant::now() + DEADLINE;
    loop {
        let online = get(admin, "/metrics")
            .await
            .map(|text| series_value(&text, "fbbus_registry_devices{status=\"online\"}"));
        if online.as_ref().is_ok_and(|&online| online as usize >= n) {
            return Ok(());
        }
        if Instant::now() > deadline {
            match online {
                Ok(online) => bail!("only {online} of {n} devices online after {DEADLINE:?}"),
                Err(e) => bail!(
                    "the broker's /metrics could not be read after {DEADLINE:?} ({e}): how \
                     many of {n} devices are online is unknown"
                ),
            }
        }
        tokio::time::sleep(Duration::from_millis(5)).await;
    }
}

fn median(v: &mut [f64]) -> f64 {
    v.sort_by(|a, b| a.total_cmp(b));
    v[v.len() / 2]
}

/// One GET on fbbus's admin endpoint: the body of a 200 answer, within 10 s.
async fn get(admin: SocketAddr, path: &str) -> Result<String, String> {
    scrape::get(&format!("http://{admin}{path}"), Duration::from_secs(10)).await
}

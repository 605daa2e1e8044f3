//! The harness end to end: the real `fbbus-loadtest` binary against real brokers (the
//! `fbbus` binary, Debian's Mosquitto) on free loopback ports, at tiny scale, checking
//! what its outputs say: report.json, batches.csv, batches.jtl, the SVG charts and the
//! terminal table. Known loss is injected by a lossy TCP proxy in front of Mosquitto and
//! must be reported exactly. Nothing here asserts performance: only counts, structure
//! and messages. Every wait is bounded (common::RUN_LIMIT for a run).

mod common;

use std::collections::HashMap;
use std::net::SocketAddr;
use std::sync::{Arc, Mutex};

use loadtest::model::{Batch, Report};

use common::{col, loadtest, svg_series, Fbbus, Mosquitto, Run};

const CSV_HEADER: [&str; 25] = [
    "target",
    "target_name",
    "label",
    "x",
    "repeat",
    "started_ms",
    "sent",
    "expected",
    "delivered",
    "lost",
    "delivery_rate",
    "delivered_fb",
    "duplicates",
    "out_of_order",
    "send_us",
    "processing_us",
    "throughput",
    "lat_mean_us",
    "lat_p50_us",
    "lat_p90_us",
    "lat_p99_us",
    "lat_p999_us",
    "lat_max_us",
    "ok",
    "error",
];

/// JMeter's 17 default CSV result fields, in JMeter's order.
const JTL_HEADER: [&str; 17] = [
    "timeStamp",
    "elapsed",
    "label",
    "responseCode",
    "responseMessage",
    "threadName",
    "dataType",
    "success",
    "failureMessage",
    "bytes",
    "sentBytes",
    "grpThreads",
    "allThreads",
    "URL",
    "Latency",
    "IdleTime",
    "Connect",
];

/// Sorted distinct x of `batches`.
fn xs<'a>(batches: impl Iterator<Item = &'a Batch>) -> Vec<u64> {
    let mut xs: Vec<u64> = batches.map(|b| b.x as u64).collect();
    xs.sort();
    xs.dedup();
    xs
}

/// Every batch of the report delivered every expected copy, nothing duplicated.
fn assert_all_delivered(r: &Report, run: &Run) {
    for b in &r.batches {
        assert!(b.sent > 0, "{b:?}");
        assert_eq!(b.delivered, b.expected, "{b:?}\n{}", run.context());
        assert_eq!((b.lost(), b.duplicates), (0, 0), "{b:?}");
        assert!(b.ok && b.error.is_none(), "{b:?}");
    }
}

/// The summaries add up to the batches, per target.
fn assert_summaries_add_up(r: &Report) {
    assert_eq!(r.summaries.len(), r.targets.len());
    for s in &r.summaries {
        let own: Vec<&Batch> = r.batches.iter().filter(|b| b.target == s.target).collect();
        assert_eq!(s.batches, own.len() as u64, "{}", s.target);
        assert_eq!(s.sent, own.iter().map(|b| b.sent).sum::<u64>());
        assert_eq!(s.expected, own.iter().map(|b| b.expected).sum::<u64>());
        assert_eq!(s.delivered, own.iter().map(|b| b.delivered).sum::<u64>());
        let fb: Vec<u64> = own.iter().filter_map(|b| b.delivered_fb).collect();
        assert_eq!(s.delivered_fb, (!fb.is_empty()).then(|| fb.iter().sum()));
    }
}

/// batches.csv and batches.jtl: one row per batch of the report, in order, agreeing with
/// it (lost = expected - delivered; JMeter success = ok).
fn assert_csv_and_jtl(run: &Run, r: &Report) {
    let csv = run.table("batches.csv", &CSV_HEADER);
    assert_eq!(csv.len(), r.batches.len(), "one CSV row per batch");
    for (row, b) in csv.iter().zip(&r.batches) {
        assert_eq!(col(row, "target"), b.target);
        assert_eq!(col(row, "label"), b.label);
        let n = |c: &str| -> u64 { col(row, c).parse().unwrap() };
        assert_eq!(
            (n("sent"), n("expected"), n("delivered")),
            (b.sent, b.expected, b.delivered)
        );
        assert_eq!(n("lost"), n("expected") - n("delivered"), "{row:?}");
        assert_eq!(col(row, "ok"), b.ok.to_string());
        assert_eq!(
            col(row, "delivered_fb"),
            b.delivered_fb.map(|d| d.to_string()).unwrap_or_default()
        );
    }
    let jtl = run.table("batches.jtl", &JTL_HEADER);
    assert_eq!(jtl.len(), r.batches.len(), "one JTL sample per batch");
    for (row, b) in jtl.iter().zip(&r.batches) {
        assert_eq!(col(row, "success"), b.ok.to_string(), "{row:?}");
        assert_eq!(col(row, "responseCode"), if b.ok { "200" } else { "500" });
        assert_eq!(col(row, "timeStamp"), b.started_ms.to_string());
        assert_eq!(col(row, "bytes"), b.delivered.to_string());
        assert_eq!(col(row, "sentBytes"), b.sent.to_string());
        assert!(col(row, "label").contains(&b.label), "{row:?}");
        assert_eq!(col(row, "failureMessage"), b.error.as_deref().unwrap_or(""));
    }
}

/// `file` exists, names every target and has a tagged series per target with one point
/// per x (`points` of them).
fn assert_chart(run: &Run, file: &str, r: &Report, points: usize) {
    let svg = run.file(file);
    assert!(svg.contains("<svg"), "{file}");
    for t in &r.targets {
        assert!(svg.contains(&t.name), "{file} does not name {}", t.name);
        let series = svg_series(&svg, &t.name)
            .unwrap_or_else(|| panic!("{file}: no data-series for {}", t.name));
        assert_eq!(series.len(), points, "{file}: points of {}", t.name);
    }
}

// ---------------------------------------------------------------------------------------
// 1. stress on fbbus

#[test]
fn stress_on_fbbus_counts_every_message_at_both_subscribers() {
    let fbbus = Fbbus::start();
    let run = loadtest(
        &[
            "--broker",
            &fbbus.url(),
            "stress",
            "--max",
            "40",
            "--repeats",
            "2",
        ],
        &[],
    );
    let r = run.ok();
    assert_eq!(r.scenario, "stress");
    assert_eq!(r.targets.len(), 1);
    assert_eq!(r.targets[0].name, "fbbus");
    assert!(r.ceiling.as_ref().is_some_and(|c| c.messages == 500));

    // Bursts 10, 20, 40, each twice, in order.
    let runs: Vec<(u64, u32)> = r.batches.iter().map(|b| (b.x as u64, b.repeat)).collect();
    assert_eq!(
        runs,
        vec![(10, 1), (10, 2), (20, 1), (20, 2), (40, 1), (40, 2)]
    );
    for b in &r.batches {
        assert_eq!(b.target, "A");
        assert_eq!(b.sent, b.x as u64, "{b:?}");
        assert_eq!(b.expected, b.sent);
        // The FB subscriber (fb-bridge client API) counted every message too.
        assert_eq!(b.delivered_fb, Some(b.sent), "{b:?}");
        assert_eq!(b.latency.count, b.delivered, "{b:?}");
    }
    assert_all_delivered(&r, &run);
    assert_summaries_add_up(&r);
    assert_eq!(r.summaries[0].sent, 2 * (10 + 20 + 40));
    assert!(r.summaries[0]
        .figures
        .iter()
        .any(|f| f.name == "max_throughput"));
    assert!(r.ratios.is_empty(), "no ratios without a second broker");
    assert_csv_and_jtl(&run, &r);
    for chart in ["stress.svg", "delivery-rate.svg"] {
        assert_chart(&run, chart, &r, 3);
    }
    // The reference line: what was sent per burst.
    assert_eq!(
        svg_series(&run.file("stress.svg"), "sent").map(|p| p.len()),
        Some(3)
    );
    let percentiles = run.file("latency-percentiles.svg");
    assert!(percentiles.contains("fbbus") && svg_series(&percentiles, "fbbus").is_some());
    // The terminal table: one row per burst size.
    for label in ["burst 10", "burst 20", "burst 40"] {
        assert!(run.stdout.contains(label), "{}", run.context());
    }
}

// ---------------------------------------------------------------------------------------
// 2. compare mode

#[test]
fn compare_mode_interleaves_fbbus_and_mosquitto() {
    let Some(mosquitto) = Mosquitto::start() else {
        return;
    };
    let fbbus = Fbbus::start();
    let run = loadtest(
        &[
            "--broker",
            &fbbus.url(),
            "--compare",
            &mosquitto.url(),
            "stress",
            "--max",
            "40",
            "--repeats",
            "2",
        ],
        &[],
    );
    let r = run.ok();
    let names: Vec<(&str, &str)> = r
        .targets
        .iter()
        .map(|t| (t.label.as_str(), t.name.as_str()))
        .collect();
    assert_eq!(names, vec![("A", "fbbus"), ("B", "mosquitto")]);
    let version = r.targets[1].version.as_deref().unwrap_or_default();
    assert!(version.starts_with("mosquitto version "), "{version:?}");
    assert!(r.targets[0]
        .version
        .as_deref()
        .is_some_and(|v| v.contains("fbbus")));

    assert_eq!(r.batches.len(), 3 * 2 * 2);
    for (i, b) in r.batches.iter().enumerate() {
        assert_eq!(
            b.target,
            ["A", "B"][i % 2],
            "batch {i} out of A B A B order"
        );
        // Each pair is the same burst and repeat, one per broker.
        let pair = &r.batches[i - i % 2];
        assert_eq!((b.x, b.repeat), (pair.x, pair.repeat));
        match b.target.as_str() {
            "A" => assert_eq!(b.delivered_fb, Some(b.sent)),
            _ => assert_eq!(b.delivered_fb, None, "no FB subscriber on Mosquitto"),
        }
    }
    assert_all_delivered(&r, &run);
    assert_summaries_add_up(&r);
    assert!(
        r.notes
            .iter()
            .any(|n| n.starts_with("B:") && n.contains("no FB subscriber")),
        "{:?}",
        r.notes
    );
    assert!(
        !r.notes.iter().any(|n| n.starts_with("A:")),
        "{:?}",
        r.notes
    );
    assert!(!r.ratios.is_empty());
    assert!(r
        .ratios
        .iter()
        .any(|x| x.figure == "delivered fraction" && x.a == 1.0 && x.b == 1.0 && x.ratio == 1.0));
    assert!(run.stdout.contains("fbbus") && run.stdout.contains("mosquitto"));
    assert!(run.stdout.contains("B/A"), "{}", run.context());
    assert_csv_and_jtl(&run, &r);
    assert_chart(&run, "stress.svg", &r, 3);
    // JMeter labels name the broker in compare mode.
    let jtl = run.file("batches.jtl");
    assert!(jtl.contains("stress burst 10 [mosquitto]"), "{jtl}");
}

// ---------------------------------------------------------------------------------------
// 3. known loss, through a lossy proxy

/// A TCP proxy in front of a broker that parses MQTT packets coming from the broker and
/// drops every `nth` PUBLISH of each connection; everything else passes untouched. It
/// counts its drops per connection, by the client id of the connection's CONNECT.
struct LossyProxy {
    addr: SocketAddr,
    drops: Arc<Mutex<HashMap<String, u64>>>,
    runtime: Option<tokio::runtime::Runtime>,
}

impl LossyProxy {
    fn start(upstream: SocketAddr, nth: u64) -> LossyProxy {
        let runtime = tokio::runtime::Builder::new_multi_thread()
            .worker_threads(1)
            .enable_all()
            .build()
            .unwrap();
        let listener = runtime
            .block_on(tokio::net::TcpListener::bind("127.0.0.1:0"))
            .unwrap();
        let addr = listener.local_addr().unwrap();
        let drops: Arc<Mutex<HashMap<String, u64>>> = Arc::default();
        let counts = drops.clone();
        runtime.spawn(async move {
            while let Ok((client, _)) = listener.accept().await {
                let counts = counts.clone();
                tokio::spawn(async move {
                    let _ = proxy(client, upstream, nth, counts).await;
                });
            }
        });
        LossyProxy {
            addr,
            drops,
            runtime: Some(runtime),
        }
    }

    fn url(&self) -> String {
        format!("mqtt://{}", self.addr)
    }

    fn drops(&self, client_id: &str) -> u64 {
        self.drops
            .lock()
            .unwrap()
            .get(client_id)
            .copied()
            .unwrap_or(0)
    }
}

impl Drop for LossyProxy {
    fn drop(&mut self) {
        if let Some(rt) = self.runtime.take() {
            rt.shutdown_background();
        }
    }
}

/// Reads one MQTT packet: its raw bytes (fixed header, remaining length, body) and where
/// the body starts.
async fn read_packet(
    r: &mut (impl tokio::io::AsyncRead + Unpin),
) -> std::io::Result<(Vec<u8>, usize)> {
    use tokio::io::AsyncReadExt;
    let mut raw = vec![r.read_u8().await?];
    let mut len = 0usize;
    for shift in (0..28).step_by(7) {
        let b = r.read_u8().await?;
        raw.push(b);
        len |= ((b & 0x7f) as usize) << shift;
        if b & 0x80 == 0 {
            let body = raw.len();
            raw.resize(body + len, 0);
            r.read_exact(&mut raw[body..]).await?;
            return Ok((raw, body));
        }
    }
    Err(std::io::Error::other("bad remaining length"))
}

/// The client id of a CONNECT body (MQTT 3.1.1 or 5).
fn connect_client_id(body: &[u8]) -> Option<String> {
    let name_len = u16::from_be_bytes([*body.first()?, *body.get(1)?]) as usize;
    let level = *body.get(2 + name_len)?;
    // Protocol level, connect flags, keep-alive.
    let mut at = 2 + name_len + 4;
    if level == 5 {
        let mut len = 0usize;
        for shift in (0..28).step_by(7) {
            let b = *body.get(at)?;
            at += 1;
            len |= ((b & 0x7f) as usize) << shift;
            if b & 0x80 == 0 {
                break;
            }
        }
        at += len;
    }
    let id_len = u16::from_be_bytes([*body.get(at)?, *body.get(at + 1)?]) as usize;
    String::from_utf8(body.get(at + 2..at + 2 + id_len)?.to_vec()).ok()
}

async fn proxy(
    client: tokio::net::TcpStream,
    upstream: SocketAddr,
    nth: u64,
    drops: Arc<Mutex<HashMap<String, u64>>>,
) -> std::io::Result<()> {
    use tokio::io::AsyncWriteExt;
    let broker = tokio::net::TcpStream::connect(upstream).await?;
    client.set_nodelay(true)?;
    broker.set_nodelay(true)?;
    let (mut client_rd, mut client_wr) = client.into_split();
    let (mut broker_rd, mut broker_wr) = broker.into_split();
    // The first packet from the client is its CONNECT: it names the connection.
    let (connect, body) = read_packet(&mut client_rd).await?;
    let id = connect_client_id(&connect[body..]).unwrap_or_default();
    broker_wr.write_all(&connect).await?;
    let upward = tokio::spawn(async move {
        let _ = tokio::io::copy(&mut client_rd, &mut broker_wr).await;
        let _ = broker_wr.shutdown().await;
    });
    let mut publishes = 0u64;
    let result = async {
        loop {
            let (packet, _) = read_packet(&mut broker_rd).await?;
            if packet[0] >> 4 == 3 {
                publishes += 1;
                if publishes.is_multiple_of(nth) {
                    *drops.lock().unwrap().entry(id.clone()).or_default() += 1;
                    continue;
                }
            }
            client_wr.write_all(&packet).await?;
        }
    }
    .await;
    upward.abort();
    result
}

#[test]
fn known_loss_is_reported_exactly() {
    let Some(mosquitto) = Mosquitto::start() else {
        return;
    };
    let proxy = LossyProxy::start(mosquitto.addr, 10);
    let run = loadtest(
        &[
            "--broker",
            &proxy.url(),
            "--no-fb",
            "stress",
            "--start",
            "10",
            "--max",
            "40",
            "--repeats",
            "1",
        ],
        &[],
    );
    let r = run.ok();
    assert_eq!(
        r.targets[0].name, "mosquitto",
        "identified through the proxy"
    );
    assert_eq!(xs(r.batches.iter()), vec![10, 20, 40]);
    for b in &r.batches {
        assert_eq!(b.sent, b.x as u64);
        assert_eq!(b.expected, b.sent);
        assert_eq!(b.lost(), b.sent / 10, "{b:?}\n{}", run.context());
        assert_eq!(b.delivery_rate(), 0.9, "{b:?}");
        assert_eq!(b.delivered_fb, None, "--no-fb");
        assert!(!b.ok, "{b:?}");
        let error = b.error.as_deref().unwrap_or_default();
        assert_eq!(error, format!("lost {} of {}", b.sent / 10, b.sent));
    }
    let total_lost: u64 = r.batches.iter().map(Batch::lost).sum();
    assert_eq!(total_lost, 1 + 2 + 4);
    // What the proxy dropped on the subscriber's connection is exactly what the harness
    // reports lost (other connections, such as the version probe, do not count).
    assert_eq!(proxy.drops("lt-a-sub-0"), total_lost);
    assert_summaries_add_up(&r);
    assert_eq!(
        r.summaries[0].expected - r.summaries[0].delivered,
        total_lost
    );

    let csv = run.table("batches.csv", &CSV_HEADER);
    for row in &csv {
        assert_eq!(col(row, "delivery_rate"), "0.9", "{row:?}");
        assert_eq!(col(row, "ok"), "false");
    }
    assert_csv_and_jtl(&run, &r);
    for row in run.table("batches.jtl", &JTL_HEADER) {
        assert_eq!(col(&row, "success"), "false");
        assert!(col(&row, "failureMessage").starts_with("lost "), "{row:?}");
    }
    // The delivery-rate chart shows the loss: a tagged series exists for the broker.
    assert_chart(&run, "delivery-rate.svg", &r, 3);

    // loss-search through the same proxy: the first burst already loses, so the search
    // ends at once with no lossless burst.
    let run = loadtest(
        &[
            "--broker",
            &proxy.url(),
            "--no-fb",
            "--prefix",
            "ls",
            "loss-search",
            "--max",
            "80",
            "--repeats",
            "1",
        ],
        &[],
    );
    let r = run.ok();
    assert_eq!(r.batches.len(), 1, "{:?}", r.batches);
    assert!(!r.batches[0].ok);
    assert_eq!(figure(&r, "largest_lossless_burst"), 0.0);
    assert!(!r.notes.iter().any(|n| n.contains("no loss up to")));
}

fn figure(r: &Report, name: &str) -> f64 {
    r.summaries[0]
        .figures
        .iter()
        .find(|f| f.name == name)
        .unwrap_or_else(|| panic!("no figure {name}: {:?}", r.summaries[0].figures))
        .value
}

#[test]
fn loss_search_on_clean_fbbus_reaches_max() {
    let fbbus = Fbbus::start();
    let run = loadtest(
        &[
            "--broker",
            &fbbus.url(),
            "loss-search",
            "--max",
            "80",
            "--repeats",
            "1",
        ],
        &[],
    );
    let r = run.ok();
    assert_eq!(r.scenario, "loss-search");
    // Doubling from 10: every probe lossless, up to --max.
    assert_eq!(xs(r.batches.iter()), vec![10, 20, 40, 80]);
    assert_all_delivered(&r, &run);
    assert_eq!(figure(&r, "largest_lossless_burst"), 80.0);
    assert!(
        r.notes.iter().any(|n| n.contains("no loss up to --max 80")),
        "{:?}",
        r.notes
    );
}

// ---------------------------------------------------------------------------------------
// 4. perf

#[test]
fn perf_on_fbbus_sweeps_batch_sizes() {
    let fbbus = Fbbus::start();
    let run = loadtest(
        &[
            "--broker",
            &fbbus.url(),
            "perf",
            "--max",
            "20",
            "--points",
            "3",
            "--repeats",
            "2",
        ],
        &[],
    );
    let r = run.ok();
    assert_eq!(r.scenario, "perf");
    let sizes = loadtest::scenario::study::Perf {
        max: 20,
        points: 3,
        repeats: 2,
    }
    .sizes();
    assert_eq!(sizes, vec![1, 10, 20]);
    assert_eq!(xs(r.batches.iter()), sizes);
    assert_eq!(r.batches.len(), 3 * 2);
    for b in &r.batches {
        assert_eq!(b.sent, b.x as u64);
        assert_eq!(b.delivered_fb, Some(b.sent));
    }
    assert_all_delivered(&r, &run);
    assert_summaries_add_up(&r);
    assert!(figure(&r, "mean_latency_at_max_batch") > 0.0);
    assert!(figure(&r, "throughput_at_max_batch") > 0.0);
    assert_csv_and_jtl(&run, &r);
    for chart in [
        "latency-vs-batch.svg",
        "throughput-vs-batch.svg",
        "processing-time.svg",
    ] {
        assert_chart(&run, chart, &r, 3);
    }
    assert!(
        !run.path("stress.svg").exists(),
        "perf draws no stress chart"
    );
}

// ---------------------------------------------------------------------------------------
// 5. flows

/// Runs `scenario --clients 3 --messages 50 --repeats 1` on fbbus closed-loop and open
/// loop at 500 and 1000 msg/s: `copies` subscribers receive each message.
fn flow(scenario: &str, publishers: u64, copies: u64) {
    let fbbus = Fbbus::start();
    let args = |extra: &[&'static str]| -> Vec<String> {
        let mut a: Vec<String> = [
            "--broker",
            &fbbus.url(),
            scenario,
            "--clients",
            "3",
            "--messages",
            "50",
            "--repeats",
            "1",
        ]
        .iter()
        .map(|s| s.to_string())
        .collect();
        a.extend(extra.iter().map(|s| s.to_string()));
        a
    };
    for (extra, labels) in [
        (&[][..], &["burst 50"][..]),
        (
            &["--rate", "500,1000"][..],
            &["rate 500/s", "rate 1000/s"][..],
        ),
    ] {
        let a = args(extra);
        let run = loadtest(&a.iter().map(String::as_str).collect::<Vec<_>>(), &[]);
        let r = run.ok();
        assert_eq!(r.scenario, scenario);
        let got: Vec<&str> = r.batches.iter().map(|b| b.label.as_str()).collect();
        assert_eq!(got, labels);
        for b in &r.batches {
            assert_eq!(b.sent, publishers * 50, "{b:?}");
            assert_eq!(b.expected, b.sent * copies, "{b:?}");
            assert_eq!(b.delivered_fb, None, "flows have no FB subscriber");
        }
        assert_all_delivered(&r, &run);
        assert_summaries_add_up(&r);
        assert_csv_and_jtl(&run, &r);
        if labels.len() > 1 {
            assert_eq!(xs(r.batches.iter()), vec![500, 1000]);
            assert_chart(&run, "throughput.svg", &r, 2);
        }
    }
}

#[test]
fn fan_in_closed_and_open_loop() {
    flow("fan-in", 3, 1);
}

#[test]
fn fan_out_closed_and_open_loop() {
    flow("fan-out", 1, 3);
}

#[test]
fn pairs_closed_and_open_loop() {
    flow("pairs", 3, 1);
}

#[test]
fn fan_out_mqtt5_qos2_on_both_brokers() {
    let Some(mosquitto) = Mosquitto::start() else {
        return;
    };
    let fbbus = Fbbus::start();
    let run = loadtest(
        &[
            "--broker",
            &fbbus.url(),
            "--compare",
            &mosquitto.url(),
            "--mqtt",
            "5",
            "--qos",
            "2",
            "fan-out",
            "--clients",
            "3",
            "--messages",
            "50",
            "--repeats",
            "1",
        ],
        &[],
    );
    let r = run.ok();
    assert_eq!(r.params["mqtt"], "V5");
    assert_eq!(r.params["qos"], 2);
    let names: Vec<&str> = r.targets.iter().map(|t| t.name.as_str()).collect();
    assert_eq!(names, vec!["fbbus", "mosquitto"]);
    let targets: Vec<&str> = r.batches.iter().map(|b| b.target.as_str()).collect();
    assert_eq!(targets, vec!["A", "B"]);
    for b in &r.batches {
        assert_eq!((b.sent, b.expected), (50, 150), "{b:?}");
    }
    assert_all_delivered(&r, &run);
    assert_summaries_add_up(&r);
    assert!(!r.ratios.is_empty());
}

// ---------------------------------------------------------------------------------------
// 6. idle

#[test]
fn idle_connections_on_fbbus_with_memory_per_connection() {
    let fbbus = Fbbus::start();
    let run = loadtest(
        &[
            "--broker",
            &fbbus.url(),
            "idle",
            "--connections",
            "50",
            "--hold-s",
            "1",
        ],
        &[],
    );
    let r = run.ok();
    assert_eq!(r.scenario, "idle");
    assert!(r.ceiling.is_none(), "no ceiling for a connection scenario");
    assert_eq!(r.batches.len(), 1);
    let b = &r.batches[0];
    assert_eq!((b.sent, b.expected, b.delivered), (50, 50, 50), "{b:?}");
    assert!(b.ok, "{b:?}");
    assert_eq!(b.latency.count, 50, "one connect latency per connection");
    // The broker runs on this machine: the harness found its process and memory.
    let per_connection = figure(&r, "rss_kib_per_idle_connection");
    assert!(per_connection.is_finite());
    assert!(figure(&r, "broker_rss_kib") > 0.0);
    assert!(
        !r.notes.iter().any(|n| n.contains("not measured")),
        "{:?}",
        r.notes
    );
    assert_csv_and_jtl(&run, &r);
}

// ---------------------------------------------------------------------------------------
// 7. storm with authentication

const STORM_PASSWORD: &str = "St0rm-pw-x7Q";
const WRONG_PASSWORD: &str = "Wr0ng-pw-k3Z";

#[test]
fn storm_with_authentication_and_refusal() {
    let fbbus = common::fbbus_with(
        "test",
        "[auth]\npassword_file = \"passwd\"\n",
        "allow_anonymous = false\n",
        "",
        |dir| {
            for i in 0..5 {
                common::add_user(&dir.join("passwd"), &format!("dev-{i}"), STORM_PASSWORD);
            }
        },
    );
    let args = [
        "--broker",
        &fbbus.url(),
        "--username",
        "dev-{i}",
        "storm",
        "--devices",
        "5",
    ];
    let run = loadtest(&args, &[("MQTT_PASSWORD", STORM_PASSWORD)]);
    let r = run.ok();
    assert_eq!(r.scenario, "storm");
    let labels: Vec<&str> = r.batches.iter().map(|b| b.label.as_str()).collect();
    assert_eq!(labels, vec!["connect storm 5", "reconnect storm 5"]);
    for b in &r.batches {
        assert_eq!((b.sent, b.delivered), (5, 5), "{b:?}");
        assert!(b.ok, "{b:?}");
    }
    assert!(figure(&r, "connect_storm_s") >= 0.0);
    assert!(figure(&r, "reconnect_storm_s") >= 0.0);
    // Both waves have a row in the terminal table.
    assert!(
        run.stdout.contains("connect storm 5") && run.stdout.contains("reconnect storm 5"),
        "{}",
        run.context()
    );
    assert_no_secret(&run, STORM_PASSWORD);

    // The wrong password: every connection refused, the batches say so and what to check.
    let run = loadtest(&args, &[("MQTT_PASSWORD", WRONG_PASSWORD)]);
    let r = run.report();
    assert_eq!(r.batches.len(), 2);
    for b in &r.batches {
        assert_eq!((b.sent, b.delivered), (5, 0), "{b:?}");
        assert!(!b.ok);
        let error = b.error.as_deref().unwrap_or_default();
        assert!(error.contains("refused"), "{error}");
        assert!(error.contains("check --username"), "{error}");
    }
    for row in run.table("batches.jtl", &JTL_HEADER) {
        assert_eq!(col(&row, "success"), "false");
    }
    assert_no_secret(&run, WRONG_PASSWORD);
}

/// The password is nowhere in what the run printed or wrote.
fn assert_no_secret(run: &Run, password: &str) {
    assert!(!run.stdout.contains(password), "stdout leaks the password");
    assert!(!run.stderr.contains(password), "stderr leaks the password");
    let mut files = 0;
    for entry in std::fs::read_dir(run.out.path()).unwrap() {
        let path = entry.unwrap().path();
        let text = std::fs::read_to_string(&path).unwrap();
        assert!(
            !text.contains(password),
            "{} leaks the password",
            path.display()
        );
        files += 1;
    }
    assert!(files >= 3, "report.json, batches.csv, batches.jtl at least");
}

// ---------------------------------------------------------------------------------------
// 8. bridge

#[test]
fn bridge_carries_every_message_from_line_a_to_line_b() {
    let zenoh_a = format!("tcp/127.0.0.1:{}", common::free_port());
    let zenoh_b = format!("tcp/127.0.0.1:{}", common::free_port());
    let line_a = common::fbbus_with(
        "la",
        "",
        "",
        &format!("[bridge]\nlisten = [\"{zenoh_a}\"]\nconnect = []\nlease_ms = 1000\n"),
        |_| {},
    );
    let line_b = common::fbbus_with(
        "lb",
        "",
        "",
        &format!(
            "[bridge]\nlisten = [\"{zenoh_b}\"]\nconnect = [\"{zenoh_a}\"]\nlease_ms = 1000\n"
        ),
        |_| {},
    );
    // The bridge is subscription-driven (docs/device-contract.md section 7): line A exports
    // only once line B's interest reached it, some time after the SUBACK. The harness
    // waits for a probe to cross before its first batch (rig.rs `across_the_bridge`);
    // without that, the batch was lost in about half the runs.

    let run = loadtest(
        &[
            "--broker",
            &line_a.url(),
            "bridge",
            "--subscribe-at",
            &line_b.url(),
            "--messages",
            "100",
            "--repeats",
            "1",
        ],
        &[],
    );
    let r = run.ok();
    assert_eq!(r.scenario, "bridge");
    assert_eq!(r.params["subscribe_at"], line_b.url());
    assert_eq!(r.batches.len(), 1);
    let b = &r.batches[0];
    assert_eq!((b.sent, b.expected), (100, 100));
    assert_eq!(
        b.delivered,
        100,
        "{b:?}\n{}\nline A:\n{}\nline B:\n{}",
        run.context(),
        line_a.log_text(),
        line_b.log_text()
    );
    assert!(b.ok && b.duplicates == 0, "{b:?}");
    // The messages crossed the bridge: line A exported them (and the probes).
    assert!(line_a.metric("fbbus_bridge_messages_total{direction=\"export\"}") >= 100.0);
}

// ---------------------------------------------------------------------------------------
// 9. time limit

#[test]
fn time_limit_stops_the_run_early() {
    // Through the lossy proxy every burst loses a message, so every batch waits out the
    // quiet time (300 ms): 50 batches cannot fit in the 1 s limit on any machine, and the
    // run must stop early (fbbus alone could finish them in time on a fast one).
    let fbbus = Fbbus::start();
    let proxy = LossyProxy::start(fbbus.mqtt, 10);
    let run = loadtest(
        &[
            "--broker",
            &proxy.url(),
            "--no-fb",
            "--time-limit-s",
            "1",
            "stress",
            "--max",
            "5120",
            "--repeats",
            "5",
        ],
        &[],
    );
    let r = run.ok();
    // 10 burst sizes x 5 repeats planned; the limit stopped it before the end.
    assert!(!r.batches.is_empty());
    assert!(r.batches.len() < 50, "{} batches", r.batches.len());
    assert!(
        r.notes.iter().any(|n| n.contains("time limit")),
        "{:?}",
        r.notes
    );
    // It stops between batches: every batch recorded ran to its end (exactly the
    // proxy's loss, not cut short).
    for b in &r.batches {
        assert_eq!(b.lost(), b.sent / 10, "{b:?}");
    }
    assert_summaries_add_up(&r);
    assert_csv_and_jtl(&run, &r);
}

// ---------------------------------------------------------------------------------------
// 10. bad input

#[test]
fn bad_targets_fail_with_advice() {
    // An unknown scheme: refused before anything runs.
    let run = loadtest(&["--broker", "http://127.0.0.1:1883", "stress"], &[]);
    assert!(!run.success, "{}", run.context());
    assert!(
        run.stderr.contains("unknown scheme")
            && run
                .stderr
                .contains("expected mqtt://host:port or mqtts://host:port"),
        "{}",
        run.context()
    );
    assert!(!run.path("report.json").exists());

    // Nothing listening: says which address and what to check.
    let port = common::free_port();
    let url = format!("mqtt://127.0.0.1:{port}");
    let run = loadtest(&["--broker", &url, "stress", "--max", "10"], &[]);
    assert!(!run.success, "{}", run.context());
    assert!(
        run.stderr.contains("cannot connect")
            && run.stderr.contains(&url)
            && run.stderr.contains("is the broker running there?"),
        "{}",
        run.context()
    );
    assert!(!run.path("report.json").exists());

    // The same for connection scenarios: nothing to measure without a broker.
    let run = loadtest(&["--broker", &url, "storm", "--devices", "3"], &[]);
    assert!(!run.success, "{}", run.context());
    assert!(
        run.stderr.contains("cannot connect") && run.stderr.contains(&url),
        "{}",
        run.context()
    );

    // A broker on another machine needs --allow-remote.
    let run = loadtest(&["--broker", "mqtt://192.0.2.1:1883", "stress"], &[]);
    assert!(!run.success, "{}", run.context());
    assert!(run.stderr.contains("--allow-remote"), "{}", run.context());
}

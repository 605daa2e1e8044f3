//! What `compare` prints: the header (machine, versions, parameters), one table per
//! scenario (a row per broker and round) and the ratio line, whose figures are each
//! broker's median over the rounds; at the end the summary table (issue 34): a row per
//! scenario, a column per broker and a ratio column per peer.

use std::path::Path;

use loadtest::broker_process::spawn::{self, Kind};

use super::scenarios::{Outcome, Params, Scenario};
use super::{Contender, Transcript, Transport, KEEP_ALIVE_SECS};

/// One run of a scenario: the broker, the round (from 1) and what it measured.
pub type Row<'a> = (&'a Contender, u32, Outcome);

#[allow(clippy::too_many_arguments)]
pub fn header(
    t: &mut Transcript,
    contenders: &[Contender],
    mosquitto: Option<&Path>,
    scenarios: &[Scenario],
    p: &Params,
    quick: bool,
    nodelay_off_too: bool,
    rounds: u32,
) {
    t.line(format!(
        "fbbus-loadtest compare {}",
        env!("CARGO_PKG_VERSION")
    ));
    t.line(format!(
        "machine:   {} cores, {}, {} RAM",
        std::thread::available_parallelism()
            .map(|n| n.get())
            .unwrap_or(0),
        read_first("/proc/cpuinfo", Some("model name")),
        read_first("/proc/meminfo", Some("MemTotal")),
    ));
    t.line(format!("kernel:    {}", read_first("/proc/version", None)));
    for c in contenders {
        match c.kind {
            Kind::Fbbus => t.line(format!(
                "{:<10} {} ({}; config defaults, [log] level = \"warn\", max_connections 10100)",
                format!("{}:", c.label),
                spawn::fbbus_version(&c.program),
                c.program.display(),
            )),
            Kind::Mosquitto => match mosquitto {
                Some(m) => t.line(format!(
                    "mosquitto: {} ({}; set_tcp_nodelay true, max_queued_messages 100000, max_inflight_messages 512, persistence false{})",
                    spawn::mosquitto_version(m),
                    m.display(),
                    if nodelay_off_too {
                        "; fanin and latency also with the shipped set_tcp_nodelay false"
                    } else {
                        ""
                    }
                )),
                None => t.line("mosquitto: not installed (apt-get install -y mosquitto)"),
            },
            Kind::Rumqttd => t.line(format!(
                "rumqttd:   {} raw (crates.io library in a child process; rumqttd.toml example values: router max_connections 10010, \
                 max_outgoing_packet_count 200, segments 100 MiB x 10; max_inflight_count 100, next_connection_delay_ms 1)",
                rumqttd_version()
            )),
            Kind::FlashMq => t.line(format!(
                "flashmq:   {} ({}; thread_count {}, listener tcp_nodelay true, no storage_dir, \
                 max_qos_msg_pending_per_client 65535, max_qos_bytes_pending_per_client 100 MiB, log_level warning{})",
                spawn::flashmq_version(&c.program),
                c.program.display(),
                std::thread::available_parallelism().map_or(1, |n| n.get()),
                c.peer_lines.iter().map(|l| format!(", {l}")).collect::<String>(),
            )),
            Kind::MosquittoDefault => {}
        }
    }
    t.line(format!(
        "clients:   bursts on raw MQTT 3.1.1 sockets, connections through rumqttc; one tokio multi-thread runtime \
         in this process, nodelay, keep-alive {KEEP_ALIVE_SECS} s, 127.0.0.1 only"
    ));
    t.line(format!(
        "params:    {}{}; scenarios {}; {rounds} round(s) per broker, alternating; deadline {} s per scenario and broker",
        if quick { "--quick" } else { "full" },
        if quick {
            " (smoke-test sizes, not a measurement)"
        } else {
            ""
        },
        scenarios
            .iter()
            .map(|s| s.name())
            .collect::<Vec<_>>()
            .join(","),
        p.deadline.as_secs()
    ));
}

/// The scenario's table: one row per broker and round, in the order they ran.
pub fn rows(
    t: &mut Transcript,
    scenario: Scenario,
    rows: &[(&Contender, u32, Outcome)],
    rounds: u32,
) {
    let mut headers = vec!["broker"];
    headers.extend_from_slice(scenario.columns());
    let mut table: Vec<Vec<String>> = rows
        .iter()
        .map(|(c, round, o)| {
            let name = if rounds > 1 {
                format!("{} #{round}", c.label)
            } else {
                c.label.clone()
            };
            let mut r = vec![name];
            r.extend(o.cells.iter().cloned());
            r
        })
        .collect();
    let widths = column_widths(headers.iter().map(|h| h.chars().count()), &table);
    let line = |cells: &[String]| aligned(cells, &widths);
    let header: Vec<String> = headers.iter().map(|h| h.to_string()).collect();
    t.line(format!("   {}", line(&header)));
    for (r, (_, _, o)) in table.iter_mut().zip(rows) {
        let mut text = line(r);
        if let Some(note) = &o.note {
            text.push_str(&format!("  [{note}]"));
        }
        t.line(format!("   {text}"));
    }
}

/// One broker's key figures over its rounds: the median of each, from the rounds that
/// did not time out.
struct Median {
    keys: Vec<Option<f64>>,
    /// The median of the messages lost, where the scenario counts them.
    lost: Option<f64>,
    /// Every round timed out.
    timed_out: bool,
}

fn median_of(rows: &[(&Contender, u32, Outcome)], label: &str) -> Option<Median> {
    let own: Vec<&Outcome> = rows
        .iter()
        .filter(|(c, _, _)| c.label == label)
        .map(|(_, _, o)| o)
        .collect();
    if own.is_empty() {
        return None;
    }
    let width = own.iter().map(|o| o.keys.len()).max().unwrap_or(0);
    let median = |pick: &dyn Fn(&Outcome) -> Option<f64>| {
        let mut v: Vec<f64> = own
            .iter()
            .filter(|o| !o.timed_out)
            .filter_map(|o| pick(o))
            .collect();
        v.sort_by(f64::total_cmp);
        match v.len() {
            0 => None,
            n if n % 2 == 1 => Some(v[n / 2]),
            n => Some((v[n / 2 - 1] + v[n / 2]) / 2.0),
        }
    };
    let keys = (0..width)
        .map(|i| median(&|o| o.keys.get(i).copied().flatten()))
        .collect();
    Some(Median {
        keys,
        lost: median(&|o| o.lost.map(|l| l as f64)),
        timed_out: own.iter().all(|o| o.timed_out),
    })
}

/// The brokers of a scenario's rows, in the order they ran, each once.
fn contenders_of<'a>(rows: &[(&'a Contender, u32, Outcome)]) -> Vec<(&'a str, Kind, Transport)> {
    let mut labels: Vec<(&str, Kind, Transport)> = Vec::new();
    for (c, _, _) in rows {
        if !labels.iter().any(|(l, _, _)| *l == c.label) {
            labels.push((&c.label, c.kind, c.transport));
        }
    }
    labels
}

/// What is divided by what (`a/b` = a's figure / b's): every fbbus by every peer
/// (Mosquitto, rumqttd, FlashMQ) on the same transport, later fbbus builds by the first,
/// and a WebSocket row by the same broker through the TCP relay (else direct TCP).
fn ratio_pairs<'a>(labels: &[(&'a str, Kind, Transport)]) -> Vec<(&'a str, &'a str)> {
    let mut pairs: Vec<(&str, &str)> = Vec::new();
    for &transport in [Transport::Tcp, Transport::TcpRelay, Transport::WebSocket].iter() {
        let fbbus: Vec<&str> = labels
            .iter()
            .filter(|(_, k, t)| *k == Kind::Fbbus && *t == transport)
            .map(|(l, _, _)| *l)
            .collect();
        for f in &fbbus {
            for (other, kind, t) in labels {
                if matches!(kind, Kind::Mosquitto | Kind::Rumqttd | Kind::FlashMq)
                    && *t == transport
                {
                    pairs.push((f, other));
                }
            }
        }
        if let Some((first, later)) = fbbus.split_first() {
            for f in later {
                pairs.push((f, first));
            }
        }
    }
    for (label, _, transport) in labels {
        if *transport != Transport::WebSocket {
            continue;
        }
        let base = label.trim_end_matches("/ws");
        let over = |t: &str| format!("{base}/{t}");
        let reference = labels
            .iter()
            .find(|(l, _, _)| *l == over("tcp-relay"))
            .or_else(|| labels.iter().find(|(l, _, _)| *l == over("tcp")));
        if let Some((reference, _, _)) = reference {
            pairs.push((label, reference));
        }
    }
    pairs
}

/// `a`'s key figures divided by `b`'s, `1.23x` each, joined by `/`; `n/a` where either
/// is missing, zero or timed out.
fn ratios(ma: &Median, mb: &Median) -> String {
    let ratios: Vec<String> = ma
        .keys
        .iter()
        .enumerate()
        .map(|(i, ka)| match (ka, mb.keys.get(i).copied().flatten()) {
            (Some(x), Some(y)) if !ma.timed_out && !mb.timed_out && y > 0.0 => {
                format!("{:.2}x", x / y)
            }
            _ => "n/a".into(),
        })
        .collect();
    if ratios.is_empty() {
        "n/a".to_string()
    } else {
        ratios.join("/")
    }
}

/// The scenario's key figures per broker and the ratios: each fbbus to each peer
/// (Mosquitto, rumqttd, FlashMQ), and each later fbbus to the first (`new/old`).
pub fn ratio_line(
    scenario: Scenario,
    p: &Params,
    rows: &[(&Contender, u32, Outcome)],
    rounds: u32,
) -> String {
    let mut line = scenario.title(p);
    if rounds > 1 {
        line.push_str(&format!(" [median of {rounds}]"));
    }
    let labels = contenders_of(rows);
    for (label, _, _) in &labels {
        let Some(m) = median_of(rows, label) else {
            continue;
        };
        let value = if m.timed_out {
            "timeout".to_string()
        } else if m.keys.iter().all(|k| k.is_none()) {
            "failed".to_string()
        } else {
            scenario.format_keys(&m.keys)
        };
        line.push_str(&format!("   {label} {value}"));
    }
    let pairs = ratio_pairs(&labels);
    for (a, b) in &pairs {
        let (Some(ma), Some(mb)) = (median_of(rows, a), median_of(rows, b)) else {
            continue;
        };
        line.push_str(&format!("   {a}/{b} {}", ratios(&ma, &mb)));
    }
    if !pairs.is_empty() {
        line.push_str(if scenario.higher_is_better() {
            "   (higher is better)"
        } else {
            "   (lower is better)"
        });
    }
    line
}

/// The summary table at the end of a run: a row per scenario with its key figures (each
/// broker's median over the rounds; after a throughput or latency figure the messages
/// lost, as a broker that drops part of a burst can show any rate), a column per broker
/// and a ratio column per pair of [`ratio_pairs`] (`fbbus/mosquitto` = fbbus's figure /
/// Mosquitto's), and which way is better. Mosquitto with the shipped `set_tcp_nodelay
/// false` (fanin and latency only) stays in the scenarios' own tables.
pub fn summary_table(t: &mut Transcript, runs: &[(Scenario, Vec<Row>)], rounds: u32) {
    let mut labels: Vec<(&str, Kind, Transport)> = Vec::new();
    for (_, rows) in runs {
        for l in contenders_of(rows) {
            if l.1 != Kind::MosquittoDefault && !labels.iter().any(|(x, _, _)| *x == l.0) {
                labels.push(l);
            }
        }
    }
    let pairs = ratio_pairs(&labels);
    let mut headers = vec!["scenario".to_string()];
    headers.extend(labels.iter().map(|(l, _, _)| l.to_string()));
    headers.extend(pairs.iter().map(|(a, b)| format!("{a}/{b}")));
    headers.push("better".into());
    let mut table: Vec<Vec<String>> = Vec::new();
    for (scenario, rows) in runs {
        let mut row = vec![scenario.summary_label().to_string()];
        for (label, _, _) in &labels {
            row.push(match median_of(rows, label) {
                None => "-".into(),
                Some(m) if m.timed_out => "timeout".into(),
                Some(m) if m.keys.iter().all(|k| k.is_none()) => "failed".into(),
                Some(m) => {
                    let figure = scenario.summary_figure(&m.keys);
                    match m.lost {
                        Some(lost) => format!("{figure} (lost {lost:.0})"),
                        None => figure,
                    }
                }
            });
        }
        for (a, b) in &pairs {
            row.push(match (median_of(rows, a), median_of(rows, b)) {
                (Some(ma), Some(mb)) => ratios(&ma, &mb),
                _ => "-".into(),
            });
        }
        row.push(
            if scenario.higher_is_better() {
                "higher"
            } else {
                "lower"
            }
            .into(),
        );
        table.push(row);
    }
    let widths = column_widths(headers.iter().map(|h| h.chars().count()), &table);
    t.line(format!(
        "== summary table ({}; ratio = the first broker's figure / the second's) ==",
        if rounds > 1 {
            format!("median of {rounds} rounds")
        } else {
            "one round".to_string()
        }
    ));
    t.line(format!("   {}", aligned(&headers, &widths)));
    for row in &table {
        t.line(format!("   {}", aligned(row, &widths)));
    }
}

/// Upstream rumqttd's version as resolved in the workspace's Cargo.lock.
fn rumqttd_version() -> &'static str {
    const LOCK: &str = include_str!("../../../Cargo.lock");
    LOCK.split("[[package]]")
        .find(|p| p.contains("\nname = \"rumqttd\"\n") && p.contains("source = \"registry+"))
        .and_then(|p| p.lines().find_map(|l| l.strip_prefix("version = ")))
        .map(|v| v.trim_matches('"'))
        .unwrap_or("0.20")
}

fn read_first(path: &str, key: Option<&str>) -> String {
    let text = std::fs::read_to_string(path).unwrap_or_default();
    let line = match key {
        Some(key) => text
            .lines()
            .find(|l| l.starts_with(key))
            .and_then(|l| l.split_once(':'))
            .map(|(_, v)| v.trim().to_string()),
        None => text.lines().next().map(|l| l.trim().to_string()),
    };
    line.unwrap_or_else(|| "unknown".into())
}

/// The width of each column: the widest of its header and its cells, in characters.
pub(super) fn column_widths(
    headers: impl Iterator<Item = usize>,
    rows: &[Vec<String>],
) -> Vec<usize> {
    let mut widths: Vec<usize> = headers.collect();
    for r in rows {
        for (w, c) in widths.iter_mut().zip(r) {
            *w = (*w).max(c.chars().count());
        }
    }
    widths
}

/// One table row, each cell left-aligned to its column's width, two spaces between.
pub(super) fn aligned(cells: &[String], widths: &[usize]) -> String {
    cells
        .iter()
        .zip(widths)
        .map(|(c, w)| format!("{c:<w$}"))
        .collect::<Vec<_>>()
        .join("  ")
        .trim_end()
        .to_string()
}

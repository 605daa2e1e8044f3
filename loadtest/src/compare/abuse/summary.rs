//! What each phase cost, read from the broker (its CPU and memory, its counters) and
//! the probe, as a table and against the goals.

use std::net::SocketAddr;
use std::sync::atomic::Ordering;
use std::time::{Duration, Instant};

use loadtest::broker_process::{self};
use loadtest::scrape;

use super::{AbuseParams, Counters, Phase, Row, Sampler, SAMPLE_EVERY};
use crate::compare::table::{aligned, column_widths};
use crate::compare::Transcript;

/// Peak VmRSS and open descriptors of `pid`, every [`SAMPLE_EVERY`] (on a thread of its
/// own, until told to stop).
pub(super) fn sample(pid: u32, s: &Sampler) {
    while !s.stop.load(Ordering::Relaxed) {
        if let Some(kib) = broker_process::rss_kib(pid) {
            s.rss_kib.fetch_max(kib, Ordering::Relaxed);
        }
        if let Some(fds) = broker_process::open_fds(pid) {
            s.fds.fetch_max(fds, Ordering::Relaxed);
        }
        std::thread::sleep(SAMPLE_EVERY);
    }
}

/// The refusal counters and the size of `/metrics`; None when the endpoint did not
/// answer within 8 s (the slow-header phase may hold every admin slot until the
/// broker's header timeout).
pub(super) async fn counters(admin: SocketAddr) -> Option<Counters> {
    let until = Instant::now() + Duration::from_secs(8);
    loop {
        if let Ok(text) =
            scrape::get(&format!("http://{admin}/metrics"), Duration::from_secs(5)).await
        {
            return Some(Counters {
                limit_refusals: sum_series(&text, "fbbus_limit_refusals_total"),
                connects_refused: sum_series(&text, "fbbus_connects_refused_total"),
                admin_refused: sum_series(&text, "fbbus_admin_connections_refused_total"),
                bytes: text.len(),
            });
        }
        if Instant::now() > until {
            return None;
        }
        tokio::time::sleep(Duration::from_millis(200)).await;
    }
}

/// The sum of every series of metric `name`, over its labels.
pub(super) fn sum_series(text: &str, name: &str) -> f64 {
    text.lines()
        .filter(|l| !l.starts_with('#'))
        .filter_map(|l| {
            let rest = l.strip_prefix(name)?;
            if !(rest.starts_with('{') || rest.starts_with(' ')) {
                return None;
            }
            l.rsplit_once(' ')?.1.trim().parse::<f64>().ok()
        })
        .sum()
}

pub(super) fn delta(
    before: Option<Counters>,
    after: Option<Counters>,
    f: impl Fn(&Counters) -> f64,
) -> Option<f64> {
    Some(f(&after?) - f(&before?))
}

// ---------------------------------------------------------------------------------------
// The report
// ---------------------------------------------------------------------------------------
pub(super) fn idle_p99(rows: &[Row]) -> Option<f64> {
    rows.iter()
        .find(|r| r.phase == Phase::Idle)
        .and_then(|r| r.p99_ms)
        .filter(|v| *v > 0.0)
}

pub(super) fn table(t: &mut Transcript, rows: &[Row]) {
    let headers = [
        "phase",
        "ops",
        "refused (limits/connects/admin)",
        "p50 ms",
        "p99 ms",
        "max ms",
        "p99/idle",
        "lost",
        "peak RSS MB",
        "peak fds",
        "/metrics KB",
    ];
    let idle = idle_p99(rows);
    let num =
        |v: Option<f64>, digits: usize| v.map_or("-".to_string(), |v| format!("{v:.digits$}"));
    let cells: Vec<Vec<String>> = rows
        .iter()
        .map(|r| {
            vec![
                r.phase.name().to_string(),
                match &r.flood {
                    Ok(f) => f.ops.clone(),
                    Err(_) => "FAILED".into(),
                },
                format!(
                    "{}/{}/{}",
                    num(r.limit_refusals, 0),
                    num(r.connects_refused, 0),
                    num(r.admin_refused, 0)
                ),
                num(r.p50_ms, 2),
                num(r.p99_ms, 2),
                num(r.max_ms, 2),
                match (r.p99_ms, idle) {
                    (Some(p), Some(i)) => format!("{:.2}x", p / i),
                    _ => "-".into(),
                },
                format!("{}/{}", r.lost, r.sent),
                format!("{:.1}", r.peak_rss_kib as f64 / 1024.0),
                r.peak_fds.to_string(),
                num(r.metrics_kb, 1),
            ]
        })
        .collect();
    let widths = column_widths(headers.iter().map(|h| h.chars().count()), &cells);
    t.line("");
    t.line("== phases ==");
    let header: Vec<String> = headers.iter().map(|h| h.to_string()).collect();
    t.line(format!("   {}", aligned(&header, &widths)));
    for c in &cells {
        t.line(format!("   {}", aligned(c, &widths)));
    }
    let mut notes = Vec::new();
    for r in rows {
        let mut parts = Vec::new();
        match &r.flood {
            Ok(f) => parts.extend(f.note.clone()),
            Err(e) => parts.push(format!("FAILED: {e}")),
        }
        if r.reconnects > 0 {
            parts.push(format!("probe reconnected {} time(s)", r.reconnects));
        }
        if !parts.is_empty() {
            notes.push(format!("   {}: {}", r.phase.name(), parts.join("; ")));
        }
    }
    if !notes.is_empty() {
        t.line("   notes:");
        for n in notes {
            t.line(n);
        }
    }
}

pub(super) fn goals(t: &mut Transcript, rows: &[Row], p: &AbuseParams) {
    t.line("");
    t.line("== goals (issue 21) ==");
    let idle = idle_p99(rows);
    for (phase, what) in [
        (Phase::AdminPoll, "during admin polling"),
        (Phase::Redeclare, "during re-declaration"),
    ] {
        let p99 = rows
            .iter()
            .find(|r| r.phase == phase)
            .and_then(|r| r.p99_ms);
        let line = match (p99, idle) {
            (Some(v), Some(i)) => {
                let ratio = v / i;
                format!(
                    "probe p99 within 2x idle {what}: {ratio:.2}x ({v:.2} ms vs {i:.2} ms) {}",
                    if ratio <= 2.0 { "MET" } else { "NOT MET" }
                )
            }
            _ => format!("probe p99 within 2x idle {what}: no figure NOT MET"),
        };
        t.line(line);
    }
    let peak = rows.iter().map(|r| r.peak_rss_kib).max().unwrap_or(0);
    let peak_mb = peak as f64 / 1024.0;
    t.line(format!(
        "resident memory within --max-rss-mb {} MB (the configured limit compared against): peak {:.1} MB {}",
        p.max_rss_mb,
        peak_mb,
        if peak > 0 && peak_mb <= p.max_rss_mb as f64 {
            "MET"
        } else {
            "NOT MET"
        }
    ));
}

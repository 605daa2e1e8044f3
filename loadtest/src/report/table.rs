//! The terminal summary: enough to read the run without opening a file.
//!
//! Three blocks, each a plain left/right-aligned text table (no colours, no box drawing,
//! so it pastes into issues and logs as is):
//! 1. provenance: tool, command, machine, each target with its version, the harness's
//!    ceiling, and the notes the reader must know;
//! 2. one row per x and target (repeats aggregated as `aggregate::Point` says), targets
//!    side by side per x so a comparison reads row against row;
//! 3. the per-target summaries and scenario figures, then in compare mode the B/A ratios.

use std::fmt::Write as _;

use super::aggregate::{display_name, points, Point};
use super::svg::compact;
use crate::model::{Latency, Report, Summary};

/// Renders `report` as the terminal summary (ends with a newline).
pub fn table(report: &Report) -> String {
    let mut out = String::new();
    header(report, &mut out);
    out.push('\n');
    batches(report, &mut out);
    out.push('\n');
    summaries(report, &mut out);
    if !report.ratios.is_empty() {
        out.push('\n');
        ratios(report, &mut out);
    }
    out
}

fn header(r: &Report, out: &mut String) {
    let m = &r.machine;
    let _ = writeln!(
        out,
        "{}  scenario {}  started {}",
        r.tool, r.scenario, r.started
    );
    let _ = writeln!(out, "command: {}", r.command);
    let _ = writeln!(
        out,
        "machine: {} ({}, {}, {} cpus, {} MiB)",
        m.hostname, m.os, m.cpu_model, m.cpus, m.memory_mib
    );
    for t in &r.targets {
        let version = t.version.as_deref().unwrap_or("version unknown");
        let _ = writeln!(
            out,
            "target {}: {} {} at {}",
            t.label,
            display_name(r, t),
            version,
            t.address
        );
    }
    if let Some(c) = &r.ceiling {
        let _ = writeln!(
            out,
            "harness ceiling (trivial sink{}): {} msg, {} msg/s, latency p50 {} p99 {} ms",
            if c.label.is_empty() {
                String::new()
            } else {
                format!(", {}", c.label)
            },
            c.messages,
            compact(c.throughput),
            ms(c.latency.p50_us as f64),
            ms(c.latency.p99_us as f64)
        );
    }
    for note in &r.notes {
        let _ = writeln!(out, "note: {note}");
    }
    for failure in &r.failures {
        let _ = writeln!(out, "FAILED: {failure}");
    }
}

fn batches(r: &Report, out: &mut String) {
    let per_target: Vec<(String, Vec<Point>)> = r
        .targets
        .iter()
        .map(|t| (display_name(r, t), points(r, &t.label)))
        .collect();
    let mut xs: Vec<f64> = per_target
        .iter()
        .flat_map(|(_, pts)| pts.iter().map(|p| p.x))
        .collect();
    xs.sort_by(f64::total_cmp);
    xs.dedup();

    let mut rows = vec![[
        "batch",
        "target",
        "reps",
        "failed",
        "sent",
        "delivered",
        "lost",
        "deliv%",
        "msg/s",
        "p50 ms",
        "p99 ms",
        "max ms",
    ]
    .map(String::from)
    .to_vec()];
    for x in xs {
        // Every point at this x: a storm's connect and reconnect waves share one x.
        for (name, pts) in &per_target {
            for p in pts.iter().filter(|p| p.x == x) {
                rows.push(vec![
                    p.label.clone(),
                    name.clone(),
                    p.repeats.to_string(),
                    p.failed.to_string(),
                    count(p.sent),
                    count(p.delivered),
                    count(p.lost),
                    format!("{:.1}", p.delivery_pct),
                    compact(p.throughput),
                    ms(p.lat_p50_us),
                    ms(p.lat_p99_us),
                    ms(p.lat_max_us as f64),
                ]);
            }
        }
    }
    if rows.len() == 1 {
        out.push_str("no batches were measured\n");
        return;
    }
    align(&rows, 2, out);
}

fn summaries(r: &Report, out: &mut String) {
    let mut rows = vec![[
        "summary",
        "batches",
        "sent",
        "expected",
        "delivered",
        "fb",
        "dups",
        "msg/s (median)",
        "mean ms",
        "p50 ms",
        "p99 ms",
        "p99.9 ms",
        "max ms",
    ]
    .map(String::from)
    .to_vec()];
    let mut figures = Vec::new();
    for s in &r.summaries {
        let l: &Latency = &s.latency;
        rows.push(vec![
            summary_name(r, s),
            s.batches.to_string(),
            s.sent.to_string(),
            s.expected.to_string(),
            s.delivered.to_string(),
            s.delivered_fb.map(|d| d.to_string()).unwrap_or("-".into()),
            s.duplicates.to_string(),
            compact(s.throughput),
            ms(l.mean_us),
            ms(l.p50_us as f64),
            ms(l.p99_us as f64),
            ms(l.p999_us as f64),
            ms(l.max_us as f64),
        ]);
        for f in &s.figures {
            figures.push(format!(
                "{}: {} = {} {}",
                summary_name(r, s),
                f.name,
                compact(f.value),
                f.unit
            ));
        }
    }
    if rows.len() > 1 {
        align(&rows, 1, out);
    }
    for f in figures {
        let _ = writeln!(out, "{f}");
    }
}

fn ratios(r: &Report, out: &mut String) {
    let name = |label: &str| {
        r.targets
            .iter()
            .find(|t| t.label == label)
            .map(|t| format!("{label} {}", display_name(r, t)))
            .unwrap_or_else(|| label.to_string())
    };
    let mut rows = vec![vec![
        "figure".to_string(),
        name("A"),
        name("B"),
        "B/A".to_string(),
    ]];
    for q in &r.ratios {
        rows.push(vec![
            q.figure.clone(),
            compact(q.a),
            compact(q.b),
            format!("{:.2}", q.ratio),
        ]);
    }
    align(&rows, 1, out);
}

fn summary_name(r: &Report, s: &Summary) -> String {
    r.targets
        .iter()
        .find(|t| t.label == s.target)
        .map(|t| format!("{} {}", t.label, display_name(r, t)))
        .unwrap_or_else(|| s.target.clone())
}

/// Writes `rows` as columns separated by two spaces: the first `left` columns (names)
/// left-aligned, the rest (numbers) right-aligned; a rule under the header row.
fn align(rows: &[Vec<String>], left: usize, out: &mut String) {
    let columns = rows.iter().map(Vec::len).max().unwrap_or(0);
    let widths: Vec<usize> = (0..columns)
        .map(|c| {
            rows.iter()
                .filter_map(|r| r.get(c))
                .map(|s| s.chars().count())
                .max()
                .unwrap_or(0)
        })
        .collect();
    for (i, row) in rows.iter().enumerate() {
        let mut line = String::new();
        for (c, cell) in row.iter().enumerate() {
            if c > 0 {
                line.push_str("  ");
            }
            let w = widths[c];
            if c < left {
                let _ = write!(line, "{cell:<w$}");
            } else {
                let _ = write!(line, "{cell:>w$}");
            }
        }
        out.push_str(line.trim_end());
        out.push('\n');
        if i == 0 {
            let total = widths.iter().sum::<usize>() + 2 * widths.len().saturating_sub(1);
            out.push_str(&"-".repeat(total));
            out.push('\n');
        }
    }
}

/// A mean count: an integer when it is one (a single repeat), else one decimal.
fn count(v: f64) -> String {
    if v.fract() == 0.0 {
        format!("{v:.0}")
    } else {
        format!("{v:.1}")
    }
}

/// Microseconds as milliseconds with the precision that matters at that size.
fn ms(us: f64) -> String {
    let v = us / 1000.0;
    if v < 10.0 {
        format!("{v:.3}")
    } else if v < 1000.0 {
        format!("{v:.1}")
    } else {
        format!("{v:.0}")
    }
}

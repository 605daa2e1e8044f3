//! The run's tables and the summary: medians over the rounds, ratios between setups and
//! the goals they are held against.

use loadtest::broker_process::spawn::Kind;

use super::Transcript;
use super::{Measure, PersistParams, Row, Setup, DEFAULT_POLICY};

/// Every row in the order it ran, columns as wide as their widest cell.
pub(super) fn table(t: &mut Transcript, m: Measure, rows: &[Row], rounds: u32) {
    let mut headers = vec!["setup".to_string()];
    headers.extend(m.columns().iter().map(|c| c.to_string()));
    let mut lines: Vec<(Vec<String>, Option<String>)> = Vec::new();
    for row in rows {
        let name = if rounds > 1 {
            format!("{} #{}", row.setup.label, row.round)
        } else {
            row.setup.label.to_string()
        };
        let mut cells = vec![name];
        match &row.result {
            Ok(f) => {
                cells.extend(f.cells.iter().cloned());
                lines.push((cells, f.note.clone()));
            }
            Err(why) => {
                cells.extend(m.columns().iter().map(|_| "-".to_string()));
                lines.push((cells, Some(why.clone())));
            }
        }
    }
    let rows: Vec<Vec<String>> = lines.iter().map(|(cells, _)| cells.clone()).collect();
    let widths =
        crate::compare::table::column_widths(headers.iter().map(|h| h.chars().count()), &rows);
    let render = |cells: &[String]| crate::compare::table::aligned(cells, &widths);
    t.line(format!("   {}", render(&headers)));
    for (cells, note) in &lines {
        let mut text = render(cells);
        if let Some(note) = note {
            text.push_str(&format!("  [{note}]"));
        }
        t.line(format!("   {text}"));
    }
}

pub(super) fn median(mut v: Vec<f64>) -> Option<f64> {
    v.sort_by(f64::total_cmp);
    match v.len() {
        0 => None,
        n if n % 2 == 1 => Some(v[n / 2]),
        n => Some((v[n / 2 - 1] + v[n / 2]) / 2.0),
    }
}

/// The median of key `i` over the setup's successful rounds.
pub(super) fn median_key(rows: &[Row], label: &str, i: usize) -> Option<f64> {
    median(
        rows.iter()
            .filter(|r| r.setup.label == label)
            .filter_map(|r| r.result.as_ref().ok())
            .filter_map(|f| f.keys.get(i).copied().flatten())
            .collect(),
    )
}

pub(super) fn format_keys(m: Measure, rows: &[Row], label: &str) -> String {
    let k = |i| median_key(rows, label, i);
    match m {
        Measure::Throughput => k(0)
            .map(|v| format!("{} msg/s", crate::compare::scenarios::si(v)))
            .unwrap_or_else(|| "failed".into()),
        Measure::Latency => match (k(0), k(1), k(2)) {
            (Some(a), Some(b), Some(c)) => format!("p50/p99/max {a:.2}/{b:.2}/{c:.2} ms"),
            _ => "failed".into(),
        },
        Measure::Restart => match k(0) {
            Some(r) => {
                let mut s = format!("{r:.3} s");
                if let (Some(read), Some(put)) = (k(2), k(3)) {
                    s.push_str(&format!(" (read {read:.0} ms, put back {put:.0} ms)"));
                }
                s
            }
            None => "failed".into(),
        },
    }
}

/// `a/b 0.85x` (throughput) or `a/b 1.10x/1.20x/0.90x` (latency p50/p99/max) or `a/b
/// 0.20x` (restart time).
pub(super) fn ratio(m: Measure, rows: &[Row], a: &str, b: &str) -> Option<String> {
    let n = match m {
        Measure::Latency => 3,
        _ => 1,
    };
    let mut parts = Vec::new();
    for i in 0..n {
        match (median_key(rows, a, i), median_key(rows, b, i)) {
            (Some(x), Some(y)) if y > 0.0 => parts.push(format!("{:.2}x", x / y)),
            _ => parts.push("n/a".into()),
        }
    }
    if parts.iter().all(|p| p == "n/a") {
        return None;
    }
    Some(format!("{a}/{b} {}", parts.join("/")))
}

/// The measurement's medians per setup, then the ratios: each fbbus policy against
/// fbbus-off and against mosquitto-persist, and Mosquitto's persistence against none.
pub(super) fn ratio_lines(
    m: Measure,
    setups: &[Setup],
    rows: &[Row],
    p: &PersistParams,
) -> Vec<String> {
    let mut line = m.title(p);
    if p.rounds > 1 {
        line.push_str(&format!(" [median of {}]", p.rounds));
    }
    let ran: Vec<&Setup> = setups
        .iter()
        .filter(|s| rows.iter().any(|r| r.setup.label == s.label))
        .collect();
    for s in &ran {
        line.push_str(&format!("   {} {}", s.label, format_keys(m, rows, s.label)));
    }
    let mut ratios = Vec::new();
    for s in ran
        .iter()
        .filter(|s| s.kind == Kind::Fbbus && s.persistent())
    {
        for base in ["fbbus-off", "mosquitto-persist"] {
            if let Some(r) = ratio(m, rows, s.label, base) {
                ratios.push(r);
            }
        }
    }
    if let Some(r) = ratio(m, rows, "mosquitto-persist", "mosquitto-nopersist") {
        ratios.push(r);
    }
    let mut out = vec![line];
    if !ratios.is_empty() {
        out.push(format!(
            "   ratios: {}   ({})",
            ratios.join("   "),
            match m {
                Measure::Throughput => "higher is better",
                Measure::Latency => "p50/p99/max, lower is better",
                Measure::Restart => "lower is better",
            }
        ));
    }
    out
}

/// The goals, met or not, from the medians.
pub(super) fn goals(t: &mut Transcript, all: &[(Measure, Vec<Row>)], p: &PersistParams) {
    let rows_of = |m: Measure| all.iter().find(|(x, _)| *x == m).map(|(_, r)| r);
    let verdict = |ok: bool| if ok { "MET" } else { "NOT MET" };
    t.line("");
    t.line("== goals (issue 17) ==");
    if let Some(rows) = rows_of(Measure::Throughput) {
        let default = median_key(rows, DEFAULT_POLICY, 0);
        for (base, want) in [("fbbus-off", 0.7), ("mosquitto-persist", 1.5)] {
            match (default, median_key(rows, base, 0)) {
                (Some(x), Some(y)) if y > 0.0 => t.line(format!(
                    "QoS 1 throughput, {DEFAULT_POLICY} (default policy) >= {want}x {base}: {:.2}x ({} / {} msg/s)  {}",
                    x / y,
                    crate::compare::scenarios::si(x),
                    crate::compare::scenarios::si(y),
                    verdict(x / y >= want)
                )),
                _ => t.line(format!(
                    "QoS 1 throughput, {DEFAULT_POLICY} (default policy) >= {want}x {base}: n/a (not measured)"
                )),
            }
        }
    }
    if let Some(rows) = rows_of(Measure::Restart) {
        match median_key(rows, DEFAULT_POLICY, 0) {
            Some(x) => {
                let worst = rows
                    .iter()
                    .filter(|r| r.setup.label == DEFAULT_POLICY)
                    .filter_map(|r| r.result.as_ref().ok()?.keys.first().copied().flatten())
                    .fold(0.0f64, f64::max);
                t.line(format!(
                    "restart of {DEFAULT_POLICY} with {} retained messages and {} sessions < 1 s: {x:.3} s \
                     (slowest round {worst:.3} s)  {}",
                    p.retained,
                    p.sessions,
                    verdict(x < 1.0)
                ))
            }
            None => t.line(format!(
                "restart of {DEFAULT_POLICY} < 1 s: n/a (not measured)"
            )),
        }
    }
}

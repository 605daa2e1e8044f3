//! `batches.jtl`: the batches as a JMeter CSV results file, one sample per batch, so the
//! study's JMeter tooling reads our runs: `jmeter -g batches.jtl -o dashboard` builds its
//! HTML dashboard from it, and JTL viewers and CI plugins load it.
//!
//! The file is what JMeter itself writes with its default CSV settings: a header row of
//! the 17 default field names in JMeter's order, millisecond epoch timestamps, integer
//! milliseconds for `elapsed` and `Latency`, `true`/`false` in lower case, `,` as the
//! separator and a field quoted (quotes doubled) only when it holds a comma, a quote or a
//! line break. The report generator finds the columns by the header, and needs
//! `timeStamp`, `elapsed`, `label`, `responseCode`, `responseMessage`, `threadName`,
//! `success`, `bytes`, `sentBytes`, `grpThreads`, `allThreads`, `Latency` and `Connect`.
//!
//! How a batch maps to a sample: elapsed = processing time (first send to last delivery),
//! `bytes`/`sentBytes` = messages delivered/sent (the dashboard's "throughput" columns
//! then count messages), `Latency` = the batch's mean per-message latency, success = the
//! batch's `ok` with response code 200, else 500 and the batch's error as the failure
//! message.

use std::path::Path;

use super::aggregate::{is_compare, name_of};
use super::csv::push_row;
use super::{write_file, ReportError};
use crate::model::{Batch, Report};

/// JMeter's default CSV fields, in the order JMeter writes them.
pub const JTL_COLUMNS: [&str; 17] = [
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

/// Writes one JMeter sample per batch of `report` to `path`.
pub fn write_jtl(report: &Report, path: &Path) -> Result<(), ReportError> {
    let mut out = String::new();
    push_row(&mut out, JTL_COLUMNS.iter().map(|c| c.to_string()));
    for batch in &report.batches {
        push_row(&mut out, sample(report, batch));
    }
    write_file(path, out.as_bytes())
}

fn sample(report: &Report, b: &Batch) -> Vec<String> {
    let name = name_of(report, &b.target);
    let mut label = format!("{} {}", report.scenario, b.label);
    if is_compare(report) {
        label.push_str(&format!(" [{name}]"));
    }
    let url = report
        .targets
        .iter()
        .find(|t| t.label == b.target)
        .map(|t| t.address.clone())
        .unwrap_or_default();
    let latency_ms = b.latency.mean_us / 1000.0;
    let latency_ms = if latency_ms.is_finite() {
        latency_ms.round() as u64
    } else {
        0
    };
    vec![
        b.started_ms.to_string(),
        (b.processing_us / 1000).to_string(),
        label,
        if b.ok { "200" } else { "500" }.to_string(),
        format!("delivered {} of {}", b.delivered, b.expected),
        format!("{name} 1-1"),
        "text".to_string(),
        b.ok.to_string(),
        b.error.clone().unwrap_or_default(),
        b.delivered.to_string(),
        b.sent.to_string(),
        "1".to_string(),
        "1".to_string(),
        url,
        latency_ms.to_string(),
        "0".to_string(),
        "0".to_string(),
    ]
}

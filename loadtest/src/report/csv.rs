//! `batches.csv`: one row per batch, in run order, for spreadsheets and data frames.
//!
//! RFC 4180 quoting (a field with a comma, a double quote or a line break is quoted, its
//! quotes doubled), a header row, `\n` line ends (which every CSV reader accepts and
//! line tools like `cut` and `awk` prefer to `\r\n`), and an empty cell for `None` and for
//! a float that is not finite. Floats are written in Rust's shortest round-trip form, so
//! a reader gets back exactly the value in `report.json`.

use std::borrow::Cow;
use std::path::Path;

use super::aggregate::name_of;
use super::{write_file, ReportError};
use crate::model::{Batch, Report};

/// The columns, in order.
pub const CSV_COLUMNS: [&str; 25] = [
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

/// Writes one row per batch of `report` to `path`.
pub fn write_csv(report: &Report, path: &Path) -> Result<(), ReportError> {
    let mut out = String::new();
    push_row(&mut out, CSV_COLUMNS.iter().map(|c| c.to_string()));
    for batch in &report.batches {
        push_row(&mut out, row(report, batch));
    }
    write_file(path, out.as_bytes())
}

fn row(report: &Report, b: &Batch) -> Vec<String> {
    let l = &b.latency;
    vec![
        b.target.clone(),
        name_of(report, &b.target),
        b.label.clone(),
        float(b.x),
        b.repeat.to_string(),
        b.started_ms.to_string(),
        b.sent.to_string(),
        b.expected.to_string(),
        b.delivered.to_string(),
        b.lost().to_string(),
        float(b.delivery_rate()),
        b.delivered_fb.map(|d| d.to_string()).unwrap_or_default(),
        b.duplicates.to_string(),
        b.out_of_order.to_string(),
        b.send_us.to_string(),
        b.processing_us.to_string(),
        float(b.throughput),
        float(l.mean_us),
        l.p50_us.to_string(),
        l.p90_us.to_string(),
        l.p99_us.to_string(),
        l.p999_us.to_string(),
        l.max_us.to_string(),
        b.ok.to_string(),
        b.error.clone().unwrap_or_default(),
    ]
}

fn float(v: f64) -> String {
    if v.is_finite() {
        v.to_string()
    } else {
        String::new()
    }
}

/// Appends one record: fields joined by commas, each quoted when needed, then `\n`.
pub(crate) fn push_row(out: &mut String, fields: impl IntoIterator<Item = String>) {
    for (i, field) in fields.into_iter().enumerate() {
        if i > 0 {
            out.push(',');
        }
        out.push_str(&quote(&field));
    }
    out.push('\n');
}

/// RFC 4180: a field containing a comma, a double quote, CR or LF is enclosed in double
/// quotes and its double quotes doubled; any other field is written as is. JMeter's
/// CSV reader follows the same rule, so the JTL uses it too.
pub(crate) fn quote(field: &str) -> Cow<'_, str> {
    if field.contains([',', '"', '\r', '\n']) {
        Cow::Owned(format!("\"{}\"", field.replace('"', "\"\"")))
    } else {
        Cow::Borrowed(field)
    }
}

//! The outputs of a run, all written from one [`Report`]: nothing here measures, every
//! figure comes from the model, so the terminal, the files and the charts always agree.
//!
//! [`write_all`] writes into one directory:
//!
//! - `report.json`: the whole [`Report`] (serde_json, pretty). The record of the run:
//!   everything else can be regenerated from it.
//! - `batches.csv`: one row per [`Batch`](crate::model::Batch), with a header, RFC 4180
//!   quoting and an empty cell for "none"; for spreadsheets, pandas, R.
//! - `batches.jtl`: the same batches as JMeter CSV samples, so the JMeter study's own
//!   tooling (`jmeter -g batches.jtl -o dashboard`, JTL viewers) reads our runs as it read
//!   its own.
//! - charts (SVG, one line per broker, drawn only when the scenario has what they show):
//!   - `stress.svg`, `delivery-rate.svg` (stress, loss-search): messages delivered and
//!     % delivered per burst size, burst size on a log2 axis, with the "sent" line;
//!   - `latency-vs-batch.svg`, `throughput-vs-batch.svg`, `processing-time.svg` (perf):
//!     the study's three perf figures against batch size;
//!   - `latency-percentiles.svg` (any scenario that measured latencies): each broker's
//!     latency percentile curve on the usual HdrHistogram axis (50% .. 99.99%);
//!   - `throughput.svg` (other scenarios, when they vary x): throughput against x.
//!
//! [`table`] renders the terminal summary: the run's provenance, one row per x and broker
//! (repeats aggregated), the summaries and, comparing two brokers, the B/A ratios.

mod aggregate;
mod csv;
mod json;
mod jtl;
mod svg;
mod table;

use std::path::{Path, PathBuf};

use crate::model::Report;

pub use self::csv::write_csv;
pub use self::json::write_json;
pub use self::jtl::write_jtl;
pub use self::svg::write_charts;
pub use self::table::table;

/// File names inside the directory given to [`write_all`].
pub const JSON_FILE: &str = "report.json";
pub const CSV_FILE: &str = "batches.csv";
pub const JTL_FILE: &str = "batches.jtl";

/// Why an output could not be written. Each message names the file and what to do.
#[derive(thiserror::Error, Debug)]
pub enum ReportError {
    #[error(
        "cannot create the report directory {}: {source}; check that the path is \
         writable or choose another output directory",
        dir.display()
    )]
    CreateDir {
        dir: PathBuf,
        #[source]
        source: std::io::Error,
    },
    #[error(
        "cannot write {}: {source}; check free disk space and permissions on the \
         output directory",
        path.display()
    )]
    Write {
        path: PathBuf,
        #[source]
        source: std::io::Error,
    },
    #[error(
        "cannot serialize the report to {}: {source}; this is a bug in \
         fbbus-loadtest, please report it with the command line",
        path.display()
    )]
    Json {
        path: PathBuf,
        #[source]
        source: serde_json::Error,
    },
    #[error(
        "cannot draw the chart {}: {message}; the other outputs are unaffected \
         (report.json has every figure), please report this with report.json",
        path.display()
    )]
    Chart { path: PathBuf, message: String },
}

/// Creates `dir` (and its parents) and writes every output into it: `report.json`,
/// `batches.csv`, `batches.jtl`, then the charts the scenario has data for. Returns the
/// paths written, in that order.
pub fn write_all(report: &Report, dir: &Path) -> Result<Vec<PathBuf>, ReportError> {
    create_dir(dir)?;
    let mut written = Vec::new();
    let json = dir.join(JSON_FILE);
    write_json(report, &json)?;
    written.push(json);
    let csv = dir.join(CSV_FILE);
    write_csv(report, &csv)?;
    written.push(csv);
    let jtl = dir.join(JTL_FILE);
    write_jtl(report, &jtl)?;
    written.push(jtl);
    written.extend(write_charts(report, dir)?);
    Ok(written)
}

fn create_dir(dir: &Path) -> Result<(), ReportError> {
    std::fs::create_dir_all(dir).map_err(|source| ReportError::CreateDir {
        dir: dir.to_path_buf(),
        source,
    })
}

/// Writes a whole file at once, mapping the error to one that names it.
fn write_file(path: &Path, contents: &[u8]) -> Result<(), ReportError> {
    std::fs::write(path, contents).map_err(|source| ReportError::Write {
        path: path.to_path_buf(),
        source,
    })
}

#[cfg(test)]
mod tests;

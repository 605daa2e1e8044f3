//! `report.json`: the whole [`Report`], pretty-printed. It is the record of the run: the
//! other files are views of it and can be regenerated from it.
//!
//! Note: JSON has no NaN or infinity; serde_json writes such a float as `null`, which does
//! not read back as `f64`. The scenarios keep every figure finite (a zero-length batch has
//! throughput 0, not infinity) for this reason.

use std::path::Path;

use super::{write_file, ReportError};
use crate::model::Report;

/// Writes `report` to `path` as pretty JSON with a trailing newline.
pub fn write_json(report: &Report, path: &Path) -> Result<(), ReportError> {
    let mut json = serde_json::to_vec_pretty(report).map_err(|source| ReportError::Json {
        path: path.to_path_buf(),
        source,
    })?;
    json.push(b'\n');
    write_file(path, &json)
}

//! `GET /api/v1/devices/{id}/ports/{FB.PORT}/history`: a port's recent values
//! ([`history`](super::history)) as JSON for the console's plots, or as CSV for a
//! spreadsheet (`?format=csv`).
//!
//! `from` and `to` bound the time (ms since 1970 UTC, or RFC 3339: `2026-11-29T08:00:00Z`),
//! `limit` keeps the newest points of that range. A declared plottable port with no value
//! yet answers an empty history; a port that is not a declared output of the device, or
//! whose values are not numbers, answers 404 saying which.

use std::sync::Arc;
use std::time::{Duration, SystemTime};

use axum::extract::{Path, Query, State};
use axum::http::{header, HeaderValue, StatusCode};
use axum::response::{IntoResponse, Response};
use fb_bridge::OutputPort;
use serde::Deserialize;

use super::history::{self, Kind, Point};
use super::{assets, Console};

#[derive(Debug, Deserialize)]
pub struct Range {
    from: Option<String>,
    to: Option<String>,
    limit: Option<usize>,
    format: Option<String>,
}

fn refuse(status: StatusCode, error: String) -> Response {
    let mut response = (status, axum::Json(serde_json::json!({ "error": error }))).into_response();
    assets::secure(&mut response);
    response
}

/// A time parameter: ms since 1970 UTC, or RFC 3339.
fn parse_time(name: &str, text: &str) -> Result<u64, String> {
    if let Ok(ms) = text.parse::<u64>() {
        return Ok(ms);
    }
    humantime::parse_rfc3339_weak(text)
        .ok()
        .and_then(|t| t.duration_since(SystemTime::UNIX_EPOCH).ok())
        .map(|d| u64::try_from(d.as_millis()).unwrap_or(u64::MAX))
        .ok_or_else(|| {
            format!("{name}: {text:?} is neither ms since 1970 nor an RFC 3339 time (2026-11-29T08:00:00Z)")
        })
}

pub async fn history(
    State(console): State<Arc<Console>>,
    Path((id, name)): Path<(String, String)>,
    Query(range): Query<Range>,
) -> Response {
    let Some(record) = console.registry.get(&id) else {
        return refuse(
            StatusCode::NOT_FOUND,
            format!("no device {id} in the registry"),
        );
    };
    let Some((fb, port)) = name.split_once('.') else {
        return refuse(
            StatusCode::NOT_FOUND,
            format!("{name}: a port is named FB.PORT (e.g. CONV.SPEED)"),
        );
    };
    let (kind, ty) = match record.interface.output(fb, port) {
        None => {
            return refuse(
                StatusCode::NOT_FOUND,
                format!("device {id} declares no output port {name}"),
            )
        }
        Some(OutputPort::Event(_)) => (Kind::Event, None),
        Some(OutputPort::Data(ty)) if history::plottable(ty) => {
            (history::data_kind(&record.interface, fb, port), Some(ty))
        }
        Some(OutputPort::Data(ty)) => {
            return refuse(
                StatusCode::NOT_FOUND,
                format!(
                    "{name} is {ty}: its values are shown as the last value, not kept as history"
                ),
            )
        }
    };
    let bound = |name, text: &Option<String>, default| match text {
        Some(text) => parse_time(name, text),
        None => Ok(default),
    };
    let (from, to) = match (
        bound("from", &range.from, 0),
        bound("to", &range.to, u64::MAX),
    ) {
        (Ok(from), Ok(to)) => (from, to),
        (Err(e), _) | (_, Err(e)) => return refuse(StatusCode::BAD_REQUEST, e),
    };
    let limit = range.limit.unwrap_or(usize::MAX);
    let answer = console.activity.history(&id, fb, port, from, to, limit);
    let points = answer.as_ref().map_or(&[][..], |a| &a.points[..]);
    let csv = match range.format.as_deref() {
        None | Some("json") => false,
        Some("csv") => true,
        Some(other) => {
            return refuse(
                StatusCode::BAD_REQUEST,
                format!("format {other:?}: json (the default) or csv"),
            )
        }
    };
    let mut response = if csv {
        csv_response(&id, &name, points)
    } else {
        let body = serde_json::json!({
            "device": id,
            "port": name,
            "type": ty.map(|t| t.to_string()),
            "kind": answer.as_ref().map_or(kind, |a| a.kind),
            "window_s": console.activity.history_window_s(),
            "capacity": answer.as_ref().map(|a| a.capacity),
            "points": points,
        });
        axum::Json(body).into_response()
    };
    assets::secure(&mut response);
    response
}

/// `time,<FB.PORT>` then one row per point, its time in RFC 3339 (UTC, ms).
fn csv_response(id: &str, name: &str, points: &[Point]) -> Response {
    let mut body = String::with_capacity(32 * (points.len() + 1));
    body.push_str("time,");
    body.push_str(name);
    body.push('\n');
    for Point(ms, value) in points {
        let at = SystemTime::UNIX_EPOCH + Duration::from_millis(*ms);
        body.push_str(&format!(
            "{},{value}\n",
            humantime::format_rfc3339_millis(at)
        ));
    }
    let file: String = format!("{id}_{name}.csv")
        .chars()
        .map(|c| match c {
            'a'..='z' | 'A'..='Z' | '0'..='9' | '.' | '_' | '-' => c,
            _ => '_',
        })
        .collect();
    let mut response = body.into_response();
    let headers = response.headers_mut();
    headers.insert(
        header::CONTENT_TYPE,
        HeaderValue::from_static("text/csv; charset=utf-8"),
    );
    if let Ok(value) = HeaderValue::from_str(&format!("attachment; filename=\"{file}\"")) {
        headers.insert(header::CONTENT_DISPOSITION, value);
    }
    response
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn times_are_ms_or_rfc3339() {
        assert_eq!(parse_time("from", "1000"), Ok(1000));
        assert_eq!(parse_time("from", "1970-01-01T00:00:01.5Z"), Ok(1500));
        let e = parse_time("to", "yesterday").unwrap_err();
        assert!(e.starts_with("to: \"yesterday\""), "{e}");
    }
}

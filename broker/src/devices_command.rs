//! `fbbus devices`: the device registry in a terminal, read from the admin endpoint;
//! `fbbus devices forget ID` removes an offline device through it.

use std::io::Write;
use std::net::SocketAddr;
use std::time::Duration;

use anyhow::Result;
use serde_json::Value;

use crate::admin_client::{delete, get, percent_encode};

pub struct Options {
    pub admin: SocketAddr,
    pub json: bool,
    pub watch: Option<Duration>,
    pub id: Option<String>,
}

pub fn run(options: Options) -> Result<()> {
    loop {
        let body = match &options.id {
            Some(id) => get(
                options.admin,
                &format!("/api/v1/devices/{}", percent_encode(id)),
            )?,
            None => every_page(options.admin)?,
        };
        let out = if options.json {
            format!("{}\n", serde_json::to_string_pretty(&body)?)
        } else {
            table(&body)
        };
        match options.watch {
            None => {
                print!("{out}");
                return Ok(());
            }
            Some(interval) => {
                // Clear the screen, then redraw: `watch`-style.
                print!("\x1b[2J\x1b[H{out}");
                std::io::stdout().flush()?;
                std::thread::sleep(interval);
            }
        }
    }
}

/// Every device, page after page (`GET /api/v1/devices` answers one page and names the
/// next in `next`), as one `{"line", "devices"}` answer.
fn every_page(admin: SocketAddr) -> Result<Value> {
    let mut after: Option<String> = None;
    let mut devices = Vec::new();
    let mut line = Value::Null;
    loop {
        let mut path = format!("/api/v1/devices?limit={PAGE}");
        if let Some(after) = &after {
            path.push_str("&after=");
            path.push_str(&percent_encode(after));
        }
        let mut page = get(admin, &path)?;
        line = page.get_mut("line").map(Value::take).unwrap_or(line);
        if let Some(Value::Array(list)) = page.get_mut("devices").map(Value::take) {
            devices.extend(list);
        }
        match page.get("next").and_then(Value::as_str) {
            // A `next` not after the last one would loop forever: the broker never sends
            // one, but a command must end.
            Some(next) if after.as_deref().is_none_or(|a| next > a) => {
                after = Some(next.to_owned())
            }
            _ => break,
        }
    }
    Ok(serde_json::json!({"line": line, "devices": devices}))
}

/// Devices asked for per request.
const PAGE: usize = 1000;

/// Forgets the offline device `id` (`DELETE /api/v1/devices/{id}`): its record, its
/// retained record and values, its metric series. The broker refuses an unknown or
/// online device, and any request not from its own host.
pub fn forget(admin: SocketAddr, id: &str) -> Result<()> {
    delete(admin, &format!("/api/v1/devices/{}", percent_encode(id)))?;
    println!("device {id} forgotten: its record and retained values are cleared");
    Ok(())
}

/// The registry as an aligned table.
fn table(body: &Value) -> String {
    let devices: Vec<&Value> = match body.get("devices").and_then(Value::as_array) {
        Some(list) => list.iter().collect(),
        None => vec![body],
    };
    let header = [
        "ID",
        "LINE",
        "STATUS",
        "SESSION",
        "SINCE",
        "FBS",
        "LAST WILL REASON",
    ];
    let mut rows: Vec<[String; 7]> = vec![header.map(str::to_owned)];
    for d in &devices {
        let text = |key: &str| match d.get(key) {
            Some(Value::String(s)) => s.clone(),
            Some(Value::Null) | None => "-".into(),
            Some(v) => v.to_string(),
        };
        let fbs = d
            .pointer("/interface/fbs")
            .and_then(Value::as_object)
            .map_or(0, |m| m.len());
        // Online and silent: connected, but its periodic outputs stopped.
        let mut status = text("status");
        if d.get("silent") == Some(&Value::Bool(true)) {
            status.push_str(", silent");
        }
        rows.push([
            text("id"),
            text("line"),
            status,
            text("session"),
            text("since"),
            fbs.to_string(),
            text("last_will_reason"),
        ]);
    }
    let mut out = crate::terminal_table::aligned(&rows);
    let online = devices
        .iter()
        .filter(|d| d.get("status").and_then(Value::as_str) == Some("online"))
        .count();
    let silent = devices
        .iter()
        .filter(|d| d.get("silent") == Some(&Value::Bool(true)))
        .count();
    out.push_str(&format!("{} devices, {online} online", devices.len()));
    if silent > 0 {
        out.push_str(&format!(" ({silent} silent)"));
    }
    out.push('\n');
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_table_has_a_row_per_device_and_a_summary() {
        let body = serde_json::json!({"line": "line-1", "devices": [
            {"id": "conv-a", "line": "line-1", "status": "online", "session": 3, "since": "2026-11-22T08:00:00.000Z", "last_will_reason": null, "interface": {"fbs": {"CONV": {}}}},
            {"id": "conv-b", "line": "line-1", "status": "offline", "session": 1, "since": "2026-11-22T08:01:00.000Z", "last_will_reason": "keep-alive expired", "interface": {"fbs": {}}},
        ]});
        let t = table(&body);
        let lines: Vec<&str> = t.lines().collect();
        assert_eq!(lines.len(), 4, "{t}");
        assert!(!t.contains("silent"), "{t}");
        assert!(lines[0].starts_with("ID"));
        assert!(lines[1].contains("conv-a") && lines[1].contains("online"));
        assert!(lines[2].contains("keep-alive expired"));
        assert_eq!(lines[3], "2 devices, 1 online");
    }

    #[test]
    fn a_silent_device_is_online_silent() {
        let body = serde_json::json!({"line": "line-1", "devices": [
            {"id": "forte-1", "line": "line-1", "status": "online", "session": 3, "since": "2026-11-22T08:00:00.000Z", "last_will_reason": null, "silent": true, "silent_since": "2026-11-22T08:05:00.000Z", "interface": {"fbs": {}}},
        ]});
        let t = table(&body);
        let lines: Vec<&str> = t.lines().collect();
        assert!(lines[1].contains("online, silent"), "{t}");
        assert_eq!(lines[2], "1 devices, 1 online (1 silent)");
    }
}

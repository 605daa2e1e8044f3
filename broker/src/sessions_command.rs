//! `fbbus sessions`: the sessions of a running broker (connected and kept), with who owns
//! each, read from the admin endpoint; `fbbus sessions drop ID` ends a kept one (issue 33:
//! a kept session of another identity would otherwise block its client id for good).

use std::net::SocketAddr;

use anyhow::Result;
use serde_json::Value;

use crate::admin_client::{delete, get, percent_encode};

/// Sessions asked for per request.
const PAGE: usize = 1000;

/// Prints every session, as a table or (`json`) as one JSON array.
pub fn list(admin: SocketAddr, json: bool) -> Result<()> {
    let mut after = String::new();
    let mut sessions = Vec::new();
    loop {
        let mut path = format!("/api/v1/sessions?limit={PAGE}");
        if !after.is_empty() {
            path.push_str("&after=");
            path.push_str(&percent_encode(&after));
        }
        let mut page = get(admin, &path)?;
        if let Some(Value::Array(list)) = page.get_mut("sessions").map(Value::take) {
            sessions.extend(list);
        }
        match page.get("next").and_then(Value::as_str) {
            // Only forward: a command must end.
            Some(next) if next > after.as_str() => after = next.to_owned(),
            _ => break,
        }
    }
    if json {
        println!("{}", serde_json::to_string_pretty(&sessions)?);
    } else {
        print!("{}", table(&sessions));
    }
    Ok(())
}

/// Drops the kept session of `client_id` (`DELETE /api/v1/sessions/{id}`). The broker
/// refuses an unknown or connected one, and any request not from its own host.
pub fn drop(admin: SocketAddr, client_id: &str) -> Result<()> {
    delete(
        admin,
        &format!("/api/v1/sessions/{}", percent_encode(client_id)),
    )?;
    println!("session of client id {client_id} dropped: the client id is free");
    Ok(())
}

/// The sessions as an aligned table, and a summary line.
fn table(sessions: &[Value]) -> String {
    let mut rows: Vec<[String; 5]> =
        vec![["CLIENT ID", "OWNER", "STATUS", "SESSION", "EXPIRES IN"].map(str::to_owned)];
    for s in sessions {
        let text = |key: &str| match s.get(key) {
            Some(Value::String(v)) => v.clone(),
            Some(Value::Null) | None => "-".into(),
            Some(v) => v.to_string(),
        };
        let expires = match s.get("expires_in_s").and_then(Value::as_u64) {
            Some(secs) => format!("{secs} s"),
            None if text("status") == "kept" => "never".into(),
            None => "-".into(),
        };
        rows.push([
            text("client_id"),
            text("owner"),
            text("status"),
            text("session"),
            expires,
        ]);
    }
    let mut out = crate::terminal_table::aligned(&rows);
    let kept = sessions
        .iter()
        .filter(|s| s.get("status").and_then(Value::as_str) == Some("kept"))
        .count();
    out.push_str(&format!(
        "{} sessions, {kept} kept offline\n",
        sessions.len()
    ));
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_table_names_owners_and_expiry() {
        let sessions = serde_json::json!([
            {"client_id": "devB", "owner": "devA", "status": "kept", "session": 7, "expires_in_s": null},
            {"client_id": "plc-1", "owner": "plc-1", "status": "connected", "session": 9, "expires_in_s": null},
        ]);
        let t = table(sessions.as_array().unwrap());
        let lines: Vec<&str> = t.lines().collect();
        assert!(lines[0].starts_with("CLIENT ID"), "{t}");
        assert!(
            lines[1].starts_with("devB")
                && lines[1].contains("devA")
                && lines[1].ends_with("never"),
            "{t}"
        );
        assert!(
            lines[2].contains("connected") && lines[2].ends_with('-'),
            "{t}"
        );
        assert_eq!(lines[3], "2 sessions, 1 kept offline");
    }
}

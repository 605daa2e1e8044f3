//! The admin endpoint, as `fbbus devices` (and `fbbus devices forget`) and `fbbus declare`
//! talk to it.
//!
//! The admin endpoint is plain HTTP on loopback and fbbus's own, so a dozen lines of
//! HTTP/1.1 here replace an HTTP client crate and its TLS stack.

use std::io::{Read, Write};
use std::net::{SocketAddr, TcpStream};
use std::time::Duration;

use anyhow::{bail, Context as _, Result};
use serde_json::Value;

/// GETs `path` and parses the JSON body.
pub fn get(admin: SocketAddr, path: &str) -> Result<Value> {
    request(admin, "GET", path, None)
}

/// PUTs `body` at `path` and parses the JSON answer.
pub fn put(admin: SocketAddr, path: &str, body: &[u8]) -> Result<Value> {
    request(admin, "PUT", path, Some(body))
}

/// DELETEs `path` and parses the JSON answer.
pub fn delete(admin: SocketAddr, path: &str) -> Result<Value> {
    request(admin, "DELETE", path, None)
}

fn request(admin: SocketAddr, method: &str, path: &str, body: Option<&[u8]>) -> Result<Value> {
    let mut stream = TcpStream::connect_timeout(&admin, Duration::from_secs(3)).with_context(
        || format!("cannot reach the broker's admin endpoint at {admin} (is fbbus running? use --admin or --config)"),
    )?;
    stream.set_read_timeout(Some(Duration::from_secs(10)))?;
    let mut head = format!(
        "{method} {path} HTTP/1.1\r\nHost: {admin}\r\nAccept: application/json\r\nConnection: close\r\n"
    );
    if let Some(body) = body {
        head.push_str(&format!(
            "Content-Type: text/plain; charset=utf-8\r\nContent-Length: {}\r\n",
            body.len()
        ));
    }
    head.push_str("\r\n");
    stream.write_all(head.as_bytes())?;
    if let Some(body) = body {
        stream.write_all(body)?;
    }
    let mut response = Vec::new();
    stream.read_to_end(&mut response)?;
    let split = response
        .windows(4)
        .position(|w| w == b"\r\n\r\n")
        .context("the admin endpoint sent no HTTP response")?;
    let head = String::from_utf8_lossy(&response[..split]);
    let body = response.get(split + 4..).unwrap_or_default();
    let status = head.split_whitespace().nth(1).unwrap_or("");
    if head
        .to_ascii_lowercase()
        .contains("transfer-encoding: chunked")
    {
        bail!("the admin endpoint sent a chunked response, which this command does not read");
    }
    let json: Value =
        serde_json::from_slice(body).context("the admin endpoint sent invalid JSON")?;
    match status {
        "200" => Ok(json),
        _ => bail!(
            "{}",
            json.get("error")
                .and_then(Value::as_str)
                .unwrap_or("request failed")
        ),
    }
}

//! The admin endpoint, as `fbbus devices` (and `fbbus devices forget`), `fbbus sessions`
//! (and `fbbus sessions drop`) and `fbbus declare` talk to it.
//!
//! The admin endpoint is plain HTTP on loopback and fbbus's own, so a dozen lines of
//! HTTP/1.1 here replace an HTTP client crate and its TLS stack.
//!
//! An admin endpoint with `[admin] password_file` wants HTTP Basic credentials: they are
//! taken from the environment, `FBBUS_ADMIN_USER` and `FBBUS_ADMIN_PASSWORD`, never from
//! the command line (which `ps` shows to every user of the host).

use std::io::{Read, Write};
use std::net::{SocketAddr, TcpStream};
use std::time::Duration;

use anyhow::{bail, Context as _, Result};
use base64::Engine as _;
use serde_json::Value;

/// The environment variables the admin credentials come from.
pub const USER_VAR: &str = "FBBUS_ADMIN_USER";
pub const PASSWORD_VAR: &str = "FBBUS_ADMIN_PASSWORD";

/// `Basic base64(user:password)` from the environment; None when neither variable is set.
fn authorization() -> Result<Option<String>> {
    let var = |name: &str| match std::env::var(name) {
        Ok(value) if !value.is_empty() => Ok(Some(value)),
        Ok(_) | Err(std::env::VarError::NotPresent) => Ok(None),
        Err(std::env::VarError::NotUnicode(_)) => bail!("{name} is not valid UTF-8"),
    };
    match (var(USER_VAR)?, var(PASSWORD_VAR)?) {
        (Some(user), Some(password)) => {
            if user.contains(':') {
                bail!("{USER_VAR} must not contain `:` (HTTP Basic credentials cannot carry it)");
            }
            let token = base64::engine::general_purpose::STANDARD
                .encode(format!("{user}:{password}").as_bytes());
            Ok(Some(format!("Basic {token}")))
        }
        (None, None) => Ok(None),
        _ => bail!(
            "set both {USER_VAR} and {PASSWORD_VAR} (the admin endpoint's credentials), or neither"
        ),
    }
}

/// `text` as one URL path segment or query value: everything but the unreserved
/// characters percent-encoded (a client id may hold any character, `/`, `?` and `&` too).
pub fn percent_encode(text: &str) -> String {
    let mut out = String::with_capacity(text.len());
    for b in text.bytes() {
        if b.is_ascii_alphanumeric() || matches!(b, b'-' | b'_' | b'.' | b'~') {
            out.push(b as char);
        } else {
            out.push_str(&format!("%{b:02X}"));
        }
    }
    out
}

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
    let authorization = authorization()?;
    let mut stream = TcpStream::connect_timeout(&admin, Duration::from_secs(3)).with_context(
        || format!("cannot reach the broker's admin endpoint at {admin} (is fbbus running? use --admin or --config)"),
    )?;
    stream.set_read_timeout(Some(Duration::from_secs(10)))?;
    let mut head = format!(
        "{method} {path} HTTP/1.1\r\nHost: {admin}\r\nAccept: application/json\r\nConnection: close\r\n"
    );
    if let Some(authorization) = &authorization {
        head.push_str(&format!("Authorization: {authorization}\r\n"));
    }
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
    match status {
        "401" if authorization.is_none() => bail!(
            "the admin endpoint at {admin} requires credentials: set {USER_VAR} and \
             {PASSWORD_VAR} to a user of its [admin] password_file and its password"
        ),
        "401" => bail!(
            "the admin endpoint at {admin} refused the credentials in {USER_VAR} and \
             {PASSWORD_VAR}: they must be a user of its [admin] password_file and its password"
        ),
        "429" => bail!(
            "the admin endpoint at {admin} refuses this address for a while after too many \
             failed logins (retry after {} s); check {USER_VAR} and {PASSWORD_VAR}",
            header(&head, "retry-after").unwrap_or("a few")
        ),
        _ => {}
    }
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

/// The value of header `name` (in any case) in a response head.
fn header<'a>(head: &'a str, name: &str) -> Option<&'a str> {
    head.lines().skip(1).find_map(|line| {
        let (key, value) = line.split_once(':')?;
        key.trim().eq_ignore_ascii_case(name).then(|| value.trim())
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn ids_are_percent_encoded_for_paths_and_queries() {
        assert_eq!(percent_encode("conv-a_1.x~"), "conv-a_1.x~");
        assert_eq!(percent_encode("a b&c=d/é"), "a%20b%26c%3Dd%2F%C3%A9");
        assert_eq!(percent_encode("a/b?c d%é"), "a%2Fb%3Fc%20d%25%C3%A9");
    }
}

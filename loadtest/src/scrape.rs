//! The broker's Prometheus endpoint (`--metrics http://127.0.0.1:9883/metrics`), read
//! before and after a campaign: one HTTP/1.0 GET, no HTTP client library, plain `http://`
//! only (fbbus's admin endpoint is plain HTTP on loopback).

use std::time::Duration;

use tokio::io::{AsyncReadExt, AsyncWriteExt};

/// The connection and session series a campaign reports: fbbus's names
/// (broker/src/metrics.rs). Every `fbbus_router_*` series is kept too.
pub const CAMPAIGN_SERIES: &[&str] = &[
    "fbbus_connections",
    "fbbus_connects_total",
    "fbbus_connects_refused_total",
    "fbbus_disconnects_total",
    "fbbus_malformed_packets_total",
    "fbbus_oversized_packets_total",
    "fbbus_messages_received_total",
    "fbbus_messages_sent_total",
    "fbbus_messages_dropped_total",
    "fbbus_wills_published_total",
    "fbbus_acl_denied_total",
    "fbbus_logins_throttled_total",
    "fbbus_registry_devices",
];

/// GETs `url` (`http://host:port/path`) and returns the body; errors say why.
pub async fn get(url: &str, timeout: Duration) -> Result<String, String> {
    let rest = url
        .strip_prefix("http://")
        .ok_or_else(|| format!("{url}: only http:// URLs are supported"))?;
    let (authority, path) = match rest.find('/') {
        Some(i) => (&rest[..i], &rest[i..]),
        None => (rest, "/"),
    };
    let address = if authority.contains(':') {
        authority.to_owned()
    } else {
        format!("{authority}:80")
    };
    let fetch = async {
        let mut s = tokio::net::TcpStream::connect(&address)
            .await
            .map_err(|e| format!("{url}: {e}"))?;
        s.write_all(format!("GET {path} HTTP/1.0\r\nHost: {authority}\r\n\r\n").as_bytes())
            .await
            .map_err(|e| format!("{url}: {e}"))?;
        let mut raw = Vec::new();
        s.read_to_end(&mut raw)
            .await
            .map_err(|e| format!("{url}: {e}"))?;
        Ok::<_, String>(raw)
    };
    let raw = tokio::time::timeout(timeout, fetch)
        .await
        .map_err(|_| format!("{url}: no answer within {timeout:?}"))??;
    let text = String::from_utf8_lossy(&raw);
    let (head, body) = text
        .split_once("\r\n\r\n")
        .ok_or_else(|| format!("{url}: not an HTTP response"))?;
    let status = head.split_whitespace().nth(1).unwrap_or("?");
    if status != "200" {
        return Err(format!("{url}: HTTP status {status}"));
    }
    Ok(body.to_owned())
}

/// The series of a Prometheus text exposition whose metric name is in `names` or starts
/// with `fbbus_router_`, as (series with labels, value), in the order exposed.
pub fn select(text: &str, names: &[&str]) -> Vec<(String, f64)> {
    text.lines()
        .filter(|l| !l.starts_with('#') && !l.trim().is_empty())
        .filter_map(|l| {
            let (series, value) = l.rsplit_once(' ')?;
            let name = series.split('{').next()?;
            let wanted = names.contains(&name) || name.starts_with("fbbus_router_");
            Some((series.to_owned(), value.trim().parse::<f64>().ok()?)).filter(|_| wanted)
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn selects_the_campaign_series() {
        let text = "# HELP fbbus_connections open\n# TYPE fbbus_connections gauge\n\
                    fbbus_connections 3\n\
                    fbbus_connects_total 10\n\
                    fbbus_disconnects_total{reason=\"client\"} 7\n\
                    fbbus_router_saved_sessions 4\n\
                    fbbus_typed_messages_accepted_total 99\n";
        assert_eq!(
            select(text, CAMPAIGN_SERIES),
            vec![
                ("fbbus_connections".into(), 3.0),
                ("fbbus_connects_total".into(), 10.0),
                ("fbbus_disconnects_total{reason=\"client\"}".into(), 7.0),
                ("fbbus_router_saved_sessions".into(), 4.0),
            ]
        );
    }

    #[tokio::test]
    async fn gets_a_page_and_refuses_other_schemes() {
        let listener = tokio::net::TcpListener::bind("127.0.0.1:0").await.unwrap();
        let addr = listener.local_addr().unwrap();
        tokio::spawn(async move {
            let (mut s, _) = listener.accept().await.unwrap();
            let mut buf = [0u8; 512];
            let _ = s.read(&mut buf).await;
            let _ = s
                .write_all(
                    b"HTTP/1.0 200 OK\r\nContent-Type: text/plain\r\n\r\nfbbus_connections 1\n",
                )
                .await;
        });
        let body = get(&format!("http://{addr}/metrics"), Duration::from_secs(5))
            .await
            .unwrap();
        assert_eq!(body, "fbbus_connections 1\n");
        assert!(get("https://x/metrics", Duration::from_secs(1))
            .await
            .is_err());
    }
}

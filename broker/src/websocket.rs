//! MQTT over WebSockets (MQTT 5.0 §6, 3.1.1 §6): a `kind = "ws"` listener's connections.
//!
//! The WebSocket handshake and framing are tokio-tungstenite's; this module checks the
//! handshake the way MQTT over WebSockets clients expect (path `/mqtt` by default,
//! subprotocol `mqtt`, or `mqttv3.1` from older clients, optionally the browser's
//! `Origin`) and turns the connection into a byte [`Stream`] ([`WsStream`]), so the
//! session reads and writes it like TCP: the same CONNECT, authentication, ACL, typed
//! checks, limits, write deadlines and metrics. Binary messages carry the MQTT byte
//! stream: a packet may span messages and a message may hold several packets, exactly as
//! on TCP, so the session's framing and its `max_packet_size` apply unchanged.

use std::io::{self, ErrorKind};
use std::net::SocketAddr;
use std::pin::Pin;
use std::task::{ready, Context, Poll};

use bytes::Bytes;
use futures_util::{Sink, Stream as _};
use tokio::io::{AsyncRead, AsyncReadExt, AsyncWrite, ReadBuf};
use tokio_tungstenite::tungstenite::handshake::server::{ErrorResponse, Request, Response};
use tokio_tungstenite::tungstenite::http::{header, HeaderValue, StatusCode};
use tokio_tungstenite::tungstenite::protocol::WebSocketConfig;
use tokio_tungstenite::tungstenite::{Error as WsError, Message};
use tokio_tungstenite::WebSocketStream;

use crate::wire::framed::Stream;

/// The subprotocols MQTT clients ask for: `mqtt` (MQTT 3.1.1 and 5), `mqttv3.1` (older
/// clients, MQTT.js among them when told to speak 3.1).
pub const SUBPROTOCOLS: [&str; 2] = ["mqtt", "mqttv3.1"];

/// The path clients use by convention (Mosquitto, HiveMQ, MQTT.js and paho examples).
pub const DEFAULT_PATH: &str = "/mqtt";

/// The largest piece of the session's write buffer sent as one WebSocket message: bounds
/// the copy each message makes.
const MAX_OUT_MESSAGE: usize = 64 * 1024;

/// tungstenite's read buffer, allocated per connection: small, as the session's own
/// buffers start small (most of a line's clients are idle most of the time).
const READ_BUFFER: usize = 4 * 1024;

/// What a `ws` listener checks in the handshake.
#[derive(Debug, Clone)]
pub struct Handshake {
    /// The request path (without its query), `/mqtt` by default.
    pub path: String,
    /// Origins a browser may connect from (`https://hmi.example:8443`); None: any. A request
    /// without `Origin` (not from a browser) is not checked: it carries no page whose
    /// script could be abusing the user's browser.
    pub allowed_origins: Option<Vec<String>>,
}

/// A handshake fbbus refused: the reason is a label of `fbbus_connects_refused_total`.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
#[error("{detail}")]
pub struct Refused {
    pub reason: &'static str,
    pub detail: String,
}

fn refused(reason: &'static str, detail: impl Into<String>) -> Refused {
    Refused {
        reason,
        detail: detail.into(),
    }
}

impl Handshake {
    /// Checks an upgrade request: the subprotocol to answer with, or why not.
    fn check(&self, request: &Request) -> Result<&'static str, Refused> {
        let path = request.uri().path();
        if path != self.path {
            return Err(refused(
                "ws_path",
                format!(
                    "path {path:?}; this listener serves MQTT on {:?}",
                    self.path
                ),
            ));
        }
        if let (Some(allowed), Some(origin)) =
            (&self.allowed_origins, request.headers().get(header::ORIGIN))
        {
            let origin = origin.to_str().unwrap_or("");
            if !allowed.iter().any(|a| a.eq_ignore_ascii_case(origin)) {
                return Err(refused(
                    "ws_origin",
                    format!("origin {origin:?} is not in this listener's allowed_origins"),
                ));
            }
        }
        let offered: Vec<&str> = request
            .headers()
            .get_all(header::SEC_WEBSOCKET_PROTOCOL)
            .iter()
            .filter_map(|v| v.to_str().ok())
            .flat_map(|v| v.split(','))
            .map(str::trim)
            .collect();
        // `mqtt` whenever offered, whatever the order: the server must choose it
        // [MQTT-6.0.0-4]; `mqttv3.1` only for a client that offers no `mqtt`.
        for known in SUBPROTOCOLS {
            if offered.iter().any(|name| name.eq_ignore_ascii_case(known)) {
                return Ok(known);
            }
        }
        Err(refused(
            "ws_subprotocol",
            "no subprotocol `mqtt` (or `mqttv3.1`) offered in Sec-WebSocket-Protocol",
        ))
    }
}

/// The tungstenite limits for a session whose packets are at most `max_packet` bytes.
fn config(max_packet: usize) -> WebSocketConfig {
    // A message holds at least one packet (at most `max_packet` bytes with its fixed
    // header), and clients sometimes put a few small ones in one message: 64 KiB at least.
    let max_message = max_packet.max(64 * 1024);
    WebSocketConfig::default()
        .read_buffer_size(READ_BUFFER)
        // Every message is handed to the socket at once: the session batches its packets
        // into one write already, and its write deadline must see a socket that waits.
        .write_buffer_size(0)
        .max_message_size(Some(max_message))
        .max_frame_size(Some(max_message))
}

/// Completes the WebSocket handshake on an accepted (and, for `wss`, TLS) connection.
///
/// An MQTT CONNECT or a TLS hello where the HTTP upgrade request belongs is refused with
/// a reason that says so, not as a malformed request.
// The handshake callback's error is tungstenite's `ErrorResponse` (an HTTP response), by
// its `Callback` trait: not ours to make smaller.
#[allow(clippy::result_large_err)]
pub async fn accept(
    stream: Box<dyn Stream>,
    tls: bool,
    handshake: &Handshake,
    max_packet: usize,
) -> Result<WsStream, Refused> {
    let mut stream = stream;
    let mut first = [0u8; 1];
    match stream.read(&mut first).await {
        Ok(1) => {}
        _ => {
            return Err(refused(
                "closed_before_connect",
                "closed before the handshake",
            ))
        }
    }
    match first[0] {
        0x10 => {
            return Err(refused(
                "mqtt_on_websocket",
                format!(
                    "an MQTT CONNECT reached a WebSocket listener: connect with {}://HOST:PORT{} \
                     or to a plain MQTT listener",
                    if tls { "wss" } else { "ws" },
                    handshake.path
                ),
            ))
        }
        0x16 if !tls => {
            return Err(refused(
                "tls_on_plain",
                "a TLS hello reached a WebSocket listener without TLS: use ws://, or give \
                 the listener a [listener.tls] for wss://",
            ))
        }
        _ => {}
    }
    let mut verdict = None;
    let callback = |request: &Request, mut response: Response| match handshake.check(request) {
        Ok(subprotocol) => {
            response.headers_mut().insert(
                header::SEC_WEBSOCKET_PROTOCOL,
                HeaderValue::from_static(subprotocol),
            );
            Ok(response)
        }
        Err(why) => {
            let status = match why.reason {
                "ws_path" => StatusCode::NOT_FOUND,
                "ws_origin" => StatusCode::FORBIDDEN,
                _ => StatusCode::BAD_REQUEST,
            };
            let mut error = ErrorResponse::new(Some(format!("{}\n", why.detail)));
            *error.status_mut() = status;
            // The detail quotes the request (its path, its origin): plain text only.
            error.headers_mut().insert(
                header::CONTENT_TYPE,
                HeaderValue::from_static("text/plain; charset=utf-8"),
            );
            verdict = Some(why);
            Err(error)
        }
    };
    let prefixed = Prefixed {
        first: Some(first[0]),
        inner: stream,
    };
    match tokio_tungstenite::accept_hdr_async_with_config(
        prefixed,
        callback,
        Some(config(max_packet)),
    )
    .await
    {
        Ok(ws) => Ok(WsStream {
            ws,
            pending: Bytes::new(),
        }),
        Err(error) => Err(verdict.unwrap_or_else(|| {
            refused(
                "ws_handshake",
                format!("WebSocket handshake failed: {error}"),
            )
        })),
    }
}

/// The stream with its first byte, read to tell an HTTP request from MQTT or TLS, put back.
struct Prefixed {
    first: Option<u8>,
    inner: Box<dyn Stream>,
}

impl AsyncRead for Prefixed {
    fn poll_read(
        mut self: Pin<&mut Self>,
        cx: &mut Context<'_>,
        buf: &mut ReadBuf<'_>,
    ) -> Poll<io::Result<()>> {
        if let Some(byte) = self.first {
            if buf.remaining() > 0 {
                buf.put_slice(&[byte]);
                self.first = None;
            }
            return Poll::Ready(Ok(()));
        }
        Pin::new(&mut self.inner).poll_read(cx, buf)
    }
}

impl AsyncWrite for Prefixed {
    fn poll_write(
        mut self: Pin<&mut Self>,
        cx: &mut Context<'_>,
        buf: &[u8],
    ) -> Poll<io::Result<usize>> {
        Pin::new(&mut self.inner).poll_write(cx, buf)
    }

    fn poll_flush(mut self: Pin<&mut Self>, cx: &mut Context<'_>) -> Poll<io::Result<()>> {
        Pin::new(&mut self.inner).poll_flush(cx)
    }

    fn poll_shutdown(mut self: Pin<&mut Self>, cx: &mut Context<'_>) -> Poll<io::Result<()>> {
        Pin::new(&mut self.inner).poll_shutdown(cx)
    }
}

/// A WebSocket connection as the byte stream MQTT runs over: binary messages in, read
/// as bytes; bytes written, sent as binary messages.
pub struct WsStream {
    ws: WebSocketStream<Prefixed>,
    /// The rest of the last binary message received, not read yet.
    pending: Bytes,
}

fn io_error(error: WsError) -> io::Error {
    match error {
        WsError::Io(e) => e,
        WsError::ConnectionClosed | WsError::AlreadyClosed => ErrorKind::BrokenPipe.into(),
        other => io::Error::new(ErrorKind::InvalidData, other),
    }
}

impl AsyncRead for WsStream {
    fn poll_read(
        mut self: Pin<&mut Self>,
        cx: &mut Context<'_>,
        buf: &mut ReadBuf<'_>,
    ) -> Poll<io::Result<()>> {
        loop {
            if !self.pending.is_empty() {
                let n = self.pending.len().min(buf.remaining());
                let chunk = self.pending.split_to(n);
                buf.put_slice(&chunk);
                return Poll::Ready(Ok(()));
            }
            match ready!(Pin::new(&mut self.ws).poll_next(cx)) {
                // The peer closed, or the connection ended: end of stream.
                None | Some(Ok(Message::Close(_))) => return Poll::Ready(Ok(())),
                Some(Ok(Message::Binary(data))) => self.pending = data,
                // MQTT 5.0 §6: any other data frame closes the connection.
                Some(Ok(Message::Text(_))) => {
                    return Poll::Ready(Err(io::Error::new(
                        ErrorKind::InvalidData,
                        "a text WebSocket message: MQTT travels in binary messages",
                    )))
                }
                // Pings are answered by tungstenite itself.
                Some(Ok(Message::Ping(_) | Message::Pong(_) | Message::Frame(_))) => {}
                Some(Err(e)) => return Poll::Ready(Err(io_error(e))),
            }
        }
    }
}

impl AsyncWrite for WsStream {
    fn poll_write(
        mut self: Pin<&mut Self>,
        cx: &mut Context<'_>,
        buf: &[u8],
    ) -> Poll<io::Result<usize>> {
        // Only once the last message is out (or with the socket's room): a peer that takes
        // nothing leaves this Pending, and the session's write deadline runs.
        ready!(Pin::new(&mut self.ws).poll_ready(cx)).map_err(io_error)?;
        let n = buf.len().min(MAX_OUT_MESSAGE);
        let message = Message::Binary(Bytes::copy_from_slice(&buf[..n]));
        Pin::new(&mut self.ws)
            .start_send(message)
            .map_err(io_error)?;
        Poll::Ready(Ok(n))
    }

    fn poll_flush(mut self: Pin<&mut Self>, cx: &mut Context<'_>) -> Poll<io::Result<()>> {
        Pin::new(&mut self.ws).poll_flush(cx).map_err(io_error)
    }

    fn poll_shutdown(mut self: Pin<&mut Self>, cx: &mut Context<'_>) -> Poll<io::Result<()>> {
        Pin::new(&mut self.ws).poll_close(cx).map_err(io_error)
    }
}

/// The log line for a refused handshake.
pub fn log_refused(listener: &str, peer: SocketAddr, why: &Refused) {
    tracing::info!(listener, %peer, reason = why.reason, detail = %why.detail,
        "WebSocket connection refused");
}

#[cfg(test)]
mod tests {
    use super::*;

    fn request(path: &str, headers: &[(&str, &str)]) -> Request {
        let mut r = Request::builder().uri(path);
        for (k, v) in headers {
            r = r.header(*k, *v);
        }
        r.body(()).unwrap()
    }

    #[test]
    fn the_handshake_wants_the_path_a_known_subprotocol_and_an_allowed_origin() {
        let open = Handshake {
            path: DEFAULT_PATH.into(),
            allowed_origins: None,
        };
        let proto = "Sec-WebSocket-Protocol";
        assert_eq!(
            open.check(&request("/mqtt", &[(proto, "mqtt")])),
            Ok("mqtt")
        );
        assert_eq!(
            open.check(&request("/mqtt?x=1", &[(proto, "foo, MQTTv3.1")])),
            Ok("mqttv3.1")
        );
        assert_eq!(
            open.check(&request("/mqtt", &[(proto, "mqttv3.1, mqtt")])),
            Ok("mqtt")
        );
        let reason = |r: Result<&str, Refused>| r.unwrap_err().reason;
        assert_eq!(
            reason(open.check(&request("/", &[(proto, "mqtt")]))),
            "ws_path"
        );
        assert_eq!(reason(open.check(&request("/mqtt", &[]))), "ws_subprotocol");
        assert_eq!(
            reason(open.check(&request("/mqtt", &[(proto, "wamp")]))),
            "ws_subprotocol"
        );
        let hmi = Handshake {
            allowed_origins: Some(vec!["https://hmi.example".into()]),
            ..open
        };
        let from = |origin| request("/mqtt", &[(proto, "mqtt"), ("Origin", origin)]);
        assert_eq!(hmi.check(&from("https://HMI.example")), Ok("mqtt"));
        assert_eq!(
            reason(hmi.check(&from("https://evil.example"))),
            "ws_origin"
        );
        // Not a browser: no page to guard against.
        assert_eq!(hmi.check(&request("/mqtt", &[(proto, "mqtt")])), Ok("mqtt"));
    }

    #[test]
    fn messages_are_bounded_by_the_packet_limit() {
        let c = config(1 << 20);
        assert_eq!(c.max_message_size, Some(1 << 20));
        assert_eq!(c.max_frame_size, Some(1 << 20));
        assert_eq!(config(1024).max_message_size, Some(64 * 1024));
    }
}

//! A relay in the harness between the scenarios' raw MQTT clients and a broker: plain TCP
//! to the broker's TCP port, or MQTT over WebSockets to its `ws://.../mqtt` port.
//!
//! Why a relay (issue 35): every scenario speaks MQTT on a `TcpStream`; the relay lets
//! `compare --transport` run them unchanged over WebSockets, one WebSocket connection per
//! client connection, each read from the client sent as one binary message. The relay
//! is a hop of its own, so WebSockets are compared with the same hop in plain TCP
//! (`tcp-relay`): the ratio ws / tcp-relay is what the WebSocket framing costs on both
//! sides, the broker's included, and the brokers' rows compare their WebSocket listeners.
//! Loopback only, like every connection of the harness.

use std::net::SocketAddr;

use futures_util::{SinkExt, StreamExt};
use tokio::io::{AsyncReadExt, AsyncWriteExt};
use tokio::net::{TcpListener, TcpStream};
use tokio::task::JoinSet;
use tokio_tungstenite::tungstenite::client::IntoClientRequest;
use tokio_tungstenite::tungstenite::http::HeaderValue;
use tokio_tungstenite::tungstenite::Message;

/// Where the relay forwards each connection.
#[derive(Debug, Clone)]
pub enum Upstream {
    /// The broker's MQTT port, byte for byte.
    Tcp(SocketAddr),
    /// The broker's MQTT-over-WebSockets port: `ws://<addr><path>`, subprotocol `mqtt`.
    WebSocket { addr: SocketAddr, path: String },
}

/// A running relay; stops (with every connection it carries) when dropped.
pub struct Relay {
    pub addr: SocketAddr,
    task: tokio::task::JoinHandle<()>,
}

impl Drop for Relay {
    fn drop(&mut self) {
        self.task.abort();
    }
}

/// Starts a relay on a free 127.0.0.1 port.
pub async fn start(upstream: Upstream) -> std::io::Result<Relay> {
    let listener = TcpListener::bind("127.0.0.1:0").await?;
    let addr = listener.local_addr()?;
    let task = tokio::spawn(async move {
        // Dropped with the accept loop: every connection's task ends with the relay.
        let mut connections = JoinSet::new();
        loop {
            tokio::select! {
                accepted = listener.accept() => {
                    let Ok((client, _)) = accepted else { continue };
                    let upstream = upstream.clone();
                    connections.spawn(async move {
                        let _ = client.set_nodelay(true);
                        let _ = match upstream {
                            Upstream::Tcp(addr) => tcp(client, addr).await,
                            Upstream::WebSocket { addr, path } => websocket(client, addr, &path).await,
                        };
                    });
                }
                Some(_) = connections.join_next(), if !connections.is_empty() => {}
            }
        }
    });
    Ok(Relay { addr, task })
}

async fn tcp(mut client: TcpStream, addr: SocketAddr) -> std::io::Result<()> {
    let mut broker = TcpStream::connect(addr).await?;
    broker.set_nodelay(true)?;
    tokio::io::copy_bidirectional(&mut client, &mut broker).await?;
    Ok(())
}

async fn websocket(client: TcpStream, addr: SocketAddr, path: &str) -> std::io::Result<()> {
    let other = |e: tokio_tungstenite::tungstenite::Error| std::io::Error::other(e.to_string());
    let stream = TcpStream::connect(addr).await?;
    stream.set_nodelay(true)?;
    let mut request = format!("ws://{addr}{path}")
        .into_client_request()
        .map_err(other)?;
    request
        .headers_mut()
        .insert("Sec-WebSocket-Protocol", HeaderValue::from_static("mqtt"));
    let (ws, _) = tokio_tungstenite::client_async(request, stream)
        .await
        .map_err(other)?;
    let (mut to_broker, mut from_broker) = ws.split();
    let (mut from_client, mut to_client) = client.into_split();
    let up = async {
        let mut buf = vec![0u8; 64 * 1024];
        loop {
            let n = from_client.read(&mut buf).await?;
            if n == 0 {
                let _ = to_broker.close().await;
                return Ok::<(), std::io::Error>(());
            }
            to_broker
                .send(Message::binary(buf[..n].to_vec()))
                .await
                .map_err(other)?;
        }
    };
    let down = async {
        while let Some(message) = from_broker.next().await {
            match message.map_err(other)? {
                Message::Binary(bytes) => to_client.write_all(&bytes).await?,
                Message::Close(_) => break,
                _ => {}
            }
        }
        to_client.shutdown().await
    };
    tokio::select! {
        r = up => r,
        r = down => r,
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A WebSocket server that answers each binary message with the same bytes, checking
    /// the path and subprotocol the relay asks for.
    // tungstenite's handshake callback returns its error response by value.
    #[allow(clippy::result_large_err)]
    async fn ws_echo() -> SocketAddr {
        let listener = TcpListener::bind("127.0.0.1:0").await.unwrap();
        let addr = listener.local_addr().unwrap();
        tokio::spawn(async move {
            let (stream, _) = listener.accept().await.unwrap();
            let check = |req: &tokio_tungstenite::tungstenite::handshake::server::Request,
                         mut resp: tokio_tungstenite::tungstenite::handshake::server::Response| {
                assert_eq!(req.uri().path(), "/mqtt");
                assert_eq!(req.headers()["Sec-WebSocket-Protocol"], "mqtt");
                resp.headers_mut()
                    .insert("Sec-WebSocket-Protocol", HeaderValue::from_static("mqtt"));
                Ok(resp)
            };
            let mut ws = tokio_tungstenite::accept_hdr_async(stream, check)
                .await
                .unwrap();
            while let Some(Ok(message)) = ws.next().await {
                if let Message::Binary(bytes) = message {
                    ws.send(Message::Binary(bytes)).await.unwrap();
                }
            }
        });
        addr
    }

    async fn round_trip(relay: &Relay) -> Vec<u8> {
        let mut client = TcpStream::connect(relay.addr).await.unwrap();
        client.write_all(b"\x10\x02ab").await.unwrap();
        let mut back = [0u8; 4];
        tokio::time::timeout(
            std::time::Duration::from_secs(5),
            client.read_exact(&mut back),
        )
        .await
        .expect("an answer through the relay")
        .unwrap();
        back.to_vec()
    }

    #[tokio::test]
    async fn bytes_cross_the_websocket_relay_both_ways() {
        let relay = start(Upstream::WebSocket {
            addr: ws_echo().await,
            path: "/mqtt".into(),
        })
        .await
        .unwrap();
        assert_eq!(round_trip(&relay).await, b"\x10\x02ab");
    }

    #[tokio::test]
    async fn bytes_cross_the_tcp_relay_both_ways() {
        let listener = TcpListener::bind("127.0.0.1:0").await.unwrap();
        let addr = listener.local_addr().unwrap();
        tokio::spawn(async move {
            let (mut s, _) = listener.accept().await.unwrap();
            let mut buf = [0u8; 4];
            s.read_exact(&mut buf).await.unwrap();
            s.write_all(&buf).await.unwrap();
        });
        let relay = start(Upstream::Tcp(addr)).await.unwrap();
        assert_eq!(round_trip(&relay).await, b"\x10\x02ab");
    }
}

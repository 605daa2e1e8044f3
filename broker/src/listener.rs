//! A listener: accepts TCP connections, completes TLS if configured, enforces the
//! connection limit, completes the WebSocket handshake on a `ws` listener
//! ([`crate::websocket`]), and hands each connection to `session::serve` on its own task.
//!
//! Unlike rumqttd's `Server`, it does not pause between accepts: a line that comes back
//! after a power cut reconnects all at once, and the limit that matters is
//! `max_connections`, enforced with a semaphore so a refused connection costs nothing.
//! Nagle is turned off: MQTT messages on a line are small and latency matters more than
//! packet count.
//!
//! Every accepted socket gets TCP keep-alive and `TCP_USER_TIMEOUT` from
//! `broker.dead_link_timeout_s` ([`dead_link_options`]), so the kernel notices a peer that
//! vanished (power cut, pulled cable) even when the client asked for no MQTT keep-alive,
//! and even with data in flight, instead of retransmitting for ~15 minutes (Linux's
//! `tcp_retries2`).
//!
//! These options are set once, on the listening socket: Linux gives an accepted socket
//! a copy of its listener's, so a connection storm does not pay six `setsockopt` calls per
//! connection (4 % of the worker's time in a storm's profile). The first accepted socket
//! is checked ([`Inheritance`]); where a kernel does not pass them on, every accepted
//! socket gets them itself, as before.

use std::net::SocketAddr;
use std::pin::Pin;
use std::sync::Arc;
use std::task::{Context, Poll};
use std::time::{Duration, Instant};

use serde::Deserialize;
use tokio::io::{AsyncRead, AsyncWrite, ReadBuf};
use tokio::net::TcpListener;
use tokio::sync::Semaphore;
use tokio_rustls::TlsAcceptor;

use crate::authenticator::AuthSection;
use crate::metrics::Metrics;
use crate::session;
use crate::tls::TlsSection;
use crate::websocket;
use crate::wire::framed::Stream;

#[derive(Debug, Clone, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ListenerSection {
    pub name: String,
    pub bind: SocketAddr,
    /// What clients speak: MQTT over TCP (the default), or over WebSockets.
    #[serde(default)]
    pub kind: ListenerKind,
    /// Clients without a username may connect. Only allowed on a loopback address.
    /// Defaults to true when there is no password file.
    pub allow_anonymous: Option<bool>,
    pub tls: Option<TlsSection>,
    /// `ws` only: the HTTP path of the upgrade request (default `/mqtt`).
    pub path: Option<String>,
    /// `ws` only: the origins browsers may connect from; unset: any.
    pub allowed_origins: Option<Vec<String>>,
}

/// A listener's transport. `wss` is `ws` with the listener's `[listener.tls]`: it is
/// accepted as a name too, and then needs the TLS section.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum ListenerKind {
    #[default]
    Mqtt,
    Ws,
    Wss,
}

impl ListenerKind {
    /// The label of the per-listener metrics and log lines: mqtt, mqtts, ws or wss.
    pub fn transport(self, tls: bool) -> &'static str {
        match (self, tls) {
            (ListenerKind::Mqtt, false) => "mqtt",
            (ListenerKind::Mqtt, true) => "mqtts",
            (_, false) => "ws",
            (_, true) => "wss",
        }
    }
}

impl ListenerSection {
    /// Whether clients without credentials are let in on this listener.
    pub fn anonymous(&self, auth: &AuthSection) -> bool {
        self.allow_anonymous.unwrap_or(auth.password_file.is_none())
    }

    /// The handshake a WebSocket listener checks; None for plain MQTT.
    pub fn websocket(&self) -> Option<websocket::Handshake> {
        (self.kind != ListenerKind::Mqtt).then(|| websocket::Handshake {
            path: self
                .path
                .clone()
                .unwrap_or_else(|| websocket::DEFAULT_PATH.to_owned()),
            allowed_origins: self.allowed_origins.clone(),
        })
    }

    /// The configuration mistakes of this listener's kind: (key, message).
    pub fn validate_kind(&self) -> Result<(), (&'static str, String)> {
        if self.kind == ListenerKind::Mqtt {
            for (key, set) in [
                ("path", self.path.is_some()),
                ("allowed_origins", self.allowed_origins.is_some()),
            ] {
                if set {
                    return Err((key, "only applies to a listener with kind = \"ws\"".into()));
                }
            }
        }
        if self.kind == ListenerKind::Wss && self.tls.is_none() {
            return Err((
                "tls",
                "kind = \"wss\" needs a [listener.tls] section (cert and key)".into(),
            ));
        }
        if let Some(path) = &self.path {
            if !path.starts_with('/') || path.contains(['?', '#', ' ']) {
                return Err((
                    "path",
                    format!("{path:?} is not an HTTP path such as \"/mqtt\""),
                ));
            }
        }
        if let Some(origins) = &self.allowed_origins {
            if let Some(bad) = origins
                .iter()
                .find(|o| !o.contains("://") || o.ends_with('/'))
            {
                return Err((
                    "allowed_origins",
                    format!("{bad:?} is not an origin such as \"https://hmi.example:8443\" (scheme, host, optional port, no path)"),
                ));
            }
        }
        Ok(())
    }
}

pub struct Listener {
    pub policy: Arc<session::ListenerPolicy>,
    pub socket: TcpListener,
    pub tls: Option<TlsAcceptor>,
    /// Set on a WebSocket listener: the handshake it checks.
    pub websocket: Option<Arc<websocket::Handshake>>,
}

impl Listener {
    pub fn local_addr(&self) -> SocketAddr {
        self.socket
            .local_addr()
            .expect("a bound listener has an address")
    }

    /// Accepts connections until the broker shuts down.
    pub async fn run(self, ctx: Arc<session::Context>, slots: Arc<Semaphore>) {
        let mut shutdown = ctx.shutdown.clone();
        let mut options = Inheritance::set_on_listener(&self.socket, ctx.dead_link);
        let (mut last_warning, mut refused_unlogged) = (None, 0u64);
        let (mut last_pending_warning, mut pending_unlogged) = (None, 0u64);
        loop {
            let (tcp, peer) = tokio::select! {
                _ = shutdown.changed() => return,
                accepted = self.socket.accept() => match accepted {
                    Ok(a) => a,
                    Err(e) => {
                        // EMFILE and friends: log, breathe, and keep serving the others.
                        tracing::error!(listener = &*self.policy.name, error = %e, "accept failed");
                        tokio::time::sleep(Duration::from_millis(50)).await;
                        continue;
                    }
                },
            };
            // Before a slot: a stranger holding sockets that never finish CONNECT must not
            // hold the slots a reconnecting device needs (`pending`).
            let Some(pending) = ctx.pending.enter(peer.ip()) else {
                ctx.metrics.refused("pending_per_address");
                pending_unlogged += 1;
                if last_pending_warning
                    .is_none_or(|t: Instant| t.elapsed() >= Duration::from_secs(60))
                {
                    last_pending_warning = Some(Instant::now());
                    tracing::warn!(
                        listener = &*self.policy.name,
                        %peer,
                        refused = pending_unlogged,
                        "too many connections from this address that have not sent CONNECT \
                         ([broker] max_pending_per_address); new ones are closed at once \
                         (fbbus_connects_refused_total{{reason=\"pending_per_address\"}}, \
                         logged once a minute)"
                    );
                    pending_unlogged = 0;
                }
                continue;
            };
            let Ok(slot) = Arc::clone(&slots).try_acquire_owned() else {
                ctx.metrics.refused("max_connections");
                // Logged once a minute, with how many were refused since: a flood of
                // connections must not become a flood of log lines.
                refused_unlogged += 1;
                if last_warning.is_none_or(|t: Instant| t.elapsed() >= Duration::from_secs(60)) {
                    last_warning = Some(Instant::now());
                    tracing::warn!(
                        listener = &*self.policy.name,
                        %peer,
                        refused = refused_unlogged,
                        "connection limit reached (fbbus_connection_limit: [broker] \
                         max_connections, or the open-file limit); new connections are closed \
                         at once (fbbus_connects_refused_total{{reason=\"max_connections\"}})"
                    );
                    refused_unlogged = 0;
                }
                continue;
            };
            options.apply(&tcp, peer, ctx.dead_link);
            let ctx = Arc::clone(&ctx);
            let policy = Arc::clone(&self.policy);
            let tls = self.tls.clone();
            let websocket = self.websocket.clone();
            tokio::spawn(async move {
                let secure = tls.is_some();
                let stream: Box<dyn Stream> = match tls {
                    None => Box::new(tcp),
                    Some(acceptor) => {
                        match tokio::time::timeout(ctx.connect_timeout, acceptor.accept(tcp)).await
                        {
                            Ok(Ok(tls)) => Box::new(tls),
                            Ok(Err(e)) => {
                                ctx.metrics.refused("tls_handshake");
                                tracing::info!(%peer, error = %e, "TLS handshake failed");
                                return;
                            }
                            Err(_) => {
                                ctx.metrics.refused("tls_handshake");
                                return;
                            }
                        }
                    }
                };
                let stream: Box<dyn Stream> = match websocket {
                    None => stream,
                    Some(handshake) => {
                        let accepted = tokio::time::timeout(
                            ctx.connect_timeout,
                            websocket::accept(stream, secure, &handshake, ctx.max_packet),
                        )
                        .await;
                        match accepted {
                            Ok(Ok(ws)) => Box::new(ws),
                            Ok(Err(why)) => {
                                ctx.metrics.refused(why.reason);
                                websocket::log_refused(&policy.name, peer, &why);
                                return;
                            }
                            Err(_) => {
                                ctx.metrics.refused("connect_timeout");
                                tracing::debug!(%peer, "no WebSocket handshake in time; closed");
                                return;
                            }
                        }
                    }
                };
                let stream = Box::new(Counted::new(&ctx.metrics, &policy, stream));
                session::serve(stream, peer, policy, ctx, slot, pending).await;
            });
        }
    }
}

/// A connection counted in its listener's `fbbus_listener_connections` for as long as its
/// stream lives: the session drops it when the connection ends, however it ends.
struct Counted {
    inner: Box<dyn Stream>,
    open: prometheus::IntGauge,
}

impl Counted {
    fn new(metrics: &Metrics, policy: &session::ListenerPolicy, inner: Box<dyn Stream>) -> Self {
        let labels = [&*policy.name, policy.transport];
        metrics.listener_accepted.with_label_values(&labels).inc();
        let open = metrics.listener_connections.with_label_values(&labels);
        open.inc();
        Counted { inner, open }
    }
}

impl Drop for Counted {
    fn drop(&mut self) {
        self.open.dec();
    }
}

impl AsyncRead for Counted {
    fn poll_read(
        mut self: Pin<&mut Self>,
        cx: &mut Context<'_>,
        buf: &mut ReadBuf<'_>,
    ) -> Poll<std::io::Result<()>> {
        Pin::new(&mut self.inner).poll_read(cx, buf)
    }
}

impl AsyncWrite for Counted {
    fn poll_write(
        mut self: Pin<&mut Self>,
        cx: &mut Context<'_>,
        buf: &[u8],
    ) -> Poll<std::io::Result<usize>> {
        Pin::new(&mut self.inner).poll_write(cx, buf)
    }

    fn poll_flush(mut self: Pin<&mut Self>, cx: &mut Context<'_>) -> Poll<std::io::Result<()>> {
        Pin::new(&mut self.inner).poll_flush(cx)
    }

    fn poll_shutdown(mut self: Pin<&mut Self>, cx: &mut Context<'_>) -> Poll<std::io::Result<()>> {
        Pin::new(&mut self.inner).poll_shutdown(cx)
    }
}

/// Whether accepted sockets come with the options set on their listener (no Nagle, the
/// dead-link options), or must each be given them.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Inheritance {
    /// Set on the listener; the first accepted socket tells whether they were passed on.
    Unchecked,
    Inherited,
    PerSocket,
}

impl Inheritance {
    /// Sets the accepted sockets' options on the listening socket: `PerSocket` when that
    /// failed, so each accepted socket is given them.
    fn set_on_listener(listener: &TcpListener, dead_link: Option<Duration>) -> Inheritance {
        let socket = socket2::SockRef::from(listener);
        let set = socket
            .set_tcp_nodelay(true)
            .and_then(|()| dead_link.map_or(Ok(()), |t| dead_link_options(&socket, t)));
        match set {
            Ok(()) => Inheritance::Unchecked,
            Err(_) => Inheritance::PerSocket,
        }
    }

    /// Gives an accepted socket its options, unless it came with them.
    fn apply(
        &mut self,
        tcp: &tokio::net::TcpStream,
        peer: SocketAddr,
        dead_link: Option<Duration>,
    ) {
        let socket = socket2::SockRef::from(tcp);
        if *self == Inheritance::Unchecked {
            *self = if has_options(&socket, dead_link) {
                Inheritance::Inherited
            } else {
                tracing::debug!(
                    "accepted sockets do not inherit their listener's options; set on each"
                );
                Inheritance::PerSocket
            };
        }
        if *self == Inheritance::Inherited {
            return;
        }
        let _ = socket.set_tcp_nodelay(true);
        if let Some(timeout) = dead_link {
            if let Err(e) = dead_link_options(&socket, timeout) {
                tracing::warn!(%peer, error = %e, "TCP keep-alive or user timeout not set");
            }
        }
    }
}

/// The socket has no Nagle and, with `dead_link`, its keep-alive and user timeout.
fn has_options(socket: &socket2::SockRef<'_>, dead_link: Option<Duration>) -> bool {
    let nodelay = socket.tcp_nodelay().unwrap_or(false);
    let dead_link_set = match dead_link {
        None => true,
        Some(timeout) => {
            let keepalive = socket.keepalive().unwrap_or(false)
                && socket.tcp_keepalive_time().ok().map(|t| t.as_secs())
                    == Some(keepalive_idle(timeout).as_secs());
            #[cfg(target_os = "linux")]
            let user_timeout = socket.tcp_user_timeout().ok() == Some(Some(timeout));
            #[cfg(not(target_os = "linux"))]
            let user_timeout = true;
            keepalive && user_timeout
        }
    };
    nodelay && dead_link_set
}

/// How long a connection is idle before its first keep-alive probe.
fn keepalive_idle(timeout: Duration) -> Duration {
    (timeout / 2).max(Duration::from_secs(1))
}

/// Makes the kernel end a connection whose peer stopped answering for `timeout`:
///
/// - `TCP_USER_TIMEOUT` = `timeout`: data sent and not acknowledged for that long ends the
///   connection (`ETIMEDOUT`), instead of the ~15 minutes of retransmissions Linux allows
///   by default; since Linux 5.11 it also ends a peer that keeps advertising a zero window
///   for that long.
/// - TCP keep-alive: an idle connection is probed after `timeout / 2`, then every
///   `max(1 s, timeout / 10)`; with the user timeout set, the kernel ends it at the first
///   probe `timeout` after the peer was last heard. So an idle peer that vanished is gone
///   within `timeout + max(1 s, timeout / 10)`, MQTT keep-alive or not.
///
/// The session's read or write then fails and it ends as a lost connection, its will
/// published.
pub fn dead_link_options(socket: &socket2::SockRef<'_>, timeout: Duration) -> std::io::Result<()> {
    let idle = keepalive_idle(timeout);
    let interval = (timeout / 10).max(Duration::from_secs(1));
    let keepalive = socket2::TcpKeepalive::new()
        .with_time(idle)
        .with_interval(interval)
        // Only used when no user timeout is in force; the user timeout decides otherwise.
        .with_retries(5);
    socket.set_tcp_keepalive(&keepalive)?;
    #[cfg(target_os = "linux")]
    socket.set_tcp_user_timeout(Some(timeout))?;
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Accepts one loopback connection on `listener`.
    async fn accept_one(listener: &TcpListener) -> tokio::net::TcpStream {
        let addr = listener.local_addr().unwrap();
        let client = tokio::net::TcpStream::connect(addr);
        let (accepted, _client) = tokio::join!(listener.accept(), client);
        accepted.unwrap().0
    }

    /// The storm saving rests on the kernel copying a listener's options into the sockets
    /// it accepts: checked here on the machine that runs the tests (Linux does).
    #[tokio::test]
    async fn accepted_sockets_carry_the_options_set_on_their_listener() {
        let timeout = Duration::from_secs(15);
        let listener = TcpListener::bind("127.0.0.1:0").await.unwrap();
        let plain = accept_one(&listener).await;
        assert!(
            !has_options(&socket2::SockRef::from(&plain), Some(timeout)),
            "a socket accepted before the options were set must not look set"
        );
        let mut inheritance = Inheritance::set_on_listener(&listener, Some(timeout));
        assert_eq!(inheritance, Inheritance::Unchecked);
        let tcp = accept_one(&listener).await;
        inheritance.apply(&tcp, "127.0.0.1:1".parse().unwrap(), Some(timeout));
        assert_eq!(inheritance, Inheritance::Inherited);
        let socket = socket2::SockRef::from(&tcp);
        assert!(socket.tcp_nodelay().unwrap());
        assert!(socket.keepalive().unwrap());
        assert_eq!(socket.tcp_keepalive_time().unwrap(), Duration::from_secs(7));
        assert_eq!(
            socket.tcp_keepalive_interval().unwrap(),
            Duration::from_secs(1)
        );
        assert_eq!(socket.tcp_user_timeout().unwrap(), Some(timeout));
    }

    /// Where the listener's options are not passed on, each accepted socket is given them.
    #[tokio::test]
    async fn a_socket_without_its_listeners_options_is_given_them() {
        let timeout = Duration::from_secs(20);
        let listener = TcpListener::bind("127.0.0.1:0").await.unwrap();
        let tcp = accept_one(&listener).await;
        let mut inheritance = Inheritance::Unchecked;
        inheritance.apply(&tcp, "127.0.0.1:1".parse().unwrap(), Some(timeout));
        assert_eq!(inheritance, Inheritance::PerSocket);
        assert!(has_options(&socket2::SockRef::from(&tcp), Some(timeout)));
    }
}

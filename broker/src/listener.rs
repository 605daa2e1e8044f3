//! A listener: accepts TCP connections, completes TLS if configured, enforces the
//! connection limit, and hands each connection to `session::serve` on its own task.
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

use std::net::SocketAddr;
use std::sync::Arc;
use std::time::{Duration, Instant};

use serde::Deserialize;
use tokio::net::TcpListener;
use tokio::sync::Semaphore;
use tokio_rustls::TlsAcceptor;

use crate::authenticator::AuthSection;
use crate::session;
use crate::session::Context;
use crate::tls::TlsSection;
use crate::wire::framed::Stream;

#[derive(Debug, Clone, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ListenerSection {
    pub name: String,
    pub bind: SocketAddr,
    /// Clients without a username may connect. Only allowed on a loopback address.
    /// Defaults to true when there is no password file.
    pub allow_anonymous: Option<bool>,
    pub tls: Option<TlsSection>,
}

impl ListenerSection {
    /// Whether clients without credentials are let in on this listener.
    pub fn anonymous(&self, auth: &AuthSection) -> bool {
        self.allow_anonymous.unwrap_or(auth.password_file.is_none())
    }
}

pub struct Listener {
    pub policy: Arc<session::ListenerPolicy>,
    pub socket: TcpListener,
    pub tls: Option<TlsAcceptor>,
}

impl Listener {
    pub fn local_addr(&self) -> SocketAddr {
        self.socket
            .local_addr()
            .expect("a bound listener has an address")
    }

    /// Accepts connections until the broker shuts down.
    pub async fn run(self, ctx: Arc<Context>, slots: Arc<Semaphore>) {
        let mut shutdown = ctx.shutdown.clone();
        let (mut last_warning, mut refused_unlogged) = (None, 0u64);
        let (mut last_pending_warning, mut pending_unlogged) = (None, 0u64);
        loop {
            let (tcp, peer) = tokio::select! {
                _ = shutdown.changed() => return,
                accepted = self.socket.accept() => match accepted {
                    Ok(a) => a,
                    Err(e) => {
                        // EMFILE and friends: log, breathe, and keep serving the others.
                        tracing::error!(listener = self.policy.name, error = %e, "accept failed");
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
                        listener = self.policy.name,
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
                        listener = self.policy.name,
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
            let _ = tcp.set_nodelay(true);
            if let Some(timeout) = ctx.dead_link {
                if let Err(e) = dead_link_options(&tcp, timeout) {
                    tracing::warn!(%peer, error = %e, "TCP keep-alive or user timeout not set");
                }
            }
            let ctx = Arc::clone(&ctx);
            let policy = Arc::clone(&self.policy);
            let tls = self.tls.clone();
            tokio::spawn(async move {
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
                session::serve(stream, peer, policy, ctx, slot, pending).await;
            });
        }
    }
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
pub fn dead_link_options(tcp: &tokio::net::TcpStream, timeout: Duration) -> std::io::Result<()> {
    let socket = socket2::SockRef::from(tcp);
    let idle = (timeout / 2).max(Duration::from_secs(1));
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

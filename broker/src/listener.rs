//! A listener: accepts TCP connections, completes TLS if configured, enforces the
//! connection limit, and hands each connection to `session::serve` on its own task.
//!
//! Unlike rumqttd's `Server`, it does not pause between accepts: a line that comes back
//! after a power cut reconnects all at once, and the limit that matters is
//! `max_connections`, enforced with a semaphore so a refused connection costs nothing.
//! Nagle is turned off: MQTT messages on a line are small and latency matters more than
//! packet count.

use std::net::SocketAddr;
use std::sync::Arc;

use tokio::net::TcpListener;
use tokio::sync::Semaphore;
use tokio_rustls::TlsAcceptor;

use crate::context::Context;
use crate::session;
use crate::wire::framed::Stream;

pub struct Listener {
    pub policy: Arc<ListenerPolicy>,
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
        loop {
            let (tcp, peer) = tokio::select! {
                _ = shutdown.changed() => return,
                accepted = self.socket.accept() => match accepted {
                    Ok(a) => a,
                    Err(e) => {
                        // EMFILE and friends: log, breathe, and keep serving the others.
                        tracing::error!(listener = self.policy.name, error = %e, "accept failed");
                        tokio::time::sleep(std::time::Duration::from_millis(50)).await;
                        continue;
                    }
                },
            };
            let Ok(slot) = Arc::clone(&slots).try_acquire_owned() else {
                ctx.metrics.refused("max_connections");
                tracing::warn!(%peer, "max_connections reached; connection closed");
                continue;
            };
            let _ = tcp.set_nodelay(true);
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
                session::serve(stream, peer, policy, ctx, slot).await;
            });
        }
    }
}

/// What a listener decides for the connections it accepts.
#[derive(Debug)]
pub struct ListenerPolicy {
    pub name: String,
    pub anonymous: bool,
}

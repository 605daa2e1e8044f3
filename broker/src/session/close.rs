//! The end of a session: why it ended ([`End`]) decides the MQTT 5 DISCONNECT reason,
//! whether the will fires and the disconnect metric's label.

use std::sync::Arc;
use std::time::Duration;

use rumqttd::protocol::{Disconnect, DisconnectReasonCode, Packet};
use tokio::io::AsyncWriteExt;
use tokio::time::timeout;

use super::context::Context;
use super::lifetime::end_idle_session;
use super::packet_ids::Resume;
use super::Session;
use crate::metrics::DisconnectReason;
use crate::policy::typed::FbSession;
use crate::policy::{Admission, Door, Publication};
use crate::router::unlink;
use crate::wills::Will;
use crate::wire::codec::Version;

/// Why a session ended.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(super) enum End {
    Client {
        with_will: bool,
    },
    Abrupt,
    KeepAlive,
    /// The client did not take its outgoing data within `broker.slow_consumer_timeout_ms`,
    /// or more than `broker.slow_consumer_max_bytes` of it waited (`session::write`).
    SlowConsumer,
    Takeover,
    Malformed,
    Oversized,
    ProtocolError(DisconnectReasonCode),
    Router,
    Shutdown,
    /// The session's task panicked (`supervisor`): closed as a lost connection.
    Panic,
}

impl End {
    /// MQTT 3.1.1 3.1.2.5 / MQTT 5 3.1.2.5: the will is published unless the client
    /// disconnected normally. A broker shutdown is not the device failing: no will.
    pub(super) fn fires_will(self) -> bool {
        !matches!(self, End::Client { with_will: false } | End::Shutdown)
    }

    pub(super) fn reason(self) -> DisconnectReason {
        match self {
            End::Client { with_will: false } => DisconnectReason::Client,
            End::Client { with_will: true } => DisconnectReason::ClientWithWill,
            End::Abrupt => DisconnectReason::Abrupt,
            End::KeepAlive => DisconnectReason::KeepAlive,
            End::SlowConsumer => DisconnectReason::SlowConsumer,
            End::Takeover => DisconnectReason::Takeover,
            End::Malformed => DisconnectReason::Malformed,
            End::Oversized => DisconnectReason::Oversized,
            End::ProtocolError(_) => DisconnectReason::ProtocolError,
            End::Router => DisconnectReason::Router,
            End::Shutdown => DisconnectReason::Shutdown,
            End::Panic => DisconnectReason::Internal,
        }
    }

    /// The DISCONNECT an MQTT 5 client is sent, when the server ends the connection.
    pub(super) fn v5_disconnect(self) -> Option<DisconnectReasonCode> {
        match self {
            End::KeepAlive => Some(DisconnectReasonCode::KeepAliveTimeout),
            // 0x97 Quota exceeded, "an implementation or administrative imposed limit has
            // been exceeded": the client's outgoing data passed this connection's limits.
            // Not 0x89 Server busy, which blames the server and invites an immediate retry.
            // (It reaches the client only if the socket takes it: see `close`.)
            End::SlowConsumer => Some(DisconnectReasonCode::QuotaExceeded),
            End::Takeover => Some(DisconnectReasonCode::SessionTakenOver),
            End::Malformed => Some(DisconnectReasonCode::MalformedPacket),
            End::Oversized => Some(DisconnectReasonCode::PacketTooLarge),
            End::ProtocolError(code) => Some(code),
            End::Shutdown => Some(DisconnectReasonCode::ServerShuttingDown),
            End::Panic => Some(DisconnectReasonCode::UnspecifiedError),
            End::Client { .. } | End::Abrupt | End::Router => None,
        }
    }

    /// Whether the client may still be sending when the server ends the connection
    /// because of what it sent: its socket is drained before it is closed ([`linger`]).
    pub(super) fn client_at_fault(self) -> bool {
        matches!(
            self,
            End::ProtocolError(_) | End::Malformed | End::Oversized
        )
    }

    /// Whether the router still holds this connection and must be told it ended.
    pub(super) fn router_link_alive(self) -> bool {
        !matches!(self, End::Takeover | End::Router)
    }
}

impl Session {
    /// Ends the session: tells the client why (MQTT 5), the router that it is gone,
    /// fires the will if the end calls for it, and meters the disconnect.
    pub(super) async fn close(mut self, end: End) {
        // What the client sent is routed: a newer connection waiting for that goes on.
        self.ctx.takeovers.finished(self.session);
        // Whether this connection still is its client id's newest (not taken over).
        let current = self
            .ctx
            .sessions
            .is_current(&self.client.client_id, self.session);
        // First, so a reconnecting client's next connection, which may already wait for
        // it, gets this session's open exchanges at once (`redelivery`).
        let open = if self.lifetime.clean_link {
            Resume::default()
        } else {
            let mut open = std::mem::take(&mut self.ids).into_resume();
            if self.special_subscriptions {
                open.subscriptions = self.subscriptions.clone();
            }
            open
        };
        let (redeliveries, client_id, session) = (
            &self.ctx.redeliveries,
            &*self.client.client_id,
            self.session,
        );
        // A kept session with an expiry is ended by the expiry task (`session::lifetime`).
        let remains = self.lifetime.remains();
        self.ctx
            .sessions
            .close_with(client_id, session, remains, |superseded| {
                redeliveries.save(client_id, session, open, superseded)
            });
        // An expiry of 0 ends a kept session now (MQTT 5 Clean Start 0, expiry 0), before
        // the client sees its connection close: a client that reconnects at once finds no
        // session. Later expiries are the expiry task's (`lifetime::expire_sessions`).
        if self.lifetime.expires_after == Some(Duration::ZERO) {
            end_idle_session(&self.ctx, &self.client.client_id, self.session).await;
        }
        // A client whose socket did not take its last write (slow consumer, keep-alive
        // expired while a write waited) would not take a DISCONNECT either: waiting for it
        // would only delay its will. Its unwritten QoS 0 deliveries are lost, and counted;
        // QoS 1/2 ones stay with a persistent session for its return (`into_resume` above,
        // the router's queue).
        // Packets queued but never tried (answers to the packets read just before a
        // protocol error) do not make a socket stalled: one try without a timer first.
        if self.io.unwritten() > 0 {
            let io = &mut self.io;
            let _ = std::future::poll_fn(|cx| std::task::Poll::Ready(io.poll_write_out(cx))).await;
        }
        let stalled = self.io.unwritten() > 0;
        if stalled {
            let reason = match end {
                End::SlowConsumer | End::KeepAlive => "slow_consumer",
                _ => "connection_closed",
            };
            self.ctx
                .metrics
                .messages_dropped
                .with_label_values(&[reason])
                .inc_by(u64::from(self.qos0_unwritten));
        } else {
            if self.version == Version::V5 {
                if let Some(reason_code) = end.v5_disconnect() {
                    self.io
                        .queue(Packet::Disconnect(Disconnect { reason_code }, None));
                    let _ = timeout(Duration::from_secs(1), self.io.flush()).await;
                }
            }
            let _ = timeout(Duration::from_secs(1), self.io.stream.shutdown()).await;
        }
        // The store: the session is offline from now (its expiry counts from here), with
        // what it did not get of its backlog; then every record this connection left.
        if self.persistent {
            self.return_backlog(true);
            if current {
                self.journal.push(crate::store::Record::Offline {
                    client: Arc::clone(&self.client.client_id),
                    at: crate::store::now(),
                    expiry: self
                        .lifetime
                        .expires_after
                        .map(|d| d.as_secs().min(u32::MAX as u64) as u32),
                });
            }
        }
        // Handed over without waiting: nothing here depends on it being written.
        if let Some(store) = &self.ctx.store {
            store.submit_now(&self.client.client_id, &mut self.journal);
        }
        if end.router_link_alive() {
            let _ = unlink(self.link_tx).await;
        }
        if self.will.is_some() {
            self.ctx.wills.disarm(&self.client.client_id, self.session);
        }
        let will = self.will.take().filter(|_| end.fires_will());
        let own_will = will.is_some();
        let (ctx, session) = (&self.ctx, self.session);
        let (client_id, username) = (&*self.client.client_id, self.client.username.as_deref());
        if let Some(will) = will.map(|w| *w) {
            fire_will(ctx, &mut self.fb, client_id, session, username, will);
        }
        // A clean session's subscriptions end with it; a persistent session's stay (the
        // router keeps queueing for it), and so does the bridge's import of them.
        if self.lifetime.clean_link {
            for f in self.subscriptions.keys() {
                self.ctx.observers.unsubscribed(f);
            }
        }
        let offline = self
            .ctx
            .fb
            .connection_ended(&self.fb, end.reason().description());
        // A profile's broker-side will, for a runtime that cannot set one: when the device
        // is offline (not when a newer connection of it took over), not besides a will
        // the device did set, and, as an MQTT will, not after a clean DISCONNECT unless
        // the profile asks for it (`liveness.will_on_clean_disconnect`).
        let fires = self
            .fb
            .profile()
            .is_some_and(|p| end.fires_will() || p.will_on_clean_disconnect);
        if offline && !own_will && fires {
            let (ctx, client_id) = (&self.ctx, &*self.client.client_id);
            fire_profile_will(ctx, &mut self.fb, client_id, session, username);
        }
        // The gauge first: a scrape that sees the disconnect counted sees the gauge down.
        self.ctx.metrics.connections.dec();
        self.ctx.metrics.disconnected(end.reason());
        tracing::info!(
            peer = %self.client.address,
            client_id = &*self.client.client_id,
            reason = end.reason().label(),
            "client disconnected"
        );
        if !stalled && end.client_at_fault() {
            linger(&mut self.io.stream).await;
        }
    }
}

/// Publishes the broker-side will of the device connection `fb` speaks for (its
/// profile's `[will]` values on its typed ports, QoS 1), each as the publication it is,
/// under that connection's identity: when the device went offline with the connection's
/// end (`close`), or when the registry ended it for its silence while the connection
/// lives on (`Session::silence_ended`).
pub(super) fn fire_profile_will(
    ctx: &Context,
    fb: &mut FbSession,
    client_id: &str,
    session: u64,
    username: Option<&str>,
) {
    let Some(profile) = fb.profile().cloned() else {
        return;
    };
    for (fb_name, port, payload) in &profile.will {
        let will = Will {
            topic: format!("fb/{}/{fb_name}/{port}", profile.device).into(),
            payload: payload.clone().into(),
            qos: 1,
            retain: false,
            properties: None,
            delay: Duration::ZERO,
        };
        fire_will(ctx, fb, client_id, session, username, will);
    }
}

/// How long a socket the server closed is drained for the client's last packets.
const LINGER: Duration = Duration::from_secs(1);
/// How much of them is read, at most.
const LINGER_BYTES: usize = 1 << 20;

/// Reads and discards what the client still sends, until it closes its side (it read
/// the DISCONNECT and the FIN after it), for at most [`LINGER`] and [`LINGER_BYTES`].
///
/// Closing a socket whose receive queue holds unread bytes makes the kernel send a reset
/// instead of a FIN, and a reset can destroy what the client has not read yet: the
/// DISCONNECT with the reason code (0x93 Receive Maximum exceeded, 0x82 Protocol Error,
/// ...) would be lost exactly when the client kept sending, which is why the server ends
/// the connection. Runs last in `close`: the will, the router and the gauges do not wait
/// for it.
async fn linger(stream: &mut Box<dyn crate::wire::framed::Stream>) {
    use tokio::io::AsyncReadExt;
    let mut buf = [0u8; 4096];
    let mut read = 0usize;
    let _ = timeout(LINGER, async {
        while read < LINGER_BYTES {
            match stream.read(&mut buf).await {
                Ok(0) | Err(_) => return,
                Ok(n) => read += n,
            }
        }
    })
    .await;
}

/// Publishes `will`, the client's or its profile's, as the publication it is: checked
/// against the access rules and the interface in force now, and re-encoded like one (the
/// reference line's CONNECT FB sets a BOOL output to FALSE this way).
fn fire_will(
    ctx: &Context,
    fb: &mut FbSession,
    client_id: &str,
    session: u64,
    username: Option<&str>,
    will: Will,
) {
    let owner = ctx.identity.owner(username);
    let topic = String::from_utf8_lossy(&will.topic).into_owned();
    let publication = Publication {
        topic: &topic,
        payload: &will.payload,
        qos: will.qos,
        retain: will.retain,
    };
    let origin: std::sync::Arc<str> = client_id.into();
    match ctx.policy.admit(Door::Will, fb, &origin, publication) {
        Admission::Route { routes: None, .. } => ctx.wills.fire(client_id, session, &owner, will),
        Admission::Route {
            routes: Some(routes),
            ..
        } => {
            for (topic, payload) in routes {
                let mut copy = will.clone();
                copy.topic = topic.into();
                copy.payload = payload;
                ctx.wills.fire(client_id, session, &owner, copy);
            }
        }
        Admission::Consumed | Admission::Refused { .. } => {}
    }
    ctx.fb.publish(fb.take_outbox());
}

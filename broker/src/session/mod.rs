//! The session layer: one MQTT connection, from CONNECT to close. The packet path runs
//! here, in this order:
//!
//! 1. **authenticated** — once, at CONNECT ([`connect`]: client id, the `Authenticator`,
//!    the will's topic, the router link, CONNACK); a session only exists for a client that
//!    passed, so every later step knows who it is;
//! 2. **authorized**, 3. **type-checked** — every PUBLISH by the publish policy
//!    (`policy::PublishPolicy::admit`: access rules, typed FB topics against the device's
//!    declared interface, origin mark), called from [`inbound`]; SUBSCRIBE filters against
//!    the access rules there too;
//! 4. **routed** — handed to rumqttd's router through the connection's `LinkTx`, one
//!    batch per network read ([`Session::route`]);
//! 5. **metered** — counted in `Metrics` as it is accepted or refused.
//!
//! The files: [`connect`] (opening), [`inbound`] (one dispatch per packet type from the
//! client, then the PUBLISH and SUBSCRIBE handlers), [`deliver`] (what the router sends
//! back: the MQTT rules its router leaves out — delivery QoS, No Local, Retain As
//! Published, the client's Maximum Packet Size and Receive Maximum — SUBACKs completed for
//! refused filters; [`read_access`]: the access rules in force at each delivery),
//! [`close`] (why a session ended, the DISCONNECT reason, the will); around them [`ack_order`], [`packet_ids`], [`redelivery`] (acknowledgements and packet
//! ids the router leaves to us), [`table`] and [`lifetime`] (session numbers, MQTT 5
//! session expiry), [`aliases`] (the topic aliases of deliveries), [`copies`] (one copy
//! for overlapping subscriptions), [`write`] (every
//! write to the client under its deadlines: liveness does not depend on the client
//! reading). Bytes and packets are `wire`'s business; who else is told of subscriptions,
//! `observer`'s.
//!
//! fbbus runs its own connection loop instead of rumqttd's `Server` because the policy
//! needs what that loop hides: the peer address (login throttling), keep-alive 0
//! (refused by rumqttd 0.20), wills on takeover and keep-alive expiry, one port for
//! MQTT 3.1.1 and 5, and refusals with the right reason codes.

pub mod ack_order;
pub mod aliases;
mod close;
mod connect;
mod context;
pub mod control;
pub mod copies;
mod deliver;
mod durable;
mod inbound;
pub mod lifetime;
pub mod packet_ids;
mod persist;
mod read_access;
pub mod redelivery;
pub mod restore;
pub mod table;
pub mod takeover;
mod write;

pub use context::Context;
pub use deliver::WRITE_BATCH;

use std::collections::{BTreeMap, BTreeSet, VecDeque};
use std::net::SocketAddr;
use std::sync::Arc;
use std::time::Duration;

use rumqttd::local::{LinkRx, LinkTx};
use rumqttd::protocol::{
    DisconnectReasonCode, Filter, Packet, Publish, PublishProperties, SubscribeReasonCode,
};
use tokio::sync::OwnedSemaphorePermit;
use tokio::time::{timeout, Instant};

use self::ack_order::AckOrder;
use self::lifetime::SessionLifetime;
use self::packet_ids::PacketIds;
use crate::policy::typed::FbSession;
use crate::supervisor::CatchPanic;
use crate::wills::Will;
use crate::wire::codec::{connack, ReadError, Version};
use crate::wire::framed::{Io, Stream};
use close::End;

/// What the listener a connection came in by decides for it (`listener`, from its
/// `[[listener]]` section).
#[derive(Debug)]
pub struct ListenerPolicy {
    /// Shared with the connections' entries in the clients list (`clients`).
    pub name: std::sync::Arc<str>,
    pub anonymous: bool,
    /// mqtt, mqtts, ws or wss: the label of the listener's metrics.
    pub transport: &'static str,
}

/// Serves one accepted connection: reads its CONNECT and logs it in on this task, then
/// runs the session on a task of its own until it ends. `slot` is its place under
/// `max_connections`, held until then.
///
/// Most connections spend their life idle in `Session::run`, and a task is allocated once,
/// as large as the largest state of its future. So the session's task is spawned only once
/// the login is done: it holds the `Session` and the waiting loop, not the room reading
/// CONNECT, authenticating and linking needed. That room is this task's, freed right after,
/// and reused by the next connection's login instead of leaving a hole next to each
/// session's memory. The close, also large and short, runs boxed. `pending` is the
/// connection's place among its address's connections before CONNECT (`pending`), given
/// back as soon as CONNECT is read.
pub async fn serve(
    stream: Box<dyn Stream>,
    peer: SocketAddr,
    listener: Arc<ListenerPolicy>,
    ctx: Arc<Context>,
    slot: OwnedSemaphorePermit,
    pending: crate::pending::PendingGuard,
) {
    let session = match CatchPanic::new(accept(stream, peer, listener, &ctx, pending)).await {
        Ok(Some(session)) => session,
        Ok(None) => return,
        Err(message) => {
            // Logged by the panic hook; the client had no session yet.
            ctx.metrics.refused("internal_error");
            tracing::error!(%peer, message, "login failed inside fbbus; connection closed");
            return;
        }
    };
    tokio::spawn(live(Box::new(session), slot));
}

/// A logged-in session's task, from its loop to its close. `slot` is its place under
/// `max_connections`, held until then.
///
/// The session comes boxed: a future keeps what it was given and what it moved that into
/// as two places (rustc does not overlap them), so a `Session` passed by value was held
/// twice in every idle connection's task, 1.9 KB of 5.
async fn live(mut session: Box<Session>, slot: OwnedSemaphorePermit) {
    let _slot = slot;
    // A panic in this one session (a bug, logged by the panic hook) ends this
    // connection only, closed like a lost connection: unlinked, will published,
    // gauges and registry updated. The rest of the line goes on.
    let end = CatchPanic::new(session.run()).await.unwrap_or(End::Panic);
    let client_id = Arc::clone(&session.client.client_id);
    if let Err(message) = CatchPanic::new((*session).close(end)).await {
        tracing::error!(
            client_id = &*client_id,
            message,
            "closing a session failed inside fbbus"
        );
    }
}

/// Reads the CONNECT and opens the session: None when the client was refused.
async fn accept(
    stream: Box<dyn Stream>,
    peer: SocketAddr,
    listener: Arc<ListenerPolicy>,
    ctx: &Arc<Context>,
    pending: crate::pending::PendingGuard,
) -> Option<Session> {
    let mut io = Io::new(stream, ctx.max_packet).with_write_timeout(ctx.write_timeout);
    let connect = timeout(ctx.connect_timeout, io.read_connect()).await;
    // CONNECT read (or not, in time): the address's place before CONNECT is free again,
    // before the login, which may wait for argon2.
    drop(pending);
    let connect = match connect {
        Ok(Ok(packet)) => packet,
        Ok(Err(refusal)) => {
            refusal.report(&ctx.metrics, peer);
            if let Some(code) = refusal.connack {
                let _ = io.send(connack(code, None)).await;
            }
            return None;
        }
        Err(_) => {
            ctx.metrics.refused("connect_timeout");
            tracing::debug!(%peer, "no CONNECT in time; closed");
            return None;
        }
    };
    Session::open(io, connect, peer, &listener, ctx).await
}

/// What woke a waiting connection up (`Session::run`).
enum Wake {
    Backlogged,
    Read(Result<usize, ReadError>),
    /// The router sent something (`linked`), or dropped this connection's link.
    Router {
        linked: bool,
    },
    /// The store wrote what acknowledgements were waiting for ([`durable`]).
    Written,
    /// The registry ended the device this connection speaks for, for its silence.
    SilenceEnded,
}

/// Resolves when the registry ends the device of `activity` for its silence; never
/// without one (a connection whose device does not end for silence: most of them).
async fn silence_ended(activity: Option<&Arc<crate::silence::Activity>>) {
    match activity {
        Some(activity) => activity.ended().await,
        None => std::future::pending().await,
    }
}

/// An authenticated client's connection, registered with the router.
///
/// Every idle connection holds one, so it is kept small: per-session tables are B-tree
/// maps (24 bytes and no allocation while empty, against 48 for a `HashMap`; they stay
/// small, bounded by the in-flight windows), and the will, which most devices set but which
/// is used once at the end, is boxed.
struct Session {
    io: Io,
    version: Version,
    keep_alive: Option<Duration>,
    will: Option<Box<Will>>,
    link_tx: LinkTx,
    link_rx: LinkRx,
    /// This connection's session number for its client id (see `table`).
    session: u64,
    /// What happens to the session in the router when this connection ends.
    lifetime: SessionLifetime,
    ctx: Arc<Context>,
    /// Packets accepted from the current network read, handed to the router as one batch.
    to_router: Vec<Packet>,
    /// QoS 1/2 publications routed and not yet acknowledged to the client: bounded by the
    /// Receive Maximum fbbus announces (MQTT 5 3.3.4).
    inflight_in: u16,
    /// The client's Topic Alias Maximum (MQTT 5 3.1.2.11.5); 0: no aliases (and 3.1.1).
    client_alias_max: u16,
    /// The topic aliases of this connection's deliveries, from the first one ([`aliases`]).
    aliases_out: Option<Box<aliases::OutAliases>>,
    /// The client's Maximum Packet Size (MQTT 5 3.1.2.11.4): larger packets are not sent.
    client_max_packet: Option<usize>,
    /// Acknowledgements to the router, kept in the order the router requires.
    ack_order: AckOrder,
    /// The client's Receive Maximum (MQTT 5 3.1.2.11.3): QoS 1/2 deliveries it may have
    /// unacknowledged at once. 65535 when not given (and on 3.1.1).
    client_receive_max: u16,
    /// QoS 1/2 deliveries sent and not yet acknowledged by the client.
    outstanding_out: u16,
    /// When the keep-alive expires (1.5 x keep-alive after the client was last heard);
    /// unused without keep-alive. Kept here, not only in `run`'s timer, because a write
    /// that waits for the client hears it too (`write`).
    alive_until: Instant,
    /// Bytes were read while a write waited; their packets are handled next in `run`.
    unhandled_read: bool,
    /// QoS 0 deliveries in the write buffer: lost, and counted, if the connection ends
    /// before the socket took them (QoS 1/2 ones stay in the session for its return).
    qos0_unwritten: u32,
    /// The packet ids the client sees for deliveries, and the router's for each; what a
    /// later connection of this session re-sends, and under which ids (`redelivery`).
    ids: PacketIds,
    /// Deliveries waiting for the client's window, in order.
    held: VecDeque<(Publish, Option<Box<PublishProperties>>)>,
    /// Topic and payload bytes of `held`: part of the outgoing bytes queued for the
    /// client (`broker.slow_consumer_max_bytes`, `write`).
    held_bytes: usize,
    /// The router paused delivery and is woken once `held` is short again.
    wake_pending: bool,
    /// The client's subscriptions by filter, with their MQTT 5 options.
    subscriptions: BTreeMap<String, Filter>,
    /// Who this connection is (client id, username, address: read through it, not kept
    /// twice) and its place in the admin plane's list of clients, with its counters.
    client: crate::clients::Entry,
    /// Some subscription uses No Local, Retain As Published or Retain Handling 2.
    special_subscriptions: bool,
    /// Two of the client's non-shared subscriptions overlap: a message may match several,
    /// and the router sends one copy per match; the client gets one ([`copies`]).
    overlapping: bool,
    /// Typed-topic state: the device's interface, event sequence numbers.
    fb: FbSession,
    /// Read verdicts by topic under the ACL in force, allocated at the first delivery
    /// checked against an ACL file ([`read_access`]).
    read_verdicts: Option<Box<read_access::ReadVerdicts>>,
    /// State most sessions never need, allocated on first use ([`Session::rare`]).
    rare: Option<Box<Rare>>,
    /// The session outlives its connection and the store keeps it ([`persist`]).
    persistent: bool,
    /// Records for the store, written with the next batch ([`persist`]).
    journal: crate::store::Journal,
    /// Stored messages on their way to the client, and acknowledgements that wait for the
    /// store, allocated on first use ([`durable`]).
    durable: Option<Box<durable::Durable>>,
}

/// What a session needs only for uncommon traffic: refused or partly refused requests,
/// QoS 2 exchanges the broker answers itself, MQTT 5 topic aliases. Boxed apart so the
/// many sessions that never need it do not carry it.
#[derive(Default)]
struct Rare {
    /// SUBSCRIBEs the ACL trimmed: pkid -> the reason code of each refused filter, by position.
    partial_subscribes: BTreeMap<u16, Vec<Option<SubscribeReasonCode>>>,
    /// Refused QoS 2 publications: their PUBREL is answered here, not by the router.
    refused_qos2: BTreeSet<u16>,
    /// QoS 2 publications this connection routed: their PUBREL goes to the router.
    qos2_routed: BTreeSet<u16>,
    /// MQTT 5 topic aliases the client set. fbbus resolves them itself, so the ACL sees the
    /// real topic and the router only ever gets full topic names.
    topic_aliases: BTreeMap<u16, String>,
    /// QoS 2 deliveries acknowledged to the router on the client's behalf (dropped, or sent
    /// at a lower QoS): the router's PUBREL for them is answered here.
    dropped_qos2: BTreeSet<u16>,
    /// QoS 2 deliveries sent at QoS 1 (published at QoS 1): the client's PUBACK becomes
    /// the PUBREC the router waits for.
    qos2_sent_as_qos1: BTreeSet<u16>,
    /// The Subscription Identifier of each subscription that has one, by filter.
    subscription_ids: BTreeMap<String, usize>,
    /// Copies of messages matching several overlapping subscriptions ([`copies`]).
    copies: copies::Copies,
    /// (action, topic) pairs already logged as denied, so a looping device logs once.
    logged_denials: BTreeSet<(&'static str, String)>,
    /// What was queued for a restored session when the broker stopped, still to be sent.
    backlog: VecDeque<crate::store::Backlogged>,
    /// Backlog messages sent and not yet acknowledged, by client packet id.
    backlog_out: BTreeMap<u16, crate::store::Backlogged>,
}

const MAX_LOGGED_DENIALS: usize = 1024;

/// Packets from one client waiting for the router before its socket is no longer read.
const ROUTER_BACKLOG: usize = 1024;

/// Deliveries held for a client's Receive Maximum before the router is no longer woken.
const HOLD_LIMIT: usize = 1024;

impl Session {
    /// The connection's loop: network reads, router deliveries, keep-alive, shutdown.
    ///
    /// The loop only waits here; what it was woken for is handled in a boxed future, so
    /// the connection's task holds the small waiting state while the device is idle and
    /// the larger state of handling a batch only while it handles one (`serve`).
    async fn run(&mut self) -> End {
        let mut shutdown = self.ctx.shutdown.clone();
        let far_future = Instant::now() + Duration::from_secs(100 * 365 * 24 * 3600);
        self.heard();
        let deadline = tokio::time::sleep_until(if self.keep_alive.is_some() {
            self.alive_until
        } else {
            far_future
        });
        tokio::pin!(deadline);
        // What a restored session had queued goes first.
        if self.backlog_waiting() {
            self.release_backlog();
            if let Err(end) = Box::pin(self.write_out()).await {
                return end;
            }
        }
        // Packets that came in the same read as CONNECT (a client that does not wait for
        // CONNACK): handled now, not when the socket next has something.
        if !self.io.read.is_empty() {
            if let Err(end) = Box::pin(self.read_packets()).await {
                return end;
            }
        }
        loop {
            // Packets read while a write waited for the client (`write`).
            if self.unhandled_read {
                if let Err(end) = Box::pin(self.read_packets()).await {
                    return end;
                }
            }
            // The registry ended this connection's device for its silence while the
            // connection was busy (its wake may have been missed): its will, once.
            self.silence_ended();
            // The client may have been heard elsewhere (`write`): one deadline for both.
            // None once a profile lifted the keep-alive (`relax_keep_alive`).
            let due = match self.keep_alive {
                Some(_) => self.alive_until,
                None => far_future,
            };
            if deadline.deadline() != due {
                deadline.as_mut().reset(due);
            }
            // Backpressure: while the router has not taken this client's previous packets,
            // stop reading its socket, so a fast publisher is slowed by TCP instead of
            // growing the router's input queue without bound.
            // Two waits, one per case; the pause timer is boxed so it only takes memory
            // while the connection is backlogged.
            let backlogged = self.link_tx.buffer().len() >= ROUTER_BACKLOG;
            let wake = if backlogged {
                tokio::select! {
                    _ = shutdown.changed() => return End::Shutdown,
                    _ = &mut deadline => return End::KeepAlive,
                    _ = Box::pin(tokio::time::sleep(Duration::from_millis(1))) => Wake::Backlogged,
                    linked = self.link_rx.wait() => Wake::Router { linked: linked.is_ok() },
                    _ = durable::Durable::next_written(&mut self.durable) => Wake::Written,
                    _ = silence_ended(self.fb.ending_activity()) => Wake::SilenceEnded,
                }
            } else {
                tokio::select! {
                    _ = shutdown.changed() => return End::Shutdown,
                    _ = &mut deadline => return End::KeepAlive,
                    read = self.io.fill() => Wake::Read(read),
                    linked = self.link_rx.wait() => Wake::Router { linked: linked.is_ok() },
                    _ = durable::Durable::next_written(&mut self.durable) => Wake::Written,
                    _ = silence_ended(self.fb.ending_activity()) => Wake::SilenceEnded,
                }
            };
            let handled = match wake {
                Wake::Backlogged => {
                    // Not reading is the broker's choice, not client silence.
                    self.heard();
                    Ok(())
                }
                Wake::Read(read) => {
                    let n = match read {
                        Ok(n) => n,
                        Err(_) => return End::Abrupt,
                    };
                    self.ctx.metrics.bytes_in.inc_by(n as u64);
                    self.heard();
                    Box::pin(self.read_packets()).await
                }
                Wake::Router { linked: true } => {
                    if self.link_rx.nudged() {
                        if let Err(end) = Box::pin(self.finish_before_takeover()).await {
                            return end;
                        }
                    }
                    Box::pin(self.deliver()).await
                }
                Wake::Router { linked: false } => Err(Box::pin(self.router_dropped()).await),
                Wake::Written => {
                    self.release_written();
                    Box::pin(self.write_out()).await
                }
                Wake::SilenceEnded => Ok(()),
            };
            if let Err(end) = handled {
                return end;
            }
        }
    }

    /// The connection speaks for a profiled device whose runtime never pings
    /// (`speaks.enforce_keep_alive = false`) and has had an own-topic publication
    /// accepted (`FbSession::keep_alive_waived`): its keep-alive is not enforced from now
    /// on.
    /// The kernel's dead-link probes still end it if its peer vanishes.
    fn relax_keep_alive(&mut self) {
        if self.fb.keep_alive_waived() && self.keep_alive.take().is_some() {
            tracing::info!(
                client_id = &*self.client.client_id,
                device = self.fb.device(),
                "keep-alive not enforced: the device's profile says its runtime never pings"
            );
        }
    }

    /// If the registry ended this connection's device for its silence
    /// (`liveness.offline_after_silent_s`) and no other connection of it took the will
    /// yet, publishes the device's broker-side will. The connection stays open: a runtime
    /// that was only paused speaks again, and its next accepted publication brings the
    /// device back online.
    fn silence_ended(&mut self) {
        if self
            .fb
            .ending_activity()
            .is_some_and(|activity| activity.take_will_due())
        {
            tracing::info!(
                client_id = &*self.client.client_id,
                device = self.fb.device(),
                "device offline for its silence: its profile's will is published"
            );
            close::fire_profile_will(
                &self.ctx,
                &mut self.fb,
                &self.client.client_id,
                self.session,
                self.client.username.as_deref(),
            );
        }
    }

    /// The client was heard (or is not read by the broker's choice): its keep-alive
    /// starts again.
    fn heard(&mut self) {
        if let Some(k) = self.keep_alive {
            self.alive_until = Instant::now() + k;
        }
    }

    /// Handles every complete packet in the read buffer, then hands the batch to the router.
    async fn read_packets(&mut self) -> Result<(), End> {
        self.unhandled_read = false;
        loop {
            let header = match self.io.next_frame() {
                Ok(Some(header)) => header,
                Ok(None) => break,
                Err(ReadError::Oversized { size, max }) => {
                    self.ctx.metrics.oversized_packets.inc();
                    if crate::logging::OUTSIDE.allow() {
                        tracing::warn!(
                            client_id = &*self.client.client_id,
                            size,
                            max,
                            "packet over max_packet_bytes; connection closed"
                        );
                    }
                    return Err(End::Oversized);
                }
                Err(e) => {
                    self.ctx.metrics.malformed_packets.inc();
                    if crate::logging::OUTSIDE.allow() {
                        tracing::warn!(client_id = &*self.client.client_id, error = %e, "malformed packet; connection closed");
                    }
                    return Err(End::Malformed);
                }
            };
            let decoded = self.io.decode(&header);
            let end = match decoded {
                Ok(packet) => self.inbound(packet).err(),
                Err(ReadError::ServerOnlyType(t)) => {
                    if crate::logging::OUTSIDE.allow() {
                        tracing::warn!(
                            client_id = &*self.client.client_id,
                            packet_type = t,
                            "server-only packet type from a client; connection closed"
                        );
                    }
                    Some(End::ProtocolError(DisconnectReasonCode::ProtocolError))
                }
                Err(e) => {
                    self.ctx.metrics.malformed_packets.inc();
                    if crate::logging::OUTSIDE.allow() {
                        tracing::warn!(client_id = &*self.client.client_id, error = %e, "malformed packet; connection closed");
                    }
                    Some(End::Malformed)
                }
            };
            if let Some(end) = end {
                // What the client sent before it ended (e.g. PUBLISH then DISCONNECT in one
                // read) is still delivered.
                self.route().await?;
                return Err(end);
            }
        }
        self.release_held();
        self.route().await?;
        self.write_out().await?;
        if self.wake_pending && self.held.len() < HOLD_LIMIT {
            self.wake_pending = false;
            self.link_rx.wake().await.map_err(|_| End::Router)?;
        }
        Ok(())
    }

    /// A newer connection of this client id waits to take it over (`takeover`): what the
    /// client sent before it came back is in the socket already, and is read and routed
    /// now, before the new connection's link makes the router drop this one. At most
    /// `FINISH_READS` reads, without waiting for more.
    async fn finish_before_takeover(&mut self) -> Result<(), End> {
        use futures_util::FutureExt;
        let mut finished = Ok(());
        for _ in 0..takeover::FINISH_READS {
            let n = match self.io.fill().now_or_never() {
                None => break,
                Some(Ok(n)) => n,
                Some(Err(_)) => {
                    finished = Err(End::Abrupt);
                    break;
                }
            };
            self.ctx.metrics.bytes_in.inc_by(n as u64);
            self.heard();
            if let Err(end) = self.read_packets().await {
                finished = Err(end);
                break;
            }
        }
        self.ctx.takeovers.finished(self.session);
        finished
    }

    /// Hands the accepted packets of this read to the router: one wake-up per batch.
    /// Then publishes the broker's answers to them (diagnostics), which must reach the
    /// router after the packets they answer (a SUBSCRIBE to the diag topic among them).
    async fn route(&mut self) -> Result<(), End> {
        if self.ctx.store.is_some() {
            self.store_batch().await;
        }
        if let Some(last) = self.to_router.pop() {
            {
                // The router takes the buffer whole and leaves it unallocated (no idle
                // connection keeps a batch's room), so room for the batch and its last
                // packet is made once here, not grown twice (4 % of the worker's
                // samples in a QoS 1 fan-in).
                let mut buffer = self.link_tx.buffer();
                buffer.reserve(self.to_router.len() + 1);
                buffer.extend(self.to_router.drain(..));
            }
            self.link_tx.send(last).await.map_err(|_| End::Router)?;
        }
        self.ctx.fb.publish(self.fb.take_outbox());
        Ok(())
    }

    /// The session's [`Rare`] state, allocated on first use.
    fn rare(&mut self) -> &mut Rare {
        self.rare.get_or_insert_with(Box::default)
    }
}

#[cfg(test)]
mod sizes {
    use super::*;

    /// The size of the future `f` makes, without running it.
    fn future_size<A, F>(_: impl FnOnce(A) -> F) -> usize {
        std::mem::size_of::<F>()
    }

    /// What every idle connection holds (issue 34, `tests/idle_memory.rs` measures the
    /// whole): its session's task must not hold the session itself (it held it twice,
    /// 1.9 KB), and the session and its waiting loop stay within their allocator size
    /// classes (896 and 640 bytes: the session fell from 1,024 to 896 when it stopped
    /// keeping its client id, username and address apart from its `clients` entry).
    #[test]
    fn an_idle_sessions_task_holds_only_what_it_waits_with() {
        let task = future_size(|(session, slot): (Box<Session>, OwnedSemaphorePermit)| {
            live(session, slot)
        });
        let run = future_size(|session: &mut Session| session.run());
        let session = std::mem::size_of::<Session>();
        assert!(task <= 128, "the session's task is {task} bytes");
        assert!(run <= 640, "the session's waiting loop is {run} bytes");
        assert!(session <= 896, "a session is {session} bytes");
    }
}

//! One MQTT connection, from CONNECT to close. This file is the packet path.
//!
//! Every packet a client sends goes through `Session::inbound`, in this order:
//!
//! 1. **authenticated** — once, at CONNECT (`Session::open` via the `Authenticator`);
//!    a session only exists for a client that passed, so every later step knows who it is;
//! 2. **authorized** — PUBLISH topics and SUBSCRIBE filters against the ACL
//!    (`Session::on_publish`, `Session::on_subscribe`); the will topic at CONNECT;
//! 3. **checked** — typed FB topics against the device's declared interface
//!    (`fb_topics`), between the ACL and the router, so an ill-typed message is never
//!    routed; declarations are consumed here;
//! 4. **routed** — handed to rumqttd's router through the connection's `LinkTx`, one
//!    batch per network read;
//! 5. **metered** — counted in `Metrics` as it is accepted or refused.
//!
//! Packets the router sends back go through `Session::outbound`: deliveries get the MQTT
//! rules rumqttd's router leaves out (delivery QoS, the client's Maximum Packet Size and
//! Receive Maximum: `Session::deliver_publish`), SUBACKs are completed for filters the
//! ACL refused, and acknowledgements towards the router keep its order (`ack_order`).
//! The end of a connection is one `End` value: it decides the MQTT 5 DISCONNECT reason,
//! whether the will fires, and the disconnect metric label. Bytes and packets are the
//! `framed` and `codec` modules' business; session lifetimes are `session_lifetime`'s.
//!
//! fbbus runs its own connection loop instead of rumqttd's `Server` because the policy
//! needs what that loop hides: the peer address (login throttling), keep-alive 0
//! (refused by rumqttd 0.20), wills on takeover and keep-alive expiry, one port for
//! MQTT 3.1.1 and 5, and refusals with the right reason codes.

use std::collections::{BTreeMap, BTreeSet, VecDeque};
use std::net::SocketAddr;
use std::sync::Arc;
use std::time::Duration;

use rumqttd::local::{LinkError, LinkRx, LinkTx};
use rumqttd::protocol::{
    ConnectReturnCode, Disconnect, DisconnectReasonCode, Filter, Packet, PingResp, PubAck,
    PubAckReason, PubComp, PubCompReason, PubRec, PubRecReason, Publish, PublishProperties,
    RetainForwardRule, SubAck, Subscribe, SubscribeProperties, SubscribeReasonCode,
};
use rumqttd::Notification;
use security::{AclRules, Identity};
use tokio::io::AsyncWriteExt;
use tokio::sync::{watch, OwnedSemaphorePermit};
use tokio::time::{timeout, Instant};

use crate::ack_order::AckOrder;
use crate::authenticator::{Authenticator, Outcome};
use crate::broker_publisher::is_reserved_client_id;
use crate::wire::codec::{connack, ReadError, Version};
use crate::fb_topics::{Check, FbSession, FbTopics, Refusal};
use crate::wire::frame;
use crate::wire::framed::{Io, Stream};
use crate::metrics::{DisconnectReason, Metrics};
use crate::origin;
use crate::packet_ids::{PacketIds, Resume};
use crate::redelivery::{self, Redeliveries};
use crate::router::{unlink, RouterHandle};
use crate::session_lifetime::{end_idle_session, purge_router_session, SessionLifetime};
use crate::session_table::{Remains, SessionTable};
use crate::supervisor::CatchPanic;
use crate::watched_file::WatchedFile;
use crate::wills::{Will, Wills};

/// Everything connections share, built once by `server`.
pub struct Context {
    pub router: RouterHandle,
    pub authenticator: Arc<Authenticator>,
    /// None: no ACL file, every authenticated client may publish and subscribe anywhere.
    pub acl: Option<Arc<WatchedFile<AclRules>>>,
    pub wills: Arc<Wills>,
    pub fb: FbTopics,
    pub sessions: SessionTable,
    pub redeliveries: Redeliveries,
    pub metrics: Arc<Metrics>,
    pub max_packet: usize,
    pub max_inflight: u16,
    /// `broker.max_keep_alive_s` (see [`keep_alive`]).
    pub max_keep_alive: u16,
    pub connect_timeout: Duration,
    /// Becomes true when the broker shuts down.
    pub shutdown: watch::Receiver<bool>,
    /// Tests only: a publication on this topic makes its session panic (`supervisor`).
    pub test_panic_topic: Option<String>,
    /// Who else wants to know what clients subscribe to: the zenoh bridge to the other
    /// lines, once started (`[bridge]` configured), imports what local clients read.
    pub bridge: std::sync::OnceLock<Arc<dyn SubscriptionObserver>>,
}

/// Told of every filter local clients start or stop reading (the bus bridge imports what
/// they read from the other lines). Called on the connection's task: must not block.
pub trait SubscriptionObserver: Send + Sync {
    /// A first local subscription to `filter` (per session).
    fn subscribed(&self, filter: &str);
    /// A session no longer reads `filter`.
    fn unsubscribed(&self, filter: &str);
}

/// What a listener decides for the connections it accepts.
#[derive(Debug)]
pub struct ListenerPolicy {
    pub name: String,
    pub anonymous: bool,
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
/// session's memory. The close, also large and short, runs boxed.
pub async fn serve(
    stream: Box<dyn Stream>,
    peer: SocketAddr,
    listener: Arc<ListenerPolicy>,
    ctx: Arc<Context>,
    slot: OwnedSemaphorePermit,
) {
    let session = match CatchPanic::new(accept(stream, peer, listener, &ctx)).await {
        Ok(Some(session)) => session,
        Ok(None) => return,
        Err(message) => {
            // Logged by the panic hook; the client had no session yet.
            ctx.metrics.refused("internal_error");
            tracing::error!(%peer, message, "login failed inside fbbus; connection closed");
            return;
        }
    };
    tokio::spawn(async move {
        let _slot = slot;
        let mut session = session;
        // A panic in this one session (a bug, logged by the panic hook) ends this
        // connection only, closed like a lost connection: unlinked, will published,
        // gauges and registry updated. The rest of the line goes on.
        let end = CatchPanic::new(session.run()).await.unwrap_or(End::Panic);
        let client_id = Arc::clone(&session.client_id);
        if let Err(message) = CatchPanic::new(session.close(end)).await {
            tracing::error!(
                client_id = &*client_id,
                message,
                "closing a session failed inside fbbus"
            );
        }
    });
}

/// Reads the CONNECT and opens the session: None when the client was refused.
async fn accept(
    stream: Box<dyn Stream>,
    peer: SocketAddr,
    listener: Arc<ListenerPolicy>,
    ctx: &Arc<Context>,
) -> Option<Session> {
    let mut io = Io::new(stream, ctx.max_packet);
    let connect = match timeout(ctx.connect_timeout, io.read_connect()).await {
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
}

/// Why a session ended.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum End {
    Client {
        with_will: bool,
    },
    Abrupt,
    KeepAlive,
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
    fn fires_will(self) -> bool {
        !matches!(self, End::Client { with_will: false } | End::Shutdown)
    }

    fn reason(self) -> DisconnectReason {
        match self {
            End::Client { with_will: false } => DisconnectReason::Client,
            End::Client { with_will: true } => DisconnectReason::ClientWithWill,
            End::Abrupt => DisconnectReason::Abrupt,
            End::KeepAlive => DisconnectReason::KeepAlive,
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
    fn v5_disconnect(self) -> Option<DisconnectReasonCode> {
        match self {
            End::KeepAlive => Some(DisconnectReasonCode::KeepAliveTimeout),
            End::Takeover => Some(DisconnectReasonCode::SessionTakenOver),
            End::Malformed => Some(DisconnectReasonCode::MalformedPacket),
            End::Oversized => Some(DisconnectReasonCode::PacketTooLarge),
            End::ProtocolError(code) => Some(code),
            End::Shutdown => Some(DisconnectReasonCode::ServerShuttingDown),
            End::Panic => Some(DisconnectReasonCode::UnspecifiedError),
            End::Client { .. } | End::Abrupt | End::Router => None,
        }
    }

    /// Whether the router still holds this connection and must be told it ended.
    fn router_link_alive(self) -> bool {
        !matches!(self, End::Takeover | End::Router)
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
    peer: SocketAddr,
    client_id: Arc<str>,
    username: Option<String>,
    version: Version,
    keep_alive: Option<Duration>,
    will: Option<Box<Will>>,
    link_tx: LinkTx,
    link_rx: LinkRx,
    /// This connection's session number for its client id (see `session_table`).
    session: u64,
    /// What happens to the session in the router when this connection ends.
    lifetime: SessionLifetime,
    ctx: Arc<Context>,
    /// Packets accepted from the current network read, handed to the router as one batch.
    to_router: Vec<Packet>,
    /// QoS 1/2 publications routed and not yet acknowledged to the client: bounded by the
    /// Receive Maximum fbbus announces (MQTT 5 3.3.4).
    inflight_in: u16,
    /// The client's Maximum Packet Size (MQTT 5 3.1.2.11.4): larger packets are not sent.
    client_max_packet: Option<usize>,
    /// Acknowledgements to the router, kept in the order the router requires.
    ack_order: AckOrder,
    /// The client's Receive Maximum (MQTT 5 3.1.2.11.3): QoS 1/2 deliveries it may have
    /// unacknowledged at once. 65535 when not given (and on 3.1.1).
    client_receive_max: u16,
    /// QoS 1/2 deliveries sent and not yet acknowledged by the client.
    outstanding_out: u16,
    /// The packet ids the client sees for deliveries, and the router's for each; what a
    /// later connection of this session re-sends, and under which ids (`redelivery`).
    ids: PacketIds,
    /// Deliveries waiting for the client's window, in order.
    held: VecDeque<(Publish, Option<PublishProperties>)>,
    /// The router paused delivery and is woken once `held` is short again.
    wake_pending: bool,
    /// The client's subscriptions by filter, with their MQTT 5 options.
    subscriptions: BTreeMap<String, Filter>,
    /// Some subscription uses No Local, Retain As Published or Retain Handling 2.
    special_subscriptions: bool,
    /// Typed-topic state: the device's interface, event sequence numbers.
    fb: FbSession,
    /// State most sessions never need, allocated on first use ([`Session::rare`]).
    rare: Option<Box<Rare>>,
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
    /// MQTT 5 topic aliases the client set. fbbus resolves them itself, so the ACL sees the
    /// real topic and the router only ever gets full topic names.
    topic_aliases: BTreeMap<u16, String>,
    /// QoS 2 deliveries acknowledged to the router on the client's behalf (dropped, or sent
    /// at a lower QoS): the router's PUBREL for them is answered here.
    dropped_qos2: BTreeSet<u16>,
    /// QoS 2 deliveries sent at QoS 1 (published at QoS 1): the client's PUBACK becomes
    /// the PUBREC the router waits for.
    qos2_sent_as_qos1: BTreeSet<u16>,
    /// (action, topic) pairs already logged as denied, so a looping device logs once.
    logged_denials: BTreeSet<(&'static str, String)>,
}

const MAX_LOGGED_DENIALS: usize = 1024;

/// The keep-alive a connection runs with, in seconds (0: off), and the Server Keep Alive
/// to announce in CONNACK. An MQTT 5 client that asks for 0 (no keep-alive) or for more
/// than `max` (`broker.max_keep_alive_s`, 0: no maximum) is told to use `max` and is held
/// to it [MQTT-3.2.2-21], so its death on a half-open link is noticed and its will
/// published. An MQTT 3.1.1 client cannot be told, and keeps the value it asked for.
fn keep_alive(version: Version, asked: u16, max: u16) -> (u16, Option<u16>) {
    let beyond_max = max > 0 && (asked == 0 || asked > max);
    if version == Version::V5 && beyond_max {
        (max, Some(max))
    } else {
        (asked, None)
    }
}

/// Packets from one client waiting for the router before its socket is no longer read.
const ROUTER_BACKLOG: usize = 1024;

/// Deliveries held for a client's Receive Maximum before the router is no longer woken.
const HOLD_LIMIT: usize = 1024;

/// The Topic Alias Maximum rumqttd's router announces in CONNACK.
const TOPIC_ALIAS_MAX: u16 = 4096;

impl Session {
    /// Authenticates the CONNECT, registers the client with the router and answers CONNACK.
    /// Returns None when the client was refused (the CONNACK said why).
    async fn open(
        mut io: Io,
        connect: Packet,
        peer: SocketAddr,
        listener: &ListenerPolicy,
        ctx: &Arc<Context>,
    ) -> Option<Session> {
        let Packet::Connect(connect, properties, will, will_properties, login) = connect else {
            unreachable!("read_connect only returns CONNECT")
        };
        let version = io.codec.0;
        let refuse = |code: ConnectReturnCode, reason: &'static str| {
            ctx.metrics.refused(reason);
            (code, reason)
        };

        let result = async {
            // Client identifier.
            let mut client_id = connect.client_id.clone();
            let mut assigned = None;
            if client_id.is_empty() {
                if !connect.clean_session {
                    return Err(refuse(
                        ConnectReturnCode::ClientIdentifierNotValid,
                        "invalid_client_id",
                    ));
                }
                client_id = format!("fbbus-{:016x}", rand_id());
                assigned = Some(client_id.clone());
            }
            // Control characters too (MQTT 1.5.4: a server may refuse them): a client id
            // goes into logs, metrics' neighbours and the registry as given.
            if is_reserved_client_id(&client_id)
                || client_id.contains(['+', '#', '/', '$'])
                || client_id.chars().any(char::is_control)
            {
                return Err(refuse(
                    ConnectReturnCode::ClientIdentifierNotValid,
                    "invalid_client_id",
                ));
            }

            // 1. Authenticate.
            let username = login
                .as_ref()
                .map(|l| l.username.clone())
                .filter(|u| !u.is_empty());
            let credentials = login
                .map(|l| (l.username, l.password))
                .filter(|(u, _)| !u.is_empty());
            match ctx
                .authenticator
                .authenticate(peer.ip(), credentials, listener.anonymous)
                .await
            {
                Outcome::Accepted => {}
                Outcome::BadCredentials => {
                    return Err(refuse(
                        ConnectReturnCode::BadUserNamePassword,
                        "bad_credentials",
                    ))
                }
                Outcome::MissingCredentials => {
                    return Err(refuse(
                        ConnectReturnCode::NotAuthorized,
                        "missing_credentials",
                    ))
                }
                Outcome::Throttled(_) => {
                    return Err(refuse(
                        ConnectReturnCode::ConnectionRateExceeded,
                        "throttled",
                    ))
                }
            }

            // 2. Authorize the will topic: a will may only go where the client may publish.
            let session_expiry = properties
                .as_ref()
                .and_then(|p| p.session_expiry_interval)
                .unwrap_or(0);
            let will = will.map(|w| Will::from_connect(w, will_properties, session_expiry));
            if let Some(w) = &will {
                let topic = String::from_utf8_lossy(&w.topic);
                let identity = Identity {
                    username: username.as_deref(),
                    client_id: &client_id,
                };
                // `fbbus/` is the broker's: a will there could forge registry records.
                let allowed = security::acl::valid_topic(&topic)
                    && !topic.starts_with(fb_bridge::topic::BROKER_NAMESPACE)
                    && ctx
                        .acl
                        .as_ref()
                        .is_none_or(|acl| acl.get().can_publish(identity, &topic));
                if !allowed {
                    ctx.metrics.acl_denied.with_label_values(&["will"]).inc();
                    tracing::warn!(client_id, ?topic, "will topic not allowed; CONNECT refused");
                    return Err(refuse(
                        ConnectReturnCode::NotAuthorized,
                        "will_not_authorized",
                    ));
                }
            }

            // Register with the router (this takes over an older session with the same id).
            ctx.wills.cancel_delayed(&client_id);
            // The session number is taken before the router link, because linking is what
            // ends an older connection with this id, and that one must see it is stale.
            let (session, predecessor_running) = ctx.sessions.open(&client_id);
            if match username.as_deref() {
                Some(user) => user == client_id,
                None => ctx.fb.anonymous_devices,
            } {
                ctx.fb.registry.session_started(&client_id, session);
            }
            // Session lifetime. rumqttd keeps a link's session after it ends unless the link
            // is clean (the MQTT 3.1.1 rule). MQTT 5 separates the two: Clean Start discards
            // an existing session now, Session Expiry decides whether this one outlives the
            // connection. So a v5 link is clean only for Clean Start with expiry 0; Clean
            // Start with expiry > 0 first ends the old session with a purge link.
            let lifetime = match version {
                Version::V311 => SessionLifetime::v311(connect.clean_session),
                Version::V5 => SessionLifetime::v5(connect.clean_session, session_expiry),
            };
            if lifetime.purge_before_link {
                purge_router_session(&ctx.router, &client_id).await;
            }
            // Topic Alias Maximum 0 towards the router: rumqttd 0.20 keys the aliases it
            // sends by subscription filter, so two topics matching one wildcard would share
            // an alias. fbbus sends full topic names.
            let linked = ctx.router.link(&client_id, lifetime.clean_link, 0).await;
            let (link_tx, link_rx, ack) = match linked {
                Ok(link) => link,
                Err(e) => {
                    ctx.sessions
                        .close_with(&client_id, session, Remains::Nothing, |superseded| {
                            ctx.redeliveries.abandoned(&client_id, session, superseded)
                        });
                    tracing::error!(client_id, error = %e, "router refused the connection");
                    return Err(refuse(
                        ConnectReturnCode::ServerUnavailable,
                        "router_refused",
                    ));
                }
            };
            Ok(Accepted {
                client_id,
                assigned,
                username,
                will,
                session,
                predecessor_running,
                lifetime,
                link_tx,
                link_rx,
                ack,
            })
        }
        .await;

        let accepted = match result {
            Ok(accepted) => accepted,
            Err((code, reason)) => {
                tracing::info!(%peer, client_id = %connect.client_id, reason, "CONNECT refused");
                let _ = io.send(connack(code, None)).await;
                return None;
            }
        };

        let (keep_alive_s, server_keep_alive) =
            keep_alive(version, connect.keep_alive, ctx.max_keep_alive);
        let mut connack_packet: Option<Packet> = accepted.ack.into();
        if let Some(Packet::ConnAck(_, props)) = &mut connack_packet {
            let mut p = props.take().unwrap_or_default();
            p.assigned_client_identifier = accepted.assigned;
            p.receive_max = Some(ctx.max_inflight);
            p.max_packet_size = Some(ctx.max_packet as u32);
            p.server_keep_alive = server_keep_alive;
            *props = Some(p);
        }
        if let Some(packet) = connack_packet {
            io.queue(packet);
        }
        if io.flush().await.is_err() {
            let _ = unlink(accepted.link_tx).await;
            let remains = accepted.lifetime.remains();
            ctx.sessions.close_with(
                &accepted.client_id,
                accepted.session,
                remains,
                |superseded| {
                    ctx.redeliveries
                        .abandoned(&accepted.client_id, accepted.session, superseded)
                },
            );
            // It may have taken an online device's session over: that device is gone now.
            ctx.fb.registry.disconnected(
                &accepted.client_id,
                accepted.session,
                DisconnectReason::Abrupt.description(),
            );
            return None;
        }

        ctx.metrics.connects.inc();
        ctx.metrics.connections.inc();
        let mut fb = FbSession::new(
            &ctx.fb,
            &accepted.client_id,
            accepted.username.as_deref(),
            accepted.session,
        );
        if fb.identity_verified() {
            fb.set_interface(
                ctx.fb
                    .registry
                    .connected(&accepted.client_id, accepted.session),
            );
        }
        tracing::info!(
            %peer,
            listener = listener.name,
            client_id = accepted.client_id,
            username = accepted.username.as_deref().unwrap_or(""),
            version = ?version,
            keep_alive = keep_alive_s,
            "client connected"
        );
        let ids = if accepted.lifetime.clean_link || accepted.lifetime.purge_before_link {
            ctx.redeliveries.forget(&accepted.client_id);
            PacketIds::default()
        } else {
            let handed_over = ctx
                .redeliveries
                .take(
                    &accepted.client_id,
                    accepted.session,
                    accepted.predecessor_running,
                )
                .await;
            PacketIds::resumed(handed_over)
        };
        Some(Session {
            io,
            peer,
            client_id: accepted.client_id.into(),
            username: accepted.username,
            version,
            // MQTT 3.1.2.10: 0 turns the keep-alive mechanism off.
            keep_alive: (keep_alive_s > 0)
                .then(|| Duration::from_secs(keep_alive_s as u64).mul_f32(1.5)),
            client_max_packet: properties
                .as_ref()
                .and_then(|p| p.max_packet_size)
                .map(|m| m as usize),
            will: accepted.will.map(Box::new),
            link_tx: accepted.link_tx,
            link_rx: accepted.link_rx,
            session: accepted.session,
            lifetime: accepted.lifetime,
            ctx: Arc::clone(ctx),
            to_router: Vec::new(),
            inflight_in: 0,
            ack_order: AckOrder::default(),
            client_receive_max: properties
                .as_ref()
                .and_then(|p| p.receive_maximum)
                .filter(|m| *m > 0)
                .unwrap_or(u16::MAX),
            outstanding_out: 0,
            ids,
            rare: None,
            held: VecDeque::new(),
            wake_pending: false,
            subscriptions: BTreeMap::new(),
            special_subscriptions: false,
            fb,
        })
    }

    /// The connection's loop: network reads, router deliveries, keep-alive, shutdown.
    ///
    /// The loop only waits here; what it was woken for is handled in a boxed future, so
    /// the connection's task holds the small waiting state while the device is idle and
    /// the larger state of handling a batch only while it handles one (`serve`).
    async fn run(&mut self) -> End {
        let mut shutdown = self.ctx.shutdown.clone();
        let far_future = Instant::now() + Duration::from_secs(100 * 365 * 24 * 3600);
        let deadline =
            tokio::time::sleep_until(self.keep_alive.map_or(far_future, |k| Instant::now() + k));
        tokio::pin!(deadline);
        // Packets that came in the same read as CONNECT (a client that does not wait for
        // CONNACK): handled now, not when the socket next has something.
        if !self.io.read.is_empty() {
            if let Err(end) = Box::pin(self.read_packets()).await {
                return end;
            }
        }
        loop {
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
                }
            } else {
                tokio::select! {
                    _ = shutdown.changed() => return End::Shutdown,
                    _ = &mut deadline => return End::KeepAlive,
                    read = self.io.fill() => Wake::Read(read),
                    linked = self.link_rx.wait() => Wake::Router { linked: linked.is_ok() },
                }
            };
            let handled = match wake {
                Wake::Backlogged => {
                    // Not reading is the broker's choice, not client silence.
                    if let Some(k) = self.keep_alive {
                        deadline.as_mut().reset(Instant::now() + k);
                    }
                    Ok(())
                }
                Wake::Read(read) => {
                    let n = match read {
                        Ok(n) => n,
                        Err(_) => return End::Abrupt,
                    };
                    self.ctx.metrics.bytes_in.inc_by(n as u64);
                    if let Some(k) = self.keep_alive {
                        deadline.as_mut().reset(Instant::now() + k);
                    }
                    Box::pin(self.read_packets()).await
                }
                Wake::Router { linked: true } => Box::pin(self.deliver()).await,
                Wake::Router { linked: false } => Err(Box::pin(self.router_dropped()).await),
            };
            if let Err(end) = handled {
                return end;
            }
        }
    }

    /// Handles every complete packet in the read buffer, then hands the batch to the router.
    async fn read_packets(&mut self) -> Result<(), End> {
        loop {
            let header = match self.io.next_frame() {
                Ok(Some(header)) => header,
                Ok(None) => break,
                Err(ReadError::Oversized { size, max }) => {
                    self.ctx.metrics.oversized_packets.inc();
                    tracing::warn!(
                        client_id = &*self.client_id,
                        size,
                        max,
                        "packet over max_packet_bytes; connection closed"
                    );
                    return Err(End::Oversized);
                }
                Err(e) => {
                    self.ctx.metrics.malformed_packets.inc();
                    tracing::warn!(client_id = &*self.client_id, error = %e, "malformed packet; connection closed");
                    return Err(End::Malformed);
                }
            };
            let qos_pkid = frame::publish_qos_and_pkid(&self.io.read, &header);
            let decoded = self.io.decode(&header);
            let end = match decoded {
                Ok(packet) => self.inbound(packet, qos_pkid).err(),
                Err(ReadError::ServerOnlyType(t)) => {
                    tracing::warn!(
                        client_id = &*self.client_id,
                        packet_type = t,
                        "server-only packet type from a client; connection closed"
                    );
                    Some(End::ProtocolError(DisconnectReasonCode::ProtocolError))
                }
                Err(e) => {
                    self.ctx.metrics.malformed_packets.inc();
                    tracing::warn!(client_id = &*self.client_id, error = %e, "malformed packet; connection closed");
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
        self.io.flush().await.map_err(|_| End::Abrupt)?;
        if self.wake_pending && self.held.len() < HOLD_LIMIT {
            self.wake_pending = false;
            self.link_rx.wake().await.map_err(|_| End::Router)?;
        }
        Ok(())
    }

    /// The packet path for one packet from the client (see the module doc).
    fn inbound(&mut self, packet: Packet, qos_pkid: Option<(u8, u16)>) -> Result<(), End> {
        // Acknowledgements of deliveries carry the client's packet ids; from here on the
        // packet path works with the router's (`packet_ids`).
        let packet = self.ids.from_client(packet);
        match packet {
            Packet::Publish(publish, properties) => {
                let (qos, pkid) = qos_pkid.unwrap_or((0, 0));
                self.on_publish(publish, properties, qos, pkid)
            }
            Packet::Subscribe(subscribe, properties) => {
                self.on_subscribe(subscribe, properties);
                Ok(())
            }
            Packet::PubRel(pubrel, _) => {
                if self
                    .rare
                    .as_mut()
                    .is_some_and(|r| r.refused_qos2.remove(&pubrel.pkid))
                {
                    // A refused QoS 2 exchange ends here, never in the router, which drops
                    // a connection that releases a packet id it never saw.
                    let reason = match self.version {
                        Version::V5 => PubCompReason::PacketIdentifierNotFound,
                        Version::V311 => PubCompReason::Success,
                    };
                    self.io.queue(Packet::PubComp(
                        PubComp {
                            pkid: pubrel.pkid,
                            reason,
                        },
                        None,
                    ));
                } else {
                    // rumqttd 0.20 ignores a PUBREL carrying MQTT 5 properties (reason
                    // string, user properties), which mean nothing to the router anyway.
                    self.to_router.push(Packet::PubRel(pubrel, None));
                }
                Ok(())
            }
            Packet::PubAck(ack, _)
                if self
                    .rare
                    .as_mut()
                    .is_some_and(|r| r.qos2_sent_as_qos1.remove(&ack.pkid)) =>
            {
                self.outstanding_out = self.outstanding_out.saturating_sub(1);
                self.ack_for_client(2, ack.pkid);
                Ok(())
            }
            Packet::PubAck(ack, properties) => {
                self.outstanding_out = self.outstanding_out.saturating_sub(1);
                let pkid = ack.pkid;
                let packet = Packet::PubAck(ack, properties);
                self.ack_order.ack(pkid, packet, &mut self.to_router);
                Ok(())
            }
            Packet::PubRec(rec, properties) => {
                let pkid = rec.pkid;
                let packet = Packet::PubRec(rec, properties);
                self.ack_order.ack(pkid, packet, &mut self.to_router);
                Ok(())
            }
            Packet::PubComp(comp, properties) => {
                self.outstanding_out = self.outstanding_out.saturating_sub(1);
                let pkid = comp.pkid;
                let packet = Packet::PubComp(comp, properties);
                self.ack_order.complete(pkid, packet, &mut self.to_router);
                Ok(())
            }
            Packet::Unsubscribe(unsubscribe, properties) => {
                if let Some(bridge) = self.ctx.bridge.get() {
                    for f in &unsubscribe.filters {
                        if self.subscriptions.contains_key(f) {
                            bridge.unsubscribed(f);
                        }
                    }
                }
                self.remember_subscriptions(std::iter::empty(), &unsubscribe.filters);
                self.to_router
                    .push(Packet::Unsubscribe(unsubscribe, properties));
                Ok(())
            }
            Packet::PingReq(_) => {
                self.io.queue(Packet::PingResp(PingResp));
                Ok(())
            }
            Packet::Disconnect(disconnect, _) => Err(End::Client {
                with_will: disconnect.reason_code
                    == DisconnectReasonCode::DisconnectWithWillMessage,
            }),
            Packet::Connect(..) => {
                tracing::warn!(
                    client_id = &*self.client_id,
                    "second CONNECT; connection closed"
                );
                Err(End::ProtocolError(DisconnectReasonCode::ProtocolError))
            }
            // Server-only types never get here: `decode_frame` refuses them.
            _ => Err(End::ProtocolError(DisconnectReasonCode::ProtocolError)),
        }
    }

    fn on_publish(
        &mut self,
        publish: Publish,
        properties: Option<PublishProperties>,
        qos: u8,
        pkid: u16,
    ) -> Result<(), End> {
        let topic = self.resolve_topic(&publish, properties.as_ref())?;
        if self.ctx.test_panic_topic.as_deref() == Some(topic.as_str()) {
            panic!("test_panic_topic: {} published on {topic}", self.client_id);
        }

        // 2. Authorize.
        if !self.may_publish(&topic) {
            self.ctx
                .metrics
                .acl_denied
                .with_label_values(&["publish"])
                .inc();
            self.log_denial("publish", &topic);
            self.refuse_publish(qos, pkid, Refusal::NotAuthorized);
            return Ok(());
        }

        // 3. Check typed FB topics; declarations end here.
        let routes = match self.fb.check(&self.ctx.fb, &topic, &publish.payload) {
            Check::Pass => Vec::new(),
            Check::Route(routes) => routes,
            Check::Consumed => {
                self.acknowledge_consumed(qos, pkid);
                return Ok(());
            }
            Check::Refused(rejection) => {
                self.refuse_publish(qos, pkid, rejection.refusal);
                return Ok(());
            }
        };

        // 4. Route, 5. meter. The router gets the full topic, never an alias.
        if qos > 0 {
            self.inflight_in = self.inflight_in.saturating_add(1);
            if self.version == Version::V5 && self.inflight_in > self.ctx.max_inflight {
                tracing::warn!(client_id = &*self.client_id, receive_maximum = self.ctx.max_inflight,
                    "more unacknowledged QoS 1/2 publications than the Receive Maximum; connection closed");
                return Err(End::ProtocolError(
                    DisconnectReasonCode::ReceiveMaximumExceeded,
                ));
            }
        }
        let mut publish = publish;
        let mut properties = properties;
        if let Some(p) = properties.as_mut().filter(|p| p.topic_alias.is_some()) {
            p.topic_alias = None;
            publish.topic = topic.into();
        }
        let retain = publish.retain;
        let origin = origin::new(qos, retain, &self.client_id);
        self.ctx.metrics.messages_in.inc();
        let mut routes = routes.into_iter();
        if let Some((topic, payload)) = routes.next() {
            // A typed message: the canonical encoding travels at the publication's QoS and
            // packet id (the router acknowledges it), the re-encodings as QoS 0 copies
            // carrying the same origin, so subscribers get them at the same delivery QoS.
            for (topic, payload) in routes {
                let copy = crate::broker_publisher::publish_packet(topic, payload, 0, retain, 0);
                let mut copy = copy;
                origin::mark(&mut copy, origin.clone());
                self.to_router
                    .push(Packet::Publish(copy, properties.clone()));
            }
            publish.topic = topic.into();
            publish.payload = payload;
        }
        origin::mark(&mut publish, origin);
        self.to_router.push(Packet::Publish(publish, properties));
        Ok(())
    }

    /// Acknowledges a publication the broker consumed (a declaration).
    fn acknowledge_consumed(&mut self, qos: u8, pkid: u16) {
        match qos {
            1 => self.io.queue(Packet::PubAck(
                PubAck {
                    pkid,
                    reason: PubAckReason::Success,
                },
                None,
            )),
            2 => {
                self.io.queue(Packet::PubRec(
                    PubRec {
                        pkid,
                        reason: PubRecReason::Success,
                    },
                    None,
                ));
                // The PUBREL is answered here, like a refused one's: the router never saw it.
                self.rare().refused_qos2.insert(pkid);
            }
            _ => {}
        }
    }

    /// The topic a PUBLISH goes to, following MQTT 5 topic aliases.
    fn resolve_topic(
        &mut self,
        publish: &Publish,
        properties: Option<&PublishProperties>,
    ) -> Result<String, End> {
        let Ok(topic) = std::str::from_utf8(&publish.topic) else {
            return Err(End::Malformed);
        };
        let alias = properties.and_then(|p| p.topic_alias);
        let topic = match (topic.is_empty(), alias) {
            (_, Some(alias)) if alias == 0 || alias > TOPIC_ALIAS_MAX => {
                return Err(End::ProtocolError(DisconnectReasonCode::TopicAliasInvalid))
            }
            (false, Some(alias)) => {
                self.rare().topic_aliases.insert(alias, topic.to_owned());
                topic.to_owned()
            }
            (false, None) => topic.to_owned(),
            (true, Some(alias)) => {
                match self.rare.as_ref().and_then(|r| r.topic_aliases.get(&alias)) {
                    Some(t) => t.clone(),
                    None => {
                        return Err(End::ProtocolError(DisconnectReasonCode::TopicAliasInvalid))
                    }
                }
            }
            (true, None) => return Err(End::ProtocolError(DisconnectReasonCode::TopicNameInvalid)),
        };
        if !security::acl::valid_topic(&topic) {
            tracing::warn!(
                client_id = &*self.client_id,
                ?topic,
                "invalid topic name in PUBLISH; connection closed"
            );
            return Err(End::ProtocolError(DisconnectReasonCode::TopicNameInvalid));
        }
        Ok(topic)
    }

    /// Answers a refused publication. MQTT 5 says "not authorized"; MQTT 3.1.1 has no way
    /// to refuse a PUBLISH, so like Mosquitto it is acknowledged and dropped — otherwise
    /// the device's in-flight window would fill with retries that can never succeed.
    fn refuse_publish(&mut self, qos: u8, pkid: u16, refusal: Refusal) {
        let v5 = self.version == Version::V5;
        let (ack, rec) = match (v5, refusal) {
            (false, _) => (PubAckReason::Success, PubRecReason::Success),
            (true, Refusal::NotAuthorized) => {
                (PubAckReason::NotAuthorized, PubRecReason::NotAuthorized)
            }
            (true, Refusal::TopicNameInvalid) => (
                PubAckReason::TopicNameInvalid,
                PubRecReason::TopicNameInvalid,
            ),
            (true, Refusal::PayloadFormatInvalid) => (
                PubAckReason::PayloadFormatInvalid,
                PubRecReason::PayloadFormatInvalid,
            ),
        };
        match qos {
            1 => self
                .io
                .queue(Packet::PubAck(PubAck { pkid, reason: ack }, None)),
            2 => {
                self.io
                    .queue(Packet::PubRec(PubRec { pkid, reason: rec }, None));
                // MQTT 5 clients should not send PUBREL after a refusing PUBREC; some
                // (paho 2.2) do, so the id is remembered for both versions.
                self.rare().refused_qos2.insert(pkid);
            }
            _ => {}
        }
    }

    fn on_subscribe(&mut self, subscribe: Subscribe, properties: Option<SubscribeProperties>) {
        let v5 = self.version == Version::V5;
        let mut refused = Vec::with_capacity(subscribe.filters.len());
        for filter in &subscribe.filters {
            let verdict = if !security::acl::valid_filter(&filter.path) {
                Some(if v5 {
                    SubscribeReasonCode::TopicFilterInvalid
                } else {
                    SubscribeReasonCode::Failure
                })
            } else if !self.may_subscribe(&filter.path) {
                self.ctx
                    .metrics
                    .acl_denied
                    .with_label_values(&["subscribe"])
                    .inc();
                self.log_denial("subscribe", &filter.path);
                Some(if v5 {
                    SubscribeReasonCode::NotAuthorized
                } else {
                    SubscribeReasonCode::Failure
                })
            } else if filter.path.starts_with('$') && !filter.path.starts_with("$share/") {
                // fbbus publishes nothing under `$` topics yet, and rumqttd's router drops a
                // connection that subscribes to one: refuse the filter, keep the client.
                Some(if v5 {
                    SubscribeReasonCode::ImplementationSpecific
                } else {
                    SubscribeReasonCode::Failure
                })
            } else {
                None
            };
            refused.push(verdict);
        }

        let granted = subscribe
            .filters
            .iter()
            .zip(&refused)
            .filter(|(_, r)| r.is_none())
            .map(|(f, _)| f);
        let granted: Vec<&Filter> = granted.collect();
        for filter in &granted {
            self.ctx.fb.subscribed(&filter.path);
            if let Some(bridge) = self.ctx.bridge.get() {
                if !self.subscriptions.contains_key(&filter.path) {
                    bridge.subscribed(&filter.path);
                }
            }
        }
        self.remember_subscriptions(granted.into_iter(), &[]);
        if refused.iter().all(Option::is_none) {
            self.to_router
                .push(Packet::Subscribe(subscribe, properties));
            return;
        }
        if refused.iter().all(Option::is_some) {
            let return_codes = refused.into_iter().flatten().collect();
            self.io.queue(Packet::SubAck(
                SubAck {
                    pkid: subscribe.pkid,
                    return_codes,
                },
                None,
            ));
            return;
        }
        // Some filters allowed: the router gets those, and its SUBACK is completed with the
        // refusals in `outbound` so the client sees one code per filter, in order.
        let allowed = subscribe
            .filters
            .into_iter()
            .zip(&refused)
            .filter(|(_, r)| r.is_none())
            .map(|(f, _)| f)
            .collect();
        self.rare()
            .partial_subscribes
            .insert(subscribe.pkid, refused);
        self.to_router.push(Packet::Subscribe(
            Subscribe {
                pkid: subscribe.pkid,
                filters: allowed,
            },
            properties,
        ));
    }

    /// The session's [`Rare`] state, allocated on first use.
    fn rare(&mut self) -> &mut Rare {
        self.rare.get_or_insert_with(Box::default)
    }

    fn identity(&self) -> Identity<'_> {
        Identity {
            username: self.username.as_deref(),
            client_id: &self.client_id,
        }
    }

    fn may_publish(&self, topic: &str) -> bool {
        self.ctx
            .acl
            .as_ref()
            .is_none_or(|acl| acl.get().can_publish(self.identity(), topic))
    }

    fn may_subscribe(&self, filter: &str) -> bool {
        self.ctx
            .acl
            .as_ref()
            .is_none_or(|acl| acl.get().can_subscribe(self.identity(), filter))
    }

    fn log_denial(&mut self, action: &'static str, topic: &str) {
        let logged = &mut self.rare().logged_denials;
        if logged.len() >= MAX_LOGGED_DENIALS {
            return;
        }
        if logged.insert((action, topic.to_owned())) {
            tracing::warn!(
                client_id = &*self.client_id,
                username = self.username.as_deref().unwrap_or(""),
                action,
                topic = ?topic,
                "denied by ACL (logged once per client and topic)"
            );
        }
    }

    /// Hands the accepted packets of this read to the router: one wake-up per batch.
    /// Then publishes the broker's answers to them (diagnostics), which must reach the
    /// router after the packets they answer (a SUBSCRIBE to the diag topic among them).
    async fn route(&mut self) -> Result<(), End> {
        if let Some(last) = self.to_router.pop() {
            {
                let mut buffer = self.link_tx.buffer();
                buffer.extend(self.to_router.drain(..));
            }
            self.link_tx.send(last).await.map_err(|_| End::Router)?;
        }
        self.ctx.fb.publish(self.fb.take_outbox());
        Ok(())
    }

    /// Writes what the router delivered, draining everything it has queued.
    async fn deliver(&mut self) -> Result<(), End> {
        let mut unscheduled = false;
        loop {
            match self.link_rx.recv_deadline(std::time::Instant::now()) {
                Ok(Some(Notification::Unschedule)) => unscheduled = true,
                Ok(Some(notification)) => self.outbound(notification),
                Ok(None) => {}
                Err(LinkError::RecvTimeout(_)) => break,
                Err(_) => return Err(self.router_dropped().await),
            }
        }
        self.route().await?;
        let written = self.io.flush().await.map_err(|_| End::Abrupt)?;
        self.ctx.metrics.bytes_out.inc_by(written as u64);
        if unscheduled {
            if self.held.len() < HOLD_LIMIT {
                self.link_rx.wake().await.map_err(|_| End::Router)?;
            } else {
                self.wake_pending = true;
            }
        }
        Ok(())
    }

    /// The router dropped this link: either a newer connection took the client id over,
    /// or the router refused something this client sent.
    async fn router_dropped(&mut self) -> End {
        let _ = self.io.flush().await;
        if self.ctx.sessions.is_current(&self.client_id, self.session) {
            tracing::warn!(
                client_id = &*self.client_id,
                "the router ended the connection"
            );
            End::Router
        } else {
            End::Takeover
        }
    }

    /// Sends held deliveries while the client's Receive Maximum allows.
    fn release_held(&mut self) {
        while self.outstanding_out < self.client_receive_max {
            let Some((publish, properties)) = self.held.pop_front() else {
                break;
            };
            self.deliver_publish(publish, properties);
        }
    }

    /// One packet from the router to the client.
    fn outbound(&mut self, notification: Notification) {
        let packet: Option<Packet> = notification.into();
        match packet {
            Some(Packet::SubAck(mut suback, properties)) => {
                let refused = self
                    .rare
                    .as_mut()
                    .and_then(|r| r.partial_subscribes.remove(&suback.pkid));
                if let Some(refused) = refused {
                    let mut granted = suback.return_codes.into_iter();
                    suback.return_codes = refused
                        .into_iter()
                        .map(|r| {
                            r.or_else(|| granted.next())
                                .unwrap_or(SubscribeReasonCode::Unspecified)
                        })
                        .collect();
                }
                self.io.queue(Packet::SubAck(suback, properties));
            }
            Some(Packet::Publish(publish, properties)) => {
                // Order is kept: once something is held, everything after it waits too.
                if self.held.is_empty() && self.outstanding_out < self.client_receive_max {
                    self.deliver_publish(publish, properties);
                } else {
                    self.held.push_back((publish, properties));
                }
            }
            Some(Packet::PubRel(mut pubrel, properties)) => {
                self.ack_order.released(pubrel.pkid);
                if self
                    .rare
                    .as_mut()
                    .is_some_and(|r| r.dropped_qos2.remove(&pubrel.pkid))
                {
                    let complete = Packet::PubComp(
                        PubComp {
                            pkid: pubrel.pkid,
                            reason: PubCompReason::Success,
                        },
                        None,
                    );
                    self.ack_order
                        .complete(pubrel.pkid, complete, &mut self.to_router);
                } else {
                    pubrel.pkid = self.ids.release(pubrel.pkid);
                    self.io.queue(Packet::PubRel(pubrel, properties));
                }
            }
            Some(packet) => {
                if matches!(packet, Packet::PubAck(..) | Packet::PubComp(..)) {
                    self.inflight_in = self.inflight_in.saturating_sub(1);
                }
                self.io.queue(packet)
            }
            None => {}
        }
    }

    /// Encodes one delivery, applying the MQTT rules rumqttd 0.20's router leaves out, in
    /// this order:
    /// - the subscriptions' options ([`Session::subscription_options`]): No Local and
    ///   Retain Handling 2 may drop the delivery, Retain As Published restores RETAIN;
    /// - the delivery QoS is min(publication QoS, subscription QoS) [MQTT-3.8.4-8]: the
    ///   router sends at the subscription's QoS, so a lower publication QoS is restored from
    ///   the message's `origin`;
    /// - a packet over the client's Maximum Packet Size is not sent [MQTT-3.1.2-25].
    ///
    /// A QoS 1/2 delivery goes out under the packet id the client sees ([`PacketIds`]):
    /// the original id and DUP=1 when it re-sends what an earlier connection of the session
    /// left unacknowledged [MQTT-4.4.0-1] [MQTT-3.3.1-1]. Whatever the client is not sent at
    /// the router's QoS is acknowledged to the router for it ([`Session::ack_for_client`]).
    fn deliver_publish(&mut self, mut publish: Publish, properties: Option<PublishProperties>) {
        let origin = origin::take(&mut publish);
        let published = origin.as_ref().map(|o| o.qos);
        let (deliver, retain_as_published) = self.subscription_options(&publish, origin.as_ref());
        if retain_as_published {
            publish.retain = true;
        }
        // `pkid` stays the router's; the client sees `client_pkid`.
        let (routed_qos, pkid) = publish.qos_and_pkid();
        let (client_pkid, dup) = if routed_qos > 0 {
            let print = redelivery::fingerprint(&publish.topic, &publish.payload);
            let delivery = self.ids.deliver(pkid, print);
            publish.set_pkid(delivery.id);
            (delivery.id, delivery.dup)
        } else {
            (0, false)
        };
        let (topic, payload, retain) = (
            publish.topic.clone(),
            publish.payload.clone(),
            publish.retain,
        );
        let may_lower = routed_qos > 0 && matches!(published, Some(0 | 1));
        let kept_properties = if may_lower { properties.clone() } else { None };

        let before = self.io.write.len();
        self.io.queue(Packet::Publish(publish, properties));

        if routed_qos > 0 {
            self.ack_order.delivered(pkid);
        }
        if !deliver {
            self.io.write.truncate(before);
            self.ids.withdraw(client_pkid);
            self.ack_for_client(routed_qos, pkid);
            return;
        }
        let qos = published.map_or(routed_qos, |q| q.min(routed_qos));
        if may_lower && qos < routed_qos {
            self.io.write.truncate(before);
            let lower_pkid = if qos == 0 { 0 } else { client_pkid };
            let lower = crate::broker_publisher::publish_packet(
                topic.clone(),
                payload.clone(),
                qos,
                retain,
                lower_pkid,
            );
            self.io.queue(Packet::Publish(lower, kept_properties));
            if qos == 0 {
                self.ids.withdraw(client_pkid);
                self.ack_for_client(routed_qos, pkid);
            } else {
                self.rare().qos2_sent_as_qos1.insert(pkid);
            }
        }

        let size = self.io.write.len() - before;
        match self.client_max_packet {
            Some(max) if size > max => {
                self.io.write.truncate(before);
                if let Some(rare) = self.rare.as_mut() {
                    rare.qos2_sent_as_qos1.remove(&pkid);
                }
                if qos > 0 {
                    self.ids.withdraw(client_pkid);
                    self.ack_for_client(routed_qos, pkid);
                }
                self.ctx
                    .metrics
                    .messages_dropped
                    .with_label_values(&["client_max_packet_size"])
                    .inc();
                tracing::debug!(
                    client_id = &*self.client_id,
                    size,
                    max,
                    "delivery larger than the client's maximum packet size; dropped"
                );
            }
            _ => {
                self.ctx.metrics.messages_out.inc();
                if qos > 0 {
                    self.outstanding_out = self.outstanding_out.saturating_add(1);
                    if dup {
                        self.io.write[before] |= 0b0000_1000;
                    }
                }
            }
        }
    }

    /// What the client's subscription options say about one delivery: whether to send it
    /// (No Local [MQTT-3.8.3-3], Retain Handling 2 [MQTT-3.3.1-11]) and whether to set RETAIN
    /// as published [MQTT-3.3.1-12]. rumqttd's router ignores these options; a delivery
    /// with RETAIN set is a retained message sent at subscribe time (the router clears
    /// RETAIN on live deliveries). When several subscriptions match, the delivery is sent
    /// unless every matching one excludes it.
    fn subscription_options(
        &self,
        publish: &Publish,
        origin: Option<&origin::Origin>,
    ) -> (bool, bool) {
        if !self.special_subscriptions {
            return (true, false);
        }
        let Ok(topic) = std::str::from_utf8(&publish.topic) else {
            return (true, false);
        };
        let matching: Vec<&Filter> = self
            .subscriptions
            .iter()
            .filter(|(path, _)| security::acl::filter_matches(path, topic))
            .map(|(_, f)| f)
            .collect();
        if matching.is_empty() {
            return (true, false);
        }
        let own = origin.is_some_and(|o| o.publisher == self.client_id);
        if own && matching.iter().all(|f| f.nolocal) {
            return (false, false);
        }
        if publish.retain
            && matching
                .iter()
                .all(|f| matches!(f.retain_forward_rule, RetainForwardRule::Never))
        {
            return (false, false);
        }
        let retained_origin = origin.is_some_and(|o| o.retain);
        let rap = !publish.retain && retained_origin && matching.iter().any(|f| f.preserve_retain);
        (true, rap)
    }

    /// Records the client's subscriptions and whether any uses an option the router ignores.
    fn remember_subscriptions<'a>(
        &mut self,
        added: impl Iterator<Item = &'a Filter>,
        removed: &[String],
    ) {
        for f in added {
            self.subscriptions.insert(f.path.clone(), f.clone());
        }
        for path in removed {
            self.subscriptions.remove(path);
        }
        self.special_subscriptions = self.subscriptions.values().any(|f| {
            f.nolocal
                || f.preserve_retain
                || matches!(f.retain_forward_rule, RetainForwardRule::Never)
        });
    }

    /// Acknowledges a delivery to the router on the client's behalf (the client was not
    /// sent it at the router's QoS), so the session's in-flight window does not leak.
    /// At QoS 2 the router answers with PUBREL, which `outbound` completes with PUBCOMP.
    fn ack_for_client(&mut self, routed_qos: u8, pkid: u16) {
        let ack = match routed_qos {
            1 => Packet::PubAck(
                PubAck {
                    pkid,
                    reason: PubAckReason::Success,
                },
                None,
            ),
            2 => {
                self.rare().dropped_qos2.insert(pkid);
                Packet::PubRec(
                    PubRec {
                        pkid,
                        reason: PubRecReason::Success,
                    },
                    None,
                )
            }
            _ => return,
        };
        self.ack_order.ack(pkid, ack, &mut self.to_router);
    }

    /// Ends the session: tells the client why (MQTT 5), the router that it is gone,
    /// fires the will if the end calls for it, and meters the disconnect.
    async fn close(mut self, end: End) {
        // First, so a reconnecting client's next connection, which may already wait for
        // it, gets this session's open exchanges at once (`redelivery`).
        let open = if self.lifetime.clean_link {
            Resume::default()
        } else {
            std::mem::take(&mut self.ids).into_resume()
        };
        let (redeliveries, client_id, session) =
            (&self.ctx.redeliveries, &*self.client_id, self.session);
        // A kept session with an expiry is ended by the expiry task (`session_lifetime`).
        let remains = self.lifetime.remains();
        self.ctx
            .sessions
            .close_with(client_id, session, remains, |superseded| {
                redeliveries.save(client_id, session, open, superseded)
            });
        if self.version == Version::V5 {
            if let Some(reason_code) = end.v5_disconnect() {
                self.io
                    .queue(Packet::Disconnect(Disconnect { reason_code }, None));
                let _ = timeout(Duration::from_secs(1), self.io.flush()).await;
            }
        }
        let _ = timeout(Duration::from_secs(1), self.io.stream.shutdown()).await;
        if end.router_link_alive() {
            let _ = unlink(self.link_tx).await;
        }
        let will = self.will.take().filter(|_| end.fires_will());
        if let Some(will) = will.map(|w| *w) {
            // A will on a typed topic is a publication like any other: checked against
            // the declaration now, and re-encoded like one (the reference line's CONNECT
            // FB sets a BOOL output to FALSE this way).
            let topic = String::from_utf8_lossy(&will.topic).into_owned();
            match self.fb.check(&self.ctx.fb, &topic, &will.payload) {
                Check::Pass => self.ctx.wills.fire(&self.client_id, self.session, will),
                Check::Route(routes) => {
                    for (topic, payload) in routes {
                        let mut copy = will.clone();
                        copy.topic = topic.into();
                        copy.payload = payload;
                        self.ctx.wills.fire(&self.client_id, self.session, copy);
                    }
                }
                Check::Consumed | Check::Refused(_) => {}
            }
            self.ctx.fb.publish(self.fb.take_outbox());
        }
        // A clean session's subscriptions end with it; a persistent session's stay (the
        // router keeps queueing for it), and so does the bridge's import of them.
        if self.lifetime.clean_link {
            if let Some(bridge) = self.ctx.bridge.get() {
                for f in self.subscriptions.keys() {
                    bridge.unsubscribed(f);
                }
            }
        }
        self.ctx.fb.registry.disconnected(
            &self.client_id,
            self.session,
            end.reason().description(),
        );
        // An expiry of 0 ends a kept session now (MQTT 5 Clean Start 0, expiry 0); later
        // ones are the expiry task's (`session_lifetime::expire_sessions`).
        if self.lifetime.expires_after == Some(Duration::ZERO) {
            end_idle_session(&self.ctx, &self.client_id, self.session).await;
        }
        self.ctx.metrics.disconnected(end.reason());
        self.ctx.metrics.connections.dec();
        tracing::info!(
            peer = %self.peer,
            client_id = &*self.client_id,
            reason = end.reason().label(),
            "client disconnected"
        );
    }
}

/// A CONNECT that passed: everything `Session::open` builds the session from.
struct Accepted {
    client_id: String,
    /// The client id fbbus chose, when the client sent none.
    assigned: Option<String>,
    username: Option<String>,
    will: Option<Will>,
    session: u64,
    /// The client id's previous connection had not closed yet when this one started.
    predecessor_running: bool,
    lifetime: SessionLifetime,
    link_tx: LinkTx,
    link_rx: LinkRx,
    ack: Notification,
}

/// A random 64-bit id for clients that connect without one.
fn rand_id() -> u64 {
    use std::hash::{BuildHasher, Hasher};
    // RandomState is seeded from the OS per process and per instance: enough for a name.
    let mut h = std::collections::hash_map::RandomState::new().build_hasher();
    h.write_u64(
        std::time::SystemTime::now()
            .duration_since(std::time::UNIX_EPOCH)
            .map(|d| d.as_nanos() as u64)
            .unwrap_or(0),
    );
    h.finish()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn mqtt5_clients_are_held_to_the_maximum_keep_alive() {
        // Off, or beyond the maximum: told to use the maximum.
        assert_eq!(keep_alive(Version::V5, 0, 300), (300, Some(300)));
        assert_eq!(keep_alive(Version::V5, 301, 300), (300, Some(300)));
        // Within it: their own, nothing announced.
        assert_eq!(keep_alive(Version::V5, 60, 300), (60, None));
        // No maximum: whatever they ask, 0 (off) included.
        assert_eq!(keep_alive(Version::V5, 0, 0), (0, None));
        // MQTT 3.1.1 cannot be told.
        assert_eq!(keep_alive(Version::V311, 0, 300), (0, None));
        assert_eq!(keep_alive(Version::V311, 900, 300), (900, None));
    }
}

//! Opening a session: the CONNECT is checked, the client authenticated (step 1 of the
//! packet path), its client id checked against its identity (`identity`: the binding and
//! the ownership rule), its will authorized, and the session linked to the router and
//! answered with CONNACK.

use std::collections::{BTreeMap, VecDeque};
use std::net::SocketAddr;
use std::sync::Arc;
use std::time::Duration;

use rumqttd::local::{LinkRx, LinkTx};
use rumqttd::protocol::{Connect, ConnectReturnCode, Login, Packet};
use rumqttd::Notification;
use security::Identity;

use super::ack_order::AckOrder;
use super::context::Context;
use super::lifetime::{purge_router_session, SessionLifetime};
use super::packet_ids::PacketIds;
use super::table::{Owned, Refusal, Remains, Running};
use super::takeover::Finished;
use super::ListenerPolicy;
use super::Session;
use crate::authenticator::Outcome;
use crate::broker_publisher::is_reserved_client_id;
use crate::identity::Owner;
use crate::metrics::DisconnectReason;
use crate::policy::typed::FbSession;
use crate::router::unlink;
use crate::wills::Will;
use crate::wire::codec::{connack, Version};
use crate::wire::framed::Io;

/// Why a CONNECT was refused: the CONNACK code and the metric's reason label.
struct Refused {
    code: ConnectReturnCode,
    reason: &'static str,
    /// The step that refused logged it already (rate-limited).
    logged: bool,
}

fn refused(code: ConnectReturnCode, reason: &'static str) -> Refused {
    Refused {
        code,
        reason,
        logged: false,
    }
}

impl Session {
    /// Opens a session for a CONNECT, in order: the client id, authentication (step 1 of
    /// the packet path), the client id's binding to the username, the will's topic, the
    /// claim on the client id's session (the ownership rule), the router link, CONNACK,
    /// then the registry and whatever an earlier connection of the session left
    /// unacknowledged. Returns None when the client was refused (its CONNACK said why) or
    /// went away. Every refusal comes before the claim and changes nothing.
    pub(super) async fn open(
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
        let session_expiry = properties
            .as_ref()
            .and_then(|p| p.session_expiry_interval)
            .unwrap_or(0);

        let accepted = async {
            let (client_id, assigned) = client_id(&connect)?;
            let username = authenticate(ctx, peer, login.map(|l| *l), listener.anonymous).await?;
            let owner = ctx.identity.owner(username.as_deref());
            bound_to_username(ctx, peer, &client_id, username.as_deref(), &owner)?;
            not_another_users_name(ctx, peer, &client_id, username.as_deref(), &owner)?;
            let will =
                will.map(|w| Will::from_connect(*w, will_properties.map(|p| *p), session_expiry));
            authorize_will(ctx, &client_id, username.as_deref(), will.as_ref())?;
            let lifetime = match version {
                Version::V311 => SessionLifetime::v311(connect.clean_session),
                Version::V5 => SessionLifetime::v5(connect.clean_session, session_expiry),
            };
            let claimed = claim(ctx, peer, &client_id, &owner)?;
            let (linked, ack) = link(
                ctx,
                &client_id,
                username.as_deref(),
                &owner,
                claimed,
                lifetime,
            )
            .await?;
            Ok(Accepted {
                client_id,
                assigned,
                username,
                will,
                lifetime,
                linked,
                ack,
            })
        }
        .await;
        let accepted = match accepted {
            Ok(accepted) => accepted,
            Err(Refused {
                code,
                reason,
                logged,
            }) => {
                ctx.metrics.refused(reason);
                if !logged && crate::logging::OUTSIDE.allow() {
                    tracing::info!(%peer, client_id = %connect.client_id, reason, "CONNECT refused");
                }
                let _ = io.send(connack(code, None)).await;
                return None;
            }
        };

        let (keep_alive_s, server_keep_alive) =
            keep_alive(version, connect.keep_alive, ctx.max_keep_alive);
        let Opened {
            client_id,
            username,
            will,
            lifetime,
            linked,
            session_present,
        } = answer(&mut io, ctx, accepted, server_keep_alive).await?;

        ctx.metrics.connects.inc();
        ctx.metrics.connections.inc();
        ctx.metrics.note_connections_peak();
        let mut fb = FbSession::new(&ctx.fb, &client_id, username.as_deref(), linked.session);
        fb.set_peer(peer.ip());
        let profiles = ctx.fb.profiles.get();
        if let Some(profile) = profiles.identify(&client_id, username.as_deref()) {
            // A device its profile recognises is online with the profile's interface, as
            // if it had declared it; a new one beyond the registry's limits is not that
            // device on this connection (told on its diag topic).
            if fb.declare_profile(&ctx.fb, profile) {
                fb.set_activity(ctx.fb.registry.activity(&profile.device));
            }
            ctx.fb.publish(fb.take_outbox());
        } else if fb.identity_verified() {
            fb.set_interface(ctx.fb.registry.connected(&client_id, linked.session));
            fb.set_activity(ctx.fb.registry.activity(&client_id));
        }
        tracing::info!(
            %peer,
            listener = &*listener.name,
            client_id,
            username = username.as_deref().unwrap_or(""),
            version = ?version,
            keep_alive = keep_alive_s,
            profile = fb.profile().map(|p| p.device.as_str()),
            "client connected"
        );
        let (ids, subscriptions) = resume(ctx, &client_id, &linked, lifetime).await;
        let owner = ctx.identity.owner(username.as_deref());
        let share = ctx.identity.share(&owner, peer.ip());
        let (persistent, journal) = stored_session(
            ctx,
            &client_id,
            (&owner, share),
            version,
            lifetime,
            session_present,
        );
        if let Some(will) = &will {
            ctx.wills.arm(&client_id, linked.session, will);
        }
        let client_id: Arc<str> = client_id.into();
        let client = ctx.clients.connected(crate::clients::Client::new(
            (Arc::clone(&client_id), linked.session),
            username.as_deref(),
            peer,
            Arc::clone(&listener.name),
            if version == Version::V5 { 5 } else { 4 },
            keep_alive_s,
        ));
        let mut session = Session {
            io,
            version,
            // MQTT 3.1.2.10: 0 turns the keep-alive mechanism off. So does a profile whose
            // runtime never pings (`Session::relax_keep_alive`).
            keep_alive: (keep_alive_s > 0 && fb.profile().is_none_or(|p| p.enforce_keep_alive))
                .then(|| Duration::from_secs(keep_alive_s as u64).mul_f32(1.5)),
            client_alias_max: properties
                .as_ref()
                .and_then(|p| p.topic_alias_max)
                .unwrap_or(0),
            aliases_out: None,
            client_max_packet: properties
                .as_ref()
                .and_then(|p| p.max_packet_size)
                .map(|m| m as usize),
            will: will.map(Box::new),
            link_tx: linked.link_tx,
            link_rx: linked.link_rx,
            session: linked.session,
            lifetime,
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
            alive_until: tokio::time::Instant::now(),
            unhandled_read: false,
            qos0_unwritten: 0,
            ids,
            rare: None,
            read_verdicts: None,
            held: VecDeque::new(),
            held_bytes: 0,
            wake_pending: false,
            subscriptions: BTreeMap::new(),
            client,
            special_subscriptions: false,
            overlapping: false,
            fb,
            persistent,
            journal,
            durable: None,
        };
        if persistent && session_present {
            session.take_backlog();
        }
        // A resumed session's subscriptions whose options the delivery path applies.
        if !subscriptions.is_empty() {
            let filters: Vec<_> = subscriptions.into_values().collect();
            session.remember_subscriptions(filters.iter(), &[]);
        }
        Some(session)
    }
}

/// Whether the store keeps this connection's session, and the record that says so: a
/// persistent session starts or resumes (`fresh` unless the router resumed one); a clean
/// connection ends the stored session its client id had.
fn stored_session(
    ctx: &Context,
    client_id: &str,
    (owner, share): (&Owner, String),
    version: Version,
    lifetime: SessionLifetime,
    session_present: bool,
) -> (bool, crate::store::Journal) {
    let mut journal = crate::store::Journal::default();
    let Some(store) = &ctx.store else {
        return (false, journal);
    };
    let persistent = matches!(lifetime.remains(), Remains::Kept(e) if e != Some(Duration::ZERO));
    if persistent {
        store.set_session(client_id, true);
        if !session_present {
            // Whatever the store still held for this client id is not this session's.
            drop(store.take_backlog(client_id));
        }
        let record = crate::store::Record::Session {
            client: client_id.into(),
            owner: match owner {
                Owner::Anonymous => String::new(),
                Owner::User(user) => user.to_string(),
            },
            share,
            v5: version == Version::V5,
            expiry: lifetime
                .expires_after
                .map(|d| d.as_secs().min(u32::MAX as u64) as u32),
            fresh: !session_present,
        };
        journal.push(record);
        (true, journal)
    } else if store.has_session(client_id) {
        store.set_session(client_id, false);
        let record = crate::store::Record::Ended {
            client: client_id.into(),
        };
        journal.push(record);
        (false, journal)
    } else {
        (false, journal)
    }
}

/// The client id the session runs under, and whether fbbus chose it (a client may send an
/// empty one with a clean session).
fn client_id(connect: &Connect) -> Result<(String, Option<String>), Refused> {
    let invalid = || {
        refused(
            ConnectReturnCode::ClientIdentifierNotValid,
            "invalid_client_id",
        )
    };
    let (client_id, assigned) = if connect.client_id.is_empty() {
        if !connect.clean_session {
            return Err(invalid());
        }
        let id = format!("fbbus-{:016x}", rand_id());
        (id.clone(), Some(id))
    } else {
        (connect.client_id.clone(), None)
    };
    // Control characters too (MQTT 1.5.4: a server may refuse them): a client id goes
    // into logs, metrics' neighbours and the registry as given.
    if is_reserved_client_id(&client_id)
        || client_id.contains(['+', '#', '/', '$'])
        || client_id.chars().any(char::is_control)
    {
        return Err(invalid());
    }
    Ok((client_id, assigned))
}

/// Step 1 of the packet path: who is this? The verified username, if one was given.
async fn authenticate(
    ctx: &Context,
    peer: SocketAddr,
    login: Option<Login>,
    anonymous: bool,
) -> Result<Option<String>, Refused> {
    let username = login
        .as_ref()
        .map(|l| l.username.clone())
        .filter(|u| !u.is_empty());
    let credentials = login
        .map(|l| (l.username, l.password))
        .filter(|(u, _)| !u.is_empty());
    match ctx
        .authenticator
        .authenticate(peer.ip(), credentials, anonymous)
        .await
    {
        Outcome::Accepted => Ok(username),
        Outcome::BadCredentials => Err(refused(
            ConnectReturnCode::BadUserNamePassword,
            "bad_credentials",
        )),
        Outcome::MissingCredentials => Err(refused(
            ConnectReturnCode::NotAuthorized,
            "missing_credentials",
        )),
        Outcome::Throttled(_) => Err(refused(
            ConnectReturnCode::ConnectionRateExceeded,
            "throttled",
        )),
    }
}

/// `[auth] client_id`: a client that logs in with a username uses a client id bound to it
/// (`identity::ClientIdRule`), or is refused (MQTT 5 0x85, 3.1.1 0x02).
fn bound_to_username(
    ctx: &Context,
    peer: SocketAddr,
    client_id: &str,
    username: Option<&str>,
    owner: &Owner,
) -> Result<(), Refused> {
    if ctx.identity.bound(client_id, username) {
        return Ok(());
    }
    Err(client_id_refused(
        ctx,
        (peer, client_id, owner),
        "[auth] client_id does not let this user use this client id",
        "client_id_binding",
    ))
}

/// A CONNECT refused for its client id (MQTT 5 0x85, 3.1.1 0x02): logged once a minute
/// per client id and user with `why`, counted under `reason` by the caller.
fn client_id_refused(
    ctx: &Context,
    (peer, client_id, owner): (SocketAddr, &str, &Owner),
    why: &str,
    reason: &'static str,
) -> Refused {
    if ctx.identity.may_log(client_id, owner) && crate::logging::OUTSIDE.allow() {
        tracing::warn!(
            %peer,
            client_id,
            username = %owner,
            "CONNECT refused: {why} (logged once a minute per client id and user; all \
             counted in fbbus_connects_refused_total{{reason=\"{reason}\"}})"
        );
    }
    Refused {
        logged: true,
        ..refused(ConnectReturnCode::ClientIdentifierNotValid, reason)
    }
}

/// A client id that is the name of a user of the password file is that user's: no other
/// client (another user, or an anonymous one on a loopback listener) may open a session
/// under it (MQTT 5 0x85, 3.1.1 0x02), whatever `[auth] client_id` allows. Without it a
/// user could open a kept session under a device's id while the device has none, and the
/// ownership rule would then refuse the device its own id for good (issue 33). Once the
/// client id has a session, the ownership rule (`claim`) decides; other client ids stay
/// free under `client_id = "any"`.
fn not_another_users_name(
    ctx: &Context,
    peer: SocketAddr,
    client_id: &str,
    username: Option<&str>,
    owner: &Owner,
) -> Result<(), Refused> {
    if username == Some(client_id)
        || !ctx.authenticator.is_user(client_id)
        || ctx.sessions.holds(client_id)
    {
        return Ok(());
    }
    Err(client_id_refused(
        ctx,
        (peer, client_id, owner),
        "this client id is the name of another user of the password file, reserved for \
         that user",
        "client_id_reserved",
    ))
}

/// The ownership rule (`identity`): a client id's session, connected or kept, belongs to
/// the identity that created it. Another identity's CONNECT is refused (MQTT 5 0x85, 3.1.1
/// 0x02) here, before anything of that session is touched: no delayed will cancelled, no
/// session number taken, no registry change, no router link (which would take the session
/// over). Otherwise the client id's next session number is taken, before the router link,
/// because linking is what ends an older connection with this id, and that one must see it
/// is stale. Returns the session number and the previous connection if it still runs.
fn claim(
    ctx: &Context,
    peer: SocketAddr,
    client_id: &str,
    owner: &Owner,
) -> Result<(u64, Option<Running>), Refused> {
    // The identity sessions are counted for: the verified username, else the peer's
    // address (every client when there is no password file).
    let identity = match owner {
        Owner::User(user) => format!("user:{user}"),
        Owner::Anonymous => format!("ip:{}", peer.ip()),
    };
    let max = ctx.max_sessions_per_identity;
    let Owned { connected } =
        match ctx
            .sessions
            .open_counted(client_id, owner, Some(&identity), Some(max))
        {
            Ok(claimed) => return Ok(claimed),
            Err(Refusal::Owned(owned)) => owned,
            Err(Refusal::Quota) => return Err(over_quota(ctx, peer, client_id, &identity, max)),
        };
    if ctx.identity.may_log(client_id, owner) && crate::logging::OUTSIDE.allow() {
        tracing::warn!(
            %peer,
            client_id,
            username = %owner,
            session = if connected { "connected" } else { "kept offline" },
            "CONNECT refused: this client id's session belongs to another identity \
             (logged once a minute per client id and user; all counted in \
             fbbus_connects_refused_total{{reason=\"client_id_owned\"}})"
        );
    }
    Err(Refused {
        logged: true,
        ..refused(
            ConnectReturnCode::ClientIdentifierNotValid,
            "client_id_owned",
        )
    })
}

/// A CONNECT beyond `[broker] max_sessions_per_identity`: refused with MQTT 5 0x97 Quota
/// exceeded (3.1.1 has no such code: 0x05 Not authorized, the closest that tells a client
/// not to retry at once), counted, and logged once.
fn over_quota(
    ctx: &Context,
    peer: SocketAddr,
    client_id: &str,
    identity: &str,
    max: usize,
) -> Refused {
    static LOGGED: std::sync::atomic::AtomicBool = std::sync::atomic::AtomicBool::new(false);
    ctx.metrics
        .limit_refusals
        .with_label_values(&["sessions_per_identity"])
        .inc();
    if !LOGGED.swap(true, std::sync::atomic::Ordering::Relaxed) {
        tracing::warn!(
            %peer,
            client_id,
            identity,
            max_sessions_per_identity = max,
            "CONNECT refused: this identity holds [broker] max_sessions_per_identity \
             connections and persistent sessions (logged once; all counted in \
             fbbus_limit_refusals_total{{limit=\"sessions_per_identity\"}})"
        );
    }
    Refused {
        logged: true,
        ..refused(ConnectReturnCode::QuotaExceeded, "sessions_per_identity")
    }
}

/// A will may only go where the client may publish (the publish policy decides).
fn authorize_will(
    ctx: &Context,
    client_id: &str,
    username: Option<&str>,
    will: Option<&Will>,
) -> Result<(), Refused> {
    let Some(will) = will else {
        return Ok(());
    };
    let topic = String::from_utf8_lossy(&will.topic);
    let who = Identity {
        username,
        client_id,
    };
    if ctx.policy.will_allowed(who, &topic) {
        return Ok(());
    }
    if crate::logging::OUTSIDE.allow() {
        tracing::warn!(client_id, ?topic, "will topic not allowed; CONNECT refused");
    }
    Err(refused(
        ConnectReturnCode::NotAuthorized,
        "will_not_authorized",
    ))
}

/// The session's place in the router: its session number and its link.
struct Linked {
    session: u64,
    /// The client id's previous connection had not closed yet when this one started.
    predecessor_running: bool,
    link_tx: LinkTx,
    link_rx: LinkRx,
}

/// Links the claimed session (`claim`) to the router, which takes over an older session
/// with the same id, once that one finished reading what its client sent (`takeover`).
/// Also returns the CONNACK: the router's for a session it may hold, made by the link for
/// a clean one, which does not wait for the router (`RouterHandle::link`).
async fn link(
    ctx: &Context,
    client_id: &str,
    username: Option<&str>,
    owner: &Owner,
    (session, predecessor): (u64, Option<Running>),
    lifetime: SessionLifetime,
) -> Result<(Linked, Notification), Refused> {
    let predecessor_running = predecessor.is_some();
    if let Some(Running {
        session: old,
        nudge: Some(nudge),
    }) = predecessor
    {
        if ctx.takeovers.finish(old, &nudge).await == Finished::TimedOut {
            ctx.metrics.takeovers_unfinished.inc();
        }
    }
    ctx.wills.cancel_delayed(client_id, owner);
    let speaks_for_device = match username {
        Some(user) => user == client_id,
        None => ctx.fb.anonymous_devices,
    };
    if speaks_for_device {
        ctx.fb.registry.session_started(client_id, session);
    }
    // Session lifetime. rumqttd keeps a link's session after it ends unless the link is
    // clean (the MQTT 3.1.1 rule). MQTT 5 separates the two: Clean Start discards an
    // existing session now, Session Expiry decides whether this one outlives the
    // connection. So a v5 link is clean only for Clean Start with expiry 0; Clean Start
    // with expiry > 0 first ends the old session with a purge link.
    if lifetime.purge_before_link {
        purge_router_session(&ctx.router, client_id).await;
    }
    // Topic Alias Maximum 0 towards the router: rumqttd 0.20 keys the aliases it sends by
    // subscription filter, so two topics matching one wildcard would share an alias.
    // fbbus sends full topic names.
    match ctx.router.link(client_id, lifetime.clean_link, 0).await {
        Ok((link_tx, link_rx, ack)) => {
            ctx.sessions.linked(client_id, session, link_rx.nudge());
            let linked = Linked {
                session,
                predecessor_running,
                link_tx,
                link_rx,
            };
            Ok((linked, ack))
        }
        Err(e) => {
            ctx.sessions
                .close_with(client_id, session, Remains::Nothing, |superseded| {
                    ctx.redeliveries.abandoned(client_id, session, superseded)
                });
            tracing::error!(client_id, error = %e, "router refused the connection");
            Err(refused(
                ConnectReturnCode::ServerUnavailable,
                "router_refused",
            ))
        }
    }
}

/// Answers CONNACK: the router's, with what fbbus announces. None when the client is gone
/// before it could be told, and the session was closed again.
async fn answer(
    io: &mut Io,
    ctx: &Context,
    accepted: Accepted,
    server_keep_alive: Option<u16>,
) -> Option<Opened> {
    let mut connack_packet: Option<Packet> = accepted.ack.into();
    let session_present =
        matches!(&connack_packet, Some(Packet::ConnAck(ack, _)) if ack.session_present);
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
    let opened = Opened {
        client_id: accepted.client_id,
        username: accepted.username,
        will: accepted.will,
        lifetime: accepted.lifetime,
        linked: accepted.linked,
        session_present,
    };
    if io.flush().await.is_ok() {
        return Some(opened);
    }
    let Opened {
        client_id,
        lifetime,
        linked,
        ..
    } = opened;
    let _ = unlink(linked.link_tx).await;
    ctx.sessions.close_with(
        &client_id,
        linked.session,
        lifetime.remains(),
        |superseded| {
            ctx.redeliveries
                .abandoned(&client_id, linked.session, superseded)
        },
    );
    // It may have taken an online device's session over: that device is gone now.
    ctx.fb.registry.disconnected(
        &client_id,
        linked.session,
        DisconnectReason::Abrupt.description(),
    );
    None
}

/// The packet ids the session starts with: fresh for a clean session, otherwise what the
/// session's previous connection left unacknowledged, to be sent again (`redelivery`).
async fn resume(
    ctx: &Context,
    client_id: &str,
    linked: &Linked,
    lifetime: SessionLifetime,
) -> (PacketIds, BTreeMap<String, rumqttd::protocol::Filter>) {
    if lifetime.clean_link || lifetime.purge_before_link {
        ctx.redeliveries.forget(client_id);
        return (PacketIds::default(), BTreeMap::new());
    }
    let mut handed_over = ctx
        .redeliveries
        .take(client_id, linked.session, linked.predecessor_running)
        .await;
    let subscriptions = std::mem::take(&mut handed_over.subscriptions);
    (PacketIds::resumed(handed_over), subscriptions)
}

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

/// A CONNECT that passed: everything `Session::open` builds the session from.
struct Accepted {
    client_id: String,
    /// The client id fbbus chose, when the client sent none.
    assigned: Option<String>,
    username: Option<String>,
    will: Option<Will>,
    lifetime: SessionLifetime,
    linked: Linked,
    /// The router's CONNACK.
    ack: Notification,
}

/// A session the client was told about (CONNACK sent).
struct Opened {
    client_id: String,
    username: Option<String>,
    will: Option<Will>,
    lifetime: SessionLifetime,
    linked: Linked,
    /// The router resumed a session of this client id.
    session_present: bool,
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

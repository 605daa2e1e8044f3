//! Stage 2 of the publish policy: typed FB topics, checked before anything is routed.
//!
//! A publication is one of:
//!
//! - **not fbbus's** (any topic outside `fb/`, `dinasore/`, `fbdk/`, `fbbus/`): routed as is;
//! - **a declaration** on `fbbus/declare/<own id>`: validated, stored in the registry,
//!   answered on `fbbus/diag/<id>`, never routed;
//! - **typed**, on `<encoding>/<device>/<fb>/<port>`: only the device itself may publish
//!   there (and anywhere under `<encoding>/<device>`, whatever the topic's depth), the port must be a declared output, and the payload must decode to values of
//!   the declared types. Accepted messages are routed canonically on `fb/...` and, once
//!   anyone has subscribed to them, re-encoded on `dinasore/...` and `fbdk/...`, so a
//!   FORTE device and a DINASORE device read each other without knowing each other's
//!   format. Refused ones are never routed: see [`Rejection`]. `fbdk` dates and times are
//!   in the broker's `[fb] fbdk_time_unit`; an accepted value that unit cannot carry (a
//!   DATE_AND_TIME after 2554 in nanoseconds) is routed everywhere else, and not on
//!   `fbdk/`, with a `not_reencoded` diagnostic for its publisher.
//!
//! In lenient mode (`[fb] undeclared = "pass"`, for migrating untyped lines) typed-namespace
//! topics nobody declared pass through unchecked; declared ports are still checked, so an
//! ill-typed message is never delivered in either mode, and another device's namespace is
//! refused in both.

mod check;
mod declare;
mod diag;
mod reencode;

use std::collections::{BTreeMap, BTreeSet};
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::Arc;
use std::time::{Instant, SystemTime};

use bytes::Bytes;
use fb_bridge::codec::{fbdk, Encoding};
use fb_bridge::profile::Profile;
use fb_bridge::{DeclarationError, Interface};
use serde::Deserialize;

use crate::broker_publisher::{BrokerPublisher, Message as BrokerMessage};
use crate::metrics::Metrics;
use crate::observer::SubscriptionObserver;
use crate::policy::budget::Budgets;
use crate::profiles::{Profiles, Speakers};
use crate::registry::Registry;
use crate::silence::Activity;

/// What to do with typed-namespace topics no device declared.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum Undeclared {
    /// Refuse them (MQTT 5: 0x90 topic name invalid).
    #[default]
    Reject,
    /// Route them unchecked.
    Pass,
}

/// Why a publication was refused; each maps to one MQTT 5 PUBACK/PUBREC reason code.
#[derive(Debug, Clone, Copy, PartialEq, Eq, PartialOrd, Ord, Hash)]
pub enum Refusal {
    /// 0x87: another device's topic, or the broker's own namespace.
    NotAuthorized,
    /// 0x90: no such declared port, or not a typed topic shape.
    TopicNameInvalid,
    /// 0x99: the payload does not decode to the declared types.
    PayloadFormatInvalid,
    /// 0x97: a limit refused it: the registry's for a new device (`[fb] max_devices`,
    /// `max_devices_per_identity`), or a declaration's (size, FBs, ports, encoded size,
    /// rate).
    QuotaExceeded,
}

impl Refusal {
    pub fn label(self) -> &'static str {
        match self {
            Refusal::NotAuthorized => "not_authorized",
            Refusal::TopicNameInvalid => "topic_name_invalid",
            Refusal::PayloadFormatInvalid => "payload_format_invalid",
            Refusal::QuotaExceeded => "quota_exceeded",
        }
    }

    pub fn code(self) -> u8 {
        match self {
            Refusal::NotAuthorized => 0x87,
            Refusal::TopicNameInvalid => 0x90,
            Refusal::PayloadFormatInvalid => 0x99,
            Refusal::QuotaExceeded => 0x97,
        }
    }
}

#[derive(Debug, Clone)]
pub struct Rejection {
    pub refusal: Refusal,
    pub detail: String,
}

/// The outcome of the check.
#[derive(Debug)]
pub enum Check {
    /// Not a topic fbbus gives meaning to: route it unchanged.
    Pass,
    /// Route these (topic, payload) pairs: the first at the publication's QoS and packet
    /// id, the others (re-encodings) as copies of it.
    Route(Vec<(String, Bytes)>),
    /// Handled by the broker (a declaration): acknowledge, do not route.
    Consumed,
    Refused(Rejection),
}

/// What one device may make the broker read, hold and answer (`[fb]`, issue 21); the
/// defaults are `[fb]`'s.
#[derive(Debug, Clone, Copy)]
pub struct Limits {
    pub max_declaration_bytes: usize,
    pub max_fbs: usize,
    pub max_ports: usize,
    pub declarations_per_minute: u32,
    pub diag_per_second: f64,
    pub diag_burst: u32,
}

impl Default for Limits {
    /// `[fb]`'s defaults, from the one place they are set.
    fn default() -> Self {
        Limits {
            max_declaration_bytes: 16 * 1024,
            max_fbs: 64,
            max_ports: 512,
            declarations_per_minute: 30,
            diag_per_second: 10.0,
            diag_burst: 20,
        }
    }
}

/// A declaration refused: the errors for the device, and the `[fb]` limit it passed, if
/// that is why.
struct Refused {
    limit: Option<&'static str>,
    errors: Vec<DeclarationError>,
}

impl Refused {
    fn limit(limit: &'static str, error: String) -> Refused {
        Refused {
            limit: Some(limit),
            errors: vec![DeclarationError {
                fb: None,
                port: None,
                error,
            }],
        }
    }
}

/// Shared by all connections.
/// The receive buffer of 4diac FORTE's MQTT layer, per subscription, in bytes: a longer
/// message corrupts that subscription's stream. The default `[fb] fbdk_max_payload`.
pub const FORTE_RECEIVE_BUFFER: usize = 255;

pub struct FbTopics {
    pub registry: Arc<Registry>,
    pub undeclared: Undeclared,
    /// No password file: a client id alone identifies a device (see
    /// [`FbSession::identity_verified`]).
    pub anonymous_devices: bool,
    /// The unit of DATE, TIME_OF_DAY and DATE_AND_TIME in `fbdk/` payloads.
    pub fbdk_unit: fbdk::TimeUnit,
    /// The largest `fbdk/` payload delivered (0: no limit); see [`FORTE_RECEIVE_BUFFER`].
    fbdk_max_payload: usize,
    /// `[broker] max_packet_bytes`: a re-encoded copy must fit it as any packet must.
    max_packet: usize,
    /// Declarations and diagnostics per device (`[fb]`).
    limits: Limits,
    /// The device profiles (`[fb] profiles_dir`).
    pub profiles: Arc<Profiles>,
    /// Declaration and diagnostics budgets, per device and identity (`budget`).
    budgets: Budgets,
    /// The connections speaking for each topics-only device.
    speakers: Speakers,
    publisher: Arc<BrokerPublisher>,
    metrics: Arc<Metrics>,
    /// Per encoding: someone subscribed to a filter that can match its namespace, so
    /// publications are re-encoded into it. Set once, never cleared.
    mirrors: [AtomicBool; 3],
}

impl FbTopics {
    /// Publishes what a connection's [`FbSession::take_outbox`] returned.
    pub fn publish(&self, messages: Vec<BrokerMessage>) {
        for m in messages {
            self.publisher.publish(m);
        }
    }

    pub fn new(
        registry: Arc<Registry>,
        undeclared: Undeclared,
        anonymous_devices: bool,
        fbdk_unit: fbdk::TimeUnit,
        publisher: Arc<BrokerPublisher>,
        metrics: Arc<Metrics>,
    ) -> FbTopics {
        FbTopics {
            registry,
            undeclared,
            anonymous_devices,
            fbdk_unit,
            fbdk_max_payload: FORTE_RECEIVE_BUFFER,
            max_packet: usize::MAX,
            limits: Limits::default(),
            profiles: Arc::new(Profiles::none()),
            budgets: Budgets::new(crate::registry::Limits::default().max_devices),
            speakers: Speakers::default(),
            publisher,
            metrics,
            mirrors: Default::default(),
        }
    }

    /// `[fb] fbdk_max_payload`: `fbdk/` payloads longer than `bytes` are not delivered
    /// (0: no limit).
    pub fn with_fbdk_max_payload(mut self, bytes: usize) -> FbTopics {
        self.fbdk_max_payload = bytes;
        self
    }

    /// The registry's `[fb] max_devices`: every device may have its own declaration and
    /// diagnostics budgets (`budget`).
    pub fn with_max_devices(mut self, max_devices: usize) -> FbTopics {
        self.budgets = Budgets::new(max_devices);
        self
    }

    /// `[broker] max_packet_bytes`: a re-encoded copy whose PUBLISH would be larger is not
    /// routed (a 60 KB message on an `ARRAY [30000] OF TIME` became 240 KB in `fbdk`).
    pub fn with_max_packet(mut self, bytes: usize) -> FbTopics {
        self.max_packet = bytes;
        self
    }

    /// `[fb]`'s limits on declarations and diagnostics.
    pub fn with_limits(mut self, limits: Limits) -> FbTopics {
        self.limits = limits;
        self
    }

    /// The device profiles the typed check and CONNECT consult.
    pub fn with_profiles(mut self, profiles: Arc<Profiles>) -> FbTopics {
        self.profiles = profiles;
        self
    }

    /// The connection `session` ended for `reason`: returns whether its device is offline
    /// now. A device has one connection at a time, except a topics-only device, which is
    /// online while any connection that speaks for it lives.
    pub fn connection_ended(&self, session: &FbSession, reason: &str) -> bool {
        let device = session.device();
        if !session.by_topics {
            return self.registry.disconnected(device, session.session, reason);
        }
        if !self.speakers.leave(device, session.session) {
            return false;
        }
        // The record carries the session that brought the device online, which may have
        // ended long ago: the device's end is its last speaker's.
        let current = self
            .registry
            .get(device)
            .map_or(session.session, |r| r.session);
        self.registry.disconnected(device, current, reason)
    }

    /// A subscription was granted: start re-encoding into the namespace it names (a
    /// filter starting with a wildcard does not match the copies: `topic::MIRROR_PREFIXES`).
    pub fn subscribed(&self, filter: &str) {
        let filter = fb_bridge::topic::filter::unshared(filter);
        let first = filter.split('/').next().unwrap_or("");
        for (i, encoding) in Encoding::ALL.into_iter().enumerate() {
            if first == encoding.namespace()
                && !self.mirrors[i].swap(true, Ordering::Relaxed)
                && encoding != Encoding::Json
            {
                tracing::info!(
                    namespace = encoding.namespace(),
                    "first subscriber: typed messages are now also published in this encoding"
                );
            }
        }
    }

    /// Whether typed messages are published in `encoding` (someone reads it; `fb/`: always).
    pub(crate) fn mirrored(&self, encoding: Encoding) -> bool {
        encoding == Encoding::Json
            || self.mirrors[Encoding::ALL
                .iter()
                .position(|e| *e == encoding)
                .unwrap_or(0)]
            .load(Ordering::Relaxed)
    }
}

/// Typed messages are re-encoded into a namespace once someone reads it.
impl SubscriptionObserver for FbTopics {
    fn subscribed(&self, filter: &str) {
        FbTopics::subscribed(self, filter)
    }

    /// Re-encoding, once started, goes on: a namespace someone read is likely read again.
    fn unsubscribed(&self, _filter: &str) {}
}

/// One connection's typed-topic state.
pub struct FbSession {
    /// The device it speaks for: its client id, or its profile's device id.
    device: String,
    /// The connection's client id, which the access rules see.
    client_id: String,
    /// No password file is configured: a client id alone identifies a device.
    anonymous_devices: bool,
    username: Option<String>,
    /// The connection's peer address (None for the bus door): who registers devices
    /// where there is no password file ([`FbSession::registrant`]).
    peer: Option<std::net::IpAddr>,
    session: u64,
    /// The device's declared interface, once it has one.
    interface: Option<Arc<Interface>>,
    /// The device's profile, when its connection was recognised by one at CONNECT: the
    /// device id and interface are the profile's.
    profile: Option<Arc<Profile>>,
    /// It speaks for a topics-only device, recognised by its publications or
    /// subscriptions.
    by_topics: bool,
    /// Of those, by an accepted publication on one of the device's outputs.
    published_own: bool,
    /// Where accepted publications on the interface's outputs are timed (`silence`); None
    /// for a connection that does not speak for a local device (the bus door's).
    activity: Option<Arc<Activity>>,
    /// Event sequence numbers stamped for publishers that send none, per fb and port.
    // B-tree maps: no allocation and 24 bytes while empty; every connection holds one.
    seq: BTreeMap<String, BTreeMap<String, u64>>,
    /// (topic, reason label) pairs already logged.
    logged: BTreeSet<(String, &'static str)>,
    /// Diagnostics dropped over the device's budget (`[fb] diag_per_second`, kept across
    /// its connections: `budget`) since the last one published: a device looping on a
    /// bad message gets its explanation, not a flood.
    diag_dropped: u64,
    diag_rate: (f64, f64),
    /// When a refusal at `[fb] declarations_per_minute` (the device's budget, kept across
    /// its connections: `budget`) was last logged.
    declare_logged: Option<Instant>,
    limits: Limits,
    /// Diagnostics for the device, published by the connection once the packets read
    /// with the publication that caused them are in the router ([`FbSession::take_outbox`]):
    /// a device that subscribes to its diag topic and declares in one write must get the
    /// answer, which it would not if the answer reached the router before the SUBSCRIBE.
    outbox: Vec<BrokerMessage>,
}

impl FbSession {
    pub fn new(fb: &FbTopics, device: &str, username: Option<&str>, session: u64) -> FbSession {
        FbSession {
            device: device.to_owned(),
            client_id: device.to_owned(),
            anonymous_devices: fb.anonymous_devices,
            username: username.map(str::to_owned),
            peer: None,
            session,
            interface: None,
            profile: None,
            by_topics: false,
            published_own: false,
            activity: None,
            seq: BTreeMap::new(),
            logged: BTreeSet::new(),
            diag_dropped: 0,
            diag_rate: (fb.limits.diag_per_second, f64::from(fb.limits.diag_burst)),
            declare_logged: None,
            limits: fb.limits,
            outbox: Vec::new(),
        }
    }

    /// Diagnostics decided since the last call, to publish now that the packets read
    /// before them are in the router.
    pub fn take_outbox(&mut self) -> Vec<BrokerMessage> {
        std::mem::take(&mut self.outbox)
    }

    /// The interface this session checks against, if any.
    #[cfg_attr(not(feature = "bridge"), allow(dead_code))]
    pub fn interface(&self) -> Option<&Arc<Interface>> {
        self.interface.as_ref()
    }

    /// The device this connection speaks for: its client id, or its profile's device.
    pub fn device(&self) -> &str {
        &self.device
    }

    /// Where the device's publications are timed, when the device may end for its
    /// silence (`liveness.offline_after_silent_s`): its connections wait on it.
    pub fn ending_activity(&self) -> Option<&Arc<Activity>> {
        match &self.profile {
            Some(p) if p.offline_after_silent.is_some() => self.activity.as_ref(),
            _ => None,
        }
    }

    /// The profile that recognised this connection, if any.
    pub fn profile(&self) -> Option<&Arc<Profile>> {
        self.profile.as_ref()
    }

    /// At CONNECT: the profile `profile` recognised this connection, so it is that device,
    /// with the profile's interface (`interface`, as the registry now holds it).
    pub fn set_profile(&mut self, profile: Arc<Profile>, interface: Arc<Interface>) {
        self.device.clone_from(&profile.device);
        self.profile = Some(profile);
        self.interface = Some(interface);
    }

    /// The interface the registry had for this device when it connected.
    pub fn set_interface(&mut self, interface: Option<Arc<Interface>>) {
        self.interface = interface;
    }

    /// Where this connection times the device's accepted publications: set for a local
    /// device's own connection only. A profile's stated periods apply to it.
    pub fn set_activity(&mut self, activity: Option<Arc<Activity>>) {
        if let (Some(activity), Some(profile)) = (&activity, &self.profile) {
            for (fb, port, period) in &profile.periods {
                activity.state_period(fb, port, *period);
            }
            activity.set_offline_after(profile.offline_after_silent);
        }
        self.activity = activity;
    }

    /// The address the connection comes from.
    pub fn set_peer(&mut self, peer: std::net::IpAddr) {
        self.peer = Some(peer.to_canonical());
    }

    /// Who registers the devices this connection declares, for
    /// `[fb] max_devices_per_identity`: the verified username where a password file
    /// exists, else the peer's address (client ids and unverified usernames are free to
    /// choose, an address is not).
    fn registrant(&self) -> String {
        match (&self.username, self.anonymous_devices, self.peer) {
            (Some(user), false, _) => format!("user:{user}"),
            (_, _, Some(ip)) => format!("address:{ip}"),
            (_, _, None) => "broker".to_owned(),
        }
    }

    /// Whose declaration and diagnostics budgets this connection spends (`budget`): its
    /// device's, as registered by its identity, so a device that reconnects finds its
    /// budget as it left it, and another device of the same identity has its own.
    fn budget_key(&self) -> String {
        format!("{}/{}", self.registrant(), self.device)
    }

    /// Who publishes, as the access rules see it.
    pub fn identity(&self) -> security::Identity<'_> {
        security::Identity {
            username: self.username.as_deref(),
            client_id: &self.client_id,
        }
    }

    /// Whether this connection speaks for the device its client id names. Client ids are
    /// chosen by clients; the username is what was verified, so a device is only itself
    /// when both are the same. Without a username the client id is trusted only on a
    /// broker with no password file at all (a loopback test line): once passwords exist,
    /// an anonymous client (a loopback listener with `allow_anonymous`) speaks for no device.
    pub fn identity_verified(&self) -> bool {
        if self.profile.is_some() {
            // `ProfileSet::identify` matched it, username included.
            return true;
        }
        match self.username.as_deref() {
            Some(user) => user == self.device,
            None => self.anonymous_devices,
        }
    }

    /// Whether the device's profile lets this connection go without its MQTT keep-alive
    /// (`speaks.enforce_keep_alive = false`): a connection recognised at CONNECT, or one
    /// that had an own-topic publication accepted. A connection that speaks for a
    /// topics-only device by subscribing only is held to its keep-alive: the runtime's
    /// subscribers ping, and a frozen one must end.
    pub fn keep_alive_waived(&self) -> bool {
        self.profile
            .as_ref()
            .is_some_and(|p| !p.enforce_keep_alive && (!self.by_topics || self.published_own))
    }
}

fn now_us() -> u64 {
    SystemTime::now()
        .duration_since(SystemTime::UNIX_EPOCH)
        .map(|d| d.as_micros() as u64)
        .unwrap_or(0)
}

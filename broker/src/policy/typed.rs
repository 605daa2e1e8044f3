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

use std::collections::{BTreeMap, BTreeSet};
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::Arc;
use std::time::{Instant, SystemTime};

use bytes::Bytes;
use fb_bridge::codec::{self, fbdk, Encoding};
use fb_bridge::profile::{self as profile_file, Identity, Profile};
use fb_bridge::topic::{self, TypedTopic};
use fb_bridge::{Declaration, DeclarationError, EventMessage, Interface, Message, OutputPort};
use serde::Deserialize;
use serde_json::json;

use crate::broker_publisher::{BrokerPublisher, Message as BrokerMessage};
use crate::metrics::Metrics;
use crate::observer::SubscriptionObserver;
use crate::profiles::{ProfileSet, Profiles, Speakers};
use crate::registry::Registry;
use crate::registry::Status;
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

/// A token bucket: `rate` tokens a second, at most `burst` held. One per connection and
/// kind, so its state is two words and dies with the connection.
#[derive(Debug)]
struct Bucket {
    tokens: f64,
    at: Instant,
}

impl Bucket {
    fn full(burst: f64) -> Bucket {
        Bucket {
            tokens: burst,
            at: Instant::now(),
        }
    }

    /// Takes a token, or says in how many seconds one will be there.
    fn take(&mut self, rate: f64, burst: f64) -> Result<(), f64> {
        let now = Instant::now();
        self.tokens = (self.tokens + now.duration_since(self.at).as_secs_f64() * rate).min(burst);
        self.at = now;
        if self.tokens >= 1.0 {
            self.tokens -= 1.0;
            Ok(())
        } else {
            Err((1.0 - self.tokens) / rate)
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

    /// A subscription was granted: start re-encoding into the namespaces it can match.
    pub fn subscribed(&self, filter: &str) {
        let filter = fb_bridge::topic::filter::unshared(filter);
        let first = filter.split('/').next().unwrap_or("");
        for (i, encoding) in Encoding::ALL.into_iter().enumerate() {
            let matches = first == encoding.namespace() || matches!(first, "#" | "+");
            if matches
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

    fn mirrored(&self, encoding: Encoding) -> bool {
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
    /// It speaks for a topics-only device, recognised by its publications.
    by_topics: bool,
    /// Where accepted publications on the interface's outputs are timed (`silence`); None
    /// for a connection that does not speak for a local device (the bus door's).
    activity: Option<Arc<Activity>>,
    /// Event sequence numbers stamped for publishers that send none, per fb and port.
    // B-tree maps: no allocation and 24 bytes while empty; every connection holds one.
    seq: BTreeMap<String, BTreeMap<String, u64>>,
    /// (topic, reason label) pairs already logged.
    logged: BTreeSet<(String, &'static str)>,
    /// Diagnostics this connection may still publish (`[fb] diag_per_second`): a device
    /// looping on a bad message gets its explanation, not a flood; and how many were
    /// dropped since the last one published.
    diag_budget: Bucket,
    diag_dropped: u64,
    diag_rate: (f64, f64),
    /// Declarations it may still send (`[fb] declarations_per_minute`), and when a refusal
    /// at that limit was last logged.
    declare_budget: Bucket,
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
            activity: None,
            seq: BTreeMap::new(),
            logged: BTreeSet::new(),
            diag_budget: Bucket::full(f64::from(fb.limits.diag_burst)),
            diag_dropped: 0,
            diag_rate: (fb.limits.diag_per_second, f64::from(fb.limits.diag_burst)),
            declare_budget: Bucket::full(f64::from(fb.limits.declarations_per_minute)),
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
    pub fn interface(&self) -> Option<&Arc<Interface>> {
        self.interface.as_ref()
    }

    /// The device this connection speaks for: its client id, or its profile's device.
    pub fn device(&self) -> &str {
        &self.device
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

    /// At CONNECT: `profile` recognised this connection, so it is that device, registered
    /// with the profile's interface, if the registry admits it. Returns whether it did;
    /// if not, the device is told on its diag topic and the connection is no device.
    pub fn declare_profile(&mut self, fb: &FbTopics, profile: &Arc<Profile>) -> bool {
        let declared = fb.registry.declare(
            &profile.device,
            self.session,
            profile.interface.clone(),
            &self.registrant(),
        );
        match declared {
            Ok(interface) => {
                self.set_profile(Arc::clone(profile), interface);
                true
            }
            Err(full) => {
                self.registry_full(fb, &profile.device, &full, true);
                false
            }
        }
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

    /// A new device beyond a registry limit: the device is told on its diag topic, and the
    /// publication refused with 0x97. The registry counted and logged it. A declaration is
    /// always answered (the device waits for the answer); a topics-only device's
    /// publications are answered within the connection's diagnostics budget.
    fn registry_full(
        &mut self,
        fb: &FbTopics,
        device: &str,
        full: &crate::registry::Full,
        declaration: bool,
    ) -> Check {
        let body = json!({
            "kind": "declaration",
            "ok": false,
            "reason": "quota_exceeded",
            "limit": full.limit(),
            "errors": [{"error": full.to_string()}],
        });
        if declaration {
            self.outbox.push(BrokerMessage::broker(
                topic::diag(device),
                body.to_string(),
                false,
            ));
        } else {
            self.diag_to(fb, device, body);
        }
        Check::Refused(Rejection {
            refusal: Refusal::QuotaExceeded,
            detail: String::new(),
        })
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

    /// An empty retained publication on one of this device's declared typed ports: it
    /// clears the port's retained value (MQTT 3.3.1.3), in every namespace, so a new
    /// subscriber of any encoding no longer gets the old value. None for anything else,
    /// which [`FbSession::check`] decides as usual.
    pub fn clear_retained(&self, topic: &str) -> Option<Check> {
        let typed = TypedTopic::parse(topic)?;
        if typed.device != self.device || !self.identity_verified() {
            return None;
        }
        self.interface.as_ref()?.output(typed.fb, typed.port)?;
        let routes = std::iter::once(Encoding::Json)
            .chain(Encoding::ALL.into_iter().filter(|e| *e != Encoding::Json))
            .map(|e| (typed.in_encoding(e), Bytes::new()))
            .collect();
        Some(Check::Route(routes))
    }

    /// Checks one publication (ACL already passed) and says what to route.
    pub fn check(&mut self, fb: &FbTopics, topic: &str, payload: &Bytes) -> Check {
        let check = self.decide(fb, topic, payload);
        if let Check::Refused(rejection) = &check {
            self.rejected(fb, topic, rejection);
        }
        check
    }

    fn decide(&mut self, fb: &FbTopics, topic: &str, payload: &Bytes) -> Check {
        // A device's namespace is its own on every topic shape and in every mode: lenient
        // mode routes topics that are not typed ports unchecked, and without this a client
        // could publish `fb/<other>/CONV/SPEED/x` or `fb/<other>` in another device's name.
        if let Some((encoding, device)) = topic::namespace_owner(topic) {
            if device != self.device || !self.identity_verified() {
                return refuse(
                    Refusal::NotAuthorized,
                    format!(
                        "only device {device} publishes under {}/{device}/, and only with \
                         its id as both client id and username",
                        encoding.namespace()
                    ),
                );
            }
        }
        // The broker's own `$` namespace: its readiness probe must not be fed or flooded.
        if topic.starts_with(crate::health::RESERVED_TOPICS) {
            return refuse(
                Refusal::NotAuthorized,
                "$fbbus/ topics are the broker's own",
            );
        }
        if let Some(rest) = topic.strip_prefix(topic::BROKER_NAMESPACE) {
            if rest.strip_prefix("declare/") == Some(self.device.as_str()) {
                return self.declare(fb, payload);
            }
            return refuse(
                Refusal::NotAuthorized,
                "fbbus/ topics are published by the broker, except fbbus/declare/<your client id>",
            );
        }
        let profiles = fb.profiles.get();
        if profiles.maps_topics() {
            if let Some((profile, i)) = profiles.output(topic) {
                return self.own_topic(fb, &profiles, profile, i, payload);
            }
            if profiles.is_input_topic(topic) {
                return refuse(
                    Refusal::NotAuthorized,
                    "an input topic of a device profile: the broker publishes it",
                );
            }
        }
        let Some(typed) = TypedTopic::parse(topic) else {
            if topic::is_typed_namespace(topic) && fb.undeclared == Undeclared::Reject {
                return refuse(
                    Refusal::TopicNameInvalid,
                    "typed topics have four levels: <fb|dinasore|fbdk>/<device>/<fb>/<port>",
                );
            }
            return Check::Pass;
        };
        // `typed.device` is this device: the namespace check above refused any other.
        let Some(interface) = self.interface.clone() else {
            return match fb.undeclared {
                Undeclared::Pass => Check::Pass,
                Undeclared::Reject => refuse(
                    Refusal::TopicNameInvalid,
                    format!(
                        "device {} has not declared its interface (publish it on fbbus/declare/{})",
                        self.device, self.device
                    ),
                ),
            };
        };
        let Some(port) = interface.output(typed.fb, typed.port) else {
            return match fb.undeclared {
                Undeclared::Pass => Check::Pass,
                Undeclared::Reject => refuse(
                    Refusal::TopicNameInvalid,
                    format!(
                        "{}.{} is not a declared output of device {}",
                        typed.fb, typed.port, self.device
                    ),
                ),
            };
        };
        let decoded = codec::decode(typed.encoding, payload, typed.port, &port, fb.fbdk_unit);
        let message = match decoded {
            Ok(m) => m,
            Err(e) => {
                return refuse(
                    Refusal::PayloadFormatInvalid,
                    format!("{}.{}: {e}", typed.fb, typed.port),
                )
            }
        };
        self.accepted(fb, &profiles, &typed, &port, message, payload, None)
    }

    /// A publication on `profile`'s own output topic number `i`: the device's, decoded
    /// the way it speaks, then routed like a typed publication of that port, on its own
    /// topic (first, as it came) and on the typed topics.
    fn own_topic(
        &mut self,
        fb: &FbTopics,
        profiles: &ProfileSet,
        profile: &Arc<Profile>,
        i: usize,
        payload: &Bytes,
    ) -> Check {
        let Some(own) = profile.outputs.get(i) else {
            return Check::Pass;
        };
        // Whose it is: the device the profile recognised, or, for a device recognised by
        // its topics only (a random client id), a client the ACL let publish here that
        // is not recognised as another device. Never a known other device: the stolen-
        // topic rule.
        let mine = match &self.profile {
            Some(p) => p.device == profile.device,
            None => {
                profile.identity == Identity::TopicsOnly
                    && self.username.as_deref().is_none_or(|u| u == profile.device)
            }
        };
        if !mine {
            return refuse(
                Refusal::NotAuthorized,
                format!(
                    "{} is device {}'s own topic (its profile): only that device publishes it",
                    own.topic, profile.device
                ),
            );
        }
        if self.profile.is_none() {
            // A topics-only device's first publication on this connection (the access rules
            // let it publish here, and it is no other device): the connection now speaks
            // for it, refusals included, so the registry shows it online until the
            // connection (or a newer one of it) ends, and its broker-side will fires then.
            // Its other connections may speak for it already: then it is online, and
            // its interface and output timing are theirs.
            let first = fb.speakers.join(&profile.device, self.session);
            let held = fb
                .registry
                .get(&profile.device)
                .filter(|r| !first && r.status == Status::Online);
            let declared = match held {
                Some(record) => Ok(record.interface),
                None => fb.registry.declare(
                    &profile.device,
                    self.session,
                    profile.interface.clone(),
                    &self.registrant(),
                ),
            };
            let interface = match declared {
                Ok(interface) => interface,
                Err(full) => {
                    fb.speakers.leave(&profile.device, self.session);
                    fb.metrics
                        .declarations
                        .with_label_values(&["refused"])
                        .inc();
                    return self.registry_full(fb, &profile.device, &full, false);
                }
            };
            self.by_topics = true;
            self.set_profile(Arc::clone(profile), interface);
            self.set_activity(fb.registry.activity(&profile.device));
            tracing::info!(
                device = profile.device,
                client_id = self.client_id,
                session = self.session,
                "a client publishes on a topics-only device's own topic: it is that device"
            );
        }
        let Some(port) = profile.interface.output(&own.fb, &own.port) else {
            return Check::Pass;
        };
        let unstrung;
        let bytes = match profile.string_numbers && own.encoding != Encoding::Fbdk {
            true => match profile_file::unstring_numbers(payload, &own.port, &port) {
                Some(b) => {
                    unstrung = b;
                    &unstrung[..]
                }
                None => &payload[..],
            },
            false => &payload[..],
        };
        let decoded = codec::decode(
            own.encoding,
            bytes,
            &own.port,
            &port,
            profile.fbdk_time_unit,
        );
        let message = match decoded {
            Ok(m) => m,
            Err(e) => {
                return refuse(
                    Refusal::PayloadFormatInvalid,
                    format!("{} ({}.{}): {e}", own.topic, own.fb, own.port),
                )
            }
        };
        let typed = TypedTopic {
            encoding: Encoding::Json,
            device: &profile.device,
            fb: &own.fb,
            port: &own.port,
        };
        let first = (own.topic.clone(), payload.clone());
        self.accepted(fb, profiles, &typed, &port, message, payload, Some(first))
    }

    /// An accepted typed message on `typed` (port shape `port`): stamped, timed, and
    /// routed on `fb/` (canonical JSON), on the other typed namespaces someone reads, and
    /// on the profile input topics it feeds. `own`: it came on a device's own topic,
    /// routed first as it came.
    #[allow(clippy::too_many_arguments)]
    fn accepted(
        &mut self,
        fb: &FbTopics,
        profiles: &ProfileSet,
        typed: &TypedTopic<'_>,
        port: &OutputPort<'_>,
        mut message: Message,
        payload: &Bytes,
        own: Option<(String, Bytes)>,
    ) -> Check {
        let stamped = self.stamp(typed, &mut message);
        fb.metrics.typed_accepted.inc();
        if let Some(activity) = &self.activity {
            activity.published(
                typed.fb,
                typed.port,
                std::time::Instant::now(),
                fb.registry.silence_bound(),
            );
        }
        // (Collecting nothing allocates nothing: the common case.)
        let feeds: Vec<(&Arc<Profile>, usize)> = match profiles.maps_topics() {
            true => profiles.feeds(typed.device, typed.fb, typed.port).collect(),
            false => Vec::new(),
        };
        // Subscribers of fb/ always get canonical JSON. JSON that came in complete (nothing
        // stamped) on a port whose types have one JSON form (or a BOOL port's `true`, not
        // its `1`: `json_is_canonical`) is canonical already and is routed as it came; other accepted forms (`"16#FF"`, `"TIME#1.5s"`, ...) are
        // re-encoded. The other encodings have one form each: their bytes pass through.
        // Whitespace around or between tokens (`" 5 "`, `"5\n"`) and `-0` are valid JSON
        // but not canonical: such a payload is re-encoded too.
        let json_as_is = own.is_none()
            && typed.encoding == Encoding::Json
            && !stamped
            && !payload.iter().any(u8::is_ascii_whitespace)
            && port.json_is_canonical(payload)
            && !payload.windows(2).any(|w| w == b"-0");
        let mut mirrors = Encoding::ALL
            .into_iter()
            .filter(|e| *e != Encoding::Json && fb.mirrored(*e))
            .peekable();
        if json_as_is && mirrors.peek().is_none() && feeds.is_empty() {
            return Check::Pass;
        }
        let mut routes = Vec::with_capacity(Encoding::ALL.len() + 1 + feeds.len());
        routes.extend(own.clone());
        for e in std::iter::once(Encoding::Json).chain(mirrors) {
            let as_is = own.is_none() && e == typed.encoding && (e != Encoding::Json || json_as_is);
            let bytes = if as_is {
                payload.clone()
            } else {
                // Only `fbdk` can fail (a date its time unit cannot carry), never `fb/`,
                // so the publication's own route is always the first.
                match codec::encode(e, &message, typed.port, port, fb.fbdk_unit) {
                    Ok(bytes) => Bytes::from(bytes),
                    Err(error) => {
                        self.not_reencoded(
                            fb,
                            &typed.in_encoding(e),
                            e.namespace(),
                            typed,
                            &error.to_string(),
                        );
                        continue;
                    }
                }
            };
            // A FORTE device's stream is never broken by a message it cannot take in.
            if e == Encoding::Fbdk && fb.fbdk_max_payload > 0 && bytes.len() > fb.fbdk_max_payload {
                let why = format!(
                    "{} bytes in fbdk, more than [fb] fbdk_max_payload ({}): a 4diac FORTE \
                     subscriber's MQTT layer would corrupt its stream",
                    bytes.len(),
                    fb.fbdk_max_payload
                );
                self.not_reencoded(fb, &typed.in_encoding(e), e.namespace(), typed, &why);
                continue;
            }
            // A copy larger than any packet this broker takes (its topic, a packet id and
            // a few header bytes besides) is not made: no subscriber was promised more.
            let topic = typed.in_encoding(e);
            if bytes.len() + topic.len() + 16 > fb.max_packet {
                let why = format!(
                    "{} bytes in {}, more than [broker] max_packet_bytes ({})",
                    bytes.len(),
                    e.namespace(),
                    fb.max_packet
                );
                self.not_reencoded(fb, &topic, e.namespace(), typed, &why);
                continue;
            }
            routes.push((topic, bytes));
        }
        for (profile, i) in feeds {
            if let Some(route) = self.feed(fb, profile, i, typed, port, &message) {
                routes.push(route);
            }
        }
        Check::Route(routes)
    }

    /// The message of `typed` (shape `port`) encoded for `profile`'s input topic number
    /// `i`, the way that device reads it; None, with a diagnostic for the publisher, when
    /// the input's types differ from the output's or the message is larger than the
    /// device can take in.
    fn feed(
        &mut self,
        fb: &FbTopics,
        profile: &Profile,
        i: usize,
        typed: &TypedTopic<'_>,
        port: &OutputPort<'_>,
        message: &Message,
    ) -> Option<(String, Bytes)> {
        let input = profile.inputs.get(i)?;
        let own = &input.own;
        let shape = profile.interface.input(&own.fb, &own.port)?;
        // The same values, whichever kind each port is: a data port's value is an
        // event's one WITH value and back.
        let fitted = match (message, &shape) {
            _ if port.value_types() != shape.value_types() => None,
            (Message::Data(v), OutputPort::Event(_)) => Some(Message::Event(EventMessage {
                seq: None,
                ts_us: None,
                data: vec![v.clone()],
            })),
            (Message::Event(e), OutputPort::Data(_)) => e.data.first().cloned().map(Message::Data),
            (m, _) => Some(m.clone()),
        };
        let bytes = match fitted {
            None => Err(format!(
                "feeds {}.{} of device {} ({}), whose types differ: not delivered there",
                own.fb, own.port, profile.device, own.topic
            )),
            Some(m) => codec::encode(own.encoding, &m, &own.port, &shape, profile.fbdk_time_unit)
                .map_err(|e| e.to_string()),
        };
        let bytes = match bytes {
            Ok(b) if profile.max_payload > 0 && b.len() > profile.max_payload => Err(format!(
                "{} bytes for {} ({}), more than its profile's max_payload ({})",
                b.len(),
                own.topic,
                profile.device,
                profile.max_payload
            )),
            other => other,
        };
        match bytes {
            Ok(b) => Some((own.topic.clone(), Bytes::from(b))),
            Err(why) => {
                self.not_reencoded(fb, &own.topic, "profile", typed, &why);
                None
            }
        }
    }

    /// An accepted message a topic cannot carry (a DATE_AND_TIME after 2554 in `fbdk`
    /// nanoseconds, an `fbdk` payload longer than its subscribers can take in, a profile
    /// input topic whose device reads other types or smaller messages): its
    /// subscribers do not get it, which is counted, logged once per topic and described to
    /// the publisher on `fbbus/diag/<device>`, as a refusal is.
    fn not_reencoded(
        &mut self,
        fb: &FbTopics,
        topic: &str,
        namespace: &'static str,
        typed: &TypedTopic<'_>,
        why: &str,
    ) {
        let detail = format!("{}.{}: {why}", typed.fb, typed.port);
        fb.metrics
            .typed_not_reencoded
            .with_label_values(&[namespace])
            .inc();
        if self.logged.len() < 1024 && self.logged.insert((topic.to_owned(), "not_reencoded")) {
            tracing::warn!(
                device = self.device,
                topic,
                detail,
                "typed publication not delivered on this topic, which cannot carry it \
                 (logged once per topic)"
            );
        }
        self.diag(
            fb,
            json!({
                "kind": "not_reencoded",
                "topic": topic,
                "namespace": namespace,
                "detail": detail,
            }),
        );
    }

    /// Gives an event the sequence number and timestamp its publisher left out.
    /// Returns whether it added any.
    fn stamp(&mut self, typed: &TypedTopic<'_>, message: &mut Message) -> bool {
        let Message::Event(event) = message else {
            return false;
        };
        let stamped = event.seq.is_none() || event.ts_us.is_none();
        if event.seq.is_none() {
            let counters = self.seq.entry(typed.fb.to_owned()).or_default();
            let counter = match counters.get_mut(typed.port) {
                Some(c) => c,
                None => counters.entry(typed.port.to_owned()).or_insert(0),
            };
            *counter += 1;
            event.seq = Some(*counter);
        }
        if event.ts_us.is_none() {
            event.ts_us = Some(now_us());
        }
        stamped
    }

    fn declare(&mut self, fb: &FbTopics, payload: &Bytes) -> Check {
        if !self.identity_verified() {
            return refuse(
                Refusal::NotAuthorized,
                "a device connects with its id as both client id and username",
            );
        }
        match self.admit_declaration(fb, payload) {
            Ok(interface) => {
                let fbs = interface.fbs.len();
                let old = fb.registry.get(&self.device).map(|r| r.interface);
                let declared =
                    fb.registry
                        .declare(&self.device, self.session, interface, &self.registrant());
                let interface = match declared {
                    Ok(interface) => interface,
                    Err(full) => {
                        fb.metrics
                            .declarations
                            .with_label_values(&["refused"])
                            .inc();
                        let device = self.device.clone();
                        return self.registry_full(fb, &device, &full, true);
                    }
                };
                // A port the new declaration removes or retypes: its retained value would
                // be ill-typed for a new subscriber. Cleared in every namespace.
                if let Some(old) = old {
                    let changed = old
                        .outputs()
                        .filter(|(f, p)| interface.output(f, p) != old.output(f, p));
                    self.outbox
                        .extend(crate::registry::retained_clears(&self.device, changed));
                }
                self.interface = Some(interface);
                self.activity = fb.registry.activity(&self.device);
                fb.metrics
                    .declarations
                    .with_label_values(&["accepted"])
                    .inc();
                tracing::info!(
                    device = self.device,
                    session = self.session,
                    fbs,
                    "interface declared"
                );
                self.diag_answer(
                    json!({"kind": "declaration", "ok": true, "session": self.session, "line": fb.registry.line()}),
                );
                Check::Consumed
            }
            Err(Refused { limit, errors }) => {
                fb.metrics
                    .declarations
                    .with_label_values(&["refused"])
                    .inc();
                if let Some(limit) = limit {
                    fb.metrics.limit_refusals.with_label_values(&[limit]).inc();
                }
                let body =
                    json!({"kind": "declaration", "ok": false, "limit": limit, "errors": errors});
                if limit == Some("declaration_rate") {
                    // Not answered beyond the diagnostics' rate, and logged once a minute:
                    // a device re-declaring in a loop costs neither a flood nor a log.
                    let now = Instant::now();
                    if self
                        .declare_logged
                        .is_none_or(|t| now.duration_since(t).as_secs() >= 60)
                    {
                        self.declare_logged = Some(now);
                        tracing::warn!(
                            device = self.device,
                            per_minute = self.limits.declarations_per_minute,
                            "declarations refused: over [fb] declarations_per_minute \
                             (logged at most once a minute per device)"
                        );
                    }
                    self.diag(fb, body);
                } else {
                    tracing::warn!(
                        device = self.device,
                        limit,
                        errors = errors.len(),
                        first = errors.first().map(ToString::to_string),
                        "interface declaration refused"
                    );
                    // Every declaration within the rate is answered (the device waits for
                    // it), within the diagnostics' size cap.
                    self.diag_answer(body);
                }
                // Counted and answered here; `rejected` must not describe it a second time.
                Check::Refused(Rejection {
                    refusal: match limit {
                        Some(_) => Refusal::QuotaExceeded,
                        None => Refusal::PayloadFormatInvalid,
                    },
                    detail: String::new(),
                })
            }
        }
    }

    /// The one place that decides whether a declaration is admitted, cheapest check
    /// first: the rate, the size, the counts (before the types are parsed), the
    /// declaration's own validity, each port's worst-case message size, the profile.
    fn admit_declaration(&mut self, fb: &FbTopics, payload: &[u8]) -> Result<Interface, Refused> {
        let limits = self.limits;
        let per_minute = f64::from(limits.declarations_per_minute);
        if let Err(wait) = self.declare_budget.take(per_minute / 60.0, per_minute) {
            return Err(Refused::limit(
                "declaration_rate",
                format!(
                    "rate limited, retry after {} s ([fb] declarations_per_minute = {})",
                    wait.ceil().max(1.0) as u64,
                    limits.declarations_per_minute
                ),
            ));
        }
        if payload.len() > limits.max_declaration_bytes {
            return Err(Refused::limit(
                "declaration_bytes",
                format!(
                    "{} bytes; at most {} ([fb] max_declaration_bytes)",
                    payload.len(),
                    limits.max_declaration_bytes
                ),
            ));
        }
        let declaration = Declaration::from_json(payload).map_err(|e| Refused {
            limit: None,
            errors: vec![e],
        })?;
        if declaration.fbs.len() > limits.max_fbs {
            return Err(Refused::limit(
                "fbs",
                format!(
                    "{} FBs declared; at most {} ([fb] max_fbs)",
                    declaration.fbs.len(),
                    limits.max_fbs
                ),
            ));
        }
        let ports = declaration.port_count();
        if ports > limits.max_ports {
            return Err(Refused::limit(
                "ports",
                format!(
                    "{ports} ports declared; at most {} ([fb] max_ports)",
                    limits.max_ports
                ),
            ));
        }
        let interface = declaration.validate().map_err(|errors| Refused {
            limit: None,
            errors,
        })?;
        let too_large: Vec<DeclarationError> = interface
            .outputs()
            .filter_map(|(f, p)| {
                let port = interface.output(f, p)?;
                let (encoding, bytes) = codec::worst::largest(p, &port);
                let topic = format!("{}/{}/{f}/{p}", encoding.namespace(), self.device);
                // As a re-encoded copy is measured (`accepted`): payload, topic, header.
                let packet = bytes + topic.len() + 16;
                (packet > fb.max_packet).then(|| DeclarationError {
                    fb: Some(f.to_owned()),
                    port: Some(p.to_owned()),
                    error: format!(
                        "a message can take {bytes} bytes on {}/ (a {packet}-byte packet), more \
                         than [broker] max_packet_bytes ({}); declare a smaller array",
                        encoding.namespace(),
                        fb.max_packet
                    ),
                })
            })
            .collect();
        if !too_large.is_empty() {
            return Err(Refused {
                limit: Some("encoded_size"),
                errors: too_large,
            });
        }
        match &self.profile {
            // A profiled device declares what its profile says, or nothing.
            Some(profile) if profile.interface != interface => Err(Refused {
                limit: None,
                errors: vec![DeclarationError {
                    fb: None,
                    port: None,
                    error: format!(
                        "differs from the interface of device {}'s profile, which stays in force",
                        profile.device
                    ),
                }],
            }),
            _ => Ok(interface),
        }
    }

    /// Counts, logs (once per topic and reason) and describes a refused publication.
    fn rejected(&mut self, fb: &FbTopics, topic: &str, rejection: &Rejection) {
        if rejection.detail.is_empty() {
            return;
        }
        // Labels stay bounded: a port only when declared (on its typed topic, or on the
        // device's own topic its profile maps), a device only when registered.
        let declared = |fb: &str, port: &str| {
            self.interface
                .as_ref()
                .is_some_and(|i| i.output(fb, port).is_some())
        };
        let own = self.profile.as_ref().and_then(|p| {
            p.outputs
                .iter()
                .find(|o| o.topic == topic)
                .map(|o| format!("{}.{}", o.fb, o.port))
        });
        let port = TypedTopic::parse(topic)
            .filter(|t| declared(t.fb, t.port))
            .map(|t| format!("{}.{}", t.fb, t.port))
            .or(own)
            .unwrap_or_else(|| "undeclared".to_owned());
        let device = if self.interface.is_some() {
            self.device.as_str()
        } else {
            "undeclared"
        };
        fb.metrics
            .typed_refused(device, &port, rejection.refusal.label());
        if self.logged.len() < 1024
            && self
                .logged
                .insert((topic.to_owned(), rejection.refusal.label()))
        {
            tracing::warn!(
                device = self.device,
                topic,
                reason = rejection.refusal.label(),
                detail = rejection.detail,
                "typed publication refused (logged once per topic and reason)"
            );
        }
        self.diag(
            fb,
            json!({
                "kind": "rejected",
                "topic": topic,
                "reason": rejection.refusal.label(),
                "code": rejection.refusal.code(),
                "detail": rejection.detail,
            }),
        );
    }

    /// Queues a diagnostic for `fbbus/diag/<device>`, within the connection's budget
    /// (`[fb] diag_per_second`); beyond it, dropped and counted. The first one published
    /// after drops is preceded by one saying how many.
    fn diag(&mut self, fb: &FbTopics, body: serde_json::Value) {
        let device = self.device.clone();
        self.diag_to(fb, &device, body);
    }

    /// [`FbSession::diag`] for `device`'s diag topic (a profiled device this connection
    /// was refused as).
    fn diag_to(&mut self, fb: &FbTopics, device: &str, body: serde_json::Value) {
        let (rate, burst) = self.diag_rate;
        if self.diag_budget.take(rate, burst).is_err() {
            self.diag_dropped += 1;
            fb.metrics.diag_dropped.inc();
            return;
        }
        self.queue_diag(device, body);
    }

    /// Queues a diagnostic that is always published: the answer to a declaration within
    /// the declaration rate (the device waits for it). It uses up the budget as any other.
    fn diag_answer(&mut self, body: serde_json::Value) {
        let (rate, burst) = self.diag_rate;
        let _ = self.diag_budget.take(rate, burst);
        let device = self.device.clone();
        self.queue_diag(&device, body);
    }

    fn queue_diag(&mut self, device: &str, body: serde_json::Value) {
        if self.diag_dropped > 0 {
            let dropped = std::mem::take(&mut self.diag_dropped);
            self.outbox.push(BrokerMessage::broker(
                topic::diag(device),
                json!({
                    "kind": "diag_dropped",
                    "dropped": dropped,
                    "detail": format!("{dropped} diag messages dropped ([fb] diag_per_second)"),
                })
                .to_string(),
                false,
            ));
        }
        self.outbox.push(BrokerMessage::broker(
            topic::diag(device),
            bounded_diag(body),
            false,
        ));
    }
}

/// The most a diagnostic carries, in bytes: a summary of what was wrong, not an echo of a
/// large bad input (issue 21: a 64 KB bad declaration made an 821 KB diagnostic).
pub const DIAG_MAX_BYTES: usize = 4096;

/// `body` as text of at most [`DIAG_MAX_BYTES`]: long strings are cut (at a character
/// boundary) and long lists keep their first entries, with `truncated: true`; if that
/// is still too long, only the kind, reason and code remain.
fn bounded_diag(mut body: serde_json::Value) -> String {
    let text = body.to_string();
    if text.len() <= DIAG_MAX_BYTES {
        return text;
    }
    fn shorten(v: &mut serde_json::Value) {
        match v {
            serde_json::Value::String(s) if s.len() > 256 => {
                let mut end = 256;
                while !s.is_char_boundary(end) {
                    end -= 1;
                }
                let more = s.len() - end;
                s.truncate(end);
                s.push_str(&format!("... ({more} bytes more)"));
            }
            serde_json::Value::Array(a) => {
                a.truncate(8);
                a.iter_mut().for_each(shorten);
            }
            serde_json::Value::Object(o) => o.values_mut().for_each(shorten),
            _ => {}
        }
    }
    shorten(&mut body);
    if let Some(o) = body.as_object_mut() {
        o.insert("truncated".into(), true.into());
    }
    let text = body.to_string();
    if text.len() <= DIAG_MAX_BYTES {
        return text;
    }
    serde_json::json!({
        "kind": body.get("kind"),
        "reason": body.get("reason"),
        "code": body.get("code"),
        "truncated": true,
    })
    .to_string()
}

fn refuse(refusal: Refusal, detail: impl Into<String>) -> Check {
    Check::Refused(Rejection {
        refusal,
        detail: detail.into(),
    })
}

fn now_us() -> u64 {
    SystemTime::now()
        .duration_since(SystemTime::UNIX_EPOCH)
        .map(|d| d.as_micros() as u64)
        .unwrap_or(0)
}

#[cfg(test)]
mod diag_tests {
    use super::*;

    #[test]
    fn diagnostics_are_bounded_and_cut_at_character_boundaries() {
        let small = serde_json::json!({"kind": "rejected", "detail": "x"});
        assert_eq!(bounded_diag(small.clone()), small.to_string());
        let errors: Vec<String> = (0..5000)
            .map(|i| format!("port {i}: é{}", "ü".repeat(300)))
            .collect();
        let big = serde_json::json!({
            "kind": "declaration_refused",
            "reason": "invalid",
            "errors": errors,
            "detail": "ß".repeat(100_000),
        });
        let text = bounded_diag(big);
        assert!(text.len() <= DIAG_MAX_BYTES, "{}", text.len());
        let v: serde_json::Value = serde_json::from_str(&text).unwrap();
        assert_eq!(v["truncated"], true);
        assert_eq!(v["kind"], "declaration_refused");
        let wide: Vec<String> = (0..100)
            .map(|i| format!("{i}{}", "a".repeat(250)))
            .collect();
        let text = bounded_diag(
            serde_json::json!({"kind": "k", "a": wide.clone(), "b": wide.clone(), "c": wide}),
        );
        assert!(text.len() <= DIAG_MAX_BYTES);
    }
}

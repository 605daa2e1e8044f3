//! The check itself: what one publication (or will) on a typed topic is, whose it is,
//! and whether it is routed, refused or consumed; and what a topics-only device's own
//! topics mean (a profile's outputs, and the inputs it subscribes to).

use std::sync::Arc;

use bytes::Bytes;
use fb_bridge::codec::{self, Encoding};
use fb_bridge::profile::{self as profile_file, Identity, Profile};
use fb_bridge::topic::{self, TypedTopic};
use serde_json::json;

use super::diag::refuse;
use super::{Check, FbSession, FbTopics, Refusal, Rejection, Undeclared};
use crate::profiles::ProfileSet;
use crate::registry::Status;

impl FbSession {
    /// Checks one publication (ACL already passed) and says what to route.
    pub fn check(&mut self, fb: &FbTopics, topic: &str, payload: &Bytes) -> Check {
        let check = self.decide(fb, topic, payload);
        if let Check::Refused(rejection) = &check {
            self.rejected(fb, topic, rejection);
        }
        check
    }

    /// [`FbSession::check`] for a will (the client's or its profile's): a will says the
    /// device is gone, so it is no sign of life and leaves the output timing (`silence`)
    /// as it was.
    pub fn check_will(&mut self, fb: &FbTopics, topic: &str, payload: &Bytes) -> Check {
        let activity = self.activity.take();
        let check = self.check(fb, topic, payload);
        self.activity = activity;
        check
    }

    pub(super) fn decide(&mut self, fb: &FbTopics, topic: &str, payload: &Bytes) -> Check {
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

    /// A publication on `profile`'s own output topic number `i`: the device's, decoded
    /// the way it speaks, then routed like a typed publication of that port, on its own
    /// topic (first, as it came) and on the typed topics.
    pub(super) fn own_topic(
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
                if profile.identity == Identity::TopicsOnly && !self.may_speak_for(profile) {
                    // Described under the device's id, where its operator looks.
                    let detail = format!(
                        "{} is topics-only device {}'s own topic; its profile lets only \
                         clients {} speak for it",
                        own.topic,
                        profile.device,
                        profile.speakers.describe()
                    );
                    return self.refused_as(fb, profile, own, Refusal::NotAuthorized, detail);
                }
                profile.identity == Identity::TopicsOnly
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
                let detail = format!("{} ({}.{}): {e}", own.topic, own.fb, own.port);
                if self.profile.is_none() {
                    // Not yet the device: a refused value speaks for nobody. It is still
                    // described under the device's id, where its operator looks.
                    return self.refused_as(
                        fb,
                        profile,
                        own,
                        Refusal::PayloadFormatInvalid,
                        detail,
                    );
                }
                return refuse(Refusal::PayloadFormatInvalid, detail);
            }
        };
        if self.profile.is_none() {
            // A topics-only device's first accepted publication on this connection: the
            // connection speaks for it from now on (`speak_for`).
            if let Err(refused) = self.speak_for(fb, profile, "publishes on") {
                return refused;
            }
            self.published_own = true;
        }
        let typed = TypedTopic {
            encoding: Encoding::Json,
            device: &profile.device,
            fb: &own.fb,
            port: &own.port,
        };
        let first = (own.topic.clone(), payload.clone());
        self.accepted(fb, profiles, &typed, &port, message, payload, Some(first))
    }

    /// Whether this connection may speak for topics-only `profile`: its username and
    /// source address as the profile's `speakers_from` and `speaker_username` allow
    /// (by default: any address, no username or the device id).
    fn may_speak_for(&self, profile: &Profile) -> bool {
        profile
            .speakers
            .admit(&profile.device, self.peer, self.username.as_deref())
    }

    /// From now on this connection speaks for the topics-only device of `profile` (it
    /// `how` one of the device's own topics: its first accepted publication on an output,
    /// or its subscription to an input): the registry shows the device online until the
    /// connection (or a newer one of it) ends, and its broker-side will fires then. Its
    /// other connections may speak for it already: then it is online, and its interface
    /// and output timing are theirs. Err: the registry is full (told and counted).
    pub(super) fn speak_for(
        &mut self,
        fb: &FbTopics,
        profile: &Arc<Profile>,
        how: &str,
    ) -> Result<(), Check> {
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
                return Err(self.registry_full(fb, &profile.device, &full, false));
            }
        };
        self.by_topics = true;
        self.set_profile(Arc::clone(profile), interface);
        self.set_activity(fb.registry.activity(&profile.device));
        tracing::info!(
            device = profile.device,
            client_id = self.client_id,
            session = self.session,
            "a client {how} a topics-only device's own topic: it is that device"
        );
        Ok(())
    }

    /// A refused publication on topics-only `profile`'s own output `own` from a
    /// connection that does not speak for the device: counted, logged and described under
    /// the device's id, and nothing else changes.
    pub(super) fn refused_as(
        &mut self,
        fb: &FbTopics,
        profile: &Profile,
        own: &fb_bridge::profile::OwnTopic,
        refusal: Refusal,
        detail: String,
    ) -> Check {
        let port = format!("{}.{}", own.fb, own.port);
        fb.metrics
            .typed_refused(&profile.device, &port, refusal.label());
        if self.logged.len() < 1024
            && self.logged.insert((own.topic.clone(), refusal.label()))
            && crate::logging::OUTSIDE.allow()
        {
            tracing::warn!(
                device = profile.device,
                client_id = self.client_id,
                topic = own.topic,
                reason = refusal.label(),
                detail,
                "typed publication refused; the client does not speak for the device \
                 (logged once per topic and reason)"
            );
        }
        self.diag_to(
            fb,
            &profile.device,
            json!({
                "kind": "rejected",
                "topic": own.topic,
                "reason": refusal.label(),
                "code": refusal.code(),
                "detail": detail,
            }),
        );
        Check::Refused(Rejection {
            refusal,
            detail: String::new(),
        })
    }

    /// A subscription `filter` was granted to this connection: if it is the input topic of
    /// a topics-only device and the connection is no device yet (nor another device's
    /// user), the connection speaks for that device from now on, as a publishing one
    /// does. A runtime that only subscribes (a DINASORE with MQTT_SUBSCRIBER FBs only) is
    /// online while it listens.
    pub fn granted_subscription(&mut self, fb: &FbTopics, filter: &str) {
        if self.profile.is_some() {
            return;
        }
        let profiles = fb.profiles.get();
        let Some(profile) = profiles.input(filter) else {
            return;
        };
        if profile.identity != Identity::TopicsOnly || !self.may_speak_for(profile) {
            return;
        }
        let profile = Arc::clone(profile);
        // Err: the registry is full, told on the device's diag topic; the subscription
        // itself stands.
        let _ = self.speak_for(fb, &profile, "subscribes to");
    }
}

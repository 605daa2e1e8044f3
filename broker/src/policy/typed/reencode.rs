//! An accepted typed message, routed canonically on `fb/` and re-encoded on `dinasore/`
//! and `fbdk/` once someone reads them (and fed to topics-only devices' inputs): stamped,
//! timed for silence, and never put where its encoding cannot carry it.

use std::sync::Arc;

use bytes::Bytes;
use fb_bridge::codec::{self, Encoding};
use fb_bridge::profile::Profile;
use fb_bridge::topic::TypedTopic;
use fb_bridge::{EventMessage, Message, OutputPort};
use serde_json::json;

use super::{now_us, Check, FbSession, FbTopics};
use crate::profiles::ProfileSet;

impl FbSession {
    /// An accepted typed message on `typed` (port shape `port`): stamped, timed, and
    /// routed on `fb/` (canonical JSON), on the other typed namespaces someone reads, and
    /// on the profile input topics it feeds. `own`: it came on a device's own topic,
    /// routed first as it came.
    #[allow(clippy::too_many_arguments)]
    pub(super) fn accepted(
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
            let back = activity.published(
                typed.fb,
                typed.port,
                std::time::Instant::now(),
                fb.registry.silence_bound(),
            );
            if back {
                // Ended for its silence (`liveness.offline_after_silent_s`), it speaks again.
                fb.registry.spoke_again(&self.device, self.session);
            }
        }
        // (Collecting nothing allocates nothing: the common case.)
        let feeds: Vec<(&Arc<Profile>, usize)> = match profiles.maps_topics() {
            true => profiles.feeds(typed.device, typed.fb, typed.port).collect(),
            false => Vec::new(),
        };
        // Subscribers of fb/ always get canonical JSON. JSON that came in complete (nothing
        // stamped) on a port whose types have one JSON form (or a BOOL port's `true`, not
        // its `1`: `json_is_canonical`) is canonical already and is routed as it came;
        // other accepted forms (`"16#FF"`, `"TIME#1.5s"`, ...) are
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
    pub(super) fn feed(
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
    pub(super) fn not_reencoded(
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
        if self.logged.len() < 1024
            && self.logged.insert((topic.to_owned(), "not_reencoded"))
            && crate::logging::OUTSIDE.allow()
        {
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
    pub(super) fn stamp(&mut self, typed: &TypedTopic<'_>, message: &mut Message) -> bool {
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
}

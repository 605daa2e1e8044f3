//! The publish policy: what every publication passes before it reaches the router,
//! whichever door it came in by.
//!
//! Three doors lead to the router:
//! - a client's PUBLISH (`session::inbound`);
//! - a client's will, fired by fbbus when the connection ends (`session::close`);
//! - a message from another line, imported from the bus (`bridge`).
//!
//! "A message obeys this line's access rules and typed check, whatever its door" holds
//! because all three call [`PublishPolicy::admit`], which runs the stages in this order:
//!
//! 1. **access** ([`access`]): the ACL, or allow-all when no ACL file is configured;
//! 2. **typed check** ([`typed`]): typed FB topics against the publishing device's
//!    declared interface; declarations are consumed here. With the Sparkplug view on,
//!    its group's topics are decided instead by [`crate::sparkplug::command`]: a host's
//!    `DCMD` is authorized per input port by the same ACL and checked against the ports'
//!    types, then delivered typed;
//! 3. **origin mark** ([`origin`]): the publication's QoS, RETAIN and publisher, which the
//!    router carries to the delivery rules.
//!
//! Refusals are counted here, by door; what the door answers (a PUBACK reason code, a
//! refused CONNECT, a dropped bus message) is the door's business. The policy owns no
//! socket and awaits nothing, so its tests (below) run without a broker.

pub mod access;
pub mod budget;
pub mod origin;
pub mod typed;

use std::sync::Arc;

use bytes::Bytes;
use security::Identity;

use crate::metrics::Metrics;
use access::Access;
use origin::Origin;
use typed::{Check, FbSession, FbTopics, Refusal};

/// The way a publication came in.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Door {
    /// A client's PUBLISH.
    Client,
    /// A client's will, fired when its connection ended. Its topic was also checked at
    /// CONNECT ([`PublishPolicy::will_allowed`]); it is checked again when it fires,
    /// against the rules and the declaration in force then.
    Will,
    /// A message another line's broker put on the bus, published there by a device of
    /// that line.
    #[cfg_attr(not(feature = "bridge"), allow(dead_code))]
    Bus,
}

/// The policy stage that refused a publication.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Stage {
    Access,
    Typed,
}

/// One publication, as the policy sees it.
#[derive(Debug, Clone, Copy)]
pub struct Publication<'a> {
    pub topic: &'a str,
    pub payload: &'a Bytes,
    pub qos: u8,
    pub retain: bool,
}

/// What to do with a publication.
#[derive(Debug)]
pub enum Admission {
    /// Route it, marked with `origin`: unchanged when `routes` is None, otherwise as these
    /// (topic, payload) pairs, the first in place of the publication (its QoS and packet
    /// id), the others as copies of it (the typed message in the other encodings).
    Route {
        origin: Origin,
        routes: Option<Vec<(String, Bytes)>>,
    },
    /// The broker handled it (a declaration): acknowledge, do not route.
    Consumed,
    /// Refused by `stage`, for `refusal` (one MQTT 5 reason code).
    Refused { stage: Stage, refusal: Refusal },
}

/// The stages, built once at start-up and shared by every door.
pub struct PublishPolicy {
    access: Access,
    typed: Arc<FbTopics>,
    /// The Sparkplug group's stage, when the view is on.
    sparkplug: Option<crate::sparkplug::command::Commands>,
    metrics: Arc<Metrics>,
}

impl PublishPolicy {
    pub fn new(access: Access, typed: Arc<FbTopics>, metrics: Arc<Metrics>) -> PublishPolicy {
        PublishPolicy {
            access,
            typed,
            sparkplug: None,
            metrics,
        }
    }

    /// Decides the Sparkplug group's topics with `commands` (`[sparkplug]` on).
    pub fn with_sparkplug(mut self, commands: crate::sparkplug::command::Commands) -> Self {
        self.sparkplug = Some(commands);
        self
    }

    /// The access rules, which also decide subscriptions.
    pub fn access(&self) -> &Access {
        &self.access
    }

    /// Runs the stages in order for `publication`, published by the device whose
    /// typed-topic state is `publisher` and whose messages carry `origin_name`.
    pub fn admit(
        &self,
        door: Door,
        publisher: &mut FbSession,
        origin_name: &Arc<str>,
        publication: Publication<'_>,
    ) -> Admission {
        let Publication {
            topic,
            payload,
            qos,
            retain,
        } = publication;

        // 1. Access.
        if !self.access.can_publish(publisher.identity(), topic) {
            self.count_refusal(door, Stage::Access);
            return Admission::Refused {
                stage: Stage::Access,
                refusal: Refusal::NotAuthorized,
            };
        }

        // 2. Typed check: a Sparkplug command (its values for input ports) or an FB topic.
        if let Some(sparkplug) = &self.sparkplug {
            let command = sparkplug.check(&self.access, publisher, &self.typed, topic, payload);
            match command {
                None => {}
                Some(Ok(routes)) => {
                    return Admission::Route {
                        origin: origin::new(qos, retain, origin_name),
                        routes: (!routes.is_empty()).then_some(routes),
                    }
                }
                Some(Err(refusal)) => {
                    self.count_refusal(door, Stage::Typed);
                    return Admission::Refused {
                        stage: Stage::Typed,
                        refusal,
                    };
                }
            }
        }
        // A message from another line is checked like a local one,
        // against its device's declaration as its own line's record gave it (the bus door
        // imports nothing for a device without one: `bridge::import`).
        let cleared = match retain && payload.is_empty() {
            true => publisher.clear_retained(topic),
            false => None,
        };
        let check = match cleared {
            Some(check) => check,
            None if door == Door::Will => publisher.check_will(&self.typed, topic, payload),
            None => publisher.check(&self.typed, topic, payload),
        };
        let routes = match check {
            Check::Pass => None,
            Check::Route(routes) => Some(routes),
            Check::Consumed => return Admission::Consumed,
            Check::Refused(rejection) => {
                self.count_refusal(door, Stage::Typed);
                return Admission::Refused {
                    stage: Stage::Typed,
                    refusal: rejection.refusal,
                };
            }
        };

        // 3. Origin mark.
        Admission::Route {
            origin: origin::new(qos, retain, origin_name),
            routes,
        }
    }

    /// At CONNECT: may the client `who` leave a will on `topic`? A will may only go where
    /// the client may publish, and never into the broker's `fbbus/` namespace, where it
    /// could forge registry records. Counted when refused.
    pub fn will_allowed(&self, who: Identity<'_>, topic: &str) -> bool {
        // (`$SYS/` is refused by `can_publish` itself.)
        let allowed = fb_bridge::topic::filter::valid_topic(topic)
            && !topic.starts_with(fb_bridge::topic::BROKER_NAMESPACE)
            && self.access.can_publish(who, topic);
        if !allowed {
            self.count_refusal(Door::Will, Stage::Access);
        }
        allowed
    }

    /// One refusal in the metric of its door. The typed stage counts its own refusals by
    /// device and port as well (`fbbus_typed_rejected_total`).
    fn count_refusal(&self, door: Door, stage: Stage) {
        let metrics = &self.metrics;
        match (door, stage) {
            (Door::Client, Stage::Access) => {
                metrics.acl_denied.with_label_values(&["publish"]).inc()
            }
            (Door::Will, Stage::Access) => metrics.acl_denied.with_label_values(&["will"]).inc(),
            (Door::Bus, Stage::Access) => metrics.bridge_dropped.with_label_values(&["acl"]).inc(),
            (Door::Bus, Stage::Typed) => metrics.bridge_dropped.with_label_values(&["type"]).inc(),
            (Door::Client | Door::Will, Stage::Typed) => {}
        }
    }
}

#[cfg(test)]
mod tests;

//! Declarations: a device's interface on `fbbus/declare/<id>` (or a profile's, at
//! CONNECT), admitted within the declaration limits and the registry's, and answered on
//! `fbbus/diag/<id>`.

use std::sync::Arc;
use std::time::Instant;

use bytes::Bytes;
use fb_bridge::codec::{self};
use fb_bridge::profile::Profile;
use fb_bridge::topic::{self};
use fb_bridge::{Declaration, DeclarationError, Interface};
use serde_json::json;

use super::diag::refuse;
use super::{Check, FbSession, FbTopics, Refusal, Refused, Rejection};
use crate::broker_publisher::Message as BrokerMessage;
use crate::policy::budget::Kind;

impl FbSession {
    pub(super) fn declare(&mut self, fb: &FbTopics, payload: &Bytes) -> Check {
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
                    fb,
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
                    self.diag_answer(fb, body);
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
    pub(super) fn admit_declaration(
        &mut self,
        fb: &FbTopics,
        payload: &[u8],
    ) -> Result<Interface, Refused> {
        let limits = self.limits;
        let per_minute = f64::from(limits.declarations_per_minute);
        let key = self.budget_key();
        let taken = fb
            .budgets
            .take(Kind::Declarations, &key, per_minute / 60.0, per_minute);
        if let Err(wait) = taken {
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

    /// A new device beyond a registry limit: the device is told on its diag topic, and the
    /// publication refused with 0x97. The registry counted and logged it. A declaration is
    /// always answered (the device waits for the answer); a topics-only device's
    /// publications are answered within the connection's diagnostics budget.
    pub(super) fn registry_full(
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
}

//! Diagnostics on `fbbus/diag/<device>`: why a publication or declaration was refused,
//! counted and logged once per topic and reason, within each connection's budget, and
//! never longer than [`DIAG_MAX_BYTES`].

use fb_bridge::topic::{self, TypedTopic};
use serde_json::json;

use super::{Check, FbSession, FbTopics, Refusal, Rejection};
use crate::broker_publisher::Message as BrokerMessage;
use crate::policy::budget::Kind;

/// The most a diagnostic carries, in bytes: a summary of what was wrong, not an echo of a
/// large bad input (issue 21: a 64 KB bad declaration made an 821 KB diagnostic).
pub const DIAG_MAX_BYTES: usize = 4096;

/// `body` as text of at most [`DIAG_MAX_BYTES`]: long strings are cut (at a character
/// boundary) and long lists keep their first entries, with `truncated: true`; if that
/// is still too long, only the kind, reason and code remain.
pub(super) fn bounded_diag(mut body: serde_json::Value) -> String {
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

pub(super) fn refuse(refusal: Refusal, detail: impl Into<String>) -> Check {
    Check::Refused(Rejection {
        refusal,
        detail: detail.into(),
    })
}

impl FbSession {
    /// Counts, logs (once per topic and reason) and describes a refused publication.
    pub(super) fn rejected(&mut self, fb: &FbTopics, topic: &str, rejection: &Rejection) {
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
            && crate::logging::OUTSIDE.allow()
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
    pub(super) fn diag(&mut self, fb: &FbTopics, body: serde_json::Value) {
        let device = self.device.clone();
        self.diag_to(fb, &device, body);
    }

    /// [`FbSession::diag`] for `device`'s diag topic (a profiled device this connection
    /// was refused as).
    pub(super) fn diag_to(&mut self, fb: &FbTopics, device: &str, body: serde_json::Value) {
        let (rate, burst) = self.diag_rate;
        let key = self.budget_key();
        if fb
            .budgets
            .take(Kind::Diagnostics, &key, rate, burst)
            .is_err()
        {
            self.diag_dropped += 1;
            fb.metrics.diag_dropped.inc();
            return;
        }
        self.queue_diag(device, body);
    }

    /// Queues a diagnostic that is always published: the answer to a declaration within
    /// the declaration rate (the device waits for it). It uses up the budget as any other.
    pub(super) fn diag_answer(&mut self, fb: &FbTopics, body: serde_json::Value) {
        let (rate, burst) = self.diag_rate;
        let key = self.budget_key();
        let _ = fb.budgets.take(Kind::Diagnostics, &key, rate, burst);
        let device = self.device.clone();
        self.queue_diag(&device, body);
    }

    pub(super) fn queue_diag(&mut self, device: &str, body: serde_json::Value) {
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

#[cfg(test)]
mod tests {
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

//! What the broker tells a device on `fbbus/diag/<id>`.

use serde_json::Value as Json;

/// One message from the broker on the device's diag topic (`docs/device-contract.md`
/// section 2 and "When a publication is refused").
#[derive(Debug, Clone, PartialEq)]
pub enum Diagnostic {
    /// The declaration was accepted: the connection's session number and the line.
    Declared { session: u64, line: String },
    /// The declaration was refused; one text per mistake, naming its FB and port.
    DeclarationRefused { errors: Vec<String> },
    /// A publication was refused and not delivered to anyone. On MQTT 3.1.1 its PUBACK
    /// looked like success: this is the only place the refusal shows.
    Rejected {
        topic: String,
        /// `not_authorized`, `topic_name_invalid` or `payload_format_invalid`.
        reason: String,
        /// The MQTT 5 reason code the refusal maps to (0x87, 0x90, 0x99).
        code: u8,
        detail: String,
    },
    /// Anything else, as sent.
    Other(Json),
}

impl Diagnostic {
    /// Reads a diag payload. Never fails: what is not understood is [`Diagnostic::Other`].
    pub fn parse(payload: &[u8]) -> Diagnostic {
        let json: Json = match serde_json::from_slice(payload) {
            Ok(json) => json,
            Err(_) => {
                return Diagnostic::Other(Json::String(
                    String::from_utf8_lossy(payload).into_owned(),
                ))
            }
        };
        let text = |key: &str| json[key].as_str().unwrap_or_default().to_owned();
        match (json["kind"].as_str(), json["ok"].as_bool()) {
            (Some("declaration"), Some(true)) => Diagnostic::Declared {
                session: json["session"].as_u64().unwrap_or_default(),
                line: text("line"),
            },
            (Some("declaration"), Some(false)) => Diagnostic::DeclarationRefused {
                errors: json["errors"]
                    .as_array()
                    .map(|errors| errors.iter().map(declaration_error).collect())
                    .unwrap_or_default(),
            },
            (Some("rejected"), _) => Diagnostic::Rejected {
                topic: text("topic"),
                reason: text("reason"),
                code: json["code"].as_u64().unwrap_or_default() as u8,
                detail: text("detail"),
            },
            _ => Diagnostic::Other(json),
        }
    }
}

/// `{"fb": "CONV", "port": "POSITION", "error": "..."}` as `FB CONV: port POSITION: ...`,
/// the way [`crate::DeclarationError`] displays itself.
fn declaration_error(e: &Json) -> String {
    let mut text = String::new();
    if let Some(fb) = e["fb"].as_str() {
        text += &format!("FB {fb}: ");
    }
    if let Some(port) = e["port"].as_str() {
        text += &format!("port {port}: ");
    }
    text + e["error"].as_str().unwrap_or("(no detail)")
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn every_kind_of_answer_is_read() {
        assert_eq!(
            Diagnostic::parse(br#"{"kind":"declaration","ok":true,"session":7,"line":"line-1"}"#),
            Diagnostic::Declared {
                session: 7,
                line: "line-1".into()
            }
        );
        assert_eq!(
            Diagnostic::parse(
                br#"{"kind":"declaration","ok":false,"errors":[
                    {"fb":"CONV","port":"POSITION","error":"unknown type 'FLOAT'"},
                    {"error":"not a valid interface declaration"}]}"#
            ),
            Diagnostic::DeclarationRefused {
                errors: vec![
                    "FB CONV: port POSITION: unknown type 'FLOAT'".into(),
                    "not a valid interface declaration".into()
                ]
            }
        );
        assert_eq!(
            Diagnostic::parse(
                br#"{"kind":"rejected","topic":"fb/a/CONV/POSITION","reason":"payload_format_invalid","code":153,"detail":"CONV.POSITION: 70000 is out of range for INT"}"#
            ),
            Diagnostic::Rejected {
                topic: "fb/a/CONV/POSITION".into(),
                reason: "payload_format_invalid".into(),
                code: 0x99,
                detail: "CONV.POSITION: 70000 is out of range for INT".into()
            }
        );
        assert!(matches!(
            Diagnostic::parse(b"not json"),
            Diagnostic::Other(_)
        ));
    }
}

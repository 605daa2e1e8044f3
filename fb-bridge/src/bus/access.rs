//! Who may do what on the bus: zenoh's access control, built from `[bridge.peers]`.
//!
//! zenoh identifies the other end of each mutual-TLS link by its certificate's common
//! name and checks every message crossing the link against these rules, before the
//! bridge sees it. Default deny; what is allowed, by what a peer is:
//!
//! | peer | may send us (ingress) |
//! |---|---|
//! | every peer | subscribe to and query `fbbus/**` and `fbbus/@/**` (reading is what the bus is for) |
//! | line `L` | put under `fbbus/L/fb/**`, `fbbus/@/record/L/**` (delete there too: a forgotten device) and `fbbus/@/loss/L/*`; liveliness tokens `fbbus/@/line/L`, `fbbus/@/interest/L/**`; queryables and replies under `fbbus/@/record/L/**`, `fbbus/@/retained/L/fb/**` |
//! | router | everything under `fbbus/**` and `fbbus/@/**`: it forwards the other lines' traffic, each checked at the router's own ingress |
//! | reader | nothing else |
//!
//! and every peer may receive the bus's keys from us (egress). Nothing outside them
//! crosses in either direction: keys outside the bus's schema are refused. (zenoh's
//! wildcards never match a verbatim `@` chunk: `fbbus/**` and `fbbus/@/**` are both
//! named.)
//!
//! This only holds what the certificate proves: that the sender *is* line `L`. That a
//! message of device X really comes from X's line is checked by the importing broker
//! against its registry (X must be a device L's own record declared).
//!
//! The same rules serve the plant's zenoh routers (`fbbus bus-acl` prints them for
//! `zenohd`), so a line behind a router is held to its scope at the router.

use serde_json::{json, Value};

use super::config::BusPeers;

/// Every kind of message zenoh's access control knows.
const ALL: [&str; 9] = [
    "put",
    "delete",
    "declare_subscriber",
    "query",
    "declare_queryable",
    "reply",
    "liveliness_token",
    "declare_liveliness_subscriber",
    "liveliness_query",
];

/// Every key of the bus: zenoh's wildcards never match a verbatim `@` chunk, so the
/// control plane is named on its own.
const BUS: [&str; 2] = ["fbbus/**", "fbbus/@/**"];

/// The keys line `line` speaks for: its data, its records, its tokens, its answers.
pub fn line_keys(line: &str) -> Vec<String> {
    vec![
        format!("fbbus/{line}/fb/**"),
        format!("fbbus/@/record/{line}/**"),
        format!("fbbus/@/line/{line}"),
        format!("fbbus/@/interest/{line}/**"),
        format!("fbbus/@/retained/{line}/fb/**"),
        format!("fbbus/@/loss/{line}/*"),
    ]
}

/// zenoh's `access_control` section for `peers`.
pub fn access_control(peers: &BusPeers) -> Value {
    let mut rules = vec![
        json!({
            "id": "read",
            "flows": ["ingress"],
            "messages": ["declare_subscriber", "query", "declare_liveliness_subscriber", "liveliness_query"],
            "key_exprs": BUS,
            "permission": "allow",
        }),
        json!({
            "id": "receive",
            "flows": ["egress"],
            "messages": ALL,
            "key_exprs": BUS,
            "permission": "allow",
        }),
    ];
    if !peers.routers.is_empty() {
        rules.push(json!({
            "id": "forward",
            "flows": ["ingress"],
            "messages": ALL,
            "key_exprs": BUS,
            "permission": "allow",
        }));
    }
    let (mut subjects, mut policies) = (Vec::new(), Vec::new());
    for line in &peers.lines {
        rules.push(json!({
            "id": format!("speak-as-{line}"),
            "flows": ["ingress"],
            "messages": ["put", "delete", "liveliness_token", "declare_queryable", "reply"],
            "key_exprs": line_keys(line),
            "permission": "allow",
        }));
        subjects.push(json!({"id": format!("line-{line}"), "cert_common_names": [line]}));
        policies.push(json!({
            "rules": ["read", "receive", format!("speak-as-{line}")],
            "subjects": [format!("line-{line}")],
        }));
    }
    for router in &peers.routers {
        subjects.push(json!({"id": format!("router-{router}"), "cert_common_names": [router]}));
        policies.push(json!({
            "rules": ["read", "receive", "forward"],
            "subjects": [format!("router-{router}")],
        }));
    }
    for reader in &peers.readers {
        subjects.push(json!({"id": format!("reader-{reader}"), "cert_common_names": [reader]}));
        policies.push(json!({
            "rules": ["read", "receive"],
            "subjects": [format!("reader-{reader}")],
        }));
    }
    json!({
        "enabled": true,
        "default_permission": "deny",
        "rules": rules,
        "subjects": subjects,
        "policies": policies,
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn each_line_speaks_only_for_itself() {
        let peers = BusPeers {
            lines: vec!["line-b".into(), "line-c".into()],
            routers: vec!["zenohd".into()],
            readers: vec!["historian".into()],
        };
        let acl = access_control(&peers);
        assert_eq!(acl["default_permission"], "deny");
        let rule = |id: &str| {
            acl["rules"]
                .as_array()
                .unwrap()
                .iter()
                .find(|r| r["id"] == id)
                .cloned()
                .unwrap_or_else(|| panic!("no rule {id}"))
        };
        let keys = rule("speak-as-line-c")["key_exprs"].to_string();
        assert!(keys.contains("fbbus/line-c/fb/**"), "{keys}");
        assert!(keys.contains("fbbus/@/loss/line-c/*"), "{keys}");
        assert!(!keys.contains("line-b"), "{keys}");
        let policy = |subject: &str| {
            acl["policies"]
                .as_array()
                .unwrap()
                .iter()
                .find(|p| p["subjects"][0] == subject)
                .cloned()
                .unwrap()
        };
        assert_eq!(
            policy("line-line-c")["rules"],
            json!(["read", "receive", "speak-as-line-c"])
        );
        assert_eq!(
            policy("reader-historian")["rules"],
            json!(["read", "receive"])
        );
        assert_eq!(
            policy("router-zenohd")["rules"],
            json!(["read", "receive", "forward"])
        );
        // Reading does not include speaking.
        assert!(!rule("read")["messages"].to_string().contains("put"));
    }
}

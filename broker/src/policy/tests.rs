//! The publish policy without a socket: each door, each stage, each refusal.
//!
//! These fail if any door stops applying the access rules or the typed check: the doors
//! differ only in the [`Door`] they pass, and every refusal test runs for all three.

use std::io::Write;

use fb_bridge::Declaration;
use security::AclRules;

use super::*;
use crate::broker_publisher::BrokerPublisher;
use crate::health::Health;
use crate::policy::typed::{Undeclared, FORTE_RECEIVE_BUFFER};
use crate::registry::Registry;
use crate::supervisor::Tasks;
use crate::watched_file::WatchedFile;

const DOORS: [Door; 3] = [Door::Client, Door::Will, Door::Bus];

/// Devices publish under their own id; `SECRET` is denied to everyone.
const ACL: &str = "\
pattern readwrite fb/%c/#
topic deny fb/plc-1/CONV/SECRET
";

/// plc-1's interface: an INT output, a BOOL one and the port the ACL denies.
const DECLARATION: &str =
    r#"{"fbs":{"CONV":{"data_out":{"SPEED":"INT","ON":"BOOL","SECRET":"INT"}}}}"#;

struct Line {
    policy: PublishPolicy,
    fb: Arc<FbTopics>,
    metrics: Arc<Metrics>,
    _acl_dir: Option<tempfile::TempDir>,
}

/// A line's policy with `acl` as its ACL file (None: no file, allow all).
fn line(acl: Option<&str>) -> Line {
    let metrics = Arc::new(Metrics::new());
    let (publisher, _) = BrokerPublisher::detached();
    let registry = Registry::open(
        "line-a",
        None,
        Arc::clone(&publisher),
        Arc::clone(&metrics),
        crate::silence::Bound::DEFAULT,
        crate::registry::Limits::NONE,
        &Tasks::new(&Health::new()),
    )
    .expect("a registry without a file always opens");
    let fb = Arc::new(FbTopics::new(
        registry,
        Undeclared::Reject,
        false,
        Default::default(),
        publisher,
        Arc::clone(&metrics),
    ));
    let (access, dir) = match acl {
        None => (Access::AllowAll, None),
        Some(text) => {
            let dir = tempfile::tempdir().unwrap();
            let path = dir.path().join("acl");
            std::fs::File::create(&path)
                .unwrap()
                .write_all(text.as_bytes())
                .unwrap();
            let file = WatchedFile::load("acl_file", &path, |p| {
                AclRules::load(p).map_err(|e| e.to_string())
            })
            .unwrap();
            (Access::new(Some(Arc::new(file))), Some(dir))
        }
    };
    Line {
        policy: PublishPolicy::new(access, Arc::clone(&fb), Arc::clone(&metrics)),
        fb,
        metrics,
        _acl_dir: dir,
    }
}

impl Line {
    /// plc-1, logged in with its id as username, with its interface declared.
    fn device(&self) -> FbSession {
        let mut session = FbSession::new(&self.fb, "plc-1", Some("plc-1"), 1);
        let interface = Declaration::from_json(DECLARATION.as_bytes())
            .unwrap()
            .validate()
            .unwrap();
        session.set_interface(self.fb.registry.declare("plc-1", 1, interface, "test").ok());
        session
    }

    fn admit(
        &self,
        door: Door,
        publisher: &mut FbSession,
        topic: &str,
        payload: &str,
    ) -> Admission {
        let payload = Bytes::from(payload.to_owned());
        self.policy.admit(
            door,
            publisher,
            &Arc::from("plc-1"),
            Publication {
                topic,
                payload: &payload,
                qos: 1,
                retain: true,
            },
        )
    }

    fn count(&self, door: Door, stage: Stage) -> u64 {
        let (vec, label) = match (door, stage) {
            (Door::Client, Stage::Access) => (&self.metrics.acl_denied, "publish"),
            (Door::Will, Stage::Access) => (&self.metrics.acl_denied, "will"),
            (Door::Bus, Stage::Access) => (&self.metrics.bridge_dropped, "acl"),
            (Door::Bus, Stage::Typed) => (&self.metrics.bridge_dropped, "type"),
            (_, Stage::Typed) => return 0,
        };
        vec.with_label_values(&[label]).get()
    }

    fn typed_rejected(&self) -> u64 {
        self.metrics
            .typed_rejected
            .with_label_values(&["plc-1", "CONV.SPEED", "payload_format_invalid"])
            .get()
    }
}

#[test]
fn every_door_routes_a_well_typed_message_with_its_origin() {
    let line = line(Some(ACL));
    for door in DOORS {
        let mut device = line.device();
        match line.admit(door, &mut device, "fb/plc-1/CONV/SPEED", "3") {
            Admission::Route { origin, routes } => {
                assert_eq!((origin.qos, origin.retain), (1, true), "{door:?}");
                assert_eq!(&*origin.publisher, "plc-1", "{door:?}");
                // Canonical JSON, nobody reads another encoding: routed as published.
                assert!(routes.is_none(), "{door:?}: {routes:?}");
            }
            other => panic!("{door:?}: {other:?}"),
        }
    }
}

#[test]
fn every_door_applies_the_access_rules() {
    let line = line(Some(ACL));
    for door in DOORS {
        let mut device = line.device();
        // Well typed, declared, and the device's own topic: only the ACL can refuse it.
        let admission = line.admit(door, &mut device, "fb/plc-1/CONV/SECRET", "3");
        assert!(
            matches!(
                admission,
                Admission::Refused {
                    stage: Stage::Access,
                    refusal: Refusal::NotAuthorized
                }
            ),
            "{door:?}: {admission:?}"
        );
        assert_eq!(line.count(door, Stage::Access), 1, "{door:?} not counted");
    }
}

#[test]
fn every_door_applies_the_typed_check() {
    let line = line(Some(ACL));
    for (n, door) in DOORS.into_iter().enumerate() {
        let mut device = line.device();
        // Allowed by the ACL; 70000 is out of range for INT.
        let admission = line.admit(door, &mut device, "fb/plc-1/CONV/SPEED", "70000");
        assert!(
            matches!(
                admission,
                Admission::Refused {
                    stage: Stage::Typed,
                    refusal: Refusal::PayloadFormatInvalid
                }
            ),
            "{door:?}: {admission:?}"
        );
        assert_eq!(line.typed_rejected(), n as u64 + 1, "{door:?} not counted");
        if door == Door::Bus {
            assert_eq!(line.count(door, Stage::Typed), 1);
        }
    }
}

#[test]
fn access_comes_before_the_typed_check() {
    let line = line(Some(ACL));
    let mut device = line.device();
    // Denied and ill-typed: the ACL answers, the typed stage never sees it.
    let admission = line.admit(Door::Client, &mut device, "fb/plc-1/CONV/SECRET", "x");
    assert!(matches!(
        admission,
        Admission::Refused {
            stage: Stage::Access,
            ..
        }
    ));
    assert_eq!(
        line.metrics
            .typed_rejected
            .with_label_values(&["plc-1", "CONV.SECRET", "payload_format_invalid"])
            .get(),
        0
    );
}

#[test]
fn without_an_acl_file_access_allows_all_and_the_typed_check_still_runs() {
    let line = line(None);
    assert!(matches!(line.policy.access(), Access::AllowAll));
    for door in DOORS {
        let mut device = line.device();
        let admission = line.admit(door, &mut device, "fb/plc-1/CONV/SECRET", "3");
        assert!(matches!(admission, Admission::Route { .. }), "{door:?}");
        let admission = line.admit(door, &mut device, "fb/plc-1/CONV/SPEED", "true");
        assert!(
            matches!(
                admission,
                Admission::Refused {
                    stage: Stage::Typed,
                    ..
                }
            ),
            "{door:?}: {admission:?}"
        );
    }
}

#[test]
fn another_devices_typed_topic_is_refused_at_every_local_door() {
    let line = line(None);
    for door in [Door::Client, Door::Will] {
        let mut device = line.device();
        let admission = line.admit(door, &mut device, "fb/plc-2/CONV/SPEED", "3");
        assert!(
            matches!(
                admission,
                Admission::Refused {
                    stage: Stage::Typed,
                    refusal: Refusal::NotAuthorized
                }
            ),
            "{door:?}: {admission:?}"
        );
    }
}

/// The bus door no longer lets a message pass unchecked because its device's record has
/// not arrived: `bridge::import` refuses it before the policy, and a bus message that
/// reaches the policy without an interface is checked like a local one.
#[test]
fn a_remote_device_without_an_interface_is_checked_like_a_local_one() {
    let line = line(None);
    for door in [Door::Bus, Door::Client, Door::Will] {
        let mut device = FbSession::new(&line.fb, "plc-1", Some("plc-1"), 1);
        let admission = line.admit(door, &mut device, "fb/plc-1/CONV/SPEED", "3");
        assert!(
            matches!(
                admission,
                Admission::Refused {
                    stage: Stage::Typed,
                    refusal: Refusal::TopicNameInvalid
                }
            ),
            "{door:?}: {admission:?}"
        );
    }
}

#[test]
fn typed_messages_are_re_encoded_once_someone_reads_another_encoding() {
    let line = line(None);
    line.fb.subscribed("fbdk/#");
    let mut device = line.device();
    match line.admit(Door::Client, &mut device, "fb/plc-1/CONV/SPEED", "3") {
        Admission::Route {
            routes: Some(routes),
            ..
        } => {
            let topics: Vec<&str> = routes.iter().map(|(t, _)| t.as_str()).collect();
            assert_eq!(topics, ["fb/plc-1/CONV/SPEED", "fbdk/plc-1/CONV/SPEED"]);
        }
        other => panic!("{other:?}"),
    }
}

#[test]
fn a_bool_is_routed_as_published_as_true_and_re_encoded_from_1() {
    let line = line(None);
    let mut device = line.device();
    match line.admit(Door::Client, &mut device, "fb/plc-1/CONV/ON", "true") {
        Admission::Route { routes: None, .. } => {}
        other => panic!("true is canonical, routed as published: {other:?}"),
    }
    match line.admit(Door::Client, &mut device, "fb/plc-1/CONV/ON", "1") {
        Admission::Route {
            routes: Some(routes),
            ..
        } => {
            assert_eq!(routes.len(), 1, "{routes:?}");
            assert_eq!(routes[0].0, "fb/plc-1/CONV/ON");
            assert_eq!(&routes[0].1[..], b"true");
        }
        other => panic!("{other:?}"),
    }
}

#[test]
fn a_declaration_is_consumed() {
    let line = line(None);
    let mut device = FbSession::new(&line.fb, "plc-1", Some("plc-1"), 1);
    let admission = line.admit(
        Door::Client,
        &mut device,
        "fbbus/declare/plc-1",
        DECLARATION,
    );
    assert!(matches!(admission, Admission::Consumed), "{admission:?}");
    assert!(device.interface().is_some());
}

#[test]
fn a_will_is_checked_at_connect() {
    let line = line(Some(ACL));
    let who = Identity {
        username: Some("plc-1"),
        client_id: "plc-1",
    };
    assert!(line.policy.will_allowed(who, "fb/plc-1/CONV/SPEED"));
    // The ACL, the broker's namespace, an invalid topic name.
    for topic in ["fb/plc-1/CONV/SECRET", "fbbus/registry/plc-1", "fb/plc-1/#"] {
        assert!(!line.policy.will_allowed(who, topic), "{topic}");
    }
    assert_eq!(line.count(Door::Will, Stage::Access), 3);
    let all = self::line(None);
    assert!(!all.policy.will_allowed(who, "fbbus/registry/plc-1"));
}

/// A line in either `undeclared` mode, without an ACL file.
fn line_in_mode(undeclared: Undeclared, anonymous_devices: bool) -> Line {
    let mut line = line(None);
    let (publisher, _) = BrokerPublisher::detached();
    line.fb = Arc::new(FbTopics::new(
        Arc::clone(&line.fb.registry),
        undeclared,
        anonymous_devices,
        Default::default(),
        publisher,
        Arc::clone(&line.metrics),
    ));
    line.policy = PublishPolicy::new(
        Access::AllowAll,
        Arc::clone(&line.fb),
        Arc::clone(&line.metrics),
    );
    line
}

/// Every shape under `<namespace>/<device>` at depths 2 to 6, in every encoding.
fn namespace_topics(device: &str) -> Vec<String> {
    let mut topics = Vec::new();
    for encoding in fb_bridge::codec::Encoding::ALL {
        for rest in [
            "",
            "/CONV",
            "/CONV/SPEED",
            "/CONV/SPEED/x",
            "/CONV/SPEED/x/ß€",
        ] {
            topics.push(format!("{}/{device}{rest}", encoding.namespace()));
        }
    }
    topics
}

fn refused_not_authorized(admission: &Admission) -> bool {
    matches!(
        admission,
        Admission::Refused {
            stage: Stage::Typed,
            refusal: Refusal::NotAuthorized
        }
    )
}

#[test]
fn another_devices_namespace_is_refused_at_every_depth_in_every_mode_and_door() {
    for undeclared in [Undeclared::Reject, Undeclared::Pass] {
        for anonymous_devices in [false, true] {
            let line = line_in_mode(undeclared, anonymous_devices);
            // Whoever publishes: another device (declared or not), a client claiming
            // plc-2's id with another identity, or plc-2's id without a username on a
            // line with passwords.
            let mut publishers = vec![
                ("plc-1, declared", line.device()),
                ("plc-1", FbSession::new(&line.fb, "plc-1", Some("plc-1"), 2)),
                (
                    "plc-2 as plc-1",
                    FbSession::new(&line.fb, "plc-2", Some("plc-1"), 3),
                ),
            ];
            if !anonymous_devices {
                publishers.push((
                    "plc-2, anonymous",
                    FbSession::new(&line.fb, "plc-2", None, 4),
                ));
            }
            for (who, mut publisher) in publishers {
                for topic in namespace_topics("plc-2")
                    .iter()
                    .chain(&["fb/".to_owned(), "fbdk//x".to_owned()])
                {
                    // The bus door checks a remote device once its record is here.
                    let doors = match publisher.interface() {
                        Some(_) => &DOORS[..],
                        None => &[Door::Client, Door::Will][..],
                    };
                    for &door in doors {
                        let admission = line.admit(door, &mut publisher, topic, "3");
                        assert!(
                            refused_not_authorized(&admission),
                            "{undeclared:?} anonymous={anonymous_devices} {who} {door:?} {topic}: {admission:?}"
                        );
                    }
                }
            }
        }
    }
}

#[test]
fn a_device_keeps_its_own_namespace_in_lenient_mode() {
    for anonymous_devices in [false, true] {
        let line = line_in_mode(Undeclared::Pass, anonymous_devices);
        let mut own = FbSession::new(&line.fb, "plc-2", Some("plc-2"), 1);
        for topic in namespace_topics("plc-2") {
            let admission = line.admit(Door::Client, &mut own, &topic, "3");
            assert!(
                matches!(admission, Admission::Route { routes: None, .. }),
                "{topic}: {admission:?}"
            );
        }
    }
    // Without passwords a client id alone is a device.
    let line = line_in_mode(Undeclared::Pass, true);
    let mut anonymous = FbSession::new(&line.fb, "plc-2", None, 1);
    let admission = line.admit(Door::Client, &mut anonymous, "fb/plc-2/CONV/SPEED/x", "3");
    assert!(
        matches!(admission, Admission::Route { .. }),
        "{admission:?}"
    );
}

#[test]
fn in_strict_mode_the_own_namespace_still_needs_the_typed_shape() {
    let line = line_in_mode(Undeclared::Reject, false);
    let mut device = line.device();
    for topic in ["fb/plc-1", "fb/plc-1/CONV", "fbdk/plc-1/CONV/SPEED/x"] {
        let admission = line.admit(Door::Client, &mut device, topic, "3");
        assert!(
            matches!(
                admission,
                Admission::Refused {
                    stage: Stage::Typed,
                    refusal: Refusal::TopicNameInvalid
                }
            ),
            "{topic}: {admission:?}"
        );
    }
}

/// plc-1 with one DATE_AND_TIME output, on a line whose `fbdk/` dates are in `unit` and
/// that re-encodes into every namespace.
fn dated_line(unit: fb_bridge::codec::fbdk::TimeUnit) -> (Line, FbSession) {
    typed_line(
        unit,
        FORTE_RECEIVE_BUFFER,
        br#"{"fbs":{"CONV":{"data_out":{"AT":"DT"}}}}"#,
    )
}

/// A line re-encoding into every namespace with these fbdk settings, and its device
/// `plc-1` with `declaration`.
fn typed_line(
    unit: fb_bridge::codec::fbdk::TimeUnit,
    fbdk_max_payload: usize,
    declaration: &[u8],
) -> (Line, FbSession) {
    let mut line = line(None);
    let (publisher, _) = BrokerPublisher::detached();
    line.fb = Arc::new(
        FbTopics::new(
            Arc::clone(&line.fb.registry),
            Undeclared::Reject,
            false,
            unit,
            publisher,
            Arc::clone(&line.metrics),
        )
        .with_fbdk_max_payload(fbdk_max_payload),
    );
    line.policy = PublishPolicy::new(
        Access::AllowAll,
        Arc::clone(&line.fb),
        Arc::clone(&line.metrics),
    );
    // Every namespace read (a `#` subscriber does not read the copies: issue 35).
    for filter in ["fb/#", "dinasore/#", "fbdk/#"] {
        line.fb.subscribed(filter);
    }
    let mut device = FbSession::new(&line.fb, "plc-1", Some("plc-1"), 1);
    let interface = Declaration::from_json(declaration)
        .unwrap()
        .validate()
        .unwrap();
    device.set_interface(line.fb.registry.declare("plc-1", 1, interface, "test").ok());
    (line, device)
}

fn routes(admission: Admission) -> Vec<(String, Vec<u8>)> {
    match admission {
        Admission::Route {
            routes: Some(routes),
            ..
        } => routes.into_iter().map(|(t, p)| (t, p.to_vec())).collect(),
        other => panic!("{other:?}"),
    }
}

/// `[fb] fbdk_time_unit`: FORTE 3.x's nanoseconds by default, FORTE 2.x's milliseconds
/// when configured; a date the unit cannot carry reaches every other namespace, and the
/// publisher is told why `fbdk/` did not get it.
#[test]
fn fbdk_dates_are_in_the_configured_unit_and_one_it_cannot_carry_is_not_sent_there() {
    use fb_bridge::codec::fbdk::TimeUnit;
    let dt = |raw: u64| {
        let mut bytes = vec![0x4F];
        bytes.extend(raw.to_be_bytes());
        bytes
    };
    // DT#2026-11-22-12:30:15.250
    let ms: u64 = 1_795_350_615_250;
    for (unit, wire) in [
        (TimeUnit::Nanoseconds, ms * 1_000_000),
        (TimeUnit::Milliseconds, ms),
    ] {
        let (line, mut device) = dated_line(unit);
        let got = routes(line.admit(
            Door::Client,
            &mut device,
            "fb/plc-1/CONV/AT",
            r#""DT#2026-11-22-12:30:15.250""#,
        ));
        assert_eq!(
            got[2],
            ("fbdk/plc-1/CONV/AT".to_owned(), dt(wire)),
            "{unit:?}"
        );
        // 2600 does not fit 64-bit nanoseconds (they end in 2554), but does milliseconds.
        let later = r#""DT#2600-01-01-00:00:00""#;
        let got = routes(line.admit(Door::Client, &mut device, "fb/plc-1/CONV/AT", later));
        let topics: Vec<&str> = got.iter().map(|(t, _)| t.as_str()).collect();
        let not_reencoded = line
            .metrics
            .typed_not_reencoded
            .with_label_values(&["fbdk"])
            .get();
        let diags: Vec<String> = device
            .take_outbox()
            .into_iter()
            .map(|m| String::from_utf8_lossy(&m.payload).into_owned())
            .collect();
        match unit {
            TimeUnit::Nanoseconds => {
                assert_eq!(topics, ["fb/plc-1/CONV/AT", "dinasore/plc-1/CONV/AT"]);
                assert_eq!(not_reencoded, 1);
                let diag: serde_json::Value = serde_json::from_str(&diags[0]).unwrap();
                assert_eq!(diag["kind"], "not_reencoded", "{diag}");
                assert_eq!(diag["topic"], "fbdk/plc-1/CONV/AT", "{diag}");
                let detail = diag["detail"].as_str().unwrap();
                assert!(
                    detail.starts_with("CONV.AT: value: DT#2600-01-01-00:00:00 (")
                        && detail.contains("2554"),
                    "{detail}"
                );
            }
            TimeUnit::Milliseconds => {
                assert_eq!(got.len(), 3, "{topics:?}");
                assert_eq!(not_reencoded, 0);
                assert!(diags.is_empty(), "{diags:?}");
            }
        }
    }
}

/// `[fb] fbdk_max_payload`: an `fbdk` payload longer than a FORTE subscriber's 255-byte
/// receive buffer is not delivered on `fbdk/` (it would corrupt that subscription's
/// stream); `fb/` and `dinasore/` still get it, the publisher is told why, it is counted.
#[test]
fn an_fbdk_payload_longer_than_forte_can_take_in_is_not_sent_there() {
    for (limit, long_reaches_fbdk) in [(FORTE_RECEIVE_BUFFER, false), (0, true)] {
        let (line, mut device) = typed_line(
            Default::default(),
            limit,
            br#"{"fbs":{"CONV":{"data_out":{"ID":"STRING"}}}}"#,
        );
        let namespaces = |got: &[(String, Vec<u8>)]| -> Vec<String> {
            got.iter()
                .map(|(t, _)| t.split('/').next().unwrap_or_default().to_owned())
                .collect()
        };
        // 252 characters: 255 bytes in fbdk (tag, 16-bit length, the characters).
        let fits = format!("\"{}\"", "x".repeat(252));
        let got = routes(line.admit(Door::Client, &mut device, "fb/plc-1/CONV/ID", &fits));
        assert_eq!(
            namespaces(&got),
            ["fb", "dinasore", "fbdk"],
            "limit {limit}"
        );
        assert_eq!(got[2].1.len(), 255);
        drop(device.take_outbox());
        let long = format!("\"{}\"", "x".repeat(253));
        let got = routes(line.admit(Door::Client, &mut device, "fb/plc-1/CONV/ID", &long));
        let diags: Vec<String> = device
            .take_outbox()
            .into_iter()
            .map(|m| String::from_utf8_lossy(&m.payload).into_owned())
            .collect();
        let counted = line
            .metrics
            .typed_not_reencoded
            .with_label_values(&["fbdk"])
            .get();
        if long_reaches_fbdk {
            assert_eq!(namespaces(&got), ["fb", "dinasore", "fbdk"]);
            assert_eq!((counted, diags.len()), (0, 0), "{diags:?}");
        } else {
            assert_eq!(namespaces(&got), ["fb", "dinasore"]);
            assert_eq!(counted, 1);
            assert!(
                diags.len() == 1
                    && diags[0].contains("not_reencoded")
                    && diags[0].contains("256 bytes in fbdk"),
                "{diags:?}"
            );
        }
    }
}

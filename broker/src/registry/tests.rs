use std::time::Duration;

use fb_bridge::topic;

use super::journal::{journal_path, Entry, File};
use super::*;
use crate::silence::Periods;

fn interface() -> Interface {
    Interface {
        fbs: Default::default(),
    }
}

/// Journal lines the snapshot already holds (a crash between the snapshot's rename
/// and the journal's truncation) are skipped: an older line never overrides it.
#[test]
fn journal_lines_older_than_the_snapshot_are_skipped() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("registry.json");
    let at = |session: u64| Record {
        session,
        ..remote("d1", "a", Status::Offline)
    };
    let snapshot = File {
        version: 1,
        seq: 5,
        devices: vec![at(50)],
        periods: BTreeMap::new(),
        registrants: BTreeMap::from([("d1".to_owned(), "127.0.0.1".to_owned())]),
    };
    std::fs::write(&path, serde_json::to_vec(&snapshot).unwrap()).unwrap();
    let mut journal = Vec::new();
    for (seq, session) in [(4, 40), (6, 60)] {
        let entry = Entry::Device {
            seq,
            record: at(session),
            periods: Periods::new(),
            registrant: Some(format!("user-{seq}")),
        };
        serde_json::to_writer(&mut journal, &entry).unwrap();
        journal.push(b'\n');
    }
    let removed = Entry::Removed {
        seq: 3,
        id: "d1".into(),
    };
    serde_json::to_writer(&mut journal, &removed).unwrap();
    journal.push(b'\n');
    std::fs::write(journal_path(&path), &journal).unwrap();
    let (records, _, registrants, state) = load(&path).unwrap();
    assert_eq!(records.len(), 1);
    assert_eq!(records[0].session, 60);
    // The registrant too comes from the newer line, not the older one or the snapshot.
    assert_eq!(registrants["d1"], "user-6");
    assert_eq!(state.seq, 6);
    assert_eq!(state.bytes, journal.len() as u64);
}

fn remote(id: &str, line: &str, status: Status) -> Record {
    Record {
        id: id.into(),
        line: line.into(),
        status,
        session: 1,
        since: now(),
        last_will_reason: None,
        silent: false,
        silent_since: None,
        interface: Arc::new(interface()),
    }
}

fn registry(
    metrics: &Arc<Metrics>,
) -> (Arc<Registry>, tokio::sync::mpsc::UnboundedReceiver<Message>) {
    let (publisher, published) = BrokerPublisher::detached();
    let bound = Bound {
        factor: 3.0,
        floor: Duration::from_secs(1),
    };
    let health = crate::health::Health::new();
    let tasks = crate::supervisor::Tasks::new(&health);
    let registry = Registry::open(
        "a",
        None,
        publisher,
        Arc::clone(metrics),
        bound,
        Limits::NONE,
        &tasks,
    );
    (registry.unwrap(), published)
}

/// The observed periods survive a restart: a device that reconnects and never
/// publishes (a FORTE whose publishers died) is still judged.
#[tokio::test]
async fn periods_are_persisted_and_given_back_on_connect() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("registry.json");
    let open = || {
        let (publisher, _) = BrokerPublisher::detached();
        let health = crate::health::Health::new();
        let bound = crate::silence::Bound::DEFAULT;
        let tasks = crate::supervisor::Tasks::new(&health);
        let metrics = Arc::new(Metrics::new());
        Registry::open(
            "a",
            Some(&path),
            publisher,
            metrics,
            bound,
            Limits::NONE,
            &tasks,
        )
        .unwrap()
    };
    let speed: Interface = serde_json::from_value(serde_json::json!({"fbs": {"CONV": {
        "data_out": {"SPEED": "REAL"},
    }}}))
    .unwrap();
    let first = open();
    first.declare("d1", 1, speed, "test").unwrap();
    let activity = first.activity("d1").unwrap();
    let t0 = Instant::now();
    for i in 0..10 {
        let at = t0 + Duration::from_millis(200) * i;
        activity.published("CONV", "SPEED", at, first.silence_bound());
    }
    first.flush();
    drop(first);

    let second = open();
    assert!(second.activity("d1").is_none());
    assert!(second.connected("d1", 2).is_some());
    let periods = second.activity("d1").unwrap().periods();
    assert!(
        (periods["CONV"]["SPEED"] - 0.2).abs() < 0.001,
        "{periods:?}"
    );
}

/// A local device whose periodic output stops turns silent once, is counted, and
/// speaks again once; going offline ends the silence.
#[test]
fn silence_is_announced_once_each_way() {
    let metrics = Arc::new(Metrics::new());
    let (registry, mut published) = registry(&metrics);
    let speed: Interface = serde_json::from_value(serde_json::json!({"fbs": {"CONV": {
        "data_out": {"SPEED": "REAL"},
    }}}))
    .unwrap();
    registry.declare("d1", 1, speed, "test").unwrap();
    registry.declare("quiet", 2, interface(), "test").unwrap();
    let activity = registry.activity("d1").unwrap();
    let bound = *registry.silence_bound();
    let t0 = Instant::now();
    let mut last = t0;
    for i in 0..20 {
        last = t0 + Duration::from_millis(200) * i;
        activity.published("CONV", "SPEED", last, &bound);
    }
    let mut records = || {
        let mut out = Vec::new();
        while let Ok(m) = published.try_recv() {
            if m.topic == topic::device_record("d1") {
                out.push(serde_json::from_slice::<Record>(&m.payload).unwrap());
            }
        }
        out
    };
    records();
    let silent = || metrics.registry_silent_devices.get();

    registry.judge_silence(last + Duration::from_millis(1000));
    assert!(records().is_empty(), "within the bound");
    registry.judge_silence(last + Duration::from_millis(1001));
    let turned = records();
    assert_eq!(turned.len(), 1);
    assert!(turned[0].silent && turned[0].silent_since.is_some());
    assert_eq!(turned[0].status, Status::Online);
    assert_eq!(silent(), 1);
    registry.judge_silence(last + Duration::from_millis(5000));
    assert!(records().is_empty(), "announced once");
    assert!(!registry.get("quiet").unwrap().silent, "no periodic port");

    let back = last + Duration::from_millis(6000);
    activity.published("CONV", "SPEED", back, &bound);
    registry.judge_silence(back);
    let turned = records();
    assert_eq!(turned.len(), 1);
    assert!(!turned[0].silent && turned[0].silent_since.is_none());
    assert_eq!(silent(), 0);

    registry.judge_silence(back + Duration::from_millis(1001));
    assert_eq!(silent(), 1);
    assert!(registry.disconnected("d1", 1, "keep-alive"));
    let record = registry.get("d1").unwrap();
    assert!(!record.silent && record.status == Status::Offline);
    assert_eq!(silent(), 0);
}

/// The counts announced after every change (gauges and the line's online count) are
/// the counts of the records, whatever the change: they are kept with each change
/// instead of recounted from every record (which made births quadratic).
#[test]
fn announced_counts_follow_every_change() {
    let (publisher, mut published) = BrokerPublisher::detached();
    let metrics = Arc::new(Metrics::new());
    let health = crate::health::Health::new();
    let registry = Registry::open(
        "a",
        None,
        publisher,
        Arc::clone(&metrics),
        crate::silence::Bound::DEFAULT,
        Limits::NONE,
        &crate::supervisor::Tasks::new(&health),
    )
    .unwrap();
    let mut line_online = None;
    let mut check = |step: &str| {
        let records = registry.list();
        let count = |status| records.iter().filter(|r| r.status == status).count() as i64;
        for status in [Status::Online, Status::Offline, Status::Unreachable] {
            let gauge = metrics
                .registry_devices
                .with_label_values(&[status.label()])
                .get();
            assert_eq!(gauge, count(status), "{step}: {} devices", status.label());
        }
        while let Ok(m) = published.try_recv() {
            if m.topic == topic::line_online("a") {
                line_online = Some(String::from_utf8(m.payload.to_vec()).unwrap());
            }
        }
        let here = records
            .iter()
            .filter(|r| r.line == "a" && r.status == Status::Online)
            .count();
        assert_eq!(line_online, Some(here.to_string()), "{step}: line online");
    };

    for (i, id) in ["d1", "d2", "d3"].into_iter().enumerate() {
        registry
            .declare(id, i as u64 + 1, interface(), "test")
            .unwrap();
    }
    check("declared");
    assert!(registry.disconnected("d1", 1, "clean disconnect"));
    check("d1 offline");
    assert!(registry.connected("d1", 4).is_some());
    check("d1 back");
    assert!(!registry.disconnected("d1", 1, "stale"));
    check("stale end ignored");
    registry.session_started("d2", 5);
    registry.declare("d2", 5, interface(), "test").unwrap();
    check("d2 declared again");
    assert_eq!(
        registry.remote_record("b", remote("r1", "b", Status::Online)),
        Ok(())
    );
    assert_eq!(
        registry.remote_record("b", remote("r2", "b", Status::Offline)),
        Ok(())
    );
    assert_eq!(
        registry.remote_record("b", remote("d3", "b", Status::Offline)),
        Err(RecordRefused::LocalDevice)
    );
    // A line speaks only for its own devices, and does not take one online elsewhere.
    assert_eq!(
        registry.remote_record("c", remote("r9", "b", Status::Online)),
        Err(RecordRefused::ForgedLine)
    );
    assert_eq!(
        registry.remote_record("c", remote("r1", "c", Status::Online)),
        Err(RecordRefused::HeldByAnotherLine)
    );
    check("remote records");
    registry.line_unreachable("b");
    check("line b unreachable");
    assert_eq!(
        registry.remote_record("b", remote("r1", "b", Status::Offline)),
        Ok(())
    );
    check("r1 replaced");
    // Offline on its line, r1 may move to line c.
    assert_eq!(
        registry.remote_record("c", remote("r1", "c", Status::Online)),
        Ok(())
    );
    assert_eq!(
        registry.remote_record("b", remote("r1", "b", Status::Offline)),
        Err(RecordRefused::HeldByAnotherLine)
    );
    assert_eq!(
        registry.remote_record("c", remote("r1", "c", Status::Offline)),
        Ok(())
    );
    assert_eq!(
        registry.remote_record("b", remote("r1", "b", Status::Offline)),
        Ok(())
    );
    check("r1 moved and back");
    // A query answered before a live record came does not undo it.
    let mark = registry.live_mark();
    let mut newer = remote("r2", "b", Status::Online);
    newer.session = 2;
    assert_eq!(registry.remote_record("b", newer.clone()), Ok(()));
    assert_eq!(
        registry.queried_record("b", remote("r2", "b", Status::Offline), mark),
        Ok(())
    );
    assert_eq!(registry.get("r2"), Some(newer));
    let mark = registry.live_mark();
    assert_eq!(
        registry.queried_record("b", remote("r2", "b", Status::Offline), mark),
        Ok(())
    );
    assert_eq!(registry.get("r2").unwrap().status, Status::Offline);
    check("queried records");
    registry.line_unreachable("b");
    check("line b unreachable");
    assert!(registry.disconnected("d3", 3, "keep-alive"));
    check("d3 offline");
}

fn limited(limits: Limits, file: Option<&Path>) -> (Arc<Registry>, Arc<Metrics>) {
    let (publisher, _) = BrokerPublisher::detached();
    let metrics = Arc::new(Metrics::new());
    let health = crate::health::Health::new();
    let registry = Registry::open(
        "a",
        file,
        publisher,
        Arc::clone(&metrics),
        crate::silence::Bound::DEFAULT,
        limits,
        &crate::supervisor::Tasks::new(&health),
    )
    .unwrap();
    (registry, metrics)
}

/// A new device beyond either limit is refused and counted; a known device declares
/// again whoever it is; other lines' devices do not count; a forgotten device frees
/// its place, and who registered what survives a restart.
#[tokio::test]
async fn new_devices_are_admitted_within_the_limits() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("registry.json");
    let limits = Limits {
        max_devices: 3,
        max_per_identity: 2,
        ..Limits::default()
    };
    let (registry, metrics) = limited(limits, Some(&path));
    let refusals = |limit: &str| metrics.limit_refusals.with_label_values(&[limit]).get();
    assert!(registry.declare("d1", 1, interface(), "a").is_ok());
    assert!(registry.declare("d2", 2, interface(), "a").is_ok());
    assert_eq!(
        registry.declare("d3", 3, interface(), "a"),
        Err(Full::PerIdentity(2))
    );
    assert_eq!(
        registry.remote_record("b", remote("r1", "b", Status::Online)),
        Ok(())
    );
    assert!(registry.declare("d3", 3, interface(), "b").is_ok());
    assert_eq!(
        registry.declare("d4", 4, interface(), "c"),
        Err(Full::Devices(3))
    );
    assert!(registry.get("d4").is_none());
    assert!(registry.declare("d1", 5, interface(), "c").is_ok(), "known");
    assert_eq!(
        (refusals("devices"), refusals("devices_per_identity")),
        (1, 1)
    );

    assert!(registry.disconnected("d1", 5, "clean disconnect"));
    registry.forget("d1", ForgetReason::Admin).unwrap();
    assert!(
        registry.declare("d4", 6, interface(), "a").is_ok(),
        "d1's place"
    );
    assert_eq!(
        registry.declare("d5", 7, interface(), "c"),
        Err(Full::Devices(3))
    );
    registry.flush();
    drop(registry);

    let (reopened, _) = limited(
        Limits {
            max_devices: 10,
            ..limits
        },
        Some(&path),
    );
    assert_eq!(
        reopened.declare("d6", 8, interface(), "a"),
        Err(Full::PerIdentity(2)),
        "a registered d2 and d4 before the restart"
    );
    assert!(reopened.declare("d6", 8, interface(), "b").is_ok());
}

/// Issue 33: other lines' devices are taken within a share per line and a whole; a line
/// over its share gets its new devices refused (counted), keeps the ones it has and may
/// change them, and another line still gets its place.
#[test]
fn other_lines_devices_are_taken_within_a_share_per_line() {
    let limits = Limits {
        max_remote_per_line: 2,
        max_remote: 3,
        ..Limits::default()
    };
    let (registry, metrics) = limited(limits, None);
    let refusals = |limit: &str| metrics.limit_refusals.with_label_values(&[limit]).get();
    assert_eq!(
        registry.remote_record("b", remote("b1", "b", Status::Online)),
        Ok(())
    );
    assert_eq!(
        registry.remote_record("b", remote("b2", "b", Status::Online)),
        Ok(())
    );
    assert_eq!(
        registry.remote_record("b", remote("b3", "b", Status::Online)),
        Err(RecordRefused::LineShare)
    );
    assert!(registry.get("b3").is_none());
    // A change of one it holds is taken.
    assert_eq!(
        registry.remote_record("b", remote("b2", "b", Status::Offline)),
        Ok(())
    );
    assert_eq!(registry.get("b2").unwrap().status, Status::Offline);
    // Another line has its place, up to the whole.
    assert_eq!(
        registry.remote_record("c", remote("c1", "c", Status::Online)),
        Ok(())
    );
    assert_eq!(
        registry.remote_record("c", remote("c2", "c", Status::Online)),
        Err(RecordRefused::RemoteFull)
    );
    assert_eq!(
        (
            refusals("remote_devices_per_line"),
            refusals("remote_devices")
        ),
        (1, 1)
    );
    // Local devices are not other lines' share.
    assert!(registry.declare("d1", 1, interface(), "a").is_ok());
}

/// Forgetting: refused for an unknown, online or remote device; an offline one goes
/// with its retained record and port values (empty retained messages), its counts
/// and its metric series.
#[test]
fn forgetting_clears_the_record_its_retained_values_and_series() {
    let metrics = Arc::new(Metrics::new());
    let (registry, mut published) = registry(&metrics);
    let speed: Interface = serde_json::from_value(serde_json::json!({"fbs": {"CONV": {
        "data_out": {"SPEED": "REAL"}, "data_in": {"SET": "REAL"},
    }}}))
    .unwrap();
    registry.declare("d1", 1, speed, "a").unwrap();
    assert_eq!(
        registry.remote_record("b", remote("r1", "b", Status::Offline)),
        Ok(())
    );
    assert_eq!(
        registry.forget("nope", ForgetReason::Admin),
        Err(ForgetError::Unknown("nope".into()))
    );
    assert_eq!(
        registry.forget("d1", ForgetReason::Admin),
        Err(ForgetError::Online("d1".into()))
    );
    assert_eq!(
        registry.forget("r1", ForgetReason::Admin),
        Err(ForgetError::OtherLine("r1".into(), "b".into()))
    );
    metrics.typed_refused("d1", "CONV.SPEED", "payload_format_invalid");
    metrics.typed_refused("d1", "undeclared", "topic_name_invalid");
    metrics.typed_refused("d2", "CONV.SPEED", "payload_format_invalid");
    assert!(registry.disconnected("d1", 1, "clean disconnect"));
    while published.try_recv().is_ok() {}

    registry.forget("d1", ForgetReason::Admin).unwrap();
    assert!(registry.get("d1").is_none());
    let mut cleared = Vec::new();
    while let Ok(m) = published.try_recv() {
        if m.payload.is_empty() {
            assert!(m.retain);
            cleared.push(String::from_utf8(m.topic.to_vec()).unwrap());
        }
    }
    cleared.sort();
    assert_eq!(
        cleared,
        [
            "dinasore/d1/CONV/SPEED",
            "fb/d1/CONV/SPEED",
            "fbbus/devices/d1",
            "fbdk/d1/CONV/SPEED"
        ]
    );
    let offline = metrics
        .registry_devices
        .with_label_values(&["offline"])
        .get();
    assert_eq!(offline, 1, "r1 only");
    let forgotten = metrics
        .registry_forgotten
        .with_label_values(&["admin"])
        .get();
    assert_eq!(forgotten, 1);
    let text = metrics.render();
    assert!(!text.contains("device=\"d1\""), "{text}");
    assert!(text.contains("device=\"d2\""), "{text}");
    assert_eq!(
        registry.forget("d1", ForgetReason::Admin),
        Err(ForgetError::Unknown("d1".into()))
    );
}

/// Local devices offline for the configured time are forgotten; online ones, those
/// offline for less, and other lines' devices are not.
#[test]
fn offline_devices_expire() {
    let metrics = Arc::new(Metrics::new());
    let (registry, _published) = registry(&metrics);
    for (i, id) in ["gone", "online", "back"].into_iter().enumerate() {
        registry
            .declare(id, i as u64 + 1, interface(), "a")
            .unwrap();
    }
    assert_eq!(
        registry.remote_record("b", remote("r1", "b", Status::Offline)),
        Ok(())
    );
    assert!(registry.disconnected("gone", 1, "keep-alive"));
    assert!(registry.disconnected("back", 3, "keep-alive"));
    assert!(registry.connected("back", 4).is_some());
    let after = Duration::from_secs(5);
    registry.expire(SystemTime::now() + Duration::from_secs(1), after);
    assert!(registry.get("gone").is_some(), "offline for less");
    registry.expire(SystemTime::now() + Duration::from_secs(6), after);
    assert!(registry.get("gone").is_none());
    for id in ["online", "back", "r1"] {
        assert!(registry.get(id).is_some(), "{id}");
    }
    let expired = metrics
        .registry_forgotten
        .with_label_values(&["expired"])
        .get();
    assert_eq!(expired, 1);
}

use std::sync::Arc;

use bytes::Bytes;
use fb_bridge::sparkplug::proto;
use prost::Message as _;

use super::*;
use crate::registry::{Record, Status};

fn interface() -> Arc<Interface> {
    let declaration = fb_bridge::Declaration::from_json(
        br#"{"fbs": {"CONV": {
            "events_out": {"MOVED": {"with": ["POSITION", "SENSOR_IN"]}},
            "events_in": {"START": {"with": ["SPEED"]}},
            "data_out": {"POSITION": "INT", "SENSOR_IN": "BOOL"},
            "data_in": {"SPEED": "REAL"}}}}"#,
    )
    .unwrap();
    Arc::new(declaration.validate().unwrap())
}

fn record(id: &str, line: &str, status: Status) -> Record {
    Record {
        id: id.to_owned(),
        line: line.to_owned(),
        status,
        session: 1,
        since: String::new(),
        last_will_reason: None,
        silent: false,
        silent_since: None,
        interface: interface(),
    }
}

fn nodes(dir: &std::path::Path) -> Nodes {
    Nodes::new(
        "g",
        "line-1",
        true,
        BdSeqs::open(Some(dir)),
        Arc::new(AliasBook::default()),
    )
}

/// (topic, seq, metrics by name or alias) of each message.
fn decode(out: &Out) -> Vec<(String, Option<u64>, proto::Payload)> {
    out.iter()
        .map(|(t, p): &(String, Bytes)| {
            let payload = proto::Payload::decode(p.as_ref()).unwrap();
            (t.clone(), payload.seq, payload)
        })
        .collect()
}

fn bdseq(payload: &proto::Payload) -> Option<u64> {
    payload
        .metrics
        .iter()
        .find(|m| m.name.as_deref() == Some(BDSEQ_METRIC))
        .and_then(|m| match m.value {
            Some(proto::payload::metric::Value::LongValue(v)) => Some(v),
            _ => None,
        })
}

#[test]
fn births_data_and_deaths_follow_the_registry_with_sequence_numbers() {
    let dir = tempfile::tempdir().unwrap();
    let mut n = nodes(dir.path());
    let out = decode(&n.start(vec![
        record("conv", "line-1", Status::Online),
        record("idle", "line-1", Status::Offline),
    ]));
    // First start: no previous death; NBIRTH seq 0 with bdSeq 0; the online device born.
    assert_eq!(out.len(), 2, "{out:?}");
    assert_eq!(out[0].0, "spBv1.0/g/NBIRTH/line-1");
    assert_eq!((out[0].1, bdseq(&out[0].2)), (Some(0), Some(0)));
    assert_eq!(out[1].0, "spBv1.0/g/DBIRTH/line-1/conv");
    assert_eq!(out[1].1, Some(1));
    let names: Vec<_> = out[1]
        .2
        .metrics
        .iter()
        .map(|m| m.name.clone().unwrap())
        .collect();
    for name in [
        "CONV/POSITION",
        "CONV/SENSOR_IN",
        "CONV/SPEED",
        "CONV/MOVED",
        "CONV/START",
        SILENT_METRIC,
    ] {
        assert!(names.iter().any(|n| n == name), "{name} in {names:?}");
    }
    // Every birth metric has an alias and a datatype; values unknown yet are null.
    assert!(out[1]
        .2
        .metrics
        .iter()
        .all(|m| m.alias.is_some() && m.datatype.is_some()));
    let position = out[1]
        .2
        .metrics
        .iter()
        .find(|m| m.name.as_deref() == Some("CONV/POSITION"))
        .unwrap();
    assert_eq!(position.is_null, Some(true));
    assert_eq!(position.datatype, Some(2)); // Int16

    // An event with its WITH data: one DDATA, by alias, at the event's ts.
    let data = decode(&n.value(
        "fb/conv/CONV/MOVED",
        br#"{"seq": 7, "ts": 1763800000123456, "data": {"POSITION": -3, "SENSOR_IN": true}}"#,
    ));
    assert_eq!(data.len(), 1);
    assert_eq!(data[0].0, "spBv1.0/g/DDATA/line-1/conv");
    assert_eq!(data[0].1, Some(2));
    assert_eq!(data[0].2.metrics.len(), 3);
    assert!(data[0]
        .2
        .metrics
        .iter()
        .all(|m| m.name.is_none() && m.alias.is_some()));
    assert!(data[0]
        .2
        .metrics
        .iter()
        .all(|m| m.timestamp == Some(1763800000123)));
    // Ill-typed or undeclared: nothing (the typed check refuses those before routing).
    assert!(n.value("fb/conv/CONV/POSITION", b"\"x\"").is_empty());
    assert!(n.value("fb/ghost/CONV/POSITION", b"1").is_empty());

    // The device goes offline: DDEATH; a value then is kept, not sent; back online: DBIRTH
    // with the value.
    let death = decode(&n.record(&record("conv", "line-1", Status::Offline)));
    assert_eq!(
        (death[0].0.as_str(), death[0].1),
        ("spBv1.0/g/DDEATH/line-1/conv", Some(3))
    );
    assert!(n.value("fb/conv/CONV/POSITION", b"5").is_empty());
    let birth = decode(&n.record(&record("conv", "line-1", Status::Online)));
    let position = birth[0]
        .2
        .metrics
        .iter()
        .find(|m| m.name.as_deref() == Some("CONV/POSITION"))
        .unwrap();
    assert_eq!(
        position.value,
        Some(proto::payload::metric::Value::IntValue(5))
    );

    // A rebirth: NBIRTH seq 0, the same bdSeq, then the device again.
    let again = decode(&n.rebirth(None));
    assert_eq!((again[0].1, bdseq(&again[0].2)), (Some(0), Some(0)));
    assert_eq!(again[1].0, "spBv1.0/g/DBIRTH/line-1/conv");

    // Shutdown: NDEATH with the bdSeq and no seq.
    let death = decode(&n.shutdown());
    assert_eq!(death[0].0, "spBv1.0/g/NDEATH/line-1");
    assert_eq!((death[0].1, bdseq(&death[0].2)), (None, Some(0)));

    // The next start: the old session's death first, then the next bdSeq.
    let mut next = nodes(dir.path());
    let out = decode(&next.start(vec![]));
    assert_eq!(out[0].0, "spBv1.0/g/NDEATH/line-1");
    assert_eq!(bdseq(&out[0].2), Some(0));
    assert_eq!(
        (out[1].0.as_str(), bdseq(&out[1].2)),
        ("spBv1.0/g/NBIRTH/line-1", Some(1))
    );
}

#[test]
fn seq_wraps_after_255() {
    let dir = tempfile::tempdir().unwrap();
    let mut n = nodes(dir.path());
    n.start(vec![record("conv", "line-1", Status::Online)]);
    let mut last = 1;
    for i in 0..300u64 {
        let out = decode(&n.value("fb/conv/CONV/POSITION", i.to_string().as_bytes()));
        let seq = out[0].1.unwrap();
        assert_eq!(seq, (last + 1) % 256);
        last = seq;
    }
}

#[test]
fn another_line_is_a_node_of_its_own_that_dies_with_the_link() {
    let dir = tempfile::tempdir().unwrap();
    let mut n = nodes(dir.path());
    n.start(vec![]);
    let out = decode(&n.record(&record("press", "line-2", Status::Online)));
    assert_eq!(out[0].0, "spBv1.0/g/NBIRTH/line-2");
    assert_eq!(out[1].0, "spBv1.0/g/DBIRTH/line-2/press");
    let out = decode(&n.record(&record("press", "line-2", Status::Unreachable)));
    assert_eq!(out.len(), 1);
    assert_eq!(
        (out[0].0.as_str(), bdseq(&out[0].2)),
        ("spBv1.0/g/NDEATH/line-2", Some(0))
    );
    // Reachable again: a new session of that node.
    let out = decode(&n.record(&record("press", "line-2", Status::Online)));
    assert_eq!(
        (out[0].0.as_str(), bdseq(&out[0].2)),
        ("spBv1.0/g/NBIRTH/line-2", Some(1))
    );
    // Forgotten: DDEATH.
    let out = decode(&n.removed("press"));
    assert_eq!(out[0].0, "spBv1.0/g/DDEATH/line-2/press");
}

#[test]
fn aliases_of_the_line_s_devices_are_in_the_book() {
    let dir = tempfile::tempdir().unwrap();
    let book = Arc::new(AliasBook::default());
    let mut n = Nodes::new(
        "g",
        "line-1",
        false,
        BdSeqs::open(Some(dir.path())),
        Arc::clone(&book),
    );
    let out = decode(&n.start(vec![record("conv", "line-1", Status::Online)]));
    let speed = out[1]
        .2
        .metrics
        .iter()
        .find(|m| m.name.as_deref() == Some("CONV/SPEED"))
        .unwrap();
    assert_eq!(
        book.resolve(speed.alias.unwrap()),
        Some(("conv".to_owned(), "CONV/SPEED".to_owned()))
    );
    n.record(&record("conv", "line-1", Status::Offline));
    assert_eq!(book.resolve(speed.alias.unwrap()), None);
    // remote_lines = false: another line's device is not shown.
    assert!(n
        .record(&record("press", "line-2", Status::Online))
        .is_empty());
}

#[test]
fn a_birth_stays_within_a_packet_whatever_the_values() {
    let dir = tempfile::tempdir().unwrap();
    let declaration = fb_bridge::Declaration::from_json(
        br#"{"fbs": {"F": {"data_out": {"A": "STRING", "B": "STRING", "C": "STRING"}}}}"#,
    )
    .unwrap();
    let mut device = record("big", "line-1", Status::Online);
    device.interface = Arc::new(declaration.validate().unwrap());
    let mut n = Nodes::new(
        "g",
        "line-1",
        false,
        BdSeqs::open(Some(dir.path())),
        Arc::new(AliasBook::default()),
    )
    .with_max_payload(5000);
    n.start(vec![device.clone()]);
    let long = format!("\"{}\"", "x".repeat(1500));
    for port in ["A", "B", "C"] {
        assert_eq!(
            n.value(&format!("fb/big/F/{port}"), long.as_bytes()).len(),
            1
        );
    }
    let birth = n.rebirth(None);
    let dbirth = &birth[1].1;
    assert!(dbirth.len() <= 5000, "{} bytes", dbirth.len());
    let payload = proto::Payload::decode(dbirth.as_ref()).unwrap();
    let nulls = payload
        .metrics
        .iter()
        .filter(|m| m.is_null == Some(true))
        .count();
    assert_eq!(nulls, 1, "the value that did not fit is null: {payload:?}");
}

#[test]
fn a_batch_of_a_device_s_values_is_one_ddata() {
    let dir = tempfile::tempdir().unwrap();
    let mut n = nodes(dir.path());
    n.start(vec![record("conv", "line-1", Status::Online)]);
    let payloads: Vec<String> = (0..50).map(|i| i.to_string()).collect();
    let out = decode(
        &n.values(
            payloads
                .iter()
                .map(|p| ("fb/conv/CONV/POSITION", p.as_bytes())),
        ),
    );
    assert_eq!(out.len(), 1);
    assert_eq!(out[0].2.metrics.len(), 50, "every value, in order");
    assert_eq!(
        out[0].2.metrics[49].value,
        Some(proto::payload::metric::Value::IntValue(49))
    );
}

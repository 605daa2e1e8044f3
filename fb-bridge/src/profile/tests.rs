use super::*;
use serde_json::json;

fn conveyor(extra: serde_json::Value) -> ProfileFile {
    let mut file = json!({
        "device": "conv2",
        "runtime": "forte",
        "speaks": {"encoding": "fbdk", "max_payload": 255},
        "interface": {"fbs": {"CONV": {
            "events_out": {"CNF": {"with": ["POSITION"]}},
            "events_in": {"REQ": {"with": ["SPEED"]}},
            "data_out": {"POSITION": "INT", "CONNECT": "BOOL"},
            "data_in": {"SPEED": "REAL"}
        }}},
        "topics": [
            {"topic": "line1/conv2/position", "port": "CONV.POSITION"},
            {"topic": "line1/conv2/speed", "port": "CONV.SPEED", "from": "conv1/CONV/SPEED_OUT", "encoding": "dinasore"}
        ],
        "will": {"CONV.CONNECT": false},
        "periods": {"CONV.POSITION": 250}
    });
    if let (Some(file), Some(extra)) = (file.as_object_mut(), extra.as_object()) {
        for (k, v) in extra {
            file.insert(k.clone(), v.clone());
        }
    }
    serde_json::from_value(file).expect("a profile file")
}

#[test]
fn a_forte_profile_resolves() {
    let profile = conveyor(json!({})).validate().expect("valid");
    assert_eq!(profile.identity, Identity::ClientId("conv2".into()));
    assert_eq!(
        profile.outputs,
        vec![OwnTopic {
            topic: "line1/conv2/position".into(),
            fb: "CONV".into(),
            port: "POSITION".into(),
            encoding: Encoding::Fbdk,
        }]
    );
    assert_eq!(profile.inputs.len(), 1);
    assert_eq!(profile.inputs[0].own.encoding, Encoding::Dinasore);
    assert_eq!(
        profile.inputs[0].from,
        Source {
            device: "conv1".into(),
            fb: "CONV".into(),
            port: "SPEED_OUT".into()
        }
    );
    assert_eq!(
        profile.will,
        vec![("CONV".into(), "CONNECT".into(), "false".into())]
    );
    assert_eq!(profile.max_payload, 255);
    assert_eq!(
        profile.periods,
        vec![(
            "CONV".into(),
            "POSITION".into(),
            std::time::Duration::from_millis(250)
        )]
    );
}

#[test]
fn every_mistake_is_reported_with_where_it_is() {
    let bad = conveyor(json!({
        "device": "a/b",
        "identity": {"client_id": "x", "username": "y"},
        "speaks": {"encoding": "xml", "qos": 3},
        "topics": [
            {"topic": "fb/conv2/CONV/POSITION", "port": "CONV.POSITION"},
            {"topic": "line1/+", "port": "CONV.POSITION"},
            {"topic": "line1/a", "port": "CONV.NOPE"},
            {"topic": "line1/b", "port": "CONV.SPEED"},
            {"topic": "line1/c", "port": "CONV.POSITION", "from": "conv1/CONV/X"},
            {"topic": "line1/d", "port": "CONV.POSITION"},
            {"topic": "line1/d", "port": "CONV.POSITION"}
        ],
        "will": {"CONV.CONNECT": 7, "CONV.SPEED": 1.0, "CNF": 1},
        "periods": {"CONV.SPEED": 100, "CONV.POSITION": 0}
    }));
    let errors = bad.validate().expect_err("invalid");
    let at: Vec<&str> = errors.iter().map(|e| e.at.as_str()).collect();
    assert_eq!(
        at,
        [
            "device",
            "identity",
            "speaks.encoding",
            "speaks.qos",
            "topics[0].topic",
            "topics[1].topic",
            "topics[2].port",
            "topics[3].from",
            "topics[4].from",
            "topics[6].topic",
            "will.CNF",
            "will.CONV.CONNECT",
            "will.CONV.SPEED",
            "periods.CONV.POSITION",
            "periods.CONV.SPEED",
        ],
        "{errors:#?}"
    );
}

#[test]
fn an_interface_mistake_is_named() {
    let bad = conveyor(json!({"interface": {"fbs": {"CONV": {"data_out": {"X": "INTEGER"}}}}}));
    let errors = bad.validate().expect_err("invalid");
    assert_eq!(errors.len(), 1);
    assert!(errors[0].error.contains("INTEGER"), "{errors:?}");
}

#[test]
fn dinasore_string_values_read_as_numbers_only_where_the_type_is_one() {
    let with = vec![
        ("SPEED", DataType::Elementary(ElementaryType::Real)),
        ("ON", DataType::Elementary(ElementaryType::Bool)),
        ("NAME", DataType::Elementary(ElementaryType::String)),
        ("N", DataType::Elementary(ElementaryType::Int)),
    ];
    let port = OutputPort::Event(with);
    let out = unstring_numbers(
        br#"{"SPEED": "21.75", "ON": "True", "NAME": "3", "N": "x3"}"#,
        "EV",
        &port,
    )
    .expect("an object");
    let out: serde_json::Value = serde_json::from_slice(&out).unwrap();
    assert_eq!(
        out,
        json!({"SPEED": 21.75, "ON": true, "NAME": "3", "N": "x3"})
    );
    let data = OutputPort::Data(DataType::Elementary(ElementaryType::Int));
    let out = unstring_numbers(br#"{"SPEED": " 3 "}"#, "SPEED", &data).unwrap();
    assert_eq!(out, br#"{"SPEED":3}"#);
    // DINASORE's VALUE is a REAL: an integer's 3 arrives as "3.0".
    let out = unstring_numbers(br#"{"SPEED": "3.0"}"#, "SPEED", &data).unwrap();
    assert_eq!(out, br#"{"SPEED":3}"#);
    let out = unstring_numbers(br#"{"SPEED": "3.5"}"#, "SPEED", &data).unwrap();
    assert_eq!(out, br#"{"SPEED":3.5}"#, "left for the decoder to refuse");
    let real = OutputPort::Data(DataType::Elementary(ElementaryType::Real));
    let out = unstring_numbers(br#"{"SPEED": "3.0"}"#, "SPEED", &real).unwrap();
    assert_eq!(out, br#"{"SPEED":3.0}"#);
    assert_eq!(unstring_numbers(b"[1]", "SPEED", &data), None);
    assert_eq!(unstring_numbers(b"\xff", "SPEED", &data), None);
}

#[test]
fn a_dinasore_input_only_takes_what_float_reads() {
    let profile = |data_in: serde_json::Value| -> ProfileFile {
        serde_json::from_value(json!({
            "device": "d",
            "runtime": "dinasore",
            "identity": {"topics_only": true},
            "speaks": {"encoding": "dinasore", "string_numbers": true},
            "interface": {"fbs": {"SUB": {"data_in": data_in}}},
            "topics": [{"topic": "line/d/in", "port": "SUB.IN", "from": "x/F/P"}]
        }))
        .unwrap()
    };
    assert!(profile(json!({"IN": "REAL"})).validate().is_ok());
    assert!(profile(json!({"IN": "BOOL"})).validate().is_ok());
    // An event whose FB reads its numeric key: the string beside it is ignored.
    let event: ProfileFile = serde_json::from_value(json!({
        "device": "d",
        "runtime": "dinasore",
        "identity": {"topics_only": true},
        "speaks": {"encoding": "dinasore"},
        "interface": {"fbs": {"SUB": {
            "events_in": {"IN": {"with": ["ID", "POSITION"]}},
            "data_in": {"ID": "STRING", "POSITION": "INT"}
        }}},
        "topics": [{"topic": "line/d/in", "port": "SUB.IN", "from": "x/F/P"}]
    }))
    .unwrap();
    assert!(event.validate().is_ok());
    for refused in ["STRING", "TIME", "DT", "ARRAY [2] OF INT"] {
        let errors = profile(json!({ "IN": refused }))
            .validate()
            .expect_err(refused);
        assert!(errors[0].error.contains("float(value)"), "{errors:?}");
    }
}

#[test]
fn liveness_follows_mqtt_by_default_and_a_dinasore_ends_after_90_s_of_silence() {
    let forte = conveyor(json!({})).validate().expect("valid");
    assert!(!forte.will_on_clean_disconnect);
    assert_eq!(
        forte.offline_after_silent, None,
        "a runtime that pings: off"
    );
    let dinasore = conveyor(json!({"runtime": "dinasore", "topics": []}))
        .validate()
        .expect("valid");
    assert_eq!(
        dinasore.offline_after_silent,
        Some(std::time::Duration::from_secs(
            DINASORE_OFFLINE_AFTER_SILENT_S
        ))
    );
    let set =
        |liveness| conveyor(json!({"runtime": "dinasore", "topics": [], "liveness": liveness}));
    let off = set(json!({"offline_after_silent_s": 0}))
        .validate()
        .expect("valid");
    assert_eq!(off.offline_after_silent, None);
    let reference = set(json!({"will_on_clean_disconnect": true, "offline_after_silent_s": 5}))
        .validate()
        .expect("valid");
    assert!(reference.will_on_clean_disconnect);
    assert_eq!(
        reference.offline_after_silent,
        Some(std::time::Duration::from_secs(5))
    );
    let errors = set(json!({"offline_after_silent_s": 86_401}))
        .validate()
        .expect_err("over a day");
    assert!(
        errors
            .iter()
            .any(|e| e.to_string().contains("liveness.offline_after_silent_s")),
        "{errors:?}"
    );
}

use super::*;
use crate::profile::fboot::tests::Noise;
use crate::profile::fboot::{import, NameError, PortNames};
use crate::profile::Identity;
use serde_json::json;

/// A conveyor module's configuration as DINASORE writes it (`save_fboot` of
/// `data_model_fboot/ua_manager.py`: `;` and the resource's CREATE, then `EMB_RES;` and
/// each request as 4diac IDE sent it, one a line, `START` last; the requests in the
/// order and form of DINASORE's `tests/configurations/full_config.fboot`, the FB types
/// and ports those of its `resources/function_blocks`): a sensor, a moving average,
/// an MQTT_PUBLISHER, an MQTT_PUBLISHER_2, an MQTT_SUBSCRIBER and an MQTT_SUBSCRIBER_2,
/// the last still pointed at another broker.
const CONV3: &str = include_str!("../../../../tests/data/dinasore.fboot");

fn profile(value: serde_json::Value) -> ProfileFile {
    serde_json::from_value(value).expect("a profile file")
}

/// A DINASORE file from request lines (`<Request ...>`), as `save_fboot` writes them.
fn file(requests: &[String]) -> String {
    file_without_sensor(&[vec![create("S", "SENSOR_SIMULATOR")], requests.to_vec()].concat())
}

fn file_without_sensor(requests: &[String]) -> String {
    let mut text = String::from(
        ";<Request ID=\"1\" Action=\"CREATE\"><FB Name=\"EMB_RES\" Type=\"EMB_RES\" /></Request>\n",
    );
    for r in requests {
        text.push_str("EMB_RES;");
        text.push_str(r);
        text.push('\n');
    }
    text
}

fn create(name: &str, fb_type: &str) -> String {
    format!(r#"<Request ID="2" Action="CREATE"><FB Name="{name}" Type="{fb_type}" /></Request>"#)
}

fn write(value: &str, destination: &str) -> String {
    format!(
        r#"<Request ID="3" Action="WRITE"><Connection Source="{value}" Destination="{destination}" /></Request>"#
    )
}

fn connect(source: &str, destination: &str) -> String {
    format!(
        r#"<Request ID="4" Action="CREATE"><Connection Source="{source}" Destination="{destination}" /></Request>"#
    )
}

/// An MQTT FB with its parameters: TOPIC, HOST 10.0.0.5, PORT 1883 and its VALUE_NAMEs
/// (a publisher's VALUEs connected from a sensor `S`).
fn mqtt(name: &str, fb_type: &str, topic: &str, names: &[&str]) -> Vec<String> {
    let mut lines = vec![
        create(name, fb_type),
        write(topic, &format!("{name}.TOPIC")),
        write("10.0.0.5", &format!("{name}.HOST")),
        write("1883", &format!("{name}.PORT")),
    ];
    match names {
        [one] => lines.push(write(one, &format!("{name}.VALUE_NAME"))),
        _ => {
            for (i, n) in names.iter().enumerate() {
                lines.push(write(n, &format!("{name}.VALUE_NAME_{}", i + 1)));
            }
        }
    }
    if fb_type.starts_with("MQTT_PUBLISHER") {
        let values: &[&str] = match names.len() {
            1 => &["VALUE"],
            _ => &["VALUE_1", "VALUE_2"],
        };
        for v in values {
            lines.push(connect("S.VALUE", &format!("{name}.{v}")));
        }
    }
    lines
}

fn import_lines(lines: &[Vec<String>]) -> FbootImport {
    import_dinasore(&file(&lines.concat()), "conv3")
}

fn speaks() -> serde_json::Value {
    json!({"encoding": "dinasore", "string_numbers": true, "enforce_keep_alive": false})
}

#[test]
fn the_conveyor_module_gives_its_profile() {
    let out = import_dinasore(CONV3, "conv3");
    let conv3 = profile(json!({
        "device": "conv3",
        "runtime": "dinasore",
        "identity": {"topics_only": true},
        "speaks": speaks(),
        "interface": {"fbs": {
            // {"SPEED": "<str(VALUE)>"}: one value, named.
            "PUB_SPEED": {"type": "MQTT_PUBLISHER",
                "data_out": {"SPEED": "REAL"}},
            // {"SPEED_RAW": ..., "SPEED_AVG": ...} at RUN.
            "PUB_STATE": {"type": "MQTT_PUBLISHER_2",
                "events_out": {"RUN": {"with": ["SPEED_RAW", "SPEED_AVG"]}},
                "data_out": {"SPEED_RAW": "REAL", "SPEED_AVG": "REAL"}},
            // float(payload["POSITION"]).
            "SUB_POS": {"type": "MQTT_SUBSCRIBER",
                "data_in": {"POSITION": "REAL"}},
            // Both out at READ_O.
            "SUB_CMD": {"type": "MQTT_SUBSCRIBER_2",
                "events_in": {"READ_O": {"with": ["TARGET", "RAMP"]}},
                "data_in": {"TARGET": "REAL", "RAMP": "REAL"}}
        }},
        "topics": [
            {"topic": "line1/conv3/speed", "port": "PUB_SPEED.SPEED"},
            {"topic": "line1/conv3/state", "port": "PUB_STATE.RUN"},
            {"topic": "line1/conv2/position", "port": "SUB_POS.POSITION"},
            {"topic": "line1/conv3/cmd", "port": "SUB_CMD.READ_O"}
        ]
    }));
    assert_eq!(out.profiles, vec![conv3]);
    assert_eq!(
        out.notes,
        [
            "The MQTT FBs connect to 2 brokers: 192.168.10.5:1883 (PUB_SPEED, PUB_STATE, \
             SUB_POS), 192.168.10.9:1883 (SUB_CMD). DINASORE connects each FB to its own HOST \
             and PORT, and the profile describes the device on one broker, fbbus's: point \
             every FB's HOST and PORT at it (two addresses of the same broker are fine).",
            "MQTT_SUBSCRIBER SUB_POS reads topic \"line1/conv2/position\": set `from` of that \
             topic in profile conv3 to the typed output that feeds it (<device>/<FB>/<PORT>).",
            "MQTT_SUBSCRIBER_2 SUB_CMD reads topic \"line1/conv3/cmd\": set `from` of that \
             topic in profile conv3 to the typed output that feeds it (<device>/<FB>/<PORT>).",
        ]
    );
}

#[test]
fn the_profile_validates_once_the_inputs_have_from() {
    let out = import_dinasore(CONV3, "conv3");
    let [conv3] = out.profiles.as_slice() else {
        panic!("one profile: {:?}", out.notes);
    };
    let errors = conv3
        .clone()
        .validate()
        .expect_err("two inputs without from");
    assert_eq!(
        errors.iter().map(|e| e.at.as_str()).collect::<Vec<_>>(),
        ["topics[2].from", "topics[3].from"],
        "{errors:?}"
    );

    let mut conv3 = conv3.clone();
    conv3.topics[2].from = Some("conv2/CONV/POSITION".into());
    conv3.topics[3].from = Some("hmi/PANEL/CMD".into());
    let p = conv3.validate().expect("valid");
    assert_eq!(p.identity, Identity::TopicsOnly);
    assert!(p.string_numbers);
    assert!(!p.enforce_keep_alive);
    assert_eq!((p.max_payload, p.qos), (0, 0));
    let outputs: Vec<(&str, &str, &str)> = p
        .outputs
        .iter()
        .map(|o| (o.topic.as_str(), o.fb.as_str(), o.port.as_str()))
        .collect();
    assert_eq!(
        outputs,
        [
            ("line1/conv3/speed", "PUB_SPEED", "SPEED"),
            ("line1/conv3/state", "PUB_STATE", "RUN")
        ]
    );
    let inputs: Vec<(&str, &str, &str)> = p
        .inputs
        .iter()
        .map(|i| (i.own.topic.as_str(), i.own.fb.as_str(), i.own.port.as_str()))
        .collect();
    assert_eq!(
        inputs,
        [
            ("line1/conv2/position", "SUB_POS", "POSITION"),
            ("line1/conv3/cmd", "SUB_CMD", "READ_O")
        ]
    );
    assert!(p
        .outputs
        .iter()
        .chain(p.inputs.iter().map(|i| &i.own))
        .all(|t| t.encoding == Encoding::Dinasore));
}

/// What DINASORE's FBs send decodes on the derived ports, string numbers and all.
#[test]
fn what_dinasore_publishes_decodes_on_the_derived_ports() {
    let out = import_dinasore(CONV3, "conv3");
    let interface = out.profiles[0].interface.clone().validate().expect("valid");
    let decode = |fb: &str, port: &str, payload: &str| {
        let shape = interface.output(fb, port).expect("an output");
        let payload = crate::profile::unstring_numbers(payload.as_bytes(), port, &shape)
            .expect("a JSON object");
        crate::codec::decode(
            Encoding::Dinasore,
            &payload,
            port,
            &shape,
            crate::codec::fbdk::TimeUnit::default(),
        )
    };
    // json.dumps({value_name: str(value)}), and the _2's two names in one object.
    assert!(decode("PUB_SPEED", "SPEED", r#"{"SPEED": "0.6425"}"#).is_ok());
    assert!(decode(
        "PUB_STATE",
        "RUN",
        r#"{"SPEED_RAW": "0.6425", "SPEED_AVG": "0.61"}"#
    )
    .is_ok());
    assert!(decode("PUB_SPEED", "SPEED", r#"{"SPEED": "None"}"#).is_err());
}

#[test]
fn a_forte_boot_file_is_no_dinasore_configuration_and_the_other_way_round() {
    let forte = include_str!("../../../../tests/data/conveyor.fboot");
    assert_eq!(import_dinasore(forte, "conv3"), FbootImport::default());
    // FORTE's import finds no PUBLISH/SUBSCRIBE in DINASORE's file, and says nothing.
    assert_eq!(import(CONV3), FbootImport::default());
    // No MQTT FB at all: nothing to say either.
    let sensor_only = file(&[]);
    assert_eq!(
        import_dinasore(&sensor_only, "conv3"),
        FbootImport::default()
    );
}

/// Each a file DINASORE does not run: no profile, one note naming the line.
#[test]
fn a_file_dinasore_does_not_run_gives_no_profile() {
    let pubs = mqtt("P", "MQTT_PUBLISHER", "line1/a", &["A"]);
    let cases: Vec<(String, &str)> = vec![
        (
            // A blank line (readlines() gives "\n", one part).
            format!("{}\n", file(&pubs)),
            "Line 9 has 1 ';'-separated parts, not the 2 DINASORE splits every line into (a \
             blank line, or a ';' in a parameter): it finds the file in an invalid state and \
             runs nothing of it (\"Awaiting deployment\"), so no profile is derived; write the \
             parameters without those characters in 4diac IDE.",
        ),
        (
            file(&[pubs.clone(), vec![write("a;b", "P.TOPIC")]].concat()),
            "Line 9 has 3 ';'-separated parts, not the 2 DINASORE splits every line into (a \
             blank line, or a ';' in a parameter): it finds the file in an invalid state and \
             runs nothing of it (\"Awaiting deployment\"), so no profile is derived; write the \
             parameters without those characters in 4diac IDE.",
        ),
        (
            // 4diac IDE does not escape '&' in a parameter.
            file(&[pubs.clone(), vec![write("line1/a&b", "P.TOPIC")]].concat()),
            "Line 9 is not XML that DINASORE's parser (Python's ElementTree) reads: attribute \
             Source of <Connection>: it has an '&' that starts no XML escape (4diac IDE writes \
             an '&' of a parameter as it is). It does not catch that error, so it runs nothing \
             of the file, and no profile is derived.",
        ),
        (
            // A STRING written with quotes, as 4diac IDE sends it: the escape has a ';'.
            file(&[pubs.clone(), vec![write("&apos;line1/a&apos;", "P.TOPIC")]].concat()),
            "Line 9 has the XML escape &apos; in a parameter (4diac IDE writes ' \" < > of a \
             parameter so: a STRING written with quotes, 'line1/a', is &apos;line1/a&apos;), \
             and DINASORE splits every line at each ';': it finds the file in an invalid state \
             and runs nothing of it (\"Awaiting deployment\"), so no profile is derived; write \
             the parameters without those characters in 4diac IDE.",
        ),
        (
            file(&[pubs.clone(), vec![write("line1&#47;a", "P.TOPIC")]].concat()),
            "Line 9 has the XML escape &#47; in a parameter (4diac IDE writes ' \" < > of a \
             parameter so: a STRING written with quotes, 'line1/a', is &apos;line1/a&apos;), \
             and DINASORE splits every line at each ';': it finds the file in an invalid state \
             and runs nothing of it (\"Awaiting deployment\"), so no profile is derived; write \
             the parameters without those characters in 4diac IDE.",
        ),
        (
            file(&[pubs.clone(), vec![write("x", "GONE.TOPIC")]].concat()),
            "Line 9: the WRITE goes to GONE, an FB it does not have; DINASORE raises there \
             while it builds its FBs from the file, so it runs nothing of it, and no profile \
             is derived.",
        ),
        (
            file(&[pubs.clone(), vec![write("UINT#1883", "P.PORT")]].concat()),
            "Line 9: P.PORT is \"UINT#1883\", which its int() cannot read (the port is a \
             UINT); DINASORE raises there while it builds its FBs from the file, so it runs \
             nothing of it, and no profile is derived.",
        ),
        (
            file(&[pubs.clone(), vec![write("fast", "P.VALUE")]].concat()),
            "Line 9: P.VALUE is \"fast\", which its float() cannot read (the value is a \
             REAL); DINASORE raises there while it builds its FBs from the file, so it runs \
             nothing of it, and no profile is derived.",
        ),
        (
            file(&[pubs.clone(), vec![connect("GONE.OUT", "P.VALUE")]].concat()),
            "Line 9: the connection comes from GONE, an FB it does not have; DINASORE raises \
             there while it builds its FBs from the file, so it runs nothing of it, and no \
             profile is derived.",
        ),
    ];
    for (text, note) in cases {
        let out = import_dinasore(&text, "conv3");
        assert_eq!(out.profiles, vec![], "{text}");
        assert_eq!(out.notes, [note], "{text}");
    }

    // A request over two lines: its second line has no ';'.
    let split = file(&pubs).replace("Destination=\"P.HOST\"", "\nDestination=\"P.HOST\"");
    let out = import_dinasore(&split, "conv3");
    assert!(out.profiles.is_empty());
    assert!(
        out.notes[0].starts_with("Line 5 is not XML") && out.notes.len() == 1,
        "{:?}",
        out.notes
    );
    // An unclosed element, two roots: ElementTree refuses them.
    for broken in [
        r#"<Request ID="9" Action="CREATE"><FB Name="X" Type="Y" />"#,
        r#"<Request ID="9" Action="START"/><Request ID="10" Action="START"/>"#,
        r#"<Request ID="9" Action="CREATE"><FB Name="X" Type="Y"></Request></FB>"#,
    ] {
        let out = import_dinasore(&file(&[pubs.clone(), vec![broken.into()]].concat()), "d");
        assert!(out.profiles.is_empty(), "{broken}");
        assert!(
            out.notes[0].starts_with("Line 9 is not XML"),
            "{:?}",
            out.notes
        );
    }
}

#[test]
fn the_file_is_read_as_dinasore_reads_it() {
    let pubs = mqtt("P", "MQTT_PUBLISHER", "line1/a", &["A"]);
    let base = import_dinasore(&file(&pubs), "conv3");
    assert_eq!(base.profiles.len(), 1, "{:?}", base.notes);
    assert_eq!(base.notes, Vec::<String>::new());

    // CRLF and lone CR line ends (Python's universal newlines), no end on the last line.
    let crlf = file(&pubs).replace('\n', "\r\n");
    assert_eq!(import_dinasore(&crlf, "conv3"), base);
    let cr = file(&pubs).replace('\n', "\r");
    assert_eq!(import_dinasore(&cr, "conv3"), base);
    let last = file(&pubs);
    assert_eq!(import_dinasore(last.trim_end(), "conv3"), base);

    // The resource name before ';' is not read; DELETE is not read; a later CREATE of
    // the same name replaces the FB; parameters apply whatever their line (FBs first).
    let mut lines = vec![write("line1/b", "P.TOPIC")];
    lines.extend(pubs.iter().cloned());
    lines.push(r#"<Request ID="9" Action="DELETE"><FB Name="P" Type="" /></Request>"#.into());
    lines.push(create("P", "MQTT_PUBLISHER"));
    let text = file(&lines).replace("EMB_RES;", "ANY;");
    let out = import_dinasore(&text, "conv3");
    assert_eq!(out.profiles[0].topics[0].topic, "line1/a");
    assert_eq!(out.notes, Vec::<String>::new());

    // FB.PORT split at the first dot; Python's int() and float() of PORT and VALUE.
    let out = import_lines(&[vec![
        create("P", "MQTT_PUBLISHER"),
        write("line1/x/y", "P.TOPIC.extra"),
        write("10.0.0.5", "P.HOST"),
        write(" 1_883 ", "P.PORT"),
        write("A", "P.VALUE_NAME"),
        write("+2.5e0", "P.VALUE"),
    ]]);
    assert_eq!(
        out.profiles[0].topics[0].topic, "line1/x/y",
        "{:?}",
        out.notes
    );
    // A tab in an attribute value is read as a space.
    let out = import_lines(&[vec![
        create("P", "MQTT_PUBLISHER"),
        write("line1/a\tb", "P.TOPIC"),
        write("10.0.0.5", "P.HOST"),
        write("1883", "P.PORT"),
        write("A", "P.VALUE_NAME"),
        connect("S.VALUE", "P.VALUE"),
    ]]);
    assert_eq!(out.profiles[0].topics[0].topic, "line1/a b");
    // A STRING parameter is taken as written: quotes that are no XML escape (a file not
    // written by 4diac IDE) are part of the topic.
    let out = import_lines(&[mqtt("P", "MQTT_PUBLISHER", "'line1/a'", &["A"])]);
    assert_eq!(out.profiles[0].topics[0].topic, "'line1/a'");
    assert_eq!(out.notes, Vec::<String>::new());
}

#[test]
fn value_names_name_the_ports() {
    // Not an identifier: left out.
    let out = import_lines(&[
        mqtt("P", "MQTT_PUBLISHER", "line1/a", &["1st"]),
        mqtt("Q", "MQTT_SUBSCRIBER_2", "line1/b", &["OK", "speed value"]),
        mqtt("R", "MQTT_PUBLISHER", "line1/c", &["C"]),
    ]);
    assert_eq!(out.profiles[0].topics.len(), 1);
    assert_eq!(
        out.notes,
        [
            "MQTT_PUBLISHER P: its VALUE_NAME \"1st\" is a payload key, which is a port name \
             in the profile and must be an IEC 61131-3 identifier; skipped: rename it in 4diac \
             IDE, in every FB that uses it.",
            "MQTT_SUBSCRIBER_2 Q: its VALUE_NAME_2 \"speed value\" is a payload key, which is a \
             port name in the profile and must be an IEC 61131-3 identifier; skipped: rename \
             it in 4diac IDE, in every FB that uses it.",
        ]
    );

    // A VALUE_NAME that is the event's name; two equal VALUE_NAMEs.
    let out = import_lines(&[
        mqtt("P", "MQTT_PUBLISHER_2", "line1/a", &["RUN", "B"]),
        mqtt("Q", "MQTT_SUBSCRIBER_2", "line1/b", &["X", "X"]),
        mqtt("R", "MQTT_PUBLISHER_2", "line1/c", &["Y", "Y"]),
    ]);
    let p = &out.profiles[0];
    assert_eq!(
        serde_json::to_value(&p.interface).unwrap(),
        json!({"fbs": {
            "P": {"type": "MQTT_PUBLISHER_2",
                "events_out": {"RUN_2": {"with": ["RUN", "B"]}},
                "data_out": {"RUN": "REAL", "B": "REAL"}},
            "Q": {"type": "MQTT_SUBSCRIBER_2", "data_in": {"X": "REAL"}},
            "R": {"type": "MQTT_PUBLISHER_2", "data_out": {"Y": "REAL"}}
        }})
    );
    let ports: Vec<&str> = p.topics.iter().map(|t| t.port.as_str()).collect();
    assert_eq!(ports, ["P.RUN_2", "Q.X", "R.Y"]);
    assert_eq!(
        out.notes,
        [
            "MQTT_PUBLISHER_2 P: one of its VALUE_NAMEs is RUN, the name of its event, so the \
             event is RUN_2 in profile conv3.",
            "MQTT_SUBSCRIBER_2 Q: VALUE_NAME_1 and VALUE_NAME_2 are both \"X\": it reads that \
             one key into both VALUE_1 and VALUE_2, so its FB in profile conv3 has the one \
             data port X.",
            "MQTT_SUBSCRIBER_2 Q reads topic \"line1/b\": set `from` of that topic in profile \
             conv3 to the typed output that feeds it (<device>/<FB>/<PORT>).",
            "MQTT_PUBLISHER_2 R: VALUE_NAME_1 and VALUE_NAME_2 are both \"Y\": its message \
             {\"Y\": ...} carries only VALUE_2, so its FB in profile conv3 has the one data \
             port Y.",
        ]
    );
    let mut p = p.clone();
    p.topics[1].from = Some("hmi/PANEL/X".into());
    p.validate().expect("valid");
}

#[test]
fn subscriptions_are_mapped_like_forte_ones() {
    let out = import_lines(&[
        // Read back from its own publisher: through the broker, not an input.
        mqtt(
            "SUB_OWN",
            "MQTT_SUBSCRIBER",
            "line1/conv3/speed",
            &["SPEED"],
        ),
        mqtt("PUB", "MQTT_PUBLISHER", "line1/conv3/speed", &["SPEED"]),
        mqtt("WILD", "MQTT_SUBSCRIBER", "line1/+/speed", &["SPEED"]),
        mqtt(
            "TYPED",
            "MQTT_SUBSCRIBER",
            "dinasore/conv2/CONV/POSITION",
            &["POSITION"],
        ),
        mqtt(
            "FBDK",
            "MQTT_SUBSCRIBER",
            "fbdk/conv2/CONV/POSITION",
            &["POSITION"],
        ),
        mqtt("OWN_NS", "MQTT_SUBSCRIBER", "fbbus/diag/conv3", &["X"]),
        mqtt("TWICE", "MQTT_SUBSCRIBER", "line1/in", &["A"]),
        mqtt("TWICE_2", "MQTT_SUBSCRIBER", "line1/in", &["A"]),
    ]);
    let p = &out.profiles[0];
    let topics: Vec<(&str, &str)> = p
        .topics
        .iter()
        .map(|t| (t.topic.as_str(), t.port.as_str()))
        .collect();
    assert_eq!(
        topics,
        [("line1/conv3/speed", "PUB.SPEED"), ("line1/in", "TWICE.A")]
    );
    assert!(p.interface.fbs.contains_key("SUB_OWN"));
    assert_eq!(
        out.notes,
        [
            "MQTT_SUBSCRIBER SUB_OWN reads topic \"line1/conv3/speed\", which PUB of the same \
             file publishes: DINASORE reaches itself through the broker as before, so the \
             topic is not mapped as an input (its port stays in the interface).",
            "MQTT_SUBSCRIBER WILD: its TOPIC \"line1/+/speed\" is a wildcard filter: it is \
             subscribed, but the FB compares each message's topic with TOPIC as a string, so \
             it reads nothing; skipped: one topic per FB.",
            "MQTT_SUBSCRIBER TYPED: it reads the typed topic \"dinasore/conv2/CONV/POSITION\" \
             directly, typed by the interface of device \"conv2\": nothing to map (its \
             VALUE_NAMEs must be POSITION or, for an event, names of its WITH data).",
            "MQTT_SUBSCRIBER FBDK: it reads \"fbdk/conv2/CONV/POSITION\", whose fbdk payloads \
             are not the JSON objects it reads, so the FB fails on the first one; skipped: \
             read \"dinasore/conv2/CONV/POSITION\" instead.",
            "MQTT_SUBSCRIBER OWN_NS: its topic \"fbbus/diag/conv3\" is in fbbus/, the broker's \
             own namespace; skipped: use a topic of its own.",
            "MQTT_SUBSCRIBER TWICE reads topic \"line1/in\": set `from` of that topic in \
             profile conv3 to the typed output that feeds it (<device>/<FB>/<PORT>).",
            "MQTT_SUBSCRIBER TWICE_2: its topic \"line1/in\" is already mapped onto TWICE.A in \
             profile conv3; a topic maps onto one port; skipped: map it by hand if it is \
             another.",
        ]
    );
}

#[test]
fn what_the_file_does_not_say_is_noted() {
    let out = import_lines(&[
        // No HOST: its INIT fails.
        vec![
            create("NO_HOST", "MQTT_PUBLISHER"),
            write("line1/a", "NO_HOST.TOPIC"),
            write("1883", "NO_HOST.PORT"),
            write("A", "NO_HOST.VALUE_NAME"),
        ],
        // PORT 0: no TCP port.
        vec![
            create("PORT_0", "MQTT_SUBSCRIBER"),
            write("line1/b", "PORT_0.TOPIC"),
            write("10.0.0.5", "PORT_0.HOST"),
            write("0", "PORT_0.PORT"),
            write("B", "PORT_0.VALUE_NAME"),
        ],
        // TOPIC from another FB at run time.
        vec![
            create("WIRED", "MQTT_PUBLISHER"),
            connect("S.NAME", "WIRED.TOPIC"),
            write("10.0.0.5", "WIRED.HOST"),
            write("1883", "WIRED.PORT"),
            write("C", "WIRED.VALUE_NAME"),
        ],
        // No VALUE_NAME.
        vec![
            create("NO_NAME", "MQTT_SUBSCRIBER"),
            write("line1/d", "NO_NAME.TOPIC"),
            write("10.0.0.5", "NO_NAME.HOST"),
            write("1883", "NO_NAME.PORT"),
        ],
        // VALUE neither connected nor written: mapped, with a note.
        vec![
            create("NO_VALUE", "MQTT_PUBLISHER"),
            write("line1/e", "NO_VALUE.TOPIC"),
            write("10.0.0.5", "NO_VALUE.HOST"),
            write("1883", "NO_VALUE.PORT"),
            write("E", "NO_VALUE.VALUE_NAME"),
        ],
        // A wildcard, a typed topic: no publication.
        mqtt("WILD", "MQTT_PUBLISHER", "line1/#", &["F"]),
        mqtt("TYPED", "MQTT_PUBLISHER", "dinasore/conv3/X/G", &["G"]),
        // A name that is no identifier; an FB inside a subapplication.
        mqtt("pub-h", "MQTT_PUBLISHER", "line1/h", &["H"]),
        vec![create("SUB.P", "MQTT_PUBLISHER")],
    ]);
    let p = &out.profiles[0];
    let topics: Vec<(&str, &str)> = p
        .topics
        .iter()
        .map(|t| (t.topic.as_str(), t.port.as_str()))
        .collect();
    assert_eq!(topics, [("line1/e", "NO_VALUE.E"), ("line1/h", "pub_h.H")]);
    assert_eq!(
        out.notes,
        [
            "MQTT_PUBLISHER NO_HOST: it has no HOST parameter, so paho's connect() raises at \
             its INIT and the FB stops; skipped: set HOST and PORT in 4diac IDE.",
            "MQTT_SUBSCRIBER PORT_0: its PORT \"0\" is no TCP port, so paho's connect() raises \
             at its INIT and the FB stops; skipped: write the broker's port.",
            "MQTT_PUBLISHER WIRED: its TOPIC comes from S.NAME at run time, which the file \
             does not say; skipped: map it by hand.",
            "MQTT_SUBSCRIBER NO_NAME: it has no VALUE_NAME parameter, so VALUE_NAME is None in \
             DINASORE and the FB fails on it; skipped: set it in 4diac IDE.",
            "MQTT_PUBLISHER NO_VALUE: NO_VALUE.VALUE is neither connected nor given a value, so \
             it publishes \"None\" for it, which the broker refuses as a REAL: connect it in \
             4diac IDE.",
            "MQTT_PUBLISHER WILD: its TOPIC \"line1/#\" is not a topic one can publish on \
             (empty or a wildcard), so paho raises at its first RUN and the FB stops; skipped: \
             fix TOPIC in 4diac IDE.",
            "MQTT_PUBLISHER TYPED: its TOPIC \"dinasore/conv3/X/G\" is in a typed namespace, \
             where a publication is typed by the interface of the device the topic names and \
             DINASORE's string values (\"3.0\") are refused; skipped: publish on a topic of its \
             own, which the profile maps.",
            "MQTT_PUBLISHER pub-h: its name is not an IEC 61131-3 identifier, so its FB in \
             profile conv3 is pub_h.",
            "MQTT_PUBLISHER SUB.P: its name has a '.' (an FB inside a subapplication), and \
             DINASORE splits FB.PORT at the first '.', so none of its parameters reaches it; \
             skipped: put it at the top level of the application.",
        ]
    );
}

#[test]
fn the_device_id_comes_from_the_caller() {
    let lines = [mqtt("P", "MQTT_PUBLISHER", "line1/a", &["A"])];
    let text = file(&lines.concat());
    assert_eq!(
        import_dinasore(&text, "line1-conv3").profiles[0].device,
        "line1-conv3"
    );
    let out = import_dinasore(&text, "line1/conv3");
    assert_eq!(out.profiles[0].device, "line1_conv3");
    assert_eq!(
        out.notes,
        [
            "The device id \"line1/conv3\" is not usable (1-256 bytes, none of / + # $, no \
          control characters): the profile's device is \"line1_conv3\"."
        ]
    );
    assert_eq!(import_dinasore(&text, "").profiles[0].device, "dinasore");

    // Nothing mappable: no profile, and why.
    let out = import_lines(&[mqtt("P", "MQTT_PUBLISHER", "line1/#", &["A"])]);
    assert!(out.profiles.is_empty());
    assert_eq!(
        out.notes.last().map(|n| n.text.as_str()),
        Some("None of its MQTT FBs can be mapped, so device conv3 has no profile.")
    );
}

#[test]
fn python_numbers_are_read_as_python_reads_them() {
    for (text, int) in [
        ("1883", Some(1883)),
        (" +1883\t", Some(1883)),
        ("1_883", Some(1883)),
        ("-1", Some(-1)),
        ("1__883", None),
        ("_1883", None),
        ("1883.0", None),
        ("0x75b", None),
        ("", None),
        (
            "99999999999999999999999999999999999999999999",
            Some(i128::MAX),
        ),
    ] {
        assert_eq!(python_int(text), int, "{text:?}");
    }
    for (text, float) in [
        ("1.5", Some(1.5)),
        (" 2 ", Some(2.0)),
        ("1_000.5", Some(1000.5)),
        ("1e3", Some(1000.0)),
        ("1__0", None),
        ("_1", None),
        ("one", None),
        ("", None),
    ] {
        assert_eq!(python_float(text), float, "{text:?}");
    }
    assert_eq!(python_lines(""), Vec::<&str>::new());
    assert_eq!(python_lines("a\r\nb\rc\n\nd"), ["a", "b", "c", "", "d"]);
}

/// The importer reads files from outside: nothing may panic, whatever the text.
#[test]
fn garbage_never_panics() {
    let run = |text: &str| {
        let out = import_dinasore(text, "conv3");
        for p in out.profiles {
            let _ = serde_json::to_string(&p).expect("serializes");
            let _ = p.validate();
        }
    };
    let mut noise = Noise(0x2545_f491_4f6c_dd1d);
    // Every cut of the fixture, at each byte (lossy, as the CLI reads it).
    for at in 0..=CONV3.len() {
        run(&String::from_utf8_lossy(&CONV3.as_bytes()[..at]));
        run(&String::from_utf8_lossy(&CONV3.as_bytes()[at..]));
    }
    const PIECES: [&str; 22] = [
        "<",
        ">",
        "\"",
        "'",
        "&",
        "&#",
        "&#x",
        ";",
        "&#0;",
        "&#xD800;",
        "&#1114112;",
        "/>",
        "</Request>",
        "\n",
        "\r",
        ".",
        "_",
        "é",
        "𝄞",
        "\u{0}",
        "=",
        "\t",
    ];
    let lines: Vec<&str> = CONV3.lines().collect();
    for _ in 0..600 {
        let mut text = String::new();
        for _ in 0..noise.below(12) {
            let line = lines[noise.below(lines.len())];
            let mut chars: Vec<char> = line.chars().collect();
            for _ in 0..noise.below(4) {
                let at = noise.below(chars.len() + 1);
                let piece = PIECES[noise.below(PIECES.len())];
                if noise.below(2) == 0 && at < chars.len() {
                    chars.remove(at);
                }
                for (k, c) in piece.chars().enumerate() {
                    chars.insert((at + k).min(chars.len()), c);
                }
            }
            text.extend(chars);
            text.push('\n');
        }
        run(&text);
        let bytes: Vec<u8> = (0..noise.below(200)).map(|_| noise.next() as u8).collect();
        run(&String::from_utf8_lossy(&bytes));
    }
}

#[test]
fn the_subscribers_missing_from_blocks_and_nothing_else_does() {
    let out = import_dinasore(CONV3, "conv3");
    let blocking: Vec<&str> = out
        .notes
        .iter()
        .filter(|n| n.is_blocking())
        .map(|n| n.text.as_str())
        .collect();
    assert_eq!(blocking.len(), 2, "{:#?}", out.notes);
    assert!(blocking[0].starts_with("MQTT_SUBSCRIBER SUB_POS reads topic"));
    assert!(blocking[1].starts_with("MQTT_SUBSCRIBER_2 SUB_CMD reads topic"));
    // The broker note comes first in the file's order, the blocking ones first when listed.
    assert!(!out.notes[0].is_blocking());
    assert!(out.notes_blocking_first()[0].starts_with("MQTT_SUBSCRIBER SUB_POS"));
    let errors = out.profiles[0].clone().validate().expect_err("no from");
    assert_eq!(errors.len(), out.blocking(), "{errors:#?}");
}

#[test]
fn event_ports_take_names_and_value_ports_keep_their_payload_keys() {
    let mut names = PortNames::new();
    names.add_arg("SUB_CMD.READ_O=COMMAND").unwrap();
    names.add_arg("PUB_STATE.RUN=STATE").unwrap();
    let out = import_dinasore_named(CONV3, "conv3", &mut names);
    names.finish().expect("event ports renamed");
    let fbs = &out.profiles[0].interface.fbs;
    assert_eq!(fbs["SUB_CMD"].events_in["COMMAND"].with, ["TARGET", "RAMP"]);
    assert_eq!(
        fbs["PUB_STATE"].events_out["STATE"].with,
        ["SPEED_RAW", "SPEED_AVG"]
    );
    let ports: Vec<&str> = out.profiles[0]
        .topics
        .iter()
        .map(|t| t.port.as_str())
        .collect();
    assert!(ports.contains(&"SUB_CMD.COMMAND") && ports.contains(&"PUB_STATE.STATE"));

    // A value's port is its payload key: renaming it would lose every message.
    let mut names = PortNames::new();
    names.add_arg("SUB_POS.POSITION=POS").unwrap();
    import_dinasore_named(CONV3, "conv3", &mut names);
    let errors = names.finish().expect_err("a payload key");
    assert!(
        matches!(&errors[..], [NameError::Fixed { fb, port, .. }] if fb == "SUB_POS" && port == "POSITION"),
        "{errors:#?}"
    );
    assert!(errors[0]
        .to_string()
        .contains("rename the VALUE_NAME in 4diac IDE"));
}

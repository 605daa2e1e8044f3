use super::*;
use crate::profile::Identity;
use serde_json::json;

/// Written in the syntax FORTE's boot-file loader reads and 4diac IDE writes (checked
/// against `src/stdfblib/ita/ForteBootFileLoader.cpp` and `src/stdfblib/ita/DEV_MGR.cpp`
/// of eclipse-4diac/4diac-forte, and the IDE-generated boot files of its `systemtests/`):
/// two resources, one MQTT client id each (on two brokers, as FORTE 3.x allows).
const CONVEYOR: &str = include_str!("../../../tests/data/conveyor.fboot");

fn profile(value: serde_json::Value) -> ProfileFile {
    serde_json::from_value(value).expect("a profile file")
}

/// A boot file of one resource `RES` from request lines (`<Request ...>` without the
/// resource prefix).
fn boot(requests: &[&str]) -> String {
    let mut text = String::from(
        ";<Request ID=\"1\" Action=\"CREATE\"><FB Name=\"RES\" Type=\"EMB_RES\" /></Request>\n",
    );
    for r in requests {
        text.push_str("RES;");
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

fn import_lines(lines: &[String]) -> FbootImport {
    let lines: Vec<&str> = lines.iter().map(String::as_str).collect();
    import(&boot(&lines))
}

#[test]
fn the_conveyor_boot_file_gives_one_profile_per_client_id() {
    let out = import(CONVEYOR);
    let speaks = json!({"encoding": "fbdk", "fbdk_time_unit": "ns", "max_payload": 255, "qos": 0});
    let conv1 = profile(json!({
        "device": "conv1",
        "runtime": "forte",
        "identity": {"client_id": "conv1"},
        "speaks": speaks,
        "interface": {"fbs": {
            // REAL: fed by F_INT_TO_REAL's OUT.
            "PUB_POS": {"type": "PUBLISH_1",
                "events_out": {"REQ": {"with": ["SD_1"]}},
                "data_out": {"SD_1": "REAL"}},
            // SD_1 from its literal UINT#7; SD_2 fed by CONVEYOR_CTRL, unknown: left out.
            "PUB_STATUS": {"type": "PUBLISH_2",
                "events_out": {"REQ": {"with": ["SD_1", "SD_2"]}},
                "data_out": {"SD_1": "UINT"}},
            // REAL: feeds F_REAL_TO_INT's IN (and CONVEYOR_CTRL, unknown).
            "SUB_SPEED": {"type": "SUBSCRIBE_1",
                "events_in": {"IND": {"with": ["RD_1"]}},
                "data_in": {"RD_1": "REAL"}}
        }},
        "topics": [
            {"topic": "line1/conv1/position", "port": "PUB_POS.REQ"},
            // The ID was &quot;-quoted and its topic had &amp;.
            {"topic": "line1/conv1/status&mode", "port": "PUB_STATUS.REQ"}
        ]
    }));
    let hmi = profile(json!({
        "device": "line1_hmi",
        "runtime": "forte",
        "identity": {"client_id": "line1/hmi"},
        "speaks": speaks,
        "interface": {"fbs": {
            // BOOL: E_SWITCH.G; TIME: E_CYCLE.DT.
            "SUB_CMD": {"type": "SUBSCRIBE_2",
                "events_in": {"IND": {"with": ["RD_1", "RD_2"]}},
                "data_in": {"RD_1": "BOOL", "RD_2": "TIME"}},
            // REAL: REAL2REAL's OUT.
            "PUB_SPEED": {"type": "PUBLISH_1",
                "events_out": {"REQ": {"with": ["SD_1"]}},
                "data_out": {"SD_1": "REAL"}},
            "PUB_ALIVE": {"type": "PUBLISH_0",
                "events_out": {"REQ": {"with": []}}}
        }},
        "topics": [
            {"topic": "line1/hmi/cmd", "port": "SUB_CMD.IND"},
            {"topic": "line1/hmi/speed", "port": "PUB_SPEED.REQ"},
            {"topic": "line1/hmi/alive", "port": "PUB_ALIVE.REQ"}
        ]
    }));
    assert_eq!(out.profiles, vec![conv1, hmi]);
    assert_eq!(
        out.notes,
        [
            "The boot file uses 2 MQTT client ids (\"conv1\", \"line1/hmi\"): FORTE 2.0.x keeps \
             one MQTT client per runtime and fails the INIT of FBs with another, FORTE 3.x one \
             per broker address; a profile is derived for each.",
            "PUBLISH_2 PUB_STATUS in resource EMB_RES: the type of PUB_STATUS.SD_2 is not \
             derivable from the boot file (it is fed by CTRL.STATE, a port of CONVEYOR_CTRL, \
             whose interface the boot file does not contain); set data_out.SD_2 of FB \
             PUB_STATUS in profile conv1.",
            "SUBSCRIBE_1 SUB_SPEED in resource EMB_RES reads topic \"line1/hmi/speed\", which \
             line1_hmi/PUB_SPEED/REQ publishes in this boot file: FORTE to FORTE through the \
             broker as before, so the topic is not mapped as an input (its port stays in the \
             interface).",
            "PUBLISH_1 LOG in resource EMB_RES: it sends raw[] payloads on \"line1/conv1/log\" \
             (the bytes of a STRING, with no type to check), which cannot be typed; skipped: \
             use fbdk[].mqtt[...] to put it on the bus typed.",
            "SUBSCRIBE_1 SUB_UP in resource EMB_RES: it reads the typed topic \
             \"fbdk/conv0/CONV/MOVED\" directly, typed by the interface of device \"conv0\": \
             nothing to map.",
            "Client id \"line1/hmi\" is not a usable device id (1-256 bytes, none of / + # $, no \
             control characters): its profile's device is \"line1_hmi\", with the client id as \
             identity.client_id; but fbbus refuses this client id at CONNECT, so change it in \
             the FBs' ID parameters (and in identity.client_id) before the device can connect.",
            "SUBSCRIBE_2 SUB_CMD in resource HMI_RES reads topic \"line1/hmi/cmd\": set `from` \
             of that topic in profile line1_hmi to the typed output that feeds it \
             (<device>/<FB>/<PORT>).",
            "CLIENT_1_1 ASK in resource HMI_RES: client/server FBs have no mapping onto the bus \
             (FORTE's MQTT layer does not implement them either); skipped: use \
             PUBLISH/SUBSCRIBE pairs.",
        ]
    );
}

#[test]
fn derived_profiles_validate_once_the_notes_are_followed() {
    let out = import(CONVEYOR);
    let [conv1, hmi] = out.profiles.as_slice() else {
        panic!("two profiles: {:?}", out.profiles);
    };

    // As derived, neither loads: a WITH value without a type, inputs without `from`.
    let errors = conv1.clone().validate().expect_err("SD_2 has no type");
    assert!(
        errors.iter().any(|e| e.error.contains("WITH SD_2")),
        "{errors:?}"
    );
    let errors = hmi
        .clone()
        .validate()
        .expect_err("SUB_CMD's topic has no from");
    assert_eq!(
        errors.iter().map(|e| e.at.as_str()).collect::<Vec<_>>(),
        ["topics[0].from"],
        "{errors:?}"
    );

    // What the notes ask for.
    let mut conv1 = conv1.clone();
    if let Some(fb) = conv1.interface.fbs.get_mut("PUB_STATUS") {
        fb.data_out.insert("SD_2".into(), "INT".into());
    }
    let conv1 = conv1.validate().expect("conv1 valid");
    assert_eq!(conv1.outputs.len(), 2);
    // SUB_SPEED reads line1_hmi's own output topic: no input mapping.
    assert!(conv1.inputs.is_empty());
    assert!(conv1.outputs.iter().all(|o| o.encoding == Encoding::Fbdk));
    assert_eq!(conv1.max_payload, 255);
    assert_eq!(conv1.identity, Identity::ClientId("conv1".into()));

    let mut hmi = hmi.clone();
    hmi.topics[0].from = Some("panel1/HMI/CMD".into());
    let hmi = hmi.validate().expect("hmi valid");
    assert_eq!(hmi.device, "line1_hmi");
    assert_eq!(hmi.identity, Identity::ClientId("line1/hmi".into()));
    assert_eq!(hmi.outputs.len(), 2);
}

#[test]
fn a_caller_who_knows_the_fb_types_supplies_them() {
    let mut types = builtin_types();
    types.insert(
        "CONVEYOR_CTRL".into(),
        BTreeMap::from([("STATE".to_owned(), "ARRAY [0..3] OF DINT".to_owned())]),
    );
    let out = import_with_types(CONVEYOR, &types);
    let status = &out.profiles[0].interface.fbs["PUB_STATUS"];
    assert_eq!(status.data_out["SD_2"], "ARRAY [4] OF DINT");
    assert!(
        !out.notes.iter().any(|n| n.contains("SD_2")),
        "{:?}",
        out.notes
    );

    // Only the table given: without the built-in one, F_INT_TO_REAL is unknown too.
    let out = import_with_types(CONVEYOR, &TypeTable::new());
    assert!(!out.profiles[0].interface.fbs["PUB_POS"]
        .data_out
        .contains_key("SD_1"));
    assert!(
        out.notes
            .iter()
            .any(|n| n.contains("POS2REAL.OUT, a port of F_INT_TO_REAL")),
        "{:?}",
        out.notes
    );

    // A type fbbus does not carry is noted, not written.
    let types = TypeTable::from([(
        "CONVEYOR_CTRL".to_owned(),
        BTreeMap::from([("STATE".to_owned(), "CONV_STATE".to_owned())]),
    )]);
    let out = import_with_types(CONVEYOR, &types);
    assert!(
        out.notes
            .iter()
            .any(|n| n.contains("CTRL.STATE, of type CONV_STATE, which fbbus does not carry")),
        "{:?}",
        out.notes
    );
}

#[test]
fn literal_types_come_from_their_prefix() {
    let elementary = |t| Ok(DataType::Elementary(t));
    use ElementaryType as E;
    for (literal, ty) in [
        ("INT#3", elementary(E::Int)),
        ("REAL#1.5", elementary(E::Real)),
        ("lreal#-1e300", elementary(E::Lreal)),
        ("T#1s", elementary(E::Time)),
        ("TIME#1h2m", elementary(E::Time)),
        ("D#2024-01-01", elementary(E::Date)),
        ("TOD#12:00:00", elementary(E::TimeOfDay)),
        ("DT#2024-01-01-12:00:00", elementary(E::DateAndTime)),
        (
            "DATE_AND_TIME#2024-01-01-12:00:00",
            elementary(E::DateAndTime),
        ),
        ("BYTE#16#FF", elementary(E::Byte)),
        ("TRUE", elementary(E::Bool)),
        ("false", elementary(E::Bool)),
        ("BOOL#1", elementary(E::Bool)),
        ("'text'", elementary(E::String)),
        ("STRING#'text'", elementary(E::String)),
        ("\"text\"", elementary(E::WString)),
        ("WSTRING#text", elementary(E::WString)),
    ] {
        assert_eq!(literal_type(literal), ty, "{literal}");
    }
    for untyped in [
        "3", "1.5", "16#FF", "2#1010", "[1, 2]", "LT#1s", "CHAR#'a'", "",
    ] {
        assert!(literal_type(untyped).is_err(), "{untyped}");
    }
}

#[test]
fn ids_are_read_as_forte_reads_them() {
    // STRING/WSTRING values: prefixes, quotes, $ escapes.
    assert_eq!(string_value("plain").as_deref(), Ok("plain"));
    assert_eq!(string_value("WSTRING#a b").as_deref(), Ok("a b"));
    assert_eq!(string_value("\"a$\"b$$c\"").as_deref(), Ok("a\"b$c"));
    assert_eq!(string_value("'a$'b$N$41'").as_deref(), Ok("a'b\nA"));
    assert_eq!(string_value("\"$00e9\"").as_deref(), Ok("é"));
    assert!(string_value("\"open").is_err());
    assert!(string_value("'bad $x'").is_err());
    assert!(string_value("'lone $").is_err());

    // Layers: `\` escapes brackets, `\\` is one backslash.
    assert_eq!(
        layers("fbdk[].mqtt[tcp://h:1883, c, a\\]b\\\\]"),
        Ok(vec![
            ("fbdk".to_owned(), String::new()),
            ("mqtt".to_owned(), "tcp://h:1883, c, a]b\\".to_owned())
        ])
    );
    assert!(layers("fbdk[").is_err());
    assert!(layers("[x]").is_err());

    // XML escapes: FORTE's five; others stay.
    assert_eq!(
        decode_entities("&quot;&apos;&amp;&lt;&gt;&#65;&x;&"),
        "\"'&<>&#65;&x;&"
    );
}

#[test]
fn publish_and_subscribe_ids_that_cannot_be_mapped_are_noted() {
    let mut lines = Vec::new();
    for (i, (fb_type, id)) in [
        ("PUBLISH_1", Some("239.0.0.1:61499")),
        ("PUBLISH_1", Some("fbdk[].ip[239.0.0.1:61499]")),
        ("PUBLISH_1", Some("fbdk[].mqtt[tcp://h:1883, c, t, extra]")),
        ("PUBLISH_1", Some("fbdk[].mqtt[tcp://h:1883, , t]")),
        ("PUBLISH_1", Some("fbdk[].mqtt[tcp://h:1883, c")),
        ("PUBLISH_1", Some("json[].mqtt[tcp://h:1883, c, t]")),
        ("PUBLISH_1", None),
        (
            "SUBSCRIBE_1",
            Some("fbdk[].mqtt[tcp://h:1883, c, line/+/pos]"),
        ),
        (
            "SUBSCRIBE_1",
            Some("fbdk[].mqtt[tcp://h:1883, c, fb/dev/CONV/POS]"),
        ),
        (
            "PUBLISH_1",
            Some("fbdk[].mqtt[tcp://h:1883, c, fbbus/declare/c]"),
        ),
        ("PUBLISH_1", Some("fbdk[].mqtt[tcp://h:1883, c, line/#]")),
        (
            "PUBLISH_1",
            Some("fbdk[].mqtt[tcp://h:1883, c, fbdk/other/CONV/POS]"),
        ),
        (
            "PUBLISH_1",
            Some("fbdk[].mqtt[tcp://h:1883, c, fb/c/CONV/POS]"),
        ),
        ("PUBLISH_300", Some("fbdk[].mqtt[tcp://h:1883, c, t]")),
    ]
    .into_iter()
    .enumerate()
    {
        let name = format!("FB{i}");
        lines.push(create(&name, fb_type));
        if let Some(id) = id {
            lines.push(write(id, &format!("{name}.ID")));
        }
    }
    lines.push(create("FEEDS_ID", "STRING2STRING"));
    lines.push(create("FB_ID", "SUBSCRIBE_1"));
    lines.push(connect("FEEDS_ID.OUT", "FB_ID.ID"));
    let out = import_lines(&lines);
    assert!(out.profiles.is_empty(), "{:?}", out.profiles);
    let expect = [
        ("FB0", "which FORTE reads as fbdk[].ip[239.0.0.1:61499], not MQTT"),
        ("FB1", "does not use MQTT"),
        ("FB2", "has 4 parameters, not the three FORTE takes"),
        ("FB3", "its client id is empty"),
        ("FB4", "is malformed (a layer has no ']')"),
        ("FB5", "its layer json[] over MQTT is not an encoding fbbus types"),
        ("FB6", "it has no ID parameter"),
        ("FB7", "subscribes to the filter \"line/+/pos\""),
        ("FB8", "which carries fb payloads its fbdk[] layer cannot decode; skipped: read \"fbdk/dev/CONV/POS\""),
        ("FB9", "is in fbbus/, the broker's own namespace"),
        ("FB10", "is not a topic name one can publish on"),
        ("FB11", "in the namespace of device \"other\", not its own (\"c\")"),
        ("FB12", "publishes fbdk[] bytes on \"fb/c/CONV/POS\", which the broker reads as fb"),
        ("FB13", "more data ports than a profile FB holds"),
        ("FB_ID", "its ID comes from FEEDS_ID.OUT at run time"),
    ];
    for (fb, text) in expect {
        assert!(
            out.notes
                .iter()
                .any(|n| n.contains(&format!(" {fb} in resource RES: ")) && n.contains(text)),
            "{fb}: {text}\n{:#?}",
            out.notes
        );
    }
    assert!(
        out.notes
            .iter()
            .any(|n| n == "Client id \"c\": none of its FBs can be mapped, so it has no profile."),
        "{:#?}",
        out.notes
    );
}

#[test]
fn a_publisher_on_a_typed_topic_declares_the_port_it_names() {
    let id = |topic: &str| format!("fbdk[].mqtt[tcp://h:1883, conv1, {topic}]");
    let lines = [
        create("POS", "INT2INT"),
        create("P1", "PUBLISH_1"),
        write(&id("fbdk/conv1/CONV/POSITION"), "P1.ID"),
        connect("POS.OUT", "P1.SD_1"),
        create("P2", "PUBLISH_2"),
        write(&id("fbdk/conv1/CONV/MOVED"), "P2.ID"),
        write("BOOL#TRUE", "P2.SD_1"),
        write("T#5ms", "P2.SD_2"),
        // The same port twice: the second is refused.
        create("P3", "PUBLISH_1"),
        write(&id("fbdk/conv1/CONV/POSITION"), "P3.ID"),
        // An instance named like the typed FB gets another name.
        create("CONV", "PUBLISH_1"),
        write(&id("line1/conv1/x"), "CONV.ID"),
        write("INT#1", "CONV.SD_1"),
    ];
    let out = import_lines(&lines);
    let expected = profile(json!({
        "device": "conv1", "runtime": "forte", "identity": {"client_id": "conv1"},
        "speaks": {"encoding": "fbdk", "max_payload": 255},
        "interface": {"fbs": {
            "CONV": {
                "events_out": {"MOVED": {"with": ["SD_1", "SD_2"]}},
                "data_out": {"POSITION": "INT", "SD_1": "BOOL", "SD_2": "TIME"}
            },
            "CONV_2": {"type": "PUBLISH_1",
                "events_out": {"REQ": {"with": ["SD_1"]}},
                "data_out": {"SD_1": "INT"}}
        }},
        "topics": [{"topic": "line1/conv1/x", "port": "CONV_2.REQ"}]
    }));
    assert_eq!(out.profiles, vec![expected.clone()], "{:#?}", out.notes);
    assert!(
        out.notes
            .iter()
            .any(|n| n.starts_with("PUBLISH_1 P3 in resource RES: ")
                && n.contains("needs port CONV.POSITION, which another FB already gave")),
        "{:#?}",
        out.notes
    );
    assert!(
        out.notes
            .iter()
            .any(|n| n.starts_with("PUBLISH_1 CONV in resource RES: ")
                && n.contains("its FB there is CONV_2")),
        "{:#?}",
        out.notes
    );
    let valid = expected.validate().expect("valid");
    assert!(valid.outputs.len() == 1 && valid.interface.output("CONV", "MOVED").is_some());
}

#[test]
fn names_and_ids_are_made_usable() {
    let id = |client: &str, topic: &str| format!("fbdk[].mqtt[tcp://h:1883, {client}, {topic}]");
    let text = [
        ";<Request ID=\"1\" Action=\"CREATE\"><FB Name=\"A\" Type=\"EMB_RES\" /></Request>"
            .to_owned(),
        format!("A;{}", create("Sub1.PUB", "PUBLISH_0")),
        format!("A;{}", write(&id("dev#1", "t/1"), "Sub1.PUB.ID")),
        format!("A;{}", create("PUB", "PUBLISH_0")),
        format!("A;{}", write(&id("dev#1", "t/2"), "PUB.ID")),
        format!("B;{}", create("PUB", "PUBLISH_0")),
        format!("B;{}", write(&id("dev#1", "t/3"), "PUB.ID")),
        format!("B;{}", create("SAME", "PUBLISH_0")),
        format!("B;{}", write(&id("dev#1", "t/3"), "SAME.ID")),
        // A client id that sanitizes to the first one's device.
        format!("B;{}", create("OTHER", "PUBLISH_0")),
        format!("B;{}", write(&id("dev+1", "t/4"), "OTHER.ID")),
    ]
    .join("\n");
    let out = import(&text);
    let devices: Vec<&str> = out.profiles.iter().map(|p| p.device.as_str()).collect();
    assert_eq!(devices, ["dev_1", "dev_1_2"], "{:#?}", out.notes);
    let fbs: Vec<&String> = out.profiles[0].interface.fbs.keys().collect();
    assert_eq!(fbs, ["PUB", "PUB_2", "Sub1_PUB"]);
    let ports: Vec<&str> = out.profiles[0]
        .topics
        .iter()
        .map(|t| t.port.as_str())
        .collect();
    assert_eq!(ports, ["Sub1_PUB.REQ", "PUB.REQ", "PUB_2.REQ"]);
    for fragment in [
        "Sub1.PUB in resource A: its name is not an IEC 61131-3 identifier, so its FB in profile dev_1 is Sub1_PUB.",
        "PUB in resource B: another FB of profile dev_1 already has its name",
        "SAME in resource B: its topic \"t/3\" is already mapped onto PUB_2.REQ",
        "Client id \"dev+1\" is not a usable device id",
    ] {
        assert!(out.notes.iter().any(|n| n.contains(fragment)), "{fragment}\n{:#?}", out.notes);
    }
    for p in &out.profiles {
        p.clone().validate().expect("valid");
    }

    assert_eq!(sanitized_device("a/b+c#d$e\u{7}", "forte"), "a_b_c_d_e_");
    assert_eq!(sanitized_device("", "forte"), "forte");
    let long: String = "é".repeat(200);
    let cut = sanitized_device(&long, "forte");
    assert!(cut.len() <= topic::MAX_DEVICE_ID && topic::is_device_id(&cut));
    assert_eq!(unique(long.clone(), |_| false, topic::MAX_DEVICE_ID), long);
    let numbered = unique(long.clone(), |n| n == long, topic::MAX_DEVICE_ID);
    assert!(numbered.ends_with("_2") && numbered.len() <= topic::MAX_DEVICE_ID);
    let named = unique(cut.clone(), |n| n == cut, topic::MAX_DEVICE_ID);
    assert!(
        named.ends_with("_2") && topic::is_device_id(&named),
        "{named}"
    );
    assert_eq!(sanitized_identifier("9lives", 64), "_9lives");
    assert_eq!(sanitized_identifier("ä.b", 64), "__b");
    assert!(is_identifier(&sanitized_identifier(&"x".repeat(100), 64)));
}

#[test]
fn the_file_is_read_as_forte_reads_it() {
    // A command over several lines, blank lines, DELETE.
    let text = "\n;<Request ID=\"1\" Action=\"CREATE\"><FB Name=\"R\" Type=\"EMB_RES\" /></Request>\n\n\
        R;<Request ID=\"2\" Action=\"CREATE\">\n  <FB Name=\"P\"\n Type=\"PUBLISH_1\" /></Request>\n\
        R;<Request ID=\"3\" Action=\"WRITE\"><Connection Source=\"fbdk[].mqtt[tcp://h:1883, d, t]\" Destination=\"P.ID\" /></Request>\n\
        R;<Request ID=\"4\" Action=\"WRITE\"><Connection Source=\"SINT#1\" Destination=\"P.SD_1\" /></Request>\n\
        R;<Request ID=\"5\" Action=\"CREATE\"><FB Name=\"GONE\" Type=\"PUBLISH_0\" /></Request>\n\
        R;<Request ID=\"6\" Action=\"WRITE\"><Connection Source=\"fbdk[].mqtt[tcp://h:1883, d, u]\" Destination=\"GONE.ID\" /></Request>\n\
        R;<Request ID=\"7\" Action=\"DELETE\"><FB Name=\"GONE\" Type=\"PUBLISH_0\" /></Request>\n\
        R;<Request ID=\"8\" Action=\"START\"/>";
    let out = import(text);
    assert!(out.notes.is_empty(), "{:#?}", out.notes);
    assert_eq!(out.profiles.len(), 1);
    assert_eq!(out.profiles[0].topics.len(), 1);
    assert_eq!(out.profiles[0].interface.fbs["P"].data_out["SD_1"], "SINT");

    // A line ending in `/>` ends the command, even inside a request, as in FORTE: the
    // `</Request>` left on its own line has no `;`, and loading stops there.
    let split = text.replace(
        " /></Request>\nR;<Request ID=\"3\"",
        " />\n</Request>\nR;<Request ID=\"3\"",
    );
    let out = import(&split);
    assert!(out.profiles.is_empty());
    assert!(
        out.notes[0].starts_with("Line 7: the line has no ';'"),
        "{:#?}",
        out.notes
    );

    // CRLF: read, with a note.
    let out = import(&text.replace('\n', "\r\n"));
    assert_eq!(out.profiles.len(), 1);
    assert!(out.notes[0].contains("CRLF"), "{:#?}", out.notes);

    // FORTE stops at the first command it cannot execute: so does the import.
    let good = [
        create("P", "PUBLISH_0"),
        write("fbdk[].mqtt[tcp://h:1883, d, t]", "P.ID"),
    ];
    for (bad, why) in [
        ("<Request ID=\"9\" Action=\"START\"/>".to_owned(), "no ';'"),
        (
            "R;<Request ID=\"9\" Action=\"CREATE\"><FB Name=\"Q\" Type=\"X\"".to_owned(),
            "not well-formed",
        ),
        (
            "R;<Request ID=\"9\" Action=\"FLY\"/>".to_owned(),
            "\"FLY\" is not a management command",
        ),
        (
            "R;<Request ID=\"9\" Action=\"CREATE\"><FB Name=\"P\" Type=\"E_CYCLE\" /></Request>"
                .to_owned(),
            "already exists",
        ),
        (
            "R;<Request ID=\"9\"><FB Name=\"Q\" /></Request>".to_owned(),
            "not a <Request> with an Action",
        ),
        (
            "R;<Request ID=\"9\" Action=\"WRITE\"><Connection Source=\"1\" /></Request>".to_owned(),
            "lacks its Source or a Destination",
        ),
    ] {
        let mut text = boot(&[&good[0], &good[1]]).replace("RES;", "R;");
        text.push_str(&bad);
        text.push('\n');
        text.push_str(&format!("R;{}\n", create("LATER", "PUBLISH_0")));
        text.push_str(&format!(
            "R;{}\n",
            write("fbdk[].mqtt[tcp://h:1883, d, later]", "LATER.ID")
        ));
        let out = import(&text);
        assert_eq!(out.profiles.len(), 1, "{bad}");
        assert_eq!(
            out.profiles[0].topics.len(),
            1,
            "{bad}: LATER is never created"
        );
        assert_eq!(out.notes.len(), 1, "{bad}: {:#?}", out.notes);
        assert!(
            out.notes[0].starts_with("Line 4: ") && out.notes[0].contains(why),
            "{bad}: {:#?}",
            out.notes
        );
    }
}

#[test]
fn a_subscriber_feeding_ports_of_different_types_is_left_untyped() {
    let lines = [
        create("S", "SUBSCRIBE_1"),
        write("fbdk[].mqtt[tcp://h:1883, d, t]", "S.ID"),
        create("A", "F_INT_TO_REAL"),
        create("B", "F_DINT_TO_REAL"),
        connect("S.RD_1", "A.IN"),
        connect("S.RD_1", "B.IN"),
        create("S2", "SUBSCRIBE_1"),
        write("fbdk[].mqtt[tcp://h:1883, d, u]", "S2.ID"),
        create("DT1", "E_DELAY"),
        create("DT2", "FB_TON"),
        connect("S2.RD_1", "DT1.DT"),
        connect("S2.RD_1", "DT2.PT"),
        connect("S2.RD_1", "NOWHERE.X"),
        create("S3", "SUBSCRIBE_1"),
        write("fbdk[].mqtt[tcp://h:1883, d, v]", "S3.ID"),
    ];
    let out = import_lines(&lines);
    let fbs = &out.profiles[0].interface.fbs;
    assert!(fbs["S"].data_in.is_empty());
    assert_eq!(fbs["S2"].data_in["RD_1"], "TIME");
    assert!(fbs["S3"].data_in.is_empty());
    assert!(out.notes.iter().any(|n| n.contains(
        "(it feeds ports of different types (A.IN INT, B.IN DINT)); set data_in.RD_1 of FB S in profile d."
    )), "{:#?}", out.notes);
    assert!(
        out.notes
            .iter()
            .any(|n| n.contains("S3.RD_1") && n.contains("it is connected to nothing")),
        "{:#?}",
        out.notes
    );
}

#[test]
fn date_and_time_ports_get_a_note_on_the_time_unit() {
    let lines = [
        create("P", "PUBLISH_1"),
        write("fbdk[].mqtt[tcp://h:1883, d, t]", "P.ID"),
        write("DT#2024-01-01-00:00:00", "P.SD_1"),
    ];
    let out = import_lines(&lines);
    assert_eq!(
        out.profiles[0].interface.fbs["P"].data_out["SD_1"],
        "DATE_AND_TIME"
    );
    assert!(
        out.notes
            .iter()
            .any(|n| n.starts_with("Profile d: ") && n.contains("fbdk_time_unit")),
        "{:#?}",
        out.notes
    );
}

#[test]
fn the_builtin_table_has_forte_s_port_types() {
    let types = builtin_types();
    for (fb_type, port, ty) in [
        ("F_INT_TO_REAL", "IN", "INT"),
        ("F_INT_TO_REAL", "OUT", "REAL"),
        ("F_DT_TO_TOD", "OUT", "TOD"),
        ("F_BYTE_BCD_TO_USINT", "OUT", "USINT"),
        ("F_TIME_IN_MS_TO_LINT", "IN", "TIME"),
        ("WSTRING2WSTRING", "OUT", "WSTRING"),
        ("E_CTU", "CV", "UINT"),
        ("E_TRAIN", "DT", "TIME"),
        ("FB_TON", "ET", "TIME"),
        ("FB_CTUD_ULINT", "CV", "ULINT"),
        ("IW", "IN", "WORD"),
        ("QX", "OUT", "BOOL"),
    ] {
        assert_eq!(types[fb_type][port], ty, "{fb_type}.{port}");
    }
    assert!(!types.contains_key("FB_CTUD_UDINT"));
    assert!(!types.contains_key("F_INT_TO_INT"));
    // Every type in it is one fbbus carries.
    for ports in types.values() {
        for ty in ports.values() {
            ty.parse::<DataType>().expect("a type fbbus carries");
        }
    }
    // A type name with a package is found by its last part.
    let out = import_lines(&[
        create("C", "iec61131::conversion::F_INT_TO_LREAL"),
        create("P", "iec61499::net::PUBLISH_1"),
        write("fbdk[].mqtt[tcp://h:1883, d, t]", "P.ID"),
        connect("C.OUT", "P.SD_1"),
    ]);
    assert_eq!(out.profiles[0].interface.fbs["P"].data_out["SD_1"], "LREAL");
}

/// A small xorshift: the garbage below is reproducible without a random-number crate.
pub(super) struct Noise(pub(super) u64);

impl Noise {
    pub(super) fn next(&mut self) -> u64 {
        self.0 ^= self.0 << 13;
        self.0 ^= self.0 >> 7;
        self.0 ^= self.0 << 17;
        self.0
    }

    pub(super) fn below(&mut self, n: usize) -> usize {
        (self.next() % n.max(1) as u64) as usize
    }
}

/// A boot file with multi-byte UTF-8 in every kind of place: names, parameters, topics,
/// escapes, resource names.
fn multibyte_boot() -> String {
    [
        ";<Request ID=\"1\" Action=\"CREATE\"><FB Name=\"RÉS\" Type=\"EMB_RES\" /></Request>",
        "RÉS;<Request ID=\"2\" Action=\"CREATE\"><FB Name=\"PÜB\" Type=\"PUBLISH_2\" /></Request>",
        "RÉS;<Request ID=\"3\" Action=\"WRITE\"><Connection Source=\"&quot;fbdk[].mqtt[tcp://h:1883, gerät€, линия/𝄞/ü\\]$&quot;x]&quot;\" Destination=\"PÜB.ID\" /></Request>",
        "RÉS;<Request ID=\"4\" Action=\"WRITE\"><Connection Source=\"STRING#'ä$'€'\" Destination=\"PÜB.SD_1\" /></Request>",
        "RÉS;<Request ID=\"5\" Action=\"CREATE\"><FB Name=\"Ω\" Type=\"F_INT_TO_REAL\" /></Request>",
        "RÉS;<Request ID=\"6\" Action=\"CREATE\"><Connection Source=\"Ω.OUT\" Destination=\"PÜB.SD_2\" /></Request>",
        "RÉS;<Request ID=\"7\" Action=\"CREATE\"><FB Name=\"SÜB\" Type=\"SUBSCRIBE_1\" /></Request>",
        "RÉS;<Request ID=\"8\" Action=\"WRITE\"><Connection Source=\"WSTRING#raw[].mqtt[tcp://h:1883, gerät€, 🚚/x]\" Destination=\"SÜB.ID\" /></Request>",
        "RÉS;<Request ID=\"9\" Action=\"START\"/>",
    ]
    .join("\n")
}

#[test]
fn multibyte_names_and_topics_are_kept() {
    let out = import(&multibyte_boot());
    assert_eq!(out.profiles.len(), 1, "{:#?}", out.notes);
    let p = &out.profiles[0];
    assert_eq!(p.device, "gerät€");
    assert_eq!(p.topics[0].topic, "линия/𝄞/ü]\"x");
    assert_eq!(p.topics[0].port, "P_B.REQ");
    assert_eq!(p.interface.fbs["P_B"].data_out["SD_1"], "STRING");
    assert_eq!(p.interface.fbs["P_B"].data_out["SD_2"], "REAL");
}

/// The importer reads files from outside: nothing may panic, whatever the text.
#[test]
fn garbage_never_panics() {
    let types = builtin_types();
    let run = |text: &str| {
        let out = import_with_types(text, &types);
        // Whatever is derived serializes, and validating it does not panic either.
        for p in out.profiles {
            let _ = serde_json::to_string(&p).expect("serializes");
            let _ = p.validate();
        }
    };

    // Every cut of a file full of multi-byte characters: at each character boundary, and
    // at each byte (the cut character becoming U+FFFD, as a lossy reader would give it).
    let multibyte = multibyte_boot();
    for at in 0..=multibyte.len() {
        if let Some(prefix) = multibyte.get(..at) {
            run(prefix);
        }
        if let Some(suffix) = multibyte.get(at..) {
            run(suffix);
        }
        run(&String::from_utf8_lossy(&multibyte.as_bytes()[..at]));
    }

    // The conveyor file cut at every line and inside every line.
    let mut noise = Noise(0x9e37_79b9_7f4a_7c15);
    let mut cut = String::new();
    for line in CONVEYOR.split_inclusive('\n') {
        for _ in 0..2 {
            let at = noise.below(line.len() + 1);
            if let Some(part) = line.get(..at) {
                run(&format!("{cut}{part}"));
            }
        }
        cut.push_str(line);
        run(&cut);
    }

    // Unbalanced quotes: each quote of each line of the conveyor file dropped in turn.
    for line in CONVEYOR.lines().take(12) {
        for (at, c) in line.char_indices().filter(|(_, c)| *c == '"') {
            let mut broken = line.to_owned();
            broken.replace_range(at..at + c.len_utf8(), "");
            run(&format!("{broken}\n{CONVEYOR}"));
            run(&format!("{CONVEYOR}{broken}\n"));
        }
    }

    // Splices of the characters the parsers look for, and random bytes.
    const PIECES: [&str; 24] = [
        "<",
        ">",
        "\"",
        "'",
        "&",
        "&quot;",
        "&amp",
        ";",
        "[",
        "]",
        "\\",
        "$",
        "#",
        "/>",
        "</Request>",
        "\n",
        "\r\n",
        ".",
        ",",
        "é",
        "€",
        "𝄞",
        "\u{0}",
        "=",
    ];
    let lines: Vec<&str> = CONVEYOR.lines().collect();
    for _ in 0..400 {
        let mut text = String::new();
        for _ in 0..noise.below(8) {
            let line = lines[noise.below(lines.len())];
            let mut chars: Vec<char> = line.chars().collect();
            for _ in 0..noise.below(4) {
                let at = noise.below(chars.len() + 1);
                let piece = PIECES[noise.below(PIECES.len())];
                chars.splice(at..at, piece.chars());
            }
            for _ in 0..noise.below(3) {
                if !chars.is_empty() {
                    let at = noise.below(chars.len());
                    chars.remove(at);
                }
            }
            text.extend(chars);
            text.push('\n');
        }
        run(&text);
    }
    for _ in 0..300 {
        let len = noise.below(600);
        let bytes: Vec<u8> = (0..len).map(|_| noise.next() as u8).collect();
        run(&String::from_utf8_lossy(&bytes));
        // Mostly ASCII, with the structure characters more likely.
        let text: String = (0..len)
            .map(|_| match noise.below(4) {
                0 => PIECES[noise.below(PIECES.len())].to_owned(),
                _ => char::from(b' ' + (noise.next() % 95) as u8).to_string(),
            })
            .collect();
        run(&text);
    }
}

/// The cases of issue 30 item 5, in a boot file as 4diac IDE writes one: a DINT count and
/// a DT stamp published; a DT stamp (a literal on its RD_1), an INT speed and a two-value
/// mode (one value wired to an FB type the file does not describe) read from another
/// device; and its own count read back into an INT input.
const CELL: &str = include_str!("../../../tests/data/cell.fboot");

#[test]
fn every_note_says_whether_it_blocks_and_the_blocking_ones_are_the_validation_errors() {
    let out = import(CELL);
    let [cell] = out.profiles.as_slice() else {
        panic!("one profile: {:#?}", out);
    };
    let blocking: Vec<&str> = out
        .notes
        .iter()
        .filter(|n| n.is_blocking())
        .map(|n| n.text.as_str())
        .collect();
    // One input type and three `from`s.
    assert_eq!(blocking.len(), 4, "{:#?}", out.notes);
    assert!(
        blocking[0].contains("S_STAMP in resource EMB_RES reads topic \"cell0/stamp\": set `from`")
    );
    assert!(
        blocking[1].contains("S_SPEED in resource EMB_RES reads topic \"cell0/speed\": set `from`")
    );
    assert!(
        blocking[2].contains("the type of S_MODE.RD_2 is not derivable")
            && blocking[2].contains("set data_in.RD_2 of FB S_MODE in profile cell1"),
        "{blocking:#?}"
    );
    assert!(
        blocking[3].contains("S_MODE in resource EMB_RES reads topic \"cell0/mode\": set `from`")
    );
    assert!(out
        .notes
        .iter()
        .all(|n| !n.is_blocking() || n.blocks.as_deref() == Some("cell1")));
    assert_eq!(out.blocking(), 4);
    let firsts: Vec<bool> = out
        .notes_blocking_first()
        .iter()
        .map(|n| n.is_blocking())
        .collect();
    assert_eq!(firsts[..4], [true; 4]);
    assert!(firsts[4..].iter().all(|b| !b));

    // As many errors as blocking notes, all in one validation.
    let errors = cell.clone().validate().expect_err("incomplete");
    assert_eq!(errors.len(), 4, "{errors:#?}");

    // Typed from the DT literal on either side; the DINT count kept where it is read as
    // INT, with a note naming both.
    let fbs = &cell.interface.fbs;
    assert_eq!(fbs["P_STAMP"].data_out["SD_1"], "DATE_AND_TIME");
    assert_eq!(fbs["S_STAMP"].data_in["RD_1"], "DATE_AND_TIME");
    assert_eq!(fbs["P_COUNT"].data_out["SD_1"], "DINT");
    assert_eq!(fbs["S_SPEED"].data_in["RD_1"], "INT");
    assert_eq!(fbs["S_COUNT"].data_in["RD_1"], "DINT");
    let width: Vec<&Note> = out
        .notes
        .iter()
        .filter(|n| n.contains("check the width"))
        .collect();
    assert_eq!(width.len(), 1, "{:#?}", out.notes);
    assert!(
        width[0].contains("S_COUNT.RD_1 as INT") && width[0].contains("SD_1 as DINT"),
        "{width:#?}"
    );
    assert!(!width[0].is_blocking());

    // Following the blocking notes makes it valid.
    let mut cell = cell.clone();
    if let Some(fb) = cell.interface.fbs.get_mut("S_MODE") {
        fb.data_in.insert("RD_2".into(), "USINT".into());
    }
    for (topic, from) in [
        ("cell0/stamp", "cell0/CLOCK/STAMP"),
        ("cell0/speed", "cell0/DRIVE/SPEED"),
        ("cell0/mode", "cell0/MODE/SET"),
    ] {
        let t = cell.topics.iter_mut().find(|t| t.topic == topic).unwrap();
        t.from = Some(from.into());
    }
    cell.validate()
        .expect("valid once the blocking notes are followed");
}

#[test]
fn a_literal_on_a_wired_pin_types_the_port() {
    // RD_1 feeds an input of an FB type the file does not describe, but that input is
    // given a DATE literal; SD_1 is fed by an output given a TIME_OF_DAY one.
    let out = import_lines(&[
        create("SUB", "SUBSCRIBE_1"),
        write("fbdk[].mqtt[tcp://b:1883, dev, line/in]", "SUB.ID"),
        create("CLOCK", "MY_CLOCK"),
        connect("SUB.RD_1", "CLOCK.DAY"),
        write("D#2024-01-01", "CLOCK.DAY"),
        create("PUB", "PUBLISH_1"),
        write("fbdk[].mqtt[tcp://b:1883, dev, line/out]", "PUB.ID"),
        connect("CLOCK.NOW", "PUB.SD_1"),
        write("TOD#12:00:00", "CLOCK.NOW"),
    ]);
    let fbs = &out.profiles[0].interface.fbs;
    assert_eq!(fbs["SUB"].data_in["RD_1"], "DATE", "{:#?}", out.notes);
    assert_eq!(
        fbs["PUB"].data_out["SD_1"], "TIME_OF_DAY",
        "{:#?}",
        out.notes
    );

    // A literal of another width on the port itself: the source's type, and a note.
    let out = import_lines(&[
        create("COUNTER", "FB_CTU_DINT"),
        create("PUB", "PUBLISH_1"),
        write("fbdk[].mqtt[tcp://b:1883, dev, line/out]", "PUB.ID"),
        connect("COUNTER.CV", "PUB.SD_1"),
        write("INT#0", "PUB.SD_1"),
        create("SUB", "SUBSCRIBE_1"),
        write("fbdk[].mqtt[tcp://b:1883, dev, line/in]", "SUB.ID"),
        write("DINT#0", "SUB.RD_1"),
        create("TO_REAL", "F_INT_TO_REAL"),
        connect("SUB.RD_1", "TO_REAL.IN"),
    ]);
    let fbs = &out.profiles[0].interface.fbs;
    assert_eq!(fbs["PUB"].data_out["SD_1"], "DINT");
    assert_eq!(fbs["SUB"].data_in["RD_1"], "DINT");
    let widths: Vec<&Note> = out
        .notes
        .iter()
        .filter(|n| n.contains("check the width"))
        .collect();
    assert_eq!(widths.len(), 2, "{:#?}", out.notes);
    assert!(widths[0].contains("PUB.SD_1 is fed a DINT by COUNTER.CV but is given the INT value"));
    assert!(
        widths[1].contains("SUB.RD_1 is given the DINT value \"DINT#0\" but feeds TO_REAL.IN INT")
    );
}

#[test]
fn the_user_names_the_generated_ports() {
    let mut names = PortNames::new();
    names.add_arg("P_COUNT.SD_1=COUNT").unwrap();
    names.add_arg("P_COUNT.REQ=COUNTED").unwrap();
    names.add("S_MODE.RD_2", "MODE").unwrap();
    names.add("S_MODE.IND", "MODE_SET").unwrap();
    let out = import_named(CELL, &builtin_types(), &mut names);
    names.finish().expect("every name used");
    let cell = &out.profiles[0];
    let count = &cell.interface.fbs["P_COUNT"];
    assert_eq!(count.events_out["COUNTED"].with, ["COUNT"]);
    assert_eq!(count.data_out["COUNT"], "DINT");
    assert!(!count.data_out.contains_key("SD_1"));
    let ports: Vec<&str> = cell.topics.iter().map(|t| t.port.as_str()).collect();
    assert!(ports.contains(&"P_COUNT.COUNTED") && ports.contains(&"S_MODE.MODE_SET"));
    let mode = &cell.interface.fbs["S_MODE"];
    assert_eq!(mode.events_in["MODE_SET"].with, ["RD_1", "MODE"]);
    // The note says where the new name goes.
    assert!(
        out.notes
            .iter()
            .any(|n| n.contains("set data_in.MODE of FB S_MODE in profile cell1")),
        "{:#?}",
        out.notes
    );
    // The reader of its own count takes the publisher's typed output by its new name.
    assert!(
        out.notes
            .iter()
            .any(|n| n.contains("cell1/P_COUNT/COUNTED publishes")),
        "{:#?}",
        out.notes
    );
    // Once the blocking notes are followed, the named profile validates.
    let mut cell = cell.clone();
    if let Some(fb) = cell.interface.fbs.get_mut("S_MODE") {
        fb.data_in.insert("MODE".into(), "USINT".into());
    }
    for t in cell
        .topics
        .iter_mut()
        .filter(|t| t.topic.starts_with("cell0/"))
    {
        t.from = Some("cell0/X/Y".into());
    }
    cell.validate().expect("valid");
}

#[test]
fn a_wrong_port_name_is_an_error_that_says_what_to_do() {
    let mut names = PortNames::new();
    assert!(matches!(
        names.add_arg("P_COUNT.SD_1=1COUNT"),
        Err(NameError::NotIdentifier { .. })
    ));
    assert!(matches!(
        names.add_arg("P_COUNT=COUNT"),
        Err(NameError::Syntax(_))
    ));
    assert!(matches!(
        names.add_arg("P_COUNT.SD_1"),
        Err(NameError::Syntax(_))
    ));
    names.add_arg("P_COUNT.SD_1=COUNT").unwrap();
    let twice = names.add_arg("P_COUNT.SD_1=TOTAL").unwrap_err();
    assert!(twice.to_string().contains("keep one"), "{twice}");
    names.add_arg("P_COUNT.SD_9=NINE").unwrap();
    names.add_arg("S_MODE.RD_1=RD_2").unwrap();
    import_named(CELL, &builtin_types(), &mut names);
    let errors = names.finish().expect_err("two wrong names");
    let text: Vec<String> = errors.iter().map(ToString::to_string).collect();
    assert_eq!(errors.len(), 2, "{text:#?}");
    assert!(
        matches!(&errors[0], NameError::Collides { fb, name, .. } if fb == "S_MODE" && name == "RD_2"),
        "{text:#?}"
    );
    assert!(text[0].contains("choose another"), "{text:#?}");
    assert!(
        matches!(&errors[1], NameError::NoSuchPort { fb, port } if fb == "P_COUNT" && port == "SD_9"),
        "{text:#?}"
    );
    assert!(text[1].contains("as the profile printed without names shows it"));
}

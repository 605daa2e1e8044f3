//! Device profiles end to end against the real `fbbus` binary (issue 16): devices that
//! never declare, publish on their own topics in their own encoding, and read their
//! inputs on their own topics.
//!
//! - `conv2` is FORTE-like: recognised by its client id, `fbdk` on its own topics, a
//!   255-byte receive limit, and a broker-side will (`CONV.CONNECT = FALSE`).
//! - `conv3` is DINASORE-like: a random client id, so recognised by its topics only;
//!   DINASORE JSON with its values written as strings (`{"SPEED": "3.5"}`).
//!
//! Each feeds the other: conv3's SPEED reaches conv2 as `fbdk` REAL on conv2's own input
//! topic; conv2's POSITION reaches conv3 as DINASORE JSON on conv3's.
//!
//! The clients here speak raw MQTT 5 so each refusal's reason code is checked;
//! `runtime_emulators.rs` drives the same profiles with clients that reproduce each
//! runtime's exact wire behaviour.

mod common;

use std::time::Duration;

use serde_json::json;

use common::fb::*;
use common::{Broker, Options};

const CONV2: &str = r#"
device = "conv2"
runtime = "forte"
[speaks]
encoding = "fbdk"
max_payload = 255
[interface.fbs.CONV.events_out]
CNF = { with = ["POSITION"] }
[interface.fbs.CONV.data_out]
POSITION = "INT"
CONNECT = "BOOL"
[interface.fbs.CONV.data_in]
SPEED = "REAL"
NOTE = "STRING"
[[topics]]
topic = "line1/conv2/position"
port = "CONV.POSITION"
[[topics]]
topic = "line1/conv2/speed"
port = "CONV.SPEED"
from = "conv3/CONV/SPEED"
[[topics]]
topic = "line1/conv2/note"
port = "CONV.NOTE"
from = "conv3/CONV/NOTE"
[will]
"CONV.CONNECT" = false
"#;

const CONV3: &str = r#"
device = "conv3"
runtime = "dinasore"
identity = { topics_only = true }
[speaks]
encoding = "dinasore"
string_numbers = true
enforce_keep_alive = false
[interface.fbs.CONV.data_out]
SPEED = "REAL"
NOTE = "STRING"
[interface.fbs.CONV.data_in]
POSITION = "INT"
[[topics]]
topic = "line1/conv3/speed"
port = "CONV.SPEED"
[[topics]]
topic = "line1/conv3/note"
port = "CONV.NOTE"
[[topics]]
topic = "line1/conv3/position"
port = "CONV.POSITION"
from = "conv2/CONV/POSITION"
"#;

fn line() -> Broker {
    Broker::start_with(
        Options {
            extra: "[fb]\nprofiles_dir = \"profiles\"\n".into(),
            ..Default::default()
        },
        |dir| {
            let profiles = dir.join("profiles");
            std::fs::create_dir(&profiles).unwrap();
            std::fs::write(profiles.join("conv2.toml"), CONV2).unwrap();
            std::fs::write(profiles.join("conv3.toml"), CONV3).unwrap();
        },
    )
}

/// `fbdk` INT.
fn fbdk_int(v: i16) -> Vec<u8> {
    let mut b = vec![0x43];
    b.extend(v.to_be_bytes());
    b
}

#[tokio::test(flavor = "multi_thread")]
async fn profiled_devices_are_typed_registered_and_fed_without_declaring() {
    let broker = line();
    let mut sub = observer(
        &broker,
        "watch",
        &["fb/#", "dinasore/#", "fbdk/#", "line1/#", "fbbus/diag/#"],
    )
    .await;

    // conv2 connects and never declares: online with its profile's interface.
    let mut conv2 = Dev::connect(broker.port(), 5, "conv2");
    let record = wait_record(&broker, "conv2", "online", |r| r["status"] == "online").await;
    assert_eq!(
        record["interface"]["fbs"]["CONV"]["data_out"]["POSITION"],
        "INT"
    );

    // Its fbdk INT on its own topic: delivered there as it came, on every typed
    // namespace, and to conv3's input topic the way DINASORE reads it.
    assert_eq!(conv2.publish("line1/conv2/position", &fbdk_int(5)), 0);
    let got = one_each(
        &mut sub,
        &[
            "line1/conv2/position",
            "fb/conv2/CONV/POSITION",
            "dinasore/conv2/CONV/POSITION",
            "fbdk/conv2/CONV/POSITION",
            "line1/conv3/position",
        ],
        &broker,
    )
    .await;
    assert_eq!(got[0], fbdk_int(5));
    assert_eq!(parse(&got[1]), json!(5));
    assert_eq!(parse(&got[2]), json!({"POSITION": 5}));
    assert_eq!(got[3], fbdk_int(5));
    assert_eq!(parse(&got[4]), json!({"POSITION": 5}));

    // Ill-typed on its own topic: a REAL where an INT is.
    assert_eq!(
        conv2.publish("line1/conv2/position", &[0x4A, 0x40, 0x60, 0, 0]),
        0x99
    );
    let rejected = diag(&mut sub, "conv2", "rejected", &broker).await;
    assert_eq!(rejected["topic"], "line1/conv2/position");
    // An input topic is the broker's to write.
    assert_eq!(
        conv2.publish("line1/conv2/speed", &[0x4A, 0, 0, 0, 0]),
        0x87
    );

    // A stranger on conv2's topic: refused, whatever it sends.
    let mut intruder = Dev::connect(broker.port(), 5, "intruder");
    assert_eq!(intruder.publish("line1/conv2/position", &fbdk_int(9)), 0x87);
    // Nor is a device recognised by its client id another device's topics-only topic.
    assert_eq!(
        conv2.publish("line1/conv3/speed", br#"{"SPEED": "1"}"#),
        0x87
    );

    // conv3, DINASORE-like: a random client id, its number as a string.
    let mut conv3 = Dev::connect(broker.port(), 5, "paho-8f2c1d");
    assert_eq!(
        conv3.publish("line1/conv3/speed", br#"{"SPEED": "3.5"}"#),
        0
    );
    let got = one_each(
        &mut sub,
        &["fb/conv3/CONV/SPEED", "line1/conv2/speed"],
        &broker,
    )
    .await;
    assert_eq!(parse(&got[0]), json!(3.5));
    // REAL 3.5 in fbdk for conv2, big-endian IEEE 754.
    assert_eq!(got[1], [0x4A, 0x40, 0x60, 0x00, 0x00]);
    // That connection now speaks for conv3: online in the registry.
    wait_record(&broker, "conv3", "online", |r| r["status"] == "online").await;
    // Not a number at all: refused, told to the publisher.
    assert_eq!(
        conv3.publish("line1/conv3/speed", br#"{"SPEED": "fast"}"#),
        0x99
    );
    // A STRING stays a string, even one that reads as a number.
    assert_eq!(conv3.publish("line1/conv3/note", br#"{"NOTE": "42"}"#), 0);
    let got = one_each(&mut sub, &["line1/conv2/note"], &broker).await;
    assert_eq!(got[0], [&[0x50, 0x00, 0x02][..], b"42"].concat());
    // Longer than conv2 can take in (255 bytes in fbdk): not delivered to it, and the
    // publisher is told why.
    let long = format!(r#"{{"NOTE": "{}"}}"#, "x".repeat(300));
    assert_eq!(conv3.publish("line1/conv3/note", long.as_bytes()), 0);
    // (The fbdk/ copy is over the line's own limit too: two diagnostics.)
    let mut topics = Vec::new();
    for _ in 0..2 {
        let skipped = diag(&mut sub, "conv3", "not_reencoded", &broker).await;
        topics.push(skipped["topic"].as_str().unwrap_or_default().to_owned());
    }
    topics.sort();
    assert_eq!(topics, ["fbdk/conv3/CONV/NOTE", "line1/conv2/note"]);
    assert!(
        next_on(&mut sub, "line1/conv2/note", Duration::from_millis(500))
            .await
            .is_none(),
        "a message over conv2's limit reached it"
    );

    // A declaration from a profiled device must equal its profile.
    assert_eq!(
        conv2.declare(r#"{"fbs": {"CONV": {"data_out": {"POSITION": "REAL"}}}}"#),
        0x99
    );
    let answer = diag(&mut sub, "conv2", "declaration", &broker).await;
    assert_eq!(answer["ok"], false, "{answer}");

    // conv2's connection dies without a will of its own: offline, and the broker
    // publishes its profile's will on its typed port.
    drop(conv2);
    wait_record(&broker, "conv2", "offline", |r| r["status"] == "offline").await;
    let got = json_on(&mut sub, "fb/conv2/CONV/CONNECT", &broker).await;
    assert_eq!(got, json!(false));
    // conv3's connection ends: offline too.
    drop(conv3);
    wait_record(&broker, "conv3", "offline", |r| r["status"] == "offline").await;
}

#[tokio::test(flavor = "multi_thread")]
async fn a_profile_written_later_applies_from_the_next_connect() {
    let broker = Broker::start_with(
        Options {
            extra: "[fb]\nprofiles_dir = \"profiles\"\n".into(),
            ..Default::default()
        },
        |dir| std::fs::create_dir(dir.join("profiles")).unwrap(),
    );
    let dir = broker.path("profiles");
    // A broken file is refused, counted, and the broker keeps serving.
    std::fs::write(
        dir.join("conv2.toml"),
        CONV2.replace("\"INT\"", "\"INTEGER\""),
    )
    .unwrap();
    assert_metric(
        &broker,
        "fbbus_file_reloads_total{file=\"profiles_dir\",result=\"error\"}",
        1.0,
    );
    std::fs::write(dir.join(".conv2.toml"), CONV2).unwrap();
    std::fs::rename(dir.join(".conv2.toml"), dir.join("conv2.toml")).unwrap();
    assert_metric(
        &broker,
        "fbbus_file_reloads_total{file=\"profiles_dir\",result=\"ok\"}",
        1.0,
    );
    let mut conv2 = Dev::connect(broker.port(), 5, "conv2");
    wait_record(&broker, "conv2", "online", |r| r["status"] == "online").await;
    assert_eq!(conv2.publish("line1/conv2/position", &fbdk_int(1)), 0);
}

/// `fbbus declare` puts a profile into a running broker, which checks it against the
/// others before anything is written.
#[tokio::test(flavor = "multi_thread")]
async fn fbbus_declare_puts_a_profile_that_the_others_allow() {
    let broker = Broker::start_with(
        Options {
            extra: "[fb]\nprofiles_dir = \"profiles\"\n".into(),
            ..Default::default()
        },
        |dir| {
            let profiles = dir.join("profiles");
            std::fs::create_dir(&profiles).unwrap();
            std::fs::write(profiles.join("conv3.toml"), CONV3).unwrap();
        },
    );
    let declare = |text: &str| {
        let file = broker.path("new.toml");
        std::fs::write(&file, text).unwrap();
        common::run(
            std::process::Command::new(common::fbbus_bin()).args([
                "declare",
                file.to_str().unwrap(),
                "--admin",
                &broker.admin.to_string(),
            ]),
            Duration::from_secs(20),
        )
    };
    // conv2 mapping conv3's output topic: refused, nothing written.
    let thief = CONV2.replace("line1/conv2/position", "line1/conv3/speed");
    let (ok, _, err) = declare(&thief);
    assert!(!ok && err.contains("line1/conv3/speed"), "{err}");
    assert!(!broker.path("profiles/conv2.toml").exists());
    // A mistake is named by its key, before the broker is asked.
    let (ok, _, err) = declare(&CONV2.replace("\"INT\"", "\"INTEGER\""));
    assert!(!ok && err.contains("INTEGER"), "{err}");
    // The real one: written, in force at once.
    let (ok, out, err) = declare(CONV2);
    assert!(ok, "{out}{err}");
    assert_eq!(
        std::fs::read_to_string(broker.path("profiles/conv2.toml")).unwrap(),
        CONV2
    );
    let (code, listed) = http_json(&broker, "/api/v1/profiles");
    assert_eq!(code, 200);
    assert_eq!(
        listed["profiles"]["conv2"]["outputs"][0]["topic"],
        "line1/conv2/position"
    );
    let mut conv2 = Dev::connect(broker.port(), 5, "conv2");
    assert_eq!(conv2.publish("line1/conv2/position", &fbdk_int(2)), 0);

    // A broker without a profiles directory says what to set.
    let plain = Broker::start();
    let file = plain.path("conv2.toml");
    std::fs::write(&file, CONV2).unwrap();
    let (ok, _, err) = common::run(
        std::process::Command::new(common::fbbus_bin()).args([
            "declare",
            file.to_str().unwrap(),
            "--admin",
            &plain.admin.to_string(),
        ]),
        Duration::from_secs(20),
    );
    assert!(!ok && err.contains("profiles_dir"), "{err}");
}

/// DINASORE's publisher FB asks for a keep-alive and never pings: a profile that says so
/// keeps its connection past the keep-alive once it speaks for the device, where any
/// other silent client is cut.
#[tokio::test(flavor = "multi_thread")]
async fn a_device_whose_runtime_never_pings_is_not_cut_for_it() {
    let broker = line();
    let connect = |id: &str| {
        Dev::try_connect(
            broker.port(),
            &common::raw::Connect {
                version: 4,
                client_id: id,
                keep_alive: 1,
                ..Default::default()
            },
        )
        .unwrap_or_else(|code| panic!("{id} refused: {code}"))
    };
    let mut conv3 = connect("paho-keepalive");
    let mut other = connect("silent-other");
    conv3.publish("line1/conv3/speed", br#"{"SPEED": "1"}"#);
    // Well past 1.5 x the keep-alive of 1 s, without a PINGREQ.
    tokio::time::sleep(Duration::from_millis(2500)).await;
    conv3.publish("line1/conv3/speed", br#"{"SPEED": "2"}"#);
    assert_eq!(record(&broker, "conv3").unwrap()["status"], "online");
    // The other client was held to its keep-alive.
    tokio::task::block_in_place(|| {
        other
            .raw
            .stream
            .set_read_timeout(Some(Duration::from_secs(5)))
            .unwrap();
        assert!(other.raw.closed_by_broker());
    });
    assert!(broker.wait_metric("fbbus_disconnects_total{reason=\"keep_alive\"}", 1.0) >= 1.0);
}

/// A profile's stated period: the device is judged silent from its first connection,
/// with no period to observe first (a FORTE whose publishers died right after a broker
/// restart publishes nothing to observe).
#[tokio::test(flavor = "multi_thread")]
async fn a_stated_period_makes_a_quiet_device_silent() {
    let profile = CONV2.replace("[will]", "[periods]\n\"CONV.POSITION\" = 200\n[will]");
    let broker = Broker::start_with(
        Options {
            extra: "[fb]\nprofiles_dir = \"profiles\"\nsilence_min_s = 0.5\n".into(),
            ..Default::default()
        },
        |dir| {
            let profiles = dir.join("profiles");
            std::fs::create_dir(&profiles).unwrap();
            std::fs::write(profiles.join("conv2.toml"), &profile).unwrap();
        },
    );
    let mut conv2 = Dev::connect(broker.port(), 5, "conv2");
    // Never publishes: silent once 3 x 200 ms (at least 0.5 s) went by.
    wait_record(&broker, "conv2", "online and silent", |r| {
        r["status"] == "online" && r["silent"] == true
    })
    .await;
    // Publishing at its period again: no longer silent (the registry judges once a
    // second, so one publication alone may fall between two judgements).
    let deadline = std::time::Instant::now() + Duration::from_secs(10);
    loop {
        assert_eq!(conv2.publish("line1/conv2/position", &fbdk_int(3)), 0);
        let r = record(&broker, "conv2").unwrap();
        if r["status"] == "online" && r["silent"] == false {
            break;
        }
        assert!(std::time::Instant::now() < deadline, "still silent: {r}");
        tokio::time::sleep(Duration::from_millis(150)).await;
    }
}

/// DINASORE opens a connection per MQTT FB, each with a random client id: the device is
/// online while any of them lives, and one ending alone does not take it offline.
#[tokio::test(flavor = "multi_thread")]
async fn a_topics_only_device_is_online_while_any_of_its_connections_lives() {
    let broker = line();
    let mut speed = Dev::connect(broker.port(), 5, "paho-speed");
    let mut note = Dev::connect(broker.port(), 5, "paho-note");
    assert_eq!(speed.publish("line1/conv3/speed", br#"{"SPEED": "1"}"#), 0);
    let first = wait_record(&broker, "conv3", "online", |r| r["status"] == "online").await;
    assert_eq!(note.publish("line1/conv3/note", br#"{"NOTE": "x"}"#), 0);
    // The first publisher's FB is deleted: the other still speaks for the device.
    speed.disconnect();
    assert_eq!(note.publish("line1/conv3/note", br#"{"NOTE": "y"}"#), 0);
    tokio::time::sleep(Duration::from_millis(300)).await;
    let r = record(&broker, "conv3").unwrap();
    assert_eq!(r["status"], "online", "{r}");
    assert_eq!(
        r["session"], first["session"],
        "one record, not one per connection"
    );
    // The last one ends: offline.
    drop(note);
    wait_record(&broker, "conv3", "offline", |r| r["status"] == "offline").await;
}

//! Issue 33, item 8: a `topics_only` device (DINASORE's MQTT FBs: random client id, no
//! username) is recognised by the topics it publishes on, so by default any client the
//! access rules let publish there speaks for it. Its profile can say who may:
//! `identity.speakers_from` (source addresses or networks) and `identity.speaker_username`.
//! A client outside them is refused (MQTT 5 0x87, named on the device's diag topic) and
//! speaks for nobody: the device stays offline; one inside is the device.

mod common;

use std::time::Duration;

use common::clients::WAIT;
use common::fb::*;
use common::raw;
use common::{add_user, Broker, Options};

const PROFILE: &str = r#"
device = "dina"
runtime = "dinasore"

[identity]
topics_only = true
speakers_from = ["127.0.0.2", "127.0.9.0/24"]

[speaks]
encoding = "dinasore"
string_numbers = true
enforce_keep_alive = false

[interface.fbs.CONV]
data_out = { SPEED = "REAL" }

[[topics]]
topic = "line1/dina/speed"
port = "CONV.SPEED"
"#;

fn line(profile: &str, auth: &str, listener: &str) -> Broker {
    let profile = profile.to_owned();
    Broker::start_with(
        Options {
            extra: format!("{auth}[fb]\nprofiles_dir = \"profiles\"\n"),
            listener_extra: listener.to_owned(),
            ..Default::default()
        },
        move |dir| {
            std::fs::create_dir_all(dir.join("profiles")).unwrap();
            std::fs::write(dir.join("profiles/dina.toml"), profile).unwrap();
            add_user(&dir.join("passwd"), "dina-runtime", "pw-runtime");
            add_user(&dir.join("passwd"), "tool", "pw-tool");
        },
    )
}

/// An MQTT 5 client with a random client id from loopback address `source`.
fn client_from(broker: &Broker, source: &str, id: &str, login: Option<(&str, &str)>) -> Dev {
    let connect = raw::Connect {
        version: 5,
        client_id: id,
        login,
        ..Default::default()
    };
    Dev::connect_from(broker, source, &connect)
}

/// `fbbus profile check` on `profile`: (passed, stderr).
fn profile_check(profile: &str) -> (bool, String) {
    let dir = tempfile::tempdir().unwrap();
    let file = dir.path().join("dina.toml");
    std::fs::write(&file, profile).unwrap();
    let (ok, _, err) = common::run(
        std::process::Command::new(common::fbbus_bin()).args([
            "profile",
            "check",
            file.to_str().unwrap(),
        ]),
        Duration::from_secs(30),
    );
    (ok, err)
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn only_the_profiles_sources_speak_for_a_topics_only_device() {
    let broker = line(PROFILE, "", "");
    let mut watch = observer(&broker, "watch", &["fbbus/diag/dina", "fb/dina/#"]).await;

    // From 127.0.0.1, not in speakers_from: refused, said on diag, nothing delivered.
    let mut stranger = client_from(&broker, "127.0.0.1", "paho-x1", None);
    assert_eq!(
        stranger.publish("line1/dina/speed", br#"{"SPEED": "1.5"}"#),
        NOT_AUTHORIZED
    );
    let (topic, body) = next_under(&mut watch, "", WAIT)
        .await
        .expect("a diagnostic");
    assert_eq!(topic, "fbbus/diag/dina");
    let diag = String::from_utf8_lossy(&body);
    assert!(
        diag.contains("lets only clients from 127.0.0.2/32, 127.0.9.0/24"),
        "{diag}"
    );
    assert!(record(&broker, "dina").is_none_or(|r| r["status"] != "online"));
    assert!(!broker.log_text().contains("it is that device"));

    // From 127.0.9.7 (in 127.0.9.0/24): accepted, delivered, the device is online.
    let mut runtime = client_from(&broker, "127.0.9.7", "paho-r2", None);
    assert_eq!(
        runtime.publish("line1/dina/speed", br#"{"SPEED": "2.5"}"#),
        0
    );
    let got = next_under(&mut watch, "fb/", WAIT).await;
    assert_eq!(
        got,
        Some(("fb/dina/CONV/SPEED".to_owned(), b"2.5".to_vec()))
    );
    let online = record(&broker, "dina").expect("dina registered");
    assert_eq!(online["status"], "online", "{online}");
    // The stranger still may not, though the device is online now.
    assert_eq!(
        stranger.publish("line1/dina/speed", br#"{"SPEED": "9"}"#),
        NOT_AUTHORIZED
    );
    assert!(drain(&mut watch, QUIET)
        .await
        .iter()
        .all(|(t, _)| t != "fb/dina/CONV/SPEED"));
}

/// `speaker_username`: only a client logged in as that user speaks for the device.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_speaker_username_admits_that_user_only() {
    let profile = PROFILE.replace(
        "speakers_from = [\"127.0.0.2\", \"127.0.9.0/24\"]",
        "speaker_username = \"dina-runtime\"",
    );
    let broker = line(
        &profile,
        "[auth]\npassword_file = \"passwd\"\n",
        "allow_anonymous = true\n",
    );
    let mut tool = client_from(&broker, "127.0.0.1", "t1", Some(("tool", "pw-tool")));
    assert_eq!(
        tool.publish("line1/dina/speed", br#"{"SPEED": "1"}"#),
        NOT_AUTHORIZED
    );
    let mut anonymous = client_from(&broker, "127.0.0.1", "a1", None);
    assert_eq!(
        anonymous.publish("line1/dina/speed", br#"{"SPEED": "1"}"#),
        NOT_AUTHORIZED
    );
    let mut runtime = client_from(
        &broker,
        "127.0.0.1",
        "r1",
        Some(("dina-runtime", "pw-runtime")),
    );
    assert_eq!(runtime.publish("line1/dina/speed", br#"{"SPEED": "2"}"#), 0);
    let online = record(&broker, "dina").expect("dina registered");
    assert_eq!(online["status"], "online", "{online}");
}

/// A bad network, or the keys on a device that is not topics-only, are profile errors.
#[test]
fn speakers_are_checked_in_the_profile() {
    let (ok, err) = profile_check(&PROFILE.replace("127.0.9.0/24", "127.0.9.0/99"));
    assert!(!ok);
    assert!(
        err.contains("identity.speakers_from[1]") && err.contains("127.0.9.0/99"),
        "{err}"
    );
    let (ok, err) = profile_check(&PROFILE.replace("topics_only = true", "client_id = \"dina\""));
    assert!(!ok);
    assert!(err.contains("are for topics_only devices"), "{err}");
    assert!(profile_check(PROFILE).0, "the test's own profile is valid");
}

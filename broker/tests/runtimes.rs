//! The runtimes as they are, on the real `fbbus` with device profiles only
//! (docs/runtimes.md): the emulators of `tests/python/` (written from 4diac FORTE's and
//! DINASORE's source, pinned against mosquitto in `runtime_emulators.rs`) run as child
//! processes against the broker, and no device ever declares anything.
//!
//! - `forte3` is a FORTE 3.x (fbdk, nanosecond dates), recognised by its client id;
//! - `forte2` is a FORTE 2.x (fbdk, millisecond dates);
//! - `dina` is a DINASORE: a random client id, so recognised by its own topics only, its
//!   numbers written as strings (`{"SPEED": "3.0"}`), one connection per MQTT FB.
//!
//! Each test starts its own broker on loopback; every wait is bounded. python3 (and
//! paho-mqtt 2.x for DINASORE) are required in CI (`CI=1`), skipped loudly elsewhere.

mod common;

use std::path::Path;
use std::time::{Duration, Instant};

use serde_json::{json, Value};

use common::bus::Python;
use common::clients::V4;
use common::fb::*;
use common::{require, require_paho, Broker, Options};

/// The longest any single expected thing may take.
const WAIT: Duration = Duration::from_secs(10);
/// How often the periodic outputs publish in the silence tests.
const PERIOD: Duration = Duration::from_millis(100);

// ------------------------------------------------------------------------- profiles

/// A FORTE 3.x device: its PUBLISH_n / SUBSCRIBE_n FBs have IDs
/// `fbdk[].mqtt[tcp://127.0.0.1:<port>, forte3, line1/forte3/<topic>]`.
const FORTE3: &str = r#"
device = "forte3"
runtime = "forte"

[identity]
client_id = "forte3"

[speaks]
encoding = "fbdk"
fbdk_time_unit = "ns"
max_payload = 255

# PUBLISH_2 on line1/forte3/pos
[interface.fbs.PUB_POS]
type = "PUBLISH_2"
events_out = { REQ = { with = ["SD_1", "SD_2"] } }
data_out = { SD_1 = "INT", SD_2 = "BOOL" }

# PUBLISH_1 on line1/forte3/speed
[interface.fbs.PUB_SPEED]
type = "PUBLISH_1"
data_out = { SD_1 = "REAL" }

# PUBLISH_1 on line1/forte3/count: INT here, but the application sends a REAL
[interface.fbs.PUB_COUNT]
type = "PUBLISH_1"
data_out = { SD_1 = "INT" }

# PUBLISH_3 on line1/forte3/at
[interface.fbs.PUB_AT]
type = "PUBLISH_3"
events_out = { REQ = { with = ["SD_1", "SD_2", "SD_3"] } }
data_out = { SD_1 = "DATE_AND_TIME", SD_2 = "TIME_OF_DAY", SD_3 = "DATE" }

# SUBSCRIBE_1 on line1/forte3/set_speed, fed by DINASORE's SPEED
[interface.fbs.SUB_SPEED]
type = "SUBSCRIBE_1"
events_in = { IND = { with = ["RD_1"] } }
data_in = { RD_1 = "REAL" }

# SUBSCRIBE_1 on line1/forte3/note, fed by DINASORE's NOTE
[interface.fbs.SUB_NOTE]
type = "SUBSCRIBE_1"
events_in = { IND = { with = ["RD_1"] } }
data_in = { RD_1 = "STRING" }

# SUBSCRIBE_3 on line1/forte3/at_in, fed by the FORTE 2.x's PUB_AT
[interface.fbs.SUB_AT]
type = "SUBSCRIBE_3"
events_in = { IND = { with = ["RD_1", "RD_2", "RD_3"] } }
data_in = { RD_1 = "DATE_AND_TIME", RD_2 = "TIME_OF_DAY", RD_3 = "DATE" }

[interface.fbs.CONV]
data_out = { CONNECT = "BOOL" }

[[topics]]
topic = "line1/forte3/pos"
port = "PUB_POS.REQ"

[[topics]]
topic = "line1/forte3/speed"
port = "PUB_SPEED.SD_1"

[[topics]]
topic = "line1/forte3/count"
port = "PUB_COUNT.SD_1"

[[topics]]
topic = "line1/forte3/at"
port = "PUB_AT.REQ"

[[topics]]
topic = "line1/forte3/set_speed"
port = "SUB_SPEED.IND"
from = "dina/CONV/SPEED"

[[topics]]
topic = "line1/forte3/note"
port = "SUB_NOTE.IND"
from = "dina/CONV/NOTE"

[[topics]]
topic = "line1/forte3/at_in"
port = "SUB_AT.IND"
from = "forte2/PUB_AT/REQ"

[will]
"CONV.CONNECT" = false
"#;

/// A FORTE 2.0.x device: dates in milliseconds.
const FORTE2: &str = r#"
device = "forte2"
runtime = "forte"

[identity]
client_id = "forte2"

[speaks]
encoding = "fbdk"
fbdk_time_unit = "ms"
max_payload = 255

[interface.fbs.PUB_AT]
type = "PUBLISH_3"
events_out = { REQ = { with = ["SD_1", "SD_2", "SD_3"] } }
data_out = { SD_1 = "DATE_AND_TIME", SD_2 = "TIME_OF_DAY", SD_3 = "DATE" }

[interface.fbs.SUB_AT]
type = "SUBSCRIBE_3"
events_in = { IND = { with = ["RD_1", "RD_2", "RD_3"] } }
data_in = { RD_1 = "DATE_AND_TIME", RD_2 = "TIME_OF_DAY", RD_3 = "DATE" }

[[topics]]
topic = "line1/forte2/at"
port = "PUB_AT.REQ"

[[topics]]
topic = "line1/forte2/at_in"
port = "SUB_AT.IND"
from = "forte3/PUB_AT/REQ"
"#;

/// A DINASORE device: MQTT_PUBLISHER FBs with VALUE_NAME SPEED, NOTE, RUNNING, and an
/// MQTT_SUBSCRIBER with VALUE_NAME POSITION fed by the FORTE's PUB_POS.
const DINA: &str = r#"
device = "dina"
runtime = "dinasore"

[identity]
topics_only = true

[speaks]
encoding = "dinasore"
string_numbers = true
enforce_keep_alive = false

[interface.fbs.CONV]
data_out = { SPEED = "REAL", NOTE = "STRING", RUNNING = "BOOL" }
events_in = { MOVED = { with = ["POSITION", "ON"] } }
data_in = { POSITION = "INT", ON = "BOOL" }

[[topics]]
topic = "line1/dina/speed"
port = "CONV.SPEED"

[[topics]]
topic = "line1/dina/note"
port = "CONV.NOTE"

[[topics]]
topic = "line1/dina/running"
port = "CONV.RUNNING"

[[topics]]
topic = "line1/dina/moved"
port = "CONV.MOVED"
from = "forte3/PUB_POS/REQ"

[will]
"CONV.RUNNING" = false
"#;

/// A broker with these profiles in its `profiles_dir` and a short silence bound
/// (`max(3 × period, 0.5 s)`).
fn line(profiles: &[&str]) -> Broker {
    Broker::start_with(
        Options {
            extra: "[fb]\nprofiles_dir = \"profiles\"\nsilence_min_s = 0.5\nsilence_factor = 3\n"
                .into(),
            ..Default::default()
        },
        |dir: &Path| {
            let dir = dir.join("profiles");
            std::fs::create_dir(&dir).unwrap();
            for (i, text) in profiles.iter().enumerate() {
                std::fs::write(dir.join(format!("{i}.toml")), text).unwrap();
            }
        },
    )
}

// ------------------------------------------------------------------------ emulators

/// One emulator process (`forte_device.py` or `dinasore_device.py`): its stdin takes
/// commands, its stdout lines are read with a timeout. Killed when dropped.
struct Emu {
    py: Python,
    who: String,
}

impl Emu {
    /// A FORTE device with client id `id` (its `fbdk[].mqtt[...]` IDs).
    fn forte(broker: &Broker, id: &str, args: &[&str]) -> Emu {
        let port = broker.port().to_string();
        let mut all = vec!["--port", &port, "--client-id", id];
        all.extend_from_slice(args);
        Emu {
            py: Python::spawn("forte_device.py", &all),
            who: id.to_owned(),
        }
    }

    /// A DINASORE device (`who` only names it in failures).
    fn dinasore(broker: &Broker, who: &str, args: &[&str]) -> Emu {
        let port = broker.port().to_string();
        let mut all = vec!["--port", &port];
        all.extend_from_slice(args);
        Emu {
            py: Python::spawn("dinasore_device.py", &all),
            who: who.to_owned(),
        }
    }

    fn send(&mut self, command: &str) {
        self.py.send(command);
    }

    /// Reads lines until one equals `want`; the lines before it.
    fn expect(&self, want: &str) -> Vec<String> {
        tokio::task::block_in_place(|| {
            let deadline = Instant::now() + WAIT;
            let mut seen = Vec::new();
            loop {
                let left = deadline.saturating_duration_since(Instant::now());
                match self.py.next_line(left) {
                    Some(line) if line == want => return seen,
                    Some(line) => seen.push(line),
                    None => panic!(
                        "{}: no line {want:?} within {WAIT:?}; it printed {seen:#?}",
                        self.who
                    ),
                }
            }
        })
    }

    /// The next line, which must be `want`.
    fn expect_next(&self, want: &str) {
        let line = tokio::task::block_in_place(|| self.py.next_line(WAIT))
            .unwrap_or_else(|| panic!("{}: no line within {WAIT:?}, expected {want:?}", self.who));
        assert_eq!(line, want, "{}: unexpected line", self.who);
    }

    /// Each of `wants`, in any order, and nothing else.
    fn expect_all(&self, wants: &[&str]) {
        let mut missing = wants.to_vec();
        while !missing.is_empty() {
            let line =
                tokio::task::block_in_place(|| self.py.next_line(WAIT)).unwrap_or_else(|| {
                    panic!(
                        "{}: nothing within {WAIT:?}, still expected {missing:?}",
                        self.who
                    )
                });
            let at = missing.iter().position(|w| *w == line).unwrap_or_else(|| {
                panic!("{}: unexpected {line:?}, expected {missing:?}", self.who)
            });
            missing.remove(at);
        }
    }

    /// Every line printed within `within` (to show what did not happen).
    fn lines_within(&self, within: Duration) -> Vec<String> {
        tokio::task::block_in_place(|| {
            let deadline = Instant::now() + within;
            let mut lines = Vec::new();
            while let Some(line) = self
                .py
                .next_line(deadline.saturating_duration_since(Instant::now()))
            {
                lines.push(line);
            }
            lines
        })
    }
}

// -------------------------------------------------------------------------- helpers

/// Bytes from hex with optional spaces between fields.
fn unhex(text: &str) -> Vec<u8> {
    let digits: String = text.split_whitespace().collect();
    (0..digits.len())
        .step_by(2)
        .map(|i| u8::from_str_radix(&digits[i..i + 2], 16).unwrap())
        .collect()
}

fn hex(bytes: &[u8]) -> String {
    bytes.iter().map(|b| format!("{b:02x}")).collect()
}

fn text(bytes: &[u8]) -> String {
    String::from_utf8_lossy(bytes).into_owned()
}

/// Everything `watch` receives until one message on each of `topics` came: (topic,
/// payload) in arrival order. A refused publication that was wrongly routed would come
/// before a later one of the same connection.
async fn until_each(watch: &mut V4, topics: &[&str], broker: &Broker) -> Vec<(String, Vec<u8>)> {
    let mut all = Vec::new();
    let deadline = Instant::now() + WAIT;
    while !topics.iter().all(|t| all.iter().any(|(got, _)| got == t)) {
        let left = deadline.saturating_duration_since(Instant::now());
        let Some(m) = next_under(watch, "", left).await else {
            panic!(
                "waiting for {topics:?}, got {all:?}\n--- broker log\n{}",
                broker.log_text()
            );
        };
        all.push(m);
    }
    all
}

/// The next `not_reencoded` diagnostic of `device` naming `topic` (others skipped).
async fn not_reencoded(watch: &mut V4, device: &str, topic: &str, broker: &Broker) -> Value {
    let deadline = Instant::now() + WAIT;
    loop {
        let d = diag(watch, device, "not_reencoded", broker).await;
        if d["topic"] == topic {
            return d;
        }
        assert!(Instant::now() < deadline, "no not_reencoded for {topic}");
    }
}

fn online(r: &Value) -> bool {
    r["status"] == "online"
}

fn offline(r: &Value) -> bool {
    r["status"] == "offline"
}

fn silent(r: &Value) -> bool {
    r["status"] == "online" && r["silent"] == true
}

fn speaking(r: &Value) -> bool {
    r["status"] == "online" && r["silent"] == false
}

/// The value of the first series of `name` whose labels contain every `labels` pair.
fn metric_with(broker: &Broker, name: &str, labels: &[&str]) -> Option<(String, f64)> {
    broker.metrics().lines().find_map(|l| {
        let (series, value) = l.rsplit_once(' ')?;
        (series.starts_with(&format!("{name}{{")) && labels.iter().all(|p| series.contains(p)))
            .then(|| (series.to_owned(), value.parse().unwrap_or(0.0)))
    })
}

/// Waits (bounded) for a series of `name` with `labels` to reach `min`.
fn wait_metric_with(broker: &Broker, name: &str, labels: &[&str], min: f64) -> String {
    let deadline = Instant::now() + WAIT;
    tokio::task::block_in_place(|| loop {
        match metric_with(broker, name, labels) {
            Some((series, v)) if v >= min => return series,
            found if Instant::now() > deadline => panic!(
                "no {name} with {labels:?} at {min} (found {found:?})\n--- metrics\n{}",
                broker.metrics()
            ),
            _ => std::thread::sleep(Duration::from_millis(50)),
        }
    })
}

// ---------------------------------------------------------------------------- FORTE

/// FORTE 3.x with a profile only: typed in all three encodings, an ill-typed publication
/// refused, online from CONNECT, offline when killed, and its profile's will published.
#[tokio::test(flavor = "multi_thread")]
async fn forte_typed_refused_registered_and_its_will() {
    if !require("python3") {
        return;
    }
    let broker = line(&[FORTE3]);
    let mut watch = observer(
        &broker,
        "watch",
        &[
            "line1/#",
            "fb/forte3/#",
            "dinasore/forte3/#",
            "fbdk/forte3/#",
            "fbbus/diag/forte3",
        ],
    )
    .await;
    assert_eq!(record(&broker, "forte3"), None, "known before it connected");

    let mut forte = Emu::forte(
        &broker,
        "forte3",
        &[
            "--pub",
            "line1/forte3/pos:INT,BOOL",
            "--pub",
            "line1/forte3/speed:REAL",
            "--pub",
            "line1/forte3/count:REAL",
        ],
    );
    forte.expect("connected");
    // Online from its CONNECT, with its profile's interface: it never declares.
    let r = wait_record(&broker, "forte3", "online at CONNECT", online).await;
    assert_eq!(r["interface"]["fbs"]["PUB_POS"]["data_out"]["SD_1"], "INT");

    // PUBLISH_2 (INT 3, BOOL TRUE) on its own topic: there as it came, and typed.
    forte.send("pub line1/forte3/pos 3 TRUE");
    forte.expect_next("sent line1/forte3/pos 43000341");
    let got = one_each(
        &mut watch,
        &[
            "line1/forte3/pos",
            "fb/forte3/PUB_POS/REQ",
            "dinasore/forte3/PUB_POS/REQ",
            "fbdk/forte3/PUB_POS/REQ",
        ],
        &broker,
    )
    .await;
    assert_eq!(got[0], unhex("43 0003 41"));
    let event = parse(&got[1]);
    assert_eq!(event["data"], json!({"SD_1": 3, "SD_2": true}), "{event}");
    assert_eq!(event["seq"], 1, "{event}");
    assert!(event["ts"].is_u64(), "{event}");
    assert_eq!(text(&got[2]), r#"{"SD_1":3,"SD_2":true}"#);
    assert_eq!(got[3], unhex("43 0003 41"));

    // PUBLISH_1 (REAL 1.5) mapped on a data port.
    forte.send("pub line1/forte3/speed REAL#1.5");
    forte.expect_next("sent line1/forte3/speed 4a3fc00000");
    let got = one_each(
        &mut watch,
        &[
            "line1/forte3/speed",
            "fb/forte3/PUB_SPEED/SD_1",
            "dinasore/forte3/PUB_SPEED/SD_1",
            "fbdk/forte3/PUB_SPEED/SD_1",
        ],
        &broker,
    )
    .await;
    assert_eq!(got[0], unhex("4a 3fc00000"));
    assert_eq!(text(&got[1]), "1.5");
    assert_eq!(text(&got[2]), r#"{"SD_1":1.5}"#);
    assert_eq!(got[3], unhex("4a 3fc00000"));

    // Its application publishes a REAL where its profile says INT: refused. FORTE speaks
    // QoS 0 over MQTT 3.1.1, so it is told nothing on its connection: counted, and
    // described on fbbus/diag/forte3.
    forte.send("pub line1/forte3/count 2.5");
    forte.expect_next("sent line1/forte3/count 4a40200000");
    let rejected = diag(&mut watch, "forte3", "rejected", &broker).await;
    assert_eq!(rejected["topic"], "line1/forte3/count", "{rejected}");
    assert_eq!(rejected["reason"], "payload_format_invalid", "{rejected}");
    assert_eq!(rejected["code"], 0x99, "{rejected}");
    wait_metric_with(
        &broker,
        "fbbus_typed_messages_rejected_total",
        &["device=\"forte3\"", "reason=\"payload_format_invalid\""],
        1.0,
    );
    // Nothing of it was delivered: the next publication arrives with nothing before it.
    forte.send("pub line1/forte3/pos 4 FALSE");
    forte.expect_next("sent line1/forte3/pos 43000440");
    let seen = until_each(
        &mut watch,
        &[
            "line1/forte3/pos",
            "fb/forte3/PUB_POS/REQ",
            "fbdk/forte3/PUB_POS/REQ",
        ],
        &broker,
    )
    .await;
    assert!(
        seen.iter()
            .all(|(t, _)| !t.contains("count") && !t.contains("PUB_COUNT")),
        "the refused publication was delivered: {seen:?}"
    );

    // Killed (no DISCONNECT, no will of its own): offline, and the broker publishes the
    // profile's will on its typed port, in every encoding.
    forte.send("kill");
    let r = wait_record(&broker, "forte3", "offline after kill", offline).await;
    assert!(r["last_will_reason"].is_string(), "{r}");
    let got = one_each(
        &mut watch,
        &[
            "fb/forte3/CONV/CONNECT",
            "dinasore/forte3/CONV/CONNECT",
            "fbdk/forte3/CONV/CONNECT",
        ],
        &broker,
    )
    .await;
    assert_eq!(text(&got[0]), "false");
    assert_eq!(text(&got[1]), r#"{"CONNECT":false}"#);
    assert_eq!(got[2], [0x40]);
}

/// FORTE's publish FB dies after a failed send (a network cut) while its connection comes
/// back: with a periodic output, the registry shows it `online, silent`; an INIT of the
/// FB makes it speak again.
#[tokio::test(flavor = "multi_thread")]
async fn forte_publisher_dead_after_a_network_cut_is_silent() {
    if !require("python3") {
        return;
    }
    let broker = line(&[FORTE3]);
    let mut forte = Emu::forte(&broker, "forte3", &["--pub", "line1/forte3/pos:INT,BOOL"]);
    forte.expect("connected");
    wait_record(&broker, "forte3", "online", online).await;

    // A cyclic PUBLISH_2: 8 values 100 ms apart give its REQ a period.
    for i in 0..8 {
        forte.send(&format!("pub line1/forte3/pos {i} TRUE"));
        forte.expect_next(&format!("sent line1/forte3/pos 4300{i:02x}41"));
        tokio::time::sleep(PERIOD).await;
    }
    let r = record(&broker, "forte3").unwrap();
    assert!(speaking(&r), "{r}");

    // The network goes away for 1 s; the next REQ finds no connection: SEND_FAILED, and
    // the FB is dead. The connection comes back, the FB stays dead.
    forte.send("drop 1");
    forte.expect_next("disconnected dropped");
    forte.send("pub line1/forte3/pos 8 TRUE");
    forte.expect_next("error line1/forte3/pos SEND_FAILED");
    forte.expect("connected");
    forte.send("pub line1/forte3/pos 9 TRUE");
    forte.expect_next("error line1/forte3/pos NO_SOCKET");

    // Online (its connection is back), silent (its periodic output stopped).
    let r = wait_record(&broker, "forte3", "online, silent", silent).await;
    assert!(r["silent_since"].is_string(), "{r}");
    assert_metric(&broker, "fbbus_registry_silent_devices", 1.0);

    // INIT (QI = TRUE) revives the FB: it speaks again.
    forte.send("init line1/forte3/pos");
    forte.expect_next("inited line1/forte3/pos");
    speak_until_speaking(&broker, "forte3", |i| {
        forte.send(&format!("pub line1/forte3/pos {i} TRUE"));
        forte.expect_next(&format!("sent line1/forte3/pos 4300{i:02x}41"));
    })
    .await;
}

/// Publishes (`publish(i)`) every [`PERIOD`] until the registry shows `device` speaking:
/// the registry judges once a second, and one publication is "speaking" only for the
/// bound (0.5 s here).
async fn speak_until_speaking(broker: &Broker, device: &str, mut publish: impl FnMut(u32)) {
    let deadline = Instant::now() + WAIT;
    for i in 10.. {
        publish(i);
        if record(broker, device).is_some_and(|r| speaking(&r)) {
            return;
        }
        assert!(
            Instant::now() < deadline,
            "{device} never shown speaking again: {:?}",
            record(broker, device)
        );
        tokio::time::sleep(PERIOD).await;
    }
}

/// DATE, TIME_OF_DAY and DATE_AND_TIME between a FORTE 2.x (milliseconds) and a FORTE
/// 3.x (nanoseconds), each fed the other's PUBLISH_3 through an input topic, and on `fb/`
/// as IEC literals.
#[tokio::test(flavor = "multi_thread")]
async fn forte_dates_between_2x_and_3x() {
    if !require("python3") {
        return;
    }
    let broker = line(&[FORTE3, FORTE2]);
    let mut watch = observer(
        &broker,
        "watch",
        &[
            "line1/#",
            "fb/+/PUB_AT/REQ",
            "fbdk/+/PUB_AT/REQ",
            "fbbus/diag/forte2",
        ],
    )
    .await;
    let at = "DT,TOD,DATE";
    let f3 = format!("line1/forte3/at:{at}");
    let f3_in = format!("line1/forte3/at_in:{at}");
    let mut forte3 = Emu::forte(&broker, "forte3", &["--pub", &f3, "--sub", &f3_in]);
    let f2 = format!("line1/forte2/at:{at}");
    let f2_in = format!("line1/forte2/at_in:{at}");
    let ms = ["--time-unit", "ms", "--tz", "utc"];
    let mut forte2 = Emu::forte(
        &broker,
        "forte2",
        &[&["--pub", &f2, "--sub", &f2_in][..], &ms[..]].concat(),
    );
    forte3.expect("subscribed line1/forte3/at_in");
    forte2.expect("subscribed line1/forte2/at_in");

    // 2.x -> 3.x: milliseconds in, nanoseconds out.
    let values = "DT#2026-11-22-12:30:15.250 TOD#12:30:15.250 D#2026-11-22";
    let in_ms = "4f 000001a2033c54d2 4e 0000000002aee0d2 4d 000001a2008d7400";
    let in_ns = "4f 18ea5ddf55415880 4e 000028f0edfc5880 4d 18ea34ee67450000";
    forte2.send(&format!("pub line1/forte2/at {values}"));
    forte2.expect_next(&format!("sent line1/forte2/at {}", hex(&unhex(in_ms))));
    forte3.expect_next(&format!("recv line1/forte3/at_in {values}"));
    let got = one_each(
        &mut watch,
        &[
            "line1/forte2/at",
            "fb/forte2/PUB_AT/REQ",
            "fbdk/forte2/PUB_AT/REQ",
            "line1/forte3/at_in",
        ],
        &broker,
    )
    .await;
    assert_eq!(got[0], unhex(in_ms));
    assert_eq!(
        parse(&got[1])["data"],
        json!({"SD_1": "DT#2026-11-22-12:30:15.250", "SD_2": "TOD#12:30:15.250", "SD_3": "D#2026-11-22"})
    );
    // fbdk/ is in the line's unit ([fb] fbdk_time_unit, ns by default).
    assert_eq!(got[2], unhex(in_ns));
    assert_eq!(got[3], unhex(in_ns));

    // 3.x -> 2.x: nanoseconds in, milliseconds out.
    let values = "DT#1999-12-31-23:59:59.999 TOD#00:00:00.001 D#2000-02-29";
    let in_ns = "4f 0d234ccf5233bdc0 4e 00000000000f4240 4d 0d35690ccf780000";
    let in_ms = "4f 000000dc6acfabff 4e 0000000000000001 4d 000000dd9aa6e000";
    forte3.send(&format!("pub line1/forte3/at {values}"));
    forte3.expect_next(&format!("sent line1/forte3/at {}", hex(&unhex(in_ns))));
    forte2.expect_next(&format!("recv line1/forte2/at_in {values}"));
    let got = one_each(
        &mut watch,
        &[
            "fb/forte3/PUB_AT/REQ",
            "fbdk/forte3/PUB_AT/REQ",
            "line1/forte2/at_in",
        ],
        &broker,
    )
    .await;
    assert_eq!(
        parse(&got[0])["data"],
        json!({"SD_1": "DT#1999-12-31-23:59:59.999", "SD_2": "TOD#00:00:00.001", "SD_3": "D#2000-02-29"})
    );
    assert_eq!(got[1], unhex(in_ns));
    assert_eq!(got[2], unhex(in_ms));

    // As documented, a profile's unit governs its own topics only: a FORTE 2.x whose ID
    // names its typed topic directly (`fbdk[].mqtt[..., fbdk/forte2/PUB_AT/REQ]`) is read
    // in the line's unit (ns here), and its midnight DATE in milliseconds is refused.
    drop(forte2); // killed: the same client id connects again below
    let mut direct = Emu::forte(
        &broker,
        "forte2",
        &[
            &["--pub", "fbdk/forte2/PUB_AT/REQ:DT,TOD,DATE"][..],
            &ms[..],
        ]
        .concat(),
    );
    direct.expect("connected");
    direct.send(
        "pub fbdk/forte2/PUB_AT/REQ DT#2026-11-22-12:30:15.250 TOD#12:30:15.250 D#2026-11-22",
    );
    direct.expect_next(
        "sent fbdk/forte2/PUB_AT/REQ 4f000001a2033c54d24e0000000002aee0d24d000001a2008d7400",
    );
    let rejected = diag(&mut watch, "forte2", "rejected", &broker).await;
    assert_eq!(rejected["topic"], "fbdk/forte2/PUB_AT/REQ", "{rejected}");
    assert!(
        rejected["detail"]
            .as_str()
            .is_some_and(|d| d.contains("not midnight")),
        "{rejected}"
    );
}

/// FORTE's subscription takes 255 bytes at most: a longer STRING (from a DINASORE
/// publisher) never reaches its input topic, the publisher is told, and FORTE's stream
/// stays intact.
#[tokio::test(flavor = "multi_thread")]
async fn forte_never_receives_more_than_255_bytes() {
    if !require_paho() {
        return;
    }
    let broker = line(&[FORTE3, DINA]);
    let mut watch = observer(&broker, "watch", &["fbbus/diag/dina", "line1/forte3/note"]).await;
    let forte = Emu::forte(&broker, "forte3", &["--sub", "line1/forte3/note:STRING"]);
    forte.expect("subscribed line1/forte3/note");
    let mut dina = Emu::dinasore(&broker, "dina", &["--pub", "line1/dina/note:NOTE"]);
    dina.expect("connected");

    // 252 characters: tag, length, 252 bytes = 255, the most FORTE takes in.
    let fits = "y".repeat(252);
    dina.send(&format!("pub line1/dina/note '{fits}'"));
    dina.expect_next(&format!(r#"sent line1/dina/note {{"NOTE": "{fits}"}}"#));
    forte.expect_next(&format!("recv line1/forte3/note '{fits}'"));
    let got = one_each(&mut watch, &["line1/forte3/note"], &broker).await;
    assert_eq!(got[0].len(), 255);

    // 253 characters, and 127 two-byte characters (the limit is in bytes): not sent.
    let long = "x".repeat(253);
    let wide = "é".repeat(127);
    // (json.dumps escapes every non-ASCII character)
    for (value, json) in [(&long, long.clone()), (&wide, "\\u00e9".repeat(127))] {
        dina.send(&format!("pub line1/dina/note '{value}'"));
        dina.expect_next(&format!(r#"sent line1/dina/note {{"NOTE": "{json}"}}"#));
        let d = not_reencoded(&mut watch, "dina", "line1/forte3/note", &broker).await;
        assert_eq!(d["namespace"], "profile", "{d}");
        assert!(
            d["detail"]
                .as_str()
                .unwrap_or_default()
                .contains("max_payload"),
            "{d}"
        );
    }
    wait_metric_with(
        &broker,
        "fbbus_typed_messages_not_reencoded_total",
        &["namespace=\"profile\""],
        2.0,
    );

    // A short value after them is received whole: no corrupted or pending stream before.
    dina.send("pub line1/dina/note 'ok'");
    forte.expect_next("recv line1/forte3/note 'ok'");
    let got = one_each(&mut watch, &["line1/forte3/note"], &broker).await;
    assert_eq!(got[0], unhex("50 0002 6f6b"));
}

// ------------------------------------------------------------------------- DINASORE

/// DINASORE with a profile only: its `{"SPEED": "3.0"}` typed in all three encodings,
/// `"3"` accepted on a REAL and `"True"` on a BOOL, an ill-typed value refused, online
/// from its first accepted publication, its keep-alive not enforced, offline when killed,
/// and its profile's will published.
#[tokio::test(flavor = "multi_thread")]
async fn dinasore_typed_refused_registered_and_its_will() {
    if !require_paho() {
        return;
    }
    let broker = line(&[DINA]);
    let mut watch = observer(
        &broker,
        "watch",
        &[
            "line1/#",
            "fb/dina/#",
            "dinasore/dina/#",
            "fbdk/dina/#",
            "fbbus/diag/#",
        ],
    )
    .await;
    let mut dina = Emu::dinasore(
        &broker,
        "dina",
        &[
            "--pub",
            "line1/dina/speed:SPEED",
            "--pub",
            "line1/dina/running:RUNNING",
        ],
    );
    dina.expect("connected");
    // Connected, but nothing says which device it is yet.
    tokio::time::sleep(Duration::from_millis(300)).await;
    assert_eq!(record(&broker, "dina"), None);

    dina.send("pub line1/dina/speed 3.0");
    dina.expect_next(r#"sent line1/dina/speed {"SPEED": "3.0"}"#);
    let got = one_each(
        &mut watch,
        &[
            "line1/dina/speed",
            "fb/dina/CONV/SPEED",
            "dinasore/dina/CONV/SPEED",
            "fbdk/dina/CONV/SPEED",
        ],
        &broker,
    )
    .await;
    assert_eq!(text(&got[0]), r#"{"SPEED": "3.0"}"#);
    assert_eq!(text(&got[1]), "3.0");
    assert_eq!(text(&got[2]), r#"{"SPEED":3.0}"#);
    assert_eq!(got[3], unhex("4a 40400000"));
    // Its first accepted publication made that connection the device: online.
    let r = wait_record(&broker, "dina", "online from its publication", online).await;
    assert_eq!(r["interface"]["fbs"]["CONV"]["data_out"]["SPEED"], "REAL");

    // "3" (an int's str()) is a REAL too; "True" a BOOL.
    dina.send("pub line1/dina/speed 3");
    dina.expect_next(r#"sent line1/dina/speed {"SPEED": "3"}"#);
    let got = one_each(
        &mut watch,
        &[
            "line1/dina/speed",
            "fb/dina/CONV/SPEED",
            "fbdk/dina/CONV/SPEED",
        ],
        &broker,
    )
    .await;
    assert_eq!(text(&got[0]), r#"{"SPEED": "3"}"#);
    assert_eq!(text(&got[1]), "3.0");
    assert_eq!(got[2], unhex("4a 40400000"));
    dina.send("pub line1/dina/running True");
    dina.expect_next(r#"sent line1/dina/running {"RUNNING": "True"}"#);
    let got = one_each(
        &mut watch,
        &[
            "fb/dina/CONV/RUNNING",
            "dinasore/dina/CONV/RUNNING",
            "fbdk/dina/CONV/RUNNING",
        ],
        &broker,
    )
    .await;
    assert_eq!(text(&got[0]), "true");
    assert_eq!(text(&got[1]), r#"{"RUNNING":true}"#);
    assert_eq!(got[2], [0x41]);

    // Not a number: refused (QoS 0: DINASORE is told nothing), counted, described.
    dina.send("pub line1/dina/speed 'fast'");
    dina.expect_next(r#"sent line1/dina/speed {"SPEED": "fast"}"#);
    let rejected = diag(&mut watch, "dina", "rejected", &broker).await;
    assert_eq!(rejected["topic"], "line1/dina/speed", "{rejected}");
    assert_eq!(rejected["reason"], "payload_format_invalid", "{rejected}");
    wait_metric_with(
        &broker,
        "fbbus_typed_messages_rejected_total",
        &["device=\"dina\"", "reason=\"payload_format_invalid\""],
        1.0,
    );
    dina.send("pub line1/dina/speed 4.5");
    dina.expect_next(r#"sent line1/dina/speed {"SPEED": "4.5"}"#);
    let seen = until_each(
        &mut watch,
        &["line1/dina/speed", "fb/dina/CONV/SPEED"],
        &broker,
    )
    .await;
    assert!(
        seen.iter().all(|(_, p)| !text(p).contains("fast")),
        "the refused publication was delivered: {seen:?}"
    );

    // Its publisher FB asks keep-alive 60 and never pings; its profile says so, so its
    // connection is not held to it (90 s are not waited here: the broker's log says it,
    // and the connection still carries the next value).
    assert!(
        broker.log_text().contains("keep-alive not enforced"),
        "{}",
        broker.log_text()
    );
    dina.send("pub line1/dina/speed 5");
    dina.expect_next(r#"sent line1/dina/speed {"SPEED": "5"}"#);
    let got = one_each(&mut watch, &["fb/dina/CONV/SPEED"], &broker).await;
    assert_eq!(text(&got[0]), "5.0");
    assert!(online(&record(&broker, "dina").unwrap()));

    // Killed (its sockets reset by the kernel, no DISCONNECT): offline, and the broker
    // publishes the profile's will.
    dina.send("kill");
    let r = wait_record(&broker, "dina", "offline after kill", offline).await;
    assert!(r["last_will_reason"].is_string(), "{r}");
    let got = one_each(
        &mut watch,
        &["fb/dina/CONV/RUNNING", "dinasore/dina/CONV/RUNNING"],
        &broker,
    )
    .await;
    assert_eq!(text(&got[0]), "false");
    assert_eq!(text(&got[1]), r#"{"RUNNING":false}"#);
    // Once, though two connections (one per publisher FB) spoke for it.
    let again = next_on(&mut watch, "fb/dina/CONV/RUNNING", QUIET).await;
    assert_eq!(again, None, "the will was published twice");
}

/// A DINASORE publisher that stops publishing (its connection lives on): silent.
#[tokio::test(flavor = "multi_thread")]
async fn dinasore_publisher_that_stops_is_silent() {
    if !require_paho() {
        return;
    }
    let broker = line(&[DINA]);
    let mut dina = Emu::dinasore(&broker, "dina", &["--pub", "line1/dina/speed:SPEED"]);
    dina.expect("connected");
    for i in 0..8 {
        dina.send(&format!("pub line1/dina/speed {i}.5"));
        dina.expect_next(&format!(r#"sent line1/dina/speed {{"SPEED": "{i}.5"}}"#));
        tokio::time::sleep(PERIOD).await;
    }
    let r = wait_record(&broker, "dina", "online", online).await;
    assert!(speaking(&r), "{r}");
    let r = wait_record(&broker, "dina", "online, silent", silent).await;
    assert!(r["silent_since"].is_string(), "{r}");
    speak_until_speaking(&broker, "dina", |i| {
        dina.send(&format!("pub line1/dina/speed {i}.5"));
        dina.expect_next(&format!(r#"sent line1/dina/speed {{"SPEED": "{i}.5"}}"#));
    })
    .await;
}

// ------------------------------------------------------------------ wired together

/// FORTE and DINASORE through fbbus, each fed the other's output on its own input topic
/// in its own encoding: FORTE's PUBLISH_2 reaches DINASORE's MQTT_SUBSCRIBER, which reads
/// `float()`; DINASORE's `{"SPEED": "2.5"}` reaches FORTE's SUBSCRIBE_1 as an fbdk REAL.
#[tokio::test(flavor = "multi_thread")]
async fn forte_and_dinasore_wired_through_fbbus() {
    if !require_paho() {
        return;
    }
    let broker = line(&[FORTE3, DINA]);
    let mut watch = observer(
        &broker,
        "watch",
        &["line1/#", "fb/forte3/CONV/CONNECT", "fb/dina/CONV/RUNNING"],
    )
    .await;
    // Its SUBSCRIBE_1 on its own input topic, and one whose ID names DINASORE's typed
    // topic directly (no mapping needed).
    let mut forte = Emu::forte(
        &broker,
        "forte3",
        &[
            "--pub",
            "line1/forte3/pos:INT,BOOL",
            "--sub",
            "line1/forte3/set_speed:REAL",
            "--sub",
            "fbdk/dina/CONV/SPEED:REAL",
        ],
    );
    forte.expect("subscribed line1/forte3/set_speed");
    forte.expect("subscribed fbdk/dina/CONV/SPEED");
    let mut dina = Emu::dinasore(
        &broker,
        "dina",
        &[
            "--pub",
            "line1/dina/speed:SPEED",
            "--sub",
            "line1/dina/moved:POSITION",
        ],
    );
    dina.expect_all(&["connected", "subscribed line1/dina/moved"]);

    // FORTE -> DINASORE: {"POSITION": 3, "ON": true}, read as float 3.0.
    forte.send("pub line1/forte3/pos 3 TRUE");
    forte.expect_next("sent line1/forte3/pos 43000341");
    dina.expect_next("recv line1/dina/moved 3.0");
    let got = one_each(&mut watch, &["line1/dina/moved"], &broker).await;
    assert_eq!(text(&got[0]), r#"{"POSITION":3,"ON":true}"#);
    forte.send("pub line1/forte3/pos -7 FALSE");
    forte.expect_next("sent line1/forte3/pos 43fff940");
    dina.expect_next("recv line1/dina/moved -7.0");

    // DINASORE -> FORTE: its strings as fbdk REALs.
    for (value, real, bytes) in [
        ("2.5", "REAL#2.5", "4a 40200000"),
        ("3", "REAL#3.0", "4a 40400000"),
        ("-0.1", "REAL#-0.1", "4a bdcccccd"),
    ] {
        dina.send(&format!("pub line1/dina/speed {value}"));
        dina.expect_next(&format!(r#"sent line1/dina/speed {{"SPEED": "{value}"}}"#));
        forte.expect_all(&[
            &format!("recv line1/forte3/set_speed {real}"),
            &format!("recv fbdk/dina/CONV/SPEED {real}"),
        ]);
        let got = one_each(&mut watch, &["line1/forte3/set_speed"], &broker).await;
        assert_eq!(got[0], unhex(bytes));
    }
    // Both are online, neither declared.
    assert!(online(&record(&broker, "forte3").unwrap()));
    assert!(online(&record(&broker, "dina").unwrap()));
    assert!(forte.lines_within(Duration::from_millis(200)).is_empty());

    // FORTE stops cleanly (its MQTTHandler sends DISCONNECT): offline, and, as an MQTT
    // will, its profile's will is not published (issue 30: a profile asks for the
    // reference line's rule with `liveness.will_on_clean_disconnect`). DINASORE's stop
    // calls each FB's `disconnect()`, which its loop-less publisher may or may not get
    // onto the wire before the process exits: either way it is offline.
    forte.send("quit");
    wait_record(&broker, "forte3", "offline", offline).await;
    dina.send("quit");
    wait_record(&broker, "dina", "offline", offline).await;
    assert_eq!(
        next_on(&mut watch, "fb/forte3/CONV/CONNECT", QUIET * 3).await,
        None,
        "a clean DISCONNECT fired forte3's profile will"
    );
}

// ------------------------------------------------------------------ refusals, where they are told

/// A refusal on a profile's own output topic is counted with the port the profile maps
/// there (`PUB_COUNT.SD_1`), as on a typed topic. (Found by this test: it was counted as
/// `port="undeclared"`.)
#[tokio::test(flavor = "multi_thread")]
async fn refusal_on_an_own_topic_is_counted_with_its_port() {
    if !require("python3") {
        return;
    }
    let broker = line(&[FORTE3]);
    let mut watch = observer(&broker, "watch", &["fbbus/diag/forte3"]).await;
    let mut forte = Emu::forte(&broker, "forte3", &["--pub", "line1/forte3/count:REAL"]);
    forte.expect("connected");
    forte.send("pub line1/forte3/count 2.5");
    forte.expect_next("sent line1/forte3/count 4a40200000");
    let rejected = diag(&mut watch, "forte3", "rejected", &broker).await;
    assert!(
        rejected["detail"]
            .as_str()
            .is_some_and(|d| d.contains("PUB_COUNT.SD_1")),
        "{rejected}"
    );
    assert_metric(
        &broker,
        &rejected_series("forte3", "PUB_COUNT.SD_1", "payload_format_invalid"),
        1.0,
    );
}

/// A DINASORE whose first publication is ill-typed (its application publishes text,
/// `nan`, or `True` on a REAL) is told so on `fbbus/diag/dina`, counted as `dina`, and
/// online: the topic, its profile's own, says which device it is. (Found by this test:
/// the refusal went to the random client id the broker assigned it, and a DINASORE whose
/// every value was refused was never online.)
#[tokio::test(flavor = "multi_thread")]
async fn a_topics_only_device_first_refusal_is_described_under_its_id() {
    if !require_paho() {
        return;
    }
    let broker = line(&[DINA]);
    let mut watch = observer(&broker, "watch", &["fbbus/diag/#"]).await;
    let mut dina = Emu::dinasore(&broker, "dina", &["--pub", "line1/dina/speed:SPEED"]);
    dina.expect("connected");
    dina.send("pub line1/dina/speed 'fast'");
    dina.expect_next(r#"sent line1/dina/speed {"SPEED": "fast"}"#);
    let (topic, body) = next_under(&mut watch, "fbbus/diag/", WAIT)
        .await
        .expect("a diagnostic");
    assert_eq!(topic, "fbbus/diag/dina", "{}", text(&body));
    wait_metric_with(
        &broker,
        "fbbus_typed_messages_rejected_total",
        &["device=\"dina\"", "reason=\"payload_format_invalid\""],
        1.0,
    );
}

// -------------------------------------------------- who speaks for a topics-only device

/// DINA with a stated period on SPEED, a short silence allowance, and (when `reference`)
/// the reference line's will rule: every departure is a disconnection.
fn dina_liveness(offline_after_s: u64, reference: bool) -> String {
    format!(
        "{DINA}\n[periods]\n\"CONV.SPEED\" = 100\n\n[liveness]\n\
         offline_after_silent_s = {offline_after_s}\nwill_on_clean_disconnect = {reference}\n"
    )
}

/// A refused publication on a topics-only device's own topic speaks for nobody: an
/// anonymous MQTT 5 client publishing `{"SPEED":"abc"}` on DINASORE `dina`'s own topic is
/// refused 0x99, described under `dina`, and changes nothing: no record, its keep-alive
/// still enforced, and no will when it leaves (cleanly or not). (Issue 30: the registry
/// showed `dina` online with the intruder's session and fired its will at its DISCONNECT.)
#[tokio::test(flavor = "multi_thread")]
async fn a_refused_publication_speaks_for_nobody() {
    let broker = line(&[DINA]);
    let mut watch = observer(&broker, "watch", &["fb/dina/#", "fbbus/diag/#"]).await;
    let mut intruder = Dev::connect(broker.port(), 5, "intruder");
    assert_eq!(
        intruder.publish("line1/dina/speed", br#"{"SPEED":"abc"}"#),
        0x99
    );
    let rejected = diag(&mut watch, "dina", "rejected", &broker).await;
    assert_eq!(rejected["reason"], "payload_format_invalid", "{rejected}");
    assert_eq!(
        record(&broker, "dina"),
        None,
        "a refused value registered dina"
    );
    assert!(
        !broker.log_text().contains("keep-alive not enforced"),
        "{}",
        broker.log_text()
    );
    intruder.disconnect();
    // Another one, cut without DISCONNECT: no will either (it never was the device).
    let mut second = Dev::connect(broker.port(), 4, "intruder-2");
    second.publish("line1/dina/speed", br#"{"SPEED":"fast"}"#);
    drop(second);
    assert_eq!(
        next_on(&mut watch, "fb/dina/CONV/RUNNING", QUIET * 3).await,
        None
    );
    assert_eq!(record(&broker, "dina"), None);

    // The same client with an accepted value is the device (the rule's other half).
    let mut tool = Dev::connect(broker.port(), 5, "tool");
    assert_eq!(tool.publish("line1/dina/speed", br#"{"SPEED":"2.5"}"#), 0);
    wait_record(&broker, "dina", "online from an accepted value", online).await;
}

/// The broker-side will follows MQTT's rule: a client that had an accepted value on
/// DINASORE `dina`'s own topic (so it spoke for it) and leaves with a clean DISCONNECT (a
/// short-lived tool) takes the device offline without its will; cut off, its will fires
/// (`dinasore_typed_refused_registered_and_its_will`: DINASORE itself never sends
/// DISCONNECT). With the reference line's `liveness.will_on_clean_disconnect = true`, a
/// clean departure fires it too.
#[tokio::test(flavor = "multi_thread")]
async fn the_profile_will_follows_mqtt_unless_the_profile_says_otherwise() {
    for reference in [false, true] {
        let profile = dina_liveness(0, reference);
        let broker = line(&[&profile]);
        let mut watch = observer(&broker, "watch", &["fb/dina/CONV/RUNNING"]).await;
        let mut tool = Dev::connect(broker.port(), 4, "tool");
        assert_eq!(tool.publish("line1/dina/speed", br#"{"SPEED":"1.5"}"#), 0);
        wait_record(&broker, "dina", "online", online).await;
        tool.disconnect();
        let r = wait_record(&broker, "dina", "offline after a clean DISCONNECT", offline).await;
        assert_eq!(r["last_will_reason"], "clean disconnect", "{r}");
        let will = next_on(&mut watch, "fb/dina/CONV/RUNNING", QUIET * 3).await;
        match reference {
            false => assert_eq!(will, None, "the will fired on a clean DISCONNECT"),
            true => assert_eq!(
                will.as_deref(),
                Some(&b"false"[..]),
                "reference line: no will"
            ),
        }
    }
}

/// Silence can end a device: a DINASORE whose runtime is frozen (SIGSTOP: its publisher
/// never pings, so keep-alive cannot notice) is offline once its periodic output has been
/// quiet for `liveness.offline_after_silent_s`, with its will, its reason and the metric;
/// its connection stays open, and when the runtime goes on, its next value brings it back.
#[tokio::test(flavor = "multi_thread")]
async fn a_frozen_dinasore_is_offline_after_its_silence_allowance() {
    if !require_paho() {
        return;
    }
    let profile = dina_liveness(2, false);
    let broker = line(&[&profile]);
    let mut watch = observer(&broker, "watch", &["fb/dina/CONV/RUNNING"]).await;
    let mut dina = Emu::dinasore(&broker, "dina", &["--pub", "line1/dina/speed:SPEED"]);
    dina.expect("connected");
    for i in 0..5 {
        dina.send(&format!("pub line1/dina/speed {i}.5"));
        dina.expect_next(&format!(r#"sent line1/dina/speed {{"SPEED": "{i}.5"}}"#));
        tokio::time::sleep(PERIOD).await;
    }
    wait_record(&broker, "dina", "online", online).await;
    let frozen = Instant::now();
    dina.py.signal("STOP");
    let r = wait_record(&broker, "dina", "offline for its silence", offline).await;
    let took = frozen.elapsed();
    dina.py.signal("CONT");
    assert!(
        r["last_will_reason"]
            .as_str()
            .is_some_and(|s| s.starts_with("silent")),
        "{r}"
    );
    // 2 s allowance, judged every second, polled every 25 ms.
    assert!(
        took >= Duration::from_secs(2) && took < Duration::from_secs(5),
        "{took:?}"
    );
    let will = next_on(&mut watch, "fb/dina/CONV/RUNNING", WAIT).await;
    assert_eq!(will.as_deref(), Some(&b"false"[..]));
    assert_metric(&broker, "fbbus_registry_silence_offline_total", 1.0);
    // Going on: its next value (on the connection that stayed open) brings it back.
    dina.send("pub line1/dina/speed 9.5");
    dina.expect_next(r#"sent line1/dina/speed {"SPEED": "9.5"}"#);
    let r = wait_record(&broker, "dina", "online again", online).await;
    assert!(r["last_will_reason"].is_null(), "{r}");
    assert_eq!(
        next_on(&mut watch, "fb/dina/CONV/RUNNING", QUIET).await,
        None
    );
}

/// A DINASORE runtime that only subscribes (MQTT_SUBSCRIBER FBs only) is online while its
/// subscriber connection listens on its input topic and offline, with its will, when that
/// connection is lost; that connection is still held to its keep-alive (its paho loop
/// pings). A subscription to another topic makes nobody a device.
#[tokio::test(flavor = "multi_thread")]
async fn a_subscribe_only_dinasore_is_online_while_it_listens() {
    if !require_paho() {
        return;
    }
    let broker = line(&[DINA]);
    let mut watch = observer(&broker, "watch", &["fb/dina/CONV/RUNNING"]).await;
    let mut other = V4::connect(broker.port(), "reader", None).await.unwrap();
    other.subscribe("line1/dina/speed").await;
    tokio::time::sleep(QUIET).await;
    assert_eq!(
        record(&broker, "dina"),
        None,
        "a reader of an output is no device"
    );

    let mut dina = Emu::dinasore(&broker, "dina", &["--sub", "line1/dina/moved:POSITION"]);
    // The SUBACK may be handled by paho's network thread before INIT returns and
    // "connected" is printed: either order.
    dina.expect_all(&["connected", "subscribed line1/dina/moved"]);
    let r = wait_record(&broker, "dina", "online from its subscription", online).await;
    assert_eq!(r["interface"]["fbs"]["CONV"]["data_in"]["POSITION"], "INT");
    assert!(
        !broker.log_text().contains("keep-alive not enforced"),
        "{}",
        broker.log_text()
    );
    dina.send("kill");
    let r = wait_record(&broker, "dina", "offline after kill", offline).await;
    assert!(r["last_will_reason"].is_string(), "{r}");
    let will = next_on(&mut watch, "fb/dina/CONV/RUNNING", WAIT).await;
    assert_eq!(will.as_deref(), Some(&b"false"[..]));
}

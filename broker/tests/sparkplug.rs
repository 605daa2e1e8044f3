//! The line as a Sparkplug B edge node (issue 36), read by independent Sparkplug
//! implementations: Python `pysparkplug` (`tests/python/sparkplug_host.py`) and Eclipse
//! Tahu's JavaScript decoder, npm `sparkplug-payload` (`tests/js/sparkplug_host.js`),
//! each a host application driven over stdin/stdout against the real `fbbus` binary.
//!
//! Covered: births, data and deaths of a JSON-declared device with every IEC elementary
//! type and arrays, a DINASORE-profile and a FORTE-profile device; `seq` and `bdSeq`
//! across a device kill, a line restart by SIGKILL and a rebirth request; a DCMD
//! delivered typed to a declared and to a FORTE-profile device, and refused for an output
//! port, a wrong type and a host the ACL does not allow; the plant engineer's
//! `deploy/sparkplug/line_view.py` printing the line from Sparkplug alone.
//!
//! python3 with paho-mqtt and pysparkplug, node with the npm packages: required in CI
//! (`.ci/run` installs them), skipped loudly elsewhere.

mod common;

use std::collections::HashMap;
use std::io::{BufRead, BufReader, Write};
use std::path::Path;
use std::process::{Child, ChildStdin, Command, Stdio};
use std::sync::mpsc;
use std::time::{Duration, Instant};

use common::fb::Dev;
use common::{Broker, Options};
use serde_json::{json, Value};

const WAIT: Duration = Duration::from_secs(15);

/// Every IEC elementary type and three arrays, on one FB.
const TYPES: &str = r#"{"fbs": {"ALL": {"data_out": {
    "B": "BOOL", "SI": "SINT", "I": "INT", "DI": "DINT", "LI": "LINT",
    "USI": "USINT", "UI": "UINT", "UDI": "UDINT", "ULI": "ULINT",
    "R": "REAL", "LR": "LREAL", "BY": "BYTE", "W": "WORD", "DW": "DWORD", "LW": "LWORD",
    "S": "STRING", "WS": "WSTRING", "T": "TIME", "D": "DATE", "TOD": "TIME_OF_DAY",
    "DT": "DATE_AND_TIME",
    "AI": "ARRAY [3] OF INT", "AB": "ARRAY [3] OF BOOL", "AS": "ARRAY [2] OF STRING"}}}}"#;

/// (port, JSON published on fb/, Sparkplug datatype id, what pysparkplug decodes, the raw
/// protobuf field's value).
fn type_cases() -> Vec<(&'static str, Value, u64, Value, Value)> {
    vec![
        ("B", json!(true), 11, json!(true), json!(true)),
        // Negative Int8/16/32: sign-extended to 32 bits in int_value (Tahu's Java form),
        // which pysparkplug 0.6.1 cannot decode (its value is null, the raw field says).
        ("SI", json!(-5), 1, Value::Null, json!(4294967291u64)),
        ("I", json!(-300), 2, Value::Null, json!(4294966996u64)),
        ("DI", json!(-70000), 3, Value::Null, json!(4294897296u64)),
        (
            "LI",
            json!(-9000000000i64),
            4,
            json!(-9000000000i64),
            json!(18446744064709551616u64),
        ),
        ("USI", json!(200), 5, json!(200), json!(200)),
        ("UI", json!(60000), 6, json!(60000), json!(60000)),
        (
            "UDI",
            json!(4000000000u64),
            7,
            json!(4000000000u64),
            json!(4000000000u64),
        ),
        (
            "ULI",
            json!(18446744073709551615u64),
            8,
            json!(18446744073709551615u64),
            json!(18446744073709551615u64),
        ),
        ("R", json!(1.5), 9, json!(1.5), json!(1.5)),
        ("LR", json!(-2.25), 10, json!(-2.25), json!(-2.25)),
        ("BY", json!(255), 5, json!(255), json!(255)),
        ("W", json!(65535), 6, json!(65535), json!(65535)),
        (
            "DW",
            json!(4294967295u64),
            7,
            json!(4294967295u64),
            json!(4294967295u64),
        ),
        ("LW", json!(1), 8, json!(1), json!(1)),
        (
            "S",
            json!("héllo €"),
            12,
            json!("héllo €"),
            json!("héllo €"),
        ),
        ("WS", json!("wïde"), 12, json!("wïde"), json!("wïde")),
        // TIME: Int64 microseconds.
        ("T", json!("T#1s500ms"), 4, json!(1500000), json!(1500000)),
        // DATE, DATE_AND_TIME: DateTime, ms since the epoch (UTC).
        (
            "D",
            json!("D#2026-11-22"),
            13,
            json!(1795305600000u64),
            json!(1795305600000u64),
        ),
        (
            "TOD",
            json!("TOD#12:30:15.250"),
            7,
            json!(45015250),
            json!(45015250),
        ),
        (
            "DT",
            json!("DT#2026-11-22-12:30:15.250"),
            13,
            json!(1795350615250u64),
            json!(1795350615250u64),
        ),
        // Arrays: Int16Array, BooleanArray, StringArray, packed little-endian in bytes.
        (
            "AI",
            json!([1, -2, 3]),
            23,
            json!([1, -2, 3]),
            json!("0100feff0300"),
        ),
        (
            "AB",
            json!([true, false, true]),
            32,
            json!([true, false, true]),
            json!("03000000a0"),
        ),
        (
            "AS",
            json!(["a", "bc"]),
            33,
            json!(["a", "bc"]),
            json!("6100626300"),
        ),
    ]
}

/// A FORTE device as its profile says (deploy/profiles/conv2-forte.toml, trimmed): an
/// `fbdk` event output on its own topic, and SUB_SPEED.IND (WITH RD_1 REAL) read on
/// `line1/conv2/speed`.
const FORTE: &str = r#"device = "conv2"
runtime = "forte"
[identity]
client_id = "conv2"
[speaks]
encoding = "fbdk"
[interface.fbs.PUB_POS]
events_out = { REQ = { with = ["SD_1"] } }
data_out = { SD_1 = "INT" }
[interface.fbs.SUB_SPEED]
events_in = { IND = { with = ["RD_1"] } }
data_in = { RD_1 = "REAL" }
[[topics]]
topic = "line1/conv2/position"
port = "PUB_POS.REQ"
[[topics]]
topic = "line1/conv2/speed"
port = "SUB_SPEED.IND"
from = "conv3/CONV/SPEED"
"#;

/// A DINASORE device as its profile says: `{"SPEED": "3"}` JSON on its own topics.
const DINASORE: &str = r#"device = "conv3"
runtime = "dinasore"
[identity]
client_id = "conv3"
[speaks]
encoding = "dinasore"
string_numbers = true
[interface.fbs.CONV]
data_out = { SPEED = "REAL" }
[[topics]]
topic = "line1/conv3/speed"
port = "CONV.SPEED"
"#;

/// A Sparkplug host application: one of the scripts, its JSON lines in, commands out.
struct Host {
    child: Child,
    stdin: ChildStdin,
    lines: mpsc::Receiver<Value>,
    name: &'static str,
    /// Every message line so far, in order.
    seen: Vec<Value>,
    /// `seen[..taken]` were passed over or returned by [`Host::message`].
    taken: usize,
}

impl Host {
    fn python(broker: &Broker, args: &[&str]) -> Option<Host> {
        if !common::require_paho() || !python_has("pysparkplug") {
            return None;
        }
        let script = format!(
            "{}/tests/python/sparkplug_host.py",
            env!("CARGO_MANIFEST_DIR")
        );
        let mut cmd = Command::new("python3");
        cmd.arg("-u").arg(script);
        Some(Host::spawn(cmd, "pysparkplug", broker, args))
    }

    fn tahu(broker: &Broker, args: &[&str]) -> Option<Host> {
        if !common::require("node") {
            return None;
        }
        common::npm_file("sparkplug-payload/package.json")?;
        let npm = common::npm_file("mqtt/package.json")?;
        let modules = npm.parent()?.parent()?.parent()?.to_path_buf();
        let script = format!("{}/tests/js/sparkplug_host.js", env!("CARGO_MANIFEST_DIR"));
        let mut cmd = Command::new("node");
        cmd.arg(script).env("FBBUS_NPM_DIR", modules);
        Some(Host::spawn(cmd, "tahu-js", broker, args))
    }

    fn spawn(mut cmd: Command, name: &'static str, broker: &Broker, args: &[&str]) -> Host {
        cmd.args(["--host", "127.0.0.1", "--port", &broker.port().to_string()])
            .args(args)
            .stdin(Stdio::piped())
            .stdout(Stdio::piped())
            .stderr(Stdio::inherit());
        let mut child = cmd
            .spawn()
            .unwrap_or_else(|e| panic!("cannot run {name}: {e}"));
        let stdin = child.stdin.take().unwrap();
        let stdout = child.stdout.take().unwrap();
        let (tx, lines) = mpsc::channel();
        std::thread::spawn(move || {
            for line in BufReader::new(stdout).lines().map_while(Result::ok) {
                let value = serde_json::from_str(&line)
                    .unwrap_or_else(|_| json!({"event": "unparsed", "line": line}));
                if tx.send(value).is_err() {
                    return;
                }
            }
        });
        let mut host = Host {
            child,
            stdin,
            lines,
            name,
            seen: Vec::new(),
            taken: 0,
        };
        host.expect("ready", |v| v["event"] == "ready");
        // The first reader's births come 250 ms after its SUBSCRIBE (the view waits for
        // the subscription to be in force), and values meanwhile go into them, not into
        // DDATA: a test publishing values waits that out.
        std::thread::sleep(Duration::from_millis(1000));
        host
    }

    fn send(&mut self, command: Value) {
        writeln!(self.stdin, "{command}").unwrap();
        self.stdin.flush().unwrap();
    }

    /// The next line `pred` accepts (earlier ones are kept in `seen`).
    fn expect(&mut self, what: &str, pred: impl Fn(&Value) -> bool) -> Value {
        let deadline = Instant::now() + WAIT;
        loop {
            let left = deadline.saturating_duration_since(Instant::now());
            match self.lines.recv_timeout(left) {
                Ok(v) => {
                    if v["event"] == "message" {
                        self.seen.push(v.clone());
                    }
                    if pred(&v) {
                        return v;
                    }
                }
                Err(_) => panic!(
                    "{}: no {what} within {WAIT:?}; seen:\n{}",
                    self.name,
                    self.seen
                        .iter()
                        .map(|v| format!("{} seq={} {}", v["topic"], v["seq"], v["metrics"]))
                        .collect::<Vec<_>>()
                        .join("\n")
                ),
            }
        }
    }

    /// The next message of `kind` on `node_device` (`line-1`, `line-1/dev`) after the last
    /// one this returned: from those already seen, else waiting for it.
    fn message(&mut self, kind: &str, node_device: &str) -> Value {
        let topic = format!("spBv1.0/fbbus/{kind}/{node_device}");
        let earlier = self.seen[self.taken..]
            .iter()
            .position(|v| v["topic"] == topic);
        if let Some(i) = earlier {
            self.taken += i + 1;
            return self.seen[self.taken - 1].clone();
        }
        let found = self.expect(&topic.clone(), move |v| {
            v["event"] == "message" && v["topic"] == topic
        });
        self.taken = self.seen.len();
        found
    }

    fn puback(&mut self) -> u64 {
        let v = self.expect("puback", |v| v["event"] == "puback");
        v["reason_code"].as_u64().unwrap()
    }
}

impl Drop for Host {
    fn drop(&mut self) {
        let _ = writeln!(self.stdin, "{}", json!({"op": "quit"}));
        let deadline = Instant::now() + Duration::from_secs(3);
        while Instant::now() < deadline {
            if let Ok(Some(_)) = self.child.try_wait() {
                return;
            }
            std::thread::sleep(Duration::from_millis(20));
        }
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

fn python_has(module: &str) -> bool {
    let ok = Command::new("python3")
        .args(["-c", &format!("import {module}")])
        .stdout(Stdio::null())
        .stderr(Stdio::null())
        .status()
        .is_ok_and(|s| s.success());
    if !ok {
        assert!(
            std::env::var_os("CI").is_none(),
            "python3 has no {module}; .ci/run should have installed it"
        );
        eprintln!("SKIPPED: python3 has no {module}");
    }
    ok
}

/// A line with the view on, the two profiled devices, and `extra` config.
fn line(extra: &str, prepare: impl FnOnce(&Path)) -> Broker {
    Broker::start_with(
        Options {
            line: "line-1".into(),
            extra: format!("[fb]\nprofiles_dir = \"profiles\"\n{extra}"),
            tables: "[sparkplug]\nenabled = true\n".into(),
            ..Default::default()
        },
        |dir| {
            let profiles = dir.join("profiles");
            std::fs::create_dir(&profiles).unwrap();
            std::fs::write(profiles.join("conv2.toml"), FORTE).unwrap();
            std::fs::write(profiles.join("conv3.toml"), DINASORE).unwrap();
            prepare(dir)
        },
    )
}

/// The metric named `name` of a birth.
fn metric<'a>(message: &'a Value, name: &str) -> &'a Value {
    message["metrics"]
        .as_array()
        .and_then(|m| m.iter().find(|m| m["name"] == name))
        .unwrap_or_else(|| panic!("no metric {name} in {message}"))
}

/// The `bdSeq` of an NBIRTH or NDEATH.
fn bdseq(message: &Value) -> u64 {
    let m = metric(message, "bdSeq");
    m["value"]
        .as_u64()
        .or_else(|| m["value"].as_str().and_then(|s| s.parse().ok()))
        .unwrap_or_else(|| panic!("bdSeq of {message}"))
}

/// Every message of each node after its NBIRTH carries the next `seq`, 0-255 wrapping;
/// NDEATH none.
fn assert_sequences(host: &Host) {
    let mut next: HashMap<String, u64> = HashMap::new();
    for m in &host.seen {
        let node = m["node"].as_str().unwrap_or_default().to_owned();
        match m["type"].as_str() {
            Some("NDEATH") => {
                assert!(m["seq"].is_null(), "{}: NDEATH with a seq: {m}", host.name);
                next.remove(&node);
            }
            Some("NBIRTH") => {
                assert_eq!(m["seq"], 0, "{}: {m}", host.name);
                next.insert(node, 1);
            }
            // Commands are the hosts', not the node's.
            Some("NCMD" | "DCMD") => {}
            Some(_) => {
                if let Some(expected) = next.get_mut(&node) {
                    assert_eq!(m["seq"], *expected, "{}: {m}", host.name);
                    *expected = (*expected + 1) % 256;
                }
            }
            None => {}
        }
    }
}

#[tokio::test(flavor = "multi_thread")]
async fn both_decoders_read_births_data_and_deaths_of_every_type_and_runtime() {
    let broker = line("", |_| {});
    let (Some(mut py), Some(mut js)) = (Host::python(&broker, &[]), Host::tahu(&broker, &[]))
    else {
        return;
    };
    // Births already published reach nobody (QoS 0, not retained): a rebirth gives them.
    for host in [&mut py, &mut js] {
        host.send(json!({"op": "rebirth", "group": "fbbus", "node": "line-1"}));
        let birth = host.message("NBIRTH", "line-1");
        assert_eq!(birth["seq"], 0);
        assert_eq!(metric(&birth, "Node Control/Rebirth")["value"], false);
    }

    // A JSON device with every type declares; the FORTE and DINASORE devices connect.
    let mut types = Dev::connect(broker.port(), 5, "types");
    assert_eq!(types.declare(TYPES), 0);
    let mut conv2 = Dev::connect(broker.port(), 4, "conv2");
    let mut conv3 = Dev::connect(broker.port(), 4, "conv3");
    for host in [&mut py, &mut js] {
        let birth = host.message("DBIRTH", "line-1/types");
        for (port, _, datatype, _, _) in type_cases() {
            let m = metric(&birth, &format!("ALL/{port}"));
            assert_eq!(m["datatype_id"], datatype, "{}: ALL/{port}: {m}", host.name);
            assert!(m["alias"].is_number(), "{m}");
        }
        let forte = host.message("DBIRTH", "line-1/conv2");
        assert_eq!(metric(&forte, "PUB_POS/SD_1")["datatype_id"], 2);
        assert_eq!(metric(&forte, "SUB_SPEED/RD_1")["datatype_id"], 9);
        assert_eq!(metric(&forte, "PUB_POS/REQ")["datatype_id"], 8);
        let dinasore = host.message("DBIRTH", "line-1/conv3");
        assert_eq!(metric(&dinasore, "CONV/SPEED")["datatype_id"], 9);
    }

    // Every type's value, as each decoder reads it.
    for (port, value, _, decoded, raw) in type_cases() {
        assert_eq!(
            types.publish(
                &format!("fb/types/ALL/{port}"),
                value.to_string().as_bytes()
            ),
            0,
            "{port}"
        );
        let data = py.message("DDATA", "line-1/types");
        let wire = &data["raw_metrics"][0];
        assert!(
            wire["name"].is_null() && wire["alias"].is_number(),
            "DDATA by alias: {wire}"
        );
        let m = &data["metrics"][0];
        if !decoded.is_null() {
            assert_eq!(m["value"], decoded, "pysparkplug, ALL/{port}: {m}");
        }
        assert_eq!(m["raw"]["value"], raw, "raw protobuf, ALL/{port}: {m}");
        let data = js.message("DDATA", "line-1/types");
        let m = &data["metrics"][0];
        // Tahu JS reads the sign-extended negatives and UInt32 in long_value (where fbbus
        // writes it), and no array type, so those are checked above only.
        match port {
            "SI" | "I" | "DI" => assert_eq!(m["value"], value, "tahu-js, ALL/{port}: {m}"),
            "B" | "USI" | "UI" | "UDI" | "R" | "LR" | "S" | "WS" | "BY" | "W" | "DW" | "TOD" => {
                assert_eq!(m["value"], decoded, "tahu-js, ALL/{port}: {m}")
            }
            _ => {}
        }
    }

    // The FORTE device's fbdk event, and the DINASORE device's string number.
    assert_eq!(
        conv2.publish("line1/conv2/position", &[0x43, 0xff, 0xf9]),
        0
    );
    let data = py.message("DDATA", "line-1/conv2");
    let values: Vec<&Value> = data["metrics"]
        .as_array()
        .unwrap()
        .iter()
        .map(|m| &m["raw"]["value"])
        .collect();
    assert!(
        values.contains(&&json!(4294967289u64)),
        "SD_1 = -7 sign-extended: {data}"
    );
    assert_eq!(
        conv3.publish("line1/conv3/speed", br#"{"SPEED": "3.5"}"#),
        0
    );
    let data = js.message("DDATA", "line-1/conv3");
    assert_eq!(data["metrics"][0]["value"], 3.5);

    // conv2 dies abruptly: DDEATH. Back: DBIRTH with its last value.
    drop(conv2);
    for host in [&mut py, &mut js] {
        host.message("DDEATH", "line-1/conv2");
    }
    let _conv2 = Dev::connect(broker.port(), 4, "conv2");
    let birth = py.message("DBIRTH", "line-1/conv2");
    assert_eq!(
        metric(&birth, "PUB_POS/SD_1")["raw"]["value"],
        4294967289u64
    );

    // Every message of the node in sequence, for both decoders.
    types.disconnect();
    for host in [&mut py, &mut js] {
        host.message("DDEATH", "line-1/types");
        assert_sequences(host);
    }
    common::fb::assert_metric(
        &broker,
        "fbbus_sparkplug_messages_total{kind=\"DDATA\"}",
        26.0,
    );
}

#[tokio::test(flavor = "multi_thread")]
async fn bdseq_pairs_births_and_deaths_across_a_sigkill_and_a_rebirth() {
    let mut broker = line("", |_| {});
    let Some(mut host) = Host::python(&broker, &[]) else {
        return;
    };
    host.send(json!({"op": "rebirth", "group": "fbbus", "node": "line-1"}));
    let first = host.message("NBIRTH", "line-1");
    let bd = bdseq(&first);
    let mut dev = Dev::connect(broker.port(), 5, "types");
    assert_eq!(dev.declare(TYPES), 0);
    host.message("DBIRTH", "line-1/types");
    assert_eq!(dev.publish("fb/types/ALL/I", b"7"), 0);
    host.message("DDATA", "line-1/types");
    assert_sequences(&host);
    drop(host);
    drop(dev);

    // Killed: no NDEATH can come from the dead broker. At restart, the old session's
    // death first, then the next session's birth.
    broker.signal("KILL");
    common::wait_until(&mut broker.child, Duration::from_secs(10)).expect("killed");
    let mut host = {
        // A host that stays subscribed through the restart: a persistent session on
        // the restarted broker is not what Sparkplug hosts do; it connects again.
        broker.start_again();
        Host::python(&broker, &[]).unwrap()
    };
    host.send(json!({"op": "rebirth", "group": "fbbus", "node": "line-1"}));
    let second = host.message("NBIRTH", "line-1");
    assert_eq!(
        bdseq(&second),
        (bd + 1) % 256,
        "a new session after a restart"
    );
    // The restart's own NDEATH(bd) and NBIRTH(bd+1) went out before this host connected;
    // a host that connected in between sees them: checked on the next restart below.
    let watcher = Host::python(&broker, &[]).unwrap();
    drop(host);
    broker.signal("TERM");
    common::wait_until(&mut broker.child, Duration::from_secs(10)).expect("stopped");
    let mut watcher = watcher;
    let death = watcher.message("NDEATH", "line-1");
    assert_eq!(
        bdseq(&death),
        (bd + 1) % 256,
        "a clean shutdown's NDEATH: {death}"
    );
    assert!(death["seq"].is_null());

    // Rebirth keeps the bdSeq and starts seq at 0.
    broker.start_again();
    let mut host = Host::python(&broker, &[]).unwrap();
    host.send(json!({"op": "rebirth", "group": "fbbus", "node": "line-1"}));
    let third = host.message("NBIRTH", "line-1");
    assert_eq!(bdseq(&third), (bd + 2) % 256);
    host.send(json!({"op": "rebirth", "group": "fbbus", "node": "line-1"}));
    let again = host.message("NBIRTH", "line-1");
    assert_eq!(
        (bdseq(&again), again["seq"].as_u64()),
        (bdseq(&third), Some(0))
    );
    assert_sequences(&host);
}

#[tokio::test(flavor = "multi_thread")]
async fn a_primary_host_coming_online_gets_every_birth() {
    let broker = line("", |_| {});
    let broker = {
        drop(broker);
        Broker::start_with(
            Options {
                line: "line-1".into(),
                tables: "[sparkplug]\nenabled = true\nprimary_host = \"scada\"\n".into(),
                ..Default::default()
            },
            |_| {},
        )
    };
    let mut dev = Dev::connect(broker.port(), 5, "types");
    assert_eq!(dev.declare(TYPES), 0);
    // A first reader gets the births when it subscribes.
    let Some(mut watcher) = Host::python(&broker, &[]) else {
        return;
    };
    watcher.message("NBIRTH", "line-1");
    watcher.message("DBIRTH", "line-1/types");
    // The primary host comes online (STATE): every node is born again, for everyone.
    let scada = Host::python(&broker, &["--host-id", "scada"]).unwrap();
    let again = watcher.message("NBIRTH", "line-1");
    assert_eq!(again["seq"], 0);
    watcher.message("DBIRTH", "line-1/types");
    drop(scada);
}

/// A line with passwords and an ACL: `scada` may write the conveyors' inputs, `viewer`
/// may send commands but write no input.
fn commanded_line() -> Broker {
    let acl =
        "user scada\ntopic read spBv1.0/#\ntopic write spBv1.0/#\ntopic write fb/+/CONV/SPEED\n\
               topic write fb/conv2/SUB_SPEED/#\n\
               user viewer\ntopic read spBv1.0/#\ntopic write spBv1.0/#\n\
               pattern write fbbus/declare/%u\npattern write fb/%u/#\npattern read fb/%u/#\n\
               pattern read fbbus/diag/%u\npattern write line1/%u/#\npattern read line1/%u/#\n";
    Broker::start_with(
        Options {
            line: "line-1".into(),
            extra: "[auth]\npassword_file = \"passwd\"\nacl_file = \"acl\"\n\
                    [fb]\nprofiles_dir = \"profiles\"\n"
                .into(),
            tables: "[sparkplug]\nenabled = true\ncommands = true\n".into(),
            ..Default::default()
        },
        |dir| {
            for user in ["scada", "viewer", "belt", "conv2"] {
                common::add_user(&dir.join("passwd"), user, "pw");
            }
            std::fs::write(dir.join("acl"), acl).unwrap();
            let profiles = dir.join("profiles");
            std::fs::create_dir(&profiles).unwrap();
            std::fs::write(profiles.join("conv2.toml"), FORTE).unwrap();
        },
    )
}

/// `id` logged in with its own name as username (password `pw`).
fn login(broker: &Broker, version: u8, id: &str) -> Dev {
    Dev::connect_from(
        broker,
        "127.0.0.1",
        &common::raw::Connect {
            version,
            client_id: id,
            login: Some((id, "pw")),
            ..Default::default()
        },
    )
}

/// Subscribes `dev` to `filter` at QoS 0 and waits for the SUBACK.
fn subscribe(dev: &mut Dev, filter: &str) {
    let pkid = dev.next_pkid();
    dev.raw
        .send(&common::raw::subscribe(dev.version, pkid, &[filter]));
    loop {
        let (byte1, body) = dev.raw.read_packet().expect("SUBACK");
        if byte1 == 0x90 {
            assert_eq!(
                common::raw::suback_codes(dev.version, &body),
                vec![0],
                "{filter}"
            );
            return;
        }
    }
}

/// The next QoS 0 PUBLISH `dev` receives within `within`: (topic, payload).
fn next_publish(dev: &mut Dev, within: Duration) -> Option<(String, Vec<u8>)> {
    dev.raw.stream.set_read_timeout(Some(within)).unwrap();
    let deadline = Instant::now() + within;
    while Instant::now() < deadline {
        let (byte1, body) = dev.raw.read_packet()?;
        if byte1 & 0xF0 != 0x30 {
            continue;
        }
        let (topic, payload) = if dev.version == 5 {
            let (topic, _, _, payload) = common::raw::parse_publish_v5(byte1, &body);
            (topic, payload)
        } else {
            let len = u16::from_be_bytes([body[0], body[1]]) as usize;
            (body[2..2 + len].to_vec(), body[2 + len..].to_vec())
        };
        return Some((String::from_utf8(topic).unwrap(), payload));
    }
    None
}

#[tokio::test(flavor = "multi_thread")]
async fn a_dcmd_reaches_an_input_typed_and_is_refused_otherwise() {
    let broker = commanded_line();
    let scada_login = ["--username", "scada", "--password", "pw"];
    let Some(mut scada) = Host::python(&broker, &scada_login) else {
        return;
    };
    let mut viewer = Host::python(
        &broker,
        &[
            "--username",
            "viewer",
            "--password",
            "pw",
            "--client-id",
            "viewer",
        ],
    )
    .unwrap();

    // A declared device with an input, reading its own input topic.
    let mut belt = login(&broker, 5, "belt");
    assert_eq!(
        belt.declare(
            r#"{"fbs": {"CONV": {"data_out": {"POSITION": "INT"}, "data_in": {"SPEED": "REAL"}}}}"#
        ),
        0
    );
    subscribe(&mut belt, "fb/belt/CONV/SPEED");
    scada.message("DBIRTH", "line-1/belt");

    let dcmd = |metrics: Value| json!({"op": "dcmd", "group": "fbbus", "node": "line-1", "device": "belt", "qos": 1, "metrics": metrics});
    // Typed and authorized: delivered in canonical JSON.
    scada.send(dcmd(
        json!([{"name": "CONV/SPEED", "datatype": "Float", "value": 2.5}]),
    ));
    assert_eq!(scada.puback(), 0);
    let (topic, payload) = next_publish(&mut belt, WAIT).expect("the command's value");
    assert_eq!(
        (topic.as_str(), payload.as_slice()),
        ("fb/belt/CONV/SPEED", &b"2.5"[..])
    );

    // An output: only the device sets it.
    scada.send(dcmd(
        json!([{"name": "CONV/POSITION", "datatype": "Int16", "value": 1}]),
    ));
    assert_eq!(scada.puback(), 0x87);
    // A wrong type: an Int16 for a REAL.
    scada.send(dcmd(
        json!([{"name": "CONV/SPEED", "datatype": "Int16", "value": 1}]),
    ));
    assert_eq!(scada.puback(), 0x99);
    // A host the ACL does not let write the input.
    viewer.send(dcmd(
        json!([{"name": "CONV/SPEED", "datatype": "Float", "value": 9.0}]),
    ));
    assert_eq!(viewer.puback(), 0x87);
    // What a stranger sends: not protobuf, another line's node, a device nobody has.
    scada.send(json!({"op": "publish", "topic": "spBv1.0/fbbus/DCMD/line-1/belt", "qos": 1, "payload_hex": "ffff0a0b0c"}));
    assert_eq!(scada.puback(), 0x99);
    for (node, device) in [("line-2", "belt"), ("line-1", "ghöst€")] {
        scada.send(
            json!({"op": "dcmd", "group": "fbbus", "node": node, "device": device, "qos": 1,
            "metrics": [{"name": "CONV/SPEED", "datatype": "Float", "value": 1.0}]}),
        );
        assert_eq!(scada.puback(), 0x90, "{node}/{device}");
    }
    // Nothing of those reached the device.
    assert!(next_publish(&mut belt, Duration::from_millis(300)).is_none());
    // And the line still takes a good command.
    scada.send(dcmd(
        json!([{"name": "CONV/SPEED", "datatype": "Float", "value": -0.5}]),
    ));
    assert_eq!(scada.puback(), 0);
    let (_, payload) = next_publish(&mut belt, WAIT).expect("the command's value");
    assert_eq!(payload, b"-0.5");
    // A client may not speak for the line's node.
    viewer.send(json!({"op": "publish", "topic": "spBv1.0/fbbus/NDEATH/line-1", "qos": 1, "payload_hex": ""}));
    assert_eq!(viewer.puback(), 0x87);

    // The FORTE device reads SUB_SPEED.IND (WITH RD_1) on its own topic in fbdk bytes:
    // writing RD_1 fires IND with it.
    let mut conv2 = login(&broker, 4, "conv2");
    subscribe(&mut conv2, "line1/conv2/speed");
    scada.message("DBIRTH", "line-1/conv2");
    scada.send(
        json!({"op": "dcmd", "group": "fbbus", "node": "line-1", "device": "conv2", "qos": 1,
        "metrics": [{"name": "SUB_SPEED/RD_1", "datatype": "Float", "value": 1.5}]}),
    );
    assert_eq!(scada.puback(), 0);
    let (topic, payload) = next_publish(&mut conv2, WAIT).expect("the command in fbdk");
    assert_eq!(topic, "line1/conv2/speed");
    let mut fbdk = vec![0x4A];
    fbdk.extend(1.5f32.to_be_bytes());
    assert_eq!(payload, fbdk);

    for (result, min) in [
        ("delivered", 3.0),
        ("port", 1.0),
        ("type", 1.0),
        ("not_authorized", 2.0),
        ("malformed", 1.0),
        ("device", 2.0),
    ] {
        common::fb::assert_metric(
            &broker,
            &format!("fbbus_sparkplug_commands_total{{result=\"{result}\"}}"),
            min,
        );
    }
}

#[tokio::test(flavor = "multi_thread")]
async fn the_conveyor_line_seen_through_sparkplug_alone() {
    if !common::require_paho() || !python_has("pysparkplug") {
        return;
    }
    let example = common::fb::conveyor_example();
    let broker = line("", |_| {});
    // The plant engineer's script, a host that knows nothing of fbbus, watches while the
    // conveyor example (fb-bridge/examples/conveyor) runs its line.
    let script = format!(
        "{}/../deploy/sparkplug/line_view.py",
        env!("CARGO_MANIFEST_DIR")
    );
    let port = broker.port().to_string();
    let mut view = Command::new("python3");
    view.args([
        script.as_str(),
        "--host",
        "127.0.0.1",
        "--port",
        &port,
        "--once",
        "6",
    ]);
    let view = std::thread::spawn(move || common::run(&mut view, Duration::from_secs(30)));
    std::thread::sleep(Duration::from_millis(1000));
    let mut conveyor = Command::new(&example);
    conveyor.args([
        "--host",
        "127.0.0.1",
        "--port",
        &port,
        "--count",
        "3",
        "--parts",
        "1",
    ]);
    let conveyor = std::thread::spawn(move || common::run(&mut conveyor, Duration::from_secs(120)));
    let (ok, out, err) = view.join().unwrap();
    assert!(ok, "line_view.py failed\n{out}\n{err}");
    eprintln!("{out}");
    for expected in [
        "conveyor-a",
        "conveyor-b",
        "conveyor-c",
        "CONV/POSITION",
        "CONV/SENSOR_IN",
        "CONV/STATE",
    ] {
        assert!(
            out.contains(expected),
            "no {expected} in line_view's table:\n{out}"
        );
    }
    // conveyor-b was unplugged abruptly: its will's CONNECT = FALSE came before its death.
    assert!(
        out.lines()
            .any(|l| l.contains("conveyor-b") && l.contains("CONV/CONNECT = false")),
        "conveyor-b's will not seen:\n{out}"
    );
    let (ok, out, err) = conveyor.join().unwrap();
    assert!(ok, "the conveyor line failed:\n{out}\n{err}");
}

#[tokio::test(flavor = "multi_thread")]
async fn another_line_is_an_edge_node_that_dies_when_its_broker_is_killed() {
    use common::bus::{Line, CONV, PROPAGATION};
    let sparkplug = |_: &Path| "[sparkplug]\nenabled = true\n".to_owned();
    let a = Line::start_with("line-a", &common::bus::tcp_endpoint(), &[], "", sparkplug);
    let b = Line::plain("line-b", &[&a.zenoh], "");
    let Some(mut host) = Host::python(&a.broker, &[]) else {
        return;
    };
    // A device of line-b: line-a's view shows it under line-b's own node.
    let mut press = Dev::connect(b.port(), 5, "press");
    assert_eq!(press.declare(CONV), 0);
    a.wait_record("press", "online", PROPAGATION);
    let birth = host.message("NBIRTH", "line-b");
    host.message("DBIRTH", "line-b/press");
    // line-b's broker is killed: no NDEATH can come from it; line-a's view says it when
    // the bus loses the line.
    b.broker.kill_now();
    let death = host.message("NDEATH", "line-b");
    assert_eq!(
        bdseq(&death),
        bdseq(&birth),
        "the death of that session: {death}"
    );
    assert!(
        host.seen
            .iter()
            .all(|m| m["topic"] != "spBv1.0/fbbus/DDEATH/line-b/press"),
        "the node's death is its devices' death"
    );
    assert_sequences(&host);
    drop(press);
}

#[tokio::test(flavor = "multi_thread")]
async fn the_view_reads_nothing_until_a_host_reads_sparkplug() {
    let broker = line("", |_| {});
    let mut dev = Dev::connect(broker.port(), 5, "types");
    assert_eq!(dev.declare(TYPES), 0);
    for i in 0..5 {
        assert_eq!(dev.publish("fb/types/ALL/I", i.to_string().as_bytes()), 0);
    }
    // A retained value: the view gets it when it starts reading.
    assert_eq!(dev.publish_retained("fb/types/ALL/UI", b"42"), 0);
    std::thread::sleep(Duration::from_millis(300));
    assert_eq!(
        broker.metric("fbbus_sparkplug_messages_total{kind=\"DDATA\"}"),
        0.0
    );
    // A host subscribes: every birth, unasked, with the retained value.
    let Some(mut host) = Host::python(&broker, &[]) else {
        return;
    };
    host.message("NBIRTH", "line-1");
    let birth = host.message("DBIRTH", "line-1/types");
    assert_eq!(metric(&birth, "ALL/UI")["value"], 42, "{birth}");
    assert_eq!(
        metric(&birth, "ALL/I")["is_null"],
        true,
        "not retained: not kept"
    );
    assert!(
        host.seen.iter().all(|m| m["type"] != "DDATA"),
        "no data before the births"
    );
}

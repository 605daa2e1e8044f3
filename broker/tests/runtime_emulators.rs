//! The runtime emulators of `tests/python/` checked against what the real runtimes put on
//! the wire, with Debian's mosquitto as the broker (loopback only) and a raw listener
//! where the exact bytes of a connection matter:
//!
//! - `forte_device.py`: 4diac FORTE's MQTT layer over Paho C. Its CONNECT is Paho C's
//!   (3.1.1, clean session, keep-alive 20, the fixed client id, no will), with Paho C's
//!   fallback to MQTT 3.1 after a failed attempt; its `fbdk` payloads are pinned here
//!   byte for byte against hand-written expectations; a message longer than FORTE's
//!   255-byte receive buffer is reported corrupted and wedges the subscriber; a publisher
//!   whose REQ finds no connection is dead until INIT.
//! - `dinasore_device.py`: DINASORE's MQTT_PUBLISHER / MQTT_SUBSCRIBER on paho: empty
//!   client id, keep-alive 60, `{"SPEED": "3"}` payloads, `float()` on the way in and a
//!   dead FB after a value `float()` refuses.
//!
//! mosquitto, mosquitto_sub, python3 (and paho-mqtt 2.x for DINASORE) are required in
//! CI (`CI=1`), skipped loudly elsewhere.

mod common;

use std::io::{BufRead, BufReader, Read, Write};
use std::net::{Shutdown, TcpListener, TcpStream};
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::sync::mpsc;
use std::time::{Duration, Instant};

use common::bus::Python;
use common::{free_port, have, require, require_paho};

const WAIT: Duration = Duration::from_secs(10);

/// The mosquitto broker binary: on PATH, or in /usr/sbin where Debian puts it (not on
/// every user's PATH). In CI its absence is a failure, elsewhere the test is skipped.
fn mosquitto_bin() -> Option<String> {
    if have("mosquitto") {
        return Some("mosquitto".into());
    }
    for path in ["/usr/sbin/mosquitto", "/usr/local/sbin/mosquitto"] {
        if Path::new(path).exists() {
            return Some(path.into());
        }
    }
    assert!(
        std::env::var_os("CI").is_none(),
        "mosquitto is not installed; .ci/run should have installed it"
    );
    eprintln!("SKIPPED: mosquitto (the broker) is not installed");
    None
}

/// A mosquitto broker on a free loopback port, logging everything (`log_type all`, the
/// lines `mosquitto -v` prints) to a file; killed when dropped.
struct Mosquitto {
    child: Child,
    port: u16,
    log: PathBuf,
    _dir: tempfile::TempDir,
}

impl Mosquitto {
    fn start(bin: &str) -> Mosquitto {
        let dir = tempfile::tempdir().unwrap();
        let port = free_port();
        let log = dir.path().join("mosquitto.log");
        let conf = dir.path().join("mosquitto.conf");
        // Started as root, mosquitto drops to the `mosquitto` user unless told otherwise,
        // and could not write its log into our directory.
        let user = if is_root() { "user root\n" } else { "" };
        std::fs::write(
            &conf,
            format!(
                "listener {port} 127.0.0.1\nallow_anonymous true\nlog_type all\n\
                 log_dest file {}\n{user}",
                log.display()
            ),
        )
        .unwrap();
        let child = Command::new(bin)
            .args(["-c", conf.to_str().unwrap()])
            .stdin(Stdio::null())
            .stdout(Stdio::null())
            .stderr(Stdio::null())
            .spawn()
            .expect("mosquitto starts");
        let broker = Mosquitto {
            child,
            port,
            log,
            _dir: dir,
        };
        let deadline = Instant::now() + WAIT;
        while TcpStream::connect(("127.0.0.1", port)).is_err() {
            assert!(
                Instant::now() < deadline,
                "mosquitto did not listen on {port}"
            );
            std::thread::sleep(Duration::from_millis(20));
        }
        broker
    }

    fn port_arg(&self) -> String {
        self.port.to_string()
    }

    fn log_text(&self) -> String {
        std::fs::read_to_string(&self.log).unwrap_or_default()
    }

    /// Waits until the log has a line containing `needle`; the whole log.
    fn wait_log(&self, needle: &str) -> String {
        self.wait_log_count(needle, 1)
    }

    /// Waits until `needle` occurs `count` times in the log; the whole log.
    fn wait_log_count(&self, needle: &str, count: usize) -> String {
        let deadline = Instant::now() + WAIT;
        loop {
            let text = self.log_text();
            if text.matches(needle).count() >= count {
                return text;
            }
            assert!(
                Instant::now() < deadline,
                "mosquitto never logged {needle:?} {count} times; log:\n{text}"
            );
            std::thread::sleep(Duration::from_millis(20));
        }
    }
}

impl Drop for Mosquitto {
    fn drop(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

fn is_root() -> bool {
    Command::new("id")
        .arg("-u")
        .output()
        .is_ok_and(|o| String::from_utf8_lossy(&o.stdout).trim() == "0")
}

/// `mosquitto_sub -v -F FORMAT` on `topic`, its lines read on a thread; killed when
/// dropped. Subscribed once mosquitto logged its SUBACK (`id` is its client id).
struct MosquittoSub {
    child: Child,
    lines: mpsc::Receiver<String>,
}

impl MosquittoSub {
    fn start(broker: &Mosquitto, id: &str, topic: &str, format: &str) -> MosquittoSub {
        let mut child = Command::new("mosquitto_sub")
            .args(["-h", "127.0.0.1", "-p", &broker.port_arg(), "-i", id])
            .args(["-t", topic, "-F", format])
            .stdout(Stdio::piped())
            .stderr(Stdio::null())
            .spawn()
            .expect("mosquitto_sub starts");
        let stdout = child.stdout.take().unwrap();
        let (tx, lines) = mpsc::channel();
        std::thread::spawn(move || {
            for line in BufReader::new(stdout).lines().map_while(Result::ok) {
                if tx.send(line).is_err() {
                    return;
                }
            }
        });
        broker.wait_log(&format!("Sending SUBACK to {id}"));
        MosquittoSub { child, lines }
    }

    fn next(&self) -> String {
        self.lines
            .recv_timeout(WAIT)
            .expect("mosquitto_sub printed nothing within 10 s")
    }
}

impl Drop for MosquittoSub {
    fn drop(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

/// Reads the emulator's lines until one equals `want` (others are kept and shown if it
/// never comes); the lines before it.
fn expect_line(py: &Python, who: &str, want: &str) -> Vec<String> {
    let deadline = Instant::now() + WAIT;
    let mut seen = Vec::new();
    loop {
        let left = deadline.saturating_duration_since(Instant::now());
        match py.next_line(left) {
            Some(line) if line == want => return seen,
            Some(line) => seen.push(line),
            None => panic!("{who}: no line {want:?} within 10 s; it printed {seen:#?}"),
        }
    }
}

/// Reads the emulator's lines until each of `wants` came, in any order, and nothing else.
fn expect_all(py: &Python, who: &str, wants: &[&str]) {
    let mut missing: Vec<&str> = wants.to_vec();
    while !missing.is_empty() {
        let line = py
            .next_line(WAIT)
            .unwrap_or_else(|| panic!("{who}: no line within 10 s, still expected {missing:?}"));
        let at = missing
            .iter()
            .position(|w| *w == line)
            .unwrap_or_else(|| panic!("{who}: unexpected line {line:?}, expected {missing:?}"));
        missing.remove(at);
    }
}

/// The emulator's next line, which must be `want`.
fn expect_next(py: &Python, who: &str, want: &str) {
    let line = py
        .next_line(WAIT)
        .unwrap_or_else(|| panic!("{who}: no line within 10 s, expected {want:?}"));
    assert_eq!(line, want, "{who}: unexpected line");
}

/// The lines the emulator prints within `within` (to show what did NOT happen).
fn lines_within(py: &Python, within: Duration) -> Vec<String> {
    let deadline = Instant::now() + within;
    let mut lines = Vec::new();
    while let Some(line) = py.next_line(deadline.saturating_duration_since(Instant::now())) {
        lines.push(line);
    }
    lines
}

fn hex(bytes: &[u8]) -> String {
    bytes.iter().map(|b| format!("{b:02x}")).collect()
}

/// Lower-case hex of a hand-written byte string with spaces between fields.
fn spaced(hex: &str) -> String {
    hex.split_whitespace().collect()
}

/// One MQTT packet from a raw connection (fixed header included), within `WAIT`.
fn read_packet(stream: &mut TcpStream) -> Vec<u8> {
    stream.set_read_timeout(Some(WAIT)).unwrap();
    let mut first = [0u8; 1];
    stream.read_exact(&mut first).expect("a packet");
    let mut packet = vec![first[0]];
    let mut len = 0usize;
    let mut shift = 0;
    loop {
        let mut b = [0u8; 1];
        stream.read_exact(&mut b).unwrap();
        packet.push(b[0]);
        len |= usize::from(b[0] & 0x7f) << shift;
        shift += 7;
        if b[0] & 0x80 == 0 {
            break;
        }
    }
    let mut body = vec![0u8; len];
    stream.read_exact(&mut body).unwrap();
    packet.extend(body);
    packet
}

/// Accepts the next connection on `listener` within `WAIT`.
fn accept(listener: &TcpListener) -> TcpStream {
    listener.set_nonblocking(true).unwrap();
    let deadline = Instant::now() + WAIT;
    loop {
        match listener.accept() {
            Ok((stream, _)) => {
                stream.set_nonblocking(false).unwrap();
                return stream;
            }
            Err(e) if e.kind() == std::io::ErrorKind::WouldBlock => {
                assert!(Instant::now() < deadline, "no connection within 10 s");
                std::thread::sleep(Duration::from_millis(10));
            }
            Err(e) => panic!("accept: {e}"),
        }
    }
}

// ------------------------------------------------------------------------------- FORTE

/// The `fbdk` types of the main test message: INT, REAL, STRING, BOOL, DT.
const OUT_TYPES: &str = "INT,REAL,STRING,BOOL,DT";
/// SINT, UINT, DINT, LREAL, TIME, BOOL, WORD.
const MIX_TYPES: &str = "SINT,UINT,DINT,LREAL,TIME,BOOL,WORD";

/// `3 REAL#1.5 'hi' TRUE DT#2026-11-22-12:30:15.250` as FORTE 3.x's fbdk layer writes it.
const OUT_HEX: &str = "43 0003 \
                       4a 3fc00000 \
                       50 0002 6869 \
                       41 \
                       4f 18ea5ddf55415880";
// INT 3: tag 0x40|3, 2 bytes. REAL 1.5: 0x40|10, IEEE single 0x3fc00000. STRING 'hi':
// 0x40|16, length 2, the bytes. BOOL TRUE: the tag 0x40|1 alone. DT: 0x40|15, 8 bytes:
// 1_795_350_615_250 ms since 1970 (2026-11-22 12:30:15.250 UTC) * 1_000_000 ns.

/// `-2 65535 -1 LREAL#-0.5 T#1s500ms FALSE 16#BEEF`.
const MIX_HEX: &str = "42 fe \
                       47 ffff \
                       44 ffffffff \
                       4b bfe0000000000000 \
                       4c 000000000016e360 \
                       40 \
                       52 beef";
// SINT -2: 0x40|2, two's complement. UINT: 0x40|7. DINT -1: 0x40|4. LREAL -0.5: 0x40|11,
// IEEE double. TIME 1.5 s: 0x40|12, 8 bytes signed MICROseconds (1_500_000 = 0x16e360).
// BOOL FALSE: the bare tag 0x40. WORD: 0x40|18.

fn forte(broker_port: &str, client_id: &str, ports: &[&str], extra: &[&str]) -> Python {
    let mut args = vec!["--port", broker_port, "--client-id", client_id];
    for port in ports {
        args.push(port);
    }
    args.extend_from_slice(extra);
    Python::spawn("forte_device.py", &args)
}

/// The fbdk bytes a FORTE 3.x publisher sends, as mosquitto_sub and a second FORTE device
/// (a subscriber with the same types) see them; a message over 255 bytes; a PUBLISH_0.
#[test]
fn forte_fbdk_payloads_on_the_wire() {
    let Some(bin) = mosquitto_bin() else { return };
    if !require("mosquitto_sub") || !require("python3") {
        return;
    }
    let broker = Mosquitto::start(&bin);
    let port = broker.port_arg();
    let mon = MosquittoSub::start(&broker, "emu-mon", "fbdk/#", "%t %x");

    let out_sub = format!("fbdk/conv2/OUT:{OUT_TYPES}");
    let mix_sub = format!("fbdk/conv2/MIX:{MIX_TYPES}");
    let subs = [
        "--sub",
        &out_sub,
        "--sub",
        &mix_sub,
        "--sub",
        "fbdk/conv2/LONG:STRING",
        "--sub",
        "fbdk/conv2/NONE:",
    ];
    let conv3 = forte(&port, "conv3", &subs, &[]);
    expect_line(&conv3, "conv3", "connected");
    for topic in ["OUT", "MIX", "LONG", "NONE"] {
        expect_line(&conv3, "conv3", &format!("subscribed fbdk/conv2/{topic}"));
    }
    let out_pub = format!("fbdk/conv2/OUT:{OUT_TYPES}");
    let mix_pub = format!("fbdk/conv2/MIX:{MIX_TYPES}");
    let pubs = [
        "--pub",
        &out_pub,
        "--pub",
        &mix_pub,
        "--pub",
        "fbdk/conv2/LONG:STRING",
        "--pub",
        "fbdk/conv2/NONE:",
    ];
    let mut conv2 = forte(&port, "conv2", &pubs, &[]);
    expect_line(&conv2, "conv2", "connected");

    // INT + REAL + STRING + BOOL + DT
    conv2.send("pub fbdk/conv2/OUT 3 REAL#1.5 'hi' TRUE DT#2026-11-22-12:30:15.250");
    let out_hex = spaced(OUT_HEX);
    expect_next(&conv2, "conv2", &format!("sent fbdk/conv2/OUT {out_hex}"));
    assert_eq!(mon.next(), format!("fbdk/conv2/OUT {out_hex}"));
    expect_next(
        &conv3,
        "conv3",
        "recv fbdk/conv2/OUT INT#3 REAL#1.5 'hi' TRUE DT#2026-11-22-12:30:15.250",
    );

    // signed, unsigned, LREAL, TIME in microseconds, BOOL FALSE, WORD
    conv2.send("pub fbdk/conv2/MIX -2 65535 DINT#-1 LREAL#-0.5 T#1s500ms FALSE 16#BEEF");
    let mix_hex = spaced(MIX_HEX);
    expect_next(&conv2, "conv2", &format!("sent fbdk/conv2/MIX {mix_hex}"));
    assert_eq!(mon.next(), format!("fbdk/conv2/MIX {mix_hex}"));
    expect_next(
        &conv3,
        "conv3",
        "recv fbdk/conv2/MIX SINT#-2 UINT#65535 DINT#-1 LREAL#-0.5 T#1s500ms FALSE WORD#48879",
    );

    // PUBLISH_0: the single NULL byte 0x05, an IND without data at the SUBSCRIBE_0
    conv2.send("pub fbdk/conv2/NONE");
    expect_next(&conv2, "conv2", "sent fbdk/conv2/NONE 05");
    assert_eq!(mon.next(), "fbdk/conv2/NONE 05");
    expect_next(&conv3, "conv3", "recv fbdk/conv2/NONE");

    // 303 bytes: tag, length 300, 300 bytes. FORTE's subscriber keeps 255 of them, its
    // fbdk layer waits for the rest of the STRING and raises no event ...
    let long = "x".repeat(300);
    conv2.send(&format!("pub fbdk/conv2/LONG '{long}'"));
    let long_hex = format!("50012c{}", "78".repeat(300));
    expect_next(&conv2, "conv2", &format!("sent fbdk/conv2/LONG {long_hex}"));
    assert_eq!(mon.next(), format!("fbdk/conv2/LONG {long_hex}"));
    expect_next(&conv3, "conv3", "corrupted fbdk/conv2/LONG 303");
    expect_next(&conv3, "conv3", "pending fbdk/conv2/LONG 255");
    // ... and glues the next, good message to those 255 bytes: still no event.
    conv2.send("pub fbdk/conv2/LONG 'ok'");
    expect_next(&conv2, "conv2", "sent fbdk/conv2/LONG 5000026f6b");
    assert_eq!(mon.next(), "fbdk/conv2/LONG 5000026f6b");
    expect_next(&conv3, "conv3", "pending fbdk/conv2/LONG 260");

    // The other subscribers of the device are unaffected.
    conv2.send("pub fbdk/conv2/OUT -32768 REAL#-0.1 '' FALSE DT#1970-01-01-00:00:00.001");
    let zeroes = spaced("43 8000 4a bdcccccd 50 0000 40 4f 00000000000f4240");
    expect_next(&conv2, "conv2", &format!("sent fbdk/conv2/OUT {zeroes}"));
    expect_next(
        &conv3,
        "conv3",
        "recv fbdk/conv2/OUT INT#-32768 REAL#-0.1 '' FALSE DT#1970-01-01-00:00:00.001",
    );
    conv2.send("quit");
    broker.wait_log("Received DISCONNECT from conv2");
}

/// FORTE 2.x: DATE, TIME_OF_DAY and DATE_AND_TIME in milliseconds (`--time-unit ms`);
/// `--tz utc` pins the bytes whatever this machine's time zone (FORTE 2.x maps the
/// literals with mktime, in the device's local time).
#[test]
fn forte_2x_dates_in_milliseconds() {
    let Some(bin) = mosquitto_bin() else { return };
    if !require("mosquitto_sub") || !require("python3") {
        return;
    }
    let broker = Mosquitto::start(&bin);
    let port = broker.port_arg();
    let mon = MosquittoSub::start(&broker, "emu-mon", "fbdk/#", "%t %x");
    let ms = ["--time-unit", "ms", "--tz", "utc"];
    let sub = forte(&port, "old2", &["--sub", "fbdk/old1/AT:DT,TOD,DATE"], &ms);
    expect_line(&sub, "old2", "subscribed fbdk/old1/AT");
    let mut publisher = forte(&port, "old1", &["--pub", "fbdk/old1/AT:DT,TOD,DATE"], &ms);
    expect_line(&publisher, "old1", "connected");

    publisher.send("pub fbdk/old1/AT DT#2026-11-22-12:30:15.250 TOD#12:30:15.250 D#2026-11-22");
    // DT: 1_795_350_615_250 ms; TOD: 45_015_250 ms since midnight; DATE: the DT's midnight.
    let expected = spaced(
        "4f 000001a2033c54d2 \
         4e 0000000002aee0d2 \
         4d 000001a2008d7400",
    );
    expect_next(&publisher, "old1", &format!("sent fbdk/old1/AT {expected}"));
    assert_eq!(mon.next(), format!("fbdk/old1/AT {expected}"));
    expect_next(
        &sub,
        "old2",
        "recv fbdk/old1/AT DT#2026-11-22-12:30:15.250 TOD#12:30:15.250 D#2026-11-22",
    );
}

/// FORTE's CONNECT as mosquitto logs it (`p2` = 3.1.1, `c1` = clean session, `k20`, a
/// `u'...'` only with credentials, no will), the PINGREQ after a keep-alive without
/// sending, and Paho C's DISCONNECT at the end.
#[test]
fn forte_connect_in_mosquitto_log() {
    let Some(bin) = mosquitto_bin() else { return };
    if !require("python3") {
        return;
    }
    let broker = Mosquitto::start(&bin);
    let port = broker.port_arg();
    let mut anon = forte(&port, "conv2", &["--pub", "fbdk/conv2/OUT:INT"], &[]);
    expect_line(&anon, "conv2", "connected");
    let with_user = forte(
        &port,
        "conv4",
        &["--sub", "fbdk/conv2/OUT:INT"],
        &["--username", "dev", "--password", "secret"],
    );
    expect_line(&with_user, "conv4", "subscribed fbdk/conv2/OUT");
    let pinger = forte(&port, "conv5", &[], &["--keepalive", "1"]);
    expect_line(&pinger, "conv5", "connected");

    let log = broker.wait_log("Received PINGREQ from conv5");
    let lines: Vec<&str> = log.lines().collect();
    let connect_of = |id: &str| {
        let at = lines
            .iter()
            .position(|l| l.contains(&format!(" as {id} (")))
            .unwrap_or_else(|| panic!("no CONNECT of {id} in the log:\n{log}"));
        (lines[at], lines[at + 1])
    };
    let (conv2, after) = connect_of("conv2");
    assert!(conv2.ends_with(" as conv2 (p2, c1, k20)."), "{conv2}");
    assert!(after.ends_with("No will message specified."), "{after}");
    let (conv4, after) = connect_of("conv4");
    assert!(
        conv4.ends_with(" as conv4 (p2, c1, k20, u'dev')."),
        "{conv4}"
    );
    assert!(after.ends_with("No will message specified."), "{after}");
    let (conv5, _) = connect_of("conv5");
    assert!(conv5.ends_with(" as conv5 (p2, c1, k1)."), "{conv5}");
    assert!(
        log.contains("conv4 0 fbdk/conv2/OUT"),
        "subscription at QoS 0:\n{log}"
    );

    anon.send("pub fbdk/conv2/OUT 1");
    expect_next(&anon, "conv2", "sent fbdk/conv2/OUT 430001");
    expect_line(&with_user, "conv4", "recv fbdk/conv2/OUT INT#1");
    let log = broker.wait_log("Received PUBLISH from conv2");
    assert!(
        log.contains(
            "Received PUBLISH from conv2 (d0, q0, r0, m0, 'fbdk/conv2/OUT', ... (3 bytes))"
        ),
        "QoS 0, not retained:\n{log}"
    );
    anon.send("quit");
    broker.wait_log("Received DISCONNECT from conv2");
}

/// The bytes of FORTE's connection on a raw listener: Paho C's CONNECT (3.1.1), its
/// retry with MQTT 3.1 when the first attempt ends without CONNACK, a REQ before CONNACK
/// (SEND_FAILED, the publisher dead for good), SUBSCRIBE, PUBLISH, DISCONNECT. (These
/// bytes were also compared once with a C program linked to Debian's libpaho-mqtt 1.3.12
/// and set up as FORTE's MQTTHandler: identical.)
#[test]
fn forte_connection_bytes() {
    if !require("python3") {
        return;
    }
    let listener = TcpListener::bind("127.0.0.1:0").unwrap();
    let port = listener.local_addr().unwrap().port().to_string();
    let mut dev = forte(
        &port,
        "conv2",
        &[
            "--pub",
            "fbdk/conv2/EARLY:INT",
            "--pub",
            "fbdk/conv2/OUT:INT",
            "--sub",
            "fbdk/conv9/IN:BOOL",
        ],
        &[],
    );

    // CONNECT: "MQTT" level 4, flags 0x02 (clean session only: no will, no username),
    // keep-alive 20, client id "conv2"; the connection closes without CONNACK.
    let mut first = accept(&listener);
    assert_eq!(
        hex(&read_packet(&mut first)),
        spaced("10 11 0004 4d515454 04 02 0014 0005 636f6e7632")
    );
    first.shutdown(Shutdown::Both).unwrap();
    drop(first);
    // Paho C's MQTTVERSION_DEFAULT retries at once with MQTT 3.1: "MQIsdp" level 3.
    let mut conn = accept(&listener);
    assert_eq!(
        hex(&read_packet(&mut conn)),
        spaced("10 13 0006 4d5149736470 03 02 0014 0005 636f6e7632")
    );

    // Before CONNACK a REQ fails (MQTTASYNC_DISCONNECTED) and the publisher is dead.
    dev.send("pub fbdk/conv2/EARLY 1");
    expect_next(&dev, "conv2", "error fbdk/conv2/EARLY SEND_FAILED");

    conn.write_all(&[0x20, 0x02, 0x00, 0x00]).unwrap();
    expect_next(&dev, "conv2", "connected");
    // SUBSCRIBE packet id 1, QoS 0
    assert_eq!(
        hex(&read_packet(&mut conn)),
        spaced("82 12 0001 000d 6662646b2f636f6e76392f494e 00")
    );
    conn.write_all(&[0x90, 0x03, 0x00, 0x01, 0x00]).unwrap();
    expect_next(&dev, "conv2", "subscribed fbdk/conv9/IN");

    dev.send("pub fbdk/conv2/EARLY 2");
    expect_next(&dev, "conv2", "error fbdk/conv2/EARLY NO_SOCKET");
    dev.send("pub fbdk/conv2/OUT 258");
    expect_next(&dev, "conv2", "sent fbdk/conv2/OUT 430102");
    // PUBLISH QoS 0, not retained, no packet id
    assert_eq!(
        hex(&read_packet(&mut conn)),
        spaced("30 13 000e 6662646b2f636f6e76322f4f5554 430102")
    );
    // A message arrives: BOOL TRUE.
    conn.write_all(&[
        0x30, 0x10, 0x00, 0x0d, b'f', b'b', b'd', b'k', b'/', b'c', b'o', b'n', b'v', b'9', b'/',
        b'I', b'N', 0x41,
    ])
    .unwrap();
    expect_line(&dev, "conv2", "recv fbdk/conv9/IN TRUE");

    dev.send("quit");
    assert_eq!(hex(&read_packet(&mut conn)), "e000", "DISCONNECT");
}

/// FORTE after a failed publish: the publisher FB stays dead (NO_SOCKET) while the
/// connection comes back and the device's subscriber is subscribed again; INIT revives it.
#[test]
fn forte_publisher_dead_after_send_failure() {
    let Some(bin) = mosquitto_bin() else { return };
    if !require("python3") {
        return;
    }
    let broker = Mosquitto::start(&bin);
    let port = broker.port_arg();
    let mut dev = forte(
        &port,
        "conv2",
        &["--pub", "fbdk/conv2/OUT:INT", "--sub", "fbdk/conv9/IN:INT"],
        &[],
    );
    expect_line(&dev, "conv2", "subscribed fbdk/conv9/IN");
    let mut other = forte(&port, "conv9", &["--pub", "fbdk/conv9/IN:INT"], &[]);
    expect_line(&other, "conv9", "connected");

    // the network goes away for 1.5 s
    dev.send("drop 1.5");
    expect_next(&dev, "conv2", "disconnected dropped");
    dev.send("pub fbdk/conv2/OUT 1");
    expect_next(&dev, "conv2", "error fbdk/conv2/OUT SEND_FAILED");
    expect_line(&dev, "conv2", "connected");
    expect_line(&dev, "conv2", "subscribed fbdk/conv9/IN");

    dev.send("pub fbdk/conv2/OUT 2");
    expect_next(&dev, "conv2", "error fbdk/conv2/OUT NO_SOCKET");
    other.send("pub fbdk/conv9/IN 5");
    expect_next(&other, "conv9", "sent fbdk/conv9/IN 430005");
    expect_next(&dev, "conv2", "recv fbdk/conv9/IN INT#5");

    dev.send("init fbdk/conv2/OUT");
    expect_next(&dev, "conv2", "inited fbdk/conv2/OUT");
    dev.send("pub fbdk/conv2/OUT 3");
    expect_next(&dev, "conv2", "sent fbdk/conv2/OUT 430003");

    let log = broker.log_text();
    assert_eq!(
        log.matches(" as conv2 (p2, c1, k20).").count(),
        2,
        "one reconnect:\n{log}"
    );
    // The drop closed the first connection without DISCONNECT; kill closes the second.
    dev.send("kill");
    let log = broker.wait_log_count("Client conv2 closed its connection.", 2);
    assert!(
        !log.contains("Received DISCONNECT from conv2"),
        "neither drop nor kill sends DISCONNECT:\n{log}"
    );
}

// ---------------------------------------------------------------------------- DINASORE

/// DINASORE's publisher and subscriber through mosquitto: the payload `json.dumps` of
/// `{VALUE_NAME: str(value)}`, `float()` on the subscriber, the subscriber FB dead after a
/// value `float()` refuses; both CONNECTs with an empty client id and keep-alive 60.
#[test]
fn dinasore_json_through_mosquitto() {
    let Some(bin) = mosquitto_bin() else { return };
    if !require("mosquitto_sub") || !require_paho() {
        return;
    }
    let broker = Mosquitto::start(&bin);
    let port = broker.port_arg();
    let mon = MosquittoSub::start(&broker, "emu-mon", "dinasore/#", "%t %p");
    let topic = "dinasore/dev/SPEED";
    let spec = format!("{topic}:SPEED");
    let sub = Python::spawn("dinasore_device.py", &["--port", &port, "--sub", &spec]);
    // `connected` once INIT returned, `subscribed` at SUBACK: either may come first
    expect_all(
        &sub,
        "dinasore sub",
        &["connected", &format!("subscribed {topic}")],
    );
    let mut publisher = Python::spawn("dinasore_device.py", &["--port", &port, "--pub", &spec]);
    expect_line(&publisher, "dinasore pub", "connected");

    for (value, payload) in [
        ("3", r#"{"SPEED": "3"}"#),
        ("3.0", r#"{"SPEED": "3.0"}"#),
        ("-1.25", r#"{"SPEED": "-1.25"}"#),
    ] {
        publisher.send(&format!("pub {topic} {value}"));
        expect_next(
            &publisher,
            "dinasore pub",
            &format!("sent {topic} {payload}"),
        );
        assert_eq!(mon.next(), format!("{topic} {payload}"));
        let float = if value == "3" { "3.0" } else { value };
        expect_next(&sub, "dinasore sub", &format!("recv {topic} {float}"));
    }

    // float('abc') raises: DINASORE's FB thread stops, the FB never outputs again
    publisher.send(&format!("pub {topic} 'abc'"));
    expect_next(
        &publisher,
        "dinasore pub",
        &format!(r#"sent {topic} {{"SPEED": "abc"}}"#),
    );
    assert_eq!(mon.next(), format!(r#"{topic} {{"SPEED": "abc"}}"#));
    expect_next(
        &sub,
        "dinasore sub",
        &format!("error {topic} ValueError: could not convert string to float: 'abc'"),
    );
    publisher.send(&format!("pub {topic} 4"));
    expect_next(
        &publisher,
        "dinasore pub",
        &format!(r#"sent {topic} {{"SPEED": "4"}}"#),
    );
    assert_eq!(mon.next(), format!(r#"{topic} {{"SPEED": "4"}}"#));
    let after = lines_within(&sub, Duration::from_millis(1500));
    assert!(after.is_empty(), "a dead subscriber FB printed {after:?}");

    // Both connected with an empty client id (mosquitto names them auto-...), MQTT 3.1.1,
    // clean session, keep-alive 60, no username, no will.
    let log = broker.log_text();
    let lines: Vec<&str> = log.lines().collect();
    let connects: Vec<usize> = (0..lines.len())
        .filter(|&i| lines[i].contains("New client connected") && lines[i].contains(" as auto-"))
        .collect();
    assert_eq!(connects.len(), 2, "two DINASORE clients:\n{log}");
    for i in connects {
        assert!(lines[i].ends_with(" (p2, c1, k60)."), "{}", lines[i]);
        assert!(
            lines[i + 1].ends_with("No will message specified."),
            "{}",
            lines[i + 1]
        );
    }
}

/// DINASORE's publisher on a raw listener: the CONNECT paho writes for `Client()` and
/// `connect(host, port)`, then PUBLISH at once, without waiting for (or ever reading)
/// a CONNACK.
#[test]
fn dinasore_connection_bytes() {
    if !require_paho() {
        return;
    }
    let listener = TcpListener::bind("127.0.0.1:0").unwrap();
    let port = listener.local_addr().unwrap().port().to_string();
    let mut publisher = Python::spawn(
        "dinasore_device.py",
        &["--port", &port, "--pub", "dinasore/a/SPEED:SPEED"],
    );
    let mut conn = accept(&listener);
    // "MQTT" level 4, flags 0x02 (clean session only), keep-alive 60, client id ""
    assert_eq!(
        hex(&read_packet(&mut conn)),
        spaced("10 0c 0004 4d515454 04 02 003c 0000")
    );
    expect_line(&publisher, "dinasore pub", "connected");
    publisher.send("pub dinasore/a/SPEED 3");
    expect_next(
        &publisher,
        "dinasore pub",
        r#"sent dinasore/a/SPEED {"SPEED": "3"}"#,
    );
    let mut expected = spaced("30 20 0010");
    expected += &hex(b"dinasore/a/SPEED");
    expected += &hex(br#"{"SPEED": "3"}"#);
    assert_eq!(hex(&read_packet(&mut conn)), expected);
    publisher.send("quit");
    assert_eq!(hex(&read_packet(&mut conn)), "e000", "DISCONNECT");
}

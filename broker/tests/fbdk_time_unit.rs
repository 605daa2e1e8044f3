//! `[fb] fbdk_time_unit` end to end against the real `fbbus` binary: DATE, TIME_OF_DAY and
//! DATE_AND_TIME in `fbdk/` payloads are nanoseconds by default, as 4diac FORTE 3.x writes
//! them, and milliseconds with `fbdk_time_unit = "ms"`, as FORTE 2.0.x does (issue 16).
//!
//! The device publishes the bytes FORTE's `fbdk` layer would; observers (rumqttc) read
//! `fb/` and `fbdk/`. Each test starts its own broker; helpers are in `common/fb.rs`.

mod common;

use serde_json::{json, Value};

use common::clients::{V4, WAIT};
use common::fb::*;
use common::{Broker, Options};

/// A conveyor with a timestamped event and one port per date type.
const DATED: &str = r#"{"fbs": {"CONV": {
    "events_out": {"MOVED": {"with": ["POS", "AT"]}},
    "data_out": {"POS": "INT", "AT": "DT", "DAY": "DATE", "CLOCK": "TOD"}
}}}"#;

/// DT#2026-11-22-12:30:15.250, the issue's example, in milliseconds since 1970.
const DT_MS: u64 = 1_795_350_615_250;
/// TOD#12:30:15.250 in milliseconds since midnight.
const TOD_MS: u64 = 45_015_250;
/// D#2026-11-22 in milliseconds since 1970.
const DAY_MS: u64 = DT_MS - TOD_MS;
const NS_PER_MS: u64 = 1_000_000;

/// A DATE (`0x4D`), TIME_OF_DAY (`0x4E`) or DATE_AND_TIME (`0x4F`) as `fbdk` bytes.
fn dated(tag: u8, raw: u64) -> Vec<u8> {
    let mut bytes = vec![tag];
    bytes.extend(raw.to_be_bytes());
    bytes
}

/// The device "forte" with [`DATED`] declared, and observers of its `fb/` and `fbdk/`
/// ports and of its diagnostics.
struct Line {
    broker: Broker,
    dev: Dev,
    fb: V4,
    fbdk: V4,
    diag: V4,
}

impl Line {
    async fn start(unit: Option<&str>) -> Line {
        let extra = unit.map_or_else(String::new, |u| format!("[fb]\nfbdk_time_unit = \"{u}\"\n"));
        let broker = Broker::start_with(
            Options {
                extra,
                ..Default::default()
            },
            |_| {},
        );
        let mut diag = observer(&broker, "watch", &["fbbus/diag/forte"]).await;
        let fb = observer(&broker, "sub-fb", &["fb/forte/#"]).await;
        let fbdk = observer(&broker, "sub-fbdk", &["fbdk/forte/#"]).await;
        let mut dev = Dev::connect(broker.port(), 5, "forte");
        declare_ok(&mut dev, DATED, &mut diag, &broker).await;
        Line {
            broker,
            dev,
            fb,
            fbdk,
            diag,
        }
    }

    /// Publishes `payload` on `<ns>/forte/CONV/<port>` and asserts it was accepted.
    fn publish(&mut self, ns: &str, port: &str, payload: &[u8]) {
        let topic = format!("{ns}/forte/CONV/{port}");
        assert_eq!(
            self.dev.publish(&topic, payload),
            0,
            "{topic} {payload:02x?} refused\n{}",
            self.broker.log_text()
        );
    }

    /// Publishes `payload` on `fbdk/forte/CONV/<port>` and asserts it was refused as
    /// ill-typed, with a diagnostic whose detail contains `why`.
    async fn refused(&mut self, port: &str, payload: &[u8], why: &str) {
        let topic = format!("fbdk/forte/CONV/{port}");
        assert_eq!(
            self.dev.publish(&topic, payload),
            REFUSED,
            "{topic} {payload:02x?} accepted"
        );
        let d = diag(&mut self.diag, "forte", "rejected", &self.broker).await;
        assert_eq!(d["topic"], topic.as_str());
        let detail = d["detail"].as_str().unwrap_or_default();
        assert!(detail.contains(why), "{topic}: {d}");
    }

    /// The next message on `fb/forte/CONV/<port>`: the value, or an event's data.
    async fn fb(&mut self, port: &str) -> Value {
        let got = json_on(&mut self.fb, &format!("fb/forte/CONV/{port}"), &self.broker).await;
        if got.is_object() {
            got["data"].clone()
        } else {
            got
        }
    }

    /// The next message on `fbdk/forte/CONV/<port>`.
    async fn fbdk(&mut self, port: &str) -> Vec<u8> {
        let topic = format!("fbdk/forte/CONV/{port}");
        next_on(&mut self.fbdk, &topic, WAIT)
            .await
            .unwrap_or_else(|| panic!("nothing on {topic}\n{}", self.broker.log_text()))
    }
}

/// The default is FORTE 3.x: a FORTE-3.x DT (nanoseconds, with digits below the
/// millisecond as `NOW()` gives them) is accepted and arrives on `fb/` as the DT FORTE
/// shows; a JSON DT arrives on `fbdk/` as nanoseconds; likewise DATE, TOD and an event.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn by_default_fbdk_dates_and_times_are_forte_3_nanoseconds() {
    let mut line = Line::start(None).await;

    // FORTE 3.x in: DT#2026-11-22-12:30:15.250 and 123,456 ns.
    let forte = dated(0x4F, DT_MS * NS_PER_MS + 123_456);
    line.publish("fbdk", "AT", &forte);
    assert_eq!(line.fb("AT").await, json!("DT#2026-11-22-12:30:15.250"));
    // fbdk subscribers get the device's bytes as they came, nanoseconds included.
    assert_eq!(line.fbdk("AT").await, forte);

    // JSON in, FORTE 3.x out: 1,795,350,615,250,000,000 ns.
    line.publish("fb", "AT", br#""DT#2026-11-22-12:30:15.250""#);
    assert_eq!(line.fb("AT").await, json!("DT#2026-11-22-12:30:15.250"));
    assert_eq!(line.fbdk("AT").await, dated(0x4F, DT_MS * NS_PER_MS));

    // DATE and TIME_OF_DAY, both ways.
    line.publish("fbdk", "DAY", &dated(0x4D, DAY_MS * NS_PER_MS));
    assert_eq!(line.fb("DAY").await, json!("D#2026-11-22"));
    line.fbdk("DAY").await;
    line.publish("fb", "CLOCK", br#""TOD#12:30:15.250""#);
    line.fb("CLOCK").await;
    assert_eq!(line.fbdk("CLOCK").await, dated(0x4E, TOD_MS * NS_PER_MS));
    line.publish("fbdk", "CLOCK", &dated(0x4E, TOD_MS * NS_PER_MS + 999_999));
    assert_eq!(line.fb("CLOCK").await, json!("TOD#12:30:15.250"));
    line.fbdk("CLOCK").await;

    // An event whose WITH data holds a FORTE 3.x DT.
    let mut moved = vec![0x43, 0x00, 0x07];
    moved.extend(&forte);
    line.publish("fbdk", "MOVED", &moved);
    assert_eq!(
        line.fb("MOVED").await,
        json!({"POS": 7, "AT": "DT#2026-11-22-12:30:15.250"})
    );
    line.fbdk("MOVED").await;

    // A FORTE 2.x device's milliseconds are read as nanoseconds: the issue's misreading,
    // which is why such a line sets `fbdk_time_unit = "ms"`.
    line.publish("fbdk", "AT", &dated(0x4F, DT_MS));
    assert_eq!(line.fb("AT").await, json!("DT#1970-01-01-00:29:55.350"));
    line.fbdk("AT").await;

    // A DATE off midnight by one nanosecond is no DATE.
    line.refused("DAY", &dated(0x4D, DAY_MS * NS_PER_MS + 1), "not midnight")
        .await;

    // A DT after 2554 does not fit 64-bit nanoseconds: fb/ has it, fbdk/ does not, and the
    // publisher is told why.
    line.publish("fb", "AT", br#""DT#2600-01-01-00:00:00""#);
    assert_eq!(line.fb("AT").await, json!("DT#2600-01-01-00:00:00"));
    let d = diag(&mut line.diag, "forte", "not_reencoded", &line.broker).await;
    assert_eq!(d["topic"], "fbdk/forte/CONV/AT", "{d}");
    assert!(d["detail"].as_str().unwrap().contains("2554"), "{d}");
    assert_metric(
        &line.broker,
        "fbbus_typed_messages_not_reencoded_total{namespace=\"fbdk\"}",
        1.0,
    );
    // The next message on fbdk/ is the next publication's.
    line.publish("fb", "AT", br#""DT#2554-07-21-23:34:33.709""#);
    assert_eq!(
        line.fbdk("AT").await,
        dated(0x4F, 18_446_744_073_709 * NS_PER_MS)
    );
}

/// `fbdk_time_unit = "ms"` is FORTE 2.0.x: milliseconds both ways, and a FORTE 3.x
/// nanosecond value (after the year 9999 as milliseconds) is refused.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn with_ms_fbdk_dates_and_times_are_forte_2_milliseconds() {
    let mut line = Line::start(Some("ms")).await;

    // FORTE 2.x in.
    line.publish("fbdk", "AT", &dated(0x4F, DT_MS));
    assert_eq!(line.fb("AT").await, json!("DT#2026-11-22-12:30:15.250"));
    assert_eq!(line.fbdk("AT").await, dated(0x4F, DT_MS));

    // JSON in, FORTE 2.x out.
    line.publish("fb", "AT", br#""DT#2026-11-22-12:30:15.250""#);
    line.fb("AT").await;
    assert_eq!(line.fbdk("AT").await, dated(0x4F, DT_MS));
    line.publish("fbdk", "DAY", &dated(0x4D, DAY_MS));
    assert_eq!(line.fb("DAY").await, json!("D#2026-11-22"));
    line.fbdk("DAY").await;
    line.publish("fb", "CLOCK", br#""TOD#12:30:15.250""#);
    line.fb("CLOCK").await;
    assert_eq!(line.fbdk("CLOCK").await, dated(0x4E, TOD_MS));

    // FORTE 3.x's nanoseconds are not a FORTE 2.x DT.
    line.refused("AT", &dated(0x4F, DT_MS * NS_PER_MS), "after 9999-12-31")
        .await;

    // Milliseconds carry every DT the IEC literals can write.
    line.publish("fb", "AT", br#""DT#2600-01-01-00:00:00""#);
    line.fb("AT").await;
    assert_eq!(line.fbdk("AT").await, dated(0x4F, 19_880_899_200_000));
}

//! Issue 37, the admin plane behind the console a shift engineer keeps open, against the
//! real broker: a port's history (bounded per port and in all, cut by time, exported as
//! CSV, gone with a forgotten device, an event's WITH data included), at plant size
//! (1,000 devices x 10 ports); the connected clients; the retained topics under a filter.

mod common;

use std::net::SocketAddr;
use std::time::{Duration, Instant};

use common::clients::V4;
use common::memory::settled_rss_kib;
use common::raw::{self, Connect, RawClient};
use common::{http_request, Broker, Options};
use rumqttc::QoS;
use serde_json::Value;

/// A conveyor: an event carrying data (WITH), plain data outputs of several types.
const CONV: &str = r#"{"fbs": {"CONV": {
    "type": "CONVEYOR",
    "events_out": {"MOVED": {"with": ["POSITION", "SENSOR_IN"]}},
    "data_out": {"POSITION": "INT", "SENSOR_IN": "BOOL", "ID": "STRING", "SPEED": "REAL"}
}}}"#;

fn get(admin: SocketAddr, path: &str) -> (u16, String, String) {
    http_request(admin, "GET", path).unwrap_or_else(|| panic!("{path}: no answer"))
}

fn json(admin: SocketAddr, path: &str) -> Value {
    let (code, _, body) = get(admin, path);
    assert_eq!(code, 200, "{path}: {body}");
    serde_json::from_str(&body).unwrap_or_else(|e| panic!("{path}: {e}: {body}"))
}

/// Reads `path` until `check` holds (5 s at most).
fn wait_json(admin: SocketAddr, path: &str, check: impl Fn(&Value) -> bool) -> Value {
    let deadline = Instant::now() + Duration::from_secs(5);
    loop {
        let value = json(admin, path);
        if check(&value) {
            return value;
        }
        assert!(Instant::now() < deadline, "{path}: still {value}");
        std::thread::sleep(Duration::from_millis(50));
    }
}

fn points(history: &Value) -> Vec<(u64, f64)> {
    history["points"]
        .as_array()
        .unwrap_or_else(|| panic!("no points: {history}"))
        .iter()
        .map(|p| (p[0].as_u64().unwrap(), p[1].as_f64().unwrap()))
        .collect()
}

async fn publish(dev: &V4, topic: &str, payload: &str) {
    dev.client
        .publish(topic, QoS::AtMostOnce, false, payload.as_bytes().to_vec())
        .await
        .unwrap();
}

/// A port's history: its newest points up to the port's cap, in order, cut by a time
/// range and a limit, as CSV; an event's occurrences and its WITH data as points; the
/// ports that keep none say why; a forgotten device's history is gone.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_port_history_is_bounded_ranged_exported_and_forgotten() {
    let broker = Broker::start_with(
        Options {
            extra: "[console]\nhistory_points_per_port = 50\n".into(),
            ..Options::default()
        },
        |_| {},
    );
    let admin = broker.admin;
    let mut dev = V4::connect(broker.port(), "belt-7", None).await.unwrap();
    dev.declare("belt-7", CONV).await;
    let path = "/api/v1/devices/belt-7/ports/CONV.POSITION/history";
    // Declared, plottable, no value yet: an empty history.
    let empty = json(admin, path);
    assert_eq!(empty["type"], "INT", "{empty}");
    assert_eq!(
        empty["kind"], "with",
        "POSITION is MOVED's WITH data: {empty}"
    );
    assert_eq!(points(&empty), vec![]);

    // One value at a time, as a line's ports send them: values that reach the console in
    // one read make one point, the newest (`activity::Newest`).
    let newest = |i: usize| move |h: &Value| points(h).last().map(|p| p.1) == Some(i as f64);
    for i in 0..80 {
        publish(&dev, "fb/belt-7/CONV/POSITION", &i.to_string()).await;
        wait_json(admin, path, newest(i));
        if i % 20 == 19 {
            // Spread over time, so a range can cut them.
            tokio::time::sleep(Duration::from_millis(30)).await;
        }
    }
    let history = wait_json(admin, path, newest(79));
    let all = points(&history);
    assert_eq!(all.len(), 50, "the port's cap: {history}");
    let values: Vec<f64> = all.iter().map(|p| p.1).collect();
    assert_eq!(values, (30..80).map(f64::from).collect::<Vec<_>>());
    assert!(all.windows(2).all(|w| w[0].0 <= w[1].0), "in time order");
    assert_eq!(history["capacity"], 50, "{history}");
    assert_eq!(history["window_s"], 3600, "{history}");

    // A range, in ms and in RFC 3339, and the newest `limit` of it.
    let (from, to) = (all[10].0, all[30].0);
    let ranged = points(&json(admin, &format!("{path}?from={from}&to={to}")));
    assert!(!ranged.is_empty());
    assert!(
        ranged.iter().all(|p| p.0 >= from && p.0 <= to),
        "{ranged:?}"
    );
    assert_eq!(
        ranged.len(),
        all.iter().filter(|p| p.0 >= from && p.0 <= to).count()
    );
    let limited = points(&json(admin, &format!("{path}?from={from}&to={to}&limit=3")));
    assert_eq!(limited[..], ranged[ranged.len() - 3..]);
    let future = points(&json(admin, &format!("{path}?from=2999-01-01T00:00:00Z")));
    assert!(future.is_empty(), "{future:?}");
    let (code, _, body) = get(admin, &format!("{path}?from=yesterday"));
    assert_eq!(code, 400, "{body}");
    assert!(body.contains("RFC 3339"), "{body}");

    // The same as CSV: a header naming the port, one row per point, UTC times.
    let (code, head, csv) = get(admin, &format!("{path}?format=csv"));
    assert_eq!(code, 200, "{csv}");
    assert!(head.contains("content-type: text/csv"), "{head}");
    assert!(
        head.contains("content-disposition: attachment; filename=\"belt-7_conv.position.csv\""),
        "{head}"
    );
    let rows: Vec<&str> = csv.lines().collect();
    assert_eq!(rows[0], "time,CONV.POSITION");
    assert_eq!(rows.len(), 51, "{csv}");
    let (time, value) = rows[50].split_once(',').unwrap();
    assert_eq!(value, "79");
    assert!(time.ends_with('Z') && time.len() == 24, "{time}");

    // An event: one point per occurrence (its seq), its WITH data as points and values.
    for seq in 1..=3 {
        let event = format!(
            r#"{{"seq": {seq}, "ts": 1763800000123456, "data": {{"POSITION": {}, "SENSOR_IN": {}}}}}"#,
            100 + seq,
            seq % 2 == 1
        );
        publish(&dev, "fb/belt-7/CONV/MOVED", &event).await;
        wait_json(
            admin,
            "/api/v1/devices/belt-7/ports/CONV.MOVED/history",
            |h| points(h).len() == seq,
        );
    }
    let moved = wait_json(
        admin,
        "/api/v1/devices/belt-7/ports/CONV.MOVED/history",
        |h| points(h).len() == 3,
    );
    assert_eq!(moved["kind"], "event", "{moved}");
    assert!(moved["type"].is_null(), "{moved}");
    let seqs: Vec<f64> = points(&moved).iter().map(|p| p.1).collect();
    assert_eq!(seqs, [1.0, 2.0, 3.0]);
    let sensor = json(admin, "/api/v1/devices/belt-7/ports/CONV.SENSOR_IN/history");
    assert_eq!(sensor["kind"], "with", "{sensor}");
    assert_eq!(sensor["type"], "BOOL", "{sensor}");
    let bools: Vec<f64> = points(&sensor).iter().map(|p| p.1).collect();
    assert_eq!(bools, [1.0, 0.0, 1.0]);
    // POSITION came on its own topic and inside MOVED: one series, its older values kept.
    let position = json(admin, path);
    assert_eq!(position["kind"], "with", "{position}");
    let values: Vec<f64> = points(&position).iter().map(|p| p.1).collect();
    assert_eq!(values.len(), 50, "{position}");
    assert_eq!(values[44..], [77.0, 78.0, 79.0, 101.0, 102.0, 103.0]);
    // The WITH data are the ports' last values too ("never seen" before issue 37).
    let activity = json(admin, "/api/v1/devices/belt-7/activity");
    assert_eq!(
        activity["ports"]["CONV.SENSOR_IN"]["value"], "true",
        "{activity}"
    );
    assert_eq!(
        activity["ports"]["CONV.POSITION"]["value"], "103",
        "{activity}"
    );

    // No history: a string port, an undeclared port, an unknown device; each says why.
    for (path, why) in [
        ("/api/v1/devices/belt-7/ports/CONV.ID/history", "STRING"),
        (
            "/api/v1/devices/belt-7/ports/CONV.NOPE/history",
            "no output port",
        ),
        ("/api/v1/devices/belt-7/ports/NODOT/history", "FB.PORT"),
        (
            "/api/v1/devices/ghost/ports/CONV.POSITION/history",
            "no device",
        ),
    ] {
        let (code, _, body) = get(admin, path);
        assert_eq!(code, 404, "{path}: {body}");
        assert!(body.contains(why), "{path}: {body}");
    }
    let series = r#"fbbus_console_entries{what="history_series"}"#;
    // POSITION, MOVED and SENSOR_IN; SPEED never had a value.
    assert_eq!(broker.metric(series), 3.0);

    // Forgotten: the device and its history are gone.
    dev.client.disconnect().await.unwrap();
    drop(dev);
    wait_json(admin, "/api/v1/devices/belt-7", |r| {
        r["status"] == "offline"
    });
    let (code, _, body) = http_request(admin, "DELETE", "/api/v1/devices/belt-7").unwrap();
    assert_eq!(code, 200, "{body}");
    assert_eq!(get(admin, path).0, 404);
    let points_kept = r#"fbbus_console_entries{what="history_points"}"#;
    let deadline = Instant::now() + Duration::from_secs(5);
    while broker.metric(points_kept) != 0.0 || broker.metric(series) != 0.0 {
        assert!(Instant::now() < deadline, "{}", broker.metrics());
        std::thread::sleep(Duration::from_millis(50));
    }
}

const DEVICES: usize = 1000;
const PORTS: usize = 10;
const VALUES: usize = 25;
const MAX_POINTS: usize = 200_000;

/// At plant size: 1,000 devices x 10 INT outputs, 25 values each (250,000 values) into a
/// history of at most 200,000 points: every port keeps its share (20 points, the newest),
/// the total stays under the bound, and the history costs the broker about what the bound
/// allows, not what was sent: the same load on a broker without history
/// (`history_max_points = 0`) is the baseline of the resident memory's growth (the
/// router's log, the registry's activity and the last values grow with both).
#[test]
fn history_memory_is_bounded_at_plant_size() {
    let without = fill(0);
    let with = fill(MAX_POINTS);
    let cost = with.grew_kib.saturating_sub(without.grew_kib);
    // Points of 16 bytes in buffers at most twice what they hold, and the series' tables.
    let bound_kib = (MAX_POINTS * 16 * 2 + DEVICES * PORTS * 400) as u64 / 1024;
    eprintln!(
        "history at plant size: {} points, {} bytes of buffers; resident memory grew by {} KiB \
         with history, {} KiB without: the history's cost {cost} KiB (bound {bound_kib} KiB)",
        with.points, with.bytes, with.grew_kib, without.grew_kib
    );
    assert_eq!(without.points, 0.0);
    assert!(with.bytes <= (MAX_POINTS * 16 * 2) as f64, "{}", with.bytes);
    assert!(cost < bound_kib, "the history cost {cost} KiB");
}

struct Filled {
    grew_kib: u64,
    points: f64,
    bytes: f64,
}

/// Registers the devices, then sends their values to a broker keeping at most
/// `max_points`; checks what it keeps, and measures its growth.
fn fill(max_points: usize) -> Filled {
    let broker = Broker::start_with(
        Options {
            extra: format!(
                "[fb]\nmax_devices_per_identity = 10000\n\
                 [console]\nhistory_max_points = {max_points}\n"
            ),
            ..Options::default()
        },
        |_| {},
    );
    let ports: Vec<String> = (0..PORTS).map(|p| format!("\"P{p}\":\"INT\"")).collect();
    let declaration = format!(
        "{{\"fbs\":{{\"F\":{{\"type\":\"T\",\"data_out\":{{{}}}}}}}}}",
        ports.join(",")
    );
    let port = broker.port();
    // Declared over 4 connections at once, each device on its own.
    let threads: Vec<_> = (0..4)
        .map(|t| {
            let declaration = declaration.clone();
            std::thread::spawn(move || {
                for i in (t..DEVICES).step_by(4) {
                    let id = format!("dev-{i:04}");
                    let mut c = RawClient::connect(port);
                    let connect = Connect {
                        version: 5,
                        client_id: &id,
                        ..Default::default()
                    };
                    assert_eq!(c.handshake(&connect), 0);
                    let topic = format!("fbbus/declare/{id}");
                    c.send(&raw::publish_v5(&topic, None, 1, 1, declaration.as_bytes()));
                    loop {
                        let (byte1, body) = c.read_packet().expect("PUBACK");
                        if byte1 >> 4 == 4 {
                            assert_eq!(body.get(2).copied().unwrap_or(0), 0, "{id}");
                            break;
                        }
                    }
                    c.send(&raw::DISCONNECT);
                    assert!(c.closed_by_broker());
                }
            })
        })
        .collect();
    for t in threads {
        t.join().unwrap();
    }
    let before = settled_rss_kib(&broker, Duration::from_secs(2));
    // The values in rounds, one value of every port each, as a line's devices send them:
    // the next round once the console took this one (values of a port that reach it in
    // one read make one point, `activity::Newest`).
    let mut devices: Vec<RawClient> = (0..DEVICES)
        .map(|i| {
            let mut c = RawClient::connect(port);
            let id = format!("dev-{i:04}");
            let connect = Connect {
                version: 5,
                client_id: &id,
                ..Default::default()
            };
            assert_eq!(c.handshake(&connect), 0);
            c
        })
        .collect();
    let taken = |round: usize| -> (&'static str, f64) {
        let values = (DEVICES * PORTS * (round + 1)) as f64;
        if max_points == 0 {
            // Nothing kept, every port counted as refused once per value.
            (
                r#"fbbus_console_dropped_total{what="history_ports"}"#,
                values,
            )
        } else {
            // The fair share here is 20 points a port (`history::share`).
            let share = (max_points / (DEVICES * PORTS)).min(round + 1);
            (
                r#"fbbus_console_entries{what="history_points"}"#,
                (DEVICES * PORTS * share) as f64,
            )
        }
    };
    for round in 0..VALUES {
        for (i, c) in devices.iter_mut().enumerate() {
            let mut batch = Vec::new();
            for p in 0..PORTS {
                let topic = format!("fb/dev-{i:04}/F/P{p}");
                batch.extend(raw::publish_v5(
                    &topic,
                    None,
                    0,
                    0,
                    round.to_string().as_bytes(),
                ));
            }
            c.send(&batch);
        }
        let (metric, want) = taken(round);
        assert_eq!(broker.wait_metric(metric, want), want, "round {round}");
    }
    for mut c in devices {
        c.send(&raw::DISCONNECT);
    }
    let series = r#"fbbus_console_entries{what="history_series"}"#;
    let kept = r#"fbbus_console_entries{what="history_points"}"#;
    let dropped = r#"fbbus_console_dropped_total{what="history_ports"}"#;
    if max_points == 0 {
        let after = settled_rss_kib(&broker, Duration::from_secs(5));
        return Filled {
            grew_kib: after.saturating_sub(before),
            points: broker.metric(kept),
            bytes: broker.metric("fbbus_console_history_bytes"),
        };
    }
    let want_series = (DEVICES * PORTS) as f64;
    let deadline = Instant::now() + Duration::from_secs(60);
    loop {
        let last = json(broker.admin, "/api/v1/devices/dev-0999/ports/F.P9/history");
        let newest = points_of(&last).last().copied();
        if broker.metric(series) == want_series && newest == Some((VALUES - 1) as f64) {
            break;
        }
        assert!(Instant::now() < deadline, "{last}\n{}", broker.metrics());
        std::thread::sleep(Duration::from_millis(200));
    }
    let points = broker.metric(kept);
    assert!(points <= max_points as f64, "{points} points kept");
    assert!(
        points >= (DEVICES * PORTS * 16) as f64,
        "every port keeps at least 16 points: {points}"
    );
    // The rounds past the share are not waited for one by one: the newest of each port
    // comes in whatever order the router serves the devices.
    let sample = wait_json(
        broker.admin,
        "/api/v1/devices/dev-0500/ports/F.P3/history",
        |h| points_of(h).last() == Some(&((VALUES - 1) as f64)),
    );
    let values: Vec<f64> = points_of(&sample);
    let share = sample["capacity"].as_u64().unwrap() as usize;
    assert_eq!(values.len(), share, "{sample}");
    assert_eq!(
        values.last(),
        Some(&((VALUES - 1) as f64)),
        "the newest kept: {sample}"
    );
    assert_eq!(broker.metric(dropped), 0.0);
    let after = settled_rss_kib(&broker, Duration::from_secs(5));
    Filled {
        grew_kib: after.saturating_sub(before),
        points,
        bytes: broker.metric("fbbus_console_history_bytes"),
    }
}

fn points_of(history: &Value) -> Vec<f64> {
    points(history).iter().map(|p| p.1).collect()
}

/// The connected clients with where they come from, protocol, keep-alive, subscriptions
/// and messages, paged; and the retained topics under a filter with size, owner and age.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn the_clients_and_the_retained_topics_are_listed() {
    let broker = Broker::start();
    let admin = broker.admin;
    let mut watch = V4::connect(broker.port(), "watch", None).await.unwrap();
    watch.subscribe("plant/#").await;
    watch.subscribe("fb/+/CONV/#").await;
    let other = V4::connect(broker.port(), "zz-other", None).await.unwrap();
    for i in 0..3 {
        watch
            .client
            .publish(
                format!("plant/Förderband/{i}"),
                QoS::AtLeastOnce,
                true,
                "ok-ä",
            )
            .await
            .unwrap();
    }
    // Received back by its own subscription: 3 in, 3 out.
    let listed = wait_json(admin, "/api/v1/clients", |c| {
        c["clients"]
            .as_array()
            .and_then(|l| l.iter().find(|c| c["client_id"] == "watch"))
            .is_some_and(|w| w["messages_in"] == 3 && w["messages_out"] == 3)
    });
    let clients = listed["clients"].as_array().unwrap();
    let ids: Vec<&str> = clients
        .iter()
        .filter_map(|c| c["client_id"].as_str())
        .collect();
    assert_eq!(ids, ["watch", "zz-other"], "{listed}");
    let w = &clients[0];
    assert_eq!(w["protocol"], "3.1.1", "{w}");
    assert_eq!(w["keep_alive_s"], 30, "{w}");
    assert_eq!(w["subscriptions"], 2, "{w}");
    assert_eq!(w["listener"], "main", "{w}");
    assert!(
        w["address"].as_str().unwrap().starts_with("127.0.0.1:"),
        "{w}"
    );
    assert!(w["username"].is_null(), "{w}");
    assert!(w["connected_since"].as_str().unwrap().ends_with('Z'), "{w}");
    assert_eq!(listed["total"], 2);
    // Paged: one at a time.
    let first = json(admin, "/api/v1/clients?limit=1");
    assert_eq!(first["next"], "watch", "{first}");
    let second = json(admin, "/api/v1/clients?limit=1&after=watch");
    assert_eq!(second["clients"][0]["client_id"], "zz-other", "{second}");
    assert_eq!(get(admin, "/api/v1/clients?limit=0").0, 400);
    // A client gone is gone from the list.
    drop(other);
    wait_json(admin, "/api/v1/clients", |c| c["total"] == 1);

    // Retained: under a filter, in topic order, with size, owner and age.
    let retained = json(admin, "/api/v1/retained?filter=plant/%2B/1");
    let list = retained["retained"].as_array().unwrap();
    assert_eq!(list.len(), 1, "{retained}");
    assert_eq!(list[0]["topic"], "plant/Förderband/1");
    assert_eq!(
        list[0]["bytes"],
        "plant/Förderband/1".len() + "ok-ä".len(),
        "{retained}"
    );
    assert_eq!(list[0]["owner"], "address:127.0.0.1", "{retained}");
    assert!(list[0]["age_s"].as_u64().is_some(), "{retained}");
    let all = json(admin, "/api/v1/retained?filter=plant/%23&limit=2");
    let topics: Vec<&str> = all["retained"]
        .as_array()
        .unwrap()
        .iter()
        .filter_map(|r| r["topic"].as_str())
        .collect();
    assert_eq!(topics, ["plant/Förderband/0", "plant/Förderband/1"]);
    assert_eq!(all["next"], "plant/Förderband/1", "{all}");
    let rest = json(
        admin,
        "/api/v1/retained?filter=plant/%23&after=plant/F%C3%B6rderband/1",
    );
    assert_eq!(rest["retained"][0]["topic"], "plant/Förderband/2", "{rest}");
    assert!(rest["next"].is_null(), "{rest}");
    let (code, _, body) = get(admin, "/api/v1/retained?filter=a/%23/b");
    assert_eq!(code, 400, "{body}");
    // Cleared: no longer listed.
    watch
        .client
        .publish("plant/Förderband/0", QoS::AtLeastOnce, true, "")
        .await
        .unwrap();
    wait_json(admin, "/api/v1/retained?filter=plant/%23", |r| {
        r["retained"].as_array().is_some_and(|l| l.len() == 2)
    });
}

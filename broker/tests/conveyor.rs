//! The conveyor line example (fb-bridge/examples/conveyor) against the real broker:
//! modules follow the online count, carry parts, and survive an addition, an abrupt
//! removal (will + count drop) and a swap; once with every module a declaring contract
//! device, once with a FORTE-like and a DINASORE-like module among them, which the
//! broker knows from the profiles the example writes.

mod common;

use std::process::Command;
use std::time::{Duration, Instant};

use common::fb::conveyor_example;
use common::{http_get, run, Broker, Options};

#[test]
fn the_conveyor_line_runs_add_remove_and_swap_to_completion() {
    let example = conveyor_example();
    let broker = Broker::start();
    let (ok, out, err) = run(
        Command::new(&example).args([
            "--host",
            "127.0.0.1",
            "--port",
            &broker.port().to_string(),
            "--count",
            "3",
            "--parts",
            "1",
        ]),
        Duration::from_secs(120),
    );
    assert!(
        ok,
        "the conveyor line failed:\n{out}\n{err}\nbroker log:\n{}",
        broker.log_text()
    );
    for phase in [
        "== phase 3: conveyor-d is plugged in",
        "== phase 4: conveyor-b is unplugged abruptly",
        "every module saw the count drop",
        "== phase 5: conveyor-a and conveyor-c swap places",
        "line: conveyor-c -> conveyor-a -> conveyor-d",
        "all phases completed",
    ] {
        assert!(out.contains(phase), "missing `{phase}` in:\n{out}");
    }
    // The broker saw typed traffic, refused none of it, and the will of the unplugged module.
    assert_typed_traffic_clean(&broker);
    assert!(broker.metric("fbbus_wills_published_total") >= 1.0);
}

/// Typed messages accepted, none refused, every re-encoding delivered.
fn assert_typed_traffic_clean(broker: &Broker) {
    assert!(broker.metric("fbbus_typed_messages_accepted_total") > 0.0);
    let metrics = broker.metrics();
    let refused: Vec<&str> = metrics
        .lines()
        .filter(|l| {
            l.starts_with("fbbus_typed_messages_rejected_total")
                || l.starts_with("fbbus_typed_messages_not_reencoded_total")
        })
        .collect();
    assert!(refused.is_empty(), "typed messages refused: {refused:?}");
}

/// Issue: "The conveyor example of the reference study (three modules, add/remove/swap)
/// runs with one module as a FORTE-like device and one as a DINASORE-like device next to
/// `fb_bridge::client` devices." conveyor-b talks as FORTE does (no declaration, no will,
/// `fbdk` on its own topics) and is the one unplugged: the broker-side will of its
/// profile is what tells the others. conveyor-c talks as DINASORE does (a connection per
/// value, random client ids, values as strings, data outputs only) and swaps places.
#[test]
fn the_conveyor_line_runs_with_forte_and_dinasore_modules() {
    let example = conveyor_example();
    let runtimes = ["--forte", "conveyor-b", "--dinasore", "conveyor-c"];
    // The example writes the two profiles; the broker reads them at start.
    let broker = Broker::start_with(
        Options {
            extra: "[fb]\nprofiles_dir = \"profiles\"\n".into(),
            ..Default::default()
        },
        |dir| {
            let profiles = dir.join("profiles");
            let (ok, out, err) = run(
                Command::new(&example)
                    .arg("--print-profiles")
                    .arg(&profiles)
                    .args(runtimes),
                Duration::from_secs(30),
            );
            assert!(ok, "--print-profiles failed:\n{out}\n{err}");
            for id in ["conveyor-b", "conveyor-c"] {
                assert!(profiles.join(format!("{id}.toml")).exists(), "{out}");
            }
        },
    );
    let started = Instant::now();
    let (ok, out, err) = run(
        Command::new(&example)
            .args([
                "--host",
                "127.0.0.1",
                "--port",
                &broker.port().to_string(),
                "--line",
                "test",
                "--count",
                "3",
                "--parts",
                "1",
                "--unplug",
                "conveyor-b",
            ])
            .args(runtimes),
        Duration::from_secs(120),
    );
    assert!(
        ok,
        "the conveyor line failed:\n{out}\n{err}\nbroker log:\n{}",
        broker.log_text()
    );
    eprintln!("the line ran in {:?}", started.elapsed());
    for expected in [
        "conveyor-b: connected (FORTE",
        "conveyor-c: connected (DINASORE",
        "== phase 3: conveyor-d is plugged in",
        "== phase 4: conveyor-b is unplugged abruptly",
        "every module saw the count drop",
        "== phase 5: conveyor-a and conveyor-c swap places",
        "line: conveyor-c -> conveyor-a -> conveyor-d",
        "all phases completed",
    ] {
        assert!(out.contains(expected), "missing `{expected}` in:\n{out}");
    }
    // Parts crossed every runtime boundary, both ways.
    for hop in [
        "conveyor-a -> conveyor-b",
        "conveyor-b -> conveyor-c",
        "conveyor-c -> conveyor-d",
        "conveyor-c -> conveyor-a",
    ] {
        assert!(
            out.lines().any(|l| l.contains("part ") && l.contains(hop)),
            "no part went {hop}:\n{out}"
        );
    }
    // FORTE's broker-side will (CONV.CONNECT = FALSE from its profile) reached the
    // contract modules and the DINASORE module.
    for module in ["conveyor-a", "conveyor-c", "conveyor-d"] {
        let heard = format!("{module}: conveyor-b CONNECT = FALSE (its will)");
        assert!(out.contains(&heard), "missing `{heard}` in:\n{out}");
    }
    assert!(broker.metric("fbbus_wills_published_total") >= 1.0);
    let (code, record) = http_get(broker.admin, "/api/v1/devices/conveyor-b").expect("admin");
    assert_eq!(code, 200, "{record}");
    assert!(record.contains("\"offline\""), "{record}");
    // Its typed traffic, own topics and re-encodings alike: accepted, none refused.
    assert_typed_traffic_clean(&broker);
}

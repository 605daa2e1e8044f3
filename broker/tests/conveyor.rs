//! The conveyor line example (fb-bridge/examples/conveyor) against the real broker:
//! modules declare typed interfaces, follow the online count, carry parts, and survive
//! an addition, an abrupt removal (will + count drop within 1.5 x keep-alive) and a swap.

mod common;

use std::path::PathBuf;
use std::process::Command;
use std::time::Duration;

use common::{run, Broker};

/// Builds the example (a no-op when `cargo test --workspace` already did) and returns it.
fn conveyor_example() -> PathBuf {
    let (ok, _, err) = run(
        Command::new(env!("CARGO")).args(["build", "-p", "fb-bridge", "--example", "conveyor"]),
        Duration::from_secs(600),
    );
    assert!(ok, "cannot build the conveyor example: {err}");
    // target/debug/fbbus -> target/debug/examples/conveyor
    PathBuf::from(env!("CARGO_BIN_EXE_fbbus"))
        .with_file_name("examples")
        .join("conveyor")
}

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
    assert!(broker.metric("fbbus_typed_messages_accepted_total") > 0.0);
    assert_eq!(
        broker
            .metrics()
            .lines()
            .filter(|l| l.starts_with("fbbus_typed_messages_rejected_total"))
            .count(),
        0,
        "no typed publication refused"
    );
    assert!(broker.metric("fbbus_wills_published_total") >= 1.0);
}

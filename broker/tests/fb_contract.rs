//! A device written from the device contract (docs/device-contract.md) alone: a paho-mqtt
//! script that knows only the contract declares, publishes, is refused, reads both
//! encodings and the registry, against the real `fbbus` binary.
//!
//! Helpers are in `common/fb.rs`.

mod common;

use std::process::Command;
use std::time::Duration;

use common::fb::*;
use common::Broker;

// ------------------------------------------------------ a device from the device contract

const CONTRACT_SCRIPT: &str = concat!(env!("CARGO_MANIFEST_DIR"), "/tests/python/fb_contract.py");

/// A paho-mqtt device that knows only docs/device-contract.md declares, publishes, is
/// refused, reads both encodings and the registry (see the script's docstring).
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn python_device_follows_the_readme_contract() {
    if !common::require_paho() {
        return;
    }
    let broker = Broker::start();
    let (ok, out, err) = tokio::task::block_in_place(|| {
        common::run(
            Command::new("python3")
                .arg("-u")
                .arg(CONTRACT_SCRIPT)
                .args(["--port", &broker.port().to_string()]),
            Duration::from_secs(60),
        )
    });
    assert!(
        ok,
        "fb_contract.py failed\n--- stdout\n{out}\n--- stderr\n{err}\n--- broker log\n{}",
        broker.log_text()
    );
    eprintln!("fb_contract.py: {}", out.trim());
    // The broker's side of the same story.
    assert_metric(
        &broker,
        r#"fbbus_declarations_total{result="accepted"}"#,
        1.0,
    );
    assert_eq!(
        broker.wait_metric(
            &rejected_series("py-dev", "CONV.MOVED", "payload_format_invalid"),
            1.0
        ),
        1.0
    );
    assert_metric(&broker, "fbbus_typed_messages_accepted_total", 2.0);
    // It disconnected cleanly at the end.
    wait_record(
        &broker,
        "py-dev",
        "disconnected",
        offline_because("clean disconnect"),
    )
    .await;
}

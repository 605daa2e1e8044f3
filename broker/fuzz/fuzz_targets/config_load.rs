//! The broker's configuration loader (`broker::config::Config`, `fbbus serve --config`
//! and `fbbus check-config`) on arbitrary text: TOML parsing with serde, the path in error
//! messages, the secure-by-default rules and the limits.
//!
//! Every input goes through `Config::parse`; one that parses is also written to a file in
//! a temporary directory (created once, the only file this target writes) and loaded with
//! `Config::load`, which resolves relative paths and checks that the files it names exist
//! (read-only `stat`s; nothing is bound, nothing is sent). The `[bridge]` section, which
//! this zenoh-free build refuses, is read and validated on its own (`BusConfig`), as a
//! build with the `bridge` feature would. What a validated config promises is checked:
//!
//! - no listener off loopback without a password file, no anonymous access off loopback;
//! - limits the broker relies on when it starts: `max_packet_bytes` within MQTT's
//!   maximum, commit-log segments of at least 1 KiB (rumqttd panics below) and at least one
//!   packet, `max_connections` within what the connection semaphore can count
//!   (`tokio::sync::Semaphore::new` panics above `MAX_PERMITS`);
//! - the login throttle built from `[auth.throttle]` as the authenticator builds it never
//!   panics, whatever the delays.
#![no_main]

use std::net::{IpAddr, Ipv4Addr};
use std::path::PathBuf;
use std::sync::OnceLock;
use std::time::{Duration, Instant};

use broker::config::Config;
use fb_bridge::bus::BusConfig;
use libfuzzer_sys::fuzz_target;
use security::{LoginThrottle, ThrottleConfig};

/// The one file this target writes, in a temporary directory of its own that is removed
/// when the process exits (libFuzzer ends a run with `exit`, so `atexit` runs; after a
/// crash the directory stays, with the crashing config in it).
fn scratch() -> &'static PathBuf {
    static FILE: OnceLock<PathBuf> = OnceLock::new();
    FILE.get_or_init(|| {
        let dir = tempfile::Builder::new()
            .prefix("fbbus-fuzz-config")
            .tempdir()
            .expect("a temporary directory")
            .keep();
        extern "C" fn remove_scratch() {
            if let Some(dir) = FILE.get().and_then(|f| f.parent()) {
                let _ = std::fs::remove_dir_all(dir);
            }
        }
        // SAFETY: registers a plain function; it only reads a set OnceLock.
        unsafe { libc::atexit(remove_scratch) };
        dir.join("fbbus.toml")
    })
}

fuzz_target!(|data: &[u8]| {
    let Ok(text) = std::str::from_utf8(data) else {
        return;
    };
    bridge_section(text);
    let config = match Config::parse(text, "fuzz.toml") {
        Ok(config) => config,
        Err(e) => {
            let message = e.to_string();
            // A value or key is named; a syntax error before any key says so.
            assert!(
                message.starts_with("config file fuzz.toml: key `")
                    || message.starts_with("config file fuzz.toml: not TOML:\n"),
                "{message}"
            );
            return;
        }
    };
    promises(&config);

    let path = scratch();
    std::fs::write(path, text).expect("write the scratch config");
    match Config::load(path) {
        Ok(loaded) => {
            promises(&loaded);
            // Relative paths are resolved against the file's directory.
            for p in loaded
                .auth
                .password_file
                .iter()
                .chain(&loaded.auth.acl_file)
            {
                assert!(p.is_absolute(), "{} not resolved", p.display());
            }
        }
        Err(e) => {
            let _ = e.to_string();
        }
    }
});

fn promises(config: &Config) {
    let b = &config.broker;
    assert!(!config.listeners.is_empty());
    for (i, l) in config.listeners.iter().enumerate() {
        let anonymous = l.anonymous(&config.auth);
        if !l.bind.ip().is_loopback() {
            assert!(
                config.auth.password_file.is_some() && !anonymous,
                "listener {i} on {} without authentication",
                l.bind
            );
        }
        if !anonymous {
            assert!(
                config.auth.password_file.is_some(),
                "listener {i}: nobody could log in"
            );
        }
        assert!(
            !config.listeners[..i].iter().any(|o| o.name == l.name),
            "listener name {:?} twice",
            l.name
        );
    }
    assert!((64..=268_435_455).contains(&b.max_packet_bytes));
    assert!(b.router_segment_bytes >= 1024 && b.router_segment_bytes >= b.max_packet_bytes);
    assert!(b.router_segment_count >= 1 && b.max_connections >= 1);
    // server.rs: `Semaphore::new(config.broker.max_connections)`.
    assert!(
        b.max_connections <= tokio::sync::Semaphore::MAX_PERMITS,
        "max_connections {} validates but the connection semaphore cannot hold it",
        b.max_connections
    );
    let _ = config.connect_timeout();

    // The throttle as `Authenticator::new` builds it, through a short failure streak.
    let t = &config.auth.throttle;
    let throttle = LoginThrottle::new(ThrottleConfig {
        free_failures: t.free_failures,
        base_delay: Duration::from_millis(t.base_delay_ms),
        max_delay: Duration::from_millis(t.max_delay_ms),
        ..ThrottleConfig::default()
    });
    let peer = IpAddr::V4(Ipv4Addr::LOCALHOST);
    let now = Instant::now();
    for _ in 0..t.free_failures.min(8) + 3 {
        if let Some(block) = throttle.record_failure(peer, now) {
            assert!(block <= Duration::from_millis(t.max_delay_ms));
        }
        let _ = throttle.check(peer, now);
    }
}

/// The `[bridge]` section, read and validated as a build with the `bridge` feature does.
fn bridge_section(text: &str) {
    let Ok(table) = text.parse::<toml::Table>() else {
        return;
    };
    let Some(bridge) = table.get("bridge").cloned() else {
        return;
    };
    let Ok(bus) = bridge.try_into::<BusConfig>() else {
        return;
    };
    let line = table
        .get("broker")
        .and_then(|b| b.get("line"))
        .and_then(|l| l.as_str())
        .unwrap_or("line-1");
    if bus.validate(line).is_ok() {
        for f in bus.export.iter().chain(&bus.import) {
            assert!(fb_bridge::bus::keys::bridgeable_filter(f));
            assert!(fb_bridge::bus::keys::import_key(f).is_some());
        }
    }
}

use super::*;

#[test]
fn embedded_default_is_loopback_and_anonymous() {
    let c = Config::embedded_default();
    assert_eq!(c.listeners.len(), 1);
    assert!(c.listeners[0].bind.ip().is_loopback());
    assert!(c.listeners[0].anonymous(&c.auth));
    assert!(c.admin.bind.ip().is_loopback());
}

#[test]
fn non_loopback_without_password_file_is_refused() {
    let err = Config::parse(
        "[[listener]]\nname = \"a\"\nbind = \"0.0.0.0:1883\"\n",
        "line.toml",
    )
    .unwrap_err()
    .to_string();
    assert!(err.contains("line.toml"), "{err}");
    assert!(err.contains("listener[0].bind"), "{err}");
    assert!(err.contains("password_file"), "{err}");
}

/// Issue 18: an admin endpoint off loopback needs its own password file; the MQTT
/// password file does not count (a device's password must not open the admin plane).
#[test]
fn non_loopback_admin_needs_an_admin_password_file() {
    let listener = "[[listener]]\nname=\"a\"\nbind=\"127.0.0.1:1\"\n";
    for bind in [
        "0.0.0.0:9883",
        "10.1.0.5:9883",
        "[::]:9883",
        "[::ffff:10.1.0.5]:9883",
    ] {
        for auth in ["", "[auth]\npassword_file = \"p\"\n"] {
            let err = Config::parse(
                &format!("{auth}{listener}[admin]\nbind = \"{bind}\"\n"),
                "line.toml",
            )
            .unwrap_err()
            .to_string();
            for part in [
                "line.toml",
                "admin.bind",
                "[admin] password_file",
                "fbbus passwd",
            ] {
                assert!(err.contains(part), "{bind} {auth}: {err}");
            }
        }
        let c = Config::parse(
            &format!("{listener}[admin]\nbind = \"{bind}\"\npassword_file = \"admin\"\n"),
            "f",
        )
        .unwrap();
        assert_eq!(c.admin.password_file, Some(PathBuf::from("admin")));
    }
    for bind in [
        "127.0.0.1:9883",
        "127.0.0.2:9883",
        "[::1]:9883",
        "[::ffff:127.0.0.1]:9883",
    ] {
        let c = Config::parse(&format!("{listener}[admin]\nbind = \"{bind}\"\n"), "f").unwrap();
        assert_eq!(c.admin.password_file, None);
    }
}

/// The admin password file is not the MQTT one, and it must exist.
#[test]
fn admin_password_file_is_its_own_and_exists() {
    let dir = tempfile::tempdir().unwrap();
    std::fs::write(dir.path().join("passwd"), "").unwrap();
    std::fs::write(dir.path().join("admin-passwd"), "").unwrap();
    let load = |auth: &str, admin: &str| {
        let path = dir.path().join("line.toml");
        std::fs::write(
            &path,
            format!(
                "[auth]\npassword_file = \"{auth}\"\n[[listener]]\nname=\"a\"\n\
                 bind=\"127.0.0.1:1\"\n[admin]\nbind=\"0.0.0.0:0\"\npassword_file = \"{admin}\"\n"
            ),
        )
        .unwrap();
        Config::load(&path).map_err(|e| e.to_string())
    };
    let c = load("passwd", "admin-passwd").unwrap();
    assert_eq!(c.admin.password_file, Some(dir.path().join("admin-passwd")));
    let err = load("passwd", "./passwd").unwrap_err();
    assert!(err.contains("admin.password_file"), "{err}");
    assert!(err.contains("[auth] password_file"), "{err}");
    let err = load("passwd", "missing").unwrap_err();
    assert!(err.contains("admin.password_file"), "{err}");
    assert!(err.contains("does not exist"), "{err}");
}

#[test]
fn anonymous_on_non_loopback_is_refused() {
    let err = Config::parse(
        "[auth]\npassword_file = \"p\"\n[[listener]]\nname = \"a\"\nbind = \"0.0.0.0:1883\"\nallow_anonymous = true\n",
        "f",
    )
    .unwrap_err()
    .to_string();
    assert!(err.contains("listener[0].allow_anonymous"), "{err}");
}

#[test]
fn unknown_key_names_the_key() {
    let err = Config::parse("[broker]\nmax_conections = 3\n", "f")
        .unwrap_err()
        .to_string();
    assert!(err.contains("max_conections"), "{err}");
    assert!(err.contains("broker"), "{err}");
}

#[test]
fn wrong_type_names_the_key() {
    let err = Config::parse(
        "[broker]\nmax_connections = \"many\"\n[[listener]]\nname=\"a\"\nbind=\"127.0.0.1:1\"\n",
        "f",
    )
    .unwrap_err()
    .to_string();
    assert!(err.contains("broker.max_connections"), "{err}");
}

#[test]
fn client_id_binding_needs_a_password_file() {
    let listener = "[[listener]]\nname=\"a\"\nbind=\"127.0.0.1:1\"\n";
    let err = Config::parse(&format!("[auth]\nclient_id = \"%u\"\n{listener}"), "f")
        .unwrap_err()
        .to_string();
    assert!(err.contains("auth.client_id"), "{err}");
    let err = Config::parse(&format!("[auth]\nclient_id = \"%c\"\n{listener}"), "f")
        .unwrap_err()
        .to_string();
    assert!(err.contains("auth.client_id"), "{err}");
    let c = Config::parse(
        &format!("[auth]\npassword_file = \"p\"\nclient_id = \"%u-*\"\n{listener}"),
        "f",
    )
    .unwrap();
    assert_eq!(
        c.auth.client_id,
        crate::identity::ClientIdRule::UsernamePrefix
    );
    assert_eq!(
        Config::embedded_default().auth.client_id,
        crate::identity::ClientIdRule::Any
    );
}

#[test]
fn fbdk_time_unit_is_ns_unless_ms_is_said() {
    use fb_bridge::codec::fbdk::TimeUnit;
    let listener = "[[listener]]\nname=\"a\"\nbind=\"127.0.0.1:1\"\n";
    let unit = |fb: &str| {
        Config::parse(&format!("[fb]\n{fb}\n{listener}"), "f")
            .map(|c| c.fb.fbdk_time_unit)
            .map_err(|e| e.to_string())
    };
    assert_eq!(unit(""), Ok(TimeUnit::Nanoseconds));
    assert_eq!(
        Config::embedded_default().fb.fbdk_time_unit,
        TimeUnit::Nanoseconds
    );
    assert_eq!(unit("fbdk_time_unit = \"ns\""), Ok(TimeUnit::Nanoseconds));
    assert_eq!(unit("fbdk_time_unit = \"ms\""), Ok(TimeUnit::Milliseconds));
    let err = unit("fbdk_time_unit = \"us\"").unwrap_err();
    assert!(err.contains("fb.fbdk_time_unit"), "{err}");
    assert!(err.contains("`ns` or `ms`"), "{err}");
}

/// The registry's bounds: 10,000 devices, 100 per identity, never forgotten by age;
/// a limit of 0 would refuse every device and is refused instead.
#[test]
fn registry_limits_default_and_are_at_least_1() {
    let listener = "[[listener]]\nname=\"a\"\nbind=\"127.0.0.1:1\"\n";
    let limits = |fb: &str| {
        Config::parse(&format!("[fb]\n{fb}\n{listener}"), "f")
            .map(|c| c.fb.registry_limits())
            .map_err(|e| e.to_string())
    };
    let default = limits("").unwrap();
    assert_eq!(
        default,
        crate::registry::Limits {
            max_devices: 10_000,
            max_per_identity: 100,
            forget_offline_after: None,
            max_remote_per_line: 5_000,
            max_remote: 40_000,
        }
    );
    let set = limits("max_remote_devices_per_line = 7\nmax_remote_devices = 70").unwrap();
    assert_eq!((set.max_remote_per_line, set.max_remote), (7, 70));
    assert!(limits("max_remote_devices = 0")
        .unwrap_err()
        .contains("fb.max_remote_devices"));
    let set = limits("max_devices = 20\nforget_offline_after_s = 3600").unwrap();
    assert_eq!(set.max_devices, 20);
    assert_eq!(
        set.forget_offline_after,
        Some(std::time::Duration::from_secs(3600))
    );
    for (bad, key) in [
        ("max_devices = 0", "fb.max_devices"),
        (
            "max_devices_per_identity = 0",
            "fb.max_devices_per_identity",
        ),
    ] {
        let err = limits(bad).unwrap_err();
        assert!(err.contains(key), "{bad}: {err}");
    }
}

/// The silence keys become durations: a value no duration can hold (negative, NaN,
/// huge) is refused here, never reaches `Duration::from_secs_f64`.
#[test]
fn silence_keys_default_to_3_and_5_s_and_are_bounded() {
    let listener = "[[listener]]\nname=\"a\"\nbind=\"127.0.0.1:1\"\n";
    let bound = |fb: &str| {
        Config::parse(&format!("[fb]\n{fb}\n{listener}"), "f")
            .map(|c| c.fb.silence_bound())
            .map_err(|e| e.to_string())
    };
    let default = bound("").unwrap();
    assert_eq!(default.factor, 3.0);
    assert_eq!(default.floor, std::time::Duration::from_secs(5));
    assert!(!bound("silence_factor = 0").unwrap().enabled());
    assert_eq!(
        bound("silence_min_s = 0.5").unwrap().floor,
        std::time::Duration::from_millis(500)
    );
    for bad in [
        "silence_factor = -1",
        "silence_factor = nan",
        "silence_min_s = 1e300",
        "silence_min_s = -0.1",
    ] {
        let err = bound(bad).unwrap_err();
        assert!(err.contains("fb.silence_"), "{bad}: {err}");
    }
}

/// Regression (broker/fuzz/regressions/config_load): a max_connections the broker
/// cannot start with is refused when the file is read.
#[test]
fn max_connections_is_bounded() {
    let config = |n: u64| {
        Config::parse(
            &format!(
                "[broker]\nmax_connections = {n}\n[[listener]]\nname=\"a\"\nbind=\"127.0.0.1:1\"\n"
            ),
            "f",
        )
    };
    for n in [0, MAX_CONNECTIONS as u64 + 1, 9_000_000_000_000_000_000] {
        let err = config(n).unwrap_err().to_string();
        assert!(err.contains("broker.max_connections"), "{n}: {err}");
    }
    assert!(config(MAX_CONNECTIONS as u64).is_ok());
}

#[test]
fn liveness_limits_are_bounded() {
    let config = |keys: &str| {
        Config::parse(
            &format!("[broker]\n{keys}\n[[listener]]\nname=\"a\"\nbind=\"127.0.0.1:1\"\n"),
            "f",
        )
    };
    let c = config("").unwrap();
    assert_eq!(c.broker.slow_consumer_timeout_ms, 10_000);
    assert_eq!(c.dead_link_timeout(), Some(Duration::from_secs(20)));
    for (keys, key) in [
        (
            "slow_consumer_timeout_ms = 0",
            "broker.slow_consumer_timeout_ms",
        ),
        (
            "slow_consumer_timeout_ms = 600001",
            "broker.slow_consumer_timeout_ms",
        ),
        (
            "slow_consumer_max_bytes = 1000",
            "broker.slow_consumer_max_bytes",
        ),
        ("dead_link_timeout_s = 3601", "broker.dead_link_timeout_s"),
        ("sys_interval_s = 86401", "broker.sys_interval_s"),
        ("worker_threads = 257", "broker.worker_threads"),
    ] {
        let err = config(keys).unwrap_err().to_string();
        assert!(err.contains(key), "{keys}: {err}");
    }
    assert_eq!(
        config("dead_link_timeout_s = 0")
            .unwrap()
            .dead_link_timeout(),
        None
    );
}

#[test]
fn websocket_listener_keys_are_checked() {
    let listener = |keys: &str| {
        Config::parse(
            &format!("[[listener]]\nname=\"a\"\nbind=\"127.0.0.1:1\"\n{keys}"),
            "f",
        )
    };
    let ws = listener(
        "kind = \"ws\"\npath = \"/line/mqtt\"\nallowed_origins = [\"https://hmi.example:8443\"]\n",
    )
    .unwrap();
    let handshake = ws.listeners[0].websocket().expect("a ws listener");
    assert_eq!(handshake.path, "/line/mqtt");
    assert!(listener("").unwrap().listeners[0].websocket().is_none());
    assert_eq!(
        listener("kind = \"ws\"\n").unwrap().listeners[0]
            .websocket()
            .unwrap()
            .path,
        "/mqtt"
    );
    for (keys, key) in [
        ("kind = \"wss\"\n", "listener[0].tls"),
        ("path = \"/mqtt\"\n", "listener[0].path"),
        ("allowed_origins = []\n", "listener[0].allowed_origins"),
        ("kind = \"ws\"\npath = \"mqtt\"\n", "listener[0].path"),
        ("kind = \"ws\"\npath = \"/mqtt?x\"\n", "listener[0].path"),
        (
            "kind = \"ws\"\nallowed_origins = [\"hmi.example\"]\n",
            "listener[0].allowed_origins",
        ),
        ("kind = \"websocket\"\n", "listener[0].kind"),
    ] {
        let err = listener(keys).unwrap_err().to_string();
        assert!(err.contains(key), "{keys}: {err}");
    }
}

/// `worker_threads = 0` leaves the router's thread a core: one fewer than the cores, never
/// none; a number given is taken as it is.
#[test]
fn worker_threads_default_to_one_fewer_than_the_cores() {
    let mut b = BrokerSection::default();
    assert_eq!(b.workers(1), 1);
    assert_eq!(b.workers(2), 1);
    assert_eq!(b.workers(8), 7);
    b.worker_threads = 4;
    assert_eq!(b.workers(2), 4);
}

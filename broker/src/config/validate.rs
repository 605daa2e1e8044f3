//! What a configuration must satisfy before anything binds: bounds on every number, the
//! security rules (a listener reachable from the network requires a password, anonymous
//! access is a loopback-only privilege, an admin endpoint off loopback requires a password
//! file of its own), and files that exist. Each refusal names the file and the key.

use std::path::Path;

use super::{Config, ConfigError, MAX_CONNECTIONS, MAX_WORKER_THREADS, MIN_QUEUED_BYTES};

impl Config {
    pub(super) fn validate(&self, file: &str) -> Result<(), ConfigError> {
        let b = &self.broker;
        if b.line.trim().is_empty() || b.line.contains(['/', '+', '#']) {
            return Err(invalid(
                file,
                "broker.line",
                "must be a non-empty name without `/`, `+` or `#`",
            ));
        }
        if !(1..=MAX_CONNECTIONS).contains(&b.max_connections) {
            return Err(invalid(
                file,
                "broker.max_connections",
                format!("must be between 1 and {MAX_CONNECTIONS}"),
            ));
        }
        if !(64..=268_435_455).contains(&b.max_packet_bytes) {
            return Err(invalid(
                file,
                "broker.max_packet_bytes",
                "must be between 64 and 268435455 (the MQTT maximum)",
            ));
        }
        let a = &self.admin;
        if !(1..=4096).contains(&a.max_connections) {
            return Err(invalid(
                file,
                "admin.max_connections",
                "must be between 1 and 4096",
            ));
        }
        if a.header_timeout_ms == 0 || a.connection_timeout_ms < a.header_timeout_ms {
            return Err(invalid(
                file,
                "admin.header_timeout_ms",
                "must be at least 1 and at most admin.connection_timeout_ms",
            ));
        }
        if !a.bind.ip().to_canonical().is_loopback() && a.password_file.is_none() {
            return Err(invalid(
                file,
                "admin.bind",
                format!(
                    "{} is not a loopback address, so the admin endpoint must require \
                     credentials: set [admin] password_file (create one with \
                     `fbbus passwd FILE add USER`; a file of its own, not [auth] password_file), \
                     or bind to 127.0.0.1",
                    a.bind
                ),
            ));
        }
        let p = &self.persistence;
        if p.max_queued_messages == 0 {
            return Err(invalid(
                file,
                "persistence.max_queued_messages",
                "must be at least 1",
            ));
        }
        if p.enabled && p.dir.as_os_str().is_empty() {
            return Err(invalid(
                file,
                "persistence.dir",
                "must name a directory (or set persistence.enabled = false)",
            ));
        }
        if b.max_retained_messages == 0 || b.max_retained_bytes == 0 {
            return Err(invalid(
                file,
                "broker.max_retained_messages",
                "max_retained_messages and max_retained_bytes must be at least 1",
            ));
        }
        if b.max_sessions_per_identity == 0 {
            return Err(invalid(
                file,
                "broker.max_sessions_per_identity",
                "must be at least 1",
            ));
        }
        if b.max_subscriptions_per_client == 0 {
            return Err(invalid(
                file,
                "broker.max_subscriptions_per_client",
                "must be at least 1",
            ));
        }
        if b.max_inflight == 0 {
            return Err(invalid(file, "broker.max_inflight", "must be at least 1"));
        }
        if b.max_inflight_out == 0 {
            return Err(invalid(
                file,
                "broker.max_inflight_out",
                "must be at least 1",
            ));
        }
        // A day bounds both: beyond it the judgement means nothing, and the durations
        // they make cannot overflow.
        for (key, value) in [
            ("fb.silence_factor", self.fb.silence_factor),
            ("fb.silence_min_s", self.fb.silence_min_s),
        ] {
            if !(0.0..=86_400.0).contains(&value) {
                return Err(invalid(file, key, "must be between 0 and 86400"));
            }
        }
        for (key, value) in [
            ("fb.max_devices", self.fb.max_devices),
            (
                "fb.max_devices_per_identity",
                self.fb.max_devices_per_identity,
            ),
            (
                "fb.max_remote_devices_per_line",
                self.fb.max_remote_devices_per_line,
            ),
            ("fb.max_remote_devices", self.fb.max_remote_devices),
        ] {
            if value == 0 {
                return Err(invalid(file, key, "must be at least 1"));
            }
        }
        let fb = &self.fb;
        for (key, value, most) in [
            (
                "fb.max_declaration_bytes",
                fb.max_declaration_bytes,
                16 << 20,
            ),
            ("fb.max_fbs", fb.max_fbs, fb_bridge::interface::MAX_FBS),
            ("fb.max_ports", fb.max_ports, 1 << 20),
            (
                "fb.declarations_per_minute",
                fb.declarations_per_minute as usize,
                1 << 20,
            ),
            ("fb.diag_burst", fb.diag_burst as usize, 1 << 20),
        ] {
            if !(1..=most).contains(&value) {
                return Err(invalid(file, key, format!("must be between 1 and {most}")));
            }
        }
        if !(fb.diag_per_second > 0.0 && fb.diag_per_second <= 1e6) {
            return Err(invalid(
                file,
                "fb.diag_per_second",
                "must be more than 0 (and at most 1000000)",
            ));
        }
        if b.connect_timeout_ms == 0 {
            return Err(invalid(
                file,
                "broker.connect_timeout_ms",
                "must be at least 1",
            ));
        }
        if b.max_pending_per_address == 0 {
            return Err(invalid(
                file,
                "broker.max_pending_per_address",
                "must be at least 1",
            ));
        }
        if b.router_segment_bytes < b.max_packet_bytes.max(1024) {
            return Err(invalid(
                file,
                "broker.router_segment_bytes",
                "must be at least 1024 (rumqttd's minimum) and at least broker.max_packet_bytes, \
                 or the largest message could not be stored",
            ));
        }
        if b.router_segment_count < 1 {
            return Err(invalid(
                file,
                "broker.router_segment_count",
                "must be at least 1",
            ));
        }
        if b.router_max_outgoing_packets == 0 {
            return Err(invalid(
                file,
                "broker.router_max_outgoing_packets",
                "must be at least 1",
            ));
        }
        if b.slow_subscriber_hold_ms > 60_000 {
            return Err(invalid(
                file,
                "broker.slow_subscriber_hold_ms",
                "must be at most 60000: a stalled subscriber would stop its filter's publishers \
                 that long",
            ));
        }
        if !(100..=600_000).contains(&b.slow_consumer_timeout_ms) {
            return Err(invalid(
                file,
                "broker.slow_consumer_timeout_ms",
                "must be between 100 and 600000: every write to a client needs a deadline",
            ));
        }
        if b.slow_consumer_max_bytes < MIN_QUEUED_BYTES + b.max_packet_bytes {
            return Err(invalid(
                file,
                "broker.slow_consumer_max_bytes",
                "must be at least 1 MiB (1048576) more than broker.max_packet_bytes: the broker \
                 writes to a client in batches of up to 1 MiB, and a healthy client may have one \
                 batch and a message waiting",
            ));
        }
        if b.dead_link_timeout_s > 3_600 {
            return Err(invalid(
                file,
                "broker.dead_link_timeout_s",
                "must be at most 3600 (0: the kernel's defaults)",
            ));
        }
        // A day at most: figures older than that are no status.
        if b.sys_interval_s > 86_400 {
            return Err(invalid(
                file,
                "broker.sys_interval_s",
                "must be at most 86400 (0: no $SYS topics)",
            ));
        }
        if b.worker_threads > MAX_WORKER_THREADS {
            return Err(invalid(
                file,
                "broker.worker_threads",
                format!("must be at most {MAX_WORKER_THREADS} (0: one fewer than the cores)"),
            ));
        }
        if self.auth.verify_concurrency == 0 {
            return Err(invalid(
                file,
                "auth.verify_concurrency",
                "must be at least 1",
            ));
        }
        if self.auth.reload_poll_ms < 100 {
            return Err(invalid(file, "auth.reload_poll_ms", "must be at least 100"));
        }
        if self.auth.client_id != crate::identity::ClientIdRule::Any
            && self.auth.password_file.is_none()
        {
            return Err(invalid(
                file,
                "auth.client_id",
                "binds client ids to verified usernames, so it needs [auth] password_file; \
                 without one nobody's username is checked",
            ));
        }
        let t = &self.auth.throttle;
        if t.base_delay_ms == 0 || t.max_delay_ms < t.base_delay_ms {
            return Err(invalid(
                file,
                "auth.throttle",
                "base_delay_ms must be at least 1 and max_delay_ms at least base_delay_ms",
            ));
        }
        if let Some(bridge) = &self.bridge {
            if !cfg!(feature = "bridge") {
                return Err(invalid(
                    file,
                    "bridge",
                    "this fbbus was built without the `bridge` cargo feature (the zenoh bus); \
                     remove the [bridge] section or use a build with it",
                ));
            }
            bridge
                .validate(&b.line)
                .map_err(|(key, message)| invalid(file, &key, message))?;
        }
        let sp = &self.sparkplug;
        if sp.enabled {
            use crate::sparkplug::valid_id;
            if !valid_id(&sp.group) {
                return Err(invalid(
                    file,
                    "sparkplug.group",
                    "must be a non-empty Sparkplug id without `/`, `+` or `#`",
                ));
            }
            if !sp.primary_host.is_empty() && !valid_id(&sp.primary_host) {
                return Err(invalid(
                    file,
                    "sparkplug.primary_host",
                    "must be empty or a Sparkplug host id without `/`, `+` or `#`",
                ));
            }
            if sp.commands && self.auth.acl_file.is_none() {
                return Err(invalid(
                    file,
                    "sparkplug.commands",
                    "a command writes a device's input, and only the ACL says which host may: \
                     set [auth] acl_file (rules granting each host `publish` on the \
                     fb/<device>/<fb>/<port> inputs it may write), or set commands = false",
                ));
            }
        }
        if self.listeners.is_empty() {
            return Err(invalid(
                file,
                "listener",
                "at least one [[listener]] is needed, e.g. bind = \"127.0.0.1:1883\"",
            ));
        }
        for (i, l) in self.listeners.iter().enumerate() {
            let key = |k: &str| format!("listener[{i}].{k}");
            if l.name.trim().is_empty() {
                return Err(invalid(file, &key("name"), "must not be empty"));
            }
            if self.listeners[..i].iter().any(|o| o.name == l.name) {
                return Err(invalid(file, &key("name"), "is used by another listener"));
            }
            l.validate_kind()
                .map_err(|(k, message)| invalid(file, &key(k), message))?;
            let loopback = l.bind.ip().is_loopback();
            let anonymous = l.anonymous(&self.auth);
            if !loopback && self.auth.password_file.is_none() {
                return Err(invalid(
                    file,
                    &key("bind"),
                    format!(
                        "{} is not a loopback address, so this listener must require authentication: \
                         set [auth] password_file (create one with `fbbus passwd FILE add USER`), \
                         or bind to 127.0.0.1",
                        l.bind
                    ),
                ));
            }
            if !loopback && anonymous {
                return Err(invalid(
                    file,
                    &key("allow_anonymous"),
                    "anonymous access is only allowed on loopback listeners",
                ));
            }
            if !anonymous && self.auth.password_file.is_none() {
                return Err(invalid(
                    file,
                    &key("allow_anonymous"),
                    "is false but there is no [auth] password_file: nobody could connect",
                ));
            }
        }
        Ok(())
    }

    /// Checks that the files the config names exist, so a typo fails at start, not at first use.
    pub(super) fn validate_files(&self, file: &str) -> Result<(), ConfigError> {
        let check = |key: String, p: &Path| -> Result<(), ConfigError> {
            if p.is_file() {
                Ok(())
            } else {
                Err(invalid(
                    file,
                    &key,
                    format!("{} does not exist or is not a file", p.display()),
                ))
            }
        };
        if let Some(p) = &self.auth.password_file {
            check("auth.password_file".into(), p)?;
        }
        if let Some(p) = &self.auth.acl_file {
            check("auth.acl_file".into(), p)?;
        }
        if let Some(p) = &self.admin.password_file {
            check("admin.password_file".into(), p)?;
            let same = |a: &Path, b: &Path| match (a.canonicalize(), b.canonicalize()) {
                (Ok(a), Ok(b)) => a == b,
                _ => a == b,
            };
            if self
                .auth
                .password_file
                .as_deref()
                .is_some_and(|m| same(m, p))
            {
                return Err(invalid(
                    file,
                    "admin.password_file",
                    "is also [auth] password_file: every device's MQTT password would open the \
                     admin plane; give the admin endpoint a file of its own \
                     (`fbbus passwd FILE add USER`)",
                ));
            }
        }
        if let Some(tls) = self.bridge.as_ref().and_then(|b| b.tls.as_ref()) {
            check("bridge.tls.root_ca".into(), &tls.root_ca)?;
            check("bridge.tls.cert".into(), &tls.cert)?;
            check("bridge.tls.key".into(), &tls.key)?;
        }
        for (i, l) in self.listeners.iter().enumerate() {
            if let Some(tls) = &l.tls {
                check(format!("listener[{i}].tls.cert"), &tls.cert)?;
                check(format!("listener[{i}].tls.key"), &tls.key)?;
                if let Some(ca) = &tls.client_ca {
                    check(format!("listener[{i}].tls.client_ca"), ca)?;
                }
            }
        }
        Ok(())
    }
}

pub(super) fn invalid(file: &str, key: &str, message: impl Into<String>) -> ConfigError {
    ConfigError::Invalid {
        file: file.to_owned(),
        key: key.to_owned(),
        message: message.into(),
    }
}

//! The line console (issue 18): a read-only web page served by the admin endpoint, so a
//! person at a line sees what the broker knows without a tool of their own.
//!
//! - `/` and `/console/*`: the page ([`assets`]), embedded in the binary;
//! - `GET /api/v1/line`: the line's name, version, uptime, the last five minutes of its
//!   rates ([`stats`]), the bridge's other lines;
//! - `GET /api/v1/events`: the live feed ([`feed`]), server-sent events;
//! - `GET /api/v1/devices/{id}/ports/{FB.PORT}/history`: a port's recent values, JSON or
//!   CSV ([`trends`], kept by [`history`]);
//! - `GET /api/v1/devices/{id}/activity`: a device's last port values, recent refusals,
//!   offline times ([`activity`]), and its observed output periods (for the page's
//!   "silent port" marker) and broker-side will.
//!
//! The device list itself is the existing paged `/api/v1/devices`. Everything here is
//! read-only and bounded (each file states its bounds), and the packet path never waits
//! for it: values come from the console's own router link, record changes from the
//! registry's bounded broadcast channel, rates from the metrics' atomics.

pub mod activity;
pub mod assets;
mod feed;
pub mod history;
pub mod stats;
mod trends;

use std::sync::Arc;
use std::time::{Duration, Instant};

use axum::extract::{Path, State};
use axum::http::StatusCode;
use axum::response::{IntoResponse, Response};
use axum::routing::get;
use axum::Router;
use prometheus::IntGauge;
use serde::Deserialize;

use crate::metrics::Metrics;
use crate::profiles::Profiles;
use crate::registry::Registry;
use crate::supervisor::Tasks;

/// The line console (`console`): the page on the admin endpoint, and what it keeps.
#[derive(Debug, Clone, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct ConsoleSection {
    /// Serve the console (`/`, `/console/*`, the feed) and keep the last port values and
    /// refusals it shows. false: none of it, and no `fbbus:console` router link.
    pub enabled: bool,
    /// Last values of declared output ports kept at most, over every device; beyond,
    /// a new port's value is not kept (counted in `fbbus_console_dropped_total`).
    pub max_port_values: usize,
    /// Refusals (from `fbbus/diag/<device>`) kept at most, over every device (and at
    /// most `console::activity::REFUSALS_PER_DEVICE` per device).
    pub max_refusals: usize,
    /// The trends (`console::history`): points older than this are dropped.
    pub history_window_s: u64,
    /// Points kept per port at most (3600: an hour at one value per second).
    pub history_points_per_port: usize,
    /// Points kept over every port at most, 16 bytes each; beyond, each port's share
    /// shrinks to `history_max_points / ports`.
    pub history_max_points: usize,
}

impl Default for ConsoleSection {
    fn default() -> Self {
        ConsoleSection {
            enabled: true,
            max_port_values: 100_000,
            max_refusals: 20_000,
            history_window_s: 3600,
            history_points_per_port: 3600,
            history_max_points: 2_000_000,
        }
    }
}

/// What the console's routes share.
pub struct Console {
    registry: Arc<Registry>,
    profiles: Arc<Profiles>,
    /// The wills connections hold now (a device's, by its client id).
    wills: Arc<crate::wills::Wills>,
    activity: Arc<activity::Activity>,
    stats: Arc<stats::Stats>,
    started: Instant,
    /// Whether the line has a `[bridge]`.
    bridge: bool,
    feed_lifetime: Duration,
    /// Live feeds open now (`fbbus_console_feeds`).
    feeds: IntGauge,
}

impl Console {
    /// Starts the console's tasks (its router link's reader, the rates' sampler).
    #[allow(clippy::too_many_arguments)]
    pub fn start(
        config: &ConsoleSection,
        connection_timeout: Duration,
        bridge: bool,
        registry: Arc<Registry>,
        profiles: Arc<Profiles>,
        wills: Arc<crate::wills::Wills>,
        metrics: Arc<Metrics>,
        link: (rumqttd::local::LinkTx, rumqttd::local::LinkRx),
        tasks: &Tasks,
    ) -> Arc<Console> {
        let activity = activity::Activity::new(
            activity::Limits {
                max_port_values: config.max_port_values,
                max_refusals: config.max_refusals,
                history: history::Limits {
                    window_ms: config.history_window_s.saturating_mul(1000),
                    points_per_port: config.history_points_per_port,
                    max_points: config.history_max_points,
                },
            },
            &metrics,
        );
        let stats = stats::Stats::new();
        let feeds = IntGauge::new(
            "fbbus_console_feeds",
            "Line console live feeds open (each holds one admin connection)",
        )
        .expect("valid metric");
        metrics.register(Box::new(feeds.clone()));
        // A thread of its own: the activity decodes every accepted typed message for the
        // trends (an event's WITH data, numbers), work that on the workers' runtime would
        // take turns with the sessions.
        crate::supervisor::spawn_apart(
            "fbbus-console",
            activity::run(Arc::clone(&activity), Arc::clone(&registry), link),
        );
        tasks.spawn(Arc::clone(&stats).run(Arc::clone(&metrics), Arc::clone(&registry)));
        Arc::new(Console {
            registry,
            profiles,
            wills,
            activity,
            stats,
            started: Instant::now(),
            bridge,
            feed_lifetime: feed::lifetime(connection_timeout),
            feeds,
        })
    }
}

/// The console's routes, for the admin router; none when the console is off.
pub fn routes<S: Clone + Send + Sync + 'static>(console: Option<Arc<Console>>) -> Router<S> {
    let Some(console) = console else {
        return Router::new();
    };
    Router::new()
        .route("/", get(assets::index))
        .route("/console/:name", get(assets::asset))
        .route("/api/v1/line", get(line))
        .route("/api/v1/events", get(feed::events))
        .route("/api/v1/devices/:id/activity", get(device_activity))
        .route(
            "/api/v1/devices/:id/ports/:port/history",
            get(trends::history),
        )
        .with_state(console)
}

async fn line(State(console): State<Arc<Console>>) -> Response {
    let body = serde_json::json!({
        "line": console.registry.line(),
        "version": env!("CARGO_PKG_VERSION"),
        "uptime_s": console.started.elapsed().as_secs(),
        "bridge": console.bridge,
        "lines": console.registry.lines(),
        "history": console.stats.history(),
        "interval_s": stats::INTERVAL.as_secs(),
    });
    let mut response = axum::Json(body).into_response();
    assets::secure(&mut response);
    response
}

/// A device's activity: last port values, refusals, offline times, observed periods,
/// the silence bound, its profile's will and the will its connection holds. 404 for a device the registry does not hold.
async fn device_activity(State(console): State<Arc<Console>>, Path(id): Path<String>) -> Response {
    let Some(record) = console.registry.get(&id) else {
        return (
            StatusCode::NOT_FOUND,
            axum::Json(serde_json::json!({"error": format!("no device {id} in the registry")})),
        )
            .into_response();
    };
    let activity = console.activity.device(&id);
    let periods = console
        .registry
        .activity(&id)
        .map(|a| a.periods())
        .unwrap_or_default();
    let bound = console.registry.silence_bound();
    let will: Option<std::collections::BTreeMap<String, String>> =
        console.profiles.get().get(&id).map(|p| {
            p.will
                .iter()
                .map(|(fb, port, v)| (format!("{fb}.{port}"), v.clone()))
                .collect()
        });
    let body = serde_json::json!({
        "id": record.id,
        "line": record.line,
        "ports": activity.as_ref().map(|a| &a.ports),
        "refusals": activity.as_ref().map(|a| &a.refusals),
        "offline": activity.as_ref().map(|a| &a.offline),
        "periods": periods,
        "silence": {"factor": bound.factor, "min_s": bound.floor.as_secs_f64()},
        "profile_will": will,
        // The will its connection holds now (the device's client id is its id).
        "will": console.wills.armed(&id),
    });
    let mut response = axum::Json(body).into_response();
    assets::secure(&mut response);
    response
}

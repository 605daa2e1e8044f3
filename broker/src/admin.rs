//! The HTTP admin endpoint: `/metrics` (Prometheus text), `/healthz` (the process runs),
//! `/readyz` (the broker routes: see `health`), and the device
//! registry as JSON: `/api/v1/devices` (every device, by id; `?status=online` filters)
//! and `/api/v1/devices/{id}` (one record, 404 if unknown); the device profiles:
//! `/api/v1/profiles` (what each profile recognises and maps) and
//! `PUT /api/v1/profiles/{device}` (a profile in TOML, as `fbbus declare` sends it).
//!
//! Bound to loopback by default; it exposes no secret. Its one command, putting a
//! profile, is refused (403) to any peer that is not on the broker's own host: the
//! endpoint has no authentication, and an admin bound to a plant network for Prometheus
//! must not let that network retype the line's devices.

use std::sync::Arc;

use std::net::SocketAddr;

use axum::extract::{ConnectInfo, Path, Query, State};
use axum::http::{header, StatusCode};
use axum::response::IntoResponse;
use axum::routing::{get, put};
use axum::Router;
use tokio::net::TcpListener;

use crate::health::Health;
use crate::metrics::Metrics;
use crate::profiles::{Profiles, PutError};
use crate::registry::Registry;

#[derive(Clone)]
pub struct AdminState {
    pub metrics: Arc<Metrics>,
    pub health: Arc<Health>,
    pub registry: Arc<Registry>,
    pub profiles: Arc<Profiles>,
}

pub fn routes(state: AdminState) -> Router {
    Router::new()
        .route("/metrics", get(metrics))
        .route("/healthz", get(|| async { "ok\n" }))
        .route("/readyz", get(readyz))
        .route("/api/v1/devices", get(devices))
        .route("/api/v1/devices/:id", get(device))
        .route("/api/v1/profiles", get(profiles))
        .route("/api/v1/profiles/:device", put(put_profile))
        .with_state(state)
}

async fn metrics(State(state): State<AdminState>) -> impl IntoResponse {
    (
        [(header::CONTENT_TYPE, "text/plain; version=0.0.4")],
        state.metrics.render(),
    )
}

/// 200 only while the broker routes: listeners bound, nothing fatal, and a probe
/// publication made the round trip through the router (`health`).
async fn readyz(State(state): State<AdminState>) -> impl IntoResponse {
    match state.health.ready().await {
        Ok(()) => (StatusCode::OK, "ready\n".to_owned()),
        Err(why) => (
            StatusCode::SERVICE_UNAVAILABLE,
            format!("not ready: {why}\n"),
        ),
    }
}

#[derive(serde::Deserialize)]
struct DeviceFilter {
    status: Option<String>,
}

async fn devices(
    State(state): State<AdminState>,
    Query(filter): Query<DeviceFilter>,
) -> impl IntoResponse {
    let mut devices = state.registry.list();
    if let Some(status) = &filter.status {
        devices.retain(|d| d.status.label() == status);
    }
    axum::Json(serde_json::json!({
        "line": state.registry.line(),
        "devices": devices,
    }))
}

async fn device(State(state): State<AdminState>, Path(id): Path<String>) -> impl IntoResponse {
    match state.registry.get(&id) {
        Some(record) => axum::Json(record).into_response(),
        None => (
            StatusCode::NOT_FOUND,
            axum::Json(serde_json::json!({"error": format!("no device {id} in the registry")})),
        )
            .into_response(),
    }
}

/// What each profile recognises and maps, by device.
async fn profiles(State(state): State<AdminState>) -> impl IntoResponse {
    let set = state.profiles.get();
    let mut devices: Vec<_> = set.devices().collect();
    devices.sort_by(|a, b| a.device.cmp(&b.device));
    let profiles: serde_json::Map<String, serde_json::Value> = devices
        .into_iter()
        .map(|p| {
            let outputs: Vec<_> = p
                .outputs
                .iter()
                .map(|o| serde_json::json!({"topic": o.topic, "port": format!("{}.{}", o.fb, o.port), "encoding": o.encoding.namespace()}))
                .collect();
            let inputs: Vec<_> = p
                .inputs
                .iter()
                .map(|i| serde_json::json!({
                    "topic": i.own.topic,
                    "port": format!("{}.{}", i.own.fb, i.own.port),
                    "encoding": i.own.encoding.namespace(),
                    "from": format!("{}/{}/{}", i.from.device, i.from.fb, i.from.port),
                }))
                .collect();
            let body = serde_json::json!({
                "identity": format!("{:?}", p.identity),
                "outputs": outputs,
                "inputs": inputs,
                "will": p.will.iter().map(|(fb, port, v)| (format!("{fb}.{port}"), v.clone())).collect::<std::collections::BTreeMap<_, _>>(),
            });
            (p.device.clone(), body)
        })
        .collect();
    axum::Json(serde_json::json!({
        "dir": state.profiles.dir().map(|d| d.display().to_string()),
        "profiles": profiles,
    }))
}

/// Puts a profile (TOML body) into the profiles directory: from the broker's host only.
async fn put_profile(
    State(state): State<AdminState>,
    ConnectInfo(peer): ConnectInfo<SocketAddr>,
    Path(device): Path<String>,
    body: String,
) -> impl IntoResponse {
    let error = |code: StatusCode, e: String| {
        (code, axum::Json(serde_json::json!({"error": e}))).into_response()
    };
    if !peer.ip().is_loopback() {
        return error(
            StatusCode::FORBIDDEN,
            "profiles are put from the broker's own host (fbbus declare), or written into its profiles directory".into(),
        );
    }
    let (profiles, metrics) = (Arc::clone(&state.profiles), Arc::clone(&state.metrics));
    let put = tokio::task::spawn_blocking(move || profiles.put(&device, &body, &metrics)).await;
    match put {
        Ok(Ok(())) => axum::Json(serde_json::json!({"ok": true})).into_response(),
        Ok(Err(e @ PutError::NoDirectory)) => error(StatusCode::CONFLICT, e.to_string()),
        Ok(Err(e @ PutError::Invalid(_))) => error(StatusCode::BAD_REQUEST, e.to_string()),
        Ok(Err(e @ PutError::Io(_))) => error(StatusCode::INTERNAL_SERVER_ERROR, e.to_string()),
        Err(e) => error(StatusCode::INTERNAL_SERVER_ERROR, e.to_string()),
    }
}

/// Serves the admin routes until `shutdown` resolves.
pub async fn serve(
    socket: TcpListener,
    state: AdminState,
    shutdown: impl std::future::Future<Output = ()> + Send + 'static,
) {
    let app = routes(state).into_make_service_with_connect_info::<SocketAddr>();
    if let Err(e) = axum::serve(socket, app)
        .with_graceful_shutdown(shutdown)
        .await
    {
        tracing::error!(error = %e, "admin endpoint failed");
    }
}

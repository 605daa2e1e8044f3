//! The HTTP admin endpoint: `/metrics` (Prometheus text), `/healthz` (the process runs),
//! `/readyz` (the broker routes: see `health`), and the device
//! registry as JSON: `/api/v1/devices` (every device, by id; `?status=online` filters)
//! and `/api/v1/devices/{id}` (one record, 404 if unknown).
//! Bound to loopback by default; it exposes no secret and accepts no command.

use std::sync::Arc;

use axum::extract::{Path, Query, State};
use axum::http::{header, StatusCode};
use axum::response::IntoResponse;
use axum::routing::get;
use axum::Router;
use tokio::net::TcpListener;

use crate::health::Health;
use crate::metrics::Metrics;
use crate::registry::Registry;

#[derive(Clone)]
pub struct AdminState {
    pub metrics: Arc<Metrics>,
    pub health: Arc<Health>,
    pub registry: Arc<Registry>,
}

pub fn routes(state: AdminState) -> Router {
    Router::new()
        .route("/metrics", get(metrics))
        .route("/healthz", get(|| async { "ok\n" }))
        .route("/readyz", get(readyz))
        .route("/api/v1/devices", get(devices))
        .route("/api/v1/devices/:id", get(device))
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

/// Serves the admin routes until `shutdown` resolves.
pub async fn serve(
    socket: TcpListener,
    state: AdminState,
    shutdown: impl std::future::Future<Output = ()> + Send + 'static,
) {
    if let Err(e) = axum::serve(socket, routes(state))
        .with_graceful_shutdown(shutdown)
        .await
    {
        tracing::error!(error = %e, "admin endpoint failed");
    }
}

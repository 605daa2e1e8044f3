//! The HTTP admin endpoint: `/metrics` (Prometheus text), `/healthz` (the process runs),
//! `/readyz` (the broker routes: see `health`), and the device
//! registry as JSON: `/api/v1/devices` (one page of devices in id order: `?limit=`,
//! `?after=`, `next`; `?status=online` filters)
//! and `/api/v1/devices/{id}` (one record, 404 if unknown); the device profiles:
//! `/api/v1/profiles` (what each profile recognises and maps) and
//! `PUT /api/v1/profiles/{device}` (a profile in TOML, as `fbbus declare` sends it);
//! `DELETE /api/v1/devices/{id}` forgets an offline device (`fbbus devices forget`); the
//! sessions (`/api/v1/sessions`), the connected clients (`/api/v1/clients`, `clients`)
//! and the retained topics clients hold (`/api/v1/retained?filter=`, `retained_share`),
//! each paged.
//!
//! Who may ask, in two rules, each in one place:
//! - Credentials: with `[admin] password_file` set, every request, whatever its route
//!   (and a path no route serves), needs HTTP Basic credentials of a user of that file,
//!   or it is answered 401 (429 while its address is throttled) before any route sees
//!   it: one layer around the whole router, `admin_auth`, so a route added later is
//!   covered too. The file is required when `[admin] bind` is not a loopback address
//!   (the broker refuses to start without it, as it refuses a non-loopback MQTT listener
//!   without `[auth] password_file`); on loopback without it the endpoint is open, as
//!   anyone on the broker's host can read its files anyway.
//! - Writes from the host only, addressed as the host: the commands (putting a profile,
//!   forgetting a device) take one extractor, `admin_writes::LocalWrite`, credentials or
//!   not: refused (403) to any peer not on the broker's own host (an admin bound to a
//!   plant network for Prometheus must not let that network retype or remove the line's
//!   devices), and to requests whose `Host` or `Origin` names another site (a web page
//!   that rebinds its own name to 127.0.0.1).
//!
//! It exposes no secret: no password, hash or key is in any answer.

use std::net::SocketAddr;
use std::path::PathBuf;
use std::sync::Arc;
use std::time::{Duration, Instant};

use axum::extract::{ConnectInfo, DefaultBodyLimit, Path, Query, State};
use axum::http::{header, StatusCode};
use axum::response::{IntoResponse, Response};
use axum::routing::{get, put};
use axum::{Extension, Router};
use hyper::server::conn::http1;
use hyper_util::rt::{TokioIo, TokioTimer};
use hyper_util::service::TowerToHyperService;
use serde::Deserialize;
use tokio::net::TcpListener;
use tokio::sync::Semaphore;

use crate::admin_auth::{self, AdminAuth};
use crate::admin_writes::{HasWriteRules, LocalWrite, WriteRules};
use crate::health::Health;
use crate::metrics::Metrics;
use crate::profiles::{Profiles, PutError};
use crate::registry::{ForgetError, ForgetReason, Registry};
use crate::session::control::{DropError, SessionControl};

#[derive(Debug, Clone, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct AdminSection {
    /// HTTP admin endpoint: /metrics, /healthz, /readyz, the registry API.
    pub bind: SocketAddr,
    /// `user:PHC` lines (argon2id, `fbbus passwd`) the admin endpoint checks HTTP Basic
    /// credentials against, on every route. Required on a non-loopback `bind`; a file of
    /// its own, so that a device's MQTT password never opens the admin plane.
    pub password_file: Option<PathBuf>,
    /// Admin connections open at once at most; beyond, a new one is closed at once.
    pub max_connections: usize,
    /// A request's header must arrive within this; an admin connection lives at most
    /// `connection_timeout_ms` (slow bodies, slow readers, idle keep-alive).
    pub header_timeout_ms: u64,
    pub connection_timeout_ms: u64,
    /// Host names under which admin writes are accepted, besides IP addresses and
    /// `localhost` (the `Host` and `Origin` headers; DNS-rebinding defence, see
    /// `admin_writes`).
    pub allowed_hosts: Vec<String>,
}

impl Default for AdminSection {
    fn default() -> Self {
        AdminSection {
            bind: SocketAddr::from(([127, 0, 0, 1], 9883)),
            password_file: None,
            max_connections: 64,
            header_timeout_ms: 5_000,
            connection_timeout_ms: 60_000,
            allowed_hosts: Vec::new(),
        }
    }
}

#[derive(Clone)]
pub struct AdminState {
    pub metrics: Arc<Metrics>,
    pub health: Arc<Health>,
    pub registry: Arc<Registry>,
    pub profiles: Arc<Profiles>,
    /// `[admin] password_file`: every request must carry credentials of its users.
    pub auth: Option<Arc<AdminAuth>>,
    /// The line console's routes (`console`), unless `[console] enabled = false`.
    pub console: Option<Arc<crate::console::Console>>,
    /// Who may write (`admin_writes`).
    pub writes: Arc<WriteRules>,
    /// The sessions, to list and to drop a kept one (`session::control`).
    pub sessions: Arc<SessionControl>,
    /// The connected clients (`clients`).
    pub clients: Arc<crate::clients::Clients>,
    /// The retained topics clients hold (`retained_share`).
    pub retained: Arc<crate::retained_share::RetainedShares>,
}

impl HasWriteRules for AdminState {
    fn write_rules(&self) -> &WriteRules {
        &self.writes
    }
}

/// Every admin route. With `state.auth`, the credential check is the outermost layer, so
/// it answers for every route above and for the fallback (an unknown path is a 401, not a
/// 404, to a client without credentials): add a route above it, never after.
pub fn routes(state: AdminState) -> Router {
    let auth = state.auth.clone();
    let router = Router::new()
        .route("/metrics", get(metrics))
        .route("/healthz", get(|| async { "ok\n" }))
        .route("/readyz", get(readyz))
        .route("/api/v1/devices", get(devices))
        .route("/api/v1/devices/:id", get(device).delete(forget_device))
        .route("/api/v1/sessions", get(sessions))
        .route(
            "/api/v1/sessions/:client_id",
            axum::routing::delete(drop_session),
        )
        .route("/api/v1/clients", get(clients))
        .route("/api/v1/retained", get(retained))
        .route("/api/v1/profiles", get(profiles))
        .route("/api/v1/profiles/:device", put(put_profile))
        .merge(crate::console::routes(state.console.clone()))
        // A request body larger than this is refused (413) before it is read further.
        .layer(DefaultBodyLimit::max(MAX_BODY_BYTES))
        .with_state(state);
    match auth {
        Some(auth) => router.layer(axum::middleware::from_fn_with_state(
            auth,
            admin_auth::require,
        )),
        None => router,
    }
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

/// Devices per page of `GET /api/v1/devices` unless `?limit=` says otherwise.
pub const DEVICES_PAGE: usize = 1000;
/// The largest page `?limit=` may ask for; a larger limit is taken as this.
pub const DEVICES_PAGE_MAX: usize = 10_000;

#[derive(serde::Deserialize)]
struct DeviceFilter {
    status: Option<String>,
    limit: Option<usize>,
    after: Option<String>,
}

/// One page of the registry, in id order (issue 21): `?limit=N` (default 1,000, at most
/// 10,000), `?after=<id>` (the page starts after this id), `?status=` filters. The answer
/// names the next page's `after` in `next` (null on the last page). The page's records
/// are copied under the registry's lock (a range walk: only the page's records), and
/// serialized after it is released, right here on the admin thread: the admin plane is
/// one thread at a lower priority ([`serve_apart`]), so concurrent listings take turns
/// instead of taking more cores from the sessions.
async fn devices(
    State(state): State<AdminState>,
    Query(filter): Query<DeviceFilter>,
) -> axum::response::Response {
    let limit = filter.limit.unwrap_or(DEVICES_PAGE);
    if limit == 0 {
        return error(StatusCode::BAD_REQUEST, "limit must be at least 1".into());
    }
    let limit = limit.min(DEVICES_PAGE_MAX);
    let registry = &state.registry;
    let status = filter.status.as_deref();
    let (devices, more) = registry.page(filter.after.as_deref(), limit, |d| {
        status.is_none_or(|s| d.status.label() == s)
    });
    let next = more
        .then(|| devices.last().map(|d| d.id.as_str()))
        .flatten();
    // Serialized straight from the records (`json!` would build a tree of every field
    // first).
    #[derive(serde::Serialize)]
    struct Page<'a> {
        line: &'a str,
        devices: &'a [crate::registry::Record],
        next: Option<&'a str>,
    }
    let body = serde_json::to_vec(&Page {
        line: registry.line(),
        devices: &devices,
        next,
    });
    match body {
        Ok(body) => ([(header::CONTENT_TYPE, "application/json")], body).into_response(),
        Err(e) => error(StatusCode::INTERNAL_SERVER_ERROR, e.to_string()),
    }
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

/// Forgets an offline device with its retained record and values: 404 if unknown, 409
/// if it is online (or another line's). From the broker's host only.
async fn forget_device(
    _: LocalWrite,
    State(state): State<AdminState>,
    Path(id): Path<String>,
) -> Response {
    match state.registry.forget(&id, ForgetReason::Admin) {
        Ok(record) => {
            axum::Json(serde_json::json!({"ok": true, "forgotten": record.id})).into_response()
        }
        Err(e @ ForgetError::Unknown(_)) => error(StatusCode::NOT_FOUND, e.to_string()),
        Err(e @ (ForgetError::Online(_) | ForgetError::OtherLine(..))) => {
            error(StatusCode::CONFLICT, e.to_string())
        }
    }
}

#[derive(serde::Deserialize)]
struct SessionPage {
    limit: Option<usize>,
    after: Option<String>,
}

/// The sessions, connected and kept, in client id order (issue 33): `?limit=N` (default
/// 1,000, at most 10,000), `?after=<client id>`; `next` names the next page's `after`.
/// Each with its owner (the username that created it, or `(anonymous)`), so an operator
/// sees who holds a device's client id.
async fn sessions(State(state): State<AdminState>, Query(page): Query<SessionPage>) -> Response {
    let limit = page.limit.unwrap_or(DEVICES_PAGE);
    if limit == 0 {
        return error(StatusCode::BAD_REQUEST, "limit must be at least 1".into());
    }
    let (listed, total) = state
        .sessions
        .list(page.after.as_deref().unwrap_or(""), limit);
    let next = (listed.len() == limit.min(crate::session::control::MAX_PAGE))
        .then(|| listed.last().map(|l| l.client_id.clone()))
        .flatten();
    let sessions: Vec<serde_json::Value> = listed
        .into_iter()
        .map(|l| {
            serde_json::json!({
                "client_id": l.client_id,
                "owner": l.owner.to_string(),
                "status": if l.connected { "connected" } else { "kept" },
                "session": l.session,
                "expires_in_s": l.expires_in.map(|d| d.as_secs()),
            })
        })
        .collect();
    axum::Json(serde_json::json!({"sessions": sessions, "total": total, "next": next}))
        .into_response()
}

/// The connected clients in client id order (issue 37): `?limit=N` (default 100, at most
/// 1,000), `?after=<client id>`; `next` names the next page's `after`.
async fn clients(State(state): State<AdminState>, Query(page): Query<SessionPage>) -> Response {
    let limit = page.limit.unwrap_or(CLIENTS_PAGE);
    if limit == 0 {
        return error(StatusCode::BAD_REQUEST, "limit must be at least 1".into());
    }
    let (listed, total) = state
        .clients
        .list(page.after.as_deref().unwrap_or(""), limit);
    let next = (listed.len() == limit.min(crate::clients::MAX_PAGE))
        .then(|| listed.last().map(|c| c.client_id.clone()))
        .flatten();
    axum::Json(serde_json::json!({"clients": listed, "total": total, "next": next})).into_response()
}

/// Clients per page of `GET /api/v1/clients` unless `?limit=` says otherwise.
const CLIENTS_PAGE: usize = 100;

#[derive(Debug, Deserialize)]
struct RetainedPage {
    filter: Option<String>,
    after: Option<String>,
    limit: Option<usize>,
}

/// The retained topics clients hold under `?filter=` (an MQTT filter, default `#`), in
/// topic order, with their size, owner and age (issue 37): `?limit=N` (default 100, at
/// most 1,000), `?after=<topic>`; `next` names the next page's `after`. The broker's own
/// retained topics (`fbbus/...`: the registry's records) are not listed: the devices are.
async fn retained(State(state): State<AdminState>, Query(page): Query<RetainedPage>) -> Response {
    let filter = page.filter.as_deref().unwrap_or("#");
    if !fb_bridge::topic::filter::valid_filter(filter) {
        return error(
            StatusCode::BAD_REQUEST,
            format!("filter {filter:?} is not an MQTT topic filter (e.g. fb/conv1/#)"),
        );
    }
    let limit = page
        .limit
        .unwrap_or(CLIENTS_PAGE)
        .min(crate::clients::MAX_PAGE);
    if limit == 0 {
        return error(StatusCode::BAD_REQUEST, "limit must be at least 1".into());
    }
    let (listed, next) = state
        .retained
        .list(filter, page.after.as_deref().unwrap_or(""), limit);
    axum::Json(serde_json::json!({
        "retained": listed,
        "total": state.retained.len(),
        "next": next,
    }))
    .into_response()
}

/// `DELETE /api/v1/sessions/<client id>`: ends a kept offline session as its expiry
/// would, so another identity may use the client id (a local write: `admin_writes`).
async fn drop_session(
    _: LocalWrite,
    State(state): State<AdminState>,
    Path(client_id): Path<String>,
) -> Response {
    match state.sessions.drop_kept(&client_id).await {
        Ok(()) => axum::Json(serde_json::json!({"ok": true, "dropped": client_id})).into_response(),
        Err(e @ DropError::Unknown(_)) => error(StatusCode::NOT_FOUND, e.to_string()),
        Err(e @ DropError::Connected(_)) => error(StatusCode::CONFLICT, e.to_string()),
        Err(e @ DropError::Stopping) => error(StatusCode::SERVICE_UNAVAILABLE, e.to_string()),
    }
}

/// An error answer: `{"error": ...}` with `code`.
fn error(code: StatusCode, message: String) -> Response {
    (code, axum::Json(serde_json::json!({"error": message}))).into_response()
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

/// Puts a profile (TOML body) into the profiles directory: from the broker's host only
/// (or written into its profiles directory).
async fn put_profile(
    _: LocalWrite,
    State(state): State<AdminState>,
    Path(device): Path<String>,
    body: String,
) -> impl IntoResponse {
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

/// What one admin client may hold (`[admin]`): the admin plane must never take the file
/// descriptors or the time the MQTT listeners need.
#[derive(Debug, Clone, Copy)]
pub struct Limits {
    pub max_connections: usize,
    pub header_timeout: Duration,
    pub connection_timeout: Duration,
}

impl From<&AdminSection> for Limits {
    fn from(a: &AdminSection) -> Limits {
        Limits {
            max_connections: a.max_connections,
            header_timeout: Duration::from_millis(a.header_timeout_ms),
            connection_timeout: Duration::from_millis(a.connection_timeout_ms),
        }
    }
}

/// A request body larger than this is refused with 413: the largest profile the profiles
/// directory takes (`profiles::MAX_FILE_BYTES`, 1 MiB), so every profile that could be
/// put is. (axum's default was 2 MB, and one more extractor could have raised it.)
pub const MAX_BODY_BYTES: usize = crate::profiles::MAX_FILE_BYTES as usize;

/// A request header larger than this closes the connection (hyper's read buffer).
const MAX_HEADER_BYTES: usize = 64 * 1024;

/// Serves the admin routes until `shutdown` resolves.
///
/// Its own accept loop rather than `axum::serve`, for the limits (issue 21): at most
/// `max_connections` connections (one more is accepted and closed at once, counted in
/// `fbbus_admin_connections_refused_total`, logged at most once a minute), a request
/// header within `header_timeout` (a client that sends half a header and waits is
/// closed), a header of at most 64 KiB, and every connection closed after
/// `connection_timeout` whatever it does. 21,000 half-sent headers held the process's
/// file descriptors before, and MQTT clients could no longer connect.
pub async fn serve(
    socket: TcpListener,
    limits: Limits,
    state: AdminState,
    shutdown: impl std::future::Future<Output = ()> + Send + 'static,
) {
    let metrics = Arc::clone(&state.metrics);
    let app = routes(state);
    let slots = Arc::new(Semaphore::new(limits.max_connections));
    // One address holds at most a quarter of the slots, so a stranger holding connections
    // with unfinished headers cannot fail an orchestrator's liveness probe from another
    // address (issue 33: /healthz answered 0 of 18 probes with 64 such connections).
    let per_address = crate::pending::Pending::new((limits.max_connections / 4).max(1));
    let mut last_warning: Option<Instant> = None;
    tokio::pin!(shutdown);
    loop {
        let accepted = tokio::select! {
            _ = &mut shutdown => return,
            accepted = socket.accept() => accepted,
        };
        let (stream, peer) = match accepted {
            Ok(accepted) => accepted,
            Err(e) => {
                // Out of file descriptors, most likely: wait a little instead of spinning.
                tracing::warn!(error = %e, "admin endpoint: accept failed");
                tokio::time::sleep(Duration::from_millis(100)).await;
                continue;
            }
        };
        let held = per_address.enter(peer.ip());
        let slot = held.and_then(|held| {
            let slot = Arc::clone(&slots).try_acquire_owned().ok()?;
            Some((slot, held))
        });
        let Some(slot) = slot else {
            metrics.admin_refused.inc();
            if last_warning.is_none_or(|t| t.elapsed() >= Duration::from_secs(60)) {
                last_warning = Some(Instant::now());
                tracing::warn!(
                    %peer,
                    max_connections = limits.max_connections,
                    "admin endpoint: connection limit reached (max_connections, or a quarter \
                     of them from one address); new connections are closed \
                     (fbbus_admin_connections_refused_total)"
                );
            }
            drop(stream);
            continue;
        };
        let service = TowerToHyperService::new(app.clone().layer(Extension(ConnectInfo(peer))));
        let metrics = Arc::clone(&metrics);
        tokio::spawn(async move {
            let _slot = slot;
            metrics.admin_connections.inc();
            let mut http = http1::Builder::new();
            http.timer(TokioTimer::new())
                .header_read_timeout(limits.header_timeout)
                .max_buf_size(MAX_HEADER_BYTES);
            let connection = http.serve_connection(TokioIo::new(stream), service);
            let _ = tokio::time::timeout(limits.connection_timeout, connection).await;
            metrics.admin_connections.dec();
        });
    }
}

/// How much lower the admin thread's scheduling priority is than the packet path's
/// (`nice` +10: the kernel gives it about a tenth of the CPU time of a normal thread
/// when both want to run). Its answers wait when the line is busy; the line does not
/// wait for its answers.
const ADMIN_NICE: libc::c_int = 10;

/// Runs [`serve`] on a thread and a runtime of its own, at a lower scheduling priority
/// ([`ADMIN_NICE`]), until `shutdown` resolves or this future is dropped (then the thread
/// is stopped and joined before the drop returns).
///
/// Why a thread (issue 21): on the broker's runtime, six loops polling the device
/// listing took CPU time from the sessions on the same workers, and a well-behaved
/// device's p99 round trip grew 5x. The admin plane holds no lock the packet path needs
/// while it serializes; a thread of its own at a lower priority also keeps it from
/// taking the packet path's CPU.
pub async fn serve_apart(
    socket: TcpListener,
    limits: Limits,
    state: AdminState,
    shutdown: impl std::future::Future<Output = ()> + Send + 'static,
) {
    let socket = match socket.into_std() {
        Ok(socket) => socket,
        Err(e) => {
            tracing::error!(error = %e, "admin endpoint: cannot hand its socket to its thread");
            return;
        }
    };
    let (stop, stopped) = tokio::sync::oneshot::channel::<()>();
    let (done, finished) = tokio::sync::oneshot::channel();
    let nice = admin_nice();
    let thread = std::thread::Builder::new()
        .name("fbbus-admin".into())
        .spawn(move || {
            let run = std::panic::AssertUnwindSafe(move || {
                set_nice(nice);
                let runtime = tokio::runtime::Builder::new_current_thread()
                    .enable_all()
                    .thread_name("fbbus-admin")
                    .on_thread_start(move || set_nice(nice))
                    .build()?;
                runtime.block_on(async move {
                    let socket = TcpListener::from_std(socket)?;
                    let shutdown = async move {
                        tokio::select! {
                            () = shutdown => {}
                            _ = stopped => {}
                        }
                    };
                    serve(socket, limits, state, shutdown).await;
                    Ok::<_, std::io::Error>(())
                })?;
                // Connections still open are cut; a listing being serialized may finish.
                runtime.shutdown_timeout(Duration::from_secs(1));
                Ok::<_, std::io::Error>(())
            });
            let _ = done.send(std::panic::catch_unwind(run));
        });
    let thread = match thread {
        Ok(thread) => thread,
        Err(e) => {
            tracing::error!(error = %e, "admin endpoint: cannot start its thread");
            return;
        }
    };
    let _joined = Joined {
        stop: Some(stop),
        thread: Some(thread),
    };
    match finished.await {
        Ok(Ok(Ok(()))) => {}
        Ok(Ok(Err(e))) => tracing::error!(error = %e, "admin endpoint: its runtime failed"),
        Ok(Err(panic)) => std::panic::resume_unwind(panic),
        Err(_) => panic!("the admin endpoint's thread ended without an answer"),
    }
}

/// Stops the admin thread and waits for it when [`serve_apart`] ends or is dropped: after
/// the broker's tasks are finished, no admin request is served.
struct Joined {
    stop: Option<tokio::sync::oneshot::Sender<()>>,
    thread: Option<std::thread::JoinHandle<()>>,
}

impl Drop for Joined {
    fn drop(&mut self) {
        drop(self.stop.take());
        if let Some(thread) = self.thread.take() {
            let _ = thread.join();
        }
    }
}

/// The admin threads' nice value: the calling thread's (the broker's) plus
/// [`ADMIN_NICE`], at most 19. Set as an absolute value in every admin thread, because a
/// thread inherits its creator's: relative steps would add up in the blocking pool.
fn admin_nice() -> libc::c_int {
    #[cfg(target_os = "linux")]
    // SAFETY: gettid and getpriority take no pointers and only read.
    let base = unsafe {
        let tid = libc::syscall(libc::SYS_gettid) as libc::id_t;
        libc::getpriority(libc::PRIO_PROCESS, tid)
    };
    #[cfg(not(target_os = "linux"))]
    let base = 0;
    base.saturating_add(ADMIN_NICE).min(19)
}

/// Sets the calling thread's nice value. On Linux the nice value is per thread
/// (`setpriority(PRIO_PROCESS, tid)`), and raising it needs no privilege. Elsewhere, or
/// if it fails, the thread keeps the broker's priority.
fn set_nice(nice: libc::c_int) {
    #[cfg(target_os = "linux")]
    // SAFETY: gettid and setpriority take no pointers and only affect this thread.
    unsafe {
        let tid = libc::syscall(libc::SYS_gettid) as libc::id_t;
        if libc::setpriority(libc::PRIO_PROCESS, tid, nice) != 0 {
            tracing::debug!("admin endpoint: could not lower its thread's priority");
        }
    }
    #[cfg(not(target_os = "linux"))]
    let _ = nice;
}

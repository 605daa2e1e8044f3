//! The console's live feed: `GET /api/v1/events[?device=ID]`, server-sent events.
//!
//! A page loads the device list through the paged API once, then applies what the feed
//! sends — changes, never snapshots:
//!
//! | event | data | when |
//! |---|---|---|
//! | `hello` | line, version, uptime, the feed's number | first |
//! | `device` | one record, as `fbbus/devices/<id>` carries it | a record changed (any line) |
//! | `removed` | `{"id"}` | a device was forgotten |
//! | `stats` | one [`stats::Sample`](super::stats::Sample) and the bridge's lines | every second |
//! | `ports` | `{"device", "ports"}`: the changed ports' last values | `?device=` only, every [`FLUSH`](super::activity::FLUSH) at most |
//! | `refusal` | `{"device", "refusal"}` | a diagnostic on `fbbus/diag/<device>` |
//! | `resync` | `{}` | the feed fell behind a channel: reload what the page shows |
//!
//! Record changes come from the registry's bounded broadcast channel, each serialized
//! once for every feed; a feed that falls more than its capacity behind is sent
//! `resync` rather than slowing anything down. Each feed is one task writing into a
//! small queue the HTTP body reads; a closed page ends it within a second (the next
//! `stats` finds the queue gone).
//!
//! **Lifetime.** Every admin connection is closed after `[admin] connection_timeout_ms`,
//! whatever it does: that bound is what keeps a client from holding an admin slot, and
//! a feed keeps it. The feed ends itself cleanly a little before (nine tenths of it),
//! with `Connection: close`, so the browser's EventSource reconnects after the `retry`
//! delay it was given (500 ms) on a fresh connection, and the page reloads its list on
//! that reconnect: a change made during the gap is not lost. Each page costs one
//! list load per minute, and at most one admin slot.

use std::convert::Infallible;
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::Arc;
use std::time::Duration;

use axum::body::Body;
use axum::extract::{Query, State};
use axum::http::header;
use axum::response::{IntoResponse, Response};
use bytes::{BufMut, Bytes, BytesMut};
use tokio::sync::{broadcast, mpsc};

use super::activity::Event as ActivityEvent;
use super::Console;
use crate::registry::Change;

/// Events a feed's queue holds before its task waits for the page to read.
const QUEUE: usize = 64;
/// What the page's EventSource waits before it reconnects, in milliseconds.
const RETRY_MS: u64 = 500;

#[derive(serde::Deserialize)]
pub(super) struct FeedQuery {
    device: Option<String>,
}

/// How long a feed lasts: nine tenths of the admin connection's lifetime.
pub(super) fn lifetime(connection_timeout: Duration) -> Duration {
    (connection_timeout * 9 / 10).max(Duration::from_millis(500))
}

/// Counts the feeds opened, for `hello`.
static OPENED: AtomicU64 = AtomicU64::new(0);

pub(super) async fn events(
    State(console): State<Arc<Console>>,
    Query(query): Query<FeedQuery>,
) -> Response {
    let (queue, body) = mpsc::channel::<Bytes>(QUEUE);
    let feed = OPENED.fetch_add(1, Ordering::Relaxed) + 1;
    let changes = console.registry.changes();
    let activity = console.activity.events();
    let stats = console.stats.subscribe();
    let watch = query.device.as_deref().map(|d| console.activity.watch(d));
    let hello = serde_json::json!({
        "line": console.registry.line(),
        "version": env!("CARGO_PKG_VERSION"),
        "uptime_s": console.started.elapsed().as_secs(),
        "feed": feed,
        "device": query.device,
    });
    let mut first = BytesMut::new();
    first.put_slice(format!("retry: {RETRY_MS}\n\n").as_bytes());
    first.put_slice(&event("hello", hello.to_string().as_bytes()));
    let _ = queue.try_send(first.freeze());
    let gauge = console.feeds.clone();
    let lifetime = console.feed_lifetime;
    tokio::spawn(async move {
        gauge.inc();
        let _ =
            tokio::time::timeout(lifetime, feed_loop(queue, changes, activity, stats, watch)).await;
        gauge.dec();
    });
    let stream = tokio_stream::wrappers::ReceiverStream::new(body);
    let stream = tokio_stream::StreamExt::map(stream, Ok::<Bytes, Infallible>);
    (
        [
            (header::CONTENT_TYPE, "text/event-stream; charset=utf-8"),
            (header::CACHE_CONTROL, "no-cache, no-store"),
            (header::CONNECTION, "close"),
        ],
        Body::from_stream(stream),
    )
        .into_response()
}

async fn feed_loop(
    queue: mpsc::Sender<Bytes>,
    mut changes: broadcast::Receiver<Change>,
    mut activity: broadcast::Receiver<ActivityEvent>,
    mut stats: tokio::sync::watch::Receiver<Bytes>,
    watch: Option<super::activity::Watch>,
) {
    let device = watch.as_ref().map(|w| w.device().to_owned());
    loop {
        let out = tokio::select! {
            change = changes.recv() => match change {
                Ok(Change::Record(_, json)) => event("device", &json),
                Ok(Change::Removed(id)) => {
                    event("removed", serde_json::json!({"id": &*id}).to_string().as_bytes())
                }
                Err(broadcast::error::RecvError::Lagged(_)) => event("resync", b"{}"),
                Err(broadcast::error::RecvError::Closed) => return,
            },
            got = activity.recv() => match got {
                Ok(ActivityEvent::Refusal { json }) => event("refusal", &json),
                Ok(ActivityEvent::Ports { device: d, json }) => {
                    if device.as_deref() != Some(&*d) {
                        continue;
                    }
                    event("ports", &json)
                }
                Err(broadcast::error::RecvError::Lagged(_)) => event("resync", b"{}"),
                Err(broadcast::error::RecvError::Closed) => return,
            },
            changed = stats.changed() => {
                if changed.is_err() {
                    return;
                }
                let json = stats.borrow_and_update().clone();
                event("stats", &json)
            }
        };
        if queue.send(out).await.is_err() {
            // The page is gone.
            return;
        }
    }
}

/// One server-sent event. `data` is JSON, which holds no raw line break.
fn event(name: &str, data: &[u8]) -> Bytes {
    let mut out = BytesMut::with_capacity(name.len() + data.len() + 16);
    out.put_slice(b"event: ");
    out.put_slice(name.as_bytes());
    out.put_slice(b"\ndata: ");
    out.put_slice(data);
    out.put_slice(b"\n\n");
    out.freeze()
}

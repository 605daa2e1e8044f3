//! Retained state across lines: other lines' queries for this line's retained messages.

use std::collections::HashMap;
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::Arc;
use std::time::Duration;

use fb_bridge::bus::link::{Link, RetainedQueries};
use fb_bridge::bus::BusConfig;
use rumqttd::protocol::{Filter, Packet, QoS, RetainForwardRule, Subscribe};
use rumqttd::Notification;

use super::IMPORT_CLIENT_ID;
use crate::policy::origin;
use crate::session::Context;

static RETAINED_LINKS: AtomicU64 = AtomicU64::new(0);

/// Answers other lines' queries for this line's retained messages: a short-lived router
/// link subscribes to the filter and collects what the router replays as retained.
pub(super) async fn serve_retained(
    link: Arc<Link>,
    queries: RetainedQueries,
    ctx: Arc<Context>,
    export: Vec<String>,
) {
    while let Some(query) = queries.recv().await {
        let messages = retained(&ctx, query.filter(), &export).await;
        link.reply_retained(&query, messages).await;
    }
}

/// This line's own retained messages matching `filter` that `export` lets leave, as
/// (topic, payload): what another line's query is answered with.
pub(super) async fn retained(
    ctx: &Context,
    filter: &str,
    export: &[String],
) -> Vec<(String, Vec<u8>)> {
    replay(ctx, filter)
        .await
        .into_iter()
        .filter(|(from_bus, topic, _)| !from_bus && BusConfig::allows(export, topic))
        .map(|(_, topic, payload)| (topic, payload))
        .collect()
}

/// Every retained message the router holds on topics matching `filter`, this line's and
/// those imported from the bus: topic -> payload.
pub(super) async fn held(ctx: &Context, filter: &str) -> HashMap<String, Vec<u8>> {
    replay(ctx, filter)
        .await
        .into_iter()
        .map(|(_, topic, payload)| (topic, payload))
        .collect()
}

/// What the router replays as retained to a short-lived link subscribing to `filter`:
/// (from the bus, topic, payload).
async fn replay(ctx: &Context, filter: &str) -> Vec<(bool, String, Vec<u8>)> {
    let id = format!(
        "fbbus:bridge-retained-{}",
        RETAINED_LINKS.fetch_add(1, Ordering::Relaxed)
    );
    let Ok((mut tx, mut rx, _)) = ctx.router.link(&id, true, 0).await else {
        return Vec::new();
    };
    let subscribe = Packet::Subscribe(
        Subscribe {
            pkid: 1,
            filters: vec![Filter {
                path: filter.to_owned(),
                qos: QoS::AtMostOnce,
                nolocal: false,
                preserve_retain: false,
                retain_forward_rule: RetainForwardRule::OnEverySubscribe,
            }],
        },
        None,
    );
    let mut out = Vec::new();
    if tx.send(subscribe).await.is_ok() {
        // The router replays retained messages right after the SUBACK; stop once it has
        // been quiet for a moment.
        let mut quiet = Duration::from_millis(500);
        while let Ok(Ok(n)) = tokio::time::timeout(quiet, rx.next()).await {
            match n {
                Some(Notification::Forward(forward)) => {
                    quiet = Duration::from_millis(50);
                    let mut publish = forward.publish;
                    let origin = origin::take(&mut publish);
                    // Retained (not a live message that happened to arrive meanwhile).
                    if origin.as_ref().is_none_or(|o| o.retain) {
                        let from_bus = origin.is_some_and(|o| &*o.publisher == IMPORT_CLIENT_ID);
                        let topic = String::from_utf8_lossy(&publish.topic).into_owned();
                        out.push((from_bus, topic, publish.payload.to_vec()));
                    }
                }
                Some(Notification::Unschedule) => {
                    let _ = rx.wake().await;
                }
                Some(_) => quiet = Duration::from_millis(50),
                None => {}
            }
        }
    }
    let _ = crate::router::unlink(tx).await;
    out
}

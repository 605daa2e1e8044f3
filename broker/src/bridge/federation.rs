//! Registry federation: this line's devices announced on the bus, the other lines'
//! records and liveliness taken into the registry.

use std::collections::HashMap;
use std::sync::Arc;

use fb_bridge::bus::link::{DeviceToken, Event, Inbox, Link};
use tokio::sync::mpsc;

use crate::context::Context;
use crate::registry::{Record, Status};

/// Liveliness and records of the other lines: the registry, and the exporter's interest.
pub(super) async fn bus_events(
    link: Arc<Link>,
    events: Inbox<Event>,
    remote_interest: mpsc::UnboundedSender<(bool, String, String)>,
    ctx: Arc<Context>,
) {
    let registry = &ctx.fb.registry;
    let liveliness = |kind: &str| {
        ctx.metrics
            .bridge_liveliness
            .with_label_values(&[kind])
            .inc()
    };
    while let Some(event) = events.recv().await {
        match event {
            Event::InterestAdded { line, filter } => {
                let _ = remote_interest.send((true, line, filter));
            }
            Event::InterestRemoved { line, filter } => {
                let _ = remote_interest.send((false, line, filter));
            }
            Event::LineUp(line) => {
                liveliness("line_up");
                tracing::info!(line, "line reachable");
                // Every record of the line, online or not, in the background: the
                // events keep flowing meanwhile.
                let (link, ctx) = (Arc::clone(&link), Arc::clone(&ctx));
                tokio::spawn(async move {
                    match link.query_records(&line).await {
                        Ok(records) => {
                            for (l, d, json) in records {
                                apply_record(&ctx, &l, &d, &json);
                            }
                        }
                        Err(e) => tracing::warn!(line, error = %e, "registry query failed"),
                    }
                });
            }
            Event::LineDown(line) => {
                liveliness("line_down");
                tracing::warn!(line, "line unreachable: its devices are marked unreachable");
                registry.line_unreachable(&line);
            }
            Event::DeviceUp { line, device } => {
                liveliness("device_up");
                if registry.get(&device).is_some_and(|r| r.line == line) {
                    registry.remote_status(&line, &device, Status::Online);
                } else {
                    let (link, ctx) = (Arc::clone(&link), Arc::clone(&ctx));
                    tokio::spawn(async move {
                        if let Ok(records) = link.query_records(&line).await {
                            for (l, d, json) in records {
                                if d == device {
                                    apply_record(&ctx, &l, &d, &json);
                                }
                            }
                        }
                    });
                }
            }
            Event::DeviceDown { line, device } => {
                liveliness("device_down");
                // Gone offline (its line put the record first) or cut off: a record that
                // still says online means this line lost sight of it.
                if registry
                    .get(&device)
                    .is_some_and(|r| r.line == line && r.status == Status::Online)
                {
                    registry.remote_status(&line, &device, Status::Unreachable);
                }
            }
            Event::Record { line, device, json } => apply_record(&ctx, &line, &device, &json),
        }
    }
}

/// A record another line put or served under its key `fbbus/@/record/<line>/<device>`.
/// Taken only if it is that line's record of that device: on a mutual-TLS bus zenoh's
/// access control lets only `line` put or reply under its key, but the body is the
/// sender's to write, and a record naming another line would make that line's devices
/// (issue 22: line C registering a device of line A on line B).
pub(super) fn apply_record(ctx: &Context, line: &str, device: &str, json: &[u8]) {
    match serde_json::from_slice::<Record>(json) {
        Ok(record) if record.line == line && record.id == device => {
            ctx.fb.registry.remote_record(record)
        }
        Ok(record) => tracing::warn!(
            key_line = line,
            key_device = device,
            line = record.line,
            device = record.id,
            "registry record refused: it is not the record of the line and device of its key"
        ),
        Err(e) => tracing::warn!(error = %e, "unreadable registry record from another line"),
    }
}

/// Puts each local record change on the bus and keeps a liveliness token per online
/// local device.
pub(super) async fn announce_local(
    link: Arc<Link>,
    now: Vec<Record>,
    mut changes: mpsc::UnboundedReceiver<Record>,
) {
    let mut tokens: HashMap<String, DeviceToken> = HashMap::new();
    for record in now {
        announce(&link, &mut tokens, record).await;
    }
    while let Some(record) = changes.recv().await {
        announce(&link, &mut tokens, record).await;
    }
}

pub(super) async fn announce(
    link: &Link,
    tokens: &mut HashMap<String, DeviceToken>,
    record: Record,
) {
    {
        let json = serde_json::to_vec(&record).expect("records serialize");
        // The record first: a line that sees the token go finds the device offline already.
        if let Err(e) = link.put_record(&record.id, json).await {
            tracing::warn!(device = record.id, error = %e, "record not put on the bus");
        }
        match record.status {
            Status::Online if !tokens.contains_key(&record.id) => {
                match link.device_online(&record.id).await {
                    Ok(token) => {
                        tokens.insert(record.id.clone(), token);
                    }
                    Err(e) => {
                        tracing::warn!(device = record.id, error = %e, "liveliness token not declared")
                    }
                }
            }
            Status::Online => {}
            _ => {
                tokens.remove(&record.id);
            }
        }
    }
}

//! Registry federation: this line's devices announced on the bus, the other lines'
//! records and liveliness taken into the registry.
//!
//! A line puts a device's record on every change, before its liveliness token, so a
//! device usually comes up here with its record already taken. Only a record missed (a
//! line that joined later, a partition) is asked for, and asking is coalesced per line
//! ([`Asks`]): the devices of one line seen without a record within [`COLLECT`] are asked
//! for one by one when they are few, with one query for the whole line when they are more
//! than [`ASK_ONE_BY_ONE`] or the line itself came up. Before (issue 32), each unknown
//! device's token made this line ask for every record of its line: a line of 1,000
//! devices coming up cost each other line 1,000 queries of 1,000 records, zenoh's queues
//! filled and it closed the transports.

use std::collections::HashMap;
use std::sync::{Arc, Mutex, PoisonError};
use std::time::Duration;

use fb_bridge::bus::link::{DeviceToken, Event, Inbox, Link};
use tokio::sync::mpsc;

use super::Interest;
use crate::registry::{LocalChange, Record, RecordRefused, Status};
use crate::session::Context;

/// Liveliness and records of the other lines: the registry, and the exporter's interest.
pub(super) async fn bus_events(
    link: Arc<Link>,
    events: Inbox<Event>,
    (remote_interest, imports): (
        mpsc::UnboundedSender<(bool, String, String)>,
        mpsc::UnboundedSender<Interest>,
    ),
    ctx: Arc<Context>,
) {
    let registry = &ctx.fb.registry;
    let asks = Asks {
        pending: Arc::default(),
        imports,
    };
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
                registry.line_reachable(&line);
                // Every record of the line, online or not, in the background: the
                // events keep flowing meanwhile.
                asks.ask(&link, &ctx, &line, None);
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
                    asks.ask(&link, &ctx, &line, Some(device));
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
            Event::Record { line, device, json } => apply_record(&ctx, &line, &device, &json, None),
            Event::Forgotten { line, device } => {
                if registry.remote_forgotten(&line, &device) {
                    liveliness("forgotten");
                }
            }
        }
    }
}

/// How long the devices of a line seen without a record are collected before they are
/// asked for together.
const COLLECT: Duration = Duration::from_millis(100);

/// More unknown devices of one line than this within [`COLLECT`]: one query for the
/// whole line instead.
const ASK_ONE_BY_ONE: usize = 16;

/// What is to be asked of each line: some devices, or (None) all of them. After a whole
/// line's records, its retained messages are asked for again (`Interest::Requery`).
#[derive(Clone)]
struct Asks {
    pending: Arc<Mutex<HashMap<String, Option<Vec<String>>>>>,
    imports: mpsc::UnboundedSender<Interest>,
}

impl Asks {
    /// Asks line `line` for the record of `device`, or (None) of every device, together
    /// with whatever else is asked of it within [`COLLECT`].
    fn ask(&self, link: &Arc<Link>, ctx: &Arc<Context>, line: &str, device: Option<String>) {
        let first = {
            let mut asks = self.pending.lock().unwrap_or_else(PoisonError::into_inner);
            let first = !asks.contains_key(line);
            let entry = asks
                .entry(line.to_owned())
                .or_insert_with(|| Some(Vec::new()));
            match (entry.as_mut(), device) {
                (Some(devices), Some(device)) if devices.len() < ASK_ONE_BY_ONE => {
                    devices.push(device)
                }
                _ => *entry = None,
            }
            first
        };
        if first {
            let (asks, link, ctx) = (self.clone(), Arc::clone(link), Arc::clone(ctx));
            let line = line.to_owned();
            tokio::spawn(async move {
                tokio::time::sleep(COLLECT).await;
                let asked = asks
                    .pending
                    .lock()
                    .unwrap_or_else(PoisonError::into_inner)
                    .remove(&line);
                let Some(asked) = asked else { return };
                let registry = &ctx.fb.registry;
                let whole_line = asked.is_none();
                let queries: Vec<Option<String>> = match asked {
                    None => vec![None],
                    // Those whose records came meanwhile are not asked for.
                    Some(devices) => devices
                        .into_iter()
                        .filter(|d| registry.get(d).is_none_or(|r| r.line != line))
                        .map(Some)
                        .collect(),
                };
                for device in queries {
                    let kind = if device.is_some() { "device" } else { "line" };
                    ctx.metrics
                        .bridge_record_queries
                        .with_label_values(&[kind])
                        .inc();
                    let mark = Some(registry.live_mark());
                    match link.query_records(&line, device.as_deref()).await {
                        Ok(records) => {
                            for (from, d, json) in records {
                                if device.as_deref().is_none_or(|wanted| wanted == d) {
                                    apply_record(&ctx, &from, &d, &json, mark);
                                }
                            }
                        }
                        Err(e) => tracing::warn!(line, error = %e, "registry query failed"),
                    }
                }
                // Its devices known, its retained messages can be taken.
                if whole_line {
                    let _ = asks.imports.send(Interest::Requery(line));
                }
            });
        }
    }
}

/// Takes a record line `from` put (live, `asked` None) or served (to a query sent at
/// registry mark `asked`) on `fbbus/@/record/<from>/<device>`: only for its own device,
/// under the key's id; refusals counted like refused messages. The query runs beside the
/// live records, so its answer can come after a newer one: the registry keeps the newer.
pub(super) fn apply_record(
    ctx: &Context,
    from: &str,
    device: &str,
    json: &[u8],
    asked: Option<u64>,
) {
    let record = match serde_json::from_slice::<Record>(json) {
        Ok(record) => record,
        Err(e) => {
            return tracing::warn!(line = from, error = %e, "unreadable registry record from another line")
        }
    };
    let registry = &ctx.fb.registry;
    let taken = match (record.id == device, asked) {
        (false, _) => Err(RecordRefused::ForgedLine),
        (true, None) => registry.remote_record(from, record),
        (true, Some(mark)) => registry.queried_record(from, record, mark),
    };
    if let Err(refused) = taken {
        ctx.metrics.bus_refused(from, refused.as_str());
        tracing::debug!(
            line = from,
            device,
            reason = refused.as_str(),
            "registry record from another line refused"
        );
    }
}

/// Puts each local record change on the bus and keeps a liveliness token per online
/// local device.
pub(super) async fn announce_local(
    link: Arc<Link>,
    now: Vec<Record>,
    mut changes: mpsc::UnboundedReceiver<LocalChange>,
) {
    let mut tokens: HashMap<String, DeviceToken> = HashMap::new();
    for record in now {
        announce(&link, &mut tokens, record).await;
    }
    while let Some(change) = changes.recv().await {
        match change {
            LocalChange::Record(record) => announce(&link, &mut tokens, record).await,
            LocalChange::Forgotten(device) => {
                tokens.remove(&device);
                if let Err(e) = link.forget_record(&device).await {
                    tracing::warn!(device, error = %e, "forgetting not put on the bus");
                }
            }
        }
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

//! Registry federation: this line's devices announced on the bus, the other lines'
//! records and liveliness taken into the registry.
//!
//! A device's state crosses the bus in its record, put on every change; the only
//! liveliness tokens are one per line (is its bridge there) and one per imported filter.
//! A line's records are asked for once, all together, when the line comes up or back
//! ([`Asks`]). Before issue 32, each online device had a liveliness token of its own and
//! a token without a record made this line ask for every record of its line: at 8 lines
//! of 1,000 devices, zenoh's routers spent most of their CPU matching each new token
//! against all the others (`Resource::matches` in a profile), the registries took 20 s
//! to converge and a router's death cost 18 s.

use std::collections::HashSet;
use std::sync::{Arc, Mutex, PoisonError};
use std::time::Duration;

use fb_bridge::bus::link::{Event, Inbox, Link};
use tokio::sync::mpsc;

use super::Interest;
use crate::registry::{LocalChange, Record, RecordRefused};
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
                asks.ask(&link, &ctx, &line);
            }
            Event::LineDown(line) => {
                liveliness("line_down");
                tracing::warn!(line, "line unreachable: its devices are marked unreachable");
                registry.line_unreachable(&line);
            }
            Event::Record { line, device, json } => apply_record(&ctx, &line, &device, &json, None),
            Event::Forgotten { line, device } => {
                if registry.remote_forgotten(&line, &device) {
                    liveliness("forgotten");
                }
            }
            Event::LossReported { line, lost } => {
                ctx.metrics.bridge_lost_reported.inc_by(lost);
                static LOGGED: crate::logging::OnceAMinute = crate::logging::OnceAMinute::new();
                if LOGGED.due() {
                    tracing::warn!(
                        line,
                        lost,
                        "another line reports messages of this line that never reached it \
                         (fbbus_bridge_lost_reported_total, logged at most once a minute)"
                    );
                }
            }
        }
    }
}

/// How long a line's coming up is left to settle before its records are asked for: a
/// line that flaps (a router failing over) is asked once.
const COLLECT: Duration = Duration::from_millis(100);

/// The lines whose records are to be asked for. After a line's records, its retained
/// messages are asked for again (`Interest::Requery`).
#[derive(Clone)]
struct Asks {
    pending: Arc<Mutex<HashSet<String>>>,
    imports: mpsc::UnboundedSender<Interest>,
}

impl Asks {
    /// Asks line `line` for every record it holds, in the background (the events keep
    /// flowing meanwhile), unless that is asked already.
    fn ask(&self, link: &Arc<Link>, ctx: &Arc<Context>, line: &str) {
        let first = self
            .pending
            .lock()
            .unwrap_or_else(PoisonError::into_inner)
            .insert(line.to_owned());
        if !first {
            return;
        }
        let (asks, link, ctx) = (self.clone(), Arc::clone(link), Arc::clone(ctx));
        let line = line.to_owned();
        tokio::spawn(async move {
            tokio::time::sleep(COLLECT).await;
            asks.pending
                .lock()
                .unwrap_or_else(PoisonError::into_inner)
                .remove(&line);
            ctx.metrics
                .bridge_record_queries
                .with_label_values(&["line"])
                .inc();
            let mark = Some(ctx.fb.registry.live_mark());
            match link.query_records(&line, None).await {
                Ok(records) => {
                    for (from, device, json) in records {
                        apply_record(&ctx, &from, &device, &json, mark);
                    }
                }
                Err(e) => tracing::warn!(line, error = %e, "registry query failed"),
            }
            // Its devices known, its retained messages can be taken.
            let _ = asks.imports.send(Interest::Requery(line));
        });
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

/// Puts each local record change on the bus: the devices there now, then every change.
pub(super) async fn announce_local(
    link: Arc<Link>,
    now: Vec<Record>,
    mut changes: mpsc::UnboundedReceiver<LocalChange>,
) {
    for record in now {
        announce(&link, &record).await;
    }
    while let Some(change) = changes.recv().await {
        match change {
            LocalChange::Record(record) => announce(&link, &record).await,
            LocalChange::Forgotten(device) => {
                if let Err(e) = link.forget_record(&device).await {
                    tracing::warn!(device, error = %e, "forgetting not put on the bus");
                }
            }
        }
    }
}

async fn announce(link: &Link, record: &Record) {
    let json = serde_json::to_vec(record).expect("records serialize");
    if let Err(e) = link.put_record(&record.id, json).await {
        tracing::warn!(device = record.id, error = %e, "record not put on the bus");
    }
}

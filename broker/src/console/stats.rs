//! The line's rates for the console's charts: one sample a second of the counters'
//! deltas (messages in and out, typed accepted and refused) and of the gauges
//! (connections, devices by status), kept for the last [`SAMPLES`] seconds.
//!
//! One task samples, whatever the number of pages: each sample is serialized once and
//! handed to every feed through a `watch` channel (a slow feed skips to the newest),
//! and the ring answers a page that opens with the last five minutes at once. The
//! counters are atomics and the registry's counts are kept up to date by every change,
//! so a sample costs one short registry lock, not a walk over the devices.

use std::collections::VecDeque;
use std::sync::atomic::Ordering;
use std::sync::{Arc, Mutex, PoisonError};
use std::time::{Duration, SystemTime, UNIX_EPOCH};

use bytes::Bytes;
use serde::Serialize;
use tokio::sync::watch;

use crate::metrics::Metrics;
use crate::registry::Registry;

/// Samples kept: five minutes at one a second.
pub const SAMPLES: usize = 300;
/// Between samples.
pub const INTERVAL: Duration = Duration::from_secs(1);

/// One second of the line.
#[derive(Debug, Clone, Copy, Default, Serialize)]
pub struct Sample {
    /// Unix time, milliseconds.
    pub t: u64,
    /// Per second over the last interval.
    pub msgs_in: f64,
    pub msgs_out: f64,
    pub accepted: f64,
    pub refused: f64,
    pub connections: i64,
    /// Every line's devices by status.
    pub online: i64,
    pub offline: i64,
    pub unreachable: i64,
    pub silent: i64,
    /// This line's online devices (what `fbbus/lines/<line>/online` says).
    pub line_online: i64,
}

#[derive(Default, Clone, Copy)]
struct Totals {
    msgs_in: u64,
    msgs_out: u64,
    accepted: u64,
    refused: u64,
}

pub struct Stats {
    ring: Mutex<VecDeque<Sample>>,
    /// The newest `stats` event's JSON (sample and bridge lines), for the feeds.
    latest: watch::Sender<Bytes>,
}

impl Stats {
    pub fn new() -> Arc<Stats> {
        Arc::new(Stats {
            ring: Mutex::new(VecDeque::with_capacity(SAMPLES)),
            latest: watch::channel(Bytes::new()).0,
        })
    }

    /// The samples of the last [`SAMPLES`] seconds, oldest first.
    pub fn history(&self) -> Vec<Sample> {
        self.ring
            .lock()
            .unwrap_or_else(PoisonError::into_inner)
            .iter()
            .copied()
            .collect()
    }

    /// Each new `stats` event.
    pub fn subscribe(&self) -> watch::Receiver<Bytes> {
        self.latest.subscribe()
    }

    /// Samples every [`INTERVAL`], until the broker stops.
    pub async fn run(self: Arc<Self>, metrics: Arc<Metrics>, registry: Arc<Registry>) {
        let mut tick = tokio::time::interval(INTERVAL);
        tick.set_missed_tick_behavior(tokio::time::MissedTickBehavior::Delay);
        tick.tick().await;
        let mut last = totals(&metrics);
        let mut at = tokio::time::Instant::now();
        loop {
            tick.tick().await;
            let now = totals(&metrics);
            let elapsed = at.elapsed().as_secs_f64().max(1e-3);
            at = tokio::time::Instant::now();
            let rate = |a: u64, b: u64| a.saturating_sub(b) as f64 / elapsed;
            let by_status = |s: &str| metrics.registry_devices.with_label_values(&[s]).get();
            let sample = Sample {
                t: SystemTime::now()
                    .duration_since(UNIX_EPOCH)
                    .map_or(0, |d| d.as_millis() as u64),
                msgs_in: rate(now.msgs_in, last.msgs_in),
                msgs_out: rate(now.msgs_out, last.msgs_out),
                accepted: rate(now.accepted, last.accepted),
                refused: rate(now.refused, last.refused),
                connections: metrics.connections.get(),
                online: by_status("online"),
                offline: by_status("offline"),
                unreachable: by_status("unreachable"),
                silent: metrics.registry_silent_devices.get(),
                line_online: registry.line_online(),
            };
            last = now;
            {
                let mut ring = self.ring.lock().unwrap_or_else(PoisonError::into_inner);
                if ring.len() == SAMPLES {
                    ring.pop_front();
                }
                ring.push_back(sample);
            }
            let event = serde_json::json!({"sample": sample, "lines": registry.lines()});
            if let Ok(json) = serde_json::to_vec(&event) {
                self.latest.send_replace(json.into());
            }
        }
    }
}

fn totals(metrics: &Metrics) -> Totals {
    Totals {
        msgs_in: metrics.messages_in.get(),
        msgs_out: metrics.messages_out.get(),
        accepted: metrics.typed_accepted.get(),
        refused: metrics.typed_refused_all.load(Ordering::Relaxed),
    }
}

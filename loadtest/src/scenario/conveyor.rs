//! `conveyor`: the study's line, simulated. N conveyor devices in a chain, each a real
//! fb-bridge client device with an FB `CONV` whose event `STATE` carries `PART` and `T0`.
//! Conveyor 0 is fed parts by the harness (REQ -> CNF, as an FB would); conveyor i has a
//! SUBSCRIBE FB on conveyor i-1's `STATE` and, on every IND, REQs its own `STATE` with
//! the same data; a SUBSCRIBE FB at the end of the line counts the parts that made it
//! through and their latency from `T0`, when the part entered the line.
//!
//! Every hop is an event through the broker with fbbus's type check, QoS 1 and a CNF, so
//! the figures are what an FB network spread over N devices sees end to end. Needs a
//! broker that speaks the fbbus device contract; for any other, the report says so.

use std::time::{Duration, Instant};

use fb_bridge::client::{Device, DeviceConfig};
use fb_bridge::{Interface, Value};
use serde::Serialize;
use tokio::task::JoinHandle;

use crate::model::Batch;
use crate::session::Session;
use crate::tally::{self, Tally};
use crate::target::Target;
use crate::{clock, Error};

/// Every conveyor's declaration.
const CONVEYOR: &str = r#"{"fbs":{"CONV":{
    "events_out":{"STATE":{"with":["PART","T0"]}},
    "data_out":{"PART":"UDINT","T0":"ULINT"}}}}"#;
/// The end-of-line observer's declaration.
const OBSERVER: &str = r#"{"fbs":{"END":{
    "events_in":{"STATE":{"with":["PART","T0"]}},
    "data_in":{"PART":"UDINT","T0":"ULINT"}}}}"#;

#[derive(Debug, Clone, Serialize)]
pub struct Conveyor {
    /// Line lengths to run (devices in the chain), each a point on the charts.
    pub devices: Vec<usize>,
    /// Parts fed into the line per batch.
    pub parts: u64,
    /// Parts per second fed into the first conveyor; `None`: one after the other, each
    /// as soon as the previous REQ's CNF is back.
    pub rate: Option<f64>,
    pub repeats: u32,
}

/// A line of conveyors on one broker.
struct Line {
    devices: Vec<Device>,
    forwarders: Vec<JoinHandle<()>>,
    feeder: fb_bridge::client::Publisher,
    observer: Device,
    counter: JoinHandle<()>,
    tally: std::sync::Arc<std::sync::Mutex<Tally>>,
    next_part: u64,
}

impl Conveyor {
    pub fn planned(&self, targets: usize) -> u64 {
        (self.devices.len() * self.repeats as usize * targets) as u64
    }

    pub async fn run(
        &self,
        s: &mut Session,
        targets: &[Target],
        prefix: &str,
        timeout: Duration,
        quiet: Duration,
    ) {
        // A target that could not build a line is not tried again for longer ones.
        let mut failed = vec![false; targets.len()];
        for &n in &self.devices {
            let mut lines = Vec::new();
            for (rig, target) in targets.iter().enumerate() {
                let label = s.labels[rig].clone();
                if failed[rig] {
                    lines.push(None);
                    continue;
                }
                let id = format!("{prefix}-{}-conv", label.to_lowercase());
                match Line::build(target, &id, n.max(1), timeout).await {
                    Ok(line) => lines.push(Some(line)),
                    Err(e) => {
                        s.notes.push(format!(
                            "{label}: no conveyor line from {n} devices on: {e} (the conveyor scenario needs a broker that speaks the fbbus device contract)"
                        ));
                        failed[rig] = true;
                        lines.push(None);
                    }
                }
            }
            for repeat in 1..=self.repeats {
                for (rig, line) in lines.iter_mut().enumerate() {
                    let Some(line) = line else { continue };
                    if s.out_of_time() {
                        break;
                    }
                    let label = s.labels[rig].clone();
                    let (batch, histogram) = line.batch(&label, n, self, repeat, quiet).await;
                    s.record(rig, batch, &histogram);
                }
            }
            for line in lines.into_iter().flatten() {
                line.stop().await;
            }
        }
    }
}

impl Line {
    async fn build(
        target: &Target,
        prefix: &str,
        n: usize,
        timeout: Duration,
    ) -> Result<Line, Error> {
        if target.tls {
            return Err(Error::Contract(
                "fb-bridge's client speaks plain MQTT only".into(),
            ));
        }
        let config = |id: String| {
            let mut c = DeviceConfig::new(&target.host, target.port, id);
            c.password = target.password.clone();
            c.timeout = timeout;
            c.keep_alive = Duration::from_secs(60);
            c
        };
        let fb_error = |e: fb_bridge::client::ClientError| Error::Contract(e.to_string());
        let conveyor: Interface = serde_json::from_str(CONVEYOR).expect("a valid interface");
        let mut devices = Vec::new();
        for i in 0..n {
            let d = Device::connect(config(format!("{prefix}-{i}")), conveyor.clone())
                .await
                .map_err(fb_error)?;
            devices.push(d);
        }
        // Conveyor i follows conveyor i-1 and passes each part on.
        let mut forwarders = Vec::new();
        for (i, device) in devices.iter().enumerate().skip(1) {
            let mut upstream = device
                .subscriber(&format!("{prefix}-{}", i - 1), "CONV", "STATE")
                .await
                .map_err(fb_error)?;
            let mut state = device.publisher("CONV", "STATE").map_err(fb_error)?;
            forwarders.push(tokio::spawn(async move {
                while let Some(ind) = upstream.ind().await {
                    if let Err(e) = state.req(ind.data).await {
                        tracing::warn!(error = %e, "conveyor REQ failed");
                    }
                }
            }));
        }
        let observer: Interface = serde_json::from_str(OBSERVER).expect("a valid interface");
        let observer = Device::connect(config(format!("{prefix}-end")), observer)
            .await
            .map_err(fb_error)?;
        let mut last = observer
            .subscriber(&format!("{prefix}-{}", n - 1), "CONV", "STATE")
            .await
            .map_err(fb_error)?;
        let tally = std::sync::Arc::new(std::sync::Mutex::new(Tally::new(1)));
        let counter = {
            let tally = tally.clone();
            tokio::spawn(async move {
                while let Some(ind) = last.ind().await {
                    let now = clock::now_us();
                    if let [Value::Udint(part), Value::Ulint(t0)] = ind.data[..] {
                        crate::contract::lock(&tally).record(0, u64::from(part), t0, now);
                    }
                }
            })
        };
        let feeder = devices[0].publisher("CONV", "STATE").map_err(fb_error)?;
        Ok(Line {
            devices,
            forwarders,
            feeder,
            observer,
            counter,
            tally,
            next_part: 1,
        })
    }

    async fn batch(
        &mut self,
        target: &str,
        n: usize,
        c: &Conveyor,
        repeat: u32,
        quiet: Duration,
    ) -> (Batch, hdrhistogram::Histogram<u64>) {
        let base = self.next_part;
        self.next_part += c.parts;
        crate::contract::lock(&self.tally).begin(&[(base, c.parts)]);
        let started_ms = clock::now_ms();
        let start = Instant::now();
        let sent_at = clock::now_us();
        let mut sent = 0;
        let mut error = None;
        for k in 0..c.parts {
            if let Some(rate) = c.rate {
                tokio::time::sleep_until((start + Duration::from_secs_f64(k as f64 / rate)).into())
                    .await;
            }
            let part = Value::Udint((base + k) as u32);
            match self
                .feeder
                .req(vec![part, Value::Ulint(clock::now_us())])
                .await
            {
                Ok(_) => sent += 1,
                Err(e) => {
                    error = Some(format!("feeding part {}: {e}", base + k));
                    break;
                }
            }
        }
        let send_us = start.elapsed().as_micros() as u64;
        // Wait for the parts to reach the end of the line (quiet-time bounded).
        let mut last = (0, Instant::now());
        loop {
            let delivered = crate::contract::lock(&self.tally).delivered();
            if delivered >= sent || last.1.elapsed() >= quiet {
                break;
            }
            if delivered != last.0 {
                last = (delivered, Instant::now());
            }
            tokio::time::sleep(Duration::from_millis(2)).await;
        }
        let counts = crate::contract::lock(&self.tally).counts();
        let processing_us = counts.last_us.map_or(0, |l| l.saturating_sub(sent_at));
        let lost = c.parts.saturating_sub(counts.delivered);
        let error =
            error.or_else(|| (lost > 0).then(|| format!("lost {lost} of {} parts", c.parts)));
        let batch = Batch {
            target: target.to_owned(),
            label: format!("line of {n}"),
            x: n as f64,
            repeat,
            started_ms,
            sent,
            delivered: counts.delivered,
            expected: c.parts,
            delivered_fb: Some(counts.delivered),
            duplicates: counts.duplicates,
            out_of_order: counts.out_of_order,
            send_us,
            processing_us,
            throughput: if processing_us == 0 {
                0.0
            } else {
                counts.delivered as f64 / (processing_us as f64 / 1e6)
            },
            latency: tally::summarize(&counts.latency),
            ok: error.is_none(),
            error,
        };
        (batch, counts.latency)
    }

    async fn stop(self) {
        for f in &self.forwarders {
            f.abort();
        }
        self.counter.abort();
        self.observer.disconnect().await;
        for d in &self.devices {
            d.disconnect().await;
        }
    }
}

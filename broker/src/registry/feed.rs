//! The change feed: every change of a record is published retained on
//! `fbbus/devices/<id>` with the line's online count when it changed, handed to the bridge's observer
//! (local devices) and sent on the console's bounded broadcast channel.

use std::sync::{Arc, PoisonError};

use fb_bridge::topic;

use super::records::{Counts, Devices, Record, Status};
use super::Registry;
use crate::broker_publisher::Message;

/// Record changes the console's broadcast channel holds ([`Registry::changes`]): a
/// receiver further behind than this is told it lagged and reloads. 4,096 covers a
/// line of 1,000 devices all changing at once (a broker restart) with room to spare;
/// each slot is an `Arc` and the record's JSON, shared by every receiver.
pub const CHANGES_CAPACITY: usize = 4096;

/// One change of a local device, as the bridge announces it to the other lines.
#[derive(Debug, Clone)]
#[cfg_attr(not(feature = "bridge"), allow(dead_code))]
pub enum LocalChange {
    /// Its record as it is now.
    Record(Record),
    /// It was forgotten (by hand or by age): the other lines forget it too.
    Forgotten(String),
}

/// One change of the registry, as the console's live feed sends it.
#[derive(Debug, Clone)]
pub enum Change {
    /// A device's record as it is now, with its JSON (the one published on
    /// `fbbus/devices/<id>`, serialized once for every receiver).
    Record(Arc<Record>, bytes::Bytes),
    /// A device was forgotten.
    Removed(Arc<str>),
}

impl Registry {
    /// Every change of a local device's record from now on is sent to `observer`.
    /// Returns the local records as they are now.
    #[cfg_attr(not(feature = "bridge"), allow(dead_code))]
    pub fn observe(
        &self,
        observer: tokio::sync::mpsc::UnboundedSender<LocalChange>,
    ) -> Vec<Record> {
        let devices = self.devices.lock().unwrap_or_else(PoisonError::into_inner);
        let _ = self.observer.set(observer);
        devices
            .values()
            .filter(|r| r.line == self.line)
            .cloned()
            .collect()
    }

    /// Every change of a record (local or remote) and every removal from now on, on a
    /// channel of [`CHANGES_CAPACITY`]: a receiver that falls further behind gets
    /// `Lagged` and must read the registry again.
    pub fn changes(&self) -> tokio::sync::broadcast::Receiver<Change> {
        self.changes.subscribe()
    }

    pub(super) fn announce(&self, record: &Record) {
        if record.line == self.line {
            if let Some(observer) = self.observer.get() {
                let _ = observer.send(LocalChange::Record(record.clone()));
            }
        }
        let payload = bytes::Bytes::from(serde_json::to_vec(record).expect("a record serializes"));
        // Without a receiver (no console) nothing is cloned.
        if self.changes.receiver_count() > 0 {
            let _ = self
                .changes
                .send(Change::Record(Arc::new(record.clone()), payload.clone()));
        }
        self.publisher.publish(Message::broker(
            topic::device_record(&record.id),
            payload,
            true,
        ));
    }

    pub(super) fn announce_count(&self, devices: &Devices) {
        let Counts {
            by_status,
            online_here,
            silent,
            ..
        } = devices.counts;
        self.metrics.registry_silent_devices.set(silent);
        for (status, count) in [Status::Online, Status::Offline, Status::Unreachable]
            .into_iter()
            .zip(by_status)
        {
            self.metrics
                .registry_devices
                .with_label_values(&[status.label()])
                .set(count);
        }
        // Called with the devices locked: the last count published is the current one.
        let before = self
            .announced_online
            .swap(online_here, std::sync::atomic::Ordering::Relaxed);
        if before != online_here {
            self.publisher.publish(Message::broker(
                topic::line_online(&self.line),
                online_here.to_string(),
                true,
            ));
        }
    }
}

//! The fbbus device contract, as far as the load needs it (docs/device-contract.md).
//!
//! Each publisher is a device `<prefix>-pub-<i>` with one FB `LOAD` whose event output
//! `MSG` carries no data: the load messages of [`crate::message`] are its events, on
//! `fb/<device>/LOAD/MSG`. On fbbus the publisher declares that interface first, so the
//! broker type-checks every message as it would a real device's. A broker that does not
//! answer the declaration (Mosquitto, any plain MQTT broker) just carries the same
//! topics; the FB subscriber is then left out and the report says so.
//!
//! The FB subscriber is where the study counted delivery: a device using fb-bridge's
//! client API, a SUBSCRIBE FB per publisher, counting typed INDs.

use std::sync::{Arc, Mutex};
use std::time::Duration;

use fb_bridge::client::{Device, DeviceConfig, Diagnostic};
use fb_bridge::{topic, Interface};
use tokio::sync::mpsc;
use tokio::task::JoinHandle;

use crate::client::{self, Client};
use crate::tally::Tally;
use crate::target::Target;
use crate::{clock, Error};

/// The publisher's declaration.
pub const PUBLISHER_INTERFACE: &str = r#"{"fbs":{"LOAD":{"events_out":{"MSG":{"with":[]}}}}}"#;
/// The FB subscriber's declaration: the matching event input.
pub const SUBSCRIBER_INTERFACE: &str = r#"{"fbs":{"SINK":{"events_in":{"MSG":{"with":[]}}}}}"#;

/// How long a broker has to answer a declaration before it is taken for one that does
/// not speak the contract.
pub const DECLARATION_WAIT: Duration = Duration::from_secs(2);

/// A publisher device's event topic.
pub fn topic(device: &str) -> String {
    format!("fb/{device}/LOAD/MSG")
}

/// What the broker said to a declaration.
#[derive(Debug, Clone, PartialEq)]
pub enum Declared {
    /// fbbus accepted it: messages are type-checked.
    Accepted,
    /// Nothing answered: not an fbbus broker.
    NoAnswer,
}

/// Declares `client`'s device. `diag` receives what arrives on its diag topic (the
/// publisher's `on_publish` forwards it).
pub async fn declare(
    client: &mut Client,
    diag: &mut mpsc::UnboundedReceiver<Vec<u8>>,
) -> Result<Declared, Error> {
    let id = client.id().to_owned();
    client
        .subscribe(&[topic::diag(&id)], client::qos(1))
        .await?;
    client
        .publish(
            &topic::declare(&id),
            client::qos(1),
            PUBLISHER_INTERFACE.as_bytes().to_vec(),
        )
        .await?;
    let answer = tokio::time::timeout(DECLARATION_WAIT, async {
        while let Some(payload) = diag.recv().await {
            match Diagnostic::parse(&payload) {
                Diagnostic::Declared { .. } => return Ok(Declared::Accepted),
                Diagnostic::DeclarationRefused { errors } => {
                    return Err(Error::Contract(format!(
                        "the broker refused the load publisher's declaration: {}",
                        errors.join("; ")
                    )))
                }
                _ => {}
            }
        }
        Ok(Declared::NoAnswer)
    })
    .await;
    answer.unwrap_or(Ok(Declared::NoAnswer))
}

/// A device with one SUBSCRIBE FB per publisher, counting INDs into its tally.
pub struct FbSubscriber {
    device: Device,
    tasks: Vec<JoinHandle<()>>,
    pub tally: Arc<Mutex<Tally>>,
}

impl FbSubscriber {
    /// Connects device `id` and INITs a SUBSCRIBE FB on each publisher's `LOAD.MSG`;
    /// publisher `publishers[i]` is tally stream `i`.
    pub async fn start(
        target: &Target,
        id: &str,
        publishers: &[String],
        timeout: Duration,
    ) -> Result<FbSubscriber, Error> {
        if target.tls {
            return Err(Error::Contract(
                "the FB subscriber (fb-bridge's client) speaks plain MQTT only".into(),
            ));
        }
        let mut config = DeviceConfig::new(&target.host, target.port, id);
        config.password = target.password.clone();
        config.timeout = timeout;
        config.keep_alive = Duration::from_secs(60);
        let interface: Interface =
            serde_json::from_str(SUBSCRIBER_INTERFACE).expect("a valid interface");
        let fb_error =
            |e: fb_bridge::client::ClientError| Error::Contract(format!("FB subscriber {id}: {e}"));
        let device = Device::connect(config, interface).await.map_err(fb_error)?;
        let tally = Arc::new(Mutex::new(Tally::new(publishers.len())));
        let mut tasks = Vec::new();
        for (stream, publisher) in publishers.iter().enumerate() {
            let mut sub = device
                .subscriber(publisher, "LOAD", "MSG")
                .await
                .map_err(fb_error)?;
            let tally = tally.clone();
            tasks.push(tokio::spawn(async move {
                while let Some(ind) = sub.ind().await {
                    let now = clock::now_us();
                    if let (Some(seq), Some(ts)) = (ind.seq, ind.ts_us) {
                        lock(&tally).record(stream, seq, ts, now);
                    }
                }
            }));
        }
        Ok(FbSubscriber {
            device,
            tasks,
            tally,
        })
    }

    pub async fn stop(self) {
        for task in &self.tasks {
            task.abort();
        }
        self.device.disconnect().await;
    }
}

/// Locks a tally; a panic elsewhere must not stop the counting.
pub fn lock(tally: &Mutex<Tally>) -> std::sync::MutexGuard<'_, Tally> {
    tally.lock().unwrap_or_else(|p| p.into_inner())
}

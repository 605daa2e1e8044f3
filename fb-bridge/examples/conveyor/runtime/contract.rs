//! A module on the device contract: a `fb_bridge::client` device. It declares `CONV`,
//! sets a typed will (`CONV.CONNECT = FALSE`), publishes at QoS 1, follows the broker's
//! online count and learns each peer's ports from the registry, so it needs no
//! engineering about the peers' runtimes: a peer whose interface has STATE is followed
//! on it, one with data outputs only (a DINASORE module) on those.

use std::sync::Arc;
use std::time::Duration;

use fb_bridge::client::{ClientError, Device, DeviceConfig, Publisher, Subscriber, WillSpec};
use fb_bridge::Value;
use tokio::sync::mpsc;
use tokio::task::JoinSet;

use super::{followed_ports, interface, Heard, Outputs, PeerUpdate, Runtime, Setup};
use crate::log;

pub struct Link {
    device: Arc<Device>,
    state: Publisher,
    connect: Publisher,
    /// The count and the followers; dropping the set (the module's task ends or is
    /// aborted) stops them, and with the last handle the device's connection ends.
    tasks: JoinSet<()>,
}

impl Link {
    pub async fn open(
        id: &str,
        setup: &Setup,
        peers: Vec<(String, Runtime)>,
        heard: mpsc::Sender<Heard>,
    ) -> Result<Link, String> {
        let mut config = DeviceConfig::new(&setup.host, setup.port, id);
        config.keep_alive = setup.keep_alive;
        config.will = Some(WillSpec::new("CONV", "CONNECT", Value::Bool(false)));
        let device = Device::connect(config, interface(Runtime::Contract))
            .await
            .map_err(|e| e.to_string())?;
        let device = Arc::new(device);
        log(format!(
            "{id}: connected (contract), session {}, line {}",
            device.session(),
            device.line()
        ));
        if device.line() != setup.line && peers.iter().any(|(_, r)| *r == Runtime::Forte) {
            log(format!(
                "{id}: WARNING: the broker serves line {:?}, FORTE modules read the count of \
                 --line {:?}",
                device.line(),
                setup.line
            ));
        }
        let mut count = device
            .online_count(&device.line())
            .await
            .map_err(|e| e.to_string())?;
        let initial = *count.borrow_and_update();
        let _ = heard.send(Heard::Count(initial)).await;
        let mut tasks = JoinSet::new();
        let count_heard = heard.clone();
        tasks.spawn(async move {
            while count.changed().await.is_ok() {
                let n = *count.borrow_and_update();
                if count_heard.send(Heard::Count(n)).await.is_err() {
                    return;
                }
            }
        });
        for (peer, _) in peers {
            tasks.spawn(follow(device.clone(), peer, heard.clone()));
        }
        Ok(Link {
            state: device
                .publisher("CONV", "STATE")
                .map_err(|e| e.to_string())?,
            connect: device
                .publisher("CONV", "CONNECT")
                .map_err(|e| e.to_string())?,
            device,
            tasks,
        })
    }

    /// CONNECT, then STATE; each REQ returns with its CNF (the broker's PUBACK).
    pub async fn publish(&mut self, id: &str, out: &Outputs) -> Result<(), String> {
        self.connect
            .req(vec![Value::Bool(true)])
            .await
            .map_err(|e| e.to_string())?;
        self.state
            .req(vec![
                Value::String(id.to_owned()),
                Value::Bool(true),
                Value::Bool(out.sensor_in),
                Value::Bool(out.sensor_out),
                Value::Int(out.position),
                Value::Bool(out.swap),
            ])
            .await
            .map_err(|e| e.to_string())?;
        Ok(())
    }

    /// INIT-: a clean DISCONNECT, no will.
    pub async fn close(&mut self) {
        self.tasks.shutdown().await;
        self.device.disconnect().await;
    }
}

/// Follows one peer, once it is in the registry: its STATE if its interface has one,
/// otherwise its data outputs; and its CONNECT.
async fn follow(device: Arc<Device>, peer: String, heard: mpsc::Sender<Heard>) {
    // Dropping the set (this task aborted) stops the forwarders.
    let mut ports = JoinSet::new();
    let runtime = match subscribe(&device, &peer, "STATE").await {
        Ok(state) => {
            ports.spawn(forward(state, peer.clone(), "STATE", heard.clone()));
            Runtime::Contract
        }
        // No STATE in its registry record: a module with data outputs only.
        Err(_) => Runtime::Dinasore,
    };
    for &port in followed_ports(runtime)
        .iter()
        .filter(|port| **port != "STATE")
    {
        match subscribe(&device, &peer, port).await {
            Ok(subscriber) => {
                ports.spawn(forward(subscriber, peer.clone(), port, heard.clone()));
            }
            Err(e) => tracing::warn!(peer, port, error = %e, "not followed"),
        }
    }
    while ports.join_next().await.is_some() {}
}

/// Hands the module every IND of one subscriber.
async fn forward(
    mut subscriber: Subscriber,
    peer: String,
    port: &'static str,
    heard: mpsc::Sender<Heard>,
) {
    while let Some(ind) = subscriber.ind().await {
        let update = PeerUpdate::from_values(port, &ind.data);
        if heard.send(Heard::Peer(peer.clone(), update)).await.is_err() {
            return;
        }
    }
}

/// SUBSCRIBE INIT, retried until the peer is in the registry; `Err` when its interface
/// has no such output.
async fn subscribe(device: &Device, peer: &str, port: &str) -> Result<Subscriber, ClientError> {
    loop {
        match device.subscriber(peer, "CONV", port).await {
            Ok(subscriber) => return Ok(subscriber),
            Err(e @ ClientError::NotAnOutput { .. }) => return Err(e),
            // Not in the registry yet: the wait for its record starts over.
            Err(ClientError::UnknownDevice(_)) => {}
            Err(e) => {
                tracing::warn!(peer, port, error = %e, "SUBSCRIBE INIT failed; retrying");
                tokio::time::sleep(Duration::from_millis(500)).await;
            }
        }
    }
}

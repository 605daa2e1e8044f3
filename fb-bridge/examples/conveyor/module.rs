//! One conveyor module: a real fbbus device with its own connection.
//!
//! Its FB `CONV` has the data outputs of the reference line and the event output `STATE`
//! carrying all of them. Like a PLC scan, the module publishes its outputs every
//! [`CYCLE`] and on every change, so a module that joins later learns the others within
//! one cycle. It follows every other module of the roster (their `STATE` and `CONNECT`
//! ports, as soon as they are in the registry) and works out from their `POSITION`s who
//! comes before and after it. A part arrives when the module before it reports
//! `SENSOR_OUT`; the first module takes parts from the line's entrance.

use std::collections::BTreeMap;
use std::sync::Arc;
use std::time::Duration;

use fb_bridge::client::{ClientError, Device, DeviceConfig, Ind, Publisher, WillSpec};
use fb_bridge::{Interface, Value};
use tokio::sync::mpsc;
use tokio::task::JoinSet;

use crate::log;

/// The PLC scan: outputs are republished this often.
const CYCLE: Duration = Duration::from_millis(250);
/// How long a part takes from SENSOR_IN to SENSOR_OUT.
const BELT: Duration = Duration::from_millis(40);

const INTERFACE: &str = r#"{"fbs": {"CONV": {
    "type": "CONVEYOR",
    "events_out": {"STATE": {"with": ["ID", "CONNECT", "SENSOR_IN", "SENSOR_OUT", "POSITION", "SWAP"]}},
    "data_out": {"ID": "STRING", "CONNECT": "BOOL", "SENSOR_IN": "BOOL",
                 "SENSOR_OUT": "BOOL", "POSITION": "INT", "SWAP": "BOOL"}
}}}"#;

/// What the plant does to a module.
pub enum Command {
    /// A part waits at the line's entrance: the first module takes it.
    Feed,
    /// The module was moved to another position (a swap).
    MoveTo(i16),
    /// INIT-: disconnect cleanly and end.
    Stop,
}

/// What a module tells the plant (for the log and the phase checks).
#[derive(Debug)]
pub enum Report {
    Count {
        id: String,
        count: u64,
    },
    Neighbours {
        id: String,
        before: Option<String>,
        after: Option<String>,
    },
    /// The part reached SENSOR_IN, handed over by `from` (`None`: from the entrance).
    Entered {
        id: String,
        from: Option<String>,
    },
    /// The part left the line after this module.
    Left {
        id: String,
    },
    Failed {
        id: String,
        error: String,
    },
}

/// What the module knows about another module, from its messages.
#[derive(Debug, Default)]
struct Peer {
    position: Option<i16>,
    connected: bool,
    sensor_out: bool,
}

/// Messages from the follower tasks.
enum Heard {
    State(String, Ind),
    Connect(String, bool),
}

pub struct Module {
    id: String,
    position: i16,
    device: Arc<Device>,
    state: Publisher,
    connect: Publisher,
    peers: BTreeMap<String, Peer>,
    /// Before and after this module, as last reported.
    neighbours: (Option<String>, Option<String>),
    reported: bool,
    reports: mpsc::Sender<Report>,
}

/// Runs module `id` at `position` until it is stopped (or its task aborted).
pub async fn run(
    mut config: DeviceConfig,
    position: i16,
    roster: Vec<String>,
    commands: mpsc::Receiver<Command>,
    reports: mpsc::Sender<Report>,
) {
    let id = config.id.clone();
    config.will = Some(WillSpec::new("CONV", "CONNECT", Value::Bool(false)));
    if let Err(e) = Module::start(config, position, roster, commands, reports.clone()).await {
        let _ = reports
            .send(Report::Failed {
                id,
                error: e.to_string(),
            })
            .await;
    }
}

impl Module {
    async fn start(
        config: DeviceConfig,
        position: i16,
        roster: Vec<String>,
        commands: mpsc::Receiver<Command>,
        reports: mpsc::Sender<Report>,
    ) -> Result<(), ClientError> {
        let interface: Interface = serde_json::from_str(INTERFACE).expect("valid interface");
        let id = config.id.clone();
        let device = Arc::new(Device::connect(config, interface).await?);
        log(format!(
            "{id}: connected, session {}, line {}",
            device.session(),
            device.line()
        ));
        let mut module = Module {
            state: device.publisher("CONV", "STATE")?,
            connect: device.publisher("CONV", "CONNECT")?,
            id,
            position,
            device,
            peers: BTreeMap::new(),
            neighbours: (None, None),
            reported: false,
            reports,
        };
        module.publish(false).await?;
        module.report_neighbours().await;
        module.run(roster, commands).await
    }

    async fn run(
        &mut self,
        roster: Vec<String>,
        mut commands: mpsc::Receiver<Command>,
    ) -> Result<(), ClientError> {
        let (heard_tx, mut heard) = mpsc::channel(256);
        // Dropping the set (when this task ends or is aborted) stops the followers.
        let mut followers = JoinSet::new();
        for peer in roster.into_iter().filter(|p| *p != self.id) {
            followers.spawn(follow(self.device.clone(), peer, heard_tx.clone()));
        }
        let mut count = self.device.online_count(&self.device.line()).await?;
        let initial = *count.borrow_and_update();
        self.count_changed(initial).await;
        let mut cycle = tokio::time::interval(CYCLE);
        loop {
            tokio::select! {
                command = commands.recv() => match command {
                    Some(Command::Feed) if self.neighbours.0.is_none() => self.take_part(None).await?,
                    Some(Command::Feed) => {}
                    Some(Command::MoveTo(position)) => {
                        log(format!("{}: moved from position {} to {position}", self.id, self.position));
                        self.position = position;
                        self.publish(true).await?;
                        self.report_neighbours().await;
                    }
                    Some(Command::Stop) | None => {
                        followers.shutdown().await;
                        self.device.disconnect().await;
                        log(format!("{}: disconnected", self.id));
                        return Ok(());
                    }
                },
                Some(message) = heard.recv() => self.heard(message).await?,
                Ok(()) = count.changed() => {
                    let n = *count.borrow_and_update();
                    self.count_changed(n).await;
                }
                _ = cycle.tick() => self.publish(false).await?,
            }
        }
    }

    /// Publishes CONNECT and STATE (with SWAP as given).
    async fn publish(&mut self, swap: bool) -> Result<(), ClientError> {
        self.publish_state(false, false, swap).await
    }

    async fn publish_state(
        &mut self,
        sensor_in: bool,
        sensor_out: bool,
        swap: bool,
    ) -> Result<(), ClientError> {
        self.connect.req(vec![Value::Bool(true)]).await?;
        self.state
            .req(vec![
                Value::String(self.id.clone()),
                Value::Bool(true),
                Value::Bool(sensor_in),
                Value::Bool(sensor_out),
                Value::Int(self.position),
                Value::Bool(swap),
            ])
            .await?;
        Ok(())
    }

    async fn count_changed(&mut self, count: u64) {
        log(format!("{}: count = {count}", self.id));
        let report = Report::Count {
            id: self.id.clone(),
            count,
        };
        let _ = self.reports.send(report).await;
    }

    async fn heard(&mut self, message: Heard) -> Result<(), ClientError> {
        match message {
            Heard::Connect(peer, connected) => {
                let known = self.peers.entry(peer.clone()).or_default();
                if known.connected && !connected {
                    log(format!("{}: {peer} CONNECT = FALSE (its will)", self.id));
                }
                known.connected = connected;
            }
            Heard::State(peer, ind) => {
                // WITH order: ID, CONNECT, SENSOR_IN, SENSOR_OUT, POSITION, SWAP.
                let (Value::Bool(sensor_out), Value::Int(position), Value::Bool(swap)) =
                    (&ind.data[3], &ind.data[4], &ind.data[5])
                else {
                    return Ok(());
                };
                let known = self.peers.entry(peer.clone()).or_default();
                if *swap {
                    log(format!(
                        "{}: {peer} is now at position {position} (SWAP)",
                        self.id
                    ));
                }
                known.position = Some(*position);
                let handed_over = *sensor_out && !known.sensor_out;
                known.sensor_out = *sensor_out;
                if handed_over && self.neighbours.0.as_deref() == Some(peer.as_str()) {
                    self.take_part(Some(peer)).await?;
                }
            }
        }
        self.report_neighbours().await;
        Ok(())
    }

    /// SENSOR_IN, the belt, SENSOR_OUT: the module after this one takes the part over.
    async fn take_part(&mut self, from: Option<String>) -> Result<(), ClientError> {
        self.publish_state(true, false, false).await?;
        let report = Report::Entered {
            id: self.id.clone(),
            from,
        };
        let _ = self.reports.send(report).await;
        tokio::time::sleep(BELT).await;
        self.publish_state(false, true, false).await?;
        if self.neighbours.1.is_none() {
            let _ = self
                .reports
                .send(Report::Left {
                    id: self.id.clone(),
                })
                .await;
        }
        self.publish_state(false, false, false).await
    }

    /// The connected modules right before and after this one, by position.
    fn neighbours(&self) -> (Option<String>, Option<String>) {
        let placed = self
            .peers
            .iter()
            .filter(|(_, p)| p.connected)
            .filter_map(|(id, p)| p.position.map(|pos| (pos, id.clone())));
        let mine = (self.position, self.id.clone());
        let before = placed.clone().filter(|p| *p < mine).max().map(|p| p.1);
        let after = placed.filter(|p| *p > mine).min().map(|p| p.1);
        (before, after)
    }

    async fn report_neighbours(&mut self) {
        let neighbours = self.neighbours();
        if self.reported && neighbours == self.neighbours {
            return;
        }
        self.reported = true;
        let role = match &neighbours {
            (None, None) => "single".to_owned(),
            (None, Some(after)) => format!("first, before {after}"),
            (Some(before), Some(after)) => format!("intermediate, after {before}, before {after}"),
            (Some(before), None) => format!("last, after {before}"),
        };
        log(format!("{}: position {}, {role}", self.id, self.position));
        self.neighbours = neighbours.clone();
        let (before, after) = neighbours;
        let report = Report::Neighbours {
            id: self.id.clone(),
            before,
            after,
        };
        let _ = self.reports.send(report).await;
    }
}

/// Follows one peer's STATE and CONNECT ports, once it is in the registry.
async fn follow(device: Arc<Device>, peer: String, heard: mpsc::Sender<Heard>) {
    let mut state = subscribe(&device, &peer, "STATE").await;
    let mut connect = subscribe(&device, &peer, "CONNECT").await;
    loop {
        let message = tokio::select! {
            Some(ind) = state.ind() => Heard::State(peer.clone(), ind),
            Some(ind) = connect.ind() => Heard::Connect(peer.clone(), ind.data[0] == Value::Bool(true)),
            else => return,
        };
        if heard.send(message).await.is_err() {
            return;
        }
    }
}

/// SUBSCRIBE INIT, retried until the peer has declared its interface.
async fn subscribe(device: &Device, peer: &str, port: &str) -> fb_bridge::client::Subscriber {
    loop {
        match device.subscriber(peer, "CONV", port).await {
            Ok(subscriber) => return subscriber,
            // Not declared yet: the wait for its registry record starts over.
            Err(ClientError::UnknownDevice(_)) => {}
            Err(e) => {
                tracing::warn!(peer, port, error = %e, "SUBSCRIBE INIT failed; retrying");
                tokio::time::sleep(Duration::from_millis(500)).await;
            }
        }
    }
}

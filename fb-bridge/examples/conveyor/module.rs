//! One conveyor module: its conveyor logic, whatever runtime it talks MQTT with.
//!
//! Its FB `CONV` has the data outputs of the reference line (CONNECT, SENSOR_IN,
//! SENSOR_OUT, POSITION, SWAP) and, for the runtimes that can send one, the event output
//! `STATE` carrying all of them (and ID). Like a PLC scan, the module publishes its
//! outputs every [`CYCLE`] and on every change, so a module that joins later learns the
//! others within one cycle. It follows every other module of the roster (their STATE or
//! data outputs, and CONNECT) and works out from their `POSITION`s who comes before and
//! after it. A part arrives when the module before it reports `SENSOR_OUT`; the first
//! module takes parts from the line's entrance.
//!
//! How it connects, publishes and hears the others is its [`Link`]
//! (`runtime/`): a `fb_bridge::client` device, a FORTE-like or a DINASORE-like device.
//! This file is the same for all three.

use std::collections::BTreeMap;
use std::sync::Arc;
use std::time::Duration;

use tokio::sync::mpsc;

use crate::log;
use crate::runtime::{Heard, Link, Outputs, PeerUpdate, Roster, Runtime, Setup};

/// The PLC scan: outputs are republished this often.
const CYCLE: Duration = Duration::from_millis(250);
/// How long a part takes from SENSOR_IN to SENSOR_OUT.
const BELT: Duration = Duration::from_millis(40);

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

pub struct Module {
    id: String,
    position: i16,
    link: Link,
    peers: BTreeMap<String, Peer>,
    /// Before and after this module, as last reported.
    neighbours: (Option<String>, Option<String>),
    reported: bool,
    /// The online count, as last reported.
    count: Option<u64>,
    reports: mpsc::Sender<Report>,
}

/// Runs module `id` of `runtime` at `position` until it is stopped (or its task aborted).
pub async fn run(
    runtime: Runtime,
    id: String,
    setup: Setup,
    position: i16,
    roster: Arc<Roster>,
    commands: mpsc::Receiver<Command>,
    reports: mpsc::Sender<Report>,
) {
    let started = Module::start(
        runtime,
        &id,
        &setup,
        position,
        &roster,
        commands,
        reports.clone(),
    );
    if let Err(error) = started.await {
        let _ = reports.send(Report::Failed { id, error }).await;
    }
}

impl Module {
    async fn start(
        runtime: Runtime,
        id: &str,
        setup: &Setup,
        position: i16,
        roster: &Roster,
        commands: mpsc::Receiver<Command>,
        reports: mpsc::Sender<Report>,
    ) -> Result<(), String> {
        let (heard_tx, heard) = mpsc::channel(256);
        let link = Link::open(runtime, id, setup, roster, heard_tx).await?;
        let mut module = Module {
            id: id.to_owned(),
            position,
            link,
            peers: BTreeMap::new(),
            neighbours: (None, None),
            reported: false,
            count: None,
            reports,
        };
        module.publish(false).await?;
        if module.link.counts_itself() {
            module.count_connected().await;
        }
        module.report_neighbours().await;
        module.run(commands, heard).await
    }

    async fn run(
        &mut self,
        mut commands: mpsc::Receiver<Command>,
        mut heard: mpsc::Receiver<Heard>,
    ) -> Result<(), String> {
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
                        self.link.close().await;
                        log(format!("{}: disconnected", self.id));
                        return Ok(());
                    }
                },
                Some(message) = heard.recv() => self.heard(message).await?,
                _ = cycle.tick() => self.publish(false).await?,
            }
        }
    }

    /// Publishes CONNECT and the outputs (with SWAP as given).
    async fn publish(&mut self, swap: bool) -> Result<(), String> {
        self.publish_state(false, false, swap).await
    }

    async fn publish_state(
        &mut self,
        sensor_in: bool,
        sensor_out: bool,
        swap: bool,
    ) -> Result<(), String> {
        let outputs = Outputs {
            sensor_in,
            sensor_out,
            position: self.position,
            swap,
        };
        self.link.publish(&self.id, &outputs).await
    }

    async fn count_changed(&mut self, count: u64) {
        if self.count == Some(count) {
            return;
        }
        self.count = Some(count);
        log(format!("{}: count = {count}", self.id));
        let report = Report::Count {
            id: self.id.clone(),
            count,
        };
        let _ = self.reports.send(report).await;
    }

    /// NUM_DEV, for a runtime that cannot read the broker's count: this module and every
    /// peer whose last CONNECT was TRUE.
    async fn count_connected(&mut self) {
        let connected = self.peers.values().filter(|p| p.connected).count() as u64;
        self.count_changed(1 + connected).await;
    }

    async fn heard(&mut self, message: Heard) -> Result<(), String> {
        let (peer, update) = match message {
            Heard::Count(count) => {
                if !self.link.counts_itself() {
                    self.count_changed(count).await;
                }
                return Ok(());
            }
            Heard::Peer(peer, update) => (peer, update),
        };
        let PeerUpdate {
            connect,
            position,
            sensor_out,
            swap,
        } = update;
        let known = self.peers.entry(peer.clone()).or_default();
        if let Some(connected) = connect {
            if known.connected && !connected {
                log(format!("{}: {peer} CONNECT = FALSE (its will)", self.id));
            }
            known.connected = connected;
        }
        if let Some(position) = position {
            known.position = Some(position);
        }
        if swap == Some(true) {
            let at = known.position.map_or("?".to_owned(), |p| p.to_string());
            log(format!(
                "{}: {peer} is now at position {at} (SWAP)",
                self.id
            ));
        }
        let mut handed_over = false;
        if let Some(sensor_out) = sensor_out {
            handed_over = sensor_out && !known.sensor_out;
            known.sensor_out = sensor_out;
        }
        if handed_over && self.neighbours.0.as_deref() == Some(peer.as_str()) {
            self.take_part(Some(peer)).await?;
        }
        if connect.is_some() && self.link.counts_itself() {
            self.count_connected().await;
        }
        self.report_neighbours().await;
        Ok(())
    }

    /// SENSOR_IN, the belt, SENSOR_OUT: the module after this one takes the part over.
    async fn take_part(&mut self, from: Option<String>) -> Result<(), String> {
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

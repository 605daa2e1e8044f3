//! The plant: where the modules physically stand, the parts fed at the entrance, and a
//! technician who adds, unplugs and swaps modules. It talks to the modules only through
//! [`Command`]s (physical events) and checks what they report; everything the modules
//! know about each other comes over fbbus.

use std::collections::BTreeMap;
use std::sync::Arc;
use std::time::{Duration, Instant};

use tokio::sync::mpsc;
use tokio::task::JoinHandle;

use crate::log;
use crate::module::{self, Command, Report};
use crate::runtime::{Roster, Runtime, Setup};

/// The bound on every wait for the modules.
pub const TIMEOUT: Duration = Duration::from_secs(10);

/// A module standing on the line.
struct Placed {
    position: i16,
    runtime: Runtime,
    commands: mpsc::Sender<Command>,
    task: JoinHandle<()>,
}

type Neighbours = (Option<String>, Option<String>);

pub struct Line {
    /// Broker address, line name and timings.
    setup: Setup,
    /// Every module of this run and its runtime, known to every module (the line's
    /// engineering).
    roster: Arc<Roster>,
    modules: BTreeMap<String, Placed>,
    reports_tx: mpsc::Sender<Report>,
    reports: mpsc::Receiver<Report>,
    /// What each placed module last reported.
    counts: BTreeMap<String, u64>,
    neighbours: BTreeMap<String, Neighbours>,
    parts: usize,
}

impl Line {
    pub fn new(setup: Setup, roster: Roster) -> Line {
        let (reports_tx, reports) = mpsc::channel(256);
        Line {
            setup,
            roster: Arc::new(roster),
            modules: BTreeMap::new(),
            reports_tx,
            reports,
            counts: BTreeMap::new(),
            neighbours: BTreeMap::new(),
            parts: 0,
        }
    }

    /// The modules standing on the line, in physical order.
    pub fn order(&self) -> Vec<String> {
        let mut order: Vec<(i16, String)> = self
            .modules
            .iter()
            .map(|(id, m)| (m.position, id.clone()))
            .collect();
        order.sort();
        order.into_iter().map(|(_, id)| id).collect()
    }

    /// Places module `id` at the end of the line and powers it on.
    pub fn start(&mut self, id: &str) {
        let position = self.modules.values().map(|m| m.position).max().unwrap_or(0) + 1;
        let runtime = self.roster.get(id).copied().unwrap_or(Runtime::Contract);
        let (commands, rx) = mpsc::channel(16);
        let task = tokio::spawn(module::run(
            runtime,
            id.to_owned(),
            self.setup.clone(),
            position,
            self.roster.clone(),
            rx,
            self.reports_tx.clone(),
        ));
        self.modules.insert(
            id.to_owned(),
            Placed {
                position,
                runtime,
                commands,
                task,
            },
        );
    }

    /// The MQTT keep-alive module `id` asks the broker for (its runtime's).
    pub fn keep_alive(&self, id: &str) -> Option<Duration> {
        let module = self.modules.get(id)?;
        Some(module.runtime.keep_alive(self.setup.keep_alive))
    }

    /// Waits until every module sees the line as it stands: the online count and its
    /// neighbours.
    pub async fn settle(&mut self) -> Result<(), String> {
        let deadline = Instant::now() + TIMEOUT;
        while let Some(problem) = self.unsettled() {
            self.next_report(deadline).await.map_err(|e| {
                format!("{e} while waiting for every module to see the line: {problem}")
            })?;
        }
        Ok(())
    }

    /// What a module does not see yet, if anything.
    fn unsettled(&self) -> Option<String> {
        let order = self.order();
        let online = order.len() as u64;
        order.iter().enumerate().find_map(|(i, id)| {
            let count = self.counts.get(id);
            let expected: Neighbours = (
                i.checked_sub(1).map(|before| order[before].clone()),
                order.get(i + 1).cloned(),
            );
            let seen = self.neighbours.get(id);
            if count != Some(&online) {
                Some(format!("{id} sees count {count:?}, not {online}"))
            } else if seen != Some(&expected) {
                Some(format!("{id} sees neighbours {seen:?}, not {expected:?}"))
            } else {
                None
            }
        })
    }

    /// Feeds `n` parts, one at a time, and checks each travels the line in order.
    pub async fn run_parts(&mut self, n: usize) -> Result<(), String> {
        for _ in 0..n {
            self.parts += 1;
            let part = self.parts;
            let expected = self.order();
            let started = Instant::now();
            for module in self.modules.values() {
                let _ = module.commands.send(Command::Feed).await;
            }
            let deadline = started + TIMEOUT;
            let mut route = Vec::new();
            loop {
                let report = self
                    .next_report(deadline)
                    .await
                    .map_err(|e| format!("{e} while part {part} travelled {route:?}"))?;
                match report {
                    Report::Entered { id, from: None } => {
                        log(format!("part {part}: enters at {id}"));
                        route.push(id);
                    }
                    Report::Entered {
                        id,
                        from: Some(from),
                    } => {
                        log(format!("part {part}: {from} -> {id}"));
                        route.push(id);
                    }
                    Report::Left { id } => {
                        log(format!(
                            "part {part}: leaves the line after {id} ({} ms)",
                            started.elapsed().as_millis()
                        ));
                        break;
                    }
                    _ => {}
                }
            }
            if route != expected {
                return Err(format!("part {part} went {route:?}, expected {expected:?}"));
            }
        }
        Ok(())
    }

    /// Unplugs module `id` without warning (its connection just ends) and returns how
    /// long it took until every other module saw the online count drop.
    pub async fn unplug(&mut self, id: &str) -> Result<Duration, String> {
        let module = self
            .modules
            .remove(id)
            .ok_or(format!("{id} is not placed"))?;
        self.counts.remove(id);
        self.neighbours.remove(id);
        let started = Instant::now();
        // Dropping the module's task drops its connections: no DISCONNECT, the will (its
        // own, or its profile's at the broker) fires.
        module.task.abort();
        let online = self.modules.len() as u64;
        let deadline = started + TIMEOUT;
        while self.counts.values().any(|count| *count != online) {
            self.next_report(deadline)
                .await
                .map_err(|e| format!("{e} while waiting for the count to drop to {online}"))?;
        }
        Ok(started.elapsed())
    }

    /// Swaps two modules' positions (the technician moves them); they learn it as a
    /// physical event and tell the others in their STATE (SWAP = TRUE).
    pub async fn swap(&mut self, a: &str, b: &str) -> Result<(), String> {
        let position = |line: &Line, id: &str| {
            line.modules
                .get(id)
                .map(|m| m.position)
                .ok_or(format!("{id} is not placed"))
        };
        let (pa, pb) = (position(self, a)?, position(self, b)?);
        for (id, to) in [(a, pb), (b, pa)] {
            let module = self.modules.get_mut(id).expect("checked above");
            module.position = to;
            let _ = module.commands.send(Command::MoveTo(to)).await;
        }
        Ok(())
    }

    /// INIT- for every module, then waits for them to end.
    pub async fn stop(&mut self) -> Result<(), String> {
        for module in self.modules.values() {
            let _ = module.commands.send(Command::Stop).await;
        }
        for (id, module) in std::mem::take(&mut self.modules) {
            tokio::time::timeout(TIMEOUT, module.task)
                .await
                .map_err(|_| format!("{id} did not stop within {TIMEOUT:?}"))?
                .map_err(|e| format!("{id}: {e}"))?;
        }
        // A module that failed while stopping reported it.
        while let Ok(report) = self.reports.try_recv() {
            if let Report::Failed { id, error } = report {
                return Err(format!("{id} failed: {error}"));
            }
        }
        Ok(())
    }

    /// The next report from a placed module, keeping track of counts and neighbours.
    async fn next_report(&mut self, deadline: Instant) -> Result<Report, String> {
        loop {
            let report = tokio::time::timeout_at(deadline.into(), self.reports.recv())
                .await
                .map_err(|_| format!("timed out after {TIMEOUT:?}"))?
                .ok_or("every module has ended")?;
            match &report {
                Report::Failed { id, error } => return Err(format!("{id} failed: {error}")),
                // Late reports from an unplugged module.
                Report::Count { id, .. }
                | Report::Neighbours { id, .. }
                | Report::Entered { id, .. }
                | Report::Left { id }
                    if !self.modules.contains_key(id) => {}
                Report::Count { id, count } => {
                    self.counts.insert(id.clone(), *count);
                    return Ok(report);
                }
                Report::Neighbours { id, before, after } => {
                    self.neighbours
                        .insert(id.clone(), (before.clone(), after.clone()));
                    return Ok(report);
                }
                _ => return Ok(report),
            }
        }
    }
}

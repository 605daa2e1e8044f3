//! One run, start to end: identify the brokers, measure the harness's ceiling, connect
//! the rigs, run the scenario, and assemble the [`Report`].

use std::time::{Duration, SystemTime};

use crate::model::{Ceiling, Report, Target as TargetInfo};
use crate::rig::{Follow, Pace, Rig, RigConfig, Shape};
use crate::scenario::Scenario;
use crate::session::Session;
use crate::sink::Sink;
use crate::target::Target;
use crate::{broker_process, client, machine, tally, Error};

/// Everything a run needs, as the command line gave it.
#[derive(Debug, Clone)]
pub struct Plan {
    /// `A`, and `B` in compare mode.
    pub targets: Vec<Target>,
    /// Names for tables and legends; `None`: detected (`fbbus`, `mosquitto`, address).
    pub names: Vec<Option<String>>,
    /// Subscribers connect here instead (line B, for `bridge`).
    pub subscribe_at: Option<Target>,
    pub scenario: Scenario,
    pub rig: RigConfig,
    /// Count at an FB subscriber too (study tests, fbbus only).
    pub fb: bool,
    /// Messages for the ceiling measurement; `None` skips it.
    pub ceiling_messages: Option<u64>,
    pub time_limit: Duration,
    /// The command line, recorded in the report (it never holds a password).
    pub command: String,
}

const LABELS: [&str; 2] = ["A", "B"];

pub async fn run(plan: &Plan) -> Result<Report, Error> {
    let started = humantime::format_rfc3339_seconds(SystemTime::now()).to_string();
    let labels: Vec<String> = LABELS[..plan.targets.len()]
        .iter()
        .map(|l| l.to_string())
        .collect();

    // Every broker must at least accept a TCP connection: otherwise a connection scenario
    // would "measure" nothing but refused connects.
    for target in plan.targets.iter().chain(&plan.subscribe_at) {
        reachable(target, plan.rig.timeout).await?;
    }

    let ceiling = match plan.ceiling_messages {
        Some(n) => Some(ceiling(n, plan).await?),
        None => None,
    };

    let mut session = match &plan.scenario {
        Scenario::Idle(_)
        | Scenario::Storm(_)
        | Scenario::Conveyor(_)
        | Scenario::Mutate(_)
        | Scenario::Churn(_) => {
            Session::new(labels.clone(), Vec::new(), plan.time_limit, planned(plan))
        }
        scenario => {
            let shape = match scenario {
                Scenario::Flow(flow) => flow.shape(),
                _ => Shape {
                    publishers: 1,
                    subscribers: 1,
                    follow: Follow::All,
                    fb: plan.fb,
                },
            };
            let mut rigs = Vec::new();
            for (label, target) in labels.iter().zip(&plan.targets) {
                let mut config = plan.rig.clone();
                config.prefix = format!("{}-{}", plan.rig.prefix, label.to_lowercase());
                rigs.push(
                    Rig::connect(label, target, plan.subscribe_at.as_ref(), &shape, &config)
                        .await?,
                );
            }
            Session::new(labels.clone(), rigs, plan.time_limit, planned(plan))
        }
    };
    let speaks_fbbus: Vec<bool> = session.rigs.iter().map(|r| r.speaks_fbbus).collect();

    let (timeout, prefix) = (plan.rig.timeout, plan.rig.prefix.as_str());
    let mut failures = Vec::new();
    match &plan.scenario {
        Scenario::Stress(s) => s.run(&mut session).await,
        Scenario::LossSearch(s) => s.run(&mut session).await,
        Scenario::Perf(s) => s.run(&mut session).await,
        Scenario::Flow(s) => s.run(&mut session).await,
        Scenario::Idle(s) => s.run(&mut session, &plan.targets, prefix, timeout).await,
        Scenario::Storm(s) => s.run(&mut session, &plan.targets, prefix, timeout).await,
        Scenario::Conveyor(s) => {
            let quiet = plan.rig.quiet;
            s.run(&mut session, &plan.targets, prefix, timeout, quiet)
                .await
        }
        Scenario::Mutate(s) => failures = s.run(&mut session, &plan.targets, prefix).await,
        Scenario::Churn(s) => failures = s.run(&mut session, &plan.targets, prefix).await,
    }
    let (batches, summaries, ratios, notes) = session.finish().await;

    let mut targets = Vec::new();
    for (i, target) in plan.targets.iter().enumerate() {
        let (name, version) = identify(target, speaks_fbbus.get(i).copied(), plan).await;
        targets.push(TargetInfo {
            label: labels[i].clone(),
            address: target.address.clone(),
            version,
            name: plan.names.get(i).cloned().flatten().unwrap_or(name),
        });
    }

    Ok(Report {
        tool: format!("fbbus-loadtest {}", env!("CARGO_PKG_VERSION")),
        command: plan.command.clone(),
        started,
        machine: machine::this_machine(),
        scenario: plan.scenario.name(),
        params: params(plan),
        targets,
        ceiling,
        batches,
        summaries,
        ratios,
        notes,
        failures,
    })
}

async fn reachable(target: &Target, timeout: Duration) -> Result<(), Error> {
    let connect = tokio::net::TcpStream::connect((target.host.as_str(), target.port));
    match tokio::time::timeout(timeout, connect).await {
        Ok(Ok(_)) => Ok(()),
        Ok(Err(e)) => Err(Error::Connect {
            id: "the harness".into(),
            address: target.address.clone(),
            reason: e.to_string(),
        }),
        Err(_) => Err(Error::Connect {
            id: "the harness".into(),
            address: target.address.clone(),
            reason: format!("no TCP connection within {timeout:?}"),
        }),
    }
}

fn planned(plan: &Plan) -> Option<u64> {
    let n = plan.targets.len();
    match &plan.scenario {
        Scenario::Stress(s) => Some(s.planned(n)),
        Scenario::LossSearch(_) => None,
        Scenario::Perf(s) => Some(s.planned(n)),
        Scenario::Flow(s) => Some(s.planned(n)),
        Scenario::Idle(s) => Some(s.planned(n)),
        Scenario::Storm(s) => Some(s.planned(n)),
        Scenario::Conveyor(s) => Some(s.planned(n)),
        Scenario::Mutate(s) => Some(s.planned(n)),
        Scenario::Churn(s) => Some(s.planned(n)),
    }
}

/// The parameters as used, for the report.
fn params(plan: &Plan) -> serde_json::Value {
    let mut p = serde_json::to_value(&plan.scenario).unwrap_or_default();
    let extra = serde_json::json!({
        "qos": plan.rig.qos,
        "payload_bytes": plan.rig.payload.max(crate::message::MIN_SIZE),
        "payload_requested": plan.rig.payload,
        "mqtt": plan.targets.first().map(|t| t.mqtt),
        "inflight": plan.rig.inflight,
        "quiet_ms": plan.rig.quiet.as_millis() as u64,
        "batch_limit_s": plan.rig.batch_limit.as_secs(),
        "time_limit_s": plan.time_limit.as_secs(),
        "fb_subscriber": plan.fb,
        "subscribe_at": plan.subscribe_at.as_ref().map(|t| t.address.clone()),
    });
    if let (Some(p), Some(extra)) = (p.as_object_mut(), extra.as_object()) {
        p.extend(extra.clone());
    }
    p
}

/// The harness against the sink, three times, best kept: the scenario's clients and first
/// pace (a flow's shape and rate), else one publisher and one subscriber with a burst of
/// `n`; always QoS 0 (the sink acknowledges but does not store).
async fn ceiling(n: u64, plan: &Plan) -> Result<Ceiling, Error> {
    let sink = Sink::start().await.map_err(Error::Io)?;
    let mut target = Target::parse(&sink.addr.to_string())?;
    target.mqtt = plan.targets.first().map_or(target.mqtt, |t| t.mqtt);
    let (shape, per_publisher, pace) = match &plan.scenario {
        Scenario::Flow(flow) => {
            let pace = flow.rates.first().map_or(Pace::Burst, |&r| Pace::Rate(r));
            (flow.shape(), flow.messages, pace)
        }
        _ => (
            Shape {
                publishers: 1,
                subscribers: 1,
                follow: Follow::All,
                fb: false,
            },
            n,
            Pace::Burst,
        ),
    };
    let label = match pace {
        Pace::Burst => format!("burst {per_publisher}"),
        Pace::Rate(r) => format!("rate {r}/s"),
    };
    let mut config = plan.rig.clone();
    config.qos = 0;
    config.prefix = format!("{}-ceiling", plan.rig.prefix);
    let mut rig = Rig::connect("ceiling", &target, None, &shape, &config).await?;
    let mut best: Option<Ceiling> = None;
    for repeat in 1..=3 {
        let (batch, _) = rig
            .batch(
                per_publisher,
                pace,
                label.clone(),
                per_publisher as f64,
                repeat,
            )
            .await;
        // Best: the highest throughput for bursts, the lowest p99 for rates.
        let better = best.as_ref().is_none_or(|b| match pace {
            Pace::Burst => batch.throughput > b.throughput,
            Pace::Rate(_) => batch.latency.p99_us < b.latency.p99_us,
        });
        if better {
            best = Some(Ceiling {
                label: label.clone(),
                messages: batch.delivered,
                throughput: batch.throughput,
                latency: batch.latency,
            });
        }
    }
    rig.close().await;
    Ok(best.unwrap_or(Ceiling {
        label,
        messages: 0,
        throughput: 0.0,
        latency: tally::summarize(&tally::histogram()),
    }))
}

/// A short name and the version string of a broker, as far as it can be found out:
/// `$SYS/broker/version` (Mosquitto and others), else the process listening on the port
/// when it runs on this machine (`fbbus --version`).
async fn identify(
    target: &Target,
    speaks_fbbus: Option<bool>,
    plan: &Plan,
) -> (String, Option<String>) {
    let mut version = sys_version(target, plan).await;
    let process = target
        .is_loopback()
        .then(|| broker_process::pid_listening_on(target.port))
        .flatten();
    let process_name = process.and_then(broker_process::name);
    if version.is_none() && process_name.as_deref() == Some("fbbus") {
        version = process.and_then(|pid| {
            let out = std::process::Command::new(format!("/proc/{pid}/exe"))
                .arg("--version")
                .output()
                .ok()?;
            let text = String::from_utf8_lossy(&out.stdout).trim().to_owned();
            (!text.is_empty()).then_some(text)
        });
    }
    let name = if speaks_fbbus == Some(true) {
        "fbbus".to_owned()
    } else if let Some(v) = version.as_deref().and_then(|v| v.split_whitespace().next()) {
        v.to_lowercase()
    } else if let Some(p) = process_name {
        p
    } else {
        format!("{}:{}", target.host, target.port)
    };
    (name, version)
}

async fn sys_version(target: &Target, plan: &Plan) -> Option<String> {
    let (tx, mut rx) = tokio::sync::mpsc::unbounded_channel();
    let on_publish: client::OnPublish = std::sync::Arc::new(move |_t: &[u8], payload: &[u8]| {
        let _ = tx.send(String::from_utf8_lossy(payload).into_owned());
    });
    // A storm's `dev-{i}` user: probe as device 0.
    let mut target = target.clone();
    target.username = target.username.map(|u| u.replace("{i}", "0"));
    let target = &target;
    let mut config = client::ClientConfig::new(format!("{}-probe", plan.rig.prefix));
    config.timeout = Duration::from_secs(2);
    let mut c = client::Client::connect(target, &config, Some(on_publish))
        .await
        .ok()?;
    let granted = c
        .subscribe(&["$SYS/broker/version".to_owned()], client::qos(0))
        .await
        .is_ok();
    let version = if granted {
        tokio::time::timeout(Duration::from_millis(500), rx.recv())
            .await
            .ok()
            .flatten()
    } else {
        None
    };
    c.disconnect().await;
    version
}

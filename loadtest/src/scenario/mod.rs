//! The scenarios: the study's three tests ([`study`]), many-client flows ([`flow`]),
//! connection scenarios ([`connections`]), the simulated conveyor line ([`conveyor`]) and
//! the network campaigns ([`mutate`], [`churn`], sharing [`campaign`]).

pub mod campaign;
pub mod churn;
pub mod connections;
pub mod conveyor;
pub mod flow;
pub mod mutate;
pub mod study;

use serde::Serialize;

/// What to run.
#[derive(Debug, Clone, Serialize)]
#[serde(tag = "scenario", rename_all = "kebab-case")]
pub enum Scenario {
    Stress(study::Stress),
    LossSearch(study::LossSearch),
    Perf(study::Perf),
    Flow(flow::Flow),
    Idle(connections::Idle),
    Storm(connections::Storm),
    Conveyor(conveyor::Conveyor),
    Mutate(mutate::Mutate),
    Churn(churn::Churn),
}

impl Scenario {
    /// The name used in reports and file names.
    pub fn name(&self) -> String {
        match self {
            Scenario::Stress(_) => "stress".into(),
            Scenario::LossSearch(_) => "loss-search".into(),
            Scenario::Perf(_) => "perf".into(),
            Scenario::Flow(f) => serde_json::to_value(f.kind)
                .ok()
                .and_then(|v| v.as_str().map(str::to_owned))
                .unwrap_or_else(|| "flow".into()),
            Scenario::Idle(_) => "idle".into(),
            Scenario::Storm(_) => "storm".into(),
            Scenario::Conveyor(_) => "conveyor".into(),
            Scenario::Mutate(_) => "mutate".into(),
            Scenario::Churn(_) => "churn".into(),
        }
    }
}

//! Beyond the study: many-client flows. `fan-in` (P publishers -> 1 subscriber),
//! `fan-out` (1 publisher -> S subscribers), `pairs` (N publisher/subscriber pairs) and
//! `bridge` (publishers on line A, subscribers on line B, across fbbus's zenoh bridge),
//! closed-loop bursts or open-loop rates.

use serde::Serialize;

use crate::rig::{Follow, Pace, Shape};
use crate::session::Session;

/// Which flow.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize)]
#[serde(rename_all = "kebab-case")]
pub enum FlowKind {
    FanIn,
    FanOut,
    Pairs,
    Bridge,
}

#[derive(Debug, Clone, Serialize)]
pub struct Flow {
    pub kind: FlowKind,
    /// Publishers (fan-in), subscribers (fan-out) or pairs; 1 publisher and 1
    /// subscriber for `bridge`.
    pub clients: usize,
    /// Messages per publisher per batch.
    pub messages: u64,
    /// Open-loop rates to run, messages per second over all publishers; empty = one
    /// closed-loop burst per repeat.
    pub rates: Vec<f64>,
    pub repeats: u32,
}

impl Flow {
    pub fn shape(&self) -> Shape {
        let n = self.clients.max(1);
        let (publishers, subscribers, follow) = match self.kind {
            FlowKind::FanIn => (n, 1, Follow::All),
            FlowKind::FanOut => (1, n, Follow::All),
            FlowKind::Pairs => (n, n, Follow::Pairs),
            FlowKind::Bridge => (1, 1, Follow::All),
        };
        Shape {
            publishers,
            subscribers,
            follow,
            fb: false,
        }
    }

    pub fn planned(&self, targets: usize) -> u64 {
        (self.rates.len().max(1) * self.repeats as usize * targets) as u64
    }

    pub async fn run(&self, s: &mut Session) {
        let paces: Vec<(Pace, String, f64)> = if self.rates.is_empty() {
            vec![(
                Pace::Burst,
                format!("burst {}", self.messages),
                self.messages as f64,
            )]
        } else {
            self.rates
                .iter()
                .map(|&r| (Pace::Rate(r), format!("rate {r}/s"), r))
                .collect()
        };
        for (pace, label, x) in paces {
            for repeat in 1..=self.repeats {
                for rig in 0..s.rigs.len() {
                    if s.out_of_time() {
                        return;
                    }
                    s.run(rig, self.messages, pace, label.clone(), x, repeat)
                        .await;
                }
            }
        }
    }
}

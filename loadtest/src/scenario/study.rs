//! The JMeter study's three tests (stress, loss search, performance: Mosquitto on a
//! Raspberry Pi 3 with a DINASORE FB subscriber; its figures are quoted in
//! loadtest/RESULTS.md), with its defaults.
//!
//! All three send closed-loop bursts from one publisher to one subscriber (plus the FB
//! subscriber on fbbus), repeat each burst, and in compare mode run A and B batch by
//! batch (A B A B) so both brokers see the same machine state.

use serde::Serialize;

use crate::rig::Pace;
use crate::session::Session;

/// `stress`: bursts doubling from `start` to `max`, each `repeats` times.
#[derive(Debug, Clone, Serialize)]
pub struct Stress {
    pub start: u64,
    pub max: u64,
    pub repeats: u32,
}

impl Stress {
    /// The burst sizes: start, 2 start, 4 start ... up to max.
    pub fn bursts(&self) -> Vec<u64> {
        let mut out = Vec::new();
        let mut x = self.start.max(1);
        while x <= self.max {
            out.push(x);
            x *= 2;
        }
        out
    }

    pub fn planned(&self, targets: usize) -> u64 {
        (self.bursts().len() * self.repeats as usize * targets) as u64
    }

    pub async fn run(&self, s: &mut Session) {
        for x in self.bursts() {
            for repeat in 1..=self.repeats {
                for rig in 0..s.rigs.len() {
                    if s.out_of_time() {
                        return;
                    }
                    s.run(rig, x, Pace::Burst, format!("burst {x}"), x as f64, repeat)
                        .await;
                }
            }
        }
        // The study's saturation point: the best delivery rate measured.
        for rig in 0..s.rigs.len() {
            let label = s.labels[rig].clone();
            let best = s
                .batches_of(&label)
                .map(|b| b.throughput)
                .fold(0.0, f64::max);
            s.figure(rig, "max_throughput", best, "msg/s");
        }
    }
}

/// `loss-search`: the largest burst delivered without loss in every repeat. Doubles from
/// `start` until a burst loses (or `max`), then halves the interval between the largest
/// lossless and the smallest lossy burst until it is at most `resolution` wide.
#[derive(Debug, Clone, Serialize)]
pub struct LossSearch {
    pub start: u64,
    pub max: u64,
    pub repeats: u32,
    pub resolution: u64,
}

/// Where one target's search stands.
#[derive(Debug, Clone, Default)]
struct Search {
    /// Largest burst lossless in every repeat so far.
    lossless: u64,
    /// Smallest burst that lost something.
    lossy: Option<u64>,
    done: bool,
}

impl LossSearch {
    /// The next burst to try, or `None` when converged.
    fn next(&self, s: &Search) -> Option<u64> {
        match s.lossy {
            None if s.lossless == 0 => Some(self.start.max(1)),
            None if s.lossless >= self.max => None,
            None => Some((s.lossless * 2).min(self.max)),
            Some(h) if h - s.lossless <= self.resolution.max(1) => None,
            Some(h) => Some(s.lossless + (h - s.lossless) / 2),
        }
    }

    pub async fn run(&self, s: &mut Session) {
        let mut searches = vec![Search::default(); s.rigs.len()];
        // At most ~2 log2(max) probes per target: bounded by construction, and by the
        // run's time limit.
        while searches.iter().any(|x| !x.done) {
            for (rig, search) in searches.iter_mut().enumerate() {
                if search.done {
                    continue;
                }
                let Some(x) = self.next(search) else {
                    search.done = true;
                    continue;
                };
                let mut lossless = true;
                for repeat in 1..=self.repeats {
                    if s.out_of_time() {
                        return self.figures(s, &searches);
                    }
                    let b = s
                        .run(rig, x, Pace::Burst, format!("burst {x}"), x as f64, repeat)
                        .await;
                    if !b.ok {
                        lossless = false;
                        break;
                    }
                }
                if lossless {
                    search.lossless = x;
                } else {
                    search.lossy = Some(x);
                    if x <= self.start.max(1) && search.lossless == 0 {
                        // Loses at the smallest burst: nothing smaller to search.
                        search.done = true;
                    }
                }
            }
        }
        self.figures(s, &searches)
    }

    fn figures(&self, s: &mut Session, searches: &[Search]) {
        for (rig, search) in searches.iter().enumerate() {
            s.figure(
                rig,
                "largest_lossless_burst",
                search.lossless as f64,
                "messages",
            );
            if search.lossy.is_none() {
                let label = s.labels[rig].clone();
                s.notes.push(format!(
                    "{label}: no loss up to --max {} messages: the largest lossless burst is at least that",
                    self.max
                ));
            }
        }
    }
}

/// `perf`: bursts of 1 ... `max` messages (`points` sizes evenly spaced, always including
/// 1 and `max`), each `repeats` times: processing time, average latency, messages/s.
#[derive(Debug, Clone, Serialize)]
pub struct Perf {
    pub max: u64,
    pub points: u64,
    pub repeats: u32,
}

impl Perf {
    pub fn sizes(&self) -> Vec<u64> {
        let max = self.max.max(1);
        let points = self.points.clamp(1, max);
        if points == 1 {
            return vec![max];
        }
        let mut out: Vec<u64> = (0..points)
            .map(|i| 1 + (max - 1) * i / (points - 1))
            .collect();
        out.dedup();
        out
    }

    pub fn planned(&self, targets: usize) -> u64 {
        (self.sizes().len() * self.repeats as usize * targets) as u64
    }

    pub async fn run(&self, s: &mut Session) {
        let sizes = self.sizes();
        for &x in &sizes {
            for repeat in 1..=self.repeats {
                for rig in 0..s.rigs.len() {
                    if s.out_of_time() {
                        return;
                    }
                    s.run(rig, x, Pace::Burst, format!("batch {x}"), x as f64, repeat)
                        .await;
                }
            }
        }
        // The study's headline figures: average latency per message and messages per
        // second at the largest batch.
        let largest = *sizes.last().expect("at least one size") as f64;
        for rig in 0..s.rigs.len() {
            let label = s.labels[rig].clone();
            let at_max: Vec<_> = s
                .batches_of(&label)
                .filter(|b| b.x == largest)
                .map(|b| (b.latency.mean_us, b.throughput))
                .collect();
            if at_max.is_empty() {
                continue;
            }
            let n = at_max.len() as f64;
            let latency = at_max.iter().map(|v| v.0).sum::<f64>() / n;
            let rate = at_max.iter().map(|v| v.1).sum::<f64>() / n;
            s.figure(rig, "mean_latency_at_max_batch", latency, "us");
            s.figure(rig, "throughput_at_max_batch", rate, "msg/s");
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn stress_doubles_like_the_study() {
        let s = Stress {
            start: 10,
            max: 5120,
            repeats: 5,
        };
        assert_eq!(
            s.bursts(),
            vec![10, 20, 40, 80, 160, 320, 640, 1280, 2560, 5120]
        );
        assert_eq!(s.planned(2), 100);
    }

    #[test]
    fn perf_sizes_span_one_to_max() {
        let p = Perf {
            max: 1045,
            points: 20,
            repeats: 10,
        };
        let sizes = p.sizes();
        assert_eq!(
            (sizes[0], *sizes.last().unwrap(), sizes.len()),
            (1, 1045, 20)
        );
        assert_eq!(
            Perf {
                max: 3,
                points: 20,
                repeats: 1
            }
            .sizes(),
            vec![1, 2, 3]
        );
    }

    /// The search converges on the true limit of a simulated broker, in few probes.
    #[test]
    fn loss_search_converges_to_the_limit() {
        let search = LossSearch {
            start: 10,
            max: 81920,
            repeats: 5,
            resolution: 5,
        };
        for limit in [1045, 10, 7, 81920, 100_000, 33_333] {
            let mut s = Search::default();
            let mut probes = 0;
            while let Some(x) = search.next(&s) {
                probes += 1;
                assert!(probes < 40, "no convergence for {limit}");
                if x <= limit {
                    s.lossless = x;
                } else {
                    s.lossy = Some(x);
                    if x <= 10 && s.lossless == 0 {
                        break;
                    }
                }
            }
            let expected_floor = limit.min(81920);
            if limit >= 10 {
                assert!(
                    s.lossless <= expected_floor && expected_floor - s.lossless <= 5,
                    "{limit}: {s:?}"
                );
            } else {
                assert_eq!(s.lossless, 0);
            }
        }
    }
}

//! A session: the rigs of one run (one per target: `A`, and `B` in compare mode), the
//! batches they produced in order, the progress bar and the run's time limit. Scenarios
//! drive it; [`Session::finish`] turns it into the report's batches, summaries and
//! ratios.

use std::time::{Duration, Instant};

use hdrhistogram::Histogram;
use indicatif::{ProgressBar, ProgressStyle};

use crate::model::{Batch, Figure, Ratio, Summary};
use crate::rig::{Pace, Rig};
use crate::tally;

pub struct Session {
    /// The targets' labels, in order (`A`, `B`).
    pub labels: Vec<String>,
    /// One rig per target for message scenarios; empty for connection scenarios.
    pub rigs: Vec<Rig>,
    batches: Vec<Batch>,
    /// Per rig: every batch's latencies merged.
    histograms: Vec<Histogram<u64>>,
    /// Per rig: scenario-specific figures.
    figures: Vec<Vec<Figure>>,
    pub notes: Vec<String>,
    progress: ProgressBar,
    deadline: Instant,
    out_of_time_noted: bool,
}

impl Session {
    /// `planned`: how many batches the scenario will run, if known (for the progress
    /// bar); `limit`: the whole run's time limit.
    pub fn new(
        labels: Vec<String>,
        rigs: Vec<Rig>,
        limit: Duration,
        planned: Option<u64>,
    ) -> Session {
        let progress = match planned {
            Some(n) => ProgressBar::new(n).with_style(
                ProgressStyle::with_template(
                    "{elapsed_precise} [{bar:30}] {pos}/{len} batches  {msg}",
                )
                .expect("valid template")
                .progress_chars("=> "),
            ),
            None => ProgressBar::new_spinner().with_style(
                ProgressStyle::with_template("{elapsed_precise} {spinner} {pos} batches  {msg}")
                    .expect("valid template"),
            ),
        };
        let notes = rigs.iter().filter_map(|r| r.fb_note.clone()).collect();
        Session {
            histograms: labels.iter().map(|_| tally::histogram()).collect(),
            figures: labels.iter().map(|_| Vec::new()).collect(),
            labels,
            rigs,
            batches: Vec::new(),
            notes,
            progress,
            deadline: Instant::now() + limit,
            out_of_time_noted: false,
        }
    }

    /// Runs one batch on rig `rig` and records it.
    pub async fn run(
        &mut self,
        rig: usize,
        per_publisher: u64,
        pace: Pace,
        label: String,
        x: f64,
        repeat: u32,
    ) -> Batch {
        let target = self.labels[rig].clone();
        self.progress
            .set_message(format!("{target}: {label} #{repeat}"));
        let (batch, histogram) = self.rigs[rig]
            .batch(per_publisher, pace, label, x, repeat)
            .await;
        self.histograms[rig]
            .add(&histogram)
            .expect("same histogram bounds");
        self.progress.inc(1);
        if !batch.ok {
            self.progress.println(format!(
                "{target} {} #{}: {}",
                batch.label,
                batch.repeat,
                batch.error.as_deref().unwrap_or("failed")
            ));
        }
        self.batches.push(batch.clone());
        batch
    }

    /// Records a batch measured outside a rig (connection scenarios).
    pub fn record(&mut self, rig: usize, batch: Batch, histogram: &Histogram<u64>) {
        self.histograms[rig]
            .add(histogram)
            .expect("same histogram bounds");
        self.progress.inc(1);
        self.batches.push(batch);
    }

    /// A scenario-specific figure of target `rig` (`largest_lossless`, ...). Recorded
    /// once per repeat; the summary holds the mean.
    pub fn figure(&mut self, rig: usize, name: &str, value: f64, unit: &str) {
        self.figures[rig].push(Figure {
            name: name.to_owned(),
            value,
            unit: unit.to_owned(),
        });
    }

    /// Whether the run's time limit has passed (noted once in the report).
    pub fn out_of_time(&mut self) -> bool {
        let out = Instant::now() >= self.deadline;
        if out && !self.out_of_time_noted {
            self.out_of_time_noted = true;
            self.notes.push(
                "the run hit its time limit (--time-limit) and stopped early: later batches were not run"
                    .into(),
            );
        }
        out
    }

    /// The batches of target `label` so far.
    pub fn batches_of<'a>(&'a self, label: &'a str) -> impl Iterator<Item = &'a Batch> + 'a {
        self.batches.iter().filter(move |b| b.target == label)
    }

    pub fn println(&self, line: String) {
        self.progress.println(line);
    }

    /// Closes every rig and returns (batches, summaries, ratios B/A, notes).
    pub async fn finish(self) -> (Vec<Batch>, Vec<Summary>, Vec<Ratio>, Vec<String>) {
        self.progress.finish_and_clear();
        let mut summaries = Vec::new();
        for ((label, histogram), figures) in
            self.labels.iter().zip(&self.histograms).zip(self.figures)
        {
            summaries.push(summarize(
                label,
                &self.batches,
                histogram,
                mean_by_name(figures),
            ));
        }
        for rig in self.rigs {
            rig.close().await;
        }
        let ratios = match summaries.as_slice() {
            [a, b] if a.batches > 0 && b.batches > 0 => ratios(a, b),
            _ => Vec::new(),
        };
        (self.batches, summaries, ratios, self.notes)
    }
}

/// One figure per name: the mean of its values (one per repeat).
fn mean_by_name(figures: Vec<Figure>) -> Vec<Figure> {
    let mut out: Vec<(Figure, u32)> = Vec::new();
    for f in figures {
        match out.iter_mut().find(|(o, _)| o.name == f.name) {
            Some((o, n)) => {
                o.value += f.value;
                *n += 1;
            }
            None => out.push((f, 1)),
        }
    }
    out.into_iter()
        .map(|(mut f, n)| {
            f.value /= f64::from(n);
            f
        })
        .collect()
}

/// One target's figures over its batches.
pub fn summarize(
    target: &str,
    batches: &[Batch],
    histogram: &Histogram<u64>,
    figures: Vec<Figure>,
) -> Summary {
    let own: Vec<&Batch> = batches.iter().filter(|b| b.target == target).collect();
    let mut throughputs: Vec<f64> = own.iter().map(|b| b.throughput).collect();
    throughputs.sort_by(f64::total_cmp);
    let fb: Vec<u64> = own.iter().filter_map(|b| b.delivered_fb).collect();
    Summary {
        target: target.to_owned(),
        batches: own.len() as u64,
        sent: own.iter().map(|b| b.sent).sum(),
        expected: own.iter().map(|b| b.expected).sum(),
        delivered: own.iter().map(|b| b.delivered).sum(),
        delivered_fb: (!fb.is_empty()).then(|| fb.iter().sum()),
        duplicates: own.iter().map(|b| b.duplicates).sum(),
        throughput: throughputs
            .get(throughputs.len() / 2)
            .copied()
            .unwrap_or(0.0),
        latency: tally::summarize(histogram),
        figures,
    }
}

/// B / A for every figure both summaries have.
pub fn ratios(a: &Summary, b: &Summary) -> Vec<Ratio> {
    let ratio = |figure: &str, a: f64, b: f64| Ratio {
        figure: figure.to_owned(),
        a,
        b,
        ratio: if a == 0.0 { 0.0 } else { b / a },
    };
    let delivery = |s: &Summary| {
        if s.expected == 0 {
            1.0
        } else {
            s.delivered as f64 / s.expected as f64
        }
    };
    let mut out = vec![
        ratio(
            "throughput msg/s (median batch)",
            a.throughput,
            b.throughput,
        ),
        ratio("delivered fraction", delivery(a), delivery(b)),
        ratio(
            "latency p50 us",
            a.latency.p50_us as f64,
            b.latency.p50_us as f64,
        ),
        ratio(
            "latency p99 us",
            a.latency.p99_us as f64,
            b.latency.p99_us as f64,
        ),
        ratio(
            "latency max us",
            a.latency.max_us as f64,
            b.latency.max_us as f64,
        ),
    ];
    for fa in &a.figures {
        if let Some(fb) = b.figures.iter().find(|f| f.name == fa.name) {
            out.push(ratio(
                &format!("{} {}", fa.name, fa.unit),
                fa.value,
                fb.value,
            ));
        }
    }
    out
}

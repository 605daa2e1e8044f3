//! What the table and the charts share: a target's batches grouped by x (the repeats of
//! one burst size, rate, ...) into one point, and the name each target is shown under.
//! One place, so a chart's point and the table's row for the same x are the same numbers.

use crate::model::{Batch, Report, Target};

/// One target's batches at one x, aggregated over the repeats.
///
/// Counts, throughput and times are means over the repeats (what one repeat looks like);
/// the delivery rate is pooled (all delivered / all expected, so a failed small repeat
/// does not weigh like a large one); p50/p99 are the mean of the repeats' percentiles
/// (the batches keep no histograms to merge) and max is the max.
#[derive(Debug, Clone)]
pub(crate) struct Point {
    pub x: f64,
    /// The first repeat's label (`burst 1280`): repeats of one x share it.
    pub label: String,
    pub repeats: usize,
    /// Repeats that were not ok.
    pub failed: usize,
    pub sent: f64,
    pub delivered: f64,
    /// Mean delivered at the FB subscriber, and that as % of sent (pooled); `None` when
    /// no repeat had an FB subscriber.
    pub delivered_fb: Option<f64>,
    pub fb_pct: Option<f64>,
    pub lost: f64,
    /// Pooled delivered / expected, in percent.
    pub delivery_pct: f64,
    pub throughput: f64,
    pub processing_us: f64,
    pub lat_mean_us: f64,
    pub lat_p50_us: f64,
    pub lat_p99_us: f64,
    pub lat_max_us: u64,
}

/// The batches of target `label`, one [`Point`] per distinct x (and label), ascending x.
pub(crate) fn points(report: &Report, label: &str) -> Vec<Point> {
    let mut batches: Vec<&Batch> = report
        .batches
        .iter()
        .filter(|b| b.target == label)
        .collect();
    // Stable: repeats of one x stay in run order. Batches of one x with different labels
    // (a storm's connect and reconnect waves) are different points.
    batches.sort_by(|a, b| a.x.total_cmp(&b.x).then_with(|| a.label.cmp(&b.label)));
    batches
        .chunk_by(|a, b| a.x == b.x && a.label == b.label)
        .map(point)
        .collect()
}

fn point(repeats: &[&Batch]) -> Point {
    let n = repeats.len() as f64;
    let mean = |f: &dyn Fn(&Batch) -> f64| repeats.iter().map(|b| f(b)).sum::<f64>() / n;
    let expected: u64 = repeats.iter().map(|b| b.expected).sum();
    let delivered: u64 = repeats.iter().map(|b| b.delivered).sum();
    // The FB subscriber counts one copy per message sent.
    let fb = repeats.iter().all(|b| b.delivered_fb.is_some()).then(|| {
        let d: u64 = repeats.iter().filter_map(|b| b.delivered_fb).sum();
        (d, repeats.iter().map(|b| b.sent).sum::<u64>())
    });
    Point {
        x: repeats[0].x,
        label: repeats[0].label.clone(),
        repeats: repeats.len(),
        failed: repeats.iter().filter(|b| !b.ok).count(),
        sent: mean(&|b| b.sent as f64),
        delivered: mean(&|b| b.delivered as f64),
        delivered_fb: fb.map(|(d, _)| d as f64 / n),
        fb_pct: fb.map(|(d, sent)| {
            if sent == 0 {
                100.0
            } else {
                100.0 * d as f64 / sent as f64
            }
        }),
        lost: mean(&|b| b.lost() as f64),
        delivery_pct: if expected == 0 {
            100.0
        } else {
            100.0 * delivered as f64 / expected as f64
        },
        throughput: mean(&|b| b.throughput),
        processing_us: mean(&|b| b.processing_us as f64),
        lat_mean_us: mean(&|b| b.latency.mean_us),
        lat_p50_us: mean(&|b| b.latency.p50_us as f64),
        lat_p99_us: mean(&|b| b.latency.p99_us as f64),
        lat_max_us: repeats.iter().map(|b| b.latency.max_us).max().unwrap_or(0),
    }
}

/// The distinct x values of all batches, ascending.
pub(crate) fn distinct_xs(report: &Report) -> Vec<f64> {
    let mut xs: Vec<f64> = report.batches.iter().map(|b| b.x).collect();
    xs.sort_by(f64::total_cmp);
    xs.dedup();
    xs
}

/// The name a target is shown under in legends, labels and tables: its `name`, or
/// `name (label)` when two targets share a name (comparing two configurations of one
/// broker), so the two are never confused.
pub(crate) fn display_name(report: &Report, target: &Target) -> String {
    let shared = report
        .targets
        .iter()
        .filter(|t| t.name == target.name)
        .count()
        > 1;
    if shared {
        format!("{} ({})", target.name, target.label)
    } else {
        target.name.clone()
    }
}

/// [`display_name`] of the target labelled `label`, or the label itself for a batch whose
/// target is not listed.
pub(crate) fn name_of(report: &Report, label: &str) -> String {
    report
        .targets
        .iter()
        .find(|t| t.label == label)
        .map(|t| display_name(report, t))
        .unwrap_or_else(|| label.to_string())
}

/// Whether the run compares brokers (several targets): labels then say which one.
pub(crate) fn is_compare(report: &Report) -> bool {
    report.targets.len() > 1
}

//! The SVG charts: the JMeter study's figures, one line per broker.
//!
//! Which charts a run gets depends on its scenario (see the module doc of `report`); a
//! chart with nothing to show is not written. Each chart is drawn with plotters' SVG
//! backend into a string, which needs no system fonts: without a font feature plotters
//! only estimates text extents and the backend writes every label as an SVG `<text>`,
//! leaving the font to the viewer.
//!
//! Every data series is one `<polyline>` with one point per distinct x (so per burst
//! size, rate, or percentile), tagged after drawing with `class="series"` and
//! `data-series="<name>"` (the legend's name): a script or a test can read the plotted
//! values back without guessing which line is which. The reference line ("sent") is
//! tagged the same way and dashed with `stroke-dasharray`. Point markers are `<circle>`s
//! and legend markers `<rect>`s, so the tagged polylines are the only polylines in a
//! series' colour.

use std::ops::Range;
use std::path::{Path, PathBuf};

use plotters::coord::ranged1d::{DefaultFormatting, KeyPointHint};
use plotters::prelude::*;

use super::aggregate::{display_name, distinct_xs, points, Point};
use super::{create_dir, write_file, ReportError};
use crate::model::Report;

const SIZE: (u32, u32) = (960, 560);
/// One colour per target, in target order (A, B, ...): colour-blind-safe tableau colours,
/// none of them the mesh's greys or black.
const PALETTE: [RGBColor; 6] = [
    RGBColor(0x1F, 0x77, 0xB4),
    RGBColor(0xD6, 0x27, 0x28),
    RGBColor(0x2C, 0xA0, 0x2C),
    RGBColor(0xFF, 0x7F, 0x0E),
    RGBColor(0x94, 0x67, 0xBD),
    RGBColor(0x8C, 0x56, 0x4B),
];
const REFERENCE: RGBColor = RGBColor(0x7F, 0x7F, 0x7F);
const STROKE: u32 = 2;

/// Draws every chart that `report` has data for into `dir` (created if missing) and
/// returns their paths.
pub fn write_charts(report: &Report, dir: &Path) -> Result<Vec<PathBuf>, ReportError> {
    create_dir(dir)?;
    let mut written = Vec::new();
    for chart in charts(report) {
        let path = dir.join(chart.file);
        let svg = chart.render().map_err(|e| ReportError::Chart {
            path: path.clone(),
            message: e.to_string(),
        })?;
        write_file(&path, svg.as_bytes())?;
        written.push(path);
    }
    Ok(written)
}

/// How the x axis maps data to the page.
#[derive(Clone, Copy, PartialEq)]
enum XScale {
    Linear,
    /// Burst sizes double from one batch to the next: log2 keeps them evenly spaced.
    Log2,
    /// Percentiles 0..100 at x = log10(1 / (1 - p/100)), so 90%, 99%, 99.9% are evenly
    /// spaced: the tail, where brokers differ, gets most of the width (HdrHistogram's plot).
    Percentile,
}

impl XScale {
    fn to_axis(self, x: f64) -> f64 {
        match self {
            XScale::Linear => x,
            XScale::Log2 => x.log2(),
            // `percentile_points` moves 100% (infinity) in; the clamp is a safety net.
            XScale::Percentile => (1.0 / (1.0 - x.min(99.999_999) / 100.0)).log10(),
        }
    }

    fn label(self, axis: f64) -> String {
        match self {
            XScale::Linear => compact(axis),
            // Burst sizes are read exactly (1280, 20480), abbreviated only from a million.
            XScale::Log2 => match axis.exp2() {
                x if x < 1e6 && (x - x.round()).abs() < 1e-6 => format!("{x:.0}"),
                x => compact(x),
            },
            XScale::Percentile => percentile_label(axis),
        }
    }

    /// Tick positions on the axis for data spanning `lo..=hi` (axis units).
    fn ticks(self, lo: f64, hi: f64, data: &[f64]) -> Vec<f64> {
        match self {
            XScale::Linear => nice_ticks(lo, hi),
            // At the data's own x values (burst sizes are 10 x 2^k as often as 2^k), thinned
            // to keep labels apart.
            XScale::Log2 => {
                let step = data.len().div_ceil(12).max(1);
                data.iter().step_by(step).copied().collect()
            }
            XScale::Percentile => {
                // 0%, 50%, 90%, 99%, 99.9%, ... as far as the data goes.
                let mut ticks = vec![0.0, 2f64.log10()];
                ticks.extend((1..=8).map(f64::from).filter(|t| *t <= hi + 1e-9));
                ticks.retain(|t| *t >= lo - 1e-9);
                ticks
            }
        }
    }
}

struct Series {
    name: String,
    color: RGBColor,
    /// Data coordinates (x before scaling).
    points: Vec<(f64, f64)>,
    dashed: bool,
}

struct Chart {
    file: &'static str,
    title: String,
    x_desc: String,
    y_desc: String,
    x_scale: XScale,
    /// The y axis always starts at 0; it ends at least here.
    y_min_top: f64,
    legend: SeriesLabelPosition,
    series: Vec<Series>,
}

/// The charts for `report`'s scenario, each with at least one point to draw.
fn charts(report: &Report) -> Vec<Chart> {
    let per_target: Vec<(String, RGBColor, Vec<Point>)> = report
        .targets
        .iter()
        .enumerate()
        .map(|(i, t)| {
            let pts = points(report, &t.label);
            (display_name(report, t), PALETTE[i % PALETTE.len()], pts)
        })
        .collect();
    let lines = |f: fn(&Point) -> f64| -> Vec<Series> {
        per_target
            .iter()
            .map(|(name, color, pts)| Series {
                name: name.clone(),
                color: *color,
                points: pts.iter().map(|p| (p.x, f(p))).collect(),
                dashed: false,
            })
            .collect()
    };
    // A target's FB subscriber, when it had one: its own line, in the next colour.
    let fb_lines = |f: fn(&Point) -> Option<f64>| -> Vec<Series> {
        per_target
            .iter()
            .enumerate()
            .filter(|(_, (_, _, pts))| pts.iter().any(|p| f(p).is_some()))
            .map(|(i, (name, _, pts))| Series {
                name: format!("{name} FB subscriber"),
                color: PALETTE[(i + per_target.len()) % PALETTE.len()],
                points: pts.iter().filter_map(|p| Some((p.x, f(p)?))).collect(),
                dashed: false,
            })
            .collect()
    };
    let brokers = per_target
        .iter()
        .map(|(name, _, _)| name.as_str())
        .collect::<Vec<_>>()
        .join(" vs ");
    let scenario = &report.scenario;
    let xs = distinct_xs(report);
    let positive = xs.first().is_some_and(|x| *x > 0.0);
    let batch_scale = if positive && is_doubling(&xs) {
        XScale::Log2
    } else {
        XScale::Linear
    };
    let chart = |file, what: &str, x_desc: &str, y_desc: &str, x_scale, series| Chart {
        file,
        title: format!("{scenario}: {what} - {brokers}"),
        x_desc: x_desc.to_string(),
        y_desc: y_desc.to_string(),
        x_scale,
        y_min_top: 0.0,
        legend: SeriesLabelPosition::UpperLeft,
        series,
    };

    let mut charts = Vec::new();
    match scenario.as_str() {
        "stress" | "loss-search" => {
            let scale = if positive {
                XScale::Log2
            } else {
                XScale::Linear
            };
            let burst = match scale {
                XScale::Log2 => "burst size (messages, log2 scale)",
                _ => "burst size (messages)",
            };
            // The reference first, so the brokers' lines are drawn over it; then the FB
            // subscribers where there were any (the study counted there).
            let mut delivered = vec![reference(report)];
            delivered.extend(lines(|p| p.delivered));
            delivered.extend(fb_lines(|p| p.delivered_fb));
            charts.push(chart(
                "stress.svg",
                "messages delivered per burst",
                burst,
                "messages delivered (mean of repeats)",
                scale,
                delivered,
            ));
            let mut rate = chart(
                "delivery-rate.svg",
                "% delivered per burst",
                burst,
                "delivered (% of expected)",
                scale,
                lines(|p| p.delivery_pct)
                    .into_iter()
                    .chain(fb_lines(|p| p.fb_pct))
                    .collect(),
            );
            rate.y_min_top = 100.0;
            rate.legend = SeriesLabelPosition::LowerLeft;
            charts.push(rate);
        }
        "perf" => {
            let batch = if batch_scale == XScale::Log2 {
                "batch size (messages, log2 scale)"
            } else {
                "batch size (messages)"
            };
            charts.push(chart(
                "latency-vs-batch.svg",
                "mean latency per message",
                batch,
                "mean latency per message (ms)",
                batch_scale,
                lines(|p| p.lat_mean_us / 1000.0),
            ));
            charts.push(chart(
                "throughput-vs-batch.svg",
                "throughput",
                batch,
                "throughput (msg/s)",
                batch_scale,
                lines(|p| p.throughput),
            ));
            charts.push(chart(
                "processing-time.svg",
                "processing time (first send to last delivery)",
                batch,
                "processing time (ms)",
                batch_scale,
                lines(|p| p.processing_us / 1000.0),
            ));
        }
        // The campaigns: connections per second of each round, against connections so far.
        "mutate" | "churn" if xs.len() > 1 => {
            charts.push(chart(
                "throughput.svg",
                "connections per second, round by round",
                "connections so far",
                "connections/s",
                XScale::Linear,
                lines(|p| p.throughput),
            ));
        }
        _ if xs.len() > 1 => {
            charts.push(chart(
                "throughput.svg",
                "throughput",
                &match batch_scale {
                    XScale::Log2 => format!("{} (log2 scale)", x_description(report)),
                    _ => x_description(report),
                },
                "throughput (msg/s)",
                batch_scale,
                lines(|p| p.throughput),
            ));
        }
        _ => {}
    }

    let curves: Vec<Series> = report
        .targets
        .iter()
        .enumerate()
        .filter_map(|(i, t)| {
            let summary = report.summaries.iter().find(|s| s.target == t.label)?;
            Some(Series {
                name: display_name(report, t),
                color: PALETTE[i % PALETTE.len()],
                points: percentile_points(&summary.latency.curve),
                dashed: false,
            })
        })
        .filter(|s| !s.points.is_empty())
        .collect();
    if !curves.is_empty() {
        charts.push(chart(
            "latency-percentiles.svg",
            "latency by percentile",
            "percentile",
            "latency (ms)",
            XScale::Percentile,
            curves,
        ));
    }

    charts.retain(|c| c.series.iter().any(|s| !s.points.is_empty()));
    charts
}

/// The dashed reference line of the stress chart: what should have arrived per burst.
/// It is "sent" when every message has one subscriber (the study's stress test), else
/// "expected" (sent x subscribers), which is what `delivered` is measured against.
fn reference(report: &Report) -> Series {
    let one_copy = report.batches.iter().all(|b| b.expected == b.sent);
    let mut by_x: Vec<(f64, f64)> = Vec::new();
    for x in distinct_xs(report) {
        let at_x: Vec<f64> = report
            .batches
            .iter()
            .filter(|b| b.x == x)
            .map(|b| if one_copy { b.sent } else { b.expected } as f64)
            .collect();
        by_x.push((x, at_x.iter().sum::<f64>() / at_x.len() as f64));
    }
    Series {
        name: if one_copy { "sent" } else { "expected" }.to_string(),
        color: REFERENCE,
        points: by_x,
        dashed: true,
    }
}

/// A latency curve as (percentile, ms) points. The 100% point (the max) would be at
/// infinity on the percentile axis: it is drawn half a decade right of the last other
/// point, where HdrHistogram's own plots end.
fn percentile_points(curve: &[(f64, u64)]) -> Vec<(f64, f64)> {
    let last_finite = curve
        .iter()
        .filter(|(p, _)| *p < 100.0)
        .map(|&(p, _)| XScale::Percentile.to_axis(p))
        .fold(0.0, f64::max);
    let max_at = 100.0 * (1.0 - 10f64.powf(-(last_finite + 0.5)));
    curve
        .iter()
        .map(|&(p, us)| (if p < 100.0 { p } else { max_at }, us as f64 / 1000.0))
        .collect()
}

/// Whether the x values grow geometrically (each about twice the previous, as the study's
/// doubling bursts), as opposed to a linear sweep such as perf's 1, 2, 3, ... N.
fn is_doubling(xs: &[f64]) -> bool {
    if xs.len() < 3 || xs[0] <= 0.0 {
        return false;
    }
    let mut ratios: Vec<f64> = xs.windows(2).map(|w| w[1] / w[0]).collect();
    ratios.sort_by(f64::total_cmp);
    ratios[ratios.len() / 2] >= 1.5
}

/// The x axis description for the generic throughput chart, from the batch labels
/// (`rate 5000/s`, `publishers 8`): their words without digits.
fn x_description(report: &Report) -> String {
    let Some(first) = report.batches.first() else {
        return "x".to_string();
    };
    let words: Vec<&str> = first
        .label
        .split_whitespace()
        .filter(|w| !w.chars().any(|c| c.is_ascii_digit()))
        .collect();
    match words.as_slice() {
        [] => "x".to_string(),
        ["rate"] => "offered rate (msg/s)".to_string(),
        words => words.join(" "),
    }
}

impl Chart {
    /// The chart as an SVG document.
    fn render(&self) -> Result<String, Box<dyn std::error::Error>> {
        let scale = self.x_scale;
        let axis_xs: Vec<f64> = {
            let mut xs: Vec<f64> = self
                .series
                .iter()
                .flat_map(|s| s.points.iter().map(|p| scale.to_axis(p.0)))
                .filter(|x| x.is_finite())
                .collect();
            xs.sort_by(f64::total_cmp);
            xs.dedup();
            xs
        };
        let (mut x_lo, mut x_hi) = match (axis_xs.first(), axis_xs.last()) {
            (Some(lo), Some(hi)) => (*lo, *hi),
            _ => (0.0, 1.0),
        };
        if scale == XScale::Percentile {
            // Always show up to 99.99%, the study's tail.
            x_lo = x_lo.min(0.0);
            x_hi = x_hi.max(4.0);
        }
        if x_hi - x_lo < 1e-9 {
            x_lo -= 1.0;
            x_hi += 1.0;
        }
        let pad = (x_hi - x_lo) * 0.03;
        let ticks = scale.ticks(x_lo, x_hi, &axis_xs);
        let y_max = self
            .series
            .iter()
            .flat_map(|s| s.points.iter().map(|p| p.1))
            .filter(|y| y.is_finite())
            .fold(self.y_min_top, f64::max);
        let y_top = if y_max > 0.0 { y_max * 1.08 } else { 1.0 };

        let mut svg = String::new();
        {
            let root = SVGBackend::with_string(&mut svg, SIZE).into_drawing_area();
            root.fill(&WHITE)?;
            let mut chart = ChartBuilder::on(&root)
                .caption(&self.title, ("sans-serif", 20))
                .margin(16)
                .x_label_area_size(52)
                .y_label_area_size(80)
                .build_cartesian_2d(
                    TickedAxis {
                        range: (x_lo - pad)..(x_hi + pad),
                        ticks,
                    },
                    0f64..y_top,
                )?;
            chart
                .configure_mesh()
                .x_desc(self.x_desc.as_str())
                .y_desc(self.y_desc.as_str())
                .x_label_formatter(&|x| scale.label(*x))
                .y_label_formatter(&|y| compact(*y))
                .bold_line_style(RGBColor(0xDD, 0xDD, 0xDD))
                .light_line_style(TRANSPARENT)
                .label_style(("sans-serif", 13))
                .axis_desc_style(("sans-serif", 15))
                .draw()?;
            for series in &self.series {
                let pts: Vec<(f64, f64)> = series
                    .points
                    .iter()
                    .map(|&(x, y)| (scale.to_axis(x), y))
                    .filter(|(x, y)| x.is_finite() && y.is_finite())
                    .collect();
                let color = series.color;
                chart
                    .draw_series(LineSeries::new(pts.clone(), color.stroke_width(STROKE)))?
                    .label(series.name.as_str())
                    .legend(move |(x, y)| {
                        Rectangle::new([(x, y - 3), (x + 18, y + 3)], color.filled())
                    });
                if !series.dashed && pts.len() <= 64 {
                    chart.draw_series(pts.iter().map(|&p| Circle::new(p, 3, color.filled())))?;
                }
            }
            chart
                .configure_series_labels()
                .position(self.legend.clone())
                .background_style(WHITE.mix(0.85))
                .border_style(RGBColor(0xAA, 0xAA, 0xAA))
                .label_font(("sans-serif", 14))
                .draw()?;
            root.present()?;
        }
        Ok(self.tag(svg))
    }

    /// Adds a `<title>` and tags each series' polyline with its name (see module doc).
    fn tag(&self, mut svg: String) -> String {
        for s in &self.series {
            let RGBColor(r, g, b) = s.color;
            let drawn = format!(
                "<polyline fill=\"none\" opacity=\"1\" stroke=\"#{r:02X}{g:02X}{b:02X}\" \
                 stroke-width=\"{STROKE}\""
            );
            let dash = if s.dashed {
                " stroke-dasharray=\"8 5\""
            } else {
                ""
            };
            let tagged = format!(
                "<polyline class=\"series\" data-series=\"{}\"{dash}{}",
                escape(&s.name),
                &drawn["<polyline".len()..]
            );
            svg = svg.replace(&drawn, &tagged);
        }
        if let Some(end) = svg.find(">\n") {
            svg.insert_str(
                end + 2,
                &format!("<title>{}</title>\n", escape(&self.title)),
            );
        }
        svg
    }
}

/// A linear f64 axis with the tick positions given, not plotters' own: the log2 and
/// percentile axes are linear in transformed units and need their ticks where the
/// untransformed values are round. (plotters' `with_key_points` does the same, but its
/// f64 form cannot take a label formatter.)
struct TickedAxis {
    range: Range<f64>,
    ticks: Vec<f64>,
}

impl Ranged for TickedAxis {
    type FormatOption = DefaultFormatting;
    type ValueType = f64;

    fn map(&self, value: &f64, limit: (i32, i32)) -> i32 {
        let Range { start, end } = self.range;
        let share = (value - start) / (end - start);
        limit.0 + (share * f64::from(limit.1 - limit.0)).round() as i32
    }

    fn key_points<Hint: KeyPointHint>(&self, hint: Hint) -> Vec<f64> {
        if hint.weight().allow_light_points() {
            Vec::new()
        } else {
            self.ticks.clone()
        }
    }

    fn range(&self) -> Range<f64> {
        self.range.clone()
    }
}

fn escape(text: &str) -> String {
    text.replace('&', "&amp;")
        .replace('<', "&lt;")
        .replace('>', "&gt;")
        .replace('"', "&quot;")
}

/// The percentile at `axis` on the percentile axis, as `99.9%`.
pub(crate) fn percentile_label(axis: f64) -> String {
    let p = 100.0 * (1.0 - 1.0 / 10f64.powf(axis));
    let s = format!("{p:.8}");
    format!("{}%", s.trim_end_matches('0').trim_end_matches('.'))
}

/// "Nice" tick positions (1, 2 or 5 x 10^k apart), about eight over `lo..=hi`.
fn nice_ticks(lo: f64, hi: f64) -> Vec<f64> {
    let raw = (hi - lo) / 8.0;
    let magnitude = 10f64.powf(raw.log10().floor());
    let step = [1.0, 2.0, 5.0, 10.0]
        .iter()
        .map(|m| m * magnitude)
        .find(|s| *s >= raw)
        .unwrap_or(magnitude * 10.0);
    let first = (lo / step).ceil() as i64;
    let last = (hi / step).floor() as i64;
    (first..=last).map(|i| i as f64 * step).collect()
}

/// A number as a short label: 950, 1.5k, 12k, 2.5M, 2.25, 0.125 (about three significant
/// digits, trailing zeros dropped).
pub(crate) fn compact(v: f64) -> String {
    let a = v.abs();
    let (value, suffix) = if a >= 1e9 {
        (v / 1e9, "G")
    } else if a >= 1e6 {
        (v / 1e6, "M")
    } else if a >= 1e4 {
        (v / 1e3, "k")
    } else {
        (v, "")
    };
    let decimals = match value.abs() {
        v if v >= 100.0 || v.fract() == 0.0 => 0,
        v if v >= 10.0 => 1,
        v if v >= 1.0 => 2,
        _ => 3,
    };
    let s = format!("{value:.decimals$}");
    let s = if s.contains('.') {
        s.trim_end_matches('0').trim_end_matches('.').to_string()
    } else {
        s
    };
    format!("{s}{suffix}")
}

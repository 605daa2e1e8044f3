//! Writes hand-built reports (a two-broker stress run with loss, a one-broker perf run)
//! and reads every output back the way its consumers would.

use std::collections::BTreeSet;
use std::path::Path;

use super::*;
use crate::model::*;

fn latency(scale: u64) -> Latency {
    Latency {
        count: 100,
        mean_us: 1.5 * scale as f64,
        p50_us: scale,
        p90_us: 2 * scale,
        p99_us: 4 * scale,
        p999_us: 8 * scale,
        max_us: 10 * scale,
        curve: vec![
            (0.0, scale / 2),
            (50.0, scale),
            (90.0, 2 * scale),
            (99.0, 4 * scale),
            (99.9, 8 * scale),
            (100.0, 10 * scale),
        ],
    }
}

fn target(label: &str, name: &str, port: u16) -> Target {
    Target {
        label: label.into(),
        address: format!("mqtt://127.0.0.1:{port}"),
        version: Some(format!("{name} 1.0")),
        name: name.into(),
    }
}

fn report(scenario: &str, targets: Vec<Target>, batches: Vec<Batch>) -> Report {
    let summaries = targets
        .iter()
        .enumerate()
        .map(|(i, t)| {
            let own: Vec<&Batch> = batches.iter().filter(|b| b.target == t.label).collect();
            Summary {
                target: t.label.clone(),
                batches: own.len() as u64,
                sent: own.iter().map(|b| b.sent).sum(),
                expected: own.iter().map(|b| b.expected).sum(),
                delivered: own.iter().map(|b| b.delivered).sum(),
                delivered_fb: None,
                duplicates: 0,
                throughput: 10_000.0 * (i + 1) as f64,
                latency: latency(1000 * (i as u64 + 1)),
                figures: vec![Figure {
                    name: "largest_lossless".into(),
                    value: 80.0,
                    unit: "messages".into(),
                }],
            }
        })
        .collect();
    let ratios = if targets.len() == 2 {
        vec![Ratio {
            figure: "throughput".into(),
            a: 10_000.0,
            b: 20_000.0,
            ratio: 2.0,
        }]
    } else {
        vec![]
    };
    Report {
        tool: "fbbus-loadtest 0.1.0".into(),
        command: "fbbus-loadtest stress --compare".into(),
        started: "2025-01-01T00:00:00Z".into(),
        machine: Machine {
            hostname: "bench".into(),
            os: "Linux 6.1".into(),
            cpu_model: "Test CPU".into(),
            cpus: 2,
            memory_mib: 24_000,
        },
        scenario: scenario.into(),
        params: serde_json::json!({"start": 10, "repeats": 2}),
        targets,
        ceiling: Some(Ceiling {
            label: "burst 20000".into(),
            messages: 100_000,
            throughput: 500_000.0,
            latency: latency(100),
        }),
        batches,
        summaries,
        ratios,
        notes: vec!["FB subscriber not used: test note".into()],
        failures: vec![],
    }
}

fn batch(target: &str, x: u64, repeat: u32, delivered: u64, started_ms: u64) -> Batch {
    let ok = delivered == x;
    Batch {
        target: target.into(),
        label: format!("burst {x}"),
        x: x as f64,
        repeat,
        started_ms,
        sent: x,
        delivered,
        expected: x,
        delivered_fb: (target == "A").then_some(delivered),
        duplicates: 0,
        out_of_order: 1,
        send_us: 10 * x,
        processing_us: 1500 * x,
        throughput: delivered as f64 / (1500e-6 * x as f64),
        latency: latency(100 * x),
        ok,
        // A comma and a quote: the CSV and JTL must quote this field.
        error: (!ok).then(|| format!("lost {} of {x}, \"queue full\"", x - delivered)),
    }
}

/// Bursts 10 .. 320 doubling, two repeats, A and B interleaved; B loses from 160 on.
fn stress() -> Report {
    let mut batches = Vec::new();
    let mut t = 1_700_000_000_000;
    for k in 0..6 {
        let x = 10u64 << k;
        for repeat in 1..=2 {
            batches.push(batch("A", x, repeat, x, t));
            let lost = if x >= 160 {
                x / 10 + u64::from(repeat)
            } else {
                0
            };
            batches.push(batch("B", x, repeat, x - lost, t + 500));
            t += 1000;
        }
    }
    let targets = vec![target("A", "fbbus", 1883), target("B", "mosquitto", 1884)];
    report("stress", targets, batches)
}

/// Batches of 1 .. 20 messages, one repeat, one broker.
fn perf() -> Report {
    let batches = (1..=20)
        .map(|x| batch("A", x, 1, x, 1_700_000_000_000 + 100 * x))
        .collect();
    report("perf", vec![target("A", "fbbus", 1883)], batches)
}

/// RFC 4180 reader: records of fields, quotes honoured.
fn parse_csv(text: &str) -> Vec<Vec<String>> {
    let mut records = Vec::new();
    let (mut record, mut field) = (Vec::new(), String::new());
    let mut chars = text.chars().peekable();
    let mut quoted = false;
    while let Some(c) = chars.next() {
        match (quoted, c) {
            (true, '"') if chars.peek() == Some(&'"') => {
                chars.next();
                field.push('"');
            }
            (true, '"') => quoted = false,
            (true, c) => field.push(c),
            (false, '"') => quoted = true,
            (false, ',') => record.push(std::mem::take(&mut field)),
            (false, '\r') => {}
            (false, '\n') => {
                record.push(std::mem::take(&mut field));
                records.push(std::mem::take(&mut record));
            }
            (false, c) => field.push(c),
        }
    }
    assert!(
        field.is_empty() && record.is_empty(),
        "file must end with a newline"
    );
    records
}

fn column<'a>(header: &[String], row: &'a [String], name: &str) -> &'a str {
    let i = header.iter().position(|h| h == name).unwrap();
    &row[i]
}

/// The points of the polyline tagged as series `name` in `svg`.
fn series_points(svg: &str, name: &str) -> Vec<(i64, i64)> {
    let tag = format!("data-series=\"{name}\"");
    let mut found = svg
        .lines()
        .filter(|l| l.contains("<polyline") && l.contains(&tag));
    let line = found.next().unwrap_or_else(|| panic!("no series {name}"));
    assert!(found.next().is_none(), "series {name} drawn twice");
    let points = line
        .split("points=\"")
        .nth(1)
        .unwrap()
        .split('"')
        .next()
        .unwrap();
    points
        .split_whitespace()
        .map(|p| {
            let (x, y) = p.split_once(',').unwrap();
            (x.parse().unwrap(), y.parse().unwrap())
        })
        .collect()
}

fn read(path: &Path) -> String {
    std::fs::read_to_string(path).unwrap()
}

fn file_names(paths: &[std::path::PathBuf]) -> BTreeSet<String> {
    paths
        .iter()
        .map(|p| p.file_name().unwrap().to_string_lossy().into_owned())
        .collect()
}

#[test]
fn json_reads_back_equal() {
    let dir = tempfile::tempdir().unwrap();
    let original = stress();
    write_all(&original, dir.path()).unwrap();
    let back: Report = serde_json::from_str(&read(&dir.path().join(JSON_FILE))).unwrap();
    assert_eq!(back.tool, original.tool);
    assert_eq!(back.command, original.command);
    assert_eq!(back.scenario, original.scenario);
    assert_eq!(back.params, original.params);
    assert_eq!(back.targets.len(), 2);
    assert_eq!(back.targets[1].name, "mosquitto");
    assert_eq!(back.batches.len(), original.batches.len());
    for (a, b) in back.batches.iter().zip(&original.batches) {
        assert_eq!((a.x, a.delivered, a.ok), (b.x, b.delivered, b.ok));
        assert_eq!(a.error, b.error);
        assert_eq!(a.latency.curve, b.latency.curve);
    }
    assert_eq!(back.summaries[0].figures[0].name, "largest_lossless");
    assert_eq!(back.ratios[0].ratio, 2.0);
    assert_eq!(back.notes, original.notes);
    // And everything else: the two serialize identically.
    assert_eq!(
        serde_json::to_value(&back).unwrap(),
        serde_json::to_value(&original).unwrap()
    );
}

#[test]
fn csv_has_one_row_per_batch() {
    let dir = tempfile::tempdir().unwrap();
    let r = stress();
    let path = dir.path().join(CSV_FILE);
    write_csv(&r, &path).unwrap();
    let records = parse_csv(&read(&path));
    let header = &records[0];
    assert_eq!(header.join(","), super::csv::CSV_COLUMNS.join(","));
    assert_eq!(records.len() - 1, r.batches.len());
    for (row, b) in records[1..].iter().zip(&r.batches) {
        assert_eq!(row.len(), header.len());
        let expected: u64 = column(header, row, "expected").parse().unwrap();
        let delivered: u64 = column(header, row, "delivered").parse().unwrap();
        let lost: u64 = column(header, row, "lost").parse().unwrap();
        assert_eq!(lost, expected - delivered);
        assert_eq!(column(header, row, "ok"), b.ok.to_string());
        assert_eq!(
            column(header, row, "error"),
            b.error.as_deref().unwrap_or("")
        );
        let fb = column(header, row, "delivered_fb");
        assert_eq!(
            fb,
            b.delivered_fb.map(|d| d.to_string()).unwrap_or_default()
        );
        let name = if b.target == "A" {
            "fbbus"
        } else {
            "mosquitto"
        };
        assert_eq!(column(header, row, "target_name"), name);
        let rate: f64 = column(header, row, "delivery_rate").parse().unwrap();
        assert_eq!(rate, b.delivery_rate());
    }
}

#[test]
fn jtl_is_a_jmeter_csv() {
    let dir = tempfile::tempdir().unwrap();
    let r = stress();
    let path = dir.path().join(JTL_FILE);
    write_jtl(&r, &path).unwrap();
    let text = read(&path);
    assert!(text.starts_with(
        "timeStamp,elapsed,label,responseCode,responseMessage,threadName,dataType,success,\
         failureMessage,bytes,sentBytes,grpThreads,allThreads,URL,Latency,IdleTime,Connect\n"
    ));
    let records = parse_csv(&text);
    let header = &records[0];
    assert_eq!(header.len(), 17);
    assert_eq!(records.len() - 1, r.batches.len());
    let mut failures = 0;
    for (row, b) in records[1..].iter().zip(&r.batches) {
        assert_eq!(row.len(), 17);
        let success = column(header, row, "success");
        assert_eq!(success, if b.ok { "true" } else { "false" });
        failures += usize::from(!b.ok);
        let code = column(header, row, "responseCode");
        assert_eq!(code, if b.ok { "200" } else { "500" });
        let ts: u64 = column(header, row, "timeStamp").parse().unwrap();
        assert_eq!(ts, b.started_ms);
        let elapsed: u64 = column(header, row, "elapsed").parse().unwrap();
        assert_eq!(elapsed, b.processing_us / 1000);
        let latency: u64 = column(header, row, "Latency").parse().unwrap();
        assert_eq!(latency, (b.latency.mean_us / 1000.0).round() as u64);
        let name = if b.target == "A" {
            "fbbus"
        } else {
            "mosquitto"
        };
        assert_eq!(
            column(header, row, "label"),
            format!("stress {} [{name}]", b.label)
        );
        assert_eq!(column(header, row, "threadName"), format!("{name} 1-1"));
        assert_eq!(
            column(header, row, "responseMessage"),
            format!("delivered {} of {}", b.delivered, b.expected)
        );
        assert_eq!(
            column(header, row, "failureMessage"),
            b.error.as_deref().unwrap_or("")
        );
        assert_eq!(column(header, row, "bytes"), b.delivered.to_string());
        assert_eq!(column(header, row, "sentBytes"), b.sent.to_string());
        assert!(column(header, row, "URL").starts_with("mqtt://127.0.0.1:188"));
    }
    assert!(failures > 0, "the fixture must have failed batches");
}

#[test]
fn jtl_label_has_no_target_outside_compare_mode() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join(JTL_FILE);
    write_jtl(&perf(), &path).unwrap();
    let records = parse_csv(&read(&path));
    assert_eq!(records[1][2], "perf burst 1");
}

fn check_svg(svg: &str, names: &[&str]) {
    assert!(svg.starts_with("<svg"), "{}", &svg[..40]);
    assert!(svg.trim_end().ends_with("</svg>"));
    assert!(svg.contains("<text"), "labels must be SVG text");
    for name in names {
        assert!(svg.contains(name), "{name} missing");
    }
}

#[test]
fn stress_charts_have_one_point_per_burst_size() {
    let dir = tempfile::tempdir().unwrap();
    let r = stress();
    let written = write_all(&r, &dir.path().join("out")).unwrap();
    let names = file_names(&written);
    let expected: BTreeSet<String> = [
        "report.json",
        "batches.csv",
        "batches.jtl",
        "stress.svg",
        "delivery-rate.svg",
        "latency-percentiles.svg",
    ]
    .map(String::from)
    .into();
    assert_eq!(names, expected);
    for file in ["stress.svg", "delivery-rate.svg"] {
        let svg = read(&dir.path().join("out").join(file));
        check_svg(&svg, &["fbbus", "mosquitto", "stress"]);
        for name in ["fbbus", "mosquitto"] {
            let pts = series_points(&svg, name);
            assert_eq!(pts.len(), 6, "{file} {name}");
            assert!(pts.windows(2).all(|w| w[0].0 < w[1].0), "x ascending");
        }
    }
    let stress_svg = read(&dir.path().join("out/stress.svg"));
    assert_eq!(series_points(&stress_svg, "sent").len(), 6);
    assert!(stress_svg.contains("stroke-dasharray"));
    // Log2 axis: the doubling bursts are evenly spaced.
    let xs: Vec<i64> = series_points(&stress_svg, "fbbus")
        .iter()
        .map(|p| p.0)
        .collect();
    let gaps: Vec<i64> = xs.windows(2).map(|w| w[1] - w[0]).collect();
    assert!(gaps.iter().all(|g| (g - gaps[0]).abs() <= 1), "{gaps:?}");
    // B loses at 160 and 320: its delivery-rate line drops (SVG y grows downwards).
    let rate_svg = read(&dir.path().join("out/delivery-rate.svg"));
    let b = series_points(&rate_svg, "mosquitto");
    assert_eq!(b[0].1, b[3].1);
    assert!(b[5].1 > b[3].1);

    let svg = read(&dir.path().join("out/latency-percentiles.svg"));
    check_svg(
        &svg,
        &["fbbus", "mosquitto", "99.9%", "99.99%", "50%", "90%"],
    );
    for name in ["fbbus", "mosquitto"] {
        assert_eq!(series_points(&svg, name).len(), 6);
    }
}

#[test]
fn perf_charts() {
    let dir = tempfile::tempdir().unwrap();
    let r = perf();
    let written = write_charts(&r, dir.path()).unwrap();
    let names = file_names(&written);
    let expected: BTreeSet<String> = [
        "latency-vs-batch.svg",
        "throughput-vs-batch.svg",
        "processing-time.svg",
        "latency-percentiles.svg",
    ]
    .map(String::from)
    .into();
    assert_eq!(names, expected);
    for (file, unit) in [
        ("latency-vs-batch.svg", "(ms)"),
        ("throughput-vs-batch.svg", "(msg/s)"),
        ("processing-time.svg", "(ms)"),
    ] {
        let svg = read(&dir.path().join(file));
        check_svg(&svg, &["fbbus", "perf", unit, "batch size (messages)"]);
        let pts = series_points(&svg, "fbbus");
        assert_eq!(pts.len(), 20, "{file}");
        // 1..20 is a linear sweep: drawn on a linear axis, evenly spaced.
        let gaps: Vec<i64> = pts.windows(2).map(|w| w[1].0 - w[0].0).collect();
        assert!(
            gaps.iter().all(|g| (g - gaps[0]).abs() <= 1),
            "{file} {gaps:?}"
        );
    }
}

#[test]
fn other_scenarios_chart_throughput_when_x_varies() {
    let dir = tempfile::tempdir().unwrap();
    let mut r = stress();
    r.scenario = "fan-in".into();
    for b in &mut r.batches {
        b.label = format!("rate {}/s", b.x);
    }
    let names = file_names(&write_charts(&r, dir.path()).unwrap());
    assert!(names.contains("throughput.svg"), "{names:?}");
    let svg = read(&dir.path().join("throughput.svg"));
    check_svg(&svg, &["fbbus", "mosquitto", "fan-in", "msg/s"]);
    assert_eq!(series_points(&svg, "mosquitto").len(), 6);

    // One x only (a connect storm): nothing to draw against x.
    let dir = tempfile::tempdir().unwrap();
    r.scenario = "storm".into();
    r.batches.retain(|b| b.x == 10.0);
    r.summaries.iter_mut().for_each(|s| s.latency.curve.clear());
    assert!(write_charts(&r, dir.path()).unwrap().is_empty());
}

#[test]
fn same_broker_twice_is_told_apart() {
    let dir = tempfile::tempdir().unwrap();
    let mut r = stress();
    r.targets[1].name = "fbbus".into();
    write_charts(&r, dir.path()).unwrap();
    let svg = read(&dir.path().join("stress.svg"));
    assert_eq!(series_points(&svg, "fbbus (A)").len(), 6);
    assert_eq!(series_points(&svg, "fbbus (B)").len(), 6);
}

#[test]
fn table_shows_rows_summaries_and_ratios() {
    let r = stress();
    let t = table(&r);
    println!("{t}");
    for needle in [
        "fbbus-loadtest 0.1.0",
        "command: fbbus-loadtest stress --compare",
        "machine: bench",
        "target A: fbbus fbbus 1.0 at mqtt://127.0.0.1:1883",
        "target B: mosquitto",
        "harness ceiling",
        "note: FB subscriber not used",
        "largest_lossless = 80 messages",
        "B/A",
    ] {
        assert!(t.contains(needle), "{needle} missing from\n{t}");
    }
    // One row per x and target.
    let rows = t.lines().filter(|l| l.starts_with("burst ")).count();
    assert_eq!(rows, 12);
    // Aligned: the rows of the batch block are as wide as its rule.
    let lines: Vec<&str> = t.lines().collect();
    let head = lines.iter().position(|l| l.starts_with("batch ")).unwrap();
    let rule = lines[head + 1].len();
    assert!(lines[head + 2..head + 14].iter().all(|l| l.len() == rule));
    // B at 320: 2 repeats losing 33 and 34, mean 33.5, delivered 89.5%.
    let b320 = lines
        .iter()
        .find(|l| l.starts_with("burst 320") && l.contains("mosquitto"))
        .unwrap();
    assert!(b320.contains("33.5") && b320.contains("89.5"), "{b320}");
}

#[test]
fn errors_name_the_file() {
    let dir = tempfile::tempdir().unwrap();
    let blocker = dir.path().join("file");
    std::fs::write(&blocker, "").unwrap();
    let err = write_all(&stress(), &blocker.join("sub")).unwrap_err();
    let msg = err.to_string();
    assert!(
        msg.contains("file/sub") && msg.contains("directory"),
        "{msg}"
    );
}

#[test]
fn compact_numbers() {
    use super::svg::compact;
    let cases = [
        (0.0, "0"),
        (0.125, "0.125"),
        (2.5, "2.5"),
        (12.25, "12.2"),
        (950.0, "950"),
        (1500.0, "1500"),
        (10_000.0, "10k"),
        (12_345.0, "12.3k"),
        (2_500_000.0, "2.5M"),
    ];
    for (v, s) in cases {
        assert_eq!(compact(v), s);
    }
}

#[test]
fn empty_run_still_writes_its_record() {
    let dir = tempfile::tempdir().unwrap();
    let r = report("idle", vec![target("A", "fbbus", 1883)], vec![]);
    let names = file_names(&write_all(&r, dir.path()).unwrap());
    // The summary has a latency curve, so its chart is drawn; nothing varies x.
    assert!(names.contains("report.json") && names.contains("batches.jtl"));
    assert!(!names.contains("throughput.svg"));
    assert_eq!(parse_csv(&read(&dir.path().join(CSV_FILE))).len(), 1);
    assert!(table(&r).contains("no batches were measured"));
}

#[test]
fn percentile_ticks_read_as_percentiles() {
    use super::svg::percentile_label;
    let labels: Vec<String> = [0.0, 2f64.log10(), 1.0, 2.0, 3.0, 4.0, 5.0, 7.0]
        .iter()
        .map(|&t| percentile_label(t))
        .collect();
    assert_eq!(
        labels,
        [
            "0%",
            "50%",
            "90%",
            "99%",
            "99.9%",
            "99.99%",
            "99.999%",
            "99.99999%"
        ]
    );
}

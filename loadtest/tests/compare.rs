//! `fbbus-loadtest compare` (the broker comparison that was `fbbus-bench`) at smoke-test
//! sizes against the real `fbbus` binary of this target directory (built once if
//! missing), Mosquitto where installed (CI installs it) and raw rumqttd: a numeric figure
//! per broker and the ratios, two fbbus binaries alternating round by round, and the
//! fbbus-only `compare bridge`, over plain TCP and over mutual TLS.

mod common;

use std::time::{Duration, Instant};

use common::{fbbus_bin, loadtest, require, Run};

/// "312.4k" -> 312400.0
fn parse_si(token: &str) -> Option<f64> {
    let (number, factor) = match token.strip_suffix('k') {
        Some(n) => (n, 1e3),
        None => match token.strip_suffix('M') {
            Some(n) => (n, 1e6),
            None => (token, 1.0),
        },
    };
    number.parse::<f64>().ok().map(|v| v * factor)
}

/// The ratio line of the scenario whose title starts with `title`.
fn ratio_line<'a>(run: &'a Run, title: &str) -> &'a str {
    run.stdout
        .lines()
        .rev()
        .find(|l| l.starts_with(title))
        .unwrap_or_else(|| panic!("no `{title}` result line\n{}", run.context()))
}

/// The msg/s figure that follows `label` in a fan-in ratio line.
fn rate_of(line: &str, label: &str) -> Option<f64> {
    let tokens: Vec<&str> = line.split_whitespace().collect();
    let at = tokens.iter().position(|t| *t == label)?;
    (tokens.get(at + 2) == Some(&"msg/s"))
        .then(|| tokens.get(at + 1).and_then(|t| parse_si(t)))
        .flatten()
}

/// The ratio `a/b 1.23x` in a ratio line.
fn ratio(line: &str, pair: &str) -> Option<f64> {
    let tokens: Vec<&str> = line.split_whitespace().collect();
    let at = tokens.iter().position(|t| *t == pair)?;
    tokens
        .get(at + 1)?
        .split('/')
        .next()?
        .strip_suffix('x')?
        .parse()
        .ok()
}

#[test]
fn quick_fanin_and_connrate_against_fbbus() {
    let fbbus = fbbus_bin();
    let started = Instant::now();
    let run = loadtest(
        &[
            "compare",
            "--quick",
            "--brokers",
            "fbbus",
            "--scenarios",
            "fanin,connrate",
            "--fbbus",
            fbbus,
        ],
        &[],
    );
    let elapsed = started.elapsed();
    assert!(run.success, "compare failed\n{}", run.context());
    // The ratio line: `burst fan-in (...)   fbbus 312.4k msg/s ...`
    let line = ratio_line(&run, "burst fan-in");
    assert!(
        matches!(rate_of(line, "fbbus"), Some(r) if r > 0.0),
        "fbbus msg/s is not a number in {line:?}\n{}",
        run.context()
    );
    assert!(
        run.stdout
            .lines()
            .any(|l| l.starts_with("connections per second") && l.contains("conn/s")),
        "no connection-rate figure\n{}",
        run.context()
    );
    // The transcript is written outside the source tree, where --out says.
    assert_eq!(run.file("compare.txt"), run.stdout);
    assert!(
        elapsed < Duration::from_secs(30),
        "the quick smoke run took {elapsed:?}"
    );
}

#[test]
fn two_fbbus_binaries_alternate_and_report_new_over_old() {
    let fbbus = fbbus_bin();
    let old = format!("old={fbbus}");
    let new = format!("new={fbbus}");
    let run = loadtest(
        &[
            "compare",
            "--quick",
            "--brokers",
            "fbbus",
            "--fbbus",
            &old,
            "--fbbus",
            &new,
            "--rounds",
            "2",
            "--scenarios",
            "fanin,idlemem",
        ],
        &[],
    );
    assert!(run.success, "compare failed\n{}", run.context());
    // A B A B: every round runs both binaries before the next round starts.
    let rows: Vec<&str> = run
        .stdout
        .lines()
        .filter_map(|l| l.trim_start().split("  ").next())
        .filter(|first| first.starts_with("old #") || first.starts_with("new #"))
        .collect();
    assert_eq!(
        rows,
        ["old #1", "new #1", "old #2", "new #2", "old #1", "new #1", "old #2", "new #2"],
        "{}",
        run.context()
    );
    let fanin = ratio_line(&run, "burst fan-in");
    assert!(fanin.contains("[median of 2]"), "{fanin}");
    assert!(
        matches!(rate_of(fanin, "old"), Some(r) if r > 0.0)
            && matches!(rate_of(fanin, "new"), Some(r) if r > 0.0),
        "{fanin}"
    );
    let r = ratio(fanin, "new/old").unwrap_or_else(|| panic!("no new/old ratio: {fanin}"));
    assert!(r > 0.0, "{fanin}");
    let idle = ratio_line(&run, "memory per idle connection");
    assert!(
        idle.contains("KB/conn") && idle.contains("new/old"),
        "{idle}"
    );
}

#[test]
fn fbbus_mosquitto_and_raw_rumqttd_side_by_side() {
    if !std::path::Path::new("/usr/sbin/mosquitto").is_file() && !require("mosquitto") {
        return;
    }
    let fbbus = fbbus_bin();
    let run = loadtest(
        &[
            "compare",
            "--quick",
            "--scenarios",
            "fanin,authstorm",
            "--fbbus",
            fbbus,
        ],
        &[],
    );
    assert!(run.success, "compare failed\n{}", run.context());
    let fanin = ratio_line(&run, "burst fan-in");
    for label in ["fbbus", "mosquitto", "rumqttd"] {
        assert!(
            matches!(rate_of(fanin, label), Some(r) if r > 0.0),
            "no {label} msg/s in {fanin}\n{}",
            run.context()
        );
    }
    assert!(fanin.contains("mosquitto (nodelay off)"), "{fanin}");
    for pair in ["fbbus/mosquitto", "fbbus/rumqttd"] {
        assert!(
            matches!(ratio(fanin, pair), Some(r) if r > 0.0),
            "no {pair} ratio in {fanin}"
        );
    }
    // Every device of every broker logged in with its password.
    let storm_rows: Vec<&str> = run
        .stdout
        .lines()
        .filter(|l| {
            ["   fbbus ", "   mosquitto ", "   rumqttd "]
                .iter()
                .any(|p| l.starts_with(p))
                && l.contains("/100 ")
        })
        .collect();
    assert_eq!(storm_rows.len(), 3, "{}", run.context());
    for row in storm_rows {
        assert!(row.contains("100/100"), "not every device connected: {row}");
    }
    let storm = ratio_line(&run, "authenticated reconnect storm");
    assert!(
        matches!(ratio(storm, "fbbus/mosquitto"), Some(r) if r > 0.0),
        "{storm}"
    );
}

/// Issue 34: the QoS 1 fan-in and the independent pairs deliver every message, and the
/// summary table has a row per scenario with the lost count next to the rate, beside
/// rumqttd with its ratio column (FlashMQ too where a `flashmq` binary is on PATH).
#[test]
fn qos1_fanin_and_pairs_in_the_summary_table() {
    let fbbus = fbbus_bin();
    let run = loadtest(
        &[
            "compare",
            "--quick",
            "--brokers",
            "fbbus,rumqttd",
            "--scenarios",
            "fanin1,pairs",
            "--fbbus",
            fbbus,
        ],
        &[],
    );
    assert!(run.success, "compare failed\n{}", run.context());
    for (title, expected) in [
        ("QoS 1 burst fan-in", "10000/10000"),
        ("independent pairs", "5000/5000"),
    ] {
        let line = ratio_line(&run, title);
        assert!(
            matches!(rate_of(line, "fbbus"), Some(r) if r > 0.0),
            "no fbbus msg/s in {line:?}\n{}",
            run.context()
        );
        let delivered = run
            .stdout
            .lines()
            .filter(|l| l.starts_with("   fbbus ") && l.contains(expected))
            .count();
        assert!(
            delivered >= 1,
            "fbbus lost messages in {title}\n{}",
            run.context()
        );
    }
    let table: Vec<&str> = run
        .stdout
        .lines()
        .skip_while(|l| !l.starts_with("== summary table"))
        .collect();
    assert!(
        table.iter().any(|l| l.contains("fbbus/rumqttd")),
        "no ratio column\n{}",
        run.context()
    );
    for row in ["fanin1 msg/s", "pairs msg/s"] {
        let line = table
            .iter()
            .find(|l| l.trim_start().starts_with(row))
            .unwrap_or_else(|| panic!("no `{row}` row\n{}", run.context()));
        assert!(line.contains("(lost 0)"), "{line}");
    }
}

/// `compare bridge --quick` links two fbbus lines over zenoh and reports the hop.
#[test]
fn quick_bridge_scenario_reports_the_hop() {
    let fbbus = fbbus_bin();
    let run = loadtest(&["compare", "bridge", "--quick", "--fbbus", fbbus], &[]);
    assert!(run.success, "compare bridge failed\n{}", run.context());
    let across = run
        .stdout
        .lines()
        .find(|l| l.starts_with("A -> B"))
        .unwrap_or_else(|| panic!("no A -> B row\n{}", run.context()));
    let cells: Vec<&str> = across.split_whitespace().collect();
    assert!(
        cells.contains(&"2000/2000"),
        "every burst message crossed: {across}"
    );
    assert!(run.stdout.contains("hop adds"), "{}", run.context());
    assert_eq!(run.file("bridge.txt"), run.stdout);
}

/// `compare bridge --bus tcp,mtls --rounds 2`: two pairs of lines per round, one linked
/// by plain TCP, one by mutual TLS with access control (certificates made by the run),
/// alternating round by round, every burst message across both, and the mtls/tcp ratios.
#[test]
fn quick_bridge_over_tcp_and_mutual_tls_alternates_and_reports_the_ratio() {
    let fbbus = fbbus_bin();
    let run = loadtest(
        &[
            "compare",
            "bridge",
            "--quick",
            "--fbbus",
            fbbus,
            "--bus",
            "tcp,mtls",
            "--rounds",
            "2",
            "--samples",
            "50",
        ],
        &[],
    );
    assert!(run.success, "compare bridge failed\n{}", run.context());
    assert!(
        run.stdout
            .contains("bus mtls: line-a listens on tls/127.0.0.1"),
        "{}",
        run.context()
    );
    // Each round: one broker, line A local (first bus), A -> B over each bus.
    let rows: Vec<(&str, Vec<&str>)> = run
        .stdout
        .lines()
        .filter_map(|l| {
            let (name, rest) = l.split_once(" #")?;
            Some((name, rest.split_whitespace().collect()))
        })
        .collect();
    let names: Vec<String> = rows
        .iter()
        .map(|(name, cells)| format!("{name} #{}", cells[0]))
        .collect();
    assert_eq!(
        names,
        [
            "one broker #1",
            "line A, local #1",
            "A -> B tcp #1",
            "A -> B mtls #1",
            "one broker #2",
            "line A, local #2",
            "A -> B tcp #2",
            "A -> B mtls #2"
        ],
        "{}",
        run.context()
    );
    for (name, cells) in &rows {
        assert!(
            cells.contains(&"2000/2000"),
            "{name}: every burst message arrived: {cells:?}"
        );
    }
    let summary = run
        .stdout
        .lines()
        .find(|l| l.starts_with("mtls/tcp"))
        .unwrap_or_else(|| panic!("no mtls/tcp line\n{}", run.context()));
    let ratio_after = |what: &str| -> f64 {
        let rest = summary
            .split_once(what)
            .unwrap_or_else(|| panic!("no {what} in {summary}"))
            .1;
        rest.split_whitespace()
            .next()
            .and_then(|t| t.strip_suffix('x'))
            .and_then(|t| t.parse().ok())
            .unwrap_or_else(|| panic!("{what} is not a ratio in {summary}"))
    };
    for what in ["p50 ", "p99 ", "burst msg/s "] {
        assert!(ratio_after(what) > 0.0, "{summary}");
    }
    for bus in ["tcp:", "mtls:"] {
        assert!(
            run.stdout.lines().any(|l| l.starts_with(bus)
                && l.contains("hop adds")
                && l.contains("lost 0 of 4000")),
            "{bus} hop line\n{}",
            run.context()
        );
    }
}

/// `compare persistence --quick`: QoS 1 throughput and latency into a persistent
/// subscriber on fbbus with its store off and under each fsync policy (and Mosquitto with
/// and without persistence where installed; CI requires it), then a restart on the store:
/// every message delivered, every retained message and the sampled session back, fbbus's
/// `store restored` figures read from its log, and the goal lines.
#[test]
fn quick_persistence_measures_the_store_and_the_restart() {
    let fbbus = fbbus_bin();
    let with_mosquitto =
        std::path::Path::new("/usr/sbin/mosquitto").is_file() || require("mosquitto");
    let mut args = vec!["compare", "persistence", "--quick", "--fbbus", fbbus];
    if !with_mosquitto {
        eprintln!("mosquitto not installed: fbbus's setups only");
        args.extend(["--brokers", "fbbus"]);
    }
    let started = Instant::now();
    let run = loadtest(&args, &[]);
    let elapsed = started.elapsed();
    assert!(run.success, "compare persistence failed\n{}", run.context());
    let mut setups = vec!["fbbus-off", "fbbus-always", "fbbus-every100ms", "fbbus-os"];
    if with_mosquitto {
        setups.extend(["mosquitto-persist", "mosquitto-nopersist"]);
    }
    let rows = |setup: &str| -> Vec<&str> {
        run.stdout
            .lines()
            .filter(|l| l.trim_start().starts_with(&format!("{setup} ")))
            .collect()
    };
    for setup in &setups {
        let rows = rows(setup);
        // --quick: 10 x 500 in the burst, 10 x 1,000 msg/s x 1 s for latency.
        assert!(
            rows.iter().any(|r| r.contains(" 5000/5000 ")),
            "{setup}: the burst was not delivered in full\n{}",
            run.context()
        );
        assert!(
            rows.iter().any(|r| r.contains(" 10000/10000 ")),
            "{setup}: the latency run was not delivered in full\n{}",
            run.context()
        );
    }
    // The restart, with the store on: 2,000 retained messages, 50 sessions with 3 queued
    // each, all back; fbbus's own log line read.
    let mut persistent = vec!["fbbus-always", "fbbus-every100ms", "fbbus-os"];
    if with_mosquitto {
        persistent.push("mosquitto-persist");
    }
    for setup in persistent {
        let restart = rows(setup)
            .into_iter()
            .find(|r| r.contains("2000/2000"))
            .unwrap_or_else(|| panic!("{setup}: no restart row\n{}", run.context()));
        assert!(restart.contains("present, 3/3"), "{setup}: {restart}");
        if setup.starts_with("fbbus") {
            assert!(restart.contains("2000/50/150"), "{setup}: {restart}");
        }
    }
    assert!(
        !rows("fbbus-off").iter().any(|r| r.contains("2000/2000")),
        "a broker without persistence has no restart row\n{}",
        run.context()
    );
    let goals: Vec<&str> = run
        .stdout
        .lines()
        .skip_while(|l| !l.starts_with("== goals"))
        .collect();
    assert!(
        goals
            .iter()
            .any(|l| l.contains(">= 0.7x fbbus-off") && l.contains('x')),
        "{}",
        run.context()
    );
    assert!(
        goals
            .iter()
            .any(|l| l.starts_with("restart of fbbus-every100ms")),
        "{}",
        run.context()
    );
    assert_eq!(run.file("persistence.txt"), run.stdout);
    assert!(
        elapsed < Duration::from_secs(60),
        "the quick smoke run took {elapsed:?}"
    );
}

/// `compare abuse --quick` (issue 21): every phase has its row with probe figures, the
/// floods did something, the broker answered throughout (no phase failed, the probe was
/// delivered), and the three goal lines say MET or NOT MET (the figures are not judged
/// here: they are the broker's, and --quick is no measurement).
#[test]
fn quick_abuse_runs_every_flood_and_states_the_goals() {
    let fbbus = fbbus_bin();
    let started = Instant::now();
    let run = loadtest(&["compare", "abuse", "--quick", "--fbbus", fbbus], &[]);
    let elapsed = started.elapsed();
    assert!(run.success, "compare abuse failed\n{}", run.context());
    let phases: Vec<&str> = run
        .stdout
        .lines()
        .skip_while(|l| !l.starts_with("== phases"))
        .collect();
    for phase in [
        "0 idle",
        "1 registry",
        "2 redeclare",
        "3 admin-poll",
        "4 slow-headers",
        "5 labels",
        "6 retained",
    ] {
        let row = phases
            .iter()
            .find(|l| l.trim_start().starts_with(phase))
            .unwrap_or_else(|| panic!("no row for {phase}\n{}", run.context()));
        let cells: Vec<&str> = row.split_whitespace().collect();
        // phase (2 words), ops, refused, p50, p99, max, p99/idle, lost, RSS, fds, KB
        assert_eq!(cells.len(), 12, "{phase}: {row}");
        assert!(
            cells[4].parse::<f64>().is_ok(),
            "{phase}: no probe p50 in {row}\n{}",
            run.context()
        );
        assert!(
            cells[10].parse::<u64>().is_ok_and(|fds| fds > 0),
            "{phase}: no fd count in {row}"
        );
        if phase != "0 idle" {
            let ops = cells[2].split('/').next().unwrap();
            assert!(
                ops.parse::<u64>().is_ok_and(|n| n > 0),
                "{phase}: no flood operations in {row}\n{}",
                run.context()
            );
        }
    }
    let slow = phases
        .iter()
        .find(|l| l.trim_start().starts_with("4 slow-headers"))
        .unwrap();
    let connects = slow.split_whitespace().nth(2).unwrap();
    // ok/tried: whether every one succeeded is the broker's figure, not the harness's.
    assert!(
        connects
            .split_once('/')
            .is_some_and(|(ok, tried)| ok.parse::<u64>().is_ok() && tried.parse::<u64>().is_ok()),
        "{slow}"
    );
    let goals: Vec<&str> = run
        .stdout
        .lines()
        .skip_while(|l| !l.starts_with("== goals"))
        .collect();
    for goal in [
        "probe p99 within 2x idle during admin polling:",
        "probe p99 within 2x idle during re-declaration:",
        "resident memory within --max-rss-mb 256 MB",
    ] {
        assert!(
            goals
                .iter()
                .any(|l| l.starts_with(goal) && (l.ends_with(" MET") || l.ends_with(" NOT MET"))),
            "no goal line `{goal}`\n{}",
            run.context()
        );
    }
    assert_eq!(run.file("abuse.txt"), run.stdout);
    assert!(
        elapsed < Duration::from_secs(90),
        "the quick smoke run took {elapsed:?}"
    );
}

//! The network campaigns `mutate` and `churn`, small and bounded, against the real `fbbus`
//! broker on a free loopback port: the broker still routes, the counts add up, memory and
//! metrics are read; and the verdict fails when the broker does not route or dies.

mod common;

use std::time::{Duration, Instant};

use loadtest::model::{Report, Summary};

use common::{loadtest, Fbbus, Mosquitto, Run};

/// One figure of a summary; panics with the figure names when it is missing.
fn figure(s: &Summary, name: &str) -> f64 {
    s.figures
        .iter()
        .find(|f| f.name == name)
        .map(|f| f.value)
        .unwrap_or_else(|| {
            let names: Vec<&str> = s.figures.iter().map(|f| f.name.as_str()).collect();
            panic!("no figure {name} in {names:?}")
        })
}

fn sum_prefixed(s: &Summary, prefix: &str) -> f64 {
    s.figures
        .iter()
        .filter(|f| f.name.starts_with(prefix))
        .map(|f| f.value)
        .sum()
}

/// What every passing campaign report must say for target `label`: `connections`
/// connections in rounds of `per_round`, each followed by a probe that routed, the broker
/// alive, every connection counted in exactly one result, memory and metrics read.
fn assert_passed(run: &Run, r: &Report, label: &str, connections: u64, per_round: u64) {
    assert!(r.failures.is_empty(), "{:?}\n{}", r.failures, run.context());
    let batches: Vec<_> = r.batches.iter().filter(|b| b.target == label).collect();
    let rounds = connections.div_ceil(per_round);
    assert_eq!(batches.len() as u64, rounds, "{}", run.context());
    for (k, b) in batches.iter().enumerate() {
        assert!(b.ok && b.error.is_none(), "{b:?}");
        let end = ((k as u64 + 1) * per_round).min(connections);
        assert_eq!(b.x as u64, end);
        assert_eq!(b.label, format!("connections {end}"));
        assert_eq!(b.sent, b.expected);
        assert_eq!(b.delivered, b.sent, "every TCP connection came up: {b:?}");
    }
    assert_eq!(batches.iter().map(|b| b.sent).sum::<u64>(), connections);
    let s = r.summaries.iter().find(|s| s.target == label).unwrap();
    assert_eq!(figure(s, "connections"), connections as f64);
    // Every connection began exactly one way.
    assert_eq!(
        sum_prefixed(s, "result_"),
        connections as f64,
        "{:?}",
        s.figures
    );
    assert_eq!(figure(s, "result_tcp_failed"), 0.0);
    assert_eq!(figure(s, "result_timed_out"), 0.0);
    assert!(figure(s, "result_connack_accepted") > 0.0);
    // Probes: before, after every round, after the settle.
    assert_eq!(figure(s, "probes_ok"), (rounds + 2) as f64);
    assert_eq!(figure(s, "probes_failed"), 0.0);
    assert_eq!(figure(s, "crashes"), 0.0);
    assert!(figure(s, "packets_sent") >= figure(s, "valid_connects"));
    assert!(figure(s, "bytes_sent") > 0.0);
    for when in ["before", "after", "settled"] {
        assert!(figure(s, &format!("rss_{when}_kib")) > 0.0);
        assert!(figure(s, &format!("fds_{when}")) > 0.0);
    }
    assert!(figure(s, "rss_settled_ratio") > 0.0);
}

/// The broker's own counters, scraped before and after: it saw the campaign's connects.
fn assert_metrics(s: &Summary, connections: u64) {
    let accepted_before = figure(s, "fbbus_connects_total before");
    let accepted_after = figure(s, "fbbus_connects_total after");
    // The probes' clients connect too: at least what the campaign saw accepted.
    assert!(
        accepted_after - accepted_before >= figure(s, "result_connack_accepted"),
        "{accepted_before} -> {accepted_after}"
    );
    assert!(accepted_after - accepted_before <= connections as f64 + 20.0);
    assert_eq!(
        figure(s, "fbbus_connections settled"),
        0.0,
        "{:?}",
        s.figures
    );
}

#[test]
fn mutate_leaves_fbbus_routing_and_counts_add_up() {
    let fbbus = Fbbus::start();
    let started = Instant::now();
    let metrics = fbbus.metrics_url();
    let run = loadtest(
        &[
            "--broker",
            &fbbus.url(),
            "mutate",
            "--connections",
            "300",
            "--probe-every",
            "100",
            "--concurrency",
            "16",
            "--settle-s",
            "1",
            "--seed",
            "14",
            "--metrics",
            &metrics,
        ],
        &[],
    );
    let r = run.ok();
    assert!(
        started.elapsed() < Duration::from_secs(20),
        "{:?}",
        started.elapsed()
    );
    assert_eq!(r.scenario, "mutate");
    assert_eq!(r.params["connections"], 300);
    assert_eq!(r.params["seed"], 14);
    assert_passed(&run, &r, "A", 300, 100);
    let s = &r.summaries[0];
    assert_metrics(s, 300);
    // It did mutate, in more than one way, and the broker closed some connections for it.
    assert!(figure(s, "packets_mutated") > 0.0);
    let kinds = s
        .figures
        .iter()
        .filter(|f| f.name.starts_with("mutation_") && f.value > 0.0)
        .count();
    assert!(kinds >= 10, "{:?}", s.figures);
    assert!(figure(s, "closed_by_broker") > 0.0);
    assert!(figure(s, "fbbus_malformed_packets_total after") > 0.0);
    // The table says it, and there is no failure line.
    assert!(run.stdout.contains("scenario mutate"), "{}", run.stdout);
    assert!(
        run.stdout.contains("A fbbus: probes_ok = 5"),
        "{}",
        run.stdout
    );
    assert!(!run.stdout.contains("FAILED"), "{}", run.stdout);
    // The broker itself lived through it and still logs no panic.
    assert!(
        !fbbus.log_text().contains("panicked"),
        "{}",
        fbbus.log_text()
    );
}

#[test]
fn churn_leaves_fbbus_routing_and_counts_add_up() {
    let fbbus = Fbbus::start();
    let started = Instant::now();
    let metrics = fbbus.metrics_url();
    let run = loadtest(
        &[
            "--broker",
            &fbbus.url(),
            "churn",
            "--connections",
            "1000",
            "--probe-every",
            "500",
            "--concurrency",
            "32",
            "--recurring-ids",
            "20",
            "--settle-s",
            "1",
            "--metrics",
            &metrics,
        ],
        &[],
    );
    let r = run.ok();
    assert!(
        started.elapsed() < Duration::from_secs(20),
        "{:?}",
        started.elapsed()
    );
    assert_eq!(r.scenario, "churn");
    assert_passed(&run, &r, "A", 1000, 500);
    let s = &r.summaries[0];
    assert_metrics(s, 1000);
    // Every kind ran, both protocol versions, and the kinds add up to the connections.
    for kind in [
        "valid",
        "pipelined",
        "persistent_random",
        "persistent_recurring",
        "abrupt",
        "malformed",
        "abandoned",
    ] {
        assert!(figure(s, &format!("kind_{kind}")) > 0.0, "{kind}");
    }
    assert_eq!(sum_prefixed(s, "kind_"), 1000.0);
    assert_eq!(figure(s, "mqtt_5") + figure(s, "mqtt_3_1_1"), 1000.0);
    // Every accepted pipelined connection is counted as closed or left open by the broker
    // (fbbus leaves open those whose packets came in the read that completed the CONNECT:
    // it handles them only when more bytes arrive).
    let pipelined: f64 = s
        .figures
        .iter()
        .filter(|f| f.name.ends_with("_closed") || f.name.ends_with("_left_open"))
        .map(|f| f.value)
        .sum();
    assert!(pipelined > 0.0 && pipelined <= figure(s, "kind_pipelined"));
    // Abandoned connections are never awaited.
    assert_eq!(figure(s, "result_not_awaited"), figure(s, "kind_abandoned"));
    // Valid CONNECTs are accepted, but not quite all: two CONNECTs of one recurring id
    // that reach fbbus's router together get the first refused (CONNACK 3, "router
    // refused the connection: Channel recv error", fbbus_connects_refused_total
    // {reason="router_refused"}) instead of accepted and then taken over.
    let valid = figure(s, "valid_connects");
    assert!(valid > 0.0);
    assert!(
        figure(s, "valid_connects_accepted") >= 0.9 * valid,
        "{:?}",
        s.figures
    );
    // The persistent connections left saved sessions in the router.
    assert!(
        figure(s, "fbbus_router_saved_sessions after") > 0.0,
        "{:?}",
        s.figures
    );
    assert!(
        !fbbus.log_text().contains("panicked"),
        "{}",
        fbbus.log_text()
    );
}

/// A broker that accepts connections but does not route wildcard subscriptions (the
/// harness's own trivial sink) fails the campaign before it starts: exit 1, the report
/// written, the reason in it.
#[test]
fn a_broker_that_does_not_route_fails_the_campaign() {
    let runtime = tokio::runtime::Runtime::new().unwrap();
    let sink = runtime.block_on(loadtest::sink::Sink::start()).unwrap();
    let run = loadtest(
        &[
            "--broker",
            &format!("mqtt://{}", sink.addr),
            "mutate",
            "--connections",
            "50",
            "--settle-s",
            "0",
            "--probe-timeout-ms",
            "500",
        ],
        &[],
    );
    assert!(!run.success, "{}", run.context());
    let r = run.report();
    assert_eq!(r.failures.len(), 1, "{:?}", r.failures);
    assert!(
        r.failures[0].starts_with("A: the broker did not route before the campaign"),
        "{:?}",
        r.failures
    );
    assert!(run.stdout.contains("FAILED: A: the broker did not route"));
    assert!(run.stderr.contains("mutate failed"), "{}", run.stderr);
    assert!(r.batches.is_empty());
}

/// The broker killed during the campaign: the campaign says it crashed and exits 1.
#[test]
fn a_broker_that_dies_during_the_campaign_fails_it() {
    let fbbus = Fbbus::start();
    let pid = fbbus.pid().to_string();
    let url = fbbus.url();
    let run = std::thread::scope(|scope| {
        let campaign = scope.spawn(|| {
            loadtest(
                &[
                    "--broker",
                    &url,
                    "churn",
                    "--pid",
                    &pid,
                    "--connections",
                    "200000",
                    "--probe-every",
                    "500",
                    "--concurrency",
                    "16",
                    "--duration",
                    "15s",
                    "--settle-s",
                    "0",
                    "--probe-timeout-ms",
                    "1000",
                    "--connack-ms",
                    "1000",
                ],
                &[],
            )
        });
        std::thread::sleep(Duration::from_millis(1500));
        fbbus.kill_now();
        campaign.join().unwrap()
    });
    assert!(!run.success, "{}", run.context());
    let r = run.report();
    assert!(
        r.failures
            .iter()
            .any(|f| f.contains(&format!("broker process {pid} exited (crashed)"))),
        "{:?}\n{}",
        r.failures,
        run.context()
    );
    let s = &r.summaries[0];
    assert_eq!(figure(s, "crashes"), 1.0);
    assert!(figure(s, "connections") < 200_000.0);
    // The failed round is the last one, and it is marked failed.
    assert!(!r.batches.last().unwrap().ok);
}

/// Side by side with Mosquitto (compare mode): both brokers get the same campaign, rounds
/// interleaved, each judged on its own.
#[test]
fn mutate_compares_fbbus_and_mosquitto() {
    let fbbus = Fbbus::start();
    let Some(mosquitto) = Mosquitto::start() else {
        return;
    };
    let run = loadtest(
        &[
            "--broker",
            &fbbus.url(),
            "--compare",
            &mosquitto.url(),
            "mutate",
            "--connections",
            "200",
            "--probe-every",
            "100",
            "--concurrency",
            "16",
            "--settle-s",
            "1",
        ],
        &[],
    );
    let r = run.ok();
    let order: Vec<&str> = r.batches.iter().map(|b| b.target.as_str()).collect();
    assert_eq!(order, ["A", "B", "A", "B"]);
    assert_passed(&run, &r, "A", 200, 100);
    assert_passed(&run, &r, "B", 200, 100);
    assert_eq!(r.targets[1].name, "mosquitto");
    assert!(r
        .ratios
        .iter()
        .any(|x| x.figure.starts_with("connections ")));
}

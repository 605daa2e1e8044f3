//! The conveyor scenario, TLS targets and `render`, against real brokers on loopback.

mod common;

use std::path::Path;

use common::{loadtest, parse_csv, svg_series, Fbbus, Mosquitto};
use rcgen::{BasicConstraints, CertificateParams, DnType, IsCa, KeyPair, KeyUsagePurpose};

/// A line of fb-bridge devices passes every part to its end; a broker without the fbbus
/// device contract runs no line and the report says why.
#[test]
fn conveyor_passes_every_part_and_skips_a_plain_broker() {
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
            "conveyor",
            "--devices",
            "2,3",
            "--parts",
            "20",
            "--repeats",
            "1",
        ],
        &[],
    );
    let r = run.ok();
    assert_eq!(r.scenario, "conveyor");
    let a: Vec<_> = r.batches.iter().filter(|b| b.target == "A").collect();
    assert_eq!(a.iter().map(|b| b.x as u64).collect::<Vec<_>>(), vec![2, 3]);
    for b in &a {
        assert_eq!((b.sent, b.expected, b.delivered), (20, 20, 20), "{b:?}");
        assert_eq!(b.delivered_fb, Some(20));
        assert!(b.ok && b.duplicates == 0 && b.out_of_order == 0, "{b:?}");
        assert_eq!(b.latency.count, 20);
    }
    assert!(r.batches.iter().all(|b| b.target == "A"), "B ran a line");
    assert!(
        r.notes
            .iter()
            .any(|n| n.starts_with("B: no conveyor line") && n.contains("device contract")),
        "{:?}",
        r.notes
    );
    // No ratios against a broker that ran nothing.
    assert!(r.ratios.is_empty(), "{:?}", r.ratios);
    let svg = run.file("throughput.svg");
    assert_eq!(svg_series(&svg, "fbbus").map(|p| p.len()), Some(2));
}

/// Writes a CA and a server certificate for localhost/127.0.0.1 into `dir`.
fn write_pki(dir: &Path) {
    let ca_key = KeyPair::generate().unwrap();
    let mut ca = CertificateParams::new(Vec::<String>::new()).unwrap();
    ca.is_ca = IsCa::Ca(BasicConstraints::Unconstrained);
    ca.distinguished_name
        .push(DnType::CommonName, "loadtest test CA");
    ca.key_usages = vec![
        KeyUsagePurpose::KeyCertSign,
        KeyUsagePurpose::DigitalSignature,
    ];
    let ca = ca.self_signed(&ca_key).unwrap();
    let key = KeyPair::generate().unwrap();
    let mut server = CertificateParams::new(vec!["localhost".into(), "127.0.0.1".into()]).unwrap();
    server
        .distinguished_name
        .push(DnType::CommonName, "localhost");
    server.use_authority_key_identifier_extension = true;
    let server = server.signed_by(&key, &ca, &ca_key).unwrap();
    std::fs::write(dir.join("ca.crt"), ca.pem()).unwrap();
    std::fs::write(dir.join("server.crt"), server.pem()).unwrap();
    std::fs::write(dir.join("server.key"), key.serialize_pem()).unwrap();
}

/// `mqtts://` with `--ca`: every message delivered over TLS; the FB subscriber (plain
/// MQTT only) is left out with a note instead of failing the run; without the CA the run
/// refuses with advice.
#[test]
fn tls_target_with_ca() {
    let fbbus = common::fbbus_with(
        "tls",
        "",
        "[listener.tls]\ncert = \"server.crt\"\nkey = \"server.key\"\n",
        "",
        write_pki,
    );
    let url = fbbus.url().replace("mqtt://127.0.0.1", "mqtts://localhost");
    let ca = fbbus.dir.path().join("ca.crt");
    let run = loadtest(
        &[
            "--broker",
            &url,
            "--ca",
            ca.to_str().unwrap(),
            "--mqtt",
            "5",
            "--qos",
            "1",
            "stress",
            "--max",
            "20",
            "--repeats",
            "1",
        ],
        &[],
    );
    let r = run.ok();
    assert_eq!(r.targets[0].address, url);
    assert_eq!(r.batches.len(), 2);
    for b in &r.batches {
        assert_eq!(
            (b.sent, b.delivered, b.delivered_fb),
            (b.x as u64, b.x as u64, None),
            "{b:?}"
        );
        assert!(b.ok);
    }
    assert!(
        r.notes.iter().any(|n| n.contains("plain MQTT only")),
        "{:?}",
        r.notes
    );

    let refused = loadtest(&["--broker", &url, "stress", "--max", "10"], &[]);
    assert!(!refused.success);
    assert!(refused.stderr.contains("--ca"), "{}", refused.stderr);
}

/// `render` writes the same files again from a report.json, and the table.
#[test]
fn render_rebuilds_the_outputs_from_report_json() {
    let fbbus = Fbbus::start();
    let run = loadtest(
        &[
            "--broker",
            &fbbus.url(),
            "stress",
            "--max",
            "20",
            "--repeats",
            "1",
        ],
        &[],
    );
    run.ok();
    // Into the helper's own --out directory: a different one.
    let rendered = loadtest(&["render", run.path("report.json").to_str().unwrap()], &[]);
    assert!(rendered.success, "{}", rendered.stderr);
    assert!(rendered.stdout.contains("burst 20"), "{}", rendered.stdout);
    // The same rows and cells; floats may differ in their last digit (report.json keeps
    // 17 significant digits, serde_json reads them back to the nearest double only
    // approximately without its float_roundtrip feature).
    for file in ["batches.csv", "batches.jtl"] {
        let (original, copy) = (parse_csv(&run.file(file)), parse_csv(&rendered.file(file)));
        assert_eq!(original.len(), copy.len(), "{file}: rows");
        for (a, b) in original.iter().zip(&copy) {
            assert_eq!(a.len(), b.len(), "{file}: cells");
            for (x, y) in a.iter().zip(b) {
                let same = match (x.parse::<f64>(), y.parse::<f64>()) {
                    (Ok(x), Ok(y)) => (x - y).abs() <= 1e-9 * x.abs().max(1.0),
                    _ => x == y,
                };
                assert!(same, "{file}: {x} vs {y}");
            }
        }
    }
    for chart in ["stress.svg", "delivery-rate.svg"] {
        for series in ["fbbus", "sent"] {
            assert_eq!(
                svg_series(&run.file(chart), series).map(|p| p.len()),
                svg_series(&rendered.file(chart), series).map(|p| p.len()),
                "{chart}: {series}"
            );
        }
    }
    assert_eq!(rendered.report().scenario, "stress");
}

/// `--payload` sets the message size (the smallest message carries seq and timestamp),
/// at every QoS, and the report records the size used.
#[test]
fn payload_size_and_qos_2() {
    let fbbus = Fbbus::start();
    let run = loadtest(
        &[
            "--broker",
            &fbbus.url(),
            "--payload",
            "2000",
            "--qos",
            "2",
            "perf",
            "--max",
            "5",
            "--points",
            "2",
            "--repeats",
            "1",
        ],
        &[],
    );
    let r = run.ok();
    assert_eq!(r.params["payload_bytes"], 2000);
    assert_eq!(r.params["qos"], 2);
    let delivered: Vec<(u64, u64)> = r.batches.iter().map(|b| (b.sent, b.delivered)).collect();
    assert_eq!(delivered, vec![(1, 1), (5, 5)]);
    // The bytes were really on the wire: 6 messages of 2,000 bytes in. Out, fbbus's
    // subscribers of fb/ get the canonical event (issue 21: whitespace is not canonical
    // JSON), so each delivery is the compact event, at least its 31 bytes.
    assert!(fbbus.metric("fbbus_bytes_received_total") >= 6.0 * 2000.0);
    assert!(fbbus.metric("fbbus_messages_sent_total") >= 6.0);
    assert!(fbbus.metric("fbbus_bytes_sent_total") >= 6.0 * 31.0);
    // Below the floor the message is as small as it can be, and says so.
    let run = loadtest(
        &[
            "--broker",
            &fbbus.url(),
            "--payload",
            "1",
            "stress",
            "--max",
            "10",
            "--repeats",
            "1",
        ],
        &[],
    );
    assert_eq!(
        run.ok().params["payload_bytes"],
        loadtest::message::MIN_SIZE
    );
}

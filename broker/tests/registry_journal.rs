//! Issue 21: the registry is written incrementally. A change is one line appended to the
//! journal beside the snapshot (`fbbus-registry.json.log`), synced within 200 ms; the
//! snapshot is rewritten (and the journal emptied) only once the journal outgrows it; a
//! crash (SIGKILL) loses nothing that was synced, and a torn last line is cut off with a
//! warning, not a refusal to start.

mod common;

use std::io::Write;
use std::time::{Duration, Instant};

use common::fb::*;
use common::{Broker, Options};

const SNAPSHOT: &str = "fbbus-registry.json";
const JOURNAL: &str = "fbbus-registry.json.log";

fn read(broker: &Broker, name: &str) -> String {
    std::fs::read_to_string(broker.path(name)).unwrap_or_default()
}

async fn wait_file(broker: &Broker, name: &str, what: &str, ok: impl Fn(&str) -> bool) {
    let deadline = Instant::now() + Duration::from_secs(10);
    while !ok(&read(broker, name)) {
        assert!(
            Instant::now() < deadline,
            "{name}: never {what}\n--- broker log\n{}",
            broker.log_text()
        );
        tokio::time::sleep(Duration::from_millis(20)).await;
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn the_registry_journal_survives_a_crash_compacts_and_tolerates_a_torn_tail() {
    // 151 devices from one address: past the default `max_devices_per_identity` (100).
    let mut broker = Broker::start_with(
        Options {
            extra: "[fb]\nmax_devices_per_identity = 1000\n".into(),
            ..Options::default()
        },
        |_| {},
    );
    let mut sub = observer(&broker, "watch", &["fbbus/diag/#"]).await;

    // One declaration: one line in the journal, no snapshot rewritten.
    let mut first = Dev::connect(broker.port(), 5, "dev-0");
    declare_ok(&mut first, CONV, &mut sub, &broker).await;
    wait_file(&broker, JOURNAL, "has dev-0", |t| t.contains("\"dev-0\"")).await;
    let journal = read(&broker, JOURNAL);
    assert_eq!(journal.lines().count(), 1, "{journal}");
    assert!(
        !broker.path(SNAPSHOT).exists(),
        "no snapshot for one change"
    );

    // Enough declarations to outgrow the compaction floor (64 KiB): the snapshot is
    // written with every device, and the journal emptied of what it holds.
    let mut devices = vec![first];
    for i in 1..150 {
        let mut dev = Dev::connect(broker.port(), 5, &format!("dev-{i}"));
        assert_eq!(dev.declare(CONV), 0);
        devices.push(dev);
    }
    wait_file(&broker, SNAPSHOT, "compacted", |t| t.contains("\"dev-10\"")).await;
    // The snapshot is renamed into place before the journal is emptied: wait for both.
    wait_file(&broker, JOURNAL, "emptied at compaction", |t| {
        t.len() < 64 * 1024
    })
    .await;
    let journal = read(&broker, JOURNAL);
    assert!(
        journal.len() < 64 * 1024,
        "the journal was emptied at compaction: {} bytes",
        journal.len()
    );

    // A change after the compaction is in the journal only; then a crash.
    let mut last = Dev::connect(broker.port(), 5, "dev-last");
    declare_ok(&mut last, CONV, &mut sub, &broker).await;
    wait_file(&broker, JOURNAL, "has dev-last", |t| {
        t.contains("\"dev-last\"")
    })
    .await;
    assert!(!read(&broker, SNAPSHOT).contains("dev-last"));
    drop(sub);
    broker.signal("KILL");
    common::wait_until(&mut broker.child, Duration::from_secs(15)).expect("killed");
    drop(devices);
    drop(last);

    // The crash cut the last append short.
    let mut journal = std::fs::OpenOptions::new()
        .append(true)
        .open(broker.path(JOURNAL))
        .unwrap();
    journal
        .write_all(br#"{"device":{"seq":999999,"record":{"id":"ghost","li"#)
        .unwrap();
    drop(journal);
    broker.start_again();

    // Every device is back (offline, "broker restart"), from the snapshot and the journal;
    // the torn line is not.
    for id in ["dev-0", "dev-77", "dev-149", "dev-last"] {
        let rec = record(&broker, id).unwrap_or_else(|| panic!("{id} lost"));
        assert_eq!(rec["status"], "offline", "{rec}");
        assert_eq!(rec["last_will_reason"], "broker restart", "{rec}");
        assert_eq!(
            rec["interface"]["fbs"]["CONV"]["data_out"]["POSITION"],
            "INT"
        );
    }
    assert_eq!(record(&broker, "ghost"), None);
    let log = broker.log_text();
    assert!(log.contains("registry journal: a torn"), "{log}");
    let journal = read(&broker, JOURNAL);
    assert!(
        journal.ends_with('\n') && !journal.contains("ghost"),
        "{journal}"
    );
    let torn: Vec<_> = std::fs::read_dir(broker.dir.path())
        .unwrap()
        .filter_map(|e| e.ok())
        .filter(|e| e.file_name().to_string_lossy().contains(".log.torn-"))
        .collect();
    assert_eq!(torn.len(), 1, "the torn tail is kept beside the journal");

    // And the journal goes on after the last whole line.
    let mut sub = observer(&broker, "watch2", &["fbbus/diag/#"]).await;
    let mut again = Dev::connect(broker.port(), 5, "dev-again");
    declare_ok(&mut again, CONV, &mut sub, &broker).await;
    wait_file(&broker, JOURNAL, "has dev-again", |t| {
        t.contains("\"dev-again\"")
    })
    .await;
    for line in read(&broker, JOURNAL).lines() {
        serde_json::from_str::<serde_json::Value>(line).unwrap_or_else(|e| panic!("{e}: {line}"));
    }

    // A forgotten device is journaled as removed: a crash does not bring it back.
    assert_eq!(forget(&broker, "dev-0"), 200);
    wait_file(&broker, JOURNAL, "has dev-0's removal", |t| {
        t.contains("\"removed\"") && t.contains("\"dev-0\"")
    })
    .await;
    drop(sub);
    drop(again);
    broker.signal("KILL");
    common::wait_until(&mut broker.child, Duration::from_secs(15)).expect("killed");
    broker.start_again();
    assert_eq!(record(&broker, "dev-0"), None, "forgotten before the crash");
    assert!(record(&broker, "dev-77").is_some());
}

/// `DELETE /api/v1/devices/<id>`: the answer's status code.
fn forget(broker: &Broker, id: &str) -> u16 {
    use std::io::Read;
    let mut s = std::net::TcpStream::connect(broker.admin).unwrap();
    s.set_read_timeout(Some(Duration::from_secs(5))).unwrap();
    write!(
        s,
        "DELETE /api/v1/devices/{id} HTTP/1.0\r\nHost: localhost\r\n\r\n"
    )
    .unwrap();
    let mut text = String::new();
    s.read_to_string(&mut text).unwrap();
    text.split_whitespace().nth(1).unwrap().parse().unwrap()
}

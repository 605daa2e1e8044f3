//! The broker process's resident memory, as the memory tests read it: against the
//! process's own baseline, never against time.

use std::time::Duration;

use fbbus_testkit::Broker;

/// The broker's resident memory now, in KiB (VmRSS of /proc/<pid>/status).
pub fn vm_rss_kib(broker: &Broker) -> u64 {
    let status = std::fs::read_to_string(format!("/proc/{}/status", broker.child.id()))
        .expect("/proc/<pid>/status");
    status
        .lines()
        .find_map(|l| l.strip_prefix("VmRSS:"))
        .and_then(|v| v.trim().trim_end_matches("kB").trim().parse().ok())
        .expect("VmRSS")
}

/// The lowest of the broker's VmRSS over `over`, read every 100 ms: its resident memory
/// once freed pages went back. The broker's jemalloc returns freed pages about a second
/// after they were freed (`broker/src/memory.rs`), later on a busy machine; what a burst
/// left behind is what stays once they went.
pub fn settled_rss_kib(broker: &Broker, over: Duration) -> u64 {
    let readings = (over.as_millis() / 100).max(1);
    let mut lowest = u64::MAX;
    for _ in 0..readings {
        lowest = lowest.min(vm_rss_kib(broker));
        std::thread::sleep(Duration::from_millis(100));
    }
    lowest
}

//! The broker's process. Found on this machine by the TCP port it listens on, so its
//! resident memory can be read (`/proc/<pid>/status` VmRSS): Linux only; where it cannot
//! be found (another host, another user's process, no /proc) the memory figures are left
//! out and the report says why. Or started by the harness itself ([`spawn`], with raw
//! rumqttd in [`rumqttd`]) for `compare`, which then knows the pid.

pub mod rumqttd;
pub mod spawn;

use std::fs;

/// The pid of the process listening on TCP `port`, if this machine has one we can see.
pub fn pid_listening_on(port: u16) -> Option<u32> {
    let inodes: Vec<String> = ["/proc/net/tcp", "/proc/net/tcp6"]
        .iter()
        .filter_map(|f| fs::read_to_string(f).ok())
        .flat_map(|text| listening_inodes(&text, port))
        .collect();
    if inodes.is_empty() {
        return None;
    }
    let wanted: Vec<String> = inodes.iter().map(|i| format!("socket:[{i}]")).collect();
    for entry in fs::read_dir("/proc").ok()?.flatten() {
        let Some(pid) = entry
            .file_name()
            .to_str()
            .and_then(|s| s.parse::<u32>().ok())
        else {
            continue;
        };
        let Ok(fds) = fs::read_dir(entry.path().join("fd")) else {
            continue;
        };
        for fd in fds.flatten() {
            if let Ok(link) = fs::read_link(fd.path()) {
                if wanted.iter().any(|w| link.as_os_str() == w.as_str()) {
                    return Some(pid);
                }
            }
        }
    }
    None
}

/// Inodes of sockets in state LISTEN (0A) on `port` in a /proc/net/tcp table.
fn listening_inodes(table: &str, port: u16) -> Vec<String> {
    table
        .lines()
        .skip(1)
        .filter_map(|line| {
            let f: Vec<&str> = line.split_whitespace().collect();
            let local_port = f.get(1)?.rsplit(':').next()?;
            (u16::from_str_radix(local_port, 16).ok()? == port && *f.get(3)? == "0A")
                .then(|| f.get(9).map(|s| s.to_string()))?
        })
        .collect()
}

/// Resident memory of `pid` in KiB.
pub fn rss_kib(pid: u32) -> Option<u64> {
    let status = fs::read_to_string(format!("/proc/{pid}/status")).ok()?;
    status
        .lines()
        .find_map(|l| l.strip_prefix("VmRSS:"))
        .and_then(|v| v.split_whitespace().next()?.parse().ok())
}

/// A `/proc/<pid>/status` field in KiB (`VmRSS`, `VmHWM`: the peak resident memory).
pub fn status_kib(pid: u32, field: &str) -> Option<u64> {
    status_number(pid, field)
}

/// The first number of a `/proc/<pid>/status` field (`Threads`, `VmRSS` in KiB).
pub fn status_number(pid: u32, field: &str) -> Option<u64> {
    let status = fs::read_to_string(format!("/proc/{pid}/status")).ok()?;
    status
        .lines()
        .find_map(|l| l.strip_prefix(field)?.strip_prefix(':'))
        .and_then(|v| v.split_whitespace().next()?.parse().ok())
}

/// Whether `pid` is still running: it exists and is not a zombie (a crashed child of
/// this process that nobody reaped yet).
pub fn alive(pid: u32) -> bool {
    fs::read_to_string(format!("/proc/{pid}/status")).is_ok_and(|s| {
        s.lines()
            .find_map(|l| l.strip_prefix("State:"))
            .is_some_and(|state| !state.trim_start().starts_with(['Z', 'X']))
    })
}

/// File descriptors `pid` has open (sockets included), when its `/proc/<pid>/fd` is
/// readable (same user or root).
pub fn open_fds(pid: u32) -> Option<u64> {
    Some(fs::read_dir(format!("/proc/{pid}/fd")).ok()?.count() as u64)
}

/// The process's name (`mosquitto`, `fbbus`).
pub fn name(pid: u32) -> Option<String> {
    fs::read_to_string(format!("/proc/{pid}/comm"))
        .ok()
        .map(|s| s.trim().to_owned())
}

/// CPU time `pid`'s live threads have run, in nanoseconds, by thread name (`comm`:
/// `router-0`, `fbbus-store`, `fbbus` for the runtime's workers), from each thread's
/// `/proc/<pid>/task/<tid>/schedstat` (nanosecond resolution, unlike `stat`'s ticks).
/// Empty where it cannot be read. A thread that ended between two readings drops out.
pub fn cpu_ns_by_thread(pid: u32) -> std::collections::BTreeMap<String, u64> {
    let mut out = std::collections::BTreeMap::new();
    let Ok(tasks) = fs::read_dir(format!("/proc/{pid}/task")) else {
        return out;
    };
    for task in tasks.flatten() {
        let dir = task.path();
        let ns = fs::read_to_string(dir.join("schedstat"))
            .ok()
            .and_then(|s| s.split_whitespace().next()?.parse::<u64>().ok());
        let name = fs::read_to_string(dir.join("comm")).map(|n| n.trim().to_owned());
        if let (Some(ns), Ok(name)) = (ns, name) {
            *out.entry(name).or_insert(0) += ns;
        }
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn finds_this_process_listening() {
        let listener = std::net::TcpListener::bind("127.0.0.1:0").unwrap();
        let port = listener.local_addr().unwrap().port();
        assert_eq!(pid_listening_on(port), Some(std::process::id()));
        assert!(rss_kib(std::process::id()).unwrap() > 0);
        let me = std::process::id();
        assert!(status_kib(me, "VmHWM").unwrap() >= status_kib(me, "VmRSS").unwrap() / 2);
        assert!(status_number(me, "Threads").unwrap() >= 1);
        assert!(open_fds(me).unwrap() >= 3);
        assert!(alive(me));
        assert!(!alive(u32::MAX));
        drop(listener);
        assert_eq!(pid_listening_on(port), None);
    }

    #[test]
    fn reads_cpu_time_by_thread_name() {
        let me = std::process::id();
        let spin = std::thread::Builder::new()
            .name("cpu-probe".into())
            .spawn(|| {
                let t = std::time::Instant::now();
                let mut x = 0u64;
                while t.elapsed() < std::time::Duration::from_millis(30) {
                    x = std::hint::black_box(x.wrapping_add(1));
                }
                cpu_ns_by_thread(std::process::id())
            })
            .unwrap()
            .join()
            .unwrap();
        assert!(
            spin.get("cpu-probe").is_some_and(|ns| *ns >= 10_000_000),
            "{spin:?}"
        );
        assert!(cpu_ns_by_thread(u32::MAX).is_empty());
        assert!(!cpu_ns_by_thread(me).is_empty());
    }
}

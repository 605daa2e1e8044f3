//! Free loopback ports for the brokers and listeners a test starts.

use std::net::TcpListener;

/// A TCP port on 127.0.0.1 that was free a moment ago, below Linux's ephemeral range.
///
/// Why not `bind(0)`: the kernel hands out ports for outgoing connections (every client a
/// test opens, thousands in the storm tests) from that same ephemeral range (32768-60999
/// by default); a port picked there and released could be taken by a client's connect
/// before the broker bound it, and the broker failed to start with `Address already in
/// use` (seen in CI). Ports 20000-32767 are never handed out that way; they are tried in
/// a pseudo-random order, so parallel tests rarely try the same one.
pub fn free_port() -> u16 {
    use std::sync::atomic::{AtomicU64, Ordering};
    static NEXT: AtomicU64 = AtomicU64::new(0);
    // Never the same port twice in one test process: a port handed out and not bound yet
    // (a test picks its listeners' ports before the broker starts) looks free to the next
    // caller too, and two of them once got one port (CI: `Address already in use`).
    static GIVEN: std::sync::Mutex<Vec<u16>> = std::sync::Mutex::new(Vec::new());
    let mut given = GIVEN
        .lock()
        .unwrap_or_else(std::sync::PoisonError::into_inner);
    let seed = std::time::SystemTime::now()
        .duration_since(std::time::UNIX_EPOCH)
        .map_or(0, |d| d.as_nanos() as u64)
        ^ (u64::from(std::process::id()) << 20);
    for _ in 0..1000 {
        let n = NEXT.fetch_add(0x9E37_79B9_7F4A_7C15, Ordering::Relaxed) ^ seed;
        let port = 20_000 + (n.wrapping_mul(0xBF58_476D_1CE4_E5B9) >> 33) % 12_768;
        let port = port as u16;
        if !given.contains(&port) && TcpListener::bind(("127.0.0.1", port)).is_ok() {
            given.push(port);
            return port;
        }
    }
    TcpListener::bind("127.0.0.1:0")
        .unwrap()
        .local_addr()
        .unwrap()
        .port()
}

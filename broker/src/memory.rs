//! Giving freed memory back to the operating system.
//!
//! A burst leaves the broker with memory it no longer uses: commit-log segments every
//! subscriber has read (freed by the router, see `router`), batch buffers of busy
//! connections, the 8 MiB argon2id blocks of a reconnect storm's logins. Rust frees it to glibc's malloc, which keeps freed pages mapped for
//! reuse: only the top of the main heap is returned by itself, and pages in the middle of a
//! heap or in the per-thread arenas of tokio's workers and the router thread stay resident
//! indefinitely. So after a burst of a million messages the process would keep its peak
//! resident size although nothing is allocated there any more.
//!
//! `malloc_trim(0)` walks every arena and returns its free pages (madvise) to the OS. It
//! takes a few milliseconds for a large heap and holds each arena's lock meanwhile, so it
//! is only called after the router released memory: when it has been quiet for a moment
//! (`router::IDLE_AFTER`, once per quiet period) or every `router::RELEASE_EVERY` under
//! steady traffic, never per packet.

/// Allocations at least this large get pages of their own (mmap), returned on free.
const MMAP_THRESHOLD: usize = 1024 * 1024;

/// Free memory at the top of a heap beyond this is returned on free.
const TRIM_THRESHOLD: usize = 4 * 1024 * 1024;

/// Fixes glibc's thresholds for large allocations. Call once, before other threads start.
///
/// By default glibc raises its mmap threshold to the size of every large block freed, up to
/// 32 MiB, and its trim threshold to twice that. After one burst, a commit-log segment's
/// entry vector (tens of MiB) is then allocated inside a thread's arena instead of getting
/// pages of its own; freed, it merges with the free space at the top of that arena, which
/// `malloc_trim` does not return for arenas other than the main one, and which the free
/// path only shrinks beyond the (now 64 MiB) trim threshold. The broker's resident size
/// after a million messages then came out at 30 MB or at 95 MB from run to run, depending
/// on where the last segment happened to lie. With fixed thresholds a block of 1 MiB or more
/// is mapped on its own and unmapped when freed, and an arena keeps at most 4 MiB free at
/// its top. The price: every argon2id login's 8 MiB working block is mapped fresh.
pub fn configure() {
    #[cfg(all(target_os = "linux", target_env = "gnu"))]
    // SAFETY: mallopt only sets allocator parameters; it is called before other threads
    // allocate (and would be safe even then: glibc takes its own locks).
    unsafe {
        libc::mallopt(libc::M_MMAP_THRESHOLD, MMAP_THRESHOLD as libc::c_int);
        libc::mallopt(libc::M_TRIM_THRESHOLD, TRIM_THRESHOLD as libc::c_int);
    }
}

/// Returns the allocator's free pages to the OS (glibc only; elsewhere a no-op).
pub fn release_freed() {
    #[cfg(all(target_os = "linux", target_env = "gnu"))]
    // SAFETY: malloc_trim only releases memory malloc holds free; it takes the arenas'
    // locks itself and may be called from any thread at any time.
    unsafe {
        libc::malloc_trim(0);
    }
}

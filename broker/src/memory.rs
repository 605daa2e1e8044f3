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

/// Returns the allocator's free pages to the OS (glibc only; elsewhere a no-op).
pub fn release_freed() {
    #[cfg(all(target_os = "linux", target_env = "gnu"))]
    // SAFETY: malloc_trim only releases memory malloc holds free; it takes the arenas'
    // locks itself and may be called from any thread at any time.
    unsafe {
        libc::malloc_trim(0);
    }
}

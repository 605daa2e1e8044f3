//! The broker's allocator, and giving freed memory back to the operating system.
//!
//! Two things decide the broker's resident size besides what it actually holds:
//!
//! - **Holes between idle sessions.** A login allocates more than the session it leaves
//!   behind (the login task, CONNECT and authentication state, router link setup), and a
//!   reconnect storm runs hundreds of logins at once. With glibc's malloc the short-lived
//!   blocks and the long-lived ones come from the same heap, interleaved; when the logins
//!   end, the holes between sessions stay resident. Measured with 1,000 argon2id devices
//!   right after their cold login storm (`fbbus-loadtest --username 'dev-{i}' idle
//!   --connections 1000 --hold-s 3`): 6.0-6.4 KiB per idle connection with glibc, of
//!   which about 3 KiB is live data; `malloc_trim` returned nothing of the rest.
//! - **Freed memory kept for reuse.** A burst leaves commit-log segments every subscriber
//!   has read (freed by the router, see `router`), batch buffers of busy connections, the
//!   8 MiB argon2id blocks of a storm's logins. An allocator keeps freed pages mapped for
//!   reuse unless told otherwise, so after a million messages the process would keep its
//!   peak resident size although nothing is allocated there any more.
//!
//! So the `fbbus` binary uses jemalloc (feature `jemalloc`, on by default) with
//! [`JEMALLOC_CONF`]: one arena, so every size class lives in slabs of its own and a freed
//! login block is reused by the next login instead of leaving a hole next to a session;
//! small per-thread caches (at most 20 blocks per size class, blocks up to 4 KiB); and a
//! background thread that returns freed pages to the OS one second after they were freed,
//! also when the broker is idle. Measured on the same storm: 3.3-3.4 KiB per idle
//! connection without thread caches.
//!
//! The thread caches (issue 34): without them every allocation and every free took the
//! arena's lock (`pthread_mutex_trylock` and its unlock were 5 % of the broker's samples in a
//! profile of 50 independent pairs). jemalloc's default caches (200 blocks per class)
//! bought 1.11-1.17x on the bursts for 9 % more memory per idle connection and 15-50 %
//! more right after a login storm; the small ones kept here, alternating against none in
//! one run (`fbbus-loadtest compare --fbbus notc=… --fbbus tcs=…`, 4 rounds): fan-in
//! 1.06x, QoS 1 fan-in 1.07x, 50 pairs 1.22x, steady p50/p99 0.92x/0.90x, idle connection
//! 1.00x, and after a storm of 1,000 argon2id logins 4.56-4.6 against 4.26-4.3 KiB per
//! idle connection. mimalloc (16-33 KiB) and jemalloc with all its defaults (7.8-8.0 KiB)
//! did worse on memory. The environment variable `_RJEM_MALLOC_CONF` overrides these
//! options for an experiment.
//!
//! Built without the feature, the binary uses glibc's malloc, with fixed thresholds for
//! large blocks ([`configure`]) and `malloc_trim` after the router released memory
//! ([`release_freed`]).

/// jemalloc's options for the broker (see the module doc), as the C string jemalloc
/// reads before `main`: one arena, small thread caches, freed pages returned after 1 s by
/// a background thread.
pub const JEMALLOC_CONF: &[u8; 125] =
    b"narenas:1,tcache:true,tcache_nslots_small_max:20,tcache_max:4096,\
background_thread:true,dirty_decay_ms:1000,muzzy_decay_ms:0\0";

/// Allocations at least this large get pages of their own (mmap), returned on free.
#[cfg(all(target_os = "linux", target_env = "gnu", not(feature = "jemalloc")))]
const MMAP_THRESHOLD: usize = 1024 * 1024;

/// Free memory at the top of a heap beyond this is returned on free.
#[cfg(all(target_os = "linux", target_env = "gnu", not(feature = "jemalloc")))]
const TRIM_THRESHOLD: usize = 4 * 1024 * 1024;

/// Fixes glibc's thresholds for large allocations (without jemalloc). Call once, before
/// other threads start.
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
    #[cfg(all(target_os = "linux", target_env = "gnu", not(feature = "jemalloc")))]
    // SAFETY: mallopt only sets allocator parameters; it is called before other threads
    // allocate (and would be safe even then: glibc takes its own locks).
    unsafe {
        libc::mallopt(libc::M_MMAP_THRESHOLD, MMAP_THRESHOLD as libc::c_int);
        libc::mallopt(libc::M_TRIM_THRESHOLD, TRIM_THRESHOLD as libc::c_int);
    }
}

/// Returns the allocator's free pages to the OS: `malloc_trim` with glibc. With jemalloc
/// its background thread does this by itself, one second after the pages were freed.
///
/// `malloc_trim(0)` walks every arena and returns its free pages (madvise) to the OS. It
/// takes a few milliseconds for a large heap and holds each arena's lock meanwhile, so it
/// is only called after the router released memory: when it has been quiet for a moment
/// (`router::IDLE_AFTER`, once per quiet period) or every `router::RELEASE_EVERY` under
/// steady traffic, never per packet.
pub fn release_freed() {
    #[cfg(all(target_os = "linux", target_env = "gnu", not(feature = "jemalloc")))]
    // SAFETY: malloc_trim only releases memory malloc holds free; it takes the arenas'
    // locks itself and may be called from any thread at any time.
    unsafe {
        libc::malloc_trim(0);
    }
}

//! How a long-running node hands freed memory back to the system (glibc's allocator on Linux).
//!
//! glibc serves blocks of at least its mmap threshold (128 KiB) from their own mappings, but the
//! first time such a block is freed it raises the threshold to that block's size (up to 32 MiB). A
//! node's large transient buffers (depth images, point clouds, serialized messages of 0.1–5 MB) are
//! then carved from the heap arenas, where one long-lived small block above them keeps the freed
//! pages resident: RSS rises in steps to the high-water mark of the largest messages seen and stays
//! there. [`keep_memory_returnable`] fixes the thresholds, so large buffers always get their own
//! mapping (unmapped when freed), and starts a thread that returns the free pages inside the heap
//! arenas (`malloc_trim`) every `trim_period`. Elsewhere (musl, other systems) it does nothing.

use std::time::Duration;

/// Blocks of at least this size get their own mapping, returned to the system when freed.
pub const MMAP_THRESHOLD_BYTES: i32 = 256 * 1024;
/// Free memory at the top of a heap beyond this is returned at once.
pub const TRIM_THRESHOLD_BYTES: i32 = 1024 * 1024;
/// How often the free pages inside the heap arenas are returned.
pub const TRIM_PERIOD: Duration = Duration::from_secs(10);

/// What [`keep_memory_returnable`] set up.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum MemoryPolicy {
    /// Fixed thresholds and the periodic trim thread.
    Returnable,
    /// The allocator refused the thresholds or the thread could not start; glibc's defaults stay.
    Default,
    /// Not glibc: nothing to do.
    NotGlibc,
}

/// Fixes glibc's mmap and trim thresholds and starts the `malloc-trim` thread (see the module doc).
/// Call once at start-up, before the node's threads allocate much.
#[cfg(all(target_os = "linux", target_env = "gnu"))]
pub fn keep_memory_returnable(trim_period: Duration) -> MemoryPolicy {
    if !set_thresholds() {
        return MemoryPolicy::Default;
    }
    let started = std::thread::Builder::new().name("malloc-trim".into()).spawn(move || loop {
        std::thread::sleep(trim_period);
        trim();
    });
    if started.is_ok() {
        MemoryPolicy::Returnable
    } else {
        MemoryPolicy::Default
    }
}

#[cfg(not(all(target_os = "linux", target_env = "gnu")))]
pub fn keep_memory_returnable(_trim_period: Duration) -> MemoryPolicy {
    MemoryPolicy::NotGlibc
}

// The allocator's own tuning calls have no safe wrapper in nix or libc.
#[cfg(all(target_os = "linux", target_env = "gnu"))]
#[allow(unsafe_code)]
fn set_thresholds() -> bool {
    use nix::libc::{mallopt, M_MMAP_THRESHOLD, M_TRIM_THRESHOLD};
    // SAFETY: mallopt takes two integers and changes allocator parameters under its own lock.
    unsafe { mallopt(M_MMAP_THRESHOLD, MMAP_THRESHOLD_BYTES) == 1 && mallopt(M_TRIM_THRESHOLD, TRIM_THRESHOLD_BYTES) == 1 }
}

/// Returns the free pages of every heap arena to the system.
#[cfg(all(target_os = "linux", target_env = "gnu"))]
#[allow(unsafe_code)]
pub fn trim() {
    // SAFETY: malloc_trim takes an integer (bytes to leave at the top) and locks each arena itself.
    unsafe {
        nix::libc::malloc_trim(0);
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Resident set size of this process (kB) from /proc/self/status.
    fn rss_kb() -> Option<u64> {
        let status = std::fs::read_to_string("/proc/self/status").ok()?;
        let line = status.lines().find(|l| l.starts_with("VmRSS:"))?;
        line.split_whitespace().nth(1)?.parse().ok()
    }

    /// With the fixed thresholds a freed large buffer leaves the resident set even when a small
    /// block allocated after it is still alive (with glibc's dynamic threshold the second buffer of
    /// that size comes from the heap and stays resident under the small block).
    #[cfg(all(target_os = "linux", target_env = "gnu"))]
    #[test]
    fn large_buffers_are_returned_when_freed() {
        assert_eq!(keep_memory_returnable(Duration::from_secs(3600)), MemoryPolicy::Returnable);
        let size = 8 << 20;
        let mut keep = Vec::new();
        for round in 0..3u8 {
            let buffer = vec![round.wrapping_add(1); size];
            std::hint::black_box(&buffer);
            keep.push(vec![round; 64]);
            drop(buffer);
        }
        let Some(before) = rss_kb() else { return };
        let buffer = vec![7u8; size];
        std::hint::black_box(&buffer);
        let Some(with_buffer) = rss_kb() else { return };
        drop(buffer);
        let Some(after) = rss_kb() else { return };
        std::hint::black_box(&keep);
        // Resident while in use (at least 6 of its 8 MiB), gone again after the drop.
        assert!(with_buffer >= before + 6 * 1024, "{before} -> {with_buffer} kB while holding 8 MiB");
        assert!(after + 6 * 1024 <= with_buffer, "{with_buffer} -> {after} kB after dropping 8 MiB");
    }
}

//! How a long-running node hands freed memory back to the system (glibc's allocator on Linux).
//!
//! glibc serves blocks of at least its mmap threshold (128 KiB) from their own mappings, but the
//! first time such a block is freed it raises the threshold to that block's size (up to 32 MiB). A
//! node's large transient buffers (depth images, raycasts, point clouds, serialized messages of
//! 0.1–5 MB) are then carved from the heap arenas, where a long-lived small block above them keeps
//! the freed pages resident: RSS rises in steps to the high-water mark of the largest messages seen
//! and stays there. [`start_trimming`] starts a thread that hands the free pages inside the arenas
//! back (`malloc_trim`) every period. Reused pages are faulted in again once per period, which costs
//! nothing measurable; fixing the mmap threshold instead (every large buffer its own mapping) would
//! fault in and zero every buffer of every frame (patch_mapper's latency p50 rose by 4 ms, p99
//! doubled). Elsewhere than glibc it does nothing.

use std::time::Duration;

/// How often the nodes hand free heap pages back.
pub const TRIM_PERIOD: Duration = Duration::from_secs(10);

/// Starts the `malloc-trim` thread (glibc); returns whether it runs.
#[cfg(all(target_os = "linux", target_env = "gnu"))]
pub fn start_trimming(period: Duration) -> bool {
    std::thread::Builder::new()
        .name("malloc-trim".into())
        .spawn(move || loop {
            std::thread::sleep(period);
            trim();
        })
        .is_ok()
}

/// Not glibc: nothing to trim.
#[cfg(not(all(target_os = "linux", target_env = "gnu")))]
pub fn start_trimming(_period: Duration) -> bool {
    false
}

/// Hands the free pages of every heap arena back to the system.
// The allocator's own call has no safe wrapper in nix or libc.
#[cfg(all(target_os = "linux", target_env = "gnu"))]
#[allow(unsafe_code)]
pub fn trim() {
    // SAFETY: malloc_trim takes an integer (bytes to leave at the top) and locks each arena itself.
    unsafe {
        nix::libc::malloc_trim(0);
    }
}

/// Not glibc: nothing to trim.
#[cfg(not(all(target_os = "linux", target_env = "gnu")))]
pub fn trim() {}

#[cfg(all(test, target_os = "linux", target_env = "gnu"))]
mod tests {
    use super::*;

    /// Resident set size of this process (kB) from /proc/self/status.
    fn rss_kb() -> Option<u64> {
        let status = std::fs::read_to_string("/proc/self/status").ok()?;
        let line = status.lines().find(|l| l.starts_with("VmRSS:"))?;
        line.split_whitespace().nth(1)?.parse().ok()
    }

    /// A large buffer freed under a live small block stays resident (glibc's raised threshold put
    /// it in the heap) until the trim hands its pages back.
    #[test]
    fn trimming_returns_a_freed_large_buffer_held_under_a_small_block() {
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
        keep.push(vec![9u8; 64]);
        drop(buffer);
        let Some(freed) = rss_kb() else { return };
        trim();
        let Some(trimmed) = rss_kb() else { return };
        std::hint::black_box(&keep);
        // The freed pages were still resident; at least 6 of the 8 MiB go back to the system.
        assert!(trimmed + 6 * 1024 <= freed, "before {before} kB, freed {freed} kB, trimmed {trimmed} kB");
    }
}

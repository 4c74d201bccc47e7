//! Process statistics the patchwalk benchmarks print beside wall time.

/// User + system CPU time of this process (s) from `/proc/self/stat` (Linux; `None` elsewhere or
/// if the file cannot be parsed): less sensitive than wall time to other processes on the cores.
pub fn process_cpu_seconds() -> Option<f64> {
    let stat = std::fs::read_to_string("/proc/self/stat").ok()?;
    // Fields after the parenthesised command name; utime and stime are fields 14 and 15 (1-based).
    let rest = stat.rsplit_once(')')?.1;
    let fields: Vec<&str> = rest.split_whitespace().collect();
    let utime: f64 = fields.get(11)?.parse().ok()?;
    let stime: f64 = fields.get(12)?.parse().ok()?;
    // Clock ticks: USER_HZ is 100 on Linux.
    Some((utime + stime) / 100.0)
}

#[cfg(test)]
mod tests {
    /// Busy work shows up as CPU time (at the 10 ms tick): within 10 s of wall time, even on a
    /// loaded host, 50 ms of it must have been counted.
    #[test]
    fn cpu_time_counts_busy_work() {
        let Some(before) = super::process_cpu_seconds() else { return };
        let start = std::time::Instant::now();
        let mut x = 0u64;
        let mut now = before;
        while now < before + 0.05 && start.elapsed().as_secs() < 10 {
            for _ in 0..100_000 {
                x = x.wrapping_mul(6364136223846793005).wrapping_add(1);
            }
            now = super::process_cpu_seconds().unwrap_or(before);
        }
        std::hint::black_box(x);
        assert!(now >= before + 0.05, "{before} -> {now} s");
    }
}

//! Absolute deadlines for the control cycle: `clock_nanosleep(CLOCK_MONOTONIC, TIMER_ABSTIME)` to
//! `start + k · period`, so a late wake-up does not shift the cycles after it (a relative sleep
//! would add every wake-up latency to the schedule). After an overrun the schedule restarts from
//! now instead of bursting to catch up, after a rest of [`OVERRUN_REST_FRACTION`] of a period: a
//! SCHED_FIFO loop whose every cycle overruns (CPU-bound work, a bus that fails at once) must still
//! leave the CPU to the host's other threads, the DDS ones that carry an e-stop included.

use std::time::Duration;

use nix::sys::time::TimeSpec;
use nix::time::{clock_gettime, clock_nanosleep, ClockId, ClockNanosleepFlags};

/// After an overrun the loop sleeps `period / OVERRUN_REST_FRACTION` before the next cycle.
pub const OVERRUN_REST_FRACTION: u32 = 10;

/// The cycle's deadline schedule on the monotonic clock.
#[derive(Debug, Clone)]
pub struct CycleClock {
    period: TimeSpec,
    next: TimeSpec,
}

fn now() -> TimeSpec {
    // CLOCK_MONOTONIC cannot fail on Linux; zero keeps the schedule valid if it ever did.
    clock_gettime(ClockId::CLOCK_MONOTONIC).unwrap_or_else(|_| TimeSpec::new(0, 0))
}

impl CycleClock {
    /// A schedule whose first deadline is now.
    pub fn start(period: Duration) -> Self {
        Self { period: TimeSpec::from(period), next: now() }
    }

    /// Sleep until the next deadline. Returns `false` when it had already passed (an overrun; the
    /// schedule then restarts from now).
    pub fn wait(&mut self) -> bool {
        self.next = self.next + self.period;
        if self.next <= now() {
            std::thread::sleep(Duration::from(self.period) / OVERRUN_REST_FRACTION);
            self.next = now();
            return false;
        }
        loop {
            match clock_nanosleep(ClockId::CLOCK_MONOTONIC, ClockNanosleepFlags::TIMER_ABSTIME, &self.next) {
                Err(nix::errno::Errno::EINTR) => continue,
                Ok(_) => return true,
                Err(_) => {
                    // Not expected on Linux; a relative sleep keeps the loop running.
                    let left = self.next - now();
                    if left > TimeSpec::new(0, 0) {
                        std::thread::sleep(Duration::from(left));
                    }
                    return true;
                }
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn deadlines_are_absolute_and_an_overrun_restarts_the_schedule() {
        let mut clock = CycleClock::start(Duration::from_millis(2));
        let first = clock.next;
        for _ in 0..3 {
            clock.wait();
        }
        // Three periods from the start whatever each wake-up's latency (unless one overran).
        let expected = first + TimeSpec::from(Duration::from_millis(6));
        assert!(clock.next >= expected);
        std::thread::sleep(Duration::from_millis(10));
        let before = now();
        assert!(!clock.wait(), "a deadline 8 ms in the past is an overrun");
        // Even so the loop rested a tenth of a period: an overrunning loop never spins.
        assert!(now() - before >= TimeSpec::from(Duration::from_millis(2) / OVERRUN_REST_FRACTION));
    }
}

//! A bus too slow for the control cycle is a fault: with answers that take 200 ms the 8 ms loop
//! runs at ~5 cycles/s, a motion's goals come 25× too late and an e-stop waits for each answer.
//! Two configurable rules (`bus.slow_bus`): N consecutive cycles whose bus work exceeded the cycle
//! (each missed its next deadline), or a cycle rate below X % of nominal over a window.

use std::time::{Duration, Instant};

use serde::{Deserialize, Serialize};

use patchwalk_dynamixel::servo_bus::BusError;

/// When the bus counts as too slow.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct SlowBusConfig {
    /// Fault after this many consecutive cycles over their budget (0 = rule off).
    pub consecutive_misses: u32,
    /// Fault when the cycle rate over `window_s` falls below this percentage of nominal (0 = rule off).
    pub min_rate_percent: f64,
    /// Window of the rate rule, s.
    pub window_s: f64,
}

impl Default for SlowBusConfig {
    fn default() -> Self {
        // 5 cycles: 40 ms at 8 ms, far below what a person notices, far above one late answer.
        Self { consecutive_misses: 5, min_rate_percent: 50.0, window_s: 1.0 }
    }
}

impl SlowBusConfig {
    pub fn validate(&self) -> Result<(), crate::config::InvalidSetting> {
        use crate::config::InvalidSetting;
        if !(self.min_rate_percent.is_finite() && (0.0..=100.0).contains(&self.min_rate_percent)) {
            return Err(InvalidSetting {
                key: "bus.slow_bus.min_rate_percent",
                rule: "must be within 0..=100",
                value: self.min_rate_percent,
            });
        }
        if !(self.window_s.is_finite() && (0.05..=60.0).contains(&self.window_s)) {
            return Err(InvalidSetting { key: "bus.slow_bus.window_s", rule: "must be within 0.05..=60", value: self.window_s });
        }
        Ok(())
    }
}

/// The running check, fed once per cycle.
#[derive(Debug, Clone)]
pub struct SlowBusDetector {
    config: SlowBusConfig,
    cycle: Duration,
    consecutive: u32,
    consecutive_busy: Duration,
    window_start: Option<Instant>,
    window_cycles: u32,
}

impl SlowBusDetector {
    pub fn new(config: SlowBusConfig, cycle: Duration) -> Self {
        Self { config, cycle, consecutive: 0, consecutive_busy: Duration::ZERO, window_start: None, window_cycles: 0 }
    }

    fn nominal_hz(&self) -> f64 {
        1.0 / self.cycle.as_secs_f64().max(1e-6)
    }

    /// Forget the history (after the loop was blocked on purpose, e.g. waiting for a servo to boot).
    pub fn reset(&mut self) {
        self.consecutive = 0;
        self.consecutive_busy = Duration::ZERO;
        self.window_start = None;
        self.window_cycles = 0;
    }

    /// One cycle that started at `started` and whose bus work took `busy`. Returns the fault when
    /// a rule trips (then starts afresh).
    pub fn observe(&mut self, started: Instant, busy: Duration) -> Option<BusError> {
        let nominal_hz = self.nominal_hz();
        if busy > self.cycle {
            self.consecutive += 1;
            self.consecutive_busy += busy;
        } else {
            self.consecutive = 0;
            self.consecutive_busy = Duration::ZERO;
        }
        if self.config.consecutive_misses > 0 && self.consecutive >= self.config.consecutive_misses {
            let rate_hz = f64::from(self.consecutive) / self.consecutive_busy.as_secs_f64().max(1e-9);
            let detail = format!(
                "{} consecutive cycles over the {:.0} ms budget, the last took {:.0} ms",
                self.consecutive,
                self.cycle.as_secs_f64() * 1e3,
                busy.as_secs_f64() * 1e3
            );
            self.reset();
            return Some(BusError::TooSlow { rate_hz, nominal_hz, detail });
        }
        let start = *self.window_start.get_or_insert(started);
        self.window_cycles += 1;
        let elapsed = started.saturating_duration_since(start);
        if elapsed.as_secs_f64() >= self.config.window_s {
            let rate_hz = f64::from(self.window_cycles - 1) / elapsed.as_secs_f64();
            self.window_start = Some(started);
            self.window_cycles = 1;
            if self.config.min_rate_percent > 0.0 && rate_hz < nominal_hz * self.config.min_rate_percent / 100.0 {
                let detail = format!("below {:.0} % of nominal over {:.1} s", self.config.min_rate_percent, elapsed.as_secs_f64());
                return Some(BusError::TooSlow { rate_hz, nominal_hz, detail });
            }
        }
        None
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    const CYCLE: Duration = Duration::from_millis(8);

    #[test]
    fn consecutive_overruns_trip_with_the_rate_in_the_message() {
        let mut detector = SlowBusDetector::new(SlowBusConfig::default(), CYCLE);
        let t0 = Instant::now();
        // Answers of 200 ms: every cycle is over budget.
        let mut fault = None;
        for i in 0..5u32 {
            fault = detector.observe(t0 + Duration::from_millis(200) * i, Duration::from_millis(200));
            if i < 4 {
                assert_eq!(fault, None, "cycle {i}");
            }
        }
        let Some(BusError::TooSlow { rate_hz, nominal_hz, .. }) = fault.clone() else { panic!("{fault:?}") };
        assert!((rate_hz - 5.0).abs() < 1e-9 && nominal_hz == 125.0);
        assert!(fault.unwrap().to_string().starts_with("bus too slow: 5.0 cycles/s of 125"));
        // One cycle within budget restarts the count.
        let mut detector = SlowBusDetector::new(SlowBusConfig { min_rate_percent: 0.0, ..Default::default() }, CYCLE);
        for i in 0..20u32 {
            let busy = if i % 4 == 3 { Duration::from_millis(1) } else { Duration::from_millis(20) };
            assert_eq!(detector.observe(t0 + Duration::from_millis(20) * i, busy), None);
        }
    }

    #[test]
    fn low_rate_over_the_window_trips_and_a_reset_forgets() {
        let config = SlowBusConfig { consecutive_misses: 0, min_rate_percent: 50.0, window_s: 1.0 };
        let mut detector = SlowBusDetector::new(config.clone(), CYCLE);
        let t0 = Instant::now();
        // 40 cycles/s (every 25 ms) with short bus work: only the rate rule can see it.
        let faults: Vec<BusError> =
            (0..=41u32).filter_map(|i| detector.observe(t0 + Duration::from_millis(25) * i, Duration::from_millis(1))).collect();
        assert_eq!(faults.len(), 1, "{faults:?}");
        assert!(matches!(&faults[0], BusError::TooSlow { rate_hz, .. } if (rate_hz - 40.0).abs() < 1e-9));
        // At the nominal rate nothing trips.
        let mut detector = SlowBusDetector::new(config, CYCLE);
        assert!((0..300u32).all(|i| detector.observe(t0 + CYCLE * i, Duration::from_millis(2)).is_none()));
        detector.reset();
        assert!(detector.observe(t0 + Duration::from_secs(10), Duration::from_millis(2)).is_none());
    }
}

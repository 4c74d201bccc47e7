//! Bus health, per servo and for the control cycle, kept by the bus thread for diagnostics
//! ([`crate::executor::Executor::health`]). Plain data; every field is documented where it is
//! declared. The cycle statistics live in fixed-size rings, so keeping them allocates nothing.

use std::time::Duration;

use patchwalk_dynamixel::servo_bus::BusError;

/// Health of one servo.
#[derive(Debug, Clone, PartialEq, Default)]
pub struct ServoHealth {
    /// Dynamixel id.
    pub id: u8,
    /// Failed reads of this servo since start (timeouts, CRC errors, malformed frames, wrong ids,
    /// status errors; hardware errors and a lost port are not counted here).
    pub comm_errors: u64,
    /// The last error seen for this servo (any kind, including a hardware error); kept after it clears.
    pub last_error: Option<BusError>,
    /// Hardware Error Status (70) bits last read (0 = none; see `mx28::hardware_error_names`);
    /// cleared by a REBOOT.
    pub hardware_error: u8,
    /// Present Temperature (146), °C, read every `bus.health_read_period_cycles` cycles.
    pub temperature_c: Option<u8>,
    /// Present Input Voltage (144), V (register in 0.1 V), read with the temperature.
    pub input_voltage_v: Option<f64>,
}

/// Health of the bus and its control cycle.
#[derive(Debug, Clone, PartialEq, Default)]
pub struct BusHealth {
    /// One entry per servo, in joint order.
    pub servos: Vec<ServoHealth>,
    /// Control cycles per second over the last [`CYCLE_WINDOW`] cycles (nominal: 1 / cycle).
    pub cycle_rate_hz: f64,
    /// Nominal cycle rate (125 Hz for 8 ms).
    pub nominal_rate_hz: f64,
    /// Cycle period (start to start), ms, median and 99th percentile over the last cycles.
    pub cycle_period_p50_ms: f64,
    pub cycle_period_p99_ms: f64,
    /// Bus time of a cycle (its transactions), ms, median and 99th percentile.
    pub cycle_busy_p50_ms: f64,
    pub cycle_busy_p99_ms: f64,
    /// Cycles whose work took longer than the cycle (the next deadline was missed), since start.
    pub deadline_misses: u64,
    /// Cycles run since start.
    pub cycles: u64,
    /// Scheduling of the bus thread (e.g. "SCHED_FIFO priority 50").
    pub scheduling: String,
}

/// Number of cycles the statistics are computed over (about 2 s at 8 ms).
pub const CYCLE_WINDOW: usize = 256;

/// Fixed-size ring of the last [`CYCLE_WINDOW`] values with percentiles computed without allocating.
#[derive(Debug, Clone)]
pub struct Ring {
    values: [f64; CYCLE_WINDOW],
    scratch: [f64; CYCLE_WINDOW],
    len: usize,
    next: usize,
}

impl Default for Ring {
    fn default() -> Self {
        Self { values: [0.0; CYCLE_WINDOW], scratch: [0.0; CYCLE_WINDOW], len: 0, next: 0 }
    }
}

impl Ring {
    pub fn push(&mut self, value: f64) {
        if let Some(slot) = self.values.get_mut(self.next) {
            *slot = value;
        }
        self.next = (self.next + 1) % CYCLE_WINDOW;
        self.len = (self.len + 1).min(CYCLE_WINDOW);
    }

    pub fn len(&self) -> usize {
        self.len
    }

    pub fn is_empty(&self) -> bool {
        self.len == 0
    }

    /// Sum of the kept values.
    pub fn sum(&self) -> f64 {
        self.values.iter().take(self.len).sum()
    }

    /// Percentiles `ps` (0..=1, nearest rank) of the kept values; NaN when empty.
    pub fn percentiles<const N: usize>(&mut self, ps: [f64; N]) -> [f64; N] {
        let n = self.len;
        let (kept, scratch) = (self.values.get(..n).unwrap_or(&[]), self.scratch.get_mut(..n).unwrap_or(&mut []));
        scratch.copy_from_slice(kept);
        scratch.sort_unstable_by(f64::total_cmp);
        ps.map(|p| {
            if n == 0 {
                f64::NAN
            } else {
                let rank = ((n - 1) as f64 * p.clamp(0.0, 1.0)).round() as usize;
                scratch.get(rank).copied().unwrap_or(f64::NAN)
            }
        })
    }
}

/// The bus thread's running account: rings of the cycle timing and per-servo counters.
#[derive(Debug, Clone)]
pub struct HealthTracker {
    pub health: BusHealth,
    periods_ms: Ring,
    busy_ms: Ring,
}

impl HealthTracker {
    pub fn new(ids: &[u8], cycle: Duration) -> Self {
        let servos = ids.iter().map(|&id| ServoHealth { id, ..Default::default() }).collect();
        let nominal_rate_hz = 1.0 / cycle.as_secs_f64().max(1e-6);
        Self { health: BusHealth { servos, nominal_rate_hz, ..Default::default() }, periods_ms: Ring::default(), busy_ms: Ring::default() }
    }

    /// One cycle's timing: its period (from the previous cycle's start) and its bus time.
    pub fn cycle(&mut self, period: Option<Duration>, busy: Duration, missed: bool) {
        self.health.cycles += 1;
        if missed {
            self.health.deadline_misses += 1;
        }
        if let Some(period) = period {
            self.periods_ms.push(period.as_secs_f64() * 1e3);
        }
        self.busy_ms.push(busy.as_secs_f64() * 1e3);
    }

    /// One position read's per-servo outcome (joint order, as [`crate::player::Player::last_errors`]).
    pub fn read(&mut self, errors: &[Option<BusError>]) {
        for (servo, error) in self.health.servos.iter_mut().zip(errors) {
            let Some(error) = error else { continue };
            match error {
                BusError::Hardware { bits, .. } => servo.hardware_error = *bits,
                BusError::Io(_) | BusError::Unread { .. } | BusError::TooSlow { .. } => {}
                _ => servo.comm_errors += 1,
            }
            if servo.last_error.as_ref() != Some(error) {
                servo.last_error = Some(error.clone());
            }
        }
    }

    /// A Present Input Voltage + Present Temperature read (addresses 144..=146) of one servo.
    pub fn vitals(&mut self, id: u8, result: &Result<Vec<u8>, BusError>) {
        let Some(servo) = self.health.servos.iter_mut().find(|s| s.id == id) else { return };
        match result {
            Ok(data) => {
                if let [v0, v1, temperature, ..] = data.as_slice() {
                    servo.input_voltage_v = Some(f64::from(u16::from_le_bytes([*v0, *v1])) / 10.0);
                    servo.temperature_c = Some(*temperature);
                }
            }
            Err(error) => {
                servo.comm_errors += 1;
                servo.last_error = Some(error.clone());
            }
        }
    }

    /// A servo was rebooted: its hardware error is gone.
    pub fn rebooted(&mut self, id: u8) {
        if let Some(servo) = self.health.servos.iter_mut().find(|s| s.id == id) {
            servo.hardware_error = 0;
        }
    }

    /// Servos whose last read hardware error bits are set.
    pub fn hardware_faulted(&self) -> impl Iterator<Item = u8> + '_ {
        self.health.servos.iter().filter(|s| s.hardware_error != 0).map(|s| s.id)
    }

    /// Recompute rate and percentiles (no allocation).
    pub fn summarise(&mut self) {
        let [p50, p99] = self.periods_ms.percentiles([0.5, 0.99]);
        self.health.cycle_period_p50_ms = p50;
        self.health.cycle_period_p99_ms = p99;
        let [b50, b99] = self.busy_ms.percentiles([0.5, 0.99]);
        self.health.cycle_busy_p50_ms = b50;
        self.health.cycle_busy_p99_ms = b99;
        let total_ms = self.periods_ms.sum();
        self.health.cycle_rate_hz = if total_ms > 0.0 { self.periods_ms.len() as f64 / total_ms * 1e3 } else { 0.0 };
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn ring_percentiles_and_wrap_around() {
        let mut ring = Ring::default();
        assert!(ring.percentiles([0.5])[0].is_nan());
        for i in 0..(CYCLE_WINDOW + 10) {
            ring.push(i as f64);
        }
        assert_eq!(ring.len(), CYCLE_WINDOW);
        let [min, p50, max] = ring.percentiles([0.0, 0.5, 1.0]);
        assert_eq!((min, max), (10.0, (CYCLE_WINDOW + 9) as f64));
        assert!((p50 - (10.0 + CYCLE_WINDOW as f64 / 2.0)).abs() <= 1.0);
    }

    #[test]
    fn counts_errors_per_servo_and_reads_vitals() {
        let mut tracker = HealthTracker::new(&[1, 2], Duration::from_millis(8));
        tracker.read(&[None, Some(BusError::Timeout { id: 2 })]);
        tracker.read(&[None, Some(BusError::Hardware { id: 2, bits: 0x04 })]);
        tracker.vitals(1, &Ok(vec![118, 0, 41]));
        for _ in 0..4 {
            tracker.cycle(Some(Duration::from_millis(10)), Duration::from_millis(2), true);
        }
        tracker.summarise();
        let h = &tracker.health;
        assert_eq!((h.servos[0].comm_errors, h.servos[1].comm_errors), (0, 1));
        assert_eq!(h.servos[1].hardware_error, 0x04);
        assert_eq!(h.servos[1].last_error, Some(BusError::Hardware { id: 2, bits: 0x04 }));
        assert_eq!((h.servos[0].temperature_c, h.servos[0].input_voltage_v), (Some(41), Some(11.8)));
        assert_eq!(tracker.hardware_faulted().collect::<Vec<_>>(), vec![2]);
        assert!((h.cycle_rate_hz - 100.0).abs() < 1e-9 && h.nominal_rate_hz == 125.0);
        assert_eq!((h.deadline_misses, h.cycles, h.cycle_period_p99_ms), (4, 4, 10.0));
        tracker.rebooted(2);
        assert_eq!(tracker.hardware_faulted().count(), 0);
    }
}

//! Step timing of a time-based page as ROBOTIS' action players play it: a control cycle of 8 ms, a
//! step's move lasting `⌊time · speed / 32⌋` cycles and its pause `⌊32 · pause / speed⌋` cycles
//! (speed 32 plays the bytes as written), and the reverse: the play speed and bytes that come closest
//! to given move and pause durations.

use super::page::NOMINAL_SPEED;

/// The action players' control cycle (s).
pub const CONTROL_CYCLE_S: f64 = 0.008;

/// Move duration (s) of a step's `time` byte at play speed `speed`.
pub fn move_seconds(time: u8, speed: u8) -> f64 {
    f64::from((u32::from(time) * u32::from(speed)) >> 5) * CONTROL_CYCLE_S
}

/// Pause duration (s) of a step's `pause` byte at play speed `speed` (speed 0 is no valid speed: 0 s).
pub fn pause_seconds(pause: u8, speed: u8) -> f64 {
    if speed == 0 {
        return 0.0;
    }
    f64::from((u32::from(pause) << 5) / u32::from(speed)) * CONTROL_CYCLE_S
}

/// The bytes of one step for a move and a pause duration.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct StepTiming {
    pub time: u8,
    pub pause: u8,
}

/// A play speed with the step bytes it gives and the largest timing error over the steps (s).
#[derive(Debug, Clone, PartialEq)]
pub struct PageTiming {
    pub speed: u8,
    pub steps: Vec<StepTiming>,
    pub max_error_s: f64,
}

/// The play speed (1..=255) and bytes closest to `durations` (move, pause in s, finite and ≥ 0):
/// the smallest largest error, ties going to `preferred`, then to speed 32, then to the lowest speed byte.
pub fn choose_timing(durations: &[(f64, f64)], preferred: u8) -> PageTiming {
    let mut order: Vec<u8> = vec![preferred, NOMINAL_SPEED];
    order.extend(1..=255u8);
    let mut best: Option<PageTiming> = None;
    for speed in order.into_iter().filter(|&s| s != 0) {
        let candidate = timing_at(durations, speed);
        if best.as_ref().is_none_or(|b| candidate.max_error_s < b.max_error_s - 1e-12) {
            best = Some(candidate);
        }
    }
    best.unwrap_or_else(|| timing_at(durations, NOMINAL_SPEED))
}

/// The closest bytes for every step at one speed.
fn timing_at(durations: &[(f64, f64)], speed: u8) -> PageTiming {
    let mut max_error_s: f64 = 0.0;
    let steps = durations
        .iter()
        .map(|&(move_s, pause_s)| {
            let (time, move_error) = closest_byte(move_s, |b| move_seconds(b, speed));
            let (pause, pause_error) = closest_byte(pause_s, |b| pause_seconds(b, speed));
            max_error_s = max_error_s.max(move_error).max(pause_error);
            StepTiming { time, pause }
        })
        .collect();
    PageTiming { speed, steps, max_error_s }
}

/// The smallest byte whose duration is closest to `seconds`, with its error.
fn closest_byte(seconds: f64, duration: impl Fn(u8) -> f64) -> (u8, f64) {
    let mut best = (0u8, (duration(0) - seconds).abs());
    for byte in 1..=255u8 {
        let error = (duration(byte) - seconds).abs();
        if error < best.1 - 1e-12 {
            best = (byte, error);
        }
    }
    best
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn bytes_at_speed_32_are_cycles_of_8_ms() {
        assert!((move_seconds(100, 32) - 0.8).abs() < 1e-12);
        assert!((pause_seconds(10, 32) - 0.08).abs() < 1e-12);
        // Speed 64: moves take twice the cycles, pauses half (the players' arithmetic).
        assert!((move_seconds(100, 64) - 1.6).abs() < 1e-12);
        assert!((pause_seconds(10, 64) - 0.04).abs() < 1e-12);
        // Integer division as in the players: 32 · 3 / 20 = 4 cycles.
        assert!((pause_seconds(3, 20) - 0.032).abs() < 1e-12);
        assert_eq!(pause_seconds(3, 0), 0.0);
    }

    #[test]
    fn durations_of_whole_cycles_keep_speed_32_exactly() {
        let timing = choose_timing(&[(0.8, 0.08), (0.4, 0.0)], 32);
        assert_eq!(timing.speed, 32);
        assert_eq!(timing.steps, vec![StepTiming { time: 100, pause: 10 }, StepTiming { time: 50, pause: 0 }]);
        assert!(timing.max_error_s < 1e-12);
    }

    #[test]
    fn the_preferred_speed_is_kept_when_it_is_exact() {
        let durations = [(move_seconds(90, 64), pause_seconds(20, 64))];
        let timing = choose_timing(&durations, 64);
        assert_eq!(timing.speed, 64);
        assert!(timing.max_error_s < 1e-12);
        assert!((move_seconds(timing.steps[0].time, 64) - durations[0].0).abs() < 1e-12);
    }

    #[test]
    fn a_move_longer_than_speed_32_allows_picks_a_faster_speed() {
        // 255 time bytes at speed 32 are 2.04 s; 4 s needs a higher speed.
        let timing = choose_timing(&[(4.0, 0.0)], 32);
        assert!(timing.speed > 32, "{timing:?}");
        assert!(timing.max_error_s <= CONTROL_CYCLE_S / 2.0, "{timing:?}");
        // Impossible together: a 16 s move needs speed ≥ 251, where the longest pause is 32 cycles.
        let timing = choose_timing(&[(16.0, 2.0)], 32);
        assert!(timing.max_error_s > 1.0, "{timing:?}");
    }
}

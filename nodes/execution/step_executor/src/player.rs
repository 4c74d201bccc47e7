//! Keyframe playback (J 6.3: "executes the corresponding motion sequence") on any [`ServoBus`].
//!
//! Design choice: interpolation on the host at a fixed 8 ms cycle rather than the MX-28's time-based
//! profiles (Drive Mode bit 2). Reasons: (a) the spec requires a present-position/hardware-error read
//! every cycle anyway, so the bus is busy at 125 Hz regardless; (b) all 12 joints follow one clock and
//! arrive together with a shared minimum-jerk profile, independent of per-servo firmware; (c) an e-stop
//! or a fault freezes the goal within one cycle at the *measured* position, whereas a servo-side
//! profile keeps moving to its final goal until told otherwise; (d) the same code runs on the mock,
//! the pty emulator and the robot, and changing Drive Mode needs EEPROM writes with torque off.
//!
//! Each cycle: e-stop check → one sync write of the 12 goal positions → e-stop check → one sync read
//! of Present Position (132) whose alert bits are resolved via Hardware Error Status (70). Any fault
//! (timeout, CRC error, malformed frame, wrong id, missing servo, hardware error, lost port, a bus
//! too slow for the cycle) latches in every state: a motion stops and holds the last measured
//! positions in the same cycle, no goal is written until the fault is cleared (torque off, or
//! REBOOT for a hardware error), and the positions are not handed out for recording.
//! Joint limits (URDF, and the servo's 0..=4095 range) are checked for the whole motion before the
//! first byte is sent, and again for every goal.

use std::time::Duration;

use serde::{Deserialize, Serialize};

use crate::config::ServoConfig;
use crate::library::{Keyframe, Motion};
use patchwalk_dynamixel::mx28;
use patchwalk_dynamixel::servo_bus::{self, BusError, ServoBus};
use patchwalk_robot_model::kinematics::JointLimits;

/// Playback configuration.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct PlayerConfig {
    /// Control cycle (ms); 8 ms as ROBOTIS OP-class action modules.
    pub cycle_ms: f64,
    /// Extra margin inside the URDF limits that goals must respect (rad).
    pub limit_margin_rad: f64,
}

impl Default for PlayerConfig {
    fn default() -> Self {
        Self { cycle_ms: 8.0, limit_margin_rad: 0.0 }
    }
}

impl PlayerConfig {
    pub fn validate(&self) -> Result<(), crate::config::InvalidSetting> {
        use crate::config::InvalidSetting;
        if !(self.cycle_ms.is_finite() && (1.0..=100.0).contains(&self.cycle_ms)) {
            return Err(InvalidSetting { key: "player.cycle_ms", rule: "must be within 1..=100", value: self.cycle_ms });
        }
        if !(self.limit_margin_rad.is_finite() && self.limit_margin_rad >= 0.0) {
            return Err(InvalidSetting { key: "player.limit_margin_rad", rule: "must be finite and ≥ 0", value: self.limit_margin_rad });
        }
        Ok(())
    }

    pub fn cycle(&self) -> Duration {
        Duration::from_secs_f64(self.cycle_ms / 1000.0)
    }
}

/// Errors refusing a motion before anything is sent.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum PlayerError {
    #[error("keyframe {keyframe}, joint {joint}: {value:.3} rad outside limits [{lower:.3}, {upper:.3}]")]
    JointLimit { keyframe: usize, joint: String, value: f64, lower: f64, upper: f64 },
    #[error("keyframe {keyframe}: {got} positions for {expected} joints")]
    WrongLength { keyframe: usize, got: usize, expected: usize },
    #[error("motion {0:?} has no keyframes")]
    Empty(String),
    #[error("the servos are faulted ({0}); clear the fault (torque off/on) first")]
    Faulted(String),
}

/// One joint: its servo and position limits.
#[derive(Debug, Clone, PartialEq)]
pub struct JointSpec {
    pub servo: ServoConfig,
    pub limits: JointLimits,
}

/// A fault that stopped the servos.
#[derive(Debug, Clone, PartialEq)]
pub struct Fault {
    pub servo_id: Option<u8>,
    pub joint: Option<String>,
    pub error: BusError,
}

impl std::fmt::Display for Fault {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match &self.joint {
            Some(joint) => write!(f, "{joint}: {}", self.error),
            None => write!(f, "{}", self.error),
        }
    }
}

/// What the player is doing.
#[derive(Debug, Clone, PartialEq)]
pub enum PlayerState {
    Idle,
    Playing {
        name: String,
    },
    /// Stopped by e-stop; holding the measured positions.
    Stopped,
    /// Stopped by a bus fault; holding the last measured positions.
    Faulted(Fault),
}

/// Events emitted by a cycle.
#[derive(Debug, Clone, PartialEq)]
pub enum PlayerEvent {
    Started { name: String },
    Finished { name: String },
    EStopped,
    Fault(Fault),
}

/// Result of one control cycle.
#[derive(Debug, Clone, PartialEq, Default)]
pub struct CycleReport {
    /// Goal positions sent this cycle (rad, joint order).
    pub goal: Option<Vec<f64>>,
    /// Measured positions (rad, joint order) where known.
    pub present: Vec<Option<f64>>,
    pub event: Option<PlayerEvent>,
}

/// Minimum-jerk time scaling s(τ) = 10τ³ − 15τ⁴ + 6τ⁵: zero velocity and acceleration at both
/// keyframes (the smooth start/stop of keyframe action players).
pub fn minimum_jerk(tau: f64) -> f64 {
    let t = tau.clamp(0.0, 1.0);
    t * t * t * (10.0 + t * (-15.0 + 6.0 * t))
}

/// A motion from given start positions through the keyframes.
#[derive(Debug, Clone, PartialEq)]
pub struct Trajectory {
    start: Vec<f64>,
    keyframes: Vec<Keyframe>,
    duration: f64,
}

impl Trajectory {
    pub fn new(start: Vec<f64>, keyframes: Vec<Keyframe>) -> Self {
        let duration = keyframes.iter().map(|k| k.move_s + k.pause_s).sum();
        Self { start, keyframes, duration }
    }

    /// Total duration (s).
    pub fn duration(&self) -> f64 {
        self.duration
    }

    /// Index of the keyframe being moved to (or paused at) at time `t` (s).
    pub fn keyframe_index(&self, t: f64) -> usize {
        let mut end = 0.0;
        for (i, frame) in self.keyframes.iter().enumerate() {
            end += frame.move_s + frame.pause_s;
            if t < end {
                return i;
            }
        }
        self.keyframes.len().saturating_sub(1)
    }

    /// Positions at time `t` (s) from the start; the last keyframe after the end.
    pub fn sample(&self, t: f64) -> Vec<f64> {
        let mut from = self.start.as_slice();
        let mut segment_start = 0.0;
        for frame in &self.keyframes {
            let arrive = segment_start + frame.move_s;
            if t < arrive {
                let s = if frame.move_s > 0.0 { minimum_jerk((t - segment_start) / frame.move_s) } else { 1.0 };
                return from.iter().zip(&frame.positions).map(|(a, b)| a + (b - a) * s).collect();
            }
            if t < arrive + frame.pause_s {
                return frame.positions.clone();
            }
            segment_start = arrive + frame.pause_s;
            from = &frame.positions;
        }
        from.to_vec()
    }
}

/// The keyframe player over 12 (or any number of) joints.
#[derive(Debug, Clone)]
pub struct Player {
    config: PlayerConfig,
    joints: Vec<JointSpec>,
    state: PlayerState,
    trajectory: Option<Trajectory>,
    cycle_index: u64,
    /// Last measured positions (rad), joint order.
    last_present: Vec<Option<f64>>,
    /// This cycle's read, per servo (preallocated, overwritten every cycle).
    read_ticks: Vec<Option<i32>>,
    read_errors: Vec<Option<BusError>>,
}

impl Player {
    pub fn new(config: PlayerConfig, joints: Vec<JointSpec>) -> Self {
        let n = joints.len();
        Self {
            config,
            joints,
            state: PlayerState::Idle,
            trajectory: None,
            cycle_index: 0,
            last_present: vec![None; n],
            read_ticks: vec![None; n],
            read_errors: vec![None; n],
        }
    }

    pub fn state(&self) -> &PlayerState {
        &self.state
    }

    pub fn joints(&self) -> &[JointSpec] {
        &self.joints
    }

    pub fn ids(&self) -> Vec<u8> {
        self.joints.iter().map(|j| j.servo.id).collect()
    }

    pub fn last_present(&self) -> &[Option<f64>] {
        &self.last_present
    }

    /// Each servo's error in the last position read (joint order; `None` = read fine).
    pub fn last_errors(&self) -> &[Option<BusError>] {
        &self.read_errors
    }

    /// Latch a fault found outside the position read (e.g. a bus too slow for the cycle): a motion
    /// stops and holds the measured pose now; nothing moves until cleared. `None` when already faulted.
    pub fn fault_external(&mut self, bus: &mut dyn ServoBus, error: BusError) -> Option<CycleReport> {
        if matches!(self.state, PlayerState::Faulted(_)) {
            return None;
        }
        let mut report = CycleReport::default();
        if matches!(self.state, PlayerState::Playing { .. }) {
            report.goal = self.hold(bus);
        }
        let fault = self.fault(error);
        self.trajectory = None;
        self.state = PlayerState::Faulted(fault.clone());
        report.event = Some(PlayerEvent::Fault(fault));
        report.present = self.last_present.clone();
        Some(report)
    }

    /// Read the present positions now (after a reboot or reconnect), outside a cycle.
    pub fn refresh(&mut self, bus: &mut dyn ServoBus) -> Result<(), BusError> {
        self.read_present(bus)
    }

    /// Keyframe being played (0 when idle).
    pub fn keyframe_index(&self) -> usize {
        self.trajectory.as_ref().map_or(0, |t| t.keyframe_index(self.elapsed()))
    }

    /// Seconds into the current motion.
    pub fn elapsed(&self) -> f64 {
        self.cycle_index as f64 * self.config.cycle_ms / 1000.0
    }

    /// Check one position vector against limits (URDF with margin, and the 0..=4095 tick range).
    fn check_limits(&self, keyframe: usize, positions: &[f64]) -> Result<(), PlayerError> {
        if positions.len() != self.joints.len() {
            return Err(PlayerError::WrongLength { keyframe, got: positions.len(), expected: self.joints.len() });
        }
        let margin = self.config.limit_margin_rad;
        for (joint, &value) in self.joints.iter().zip(positions) {
            let lower = joint.limits.lower + margin;
            let upper = joint.limits.upper - margin;
            let ticks = joint.servo.ticks_from_joint(value);
            if !(value >= lower && value <= upper && (0.0..=4095.0).contains(&ticks.round())) {
                return Err(PlayerError::JointLimit { keyframe, joint: joint.servo.joint.clone(), value, lower, upper });
            }
        }
        Ok(())
    }

    /// Start a motion from the current measured positions. Every keyframe is checked against the
    /// joint limits before anything is sent.
    pub fn start(&mut self, motion: &Motion) -> Result<PlayerEvent, PlayerError> {
        if let PlayerState::Faulted(fault) = &self.state {
            return Err(PlayerError::Faulted(fault.to_string()));
        }
        if motion.keyframes.is_empty() {
            return Err(PlayerError::Empty(motion.name.clone()));
        }
        for (i, frame) in motion.keyframes.iter().enumerate() {
            self.check_limits(i, &frame.positions)?;
        }
        // Start from the measured pose; unknown joints start at their first keyframe value.
        let first = &motion.keyframes[0].positions;
        let start: Vec<f64> = self.last_present.iter().zip(first).map(|(p, f)| p.unwrap_or(*f)).collect();
        self.trajectory = Some(Trajectory::new(start, motion.keyframes.clone()));
        self.cycle_index = 0;
        self.state = PlayerState::Playing { name: motion.name.clone() };
        Ok(PlayerEvent::Started { name: motion.name.clone() })
    }

    /// Clear a fault/stop (after the operator toggled torque); back to idle.
    pub fn reset(&mut self) {
        self.state = PlayerState::Idle;
        self.trajectory = None;
    }

    /// Goal ticks for positions (rad).
    fn goal_ticks(&self, positions: &[f64]) -> Vec<(u8, u32)> {
        self.joints
            .iter()
            .zip(positions)
            .map(|(j, &q)| (j.servo.id, j.servo.ticks_from_joint(q).round().clamp(0.0, 4095.0) as u32))
            .collect()
    }

    /// Hold: command the last measured position of every servo that has one (best effort).
    fn hold(&mut self, bus: &mut dyn ServoBus) -> Option<Vec<f64>> {
        let targets: Vec<(u8, u32)> = self
            .joints
            .iter()
            .zip(&self.last_present)
            .filter_map(|(j, p)| p.map(|q| (j.servo.id, j.servo.ticks_from_joint(q).round().clamp(0.0, 4095.0) as u32)))
            .collect();
        if targets.is_empty() {
            return None;
        }
        servo_bus::sync_write_u32(bus, mx28::GOAL_POSITION, &targets).ok()?;
        Some(self.last_present.iter().map(|p| p.unwrap_or(f64::NAN)).collect())
    }

    fn fault(&self, error: BusError) -> Fault {
        let servo_id = error.servo_id();
        let joint = servo_id.and_then(|id| self.joints.iter().find(|j| j.servo.id == id)).map(|j| j.servo.joint.clone());
        Fault { servo_id, joint, error }
    }

    /// Read present positions; on failure keep the partial readings.
    fn read_present(&mut self, bus: &mut dyn ServoBus) -> Result<(), BusError> {
        let ids = self.ids();
        let result = servo_bus::read_present_each(bus, &ids, &mut self.read_ticks, &mut self.read_errors);
        for ((slot, joint), ticks) in self.last_present.iter_mut().zip(&self.joints).zip(&self.read_ticks) {
            if let Some(ticks) = ticks {
                *slot = Some(joint.servo.joint_from_ticks(f64::from(*ticks)));
            }
        }
        result
    }

    /// One control cycle. `estop` is the operator's stop request (honoured in this cycle).
    pub fn cycle(&mut self, bus: &mut dyn ServoBus, estop: bool) -> CycleReport {
        self.cycle_with_stop(bus, estop, &mut || false)
    }

    /// [`Player::cycle`] that also asks `stop_requested` between its transactions (after the goal
    /// write, before the read): a stop arriving during the write is honoured before the read
    /// instead of after it, so it never waits behind more than one bus transaction.
    pub fn cycle_with_stop(&mut self, bus: &mut dyn ServoBus, estop: bool, stop_requested: &mut dyn FnMut() -> bool) -> CycleReport {
        let mut report = CycleReport::default();
        let playing = matches!(self.state, PlayerState::Playing { .. });
        if estop && playing {
            // Freeze at the last measured pose and report it at once: the next cycle's read
            // refreshes the measurement (a read here would hold the report back by one more
            // transaction, 200 ms on a slow bus).
            report.goal = self.hold(bus);
            self.state = PlayerState::Stopped;
            self.trajectory = None;
            report.event = Some(PlayerEvent::EStopped);
            report.present = self.last_present.clone();
            return report;
        }
        if let (PlayerState::Playing { name }, Some(trajectory)) = (&self.state, &self.trajectory) {
            let name = name.clone();
            let t = self.elapsed();
            let goal = trajectory.sample(t);
            // 1 µs tolerance: keyframe durations are decimal seconds, cycle times are multiples of 8 ms.
            let finished = t >= trajectory.duration() - 1e-6;
            if let Err(limit) = self.check_limits(0, &goal) {
                let error = BusError::InvalidRequest(limit.to_string());
                report.event = Some(PlayerEvent::Fault(self.fault(error.clone())));
                self.state = PlayerState::Faulted(self.fault(error));
                report.goal = self.hold(bus);
                return report;
            }
            if let Err(error) = servo_bus::sync_write_u32(bus, mx28::GOAL_POSITION, &self.goal_ticks(&goal)) {
                let fault = self.fault(error);
                report.event = Some(PlayerEvent::Fault(fault.clone()));
                self.state = PlayerState::Faulted(fault);
                self.trajectory = None;
                return report;
            }
            report.goal = Some(goal);
            self.cycle_index += 1;
            if stop_requested() {
                // Freeze at the pose measured last cycle (the goal just written is one 8 ms step on).
                report.goal = self.hold(bus);
                self.state = PlayerState::Stopped;
                self.trajectory = None;
                report.event = Some(PlayerEvent::EStopped);
                report.present = self.last_present.clone();
                return report;
            }
            if finished {
                self.state = PlayerState::Idle;
                self.trajectory = None;
                report.event = Some(PlayerEvent::Finished { name });
            }
        }
        if let Err(error) = self.read_present(bus) {
            report.present = self.last_present.clone();
            let fault = self.fault(error);
            if matches!(self.state, PlayerState::Playing { .. }) {
                // During a motion: stop, hold the measured pose, latch until cleared.
                report.goal = self.hold(bus);
                self.trajectory = None;
                self.state = PlayerState::Faulted(fault.clone());
                report.event = Some(PlayerEvent::Fault(fault));
            } else if !matches!(self.state, PlayerState::Faulted(_)) {
                // Idle or training (torque off): nothing to stop; latch it so that nothing starts
                // and no stale position is recorded until the fault is cleared.
                self.state = PlayerState::Faulted(fault.clone());
                report.event = Some(PlayerEvent::Fault(fault));
            }
            return report;
        }
        report.present = self.last_present.clone();
        report
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use patchwalk_dynamixel::servo_bus::mock::MockBus;
    use patchwalk_spl::patch::Patch;

    fn joints(n: u8) -> Vec<JointSpec> {
        (1..=n)
            .map(|id| JointSpec {
                servo: ServoConfig { joint: format!("j{id}"), id, zero_offset: 0.0, direction: 1 },
                limits: JointLimits { lower: -1.5, upper: 1.5 },
            })
            .collect()
    }

    fn motion(frames: Vec<Keyframe>) -> Motion {
        Motion { name: "step".into(), patch: Patch::level_disc(0.02, nalgebra::Vector3::new(0.1, 0.0, -0.28)).unwrap(), keyframes: frames }
    }

    fn frame(value: f64, n: usize, move_s: f64, pause_s: f64) -> Keyframe {
        Keyframe { positions: vec![value; n], move_s, pause_s }
    }

    /// Torque on, one cycle to learn the present pose.
    fn ready(n: u8) -> (Player, MockBus) {
        let mut bus = MockBus::new(&(1..=n).collect::<Vec<_>>());
        for id in 1..=n {
            bus.write(id, mx28::TORQUE_ENABLE, &[1]).unwrap();
        }
        let mut player = Player::new(PlayerConfig::default(), joints(n));
        player.cycle(&mut bus, false);
        (player, bus)
    }

    #[test]
    fn minimum_jerk_profile_shape() {
        assert_eq!(minimum_jerk(0.0), 0.0);
        assert_eq!(minimum_jerk(1.0), 1.0);
        assert!((minimum_jerk(0.5) - 0.5).abs() < 1e-12);
        // zero slope at the ends, monotone in between
        assert!(minimum_jerk(1e-3) < 1e-8 && 1.0 - minimum_jerk(1.0 - 1e-3) < 1e-8);
        let samples: Vec<f64> = (0..=100).map(|i| minimum_jerk(f64::from(i) / 100.0)).collect();
        assert!(samples.windows(2).all(|w| w[1] >= w[0]));
    }

    #[test]
    fn trajectory_interpolates_pauses_and_ends_on_keyframes() {
        let traj = Trajectory::new(vec![0.0], vec![frame(1.0, 1, 1.0, 0.5), frame(-1.0, 1, 2.0, 0.0)]);
        assert_eq!(traj.duration(), 3.5);
        assert!((traj.sample(0.5)[0] - 0.5).abs() < 1e-12);
        assert_eq!(traj.sample(1.2), vec![1.0]);
        assert!((traj.sample(2.5)[0] - 0.0).abs() < 1e-12);
        assert_eq!(traj.sample(9.0), vec![-1.0]);
        assert_eq!((traj.keyframe_index(0.0), traj.keyframe_index(1.4), traj.keyframe_index(1.5), traj.keyframe_index(9.0)), (0, 0, 1, 1));
        let zero_move = Trajectory::new(vec![0.0], vec![frame(0.3, 1, 0.0, 0.1)]);
        assert_eq!(zero_move.sample(0.0), vec![0.3]);
    }

    #[test]
    fn timing_one_goal_write_per_8ms_cycle_until_the_end() {
        let (mut player, mut bus) = ready(12);
        player.start(&motion(vec![frame(0.5, 12, 0.4, 0.08), frame(0.0, 12, 0.4, 0.0)])).unwrap();
        let mut cycles = 0;
        let mut finished = false;
        while !finished && cycles < 1000 {
            let report = player.cycle(&mut bus, false);
            cycles += 1;
            finished = matches!(report.event, Some(PlayerEvent::Finished { .. }));
            assert!(report.goal.is_some());
        }
        // 0.88 s at 8 ms: goals at t = 0, 8, ..., 880 ms → 111 cycles, one sync write each.
        assert!(finished);
        assert_eq!(cycles, 111);
        let state = bus.state();
        assert_eq!(state.goal_writes.len(), 111);
        assert!(state.goal_writes.iter().all(|w| w.len() == 12));
        // Keyframe 1 reached exactly at t = 0.4 s (cycle 50) and held through the pause.
        let ticks_half = (2048.0 + 0.5 * 4096.0 / std::f64::consts::TAU).round() as i32;
        assert!(state.goal_writes[50..=60].iter().all(|w| w[0].1 == ticks_half));
        assert_eq!(state.goal_writes[110][0].1, 2048);
        drop(state);
        assert_eq!(player.state(), &PlayerState::Idle);
    }

    #[test]
    fn interpolation_is_monotone_between_keyframes() {
        let (mut player, mut bus) = ready(2);
        player.start(&motion(vec![frame(1.0, 2, 0.2, 0.0)])).unwrap();
        while !matches!(player.cycle(&mut bus, false).event, Some(PlayerEvent::Finished { .. })) {}
        let goals: Vec<i32> = bus.state().goal_writes.iter().map(|w| w[0].1).collect();
        assert_eq!(goals.first(), Some(&2048));
        assert!(goals.windows(2).all(|w| w[1] >= w[0]), "{goals:?}");
        assert_eq!(goals.last(), Some(&(2048 + (4096.0 / std::f64::consts::TAU).round() as i32)));
    }

    #[test]
    fn joint_limits_checked_before_anything_is_sent() {
        let (mut player, mut bus) = ready(12);
        let mut bad = frame(0.2, 12, 0.5, 0.0);
        bad.positions[7] = 1.6;
        let err = player.start(&motion(vec![frame(0.1, 12, 0.5, 0.0), bad])).unwrap_err();
        assert!(matches!(err, PlayerError::JointLimit { keyframe: 1, ref joint, .. } if joint == "j8"), "{err}");
        player.cycle(&mut bus, false);
        assert!(bus.state().goal_writes.is_empty());
        assert!(matches!(player.start(&motion(vec![frame(0.1, 11, 0.5, 0.0)])), Err(PlayerError::WrongLength { .. })));
    }

    #[test]
    fn missing_servo_mid_motion_stops_and_holds() {
        let (mut player, mut bus) = ready(12);
        bus.state().max_step_ticks = 5;
        player.start(&motion(vec![frame(1.0, 12, 1.0, 0.0)])).unwrap();
        for _ in 0..20 {
            assert!(player.cycle(&mut bus, false).event.is_none());
        }
        bus.state().servos.get_mut(&4).unwrap().silent = true;
        let report = player.cycle(&mut bus, false);
        let Some(PlayerEvent::Fault(fault)) = report.event else { panic!("{report:?}") };
        assert_eq!(fault.servo_id, Some(4));
        assert_eq!(fault.joint.as_deref(), Some("j4"));
        assert_eq!(fault.error, BusError::Timeout { id: 4 });
        // Hold: the last write commands the measured positions (goal == present for live servos).
        let state = bus.state();
        let hold = state.goal_writes.last().unwrap();
        assert_eq!(hold.len(), 11);
        for (id, goal) in hold {
            assert_eq!(*goal, state.servos[id].present, "servo {id}");
        }
        let writes = state.goal_writes.len();
        drop(state);
        // Faulted: later cycles send nothing and playback cannot restart until reset.
        player.cycle(&mut bus, false);
        assert_eq!(bus.state().goal_writes.len(), writes);
        assert!(matches!(player.start(&motion(vec![frame(0.0, 12, 0.1, 0.0)])), Err(PlayerError::Faulted(_))));
        player.reset();
        assert_eq!(player.state(), &PlayerState::Idle);
    }

    #[test]
    fn idle_read_failure_latches_until_reset() {
        let (mut player, mut bus) = ready(3);
        bus.state().servos.get_mut(&2).unwrap().silent = true;
        let report = player.cycle(&mut bus, false);
        assert!(matches!(report.event, Some(PlayerEvent::Fault(Fault { servo_id: Some(2), .. }))), "{report:?}");
        assert!(matches!(player.state(), PlayerState::Faulted(_)));
        assert_eq!(player.last_errors()[1], Some(BusError::Timeout { id: 2 }));
        assert_eq!(player.last_errors()[0], None);
        // Reported once, refused to start, nothing written.
        assert_eq!(player.cycle(&mut bus, false).event, None);
        assert!(matches!(player.start(&motion(vec![frame(0.1, 3, 0.1, 0.0)])), Err(PlayerError::Faulted(_))));
        assert!(bus.state().goal_writes.is_empty());
        bus.state().servos.get_mut(&2).unwrap().silent = false;
        player.reset();
        assert_eq!(player.cycle(&mut bus, false).event, None);
        assert_eq!(player.state(), &PlayerState::Idle);
    }

    #[test]
    fn external_fault_holds_a_motion_and_a_stop_between_transactions_is_honoured() {
        let (mut player, mut bus) = ready(2);
        bus.state().max_step_ticks = 3;
        player.start(&motion(vec![frame(1.0, 2, 1.0, 0.0)])).unwrap();
        for _ in 0..5 {
            player.cycle(&mut bus, false);
        }
        let report = player.fault_external(&mut bus, BusError::TooSlow { rate_hz: 5.0, nominal_hz: 125.0, detail: "test".into() }).unwrap();
        assert!(matches!(report.event, Some(PlayerEvent::Fault(Fault { servo_id: None, .. }))));
        let state = bus.state();
        assert!(state.goal_writes.last().unwrap().iter().all(|(id, goal)| *goal == state.servos[id].present));
        drop(state);
        assert!(player.fault_external(&mut bus, BusError::Io("again".into())).is_none(), "latched once");
        player.reset();
        player.start(&motion(vec![frame(1.0, 2, 1.0, 0.0)])).unwrap();
        let reads = bus.state().sync_reads;
        let report = player.cycle_with_stop(&mut bus, false, &mut || true);
        assert_eq!(report.event, Some(PlayerEvent::EStopped));
        assert_eq!(bus.state().sync_reads, reads, "stopped before the read");
        assert_eq!(player.state(), &PlayerState::Stopped);
    }

    #[test]
    fn hardware_error_bit_is_reported_with_servo_and_bits() {
        let (mut player, mut bus) = ready(12);
        player.start(&motion(vec![frame(0.5, 12, 0.5, 0.0)])).unwrap();
        player.cycle(&mut bus, false);
        bus.state().servos.get_mut(&9).unwrap().hardware_error = mx28::HW_OVERHEATING;
        let report = player.cycle(&mut bus, false);
        let Some(PlayerEvent::Fault(fault)) = report.event else { panic!("{report:?}") };
        assert_eq!(fault.error, BusError::Hardware { id: 9, bits: mx28::HW_OVERHEATING });
        assert!(matches!(player.state(), PlayerState::Faulted(_)));
    }

    #[test]
    fn estop_is_honoured_in_the_same_cycle() {
        let (mut player, mut bus) = ready(12);
        bus.state().max_step_ticks = 3;
        player.start(&motion(vec![frame(1.0, 12, 1.0, 0.0)])).unwrap();
        for _ in 0..10 {
            player.cycle(&mut bus, false);
        }
        let writes_before = bus.state().goal_writes.len();
        let report = player.cycle(&mut bus, true);
        assert_eq!(report.event, Some(PlayerEvent::EStopped));
        let state = bus.state();
        // Exactly one more write: the hold at the measured pose, not a trajectory goal.
        assert_eq!(state.goal_writes.len(), writes_before + 1);
        let hold = state.goal_writes.last().unwrap();
        assert!(hold.iter().all(|(id, goal)| *goal == state.servos[id].present));
        drop(state);
        assert_eq!(player.state(), &PlayerState::Stopped);
        player.cycle(&mut bus, false);
        assert_eq!(bus.state().goal_writes.len(), writes_before + 1);
    }
}

//! Head motion: where the robot stands and where its camera looks.
//!
//! The robot stands at a station in front of a rock in the lookdown pose of J 6.3 (camera ≈ 0.45 m
//! above the table, pitched ≈ 49° down, as in `urdf/rpbp.urdf`), optionally with a walking-like sway
//! (lateral sway at the gait frequency, vertical bob at twice it, roll) plus smooth seeded jitter.
//! `StanceTracker` lets the pose follow the servos: the lower foot stays planted on the table and
//! `world_from_base = world_from_stance_foot · base_from_stance_foot(q)⁻¹`.

use std::f64::consts::{FRAC_PI_2, TAU};

use nalgebra::{Isometry3, Translation3, UnitQuaternion, Vector3};
use rand::{Rng, SeedableRng};
use serde::{Deserialize, Serialize};

/// Walking-like sway and jitter of the base (all amplitudes are peak values).
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct SwayConfig {
    pub enabled: bool,
    /// Gait (stride) frequency (Hz); small bipeds step at ≈ 1–2 Hz, one sway period per stride.
    pub frequency_hz: f64,
    /// Lateral (y) sway amplitude (m).
    pub lateral_m: f64,
    /// Vertical bob amplitude (m), at twice the gait frequency.
    pub vertical_m: f64,
    /// Roll amplitude (deg) in phase with the lateral sway.
    pub roll_deg: f64,
    /// Smooth random jitter amplitude per rotation axis (deg) and per translation axis (m).
    pub jitter_deg: f64,
    pub jitter_m: f64,
}

impl Default for SwayConfig {
    fn default() -> Self {
        Self { enabled: false, frequency_hz: 0.8, lateral_m: 0.012, vertical_m: 0.004, roll_deg: 2.0, jitter_deg: 0.3, jitter_m: 0.002 }
    }
}

/// The lookdown pose (defaults from `urdf/rpbp.urdf` at zero joint angles).
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct MotionConfig {
    /// `base_link` height above the table with straight legs (forward kinematics of `urdf/rpbp.urdf`
    /// at zero angles: sole 0.295 m below base_link; the URDF header comment says 0.285).
    pub base_height_m: f64,
    /// `camera_optical` origin in `base_link` (URDF head 0.01,0,0.14 + camera 0.03,0,0.03).
    pub camera_in_base_m: [f64; 3],
    /// Camera pitch down (rad); URDF `camera_fixed` rpy 0 0.85 0 (≈ 49°, J 6.3 lookdown pose).
    pub camera_pitch_rad: f64,
    pub sway: SwayConfig,
}

impl Default for MotionConfig {
    fn default() -> Self {
        Self { base_height_m: 0.295, camera_in_base_m: [0.04, 0.0, 0.17], camera_pitch_rad: 0.85, sway: SwayConfig::default() }
    }
}

/// `camera_link_from_camera_optical` (REP-103 optical frame: x right, y down, z forward).
pub fn link_from_optical() -> UnitQuaternion<f64> {
    UnitQuaternion::from_euler_angles(-FRAC_PI_2, 0.0, -FRAC_PI_2)
}

/// `base_from_camera` (optical) of the lookdown pose.
pub fn base_from_camera_lookdown(config: &MotionConfig) -> Isometry3<f64> {
    let [x, y, z] = config.camera_in_base_m;
    let base_from_link = UnitQuaternion::from_euler_angles(0.0, config.camera_pitch_rad, 0.0);
    Isometry3::from_parts(Translation3::new(x, y, z), base_from_link * link_from_optical())
}

/// Deterministic head motion over time around a station.
#[derive(Debug, Clone)]
pub struct HeadMotion {
    pub config: MotionConfig,
    /// Jitter: per axis (3 rotation + 3 translation) three (frequency Hz, phase) components.
    jitter: [[(f64, f64); 3]; 6],
    sway_phase: f64,
}

impl HeadMotion {
    pub fn new(config: MotionConfig, seed: u64) -> Self {
        let mut rng = rand::rngs::StdRng::seed_from_u64(seed ^ 0x6d6f_7469_6f6e);
        let mut jitter = [[(0.0, 0.0); 3]; 6];
        for axis in &mut jitter {
            for component in axis.iter_mut() {
                *component = (rng.random_range(1.1..4.3), rng.random_range(0.0..TAU));
            }
        }
        Self { config, jitter, sway_phase: rng.random_range(0.0..TAU) }
    }

    /// `world_from_base` at time `t` (s) for a robot standing at `world_from_station` (a pose on
    /// the table under `base_link`).
    pub fn world_from_base(&self, world_from_station: &Isometry3<f64>, t: f64) -> Isometry3<f64> {
        let standing = world_from_station * Isometry3::translation(0.0, 0.0, self.config.base_height_m);
        standing * self.sway(t)
    }

    /// `world_from_camera` (optical) at time `t`.
    pub fn world_from_camera(&self, world_from_station: &Isometry3<f64>, base_from_camera: &Isometry3<f64>, t: f64) -> Isometry3<f64> {
        self.world_from_base(world_from_station, t) * base_from_camera
    }

    /// Offset of the swaying base from its standing pose (identity when disabled).
    pub fn sway(&self, t: f64) -> Isometry3<f64> {
        let s = &self.config.sway;
        if !s.enabled {
            return Isometry3::identity();
        }
        let phase = TAU * s.frequency_hz * t + self.sway_phase;
        let jitter = |axis: usize| -> f64 {
            self.jitter.get(axis).map_or(0.0, |components| components.iter().map(|(f, p)| (TAU * f * t + p).sin()).sum::<f64>() / 3.0)
        };
        let jitter_rad = s.jitter_deg.to_radians();
        let translation = Vector3::new(
            s.jitter_m * jitter(3),
            s.lateral_m * phase.sin() + s.jitter_m * jitter(4),
            s.vertical_m * (2.0 * phase).sin() + s.jitter_m * jitter(5),
        );
        let rotation = UnitQuaternion::from_euler_angles(
            s.roll_deg.to_radians() * phase.sin() + jitter_rad * jitter(0),
            jitter_rad * jitter(1),
            jitter_rad * jitter(2),
        );
        Isometry3::from_parts(Translation3::from(translation), rotation)
    }
}

/// Keeps the supporting foot planted while joint positions change, so the base (and camera) move
/// as the servos do.
#[derive(Debug, Clone)]
pub struct StanceTracker {
    world_from_base: Isometry3<f64>,
    /// Planted foot: (is_left, world_from_foot).
    stance: Option<(bool, Isometry3<f64>)>,
}

impl StanceTracker {
    /// Starts at a station: the base is placed so the lower foot stands on the table (z = 0).
    pub fn new(world_from_station: &Isometry3<f64>, base_from_left: &Isometry3<f64>, base_from_right: &Isometry3<f64>) -> Self {
        let lowest = base_from_left.translation.z.min(base_from_right.translation.z);
        let world_from_base = world_from_station * Isometry3::translation(0.0, 0.0, -lowest);
        let mut tracker = Self { world_from_base, stance: None };
        tracker.update(base_from_left, base_from_right);
        tracker
    }

    /// New joint positions (as foot poses in `base_link`): the lower foot is the stance foot; if it
    /// changed, it is planted where it now is. Returns `world_from_base`.
    pub fn update(&mut self, base_from_left: &Isometry3<f64>, base_from_right: &Isometry3<f64>) -> Isometry3<f64> {
        let left_is_lower = base_from_left.translation.z <= base_from_right.translation.z;
        let base_from_stance = if left_is_lower { base_from_left } else { base_from_right };
        match self.stance {
            Some((left, world_from_foot)) if left == left_is_lower => {
                self.world_from_base = world_from_foot * base_from_stance.inverse();
            }
            _ => {
                self.stance = Some((left_is_lower, self.world_from_base * base_from_stance));
            }
        }
        self.world_from_base
    }

    pub fn world_from_base(&self) -> Isometry3<f64> {
        self.world_from_base
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn lookdown_camera_is_high_and_pitched_down() {
        let config = MotionConfig::default();
        let base_from_camera = base_from_camera_lookdown(&config);
        let motion = HeadMotion::new(config, 1);
        let world_from_camera = motion.world_from_camera(&Isometry3::translation(0.5, 0.2, 0.0), &base_from_camera, 0.0);
        assert!((world_from_camera.translation.z - 0.465).abs() < 1e-12);
        let optical_axis = world_from_camera.rotation * Vector3::z();
        let pitch_down = (-optical_axis.z).asin();
        assert!((pitch_down - 0.85).abs() < 1e-9, "{pitch_down}");
        assert!(optical_axis.x > 0.0 && optical_axis.y.abs() < 1e-12);
        // Image x (right) points to the robot's right (−y), image y (down) has a downward component.
        assert!(((world_from_camera.rotation * Vector3::x()) + Vector3::y()).norm() < 1e-9);
        assert!((world_from_camera.rotation * Vector3::y()).z < 0.0);
    }

    #[test]
    fn sway_is_bounded_smooth_and_seeded() {
        let config = MotionConfig { sway: SwayConfig { enabled: true, ..SwayConfig::default() }, ..MotionConfig::default() };
        let a = HeadMotion::new(config, 3);
        let b = HeadMotion::new(config, 3);
        let station = Isometry3::identity();
        let mut max_lateral: f64 = 0.0;
        for i in 0..400 {
            let t = i as f64 * 0.01;
            let pose = a.world_from_base(&station, t);
            assert_eq!(pose, b.world_from_base(&station, t));
            max_lateral = max_lateral.max(pose.translation.y.abs());
            let next = a.world_from_base(&station, t + 0.001);
            assert!((next.translation.vector - pose.translation.vector).norm() < 1e-3);
        }
        assert!(max_lateral > 0.008 && max_lateral <= 0.012 + 0.002 + 1e-9, "{max_lateral}");
        assert_eq!(HeadMotion::new(MotionConfig::default(), 3).sway(1.3), Isometry3::identity());
    }

    #[test]
    fn stance_foot_stays_planted() {
        let left = Isometry3::translation(0.0, 0.04, -0.285);
        let right = Isometry3::translation(0.0, -0.04, -0.285);
        let station = Isometry3::translation(1.0, 2.0, 0.0);
        let mut tracker = StanceTracker::new(&station, &left, &right);
        assert!((tracker.world_from_base().translation.vector - Vector3::new(1.0, 2.0, 0.285)).norm() < 1e-12);
        // Right foot lifts; knees bend so the left foot is 2 cm closer to the base: base drops 2 cm.
        let left_bent = Isometry3::translation(0.0, 0.04, -0.265);
        let right_up = Isometry3::translation(0.05, -0.04, -0.20);
        let base = tracker.update(&left_bent, &right_up);
        assert!((base.translation.z - 0.265).abs() < 1e-12);
        let world_left = base * left_bent;
        assert!(world_left.translation.z.abs() < 1e-12);
    }
}

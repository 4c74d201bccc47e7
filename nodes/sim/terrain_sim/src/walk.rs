//! A walk along the table, for tracking tests and benches: the robot side-steps along the line of
//! stations (station +y) facing the rocks, in steps (its speed goes from 0 to twice the mean within
//! each step), bobbing up at every step and rolling from foot to foot, while its heading sways. The
//! camera clock runs at `camera.rate_hz`; taking every k-th frame gives sequences with k times the
//! motion between frames (e.g. 10 cm and 10° at k = 12 with the defaults).
//!
//! ```text
//! y(t)    = v t − v/(4π f) sin(2π f t)          (steps at f Hz: speed v/2 … 3v/2)
//! z(t)    = z₀ + b |sin(π f t)|                  (a bob at every step)
//! roll(t) = ρ sin(π f t)                          (foot to foot)
//! yaw(t)  = A sin(2π t / T)                       (heading sway)
//! world_from_camera(t) = station · Trans(0, y, z) · Rz(yaw) · Rx(roll) · base_from_camera
//! ```

use nalgebra::{Isometry3, Translation3, UnitQuaternion, Vector3};
use serde::{Deserialize, Serialize};
use std::f64::consts::{PI, TAU};

use crate::imu::ImuSample;
use crate::sim::{DepthFrame, Simulator};

/// The walk's parameters.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct WalkConfig {
    /// Mean walking speed v (m/s).
    pub speed_mps: f64,
    /// Steps per second f.
    pub step_hz: f64,
    /// Bob height b at each step (m).
    pub bob_m: f64,
    /// Roll amplitude ρ (deg).
    pub roll_deg: f64,
    /// Heading sway amplitude A (deg) and period T (s).
    pub yaw_amplitude_deg: f64,
    pub yaw_period_s: f64,
}

impl Default for WalkConfig {
    fn default() -> Self {
        // A small biped's 12.5 cm steps at 2 Hz, with a 20° heading sway over 5 s: 10 cm and up to
        // 10° between frames at 12 frames (0.4 s) apart.
        Self { speed_mps: 0.25, step_hz: 2.0, bob_m: 0.01, roll_deg: 3.0, yaw_amplitude_deg: 20.0, yaw_period_s: 5.0 }
    }
}

/// A walking simulator: the scene, camera and IMU of `sim` along the walk from its station.
#[derive(Debug, Clone)]
pub struct Walk<'a> {
    pub sim: &'a Simulator,
    pub config: WalkConfig,
}

impl<'a> Walk<'a> {
    pub fn new(sim: &'a Simulator, config: WalkConfig) -> Self {
        Self { sim, config }
    }

    /// `world_from_base` at time `t` (s).
    pub fn world_from_base(&self, t: f64) -> Isometry3<f64> {
        let c = &self.config;
        let f = c.step_hz;
        let y = if f > 0.0 { c.speed_mps * t - c.speed_mps / (2.0 * TAU * f) * (TAU * f * t).sin() } else { c.speed_mps * t };
        let z = self.sim.config.motion.base_height_m + c.bob_m * (PI * f * t).sin().abs();
        let roll = c.roll_deg.to_radians() * (PI * f * t).sin();
        let yaw = if c.yaw_period_s > 0.0 { c.yaw_amplitude_deg.to_radians() * (TAU * t / c.yaw_period_s).sin() } else { 0.0 };
        let rotation = UnitQuaternion::from_axis_angle(&Vector3::z_axis(), yaw) * UnitQuaternion::from_axis_angle(&Vector3::x_axis(), roll);
        self.sim.world_from_station * Isometry3::from_parts(Translation3::new(0.0, y, z), rotation)
    }

    /// `world_from_camera` (optical) at time `t`.
    pub fn world_from_camera(&self, t: f64) -> Isometry3<f64> {
        self.world_from_base(t) * self.sim.base_from_camera
    }

    /// Depth frame `index` of the camera clock, rendered on the walk.
    pub fn depth_frame(&self, index: u64) -> DepthFrame {
        let t = index as f64 / self.sim.config.camera.rate_hz;
        self.sim.render_at(t, &self.world_from_camera(t), index)
    }

    /// IMU sample `index` of the IMU clock on the walk (the accelerometer feels the walk's accelerations).
    pub fn imu_sample(&self, index: u64) -> ImuSample {
        let t = index as f64 / self.sim.config.imu.rate_hz;
        self.sim.imu.sample(|time| self.world_from_camera(time), t, crate::camera::mix(self.sim.config.seed ^ 0x1a0, index))
    }

    /// Unit gravity (down) in the camera frame at time `t` as the pipeline gets it: the accelerometer
    /// readings within `half_window_s` of `t` (their per-axis median ā), `ĝ = −camera_from_imu · ā / |ā|`
    /// (J 2.2).
    pub fn gravity_in_camera(&self, t: f64, half_window_s: f64) -> Option<Vector3<f64>> {
        let rate = self.sim.config.imu.rate_hz;
        let first = ((t - half_window_s) * rate).ceil().max(0.0) as u64;
        let last = ((t + half_window_s) * rate).floor().max(0.0) as u64;
        let readings: Vec<Vector3<f64>> = (first..=last).map(|j| self.imu_sample(j).linear_acceleration_in_imu).collect();
        let median = patchwalk_fusion::dataset::median_per_axis(&readings)?;
        (-(self.sim.imu.camera_from_imu * median)).try_normalize(1e-9)
    }

    /// How far the camera moves from frame `a` to frame `b` of the camera clock: (m, deg).
    pub fn motion_between(&self, a: u64, b: u64) -> (f64, f64) {
        let rate = self.sim.config.camera.rate_hz;
        let step = self.world_from_camera(a as f64 / rate).inverse() * self.world_from_camera(b as f64 / rate);
        (step.translation.vector.norm(), step.rotation.angle().to_degrees())
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::config::SimConfig;

    #[test]
    fn every_twelfth_frame_is_about_ten_centimetres_and_up_to_ten_degrees_apart() {
        let sim = Simulator::new(SimConfig::default()).unwrap();
        let walk = Walk::new(&sim, WalkConfig::default());
        let steps: Vec<(f64, f64)> = (0..25u64).map(|k| walk.motion_between(12 * k, 12 * (k + 1))).collect();
        let mean_m = steps.iter().map(|s| s.0).sum::<f64>() / steps.len() as f64;
        let max_deg = steps.iter().map(|s| s.1).fold(0.0, f64::max);
        assert!((0.08..0.13).contains(&mean_m), "{mean_m}");
        assert!((8.0..13.0).contains(&max_deg), "{max_deg}");
        // The walk starts at the station's standing pose and stays on the table (z = 0 plane below).
        let start = walk.world_from_base(0.0);
        let standing = sim.world_from_station * Isometry3::translation(0.0, 0.0, sim.config.motion.base_height_m);
        assert!((start.translation.vector - standing.translation.vector).norm() < 1e-9);
        let frame = walk.depth_frame(36);
        assert!(frame.depth.valid_count() > frame.depth.depth_m.len() / 2, "the table fills the view");
        // The accelerometer's gravity is off the truth by the walk's accelerations (the steps' up to
        // 1.6 m/s² tilt it by up to 9°), not more.
        let t = 36.0 / sim.config.camera.rate_hz;
        let truth = walk.world_from_camera(t).rotation.inverse() * -Vector3::z();
        let measured = walk.gravity_in_camera(t, 0.05).unwrap();
        let error_deg = measured.angle(&truth).to_degrees();
        assert!(error_deg < 10.0, "{error_deg}");
    }
}

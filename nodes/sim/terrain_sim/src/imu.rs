//! Simulated IMU (J 2.2, 6.2: CH Robotics UM6 on top of the depth camera, 100 Hz): accelerometer
//! (specific force = body acceleration + gravity reaction, plus noise), gyroscope and orientation
//! relative to a gravity-aligned world, rigidly mounted with a known rotation `camera_from_imu`.

use nalgebra::{Isometry3, Quaternion, UnitQuaternion, Vector3};
use rand::SeedableRng;
use rand_distr::{Distribution, StandardNormal};
use serde::{Deserialize, Serialize};

/// IMU rate, mounting and noise.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct ImuConfig {
    /// J 2.2: 100 Hz IMU data.
    pub rate_hz: f64,
    /// Rotation `camera_from_imu` as a quaternion `[x, y, z, w]` (`camera_optical` from `imu`).
    /// Default: the URDF mount (IMU axes = camera_link axes: x forward, y left, z up).
    pub camera_from_imu_xyzw: [f64; 4],
    /// Accelerometer white noise σ per axis (m/s²), MEMS order at 100 Hz.
    pub accel_noise_mps2: f64,
    /// Gyroscope white noise σ per axis (rad/s).
    pub gyro_noise_radps: f64,
    /// Orientation estimate noise σ per axis (deg).
    pub orientation_noise_deg: f64,
    /// Gravity magnitude (m/s²).
    pub gravity_mps2: f64,
}

impl Default for ImuConfig {
    fn default() -> Self {
        Self {
            rate_hz: 100.0,
            camera_from_imu_xyzw: [0.5, -0.5, 0.5, 0.5],
            accel_noise_mps2: 0.02,
            gyro_noise_radps: 0.005,
            orientation_noise_deg: 0.3,
            gravity_mps2: 9.81,
        }
    }
}

impl ImuConfig {
    /// The mounting rotation; errors if the quaternion is not finite or zero.
    pub fn camera_from_imu(&self) -> Result<UnitQuaternion<f64>, ImuError> {
        let [x, y, z, w] = self.camera_from_imu_xyzw;
        let q = Quaternion::new(w, x, y, z);
        let norm = q.norm();
        if !(norm.is_finite() && norm > 1e-9) {
            return Err(ImuError::Invalid(format!("camera_from_imu_xyzw {:?} is not a rotation", self.camera_from_imu_xyzw)));
        }
        Ok(UnitQuaternion::from_quaternion(q))
    }
}

#[derive(Debug, thiserror::Error, PartialEq)]
pub enum ImuError {
    #[error("invalid imu config: {0}")]
    Invalid(String),
}

/// One IMU sample, all vectors in the `imu` frame.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ImuSample {
    pub timestamp: f64,
    /// Specific force (m/s²): reads ≈ +g upward at rest.
    pub linear_acceleration_in_imu: Vector3<f64>,
    pub angular_velocity_in_imu: Vector3<f64>,
    /// Orientation estimate (`world_from_imu`, world z up).
    pub world_from_imu: UnitQuaternion<f64>,
}

/// The simulated IMU.
#[derive(Debug, Clone)]
pub struct Imu {
    pub config: ImuConfig,
    pub camera_from_imu: UnitQuaternion<f64>,
}

/// Finite-difference step (s) for velocities and accelerations of the analytic motion.
const DIFF_STEP_S: f64 = 2e-3;

impl Imu {
    pub fn new(config: ImuConfig) -> Result<Self, ImuError> {
        if !(config.rate_hz > 0.0 && config.gravity_mps2 > 0.0) {
            return Err(ImuError::Invalid("rate_hz and gravity_mps2 must be positive".into()));
        }
        if !(config.accel_noise_mps2 >= 0.0 && config.gyro_noise_radps >= 0.0 && config.orientation_noise_deg >= 0.0) {
            return Err(ImuError::Invalid("noise sigmas must be ≥ 0".into()));
        }
        Ok(Self { camera_from_imu: config.camera_from_imu()?, config })
    }

    /// Sample at time `t` of an IMU on a camera moving as `world_from_camera(t)`; `noise_seed`
    /// (e.g. seed ⊕ sample index) makes the noise reproducible.
    pub fn sample(&self, world_from_camera: impl Fn(f64) -> Isometry3<f64>, t: f64, noise_seed: u64) -> ImuSample {
        let world_from_imu = |time: f64| {
            let pose = world_from_camera(time);
            Isometry3::from_parts(pose.translation, pose.rotation * self.camera_from_imu)
        };
        let h = DIFF_STEP_S;
        // The motion starts at t = 0 (a camera path is held at its start before it): the derivatives
        // of the first samples come from the stencil one step on, as a recording that begins on the
        // move feels them. The held start would read the path's speed appearing within a step as an
        // acceleration of tens of m/s², and the gravity of the first frames with it.
        let centre = t.max(h);
        let (before, middle, after) = (world_from_imu(centre - h), world_from_imu(centre), world_from_imu(centre + h));
        let now = if t < h { world_from_imu(t) } else { middle };
        let acceleration_in_world = (after.translation.vector - 2.0 * middle.translation.vector + before.translation.vector) / (h * h);
        let specific_force_in_world = acceleration_in_world + Vector3::new(0.0, 0.0, self.config.gravity_mps2);
        // ω (world) from R(t+h)·R(t−h)ᵀ = exp(2h·[ω]×).
        let angular_velocity_in_world = (after.rotation * before.rotation.inverse()).scaled_axis() / (2.0 * h);
        let imu_from_world = now.rotation.inverse();
        let mut rng = rand::rngs::SmallRng::seed_from_u64(noise_seed);
        let mut gaussian = |sigma: f64| {
            let e: [f64; 3] = [StandardNormal.sample(&mut rng), StandardNormal.sample(&mut rng), StandardNormal.sample(&mut rng)];
            Vector3::new(e[0], e[1], e[2]) * sigma
        };
        let accel_noise = gaussian(self.config.accel_noise_mps2);
        let gyro_noise = gaussian(self.config.gyro_noise_radps);
        let orientation_noise = gaussian(self.config.orientation_noise_deg.to_radians());
        ImuSample {
            timestamp: t,
            linear_acceleration_in_imu: imu_from_world * specific_force_in_world + accel_noise,
            angular_velocity_in_imu: imu_from_world * angular_velocity_in_world + gyro_noise,
            world_from_imu: now.rotation * UnitQuaternion::from_scaled_axis(orientation_noise),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::motion::{base_from_camera_lookdown, HeadMotion, MotionConfig, SwayConfig};

    #[test]
    fn default_mount_maps_imu_axes_like_the_urdf() {
        let camera_from_imu = ImuConfig::default().camera_from_imu().unwrap();
        // IMU x forward → optical z; y left → optical −x; z up → optical −y.
        assert!((camera_from_imu * Vector3::x() - Vector3::z()).norm() < 1e-12);
        assert!((camera_from_imu * Vector3::y() + Vector3::x()).norm() < 1e-12);
        assert!((camera_from_imu * Vector3::z() + Vector3::y()).norm() < 1e-12);
    }

    /// The mapper's configuration for the simulated rig carries this mount as its row-major
    /// `mapper.acquire.camera_from_imu`; the two must agree.
    #[test]
    fn mapper_sim_config_has_the_default_mount() {
        let path = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("../../../config/patch_mapper_sim.yaml");
        let config: serde_yaml_ng::Value = serde_yaml_ng::from_str(&std::fs::read_to_string(path).unwrap()).unwrap();
        let params = &config["/**/patch_mapper"]["ros__parameters"];
        let rows: Vec<Vec<f64>> = serde_yaml_ng::from_value(params["mapper"]["acquire"]["camera_from_imu"].clone()).unwrap();
        let configured = nalgebra::Matrix3::from_fn(|r, c| rows[r][c]);
        let mount = ImuConfig::default().camera_from_imu().unwrap().to_rotation_matrix().into_inner();
        assert!((configured - mount).norm() < 1e-12, "{configured} vs {mount}");
    }

    #[test]
    fn gravity_in_camera_frame_matches_mounting() {
        // A deliberately misaligned mount: the accelerometer, rotated into the camera frame with
        // camera_from_imu, must point opposite to gravity (world −z) seen from the camera.
        let mount = UnitQuaternion::from_euler_angles(0.3, -0.2, 1.1);
        let q = mount.quaternion();
        let config = ImuConfig { camera_from_imu_xyzw: [q.i, q.j, q.k, q.w], accel_noise_mps2: 0.0, ..ImuConfig::default() };
        let imu = Imu::new(config).unwrap();
        let motion = HeadMotion::new(MotionConfig::default(), 0);
        let base_from_camera = base_from_camera_lookdown(&MotionConfig::default());
        let station = Isometry3::translation(0.3, 0.2, 0.0);
        let world_from_camera = |t: f64| motion.world_from_camera(&station, &base_from_camera, t);
        let sample = imu.sample(world_from_camera, 0.5, 9);
        let up_in_camera = world_from_camera(0.5).rotation.inverse() * Vector3::z();
        let accel_in_camera = imu.camera_from_imu * sample.linear_acceleration_in_imu;
        assert!((accel_in_camera.normalize() - up_in_camera).norm() < 1e-6);
        assert!((sample.linear_acceleration_in_imu.norm() - 9.81).abs() < 1e-6);
        assert!(sample.angular_velocity_in_imu.norm() < 0.05);
    }

    #[test]
    fn sway_shows_in_accelerometer_and_gyro() {
        let config = MotionConfig { sway: SwayConfig { enabled: true, ..SwayConfig::default() }, ..MotionConfig::default() };
        let motion = HeadMotion::new(config, 2);
        let base_from_camera = base_from_camera_lookdown(&config);
        let imu = Imu::new(ImuConfig::default()).unwrap();
        let station = Isometry3::identity();
        let samples: Vec<ImuSample> =
            (0..200).map(|i| imu.sample(|t| motion.world_from_camera(&station, &base_from_camera, t), i as f64 * 0.01, i)).collect();
        let mean_norm = samples.iter().map(|s| s.linear_acceleration_in_imu.norm()).sum::<f64>() / 200.0;
        assert!((mean_norm - 9.81).abs() < 0.1, "{mean_norm}");
        let max_gyro = samples.iter().map(|s| s.angular_velocity_in_imu.norm()).fold(0.0, f64::max);
        // Roll 2° at 0.8 Hz → ≈ 0.18 rad/s peak.
        assert!(max_gyro > 0.1, "{max_gyro}");
        // Same seed → same noise.
        let again = imu.sample(|t| motion.world_from_camera(&station, &base_from_camera, t), 0.3, 30);
        assert_eq!(again, samples[30]);
    }

    #[test]
    fn a_path_that_starts_on_the_move_reads_only_gravity_at_its_start() {
        // Held at the origin before t = 0, then walking at 0.15 m/s along x.
        let imu = Imu::new(ImuConfig { accel_noise_mps2: 0.0, gyro_noise_radps: 0.0, ..ImuConfig::default() }).unwrap();
        let walk = |t: f64| Isometry3::translation(0.15 * t.max(0.0), 0.0, 0.0);
        for t in [0.0, 0.001, 0.01] {
            let sample = imu.sample(walk, t, 1);
            assert!((sample.linear_acceleration_in_imu.norm() - 9.81).abs() < 1e-6, "t = {t}: {}", sample.linear_acceleration_in_imu);
            assert!(sample.angular_velocity_in_imu.norm() < 1e-9);
            assert_eq!(sample.timestamp, t);
        }
    }

    #[test]
    fn bad_mount_is_an_error() {
        let config = ImuConfig { camera_from_imu_xyzw: [0.0; 4], ..ImuConfig::default() };
        assert!(Imu::new(config).is_err());
    }
}

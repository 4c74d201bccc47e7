//! The simulator: scene + head motion (standing at a rock, or walking a camera path over a
//! terrain) + depth camera + IMU on one clock, for the node, the recorder and the bench. Frame `i` of the camera is at `i / camera.rate_hz` seconds, IMU sample
//! `j` at `j / imu.rate_hz`; noise seeds derive from the config seed and the sample index.

use nalgebra::Isometry3;
use patchwalk_fusion::camera::DepthImage;

use crate::camera::{mix, DepthCamera, DepthCameraError, RenderCache};
use crate::camera_path::{CameraPath, CameraPathError};
use crate::config::SimConfig;
use crate::imu::{Imu, ImuError, ImuSample};
use crate::motion::{base_from_camera_lookdown, HeadMotion};
use crate::scene::{Scene, SceneError};

#[derive(Debug, thiserror::Error)]
pub enum SimError {
    #[error(transparent)]
    Scene(#[from] SceneError),
    #[error(transparent)]
    Camera(#[from] DepthCameraError),
    #[error(transparent)]
    Imu(#[from] ImuError),
    #[error(transparent)]
    Path(#[from] CameraPathError),
}

/// One rendered depth frame with its ground truth.
#[derive(Debug, Clone)]
pub struct DepthFrame {
    pub timestamp: f64,
    pub depth: DepthImage,
    pub world_from_camera: Isometry3<f64>,
}

/// Everything needed to produce sensor data.
#[derive(Debug, Clone)]
pub struct Simulator {
    pub config: SimConfig,
    pub scene: Scene,
    pub camera: DepthCamera,
    pub imu: Imu,
    pub motion: HeadMotion,
    /// Where the robot stands (`world_from_station`, on the table under `base_link`).
    pub world_from_station: Isometry3<f64>,
    /// Camera mount on the robot (`base_from_camera`, optical).
    pub base_from_camera: Isometry3<f64>,
    /// The camera path, followed instead of the station pose: always in a terrain scene, in the rock
    /// scene when `path.enabled`.
    pub path: Option<CameraPath>,
}

impl Simulator {
    pub fn new(config: SimConfig) -> Result<Self, SimError> {
        let scene = Scene::new(&config.scene, config.seed)?;
        let world_from_station = if scene.rocks.is_empty() { Isometry3::identity() } else { scene.station(config.start_rock)? };
        let path = if scene.terrain.is_some() || config.path.enabled {
            Some(CameraPath::new(&config.path, &scene, config.camera.rate_hz)?)
        } else {
            None
        };
        Ok(Self {
            path,
            camera: DepthCamera::new(config.camera)?,
            imu: Imu::new(config.imu)?,
            motion: HeadMotion::new(config.motion, config.seed),
            base_from_camera: base_from_camera_lookdown(&config.motion),
            world_from_station,
            scene,
            config,
        })
    }

    /// Places the robot in front of rock `index`.
    pub fn place_at_rock(&mut self, index: usize) -> Result<(), SimError> {
        self.world_from_station = self.scene.station(index)?;
        Ok(())
    }

    /// Camera pose at time `t` (s): on the path if there is one, else standing at the station.
    pub fn world_from_camera(&self, t: f64) -> Isometry3<f64> {
        match &self.path {
            Some(path) => path.world_from_walker(&self.scene, t) * self.motion.sway(t) * path.walker_from_camera(),
            None => self.motion.world_from_camera(&self.world_from_station, &self.base_from_camera, t),
        }
    }

    /// Depth frame `index` on the camera clock.
    pub fn depth_frame(&self, index: u64) -> DepthFrame {
        let timestamp = index as f64 / self.config.camera.rate_hz;
        let world_from_camera = self.world_from_camera(timestamp);
        self.render_at(timestamp, &world_from_camera, index)
    }

    /// Renders at an explicit pose (e.g. one following the servos); `index` seeds the noise.
    pub fn render_at(&self, timestamp: f64, world_from_camera: &Isometry3<f64>, index: u64) -> DepthFrame {
        let depth = self.camera.render(&self.scene, world_from_camera, mix(self.config.seed, index));
        DepthFrame { timestamp, depth, world_from_camera: *world_from_camera }
    }

    /// [`render_at`](Self::render_at) reusing the ray casting while the pose stays the same
    /// (see `DepthCamera::render_reusing`).
    pub fn render_at_reusing(
        &self,
        timestamp: f64,
        world_from_camera: &Isometry3<f64>,
        index: u64,
        cache: &mut Option<RenderCache>,
    ) -> DepthFrame {
        let depth = self.camera.render_reusing(&self.scene, world_from_camera, mix(self.config.seed, index), cache);
        DepthFrame { timestamp, depth, world_from_camera: *world_from_camera }
    }

    /// IMU sample `index` on the IMU clock.
    pub fn imu_sample(&self, index: u64) -> ImuSample {
        let timestamp = index as f64 / self.config.imu.rate_hz;
        self.imu.sample(|t| self.world_from_camera(t), timestamp, mix(self.config.seed ^ 0x1a0, index))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn lookdown_view_sees_the_rock_top() {
        let mut sim = Simulator::new(SimConfig::default()).unwrap();
        for index in 0..sim.scene.rocks.len() {
            sim.place_at_rock(index).unwrap();
            let frame = sim.depth_frame(0);
            let foothold = sim.scene.rocks[index].foothold();
            let top_in_camera = frame.world_from_camera.inverse_transform_point(&foothold.top_in_world.into()).coords;
            let (u, v) = sim.camera.intrinsics.pixel_of(&top_in_camera).unwrap();
            // Well inside the image, in its lower half (the lookdown pose looks at the rock).
            assert!((240..440).contains(&v) && (160..480).contains(&u), "rock {index}: top at pixel ({u}, {v})");
            // The measured depth near the top pixel agrees with the true top within noise.
            let window = (0..5).flat_map(|du| (0..5).map(move |dv| (u + du, v + dv)));
            let z = window.filter_map(|(uu, vv)| frame.depth.get(uu.saturating_sub(2), vv.saturating_sub(2))).next().unwrap();
            assert!((f64::from(z) - top_in_camera.z).abs() < 0.01, "rock {index}: {z} vs {}", top_in_camera.z);
            assert!(frame.depth.valid_count() > 280_000, "rock {index}: {}", frame.depth.valid_count());
            // Only table and rocks in view: nothing as far as the floor.
            assert!(frame.depth.depth_m.iter().filter(|z| z.is_finite()).all(|&z| z < 1.3), "rock {index}");
        }
        assert!(sim.place_at_rock(100).is_err());
    }
}

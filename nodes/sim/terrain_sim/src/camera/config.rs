//! Configuration of the virtual depth camera: resolution and pinhole intrinsics of the Carmine 1.09
//! (J 2.1), the stereo baseline, the Murray–Little noise (J eq. 2) and where data go missing.

use patchwalk_fusion::camera::{CameraError, Intrinsics};
use serde::{Deserialize, Serialize};

/// Sensor noise (J 2.1, eq. 2).
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct NoiseConfig {
    pub enabled: bool,
    /// Pointing error σp of the measurement rays (px); J 2.1: 0.35 px (Kinect, from \[62\]).
    pub sigma_pointing_px: f64,
    /// Disparity matching error σm (px); J 2.1: 0.17 px.
    pub sigma_disparity_px: f64,
    /// Disparity quantisation (px); PrimeSense sensors report 1/8-pixel sub-pixel disparity. 0 = off.
    pub disparity_step_px: f64,
    /// Output depth quantisation (m); 16UC1 millimetres. 0 = off.
    pub depth_step_m: f64,
}

impl Default for NoiseConfig {
    fn default() -> Self {
        Self { enabled: true, sigma_pointing_px: 0.35, sigma_disparity_px: 0.17, disparity_step_px: 0.125, depth_step_m: 0.001 }
    }
}

/// Where a structured-light sensor returns no depth.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct MissingDataConfig {
    /// Surfaces seen at more than this angle between ray and normal return nothing (grazing).
    pub max_incidence_deg: f64,
    /// A pixel whose 4-neighbour depth differs by more than this fraction of its depth is dropped
    /// (depth edges).
    pub edge_jump_ratio: f64,
    /// Drop points the projector cannot see (occluded along the baseline).
    pub projector_shadow: bool,
}

impl Default for MissingDataConfig {
    fn default() -> Self {
        Self { max_incidence_deg: 78.0, edge_jump_ratio: 0.03, projector_shadow: true }
    }
}

/// The depth camera: intrinsics, rate, range, baseline, noise and missing data.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct CameraConfig {
    /// J 2.1: 640 × 480 images at 30 Hz.
    pub width: usize,
    pub height: usize,
    /// Carmine 1.09 depth focal length (px); OpenNI reports ≈ 570.3 at VGA.
    pub fx: f64,
    pub fy: f64,
    pub cx: f64,
    pub cy: f64,
    pub rate_hz: f64,
    /// Projector–camera baseline b (m) of J eq. 2; the projector sits at +x of `camera_optical`.
    pub baseline_m: f64,
    /// Range limits (m); Carmine 1.09 is rated 0.35–1.4 m and still returns depth further out.
    pub min_depth_m: f64,
    pub max_depth_m: f64,
    pub noise: NoiseConfig,
    pub missing: MissingDataConfig,
}

impl Default for CameraConfig {
    fn default() -> Self {
        Self {
            width: 640,
            height: 480,
            fx: 570.3,
            fy: 570.3,
            cx: 319.5,
            cy: 239.5,
            rate_hz: 30.0,
            baseline_m: 0.075,
            min_depth_m: 0.35,
            max_depth_m: 3.5,
            noise: NoiseConfig::default(),
            missing: MissingDataConfig::default(),
        }
    }
}

impl CameraConfig {
    pub fn intrinsics(&self) -> Result<Intrinsics, CameraError> {
        Intrinsics::new(self.width, self.height, self.fx, self.fy, self.cx, self.cy)
    }

    /// First-order depth standard deviation of J eq. 2 at depth `z`: σz = z²·σm/(f·b).
    pub fn depth_sigma(&self, z: f64) -> f64 {
        z * z * self.noise.sigma_disparity_px / (self.fx * self.baseline_m)
    }

    /// This sensor's parameters for the mapper's Murray–Little covariance model
    /// (`patchwalk_spl::sensor::murray_little`), so perception can use the simulator's true noise.
    pub fn stereo_error_params(&self) -> patchwalk_spl::sensor::StereoErrorParams {
        patchwalk_spl::sensor::StereoErrorParams {
            sigma_pointing_px: self.noise.sigma_pointing_px,
            sigma_disparity_px: self.noise.sigma_disparity_px,
            baseline_m: self.baseline_m,
            focal_px: self.fx,
        }
    }
}

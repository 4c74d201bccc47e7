//! Camera tracking (J 5.1) and the per-frame moving-volume fusion loop (J 5.2 steps 3–5).
//!
//! ICP is frame-to-model: the new depth frame (a 2×2 pyramid, coarse to fine) is aligned to the
//! model raycast from the previous pose by projective data association and point-to-plane Gauss–Newton
//! steps; the 6×6 normal equations are summed in parallel (f32 over batches of 64 inliers, f64
//! totals), with Huber weights and a distance gate. Loss is declared on few inliers, a large residual, a degenerate system or a pose jump, and
//! the volume is reset (J 5.2: "if camera tracking does fail, then the whole patch map is reset").
//!
//! `Tracker::process` reads as the paper's loop: track → integrate → remap → raycast the model.
//! The ICP itself (pyramid, association, normal equations) is in the `icp` module; trajectory evaluation
//! against ground truth in [`crate::trajectory`].

use std::time::Instant;

use nalgebra::{Isometry3, Translation3, Vector3};

mod icp;

use crate::camera::{DepthImage, Intrinsics};
use crate::fusion::{FusionError, TsdfConfig, TsdfVolume};
use crate::raycast::{raycast_birds_eye, raycast_guided, BirdsEyeConfig, BirdsEyeView, ModelRaycast, RayHint, RaycastConfig};
use crate::volume::{initial_volume_from_camera, map_from_volume_rotation, plan_remap, remap_tsdf, MovingVolumeConfig};
use icp::source_pyramid;
pub use icp::{build_pyramid, downsample, icp, IcpResult, SourceLevel};

/// Errors of the tracking loop (bad input; tracking loss is a status, not an error).
#[derive(Debug, thiserror::Error, PartialEq)]
pub enum TrackingError {
    #[error(transparent)]
    Fusion(#[from] FusionError),
    #[error("depth image is {image_width}x{image_height} but the tracker expects {width}x{height}")]
    SizeMismatch { image_width: usize, image_height: usize, width: usize, height: usize },
    #[error("invalid tracker configuration: {0}")]
    InvalidConfig(String),
}

/// ICP parameters (J 5.1 camera tracking; values follow KinectFusion practice).
#[derive(Debug, Clone, PartialEq, serde::Serialize, serde::Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct IcpConfig {
    /// Gauss–Newton iterations per pyramid level, coarse (1/4 resolution) to fine (full resolution);
    /// [10, 3, 0] gives the same TUM fr1_xyz ATE (3.0 mm) as [8, 6, 3] at a third of the cost.
    pub iterations: [usize; 3],
    /// Correspondence gate per level (m), coarse to fine.
    pub max_correspondence_m: [f64; 3],
    /// Huber threshold on the point-to-plane residual (m).
    pub huber_m: f64,
    /// Stop a level when the update is below this (m and rad). 1e-4 (0.1 mm, 0.006°; far below the
    /// 3 mm TUM fr1_xyz ATE) stops converged levels early: same ATE as 1e-5 with ~30 % less ICP time;
    /// large (jerky) motions still get every iteration.
    pub convergence: f64,
    /// Neighbouring depths farther apart than this are not averaged when downsampling (m).
    pub pyramid_depth_jump_m: f32,
    /// Loss: fewer inliers than this fraction of the source points that met a model surface.
    pub min_inlier_ratio: f64,
    /// Loss: inlier point-to-plane RMS residual above this (m).
    pub max_rms_m: f64,
    /// Loss: frame-to-frame translation above this (m).
    pub max_translation_jump_m: f64,
    /// Loss: frame-to-frame rotation above this (deg).
    pub max_rotation_jump_deg: f64,
    /// Loss: fewer than this many inliers at the last level.
    pub min_inliers: usize,
}

impl Default for IcpConfig {
    fn default() -> Self {
        Self {
            iterations: [10, 3, 0],
            max_correspondence_m: [0.08, 0.04, 0.02],
            huber_m: 0.01,
            convergence: 1e-4,
            pyramid_depth_jump_m: 0.03,
            min_inlier_ratio: 0.3,
            max_rms_m: 0.02,
            max_translation_jump_m: 0.2,
            max_rotation_jump_deg: 25.0,
            min_inliers: 500,
        }
    }
}

/// Configuration of the whole tracking loop.
#[derive(Debug, Clone, PartialEq, serde::Serialize, serde::Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct TrackerConfig {
    pub tsdf: TsdfConfig,
    pub raycast: RaycastConfig,
    pub icp: IcpConfig,
    pub moving_volume: MovingVolumeConfig,
    pub birds_eye: BirdsEyeConfig,
    /// Resolution of the model raycast used for ICP, as a fraction of the input (0.25: 160×120 from
    /// 640×480; same ATE on TUM fr1_xyz as 0.5 at a quarter of the rays).
    pub model_scale: f64,
    /// With an external pose: refine it by ICP (true) or take it as is (false).
    pub refine_external_pose: bool,
}

impl Default for TrackerConfig {
    fn default() -> Self {
        Self {
            tsdf: TsdfConfig::default(),
            raycast: RaycastConfig::default(),
            icp: IcpConfig::default(),
            moving_volume: MovingVolumeConfig::default(),
            birds_eye: BirdsEyeConfig::default(),
            model_scale: 0.25,
            refine_external_pose: true,
        }
    }
}

/// One input frame.
#[derive(Debug, Clone, Copy)]
pub struct Frame<'a> {
    pub depth: &'a DepthImage,
    /// Unit gravity (down) in the camera frame, from the calibrated IMU (J 4.1 step 2).
    pub gravity_in_camera: Option<Vector3<f64>>,
    /// Camera pose from elsewhere (e.g. kinematics), in the `map` frame.
    pub external_map_from_camera: Option<Isometry3<f64>>,
}

/// Why tracking was declared lost.
#[derive(Debug, Clone, PartialEq)]
pub enum LossReason {
    TooFewInliers { inliers: usize, associated: usize },
    LargeResidual { rms_m: f64 },
    PoseJump { translation_m: f64, rotation_deg: f64 },
    Degenerate,
}

/// Outcome of a frame.
#[derive(Debug, Clone, PartialEq)]
pub enum TrackingStatus {
    /// First frame (or first after a reset): the volume was (re)initialised around the camera.
    Initialized,
    /// ICP tracked the frame.
    Tracked,
    /// The external pose was used (without ICP refinement).
    External,
    /// Tracking was lost: the volume was reset and re-initialised at this frame.
    Lost(LossReason),
}

/// ICP diagnostics of the last level.
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub struct IcpSummary {
    pub iterations: usize,
    pub inliers: usize,
    pub valid_source_points: usize,
    /// Source points that projected onto a model surface pixel (the inlier ratio's denominator).
    pub associated: usize,
    pub rms_m: f64,
}

/// Wall time of each stage of one frame (ms).
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub struct StageTimings {
    pub icp_ms: f64,
    pub integrate_ms: f64,
    pub remap_ms: f64,
    pub raycast_ms: f64,
}

/// What happened in one frame.
#[derive(Debug, Clone, PartialEq)]
pub struct FrameReport {
    pub status: TrackingStatus,
    pub map_from_camera: Isometry3<f64>,
    pub volume_from_camera: Isometry3<f64>,
    /// `new_volume_from_old_volume` if the volume was remapped this frame (J 5.2 step 5).
    pub remap: Option<Isometry3<f64>>,
    pub icp: Option<IcpSummary>,
    pub timings: StageTimings,
}

/// The moving-volume KinectFusion loop on CPU.
pub struct Tracker {
    config: TrackerConfig,
    intrinsics: Intrinsics,
    volume: TsdfVolume,
    map_from_volume: Isometry3<f64>,
    volume_from_camera: Isometry3<f64>,
    model: Option<ModelRaycast>,
    frames: usize,
}

impl Tracker {
    pub fn new(config: TrackerConfig, intrinsics: Intrinsics) -> Result<Self, TrackingError> {
        intrinsics.validate().map_err(|e| TrackingError::InvalidConfig(e.to_string()))?;
        if !(config.model_scale > 0.05 && config.model_scale <= 1.0) {
            return Err(TrackingError::InvalidConfig(format!("model_scale {} must be in (0.05, 1]", config.model_scale)));
        }
        let volume = TsdfVolume::new(config.tsdf)?;
        Ok(Self {
            config,
            intrinsics,
            volume,
            map_from_volume: Isometry3::identity(),
            volume_from_camera: Isometry3::identity(),
            model: None,
            frames: 0,
        })
    }

    pub fn config(&self) -> &TrackerConfig {
        &self.config
    }
    pub fn volume(&self) -> &TsdfVolume {
        &self.volume
    }
    pub fn map_from_volume(&self) -> Isometry3<f64> {
        self.map_from_volume
    }
    pub fn volume_from_camera(&self) -> Isometry3<f64> {
        self.volume_from_camera
    }
    pub fn map_from_camera(&self) -> Isometry3<f64> {
        self.map_from_volume * self.volume_from_camera
    }
    /// The model raycast from the current pose (what the next frame is aligned to).
    pub fn model(&self) -> Option<&ModelRaycast> {
        self.model.as_ref()
    }
    /// Frames processed since construction.
    pub fn frames(&self) -> usize {
        self.frames
    }

    /// Forgets the volume; the next frame re-initialises it (J 5.2 reset).
    pub fn reset(&mut self) {
        self.volume.clear();
        self.model = None;
    }

    /// Birds-eye raycast at the current camera pose (J 5.2 step 8).
    pub fn birds_eye(&self) -> BirdsEyeView {
        raycast_birds_eye(&self.volume, &self.config.raycast, &self.config.birds_eye, &self.volume_from_camera)
    }

    /// Birds-eye view pose in the map frame.
    pub fn map_from_birds_eye(&self, view: &BirdsEyeView) -> Isometry3<f64> {
        self.map_from_volume * view.volume_from_birds_eye
    }

    /// One frame of J 5.2 stage II: track (step 3), integrate (step 4), remap (step 5), then raycast
    /// the model for the next frame.
    pub fn process(&mut self, frame: Frame<'_>) -> Result<FrameReport, TrackingError> {
        let depth = frame.depth;
        if depth.width != self.intrinsics.width || depth.height != self.intrinsics.height {
            return Err(TrackingError::SizeMismatch {
                image_width: depth.width,
                image_height: depth.height,
                width: self.intrinsics.width,
                height: self.intrinsics.height,
            });
        }
        let mut timings = StageTimings::default();
        self.frames += 1;
        let started = Instant::now();
        let jump = self.config.icp.pyramid_depth_jump_m;
        let half = downsample(depth, jump);
        let quarter = downsample(&half, jump);
        let images = [&quarter, &half, depth];
        let (status, icp) = match self.model.take() {
            None => {
                self.initialize(&frame);
                (TrackingStatus::Initialized, None)
            }
            Some(model) => self.track(&frame, &images, &model),
        };
        timings.icp_ms = elapsed_ms(started);
        if let TrackingStatus::Lost(_) = status {
            self.volume.clear();
            self.initialize(&frame);
        }

        let started = Instant::now();
        self.volume.integrate(depth, &self.intrinsics, &self.volume_from_camera)?;
        timings.integrate_ms = elapsed_ms(started);

        let started = Instant::now();
        let edge = f64::from(self.volume.edge_m());
        let block = f64::from(self.volume.block_size());
        let remap = plan_remap(&self.config.moving_volume, &self.volume_from_camera, edge, block);
        if let Some(new_from_old) = remap {
            remap_tsdf(&mut self.volume, &new_from_old);
            self.volume_from_camera = new_from_old * self.volume_from_camera;
            self.map_from_volume *= new_from_old.inverse();
        }
        timings.remap_ms = elapsed_ms(started);

        let started = Instant::now();
        let model_intrinsics = self.intrinsics.scaled(self.config.model_scale);
        // The frame just integrated at this pose tells where each model ray meets the surface; the
        // full-resolution frame fills the holes (depth edges) of the downsampled one.
        let hint = images
            .into_iter()
            .find(|image| image.width == model_intrinsics.width && image.height == model_intrinsics.height)
            .map(|image| RayHint { depth: image, fine: Some(depth) });
        self.model = Some(raycast_guided(&self.volume, &self.config.raycast, &model_intrinsics, &self.volume_from_camera, hint));
        timings.raycast_ms = elapsed_ms(started);

        Ok(FrameReport {
            status,
            map_from_camera: self.map_from_camera(),
            volume_from_camera: self.volume_from_camera,
            remap,
            icp,
            timings,
        })
    }

    /// (Re)initialises the volume around the camera (J 5.2): y along gravity, z forward, camera at
    /// the nominal position; the map frame keeps the external pose if one is given.
    fn initialize(&mut self, frame: &Frame<'_>) {
        let edge = f64::from(self.volume.edge_m());
        self.volume_from_camera = initial_volume_from_camera(frame.gravity_in_camera, edge, &self.config.moving_volume);
        self.map_from_volume = match frame.external_map_from_camera {
            Some(map_from_camera) => map_from_camera * self.volume_from_camera.inverse(),
            None if self.frames <= 1 => Isometry3::from_parts(Translation3::identity(), map_from_volume_rotation()),
            // After a loss, keep the map continuous at the last known camera pose.
            None => self.map_from_camera() * self.volume_from_camera.inverse(),
        };
    }

    fn track(&mut self, frame: &Frame<'_>, images: &[&DepthImage; 3], model: &ModelRaycast) -> (TrackingStatus, Option<IcpSummary>) {
        let previous = self.volume_from_camera;
        let prior = frame.external_map_from_camera.map(|m| self.map_from_volume.inverse() * m);
        if let (Some(pose), false) = (prior, self.config.refine_external_pose) {
            self.volume_from_camera = pose;
            return (TrackingStatus::External, None);
        }
        let initial = prior.unwrap_or(previous);
        let pyramid = source_pyramid(images, &self.intrinsics, &self.config.icp.iterations);
        let result = icp(&self.config.icp, &pyramid, model, &initial);
        match check_loss(&self.config.icp, &result, &previous) {
            Some(reason) => (TrackingStatus::Lost(reason), Some(result.summary)),
            None => {
                self.volume_from_camera = result.volume_from_camera;
                (TrackingStatus::Tracked, Some(result.summary))
            }
        }
    }
}

fn elapsed_ms(started: Instant) -> f64 {
    started.elapsed().as_secs_f64() * 1e3
}

/// Tracking-loss checks (J 5.2: loss → reset): inlier ratio, residual, degeneracy, pose jump.
fn check_loss(config: &IcpConfig, result: &IcpResult, previous: &Isometry3<f64>) -> Option<LossReason> {
    let s = result.summary;
    if s.inliers < config.min_inliers || (s.inliers as f64) < config.min_inlier_ratio * s.associated as f64 {
        return Some(LossReason::TooFewInliers { inliers: s.inliers, associated: s.associated });
    }
    if s.rms_m > config.max_rms_m {
        return Some(LossReason::LargeResidual { rms_m: s.rms_m });
    }
    // A NaN eigenvalue is degenerate too.
    if result.min_eigenvalue.is_nan() || result.min_eigenvalue <= 1e-9 {
        return Some(LossReason::Degenerate);
    }
    let jump = previous.inverse() * result.volume_from_camera;
    let translation_m = jump.translation.vector.norm();
    let rotation_deg = jump.rotation.angle().to_degrees();
    if translation_m > config.max_translation_jump_m || rotation_deg > config.max_rotation_jump_deg {
        return Some(LossReason::PoseJump { translation_m, rotation_deg });
    }
    None
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::dataset::{test_data_dir, Dataset};
    use crate::trajectory::{absolute_trajectory_rmse, relative_pose_errors};

    fn tum_config() -> TrackerConfig {
        TrackerConfig {
            tsdf: TsdfConfig { voxel_size_m: 0.005, size_m: 4.0, ..TsdfConfig::default() },
            moving_volume: MovingVolumeConfig { enabled: false, ..MovingVolumeConfig::default() },
            ..TrackerConfig::default()
        }
    }

    /// Tracks a dataset and returns matched (estimate, ground truth) poses.
    fn track_dataset(dataset: &Dataset, config: TrackerConfig, max_gap: f64) -> (Vec<Isometry3<f64>>, Vec<Isometry3<f64>>) {
        let mut tracker = Tracker::new(config, dataset.intrinsics).unwrap();
        let (mut estimate, mut reference) = (Vec::new(), Vec::new());
        for (index, frame) in dataset.frames.iter().enumerate() {
            let depth = dataset.load_depth(index).unwrap();
            let report = tracker.process(Frame { depth: &depth, gravity_in_camera: None, external_map_from_camera: None }).unwrap();
            assert!(!matches!(report.status, TrackingStatus::Lost(_)), "frame {index}: {:?}", report.status);
            if let Some(gt) = dataset.groundtruth_near(frame.timestamp, max_gap) {
                estimate.push(report.map_from_camera);
                reference.push(gt.world_from_camera);
            }
        }
        (estimate, reference)
    }

    #[test]
    fn tum_fr1_xyz_ate_is_within_4_mm() {
        let dataset = Dataset::open(&test_data_dir().join("tum_fr1_xyz")).unwrap();
        let (estimate, reference) = track_dataset(&dataset, tum_config(), 0.02);
        assert!(estimate.len() >= 30);
        let ate = absolute_trajectory_rmse(&estimate, &reference).unwrap();
        // Travelled path length, to make sure the camera actually moved.
        let path: f64 = reference.windows(2).map(|w| (w[1].translation.vector - w[0].translation.vector).norm()).sum();
        eprintln!("ATE {:.2} mm over {} frames, path {:.3} m", ate * 1e3, estimate.len(), path);
        assert!(path > 0.1);
        assert!(ate < 0.004, "ATE {ate}");
    }

    #[test]
    fn open3d_frames_relative_pose_errors_are_small() {
        let dataset = Dataset::open(&test_data_dir().join("open3d_rgbd")).unwrap();
        let (estimate, reference) = track_dataset(&dataset, tum_config(), 0.5);
        assert_eq!(estimate.len(), 5);
        let errors = relative_pose_errors(&estimate, &reference);
        for (i, (t, r)) in errors.iter().enumerate() {
            eprintln!("pair {i}: {:.2} mm, {:.3} deg", t * 1e3, r);
            assert!(*t < 0.02 && *r < 1.0, "pair {i}: {t} m, {r} deg");
        }
    }

    #[test]
    fn wrong_image_size_is_an_error_and_empty_frames_lose_tracking() {
        let intrinsics = Intrinsics::primesense_default().scaled(0.25);
        let mut tracker = Tracker::new(TrackerConfig::default(), intrinsics).unwrap();
        let bad = DepthImage::new(3, 3, vec![1.0; 9]).unwrap();
        let frame = Frame { depth: &bad, gravity_in_camera: None, external_map_from_camera: None };
        assert!(matches!(tracker.process(frame), Err(TrackingError::SizeMismatch { .. })));
        let empty = DepthImage::new(intrinsics.width, intrinsics.height, vec![f32::NAN; intrinsics.width * intrinsics.height]).unwrap();
        let frame = Frame { depth: &empty, gravity_in_camera: None, external_map_from_camera: None };
        assert_eq!(tracker.process(frame).unwrap().status, TrackingStatus::Initialized);
        let report = tracker.process(frame).unwrap();
        assert!(matches!(report.status, TrackingStatus::Lost(LossReason::TooFewInliers { .. })), "{:?}", report.status);
        assert!(Tracker::new(TrackerConfig { model_scale: 0.0, ..TrackerConfig::default() }, intrinsics).is_err());
    }
}

//! Camera tracking (J 5.1) and the per-frame moving-volume fusion loop (J 5.2 steps 3–5).
//!
//! ICP is frame-to-model: the new depth frame (a 2×2 pyramid, coarse to fine) is aligned to the
//! model raycast from the previous pose by projective data association and point-to-plane Gauss–Newton
//! steps; the 6×6 normal equations are summed in parallel (f32 over batches of 64 inliers, f64
//! totals), with Huber weights and a distance gate.
//!
//! For a walking robot (10 cm and 10° between frames at a step) three things come before and after it:
//!
//! - **the initial pose** is the constant-velocity prediction of the camera ([`prior`]), with its tilt
//!   from the IMU's gravity on the wide attempts;
//! - **a wide first level** ([`level_plan`]: the 1/4 image subsampled, 0.3 m and 40° gates) runs when
//!   the predicted motion is large, and on every retry;
//! - **a failed frame is a short loss, not a reset** ([`relocalise`]): the frame is retried within the
//!   frame (wide level, from the prediction and from the last good pose); if that fails too, the map
//!   and the last good pose are kept, the frame is not fused (`Relocalising`), and the next frames are
//!   aligned against the kept model the same way. The first frame that passes the loss checks is
//!   `Relocalised`; only `relocalisation.max_lost_frames` failed frames in a row are a real loss
//!   (`Lost`), which resets the volume (J 5.2: "if camera tracking does fail, then the whole patch
//!   map is reset").
//!
//! A frame fails on few inliers, a large residual, a degenerate system, a pose that moved farther
//! from its initial guess than `max_translation_jump_m` / `max_rotation_jump_deg`, or a tilt that
//! contradicts the IMU by more than `motion_prior.max_tilt_error_deg`.
//!
//! `Tracker::process` reads as the paper's loop: track → integrate → remap → raycast the model.
//! The ICP itself (pyramid, association, normal equations) is in the `icp` module; trajectory evaluation
//! against ground truth in [`crate::trajectory`].

use std::time::Instant;

use nalgebra::{Isometry3, Translation3, Vector3};

mod icp;
pub mod prior;
pub mod relocalise;

use crate::camera::{DepthImage, Intrinsics};
use crate::fusion::{FusionError, TsdfConfig, TsdfVolume};
use crate::raycast::{
    birds_eye_camera, raycast_birds_eye, raycast_birds_eye_within, raycast_guided, BirdsEyeConfig, BirdsEyeView, ModelRaycast, RayHint,
    RaycastConfig,
};
use crate::volume::{initial_volume_from_camera, map_from_volume_rotation, plan_remap, remap_tsdf, MovingVolumeConfig};
use icp::plan_source;
pub use icp::{build_pyramid, downsample, icp, level_plan, IcpResult, LevelPlan, SourceLevel, PYRAMID_SCALES};
use prior::{tilt_corrected, tilt_error_deg, MotionModel};
use relocalise::{Recovery, Transition};

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
    /// [10, 3, 0] gives the same TUM fr1_xyz ATE as [8, 6, 3] at a third of the cost.
    pub iterations: [usize; 3],
    /// Correspondence gate per level (m), coarse to fine.
    pub max_correspondence_m: [f64; 3],
    /// Huber threshold on the point-to-plane residual (m) of a point 1 m away (scaled with the
    /// point's depth noise, `depth_noise_power`).
    pub huber_m: f64,
    /// Each pair's residual is weighted by the inverse variance of its depth, σ ∝ z^power with z the
    /// frame point's depth in metres: 2 for stereo and structured-light cameras (J eq 2: σ_z =
    /// z² σ_d / (f b)), 1 roughly for time of flight, 0 for KinectFusion's equal weights. Far points
    /// of a room-scale view carry a fraction of a near point's information; unweighted they pull the
    /// pose as much.
    pub depth_noise_power: u32,
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
    /// Loss: ICP moved the pose farther than this from its initial guess (the prediction) (m).
    pub max_translation_jump_m: f64,
    /// Loss: ICP turned the pose farther than this from its initial guess (deg).
    pub max_rotation_jump_deg: f64,
    /// Loss: fewer than this many inliers at the last level.
    pub min_inliers: usize,
    /// The wide first level for large motions and retries.
    pub wide: WideLevelConfig,
}

/// The wide first level of the coarse-to-fine search: the 1/4 image, every `stride`-th pixel, with
/// distance and normal-angle gates wide enough for a pose 10–30 cm or 10–20° off.
#[derive(Debug, Clone, PartialEq, serde::Serialize, serde::Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct WideLevelConfig {
    /// Gauss–Newton iterations (0: no wide level).
    pub iterations: usize,
    /// Every `stride`-th pixel of the 1/4 image in both directions (2: 80×60 from 640×480).
    pub stride: usize,
    /// Correspondence gate (m).
    pub max_correspondence_m: f64,
    /// Largest angle between the frame's and the model's normals of a pair (deg).
    pub max_normal_angle_deg: f64,
    /// Run it first when the predicted motion since the last tracked frame is above this (m) ...
    pub when_translation_m: f64,
    /// ... or above this (deg); retries and relocalisation always run it.
    pub when_rotation_deg: f64,
    /// Levenberg damping d of its steps (H + d·tr(H)/6·I).
    pub damping: f64,
    /// Largest step per iteration (m, deg).
    pub max_step_m: f64,
    pub max_step_deg: f64,
    /// Coarse search before it: the wide level also starts from the initial pose moved ± this much
    /// horizontally (along the volume's x and z) and turned ± `search_deg` about gravity; the start
    /// with the most inliers goes on to the finer levels (0 and 0: no search).
    pub search_m: f64,
    pub search_deg: f64,
}

impl Default for WideLevelConfig {
    fn default() -> Self {
        Self {
            iterations: 12,
            stride: 2,
            max_correspondence_m: 0.3,
            max_normal_angle_deg: 40.0,
            when_translation_m: 0.04,
            when_rotation_deg: 4.0,
            damping: 0.01,
            max_step_m: 0.05,
            max_step_deg: 5.0,
            search_m: 0.08,
            search_deg: 8.0,
        }
    }
}

/// The initial pose of ICP ([`prior`]).
#[derive(Debug, Clone, PartialEq, serde::Serialize, serde::Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct MotionPriorConfig {
    /// Start ICP from the constant-velocity prediction (false: from the last pose).
    pub constant_velocity: bool,
    /// The prediction extrapolates at most this many of the last frame steps (a gap of skipped
    /// frames, a relocalisation after a few lost ones).
    pub max_extrapolation: f64,
    /// On the wide attempts, take roll and pitch of the initial pose from the IMU's gravity.
    pub gravity_tilt: bool,
    /// Loss: the tracked pose's gravity differs from the IMU's by more than this (deg). The
    /// accelerometer of a walking robot also measures its accelerations (1 m/s² tilts it by 6°, the
    /// 3 m/s² of a brisk step by 17°).
    pub max_tilt_error_deg: f64,
}

impl Default for MotionPriorConfig {
    fn default() -> Self {
        Self { constant_velocity: true, max_extrapolation: 4.0, gravity_tilt: true, max_tilt_error_deg: 30.0 }
    }
}

/// Short losses ([`relocalise`]).
#[derive(Debug, Clone, PartialEq, serde::Serialize, serde::Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct RelocalisationConfig {
    /// Failed frames in a row kept as a short loss (map and last good pose kept, relocalisation tried
    /// on each new frame) before the loss is real and the volume is reset; 0: every failure resets
    /// (J 5.2 as written). 10 frames are a third of a second at 30 Hz.
    pub max_lost_frames: usize,
    /// Retry a failed frame at once with the wide level (from the prediction and the last good pose)
    /// before calling it lost.
    pub retry_within_frame: bool,
}

impl Default for RelocalisationConfig {
    fn default() -> Self {
        Self { max_lost_frames: 10, retry_within_frame: true }
    }
}

impl Default for IcpConfig {
    fn default() -> Self {
        Self {
            iterations: [10, 3, 0],
            max_correspondence_m: [0.08, 0.04, 0.02],
            huber_m: 0.01,
            depth_noise_power: 2,
            convergence: 1e-4,
            pyramid_depth_jump_m: 0.03,
            min_inlier_ratio: 0.3,
            max_rms_m: 0.02,
            max_translation_jump_m: 0.2,
            max_rotation_jump_deg: 25.0,
            min_inliers: 500,
            wide: WideLevelConfig::default(),
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
    pub motion_prior: MotionPriorConfig,
    pub relocalisation: RelocalisationConfig,
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
            motion_prior: MotionPriorConfig::default(),
            relocalisation: RelocalisationConfig::default(),
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
    /// Capture time (s), for the constant-velocity prediction across skipped frames; without it every
    /// frame counts as one time step.
    pub timestamp: Option<f64>,
}

/// Why tracking was declared lost.
#[derive(Debug, Clone, PartialEq)]
pub enum LossReason {
    TooFewInliers {
        inliers: usize,
        associated: usize,
    },
    LargeResidual {
        rms_m: f64,
    },
    PoseJump {
        translation_m: f64,
        rotation_deg: f64,
    },
    Degenerate,
    /// The pose's gravity and the IMU's disagree.
    TiltMismatch {
        tilt_error_deg: f64,
    },
}

impl std::fmt::Display for LossReason {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            Self::TooFewInliers { inliers, associated } => write!(f, "too few ICP inliers ({inliers} of {associated} associated)"),
            Self::LargeResidual { rms_m } => write!(f, "ICP residual {:.1} mm RMS", rms_m * 1e3),
            Self::PoseJump { translation_m, rotation_deg } => {
                write!(f, "ICP moved {:.0} mm / {rotation_deg:.1}° from its initial guess", translation_m * 1e3)
            }
            Self::Degenerate => write!(f, "degenerate ICP system (no geometry to align)"),
            Self::TiltMismatch { tilt_error_deg } => write!(f, "pose tilt {tilt_error_deg:.1}° off the IMU's gravity"),
        }
    }
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
    /// ICP failed on this frame, `frames_lost` in a row: a short loss. The volume, the model and the
    /// last good pose (the reported one) are kept, the frame is not fused; the next frames try to
    /// relocalise against the model.
    Relocalising { frames_lost: usize, reason: LossReason },
    /// Tracked again against the kept model after `frames_lost` failed frames; fused as usual.
    Relocalised { frames_lost: usize },
    /// Tracking was lost for good (more than `relocalisation.max_lost_frames` failed frames in a
    /// row): the volume was reset and re-initialised at this frame.
    Lost(LossReason),
}

impl TrackingStatus {
    /// Whether the frame's pose was found (and the frame fused).
    pub fn has_pose(&self) -> bool {
        !matches!(self, Self::Relocalising { .. } | Self::Lost(_))
    }
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
    /// ICP runs this frame (a first attempt, retries, relocalisation hypotheses).
    pub attempts: usize,
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
    /// The last integrated frame (its model-resolution image, if the pyramid has one, and the full
    /// one) while the model for the next frame is not raycast yet (see [`Tracker::prepare_model`]).
    pending_model: Option<(Option<DepthImage>, DepthImage)>,
    /// Time of the last model raycast (ms), reported with the frame aligned to that model.
    model_raycast_ms: f64,
    frames: usize,
    /// Tracked poses for the constant-velocity prediction.
    motion: MotionModel,
    /// Short losses.
    recovery: Recovery,
    /// The volume's y axis is gravity (the volume was initialised with the IMU's gravity).
    gravity_aligned: bool,
}

impl Tracker {
    pub fn new(config: TrackerConfig, intrinsics: Intrinsics) -> Result<Self, TrackingError> {
        intrinsics.validate().map_err(|e| TrackingError::InvalidConfig(e.to_string()))?;
        if !(config.model_scale > 0.05 && config.model_scale <= 1.0) {
            return Err(TrackingError::InvalidConfig(format!("model_scale {} must be in (0.05, 1]", config.model_scale)));
        }
        let wide = &config.icp.wide;
        if !(wide.max_correspondence_m > 0.0 && wide.max_normal_angle_deg > 0.0 && wide.stride >= 1) {
            return Err(TrackingError::InvalidConfig(format!(
                "icp.wide: max_correspondence_m ({}) and max_normal_angle_deg ({}) must be positive and stride ({}) at least 1",
                wide.max_correspondence_m, wide.max_normal_angle_deg, wide.stride
            )));
        }
        let prior = &config.motion_prior;
        if !(prior.max_extrapolation >= 0.0 && prior.max_extrapolation.is_finite() && prior.max_tilt_error_deg > 0.0) {
            return Err(TrackingError::InvalidConfig(format!(
                "motion_prior: max_extrapolation ({}) must be finite and >= 0, max_tilt_error_deg ({}) positive",
                prior.max_extrapolation, prior.max_tilt_error_deg
            )));
        }
        let volume = TsdfVolume::new(config.tsdf)?;
        let recovery = Recovery::new(config.relocalisation.max_lost_frames);
        Ok(Self {
            config,
            intrinsics,
            volume,
            map_from_volume: Isometry3::identity(),
            volume_from_camera: Isometry3::identity(),
            model: None,
            pending_model: None,
            model_raycast_ms: 0.0,
            frames: 0,
            motion: MotionModel::default(),
            recovery,
            gravity_aligned: false,
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
    /// The model raycast from the current pose (what the next frame is aligned to), raycast now if
    /// it was still to do.
    pub fn model(&mut self) -> Option<&ModelRaycast> {
        self.prepare_model();
        self.model.as_ref()
    }
    /// Frames processed since construction.
    pub fn frames(&self) -> usize {
        self.frames
    }
    /// Failed frames in a row of the current short loss (0 while tracking).
    pub fn frames_lost(&self) -> usize {
        self.recovery.frames_lost()
    }

    /// Forgets the volume; the next frame re-initialises it (J 5.2 reset).
    pub fn reset(&mut self) {
        self.volume.clear();
        self.model = None;
        self.pending_model = None;
        self.motion.clear();
        self.recovery.reset();
    }

    /// Raycasts the model the next frame is aligned to (J 5.2 step 7) from the frame last
    /// integrated, if that is still to do. `process` leaves it for later so that a caller who needs
    /// the frame's outputs first (the ROS node publishes its patches) can call this once they are
    /// out; otherwise the next `process` does it first. Either way the model is the same.
    pub fn prepare_model(&mut self) {
        let Some((hint_image, full)) = self.pending_model.take() else { return };
        let started = Instant::now();
        let model_intrinsics = self.intrinsics.scaled(self.config.model_scale);
        // The frame just integrated at this pose tells where each model ray meets the surface; the
        // full-resolution frame fills the holes (depth edges) of the downsampled one.
        let hint = hint_image.as_ref().map(|depth| RayHint { depth, fine: Some(&full) });
        self.model = Some(raycast_guided(&self.volume, &self.config.raycast, &model_intrinsics, &self.volume_from_camera, hint));
        self.model_raycast_ms = elapsed_ms(started);
    }

    /// Birds-eye raycast at the current camera pose (J 5.2 step 8).
    pub fn birds_eye(&self) -> BirdsEyeView {
        raycast_birds_eye(&self.volume, &self.config.raycast, &self.config.birds_eye, &self.volume_from_camera)
    }

    /// [`Tracker::birds_eye`] of only the pixels `within` marks ([`raycast_birds_eye_within`]).
    pub fn birds_eye_within(&self, within: &[bool]) -> BirdsEyeView {
        raycast_birds_eye_within(&self.volume, &self.config.raycast, &self.config.birds_eye, &self.volume_from_camera, Some(within))
    }

    /// The birds-eye camera's intrinsics and pose in the volume at the current camera pose.
    pub fn birds_eye_camera(&self) -> (Intrinsics, Isometry3<f64>) {
        birds_eye_camera(&self.config.birds_eye, &self.volume_from_camera)
    }

    /// Birds-eye view pose in the map frame.
    pub fn map_from_birds_eye(&self, view: &BirdsEyeView) -> Isometry3<f64> {
        self.map_from_volume * view.volume_from_birds_eye
    }

    /// One frame of J 5.2 stage II: track (step 3), integrate (step 4), remap (step 5); the model for
    /// the next frame is raycast by [`Tracker::prepare_model`] (by the caller, or first thing in the
    /// next call). A frame of a short loss (`Relocalising`) is only tracked.
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
        if self.awaits_gravity(&frame) {
            // The volume and the map frame were set up before the IMU's gravity was known (camera y
            // taken as down): the first frame with gravity starts both again, gravity-aligned (J 5.2).
            self.reset();
            self.frames = 0;
        }
        // The model this frame is aligned to, unless the caller raycast it after the last frame.
        self.prepare_model();
        timings.raycast_ms = std::mem::take(&mut self.model_raycast_ms);
        self.frames += 1;
        let time = frame.timestamp.unwrap_or(self.frames as f64);
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
            Some(model) => {
                let (status, icp) = self.track(&frame, &images, &model, time);
                if let TrackingStatus::Relocalising { .. } = status {
                    // The kept model is what the next frames relocalise against.
                    self.model = Some(model);
                }
                (status, icp)
            }
        };
        timings.icp_ms = elapsed_ms(started);
        if let TrackingStatus::Relocalising { .. } = status {
            return Ok(FrameReport {
                status,
                map_from_camera: self.map_from_camera(),
                volume_from_camera: self.volume_from_camera,
                remap: None,
                icp,
                timings,
            });
        }
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
        // The map frame does not move with remaps: the motion model keeps map poses.
        self.motion.push(time, self.map_from_camera());

        // The model for the next frame is raycast by `prepare_model`: by the caller once it has
        // used this frame's outputs, else at the start of the next frame.
        let model_intrinsics = self.intrinsics.scaled(self.config.model_scale);
        let hint = images.into_iter().find(|image| image.width == model_intrinsics.width && image.height == model_intrinsics.height);
        self.pending_model = Some((hint.cloned(), depth.clone()));

        Ok(FrameReport {
            status,
            map_from_camera: self.map_from_camera(),
            volume_from_camera: self.volume_from_camera,
            remap,
            icp,
            timings,
        })
    }

    /// Whether the volume was initialised without gravity and this frame brings it.
    fn awaits_gravity(&self, frame: &Frame<'_>) -> bool {
        let volume_exists = self.model.is_some() || self.pending_model.is_some();
        volume_exists && !self.gravity_aligned && usable_gravity(frame).is_some()
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
        self.gravity_aligned = usable_gravity(frame).is_some();
        self.motion.clear();
        self.recovery.reset();
    }

    /// ICP against the model from the hypotheses of this frame (see the module doc), and what the
    /// outcome means for the short-loss state machine.
    fn track(
        &mut self,
        frame: &Frame<'_>,
        images: &[&DepthImage; 3],
        model: &ModelRaycast,
        time: f64,
    ) -> (TrackingStatus, Option<IcpSummary>) {
        let last_good = self.volume_from_camera;
        let prior = frame.external_map_from_camera.map(|m| self.map_from_volume.inverse() * m);
        if let (Some(pose), false) = (prior, self.config.refine_external_pose) {
            self.volume_from_camera = pose;
            self.recovery.on_tracked();
            return (TrackingStatus::External, None);
        }
        let config = &self.config;
        let predicted = prior.unwrap_or_else(|| {
            let prediction =
                config.motion_prior.constant_velocity.then(|| self.motion.predict(time, config.motion_prior.max_extrapolation));
            prediction.flatten().map_or(last_good, |map_from_camera| self.map_from_volume.inverse() * map_from_camera)
        });
        // Gravity in the volume frame is its y axis (J 5.2), when the volume was set up with the IMU.
        let gravity = usable_gravity(frame).filter(|_| self.gravity_aligned);
        let tilt = |pose: Isometry3<f64>| match gravity.filter(|_| config.motion_prior.gravity_tilt) {
            Some(g) => tilt_corrected(&pose, &g, &Vector3::y()),
            None => pose,
        };
        let hypotheses = hypotheses(config, self.recovery.frames_lost() > 0, &last_good, &predicted);
        let mut sources = Sources::new(images, &self.intrinsics);
        let mut summary = None;
        let mut failure = LossReason::Degenerate;
        let mut accepted = None;
        for (attempt, (start, wide)) in hypotheses.into_iter().enumerate() {
            let start = if wide { tilt(start) } else { start };
            let plan = level_plan(&config.icp, wide);
            let levels = sources.levels(&plan);
            let result = match levels.split_first() {
                Some((first, finer)) if wide && plan.first().is_some_and(|p| p.max_normal_angle_deg < 180.0) => {
                    // The coarse search: the wide level from each start, the best on to the finer levels.
                    let best = search_starts(&config.icp.wide, &start)
                        .iter()
                        .map(|candidate| icp(&config.icp, std::slice::from_ref(first), model, candidate))
                        .max_by(|a, b| search_score(&config.icp, a).total_cmp(&search_score(&config.icp, b)));
                    match best {
                        Some(best) if !finer.is_empty() => icp(&config.icp, finer, model, &best.volume_from_camera),
                        Some(best) => best,
                        None => icp(&config.icp, &levels, model, &start),
                    }
                }
                _ => icp(&config.icp, &levels, model, &start),
            };
            summary = Some(IcpSummary { attempts: attempt + 1, ..result.summary });
            match check_loss(config, &result, &start, gravity.as_ref()) {
                Some(reason) => failure = reason,
                None => {
                    accepted = Some(result.volume_from_camera);
                    break;
                }
            }
        }
        if let Some(pose) = accepted {
            self.volume_from_camera = pose;
            return match self.recovery.on_tracked() {
                Transition::Relocalised { frames_lost } => (TrackingStatus::Relocalised { frames_lost }, summary),
                _ => (TrackingStatus::Tracked, summary),
            };
        }
        match self.recovery.on_failed() {
            Transition::Coasting { frames_lost } => (TrackingStatus::Relocalising { frames_lost, reason: failure }, summary),
            _ => (TrackingStatus::Lost(failure), summary),
        }
    }
}

/// Whether the first attempt runs the wide level: the predicted motion since the last tracked pose
/// is above `icp.wide.when_translation_m` or `when_rotation_deg`.
pub fn wide_first(config: &IcpConfig, last_good: &Isometry3<f64>, predicted: &Isometry3<f64>) -> bool {
    let (translation_m, rotation_deg) = motion_between(last_good, predicted);
    translation_m > config.wide.when_translation_m || rotation_deg > config.wide.when_rotation_deg
}

/// Translation (m) and rotation (deg) from `a` to `b`.
fn motion_between(a: &Isometry3<f64>, b: &Isometry3<f64>) -> (f64, f64) {
    let motion = a.inverse() * b;
    (motion.translation.vector.norm(), motion.rotation.angle().to_degrees())
}

/// The ICP attempts of a frame, in order, as (initial pose, wide level first): while tracking, the
/// prediction (wide if [`wide_first`]), then with `retry_within_frame` the prediction with the wide
/// level (if the first was narrow) and the last good pose with it (if it differs from the prediction);
/// during a short loss, the prediction and the last good pose, both wide.
pub fn hypotheses(
    config: &TrackerConfig,
    lost: bool,
    last_good: &Isometry3<f64>,
    predicted: &Isometry3<f64>,
) -> Vec<(Isometry3<f64>, bool)> {
    let (translation_m, rotation_deg) = motion_between(last_good, predicted);
    // A prediction within 0.1 mm and 0.01° of the last pose is the same start.
    let distinct = translation_m > 1e-4 || rotation_deg > 0.01;
    let has_wide = config.icp.wide.iterations > 0;
    let mut attempts = Vec::with_capacity(3);
    if lost {
        attempts.push((*predicted, has_wide));
        if distinct {
            attempts.push((*last_good, has_wide));
        }
        return attempts;
    }
    let first_wide = has_wide && wide_first(&config.icp, last_good, predicted);
    attempts.push((*predicted, first_wide));
    if config.relocalisation.retry_within_frame && has_wide {
        if !first_wide {
            attempts.push((*predicted, true));
        }
        if distinct {
            attempts.push((*last_good, true));
        }
    }
    attempts
}

/// The frame's unit gravity (camera frame), if it has a finite, non-zero one.
fn usable_gravity(frame: &Frame<'_>) -> Option<Vector3<f64>> {
    frame.gravity_in_camera.and_then(|g| g.try_normalize(1e-9)).filter(|g| g.iter().all(|v| v.is_finite()))
}

/// The starts of the coarse search around `start` (`volume_from_camera`): itself, moved ±`search_m`
/// along the volume's horizontal axes (x, z), and turned ±`search_deg` about the vertical (volume y,
/// gravity) through the camera centre.
pub fn search_starts(wide: &WideLevelConfig, start: &Isometry3<f64>) -> Vec<Isometry3<f64>> {
    let mut starts = vec![*start];
    if wide.search_m > 0.0 {
        for offset in [Vector3::x(), -Vector3::x(), Vector3::z(), -Vector3::z()] {
            starts.push(Isometry3::from_parts(Translation3::from(start.translation.vector + offset * wide.search_m), start.rotation));
        }
    }
    if wide.search_deg > 0.0 {
        for angle in [wide.search_deg, -wide.search_deg] {
            let turn = nalgebra::UnitQuaternion::from_axis_angle(&Vector3::y_axis(), angle.to_radians());
            starts.push(Isometry3::from_parts(start.translation, turn * start.rotation));
        }
    }
    starts
}

/// How well a wide-level result fits: its inliers weighted by h² / (rms² + h²) (h: the Huber
/// threshold), a soft count of the points that lie on the model.
fn search_score(config: &IcpConfig, result: &IcpResult) -> f64 {
    let h2 = config.huber_m * config.huber_m;
    let s = result.summary;
    s.inliers as f64 * h2 / (s.rms_m * s.rms_m + h2)
}

/// The source levels of one frame, each built once for all the attempts that use it.
struct Sources<'a> {
    images: &'a [&'a DepthImage; 3],
    intrinsics: &'a Intrinsics,
    built: Vec<(LevelPlan, SourceLevel)>,
}

impl<'a> Sources<'a> {
    fn new(images: &'a [&'a DepthImage; 3], intrinsics: &'a Intrinsics) -> Self {
        Self { images, intrinsics, built: Vec::new() }
    }

    /// Same source points: same image, stride and whether normals are needed.
    fn same_source(a: &LevelPlan, b: &LevelPlan) -> bool {
        a.image == b.image && a.stride == b.stride && (a.max_normal_angle_deg < 180.0) == (b.max_normal_angle_deg < 180.0)
    }

    fn levels(&mut self, plan: &[LevelPlan]) -> Vec<(LevelPlan, &SourceLevel)> {
        for level in plan {
            if !self.built.iter().any(|(built, _)| Self::same_source(built, level)) {
                self.built.push((*level, plan_source(self.images, self.intrinsics, level)));
            }
        }
        plan.iter()
            .filter_map(|level| self.built.iter().find(|(built, _)| Self::same_source(built, level)).map(|(_, source)| (*level, source)))
            .collect()
    }
}

fn elapsed_ms(started: Instant) -> f64 {
    started.elapsed().as_secs_f64() * 1e3
}

/// Tracking-loss checks (J 5.2: loss → reset): inlier ratio, residual, degeneracy, the pose's move from
/// its initial guess, and its tilt against the IMU's gravity (`gravity_in_volume`'s frame: volume y).
fn check_loss(
    config: &TrackerConfig,
    result: &IcpResult,
    start: &Isometry3<f64>,
    gravity_in_camera: Option<&Vector3<f64>>,
) -> Option<LossReason> {
    let icp = &config.icp;
    let s = result.summary;
    if s.inliers < icp.min_inliers || (s.inliers as f64) < icp.min_inlier_ratio * s.associated as f64 {
        return Some(LossReason::TooFewInliers { inliers: s.inliers, associated: s.associated });
    }
    if s.rms_m > icp.max_rms_m {
        return Some(LossReason::LargeResidual { rms_m: s.rms_m });
    }
    // A NaN eigenvalue is degenerate too.
    if result.min_eigenvalue.is_nan() || result.min_eigenvalue <= 1e-9 {
        return Some(LossReason::Degenerate);
    }
    let jump = start.inverse() * result.volume_from_camera;
    let translation_m = jump.translation.vector.norm();
    let rotation_deg = jump.rotation.angle().to_degrees();
    if translation_m > icp.max_translation_jump_m || rotation_deg > icp.max_rotation_jump_deg {
        return Some(LossReason::PoseJump { translation_m, rotation_deg });
    }
    if let Some(g) = gravity_in_camera {
        let tilt_error_deg = tilt_error_deg(&result.volume_from_camera, g, &Vector3::y());
        if tilt_error_deg > config.motion_prior.max_tilt_error_deg {
            return Some(LossReason::TiltMismatch { tilt_error_deg });
        }
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
            let report =
                tracker.process(Frame { depth: &depth, gravity_in_camera: None, external_map_from_camera: None, timestamp: None }).unwrap();
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

    /// The depth-noise weights of ICP (σ ∝ z²) against KinectFusion's equal weights on the real TUM
    /// excerpt, whose desk at ~1 m has a 2–3 m room behind it: a lower ATE, under 3 mm.
    #[test]
    fn depth_noise_weights_lower_the_tum_ate() {
        let dataset = Dataset::open(&test_data_dir().join("tum_fr1_xyz")).unwrap();
        let ate = |power: u32| {
            let mut config = tum_config();
            config.icp.depth_noise_power = power;
            let (estimate, reference) = track_dataset(&dataset, config, 0.02);
            absolute_trajectory_rmse(&estimate, &reference).unwrap()
        };
        let (equal, weighted) = (ate(0), ate(2));
        eprintln!("TUM ATE {:.2} mm with equal weights, {:.2} mm with depth-noise weights", equal * 1e3, weighted * 1e3);
        assert!(weighted < equal - 1e-4 && weighted < 0.003, "{weighted} vs {equal}");
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
    fn a_model_prepared_after_the_outputs_tracks_as_one_raycast_by_the_next_frame() {
        let dataset = Dataset::open(&test_data_dir().join("open3d_rgbd")).unwrap();
        let mut lazy = Tracker::new(tum_config(), dataset.intrinsics).unwrap();
        let mut early = Tracker::new(tum_config(), dataset.intrinsics).unwrap();
        for index in 0..dataset.frames.len() {
            let depth = dataset.load_depth(index).unwrap();
            let frame = Frame { depth: &depth, gravity_in_camera: None, external_map_from_camera: None, timestamp: None };
            let (a, b) = (lazy.process(frame).unwrap(), early.process(frame).unwrap());
            // The early tracker's caller prepares the model once it has the frame's outputs.
            assert!(early.pending_model.is_some());
            early.prepare_model();
            assert!(early.pending_model.is_none() && early.model.is_some());
            let jump = a.map_from_camera.inverse() * b.map_from_camera;
            assert!(jump.translation.vector.norm() < 1e-6 && jump.rotation.angle() < 1e-6, "frame {index}: {jump:?}");
            if index > 0 {
                // The model raycast is timed with the frame aligned to it, whoever ran it.
                assert!(a.timings.raycast_ms > 0.0 && b.timings.raycast_ms > 0.0);
            }
        }
    }

    #[test]
    fn the_wide_level_runs_first_on_large_predicted_motion_and_on_every_retry() {
        let config = TrackerConfig::default();
        let last = Isometry3::translation(0.5, 0.3, 0.5);
        let small = last * Isometry3::translation(0.01, 0.0, 0.0);
        let large = last * Isometry3::translation(0.1, 0.0, 0.0);
        let turned = Isometry3::from_parts(last.translation, nalgebra::UnitQuaternion::from_euler_angles(0.0, 0.17, 0.0));
        assert!(!wide_first(&config.icp, &last, &small));
        assert!(wide_first(&config.icp, &last, &large) && wide_first(&config.icp, &last, &turned));
        // Tracking, small motion: narrow first, then the wide retries from the prediction and the last pose.
        assert_eq!(hypotheses(&config, false, &last, &small), vec![(small, false), (small, true), (last, true)]);
        // Large motion: wide first, then from the last pose.
        assert_eq!(hypotheses(&config, false, &last, &large), vec![(large, true), (last, true)]);
        // No velocity (prediction = last pose): one start, narrow then wide.
        assert_eq!(hypotheses(&config, false, &last, &last), vec![(last, false), (last, true)]);
        // During a short loss: both starts, wide.
        assert_eq!(hypotheses(&config, true, &last, &large), vec![(large, true), (last, true)]);
        // Without retries or the wide level: one narrow attempt.
        let mut plain = config.clone();
        plain.relocalisation.retry_within_frame = false;
        assert_eq!(hypotheses(&plain, false, &last, &small), vec![(small, false)]);
        plain.icp.wide.iterations = 0;
        assert_eq!(hypotheses(&plain, false, &last, &large), vec![(large, false)]);
        // The coarse search: the start, 4 horizontal moves, 2 turns about gravity.
        let starts = search_starts(&config.icp.wide, &last);
        assert_eq!(starts.len(), 7);
        assert_eq!(starts[0], last);
        for moved in &starts[1..5] {
            let d = moved.translation.vector - last.translation.vector;
            assert!((d.norm() - config.icp.wide.search_m).abs() < 1e-12 && d.y == 0.0);
        }
        for turned in &starts[5..] {
            let turn = turned.rotation * last.rotation.inverse();
            assert!((turn.angle().to_degrees() - config.icp.wide.search_deg).abs() < 1e-9);
            assert!(turn.axis().is_some_and(|a| a.y.abs() > 0.999999));
        }
    }

    #[test]
    fn wrong_image_size_is_an_error_and_empty_frames_lose_tracking() {
        let intrinsics = Intrinsics::primesense_default().scaled(0.25);
        let mut tracker = Tracker::new(TrackerConfig::default(), intrinsics).unwrap();
        let bad = DepthImage::new(3, 3, vec![1.0; 9]).unwrap();
        let frame = Frame { depth: &bad, gravity_in_camera: None, external_map_from_camera: None, timestamp: None };
        assert!(matches!(tracker.process(frame), Err(TrackingError::SizeMismatch { .. })));
        let empty = DepthImage::new(intrinsics.width, intrinsics.height, vec![f32::NAN; intrinsics.width * intrinsics.height]).unwrap();
        let frame = Frame { depth: &empty, gravity_in_camera: None, external_map_from_camera: None, timestamp: None };
        assert_eq!(tracker.process(frame).unwrap().status, TrackingStatus::Initialized);
        // An empty frame fails ICP: a short loss first (map kept) ...
        let report = tracker.process(frame).unwrap();
        assert!(
            matches!(report.status, TrackingStatus::Relocalising { frames_lost: 1, reason: LossReason::TooFewInliers { .. } }),
            "{:?}",
            report.status
        );
        assert_eq!(report.icp.map(|s| s.attempts), Some(2), "the first attempt and the wide retry from the same pose");
        // ... a reset at once without short losses (J 5.2 as written).
        let config =
            TrackerConfig { relocalisation: RelocalisationConfig { max_lost_frames: 0, ..Default::default() }, ..TrackerConfig::default() };
        let mut tracker = Tracker::new(config, intrinsics).unwrap();
        assert_eq!(tracker.process(frame).unwrap().status, TrackingStatus::Initialized);
        let report = tracker.process(frame).unwrap();
        assert!(matches!(report.status, TrackingStatus::Lost(LossReason::TooFewInliers { .. })), "{:?}", report.status);
        assert!(Tracker::new(TrackerConfig { model_scale: 0.0, ..TrackerConfig::default() }, intrinsics).is_err());
        let mut bad = TrackerConfig::default();
        bad.icp.wide.stride = 0;
        assert!(matches!(Tracker::new(bad, intrinsics), Err(TrackingError::InvalidConfig(m)) if m.contains("icp.wide")));
        let mut bad = TrackerConfig::default();
        bad.motion_prior.max_extrapolation = f64::NAN;
        assert!(matches!(Tracker::new(bad, intrinsics), Err(TrackingError::InvalidConfig(m)) if m.contains("motion_prior")));
    }
}

//! Camera tracking (J 5.1) and the per-frame moving-volume fusion loop (J 5.2 steps 3–5).
//!
//! ICP is frame-to-model: the new depth frame (a 2×2 pyramid, coarse to fine) is aligned to the
//! model raycast from the previous pose by projective data association and point-to-plane Gauss–Newton
//! steps; the 6×6 normal equations are summed in parallel (f32 over batches of 64 inliers, f64
//! totals), with Huber weights and a distance gate. Loss is declared on few inliers, a large residual, a degenerate system or a pose jump, and
//! the volume is reset (J 5.2: "if camera tracking does fail, then the whole patch map is reset").
//!
//! `Tracker::process` reads as the paper's loop: track → integrate → remap → raycast the model.
//! Also here: trajectory evaluation (rigid alignment, ATE RMSE, relative pose errors).

use std::time::Instant;

use nalgebra::{Isometry3, Matrix3, Matrix6, Point3, Translation3, UnitQuaternion, Vector3, Vector6};
use rayon::prelude::*;

use crate::camera::{DepthImage, Intrinsics};
use crate::fusion::{floor_small, FusionError, TsdfConfig, TsdfVolume};
use crate::raycast::{raycast_birds_eye, raycast_guided, BirdsEyeConfig, BirdsEyeView, ModelRaycast, RayHint, RaycastConfig};
use crate::volume::{initial_volume_from_camera, map_from_volume_rotation, plan_remap, remap_tsdf, MovingVolumeConfig};

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

/// One pyramid level of the new frame: intrinsics and its valid points in the camera frame.
pub struct SourceLevel {
    pub intrinsics: Intrinsics,
    pub points_in_camera: Vec<Vector3<f32>>,
}

/// Depth pyramid, coarsest first (1/4, 1/2, 1 of the input resolution).
pub fn build_pyramid(depth: &DepthImage, intrinsics: &Intrinsics, depth_jump_m: f32) -> Vec<SourceLevel> {
    let half = downsample(depth, depth_jump_m);
    let quarter = downsample(&half, depth_jump_m);
    source_pyramid(&[&quarter, &half, depth], intrinsics, &[1, 1, 1])
}

/// Source levels from depth images at 1/4, 1/2, 1 of the input resolution; levels without ICP
/// iterations stay empty (not back-projected).
fn source_pyramid(images: &[&DepthImage; 3], intrinsics: &Intrinsics, iterations: &[usize; 3]) -> Vec<SourceLevel> {
    images
        .iter()
        .zip(iterations)
        .zip([0.25, 0.5, 1.0])
        .map(|((image, &n), scale)| {
            let level_intrinsics = intrinsics.scaled(scale);
            if n == 0 {
                SourceLevel { intrinsics: level_intrinsics, points_in_camera: Vec::new() }
            } else {
                source_level(image, &level_intrinsics)
            }
        })
        .collect()
}

/// 2×2 block average of depths that agree within `depth_jump_m` (NaN otherwise).
pub fn downsample(depth: &DepthImage, depth_jump_m: f32) -> DepthImage {
    let (width, height) = (depth.width / 2, depth.height / 2);
    let mut depth_m = vec![f32::NAN; width * height];
    let input_width = depth.width.max(1);
    depth_m.par_chunks_mut(width.max(1)).enumerate().for_each(|(v, row)| {
        // The two input rows of output row v (2v + 1 < height for every output row).
        let top = depth.depth_m.get(2 * v * input_width..(2 * v + 1) * input_width).unwrap_or(&[]);
        let bottom = depth.depth_m.get((2 * v + 1) * input_width..(2 * v + 2) * input_width).unwrap_or(&[]);
        for (u, out) in row.iter_mut().enumerate() {
            let mut sum = 0.0;
            let mut count = 0;
            let (mut lo, mut hi) = (f32::INFINITY, f32::NEG_INFINITY);
            let quad = [top.get(2 * u), top.get(2 * u + 1), bottom.get(2 * u), bottom.get(2 * u + 1)];
            for &d in quad.into_iter().flatten() {
                if d.is_finite() {
                    sum += d;
                    count += 1;
                    lo = lo.min(d);
                    hi = hi.max(d);
                }
            }
            if count >= 2 && hi - lo <= depth_jump_m {
                *out = sum / count as f32;
            }
        }
    });
    DepthImage { width: width.max(1), height: height.max(1), depth_m }
}

fn source_level(depth: &DepthImage, intrinsics: &Intrinsics) -> SourceLevel {
    let (fx, fy, cx, cy) = (intrinsics.fx as f32, intrinsics.fy as f32, intrinsics.cx as f32, intrinsics.cy as f32);
    // Ray slopes per column and row, computed once (no per-pixel division).
    let x_slopes: Vec<f32> = (0..depth.width).map(|u| (u as f32 - cx) / fx).collect();
    let mut points_in_camera = Vec::with_capacity(depth.depth_m.len());
    for (v, row) in depth.depth_m.chunks(depth.width.max(1)).enumerate() {
        let y_slope = (v as f32 - cy) / fy;
        for (&d, x_slope) in row.iter().zip(&x_slopes) {
            if d.is_finite() {
                points_in_camera.push(Vector3::new(x_slope * d, y_slope * d, d));
            }
        }
    }
    SourceLevel { intrinsics: *intrinsics, points_in_camera }
}

/// Result of one ICP run.
#[derive(Debug, Clone, Copy)]
pub struct IcpResult {
    pub volume_from_camera: Isometry3<f64>,
    pub summary: IcpSummary,
    /// Smallest eigenvalue of the last normal matrix divided by the inlier count.
    pub min_eigenvalue: f64,
}

/// Normal equations of point-to-plane ICP: Σ w JᵀJ, Σ w Jᵀr, with statistics.
#[derive(Clone, Copy)]
struct Normal {
    jtj: [f64; 21],
    jtr: [f64; 6],
    inliers: usize,
    /// Source points that landed on a model pixel with a surface (before the distance gate).
    associated: usize,
    squared_residuals: f64,
}

impl Normal {
    fn zero() -> Self {
        Self { jtj: [0.0; 21], jtr: [0.0; 6], inliers: 0, associated: 0, squared_residuals: 0.0 }
    }
    fn add(mut self, other: Self) -> Self {
        for (a, b) in self.jtj.iter_mut().zip(other.jtj.iter()) {
            *a += b;
        }
        for (a, b) in self.jtr.iter_mut().zip(other.jtr.iter()) {
            *a += b;
        }
        self.inliers += other.inliers;
        self.associated += other.associated;
        self.squared_residuals += other.squared_residuals;
        self
    }
    fn matrices(&self) -> (Matrix6<f64>, Vector6<f64>) {
        let mut h = Matrix6::zeros();
        let mut k = 0;
        for r in 0..6 {
            for c in r..6 {
                h[(r, c)] = self.jtj[k];
                h[(c, r)] = self.jtj[k];
                k += 1;
            }
        }
        (h, Vector6::from_column_slice(&self.jtr))
    }
}

/// Frame-to-model point-to-plane ICP (J 5.1), coarse to fine over the source pyramid.
pub fn icp(config: &IcpConfig, pyramid: &[SourceLevel], model: &ModelRaycast, initial: &Isometry3<f64>) -> IcpResult {
    let mut pose = *initial;
    let mut summary = IcpSummary::default();
    // Normal matrix and inlier count of the last successful iteration: its smallest eigenvalue (the
    // degeneracy check) is computed once after the last iteration, not at every iteration.
    let mut last_system: Option<(Matrix6<f64>, usize)> = None;
    let model_from_volume = model.volume_from_camera.inverse().cast::<f32>();
    for (level, source) in pyramid.iter().enumerate() {
        let iterations = config.iterations.get(level).copied().unwrap_or(0);
        let gate = config.max_correspondence_m.get(level).copied().unwrap_or(0.05);
        for _ in 0..iterations {
            let normal = accumulate(source, model, &model_from_volume, &pose, gate as f32, config.huber_m);
            summary = IcpSummary {
                iterations: summary.iterations + 1,
                inliers: normal.inliers,
                valid_source_points: source.points_in_camera.len(),
                associated: normal.associated,
                rms_m: (normal.squared_residuals / normal.inliers.max(1) as f64).sqrt(),
            };
            if normal.inliers < 6 {
                last_system = None;
                break;
            }
            let (h, g) = normal.matrices();
            let Some(cholesky) = h.cholesky() else {
                last_system = None;
                break;
            };
            last_system = Some((h, normal.inliers));
            let delta = cholesky.solve(&(-g));
            let translation = Vector3::new(delta[0], delta[1], delta[2]);
            let rotation = Vector3::new(delta[3], delta[4], delta[5]);
            // Left-multiplied increment: p' ← exp(δ) p'.
            let increment = Isometry3::from_parts(Translation3::from(translation), UnitQuaternion::from_scaled_axis(rotation));
            pose = increment * pose;
            if translation.norm() < config.convergence && rotation.norm() < config.convergence {
                break;
            }
        }
    }
    let min_eigenvalue = last_system.map_or(0.0, |(h, inliers)| h.symmetric_eigenvalues().min() / inliers as f64);
    IcpResult { volume_from_camera: pose, summary, min_eigenvalue }
}

/// Inliers gathered before their products are summed (in f32) and added to the f64 totals: f32
/// rounding over this many terms stays near 1e-5 relative, far below what moves the Gauss–Newton step.
const BATCH: usize = 64;

/// A batch of weighted point-to-plane rows √w·(J, r), J = [n, p × n], as columns (structure of
/// arrays, so the 27 sums of products of column pairs vectorise); unused entries are zero.
struct RowBatch {
    columns: [[f32; BATCH]; 7],
    len: usize,
}

impl RowBatch {
    fn new() -> Self {
        Self { columns: [[0.0; BATCH]; 7], len: 0 }
    }
}

/// Σ a·b over a batch, in 8 lanes.
#[inline]
fn batch_dot(a: &[f32; BATCH], b: &[f32; BATCH]) -> f32 {
    let mut lanes = [0.0f32; 8];
    for (chunk_a, chunk_b) in a.chunks_exact(8).zip(b.chunks_exact(8)) {
        for ((lane, x), y) in lanes.iter_mut().zip(chunk_a).zip(chunk_b) {
            *lane += x * y;
        }
    }
    lanes.iter().sum()
}

/// Adds the batch's JᵀWJ (upper triangle) and JᵀWr to the f64 totals and empties the batch.
fn flush_batch(acc: &mut Normal, batch: &mut RowBatch) {
    if batch.len == 0 {
        return;
    }
    let mut k = 0;
    for (a, column_a) in batch.columns.iter().take(6).enumerate() {
        for column_b in batch.columns.iter().take(6).skip(a) {
            if let Some(total) = acc.jtj.get_mut(k) {
                *total += f64::from(batch_dot(column_a, column_b));
            }
            k += 1;
        }
        if let Some(total) = acc.jtr.get_mut(a) {
            *total += f64::from(batch_dot(column_a, &batch.columns[6]));
        }
    }
    *batch = RowBatch::new();
}

/// Projective association + point-to-plane linearisation, summed in parallel (f32 sums over
/// batches of `BATCH` inliers, f64 totals).
fn accumulate(
    source: &SourceLevel,
    model: &ModelRaycast,
    model_from_volume: &Isometry3<f32>,
    volume_from_camera: &Isometry3<f64>,
    gate: f32,
    huber: f64,
) -> Normal {
    let pose = volume_from_camera.cast::<f32>();
    // Projection straight from the source camera into the model camera; the volume-frame point is
    // only needed for the points that find a model surface.
    let model_from_camera = model_from_volume * pose;
    let huber = huber as f32;
    let mi = &model.intrinsics;
    let (fx, fy, cx, cy) = (mi.fx as f32, mi.fy as f32, mi.cx as f32, mi.cy as f32);
    let (w, h) = (mi.width as f32 - 0.5, mi.height as f32 - 0.5);
    source
        .points_in_camera
        .par_chunks(1024)
        .map(|chunk| {
            let mut acc = Normal::zero();
            let mut batch = RowBatch::new();
            for point in chunk {
                let m = model_from_camera * Point3::from(*point);
                if m.z <= 0.0 {
                    continue;
                }
                let inv_z = 1.0 / m.z;
                let u = fx * m.x * inv_z + cx;
                let v = fy * m.y * inv_z + cy;
                if !(u >= -0.5 && v >= -0.5 && u < w && v < h) {
                    continue;
                }
                let index = floor_small(v + 0.5) as usize * mi.width + floor_small(u + 0.5) as usize;
                let (Some(q), Some(n)) = (model.points_in_volume.get(index), model.normals_in_volume.get(index)) else {
                    continue;
                };
                if !q.x.is_finite() {
                    continue;
                }
                acc.associated += 1;
                let p = pose * Point3::from(*point);
                let difference = p - q;
                if difference.norm_squared() > gate * gate {
                    continue;
                }
                let r = n.dot(&difference);
                // Huber weight w, applied as √w to both factors of each product.
                let sqrt_weight = if r.abs() <= huber { 1.0 } else { (huber / r.abs()).sqrt() };
                let c = p.coords.cross(n);
                let row = [n.x, n.y, n.z, c.x, c.y, c.z, r];
                let slot = batch.len;
                for (column, value) in batch.columns.iter_mut().zip(row) {
                    if let Some(entry) = column.get_mut(slot) {
                        *entry = sqrt_weight * value;
                    }
                }
                batch.len += 1;
                acc.inliers += 1;
                acc.squared_residuals += f64::from(r * r);
                if batch.len == BATCH {
                    flush_batch(&mut acc, &mut batch);
                }
            }
            flush_batch(&mut acc, &mut batch);
            acc
        })
        .reduce(Normal::zero, Normal::add)
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
    if !(result.min_eigenvalue > 1e-9) {
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

/// Rigid transform `reference_from_estimate` minimising Σ‖R e + t − r‖² (Horn / Kabsch via SVD).
pub fn align_rigid(estimate: &[Vector3<f64>], reference: &[Vector3<f64>]) -> Option<Isometry3<f64>> {
    if estimate.len() != reference.len() || estimate.len() < 3 {
        return None;
    }
    let n = estimate.len() as f64;
    let mean_e: Vector3<f64> = estimate.iter().sum::<Vector3<f64>>() / n;
    let mean_r: Vector3<f64> = reference.iter().sum::<Vector3<f64>>() / n;
    let mut covariance = Matrix3::zeros();
    for (e, r) in estimate.iter().zip(reference) {
        covariance += (r - mean_r) * (e - mean_e).transpose();
    }
    let rotation = patchwalk_spl::geometry::nearest_rotation(&covariance)?;
    let translation = mean_r - rotation * mean_e;
    Some(Isometry3::from_parts(Translation3::from(translation), UnitQuaternion::from_rotation_matrix(&rotation)))
}

/// Absolute trajectory error (RMSE of positions after rigid alignment) of matched pose pairs.
pub fn absolute_trajectory_rmse(estimate: &[Isometry3<f64>], reference: &[Isometry3<f64>]) -> Option<f64> {
    let e: Vec<Vector3<f64>> = estimate.iter().map(|p| p.translation.vector).collect();
    let r: Vec<Vector3<f64>> = reference.iter().map(|p| p.translation.vector).collect();
    let alignment = align_rigid(&e, &r)?;
    let sum: f64 = e.iter().zip(&r).map(|(e, r)| (alignment * Point3::from(*e) - Point3::from(*r)).norm_squared()).sum();
    Some((sum / e.len() as f64).sqrt())
}

/// Relative pose errors between consecutive matched poses: (translation m, rotation deg) per pair.
pub fn relative_pose_errors(estimate: &[Isometry3<f64>], reference: &[Isometry3<f64>]) -> Vec<(f64, f64)> {
    estimate
        .windows(2)
        .zip(reference.windows(2))
        .filter_map(|(e, r)| {
            let (e0, e1, r0, r1) = (e.first()?, e.get(1)?, r.first()?, r.get(1)?);
            let error = (r0.inverse() * r1).inverse() * (e0.inverse() * e1);
            Some((error.translation.vector.norm(), error.rotation.angle().to_degrees()))
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::dataset::{test_data_dir, Dataset};

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
    fn downsample_averages_agreeing_depths_only() {
        let nan = f32::NAN;
        // Three 2×2 cells: four agreeing depths, one valid depth, and a 10 cm jump.
        #[rustfmt::skip]
        let depth = DepthImage::new(6, 2, vec![
            1.0, 1.02, 2.0, nan, 1.0, 1.1,
            1.01, 1.03, nan, nan, 1.0, 1.1,
        ]).unwrap();
        let half = downsample(&depth, 0.03);
        assert_eq!((half.width, half.height), (3, 1));
        assert!((half.depth_m[0] - 1.015).abs() < 1e-6, "{}", half.depth_m[0]);
        assert!(half.depth_m[1].is_nan() && half.depth_m[2].is_nan());
    }

    #[test]
    fn alignment_recovers_a_known_transform() {
        let truth = Isometry3::new(Vector3::new(0.3, -1.0, 2.0), Vector3::new(0.1, -0.4, 0.9));
        let points: Vec<Vector3<f64>> = (0..10).map(|i| Vector3::new(i as f64, (i * i) as f64 * 0.1, (i as f64).sin())).collect();
        let moved: Vec<Vector3<f64>> = points.iter().map(|p| (truth * Point3::from(*p)).coords).collect();
        let found = align_rigid(&points, &moved).unwrap();
        assert!((found.to_homogeneous() - truth.to_homogeneous()).norm() < 1e-9);
        assert!(align_rigid(&points[..2], &moved[..2]).is_none());
        let poses: Vec<Isometry3<f64>> = points.iter().map(|p| Isometry3::translation(p.x, p.y, p.z)).collect();
        let moved_poses: Vec<Isometry3<f64>> = poses.iter().map(|p| truth * p).collect();
        assert!(absolute_trajectory_rmse(&poses, &moved_poses).unwrap() < 1e-9);
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

//! The per-frame perception pipeline of the patch_mapper node (J 5.2, "stage II" per frame), ROS-free:
//!
//! 1. input checks (stamp order, valid depth fraction),
//! 2. gravity from the IMU: the accelerometer readings around the frame stamp (their per-axis
//!    median) through `camera_from_imu` (J 2.2, J 4.1 step 2),
//! 3. tracking + fusion: ICP, TSDF integration, moving-volume remap ([`Tracker::process`], J 5.1–5.2
//!    steps 3–5),
//! 4. patch tracking on remaps / re-initialisations: the patch map is re-gridded to the new volume and
//!    patches that left the cube are dropped (J 5.2 step 6, with [`PatchMap::set_grid`] and
//!    [`PatchMap::drop_outside_volume`]). A frame ICP cannot align is a short loss: the tracker keeps
//!    the volume and the last good pose, the frame is refused ([`PipelineError::Relocalising`]) and
//!    the patch map is kept; the next frame that aligns against the kept model is `Relocalised` and
//!    mapped as usual. Only a real loss (more than `tracker.relocalisation.max_lost_frames` failed
//!    frames in a row) resets the whole map (J 5.2),
//! 5. birds-eye raycast of the volume (J 5.2 step 8), of the part the mapper reads: around the DtFP
//!    ball and the patches it re-fits this frame (`PipelineConfig::raycast_mapped_region`),
//! 6. patch mapping on the birds-eye view ([`Mapper::process`], J 4 stages i–v, J 5.2 step 9): seeds
//!    fill the gravity-aligned grid nearest-cell-first around the camera, i.e. around and in front of
//!    the feet; the saliency fixation point sits `fixation_forward_m` ahead.
//!
//! Frames: patches and the camera pose are in the `map` frame: gravity aligned, z up (REP-103). It is
//! the tracker's fixed world frame: `map_from_volume` is the rotation of
//! [`patchwalk_fusion::volume::map_from_volume_rotation`] (map x = volume x, map y = volume z (forward),
//! map z = −volume y (up, the volume's y points along gravity)) composed with the translations of the
//! moving-volume remaps, so the map stays put while the volume follows the camera. Its origin is the
//! corner of the first volume (the camera starts at the volume's nominal position).

use std::collections::VecDeque;
use std::time::Instant;

use nalgebra::{Isometry3, Point3, Rotation3, Unit, Vector3};

use crate::acquire::{gravity_from_accelerometer, AcquireError};
use crate::mapper::{FrameInput, FrameSummary, Mapper, MapperConfig, MapperError, SeedOutcome};
use crate::patch_map::{PatchMap, VolumeGrid};
use patchwalk_fusion::camera::{DepthImage, Intrinsics};
use patchwalk_fusion::dataset::median_per_axis;
use patchwalk_fusion::raycast::BirdsEyeView;
use patchwalk_fusion::tracking::{FrameReport, LossReason, Tracker, TrackerConfig, TrackingError, TrackingStatus};
use patchwalk_spl::sensor::ErrorModel;

/// Name of the gravity-aligned output frame (REP-105 `map`).
pub const MAP_FRAME: &str = "map";

/// Pipeline-level parameters (`pipeline:` in config/patch_mapper.yaml). Gravity comes from the
/// `mapper.acquire` section (`camera_from_imu`, `accel_half_window_s`).
#[derive(Debug, Clone, PartialEq, serde::Serialize, serde::Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct PipelineConfig {
    /// Frames with fewer valid depth pixels than this fraction are skipped (an all-zero or all-NaN
    /// frame would otherwise be a tracking loss and reset the map, J 5.2).
    pub min_valid_fraction: f64,
    /// Without any IMU sample so far, run with the camera's y axis as "down" (true) or skip frames
    /// (false). Once the IMU has been heard, frames without samples near their stamp are skipped.
    pub allow_missing_imu: bool,
    /// Accelerometer samples older than this (s) before the newest one are forgotten.
    pub imu_buffer_s: f64,
    /// Raycast only the part of the birds-eye view the mapper reads (true), or all of it: the DtFP
    /// ball (J 4.2.1 step 6.2), the map patches it re-fits this frame and the predicted footholds it
    /// may seed at (`mapper.seeds.order`), widened by
    /// [`crate::mapper::REGION_MARGIN_RADII`] foot radii. The whole view is raycast without a DtFP ball (an infinite
    /// `mapper.saliency.fixation_radius_m`), after a frame whose ball held no salient point (the
    /// saliency then looks at the whole view), and while [`Pipeline::set_whole_view`] asks for it.
    pub raycast_mapped_region: bool,
}

impl Default for PipelineConfig {
    fn default() -> Self {
        Self { min_valid_fraction: 0.05, allow_missing_imu: true, imu_buffer_s: 2.0, raycast_mapped_region: true }
    }
}

/// The mapper configuration of the node: J's values (`MapperConfig::default()`) except where the
/// birds-eye input and the robot's size ask otherwise.
pub fn default_mapper_config() -> MapperConfig {
    let mut config = MapperConfig::default();
    // J 4.1 step 5: the 200×200 birds-eye raycast is used as D directly (no 2×2 median downsample).
    config.preprocess.median_downsample = false;
    // J 6.3: the robot's birds-eye camera is bo = 0.5 m above a camera about 0.45 m above the ground,
    // and the footholds of interest are right in front of the feet (J 6.3: "a rock in front of the
    // robot"), not two human steps ahead.
    config.saliency.fixation_down_m = 0.95;
    config.saliency.fixation_forward_m = 0.25;
    // J 6.3 "Foot Placement Tests": the map is made "using seeds in the area around the robot's
    // feet" and a trained patch matches only within rs = 0.01 m of its position, so the foothold
    // area is seeded densely instead of one random seed per 16 cm cell (Vg = 8, J 4.3): a
    // 0.12 m fixation ball (DtFP) with 1 cm cells (Vg = 128 over the 1.28 m volume), one patch per
    // cell, so some patch centre lies within a few mm of any point of a rock top.
    config.saliency.fixation_radius_m = 0.12;
    config.seeds.cells_per_side = 128;
    config.seeds.per_cell = 1;
    config.seeds.max_seeds = 256;
    // The birds-eye points are raycast from the fused TSDF, not measured by the Kinect: J eq 2's
    // single-frame disparity noise (≈ 4 mm at 1 m from the virtual camera) hides a 5 cm log's
    // κ = −11 m⁻¹ from the step-3 significance test. A constant 1 mm along the (vertical) ray;
    // the fit inflates its covariance by the residual where the data is noisier (s² ≥ 1).
    config.sensor = ErrorModel::Constant { sigma_m: 0.001 };
    // At the sensor rate (30 Hz) stages iii–v get what fusion leaves of the 33 ms frame (J 6.1.2
    // limits the frame to "e.g. 100 ms" offline); the map fills up over a few frames instead.
    config.time_limit_ms = 15.0;
    config
}

/// Why a frame or an IMU sample was not used. Every variant leaves the pipeline usable.
#[derive(Debug, thiserror::Error, PartialEq)]
pub enum PipelineError {
    #[error("depth stamp {stamp:.6} s is not after the last frame's {last:.6} s (out of order or duplicate)")]
    StampOrder { stamp: f64, last: f64 },
    #[error("IMU stamp {stamp:.6} s is not after the last sample's {last:.6} s (out of order or duplicate)")]
    ImuStampOrder { stamp: f64, last: f64 },
    #[error("IMU sample is not finite or not a gravity reading: {0:?}")]
    BadImu([f64; 3]),
    #[error("no accelerometer sample within {half_window_s} s of the depth stamp {stamp:.6} s (IMU gap)")]
    ImuGap { stamp: f64, half_window_s: f64 },
    #[error("no IMU sample received yet and pipeline.allow_missing_imu is false")]
    NoImu,
    #[error("only {valid} of {total} depth pixels are valid (NaN/zero depth)")]
    TooFewValid { valid: usize, total: usize },
    #[error("non-finite timestamp {0}")]
    BadStamp(f64),
    #[error(
        "{input} stamp {stamp:.6} s is {ahead:.3} s ahead of the node clock ({now:.6} s); at most {max_future_s} s allowed (ros.max_stamp_skew_s.future)"
    )]
    FutureStamp { input: &'static str, stamp: f64, now: f64, ahead: f64, max_future_s: f64 },
    #[error(
        "{input} stamp {stamp:.6} s is {behind:.3} s behind the node clock ({now:.6} s); at most {max_past_s} s allowed (ros.max_stamp_skew_s.past)"
    )]
    PastStamp { input: &'static str, stamp: f64, now: f64, behind: f64, max_past_s: f64 },
    #[error(transparent)]
    Gravity(#[from] AcquireError),
    #[error(transparent)]
    Tracking(#[from] TrackingError),
    #[error("tracking lost for {frames_lost} of at most {max_lost_frames} frames ({reason}): map kept, relocalising against it")]
    Relocalising { frames_lost: usize, max_lost_frames: usize, reason: LossReason },
    #[error(transparent)]
    Mapper(#[from] MapperError),
    #[error("invalid pipeline configuration: {0}")]
    Config(String),
}

/// The plausible stamps of an input around the clock of the node that receives it
/// (`ros.max_stamp_skew_s` in config/patch_mapper.yaml).
///
/// The pipeline orders frames and IMU samples by their stamps, so one stamp far in the future would
/// make every later, correctly stamped input look out of order; such stamps are refused where the
/// input enters. The future bound is small (a clock offset between hosts, transport delay). The past
/// bound is unlimited by default: an old stamp cannot hold later inputs back (the next newer input is
/// used), and recorded data replayed with its own stamps (bags, datasets) or a simulator's clock
/// starting at 0 is legitimately far behind the wall clock. A robot with synchronised clocks may set
/// it (e.g. 3600 s) to refuse stale input.
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize, serde::Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct StampWindow {
    /// Stamps more than this (s) ahead of the node clock are refused.
    pub future: f64,
    /// Stamps more than this (s) behind the node clock are refused (`.inf`: none).
    pub past: f64,
}

impl Default for StampWindow {
    fn default() -> Self {
        Self { future: 10.0, past: f64::INFINITY }
    }
}

impl StampWindow {
    /// Checks the bounds themselves (non-negative; the past bound may be infinite).
    pub fn validate(&self) -> Result<(), PipelineError> {
        if !(self.future.is_finite() && self.future >= 0.0 && self.past >= 0.0) {
            return Err(PipelineError::Config(format!(
                "max_stamp_skew_s: future must be finite and >= 0, past >= 0 (got future {}, past {})",
                self.future, self.past
            )));
        }
        Ok(())
    }

    /// Whether `stamp` (s) of an input (`input`: "depth", "IMU") is plausible at the node clock `now` (s).
    pub fn check(&self, input: &'static str, stamp: f64, now: f64) -> Result<(), PipelineError> {
        if !stamp.is_finite() {
            return Err(PipelineError::BadStamp(stamp));
        }
        let ahead = stamp - now;
        if ahead > self.future {
            return Err(PipelineError::FutureStamp { input, stamp, now, ahead, max_future_s: self.future });
        }
        if -ahead > self.past {
            return Err(PipelineError::PastStamp { input, stamp, now, behind: -ahead, max_past_s: self.past });
        }
        Ok(())
    }
}

/// Wall time of each stage of one frame (ms), in pipeline order.
#[derive(Debug, Clone, Copy, Default, PartialEq, serde::Serialize)]
pub struct PipelineTimings {
    pub gravity_ms: f64,
    pub icp_ms: f64,
    pub integrate_ms: f64,
    pub remap_ms: f64,
    pub model_raycast_ms: f64,
    pub patch_tracking_ms: f64,
    pub birds_eye_ms: f64,
    pub map_preprocess_ms: f64,
    pub map_saliency_ms: f64,
    pub map_seeds_ms: f64,
    pub map_fit_ms: f64,
    /// The part of `map_fit_ms` spent re-fitting mapped patches and fusing them (`mapper.fusion`).
    pub map_reobserve_ms: f64,
    pub total_ms: f64,
}

impl PipelineTimings {
    /// `(name, ms)` pairs for diagnostics (MapperStatus.timing_names / timing_ms).
    pub fn named(&self) -> [(&'static str, f64); 13] {
        [
            ("gravity", self.gravity_ms),
            ("icp", self.icp_ms),
            ("integrate", self.integrate_ms),
            ("remap", self.remap_ms),
            ("model_raycast", self.model_raycast_ms),
            ("patch_tracking", self.patch_tracking_ms),
            ("birds_eye_raycast", self.birds_eye_ms),
            ("map_preprocess", self.map_preprocess_ms),
            ("map_saliency", self.map_saliency_ms),
            ("map_seeds", self.map_seeds_ms),
            ("map_fit_validate", self.map_fit_ms),
            ("map_reobserve_fuse", self.map_reobserve_ms),
            ("total", self.total_ms),
        ]
    }
}

/// What one frame produced; the patches themselves are read from [`Pipeline::map`].
#[derive(Debug, Clone)]
pub struct FrameOutput {
    pub timestamp: f64,
    /// Camera pose in the map frame.
    pub map_from_camera: Isometry3<f64>,
    pub tracking: TrackingStatus,
    /// Unit gravity (down) in the camera frame used for this frame, if the IMU gave one.
    pub gravity_in_camera: Option<Unit<Vector3<f64>>>,
    /// The birds-eye raycast the patches were mapped on, and its pose in the map frame.
    pub birds_eye: BirdsEyeView,
    pub map_from_birds_eye: Isometry3<f64>,
    /// J Table 2 counts of this frame's seeds.
    pub mapped: FrameSummary,
    /// Every seed of this frame with its fitted patch (in the birds-eye camera frame) and verdict.
    pub seeds: Vec<SeedOutcome>,
    /// Patches dropped this frame by patch tracking (left the volume), a map reset, or to keep the
    /// map within `max_patches`.
    pub patches_dropped: usize,
    pub timings: PipelineTimings,
}

/// One accelerometer sample in the IMU frame.
#[derive(Debug, Clone, Copy, PartialEq)]
struct AccelSample {
    timestamp: f64,
    acceleration_in_imu: Vector3<f64>,
}

/// The running pipeline: tracker (volume + pose), mapper (patch map), IMU buffer.
pub struct Pipeline {
    config: PipelineConfig,
    tracker: Tracker,
    mapper: Mapper,
    imu: VecDeque<AccelSample>,
    imu_heard: bool,
    last_stamp: Option<f64>,
    intrinsics: Intrinsics,
    /// The last frame's saliency fell back to the whole view (its DtFP ball held no salient point).
    fell_back: bool,
    /// A caller wants the whole birds-eye view (e.g. to show it).
    whole_view: bool,
}

impl Pipeline {
    /// A pipeline for depth images of `intrinsics`. `mapper.volume_edge_m` must equal the TSDF edge
    /// (both are Vs, J 4.3 / J 5.2).
    pub fn new(
        config: PipelineConfig,
        tracker: TrackerConfig,
        mapper: MapperConfig,
        intrinsics: Intrinsics,
    ) -> Result<Self, PipelineError> {
        if !((0.0..=1.0).contains(&config.min_valid_fraction) && config.imu_buffer_s.is_finite() && config.imu_buffer_s > 0.0) {
            return Err(PipelineError::Config("min_valid_fraction must be in [0, 1] and imu_buffer_s positive".into()));
        }
        let tracker = Tracker::new(tracker, intrinsics)?;
        let edge = f64::from(tracker.volume().edge_m());
        let voxel = f64::from(tracker.volume().voxel_size());
        if (mapper.volume_edge_m - edge).abs() > voxel {
            return Err(PipelineError::Config(format!(
                "mapper.volume_edge_m = {} but the TSDF volume edge is {edge} m (tracker.tsdf.size_m rounded to blocks)",
                mapper.volume_edge_m
            )));
        }
        let mapper = Mapper::new(mapper, MAP_FRAME, tracker.map_from_volume().inverse())?;
        Ok(Self {
            config,
            tracker,
            mapper,
            imu: VecDeque::new(),
            imu_heard: false,
            last_stamp: None,
            intrinsics,
            fell_back: false,
            whole_view: false,
        })
    }

    /// New mapper parameters from the next frame on; see [`Mapper::set_config`].
    pub fn set_mapper_config(&mut self, mapper: MapperConfig) -> Result<(), PipelineError> {
        Ok(self.mapper.set_config(mapper)?)
    }

    /// Predicted footholds (points in the `map` frame, scores in [0, 1]) for the learned seed orders
    /// (`mapper.seeds.order`), from the next frame on until replaced; a map reset clears them (they
    /// belong to the map frame of the map they were made for).
    pub fn set_seed_priors(&mut self, priors_in_map: Vec<(Vector3<f64>, f64)>) {
        self.mapper.set_seed_priors(priors_in_map);
    }

    /// The patch map (patches in the `map` frame).
    pub fn map(&self) -> &PatchMap {
        &self.mapper.map
    }

    /// Raycasts the model the next frame's ICP aligns to (J 5.2 step 7). `process` returns without
    /// it, so that the frame's outputs are not held up by work only the next frame needs: call this
    /// once they are out (the ROS node does, after publishing), or let the next `process` do it.
    pub fn prepare_next_frame(&mut self) {
        on_thread_pool(|| self.tracker.prepare_model());
    }

    /// The pixels of the birds-eye view the mapper reads this frame ([`Mapper::read_region`]),
    /// `None` for all of them (see `PipelineConfig::raycast_mapped_region`).
    fn mapped_region(&self) -> Option<Vec<bool>> {
        if !self.config.raycast_mapped_region || self.whole_view || self.fell_back {
            return None;
        }
        let (intrinsics, volume_from_birds_eye) = self.tracker.birds_eye_camera();
        self.mapper.read_region(&intrinsics, &volume_from_birds_eye, |pixels| self.tracker.birds_eye_within(pixels).depth)
    }

    /// The tracker (volume, pose).
    pub fn tracker(&self) -> &Tracker {
        &self.tracker
    }

    /// Replaces `mapper.acquire.camera_from_imu` (the IMU mount found at run time, e.g. in TF).
    pub fn set_camera_from_imu(&mut self, camera_from_imu: &Rotation3<f64>) {
        self.mapper.config.acquire.camera_from_imu = std::array::from_fn(|r| std::array::from_fn(|c| camera_from_imu[(r, c)]));
    }

    /// Intrinsics the pipeline was built for.
    pub fn intrinsics(&self) -> &Intrinsics {
        &self.intrinsics
    }

    /// Adds an accelerometer reading (m/s², IMU frame). Out-of-order, duplicate or non-finite samples
    /// are rejected (the buffer is unchanged).
    pub fn push_imu(&mut self, timestamp: f64, acceleration_in_imu: Vector3<f64>) -> Result<(), PipelineError> {
        if !timestamp.is_finite() {
            return Err(PipelineError::BadStamp(timestamp));
        }
        if !(acceleration_in_imu.iter().all(|v| v.is_finite()) && acceleration_in_imu.norm() > 1e-3) {
            return Err(PipelineError::BadImu(acceleration_in_imu.into()));
        }
        if let Some(last) = self.imu.back() {
            if timestamp <= last.timestamp {
                return Err(PipelineError::ImuStampOrder { stamp: timestamp, last: last.timestamp });
            }
        }
        self.imu.push_back(AccelSample { timestamp, acceleration_in_imu });
        self.imu_heard = true;
        while self.imu.front().is_some_and(|s| s.timestamp < timestamp - self.config.imu_buffer_s) {
            self.imu.pop_front();
        }
        Ok(())
    }

    /// Forgets the volume, the patch map and every piece of time state: the depth stamp order and the
    /// buffered IMU samples (whose order the next sample is checked against). Whether an IMU has been
    /// heard is kept, so a frame after the reset waits for gravity instead of guessing it. The next frame
    /// re-initialises the volume at the camera (J 5.2 reset).
    pub fn reset(&mut self) {
        self.tracker.reset();
        self.mapper.map.retain(|_| false);
        self.mapper.set_seed_priors(Vec::new());
        self.last_stamp = None;
        self.imu.clear();
        self.fell_back = false;
    }

    /// Raycast the whole birds-eye view from the next frame on (true), or only the part the mapper
    /// reads when `raycast_mapped_region` is on (false).
    pub fn set_whole_view(&mut self, whole: bool) {
        self.whole_view = whole;
    }

    /// The stamp of the last processed frame (s), `None` after a reset.
    pub fn last_stamp(&self) -> Option<f64> {
        self.last_stamp
    }

    /// The number of buffered accelerometer samples.
    pub fn imu_samples(&self) -> usize {
        self.imu.len()
    }

    /// One depth frame (metres, stamp in s) through the whole pipeline.
    pub fn process(&mut self, depth: &DepthImage, timestamp: f64) -> Result<FrameOutput, PipelineError> {
        on_thread_pool(|| self.process_frame(depth, timestamp))
    }

    fn process_frame(&mut self, depth: &DepthImage, timestamp: f64) -> Result<FrameOutput, PipelineError> {
        let start = Instant::now();
        // 1. Input checks: nothing below changes state if they fail.
        self.check_frame(depth, timestamp)?;
        // 2. Gravity (J 2.2).
        let gravity_in_camera = self.gravity_at(timestamp)?;
        let t_gravity = Instant::now();
        // 3. Track, integrate, remap (J 5.2 steps 3–5).
        let report = self.tracker.process(patchwalk_fusion::tracking::Frame {
            depth,
            gravity_in_camera: gravity_in_camera.map(Unit::into_inner),
            external_map_from_camera: None,
            timestamp: Some(timestamp),
        })?;
        self.last_stamp = Some(timestamp);
        if let TrackingStatus::Relocalising { frames_lost, reason } = report.status {
            // A short loss: the frame has no pose; the map and the volume stay as they are.
            let max_lost_frames = self.tracker.config().relocalisation.max_lost_frames;
            return Err(PipelineError::Relocalising { frames_lost, max_lost_frames, reason });
        }
        // 4. Patch tracking (J 5.2 step 6).
        let t_track = Instant::now();
        let patches_dropped = self.track_patches(&report);
        let t_patch = Instant::now();
        // 5. Birds-eye raycast (J 5.2 step 8), of the part the mapper reads.
        let birds_eye = match self.mapped_region() {
            Some(region) => self.tracker.birds_eye_within(&region),
            None => self.tracker.birds_eye(),
        };
        let map_from_birds_eye = self.tracker.map_from_birds_eye(&birds_eye);
        let t_birds_eye = Instant::now();
        // 6. Patch mapping on the birds-eye view (J 5.2 step 9, J 4).
        let mapped = self.mapper.process(&FrameInput {
            depth: &birds_eye.depth,
            intrinsics: &birds_eye.intrinsics,
            volume_from_camera: birds_eye.volume_from_birds_eye,
            timestamp,
        })?;
        self.fell_back = mapped.saliency.dtfp_fallback.is_some();
        let ms = |a: Instant, b: Instant| (b - a).as_secs_f64() * 1e3;
        let timings = PipelineTimings {
            gravity_ms: ms(start, t_gravity),
            icp_ms: report.timings.icp_ms,
            integrate_ms: report.timings.integrate_ms,
            remap_ms: report.timings.remap_ms,
            model_raycast_ms: report.timings.raycast_ms,
            patch_tracking_ms: ms(t_track, t_patch),
            birds_eye_ms: ms(t_patch, t_birds_eye),
            map_preprocess_ms: mapped.timings.preprocess_ms,
            map_saliency_ms: mapped.timings.saliency_ms,
            map_seeds_ms: mapped.timings.seeds_ms,
            map_fit_ms: mapped.timings.fit_stage_ms,
            map_reobserve_ms: mapped.timings.reobserve_ms,
            total_ms: ms(start, Instant::now()),
        };
        Ok(FrameOutput {
            timestamp,
            map_from_camera: report.map_from_camera,
            tracking: report.status,
            gravity_in_camera,
            birds_eye,
            map_from_birds_eye,
            mapped: mapped.summary(),
            seeds: mapped.outcomes,
            patches_dropped: patches_dropped + mapped.evicted,
            timings,
        })
    }

    fn check_frame(&self, depth: &DepthImage, timestamp: f64) -> Result<(), PipelineError> {
        if !timestamp.is_finite() {
            return Err(PipelineError::BadStamp(timestamp));
        }
        if let Some(last) = self.last_stamp {
            if timestamp <= last {
                return Err(PipelineError::StampOrder { stamp: timestamp, last });
            }
        }
        let total = depth.width * depth.height;
        let valid = depth.valid_count();
        if (valid as f64) < self.config.min_valid_fraction * total as f64 || valid == 0 {
            return Err(PipelineError::TooFewValid { valid, total });
        }
        Ok(())
    }

    /// The accelerometer readings within `accel_half_window_s` of the stamp (their per-axis median
    /// ā, see [`median_per_axis`]) as unit gravity in the camera frame: `ĝ = −camera_from_imu · ā / |ā|`
    /// (J 2.2).
    fn gravity_at(&self, timestamp: f64) -> Result<Option<Unit<Vector3<f64>>>, PipelineError> {
        let acquire = &self.mapper.config.acquire;
        if !self.imu_heard {
            return if self.config.allow_missing_imu { Ok(None) } else { Err(PipelineError::NoImu) };
        }
        let half_window_s = acquire.accel_half_window_s;
        let window: Vec<Vector3<f64>> =
            self.imu.iter().filter(|s| (s.timestamp - timestamp).abs() <= half_window_s).map(|s| s.acceleration_in_imu).collect();
        let Some(acceleration) = median_per_axis(&window) else {
            return Err(PipelineError::ImuGap { stamp: timestamp, half_window_s });
        };
        let camera_from_imu = acquire.camera_from_imu()?;
        Ok(Some(gravity_from_accelerometer(&acceleration, &camera_from_imu)?))
    }

    /// J 5.2 step 6: after a remap or re-initialisation the map frame stays put and the grid follows
    /// the new volume; patches whose centre left the cube are dropped. A real tracking loss resets the
    /// map (a relocalised frame keeps it).
    fn track_patches(&mut self, report: &FrameReport) -> usize {
        let before = self.mapper.map.len();
        if matches!(report.status, TrackingStatus::Lost(_)) || (report.status == TrackingStatus::Initialized && before > 0) {
            self.mapper.map.retain(|_| false);
            self.mapper.set_seed_priors(Vec::new());
        }
        let volume_from_map = self.tracker.map_from_volume().inverse();
        if self.mapper.map.grid().volume_from_map != volume_from_map {
            let grid = VolumeGrid { volume_from_map, ..*self.mapper.map.grid() };
            self.mapper.map.set_grid(grid);
            self.mapper.map.drop_outside_volume();
        }
        before - self.mapper.map.len()
    }
}

/// Points of a birds-eye view in the map frame (for the PointCloud2), skipping pixels without a hit.
pub fn birds_eye_points_in_map(view: &BirdsEyeView, map_from_birds_eye: &Isometry3<f64>) -> Vec<Point3<f32>> {
    let mut points = Vec::with_capacity(view.depth.valid_count());
    for v in 0..view.depth.height {
        for u in 0..view.depth.width {
            if let Some(z) = view.depth.get(u, v) {
                let point_in_birds_eye = view.intrinsics.back_project(u as f64, v as f64, f64::from(z));
                points.push((map_from_birds_eye * Point3::from(point_in_birds_eye)).cast::<f32>());
            }
        }
    }
    points
}

/// Runs `op` on a thread of rayon's pool (inline when already on one, as in the ROS node, whose
/// worker runs in a pool of its own), the calling thread waiting once. A frame runs dozens of
/// parallel loops (the raycasts' rows, each ICP iteration's reduction, the mapper's tables); started
/// from a thread outside any pool (the replay loop, the benches), each of them would be handed to
/// the pool and waited for across threads, and the offline timings would not be the node's. Replays
/// of a walk: ICP p99 6.7 → 4.9 ms, frame p99 18.6 → 17.7 ms (means of 6 runs).
fn on_thread_pool<R: Send>(op: impl FnOnce() -> R + Send) -> R {
    rayon::scope(|_| op())
}

#[cfg(test)]
mod tests {
    use super::*;
    use patchwalk_fusion::calibration::{calibrate_dataset, CalibrationConfig};
    use patchwalk_fusion::dataset::{test_data_dir, Dataset};
    use patchwalk_fusion::fusion::TsdfConfig;

    /// TUM fr1_xyz: the Kinect is about 1 m from the desk, so a 2.56 m volume at 1 cm voxels; the
    /// desk fills the view, so the fixation ball is disabled.
    fn tum_pipeline(dataset: &Dataset) -> Pipeline {
        let tracker =
            TrackerConfig { tsdf: TsdfConfig { voxel_size_m: 0.01, size_m: 2.56, ..TsdfConfig::default() }, ..TrackerConfig::default() };
        let mut mapper = MapperConfig { volume_edge_m: 2.56, time_limit_ms: f64::INFINITY, ..MapperConfig::default() };
        mapper.preprocess.median_downsample = false;
        mapper.saliency.fixation_radius_m = f64::INFINITY;
        // More, smaller cells than J's Vg = 8: most seeds on the cluttered desk fail J's coverage test.
        mapper.seeds.cells_per_side = 16;
        mapper.seeds.per_cell = 2;
        mapper.seeds.max_seeds = 256;
        let calibration = calibrate_dataset(dataset, &CalibrationConfig::default()).unwrap();
        let rotation = calibration.camera_from_imu.to_rotation_matrix();
        mapper.acquire.camera_from_imu = std::array::from_fn(|r| std::array::from_fn(|c| rotation[(r, c)]));
        Pipeline::new(PipelineConfig::default(), tracker, mapper, dataset.intrinsics).unwrap()
    }

    /// Feeds the accelerometer samples up to `until` (as a driver would, in stamp order).
    fn feed_imu(pipeline: &mut Pipeline, dataset: &Dataset, next: &mut usize, until: f64) {
        while let Some(sample) = dataset.accelerometer.get(*next).filter(|s| s.timestamp <= until) {
            // The TUM log has a few repeated stamps: those are rejected, which is the point.
            let _ = pipeline.push_imu(sample.timestamp, sample.acceleration_in_imu);
            *next += 1;
        }
    }

    #[test]
    fn tum_sequence_gives_a_gravity_aligned_patch_map() {
        let dataset = Dataset::open(&test_data_dir().join("tum_fr1_xyz")).unwrap();
        let mut pipeline = tum_pipeline(&dataset);
        let mut next_imu = 0;
        let mut outputs = Vec::new();
        for (index, frame) in dataset.frames.iter().enumerate() {
            feed_imu(&mut pipeline, &dataset, &mut next_imu, frame.timestamp + 0.05);
            let depth = dataset.load_depth(index).unwrap();
            let output = pipeline.process(&depth, frame.timestamp).unwrap();
            assert!(!matches!(output.tracking, TrackingStatus::Lost(_)), "frame {index}: {:?}", output.tracking);
            assert!(output.gravity_in_camera.is_some());
            assert!(output.timings.total_ms >= output.timings.icp_ms);
            outputs.push(output);
        }
        let map = pipeline.map();
        eprintln!("{} patches, stats {:?}", map.len(), map.stats());
        assert_eq!(map.frame_id, "map");
        // The cluttered desk seen from 0.5 m above the camera gives few valid foot-size patches (most
        // seeds fail J's coverage test at the edges of the seen area); every patch is horizontal.
        assert!(!map.is_empty());
        assert!(map.patches().iter().any(|p| p.patch.normal().z.abs() > 0.95));
        for mapped in map.patches() {
            let p = mapped.patch.dof();
            assert_eq!(mapped.patch.covariance.shape(), (p, p));
            assert!(mapped.patch.params().iter().all(|v| v.is_finite()));
            assert!(mapped.patch.residual.is_finite() && mapped.patch.residual < 0.01);
            assert!(mapped.first_seen <= mapped.last_seen);
        }
        // The camera looks down at the desk: its optical axis points below the horizon in the map.
        let last = outputs.last().unwrap();
        let forward_in_map = last.map_from_camera.rotation * Vector3::z();
        assert!(forward_in_map.z < -0.3, "{forward_in_map}");
        // Patches lie below the camera.
        let camera_z = last.map_from_camera.translation.vector.z;
        assert!(map.patches().iter().all(|p| p.patch.center.z < camera_z));
        // The birds-eye cloud lies in the same place as the patches.
        let cloud = birds_eye_points_in_map(&last.birds_eye, &last.map_from_birds_eye);
        assert!(cloud.len() > 1000);
        let mut heights: Vec<f64> = cloud.iter().map(|p| f64::from(p.z)).collect();
        heights.sort_by(f64::total_cmp);
        let median_z = heights[heights.len() / 2];
        assert!(median_z < camera_z, "{median_z} vs camera {camera_z}");
        // Gravity alignment: the horizontal desk top is a thin layer of constant map z (a tilt of a
        // 10° tilt would spread it over 17 cm across the metre-wide view; the calibrated TUM IMU leaves
        // a few degrees, about 8 cm).
        let on_desk = heights.iter().filter(|z| (*z - median_z).abs() < 0.05).count();
        assert!(on_desk * 2 >= heights.len(), "{on_desk} of {} birds-eye points within 5 cm of the desk", heights.len());
        let named = last.timings.named();
        assert_eq!(named.last().map(|n| n.0), Some("total"));
    }

    /// The robot's view (J 6.3): camera 0.45 m above a floor, pitched down by 0.85 rad, a spherical
    /// rock (radius 8 cm) 0.4 m ahead. Returns the depth and the gravity (down) in the camera frame.
    fn robot_scene(intrinsics: &Intrinsics) -> (DepthImage, Vector3<f64>) {
        let pitch: f64 = 0.85;
        let down = Vector3::new(0.0, pitch.cos(), pitch.sin());
        let forward = Vector3::x().cross(&down).normalize();
        let height = 0.45;
        let rock = down * (height - 0.03) + forward * 0.4;
        let depth = crate::saliency::tests::render(intrinsics, |p| (height - p.dot(&down)).min((p - rock).norm() - 0.08));
        (depth, down)
    }

    /// The robot scene and a pipeline with the node's defaults, without the per-frame time limit
    /// (deterministic under any load).
    fn robot_scene_pipeline() -> (Pipeline, DepthImage, Vector3<f64>) {
        let intrinsics = Intrinsics::primesense_default().scaled(0.5);
        let (depth, down) = robot_scene(&intrinsics);
        let mapper = MapperConfig { time_limit_ms: f64::INFINITY, ..default_mapper_config() };
        let pipeline = Pipeline::new(PipelineConfig::default(), TrackerConfig::default(), mapper, intrinsics).unwrap();
        (pipeline, depth, down)
    }

    #[test]
    fn robot_scene_with_defaults_maps_the_floor_in_front_of_the_feet() {
        let (mut pipeline, depth, down) = robot_scene_pipeline();
        let mut summary = FrameSummary::default();
        let mut last = None;
        for frame in 0..6 {
            let t = frame as f64 / 30.0;
            // Accelerometer at rest measures "up"; camera_from_imu is the identity by default.
            pipeline.push_imu(t - 0.005, -down * 9.81).unwrap();
            let output = pipeline.process(&depth, t).unwrap();
            eprintln!(
                "frame {frame}: {:?} {:?} birds-eye {} map {}",
                output.tracking,
                output.mapped,
                output.birds_eye.depth.valid_count(),
                pipeline.map().len()
            );
            summary.add(&output.mapped);
            last = Some(output);
        }
        let last = last.unwrap();
        assert!((last.gravity_in_camera.unwrap().into_inner() - down).norm() < 1e-9);
        let map = pipeline.map();
        assert!(map.len() >= 8, "{} patches, {summary:?}", map.len());
        let camera_in_map = last.map_from_camera.translation.vector;
        let mut floor = 0;
        for mapped in map.patches() {
            let patch = &mapped.patch;
            // On the floor (0.45 m below the camera) or on the rock (up to 0.16 m above the floor).
            let height_above_floor = patch.center.z - (camera_in_map.z - 0.45);
            assert!((-0.01..0.17).contains(&height_above_floor), "{height_above_floor}");
            if height_above_floor.abs() < 0.005 {
                assert!(patch.normal().z.abs() > 0.99, "{:?}", patch.normal());
                floor += 1;
            }
            assert_eq!(patch.covariance.shape(), (patch.dof(), patch.dof()));
        }
        assert!(floor >= 5, "{floor} floor patches");
    }

    #[test]
    fn raycasting_only_what_the_mapper_reads_maps_the_same_patches() {
        // The robot scene mapped twice, the birds-eye view raycast whole and only where the mapper
        // reads (the DtFP ball, the patches it re-fits): the same map, from fewer rays. Seeds are
        // fitted in parallel until J eq 19's patch target is reached, so which seeds are kept
        // depends on the threads' timing; on one thread both runs are reproducible, and the maps
        // are matched patch by patch.
        let one_thread = rayon::ThreadPoolBuilder::new().num_threads(1).build().unwrap();
        let run = |region: bool| {
            let (mut pipeline, depth, down) = robot_scene_pipeline();
            pipeline.config.raycast_mapped_region = region;
            let mut raycast = 0;
            for frame in 0..8 {
                let t = frame as f64 / 30.0;
                pipeline.push_imu(t - 0.005, -down * 9.81).unwrap();
                raycast += pipeline.process(&depth, t).unwrap().birds_eye.depth.valid_count();
            }
            let centres: Vec<_> = pipeline.map().patches().iter().map(|m| m.patch.center).collect();
            (centres, raycast)
        };
        let (whole, whole_hits) = one_thread.install(|| run(false));
        let (part, part_hits) = one_thread.install(|| run(true));
        assert!(whole.len() >= 8, "{}", whole.len());
        assert!(whole.len().abs_diff(part.len()) <= whole.len() / 5, "{} vs {} patches", whole.len(), part.len());
        let matched = |a: &[Vector3<f64>], b: &[Vector3<f64>]| a.iter().filter(|p| b.iter().any(|q| (*p - q).norm() < 0.005)).count();
        assert!(matched(&part, &whole) * 4 >= part.len() * 3, "{} of {} patches matched", matched(&part, &whole), part.len());
        assert!(matched(&whole, &part) * 4 >= whole.len() * 3, "{} of {} patches matched", matched(&whole, &part), whole.len());
        assert!(part_hits < whole_hits, "{part_hits} of {whole_hits} birds-eye hits");
    }

    #[test]
    fn frames_before_the_first_imu_sample_are_mapped_again_once_gravity_is_known() {
        let (mut pipeline, depth, down) = robot_scene_pipeline();
        // Depth before any IMU sample (a driver that starts its IMU stream late): camera y is taken as
        // down, so the map frame is tilted by the camera's pitch.
        for frame in 0..3 {
            let output = pipeline.process(&depth, frame as f64 / 30.0).unwrap();
            assert!(output.gravity_in_camera.is_none());
        }
        let tilted = pipeline.process(&depth, 0.1).unwrap().map_from_camera.rotation * down;
        assert!(tilted.z > -0.9, "{tilted:?}");
        // The first frame with gravity starts the volume and the map frame again, gravity-aligned.
        let mut outputs = Vec::new();
        for frame in 4..8 {
            let t = frame as f64 / 30.0;
            pipeline.push_imu(t - 0.005, -down * 9.81).unwrap();
            outputs.push(pipeline.process(&depth, t).unwrap());
        }
        assert_eq!(outputs[0].tracking, TrackingStatus::Initialized);
        assert!(
            outputs[1..].iter().all(|o| o.tracking == TrackingStatus::Tracked),
            "{:?}",
            outputs.iter().map(|o| &o.tracking).collect::<Vec<_>>()
        );
        let last = &outputs[3];
        let down_in_map = last.map_from_camera.rotation * down;
        assert!((down_in_map + Vector3::z()).norm() < 2e-3, "{down_in_map:?}");
        // Every patch is in the aligned map: the floor's are horizontal.
        let camera_in_map = last.map_from_camera.translation.vector;
        let floor: Vec<_> =
            pipeline.map().patches().iter().filter(|m| (m.patch.center.z - (camera_in_map.z - 0.45)).abs() < 0.005).collect();
        assert!(floor.len() >= 5, "{} floor patches of {}", floor.len(), pipeline.map().len());
        assert!(floor.iter().all(|m| m.patch.normal().z.abs() > 0.99));
    }

    #[test]
    fn a_spike_in_the_accelerometer_window_does_not_tilt_gravity() {
        let g = Vector3::new(0.0, 9.81, 0.0);
        assert_eq!(median_per_axis(&[]), None);
        assert_eq!(median_per_axis(&[g, g + Vector3::new(0.2, 0.0, 0.0)]), Some(g + Vector3::new(0.1, 0.0, 0.0)));
        let intrinsics = Intrinsics::primesense_default().scaled(0.5);
        let mut pipeline = Pipeline::new(PipelineConfig::default(), TrackerConfig::default(), default_mapper_config(), intrinsics).unwrap();
        // Eleven readings of gravity (camera y down, the identity mount) around the frame, one of
        // them a 75 m/s² spike: the mean would tilt gravity by about 35°.
        for i in 0..11 {
            let t = 1.0 + (i as f64 - 5.0) * 0.01;
            let reading = if i == 3 { -g + Vector3::new(35.5, 0.0, 66.6) } else { -g };
            pipeline.push_imu(t, reading).unwrap();
        }
        let gravity = pipeline.gravity_at(1.0).unwrap().unwrap();
        assert!((gravity.into_inner() - Vector3::y()).norm() < 1e-9, "{gravity:?}");
    }

    #[test]
    fn bad_input_is_rejected_and_the_pipeline_keeps_working() {
        let intrinsics = Intrinsics::primesense_default().scaled(0.5);
        let (depth, down) = robot_scene(&intrinsics);
        // The node's defaults without the per-frame time limit (a loaded test host must not empty the map).
        let mapper = || MapperConfig { time_limit_ms: f64::INFINITY, ..default_mapper_config() };
        let new = || Pipeline::new(PipelineConfig::default(), TrackerConfig::default(), mapper(), intrinsics).unwrap();
        let mut pipeline = new();
        let t0 = 100.0;
        // No IMU yet: allowed by default (camera y taken as down), refused when configured.
        let strict = PipelineConfig { allow_missing_imu: false, ..PipelineConfig::default() };
        let mut strict = Pipeline::new(strict, TrackerConfig::default(), default_mapper_config(), intrinsics).unwrap();
        assert_eq!(strict.process(&depth, t0).unwrap_err(), PipelineError::NoImu);
        // IMU: out of order, duplicate and garbage samples are refused.
        let g = -down * 9.81;
        pipeline.push_imu(t0 - 0.01, g).unwrap();
        assert!(matches!(pipeline.push_imu(t0 - 0.02, g), Err(PipelineError::ImuStampOrder { .. })));
        assert!(matches!(pipeline.push_imu(t0 - 0.01, g), Err(PipelineError::ImuStampOrder { .. })));
        assert!(matches!(pipeline.push_imu(t0, Vector3::new(f64::NAN, 0.0, 0.0)), Err(PipelineError::BadImu(_))));
        assert!(matches!(pipeline.push_imu(f64::INFINITY, g), Err(PipelineError::BadStamp(_))));
        // IMU gap: the only sample is 1 s away.
        assert!(matches!(pipeline.process(&depth, t0 + 1.0), Err(PipelineError::ImuGap { .. })));
        // All-NaN and all-zero frames are skipped without touching the state.
        let empty = DepthImage::new(depth.width, depth.height, vec![0.0; depth.width * depth.height]).unwrap();
        assert!(matches!(pipeline.process(&empty, t0), Err(PipelineError::TooFewValid { valid: 0, .. })));
        assert!(matches!(pipeline.process(&depth, f64::NAN), Err(PipelineError::BadStamp(_))));
        // Wrong size for the tracker.
        let small = DepthImage::new(4, 4, vec![1.0; 16]).unwrap();
        assert!(matches!(pipeline.process(&small, t0), Err(PipelineError::Tracking(TrackingError::SizeMismatch { .. }))));
        // A good frame goes through; the same stamp again is a duplicate, an older one out of order.
        let first = pipeline.process(&depth, t0).unwrap();
        assert_eq!(first.tracking, TrackingStatus::Initialized);
        assert!(!pipeline.map().is_empty());
        assert!(matches!(pipeline.process(&depth, t0), Err(PipelineError::StampOrder { .. })));
        assert!(matches!(pipeline.process(&depth, t0 - 0.5), Err(PipelineError::StampOrder { .. })));
        pipeline.push_imu(t0 + 0.02, g).unwrap();
        let second = pipeline.process(&depth, t0 + 0.03).unwrap();
        assert_eq!(second.tracking, TrackingStatus::Tracked);
        // Reset: empty map, the stamp order of frames and IMU samples starts over, the volume is
        // re-initialised.
        pipeline.reset();
        assert!(pipeline.map().is_empty());
        assert_eq!(new().map().len(), 0);
        pipeline.push_imu(t0 - 0.01, g).unwrap();
        let again = pipeline.process(&depth, t0).unwrap();
        assert_eq!(again.tracking, TrackingStatus::Initialized);
        // Mismatched volume edges are a configuration error.
        let mapper = MapperConfig { volume_edge_m: 2.0, ..MapperConfig::default() };
        assert!(matches!(
            Pipeline::new(PipelineConfig::default(), TrackerConfig::default(), mapper, intrinsics),
            Err(PipelineError::Config(_))
        ));
    }

    #[test]
    fn a_frame_icp_cannot_align_keeps_the_map_and_the_next_one_relocalises() {
        use rand::{Rng, SeedableRng};
        let intrinsics = Intrinsics::primesense_default().scaled(0.5);
        let (depth, down) = robot_scene(&intrinsics);
        let mapper = MapperConfig { time_limit_ms: f64::INFINITY, ..default_mapper_config() };
        let mut pipeline = Pipeline::new(PipelineConfig::default(), TrackerConfig::default(), mapper, intrinsics).unwrap();
        let g = -down * 9.81;
        let frame = |pipeline: &mut Pipeline, k: usize, depth: &DepthImage| {
            let t = k as f64 / 30.0;
            pipeline.push_imu(t - 0.005, g).unwrap();
            pipeline.process(depth, t)
        };
        for k in 0..3 {
            assert!(frame(&mut pipeline, k, &depth).unwrap().tracking.has_pose());
        }
        let patches = pipeline.map().len();
        assert!(patches > 0);
        // Depth noise all over the image (a jolted, smeared frame): ICP finds no consistent surface.
        let mut rng = rand::rngs::StdRng::seed_from_u64(5);
        let noise =
            DepthImage::new(depth.width, depth.height, (0..depth.depth_m.len()).map(|_| rng.random_range(0.4f32..3.0)).collect()).unwrap();
        let error = frame(&mut pipeline, 3, &noise).unwrap_err();
        assert!(matches!(error, PipelineError::Relocalising { frames_lost: 1, max_lost_frames: 10, .. }), "{error:?}");
        assert!(error.to_string().contains("map kept, relocalising"), "{error}");
        assert_eq!(pipeline.map().len(), patches, "the map is kept");
        assert_eq!(pipeline.last_stamp(), Some(3.0 / 30.0), "the frame was consumed");
        // The next good frame is aligned against the kept model: relocalised, nothing dropped.
        let back = frame(&mut pipeline, 4, &depth).unwrap();
        assert_eq!(back.tracking, TrackingStatus::Relocalised { frames_lost: 1 });
        assert_eq!(back.patches_dropped, 0);
        assert!(pipeline.map().len() >= patches);
        assert_eq!(frame(&mut pipeline, 5, &depth).unwrap().tracking, TrackingStatus::Tracked);
        // More than max_lost_frames failures in a row are a real loss: the map is reset.
        let mut strict = TrackerConfig::default();
        strict.relocalisation.max_lost_frames = 1;
        let mapper = MapperConfig { time_limit_ms: f64::INFINITY, ..default_mapper_config() };
        let mut pipeline = Pipeline::new(PipelineConfig::default(), strict, mapper, intrinsics).unwrap();
        frame(&mut pipeline, 0, &depth).unwrap();
        assert!(!pipeline.map().is_empty());
        assert!(matches!(frame(&mut pipeline, 1, &noise), Err(PipelineError::Relocalising { frames_lost: 1, .. })));
        let lost = frame(&mut pipeline, 2, &noise).unwrap();
        assert!(matches!(lost.tracking, TrackingStatus::Lost(_)), "{:?}", lost.tracking);
        assert!(lost.patches_dropped > 0);
    }

    #[test]
    fn reset_clears_every_piece_of_time_state() {
        let intrinsics = Intrinsics::primesense_default().scaled(0.5);
        let (depth, down) = robot_scene(&intrinsics);
        let mapper = MapperConfig { time_limit_ms: f64::INFINITY, ..default_mapper_config() };
        let mut pipeline = Pipeline::new(PipelineConfig::default(), TrackerConfig::default(), mapper, intrinsics).unwrap();
        let g = -down * 9.81;
        // A frame and an IMU sample stamped 2^31 - 2 s (e.g. a sensor clock gone wrong) are used...
        let far = f64::from(i32::MAX) - 1.0;
        pipeline.push_imu(far, g).unwrap();
        pipeline.process(&depth, far).unwrap();
        assert_eq!(pipeline.last_stamp(), Some(far));
        // ... and every correctly stamped input after them looks out of order.
        let t0 = 1_700_000_000.0;
        assert!(matches!(pipeline.push_imu(t0, g), Err(PipelineError::ImuStampOrder { .. })));
        assert!(matches!(pipeline.process(&depth, t0), Err(PipelineError::StampOrder { .. })));
        // Reset forgets the stamp order of both the frames and the IMU.
        pipeline.reset();
        assert_eq!((pipeline.last_stamp(), pipeline.imu_samples()), (None, 0));
        // The IMU has been heard: without a sample near the stamp the frame waits for one.
        assert!(matches!(pipeline.process(&depth, t0), Err(PipelineError::ImuGap { .. })));
        pipeline.push_imu(t0 - 0.005, g).unwrap();
        assert_eq!(pipeline.process(&depth, t0).unwrap().tracking, TrackingStatus::Initialized);
        pipeline.push_imu(t0 + 0.03, g).unwrap();
        assert_eq!(pipeline.process(&depth, t0 + 0.033).unwrap().tracking, TrackingStatus::Tracked);
    }

    #[test]
    fn stamps_outside_the_window_around_the_node_clock_are_refused() {
        let window = StampWindow::default();
        window.validate().unwrap();
        let now = 1_700_000_000.0;
        window.check("depth", now, now).unwrap();
        window.check("depth", now + 9.5, now).unwrap();
        // Recorded or simulated stamps far behind the clock are accepted by default.
        window.check("depth", 1_305_031_102.0, now).unwrap();
        window.check("IMU", 0.5, now).unwrap();
        let future = window.check("IMU", f64::from(i32::MAX), now).unwrap_err();
        assert!(matches!(future, PipelineError::FutureStamp { input: "IMU", max_future_s, .. } if max_future_s == 10.0), "{future:?}");
        assert!(future.to_string().contains("ahead of the node clock"), "{future}");
        assert!(future.to_string().contains("ros.max_stamp_skew_s.future"), "{future}");
        assert!(matches!(window.check("depth", f64::NAN, now), Err(PipelineError::BadStamp(_))));
        // A bounded past.
        let strict = StampWindow { future: 1.0, past: 3600.0 };
        strict.check("depth", now - 3599.0, now).unwrap();
        let past = strict.check("depth", now - 3601.0, now).unwrap_err();
        assert!(matches!(past, PipelineError::PastStamp { input: "depth", .. }), "{past:?}");
        assert!(matches!(strict.check("depth", now + 1.5, now), Err(PipelineError::FutureStamp { .. })));
        // Nonsense bounds are a configuration error.
        assert!(StampWindow { future: f64::INFINITY, past: 1.0 }.validate().is_err());
        assert!(StampWindow { future: -1.0, past: 1.0 }.validate().is_err());
        assert!(StampWindow { future: 1.0, past: f64::NAN }.validate().is_err());
    }
}

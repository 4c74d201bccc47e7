//! Runs the mapper's tracker (`patchwalk_fusion::tracking`, J 5) over a simulated walk taken every
//! k-th camera frame, with the accelerometer's gravity of each frame and optional dropouts, and
//! measures what the tracker makes of it against the simulator's ground truth.

use std::time::Instant;

use patchwalk_fusion::camera::DepthImage;
use patchwalk_fusion::tracking::{Frame, Tracker, TrackerConfig, TrackingError, TrackingStatus};
use patchwalk_fusion::trajectory::absolute_trajectory_rmse;

use crate::walk::Walk;

/// A frame of the subsampled sequence that does not arrive as rendered.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Dropout {
    /// The n-th frame of the sequence is all zeros (no depth).
    Zeros(usize),
    /// The n-th frame of the sequence never arrives.
    Skipped(usize),
}

/// What to run.
#[derive(Debug, Clone)]
pub struct WalkRun {
    /// Take every `every`-th camera frame.
    pub every: u64,
    /// Frames of the subsampled sequence.
    pub frames: usize,
    pub dropouts: Vec<Dropout>,
    /// Give the tracker the accelerometer's gravity (mean over ± this, s); `None`: no IMU.
    pub gravity_half_window_s: Option<f64>,
}

/// What the tracker made of it.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct WalkResult {
    pub frames: usize,
    /// Mean translation (m) and largest rotation (deg) between consecutive frames of the sequence.
    pub mean_step_m: f64,
    pub max_step_deg: f64,
    /// Frames without a pose: short losses (`Relocalising`) and real losses (`Lost`).
    pub frames_lost: usize,
    /// Real losses: the volume (and the patch map) was reset.
    pub resets: usize,
    /// Short losses ended by relocalising against the kept map.
    pub relocalisations: usize,
    /// ATE (RMSE after rigid alignment, m) over the frames with a pose.
    pub ate_m: Option<f64>,
    /// Median and largest wall time of `Tracker::process` (ms).
    pub median_ms: f64,
    pub max_ms: f64,
    /// Every frame's status, in order (dropped frames left out).
    pub statuses: Vec<TrackingStatus>,
}

/// Tracks `run` over `walk` with `config` (intrinsics of the simulated camera).
pub fn track_walk(walk: &Walk<'_>, config: &TrackerConfig, run: &WalkRun) -> Result<WalkResult, TrackingError> {
    let intrinsics = walk.sim.camera.intrinsics;
    let mut tracker = Tracker::new(config.clone(), intrinsics)?;
    let rate = walk.sim.config.camera.rate_hz;
    let mut result = WalkResult { frames: run.frames, ..WalkResult::default() };
    let (mut estimate, mut reference, mut times) = (Vec::new(), Vec::new(), Vec::new());
    let (mut step_sum, mut steps) = (0.0, 0);
    for n in 0..run.frames {
        let index = n as u64 * run.every;
        if n > 0 {
            let (m, deg) = walk.motion_between(index - run.every, index);
            step_sum += m;
            steps += 1;
            result.max_step_deg = result.max_step_deg.max(deg);
        }
        if run.dropouts.contains(&Dropout::Skipped(n)) {
            continue;
        }
        let rendered = walk.depth_frame(index);
        let depth = if run.dropouts.contains(&Dropout::Zeros(n)) {
            // Zero depth is "no data": NaN, as `DepthImage::new` and `from_u16` make it.
            DepthImage { width: rendered.depth.width, height: rendered.depth.height, depth_m: vec![f32::NAN; rendered.depth.depth_m.len()] }
        } else {
            rendered.depth
        };
        let t = index as f64 / rate;
        let gravity_in_camera = run.gravity_half_window_s.and_then(|half| walk.gravity_in_camera(t, half));
        let started = Instant::now();
        let report = tracker.process(Frame { depth: &depth, gravity_in_camera, external_map_from_camera: None, timestamp: Some(t) })?;
        times.push(started.elapsed().as_secs_f64() * 1e3);
        match &report.status {
            TrackingStatus::Relocalising { .. } => result.frames_lost += 1,
            TrackingStatus::Lost(_) => {
                result.frames_lost += 1;
                result.resets += 1;
            }
            TrackingStatus::Relocalised { .. } => result.relocalisations += 1,
            _ => {}
        }
        if report.status.has_pose() {
            estimate.push(report.map_from_camera);
            reference.push(rendered.world_from_camera);
        }
        result.statuses.push(report.status);
    }
    result.mean_step_m = if steps > 0 { step_sum / steps as f64 } else { 0.0 };
    result.ate_m = absolute_trajectory_rmse(&estimate, &reference);
    times.sort_by(f64::total_cmp);
    result.median_ms = times.get(times.len() / 2).copied().unwrap_or(f64::NAN);
    result.max_ms = times.last().copied().unwrap_or(f64::NAN);
    Ok(result)
}

/// The tracker as J 5.2 describes it, for comparison: ICP from the last pose with KinectFusion's
/// equal weights, no wide level, no IMU tilt, and every failed frame resets the volume.
pub fn j52_as_written(config: &TrackerConfig) -> TrackerConfig {
    let mut config = config.clone();
    config.icp.wide.iterations = 0;
    config.icp.depth_noise_power = 0;
    config.motion_prior.constant_velocity = false;
    config.motion_prior.gravity_tilt = false;
    config.motion_prior.max_tilt_error_deg = 180.0;
    config.relocalisation.max_lost_frames = 0;
    config.relocalisation.retry_within_frame = false;
    config
}

//! `patch_mapper track <dataset> [--out dir]`: runs the moving-volume TSDF fusion + ICP tracking loop
//! (J 5) over a recorded dataset; writes the estimated trajectory (TUM format, `map` frame) and
//! birds-eye pictures (shaded raycast depth of the virtual camera, J 5.1), prints per-stage timings
//! and, with ground truth, the trajectory error.

use std::path::{Path, PathBuf};

use anyhow::Context;
use indicatif::{ProgressBar, ProgressStyle};
use nalgebra::{Quaternion, UnitQuaternion, Vector3};
use patchwalk_fusion::calibration::{calibrate_dataset, dominant_plane, gravity_from_acceleration, CalibrationConfig};
use patchwalk_fusion::dataset::{write_tum_poses, Dataset, StampedPose};
use patchwalk_fusion::fusion::TsdfConfig;
use patchwalk_fusion::raycast::BirdsEyeView;
use patchwalk_fusion::tracking::{Frame, Tracker, TrackerConfig, TrackingStatus};
use patchwalk_fusion::trajectory::{absolute_trajectory_rmse, relative_pose_errors};

/// Where the gravity direction of each frame comes from.
#[derive(clap::ValueEnum, Clone, Copy, Debug, PartialEq)]
pub enum GravitySource {
    /// None: the first camera's y axis is taken as down.
    None,
    /// Downward normal of the first frame's dominant plane (a horizontal floor or desk).
    Plane,
    /// Accelerometer, rotated by `--camera-from-imu` or by a calibration on the dataset itself (J 2.2).
    Imu,
}

/// Arguments of `patch_mapper track`.
#[derive(clap::Args, Debug)]
pub struct TrackArgs {
    /// Dataset: TUM directory, or a directory of depth PNGs with intrinsics JSON.
    pub dataset: PathBuf,
    /// Output directory for `trajectory.txt` and `birds_eye_*.png`.
    #[arg(long, default_value = "track_out")]
    pub out: PathBuf,
    /// Voxel size (m).
    #[arg(long, default_value_t = TsdfConfig::default().voxel_size_m)]
    pub voxel_size: f32,
    /// Volume edge Vs (m).
    #[arg(long, default_value_t = TsdfConfig::default().size_m)]
    pub volume_size: f32,
    /// Frames beyond this depth are not fused (m).
    #[arg(long, default_value_t = TsdfConfig::default().max_depth_m)]
    pub max_depth: f32,
    /// Keep the volume fixed (no remaps).
    #[arg(long)]
    pub fixed_volume: bool,
    /// Gravity source for the volume's y axis.
    #[arg(long, value_enum, default_value_t = GravitySource::Plane)]
    pub gravity: GravitySource,
    /// IMU→camera rotation as "qx qy qz qw" (for `--gravity imu`; calibrated on the dataset if absent).
    #[arg(long)]
    pub camera_from_imu: Option<String>,
    /// Write a birds-eye picture every n frames (0: never).
    #[arg(long, default_value_t = 5)]
    pub birds_eye_every: usize,
    /// Process at most this many frames.
    #[arg(long)]
    pub max_frames: Option<usize>,
    /// Use every n-th frame of the dataset only (larger motion between the frames tracked).
    #[arg(long, default_value_t = 1, value_parser = clap::value_parser!(u64).range(1..))]
    pub every: u64,
    /// YAML file with a full `TrackerConfig` (overrides the flags above).
    #[arg(long)]
    pub config: Option<PathBuf>,
}

pub fn run(args: TrackArgs) -> anyhow::Result<()> {
    let dataset = Dataset::open(&args.dataset).with_context(|| format!("opening {}", args.dataset.display()))?;
    let config = match &args.config {
        Some(path) => {
            let text = std::fs::read_to_string(path).with_context(|| format!("reading {}", path.display()))?;
            serde_yaml_ng::from_str(&text).with_context(|| format!("parsing {}", path.display()))?
        }
        None => {
            let mut config = TrackerConfig {
                tsdf: TsdfConfig {
                    voxel_size_m: args.voxel_size,
                    size_m: args.volume_size,
                    max_depth_m: args.max_depth,
                    ..TsdfConfig::default()
                },
                ..TrackerConfig::default()
            };
            config.moving_volume.enabled = !args.fixed_volume;
            config
        }
    };
    std::fs::create_dir_all(&args.out).with_context(|| format!("creating {}", args.out.display()))?;
    let camera_from_imu = match (args.gravity, &args.camera_from_imu) {
        (GravitySource::Imu, Some(text)) => Some(parse_quaternion(text)?),
        (GravitySource::Imu, None) => {
            let calibration = calibrate_dataset(&dataset, &CalibrationConfig::default()).context("calibrating the IMU")?;
            eprintln!("camera_from_imu calibrated on the dataset: residual RMS {:.2} deg", calibration.rms_residual_deg);
            Some(calibration.camera_from_imu)
        }
        _ => None,
    };
    let mut tracker = Tracker::new(config, dataset.intrinsics)?;
    let every = usize::try_from(args.every).unwrap_or(1).max(1);
    let count = args.max_frames.unwrap_or(usize::MAX).min(dataset.frames.len().div_ceil(every));
    let progress = ProgressBar::new(count as u64);
    progress.set_style(
        ProgressStyle::with_template("{bar:40} {pos}/{len} frames {msg} [{elapsed_precise}<{eta_precise}]")
            .unwrap_or_else(|_| ProgressStyle::default_bar()),
    );
    let mut trajectory = Vec::new();
    let (mut estimate, mut reference) = (Vec::new(), Vec::new());
    let mut timings = Vec::new();
    let (mut lost, mut remaps, mut relocalised, mut coasting) = (0, 0, 0, 0);
    for (index, frame) in dataset.frames.iter().enumerate().step_by(every).take(count) {
        let depth = dataset.load_depth(index)?;
        let gravity_in_camera = match args.gravity {
            GravitySource::None => None,
            GravitySource::Plane if tracker.model().is_none() => {
                dominant_plane(&depth, &dataset.intrinsics, &CalibrationConfig::default()).map(|plane| plane.normal)
            }
            GravitySource::Plane => None,
            GravitySource::Imu => camera_from_imu.and_then(|rotation| {
                let acceleration = dataset.mean_acceleration_near(frame.timestamp, 0.02)?;
                gravity_from_acceleration(&acceleration).map(|g| rotation * g)
            }),
        };
        let report = tracker.process(Frame {
            depth: &depth,
            gravity_in_camera,
            external_map_from_camera: None,
            timestamp: Some(frame.timestamp),
        })?;
        match &report.status {
            TrackingStatus::Lost(reason) => {
                lost += 1;
                progress.println(format!("frame {index}: tracking lost ({reason}); volume reset"));
            }
            TrackingStatus::Relocalising { frames_lost, reason } => {
                coasting += 1;
                progress.println(format!("frame {index}: lost ({reason}), map kept, relocalising ({frames_lost} frames so far)"));
            }
            TrackingStatus::Relocalised { frames_lost } => {
                relocalised += 1;
                progress.println(format!("frame {index}: relocalised against the map after {frames_lost} lost frames"));
            }
            _ => {}
        }
        if let TrackingStatus::Relocalising { .. } = report.status {
            // No pose for this frame (the last good one is kept): not in the trajectory.
            progress.inc(1);
            continue;
        }
        remaps += usize::from(report.remap.is_some());
        let t = report.timings;
        timings.push(t.icp_ms + t.integrate_ms + t.remap_ms + t.raycast_ms);
        trajectory.push(StampedPose { timestamp: frame.timestamp, world_from_camera: report.map_from_camera });
        if let Some(gt) = dataset.groundtruth_near(frame.timestamp, 0.02) {
            estimate.push(report.map_from_camera);
            reference.push(gt.world_from_camera);
        }
        if args.birds_eye_every > 0 && index % args.birds_eye_every == 0 {
            let view = tracker.birds_eye();
            let path = args.out.join(format!("birds_eye_{index:05}.png"));
            write_birds_eye_png(&path, &view)?;
        }
        progress.set_message(format!("{:.1} ms/frame", t.icp_ms + t.integrate_ms + t.remap_ms + t.raycast_ms));
        progress.inc(1);
    }
    progress.finish();
    let path = args.out.join("trajectory.txt");
    write_tum_poses(&path, &trajectory)?;
    timings.sort_by(f64::total_cmp);
    let median = timings.get(timings.len() / 2).copied().unwrap_or(f64::NAN);
    println!(
        "wrote {} ({} poses), {} remaps, {} frames without a pose (short losses), {} relocalisations, {} tracking losses (volume reset)",
        path.display(),
        trajectory.len(),
        remaps,
        coasting,
        relocalised,
        lost
    );
    println!("fusion + tracking: median {median:.1} ms/frame ({:.1} Hz)", 1e3 / median);
    if let Some(ate) = absolute_trajectory_rmse(&estimate, &reference) {
        println!("ATE (RMSE after rigid alignment) {:.2} mm over {} poses", ate * 1e3, estimate.len());
    }
    let rpe = relative_pose_errors(&estimate, &reference);
    if !rpe.is_empty() {
        let n = rpe.len() as f64;
        let t = (rpe.iter().map(|(t, _)| t * t).sum::<f64>() / n).sqrt();
        let r = (rpe.iter().map(|(_, r)| r * r).sum::<f64>() / n).sqrt();
        println!("RPE (consecutive poses) RMS {:.2} mm, {:.3} deg", t * 1e3, r);
    }
    Ok(())
}

fn parse_quaternion(text: &str) -> anyhow::Result<UnitQuaternion<f64>> {
    let values: Vec<f64> = text
        .split(|c: char| c.is_whitespace() || c == ',')
        .filter(|s| !s.is_empty())
        .map(str::parse)
        .collect::<Result<_, _>>()
        .with_context(|| format!("--camera-from-imu {text:?}: expected 4 numbers \"qx qy qz qw\""))?;
    let [x, y, z, w] = values[..] else {
        anyhow::bail!("--camera-from-imu {text:?}: expected 4 numbers \"qx qy qz qw\", got {}", values.len());
    };
    let q = Quaternion::new(w, x, y, z);
    anyhow::ensure!(q.norm() > 1e-9, "--camera-from-imu: zero quaternion");
    Ok(UnitQuaternion::from_quaternion(q))
}

/// Writes the birds-eye view as an RGB PNG: Lambert shading from the normals, tinted by depth.
fn write_birds_eye_png(path: &Path, view: &BirdsEyeView) -> anyhow::Result<()> {
    let (width, height) = (view.depth.width, view.depth.height);
    let finite: Vec<f32> = view.depth.depth_m.iter().copied().filter(|d| d.is_finite()).collect();
    let lo = finite.iter().copied().fold(f32::INFINITY, f32::min);
    let hi = finite.iter().copied().fold(f32::NEG_INFINITY, f32::max);
    let span = (hi - lo).max(1e-3);
    // Light from above-front in the volume frame (y down).
    let light = Vector3::new(0.3f32, -1.0, -0.4).normalize();
    let mut rgb = Vec::with_capacity(width * height * 3);
    for (d, n) in view.depth.depth_m.iter().zip(&view.normals_in_volume) {
        if d.is_finite() && n.x.is_finite() {
            let shade = 0.25 + 0.75 * (-n.dot(&light)).abs();
            let near = 1.0 - (d - lo) / span;
            let colour = [0.55 + 0.45 * near, 0.75, 1.0 - 0.5 * near].map(|c| (255.0 * (c * shade).clamp(0.0, 1.0)) as u8);
            rgb.extend_from_slice(&colour);
        } else {
            rgb.extend_from_slice(&[0, 0, 0]);
        }
    }
    let file = std::fs::File::create(path).with_context(|| format!("creating {}", path.display()))?;
    let mut encoder = png::Encoder::new(std::io::BufWriter::new(file), width as u32, height as u32);
    encoder.set_color(png::ColorType::Rgb);
    encoder.set_depth(png::BitDepth::Eight);
    let mut writer = encoder.write_header()?;
    writer.write_image_data(&rgb)?;
    writer.finish()?;
    Ok(())
}

//! `patch_mapper replay <dataset>`: the node's whole per-frame pipeline (gravity from the IMU, TSDF
//! fusion + ICP, moving volume, birds-eye raycast, patch mapping and tracking) run offline over a
//! recorded dataset or rosbag2 MCAP bag, with the node's configuration (`config/patch_mapper.yaml` +
//! `--param`).
//! What the node would publish, without ROS: the final patch map as JSON lines, every seed's
//! verdict per frame, the trajectory, and birds-eye pictures with the frame's patches (J Fig. 6
//! colours). With ground truth (`groundtruth.txt`, e.g. from `terrain_sim record`, a `--groundtruth`
//! file, or a bag's ground-truth pose topic) the patches are also given in the dataset's world frame,
//! to compare with the scene's footholds, and the trajectory's ATE is measured. `stats.json` holds
//! the throughput, each stage's p50/p99 wall time and the ATE; `timings.csv` each frame's stage times.
//!
//! On a dataset directory the robot-scale configuration adapts to the recording unless `--no-adapt`
//! is given: an accelerometer with the identity `mapper.acquire.camera_from_imu` gets a rotation
//! calibrated on the dataset (J 2.2); when more than half of the first frame's valid depth lies
//! outside the configured moving volume, the volume (`tracker.tsdf.size_m` = `mapper.volume_edge_m`
//! and the camera's nominal place) is fitted to the first frames' depth; the fixation point's
//! `l_d` becomes the birds-eye offset plus the camera height above the ground plane.

use std::io::Write;
use std::path::{Path, PathBuf};
use std::time::Instant;

use anyhow::{Context, Result};
use indicatif::{ProgressBar, ProgressStyle};
use nalgebra::{Isometry3, Unit};
use patchwalk_fusion::camera::{DepthImage, Intrinsics};
use patchwalk_fusion::dataset::{nearest_by_time, read_tum_poses, write_tum_poses, AccelSample, Dataset, StampedPose};
use patchwalk_fusion::trajectory::absolute_trajectory_rmse;
use patchwalk_fusion::volume::{depth_points, initial_volume_from_camera, share_inside, size_volume_to_depth, VolumeSizing};
use patchwalk_mapping::acquire::{gravity_from_accelerometer, gravity_from_ground_plane, ground_plane, organized_cloud};
use patchwalk_mapping::mapper::FrameSummary;
use patchwalk_mapping::pipeline::{birds_eye_points_in_map, Pipeline, PipelineTimings};
use patchwalk_mapping::record::PatchRecord;
use patchwalk_mapping::render::render_patches;
use patchwalk_mapping::rig::RigEstimate;
use patchwalk_spl::transform::transform_patch;
use serde::Serialize;

use super::bag_input::{BagInput, BagTopics};
use crate::ros::diagnostics::quantile;
use crate::ros::PatchMapperConfig;

/// Arguments of `patch_mapper replay`.
#[derive(clap::Args, Debug)]
pub struct ReplayArgs {
    /// Dataset: TUM directory (depth.txt + accelerometer.txt [+ groundtruth.txt]), or a rosbag2 MCAP
    /// bag (a `.mcap` file or a bag directory with metadata.yaml).
    pub dataset: PathBuf,
    /// Depth image topic of a bag (`sensor_msgs/msg/Image`, 16UC1 or 32FC1); default: the node's `ros.depth_topic`.
    #[arg(long)]
    pub depth_topic: Option<String>,
    /// CameraInfo topic of a bag; default: the node's `ros.camera_info_topic`.
    #[arg(long)]
    pub camera_info_topic: Option<String>,
    /// IMU topic of a bag (`sensor_msgs/msg/Imu`); default: the node's `ros.imu_topic`.
    #[arg(long)]
    pub imu_topic: Option<String>,
    /// Ground-truth camera pose topic of a bag (`geometry_msgs/msg/PoseStamped`, or
    /// `tf2_msgs/msg/TFMessage` with the camera frame as child), used when present.
    #[arg(long, default_value = "/groundtruth")]
    pub groundtruth_topic: String,
    /// Ground-truth camera poses (TUM format: `t tx ty tz qx qy qz qw`), instead of the dataset's own.
    #[arg(long)]
    pub groundtruth: Option<PathBuf>,
    /// The node's YAML configuration (config/patch_mapper.yaml); embedded defaults when omitted.
    #[arg(long)]
    pub config: Option<PathBuf>,
    /// Override `dotted.key=value` (YAML value), as for `patch_mapper run`.
    #[arg(short = 'p', long = "param", value_name = "KEY=VALUE")]
    pub params: Vec<String>,
    /// Output directory for patches.jsonl, seeds.jsonl, trajectory.txt, timings.csv, stats.json and pictures.
    #[arg(long, default_value = "replay_out")]
    pub out: PathBuf,
    /// Write a birds-eye picture every n frames (0: only the last frame). These frames raycast the
    /// whole birds-eye view, the others only the part the mapper reads (`pipeline.raycast_mapped_region`):
    /// for timings, use 0.
    #[arg(long, default_value_t = 10)]
    pub picture_every: usize,
    /// Process at most this many frames.
    #[arg(long)]
    pub max_frames: Option<usize>,
    /// Keep the configured volume, IMU rotation and fixation point as they are instead of adapting
    /// them to a dataset (see the module docs).
    #[arg(long)]
    pub no_adapt: bool,
}

/// One line of seeds.jsonl: a seed's patch (map frame) and what validation said.
#[derive(Serialize)]
struct SeedLine {
    frame: usize,
    neighbourhood_points: usize,
    /// Seed point in the map frame.
    seed_in_map: [f64; 3],
    /// Patch centre in the dataset's world frame (with ground truth).
    center_in_world: Option<[f64; 3]>,
    #[serde(flatten)]
    record: PatchRecord,
}

/// One line of patches.jsonl: a patch of the final map.
#[derive(Serialize)]
struct MapLine {
    id: u64,
    first_seen: f64,
    last_seen: f64,
    center_in_world: Option<[f64; 3]>,
    normal_in_world: Option<[f64; 3]>,
    #[serde(flatten)]
    record: PatchRecord,
}

/// stats.json: how fast the replay ran and how well it tracked.
#[derive(Serialize)]
struct Stats {
    input: String,
    frames: usize,
    frames_skipped: usize,
    messages_skipped: usize,
    seconds: f64,
    frames_per_s: f64,
    pipeline_median_ms: f64,
    /// Per pipeline stage (in pipeline order): p50 and p99 of its wall time over the processed frames (ms).
    stage_ms: Vec<StageLatency>,
    ate_m: Option<f64>,
    ate_frames: usize,
    patches: usize,
}

/// One pipeline stage's wall time over a replay (ms, nearest rank).
#[derive(Serialize)]
struct StageLatency {
    stage: &'static str,
    p50_ms: f64,
    p99_ms: f64,
    max_ms: f64,
}

/// p50/p99/max of every stage of `timings` (NaN when there are none).
fn stage_latencies(timings: &[PipelineTimings]) -> Vec<StageLatency> {
    let names = PipelineTimings::default().named().map(|(name, _)| name);
    names
        .iter()
        .enumerate()
        .map(|(i, &stage)| {
            let mut ms: Vec<f64> = timings.iter().map(|t| t.named()[i].1).collect();
            ms.sort_by(f64::total_cmp);
            let rank = |q: f64| quantile(&ms, q).unwrap_or(f64::NAN);
            StageLatency { stage, p50_ms: rank(0.5), p99_ms: rank(0.99), max_ms: rank(1.0) }
        })
        .collect()
}

/// One line per processed frame: its stamp and every stage's wall time (ms), with a header line.
fn timings_csv(trajectory: &[StampedPose], timings: &[PipelineTimings]) -> String {
    let header: Vec<&str> = PipelineTimings::default().named().iter().map(|(name, _)| *name).collect();
    let mut text = format!("timestamp,{}\n", header.join(","));
    for (pose, frame) in trajectory.iter().zip(timings) {
        let ms: Vec<String> = frame.named().iter().map(|(_, ms)| format!("{ms:.3}")).collect();
        text += &format!("{:.6},{}\n", pose.timestamp, ms.join(","));
    }
    text
}

/// The recorded input: a dataset directory or a bag, and what the replay loop needs of it.
enum Input {
    Dataset(Dataset),
    Bag(Box<BagInput>),
}

/// A rosbag2 bag: an `.mcap` file or a directory with `metadata.yaml`.
pub fn is_bag(path: &Path) -> bool {
    (path.is_file() && path.extension().is_some_and(|e| e.eq_ignore_ascii_case("mcap"))) || path.join("metadata.yaml").is_file()
}

/// A topic name as a bag records it: `camera/depth/image_raw` → `/camera/depth/image_raw`.
fn bag_topic(name: &str) -> String {
    if name.starts_with('/') {
        name.to_string()
    } else {
        format!("/{name}")
    }
}

impl Input {
    fn open(args: &ReplayArgs, config: &PatchMapperConfig) -> Result<Self> {
        if !is_bag(&args.dataset) {
            let dataset = Dataset::open(&args.dataset).with_context(|| format!("opening {}", args.dataset.display()))?;
            return Ok(Input::Dataset(dataset));
        }
        // Bags record fully qualified names; the node's relative defaults are those of the root namespace.
        let topics = BagTopics {
            depth: bag_topic(args.depth_topic.as_ref().unwrap_or(&config.ros.depth_topic)),
            camera_info: bag_topic(args.camera_info_topic.as_ref().unwrap_or(&config.ros.camera_info_topic)),
            imu: bag_topic(args.imu_topic.as_ref().unwrap_or(&config.ros.imu_topic)),
            groundtruth: bag_topic(&args.groundtruth_topic),
        };
        let bag = BagInput::open(&args.dataset, topics).with_context(|| format!("reading the bag {}", args.dataset.display()))?;
        Ok(Input::Bag(Box::new(bag)))
    }

    fn intrinsics(&self) -> Intrinsics {
        match self {
            Input::Dataset(d) => d.intrinsics,
            Input::Bag(b) => b.intrinsics,
        }
    }

    fn frame_stamps(&self) -> Vec<f64> {
        match self {
            Input::Dataset(d) => d.frames.iter().map(|f| f.timestamp).collect(),
            Input::Bag(b) => b.frames.iter().map(|f| f.timestamp).collect(),
        }
    }

    fn accelerometer(&self) -> &[AccelSample] {
        match self {
            Input::Dataset(d) => &d.accelerometer,
            Input::Bag(b) => &b.accelerometer,
        }
    }

    fn groundtruth(&self) -> &[StampedPose] {
        match self {
            Input::Dataset(d) => &d.groundtruth,
            Input::Bag(b) => &b.groundtruth,
        }
    }
}

/// Ground-truth pose nearest in time to `timestamp`, if one lies within `max_gap` seconds.
fn groundtruth_near(poses: &[StampedPose], timestamp: f64, max_gap: f64) -> Option<StampedPose> {
    nearest_by_time(poses, timestamp, |pose| pose.timestamp).filter(|pose| (pose.timestamp - timestamp).abs() <= max_gap).copied()
}

/// Largest gap between a frame and its ground-truth pose (TUM's association window).
const GROUNDTRUTH_MAX_GAP_S: f64 = 0.02;

pub fn run(args: ReplayArgs) -> Result<()> {
    let mut config: PatchMapperConfig = patchwalk_ros::params::load_config(args.config.as_deref(), &args.params)?;
    let input = Input::open(&args, &config)?;
    if let (Input::Dataset(dataset), false) = (&input, args.no_adapt) {
        adapt_to_dataset(dataset, &mut config)?;
    }
    let stamps = input.frame_stamps();
    let count = stamps.len().min(args.max_frames.unwrap_or(usize::MAX));
    let groundtruth = match &args.groundtruth {
        Some(path) => read_tum_poses(path).with_context(|| format!("reading ground truth {}", path.display()))?,
        None => input.groundtruth().to_vec(),
    };
    if let Input::Bag(bag) = &input {
        report_bag_errors(bag);
    }
    let started = Instant::now();
    let mut replay = Replay::new(&args, &config, input.intrinsics(), input.accelerometer(), &groundtruth, count)?;
    // Why the bag could not be read to its end: reported after the frames before the damage are written.
    let mut damage = None;
    match &input {
        Input::Dataset(dataset) => {
            for (index, timestamp) in stamps.iter().take(count).enumerate() {
                replay.frame(index, *timestamp, Ok(dataset.load_depth(index)?))?;
            }
        }
        Input::Bag(bag) => {
            // The bag's depth frames are decoded on a second thread while the pipeline runs.
            let streamed = std::thread::scope(|scope| -> Result<Result<(), patchwalk_bag::BagError>> {
                let (sender, receiver) = crossbeam_channel::bounded(2);
                let reader = scope.spawn(move || bag.stream_depth(count, |index, depth| sender.send((index, depth)).is_ok()));
                let mut replayed = Ok(());
                for (index, depth) in receiver.iter() {
                    let timestamp = stamps.get(index).copied().unwrap_or(f64::NAN);
                    replayed = replay.frame(index, timestamp, depth.map_err(|e| e.to_string()));
                    if replayed.is_err() {
                        break;
                    }
                }
                // Dropping the receiver stops the reading thread.
                drop(receiver);
                let streamed = reader.join().map_err(|_| anyhow::anyhow!("the bag reading thread failed"))?;
                replayed.map(|()| streamed)
            })?;
            damage = bag.broken.as_ref().map(ToString::to_string).or_else(|| streamed.err().map(|e| e.to_string()));
        }
    }
    let elapsed = started.elapsed().as_secs_f64();
    let messages_skipped = match &input {
        Input::Bag(bag) => bag.errors.len(),
        Input::Dataset(_) => 0,
    };
    replay.finish(&args, elapsed, messages_skipped)?;
    match damage {
        Some(err) => anyhow::bail!("the bag could not be read to its end (the frames before the damage were replayed): {err}"),
        None => Ok(()),
    }
}

/// Prints the skipped messages of a bag: up to 5 per topic, then a count.
/// Frames whose depth a fitted volume is sized from.
const FIT_FRAMES: usize = 5;

/// The adaptations of the module docs, each reported on stderr.
fn adapt_to_dataset(dataset: &Dataset, config: &mut PatchMapperConfig) -> Result<()> {
    let configured = config.mapper.acquire.camera_from_imu()?;
    if !dataset.accelerometer.is_empty() && configured.matrix() == &nalgebra::Matrix3::identity() {
        if let (Some(rotation), how) = super::dataset_camera_from_imu(dataset, &configured) {
            eprintln!("IMU: {how}");
            config.mapper.acquire.camera_from_imu = std::array::from_fn(|r| std::array::from_fn(|c| rotation[(r, c)]));
        }
    }
    let Some(frame) = dataset.frames.first() else { return Ok(()) };
    let depth = dataset.load_depth(0)?;
    let cloud = organized_cloud(&depth, &dataset.intrinsics)?;
    let gravity = match dataset.acceleration_near(frame.timestamp, config.mapper.acquire.accel_half_window_s) {
        Some(acceleration) => gravity_from_accelerometer(&acceleration, &config.mapper.acquire.camera_from_imu()?).ok(),
        None => gravity_from_ground_plane(&cloud, 0.02, &config.mapper.acquire.plane_prior, 0).ok(),
    };
    let tsdf = &config.tracker.tsdf;
    let (min_depth, max_depth) = (f64::from(tsdf.min_depth_m), f64::from(tsdf.max_depth_m));
    let mut points = depth_points(&depth, &dataset.intrinsics, min_depth, max_depth, 8);
    let edge = f64::from(tsdf.size_m);
    let pose = initial_volume_from_camera(gravity.map(Unit::into_inner), edge, &config.tracker.moving_volume);
    let outside = 1.0 - share_inside(&points, &pose, edge);
    if outside > 0.5 {
        for index in 1..FIT_FRAMES.min(dataset.frames.len()) {
            points.extend(depth_points(&dataset.load_depth(index)?, &dataset.intrinsics, min_depth, max_depth, 8));
        }
        let block = f64::from(tsdf.voxel_size_m) * 8.0;
        if let Some(fit) = size_volume_to_depth(&points, gravity.map(Unit::into_inner), block, &VolumeSizing::default()) {
            eprintln!(
                "volume: {:.0} % of the first frame's valid depth lies outside the {edge:.2} m volume; fitted a {:.2} m volume to the first \
                 frames ({:.0} % inside); --no-adapt or -p tracker.tsdf.size_m=.. -p mapper.volume_edge_m=.. keep a fixed one",
                100.0 * outside,
                fit.edge_m,
                100.0 * fit.inside_share
            );
            config.tracker.tsdf.size_m = fit.edge_m as f32;
            config.mapper.volume_edge_m = fit.edge_m;
            config.tracker.moving_volume.nominal_position_fraction = fit.nominal_position_fraction;
        }
    } else if outside > 0.2 {
        eprintln!("warning: {:.0} % of the first frame's valid depth lies outside the {edge:.2} m volume (-p tracker.tsdf.size_m=.. -p mapper.volume_edge_m=..)", 100.0 * outside);
    }
    if let Some(gravity) = gravity {
        match ground_plane(&cloud, 0.02, &gravity, 15.0, 0)
            .map_err(anyhow::Error::from)
            .and_then(|g| Ok(RigEstimate::new(g.distance_m, &gravity)?))
        {
            Ok(rig) => {
                let down = rig.camera_height_m + config.tracker.birds_eye.offset_above_camera_m;
                eprintln!(
                    "rig: camera {:.2} m above the ground, pitched {:.0}° down; fixation point {down:.2} m below the birds-eye camera",
                    rig.camera_height_m, rig.pitch_deg
                );
                config.mapper.saliency.fixation_down_m = down;
            }
            Err(err) => eprintln!("warning: no camera height from the first frame ({err:#}); the configured fixation point is used"),
        }
    }
    Ok(())
}

fn report_bag_errors(bag: &BagInput) {
    let mut shown: std::collections::BTreeMap<&str, usize> = std::collections::BTreeMap::new();
    for err in &bag.errors {
        let n = shown.entry(err.topic.as_str()).or_default();
        *n += 1;
        if *n <= 5 {
            eprintln!("skipped: {err}");
        }
    }
    for (topic, n) in shown.iter().filter(|(_, n)| **n > 5) {
        eprintln!("skipped: {} more messages of {topic}", n - 5);
    }
}

/// The replay loop's state: the pipeline, the outputs being written, the trajectory.
struct Replay<'a> {
    pipeline: Pipeline,
    accelerometer: &'a [AccelSample],
    groundtruth: &'a [StampedPose],
    half_window_s: f64,
    out: PathBuf,
    picture_every: usize,
    count: usize,
    seeds_path: PathBuf,
    seeds_out: std::io::BufWriter<std::fs::File>,
    bar: ProgressBar,
    next_imu: usize,
    world_from_map: Option<Isometry3<f64>>,
    trajectory: Vec<StampedPose>,
    summary: FrameSummary,
    skipped: usize,
    timings: Vec<PipelineTimings>,
}

impl<'a> Replay<'a> {
    fn new(
        args: &ReplayArgs,
        config: &PatchMapperConfig,
        intrinsics: Intrinsics,
        accelerometer: &'a [AccelSample],
        groundtruth: &'a [StampedPose],
        count: usize,
    ) -> Result<Self> {
        let pipeline = Pipeline::new(config.pipeline.clone(), config.tracker.clone(), config.mapper.clone(), intrinsics)?;
        std::fs::create_dir_all(&args.out).with_context(|| format!("creating {}", args.out.display()))?;
        let seeds_path = args.out.join("seeds.jsonl");
        let seeds_out =
            std::io::BufWriter::new(std::fs::File::create(&seeds_path).with_context(|| format!("creating {}", seeds_path.display()))?);
        let bar = ProgressBar::new(count as u64);
        bar.set_style(
            ProgressStyle::with_template("{bar:40} {pos}/{len} frames {elapsed_precise} {msg}")
                .unwrap_or_else(|_| ProgressStyle::default_bar()),
        );
        Ok(Self {
            pipeline,
            accelerometer,
            groundtruth,
            half_window_s: config.mapper.acquire.accel_half_window_s,
            out: args.out.clone(),
            picture_every: args.picture_every,
            count,
            seeds_path,
            seeds_out,
            bar,
            next_imu: 0,
            world_from_map: None,
            trajectory: Vec::new(),
            summary: FrameSummary::default(),
            skipped: 0,
            timings: Vec::new(),
        })
    }

    /// Runs the pipeline on frame `index` (or counts it skipped when its depth could not be read).
    fn frame(&mut self, index: usize, timestamp: f64, depth: std::result::Result<DepthImage, String>) -> Result<()> {
        // The IMU samples up to the frame stamp (+ the averaging half window), in stamp order, as a driver delivers them.
        let until = timestamp + self.half_window_s;
        while let Some(sample) = self.accelerometer.get(self.next_imu).filter(|s| s.timestamp <= until) {
            if let Err(err) = self.pipeline.push_imu(sample.timestamp, sample.acceleration_in_imu) {
                self.bar.println(format!("IMU sample {} skipped: {err}", self.next_imu));
            }
            self.next_imu += 1;
        }
        // A frame that is drawn shows the whole birds-eye view, not just the part the mapper reads.
        let last = index + 1 == self.count;
        let pictured = last || (self.picture_every > 0 && index % self.picture_every == 0);
        self.pipeline.set_whole_view(pictured);
        let output = match depth.map_err(anyhow::Error::msg).and_then(|d| Ok(self.pipeline.process(&d, timestamp)?)) {
            Ok(output) => output,
            Err(err) => {
                self.bar.println(format!("frame {index} skipped: {err}"));
                self.skipped += 1;
                self.bar.inc(1);
                return Ok(());
            }
        };
        if self.world_from_map.is_none() {
            self.world_from_map = groundtruth_near(self.groundtruth, timestamp, GROUNDTRUTH_MAX_GAP_S)
                .map(|gt| gt.world_from_camera * output.map_from_camera.inverse());
        }
        self.trajectory.push(StampedPose { timestamp, world_from_camera: output.map_from_camera });
        self.summary.add(&output.mapped);
        self.timings.push(output.timings);
        for outcome in &output.seeds {
            let Some(patch) = outcome.patch_in_camera.as_ref().and_then(|p| transform_patch(p, &output.map_from_birds_eye)) else {
                continue;
            };
            let center_in_world = self.world_from_map.map(|w| (w * nalgebra::Point3::from(patch.center)).coords.into());
            let line = SeedLine {
                frame: index,
                neighbourhood_points: outcome.neighbourhood_size,
                seed_in_map: (output.map_from_birds_eye * nalgebra::Point3::from(outcome.seed.point_in_camera)).coords.into(),
                center_in_world,
                record: PatchRecord::with_verdict(patch, &outcome.verdict, outcome.validation.as_ref()),
            };
            serde_json::to_writer(&mut self.seeds_out, &line)?;
            self.seeds_out.write_all(b"\n")?;
        }
        if pictured {
            let path = self.out.join(format!("birds_eye_{index:05}.png"));
            render_patches(&output.birds_eye.depth, &output.birds_eye.intrinsics, &output.seeds).save_png(&path)?;
        }
        if last {
            // The last birds-eye cloud in the map frame, as CSV (x,y,z), readable by `patch_mapper fit`.
            let cloud = birds_eye_points_in_map(&output.birds_eye, &output.map_from_birds_eye);
            let text: String = cloud.iter().map(|p| format!("{},{},{}\n", p.x, p.y, p.z)).collect();
            let path = self.out.join("birds_eye_last_in_map.csv");
            std::fs::write(&path, text).with_context(|| format!("writing {}", path.display()))?;
        }
        // As the node does after publishing: the stage times are those of its depth-to-patches path.
        self.pipeline.prepare_next_frame();
        self.bar.set_message(format!("{} patches in the map", self.pipeline.map().len()));
        self.bar.inc(1);
        Ok(())
    }

    /// The trajectory's ATE against the ground truth (poses matched within the association window).
    fn ate(&self) -> (Option<f64>, usize) {
        let (estimate, reference): (Vec<_>, Vec<_>) = self
            .trajectory
            .iter()
            .filter_map(|pose| {
                groundtruth_near(self.groundtruth, pose.timestamp, GROUNDTRUTH_MAX_GAP_S)
                    .map(|gt| (pose.world_from_camera, gt.world_from_camera))
            })
            .unzip();
        let ate = if estimate.len() >= 3 { absolute_trajectory_rmse(&estimate, &reference) } else { None };
        (ate, estimate.len())
    }

    fn finish(mut self, args: &ReplayArgs, elapsed_s: f64, messages_skipped: usize) -> Result<()> {
        self.bar.finish_and_clear();
        self.seeds_out.flush()?;
        write_tum_poses(&self.out.join("trajectory.txt"), &self.trajectory)?;
        let timings_path = self.out.join("timings.csv");
        std::fs::write(&timings_path, timings_csv(&self.trajectory, &self.timings))
            .with_context(|| format!("writing {}", timings_path.display()))?;
        let map_path = self.out.join("patches.jsonl");
        let mut map_out =
            std::io::BufWriter::new(std::fs::File::create(&map_path).with_context(|| format!("creating {}", map_path.display()))?);
        for mapped in self.pipeline.map().patches() {
            let line = MapLine {
                id: mapped.id,
                first_seen: mapped.first_seen,
                last_seen: mapped.last_seen,
                center_in_world: self.world_from_map.map(|w| (w * nalgebra::Point3::from(mapped.patch.center)).coords.into()),
                normal_in_world: self.world_from_map.map(|w| (w.rotation * mapped.patch.normal()).into()),
                record: PatchRecord::mapped(mapped.patch.clone()),
            };
            serde_json::to_writer(&mut map_out, &line)?;
            map_out.write_all(b"\n")?;
        }
        map_out.flush()?;
        let stage_ms = stage_latencies(&self.timings);
        let median = stage_ms.iter().find(|s| s.stage == "total").map_or(f64::NAN, |s| s.p50_ms);
        let (count, skipped, summary) = (self.count, self.skipped, &self.summary);
        println!(
            "{count} frames ({skipped} skipped), pipeline median {median:.1} ms/frame; seeds {} fitted {} valid {} | dropped: residual {} coverage {} curvature {} tilt {} edge {} unseen {} | failed {} skipped {}",
            summary.seeds,
            summary.fitted,
            summary.valid,
            summary.residual,
            summary.coverage,
            summary.curvature,
            summary.tilt,
            summary.edge,
            summary.unseen,
            summary.failed,
            summary.skipped
        );
        let stages: Vec<String> = stage_ms.iter().map(|s| format!("{} {:.1}/{:.1}", s.stage, s.p50_ms, s.p99_ms)).collect();
        println!("stage ms p50/p99: {}", stages.join(", "));
        let (ate, ate_frames) = self.ate();
        let frames_per_s = count as f64 / elapsed_s.max(1e-9);
        let ate_text = ate.map_or_else(|| "no ground truth".to_string(), |a| format!("ATE {:.2} mm over {ate_frames} frames", a * 1e3));
        println!("replay: {count} frames in {elapsed_s:.2} s ({frames_per_s:.2} frames/s, reading included); {ate_text}");
        println!("final map: {} patches -> {}; seeds -> {}", self.pipeline.map().len(), map_path.display(), self.seeds_path.display());
        let stats = Stats {
            input: args.dataset.display().to_string(),
            frames: count,
            frames_skipped: skipped,
            messages_skipped,
            seconds: elapsed_s,
            frames_per_s,
            pipeline_median_ms: median,
            stage_ms,
            ate_m: ate,
            ate_frames,
            patches: self.pipeline.map().len(),
        };
        let path = self.out.join("stats.json");
        std::fs::write(&path, serde_json::to_string_pretty(&stats)?).with_context(|| format!("writing {}", path.display()))?;
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use nalgebra::{Vector2, Vector3};
    use patchwalk_mapping::mapper::Verdict;
    use patchwalk_spl::patch::{BoundaryType, Patch, SurfaceType};

    #[test]
    fn seed_and_map_lines_parse_into_the_patch_record() {
        let patch = Patch::new(
            SurfaceType::Plane,
            BoundaryType::Circle,
            vec![0.05],
            Vector2::zeros(),
            Vector3::zeros(),
            Vector3::new(0.0, 0.0, 1.0),
        )
        .unwrap();
        let seed = SeedLine {
            frame: 0,
            neighbourhood_points: 40,
            seed_in_map: [0.0; 3],
            center_in_world: None,
            record: PatchRecord::with_verdict(patch.clone(), &Verdict::Residual, None),
        };
        let map = MapLine {
            id: 7,
            first_seen: 0.0,
            last_seen: 1.0,
            center_in_world: None,
            normal_in_world: None,
            record: PatchRecord::mapped(patch.clone()),
        };
        for (text, valid, verdict) in
            [(serde_json::to_string(&seed).unwrap(), false, "residual"), (serde_json::to_string(&map).unwrap(), true, "valid")]
        {
            let record: PatchRecord = serde_json::from_str(&text).unwrap();
            assert_eq!((record.valid, record.verdict.as_str(), &record.patch), (valid, verdict, &patch), "{text}");
        }
    }
}

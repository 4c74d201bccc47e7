//! ROS 2 wiring of the patch_mapper node (`patch_mapper run`): subscribes the depth camera and IMU
//! (sensor-data QoS), converts messages for the ROS-free [`Pipeline`], publishes PatchArray /
//! MarkerArray / birds-eye PointCloud2 (reliable) and MapperStatus, and serves `/patch_mapper/reset`.
//!
//! Two threads. The ROS loop never blocks: it drains the subscriptions, converts and checks each
//! message, forwards IMU samples, hands depth frames to the worker keep-latest (a frame still waiting
//! when a newer one arrives is dropped and counted as skipped), serves reset, publishes the status and
//! waits for the next input (`patchwalk_ros::wait`). The worker runs the pipeline at the sensor rate
//! and publishes its outputs.
//! Every bad input (wrong encoding or size, NaN/zero depth, missing CameraInfo, IMU gaps, out-of-order
//! or duplicate stamps, stamps far ahead of the node clock) is counted, logged once per period, and
//! skipped — the node keeps running.
//!
//! Time and frames: stamps come from the inputs or the node clock (`use_sim_time`: `/clock`); the
//! tracked pose is published on `/tf` and the IMU mount read from `/tf_static` (see [`tf`]); each depth
//! image is paired with its CameraInfo (see [`camera_info`]).
//!
//! Optional third thread, the foothold stage ([`footholds`]): learned footholds of the mapped frames
//! and the coarse route, off the PatchArray path (the pipeline thread hands it each mapped frame
//! keep-latest after publishing, and takes its predictions for the learned seed orders).

mod camera_info;
pub(crate) mod diagnostics;
mod foothold_msgs;
mod footholds;
mod latest;
mod publish;
mod tf;

use patch_mapper::convert;

/// The longest the loop sleeps without input (a shutdown request is seen within this).
const MAX_WAIT: Duration = Duration::from_millis(100);

use std::collections::VecDeque;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

use anyhow::Context as _;
use crossbeam_channel::{Receiver, Sender, TrySendError};
use nalgebra::Vector3;
use patchwalk_ros::wait::Wakeup;
use serde::{Deserialize, Serialize};

use patchwalk_fusion::camera::{DepthImage, Intrinsics};
use patchwalk_fusion::tracking::TrackerConfig;
use patchwalk_fusion::tracking::TrackingStatus;
use patchwalk_mapping::mapper::MapperConfig;
use patchwalk_mapping::pipeline::{birds_eye_points_in_map, default_mapper_config, Pipeline, PipelineConfig, PipelineError, StampWindow};
use patchwalk_msgs::builtin_interfaces::msg::Time;
use patchwalk_msgs::geometry_msgs::msg::PoseStamped;
use patchwalk_msgs::msg::{MapperStatus, PatchArray};
use patchwalk_msgs::sensor_msgs::msg::{CameraInfo, Image, Imu, PointCloud2};
use patchwalk_msgs::std_srvs::srv::{Trigger, TriggerResponse};
use patchwalk_msgs::visualization_msgs::msg::MarkerArray;
use patchwalk_ros::clock::{ClockListener, NodeClock};
use patchwalk_ros::declared::{self as node_params, Declared};
use patchwalk_ros::node::{self, NodeArgs, RateLimitedLog, RosNode, Shutdown};
use patchwalk_ros::param_server::ParameterServer;
use patchwalk_ros::tf::{SharedTf, TfBroadcaster, TfListener};
use ros2_client::Publisher;

/// Arguments of `patch_mapper run`.
#[derive(clap::Args, Debug, Default)]
pub struct RunArgs {
    #[command(flatten)]
    pub node: NodeArgs,
}

/// Top level of `config/patch_mapper.yaml`: the ROS wiring and the pipeline's three sections (each
/// with its own `Default` = the paper's values; `mapper` = [`default_mapper_config`]).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct PatchMapperConfig {
    pub ros: MapperRosParams,
    pub pipeline: PipelineConfig,
    pub tracker: TrackerConfig,
    /// Keys given here are laid over [`default_mapper_config`] (not over J's `MapperConfig::default()`),
    /// so a partial `mapper:` section or a `--param mapper.x=..` keeps the node's other values.
    #[serde(deserialize_with = "mapper_over_node_defaults")]
    pub mapper: MapperConfig,
}

/// Deserialises a (partial) `mapper:` section on top of [`default_mapper_config`]; unknown keys are
/// still rejected by `MapperConfig`'s `deny_unknown_fields`.
fn mapper_over_node_defaults<'de, D: serde::Deserializer<'de>>(deserializer: D) -> Result<MapperConfig, D::Error> {
    use serde::de::Error as _;
    use serde_yaml_ng::Value;
    fn merge(base: &mut Value, over: Value) {
        match (base, over) {
            (Value::Mapping(base), Value::Mapping(over)) => {
                for (key, value) in over {
                    match base.get_mut(&key) {
                        Some(slot) => merge(slot, value),
                        None => {
                            base.insert(key, value);
                        }
                    }
                }
            }
            (slot, value) => *slot = value,
        }
    }
    let given = Value::deserialize(deserializer)?;
    let mut merged = serde_yaml_ng::to_value(default_mapper_config()).map_err(D::Error::custom)?;
    merge(&mut merged, given);
    serde_yaml_ng::from_value(merged).map_err(D::Error::custom)
}

impl Default for PatchMapperConfig {
    fn default() -> Self {
        Self {
            ros: MapperRosParams::default(),
            pipeline: PipelineConfig::default(),
            tracker: TrackerConfig::default(),
            mapper: default_mapper_config(),
        }
    }
}

/// ROS-level parameters of the node (input topics may be remapped here; the output names are the
/// constants below).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct MapperRosParams {
    /// Depth image input (16UC1 mm or 32FC1 m).
    pub depth_topic: String,
    /// Intrinsics of the depth image.
    pub camera_info_topic: String,
    /// IMU input.
    pub imu_topic: String,
    /// Period of /patch_mapper/status in s.
    pub status_period_s: f64,
    /// Minimum time between two identical warnings in s.
    pub log_period_s: f64,
    /// Publish the birds-eye raycast as PointCloud2 on /patch_mapper/birds_eye_cloud.
    pub publish_birds_eye_cloud: bool,
    /// Publish RViz markers on /patch_mapper/markers.
    pub publish_markers: bool,
    /// Depth and IMU stamps farther than this from the node clock are refused where they enter
    /// ([`StampWindow`]: 10 s into the future, any age by default, so bags and simulators work).
    pub max_stamp_skew_s: StampWindow,
    /// Frames and `/tf`: the fixed frame's name, what is published, the IMU mount from TF.
    pub tf: tf::TfParams,
    /// The learned foothold stage (`~/footholds`, off by default).
    pub footholds: footholds::FootholdParams,
    /// The coarse route toward `~/route_goal` (`~/route`, off by default).
    pub route: footholds::RouteParams,
}

impl Default for MapperRosParams {
    fn default() -> Self {
        Self {
            // Relative: they follow the node's namespace (`/camera/depth/image_raw` in the root one).
            depth_topic: "camera/depth/image_raw".into(),
            camera_info_topic: "camera/depth/camera_info".into(),
            imu_topic: "imu/data".into(),
            status_period_s: 0.5,
            log_period_s: 2.0,
            publish_birds_eye_cloud: true,
            publish_markers: true,
            max_stamp_skew_s: StampWindow::default(),
            tf: tf::TfParams::default(),
            footholds: footholds::FootholdParams::default(),
            route: footholds::RouteParams::default(),
        }
    }
}

/// Output topic and service names of the node (the topic table of the README) in the root namespace;
/// the node creates them relative to itself (`~/patches`, see [`RosNode::relative`]).
pub const PATCHES_TOPIC: &str = "/patch_mapper/patches";
pub const MARKERS_TOPIC: &str = "/patch_mapper/markers";
pub const BIRDS_EYE_TOPIC: &str = "/patch_mapper/birds_eye_cloud";
pub const STATUS_TOPIC: &str = "/patch_mapper/status";
pub const RESET_SERVICE: &str = "/patch_mapper/reset";

/// A checked depth frame on its way to the worker.
struct DepthJob {
    /// The Image's `frame_id` (the camera frame in TF).
    frame_id: String,
    depth: DepthImage,
    intrinsics: Intrinsics,
    stamp: Time,
    received: Instant,
    /// The node clock at `received` minus the header stamp (ms): the driver's and DDS's delay.
    age_ms: f64,
}

/// What the ROS loop hands the worker.
enum WorkerInput {
    Imu {
        stamp: f64,
        acceleration_in_imu: Vector3<f64>,
        frame_id: String,
    },
    /// New mapper parameters (a parameter set), from the next frame on.
    Mapper {
        config: Box<MapperConfig>,
        accepted_at: Instant,
    },
}

/// The parameters of the node that change while it runs (the rest are read at start): the loop's
/// periods and stamp window at the next pass, the mapper's at the next frame, except its grid.
pub const PARAMETERS: node_params::ParameterSpec<PatchMapperConfig> = node_params::ParameterSpec {
    runtime: &[
        "ros.status_period_s",
        "ros.log_period_s",
        "ros.max_stamp_skew_s",
        "ros.footholds.threshold",
        "ros.footholds.max_rate_hz",
        "mapper",
    ],
    restart: &["mapper.volume_edge_m", "mapper.seeds.cells_per_side"],
    applied: "at the next frame (ros.*: at the next loop pass; ros.footholds.*: at the next prediction)",
    validate: validate_config,
};

/// What a parameter set must keep true (checked again at start, where a failure is fatal).
fn validate_config(config: &PatchMapperConfig) -> Result<(), String> {
    let ros = &config.ros;
    for (key, value) in [("ros.status_period_s", ros.status_period_s), ("ros.log_period_s", ros.log_period_s)] {
        if Duration::try_from_secs_f64(value).is_err() {
            return Err(format!("{key} = {value} is not a duration"));
        }
    }
    ros.max_stamp_skew_s.validate().map_err(|e| format!("ros.max_stamp_skew_s: {e}"))?;
    config.ros.tf.validate()?;
    footholds::validate(&ros.footholds, &ros.route)?;
    patchwalk_mapping::mapper::check_config(&config.mapper).map_err(|e| format!("mapper: {e}"))
}

/// Status shared by both threads (counters of MapperStatus, last error, timings).
type SharedStatus = Arc<Mutex<MapperStatus>>;

/// How tracking fares, written by the pipeline thread, read for `/diagnostics`.
type SharedTracking = Arc<Mutex<diagnostics::TrackingHealth>>;

fn with_status(status: &SharedStatus, update: impl FnOnce(&mut MapperStatus)) {
    if let Ok(mut status) = status.lock() {
        update(&mut status);
    }
}

/// What the ROS loop knows between messages.
struct State {
    status: SharedStatus,
    camera_info: camera_info::CameraInfoPairing,
    clock: NodeClock,
    jobs: Sender<DepthJob>,
    /// The ROS loop's own end of the job queue, to replace a waiting frame by a newer one.
    stale_jobs: Receiver<DepthJob>,
    imu: Sender<WorkerInput>,
    stamp_window: StampWindow,
}

impl State {
    fn new(
        status: SharedStatus,
        jobs: Sender<DepthJob>,
        stale_jobs: Receiver<DepthJob>,
        imu: Sender<WorkerInput>,
        stamp_window: StampWindow,
        clock: NodeClock,
    ) -> Self {
        Self { status, camera_info: camera_info::CameraInfoPairing::default(), clock, jobs, stale_jobs, imu, stamp_window }
    }

    /// Whether a message stamp is within [`StampWindow`] of the node clock; a refusal is reported once
    /// per period for each input (`key`). Simulated time before the first `/clock` accepts any stamp.
    fn stamp_plausible(&mut self, log: &mut RateLimitedLog, key: &str, input: &'static str, stamp: &Time) -> bool {
        let Some(now_ns) = self.clock.now_ns_if_known() else { return true };
        let now = now_ns as f64 * 1e-9;
        match self.stamp_window.check(input, publish::seconds_from_time(stamp), now) {
            Ok(()) => true,
            Err(e) => {
                self.fail(log, key, format!("{input} message rejected: {e}"));
                false
            }
        }
    }

    fn count(&self, update: impl FnOnce(&mut MapperStatus)) {
        with_status(&self.status, update);
    }

    /// A depth image arrived: stage i (conversion, intrinsics, size check) or a counted rejection;
    /// accepted frames go to the worker, replacing a frame still waiting there.
    fn on_depth(&mut self, msg: &Image, log: &mut RateLimitedLog) {
        let received = Instant::now();
        let taken_s = self.clock.now_s();
        self.count(|s| s.frames_received += 1);
        let depth = match convert::depth_image(msg) {
            Ok(depth) => depth,
            Err(e) => {
                self.count(|s| s.frames_rejected += 1);
                self.fail(log, "depth", format!("depth image rejected: {e}"));
                return;
            }
        };
        let intrinsics = match self.camera_info.pair(&msg.header.stamp, depth.width, depth.height) {
            Ok(intrinsics) => intrinsics,
            Err(e @ camera_info::PairingError::NoCameraInfo) => {
                self.count(|s| s.frames_skipped += 1);
                self.fail(log, "no_camera_info", format!("depth frame skipped: {e}"));
                return;
            }
            Err(e) => {
                self.count(|s| s.frames_rejected += 1);
                self.fail(log, "size", format!("depth frame rejected: {e}"));
                return;
            }
        };
        // An unset stamp (0) means "now" (publishers that do not stamp their images).
        let stamp = if msg.header.stamp.sec == 0 && msg.header.stamp.nanosec == 0 { self.clock.now() } else { msg.header.stamp.clone() };
        if !self.stamp_plausible(log, "depth_stamp", "depth", &stamp) {
            self.count(|s| s.frames_rejected += 1);
            return;
        }
        let age_ms = (taken_s - publish::seconds_from_time(&stamp)) * 1e3;
        let job = DepthJob { frame_id: msg.header.frame_id.clone(), depth, intrinsics, stamp, received, age_ms };
        if let Err(TrySendError::Full(job)) = self.jobs.try_send(job) {
            // Keep-latest: the waiting frame is dropped for the newer one.
            if self.stale_jobs.try_recv().is_ok() {
                self.count(|s| s.frames_skipped += 1);
                log.warn("busy", format_args!("pipeline busy: an older depth frame was dropped for a newer one"));
            }
            let _ = self.jobs.try_send(job);
        }
    }

    fn on_camera_info(&mut self, msg: &CameraInfo, log: &mut RateLimitedLog) {
        self.count(|s| s.camera_infos_received += 1);
        match convert::intrinsics(msg) {
            Ok(intrinsics) => self.camera_info.push(&msg.header.stamp, intrinsics),
            Err(e) => self.fail(log, "camera_info", format!("CameraInfo rejected: {e}")),
        }
    }

    fn on_imu(&mut self, msg: &Imu, log: &mut RateLimitedLog) {
        self.count(|s| s.imu_received += 1);
        let stamp = if msg.header.stamp.sec == 0 && msg.header.stamp.nanosec == 0 { self.clock.now() } else { msg.header.stamp.clone() };
        let acceleration_in_imu = match convert::imu_acceleration(msg) {
            Ok(acceleration) => acceleration,
            Err(e) => {
                self.fail(log, "imu", format!("IMU sample rejected: {e}"));
                return;
            }
        };
        if !self.stamp_plausible(log, "imu_stamp", "IMU", &stamp) {
            return;
        }
        let frame_id = msg.header.frame_id.clone();
        let _ = self.imu.send(WorkerInput::Imu { stamp: publish::seconds_from_time(&stamp), acceleration_in_imu, frame_id });
    }

    fn fail(&mut self, log: &mut RateLimitedLog, key: &str, message: String) {
        log.warn(key, format_args!("{message}"));
        self.count(|s| s.last_error = message);
    }
}

/// Publishers the worker owns.
struct Outputs {
    patches: Publisher<PatchArray>,
    markers: Option<OnDemand<MarkerArray>>,
    birds_eye: Option<OnDemand<PointCloud2>>,
    tf: Option<TfBroadcaster>,
}

/// A publisher whose messages are only built while a subscription is matched, as rclcpp nodes do
/// with `get_subscription_count()`: the markers and the birds-eye cloud cost about 3 ms of the
/// pipeline thread per frame, for RViz only. The ROS loop counts the matches (`refresh`, at each
/// status period), the pipeline thread reads the flag.
struct OnDemand<M: Serialize> {
    publisher: Arc<Publisher<M>>,
    wanted: Arc<AtomicBool>,
}

impl<M: Serialize> OnDemand<M> {
    fn new(publisher: Publisher<M>) -> Self {
        Self { publisher: Arc::new(publisher), wanted: Arc::new(AtomicBool::new(false)) }
    }

    /// The publisher if some subscription is matched.
    fn wanted(&self) -> Option<&Publisher<M>> {
        self.wanted.load(Ordering::Relaxed).then_some(&*self.publisher)
    }

    /// A handle for the ROS loop, which owns the node that counts the matches.
    fn share(&self) -> Self {
        Self { publisher: self.publisher.clone(), wanted: self.wanted.clone() }
    }

    /// Counts the subscriptions matched to the publisher now.
    fn refresh(&self, node: &ros2_client::Node) {
        self.wanted.store(self.publisher.get_subscription_count(node) > 0, Ordering::Relaxed);
    }
}

/// The worker: builds the pipeline for the current intrinsics, runs it on each frame, publishes.
struct Worker {
    config: PatchMapperConfig,
    pipeline: Option<Pipeline>,
    recent_imu: VecDeque<(f64, Vector3<f64>)>,
    status: SharedStatus,
    tracking: SharedTracking,
    outputs: Outputs,
    log: RateLimitedLog,
    dds_log: RateLimitedLog,
    /// The last reset, to drop the frames that were on their way when it came.
    last_reset: Option<ResetMark>,
    /// Set by the reset service, taken by the worker.
    reset_request: Arc<Mutex<Option<ResetMark>>>,
    /// The TF tree the ROS loop fills (robot tree, IMU mount).
    tf: SharedTf,
    extrinsics: tf::Extrinsics,
    /// The `frame_id` of the latest IMU sample.
    imu_frame: Option<String>,
    /// When the parameter set now waiting for its first frame was accepted.
    parameters_since: Option<Instant>,
    /// The foothold stage, when on: mapped frames go to it, its predictions come back as seed priors.
    footholds: Option<Arc<footholds::FootholdStage>>,
}

/// When `/patch_mapper/reset` was served: a frame taken from DDS before it, or stamped up to
/// [`STALE_FRAME_WINDOW_S`] before it, shows the world before the reset (e.g. before the robot was
/// carried to another rock) and is dropped. Older stamps are a camera clock offset and are kept.
#[derive(Debug, Clone, Copy)]
struct ResetMark {
    at: Instant,
    stamp_s: f64,
}

const STALE_FRAME_WINDOW_S: f64 = 0.5;

impl ResetMark {
    fn now(clock: &NodeClock) -> Self {
        Self { at: Instant::now(), stamp_s: clock.now_s() }
    }

    fn is_stale(&self, received: Instant, stamp_s: f64) -> bool {
        received < self.at || (self.stamp_s - STALE_FRAME_WINDOW_S..self.stamp_s).contains(&stamp_s)
    }
}

impl Worker {
    fn run(mut self, jobs: Receiver<DepthJob>, inputs: Receiver<WorkerInput>, stop: Arc<AtomicBool>) {
        while !stop.load(Ordering::Relaxed) {
            let job = jobs.recv_timeout(Duration::from_millis(50));
            if let Some(mark) = self.reset_request.lock().ok().and_then(|mut r| r.take()) {
                // Every piece of time state goes: the pipeline's stamp order and IMU buffer, and the
                // samples kept for a pipeline built later.
                if let Some(pipeline) = self.pipeline.as_mut() {
                    pipeline.reset();
                }
                self.recent_imu.clear();
                self.last_reset = Some(mark);
                with_status(&self.status, |s| s.patches_in_map = 0);
                if let Ok(mut health) = self.tracking.lock() {
                    health.frames_lost = 0;
                }
            }
            self.take_inputs(&inputs);
            if let Ok(job) = job {
                self.process(job);
            }
        }
    }

    fn take_inputs(&mut self, inputs: &Receiver<WorkerInput>) {
        for input in inputs.try_iter() {
            let (stamp, acceleration_in_imu) = match input {
                WorkerInput::Imu { stamp, acceleration_in_imu, frame_id } => {
                    if self.imu_frame.as_deref() != Some(frame_id.as_str()) {
                        self.imu_frame = Some(frame_id);
                    }
                    (stamp, acceleration_in_imu)
                }
                WorkerInput::Mapper { config, accepted_at } => {
                    self.set_mapper_config(*config, accepted_at);
                    continue;
                }
            };
            // Kept for a pipeline built later (first CameraInfo, new intrinsics).
            self.recent_imu.push_back((stamp, acceleration_in_imu));
            while self.recent_imu.front().is_some_and(|(t, _)| *t < stamp - self.config.pipeline.imu_buffer_s) {
                self.recent_imu.pop_front();
            }
            if let Some(pipeline) = self.pipeline.as_mut() {
                if let Err(e) = pipeline.push_imu(stamp, acceleration_in_imu) {
                    self.warn("imu", format!("IMU sample skipped: {e}"));
                }
            }
        }
    }

    /// A parameter set's mapper config: kept for later pipelines and given to the running one.
    fn set_mapper_config(&mut self, config: MapperConfig, accepted_at: Instant) {
        if let Some(pipeline) = self.pipeline.as_mut() {
            if let Err(e) = pipeline.set_mapper_config(config.clone()) {
                self.warn("parameters", format!("mapper parameters not applied: {e}"));
                return;
            }
        }
        self.config.mapper = config;
        self.parameters_since = Some(accepted_at);
    }

    fn process(&mut self, job: DepthJob) {
        let queued_ms = job.received.elapsed().as_secs_f64() * 1e3;
        if self.last_reset.is_some_and(|mark| mark.is_stale(job.received, publish::seconds_from_time(&job.stamp))) {
            with_status(&self.status, |s| s.frames_skipped += 1);
            tracing::debug!("depth frame from before the last reset dropped");
            return;
        }
        if self.pipeline.as_ref().is_none_or(|p| *p.intrinsics() != job.intrinsics) {
            let c = &self.config;
            match Pipeline::new(c.pipeline.clone(), c.tracker.clone(), c.mapper.clone(), job.intrinsics) {
                Ok(mut pipeline) => {
                    for (stamp, acceleration_in_imu) in &self.recent_imu {
                        // Rejected samples were already reported when they arrived.
                        let _ = pipeline.push_imu(*stamp, *acceleration_in_imu);
                    }
                    tracing::info!(width = job.intrinsics.width, height = job.intrinsics.height, "pipeline (re)built for new intrinsics");
                    self.pipeline = Some(pipeline);
                }
                Err(e) => {
                    with_status(&self.status, |s| s.frames_skipped += 1);
                    self.warn("pipeline", format!("depth frame skipped: cannot build the pipeline: {e}"));
                    return;
                }
            }
        }
        let Some(pipeline) = self.pipeline.as_mut() else { return };
        if let Some(priors) = self.footholds.as_ref().filter(|stage| stage.seed_priors).and_then(|stage| stage.take_priors()) {
            pipeline.set_seed_priors(priors);
        }
        match self.extrinsics.camera_from_imu(&self.tf, &job.frame_id, self.imu_frame.as_deref(), Instant::now()) {
            tf::MountChoice::FromTf(camera_from_imu) => pipeline.set_camera_from_imu(&camera_from_imu),
            tf::MountChoice::Config => {
                if let Ok(configured) = self.config.mapper.acquire.camera_from_imu() {
                    pipeline.set_camera_from_imu(&configured);
                }
            }
            tf::MountChoice::Wait => {
                with_status(&self.status, |s| s.frames_skipped += 1);
                self.log.warn("extrinsics_wait", format_args!("depth frame skipped: waiting for the IMU mount on /tf_static"));
                return;
            }
        }
        // The birds-eye cloud shows the whole view; without it the pipeline raycasts what it maps.
        pipeline.set_whole_view(self.outputs.birds_eye.as_ref().is_some_and(|cloud| cloud.wanted().is_some()));
        let output = match pipeline.process(&job.depth, publish::seconds_from_time(&job.stamp)) {
            Ok(output) => output,
            Err(PipelineError::Relocalising { frames_lost, max_lost_frames, reason }) => {
                // A short loss: the map is kept and not published until the camera is found again.
                if let Ok(mut health) = self.tracking.lock() {
                    health.frames_lost = frames_lost as u64;
                    health.max_lost_frames = max_lost_frames as u64;
                    health.last_loss = reason.to_string();
                }
                with_status(&self.status, |s| s.frames_skipped += 1);
                let message = PipelineError::Relocalising { frames_lost, max_lost_frames, reason }.to_string();
                self.warn("relocalising", format!("depth frame skipped: {message}"));
                return;
            }
            Err(e) => {
                with_status(&self.status, |s| s.frames_skipped += 1);
                self.warn("frame", format!("depth frame skipped: {e}"));
                return;
            }
        };
        if output.gravity_in_camera.is_none() {
            self.log.warn(
                "no_imu",
                format_args!("no IMU sample yet: camera y is taken as down; the first sample starts the map again, gravity-aligned"),
            );
        }
        if self.reset_request.lock().is_ok_and(|r| r.is_some()) {
            // A reset came while this frame was processed: its map shows the world before it.
            with_status(&self.status, |s| s.frames_skipped += 1);
            return;
        }
        if let Ok(mut health) = self.tracking.lock() {
            match &output.tracking {
                TrackingStatus::Relocalised { frames_lost } => {
                    health.relocalisations += 1;
                    health.last_relocalised_after = *frames_lost as u64;
                    tracing::info!("tracking relocalised against the map after {frames_lost} lost frames (map kept)");
                }
                TrackingStatus::Lost(reason) => {
                    health.map_resets += 1;
                    health.last_loss = reason.to_string();
                    tracing::warn!("tracking lost: {reason}; the map was reset");
                }
                _ => {}
            }
            health.frames_lost = 0;
        }
        if let Some(accepted_at) = self.parameters_since.take() {
            let ms = accepted_at.elapsed().as_secs_f64() * 1e3;
            tracing::info!("mapper parameters in effect from this frame, {ms:.1} ms after the set was accepted");
        }
        let map = pipeline.map();
        let started = Instant::now();
        let fixed_frame = self.config.ros.tf.fixed_frame.as_str();
        if let Some(broadcaster) = self.outputs.tf.as_mut() {
            let transform = tf::pose_transform(&self.config.ros.tf, &self.tf.lock(), &job.frame_id, &job.stamp, &output.map_from_camera);
            if let Some(transform) = transform {
                broadcaster.send(vec![transform]);
            }
        }
        let mut array = publish::patch_array(map, &output.map_from_camera, &job.stamp);
        array.header.frame_id = fixed_frame.to_string();
        node::publish(&self.outputs.patches, PATCHES_TOPIC, array, &mut self.dds_log);
        let latency_ms = job.received.elapsed().as_secs_f64() * 1e3;
        let patches_out_ms = started.elapsed().as_secs_f64() * 1e3;
        if let Some(markers) = self.outputs.markers.as_ref().and_then(OnDemand::wanted) {
            let mut msg = publish::markers(map, &job.stamp);
            for marker in &mut msg.markers {
                marker.header.frame_id = fixed_frame.to_string();
            }
            node::publish(markers, MARKERS_TOPIC, msg, &mut self.dds_log);
        }
        if let Some(cloud) = self.outputs.birds_eye.as_ref().and_then(OnDemand::wanted) {
            let points = birds_eye_points_in_map(&output.birds_eye, &output.map_from_birds_eye);
            node::publish(cloud, BIRDS_EYE_TOPIC, publish::point_cloud(&points, &job.stamp, fixed_frame), &mut self.dds_log);
        }
        let publish_ms = started.elapsed().as_secs_f64() * 1e3;
        let patches = map.len();
        if let Some(stage) = &self.footholds {
            // After the PatchArray: the stage takes the frame when it is free (keep-latest, never waits).
            let patch_holds = if stage.wants_patch_holds { footholds::patch_holds(map, stage.max_slope_deg) } else { Vec::new() };
            stage.offer(footholds::FootholdFrame {
                depth: job.depth,
                intrinsics: job.intrinsics,
                stamp: job.stamp.clone(),
                fixed_from_camera: output.map_from_camera,
                patch_holds,
            });
        }
        // Work only the next frame needs comes after this frame's outputs.
        pipeline.prepare_next_frame();
        with_status(&self.status, |s| {
            s.frames_processed += 1;
            s.patches_in_map = u32::try_from(patches).unwrap_or(u32::MAX);
            let named = output.timings.named();
            let node_timings = [
                ("depth_age", job.age_ms),
                ("queued", queued_ms),
                ("patches_out", patches_out_ms),
                ("publish", publish_ms),
                (diagnostics::LATENCY_NAME, latency_ms),
            ];
            s.timing_names = named.iter().map(|(n, _)| *n).chain(node_timings.iter().map(|(n, _)| *n)).map(String::from).collect();
            s.timing_ms = named.iter().map(|(_, ms)| *ms).chain(node_timings.iter().map(|(_, ms)| *ms)).collect();
        });
    }

    fn warn(&mut self, key: &str, message: String) {
        self.log.warn(key, format_args!("{message}"));
        with_status(&self.status, |s| s.last_error = message);
    }
}

pub fn run(args: RunArgs) -> anyhow::Result<()> {
    node::init_tracing_with(&args.node.ros.log_levels);
    node::keep_memory_returnable();
    let names = args.node.names("patch_mapper")?;
    let loaded = args.node.load_config::<PatchMapperConfig>(&names)?;
    let clock = NodeClock::new(loaded.use_sim_time);
    let config = loaded.config;
    let mut params = config.ros.clone();
    let network = node::DdsNetwork::resolve(args.node.dds_network)?;
    let shutdown = Shutdown::install()?;
    let declared = Declared::new(&config, loaded.use_sim_time, &PARAMETERS)?;

    let mut ros = RosNode::with_names("patch_mapper", names, network)?;
    let mut depth_sub = ros.subscription::<Image>(&params.depth_topic, node::sensor_data_qos())?;
    let mut info_sub = ros.subscription::<CameraInfo>(&params.camera_info_topic, node::sensor_data_qos())?;
    let mut imu_sub = ros.subscription::<Imu>(&params.imu_topic, node::sensor_data_qos())?;
    let patches_pub = ros.publisher::<PatchArray>(&ros.relative(PATCHES_TOPIC), node::reliable_qos())?;
    let markers_pub = ros.publisher::<MarkerArray>(&ros.relative(MARKERS_TOPIC), node::latest_reliable_qos())?;
    let birds_eye_pub = ros.publisher::<PointCloud2>(&ros.relative(BIRDS_EYE_TOPIC), node::latest_reliable_qos())?;
    let status_pub = ros.publisher::<MapperStatus>(&ros.relative(STATUS_TOPIC), node::reliable_qos())?;
    let mut reset_srv = ros.server::<Trigger>(&ros.relative(RESET_SERVICE))?;
    let diagnostics_pub =
        ros.publisher::<patchwalk_msgs::diagnostic_msgs::msg::DiagnosticArray>(diagnostics::DIAGNOSTICS_TOPIC, node::reliable_qos())?;
    // The foothold stage (learned footholds, the coarse route): its endpoints exist only when it is on.
    footholds::validate(&params.footholds, &params.route).map_err(anyhow::Error::msg)?;
    let stage_parts = if params.footholds.enabled || params.route.enabled {
        let model = if params.footholds.enabled {
            let path = footholds::find_weights(&params.footholds.weights_path)
                .with_context(|| format!("ros.footholds.weights_path: {} not found", params.footholds.weights_path))?;
            let mut model = patchwalk_footholds::model::FootholdModel::load(&path)
                .with_context(|| format!("ros.footholds.weights_path: cannot load {}", path.display()))?;
            model.mirror_average = params.footholds.mirror_average;
            tracing::info!("foothold stage: weights {}", path.display());
            Some(model)
        } else {
            None
        };
        let planner = footholds::route_planner(&params.route).context("ros.route")?;
        let outputs = footholds::StageOutputs {
            footholds: ros.publisher(&ros.relative(footholds::FOOTHOLDS_TOPIC), node::reliable_qos())?,
            markers: if params.footholds.publish_markers {
                Some(ros.publisher(&ros.relative(footholds::FOOTHOLD_MARKERS_TOPIC), node::reliable_qos())?)
            } else {
                None
            },
            scores: ros.publisher(&ros.relative(footholds::FOOTHOLD_SCORES_TOPIC), node::reliable_qos())?,
            route: if params.route.enabled {
                Some((
                    ros.publisher(&ros.relative(footholds::ROUTE_TOPIC), node::reliable_qos())?,
                    ros.publisher(&ros.relative(footholds::ROUTE_MARKERS_TOPIC), node::reliable_qos())?,
                ))
            } else {
                None
            },
        };
        let goal_sub = if params.route.enabled {
            // Best effort: matches reliable (RViz) and best-effort publishers alike.
            Some(ros.subscription::<PoseStamped>(&ros.relative(footholds::ROUTE_GOAL_TOPIC), node::sensor_data_qos())?)
        } else {
            None
        };
        let pool = rayon::ThreadPoolBuilder::new()
            .num_threads(params.footholds.threads)
            .thread_name(|i| format!("footholds-{i}"))
            .build()
            .context("the foothold stage's thread pool")?;
        Some((model, planner, outputs, goal_sub, pool))
    } else {
        None
    };
    let tf_tree = SharedTf::default();
    let mut tf_listener = TfListener::new(&mut ros, tf_tree.clone())?;
    let tf_broadcaster = if params.tf.publish == tf::TfPublish::Off { None } else { Some(TfBroadcaster::new(&mut ros)?) };
    if let Some(broadcaster) = &tf_broadcaster {
        tf_listener.ignore_own(broadcaster);
    }
    let mut clock_listener = ClockListener::new(&mut ros, &clock)?;
    // The loop sleeps until an input is ready or the status is due.
    let mut wakeup = Wakeup::new()?;
    let parameters = ParameterServer::start(&mut ros, declared, Some(wakeup.waker()), clock.clone())?;
    wakeup.watch(&mut depth_sub)?;
    wakeup.watch(&mut info_sub)?;
    wakeup.watch(&mut imu_sub)?;
    wakeup.watch(&mut reset_srv)?;
    tf_listener.watch(&wakeup)?;
    if let Some(listener) = clock_listener.as_mut() {
        wakeup.watch(&mut listener.subscription)?;
    }

    let mut status_period = Duration::try_from_secs_f64(params.status_period_s)
        .with_context(|| format!("ros.status_period_s = {} is not a duration", params.status_period_s))?;
    let log_period = Duration::try_from_secs_f64(params.log_period_s)
        .with_context(|| format!("ros.log_period_s = {} is not a duration", params.log_period_s))?;
    params.max_stamp_skew_s.validate().context("invalid ros.max_stamp_skew_s")?;
    params.tf.validate().map_err(anyhow::Error::msg)?;
    // Check the pipeline sections now, so a bad config fails at start and not at the first frame.
    Pipeline::new(config.pipeline.clone(), config.tracker.clone(), config.mapper.clone(), Intrinsics::primesense_default())
        .context("invalid pipeline/tracker/mapper configuration")?;

    let status: SharedStatus = Arc::default();
    let tracking: SharedTracking = Arc::new(Mutex::new(diagnostics::TrackingHealth {
        max_lost_frames: config.tracker.relocalisation.max_lost_frames as u64,
        ..Default::default()
    }));
    let (job_tx, job_rx) = crossbeam_channel::bounded::<DepthJob>(1);
    let (input_tx, input_rx) = crossbeam_channel::unbounded::<WorkerInput>();
    let reset: Arc<Mutex<Option<ResetMark>>> = Arc::default();
    let stop = Arc::new(AtomicBool::new(false));
    let extrinsics = tf::Extrinsics::new(config.ros.tf.clone());
    let foot_radius_m = config.mapper.foot_radius_m;
    let (stage, stage_thread, mut goal_sub) = match stage_parts {
        Some((model, planner, outputs, goal_sub, pool)) => {
            let stage = Arc::new(footholds::FootholdStage::new(&params.footholds, &params.route));
            let worker = footholds::StageWorker {
                stage: stage.clone(),
                model,
                planner,
                outputs,
                fixed_frame: params.tf.fixed_frame.clone(),
                foot_radius_m,
                pool,
                log: RateLimitedLog::new(log_period),
            };
            let thread = std::thread::Builder::new().name("footholds".into()).spawn(move || worker.run())?;
            (Some(stage), Some(thread), goal_sub)
        }
        None => (None, None, None),
    };
    if let Some(sub) = goal_sub.as_mut() {
        wakeup.watch(sub)?;
    }
    let markers = params.publish_markers.then(|| OnDemand::new(markers_pub));
    let birds_eye = params.publish_birds_eye_cloud.then(|| OnDemand::new(birds_eye_pub));
    let markers_demand = markers.as_ref().map(OnDemand::share);
    let birds_eye_demand = birds_eye.as_ref().map(OnDemand::share);
    let worker = Worker {
        config,
        pipeline: None,
        recent_imu: VecDeque::new(),
        status: status.clone(),
        tracking: tracking.clone(),
        outputs: Outputs { patches: patches_pub, markers, birds_eye, tf: tf_broadcaster },
        log: RateLimitedLog::new(log_period),
        dds_log: RateLimitedLog::new(log_period),
        last_reset: None,
        reset_request: reset.clone(),
        tf: tf_tree.clone(),
        extrinsics,
        imu_frame: None,
        parameters_since: None,
        footholds: stage.clone(),
    };
    // The worker's loop runs on a thread of the pipeline's own pool, so that the parallel parts of
    // each frame (the ICP iterations, the raycasts, the mapper's stages: dozens a frame) are split
    // among the pool's threads from within, instead of each being handed to the pool from outside
    // and waited for (two thread wake-ups per part).
    let pipeline_pool =
        rayon::ThreadPoolBuilder::new().thread_name(|i| format!("pipeline-{i}")).build().context("the pipeline's thread pool")?;
    let worker_thread = {
        let (jobs, stop) = (job_rx.clone(), stop.clone());
        std::thread::Builder::new()
            .name("pipeline".into())
            .spawn(move || pipeline_pool.install(move || worker.run(jobs, input_rx, stop)))?
    };

    // Two logs so the middleware's and the messages' warnings are limited independently.
    let mut dds_log = RateLimitedLog::new(log_period);
    let mut log = RateLimitedLog::new(log_period);
    let mut state = State::new(status.clone(), job_tx, job_rx, input_tx.clone(), params.max_stamp_skew_s, clock.clone());
    let mut next_status = Instant::now();
    let mut diagnostics_window = diagnostics::MapperWindow::default();
    let mut foothold_window = diagnostics::FootholdWindow::default();
    let mut next_diagnostics = Instant::now() + diagnostics::DIAGNOSTICS_PERIOD;
    tracing::info!(
        depth = %ros.resolve_text(&params.depth_topic)?,
        info = %ros.resolve_text(&params.camera_info_topic)?,
        imu = %ros.resolve_text(&params.imu_topic)?,
        "patch_mapper running"
    );

    while !shutdown.requested() {
        // Time and the TF tree first: the inputs below are checked against them.
        if let Some(listener) = clock_listener.as_mut() {
            listener.drain();
        }
        let mut more = tf_listener.drain();
        // Parameter sets: the loop's own at once, the mapper's from the worker's next frame.
        if let Some(update) = parameters.take_update() {
            let new = &update.config.ros;
            status_period = Duration::try_from_secs_f64(new.status_period_s).unwrap_or(status_period);
            next_status = next_status.min(Instant::now() + status_period);
            if let Ok(period) = Duration::try_from_secs_f64(new.log_period_s) {
                (log, dds_log) = (RateLimitedLog::new(period), RateLimitedLog::new(period));
            }
            state.stamp_window = new.max_stamp_skew_s;
            if let Some(stage) = &stage {
                stage.set_settings(footholds::StageSettings { threshold: new.footholds.threshold, max_rate_hz: new.footholds.max_rate_hz });
            }
            if update.changed("mapper") {
                let _ =
                    input_tx.send(WorkerInput::Mapper { config: Box::new(update.config.mapper.clone()), accepted_at: update.accepted_at });
            }
            params = update.config.ros.clone();
            let ms = update.accepted_at.elapsed().as_secs_f64() * 1e3;
            tracing::info!("parameters {} taken by the loop {ms:.2} ms after the set was accepted", update.keys.join(", "));
        }
        more |= node::drain(&info_sub, &params.camera_info_topic, 16, &mut dds_log, |msg, _| state.on_camera_info(&msg, &mut log)) >= 16;
        more |= node::drain(&imu_sub, &params.imu_topic, 256, &mut dds_log, |msg, _| state.on_imu(&msg, &mut log)) >= 256;
        more |= node::drain(&depth_sub, &params.depth_topic, 8, &mut dds_log, |msg, _| state.on_depth(&msg, &mut log)) >= 8;
        if let (Some(sub), Some(stage)) = (goal_sub.as_ref(), stage.as_ref()) {
            node::drain(sub, footholds::ROUTE_GOAL_TOPIC, 8, &mut dds_log, |msg, _| {
                match footholds::goal_in_fixed(&msg, &params.tf.fixed_frame, &tf_tree.lock()) {
                    Ok(goal) => {
                        tracing::info!("route goal ({:.2}, {:.2}) in {}", goal.x, goal.y, params.tf.fixed_frame);
                        stage.set_goal(Some(goal));
                    }
                    Err(e) => {
                        log.warn("route_goal", format_args!("route goal ignored: {e}"));
                    }
                }
            });
        }
        more |= node::serve(&reset_srv, RESET_SERVICE, &mut dds_log, |_| {
            if let Ok(mut mark) = reset.lock() {
                *mark = Some(ResetMark::now(&clock));
            }
            let frames = status.lock().map(|mut s| {
                s.last_error.clear();
                s.frames_processed
            });
            let frames = frames.unwrap_or(0);
            tracing::info!("reset: map cleared after {frames} processed frames");
            TriggerResponse { success: true, message: format!("map cleared ({frames} frames processed so far)") }
        }) >= 64;
        let now = Instant::now();
        if now >= next_status {
            if let Ok(mut s) = status.lock() {
                s.stamp = clock.now();
                node::publish(&status_pub, STATUS_TOPIC, s.clone(), &mut dds_log);
            }
            if let Some(node) = ros.node_mut() {
                markers_demand.iter().for_each(|d| d.refresh(node));
                birds_eye_demand.iter().for_each(|d| d.refresh(node));
            }
            next_status = now + status_period;
        }
        if let Ok(s) = status.lock() {
            diagnostics_window.sample(&s, now);
            if now >= next_diagnostics {
                let health = tracking.lock().map(|t| t.clone()).unwrap_or_default();
                let mut array = diagnostics_window.diagnostics(&s, &health, now, clock.now());
                if let Some(stage) = stage.as_ref().filter(|_| params.footholds.enabled) {
                    array.status.push(foothold_window.status(&stage.health(), now));
                }
                node::publish(&diagnostics_pub, diagnostics::DIAGNOSTICS_TOPIC, array, &mut dds_log);
                next_diagnostics = now + diagnostics::DIAGNOSTICS_PERIOD;
            }
        }
        if worker_thread.is_finished() {
            anyhow::bail!("the pipeline thread ended unexpectedly");
        }
        let timeout = if more {
            Duration::ZERO
        } else {
            next_status.min(next_diagnostics).min(Instant::now() + MAX_WAIT).saturating_duration_since(Instant::now())
        };
        wakeup.wait(timeout);
    }
    stop.store(true, Ordering::Relaxed);
    if let Some(stage) = &stage {
        stage.close();
    }
    if worker_thread.join().is_err() {
        tracing::error!("the pipeline thread panicked");
    }
    if stage_thread.is_some_and(|thread| thread.join().is_err()) {
        tracing::error!("the foothold thread panicked");
    }
    tracing::info!("patch_mapper: shutting down");
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn shipped_config_file_equals_the_embedded_defaults() {
        let path = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("../../../config/patch_mapper.yaml");
        let from_file: PatchMapperConfig = patchwalk_ros::params::load_config(Some(&path), &[]).unwrap();
        assert_eq!(from_file, PatchMapperConfig::default());
        let bad = patchwalk_ros::params::load_config::<PatchMapperConfig>(Some(&path), &["mapper.no_such_key=1".into()]);
        assert!(bad.unwrap_err().to_string().contains("no_such_key"));
        // A partial mapper section keeps the node's birds-eye settings.
        let partial: PatchMapperConfig = patchwalk_ros::params::load_config(None, &["mapper.seeds.cells_per_side=16".into()]).unwrap();
        assert_eq!(partial.mapper.seeds.cells_per_side, 16);
        assert_eq!(partial.mapper.preprocess, default_mapper_config().preprocess);
        assert_eq!(partial.mapper.saliency, default_mapper_config().saliency);
    }

    fn state() -> (State, Receiver<DepthJob>, Receiver<WorkerInput>) {
        let (jobs, job_rx) = crossbeam_channel::bounded(1);
        let (imu, imu_rx) = crossbeam_channel::unbounded();
        (State::new(SharedStatus::default(), jobs, job_rx.clone(), imu, StampWindow::default(), NodeClock::wall()), job_rx, imu_rx)
    }

    #[test]
    fn frames_are_counted_by_outcome_and_the_latest_waits() {
        let mut log = RateLimitedLog::new(Duration::from_secs(3600));
        let (mut state, jobs, _imu) = state();
        let depth =
            Image { encoding: "16UC1".into(), width: 2, height: 1, step: 4, data: vec![0xE8, 0x03, 0xE8, 0x03], ..Default::default() };
        let status = |state: &State| state.status.lock().unwrap().clone();
        state.on_depth(&depth, &mut log);
        assert_eq!((status(&state).frames_received, status(&state).frames_skipped), (1, 1));
        let mut info = CameraInfo { width: 2, height: 1, ..Default::default() };
        info.k = [1.0, 0.0, 0.5, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0];
        state.on_camera_info(&info, &mut log);
        let mut first = depth.clone();
        first.header.stamp = Time { sec: 1, nanosec: 0 };
        state.on_depth(&first, &mut log);
        assert_eq!(jobs.len(), 1);
        // A second frame while the first still waits: the first is dropped (keep-latest).
        let mut second = depth.clone();
        second.header.stamp = Time { sec: 2, nanosec: 0 };
        state.on_depth(&second, &mut log);
        assert_eq!(jobs.len(), 1);
        assert_eq!(jobs.try_recv().unwrap().stamp.sec, 2);
        assert_eq!(status(&state).frames_skipped, 2);
        let bad = Image { encoding: "rgb8".into(), ..depth.clone() };
        state.on_depth(&bad, &mut log);
        assert_eq!(status(&state).frames_rejected, 1);
        assert!(status(&state).last_error.contains("rgb8"));
        let wrong_size = Image { width: 1, step: 2, data: vec![0, 0], ..depth };
        state.on_depth(&wrong_size, &mut log);
        assert_eq!((status(&state).frames_received, status(&state).frames_rejected), (5, 2));
    }

    #[test]
    fn imu_samples_are_forwarded_and_garbage_is_not() {
        let mut log = RateLimitedLog::new(Duration::from_secs(3600));
        let (mut state, _jobs, imu) = state();
        let mut msg = Imu::default();
        msg.header.stamp = Time { sec: 3, nanosec: 500_000_000 };
        msg.linear_acceleration.z = 9.81;
        state.on_imu(&msg, &mut log);
        let WorkerInput::Imu { stamp, acceleration_in_imu, .. } = imu.try_recv().unwrap() else { panic!("expected an IMU sample") };
        assert_eq!((stamp, acceleration_in_imu.z), (3.5, 9.81));
        msg.linear_acceleration.x = f64::NAN;
        state.on_imu(&msg, &mut log);
        assert!(imu.try_recv().is_err());
        assert_eq!(state.status.lock().unwrap().imu_received, 2);
    }

    #[test]
    fn stamps_far_ahead_of_the_node_clock_are_refused_where_they_enter() {
        let mut log = RateLimitedLog::new(Duration::from_secs(3600));
        let (mut state, jobs, imu) = state();
        let far = Time { sec: i32::MAX, nanosec: 0 };
        let mut sample = Imu::default();
        sample.header.stamp = far.clone();
        sample.linear_acceleration.z = 9.81;
        state.on_imu(&sample, &mut log);
        assert!(imu.try_recv().is_err());
        assert!(state.status.lock().unwrap().last_error.contains("ahead of the node clock"));
        let mut info = CameraInfo { width: 2, height: 1, ..Default::default() };
        info.k = [1.0, 0.0, 0.5, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0];
        state.on_camera_info(&info, &mut log);
        let mut depth =
            Image { encoding: "16UC1".into(), width: 2, height: 1, step: 4, data: vec![0xE8, 0x03, 0xE8, 0x03], ..Default::default() };
        depth.header.stamp = Time { sec: i32::MAX - 1, nanosec: 0 };
        state.on_depth(&depth, &mut log);
        assert!(jobs.try_recv().is_err());
        let status = state.status.lock().unwrap().clone();
        assert_eq!((status.frames_received, status.frames_rejected), (1, 1));
        assert!(status.last_error.starts_with("depth message rejected: depth stamp 2147483646"), "{}", status.last_error);
        // Correctly stamped input still goes through.
        depth.header.stamp = node::now_stamp();
        state.on_depth(&depth, &mut log);
        assert_eq!(jobs.len(), 1);
        sample.header.stamp = node::now_stamp();
        state.on_imu(&sample, &mut log);
        assert!(imu.try_recv().is_ok());
    }

    #[test]
    fn the_skew_window_is_measured_against_simulated_time() {
        let mut log = RateLimitedLog::new(Duration::from_secs(3600));
        let (jobs, job_rx) = crossbeam_channel::bounded(1);
        let (imu_tx, imu) = crossbeam_channel::unbounded();
        let clock = NodeClock::sim();
        let mut state = State::new(SharedStatus::default(), jobs, job_rx, imu_tx, StampWindow::default(), clock.clone());
        let mut sample = Imu::default();
        sample.linear_acceleration.z = 9.81;
        // Before the first /clock any stamp goes through (nothing to compare with).
        sample.header.stamp = Time { sec: 50, nanosec: 0 };
        state.on_imu(&sample, &mut log);
        assert!(imu.try_recv().is_ok());
        clock.set_sim_time(&Time { sec: 20, nanosec: 0 });
        sample.header.stamp = Time { sec: 31, nanosec: 0 };
        state.on_imu(&sample, &mut log);
        assert!(imu.try_recv().is_err(), "11 s ahead of simulated time");
        sample.header.stamp = Time { sec: 0, nanosec: 0 };
        state.on_imu(&sample, &mut log);
        let WorkerInput::Imu { stamp, .. } = imu.try_recv().unwrap() else { panic!("expected an IMU sample") };
        assert_eq!(stamp, 20.0, "an unset stamp is the node clock's now");
    }
}

//! ROS 2 wiring of the patch_mapper node (`patch_mapper run`): subscribes the depth camera and IMU
//! (sensor-data QoS), converts messages for the ROS-free library, publishes PatchArray / MarkerArray /
//! birds-eye PointCloud2 / MapperStatus (reliable) and serves `/patch_mapper/reset`.
//!
//! The loop is single-threaded and never blocks on input: drain the subscriptions, serve reset,
//! publish the status every `status_period_s`, sleep `poll_period_ms`. Every malformed message is
//! counted, logged once per period, and skipped — the node keeps running.

mod convert;

use std::time::{Duration, Instant};

use anyhow::Context as _;
use serde::{Deserialize, Serialize};

use patch_mapper::camera::Intrinsics;
use patchwalk_msgs::msg::{MapperStatus, PatchArray};
use patchwalk_msgs::node::{self, NodeArgs, RateLimitedLog, RosNode, Shutdown};
use patchwalk_msgs::sensor_msgs::msg::{CameraInfo, Image, Imu, PointCloud2};
use patchwalk_msgs::std_srvs::srv::{Trigger, TriggerResponse};
use patchwalk_msgs::visualization_msgs::msg::MarkerArray;

/// Arguments of `patch_mapper run`.
#[derive(clap::Args, Debug, Default)]
pub struct RunArgs {
    #[command(flatten)]
    pub node: NodeArgs,
}

/// Top level of `config/patch_mapper.yaml`. Library sections are added here as fields (each with its
/// own `Default` = the paper's values).
#[derive(Debug, Clone, PartialEq, Default, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct PatchMapperConfig {
    pub ros: MapperRosParams,
}

/// ROS-level parameters of the node (names per names.md; topics may be remapped here).
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
    /// Sleep between two polls of the inputs in ms (bounds the added latency).
    pub poll_period_ms: u64,
    /// Minimum time between two identical warnings in s.
    pub log_period_s: f64,
}

impl Default for MapperRosParams {
    fn default() -> Self {
        Self {
            depth_topic: "/camera/depth/image_raw".into(),
            camera_info_topic: "/camera/depth/camera_info".into(),
            imu_topic: "/imu/data".into(),
            status_period_s: 0.5,
            poll_period_ms: 2,
            log_period_s: 2.0,
        }
    }
}

/// Output topic and service names (names.md).
pub const PATCHES_TOPIC: &str = "/patch_mapper/patches";
pub const MARKERS_TOPIC: &str = "/patch_mapper/markers";
pub const BIRDS_EYE_TOPIC: &str = "/patch_mapper/birds_eye_cloud";
pub const STATUS_TOPIC: &str = "/patch_mapper/status";
pub const RESET_SERVICE: &str = "/patch_mapper/reset";

/// What the node knows between messages.
#[derive(Default)]
struct State {
    status: MapperStatus,
    intrinsics: Option<Intrinsics>,
}

impl State {
    /// A depth image arrived: stage i (conversion, intrinsics, size check) or a counted rejection.
    fn on_depth(&mut self, msg: &Image, log: &mut RateLimitedLog) {
        self.status.frames_received += 1;
        let depth = match convert::depth_image(msg) {
            Ok(depth) => depth,
            Err(e) => {
                self.status.frames_rejected += 1;
                self.fail(log, "depth", format!("depth image rejected: {e}"));
                return;
            }
        };
        let Some(intrinsics) = self.intrinsics else {
            self.status.frames_skipped += 1;
            self.fail(log, "no_camera_info", "depth frame skipped: no valid CameraInfo received yet".into());
            return;
        };
        if (depth.width, depth.height) != (intrinsics.width, intrinsics.height) {
            self.status.frames_rejected += 1;
            self.fail(
                log,
                "size",
                format!(
                    "depth image is {}x{} but CameraInfo says {}x{}",
                    depth.width, depth.height, intrinsics.width, intrinsics.height
                ),
            );
            return;
        }
        self.status.frames_processed += 1;
    }

    fn on_camera_info(&mut self, msg: &CameraInfo, log: &mut RateLimitedLog) {
        self.status.camera_infos_received += 1;
        match convert::intrinsics(msg) {
            Ok(intrinsics) => self.intrinsics = Some(intrinsics),
            Err(e) => self.fail(log, "camera_info", format!("CameraInfo rejected: {e}")),
        }
    }

    fn on_imu(&mut self, _msg: &Imu) {
        self.status.imu_received += 1;
    }

    fn reset(&mut self) -> TriggerResponse {
        let frames = self.status.frames_processed;
        self.status.patches_in_map = 0;
        self.status.last_error.clear();
        tracing::info!("reset: map cleared after {frames} processed frames");
        TriggerResponse { success: true, message: format!("map cleared ({frames} frames processed so far)") }
    }

    fn fail(&mut self, log: &mut RateLimitedLog, key: &str, message: String) {
        log.warn(key, format_args!("{message}"));
        self.status.last_error = message;
    }
}

pub fn run(args: RunArgs) -> anyhow::Result<()> {
    node::init_tracing();
    let config: PatchMapperConfig =
        patchwalk_msgs::params::load_config(args.node.config.as_deref(), &args.node.params)?;
    let params = config.ros;
    let network = node::DdsNetwork::resolve(args.node.dds_network)?;
    let shutdown = Shutdown::install()?;

    let mut ros = RosNode::new("patch_mapper", network)?;
    let depth_sub = ros.subscription::<Image>(&params.depth_topic, node::sensor_data_qos())?;
    let info_sub = ros.subscription::<CameraInfo>(&params.camera_info_topic, node::sensor_data_qos())?;
    let imu_sub = ros.subscription::<Imu>(&params.imu_topic, node::sensor_data_qos())?;
    // Outputs of the mapping pipeline (issue 7 publishes on them once the library is connected).
    let _patches_pub = ros.publisher::<PatchArray>(PATCHES_TOPIC, node::reliable_qos())?;
    let _markers_pub = ros.publisher::<MarkerArray>(MARKERS_TOPIC, node::reliable_qos())?;
    let _birds_eye_pub = ros.publisher::<PointCloud2>(BIRDS_EYE_TOPIC, node::reliable_qos())?;
    let status_pub = ros.publisher::<MapperStatus>(STATUS_TOPIC, node::reliable_qos())?;
    let reset_srv = ros.server::<Trigger>(RESET_SERVICE)?;

    let status_period = Duration::try_from_secs_f64(params.status_period_s)
        .with_context(|| format!("ros.status_period_s = {} is not a duration", params.status_period_s))?;
    let log_period = Duration::try_from_secs_f64(params.log_period_s)
        .with_context(|| format!("ros.log_period_s = {} is not a duration", params.log_period_s))?;
    let poll_period = Duration::from_millis(params.poll_period_ms);
    // Two logs so the middleware's and the messages' warnings are limited independently.
    let mut dds_log = RateLimitedLog::new(log_period);
    let mut log = RateLimitedLog::new(log_period);
    let mut state = State::default();
    let mut next_status = Instant::now();
    tracing::info!(depth = %params.depth_topic, info = %params.camera_info_topic, imu = %params.imu_topic, "patch_mapper running");

    while !shutdown.requested() {
        node::drain(&info_sub, &params.camera_info_topic, 16, &mut dds_log, |msg, _| {
            state.on_camera_info(&msg, &mut log)
        });
        node::drain(&imu_sub, &params.imu_topic, 256, &mut dds_log, |msg, _| state.on_imu(&msg));
        node::drain(&depth_sub, &params.depth_topic, 8, &mut dds_log, |msg, _| state.on_depth(&msg, &mut log));
        node::serve(&reset_srv, RESET_SERVICE, &mut dds_log, |_| state.reset());
        let now = Instant::now();
        if now >= next_status {
            state.status.stamp = node::now_stamp();
            node::publish(&status_pub, STATUS_TOPIC, state.status.clone(), &mut dds_log);
            next_status = now + status_period;
        }
        std::thread::sleep(poll_period);
    }
    tracing::info!("patch_mapper: shutting down");
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn shipped_config_file_equals_the_embedded_defaults() {
        let path = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("../../config/patch_mapper.yaml");
        let from_file: PatchMapperConfig = patchwalk_msgs::params::load_config(Some(&path), &[]).unwrap();
        assert_eq!(from_file.ros, MapperRosParams::default());
    }

    #[test]
    fn frames_are_counted_by_outcome() {
        let mut log = RateLimitedLog::new(Duration::from_secs(3600));
        let mut state = State::default();
        let depth = Image {
            encoding: "16UC1".into(),
            width: 2,
            height: 1,
            step: 4,
            data: vec![0xE8, 0x03, 0xE8, 0x03],
            ..Default::default()
        };
        state.on_depth(&depth, &mut log);
        assert_eq!((state.status.frames_received, state.status.frames_skipped), (1, 1));
        let mut info = CameraInfo { width: 2, height: 1, ..Default::default() };
        info.k = [1.0, 0.0, 0.5, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0];
        state.on_camera_info(&info, &mut log);
        state.on_depth(&depth, &mut log);
        assert_eq!(state.status.frames_processed, 1);
        let bad = Image { encoding: "rgb8".into(), ..depth.clone() };
        state.on_depth(&bad, &mut log);
        assert_eq!(state.status.frames_rejected, 1);
        assert!(state.status.last_error.contains("rgb8"));
        let wrong_size = Image { width: 1, step: 2, data: vec![0, 0], ..depth };
        state.on_depth(&wrong_size, &mut log);
        assert_eq!((state.status.frames_received, state.status.frames_rejected), (4, 2));
        assert!(state.reset().success);
        assert!(state.status.last_error.is_empty());
    }
}

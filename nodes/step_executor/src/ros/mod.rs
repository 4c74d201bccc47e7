//! ROS 2 wiring of the step_executor node (`step_executor run`): subscribes the patch map, publishes
//! /joint_states and /step_executor/status, and serves the training/playback services of names.md.
//!
//! The loop is single-threaded and never blocks on input: drain the patch map, serve every service,
//! publish the status every `1 / status_rate_hz`, sleep `poll_period_ms`.
//!
//! Connected so far: the status, arm/disarm, e-stop and the (empty until the library is connected)
//! motion list. Services that need the servo bus or the motion library answer `success = false` with
//! a message saying so; the library wiring (issue 4) replaces [`Executor`]'s handlers.

use std::time::{Duration, Instant};

use anyhow::Context as _;
use serde::{Deserialize, Serialize};

use patchwalk_msgs::msg::{ExecutorStatus, PatchArray};
use patchwalk_msgs::node::{self, NodeArgs, RateLimitedLog, RosNode, Shutdown};
use patchwalk_msgs::sensor_msgs::msg::JointState;
use patchwalk_msgs::srv;
use patchwalk_msgs::std_srvs::srv::{SetBool, SetBoolRequest, SetBoolResponse, Trigger, TriggerResponse};

/// Arguments of `step_executor run`.
#[derive(clap::Args, Debug, Default)]
pub struct RunArgs {
    #[command(flatten)]
    pub node: NodeArgs,
}

/// The part of `config/step_executor.yaml` the ROS layer reads (its `ros:` section). The other
/// sections belong to the library's `StepExecutorConfig`, which checks them (and rejects unknown keys)
/// once it is wired in here.
#[derive(Debug, Clone, PartialEq, Default, Serialize, Deserialize)]
#[serde(default)]
pub struct ExecutorFileView {
    pub ros: ExecutorRosParams,
}

/// ROS-level parameters of the node.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct ExecutorRosParams {
    /// /joint_states rate while idle (during playback every control cycle is published), Hz.
    pub joint_state_rate_hz: f64,
    /// /step_executor/status rate, Hz.
    pub status_rate_hz: f64,
}

impl Default for ExecutorRosParams {
    fn default() -> Self {
        Self { joint_state_rate_hz: 50.0, status_rate_hz: 5.0 }
    }
}

/// Topic and service names (names.md).
pub const PATCHES_TOPIC: &str = "/patch_mapper/patches";
pub const JOINT_STATES_TOPIC: &str = "/joint_states";
pub const STATUS_TOPIC: &str = "/step_executor/status";
pub const SET_TORQUE: &str = "/step_executor/set_torque";
pub const RECORD_KEYFRAME: &str = "/step_executor/record_keyframe";
pub const SELECT_TARGET: &str = "/step_executor/select_target";
pub const SAVE_MOTION: &str = "/step_executor/save_motion";
pub const LIST_MOTIONS: &str = "/step_executor/list_motions";
pub const DELETE_MOTION: &str = "/step_executor/delete_motion";
pub const PLAY_MOTION: &str = "/step_executor/play_motion";
pub const STOP: &str = "/step_executor/stop";
pub const ARM: &str = "/step_executor/arm";

/// Poll period of the loop in ms.
const POLL_PERIOD_MS: u64 = 2;

const NO_BUS: &str = "not available yet: the servo bus is not connected to the ROS node";
const NO_LIBRARY: &str = "not available yet: the motion library is not connected to the ROS node";

/// Node state and the service handlers.
#[derive(Default)]
struct Executor {
    status: ExecutorStatus,
    latest_map: Option<PatchArray>,
    maps_received: u64,
}

impl Executor {
    fn on_patches(&mut self, map: PatchArray) {
        self.maps_received += 1;
        self.latest_map = Some(map);
    }

    fn set_torque(&mut self, request: SetBoolRequest) -> SetBoolResponse {
        failure_bool(format!("set_torque({}): {NO_BUS}", request.data))
    }

    fn record_keyframe(&mut self, _request: srv::RecordKeyframeRequest) -> srv::RecordKeyframeResponse {
        srv::RecordKeyframeResponse { success: false, message: format!("record_keyframe: {NO_BUS}"), ..Default::default() }
    }

    fn select_target(&mut self, _request: srv::SelectTargetRequest) -> srv::SelectTargetResponse {
        let patches = self.latest_map.as_ref().map_or(0, |map| map.patches.len());
        srv::SelectTargetResponse {
            success: false,
            message: format!("select_target: {NO_LIBRARY} (latest patch map: {patches} patches)"),
            ..Default::default()
        }
    }

    fn save_motion(&mut self, request: srv::SaveMotionRequest) -> srv::SaveMotionResponse {
        srv::SaveMotionResponse { success: false, message: format!("save_motion({:?}): {NO_LIBRARY}", request.name) }
    }

    fn list_motions(&mut self, _request: srv::ListMotionsRequest) -> srv::ListMotionsResponse {
        srv::ListMotionsResponse { success: true, message: "0 motions".into(), motions: Vec::new() }
    }

    fn delete_motion(&mut self, request: srv::DeleteMotionRequest) -> srv::DeleteMotionResponse {
        srv::DeleteMotionResponse { success: false, message: format!("no motion named {:?} (library is empty)", request.name) }
    }

    fn play_motion(&mut self, request: srv::PlayMotionRequest) -> srv::PlayMotionResponse {
        srv::PlayMotionResponse { success: false, message: format!("play_motion({:?}): {NO_BUS}", request.name) }
    }

    /// E-stop: always succeeds; disarms and latches `STATE_ESTOPPED` until re-armed.
    fn stop(&mut self) -> TriggerResponse {
        self.status.state = ExecutorStatus::STATE_ESTOPPED;
        self.status.armed = false;
        self.status.current_motion.clear();
        tracing::warn!("e-stop requested");
        TriggerResponse { success: true, message: "stopped; disarmed".into() }
    }

    /// Arm/disarm automatic execution on match; arming clears a latched e-stop.
    fn arm(&mut self, request: SetBoolRequest) -> SetBoolResponse {
        self.status.armed = request.data;
        if request.data && self.status.state == ExecutorStatus::STATE_ESTOPPED {
            self.status.state = ExecutorStatus::STATE_IDLE;
        }
        let message = if request.data { "armed" } else { "disarmed" };
        tracing::info!("{message}");
        SetBoolResponse { success: true, message: message.into() }
    }
}

fn failure_bool(message: String) -> SetBoolResponse {
    SetBoolResponse { success: false, message }
}

fn period(rate_hz: f64, key: &str) -> anyhow::Result<Duration> {
    if !(rate_hz.is_finite() && rate_hz > 0.0) {
        anyhow::bail!("{key} = {rate_hz} must be a positive rate in Hz");
    }
    Duration::try_from_secs_f64(1.0 / rate_hz).with_context(|| format!("{key} = {rate_hz}"))
}

pub fn run(args: RunArgs) -> anyhow::Result<()> {
    node::init_tracing();
    let config: ExecutorFileView = patchwalk_msgs::params::load_config(args.node.config.as_deref(), &args.node.params)?;
    let params = config.ros;
    let status_period = period(params.status_rate_hz, "ros.status_rate_hz")?;
    period(params.joint_state_rate_hz, "ros.joint_state_rate_hz")?;
    let network = node::DdsNetwork::resolve(args.node.dds_network)?;
    let shutdown = Shutdown::install()?;

    let mut ros = RosNode::new("step_executor", network)?;
    let patches_sub = ros.subscription::<PatchArray>(PATCHES_TOPIC, node::reliable_qos())?;
    // Joint states come from the servo bus (issue 4); nothing is published without one.
    let _joint_states_pub = ros.publisher::<JointState>(JOINT_STATES_TOPIC, node::reliable_qos())?;
    let status_pub = ros.publisher::<ExecutorStatus>(STATUS_TOPIC, node::reliable_qos())?;
    let set_torque_srv = ros.server::<SetBool>(SET_TORQUE)?;
    let record_keyframe_srv = ros.server::<srv::RecordKeyframe>(RECORD_KEYFRAME)?;
    let select_target_srv = ros.server::<srv::SelectTarget>(SELECT_TARGET)?;
    let save_motion_srv = ros.server::<srv::SaveMotion>(SAVE_MOTION)?;
    let list_motions_srv = ros.server::<srv::ListMotions>(LIST_MOTIONS)?;
    let delete_motion_srv = ros.server::<srv::DeleteMotion>(DELETE_MOTION)?;
    let play_motion_srv = ros.server::<srv::PlayMotion>(PLAY_MOTION)?;
    let stop_srv = ros.server::<Trigger>(STOP)?;
    let arm_srv = ros.server::<SetBool>(ARM)?;

    let mut log = RateLimitedLog::default();
    let mut executor = Executor::default();
    let mut next_status = Instant::now();
    tracing::info!("step_executor running");

    while !shutdown.requested() {
        node::drain(&patches_sub, PATCHES_TOPIC, 8, &mut log, |map, _| executor.on_patches(map));
        // E-stop first: it must not wait behind other requests.
        node::serve(&stop_srv, STOP, &mut log, |_| executor.stop());
        node::serve(&arm_srv, ARM, &mut log, |r| executor.arm(r));
        node::serve(&set_torque_srv, SET_TORQUE, &mut log, |r| executor.set_torque(r));
        node::serve(&record_keyframe_srv, RECORD_KEYFRAME, &mut log, |r| executor.record_keyframe(r));
        node::serve(&select_target_srv, SELECT_TARGET, &mut log, |r| executor.select_target(r));
        node::serve(&save_motion_srv, SAVE_MOTION, &mut log, |r| executor.save_motion(r));
        node::serve(&list_motions_srv, LIST_MOTIONS, &mut log, |r| executor.list_motions(r));
        node::serve(&delete_motion_srv, DELETE_MOTION, &mut log, |r| executor.delete_motion(r));
        node::serve(&play_motion_srv, PLAY_MOTION, &mut log, |r| executor.play_motion(r));
        let now = Instant::now();
        if now >= next_status {
            executor.status.stamp = node::now_stamp();
            node::publish(&status_pub, STATUS_TOPIC, executor.status.clone(), &mut log);
            next_status = now + status_period;
        }
        std::thread::sleep(Duration::from_millis(POLL_PERIOD_MS));
    }
    tracing::info!(maps_received = executor.maps_received, "step_executor: shutting down");
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn stop_latches_and_arming_clears_it() {
        let mut executor = Executor::default();
        assert!(executor.arm(SetBoolRequest { data: true }).success);
        assert!(executor.status.armed);
        assert!(executor.stop().success);
        assert_eq!(executor.status.state, ExecutorStatus::STATE_ESTOPPED);
        assert!(!executor.status.armed);
        executor.arm(SetBoolRequest { data: true });
        assert_eq!(executor.status.state, ExecutorStatus::STATE_IDLE);
    }

    #[test]
    fn unconnected_services_fail_with_a_reason() {
        let mut executor = Executor::default();
        let response = executor.play_motion(srv::PlayMotionRequest { name: "rock1".into() });
        assert!(!response.success && response.message.contains("not available yet"));
        let response = executor.list_motions(srv::ListMotionsRequest::default());
        assert!(response.success && response.motions.is_empty());
    }

    #[test]
    fn ros_section_is_read_and_other_sections_are_left_to_the_library() {
        let mut file = tempfile::NamedTempFile::new().unwrap();
        std::io::Write::write_all(&mut file, b"bus:\n  baud: 57600\nros:\n  status_rate_hz: 2.0\n").unwrap();
        let view: ExecutorFileView = patchwalk_msgs::params::load_config(Some(file.path()), &[]).unwrap();
        assert_eq!(view.ros.status_rate_hz, 2.0);
        let err = patchwalk_msgs::params::load_config::<ExecutorFileView>(None, &["ros.status_rate=1".into()]);
        assert!(err.unwrap_err().to_string().contains("status_rate"));
        assert!(period(0.0, "x").is_err());
    }
}

//! ROS 2 wiring of the step_executor node (`step_executor run`): subscribes the patch map, publishes
//! /joint_states and /step_executor/status, and serves the training/playback services named below.
//!
//! The loop waits for input (`patchwalk_ros::wait`) instead of polling: on every wake-up it answers
//! the e-stop first, then the other services, hands long work (a training fit, a library save or
//! delete with fsync) to a worker thread (`jobs`) and answers those requests when their job is done,
//! takes the patch map, publishes joint states and the status. Nothing it does takes long, so an
//! e-stop is answered within a pass whatever else was asked.
//!
//! The handlers delegate to the library's [`Runtime`] (motion library, J 6.3 matcher, servo bus
//! thread); this layer converts messages (`convert`). Without a servo bus (port missing) the node
//! still starts: bus services answer `success = false` with the reason, the status carries it too.

mod action;
mod convert;
mod diagnostics;
mod estop;
mod heartbeat;
mod jobs;
mod tf;

use std::sync::Arc;
use std::time::{Duration, Instant};

use anyhow::Context as _;

use patchwalk_msgs::builtin_interfaces::msg::Time;
use patchwalk_msgs::msg::{ExecutorStatus, MotionSummary, PatchArray};
use patchwalk_msgs::sensor_msgs::msg::{JointState, PointCloud2};
use patchwalk_msgs::srv;
use patchwalk_msgs::std_srvs::srv::{SetBool, SetBoolRequest, SetBoolResponse, Trigger, TriggerResponse};
use patchwalk_ros::clock::{ClockListener, NodeClock};
use patchwalk_ros::declared::{Declared, ParameterSpec};
use patchwalk_ros::node::{self, NodeArgs, RateLimitedLog, RosNode, Shutdown};
use patchwalk_ros::param_server::ParameterServer;
use patchwalk_ros::patch_msg;
use patchwalk_ros::tf::{SharedTf, TfListener};
use patchwalk_ros::wait::Wakeup;
use patchwalk_spl::patch::Patch;
use ros2_client::service::RmwRequestId;
use step_executor::runtime::{CommandError, FitJob, LibraryChange, RunState, Runtime};

use action::PlayMotionAction;
use diagnostics::{CycleWindow, Snapshot, DIAGNOSTICS_PERIOD, DIAGNOSTICS_TOPIC};
use estop::EStopTopic;
use heartbeat::{Deadman, HEARTBEAT_TOPIC};
use jobs::{Finished, Job, Jobs};
use patchwalk_msgs::diagnostic_msgs::msg::DiagnosticArray;
use patchwalk_msgs::std_msgs::msg::Empty;

/// Arguments of `step_executor run`.
#[derive(clap::Args, Debug, Default)]
pub struct RunArgs {
    #[command(flatten)]
    pub node: NodeArgs,
}

/// `config/step_executor.yaml`: the library's config (unknown keys rejected naming the key); its
/// `ros:` section holds the ROS-level parameters.
pub type ExecutorFileView = step_executor::config::StepExecutorConfig;

/// Topic and service names in the root namespace (the README's table); the node creates them
/// relative to itself (`~/stop`, `patch_mapper/patches`, see [`RosNode::relative`]).
pub const PATCHES_TOPIC: &str = "/patch_mapper/patches";
/// The mapper's birds-eye cloud (map frame): what `select_target` MODE_FIT_AT_POINT fits.
pub const CLOUD_TOPIC: &str = "/patch_mapper/birds_eye_cloud";
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
pub const RESET_ESTOP: &str = "/step_executor/reset_estop";
/// Fault recovery: Protocol 2.0 REBOOT of the faulted (or named) servos, a lost port reopened.
pub const REBOOT_SERVOS: &str = "/step_executor/reboot_servos";

/// The parameters of the node that change while it runs (the rest are read at start): the matcher's
/// thresholds from the next patch map, the output rates at the next loop pass.
pub const PARAMETERS: ParameterSpec<ExecutorFileView> = ParameterSpec {
    runtime: &["matcher", "ros.status_rate_hz", "ros.joint_state_rate_hz"],
    restart: &[],
    applied: "at the next patch map (ros.*: at the next loop pass)",
    validate: validate_config,
};

fn validate_config(config: &ExecutorFileView) -> Result<(), String> {
    config.validate().map_err(|e| e.to_string())?;
    period(config.ros.status_rate_hz, "ros.status_rate_hz").map_err(|e| e.to_string())?;
    period(config.ros.joint_state_rate_hz, "ros.joint_state_rate_hz").map_err(|e| e.to_string())?;
    Ok(())
}

/// The longest the loop sleeps without input (it also wakes for status, joint states and jobs).
const MAX_WAIT: Duration = Duration::from_millis(100);
/// Requests of one service taken per loop pass (the rest wait for the next pass, so a flood of one
/// service cannot hold up the others).
const REQUESTS_PER_PASS: usize = 64;

/// Node state and the service handlers (delegating to the library's [`Runtime`]).
struct Executor {
    runtime: Runtime,
    maps_received: u64,
    log: RateLimitedLog,
    /// Latest birds-eye cloud, decoded only when a fit is asked for.
    latest_cloud: Option<Arc<PointCloud2>>,
    jobs_pending: JobsPending,
    /// Stops taken in the current loop pass (see [`Executor::reset_estop`]).
    stops_in_pass: usize,
    /// The operator's heartbeat, required to arm (see `heartbeat`).
    deadman: Deadman,
    /// The TF tree (`/tf`, `/tf_static`): patch maps go to base_link through it when it has their frame.
    tf: SharedTf,
    clock: NodeClock,
}

impl Executor {
    fn new(runtime: Runtime, heartbeat_timeout: Duration) -> Self {
        Self {
            runtime,
            maps_received: 0,
            log: RateLimitedLog::default(),
            latest_cloud: None,
            jobs_pending: JobsPending::default(),
            stops_in_pass: 0,
            deadman: Deadman::new(heartbeat_timeout),
            tf: SharedTf::default(),
            clock: NodeClock::wall(),
        }
    }

    /// The deadman after this pass's heartbeats and bus cycles: the armed step ends when the
    /// executor is neither armed nor playing; heartbeats missing for longer than the timeout
    /// disarm and hold.
    fn check_deadman(&mut self, now: Instant) {
        let status = self.runtime.status();
        if self.deadman.engaged() && !status.armed && status.state != RunState::Playing {
            if let Some(late) = self.deadman.end_step(now) {
                tracing::warn!("{late}");
            }
        }
        if let Some(reason) = self.deadman.expired(now) {
            tracing::warn!("{reason}");
            self.runtime.deadman_lost(reason);
        }
    }

    /// A patch map: convert, express in base_link, match (J 6.3), auto-play when armed.
    fn on_patches(&mut self, map: PatchArray) {
        self.maps_received += 1;
        let map_from_camera = match patch_msg::isometry_from_pose(&map.camera_pose) {
            Ok(pose) => pose,
            Err(e) => {
                self.log.warn("camera_pose", format_args!("{PATCHES_TOPIC}: map ignored, camera_pose: {e}"));
                return;
            }
        };
        let mut patches = Vec::with_capacity(map.patches.len());
        for msg in &map.patches {
            match patch_msg::patch_from_msg(msg) {
                Ok(patch) => patches.push(patch),
                Err(e) => {
                    self.log.warn("patch", format_args!("{PATCHES_TOPIC}: patch skipped: {e}"));
                }
            }
        }
        let in_tree = tf::base_from_map(&self.tf.lock(), &map.header.frame_id, &map.header.stamp);
        let result = match in_tree {
            Some(base_from_map) => self.runtime.on_patch_map_in_base(&patches, base_from_map),
            None => self.runtime.on_patch_map(&patches, &map_from_camera),
        };
        match result {
            Ok(report) => match (&report.best, report.near_misses.first()) {
                (Some(best), _) => tracing::debug!(?best, "patch map matched"),
                (None, Some(miss)) => {
                    tracing::debug!("no match; nearest: map patch {} vs trained {}: {}", miss.map_index, miss.trained_index, miss.reason)
                }
                (None, None) => {}
            },
            Err(e) => {
                self.log.warn("match", format_args!("{PATCHES_TOPIC}: {e}"));
            }
        }
    }

    fn status(&self) -> ExecutorStatus {
        let s = self.runtime.status();
        ExecutorStatus {
            stamp: self.clock.now(),
            state: match s.state {
                RunState::Idle => ExecutorStatus::STATE_IDLE,
                RunState::Playing => ExecutorStatus::STATE_PLAYING,
                RunState::HoldingFault => ExecutorStatus::STATE_HOLDING_FAULT,
                RunState::EStopped => ExecutorStatus::STATE_ESTOPPED,
            },
            armed: s.armed,
            torque_enabled: s.torque_enabled,
            current_motion: s.current_motion,
            keyframe_index: s.keyframe_index,
            last_match: s.last_match,
            fault_servo_id: s.fault_servo_id,
            last_fault: s.last_fault,
            library_size: s.library_size,
            recorded_keyframes: s.recorded_keyframes,
        }
    }

    fn set_torque(&mut self, request: SetBoolRequest) -> SetBoolResponse {
        match self.runtime.set_torque(request.data) {
            Ok(message) => SetBoolResponse { success: true, message },
            Err(e) => failure_bool(format!("set_torque({}): {e}", request.data)),
        }
    }

    fn record_keyframe(&mut self, request: srv::RecordKeyframeRequest) -> srv::RecordKeyframeResponse {
        match self.runtime.record_keyframe(request.duration, request.pause) {
            Ok((index, positions)) => {
                let mut fixed = [0.0; 12];
                for (slot, q) in fixed.iter_mut().zip(&positions) {
                    *slot = *q;
                }
                srv::RecordKeyframeResponse {
                    success: true,
                    message: format!("keyframe {index} recorded"),
                    keyframe_index: index as u32,
                    positions: fixed,
                }
            }
            Err(e) => srv::RecordKeyframeResponse { success: false, message: format!("record_keyframe: {e}"), ..Default::default() },
        }
    }

    /// `select_target`: the nearest patch is answered at once; a fit becomes a job.
    fn select_target(&mut self, request: srv::SelectTargetRequest) -> Handled<srv::SelectTargetResponse> {
        let p = &request.point;
        let point = [p.x, p.y, p.z];
        let selected = match request.mode {
            srv::SelectTargetRequest::MODE_NEAREST_POINT => self.runtime.select_nearest(point).map_err(|e| e.to_string()),
            srv::SelectTargetRequest::MODE_FIT_AT_POINT => {
                // The request is checked before the node's state: a bad point is named as such.
                let started = match (self.runtime.fit_job(point, request.radius), &self.latest_cloud, self.jobs_pending.fit) {
                    (Err(e), _, _) => Err(e.to_string()),
                    (Ok(_), _, true) => Err("a fit is in progress; call again when it is answered".to_string()),
                    (Ok(_), None, _) => Err(format!("no birds-eye cloud received on {CLOUD_TOPIC} yet")),
                    (Ok(job), Some(cloud), false) => Ok(Later::Fit(job, Arc::clone(cloud))),
                };
                return match started {
                    Ok(later) => Handled::Later(Box::new(later)),
                    Err(e) => Handled::Answer(select_target_response(Err(e))),
                };
            }
            mode => Err(CommandError::InvalidArgument {
                field: "mode",
                reason: format!("{mode} is unknown (0 = nearest point, 1 = fit at point)"),
            }
            .to_string()),
        };
        Handled::Answer(select_target_response(selected))
    }

    /// `save_motion`: the new library is prepared now and written by a job.
    fn save_motion(&mut self, request: srv::SaveMotionRequest) -> Handled<srv::SaveMotionResponse> {
        let failed = |e: &dyn std::fmt::Display| {
            Handled::Answer(srv::SaveMotionResponse { success: false, message: format!("save_motion({:?}): {e}", request.name) })
        };
        if let Some(busy) = self.jobs_pending.library_busy() {
            return failed(&busy);
        }
        match self.runtime.prepare_save(&request.name) {
            Ok(change) => Handled::Later(Box::new(Later::Write { save: true, name: request.name.clone(), change })),
            Err(e) => failed(&e),
        }
    }

    fn list_motions(&mut self, _request: srv::ListMotionsRequest) -> srv::ListMotionsResponse {
        let motions: Vec<MotionSummary> = self
            .runtime
            .list_motions()
            .into_iter()
            .map(|m| MotionSummary {
                name: m.name,
                surface: m.surface,
                boundary: m.boundary,
                keyframe_count: m.keyframe_count,
                duration: m.duration,
            })
            .collect();
        srv::ListMotionsResponse { success: true, message: format!("{} motions", motions.len()), motions }
    }

    /// `delete_motion`: prepared now, written by a job.
    fn delete_motion(&mut self, request: srv::DeleteMotionRequest) -> Handled<srv::DeleteMotionResponse> {
        let failed = |message: String| Handled::Answer(srv::DeleteMotionResponse { success: false, message });
        if let Some(busy) = self.jobs_pending.library_busy() {
            return failed(format!("delete_motion({:?}): {busy}", request.name));
        }
        match self.runtime.prepare_delete(&request.name) {
            Ok(change) => Handled::Later(Box::new(Later::Write { save: false, name: request.name.clone(), change })),
            Err(e) => failed(format!("delete_motion({:?}): {e}", request.name)),
        }
    }

    /// A finished job: take its result into the runtime and build the answer.
    fn finish(&mut self, finished: Finished) -> FinishedAnswer {
        match finished {
            Finished::Fit { request_id, result } => {
                self.jobs_pending.fit = false;
                if let Ok(patch) = &result {
                    self.runtime.set_target(patch.clone());
                }
                FinishedAnswer::SelectTarget(request_id, Box::new(select_target_response(result.map_err(|e| e.to_string()))))
            }
            Finished::Write { request_id, save, name, change, result } => {
                self.jobs_pending.write = false;
                let result = result.map(|()| self.runtime.commit(change));
                if save {
                    let response = match result {
                        Ok(message) => srv::SaveMotionResponse { success: true, message },
                        Err(e) => srv::SaveMotionResponse { success: false, message: format!("save_motion({name:?}): {e}") },
                    };
                    FinishedAnswer::SaveMotion(request_id, response)
                } else {
                    let response = match result {
                        Ok(message) => srv::DeleteMotionResponse { success: true, message },
                        Err(e) => srv::DeleteMotionResponse { success: false, message: format!("delete_motion({name:?}): {e}") },
                    };
                    FinishedAnswer::DeleteMotion(request_id, response)
                }
            }
        }
    }

    fn play_motion(&mut self, request: srv::PlayMotionRequest) -> srv::PlayMotionResponse {
        match self.runtime.play_motion(&request.name) {
            Ok(message) => srv::PlayMotionResponse { success: true, message },
            Err(e) => srv::PlayMotionResponse { success: false, message: format!("play_motion({:?}): {e}", request.name) },
        }
    }

    /// Start of a loop pass: the stop requests are taken next, then the resets.
    fn begin_pass(&mut self) {
        self.stops_in_pass = 0;
    }

    /// E-stop: always succeeds; disarms, stops the servos within one cycle and latches
    /// `STATE_ESTOPPED` until an explicit `reset_estop` (arming does not clear it).
    fn stop(&mut self) -> TriggerResponse {
        self.stops_in_pass += 1;
        self.deadman.disengage();
        let message = self.runtime.stop();
        tracing::warn!("e-stop requested");
        TriggerResponse { success: true, message }
    }

    /// Clear a latched e-stop, unless a stop was taken in this same pass.
    ///
    /// Each pass takes the stop requests before the resets. A stop that arrived after a reset but
    /// was taken before it can therefore only have been taken in the reset's own pass (the reset
    /// was waiting before the stop came, so the next reset drain after that stop takes it). Refusing
    /// the reset in that case keeps every acknowledged stop in force until a reset that arrived
    /// after it; the caller is told to send the reset again.
    fn reset_estop(&mut self) -> TriggerResponse {
        if self.stops_in_pass > 0 {
            return TriggerResponse {
                success: false,
                message: "refused: an e-stop arrived together with this reset and stays in force; send reset_estop again".into(),
            };
        }
        let message = self.runtime.reset_estop();
        tracing::info!("{message}");
        TriggerResponse { success: true, message }
    }

    /// Reboot servos to clear a fault (see `srv/RebootServos.srv`); refused while playing.
    fn reboot_servos(&mut self, request: srv::RebootServosRequest) -> srv::RebootServosResponse {
        match self.runtime.reboot_servos(&request.ids) {
            Ok((message, rebooted)) => {
                tracing::info!("{message}");
                srv::RebootServosResponse { success: true, message, rebooted }
            }
            Err(e) => srv::RebootServosResponse {
                success: false,
                message: format!("reboot_servos({:?}): {e}", request.ids),
                rebooted: Vec::new(),
            },
        }
    }

    /// Arm/disarm automatic execution on match; refused while an e-stop is latched or without a
    /// recent heartbeat (the deadman).
    fn arm(&mut self, request: SetBoolRequest) -> SetBoolResponse {
        // A latched e-stop is named first (the deadman is the second reason not to arm).
        if request.data && self.runtime.status().state != RunState::EStopped {
            if let Err(reason) = self.deadman.check_arm(Instant::now()) {
                return failure_bool(format!("arm(true): refused: {reason}"));
            }
        }
        match self.runtime.arm(request.data) {
            Ok(message) => {
                tracing::info!("{message}");
                if request.data {
                    self.deadman.engage();
                } else {
                    self.deadman.disengage();
                }
                SetBoolResponse { success: true, message }
            }
            Err(e) => failure_bool(format!("arm({}): {e}", request.data)),
        }
    }
}

/// A service handler's decision: answer now, or start a job that answers when it finishes.
enum Handled<R> {
    Answer(R),
    Later(Box<Later>),
}

/// A job as the handler decided it (the loop adds the request id).
enum Later {
    Fit(FitJob, Arc<PointCloud2>),
    Write { save: bool, name: String, change: LibraryChange },
}

/// Which kinds of job are running: one fit and one library write at a time.
#[derive(Debug, Default)]
struct JobsPending {
    fit: bool,
    write: bool,
}

impl JobsPending {
    /// Why a library change cannot start now: one write at a time, and a save must not take the
    /// target while a fit is about to replace it.
    fn library_busy(&self) -> Option<&'static str> {
        if self.write {
            Some("a save or delete is in progress; call again when it is answered")
        } else if self.fit {
            Some("a select_target fit is in progress; call again when it is answered")
        } else {
            None
        }
    }
}

/// The answer to a request whose job has finished.
enum FinishedAnswer {
    SelectTarget(RmwRequestId, Box<srv::SelectTargetResponse>),
    SaveMotion(RmwRequestId, srv::SaveMotionResponse),
    DeleteMotion(RmwRequestId, srv::DeleteMotionResponse),
}

fn select_target_response(selected: Result<Patch, String>) -> srv::SelectTargetResponse {
    match selected {
        Ok(patch) => srv::SelectTargetResponse {
            success: true,
            message: format!("target: {:?}/{:?} at {:?} in base_link", patch.surface, patch.boundary, patch.center.as_slice()),
            patch: patch_msg::msg_from_patch(0, &patch, Time::default(), Time::default()),
        },
        Err(e) => srv::SelectTargetResponse { success: false, message: format!("select_target: {e}"), ..Default::default() },
    }
}

/// Take up to [`REQUESTS_PER_PASS`] requests of a service whose work may take long: each is answered
/// now, or its job is queued and answered when it finishes. Returns whether requests may be left.
fn serve_or_start<Req, Resp>(
    server: &ros2_client::Server<Req, Resp>,
    name: &str,
    executor: &mut Executor,
    jobs: &Jobs,
    log: &mut RateLimitedLog,
    handle: fn(&mut Executor, Req) -> Handled<Resp>,
) -> bool
where
    Req: ros2_client::Message + Clone + 'static,
    Resp: ros2_client::Message + 'static,
{
    let requests = node::take_requests(server, name, REQUESTS_PER_PASS, log);
    let more = requests.len() >= REQUESTS_PER_PASS;
    for (request_id, request) in requests {
        match handle(executor, request) {
            Handled::Answer(response) => node::respond(server, name, request_id, response, log),
            Handled::Later(later) => start(executor, jobs, request_id, later, log),
        }
    }
    more
}

/// Queue a handler's job; if the worker is gone, answer the request with the failure at once.
fn start(executor: &mut Executor, jobs: &Jobs, request_id: RmwRequestId, later: Box<Later>, log: &mut RateLimitedLog) {
    let job = match *later {
        Later::Fit(job, cloud) => {
            executor.jobs_pending.fit = true;
            Job::Fit { request_id, job, cloud }
        }
        Later::Write { save, name, change } => {
            executor.jobs_pending.write = true;
            Job::Write { request_id, save, name, change }
        }
    };
    if let Err(e) = jobs.submit(job) {
        executor.jobs_pending = JobsPending::default();
        log.warn("jobs", format_args!("step_executor: {e}"));
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
    node::init_tracing_with(&args.node.ros.log_levels);
    node::keep_memory_returnable();
    let names = args.node.names("step_executor")?;
    let loaded = args.node.load_config::<ExecutorFileView>(&names)?;
    let clock = NodeClock::new(loaded.use_sim_time);
    let config = loaded.config;
    config.validate()?;
    let declared = Declared::new(&config, loaded.use_sim_time, &PARAMETERS)?;
    let params = config.ros.clone();
    let urdf = tf::urdf_text(&config.urdf_path);
    let mut status_period = period(params.status_rate_hz, "ros.status_rate_hz")?;
    let heartbeat_timeout = match Duration::try_from_secs_f64(params.heartbeat_timeout_s) {
        Ok(timeout) if timeout > Duration::ZERO => timeout,
        _ => anyhow::bail!("ros.heartbeat_timeout_s = {} must be a positive duration in s", params.heartbeat_timeout_s),
    };
    let mut joint_state_period = period(params.joint_state_rate_hz, "ros.joint_state_rate_hz")?;
    // Library, URDF and the servo bus thread (a missing bus or a broken library file is reported, not fatal).
    let (runtime, warnings) = Runtime::new(config)?;
    for warning in &warnings {
        tracing::warn!("{warning}");
    }
    let network = node::DdsNetwork::resolve(args.node.dds_network)?;
    let shutdown = Shutdown::install()?;

    // The ROS loop answers the e-stop first on every wake-up; at nice -15 or SCHED_FIFO (inherited by
    // the DDS threads created below) it also wakes ahead of the host's other work.
    if params.realtime_priority > 0 {
        let priority = patchwalk_dynamixel::priority::make_realtime(params.realtime_priority);
        tracing::info!("ROS loop and DDS threads: {priority}");
    } else if patchwalk_dynamixel::priority::raise_thread_priority() {
        tracing::info!("ROS loop and DDS threads: nice -15");
    } else {
        tracing::info!("ROS loop and DDS threads: normal priority (nice -15 not permitted)");
    }
    let mut ros = RosNode::with_names("step_executor", names, network)?;
    let mut patches_sub = ros.subscription::<PatchArray>(&ros.relative(PATCHES_TOPIC), node::reliable_qos())?;
    let mut cloud_sub = ros.subscription::<PointCloud2>(&ros.relative(CLOUD_TOPIC), node::reliable_qos())?;
    // Joint states come from the servo bus thread; nothing is published without a bus.
    let joint_states_pub = ros.publisher::<JointState>(&ros.relative(JOINT_STATES_TOPIC), node::reliable_qos())?;
    let status_pub = ros.publisher::<ExecutorStatus>(&ros.relative(STATUS_TOPIC), node::reliable_qos())?;
    let mut set_torque_srv = ros.server::<SetBool>(&ros.relative(SET_TORQUE))?;
    let mut record_keyframe_srv = ros.server::<srv::RecordKeyframe>(&ros.relative(RECORD_KEYFRAME))?;
    let mut select_target_srv = ros.server::<srv::SelectTarget>(&ros.relative(SELECT_TARGET))?;
    let mut save_motion_srv = ros.server::<srv::SaveMotion>(&ros.relative(SAVE_MOTION))?;
    let mut list_motions_srv = ros.server::<srv::ListMotions>(&ros.relative(LIST_MOTIONS))?;
    let mut delete_motion_srv = ros.server::<srv::DeleteMotion>(&ros.relative(DELETE_MOTION))?;
    let mut play_motion_srv = ros.server::<srv::PlayMotion>(&ros.relative(PLAY_MOTION))?;
    let mut stop_srv = ros.server::<Trigger>(&ros.relative(STOP))?;
    let mut arm_srv = ros.server::<SetBool>(&ros.relative(ARM))?;
    let mut reset_estop_srv = ros.server::<Trigger>(&ros.relative(RESET_ESTOP))?;
    let mut estop_topic = EStopTopic::new(&mut ros)?;
    let mut heartbeat_sub = ros.subscription::<Empty>(&ros.relative(HEARTBEAT_TOPIC), heartbeat::heartbeat_qos())?;
    let mut play_action = PlayMotionAction::new(&mut ros)?;
    let diagnostics_pub = ros.publisher::<DiagnosticArray>(DIAGNOSTICS_TOPIC, node::reliable_qos())?;
    let _robot_description_pub = tf::publish_robot_description(&mut ros, urdf)?;
    let tf_tree = SharedTf::default();
    let mut tf_listener = TfListener::new(&mut ros, tf_tree.clone())?;
    let mut clock_listener = ClockListener::new(&mut ros, &clock)?;
    let mut reboot_servos_srv = ros.server::<srv::RebootServos>(&ros.relative(REBOOT_SERVOS))?;

    // The loop sleeps until an input is ready, a job finishes, the bus thread has a motion cycle or
    // an event, or a periodic output is due.
    let mut wakeup = Wakeup::new()?;
    wakeup.watch(estop_topic.source())?;
    wakeup.watch(&mut heartbeat_sub)?;
    play_action.watch(&wakeup)?;
    wakeup.watch(&mut patches_sub)?;
    wakeup.watch(&mut cloud_sub)?;
    wakeup.watch(&mut stop_srv)?;
    wakeup.watch(&mut reset_estop_srv)?;
    wakeup.watch(&mut arm_srv)?;
    wakeup.watch(&mut set_torque_srv)?;
    wakeup.watch(&mut record_keyframe_srv)?;
    wakeup.watch(&mut select_target_srv)?;
    wakeup.watch(&mut save_motion_srv)?;
    wakeup.watch(&mut list_motions_srv)?;
    wakeup.watch(&mut delete_motion_srv)?;
    wakeup.watch(&mut play_motion_srv)?;
    tf_listener.watch(&wakeup)?;
    if let Some(listener) = clock_listener.as_mut() {
        wakeup.watch(&mut listener.subscription)?;
    }
    wakeup.watch(&mut reboot_servos_srv)?;
    let parameters = ParameterServer::start(&mut ros, declared, Some(wakeup.waker()), clock.clone())?;
    let job_waker = wakeup.waker();
    let jobs = Jobs::spawn(move || {
        let _ = job_waker.wake();
    })
    .context("cannot start the job worker")?;

    let mut log = RateLimitedLog::default();
    let mut executor = Executor::new(runtime, heartbeat_timeout);
    executor.tf = tf_tree;
    executor.clock = clock.clone();
    let bus_waker = wakeup.waker();
    executor.runtime.set_bus_notify(Box::new(move || {
        let _ = bus_waker.wake();
    }));
    let has_bus = executor.runtime.has_bus();
    let joint_names = executor.runtime.joint_names().to_vec();
    let mut next_status = Instant::now();
    let mut next_joint_state = Instant::now();
    let mut next_diagnostics = Instant::now();
    let mut cycles = CycleWindow::default();
    let servos = executor.runtime.config().servos.clone();
    let cycle = executor.runtime.config().player.cycle();
    tracing::info!("step_executor running");

    while !shutdown.requested() {
        let full = |n: usize| n >= REQUESTS_PER_PASS;
        // E-stop first, the topic and then the service: it never waits behind other work; then the
        // resets of this pass (refused when a stop came in the same pass, see `Executor::reset_estop`).
        executor.begin_pass();
        for _ in 0..estop_topic.take_stops(&mut log) {
            executor.stop();
        }
        let mut more = full(node::serve(&stop_srv, STOP, &mut log, |_| executor.stop()));
        let beats = node::drain(&heartbeat_sub, HEARTBEAT_TOPIC, 1024, &mut log, |_, _| {});
        if beats > 0 {
            executor.deadman.beat(Instant::now());
        }
        // Parameter sets (validated by the parameter thread): rates now, thresholds from the next map.
        if let Some(update) = parameters.take_update() {
            let ros_params = &update.config.ros;
            status_period = period(ros_params.status_rate_hz, "ros.status_rate_hz").unwrap_or(status_period);
            joint_state_period = period(ros_params.joint_state_rate_hz, "ros.joint_state_rate_hz").unwrap_or(joint_state_period);
            next_status = next_status.min(Instant::now() + status_period);
            if update.changed("matcher") {
                executor.runtime.set_matcher_config(update.config.matcher.clone());
            }
            let ms = update.accepted_at.elapsed().as_secs_f64() * 1e3;
            tracing::info!("parameters {} applied {ms:.2} ms after the set was accepted", update.keys.join(", "));
        }
        more |= full(node::serve(&reset_estop_srv, RESET_ESTOP, &mut log, |_| executor.reset_estop()));
        more |= full(node::serve(&arm_srv, ARM, &mut log, |r| executor.arm(r)));
        more |= full(node::serve(&set_torque_srv, SET_TORQUE, &mut log, |r| executor.set_torque(r)));
        more |= full(node::serve(&record_keyframe_srv, RECORD_KEYFRAME, &mut log, |r| executor.record_keyframe(r)));
        more |= full(node::serve(&list_motions_srv, LIST_MOTIONS, &mut log, |r| executor.list_motions(r)));
        more |= full(node::serve(&play_motion_srv, PLAY_MOTION, &mut log, |r| executor.play_motion(r)));
        more |= play_action.serve(&mut executor.runtime, &mut log);
        more |= full(node::serve(&reboot_servos_srv, REBOOT_SERVOS, &mut log, |r| executor.reboot_servos(r)));
        // Services whose work may take long: answered now, or by a job when it finishes.
        more |= serve_or_start(&select_target_srv, SELECT_TARGET, &mut executor, &jobs, &mut log, Executor::select_target);
        more |= serve_or_start(&save_motion_srv, SAVE_MOTION, &mut executor, &jobs, &mut log, Executor::save_motion);
        more |= serve_or_start(&delete_motion_srv, DELETE_MOTION, &mut executor, &jobs, &mut log, Executor::delete_motion);
        if let Some(listener) = clock_listener.as_mut() {
            listener.drain();
        }
        more |= tf_listener.drain();
        let finished: Vec<Finished> = jobs.finished().collect();
        for done in finished {
            match executor.finish(done) {
                FinishedAnswer::SelectTarget(id, response) => node::respond(&select_target_srv, SELECT_TARGET, id, *response, &mut log),
                FinishedAnswer::SaveMotion(id, response) => node::respond(&save_motion_srv, SAVE_MOTION, id, response, &mut log),
                FinishedAnswer::DeleteMotion(id, response) => node::respond(&delete_motion_srv, DELETE_MOTION, id, response, &mut log),
            }
        }
        more |= node::drain(&patches_sub, PATCHES_TOPIC, 8, &mut log, |map, _| executor.on_patches(map)) >= 8;
        more |= node::drain(&cloud_sub, CLOUD_TOPIC, 4, &mut log, |cloud, _| executor.latest_cloud = Some(Arc::new(cloud))) >= 4;
        // Every control cycle while playing, at joint_state_rate_hz otherwise.
        let telemetry = executor.runtime.poll();
        // The cycles queued before the last command was answered (a goal's motion just started) end
        // nothing of that goal.
        let current = telemetry.iter().position(|t| executor.runtime.is_current(t)).unwrap_or(telemetry.len());
        play_action.on_telemetry(telemetry.get(current..).unwrap_or_default(), &executor.runtime, &mut log);
        cycles.add(&telemetry);
        executor.check_deadman(Instant::now());
        for telemetry in telemetry {
            let playing = telemetry.goal.is_some();
            let now = Instant::now();
            if playing || now >= next_joint_state {
                let mut msg = JointState { name: joint_names.clone(), ..Default::default() };
                msg.header.stamp = clock.now();
                msg.position = telemetry.positions.iter().map(|p| p.unwrap_or(f64::NAN)).collect();
                node::publish(&joint_states_pub, JOINT_STATES_TOPIC, msg, &mut log);
                next_joint_state = now + joint_state_period;
            }
        }
        let now = Instant::now();
        let status = executor.runtime.status();
        estop_topic.publish_state(status.state == RunState::EStopped, &mut log);
        play_action.publish_status(&mut log);
        if now >= next_status {
            node::publish(&status_pub, STATUS_TOPIC, executor.status(), &mut log);
            next_status = now + status_period;
        }
        if now >= next_diagnostics {
            let health = executor.runtime.bus_health();
            let snapshot = Snapshot {
                health: health.as_ref(),
                status: &status,
                has_bus,
                servos: &servos,
                cycle,
                heartbeat_age: executor.deadman.age(now),
                heartbeat_timeout,
                deadman_engaged: executor.deadman.engaged(),
                action_goal_active: play_action.active_goal(),
            };
            node::publish(
                &diagnostics_pub,
                DIAGNOSTICS_TOPIC,
                diagnostics::diagnostics(&snapshot, &mut cycles, now, clock.now()),
                &mut log,
            );
            next_diagnostics = now + DIAGNOSTICS_PERIOD;
        }
        let mut due = next_status.min(next_diagnostics).min(now + MAX_WAIT);
        if let Some(deadline) = executor.deadman.deadline() {
            // Just after the deadline, so the expiry is seen in that pass.
            due = due.min(deadline + Duration::from_millis(1));
        }
        if has_bus {
            due = due.min(next_joint_state);
        }
        let timeout = if more { Duration::ZERO } else { due.saturating_duration_since(Instant::now()) };
        wakeup.wait(timeout);
    }
    tracing::info!(maps_received = executor.maps_received, "step_executor: shutting down");
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    impl<R> Handled<R> {
        fn answer(self) -> R {
            match self {
                Handled::Answer(r) => r,
                Handled::Later(_) => panic!("expected an answer, got a job"),
            }
        }
    }

    /// An executor on the real config and URDF with no servo bus.
    fn without_bus() -> (Executor, tempfile::TempDir) {
        let dir = tempfile::tempdir().unwrap();
        let root = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("../../..");
        let mut config: ExecutorFileView = patchwalk_ros::params::load_config(Some(&root.join("config/step_executor.yaml")), &[]).unwrap();
        config.urdf_path = root.join("urdf/rpbp.urdf");
        config.library_path = dir.path().join("motions.yaml");
        let (runtime, _) = Runtime::with_bus(config, || Err("no bus in this test".into())).unwrap();
        let mut executor = Executor::new(runtime, Duration::from_millis(500));
        executor.deadman.beat(Instant::now());
        (executor, dir)
    }

    #[test]
    fn stop_latches_until_an_explicit_reset() {
        let (mut executor, _dir) = without_bus();
        assert!(executor.arm(SetBoolRequest { data: true }).success);
        assert!(executor.status().armed);
        executor.begin_pass();
        assert!(executor.stop().success);
        assert_eq!(executor.status().state, ExecutorStatus::STATE_ESTOPPED);
        assert!(!executor.status().armed);
        // Arming neither clears the stop nor arms.
        let response = executor.arm(SetBoolRequest { data: true });
        assert!(!response.success && response.message.contains("reset_estop"), "{}", response.message);
        assert_eq!(executor.status().state, ExecutorStatus::STATE_ESTOPPED);
        assert!(!executor.status().armed);
        // A reset taken in the same pass as a stop is refused; in a later pass it clears, unarmed.
        let response = executor.reset_estop();
        assert!(!response.success && response.message.contains("again"), "{}", response.message);
        assert_eq!(executor.status().state, ExecutorStatus::STATE_ESTOPPED);
        executor.begin_pass();
        assert!(executor.reset_estop().success);
        assert_eq!(executor.status().state, ExecutorStatus::STATE_IDLE);
        assert!(!executor.status().armed);
        assert!(executor.arm(SetBoolRequest { data: true }).success);
    }

    #[test]
    fn services_without_a_bus_fail_with_a_reason() {
        let (mut executor, _dir) = without_bus();
        let response = executor.play_motion(srv::PlayMotionRequest { name: "rock1".into() });
        assert!(!response.success && response.message.contains("not available"), "{}", response.message);
        let response = executor.list_motions(srv::ListMotionsRequest::default());
        assert!(response.success && response.motions.is_empty());
        let response = executor.select_target(srv::SelectTargetRequest::default()).answer();
        assert!(!response.success && response.message.contains("no patch map"));
    }

    /// A 3 cm disc of plane 40 cm in front of the camera.
    fn plane_patch() -> patchwalk_spl::patch::Patch {
        patchwalk_spl::patch::Patch::new(
            patchwalk_spl::patch::SurfaceType::Plane,
            patchwalk_spl::patch::BoundaryType::Circle,
            vec![0.03],
            nalgebra::Vector2::zeros(),
            nalgebra::Vector3::zeros(),
            nalgebra::Vector3::new(0.0, 0.1, 0.4),
        )
        .unwrap()
    }

    #[test]
    fn patch_map_is_converted_and_kept_for_target_selection() {
        let (mut executor, _dir) = without_bus();
        let patch = plane_patch();
        let mut bad = patch_msg::msg_from_patch(1, &patch, Time::default(), Time::default());
        bad.surface = 42;
        let map =
            PatchArray { patches: vec![patch_msg::msg_from_patch(1, &patch, Time::default(), Time::default()), bad], ..Default::default() };
        executor.on_patches(map);
        let response = executor.select_target(srv::SelectTargetRequest::default()).answer();
        assert!(response.success, "{}", response.message);
        assert_eq!(response.patch.surface, patchwalk_msgs::msg::Patch::PLANE);
    }

    #[test]
    fn non_finite_points_and_camera_poses_are_refused() {
        let (mut executor, _dir) = without_bus();
        let patch = plane_patch();
        let map =
            PatchArray { patches: vec![patch_msg::msg_from_patch(1, &patch, Time::default(), Time::default())], ..Default::default() };
        executor.on_patches(map.clone());
        for mode in [srv::SelectTargetRequest::MODE_NEAREST_POINT, srv::SelectTargetRequest::MODE_FIT_AT_POINT] {
            for bad in [f64::NAN, f64::INFINITY] {
                let mut request = srv::SelectTargetRequest { mode, radius: 0.05, ..Default::default() };
                request.point.y = bad;
                let response = executor.select_target(request).answer();
                assert!(!response.success, "mode {mode}: {}", response.message);
                assert!(response.message.contains("invalid point") && response.message.contains("finite"), "{}", response.message);
            }
        }
        let response = executor.select_target(srv::SelectTargetRequest { mode: 7, ..Default::default() }).answer();
        assert!(!response.success && response.message.contains("invalid mode"), "{}", response.message);
        // A map whose camera pose is not finite is ignored as a whole: the previous map stays.
        let mut nan_pose = PatchArray { patches: Vec::new(), ..map };
        nan_pose.camera_pose.position.x = f64::NAN;
        executor.on_patches(nan_pose);
        assert_eq!(executor.maps_received, 2);
        let response = executor.select_target(srv::SelectTargetRequest::default()).answer();
        assert!(response.success, "{}", response.message);
    }

    #[test]
    fn config_file_view_is_the_library_config() {
        let mut file = tempfile::NamedTempFile::new().unwrap();
        std::io::Write::write_all(&mut file, b"bus:\n  baud: 57600\nros:\n  status_rate_hz: 2.0\n").unwrap();
        let view: ExecutorFileView = patchwalk_ros::params::load_config(Some(file.path()), &[]).unwrap();
        assert_eq!(view.ros.status_rate_hz, 2.0);
        assert_eq!(view.bus.baud, 57600);
        let err = patchwalk_ros::params::load_config::<ExecutorFileView>(None, &["ros.status_rate=1".into()]);
        assert!(err.unwrap_err().to_string().contains("status_rate"));
        assert!(period(0.0, "x").is_err());
    }
}

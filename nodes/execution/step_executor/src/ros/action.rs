//! `/step_executor/play_motion` as a ROS 2 action (`patchwalk_msgs/action/PlayMotion`), beside the
//! service of the same name (the action's endpoints live under `play_motion/_action/`, so the two
//! never share a topic). The service starts a motion and answers at once; the action also reports
//! progress (feedback: keyframe index of the count, fraction of the motion's duration done) and the
//! outcome (result: completed, faulted with the servo and the reason, cancelled, or refused).
//!
//! - One goal at a time. A goal that cannot start (e-stop latched, a motion already playing, no
//!   bus, an unknown name) is accepted and at once aborted with `OUTCOME_REFUSED` and the reason, so
//!   the caller learns why (a bare rejection carries no text).
//! - Cancelling holds the measured pose within one cycle without latching the e-stop (status
//!   CANCELED, `OUTCOME_CANCELLED`); the next goal may start at once. An e-stop during a goal ends
//!   it as ABORTED, `OUTCOME_CANCELLED`, "stopped by the e-stop".
//! - Motions started by a match while armed are not goals (no client asked for them): they are
//!   reported on `/step_executor/status` (`current_motion`, `keyframe_index`) and /diagnostics, and
//!   a goal sent meanwhile is refused because a motion plays.

use std::collections::VecDeque;
use std::time::{Duration, Instant};

use ros2_client::action::{ActionServer, ActionServerQosPolicies, GetResultResponse, GoalId, GoalInfo, GoalStatusEnum, SendGoalResponse};
use ros2_client::action_msgs::{CancelGoalResponse, CancelGoalResponseEnum, GoalStatus, GoalStatusArray};
use ros2_client::builtin_interfaces::Time as RosTime;
use ros2_client::dds::ServiceMapping;
use ros2_client::qos::{Durability, History, QosProfile, WhenFull};
use ros2_client::service::RmwRequestId;

use patchwalk_msgs::action::{PlayMotion, PlayMotionFeedback, PlayMotionGoal, PlayMotionResult};
use patchwalk_msgs::interface::RosAction;
use patchwalk_ros::node::{self, NodeError, RateLimitedLog, RosNode};
use step_executor::executor::Telemetry;
use step_executor::player::PlayerEvent;
use step_executor::runtime::{RunState, Runtime};

/// The action's name (its endpoints are `<name>/_action/{send_goal,cancel_goal,get_result,feedback,status}`).
pub const PLAY_MOTION_ACTION: &str = "/step_executor/play_motion";

/// Finished goals kept for late `get_result` calls and the status array.
const KEEP_FINISHED: usize = 16;
/// Feedback at most this often (and on every keyframe change).
const FEEDBACK_PERIOD: Duration = Duration::from_millis(100);

type Server = ActionServer<PlayMotionGoal, PlayMotionResult, PlayMotionFeedback>;

/// What the runtime is asked to do for a goal (a seam for tests).
pub trait Motions {
    /// Start `name`; `Ok((keyframe_count, duration_s))` or why not.
    fn start(&mut self, name: &str) -> Result<(u32, f64), String>;
    /// Hold a running motion without latching the e-stop.
    fn hold(&mut self);
    /// Whether the e-stop is latched.
    fn estopped(&self) -> bool;
}

impl Motions for Runtime {
    fn start(&mut self, name: &str) -> Result<(u32, f64), String> {
        if self.status().state == RunState::Playing {
            let playing = self.status().current_motion;
            return Err(format!("refused: motion {playing:?} is playing; wait for it or cancel it"));
        }
        let info = self.list_motions().into_iter().find(|m| m.name == name);
        self.play_motion(name).map_err(|e| format!("refused: {e}"))?;
        Ok(info.map_or((0, 0.0), |m| (m.keyframe_count, m.duration)))
    }

    fn hold(&mut self) {
        Runtime::hold(self);
    }

    fn estopped(&self) -> bool {
        self.status().state == RunState::EStopped
    }
}

struct Active {
    info: GoalInfo,
    keyframe_count: u32,
    duration_s: f64,
    started: Instant,
    cancel_requested: bool,
    last_feedback: Option<(Instant, u32)>,
}

struct Finished {
    info: GoalInfo,
    status: GoalStatusEnum,
    result: PlayMotionResult,
}

/// The action server and its goal bookkeeping (driven by the node's loop).
pub struct PlayMotionAction {
    server: Server,
    active: Option<Active>,
    finished: VecDeque<Finished>,
    /// `get_result` calls waiting for the active goal to end.
    waiting: Vec<(RmwRequestId, GoalId)>,
    status_changed: bool,
}

fn action_qos() -> ActionServerQosPolicies {
    let service = node::service_qos();
    let status = QosProfile::publisher_default()
        .reliability_reliable(WhenFull::DEFAULT)
        .durability(Durability::TransientLocal)
        .history(History::KeepLast { depth: 1 });
    ActionServerQosPolicies {
        goal_service: service.clone(),
        result_service: service.clone(),
        cancel_service: service,
        feedback_publisher: node::reliable_qos(),
        status_publisher: status,
    }
}

impl PlayMotionAction {
    pub fn new(ros: &mut RosNode) -> Result<Self, NodeError> {
        let err = |reason: String| NodeError::Endpoint { what: "action server", name: PLAY_MOTION_ACTION.to_string(), reason };
        let name = ros.resolve(&ros.relative(PLAY_MOTION_ACTION))?;
        let node = ros.node_mut().ok_or_else(|| err("the node is shutting down".into()))?;
        let server = node
            .create_action_server::<PlayMotionGoal, PlayMotionResult, PlayMotionFeedback>(
                ServiceMapping::Enhanced,
                &name,
                &PlayMotion::type_name(),
                action_qos(),
            )
            .map_err(|e| err(format!("{e:?}")))?;
        Ok(Self { server, active: None, finished: VecDeque::new(), waiting: Vec::new(), status_changed: true })
    }

    /// The three servers, to wake the loop on requests.
    pub fn watch(&mut self, wakeup: &patchwalk_ros::wait::Wakeup) -> Result<(), NodeError> {
        wakeup.watch(self.server.goal_server())?;
        wakeup.watch(self.server.cancel_server())?;
        wakeup.watch(self.server.result_server())
    }

    /// Goals, cancels and result requests; returns whether requests may be left (bounded per pass).
    pub fn serve(&mut self, motions: &mut impl Motions, log: &mut RateLimitedLog) -> bool {
        let mut goals = 0;
        for _ in 0..16 {
            match self.server.receive_goal() {
                Ok(Some((request_id, request))) => self.on_goal(request_id, request.goal_id, request.goal, motions, log),
                Ok(None) => break,
                Err(e) => {
                    log.warn("action_goal", format_args!("{PLAY_MOTION_ACTION}: cannot read a goal: {e:?}"));
                }
            }
            goals += 1;
        }
        let more = goals >= 16;
        for _ in 0..16 {
            match self.server.receive_cancel_request() {
                Ok(Some((request_id, request))) => {
                    let response = self.on_cancel(&request, motions);
                    if let Err(e) = self.server.send_cancel_response(request_id, response) {
                        log.warn("action_cancel", format_args!("{PLAY_MOTION_ACTION}: cannot answer a cancel: {e:?}"));
                    }
                }
                Ok(None) => break,
                Err(e) => {
                    log.warn("action_cancel", format_args!("{PLAY_MOTION_ACTION}: cannot read a cancel request: {e:?}"));
                }
            }
        }
        for _ in 0..16 {
            match self.server.receive_result_request() {
                Ok(Some((request_id, request))) => self.on_result_request(request_id, request.goal_id, log),
                Ok(None) => break,
                Err(e) => {
                    log.warn("action_result", format_args!("{PLAY_MOTION_ACTION}: cannot read a result request: {e:?}"));
                }
            }
        }
        more
    }

    fn on_goal(
        &mut self,
        request_id: RmwRequestId,
        goal_id: GoalId,
        goal: PlayMotionGoal,
        motions: &mut impl Motions,
        log: &mut RateLimitedLog,
    ) {
        let stamp = RosTime::now();
        let info = GoalInfo { goal_id, stamp };
        if let Err(e) = self.server.send_goal_response(request_id, SendGoalResponse { accepted: true, stamp }) {
            log.warn("action_goal", format_args!("{PLAY_MOTION_ACTION}: cannot answer a goal: {e:?}"));
            return;
        }
        let started = if self.active.is_some() {
            Err("refused: another play_motion goal is running; wait for it or cancel it".to_string())
        } else {
            motions.start(&goal.name)
        };
        match started {
            Ok((keyframe_count, duration_s)) => {
                tracing::info!("{PLAY_MOTION_ACTION}: playing {:?} (goal {goal_id:?})", goal.name);
                self.active = Some(Active {
                    info,
                    keyframe_count,
                    duration_s,
                    started: Instant::now(),
                    cancel_requested: false,
                    last_feedback: None,
                });
            }
            Err(reason) => {
                tracing::warn!("{PLAY_MOTION_ACTION}: goal {:?}: {reason}", goal.name);
                let result = PlayMotionResult {
                    outcome: PlayMotionResult::OUTCOME_REFUSED,
                    fault_servo_id: 0,
                    message: format!("{:?}: {reason}", goal.name),
                };
                self.finish(info, GoalStatusEnum::Aborted, result, log);
            }
        }
        self.status_changed = true;
    }

    /// rcl's cancel policy: a zero id with a zero stamp cancels every goal, a stamp every goal
    /// accepted at or before it, an id that goal.
    fn on_cancel(&mut self, request: &ros2_client::action::CancelGoalRequest, motions: &mut impl Motions) -> CancelGoalResponse {
        let (goal_id, stamp) = cancel_target(request);
        let respond = |return_code, goals_canceling| CancelGoalResponse { return_code, goals_canceling };
        if let Some(active) = &mut self.active {
            let by_id = goal_id == GoalId::ZERO && stamp == RosTime::ZERO || goal_id == active.info.goal_id;
            let by_stamp = stamp != RosTime::ZERO && active.info.stamp <= stamp;
            if by_id || by_stamp {
                if !active.cancel_requested {
                    active.cancel_requested = true;
                    motions.hold();
                    self.status_changed = true;
                }
                return respond(CancelGoalResponseEnum::None, vec![active.info.clone()]);
            }
        }
        if goal_id != GoalId::ZERO && self.finished.iter().any(|f| f.info.goal_id == goal_id) {
            return respond(CancelGoalResponseEnum::GoalTerminated, Vec::new());
        }
        if goal_id != GoalId::ZERO {
            return respond(CancelGoalResponseEnum::UnknownGoal, Vec::new());
        }
        respond(CancelGoalResponseEnum::Rejected, Vec::new())
    }

    fn on_result_request(&mut self, request_id: RmwRequestId, goal_id: GoalId, log: &mut RateLimitedLog) {
        if let Some(done) = self.finished.iter().find(|f| f.info.goal_id == goal_id) {
            let response = GetResultResponse { status: done.status, result: done.result.clone() };
            if let Err(e) = self.server.send_result(request_id, response) {
                log.warn("action_result", format_args!("{PLAY_MOTION_ACTION}: cannot send a result: {e:?}"));
            }
        } else if self.active.as_ref().is_some_and(|a| a.info.goal_id == goal_id) {
            self.waiting.push((request_id, goal_id));
        } else {
            let response = GetResultResponse {
                status: GoalStatusEnum::Unknown,
                result: PlayMotionResult { message: format!("unknown goal {goal_id:?}"), ..Default::default() },
            };
            if let Err(e) = self.server.send_result(request_id, response) {
                log.warn("action_result", format_args!("{PLAY_MOTION_ACTION}: cannot send a result: {e:?}"));
            }
        }
    }

    /// The bus thread's cycles since the last pass: feedback and the end of the active goal.
    pub fn on_telemetry(&mut self, telemetry: &[Telemetry], motions: &impl Motions, log: &mut RateLimitedLog) {
        let Some(active) = &mut self.active else { return };
        let mut ended: Option<(GoalStatusEnum, PlayMotionResult)> = None;
        for t in telemetry {
            match &t.event {
                Some(PlayerEvent::Finished { name }) => {
                    let message = format!("{name:?} completed");
                    ended = Some((
                        GoalStatusEnum::Succeeded,
                        PlayMotionResult { outcome: PlayMotionResult::OUTCOME_COMPLETED, fault_servo_id: 0, message },
                    ));
                }
                Some(PlayerEvent::Fault(fault)) => {
                    let result = PlayMotionResult {
                        outcome: PlayMotionResult::OUTCOME_FAULTED,
                        fault_servo_id: fault.servo_id.unwrap_or(0),
                        message: fault.to_string(),
                    };
                    ended = Some((GoalStatusEnum::Aborted, result));
                }
                Some(PlayerEvent::EStopped) => {
                    let (status, message) = if motions.estopped() {
                        (GoalStatusEnum::Aborted, "stopped by the e-stop; holding".to_string())
                    } else if active.cancel_requested {
                        (GoalStatusEnum::Canceled, "cancelled; holding the measured pose (e-stop not latched)".to_string())
                    } else {
                        (GoalStatusEnum::Aborted, "stopped; holding the measured pose".to_string())
                    };
                    ended = Some((status, PlayMotionResult { outcome: PlayMotionResult::OUTCOME_CANCELLED, fault_servo_id: 0, message }));
                }
                Some(PlayerEvent::Started { .. }) | None => {}
            }
            if ended.is_some() {
                break;
            }
        }
        if ended.is_none() {
            if let Some(last) = telemetry.last() {
                let keyframe = u32::try_from(last.keyframe_index).unwrap_or(u32::MAX);
                let now = Instant::now();
                let due = active.last_feedback.is_none_or(|(at, k)| k != keyframe || now.duration_since(at) >= FEEDBACK_PERIOD);
                if due {
                    let elapsed = now.duration_since(active.started).as_secs_f64();
                    let fraction = if active.duration_s > 0.0 { (elapsed / active.duration_s).clamp(0.0, 1.0) } else { 0.0 };
                    let feedback = PlayMotionFeedback {
                        keyframe_index: keyframe,
                        keyframe_count: active.keyframe_count,
                        fraction_done: fraction as f32,
                    };
                    if let Err(e) = self.server.send_feedback(active.info.goal_id, feedback) {
                        log.warn("action_feedback", format_args!("{PLAY_MOTION_ACTION}: cannot publish feedback: {e:?}"));
                    }
                    active.last_feedback = Some((now, keyframe));
                }
            }
            return;
        }
        if let (Some((status, result)), Some(active)) = (ended, self.active.take()) {
            tracing::info!("{PLAY_MOTION_ACTION}: goal {:?} ended: {}", active.info.goal_id, result.message);
            self.finish(active.info, status, result, log);
        }
    }

    fn finish(&mut self, info: GoalInfo, status: GoalStatusEnum, result: PlayMotionResult, log: &mut RateLimitedLog) {
        let goal_id = info.goal_id;
        let (answer, keep): (Vec<_>, Vec<_>) = self.waiting.drain(..).partition(|(_, id)| *id == goal_id);
        self.waiting = keep;
        for (request_id, _) in answer {
            if let Err(e) = self.server.send_result(request_id, GetResultResponse { status, result: result.clone() }) {
                log.warn("action_result", format_args!("{PLAY_MOTION_ACTION}: cannot send a result: {e:?}"));
            }
        }
        self.finished.push_back(Finished { info, status, result });
        while self.finished.len() > KEEP_FINISHED {
            self.finished.pop_front();
        }
        self.status_changed = true;
    }

    /// Publish the goal status array when it changed.
    pub fn publish_status(&mut self, log: &mut RateLimitedLog) {
        if !std::mem::take(&mut self.status_changed) {
            return;
        }
        let mut status_list: Vec<GoalStatus> =
            self.finished.iter().map(|f| GoalStatus { goal_info: f.info.clone(), status: f.status }).collect();
        if let Some(active) = &self.active {
            let status = if active.cancel_requested { GoalStatusEnum::Canceling } else { GoalStatusEnum::Executing };
            status_list.push(GoalStatus { goal_info: active.info.clone(), status });
        }
        if let Err(e) = self.server.send_goal_statuses(GoalStatusArray { status_list }) {
            log.warn("action_status", format_args!("{PLAY_MOTION_ACTION}: cannot publish the goal status: {e:?}"));
        }
    }

    /// Whether a goal is being played (for diagnostics).
    pub fn active_goal(&self) -> bool {
        self.active.is_some()
    }
}

/// The goal id and stamp of a cancel request. ros2-client keeps the request's fields private; its
/// serde form (which is the wire layout) is read back into a mirror struct.
fn cancel_target(request: &ros2_client::action::CancelGoalRequest) -> (GoalId, RosTime) {
    #[derive(serde::Deserialize)]
    struct Mirror {
        goal_info: GoalInfo,
    }
    match serde_json::to_value(request).and_then(serde_json::from_value::<Mirror>) {
        Ok(mirror) => (mirror.goal_info.goal_id, mirror.goal_info.stamp),
        // Unreadable: treat as "cancel everything", the safe side for a motion.
        Err(_) => (GoalId::ZERO, RosTime::ZERO),
    }
}

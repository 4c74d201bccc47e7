//! `patchwalk_dds_probe`: what a DDS participant can reach of a running step_executor — a check of the
//! DDS Security setup from the outside, and handy when a robot's credentials are in doubt.
//!
//! For `--seconds` it counts the `/step_executor/status` messages it receives and calls
//! `/step_executor/arm` (`true`) and `/step_executor/play_motion` (a motion name) until each is answered,
//! then prints one JSON line: `{"status_messages": N, "arm": {"answered": bool, "success": bool,
//! "message": "..."}, "play_motion": {...}}`. It joins the domain like the nodes do, so the
//! `ROS_SECURITY_*` variables (see `patchwalk_ros::security`) decide its credentials: without them it is an
//! unauthenticated participant.
//!
//! `--no-calls` only listens; `--until-answered` ends once a status arrived and every call is answered.

use std::time::{Duration, Instant};

use clap::Parser;
use patchwalk_msgs::msg::ExecutorStatus;
use patchwalk_msgs::srv::{PlayMotion, PlayMotionRequest};
use patchwalk_msgs::std_srvs::srv::{SetBool, SetBoolRequest};
use patchwalk_ros::node::{self, NodeArgs, RateLimitedLog, RosNode, Shutdown};
use ros2_client::Client;
use serde::Serialize;

#[derive(Parser)]
#[command(name = "patchwalk_dds_probe", about = "Count step_executor status messages and try to arm it / play a motion")]
struct Args {
    #[command(flatten)]
    node: NodeArgs,
    /// How long to listen and call.
    #[arg(long, default_value_t = 10.0)]
    seconds: f64,
    /// Motion name sent to play_motion.
    #[arg(long, default_value = "probe")]
    motion: String,
    /// Only listen; call nothing.
    #[arg(long)]
    no_calls: bool,
    /// End as soon as a status message has arrived and every call is answered.
    #[arg(long)]
    until_answered: bool,
}

#[derive(Serialize, Default)]
struct Answer {
    answered: bool,
    success: bool,
    message: String,
}

#[derive(Serialize, Default)]
struct Report {
    status_messages: usize,
    arm: Answer,
    play_motion: Answer,
}

/// One call, resent every second until answered (a request sent before the server matched is lost).
struct Call<Req: ros2_client::Message + Clone + 'static, Resp: ros2_client::Message + 'static> {
    client: Client<Req, Resp>,
    request: Req,
    sent_at: Option<Instant>,
}

impl<Req: ros2_client::Message + Clone + 'static, Resp: ros2_client::Message + 'static> Call<Req, Resp> {
    fn poll(&mut self, answer: &mut Answer, done: impl Fn(Resp) -> (bool, String)) {
        if answer.answered {
            return;
        }
        if let Ok(Some((_, response))) = self.client.receive_response() {
            let (success, message) = done(response);
            *answer = Answer { answered: true, success, message };
            return;
        }
        if self.sent_at.is_none_or(|t| t.elapsed() > Duration::from_secs(1)) {
            // A send error (no matched reader yet) is retried on the next second.
            let _ = self.client.send_request(self.request.clone());
            self.sent_at = Some(Instant::now());
        }
    }
}

fn main() -> anyhow::Result<()> {
    let args = Args::parse();
    node::init_tracing();
    let network = node::DdsNetwork::resolve(args.node.dds_network)?;
    let shutdown = Shutdown::install()?;
    let mut ros = RosNode::new("patchwalk_dds_probe", network)?;
    let status = ros.subscription::<ExecutorStatus>("/step_executor/status", node::reliable_qos())?;
    let mut calls = if args.no_calls {
        None
    } else {
        let arm = Call { client: ros.client::<SetBool>("/step_executor/arm")?, request: SetBoolRequest { data: true }, sent_at: None };
        let play = Call {
            client: ros.client::<PlayMotion>("/step_executor/play_motion")?,
            request: PlayMotionRequest { name: args.motion.clone() },
            sent_at: None,
        };
        Some((arm, play))
    };
    let mut report = Report::default();
    let mut log = RateLimitedLog::default();
    let end = Instant::now() + Duration::from_secs_f64(args.seconds.max(0.0));
    while !shutdown.requested() && Instant::now() < end {
        report.status_messages += node::drain(&status, "/step_executor/status", 64, &mut log, |_, _| {});
        if let Some((arm, play)) = calls.as_mut() {
            arm.poll(&mut report.arm, |r| (r.success, r.message));
            play.poll(&mut report.play_motion, |r| (r.success, r.message));
        }
        let calls_done = calls.is_none() || (report.arm.answered && report.play_motion.answered);
        if args.until_answered && calls_done && report.status_messages > 0 {
            break;
        }
        std::thread::sleep(Duration::from_millis(10));
    }
    println!("{}", serde_json::to_string(&report)?);
    Ok(())
}

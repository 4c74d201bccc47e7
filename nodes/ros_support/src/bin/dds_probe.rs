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
//! `--stop` also calls `/step_executor/stop` (after `arm` and `play_motion` are answered) and reports
//! its answer as `"stop"` and, as `"estopped"`, whether a status message with `STATE_ESTOPPED` arrived
//! after it.
//!
//! `--time-stop N` measures instead: it waits until `/step_executor/stop` is ready (its request reader
//! and reply writer matched), times the first call, then `N` more calls one after the other, and prints
//! `{"ready_ms": .., "first_call_ms": .., "round_trip_ms": {"calls": N, "p50": .., "max": ..}}`
//! (`ready_ms` counted from the participant's creation). Each call is one request, waited for without
//! polling (the client's readiness); a call not answered within `--seconds` of the start fails the run.

use std::time::{Duration, Instant};

use anyhow::{bail, Context as _};
use clap::Parser;
use futures::FutureExt as _;
use patchwalk_msgs::msg::ExecutorStatus;
use patchwalk_msgs::srv::{PlayMotion, PlayMotionRequest};
use patchwalk_msgs::std_srvs::srv::{SetBool, SetBoolRequest, Trigger, TriggerRequest, TriggerResponse};
use patchwalk_ros::node::{self, NodeArgs, RateLimitedLog, RosNode, Shutdown};
use patchwalk_ros::wait::Wakeup;
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
    /// Also call /step_executor/stop once arm and play_motion are answered, and watch the status for
    /// the e-stop.
    #[arg(long)]
    stop: bool,
    /// Measure the first call and N more calls of /step_executor/stop (nothing else is called).
    #[arg(long, value_name = "N")]
    time_stop: Option<usize>,
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
    #[serde(skip_serializing_if = "Option::is_none")]
    stop: Option<Answer>,
    /// With `--stop`: a status message showing the e-stop arrived after the stop was answered.
    #[serde(skip_serializing_if = "Option::is_none")]
    estopped: Option<bool>,
}

#[derive(Serialize)]
struct Timing {
    ready_ms: f64,
    first_call_ms: f64,
    round_trip_ms: RoundTrips,
}

#[derive(Serialize)]
struct RoundTrips {
    calls: usize,
    p50: f64,
    max: f64,
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
    let created = Instant::now();
    let mut ros = RosNode::new("patchwalk_dds_probe", network)?;
    let end = created + Duration::from_secs_f64(args.seconds.max(0.0));
    if let Some(calls) = args.time_stop {
        let timing = time_stop(&mut ros, calls, created, end, &shutdown)?;
        println!("{}", serde_json::to_string(&timing)?);
        return Ok(());
    }
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
    let mut stop = if args.stop && !args.no_calls {
        Some(Call { client: ros.client::<Trigger>("/step_executor/stop")?, request: TriggerRequest {}, sent_at: None })
    } else {
        None
    };
    let mut report = Report::default();
    if stop.is_some() {
        report.stop = Some(Answer::default());
        report.estopped = Some(false);
    }
    let mut log = RateLimitedLog::default();
    while !shutdown.requested() && Instant::now() < end {
        let stop_answered = report.stop.as_ref().is_some_and(|answer| answer.answered);
        let mut estopped_seen = false;
        report.status_messages += node::drain(&status, "/step_executor/status", 64, &mut log, |msg, _| {
            estopped_seen |= stop_answered && msg.state == ExecutorStatus::STATE_ESTOPPED;
        });
        if estopped_seen {
            report.estopped = Some(true);
        }
        if let Some((arm, play)) = calls.as_mut() {
            arm.poll(&mut report.arm, |r| (r.success, r.message));
            play.poll(&mut report.play_motion, |r| (r.success, r.message));
        }
        let arm_and_play_done = calls.is_none() || (report.arm.answered && report.play_motion.answered);
        if let (true, Some(stop), Some(answer)) = (arm_and_play_done, stop.as_mut(), report.stop.as_mut()) {
            stop.poll(answer, |r| (r.success, r.message));
        }
        let calls_done = arm_and_play_done && report.estopped != Some(false);
        if args.until_answered && calls_done && report.status_messages > 0 {
            break;
        }
        std::thread::sleep(Duration::from_millis(10));
    }
    println!("{}", serde_json::to_string(&report)?);
    Ok(())
}

/// `--time-stop`: readiness of `/step_executor/stop`, its first call and `calls` more, one at a time.
fn time_stop(ros: &mut RosNode, calls: usize, created: Instant, end: Instant, shutdown: &Shutdown) -> anyhow::Result<Timing> {
    let mut client = ros.client::<Trigger>("/step_executor/stop")?;
    let mut wakeup = Wakeup::new()?;
    wakeup.watch(&mut client)?;
    loop {
        let node = ros.node_mut().context("the node is shutting down")?;
        if client.wait_for_service(node).now_or_never().is_some() {
            break;
        }
        if shutdown.requested() || Instant::now() >= end {
            bail!("/step_executor/stop was not ready within --seconds");
        }
        std::thread::sleep(Duration::from_millis(2));
    }
    let ready = created.elapsed();
    let first_call = call_once(&client, &mut wakeup, end, shutdown)?;
    let mut trips = Vec::with_capacity(calls);
    for _ in 0..calls {
        trips.push(call_once(&client, &mut wakeup, end, shutdown)?);
    }
    trips.sort();
    let ms = |d: Duration| d.as_secs_f64() * 1e3;
    Ok(Timing {
        ready_ms: ms(ready),
        first_call_ms: ms(first_call),
        round_trip_ms: RoundTrips { calls, p50: trips.get(calls / 2).copied().map_or(0.0, ms), max: trips.last().copied().map_or(0.0, ms) },
    })
}

/// One stop request and the time until its own answer arrives.
fn call_once(
    client: &Client<TriggerRequest, TriggerResponse>,
    wakeup: &mut Wakeup,
    end: Instant,
    shutdown: &Shutdown,
) -> anyhow::Result<Duration> {
    let sent = Instant::now();
    let id = client.send_request(TriggerRequest {}).map_err(|e| anyhow::anyhow!("cannot send a stop request: {e:?}"))?;
    loop {
        // Every answer that arrived is read before waiting again: readiness is reported per arrival.
        while let Some((answered, _)) = client.receive_response().map_err(|e| anyhow::anyhow!("cannot read a stop answer: {e:?}"))? {
            if answered == id {
                return Ok(sent.elapsed());
            }
        }
        let now = Instant::now();
        if shutdown.requested() || now >= end {
            bail!("a stop request was not answered within --seconds");
        }
        wakeup.wait((end - now).min(Duration::from_millis(100)));
    }
}

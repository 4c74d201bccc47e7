//! `patchwalk_interface_echo`: republishes every patchwalk_msgs message it receives on
//! `/patchwalk_echo/in/<Type>` to `/patchwalk_echo/out/<Type>`, unchanged, through the Rust types.
//!
//! A wire-compatibility check between any ROS 2 implementation and these Rust structs: publish a fully
//! populated message, compare what comes back field by field (the CDR format is positional, so a
//! mismatch shows as changed values). Used by tests/test_interfaces.py; also handy on a new setup.
//!
//! Options: the common node options (`--dds-network`, see `patchwalk_ros::node::NodeArgs`).

use std::time::Duration;

use clap::Parser;
use patchwalk_msgs::interface::RosMessage;
use patchwalk_msgs::msg::{ExecutorStatus, MapperStatus, MotionSummary, Patch, PatchArray};
use patchwalk_ros::node::{self, NodeArgs, RateLimitedLog, RosNode, Shutdown};
use ros2_client::{Publisher, Subscription};

#[derive(Parser)]
#[command(name = "patchwalk_interface_echo", about = "Echo patchwalk_msgs messages back through the Rust types")]
struct Args {
    #[command(flatten)]
    node: NodeArgs,
}

/// One echoed type: its subscription and publisher.
struct Echo<M: RosMessage> {
    input: String,
    sub: Subscription<M>,
    output: String,
    publisher: Publisher<M>,
}

impl<M: RosMessage> Echo<M> {
    fn new(ros: &mut RosNode) -> anyhow::Result<Echo<M>> {
        let input = format!("/patchwalk_echo/in/{}", M::NAME);
        let output = format!("/patchwalk_echo/out/{}", M::NAME);
        let sub = ros.subscription::<M>(&input, node::reliable_qos())?;
        let publisher = ros.publisher::<M>(&output, node::reliable_qos())?;
        Ok(Echo { input, sub, output, publisher })
    }

    fn pump(&self, log: &mut RateLimitedLog) {
        let mut received = Vec::new();
        node::drain(&self.sub, &self.input, 16, log, |msg, _| received.push(msg));
        for msg in received {
            node::publish(&self.publisher, &self.output, msg, log);
        }
    }
}

fn main() -> anyhow::Result<()> {
    let args = Args::parse();
    node::init_tracing();
    let network = node::DdsNetwork::resolve(args.node.dds_network)?;
    let shutdown = Shutdown::install()?;
    let mut ros = RosNode::new("patchwalk_interface_echo", network)?;
    let patch = Echo::<Patch>::new(&mut ros)?;
    let patch_array = Echo::<PatchArray>::new(&mut ros)?;
    let mapper_status = Echo::<MapperStatus>::new(&mut ros)?;
    let executor_status = Echo::<ExecutorStatus>::new(&mut ros)?;
    let motion_summary = Echo::<MotionSummary>::new(&mut ros)?;
    let mut log = RateLimitedLog::default();
    tracing::info!("echoing /patchwalk_echo/in/<Type> -> /patchwalk_echo/out/<Type>");
    while !shutdown.requested() {
        patch.pump(&mut log);
        patch_array.pump(&mut log);
        mapper_status.pump(&mut log);
        executor_status.pump(&mut log);
        motion_summary.pump(&mut log);
        std::thread::sleep(Duration::from_millis(2));
    }
    tracing::info!("patchwalk_interface_echo: shutting down");
    Ok(())
}

//! ROS 2 wiring of the step_executor node (placeholder until the foundation lands).

/// Arguments of `step_executor run`.
#[derive(clap::Args, Debug, Default)]
pub struct RunArgs {}

pub fn run(_args: RunArgs) -> anyhow::Result<()> {
    anyhow::bail!("the ROS 2 node is not available yet")
}

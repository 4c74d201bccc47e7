//! `step_executor sim-bus` (placeholder until the step-executor issue lands).

/// Arguments of `step_executor sim-bus`.
#[derive(clap::Args, Debug)]
pub struct SimBusArgs {}

pub fn run(_args: SimBusArgs) -> anyhow::Result<()> {
    anyhow::bail!("`sim-bus` is not available yet")
}

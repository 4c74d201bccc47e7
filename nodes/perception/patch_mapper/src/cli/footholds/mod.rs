//! `patch_mapper footholds ...`: footholds from the command line.
//!
//! - `plan`: a coarse route over footholds for one depth frame (CNN IV).
//!
//! The subcommands are one enum; a new one is one more variant and module.

/// Arguments of `patch_mapper footholds`.
#[derive(clap::Args, Debug)]
pub struct FootholdsArgs {
    #[command(subcommand)]
    pub command: FootholdsCommand,
}

/// The `footholds` subcommands.
#[derive(clap::Subcommand, Debug)]
pub enum FootholdsCommand {
    /// Plan a coarse route over footholds (CNN IV) on one frame of a dataset; write route.json and route.png.
    Plan(super::footholds_plan::PlanArgs),
}

pub fn run(args: FootholdsArgs) -> anyhow::Result<()> {
    match args.command {
        FootholdsCommand::Plan(args) => super::footholds_plan::run(args),
    }
}

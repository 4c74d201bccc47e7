//! `patch_mapper footholds ...`: footholds from the command line.
//!
//! - `label`: fuse simulated or recorded sequences with the patch pipeline and write labelled,
//!   augmented region samples (safetensors);
//! - `train`: train the foothold network (and the hand-feature SVM baseline) on such samples;
//! - `eval`: one table on held-apart scenes and real frames: the CNN, the CNN without tilt, the
//!   SVM and the patch pipeline on single frames, plus a CNN Fig. 6-like picture;
//! - `plan`: a coarse route over footholds for one depth frame (CNN IV).
//!
//! The subcommands are one enum; a new one is one more variant and module.

mod eval;
mod label;
mod train;

/// Arguments of `patch_mapper footholds`.
#[derive(clap::Args, Debug)]
pub struct FootholdsArgs {
    #[command(subcommand)]
    pub command: FootholdsCommand,
}

/// The `footholds` subcommands.
#[derive(clap::Subcommand, Debug)]
pub enum FootholdsCommand {
    /// Label the regions of datasets from their fused patch maps and write a sample set.
    Label(label::LabelArgs),
    /// Train the foothold network (and the SVM baseline) on sample sets.
    Train(train::TrainArgs),
    /// Score the CNN, the CNN without tilt, the SVM and the single-frame patch pipeline on held-apart datasets.
    Eval(eval::EvalArgs),
    /// Plan a coarse route over footholds (CNN IV) on one frame of a dataset; write route.json and route.png.
    Plan(super::footholds_plan::PlanArgs),
}

pub fn run(args: FootholdsArgs) -> anyhow::Result<()> {
    match args.command {
        FootholdsCommand::Label(args) => label::run(args),
        FootholdsCommand::Train(args) => train::run(args),
        FootholdsCommand::Eval(args) => eval::run(args),
        FootholdsCommand::Plan(args) => super::footholds_plan::run(args),
    }
}

//! `patch_mapper footholds eval`: CNN III-D/E's comparison on datasets held apart from training, in
//! one table: classification and regression error of the CNN, the CNN without tilt ("No angle"),
//! the linear SVM on hand features, and the patch pipeline itself on each single frame (the
//! geometric baseline) with its time per frame. Labels come from each sequence's fused map (see
//! `patchwalk_footholds::labels`). Also writes pictures like CNN Fig. 6 and the table as JSON.

use std::path::PathBuf;

use anyhow::{Context, Result};
use patchwalk_footholds::evaluation::{evaluate_group, format_table, Methods};
use patchwalk_footholds::model::FootholdModel;
use patchwalk_footholds::svm::LinearSvm;

/// Arguments of `patch_mapper footholds eval`.
#[derive(clap::Args, Debug)]
pub struct EvalArgs {
    /// Held-apart simulated datasets (e.g. `terrain_sim record` with seeds not used for training).
    #[arg(long = "test", required = true)]
    pub test: Vec<PathBuf>,
    /// Real recorded datasets (TUM layout with accelerometer.txt), evaluation only.
    #[arg(long = "real")]
    pub real: Vec<PathBuf>,
    /// The foothold network's weights; default: the shipped ones.
    #[arg(long)]
    pub weights: Option<PathBuf>,
    /// The network trained without tilt; default: the shipped one.
    #[arg(long)]
    pub no_angle_weights: Option<PathBuf>,
    /// The SVM baseline (JSON from `footholds train --svm-out`); default: the shipped one.
    #[arg(long)]
    pub svm: Option<PathBuf>,
    /// Label every n-th tracked frame of each sequence.
    #[arg(long, default_value_t = 5)]
    pub frame_stride: usize,
    /// Output directory for the pictures and eval.json.
    #[arg(long, default_value = "footholds_eval")]
    pub out: PathBuf,
}

pub fn run(args: EvalArgs) -> Result<()> {
    let weights = args.weights.clone().unwrap_or_else(|| patchwalk_footholds::shipped_weights_path(false));
    let no_angle_weights = args.no_angle_weights.clone().unwrap_or_else(|| patchwalk_footholds::shipped_weights_path(true));
    let svm_path = args.svm.clone().unwrap_or_else(patchwalk_footholds::shipped_svm_path);
    let cnn = FootholdModel::load(&weights)?;
    let no_angle = FootholdModel::load(&no_angle_weights)?;
    if no_angle.regions != cnn.regions {
        anyhow::bail!("{} and {} were trained on different region configurations", weights.display(), no_angle_weights.display());
    }
    let svm: LinearSvm =
        serde_json::from_str(&std::fs::read_to_string(&svm_path).with_context(|| format!("reading {}", svm_path.display()))?)
            .with_context(|| format!("parsing {}", svm_path.display()))?;
    let methods = Methods { cnn, no_angle, svm };
    std::fs::create_dir_all(&args.out).with_context(|| format!("creating {}", args.out.display()))?;
    let mut results = Vec::new();
    for (group, paths) in [("held-apart sim scenes", &args.test), ("real frames", &args.real)] {
        if paths.is_empty() {
            continue;
        }
        let picture = args.out.join(if results.is_empty() { "fig6_sim.png" } else { "fig6_real.png" });
        results.push(evaluate_group(group, paths, &methods, args.frame_stride, &picture)?);
    }
    print!("{}", format_table(&results));
    let path = args.out.join("eval.json");
    std::fs::write(&path, serde_json::to_string_pretty(&results)?).with_context(|| format!("writing {}", path.display()))?;
    println!(
        "pictures (CNN Fig. 6: red dot true positive, yellow cross false positive, blue square missed) and eval.json in {}",
        args.out.display()
    );
    Ok(())
}

//! `patch_mapper footholds eval`: CNN III-D/E's comparison on datasets held apart from training, in
//! one table: classification and regression error of the CNN, the CNN without tilt ("No angle"),
//! the linear SVM on hand features, and the patch pipeline itself on each single frame (the
//! geometric baseline) with its time per frame. Labels come from each sequence's fused map (see
//! `patchwalk_footholds::labels`). The held-apart datasets are scored per parent directory (one
//! source of scenes each, e.g. `sim/rocks/seed_101`, `sim/stairs/seed_101`) and all together. Also
//! writes pictures like CNN Fig. 6 (one per group) and the table as JSON.

use std::path::PathBuf;

use anyhow::{Context, Result};
use patchwalk_footholds::evaluation::{evaluate_group, format_region_rows, format_table, GroupResult, Methods};
use patchwalk_footholds::labels::LabelConfig;
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
    /// Radius (m, on the surface) of the disc painted around each foothold for a positive region's
    /// (x, y) (see `patchwalk_footholds::labels`); 0 scores against the foothold centre nearest the
    /// region centre instead.
    #[arg(long, default_value_t = LabelConfig::default().paint_radius_m)]
    pub paint_radius_m: f64,
    /// Score both networks on each region alone, without averaging with its mirror image.
    #[arg(long)]
    pub single_pass: bool,
}

pub fn run(args: EvalArgs) -> Result<()> {
    if !(args.paint_radius_m >= 0.0 && args.paint_radius_m.is_finite()) {
        anyhow::bail!("--paint-radius-m must be a finite radius >= 0 (m)");
    }
    let weights = args.weights.clone().unwrap_or_else(|| patchwalk_footholds::shipped_weights_path(false));
    let no_angle_weights = args.no_angle_weights.clone().unwrap_or_else(|| patchwalk_footholds::shipped_weights_path(true));
    let svm_path = args.svm.clone().unwrap_or_else(patchwalk_footholds::shipped_svm_path);
    let mut cnn = FootholdModel::load(&weights)?;
    let mut no_angle = FootholdModel::load(&no_angle_weights)?;
    cnn.mirror_average = !args.single_pass;
    no_angle.mirror_average = !args.single_pass;
    if no_angle.regions != cnn.regions {
        anyhow::bail!("{} and {} were trained on different region configurations", weights.display(), no_angle_weights.display());
    }
    let svm: LinearSvm =
        serde_json::from_str(&std::fs::read_to_string(&svm_path).with_context(|| format!("reading {}", svm_path.display()))?)
            .with_context(|| format!("parsing {}", svm_path.display()))?;
    let methods = Methods { cnn, no_angle, svm };
    let label = LabelConfig { paint_radius_m: args.paint_radius_m, ..LabelConfig::default() };
    std::fs::create_dir_all(&args.out).with_context(|| format!("creating {}", args.out.display()))?;
    // Held-apart datasets grouped by their parent directory, in the order given.
    let mut sources: Vec<(String, Vec<PathBuf>)> = Vec::new();
    for path in &args.test {
        let source = path.parent().and_then(|p| p.file_name()).map_or_else(|| "sim".to_string(), |n| n.to_string_lossy().into_owned());
        match sources.iter_mut().find(|(name, _)| *name == source) {
            Some((_, paths)) => paths.push(path.clone()),
            None => sources.push((source, vec![path.clone()])),
        }
    }
    let mut results = Vec::new();
    for (source, paths) in &sources {
        let picture = args.out.join(format!("fig6_{source}.png"));
        results.push(evaluate_group(&format!("held-apart {source}"), paths, &methods, &label, args.frame_stride, &picture)?);
    }
    if results.len() > 1 {
        let total = GroupResult::merged("held-apart sim scenes, all", &results);
        results.push(total);
    }
    if !args.real.is_empty() {
        results.push(evaluate_group("real frames", &args.real, &methods, &label, args.frame_stride, &args.out.join("fig6_real.png"))?);
    }
    print!("{}", format_table(&results));
    let path = args.out.join("eval.json");
    std::fs::write(&path, serde_json::to_string_pretty(&results)?).with_context(|| format!("writing {}", path.display()))?;
    let path = args.out.join("regions.csv");
    std::fs::write(&path, format_region_rows(&results)).with_context(|| format!("writing {}", path.display()))?;
    println!(
        "pictures (CNN Fig. 6: red dot true positive, yellow cross false positive, blue square missed), eval.json and regions.csv (every known region, each method's answer) in {}",
        args.out.display()
    );
    Ok(())
}

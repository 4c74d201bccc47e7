//! `patch_mapper footholds train`: trains the foothold network on labelled samples with CNN eq 1 and
//! writes its weights (safetensors, with the configuration and how it was trained); optionally fits
//! the hand-feature SVM baseline on the same samples.

use std::path::PathBuf;
use std::time::Instant;

use anyhow::{Context, Result};
use patchwalk_footholds::model::FootholdModel;
use patchwalk_footholds::network::NetConfig;
use patchwalk_footholds::samples::SampleSet;
use patchwalk_footholds::svm::{LinearSvm, SvmConfig};
use patchwalk_footholds::train::{train, TrainConfig};
use rand::SeedableRng;

/// Arguments of `patch_mapper footholds train`.
#[derive(clap::Args, Debug)]
pub struct TrainArgs {
    /// Sample sets written by `footholds label` (same region configuration).
    #[arg(long = "set", required = true)]
    pub sets: Vec<PathBuf>,
    /// Output weights (safetensors).
    #[arg(long)]
    pub out: PathBuf,
    /// Train without the tilt side channels (CNN's "No angle").
    #[arg(long)]
    pub no_angle: bool,
    #[arg(long, default_value_t = TrainConfig::default().epochs)]
    pub epochs: usize,
    #[arg(long, default_value_t = TrainConfig::default().batch)]
    pub batch: usize,
    #[arg(long, default_value_t = TrainConfig::default().learning_rate)]
    pub learning_rate: f64,
    /// Learning rate of epoch e: `learning_rate · lr_decay^e`.
    #[arg(long, default_value_t = TrainConfig::default().lr_decay)]
    pub lr_decay: f64,
    /// Dropout rate of the two fully connected layers while training (0: none).
    #[arg(long, default_value_t = TrainConfig::default().dropout)]
    pub dropout: f64,
    /// Balanced batches with this share of positives (default: the set's own shares).
    #[arg(long)]
    pub positive_share: Option<f64>,
    /// Seed of the initial weights and of the batch order.
    #[arg(long, default_value_t = 1)]
    pub seed: u64,
    /// Train on at most this many samples (a seeded random subset of the sets), for the CPU budget.
    #[arg(long)]
    pub max_samples: Option<usize>,
    /// Seed of that subset.
    #[arg(long, default_value_t = 7)]
    pub subsample_seed: u64,
    /// Also fit the linear SVM on the same samples and write it (JSON).
    #[arg(long)]
    pub svm_out: Option<PathBuf>,
}

pub fn run(args: TrainArgs) -> Result<()> {
    let mut set: Option<SampleSet> = None;
    for path in &args.sets {
        let loaded = SampleSet::load(path).with_context(|| format!("reading {}", path.display()))?;
        match &mut set {
            None => set = Some(loaded),
            Some(set) => set.extend(loaded).with_context(|| format!("adding {}", path.display()))?,
        }
    }
    let Some(mut set) = set else { anyhow::bail!("no sample set given") };
    if let Some(max) = args.max_samples {
        let total = set.len();
        set = set.subsample(max, args.subsample_seed);
        println!("training on {} of {total} samples", set.len());
    }
    println!("{} samples ({} positive, {:.1} %)", set.len(), set.positives(), 100.0 * set.positives() as f64 / set.len().max(1) as f64);
    if let Some(svm_out) = &args.svm_out {
        let started = Instant::now();
        let svm = LinearSvm::fit(&set, &SvmConfig { seed: args.seed, ..SvmConfig::default() })?;
        std::fs::write(svm_out, serde_json::to_string_pretty(&svm)?).with_context(|| format!("writing {}", svm_out.display()))?;
        println!("linear SVM fitted in {:.1} s -> {}", started.elapsed().as_secs_f64(), svm_out.display());
    }
    let net = NetConfig {
        in_channels: set.regions.channels(),
        input_px: set.regions.out_px,
        side_channels: !args.no_angle,
        ..NetConfig::default()
    };
    let mut model = FootholdModel::new(net, set.regions.clone(), args.seed)?;
    let config = TrainConfig {
        epochs: args.epochs,
        batch: args.batch,
        learning_rate: args.learning_rate,
        seed: args.seed,
        lr_decay: args.lr_decay,
        positive_share: args.positive_share,
        dropout: args.dropout,
        ..TrainConfig::default()
    };
    let per_epoch = patchwalk_footholds::train::epoch_order(&set, &config, &mut rand::rngs::StdRng::seed_from_u64(config.seed)).len();
    let started = Instant::now();
    let losses = train(&model.net, &set, &config, |epoch, loss| {
        let s = started.elapsed().as_secs_f64();
        println!("epoch {}: loss {loss:.4} ({:.0} s, {:.1} samples/s)", epoch + 1, s, (epoch + 1) as f64 * per_epoch as f64 / s.max(1e-9));
    })?;
    let seconds = started.elapsed().as_secs_f64();
    model.notes = serde_json::json!({
        "sets": args.sets.iter().map(|p| p.display().to_string()).collect::<Vec<_>>(),
        "samples": set.len(),
        "positives": set.positives(),
        "train": config,
        "epoch_losses": losses,
        "train_seconds": seconds,
        "samples_per_second": (args.epochs * per_epoch) as f64 / seconds.max(1e-9),
    });
    model.save(&args.out)?;
    println!("trained {} epochs on {} samples in {seconds:.0} s -> {}", args.epochs, set.len(), args.out.display());
    Ok(())
}

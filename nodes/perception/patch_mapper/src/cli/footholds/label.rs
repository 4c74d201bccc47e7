//! `patch_mapper footholds label`: labelled region samples from datasets (see
//! `patchwalk_footholds::labels` for how a region becomes positive).

use std::path::{Path, PathBuf};
use std::time::Instant;

use anyhow::{Context, Result};
use patchwalk_footholds::labels::{Label, LabelConfig, LabelledFrame};
use patchwalk_footholds::regions::RegionConfig;
use patchwalk_footholds::render::{Mark, Picture};
use patchwalk_footholds::samples::{Augment, SampleSet};
use patchwalk_fusion::camera::DepthImage;
use rand::SeedableRng;
use rayon::prelude::*;

use patchwalk_footholds::sequence::Sequence;

/// Arguments of `patch_mapper footholds label`.
#[derive(clap::Args, Debug)]
pub struct LabelArgs {
    /// Datasets (TUM layout with accelerometer.txt, e.g. from `terrain_sim record`).
    #[arg(required = true)]
    pub datasets: Vec<PathBuf>,
    /// Output sample set (safetensors).
    #[arg(long)]
    pub out: PathBuf,
    /// Label every n-th tracked frame of each sequence (all frames are fused).
    #[arg(long, default_value_t = 5)]
    pub frame_stride: usize,
    /// Add a horizontally mirrored copy of every region.
    #[arg(long)]
    pub mirror: bool,
    /// Add this many copies with Gaussian depth noise of `--noise-sigma-m`.
    #[arg(long, default_value_t = 0)]
    pub noisy_copies: usize,
    #[arg(long, default_value_t = 0.002)]
    pub noise_sigma_m: f64,
    /// Add this many copies with holes in the depth (1-3 blobs, 5-40 % of the region), as a real
    /// camera loses dark, shiny and distant surfaces.
    #[arg(long, default_value_t = 0)]
    pub hole_copies: usize,
    /// Add the surface-normal channels (nx, ny) to the depth channel.
    #[arg(long)]
    pub normals: bool,
    /// Seed of the augmentation noise.
    #[arg(long, default_value_t = 1)]
    pub seed: u64,
    /// Write the first labelled frame of every dataset here as `<dataset>.png`: the depth image with
    /// the positive regions' footholds as red dots and the negative regions' centres as yellow crosses.
    #[arg(long)]
    pub pictures: Option<PathBuf>,
}

/// The labels of one frame drawn on its depth image.
fn draw_labels(depth: &DepthImage, frame: &LabelledFrame, path: &Path) -> Result<()> {
    let mut picture = Picture::of_depth(depth);
    for (region, label) in frame.regions.iter().zip(&frame.labels) {
        match label {
            Label::Positive { x, y } => {
                let (u, v) = region.to_image(*x, *y);
                picture.mark(u, v, Mark::TruePositive);
            }
            Label::Negative => picture.mark(region.u, region.v, Mark::FalsePositive),
            Label::Unknown => {}
        }
    }
    picture.save_png(path)?;
    Ok(())
}

pub fn run(args: LabelArgs) -> Result<()> {
    let started = Instant::now();
    let regions = RegionConfig { normals: args.normals, ..RegionConfig::default() };
    let label = LabelConfig::default();
    let augment =
        Augment { mirror: args.mirror, noise_sigma_m: args.noise_sigma_m, noisy_copies: args.noisy_copies, hole_copies: args.hole_copies };
    let mut set = SampleSet::new(regions.clone());
    let mut rng = rand::rngs::StdRng::seed_from_u64(args.seed);
    let (mut frames, mut unknown, mut known) = (0usize, 0usize, 0usize);
    // Each sequence is fused on one thread (the labels do not depend on the run), so the datasets
    // are labelled side by side, a core's worth at a time, and reported in the order given.
    let label_one = |path: &PathBuf| -> Result<_> {
        let sequence = Sequence::open(path)?;
        let (fused, labelled) =
            sequence.label(args.frame_stride, &regions, &label).with_context(|| format!("labelling {}", path.display()))?;
        Ok((path.clone(), sequence, fused, labelled))
    };
    let chunks = args.datasets.chunks(rayon::current_num_threads().max(1));
    for labelled_set in chunks.flat_map(|chunk| chunk.par_iter().map(label_one).collect::<Vec<_>>()) {
        let (path, sequence, fused, labelled) = labelled_set?;
        let positives: usize = labelled.iter().map(|(_, f)| f.labels.iter().filter(|l| matches!(l, Label::Positive { .. })).count()).sum();
        let seq_known: usize = labelled.iter().map(|(_, f)| f.labels.iter().filter(|l| l.is_known()).count()).sum();
        let seq_all: usize = labelled.iter().map(|(_, f)| f.labels.len()).sum();
        let volume = fused.fitted_edge_m.map_or_else(String::new, |e| format!(" ({e:.2} m volume fitted)"));
        println!(
            "{}: {} frames fused{volume}, {} map patches, {} footholds; {} frames labelled: {seq_known} regions known ({positives} positive, {:.1} %), {} unknown",
            sequence.name,
            fused.frames.len(),
            fused.map_patches,
            fused.footholds_in_map.len(),
            labelled.len(),
            100.0 * positives as f64 / seq_known.max(1) as f64,
            seq_all - seq_known
        );
        if let (Some(dir), Some((index, frame))) = (&args.pictures, labelled.first()) {
            draw_labels(&sequence.dataset.load_depth(*index)?, frame, &dir.join(format!("{}.png", picture_name(&path))))?;
        }
        for (index, frame) in &labelled {
            set.add_frame(frame, &sequence.name, *index, augment, &mut rng)?;
        }
        frames += labelled.len();
        known += seq_known;
        unknown += seq_all - seq_known;
    }
    set.save(&args.out)?;
    println!(
        "{} samples ({} positive) from {frames} frames of {} datasets ({known} regions known, {unknown} unknown) -> {} in {:.1} s",
        set.len(),
        set.positives(),
        args.datasets.len(),
        args.out.display(),
        started.elapsed().as_secs_f64()
    );
    Ok(())
}

/// `<parent>_<name>` of a dataset directory (several sources may have a `seed_1`).
fn picture_name(path: &Path) -> String {
    let name = |p: Option<&Path>| p.and_then(Path::file_name).map(|n| n.to_string_lossy().into_owned());
    match (name(path.parent()), name(Some(path))) {
        (Some(parent), Some(own)) => format!("{parent}_{own}"),
        (None, Some(own)) => own,
        _ => "dataset".to_string(),
    }
}

//! Learned seeding against hiking saliency on the same frames: the node's whole pipeline (TSDF + ICP,
//! birds-eye raycast, mapper) over a sequence once per seed order (`mapper.seeds.order`: `saliency`,
//! `learned_first`, `learned_only`), the learned orders seeded from the CNN's footholds of the
//! previous frame (as in the node, where the predictions arrive after the frame they were made on),
//! lifted into the map frame with that frame's tracked pose. Tracking does not depend on the seeds,
//! so every order sees the same poses and birds-eye views.
//!
//! Printed per sequence and order: frames mapped, seeds and valid new patches per frame, the time of
//! stages iii–v (seed selection + fit/validation) per frame, valid patches per ms of it, the patches
//! in the map at the end; and the network's cost per frame (not part of the stages' time: in the
//! node it runs on its own thread). Two time limits: none (every seed is fitted) and the node's
//! per-frame `mapper.time_limit_ms` (15 ms, where the order decides which seeds are fitted).
//!
//! `cargo run --release -p patch_mapper --bin bench_learned_seeds -- [--sim DIR]... [--no-tum]
//! [--weights FILE] [--threshold 0.5]`; `--sim` takes `terrain_sim record` directories (e.g.
//! `terrain_sim record /tmp/seed201 --frames 20 -p seed=201`, seeds the shipped weights were not
//! trained on), the TUM fr1_xyz excerpt is always included unless `--no-tum`.

use std::path::{Path, PathBuf};
use std::time::Instant;

use anyhow::{Context, Result};
use clap::Parser;
use nalgebra::{Isometry3, Vector3};
use patch_mapper::foothold_points::lift;
use patchwalk_footholds::model::FootholdModel;
use patchwalk_footholds::tilt::Tilt;
use patchwalk_fusion::calibration::{calibrate_dataset, CalibrationConfig};
use patchwalk_fusion::camera::DepthImage;
use patchwalk_fusion::dataset::{test_data_dir, Dataset};
use patchwalk_fusion::fusion::TsdfConfig;
use patchwalk_fusion::tracking::TrackerConfig;
use patchwalk_mapping::mapper::MapperConfig;
use patchwalk_mapping::pipeline::{default_mapper_config, Pipeline, PipelineConfig};
use patchwalk_mapping::seeds::SeedOrder;

#[derive(Parser)]
#[command(about = "Valid patches per frame and per ms: learned seeds vs hiking saliency")]
struct Args {
    /// `terrain_sim record` directories (the node's simulated-rig configuration).
    #[arg(long)]
    sim: Vec<PathBuf>,
    /// Leave out the TUM fr1_xyz excerpt.
    #[arg(long)]
    no_tum: bool,
    /// Network weights; default: the shipped ones.
    #[arg(long)]
    weights: Option<PathBuf>,
    /// Footholds are the regions with p ≥ this.
    #[arg(long, default_value_t = 0.5)]
    threshold: f32,
    /// The node's per-frame time limit of stages iii–v (ms) for the second run of each order.
    #[arg(long, default_value_t = 15.0)]
    time_limit_ms: f64,
}

/// One sequence and how to run the pipeline on it.
struct Sequence {
    name: String,
    frames: Vec<(DepthImage, f64)>,
    imu: Vec<(f64, Vector3<f64>)>,
    dataset: Dataset,
    tracker: TrackerConfig,
    mapper: MapperConfig,
}

/// What one run of a sequence gave.
#[derive(Default)]
struct Run {
    frames: usize,
    seeds: usize,
    valid: usize,
    stage_ms: f64,
    patches_at_end: usize,
    /// Per frame: the tracked pose (for the predictions).
    poses: Vec<Option<Isometry3<f64>>>,
}

fn camera_from_imu(dataset: &Dataset) -> Result<[[f64; 3]; 3]> {
    let calibration = calibrate_dataset(dataset, &CalibrationConfig::default())?;
    let rotation = calibration.camera_from_imu.to_rotation_matrix();
    Ok(std::array::from_fn(|r| std::array::from_fn(|c| rotation[(r, c)])))
}

fn load(dataset: Dataset, name: String, tracker: TrackerConfig, mut mapper: MapperConfig) -> Result<Sequence> {
    mapper.acquire.camera_from_imu = camera_from_imu(&dataset)?;
    let frames = (0..dataset.frames.len()).map(|i| Ok((dataset.load_depth(i)?, dataset.frames[i].timestamp))).collect::<Result<_>>()?;
    let imu = dataset.accelerometer.iter().map(|s| (s.timestamp, s.acceleration_in_imu)).collect();
    Ok(Sequence { name, frames, imu, dataset, tracker, mapper })
}

/// The TUM excerpt configured as the pipeline's TUM test (2.56 m volume at 1 cm, seeds over the
/// whole view in 16 cells per side, two per cell).
fn tum() -> Result<Sequence> {
    let dataset = Dataset::open(&test_data_dir().join("tum_fr1_xyz"))?;
    let tracker =
        TrackerConfig { tsdf: TsdfConfig { voxel_size_m: 0.01, size_m: 2.56, ..TsdfConfig::default() }, ..TrackerConfig::default() };
    let mut mapper = MapperConfig { volume_edge_m: 2.56, ..MapperConfig::default() };
    mapper.preprocess.median_downsample = false;
    mapper.saliency.fixation_radius_m = f64::INFINITY;
    mapper.seeds.cells_per_side = 16;
    mapper.seeds.per_cell = 2;
    mapper.seeds.max_seeds = 256;
    load(dataset, "TUM fr1_xyz excerpt".into(), tracker, mapper)
}

/// A simulated recording with the node's defaults (the simulated robot's rig).
fn sim(dir: &Path) -> Result<Sequence> {
    let dataset = Dataset::open(dir).with_context(|| format!("opening {}", dir.display()))?;
    load(dataset, format!("terrain_sim {}", dir.display()), TrackerConfig::default(), default_mapper_config())
}

/// The pipeline over the sequence; `priors[i]` seeds frame i (map frame).
fn run(seq: &Sequence, mapper: MapperConfig, priors: &[Vec<(Vector3<f64>, f64)>]) -> Result<Run> {
    let mut pipeline = Pipeline::new(PipelineConfig::default(), seq.tracker.clone(), mapper, seq.dataset.intrinsics)?;
    let mut next_imu = 0;
    let mut out = Run::default();
    for (i, (depth, stamp)) in seq.frames.iter().enumerate() {
        while let Some((t, a)) = seq.imu.get(next_imu).filter(|(t, _)| *t <= stamp + 0.05) {
            // Repeated stamps in a log are refused, as in the node.
            let _ = pipeline.push_imu(*t, *a);
            next_imu += 1;
        }
        if let Some(p) = priors.get(i) {
            pipeline.set_seed_priors(p.clone());
        }
        match pipeline.process(depth, *stamp) {
            Ok(output) => {
                out.frames += 1;
                out.seeds += output.mapped.seeds;
                out.valid += output.mapped.valid;
                out.stage_ms += output.timings.map_seeds_ms + output.timings.map_fit_ms;
                out.poses.push(Some(output.map_from_camera));
            }
            Err(_) => out.poses.push(None),
        }
    }
    out.patches_at_end = pipeline.map().len();
    Ok(out)
}

fn main() -> Result<()> {
    let args = Args::parse();
    let weights = args.weights.clone().unwrap_or_else(|| patchwalk_footholds::shipped_weights_path(false));
    let model = FootholdModel::load(&weights).with_context(|| format!("loading {}", weights.display()))?;
    let mut sequences = Vec::new();
    if !args.no_tum {
        sequences.push(tum()?);
    }
    for dir in &args.sim {
        sequences.push(sim(dir)?);
    }
    println!("threads: {}; weights {}; footholds at p >= {}", rayon::current_num_threads(), weights.display(), args.threshold);
    for seq in &sequences {
        let unlimited = MapperConfig { time_limit_ms: f64::INFINITY, ..seq.mapper.clone() };
        // The poses (the same for every order: tracking does not see the seeds), then the footholds
        // of each frame in the map frame.
        let reference = run(seq, unlimited.clone(), &[])?;
        let mut predict_ms = Vec::new();
        let mut per_frame: Vec<Vec<(Vector3<f64>, f64)>> = vec![Vec::new()];
        for ((depth, _), pose) in seq.frames.iter().zip(&reference.poses) {
            let holds = match pose {
                Some(map_from_camera) => {
                    let tilt = Tilt::from_gravity_in_camera(&map_from_camera.inverse_transform_vector(&-Vector3::z()))?;
                    let started = Instant::now();
                    let prediction = model.predict_frame(depth, &seq.dataset.intrinsics, tilt)?;
                    predict_ms.push(started.elapsed().as_secs_f64() * 1e3);
                    let radius = seq.mapper.foot_radius_m;
                    lift(&prediction.footholds(args.threshold), depth, &seq.dataset.intrinsics, map_from_camera, radius)
                        .iter()
                        .map(|h| (h.position, h.score))
                        .collect()
                }
                None => Vec::new(),
            };
            // Frame i is seeded with the footholds of frame i − 1.
            per_frame.push(holds);
        }
        predict_ms.sort_by(f64::total_cmp);
        let median = predict_ms.get(predict_ms.len() / 2).copied().unwrap_or(f64::NAN);
        let holds_per_frame = per_frame.iter().map(Vec::len).sum::<usize>() as f64 / seq.frames.len().max(1) as f64;
        println!(
            "\n{} ({} frames): {holds_per_frame:.1} predicted footholds per frame, network + regions median {median:.0} ms per frame",
            seq.name,
            seq.frames.len()
        );
        println!(
            "  {:<14} {:>10} {:>7} {:>13} {:>13} {:>15} {:>13} {:>10}",
            "order", "time limit", "frames", "seeds/frame", "valid/frame", "iii–v ms/frame", "valid per ms", "map end"
        );
        for limit in [f64::INFINITY, args.time_limit_ms] {
            for order in [SeedOrder::Saliency, SeedOrder::LearnedFirst, SeedOrder::LearnedOnly] {
                let mut mapper = MapperConfig { time_limit_ms: limit, ..seq.mapper.clone() };
                mapper.seeds.order = order;
                let r = if order == SeedOrder::Saliency && limit.is_infinite() { None } else { Some(run(seq, mapper, &per_frame)?) };
                let r = r.as_ref().unwrap_or(&reference);
                let frames = r.frames.max(1) as f64;
                let limit_text = if limit.is_finite() { format!("{limit:.0} ms") } else { "none".to_string() };
                println!(
                    "  {:<14} {:>10} {:>7} {:>13.1} {:>13.2} {:>15.2} {:>13.3} {:>10}",
                    format!("{order:?}"),
                    limit_text,
                    r.frames,
                    r.seeds as f64 / frames,
                    r.valid as f64 / frames,
                    r.stage_ms / frames,
                    if r.stage_ms > 0.0 { r.valid as f64 / r.stage_ms } else { 0.0 },
                    r.patches_at_end
                );
            }
        }
    }
    Ok(())
}

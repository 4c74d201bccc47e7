//! Tracking under large motion between frames, before/after: the mapper's tracker (node defaults,
//! `TrackerConfig::default()`) beside the same tracker as J 5.2 describes it (ICP from the last pose,
//! no wide level, no IMU tilt, a failed frame resets the map), on
//!
//! 1. simulated walks (`terrain_sim::walk`: stop-and-go side steps along the table, heading sway,
//!    bob and roll, the accelerometer's gravity) on scene seeds other than the development seed,
//!    taken every k-th frame: step size → frames lost, map resets, ATE, ms per frame;
//! 2. the same walk with a one-frame dropout (a frame of zeros, a frame that never comes);
//! 3. the TUM fr1_xyz excerpt taken every 1st…4th frame (no IMU).
//!
//! Usage: `cargo run --release -p terrain_sim --bin bench_tracking -- [--seeds 11,23,42]
//! [--every 3,6,12,18,24,36] [--seconds 12] [--tum DIR] [--tum-every 1,2,3,4]`

use anyhow::Context;
use patchwalk_fusion::dataset::{test_data_dir, Dataset};
use patchwalk_fusion::fusion::TsdfConfig;
use patchwalk_fusion::tracking::{Frame, Tracker, TrackerConfig, TrackingStatus};
use patchwalk_fusion::trajectory::absolute_trajectory_rmse;
use patchwalk_fusion::volume::MovingVolumeConfig;
use std::path::PathBuf;
use std::time::Instant;
use terrain_sim::config::SimConfig;
use terrain_sim::sim::Simulator;
use terrain_sim::track_walk::{j52_as_written, track_walk, Dropout, WalkResult, WalkRun};
use terrain_sim::walk::{Walk, WalkConfig};

struct Args {
    seeds: Vec<u64>,
    every: Vec<u64>,
    seconds: f64,
    tum: PathBuf,
    tum_every: Vec<usize>,
}

fn list<T: std::str::FromStr>(text: &str, name: &str) -> anyhow::Result<Vec<T>> {
    text.split(',').map(|v| v.trim().parse::<T>().map_err(|_| anyhow::anyhow!("{name}: {v:?} is not a number"))).collect()
}

fn parse_args() -> anyhow::Result<Args> {
    let mut args = Args {
        seeds: vec![11, 23, 42],
        every: vec![3, 6, 12, 18, 24, 36],
        seconds: 12.0,
        tum: test_data_dir().join("tum_fr1_xyz"),
        tum_every: vec![1, 2, 3, 4],
    };
    let mut it = std::env::args().skip(1);
    while let Some(flag) = it.next() {
        let value = it.next().with_context(|| format!("{flag} needs a value"))?;
        match flag.as_str() {
            "--seeds" => args.seeds = list(&value, "--seeds")?,
            "--every" => args.every = list(&value, "--every")?,
            "--seconds" => args.seconds = value.parse().context("--seconds")?,
            "--tum" => args.tum = value.into(),
            "--tum-every" => args.tum_every = list(&value, "--tum-every")?,
            other => anyhow::bail!("unknown option {other} (--seeds, --every, --seconds, --tum, --tum-every)"),
        }
    }
    anyhow::ensure!(args.every.iter().all(|k| *k >= 1) && args.tum_every.iter().all(|k| *k >= 1), "--every values must be >= 1");
    Ok(args)
}

/// Sums over seeds.
#[derive(Default)]
struct Row {
    frames: usize,
    lost: usize,
    resets: usize,
    relocalisations: usize,
    ate_mm: Vec<f64>,
    ms: Vec<f64>,
    max_ms: f64,
    step_m: Vec<f64>,
    step_deg: f64,
}

impl Row {
    fn add(&mut self, r: &WalkResult) {
        self.frames += r.statuses.len();
        self.lost += r.frames_lost;
        self.resets += r.resets;
        self.relocalisations += r.relocalisations;
        if let Some(ate) = r.ate_m {
            self.ate_mm.push(ate * 1e3);
        }
        self.ms.push(r.median_ms);
        self.max_ms = self.max_ms.max(r.max_ms);
        self.step_m.push(r.mean_step_m);
        self.step_deg = self.step_deg.max(r.max_step_deg);
    }
    fn cells(&self) -> String {
        let mean = |v: &[f64]| if v.is_empty() { f64::NAN } else { v.iter().sum::<f64>() / v.len() as f64 };
        let worst = self.ate_mm.iter().copied().fold(f64::NAN, f64::max);
        format!(
            "{:>4} {:>5} {:>6} {:>7} {:>8.1} {:>8.1} {:>7.1} {:>7.1}",
            self.frames,
            self.lost,
            self.resets,
            self.relocalisations,
            mean(&self.ate_mm),
            worst,
            mean(&self.ms),
            self.max_ms
        )
    }
}

const HEADER: &str = "frames  lost resets reloc'd  ATE mm  worst mm   ms/fr  max ms";

fn main() -> anyhow::Result<()> {
    let args = parse_args()?;
    let after = TrackerConfig::default();
    let before = j52_as_written(&after);
    let configs = [("before (J 5.2 as written)", &before), ("after (this tracker)", &after)];
    let threads = rayon::current_num_threads();
    let load = std::fs::read_to_string("/proc/loadavg").unwrap_or_default();
    println!("bench_tracking: seeds {:?}, {} s walks, {threads} rayon threads, load {}", args.seeds, args.seconds, load.trim());
    let sims: Vec<Simulator> =
        args.seeds.iter().map(|&seed| Simulator::new(SimConfig { seed, ..SimConfig::default() })).collect::<Result<_, _>>()?;
    let rate = SimConfig::default().camera.rate_hz;

    println!("\n1. simulated walk every k-th frame (640x480, accelerometer gravity), sums over {} seeds", sims.len());
    println!("{:>3} {:>7} {:>6} | {:<27} {HEADER}", "k", "step cm", "max °", "tracker");
    for &every in &args.every {
        let frames = ((args.seconds * rate) as u64 / every) as usize + 1;
        let run = WalkRun { every, frames, dropouts: Vec::new(), gravity_half_window_s: Some(0.05) };
        for (name, config) in configs {
            let mut row = Row::default();
            for sim in &sims {
                row.add(&track_walk(&Walk::new(sim, WalkConfig::default()), config, &run)?);
            }
            let step_cm = row.step_m.iter().sum::<f64>() / row.step_m.len().max(1) as f64 * 100.0;
            println!("{every:>3} {step_cm:>7.1} {:>6.1} | {name:<27} {}", row.step_deg, row.cells());
        }
    }

    println!("\n2. one-frame dropouts at k = 12 (10 cm / 10°): frame 8 all zeros, frame 16 never arrives");
    println!("{:<27} {HEADER}", "tracker");
    let frames = ((args.seconds * rate) as u64 / 12) as usize + 1;
    let run = WalkRun { every: 12, frames, dropouts: vec![Dropout::Zeros(8), Dropout::Skipped(16)], gravity_half_window_s: Some(0.05) };
    for (name, config) in configs {
        let mut row = Row::default();
        for sim in &sims {
            row.add(&track_walk(&Walk::new(sim, WalkConfig::default()), config, &run)?);
        }
        println!("{name:<27} {}", row.cells());
    }

    println!("\n3. TUM fr1_xyz every n-th frame ({}; no IMU; 5 mm voxels, 4 m fixed volume as bench_fusion)", args.tum.display());
    let dataset = Dataset::open(&args.tum).with_context(|| format!("opening {}", args.tum.display()))?;
    let depths: Vec<_> = (0..dataset.frames.len()).map(|i| dataset.load_depth(i)).collect::<Result<_, _>>()?;
    println!("{:>3} | {:<27} {HEADER}", "n", "tracker");
    for &every in &args.tum_every {
        for (name, config) in configs {
            let config = TrackerConfig {
                tsdf: TsdfConfig { voxel_size_m: 0.005, size_m: 4.0, ..TsdfConfig::default() },
                moving_volume: MovingVolumeConfig { enabled: false, ..MovingVolumeConfig::default() },
                ..config.clone()
            };
            let mut tracker = Tracker::new(config, dataset.intrinsics)?;
            let (mut estimate, mut reference, mut times) = (Vec::new(), Vec::new(), Vec::new());
            let mut result = WalkResult::default();
            for (index, depth) in depths.iter().enumerate().step_by(every) {
                let Some(frame) = dataset.frames.get(index) else { continue };
                let started = Instant::now();
                let report = tracker.process(Frame {
                    depth,
                    gravity_in_camera: None,
                    external_map_from_camera: None,
                    timestamp: Some(frame.timestamp),
                })?;
                times.push(started.elapsed().as_secs_f64() * 1e3);
                match report.status {
                    TrackingStatus::Relocalising { .. } => result.frames_lost += 1,
                    TrackingStatus::Lost(_) => {
                        result.frames_lost += 1;
                        result.resets += 1;
                    }
                    TrackingStatus::Relocalised { .. } => result.relocalisations += 1,
                    _ => {}
                }
                if report.status.has_pose() {
                    if let Some(gt) = dataset.groundtruth_near(frame.timestamp, 0.02) {
                        estimate.push(report.map_from_camera);
                        reference.push(gt.world_from_camera);
                    }
                }
                result.statuses.push(report.status);
            }
            result.ate_m = absolute_trajectory_rmse(&estimate, &reference);
            times.sort_by(f64::total_cmp);
            result.median_ms = times.get(times.len() / 2).copied().unwrap_or(f64::NAN);
            result.max_ms = times.last().copied().unwrap_or(f64::NAN);
            let mut row = Row::default();
            row.add(&result);
            println!("{every:>3} | {name:<27} {}", row.cells());
        }
    }
    Ok(())
}

//! Benchmark of the patch map's fusion of re-observed patches (`mapper.fusion`):
//!
//! 1. Σ honesty on the simulator, where the truth is known: random patches of every type seen from
//!    up to 10 independent viewpoints (`patchwalk_spl::fuse_views`), fused one view after the other;
//!    the share of trials whose truth lies inside the 95 % ellipsoid of Σ after k = 1, 2, 5, 10 views
//!    and the median trace of Σ relative to the single fit.
//! 2. Id retention and per-frame cost on sequences through the node's whole pipeline (TSDF + ICP,
//!    birds-eye raycast, mapper), fusion off and on: the TUM fr1_xyz excerpt (37 frames, static desk,
//!    moving Kinect) and a static simulated scene (a rock in front
//!    of the robot, 30 frames with independent 1 mm depth noise).
//!
//! `cargo run --release -p patch_mapper --bin bench_patch_fusion [-- --trials N --seed S]`

use std::time::Instant;

use anyhow::{Context, Result};
use nalgebra::Vector3;
use rand::SeedableRng;
use rand_distr::{Distribution, Normal};

use patchwalk_fusion::calibration::{calibrate_dataset, CalibrationConfig};
use patchwalk_fusion::camera::{DepthImage, Intrinsics};
use patchwalk_fusion::dataset::{test_data_dir, Dataset};
use patchwalk_fusion::fusion::TsdfConfig;
use patchwalk_fusion::tracking::TrackerConfig;
use patchwalk_mapping::mapper::MapperConfig;
use patchwalk_mapping::patch_fusion::{id_retention, FusionCounts};
use patchwalk_mapping::pipeline::{default_mapper_config, Pipeline, PipelineConfig};
use patchwalk_spl::fit::simulate::{chi2_95, error_on_manifold, mahalanobis, truth_params};
use patchwalk_spl::fuse::fuse;
use patchwalk_spl::fuse_views::{observe, world_truth};
use patchwalk_spl::patch::PATCH_TYPES;

const KS: [usize; 4] = [1, 2, 5, 10];

fn arg<T: std::str::FromStr>(name: &str, default: T) -> Result<T> {
    match std::env::args().skip_while(|a| a != name).nth(1) {
        Some(v) => v.parse().ok().with_context(|| format!("{name}: cannot parse {v:?}")),
        None => Ok(default),
    }
}

fn quantile(samples: &mut [f64], q: f64) -> f64 {
    samples.sort_by(f64::total_cmp);
    samples.get(((samples.len() as f64 - 1.0) * q).round() as usize).copied().unwrap_or(f64::NAN)
}

/// Part 1: NEES coverage and Σ size after k fused views.
fn simulator(trials: usize, seed: u64) {
    let mut rng = rand::rngs::StdRng::seed_from_u64(seed);
    let mut inside = [0usize; 4];
    let mut counted = [0usize; 4];
    let mut ratios: [Vec<f64>; 4] = Default::default();
    let mut fuse_us: Vec<f64> = Vec::new();
    println!("1. Simulator (seed {seed}, {trials} patches per type, 150 points per view, independent views within 20° of the normal):");
    println!("   {:<34} {:>8} {:>8} {:>8} {:>8}", "type: inside the 95 % ellipsoid at k =", 1, 2, 5, 10);
    for (s, b) in PATCH_TYPES {
        let mut type_inside = [0usize; 4];
        let mut type_counted = [0usize; 4];
        for _ in 0..trials {
            let Some(truth) = world_truth(&mut rng, s, b) else { continue };
            let views: Vec<_> = (0..10).filter_map(|_| observe(&mut rng, &truth, 150, 0.35)).collect();
            let Some(first) = views.first() else { continue };
            let mut fused = first.clone();
            for (k, view) in views.iter().enumerate() {
                if k > 0 {
                    let t = Instant::now();
                    let result = fuse(&fused, view, 1.0);
                    fuse_us.push(t.elapsed().as_secs_f64() * 1e6);
                    match result {
                        Ok((f, _)) => fused = f,
                        Err(_) => break,
                    }
                }
                let Some(slot) = KS.iter().position(|&n| n == k + 1) else { continue };
                let Some(tp) = truth_params(&mut rng, &truth, &fused, 0.95) else { continue };
                let Some((m2, rank)) = mahalanobis(&error_on_manifold(&fused, &tp), &fused.covariance) else { continue };
                type_inside[slot] += usize::from(m2 <= chi2_95(rank));
                type_counted[slot] += 1;
                ratios[slot].push(fused.covariance.trace() / first.covariance.trace());
            }
        }
        let cells: Vec<String> =
            (0..4).map(|i| format!("{:>7.1}%", 100.0 * type_inside[i] as f64 / type_counted[i].max(1) as f64)).collect();
        println!("   {:<34} {}", format!("{s:?} {b:?}"), cells.join(" "));
        for i in 0..4 {
            inside[i] += type_inside[i];
            counted[i] += type_counted[i];
        }
    }
    let cells: Vec<String> = (0..4).map(|i| format!("{:>7.1}%", 100.0 * inside[i] as f64 / counted[i].max(1) as f64)).collect();
    println!("   {:<34} {}", "all types", cells.join(" "));
    let cells: Vec<String> = (0..4).map(|i| format!("{:>8}", counted[i])).collect();
    println!("   {:<34} {}", "trials", cells.join(" "));
    let cells: Vec<String> = (0..4).map(|i| format!("{:>8.3}", quantile(&mut ratios[i], 0.5))).collect();
    println!("   {:<34} {}", "median tr Σ_k / tr Σ_1 (1/k ideal)", cells.join(" "));
    println!(
        "   one fusion (align, chart, gate, update, Jacobians): median {:.1} µs, p95 {:.1} µs over {} updates",
        quantile(&mut fuse_us, 0.5),
        quantile(&mut fuse_us, 0.95),
        fuse_us.len()
    );
}

/// What one sequence through the pipeline gave.
struct SequenceRun {
    frames: usize,
    retention: Vec<f64>,
    counts: FusionCounts,
    reobserve_us: Vec<f64>,
    fit_ms: Vec<f64>,
    total_ms: Vec<f64>,
    patches: usize,
    mean_observations: f64,
}

fn run_sequence(mut pipeline: Pipeline, frames: &[(DepthImage, f64)], imu: &[(f64, Vector3<f64>)]) -> Result<SequenceRun> {
    let mut next_imu = 0;
    let mut run = SequenceRun {
        frames: 0,
        retention: Vec::new(),
        counts: FusionCounts::default(),
        reobserve_us: Vec::new(),
        fit_ms: Vec::new(),
        total_ms: Vec::new(),
        patches: 0,
        mean_observations: 0.0,
    };
    for (depth, stamp) in frames {
        while let Some((t, a)) = imu.get(next_imu).filter(|(t, _)| *t <= stamp + 0.05) {
            // Repeated stamps in a log are refused, as in the node.
            let _ = pipeline.push_imu(*t, *a);
            next_imu += 1;
        }
        let before: Vec<u64> = pipeline.map().patches().iter().map(|p| p.id).collect();
        let Ok(output) = pipeline.process(depth, *stamp) else { continue };
        let after: Vec<u64> = pipeline.map().patches().iter().map(|p| p.id).collect();
        if run.frames > 0 && output.patches_dropped == 0 {
            run.retention.push(id_retention(&before, &after));
        }
        run.frames += 1;
        run.counts.add(&output.mapped.fusion);
        run.reobserve_us.push(output.timings.map_reobserve_ms * 1e3);
        run.fit_ms.push(output.timings.map_fit_ms);
        run.total_ms.push(output.timings.total_ms);
    }
    let map = pipeline.map();
    run.patches = map.len();
    run.mean_observations = map.patches().iter().map(|p| f64::from(p.observations)).sum::<f64>() / map.len().max(1) as f64;
    Ok(run)
}

fn report(name: &str, fusion_off: &mut SequenceRun, fusion_on: &mut SequenceRun) {
    println!("   {name}");
    for (label, run) in [("fusion off", &mut *fusion_off), ("fusion on ", &mut *fusion_on)] {
        let retention = run.retention.iter().sum::<f64>() / run.retention.len().max(1) as f64;
        let c = run.counts;
        println!(
            "     {label}: {} frames, ids kept frame to frame {:.1} %, {} patches (mean {:.1} observations); re-fits {} valid {} fused {} retyped {} replaced {}",
            run.frames,
            100.0 * retention,
            run.patches,
            run.mean_observations,
            c.revisited,
            c.reobserved,
            c.fused,
            c.retyped,
            c.replaced
        );
        println!(
            "       per frame: re-fit + fusion median {:.0} µs p95 {:.0} µs; fit stage median {:.2} ms; whole frame median {:.1} ms p95 {:.1} ms",
            quantile(&mut run.reobserve_us, 0.5),
            quantile(&mut run.reobserve_us, 0.95),
            quantile(&mut run.fit_ms, 0.5),
            quantile(&mut run.total_ms, 0.5),
            quantile(&mut run.total_ms, 0.95)
        );
    }
}

fn with_fusion(mut mapper: MapperConfig, enabled: bool) -> MapperConfig {
    mapper.fusion.enabled = enabled;
    mapper
}

fn main() -> Result<()> {
    let trials: usize = arg("--trials", 40)?;
    let seed: u64 = arg("--seed", 4242)?;
    println!("threads: {}", rayon::current_num_threads());
    let start = Instant::now();
    simulator(trials, seed);
    println!("2. Sequences through the pipeline (time limit off, so both runs fit the same seeds):");

    // TUM fr1_xyz, configured as the pipeline's TUM test (2.56 m volume, IMU calibrated on the desk).
    let dataset = Dataset::open(&test_data_dir().join("tum_fr1_xyz"))?;
    let tracker =
        TrackerConfig { tsdf: TsdfConfig { voxel_size_m: 0.01, size_m: 2.56, ..TsdfConfig::default() }, ..TrackerConfig::default() };
    let mut mapper = MapperConfig { volume_edge_m: 2.56, time_limit_ms: f64::INFINITY, ..MapperConfig::default() };
    mapper.preprocess.median_downsample = false;
    mapper.saliency.fixation_radius_m = f64::INFINITY;
    mapper.seeds.cells_per_side = 16;
    mapper.seeds.per_cell = 2;
    mapper.seeds.max_seeds = 256;
    let calibration = calibrate_dataset(&dataset, &CalibrationConfig::default())?;
    let rotation = calibration.camera_from_imu.to_rotation_matrix();
    mapper.acquire.camera_from_imu = std::array::from_fn(|r| std::array::from_fn(|c| rotation[(r, c)]));
    let frames: Vec<(DepthImage, f64)> =
        dataset.frames.iter().enumerate().map(|(i, f)| Ok((dataset.load_depth(i)?, f.timestamp))).collect::<Result<_>>()?;
    let imu: Vec<(f64, Vector3<f64>)> = dataset.accelerometer.iter().map(|s| (s.timestamp, s.acceleration_in_imu)).collect();
    let mut runs = [false, true].map(|on| {
        Pipeline::new(PipelineConfig::default(), tracker.clone(), with_fusion(mapper.clone(), on), dataset.intrinsics)
            .map_err(anyhow::Error::from)
            .and_then(|p| run_sequence(p, &frames, &imu))
    });
    if let [Ok(off), Ok(on)] = &mut runs {
        report("TUM fr1_xyz (static desk, Kinect moving 0.4 m)", off, on);
    }

    // Static simulated scene: the robot's view (camera 0.45 m above a floor pitched down 0.85 rad, an
    // 8 cm rock 0.4 m ahead), the node's defaults, 30 frames at 30 Hz with independent 1 mm noise.
    let intrinsics = Intrinsics::primesense_default().scaled(0.5);
    let pitch: f64 = 0.85;
    let down = Vector3::new(0.0, pitch.cos(), pitch.sin());
    let forward = Vector3::x().cross(&down).normalize();
    let rock = down * 0.42 + forward * 0.4;
    let clean = render(&intrinsics, |p| (0.45 - p.dot(&down)).min((p - rock).norm() - 0.08));
    let mut rng = rand::rngs::StdRng::seed_from_u64(seed);
    let noise = Normal::new(0.0, 0.001)?;
    let frames: Vec<(DepthImage, f64)> = (0..30)
        .map(|k| {
            let noisy = clean.depth_m.iter().map(|&d| if d.is_finite() { d + noise.sample(&mut rng) as f32 } else { d }).collect();
            Ok((DepthImage::new(clean.width, clean.height, noisy)?, 100.0 + f64::from(k) / 30.0))
        })
        .collect::<Result<_>>()?;
    let imu: Vec<(f64, Vector3<f64>)> = (0..300).map(|k| (99.9 + f64::from(k) / 300.0, -down * 9.81)).collect();
    let mapper = MapperConfig { time_limit_ms: f64::INFINITY, ..default_mapper_config() };
    let mut runs = [false, true].map(|on| {
        Pipeline::new(PipelineConfig::default(), TrackerConfig::default(), with_fusion(mapper.clone(), on), intrinsics)
            .map_err(anyhow::Error::from)
            .and_then(|p| run_sequence(p, &frames, &imu))
    });
    if let [Ok(off), Ok(on)] = &mut runs {
        report("simulated rock in front of the robot (static, 30 frames, node defaults)", off, on);
    }
    println!("total {:.1} s", start.elapsed().as_secs_f64());
    Ok(())
}

/// Ray-marched depth of an implicit scene (`surface(p)` changes sign at the surface; camera frame).
fn render(intrinsics: &Intrinsics, surface: impl Fn(&Vector3<f64>) -> f64) -> DepthImage {
    let mut depth = vec![f32::NAN; intrinsics.width * intrinsics.height];
    for (i, d) in depth.iter_mut().enumerate() {
        let ray = intrinsics.back_project((i % intrinsics.width) as f64, (i / intrinsics.width) as f64, 1.0);
        let (mut t0, mut s0) = (0.2, surface(&(ray * 0.2)));
        while t0 < 6.0 {
            let t1 = t0 + 0.01;
            let s1 = surface(&(ray * t1));
            if s0.signum() != s1.signum() {
                let (mut a, mut b) = (t0, t1);
                for _ in 0..30 {
                    let m = 0.5 * (a + b);
                    if surface(&(ray * m)).signum() == s0.signum() {
                        a = m;
                    } else {
                        b = m;
                    }
                }
                // Depth is z along the optical axis; the ray has z = 1.
                *d = (0.5 * (a + b)) as f32;
                break;
            }
            (t0, s0) = (t1, s1);
        }
    }
    DepthImage { width: intrinsics.width, height: intrinsics.height, depth_m: depth }
}

//! Benchmark of the single-frame mapper (J 6.1.2 "Computational Cost") on the real 640×480 frames:
//! per-stage times (median / p95 / p99 over repeated runs) and the patch throughput of stages iv–v.
//!
//! `cargo run --release -p patch_mapper --bin bench_mapper [-- --repeats N]`

use std::time::Instant;

use anyhow::{Context, Result};
use patchwalk_fusion::dataset::{test_data_dir, Dataset};
use patchwalk_mapping::acquire::{gravity_from_dominant_plane, organized_cloud};
use patchwalk_mapping::mapper::{default_volume_from_map, single_frame_volume_from_camera, FrameInput, Mapper, MapperConfig};
use patchwalk_mapping::preprocess::{bilateral_filter, median_downsample_2x2, preprocess, remove_background};
use patchwalk_mapping::saliency::hiking_saliency;

fn stats(name: &str, mut samples: Vec<f64>) {
    samples.sort_by(f64::total_cmp);
    let at = |q: f64| samples.get(((samples.len() as f64 - 1.0) * q).round() as usize).copied().unwrap_or(f64::NAN);
    println!("{name:<34} median {:>8.3}  p95 {:>8.3}  p99 {:>8.3}  (n = {})", at(0.5), at(0.95), at(0.99), samples.len());
}

fn time<T>(f: impl FnOnce() -> T) -> (T, f64) {
    let start = Instant::now();
    let out = f();
    (out, start.elapsed().as_secs_f64() * 1e3)
}

fn main() -> Result<()> {
    let repeats: usize =
        std::env::args().skip_while(|a| a != "--repeats").nth(1).map(|s| s.parse()).transpose().context("--repeats N")?.unwrap_or(30);
    println!("threads: {}", rayon::current_num_threads());
    let dataset = Dataset::open(&test_data_dir().join("tum_fr1_xyz"))?;
    let depths: Vec<_> = (0..dataset.frames.len().min(10)).map(|i| dataset.load_depth(i)).collect::<Result<_, _>>()?;
    let intrinsics = dataset.intrinsics;
    let config = MapperConfig::default();
    let (mut background, mut bilateral, mut median, mut preprocessing, mut cloud_ms, mut saliency_ms, mut pre_sal) =
        (vec![], vec![], vec![], vec![], vec![], vec![], vec![]);
    for r in 0..repeats {
        let depth = &depths[r % depths.len()];
        let gravity = gravity_from_dominant_plane(&organized_cloud(depth, &intrinsics)?, 0.02, 1)?;
        let (fg, t) = time(|| remove_background(depth, 0.3, 4.0));
        background.push(t);
        let (filtered, t) = time(|| bilateral_filter(&fg, 2, 1.5, 0.01));
        bilateral.push(t);
        median.push(time(|| median_downsample_2x2(&filtered)).1);
        let (pre, t_pre) = time(|| preprocess(depth, &intrinsics, &config.preprocess));
        let pre = pre?;
        preprocessing.push(t_pre);
        cloud_ms.push(time(|| organized_cloud(&pre.filtered, &intrinsics)).1);
        let (_, t_sal) =
            time(|| hiking_saliency(&pre.auxiliary, &pre.auxiliary_intrinsics, &gravity, config.foot_radius_m, &config.saliency));
        saliency_ms.push(t_sal);
        pre_sal.push(t_pre + t_sal);
    }
    println!("TUM fr1 640x480, times in ms:");
    // Steps 3 and 4 each on their own (the public functions); `preprocess` fuses them in one pass.
    stats("  step 3 background (alone)", background);
    stats("  step 4 bilateral 5x5 (alone)", bilateral);
    stats("  step 5 median 2x2", median);
    stats("steps 3-5 preprocess", preprocessing);
    stats("organized cloud C", cloud_ms);
    stats("step 6 saliency (normals, DoN, DoNG)", saliency_ms.clone());
    stats("preprocess + saliency", pre_sal);

    // Stages iv–v throughput: many seeds per frame (ng = 8 per cell, ns = 512, no DtFP, no limits).
    let mut config =
        MapperConfig { time_limit_ms: f64::INFINITY, coverage_fraction: f64::INFINITY, volume_edge_m: 3.0, ..Default::default() };
    config.saliency.fixation_radius_m = f64::INFINITY;
    config.seeds.per_cell = 8;
    config.seeds.max_seeds = 512;
    let (mut per_patch_us, mut patches_per_s, mut nbh_us, mut frame_ms, mut validate_us) = (vec![], vec![], vec![], vec![], vec![]);
    let mut frame_patches_per_s = vec![];
    let (mut fixed_ms, mut fitted_per_frame, mut stage_ms) = (vec![], vec![], [vec![], vec![], vec![]]);
    for r in 0..repeats.div_ceil(3) {
        let depth = &depths[r % depths.len()];
        let gravity = gravity_from_dominant_plane(&organized_cloud(depth, &intrinsics)?, 0.02, 1)?;
        let mut mapper = Mapper::new(config.clone(), "map", default_volume_from_map())?;
        let volume_from_camera = single_frame_volume_from_camera(&gravity, 3.0);
        let result = mapper.process(&FrameInput { depth, intrinsics: &intrinsics, volume_from_camera, timestamp: 0.0 })?;
        let fitted = result.outcomes.iter().filter(|o| o.patch_in_camera.is_some()).count().max(1) as f64;
        per_patch_us.push(1e3 * result.timings.fit_validate_cpu_ms / fitted);
        validate_us.push(1e3 * result.timings.validate_cpu_ms / fitted);
        nbh_us.push(1e3 * result.timings.neighbourhood_cpu_ms / result.outcomes.len().max(1) as f64);
        patches_per_s.push(fitted / (result.timings.fit_stage_ms / 1e3));
        frame_ms.push(result.timings.total_ms);
        frame_patches_per_s.push(fitted / (result.timings.total_ms / 1e3));
        fixed_ms.push(result.timings.total_ms - result.timings.fit_stage_ms);
        fitted_per_frame.push(fitted);
        for (v, t) in stage_ms.iter_mut().zip([result.timings.preprocess_ms, result.timings.saliency_ms, result.timings.seeds_ms]) {
            v.push(t);
        }
    }
    println!("stages iv-v with ns = 512 seeds per frame:");
    stats("  neighbourhood CPU per seed (us)", nbh_us);
    stats("  fit + validate CPU per patch (us)", per_patch_us);
    stats("  of which validate (us)", validate_us);
    stats("  patches/s (stages iv-v wall)", patches_per_s);
    stats("  whole frame (ms)", frame_ms);
    stats("  patches/s (whole frame, stages i-v)", frame_patches_per_s);
    stats("  per-frame part, stages i-iii (ms)", fixed_ms);
    stats("  patches fitted per frame", fitted_per_frame);
    for (name, v) in ["    of which preprocess (ms)", "    of which saliency (ms)", "    of which seeds (ms)"].into_iter().zip(stage_ms) {
        stats(name, v);
    }
    Ok(())
}

//! Per-stage timing of the fusion + tracking loop on the TUM fr1_xyz excerpt (640×480), at 5 mm and
//! 1 cm voxels: ICP, integration, model raycast (ICP resolution), remap, plus a full-resolution
//! 640×480 real-camera raycast and the birds-eye raycast (`BirdsEyeConfig` default, J 5.2 step 8;
//! measured separately each frame). Prints median / p95 / p99 per stage, the per-frame total with
//! the birds-eye raycast (what the patch mapper node does every frame), process CPU time per frame,
//! and the trajectory error against the ground truth.
//!
//! Usage: `cargo run --release -p patch_mapper --bin bench_fusion -- [dataset_dir] [passes]`
//! (`RAYON_NUM_THREADS=2` to pin the thread count; `BENCH_VOXELS_MM=5` for one voxel size;
//! `BENCH_FULL_RAYCAST=0` to skip the 640×480 real-camera raycast, which is not part of the loop).

use patchwalk_ros::process::process_cpu_seconds;
use std::time::Instant;

use anyhow::Context;
use patchwalk_fusion::dataset::{test_data_dir, Dataset};
use patchwalk_fusion::fusion::TsdfConfig;
use patchwalk_fusion::raycast::raycast;
use patchwalk_fusion::tracking::{Frame, Tracker, TrackerConfig, TrackingStatus};
use patchwalk_fusion::trajectory::absolute_trajectory_rmse;
use patchwalk_fusion::volume::MovingVolumeConfig;

fn percentile(sorted: &[f64], p: f64) -> f64 {
    if sorted.is_empty() {
        return f64::NAN;
    }
    let index = ((sorted.len() - 1) as f64 * p).round() as usize;
    sorted.get(index).copied().unwrap_or(f64::NAN)
}

fn report(name: &str, values: &mut [f64]) {
    values.sort_by(f64::total_cmp);
    println!(
        "  {name:<28} median {:7.2} ms   p95 {:7.2} ms   p99 {:7.2} ms   (n = {})",
        percentile(values, 0.5),
        percentile(values, 0.95),
        percentile(values, 0.99),
        values.len()
    );
}

fn main() -> anyhow::Result<()> {
    let mut args = std::env::args().skip(1);
    let root = args.next().map(Into::into).unwrap_or_else(|| test_data_dir().join("tum_fr1_xyz"));
    let passes: usize = args.next().map(|s| s.parse()).transpose().context("passes must be a number")?.unwrap_or(3);
    let dataset = Dataset::open(&root).with_context(|| format!("opening {}", root.display()))?;
    let frames: Vec<_> = (0..dataset.frames.len()).map(|i| dataset.load_depth(i)).collect::<Result<_, _>>()?;
    println!(
        "bench_fusion: {} frames {}x{} from {}, {} passes, {} rayon threads",
        frames.len(),
        dataset.intrinsics.width,
        dataset.intrinsics.height,
        root.display(),
        passes,
        rayon::current_num_threads()
    );
    let voxels: Vec<f32> = match std::env::var("BENCH_VOXELS_MM") {
        Ok(text) => {
            text.split(',').map(|v| v.parse::<f32>().map(|mm| mm * 1e-3)).collect::<Result<_, _>>().context("BENCH_VOXELS_MM=5,10")?
        }
        Err(_) => vec![0.005, 0.01],
    };
    let full_raycast_enabled = std::env::var("BENCH_FULL_RAYCAST").map_or(true, |v| v != "0");
    for voxel in voxels {
        let mut config = TrackerConfig {
            tsdf: TsdfConfig { voxel_size_m: voxel, size_m: 4.0, ..TsdfConfig::default() },
            moving_volume: MovingVolumeConfig { enabled: false, ..MovingVolumeConfig::default() },
            ..TrackerConfig::default()
        };
        if let Ok(text) = std::env::var("BENCH_ICP_ITERATIONS") {
            let values: Vec<usize> = text.split(',').map(str::parse).collect::<Result<_, _>>().context("BENCH_ICP_ITERATIONS=a,b,c")?;
            if let [a, b, c] = values[..] {
                config.icp.iterations = [a, b, c];
            }
        }
        if let Ok(text) = std::env::var("BENCH_ICP_CONVERGENCE") {
            config.icp.convergence = text.parse().context("BENCH_ICP_CONVERGENCE=1e-5")?;
        }
        if let Ok(text) = std::env::var("BENCH_MODEL_SCALE") {
            config.model_scale = text.parse().context("BENCH_MODEL_SCALE=0.5")?;
        }
        println!("ICP iterations per level (1/4, 1/2, 1): {:?}", config.icp.iterations);
        let (mut icp, mut integrate, mut model_raycast, mut remap, mut total) = (vec![], vec![], vec![], vec![], vec![]);
        let (mut full_raycast, mut birds_eye, mut with_birds_eye) = (vec![], vec![], vec![]);
        let mut cpu_seconds = 0.0;
        let mut cpu_frames = 0usize;
        let mut ate = Vec::new();
        let mut blocks = 0;
        for _ in 0..passes {
            let mut tracker = Tracker::new(config.clone(), dataset.intrinsics)?;
            let (mut estimate, mut reference) = (Vec::new(), Vec::new());
            for (index, depth) in frames.iter().enumerate() {
                let cpu_before = process_cpu_seconds();
                let started = Instant::now();
                let report = tracker.process(Frame {
                    depth,
                    gravity_in_camera: None,
                    external_map_from_camera: None,
                    timestamp: dataset.frames.get(index).map(|f| f.timestamp),
                })?;
                let frame_ms = started.elapsed().as_secs_f64() * 1e3;
                match &report.status {
                    TrackingStatus::Lost(reason) => println!("  frame {index}: tracking lost: {reason}"),
                    TrackingStatus::Relocalising { reason, .. } => println!("  frame {index}: short loss: {reason}"),
                    TrackingStatus::Relocalised { frames_lost } => println!("  frame {index}: relocalised after {frames_lost} frames"),
                    _ => {}
                }
                let t = report.timings;
                let tracked = report.status == TrackingStatus::Tracked;
                if tracked {
                    icp.push(t.icp_ms);
                    total.push(frame_ms);
                }
                integrate.push(t.integrate_ms);
                model_raycast.push(t.raycast_ms);
                remap.push(t.remap_ms);
                let started = Instant::now();
                let view = tracker.birds_eye();
                let birds_eye_ms = started.elapsed().as_secs_f64() * 1e3;
                birds_eye.push(birds_eye_ms);
                std::hint::black_box(view.depth.valid_count());
                if tracked {
                    with_birds_eye.push(frame_ms + birds_eye_ms);
                    if let (Some(before), Some(after)) = (cpu_before, process_cpu_seconds()) {
                        cpu_seconds += after - before;
                        cpu_frames += 1;
                    }
                }
                if full_raycast_enabled {
                    let started = Instant::now();
                    let full = raycast(tracker.volume(), &config.raycast, &dataset.intrinsics, &tracker.volume_from_camera());
                    full_raycast.push(started.elapsed().as_secs_f64() * 1e3);
                    std::hint::black_box(full.hit_count());
                }
                if let Some(frame) = dataset.frames.get(index) {
                    if let Some(gt) = dataset.groundtruth_near(frame.timestamp, 0.02) {
                        estimate.push(report.map_from_camera);
                        reference.push(gt.world_from_camera);
                    }
                }
            }
            blocks = tracker.volume().block_count();
            if let Some(rmse) = absolute_trajectory_rmse(&estimate, &reference) {
                ate.push(rmse);
            }
        }
        let model = dataset.intrinsics.scaled(config.model_scale);
        println!("voxel {:.0} mm (truncation {} voxels, {} blocks at the end):", voxel * 1e3, config.tsdf.truncation_voxels, blocks);
        report("ICP", &mut icp);
        report("integrate", &mut integrate);
        report(&format!("raycast model {}x{}", model.width, model.height), &mut model_raycast);
        report("remap", &mut remap);
        report("fusion+tracking per frame", &mut total);
        let br = config.birds_eye.resolution_px;
        report(&format!("raycast birds-eye {br}x{br}"), &mut birds_eye);
        report("fusion+tracking+birds-eye", &mut with_birds_eye);
        if full_raycast_enabled {
            report("raycast real 640x480", &mut full_raycast);
        }
        let median_total = percentile(&total, 0.5);
        let median_with_birds_eye = percentile(&with_birds_eye, 0.5);
        println!(
            "  => {:.1} Hz (median frame), {:.1} Hz with the birds-eye raycast, process CPU {:.1} ms per frame (tracking + birds-eye), ATE {:?} mm",
            1e3 / median_total,
            1e3 / median_with_birds_eye,
            cpu_seconds * 1e3 / cpu_frames.max(1) as f64,
            ate.iter().map(|a| (a * 1e4).round() / 10.0).collect::<Vec<_>>()
        );
    }
    Ok(())
}

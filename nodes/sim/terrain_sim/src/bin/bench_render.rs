//! Bench: depth rendering speed of the virtual Carmine (640×480, noise, missing data) in the
//! lookdown pose in front of every rock. Prints per-frame median / p95 / p99 and frames/s.
//!
//! `cargo run --release -p terrain_sim --bin bench_render -- [frames per rock] [--sway] [--no-noise] [--no-shadow] [--reuse]`
//! (threads: `RAYON_NUM_THREADS`, default = all cores).

use patchwalk_ros::process::process_cpu_seconds;
use std::time::Instant;

use terrain_sim::config::SimConfig;
use terrain_sim::sim::Simulator;

fn main() -> anyhow::Result<()> {
    let args: Vec<String> = std::env::args().skip(1).collect();
    let frames_per_rock: usize = args.iter().find_map(|a| a.parse().ok()).unwrap_or(60);
    let mut config = SimConfig::default();
    config.motion.sway.enabled = args.iter().any(|a| a == "--sway");
    // Ablations, to see what each part costs.
    config.camera.noise.enabled = !args.iter().any(|a| a == "--no-noise");
    config.camera.missing.projector_shadow = !args.iter().any(|a| a == "--no-shadow");
    let mut sim = Simulator::new(config)?;
    let rocks = sim.scene.rocks.len();
    println!(
        "bench_render: {}x{} depth, {} rocks, {} frames per rock, {} rayon threads, sway {}, noise {}, projector shadow {}",
        sim.camera.intrinsics.width,
        sim.camera.intrinsics.height,
        rocks,
        frames_per_rock,
        rayon::current_num_threads(),
        sim.config.motion.sway.enabled,
        sim.config.camera.noise.enabled,
        sim.config.camera.missing.projector_shadow
    );
    // Warm-up (thread pool, caches).
    let _ = sim.depth_frame(0);
    // `--reuse`: the node's path, reusing the ray casting while the pose is unchanged.
    let reuse = args.iter().any(|a| a == "--reuse");
    println!("reuse static render: {reuse}");
    let mut times_ms = Vec::with_capacity(rocks * frames_per_rock);
    let mut valid = 0usize;
    let started = Instant::now();
    let cpu_start = process_cpu_seconds();
    for rock in 0..rocks {
        sim.place_at_rock(rock)?;
        let mut cache = None;
        for i in 0..frames_per_rock {
            let t0 = Instant::now();
            let frame = if reuse {
                let t = i as f64 / sim.config.camera.rate_hz;
                sim.render_at_reusing(t, &sim.world_from_camera(t), i as u64, &mut cache)
            } else {
                sim.depth_frame(i as u64)
            };
            times_ms.push(t0.elapsed().as_secs_f64() * 1e3);
            valid += frame.depth.valid_count();
        }
    }
    let wall = started.elapsed().as_secs_f64();
    let cpu = process_cpu_seconds().zip(cpu_start).map(|(end, start)| end - start);
    times_ms.sort_by(f64::total_cmp);
    anyhow::ensure!(!times_ms.is_empty(), "no frames rendered (frames per rock must be ≥ 1)");
    let pct = |p: f64| times_ms.get(((times_ms.len() - 1) as f64 * p).round() as usize).copied().unwrap_or(f64::NAN);
    println!("render ms/frame: median {:.2}  p95 {:.2}  p99 {:.2}  max {:.2}", pct(0.5), pct(0.95), pct(0.99), pct(1.0));
    println!(
        "throughput: {:.1} frames/s (median-based {:.1} frames/s); valid pixels {:.1}%",
        times_ms.len() as f64 / wall,
        1e3 / pct(0.5),
        100.0 * valid as f64 / (times_ms.len() * 640 * 480) as f64
    );
    if let Some(cpu) = cpu {
        // CPU time is what the other processes on the machine cannot inflate (wall time can).
        let per_frame_ms = cpu * 1e3 / times_ms.len() as f64;
        println!(
            "cpu: {per_frame_ms:.2} ms of CPU per frame → {:.1} frames/s per core, {:.1} frames/s on 2 idle cores",
            1e3 / per_frame_ms,
            2e3 / per_frame_ms
        );
    }
    let t0 = Instant::now();
    let samples = 10_000;
    for j in 0..samples {
        std::hint::black_box(sim.imu_sample(j));
    }
    println!("imu: {:.2} µs/sample", t0.elapsed().as_secs_f64() * 1e6 / samples as f64);
    Ok(())
}

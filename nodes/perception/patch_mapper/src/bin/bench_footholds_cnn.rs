//! Foothold prediction speed per 640 × 480 frame: region proposal (CNN III-A) plus the network's
//! inference (CNN III-B) through both forward passes (the dedicated inference path that
//! `FootholdModel::predict_frame` uses, and candle's), side by side with the linear SVM baseline (the
//! same regions, its 22 hand features and decision). Prints the median and the 90th percentile over
//! the runs, the thread count and the machine's load average.
//!
//! `cargo run --release -p patch_mapper --bin bench_footholds_cnn -- [--dataset DIR] [--frame 0]
//! [--runs 30] [--candle-runs 10] [--weights FILE] [--svm FILE]` (defaults: the recorded TUM fr1_xyz
//! excerpt and the shipped weights; `RAYON_NUM_THREADS` limits the threads).

use std::path::PathBuf;
use std::time::Instant;

use anyhow::{Context, Result};
use clap::Parser;
use patchwalk_footholds::model::{FootholdModel, Inference};
use patchwalk_footholds::regions::propose;
use patchwalk_footholds::svm::{features, LinearSvm};
use patchwalk_footholds::tilt::Tilt;
use patchwalk_fusion::camera::{DepthImage, Intrinsics};
use patchwalk_fusion::dataset::Dataset;

#[derive(Parser)]
#[command(about = "Foothold CNN vs SVM speed per depth frame")]
struct Args {
    /// Dataset with depth frames (TUM layout); default: the recorded tum_fr1_xyz excerpt.
    #[arg(long)]
    dataset: Option<PathBuf>,
    #[arg(long, default_value_t = 0)]
    frame: usize,
    /// Timed frames of the fast path and the SVM.
    #[arg(long, default_value_t = 30)]
    runs: usize,
    /// Timed frames of the candle forward pass (slower).
    #[arg(long, default_value_t = 10)]
    candle_runs: usize,
    /// Network weights; default: the shipped ones.
    #[arg(long)]
    weights: Option<PathBuf>,
    /// SVM (JSON); default: the shipped one.
    #[arg(long)]
    svm: Option<PathBuf>,
    /// Camera tilt (degrees) for the side channels.
    #[arg(long, default_value_t = 45.0)]
    tilt_deg: f64,
}

fn percentiles(mut v: Vec<f64>) -> (f64, f64) {
    v.sort_by(f64::total_cmp);
    let at = |q: f64| v.get(((v.len().saturating_sub(1)) as f64 * q).round() as usize).copied().unwrap_or(f64::NAN);
    (at(0.5), at(0.9))
}

/// The 1-minute load average (Linux), for the report.
fn load_average() -> String {
    std::fs::read_to_string("/proc/loadavg")
        .ok()
        .and_then(|s| s.split_whitespace().next().map(str::to_string))
        .unwrap_or_else(|| "?".into())
}

/// CPU time of the process so far (user + system, all threads; ms), from `/proc/self/stat` (ticks of
/// 10 ms), or NaN elsewhere.
fn cpu_ms() -> f64 {
    let stat = std::fs::read_to_string("/proc/self/stat").unwrap_or_default();
    // The fields after the command name (which is in parentheses): utime and stime are the 12th and
    // 13th of them.
    let fields: Vec<&str> = stat.rsplit_once(')').map(|(_, rest)| rest.split_whitespace().collect()).unwrap_or_default();
    match (fields.get(11).and_then(|v| v.parse::<f64>().ok()), fields.get(12).and_then(|v| v.parse::<f64>().ok())) {
        (Some(user), Some(system)) => (user + system) * 10.0,
        _ => f64::NAN,
    }
}

/// Per frame: total, region proposal and network times (ms) of `runs` predictions, and the mean CPU
/// time per frame (ms, all threads).
fn time_cnn(
    model: &FootholdModel,
    depth: &DepthImage,
    k: &Intrinsics,
    tilt: Tilt,
    path: Inference,
    runs: usize,
) -> Result<([Vec<f64>; 3], f64)> {
    let mut times: [Vec<f64>; 3] = Default::default();
    let cpu_start = cpu_ms();
    for _ in 0..runs {
        let started = Instant::now();
        let frame = model.predict_frame_with(depth, k, tilt, path)?;
        times[0].push(started.elapsed().as_secs_f64() * 1e3);
        times[1].push(frame.regions_ms);
        times[2].push(frame.network_ms);
    }
    Ok((times, (cpu_ms() - cpu_start) / runs as f64))
}

fn main() -> Result<()> {
    let args = Args::parse();
    let dataset_dir = args.dataset.clone().unwrap_or_else(|| patchwalk_fusion::dataset::test_data_dir().join("tum_fr1_xyz"));
    let dataset = Dataset::open(&dataset_dir).with_context(|| format!("opening {}", dataset_dir.display()))?;
    let depth = dataset.load_depth(args.frame)?;
    let k = dataset.intrinsics;
    let weights = args.weights.clone().unwrap_or_else(|| patchwalk_footholds::shipped_weights_path(false));
    let mut model = FootholdModel::load(&weights).with_context(|| format!("loading {}", weights.display()))?;
    let svm_path = args.svm.clone().unwrap_or_else(patchwalk_footholds::shipped_svm_path);
    let svm: LinearSvm =
        serde_json::from_str(&std::fs::read_to_string(&svm_path).with_context(|| format!("reading {}", svm_path.display()))?)?;
    let tilt = Tilt::from_degrees(args.tilt_deg)?;
    let runs = args.runs.max(1);
    println!(
        "frame {} of {} ({}x{}), {} threads, network {} multiply-adds per region, load average {} at start",
        args.frame,
        dataset_dir.display(),
        depth.width,
        depth.height,
        rayon::current_num_threads(),
        model.net.config.multiply_adds(),
        load_average()
    );
    // Warm-up (allocations, thread pool, the fast path's buffers).
    let warm = model.predict_frame(&depth, &k, tilt)?;
    model.predict_frame_with(&depth, &k, tilt, Inference::Candle)?;
    let fast = time_cnn(&model, &depth, &k, tilt, Inference::Fast, runs)?;
    let candle = time_cnn(&model, &depth, &k, tilt, Inference::Candle, args.candle_runs.max(1))?;
    model.mirror_average = false;
    let single = time_cnn(&model, &depth, &k, tilt, Inference::Fast, runs)?;
    let mut svm_total = Vec::new();
    let s = model.regions.out_px;
    let len = model.regions.input_len();
    let mut positives = 0;
    let mut inputs = Vec::new();
    let cpu_start = cpu_ms();
    for _ in 0..runs {
        let started = Instant::now();
        let regions = propose(&depth, &k, &model.regions, &mut inputs)?;
        positives = (0..regions.len())
            .filter(|&i| svm.predict_features(&features(&inputs[i * len..i * len + s * s], s, tilt.channels()[2])).p >= 0.5)
            .count();
        svm_total.push(started.elapsed().as_secs_f64() * 1e3);
    }
    let svm_cpu = (cpu_ms() - cpu_start) / runs as f64;
    println!(
        "{} regions ({:.2} G multiply-adds); CNN predicts {} footholds, the SVM {positives}",
        warm.regions.len(),
        (warm.regions.len() * model.net.config.multiply_adds()) as f64 * 1e-9,
        warm.footholds(0.5).len()
    );
    println!("{:<40} {:>10} {:>10} {:>10}", "per frame", "median ms", "p90 ms", "CPU ms");
    for (name, (times, cpu)) in
        [("CNN, fast path", &fast), ("CNN, candle forward", &candle), ("CNN, fast path, no mirror average", &single)]
    {
        let row = |label: &str, v: &Vec<f64>, cpu: Option<f64>| {
            let (m, p) = percentiles(v.clone());
            let cpu = cpu.map(|c| format!("{c:.1}")).unwrap_or_default();
            println!("{label:<40} {m:>10.1} {p:>10.1} {cpu:>10}");
        };
        row(&format!("{name}: regions + network"), &times[0], Some(*cpu));
        row("  of which region proposal", &times[1], None);
        row("  of which network", &times[2], None);
    }
    let (s50, s90) = percentiles(svm_total);
    println!("{:<40} {:>10.1} {:>10.1} {:>10.1}", "SVM: regions + features + decision", s50, s90, svm_cpu);
    println!("(CPU ms: mean CPU time per frame over all threads, from /proc/self/stat in 10 ms ticks)");
    println!("load average {} at the end", load_average());
    Ok(())
}

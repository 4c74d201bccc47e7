//! `terrain_sim` binary: publishes simulated depth, CameraInfo and IMU like the real sensors
//! (`run`, the default), writes the stream as a TUM-format dataset and/or a rosbag2 MCAP bag
//! (`record`), or prints the scene
//! with its ground-truth footholds (`scene`).

mod frames;
mod node;

use std::path::PathBuf;

use anyhow::Context as _;
use clap::{Parser, Subcommand};
use terrain_sim::config::SimConfig;
use terrain_sim::sim::Simulator;

#[derive(Parser, Debug)]
#[command(name = "terrain_sim", version, about = "Rough-terrain simulator: rocks on a table, a Carmine-like depth camera and an IMU")]
#[command(args_conflicts_with_subcommands = true)]
struct Cli {
    #[command(subcommand)]
    command: Option<Command>,
    /// Options of `run` when no subcommand is given.
    #[command(flatten)]
    run: node::RunArgs,
}

#[derive(Subcommand, Debug)]
enum Command {
    /// ROS 2 node: /camera/depth/image_raw, /camera/depth/camera_info, /imu/data (default).
    Run(node::RunArgs),
    /// Write a TUM-format dataset (depth PNGs 1/5000 m, depth.txt, accelerometer.txt,
    /// groundtruth.txt, intrinsics.json, scene.json) and/or a rosbag2 MCAP bag (`--mcap`), both
    /// readable by `patch_mapper replay`.
    Record(RecordArgs),
    /// Print the scene (rocks, stations, ground-truth footholds) as JSON.
    Scene(ConfigArgs),
}

#[derive(clap::Args, Debug)]
struct ConfigArgs {
    /// YAML config (config/terrain_sim.yaml); defaults when omitted.
    #[arg(long, value_name = "FILE")]
    config: Option<PathBuf>,
    /// Override `dotted.key=value` (YAML value), e.g. `-p seed=3 -p motion.sway.enabled=true`.
    #[arg(short = 'p', long = "param", value_name = "KEY=VALUE")]
    params: Vec<String>,
}

#[derive(clap::Args, Debug)]
struct RecordArgs {
    /// Output directory of the TUM-format dataset (created).
    #[arg(required_unless_present = "mcap")]
    out_dir: Option<PathBuf>,
    /// Also (or only) write a rosbag2 bag: a `.mcap` file, or a bag directory (metadata.yaml +
    /// `<name>_0.mcap`) for any other path. Topics as the node publishes them, plus /tf_static
    /// (camera and IMU mount) and /groundtruth (the camera's pose in `world`).
    #[arg(long, value_name = "PATH")]
    mcap: Option<PathBuf>,
    /// Depth encoding of the bag's images: 16UC1 (millimetres) or 32FC1 (metres).
    #[arg(long, default_value = "16UC1", value_parser = clap::value_parser!(terrain_sim::record_bag::DepthEncoding))]
    depth_encoding: terrain_sim::record_bag::DepthEncoding,
    /// Chunk compression of the bag: zstd (as `ros2 bag record`), lz4 or none.
    #[arg(long, default_value = "zstd", value_parser = ["zstd", "lz4", "none"])]
    compression: String,
    /// Number of depth frames (at the camera rate).
    #[arg(long, default_value_t = 90)]
    frames: usize,
    /// Rock to stand in front of (overrides `start_rock`).
    #[arg(long)]
    rock: Option<usize>,
    /// Walking-like sway with jitter (overrides `motion.sway.enabled`).
    #[arg(long)]
    sway: bool,
    #[command(flatten)]
    config: ConfigArgs,
}

fn main() -> std::process::ExitCode {
    // `--ros-args ...` (what `ros2 run`/`ros2 launch` append) is taken out before the options.
    let (cli, ros_args) = match patchwalk_ros::node::parse_command_line::<Cli>() {
        Ok(parsed) => parsed,
        Err(err) => {
            eprintln!("terrain_sim: {err}");
            return std::process::ExitCode::from(2);
        }
    };
    let result = match cli.command {
        None | Some(Command::Run(_)) => {
            let mut args = match cli.command {
                Some(Command::Run(args)) => args,
                _ => cli.run,
            };
            args.node.ros = ros_args;
            node::run(args)
        }
        Some(Command::Record(args)) => record(args),
        Some(Command::Scene(args)) => scene(args),
    };
    match result {
        Ok(()) => std::process::ExitCode::SUCCESS,
        Err(e) => {
            eprintln!("terrain_sim: {e:#}");
            std::process::ExitCode::FAILURE
        }
    }
}

fn load(args: &ConfigArgs) -> anyhow::Result<SimConfig> {
    Ok(patchwalk_ros::params::load_config(args.config.as_deref(), &args.params)?)
}

fn record(args: RecordArgs) -> anyhow::Result<()> {
    let mut config = load(&args.config)?;
    if let Some(rock) = args.rock {
        config.start_rock = rock;
    }
    config.motion.sway.enabled |= args.sway;
    let sim = Simulator::new(config)?;
    let rock = sim.scene.rocks.get(sim.config.start_rock).map(|r| r.name.clone()).unwrap_or_else(|| "?".into());
    if let Some(out_dir) = &args.out_dir {
        let started = std::time::Instant::now();
        let summary = terrain_sim::record::record(&sim, out_dir, args.frames, |i| {
            if (i + 1) % 30 == 0 {
                eprint!("\rterrain_sim record: {}/{} frames", i + 1, args.frames);
            }
        })
        .with_context(|| format!("recording into {}", out_dir.display()))?;
        eprintln!();
        println!(
            "wrote {} depth frames, {} IMU samples ({:.2} s of data, in front of {rock:?}) to {} in {:.1} s",
            summary.frames,
            summary.imu_samples,
            summary.duration_s,
            out_dir.display(),
            started.elapsed().as_secs_f64()
        );
    }
    if let Some(path) = &args.mcap {
        let compression = match args.compression.as_str() {
            "lz4" => patchwalk_bag::Compression::Lz4,
            "none" => patchwalk_bag::Compression::None,
            _ => patchwalk_bag::Compression::Zstd,
        };
        let topics = terrain_sim::record_bag::BagTopics {
            image: node::IMAGE_TOPIC.into(),
            camera_info: node::CAMERA_INFO_TOPIC.into(),
            imu: node::IMU_TOPIC.into(),
            tf_static: "/tf_static".into(),
            groundtruth: "/groundtruth".into(),
        };
        let target = terrain_sim::record_bag::target_for(path);
        let started = std::time::Instant::now();
        let summary = terrain_sim::record_bag::record_bag(&sim, &target, args.frames, args.depth_encoding, &topics, compression, |i| {
            if (i + 1) % 30 == 0 {
                eprint!("\rterrain_sim record: {}/{} frames", i + 1, args.frames);
            }
        })
        .with_context(|| format!("recording the bag {}", path.display()))?;
        eprintln!();
        let seconds = started.elapsed().as_secs_f64().max(1e-9);
        println!(
            "wrote a bag of {} depth frames, {} IMU samples ({:.2} s of data, in front of {rock:?}) to {}: {} messages, {:.1} MB of messages, {:.1} MB on disk",
            summary.frames,
            summary.imu_samples,
            summary.duration_s,
            summary.bag.file.display(),
            summary.bag.messages,
            summary.bag.payload_bytes as f64 / 1e6,
            summary.bag.file_bytes as f64 / 1e6
        );
        println!(
            "record: {:.2} s, {:.1} frames/s, {:.1} MB/s of messages ({} compression)",
            seconds,
            summary.frames as f64 / seconds,
            summary.bag.payload_bytes as f64 / 1e6 / seconds,
            args.compression
        );
    }
    Ok(())
}

fn scene(args: ConfigArgs) -> anyhow::Result<()> {
    let sim = Simulator::new(load(&args)?)?;
    println!("{}", serde_json::to_string_pretty(&terrain_sim::record::scene_json(&sim))?);
    Ok(())
}

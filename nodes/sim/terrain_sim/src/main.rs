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
#[command(
    name = "terrain_sim",
    version,
    about = "Rough-terrain simulator: rocks on a table or your own terrain (heightmap PNG, PCD/PLY cloud), a Carmine-like depth camera and an IMU"
)]
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
    /// groundtruth.txt, intrinsics.json, scene.json; with `--terrain` also terrain.json +
    /// terrain_heights.f32) and/or a rosbag2 MCAP bag (`--mcap`), both readable by `patch_mapper replay`.
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
    terrain: TerrainArgs,
    #[command(flatten)]
    config: ConfigArgs,
}

/// Bring-your-own terrain and the camera path over it (each flag sets a config key).
#[derive(clap::Args, Debug, Default)]
struct TerrainArgs {
    /// Terrain file instead of the rock scene (`scene.terrain.path`): a heightmap `.png` (8- or
    /// 16-bit grey, grey+alpha, RGB or RGBA; column → +x, top of the image → +y) or a point cloud
    /// `.pcd` (DATA ascii, binary, binary_compressed) / `.ply` (ascii, binary_little_endian) in metres,
    /// z up, gridded into a heightfield. Its exact ground truth is written next to the data
    /// (terrain.json + terrain_heights.f32).
    #[arg(long, value_name = "FILE")]
    terrain: Option<PathBuf>,
    /// Heightmap: metres between pixel centres (`scene.terrain.metres_per_pixel`; default 0.04).
    #[arg(long, value_name = "M")]
    metres_per_pixel: Option<f64>,
    /// Heightmap: heights (m) of grey level 0 and of the largest level, `MIN,MAX`
    /// (`scene.terrain.height_min_m`, `height_max_m`; default 0,1).
    #[arg(long, value_name = "MIN,MAX", value_parser = parse_pair, allow_hyphen_values = true)]
    height_range: Option<[f64; 2]>,
    /// Point cloud: grid spacing (m) of the heightfield its points are gridded into
    /// (`scene.terrain.cloud_resolution_m`; default 0.02).
    #[arg(long, value_name = "M")]
    cloud_resolution: Option<f64>,
    /// Camera path through waypoints `X,Y;X,Y;...` (m, world) instead of a straight walk (`path.waypoints_m`).
    #[arg(long, value_name = "X,Y;X,Y;...", allow_hyphen_values = true)]
    waypoints: Option<String>,
    /// Straight walk: start `X,Y` (m) (`path.start_m`; default 0.5 m inside the terrain's −x edge, halfway along y).
    #[arg(long, value_name = "X,Y", value_parser = parse_pair, allow_hyphen_values = true)]
    start: Option<[f64; 2]>,
    /// Straight walk: heading (deg, 0 = +x, counter-clockwise; `path.heading_deg`).
    #[arg(long, value_name = "DEG", allow_hyphen_values = true)]
    heading: Option<f64>,
    /// Distance walked per camera frame (m; `path.step_per_frame_m`; default 0.005 = 0.15 m/s at 30 Hz).
    #[arg(long, value_name = "M")]
    step: Option<f64>,
    /// Camera height above the smoothed ground (m; `path.camera_height_m`; default 0.45).
    #[arg(long, value_name = "M")]
    camera_height: Option<f64>,
    /// Camera pitch below the horizon (deg; `path.pitch_deg`; default 45).
    #[arg(long, value_name = "DEG", allow_hyphen_values = true)]
    pitch: Option<f64>,
    /// Walk the camera path in the rock scene too (`path.enabled`; a terrain scene always walks).
    #[arg(long)]
    walk: bool,
}

/// `A,B` as two numbers.
fn parse_pair(text: &str) -> Result<[f64; 2], String> {
    let values: Vec<f64> = text
        .split(',')
        .map(|v| v.trim().parse::<f64>().map_err(|_| format!("{v:?} in {text:?} is not a number")))
        .collect::<Result<_, _>>()?;
    match values.as_slice() {
        [a, b] if a.is_finite() && b.is_finite() => Ok([*a, *b]),
        _ => Err(format!("{text:?}: expected two finite numbers A,B")),
    }
}

impl TerrainArgs {
    /// Applies the flags to the config.
    fn apply(&self, config: &mut SimConfig) -> anyhow::Result<()> {
        let terrain = &mut config.scene.terrain;
        if let Some(path) = &self.terrain {
            terrain.path = path.clone();
        }
        if let Some(m) = self.metres_per_pixel {
            terrain.metres_per_pixel = m;
        }
        if let Some([min, max]) = self.height_range {
            (terrain.height_min_m, terrain.height_max_m) = (min, max);
        }
        if let Some(m) = self.cloud_resolution {
            terrain.cloud_resolution_m = m;
        }
        let path = &mut config.path;
        if let Some(text) = &self.waypoints {
            path.waypoints_m = text
                .split(';')
                .filter(|p| !p.trim().is_empty())
                .map(parse_pair)
                .collect::<Result<_, _>>()
                .map_err(|e| anyhow::anyhow!("--waypoints: {e}"))?;
            anyhow::ensure!(!path.waypoints_m.is_empty(), "--waypoints: no waypoint in {text:?}");
        }
        if let Some(start) = self.start {
            path.start_m = Some(start);
        }
        if let Some(heading) = self.heading {
            path.heading_deg = heading;
        }
        if let Some(step) = self.step {
            path.step_per_frame_m = step;
        }
        if let Some(height) = self.camera_height {
            path.camera_height_m = height;
        }
        if let Some(pitch) = self.pitch {
            path.pitch_deg = pitch;
        }
        path.enabled |= self.walk;
        Ok(())
    }
}

fn main() -> std::process::ExitCode {
    // Before anything else runs: a binary built for another CPU would stop at its first unknown instruction.
    if let Err(err) = patchwalk_ros::cpu::check() {
        eprintln!("terrain_sim: {err}");
        return std::process::ExitCode::from(1);
    }
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
    args.terrain.apply(&mut config)?;
    let started = std::time::Instant::now();
    let sim = Simulator::new(config)?;
    let rock = match (&sim.scene.terrain, &sim.path) {
        (Some(terrain), _) => {
            let [[x0, y0], [x1, y1]] = terrain.extent_m();
            println!(
                "terrain {}: {} × {} samples at {} m ({x0:.2}..{x1:.2} × {y0:.2}..{y1:.2} m, heights {:.3}..{:.3} m), loaded in {:.2} s",
                sim.config.scene.terrain.path.display(),
                terrain.columns(),
                terrain.rows(),
                terrain.resolution_m(),
                terrain.z_range_m()[0],
                terrain.z_range_m()[1],
                started.elapsed().as_secs_f64()
            );
            "the terrain".to_string()
        }
        (None, Some(_)) => "the camera path".to_string(),
        (None, None) => sim.scene.rocks.get(sim.config.start_rock).map(|r| r.name.clone()).unwrap_or_else(|| "?".into()),
    };
    if let Some(out_dir) = &args.out_dir {
        let started = std::time::Instant::now();
        let summary = terrain_sim::record::record(&sim, out_dir, args.frames, |i| {
            if (i + 1) % 30 == 0 {
                eprint!("\rterrain_sim record: {}/{} frames", i + 1, args.frames);
            }
        })
        .with_context(|| format!("recording into {}", out_dir.display()))?;
        eprintln!();
        let seconds = started.elapsed().as_secs_f64().max(1e-9);
        println!(
            "wrote {} depth frames, {} IMU samples ({:.2} s of data, in front of {rock:?}) to {} in {:.1} s ({:.1} frames/s)",
            summary.frames,
            summary.imu_samples,
            summary.duration_s,
            out_dir.display(),
            seconds,
            summary.frames as f64 / seconds
        );
        if sim.scene.terrain.is_some() {
            println!("terrain ground truth: {}", out_dir.join(terrain_sim::scene::ground_truth::DESCRIPTOR_FILE).display());
        }
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
        // The terrain's ground truth next to the bag: inside a bag directory, else in `<name>_terrain/`.
        let truth_dir = match &target {
            terrain_sim::record_bag::BagTarget::Directory(dir) => dir.clone(),
            terrain_sim::record_bag::BagTarget::File(file) => {
                file.with_file_name(format!("{}_terrain", file.file_stem().and_then(|s| s.to_str()).unwrap_or("bag")))
            }
        };
        if sim.scene.terrain.is_some() {
            std::fs::create_dir_all(&truth_dir).with_context(|| format!("creating {}", truth_dir.display()))?;
            terrain_sim::record::write_terrain_ground_truth(&sim, &truth_dir)?;
            println!("terrain ground truth: {}", truth_dir.join(terrain_sim::scene::ground_truth::DESCRIPTOR_FILE).display());
        }
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

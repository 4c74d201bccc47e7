//! `patch_mapper` binary: the ROS 2 perception node (`patch_mapper run`, the default) and the offline
//! tools users reach for first (`fit`, `map`, `track`, `calibrate-imu`, `replay`,
//! `footholds`).

mod cli;
mod ros;

use clap::{Parser, Subcommand};

#[derive(Parser)]
#[command(name = "patch_mapper", version, about = "patchwalk perception: depth + IMU -> bounded curved patches")]
struct Cli {
    #[command(subcommand)]
    command: Option<Command>,
}

#[derive(Subcommand)]
enum Command {
    /// Run the ROS 2 node (default when no subcommand is given).
    Run(ros::RunArgs),
    /// Fit one patch to a point file and print it as JSON.
    Fit(cli::fit::FitArgs),
    /// Map patches in depth frames offline (TUM dir, PNG dir + intrinsics, or one PNG).
    Map(cli::map::MapArgs),
    /// Track the camera through a dataset with TSDF fusion + ICP; write trajectory and pictures.
    Track(cli::track::TrackArgs),
    /// Calibrate the IMU->camera rotation from a dataset with a dominant horizontal plane.
    CalibrateImu(cli::calibrate_imu::CalibrateImuArgs),
    /// Run the node's whole pipeline (fusion, tracking, birds-eye mapping) offline over a dataset.
    Replay(cli::replay::ReplayArgs),
    /// Footholds: learned prediction from one depth image and the tilt (label, train, eval) and coarse route planning over them (plan).
    Footholds(cli::footholds::FootholdsArgs),
}

fn main() -> std::process::ExitCode {
    // Before anything else runs: a binary built for another CPU would stop at its first unknown instruction.
    if let Err(err) = patchwalk_ros::cpu::check() {
        eprintln!("patch_mapper: error: {err}");
        return std::process::ExitCode::from(1);
    }
    // `--ros-args ...` (what `ros2 run`/`ros2 launch` append) is taken out before the options.
    let (cli, ros_args) = match patchwalk_ros::node::parse_command_line::<Cli>() {
        Ok(parsed) => parsed,
        Err(err) => {
            eprintln!("patch_mapper: error: {err}");
            return std::process::ExitCode::from(2);
        }
    };
    let result = match cli.command {
        // No subcommand (what launch_ros runs): the node.
        None | Some(Command::Run(_)) => {
            let mut args = match cli.command {
                Some(Command::Run(args)) => args,
                _ => ros::RunArgs::default(),
            };
            args.node.ros = ros_args;
            ros::run(args)
        }
        Some(Command::Fit(args)) => cli::fit::run(args),
        Some(Command::Map(args)) => cli::map::run(args),
        Some(Command::Track(args)) => cli::track::run(args),
        Some(Command::CalibrateImu(args)) => cli::calibrate_imu::run(args),
        Some(Command::Replay(args)) => cli::replay::run(args),
        Some(Command::Footholds(args)) => cli::footholds::run(args),
    };
    match result {
        Ok(()) => std::process::ExitCode::SUCCESS,
        Err(err) => {
            eprintln!("patch_mapper: error: {err:#}");
            std::process::ExitCode::FAILURE
        }
    }
}

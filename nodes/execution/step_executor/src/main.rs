//! `step_executor` binary: the ROS 2 execution node (`step_executor run`, the default) and the
//! simulated MX-28 servo chain on a pty (`step_executor sim-bus`), and ROBOTIS action file pages
//! imported into and exported from the motion library (`import-motion`, `export-motion`).

mod cli;
mod ros;

use clap::{Parser, Subcommand};

#[derive(Parser)]
#[command(name = "step_executor", version, about = "patchwalk execution: patch -> trained footstep motion -> 12 MX-28 servos")]
struct Cli {
    #[command(subcommand)]
    command: Option<Command>,
}

#[derive(Subcommand)]
enum Command {
    /// Run the ROS 2 node (default when no subcommand is given).
    Run(ros::RunArgs),
    /// Start a simulated MX-28 (Protocol 2.0) servo chain on a pty and print its device path.
    SimBus(cli::sim_bus::SimBusArgs),
    /// Add one page of a ROBOTIS action file (DARwIn-OP motion_4096.bin, OP3 motion_4095.bin) to the
    /// motion library as a new motion.
    ImportMotion(cli::import_motion::ImportMotionArgs),
    /// Write a library motion as one page of a ROBOTIS action file (existing or new).
    ExportMotion(cli::export_motion::ExportMotionArgs),
}

fn main() -> std::process::ExitCode {
    // Before anything else runs: a binary built for another CPU would stop at its first unknown instruction.
    if let Err(err) = patchwalk_ros::cpu::check() {
        eprintln!("step_executor: error: {err}");
        return std::process::ExitCode::from(1);
    }
    // `--ros-args ...` (what `ros2 run`/`ros2 launch` append) is taken out before the options.
    let (cli, ros_args) = match patchwalk_ros::node::parse_command_line::<Cli>() {
        Ok(parsed) => parsed,
        Err(err) => {
            eprintln!("step_executor: error: {err}");
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
        Some(Command::SimBus(args)) => cli::sim_bus::run(args),
        Some(Command::ImportMotion(args)) => cli::import_motion::run(args),
        Some(Command::ExportMotion(args)) => cli::export_motion::run(args),
    };
    match result {
        Ok(()) => std::process::ExitCode::SUCCESS,
        Err(err) => {
            eprintln!("step_executor: error: {err:#}");
            std::process::ExitCode::FAILURE
        }
    }
}

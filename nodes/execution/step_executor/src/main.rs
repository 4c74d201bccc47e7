//! `step_executor` binary: the ROS 2 execution node (`step_executor run`, the default) and the
//! simulated MX-28 servo chain on a pty (`step_executor sim-bus`).

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
}

fn main() -> std::process::ExitCode {
    let cli = Cli::parse();
    let result = match cli.command {
        None => ros::run(ros::RunArgs::default()),
        Some(Command::Run(args)) => ros::run(args),
        Some(Command::SimBus(args)) => cli::sim_bus::run(args),
    };
    match result {
        Ok(()) => std::process::ExitCode::SUCCESS,
        Err(err) => {
            eprintln!("step_executor: error: {err:#}");
            std::process::ExitCode::FAILURE
        }
    }
}

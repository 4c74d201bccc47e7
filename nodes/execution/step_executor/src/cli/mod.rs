//! Non-ROS subcommands of the `step_executor` binary.
pub mod sim_bus;

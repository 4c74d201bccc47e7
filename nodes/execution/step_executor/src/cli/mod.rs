//! Non-ROS subcommands of the `step_executor` binary.
pub mod export_motion;
pub mod import_motion;
pub mod motion_files;
pub mod sim_bus;

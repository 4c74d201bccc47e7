//! Offline subcommands of the `patch_mapper` binary.
pub mod calibrate_imu;
pub mod fit;
pub mod map;
pub mod replay;
pub mod track;

//! patch_mapper library: the node's conversions of what it receives from the world, so they can be
//! driven byte for byte outside the ROS loop.
//!
//! - [`convert`]: `sensor_msgs/Image`, `CameraInfo` and `Imu` into the pipeline's types, every
//!   malformed message a typed error.
//! - [`bag_input`]: a rosbag2 MCAP bag as the input of `patch_mapper replay` (two streaming passes).
//! - [`foothold_points`]: predicted footholds lifted into the fixed frame with their surface normals
//!   (the node's foothold stage and `bench_learned_seeds`).
//! - [`inputs`]: serialized payloads as they arrive on the wire (and bags as bytes), through the same decoder the node's
//!   subscriptions use, the conversions and (for [`inputs::pipeline_frame`]) the per-frame pipeline;
//!   the fuzz targets in `nodes/fuzz` and the regression tests over `tests/data/fuzz/` call them.

#[path = "cli/bag_input.rs"]
pub mod bag_input;
#[path = "ros/convert.rs"]
pub mod convert;
#[path = "ros/foothold_points.rs"]
pub mod foothold_points;
pub mod inputs;

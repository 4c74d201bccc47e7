//! patch_mapper library: the node's conversions of what it receives from the world, so they can be
//! driven byte for byte outside the ROS loop.
//!
//! - [`convert`]: `sensor_msgs/Image`, `CameraInfo` and `Imu` into the pipeline's types, every
//!   malformed message a typed error.
//! - [`inputs`]: serialized payloads as they arrive on the wire, through the same decoder the node's
//!   subscriptions use, the conversions and (for [`inputs::pipeline_frame`]) the per-frame pipeline;
//!   the fuzz targets in `nodes/fuzz` and the regression tests over `tests/data/fuzz/` call them.

#[path = "ros/convert.rs"]
pub mod convert;
pub mod inputs;

//! Rust side of the `patchwalk_msgs` ROS 2 interface package.
//!
//! - [`msg`], [`srv`], [`action`]: our interfaces. The `.msg`/`.srv`/`.action` files next to this crate are the single source
//!   of truth; the structs mirror them field by field (the CDR wire format is positional) and
//!   `rust/tests/interface_files.rs` parses the files and checks every struct against them.
//! - [`builtin_interfaces`], [`std_msgs`], [`geometry_msgs`], [`sensor_msgs`], [`std_srvs`],
//!   [`visualization_msgs`], [`diagnostic_msgs`], [`tf2_msgs`] (`/tf`, `/tf_static`), [`rosgraph_msgs`]
//!   (`/clock`), [`nav_msgs`] (`Path`): the standard ROS 2 Jazzy types, re-exported from
//!   `ros2-interfaces-jazzy-serde` ([`sensor_msgs`] with its own `Image` and `PointCloud2`, whose byte
//!   arrays are (de)serialized as one block: the same wire format, checked against the upstream types).
//! - [`interface`]: ROS 2 type names of every type (`RosMessage`, `RosService`, `RosAction`).

pub mod action;
pub mod interface;
pub mod msg;
pub mod sensor_msgs;
pub mod srv;

pub use ros2_interfaces_jazzy_serde::{
    builtin_interfaces, diagnostic_msgs, geometry_msgs, nav_msgs, rcl_interfaces, rosgraph_msgs, std_msgs, std_srvs, tf2_msgs,
    visualization_msgs,
};

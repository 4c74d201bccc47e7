//! The ROS 2 plumbing shared by the patchwalk nodes (over ros2-client/rustdds, no ROS install):
//!
//! - [`node`]: the participant on `ROS_DOMAIN_ID` (loopback only by default), QoS presets, typed
//!   endpoints, the non-blocking `drain`/`serve`/`publish` helpers, shutdown on SIGINT/SIGTERM,
//!   tracing, and [`node::RateLimitedLog`] for bad input that must not flood the log.
//! - [`params`]: YAML configuration files (plain or ROS 2 format) with `--param key=value`
//!   overrides, unknown keys named.
//! - [`ros_args`]: the ROS 2 command line (`--ros-args -r/-p/--params-file/--log-level ...`).
//! - [`names`]: topic and service names resolved relative to the node (namespace, `~`, remaps).
//! - [`declared`]: the node's config as declared ROS 2 parameters (dotted keys, typed, validated).
//! - [`param_server`]: the rcl parameter services over them (`ros2 param list/get/set/describe`).
//! - [`process`]: process CPU time for the benchmarks.
//! - [`cpu`]: whether the CPU has the instructions the binary was compiled for (checked at start).
//! - [`memory`]: free heap pages handed back to the system (periodic glibc trim).
//! - [`wait`]: the loop's wake-up on input readiness (no polling between inputs).
//! - [`patch_msg`]: the Surface Patch Library's patch on the wire, validated where it enters.
//! - [`security`]: DDS Security from an SROS2 keystore, configured by `ROS_SECURITY_*` as rcl does.
//! - [`share`]: where a node finds its URDF and YAML files: working directory, package share
//!   directory (ament index, for a colcon install), source tree.
//! - [`tf_buffer`]: a transform tree (static + dynamic with interpolation), `target_from_source`
//!   lookups at a stamp; [`tf`]: its `/tf` + `/tf_static` listener and broadcasters (tf2_ros QoS).
//! - [`diagnostics`]: `/diagnostics` (REP-107) statuses and arrays.
//! - [`rosout`]: the node's log lines on `/rosout` (`rcl_interfaces/msg/Log`).
//! - [`clock`]: the node clock (wall, or `/clock` with `use_sim_time`) and a `/clock` publisher.
//! - [`wire`]: a serialized payload (encapsulation header + CDR) decoded as the nodes' readers decode it.
//!
//! The `patchwalk_interface_echo` binary republishes every patchwalk_msgs type, for wire checks
//! against other ROS 2 implementations.

pub mod clock;
pub mod cpu;
pub mod declared;
pub mod diagnostics;
pub mod memory;
pub mod names;
pub mod node;
pub mod param_server;
pub mod params;
pub mod patch_msg;
pub mod process;
pub mod ros_args;
pub mod rosout;
pub mod security;
pub mod share;
pub mod tf;
pub mod tf_buffer;
pub mod wait;
pub mod wire;

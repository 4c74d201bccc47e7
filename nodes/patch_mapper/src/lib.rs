//! patch_mapper: ROS-free perception library of patchwalk.
//!
//! Depth frames + IMU -> (fusion, tracking, raycast) -> (acquire, preprocess, saliency, seeds,
//! neighbourhood, fit, validate) -> patch map. The ROS 2 wiring lives in the binary (`src/ros/`).
//! Papers are cited as IROS (curved patches with quantified uncertainty) and J (patch mapping and
//! tracking for biped foot placement).

// Shared camera model and data readers.
pub mod camera;
pub mod dataset;

// Patch core (issue: curved patch core).
pub mod fit;
pub mod geometry;
pub mod patch;
pub mod points_io;
pub mod sensor;
pub mod validate;

// Single-frame mapping stages (issue: patch mapping).
pub mod acquire;
pub mod mapper;
pub mod neighbourhood;
pub mod patch_map;
pub mod preprocess;
pub mod render;
pub mod saliency;
pub mod seeds;

// Fusion and tracking (issue: moving-volume TSDF fusion).
pub mod calibration;
pub mod fusion;
pub mod patch_tracking;
// Per-frame perception pipeline of the node (issue 7).
pub mod pipeline;
pub mod raycast;
pub mod tracking;
pub mod volume;

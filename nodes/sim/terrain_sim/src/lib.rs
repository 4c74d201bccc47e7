//! terrain_sim: ROS-free rough-terrain simulator library of patchwalk.
//!
//! `scene` (table + rocks, J 6.3 Fig. 10) → `motion` (robot/head pose in front of a rock) →
//! `camera` (Carmine 1.09-like depth camera with Murray–Little noise, J 2.1) and `imu` (100 Hz
//! gravity + noise, J 2.2) → `record` (TUM-format dataset) and `record_bag` (rosbag2 MCAP bag); `walk` moves the
//! robot along the table in steps (tracking tests and `bench_tracking`). The ROS 2 node is in the binary.
//!
//! Bring-your-own terrain: `scene::terrain` loads a heightmap PNG or a PCD/PLY point cloud into a
//! `scene::Heightfield` with exact ground truth (`height_at`, `normal_at`, ray intersection;
//! `scene::ground_truth` writes and re-reads it next to a dataset), and `camera_path` walks the
//! camera over it like a small biped.

pub mod camera;
pub mod camera_path;
pub mod config;
pub mod imu;
pub mod motion;
pub mod record;
pub mod record_bag;
pub mod scene;
pub mod sim;
pub mod track_walk;
pub mod walk;

//! Patch mapping of patchwalk's perception (J 3–5): from one depth frame (or the fused birds-eye
//! raycast) to a map of validated foothold patches around the robot.
//!
//! Stages in the order of J 3.2: [`acquire`] (organized cloud, gravity) → [`preprocess`]
//! (bilateral filter, normals) → [`saliency`] (hiking saliency, J 3.1, with [`depth_edges`] keeping foot windows off depth discontinuities and [`window_flatness`] off steps and bumps) → [`seeds`] (J 3.2.1
//! steps 1–10) → [`neighbourhood`] (r-balls, nf subsets) → fit and validate (the Surface Patch
//! Library; [`foot_column`] gathers the foot disc's terrain for its edge test) → [`patch_map`] (J 4.6),
//! [`patch_fusion`] (re-observed patches fused with their Σ) and [`patch_tracking`] (J 5.2). [`mapper`] runs one frame,
//! [`pipeline`] the node's per-frame sequence with fusion and tracking; [`render`] draws pictures;
//! [`rig`] turns camera height and pitch into the fixation point and seed area; [`record`] is the one JSON record of a patch and its verdict that the CLIs write.
//!
//! ROS-free; the `patch_mapper` node wraps it.

pub mod acquire;
pub mod depth_edges;
pub mod foot_column;
pub mod mapper;
pub mod neighbourhood;
pub mod patch_fusion;
pub mod patch_map;
pub mod patch_tracking;
pub mod pipeline;
pub mod preprocess;
pub mod record;
pub mod render;
pub mod rig;
pub mod saliency;
pub mod seeds;
pub mod window_flatness;

//! Rust structs of `patchwalk_msgs/msg/*` — field for field, in file order (the CDR wire format is
//! positional). `rust/tests/interface_files.rs` parses the `.msg` files and checks these structs against
//! them, so a renamed, reordered or retyped field fails the tests instead of corrupting values on the wire.

use serde::{Deserialize, Serialize};

use crate::builtin_interfaces::msg::Time;
use crate::geometry_msgs::msg::Pose;
use crate::std_msgs::msg::Header;

/// `patchwalk_msgs/Patch`: one bounded curved surface patch by its minimal parameters (IROS Table I).
#[derive(Debug, Clone, PartialEq, Default, Serialize, Deserialize)]
pub struct Patch {
    pub id: u32,
    pub surface: u8,
    pub boundary: u8,
    pub curvatures: Vec<f64>,
    pub boundary_params: Vec<f64>,
    pub rotation: [f64; 3],
    pub center: [f64; 3],
    pub pose: Pose,
    pub covariance: Vec<f64>,
    pub residual: f64,
    pub num_points: u32,
    pub first_seen: Time,
    pub last_seen: Time,
}

impl Patch {
    pub const ELLIPTIC_PARABOLOID: u8 = 0;
    pub const HYPERBOLIC_PARABOLOID: u8 = 1;
    pub const CYLINDRIC_PARABOLOID: u8 = 2;
    pub const CIRCULAR_PARABOLOID: u8 = 3;
    pub const PLANE: u8 = 4;
    pub const SPHERE: u8 = 5;
    pub const CIRCULAR_CYLINDER: u8 = 6;

    pub const ELLIPSE: u8 = 0;
    pub const CIRCLE: u8 = 1;
    pub const RECTANGLE: u8 = 2;
    pub const QUADRILATERAL: u8 = 3;

    /// Upper bounds of the bounded sequences (`float64[<=2] curvatures`, `float64[<=5] boundary_params`).
    pub const MAX_CURVATURES: usize = 2;
    pub const MAX_BOUNDARY_PARAMS: usize = 5;
}

/// `patchwalk_msgs/PatchArray`: the patch map in the gravity-aligned map frame.
#[derive(Debug, Clone, PartialEq, Default, Serialize, Deserialize)]
pub struct PatchArray {
    pub header: Header,
    pub camera_pose: Pose,
    pub patches: Vec<Patch>,
}

/// `patchwalk_msgs/MapperStatus`: periodic diagnostics of patch_mapper.
#[derive(Debug, Clone, PartialEq, Default, Serialize, Deserialize)]
pub struct MapperStatus {
    pub stamp: Time,
    pub frames_received: u64,
    pub frames_processed: u64,
    pub frames_skipped: u64,
    pub frames_rejected: u64,
    pub camera_infos_received: u64,
    pub imu_received: u64,
    pub patches_in_map: u32,
    pub last_error: String,
    pub timing_names: Vec<String>,
    pub timing_ms: Vec<f64>,
}

/// `patchwalk_msgs/ExecutorStatus`: periodic state of step_executor.
#[derive(Debug, Clone, PartialEq, Default, Serialize, Deserialize)]
pub struct ExecutorStatus {
    pub stamp: Time,
    pub state: u8,
    pub armed: bool,
    pub torque_enabled: bool,
    pub current_motion: String,
    pub keyframe_index: u32,
    pub last_match: String,
    pub fault_servo_id: u8,
    pub last_fault: String,
    pub library_size: u32,
    pub recorded_keyframes: u32,
}

impl ExecutorStatus {
    pub const STATE_IDLE: u8 = 0;
    pub const STATE_PLAYING: u8 = 1;
    pub const STATE_HOLDING_FAULT: u8 = 2;
    pub const STATE_ESTOPPED: u8 = 3;
}

/// `patchwalk_msgs/MotionSummary`: one trained motion as listed by `list_motions`.
#[derive(Debug, Clone, PartialEq, Default, Serialize, Deserialize)]
pub struct MotionSummary {
    pub name: String,
    pub surface: u8,
    pub boundary: u8,
    pub keyframe_count: u32,
    pub duration: f64,
}

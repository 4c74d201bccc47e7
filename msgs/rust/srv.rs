//! Rust structs of `patchwalk_msgs/srv/*` (request and response of each service, in file order) and a
//! marker type per service implementing [`crate::interface::RosService`].
//! Checked against the `.srv` files by `rust/tests/interface_files.rs`.

use serde::{Deserialize, Serialize};

use crate::geometry_msgs::msg::Point;
use crate::msg::{MotionSummary, Patch};

/// `patchwalk_msgs/srv/RecordKeyframe`: append the servos' present positions as a keyframe.
pub struct RecordKeyframe;

#[derive(Debug, Clone, PartialEq, Default, Serialize, Deserialize)]
pub struct RecordKeyframeRequest {
    pub duration: f64,
    pub pause: f64,
}

#[derive(Debug, Clone, PartialEq, Default, Serialize, Deserialize)]
pub struct RecordKeyframeResponse {
    pub success: bool,
    pub message: String,
    pub keyframe_index: u32,
    pub positions: [f64; 12],
}

/// `patchwalk_msgs/srv/SelectTarget`: choose the training target patch from the map.
pub struct SelectTarget;

#[derive(Debug, Clone, PartialEq, Default, Serialize, Deserialize)]
pub struct SelectTargetRequest {
    pub mode: u8,
    pub point: Point,
    pub radius: f64,
}

impl SelectTargetRequest {
    pub const MODE_NEAREST_POINT: u8 = 0;
    pub const MODE_FIT_AT_POINT: u8 = 1;
}

#[derive(Debug, Clone, PartialEq, Default, Serialize, Deserialize)]
pub struct SelectTargetResponse {
    pub success: bool,
    pub message: String,
    pub patch: Patch,
}

/// `patchwalk_msgs/srv/SaveMotion`: save the motion being trained under a name.
pub struct SaveMotion;

#[derive(Debug, Clone, PartialEq, Default, Serialize, Deserialize)]
pub struct SaveMotionRequest {
    pub name: String,
}

#[derive(Debug, Clone, PartialEq, Default, Serialize, Deserialize)]
pub struct SaveMotionResponse {
    pub success: bool,
    pub message: String,
}

/// `patchwalk_msgs/srv/ListMotions`: list the library.
pub struct ListMotions;

/// Empty request. ROS 2 puts a one-byte `structure_needs_at_least_one_member` field into empty
/// structs on the wire; this field mirrors it so the CDR encoding matches rclpy/rclcpp.
#[derive(Debug, Clone, PartialEq, Default, Serialize, Deserialize)]
pub struct ListMotionsRequest {
    pub structure_needs_at_least_one_member: u8,
}

#[derive(Debug, Clone, PartialEq, Default, Serialize, Deserialize)]
pub struct ListMotionsResponse {
    pub success: bool,
    pub message: String,
    pub motions: Vec<MotionSummary>,
}

/// `patchwalk_msgs/srv/DeleteMotion`: remove a motion from the library.
pub struct DeleteMotion;

#[derive(Debug, Clone, PartialEq, Default, Serialize, Deserialize)]
pub struct DeleteMotionRequest {
    pub name: String,
}

#[derive(Debug, Clone, PartialEq, Default, Serialize, Deserialize)]
pub struct DeleteMotionResponse {
    pub success: bool,
    pub message: String,
}

/// `patchwalk_msgs/srv/PlayMotion`: play a motion by name.
pub struct PlayMotion;

#[derive(Debug, Clone, PartialEq, Default, Serialize, Deserialize)]
pub struct PlayMotionRequest {
    pub name: String,
}

#[derive(Debug, Clone, PartialEq, Default, Serialize, Deserialize)]
pub struct PlayMotionResponse {
    pub success: bool,
    pub message: String,
}

/// `patchwalk_msgs/srv/RebootServos`: REBOOT servos (empty ids = the faulted ones) to recover from a fault.
pub struct RebootServos;

#[derive(Debug, Clone, PartialEq, Default, Serialize, Deserialize)]
pub struct RebootServosRequest {
    pub ids: Vec<u8>,
}

#[derive(Debug, Clone, PartialEq, Default, Serialize, Deserialize)]
pub struct RebootServosResponse {
    pub success: bool,
    pub message: String,
    pub rebooted: Vec<u8>,
}

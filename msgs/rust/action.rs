//! Rust structs of `patchwalk_msgs/action/*` (goal, result and feedback of each action, in file
//! order) and a marker type per action implementing [`crate::interface::RosAction`].
//! Checked against the `.action` files by `rust/tests/interface_files.rs`.

use serde::{Deserialize, Serialize};

/// `patchwalk_msgs/action/PlayMotion`: play a trained motion with progress and a final outcome.
pub struct PlayMotion;

#[derive(Debug, Clone, PartialEq, Default, Serialize, Deserialize)]
pub struct PlayMotionGoal {
    pub name: String,
}

#[derive(Debug, Clone, PartialEq, Default, Serialize, Deserialize)]
pub struct PlayMotionResult {
    pub outcome: u8,
    pub fault_servo_id: u8,
    pub message: String,
}

impl PlayMotionResult {
    pub const OUTCOME_COMPLETED: u8 = 0;
    pub const OUTCOME_FAULTED: u8 = 1;
    pub const OUTCOME_CANCELLED: u8 = 2;
    pub const OUTCOME_REFUSED: u8 = 3;
}

#[derive(Debug, Clone, PartialEq, Default, Serialize, Deserialize)]
pub struct PlayMotionFeedback {
    pub keyframe_index: u32,
    pub keyframe_count: u32,
    pub fraction_done: f32,
}

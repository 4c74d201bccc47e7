//! The robot model of patchwalk: URDF kinematics (forward kinematics of the leg chains, joint
//! limits, `base_link → camera` and foot frames) and the RPBP joint order. ROS-free; used by the step
//! executor (patches relative to the robot, limits checked before motion) and the simulator (the
//! camera moved by the joints).

pub mod kinematics;

/// The RPBP robot description shipped with patchwalk (`urdf/rpbp.urdf`).
pub const RPBP_URDF: &str = include_str!("../../../../urdf/rpbp.urdf");

/// The RPBP leg joints in keyframe order, DARwIn-OP ID order (right before left, hip to ankle).
pub const DEFAULT_JOINTS: [&str; 12] = [
    "r_hip_yaw",
    "l_hip_yaw",
    "r_hip_roll",
    "l_hip_roll",
    "r_hip_pitch",
    "l_hip_pitch",
    "r_knee",
    "l_knee",
    "r_ankle_pitch",
    "l_ankle_pitch",
    "r_ankle_roll",
    "l_ankle_roll",
];

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

#[cfg(test)]
mod tests {
    /// Every physical link of the shipped model has a visual and a collision shape (RViz shows the
    /// robot); only the frames without a body (optical frame, soles) have none.
    #[test]
    fn the_rpbp_model_has_visuals_and_collisions() {
        let robot = urdf_rs::read_from_string(super::RPBP_URDF).unwrap();
        for link in &robot.links {
            let frame_only = ["camera_optical", "left_foot", "right_foot"].contains(&link.name.as_str());
            assert_eq!(link.visual.is_empty(), frame_only, "{}: visual", link.name);
            assert_eq!(link.collision.is_empty(), frame_only, "{}: collision", link.name);
        }
        assert_eq!(robot.materials.len(), 3);
        crate::kinematics::RobotModel::from_urdf_str(super::RPBP_URDF).unwrap();
    }

    /// The keyframe joints (the names step_executor publishes on /joint_states by default) are the
    /// model's movable joints, each once, with position limits; robot_state_publisher finds them all.
    #[test]
    fn every_keyframe_joint_is_a_limited_revolute_joint_of_the_model() {
        let robot = urdf_rs::read_from_string(super::RPBP_URDF).unwrap();
        let movable: Vec<&urdf_rs::Joint> = robot.joints.iter().filter(|j| !matches!(j.joint_type, urdf_rs::JointType::Fixed)).collect();
        assert_eq!(movable.len(), super::DEFAULT_JOINTS.len());
        for name in super::DEFAULT_JOINTS {
            let joint = movable.iter().find(|j| j.name == name).unwrap_or_else(|| panic!("{name} is not a movable joint"));
            assert!(matches!(joint.joint_type, urdf_rs::JointType::Revolute), "{name}: {:?}", joint.joint_type);
            assert!(joint.limit.lower < joint.limit.upper, "{name}: limits {} .. {}", joint.limit.lower, joint.limit.upper);
        }
    }
}

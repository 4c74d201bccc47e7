//! step_executor and TF: `/robot_description` (the URDF text, for robot_state_publisher and RViz),
//! and patch maps moved into `base_link` through the TF tree when it has the map's frame
//! (`base_link ← <PatchArray frame_id>` at the map's stamp: the mapper's `odom → base_link` below
//! the robot tree), through the node's own URDF kinematics and `PatchArray.camera_pose` otherwise.

use std::path::Path;

use nalgebra::Isometry3;
use patchwalk_msgs::builtin_interfaces::msg::Time;
use patchwalk_msgs::std_msgs::msg::String as StringMsg;
use patchwalk_ros::clock::stamp_ns;
use patchwalk_ros::node::{self, NodeError, RateLimitedLog, RosNode};
use patchwalk_ros::tf_buffer::{LookupTime, TfBuffer};
use ros2_client::qos::{Durability, History, QosProfile, WhenFull};
use ros2_client::Publisher;

/// The URDF for robot_state_publisher and RViz (their default topic).
pub const ROBOT_DESCRIPTION_TOPIC: &str = "/robot_description";

/// The robot's root frame, which patches are matched in.
pub const BASE_FRAME: &str = "base_link";

/// robot_state_publisher's profile: reliable, transient local, keep last 1 (a late RViz gets it).
pub fn robot_description_qos() -> QosProfile {
    QosProfile::publisher_default()
        .reliability_reliable(WhenFull::DEFAULT)
        .durability(Durability::TransientLocal)
        .history(History::KeepLast { depth: 1 })
}

/// The URDF text the node runs with: the file at `urdf_path`, else the built-in RPBP model (as the
/// runtime falls back to it).
pub fn urdf_text(urdf_path: &Path) -> String {
    step_executor::runtime::find_urdf(urdf_path)
        .and_then(|(path, _)| std::fs::read_to_string(path).ok())
        .unwrap_or_else(|| step_executor::runtime::BUILT_IN_URDF.to_string())
}

/// Publishes the URDF once (transient local keeps it for late subscribers).
pub fn publish_robot_description(ros: &mut RosNode, urdf: String) -> Result<Publisher<StringMsg>, NodeError> {
    let publisher = ros.publisher::<StringMsg>(&ros.relative(ROBOT_DESCRIPTION_TOPIC), robot_description_qos())?;
    node::publish(&publisher, ROBOT_DESCRIPTION_TOPIC, StringMsg { data: urdf }, &mut RateLimitedLog::default());
    Ok(publisher)
}

/// `base_from_map` from the TF tree at the map's stamp, when the tree connects the two frames there.
pub fn base_from_map(tf: &TfBuffer, map_frame: &str, stamp: &Time) -> Option<Isometry3<f64>> {
    if map_frame.is_empty() {
        return None;
    }
    tf.lookup(BASE_FRAME, map_frame, LookupTime::At(stamp_ns(stamp))).ok()
}

#[cfg(test)]
mod tests {
    use super::*;
    use nalgebra::{Translation3, UnitQuaternion};
    use patchwalk_robot_model::kinematics::RobotModel;

    #[test]
    fn the_map_is_moved_to_base_link_through_the_tree_at_its_stamp() {
        let mut tf = TfBuffer::default();
        let stamp = Time { sec: 10, nanosec: 0 };
        assert!(base_from_map(&tf, "odom", &stamp).is_none(), "no tree: the URDF path is used");
        let odom_from_base = Isometry3::from_parts(Translation3::new(0.3, 0.1, 0.0), UnitQuaternion::from_euler_angles(0.0, 0.0, 0.4));
        tf.set_dynamic("odom", "base_link", stamp_ns(&stamp), odom_from_base).unwrap();
        let base_from_odom = base_from_map(&tf, "odom", &stamp).unwrap();
        assert!((base_from_odom * odom_from_base).translation.vector.norm() < 1e-12);
        assert!(base_from_map(&tf, "odom", &Time { sec: 11, nanosec: 0 }).is_none(), "no transform at that stamp");
        assert!(base_from_map(&tf, "map", &stamp).is_none(), "a frame the tree does not have");
    }

    #[test]
    fn joint_state_names_are_the_urdf_joints_and_the_description_is_the_urdf() {
        let root = Path::new(env!("CARGO_MANIFEST_DIR")).join("../../..");
        let config: step_executor::config::StepExecutorConfig =
            patchwalk_ros::params::load_config(Some(&root.join("config/step_executor.yaml")), &[]).unwrap();
        let text = urdf_text(&root.join("urdf/rpbp.urdf"));
        let model = RobotModel::from_urdf_str(&text).unwrap();
        let names = config.joint_names();
        assert_eq!(names.len(), 12);
        for name in &names {
            assert!(model.joint_limits(name).unwrap().is_some(), "/joint_states name {name:?} is a movable URDF joint");
        }
        let movable_in_urdf = text.matches("type=\"revolute\"").count();
        assert_eq!(movable_in_urdf, names.len(), "every movable URDF joint is in /joint_states");
        assert_eq!(urdf_text(Path::new("/nonexistent.urdf")), step_executor::runtime::BUILT_IN_URDF);
        assert_eq!(robot_description_qos().durability, Durability::TransientLocal);
    }
}

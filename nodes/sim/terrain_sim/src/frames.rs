//! The simulated rig's mount on `/tf_static`, as a RealSense/Orbbec driver publishes its own:
//! `base_link → <camera frame>` (the camera of the lookdown pose, `Simulator::base_from_camera`, equal
//! to the URDF's `base_link → … → camera_optical` chain) and `<camera frame> → <imu frame>` (the
//! simulator's `imu.camera_from_imu_xyzw`, the URDF's `imu` rotation). The simulated accelerometer
//! sits at the camera centre (no lever arm), so the IMU translation is zero; the URDF places it 15 mm
//! above the camera body, which does not change the gravity direction the mapper uses.

use nalgebra::Isometry3;
use patchwalk_msgs::builtin_interfaces::msg::Time;
use patchwalk_msgs::geometry_msgs::msg::TransformStamped;
use patchwalk_ros::tf::transform_msg;
use terrain_sim::sim::Simulator;

/// The robot's root frame (REP-105).
pub const BASE_FRAME: &str = "base_link";

/// The static transforms of the rig, stamped `stamp` (the time they became valid).
pub fn mount_transforms(sim: &Simulator, stamp: Time) -> Vec<TransformStamped> {
    let node = &sim.config.node;
    let camera_from_imu = Isometry3::from_parts(nalgebra::Translation3::identity(), sim.imu.camera_from_imu);
    vec![
        transform_msg(BASE_FRAME, &node.camera_frame_id, stamp.clone(), &sim.base_from_camera),
        transform_msg(&node.camera_frame_id, &node.imu_frame_id, stamp, &camera_from_imu),
    ]
}

#[cfg(test)]
mod tests {
    use super::*;
    use patchwalk_robot_model::kinematics::RobotModel;
    use patchwalk_ros::tf::insert_message;
    use patchwalk_ros::tf_buffer::{LookupTime, TfBuffer};
    use terrain_sim::config::SimConfig;

    #[test]
    fn the_published_mount_is_the_urdf_one() {
        let sim = Simulator::new(SimConfig::default()).unwrap();
        let mut tf = TfBuffer::default();
        let msg = patchwalk_msgs::tf2_msgs::msg::TFMessage { transforms: mount_transforms(&sim, Time::default()) };
        assert!(insert_message(&mut tf, &msg, true).is_empty());
        let path = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("../../../urdf/rpbp.urdf");
        let urdf = RobotModel::from_file(&path).unwrap();
        let zero = patchwalk_robot_model::DEFAULT_JOINTS.iter().map(|j| ((*j).to_string(), 0.0)).collect();
        let urdf_base_from_optical = urdf.root_from_link("camera_optical", &zero).unwrap();
        let urdf_base_from_imu = urdf.root_from_link("imu", &zero).unwrap();
        let base_from_optical = tf.lookup("base_link", "camera_optical", LookupTime::Latest).unwrap();
        assert!((base_from_optical.translation.vector - urdf_base_from_optical.translation.vector).norm() < 1e-9);
        assert!(base_from_optical.rotation.angle_to(&urdf_base_from_optical.rotation) < 1e-9);
        let base_from_imu = tf.lookup("base_link", "imu", LookupTime::Latest).unwrap();
        assert!(base_from_imu.rotation.angle_to(&urdf_base_from_imu.rotation) < 1e-9, "IMU axes as in the URDF");
        // The optical → imu rotation is what patch_mapper needs as camera_from_imu.
        let optical_from_imu = tf.lookup("camera_optical", "imu", LookupTime::At(123)).unwrap();
        assert!(optical_from_imu.rotation.angle_to(&sim.imu.camera_from_imu) < 1e-12);
    }
}

//! patch_mapper and TF: the tracked pose goes out on `/tf` at the depth stamp, and the IMU mount
//! (`camera_from_imu`) comes in from `/tf_static`.
//!
//! The tracker's frame is fixed, gravity aligned (z up) and drifts slowly: REP-105's `odom` (the
//! default name of `ros.tf.fixed_frame`; `map` when nothing else provides one). When the robot's tree
//! has `base_link → <camera frame>` (the depth Image's `frame_id`), the node publishes
//! `odom → base_link = odom_from_camera · base_from_camera⁻¹`, as visual-odometry nodes do, so
//! robot_state_publisher's tree hangs below it; without a robot tree (a hand-held camera) it
//! publishes `odom → <camera frame>`. PatchArray, markers and the birds-eye cloud are in the fixed
//! frame.
//!
//! The IMU mount is looked up as `<camera frame> ← <imu frame>` (the Image's and the Imu's
//! `frame_id`s), as RealSense/Orbbec drivers publish it; until `/tf_static` has it, frames wait up to
//! `ros.tf.extrinsics_wait_s` after the first one, then `mapper.acquire.camera_from_imu` is used with
//! one warning.

use std::time::{Duration, Instant};

use nalgebra::{Isometry3, Rotation3};
use patchwalk_msgs::builtin_interfaces::msg::Time;
use patchwalk_msgs::geometry_msgs::msg::TransformStamped;
use patchwalk_ros::clock::stamp_ns;
use patchwalk_ros::tf::{transform_msg, SharedTf};
use patchwalk_ros::tf_buffer::{LookupTime, TfBuffer, TfError};
use serde::{Deserialize, Serialize};

/// What the node publishes on `/tf`.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum TfPublish {
    /// `fixed_frame → base_frame` when the tree has `base_frame → <camera frame>`, else
    /// `fixed_frame → <camera frame>`.
    Auto,
    /// Always `fixed_frame → <camera frame>` (ignore a robot tree).
    Camera,
    /// Nothing on `/tf` (another node owns the fixed frame's transform).
    Off,
}

/// `ros.tf` of the config.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct TfParams {
    /// The tracker's fixed, gravity-aligned frame (REP-105 `odom`; `map` allowed).
    pub fixed_frame: String,
    /// The robot's root frame looked up for `fixed_frame → base_frame`.
    pub base_frame: String,
    pub publish: TfPublish,
    /// Take `camera_from_imu` from `/tf_static` (`<camera frame> ← <imu frame>`) when it is there.
    pub extrinsics_from_tf: bool,
    /// How long after the first depth frame the node waits for that transform before falling back
    /// to `mapper.acquire.camera_from_imu` (s); frames in between are skipped.
    pub extrinsics_wait_s: f64,
}

impl Default for TfParams {
    fn default() -> Self {
        Self {
            fixed_frame: "odom".into(),
            base_frame: "base_link".into(),
            publish: TfPublish::Auto,
            extrinsics_from_tf: true,
            extrinsics_wait_s: 2.0,
        }
    }
}

impl TfParams {
    pub fn validate(&self) -> Result<(), String> {
        if self.fixed_frame.trim_start_matches('/').is_empty() || self.base_frame.trim_start_matches('/').is_empty() {
            return Err("ros.tf.fixed_frame and ros.tf.base_frame must not be empty".into());
        }
        if !(self.extrinsics_wait_s.is_finite() && self.extrinsics_wait_s >= 0.0) {
            return Err(format!("ros.tf.extrinsics_wait_s = {} must be >= 0", self.extrinsics_wait_s));
        }
        Ok(())
    }
}

/// A transform that holds at every time when static, else at `stamp` (the newest one otherwise,
/// for a link published less often than the frames arrive).
fn lookup_near(tf: &TfBuffer, target: &str, source: &str, stamp: &Time) -> Result<Isometry3<f64>, TfError> {
    tf.lookup(target, source, LookupTime::At(stamp_ns(stamp))).or_else(|_| tf.lookup(target, source, LookupTime::Latest))
}

/// The `/tf` message of the tracked pose `fixed_from_camera` at the depth `stamp`.
pub fn pose_transform(
    params: &TfParams,
    tf: &TfBuffer,
    camera_frame: &str,
    stamp: &Time,
    fixed_from_camera: &Isometry3<f64>,
) -> Option<TransformStamped> {
    if camera_frame.is_empty() {
        return None;
    }
    match params.publish {
        TfPublish::Off => None,
        TfPublish::Camera => Some(transform_msg(&params.fixed_frame, camera_frame, stamp.clone(), fixed_from_camera)),
        TfPublish::Auto => match lookup_near(tf, &params.base_frame, camera_frame, stamp) {
            Ok(base_from_camera) => Some(transform_msg(
                &params.fixed_frame,
                &params.base_frame,
                stamp.clone(),
                &(fixed_from_camera * base_from_camera.inverse()),
            )),
            Err(_) => Some(transform_msg(&params.fixed_frame, camera_frame, stamp.clone(), fixed_from_camera)),
        },
    }
}

/// Where `camera_from_imu` comes from, and when the node started waiting for it.
#[derive(Debug)]
pub struct Extrinsics {
    params: TfParams,
    waiting_since: Option<Instant>,
    /// The source last reported ("tf" or "config"), to log each change once.
    reported: Option<&'static str>,
}

/// The outcome of [`Extrinsics::camera_from_imu`].
#[derive(Debug, Clone, PartialEq)]
pub enum MountChoice {
    /// From `/tf_static`.
    FromTf(Rotation3<f64>),
    /// Not (yet) in TF and the wait is over: keep the config's value.
    Config,
    /// Still waiting for `/tf_static`: skip this frame.
    Wait,
}

impl Extrinsics {
    pub fn new(params: TfParams) -> Self {
        Self { params, waiting_since: None, reported: None }
    }

    /// The mount for a frame from `camera_frame` with IMU samples from `imu_frame` (`None`: no IMU
    /// heard yet, nothing to wait for).
    pub fn camera_from_imu(&mut self, tf: &SharedTf, camera_frame: &str, imu_frame: Option<&str>, now: Instant) -> MountChoice {
        let Some(imu_frame) = imu_frame.filter(|f| !f.is_empty() && self.params.extrinsics_from_tf && !camera_frame.is_empty()) else {
            self.report("config", camera_frame, "");
            return MountChoice::Config;
        };
        if camera_frame.trim_start_matches('/') == imu_frame.trim_start_matches('/') {
            // The IMU reports in the camera's own axes: the identity, no lookup needed.
            self.report("tf", camera_frame, imu_frame);
            return MountChoice::FromTf(Rotation3::identity());
        }
        if let Ok(camera_from_imu) = tf.lock().lookup(camera_frame, imu_frame, LookupTime::Latest) {
            self.report("tf", camera_frame, imu_frame);
            return MountChoice::FromTf(camera_from_imu.rotation.to_rotation_matrix());
        }
        let since = *self.waiting_since.get_or_insert(now);
        if now.duration_since(since) < Duration::from_secs_f64(self.params.extrinsics_wait_s) {
            return MountChoice::Wait;
        }
        self.report("config", camera_frame, imu_frame);
        MountChoice::Config
    }

    fn report(&mut self, source: &'static str, camera_frame: &str, imu_frame: &str) {
        if self.reported == Some(source) {
            return;
        }
        match source {
            "tf" => tracing::info!("camera_from_imu from TF: {camera_frame:?} ← {imu_frame:?}"),
            _ if !self.params.extrinsics_from_tf => tracing::info!("camera_from_imu from mapper.acquire.camera_from_imu (ros.tf.extrinsics_from_tf is off)"),
            _ if imu_frame.is_empty() => {}
            _ => tracing::warn!(
                "no transform {camera_frame:?} ← {imu_frame:?} on /tf_static after {} s: using mapper.acquire.camera_from_imu from the config \
                 (publish the IMU mount on /tf_static, or set it there)",
                self.params.extrinsics_wait_s
            ),
        }
        self.reported = Some(source);
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use nalgebra::{Translation3, UnitQuaternion};

    fn base_from_camera() -> Isometry3<f64> {
        Isometry3::from_parts(Translation3::new(0.04, 0.0, 0.17), UnitQuaternion::from_euler_angles(-2.4, 0.0, -1.57))
    }

    #[test]
    fn the_pose_goes_out_through_base_link_when_the_robot_tree_has_the_camera() {
        let params = TfParams::default();
        let stamp = Time { sec: 5, nanosec: 0 };
        let odom_from_camera = Isometry3::from_parts(Translation3::new(0.1, 0.2, 0.3), UnitQuaternion::from_euler_angles(-2.0, 0.1, 0.3));
        let empty = TfBuffer::default();
        let hand_held = pose_transform(&params, &empty, "camera_optical", &stamp, &odom_from_camera).unwrap();
        assert_eq!((hand_held.header.frame_id.as_str(), hand_held.child_frame_id.as_str()), ("odom", "camera_optical"));
        let mut robot = TfBuffer::default();
        robot.set_static("base_link", "camera_optical", base_from_camera()).unwrap();
        let msg = pose_transform(&params, &robot, "camera_optical", &stamp, &odom_from_camera).unwrap();
        assert_eq!((msg.header.frame_id.as_str(), msg.child_frame_id.as_str(), msg.header.stamp.sec), ("odom", "base_link", 5));
        // odom → base_link → camera gives back the tracked camera pose.
        robot.set_dynamic("odom", "base_link", stamp_ns(&stamp), patchwalk_ros::tf::isometry_from_transform(&msg).unwrap()).unwrap();
        let through_tree = robot.lookup("odom", "camera_optical", LookupTime::At(stamp_ns(&stamp))).unwrap();
        assert!((through_tree.translation.vector - odom_from_camera.translation.vector).norm() < 1e-12);
        assert!(through_tree.rotation.angle_to(&odom_from_camera.rotation) < 1e-12);
        let camera = TfParams { publish: TfPublish::Camera, fixed_frame: "map".into(), ..TfParams::default() };
        assert_eq!(pose_transform(&camera, &robot, "camera_optical", &stamp, &odom_from_camera).unwrap().child_frame_id, "camera_optical");
        let off = TfParams { publish: TfPublish::Off, ..TfParams::default() };
        assert!(pose_transform(&off, &robot, "camera_optical", &stamp, &odom_from_camera).is_none());
        assert!(pose_transform(&params, &robot, "", &stamp, &odom_from_camera).is_none(), "no frame id, nothing to name");
    }

    #[test]
    fn the_imu_mount_comes_from_tf_after_a_bounded_wait() {
        let tf = SharedTf::default();
        let mut extrinsics = Extrinsics::new(TfParams { extrinsics_wait_s: 1.0, ..TfParams::default() });
        let start = Instant::now();
        assert_eq!(extrinsics.camera_from_imu(&tf, "camera_optical", None, start), MountChoice::Config, "no IMU heard");
        assert_eq!(extrinsics.camera_from_imu(&tf, "camera_optical", Some("imu"), start), MountChoice::Wait);
        let mount = UnitQuaternion::from_euler_angles(0.1, 0.2, 0.3);
        tf.lock().set_static("camera_optical", "imu", Isometry3::from_parts(Translation3::identity(), mount)).unwrap();
        let MountChoice::FromTf(rotation) = extrinsics.camera_from_imu(&tf, "camera_optical", Some("imu"), start) else {
            panic!("from TF")
        };
        assert!((rotation.into_inner() - mount.to_rotation_matrix().into_inner()).norm() < 1e-12);
        assert_eq!(extrinsics.camera_from_imu(&tf, "cam", Some("cam"), start), MountChoice::FromTf(Rotation3::identity()));
        let mut late = Extrinsics::new(TfParams { extrinsics_wait_s: 1.0, ..TfParams::default() });
        assert_eq!(late.camera_from_imu(&tf, "camera_optical", Some("other_imu"), start), MountChoice::Wait);
        assert_eq!(late.camera_from_imu(&tf, "camera_optical", Some("other_imu"), start + Duration::from_secs(2)), MountChoice::Config);
        let mut off = Extrinsics::new(TfParams { extrinsics_from_tf: false, ..TfParams::default() });
        assert_eq!(off.camera_from_imu(&tf, "camera_optical", Some("imu"), start), MountChoice::Config);
        assert!(TfParams { extrinsics_wait_s: -1.0, ..TfParams::default() }.validate().is_err());
    }
}

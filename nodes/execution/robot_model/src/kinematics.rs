//! Forward kinematics of the RPBP from its URDF (loaded with `urdf-rs`): `base_from_link` for any
//! link at given joint positions, hence `base_from_camera` (to express patches relative to the robot,
//! as J 6.3 stores them) and `base_from_foot`; plus the URDF joint limits the player enforces.
//!
//! The chain product is done here with nalgebra 0.34 (the `k` crate pins nalgebra 0.30): each URDF
//! joint contributes `parent_from_child = origin(xyz, rpy) · motion(axis, q)`.

use std::collections::HashMap;
use std::path::Path;

use nalgebra::{Isometry3, Translation3, Unit, UnitQuaternion, Vector3};

/// Errors loading the robot model or evaluating it.
#[derive(Debug, thiserror::Error)]
pub enum KinematicsError {
    #[error("cannot load URDF: {0}")]
    Urdf(String),
    #[error("URDF has no link named {0:?}")]
    UnknownLink(String),
    #[error("URDF has no joint named {0:?}")]
    UnknownJoint(String),
    #[error("joint {joint:?} has no position (joint positions given: {given})")]
    MissingJointPosition { joint: String, given: usize },
    #[error("URDF link {0:?} is its own ancestor (cycle)")]
    Cycle(String),
}

/// Position limits of one joint (rad).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct JointLimits {
    pub lower: f64,
    pub upper: f64,
}

#[derive(Debug, Clone)]
enum Motion {
    Fixed,
    Revolute { axis: Unit<Vector3<f64>>, limits: Option<JointLimits> },
    Prismatic { axis: Unit<Vector3<f64>>, limits: Option<JointLimits> },
}

#[derive(Debug, Clone)]
struct JointModel {
    name: String,
    parent: String,
    parent_from_joint: Isometry3<f64>,
    motion: Motion,
}

/// The kinematic tree of a URDF robot.
#[derive(Debug, Clone)]
pub struct RobotModel {
    root: String,
    /// child link → the joint that attaches it to its parent.
    joint_of_child: HashMap<String, JointModel>,
}

/// `parent_from_joint` of a URDF `<origin xyz rpy>`: R = Rz(yaw)·Ry(pitch)·Rx(roll) (URDF fixed-axis rpy).
fn isometry_from_origin(xyz: [f64; 3], rpy: [f64; 3]) -> Isometry3<f64> {
    let rotation = UnitQuaternion::from_euler_angles(rpy[0], rpy[1], rpy[2]);
    Isometry3::from_parts(Translation3::new(xyz[0], xyz[1], xyz[2]), rotation)
}

fn unit_axis(xyz: [f64; 3], joint: &str) -> Result<Unit<Vector3<f64>>, KinematicsError> {
    Unit::try_new(Vector3::new(xyz[0], xyz[1], xyz[2]), 1e-9)
        .ok_or_else(|| KinematicsError::Urdf(format!("joint {joint:?} has a zero axis")))
}

impl RobotModel {
    /// Load from a URDF file.
    pub fn from_file(path: &Path) -> Result<Self, KinematicsError> {
        let text = std::fs::read_to_string(path).map_err(|e| KinematicsError::Urdf(format!("{}: {e}", path.display())))?;
        Self::from_urdf_str(&text)
    }

    /// Parse URDF text.
    pub fn from_urdf_str(text: &str) -> Result<Self, KinematicsError> {
        let robot = urdf_rs::read_from_string(text).map_err(|e| KinematicsError::Urdf(e.to_string()))?;
        let mut joint_of_child = HashMap::new();
        for joint in &robot.joints {
            let limits = Some(JointLimits { lower: joint.limit.lower, upper: joint.limit.upper });
            let motion = match joint.joint_type {
                urdf_rs::JointType::Fixed => Motion::Fixed,
                urdf_rs::JointType::Revolute => Motion::Revolute { axis: unit_axis(joint.axis.xyz.0, &joint.name)?, limits },
                urdf_rs::JointType::Continuous => Motion::Revolute { axis: unit_axis(joint.axis.xyz.0, &joint.name)?, limits: None },
                urdf_rs::JointType::Prismatic => Motion::Prismatic { axis: unit_axis(joint.axis.xyz.0, &joint.name)?, limits },
                ref other => return Err(KinematicsError::Urdf(format!("joint {:?}: unsupported type {other:?}", joint.name))),
            };
            let model = JointModel {
                name: joint.name.clone(),
                parent: joint.parent.link.clone(),
                parent_from_joint: isometry_from_origin(joint.origin.xyz.0, joint.origin.rpy.0),
                motion,
            };
            if joint_of_child.insert(joint.child.link.clone(), model).is_some() {
                return Err(KinematicsError::Urdf(format!("link {:?} has two parent joints", joint.child.link)));
            }
        }
        let roots: Vec<&str> = robot.links.iter().map(|l| l.name.as_str()).filter(|name| !joint_of_child.contains_key(*name)).collect();
        let root = match roots.as_slice() {
            [root] => (*root).to_string(),
            _ => return Err(KinematicsError::Urdf(format!("expected exactly one root link, found {roots:?}"))),
        };
        Ok(Self { root, joint_of_child })
    }

    /// The root link (`base_link` for the RPBP).
    pub fn root(&self) -> &str {
        &self.root
    }

    /// Limits of a movable joint (None for continuous/fixed joints).
    pub fn joint_limits(&self, joint: &str) -> Result<Option<JointLimits>, KinematicsError> {
        let model =
            self.joint_of_child.values().find(|j| j.name == joint).ok_or_else(|| KinematicsError::UnknownJoint(joint.to_string()))?;
        Ok(match &model.motion {
            Motion::Fixed => None,
            Motion::Revolute { limits, .. } | Motion::Prismatic { limits, .. } => *limits,
        })
    }

    /// `root_from_link` at the given joint positions (rad / m, by joint name).
    pub fn root_from_link(&self, link: &str, positions: &HashMap<String, f64>) -> Result<Isometry3<f64>, KinematicsError> {
        if link == self.root {
            return Ok(Isometry3::identity());
        }
        let mut child_from_link = Isometry3::identity();
        let mut current = link;
        let mut steps = 0usize;
        while current != self.root {
            let joint = self.joint_of_child.get(current).ok_or_else(|| KinematicsError::UnknownLink(current.to_string()))?;
            let joint_from_child = match &joint.motion {
                Motion::Fixed => Isometry3::identity(),
                Motion::Revolute { axis, .. } => {
                    let q = joint_position(positions, &joint.name)?;
                    Isometry3::from_parts(Translation3::identity(), UnitQuaternion::from_axis_angle(axis, q))
                }
                Motion::Prismatic { axis, .. } => {
                    let q = joint_position(positions, &joint.name)?;
                    Isometry3::from_parts(Translation3::from(axis.into_inner() * q), UnitQuaternion::identity())
                }
            };
            child_from_link = joint.parent_from_joint * joint_from_child * child_from_link;
            current = &joint.parent;
            steps += 1;
            if steps > self.joint_of_child.len() {
                return Err(KinematicsError::Cycle(link.to_string()));
            }
        }
        Ok(child_from_link)
    }

    /// `base_from_camera`: pose of the depth camera's optical frame in `base_link`.
    pub fn base_from_camera(&self, positions: &HashMap<String, f64>) -> Result<Isometry3<f64>, KinematicsError> {
        self.root_from_link("camera_optical", positions)
    }

    /// `base_from_foot` for `left_foot` / `right_foot`.
    pub fn base_from_foot(&self, foot_link: &str, positions: &HashMap<String, f64>) -> Result<Isometry3<f64>, KinematicsError> {
        self.root_from_link(foot_link, positions)
    }
}

fn joint_position(positions: &HashMap<String, f64>, joint: &str) -> Result<f64, KinematicsError> {
    positions.get(joint).copied().ok_or_else(|| KinematicsError::MissingJointPosition { joint: joint.to_string(), given: positions.len() })
}

/// Joint positions by name from parallel name/value slices.
pub fn positions_by_name(names: &[String], values: &[f64]) -> HashMap<String, f64> {
    names.iter().cloned().zip(values.iter().copied()).collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    fn rpbp() -> RobotModel {
        let path = Path::new(env!("CARGO_MANIFEST_DIR")).join("../../../urdf/rpbp.urdf");
        RobotModel::from_file(&path).unwrap()
    }

    fn zeros() -> HashMap<String, f64> {
        crate::DEFAULT_JOINTS.iter().map(|j| ((*j).to_string(), 0.0)).collect()
    }

    #[test]
    fn rpbp_loads_with_twelve_limited_joints() {
        let model = rpbp();
        assert_eq!(model.root(), "base_link");
        for joint in crate::DEFAULT_JOINTS {
            let limits = model.joint_limits(joint).unwrap().unwrap();
            assert!(limits.lower < limits.upper, "{joint}");
            assert!(limits.lower > -std::f64::consts::PI && limits.upper < std::f64::consts::PI, "{joint}");
        }
    }

    #[test]
    fn straight_legs_put_soles_below_hips_and_robot_is_47cm() {
        let model = rpbp();
        let left = model.base_from_foot("left_foot", &zeros()).unwrap();
        let right = model.base_from_foot("right_foot", &zeros()).unwrap();
        assert!((left.translation.vector - Vector3::new(0.0, 0.037, -0.295)).norm() < 1e-9);
        assert!((right.translation.vector - Vector3::new(0.0, -0.037, -0.295)).norm() < 1e-9);
        let camera = model.base_from_camera(&zeros()).unwrap();
        let height = camera.translation.z - left.translation.z;
        assert!((0.44..0.48).contains(&height), "height {height}");
    }

    #[test]
    fn camera_optical_looks_forward_and_down() {
        let camera = rpbp().base_from_camera(&zeros()).unwrap();
        // optical z (viewing direction) in base: forward and down; optical x (image right) = -y_base.
        let z_in_base = camera.rotation * Vector3::z();
        assert!(z_in_base.x > 0.5 && z_in_base.z < -0.5, "{z_in_base:?}");
        let x_in_base = camera.rotation * Vector3::x();
        assert!((x_in_base - Vector3::new(0.0, -1.0, 0.0)).norm() < 1e-9);
    }

    #[test]
    fn knee_bend_moves_foot_back_and_up() {
        let model = rpbp();
        let mut q = zeros();
        q.insert("l_knee".into(), std::f64::consts::FRAC_PI_2);
        let foot = model.base_from_foot("left_foot", &q).unwrap();
        // shin (0.100 + 0.035) now points backwards from the knee at z = -0.160.
        assert!((foot.translation.vector - Vector3::new(-0.135, 0.037, -0.160)).norm() < 1e-9, "{foot:?}");
    }

    #[test]
    fn errors_are_typed() {
        let model = rpbp();
        assert!(matches!(model.base_from_foot("nope", &zeros()), Err(KinematicsError::UnknownLink(_))));
        assert!(matches!(model.base_from_foot("left_foot", &HashMap::new()), Err(KinematicsError::MissingJointPosition { .. })));
        assert!(matches!(RobotModel::from_urdf_str("<robot"), Err(KinematicsError::Urdf(_))));
    }
}

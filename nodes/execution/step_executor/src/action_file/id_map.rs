//! Which servo ID of an action file drives which library joint, and how its ticks map to the joint
//! angle. The default is the DARwIn-OP leg table: ROBOTIS' DARwIn-OP (and OP2/OP3) number the leg
//! servos 7–18 right before left, hip to ankle (`JointData.h` of the DARwIn-OP framework: 7 R_HIP_YAW,
//! 8 L_HIP_YAW, 9 R_HIP_ROLL, 10 L_HIP_ROLL, 11 R_HIP_PITCH, 12 L_HIP_PITCH, 13 R_KNEE, 14 L_KNEE,
//! 15 R_ANKLE_PITCH, 16 L_ANKLE_PITCH, 17 R_ANKLE_ROLL, 18 L_ANKLE_ROLL), the order of the RPBP's
//! 12 leg joints ([`patchwalk_robot_model::DEFAULT_JOINTS`]), each with direction +1 and zero offset 0.
//!
//! A table file is a YAML list with one entry per library joint, the entries of the servo
//! configuration: `- { id: 7, joint: r_hip_yaw, direction: -1, zero_offset: 0.02 }` (`direction` and
//! `zero_offset` optional).

use std::collections::BTreeSet;

use patchwalk_robot_model::DEFAULT_JOINTS;

use super::page::JOINT_SLOTS;
use crate::config::ServoConfig;

/// The first DARwIn-OP leg servo ID (right hip yaw).
pub const DARWIN_OP_FIRST_LEG_ID: u8 = 7;

/// Why an ID table is refused; entries are counted from 0 in the file's order.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum IdMapError {
    #[error("ID table {origin}: {message}")]
    Parse { origin: String, message: String },
    #[error("ID table entry {entry}: ID {id} is not a position slot of an action page (IDs 0..=30)")]
    IdOutOfRange { entry: usize, id: u8 },
    #[error("ID table entry {entry}: ID {id} is already mapped")]
    DuplicateId { entry: usize, id: u8 },
    #[error("ID table entry {entry}: joint {joint:?} is already mapped")]
    DuplicateJoint { entry: usize, joint: String },
    #[error("ID table entry {entry}: unknown joint {joint:?} (the library's joints are {known:?})")]
    UnknownJoint { entry: usize, joint: String, known: Vec<String> },
    #[error("ID table: library joint {0:?} has no ID")]
    MissingJoint(String),
    #[error("ID table entry {entry}: direction must be 1 or -1, got {direction}")]
    Direction { entry: usize, direction: i8 },
    #[error("ID table entry {entry}: zero_offset is not finite")]
    ZeroOffset { entry: usize },
}

/// The table in library joint order: entry `j` is the servo of library joint `j`.
#[derive(Debug, Clone, PartialEq)]
pub struct IdMap {
    servos: Vec<ServoConfig>,
}

impl IdMap {
    /// The DARwIn-OP leg table (IDs 7–18 in RPBP joint order, direction +1, zero offset 0).
    pub fn darwin_op_legs() -> Vec<ServoConfig> {
        DEFAULT_JOINTS
            .iter()
            .zip(DARWIN_OP_FIRST_LEG_ID..)
            .map(|(joint, id)| ServoConfig { joint: (*joint).to_string(), id, zero_offset: 0.0, direction: 1 })
            .collect()
    }

    /// Parse a table file's text (`origin` names it in errors).
    pub fn parse_entries(text: &str, origin: &str) -> Result<Vec<ServoConfig>, IdMapError> {
        serde_yaml_ng::from_str(text).map_err(|e| IdMapError::Parse { origin: origin.to_string(), message: e.to_string() })
    }

    /// Check `entries` against the library's joint order: IDs are page slots and unique, every joint
    /// is a library joint mapped exactly once, directions ±1, offsets finite.
    pub fn for_joints(entries: &[ServoConfig], joints: &[String]) -> Result<Self, IdMapError> {
        let mut ids = BTreeSet::new();
        let mut seen = BTreeSet::new();
        for (entry, servo) in entries.iter().enumerate() {
            if usize::from(servo.id) >= JOINT_SLOTS {
                return Err(IdMapError::IdOutOfRange { entry, id: servo.id });
            }
            if !ids.insert(servo.id) {
                return Err(IdMapError::DuplicateId { entry, id: servo.id });
            }
            if !joints.contains(&servo.joint) {
                return Err(IdMapError::UnknownJoint { entry, joint: servo.joint.clone(), known: joints.to_vec() });
            }
            if !seen.insert(servo.joint.as_str()) {
                return Err(IdMapError::DuplicateJoint { entry, joint: servo.joint.clone() });
            }
            if servo.direction != 1 && servo.direction != -1 {
                return Err(IdMapError::Direction { entry, direction: servo.direction });
            }
            if !servo.zero_offset.is_finite() {
                return Err(IdMapError::ZeroOffset { entry });
            }
        }
        let servos = joints
            .iter()
            .map(|joint| entries.iter().find(|s| &s.joint == joint).cloned().ok_or_else(|| IdMapError::MissingJoint(joint.clone())))
            .collect::<Result<Vec<_>, _>>()?;
        Ok(Self { servos })
    }

    /// The servos in library joint order.
    pub fn servos(&self) -> &[ServoConfig] {
        &self.servos
    }

    /// Whether `id` drives a library joint.
    pub fn maps(&self, id: usize) -> bool {
        self.servos.iter().any(|s| usize::from(s.id) == id)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn joints() -> Vec<String> {
        DEFAULT_JOINTS.iter().map(|j| j.to_string()).collect()
    }

    #[test]
    fn the_default_table_maps_ids_7_to_18_to_the_leg_joints() {
        let map = IdMap::for_joints(&IdMap::darwin_op_legs(), &joints()).unwrap();
        let ids: Vec<u8> = map.servos().iter().map(|s| s.id).collect();
        assert_eq!(ids, (7..=18).collect::<Vec<u8>>());
        assert_eq!(map.servos()[0].joint, "r_hip_yaw");
        assert_eq!(map.servos()[11].joint, "l_ankle_roll");
        assert!(map.maps(18) && !map.maps(6) && !map.maps(19));
    }

    #[test]
    fn a_table_file_is_put_in_library_order() {
        let mut text = String::new();
        for (joint, id) in joints().iter().rev().zip(1u8..) {
            text.push_str(&format!("- {{ id: {id}, joint: {joint}, direction: -1 }}\n"));
        }
        let map = IdMap::for_joints(&IdMap::parse_entries(&text, "t.yaml").unwrap(), &joints()).unwrap();
        assert_eq!(map.servos()[0].joint, "r_hip_yaw");
        assert_eq!(map.servos()[0].id, 12);
        assert_eq!(map.servos()[0].direction, -1);
    }

    #[test]
    fn bad_tables_are_refused_naming_the_entry() {
        let mut entries = IdMap::darwin_op_legs();
        entries[3].id = 31;
        assert_eq!(IdMap::for_joints(&entries, &joints()).unwrap_err(), IdMapError::IdOutOfRange { entry: 3, id: 31 });
        let mut entries = IdMap::darwin_op_legs();
        entries[4].id = 7;
        assert_eq!(IdMap::for_joints(&entries, &joints()).unwrap_err(), IdMapError::DuplicateId { entry: 4, id: 7 });
        let mut entries = IdMap::darwin_op_legs();
        entries[2].joint = "r_elbow".into();
        let err = IdMap::for_joints(&entries, &joints()).unwrap_err();
        assert!(matches!(&err, IdMapError::UnknownJoint { entry: 2, joint, .. } if joint == "r_elbow"), "{err}");
        let mut entries = IdMap::darwin_op_legs();
        entries.pop();
        assert_eq!(IdMap::for_joints(&entries, &joints()).unwrap_err(), IdMapError::MissingJoint("l_ankle_roll".into()));
        let mut entries = IdMap::darwin_op_legs();
        entries[1].joint = entries[0].joint.clone();
        assert!(matches!(IdMap::for_joints(&entries, &joints()).unwrap_err(), IdMapError::DuplicateJoint { entry: 1, .. }));
        let mut entries = IdMap::darwin_op_legs();
        entries[0].direction = 2;
        assert_eq!(IdMap::for_joints(&entries, &joints()).unwrap_err(), IdMapError::Direction { entry: 0, direction: 2 });
        let err = IdMap::parse_entries("- { id: 7, joint: r_hip_yaw, speed: 3 }\n", "m.yaml").unwrap_err();
        assert!(err.to_string().contains("m.yaml") && err.to_string().contains("speed"), "{err}");
    }
}

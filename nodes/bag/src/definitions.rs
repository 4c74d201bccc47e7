//! The ros2msg definitions of the message types this crate (de)serialises, as rosbag2 stores them in
//! an MCAP schema record: the type's own `.msg` text, then for each type it uses (recursively, each
//! once) a line of 80 `=`, a line `MSG: pkg/Type` and that type's text. ROS 2 Jazzy's definitions,
//! field for field (comments left out).

/// One message type: its name (`pkg/msg/Type`), its own fields, and the types those fields use.
pub struct TypeDefinition {
    pub name: &'static str,
    pub text: &'static str,
    pub uses: &'static [&'static TypeDefinition],
}

pub static TIME: TypeDefinition = TypeDefinition { name: "builtin_interfaces/msg/Time", text: "int32 sec\nuint32 nanosec\n", uses: &[] };
pub static HEADER: TypeDefinition =
    TypeDefinition { name: "std_msgs/msg/Header", text: "builtin_interfaces/Time stamp\nstring frame_id\n", uses: &[&TIME] };
pub static IMAGE: TypeDefinition = TypeDefinition {
    name: "sensor_msgs/msg/Image",
    text: "std_msgs/Header header\nuint32 height\nuint32 width\nstring encoding\nuint8 is_bigendian\nuint32 step\nuint8[] data\n",
    uses: &[&HEADER],
};
pub static REGION_OF_INTEREST: TypeDefinition = TypeDefinition {
    name: "sensor_msgs/msg/RegionOfInterest",
    text: "uint32 x_offset\nuint32 y_offset\nuint32 height\nuint32 width\nbool do_rectify\n",
    uses: &[],
};
pub static CAMERA_INFO: TypeDefinition = TypeDefinition {
    name: "sensor_msgs/msg/CameraInfo",
    text: "std_msgs/Header header\nuint32 height\nuint32 width\nstring distortion_model\nfloat64[] d\nfloat64[9] k\nfloat64[9] r\n\
           float64[12] p\nuint32 binning_x\nuint32 binning_y\nsensor_msgs/RegionOfInterest roi\n",
    uses: &[&HEADER, &REGION_OF_INTEREST],
};
pub static VECTOR3: TypeDefinition =
    TypeDefinition { name: "geometry_msgs/msg/Vector3", text: "float64 x\nfloat64 y\nfloat64 z\n", uses: &[] };
pub static POINT: TypeDefinition = TypeDefinition { name: "geometry_msgs/msg/Point", text: "float64 x\nfloat64 y\nfloat64 z\n", uses: &[] };
pub static QUATERNION: TypeDefinition =
    TypeDefinition { name: "geometry_msgs/msg/Quaternion", text: "float64 x 0\nfloat64 y 0\nfloat64 z 0\nfloat64 w 1\n", uses: &[] };
pub static IMU: TypeDefinition = TypeDefinition {
    name: "sensor_msgs/msg/Imu",
    text: "std_msgs/Header header\ngeometry_msgs/Quaternion orientation\nfloat64[9] orientation_covariance\n\
           geometry_msgs/Vector3 angular_velocity\nfloat64[9] angular_velocity_covariance\ngeometry_msgs/Vector3 linear_acceleration\n\
           float64[9] linear_acceleration_covariance\n",
    uses: &[&HEADER, &QUATERNION, &VECTOR3],
};
pub static TRANSFORM: TypeDefinition = TypeDefinition {
    name: "geometry_msgs/msg/Transform",
    text: "geometry_msgs/Vector3 translation\ngeometry_msgs/Quaternion rotation\n",
    uses: &[&VECTOR3, &QUATERNION],
};
pub static TRANSFORM_STAMPED: TypeDefinition = TypeDefinition {
    name: "geometry_msgs/msg/TransformStamped",
    text: "std_msgs/Header header\nstring child_frame_id\ngeometry_msgs/Transform transform\n",
    uses: &[&HEADER, &TRANSFORM],
};
pub static TF_MESSAGE: TypeDefinition =
    TypeDefinition { name: "tf2_msgs/msg/TFMessage", text: "geometry_msgs/TransformStamped[] transforms\n", uses: &[&TRANSFORM_STAMPED] };
pub static POSE: TypeDefinition = TypeDefinition {
    name: "geometry_msgs/msg/Pose",
    text: "geometry_msgs/Point position\ngeometry_msgs/Quaternion orientation\n",
    uses: &[&POINT, &QUATERNION],
};
pub static POSE_STAMPED: TypeDefinition = TypeDefinition {
    name: "geometry_msgs/msg/PoseStamped",
    text: "std_msgs/Header header\ngeometry_msgs/Pose pose\n",
    uses: &[&HEADER, &POSE],
};

impl TypeDefinition {
    /// The schema text rosbag2 writes for this type (its definition and those of every type it uses).
    pub fn schema_text(&self) -> String {
        let mut text = self.text.to_string();
        let mut seen = vec![self.name];
        let mut pending: Vec<&TypeDefinition> = self.uses.to_vec();
        // Depth first in field order, each dependency once.
        pending.reverse();
        while let Some(dependency) = pending.pop() {
            if seen.contains(&dependency.name) {
                continue;
            }
            seen.push(dependency.name);
            text.push_str(&"=".repeat(80));
            text.push_str("\nMSG: ");
            text.push_str(&dependency.name.replacen("/msg/", "/", 1));
            text.push('\n');
            text.push_str(dependency.text);
            pending.extend(dependency.uses.iter().rev());
        }
        text
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn schema_lists_every_used_type_once_after_a_separator() {
        let text = TF_MESSAGE.schema_text();
        let sections: Vec<&str> = text.split(&format!("{}\n", "=".repeat(80))).collect();
        assert_eq!(sections[0], "geometry_msgs/TransformStamped[] transforms\n");
        let names: Vec<&str> = sections[1..].iter().map(|s| s.lines().next().unwrap()).collect();
        assert_eq!(
            names,
            [
                "MSG: geometry_msgs/TransformStamped",
                "MSG: std_msgs/Header",
                "MSG: builtin_interfaces/Time",
                "MSG: geometry_msgs/Transform",
                "MSG: geometry_msgs/Vector3",
                "MSG: geometry_msgs/Quaternion"
            ]
        );
        // Every field type named in a section is defined in the text (or is a primitive).
        for section in &sections {
            for line in section.lines().filter(|l| !l.starts_with("MSG:")) {
                let field_type = line.split_whitespace().next().unwrap().split('[').next().unwrap();
                if field_type.contains('/') {
                    assert!(text.contains(&format!("MSG: {field_type}\n")), "{field_type} undefined in\n{text}");
                }
            }
        }
    }
}

//! The ROS 2 messages a depth + IMU bag carries, as plain Rust structs with their CDR codec:
//! `sensor_msgs/msg/{Image, CameraInfo, Imu}`, `tf2_msgs/msg/TFMessage`, `geometry_msgs/msg/PoseStamped`
//! and the types they use. Fields in the order of the Jazzy `.msg` files (CDR is positional).

use crate::cdr::{CdrError, CdrReader, CdrWriter};
use crate::definitions::{self, TypeDefinition};

/// A message type this crate can put in and take out of a bag.
pub trait RosMessage: Sized {
    /// Its ros2msg definition (name, fields, used types).
    const DEFINITION: &'static TypeDefinition;
    fn write_cdr(&self, w: &mut CdrWriter);
    fn read_cdr(r: &mut CdrReader<'_>) -> Result<Self, CdrError>;

    /// The serialised message (CDR, little endian).
    fn to_cdr(&self) -> Vec<u8> {
        let mut w = CdrWriter::new();
        self.write_cdr(&mut w);
        w.finish()
    }

    /// Reads a serialised message; bytes after its last field are ignored (CDR pads to 4).
    fn from_cdr(payload: &[u8]) -> Result<Self, CdrError> {
        Self::read_cdr(&mut CdrReader::new(payload)?)
    }
}

/// `builtin_interfaces/msg/Time`.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, PartialOrd, Ord)]
pub struct Time {
    pub sec: i32,
    pub nanosec: u32,
}

impl Time {
    /// The time of `nanoseconds` since the epoch (saturating outside the `i32` seconds range).
    pub fn from_nanos(nanoseconds: i64) -> Self {
        let sec = nanoseconds.div_euclid(1_000_000_000);
        let nanosec = nanoseconds.rem_euclid(1_000_000_000) as u32;
        match i32::try_from(sec) {
            Ok(sec) => Self { sec, nanosec },
            Err(_) if sec < 0 => Self { sec: i32::MIN, nanosec: 0 },
            Err(_) => Self { sec: i32::MAX, nanosec: 999_999_999 },
        }
    }

    /// The time of `seconds` (rounded to the nanosecond; whole seconds and the fraction are
    /// converted apart, as `seconds * 1e9` would lose the nanoseconds of an epoch time).
    pub fn from_seconds(seconds: f64) -> Self {
        let whole = seconds.floor();
        let fraction_ns = ((seconds - whole) * 1e9).round() as i64;
        Self::from_nanos((whole as i64).saturating_mul(1_000_000_000).saturating_add(fraction_ns))
    }

    pub fn nanos(&self) -> i64 {
        i64::from(self.sec) * 1_000_000_000 + i64::from(self.nanosec)
    }

    pub fn seconds(&self) -> f64 {
        f64::from(self.sec) + f64::from(self.nanosec) * 1e-9
    }

    fn write(&self, w: &mut CdrWriter) {
        w.i32(self.sec);
        w.u32(self.nanosec);
    }

    fn read(r: &mut CdrReader<'_>) -> Result<Self, CdrError> {
        Ok(Self { sec: r.i32("header.stamp.sec")?, nanosec: r.u32("header.stamp.nanosec")? })
    }
}

/// `std_msgs/msg/Header`.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct Header {
    pub stamp: Time,
    pub frame_id: String,
}

impl Header {
    pub fn new(stamp: Time, frame_id: &str) -> Self {
        Self { stamp, frame_id: frame_id.to_string() }
    }

    fn write(&self, w: &mut CdrWriter) {
        self.stamp.write(w);
        w.string(&self.frame_id);
    }

    fn read(r: &mut CdrReader<'_>) -> Result<Self, CdrError> {
        Ok(Self { stamp: Time::read(r)?, frame_id: r.string("header.frame_id")? })
    }
}

/// `geometry_msgs/msg/Vector3` (also the layout of `geometry_msgs/msg/Point`).
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub struct Vector3 {
    pub x: f64,
    pub y: f64,
    pub z: f64,
}

impl Vector3 {
    pub fn new(x: f64, y: f64, z: f64) -> Self {
        Self { x, y, z }
    }

    fn write(&self, w: &mut CdrWriter) {
        w.f64_slice(&[self.x, self.y, self.z]);
    }

    fn read(r: &mut CdrReader<'_>, what: &'static str) -> Result<Self, CdrError> {
        let [x, y, z] = r.f64_array(what)?;
        Ok(Self { x, y, z })
    }
}

/// `geometry_msgs/msg/Quaternion`.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Quaternion {
    pub x: f64,
    pub y: f64,
    pub z: f64,
    pub w: f64,
}

impl Default for Quaternion {
    fn default() -> Self {
        Self { x: 0.0, y: 0.0, z: 0.0, w: 1.0 }
    }
}

impl Quaternion {
    fn write(&self, w: &mut CdrWriter) {
        w.f64_slice(&[self.x, self.y, self.z, self.w]);
    }

    fn read(r: &mut CdrReader<'_>, what: &'static str) -> Result<Self, CdrError> {
        let [x, y, z, w] = r.f64_array(what)?;
        Ok(Self { x, y, z, w })
    }
}

/// `sensor_msgs/msg/Image`.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct Image {
    pub header: Header,
    pub height: u32,
    pub width: u32,
    pub encoding: String,
    pub is_bigendian: u8,
    /// Row length in bytes.
    pub step: u32,
    pub data: Vec<u8>,
}

impl RosMessage for Image {
    const DEFINITION: &'static TypeDefinition = &definitions::IMAGE;

    fn write_cdr(&self, w: &mut CdrWriter) {
        self.header.write(w);
        w.u32(self.height);
        w.u32(self.width);
        w.string(&self.encoding);
        w.u8(self.is_bigendian);
        w.u32(self.step);
        w.bytes(&self.data);
    }

    fn read_cdr(r: &mut CdrReader<'_>) -> Result<Self, CdrError> {
        Ok(Self {
            header: Header::read(r)?,
            height: r.u32("height")?,
            width: r.u32("width")?,
            encoding: r.string("encoding")?,
            is_bigendian: r.u8("is_bigendian")?,
            step: r.u32("step")?,
            data: r.bytes("data")?,
        })
    }
}

/// `sensor_msgs/msg/RegionOfInterest`.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct RegionOfInterest {
    pub x_offset: u32,
    pub y_offset: u32,
    pub height: u32,
    pub width: u32,
    pub do_rectify: bool,
}

/// `sensor_msgs/msg/CameraInfo`.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct CameraInfo {
    pub header: Header,
    pub height: u32,
    pub width: u32,
    pub distortion_model: String,
    pub d: Vec<f64>,
    /// Row-major 3×3 intrinsic matrix `[fx 0 cx; 0 fy cy; 0 0 1]`.
    pub k: [f64; 9],
    pub r: [f64; 9],
    pub p: [f64; 12],
    pub binning_x: u32,
    pub binning_y: u32,
    pub roi: RegionOfInterest,
}

impl RosMessage for CameraInfo {
    const DEFINITION: &'static TypeDefinition = &definitions::CAMERA_INFO;

    fn write_cdr(&self, w: &mut CdrWriter) {
        self.header.write(w);
        w.u32(self.height);
        w.u32(self.width);
        w.string(&self.distortion_model);
        w.f64_sequence(&self.d);
        w.f64_slice(&self.k);
        w.f64_slice(&self.r);
        w.f64_slice(&self.p);
        w.u32(self.binning_x);
        w.u32(self.binning_y);
        w.u32(self.roi.x_offset);
        w.u32(self.roi.y_offset);
        w.u32(self.roi.height);
        w.u32(self.roi.width);
        w.bool(self.roi.do_rectify);
    }

    fn read_cdr(r: &mut CdrReader<'_>) -> Result<Self, CdrError> {
        Ok(Self {
            header: Header::read(r)?,
            height: r.u32("height")?,
            width: r.u32("width")?,
            distortion_model: r.string("distortion_model")?,
            d: r.f64_sequence("d")?,
            k: r.f64_array("k")?,
            r: r.f64_array("r")?,
            p: r.f64_array("p")?,
            binning_x: r.u32("binning_x")?,
            binning_y: r.u32("binning_y")?,
            roi: RegionOfInterest {
                x_offset: r.u32("roi.x_offset")?,
                y_offset: r.u32("roi.y_offset")?,
                height: r.u32("roi.height")?,
                width: r.u32("roi.width")?,
                do_rectify: r.bool("roi.do_rectify")?,
            },
        })
    }
}

/// `sensor_msgs/msg/Imu`.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct Imu {
    pub header: Header,
    pub orientation: Quaternion,
    pub orientation_covariance: [f64; 9],
    pub angular_velocity: Vector3,
    pub angular_velocity_covariance: [f64; 9],
    /// Specific force (m/s²) in the IMU frame.
    pub linear_acceleration: Vector3,
    pub linear_acceleration_covariance: [f64; 9],
}

impl RosMessage for Imu {
    const DEFINITION: &'static TypeDefinition = &definitions::IMU;

    fn write_cdr(&self, w: &mut CdrWriter) {
        self.header.write(w);
        self.orientation.write(w);
        w.f64_slice(&self.orientation_covariance);
        self.angular_velocity.write(w);
        w.f64_slice(&self.angular_velocity_covariance);
        self.linear_acceleration.write(w);
        w.f64_slice(&self.linear_acceleration_covariance);
    }

    fn read_cdr(r: &mut CdrReader<'_>) -> Result<Self, CdrError> {
        Ok(Self {
            header: Header::read(r)?,
            orientation: Quaternion::read(r, "orientation")?,
            orientation_covariance: r.f64_array("orientation_covariance")?,
            angular_velocity: Vector3::read(r, "angular_velocity")?,
            angular_velocity_covariance: r.f64_array("angular_velocity_covariance")?,
            linear_acceleration: Vector3::read(r, "linear_acceleration")?,
            linear_acceleration_covariance: r.f64_array("linear_acceleration_covariance")?,
        })
    }
}

/// `geometry_msgs/msg/TransformStamped`: `child_frame_id`'s pose in `header.frame_id`.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct TransformStamped {
    pub header: Header,
    pub child_frame_id: String,
    pub translation: Vector3,
    pub rotation: Quaternion,
}

/// `tf2_msgs/msg/TFMessage`.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct TfMessage {
    pub transforms: Vec<TransformStamped>,
}

impl RosMessage for TfMessage {
    const DEFINITION: &'static TypeDefinition = &definitions::TF_MESSAGE;

    fn write_cdr(&self, w: &mut CdrWriter) {
        w.sequence_len(self.transforms.len());
        for transform in &self.transforms {
            transform.header.write(w);
            w.string(&transform.child_frame_id);
            transform.translation.write(w);
            transform.rotation.write(w);
        }
    }

    fn read_cdr(r: &mut CdrReader<'_>) -> Result<Self, CdrError> {
        // Each transform takes at least 4 + 4 + 4 + 4 + 56 bytes.
        let count = r.sequence_len("transforms", 72)?;
        let transforms = (0..count)
            .map(|_| {
                Ok(TransformStamped {
                    header: Header::read(r)?,
                    child_frame_id: r.string("child_frame_id")?,
                    translation: Vector3::read(r, "transform.translation")?,
                    rotation: Quaternion::read(r, "transform.rotation")?,
                })
            })
            .collect::<Result<_, CdrError>>()?;
        Ok(Self { transforms })
    }
}

/// `geometry_msgs/msg/PoseStamped`.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct PoseStamped {
    pub header: Header,
    pub position: Vector3,
    pub orientation: Quaternion,
}

impl RosMessage for PoseStamped {
    const DEFINITION: &'static TypeDefinition = &definitions::POSE_STAMPED;

    fn write_cdr(&self, w: &mut CdrWriter) {
        self.header.write(w);
        self.position.write(w);
        self.orientation.write(w);
    }

    fn read_cdr(r: &mut CdrReader<'_>) -> Result<Self, CdrError> {
        Ok(Self {
            header: Header::read(r)?,
            position: Vector3::read(r, "pose.position")?,
            orientation: Quaternion::read(r, "pose.orientation")?,
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn header() -> Header {
        Header::new(Time { sec: 1_305_031_102, nanosec: 160_407_000 }, "camera_optical")
    }

    fn round_trip<M: RosMessage + PartialEq + std::fmt::Debug>(message: &M) {
        let bytes = message.to_cdr();
        assert_eq!(&M::from_cdr(&bytes).unwrap(), message);
        // Every strict prefix is an error, never a panic.
        for len in 0..bytes.len().saturating_sub(3) {
            assert!(M::from_cdr(&bytes[..len]).is_err(), "{} of {} bytes parsed", len, bytes.len());
        }
    }

    #[test]
    fn image_layout_matches_rclpy() {
        // rclpy's serialize_message of Image(header.stamp=(1, 2), frame_id "c", height 1, width 2,
        // encoding "16UC1", step 4, data [1, 0, 2, 0]).
        let image = Image {
            header: Header::new(Time { sec: 1, nanosec: 2 }, "c"),
            height: 1,
            width: 2,
            encoding: "16UC1".into(),
            is_bigendian: 0,
            step: 4,
            data: vec![1, 0, 2, 0],
        };
        let expected: Vec<u8> = [
            &[0, 1, 0, 0][..],
            &[1, 0, 0, 0, 2, 0, 0, 0],
            &[2, 0, 0, 0, b'c', 0, 0, 0],
            &[1, 0, 0, 0, 2, 0, 0, 0],
            &[6, 0, 0, 0, b'1', b'6', b'U', b'C', b'1', 0],
            &[0],
            &[0],
            &[4, 0, 0, 0],
            &[4, 0, 0, 0, 1, 0, 2, 0],
        ]
        .concat();
        assert_eq!(image.to_cdr(), expected);
        round_trip(&image);
    }

    #[test]
    fn camera_info_imu_tf_and_pose_round_trip() {
        round_trip(&CameraInfo {
            header: header(),
            height: 480,
            width: 640,
            distortion_model: "plumb_bob".into(),
            d: vec![0.26, -0.95, 0.0, 0.0, 1.16],
            k: [517.3, 0.0, 318.6, 0.0, 516.5, 255.3, 0.0, 0.0, 1.0],
            r: [1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0],
            p: [517.3, 0.0, 318.6, 0.0, 0.0, 516.5, 255.3, 0.0, 0.0, 0.0, 1.0, 0.0],
            binning_x: 1,
            binning_y: 2,
            roi: RegionOfInterest { x_offset: 1, y_offset: 2, height: 3, width: 4, do_rectify: true },
        });
        round_trip(&Imu {
            header: header(),
            orientation: Quaternion { x: 0.1, y: 0.2, z: 0.3, w: 0.9 },
            orientation_covariance: [0.5; 9],
            angular_velocity: Vector3::new(1.0, 2.0, 3.0),
            angular_velocity_covariance: [0.25; 9],
            linear_acceleration: Vector3::new(0.1, 9.8, -0.2),
            linear_acceleration_covariance: [0.125; 9],
        });
        let transform = TransformStamped {
            header: Header::new(Time { sec: 0, nanosec: 0 }, "base_link"),
            child_frame_id: "camera_optical".into(),
            translation: Vector3::new(0.1, 0.0, 0.3),
            rotation: Quaternion { x: 0.5, y: -0.5, z: 0.5, w: -0.5 },
        };
        round_trip(&TfMessage { transforms: vec![transform.clone(), TransformStamped { child_frame_id: "imu".into(), ..transform }] });
        round_trip(&TfMessage::default());
        round_trip(&PoseStamped { header: header(), position: Vector3::new(1.0, -2.0, 0.5), orientation: Quaternion::default() });
    }

    #[test]
    fn times_convert_to_and_from_seconds() {
        assert_eq!(Time::from_seconds(2.5), Time { sec: 2, nanosec: 500_000_000 });
        assert_eq!(Time::from_seconds(-0.25), Time { sec: -1, nanosec: 750_000_000 });
        // An epoch stamp to the precision of its f64 (0.24 µs at 1.3e9 s); `seconds * 1e9` would round to 256 ns steps on top.
        let t = Time::from_seconds(1305031102.160407);
        assert_eq!(t.sec, 1305031102);
        assert!(t.nanosec.abs_diff(160_407_000) < 120, "{t:?}");
        assert_eq!(Time::from_seconds(t.seconds()), t);
        assert_eq!(Time::from_nanos(-1), Time { sec: -1, nanosec: 999_999_999 });
        assert_eq!(Time::from_nanos(i64::MAX).sec, i32::MAX);
        assert_eq!(Time::from_nanos(1_500_000_000).nanos(), 1_500_000_000);
    }
}

//! Writes the simulated stream as a rosbag2 MCAP bag, the messages the node publishes plus the
//! rig's mount and the ground truth: depth (`sensor_msgs/msg/Image`, 16UC1 millimetres or 32FC1
//! metres), `sensor_msgs/msg/CameraInfo` with every frame, `sensor_msgs/msg/Imu`, `/tf_static`
//! (`base_link` → camera, camera → IMU) and the camera's ground-truth pose
//! (`geometry_msgs/msg/PoseStamped` in `world`). Stamps and record times are the simulation's clock
//! (starting at 0), messages in time order.

use std::path::{Path, PathBuf};

use nalgebra::{Isometry3, UnitQuaternion};
use patchwalk_bag::messages::{CameraInfo, Header, Image, Imu, PoseStamped, Quaternion, TfMessage, Time, TransformStamped, Vector3};
use patchwalk_bag::metadata::Qos;
use patchwalk_bag::{BagError, BagSummary, BagWriter, Compression};
use patchwalk_fusion::camera::DepthImage;

use crate::camera::to_millimetres;
use crate::imu::ImuSample;
use crate::sim::Simulator;

/// How depth is encoded in the bag's images.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum DepthEncoding {
    /// `16UC1`: millimetres, 0 = no data (what the node publishes).
    #[default]
    Millimetres16,
    /// `32FC1`: metres, NaN = no data.
    Metres32,
}

impl std::str::FromStr for DepthEncoding {
    type Err = String;

    fn from_str(s: &str) -> Result<Self, Self::Err> {
        match s {
            "16UC1" => Ok(Self::Millimetres16),
            "32FC1" => Ok(Self::Metres32),
            other => Err(format!("depth encoding {other:?} is not 16UC1 or 32FC1")),
        }
    }
}

/// Topic names of the bag (the node's).
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct BagTopics {
    pub image: String,
    pub camera_info: String,
    pub imu: String,
    pub tf_static: String,
    pub groundtruth: String,
}

/// Where the bag goes.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum BagTarget {
    /// One `.mcap` file.
    File(PathBuf),
    /// A bag directory (`metadata.yaml` + `<name>_0.mcap`), which must not exist yet.
    Directory(PathBuf),
}

/// What was written.
#[derive(Debug, Clone, PartialEq)]
pub struct BagRecordSummary {
    pub frames: usize,
    pub imu_samples: usize,
    pub duration_s: f64,
    pub bag: BagSummary,
}

#[derive(Debug, thiserror::Error)]
pub enum BagRecordError {
    #[error(transparent)]
    Bag(#[from] BagError),
    #[error("nothing to record: frames must be ≥ 1")]
    NoFrames,
}

fn transform(stamp: Time, parent: &str, child: &str, pose: &Isometry3<f64>) -> TransformStamped {
    let (t, q) = (pose.translation.vector, pose.rotation);
    TransformStamped {
        header: Header::new(stamp, parent),
        child_frame_id: child.to_string(),
        translation: Vector3::new(t.x, t.y, t.z),
        rotation: Quaternion { x: q.i, y: q.j, z: q.k, w: q.w },
    }
}

/// The depth image message of `depth`.
pub fn depth_image(depth: &DepthImage, encoding: DepthEncoding, header: Header) -> Image {
    let (name, bytes_per_pixel, data): (&str, usize, Vec<u8>) = match encoding {
        DepthEncoding::Millimetres16 => ("16UC1", 2, to_millimetres(depth).iter().flat_map(|mm| mm.to_le_bytes()).collect()),
        DepthEncoding::Metres32 => ("32FC1", 4, depth.depth_m.iter().flat_map(|m| m.to_le_bytes()).collect()),
    };
    Image {
        header,
        height: depth.height as u32,
        width: depth.width as u32,
        encoding: name.into(),
        is_bigendian: 0,
        step: (depth.width * bytes_per_pixel) as u32,
        data,
    }
}

fn imu_message(sample: &ImuSample, sim: &Simulator, header: Header) -> Imu {
    let diagonal = |sigma: f64| {
        let v = sigma * sigma;
        [v, 0.0, 0.0, 0.0, v, 0.0, 0.0, 0.0, v]
    };
    let vector = |v: &nalgebra::Vector3<f64>| Vector3::new(v.x, v.y, v.z);
    let q: &UnitQuaternion<f64> = &sample.world_from_imu;
    let config = &sim.config.imu;
    Imu {
        header,
        orientation: Quaternion { x: q.i, y: q.j, z: q.k, w: q.w },
        orientation_covariance: diagonal(config.orientation_noise_deg.to_radians()),
        angular_velocity: vector(&sample.angular_velocity_in_imu),
        angular_velocity_covariance: diagonal(config.gyro_noise_radps),
        linear_acceleration: vector(&sample.linear_acceleration_in_imu),
        linear_acceleration_covariance: diagonal(config.accel_noise_mps2),
    }
}

fn nanos(seconds: f64) -> u64 {
    (seconds * 1e9).round().max(0.0) as u64
}

/// Records `frames` depth frames and the IMU samples over the same time span into `target`,
/// calling `progress(i)` after each frame.
pub fn record_bag(
    sim: &Simulator,
    target: &BagTarget,
    frames: usize,
    encoding: DepthEncoding,
    topics: &BagTopics,
    compression: Compression,
    mut progress: impl FnMut(usize),
) -> Result<BagRecordSummary, BagRecordError> {
    if frames == 0 {
        return Err(BagRecordError::NoFrames);
    }
    let mut bag = match target {
        BagTarget::File(path) => BagWriter::create(path, compression)?,
        BagTarget::Directory(path) => BagWriter::create_directory(path, compression)?,
    };
    let tf_topic = bag.add_topic::<TfMessage>(&topics.tf_static, Qos::Latched)?;
    let info_topic = bag.add_topic::<CameraInfo>(&topics.camera_info, Qos::SensorData)?;
    let image_topic = bag.add_topic::<Image>(&topics.image, Qos::SensorData)?;
    let imu_topic = bag.add_topic::<Imu>(&topics.imu, Qos::SensorData)?;
    let groundtruth_topic = bag.add_topic::<PoseStamped>(&topics.groundtruth, Qos::Reliable(10))?;
    let (camera_frame, imu_frame) = (sim.config.node.camera_frame_id.as_str(), sim.config.node.imu_frame_id.as_str());
    let zero = Time::default();
    let mount = TfMessage {
        transforms: vec![
            transform(zero, "base_link", camera_frame, &sim.base_from_camera),
            transform(zero, camera_frame, imu_frame, &Isometry3::from_parts(Default::default(), sim.imu.camera_from_imu)),
        ],
    };
    bag.write(tf_topic, 0, &mount)?;

    let duration_s = (frames - 1) as f64 / sim.config.camera.rate_hz;
    let imu_samples = (duration_s * sim.config.imu.rate_hz).floor() as usize + 1;
    let k = &sim.camera.intrinsics;
    let mut next_imu = 0;
    for index in 0..frames {
        let frame = sim.depth_frame(index as u64);
        // The IMU samples up to this frame first: the bag is in time order.
        while next_imu < imu_samples {
            let sample = sim.imu_sample(next_imu as u64);
            if sample.timestamp > frame.timestamp {
                break;
            }
            let header = Header::new(Time::from_seconds(sample.timestamp), imu_frame);
            bag.write(imu_topic, nanos(sample.timestamp), &imu_message(&sample, sim, header))?;
            next_imu += 1;
        }
        let stamp = Time::from_seconds(frame.timestamp);
        let at = nanos(frame.timestamp);
        let info = CameraInfo {
            header: Header::new(stamp, camera_frame),
            height: k.height as u32,
            width: k.width as u32,
            distortion_model: "plumb_bob".into(),
            d: vec![0.0; 5],
            k: [k.fx, 0.0, k.cx, 0.0, k.fy, k.cy, 0.0, 0.0, 1.0],
            r: [1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0],
            p: [k.fx, 0.0, k.cx, 0.0, 0.0, k.fy, k.cy, 0.0, 0.0, 0.0, 1.0, 0.0],
            ..CameraInfo::default()
        };
        bag.write(info_topic, at, &info)?;
        bag.write(image_topic, at, &depth_image(&frame.depth, encoding, Header::new(stamp, camera_frame)))?;
        let (t, q) = (frame.world_from_camera.translation.vector, frame.world_from_camera.rotation);
        let pose = PoseStamped {
            header: Header::new(stamp, "world"),
            position: Vector3::new(t.x, t.y, t.z),
            orientation: Quaternion { x: q.i, y: q.j, z: q.k, w: q.w },
        };
        bag.write(groundtruth_topic, at, &pose)?;
        progress(index);
    }
    for index in next_imu..imu_samples {
        let sample = sim.imu_sample(index as u64);
        let header = Header::new(Time::from_seconds(sample.timestamp), imu_frame);
        bag.write(imu_topic, nanos(sample.timestamp), &imu_message(&sample, sim, header))?;
    }
    Ok(BagRecordSummary { frames, imu_samples, duration_s, bag: bag.finish()? })
}

/// A `.mcap` path: a file target; anything else: a bag directory.
pub fn target_for(path: &Path) -> BagTarget {
    if path.extension().is_some_and(|e| e.eq_ignore_ascii_case("mcap")) {
        BagTarget::File(path.to_path_buf())
    } else {
        BagTarget::Directory(path.to_path_buf())
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::config::SimConfig;
    use patchwalk_bag::messages::RosMessage;
    use patchwalk_bag::BagReader;
    use std::ops::ControlFlow;

    fn topics() -> BagTopics {
        BagTopics {
            image: "/camera/depth/image_raw".into(),
            camera_info: "/camera/depth/camera_info".into(),
            imu: "/imu/data".into(),
            tf_static: "/tf_static".into(),
            groundtruth: "/groundtruth".into(),
        }
    }

    #[test]
    fn recorded_bag_holds_the_stream_in_time_order() {
        let dir = tempfile::tempdir().unwrap();
        let sim = Simulator::new(SimConfig::default()).unwrap();
        for (encoding, target) in [
            (DepthEncoding::Millimetres16, BagTarget::File(dir.path().join("sim.mcap"))),
            (DepthEncoding::Metres32, BagTarget::Directory(dir.path().join("sim_bag"))),
        ] {
            let summary = record_bag(&sim, &target, 4, encoding, &topics(), Compression::Zstd, |_| {}).unwrap();
            assert_eq!((summary.frames, summary.imu_samples), (4, 11));
            assert_eq!(summary.bag.messages, 1 + 4 * 3 + 11);
            let path = match &target {
                BagTarget::File(p) | BagTarget::Directory(p) => p.clone(),
            };
            let mut last_time = 0;
            let mut images = Vec::new();
            let mut tf = None;
            BagReader::open(&path)
                .unwrap()
                .for_each(|m| {
                    assert!(m.log_time_ns >= last_time, "{} at {}", m.topic, m.log_time_ns);
                    last_time = m.log_time_ns;
                    match m.topic {
                        "/camera/depth/image_raw" => images.push(m.decode::<Image>().unwrap()),
                        "/tf_static" => tf = Some(m.decode::<TfMessage>().unwrap()),
                        _ => {}
                    }
                    ControlFlow::Continue(())
                })
                .unwrap();
            assert_eq!(images.len(), 4);
            let rendered = sim.depth_frame(2).depth;
            let image = &images[2];
            assert_eq!((image.width as usize, image.height as usize), (rendered.width, rendered.height));
            assert_eq!(image.header.stamp, Time::from_seconds(2.0 / sim.config.camera.rate_hz));
            match encoding {
                DepthEncoding::Millimetres16 => {
                    assert_eq!(image.encoding, "16UC1");
                    assert_eq!(image.data, depth_image(&rendered, encoding, Header::default()).data);
                }
                DepthEncoding::Metres32 => {
                    assert_eq!(image.encoding, "32FC1");
                    let first_valid = rendered.depth_m.iter().position(|d| d.is_finite()).unwrap();
                    let bytes: [u8; 4] = image.data[first_valid * 4..first_valid * 4 + 4].try_into().unwrap();
                    assert_eq!(f32::from_le_bytes(bytes), rendered.depth_m[first_valid]);
                }
            }
            let tf = tf.unwrap();
            assert_eq!(tf.transforms[1].child_frame_id, "imu");
            let q = sim.imu.camera_from_imu;
            assert_eq!(tf.transforms[1].rotation, Quaternion { x: q.i, y: q.j, z: q.k, w: q.w });
            assert_eq!(TfMessage::from_cdr(&tf.to_cdr()).unwrap(), tf);
        }
        assert!(matches!(
            record_bag(
                &sim,
                &BagTarget::File(dir.path().join("x.mcap")),
                0,
                DepthEncoding::default(),
                &topics(),
                Compression::None,
                |_| {}
            ),
            Err(BagRecordError::NoFrames)
        ));
        assert_eq!("32FC1".parse::<DepthEncoding>(), Ok(DepthEncoding::Metres32));
        assert!("rgb8".parse::<DepthEncoding>().is_err());
    }
}

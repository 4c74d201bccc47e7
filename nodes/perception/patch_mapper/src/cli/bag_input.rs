//! A rosbag2 MCAP bag as the input of `patch_mapper replay`: depth images (`sensor_msgs/msg/Image`,
//! 16UC1 millimetres or 32FC1 metres), the camera's `sensor_msgs/msg/CameraInfo`, the IMU's
//! `sensor_msgs/msg/Imu` and, when the bag has one, a ground-truth camera pose topic
//! (`geometry_msgs/msg/PoseStamped`, or `tf2_msgs/msg/TFMessage` with the camera frame as child).
//!
//! The bag is read twice, streaming: a first pass checks every message and keeps the small ones
//! (intrinsics, IMU samples, poses) and the stamps of the good depth frames; the second pass
//! decodes those frames one by one while the pipeline runs. A bad message is skipped with an
//! error naming its topic and index; a file that cannot be read to its end is reported after the
//! frames before the damage have been replayed.

use std::ops::ControlFlow;
use std::path::Path;

use nalgebra::{Isometry3, Quaternion, Translation3, UnitQuaternion, Vector3};
use patchwalk_bag::messages::{CameraInfo, Image, Imu, PoseStamped, TfMessage};
use patchwalk_bag::{BagError, BagMessage, BagReader, MessageError, Problem};
use patchwalk_fusion::camera::{DepthImage, Intrinsics};
use patchwalk_fusion::dataset::{AccelSample, StampedPose};

/// The topics to read.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct BagTopics {
    pub depth: String,
    pub camera_info: String,
    pub imu: String,
    pub groundtruth: String,
}

/// A good depth frame found by the first pass.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct BagFrame {
    pub timestamp: f64,
    /// The message's index on the depth topic.
    pub index: usize,
}

/// What the first pass found.
#[derive(Debug)]
pub struct BagInput {
    pub reader: BagReader,
    pub topics: BagTopics,
    pub intrinsics: Intrinsics,
    pub frames: Vec<BagFrame>,
    /// Accelerometer samples sorted by stamp.
    pub accelerometer: Vec<AccelSample>,
    /// Ground-truth camera poses (`world_from_camera`) sorted by stamp.
    pub groundtruth: Vec<StampedPose>,
    /// Messages skipped, with why.
    pub errors: Vec<MessageError>,
    /// Why the bag could not be read to its end, if it could not.
    pub broken: Option<BagError>,
}

/// Errors that leave nothing to replay.
#[derive(Debug, thiserror::Error)]
pub enum BagInputError {
    #[error(transparent)]
    Bag(#[from] BagError),
    #[error("{path}: no usable {what} on topic {topic}{}", .cause.as_ref().map(|c| format!(" (first problem: {c})")).unwrap_or_default())]
    Missing { path: String, what: &'static str, topic: String, cause: Option<Box<MessageError>> },
}

/// Depth in metres from a `sensor_msgs/Image` (16UC1/mono16 millimetres, 32FC1 metres).
pub fn depth_from_image(message: &BagMessage<'_>, image: &Image) -> Result<DepthImage, MessageError> {
    let invalid = |reason: String| message.error(Problem::Invalid(reason));
    let bytes_per_pixel = match image.encoding.as_str() {
        "16UC1" | "mono16" => 2,
        "32FC1" => 4,
        other => return Err(invalid(format!("encoding {other:?} is not a depth encoding (16UC1 or 32FC1)"))),
    };
    let (width, height, step) = (image.width as usize, image.height as usize, image.step as usize);
    if width == 0 || height == 0 {
        return Err(invalid(format!("image is {width}x{height}")));
    }
    if step < width * bytes_per_pixel {
        return Err(invalid(format!("step {step} is less than width × {bytes_per_pixel} bytes = {}", width * bytes_per_pixel)));
    }
    if image.data.len() < height * step {
        return Err(invalid(format!(
            "data is {} bytes, shorter than height × step = {height} × {step} = {}",
            image.data.len(),
            height * step
        )));
    }
    let big_endian = image.is_bigendian != 0;
    let mut depth_m = Vec::with_capacity(width * height);
    for row in image.data.chunks_exact(step).take(height) {
        for pixel in row[..width * bytes_per_pixel].chunks_exact(bytes_per_pixel) {
            let value = match *pixel {
                [a, b] => {
                    let mm = if big_endian { u16::from_be_bytes([a, b]) } else { u16::from_le_bytes([a, b]) };
                    if mm == 0 {
                        f32::NAN
                    } else {
                        (f64::from(mm) * 0.001) as f32
                    }
                }
                [a, b, c, d] => {
                    if big_endian {
                        f32::from_be_bytes([a, b, c, d])
                    } else {
                        f32::from_le_bytes([a, b, c, d])
                    }
                }
                _ => f32::NAN,
            };
            depth_m.push(value);
        }
    }
    DepthImage::new(width, height, depth_m).map_err(|e| invalid(e.to_string()))
}

/// Pinhole intrinsics of a `CameraInfo` (`k` = [fx 0 cx; 0 fy cy; 0 0 1]); distortion is ignored.
pub fn intrinsics_from_camera_info(message: &BagMessage<'_>, info: &CameraInfo) -> Result<Intrinsics, MessageError> {
    Intrinsics::new(info.width as usize, info.height as usize, info.k[0], info.k[4], info.k[2], info.k[5])
        .map_err(|e| message.error(Problem::Invalid(e.to_string())))
}

fn pose(message: &BagMessage<'_>, translation: [f64; 3], rotation: [f64; 4]) -> Result<Isometry3<f64>, MessageError> {
    if !translation.iter().chain(&rotation).all(|v| v.is_finite()) {
        return Err(message.error(Problem::Invalid("pose has non-finite values".into())));
    }
    let [x, y, z, w] = rotation;
    let norm = (x * x + y * y + z * z + w * w).sqrt();
    if (norm - 1.0).abs() > 1e-3 {
        return Err(message.error(Problem::Invalid(format!("orientation quaternion has norm {norm}, not 1"))));
    }
    let [tx, ty, tz] = translation;
    Ok(Isometry3::from_parts(Translation3::new(tx, ty, tz), UnitQuaternion::from_quaternion(Quaternion::new(w, x, y, z))))
}

/// Ground-truth poses from a PoseStamped or TFMessage message (the transform whose child is the camera frame).
fn groundtruth_poses(message: &BagMessage<'_>, camera_frame: Option<&str>) -> Result<Vec<StampedPose>, MessageError> {
    if message.schema_name == "tf2_msgs/msg/TFMessage" {
        let tf: TfMessage = message.decode()?;
        let only_one = tf.transforms.len() == 1;
        tf.transforms
            .iter()
            .filter(|t| only_one || camera_frame.is_some_and(|frame| t.child_frame_id == frame))
            .map(|t| {
                let (p, q) = (t.translation, t.rotation);
                Ok(StampedPose {
                    timestamp: t.header.stamp.seconds(),
                    world_from_camera: pose(message, [p.x, p.y, p.z], [q.x, q.y, q.z, q.w])?,
                })
            })
            .collect()
    } else {
        let pose_stamped: PoseStamped = message.decode()?;
        let (p, q) = (pose_stamped.position, pose_stamped.orientation);
        Ok(vec![StampedPose {
            timestamp: pose_stamped.header.stamp.seconds(),
            world_from_camera: pose(message, [p.x, p.y, p.z], [q.x, q.y, q.z, q.w])?,
        }])
    }
}

impl BagInput {
    /// First pass over the bag at `path` (an `.mcap` file or a bag directory).
    pub fn open(path: &Path, topics: BagTopics) -> Result<Self, BagInputError> {
        Self::from_reader(BagReader::open(path)?, topics)
    }

    /// First pass over an opened bag (a file, a directory or bytes in memory).
    pub fn from_reader(reader: BagReader, topics: BagTopics) -> Result<Self, BagInputError> {
        let path = reader.path().to_path_buf();
        let mut intrinsics: Option<Intrinsics> = None;
        let mut frames = Vec::new();
        let mut sizes = Vec::new();
        let mut accelerometer = Vec::new();
        let mut groundtruth = Vec::new();
        let mut errors = Vec::new();
        let mut camera_frame: Option<String> = None;
        // Ground-truth messages wait for the camera frame (known from the first good image).
        let mut groundtruth_messages: Vec<(String, usize, String, Vec<u8>)> = Vec::new();
        let result = reader.for_each(|message| {
            let topic = message.topic;
            if topic == topics.depth {
                match message.decode::<Image>().and_then(|image| depth_from_image(message, &image).map(|d| (image, d))) {
                    Ok((image, depth)) => {
                        camera_frame.get_or_insert_with(|| image.header.frame_id.clone());
                        frames.push(BagFrame { timestamp: image.header.stamp.seconds(), index: message.index });
                        sizes.push((depth.width, depth.height));
                    }
                    Err(err) => errors.push(err),
                }
            } else if topic == topics.camera_info {
                match message.decode::<CameraInfo>().and_then(|info| intrinsics_from_camera_info(message, &info)) {
                    Ok(k) => {
                        intrinsics.get_or_insert(k);
                    }
                    Err(err) => errors.push(err),
                }
            } else if topic == topics.imu {
                match message.decode::<Imu>() {
                    Ok(imu) => {
                        let a = imu.linear_acceleration;
                        if [a.x, a.y, a.z].iter().all(|v| v.is_finite()) {
                            accelerometer.push(AccelSample {
                                timestamp: imu.header.stamp.seconds(),
                                acceleration_in_imu: Vector3::new(a.x, a.y, a.z),
                            });
                        } else {
                            errors.push(message.error(Problem::Invalid("linear_acceleration has non-finite values".into())));
                        }
                    }
                    Err(err) => errors.push(err),
                }
            } else if topic == topics.groundtruth {
                groundtruth_messages.push((
                    message.schema_name.to_string(),
                    message.index,
                    message.message_encoding.to_string(),
                    message.data.to_vec(),
                ));
            }
            ControlFlow::Continue(())
        });
        let broken = result.err();
        for (schema_name, index, message_encoding, data) in &groundtruth_messages {
            let message = BagMessage {
                topic: &topics.groundtruth,
                schema_name,
                schema_encoding: "ros2msg",
                message_encoding,
                index: *index,
                log_time_ns: 0,
                data,
            };
            match groundtruth_poses(&message, camera_frame.as_deref()) {
                Ok(poses) => groundtruth.extend(poses),
                Err(err) => errors.push(err),
            }
        }
        let path_text = path.display().to_string();
        let missing = |what, topic: &str, errors: &[MessageError]| BagInputError::Missing {
            path: path_text.clone(),
            what,
            topic: topic.to_string(),
            cause: errors.iter().find(|e| e.topic == topic).cloned().map(Box::new),
        };
        let Some(intrinsics) = intrinsics else {
            return Err(match broken {
                Some(err) if errors.is_empty() => BagInputError::Bag(err),
                _ => missing("CameraInfo", &topics.camera_info, &errors),
            });
        };
        // Frames of another size than the camera's are skipped.
        let mut kept = Vec::with_capacity(frames.len());
        for (frame, (width, height)) in frames.into_iter().zip(sizes) {
            if (width, height) == (intrinsics.width, intrinsics.height) {
                kept.push(frame);
            } else {
                errors.push(MessageError {
                    topic: topics.depth.clone(),
                    index: frame.index,
                    problem: Problem::Invalid(format!(
                        "image is {width}x{height} but the CameraInfo is for {}x{}",
                        intrinsics.width, intrinsics.height
                    )),
                });
            }
        }
        if kept.is_empty() {
            return Err(match broken {
                Some(err) if errors.is_empty() => BagInputError::Bag(err),
                _ => missing("depth images", &topics.depth, &errors),
            });
        }
        accelerometer.sort_by(|a: &AccelSample, b| a.timestamp.total_cmp(&b.timestamp));
        groundtruth.sort_by(|a: &StampedPose, b| a.timestamp.total_cmp(&b.timestamp));
        errors.sort_by(|a, b| (&a.topic, a.index).cmp(&(&b.topic, b.index)));
        Ok(Self { reader, topics, intrinsics, frames: kept, accelerometer, groundtruth, errors, broken })
    }

    /// Second pass: decodes the first `count` good frames in order and hands each to `send`
    /// (position in `frames`, depth) until `send` returns false.
    pub fn stream_depth(
        &self,
        count: usize,
        mut send: impl FnMut(usize, Result<DepthImage, MessageError>) -> bool,
    ) -> Result<(), BagError> {
        let mut next = 0;
        self.reader.for_each(|message| {
            let Some(frame) = self.frames.get(next).filter(|_| next < count) else {
                return ControlFlow::Break(());
            };
            if message.topic != self.topics.depth || message.index != frame.index {
                return ControlFlow::Continue(());
            }
            let depth = message.decode::<Image>().and_then(|image| depth_from_image(message, &image));
            let keep_going = send(next, depth);
            next += 1;
            if keep_going {
                ControlFlow::Continue(())
            } else {
                ControlFlow::Break(())
            }
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use patchwalk_bag::messages::{Header, RosMessage, Time};

    fn message<'a>(data: &'a [u8]) -> BagMessage<'a> {
        BagMessage {
            topic: "/camera/depth/image_raw",
            schema_name: "sensor_msgs/msg/Image",
            schema_encoding: "ros2msg",
            message_encoding: "cdr",
            index: 4,
            log_time_ns: 0,
            data,
        }
    }

    fn image(encoding: &str, step: u32, data: Vec<u8>) -> Image {
        Image { header: Header::new(Time::default(), "c"), height: 2, width: 2, encoding: encoding.into(), is_bigendian: 0, step, data }
    }

    #[test]
    fn depth_encodings_convert_to_metres() {
        let mm: Vec<u8> = [1000u16, 0, 250, 65535].iter().flat_map(|v| v.to_le_bytes()).collect();
        let depth = depth_from_image(&message(&[]), &image("16UC1", 4, mm)).unwrap();
        assert_eq!(depth.get(0, 0), Some(1.0));
        assert!(depth.get(1, 0).is_none());
        assert_eq!(depth.get(0, 1), Some(0.25));
        // Rows padded to 12 bytes: the padding (9.0) is not read.
        let metres: Vec<u8> = [1.5f32, f32::NAN, 9.0, 2.0, -1.0, 9.0].iter().flat_map(|v| v.to_le_bytes()).collect();
        let depth = depth_from_image(&message(&[]), &image("32FC1", 12, metres)).unwrap();
        assert_eq!(depth.depth_m.len(), 4);
        assert_eq!(depth.get(0, 0), Some(1.5));
        assert!(depth.get(1, 0).is_none());
        assert_eq!(depth.get(0, 1), Some(2.0));
        assert!(depth.get(1, 1).is_none());
    }

    #[test]
    fn bad_images_and_intrinsics_name_topic_and_index() {
        let short = depth_from_image(&message(&[]), &image("16UC1", 4, vec![0; 5])).unwrap_err().to_string();
        assert_eq!(short, "topic /camera/depth/image_raw message 4: data is 5 bytes, shorter than height × step = 2 × 4 = 8");
        let encoding = depth_from_image(&message(&[]), &image("rgb8", 6, vec![0; 12])).unwrap_err().to_string();
        assert!(encoding.contains("encoding \"rgb8\" is not a depth encoding"), "{encoding}");
        let step = depth_from_image(&message(&[]), &image("32FC1", 4, vec![0; 16])).unwrap_err().to_string();
        assert!(step.contains("step 4 is less than width × 4 bytes = 8"), "{step}");
        let info =
            CameraInfo { width: 640, height: 480, k: [f64::NAN, 0.0, 320.0, 0.0, 525.0, 240.0, 0.0, 0.0, 1.0], ..CameraInfo::default() };
        let bytes = info.to_cdr();
        let err = intrinsics_from_camera_info(&message(&bytes), &info).unwrap_err().to_string();
        assert!(err.starts_with("topic /camera/depth/image_raw message 4: invalid intrinsics: fx = NaN"), "{err}");
    }
}

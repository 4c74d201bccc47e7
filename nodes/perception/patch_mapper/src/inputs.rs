//! The node's inputs as bytes: entry points that take a serialized payload as it arrives on the
//! wire (encapsulation header + CDR, decoded by [`patchwalk_ros::wire::decode`], the decoder of the
//! node's subscriptions) and run the node's checks and conversions on it, without ROS. The fuzz
//! targets of `nodes/fuzz` call them, and the regression tests replay every stored input of
//! `tests/data/fuzz/` through them, so an input that once crashed the node stays a test.

use patchwalk_bag::BagReader;
use patchwalk_fusion::camera::Intrinsics;
use patchwalk_fusion::tracking::TrackerConfig;
use patchwalk_mapping::pipeline::{default_mapper_config, Pipeline, PipelineConfig, PipelineError, StampWindow};
use patchwalk_msgs::builtin_interfaces::msg::Time;
use patchwalk_msgs::sensor_msgs::msg::{CameraInfo, Image, Imu};
use patchwalk_ros::wire::{self, WireError};

use crate::bag_input::{BagInput, BagInputError, BagTopics};
use crate::convert::{self, CameraInfoError, ImageError, ImuError};

/// The node clock the replayed inputs are checked against (s): stamps are judged by
/// [`StampWindow::default`] around it, as the node judges them around its own clock.
pub const REPLAY_NOW_S: f64 = 1.0e9;

/// Largest depth image [`pipeline_frame`] runs through the pipeline (pixels): one frame of this size
/// takes milliseconds, so a fuzzer gets through thousands of frames a minute. Larger frames are
/// refused as over the budget (the node itself takes up to 16,384 px a side).
pub const PIPELINE_MAX_PIXELS: usize = 64 * 48;

/// Birds-eye raycast resolution of the [`pipeline_frame`] pipeline (px; the node uses 200).
const PIPELINE_BIRDS_EYE_PX: usize = 48;

/// Why a serialized input was refused: each names the stage.
#[derive(Debug, thiserror::Error)]
pub enum InputError {
    #[error("empty input")]
    Empty,
    #[error("unknown input selector {0}")]
    Selector(u8),
    #[error("payload length prefix {length} exceeds the {left} bytes left")]
    Length { length: usize, left: usize },
    #[error(transparent)]
    Wire(#[from] WireError),
    #[error("depth image rejected: {0}")]
    Image(#[from] ImageError),
    #[error("CameraInfo rejected: {0}")]
    CameraInfo(#[from] CameraInfoError),
    #[error("IMU sample rejected: {0}")]
    Imu(#[from] ImuError),
    #[error("depth image is {depth_width}x{depth_height} but CameraInfo says {info_width}x{info_height}")]
    SizeMismatch { depth_width: usize, depth_height: usize, info_width: usize, info_height: usize },
    #[error("depth image of {pixels} px is over the replay budget of {PIPELINE_MAX_PIXELS} px")]
    Budget { pixels: usize },
    #[error(transparent)]
    Pipeline(#[from] PipelineError),
    #[error(transparent)]
    Bag(#[from] BagInputError),
}

/// What one sensor message turned into.
#[derive(Debug)]
pub enum SensorOutput {
    Depth { width: usize, height: usize, valid: usize },
    Intrinsics(Intrinsics),
    Acceleration([f64; 3]),
}

/// One message of the node's sensor topics: byte 0 selects the topic (0 depth image, 1 CameraInfo,
/// 2 IMU), the rest is its serialized payload. Decoded and converted as the node does; stamps are
/// checked against [`REPLAY_NOW_S`].
pub fn sensor_message(bytes: &[u8]) -> Result<SensorOutput, InputError> {
    let (&selector, payload) = bytes.split_first().ok_or(InputError::Empty)?;
    match selector {
        0 => {
            let msg: Image = wire::decode(payload)?;
            let depth = convert::depth_image(&msg)?;
            check_stamp("depth", &msg.header.stamp)?;
            Ok(SensorOutput::Depth { width: depth.width, height: depth.height, valid: depth.valid_count() })
        }
        1 => Ok(SensorOutput::Intrinsics(convert::intrinsics(&wire::decode::<CameraInfo>(payload)?)?)),
        2 => {
            let msg: Imu = wire::decode(payload)?;
            let acceleration = convert::imu_acceleration(&msg)?;
            check_stamp("IMU", &msg.header.stamp)?;
            Ok(SensorOutput::Acceleration(acceleration.into()))
        }
        other => Err(InputError::Selector(other)),
    }
}

/// What the pipeline made of a frame.
#[derive(Debug)]
pub struct FrameSummary {
    pub patches_in_map: usize,
    pub seeds: usize,
}

/// One depth frame through the node's conversions and its whole per-frame pipeline (gravity, TSDF
/// fusion + ICP, birds-eye raycast, patch mapping) on a small budget ([`PIPELINE_MAX_PIXELS`], a
/// 48 px birds-eye view, a 2 ms mapping time limit). The bytes are three serialized payloads:
/// `u16` little-endian length + CameraInfo, `u16` length + Imu, then the Image to the end.
pub fn pipeline_frame(bytes: &[u8]) -> Result<FrameSummary, InputError> {
    let (info, rest) = length_prefixed(bytes)?;
    let (imu, image) = length_prefixed(rest)?;
    let intrinsics = convert::intrinsics(&wire::decode::<CameraInfo>(info)?)?;
    let imu: Imu = wire::decode(imu)?;
    let acceleration = convert::imu_acceleration(&imu)?;
    let image: Image = wire::decode(image)?;
    let depth = convert::depth_image(&image)?;
    if (depth.width, depth.height) != (intrinsics.width, intrinsics.height) {
        return Err(InputError::SizeMismatch {
            depth_width: depth.width,
            depth_height: depth.height,
            info_width: intrinsics.width,
            info_height: intrinsics.height,
        });
    }
    let pixels = depth.width * depth.height;
    if pixels > PIPELINE_MAX_PIXELS {
        return Err(InputError::Budget { pixels });
    }
    let imu_stamp = check_stamp("IMU", &imu.header.stamp)?;
    let depth_stamp = check_stamp("depth", &image.header.stamp)?;
    let mut tracker = TrackerConfig::default();
    tracker.birds_eye.resolution_px = PIPELINE_BIRDS_EYE_PX;
    let mut mapper = default_mapper_config();
    mapper.time_limit_ms = 2.0;
    let mut pipeline = Pipeline::new(PipelineConfig::default(), tracker, mapper, intrinsics)?;
    pipeline.push_imu(imu_stamp, acceleration)?;
    let output = pipeline.process(&depth, depth_stamp)?;
    Ok(FrameSummary { patches_in_map: pipeline.map().len(), seeds: output.seeds.len() })
}

/// The bytes [`pipeline_frame`] takes, from the three messages (seeds and tests are made with it).
pub fn encode_pipeline_frame(info: &CameraInfo, imu: &Imu, image: &Image) -> Result<Vec<u8>, InputError> {
    let mut bytes = Vec::new();
    for payload in [wire::encode(info)?, wire::encode(imu)?] {
        let length = u16::try_from(payload.len()).map_err(|_| InputError::Length { length: payload.len(), left: usize::from(u16::MAX) })?;
        bytes.extend_from_slice(&length.to_le_bytes());
        bytes.extend_from_slice(&payload);
    }
    bytes.extend_from_slice(&wire::encode(image)?);
    Ok(bytes)
}

/// The topics [`bag`] reads: `patch_mapper replay`'s defaults (the node's topics in the root
/// namespace and `/groundtruth`).
pub fn replay_bag_topics() -> BagTopics {
    BagTopics {
        depth: "/camera/depth/image_raw".into(),
        camera_info: "/camera/depth/camera_info".into(),
        imu: "/imu/data".into(),
        groundtruth: "/groundtruth".into(),
    }
}

/// What `patch_mapper replay` would get from a bag.
#[derive(Debug)]
pub struct BagSummary {
    /// Depth frames decoded by the second pass.
    pub frames: usize,
    pub imu_samples: usize,
    pub groundtruth_poses: usize,
    /// Messages skipped (each named by topic and index).
    pub skipped: usize,
    /// The file could not be read to its end.
    pub broken: bool,
}

/// An MCAP file's bytes through the bag reader of `patch_mapper replay` ([`BagReader::from_bytes`],
/// [`BagInput`]) with [`replay_bag_topics`]: the first pass checks every message, the second
/// decodes every good depth frame.
pub fn bag(bytes: &[u8]) -> Result<BagSummary, InputError> {
    let input = BagInput::from_reader(BagReader::from_bytes("input.mcap", bytes), replay_bag_topics())?;
    let mut frames = 0;
    let mut skipped = input.errors.len();
    let streamed = input.stream_depth(input.frames.len(), |_, depth| {
        match depth {
            Ok(_) => frames += 1,
            Err(_) => skipped += 1,
        }
        true
    });
    Ok(BagSummary {
        frames,
        imu_samples: input.accelerometer.len(),
        groundtruth_poses: input.groundtruth.len(),
        skipped,
        broken: input.broken.is_some() || streamed.is_err(),
    })
}

/// A stamp in seconds, refused outside [`StampWindow::default`] around [`REPLAY_NOW_S`].
fn check_stamp(input: &'static str, stamp: &Time) -> Result<f64, InputError> {
    let seconds = f64::from(stamp.sec) + f64::from(stamp.nanosec) * 1e-9;
    StampWindow::default().check(input, seconds, REPLAY_NOW_S)?;
    Ok(seconds)
}

/// Split off a `u16` little-endian length-prefixed payload.
fn length_prefixed(bytes: &[u8]) -> Result<(&[u8], &[u8]), InputError> {
    let (Some(prefix), rest) = (bytes.get(..2), bytes.get(2..).unwrap_or_default()) else {
        return Err(InputError::Length { length: 2, left: bytes.len() });
    };
    let length = usize::from(u16::from_le_bytes([prefix[0], prefix[1]]));
    if length > rest.len() {
        return Err(InputError::Length { length, left: rest.len() });
    }
    Ok(rest.split_at(length))
}

#[cfg(test)]
mod tests;

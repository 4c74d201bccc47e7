//! rosbag2's bag description (`metadata.yaml`, format version 9 as ROS 2 Jazzy writes it, also
//! stored in the MCAP as the `rosbag2` metadata record) and the QoS profiles recorded per topic.

use serde::{Deserialize, Serialize};

/// The rosbag2 metadata format version written (Jazzy).
pub const METADATA_VERSION: u32 = 9;

/// A ROS 2 duration as rosbag2 writes it in QoS profiles.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, Serialize, Deserialize)]
pub struct QosDuration {
    pub sec: i64,
    pub nsec: u64,
}

/// One offered QoS profile of a topic's publisher (v9 spelling: names, not numbers).
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
pub struct QosProfile {
    pub history: String,
    pub depth: u32,
    pub reliability: String,
    pub durability: String,
    pub deadline: QosDuration,
    pub lifespan: QosDuration,
    pub liveliness: String,
    pub liveliness_lease_duration: QosDuration,
    pub avoid_ros_namespace_conventions: bool,
}

/// The QoS a recorded topic was published with; `ros2 bag play` offers it again.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Qos {
    /// Sensor data: best effort, volatile, keep last 5.
    SensorData,
    /// Reliable, volatile, keep last `depth`.
    Reliable(u32),
    /// Reliable, transient local, keep last 1 (`/tf_static`: late subscribers get it).
    Latched,
}

impl Qos {
    pub fn profile(self) -> QosProfile {
        let (reliability, durability, depth) = match self {
            Qos::SensorData => ("best_effort", "volatile", 5),
            Qos::Reliable(depth) => ("reliable", "volatile", depth),
            Qos::Latched => ("reliable", "transient_local", 1),
        };
        QosProfile {
            history: "keep_last".into(),
            depth,
            reliability: reliability.into(),
            durability: durability.into(),
            deadline: QosDuration::default(),
            lifespan: QosDuration::default(),
            liveliness: "automatic".into(),
            liveliness_lease_duration: QosDuration::default(),
            avoid_ros_namespace_conventions: false,
        }
    }
}

#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, Serialize, Deserialize)]
pub struct Nanoseconds {
    pub nanoseconds: u64,
}

#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, Serialize, Deserialize)]
pub struct NanosecondsSinceEpoch {
    pub nanoseconds_since_epoch: u64,
}

#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
pub struct TopicMetadata {
    pub name: String,
    #[serde(rename = "type")]
    pub type_name: String,
    pub serialization_format: String,
    pub offered_qos_profiles: Vec<QosProfile>,
    pub type_description_hash: String,
}

#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
pub struct TopicWithCount {
    pub topic_metadata: TopicMetadata,
    pub message_count: u64,
}

#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
pub struct FileInformation {
    pub path: String,
    pub starting_time: NanosecondsSinceEpoch,
    pub duration: Nanoseconds,
    pub message_count: u64,
}

/// `rosbag2_bagfile_information`.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
pub struct BagInformation {
    pub version: u32,
    pub storage_identifier: String,
    pub duration: Nanoseconds,
    pub starting_time: NanosecondsSinceEpoch,
    pub message_count: u64,
    pub topics_with_message_count: Vec<TopicWithCount>,
    pub compression_format: String,
    pub compression_mode: String,
    pub relative_file_paths: Vec<String>,
    pub files: Vec<FileInformation>,
    pub custom_data: Option<std::collections::BTreeMap<String, String>>,
    pub ros_distro: String,
}

/// The top level of `metadata.yaml`.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
pub struct MetadataFile {
    pub rosbag2_bagfile_information: BagInformation,
}

/// What a reader needs of a `metadata.yaml` written by any rosbag2 version: the storage plugin and
/// the bag's files, in order. Other keys are not looked at.
#[derive(Debug, Clone, PartialEq, Eq, Deserialize)]
pub struct StorageFiles {
    pub storage_identifier: String,
    pub relative_file_paths: Vec<String>,
}

#[derive(Debug, Deserialize)]
pub(crate) struct StorageFilesFile {
    pub rosbag2_bagfile_information: StorageFiles,
}

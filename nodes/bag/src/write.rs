//! Writing a bag as rosbag2 does: an MCAP file with profile `ros2`, one ros2msg schema per type
//! (with its dependent types), one CDR channel per topic carrying its offered QoS, chunked and
//! indexed, and the `rosbag2` metadata record; for a bag directory also `metadata.yaml`.

use std::collections::BTreeMap;
use std::io::BufWriter;
use std::marker::PhantomData;
use std::path::{Path, PathBuf};

use crate::messages::RosMessage;
use crate::metadata::{
    BagInformation, FileInformation, MetadataFile, Nanoseconds, NanosecondsSinceEpoch, Qos, TopicMetadata, TopicWithCount, METADATA_VERSION,
};
use crate::BagError;

/// Chunk compression.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum Compression {
    /// zstd, as `ros2 bag record` writes MCAP by default.
    #[default]
    Zstd,
    Lz4,
    None,
}

/// A topic added to a [`BagWriter`], typed by its message.
#[derive(Debug)]
pub struct Topic<M> {
    index: usize,
    message: PhantomData<fn(&M)>,
}

impl<M> Clone for Topic<M> {
    fn clone(&self) -> Self {
        *self
    }
}

impl<M> Copy for Topic<M> {}

struct TopicState {
    name: String,
    type_name: &'static str,
    qos: Qos,
    channel_id: u16,
    count: u64,
}

/// What a finished bag holds.
#[derive(Debug, Clone, PartialEq)]
pub struct BagSummary {
    /// The MCAP file.
    pub file: PathBuf,
    pub messages: u64,
    /// Message payload bytes (before compression).
    pub payload_bytes: u64,
    /// Size of the MCAP file.
    pub file_bytes: u64,
    /// Messages per topic, in the order the topics were added.
    pub topics: Vec<(String, u64)>,
}

/// Writes a rosbag2 MCAP bag.
pub struct BagWriter {
    writer: mcap::Writer<BufWriter<std::fs::File>>,
    file: PathBuf,
    /// The bag directory, when `metadata.yaml` is to be written.
    directory: Option<PathBuf>,
    topics: Vec<TopicState>,
    schemas: BTreeMap<&'static str, u16>,
    first_ns: Option<u64>,
    last_ns: u64,
    payload_bytes: u64,
}

impl BagWriter {
    /// Creates (or replaces) the MCAP file `path`.
    pub fn create(path: &Path, compression: Compression) -> Result<Self, BagError> {
        if let Some(parent) = path.parent().filter(|p| !p.as_os_str().is_empty()) {
            std::fs::create_dir_all(parent).map_err(|source| BagError::Io { path: parent.to_path_buf(), source })?;
        }
        let file = std::fs::File::create(path).map_err(|source| BagError::Io { path: path.to_path_buf(), source })?;
        let options = mcap::WriteOptions::new()
            .profile("ros2")
            .library(format!("patchwalk_bag {}", env!("CARGO_PKG_VERSION")))
            .compression(match compression {
                Compression::Zstd => Some(mcap::Compression::Zstd),
                Compression::Lz4 => Some(mcap::Compression::Lz4),
                Compression::None => None,
            });
        let writer = options
            .create(BufWriter::with_capacity(1 << 20, file))
            .map_err(|source| BagError::Mcap { path: path.to_path_buf(), source })?;
        Ok(Self {
            writer,
            file: path.to_path_buf(),
            directory: None,
            topics: Vec::new(),
            schemas: BTreeMap::new(),
            first_ns: None,
            last_ns: 0,
            payload_bytes: 0,
        })
    }

    /// Creates the bag directory `dir` (it must not exist, as with `ros2 bag record -o`): the MCAP
    /// file `<dir name>_0.mcap` and, on [`finish`](Self::finish), `metadata.yaml`.
    pub fn create_directory(dir: &Path, compression: Compression) -> Result<Self, BagError> {
        if dir.exists() {
            return Err(BagError::Layout { path: dir.to_path_buf(), reason: "already exists".into() });
        }
        std::fs::create_dir_all(dir).map_err(|source| BagError::Io { path: dir.to_path_buf(), source })?;
        let name = dir.file_name().map_or_else(|| "bag".into(), |n| n.to_string_lossy().into_owned());
        let mut writer = Self::create(&dir.join(format!("{name}_0.mcap")), compression)?;
        writer.directory = Some(dir.to_path_buf());
        Ok(writer)
    }

    fn mcap_error(&self) -> impl Fn(mcap::McapError) -> BagError + '_ {
        |source| BagError::Mcap { path: self.file.clone(), source }
    }

    /// Adds a topic of message type `M`, published with `qos`.
    pub fn add_topic<M: RosMessage>(&mut self, name: &str, qos: Qos) -> Result<Topic<M>, BagError> {
        let definition = M::DEFINITION;
        let schema_id = match self.schemas.get(definition.name) {
            Some(id) => *id,
            None => {
                let id = self
                    .writer
                    .add_schema(definition.name, "ros2msg", definition.schema_text().as_bytes())
                    .map_err(|source| BagError::Mcap { path: self.file.clone(), source })?;
                self.schemas.insert(definition.name, id);
                id
            }
        };
        let qos_text = serde_yaml_ng::to_string(&vec![qos.profile()])
            .map_err(|e| BagError::Layout { path: self.file.clone(), reason: format!("QoS profile: {e}") })?;
        let metadata = BTreeMap::from([("offered_qos_profiles".to_string(), qos_text.trim_end().to_string())]);
        let channel_id = self.writer.add_channel(schema_id, name, "cdr", &metadata).map_err(self.mcap_error())?;
        self.topics.push(TopicState { name: name.to_string(), type_name: definition.name, qos, channel_id, count: 0 });
        Ok(Topic { index: self.topics.len() - 1, message: PhantomData })
    }

    /// Writes `message` on `topic`, recorded at `log_time_ns`; returns its serialised size.
    pub fn write<M: RosMessage>(&mut self, topic: Topic<M>, log_time_ns: u64, message: &M) -> Result<usize, BagError> {
        let data = message.to_cdr();
        let state = self.topics.get_mut(topic.index).ok_or_else(|| BagError::Layout {
            path: self.file.clone(),
            reason: format!("topic {} was not added to this bag", topic.index),
        })?;
        let header = mcap::records::MessageHeader {
            channel_id: state.channel_id,
            sequence: u32::try_from(state.count).unwrap_or(u32::MAX),
            log_time: log_time_ns,
            publish_time: log_time_ns,
        };
        state.count += 1;
        self.first_ns = Some(self.first_ns.map_or(log_time_ns, |first| first.min(log_time_ns)));
        self.last_ns = self.last_ns.max(log_time_ns);
        self.payload_bytes += data.len() as u64;
        self.writer.write_to_known_channel(&header, &data).map_err(|source| BagError::Mcap { path: self.file.clone(), source })?;
        Ok(data.len())
    }

    fn information(&self) -> BagInformation {
        let start = self.first_ns.unwrap_or(0);
        let duration = Nanoseconds { nanoseconds: self.last_ns.saturating_sub(start) };
        let starting_time = NanosecondsSinceEpoch { nanoseconds_since_epoch: start };
        let message_count = self.topics.iter().map(|t| t.count).sum();
        let file_name = self.file.file_name().map_or_else(String::new, |n| n.to_string_lossy().into_owned());
        BagInformation {
            version: METADATA_VERSION,
            storage_identifier: "mcap".into(),
            duration,
            starting_time,
            message_count,
            topics_with_message_count: self
                .topics
                .iter()
                .map(|t| TopicWithCount {
                    topic_metadata: TopicMetadata {
                        name: t.name.clone(),
                        type_name: t.type_name.into(),
                        serialization_format: "cdr".into(),
                        offered_qos_profiles: vec![t.qos.profile()],
                        type_description_hash: String::new(),
                    },
                    message_count: t.count,
                })
                .collect(),
            // Chunk compression inside MCAP is the storage's business: rosbag2 reports no bag compression.
            compression_format: String::new(),
            compression_mode: String::new(),
            relative_file_paths: vec![file_name.clone()],
            files: vec![FileInformation { path: file_name, starting_time, duration, message_count }],
            custom_data: None,
            ros_distro: "jazzy".into(),
        }
    }

    /// Writes the metadata record, the summary and the index, and `metadata.yaml` for a bag directory.
    pub fn finish(mut self) -> Result<BagSummary, BagError> {
        let information = self.information();
        let serialized = to_yaml(&self.file, &information)?;
        let record = mcap::records::Metadata {
            name: "rosbag2".into(),
            metadata: BTreeMap::from([("serialized_metadata".to_string(), serialized), ("ROS_DISTRO".to_string(), "jazzy".to_string())]),
        };
        self.writer.write_metadata(&record).map_err(|source| BagError::Mcap { path: self.file.clone(), source })?;
        self.writer.finish().map_err(|source| BagError::Mcap { path: self.file.clone(), source })?;
        if let Some(dir) = &self.directory {
            let text = to_yaml(&self.file, &MetadataFile { rosbag2_bagfile_information: information.clone() })?;
            let path = dir.join("metadata.yaml");
            std::fs::write(&path, text).map_err(|source| BagError::Io { path, source })?;
        }
        let file_bytes = std::fs::metadata(&self.file).map(|m| m.len()).unwrap_or(0);
        Ok(BagSummary {
            file: self.file.clone(),
            messages: information.message_count,
            payload_bytes: self.payload_bytes,
            file_bytes,
            topics: self.topics.iter().map(|t| (t.name.clone(), t.count)).collect(),
        })
    }
}

fn to_yaml<T: serde::Serialize>(file: &Path, value: &T) -> Result<String, BagError> {
    serde_yaml_ng::to_string(value).map_err(|e| BagError::Layout { path: file.to_path_buf(), reason: format!("rosbag2 metadata: {e}") })
}

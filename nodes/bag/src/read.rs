//! Reading a bag: every message of a `.mcap` file (or of the files a bag directory's
//! `metadata.yaml` lists, or of an MCAP file's bytes already in memory), in file order, streamed
//! (chunks are decompressed one at a time), with its topic, schema and per-topic index; decoding
//! checks the channel's encodings and schema name before the CDR.

use std::collections::HashMap;
use std::io::Read;
use std::ops::ControlFlow;
use std::path::{Path, PathBuf};
use std::sync::Arc;

use mcap::records::Record;
use mcap::sans_io::{LinearReadEvent, LinearReader, LinearReaderOptions};

use crate::cdr::CdrError;
use crate::messages::RosMessage;
use crate::metadata::StorageFilesFile;
use crate::BagError;

/// Largest record accepted inside a compressed chunk of a file smaller than it.
const MAX_RECORD_IN_CHUNK: usize = 1 << 30;

/// One message of a bag.
#[derive(Debug, Clone, Copy)]
pub struct BagMessage<'a> {
    pub topic: &'a str,
    /// The channel's schema name (`sensor_msgs/msg/Image`), empty when it has none.
    pub schema_name: &'a str,
    /// The schema's encoding (`ros2msg` for rosbag2).
    pub schema_encoding: &'a str,
    /// The channel's message encoding (`cdr` for rosbag2).
    pub message_encoding: &'a str,
    /// 0-based position among the messages of its topic, in file order.
    pub index: usize,
    /// When it was recorded (ns since the epoch, or since the simulation's start).
    pub log_time_ns: u64,
    /// The serialised message.
    pub data: &'a [u8],
}

/// Why one message could not be used.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum Problem {
    #[error("message encoding {0:?} is not cdr")]
    MessageEncoding(String),
    #[error("schema encoding {0:?} is not ros2msg")]
    SchemaEncoding(String),
    #[error("schema {found:?} is not the expected {expected}")]
    Schema { found: String, expected: &'static str },
    #[error("{0}")]
    Cdr(#[from] CdrError),
    #[error("{0}")]
    Invalid(String),
}

/// A message that could not be used, named by its topic and index.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
#[error("topic {topic} message {index}: {problem}")]
pub struct MessageError {
    pub topic: String,
    pub index: usize,
    pub problem: Problem,
}

impl BagMessage<'_> {
    /// An error about this message.
    pub fn error(&self, problem: Problem) -> MessageError {
        MessageError { topic: self.topic.to_string(), index: self.index, problem }
    }

    /// Decodes the message as `M`, after checking the channel is CDR with a ros2msg schema of `M`'s type.
    pub fn decode<M: RosMessage>(&self) -> Result<M, MessageError> {
        if self.message_encoding != "cdr" {
            return Err(self.error(Problem::MessageEncoding(self.message_encoding.to_string())));
        }
        if self.schema_name != M::DEFINITION.name {
            return Err(self.error(Problem::Schema { found: self.schema_name.to_string(), expected: M::DEFINITION.name }));
        }
        if self.schema_encoding != "ros2msg" {
            return Err(self.error(Problem::SchemaEncoding(self.schema_encoding.to_string())));
        }
        M::from_cdr(self.data).map_err(|e| self.error(Problem::Cdr(e)))
    }
}

/// A bag on disk (one `.mcap` file, or a rosbag2 directory with `metadata.yaml`) or in memory.
#[derive(Debug, Clone)]
pub struct BagReader {
    path: PathBuf,
    files: Vec<PathBuf>,
    /// The MCAP file's bytes, for a bag read from memory ([`BagReader::from_bytes`]).
    memory: Option<Arc<[u8]>>,
}

struct Schema {
    name: String,
    encoding: String,
}

struct Channel {
    topic: String,
    schema_id: u16,
    message_encoding: String,
}

impl BagReader {
    /// Opens `path`: an MCAP file, or a directory with a rosbag2 `metadata.yaml` (storage `mcap`).
    pub fn open(path: &Path) -> Result<Self, BagError> {
        let layout = |reason: String| BagError::Layout { path: path.to_path_buf(), reason };
        if path.is_file() {
            return Ok(Self { path: path.to_path_buf(), files: vec![path.to_path_buf()], memory: None });
        }
        let metadata_path = path.join("metadata.yaml");
        if !metadata_path.is_file() {
            return Err(layout("neither an MCAP file nor a bag directory with metadata.yaml".into()));
        }
        let text = std::fs::read_to_string(&metadata_path).map_err(|source| BagError::Io { path: metadata_path.clone(), source })?;
        let metadata: StorageFilesFile = serde_yaml_ng::from_str(&text)
            .map_err(|e| BagError::Layout { path: metadata_path.clone(), reason: format!("not a rosbag2 metadata file: {e}") })?;
        let info = metadata.rosbag2_bagfile_information;
        if info.storage_identifier != "mcap" {
            return Err(BagError::Layout {
                path: metadata_path,
                reason: format!("storage {:?} is not supported (only mcap)", info.storage_identifier),
            });
        }
        if info.relative_file_paths.is_empty() {
            return Err(BagError::Layout { path: metadata_path, reason: "relative_file_paths is empty".into() });
        }
        let files = info.relative_file_paths.iter().map(|file| path.join(file)).collect();
        Ok(Self { path: path.to_path_buf(), files, memory: None })
    }

    /// A bag whose MCAP file is `bytes` (received, or read by the caller); `name` stands for its
    /// path in errors. Read exactly as a file of these bytes.
    pub fn from_bytes(name: &str, bytes: impl Into<Arc<[u8]>>) -> Self {
        Self { path: PathBuf::from(name), files: Vec::new(), memory: Some(bytes.into()) }
    }

    pub fn path(&self) -> &Path {
        &self.path
    }

    /// The MCAP files, in order (none for a bag in memory).
    pub fn files(&self) -> &[PathBuf] {
        &self.files
    }

    /// Calls `visit` with every message of every file, in file order, until it returns
    /// `ControlFlow::Break`. Fails on the first record that cannot be read (a truncated or corrupt
    /// file), after visiting the messages before it.
    pub fn for_each(&self, mut visit: impl FnMut(&BagMessage<'_>) -> ControlFlow<()>) -> Result<(), BagError> {
        let mut counts: HashMap<String, usize> = HashMap::new();
        if let Some(bytes) = &self.memory {
            return read_mcap(&self.path, &bytes[..], bytes.len() as u64, &mut counts, &mut visit).map(|_| ());
        }
        for file in &self.files {
            if read_file(file, &mut counts, &mut visit)?.is_break() {
                break;
            }
        }
        Ok(())
    }
}

fn read_file(
    path: &Path,
    counts: &mut HashMap<String, usize>,
    visit: &mut impl FnMut(&BagMessage<'_>) -> ControlFlow<()>,
) -> Result<ControlFlow<()>, BagError> {
    let file = std::fs::File::open(path).map_err(|source| BagError::Io { path: path.to_path_buf(), source })?;
    let file_len = file.metadata().map(|m| m.len()).unwrap_or(0);
    read_mcap(path, file, file_len, counts, visit)
}

/// The messages of one MCAP file of `file_len` bytes read from `file` (`path` names it in errors).
fn read_mcap(
    path: &Path,
    mut file: impl Read,
    file_len: u64,
    counts: &mut HashMap<String, usize>,
    visit: &mut impl FnMut(&BagMessage<'_>) -> ControlFlow<()>,
) -> Result<ControlFlow<()>, BagError> {
    let mcap_error = |source| BagError::Mcap { path: path.to_path_buf(), source };
    let layout = |reason: String| BagError::Layout { path: path.to_path_buf(), reason };
    // A corrupt length field must not make the reader allocate it: no record is longer than the
    // file, or than 1 GiB where a compressed chunk holds more than the file's size.
    let limit = usize::try_from(file_len).unwrap_or(usize::MAX).max(MAX_RECORD_IN_CHUNK);
    let mut reader = LinearReader::new_with_options(LinearReaderOptions::default().with_record_length_limit(limit));
    let mut schemas: HashMap<u16, Schema> = HashMap::new();
    let mut channels: HashMap<u16, Channel> = HashMap::new();
    while let Some(event) = reader.next_event() {
        match event.map_err(mcap_error)? {
            LinearReadEvent::ReadRequest(need) => {
                let read = file.read(reader.insert(need)).map_err(|source| BagError::Io { path: path.to_path_buf(), source })?;
                reader.notify_read(read);
            }
            LinearReadEvent::Record { data, opcode } => match mcap::parse_record(opcode, data).map_err(mcap_error)? {
                Record::Schema { header, .. } => {
                    schemas.insert(header.id, Schema { name: header.name, encoding: header.encoding });
                }
                Record::Channel(channel) => {
                    channels.insert(
                        channel.id,
                        Channel { topic: channel.topic, schema_id: channel.schema_id, message_encoding: channel.message_encoding },
                    );
                }
                Record::Message { header, data } => {
                    let channel = channels.get(&header.channel_id).ok_or_else(|| {
                        layout(format!("a message refers to channel {} before any channel record of it", header.channel_id))
                    })?;
                    let schema = schemas.get(&channel.schema_id);
                    let count = counts.entry(channel.topic.clone()).or_default();
                    let message = BagMessage {
                        topic: &channel.topic,
                        schema_name: schema.map_or("", |s| s.name.as_str()),
                        schema_encoding: schema.map_or("", |s| s.encoding.as_str()),
                        message_encoding: &channel.message_encoding,
                        index: *count,
                        log_time_ns: header.log_time,
                        data: &data,
                    };
                    *count += 1;
                    if visit(&message).is_break() {
                        return Ok(ControlFlow::Break(()));
                    }
                }
                _ => {}
            },
        }
    }
    Ok(ControlFlow::Continue(()))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::messages::{Header, Image, Imu, TfMessage, Time};
    use crate::metadata::{MetadataFile, Qos};
    use crate::{BagWriter, Compression};

    fn image(sec: i32) -> Image {
        Image {
            header: Header::new(Time { sec, nanosec: 5 }, "camera_optical"),
            height: 2,
            width: 3,
            encoding: "16UC1".into(),
            is_bigendian: 0,
            step: 6,
            data: (0..12).collect(),
        }
    }

    fn write_bag(writer: &mut BagWriter) {
        let images = writer.add_topic::<Image>("/camera/depth/image_raw", Qos::SensorData).unwrap();
        let imu = writer.add_topic::<Imu>("/imu/data", Qos::SensorData).unwrap();
        let tf = writer.add_topic::<TfMessage>("/tf_static", Qos::Latched).unwrap();
        writer.write(tf, 0, &TfMessage::default()).unwrap();
        for sec in 0..3 {
            writer.write(imu, sec as u64 * 1_000_000_000, &Imu::default()).unwrap();
            writer.write(images, sec as u64 * 1_000_000_000 + 5, &image(sec)).unwrap();
        }
    }

    /// topic, schema name, index, log time, data.
    type Row = (String, String, usize, u64, Vec<u8>);

    fn collect(reader: &BagReader) -> Result<Vec<Row>, BagError> {
        let mut out = Vec::new();
        reader.for_each(|m| {
            out.push((m.topic.to_string(), m.schema_name.to_string(), m.index, m.log_time_ns, m.data.to_vec()));
            ControlFlow::Continue(())
        })?;
        Ok(out)
    }

    #[test]
    fn written_file_reads_back_with_schemas_indices_and_times() {
        for compression in [Compression::Zstd, Compression::Lz4, Compression::None] {
            let dir = tempfile::tempdir().unwrap();
            let path = dir.path().join("run.mcap");
            let mut writer = BagWriter::create(&path, compression).unwrap();
            write_bag(&mut writer);
            let summary = writer.finish().unwrap();
            assert_eq!(summary.messages, 7);
            assert_eq!(summary.topics[0], ("/camera/depth/image_raw".to_string(), 3));
            let reader = BagReader::open(&path).unwrap();
            let messages = collect(&reader).unwrap();
            assert_eq!(messages.len(), 7);
            let images: Vec<_> = messages.iter().filter(|m| m.0 == "/camera/depth/image_raw").collect();
            assert_eq!(images.iter().map(|m| m.2).collect::<Vec<_>>(), [0, 1, 2]);
            assert_eq!(images[2].3, 2_000_000_005);
            assert_eq!(images[1].1, "sensor_msgs/msg/Image");
            assert_eq!(Image::from_cdr(&images[1].4).unwrap(), image(1));
            // The header says ros2, the schemas are ros2msg.
            let bytes = std::fs::read(&path).unwrap();
            let header = mcap::read::LinearReader::new(&bytes).unwrap().next().unwrap().unwrap();
            assert!(matches!(header, mcap::records::Record::Header(h) if h.profile == "ros2"), "{compression:?}");
        }
    }

    #[test]
    fn bytes_in_memory_read_as_the_file() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("run.mcap");
        let mut writer = BagWriter::create(&path, Compression::Zstd).unwrap();
        write_bag(&mut writer);
        writer.finish().unwrap();
        let bytes = std::fs::read(&path).unwrap();
        let from_file = collect(&BagReader::open(&path).unwrap()).unwrap();
        let memory = BagReader::from_bytes("received.mcap", bytes.clone());
        assert!(memory.files().is_empty());
        assert_eq!(collect(&memory).unwrap(), from_file);
        let cut = BagReader::from_bytes("received.mcap", &bytes[..bytes.len() / 2]);
        let error = collect(&cut).unwrap_err();
        assert!(error.to_string().starts_with("received.mcap: "), "{error}");
    }

    #[test]
    fn decode_checks_encoding_and_schema() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("run.mcap");
        let mut writer = BagWriter::create(&path, Compression::None).unwrap();
        write_bag(&mut writer);
        writer.finish().unwrap();
        let mut errors = Vec::new();
        BagReader::open(&path)
            .unwrap()
            .for_each(|m| {
                if m.topic == "/imu/data" && m.index == 1 {
                    errors.push(m.decode::<Image>().unwrap_err());
                    let mut other = *m;
                    other.message_encoding = "json";
                    errors.push(other.decode::<Imu>().unwrap_err());
                    other.message_encoding = "cdr";
                    other.data = &m.data[..10];
                    errors.push(other.decode::<Imu>().unwrap_err());
                    assert!(m.decode::<Imu>().is_ok());
                }
                ControlFlow::Continue(())
            })
            .unwrap();
        let texts: Vec<String> = errors.iter().map(ToString::to_string).collect();
        assert_eq!(texts[0], "topic /imu/data message 1: schema \"sensor_msgs/msg/Imu\" is not the expected sensor_msgs/msg/Image");
        assert_eq!(texts[1], "topic /imu/data message 1: message encoding \"json\" is not cdr");
        assert!(texts[2].starts_with("topic /imu/data message 1: payload ends at byte 10"), "{}", texts[2]);
    }

    #[test]
    fn bag_directory_has_metadata_and_truncated_files_are_errors() {
        let dir = tempfile::tempdir().unwrap();
        let bag = dir.path().join("sim_bag");
        let mut writer = BagWriter::create_directory(&bag, Compression::Zstd).unwrap();
        write_bag(&mut writer);
        writer.finish().unwrap();
        assert!(BagWriter::create_directory(&bag, Compression::Zstd).is_err());
        let metadata: MetadataFile = serde_yaml_ng::from_str(&std::fs::read_to_string(bag.join("metadata.yaml")).unwrap()).unwrap();
        let info = &metadata.rosbag2_bagfile_information;
        assert_eq!((info.version, info.storage_identifier.as_str(), info.message_count), (9, "mcap", 7));
        assert_eq!(info.relative_file_paths, ["sim_bag_0.mcap"]);
        assert_eq!(info.topics_with_message_count[2].topic_metadata.offered_qos_profiles[0].durability, "transient_local");
        assert_eq!(info.duration.nanoseconds, 2_000_000_005);
        let reader = BagReader::open(&bag).unwrap();
        assert_eq!(collect(&reader).unwrap().len(), 7);
        // Cut the file in its data section: the messages before the cut are visited, then an error.
        let file = bag.join("sim_bag_0.mcap");
        let bytes = std::fs::read(&file).unwrap();
        let cut = dir.path().join("cut.mcap");
        std::fs::write(&cut, &bytes[..bytes.len() / 2]).unwrap();
        let result = BagReader::open(&cut).unwrap().for_each(|_| ControlFlow::Continue(()));
        assert!(matches!(result, Err(BagError::Mcap { .. })), "{result:?}");
        // A record claiming an absurd length after a valid magic is an error, not an allocation.
        let mut huge = b"\x89MCAP0\r\n".to_vec();
        huge.extend_from_slice(&[0x01, 0xff, 0xff, 0xff, 0xff, 0xff, 0xff, 0xff, 0x6e]);
        std::fs::write(&cut, &huge).unwrap();
        assert!(matches!(BagReader::open(&cut).unwrap().for_each(|_| ControlFlow::Continue(())), Err(BagError::Mcap { .. })));
        std::fs::write(&cut, b"not an mcap file at all").unwrap();
        assert!(matches!(BagReader::open(&cut).unwrap().for_each(|_| ControlFlow::Continue(())), Err(BagError::Mcap { .. })));
        assert!(BagReader::open(dir.path()).is_err());
        std::fs::write(
            bag.join("metadata.yaml"),
            "rosbag2_bagfile_information:\n  storage_identifier: sqlite3\n  relative_file_paths: [a.db3]\n",
        )
        .unwrap();
        assert!(BagReader::open(&bag).unwrap_err().to_string().contains("sqlite3"));
    }
}

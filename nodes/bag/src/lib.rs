//! rosbag2 bags in MCAP storage, without ROS: read the messages of a `.mcap` file or of a bag
//! directory (`metadata.yaml` + its `.mcap` files), and write bags that `ros2 bag info/play`,
//! Foxglove and the Python `rosbags` library read (profile `ros2`, ros2msg schemas with their
//! dependent types, CDR messages, the `rosbag2` metadata record and optionally `metadata.yaml`).
//!
//! The message types a depth camera + IMU rig records are plain structs with their CDR codec
//! ([`messages`]); others can be read as raw bytes ([`BagMessage::data`]).
//!
//! ```no_run
//! use patchwalk_bag::{messages::Imu, BagReader};
//! let bag = BagReader::open(std::path::Path::new("run.mcap"))?;
//! bag.for_each(|message| {
//!     if message.topic == "/imu/data" {
//!         match message.decode::<Imu>() {
//!             Ok(imu) => println!("{} {:?}", imu.header.stamp.seconds(), imu.linear_acceleration),
//!             Err(err) => eprintln!("{err}"), // names the topic and the message's index
//!         }
//!     }
//!     std::ops::ControlFlow::Continue(())
//! })?;
//! # Ok::<(), patchwalk_bag::BagError>(())
//! ```

pub mod cdr;
pub mod definitions;
pub mod messages;
pub mod metadata;
mod read;
mod write;

use std::path::PathBuf;

pub use read::{BagMessage, BagReader, MessageError, Problem};
pub use write::{BagSummary, BagWriter, Compression, Topic};

/// What went wrong with a bag as a whole (a single bad message is a [`MessageError`]).
#[derive(Debug, thiserror::Error)]
pub enum BagError {
    #[error("{path}: {source}")]
    Io { path: PathBuf, source: std::io::Error },
    #[error("{path}: not a readable MCAP file: {source}")]
    Mcap { path: PathBuf, source: mcap::McapError },
    #[error("{path}: {reason}")]
    Layout { path: PathBuf, reason: String },
}

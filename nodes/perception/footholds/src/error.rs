//! The one error type of the crate: every bad input names what was wrong.

use std::path::PathBuf;

/// Why a foothold operation could not be done.
#[derive(Debug, thiserror::Error)]
pub enum FootholdError {
    /// The depth image is too small for one region window, or its size disagrees with the intrinsics.
    #[error("depth image {width}x{height}: {reason}")]
    Image { width: usize, height: usize, reason: String },
    /// The depth image has no finite positive depth at all.
    #[error("depth image {width}x{height} has no valid depth (all NaN, zero or negative)")]
    NoValidDepth { width: usize, height: usize },
    /// The gravity vector cannot give a tilt (zero length or not finite).
    #[error("gravity in the camera frame {0:?} is zero or not finite: no camera tilt")]
    BadGravity([f64; 3]),
    /// A tilt angle outside [-90°, 90°] or not finite.
    #[error("camera tilt {0}° is not finite or outside [-90°, 90°]")]
    BadTilt(f64),
    /// A configuration value out of range.
    #[error("invalid configuration: {0}")]
    Config(String),
    /// Inputs whose shapes disagree (batch sizes, channel counts).
    #[error("shape mismatch: {0}")]
    Shape(String),
    /// A training or evaluation set without samples.
    #[error("empty sample set: {0}")]
    Empty(String),
    /// Errors of the tensor library.
    #[error("tensor operation: {0}")]
    Tensor(#[from] candle_core::Error),
    /// Weights file problems (missing tensor, wrong shape, unreadable metadata).
    #[error("weights {path}: {reason}")]
    Weights { path: PathBuf, reason: String },
    /// File I/O.
    #[error("{path}: {source}")]
    Io { path: PathBuf, source: std::io::Error },
    /// A sample or weights metadata file that does not parse.
    #[error("{path}: {reason}")]
    Format { path: PathBuf, reason: String },
    /// The depth dataset could not be read.
    #[error(transparent)]
    Dataset(#[from] patchwalk_fusion::dataset::DatasetError),
    /// The patch pipeline refused its configuration.
    #[error(transparent)]
    Pipeline(#[from] patchwalk_mapping::pipeline::PipelineError),
    /// Writing a picture failed.
    #[error("writing the picture {path}: {reason}")]
    Picture { path: PathBuf, reason: String },
}

/// An I/O error with its path.
pub(crate) fn io_error(path: &std::path::Path) -> impl FnOnce(std::io::Error) -> FootholdError + '_ {
    move |source| FootholdError::Io { path: path.to_path_buf(), source }
}

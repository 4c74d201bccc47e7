//! Learned foothold prediction from one depth image and the camera tilt (CNN: "Learning to predict
//! footholds and handholds from RGB-D", sections III-A..E), in pure Rust on the CPU with candle.
//!
//! - [`regions`]: the m × n grid of perspective-corrected regions (CNN III-A), resampled to 60 × 60
//!   and normalised; depth only, optionally with surface-normal channels.
//! - [`tilt`]: the side channels (cos θ, sin θ, θ/90°) from the IMU's gravity (CNN III-B).
//! - [`network`]: four convolutions (30, 30, 60, 60), two fully connected layers of 500, tilt mixed
//!   in after the convolutions, per body part p (a foothold exists) and (x, y); the loss CNN eq 1.
//! - [`labels`]: labels without a human: the patch pipeline fused over a sequence says where the
//!   valid, foot-sized, walkable patches are (in place of CNN III-C's painting).
//! - [`samples`], [`train`], [`model`]: labelled sets with augmentation, deterministic training,
//!   weights as safetensors, whole-frame prediction.
//! - [`inference`]: the network's forward pass without candle (im2col + gemm, fused bias, ReLU and
//!   pooling, regions in parallel), what whole-frame prediction uses.
//! - [`svm`]: the hand-feature linear SVM of CNN III-E; [`eval`]: the errors of CNN Tables I–II;
//!   [`evaluation`]: the comparison table; [`render`]: pictures like CNN Fig. 6; [`sequence`]: a
//!   dataset with its IMU mount, labelled.
//!
//! ROS-free; `patch_mapper footholds ...` is the command line. Predicting the footholds of a frame:
//!
//! ```no_run
//! # fn main() -> Result<(), patchwalk_footholds::FootholdError> {
//! use patchwalk_footholds::{model::FootholdModel, tilt::Tilt};
//! let model = FootholdModel::load(&patchwalk_footholds::shipped_weights_path(false))?;
//! let dataset = patchwalk_fusion::dataset::Dataset::open(std::path::Path::new("tests/data/tum_fr1_xyz"))?;
//! let depth = dataset.load_depth(0)?;
//! // Gravity (down) in the camera frame, e.g. from the IMU: here the camera looks 49° down.
//! let tilt = Tilt::from_gravity_in_camera(&nalgebra::Vector3::new(0.0, 0.66, 0.75))?;
//! let frame = model.predict_frame(&depth, &dataset.intrinsics, tilt)?;
//! for (u, v, p) in frame.footholds(0.5) {
//!     println!("foothold at pixel ({u:.0}, {v:.0}), p = {p:.2}");
//! }
//! # Ok(()) }
//! ```

pub mod error;
pub mod eval;
pub mod evaluation;
pub mod inference;
pub mod labels;
pub mod model;
pub mod network;
pub mod regions;
pub mod render;
pub mod samples;
pub mod sequence;
pub mod svm;
pub mod tensors_io;
pub mod tilt;
pub mod train;

pub use error::FootholdError;

/// The shipped weights of the foothold network (depth only, with tilt), relative to the repository root.
pub const SHIPPED_WEIGHTS: &str = "nodes/perception/footholds/weights/foot_d.safetensors";
/// The shipped weights of the same network trained without the tilt side channels (CNN's "No angle").
pub const SHIPPED_WEIGHTS_NO_ANGLE: &str = "nodes/perception/footholds/weights/foot_d_noangle.safetensors";

/// The shipped linear SVM baseline (JSON), resolved against the crate's directory.
pub fn shipped_svm_path() -> std::path::PathBuf {
    std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("weights").join("svm.json")
}

/// The shipped weights resolved against the crate's directory (for tests, benches and the CLI when
/// run from elsewhere).
pub fn shipped_weights_path(no_angle: bool) -> std::path::PathBuf {
    let name = if no_angle { "foot_d_noangle.safetensors" } else { "foot_d.safetensors" };
    std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("weights").join(name)
}

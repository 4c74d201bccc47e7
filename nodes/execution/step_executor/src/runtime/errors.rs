//! Why the runtime refuses or fails a command, and why a training fit gives no patch.

use crate::executor::ExecutorError;
use crate::library::{LibraryError, NameError};
use patchwalk_robot_model::kinematics::KinematicsError;
use patchwalk_spl::fit::neighbourhood::NeighbourhoodFitError;

/// Why a command of the node was refused or failed. Every variant leaves the runtime as it was
/// (nothing half done), so the caller may correct the request and send it again.
#[derive(Debug, thiserror::Error)]
pub enum CommandError {
    /// The servo bus did not open or did not answer at start (the reason is the bus's own).
    #[error("servo bus not available: {0}")]
    BusUnavailable(String),
    /// Arming and playing are refused while an e-stop is latched.
    #[error("e-stopped: call reset_estop first (arming does not clear an e-stop)")]
    EStopped,
    /// The bus thread refused or failed the command.
    #[error(transparent)]
    Executor(#[from] ExecutorError),
    #[error(transparent)]
    Library(#[from] LibraryError),
    /// A motion name breaking one of [`crate::library::validate_name`]'s rules.
    #[error(transparent)]
    InvalidName(#[from] NameError),
    /// A request field out of its range (`field` is the request's field name).
    #[error("invalid {field}: {reason}")]
    InvalidArgument { field: &'static str, reason: String },
    /// A recorded pose outside the URDF limits.
    #[error("{joint} at {value:.3} rad is outside its limits [{lower:.3}, {upper:.3}]")]
    OutsideLimits { joint: String, value: f64, lower: f64, upper: f64 },
    #[error("no target patch selected (call select_target first)")]
    NoTarget,
    #[error("no keyframes recorded (call record_keyframe first)")]
    NoKeyframes,
    #[error("no patch map received yet (or it was empty)")]
    NoPatches,
    #[error("no patch map received yet (its camera pose places the cloud)")]
    NoPatchMap,
    #[error(transparent)]
    Fit(#[from] FitError),
    /// Forward kinematics at the measured joint positions.
    #[error("robot model: {0}")]
    Model(#[from] KinematicsError),
}

/// Why a training fit ([`super::FitJob::run`]) gave no patch.
#[derive(Debug, thiserror::Error)]
pub enum FitError {
    #[error("no birds-eye cloud received yet (is patch_mapper publishing ros.publish_birds_eye_cloud?)")]
    NoCloud,
    #[error("birds-eye cloud: {0}")]
    BadCloud(String),
    #[error("only {found} cloud points within {radius_m} m of the point (need {needed})")]
    TooFewPoints { found: usize, radius_m: f64, needed: usize },
    #[error("fit: {0}")]
    Fit(#[from] NeighbourhoodFitError),
    #[error("fit: the patch could not be moved to base_link")]
    NotMovable,
}

pub(super) fn invalid(field: &'static str, reason: String) -> CommandError {
    CommandError::InvalidArgument { field, reason }
}

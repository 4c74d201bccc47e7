//! The node's inputs as bytes: entry points that take what arrives from the world — a serialized
//! patch map or service request (encapsulation header + CDR, decoded by
//! [`patchwalk_ros::wire::decode`], the decoder of the node's endpoints), the motion library file,
//! the configuration file, a page of a ROBOTIS action file — and run the node's checks on it, without ROS or a servo bus. The fuzz
//! targets of `nodes/fuzz` call them, and the regression tests replay every stored input of
//! `tests/data/fuzz/` through them.
//!
//! Requests and patch maps go to a [`Runtime`] built as the node builds it, without a bus, over a
//! library holding one trained motion (a plane in front of the left foot), so the matcher compares.

use std::path::{Path, PathBuf};
use std::sync::OnceLock;

use nalgebra::Vector3;
use patchwalk_msgs::msg::PatchArray;
use patchwalk_msgs::srv;
use patchwalk_robot_model::kinematics::{JointLimits, RobotModel};
use patchwalk_ros::params::ParamError;
use patchwalk_ros::patch_msg::{self, PatchMsgError};
use patchwalk_ros::wire::{self, WireError};
use patchwalk_spl::patch::Patch;

use crate::action_file::{self, ExportError, IdMap, IdMapError, ImportError, PageError};
use crate::config::{ConfigError, StepExecutorConfig};
use crate::library::{Keyframe, LibraryError, Motion, MotionLibrary};
use crate::runtime::{CommandError, Runtime};

/// Why an input was refused: each names the stage.
#[derive(Debug, thiserror::Error)]
pub enum InputError {
    #[error("empty input")]
    Empty,
    #[error("unknown service selector {0}")]
    Selector(u8),
    #[error(transparent)]
    Wire(#[from] WireError),
    #[error("camera_pose: {0}")]
    Pose(PatchMsgError),
    #[error(transparent)]
    Command(#[from] CommandError),
    #[error(transparent)]
    Library(#[from] LibraryError),
    #[error(transparent)]
    Params(#[from] ParamError),
    #[error(transparent)]
    Config(#[from] ConfigError),
    #[error("the replay runtime could not be built: {0}")]
    Runtime(String),
    #[error(transparent)]
    Page(#[from] PageError),
    #[error("the parsed page does not write back byte for byte")]
    PageRoundTrip,
    #[error(transparent)]
    Import(#[from] ImportError),
    #[error(transparent)]
    IdMap(#[from] IdMapError),
    #[error("the robot model: {0}")]
    Model(String),
}

/// The services whose request [`service_request`] takes, by selector byte.
pub const SERVICES: [&str; 6] = ["record_keyframe", "select_target", "save_motion", "list_motions", "delete_motion", "play_motion"];

/// What the node would answer.
#[derive(Debug)]
pub struct Answer {
    pub success: bool,
    pub message: String,
}

/// One `patchwalk_msgs` service request: byte 0 selects the service ([`SERVICES`] order), the rest
/// is the serialized request. Decoded and handled by the runtime as the node's handlers do (a fit
/// is checked and prepared, not run; a save or delete is prepared, not written).
pub fn service_request(bytes: &[u8]) -> Result<Answer, InputError> {
    let (&selector, payload) = bytes.split_first().ok_or(InputError::Empty)?;
    let mut runtime = replay_runtime()?;
    let result: Result<String, CommandError> = match selector {
        0 => {
            let request: srv::RecordKeyframeRequest = wire::decode(payload)?;
            runtime.record_keyframe(request.duration, request.pause).map(|(index, _)| format!("keyframe {index} recorded"))
        }
        1 => {
            let request: srv::SelectTargetRequest = wire::decode(payload)?;
            let point = [request.point.x, request.point.y, request.point.z];
            match request.mode {
                srv::SelectTargetRequest::MODE_NEAREST_POINT => runtime.select_nearest(point).map(|p| format!("{:?}", p.surface)),
                srv::SelectTargetRequest::MODE_FIT_AT_POINT => runtime.fit_job(point, request.radius).map(|_| "fit started".into()),
                mode => Err(CommandError::InvalidArgument { field: "mode", reason: format!("{mode} is unknown") }),
            }
        }
        2 => runtime.prepare_save(&wire::decode::<srv::SaveMotionRequest>(payload)?.name).map(|_| "save prepared".into()),
        3 => {
            wire::decode::<srv::ListMotionsRequest>(payload)?;
            Ok(format!("{} motions", runtime.list_motions().len()))
        }
        4 => runtime.prepare_delete(&wire::decode::<srv::DeleteMotionRequest>(payload)?.name).map(|_| "delete prepared".into()),
        5 => runtime.play_motion(&wire::decode::<srv::PlayMotionRequest>(payload)?.name),
        other => return Err(InputError::Selector(other)),
    };
    Ok(match result {
        Ok(message) => Answer { success: true, message },
        Err(e) => Answer { success: false, message: e.to_string() },
    })
}

/// What a patch map gave.
#[derive(Debug)]
pub struct MapOutcome {
    pub patches: usize,
    pub skipped: usize,
    pub matched: Option<usize>,
}

/// A serialized `patchwalk_msgs/PatchArray` as step_executor takes it from `/patch_mapper/patches`:
/// the camera pose and every patch validated (a bad patch is skipped, as the node skips it), then
/// moved to `base_link` and matched against the replay library (J 6.3).
pub fn patch_map(bytes: &[u8]) -> Result<MapOutcome, InputError> {
    let map: PatchArray = wire::decode(bytes)?;
    let map_from_camera = patch_msg::isometry_from_pose(&map.camera_pose).map_err(InputError::Pose)?;
    let patches: Vec<Patch> = map.patches.iter().filter_map(|m| patch_msg::patch_from_msg(m).ok()).collect();
    let skipped = map.patches.len() - patches.len();
    let mut runtime = replay_runtime()?;
    let report = runtime.on_patch_map(&patches, &map_from_camera)?;
    Ok(MapOutcome { patches: patches.len(), skipped, matched: report.best.map(|best| best.trained_index) })
}

/// A motion library file's bytes through [`MotionLibrary::from_text`] (the loader of the node),
/// with the default configuration's joints. Bytes that are not UTF-8 are refused as the loader's
/// file read refuses them.
pub fn library_file(bytes: &[u8]) -> Result<usize, InputError> {
    let path = Path::new("motions.yaml");
    let text = std::str::from_utf8(bytes).map_err(|e| LibraryError::Malformed {
        path: path.to_path_buf(),
        location: "file".into(),
        message: format!("not UTF-8: {e}"),
    })?;
    let library = MotionLibrary::from_text(path, text, &StepExecutorConfig::default().joint_names())?;
    Ok(library.motions().len())
}

/// A configuration file and its `--param` overrides, as `step_executor run --config FILE -p ..`
/// takes them: the file's text up to the first NUL byte, then NUL-separated overrides. Loaded by
/// `patchwalk_ros::params` and validated as the node does before it starts.
pub fn config_file(bytes: &[u8]) -> Result<StepExecutorConfig, InputError> {
    let (text, overrides) = split_config_input(bytes);
    let config: StepExecutorConfig = patchwalk_ros::params::load_config_from_str(&text, Path::new("step_executor.yaml"), &overrides)?;
    config.validate()?;
    Ok(config)
}

/// The file text and overrides of a [`config_file`] input (invalid UTF-8 replaced, as a file the
/// loader reads would have been refused; the replacement keeps the rest of the input useful).
pub fn split_config_input(bytes: &[u8]) -> (String, Vec<String>) {
    let mut parts = bytes.split(|b| *b == 0).map(|part| String::from_utf8_lossy(part).into_owned());
    let text = parts.next().unwrap_or_default();
    (text, parts.collect())
}

/// What a page of an action file gave.
#[derive(Debug)]
pub struct PageOutcome {
    /// Keyframes imported from the page.
    pub keyframes: usize,
    /// The imported keyframes written back as a page ([`action_file::keyframes_to_page`] over the
    /// page itself) and imported again: the largest joint angle difference (rad), or why the export
    /// refused them.
    pub reexport: Result<f64, ExportError>,
}

/// One ROBOTIS action file page as `step_executor import-motion` reads it: the page's 512 bytes
/// follow byte 0, whose bit 0 set means "put the right checksum in first" (so a fuzzer gets past the
/// checksum to the page's fields). Parsed ([`action_file::parse_page`], which must write it back
/// byte for byte), converted to keyframes with DARwIn-OP's leg IDs and the built-in robot model's
/// joint limits (the default configuration's margin), and those exported again over the page.
pub fn action_page(bytes: &[u8]) -> Result<PageOutcome, InputError> {
    let (&flags, page_bytes) = bytes.split_first().ok_or(InputError::Empty)?;
    let mut page_bytes = page_bytes.to_vec();
    if flags & 1 == 1 {
        if let Ok(fixed) = <&mut [u8; action_file::PAGE_BYTES]>::try_from(page_bytes.as_mut_slice()) {
            fixed[31] = action_file::page::checksum_for(fixed);
        }
    }
    let page = action_file::parse_page(&page_bytes)?;
    if page.to_bytes()[..] != page_bytes[..] {
        return Err(InputError::PageRoundTrip);
    }
    let (map, limits) = import_tables()?;
    let imported = action_file::page_to_keyframes(&page, &map, &limits)?;
    let reexport = action_file::keyframes_to_page(&imported.keyframes, &map, &limits, &page, page.name).map(|exported| {
        match action_file::page_to_keyframes(&exported.page, &map, &limits) {
            Ok(again) => imported
                .keyframes
                .iter()
                .zip(&again.keyframes)
                .flat_map(|(a, b)| a.positions.iter().zip(&b.positions).map(|(x, y)| (x - y).abs()))
                .chain((again.keyframes.len() != imported.keyframes.len()).then_some(f64::INFINITY))
                .fold(0.0, f64::max),
            Err(_) => f64::INFINITY,
        }
    });
    Ok(PageOutcome { keyframes: imported.keyframes.len(), reexport })
}

/// The ID table and joint limits [`action_page`] imports with: DARwIn-OP's leg IDs in the default
/// configuration's joint order, the built-in robot model's limits narrowed by the player's margin
/// (as `import-motion` without options).
pub fn import_tables() -> Result<(IdMap, Vec<JointLimits>), InputError> {
    let config = StepExecutorConfig::default();
    let joints = config.joint_names();
    let map = IdMap::for_joints(&IdMap::darwin_op_legs(), &joints)?;
    let model = RobotModel::from_urdf_str(patchwalk_robot_model::RPBP_URDF).map_err(|e| InputError::Model(e.to_string()))?;
    let margin = config.player.limit_margin_rad;
    let limits = joints
        .iter()
        .map(|joint| match model.joint_limits(joint) {
            Ok(Some(l)) => Ok(JointLimits { lower: l.lower + margin, upper: l.upper - margin }),
            Ok(None) => Err(InputError::Model(format!("joint {joint:?} has no position limits"))),
            Err(e) => Err(InputError::Model(e.to_string())),
        })
        .collect::<Result<Vec<_>, _>>()?;
    Ok((map, limits))
}

/// A runtime as the node builds it (default configuration, the built-in robot model), without a
/// servo bus, over the replay library.
fn replay_runtime() -> Result<Runtime, InputError> {
    let library_path = replay_library()?;
    let config = StepExecutorConfig {
        urdf_path: PathBuf::from("/nonexistent/urdf/rpbp.urdf"),
        library_path: library_path.clone(),
        ..StepExecutorConfig::default()
    };
    let (runtime, _warnings) =
        Runtime::with_bus(config, || Err("replay: no servo bus".into())).map_err(|e| InputError::Runtime(e.to_string()))?;
    Ok(runtime)
}

/// The replay library file, written once per process into the temp directory.
fn replay_library() -> Result<PathBuf, InputError> {
    static PATH: OnceLock<Result<PathBuf, String>> = OnceLock::new();
    PATH.get_or_init(|| write_replay_library().map_err(|e| e.to_string())).clone().map_err(InputError::Runtime)
}

fn write_replay_library() -> Result<PathBuf, LibraryError> {
    let dir = std::env::temp_dir().join(format!("patchwalk-replay-{}", std::process::id()));
    std::fs::create_dir_all(&dir).map_err(|source| LibraryError::Io { path: dir.clone(), source })?;
    let path = dir.join("motions.yaml");
    let joints = StepExecutorConfig::default().joint_names();
    let mut library = MotionLibrary::new(&path, joints.clone());
    let patch = Patch::level_disc(0.03, Vector3::new(0.12, 0.04, -0.3)).map_err(|e| LibraryError::Malformed {
        path: path.clone(),
        location: "patch".into(),
        message: e.to_string(),
    })?;
    let keyframes = vec![Keyframe { positions: vec![0.0; joints.len()], move_s: 0.5, pause_s: 0.1 }];
    library.insert(Motion { name: "replay_step".into(), patch, keyframes })?;
    library.save()?;
    Ok(path)
}

#[cfg(test)]
mod tests;

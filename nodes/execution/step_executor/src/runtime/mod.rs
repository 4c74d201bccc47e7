//! The node's logic without ROS: loads the URDF, the motion library and the servo bus from the
//! configuration, trains motions (torque off → pose → record keyframes → select the target patch →
//! save), matches every incoming patch map against the library (J 6.3) after expressing it relative
//! to the robot (`patch_in_base = base_from_camera · camera_from_map · patch_in_map`), and, when
//! armed, plays the matched motion on the bus thread (one-shot: arming allows one automatic step).
//! The ROS layer only converts messages.

use std::collections::HashMap;

use nalgebra::{Isometry3, Point3, Vector3};
use patchwalk_spl::transform::transform_patch;

use crate::config::StepExecutorConfig;
use crate::executor::{initialise_bus, Executor, LoopSettings, Telemetry};
use crate::health::BusHealth;
use crate::library::{remove_stale_temp_files, validate_name, Keyframe, LibraryError, Motion, MotionLibrary};
use crate::matcher::{MatchReport, Matcher};
use crate::player::{JointSpec, Player, PlayerEvent, PlayerState};
use patchwalk_dynamixel::servo_bus::dynamixel::DynamixelBus;
use patchwalk_dynamixel::servo_bus::ServoBus;
use patchwalk_robot_model::kinematics::{positions_by_name, RobotModel};
use patchwalk_spl::patch::Patch;

/// The RPBP model shipped with the repository, used when `urdf_path` is found nowhere.
pub const BUILT_IN_URDF: &str = patchwalk_robot_model::RPBP_URDF;
/// The colcon package whose share directory holds `urdf/rpbp.urdf` when installed.
const PACKAGE: &str = "step_executor";

/// The repository this crate was built from (the parent of `config/` and `urdf/`).
fn source_root() -> std::path::PathBuf {
    std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("../../..")
}

/// The URDF file `urdf_path` names: looked up in the working directory, the package's share directory
/// (a colcon install, through the ament index) and the source tree, in that order.
pub fn find_urdf(urdf_path: &std::path::Path) -> Option<(std::path::PathBuf, patchwalk_ros::share::Origin)> {
    patchwalk_ros::share::find_data_file(urdf_path, PACKAGE, &source_root())
}

/// Coarse state for the status message.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum RunState {
    Idle,
    Playing,
    HoldingFault,
    EStopped,
}

/// Snapshot for the status message.
#[derive(Debug, Clone, PartialEq)]
pub struct RuntimeStatus {
    pub state: RunState,
    pub armed: bool,
    pub torque_enabled: bool,
    pub current_motion: String,
    pub keyframe_index: u32,
    pub last_match: String,
    pub fault_servo_id: u8,
    pub last_fault: String,
    pub library_size: u32,
    pub recorded_keyframes: u32,
}

/// One library entry as listed.
#[derive(Debug, Clone, PartialEq)]
pub struct MotionInfo {
    pub name: String,
    pub surface: u8,
    pub boundary: u8,
    pub keyframe_count: u32,
    pub duration: f64,
}

mod errors;
mod jobs;
#[cfg(test)]
mod tests;

use errors::invalid;
pub use errors::{CommandError, FitError};
pub use jobs::{FitJob, LibraryChange};

/// How a servo bus is opened: the bus, or why not (a reason shown to the user).
pub type BusResult = Result<Box<dyn ServoBus>, Box<dyn std::error::Error + Send + Sync>>;

/// The ROS-free node core.
pub struct Runtime {
    config: StepExecutorConfig,
    model: RobotModel,
    joint_names: Vec<String>,
    joint_specs: Vec<JointSpec>,
    library: MotionLibrary,
    matcher: Matcher,
    bus: Option<Executor>,
    /// Why there is no bus (the bus's own reason).
    bus_error: Option<String>,
    // training
    target: Option<Patch>,
    recorded: Vec<Keyframe>,
    // runtime state
    armed: bool,
    estopped: bool,
    torque: bool,
    player_state: PlayerState,
    current_motion: String,
    keyframe_index: u32,
    last_match: String,
    last_fault: Option<(u8, String)>,
    positions: Vec<Option<f64>>,
    latest_map_in_base: Vec<Patch>,
    /// Where the latest patch map's frame was relative to the robot when the map arrived (places
    /// the mapper's cloud, like the patches, relative to the robot).
    latest_base_from_map: Option<Isometry3<f64>>,
    last_report: Option<MatchReport>,
}

/// Why the runtime could not start at all (bad URDF or config); bus and library problems are not
/// fatal: the node starts and reports them.
#[derive(Debug, thiserror::Error)]
pub enum RuntimeError {
    #[error("robot model: {0}")]
    Model(#[from] patchwalk_robot_model::kinematics::KinematicsError),
    #[error("joint {0:?} of the servo config has no position limits in the URDF")]
    NoLimits(String),
}

impl Runtime {
    /// Build from the configuration; opens the configured serial port.
    pub fn new(config: StepExecutorConfig) -> Result<(Self, Vec<String>), RuntimeError> {
        let port = config.bus.port.clone();
        let baud = config.bus.baud;
        let timeout = std::time::Duration::from_secs_f64(config.bus.response_timeout_ms / 1000.0);
        Self::with_bus(config, move || {
            DynamixelBus::open(&port, baud).map(|bus| Box::new(bus.with_response_timeout(timeout)) as Box<dyn ServoBus>).map_err(Into::into)
        })
    }

    /// Build with a given bus factory (tests: mock or simulated chain). Returns warnings to log.
    pub fn with_bus(config: StepExecutorConfig, open_bus: impl FnOnce() -> BusResult) -> Result<(Self, Vec<String>), RuntimeError> {
        let mut warnings = Vec::new();
        let model = match find_urdf(&config.urdf_path) {
            Some((path, origin)) => {
                let model = RobotModel::from_file(&path)?;
                tracing::info!("robot model {} ({origin})", path.display());
                model
            }
            // Neither installed nor started from the repository: the RPBP model compiled into the binary.
            None => {
                warnings.push(format!("{} not found; using the built-in urdf/rpbp.urdf", config.urdf_path.display()));
                RobotModel::from_urdf_str(BUILT_IN_URDF)?
            }
        };
        let joint_names = config.joint_names();
        let mut joint_specs = Vec::with_capacity(config.servos.len());
        for servo in &config.servos {
            let limits = model.joint_limits(&servo.joint)?.ok_or_else(|| RuntimeError::NoLimits(servo.joint.clone()))?;
            joint_specs.push(JointSpec { servo: servo.clone(), limits });
        }
        match remove_stale_temp_files(&config.library_path) {
            Ok(removed) => warnings.extend(removed.iter().map(|f| format!("removed {} left by an interrupted save", f.display()))),
            Err(e) => warnings.push(format!("cannot clean temp files beside the library: {e}")),
        }
        let (library, library_error) = MotionLibrary::load_or_empty(&config.library_path, &joint_names);
        if let Some(err) = library_error {
            warnings.push(format!("{err}; starting with an empty library (the file is kept and moved aside on the next save)"));
        }
        let matcher = Matcher::new(config.matcher.clone(), library.motions().iter().map(|m| &m.patch));
        let player = Player::new(config.player.clone(), joint_specs.clone());
        let (bus, bus_error) = match open_bus() {
            Err(e) => (None, Some(e.to_string())),
            Ok(mut bus) => match initialise_bus(bus.as_mut(), &player, &config.bus) {
                Err(e) => (None, Some(e.to_string())),
                Ok(()) => match Executor::spawn(bus, player, LoopSettings::from_config(&config)) {
                    Ok(executor) => (Some(executor), None),
                    Err(e) => (None, Some(e.to_string())),
                },
            },
        };
        if let Some(reason) = &bus_error {
            warnings.push(CommandError::BusUnavailable(reason.clone()).to_string());
        }
        let n = joint_names.len();
        let runtime = Self {
            config,
            model,
            joint_names,
            joint_specs,
            library,
            matcher,
            bus,
            bus_error,
            target: None,
            recorded: Vec::new(),
            armed: false,
            estopped: false,
            torque: false,
            player_state: PlayerState::Idle,
            current_motion: String::new(),
            keyframe_index: 0,
            last_match: String::new(),
            last_fault: None,
            positions: vec![None; n],
            latest_map_in_base: Vec::new(),
            latest_base_from_map: None,
            last_report: None,
        };
        Ok((runtime, warnings))
    }

    /// See [`Executor::set_notify`]; without a bus there is nothing to notify about.
    pub fn set_bus_notify(&self, notify: crate::executor::Notify) {
        if let Some(bus) = &self.bus {
            bus.set_notify(notify);
        }
    }

    /// Whether the servo bus thread runs (the bus opened and every servo answered).
    pub fn has_bus(&self) -> bool {
        self.bus.is_some()
    }

    pub fn joint_names(&self) -> &[String] {
        &self.joint_names
    }

    pub fn config(&self) -> &StepExecutorConfig {
        &self.config
    }

    fn bus(&self) -> Result<&Executor, CommandError> {
        self.bus.as_ref().ok_or_else(|| CommandError::BusUnavailable(self.bus_error.clone().unwrap_or_else(|| "not opened".into())))
    }

    /// Drain the bus thread's telemetry (call every loop iteration); returns it for /joint_states.
    pub fn poll(&mut self) -> Vec<Telemetry> {
        let Some(bus) = &self.bus else { return Vec::new() };
        let telemetry: Vec<Telemetry> = bus.telemetry().try_iter().collect();
        for t in &telemetry {
            self.positions = t.positions.clone();
            if let Some(PlayerEvent::Fault(fault)) = &t.event {
                self.last_fault = Some((fault.servo_id.unwrap_or(0), fault.to_string()));
            }
            // Cycles from before the last answered command (a motion just started, torque just
            // switched) would turn the state back to what that command changed.
            if !bus.is_current(t) {
                continue;
            }
            self.torque = t.torque;
            self.player_state = t.state.clone();
            self.keyframe_index = u32::try_from(t.keyframe_index).unwrap_or(u32::MAX);
            match &t.event {
                Some(PlayerEvent::Fault(_)) | Some(PlayerEvent::Finished { .. }) | Some(PlayerEvent::EStopped) => {
                    self.current_motion.clear()
                }
                Some(PlayerEvent::Started { name }) => self.current_motion = name.clone(),
                None => {}
            }
            if let PlayerState::Playing { name } = &t.state {
                self.current_motion = name.clone();
            }
        }
        telemetry
    }

    /// Whether `telemetry` from [`Runtime::poll`] came after the last answered bus command (see
    /// [`Executor::is_current`]); older cycles' events concern what ran before that command.
    pub fn is_current(&self, telemetry: &Telemetry) -> bool {
        self.bus.as_ref().is_some_and(|bus| bus.is_current(telemetry))
    }

    /// Measured joint positions (rad; 0 where unknown) by name, for forward kinematics.
    fn positions_map(&self) -> HashMap<String, f64> {
        let values: Vec<f64> = self.positions.iter().map(|p| p.unwrap_or(0.0)).collect();
        positions_by_name(&self.joint_names, &values)
    }

    /// `base_from_camera` at the measured joint positions.
    pub fn base_from_camera(&self) -> Result<Isometry3<f64>, CommandError> {
        Ok(self.model.base_from_camera(&self.positions_map())?)
    }

    /// A new patch map (patches in the map frame, `map_from_camera` at the map's stamp). Expresses
    /// the patches in `base_link`, matches them (J 6.3) and, when armed and idle, plays the match.
    /// Returns the match report.
    pub fn on_patch_map(&mut self, patches_in_map: &[Patch], map_from_camera: &Isometry3<f64>) -> Result<MatchReport, CommandError> {
        let base_from_map = self.base_from_camera()? * map_from_camera.inverse();
        self.on_patch_map_in_base(patches_in_map, base_from_map)
    }

    /// [`Runtime::on_patch_map`] with `base_from_map` known (looked up in TF at the map's stamp).
    pub fn on_patch_map_in_base(&mut self, patches_in_map: &[Patch], base_from_map: Isometry3<f64>) -> Result<MatchReport, CommandError> {
        self.latest_base_from_map = Some(base_from_map);
        self.latest_map_in_base = patches_in_map.iter().filter_map(|p| pose_in(&base_from_map, p)).collect();
        let report = self.matcher.report(&self.latest_map_in_base);
        if let Some(best) = &report.best {
            if let Some(motion) = self.library.motions().get(best.trained_index) {
                self.last_match = motion.name.clone();
                let idle = matches!(self.player_state, PlayerState::Idle | PlayerState::Stopped);
                if self.armed && !self.estopped && idle && self.bus.is_some() {
                    // One step per arming (J 6.3: one trained motion per match); re-arm for the next.
                    self.armed = false;
                    let motion = motion.clone();
                    if let Err(e) = self.start(motion) {
                        self.last_fault = Some((0, format!("automatic play of {:?}: {e}", self.last_match)));
                    }
                }
            }
        }
        self.last_report = Some(report.clone());
        Ok(report)
    }

    fn start(&mut self, motion: Motion) -> Result<(), CommandError> {
        let name = motion.name.clone();
        self.bus()?.play(motion)?;
        self.current_motion = name.clone();
        self.player_state = PlayerState::Playing { name };
        self.torque = true;
        Ok(())
    }

    pub fn set_torque(&mut self, on: bool) -> Result<String, CommandError> {
        self.bus()?.set_torque(on)?;
        self.torque = on;
        if !on {
            self.last_fault = None;
            self.player_state = PlayerState::Idle;
        }
        Ok(if on { "torque on".into() } else { "torque off (compliant); fault cleared".into() })
    }

    /// Recovery from a servo fault: REBOOT `ids` (empty: the faulted servos; a lost port is reopened
    /// first), then the executor re-reads the positions and holds torque off; a motion plays only
    /// after an explicit `set_torque(true)`. Refused while a motion plays. Returns the message and
    /// the ids rebooted.
    pub fn reboot_servos(&mut self, ids: &[u8]) -> Result<(String, Vec<u8>), CommandError> {
        let rebooted = self.bus()?.reboot(ids.to_vec())?;
        self.torque = false;
        self.last_fault = None;
        self.player_state = PlayerState::Idle;
        let message = if rebooted.is_empty() {
            "port reopened; positions re-read; torque off (call set_torque true before playing)".to_string()
        } else {
            format!("rebooted servos {rebooted:?}; positions re-read; torque off (call set_torque true before playing)")
        };
        Ok((message, rebooted))
    }

    /// Per-servo and cycle health of the bus (`None` without a bus).
    pub fn bus_health(&self) -> Option<BusHealth> {
        self.bus.as_ref().map(Executor::health)
    }

    /// Append the present pose as a keyframe of the motion being trained.
    pub fn record_keyframe(&mut self, move_s: f64, pause_s: f64) -> Result<(usize, Vec<f64>), CommandError> {
        for (field, value) in [("duration", move_s), ("pause", pause_s)] {
            if !(value.is_finite() && value >= 0.0) {
                return Err(invalid(field, format!("{value} s must be finite and ≥ 0")));
            }
        }
        let positions = self.bus()?.positions()?;
        for (spec, q) in self.joint_specs.iter().zip(&positions) {
            if *q < spec.limits.lower || *q > spec.limits.upper {
                return Err(CommandError::OutsideLimits {
                    joint: spec.servo.joint.clone(),
                    value: *q,
                    lower: spec.limits.lower,
                    upper: spec.limits.upper,
                });
            }
        }
        self.recorded.push(Keyframe { positions: positions.clone(), move_s, pause_s });
        Ok((self.recorded.len() - 1, positions))
    }

    /// Select the training target: the patch of the latest map whose centre is nearest `point_in_base`.
    pub fn select_nearest(&mut self, point_in_base: [f64; 3]) -> Result<Patch, CommandError> {
        check_point(point_in_base)?;
        let point = Point3::from(point_in_base);
        let nearest = self
            .latest_map_in_base
            .iter()
            .min_by(|a, b| {
                let da = (Point3::from(a.center) - point).norm();
                let db = (Point3::from(b.center) - point).norm();
                da.total_cmp(&db)
            })
            .cloned()
            .ok_or(CommandError::NoPatches)?;
        self.target = Some(nearest.clone());
        Ok(nearest)
    }

    /// Training target by fitting (J 6.3: "we manually select a neighborhood where we would like the
    /// robot to place its foot and we fit a patch"): the points of the mapper's birds-eye cloud
    /// (`cloud_in_map`, in the latest patch map's frame; non-finite points are ignored) within
    /// `radius_m` of `point_in_base`, fitted with the patch core (IROS IV, type by discrimination),
    /// boundaries sized as the mapper sizes them so the target compares with mapped patches.
    pub fn select_fit(&mut self, cloud_in_map: &[Vector3<f64>], point_in_base: [f64; 3], radius_m: f64) -> Result<Patch, CommandError> {
        let patch = self.fit_job(point_in_base, radius_m)?.run(cloud_in_map)?;
        self.set_target(patch.clone());
        Ok(patch)
    }

    /// [`Runtime::select_fit`] in parts, so that the fit can run on another thread: the checked
    /// request (the point, the radius, where the cloud's frame is, the fit's configuration).
    pub fn fit_job(&self, point_in_base: [f64; 3], radius_m: f64) -> Result<FitJob, CommandError> {
        check_point(point_in_base)?;
        if !(radius_m.is_finite() && radius_m > 0.0 && radius_m <= 0.5) {
            return Err(invalid("radius", format!("{radius_m} m must be in (0, 0.5]")));
        }
        let base_from_map = self.latest_base_from_map.ok_or(CommandError::NoPatchMap)?;
        Ok(FitJob { point_in_base, radius_m, base_from_map, config: self.config.training_fit.clone() })
    }

    /// The training target from now on (a fitted or selected patch in `base_link`).
    pub fn set_target(&mut self, patch: Patch) {
        self.target = Some(patch);
    }

    /// Save the trained motion (target + recorded keyframes) atomically under `name`.
    pub fn save_motion(&mut self, name: &str) -> Result<String, CommandError> {
        let change = self.prepare_save(name)?;
        change.write()?;
        Ok(self.commit(change))
    }

    pub fn delete_motion(&mut self, name: &str) -> Result<String, CommandError> {
        let change = self.prepare_delete(name)?;
        change.write()?;
        Ok(self.commit(change))
    }

    /// The library with the trained motion added, ready to be written ([`LibraryChange::write`],
    /// on any thread) and then committed ([`Runtime::commit`]); nothing changes until then.
    pub fn prepare_save(&self, name: &str) -> Result<LibraryChange, CommandError> {
        validate_name(name)?;
        let patch = self.target.clone().ok_or(CommandError::NoTarget)?;
        if self.recorded.is_empty() {
            return Err(CommandError::NoKeyframes);
        }
        let count = self.recorded.len();
        let motion = Motion { name: name.to_string(), patch, keyframes: self.recorded.clone() };
        let mut library = self.library.clone();
        library.insert(motion)?;
        let message = format!("saved {name:?} ({count} keyframes) to {}", library.path().display());
        Ok(LibraryChange { library, trained: true, message })
    }

    /// The library without `name`, ready to be written and committed like [`Runtime::prepare_save`].
    pub fn prepare_delete(&self, name: &str) -> Result<LibraryChange, CommandError> {
        validate_name(name)?;
        let mut library = self.library.clone();
        library.remove(name)?;
        Ok(LibraryChange { library, trained: false, message: format!("deleted {name:?}") })
    }

    /// Take a written library change: the matcher uses it from the next patch map on; after a save,
    /// training starts afresh. Returns the message for the caller.
    pub fn commit(&mut self, change: LibraryChange) -> String {
        let LibraryChange { mut library, trained, message, .. } = change;
        library.mark_saved();
        self.library = library;
        self.rebuild_matcher();
        if trained {
            self.recorded.clear();
            self.target = None;
        }
        message
    }

    /// New matcher thresholds (J 6.3 ds, ks, as, rs and the variants) from the next patch map on.
    pub fn set_matcher_config(&mut self, matcher: crate::matcher::MatcherConfig) {
        self.config.matcher = matcher;
        self.rebuild_matcher();
    }

    fn rebuild_matcher(&mut self) {
        self.matcher = Matcher::new(self.config.matcher.clone(), self.library.motions().iter().map(|m| &m.patch));
    }

    pub fn list_motions(&self) -> Vec<MotionInfo> {
        self.library
            .motions()
            .iter()
            .map(|m| MotionInfo {
                name: m.name.clone(),
                surface: m.patch.surface as u8,
                boundary: m.patch.boundary as u8,
                keyframe_count: m.keyframes.len() as u32,
                duration: m.keyframes.iter().map(|k| k.move_s + k.pause_s).sum(),
            })
            .collect()
    }

    pub fn play_motion(&mut self, name: &str) -> Result<String, CommandError> {
        validate_name(name)?;
        self.bus()?;
        if self.estopped {
            return Err(CommandError::EStopped);
        }
        let motion = self.library.get(name).cloned().ok_or_else(|| LibraryError::NotFound(name.to_string()))?;
        self.start(motion)?;
        Ok(format!("playing {name:?}"))
    }

    /// E-stop: disarm, latch, stop the servos within one cycle. The latch holds until
    /// [`Runtime::reset_estop`]; arming does not clear it.
    pub fn stop(&mut self) -> String {
        self.armed = false;
        self.estopped = true;
        if let Some(bus) = &self.bus {
            bus.estop();
        }
        self.current_motion.clear();
        "stopped; disarmed; latched until reset_estop".into()
    }

    /// Stop a running motion and hold the measured pose (within one cycle), without latching the
    /// e-stop: a new motion may start at once. Returns whether a motion was running.
    pub fn hold(&mut self) -> bool {
        let playing = matches!(self.player_state, PlayerState::Playing { .. });
        if playing {
            if let Some(bus) = &self.bus {
                bus.estop();
            }
        }
        playing
    }

    /// The operator's deadman (heartbeat) was lost: disarm, hold a running motion and report
    /// `reason` as the last fault. Not latched: arming again (with heartbeats) is allowed.
    pub fn deadman_lost(&mut self, reason: String) {
        self.armed = false;
        self.hold();
        self.last_fault = Some((0, reason));
    }

    /// Clear a latched e-stop. Does not arm: automatic execution needs a separate `arm`.
    pub fn reset_estop(&mut self) -> String {
        let was = std::mem::replace(&mut self.estopped, false);
        if was {
            "e-stop cleared; disarmed".into()
        } else {
            "not e-stopped; disarmed".into()
        }
    }

    /// Arm/disarm automatic execution. Arming is refused while an e-stop is latched.
    pub fn arm(&mut self, on: bool) -> Result<String, CommandError> {
        if on && self.estopped {
            return Err(CommandError::EStopped);
        }
        self.armed = on;
        Ok(if on { "armed".into() } else { "disarmed".into() })
    }

    /// Nearest failed candidates of the last match, for logs.
    pub fn last_report(&self) -> Option<&MatchReport> {
        self.last_report.as_ref()
    }

    pub fn status(&self) -> RuntimeStatus {
        let state = if self.estopped {
            RunState::EStopped
        } else {
            match self.player_state {
                PlayerState::Playing { .. } => RunState::Playing,
                PlayerState::Faulted(_) => RunState::HoldingFault,
                PlayerState::Idle | PlayerState::Stopped => RunState::Idle,
            }
        };
        let (fault_servo_id, last_fault) = match (&self.last_fault, &self.bus_error) {
            (Some((id, text)), _) => (*id, text.clone()),
            (None, Some(reason)) => (0, CommandError::BusUnavailable(reason.clone()).to_string()),
            (None, None) => (0, String::new()),
        };
        RuntimeStatus {
            state,
            armed: self.armed,
            torque_enabled: self.torque,
            current_motion: self.current_motion.clone(),
            keyframe_index: self.keyframe_index,
            last_match: self.last_match.clone(),
            fault_servo_id,
            last_fault,
            library_size: self.library.motions().len() as u32,
            recorded_keyframes: self.recorded.len() as u32,
        }
    }

    /// Latest measured positions (rad) where known.
    pub fn positions(&self) -> &[Option<f64>] {
        &self.positions
    }
}

/// A request's point (m, `base_link`) must be finite: a NaN would be stored as a target nothing matches.
fn check_point(point_in_base: [f64; 3]) -> Result<(), CommandError> {
    if point_in_base.iter().any(|v| !v.is_finite()) {
        return Err(invalid("point", format!("{point_in_base:?} must be finite")));
    }
    Ok(())
}

/// A map patch expressed in `base_link` for matching (J 6.3 compares parameters and poses, not
/// their uncertainty, so the covariance is not propagated); `None` for a patch that cannot be moved.
fn pose_in(base_from_map: &Isometry3<f64>, patch_in_map: &Patch) -> Option<Patch> {
    // Built field by field: cloning the patch would copy the covariance only to drop it.
    let p = patch_in_map;
    let bare = Patch {
        surface: p.surface,
        boundary: p.boundary,
        boundary_params: p.boundary_params.clone(),
        curvatures: p.curvatures,
        rotation: p.rotation,
        center: p.center,
        covariance: nalgebra::DMatrix::zeros(0, 0),
        residual: p.residual,
        num_points: p.num_points,
    };
    transform_patch(&bare, base_from_map)
}

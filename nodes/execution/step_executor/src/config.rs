//! Configuration of the step executor (`config/step_executor.yaml`): servo ID ↔ joint mapping with
//! zero offsets and directions, the RS-485 bus (port, 1 Mbps, return delay), the matcher thresholds of
//! J 6.3, playback timing, and file locations. Unknown keys are rejected naming the key.

use std::path::{Path, PathBuf};

use serde::{Deserialize, Serialize};

use patchwalk_spl::fit::neighbourhood::NeighbourhoodFit;
use patchwalk_spl::sensor::ErrorModel;

use crate::matcher::MatcherConfig;
use crate::player::PlayerConfig;

/// Encoder ticks per revolution of the MX-28 (12-bit magnetic encoder, 0..=4095).
pub const TICKS_PER_REV: f64 = 4096.0;
/// Tick value at the servo's mechanical centre (0 rad).
pub const CENTER_TICKS: f64 = 2048.0;

/// Errors while loading or validating the configuration.
#[derive(Debug, thiserror::Error)]
pub enum ConfigError {
    #[error("invalid config {path}: {message}")]
    Parse { path: PathBuf, message: String },
    #[error("invalid config: {0}")]
    Invalid(String),
    #[error("invalid config: {0}")]
    Setting(#[from] InvalidSetting),
}

/// A configuration value outside its range: the dotted key, the rule it breaks and the value given.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
#[error("{key}: {rule}, got {value}")]
pub struct InvalidSetting {
    pub key: &'static str,
    pub rule: &'static str,
    pub value: f64,
}

/// Top level of `config/step_executor.yaml`.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct StepExecutorConfig {
    /// Robot model. A relative path is looked up in the working directory, the installed package's share
    /// directory (ament index), then the source tree; the built-in RPBP model when it is in none.
    pub urdf_path: PathBuf,
    /// Motion library file (J 6.3: "a library of stored stepping motions").
    pub library_path: PathBuf,
    pub bus: BusConfig,
    /// The 12 leg servos in keyframe order (J 6.2: 6-DoF legs like the DARwIn-OP).
    pub servos: Vec<ServoConfig>,
    pub matcher: MatcherConfig,
    pub player: PlayerConfig,
    /// How `select_target` fits a training target in the mapper's birds-eye cloud: set it as the
    /// running mapper is configured, so a target compares with mapped patches (J 6.3).
    pub training_fit: TrainingFitConfig,
    /// ROS 2 wiring options (owned by the ROS layer; kept here so the file has one schema).
    pub ros: RosConfig,
}

/// RS-485 Dynamixel bus settings.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct BusConfig {
    /// Serial device of the RS-485 adapter (or the pty printed by `step_executor sim-bus`).
    pub port: PathBuf,
    /// Baud rate; 1 Mbps is the MX-28 rate used by DARwIn-OP class robots.
    pub baud: u32,
    /// Return Delay Time written to every servo at start-up, microseconds (register 9, 2 µs units);
    /// 0 keeps a 12-servo sync read within one 8 ms cycle (factory value 500 µs would add 6 ms).
    pub return_delay_us: u32,
    /// Model number every servo must report on ping (MX-28 with Protocol 2.0 firmware = 30).
    pub expected_model: u16,
    /// Time allowed for a status packet beyond its transfer time, ms (ROBOTIS SDK and dynamixel2:
    /// 34 = 2 × 16 ms USB latency timer + 2 ms). Raise it for a pty on a loaded host.
    pub response_timeout_ms: f64,
    /// When a bus too slow for the control cycle becomes a fault.
    pub slow_bus: crate::slow_bus::SlowBusConfig,
    /// Present Input Voltage and Temperature of every servo are read every this many cycles
    /// (one extra sync read; 25 = 5 Hz at 8 ms; 0 = never), skipped when the cycle is short of time.
    pub health_read_period_cycles: u32,
    /// After a REBOOT, how long to wait for the servo to answer a ping again, ms.
    pub reboot_wait_ms: f64,
    /// SCHED_FIFO priority of the bus thread (1..=99; 0 = do not ask). Where SCHED_FIFO is not
    /// permitted the thread runs at nice -15 (logged once at start).
    pub realtime_priority: i32,
}

/// One servo: which joint it drives and how its ticks map to the joint angle.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ServoConfig {
    /// Joint name in the URDF.
    pub joint: String,
    /// Dynamixel ID (1..=252).
    pub id: u8,
    /// Servo angle (rad, from the 2048-tick centre) at which the joint is at 0 rad.
    #[serde(default)]
    pub zero_offset: f64,
    /// +1 or -1: sign between joint angle and servo angle.
    #[serde(default = "default_direction")]
    pub direction: i8,
}

fn default_direction() -> i8 {
    1
}

/// The training target's fit: J 3.2.1 step 13 on the cloud around the chosen point.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct TrainingFitConfig {
    /// Sensor model, fit settings, containment and plane sizing (the mapper's `sensor`, `fit`,
    /// `containment`, `plane_boundary_j_step5`).
    pub fit: NeighbourhoodFit,
    /// nf: points fitted (the mapper's `neighbourhood.fit_points`, J 6.1.2: 50).
    pub fit_points: usize,
    /// Fewer cloud points than this around the point: no fit (the mapper's `neighbourhood.min_points`).
    pub min_points: usize,
}

impl Default for TrainingFitConfig {
    fn default() -> Self {
        Self {
            // The cloud is the mapper's birds-eye raycast of the fused TSDF, not a Kinect frame: the
            // patch_mapper node models its points with a constant 1 mm along the ray, and so does this.
            fit: NeighbourhoodFit { sensor: ErrorModel::Constant { sigma_m: 0.001 }, ..NeighbourhoodFit::default() },
            fit_points: 50,
            min_points: 20,
        }
    }
}

/// ROS 2 node options (publish rates); the ROS layer may extend this struct.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct RosConfig {
    /// /joint_states rate while idle (during playback every control cycle is published), Hz.
    pub joint_state_rate_hz: f64,
    /// /step_executor/status rate, Hz.
    pub status_rate_hz: f64,
    /// Automatic execution stays armed only while heartbeats arrive on /step_executor/heartbeat at
    /// most this far apart, s (the operator's deadman).
    pub heartbeat_timeout_s: f64,
    /// Scheduling of the node's ROS loop and DDS threads, so that an e-stop request is read and
    /// answered ahead of the host's other work: 0 = nice -15 (where permitted); 1..=99 (below the bus
    /// thread's) = SCHED_FIFO at that priority. SCHED_FIFO is off by default: while the ROS side works
    /// through a burst of calls or a large reply it keeps the kernel's tty work items (which carry the
    /// serial port's bytes, USB adapters and ptys alike) off the CPU, and the bus cycle stalls for tens
    /// of ms. Long jobs (training fits, library writes) run at normal priority either way.
    pub realtime_priority: i32,
}

impl Default for RosConfig {
    fn default() -> Self {
        Self { joint_state_rate_hz: 50.0, status_rate_hz: 5.0, heartbeat_timeout_s: 0.5, realtime_priority: 0 }
    }
}

impl Default for BusConfig {
    fn default() -> Self {
        Self {
            port: PathBuf::from("/dev/ttyUSB0"),
            baud: 1_000_000,
            return_delay_us: 0,
            expected_model: patchwalk_dynamixel::mx28::MODEL_NUMBER,
            response_timeout_ms: 34.0,
            slow_bus: crate::slow_bus::SlowBusConfig::default(),
            health_read_period_cycles: 25,
            // The MX-28 boots within a few hundred ms.
            reboot_wait_ms: 2000.0,
            realtime_priority: 50,
        }
    }
}

pub use patchwalk_robot_model::DEFAULT_JOINTS;

impl Default for StepExecutorConfig {
    fn default() -> Self {
        let servos = DEFAULT_JOINTS
            .iter()
            .zip(1u8..)
            .map(|(joint, id)| ServoConfig { joint: (*joint).to_string(), id, zero_offset: 0.0, direction: 1 })
            .collect();
        Self {
            urdf_path: PathBuf::from("urdf/rpbp.urdf"),
            library_path: PathBuf::from("motions.yaml"),
            bus: BusConfig::default(),
            servos,
            matcher: MatcherConfig::default(),
            player: PlayerConfig::default(),
            training_fit: TrainingFitConfig::default(),
            ros: RosConfig::default(),
        }
    }
}

impl StepExecutorConfig {
    /// Parse from YAML text and validate.
    pub fn from_yaml(text: &str, path: &Path) -> Result<Self, ConfigError> {
        let config: Self =
            serde_yaml_ng::from_str(text).map_err(|e| ConfigError::Parse { path: path.to_path_buf(), message: e.to_string() })?;
        config.validate()?;
        Ok(config)
    }

    /// Joint names in keyframe order.
    pub fn joint_names(&self) -> Vec<String> {
        self.servos.iter().map(|s| s.joint.clone()).collect()
    }

    /// Servo IDs in keyframe order.
    pub fn servo_ids(&self) -> Vec<u8> {
        self.servos.iter().map(|s| s.id).collect()
    }

    /// Check IDs unique and in range, directions ±1, joints unique, thresholds positive.
    pub fn validate(&self) -> Result<(), ConfigError> {
        if self.servos.is_empty() {
            return Err(ConfigError::Invalid("servos: at least one servo is required".into()));
        }
        let mut ids = std::collections::BTreeSet::new();
        let mut joints = std::collections::BTreeSet::new();
        for (i, servo) in self.servos.iter().enumerate() {
            if servo.id == 0 || servo.id > 252 {
                return Err(ConfigError::Invalid(format!("servos[{i}].id: {} is outside 1..=252", servo.id)));
            }
            if !ids.insert(servo.id) {
                return Err(ConfigError::Invalid(format!("servos[{i}].id: duplicate id {}", servo.id)));
            }
            if !joints.insert(servo.joint.as_str()) {
                return Err(ConfigError::Invalid(format!("servos[{i}].joint: duplicate joint {}", servo.joint)));
            }
            if servo.direction != 1 && servo.direction != -1 {
                return Err(ConfigError::Invalid(format!("servos[{i}].direction: must be 1 or -1")));
            }
            if !servo.zero_offset.is_finite() {
                return Err(ConfigError::Invalid(format!("servos[{i}].zero_offset: not finite")));
            }
        }
        if patchwalk_dynamixel::mx28::baud_register(self.bus.baud).is_none() {
            return Err(ConfigError::Invalid(format!("bus.baud: {} is not an MX-28 baud rate", self.bus.baud)));
        }
        if !(self.bus.response_timeout_ms.is_finite() && (1.0..=10_000.0).contains(&self.bus.response_timeout_ms)) {
            return Err(ConfigError::Invalid("bus.response_timeout_ms: must be within 1..=10000".into()));
        }
        if self.bus.return_delay_us > 508 {
            return Err(ConfigError::Invalid("bus.return_delay_us: at most 508 (register 9 is 2 µs × 0..=254)".into()));
        }
        if !(self.bus.reboot_wait_ms.is_finite() && (1.0..=30_000.0).contains(&self.bus.reboot_wait_ms)) {
            return Err(ConfigError::Invalid("bus.reboot_wait_ms: must be within 1..=30000".into()));
        }
        if !(0..=99).contains(&self.bus.realtime_priority) {
            return Err(ConfigError::Invalid(format!("bus.realtime_priority: {} is outside 0..=99", self.bus.realtime_priority)));
        }
        if !(0..=99).contains(&self.ros.realtime_priority) {
            return Err(ConfigError::Invalid(format!("ros.realtime_priority: {} is outside 0..=99", self.ros.realtime_priority)));
        }
        self.bus.slow_bus.validate()?;
        self.matcher.validate()?;
        self.player.validate()?;
        Ok(())
    }
}

impl ServoConfig {
    /// Joint angle (rad) → goal position ticks (may be outside 0..=4095; callers check limits).
    pub fn ticks_from_joint(&self, joint_rad: f64) -> f64 {
        CENTER_TICKS + (f64::from(self.direction) * joint_rad + self.zero_offset) * TICKS_PER_REV / std::f64::consts::TAU
    }

    /// Present position ticks → joint angle (rad).
    pub fn joint_from_ticks(&self, ticks: f64) -> f64 {
        f64::from(self.direction) * ((ticks - CENTER_TICKS) * std::f64::consts::TAU / TICKS_PER_REV - self.zero_offset)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn default_is_valid_and_round_trips_yaml() {
        let config = StepExecutorConfig::default();
        config.validate().unwrap();
        let text = serde_yaml_ng::to_string(&config).unwrap();
        let back = StepExecutorConfig::from_yaml(&text, Path::new("x.yaml")).unwrap();
        assert_eq!(back, config);
        assert_eq!(back.servos.len(), 12);
    }

    #[test]
    fn shipped_config_file_is_valid_and_equals_defaults() {
        let path = Path::new(env!("CARGO_MANIFEST_DIR")).join("../../../config/step_executor.yaml");
        let config: StepExecutorConfig = patchwalk_ros::params::load_config(Some(&path), &[]).unwrap();
        config.validate().unwrap();
        assert_eq!(config, StepExecutorConfig::default());
    }

    #[test]
    fn unknown_key_is_named() {
        let err = StepExecutorConfig::from_yaml("bus:\n  bogus_key: 3\n", Path::new("c.yaml")).unwrap_err();
        assert!(err.to_string().contains("bogus_key"), "{err}");
    }

    #[test]
    fn duplicate_ids_rejected() {
        let mut config = StepExecutorConfig::default();
        config.servos[1].id = config.servos[0].id;
        assert!(config.validate().unwrap_err().to_string().contains("duplicate id"));
    }

    #[test]
    fn tick_conversion_round_trips_with_offset_and_direction() {
        let servo = ServoConfig { joint: "j".into(), id: 1, zero_offset: 0.1, direction: -1 };
        let ticks = servo.ticks_from_joint(0.7);
        assert!((servo.joint_from_ticks(ticks) - 0.7).abs() < 1e-12);
        let plain = ServoConfig { joint: "j".into(), id: 1, zero_offset: 0.0, direction: 1 };
        assert_eq!(plain.ticks_from_joint(0.0), 2048.0);
        assert!((plain.ticks_from_joint(std::f64::consts::FRAC_PI_2) - 3072.0).abs() < 1e-9);
    }
}

//! Configuration of the simulator (`config/terrain_sim.yaml`): seed, scene, camera, IMU, motion and
//! node wiring. One struct per stage, `Default` = the paper's values; unknown keys are rejected
//! naming the key.

use std::path::PathBuf;

use serde::{Deserialize, Serialize};

use crate::camera::CameraConfig;
use crate::camera_path::CameraPathConfig;
use crate::imu::ImuConfig;
use crate::motion::MotionConfig;
use crate::scene::SceneConfig;

/// ROS 2 node wiring (used by the binary only).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct NodeConfig {
    /// Frame ids of the published messages (REP-103 `camera_optical`, `imu`).
    pub camera_frame_id: String,
    pub imu_frame_id: String,
    /// Robot model for following `/joint_states` (relative to the workspace root); empty = ignore
    /// joint states and keep the lookdown pose of `motion`.
    pub urdf_path: PathBuf,
    /// Follow `/joint_states` (the servo positions of the simulated bus).
    pub follow_joint_states: bool,
}

impl Default for NodeConfig {
    fn default() -> Self {
        Self {
            camera_frame_id: "camera_optical".into(),
            imu_frame_id: "imu".into(),
            urdf_path: PathBuf::from("urdf/rpbp.urdf"),
            follow_joint_states: true,
        }
    }
}

/// Top level of `config/terrain_sim.yaml`.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct SimConfig {
    /// Seed of everything random (untrained rocks, noise, jitter).
    pub seed: u64,
    /// Index of the rock the robot starts in front of.
    pub start_rock: usize,
    pub scene: SceneConfig,
    pub camera: CameraConfig,
    pub imu: ImuConfig,
    pub motion: MotionConfig,
    /// Camera path over a terrain (see `camera_path`).
    pub path: CameraPathConfig,
    pub node: NodeConfig,
}

impl Default for SimConfig {
    fn default() -> Self {
        Self {
            seed: 7,
            start_rock: 0,
            scene: SceneConfig::default(),
            camera: CameraConfig::default(),
            imu: ImuConfig::default(),
            motion: MotionConfig::default(),
            path: CameraPathConfig::default(),
            node: NodeConfig::default(),
        }
    }
}

impl SimConfig {
    /// Parses YAML text (error message names the offending key).
    pub fn from_yaml(text: &str) -> Result<Self, serde_yaml_ng::Error> {
        if text.trim().is_empty() {
            return Ok(Self::default());
        }
        serde_yaml_ng::from_str(text)
    }
}

/// A configuration file and its `--param` overrides as `terrain_sim run --config FILE -p ..` takes
/// them (the file's text up to the first NUL byte, then NUL-separated overrides; invalid UTF-8
/// replaced), loaded by `patchwalk_ros::params` and checked by building the simulator from it, as the
/// node does before it starts.
pub fn config_file(bytes: &[u8]) -> Result<crate::sim::Simulator, ConfigFileError> {
    let mut parts = bytes.split(|b| *b == 0).map(|part| String::from_utf8_lossy(part).into_owned());
    let text = parts.next().unwrap_or_default();
    let overrides: Vec<String> = parts.collect();
    let config: SimConfig = patchwalk_ros::params::load_config_from_str(&text, std::path::Path::new("terrain_sim.yaml"), &overrides)?;
    Ok(crate::sim::Simulator::new(config)?)
}

/// Why a configuration input was refused.
#[derive(Debug, thiserror::Error)]
pub enum ConfigFileError {
    #[error(transparent)]
    Params(#[from] patchwalk_ros::params::ParamError),
    #[error(transparent)]
    Simulator(#[from] crate::sim::SimError),
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Every stored fuzz input of the configuration loader (seeds, minimised corpus, inputs that
    /// once crashed) loads or is refused with a message; the shipped config must load.
    #[test]
    fn stored_params_inputs_are_handled() {
        let inputs = patchwalk_test_support::stored_fuzz_inputs("params_yaml");
        let mut loaded = 0;
        for (path, bytes) in &inputs {
            match config_file(bytes) {
                Ok(_) => loaded += 1,
                Err(e) => assert!(!e.to_string().is_empty(), "{}", path.display()),
            }
        }
        assert!(loaded > 0, "{loaded} of {} stored params_yaml inputs loaded", inputs.len());
    }

    #[test]
    fn shipped_config_parses() {
        let path = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("../../../config/terrain_sim.yaml");
        let config: SimConfig = patchwalk_ros::params::load_config(Some(&path), &[]).unwrap();
        assert_eq!(config, SimConfig::default(), "config/terrain_sim.yaml holds only examples in comments");
    }

    #[test]
    fn unknown_keys_are_named() {
        let error = SimConfig::from_yaml("camera:\n  fxx: 500\n").unwrap_err().to_string();
        assert!(error.contains("fxx"), "{error}");
        let config = SimConfig::from_yaml("seed: 3\ncamera:\n  fx: 500\n").unwrap();
        assert_eq!((config.seed, config.camera.fx, config.camera.fy), (3, 500.0, 570.3));
        assert_eq!(SimConfig::from_yaml("").unwrap(), SimConfig::default());
    }

    #[test]
    fn rock_shapes_parse_from_yaml() {
        let text = "scene:\n  training_rocks:\n    - kind: lying_cylinder\n      radius_m: 0.04\n      length_m: 0.2\n";
        let config = SimConfig::from_yaml(text).unwrap();
        assert_eq!(config.scene.training_rocks.map(|r| r.len()), Some(1));
    }
}

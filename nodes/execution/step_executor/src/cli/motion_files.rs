//! What `import-motion` and `export-motion` share: the options naming the configuration, library and
//! ID table, and loading them (the library strictly: a malformed file is an error, never replaced).

use std::path::{Path, PathBuf};

use anyhow::Context;
use patchwalk_robot_model::kinematics::{JointLimits, RobotModel};
use step_executor::action_file::IdMap;
use step_executor::config::StepExecutorConfig;
use step_executor::library::MotionLibrary;

/// Options of both commands.
#[derive(clap::Args, Debug, Clone)]
pub struct LibraryArgs {
    /// Motion library file [default: the configuration's `library_path`, motions.yaml].
    #[arg(long, value_name = "FILE")]
    pub library: Option<PathBuf>,
    /// ID table: a YAML list `- { id: 7, joint: r_hip_yaw, direction: 1, zero_offset: 0.0 }`, one entry
    /// per library joint [default: DARwIn-OP's leg servos 7–18 in the library's joint order].
    #[arg(long, value_name = "FILE")]
    pub id_map: Option<PathBuf>,
    /// step_executor configuration (joint order, URDF, library path, `player.limit_margin_rad`)
    /// [default: the built-in configuration].
    #[arg(long, value_name = "FILE")]
    pub config: Option<PathBuf>,
}

/// The library, the ID table in its joint order and the joints' limits (with the player's margin).
pub struct MotionFiles {
    pub library: MotionLibrary,
    pub map: IdMap,
    pub limits: Vec<JointLimits>,
}

impl LibraryArgs {
    pub fn load(&self) -> anyhow::Result<MotionFiles> {
        let config: StepExecutorConfig = patchwalk_ros::params::load_config(self.config.as_deref(), &[])?;
        config.validate()?;
        let joints = config.joint_names();
        let model = if config.urdf_path.exists() {
            RobotModel::from_file(&config.urdf_path)?
        } else {
            RobotModel::from_urdf_str(patchwalk_robot_model::RPBP_URDF)?
        };
        let margin = config.player.limit_margin_rad;
        let limits = joints
            .iter()
            .map(|joint| {
                let limits = model.joint_limits(joint)?.with_context(|| format!("joint {joint:?} has no position limits in the URDF"))?;
                Ok(JointLimits { lower: limits.lower + margin, upper: limits.upper - margin })
            })
            .collect::<anyhow::Result<Vec<_>>>()?;
        let entries = match &self.id_map {
            None => IdMap::darwin_op_legs(),
            Some(path) => {
                let text = std::fs::read_to_string(path).with_context(|| format!("cannot read ID table {}", path.display()))?;
                IdMap::parse_entries(&text, &path.display().to_string())?
            }
        };
        let map = IdMap::for_joints(&entries, &joints)?;
        let library_path = self.library.clone().unwrap_or(config.library_path);
        let library = MotionLibrary::load(&library_path, &joints)?;
        Ok(MotionFiles { library, map, limits })
    }
}

/// Refuse DARwIn-OP's `motion_1024.bin`: same layout, but 1024 ticks per 300°, which these commands
/// do not convert.
pub fn refuse_1024_tick_file(path: &Path) -> anyhow::Result<()> {
    if path.file_name().and_then(|n| n.to_str()).is_some_and(|n| n.contains("1024")) {
        anyhow::bail!(
            "{}: a 1024-tick action file (DARwIn-OP's motion_1024.bin, 300° over 1024 ticks) is not supported; \
             use the 4096-tick motion_4096.bin or OP3's motion_4095.bin",
            path.display()
        );
    }
    Ok(())
}

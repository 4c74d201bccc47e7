//! What the footholds subcommands share: opening a dataset with its IMU mount and labelling it.

use std::path::Path;

use anyhow::{Context, Result};
use nalgebra::UnitQuaternion;
use patchwalk_footholds::labels::{dataset_camera_from_imu, fuse_sequence, label_frame, FusedSequence, LabelConfig, LabelledFrame};
use patchwalk_footholds::regions::RegionConfig;
use patchwalk_fusion::calibration::{calibrate_dataset, CalibrationConfig};
use patchwalk_fusion::dataset::Dataset;

/// A dataset and the rotation of its IMU into the camera frame: `intrinsics.json`'s mount
/// (`terrain_sim record`), else calibrated from its dominant horizontal plane (J 2.2, as
/// `patch_mapper calibrate-imu`).
pub struct Sequence {
    pub name: String,
    pub dataset: Dataset,
    pub camera_from_imu: UnitQuaternion<f64>,
}

impl Sequence {
    pub fn open(path: &Path) -> Result<Self> {
        let dataset = Dataset::open(path).with_context(|| format!("opening {}", path.display()))?;
        if dataset.accelerometer.is_empty() {
            anyhow::bail!("{}: no accelerometer data (accelerometer.txt): the camera tilt is unknown", path.display());
        }
        let camera_from_imu = match dataset_camera_from_imu(&dataset)? {
            Some(q) => q,
            None => calibrate_dataset(&dataset, &CalibrationConfig::default())
                .with_context(|| format!("calibrating the IMU mount of {} from its dominant plane", path.display()))?
                .camera_from_imu,
        };
        let name = path.file_name().map_or_else(|| path.display().to_string(), |n| n.to_string_lossy().into_owned());
        Ok(Self { name, dataset, camera_from_imu })
    }
}

/// The fused sequence and every `stride`-th tracked frame labelled from it: (frame index, frame).
pub fn label_sequence(
    sequence: &Sequence,
    stride: usize,
    regions: &RegionConfig,
    label: &LabelConfig,
) -> Result<(FusedSequence, Vec<(usize, LabelledFrame)>)> {
    let fused = fuse_sequence(&sequence.dataset, &sequence.camera_from_imu, None, label)
        .with_context(|| format!("fusing {}", sequence.name))?;
    let mut frames = Vec::new();
    for pose in fused.frames.iter().step_by(stride.max(1)) {
        let depth = sequence.dataset.load_depth(pose.index)?;
        let labelled = label_frame(&depth, &sequence.dataset.intrinsics, pose, &fused.footholds_in_map, &fused.grid, regions, label)
            .with_context(|| format!("labelling frame {} of {}", pose.index, sequence.name))?;
        frames.push((pose.index, labelled));
    }
    Ok((fused, frames))
}

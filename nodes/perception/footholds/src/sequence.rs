//! A recorded or simulated sequence with its IMU mount, and its labelled frames.

use std::path::Path;

use nalgebra::UnitQuaternion;
use patchwalk_fusion::calibration::{calibrate_dataset, CalibrationConfig};
use patchwalk_fusion::dataset::Dataset;

use crate::error::FootholdError;
use crate::labels::{
    dataset_camera_from_imu, fuse_sequence, label_frame, labelling_configs, FusedSequence, LabelConfig, LabelledFrame, LabellingConfigs,
};
use crate::regions::RegionConfig;

/// A dataset and the rotation of its IMU into the camera frame: `intrinsics.json`'s mount
/// (`terrain_sim record`), else calibrated from its dominant horizontal plane (J 2.2, as
/// `patch_mapper calibrate-imu`), and the labelling run's configurations fitted to its depth.
pub struct Sequence {
    pub name: String,
    pub dataset: Dataset,
    pub camera_from_imu: UnitQuaternion<f64>,
    pub configs: LabellingConfigs,
}

impl Sequence {
    pub fn open(path: &Path) -> Result<Self, FootholdError> {
        let dataset = Dataset::open(path)?;
        if dataset.accelerometer.is_empty() {
            return Err(FootholdError::Config(format!(
                "{}: no accelerometer data (accelerometer.txt): the camera tilt is unknown",
                path.display()
            )));
        }
        let camera_from_imu = match dataset_camera_from_imu(&dataset)? {
            Some(q) => q,
            None => {
                calibrate_dataset(&dataset, &CalibrationConfig::default())
                    .map_err(|e| {
                        FootholdError::Config(format!("calibrating the IMU mount of {} from its dominant plane: {e}", path.display()))
                    })?
                    .camera_from_imu
            }
        };
        // `<parent>/<directory>`: several sources may each have a `seed_1`.
        let file = |p: &Path| p.file_name().map(|n| n.to_string_lossy().into_owned());
        let name = match (path.parent().and_then(file), file(path)) {
            (Some(parent), Some(own)) => format!("{parent}/{own}"),
            (None, Some(own)) => own,
            _ => path.display().to_string(),
        };
        let configs = labelling_configs(&dataset, &camera_from_imu)?;
        Ok(Self { name, dataset, camera_from_imu, configs })
    }

    /// The fused sequence and every `stride`-th tracked frame labelled from it: (frame index, frame).
    /// The sequence is fused on one thread: tracking and fitting sum in parallel, and sums split
    /// differently from run to run move a pose by a rounding error, which can turn a patch at the
    /// edge of the validator's limits. On one thread the labels are the same in every run.
    pub fn label(
        &self,
        stride: usize,
        regions: &RegionConfig,
        label: &LabelConfig,
    ) -> Result<(FusedSequence, Vec<(usize, LabelledFrame)>), FootholdError> {
        let one_thread = rayon::ThreadPoolBuilder::new()
            .num_threads(1)
            .build()
            .map_err(|e| FootholdError::Config(format!("a labelling thread: {e}")))?;
        let fused = one_thread.install(|| fuse_sequence(&self.dataset, &self.camera_from_imu, &self.configs, None, label))?;
        let mut frames = Vec::new();
        for pose in fused.frames.iter().step_by(stride.max(1)) {
            let depth = self.dataset.load_depth(pose.index)?;
            frames.push((
                pose.index,
                label_frame(
                    &depth,
                    &self.dataset.intrinsics,
                    pose,
                    &fused.footholds_in_map,
                    &fused.rejected_in_map,
                    &fused.grid,
                    regions,
                    label,
                )?,
            ));
        }
        Ok((fused, frames))
    }
}

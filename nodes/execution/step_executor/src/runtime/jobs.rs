//! Work of the runtime in parts that can run on another thread: a training fit, a library change
//! to write. The node prepares them, runs them off its loop and takes the result back.

use nalgebra::{Isometry3, Point3, Translation3, UnitQuaternion, Vector3};
use patchwalk_spl::fit::neighbourhood::fit_neighbourhood;
use patchwalk_spl::patch::Patch;
use patchwalk_spl::transform::transform_patch;

use super::FitError;
use crate::config::TrainingFitConfig;
use crate::library::{LibraryError, MotionLibrary};

/// A training fit requested by [`super::Runtime::fit_job`], to run where it does not hold up the node.
#[derive(Debug, Clone)]
pub struct FitJob {
    pub(super) point_in_base: [f64; 3],
    pub(super) radius_m: f64,
    pub(super) base_from_map: Isometry3<f64>,
    pub(super) config: TrainingFitConfig,
}

impl FitJob {
    /// Fit the cloud points (in the latest patch map's frame; non-finite ones are ignored) within
    /// the radius of the point, as the mapper fits its seeds (`training_fit`: nf points spread over
    /// the neighbourhood, sensor model, boundary sizing), in a virtual birds-eye camera 1 m above the
    /// point looking down (map z is up, REP-103), so the target compares with mapped patches under
    /// J 6.3's thresholds. The patch comes back in `base_link`.
    pub fn run(&self, cloud_in_map: &[Vector3<f64>]) -> Result<Patch, FitError> {
        let (base_from_map, radius_m, config) = (&self.base_from_map, self.radius_m, &self.config);
        if cloud_in_map.is_empty() {
            return Err(FitError::NoCloud);
        }
        let point_in_map = (base_from_map.inverse() * Point3::from(self.point_in_base)).coords;
        // NaN and infinite points fail the distance test.
        let points: Vec<Vector3<f64>> = cloud_in_map.iter().filter(|p| (*p - point_in_map).norm() <= radius_m).copied().collect();
        let min_points = config.min_points.max(1);
        if points.len() < min_points {
            return Err(FitError::TooFewPoints { found: points.len(), radius_m, needed: min_points });
        }
        let map_from_camera = Isometry3::from_parts(
            Translation3::from(point_in_map + Vector3::z()),
            UnitQuaternion::from_axis_angle(&Vector3::x_axis(), std::f64::consts::PI),
        );
        let points_in_camera: Vec<Vector3<f64>> = points.iter().map(|p| (map_from_camera.inverse() * Point3::from(*p)).coords).collect();
        let nf = config.fit_points.clamp(1, points_in_camera.len());
        let fit_points: Vec<Vector3<f64>> =
            (0..nf).filter_map(|i| points_in_camera.get(i * points_in_camera.len() / nf).copied()).collect();
        let fitted_in_camera = fit_neighbourhood(&fit_points, &points_in_camera, &config.fit)?;
        transform_patch(&fitted_in_camera, &(base_from_map * map_from_camera)).ok_or(FitError::NotMovable)
    }
}

/// A library change prepared by [`super::Runtime::prepare_save`] or [`super::Runtime::prepare_delete`].
#[derive(Debug)]
pub struct LibraryChange {
    pub(super) library: MotionLibrary,
    /// A save of the trained motion (training starts afresh once committed).
    pub(super) trained: bool,
    pub(super) message: String,
}

impl LibraryChange {
    /// Serialise and write the file atomically (fsync); the runtime's library is untouched.
    pub fn write(&self) -> Result<(), LibraryError> {
        self.library.save_job()?.run()
    }
}

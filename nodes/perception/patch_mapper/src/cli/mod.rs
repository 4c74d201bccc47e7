//! Offline subcommands of the `patch_mapper` binary.
pub use patch_mapper::bag_input;
pub mod calibrate_imu;
pub mod fit;
pub mod footholds;
pub mod footholds_plan;
pub mod map;
pub mod replay;
pub mod track;

use nalgebra::{Matrix3, Rotation3, Vector3};
use patchwalk_fusion::calibration::{calibrate_dataset, CalibrationConfig};
use patchwalk_fusion::dataset::Dataset;

/// The IMU→camera rotation to use with a dataset's accelerometer: the configured
/// `mapper.acquire.camera_from_imu` when it is set (not the identity), otherwise one calibrated on the
/// dataset itself (J 2.2: accelerometer against the dominant plane of its frames). `None` when the
/// dataset has no accelerometer or the calibration fails (then gravity comes from the ground plane);
/// the message says which it was.
pub fn dataset_camera_from_imu(dataset: &Dataset, configured: &Rotation3<f64>) -> (Option<Rotation3<f64>>, String) {
    if dataset.accelerometer.is_empty() {
        return (None, "no accelerometer in the data".into());
    }
    if configured.matrix() != &Matrix3::identity() {
        return (Some(*configured), "configured mapper.acquire.camera_from_imu".into());
    }
    match calibrate_dataset(dataset, &CalibrationConfig::default()) {
        Ok(calibration) => (
            Some(calibration.camera_from_imu.to_rotation_matrix()),
            format!("camera_from_imu calibrated on the data, residual RMS {:.2}°", calibration.rms_residual_deg),
        ),
        Err(err) => (None, format!("the accelerometer could not be calibrated against the data ({err})")),
    }
}

/// Errors of command-line values.
#[derive(Debug, thiserror::Error, PartialEq)]
pub enum ArgError {
    /// Not three comma-separated finite numbers.
    #[error("expected three finite numbers x,y,z, got '{0}'")]
    NotVec3(String),
}

/// A vector `x,y,z` of three finite numbers (the `--sensor-origin` / `--gravity` values).
pub fn parse_vec3(s: &str) -> Result<Vector3<f64>, ArgError> {
    let v: Result<Vec<f64>, _> = s.split(',').map(|p| p.trim().parse::<f64>()).collect();
    match v.as_deref() {
        Ok([x, y, z]) if [x, y, z].iter().all(|c| c.is_finite()) => Ok(Vector3::new(*x, *y, *z)),
        _ => Err(ArgError::NotVec3(s.to_string())),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn vectors_parse_and_bad_ones_are_rejected() {
        assert_eq!(parse_vec3("0, 0.79,-0.62").unwrap(), Vector3::new(0.0, 0.79, -0.62));
        for bad in ["1,2", "1,2,3,4", "a,b,c", "1,inf,2", "1,NaN,2"] {
            assert_eq!(parse_vec3(bad), Err(ArgError::NotVec3(bad.to_string())), "{bad}");
        }
    }
}

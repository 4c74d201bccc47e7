//! IMU–camera rotation calibration (J 2.2): from frames of a dominant horizontal plane, pair the IMU's
//! gravity with the plane's downward normal in the camera frame and solve the orthogonal Procrustes
//! problem for `camera_from_imu`.
//!
//! Gravity in the IMU frame is the negated, normalised accelerometer reading (a static accelerometer
//! measures the specific force, pointing up). The dominant plane is found by RANSAC on a subsampled
//! cloud and refined by least squares (PCA of the inliers); its normal is oriented away from the
//! camera (the floor/desk is below and in front of it), which is "down".

use nalgebra::{Matrix3, UnitQuaternion, Vector3};
use rand::{Rng, SeedableRng};

use crate::camera::{DepthImage, Intrinsics};
use crate::dataset::{Dataset, DatasetError};
use patchwalk_spl::geometry::nearest_rotation;

/// Errors of the calibration.
#[derive(Debug, thiserror::Error)]
pub enum CalibrationError {
    #[error(transparent)]
    Dataset(#[from] DatasetError),
    #[error("calibration needs accelerometer data, the dataset has none")]
    NoAccelerometer,
    #[error("only {found} usable frames (plane + accelerometer), need at least {needed}")]
    TooFewPairs { found: usize, needed: usize },
}

/// Calibration parameters.
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize, serde::Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct CalibrationConfig {
    /// RANSAC inlier distance to the plane (m).
    pub plane_inlier_m: f64,
    /// RANSAC hypotheses per frame.
    pub ransac_iterations: usize,
    /// Pixel stride of the cloud used for plane fitting.
    pub pixel_stride: usize,
    /// A frame is used only if the plane holds at least this fraction of its sampled points.
    pub min_plane_fraction: f64,
    /// Accelerometer samples within ± this many seconds of a frame are averaged.
    pub accelerometer_half_window_s: f64,
    /// Use every n-th frame.
    pub frame_stride: usize,
    /// RNG seed (deterministic runs).
    pub seed: u64,
}

impl Default for CalibrationConfig {
    fn default() -> Self {
        Self {
            plane_inlier_m: 0.01,
            ransac_iterations: 300,
            pixel_stride: 4,
            min_plane_fraction: 0.2,
            accelerometer_half_window_s: 0.02,
            frame_stride: 1,
            seed: 7,
        }
    }
}

/// A plane `normal · p = offset` in the camera frame with its support.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Plane {
    pub normal: Vector3<f64>,
    pub offset: f64,
    pub inliers: usize,
    pub sampled: usize,
}

/// The calibration result.
#[derive(Debug, Clone, PartialEq)]
pub struct ImuCalibration {
    pub camera_from_imu: UnitQuaternion<f64>,
    /// RMS angle between the rotated IMU gravity and the plane-normal gravity (deg).
    pub rms_residual_deg: f64,
    pub max_residual_deg: f64,
    /// Singular values of Σ g_cam g_imuᵀ: a small second value means the pairs span ~one
    /// direction, so the rotation about gravity is not observable.
    pub singular_values: [f64; 3],
    pub pairs: usize,
}

/// Orthogonal Procrustes: the rotation R minimising Σ‖R aᵢ − bᵢ‖² over pairs (aᵢ in IMU, bᵢ in camera).
pub fn solve_procrustes(pairs: &[(Vector3<f64>, Vector3<f64>)]) -> Option<ImuCalibration> {
    if pairs.is_empty() {
        return None;
    }
    let mut m = Matrix3::zeros();
    for (a, b) in pairs {
        m += b.normalize() * a.normalize().transpose();
    }
    let rotation = nearest_rotation(&m)?;
    let singular = m.singular_values();
    let angles: Vec<f64> = pairs.iter().map(|(a, b)| (rotation * a.normalize()).angle(&b.normalize()).to_degrees()).collect();
    let rms = (angles.iter().map(|x| x * x).sum::<f64>() / angles.len() as f64).sqrt();
    let max = angles.iter().copied().fold(0.0, f64::max);
    Some(ImuCalibration {
        camera_from_imu: UnitQuaternion::from_rotation_matrix(&rotation),
        rms_residual_deg: rms,
        max_residual_deg: max,
        singular_values: [singular[0], singular[1], singular[2]],
        pairs: pairs.len(),
    })
}

/// Gravity (unit, down) in the IMU frame from an accelerometer reading.
pub fn gravity_from_acceleration(acceleration_in_imu: &Vector3<f64>) -> Option<Vector3<f64>> {
    (-acceleration_in_imu).try_normalize(1e-9)
}

/// Dominant plane of a depth frame by RANSAC + least-squares refinement; normal oriented away from
/// the camera (`offset > 0`).
pub fn dominant_plane(depth: &DepthImage, intrinsics: &Intrinsics, config: &CalibrationConfig) -> Option<Plane> {
    let stride = config.pixel_stride.max(1);
    let mut points = Vec::new();
    for v in (0..depth.height).step_by(stride) {
        for u in (0..depth.width).step_by(stride) {
            if let Some(z) = depth.get(u, v) {
                points.push(intrinsics.back_project(u as f64, v as f64, f64::from(z)));
            }
        }
    }
    if points.len() < 3 {
        return None;
    }
    let mut rng = rand::rngs::StdRng::seed_from_u64(config.seed);
    let mut best: Option<(Vector3<f64>, f64, usize)> = None;
    for _ in 0..config.ransac_iterations {
        let pick = |rng: &mut rand::rngs::StdRng| points.get(rng.random_range(0..points.len())).copied();
        let (Some(a), Some(b), Some(c)) = (pick(&mut rng), pick(&mut rng), pick(&mut rng)) else { continue };
        let Some(normal) = (b - a).cross(&(c - a)).try_normalize(1e-12) else { continue };
        let offset = normal.dot(&a);
        let count = points.iter().filter(|p| (normal.dot(p) - offset).abs() < config.plane_inlier_m).count();
        if best.is_none_or(|(_, _, n)| count > n) {
            best = Some((normal, offset, count));
        }
    }
    let (normal, offset, _) = best?;
    let inliers: Vec<Vector3<f64>> = points.iter().copied().filter(|p| (normal.dot(p) - offset).abs() < config.plane_inlier_m).collect();
    if inliers.len() < 3 {
        return None;
    }
    // Least squares: normal = eigenvector of the smallest eigenvalue of the inlier scatter.
    let centroid: Vector3<f64> = inliers.iter().sum::<Vector3<f64>>() / inliers.len() as f64;
    let scatter: Matrix3<f64> = inliers.iter().map(|p| (p - centroid) * (p - centroid).transpose()).sum();
    let eigen = scatter.symmetric_eigen();
    let smallest = eigen.eigenvalues.imin();
    let mut refined: Vector3<f64> = eigen.eigenvectors.column(smallest).into_owned();
    if refined.dot(&centroid) < 0.0 {
        refined = -refined;
    }
    Some(Plane { normal: refined, offset: refined.dot(&centroid), inliers: inliers.len(), sampled: points.len() })
}

/// Calibrates `camera_from_imu` on a dataset whose dominant plane is horizontal (J 2.2).
pub fn calibrate_dataset(dataset: &Dataset, config: &CalibrationConfig) -> Result<ImuCalibration, CalibrationError> {
    if dataset.accelerometer.is_empty() {
        return Err(CalibrationError::NoAccelerometer);
    }
    let mut pairs = Vec::new();
    for (index, frame) in dataset.frames.iter().enumerate().step_by(config.frame_stride.max(1)) {
        let Some(acceleration) = dataset.acceleration_near(frame.timestamp, config.accelerometer_half_window_s) else {
            continue;
        };
        let Some(gravity_in_imu) = gravity_from_acceleration(&acceleration) else { continue };
        let depth = dataset.load_depth(index)?;
        let Some(plane) = dominant_plane(&depth, &dataset.intrinsics, config) else { continue };
        if (plane.inliers as f64) < config.min_plane_fraction * plane.sampled as f64 {
            continue;
        }
        pairs.push((gravity_in_imu, plane.normal));
    }
    let needed = 2;
    if pairs.len() < needed {
        return Err(CalibrationError::TooFewPairs { found: pairs.len(), needed });
    }
    solve_procrustes(&pairs).ok_or(CalibrationError::TooFewPairs { found: 0, needed })
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::dataset::test_data_dir;

    #[test]
    fn procrustes_recovers_a_known_rotation() {
        let truth = UnitQuaternion::from_euler_angles(0.3, -1.2, 2.0);
        let mut rng = rand::rngs::StdRng::seed_from_u64(3);
        let pairs: Vec<_> = (0..20)
            .map(|_| {
                let a = Vector3::new(rng.random_range(-1.0..1.0), rng.random_range(-1.0..1.0), rng.random_range(-1.0..1.0));
                (a, truth * a)
            })
            .collect();
        let calibration = solve_procrustes(&pairs).unwrap();
        assert!(calibration.camera_from_imu.angle_to(&truth) < 1e-9);
        assert!(calibration.rms_residual_deg < 1e-6);
        assert!(solve_procrustes(&[]).is_none());
    }

    #[test]
    fn plane_normal_points_away_from_the_camera() {
        let intrinsics = Intrinsics::primesense_default().scaled(0.25);
        let normal = Vector3::new(0.0, 0.8, 0.6);
        let depth = crate::fusion::tests::render_plane(&intrinsics, &nalgebra::Isometry3::identity(), normal, 1.0);
        let plane = dominant_plane(&depth, &intrinsics, &CalibrationConfig::default()).unwrap();
        assert!((plane.normal - normal).norm() < 1e-6, "{}", plane.normal);
        assert!((plane.offset - 1.0).abs() < 1e-6);
    }

    #[test]
    fn tum_desk_gives_a_consistent_rotation() {
        let dataset = Dataset::open(&test_data_dir().join("tum_fr1_xyz")).unwrap();
        let calibration = calibrate_dataset(&dataset, &CalibrationConfig::default()).unwrap();
        eprintln!("{calibration:?}");
        assert!(calibration.pairs >= 30);
        // The desk is horizontal; the residual is the IMU/plane disagreement (noise + motion).
        assert!(calibration.rms_residual_deg < 5.0, "{}", calibration.rms_residual_deg);
        // README: mean accelerometer / g ≈ (0.04, 0.75, −0.66), up in the optical frame ≈ (0.01, −0.79, −0.62).
        let up_in_camera = calibration.camera_from_imu * Vector3::new(0.04, 0.75, -0.66).normalize();
        assert!(up_in_camera.angle(&Vector3::new(0.01, -0.79, -0.62)) < 5f64.to_radians(), "{up_in_camera}");
    }
}

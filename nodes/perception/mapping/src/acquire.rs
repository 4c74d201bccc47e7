//! Stage i (J 4.1, steps 1–2): depth image + intrinsics -> organized point cloud in the camera
//! frame (NaN where invalid); IMU orientation or accelerometer -> unit gravity in the camera frame;
//! a gravity-aligned `map_from_camera` for single frames.
//!
//! Gravity sources, in the order a caller usually prefers them:
//! 1. an explicit gravity vector in the camera frame (e.g. `--gravity` of `patch_mapper map`),
//! 2. an IMU orientation quaternion or an accelerometer reading, through `camera_from_imu`
//!    (J 2.2: the rotation found by Procrustes calibration, see `calibration.rs`),
//! 3. the fallback: the normal of the dominant plane of the frame ([`gravity_from_dominant_plane`]),
//!    valid when the frame is dominated by a horizontal floor or table (the assumption J 2.2 makes
//!    for calibration).

use nalgebra::{Isometry3, Matrix3, Rotation3, Translation3, Unit, UnitQuaternion, Vector3};
use rand::{Rng, SeedableRng};
use rayon::prelude::*;

use patchwalk_fusion::camera::{DepthImage, Intrinsics};

/// Errors of stage i.
#[derive(Debug, thiserror::Error, PartialEq)]
pub enum AcquireError {
    #[error("depth image is {image_w}x{image_h} but the intrinsics are for {intr_w}x{intr_h}")]
    SizeMismatch { image_w: usize, image_h: usize, intr_w: usize, intr_h: usize },
    #[error("gravity vector {0:?} is zero or not finite")]
    BadGravity([f64; 3]),
    #[error("camera_from_imu is not a rotation matrix (det {det:.3}, orthogonality error {error:.3})")]
    BadRotation { det: f64, error: f64 },
    #[error("no dominant plane: {0}")]
    NoPlane(String),
}

/// Configuration of stage i.
#[derive(Debug, Clone, PartialEq, serde::Serialize, serde::Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct AcquireConfig {
    /// Row-major rotation `camera_from_imu` (J 2.2: from Procrustes calibration). Identity when
    /// the IMU axes are the optical axes.
    pub camera_from_imu: [[f64; 3]; 3],
    /// Half window (s) over which accelerometer samples are averaged around a frame timestamp.
    pub accel_half_window_s: f64,
}

impl Default for AcquireConfig {
    fn default() -> Self {
        Self { camera_from_imu: [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]], accel_half_window_s: 0.05 }
    }
}

impl AcquireConfig {
    /// The configured `camera_from_imu`, checked to be a proper rotation.
    pub fn camera_from_imu(&self) -> Result<Rotation3<f64>, AcquireError> {
        let m = Matrix3::from_fn(|r, c| self.camera_from_imu[r][c]);
        let det = m.determinant();
        let error = (m.transpose() * m - Matrix3::identity()).norm();
        if !(det.is_finite() && (det - 1.0).abs() < 1e-3 && error < 1e-3) {
            return Err(AcquireError::BadRotation { det, error });
        }
        Ok(Rotation3::from_matrix(&m))
    }
}

/// An organized point cloud (J step 2): one point per pixel, row-major, NaN where invalid.
#[derive(Debug, Clone, PartialEq)]
pub struct OrganizedCloud {
    pub width: usize,
    pub height: usize,
    /// Points in the camera frame (metres); all-NaN where there is no data.
    pub points_in_camera: Vec<Vector3<f32>>,
}

impl OrganizedCloud {
    /// Point at column `u`, row `v` if inside the image and valid.
    #[inline]
    pub fn get(&self, u: usize, v: usize) -> Option<Vector3<f32>> {
        if u >= self.width {
            return None;
        }
        self.points_in_camera.get(v * self.width + u).copied().filter(|p| p.z.is_finite())
    }

    /// Number of valid points.
    pub fn valid_count(&self) -> usize {
        self.points_in_camera.iter().filter(|p| p.z.is_finite()).count()
    }
}

/// J step 2: converts a metric depth image to an organized cloud in the camera frame.
pub fn organized_cloud(depth: &DepthImage, intrinsics: &Intrinsics) -> Result<OrganizedCloud, AcquireError> {
    check_size(depth, intrinsics)?;
    let (inv_fx, inv_fy) = ((1.0 / intrinsics.fx) as f32, (1.0 / intrinsics.fy) as f32);
    let (cx, cy) = (intrinsics.cx as f32, intrinsics.cy as f32);
    let mut points_in_camera = vec![Vector3::repeat(f32::NAN); depth.width * depth.height];
    // Rows in parallel.
    points_in_camera.par_chunks_mut(depth.width).zip(depth.depth_m.par_chunks(depth.width)).enumerate().for_each(|(v, (out, row))| {
        let y_per_z = (v as f32 - cy) * inv_fy;
        for (u, (p, &z)) in out.iter_mut().zip(row).enumerate() {
            if z.is_finite() {
                *p = Vector3::new((u as f32 - cx) * inv_fx * z, y_per_z * z, z);
            }
        }
    });
    Ok(OrganizedCloud { width: depth.width, height: depth.height, points_in_camera })
}

/// Checks that a depth image matches its intrinsics.
pub fn check_size(depth: &DepthImage, intrinsics: &Intrinsics) -> Result<(), AcquireError> {
    if depth.width != intrinsics.width || depth.height != intrinsics.height {
        return Err(AcquireError::SizeMismatch {
            image_w: depth.width,
            image_h: depth.height,
            intr_w: intrinsics.width,
            intr_h: intrinsics.height,
        });
    }
    Ok(())
}

/// Normalises a gravity vector given in the camera frame (pointing down).
pub fn gravity_from_vector(gravity_in_camera: Vector3<f64>) -> Result<Unit<Vector3<f64>>, AcquireError> {
    let norm = gravity_in_camera.norm();
    if !(norm.is_finite() && norm > 1e-9) {
        return Err(AcquireError::BadGravity(gravity_in_camera.into()));
    }
    Ok(Unit::new_unchecked(gravity_in_camera / norm))
}

/// J step 2 from an accelerometer: at rest it measures the specific force, i.e. *up*; gravity
/// (down) in the camera frame is `−camera_from_imu · a / |a|`.
pub fn gravity_from_accelerometer(
    acceleration_in_imu: &Vector3<f64>,
    camera_from_imu: &Rotation3<f64>,
) -> Result<Unit<Vector3<f64>>, AcquireError> {
    gravity_from_vector(-(camera_from_imu * acceleration_in_imu))
}

/// J step 2 from an absolute IMU orientation `world_from_imu` (world z up, REP-103): gravity in the
/// world is −ẑ, so `ĝ_camera = camera_from_imu · imu_from_world · (0, 0, −1)`.
pub fn gravity_from_orientation(world_from_imu: &UnitQuaternion<f64>, camera_from_imu: &Rotation3<f64>) -> Unit<Vector3<f64>> {
    let down_in_imu = world_from_imu.inverse() * Vector3::new(0.0, 0.0, -1.0);
    Unit::new_normalize(camera_from_imu * down_in_imu)
}

/// Gravity-aligned `map_from_camera` with its origin at the camera: map z up (−ĝ), map x the camera's
/// forward direction projected on the horizontal plane (J 4.5/5.2: `x̂ × ĝ`), map y left.
/// Fails only when the camera looks straight along gravity, where "forward" is undefined; then the
/// camera's −y axis (image up) projected on the horizontal plane is used instead.
pub fn map_from_camera_from_gravity(gravity_in_camera: &Unit<Vector3<f64>>) -> Isometry3<f64> {
    let up = -gravity_in_camera.into_inner();
    let mut forward = Vector3::x().cross(gravity_in_camera);
    if forward.norm() < 1e-6 {
        forward = -Vector3::y() - up * (-Vector3::y()).dot(&up);
    }
    let forward = forward.normalize();
    let left = up.cross(&forward);
    // Columns of camera_from_map are the map axes expressed in the camera frame.
    let camera_from_map = Rotation3::from_matrix_unchecked(Matrix3::from_columns(&[forward, left, up]));
    Isometry3::from_parts(Translation3::identity(), UnitQuaternion::from_rotation_matrix(&camera_from_map.inverse()))
}

/// Fallback gravity: the normal of the dominant plane of the cloud (RANSAC on a subsample, then a
/// least-squares refit on the inliers), oriented away from the camera (the camera sees the top of
/// the floor, so down points from the camera towards the plane). Deterministic for a given `seed`.
pub fn gravity_from_dominant_plane(cloud: &OrganizedCloud, inlier_distance_m: f64, seed: u64) -> Result<Unit<Vector3<f64>>, AcquireError> {
    let valid: Vec<Vector3<f64>> = cloud.points_in_camera.iter().step_by(7).filter(|p| p.z.is_finite()).map(|p| p.cast::<f64>()).collect();
    if valid.len() < 50 {
        return Err(AcquireError::NoPlane(format!("only {} valid sample points", valid.len())));
    }
    let mut rng = rand::rngs::StdRng::seed_from_u64(seed);
    let mut best: Option<(usize, Vector3<f64>, f64)> = None;
    for _ in 0..200 {
        let [a, b, c] = [0; 3].map(|_| valid[rng.random_range(0..valid.len())]);
        let normal = (b - a).cross(&(c - a));
        if normal.norm() < 1e-9 {
            continue;
        }
        let normal = normal.normalize();
        let offset = normal.dot(&a);
        let inliers = valid.iter().filter(|p| (normal.dot(p) - offset).abs() < inlier_distance_m).count();
        if best.is_none_or(|(count, _, _)| inliers > count) {
            best = Some((inliers, normal, offset));
        }
    }
    let (count, normal, offset) = best.ok_or_else(|| AcquireError::NoPlane("degenerate samples".into()))?;
    if count < valid.len() / 10 {
        return Err(AcquireError::NoPlane(format!("best plane holds {count} of {} points", valid.len())));
    }
    // Least-squares refit: smallest eigenvector of the inliers' covariance.
    let inliers: Vec<_> = valid.iter().filter(|p| (normal.dot(p) - offset).abs() < inlier_distance_m).collect();
    let mean = inliers.iter().copied().sum::<Vector3<f64>>() / inliers.len() as f64;
    let covariance = inliers.iter().fold(Matrix3::zeros(), |acc, p| acc + (*p - mean) * (*p - mean).transpose());
    let eigen = covariance.symmetric_eigen();
    let smallest = eigen.eigenvalues.imin();
    let mut normal: Vector3<f64> = eigen.eigenvectors.column(smallest).into_owned();
    if normal.dot(&mean) < 0.0 {
        normal = -normal;
    }
    gravity_from_vector(normal)
}

#[cfg(test)]
mod tests {
    use super::*;
    use patchwalk_fusion::dataset::{test_data_dir, Dataset};

    #[test]
    fn organized_cloud_keeps_layout_and_nans() {
        let intrinsics = Intrinsics::new(4, 3, 2.0, 2.0, 1.5, 1.0).unwrap();
        let mut depth = vec![1.0f32; 12];
        depth[5] = f32::NAN;
        let image = DepthImage::new(4, 3, depth).unwrap();
        let cloud = organized_cloud(&image, &intrinsics).unwrap();
        assert_eq!(cloud.points_in_camera.len(), 12);
        assert!(cloud.get(1, 1).is_none());
        let p = cloud.get(3, 2).unwrap();
        let expected = intrinsics.back_project(3.0, 2.0, 1.0);
        assert!((p.cast::<f64>() - expected).norm() < 1e-6);
        assert_eq!(cloud.valid_count(), 11);
        let wrong = Intrinsics::new(5, 3, 2.0, 2.0, 1.5, 1.0).unwrap();
        assert!(matches!(organized_cloud(&image, &wrong), Err(AcquireError::SizeMismatch { .. })));
    }

    #[test]
    fn real_tum_frame_converts_with_matching_valid_count() {
        let dataset = Dataset::open(&test_data_dir().join("tum_fr1_xyz")).unwrap();
        let depth = dataset.load_depth(0).unwrap();
        let cloud = organized_cloud(&depth, &dataset.intrinsics).unwrap();
        assert_eq!((cloud.width, cloud.height), (640, 480));
        assert_eq!(cloud.valid_count(), depth.valid_count());
        assert!(cloud.valid_count() > 100_000);
    }

    #[test]
    fn accelerometer_and_orientation_give_down() {
        let identity = Rotation3::identity();
        // IMU at rest with z up reads +9.81 on z: gravity is −z.
        let g = gravity_from_accelerometer(&Vector3::new(0.0, 0.0, 9.81), &identity).unwrap();
        assert!((g.into_inner() - Vector3::new(0.0, 0.0, -1.0)).norm() < 1e-12);
        // Camera y axis is the IMU's −z axis (optical y down): gravity is +y in the camera.
        let camera_from_imu = Rotation3::from_matrix_unchecked(Matrix3::new(1.0, 0.0, 0.0, 0.0, 0.0, -1.0, 0.0, 1.0, 0.0));
        let g = gravity_from_accelerometer(&Vector3::new(0.0, 0.0, 9.81), &camera_from_imu).unwrap();
        assert!((g.into_inner() - Vector3::y()).norm() < 1e-12);
        let g = gravity_from_orientation(&UnitQuaternion::identity(), &camera_from_imu);
        assert!((g.into_inner() - Vector3::y()).norm() < 1e-12);
        assert!(gravity_from_accelerometer(&Vector3::zeros(), &identity).is_err());
    }

    #[test]
    fn config_rejects_non_rotations() {
        let mut config = AcquireConfig::default();
        assert!(config.camera_from_imu().is_ok());
        config.camera_from_imu[0][0] = 2.0;
        assert!(matches!(config.camera_from_imu(), Err(AcquireError::BadRotation { .. })));
    }

    #[test]
    fn map_frame_is_gravity_aligned_and_forward() {
        // Camera pitched down by 30°: gravity in camera frame.
        let pitch = 30f64.to_radians();
        let g = Unit::new_normalize(Vector3::new(0.0, pitch.cos(), pitch.sin()));
        let map_from_camera = map_from_camera_from_gravity(&g);
        let g_in_map = map_from_camera.rotation * g.into_inner();
        assert!((g_in_map - Vector3::new(0.0, 0.0, -1.0)).norm() < 1e-12);
        // The optical axis points forward (+x) and down in the map.
        let forward = map_from_camera.rotation * Vector3::z();
        assert!(forward.x > 0.8 && forward.y.abs() < 1e-12 && forward.z < 0.0);
        // Camera x (right) is map −y.
        assert!((map_from_camera.rotation * Vector3::x() - Vector3::new(0.0, -1.0, 0.0)).norm() < 1e-12);
    }

    #[test]
    fn dominant_plane_of_tum_desk_is_close_to_documented_up() {
        // tests/data/README.md: world-up in the optical frame is about (0.01, −0.79, −0.62).
        let dataset = Dataset::open(&test_data_dir().join("tum_fr1_xyz")).unwrap();
        let cloud = organized_cloud(&dataset.load_depth(0).unwrap(), &dataset.intrinsics).unwrap();
        let g = gravity_from_dominant_plane(&cloud, 0.02, 7).unwrap();
        let documented_down = Vector3::new(-0.01, 0.79, 0.62).normalize();
        let angle = g.dot(&documented_down).clamp(-1.0, 1.0).acos().to_degrees();
        assert!(angle < 10.0, "angle to documented gravity {angle}°");
    }
}

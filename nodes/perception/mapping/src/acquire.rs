//! Stage i (J 4.1, steps 1–2): depth image + intrinsics -> organized point cloud in the camera
//! frame (NaN where invalid); IMU orientation or accelerometer -> unit gravity in the camera frame;
//! a gravity-aligned `map_from_camera` for single frames.
//!
//! Gravity sources, in the order a caller usually prefers them:
//! 1. an explicit gravity vector in the camera frame (e.g. `--gravity` of `patch_mapper map`),
//! 2. an IMU orientation quaternion or an accelerometer reading, through `camera_from_imu`
//!    (J 2.2: the rotation found by Procrustes calibration, see `calibration.rs`),
//! 3. the fallback: the normal of a dominant plane of the frame ([`gravity_from_ground_plane`]): of
//!    up to four RANSAC planes, the largest whose normal agrees with the camera's nominal down
//!    ([`PlanePrior`]); a frame with no such plane (only walls) is refused with
//!    [`AcquireError::NoGroundPlane`] instead of taking a wall for the floor. J 2.2 makes the same
//!    horizontal-floor assumption for calibration.

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
    #[error(
        "no dominant plane is within {tolerance_deg}° of the nominal down {down:.2?} (planes found: {}); the view holds no floor: set mapper.acquire.plane_prior (nominal_pitch_deg, tolerance_deg) or give gravity (--gravity, an IMU)",
        if found.is_empty() { "none".to_string() } else { found.join("; ") }
    )]
    NoGroundPlane { down: [f64; 3], tolerance_deg: f64, found: Vec<String> },
    #[error("invalid plane prior: {0}")]
    BadPrior(String),
}

/// Configuration of stage i.
#[derive(Debug, Clone, PartialEq, serde::Serialize, serde::Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct AcquireConfig {
    /// Row-major rotation `camera_from_imu` (J 2.2: from Procrustes calibration). Identity when
    /// the IMU axes are the optical axes.
    pub camera_from_imu: [[f64; 3]; 3],
    /// Half window (s) of the accelerometer samples around a frame timestamp whose per-axis median
    /// gives the frame's gravity.
    pub accel_half_window_s: f64,
    /// Plane gravity (no IMU): which of the dominant planes may be the ground.
    pub plane_prior: PlanePrior,
}

impl Default for AcquireConfig {
    fn default() -> Self {
        Self {
            camera_from_imu: [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]],
            accel_half_window_s: 0.05,
            plane_prior: PlanePrior::default(),
        }
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

/// The prior on "down" that plane gravity checks its planes against: the camera's nominal down in
/// the optical frame is +y (image down) rotated about the optical x axis by the nominal pitch,
/// `d = (0, cos θ, sin θ)` (θ = 0: looking level, 90°: looking straight down). A plane is taken as
/// the ground only if its downward normal lies within `tolerance_deg` of `d`, so a wall (normal
/// horizontal) or a desk front cannot become "down".
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize, serde::Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct PlanePrior {
    /// θ: nominal pitch of the optical axis below the horizontal (degrees).
    pub nominal_pitch_deg: f64,
    /// Largest angle between a plane's downward normal and the nominal down (degrees).
    pub tolerance_deg: f64,
}

impl Default for PlanePrior {
    /// 35° ± 40°: from a level camera to one looking 75° down (hand-held rigs, robot heads, the
    /// TUM and Open3D recordings); a wall seen by such a camera is at least 50° off.
    fn default() -> Self {
        Self { nominal_pitch_deg: 35.0, tolerance_deg: 40.0 }
    }
}

impl PlanePrior {
    /// The nominal down `(0, cos θ, sin θ)` in the optical frame.
    pub fn nominal_down(&self) -> Unit<Vector3<f64>> {
        let pitch = self.nominal_pitch_deg.to_radians();
        Unit::new_normalize(Vector3::new(0.0, pitch.cos(), pitch.sin()))
    }

    /// Checks the prior's numbers.
    pub fn validate(&self) -> Result<(), AcquireError> {
        if !(self.nominal_pitch_deg.is_finite() && (-90.0..=90.0).contains(&self.nominal_pitch_deg)) {
            return Err(AcquireError::BadPrior(format!("nominal_pitch_deg {} is not in [-90, 90]", self.nominal_pitch_deg)));
        }
        if !(self.tolerance_deg.is_finite() && self.tolerance_deg > 0.0 && self.tolerance_deg <= 180.0) {
            return Err(AcquireError::BadPrior(format!("tolerance_deg {} is not in (0, 180]", self.tolerance_deg)));
        }
        Ok(())
    }
}

/// One plane found by [`dominant_planes`], in the camera frame.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Plane {
    /// Unit normal pointing away from the camera (for the ground: gravity, down).
    pub normal_away: Unit<Vector3<f64>>,
    /// Distance from the camera centre to the plane (m): the camera height for the ground.
    pub distance_m: f64,
    /// Share of the sampled valid points that are inliers of this plane.
    pub share: f64,
}

impl Plane {
    /// Angle between the plane's away-normal and `down` (degrees).
    pub fn angle_to_deg(&self, down: &Unit<Vector3<f64>>) -> f64 {
        self.normal_away.dot(down).clamp(-1.0, 1.0).acos().to_degrees()
    }
}

/// Smallest share of the sampled points a plane needs to count as dominant.
const MIN_PLANE_SHARE: f64 = 0.05;

/// Up to `max_planes` dominant planes of the cloud, largest first: sequential RANSAC on a subsample
/// (each plane's inliers are removed before the next is searched), each plane refitted by least
/// squares on its inliers. Planes holding less than 5 % of the sampled points are not reported.
/// Deterministic for a given `seed`.
pub fn dominant_planes(cloud: &OrganizedCloud, inlier_distance_m: f64, max_planes: usize, seed: u64) -> Result<Vec<Plane>, AcquireError> {
    let mut remaining: Vec<Vector3<f64>> =
        cloud.points_in_camera.iter().step_by(7).filter(|p| p.z.is_finite()).map(|p| p.cast::<f64>()).collect();
    let sampled = remaining.len();
    if sampled < 50 {
        return Err(AcquireError::NoPlane(format!("only {sampled} valid sample points")));
    }
    let mut rng = rand::rngs::StdRng::seed_from_u64(seed);
    let mut planes = Vec::new();
    while planes.len() < max_planes && remaining.len() >= 50 {
        let mut best: Option<(usize, Vector3<f64>, f64)> = None;
        for _ in 0..200 {
            let [a, b, c] = [0; 3].map(|_| remaining[rng.random_range(0..remaining.len())]);
            let Some(normal) = (b - a).cross(&(c - a)).try_normalize(1e-9) else { continue };
            let offset = normal.dot(&a);
            let inliers = remaining.par_iter().filter(|p| (normal.dot(p) - offset).abs() < inlier_distance_m).count();
            if best.is_none_or(|(count, _, _)| inliers > count) {
                best = Some((inliers, normal, offset));
            }
        }
        let Some((count, normal, offset)) = best else { break };
        if (count as f64) < MIN_PLANE_SHARE * sampled as f64 {
            break;
        }
        let (inliers, rest): (Vec<_>, Vec<_>) = remaining.iter().partition(|p| (normal.dot(p) - offset).abs() < inlier_distance_m);
        remaining = rest;
        // Least-squares refit: smallest eigenvector of the inliers' covariance.
        let mean = inliers.iter().sum::<Vector3<f64>>() / inliers.len() as f64;
        let covariance = inliers.iter().fold(Matrix3::zeros(), |acc, p| acc + (p - mean) * (p - mean).transpose());
        let eigen = covariance.symmetric_eigen();
        let mut normal: Vector3<f64> = eigen.eigenvectors.column(eigen.eigenvalues.imin()).into_owned();
        if normal.dot(&mean) < 0.0 {
            normal = -normal;
        }
        planes.push(Plane {
            normal_away: Unit::new_normalize(normal),
            distance_m: normal.dot(&mean),
            share: inliers.len() as f64 / sampled as f64,
        });
    }
    if planes.is_empty() {
        return Err(AcquireError::NoPlane(format!("no plane holds {:.0} % of the {sampled} sampled points", 100.0 * MIN_PLANE_SHARE)));
    }
    Ok(planes)
}

/// The ground among the dominant planes: the largest plane whose away-normal lies within
/// `tolerance_deg` of `down` (the nominal down of a [`PlanePrior`], or a measured gravity when only
/// the camera height is wanted). Refuses a frame where no plane qualifies, listing the planes found.
pub fn ground_plane(
    cloud: &OrganizedCloud,
    inlier_distance_m: f64,
    down: &Unit<Vector3<f64>>,
    tolerance_deg: f64,
    seed: u64,
) -> Result<Plane, AcquireError> {
    let planes = dominant_planes(cloud, inlier_distance_m, 4, seed)?;
    if let Some(ground) = planes.iter().find(|p| p.angle_to_deg(down) <= tolerance_deg) {
        return Ok(*ground);
    }
    let found = planes.iter().map(|p| format!("{:.0}° off, {:.0} % of the points", p.angle_to_deg(down), 100.0 * p.share)).collect();
    Err(AcquireError::NoGroundPlane { down: (*down).into_inner().into(), tolerance_deg, found })
}

/// Plane gravity: the downward normal of the ground plane chosen by [`ground_plane`] against the
/// prior's nominal down (the camera sees the top of the floor, so down points from the camera towards
/// the plane).
pub fn gravity_from_ground_plane(
    cloud: &OrganizedCloud,
    inlier_distance_m: f64,
    prior: &PlanePrior,
    seed: u64,
) -> Result<Unit<Vector3<f64>>, AcquireError> {
    prior.validate()?;
    Ok(ground_plane(cloud, inlier_distance_m, &prior.nominal_down(), prior.tolerance_deg, seed)?.normal_away)
}

/// [`gravity_from_ground_plane`] with the default [`PlanePrior`].
pub fn gravity_from_dominant_plane(cloud: &OrganizedCloud, inlier_distance_m: f64, seed: u64) -> Result<Unit<Vector3<f64>>, AcquireError> {
    gravity_from_ground_plane(cloud, inlier_distance_m, &PlanePrior::default(), seed)
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

    /// A camera 0.4 m above a floor pitched 10° down, facing a wall 0.9 m ahead that fills most of the
    /// view (the wall is the largest plane).
    fn wall_and_floor() -> (OrganizedCloud, Unit<Vector3<f64>>) {
        use crate::saliency::tests::{render, small_camera};
        let intrinsics = small_camera();
        let pitch = 10f64.to_radians();
        let down = Unit::new_normalize(Vector3::new(0.0, pitch.cos(), pitch.sin()));
        let forward = Vector3::new(0.0, -pitch.sin(), pitch.cos());
        let depth = render(&intrinsics, |p| (0.4 - down.dot(p)).min(0.9 - forward.dot(p)));
        (organized_cloud(&depth, &intrinsics).unwrap(), down)
    }

    #[test]
    fn plane_gravity_takes_the_floor_not_the_larger_wall() {
        let (cloud, down) = wall_and_floor();
        let planes = dominant_planes(&cloud, 0.02, 4, 3).unwrap();
        assert!(planes.len() >= 2, "{planes:?}");
        // The wall is the dominant plane; the prior still picks the floor.
        assert!(planes[0].angle_to_deg(&down) > 80.0, "{planes:?}");
        let g = gravity_from_dominant_plane(&cloud, 0.02, 3).unwrap();
        assert!(g.dot(&down) > 1f64.to_radians().cos(), "{g:?}");
        let ground = ground_plane(&cloud, 0.02, &down, 10.0, 3).unwrap();
        assert!((ground.distance_m - 0.4).abs() < 0.01, "{ground:?}");
    }

    #[test]
    fn a_frame_of_walls_only_is_refused_with_the_planes_found() {
        use crate::saliency::tests::{render, small_camera};
        let intrinsics = small_camera();
        // A level camera facing a wall 1.5 m ahead: no floor in view.
        let cloud = organized_cloud(&render(&intrinsics, |p| 1.5 - p.z), &intrinsics).unwrap();
        let err = gravity_from_dominant_plane(&cloud, 0.02, 1).unwrap_err();
        let AcquireError::NoGroundPlane { found, tolerance_deg, .. } = &err else { panic!("{err:?}") };
        assert_eq!(*tolerance_deg, 40.0);
        assert_eq!(found.len(), 1, "{found:?}");
        assert!(err.to_string().contains("plane_prior") && err.to_string().contains("55° off"), "{err}");
        // A prior that expects the camera to look straight down takes the wall for the ground.
        let level = PlanePrior { nominal_pitch_deg: 90.0, tolerance_deg: 10.0 };
        assert!(gravity_from_ground_plane(&cloud, 0.02, &level, 1).is_ok());
        assert!(matches!(PlanePrior { nominal_pitch_deg: 120.0, ..level }.validate(), Err(AcquireError::BadPrior(_))));
    }

    #[test]
    fn real_frames_get_a_ground_plane_consistent_with_the_prior() {
        let data = test_data_dir();
        for (name, frame) in
            [("tum_fr1_xyz", 0), ("tum_fr1_xyz", 36), ("open3d_rgbd", 0), ("open3d_rgbd", 4), ("cape_tunnel/depth_0.png", 0)]
        {
            let dataset = Dataset::open(&data.join(name)).unwrap();
            let cloud = organized_cloud(&dataset.load_depth(frame).unwrap(), &dataset.intrinsics).unwrap();
            let prior = PlanePrior::default();
            let g = gravity_from_ground_plane(&cloud, 0.02, &prior, 7).unwrap_or_else(|e| panic!("{name} {frame}: {e}"));
            let angle = g.dot(&prior.nominal_down()).acos().to_degrees();
            assert!(angle <= prior.tolerance_deg, "{name} {frame}: {angle}°");
        }
    }
}

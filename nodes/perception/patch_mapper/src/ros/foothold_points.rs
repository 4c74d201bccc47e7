//! Predicted footholds as points in the fixed frame: each predicted image position (CNN III-D: the
//! region's (x, y) mapped back to the image) is lifted onto the depth under it and moved into the
//! fixed frame with the tracked camera pose; its orientation is the local surface normal, the
//! smallest principal axis of the depth points within a foot radius (gravity-up when too few points
//! lie there).

use nalgebra::{Isometry3, Matrix3, Point3, SymmetricEigen, Vector3};
use patchwalk_fusion::camera::{DepthImage, Intrinsics};

/// One foothold in the fixed frame (z up).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ScoredHold {
    pub position: Vector3<f64>,
    /// Unit normal pointing up (gravity-up when the surface gave none).
    pub normal: Vector3<f64>,
    /// Whether `normal` came from the surface (else it is gravity-up).
    pub from_surface: bool,
    /// The predictor's probability p in [0, 1].
    pub score: f64,
}

/// Fewest depth points in the foot disc for a surface normal.
const MIN_NORMAL_POINTS: usize = 8;
/// At most this many samples per side of the pixel window the normal is estimated from.
const NORMAL_SAMPLES_PER_SIDE: usize = 15;
/// Half side (pixels) of the window searched for depth when the predicted pixel has none.
const DEPTH_SEARCH_PX: usize = 3;

/// Lifts predicted footholds `(u, v, p)` (image pixels) into the fixed frame. Predictions without
/// depth near their pixel are left out; `foot_radius_m` sizes the disc the normal is fitted to.
pub fn lift(
    predictions: &[(f64, f64, f32)],
    depth: &DepthImage,
    intrinsics: &Intrinsics,
    fixed_from_camera: &Isometry3<f64>,
    foot_radius_m: f64,
) -> Vec<ScoredHold> {
    predictions
        .iter()
        .filter(|(u, v, p)| u.is_finite() && v.is_finite() && p.is_finite())
        .filter_map(|&(u, v, p)| {
            let z = depth_near(depth, u, v)?;
            let point_in_camera = intrinsics.back_project(u, v, f64::from(z));
            let position = (fixed_from_camera * Point3::from(point_in_camera)).coords;
            let normal_in_camera = surface_normal(depth, intrinsics, u, v, &point_in_camera, foot_radius_m);
            let (normal, from_surface) = match normal_in_camera {
                Some(n) => {
                    let n = fixed_from_camera.rotation * n;
                    (if n.z < 0.0 { -n } else { n }, true)
                }
                None => (Vector3::z(), false),
            };
            Some(ScoredHold { position, normal, from_surface, score: f64::from(p).clamp(0.0, 1.0) })
        })
        .collect()
}

/// The depth at the pixel, else the median of the valid depths within [`DEPTH_SEARCH_PX`].
fn depth_near(depth: &DepthImage, u: f64, v: f64) -> Option<f32> {
    if u < -0.5 || v < -0.5 {
        return None;
    }
    let (u0, v0) = (u.round() as usize, v.round() as usize);
    if u0 >= depth.width || v0 >= depth.height {
        return None;
    }
    if let Some(z) = depth.get(u0, v0).filter(|z| *z > 0.0) {
        return Some(z);
    }
    let mut near: Vec<f32> = Vec::new();
    for pv in v0.saturating_sub(DEPTH_SEARCH_PX)..=(v0 + DEPTH_SEARCH_PX).min(depth.height - 1) {
        for pu in u0.saturating_sub(DEPTH_SEARCH_PX)..=(u0 + DEPTH_SEARCH_PX).min(depth.width - 1) {
            near.extend(depth.get(pu, pv).filter(|z| *z > 0.0));
        }
    }
    if near.is_empty() {
        return None;
    }
    near.sort_by(f32::total_cmp);
    near.get(near.len() / 2).copied()
}

/// The unit normal (camera frame, facing the camera) of the depth points within `radius_m` of
/// `centre`, from the pixel window the disc covers: the eigenvector of the smallest eigenvalue of
/// their scatter matrix. `None` with fewer than [`MIN_NORMAL_POINTS`] points.
fn surface_normal(
    depth: &DepthImage,
    intrinsics: &Intrinsics,
    u: f64,
    v: f64,
    centre: &Vector3<f64>,
    radius_m: f64,
) -> Option<Vector3<f64>> {
    if !(centre.z > 0.0 && radius_m > 0.0) {
        return None;
    }
    let half = (intrinsics.fx.max(intrinsics.fy) * radius_m / centre.z).ceil().max(1.0) as usize;
    let step = (2 * half / NORMAL_SAMPLES_PER_SIDE).max(1);
    let (u0, v0) = (u.round() as usize, v.round() as usize);
    let mut points = Vec::new();
    for pv in (v0.saturating_sub(half)..=(v0 + half).min(depth.height.saturating_sub(1))).step_by(step) {
        for pu in (u0.saturating_sub(half)..=(u0 + half).min(depth.width.saturating_sub(1))).step_by(step) {
            let Some(z) = depth.get(pu, pv).filter(|z| *z > 0.0) else { continue };
            let p = intrinsics.back_project(pu as f64, pv as f64, f64::from(z));
            if (p - centre).norm() <= radius_m {
                points.push(p);
            }
        }
    }
    if points.len() < MIN_NORMAL_POINTS {
        return None;
    }
    let mean = points.iter().sum::<Vector3<f64>>() / points.len() as f64;
    let scatter = points.iter().fold(Matrix3::zeros(), |s, p| {
        let d = p - mean;
        s + d * d.transpose()
    });
    let eigen = SymmetricEigen::new(scatter);
    let (smallest, _) = eigen.eigenvalues.iter().enumerate().min_by(|a, b| a.1.total_cmp(b.1))?;
    let normal = eigen.eigenvectors.column(smallest).into_owned();
    let normal = normal.try_normalize(1e-12)?;
    // Facing the camera (the camera sees the surface from its side).
    Some(if normal.dot(&mean) > 0.0 { -normal } else { normal })
}

#[cfg(test)]
mod tests {
    use super::*;
    use nalgebra::{Translation3, UnitQuaternion};

    /// A camera 0.5 m above a floor, looking down 49°: the depth image of the floor, and the
    /// camera's pose in a z-up fixed frame with the floor at z = 0.
    fn floor_view() -> (DepthImage, Intrinsics, Isometry3<f64>) {
        let k = Intrinsics::new(160, 120, 131.0, 131.0, 79.5, 59.5).unwrap();
        let pitch = 49f64.to_radians();
        // Optical axes in the fixed frame: x right = −y, z forward = (cos, 0, −sin), y down = z × x.
        let forward = Vector3::new(pitch.cos(), 0.0, -pitch.sin());
        let right = Vector3::new(0.0, -1.0, 0.0);
        let down = forward.cross(&right);
        let rotation = nalgebra::Rotation3::from_matrix_unchecked(Matrix3::from_columns(&[right, down, forward]));
        let fixed_from_camera = Isometry3::from_parts(Translation3::new(0.0, 0.0, 0.5), UnitQuaternion::from_rotation_matrix(&rotation));
        let up_in_camera = fixed_from_camera.inverse_transform_vector(&Vector3::z());
        let camera_height = 0.5;
        let depth: Vec<f32> = (0..k.width * k.height)
            .map(|i| {
                let ray = k.back_project((i % k.width) as f64, (i / k.width) as f64, 1.0);
                let along = -ray.dot(&up_in_camera);
                if along > 1e-6 {
                    (camera_height / along) as f32
                } else {
                    f32::NAN
                }
            })
            .collect();
        (DepthImage::new(k.width, k.height, depth).unwrap(), k, fixed_from_camera)
    }

    #[test]
    fn predictions_land_on_the_floor_with_an_upright_normal() {
        let (depth, k, fixed_from_camera) = floor_view();
        let predictions = [(80.0, 90.0, 0.9f32), (40.5, 100.2, 0.6), (80.0, 60.0, 0.7)];
        let holds = lift(&predictions, &depth, &k, &fixed_from_camera, 0.05);
        assert_eq!(holds.len(), 3);
        for hold in &holds {
            assert!(hold.position.z.abs() < 1e-3, "on the floor: {:?}", hold.position);
            assert!(hold.position.x > 0.0, "ahead of the camera");
            assert!(hold.from_surface && (hold.normal - Vector3::z()).norm() < 1e-3, "{:?}", hold.normal);
        }
        assert_eq!(holds[0].score, f64::from(0.9f32));
        // The pixel below the centre is nearer than the centre pixel.
        assert!(holds[0].position.x < holds[2].position.x);
    }

    #[test]
    fn predictions_without_depth_are_left_out_and_few_points_give_gravity_up() {
        let (mut depth, k, fixed_from_camera) = floor_view();
        // Off the image, NaN coordinates: nothing.
        let off = [(-5.0, 10.0, 0.9f32), (f64::NAN, 3.0, 0.9), (500.0, 10.0, 0.9)];
        assert!(lift(&off, &depth, &k, &fixed_from_camera, 0.05).is_empty());
        // A hole around one pixel bigger than the search window: no depth there.
        for v in 80..101 {
            for u in 60..101 {
                depth.depth_m[v * k.width + u] = f32::NAN;
            }
        }
        assert!(lift(&[(80.0, 90.0, 0.9)], &depth, &k, &fixed_from_camera, 0.05).is_empty());
        // Only a sliver of depth next to the hole: the position from the median nearby, gravity-up.
        let mut sliver = DepthImage::new(k.width, k.height, vec![f32::NAN; k.width * k.height]).unwrap();
        let (full, _, _) = floor_view();
        for u in 78..81 {
            sliver.depth_m[90 * k.width + u] = full.depth_m[90 * k.width + u];
        }
        let holds = lift(&[(80.0, 91.0, 0.5)], &sliver, &k, &fixed_from_camera, 0.05);
        assert_eq!(holds.len(), 1);
        assert!(!holds[0].from_surface && holds[0].normal == Vector3::z());
        assert!(holds[0].position.z.abs() < 0.02, "{:?}", holds[0].position);
    }
}

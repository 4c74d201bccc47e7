//! Point covariances evaluated on the fitted surface (beyond IROS, `FitConfig::covariances_on_surface`).
//!
//! A range sensor's noise depends on the true range of a point (J eq 2: σ_z ∝ z² for the
//! Murray–Little model), but a fit only has the measured one. Covariances evaluated at the measured
//! points weight the points measured too near more than those measured too far (weight ∝ z⁻⁴), which
//! pulls the fitted surface towards the sensor by about `4 σ_z² / z` — 0.06 mm at 1 m for the Kinect,
//! a fifth of the offset's standard deviation for 150 points, and a bias that fusing views from the
//! same side does not average out (it grows to ~0.9 σ after ten fused views). Evaluating Σ_i where
//! each measurement ray meets the fitted surface (the maximum-likelihood estimate of the true point
//! along the ray) and fitting once more removes it.

use nalgebra::{Matrix3, Vector3};

use crate::patch::Patch;
use crate::sensor::{ErrorModel, SensorError};

/// Whether a model's covariance changes along a ray (only then does evaluating it on the surface
/// change anything): the constant range model's does not.
pub fn depends_on_range(model: &ErrorModel) -> bool {
    !matches!(model, ErrorModel::Constant { .. })
}

/// Relative change of the range beyond which the ray's intersection with the fitted surface is not
/// taken as the point's true position (a ray grazing the surface, or meeting it again elsewhere):
/// the measured point is kept. Sensor noise is well below 1 % of the range.
const MAX_RANGE_CHANGE: f64 = 0.05;

/// Range along `ray` (unit, sensor frame) from `range` to the patch's unbounded surface, by Newton's
/// method on its implicit form (eq 37) restricted to the ray; `None` if it does not converge near
/// `range`.
fn range_on_surface(patch: &Patch, ray: &Vector3<f64>, range: f64) -> Option<f64> {
    let rot_t = patch.rotation_matrix().transpose();
    let k = patch.k3();
    // q_l(t) = t a − b: f(t) = (ta − b)ᵀ K (ta − b) − 2 (ta − b)_z.
    let a = rot_t * ray;
    let b = rot_t * patch.center;
    let mut t = range;
    for _ in 0..8 {
        let q = a * t - b;
        let f = patch.implicit_local(&q);
        let df = 2.0 * (k.x * q.x * a.x + k.y * q.y * a.y + k.z * q.z * a.z - a.z);
        if df == 0.0 || !df.is_finite() {
            return None;
        }
        let step = f / df;
        t -= step;
        if !t.is_finite() || (t - range).abs() > MAX_RANGE_CHANGE * range {
            return None;
        }
        if step.abs() <= 1e-12 * range {
            break;
        }
    }
    Some(t)
}

/// The points' covariances under `model`, each evaluated where its measurement ray (from the sensor
/// at the origin of the points' frame) meets the fitted patch's surface; at the measured point where
/// the ray does not meet the surface near it.
pub fn covariances_on_surface(
    patch: &Patch,
    points_in_sensor: &[Vector3<f64>],
    model: &ErrorModel,
) -> Result<Vec<Matrix3<f64>>, SensorError> {
    points_in_sensor
        .iter()
        .map(|q| {
            let range = q.norm();
            let on_surface = (range > 0.0).then(|| q / range).and_then(|ray| range_on_surface(patch, &ray, range).map(|t| ray * t));
            model.covariance(&on_surface.unwrap_or(*q))
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::patch::tests::disc_facing_the_camera;
    use crate::patch::{BoundaryType, SurfaceType};
    use nalgebra::Vector2;

    fn facing_sphere(kappa: f64, centre: Vector3<f64>) -> Patch {
        // Normal towards the sensor (−z): a rotation by π about x.
        Patch::new(
            SurfaceType::Sphere,
            BoundaryType::Circle,
            vec![0.05],
            Vector2::new(kappa, kappa),
            Vector3::new(std::f64::consts::PI, 0.0, 0.0),
            centre,
        )
        .unwrap()
    }

    #[test]
    fn a_ray_meets_a_facing_plane_at_its_depth() {
        let plane = disc_facing_the_camera();
        let ray = Vector3::new(0.1, -0.05, 1.0).normalize();
        let t = range_on_surface(&plane, &ray, 1.01).unwrap();
        assert!(((ray * t).z - 1.0).abs() < 1e-12, "{t}");
    }

    #[test]
    fn a_ray_meets_a_sphere_where_its_implicit_form_vanishes() {
        let sphere = facing_sphere(5.0, Vector3::new(0.02, 0.0, 0.9));
        let ray = Vector3::new(0.05, 0.01, 1.0).normalize();
        let t = range_on_surface(&sphere, &ray, 0.92).unwrap();
        let q_l = sphere.to_local(&(ray * t));
        assert!(sphere.implicit_local(&q_l).abs() < 1e-12);
        // A ray that misses the patch's neighbourhood keeps its measured point.
        let away = Vector3::new(1.0, 0.0, 0.2).normalize();
        assert!(range_on_surface(&sphere, &away, 0.9).is_none());
    }

    #[test]
    fn covariances_are_those_of_the_points_on_the_surface() {
        let plane = disc_facing_the_camera();
        let model = ErrorModel::default();
        let near = Vector3::new(0.02, 0.01, 0.995);
        let covs = covariances_on_surface(&plane, &[near], &model).unwrap();
        let expected = model.covariance(&(near * (1.0 / near.z))).unwrap();
        assert!((covs[0] - expected).norm() < 1e-15 * expected.norm().max(1.0), "{} vs {}", covs[0], expected);
        assert!((covs[0] - model.covariance(&near).unwrap()).norm() > 1e-3 * expected.norm());
        assert!(!depends_on_range(&ErrorModel::Constant { sigma_m: 0.001 }) && depends_on_range(&model));
    }
}

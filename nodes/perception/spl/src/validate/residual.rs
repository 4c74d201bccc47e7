//! Residual evaluation (J 3.3.1): the RMS Euclidean distance of the neighbourhood's points to the
//! bounded patch, J eq 15.

use crate::patch::{Patch, PatchQuery};
use nalgebra::Vector3;

/// Residual `ρ = RMS ‖q_i − p_i‖` with `p_i` the closest point on the bounded patch (J eq 15).
/// Infinite for an empty or non-finite neighbourhood.
pub fn residual(patch: &Patch, points: &[Vector3<f64>]) -> f64 {
    let query = PatchQuery::new(patch);
    let local: Vec<Vector3<f64>> = points.iter().map(|q| query.to_local(q)).collect();
    residual_local(&query, &local)
}

/// [`residual`] of points already in the patch frame.
pub(super) fn residual_local(query: &PatchQuery, local: &[Vector3<f64>]) -> f64 {
    if local.is_empty() {
        return f64::INFINITY;
    }
    let shape = query.shape();
    let sum: f64 = local.iter().map(|q| (shape.closest_point_local(q) - q).norm_squared()).sum();
    let rho = (sum / local.len() as f64).sqrt();
    if rho.is_finite() {
        rho
    } else {
        f64::INFINITY
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::validate::tests::disk;
    use crate::validate::{validate_patch, ValidateConfig};
    use rand::SeedableRng;

    #[test]
    fn step_edge_fails_residual() {
        let mut rng = rand::rngs::StdRng::seed_from_u64(2);
        let mut pts = disk(0.1).sample_points(&mut rng, 3000);
        for p in pts.iter_mut() {
            if p.x > 0.0 {
                p.z += 0.04;
            }
        }
        let flat = disk(0.1);
        let v = validate_patch(&flat, &pts, &ValidateConfig::default());
        assert!(!v.residual.passed);
        assert!(v.failures().iter().any(|f| f.starts_with("residual")));
        assert!((v.residual.value - 0.04 / 2f64.sqrt()).abs() < 0.003);
        assert!((residual(&flat, &pts) - v.residual.value).abs() < 1e-12);
    }

    #[test]
    fn empty_or_non_finite_points_have_an_infinite_residual() {
        assert_eq!(residual(&disk(0.1), &[]), f64::INFINITY);
        assert_eq!(residual(&disk(0.1), &[Vector3::new(f64::NAN, 0.0, 0.0)]), f64::INFINITY);
    }
}

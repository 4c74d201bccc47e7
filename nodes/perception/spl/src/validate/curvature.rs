//! Curvature evaluation (J 3.3.3): the principal curvatures of the fitted surface against
//! `[κ_min,t, κ_max,t]`.

use crate::patch::{Patch, SurfaceType};

/// `(min, max)` principal curvature of the patch (J 3.3.3).
pub fn principal_curvature_range(patch: &Patch) -> (f64, f64) {
    let k = patch.curvatures;
    match patch.surface {
        SurfaceType::CylindricParaboloid | SurfaceType::CircularCylinder => (k.y.min(0.0), k.y.max(0.0)),
        _ => (k.x.min(k.y), k.x.max(k.y)),
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::patch::BoundaryType;
    use crate::validate::{validate_patch, ValidateConfig};
    use nalgebra::{Vector2, Vector3};
    use rand::SeedableRng;

    #[test]
    fn too_curved_bump_fails_curvature() {
        let bump = Patch::new(
            SurfaceType::CircularParaboloid,
            BoundaryType::Circle,
            vec![0.05],
            Vector2::new(-25.0, -25.0),
            Vector3::zeros(),
            Vector3::zeros(),
        )
        .unwrap();
        let mut rng = rand::rngs::StdRng::seed_from_u64(4);
        let pts = bump.sample_points(&mut rng, 2000);
        let v = validate_patch(&bump, &pts, &ValidateConfig::default());
        assert!(!v.curvature_min.passed && v.curvature_max.passed);
        assert!(v.failures().iter().any(|f| f.contains("curvature -25.00")));
        assert_eq!(principal_curvature_range(&bump), (-25.0, -25.0));
    }
}

//! Tilt evaluation (a foothold test beyond J 3.3): the patch normal must lie within a cone about
//! gravity's up. J uses the angle between normal and `−ĝ` only as a seed saliency (DoNG, J step
//! 6.5, a human statistic of 35°); a foot placed on a fitted patch needs it as a hard limit, since
//! a wall or a steep flank can pass residual, coverage and curvature.
//!
//! The default, 20°, comes from the foot: the RPBP's soles are 3D-printed hard plastic, whose static
//! friction on dry wood or rock is about μ = 0.45 (0.3–0.5 in the usual tables for hard plastics on
//! wood and stone); a loaded foot starts to slide where `tan θ = μ`, θ = 24°. Stepping adds
//! tangential load (push-off, the swing leg's reaction), so only 80 % of μ is used:
//! `tan θ_max = 0.8 · 0.45 = 0.36`, θ_max = 20°.

use crate::patch::Patch;
use nalgebra::Vector3;

/// Default tilt limit (degrees): `atan(0.8 μ)` with μ = 0.45 (see the module doc).
pub const DEFAULT_TILT_MAX_DEG: f64 = 20.0;

/// Angle (degrees) between the patch normal at its centre and `up` (any length; the direction
/// opposite to gravity, in the patch's frame). The normal's sign is used as fitted: the fit turns it
/// towards the sensor, so a surface seen from below (an overhang's underside) tilts by more than
/// 90°. NaN when `up` is zero or not finite.
pub fn tilt_deg(patch: &Patch, up: &Vector3<f64>) -> f64 {
    let norm = up.norm();
    if !(norm.is_finite() && norm > 0.0) {
        return f64::NAN;
    }
    let cos = (patch.normal().dot(up) / norm).clamp(-1.0, 1.0);
    cos.acos().to_degrees()
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::patch::{BoundaryType, SurfaceType};
    use crate::validate::{validate_foothold, Foothold, ValidateConfig};
    use nalgebra::Vector2;
    use rand::SeedableRng;

    /// A plane disc of radius 5 cm tilted by `deg` about the x axis (up = +z).
    fn tilted(deg: f64) -> Patch {
        Patch::new(
            SurfaceType::Plane,
            BoundaryType::Circle,
            vec![0.05],
            Vector2::zeros(),
            Vector3::new(deg.to_radians(), 0.0, 0.0),
            Vector3::zeros(),
        )
        .unwrap()
    }

    #[test]
    fn tilt_is_the_angle_between_normal_and_up() {
        for deg in [0.0, 10.0, 20.0, 45.0, 89.0, 135.0] {
            assert!((tilt_deg(&tilted(deg), &Vector3::new(0.0, 0.0, 2.0)) - deg).abs() < 1e-9, "{deg}");
        }
        assert!(tilt_deg(&tilted(0.0), &Vector3::zeros()).is_nan());
        assert!(tilt_deg(&tilted(0.0), &Vector3::new(f64::NAN, 0.0, 1.0)).is_nan());
    }

    #[test]
    fn plane_at_the_limit_passes_one_degree_below_and_fails_one_degree_above() {
        let config = ValidateConfig::default();
        let up = Vector3::z();
        let mut rng = rand::rngs::StdRng::seed_from_u64(7);
        for (deg, pass) in [(config.tilt_max_deg - 1.0, true), (config.tilt_max_deg + 1.0, false)] {
            let patch = tilted(deg);
            let points = patch.sample_points(&mut rng, 2000);
            let v = validate_foothold(
                &patch,
                &points,
                &Foothold { up: Some(up), column: None, sampled: None, view: None, out_of_view: None },
                &config,
            );
            let tilt = v.tilt.unwrap();
            assert_eq!(tilt.passed, pass, "{deg}°: {v:?}");
            assert!((tilt.value - deg).abs() < 1e-9 && tilt.threshold == config.tilt_max_deg);
            // Every J test passes: only the tilt decides.
            assert!(v.residual.passed && v.coverage.passed && v.curvature_ok());
            assert_eq!(v.is_valid(), pass);
            if !pass {
                assert_eq!(v.failures(), vec![format!("tilt {:.1}° > {:.1}°", deg, config.tilt_max_deg)]);
            }
        }
    }

    #[test]
    fn a_wall_fails_tilt_and_an_unknown_gravity_skips_it() {
        let wall = tilted(88.0);
        let mut rng = rand::rngs::StdRng::seed_from_u64(8);
        let points = wall.sample_points(&mut rng, 2000);
        let config = ValidateConfig::default();
        let v = validate_foothold(
            &wall,
            &points,
            &Foothold { up: Some(Vector3::z()), column: None, sampled: None, view: None, out_of_view: None },
            &config,
        );
        assert!(!v.is_valid() && !v.tilt.unwrap().passed);
        // Without gravity there is no tilt test (J 3.3 as written judges the wall valid).
        let v =
            validate_foothold(&wall, &points, &Foothold { up: None, column: None, sampled: None, view: None, out_of_view: None }, &config);
        assert!(v.tilt.is_none() && v.is_valid(), "{v:?}");
        // A NaN gravity fails with the value named.
        let v = validate_foothold(
            &wall,
            &points,
            &Foothold { up: Some(Vector3::new(f64::NAN, 0.0, 0.0)), column: None, sampled: None, view: None, out_of_view: None },
            &config,
        );
        assert!(!v.is_valid() && v.failures().iter().any(|f| f.starts_with("tilt NaN")), "{:?}", v.failures());
    }
}

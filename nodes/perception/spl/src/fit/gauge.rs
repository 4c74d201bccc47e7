//! The gauge of each surface (IROS IV steps 6 and 9): the frame moved along the directions the
//! surface leaves free (centre and in-plane rotation of planes, the apex of spheres and cylinders
//! around their centre/axis, of cylindric paraboloids along the axis) to where the data moments put
//! it, with the sphere and cylinder heights of eq 22–23 and 27.

use super::boundary;
use super::wlm::SurfaceState;
use super::FitError;
use crate::geometry::{exp_map, rotation_from_normal};
use crate::patch::{BoundaryType, SurfaceType};
use nalgebra::{Matrix3, Vector3};

/// Height and gradient of a sphere (`s = uᵀu`) or cylinder (`s = u_y²`) of curvature κ (eq 23, 27).
fn round_height(kappa: f64, s: f64) -> Option<(f64, f64)> {
    let arg = 1.0 - kappa * kappa * s;
    if arg.is_nan() || arg <= 0.0 {
        return None;
    }
    let root = arg.sqrt();
    Some((kappa * s / (1.0 + root), kappa / root))
}

/// The point of the sphere `κ|q|² − 2z = 0` (eq 22, centre `(0, 0, 1/κ)`) on the ray from its
/// centre through `target`, and the unit normal there on the apex side (`+z` at the apex).
/// `None` for κ = 0 or a target at the centre.
fn round_point_towards(kappa: f64, target: &Vector3<f64>) -> Option<(Vector3<f64>, Vector3<f64>)> {
    if kappa == 0.0 || !kappa.is_finite() {
        return None;
    }
    let centre = Vector3::new(0.0, 0.0, 1.0 / kappa);
    let dir = (target - centre).try_normalize(f64::MIN_POSITIVE)?;
    Some((centre + dir / kappa.abs(), -dir * kappa.signum()))
}

/// Move the frame along the surface's free directions to where the data moments put it
/// (steps 6, 9; the apex of spheres and cylinders follows the data around the centre/axis).
///
/// Spheres and cylinders go to the surface point whose normal line passes through the data centroid
/// `mean_local` (local frame of `state`): the point where the centroid's own tangent-frame x/y are
/// zero, i.e. the fixed point of IROS step 6's "surface point above the centroid". A single step 6
/// projects along the normal at the starting apex instead, which lands `|z̄| κ Δ` off for a centroid
/// `z̄` below the surface and a start `Δ` from it (~1 mm for a κ = 10 m⁻¹ cap with the start from
/// 150 fit points and the moments over the whole neighbourhood).
pub(super) fn apply_gauge(
    surface: SurfaceType,
    boundary: BoundaryType,
    state: &SurfaceState,
    m: &boundary::Moments,
    mean_local: &Vector3<f64>,
    in_plane_angle: f64,
) -> Result<SurfaceState, FitError> {
    let (xm, ym) = (m[0], m[1]);
    let rot = state.rot;
    let z_world = rot.column(2).into_owned();
    let out = match surface {
        SurfaceType::Plane => {
            let c = state.c + rot * Vector3::new(xm, ym, 0.0);
            let rot = if boundary == BoundaryType::Circle {
                rotation_from_normal(&z_world)
            } else {
                rot * exp_map(&Vector3::new(0.0, 0.0, in_plane_angle))
            };
            SurfaceState { rot, c, ..*state }
        }
        SurfaceType::CylindricParaboloid => SurfaceState { c: state.c + rot * Vector3::new(xm, 0.0, 0.0), ..*state },
        SurfaceType::CircularParaboloid => SurfaceState { rot: rotation_from_normal(&z_world), ..*state },
        SurfaceType::Sphere => {
            // Centre of the sphere (eq 22) at local (0, 0, 1/κ); the apex on the ray from it
            // through the centroid, the normal along that ray towards the viewer side.
            let kappa = state.k3.x;
            let (c_l, n_l) = match round_point_towards(kappa, mean_local) {
                Some(found) => found,
                None => {
                    let (z, dz) =
                        round_height(kappa, xm * xm + ym * ym).ok_or(FitError::Degenerate("data centroid beyond the fitted sphere"))?;
                    (Vector3::new(xm, ym, z), Vector3::new(-xm * dz, -ym * dz, 1.0).normalize())
                }
            };
            SurfaceState { rot: rotation_from_normal(&(rot * n_l)), c: state.c + rot * c_l, ..*state }
        }
        SurfaceType::CircularCylinder => {
            // The same in the cross-section (local y/z); along the axis (x) the centroid's x.
            let kappa = state.k3.y;
            let (c_l, z_l) = match round_point_towards(kappa, &Vector3::new(0.0, mean_local.y, mean_local.z)) {
                Some((c_l, n_l)) => (Vector3::new(xm, c_l.y, c_l.z), n_l),
                None => {
                    let (z, dz) = round_height(kappa, ym * ym).ok_or(FitError::Degenerate("data centroid beyond the fitted cylinder"))?;
                    (Vector3::new(xm, ym, z), Vector3::new(0.0, -ym * dz, 1.0).normalize())
                }
            };
            let x_l = Vector3::x();
            let y_l = z_l.cross(&x_l);
            SurfaceState { rot: rot * Matrix3::from_columns(&[x_l, y_l, z_l]), c: state.c + rot * c_l, ..*state }
        }
        SurfaceType::EllipticParaboloid | SurfaceType::HyperbolicParaboloid => *state,
    };
    Ok(out)
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The gauge point of a sphere lies on it, on the line from its centre through the target, with
    /// the normal of the implicit form there (pointing to the apex side, +z at the apex).
    #[test]
    fn round_point_lies_on_the_normal_line_through_the_target() {
        for kappa in [10.0, -4.0, 0.5] {
            for target in [Vector3::new(0.0, 0.0, 0.3 * 0.5 / kappa), Vector3::new(0.02, -0.01, 0.01), Vector3::new(-0.03, 0.04, -0.005)] {
                let (c, n) = round_point_towards(kappa, &target).unwrap();
                assert!((kappa * c.norm_squared() - 2.0 * c.z).abs() < 1e-12, "κ {kappa}: {c} not on the sphere");
                // ∇f = 2(κ q − ẑ) is along the normal, opposite for κ > 0 (f grows away from the centre).
                let grad = (c * kappa - Vector3::z()).normalize();
                assert!(grad.cross(&n).norm() < 1e-9 && (n.norm() - 1.0).abs() < 1e-12);
                let centre = Vector3::new(0.0, 0.0, 1.0 / kappa);
                assert!((target - centre).cross(&(c - centre)).norm() < 1e-9 * (c - centre).norm().max(1.0));
            }
            let (apex, normal) = round_point_towards(kappa, &Vector3::new(0.0, 0.0, 0.1 / kappa)).unwrap();
            assert!(apex.norm() < 1e-12 && (normal - Vector3::z()).norm() < 1e-12);
        }
        assert!(round_point_towards(0.0, &Vector3::zeros()).is_none());
    }

    /// The moments' picture of the sphere's gauge (what Σ propagates the centroid's sampling noise
    /// through) moves the apex and its normal as the gauge itself does: a sideways centroid shift
    /// `x̄` at height `z̄` inside the surface moves the apex by `x̄ / (1 − κ z̄)` and tilts it by κ
    /// times that, not by `x̄` and `κ x̄` (20 % short for κ z̄ = 0.2, the variance 36 % short).
    #[test]
    fn the_moments_move_a_sphere_apex_as_the_gauge_does() {
        for (kappa, height) in [(10.0, 0.02), (-8.0, -0.02), (10.0, 0.0)] {
            let shift = 1e-5;
            let (apex, normal) = round_point_towards(kappa, &Vector3::new(shift, 0.0, height)).unwrap();
            let tilt = (-normal.x).atan2(normal.z) * kappa.signum();
            let m = boundary::Moments::from_column_slice(&[shift, 0.0, 1e-4, 1e-4, 0.0]);
            let map = boundary::MomentMap {
                surface: SurfaceType::Sphere,
                boundary: BoundaryType::Circle,
                kappa,
                lambda: 1.96,
                ln_term: 3.0,
                centroid_height: height,
            };
            let moved = boundary::from_moments(&map, &m);
            let follow = 1.0 / (1.0 - kappa * height);
            assert!((apex.x / shift - follow).abs() < 1e-3 * follow, "κ {kappa}: apex moved {} of the shift", apex.x / shift);
            assert!((moved.local[3] - apex.x).abs() < 1e-3 * apex.x.abs(), "κ {kappa}: {} vs {}", moved.local[3], apex.x);
            // The tilt about y, −κ x̄ f, as large as the gauge's normal turns.
            assert!((moved.local[1] + kappa * shift * follow).abs() < 1e-9);
            assert!((tilt.abs() - (kappa * shift * follow).abs()).abs() < 1e-3 * (kappa * shift * follow).abs(), "κ {kappa}: tilt {tilt}");
        }
    }
}

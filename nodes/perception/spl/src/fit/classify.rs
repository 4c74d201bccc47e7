//! Type discrimination (IROS IV step 3): the simplest curvature model (plane, circular, cylindric,
//! full) that the fitted curvatures `k̂` support under their own covariance, by significance tests in
//! place of IROS's fixed ε_k, and elliptic vs hyperbolic paraboloids by the curvature signs.

use super::boundary;
use crate::patch::SurfaceType;
use nalgebra::{Matrix2, Vector2, Vector3};

/// Outcome of the step-3 curvature discrimination.
#[derive(Clone, Copy, Debug, PartialEq)]
pub(super) enum Curvature {
    Plane,
    Circular,
    /// Cylindric; `true` if the zero curvature is on local y (axes must be swapped).
    Cylindric(bool),
    Full,
}

/// Step 3 with significance tests instead of a fixed ε_k: the simplest curvature model whose
/// linear constraint on `k̂` is not rejected at level α under the fit's own covariance `C_k`
/// (Mahalanobis distance of `k̂` to the constraint vs the χ² quantile).
pub(super) fn classify(k: &Vector2<f64>, ck: &Matrix2<f64>, alpha: f64) -> Curvature {
    let q2 = -2.0 * alpha.clamp(1e-300, 1.0).ln();
    let z = std::f64::consts::SQRT_2 * boundary::erf_inv(1.0 - alpha.clamp(1e-300, 1.0));
    let q1 = z * z;
    let m_plane = match ck.try_inverse() {
        Some(inv) => (k.transpose() * inv * k)[(0, 0)],
        None => f64::INFINITY,
    };
    if m_plane <= q2 {
        return Curvature::Plane;
    }
    let var_diff = (ck[(0, 0)] + ck[(1, 1)] - 2.0 * ck[(0, 1)]).max(f64::MIN_POSITIVE);
    let m_circ = (k.x - k.y).powi(2) / var_diff;
    let m_cx = k.x * k.x / ck[(0, 0)].max(f64::MIN_POSITIVE);
    let m_cy = k.y * k.y / ck[(1, 1)].max(f64::MIN_POSITIVE);
    let m_cyl = m_cx.min(m_cy);
    let circ_ok = m_circ <= q1;
    let cyl_ok = m_cyl <= q1;
    if circ_ok && (!cyl_ok || m_circ <= m_cyl) {
        Curvature::Circular
    } else if cyl_ok {
        Curvature::Cylindric(m_cy < m_cx)
    } else {
        Curvature::Full
    }
}

pub(super) fn by_sign(k: &Vector3<f64>) -> SurfaceType {
    if k.x * k.y >= 0.0 {
        SurfaceType::EllipticParaboloid
    } else {
        SurfaceType::HyperbolicParaboloid
    }
}

//! Synthetic ground truth for tests and benches: random patches of every type in front of a virtual
//! Kinect, sampled with Murray–Little noise (J eq 2), and the "estimand" of the boundary parameters
//! (what the moment-based boundary fit converges to for uniform samples of the true boundary).

use super::boundary;
use crate::geometry::{exp_map, log_map, r_xy_from_normal, r_xy_jacobian, right_jacobian_inverse};
use crate::patch::{BoundaryType, Patch, SurfaceType};
use crate::sensor::{sample_noise, ErrorModel};
use nalgebra::{DMatrix, DVector, Matrix3, Vector2, Vector3};
use rand::Rng;

/// Ranges of the random scenes.
#[derive(Clone, Copy, Debug)]
pub struct SceneConfig {
    /// Distance of the patch centre from the camera (m).
    pub range: (f64, f64),
    /// Maximum angle between the optical axis and the direction to the patch (rad).
    pub max_off_axis: f64,
    /// Maximum angle between the patch normal and the direction to the camera (rad).
    pub max_tilt: f64,
    /// Boundary half-size range (m).
    pub size: (f64, f64),
    /// Magnitude range of non-zero curvatures (m⁻¹).
    pub curvature: (f64, f64),
}

impl Default for SceneConfig {
    /// Foot-sized patches (J: r = 0.1 m) at 0.6–1.5 m, curvatures within J's bounds.
    fn default() -> Self {
        Self { range: (0.6, 1.5), max_off_axis: 0.35, max_tilt: 0.7, size: (0.05, 0.1), curvature: (3.0, 10.0) }
    }
}

fn signed<R: Rng + ?Sized>(rng: &mut R, range: (f64, f64)) -> f64 {
    let m = rng.random_range(range.0..range.1);
    if rng.random_bool(0.5) {
        m
    } else {
        -m
    }
}

/// A random patch of the given type facing a camera at the origin (optical frame, z forward).
pub fn random_patch<R: Rng + ?Sized>(
    rng: &mut R,
    surface: SurfaceType,
    boundary: BoundaryType,
    cfg: &SceneConfig,
) -> Result<Patch, crate::patch::PatchError> {
    let (lo, hi) = cfg.size;
    let mut size = || rng.random_range(lo..hi);
    let d = match boundary {
        BoundaryType::Circle => vec![size()],
        BoundaryType::Ellipse | BoundaryType::Rectangle if surface == SurfaceType::Plane => {
            // Clearly elongated (d_y ≤ 0.75 d_x) so the in-plane principal axes are defined.
            let a = size();
            vec![a, a * rng.random_range(0.45..0.75)]
        }
        BoundaryType::Ellipse | BoundaryType::Rectangle => vec![size(), size()],
        BoundaryType::Quadrilateral => {
            let dd = size() * 1.2;
            vec![dd, dd, dd, dd, rng.random_range(0.4..0.6)]
        }
    };
    let k = match surface {
        SurfaceType::EllipticParaboloid => {
            let kx = rng.random_range(cfg.curvature.0..cfg.curvature.1) * 0.6;
            let ky = kx * rng.random_range(1.6..2.5);
            if rng.random_bool(0.5) {
                Vector2::new(kx, ky)
            } else {
                Vector2::new(-kx, -ky)
            }
        }
        SurfaceType::HyperbolicParaboloid => {
            let kx = signed(rng, (cfg.curvature.0 * 0.8, cfg.curvature.1 * 0.6));
            let ky = -kx.signum() * rng.random_range(kx.abs()..cfg.curvature.1);
            Vector2::new(kx, ky)
        }
        SurfaceType::Plane => Vector2::zeros(),
        _ => {
            let kk = signed(rng, cfg.curvature);
            Vector2::new(kk, kk)
        }
    };
    // Centre direction within the field of view, at the requested range.
    let off = rng.random_range(0.0..cfg.max_off_axis);
    let az = rng.random_range(0.0..std::f64::consts::TAU);
    let dir = Vector3::new(off.sin() * az.cos(), off.sin() * az.sin(), off.cos());
    let center = dir * rng.random_range(cfg.range.0..cfg.range.1);
    // Normal towards the camera, tilted by up to max_tilt, random twist.
    let to_cam = -dir;
    let tilt = rng.random_range(0.0..cfg.max_tilt);
    let tilt_az = rng.random_range(0.0..std::f64::consts::TAU);
    let base = crate::geometry::rotation_from_normal(&to_cam);
    let normal = base * Vector3::new(tilt.sin() * tilt_az.cos(), tilt.sin() * tilt_az.sin(), tilt.cos());
    let rxy = r_xy_from_normal(&normal);
    let twist = rng.random_range(-std::f64::consts::PI..std::f64::consts::PI);
    let rot = exp_map(&Vector3::new(rxy.x, rxy.y, 0.0)) * exp_map(&Vector3::new(0.0, 0.0, twist));
    let r = crate::geometry::log_map(&rot);
    Patch::new(surface, boundary, d, k, r, center)
}

/// A random patch (see [`random_patch`]) whose whole surface faces the sensor at the origin, so that
/// uniform samples of its boundary are all visible (up to 100 attempts).
pub fn random_visible_patch<R: Rng + ?Sized>(
    rng: &mut R,
    surface: SurfaceType,
    boundary: BoundaryType,
    cfg: &SceneConfig,
) -> Result<Patch, crate::patch::PatchError> {
    let mut patch = random_patch(rng, surface, boundary, cfg)?;
    for _ in 0..100 {
        if fully_visible(rng, &patch) {
            break;
        }
        patch = random_patch(rng, surface, boundary, cfg)?;
    }
    Ok(patch)
}

fn fully_visible<R: Rng + ?Sized>(rng: &mut R, patch: &Patch) -> bool {
    let rot = patch.rotation_matrix();
    (0..300).all(|_| {
        let u = patch.sample_uv(rng);
        match patch.height(&u) {
            Some((z, g)) => {
                let q = rot * Vector3::new(u.x, u.y, z) + patch.center;
                // Visible with some margin (incidence below ~80°).
                (rot * Vector3::new(-g.x, -g.y, 1.0)).normalize().dot(&(-q).normalize()) > 0.17
            }
            None => false,
        }
    })
}

/// `n` noisy samples of a patch seen by a sensor at the origin: uniform in the boundary, visible
/// (surface normal facing the sensor), perturbed by `N(0, Σ)` of the error model. Returns the
/// measured points and their covariances (evaluated at the measured points, as a real system does).
pub fn sample_sensor<R: Rng + ?Sized>(rng: &mut R, patch: &Patch, n: usize, model: &ErrorModel) -> (Vec<Vector3<f64>>, Vec<Matrix3<f64>>) {
    let rot = patch.rotation_matrix();
    let mut points = Vec::with_capacity(n);
    let mut covs = Vec::with_capacity(n);
    let mut guard = 0;
    while points.len() < n && guard < 50 * n + 100 {
        guard += 1;
        let u = patch.sample_uv(rng);
        let Some((z, g)) = patch.height(&u) else { continue };
        let q = rot * Vector3::new(u.x, u.y, z) + patch.center;
        let n_w = rot * Vector3::new(-g.x, -g.y, 1.0);
        if n_w.dot(&(-q)) <= 0.0 {
            continue;
        }
        let Ok(cov_true) = model.covariance(&q) else { continue };
        let measured = q + sample_noise(rng, &cov_true);
        let Ok(cov) = model.covariance(&measured) else { continue };
        points.push(measured);
        covs.push(cov);
    }
    (points, covs)
}

/// Population moments `[0, 0, α, φ, c_xy]` of a uniform distribution over the patch boundary
/// (closed forms; Monte Carlo for quadrilaterals).
pub fn population_moments<R: Rng + ?Sized>(rng: &mut R, patch: &Patch) -> boundary::Moments {
    let d = &patch.boundary_params;
    let (a, p, c) = match (patch.boundary, d.as_slice()) {
        (BoundaryType::Ellipse, [dx, dy]) => (dx * dx / 4.0, dy * dy / 4.0, 0.0),
        (BoundaryType::Circle, [dc]) => (dc * dc / 4.0, dc * dc / 4.0, 0.0),
        (BoundaryType::Rectangle, [dx, dy]) => (dx * dx / 3.0, dy * dy / 3.0, 0.0),
        _ => {
            let n = 40_000;
            let mut acc = Vector3::zeros();
            let mut mean = Vector2::zeros();
            let samples: Vec<Vector2<f64>> = (0..n).map(|_| patch.sample_uv(rng)).collect();
            for u in &samples {
                mean += u;
            }
            mean /= n as f64;
            for u in &samples {
                let v = u - mean;
                acc += Vector3::new(v.x * v.x, v.y * v.y, v.x * v.y);
            }
            acc /= n as f64;
            (acc.x, acc.y, acc.z)
        }
    };
    boundary::Moments::from_column_slice(&[0.0, 0.0, a, p, c])
}

/// The boundary parameters the moment-based fit estimates for uniform samples of this patch
/// (IROS steps 6–9 applied to the population moments).
pub fn boundary_estimand<R: Rng + ?Sized>(rng: &mut R, patch: &Patch, containment: f64) -> Vec<f64> {
    let m = population_moments(rng, patch);
    let gamma = containment.min(1.0 - 1e-9);
    let lambda = std::f64::consts::SQRT_2 * boundary::erf_inv(gamma);
    let ln_term = -(1.0 - gamma).ln();
    let kappa = patch.curvatures.y;
    // The extents do not depend on the centroid's height.
    let map = boundary::MomentMap { surface: patch.surface, boundary: patch.boundary, kappa, lambda, ln_term, centroid_height: 0.0 };
    let out = boundary::from_moments(&map, &m);
    out.d.iter().take(out.nd).copied().collect()
}

/// The mean of `values` over their sample standard deviation (a bias in units of the scatter); NaN
/// for fewer than two values.
pub fn mean_over_scatter(values: &[f64]) -> f64 {
    let n = values.len() as f64;
    let mean = values.iter().sum::<f64>() / n;
    let sd = (values.iter().map(|v| (v - mean) * (v - mean)).sum::<f64>() / (n - 1.0)).sqrt();
    mean / sd
}

/// χ²_k 95% quantile (Wilson–Hilferty; within 0.1% for k ≥ 2).
pub fn chi2_95(k: usize) -> f64 {
    let k = k as f64;
    let z = 1.644_853_626_951_472_2;
    let a = 2.0 / (9.0 * k);
    k * (1.0 - a + z * a.sqrt()).powi(3)
}

/// Truth parameter vector in the fit's representation: boundary estimand, and of the equivalent
/// descriptions of the true patch (quarter turns about the normal where the type allows them, as
/// [`crate::fuse::align`] chooses for fusion) the one nearest the estimate.
pub fn truth_params<R: Rng + ?Sized>(rng: &mut R, truth: &Patch, fit: &Patch, containment: f64) -> Option<DVector<f64>> {
    let mut t = crate::fuse::align(fit, truth)?;
    t.boundary_params = boundary_estimand(rng, &t, containment);
    Some(t.params())
}

/// `fit − truth` with the rotation part measured on SO(3), not as a difference of exp-map vectors:
/// `R_truth = R(r̂)·exp(δ)` with `δ = log(R(r̂)ᵀ R_truth)`, mapped into the chart at r̂ by the same
/// first-order map the fit uses for Σ (right Jacobian inverse, and eq 45 for 5-DoF r_xy). Camera-facing
/// patches have ‖r‖ ≈ π, where the exp-map chart is strongly curved: there a plain difference of r
/// vectors leaves the linear regime Σ describes although the rotations differ by a fraction of a degree.
pub fn error_on_manifold(fit: &Patch, truth_params: &DVector<f64>) -> DVector<f64> {
    let mut err = fit.params() - truth_params;
    let at = fit.boundary.num_params() + fit.surface.num_curvatures();
    let is5 = fit.is_5dof();
    let r_truth = if is5 {
        Vector3::new(truth_params[at], truth_params[at + 1], 0.0)
    } else {
        Vector3::new(truth_params[at], truth_params[at + 1], truth_params[at + 2])
    };
    let rot_fit = fit.rotation_matrix();
    let jr_inv = right_jacobian_inverse(&fit.rotation);
    if is5 {
        // Only the normal is defined: the tilt that takes the fitted normal to the true one, in the
        // fitted frame (no twist, which r_xy does not see but which would leak in at second order).
        let n_truth_local = rot_fit.transpose() * exp_map(&r_truth).column(2);
        let axis = Vector3::z().cross(&n_truth_local);
        let angle = axis.norm().atan2(n_truth_local.z);
        let delta = if axis.norm() > 0.0 { axis * (angle / axis.norm()) } else { Vector3::zeros() };
        let e = -(r_xy_jacobian(&fit.rotation) * jr_inv * delta);
        err[at] = e.x;
        err[at + 1] = e.y;
    } else {
        let delta = log_map(&(rot_fit.transpose() * exp_map(&r_truth)));
        let e = -(jr_inv * delta);
        for i in 0..3 {
            err[at + i] = e[i];
        }
    }
    err
}

/// Mahalanobis distance² of the truth under Σ (pseudo-inverse) and the rank used as χ² dof.
pub fn mahalanobis(err: &DVector<f64>, cov: &DMatrix<f64>) -> Option<(f64, usize)> {
    let eig = cov.clone().symmetric_eigen();
    let max = eig.eigenvalues.iter().cloned().fold(0.0, f64::max);
    if max.is_nan() || max <= 0.0 {
        return None;
    }
    let mut m2 = 0.0;
    let mut rank = 0;
    for (i, &l) in eig.eigenvalues.iter().enumerate() {
        if l > 1e-12 * max {
            let proj = eig.eigenvectors.column(i).dot(err);
            m2 += proj * proj / l;
            rank += 1;
        }
    }
    Some((m2, rank))
}

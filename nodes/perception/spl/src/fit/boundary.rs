//! Boundary fitting from 1D/2D data moments (IROS IV steps 4–9, eq 30–32) and the gauge directions
//! of the surface (centre along symmetric directions, in-plane rotation), with their sampling
//! covariance.
//!
//! The moments are treated as sample means of i.i.d. draws from the patch area; their covariance is
//! the empirical covariance of the per-point terms divided by N (delta method). This is the
//! uncertainty of everything the fit takes from moments (boundary extents, centre of a plane, the
//! apex of spheres/cylinders along their symmetry directions, a plane's in-plane rotation).

use crate::patch::{BoundaryType, SurfaceType};
use nalgebra::{Matrix3, SMatrix, SVector, Vector3};

/// `[x̄, ȳ, α, φ, c_xy]`: means and central second moments of the projected points (eq 30 uses
/// `β = 2 c_xy`).
pub type Moments = SVector<f64, 5>;

/// Moments of `u_i = Π_xy Rᵀ(q_i − c)` (eq 16), their sampling covariance, and their first-order
/// dependence on the surface frame; [`moments`] takes the points `Rᵀ(q_i − c)` ([`to_local`]).
pub(crate) struct MomentStats {
    /// `[x̄, ȳ, α, φ, c_xy]`.
    pub m: Moments,
    /// Sampling covariance of `m` (empirical covariance of the per-point terms / N).
    pub cov: SMatrix<f64, 5, 5>,
    /// `∂m/∂(κ3, δ, δc)`: how the moments move with a local increment of the frame (eq 16 with
    /// `q_l' = q_l + [q_l]× δ − δc`).
    pub frame_jacobian: SMatrix<f64, 5, 9>,
    /// Local height `z̄` of the data centroid (see [`MomentMap`]).
    pub centroid_height: f64,
}

pub(crate) fn moments(local: &[Vector3<f64>]) -> MomentStats {
    let (mean, c3) = mean_and_scatter(local);
    let n = local.len().max(1) as f64;
    let m = Moments::from_column_slice(&[mean.x, mean.y, c3.xx, c3.yy, c3.xy]);
    // Σ ψ ψᵀ, upper triangle (row ≤ column, column by column) summed point by point.
    let mut upper = [0.0f64; 15];
    for q in local {
        let (dx, dy) = (q.x - mean.x, q.y - mean.y);
        let [p0, p1, p2, p3, p4] = [dx, dy, dx * dx - c3.xx, dy * dy - c3.yy, dx * dy - c3.xy];
        let terms = [
            p0 * p0,
            p0 * p1,
            p1 * p1,
            p0 * p2,
            p1 * p2,
            p2 * p2,
            p0 * p3,
            p1 * p3,
            p2 * p3,
            p3 * p3,
            p0 * p4,
            p1 * p4,
            p2 * p4,
            p3 * p4,
            p4 * p4,
        ];
        for (sum, t) in upper.iter_mut().zip(terms) {
            *sum += t;
        }
    }
    let mut cov = SMatrix::<f64, 5, 5>::zeros();
    let mut k = 0;
    for j in 0..5 {
        for i in 0..=j {
            let v = upper.get(k).copied().unwrap_or(0.0);
            cov[(i, j)] = v;
            cov[(j, i)] = v;
            k += 1;
        }
    }
    // Unbiased empirical covariance of ψ, divided by N for the mean.
    cov /= (n - 1.0).max(1.0) * n;
    // Δx = q_y δz − q_z δy − δcx, Δy = q_z δx − q_x δz − δcy (local slots 3..6 = δ, 6..9 = δc).
    let mut a = SMatrix::<f64, 5, 9>::zeros();
    a[(0, 4)] = -mean.z;
    a[(0, 5)] = mean.y;
    a[(0, 6)] = -1.0;
    a[(1, 3)] = mean.z;
    a[(1, 5)] = -mean.x;
    a[(1, 7)] = -1.0;
    a[(2, 4)] = -2.0 * c3.xz;
    a[(2, 5)] = 2.0 * c3.xy;
    a[(3, 3)] = 2.0 * c3.yz;
    a[(3, 5)] = -2.0 * c3.xy;
    a[(4, 3)] = c3.xz;
    a[(4, 4)] = -c3.yz;
    a[(4, 5)] = c3.yy - c3.xx;
    MomentStats { m, cov, frame_jacobian: a, centroid_height: mean.z }
}

impl MomentStats {
    /// The sampling covariance of a centrally symmetric boundary (ellipse, circle, rectangle): the
    /// centroid and the second moments uncorrelated. Their sample covariance is the data's third
    /// central moments over N, zero for such a boundary; the sample's own third moments are noise
    /// about that zero, and noise tied to the centroid's error (points bunched on one side move the
    /// centroid there and skew the rest the other way). Fusion would multiply that cross term by the
    /// centre's innovation and push fused extents up, by a third of their fused σ over ten views of
    /// a plane.
    pub fn centrally_symmetric(mut self) -> Self {
        for i in 0..2 {
            for j in 2..5 {
                self.cov[(i, j)] = 0.0;
                self.cov[(j, i)] = 0.0;
            }
        }
        self
    }
}

/// The moments `m` of [`moments`] alone (no sampling covariance, no frame Jacobian), and the
/// points' 3D mean (the centroid in the local frame).
pub(crate) fn moment_values(local: &[Vector3<f64>]) -> (Moments, Vector3<f64>) {
    let (mean, c3) = mean_and_scatter(local);
    (Moments::from_column_slice(&[mean.x, mean.y, c3.xx, c3.yy, c3.xy]), mean)
}

/// `Rᵀ(q_i − c)` (eq 16 before the projection), once per point for all moment passes.
pub(crate) fn to_local(points: &[Vector3<f64>], rot: &Matrix3<f64>, c: &Vector3<f64>) -> Vec<Vector3<f64>> {
    let rt = rot.transpose();
    points.iter().map(|q| rt * (q - c)).collect()
}

/// The central second moments the boundary needs (`zz` is never used).
struct Scatter {
    xx: f64,
    yy: f64,
    xy: f64,
    xz: f64,
    yz: f64,
}

/// Mean and central second moments (divided by N) of local points (two-pass).
fn mean_and_scatter(local: &[Vector3<f64>]) -> (Vector3<f64>, Scatter) {
    let n = local.len().max(1) as f64;
    let mut mean = Vector3::zeros();
    for q in local {
        mean += q;
    }
    mean /= n;
    let (mut xx, mut yy, mut xy, mut xz, mut yz) = (0.0, 0.0, 0.0, 0.0, 0.0);
    for q in local {
        let d = q - mean;
        xx += d.x * d.x;
        yy += d.y * d.y;
        xy += d.x * d.y;
        xz += d.x * d.z;
        yz += d.y * d.z;
    }
    (mean, Scatter { xx: xx / n, yy: yy / n, xy: xy / n, xz: xz / n, yz: yz / n })
}

/// Values taken from the moments: boundary params (up to 5) and the moment-fixed local increments
/// `[δx, δy, δz, δcx, δcy, δcz]` of the final frame.
pub struct FromMoments {
    pub d: [f64; 5],
    pub nd: usize,
    pub local: [f64; 6],
}

/// What turns the moments into boundary parameters and gauge increments (IROS steps 4–9).
///
/// The apex of spheres and cylinders is where the ray from the centre (axis) through the centroid
/// meets the surface ([`super::gauge`]). The centroid lies `z̄ ≈ κ⟨ρ²⟩/2` inside the surface, so a
/// sideways shift `x̄` of it moves the apex by `x̄ / (1 − κ z̄)` along the surface and tilts it by
/// `κ x̄ / (1 − κ z̄)`: for a cap of κr = 0.55 the sampling noise of the centroid moves the apex
/// 8 % farther (its variance 17 %) than the tangent-plane picture `x̄`, `κ x̄` says.
#[derive(Debug, Clone, Copy)]
pub struct MomentMap {
    pub surface: SurfaceType,
    pub boundary: BoundaryType,
    /// Curvature of spheres/cylinders (for the rotation that follows the apex).
    pub kappa: f64,
    /// `λ = √2 erf⁻¹(Γ)` (step 4).
    pub lambda: f64,
    /// `−ln(1 − Γ)` (eq 30).
    pub ln_term: f64,
    /// Local height `z̄` of the data's 3D centroid.
    pub centroid_height: f64,
}

/// Boundary parameters and gauge increments as functions of the moments (IROS steps 5–9).
pub fn from_moments(map: &MomentMap, m: &Moments) -> FromMoments {
    let MomentMap { surface, boundary, kappa, lambda, ln_term, centroid_height } = *map;
    let (xm, ym, alpha, phi, cxy) = (m[0], m[1], m[2], m[3], m[4]);
    // Apex shift per unit of sideways centroid shift on spheres and cylinders (see above); a
    // centroid near the centre (a half sphere) would make it unbounded: capped at 10.
    let follow = 1.0 / (1.0 - kappa * centroid_height).max(0.1);
    let follow = if follow.is_finite() { follow } else { 1.0 };
    let sq = |v: f64| v.max(0.0).sqrt();
    let mut out = FromMoments { d: [0.0; 5], nd: boundary.num_params(), local: [0.0; 6] };
    match surface {
        SurfaceType::Plane => {
            // Step 9: centre at the centroid, eq 30–32 for extents and in-plane rotation.
            let beta = 2.0 * cxy;
            let root = (beta * beta + (alpha - phi).powi(2)).sqrt();
            let lp = sq(ln_term * (alpha + phi + root));
            let lm = sq(ln_term * (alpha + phi - root));
            out.local[3] = xm;
            out.local[4] = ym;
            match boundary {
                // The circle's radius from the mean principal moment (IROS: the larger one, which
                // for round data is the larger of two noisy estimates, biased up by ~0.56σ).
                BoundaryType::Circle => out.d[0] = sq(ln_term * (alpha + phi)),
                BoundaryType::Ellipse | BoundaryType::Rectangle => {
                    out.d[0] = lp;
                    out.d[1] = lm;
                    out.local[2] = 0.5 * beta.atan2(alpha - phi);
                }
                BoundaryType::Quadrilateral => {
                    // eq 31
                    let d = (lm * lm + lp * lp).sqrt();
                    out.d = [d, d, d, d, lm.atan2(lp)];
                    out.local[2] = 0.5 * beta.atan2(alpha - phi);
                }
            }
        }
        SurfaceType::CylindricParaboloid => {
            // Step 6: d_r = λ[√(v_x − x̄²) √v_y], centre slides to x̄ along the axis.
            out.d[0] = lambda * sq(alpha);
            out.d[1] = lambda * sq(phi + ym * ym);
            out.local[3] = xm;
        }
        SurfaceType::CircularCylinder => {
            out.d[0] = lambda * sq(alpha);
            out.d[1] = lambda * sq(phi + ym * ym);
            // Apex follows the data around the axis: rotation about x by κȳ with the apex.
            out.local[3] = xm;
            out.local[4] = ym * follow;
            out.local[0] = kappa * ym * follow;
        }
        SurfaceType::CircularParaboloid => {
            // Step 7 with the mean of v_x and v_y instead of their maximum (see `round_radius`).
            out.d[0] = round_radius(lambda, alpha + xm * xm, phi + ym * ym);
        }
        SurfaceType::Sphere => {
            out.d[0] = round_radius(lambda, alpha + xm * xm, phi + ym * ym);
            // Apex follows the data over the sphere: tilt (κȳ, −κx̄) with the apex at (x̄, ȳ).
            out.local[3] = xm * follow;
            out.local[4] = ym * follow;
            out.local[0] = kappa * ym * follow;
            out.local[1] = -kappa * xm * follow;
        }
        SurfaceType::EllipticParaboloid | SurfaceType::HyperbolicParaboloid => {
            // Step 8
            out.d[0] = lambda * sq(alpha + xm * xm);
            out.d[1] = lambda * sq(phi + ym * ym);
        }
    }
    out
}

/// Radius `d_c = λ √((v_x + v_y)/2)` of a circle boundary from the second moments about its centre.
/// IROS step 7 takes `λ max(√v_x, √v_y)`: for round data that is the larger of two noisy estimates
/// of the same value, biased up by ~0.56σ, so the true radius fell outside Σ's ellipsoid ever more
/// often as Σ shrinks with more points (`bench_fit`: spheres 83 % inside at 600 points). The mean is
/// the moment estimate of a uniform disc.
fn round_radius(lambda: f64, vx: f64, vy: f64) -> f64 {
    lambda * (0.5 * (vx + vy)).max(0.0).sqrt()
}

/// `∂(d, local)/∂m` by central differences (the maps are smooth closed forms; 10 evaluations).
pub(crate) fn from_moments_jacobian(map: &MomentMap, m: &Moments) -> SMatrix<f64, 11, 5> {
    let scale = (m[2] + m[3]).abs().sqrt().max(1e-6);
    let mut jac = SMatrix::<f64, 11, 5>::zeros();
    for j in 0..5 {
        let h = if j < 2 { 1e-6 * scale } else { 1e-6 * scale * scale };
        let mut mp = *m;
        let mut mm = *m;
        mp[j] += h;
        mm[j] -= h;
        let p = from_moments(map, &mp);
        let q = from_moments(map, &mm);
        for i in 0..5 {
            jac[(i, j)] = (p.d[i] - q.d[i]) / (2.0 * h);
        }
        for i in 0..6 {
            jac[(5 + i, j)] = (p.local[i] - q.local[i]) / (2.0 * h);
        }
    }
    jac
}

/// Error function (Numerical Recipes `erfc` Chebyshev fit, fractional error < 1.2e-7, refined by the
/// series for small arguments).
pub fn erf(x: f64) -> f64 {
    if x.abs() < 0.5 {
        // Maclaurin series, converges fast here.
        let x2 = x * x;
        let mut term = x;
        let mut sum = x;
        for n in 1..30 {
            term *= -x2 / n as f64;
            let add = term / (2 * n + 1) as f64;
            sum += add;
            if add.abs() < 1e-17 {
                break;
            }
        }
        return sum * 2.0 / std::f64::consts::PI.sqrt();
    }
    let z = x.abs();
    let t = 1.0 / (1.0 + 0.5 * z);
    let poly = -z * z - 1.265_512_23
        + t * (1.000_023_68
            + t * (0.374_091_96
                + t * (0.096_784_18
                    + t * (-0.186_288_06
                        + t * (0.278_868_07 + t * (-1.135_203_98 + t * (1.488_515_87 + t * (-0.822_152_23 + t * 0.170_872_77))))))));
    let erfc = t * poly.exp();
    if x >= 0.0 {
        1.0 - erfc
    } else {
        erfc - 1.0
    }
}

/// Inverse error function on (−1, 1) (Giles' approximation refined by Newton steps on [`erf`]).
pub fn erf_inv(y: f64) -> f64 {
    if y <= -1.0 {
        return f64::NEG_INFINITY;
    }
    if y >= 1.0 {
        return f64::INFINITY;
    }
    let w = -((1.0 - y) * (1.0 + y)).ln();
    let mut x = if w < 5.0 {
        let w = w - 2.5;
        let mut p = 2.810_226_36e-08;
        for c in [
            3.432_739_39e-07,
            -3.523_387_7e-06,
            -4.391_506_54e-06,
            0.000_218_580_87,
            -0.001_253_725_03,
            -0.004_177_681_64,
            0.246_640_727,
            1.501_409_41,
        ] {
            p = c + p * w;
        }
        p * y
    } else {
        let w = w.sqrt() - 3.0;
        let mut p = -0.000_200_214_257;
        for c in [
            0.000_100_950_558,
            0.001_349_343_22,
            -0.003_673_428_44,
            0.005_739_507_73,
            -0.007_622_461_3,
            0.009_438_870_47,
            1.001_674_06,
            2.832_976_82,
        ] {
            p = c + p * w;
        }
        p * y
    };
    for _ in 0..3 {
        let err = erf(x) - y;
        let deriv = 2.0 / std::f64::consts::PI.sqrt() * (-x * x).exp();
        if deriv <= 0.0 {
            break;
        }
        x -= err / deriv;
    }
    x
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The circle radius from 150 uniform samples of a disc is unbiased: over 400 draws its mean is
    /// within 3 standard errors of the population value λR/2 (the maximum of the two moments was
    /// ~0.56σ high).
    #[test]
    fn circle_radius_of_uniform_disc_samples_is_unbiased() {
        use rand::{Rng, SeedableRng};
        let mut rng = rand::rngs::StdRng::seed_from_u64(5);
        let (radius, lambda) = (0.07, std::f64::consts::SQRT_2 * erf_inv(0.95));
        // Population: v_x = v_y = R²/4 about the centre.
        let truth = lambda * radius / 2.0;
        let estimates: Vec<f64> = (0..400)
            .map(|_| {
                let local: Vec<Vector3<f64>> = (0..150)
                    .map(|_| {
                        let (r, a) = (radius * rng.random::<f64>().sqrt(), rng.random_range(0.0..std::f64::consts::TAU));
                        Vector3::new(r * a.cos(), r * a.sin(), 0.0)
                    })
                    .collect();
                let (m, _) = moment_values(&local);
                let map = MomentMap {
                    surface: SurfaceType::Sphere,
                    boundary: BoundaryType::Circle,
                    kappa: 0.0,
                    lambda,
                    ln_term: 0.0,
                    centroid_height: 0.0,
                };
                from_moments(&map, &m).d[0]
            })
            .collect();
        let mean = estimates.iter().sum::<f64>() / estimates.len() as f64;
        let sd = (estimates.iter().map(|d| (d - mean).powi(2)).sum::<f64>() / (estimates.len() - 1) as f64).sqrt();
        let standard_error = sd / (estimates.len() as f64).sqrt();
        assert!((mean - truth).abs() < 3.0 * standard_error, "mean {mean} vs {truth} (σ {sd})");
    }

    #[test]
    fn erf_and_inverse() {
        // erf(1) = 0.8427007929497149
        assert!((erf(1.0) - 0.842_700_792_949_714_9).abs() < 2e-7);
        assert!((erf(0.3) - 0.328_626_759_459_127_4).abs() < 1e-12);
        for y in [-0.99, -0.5, 0.0, 0.2, 0.6827, 0.95, 0.999] {
            assert!((erf(erf_inv(y)) - y).abs() < 1e-9, "{y}");
        }
        // λ for Γ = 0.95 is the 97.5% normal quantile 1.959964.
        assert!((2f64.sqrt() * erf_inv(0.95) - 1.959_964).abs() < 1e-5);
    }

    #[test]
    fn plane_ellipse_moments_give_orientation_and_extents() {
        // Uniform ellipse with radii (a, b) rotated by 0.4 rad: α' = a²/4, φ' = b²/4.
        let (a, b, th) = (0.1f64, 0.05f64, 0.4f64);
        let (s, c) = th.sin_cos();
        let (va, vb) = (a * a / 4.0, b * b / 4.0);
        let alpha = c * c * va + s * s * vb;
        let phi = s * s * va + c * c * vb;
        let cxy = s * c * (va - vb);
        let m = Moments::from_column_slice(&[0.01, -0.02, alpha, phi, cxy]);
        let ln_term = -(1.0f64 - 0.95).ln();
        let map = MomentMap {
            surface: SurfaceType::Plane,
            boundary: BoundaryType::Ellipse,
            kappa: 0.0,
            lambda: 1.96,
            ln_term,
            centroid_height: 0.0,
        };
        let out = from_moments(&map, &m);
        assert!((out.local[2] - th).abs() < 1e-12);
        assert!((out.d[0] - (2.0 * ln_term * va).sqrt()).abs() < 1e-12);
        assert!((out.d[1] - (2.0 * ln_term * vb).sqrt()).abs() < 1e-12);
        assert_eq!((out.local[3], out.local[4]), (0.01, -0.02));
        let jac = from_moments_jacobian(&map, &m);
        assert!((jac[(8, 0)] - 1.0).abs() < 1e-6 && (jac[(9, 1)] - 1.0).abs() < 1e-6);
    }
}

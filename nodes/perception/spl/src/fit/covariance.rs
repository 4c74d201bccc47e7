//! IROS IV steps 4–9 and the output covariance Σ over the patch's minimal parameters.
//!
//! The boundary comes from the data moments (eq 30–32, [`super::boundary`]) after the gauge
//! ([`super::gauge`]). Σ is first-order propagation of two independent sources to the minimal vector
//! `[d, k, r|r_xy, c]`: the WLM information of the surface increments (eq 36, measurement noise of
//! the points) and the sampling covariance of the moments; the rotation goes through the right
//! Jacobian of the exponential map (eq 45 for the 5-DoF types). The second-order terms that
//! first-order propagation misses (apex sag, extents measured about an uncertain apex or along an
//! uncertain twist) are added explicitly.

use super::boundary;
use super::gauge::apply_gauge;
use super::request::{model_for, settings_for, FitConfig};
use super::surface::residual_scale;
use super::wlm::{self, LmSettings, PointSet, SurfaceState};
use super::FitError;
use crate::geometry::{log_map, r_xy_from_normal, r_xy_jacobian, right_jacobian_inverse};
use crate::patch::{BoundaryType, Patch, SurfaceType};
use nalgebra::{DMatrix, Matrix2, SMatrix, SVector, Vector2, Vector3};

/// Second-order variance of the apex height along the local normal (index δcz of the local layout).
///
/// On a curved surface the data fix the surface near them; an error `u` of the apex along the local
/// x/y axes (with the matching tilt, which is the first-order picture Σ describes) also drops the
/// apex by the sag `½ uᵀ K u`, K = diag(κx, κy) (eq 12; κ along the curved axes of cylinders). That
/// quadratic term is invisible to first-order propagation, yet for 1 cm apex errors on a κ = 5 m⁻¹
/// patch it is as large as the height uncertainty itself, so the truth falls outside the linear
/// ellipsoid on the concave side. For `u ~ N(0, S)` its second moment is
/// `Var + mean² = ½ tr(KSKS) + ¼ tr(KS)²`, added to the height variance.
fn slide_sag_variance(surface: SurfaceType, k3: &Vector3<f64>, s: &Matrix2<f64>) -> f64 {
    let k = match surface {
        SurfaceType::Plane => return 0.0,
        SurfaceType::CylindricParaboloid | SurfaceType::CircularCylinder => Matrix2::new(0.0, 0.0, 0.0, k3.y),
        SurfaceType::CircularParaboloid | SurfaceType::Sphere => Matrix2::identity() * k3.x,
        SurfaceType::EllipticParaboloid | SurfaceType::HyperbolicParaboloid => Matrix2::new(k3.x, 0.0, 0.0, k3.y),
    };
    let ks = k * s;
    let sag = 0.5 * ks.trace();
    let out = 0.5 * (ks * ks).trace() + sag * sag;
    if out.is_finite() {
        out
    } else {
        0.0
    }
}

/// Second-order terms of the extents that steps 6–8 take from moments about the apex (not about the
/// data centroid): an apex error `u_i` along axis i adds `u_i²` to `v_i = avg(x_i²)`, so
/// `d_i = λ√v_i` grows by `λ² u_i² / (2 d_i)` — zero to first order, and always upward. For
/// `u ~ N(0, S)`: `E[u_i² u_j²] = S_ii S_jj + 2 S_ij²`. Returns `(row, col, added second moment)` in
/// the local layout (d at 0..5).
fn apex_moment_second_order(surface: SurfaceType, d: &[f64], lambda: f64, s: &Matrix2<f64>) -> Vec<(usize, usize, f64)> {
    // (index in d, local axis) of the extents measured about the apex.
    let axes: &[(usize, usize)] = match surface {
        SurfaceType::EllipticParaboloid | SurfaceType::HyperbolicParaboloid => &[(0, 0), (1, 1)],
        SurfaceType::CylindricParaboloid => &[(1, 1)],
        SurfaceType::CircularParaboloid => &[(0, if s[(0, 0)] >= s[(1, 1)] { 0 } else { 1 })],
        _ => &[],
    };
    // Per extent: the second moment of its growth, `3 g² S_ii²` with `g = λ²/(2 d)`, capped at the
    // large-slide limit `λ² S_ii` (`(λ√(v + u²) − λ√v)² ≤ λ² u²`: once the apex is uncertain by more
    // than the extent, the growth is linear in u — weakly curved patches far from their apex).
    // Between two extents the correlation of u_i² and u_j², `(S_ii S_jj + 2 S_ij²) / (3 S_ii S_jj)`,
    // which keeps the added block positive semi-definite.
    let rms = |a: usize, i: usize| -> Option<f64> {
        let d = *d.get(a)?;
        let g = lambda * lambda / (2.0 * d);
        let v = (3.0 * g * g * s[(i, i)] * s[(i, i)]).min(lambda * lambda * s[(i, i)]);
        (d > 0.0 && v.is_finite() && v >= 0.0).then(|| v.sqrt())
    };
    let mut out = Vec::with_capacity(axes.len() * axes.len());
    for &(a, i) in axes {
        for &(b, j) in axes {
            let (Some(ea), Some(eb)) = (rms(a, i), rms(b, j)) else { continue };
            let denominator = 3.0 * s[(i, i)] * s[(j, j)];
            let correlation = if denominator > 0.0 { (s[(i, i)] * s[(j, j)] + 2.0 * s[(i, j)] * s[(i, j)]) / denominator } else { 0.0 };
            out.push((a, b, correlation.min(1.0) * ea * eb));
        }
    }
    out
}

/// Second-order terms of the extents measured along in-plane axes that the surface fixes (the
/// principal curvature directions of elliptic/hyperbolic paraboloids, the axis of cylindric ones
/// and cylinders): a twist error ψ about the normal mixes the moments, `v_x ← v_x + (v_y − v_x) ψ²`
/// (the first-order term `2 v_xy ψ` is in the frame Jacobian of the moments), so with `v = d²/λ²`
/// `Δd_x = (d_y² − d_x²) ψ² / (2 d_x)` and the opposite for `d_y`. For `ψ ~ N(0, σ²)`,
/// `E[ψ⁴] = 3σ⁴`; each change is capped at `|d_y − d_x|` (a quarter turn swaps the extents), and
/// the two are perfectly anti-correlated (a rank-1, positive semi-definite block). Returns
/// `(row, col, added second moment)` in the local layout (d at 0..5).
fn twist_moment_second_order(surface: SurfaceType, d: &[f64], twist_variance: f64) -> Vec<(usize, usize, f64)> {
    let twisted = matches!(
        surface,
        SurfaceType::EllipticParaboloid
            | SurfaceType::HyperbolicParaboloid
            | SurfaceType::CylindricParaboloid
            | SurfaceType::CircularCylinder
    );
    let (Some(&dx), Some(&dy)) = (d.first(), d.get(1)) else { return Vec::new() };
    if !(twisted && dx > 0.0 && dy > 0.0 && twist_variance.is_finite() && twist_variance > 0.0) {
        return Vec::new();
    }
    let cap = (dy - dx).abs();
    let change = |mine: f64, other: f64| {
        let a = (other * other - mine * mine) / (2.0 * mine);
        a.signum() * (3.0f64.sqrt() * a.abs() * twist_variance).min(cap)
    };
    let e = [change(dx, dy), change(dy, dx)];
    (0..2).flat_map(|i| (0..2).map(move |j| (i, j, e[i] * e[j]))).collect()
}

/// Steps 4–9 and the covariance Σ over the minimal parameters.
#[allow(clippy::too_many_arguments)]
pub(super) fn finish(
    surface: SurfaceType,
    boundary: BoundaryType,
    state: SurfaceState,
    points: &[Vector3<f64>],
    boundary_points: &[Vector3<f64>],
    covs: &PointSet,
    settings: &LmSettings,
    config: &FitConfig,
    containment: f64,
    weighted: bool,
) -> Result<Patch, FitError> {
    // Step 4: λ = √2 erf⁻¹(Γ); eq 30 uses −ln(1 − Γ). Γ = 1 would be unbounded: clamp just below.
    let gamma = containment.min(1.0 - 1e-9);
    let lambda = std::f64::consts::SQRT_2 * boundary::erf_inv(gamma);
    let ln_term = -(1.0 - gamma).ln();
    let kappa = match surface {
        SurfaceType::CylindricParaboloid | SurfaceType::CircularCylinder => state.k3.y,
        _ => state.k3.x,
    };
    // Steps 5–9: moments in the surface frame, move to the final frame, moments again there.
    let local = boundary::to_local(boundary_points, &state.rot, &state.c);
    let (m0, mean_local) = boundary::moment_values(&local);
    let map = boundary::MomentMap { surface, boundary, kappa, lambda, ln_term, centroid_height: mean_local.z };
    let first = boundary::from_moments(&map, &m0);
    let gauged = apply_gauge(surface, boundary, &state, &m0, &mean_local, first.local[2])?;
    // Paraboloids keep their frame (no gauge freedom): the points are in it already.
    let local = if gauged == state { local } else { boundary::to_local(boundary_points, &gauged.rot, &gauged.c) };
    let state = gauged;
    let stats = match boundary {
        BoundaryType::Quadrilateral => boundary::moments(&local),
        _ => boundary::moments(&local).centrally_symmetric(),
    };
    let m = stats.m;
    let map = boundary::MomentMap { centroid_height: stats.centroid_height, ..map };
    let from_m = boundary::from_moments(&map, &m);
    let mut d: Vec<f64> = from_m.d.iter().take(from_m.nd).copied().collect();
    // Table I: |κ| d ≤ 1 for spheres (d_c) and cylinders (d_y).
    match surface {
        SurfaceType::Sphere if kappa != 0.0 => d.iter_mut().for_each(|v| *v = v.min(1.0 / kappa.abs())),
        SurfaceType::CircularCylinder if kappa != 0.0 => {
            if let Some(v) = d.get_mut(1) {
                *v = v.min(1.0 / kappa.abs());
            }
        }
        _ => {}
    }

    // Surface part of Σ: WLM information at the final frame (measurement noise).
    let model = model_for(surface);
    let mfree = model.num_free();
    let normal = wlm::accumulate_with_prior(model, &state, covs, &settings_for(model, settings, config), true);
    let scale = residual_scale(normal.chi2, points.len(), mfree, weighted, config);
    let h_inv = wlm::inverse_leading(mfree, &normal.h).ok_or(FitError::Degenerate("singular information matrix"))?;
    let mut cov_free = SMatrix::<f64, { wlm::MAX_FREE }, { wlm::MAX_FREE }>::zeros();
    for r in 0..mfree {
        for c in 0..mfree {
            cov_free[(r, c)] = h_inv[(r, c)] * scale;
        }
    }
    // Local layout (14): [d (5) | κx κy κz | δx δy δz | δcx δcy δcz], a linear function of two
    // independent sources: the surface increments s (9 slots, WLM covariance) and the sampling
    // noise of the moments (5): local = [G_d (A s + m); s + G_pose (A s + m)], A = ∂m/∂s.
    // E C Eᵀ with the 0/1 embedding E: every local slot belongs to at most one free parameter.
    let slot_param: [Option<usize>; 9] = std::array::from_fn(|slot| model.free_slots().iter().position(|mask| mask & (1 << slot) != 0));
    let cov_s = SMatrix::<f64, 9, 9>::from_fn(|a, b| match (slot_param[a], slot_param[b]) {
        (Some(i), Some(j)) => cov_free[(i, j)],
        _ => 0.0,
    });
    let jm = boundary::from_moments_jacobian(&map, &m);
    let mut g = SMatrix::<f64, 14, 5>::zeros();
    for j in 0..5 {
        for i in 0..5 {
            g[(i, j)] = jm[(i, j)];
        }
        for i in 0..6 {
            g[(8 + i, j)] = jm[(5 + i, j)];
        }
    }
    let mut from_s = g * stats.frame_jacobian;
    for i in 0..9 {
        from_s[(5 + i, i)] += 1.0;
    }
    let mut cov_local = sandwich_over_slots(&from_s, &cov_s, &slot_param) + g * stats.cov * g.transpose();
    let slide = cov_local.fixed_view::<2, 2>(11, 11).into_owned();
    cov_local[(13, 13)] += slide_sag_variance(surface, &state.k3, &slide);
    let twist_variance = cov_local[(10, 10)];
    for (i, j, extra) in
        apex_moment_second_order(surface, &d, lambda, &slide).into_iter().chain(twist_moment_second_order(surface, &d, twist_variance))
    {
        cov_local[(i, j)] += extra;
    }

    // Minimal parameters and the map from local increments to them.
    let is5 = crate::patch::is_5dof(surface, boundary);
    let z_world = state.rot.column(2).into_owned();
    let r = if is5 {
        let rxy = r_xy_from_normal(&z_world);
        Vector3::new(rxy.x, rxy.y, 0.0)
    } else {
        log_map(&state.rot)
    };
    let curv = match surface {
        SurfaceType::CylindricParaboloid | SurfaceType::CircularCylinder => Vector2::new(0.0, state.k3.y),
        SurfaceType::CircularParaboloid | SurfaceType::Sphere => Vector2::new(state.k3.x, state.k3.x),
        SurfaceType::Plane => Vector2::zeros(),
        _ => state.k3.xy(),
    };
    let mut patch = Patch::new(surface, boundary, d, curv, r, state.c).map_err(|e| FitError::InvalidRequest(e.to_string()))?;
    let p = patch.dof();
    let nd = boundary.num_params();
    // T (p × 14, local layout → minimal parameters) row by row as its non-zeros (at most 3).
    let mut t: Vec<SparseRow> = (0..nd).map(|i| SparseRow::one(i, 1.0)).collect();
    match surface {
        SurfaceType::EllipticParaboloid | SurfaceType::HyperbolicParaboloid => {
            t.push(SparseRow::one(5, 1.0));
            t.push(SparseRow::one(6, 1.0));
        }
        SurfaceType::CylindricParaboloid | SurfaceType::CircularCylinder => t.push(SparseRow::one(6, 1.0)),
        SurfaceType::CircularParaboloid | SurfaceType::Sphere => t.push(SparseRow::one(5, 1.0)),
        SurfaceType::Plane => {}
    }
    let jr_inv = right_jacobian_inverse(&r);
    if is5 {
        // The final frame of 5-DoF types is R([r_xy 0]); the local tilt maps through eq 45.
        let a = r_xy_jacobian(&r) * jr_inv;
        for i in 0..2 {
            t.push(SparseRow::three(8, [a[(i, 0)], a[(i, 1)], a[(i, 2)]]));
        }
    } else {
        for i in 0..3 {
            t.push(SparseRow::three(8, [jr_inv[(i, 0)], jr_inv[(i, 1)], jr_inv[(i, 2)]]));
        }
    }
    for i in 0..3 {
        t.push(SparseRow::three(11, [state.rot[(i, 0)], state.rot[(i, 1)], state.rot[(i, 2)]]));
    }
    let cov = DMatrix::from_fn(p, p, |i, j| match (t.get(i), t.get(j)) {
        (Some(ti), Some(tj)) => ti.sandwich(&cov_local, tj),
        _ => f64::NAN,
    });
    if !cov.iter().all(|v| v.is_finite()) {
        return Err(FitError::Diverged("non-finite covariance"));
    }
    patch.covariance = (&cov + cov.transpose()) * 0.5;
    patch.residual = (normal.sampson_sq / points.len() as f64).sqrt();
    patch.num_points = points.len();
    Ok(patch)
}

/// `F C Fᵀ` for a `C` that is zero outside the slots with a free parameter (`E C_free Eᵀ`, eq 36's
/// information embedded): the products of nalgebra's `F * C * F.transpose()` (column by column, the
/// terms of every sum in slot order) without the terms that are exact zeros, so the non-zero entries
/// are bit-identical and the work scales with the number of free slots (3 for planes, 8 for general
/// paraboloids) instead of 9.
fn sandwich_over_slots(f: &SMatrix<f64, 14, 9>, c: &SMatrix<f64, 9, 9>, slot_param: &[Option<usize>; 9]) -> SMatrix<f64, 14, 14> {
    let mut slots = [0usize; 9];
    let mut n = 0;
    for (slot, param) in slot_param.iter().enumerate() {
        if param.is_some() {
            if let Some(s) = slots.get_mut(n) {
                *s = slot;
            }
            n += 1;
        }
    }
    let slots = slots.get(..n).unwrap_or(&[]);
    // F C, column b (free slots only): Σ_a F[:, a] C[a, b] over the free slots a.
    let mut fc = SMatrix::<f64, 14, 9>::zeros();
    for &b in slots {
        fc.set_column(b, &column_sum(slots, |a| f.column(a).into_owned(), |a| c[(a, b)]));
    }
    // (F C) Fᵀ, column j: Σ_b (F C)[:, b] F[j, b] over the free slots b.
    let mut out = SMatrix::<f64, 14, 14>::zeros();
    for j in 0..14 {
        out.set_column(j, &column_sum(slots, |b| fc.column(b).into_owned(), |b| f[(j, b)]));
    }
    out
}

/// `Σ_k column(slot_k) · weight(slot_k)` in slot order, the first term assigned rather than added
/// to zero (nalgebra's product summation order, so the result is bit-identical to the dense product).
fn column_sum(slots: &[usize], column: impl Fn(usize) -> SVector<f64, 14>, weight: impl Fn(usize) -> f64) -> SVector<f64, 14> {
    let mut sum = SVector::<f64, 14>::zeros();
    for (k, &slot) in slots.iter().enumerate() {
        if k == 0 {
            sum = column(slot) * weight(slot);
        } else {
            sum += column(slot) * weight(slot);
        }
    }
    sum
}

/// One row of a sparse matrix over the 14 local slots: up to three consecutive non-zeros.
struct SparseRow {
    start: usize,
    len: usize,
    values: [f64; 3],
}

impl SparseRow {
    fn one(col: usize, value: f64) -> Self {
        Self { start: col, len: 1, values: [value, 0.0, 0.0] }
    }

    fn three(start: usize, values: [f64; 3]) -> Self {
        Self { start, len: 3, values }
    }

    /// `self · C · otherᵀ`.
    fn sandwich(&self, c: &SMatrix<f64, 14, 14>, other: &Self) -> f64 {
        let mut sum = 0.0;
        for (a, alpha) in self.values.iter().take(self.len).enumerate() {
            for (b, beta) in other.values.iter().take(other.len).enumerate() {
                sum += alpha * beta * c[(self.start + a, other.start + b)];
            }
        }
        sum
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::SeedableRng;

    #[test]
    fn sag_second_moment_matches_monte_carlo() {
        use rand_distr::{Distribution, StandardNormal};
        let mut rng = rand::rngs::StdRng::seed_from_u64(21);
        let s = Matrix2::new(4e-5, 1.5e-5, 1.5e-5, 9e-5);
        let k3 = Vector3::new(-4.0, 9.0, 0.0);
        let l = s.cholesky().unwrap().l();
        let n = 200_000;
        let mut acc = 0.0;
        for _ in 0..n {
            let z = Vector2::new(StandardNormal.sample(&mut rng), StandardNormal.sample(&mut rng));
            let u = l * z;
            let sag: f64 = 0.5 * (k3.x * u.x * u.x + k3.y * u.y * u.y);
            acc += sag * sag;
        }
        let mc = acc / n as f64;
        let closed = slide_sag_variance(SurfaceType::HyperbolicParaboloid, &k3, &s);
        assert!((closed - mc).abs() < 0.02 * mc, "closed form {closed:e} vs Monte Carlo {mc:e}");
        assert_eq!(slide_sag_variance(SurfaceType::Plane, &k3, &s), 0.0);
    }
}

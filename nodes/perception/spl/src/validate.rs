//! Patch validation (J 3.3): Euclidean residual, coverage grid, curvature bounds; every rejection
//! names the failed test and by how much.

use crate::patch::{Patch, PatchQuery, PatchShape};
use nalgebra::{Vector2, Vector3};
use serde::{Deserialize, Serialize};

/// Validation thresholds (J 3.3; defaults are the paper's values).
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct ValidateConfig {
    /// Residual threshold T_r (m) on the RMS Euclidean distance (J 3.3.1: 0.01 m).
    pub residual_threshold: f64,
    /// Coverage cell pitch w_c (m) (J 3.3.2: 0.01 m).
    pub cell_size: f64,
    /// Inside-count factor ζ_i of T_i = ζ_i N_e (J eq 17: 0.8).
    pub zeta_inside: f64,
    /// Outside-count factor ζ_o of T_o = ζ_o N_e (J eq 17: 0.2).
    pub zeta_outside: f64,
    /// Bad-cell limit T_p as a fraction of N_p (J 3.3.2: 0.3).
    pub bad_cell_fraction: f64,
    /// Minimum curvature κ_min,t (m⁻¹) (J 3.3.3 / \[10\]: −13.6).
    pub curvature_min: f64,
    /// Maximum curvature κ_max,t (m⁻¹) (J 3.3.3 / \[10\]: 19.7).
    pub curvature_max: f64,
    /// Sub-samples per cell side for the cell ∩ boundary area A_i (approximation of the exact
    /// intersection area; 4 → 16 samples per cell).
    pub area_subsamples: usize,
    /// Least expected points per full cell, N_e of J eq 17. J's w_c = 0.01 m presumes dense data
    /// (a 640×480 frame puts tens of points in a 1 cm cell); on sparser data (a 5 mm birds-eye
    /// raycast gives about 4) the integer counts of a regular pixel grid alias against the cell
    /// grid and half the cells of a perfect fit come out "bad". The cell then grows to
    /// `w = max(w_c, √(A·N_min/N))` so that N_e ≥ N_min. 0 keeps w_c as it is.
    pub min_points_per_cell: f64,
    /// Counting tolerance k of J eq 16 in standard deviations: a cell is bad when
    /// `n_in < A_i/w² · T_i − k·√(A_i/w² · N_e)` or `n_out > (1 − A_i/w²) · T_o + k·√((1 − A_i/w²) · N_e)`.
    /// J's thresholds compare counts with their expectation; the counts of a correct fit scatter
    /// about it by ≈ √expected (Poisson; ±1 point per cell side on a regular pixel grid), which
    /// J's dense data (N_e ≫ 10) makes negligible and a sparse birds-eye raycast (N_e ≈ 8) does not.
    /// 0 is J's test as written.
    pub count_tolerance_sigmas: f64,
}

impl Default for ValidateConfig {
    fn default() -> Self {
        Self {
            residual_threshold: 0.01,
            cell_size: 0.01,
            zeta_inside: 0.8,
            zeta_outside: 0.2,
            bad_cell_fraction: 0.3,
            curvature_min: -13.6,
            curvature_max: 19.7,
            area_subsamples: 4,
            min_points_per_cell: 8.0,
            count_tolerance_sigmas: 1.0,
        }
    }
}

/// One test's outcome: the measured value against its threshold.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct TestResult {
    /// Whether the test passed.
    pub passed: bool,
    /// The measured value.
    pub value: f64,
    /// The threshold it was compared with.
    pub threshold: f64,
}

/// Result of [`validate_patch`].
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct Validation {
    /// RMS Euclidean point-to-patch distance (m) vs T_r (J eq 15).
    pub residual: TestResult,
    /// Number of bad coverage cells vs T_p (J eq 16–17).
    pub coverage: TestResult,
    /// Minimum principal curvature (m⁻¹) vs κ_min,t (passes if value ≥ threshold).
    pub curvature_min: TestResult,
    /// Maximum principal curvature (m⁻¹) vs κ_max,t (passes if value ≤ threshold).
    pub curvature_max: TestResult,
}

impl Validation {
    /// Whether the patch passed every test.
    pub fn is_valid(&self) -> bool {
        self.residual.passed && self.coverage.passed && self.curvature_ok()
    }

    /// Whether both curvature bounds hold.
    pub fn curvature_ok(&self) -> bool {
        self.curvature_min.passed && self.curvature_max.passed
    }

    /// One line per failed test, naming it and the amount by which it failed.
    pub fn failures(&self) -> Vec<String> {
        let mut out = Vec::new();
        if !self.residual.passed {
            out.push(format!("residual {:.4} m > {:.4} m", self.residual.value, self.residual.threshold));
        }
        if !self.coverage.passed {
            out.push(format!("coverage: {:.0} bad cells > {:.1} allowed", self.coverage.value, self.coverage.threshold));
        }
        if !self.curvature_min.passed {
            out.push(format!("curvature {:.2} 1/m < {:.2} 1/m", self.curvature_min.value, self.curvature_min.threshold));
        }
        if !self.curvature_max.passed {
            out.push(format!("curvature {:.2} 1/m > {:.2} 1/m", self.curvature_max.value, self.curvature_max.threshold));
        }
        out
    }
}

/// Validate a fitted patch against its (full) neighbourhood points (J 3.3).
pub fn validate_patch(patch: &Patch, neighbourhood: &[Vector3<f64>], config: &ValidateConfig) -> Validation {
    // The points in the patch frame once (eq 4), for both the residual and the coverage grid.
    let query = PatchQuery::new(patch);
    let local: Vec<Vector3<f64>> = neighbourhood.iter().map(|q| query.to_local(q)).collect();
    let rho = residual_local(&query, &local);
    let residual = TestResult { passed: rho <= config.residual_threshold, value: rho, threshold: config.residual_threshold };
    let (bad, allowed) = coverage_bad_cells_local(patch, query.shape(), &local, config);
    let coverage = TestResult { passed: bad as f64 <= allowed, value: bad as f64, threshold: allowed };
    let (kmin, kmax) = principal_curvature_range(patch);
    Validation {
        residual,
        coverage,
        curvature_min: TestResult { passed: kmin >= config.curvature_min, value: kmin, threshold: config.curvature_min },
        curvature_max: TestResult { passed: kmax <= config.curvature_max, value: kmax, threshold: config.curvature_max },
    }
}

/// Residual `ρ = RMS ‖q_i − p_i‖` with `p_i` the closest point on the bounded patch (J eq 15).
/// Infinite for an empty or non-finite neighbourhood.
pub fn residual(patch: &Patch, points: &[Vector3<f64>]) -> f64 {
    let query = PatchQuery::new(patch);
    let local: Vec<Vector3<f64>> = points.iter().map(|q| query.to_local(q)).collect();
    residual_local(&query, &local)
}

/// [`residual`] of points already in the patch frame.
fn residual_local(query: &PatchQuery, local: &[Vector3<f64>]) -> f64 {
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

/// `(min, max)` principal curvature of the patch (J 3.3.3).
pub fn principal_curvature_range(patch: &Patch) -> (f64, f64) {
    let k = patch.curvatures;
    match patch.surface {
        crate::patch::SurfaceType::CylindricParaboloid | crate::patch::SurfaceType::CircularCylinder => (k.y.min(0.0), k.y.max(0.0)),
        _ => (k.x.min(k.y), k.x.max(k.y)),
    }
}

/// Cell pitch of the coverage grid: J's w_c, grown so that a full cell expects at least
/// `min_points_per_cell` of the `n` points spread over `area` (see [`ValidateConfig`]).
pub fn coverage_cell_size(area: f64, n: usize, config: &ValidateConfig) -> f64 {
    let wc = config.cell_size;
    let per_cell = config.min_points_per_cell;
    if per_cell.is_nan() || per_cell <= 0.0 || n == 0 || area.is_nan() || area <= 0.0 {
        return wc;
    }
    wc.max((area * config.min_points_per_cell / n as f64).sqrt())
}

/// Coverage test of J eq 16–17: returns `(bad cells, T_p)`. The grid of pitch w_c covers the
/// projected boundary and the projected points (limited to 3× the boundary box).
pub fn coverage_bad_cells(patch: &Patch, points: &[Vector3<f64>], config: &ValidateConfig) -> (usize, f64) {
    let query = PatchQuery::new(patch);
    let local: Vec<Vector3<f64>> = points.iter().map(|q| query.to_local(q)).collect();
    coverage_bad_cells_local(patch, query.shape(), &local, config)
}

/// [`coverage_bad_cells`] of points already in the patch frame.
fn coverage_bad_cells_local(patch: &Patch, shape: &PatchShape, local: &[Vector3<f64>], config: &ValidateConfig) -> (usize, f64) {
    let area = patch.boundary_area();
    let wc = coverage_cell_size(area, local.len(), config);
    let n_p = area / (wc * wc);
    let allowed = config.bad_cell_fraction * n_p;
    if local.is_empty() || n_p.is_nan() || n_p <= 0.0 || wc.is_nan() || wc <= 0.0 {
        return (usize::MAX, allowed);
    }
    let h = patch.boundary_half_extents();
    let limit = h * 3.0;
    // u = Π_xy X_r(q) (eq 16)
    let mut lo = -h;
    let mut hi = h;
    for q in local {
        let u = q.xy();
        if u.x.abs() <= limit.x && u.y.abs() <= limit.y {
            lo = lo.inf(&u);
            hi = hi.sup(&u);
        }
    }
    // Grid anchored at the patch centre so cells are symmetric about it.
    let i0 = (lo.x / wc).floor() as i64;
    let j0 = (lo.y / wc).floor() as i64;
    let nx = ((hi.x / wc).ceil() as i64 - i0).max(1) as usize;
    let ny = ((hi.y / wc).ceil() as i64 - j0).max(1) as usize;
    if nx.saturating_mul(ny) > 4_000_000 {
        return (usize::MAX, allowed);
    }
    // Per cell: [points inside the boundary, points outside]; on the stack for the usual few cells.
    let mut small = [[0u32; 2]; SMALL_GRID];
    let mut large = Vec::new();
    let counts: &mut [[u32; 2]] = if nx * ny <= SMALL_GRID {
        small.get_mut(..nx * ny).unwrap_or_default()
    } else {
        large.resize(nx * ny, [0u32; 2]);
        &mut large
    };
    for q in local {
        let u = q.xy();
        let ci = floor_to_i64(u.x / wc) - i0;
        let cj = floor_to_i64(u.y / wc) - j0;
        if ci < 0 || cj < 0 || ci >= nx as i64 || cj >= ny as i64 {
            continue;
        }
        let idx = cj as usize * nx + ci as usize;
        let side = if shape.contains_uv(&u) { 0 } else { 1 };
        if let Some(c) = counts.get_mut(idx) {
            c[side] += 1;
        }
    }
    let n_e = local.len() as f64 / n_p;
    let t_i = config.zeta_inside * n_e;
    let t_o = config.zeta_outside * n_e;
    let s = config.area_subsamples.max(1);
    let k = config.count_tolerance_sigmas.max(0.0);
    // Cells beyond the boundary's bounding box (by more than rounding) hold no boundary area:
    // every corner and sub-sample there is outside.
    let margin = 1e-9 * (h.x + h.y + wc);
    let mut bad = 0;
    for cj in 0..ny {
        for ci in 0..nx {
            let x0 = (i0 + ci as i64) as f64 * wc;
            let y0 = (j0 + cj as i64) as f64 * wc;
            let beyond_box = x0 > h.x + margin || x0 + wc < -h.x - margin || y0 > h.y + margin || y0 + wc < -h.y - margin;
            // A_i / w_c²: 1 if all corners are inside (convex boundary), else by sub-sampling.
            let corners_inside = !beyond_box
                && [(0.0, 0.0), (wc, 0.0), (0.0, wc), (wc, wc)].iter().all(|(dx, dy)| shape.contains_uv(&Vector2::new(x0 + dx, y0 + dy)));
            let frac = if beyond_box {
                0.0
            } else if corners_inside {
                1.0
            } else {
                let mut hits = 0;
                for a in 0..s {
                    let x = x0 + (a as f64 + 0.5) * wc / s as f64;
                    for b in 0..s {
                        let u = Vector2::new(x, y0 + (b as f64 + 0.5) * wc / s as f64);
                        if shape.contains_uv(&u) {
                            hits += 1;
                        }
                    }
                }
                hits as f64 / (s * s) as f64
            };
            let [ic, oc] = counts.get(cj * nx + ci).copied().unwrap_or([0, 0]);
            let (ic, oc) = (ic as f64, oc as f64);
            // J eq 16, with the counting tolerance.
            if ic < frac * t_i - k * (frac * n_e).sqrt() || oc > (1.0 - frac) * t_o + k * ((1.0 - frac) * n_e).sqrt() {
                bad += 1;
            }
        }
    }
    (bad, allowed)
}

/// Coverage grids of up to this many cells count on the stack (no allocation for the usual small grids).
const SMALL_GRID: usize = 64;

/// `x.floor() as i64` without the libm call (the baseline x86-64 target has no `roundsd`):
/// truncate, then step down for negative non-integers. Saturates like the cast.
#[inline(always)]
fn floor_to_i64(x: f64) -> i64 {
    let t = x as i64;
    if (t as f64) > x {
        t.saturating_sub(1)
    } else {
        t
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::patch::{BoundaryType, SurfaceType};
    use rand::{Rng, SeedableRng};

    fn disk(r: f64) -> Patch {
        Patch::new(SurfaceType::Plane, BoundaryType::Circle, vec![r], Vector2::zeros(), Vector3::zeros(), Vector3::new(0.0, 0.0, 1.0))
            .unwrap()
    }

    fn dense_disk(rng: &mut rand::rngs::StdRng, r: f64, n: usize) -> Vec<Vector3<f64>> {
        disk(r).sample_points(rng, n)
    }

    #[test]
    fn floor_to_i64_matches_the_cast_of_floor() {
        for x in [
            0.0,
            -0.0,
            0.5,
            -0.5,
            1.0,
            -1.0,
            2.999_999,
            -2.000_001,
            1e300,
            -1e300,
            f64::INFINITY,
            f64::NEG_INFINITY,
            f64::NAN,
            4.5e15 + 0.5,
            -4.5e15 - 0.5,
        ] {
            assert_eq!(floor_to_i64(x), x.floor() as i64, "{x}");
        }
    }

    #[test]
    fn good_patch_passes() {
        let mut rng = rand::rngs::StdRng::seed_from_u64(1);
        let pts = dense_disk(&mut rng, 0.1, 3000);
        let v = validate_patch(&disk(0.1), &pts, &ValidateConfig::default());
        assert!(v.is_valid(), "{:?}", v.failures());
        assert!(v.residual.value < 1e-9);
    }

    #[test]
    fn step_edge_fails_residual() {
        let mut rng = rand::rngs::StdRng::seed_from_u64(2);
        let mut pts = dense_disk(&mut rng, 0.1, 3000);
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
    }

    #[test]
    fn half_covered_neighbourhood_fails_coverage() {
        let mut rng = rand::rngs::StdRng::seed_from_u64(3);
        let pts: Vec<_> = dense_disk(&mut rng, 0.1, 6000).into_iter().filter(|p| p.x < -0.02).collect();
        let v = validate_patch(&disk(0.1), &pts, &ValidateConfig::default());
        assert!(v.residual.passed);
        assert!(!v.coverage.passed, "{v:?}");
        // Points spilling far outside the boundary also fail.
        let mut spill = dense_disk(&mut rng, 0.1, 3000);
        spill.extend((0..3000).map(|_| Vector3::new(rng.random_range(0.1..0.2), rng.random_range(-0.2..0.2), 1.0)));
        assert!(!validate_patch(&disk(0.1), &spill, &ValidateConfig::default()).coverage.passed);
    }

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
    }

    /// A perfect fit on a regular 6.4 mm point grid at an angle (a birds-eye raycast): J's fixed
    /// 1 cm cells see 1 to 4 points each and alias; the grown cells pass it, and still fail a
    /// half-covered disc.
    #[test]
    fn sparse_regular_grid_passes_with_grown_cells() {
        let r = 0.05;
        let pitch = 0.0064;
        let n = (r / pitch) as i64 + 2;
        let (s, c) = 0.3f64.sin_cos();
        let grid: Vec<_> = (-n..=n)
            .flat_map(|i| (-n..=n).map(move |j| (i as f64 * pitch + 0.0013, j as f64 * pitch + 0.0031)))
            .map(|(x, y)| Vector3::new(c * x - s * y, s * x + c * y, 0.0))
            .filter(|p| p.xy().norm() <= r)
            .collect();
        let patch = disk(r * 0.98);
        let fixed = ValidateConfig { min_points_per_cell: 0.0, count_tolerance_sigmas: 0.0, ..ValidateConfig::default() };
        let grown = ValidateConfig { count_tolerance_sigmas: 0.0, ..ValidateConfig::default() };
        assert!(coverage_cell_size(patch.boundary_area(), grid.len(), &grown) > 0.012);
        let (bad_fixed, allowed) = coverage_bad_cells(&patch, &grid, &fixed);
        assert!(bad_fixed as f64 > allowed, "{bad_fixed} bad of {allowed} allowed with 1 cm cells");
        assert!(validate_patch(&patch, &grid, &grown).coverage.passed);
        let half: Vec<_> = grid.iter().copied().filter(|p| p.x < 0.0).collect();
        assert!(!validate_patch(&patch, &half, &grown).coverage.passed);
    }

    #[test]
    fn empty_neighbourhood_is_invalid() {
        let v = validate_patch(&disk(0.1), &[], &ValidateConfig::default());
        assert!(!v.is_valid());
    }
}

//! Coverage evaluation (J 3.3.2): a grid of cells over the projected boundary; a cell is bad when
//! it holds too few points inside the boundary or too many outside (J eq 16–17).
//!
//! J's test presumes the points were gathered wherever the boundary reaches. A mapper's
//! neighbourhood is a ball of radius r about the seed, and the moment boundaries reach past it:
//! a rectangle of half sides λ√v = 0.98 r (IROS step 6) over the disc of data leaves its corners,
//! 18 % of its area, without a single point however flat the terrain. Given the ball
//! ([`SampledBall`]), a cell expects the neighbourhood's points only where the patch surface lies
//! inside it: `A_i` of eq 16 becomes the area of cell ∩ boundary ∩ ball, and `N_e` counts that
//! area. The boundary beyond the ball is judged on the points the camera has there (the foot
//! disc's column, gathered from the whole frame): a cell is bad when that part holds fewer column
//! points than ζ_i times the column's density inside the ball expects, so a corner the camera never
//! saw (a shadow, a hole, off the image) still fails the patch.

use super::ValidateConfig;
use crate::patch::{Patch, PatchQuery, PatchShape};
use nalgebra::{Vector2, Vector3};

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

/// The region the points were gathered from: a ball (centre in the points' frame, radius in m).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct SampledBall {
    pub centre: Vector3<f64>,
    pub radius: f64,
}

/// Coverage test of J eq 16–17: returns `(bad cells, T_p)`. The grid of pitch w_c covers the
/// projected boundary and the projected points (limited to 3× the boundary box).
pub fn coverage_bad_cells(patch: &Patch, points: &[Vector3<f64>], config: &ValidateConfig) -> (usize, f64) {
    let query = PatchQuery::new(patch);
    let local: Vec<Vector3<f64>> = points.iter().map(|q| query.to_local(q)).collect();
    coverage_bad_cells_local(patch, query.shape(), &local, None, config)
}

/// One cell of the coverage grid as J eq 16 judges it (for diagnostics: [`coverage_cells`]).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct CoverageCell {
    /// Lower corner of the cell in the patch's xy-plane (m) and its pitch w.
    pub x0: f64,
    pub y0: f64,
    pub pitch: f64,
    /// `A_i / w²`: the fraction of the cell inside the projected boundary.
    pub inside_fraction: f64,
    /// The fraction of the cell inside the projected boundary where the patch surface lies in the
    /// sampled ball (`inside_fraction` without a ball): the share that expects points.
    pub sampled_fraction: f64,
    /// Column points in the cell's boundary part beyond the ball.
    pub beyond_ball: u32,
    /// Points projected into the cell inside (`I_c`) and outside (`O_c`) the boundary.
    pub inside: u32,
    pub outside: u32,
    /// `N_e` of J eq 17 (expected points in a full cell).
    pub expected: f64,
    /// Bad by J eq 16's first clause (too few points inside) or its second (too many outside).
    pub too_few_inside: bool,
    pub too_many_outside: bool,
    /// Bad because the boundary beyond the ball holds too few column points.
    pub too_few_beyond_ball: bool,
}

/// Every cell of the coverage grid of [`coverage_bad_cells`], for diagnostics (empty when the test
/// cannot be evaluated: no points, a degenerate boundary).
/// `sampled`: the ball the points were gathered from and the foot column's points (see the module
/// doc), in the points' frame.
pub fn coverage_cells(
    patch: &Patch,
    points: &[Vector3<f64>],
    sampled: Option<(&SampledBall, &[Vector3<f64>])>,
    config: &ValidateConfig,
) -> Vec<CoverageCell> {
    let query = PatchQuery::new(patch);
    let local: Vec<Vector3<f64>> = points.iter().map(|q| query.to_local(q)).collect();
    let ball = sampled.map(|(ball, _)| SampledBall { centre: query.to_local(&ball.centre), ..*ball });
    let column: Vec<Vector3<f64>> = sampled.map(|(_, column)| column.iter().map(|q| query.to_local(q)).collect()).unwrap_or_default();
    let mut cells = Vec::new();
    coverage_scan_local(patch, query.shape(), &local, ball.as_ref().map(|b| (b, column.as_slice())), config, &mut |cell| cells.push(*cell));
    cells
}

/// [`coverage_bad_cells`] of points already in the patch frame (`sampled` too).
pub(super) fn coverage_bad_cells_local(
    patch: &Patch,
    shape: &PatchShape,
    local: &[Vector3<f64>],
    sampled: Option<(&SampledBall, &[Vector3<f64>])>,
    config: &ValidateConfig,
) -> (usize, f64) {
    coverage_scan_local(patch, shape, local, sampled, config, &mut |_| {})
}

/// Whether the patch surface above `u` lies inside the ball (patch frame).
#[inline(always)]
fn surface_in_ball(shape: &PatchShape, u: &Vector2<f64>, ball: &SampledBall) -> bool {
    shape.height(u).is_some_and(|(z, _)| (Vector3::new(u.x, u.y, z) - ball.centre).norm_squared() <= ball.radius * ball.radius)
}

/// The coverage grid of points in the patch frame: `(bad cells, T_p)`, each cell handed to `visit`.
#[inline(always)]
fn coverage_scan_local(
    patch: &Patch,
    shape: &PatchShape,
    local: &[Vector3<f64>],
    sampled: Option<(&SampledBall, &[Vector3<f64>])>,
    config: &ValidateConfig,
    visit: &mut impl FnMut(&CoverageCell),
) -> (usize, f64) {
    let (sampled, column) = match sampled {
        Some((ball, column)) => (Some(ball), column),
        None => (None, &[][..]),
    };
    let area = patch.boundary_area();
    let wc = coverage_cell_size(area, local.len(), config);
    let boundary_cells = area / (wc * wc);
    if local.is_empty() || boundary_cells.is_nan() || boundary_cells <= 0.0 || wc.is_nan() || wc <= 0.0 {
        return (usize::MAX, config.bad_cell_fraction * boundary_cells);
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
        return (usize::MAX, config.bad_cell_fraction * boundary_cells);
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
    // Per cell: [A_i / w², the part of it that expects points].
    let mut small_fractions = [[0f64; 2]; SMALL_GRID];
    let mut large_fractions = Vec::new();
    let fractions: &mut [[f64; 2]] = if nx * ny <= SMALL_GRID {
        small_fractions.get_mut(..nx * ny).unwrap_or_default()
    } else {
        large_fractions.resize(nx * ny, [0f64; 2]);
        &mut large_fractions
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
    // Per cell: column points inside the boundary [within the ball, beyond it].
    let mut small_column = [[0u32; 2]; SMALL_GRID];
    let mut large_column = Vec::new();
    let column_counts: &mut [[u32; 2]] = if nx * ny <= SMALL_GRID {
        small_column.get_mut(..nx * ny).unwrap_or_default()
    } else {
        large_column.resize(nx * ny, [0u32; 2]);
        &mut large_column
    };
    if let Some(ball) = sampled {
        for q in column {
            let u = q.xy();
            let ci = floor_to_i64(u.x / wc) - i0;
            let cj = floor_to_i64(u.y / wc) - j0;
            if ci < 0 || cj < 0 || ci >= nx as i64 || cj >= ny as i64 || !shape.contains_uv(&u) {
                continue;
            }
            let side = usize::from(!surface_in_ball(shape, &u, ball));
            if let Some(c) = column_counts.get_mut(cj as usize * nx + ci as usize).and_then(|c| c.get_mut(side)) {
                *c += 1;
            }
        }
    }
    let s = config.area_subsamples.max(1);
    // Cells beyond the boundary's bounding box (by more than rounding) hold no boundary area:
    // every corner and sub-sample there is outside.
    let margin = 1e-9 * (h.x + h.y + wc);
    let cell_corner = |ci: usize, cj: usize| ((i0 + ci as i64) as f64 * wc, (j0 + cj as i64) as f64 * wc);
    for cj in 0..ny {
        for ci in 0..nx {
            let (x0, y0) = cell_corner(ci, cj);
            let beyond_box = x0 > h.x + margin || x0 + wc < -h.x - margin || y0 > h.y + margin || y0 + wc < -h.y - margin;
            let corners = [(0.0, 0.0), (wc, 0.0), (0.0, wc), (wc, wc)].map(|(dx, dy)| Vector2::new(x0 + dx, y0 + dy));
            // A_i / w²: 1 if all corners are inside (convex boundary), else by sub-sampling; the
            // sampled part likewise (the ball's footprint on a patch surface is convex for planes
            // and nearly so within the curvature bounds).
            let corners_inside = !beyond_box && corners.iter().all(|u| shape.contains_uv(u));
            let corners_sampled = corners_inside && sampled.is_none_or(|ball| corners.iter().all(|u| surface_in_ball(shape, u, ball)));
            let frac = if beyond_box {
                [0.0, 0.0]
            } else if corners_sampled {
                [1.0, 1.0]
            } else {
                let (mut hits, mut sampled_hits) = (0, 0);
                for a in 0..s {
                    let x = x0 + (a as f64 + 0.5) * wc / s as f64;
                    for b in 0..s {
                        let u = Vector2::new(x, y0 + (b as f64 + 0.5) * wc / s as f64);
                        if corners_inside || shape.contains_uv(&u) {
                            hits += 1;
                            sampled_hits += usize::from(sampled.is_none_or(|ball| surface_in_ball(shape, &u, ball)));
                        }
                    }
                }
                let n = (s * s) as f64;
                [hits as f64 / n, sampled_hits as f64 / n]
            };
            if let Some(f) = fractions.get_mut(cj * nx + ci) {
                *f = frac;
            }
        }
    }
    // N_p: the cells' worth of boundary that expects the neighbourhood's points (J: the whole
    // boundary); the part beyond the ball is judged too when there are column points.
    let n_p = if sampled.is_some() { fractions.iter().map(|f| f[1]).sum::<f64>() } else { boundary_cells };
    let judged_beyond = sampled.is_some() && !column.is_empty();
    let allowed = config.bad_cell_fraction * if judged_beyond { fractions.iter().map(|f| f[0]).sum::<f64>() } else { n_p };
    if n_p <= 0.0 {
        return (usize::MAX, allowed);
    }
    let n_e = local.len() as f64 / n_p;
    // Column points per full cell, from their density inside the ball.
    let column_n_e = column_counts.iter().map(|c| f64::from(c[0])).sum::<f64>() / n_p;
    let t_i = config.zeta_inside * n_e;
    let t_o = config.zeta_outside * n_e;
    let k = config.count_tolerance_sigmas.max(0.0);
    let mut bad = 0;
    for cj in 0..ny {
        for ci in 0..nx {
            let (x0, y0) = cell_corner(ci, cj);
            let [frac, sampled_frac] = fractions.get(cj * nx + ci).copied().unwrap_or([0.0, 0.0]);
            let [ic, oc] = counts.get(cj * nx + ci).copied().unwrap_or([0, 0]);
            let (ic, oc) = (ic as f64, oc as f64);
            // J eq 16, with the counting tolerance.
            let too_few_inside = ic < sampled_frac * t_i - k * (sampled_frac * n_e).sqrt();
            let too_many_outside = oc > (1.0 - frac) * t_o + k * ((1.0 - frac) * n_e).sqrt();
            let beyond_frac = (frac - sampled_frac).max(0.0);
            let beyond = column_counts.get(cj * nx + ci).map_or(0, |c| c[1]);
            let too_few_beyond_ball = judged_beyond
                && beyond_frac > 0.0
                && f64::from(beyond) < beyond_frac * config.zeta_inside * column_n_e - k * (beyond_frac * column_n_e).sqrt();
            if too_few_inside || too_many_outside || too_few_beyond_ball {
                bad += 1;
            }
            visit(&CoverageCell {
                x0,
                y0,
                pitch: wc,
                inside_fraction: frac,
                sampled_fraction: sampled_frac,
                beyond_ball: beyond,
                inside: ic as u32,
                outside: oc as u32,
                expected: n_e,
                too_few_inside,
                too_many_outside,
                too_few_beyond_ball,
            });
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
    use crate::validate::tests::disk;
    use crate::validate::validate_patch;
    use rand::{Rng, SeedableRng};

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
    fn half_covered_neighbourhood_fails_coverage() {
        let mut rng = rand::rngs::StdRng::seed_from_u64(3);
        let pts: Vec<_> = disk(0.1).sample_points(&mut rng, 6000).into_iter().filter(|p| p.x < -0.02).collect();
        let v = validate_patch(&disk(0.1), &pts, &ValidateConfig::default());
        assert!(v.residual.passed);
        assert!(!v.coverage.passed, "{v:?}");
        // Points spilling far outside the boundary also fail.
        let mut spill = disk(0.1).sample_points(&mut rng, 3000);
        spill.extend((0..3000).map(|_| Vector3::new(rng.random_range(0.1..0.2), rng.random_range(-0.2..0.2), 1.0)));
        assert!(!validate_patch(&disk(0.1), &spill, &ValidateConfig::default()).coverage.passed);
    }

    /// A rectangle of half sides 0.98 r (IROS step 6 on disc data) over an r-ball's disc of points:
    /// its corners have no points by construction. J's test over the whole boundary counts them bad; judged
    /// within the ball it passes when the camera saw the corners (the column has points there) and
    /// fails when it did not, and a half-covered disc still fails.
    #[test]
    fn a_rectangle_over_the_ball_is_judged_inside_the_ball_and_on_the_column_beyond() {
        use crate::patch::{BoundaryType, SurfaceType};
        use nalgebra::Vector2;
        let r = 0.05;
        let rect = Patch::new(
            SurfaceType::Plane,
            BoundaryType::Rectangle,
            vec![0.98 * r, 0.98 * r],
            Vector2::zeros(),
            Vector3::zeros(),
            Vector3::zeros(),
        )
        .unwrap();
        let grid = |keep: &dyn Fn(f64, f64) -> bool| -> Vec<Vector3<f64>> {
            (-40..=40)
                .flat_map(|i| (-40..=40).map(move |j| (f64::from(i) * 0.0021 + 0.0003, f64::from(j) * 0.0021 - 0.0007)))
                .filter(|&(x, y)| keep(x, y))
                .map(|(x, y)| Vector3::new(x, y, 0.0))
                .collect()
        };
        let disc = grid(&|x, y| x * x + y * y <= r * r);
        let square = grid(&|x, y| x.abs() <= r && y.abs() <= r);
        let ball = SampledBall { centre: Vector3::zeros(), radius: r };
        let config = ValidateConfig::default();
        // Over the whole boundary the corner cells come out bad: 22 of 96 on this ideal grid, three
        // quarters of J's 30 % allowance before any noise or hole.
        let (whole, allowed) = coverage_bad_cells(&rect, &disc, &config);
        assert!(whole as f64 > 0.7 * allowed, "whole boundary: {whole} bad of {allowed} allowed");
        let judge = |points: &[Vector3<f64>], column: &[Vector3<f64>]| {
            let query = PatchQuery::new(&rect);
            coverage_bad_cells_local(&rect, query.shape(), points, Some((&ball, column)), &config)
        };
        let (bad, allowed) = judge(&disc, &square);
        assert!(3 * bad < whole && bad as f64 <= allowed, "corners seen: {bad} bad of {allowed} allowed");
        let (bad, allowed) = judge(&disc, &disc);
        assert!(bad as f64 > allowed, "corners unseen: {bad} bad of {allowed} allowed");
        let half: Vec<_> = disc.iter().copied().filter(|p| p.x < 0.0).collect();
        let half_square: Vec<_> = square.iter().copied().filter(|p| p.x < 0.0).collect();
        let (bad, allowed) = judge(&half, &half_square);
        assert!(bad as f64 > allowed, "half covered: {bad} bad of {allowed} allowed");
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
}

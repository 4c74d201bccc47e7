//! How far the points of a pixel's foot window lie off a plane, and off the quadric that fits them
//! best: RMS distances from summed-area tables of the points and their moments.
//!
//! J's DoN (step 6.4) compares the normals of two windows; a surface whose normals agree can still
//! be a step of a few centimetres or a tight bump, which the fit then drapes (J 3.3's curvature
//! limit) or the foot disc straddles (the foothold edge test). The spread of the window's points
//! about their plane says so before any patch is fitted: for a paraboloid of curvature κ over a disc
//! of radius r it is `κ r² / √48` (7 mm at J's κ_max = 19.7 m⁻¹ and r = 5 cm), over the square of half
//! side r the saliency's foot window covers `κ r² √(2/45)` (10.4 mm), and a step of height h
//! through a window's middle gives about h/2 about the window's mean along the levels' normal (less
//! along a normal tilted towards the step, as the saliency's coarse one is).
//!
//! A smooth bump within κ_max is a foothold all the same (a rock's top), and the plane cannot tell
//! it from a step. A quadric can: the least-squares `z = c + a·(x, y) + (x, y) H (x, y)ᵀ / 2` over the
//! window (x, y across the view, z along it) leaves a bump of any curvature nothing, while a step
//! of height h through the window's middle leaves h/4 (the step is odd and the quadratic terms
//! even, so only the slope takes some of it: half of the plane's h/2), and less where it crosses
//! the window nearer its side. The eigenvalues of H are the bump's principal curvatures
//! (exactly at a top seen straight on; sloped surfaces read higher, so a limit on them is strict).

use nalgebra::{Matrix3, Matrix5, Vector3, Vector5};
use rayon::prelude::*;

use patchwalk_fusion::camera::{DepthImage, Intrinsics};

/// Summed-area table (`(width + 1) × (height + 1)`, row 0 and column 0 zero) of `channels(p)` over
/// the back-projected points of D, written into `sums` (its memory reused from the last frame:
/// every entry is written, so it is neither reallocated nor zeroed first); invalid pixels add
/// nothing. The per-row prefix sums run in parallel; each entry is then `above + row prefix`, the
/// same additions in the same order as a sequential pass.
pub(crate) fn summed_area_table<const C: usize>(
    depth: &DepthImage,
    intrinsics: &Intrinsics,
    channels: impl Fn(&Vector3<f64>) -> [f64; C] + Sync,
    sums: &mut Vec<[f64; C]>,
) {
    let (width, height) = (depth.width, depth.height);
    let stride = width + 1;
    if depth.depth_m.len() != width * height {
        // A malformed image: every entry its rows do not reach stays zero, as in a new table.
        sums.clear();
    }
    sums.resize(stride * (height + 1), [0.0; C]);
    if let Some(first_row) = sums.get_mut(..stride) {
        first_row.fill([0.0; C]);
    }
    sums.par_chunks_mut(stride).skip(1).zip(depth.depth_m.par_chunks(width.max(1))).enumerate().for_each(|(v, (out, src))| {
        let mut row = [0.0f64; C];
        if let Some(first) = out.first_mut() {
            *first = row;
        }
        for (u, (o, &z)) in out.iter_mut().skip(1).zip(src).enumerate() {
            let z = f64::from(z);
            if z.is_finite() {
                let c = channels(&intrinsics.back_project(u as f64, v as f64, z));
                for (r, c) in row.iter_mut().zip(c) {
                    *r += c;
                }
            }
            *o = row;
        }
    });
    for v in 1..height {
        let (done, rest) = sums.split_at_mut((v + 1) * stride);
        let (above, row) = (&done[v * stride..], &mut rest[..stride]);
        for (r, a) in row.iter_mut().zip(above) {
            for (r, a) in r.iter_mut().zip(a) {
                *r += a;
            }
        }
    }
}

/// Points (x, y, z, count) and second moments (xx, xy, xz, yy, yz, zz) of D, summed; for quadrics
/// also the third and fourth moments of (x, y) and z·(xx, xy, yy).
#[derive(Debug, Clone, Default)]
pub struct WindowMoments {
    width: usize,
    height: usize,
    sums: Vec<[f64; 10]>,
    /// xxx, xxy, xyy, yyy, xxxx, xxxy, xxyy, xyyy, yyyy, zxx, zxy, zyy (built by `with_quadrics`).
    higher: Option<Vec<[f64; 12]>>,
}

/// The least-squares quadric of a foot window ([`WindowMoments::quadric`]).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct WindowQuadric {
    /// RMS distance (m, along the view) of the window's points from the quadric.
    pub rms_m: f64,
    /// The larger magnitude of the eigenvalues of H, the principal curvatures at a top (m⁻¹).
    pub curvature_max: f64,
}

impl WindowMoments {
    /// The sums planes need ([`WindowMoments::rms_off_plane`]).
    pub fn new(depth: &DepthImage, intrinsics: &Intrinsics) -> Self {
        let mut moments = Self::default();
        moments.rebuild(depth, intrinsics, false);
        moments
    }

    /// The sums planes and quadrics need ([`WindowMoments::quadric`]), the two tables side by side.
    pub fn with_quadrics(depth: &DepthImage, intrinsics: &Intrinsics) -> Self {
        let mut moments = Self::default();
        moments.rebuild(depth, intrinsics, true);
        moments
    }

    /// [`WindowMoments::new`] (or, with `quadrics`, [`WindowMoments::with_quadrics`]) of another
    /// frame, in the memory of this one's tables.
    pub fn rebuild(&mut self, depth: &DepthImage, intrinsics: &Intrinsics, quadrics: bool) {
        (self.width, self.height) = (depth.width, depth.height);
        let higher = if quadrics { Some(self.higher.get_or_insert_with(Vec::new)) } else { None };
        rayon::join(
            || plane_sums(depth, intrinsics, &mut self.sums),
            || {
                if let Some(higher) = higher {
                    summed_area_table(
                        depth,
                        intrinsics,
                        |p| {
                            let (x, y, z) = (p.x, p.y, p.z);
                            let (xx, xy, yy) = (x * x, x * y, y * y);
                            [xx * x, xx * y, x * yy, yy * y, xx * xx, xx * xy, xx * yy, xy * yy, yy * yy, z * xx, z * xy, z * yy]
                        },
                        higher,
                    );
                }
            },
        );
        if !quadrics {
            self.higher = None;
        }
    }

    /// The image rectangle `[u0, u1) × [v0, v1)` of the window `[u − half, u + half]²` clipped to
    /// the image, if not empty.
    fn window(&self, u: usize, v: usize, half: usize) -> Option<[usize; 4]> {
        let (u0, u1) = (u.saturating_sub(half), (u + half + 1).min(self.width));
        let (v0, v1) = (v.saturating_sub(half), (v + half + 1).min(self.height));
        (u0 < u1 && v0 < v1).then_some([u0, u1, v0, v1])
    }

    /// A table's sums over the rectangle `[u0, u1, v0, v1]` of [`WindowMoments::window`].
    fn box_sums<const C: usize>(&self, table: &[[f64; C]], [u0, u1, v0, v1]: [usize; 4]) -> [f64; C] {
        let stride = self.width + 1;
        let at = |r: usize, c: usize| table.get(r * stride + c).copied().unwrap_or([0.0; C]);
        let (a, b, c, d) = (at(v1, u1), at(v1, u0), at(v0, u1), at(v0, u0));
        std::array::from_fn(|i| a[i] - b[i] - c[i] + d[i])
    }

    /// RMS distance (m) of the valid points of the window `[u − half, u + half]²` (clipped to the
    /// image) from the plane through their mean with unit normal `normal`; `None` with fewer than
    /// `min_points` points.
    pub fn rms_off_plane(&self, u: usize, v: usize, half: usize, normal: &Vector3<f64>, min_points: f64) -> Option<f64> {
        let s = self.box_sums(&self.sums, self.window(u, v, half)?);
        let n = s[3];
        if n.is_nan() || n < min_points.max(3.0) {
            return None;
        }
        let mean = Vector3::new(s[0], s[1], s[2]) / n;
        let second = Matrix3::new(s[4], s[5], s[6], s[5], s[7], s[8], s[6], s[8], s[9]) / n;
        let variance = normal.dot(&(second * normal)) - normal.dot(&mean).powi(2);
        Some(variance.max(0.0).sqrt())
    }

    /// The least-squares quadric `z(x, y)` of the valid points of the window `[u − half, u + half]²`
    /// (clipped to the image): its RMS residual and curvature. `None` without the quadric tables
    /// ([`WindowMoments::with_quadrics`]), with fewer than `min_points` points, or when the points
    /// do not determine a quadric (all on a line).
    pub fn quadric(&self, u: usize, v: usize, half: usize, min_points: f64) -> Option<WindowQuadric> {
        let window = self.window(u, v, half)?;
        let s = self.box_sums(&self.sums, window);
        let h = self.box_sums(self.higher.as_deref()?, window);
        let n = s[3];
        if n.is_nan() || n < min_points.max(6.0) {
            return None;
        }
        // Mean moments E[x^k y^l] (k + l ≤ 4) and E[z x^k y^l] (k + l ≤ 2).
        let xy_moment = |k: usize, l: usize| -> f64 {
            let sum = match (k, l) {
                (0, 0) => n,
                (1, 0) => s[0],
                (0, 1) => s[1],
                (2, 0) => s[4],
                (1, 1) => s[5],
                (0, 2) => s[7],
                (3, 0) => h[0],
                (2, 1) => h[1],
                (1, 2) => h[2],
                (0, 3) => h[3],
                (4, 0) => h[4],
                (3, 1) => h[5],
                (2, 2) => h[6],
                (1, 3) => h[7],
                (0, 4) => h[8],
                _ => f64::NAN,
            };
            sum / n
        };
        let z_moment = |k: usize, l: usize| -> f64 {
            let sum = match (k, l) {
                (0, 0) => s[2],
                (1, 0) => s[6],
                (0, 1) => s[8],
                (2, 0) => h[9],
                (1, 1) => h[10],
                (0, 2) => h[11],
                _ => f64::NAN,
            };
            sum / n
        };
        let (mean_x, mean_y, mean_z) = (s[0] / n, s[1] / n, s[2] / n);
        // E[f · X^i Y^j] about the mean (X = x − x̄, Y = y − ȳ), by the binomial expansion.
        let central = |moment: &dyn Fn(usize, usize) -> f64, i: usize, j: usize| -> f64 {
            let mut sum = 0.0;
            for k in 0..=i {
                for l in 0..=j {
                    sum += binomial(i, k) * binomial(j, l) * moment(k, l) * (-mean_x).powi((i - k) as i32) * (-mean_y).powi((j - l) as i32);
                }
            }
            sum
        };
        // Basis X, Y, X², XY, Y² with the constant taken out by centring: covariances.
        const BASIS: [(usize, usize); 5] = [(1, 0), (0, 1), (2, 0), (1, 1), (0, 2)];
        let basis_mean = BASIS.map(|(i, j)| central(&xy_moment, i, j));
        let covariance =
            Matrix5::from_fn(|a, b| central(&xy_moment, BASIS[a].0 + BASIS[b].0, BASIS[a].1 + BASIS[b].1) - basis_mean[a] * basis_mean[b]);
        let with_z = Vector5::from_fn(|a, _| central(&z_moment, BASIS[a].0, BASIS[a].1) - mean_z * basis_mean[a]);
        let coefficients = covariance.cholesky()?.solve(&with_z);
        let variance_z = s[9] / n - mean_z * mean_z;
        let rms_m = (variance_z - with_z.dot(&coefficients)).max(0.0).sqrt();
        // H = [[2 c_xx, c_xy], [c_xy, 2 c_yy]]: eigenvalues t ± √(t² − det) with t = tr/2.
        let (hxx, hxy, hyy) = (2.0 * coefficients[2], coefficients[3], 2.0 * coefficients[4]);
        let half_trace = 0.5 * (hxx + hyy);
        let spread = (0.25 * (hxx - hyy).powi(2) + hxy * hxy).sqrt();
        let curvature_max = (half_trace.abs() + spread).max(0.0);
        (rms_m.is_finite() && curvature_max.is_finite()).then_some(WindowQuadric { rms_m, curvature_max })
    }
}

/// The summed-area table of the points and their second moments, into `sums`.
fn plane_sums(depth: &DepthImage, intrinsics: &Intrinsics, sums: &mut Vec<[f64; 10]>) {
    summed_area_table(depth, intrinsics, |p| [p.x, p.y, p.z, 1.0, p.x * p.x, p.x * p.y, p.x * p.z, p.y * p.y, p.y * p.z, p.z * p.z], sums);
}

/// The binomial coefficient C(n, k) for the small n of the moments (≤ 4).
fn binomial(n: usize, k: usize) -> f64 {
    (1..=k).fold(1.0, |c, i| c * (n + 1 - i) as f64 / i as f64)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::saliency::tests::{render, small_camera};

    #[test]
    fn a_plane_is_flat_and_a_step_is_not() {
        // Looking straight down at a floor 1 m away; a 3 cm step at x = 0.
        let intrinsics = small_camera();
        let floor = render(&intrinsics, |p| 1.0 - p.z);
        let step = render(&intrinsics, |p| if p.x < 0.0 { 0.97 - p.z } else { 1.0 - p.z });
        let n = Vector3::new(0.0, 0.0, -1.0);
        let half = 7;
        let flat = WindowMoments::new(&floor, &intrinsics);
        let rms = flat.rms_off_plane(80, 60, half, &n, 10.0).unwrap();
        assert!(rms < 1e-5, "{rms}");
        let stepped = WindowMoments::new(&step, &intrinsics);
        // The window centred on the step: half its points 3 cm above the other half, RMS 1.5 cm.
        let rms = stepped.rms_off_plane(80, 60, half, &n, 10.0).unwrap();
        assert!((rms - 0.015).abs() < 0.002, "{rms}");
        // A window clear of the step is flat again.
        let rms = stepped.rms_off_plane(40, 60, half, &n, 10.0).unwrap();
        assert!(rms < 1e-5, "{rms}");
        // Off the image: no points.
        assert!(flat.rms_off_plane(500, 500, half, &n, 10.0).is_none());
    }

    #[test]
    fn a_paraboloid_spreads_as_its_curvature() {
        // z = 1 − κ/2 (x² + y²) seen from above: the tables' RMS equals the one computed point
        // by point over the same window.
        let intrinsics = small_camera();
        let kappa = 20.0;
        let depth = render(&intrinsics, |p| 1.0 - kappa / 2.0 * (p.x * p.x + p.y * p.y) - p.z);
        let moments = WindowMoments::new(&depth, &intrinsics);
        let half = 7;
        let (u, v) = (80usize, 60usize);
        let mut points = Vec::new();
        for y in v - half..=v + half {
            for x in u - half..=u + half {
                if let Some(z) = depth.get(x, y) {
                    points.push(intrinsics.back_project(x as f64, y as f64, f64::from(z)));
                }
            }
        }
        let n = Vector3::new(0.0, 0.0, -1.0);
        let mean = points.iter().map(|p| n.dot(p)).sum::<f64>() / points.len() as f64;
        let expected = (points.iter().map(|p| (n.dot(p) - mean).powi(2)).sum::<f64>() / points.len() as f64).sqrt();
        let rms = moments.rms_off_plane(u, v, half, &n, 10.0).unwrap();
        assert!(expected > 1e-3 && (rms - expected).abs() < 1e-5, "{rms} vs {expected}");
    }

    /// Least-squares quadric of the window's points computed point by point (the reference).
    fn quadric_by_points(depth: &DepthImage, intrinsics: &Intrinsics, u: usize, v: usize, half: usize) -> (f64, f64) {
        let mut points = Vec::new();
        for y in v - half..=v + half {
            for x in u - half..=u + half {
                if let Some(z) = depth.get(x, y) {
                    points.push(intrinsics.back_project(x as f64, y as f64, f64::from(z)));
                }
            }
        }
        let design = nalgebra::DMatrix::from_fn(points.len(), 6, |r, c| {
            let p = points[r];
            [1.0, p.x, p.y, p.x * p.x, p.x * p.y, p.y * p.y][c]
        });
        let z = nalgebra::DVector::from_fn(points.len(), |r, _| points[r].z);
        let coefficients = design.clone().svd(true, true).solve(&z, 1e-15).unwrap();
        let rms = ((&design * &coefficients - &z).norm_squared() / points.len() as f64).sqrt();
        let hessian = nalgebra::Matrix2::new(2.0 * coefficients[3], coefficients[4], coefficients[4], 2.0 * coefficients[5]);
        let curvature = hessian.symmetric_eigenvalues().iter().fold(0.0f64, |m, e| m.max(e.abs()));
        (rms, curvature)
    }

    #[test]
    fn the_tables_quadric_is_the_least_squares_quadric() {
        // A cubic, tilted surface off the image centre: the quadric leaves a residual, and the
        // moments about the window's mean (from tables of raw moments) must match the direct fit.
        let intrinsics = small_camera();
        let depth = render(&intrinsics, |p| 1.0 + 0.2 * p.x - 0.1 * p.y + 6.0 * p.x * p.x - 3.0 * p.x * p.y + 40.0 * p.x.powi(3) - p.z);
        let moments = WindowMoments::with_quadrics(&depth, &intrinsics);
        for (u, v, half) in [(80, 60, 7), (100, 45, 9), (60, 75, 5)] {
            let q = moments.quadric(u, v, half, 10.0).unwrap();
            let (rms, curvature) = quadric_by_points(&depth, &intrinsics, u, v, half);
            assert!(rms > 1e-5 && (q.rms_m - rms).abs() < 1e-3 * rms + 1e-8, "({u}, {v}): {} vs {rms}", q.rms_m);
            assert!((q.curvature_max - curvature).abs() < 1e-6 * curvature, "({u}, {v}): {} vs {curvature}", q.curvature_max);
        }
        // Without the quadric tables there is no quadric.
        assert!(WindowMoments::new(&depth, &intrinsics).quadric(80, 60, 7, 10.0).is_none());
    }

    #[test]
    fn a_quadric_explains_a_bump_but_not_a_step() {
        // Seen from 1 m: a κ = 15 m⁻¹ bump (its top at the window centre) spreads 7.9 mm off its
        // plane and nothing off its quadric, whose curvature is the bump's; a 3 cm step through
        // the window's middle leaves h/4.
        let intrinsics = small_camera();
        let kappa = 15.0;
        let bump = render(&intrinsics, |p| 1.0 - kappa / 2.0 * (p.x * p.x + p.y * p.y) - p.z);
        let step = render(&intrinsics, |p| if p.x < 0.0 { 0.97 - p.z } else { 1.0 - p.z });
        let (u, v, half) = (80, 60, 7);
        let n = Vector3::new(0.0, 0.0, -1.0);
        let bump_moments = WindowMoments::with_quadrics(&bump, &intrinsics);
        assert!(bump_moments.rms_off_plane(u, v, half, &n, 10.0).unwrap() > 0.005);
        let q = bump_moments.quadric(u, v, half, 10.0).unwrap();
        assert!(q.rms_m < 1e-4, "{q:?}");
        assert!((q.curvature_max - kappa).abs() < 0.05 * kappa, "{q:?}");
        let q = WindowMoments::with_quadrics(&step, &intrinsics).quadric(u, v, half, 10.0).unwrap();
        assert!((q.rms_m - 0.03 / 4.0).abs() < 0.0015, "{q:?}");
    }
}

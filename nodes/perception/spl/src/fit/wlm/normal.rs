//! The normal equations of the WLM objective (IROS eq 33–41): per point `F_i = f(q_i, p)/σ_i`
//! (eq 35) with `σ_i² = ∇_q f Σ_i ∇_q fᵀ` (eq 34) and its gradient over the local increments with the
//! `∂σ/∂p` term of eq 36, summed as `χ²`, `H = Σ ∇F ∇Fᵀ`, `b = Σ ∇F F` over the free parameters of a
//! model. The points are packed in blocks of four (struct of arrays) and the per-point loop is
//! fixed-size and allocation-free; `point_terms` is the reference form of one point the tests
//! compare it with bit for bit.

use super::{Free, FreeMatrix, Local, Model, SurfaceState, MAX_FREE};
use nalgebra::{Matrix3, SMatrix, SVector, Vector3};

/// Per-point values of the WLM objective: `F`, `∇F` over the local slots, and the Sampson
/// (first-order Euclidean) distance `|f| / ‖∇_q f‖`. The reference form of one point: the passes
/// use [`block_terms`], which the tests check against it bit for bit.
#[cfg(test)]
pub(crate) fn point_terms(
    state: &SurfaceState,
    q_w: &Vector3<f64>,
    cov_w: &Matrix3<f64>,
    min_variance: f64,
    with_gradient: bool,
    weight_derivative: bool,
    with_sampson: bool,
) -> (f64, Local, f64) {
    let k = &state.k3;
    let q = state.rot.transpose() * (q_w - state.c);
    // a = K q_l − ẑ; ∂f/∂q_l = 2a (eq 39)
    let a = Vector3::new(k.x * q.x, k.y * q.y, k.z * q.z - 1.0);
    let f = k.x * q.x * q.x + k.y * q.y * q.y + k.z * q.z * q.z - 2.0 * q.z;
    let g_l = a * 2.0;
    let g_w = state.rot * g_l;
    let s_w = cov_w * g_w;
    let var_raw = g_w.dot(&s_w);
    let clamped = var_raw < min_variance;
    let var = if clamped { min_variance } else { var_raw };
    let sigma = var.sqrt();
    // One division per point; the LM loop only needs the Sampson distance at the end (`finish`).
    let inv_sigma = 1.0 / sigma;
    let raw_f = f * inv_sigma;
    let scale = DistanceScale::new(k.z, f);
    let big_f = raw_f * scale.h;
    let sampson = if with_sampson {
        let grad_norm = g_l.norm();
        if grad_norm > 0.0 {
            f.abs() / grad_norm
        } else {
            f.abs()
        }
    } else {
        0.0
    };
    if !with_gradient {
        return (big_f, Local::zeros(), sampson);
    }
    // ∂f/∂p (eq 40 in local increments): κ_j → q_j², δ → g_l × q_l, δc → −g_l
    let df_dd = g_l.cross(&q);
    let df = Local::from_column_slice(&[q.x * q.x, q.y * q.y, q.z * q.z, df_dd.x, df_dd.y, df_dd.z, -g_l.x, -g_l.y, -g_l.z]);
    if clamped || !weight_derivative {
        return (big_f, scale.gradient(df * inv_sigma, &df, k.z, f, raw_f), sampson);
    }
    // ∂σ²/∂p = 2 s_lᵀ Rᵀ ∂g_w/∂p (eq 41): κ_j → 4 s_j q_j, δ → 4(a × s + (K s) × q), δc → −4 K s
    let s = state.rot.transpose() * s_w;
    let ks = Vector3::new(k.x * s.x, k.y * s.y, k.z * s.z);
    let dv_dd = (a.cross(&s) + ks.cross(&q)) * 4.0;
    let dv = Local::from_column_slice(&[
        4.0 * s.x * q.x,
        4.0 * s.y * q.y,
        4.0 * s.z * q.z,
        dv_dd.x,
        dv_dd.y,
        dv_dd.z,
        -4.0 * ks.x,
        -4.0 * ks.y,
        -4.0 * ks.z,
    ]);
    // eq 36: ∂F/∂p = ∂f/∂p / σ − f ∂σ²/∂p / (2σ³)
    let w = raw_f / (2.0 * var);
    (big_f, scale.gradient(df * inv_sigma - dv * w, &df, k.z, f, raw_f), sampson)
}

/// The exact distance of spheres and cylinders (beyond IROS). Their implicit form (eq 22, 26) has
/// a quadratic term along the normal, `κ q_z²`, so `F = f / σ` with `σ` from `∇f` at the point
/// (eq 34) is the point's distance `e` to the surface only to first order: with `s = √(1 + κz f)`
/// (`s/|κ|` is the point's distance to the centre of curvature, `‖∇f‖ = 2s`) the distance is
/// `f / (1 + s)` and `F = e (1 − κ e / 2) / σ_e`. Noise along the normal then biases the fitted
/// surface by `−1.5 κ σ_e²` (0.15 mm for Kinect noise at 1 m and κ ≈ 5 m⁻¹, a quarter of the
/// offset's standard deviation for 150 points, and a bias that fusion does not average out).
/// `F̃ = F h`, `h = 2s / (1 + s)`, is the distance over its standard deviation exactly. For the
/// paraboloid forms (`κz = 0`) `h = 1`.
#[derive(Clone, Copy)]
struct DistanceScale {
    /// `h = 2s / (1 + s)`.
    h: f64,
    /// `dh/dx = 1 / (s (1 + s)²)` at `x = κz f`.
    dh: f64,
}

impl DistanceScale {
    #[inline(always)]
    fn new(kz: f64, f: f64) -> Self {
        if kz == 0.0 {
            return Self { h: 1.0, dh: 0.25 };
        }
        // 1 + κz f = (κ ρ)² ≥ 0 (ρ the distance to the centre of curvature); the floor keeps a
        // point at the centre itself finite.
        let s = (1.0 + kz * f).max(1e-12).sqrt();
        Self { h: 2.0 * s / (1.0 + s), dh: 1.0 / (s * (1.0 + s) * (1.0 + s)) }
    }

    /// `∂F̃/∂p = h ∂F/∂p + F h' ∂(κz f)/∂p` with `∂(κz f)/∂p = κz ∂f/∂p + f ∂κz/∂p` (local slots;
    /// κz is slot 2).
    #[inline(always)]
    fn gradient(&self, grad: Local, df: &Local, kz: f64, f: f64, raw_f: f64) -> Local {
        let w = raw_f * self.dh;
        let mut out = if kz == 0.0 { grad } else { grad * self.h + df * (kz * w) };
        out[2] += f * w;
        out
    }
}

/// Accumulated normal equations over the free parameters.
pub(crate) struct Normal {
    pub chi2: f64,
    pub h: FreeMatrix,
    pub b: Free,
    pub sampson_sq: f64,
}

/// One pass over the points: χ², `H = Σ ∇F ∇Fᵀ`, `b = Σ ∇F F` over the free parameters (eq 36;
/// the Gauss–Newton part of the Hessian). The Sampson sum is only formed if `with_sampson`.
pub(crate) fn accumulate(
    model: Model,
    state: &SurfaceState,
    set: &PointSet,
    min_variance: f64,
    weight_derivative: bool,
    with_sampson: bool,
) -> Normal {
    let run = Pass { state, set, min_variance, weight_derivative, with_sampson };
    // Each model's free parameters as sums of the local slots (the columns of `Model::embedding`),
    // so the per-point update is a rank-1 update of the (small) free matrix only.
    match model {
        Model::Plane => run.free::<3>(|g| SVector::from([g[3], g[4], g[8]])),
        Model::Paraboloid => run.free::<8>(|g| SVector::from([g[0], g[1], g[3], g[4], g[5], g[6], g[7], g[8]])),
        Model::CircularParaboloid => run.free::<6>(|g| SVector::from([g[0] + g[1], g[3], g[4], g[6], g[7], g[8]])),
        Model::CylindricParaboloid => run.free::<6>(|g| SVector::from([g[1], g[3], g[4], g[5], g[7], g[8]])),
        Model::Sphere => run.free::<4>(|g| SVector::from([g[0] + g[1] + g[2], g[3], g[4], g[8]])),
        Model::Cylinder => run.free::<5>(|g| SVector::from([g[1] + g[2], g[3], g[4], g[5], g[8]])),
    }
}

/// `χ² = Σ F_i²` (eq 33, 35) alone: the same per-point arithmetic and summation order as
/// [`accumulate`] (so the value is bit-identical), without the gradient and the rank-1 updates of
/// eq 36. LM uses it to accept or reject a trial step; most trials near convergence are rejected.
pub(crate) fn chi_square(state: &SurfaceState, set: &PointSet, min_variance: f64) -> f64 {
    chi_square_unless_above(state, set, min_variance, f64::INFINITY, 0.0)
}

/// [`chi_square`], or the first partial sum `s` with `s > base` and `s − base ≥ margin`. The terms
/// are non-negative and rounding is monotone, so χ² is then at least `s` and both `χ² ≤ base` and
/// `χ² − base < margin` are false, as for `s`: LM decides a trial step whose χ² rises by more than
/// the tolerance after a part of the points, with the outcome of the full sum.
pub(super) fn chi_square_unless_above(state: &SurfaceState, set: &PointSet, min_variance: f64, base: f64, margin: f64) -> f64 {
    let frame = Frame::new(state);
    let mut squares = [0.0; BLOCK];
    let mut chi2 = 0.0;
    for (chunk, len) in set.chunks() {
        block_terms(&frame, chunk, min_variance, |j, lane| squares[j] = lane.big_f * lane.big_f);
        for f2 in squares.iter().take(len) {
            chi2 += f2;
        }
        if chi2 > base && chi2 - base >= margin {
            return chi2;
        }
    }
    chi2
}

/// Inputs of one [`accumulate`] pass.
struct Pass<'a> {
    state: &'a SurfaceState,
    set: &'a PointSet,
    min_variance: f64,
    weight_derivative: bool,
    with_sampson: bool,
}

impl Pass<'_> {
    /// The pass with `M` free parameters; `project` maps the 9 local slots to them.
    #[inline(always)]
    fn free<const M: usize>(&self, project: impl Fn(&Local) -> SVector<f64, M>) -> Normal {
        let mut sums = Sums::<M>::new();
        // Per-point values block-wise in a vectorisable loop, then the sums in point order
        // (bit-identical to `point_terms`).
        let frame = Frame::new(self.state);
        let [kx, ky, kz] = frame.k;
        let mut fs = [0.0; BLOCK];
        let mut ds = [0.0; BLOCK];
        let mut gs = [SVector::<f64, M>::zeros(); BLOCK];
        for (chunk, len) in self.set.chunks() {
            block_terms(&frame, chunk, self.min_variance, |j, lane| {
                let ([qx, qy, qz], [gx, gy, gz], inv_sigma) = (lane.q, lane.g, lane.inv_sigma);
                fs[j] = lane.big_f;
                if self.with_sampson {
                    let grad_norm = (gx * gx + gy * gy + gz * gz).sqrt();
                    ds[j] = if grad_norm > 0.0 { lane.f.abs() / grad_norm } else { lane.f.abs() };
                }
                // ∂f/∂p (eq 40 in local increments): κ_j → q_j², δ → g_l × q_l, δc → −g_l
                let df = Local::from([qx * qx, qy * qy, qz * qz, gy * qz - gz * qy, gz * qx - gx * qz, gx * qy - gy * qx, -gx, -gy, -gz]);
                let grad = if self.weight_derivative && !lane.clamped {
                    // ∂σ²/∂p = 2 s_lᵀ Rᵀ ∂g_w/∂p (eq 41): κ_j → 4 s_j q_j, δ → 4(a × s + (K s) × q),
                    // δc → −4 K s, with a = g_l / 2; eq 36: ∂F/∂p = ∂f/∂p / σ − f ∂σ²/∂p / (2σ³)
                    let [sx, sy, sz] = lane.s;
                    let (ax, ay, az) = (kx * qx, ky * qy, kz * qz - 1.0);
                    let (ksx, ksy, ksz) = (kx * sx, ky * sy, kz * sz);
                    let dv = Local::from([
                        4.0 * sx * qx,
                        4.0 * sy * qy,
                        4.0 * sz * qz,
                        ((ay * sz - az * sy) + (ksy * qz - ksz * qy)) * 4.0,
                        ((az * sx - ax * sz) + (ksz * qx - ksx * qz)) * 4.0,
                        ((ax * sy - ay * sx) + (ksx * qy - ksy * qx)) * 4.0,
                        -4.0 * ksx,
                        -4.0 * ksy,
                        -4.0 * ksz,
                    ]);
                    let w = lane.raw_f / (2.0 * lane.var);
                    df * inv_sigma - dv * w
                } else {
                    df * inv_sigma
                };
                gs[j] = project(&lane.scale.gradient(grad, &df, kz, lane.f, lane.raw_f));
            });
            if len == BLOCK {
                sums.add_block(&fs, &gs, &ds);
            } else {
                for j in 0..len {
                    sums.add_point(fs[j], &gs[j], ds[j]);
                }
            }
        }
        sums.normal()
    }
}

/// Running sums of one [`accumulate`] pass over `M` free parameters, point by point in point order.
struct Sums<const M: usize> {
    /// Lower triangle of `H` (symmetric; mirrored by [`Sums::normal`]).
    h: SMatrix<f64, M, M>,
    b: SVector<f64, M>,
    chi2: f64,
    sampson_sq: f64,
}

impl<const M: usize> Sums<M> {
    fn new() -> Self {
        Self { h: SMatrix::zeros(), b: SVector::zeros(), chi2: 0.0, sampson_sq: 0.0 }
    }

    /// One point: `H += ∇F ∇Fᵀ`, `b += F ∇F` (eq 36), `χ² += F²`.
    #[inline(always)]
    fn add_point(&mut self, f: f64, g: &SVector<f64, M>, d: f64) {
        for c in 0..M {
            let gc = g[c];
            for r in c..M {
                self.h[(r, c)] += g[r] * gc;
            }
        }
        self.b.axpy(f, g, 1.0);
        self.chi2 += f * f;
        self.sampson_sq += d * d;
    }

    /// `BLOCK` points at once: every entry of `H` is loaded and stored once per block, and its
    /// terms are added in point order (the same sums as [`Sums::add_point`] point by point).
    #[inline(always)]
    fn add_block(&mut self, fs: &[f64; BLOCK], gs: &[SVector<f64, M>; BLOCK], ds: &[f64; BLOCK]) {
        for c in 0..M {
            for r in c..M {
                let mut h = self.h[(r, c)];
                for g in gs {
                    h += g[r] * g[c];
                }
                self.h[(r, c)] = h;
            }
        }
        for (g, f) in gs.iter().zip(fs) {
            self.b.axpy(*f, g, 1.0);
        }
        for (f, d) in fs.iter().zip(ds) {
            self.chi2 += f * f;
            self.sampson_sq += d * d;
        }
    }

    /// The normal equations over `MAX_FREE` slots (identity beyond `M`).
    fn normal(&self) -> Normal {
        let mut h = FreeMatrix::zeros();
        let mut b = Free::zeros();
        for c in 0..M {
            for r in c..M {
                h[(r, c)] = self.h[(r, c)];
                h[(c, r)] = self.h[(r, c)];
            }
            b[c] = self.b[c];
        }
        for r in M..MAX_FREE {
            h[(r, r)] = 1.0;
        }
        Normal { chi2: self.chi2, h, b, sampson_sq: self.sampson_sq }
    }
}

/// Points per chunk of [`PointSet`] and [`block_terms`].
const BLOCK: usize = 4;

/// The surface state as plain numbers for [`block_terms`].
struct Frame {
    /// `R` row-major.
    r: [[f64; 3]; 3],
    c: [f64; 3],
    k: [f64; 3],
}

impl Frame {
    fn new(state: &SurfaceState) -> Self {
        let m = &state.rot;
        Self {
            r: [[m[(0, 0)], m[(0, 1)], m[(0, 2)]], [m[(1, 0)], m[(1, 1)], m[(1, 2)]], [m[(2, 0)], m[(2, 1)], m[(2, 2)]]],
            c: [state.c.x, state.c.y, state.c.z],
            k: [state.k3.x, state.k3.y, state.k3.z],
        }
    }
}

/// One point's values of `point_terms`: what the χ², the gradient of eq 40 and the weight
/// derivative of eq 41 (formed by the caller) need.
struct Lane {
    /// `F = f / σ` (eq 35), scaled to the exact distance where that differs ([`DistanceScale`]).
    big_f: f64,
    /// `f / σ` unscaled.
    raw_f: f64,
    /// The scale to the exact distance (`F = raw_f · h`) and its derivative.
    scale: DistanceScale,
    /// `f` (eq 37).
    f: f64,
    inv_sigma: f64,
    /// `q_l` (eq 38).
    q: [f64; 3],
    /// `∂f/∂q_l` (eq 39).
    g: [f64; 3],
    /// `s_l = Rᵀ Σ_i R ∂f/∂q_l` (for the weight derivative, eq 41).
    s: [f64; 3],
    /// `σ²` (eq 34), clamped at the minimum variance.
    var: f64,
    /// Whether the clamp applied (then σ does not depend on the parameters).
    clamped: bool,
}

/// The per-point values of `point_terms` ([`Lane`]) for all `BLOCK` slots of a chunk (the padding
/// of the last chunk included; the caller ignores it), handed to `sink` with the slot index. The
/// arithmetic is that of `point_terms` operation by operation (nalgebra's `M v` is
/// `(m₀ v₀ + m₁ v₁) + m₂ v₂` per row, dot products likewise), so the results are bit-identical;
/// the fixed-length loop has no branches and vectorises when `sink` writes to arrays.
#[inline(always)]
fn block_terms(fr: &Frame, chunk: &Chunk, min_variance: f64, mut sink: impl FnMut(usize, &Lane)) {
    let [r0, r1, r2] = fr.r;
    let [kx, ky, kz] = fr.k;
    let [cx, cy, cz] = fr.c;
    let [xs, ys, zs, c0, c1, c2, c3, c4, c5, c6, c7, c8] = chunk;
    for j in 0..BLOCK {
        let (dx, dy, dz) = (xs[j] - cx, ys[j] - cy, zs[j] - cz);
        // q_l = Rᵀ(q − c) (eq 38)
        let qx = r0[0] * dx + r1[0] * dy + r2[0] * dz;
        let qy = r0[1] * dx + r1[1] * dy + r2[1] * dz;
        let qz = r0[2] * dx + r1[2] * dy + r2[2] * dz;
        // f (eq 37) and ∂f/∂q_l = 2(K q_l − ẑ) (eq 39)
        let (ax, ay, az) = (kx * qx, ky * qy, kz * qz - 1.0);
        let f = kx * qx * qx + ky * qy * qy + kz * qz * qz - 2.0 * qz;
        let (gx, gy, gz) = (ax * 2.0, ay * 2.0, az * 2.0);
        let gwx = r0[0] * gx + r0[1] * gy + r0[2] * gz;
        let gwy = r1[0] * gx + r1[1] * gy + r1[2] * gz;
        let gwz = r2[0] * gx + r2[1] * gy + r2[2] * gz;
        // σ² = ∇f Σ_i ∇fᵀ (eq 34), Σ_i column-major in c0..c8
        let swx = c0[j] * gwx + c3[j] * gwy + c6[j] * gwz;
        let swy = c1[j] * gwx + c4[j] * gwy + c7[j] * gwz;
        let swz = c2[j] * gwx + c5[j] * gwy + c8[j] * gwz;
        let var_raw = gwx * swx + gwy * swy + gwz * swz;
        let clamped = var_raw < min_variance;
        let var = if clamped { min_variance } else { var_raw };
        let inv_sigma = 1.0 / var.sqrt();
        // s_l = Rᵀ s_w
        let sx = r0[0] * swx + r1[0] * swy + r2[0] * swz;
        let sy = r0[1] * swx + r1[1] * swy + r2[1] * swz;
        let sz = r0[2] * swx + r1[2] * swy + r2[2] * swz;
        let raw_f = f * inv_sigma;
        let scale = DistanceScale::new(kz, f);
        sink(
            j,
            &Lane { big_f: raw_f * scale.h, raw_f, scale, f, inv_sigma, q: [qx, qy, qz], g: [gx, gy, gz], s: [sx, sy, sz], var, clamped },
        );
    }
}

/// `BLOCK` points: `[x, y, z, Σ (9 entries, column-major)]`, one array per value.
type Chunk = [[f64; BLOCK]; 12];

/// The fit points and their covariances as structure of arrays in chunks of `BLOCK` points,
/// built once per fit (every pass of [`accumulate`] and [`chi_square`] reads them). The last
/// chunk is padded with the origin and Σ = I.
pub(crate) struct PointSet {
    n: usize,
    chunks: Vec<Chunk>,
}

impl PointSet {
    pub(crate) fn new(points: &[Vector3<f64>], covs: &Covariances<'_>) -> Self {
        let mut pad = [[0.0; BLOCK]; 12];
        for k in [3, 7, 11] {
            pad[k] = [1.0; BLOCK];
        }
        let mut chunks = vec![pad; points.len().div_ceil(BLOCK)];
        for (i, q) in points.iter().enumerate() {
            let (Some(chunk), j) = (chunks.get_mut(i / BLOCK), i % BLOCK) else { break };
            let cov = covs.get(i);
            let [xs, ys, zs, cv @ ..] = chunk;
            (xs[j], ys[j], zs[j]) = (q.x, q.y, q.z);
            for (column, v) in cv.iter_mut().zip(cov.iter()) {
                column[j] = *v;
            }
        }
        Self { n: points.len(), chunks }
    }

    #[cfg(test)]
    fn len(&self) -> usize {
        self.n
    }

    /// The chunks with the number of real points in each.
    fn chunks(&self) -> impl Iterator<Item = (&Chunk, usize)> {
        self.chunks.iter().enumerate().map(move |(b, c)| (c, self.n.saturating_sub(b * BLOCK).min(BLOCK)))
    }
}

/// Point covariances: per point, or one constant matrix (no sensor model).
pub(crate) enum Covariances<'a> {
    PerPoint(&'a [Matrix3<f64>]),
    Constant(Matrix3<f64>),
}

impl Covariances<'_> {
    #[inline(always)]
    fn get(&self, i: usize) -> Matrix3<f64> {
        match self {
            Covariances::PerPoint(c) => c.get(i).copied().unwrap_or_else(Matrix3::identity),
            Covariances::Constant(c) => *c,
        }
    }
}

#[cfg(test)]
pub(super) mod tests {
    use super::*;

    #[test]
    fn gradient_matches_finite_differences() {
        let state = SurfaceState {
            k3: Vector3::new(3.0, -2.0, 1.5),
            rot: crate::geometry::exp_map(&Vector3::new(0.3, -0.4, 0.2)),
            c: Vector3::new(0.1, -0.2, 1.0),
        };
        let q = Vector3::new(0.15, -0.17, 1.02);
        let cov = Matrix3::new(2.0, 0.3, 0.1, 0.3, 1.0, 0.2, 0.1, 0.2, 5.0) * 1e-6;
        let (_, grad, _) = point_terms(&state, &q, &cov, 1e-20, true, true, true);
        for slot in 0..9 {
            let mut e = Local::zeros();
            e[slot] = 1e-7;
            let (fp, _, _) = point_terms(&state.apply(&e), &q, &cov, 1e-20, false, true, false);
            let (fm, _, _) = point_terms(&state.apply(&(-e)), &q, &cov, 1e-20, false, true, false);
            let fd = (fp - fm) / 2e-7;
            assert!((fd - grad[slot]).abs() < 1e-4 * (1.0 + fd.abs()), "slot {slot}: fd {fd} analytic {}", grad[slot]);
        }
    }

    /// A tilted surface state (κz given), `n` points near it and anisotropic covariances.
    pub(crate) fn fixture(kappa_z: f64, n: usize) -> (SurfaceState, Vec<Vector3<f64>>, Vec<Matrix3<f64>>) {
        let state = SurfaceState {
            k3: Vector3::new(3.0, -2.0, kappa_z),
            rot: crate::geometry::exp_map(&Vector3::new(0.3, -0.4, 0.2)),
            c: Vector3::new(0.1, -0.2, 1.0),
        };
        let points =
            (0..n).map(|i| Vector3::new(0.1 + 0.003 * i as f64, -0.2 + 0.002 * (i % 7) as f64, 1.0 + 0.001 * (i % 5) as f64)).collect();
        let covs = (0..n).map(|i| Matrix3::new(2.0, 0.3, 0.1, 0.3, 1.0, 0.2, 0.1, 0.2, 5.0 + i as f64) * 1e-6).collect();
        (state, points, covs)
    }

    /// The chunked pass reproduces `point_terms` bit for bit (the paraboloid's free parameters
    /// are a plain selection of the local slots), also for a point count that leaves padding in
    /// the last chunk; `chi_square` is its χ²; the weight-derivative branch is eq 36 in full.
    #[test]
    fn chunked_pass_is_bit_identical_to_point_terms() {
        let (state, points, covs) = fixture(0.0, 43);
        let covs = Covariances::PerPoint(&covs);
        let set = PointSet::new(&points, &covs);
        assert_eq!(set.len(), 43);
        for weight_derivative in [false, true] {
            let mut h = FreeMatrix::zeros();
            let mut b = Free::zeros();
            let (mut chi2, mut sampson_sq) = (0.0, 0.0);
            for (i, q) in points.iter().enumerate() {
                let (f, grad, d) = point_terms(&state, q, &covs.get(i), 1e-20, true, weight_derivative, true);
                let g = Free::from_fn(|r, _| grad[[0, 1, 3, 4, 5, 6, 7, 8][r]]);
                for c in 0..MAX_FREE {
                    for r in c..MAX_FREE {
                        h[(r, c)] += g[r] * g[c];
                    }
                }
                b.axpy(f, &g, 1.0);
                chi2 += f * f;
                sampson_sq += d * d;
            }
            let n = accumulate(Model::Paraboloid, &state, &set, 1e-20, weight_derivative, true);
            for c in 0..MAX_FREE {
                for r in c..MAX_FREE {
                    assert_eq!(n.h[(r, c)], h[(r, c)], "{weight_derivative} ({r}, {c})");
                }
            }
            assert_eq!((n.b, n.chi2, n.sampson_sq), (b, chi2, sampson_sq), "{weight_derivative}");
            assert_eq!(chi_square(&state, &set, 1e-20), chi2);
        }
    }

    /// The early-stopping χ² pass is the full sum, or a partial sum that already decides both LM
    /// comparisons (`χ² ≤ base`, `χ² − base < margin`) as the full sum does.
    #[test]
    fn early_stopping_chi_square_decides_as_the_full_sum() {
        let (state, points, _) = fixture(0.0, 43);
        let covs = Covariances::Constant(Matrix3::identity() * 1e-6);
        let set = PointSet::new(&points, &covs);
        let full = chi_square(&state, &set, 1e-20);
        let mut early = 0;
        for base in [0.0, 0.1 * full, 0.5 * full, full - 1e-3, full, 2.0 * full] {
            for margin in [0.0, 1e-2, 0.3 * full] {
                let s = chi_square_unless_above(&state, &set, 1e-20, base, margin);
                assert!(s <= full);
                assert_eq!((s <= base, s - base < margin), (full <= base, full - base < margin), "{base} {margin}");
                early += usize::from(s < full);
            }
        }
        assert!(early > 0);
    }

    /// The free-parameter accumulation equals `Eᵀ (Σ ∇F ∇Fᵀ) E` over the 9 local slots.
    #[test]
    fn free_accumulation_matches_the_embedding() {
        let (state, points, covs) = fixture(1.5, 40);
        let covs = Covariances::PerPoint(&covs);
        for model in
            [Model::Plane, Model::Paraboloid, Model::CircularParaboloid, Model::CylindricParaboloid, Model::Sphere, Model::Cylinder]
        {
            let mut h9 = SMatrix::<f64, 9, 9>::zeros();
            let mut b9 = Local::zeros();
            let mut sampson_sq = 0.0;
            for (i, q) in points.iter().enumerate() {
                let (f, grad, d) = point_terms(&state, q, &covs.get(i), 1e-20, true, false, true);
                h9.ger(1.0, &grad, &grad, 1.0);
                b9.axpy(f, &grad, 1.0);
                sampson_sq += d * d;
            }
            let e = model.embedding();
            let mut h = e.transpose() * h9 * e;
            for r in model.num_free()..MAX_FREE {
                h[(r, r)] = 1.0;
            }
            let b = e.transpose() * b9;
            let n = accumulate(model, &state, &PointSet::new(&points, &covs), 1e-20, false, true);
            assert!((n.h - h).norm() <= 1e-12 * h.norm(), "{model:?}");
            assert!((n.b - b).norm() <= 1e-12 * b.norm(), "{model:?}");
            assert!((n.sampson_sq - sampson_sq).abs() <= 1e-12 * sampson_sq, "{model:?}");
        }
    }
}

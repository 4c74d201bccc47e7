//! Weighted Levenberg–Marquardt on the common implicit surface form (IROS IV-A, eq 33–41).
//!
//! The objective is `χ² = Σ F_i²` with `F_i = f(q_i, p) / σ_i` (eq 35), `f` the world-frame implicit
//! form `f_w(q) = q_lᵀ K q_l − 2 q_l·ẑ`, `q_l = Rᵀ(q − c)` (eq 37–38) and `σ_i² = ∇_q f Σ_i ∇_q fᵀ`
//! (eq 34). Its gradient is eq 36 with the derivatives of eq 39–41, including the `∂σ/∂p` term of
//! the weights (`FitConfig::weight_derivative`), which removes the errors-in-variables bias of plain
//! re-weighting. For paraboloids that term alone would reward moving the apex away from the data
//! (`‖∇f‖` grows away from the apex, inflating `σ_i`: 16° median normal error and 69 % type
//! classification in `bench_fit`); the apex pseudo-observation [`ApexPrior`] (the data centroid,
//! around which the patch boundary is centred) holds it, and with both the paraboloid fits reach
//! 1.0–1.4° at the apex and their Σ contains the truth in 94–96 % of the trials.
//!
//! The pose is updated on the manifold: `R ← R exp([δ]×)`, `c ← c + R δc`, so the derivatives are
//! those of eq 39–41 evaluated at `r = 0` of the increment (`∂q_l/∂δ = [q_l]×`, `∂q_l/∂δc = −I`);
//! the final covariance is mapped to the exponential-map vector `r` with the right Jacobian. The
//! increments of the gauge directions of each surface (rotation about a symmetry axis, sliding along
//! it) are held at zero so the normal equations are never singular; those directions are fixed by
//! the data moments afterwards (IROS steps 5–9). Everything in the per-point loop is fixed-size and
//! allocation-free.

use super::FitError;
use nalgebra::{Matrix2, Matrix3, SMatrix, SVector, Vector2, Vector3};

/// Local increment slots: `[κx, κy, κz, δx, δy, δz, δcx, δcy, δcz]`.
pub(crate) type Local = SVector<f64, 9>;
/// Maximum number of free parameters (general paraboloid).
pub(crate) const MAX_FREE: usize = 8;
pub(crate) type Free = SVector<f64, MAX_FREE>;
pub(crate) type FreeMatrix = SMatrix<f64, MAX_FREE, MAX_FREE>;

/// The surface model of one WLM run: which combinations of local slots are free.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub(crate) enum Model {
    /// `K = 0`; free: tilt `δx, δy` and offset `δcz` (step 1-ii).
    Plane,
    /// `K = diag(κx, κy, 0)`; free: both curvatures and the full pose (step 2, `s = parab`).
    Paraboloid,
    /// `K = diag(κ, κ, 0)`; free: κ, tilt, apex.
    CircularParaboloid,
    /// `K = diag(0, κ, 0)`; free: κ, rotation, apex y/z (sliding along x is a symmetry).
    CylindricParaboloid,
    /// `K = κ I` (eq 22); free: κ, tilt about the apex, `δcz`.
    Sphere,
    /// `K = diag(0, κ, κ)` (eq 26); free: κ, rotation about the apex, `δcz`.
    Cylinder,
}

impl Model {
    /// Bit masks over the 9 local slots, one per free parameter.
    pub(crate) fn free_slots(self) -> &'static [u16] {
        const K_X: u16 = 1;
        const K_Y: u16 = 2;
        const K_Z: u16 = 4;
        const D_X: u16 = 8;
        const D_Y: u16 = 16;
        const D_Z: u16 = 32;
        const C_X: u16 = 64;
        const C_Y: u16 = 128;
        const C_Z: u16 = 256;
        match self {
            Model::Plane => &[D_X, D_Y, C_Z],
            Model::Paraboloid => &[K_X, K_Y, D_X, D_Y, D_Z, C_X, C_Y, C_Z],
            Model::CircularParaboloid => &[K_X | K_Y, D_X, D_Y, C_X, C_Y, C_Z],
            Model::CylindricParaboloid => &[K_Y, D_X, D_Y, D_Z, C_Y, C_Z],
            Model::Sphere => &[K_X | K_Y | K_Z, D_X, D_Y, C_Z],
            Model::Cylinder => &[K_Y | K_Z, D_X, D_Y, D_Z, C_Z],
        }
    }

    /// Number of free parameters.
    pub(crate) fn num_free(self) -> usize {
        self.free_slots().len()
    }

    /// The 9 × MAX_FREE map from free parameters to local slots.
    pub(crate) fn embedding(self) -> SMatrix<f64, 9, MAX_FREE> {
        let mut m = SMatrix::<f64, 9, MAX_FREE>::zeros();
        for (j, mask) in self.free_slots().iter().enumerate() {
            for slot in 0..9 {
                if mask & (1 << slot) != 0 {
                    m[(slot, j)] = 1.0;
                }
            }
        }
        m
    }
}

/// Unbounded surface state: `K = diag(k3)`, local frame `(R, c)`.
#[derive(Clone, Copy, Debug, PartialEq)]
pub(crate) struct SurfaceState {
    pub k3: Vector3<f64>,
    pub rot: Matrix3<f64>,
    pub c: Vector3<f64>,
}

impl SurfaceState {
    /// Apply a local increment (on-manifold update). The in-plane part of `δc` moves the centre
    /// along the surface (second-order lift `½(κx δcx² + κy δcy²)` along the normal): sliding the
    /// apex of a curved patch is then a straight line in the increments, so Gauss–Newton steps stay
    /// in the (otherwise banana-shaped) valley of the weakly determined apex. The first-order
    /// Jacobian is unchanged.
    pub(crate) fn apply(&self, local: &Local) -> Self {
        let k3 = self.k3 + Vector3::new(local[0], local[1], local[2]);
        let delta = Vector3::new(local[3], local[4], local[5]);
        let lift = 0.5 * (self.k3.x * local[6] * local[6] + self.k3.y * local[7] * local[7]);
        let dc = Vector3::new(local[6], local[7], local[8] + lift);
        let rot = self.rot * crate::geometry::exp_map(&delta);
        Self { k3, rot, c: self.c + self.rot * dc }
    }
}

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
    let big_f = f * inv_sigma;
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
        return (big_f, df * inv_sigma, sampson);
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
    let w = big_f / (2.0 * var);
    (big_f, df * inv_sigma - dv * w, sampson)
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
fn chi_square_unless_above(state: &SurfaceState, set: &PointSet, min_variance: f64, base: f64, margin: f64) -> f64 {
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
                    let w = lane.big_f / (2.0 * lane.var);
                    df * inv_sigma - dv * w
                } else {
                    df * inv_sigma
                };
                gs[j] = project(&grad);
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

/// One point's values of [`point_terms`]: what the χ², the gradient of eq 40 and the weight
/// derivative of eq 41 (formed by the caller) need.
struct Lane {
    /// `F = f / σ` (eq 35).
    big_f: f64,
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

/// The per-point values of [`point_terms`] ([`Lane`]) for all `BLOCK` slots of a chunk (the padding
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
        sink(j, &Lane { big_f: f * inv_sigma, f, inv_sigma, q: [qx, qy, qz], g: [gx, gy, gz], s: [sx, sy, sz], var, clamped });
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

/// The apex observed through the data centroid (beyond IROS, `FitConfig::apex_from_centroid`).
///
/// A paraboloid patch's boundary is centred on its apex (IROS Table I, eq 17–21) and range data
/// sample the patch nearly uniformly, so the centroid of the points observes the apex: in the local
/// frame `ū = [Rᵀ(q̄ − c)]_xy` has mean ≈ 0 and covariance `(Rᵀ C_q̄ R)_xy`, the points' scatter
/// over N. The surface alone determines the apex only weakly (sliding it along the surface is a
/// tilt plus an offset to first order: σ of centimetres at Kinect noise), and it is the apex the
/// boundary and the patch centre hang on. Planes, spheres and cylinders get the same information
/// from steps 1-ii and 6 (centre at the centroid); for paraboloids it enters the WLM objective as
/// the pseudo-observation `χ²_c = ūᵀ C_ū⁻¹ ū`, on the local axes along which the apex is free.
#[derive(Clone, Copy, Debug, PartialEq)]
pub(crate) struct ApexPrior {
    /// Centroid `q̄` of the boundary points (world).
    pub mean: Vector3<f64>,
    /// Covariance of `q̄`: the points' sample covariance over their number (world).
    pub cov_of_mean: Matrix3<f64>,
}

impl ApexPrior {
    /// From the points the boundary is fitted to; `None` for fewer than 3 points.
    pub(crate) fn from_points(points: &[Vector3<f64>]) -> Option<Self> {
        let n = points.len();
        if n < 3 {
            return None;
        }
        let mean = points.iter().sum::<Vector3<f64>>() / n as f64;
        let mut scatter = Matrix3::zeros();
        for q in points {
            let d = q - mean;
            scatter.ger(1.0, &d, &d, 1.0);
        }
        Some(Self { mean, cov_of_mean: scatter / ((n - 1) as f64 * n as f64) })
    }

    /// The local axes along which `model` leaves the apex free (x, y): both for general and
    /// circular paraboloids, y for cylindric ones (their x is fixed by step 6), none otherwise.
    fn axes(model: Model) -> [bool; 2] {
        match model {
            Model::Paraboloid | Model::CircularParaboloid => [true, true],
            Model::CylindricParaboloid => [false, true],
            Model::Plane | Model::Sphere | Model::Cylinder => [false, false],
        }
    }

    /// `ū`, its information matrix `C_ū⁻¹` (zero on unobserved axes) and `∂ū/∂(local slots)`:
    /// `∂q_l/∂δ = [q_l]×`, `∂q_l/∂δc = −I` as for the points (module doc).
    fn terms(&self, model: Model, state: &SurfaceState) -> Option<(Vector2<f64>, Matrix2<f64>, SMatrix<f64, 2, 9>)> {
        let axes = Self::axes(model);
        if axes == [false, false] {
            return None;
        }
        let q = state.rot.transpose() * (self.mean - state.c);
        let cov = (state.rot.transpose() * self.cov_of_mean * state.rot).fixed_view::<2, 2>(0, 0).into_owned();
        let info = if axes == [true, true] { cov.try_inverse()? } else { Matrix2::new(0.0, 0.0, 0.0, 1.0 / cov[(1, 1)]) };
        if !info.iter().all(|v| v.is_finite()) {
            return None;
        }
        let mut jac = SMatrix::<f64, 2, 9>::zeros();
        jac[(0, 4)] = -q.z;
        jac[(0, 5)] = q.y;
        jac[(1, 3)] = q.z;
        jac[(1, 5)] = -q.x;
        jac[(0, 6)] = -1.0;
        jac[(1, 7)] = -1.0;
        Some((q.xy(), info, jac))
    }

    /// `χ²_c` at `state` (0 if the model has no free apex axis).
    fn chi_square(&self, model: Model, state: &SurfaceState) -> f64 {
        self.terms(model, state).map_or(0.0, |(u, info, _)| (u.transpose() * info * u)[(0, 0)])
    }

    /// Add `χ²_c` and its Gauss–Newton terms to the normal equations of `model` at `state`.
    pub(crate) fn add_to(&self, model: Model, state: &SurfaceState, normal: &mut Normal) {
        let Some((u, info, jac)) = self.terms(model, state) else { return };
        let jf = jac * model.embedding();
        let weighted = info * jf;
        normal.h += jf.transpose() * weighted;
        normal.b += weighted.transpose() * u;
        normal.chi2 += (u.transpose() * info * u)[(0, 0)];
    }
}

/// [`accumulate`] plus the apex pseudo-observation of `settings`, if any.
pub(crate) fn accumulate_with_prior(
    model: Model,
    state: &SurfaceState,
    set: &PointSet,
    settings: &LmSettings,
    with_sampson: bool,
) -> Normal {
    let mut normal = accumulate(model, state, set, settings.min_variance, settings.weight_derivative, with_sampson);
    if let Some(prior) = &settings.apex_prior {
        prior.add_to(model, state, &mut normal);
    }
    normal
}

/// Result of a WLM run.
pub(crate) struct WlmResult {
    pub state: SurfaceState,
    /// Normal equations at `state` (undamped).
    pub normal: Normal,
}

/// LM settings used by [`run`].
#[derive(Clone, Copy)]
pub(crate) struct LmSettings {
    pub max_iterations: usize,
    pub initial_damping: f64,
    pub chi2_tolerance: f64,
    pub min_variance: f64,
    pub weight_derivative: bool,
    /// The apex observed through the data centroid (paraboloid models only).
    pub apex_prior: Option<ApexPrior>,
}

/// Steps smaller than this in every free parameter (1/m, rad, m) change nothing measurable: far
/// below the parameters' standard deviations (≥ 1e-5 for nf = 50 Kinect points) and ~1e-9 relative
/// to the patch pose.
const NEGLIGIBLE_STEP: f64 = 1e-9;

/// Weighted Levenberg–Marquardt (IROS IV-A) from `start`: the converged surface alone.
pub(crate) fn run(model: Model, start: SurfaceState, set: &PointSet, settings: &LmSettings) -> Result<SurfaceState, FitError> {
    levenberg_marquardt(model, start, set, settings, false).map(|r| r.state)
}

/// [`run`] with the normal equations (eq 36) at the converged surface, e.g. for its covariance.
pub(crate) fn run_with_normal(model: Model, start: SurfaceState, set: &PointSet, settings: &LmSettings) -> Result<WlmResult, FitError> {
    levenberg_marquardt(model, start, set, settings, true)
}

/// The LM iteration of [`run`]. Without `final_normal` the run ends after an accepted step below
/// the tolerance without the normal equations at the new state (only their χ² is set), which
/// nothing else would use; the iterates and the result are the same either way.
fn levenberg_marquardt(
    model: Model,
    start: SurfaceState,
    set: &PointSet,
    settings: &LmSettings,
    final_normal: bool,
) -> Result<WlmResult, FitError> {
    let m = model.num_free();
    let embed = model.embedding();
    let mut state = start;
    let mut normal = accumulate_with_prior(model, &state, set, settings, false);
    if !normal.chi2.is_finite() {
        return Err(FitError::Diverged("non-finite residual at the start"));
    }
    let mut lambda = settings.initial_damping;
    // Converged when the undamped Gauss–Newton step would lower χ² by less than the tolerance
    // (or, below, when an accepted step lowered it by less). Changes only with the normal equations.
    let predicted_decrease = |normal: &Normal| solve_leading(m, &normal.h, &normal.b).map(|x| normal.b.dot(&x)).unwrap_or(f64::INFINITY);
    // Computed only when needed: the damped matrix A below is H plus a non-negative diagonal, so the
    // damped decrease bᵀA⁻¹b is at most bᵀH⁻¹b; while it is clearly above the tolerance the undamped
    // test cannot stop the run (the 0.1 % margin covers rounding), and H needs no factorisation.
    let mut predicted = None;
    for _ in 0..settings.max_iterations {
        let mut a = normal.h;
        for i in 0..m {
            a[(i, i)] *= 1.0 + lambda;
            if a[(i, i)] <= 0.0 {
                a[(i, i)] = lambda.max(1e-12);
            }
        }
        let solution = solve_leading(m, &a, &normal.b);
        if !solution.is_some_and(|x| normal.b.dot(&x) >= 1.001 * settings.chi2_tolerance)
            && *predicted.get_or_insert_with(|| predicted_decrease(&normal)) < settings.chi2_tolerance
        {
            break;
        }
        let Some(solution) = solution else {
            lambda *= 10.0;
            if lambda > 1e12 {
                break;
            }
            continue;
        };
        let step = -solution;
        if !step.iter().all(|v| v.is_finite()) {
            return Err(FitError::Diverged("non-finite step"));
        }
        let trial = state.apply(&(embed * step));
        // χ² first; the normal equations (eq 36) only for an accepted step.
        // Only the outcomes below matter for a χ² that exceeds the current one by more than the
        // tolerance (rejected, not flat), so its pass may stop early (same decisions, same results).
        // The pseudo-observation's χ² is non-negative, so a partial sum of the points' terms above
        // the current χ² still decides the trial (early stop as without it).
        let prior_chi2 = settings.apex_prior.map_or(0.0, |p| p.chi_square(model, &trial));
        let trial_chi2 =
            prior_chi2 + chi_square_unless_above(&trial, set, settings.min_variance, normal.chi2 - prior_chi2, settings.chi2_tolerance);
        if trial_chi2.is_finite() && trial_chi2 <= normal.chi2 {
            let decrease = normal.chi2 - trial_chi2;
            state = trial;
            if decrease < settings.chi2_tolerance && !final_normal {
                normal.chi2 = trial_chi2;
                break;
            }
            normal = accumulate_with_prior(model, &state, set, settings, false);
            lambda = (lambda * 0.1).max(1e-9);
            // A full step that gains nothing measurable: converged (or crawling along a
            // degenerate valley, e.g. the apex of nearly flat data, where the covariance is large).
            if decrease < settings.chi2_tolerance {
                break;
            }
            predicted = None;
        } else {
            // A rejected step below NEGLIGIBLE_STEP in every parameter: the larger damping of the
            // following trials only shrinks the step further (‖step‖ decreases with λ), so at most a
            // last step of that size could still be accepted (its χ² change is far below the
            // tolerance, which would end the run). Near convergence the re-weighted objective rises
            // along the Gauss–Newton direction (the σ_i(p) term of eq 36 that the steps ignore) and
            // LM would otherwise reject its way up to λ = 1e12.
            if step.amax() < NEGLIGIBLE_STEP {
                break;
            }
            // A rejected step that raises χ² by less than the tolerance: χ² is flat within the
            // tolerance along the step, so the larger damping of the following trials (a shorter
            // step in nearly the same direction) could gain at most that much: converged, as after
            // an accepted step below the tolerance. Saves the trials that shrink the step until it
            // is accepted or negligible (typically λ from 1e-7 up past 1, several χ² passes).
            if trial_chi2 - normal.chi2 < settings.chi2_tolerance {
                break;
            }
            lambda *= 10.0;
            if lambda > 1e12 {
                break;
            }
        }
    }
    if !normal.chi2.is_finite() || !state.k3.iter().chain(state.c.iter()).all(|v| v.is_finite()) {
        return Err(FitError::Diverged("non-finite parameters"));
    }
    Ok(WlmResult { state, normal })
}

/// `A⁻¹ b` for the symmetric positive definite leading `m × m` block of `a` (the free parameters;
/// zero beyond `m`), `None` if its Cholesky factorisation fails. Fixed-size code per model size
/// with nalgebra's Cholesky algorithm and operation order, so the values are bit-identical to
/// `a.cholesky()?.solve(b)` on the block padded with the identity as [`accumulate`] returns it,
/// without the work on the padding.
pub(crate) fn solve_leading(m: usize, a: &FreeMatrix, b: &Free) -> Option<Free> {
    match m {
        3 => Cholesky::<3>::new(a).map(|c| c.solve(b)),
        4 => Cholesky::<4>::new(a).map(|c| c.solve(b)),
        5 => Cholesky::<5>::new(a).map(|c| c.solve(b)),
        6 => Cholesky::<6>::new(a).map(|c| c.solve(b)),
        _ => Cholesky::<MAX_FREE>::new(a).map(|c| c.solve(b)),
    }
}

/// The inverse of the leading `m × m` block of `a` (zero elsewhere), as [`solve_leading`] for
/// the unit vectors (nalgebra's `Cholesky::inverse`, bit-identical on the block).
pub(crate) fn inverse_leading(m: usize, a: &FreeMatrix) -> Option<FreeMatrix> {
    match m {
        3 => Cholesky::<3>::new(a).map(|c| c.inverse()),
        4 => Cholesky::<4>::new(a).map(|c| c.inverse()),
        5 => Cholesky::<5>::new(a).map(|c| c.inverse()),
        6 => Cholesky::<6>::new(a).map(|c| c.inverse()),
        _ => Cholesky::<MAX_FREE>::new(a).map(|c| c.inverse()),
    }
}

/// Lower Cholesky factor of a leading `M × M` block, column-major (`l[column][row]`).
struct Cholesky<const M: usize> {
    l: [[f64; M]; M],
}

impl<const M: usize> Cholesky<M> {
    /// nalgebra's right-looking factorisation of the lower triangle: column `j` minus `L_jk` times
    /// column `k` for `k < j`, then `√` of the diagonal (`None` unless positive) and the division
    /// of the column below it.
    #[inline(always)]
    fn new(a: &FreeMatrix) -> Option<Self> {
        let mut l = [[0.0; M]; M];
        for (c, column) in l.iter_mut().enumerate() {
            for (r, v) in column.iter_mut().enumerate().skip(c) {
                *v = a[(r, c)];
            }
        }
        // Column j is updated from the columns k < j of the same array: indices, not iterators.
        #[allow(clippy::needless_range_loop)]
        for j in 0..M {
            for k in 0..j {
                let factor = -l[k][j];
                for i in j..M {
                    // IEEE addition is commutative: the same value as nalgebra's `factor * l_k + l_j`.
                    l[j][i] += factor * l[k][i];
                }
            }
            let diag = l[j][j];
            if diag.is_nan() || diag <= 0.0 {
                return None;
            }
            let denom = diag.sqrt();
            l[j][j] = denom;
            for i in j + 1..M {
                l[j][i] /= denom;
            }
        }
        Some(Self { l })
    }

    /// `L Lᵀ x = b` over the first `M` entries (forward substitution by columns, back substitution
    /// by dot products in increasing index order, as nalgebra's `Cholesky::solve`).
    #[inline(always)]
    fn solve(&self, b: &Free) -> Free {
        let l = &self.l;
        let mut x = [0.0; M];
        for (i, v) in x.iter_mut().enumerate() {
            *v = b[i];
        }
        for i in 0..M {
            let coeff = x[i] / l[i][i];
            x[i] = coeff;
            for r in i + 1..M {
                x[r] += -coeff * l[i][r];
            }
        }
        for i in (0..M).rev() {
            let mut dot = 0.0;
            for k in i + 1..M {
                dot += l[i][k] * x[k];
            }
            x[i] = (x[i] - dot) / l[i][i];
        }
        Free::from_fn(|r, _| x.get(r).copied().unwrap_or(0.0))
    }

    /// The inverse of the block (zero beyond it), column by column as [`Cholesky::solve`].
    fn inverse(&self) -> FreeMatrix {
        let mut out = FreeMatrix::zeros();
        for c in 0..M {
            let e = Free::from_fn(|r, _| if r == c { 1.0 } else { 0.0 });
            out.set_column(c, &self.solve(&e));
        }
        out
    }
}

#[cfg(test)]
mod tests {
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

    /// The apex pseudo-observation's residual changes by its Jacobian under a local increment
    /// (free slots of each model), its χ² is `ūᵀ C_ū⁻¹ ū`, and it is absent for planes.
    #[test]
    fn apex_prior_jacobian_matches_finite_differences() {
        let (state, points, _) = fixture(0.0, 40);
        let Some(prior) = ApexPrior::from_points(&points) else { panic!("40 points give a prior") };
        assert!(prior.terms(Model::Plane, &state).is_none());
        for model in [Model::Paraboloid, Model::CircularParaboloid, Model::CylindricParaboloid] {
            let Some((u, info, jac)) = prior.terms(model, &state) else { panic!("{model:?} observes its apex") };
            assert!((prior.chi_square(model, &state) - (u.transpose() * info * u)[(0, 0)]).abs() < 1e-12);
            for slot in 0..9 {
                let mut e = Local::zeros();
                e[slot] = 1e-7;
                let up = prior.terms(model, &state.apply(&e)).map(|t| t.0).unwrap_or_default();
                let um = prior.terms(model, &state.apply(&(-e))).map(|t| t.0).unwrap_or_default();
                let fd = (up - um) / 2e-7;
                for row in 0..2 {
                    assert!(
                        (fd[row] - jac[(row, slot)]).abs() < 1e-6,
                        "{model:?} slot {slot} row {row}: fd {} analytic {}",
                        fd[row],
                        jac[(row, slot)]
                    );
                }
            }
        }
        // The cylindric paraboloid observes local y only (its x is fixed by step 6).
        let Some((_, info, _)) = prior.terms(Model::CylindricParaboloid, &state) else { panic!("cylindric observes y") };
        assert_eq!((info[(0, 0)], info[(0, 1)]), (0.0, 0.0));
        assert!(info[(1, 1)] > 0.0);
    }

    /// A tilted surface state (κz given), `n` points near it and anisotropic covariances.
    fn fixture(kappa_z: f64, n: usize) -> (SurfaceState, Vec<Vector3<f64>>, Vec<Matrix3<f64>>) {
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

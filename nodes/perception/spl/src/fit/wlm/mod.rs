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
//!
//! Here: the models and the surface state, and the LM iteration; [`normal`] sums the normal
//! equations over the points, [`apex_prior`] adds the apex pseudo-observation and [`cholesky`]
//! solves them.

mod apex_prior;
mod cholesky;
mod normal;

use super::FitError;
use nalgebra::{Matrix3, SMatrix, SVector, Vector3};

pub(crate) use apex_prior::{accumulate_with_prior, ApexPrior};
pub(crate) use cholesky::{inverse_leading, solve_leading};
use normal::chi_square_unless_above;
pub(crate) use normal::{chi_square, Covariances, Normal, PointSet};

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

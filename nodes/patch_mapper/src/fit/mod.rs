//! Patch fitting (IROS IV steps 1-9): LLS plane, weighted Levenberg-Marquardt, type discrimination,
//! boundary moments, output covariance.
//!
//! (Public API first; the full weighted-LM pipeline lands in the next commit.)

use crate::patch::{BoundaryType, Patch, SurfaceType};
use nalgebra::{Matrix3, Vector2, Vector3};
use serde::{Deserialize, Serialize};

/// Which surface to fit (IROS IV input `s`).
#[derive(Clone, Copy, Debug, PartialEq, Eq, Default, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum SurfaceRequest {
    /// IROS `s = parab` with step-3 discrimination: plane, circular, cylindric, elliptic or
    /// hyperbolic paraboloid, decided by significance tests on the fitted curvatures.
    #[default]
    Auto,
    /// A general paraboloid without discrimination (elliptic or hyperbolic by the curvature signs).
    Paraboloid,
    /// Exactly this surface type (constrained fit).
    Exactly(SurfaceType),
}

/// Which boundary to fit (IROS IV input `b`; only free for planes).
#[derive(Clone, Copy, Debug, PartialEq, Eq, Default, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum BoundaryRequest {
    /// The boundary implied by the surface (ellipse for planes, IROS step 3).
    #[default]
    Auto,
    /// Exactly this boundary (must be valid for the surface, IROS Table I).
    Exactly(BoundaryType),
}

/// What to fit.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct FitRequest {
    /// Surface type request.
    pub surface: SurfaceRequest,
    /// Boundary type request.
    pub boundary: BoundaryRequest,
    /// Boundary containment probability Γ ∈ (0, 1] (IROS IV input; 0.95).
    pub containment: f64,
    /// Viewpoint (sensor position, same frame as the points): the patch normal is oriented towards
    /// it, so positive curvature means concave as seen from the sensor (IROS III-A).
    pub viewpoint: Vector3<f64>,
}

impl Default for FitRequest {
    fn default() -> Self {
        Self { surface: SurfaceRequest::Auto, boundary: BoundaryRequest::Auto, containment: 0.95, viewpoint: Vector3::zeros() }
    }
}

/// Fitting parameters (IROS IV; defaults cite their source).
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct FitConfig {
    /// Maximum Levenberg–Marquardt iterations per WLM run.
    pub max_iterations: usize,
    /// Initial Marquardt damping λ (Numerical Recipes: 1e-3).
    pub initial_damping: f64,
    /// Convergence: stop when the relative χ² decrease is below this.
    pub relative_tolerance: f64,
    /// Minimum variance of the implicit function per point (IROS footnote 10: clamp for semi-definite Σ_i).
    pub min_variance: f64,
    /// Significance level of the curvature tests replacing ε_k (IROS step 3): a curvature (or a
    /// difference of two) counts as non-zero if it is outside its (1 − α) confidence interval.
    pub significance: f64,
    /// Fallback absolute threshold ε_k (m⁻¹) used only when no point covariances are given.
    pub curvature_epsilon: f64,
    /// Scale the output covariance by max(1, χ²/(N − p)) (model noise beyond the sensor model).
    pub inflate_by_residual: bool,
}

impl Default for FitConfig {
    fn default() -> Self {
        Self {
            max_iterations: 50,
            initial_damping: 1e-3,
            relative_tolerance: 1e-9,
            min_variance: 1e-14,
            significance: 0.01,
            curvature_epsilon: 0.5,
            inflate_by_residual: true,
        }
    }
}

/// Fitting errors (never panics).
#[derive(Debug, thiserror::Error, PartialEq)]
pub enum FitError {
    /// Fewer points than the patch type's degrees of freedom.
    #[error("need at least {needed} points, got {got}")]
    TooFewPoints { needed: usize, got: usize },
    /// A NaN or infinite coordinate.
    #[error("point {index} is not finite")]
    NonFinitePoint { index: usize },
    /// Point covariances count differs from the points.
    #[error("{points} points but {covariances} covariances")]
    CovarianceCountMismatch { points: usize, covariances: usize },
    /// A covariance that is not symmetric positive semi-definite (or not finite).
    #[error("covariance of point {index} is not positive semi-definite")]
    InvalidCovariance { index: usize },
    /// The points do not determine the surface (all equal, collinear, ...).
    #[error("degenerate points: {0}")]
    Degenerate(&'static str),
    /// The surface/boundary request is not a valid patch type.
    #[error("invalid request: {0}")]
    InvalidRequest(String),
    /// Levenberg–Marquardt produced non-finite values or failed to converge.
    #[error("Levenberg-Marquardt diverged: {0}")]
    Diverged(&'static str),
}

/// Fit a bounded patch to points (IROS IV).
pub fn fit_patch(
    points: &[Vector3<f64>],
    point_covariances: Option<&[Matrix3<f64>]>,
    request: &FitRequest,
    config: &FitConfig,
) -> Result<Patch, FitError> {
    let _ = (point_covariances, config);
    if points.len() < 3 {
        return Err(FitError::TooFewPoints { needed: 3, got: points.len() });
    }
    let n = points.len() as f64;
    let mean = points.iter().sum::<Vector3<f64>>() / n;
    let scatter = points.iter().fold(Matrix3::zeros(), |acc, q| acc + (q - mean) * (q - mean).transpose());
    let eig = scatter.symmetric_eigen();
    let imin = eig.eigenvalues.imin();
    let mut normal = eig.eigenvectors.column(imin).into_owned();
    if normal.dot(&(request.viewpoint - mean)) < 0.0 {
        normal = -normal;
    }
    let r = crate::geometry::r_xy_from_normal(&normal);
    let radius = (points.iter().map(|q| (q - mean).norm_squared()).sum::<f64>() / n).sqrt() * 1.4;
    Patch::new(SurfaceType::Plane, BoundaryType::Circle, vec![radius], Vector2::zeros(), Vector3::new(r.x, r.y, 0.0), mean)
        .map_err(|e| FitError::InvalidRequest(e.to_string()))
}

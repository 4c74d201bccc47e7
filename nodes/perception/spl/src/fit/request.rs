//! What a fit is asked for and how it is tuned: the IROS IV inputs (surface `s`, boundary `b`,
//! containment Γ, viewpoint), the fit configuration with its defaults, and the patch type a request
//! resolves to (IROS Table I).

use super::wlm::{LmSettings, Model};
use super::FitError;
use crate::patch::{BoundaryType, SurfaceType};
use nalgebra::Vector3;
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

/// Which surface models differentiate the weights `σ_i(p)` in WLM (IROS eq 36).
///
/// The full eq 36 is the maximum-likelihood gradient: re-weighting without it (iteratively
/// re-weighted Gauss–Newton) solves `Σ f_i ∇_p f_i / σ_i² = 0`, whose expectation at the truth is not
/// zero when the noise is along the rays (errors in variables: `E[f_i ∇_p f_i] = ∇_q f Σ_i …`), which
/// biases planes by ~0.5σ in tilt at Kinect noise (`bench_fit`: 88–90 % instead of ~95 % of the
/// truths inside the 95 % ellipsoid). Planes, spheres and circular cylinders have implicit forms
/// whose gradient norm is constant on the surface (a scaled Euclidean distance), so eq 36 is safe
/// there. The paraboloid forms are not: `‖∇f‖` grows away from the apex, and eq 36 alone rewards
/// moving the apex away from the data to inflate σ_i (16° median normal error at the apex). With
/// [`FitConfig::apex_from_centroid`] (default) the apex is held by the data centroid and `Always`
/// is the better choice for them too (1.0–1.4° at the apex, Σ honest in 94–96 % of the trials,
/// against 2.5–3.7° and 93–96 % re-weighted); without it use `DistanceLike`.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum WeightDerivative {
    /// Never differentiate (iteratively re-weighted Gauss–Newton everywhere).
    Never,
    /// Differentiate for planes, spheres and circular cylinders only.
    DistanceLike,
    /// Always differentiate (eq 36 as written; default).
    Always,
}

impl WeightDerivative {
    fn applies_to(self, model: Model) -> bool {
        match self {
            WeightDerivative::Never => false,
            WeightDerivative::Always => true,
            WeightDerivative::DistanceLike => matches!(model, Model::Plane | Model::Sphere | Model::Cylinder),
        }
    }
}

/// `settings` with the weight derivative resolved for one model.
pub(super) fn settings_for(model: Model, settings: &LmSettings, config: &FitConfig) -> LmSettings {
    LmSettings { weight_derivative: config.weight_derivative.applies_to(model), ..*settings }
}

/// Fitting parameters (IROS IV; defaults cite their source).
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct FitConfig {
    /// Maximum Levenberg–Marquardt iterations per WLM run.
    pub max_iterations: usize,
    /// Initial Marquardt damping λ (Numerical Recipes: 1e-3).
    pub initial_damping: f64,
    /// Convergence: stop when the undamped Gauss–Newton step would lower χ² by less than this, or an
    /// accepted step did (χ² units; χ² itself fluctuates by √(2N) ≫ 0.01 between data sets).
    pub chi2_tolerance: f64,
    /// Minimum variance of the implicit function per point (IROS footnote 10: clamp for semi-definite Σ_i).
    pub min_variance: f64,
    /// Significance level of the curvature tests replacing ε_k (IROS step 3): a curvature (or a
    /// difference of two) counts as non-zero if it is outside its (1 − α) confidence interval.
    pub significance: f64,
    /// Scale the output covariance by max(1, χ²/(N − p)) (model noise beyond the sensor model).
    pub inflate_by_residual: bool,
    /// Which WLM runs differentiate the per-point weights σ_i(p) as in IROS eq 36; the others
    /// re-weight at every iterate without differentiating (see [`WeightDerivative`]).
    pub weight_derivative: WeightDerivative,
    /// Beyond IROS: the apex of paraboloid patches is also observed through the centroid of the
    /// boundary points (the boundary is centred on the apex, eq 17–21; see `wlm::ApexPrior`), as
    /// planes, spheres and cylinders take their centre from it (steps 1-ii, 6). Without it the apex
    /// is what the surface shape alone says: 8–12 mm median off at Kinect noise and 150 points,
    /// against 3.6–4.1 mm (`bench_fit --no-apex-from-centroid --weight-derivative distance_like`).
    pub apex_from_centroid: bool,
    /// Beyond IROS, for fits that know the sensor ([`super::neighbourhood::fit_neighbourhood`]): the
    /// point covariances of a range-dependent sensor model are evaluated again where each
    /// measurement ray meets the fitted surface, and the patch is fitted once more with them (see
    /// [`super::sensed`]; removes the pull towards the sensor of covariances taken at the measured
    /// depth). Costs a second fit of the same type; nothing changes for the constant range model.
    pub covariances_on_surface: bool,
}

impl Default for FitConfig {
    fn default() -> Self {
        Self {
            max_iterations: 50,
            initial_damping: 1e-3,
            chi2_tolerance: 1e-2,
            min_variance: 1e-14,
            significance: 0.01,
            inflate_by_residual: true,
            weight_derivative: WeightDerivative::Always,
            apex_from_centroid: true,
            covariances_on_surface: true,
        }
    }
}

/// The resolved target of a fit.
#[derive(Clone, Copy, Debug, PartialEq)]
pub(super) enum Target {
    /// Paraboloid family with step-3 discrimination; boundary used if the result is a plane.
    Auto(BoundaryType),
    /// General paraboloid (elliptic or hyperbolic by sign).
    Paraboloid,
    /// A specific patch type.
    Fixed(SurfaceType, BoundaryType),
}

impl Target {
    pub(super) fn resolve(request: &FitRequest) -> Result<Self, FitError> {
        let boundary = match request.boundary {
            BoundaryRequest::Auto => None,
            BoundaryRequest::Exactly(b) => Some(b),
        };
        match request.surface {
            SurfaceRequest::Auto => Ok(Target::Auto(boundary.unwrap_or(BoundaryType::Ellipse))),
            SurfaceRequest::Paraboloid => match boundary {
                None | Some(BoundaryType::Ellipse) => Ok(Target::Paraboloid),
                Some(b) => Err(FitError::InvalidRequest(format!("a general paraboloid has an ellipse boundary, not {}", b.name()))),
            },
            SurfaceRequest::Exactly(s) => {
                let b = match (s.implied_boundary(), boundary) {
                    (None, b) => b.unwrap_or(BoundaryType::Ellipse),
                    (Some(implied), None) => implied,
                    (Some(implied), Some(b)) if b == implied => b,
                    (Some(_), Some(b)) => {
                        return Err(FitError::InvalidRequest(format!(
                            "{} patches cannot have a {} boundary (IROS Table I)",
                            s.name(),
                            b.name()
                        )))
                    }
                };
                Ok(Target::Fixed(s, b))
            }
        }
    }

    /// Minimum number of points: the DoF of the (largest possible) patch type.
    pub(super) fn min_points(self) -> usize {
        match self {
            Target::Auto(_) | Target::Paraboloid => crate::patch::dof(SurfaceType::EllipticParaboloid, BoundaryType::Ellipse),
            Target::Fixed(s, b) => crate::patch::dof(s, b),
        }
    }
}

/// The WLM model that carries the surface parameters of a patch type.
pub(super) fn model_for(surface: SurfaceType) -> Model {
    match surface {
        SurfaceType::EllipticParaboloid | SurfaceType::HyperbolicParaboloid => Model::Paraboloid,
        SurfaceType::CylindricParaboloid => Model::CylindricParaboloid,
        SurfaceType::CircularParaboloid => Model::CircularParaboloid,
        SurfaceType::Plane => Model::Plane,
        SurfaceType::Sphere => Model::Sphere,
        SurfaceType::CircularCylinder => Model::Cylinder,
    }
}

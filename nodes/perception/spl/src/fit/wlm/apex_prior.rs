//! The apex pseudo-observation of paraboloid fits (beyond IROS, `FitConfig::apex_from_centroid`):
//! the centroid of the boundary points observes the apex the boundary is centred on (eq 17–21),
//! added to the WLM normal equations as `χ²_c = ūᵀ C_ū⁻¹ ū` on the local axes along which the apex
//! is free.

use super::normal::{accumulate, Normal, PointSet};
use super::{LmSettings, Model, SurfaceState};
use nalgebra::{Matrix2, Matrix3, SMatrix, Vector2, Vector3};

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
    pub(super) fn chi_square(&self, model: Model, state: &SurfaceState) -> f64 {
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

#[cfg(test)]
mod tests {
    use super::*;
    use crate::fit::wlm::normal::tests::fixture;
    use crate::fit::wlm::Local;

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
}

//! J 3.2.1 step 13 for one neighbourhood: the surface fitted to nf points with the sensor's point
//! covariances, the boundary moments over the whole neighbourhood, plane boundaries sized like every
//! other type's (step 5). The mapper calls it for every seed; anything else that fits a patch "as
//! the mapper does" (a training target picked by hand) calls it with the same configuration.

use nalgebra::Vector3;
use serde::{Deserialize, Serialize};

use crate::fit::sensed::{covariances_on_surface, depends_on_range};
use crate::fit::{fit_patch_with_boundary_points, BoundaryRequest, FitConfig, FitError, FitRequest, SurfaceRequest};
use crate::patch::{Patch, SurfaceType};
use crate::sensor::{covariances_for, ErrorModel, SensorError};

/// What [`fit_neighbourhood`] needs: the sensor's error model, the fit's settings, the boundary
/// containment Γ and the plane sizing rule.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct NeighbourhoodFit {
    /// Point covariances for the fit (J eq 2, Murray–Little with the Kinect values by default).
    pub sensor: ErrorModel,
    pub fit: FitConfig,
    /// Γ: boundary containment probability (J 3.2.1 step 4 / IROS IV: 0.95).
    pub containment: f64,
    /// Size plane boundaries with J 3.2.1 step 5, `d_e = λ[√v_x √v_y]`, `λ = √2 erf⁻¹(Γ)`, instead
    /// of IROS eq 30, `d = √(−2 ln(1 − Γ) v)`, which leaves a third of an r-ball's disc without data.
    pub plane_boundary_j_step5: bool,
}

impl Default for NeighbourhoodFit {
    fn default() -> Self {
        Self { sensor: ErrorModel::default(), fit: FitConfig::default(), containment: 0.95, plane_boundary_j_step5: true }
    }
}

/// Why a neighbourhood could not be fitted.
#[derive(Debug, thiserror::Error, PartialEq)]
pub enum NeighbourhoodFitError {
    #[error("point covariances: {0}")]
    Sensor(#[from] SensorError),
    #[error("{0}")]
    Fit(#[from] FitError),
}

/// `λ / √(−2 ln(1 − Γ))`: J 3.2.1 step 5 extents over IROS eq 30 extents for a plane.
pub fn plane_boundary_factor(containment: f64) -> f64 {
    let gamma = containment.clamp(1e-9, 1.0 - 1e-9);
    let lambda = std::f64::consts::SQRT_2 * crate::fit::boundary::erf_inv(gamma);
    lambda / (-2.0 * (1.0 - gamma).ln()).sqrt()
}

/// The patch of one neighbourhood: the surface fitted to `fit_points_in_camera` with the
/// configured sensor covariances (points in the sensor frame, the sensor at its origin), the
/// boundary moments over `boundary_points_in_camera`, plane boundaries sized by J 3.2.1 step 5 when
/// configured.
pub fn fit_neighbourhood(
    fit_points_in_camera: &[Vector3<f64>],
    boundary_points_in_camera: &[Vector3<f64>],
    config: &NeighbourhoodFit,
) -> Result<Patch, NeighbourhoodFitError> {
    let covariances = covariances_for(fit_points_in_camera, &Vector3::zeros(), &config.sensor)?;
    let request = FitRequest { containment: config.containment, ..FitRequest::default() };
    let first = fit_patch_with_boundary_points(fit_points_in_camera, Some(&covariances), boundary_points_in_camera, &request, &config.fit)?;
    let mut patch = refit_on_surface(first, fit_points_in_camera, boundary_points_in_camera, &config.sensor, &request, &config.fit);
    if config.plane_boundary_j_step5 && patch.surface == SurfaceType::Plane {
        rescale_boundary(&mut patch, plane_boundary_factor(config.containment));
    }
    Ok(patch)
}

/// With [`FitConfig::covariances_on_surface`] and a range-dependent sensor model, `first` fitted
/// again (same type, same request otherwise) with the point covariances evaluated on its surface
/// ([`crate::fit::sensed`]); `first` itself when the option is off, the model does not depend on
/// the range, or the second fit fails (the first is then the best estimate there is).
pub fn refit_on_surface(
    first: Patch,
    fit_points_in_sensor: &[Vector3<f64>],
    boundary_points_in_sensor: &[Vector3<f64>],
    sensor: &ErrorModel,
    request: &FitRequest,
    config: &FitConfig,
) -> Patch {
    if !(config.covariances_on_surface && depends_on_range(sensor)) {
        return first;
    }
    let Ok(covariances) = covariances_on_surface(&first, fit_points_in_sensor, sensor) else { return first };
    let same_type =
        FitRequest { surface: SurfaceRequest::Exactly(first.surface), boundary: BoundaryRequest::Exactly(first.boundary), ..*request };
    fit_patch_with_boundary_points(fit_points_in_sensor, Some(&covariances), boundary_points_in_sensor, &same_type, config).unwrap_or(first)
}

/// Scales the boundary extents `d` of a patch (not a quad's angle) and their covariance rows/columns.
fn rescale_boundary(patch: &mut Patch, factor: f64) {
    let extents = patch.boundary.num_extents();
    for (i, d) in patch.boundary_params.iter_mut().enumerate().take(extents) {
        *d *= factor;
        if i < patch.covariance.nrows() {
            patch.covariance.row_mut(i).scale_mut(factor);
            patch.covariance.column_mut(i).scale_mut(factor);
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn plane_factor_is_j_step5_over_iros_eq30() {
        // λ√v = 0.98 r for the uniform disc, IROS eq 30: 1.22 r.
        assert!((plane_boundary_factor(0.95) - 1.96 / 2.4477).abs() < 1e-3);
    }

    #[test]
    fn a_disc_of_points_gives_a_plane_sized_by_step5() {
        let r = 0.05;
        let mut points = Vec::new();
        for i in -20..=20 {
            for j in -20..=20 {
                let (x, y) = (f64::from(i) * r / 20.0, f64::from(j) * r / 20.0);
                if x * x + y * y <= r * r {
                    points.push(Vector3::new(x, y, 1.0));
                }
            }
        }
        let config = NeighbourhoodFit { sensor: ErrorModel::Constant { sigma_m: 0.001 }, ..NeighbourhoodFit::default() };
        let sized = fit_neighbourhood(&points, &points, &config).unwrap();
        let iros = fit_neighbourhood(&points, &points, &NeighbourhoodFit { plane_boundary_j_step5: false, ..config }).unwrap();
        assert_eq!(sized.surface, SurfaceType::Plane);
        let ratio = sized.boundary_params[0] / iros.boundary_params[0];
        assert!((ratio - plane_boundary_factor(0.95)).abs() < 1e-9, "{ratio}");
        assert!((sized.boundary_params[0] - r).abs() < 0.1 * r, "{sized:?}");
    }

    /// Mean offset of the fitted plane from the truth along its normal, over its scatter, for a
    /// plane facing the camera at 1.5 m sampled with Kinect noise (150 points, 300 samplings):
    /// covariances taken at the measured depths pull it towards the camera (the truth lies behind
    /// it); evaluated on the first fit's surface they do not.
    #[test]
    fn covariances_on_the_surface_remove_the_pull_towards_the_camera() {
        use crate::fit::simulate::{mean_over_scatter, sample_sensor};
        use crate::fit::FitConfig;
        use crate::patch::tests::disc_facing_the_camera;
        use rand::SeedableRng;
        let mut truth = disc_facing_the_camera();
        truth.center.z = 1.5;
        let offset_over_scatter = |on: bool| {
            let mut rng = rand::rngs::StdRng::seed_from_u64(41);
            let config =
                NeighbourhoodFit { fit: FitConfig { covariances_on_surface: on, ..FitConfig::default() }, ..NeighbourhoodFit::default() };
            let offsets: Vec<f64> = (0..300)
                .filter_map(|_| {
                    let (points, _) = sample_sensor(&mut rng, &truth, 150, &ErrorModel::default());
                    let fit = fit_neighbourhood(&points, &points, &config).ok()?;
                    Some(-0.5 * fit.implicit_local(&fit.to_local(&truth.center)))
                })
                .collect();
            mean_over_scatter(&offsets)
        };
        let (measured, on_surface) = (offset_over_scatter(false), offset_over_scatter(true));
        eprintln!("mean offset / scatter: covariances at the measured points {measured:+.3}, on the surface {on_surface:+.3}");
        assert!(measured < -0.1, "{measured}");
        assert!(on_surface.abs() < 0.5 * measured.abs(), "{on_surface} vs {measured}");
    }
}

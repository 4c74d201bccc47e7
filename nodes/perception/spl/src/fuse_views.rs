//! Simulated re-observations of one patch, for the fusion's tests and benches: a random patch of a
//! given type lying in a z-up world frame, and views of it from cameras looking down at it, each
//! fitted in its camera frame (Murray–Little noise, J eq 2) and moved to the world with its Σ.

use nalgebra::{Isometry3, Translation3, UnitQuaternion, Vector3};
use rand::Rng;

use crate::fit::neighbourhood::refit_on_surface;
use crate::fit::simulate::{random_visible_patch, sample_sensor, SceneConfig};
use crate::fit::{fit_patch, BoundaryRequest, FitConfig, FitRequest, SurfaceRequest};
use crate::geometry::exp_map;
use crate::patch::{BoundaryType, Patch, SurfaceType};
use crate::sensor::ErrorModel;
use crate::transform::transform_patch;

/// One simulated view of `truth` (world frame, z up) from a camera looking down at it from a
/// random direction within `max_angle` of the vertical, at 0.8–1.2 m: the fit in the camera frame
/// moved to the world with its Σ.
pub fn observe<R: Rng>(rng: &mut R, truth: &Patch, points: usize, max_angle: f64) -> Option<Patch> {
    let tilt = rng.random_range(0.0..max_angle);
    let azimuth = rng.random_range(0.0..std::f64::consts::TAU);
    let towards_camera = Vector3::new(tilt.sin() * azimuth.cos(), tilt.sin() * azimuth.sin(), tilt.cos());
    let eye = truth.center + towards_camera * rng.random_range(0.8..1.2);
    // Camera z towards the patch centre, a random roll.
    let z = -towards_camera;
    let roll = rng.random_range(0.0..std::f64::consts::TAU);
    let base = crate::geometry::rotation_from_normal(&z) * exp_map(&Vector3::new(0.0, 0.0, roll));
    let world_from_camera = Isometry3::from_parts(
        Translation3::from(eye),
        UnitQuaternion::from_rotation_matrix(&nalgebra::Rotation3::from_matrix_unchecked(base)),
    );
    let in_camera = transform_patch(truth, &world_from_camera.inverse())?;
    let (pts, covs) = sample_sensor(rng, &in_camera, points, &ErrorModel::default());
    let request = FitRequest {
        surface: SurfaceRequest::Exactly(truth.surface),
        boundary: BoundaryRequest::Exactly(truth.boundary),
        ..FitRequest::default()
    };
    let config = FitConfig::default();
    let first = fit_patch(&pts, Some(&covs), &request, &config).ok()?;
    let fit = refit_on_surface(first, &pts, &pts, &ErrorModel::default(), &request, &config);
    transform_patch(&fit, &world_from_camera)
}

/// A random patch of the type in the world frame (z up): a camera-facing patch of the simulator
/// turned so its normal points up.
pub fn world_truth<R: Rng>(rng: &mut R, s: SurfaceType, b: BoundaryType) -> Option<Patch> {
    let scene = SceneConfig { max_tilt: 0.3, ..SceneConfig::default() };
    let in_camera = random_visible_patch(rng, s, b, &scene).ok()?;
    // Camera frame → a world whose z is the camera's −z (x kept); the centre is then placed at
    // random in a 1 m square of the ground plane.
    let flip = Isometry3::from_parts(Translation3::identity(), UnitQuaternion::from_axis_angle(&Vector3::x_axis(), std::f64::consts::PI));
    let mut t = transform_patch(&in_camera, &flip)?;
    t.center = Vector3::new(rng.random_range(-0.5..0.5), rng.random_range(-0.5..0.5), 0.0);
    Some(t)
}

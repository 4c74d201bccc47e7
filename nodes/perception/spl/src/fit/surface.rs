//! IROS IV steps 1–3, the unbounded surface: the least-squares plane (step 1-i), the weighted
//! Levenberg–Marquardt runs of [`super::wlm`] (steps 1-ii and 2, eq 33–41) started from a linear
//! least-squares quadric, the step-3 discrimination of [`super::classify`] and the constrained refit
//! of the chosen type.

use super::classify::{by_sign, classify, Curvature};
use super::request::{settings_for, FitConfig, Target};
use super::wlm::{self, LmSettings, Model, PointSet, SurfaceState};
use super::FitError;
use crate::geometry::exp_map;
use crate::patch::{BoundaryType, SurfaceType};
use nalgebra::{Matrix2, Matrix3, SMatrix, Vector2, Vector3};

/// Step 1-i: least-squares plane through the centroid; the normal faces the viewpoint.
pub(super) fn lls_plane(points: &[Vector3<f64>], viewpoint: &Vector3<f64>) -> Result<(Vector3<f64>, Vector3<f64>), FitError> {
    let n = points.len() as f64;
    let centroid = points.iter().sum::<Vector3<f64>>() / n;
    let scatter = points.iter().fold(Matrix3::zeros(), |acc, q| {
        let d = q - centroid;
        acc + d * d.transpose()
    });
    let eig = scatter.symmetric_eigen();
    let mut order = [0usize, 1, 2];
    order.sort_by(|&a, &b| eig.eigenvalues[a].total_cmp(&eig.eigenvalues[b]));
    let (lmin, lmid, lmax) = (eig.eigenvalues[order[0]], eig.eigenvalues[order[1]], eig.eigenvalues[order[2]]);
    if lmax.is_nan() || lmax <= 0.0 {
        return Err(FitError::Degenerate("all points are equal"));
    }
    if lmid <= 1e-10 * lmax {
        return Err(FitError::Degenerate("points are collinear"));
    }
    let _ = lmin;
    let mut normal = eig.eigenvectors.column(order[0]).into_owned();
    if normal.dot(&(viewpoint - centroid)) < 0.0 {
        normal = -normal;
    }
    Ok((centroid, normal))
}

/// Swap local x/y so that `|κx| ≤ |κy|` (IROS footnote 5): `R ← R [ŷ −x̂ ẑ]`.
fn order_axes(state: SurfaceState) -> (SurfaceState, bool) {
    if state.k3.x.abs() <= state.k3.y.abs() {
        return (state, false);
    }
    (swap_axes(&state), true)
}

fn swap_axes(state: &SurfaceState) -> SurfaceState {
    let q = Matrix3::new(0.0, -1.0, 0.0, 1.0, 0.0, 0.0, 0.0, 0.0, 1.0);
    SurfaceState { k3: Vector3::new(state.k3.y, state.k3.x, state.k3.z), rot: state.rot * q, c: state.c }
}

/// Covariance scale of the WLM information: the residual variance without point covariances,
/// otherwise `max(1, χ²/(N − m))` if configured.
pub(super) fn residual_scale(chi2: f64, n: usize, m: usize, weighted: bool, config: &FitConfig) -> f64 {
    let dof = n.saturating_sub(m).max(1) as f64;
    let s2 = chi2 / dof;
    if !weighted {
        s2
    } else if config.inflate_by_residual {
        s2.max(1.0)
    } else {
        1.0
    }
}

/// Steps 1-ii to 3: fit the unbounded surface of the requested (or discriminated) type.
pub(super) fn fit_surface(
    target: Target,
    start: SurfaceState,
    points: &[Vector3<f64>],
    covs: &PointSet,
    settings: &LmSettings,
    config: &FitConfig,
    weighted: bool,
) -> Result<(SurfaceType, BoundaryType, SurfaceState), FitError> {
    match target {
        Target::Fixed(SurfaceType::Plane, b) => {
            Ok((SurfaceType::Plane, b, wlm::run(Model::Plane, start, covs, &settings_for(Model::Plane, settings, config))?))
        }
        Target::Fixed(SurfaceType::Sphere, b) => {
            Ok((SurfaceType::Sphere, b, wlm::run(Model::Sphere, start, covs, &settings_for(Model::Sphere, settings, config))?))
        }
        _ => {
            // Step 2: general paraboloid, started from the LLS quadric graph over the plane.
            let par = wlm::run_with_normal(
                Model::Paraboloid,
                quadric_start(&start, points),
                covs,
                &settings_for(Model::Paraboloid, settings, config),
            )?;
            let (state, swapped) = order_axes(par.state);
            let surface = match target {
                Target::Auto(_) => {
                    let normal = &par.normal;
                    let scale = residual_scale(normal.chi2, points.len(), Model::Paraboloid.num_free(), weighted, config);
                    let mut ck = wlm::inverse_leading(Model::Paraboloid.num_free(), &normal.h)
                        .map(|inv| inv.fixed_view::<2, 2>(0, 0).into_owned() * scale)
                        .unwrap_or_else(|| Matrix2::identity() * f64::INFINITY);
                    if swapped {
                        ck = Matrix2::new(ck[(1, 1)], ck[(1, 0)], ck[(0, 1)], ck[(0, 0)]);
                    }
                    match classify(&state.k3.xy(), &ck, config.significance) {
                        Curvature::Plane => SurfaceType::Plane,
                        Curvature::Circular => SurfaceType::CircularParaboloid,
                        Curvature::Cylindric(_) => SurfaceType::CylindricParaboloid,
                        Curvature::Full => by_sign(&state.k3),
                    }
                }
                Target::Paraboloid => by_sign(&state.k3),
                Target::Fixed(s, _) => s,
            };
            let boundary = match target {
                Target::Auto(b) if surface == SurfaceType::Plane => b,
                Target::Fixed(_, b) => b,
                _ => surface.implied_boundary().unwrap_or(BoundaryType::Ellipse),
            };
            let k = state.k3;
            let refit = |model: Model, k3: Vector3<f64>, st: SurfaceState| -> Result<SurfaceState, FitError> {
                wlm::run(model, SurfaceState { k3, ..st }, covs, &settings_for(model, settings, config))
            };
            let state = match surface {
                SurfaceType::Plane => refit(Model::Plane, Vector3::zeros(), state)?,
                SurfaceType::CircularParaboloid => {
                    let m = 0.5 * (k.x + k.y);
                    refit(Model::CircularParaboloid, Vector3::new(m, m, 0.0), state)?
                }
                SurfaceType::CylindricParaboloid => {
                    // The curved direction is local y (|κx| ≤ |κy| after ordering).
                    refit(Model::CylindricParaboloid, Vector3::new(0.0, k.y, 0.0), state)?
                }
                SurfaceType::CircularCylinder => refit(Model::Cylinder, Vector3::new(0.0, k.y, k.y), state)?,
                SurfaceType::Sphere => refit(Model::Sphere, Vector3::new(0.5 * (k.x + k.y), 0.5 * (k.x + k.y), 0.5 * (k.x + k.y)), state)?,
                SurfaceType::EllipticParaboloid | SurfaceType::HyperbolicParaboloid => {
                    if by_sign(&k) != surface {
                        return Err(FitError::ConstraintViolated(format!(
                            "{} requested but the fitted curvatures are ({:.3}, {:.3})",
                            surface.name(),
                            k.x,
                            k.y
                        )));
                    }
                    state
                }
            };
            Ok((surface, boundary, state))
        }
    }
}

/// Initial paraboloid for step 2 by linear least squares (cf. IROS \[5\]): in the step-1 plane frame fit
/// the graph `z = ½ uᵀ A u + gᵀ u + h`; the principal axes of `A` give the local x/y axes and
/// curvatures, and the stationary point `−A⁻¹ g` the apex (kept at the centroid along directions
/// whose curvature does not determine it within the data extent). Falls back to the plane.
fn quadric_start(plane: &SurfaceState, points: &[Vector3<f64>]) -> SurfaceState {
    let rt = plane.rot.transpose();
    let mut ata = SMatrix::<f64, 6, 6>::zeros();
    let mut atb = SMatrix::<f64, 6, 1>::zeros();
    let mut extent = 0.0f64;
    for q in points {
        let l = rt * (q - plane.c);
        let row = SMatrix::<f64, 6, 1>::from_column_slice(&[0.5 * l.x * l.x, l.x * l.y, 0.5 * l.y * l.y, l.x, l.y, 1.0]);
        // Lower triangle only: the Cholesky factorisation below reads nothing else.
        for c in 0..6 {
            for r in c..6 {
                ata[(r, c)] += row[r] * row[c];
            }
        }
        atb.axpy(l.z, &row, 1.0);
        extent = extent.max(l.x * l.x + l.y * l.y);
    }
    let Some(sol) = ata.cholesky().map(|c| c.solve(&atb)) else { return *plane };
    let a = Matrix2::new(sol[0], sol[1], sol[1], sol[2]);
    let g = Vector2::new(sol[3], sol[4]);
    let eig = a.symmetric_eigen();
    let radius = extent.sqrt();
    let mut apex = Vector2::zeros();
    for i in 0..2 {
        let v = eig.eigenvectors.column(i).into_owned();
        let lam = eig.eigenvalues[i];
        if lam.abs() > 1e-9 {
            let t = -g.dot(&v) / lam;
            if t.abs() < radius {
                apex += v * t;
            }
        }
    }
    let (Some(v0), Some(&k0), Some(&k1)) = (Some(eig.eigenvectors.column(0).into_owned()), eig.eigenvalues.get(0), eig.eigenvalues.get(1))
    else {
        return *plane;
    };
    let z = 0.5 * (apex.transpose() * a * apex)[(0, 0)] + g.dot(&apex) + sol[5];
    let angle = v0.y.atan2(v0.x);
    let rot = plane.rot * exp_map(&Vector3::new(0.0, 0.0, angle));
    let state = SurfaceState { k3: Vector3::new(k0, k1, 0.0), rot, c: plane.c + plane.rot * Vector3::new(apex.x, apex.y, z) };
    if state.k3.iter().chain(state.c.iter()).all(|v| v.is_finite()) {
        state
    } else {
        *plane
    }
}

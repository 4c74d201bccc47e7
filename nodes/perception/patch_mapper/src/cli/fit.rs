//! `patch_mapper fit`: fit one patch to a point file (CSV or PLY) and print it as one JSON line
//! (IROS IV fit + J 3.3 validation).

use anyhow::{bail, Context, Result};
use nalgebra::Vector3;
use patchwalk_spl::fit::{fit_patch, BoundaryRequest, FitConfig, FitRequest, SurfaceRequest};
use patchwalk_spl::patch::{BoundaryType, PatchJson, SurfaceType};
use patchwalk_spl::points_io::read_points;
use patchwalk_spl::sensor::{covariances_for, ErrorModel};
use patchwalk_spl::validate::{validate_patch, ValidateConfig};
use serde::Serialize;
use std::path::PathBuf;
use std::time::Instant;

/// Arguments of `patch_mapper fit`.
#[derive(clap::Args, Debug)]
pub struct FitArgs {
    /// Points file: CSV `x,y,z` or `x,y,z,cxx,cyy,czz,cxy,cyz,cxz` (one point per line), or PLY.
    pub points: PathBuf,
    /// Surface: auto (IROS paraboloid family with discrimination), paraboloid, plane, sphere,
    /// cylinder, or a full type name (elliptic_paraboloid, ..., circular_cylinder).
    #[arg(long, default_value = "auto")]
    pub surface: String,
    /// Boundary: ellipse, circle, rect, quad (free only for planes; default: implied by the surface).
    #[arg(long)]
    pub boundary: Option<String>,
    /// Sensor position `x,y,z` in the points' frame (axes of the camera optical frame): the patch
    /// normal faces it and the error model is evaluated from it.
    #[arg(long, value_parser = parse_vec3, allow_hyphen_values = true)]
    pub sensor_origin: Option<Vector3<f64>>,
    /// Point error model when the file has no covariances: kinect (Murray–Little, J eq 2) or none
    /// (unweighted, covariance scaled by the residual).
    #[arg(long, default_value = "none")]
    pub error_model: String,
    /// Boundary containment probability Γ ∈ (0, 1].
    #[arg(long, default_value_t = 0.95)]
    pub containment: f64,
}

fn parse_vec3(s: &str) -> Result<Vector3<f64>, String> {
    let v: Vec<f64> =
        s.split(',').map(|p| p.trim().parse::<f64>()).collect::<Result<_, _>>().map_err(|e| format!("expected x,y,z: {e}"))?;
    match v.as_slice() {
        [x, y, z] if v.iter().all(|c| c.is_finite()) => Ok(Vector3::new(*x, *y, *z)),
        _ => Err(format!("expected three finite numbers x,y,z, got '{s}'")),
    }
}

fn surface_request(name: &str) -> Result<SurfaceRequest> {
    Ok(match name {
        "auto" => SurfaceRequest::Auto,
        "paraboloid" => SurfaceRequest::Paraboloid,
        "cylinder" => SurfaceRequest::Exactly(SurfaceType::CircularCylinder),
        other => SurfaceRequest::Exactly(SurfaceType::from_name(other).with_context(|| format!("unknown surface '{other}'"))?),
    })
}

#[derive(Serialize)]
struct FitOutput {
    #[serde(flatten)]
    patch: PatchJson,
    coverage_ok: bool,
    curvature_ok: bool,
    valid: bool,
    failures: Vec<String>,
    fit_us: f64,
}

/// Run `patch_mapper fit`.
pub fn run(args: FitArgs) -> Result<()> {
    let set = read_points(&args.points).with_context(|| format!("reading {}", args.points.display()))?;
    let origin = args.sensor_origin.unwrap_or_else(Vector3::zeros);
    let covariances = match (set.covariances, args.error_model.as_str()) {
        (Some(c), _) => Some(c),
        (None, "none") => None,
        (None, "kinect") => Some(covariances_for(&set.points, &origin, &ErrorModel::default()).context("kinect error model")?),
        (None, other) => bail!("unknown error model '{other}' (kinect|none)"),
    };
    let boundary = match &args.boundary {
        None => BoundaryRequest::Auto,
        Some(b) => BoundaryRequest::Exactly(
            BoundaryType::from_name(b).with_context(|| format!("unknown boundary '{b}' (ellipse|circle|rect|quad)"))?,
        ),
    };
    let request = FitRequest { surface: surface_request(&args.surface)?, boundary, containment: args.containment, viewpoint: origin };
    let start = Instant::now();
    let patch = fit_patch(&set.points, covariances.as_deref(), &request, &FitConfig::default())?;
    let fit_us = start.elapsed().as_secs_f64() * 1e6;
    let validation = validate_patch(&patch, &set.points, &ValidateConfig::default());
    let mut json = PatchJson::from(patch);
    json.residual = validation.residual.value;
    let out = FitOutput {
        patch: json,
        coverage_ok: validation.coverage.passed,
        curvature_ok: validation.curvature_ok(),
        valid: validation.is_valid(),
        failures: validation.failures(),
        fit_us,
    };
    println!("{}", serde_json::to_string(&out)?);
    Ok(())
}

//! `patch_mapper fit`: fit one patch to a point file (CSV or PLY) and print it as one JSON line
//! (IROS IV fit + J 3.3 validation).

use anyhow::{bail, Context, Result};
use nalgebra::Vector3;
use patchwalk_mapping::record::PatchRecord;
use patchwalk_spl::fit::{fit_patch, BoundaryRequest, FitConfig, FitRequest, SurfaceRequest};
use patchwalk_spl::patch::{BoundaryType, SurfaceType};
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
    #[arg(long, value_parser = super::parse_vec3, allow_hyphen_values = true)]
    pub sensor_origin: Option<Vector3<f64>>,
    /// Point error model when the file has no covariances: kinect (Murray–Little, J eq 2) or none
    /// (unweighted, covariance scaled by the residual).
    #[arg(long, default_value = "none")]
    pub error_model: String,
    /// Boundary containment probability Γ ∈ (0, 1].
    #[arg(long, default_value_t = 0.95)]
    pub containment: f64,
}

fn surface_request(name: &str) -> Result<SurfaceRequest> {
    Ok(match name {
        "auto" => SurfaceRequest::Auto,
        "paraboloid" => SurfaceRequest::Paraboloid,
        "cylinder" => SurfaceRequest::Exactly(SurfaceType::CircularCylinder),
        other => SurfaceRequest::Exactly(SurfaceType::from_name(other).with_context(|| format!("unknown surface '{other}'"))?),
    })
}

/// The JSON line of `patch_mapper fit`: the patch record (with `valid`, `verdict`, `failures`) and
/// the fit's own extras.
#[derive(Serialize)]
struct FitOutput {
    #[serde(flatten)]
    record: PatchRecord,
    coverage_ok: bool,
    curvature_ok: bool,
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
    let mut patch = fit_patch(&set.points, covariances.as_deref(), &request, &FitConfig::default())?;
    let fit_us = start.elapsed().as_secs_f64() * 1e6;
    let validation = validate_patch(&patch, &set.points, &ValidateConfig::default());
    // The residual reported is validation's (J eq 15: Euclidean distances to the bounded patch).
    patch.residual = validation.residual.value;
    let out = FitOutput {
        record: PatchRecord::validated(patch, &validation),
        coverage_ok: validation.coverage.passed,
        curvature_ok: validation.curvature_ok(),
        fit_us,
    };
    println!("{}", serde_json::to_string(&out)?);
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn output_parses_into_the_patch_record() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("disc.csv");
        let text: String =
            (0..400).map(|i| format!("{},{},1.0\n", f64::from(i % 20) * 0.004 - 0.04, f64::from(i / 20) * 0.004 - 0.04)).collect();
        std::fs::write(&path, text).unwrap();
        let set = read_points(&path).unwrap();
        let patch = fit_patch(&set.points, None, &FitRequest::default(), &FitConfig::default()).unwrap();
        let validation = validate_patch(&patch, &set.points, &ValidateConfig::default());
        let out = FitOutput { record: PatchRecord::validated(patch, &validation), coverage_ok: true, curvature_ok: true, fit_us: 1.0 };
        let line = serde_json::to_string(&out).unwrap();
        let record: PatchRecord = serde_json::from_str(&line).unwrap();
        // serde_json's float parsing may differ from the written value in the last bit.
        assert_eq!((record.valid, &record.verdict, &record.failures), (out.record.valid, &out.record.verdict, &out.record.failures));
        assert_eq!(
            (record.patch.surface, record.patch.boundary, record.patch.num_points),
            (out.record.patch.surface, out.record.patch.boundary, 400)
        );
        assert!((record.patch.params() - out.record.patch.params()).norm() < 1e-12);
        let value: serde_json::Value = serde_json::from_str(&line).unwrap();
        assert!(value["valid"].is_boolean() && value["verdict"].is_string() && value["failures"].is_array(), "{line}");
    }
}

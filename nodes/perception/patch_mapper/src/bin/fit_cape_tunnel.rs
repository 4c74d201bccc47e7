//! Real-data check of the patch fit on the CAPE tunnel frame (`tests/data/cape_tunnel`, a cylindrical
//! tunnel wall and a flat floor, Kinect-like IR depth): fits the wall window as a circular cylinder,
//! the floor window as a plane, and both with `surface auto`; prints curvature/radius, residuals
//! and validation.
//!
//! `cargo run --release -p patch_mapper --bin fit_cape_tunnel -- [path/to/depth_0.png]`

use anyhow::{Context, Result};
use nalgebra::Vector3;
use patchwalk_spl::fit::{fit_patch, FitConfig, FitRequest, SurfaceRequest};
use patchwalk_spl::patch::SurfaceType;
use patchwalk_spl::sensor::{covariances_for, ErrorModel};
use patchwalk_spl::validate::{validate_patch, ValidateConfig};
use std::time::Instant;

/// IR intrinsics from `calib_params.xml` (fx, fy, cx, cy).
const INTRINSICS: (f64, f64, f64, f64) = (575.9, 576.4, 315.2, 230.6);

fn load_depth(path: &str) -> Result<(usize, usize, Vec<u16>)> {
    let bytes = std::fs::read(path).with_context(|| format!("reading {path}"))?;
    let mut reader = png::Decoder::new(std::io::Cursor::new(bytes)).read_info()?;
    let mut buf = vec![0u8; reader.output_buffer_size().context("png size")?];
    let info = reader.next_frame(&mut buf)?;
    anyhow::ensure!(info.bit_depth == png::BitDepth::Sixteen, "expected a 16-bit depth PNG");
    let depth = buf.chunks_exact(2).map(|c| u16::from_be_bytes([c[0], c[1]])).collect();
    Ok((info.width as usize, info.height as usize, depth))
}

/// Back-project every `step`-th pixel of a window (depth in mm) into the camera optical frame.
fn window(depth: &[u16], width: usize, (u0, v0, u1, v1): (usize, usize, usize, usize), step: usize) -> Vec<Vector3<f64>> {
    let (fx, fy, cx, cy) = INTRINSICS;
    let mut pts = Vec::new();
    for v in (v0..v1).step_by(step) {
        for u in (u0..u1).step_by(step) {
            let Some(&d) = depth.get(v * width + u) else { continue };
            if d == 0 {
                continue;
            }
            let z = d as f64 / 1000.0;
            pts.push(Vector3::new((u as f64 - cx) * z / fx, (v as f64 - cy) * z / fy, z));
        }
    }
    pts
}

fn main() -> Result<()> {
    let path = std::env::args().nth(1).unwrap_or_else(|| "tests/data/cape_tunnel/depth_0.png".into());
    let (w, _h, depth) = load_depth(&path)?;
    let cases = [("wall (u 20-180, v 150-330)", (20, 150, 180, 330)), ("floor (u 440-620, v 380-470)", (440, 380, 620, 470))];
    let model = ErrorModel::default();
    for (name, win) in cases {
        // Dense points for validation, a 150-point subsample for the fit (the mapper's nf).
        let dense = window(&depth, w, win, 2);
        let stride = (dense.len() / 150).max(1);
        let fit_pts: Vec<_> = dense.iter().step_by(stride).copied().collect();
        let covs = covariances_for(&fit_pts, &Vector3::zeros(), &model)?;
        println!("== {name}: {} dense points, {} fit points", dense.len(), fit_pts.len());
        for (label, surface) in [
            ("auto", SurfaceRequest::Auto),
            ("cylinder", SurfaceRequest::Exactly(SurfaceType::CircularCylinder)),
            ("plane", SurfaceRequest::Exactly(SurfaceType::Plane)),
        ] {
            let request = FitRequest { surface, ..FitRequest::default() };
            let t0 = Instant::now();
            match fit_patch(&fit_pts, Some(&covs), &request, &FitConfig::default()) {
                Ok(p) => {
                    let us = t0.elapsed().as_secs_f64() * 1e6;
                    let val = validate_patch(&p, &dense, &ValidateConfig::default());
                    let k = p.curvatures;
                    let kmax = if k.x.abs() > k.y.abs() { k.x } else { k.y };
                    let sd: Vec<String> = p.covariance.diagonal().iter().map(|v| format!("{:.2e}", v.max(0.0).sqrt())).collect();
                    println!(
                        "  {label:<9} -> {:<22} κ = ({:+.3}, {:+.3}) 1/m  radius {:.3} m  normal {:.3?}  RMS residual {:.2} mm  valid {} {:?}  fit {:.0} µs",
                        p.surface.name(),
                        k.x,
                        k.y,
                        if kmax != 0.0 { 1.0 / kmax.abs() } else { f64::INFINITY },
                        p.normal().as_slice(),
                        val.residual.value * 1000.0,
                        val.is_valid(),
                        val.failures(),
                        us
                    );
                    println!("            σ(params) = [{}]", sd.join(", "));
                }
                Err(e) => println!("  {label:<9} -> error: {e}"),
            }
        }
    }
    Ok(())
}

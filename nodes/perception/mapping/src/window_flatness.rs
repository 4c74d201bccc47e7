//! How far the points of a pixel's foot window lie off a plane: the RMS distance along the window's
//! normal, from summed-area tables of the points and their second moments.
//!
//! J's DoN (step 6.4) compares the normals of two windows; a surface whose normals agree can still
//! be a step of a few centimetres or a tight bump, which the fit then drapes (J 3.3's curvature
//! limit) or the foot disc straddles (the foothold edge test). The spread of the window's points
//! about their plane says so before any patch is fitted: for a paraboloid of curvature κ over a disc
//! of radius r it is `κ r² / √48` (7 mm at J's κ_max = 19.7 m⁻¹ and r = 5 cm), over the square of half
//! side r the saliency's foot window covers `κ r² √(2/45)` (10.4 mm), and a step of height h
//! through a window's middle gives about h/2 about the window's mean.

use nalgebra::{Matrix3, Vector3};
use rayon::prelude::*;

use patchwalk_fusion::camera::{DepthImage, Intrinsics};

/// Summed-area table (`(width + 1) × (height + 1)`, row 0 and column 0 zero) of `channels(p)` over
/// the back-projected points of D; invalid pixels add nothing. The per-row prefix sums run in
/// parallel; each entry is then `above + row prefix`, the same additions in the same order as a
/// sequential pass.
pub(crate) fn summed_area_table<const C: usize>(
    depth: &DepthImage,
    intrinsics: &Intrinsics,
    channels: impl Fn(&Vector3<f64>) -> [f64; C] + Sync,
) -> Vec<[f64; C]> {
    let (width, height) = (depth.width, depth.height);
    let stride = width + 1;
    let mut sums = vec![[0.0f64; C]; stride * (height + 1)];
    sums.par_chunks_mut(stride).skip(1).zip(depth.depth_m.par_chunks(width.max(1))).enumerate().for_each(|(v, (out, src))| {
        let mut row = [0.0f64; C];
        for (u, (o, &z)) in out.iter_mut().skip(1).zip(src).enumerate() {
            let z = f64::from(z);
            if z.is_finite() {
                let c = channels(&intrinsics.back_project(u as f64, v as f64, z));
                for (r, c) in row.iter_mut().zip(c) {
                    *r += c;
                }
            }
            *o = row;
        }
    });
    for v in 1..height {
        let (done, rest) = sums.split_at_mut((v + 1) * stride);
        let (above, row) = (&done[v * stride..], &mut rest[..stride]);
        for (r, a) in row.iter_mut().zip(above) {
            for (r, a) in r.iter_mut().zip(a) {
                *r += a;
            }
        }
    }
    sums
}

/// Points (x, y, z, count) and second moments (xx, xy, xz, yy, yz, zz) of D, summed.
#[derive(Debug, Clone)]
pub struct WindowMoments {
    width: usize,
    height: usize,
    sums: Vec<[f64; 10]>,
}

impl WindowMoments {
    pub fn new(depth: &DepthImage, intrinsics: &Intrinsics) -> Self {
        let sums = summed_area_table(depth, intrinsics, |p| {
            [p.x, p.y, p.z, 1.0, p.x * p.x, p.x * p.y, p.x * p.z, p.y * p.y, p.y * p.z, p.z * p.z]
        });
        Self { width: depth.width, height: depth.height, sums }
    }

    /// RMS distance (m) of the valid points of the window `[u − half, u + half]²` (clipped to the
    /// image) from the plane through their mean with unit normal `normal`; `None` with fewer than
    /// `min_points` points.
    pub fn rms_off_plane(&self, u: usize, v: usize, half: usize, normal: &Vector3<f64>, min_points: f64) -> Option<f64> {
        let (u0, u1) = (u.saturating_sub(half), (u + half + 1).min(self.width));
        let (v0, v1) = (v.saturating_sub(half), (v + half + 1).min(self.height));
        if u0 >= u1 || v0 >= v1 {
            return None;
        }
        let stride = self.width + 1;
        let at = |r: usize, c: usize| self.sums.get(r * stride + c).copied().unwrap_or([0.0; 10]);
        let (a, b, c, d) = (at(v1, u1), at(v1, u0), at(v0, u1), at(v0, u0));
        let s: [f64; 10] = std::array::from_fn(|i| a[i] - b[i] - c[i] + d[i]);
        let n = s[3];
        if n.is_nan() || n < min_points.max(3.0) {
            return None;
        }
        let mean = Vector3::new(s[0], s[1], s[2]) / n;
        let second = Matrix3::new(s[4], s[5], s[6], s[5], s[7], s[8], s[6], s[8], s[9]) / n;
        let variance = normal.dot(&(second * normal)) - normal.dot(&mean).powi(2);
        Some(variance.max(0.0).sqrt())
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::saliency::tests::{render, small_camera};

    #[test]
    fn a_plane_is_flat_and_a_step_is_not() {
        // Looking straight down at a floor 1 m away; a 3 cm step at x = 0.
        let intrinsics = small_camera();
        let floor = render(&intrinsics, |p| 1.0 - p.z);
        let step = render(&intrinsics, |p| if p.x < 0.0 { 0.97 - p.z } else { 1.0 - p.z });
        let n = Vector3::new(0.0, 0.0, -1.0);
        let half = 7;
        let flat = WindowMoments::new(&floor, &intrinsics);
        let rms = flat.rms_off_plane(80, 60, half, &n, 10.0).unwrap();
        assert!(rms < 1e-5, "{rms}");
        let stepped = WindowMoments::new(&step, &intrinsics);
        // The window centred on the step: half its points 3 cm above the other half, RMS 1.5 cm.
        let rms = stepped.rms_off_plane(80, 60, half, &n, 10.0).unwrap();
        assert!((rms - 0.015).abs() < 0.002, "{rms}");
        // A window clear of the step is flat again.
        let rms = stepped.rms_off_plane(40, 60, half, &n, 10.0).unwrap();
        assert!(rms < 1e-5, "{rms}");
        // Off the image: no points.
        assert!(flat.rms_off_plane(500, 500, half, &n, 10.0).is_none());
    }

    #[test]
    fn a_paraboloid_spreads_as_its_curvature() {
        // z = 1 − κ/2 (x² + y²) seen from above: the tables' RMS equals the one computed point
        // by point over the same window.
        let intrinsics = small_camera();
        let kappa = 20.0;
        let depth = render(&intrinsics, |p| 1.0 - kappa / 2.0 * (p.x * p.x + p.y * p.y) - p.z);
        let moments = WindowMoments::new(&depth, &intrinsics);
        let half = 7;
        let (u, v) = (80usize, 60usize);
        let mut points = Vec::new();
        for y in v - half..=v + half {
            for x in u - half..=u + half {
                if let Some(z) = depth.get(x, y) {
                    points.push(intrinsics.back_project(x as f64, y as f64, f64::from(z)));
                }
            }
        }
        let n = Vector3::new(0.0, 0.0, -1.0);
        let mean = points.iter().map(|p| n.dot(p)).sum::<f64>() / points.len() as f64;
        let expected = (points.iter().map(|p| (n.dot(p) - mean).powi(2)).sum::<f64>() / points.len() as f64).sqrt();
        let rms = moments.rms_off_plane(u, v, half, &n, 10.0).unwrap();
        assert!(expected > 1e-3 && (rms - expected).abs() < 1e-5, "{rms} vs {expected}");
    }
}

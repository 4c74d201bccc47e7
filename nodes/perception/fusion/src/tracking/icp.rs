//! Frame-to-model point-to-plane ICP (J 5.1, KinectFusion): the new frame's depth pyramid (1/4, 1/2,
//! 1 resolution, coarse to fine), projective data association against the model raycast, Huber
//! weights and a distance gate, and the 6×6 Gauss–Newton normal equations summed in parallel (f32
//! over batches of 64 inliers, f64 totals).

use super::{IcpConfig, IcpSummary};
use crate::camera::{DepthImage, Intrinsics};
use crate::fusion::floor_small;
use crate::raycast::ModelRaycast;
use nalgebra::{Isometry3, Matrix6, Point3, Translation3, UnitQuaternion, Vector3, Vector6};
use rayon::prelude::*;

/// One pyramid level of the new frame: intrinsics and its valid points in the camera frame.
pub struct SourceLevel {
    pub intrinsics: Intrinsics,
    pub points_in_camera: Vec<Vector3<f32>>,
}

/// Depth pyramid, coarsest first (1/4, 1/2, 1 of the input resolution).
pub fn build_pyramid(depth: &DepthImage, intrinsics: &Intrinsics, depth_jump_m: f32) -> Vec<SourceLevel> {
    let half = downsample(depth, depth_jump_m);
    let quarter = downsample(&half, depth_jump_m);
    source_pyramid(&[&quarter, &half, depth], intrinsics, &[1, 1, 1])
}

/// Source levels from depth images at 1/4, 1/2, 1 of the input resolution; levels without ICP
/// iterations stay empty (not back-projected).
pub(super) fn source_pyramid(images: &[&DepthImage; 3], intrinsics: &Intrinsics, iterations: &[usize; 3]) -> Vec<SourceLevel> {
    images
        .iter()
        .zip(iterations)
        .zip([0.25, 0.5, 1.0])
        .map(|((image, &n), scale)| {
            let level_intrinsics = intrinsics.scaled(scale);
            if n == 0 {
                SourceLevel { intrinsics: level_intrinsics, points_in_camera: Vec::new() }
            } else {
                source_level(image, &level_intrinsics)
            }
        })
        .collect()
}

/// 2×2 block average of depths that agree within `depth_jump_m` (NaN otherwise).
pub fn downsample(depth: &DepthImage, depth_jump_m: f32) -> DepthImage {
    let (width, height) = (depth.width / 2, depth.height / 2);
    let mut depth_m = vec![f32::NAN; width * height];
    let input_width = depth.width.max(1);
    depth_m.par_chunks_mut(width.max(1)).enumerate().for_each(|(v, row)| {
        // The two input rows of output row v (2v + 1 < height for every output row).
        let top = depth.depth_m.get(2 * v * input_width..(2 * v + 1) * input_width).unwrap_or(&[]);
        let bottom = depth.depth_m.get((2 * v + 1) * input_width..(2 * v + 2) * input_width).unwrap_or(&[]);
        for (u, out) in row.iter_mut().enumerate() {
            let mut sum = 0.0;
            let mut count = 0;
            let (mut lo, mut hi) = (f32::INFINITY, f32::NEG_INFINITY);
            let quad = [top.get(2 * u), top.get(2 * u + 1), bottom.get(2 * u), bottom.get(2 * u + 1)];
            for &d in quad.into_iter().flatten() {
                if d.is_finite() {
                    sum += d;
                    count += 1;
                    lo = lo.min(d);
                    hi = hi.max(d);
                }
            }
            if count >= 2 && hi - lo <= depth_jump_m {
                *out = sum / count as f32;
            }
        }
    });
    DepthImage { width: width.max(1), height: height.max(1), depth_m }
}

fn source_level(depth: &DepthImage, intrinsics: &Intrinsics) -> SourceLevel {
    let (fx, fy, cx, cy) = (intrinsics.fx as f32, intrinsics.fy as f32, intrinsics.cx as f32, intrinsics.cy as f32);
    // Ray slopes per column and row, computed once (no per-pixel division).
    let x_slopes: Vec<f32> = (0..depth.width).map(|u| (u as f32 - cx) / fx).collect();
    let mut points_in_camera = Vec::with_capacity(depth.depth_m.len());
    for (v, row) in depth.depth_m.chunks(depth.width.max(1)).enumerate() {
        let y_slope = (v as f32 - cy) / fy;
        for (&d, x_slope) in row.iter().zip(&x_slopes) {
            if d.is_finite() {
                points_in_camera.push(Vector3::new(x_slope * d, y_slope * d, d));
            }
        }
    }
    SourceLevel { intrinsics: *intrinsics, points_in_camera }
}

/// Result of one ICP run.
#[derive(Debug, Clone, Copy)]
pub struct IcpResult {
    pub volume_from_camera: Isometry3<f64>,
    pub summary: IcpSummary,
    /// Smallest eigenvalue of the last normal matrix divided by the inlier count.
    pub min_eigenvalue: f64,
}

/// Normal equations of point-to-plane ICP: Σ w JᵀJ, Σ w Jᵀr, with statistics.
#[derive(Clone, Copy)]
struct Normal {
    jtj: [f64; 21],
    jtr: [f64; 6],
    inliers: usize,
    /// Source points that landed on a model pixel with a surface (before the distance gate).
    associated: usize,
    squared_residuals: f64,
}

impl Normal {
    fn zero() -> Self {
        Self { jtj: [0.0; 21], jtr: [0.0; 6], inliers: 0, associated: 0, squared_residuals: 0.0 }
    }
    fn add(mut self, other: Self) -> Self {
        for (a, b) in self.jtj.iter_mut().zip(other.jtj.iter()) {
            *a += b;
        }
        for (a, b) in self.jtr.iter_mut().zip(other.jtr.iter()) {
            *a += b;
        }
        self.inliers += other.inliers;
        self.associated += other.associated;
        self.squared_residuals += other.squared_residuals;
        self
    }
    fn matrices(&self) -> (Matrix6<f64>, Vector6<f64>) {
        let mut h = Matrix6::zeros();
        let mut k = 0;
        for r in 0..6 {
            for c in r..6 {
                h[(r, c)] = self.jtj[k];
                h[(c, r)] = self.jtj[k];
                k += 1;
            }
        }
        (h, Vector6::from_column_slice(&self.jtr))
    }
}

/// Frame-to-model point-to-plane ICP (J 5.1), coarse to fine over the source pyramid.
pub fn icp(config: &IcpConfig, pyramid: &[SourceLevel], model: &ModelRaycast, initial: &Isometry3<f64>) -> IcpResult {
    let mut pose = *initial;
    let mut summary = IcpSummary::default();
    // Normal matrix and inlier count of the last successful iteration: its smallest eigenvalue (the
    // degeneracy check) is computed once after the last iteration, not at every iteration.
    let mut last_system: Option<(Matrix6<f64>, usize)> = None;
    let model_from_volume = model.volume_from_camera.inverse().cast::<f32>();
    for (level, source) in pyramid.iter().enumerate() {
        let iterations = config.iterations.get(level).copied().unwrap_or(0);
        let gate = config.max_correspondence_m.get(level).copied().unwrap_or(0.05);
        for _ in 0..iterations {
            let normal = accumulate(source, model, &model_from_volume, &pose, gate as f32, config.huber_m);
            summary = IcpSummary {
                iterations: summary.iterations + 1,
                inliers: normal.inliers,
                valid_source_points: source.points_in_camera.len(),
                associated: normal.associated,
                rms_m: (normal.squared_residuals / normal.inliers.max(1) as f64).sqrt(),
            };
            if normal.inliers < 6 {
                last_system = None;
                break;
            }
            let (h, g) = normal.matrices();
            let Some(cholesky) = h.cholesky() else {
                last_system = None;
                break;
            };
            last_system = Some((h, normal.inliers));
            let delta = cholesky.solve(&(-g));
            let translation = Vector3::new(delta[0], delta[1], delta[2]);
            let rotation = Vector3::new(delta[3], delta[4], delta[5]);
            // Left-multiplied increment: p' ← exp(δ) p'.
            let increment = Isometry3::from_parts(Translation3::from(translation), UnitQuaternion::from_scaled_axis(rotation));
            pose = increment * pose;
            if translation.norm() < config.convergence && rotation.norm() < config.convergence {
                break;
            }
        }
    }
    let min_eigenvalue = last_system.map_or(0.0, |(h, inliers)| h.symmetric_eigenvalues().min() / inliers as f64);
    IcpResult { volume_from_camera: pose, summary, min_eigenvalue }
}

/// Inliers gathered before their products are summed (in f32) and added to the f64 totals: f32
/// rounding over this many terms stays near 1e-5 relative, far below what moves the Gauss–Newton step.
const BATCH: usize = 64;

/// A batch of weighted point-to-plane rows √w·(J, r), J = [n, p × n], as columns (structure of
/// arrays, so the 27 sums of products of column pairs vectorise); unused entries are zero.
struct RowBatch {
    columns: [[f32; BATCH]; 7],
    len: usize,
}

impl RowBatch {
    fn new() -> Self {
        Self { columns: [[0.0; BATCH]; 7], len: 0 }
    }
}

/// Σ a·b over a batch, in 8 lanes.
#[inline]
fn batch_dot(a: &[f32; BATCH], b: &[f32; BATCH]) -> f32 {
    let mut lanes = [0.0f32; 8];
    for (chunk_a, chunk_b) in a.chunks_exact(8).zip(b.chunks_exact(8)) {
        for ((lane, x), y) in lanes.iter_mut().zip(chunk_a).zip(chunk_b) {
            *lane += x * y;
        }
    }
    lanes.iter().sum()
}

/// Adds the batch's JᵀWJ (upper triangle) and JᵀWr to the f64 totals and empties the batch.
fn flush_batch(acc: &mut Normal, batch: &mut RowBatch) {
    if batch.len == 0 {
        return;
    }
    let mut k = 0;
    for (a, column_a) in batch.columns.iter().take(6).enumerate() {
        for column_b in batch.columns.iter().take(6).skip(a) {
            if let Some(total) = acc.jtj.get_mut(k) {
                *total += f64::from(batch_dot(column_a, column_b));
            }
            k += 1;
        }
        if let Some(total) = acc.jtr.get_mut(a) {
            *total += f64::from(batch_dot(column_a, &batch.columns[6]));
        }
    }
    *batch = RowBatch::new();
}

/// Projective association + point-to-plane linearisation, summed in parallel (f32 sums over
/// batches of `BATCH` inliers, f64 totals).
fn accumulate(
    source: &SourceLevel,
    model: &ModelRaycast,
    model_from_volume: &Isometry3<f32>,
    volume_from_camera: &Isometry3<f64>,
    gate: f32,
    huber: f64,
) -> Normal {
    let pose = volume_from_camera.cast::<f32>();
    // Projection straight from the source camera into the model camera; the volume-frame point is
    // only needed for the points that find a model surface.
    let model_from_camera = model_from_volume * pose;
    let huber = huber as f32;
    let mi = &model.intrinsics;
    let (fx, fy, cx, cy) = (mi.fx as f32, mi.fy as f32, mi.cx as f32, mi.cy as f32);
    let (w, h) = (mi.width as f32 - 0.5, mi.height as f32 - 0.5);
    source
        .points_in_camera
        .par_chunks(1024)
        .map(|chunk| {
            let mut acc = Normal::zero();
            let mut batch = RowBatch::new();
            for point in chunk {
                let m = model_from_camera * Point3::from(*point);
                if m.z <= 0.0 {
                    continue;
                }
                let inv_z = 1.0 / m.z;
                let u = fx * m.x * inv_z + cx;
                let v = fy * m.y * inv_z + cy;
                if !(u >= -0.5 && v >= -0.5 && u < w && v < h) {
                    continue;
                }
                let index = floor_small(v + 0.5) as usize * mi.width + floor_small(u + 0.5) as usize;
                let (Some(q), Some(n)) = (model.points_in_volume.get(index), model.normals_in_volume.get(index)) else {
                    continue;
                };
                if !q.x.is_finite() {
                    continue;
                }
                acc.associated += 1;
                let p = pose * Point3::from(*point);
                let difference = p - q;
                if difference.norm_squared() > gate * gate {
                    continue;
                }
                let r = n.dot(&difference);
                // Huber weight w, applied as √w to both factors of each product.
                let sqrt_weight = if r.abs() <= huber { 1.0 } else { (huber / r.abs()).sqrt() };
                let c = p.coords.cross(n);
                let row = [n.x, n.y, n.z, c.x, c.y, c.z, r];
                let slot = batch.len;
                for (column, value) in batch.columns.iter_mut().zip(row) {
                    if let Some(entry) = column.get_mut(slot) {
                        *entry = sqrt_weight * value;
                    }
                }
                batch.len += 1;
                acc.inliers += 1;
                acc.squared_residuals += f64::from(r * r);
                if batch.len == BATCH {
                    flush_batch(&mut acc, &mut batch);
                }
            }
            flush_batch(&mut acc, &mut batch);
            acc
        })
        .reduce(Normal::zero, Normal::add)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn downsample_averages_agreeing_depths_only() {
        let nan = f32::NAN;
        // Three 2×2 cells: four agreeing depths, one valid depth, and a 10 cm jump.
        #[rustfmt::skip]
        let depth = DepthImage::new(6, 2, vec![
            1.0, 1.02, 2.0, nan, 1.0, 1.1,
            1.01, 1.03, nan, nan, 1.0, 1.1,
        ]).unwrap();
        let half = downsample(&depth, 0.03);
        assert_eq!((half.width, half.height), (3, 1));
        assert!((half.depth_m[0] - 1.015).abs() < 1e-6, "{}", half.depth_m[0]);
        assert!(half.depth_m[1].is_nan() && half.depth_m[2].is_nan());
    }
}

//! Frame-to-model point-to-plane ICP (J 5.1, KinectFusion): the new frame's depth pyramid (1/4, 1/2,
//! 1 resolution, coarse to fine), projective data association against the model raycast, Huber
//! weights, a distance gate and (on the wide level) a normal-angle gate, and the 6×6 Gauss–Newton
//! normal equations summed in parallel (f32 over batches of 64 inliers, f64 totals).
//!
//! Each Gauss–Newton step minimises the linearised point-to-plane energy (Low 2004; KinectFusion,
//! Newcombe et al. 2011, sec. 3.5)
//!
//! ```text
//! E(ξ) = Σᵢ wᵢ (nᵢ · (exp(ξ) T pᵢ − qᵢ))²  ≈  Σᵢ wᵢ (Jᵢ ξ + rᵢ)²,   Jᵢ = [nᵢᵀ, (T pᵢ × nᵢ)ᵀ],  rᵢ = nᵢ · (T pᵢ − qᵢ)
//! ξ = −(Σ wᵢ JᵢᵀJᵢ)⁻¹ Σ wᵢ Jᵢᵀ rᵢ,      T ← exp(ξ) T
//! ```
//!
//! with wᵢ = min(1, h / |rᵢ/sᵢ|) / sᵢ², the Huber weight of the residual over the depth's relative
//! noise sᵢ = zᵢ^k (k = `IcpConfig::depth_noise_power`, 2 for J eq 2's stereo noise; 0 gives
//! KinectFusion's Huber weight alone), over the pairs (pᵢ, qᵢ) that projective association
//! finds within the level's gates: ‖T pᵢ − qᵢ‖ ≤ d_max and, where the level has one, ∠(R nₚᵢ, nᵢ) ≤ θ_max.
//! The schedule of levels is [`level_plan`]: optionally a *wide* level first (the 1/4 image
//! subsampled, wide distance gate, normal-angle gate) that pulls in a pose 10–30 cm or 10–20° off,
//! then the usual 1/4 → 1/2 → 1 levels.

use super::{IcpConfig, IcpSummary};
use crate::camera::{DepthImage, Intrinsics};
use crate::fusion::floor_small;
use crate::raycast::ModelRaycast;
use nalgebra::{Isometry3, Matrix6, Point3, Translation3, UnitQuaternion, Vector3, Vector6};
use rayon::prelude::*;

/// One pyramid level of the new frame: intrinsics and its valid points in the camera frame (with
/// their normals, toward the camera, when the level gates on the normal angle; empty otherwise).
pub struct SourceLevel {
    pub intrinsics: Intrinsics,
    pub points_in_camera: Vec<Vector3<f32>>,
    pub normals_in_camera: Vec<Vector3<f32>>,
}

/// Scale of each pyramid image relative to the input, coarsest first.
pub const PYRAMID_SCALES: [f64; 3] = [0.25, 0.5, 1.0];

/// One level of the coarse-to-fine schedule.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct LevelPlan {
    /// Pyramid image: 0 = 1/4, 1 = 1/2, 2 = full resolution.
    pub image: usize,
    /// Every `stride`-th pixel in both directions.
    pub stride: usize,
    pub iterations: usize,
    /// Correspondence distance gate d_max (m).
    pub gate_m: f64,
    /// Normal-angle gate θ_max (deg); 180 or more: none (the normals are not computed).
    pub max_normal_angle_deg: f64,
    /// Levenberg damping d (0: plain Gauss–Newton).
    pub damping: f64,
    /// Largest step per iteration (m, deg); infinite: unlimited.
    pub max_step_m: f64,
    pub max_step_deg: f64,
}

impl LevelPlan {
    fn uses_normals(&self) -> bool {
        self.max_normal_angle_deg < 180.0
    }
}

/// The schedule of levels, coarse to fine: with `wide`, first the wide level (`IcpConfig::wide`: the
/// 1/4 image every `stride`-th pixel, wide distance gate, normal-angle gate), then the 1/4, 1/2 and
/// full levels of `iterations` / `max_correspondence_m`. Levels without iterations are left out.
pub fn level_plan(config: &IcpConfig, wide: bool) -> Vec<LevelPlan> {
    let mut plan = Vec::with_capacity(4);
    if wide && config.wide.iterations > 0 {
        plan.push(LevelPlan {
            image: 0,
            stride: config.wide.stride.max(1),
            iterations: config.wide.iterations,
            gate_m: config.wide.max_correspondence_m,
            max_normal_angle_deg: config.wide.max_normal_angle_deg,
            damping: config.wide.damping,
            max_step_m: config.wide.max_step_m,
            max_step_deg: config.wide.max_step_deg,
        });
    }
    for (image, (&iterations, &gate_m)) in config.iterations.iter().zip(&config.max_correspondence_m).enumerate() {
        if iterations > 0 {
            let unlimited = f64::INFINITY;
            plan.push(LevelPlan {
                image,
                stride: 1,
                iterations,
                gate_m,
                max_normal_angle_deg: 180.0,
                damping: 0.0,
                max_step_m: unlimited,
                max_step_deg: unlimited,
            });
        }
    }
    plan
}

/// Depth pyramid, coarsest first (1/4, 1/2, 1 of the input resolution), every point of each.
pub fn build_pyramid(depth: &DepthImage, intrinsics: &Intrinsics, depth_jump_m: f32) -> Vec<SourceLevel> {
    let half = downsample(depth, depth_jump_m);
    let quarter = downsample(&half, depth_jump_m);
    [&quarter, &half, depth]
        .iter()
        .zip(PYRAMID_SCALES)
        .map(|(image, scale)| source_level(image, &intrinsics.scaled(scale), 1, false))
        .collect()
}

/// The source level of one plan entry from the pyramid images (1/4, 1/2, 1 of the input).
pub(super) fn plan_source(images: &[&DepthImage; 3], intrinsics: &Intrinsics, plan: &LevelPlan) -> SourceLevel {
    let scale = PYRAMID_SCALES.get(plan.image).copied().unwrap_or(1.0);
    let level_intrinsics = intrinsics.scaled(scale);
    match images.get(plan.image) {
        Some(image) => source_level(image, &level_intrinsics, plan.stride, plan.uses_normals()),
        None => SourceLevel { intrinsics: level_intrinsics, points_in_camera: Vec::new(), normals_in_camera: Vec::new() },
    }
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

/// Back-projects every `stride`-th valid pixel; with `normals`, only pixels whose four neighbours are
/// valid, each with its central-difference normal n = (p(u+1) − p(u−1)) × (p(v+1) − p(v−1)),
/// normalised and turned toward the camera.
fn source_level(depth: &DepthImage, intrinsics: &Intrinsics, stride: usize, normals: bool) -> SourceLevel {
    let (fx, fy, cx, cy) = (intrinsics.fx as f32, intrinsics.fy as f32, intrinsics.cx as f32, intrinsics.cy as f32);
    let stride = stride.max(1);
    // Ray slopes per column and row, computed once (no per-pixel division).
    let x_slopes: Vec<f32> = (0..depth.width).map(|u| (u as f32 - cx) / fx).collect();
    let point = |u: usize, v: usize| -> Option<Vector3<f32>> {
        let d = *depth.depth_m.get(v.checked_mul(depth.width)?.checked_add(u)?)?;
        let x_slope = x_slopes.get(u)?;
        d.is_finite().then(|| Vector3::new(x_slope * d, (v as f32 - cy) / fy * d, d))
    };
    let mut points_in_camera = Vec::with_capacity(depth.depth_m.len() / (stride * stride));
    let mut normals_in_camera = Vec::new();
    for v in (0..depth.height).step_by(stride) {
        for u in (0..depth.width).step_by(stride) {
            let Some(p) = point(u, v) else { continue };
            if !normals {
                points_in_camera.push(p);
                continue;
            }
            let neighbours =
                (u.checked_sub(1).and_then(|l| point(l, v)), point(u + 1, v), v.checked_sub(1).and_then(|t| point(u, t)), point(u, v + 1));
            let (Some(left), Some(right), Some(top), Some(bottom)) = neighbours else { continue };
            let Some(n) = (right - left).cross(&(bottom - top)).try_normalize(1e-12) else { continue };
            points_in_camera.push(p);
            normals_in_camera.push(if n.dot(&p) > 0.0 { -n } else { n });
        }
    }
    SourceLevel { intrinsics: *intrinsics, points_in_camera, normals_in_camera }
}

/// Result of one ICP run.
#[derive(Debug, Clone, Copy)]
pub struct IcpResult {
    pub volume_from_camera: Isometry3<f64>,
    pub summary: IcpSummary,
    /// Smallest eigenvalue of the last normal matrix divided by the inliers' summed depth weights
    /// (the inlier count when they are unweighted).
    pub min_eigenvalue: f64,
}

/// Normal equations of point-to-plane ICP: Σ w JᵀJ, Σ w Jᵀr, with statistics.
#[derive(Clone, Copy)]
struct Normal {
    jtj: [f64; 21],
    jtr: [f64; 6],
    inliers: usize,
    /// Σ of the inliers' depth weights (`IcpConfig::depth_noise_power`).
    weight_sum: f64,
    /// Source points that landed on a model pixel with a surface (before the distance gate).
    associated: usize,
    squared_residuals: f64,
}

impl Normal {
    fn zero() -> Self {
        Self { jtj: [0.0; 21], jtr: [0.0; 6], inliers: 0, weight_sum: 0.0, associated: 0, squared_residuals: 0.0 }
    }
    fn add(mut self, other: Self) -> Self {
        for (a, b) in self.jtj.iter_mut().zip(other.jtj.iter()) {
            *a += b;
        }
        for (a, b) in self.jtr.iter_mut().zip(other.jtr.iter()) {
            *a += b;
        }
        self.inliers += other.inliers;
        self.weight_sum += other.weight_sum;
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

/// Frame-to-model point-to-plane ICP (J 5.1), coarse to fine over the levels of a [`level_plan`]
/// (each with its source level), from `initial` (`volume_from_camera`).
pub fn icp(config: &IcpConfig, levels: &[(LevelPlan, &SourceLevel)], model: &ModelRaycast, initial: &Isometry3<f64>) -> IcpResult {
    let mut pose = *initial;
    let mut summary = IcpSummary::default();
    // Normal matrix and inlier count of the last successful iteration: its smallest eigenvalue (the
    // degeneracy check) is computed once after the last iteration, not at every iteration.
    let mut last_system: Option<(Matrix6<f64>, f64)> = None;
    let model_from_volume = model.volume_from_camera.inverse().cast::<f32>();
    for (plan, source) in levels {
        let min_normal_cos = if plan.uses_normals() { plan.max_normal_angle_deg.to_radians().cos() as f32 } else { -2.0 };
        let gates = Gates { distance_m: plan.gate_m as f32, min_normal_cos };
        for _ in 0..plan.iterations {
            let normal = accumulate(source, model, &model_from_volume, &pose, gates, config.huber_m, config.depth_noise_power);
            summary = IcpSummary {
                iterations: summary.iterations + 1,
                inliers: normal.inliers,
                valid_source_points: source.points_in_camera.len(),
                associated: normal.associated,
                rms_m: (normal.squared_residuals / normal.inliers.max(1) as f64).sqrt(),
                attempts: 1,
            };
            if normal.inliers < 6 {
                last_system = None;
                break;
            }
            let (h, g) = normal.matrices();
            // Levenberg damping (H + λI, λ = d·tr(H)/6) where the level asks for it: directions the
            // data does not constrain (a flat floor's in-plane motion) keep the initial guess.
            let damped = if plan.damping > 0.0 { h + Matrix6::identity() * (plan.damping * h.trace() / 6.0) } else { h };
            let Some(cholesky) = damped.cholesky() else {
                last_system = None;
                break;
            };
            last_system = Some((h, normal.weight_sum));
            let delta = cholesky.solve(&(-g));
            let mut translation = Vector3::new(delta[0], delta[1], delta[2]);
            let mut rotation = Vector3::new(delta[3], delta[4], delta[5]);
            // At most max_step per iteration (the whole step scaled down): far-off associations of a
            // wide gate cannot fling the pose away in one step.
            let scale =
                (plan.max_step_m / translation.norm().max(1e-12)).min(plan.max_step_deg.to_radians() / rotation.norm().max(1e-12)).min(1.0);
            translation *= scale;
            rotation *= scale;
            // Left-multiplied increment: p' ← exp(δ) p'.
            let increment = Isometry3::from_parts(Translation3::from(translation), UnitQuaternion::from_scaled_axis(rotation));
            pose = increment * pose;
            if translation.norm() < config.convergence && rotation.norm() < config.convergence {
                break;
            }
        }
    }
    let min_eigenvalue = last_system.map_or(0.0, |(h, weight_sum)| h.symmetric_eigenvalues().min() / weight_sum.max(f64::MIN_POSITIVE));
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

/// Correspondence gates of one level: distance, and the cosine of the largest normal angle (below −1:
/// no normal gate).
#[derive(Debug, Clone, Copy)]
struct Gates {
    distance_m: f32,
    min_normal_cos: f32,
}

/// Projective association + point-to-plane linearisation, summed in parallel (f32 sums over
/// batches of `BATCH` inliers, f64 totals).
fn accumulate(
    source: &SourceLevel,
    model: &ModelRaycast,
    model_from_volume: &Isometry3<f32>,
    volume_from_camera: &Isometry3<f64>,
    gates: Gates,
    huber: f64,
    depth_noise_power: u32,
) -> Normal {
    let gate = gates.distance_m;
    let normal_gate = gates.min_normal_cos >= -1.0 && source.normals_in_camera.len() == source.points_in_camera.len();
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
        .enumerate()
        .map(|(chunk_index, chunk)| {
            let mut acc = Normal::zero();
            let mut batch = RowBatch::new();
            for (offset, point) in chunk.iter().enumerate() {
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
                if normal_gate {
                    let Some(source_normal) = source.normals_in_camera.get(chunk_index * 1024 + offset) else { continue };
                    if (pose.rotation * source_normal).dot(n) < gates.min_normal_cos {
                        continue;
                    }
                }
                let r = n.dot(&difference);
                // The depth's relative noise s = z^power (1 at 1 m): the residual counts as r/s, with
                // the Huber weight on r/s; both applied as √w to both factors of each product.
                let noise = point.z.max(1e-3).powi(depth_noise_power as i32);
                let scaled = r.abs() / noise;
                let huber_weight = if scaled <= huber { 1.0 } else { huber / scaled };
                let depth_weight = 1.0 / (noise * noise);
                let sqrt_weight = (huber_weight * depth_weight).sqrt();
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
                acc.weight_sum += f64::from(depth_weight);
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

    #[test]
    fn level_plan_puts_the_wide_level_first_and_skips_empty_levels() {
        let config = IcpConfig::default();
        let narrow = level_plan(&config, false);
        assert_eq!(narrow.iter().map(|l| l.image).collect::<Vec<_>>(), vec![0, 1], "the full level has 0 iterations by default");
        assert!(narrow.iter().all(|l| l.stride == 1 && l.max_normal_angle_deg >= 180.0));
        assert_eq!(narrow[0].gate_m, config.max_correspondence_m[0]);
        let wide = level_plan(&config, true);
        assert_eq!(wide.len(), narrow.len() + 1);
        assert_eq!(&wide[1..], &narrow[..]);
        let first = wide[0];
        assert_eq!((first.image, first.stride, first.iterations), (0, config.wide.stride, config.wide.iterations));
        assert!(first.gate_m > 2.0 * config.max_correspondence_m[0] && first.max_normal_angle_deg < 180.0);
        // No wide iterations: the wide schedule is the narrow one.
        let mut off = config.clone();
        off.wide.iterations = 0;
        assert_eq!(level_plan(&off, true), narrow);
    }

    #[test]
    fn source_levels_subsample_and_carry_normals_toward_the_camera() {
        // A plane z = 1 + 0.5 x seen by a 40×30 camera.
        let intrinsics = Intrinsics { width: 40, height: 30, fx: 40.0, fy: 40.0, cx: 19.5, cy: 14.5 };
        let depth_m = (0..30)
            .flat_map(|v| (0..40).map(move |u| (u, v)))
            .map(|(u, _v)| {
                let x_slope = (u as f32 - 19.5) / 40.0;
                1.0 / (1.0 - 0.5 * x_slope)
            })
            .collect();
        let depth = DepthImage::new(40, 30, depth_m).unwrap();
        let all = source_level(&depth, &intrinsics, 1, false);
        assert_eq!((all.points_in_camera.len(), all.normals_in_camera.len()), (1200, 0));
        let strided = source_level(&depth, &intrinsics, 2, true);
        // Every 2nd pixel of both directions, without the border (no neighbours there).
        assert_eq!(strided.points_in_camera.len(), strided.normals_in_camera.len());
        assert_eq!(strided.points_in_camera.len(), 19 * 14);
        let expected = Vector3::new(0.5f32, 0.0, -1.0).normalize();
        for (p, n) in strided.points_in_camera.iter().zip(&strided.normals_in_camera) {
            assert!((p.z - (1.0 + 0.5 * p.x)).abs() < 1e-4);
            assert!((n - expected).norm() < 1e-3, "{n}");
        }
    }
}

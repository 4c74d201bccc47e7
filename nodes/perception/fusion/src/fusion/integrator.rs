//! Projective integration of a depth frame into the TSDF volume (J 5.1 "Data Fusion"; Curless &
//! Levoy running weighted average): the blocks the frame's truncation band passes through are found
//! by walking the band of every second pixel and allocated, then their voxels are updated in
//! parallel (rayon over blocks) by projecting each voxel into the depth image.

use std::sync::atomic::Ordering;

use nalgebra::{Isometry3, Point3, Vector3};
use rayon::prelude::*;

use super::block::{Block, BLOCK_EDGE};
use super::tsdf_volume::{TsdfVolume, NONE};
use super::{floor_i, floor_small, FusionError, TsdfConfig};
use crate::camera::{DepthImage, Intrinsics};

/// Statistics of one integration.
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub struct IntegrationStats {
    pub blocks_touched: usize,
    pub blocks_allocated: usize,
}

impl TsdfVolume {
    /// Integrates one depth frame seen from `volume_from_camera` (J 5.1 step "Data Fusion").
    pub fn integrate(
        &mut self,
        depth: &DepthImage,
        intrinsics: &Intrinsics,
        volume_from_camera: &Isometry3<f64>,
    ) -> Result<IntegrationStats, FusionError> {
        if depth.width != intrinsics.width || depth.height != intrinsics.height {
            return Err(FusionError::SizeMismatch {
                image_width: depth.width,
                image_height: depth.height,
                width: intrinsics.width,
                height: intrinsics.height,
            });
        }
        let touched_slots = self.touched_blocks(depth, intrinsics, volume_from_camera);
        let before = self.blocks.len();
        let mut touched: Vec<u32> = Vec::with_capacity(touched_slots.len());
        for slot_index in touched_slots {
            let Some(&slot) = self.slots.get(slot_index) else { continue };
            if slot == NONE {
                let n = self.blocks_per_edge;
                let coords = [(slot_index % n) as u16, ((slot_index / n) % n) as u16, (slot_index / (n * n)) as u16];
                touched.push(self.blocks.len() as u32);
                let block = self.empty_block();
                self.allocate(slot_index, coords, block);
            } else {
                touched.push(slot);
            }
        }
        let blocks_touched = touched.len();
        let mut is_touched = vec![false; self.blocks.len()];
        for index in touched {
            if let Some(flag) = is_touched.get_mut(index as usize) {
                *flag = true;
            }
        }
        let camera_from_volume = volume_from_camera.inverse().cast::<f32>();
        let projector = Projector::new(intrinsics, &self.config);
        let voxel_size = self.config.voxel_size_m;
        self.blocks
            .par_iter_mut()
            .zip(self.coords.par_iter())
            .zip(is_touched.par_iter())
            .with_min_len(4)
            .filter(|(_, touched)| **touched)
            .for_each(|((block, coords), _)| {
                integrate_block(block, coords, voxel_size, &camera_from_volume, &projector, depth);
            });
        Ok(IntegrationStats { blocks_touched, blocks_allocated: self.blocks.len() - before })
    }

    /// Slot indices of blocks crossed by the truncation band of the frame (deduplicated, sorted), from
    /// a subsample of the pixels.
    fn touched_blocks(&self, depth: &DepthImage, intrinsics: &Intrinsics, volume_from_camera: &Isometry3<f64>) -> Vec<usize> {
        let pose = volume_from_camera.cast::<f32>();
        let mu = self.truncation();
        let block = self.block_size();
        // Samples along the band [d − μ, d + μ], at most half a block apart.
        let samples = ((2.0 * mu) / (0.5 * block)).ceil().max(1.0) as usize + 1;
        let (min_d, max_d) = (self.config.min_depth_m, self.config.max_depth_m);
        let (fx, fy, cx, cy) = (intrinsics.fx as f32, intrinsics.fy as f32, intrinsics.cx as f32, intrinsics.cy as f32);
        // Every 4th pixel: at 3 m a 640-px-wide view puts 4 pixels ≈ 2.3 cm apart, under the 4 cm
        // block at 5 mm voxels; the ±μ band then covers every block the surface passes through.
        let stride = if self.block_size() >= 0.04 { 4 } else { 2 };
        // Marked in a bitmap (in parallel; each row skips repeats of its last slot), read back in
        // slot order: sorted and deduplicated without sorting.
        (0..depth.height).into_par_iter().step_by(stride).for_each(|v| {
            let mut last = usize::MAX;
            for u in (0..depth.width).step_by(stride) {
                let Some(&d) = depth.depth_m.get(v * depth.width + u) else { continue };
                if !(d >= min_d && d <= max_d) {
                    continue;
                }
                let ray = Vector3::new((u as f32 - cx) / fx, (v as f32 - cy) / fy, 1.0);
                for s in 0..samples {
                    let z = d - mu + 2.0 * mu * s as f32 / (samples - 1).max(1) as f32;
                    let p = pose * Point3::from(ray * z);
                    let b = p.coords / block;
                    if let Some(slot) = self.slot_index(floor_i(b.x), floor_i(b.y), floor_i(b.z)) {
                        if slot != last {
                            if let Some(word) = self.touched.get(slot / 64) {
                                word.fetch_or(1 << (slot % 64), Ordering::Relaxed);
                            }
                            last = slot;
                        }
                    }
                }
            }
        });
        let mut slots = Vec::new();
        for (index, word) in self.touched.iter().enumerate() {
            if word.load(Ordering::Relaxed) == 0 {
                continue;
            }
            let mut bits = word.swap(0, Ordering::Relaxed);
            while bits != 0 {
                slots.push(index * 64 + bits.trailing_zeros() as usize);
                bits &= bits - 1;
            }
        }
        slots
    }
}

/// Pinhole projection and the per-frame fusion constants.
struct Projector {
    fx: f32,
    fy: f32,
    cx: f32,
    cy: f32,
    width: usize,
    height: usize,
    mu: f32,
    max_weight: f32,
    min_depth: f32,
    max_depth: f32,
}

impl Projector {
    fn new(intrinsics: &Intrinsics, config: &TsdfConfig) -> Self {
        Self {
            fx: intrinsics.fx as f32,
            fy: intrinsics.fy as f32,
            cx: intrinsics.cx as f32,
            cy: intrinsics.cy as f32,
            width: intrinsics.width,
            height: intrinsics.height,
            mu: config.truncation_m(),
            max_weight: config.max_weight,
            min_depth: config.min_depth_m,
            max_depth: config.max_depth_m,
        }
    }
}

/// Projective TSDF update of one block: each voxel centre is projected into the image, the signed
/// distance along the optical axis `sdf = d − z` is truncated to μ, and averaged with weight 1
/// (Curless & Levoy; KinectFusion's projective TSDF), skipping voxels more than μ behind the surface.
fn integrate_block(
    block: &mut Block,
    coords: &[u16; 3],
    voxel_size: f32,
    camera_from_volume: &Isometry3<f32>,
    p: &Projector,
    depth: &DepthImage,
) {
    let rotation = camera_from_volume.rotation.to_rotation_matrix();
    let r = rotation.matrix();
    let step_x = r.column(0) * voxel_size;
    let step_y = r.column(1) * voxel_size;
    let step_z = r.column(2) * voxel_size;
    let origin = Point3::new(
        (coords[0] as usize * BLOCK_EDGE) as f32 + 0.5,
        (coords[1] as usize * BLOCK_EDGE) as f32 + 0.5,
        (coords[2] as usize * BLOCK_EDGE) as f32 + 0.5,
    ) * voxel_size;
    let base = camera_from_volume * origin;
    let inv_mu = 1.0 / p.mu;
    let (w_max, h_max) = (p.width as f32 - 0.5, p.height as f32 - 0.5);
    // Largest column and row indices as floats: pixel coordinates are clamped to them (a no-op for
    // the pixels inside the image) so that `floor_small` sees its valid range.
    let (col_last, row_last) = ((p.width.max(1) - 1) as f32, (p.height.max(1) - 1) as f32);
    let near = p.min_depth * 0.5;
    let width = p.width as i32;
    let lanes: [f32; BLOCK_EDGE] = std::array::from_fn(|x| x as f32);
    for (row_index, row_voxels) in block.voxels.chunks_exact_mut(BLOCK_EDGE).enumerate() {
        let (y, z) = (row_index % BLOCK_EDGE, row_index / BLOCK_EDGE);
        // One row of voxels along x in two passes: camera-frame points and their pixels first
        // (branch-free, so it vectorises), then the depth look-ups and the running averages.
        let q = base.coords + step_y * y as f32 + step_z * z as f32;
        let mut pixels = [-1i32; BLOCK_EDGE];
        let mut zs = [0.0f32; BLOCK_EDGE];
        for ((pixel, pz), lane) in pixels.iter_mut().zip(zs.iter_mut()).zip(lanes.iter()) {
            let (px, py) = (q.x + step_x.x * lane, q.y + step_x.y * lane);
            *pz = q.z + step_x.z * lane;
            let inv_z = 1.0 / *pz;
            let u = p.fx * px * inv_z + p.cx;
            let v = p.fy * py * inv_z + p.cy;
            let inside = (*pz > near) & (u >= -0.5) & (v >= -0.5) & (u < w_max) & (v < h_max);
            let col = floor_small((u + 0.5).max(0.0).min(col_last));
            let row = floor_small((v + 0.5).max(0.0).min(row_last));
            *pixel = if inside { row * width + col } else { -1 };
        }
        for ((voxel, pixel), pz) in row_voxels.iter_mut().zip(pixels.iter()).zip(zs.iter()) {
            let Ok(pixel) = usize::try_from(*pixel) else { continue };
            let Some(&d) = depth.depth_m.get(pixel) else { continue };
            if !(d >= p.min_depth && d <= p.max_depth) {
                continue;
            }
            let sdf = d - *pz;
            if sdf < -p.mu {
                continue;
            }
            let tsdf = (sdf * inv_mu).min(1.0);
            let new_weight = voxel.weight + 1.0;
            voxel.tsdf = (voxel.tsdf * voxel.weight + tsdf) / new_weight;
            voxel.weight = new_weight.min(p.max_weight);
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::fusion::tests::{looking_down_pose, render_plane};

    #[test]
    fn integrating_a_plane_puts_the_zero_crossing_on_it() {
        let config = TsdfConfig { voxel_size_m: 0.01, size_m: 1.28, ..TsdfConfig::default() };
        let mut volume = TsdfVolume::new(config).unwrap();
        let intrinsics = Intrinsics::primesense_default().scaled(0.5);
        let pose = looking_down_pose(Vector3::new(0.64, 0.2, 0.64));
        // Floor at y = 0.9 m in the volume (0.7 m below the camera).
        let depth = render_plane(&intrinsics, &pose, Vector3::y(), 0.9);
        let stats = volume.integrate(&depth, &intrinsics, &pose).unwrap();
        assert!(stats.blocks_allocated > 50, "{stats:?}");
        assert_eq!(stats.blocks_touched, stats.blocks_allocated);
        // Along the vertical through the camera the TSDF changes sign at y = 0.9.
        let s = config.voxel_size_m;
        let above = volume.trilinear(&(Vector3::new(0.64, 0.88, 0.64) / s)).unwrap();
        assert_eq!(volume.trilinear_tsdf(&(Vector3::new(0.64, 0.88, 0.64) / s)), Some(above.tsdf));
        let below = volume.trilinear(&(Vector3::new(0.64, 0.92, 0.64) / s)).unwrap();
        assert!((above.tsdf - 0.5).abs() < 0.05, "{}", above.tsdf);
        assert!((below.tsdf + 0.5).abs() < 0.05, "{}", below.tsdf);
        // Gradient points away from the surface toward the camera side (−y), magnitude 1/μ.
        let g = above.gradient.normalize();
        assert!(g.y < -0.99, "{g}");
        assert!((above.gradient.norm() - 1.0 / config.truncation_m()).abs() < 2.0);
        // Surface voxels all lie within half a voxel of the plane.
        let surface = volume.surface_voxels(0.3);
        assert!(!surface.is_empty());
        assert!(surface.iter().all(|p| (p.y - 0.9).abs() < 0.4 * config.truncation_m()));
    }

    #[test]
    fn a_cleared_volume_integrates_into_its_old_blocks_as_into_new_ones() {
        let config = TsdfConfig { voxel_size_m: 0.02, size_m: 1.28, ..TsdfConfig::default() };
        let intrinsics = Intrinsics::primesense_default().scaled(0.25);
        let pose = looking_down_pose(Vector3::new(0.64, 0.2, 0.64));
        let floor = render_plane(&intrinsics, &pose, Vector3::y(), 0.9);
        let higher = render_plane(&intrinsics, &pose, Vector3::y(), 0.7);
        let mut fresh = TsdfVolume::new(config).unwrap();
        fresh.integrate(&higher, &intrinsics, &pose).unwrap();
        let mut reused = TsdfVolume::new(config).unwrap();
        reused.integrate(&floor, &intrinsics, &pose).unwrap();
        let peak = reused.block_count();
        reused.clear();
        assert_eq!((reused.block_count(), reused.spare_count()), (0, peak), "the blocks are kept");
        let stats = reused.integrate(&higher, &intrinsics, &pose).unwrap();
        assert_eq!(stats.blocks_allocated, fresh.block_count());
        assert_eq!(
            reused.block_count() + reused.spare_count(),
            peak.max(fresh.block_count()),
            "no block allocated while spare ones were left"
        );
        // Same content, voxel for voxel: nothing of the floor is left in the reused blocks.
        type Voxels = Vec<(u32, u32)>;
        let content = |v: &TsdfVolume| {
            let mut blocks: Vec<([u16; 3], Voxels)> =
                v.blocks().map(|(c, b)| (c, b.voxels.iter().map(|x| (x.tsdf.to_bits(), x.weight.to_bits())).collect())).collect();
            blocks.sort_by_key(|(c, _)| *c);
            blocks
        };
        assert_eq!(content(&reused), content(&fresh));
    }

    #[test]
    fn repeated_frames_average_and_cap_weight() {
        let config = TsdfConfig { voxel_size_m: 0.02, size_m: 1.28, max_weight: 3.0, ..TsdfConfig::default() };
        let mut volume = TsdfVolume::new(config).unwrap();
        let intrinsics = Intrinsics::primesense_default().scaled(0.25);
        let pose = looking_down_pose(Vector3::new(0.64, 0.2, 0.64));
        let depth = render_plane(&intrinsics, &pose, Vector3::y(), 0.9);
        for _ in 0..5 {
            let stats = volume.integrate(&depth, &intrinsics, &pose).unwrap();
            assert!(stats.blocks_touched > 0);
        }
        let (_, weight) = volume.voxel(32, 44, 32).unwrap();
        assert_eq!(weight, 3.0);
    }
}

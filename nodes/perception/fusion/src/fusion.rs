//! TSDF volume (J 5.1): a cube of truncated signed distances + weights in the `volume` frame, stored as
//! 8×8×8 voxel blocks allocated only near observed surfaces, with projective integration of depth frames.
//!
//! Layout: a dense grid of block slots (`u32` per block, `NONE` where empty) over the cube, and a pool
//! of blocks holding `f32` TSDF (in units of the truncation distance, in [-1, 1]) and `f32` weight per
//! voxel, interleaved (one 8-byte voxel: a raycast step or trilinear corner reads one cache line), voxel
//! order x fastest. Integration touches only the blocks the current frame's truncation
//! band passes through (found by walking the band of every second pixel), then updates their voxels
//! in parallel (rayon over blocks) by projecting each voxel into the depth image (J 5.1 "Data Fusion";
//! Curless & Levoy running weighted average).
//!
//! Voxel `(i, j, k)` has its centre at `((i, j, k) + 0.5) · voxel_size` in the volume frame, whose
//! origin is a corner of the cube (J 4, Fig. 8-(ii)).

use std::sync::atomic::{AtomicU64, Ordering};

use nalgebra::{Isometry3, Point3, Vector3};
use rayon::prelude::*;

use crate::camera::{DepthImage, Intrinsics};

/// Voxels per block edge.
pub const BLOCK_EDGE: usize = 8;
/// Voxels per block.
pub const BLOCK_VOXELS: usize = BLOCK_EDGE * BLOCK_EDGE * BLOCK_EDGE;
const NONE: u32 = u32::MAX;
/// Blocks per superblock edge of the coarse occupancy grid used for empty-space leaping.
pub const SUPERBLOCK_EDGE: usize = 4;

/// `floor` as an integer without a libm call (not inlined without SSE4.1).
#[inline(always)]
pub fn floor_i(x: f32) -> i32 {
    let i = x as i32;
    i - i32::from((i as f32) > x)
}

/// `floor` of `x` in [0, 2²²) without a float → integer conversion, so that loops using it
/// vectorise (a saturating `as` cast does not): adding 2²³ rounds `x` to the nearest integer in the
/// low mantissa bits, one is taken off where that rounded up.
#[inline(always)]
pub fn floor_small(x: f32) -> i32 {
    const SHIFT: f32 = 8_388_608.0;
    let nearest = (x + SHIFT) - SHIFT;
    let floor = nearest - if nearest > x { 1.0 } else { 0.0 };
    ((floor + SHIFT).to_bits() as i32).wrapping_sub(SHIFT.to_bits() as i32)
}

/// Errors from building or updating a TSDF volume.
#[derive(Debug, thiserror::Error, PartialEq)]
pub enum FusionError {
    #[error("invalid TSDF configuration: {0}")]
    InvalidConfig(String),
    #[error("depth image is {image_width}x{image_height} but the intrinsics are for {width}x{height}")]
    SizeMismatch { image_width: usize, image_height: usize, width: usize, height: usize },
}

/// TSDF volume parameters.
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize, serde::Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct TsdfConfig {
    /// Voxel edge (m). J 5 leaves it to the KinectFusion implementation; 5 mm is the design target.
    pub voxel_size_m: f32,
    /// Cube edge Vs (m) (J 4, "its size Vs (a predefined constant)"); rounded up to whole blocks.
    pub size_m: f32,
    /// Truncation distance in voxels (KinectFusion / Open3D convention: 4 voxels).
    pub truncation_voxels: f32,
    /// Weight cap of the running average (lets the volume adapt, KinectFusion).
    pub max_weight: f32,
    /// Depths outside [min_depth_m, max_depth_m] are not integrated (J 4.2 step 3 "background" filter).
    pub min_depth_m: f32,
    pub max_depth_m: f32,
}

impl Default for TsdfConfig {
    fn default() -> Self {
        Self { voxel_size_m: 0.005, size_m: 1.28, truncation_voxels: 4.0, max_weight: 64.0, min_depth_m: 0.2, max_depth_m: 3.0 }
    }
}

impl TsdfConfig {
    /// Truncation distance μ (m).
    pub fn truncation_m(&self) -> f32 {
        self.truncation_voxels * self.voxel_size_m
    }

    fn validate(&self) -> Result<(), FusionError> {
        let positive = |name: &str, v: f32| {
            if v.is_finite() && v > 0.0 {
                Ok(())
            } else {
                Err(FusionError::InvalidConfig(format!("{name} = {v} must be positive and finite")))
            }
        };
        positive("voxel_size_m", self.voxel_size_m)?;
        positive("size_m", self.size_m)?;
        positive("truncation_voxels", self.truncation_voxels)?;
        positive("max_weight", self.max_weight)?;
        positive("max_depth_m", self.max_depth_m)?;
        if !(self.min_depth_m.is_finite() && self.min_depth_m >= 0.0 && self.min_depth_m < self.max_depth_m) {
            return Err(FusionError::InvalidConfig(format!("depth range [{}, {}] is empty", self.min_depth_m, self.max_depth_m)));
        }
        let blocks = (self.size_m / (self.voxel_size_m * BLOCK_EDGE as f32)).ceil();
        if blocks > 1024.0 {
            return Err(FusionError::InvalidConfig(format!("{blocks} blocks per edge is too many (max 1024)")));
        }
        Ok(())
    }
}

/// One voxel: TSDF in units of μ and the fusion weight (0 = never observed).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Voxel {
    pub tsdf: f32,
    pub weight: f32,
}

impl Voxel {
    /// Never observed (weight 0; TSDF at the truncation, "free").
    pub const EMPTY: Self = Self { tsdf: 1.0, weight: 0.0 };
}

/// One 8×8×8 block of voxels, x fastest.
#[derive(Clone)]
pub struct Block {
    pub voxels: [Voxel; BLOCK_VOXELS],
}

impl Block {
    /// A block of never-observed voxels.
    pub fn empty() -> Box<Self> {
        Box::new(Self { voxels: [Voxel::EMPTY; BLOCK_VOXELS] })
    }
}

/// A sampled TSDF value with its gradient (both in units of μ and μ per metre).
#[derive(Debug, Clone, Copy)]
pub struct TsdfSample {
    pub tsdf: f32,
    pub gradient: Vector3<f32>,
}

/// Statistics of one integration.
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub struct IntegrationStats {
    pub blocks_touched: usize,
    pub blocks_allocated: usize,
}

/// The sparse-block TSDF cube in the `volume` frame.
pub struct TsdfVolume {
    config: TsdfConfig,
    blocks_per_edge: usize,
    /// Dense slot grid: block (bx, by, bz) → pool index or `NONE`.
    slots: Vec<u32>,
    blocks: Vec<Box<Block>>,
    /// Block coordinates of every pooled block.
    coords: Vec<[u16; 3]>,
    /// Allocated blocks per superblock (SUPERBLOCK_EDGE³ blocks), for empty-space leaping.
    occupancy: Vec<u32>,
    superblocks_per_edge: usize,
    /// One bit per slot: the blocks the frame being integrated touches (all clear between frames).
    touched: Vec<AtomicU64>,
    /// Inclusive block-coordinate bounds of the allocated blocks (min > max when empty).
    bounds_min: [i32; 3],
    bounds_max: [i32; 3],
}

impl TsdfVolume {
    /// An empty volume (no blocks).
    pub fn new(config: TsdfConfig) -> Result<Self, FusionError> {
        config.validate()?;
        let blocks_per_edge = (config.size_m / (config.voxel_size_m * BLOCK_EDGE as f32)).ceil().max(1.0) as usize;
        let superblocks_per_edge = blocks_per_edge.div_ceil(SUPERBLOCK_EDGE);
        Ok(Self {
            config,
            blocks_per_edge,
            slots: vec![NONE; blocks_per_edge * blocks_per_edge * blocks_per_edge],
            blocks: Vec::new(),
            coords: Vec::new(),
            occupancy: vec![0; superblocks_per_edge * superblocks_per_edge * superblocks_per_edge],
            superblocks_per_edge,
            touched: (0..(blocks_per_edge * blocks_per_edge * blocks_per_edge).div_ceil(64)).map(|_| AtomicU64::new(0)).collect(),
            bounds_min: [i32::MAX; 3],
            bounds_max: [i32::MIN; 3],
        })
    }

    pub fn config(&self) -> &TsdfConfig {
        &self.config
    }

    pub fn voxel_size(&self) -> f32 {
        self.config.voxel_size_m
    }

    /// Truncation distance μ (m).
    pub fn truncation(&self) -> f32 {
        self.config.truncation_m()
    }

    /// Block edge (m).
    pub fn block_size(&self) -> f32 {
        self.config.voxel_size_m * BLOCK_EDGE as f32
    }

    pub fn blocks_per_edge(&self) -> usize {
        self.blocks_per_edge
    }

    /// Cube edge (m) after rounding up to whole blocks.
    pub fn edge_m(&self) -> f32 {
        self.blocks_per_edge as f32 * self.block_size()
    }

    /// Number of allocated blocks.
    pub fn block_count(&self) -> usize {
        self.blocks.len()
    }

    /// Drops every block (tracking-loss reset, J 5.2).
    pub fn clear(&mut self) {
        self.slots.fill(NONE);
        self.blocks.clear();
        self.coords.clear();
        self.occupancy.fill(0);
        self.bounds_min = [i32::MAX; 3];
        self.bounds_max = [i32::MIN; 3];
    }

    /// Pools a new block at block coordinates `c` for slot `slot_index` (caller checked it is free).
    fn allocate(&mut self, slot_index: usize, c: [u16; 3], block: Box<Block>) {
        if let Some(slot) = self.slots.get_mut(slot_index) {
            *slot = self.blocks.len() as u32;
        }
        self.blocks.push(block);
        self.coords.push(c);
        let n = self.superblocks_per_edge;
        let s = |v: u16| v as usize / SUPERBLOCK_EDGE;
        if let Some(count) = self.occupancy.get_mut((s(c[2]) * n + s(c[1])) * n + s(c[0])) {
            *count += 1;
        }
        for axis in 0..3 {
            self.bounds_min[axis] = self.bounds_min[axis].min(i32::from(c[axis]));
            self.bounds_max[axis] = self.bounds_max[axis].max(i32::from(c[axis]));
        }
    }

    /// Axis-aligned bounds (m, volume frame) of the allocated blocks, if any.
    pub fn allocated_bounds(&self) -> Option<(Vector3<f32>, Vector3<f32>)> {
        if self.blocks.is_empty() {
            return None;
        }
        let b = self.block_size();
        let lo = Vector3::new(self.bounds_min[0] as f32, self.bounds_min[1] as f32, self.bounds_min[2] as f32) * b;
        let hi = Vector3::new(self.bounds_max[0] as f32 + 1.0, self.bounds_max[1] as f32 + 1.0, self.bounds_max[2] as f32 + 1.0) * b;
        Some((lo, hi))
    }

    /// Whether the superblock containing voxel `(i, j, k)` holds any allocated block.
    #[inline]
    pub fn superblock_occupied(&self, i: i32, j: i32, k: i32) -> bool {
        let shift = (BLOCK_EDGE * SUPERBLOCK_EDGE).trailing_zeros();
        let n = self.superblocks_per_edge as i32;
        let (x, y, z) = (i >> shift, j >> shift, k >> shift);
        if x < 0 || y < 0 || z < 0 || x >= n || y >= n || z >= n {
            return false;
        }
        self.occupancy.get(((z * n + y) * n + x) as usize).is_some_and(|c| *c > 0)
    }

    /// Whether a point (volume frame, m) lies inside the cube.
    pub fn contains(&self, point_in_volume: &Point3<f32>) -> bool {
        let edge = self.edge_m();
        point_in_volume.iter().all(|c| *c >= 0.0 && *c < edge)
    }

    #[inline]
    fn slot_index(&self, bx: i32, by: i32, bz: i32) -> Option<usize> {
        let n = self.blocks_per_edge as i32;
        if bx < 0 || by < 0 || bz < 0 || bx >= n || by >= n || bz >= n {
            return None;
        }
        Some(((bz as usize * self.blocks_per_edge) + by as usize) * self.blocks_per_edge + bx as usize)
    }

    /// The block at block coordinates, if allocated.
    #[inline]
    pub fn block(&self, bx: i32, by: i32, bz: i32) -> Option<&Block> {
        let slot = *self.slots.get(self.slot_index(bx, by, bz)?)?;
        if slot == NONE {
            return None;
        }
        self.blocks.get(slot as usize).map(|b| &**b)
    }

    /// The block containing voxel `(i, j, k)`, if allocated.
    #[inline]
    pub fn block_of_voxel(&self, i: i32, j: i32, k: i32) -> Option<&Block> {
        self.block(i >> 3, j >> 3, k >> 3)
    }

    /// TSDF and weight of voxel `(i, j, k)`; `None` outside allocated blocks.
    #[inline]
    pub fn voxel(&self, i: i32, j: i32, k: i32) -> Option<(f32, f32)> {
        let block = self.block_of_voxel(i, j, k)?;
        let local = local_index(i, j, k);
        let voxel = block.voxels.get(local)?;
        Some((voxel.tsdf, voxel.weight))
    }

    /// Observed TSDF of the voxel containing a point given in voxel units (`None` if unobserved).
    #[inline]
    pub fn nearest(&self, voxel: &Vector3<f32>) -> Option<f32> {
        let (t, w) = self.voxel(floor_i(voxel.x), floor_i(voxel.y), floor_i(voxel.z))?;
        (w > 0.0).then_some(t)
    }

    /// The 8 TSDF values around a point in voxel units (x fastest) and the point's fractional
    /// position between them; `None` unless all 8 voxels are observed.
    #[inline]
    fn trilinear_cell(&self, voxel: &Vector3<f32>) -> Option<([f32; 8], [f32; 3])> {
        // Voxel centres sit at integer + 0.5.
        let g = voxel - Vector3::repeat(0.5);
        let (i, j, k) = (floor_i(g.x), floor_i(g.y), floor_i(g.z));
        let (fx, fy, fz) = (g.x - i as f32, g.y - j as f32, g.z - k as f32);
        let mut c = [0.0f32; 8];
        let edge = BLOCK_EDGE as i32 - 1;
        if (i & 7) < edge && (j & 7) < edge && (k & 7) < edge {
            // Fast path: all 8 corners in one block.
            let block = self.block_of_voxel(i, j, k)?;
            let base = local_index(i, j, k);
            for (n, value) in c.iter_mut().enumerate() {
                let offset = (n & 1) + ((n >> 1) & 1) * BLOCK_EDGE + ((n >> 2) & 1) * BLOCK_EDGE * BLOCK_EDGE;
                let Some(voxel) = block.voxels.get(base + offset) else {
                    return None;
                };
                if voxel.weight <= 0.0 {
                    return None;
                }
                *value = voxel.tsdf;
            }
        } else {
            for (n, value) in c.iter_mut().enumerate() {
                let (dx, dy, dz) = ((n & 1) as i32, ((n >> 1) & 1) as i32, ((n >> 2) & 1) as i32);
                let (t, w) = self.voxel(i + dx, j + dy, k + dz)?;
                if w <= 0.0 {
                    return None;
                }
                *value = t;
            }
        }
        Some((c, [fx, fy, fz]))
    }

    /// Trilinear TSDF at a point in voxel units (the value of `trilinear`, without the gradient).
    pub fn trilinear_tsdf(&self, voxel: &Vector3<f32>) -> Option<f32> {
        let (c, [fx, fy, fz]) = self.trilinear_cell(voxel)?;
        let lerp = |a: f32, b: f32, f: f32| a + (b - a) * f;
        let y0 = lerp(lerp(c[0], c[1], fx), lerp(c[2], c[3], fx), fy);
        let y1 = lerp(lerp(c[4], c[5], fx), lerp(c[6], c[7], fx), fy);
        Some(lerp(y0, y1, fz))
    }

    /// Trilinear TSDF and its analytic gradient at a point in voxel units; `None` unless all 8
    /// surrounding voxels are observed.
    pub fn trilinear(&self, voxel: &Vector3<f32>) -> Option<TsdfSample> {
        let (c, [fx, fy, fz]) = self.trilinear_cell(voxel)?;
        let lerp = |a: f32, b: f32, f: f32| a + (b - a) * f;
        let x00 = lerp(c[0], c[1], fx);
        let x10 = lerp(c[2], c[3], fx);
        let x01 = lerp(c[4], c[5], fx);
        let x11 = lerp(c[6], c[7], fx);
        let y0 = lerp(x00, x10, fy);
        let y1 = lerp(x01, x11, fy);
        let tsdf = lerp(y0, y1, fz);
        // d/dx, d/dy, d/dz of the trilinear interpolant (per voxel), converted to per metre.
        let dx = lerp(lerp(c[1] - c[0], c[3] - c[2], fy), lerp(c[5] - c[4], c[7] - c[6], fy), fz);
        let dy = lerp(x10 - x00, x11 - x01, fz);
        let dz = y1 - y0;
        let gradient = Vector3::new(dx, dy, dz) / self.config.voxel_size_m;
        Some(TsdfSample { tsdf, gradient })
    }

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
                self.allocate(slot_index, coords, Block::empty());
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

    /// Blocks with their block coordinates (for remapping and export).
    pub fn blocks(&self) -> impl Iterator<Item = ([u16; 3], &Block)> {
        self.coords.iter().copied().zip(self.blocks.iter().map(|b| &**b))
    }

    /// Replaces the content with the given blocks (coordinates outside the cube are dropped).
    pub(crate) fn rebuild(&mut self, blocks: Vec<([i32; 3], Box<Block>)>) {
        self.clear();
        for (c, block) in blocks {
            let Some(slot_index) = self.slot_index(c[0], c[1], c[2]) else { continue };
            if self.slots.get(slot_index) != Some(&NONE) {
                continue;
            }
            self.allocate(slot_index, [c[0] as u16, c[1] as u16, c[2] as u16], block);
        }
    }

    /// Takes all blocks out (coordinates + data), leaving the volume empty.
    pub(crate) fn take_blocks(&mut self) -> Vec<([u16; 3], Box<Block>)> {
        let coords = std::mem::take(&mut self.coords);
        let taken = coords.into_iter().zip(std::mem::take(&mut self.blocks)).collect();
        self.clear();
        taken
    }

    /// Points (volume frame, m) of voxels with |tsdf| below `band` (in μ units), for tests and export.
    pub fn surface_voxels(&self, band: f32) -> Vec<Point3<f32>> {
        let s = self.config.voxel_size_m;
        let mut points = Vec::new();
        for (c, block) in self.blocks() {
            for (n, voxel) in block.voxels.iter().enumerate() {
                if voxel.weight > 0.0 && voxel.tsdf.abs() < band {
                    let (x, y, z) = (n % BLOCK_EDGE, (n / BLOCK_EDGE) % BLOCK_EDGE, n / (BLOCK_EDGE * BLOCK_EDGE));
                    let i = Vector3::new(
                        (c[0] as usize * BLOCK_EDGE + x) as f32,
                        (c[1] as usize * BLOCK_EDGE + y) as f32,
                        (c[2] as usize * BLOCK_EDGE + z) as f32,
                    );
                    points.push(Point3::from((i + Vector3::repeat(0.5)) * s));
                }
            }
        }
        points
    }
}

/// Index of voxel `(i, j, k)` inside its block (x fastest).
#[inline(always)]
fn local_index(i: i32, j: i32, k: i32) -> usize {
    ((i & 7) + 8 * ((j & 7) + 8 * (k & 7))) as usize
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
pub(crate) mod tests {
    use super::*;
    use nalgebra::{Translation3, UnitQuaternion};

    /// Renders a depth image of the plane `n·x = offset` (world frame = volume frame here).
    pub(crate) fn render_plane(
        intrinsics: &Intrinsics,
        volume_from_camera: &Isometry3<f64>,
        normal: Vector3<f64>,
        offset: f64,
    ) -> DepthImage {
        let mut depth = vec![f32::NAN; intrinsics.width * intrinsics.height];
        let origin = volume_from_camera.translation.vector;
        for v in 0..intrinsics.height {
            for u in 0..intrinsics.width {
                let ray_in_camera = intrinsics.back_project(u as f64, v as f64, 1.0);
                let ray = volume_from_camera.rotation * ray_in_camera;
                let denominator = normal.dot(&ray);
                if denominator.abs() < 1e-9 {
                    continue;
                }
                let z = (offset - normal.dot(&origin)) / denominator;
                if z > 0.0 {
                    depth[v * intrinsics.width + u] = z as f32;
                }
            }
        }
        DepthImage::new(intrinsics.width, intrinsics.height, depth).unwrap()
    }

    pub(crate) fn looking_down_pose(position: Vector3<f64>) -> Isometry3<f64> {
        // Camera z along volume +y (down), x along volume x.
        let rotation =
            nalgebra::Rotation3::from_matrix_unchecked(nalgebra::Matrix3::from_columns(&[Vector3::x(), -Vector3::z(), Vector3::y()]));
        Isometry3::from_parts(Translation3::from(position), UnitQuaternion::from_rotation_matrix(&rotation))
    }

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
    fn floor_small_matches_floor() {
        for x in [0.0f32, 0.25, 0.5, 0.999_999, 1.0, 2.5, 3.5, 639.5, 639.999, 4_194_303.5] {
            assert_eq!(floor_small(x), x.floor() as i32, "{x}");
        }
        for i in 0..100_000 {
            let x = i as f32 * 0.013_7;
            assert_eq!(floor_small(x), x.floor() as i32, "{x}");
        }
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

    #[test]
    fn bad_config_and_sizes_are_errors() {
        assert!(TsdfVolume::new(TsdfConfig { voxel_size_m: 0.0, ..TsdfConfig::default() }).is_err());
        assert!(TsdfVolume::new(TsdfConfig { min_depth_m: 5.0, ..TsdfConfig::default() }).is_err());
        assert!(TsdfVolume::new(TsdfConfig { size_m: 1000.0, ..TsdfConfig::default() }).is_err());
        let mut volume = TsdfVolume::new(TsdfConfig::default()).unwrap();
        let depth = DepthImage::new(2, 2, vec![1.0; 4]).unwrap();
        let result = volume.integrate(&depth, &Intrinsics::primesense_default(), &Isometry3::identity());
        assert!(matches!(result, Err(FusionError::SizeMismatch { .. })));
        // Points outside the cube and NaN depths are ignored, not a panic.
        let intrinsics = Intrinsics::new(2, 2, 1.0, 1.0, 0.5, 0.5).unwrap();
        let far = DepthImage::new(2, 2, vec![f32::NAN, 1.0, 2.0, 2.5]).unwrap();
        let away = Isometry3::translation(-10.0, -10.0, -10.0);
        assert_eq!(volume.integrate(&far, &intrinsics, &away).unwrap().blocks_touched, 0);
    }
}

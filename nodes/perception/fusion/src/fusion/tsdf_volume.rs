//! The sparse-block TSDF cube in the `volume` frame (J 5.1, Fig. 8-(ii)): the dense grid of block
//! slots over the cube and the pool of allocated blocks, the superblock occupancy for empty-space
//! leaping, voxel lookup and trilinear sampling of the TSDF and its gradient (for raycasting and
//! ICP), and the block moves of the moving volume (J 5.2).

use std::sync::atomic::AtomicU64;

use nalgebra::{Point3, Vector3};

use super::block::{local_index, Block, Voxel, BLOCK_EDGE, SUPERBLOCK_EDGE};
use super::{floor_i, FusionError, TsdfConfig};

/// Slot of no block in the dense slot grid.
pub(super) const NONE: u32 = u32::MAX;

/// A sampled TSDF value with its gradient (both in units of μ and μ per metre).
#[derive(Debug, Clone, Copy)]
pub struct TsdfSample {
    pub tsdf: f32,
    pub gradient: Vector3<f32>,
}

/// The sparse-block TSDF cube in the `volume` frame.
pub struct TsdfVolume {
    pub(super) config: TsdfConfig,
    pub(super) blocks_per_edge: usize,
    /// Dense slot grid: block (bx, by, bz) → pool index or `NONE`.
    pub(super) slots: Vec<u32>,
    pub(super) blocks: Vec<Box<Block>>,
    /// Blocks given up by a clear, a reset or a remap, kept for the next allocations: a node that
    /// resets its map every few seconds allocates its blocks once instead of handing thousands of
    /// 4 kB blocks back and forth with the allocator among its transient per-frame buffers (the
    /// freed blocks' pages would stay pinned by whatever small allocation lands beside them).
    /// Blocks in use plus spare stay at the most the volume ever needed at once (a rotation remap
    /// needs the old and the resampled blocks together).
    spare: Vec<Box<Block>>,
    /// Block coordinates of every pooled block.
    pub(super) coords: Vec<[u16; 3]>,
    /// Allocated blocks per superblock (SUPERBLOCK_EDGE³ blocks), for empty-space leaping.
    pub(super) occupancy: Vec<u32>,
    pub(super) superblocks_per_edge: usize,
    /// One bit per slot: the blocks the frame being integrated touches (all clear between frames).
    pub(super) touched: Vec<AtomicU64>,
    /// Inclusive block-coordinate bounds of the allocated blocks (min > max when empty).
    pub(super) bounds_min: [i32; 3],
    pub(super) bounds_max: [i32; 3],
}

impl TsdfVolume {
    /// An empty volume (no blocks).
    pub fn new(config: TsdfConfig) -> Result<Self, FusionError> {
        config.validate()?;
        // Whole blocks covering size_m; an edge that is a whole number of blocks up to f32 rounding
        // (2.2 m of 4 cm blocks is 55.000001 of them) is that number.
        let blocks = f64::from(config.size_m) / (f64::from(config.voxel_size_m) * BLOCK_EDGE as f64);
        let blocks_per_edge = (blocks - 1e-4).ceil().max(1.0) as usize;
        let superblocks_per_edge = blocks_per_edge.div_ceil(SUPERBLOCK_EDGE);
        Ok(Self {
            config,
            blocks_per_edge,
            slots: vec![NONE; blocks_per_edge * blocks_per_edge * blocks_per_edge],
            blocks: Vec::new(),
            spare: Vec::new(),
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

    /// Number of spare blocks (given up, kept for reuse).
    pub fn spare_count(&self) -> usize {
        self.spare.len()
    }

    /// Drops every block (tracking-loss reset, J 5.2); their memory is kept for reuse.
    pub fn clear(&mut self) {
        self.slots.fill(NONE);
        self.spare.append(&mut self.blocks);
        self.coords.clear();
        self.occupancy.fill(0);
        self.bounds_min = [i32::MAX; 3];
        self.bounds_max = [i32::MIN; 3];
    }

    /// A block of never-observed voxels: a spare one if there is one, else a new one.
    pub(crate) fn empty_block(&mut self) -> Box<Block> {
        match self.spare.pop() {
            Some(mut block) => {
                block.voxels.fill(Voxel::EMPTY);
                block
            }
            None => Block::empty(),
        }
    }

    /// Keeps `blocks` (no longer in the volume) for reuse.
    pub(crate) fn give_back(&mut self, blocks: impl IntoIterator<Item = Box<Block>>) {
        self.spare.extend(blocks);
    }

    /// Pools a new block at block coordinates `c` for slot `slot_index` (caller checked it is free).
    pub(super) fn allocate(&mut self, slot_index: usize, c: [u16; 3], block: Box<Block>) {
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
        for ((min, max), &v) in self.bounds_min.iter_mut().zip(self.bounds_max.iter_mut()).zip(&c) {
            *min = (*min).min(i32::from(v));
            *max = (*max).max(i32::from(v));
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
    pub(super) fn slot_index(&self, bx: i32, by: i32, bz: i32) -> Option<usize> {
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
                let voxel = block.voxels.get(base + offset)?;
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

    /// Blocks with their block coordinates (for remapping and export).
    pub fn blocks(&self) -> impl Iterator<Item = ([u16; 3], &Block)> {
        self.coords.iter().copied().zip(self.blocks.iter().map(|b| &**b))
    }

    /// Replaces the content with the given blocks (those outside the cube, or at a taken slot, are
    /// kept as spare).
    pub(crate) fn rebuild(&mut self, blocks: Vec<([i32; 3], Box<Block>)>) {
        self.clear();
        for (c, block) in blocks {
            let Some(slot_index) = self.slot_index(c[0], c[1], c[2]).filter(|&s| self.slots.get(s) == Some(&NONE)) else {
                self.spare.push(block);
                continue;
            };
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

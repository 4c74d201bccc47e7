//! Voxels and voxel blocks of the TSDF volume: a voxel is a TSDF value in units of the truncation
//! distance μ and a fusion weight (J 5.1, Curless & Levoy); a block is 8×8×8 of them, x fastest, the
//! unit of allocation near observed surfaces.

/// Voxels per block edge.
pub const BLOCK_EDGE: usize = 8;
/// Voxels per block.
pub const BLOCK_VOXELS: usize = BLOCK_EDGE * BLOCK_EDGE * BLOCK_EDGE;

/// Blocks per superblock edge of the coarse occupancy grid used for empty-space leaping.
pub const SUPERBLOCK_EDGE: usize = 4;

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

/// Index of voxel `(i, j, k)` inside its block (x fastest).
#[inline(always)]
pub(super) fn local_index(i: i32, j: i32, k: i32) -> usize {
    ((i & 7) + 8 * ((j & 7) + 8 * (k & 7))) as usize
}

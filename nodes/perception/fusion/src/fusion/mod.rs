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
//!
//! One concept per module, as nvblox does: `block` (voxels and voxel blocks), `tsdf_volume` (the
//! block storage, lookup and sampling), `integrator` (projective integration of a frame); here the
//! configuration, errors and the integer helpers they share.

mod block;
mod integrator;
mod tsdf_volume;

pub use block::{Block, Voxel, BLOCK_EDGE, BLOCK_VOXELS, SUPERBLOCK_EDGE};
pub use integrator::IntegrationStats;
pub use tsdf_volume::{TsdfSample, TsdfVolume};

/// `floor` as an integer without a libm call (not inlined without SSE4.1); saturating outside the
/// `i32` range like `as` (a point far off the volume, e.g. from a garbage pose), NaN gives 0.
#[inline(always)]
pub fn floor_i(x: f32) -> i32 {
    let i = x as i32;
    i.saturating_sub(i32::from((i as f32) > x))
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

#[cfg(test)]
pub(crate) mod tests {
    use super::*;
    use crate::camera::{DepthImage, Intrinsics};
    use nalgebra::{Isometry3, Vector3};
    use nalgebra::{Translation3, UnitQuaternion};

    #[test]
    fn an_edge_of_whole_blocks_keeps_its_size_through_f32_rounding() {
        for (size_m, blocks) in [(2.2, 55), (1.28, 32), (1.52, 38), (2.21, 56)] {
            let volume = TsdfVolume::new(TsdfConfig { voxel_size_m: 0.005, size_m, ..TsdfConfig::default() }).unwrap();
            assert_eq!(volume.blocks_per_edge(), blocks, "{size_m} m");
        }
    }

    #[test]
    fn floor_i_is_floor_and_saturates_outside_the_i32_range() {
        for x in [-2.5f32, -2.0, -0.5, 0.0, 0.5, 2.0, 2.5, 1e6 + 0.5] {
            assert_eq!(floor_i(x), x.floor() as i32, "{x}");
        }
        // Far off the volume (a garbage pose): no overflow, the ends of the range.
        assert_eq!(floor_i(-3e9), i32::MIN);
        assert_eq!(floor_i(f32::NEG_INFINITY), i32::MIN);
        assert_eq!(floor_i(3e9), i32::MAX);
        assert_eq!(floor_i(f32::NAN), 0);
    }

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

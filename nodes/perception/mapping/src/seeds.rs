//! Stage iii (J 4.3, steps 7–10): seed selection on the gravity-aligned Vg × Vg grid of the volume
//! xz-plane: salient points are bucketed by cell, cells are visited nearest-to-the-camera first,
//! and each cell gets random seeds until it holds ng (counting patches already mapped in it), with
//! at most ns seeds in total.

use nalgebra::{Isometry3, Point3, Vector3};
use rand::{rngs::StdRng, SeedableRng};

use crate::patch_map::{Cell, VolumeGrid};
use crate::saliency::Saliency;
use patchwalk_fusion::camera::{DepthImage, Intrinsics};

/// Configuration of stage iii (J 4.3, J 6.1.2).
#[derive(Debug, Clone, PartialEq, serde::Serialize, serde::Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct SeedConfig {
    /// Vg: grid cells per side of the volume xz-plane (J 4.3: "we typically use Vg = 8").
    pub cells_per_side: usize,
    /// ng: seeds (and patches) per cell (J 4.3, Fig. 8: ng = 1).
    pub per_cell: usize,
    /// ns: seeds per frame in total (J 6.1.2: "up to ng·Vg²" patches per frame = 64).
    pub max_seeds: usize,
    /// RNG seed of the random choice within a cell (deterministic runs).
    pub rng_seed: u64,
}

impl Default for SeedConfig {
    fn default() -> Self {
        Self { cells_per_side: 8, per_cell: 1, max_seeds: 64, rng_seed: 0 }
    }
}

/// A seed point (J step 10).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Seed {
    /// Pixel `(u, v)` in the auxiliary image D.
    pub pixel: (usize, usize),
    /// The seed point in the camera frame.
    pub point_in_camera: Vector3<f64>,
    /// Its grid cell.
    pub cell: Cell,
}

/// The auxiliary depth image D the seeds are drawn from, with its intrinsics.
#[derive(Debug, Clone, Copy)]
pub struct AuxiliaryImage<'a> {
    pub depth: &'a DepthImage,
    pub intrinsics: &'a Intrinsics,
}

/// Steps 7–10. `occupied[grid.flat(cell)]` is the number of patches the map already holds in each
/// cell (empty slice = none). The frame counter `frame` is mixed into the RNG seed so consecutive
/// frames draw different seeds while runs stay reproducible.
pub fn select_seeds(
    saliency: &Saliency,
    auxiliary: AuxiliaryImage<'_>,
    grid: &VolumeGrid,
    volume_from_camera: &Isometry3<f64>,
    occupied: &[usize],
    config: &SeedConfig,
    frame: u64,
) -> Vec<Seed> {
    let AuxiliaryImage { depth: auxiliary, intrinsics: auxiliary_intrinsics } = auxiliary;
    let n = grid.cells_per_side;
    // Step 8: bucket H by cell.
    let mut buckets: Vec<Vec<(usize, Vector3<f64>)>> = vec![Vec::new(); n * n];
    for index in saliency.salient_indices() {
        let (u, v) = (index % auxiliary.width, index / auxiliary.width);
        let Some(z) = auxiliary.get(u, v) else { continue };
        let point_in_camera = auxiliary_intrinsics.back_project(u as f64, v as f64, f64::from(z));
        let point_in_volume = (volume_from_camera * Point3::from(point_in_camera)).coords;
        if let Some(bucket) = grid.cell_of_volume_point(&point_in_volume).and_then(|cell| buckets.get_mut(grid.flat(cell))) {
            bucket.push((index, point_in_camera));
        }
    }
    // Step 9: cells by distance to the camera projected on the xz-plane.
    let camera_in_volume = volume_from_camera.translation.vector;
    let order = grid.cells_by_distance(camera_in_volume.x, camera_in_volume.z);
    // Step 10.
    let mut rng = StdRng::seed_from_u64(config.rng_seed ^ frame.wrapping_mul(0x9E37_79B9_7F4A_7C15));
    let mut seeds = Vec::with_capacity(config.max_seeds);
    for cell in order {
        let remaining = config.max_seeds.saturating_sub(seeds.len());
        if remaining == 0 {
            break;
        }
        let flat = grid.flat(cell);
        let Some(bucket) = buckets.get(flat) else { continue };
        let free = config.per_cell.saturating_sub(occupied.get(flat).copied().unwrap_or(0));
        let take = free.min(remaining).min(bucket.len());
        if take == 0 {
            continue;
        }
        for pick in rand::seq::index::sample(&mut rng, bucket.len(), take) {
            if let Some(&(index, point_in_camera)) = bucket.get(pick) {
                seeds.push(Seed { pixel: (index % auxiliary.width, index / auxiliary.width), point_in_camera, cell });
            }
        }
    }
    seeds
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::acquire::gravity_from_vector;
    use crate::saliency::tests::{floor_and_wall, small_camera};
    use crate::saliency::{hiking_saliency, SaliencyConfig};
    use patchwalk_fusion::volume::{initial_volume_from_camera, map_from_volume_rotation, MovingVolumeConfig};

    fn setup() -> (DepthImage, Intrinsics, Saliency, VolumeGrid, Isometry3<f64>) {
        let intrinsics = small_camera();
        let depth = floor_and_wall(&intrinsics);
        let g = gravity_from_vector(Vector3::y()).unwrap();
        let config = SaliencyConfig { fixation_radius_m: f64::INFINITY, ..Default::default() };
        let saliency = hiking_saliency(&depth, &intrinsics, &g, 0.05, &config);
        // Camera at the middle of the top of the back face of a 2 m cube.
        let volume_config = MovingVolumeConfig { nominal_position_fraction: [0.5, 0.0, 0.0], ..Default::default() };
        let volume_from_camera = initial_volume_from_camera(Some(Vector3::y()), 2.0, &volume_config);
        let volume_from_map = Isometry3::from_parts(Default::default(), map_from_volume_rotation().inverse());
        let grid = VolumeGrid { volume_from_map, edge_m: 2.0, cells_per_side: 8 };
        (depth, intrinsics, saliency, grid, volume_from_camera)
    }

    #[test]
    fn seeds_respect_caps_order_and_saliency() {
        let (depth, intrinsics, saliency, grid, volume_from_camera) = setup();
        let config = SeedConfig { max_seeds: 1000, ..Default::default() };
        let seeds =
            select_seeds(&saliency, AuxiliaryImage { depth: &depth, intrinsics: &intrinsics }, &grid, &volume_from_camera, &[], &config, 0);
        assert!(seeds.len() >= 10, "{} seeds", seeds.len());
        // ng = 1: every cell at most once, every seed salient and inside its cell.
        let mut cells: Vec<_> = seeds.iter().map(|s| s.cell).collect();
        cells.sort_unstable();
        cells.dedup();
        assert_eq!(cells.len(), seeds.len());
        for seed in &seeds {
            let index = seed.pixel.1 * depth.width + seed.pixel.0;
            assert_eq!(saliency.labels[index], crate::saliency::SaliencyLabel::Salient);
            let p = (volume_from_camera * Point3::from(seed.point_in_camera)).coords;
            assert_eq!(grid.cell_of_volume_point(&p), Some(seed.cell));
        }
        // Cells come nearest-first.
        let camera = volume_from_camera.translation.vector;
        let distance = |c: Cell| {
            let (x, z) = grid.cell_centre_xz(c);
            (x - camera.x).hypot(z - camera.z)
        };
        assert!(seeds.windows(2).all(|w| distance(w[0].cell) <= distance(w[1].cell)));
        // ns caps the total and keeps the nearest cells.
        let capped = select_seeds(
            &saliency,
            AuxiliaryImage { depth: &depth, intrinsics: &intrinsics },
            &grid,
            &volume_from_camera,
            &[],
            &SeedConfig { max_seeds: 3, ..config.clone() },
            0,
        );
        assert_eq!(capped.len(), 3);
        assert_eq!(capped.iter().map(|s| s.cell).collect::<Vec<_>>(), seeds[..3].iter().map(|s| s.cell).collect::<Vec<_>>());
        // ng = 3 gives up to 3 per cell.
        let three = select_seeds(
            &saliency,
            AuxiliaryImage { depth: &depth, intrinsics: &intrinsics },
            &grid,
            &volume_from_camera,
            &[],
            &SeedConfig { per_cell: 3, ..config.clone() },
            0,
        );
        assert!(three.len() > 2 * seeds.len());
        // Deterministic for the same frame, different for another frame.
        let again =
            select_seeds(&saliency, AuxiliaryImage { depth: &depth, intrinsics: &intrinsics }, &grid, &volume_from_camera, &[], &config, 0);
        assert_eq!(again, seeds);
        let other =
            select_seeds(&saliency, AuxiliaryImage { depth: &depth, intrinsics: &intrinsics }, &grid, &volume_from_camera, &[], &config, 1);
        assert_ne!(other, seeds);
    }

    #[test]
    fn occupied_cells_take_no_new_seeds() {
        let (depth, intrinsics, saliency, grid, volume_from_camera) = setup();
        let config = SeedConfig { max_seeds: 1000, ..Default::default() };
        let all =
            select_seeds(&saliency, AuxiliaryImage { depth: &depth, intrinsics: &intrinsics }, &grid, &volume_from_camera, &[], &config, 0);
        let mut occupied = vec![0; 64];
        let full = all[0].cell;
        occupied[grid.flat(full)] = 1;
        let rest = select_seeds(
            &saliency,
            AuxiliaryImage { depth: &depth, intrinsics: &intrinsics },
            &grid,
            &volume_from_camera,
            &occupied,
            &config,
            0,
        );
        assert_eq!(rest.len(), all.len() - 1);
        assert!(rest.iter().all(|s| s.cell != full));
    }
}

//! Stage iii (J 4.3, steps 7–10): seed selection on the gravity-aligned Vg × Vg grid of the volume
//! xz-plane: salient points are bucketed by cell, cells are visited nearest-to-the-camera first,
//! and each cell gets random seeds until it holds ng (counting patches already mapped in it), with
//! at most ns seeds in total.
//!
//! Learned seeding (`seeds.order`): footholds predicted by a learned model (the CNN paper's
//! network, `patchwalk_footholds`) with their scores can order the cells (`learned_first`: cells
//! holding a prediction first, best score first, each seeded at its salient point nearest the
//! prediction, then J's order for the rest) or replace the salient points (`learned_only`: one seed
//! at each predicted foothold, on the surface the auxiliary image shows there). The caps ng and ns
//! and the cells already mapped apply to every order.

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
    /// Where the seeds come from: hiking saliency alone (J), or learned foothold predictions in
    /// addition to it or instead of it (see [`SeedOrder`]).
    pub order: SeedOrder,
}

impl Default for SeedConfig {
    fn default() -> Self {
        Self { cells_per_side: 8, per_cell: 1, max_seeds: 64, rng_seed: 0, order: SeedOrder::Saliency }
    }
}

/// How stage iii orders and chooses its seeds (`seeds.order`).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, serde::Serialize, serde::Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum SeedOrder {
    /// J steps 8–10: salient points, cells nearest the camera first, a random one per cell.
    #[default]
    Saliency,
    /// Predictions in addition to saliency: the cells holding a predicted foothold come first, the
    /// best-scored first, each seeded at its salient point nearest the prediction; the other cells
    /// follow in J's order. Without predictions this is `saliency`.
    LearnedFirst,
    /// Predictions instead of saliency: a seed at each predicted foothold, the best-scored first,
    /// at the auxiliary image's surface point under it (its pixel needs depth, not saliency). Without
    /// predictions no seeds.
    LearnedOnly,
}

/// A predicted foothold to seed from: its position in the volume frame and its score in [0, 1].
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct SeedPrior {
    pub point_in_volume: Vector3<f64>,
    pub score: f64,
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

/// Steps 7–10 in the order `config.order` asks for. `occupied[grid.flat(cell)]` is the number of
/// patches the map already holds in each cell (empty slice = none). `priors` are the predicted
/// footholds (used by the learned orders only). The frame counter `frame` is mixed into the RNG seed
/// so consecutive frames draw different seeds while runs stay reproducible.
#[allow(clippy::too_many_arguments)]
pub fn select_seeds(
    saliency: &Saliency,
    auxiliary: AuxiliaryImage<'_>,
    grid: &VolumeGrid,
    volume_from_camera: &Isometry3<f64>,
    occupied: &[usize],
    priors: &[SeedPrior],
    config: &SeedConfig,
    frame: u64,
) -> Vec<Seed> {
    match config.order {
        SeedOrder::Saliency => salient_seeds(saliency, auxiliary, grid, volume_from_camera, occupied, &[], config, frame),
        SeedOrder::LearnedFirst => salient_seeds(saliency, auxiliary, grid, volume_from_camera, occupied, priors, config, frame),
        SeedOrder::LearnedOnly => learned_seeds(auxiliary, grid, volume_from_camera, occupied, priors, config),
    }
}

/// The best prediction per cell (flat index → score and position in the volume), inside the grid.
fn best_prior_per_cell(grid: &VolumeGrid, priors: &[SeedPrior]) -> Vec<Option<SeedPrior>> {
    let mut best: Vec<Option<SeedPrior>> = vec![None; grid.cells_per_side * grid.cells_per_side];
    for prior in priors.iter().filter(|p| p.score.is_finite() && p.point_in_volume.iter().all(|v| v.is_finite())) {
        let Some(slot) = grid.cell_of_volume_point(&prior.point_in_volume).and_then(|cell| best.get_mut(grid.flat(cell))) else {
            continue;
        };
        if slot.is_none_or(|b| prior.score > b.score) {
            *slot = Some(*prior);
        }
    }
    best
}

/// J steps 8–10 over the salient points; with `priors`, the cells holding one come first (best
/// score first, nearest first on ties) and take the salient point nearest the prediction.
#[allow(clippy::too_many_arguments)]
fn salient_seeds(
    saliency: &Saliency,
    auxiliary: AuxiliaryImage<'_>,
    grid: &VolumeGrid,
    volume_from_camera: &Isometry3<f64>,
    occupied: &[usize],
    priors: &[SeedPrior],
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
    // Step 9: cells by distance to the camera projected on the xz-plane (learned first: the cells
    // holding a prediction before them, by score; the sort is stable, so ties stay nearest-first).
    let camera_in_volume = volume_from_camera.translation.vector;
    let mut order = grid.cells_by_distance(camera_in_volume.x, camera_in_volume.z);
    let best = if priors.is_empty() { Vec::new() } else { best_prior_per_cell(grid, priors) };
    let prior_of = |cell: Cell| best.get(grid.flat(cell)).copied().flatten();
    if !best.is_empty() {
        order.sort_by(|a, b| {
            let score = |c: Cell| prior_of(c).map_or(f64::NEG_INFINITY, |p| p.score);
            score(*b).total_cmp(&score(*a))
        });
    }
    // Step 10.
    let mut rng = StdRng::seed_from_u64(config.rng_seed ^ frame.wrapping_mul(0x9E37_79B9_7F4A_7C15));
    let mut seeds = Vec::with_capacity(config.max_seeds);
    let camera_from_volume = volume_from_camera.inverse();
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
        let picks: Vec<usize> = match prior_of(cell) {
            // The salient points nearest the prediction.
            Some(prior) => {
                let target = (camera_from_volume * Point3::from(prior.point_in_volume)).coords;
                let mut by_distance: Vec<(f64, usize)> =
                    bucket.iter().enumerate().map(|(i, (_, p))| ((p - target).norm_squared(), i)).collect();
                by_distance.sort_by(|a, b| a.0.total_cmp(&b.0));
                by_distance.into_iter().take(take).map(|(_, i)| i).collect()
            }
            None => rand::seq::index::sample(&mut rng, bucket.len(), take).into_vec(),
        };
        for pick in picks {
            if let Some(&(index, point_in_camera)) = bucket.get(pick) {
                seeds.push(Seed { pixel: (index % auxiliary.width, index / auxiliary.width), point_in_camera, cell });
            }
        }
    }
    seeds
}

/// A seed at each predicted foothold, best score first: the prediction projected into the auxiliary
/// image, the seed the surface point of that pixel (the nearest pixel with depth within
/// [`LEARNED_SEARCH_PX`]), in the cell it falls in; the caps ng (with the mapped patches) and ns hold.
fn learned_seeds(
    auxiliary: AuxiliaryImage<'_>,
    grid: &VolumeGrid,
    volume_from_camera: &Isometry3<f64>,
    occupied: &[usize],
    priors: &[SeedPrior],
    config: &SeedConfig,
) -> Vec<Seed> {
    let AuxiliaryImage { depth, intrinsics } = auxiliary;
    let camera_from_volume = volume_from_camera.inverse();
    let mut ranked: Vec<&SeedPrior> =
        priors.iter().filter(|p| p.score.is_finite() && p.point_in_volume.iter().all(|v| v.is_finite())).collect();
    ranked.sort_by(|a, b| b.score.total_cmp(&a.score));
    let mut taken = vec![0usize; grid.cells_per_side * grid.cells_per_side];
    let mut seeds = Vec::with_capacity(config.max_seeds.min(ranked.len()));
    for prior in ranked {
        if seeds.len() >= config.max_seeds {
            break;
        }
        let target = (camera_from_volume * Point3::from(prior.point_in_volume)).coords;
        let Some((u, v)) = intrinsics.project(&target) else { continue };
        let Some((pixel, z)) = nearest_with_depth(depth, u, v, LEARNED_SEARCH_PX) else { continue };
        let point_in_camera = intrinsics.back_project(pixel.0 as f64, pixel.1 as f64, f64::from(z));
        let point_in_volume = (volume_from_camera * Point3::from(point_in_camera)).coords;
        let Some(cell) = grid.cell_of_volume_point(&point_in_volume) else { continue };
        let flat = grid.flat(cell);
        let Some(count) = taken.get_mut(flat) else { continue };
        if *count + occupied.get(flat).copied().unwrap_or(0) >= config.per_cell {
            continue;
        }
        *count += 1;
        seeds.push(Seed { pixel, point_in_camera, cell });
    }
    seeds
}

/// How far (pixels) a learned seed looks around its projection for a pixel with depth.
pub const LEARNED_SEARCH_PX: usize = 3;

/// The pixel nearest `(u, v)` with depth, within `radius` pixels (square rings), and its depth.
fn nearest_with_depth(depth: &DepthImage, u: f64, v: f64, radius: usize) -> Option<((usize, usize), f32)> {
    if !(u.is_finite() && v.is_finite() && u >= -0.5 && v >= -0.5) {
        return None;
    }
    let (u0, v0) = (u.round() as usize, v.round() as usize);
    if u0 >= depth.width || v0 >= depth.height {
        return None;
    }
    let mut best: Option<(usize, (usize, usize), f32)> = None;
    let (lo_u, hi_u) = (u0.saturating_sub(radius), (u0 + radius).min(depth.width - 1));
    let (lo_v, hi_v) = (v0.saturating_sub(radius), (v0 + radius).min(depth.height - 1));
    for pv in lo_v..=hi_v {
        for pu in lo_u..=hi_u {
            let Some(z) = depth.get(pu, pv) else { continue };
            let d = pu.abs_diff(u0).pow(2) + pv.abs_diff(v0).pow(2);
            if best.is_none_or(|(bd, _, _)| d < bd) {
                best = Some((d, (pu, pv), z));
            }
        }
    }
    best.map(|(_, pixel, z)| (pixel, z))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::acquire::gravity_from_vector;
    use crate::saliency::tests::{floor_and_wall, small_camera};
    use crate::saliency::{hiking_saliency, SaliencyConfig};
    use patchwalk_fusion::volume::{initial_volume_from_camera, map_from_volume_rotation, MovingVolumeConfig};

    type Scene = (DepthImage, Intrinsics, Saliency, VolumeGrid, Isometry3<f64>);

    /// [`select_seeds`] on the scene of [`setup`].
    fn select(scene: &Scene, occupied: &[usize], priors: &[SeedPrior], config: &SeedConfig, frame: u64) -> Vec<Seed> {
        let (depth, intrinsics, saliency, grid, volume_from_camera) = scene;
        select_seeds(saliency, AuxiliaryImage { depth, intrinsics }, grid, volume_from_camera, occupied, priors, config, frame)
    }

    fn setup() -> Scene {
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
        let scene = setup();
        let (depth, _, saliency, grid, volume_from_camera) = &scene;
        let config = SeedConfig { max_seeds: 1000, ..Default::default() };
        let seeds = select(&scene, &[], &[], &config, 0);
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
        let capped = select(&scene, &[], &[], &SeedConfig { max_seeds: 3, ..config.clone() }, 0);
        assert_eq!(capped.len(), 3);
        assert_eq!(capped.iter().map(|s| s.cell).collect::<Vec<_>>(), seeds[..3].iter().map(|s| s.cell).collect::<Vec<_>>());
        // ng = 3 gives up to 3 per cell.
        let three = select(&scene, &[], &[], &SeedConfig { per_cell: 3, ..config.clone() }, 0);
        assert!(three.len() > 2 * seeds.len());
        // Deterministic for the same frame, different for another frame.
        let again = select(&scene, &[], &[], &config, 0);
        assert_eq!(again, seeds);
        let other = select(&scene, &[], &[], &config, 1);
        assert_ne!(other, seeds);
    }

    #[test]
    fn occupied_cells_take_no_new_seeds() {
        let scene = setup();
        let (_, _, _, grid, _) = &scene;
        let config = SeedConfig { max_seeds: 1000, ..Default::default() };
        let all = select(&scene, &[], &[], &config, 0);
        let mut occupied = vec![0; 64];
        let full = all[0].cell;
        occupied[grid.flat(full)] = 1;
        let rest = select(&scene, &occupied, &[], &config, 0);
        assert_eq!(rest.len(), all.len() - 1);
        assert!(rest.iter().all(|s| s.cell != full));
    }

    /// A prediction on the surface under the salient pixel `index` of the setup, in the volume.
    fn prior_at(
        depth: &DepthImage,
        intrinsics: &Intrinsics,
        volume_from_camera: &Isometry3<f64>,
        pixel: (usize, usize),
        score: f64,
    ) -> SeedPrior {
        let z = depth.get(pixel.0, pixel.1).unwrap();
        let point = intrinsics.back_project(pixel.0 as f64, pixel.1 as f64, f64::from(z));
        SeedPrior { point_in_volume: (volume_from_camera * Point3::from(point)).coords, score }
    }

    #[test]
    fn learned_first_puts_predicted_cells_first_and_seeds_next_to_the_prediction() {
        let scene = setup();
        let (depth, intrinsics, _, grid, volume_from_camera) = &scene;
        let config = SeedConfig { max_seeds: 1000, ..Default::default() };
        let plain = select(&scene, &[], &[], &config, 0);
        // Two predictions in the two farthest seeded cells, the farther one scored higher.
        let far = plain[plain.len() - 1];
        let second = plain[plain.len() - 2];
        let priors = [
            prior_at(depth, intrinsics, volume_from_camera, second.pixel, 0.6),
            prior_at(depth, intrinsics, volume_from_camera, far.pixel, 0.9),
        ];
        let learned = SeedConfig { order: SeedOrder::LearnedFirst, ..config.clone() };
        let seeds = select(&scene, &[], &priors, &learned, 0);
        assert_eq!(seeds.len(), plain.len(), "the same cells are seeded");
        assert_eq!((seeds[0].cell, seeds[1].cell), (far.cell, second.cell), "best score first");
        // Each at the salient point nearest its prediction: here the very pixel predicted.
        assert_eq!((seeds[0].pixel, seeds[1].pixel), (far.pixel, second.pixel));
        // The other cells keep J's nearest-first order.
        let camera = volume_from_camera.translation.vector;
        let distance = |c: Cell| {
            let (x, z) = grid.cell_centre_xz(c);
            (x - camera.x).hypot(z - camera.z)
        };
        assert!(seeds[2..].windows(2).all(|w| distance(w[0].cell) <= distance(w[1].cell)));
        // ns keeps the predicted cells.
        let capped = select(&scene, &[], &priors, &SeedConfig { max_seeds: 1, ..learned.clone() }, 0);
        assert_eq!(capped.iter().map(|s| s.cell).collect::<Vec<_>>(), vec![far.cell]);
        // Without predictions (or with non-finite ones) it is J's order.
        assert_eq!(select(&scene, &[], &[], &learned, 0), plain);
        let nan = [SeedPrior { point_in_volume: Vector3::new(f64::NAN, 0.0, 0.0), score: 1.0 }];
        assert_eq!(select(&scene, &[], &nan, &learned, 0), plain);
    }

    #[test]
    fn learned_only_seeds_at_the_predictions_by_score_within_the_caps() {
        let scene = setup();
        let (depth, intrinsics, _, grid, volume_from_camera) = &scene;
        let config = SeedConfig { max_seeds: 1000, order: SeedOrder::LearnedOnly, ..Default::default() };
        assert!(select(&scene, &[], &[], &config, 0).is_empty(), "no predictions, no seeds");
        let plain = select(&scene, &[], &[], &SeedConfig { order: SeedOrder::Saliency, ..config.clone() }, 0);
        let (a, b) = (plain[0], plain[plain.len() / 2]);
        // A third prediction in a's cell scored below it: ng = 1 keeps only the better one.
        let mut beside = a.pixel;
        beside.0 += 1;
        let priors = [
            prior_at(depth, intrinsics, volume_from_camera, a.pixel, 0.7),
            prior_at(depth, intrinsics, volume_from_camera, b.pixel, 0.8),
            prior_at(depth, intrinsics, volume_from_camera, beside, 0.5),
            // Behind the camera: not in the image, no seed.
            SeedPrior { point_in_volume: (volume_from_camera * Point3::new(0.0, 0.0, -1.0)).coords, score: 1.0 },
        ];
        let seeds = select(&scene, &[], &priors, &config, 0);
        let cell_of_beside = {
            let p = priors[2].point_in_volume;
            grid.cell_of_volume_point(&p).unwrap()
        };
        let expected = if cell_of_beside == a.cell { 2 } else { 3 };
        assert_eq!(seeds.len(), expected, "{seeds:?}");
        assert_eq!((seeds[0].pixel, seeds[0].cell), (b.pixel, b.cell), "best score first");
        assert_eq!((seeds[1].pixel, seeds[1].cell), (a.pixel, a.cell));
        // The seed is the surface point of its pixel.
        let z = depth.get(b.pixel.0, b.pixel.1).unwrap();
        assert!((seeds[0].point_in_camera - intrinsics.back_project(b.pixel.0 as f64, b.pixel.1 as f64, f64::from(z))).norm() < 1e-12);
        // A mapped patch in b's cell: the cell takes no learned seed either; ns caps the total.
        let mut occupied = vec![0; 64];
        occupied[grid.flat(b.cell)] = 1;
        let rest = select(&scene, &occupied, &priors, &config, 0);
        assert!(rest.iter().all(|s| s.cell != b.cell) && rest.len() == expected - 1);
        let one = select(&scene, &[], &priors, &SeedConfig { max_seeds: 1, ..config.clone() }, 0);
        assert_eq!(one.len(), 1);
    }

    #[test]
    fn the_order_is_read_from_config() {
        let config: SeedConfig = serde_json::from_str(r#"{"order": "learned_first"}"#).unwrap();
        assert_eq!(config.order, SeedOrder::LearnedFirst);
        assert_eq!(SeedConfig::default().order, SeedOrder::Saliency);
        assert!(serde_json::from_str::<SeedConfig>(r#"{"order": "cnn"}"#).is_err());
    }
}

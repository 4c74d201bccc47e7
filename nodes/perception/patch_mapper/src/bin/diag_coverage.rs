//! Why patches fail J's coverage test (J eq 16–17) on real frames: runs `patch_mapper map`'s
//! single-frame mapper (J's defaults, gravity from the dominant plane) over a dataset and sorts
//! every bad cell of every coverage-rejected patch by cause:
//!
//! - `outside`: too many points outside the boundary (eq 16's second clause);
//! - `beyond the ball`: the boundary's part beyond the neighbourhood's r-ball holds too few of the
//!   foot column's points (the camera did not see it);
//! - `inside, sparse`: too few inside, but some (point density below ζ_i·N_e);
//! - `inside, empty`, by what the camera has where the cell's centre (lifted onto the surface)
//!   projects: `no depth` (a hole of the sensor: a depth edge's shadow, a dark or shiny surface),
//!   `off image` (the neighbourhood cut at the image border), `another surface` (the pixel sees
//!   something more than 2 cm off the patch, an occluder or a surface behind), `beyond the ball`
//!   (the pixel is on the surface but further than r from the seed: the boundary reaches past the
//!   r-ball), or `on the surface` (data there, yet not in the cell).
//!
//! It also gives the coverage failures by surface type, the angle between each seed's saliency
//! normal and its patch's normal (seeds whose box normals mix two surfaces disagree with their
//! patch), and counts the neighbourhood points that lie off the patch surface by more than 2 cm
//! (points of a second surface in the r-ball inflate N of J eq 17 and with it N_e).
//!
//! `cargo run --release -p patch_mapper --bin diag_coverage [-- DATASET] [--config FILE] [--max-frames N] [--gravity-from-groundtruth]`
//!
//! `--gravity-from-groundtruth` takes gravity from the dataset's ground-truth poses (world z up, as
//! `terrain_sim record` writes them) instead of the dominant plane.

use std::collections::BTreeMap;

use anyhow::{Context, Result};
use patchwalk_fusion::dataset::{test_data_dir, Dataset};
use patchwalk_mapping::acquire::{gravity_from_dominant_plane, organized_cloud};
use patchwalk_mapping::foot_column::{foot_column, DEFAULT_MAX_PIXELS};
use patchwalk_mapping::mapper::{default_volume_from_map, single_frame_volume_from_camera, FrameInput, Mapper, MapperConfig, Verdict};
use patchwalk_mapping::neighbourhood::{ball_neighbourhood, gather};
use patchwalk_spl::patch::PatchQuery;
use patchwalk_spl::validate::coverage_cells;

fn main() -> Result<()> {
    let args: Vec<String> = std::env::args().skip(1).collect();
    let flag = |name: &str| args.iter().position(|a| a == name).and_then(|i| args.get(i + 1)).cloned();
    let input = args.first().filter(|a| !a.starts_with("--")).map_or_else(|| test_data_dir().join("tum_fr1_xyz"), Into::into);
    // A simulator's dataset (terrain_sim record): gravity from the ground-truth pose (world z up).
    let from_groundtruth = args.iter().any(|a| a == "--gravity-from-groundtruth");
    let max_frames: usize = flag("--max-frames").map(|s| s.parse()).transpose().context("--max-frames N")?.unwrap_or(usize::MAX);
    let config = match flag("--config") {
        Some(path) => {
            #[derive(serde::Deserialize, Default)]
            #[serde(default)]
            struct File {
                mapper: MapperConfig,
            }
            let file: File = patchwalk_ros::params::load_config(Some(std::path::Path::new(&path)), &[])
                .with_context(|| format!("{path}: invalid mapper configuration"))?;
            file.mapper
        }
        None => MapperConfig::default(),
    };
    let dataset = Dataset::open(&input).with_context(|| format!("opening {}", input.display()))?;
    let intrinsics = dataset.intrinsics;
    let mut causes: BTreeMap<&str, usize> = BTreeMap::new();
    let mut by_surface: BTreeMap<&str, [usize; 2]> = BTreeMap::new();
    // Angle (degrees) between the seed's saliency normal and its patch's normal: [not valid, valid].
    let mut normal_angles: [Vec<f64>; 2] = [Vec::new(), Vec::new()];
    let (mut fitted, mut valid, mut coverage_failed, mut bad_cells, mut cut_at_border) = (0, 0, 0, 0, 0);
    let (mut off_surface_points, mut points_total) = (0usize, 0usize);
    let mut scratch = Vec::new();
    let mut column = Vec::new();
    for index in (0..dataset.frames.len()).take(max_frames) {
        let depth = dataset.load_depth(index)?;
        let cloud = organized_cloud(&depth, &intrinsics)?;
        let gravity = if from_groundtruth {
            let pose = dataset.groundtruth_near(dataset.frames[index].timestamp, 0.05).context("no ground-truth pose near the frame")?;
            nalgebra::Unit::new_normalize(pose.world_from_camera.inverse().rotation * -nalgebra::Vector3::z())
        } else {
            gravity_from_dominant_plane(&cloud, 0.02, index as u64).context("no dominant plane")?
        };
        let volume_from_camera = single_frame_volume_from_camera(&gravity, config.volume_edge_m);
        let mut mapper = Mapper::new(config.clone(), "camera_optical", default_volume_from_map())?;
        let result = mapper.process(&FrameInput { depth: &depth, intrinsics: &intrinsics, volume_from_camera, timestamp: 0.0 })?;
        let filtered = organized_cloud(&result.preprocessed.filtered, &intrinsics)?;
        fitted += result.summary().fitted;
        valid += result.summary().valid;
        for outcome in &result.outcomes {
            if let Some(patch) = &outcome.patch_in_camera {
                let entry = by_surface.entry(patch.surface.name()).or_default();
                entry[0] += 1;
                entry[1] += usize::from(outcome.verdict == Verdict::Coverage);
            }
        }
        for outcome in &result.outcomes {
            let Some(patch) = &outcome.patch_in_camera else { continue };
            let (u, v) = outcome.seed.pixel;
            let Some(seed_normal) = result.saliency.normals_in_camera.get(v * result.saliency.width + u).map(|n| n.cast::<f64>()) else {
                continue;
            };
            let angle = seed_normal.dot(&patch.normal()).abs().min(1.0).acos().to_degrees();
            if angle.is_finite() {
                normal_angles[usize::from(outcome.verdict.is_valid())].push(angle);
            }
        }
        for outcome in result.outcomes.iter().filter(|o| o.verdict == Verdict::Coverage) {
            let Some(patch) = &outcome.patch_in_camera else { continue };
            coverage_failed += 1;
            ball_neighbourhood(&filtered, &intrinsics, &outcome.seed.point_in_camera, config.foot_radius_m, &mut scratch);
            let points = gather(&filtered, &scratch);
            let query = PatchQuery::new(patch);
            points_total += points.len();
            off_surface_points += points.iter().filter(|q| query.distance(q) > 0.02).count();
            let mut cut = false;
            let ball = patchwalk_spl::validate::SampledBall { centre: outcome.seed.point_in_camera, radius: config.foot_radius_m };
            let up = -result.gravity_in_camera.into_inner();
            foot_column(&filtered, &intrinsics, patch, &up, config.validate.edge_column_height_m, DEFAULT_MAX_PIXELS, &mut column, None);
            let sampled = config.validate.coverage_within_sampled_ball.then_some((&ball, column.as_slice()));
            for cell in coverage_cells(patch, &points, sampled, &config.validate) {
                if !(cell.too_few_inside || cell.too_many_outside) {
                    continue;
                }
                bad_cells += 1;
                let cause = if cell.too_few_beyond_ball && !cell.too_few_inside && !cell.too_many_outside {
                    "beyond the ball: too few column points"
                } else if cell.too_many_outside {
                    "outside"
                } else if cell.inside > 0 {
                    "inside, sparse"
                } else {
                    let u = nalgebra::Vector2::new(cell.x0 + 0.5 * cell.pitch, cell.y0 + 0.5 * cell.pitch);
                    let centre = patch.explicit_world(&u).unwrap_or(patch.center);
                    match intrinsics.pixel_of(&centre) {
                        None => {
                            cut = true;
                            "inside, empty: off image"
                        }
                        Some((px, py)) => match filtered.get(px, py).map(|p| p.cast::<f64>()) {
                            None => "inside, empty: no depth",
                            Some(p) if query.distance(&p) > 0.02 => "inside, empty: another surface",
                            Some(p) if (p - outcome.seed.point_in_camera).norm() > config.foot_radius_m => "inside, empty: beyond the ball",
                            Some(_) => "inside, empty: on the surface",
                        },
                    }
                };
                *causes.entry(cause).or_default() += 1;
            }
            cut_at_border += usize::from(cut);
        }
    }
    println!("{}: {fitted} fitted, {valid} valid, {coverage_failed} failed coverage ({bad_cells} bad cells)", input.display());
    println!("bad cells by cause:");
    for (cause, n) in &causes {
        println!("  {cause:<34} {n:>6}  ({:.0} %)", 100.0 * *n as f64 / bad_cells.max(1) as f64);
    }
    println!("coverage failures by surface type:");
    for (surface, [n, failed]) in &by_surface {
        println!("  {surface:<34} {failed:>6} of {n:>6}  ({:.0} %)", 100.0 * *failed as f64 / (*n).max(1) as f64);
    }
    let [mut not_valid, mut valid_angles] = normal_angles;
    for (name, angles) in [("valid", &mut valid_angles), ("not valid", &mut not_valid)] {
        angles.sort_by(f64::total_cmp);
        let q = |p: f64| angles.get(((angles.len().max(1) - 1) as f64 * p).round() as usize).copied().unwrap_or(f64::NAN);
        println!("seed normal vs patch normal, {name} patches: p50 {:.1}°, p90 {:.1}° ({} patches)", q(0.5), q(0.9), angles.len());
    }
    println!("coverage-failed patches with cells off the image: {cut_at_border}");
    println!(
        "their r-ball points off the surface by > 2 cm: {off_surface_points} of {points_total} ({:.1} %)",
        100.0 * off_surface_points as f64 / points_total.max(1) as f64
    );
    Ok(())
}

//! Bench: foothold validation against ground truth. Real terrains (the heightmaps of
//! `tests/data/heightmaps/`, at 1 cm per pixel with heights scaled alike, so stairs and blocks are
//! foot-sized) rendered with the simulated Carmine's noise and missing data from a small biped's head
//! (0.45 m above the ground, pitched 45° down) walking paths over them; every frame goes through the
//! single-frame mapper (J's defaults as `patch_mapper map --no-dtfp` runs them, gravity from the
//! camera pose) and every fitted patch is checked against the terrain's exact surface.
//!
//! Printed per scene, for J 3.3's tests alone, with the default foothold tests (tilt, edge, the disc
//! in view: `--out-of-view-max`, the default 0.02 unless given), with the
//! open-rim test switched on too (`--open-rim-max`, 0.01 unless given) and with the visibility test
//! on top (`--unseen-max`, 0.02 unless given): fitted patches, valid
//! share, mean residual of the valid ones, the share of valid patches lying across an edge
//! (ground-truth terrain more than 2 cm off the patch surface inside the foot disc's column
//! along gravity), and walls accepted (valid patches where the plane through the true terrain under
//! the foot disc is tilted more than 45°; beside it, how many have a 1 cm cell steeper than 45°
//! under their centre, which on the scanned staircase's rough flanks happens under discs the terrain
//! follows within 2 cm everywhere).
//!
//! `cargo run --release -p terrain_sim --bin bench_footholds -- [--frames N] [--seeds 11,12] [--detail] [--edge-quantile Q] [--open-rim-max F] [--unseen-max F] [--out-of-view-max F]`

use anyhow::{Context, Result};
use nalgebra::{Unit, Vector3};
use patchwalk_mapping::mapper::{default_volume_from_map, single_frame_volume_from_camera, FrameInput, Mapper, MapperConfig, Verdict};
use patchwalk_spl::patch::Patch;
use patchwalk_spl::transform::transform_patch;
use patchwalk_spl::validate::visibility::{SUGGESTED_OPEN_RIM_MAX_FRACTION, SUGGESTED_UNSEEN_MAX_FRACTION};
use patchwalk_spl::validate::{DiscView, FootColumn, ValidateConfig};
use terrain_sim::config::SimConfig;
use terrain_sim::scene::Heightfield;
use terrain_sim::sim::Simulator;

/// The true terrain in the foot disc's column of one valid patch (world frame, z up).
#[derive(Debug, Default)]
struct Truth {
    /// Terrain samples in the column.
    samples: usize,
    /// Of them more than 2 cm off the patch surface, below it (a drop) and above it (a bump).
    below: usize,
    above: usize,
    /// Largest distance off the surface (m).
    max_offset: f64,
    /// The true terrain under the foot disc (the plane through its samples in the column) is tilted
    /// more than 45°: a wall at the scale of the foot.
    wall: bool,
    /// The true surface of the 1 cm cell under the centre is tilted more than 45° (a wall, or one
    /// steep cell of a rough surface the disc as a whole follows).
    steep_centre: bool,
}

impl Truth {
    fn across(&self) -> bool {
        self.below + self.above > 0
    }
}

/// Ground truth's verdict on one valid patch (world frame, z up).
fn ground_truth(patch: &Patch, terrain: &Heightfield) -> Truth {
    let up = Vector3::z();
    let column = FootColumn::new(patch, Some(&up), ValidateConfig::default().edge_column_height_m);
    // The terrain under the disc on a 4 mm grid over the boundary's reach (tilted discs reach further).
    let reach = patch.boundary_half_extents().max() + 0.05;
    let step = 0.004;
    let n = (reach / step).ceil() as i64;
    let mut truth = Truth::default();
    // Least squares plane z = a·x + b·y + c through the samples in the column: Σ [x y 1]ᵀ[x y 1], Σ [x y 1]ᵀ z.
    let mut normal_matrix = nalgebra::Matrix3::<f64>::zeros();
    let mut rhs = Vector3::<f64>::zeros();
    for i in -n..=n {
        for j in -n..=n {
            let (x, y) = (patch.center.x + i as f64 * step, patch.center.y + j as f64 * step);
            let Some(z) = terrain.height_at(x, y) else { continue };
            if let Some(local) = column.local_if_inside(&Vector3::new(x, y, z)) {
                truth.samples += 1;
                let row = Vector3::new(x - patch.center.x, y - patch.center.y, 1.0);
                normal_matrix += row * row.transpose();
                rhs += row * z;
                let distance = column.distance_local(&local);
                truth.max_offset = truth.max_offset.max(distance);
                if distance > 0.02 {
                    if local.z < 0.0 {
                        truth.below += 1;
                    } else {
                        truth.above += 1;
                    }
                }
            }
        }
    }
    let steep = |n: Vector3<f64>| n.z.abs() < 45f64.to_radians().cos();
    truth.steep_centre = terrain.normal_at(patch.center.x, patch.center.y).is_some_and(steep);
    truth.wall = normal_matrix
        .try_inverse()
        .map(|inverse| inverse * rhs)
        .is_some_and(|plane| steep(Vector3::new(-plane.x, -plane.y, 1.0).normalize()));
    truth
}

/// Pixels of the full-resolution depth image whose points lie in the foot disc's column of `patch`
/// (world frame), and of them more than 2 cm off its surface.
fn depth_in_column(
    patch: &Patch,
    depth: &patchwalk_fusion::camera::DepthImage,
    intrinsics: &patchwalk_fusion::camera::Intrinsics,
    world_from_camera: &nalgebra::Isometry3<f64>,
) -> (usize, usize, Option<DiscView>) {
    let column = FootColumn::new(patch, Some(&Vector3::z()), ValidateConfig::default().edge_column_height_m);
    let in_camera = transform_patch(patch, &world_from_camera.inverse());
    let mut view = in_camera.as_ref().map(|p| DiscView::new(p, 0.02));
    let (mut inside, mut off) = (0, 0);
    for v in 0..depth.height {
        for u in 0..depth.width {
            let z = f64::from(depth.depth_m[v * depth.width + u]);
            let ray = Vector3::new((u as f64 - intrinsics.cx) / intrinsics.fx, (v as f64 - intrinsics.cy) / intrinsics.fy, 1.0);
            if let Some(view) = view.as_mut() {
                view.add(&Vector3::zeros(), &ray, Some(z));
            }
            if !z.is_finite() {
                continue;
            }
            let q = world_from_camera * nalgebra::Point3::from(ray * z);
            if let Some(local) = column.local_if_inside(&q.coords) {
                inside += 1;
                off += usize::from(column.distance_local(&local) > 0.02);
            }
        }
    }
    (inside, off, view)
}

#[derive(Default)]
struct Tally {
    fitted: usize,
    valid: usize,
    residual_sum: f64,
    across: usize,
    walls: usize,
    steep_centres: usize,
    verdicts: std::collections::BTreeMap<&'static str, usize>,
}

impl Tally {
    fn line(&self, name: &str) -> String {
        let pct = |a: usize, b: usize| if b == 0 { 0.0 } else { 100.0 * a as f64 / b as f64 };
        format!(
            "{name:<22} fitted {:>5}  valid {:>5} ({:>5.1} %)  mean residual {:>5.2} mm  valid across an edge {:>4} ({:>5.1} %)  walls accepted {:>3} (steep cell under the centre {:>3})  dropped {:?}",
            self.fitted,
            self.valid,
            pct(self.valid, self.fitted),
            if self.valid == 0 { 0.0 } else { 1e3 * self.residual_sum / self.valid as f64 },
            self.across,
            pct(self.across, self.valid),
            self.walls,
            self.steep_centres,
            self.verdicts
        )
    }
}

fn main() -> Result<()> {
    let args: Vec<String> = std::env::args().skip(1).collect();
    let flag = |name: &str| args.iter().position(|a| a == name).and_then(|i| args.get(i + 1)).cloned();
    // --detail: one line per valid patch across an edge or on a wall.
    let detail = args.iter().any(|a| a == "--detail");
    let frames: usize = flag("--frames").map(|s| s.parse()).transpose().context("--frames N")?.unwrap_or(12);
    let seeds: Vec<u64> =
        flag("--seeds").unwrap_or_else(|| "11,12".into()).split(',').map(|s| s.parse()).collect::<Result<_, _>>().context("--seeds a,b")?;
    let data = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("../../../tests/data/heightmaps");
    // (name, file, height range at 1 cm/px: the README's 0.04 m/px course scaled by 1/4)
    let scenes = [("terrain.png", data.join("terrain.png"), 0.25), ("real_stairs_125cm.png", data.join("real_stairs_125cm.png"), 0.3125)];
    let mut j33 = MapperConfig { time_limit_ms: f64::INFINITY, coverage_fraction: f64::INFINITY, ..MapperConfig::default() };
    j33.saliency.fixation_radius_m = f64::INFINITY;
    j33.volume_edge_m = 2.56;
    let mut footholds = j33.clone();
    j33.validate.tilt_max_deg = f64::INFINITY;
    j33.validate.edge_max_offset_m = f64::INFINITY;
    j33.validate.unseen_max_fraction = f64::INFINITY;
    j33.validate.out_of_view_max_fraction = f64::INFINITY;
    footholds.validate = ValidateConfig::default();
    footholds.validate.unseen_max_fraction = SUGGESTED_UNSEEN_MAX_FRACTION;
    // --edge-quantile Q, --unseen-max F: the edge and visibility tests' thresholds (default ValidateConfig's).
    if let Some(q) = flag("--edge-quantile") {
        footholds.validate.edge_quantile = q.parse().context("--edge-quantile Q")?;
    }
    if let Some(f) = flag("--unseen-max") {
        footholds.validate.unseen_max_fraction = f.parse().context("--unseen-max F")?;
    }
    // --out-of-view-max F: the out-of-view test's threshold (inf switches it off).
    if let Some(f) = flag("--out-of-view-max") {
        footholds.validate.out_of_view_max_fraction = f.parse().context("--out-of-view-max F")?;
    }
    // --open-rim-max F: the open-rim test's threshold (0.01 unless given).
    footholds.validate.open_rim_max_fraction = SUGGESTED_OPEN_RIM_MAX_FRACTION;
    if let Some(f) = flag("--open-rim-max") {
        footholds.validate.open_rim_max_fraction = f.parse().context("--open-rim-max F")?;
    }
    let mut open_rim = footholds.clone();
    open_rim.validate.unseen_max_fraction = f64::INFINITY;
    let mut tilt_edge = open_rim.clone();
    tilt_edge.validate.open_rim_max_fraction = f64::INFINITY;
    let configs = [
        ("J 3.3 tests only", &j33),
        ("+ tilt, edge", &tilt_edge),
        ("+ tilt, edge, open rim", &open_rim),
        ("+ tilt, edge, open rim, unseen", &footholds),
    ];
    println!("bench_footholds: {frames} frames per path, seeds {seeds:?}, {} threads", rayon::current_num_threads());
    for (name, path, height_max) in &scenes {
        let mut tallies: [Tally; 4] = Default::default();
        for &seed in &seeds {
            let mut config = SimConfig { seed, ..SimConfig::default() };
            config.scene.terrain.path = path.clone();
            config.scene.terrain.metres_per_pixel = 0.01;
            config.scene.terrain.height_min_m = 0.0;
            config.scene.terrain.height_max_m = *height_max;
            let probe = Simulator::new(config.clone()).with_context(|| format!("loading {}", path.display()))?;
            let terrain = probe.scene.terrain.clone().context("no terrain")?;
            let [[x0, y0], [x1, y1]] = terrain.extent_m();
            // A path per seed: a start inside the terrain and a heading, from the seed.
            let mut rng = <rand::rngs::StdRng as rand::SeedableRng>::seed_from_u64(seed);
            let fx = rand::Rng::random_range(&mut rng, 0.15..0.6);
            let fy = rand::Rng::random_range(&mut rng, 0.2..0.8);
            config.path.start_m = Some([x0 + fx * (x1 - x0), y0 + fy * (y1 - y0)]);
            config.path.heading_deg = rand::Rng::random_range(&mut rng, -30.0..30.0);
            config.path.step_per_frame_m = 0.05;
            let sim = Simulator::new(config)?;
            for frame in 0..frames as u64 {
                let rendered = sim.depth_frame(frame);
                let gravity = Unit::new_normalize(rendered.world_from_camera.inverse().rotation * -Vector3::z());
                for (row, (tally, (config_name, mapper_config))) in tallies.iter_mut().zip(configs).enumerate() {
                    let volume_from_camera = single_frame_volume_from_camera(&gravity, mapper_config.volume_edge_m);
                    let mut mapper = Mapper::new(mapper_config.clone(), "camera_optical", default_volume_from_map())?;
                    let result = mapper.process(&FrameInput {
                        depth: &rendered.depth,
                        intrinsics: &sim.camera.intrinsics,
                        volume_from_camera,
                        timestamp: rendered.timestamp,
                    })?;
                    let s = result.summary();
                    tally.fitted += s.fitted;
                    for outcome in &result.outcomes {
                        let Some(patch) = &outcome.patch_in_camera else { continue };
                        if !outcome.verdict.is_valid() {
                            if !matches!(outcome.verdict, Verdict::TooFewPoints | Verdict::FitFailed(_) | Verdict::Skipped) {
                                *tally.verdicts.entry(outcome.verdict.name()).or_default() += 1;
                            }
                            continue;
                        }
                        let Some(world) = transform_patch(patch, &rendered.world_from_camera) else { continue };
                        let truth = ground_truth(&world, &terrain);
                        tally.valid += 1;
                        tally.residual_sum += patch.residual;
                        tally.across += usize::from(truth.across());
                        tally.walls += usize::from(truth.wall);
                        tally.steep_centres += usize::from(truth.steep_centre);
                        // The disc's view from the full-resolution depth (without the hole search) and the
                        // open-rim share the mapper measured, on the open-rim row; the verdicts on the others.
                        if detail && row > 0 {
                            let (seen, seen_off, view) =
                                depth_in_column(&world, &rendered.depth, &sim.camera.intrinsics, &rendered.world_from_camera);
                            let view_text = view.map_or("no view".to_string(), |v| {
                                format!(
                                    "disc pixels {} through {} ({:.2} %) occluded {} missing {}",
                                    v.pixels,
                                    v.through,
                                    100.0 * v.through_fraction(),
                                    v.occluded,
                                    v.missing
                                )
                            });
                            if row == 2 {
                                let unseen = view.map_or(f64::NAN, |v| 100.0 * v.unseen_fraction());
                                let open = outcome.validation.as_ref().and_then(|v| v.open_rim).map_or(f64::NAN, |t| 100.0 * t.value);
                                println!("    view: across {} unseen {unseen:.2} % open {open:.2} % ({view_text})", truth.across());
                                continue;
                            }
                            if !(truth.across() || truth.wall || truth.steep_centre) {
                                continue;
                            }
                            let edge = outcome.validation.as_ref().and_then(|v| v.edge.as_ref()).map_or(f64::NAN, |t| t.value);
                            println!(
                                "    seed {seed} frame {frame} {}: {:?}/{:?} r {:.3} m at {:.2} m, {} of {} terrain samples > 2 cm off ({} below, {} above), max {:.1} mm{}; depth pixels in the column {seen}, > 2 cm off {seen_off}; edge test {:.1} mm",
                                config_name,
                                patch.surface,
                                patch.boundary,
                                patch.boundary_half_extents().max(),
                                patch.center.norm(),
                                truth.below + truth.above,
                                truth.samples,
                                truth.below,
                                truth.above,
                                1e3 * truth.max_offset,
                                match (truth.wall, truth.steep_centre) {
                                    (true, _) => ", wall",
                                    (false, true) => ", steep cell under the centre",
                                    _ => "",
                                },
                                1e3 * edge
                            );
                        }
                    }
                }
            }
        }
        println!("{name}:");
        for (tally, (config_name, _)) in tallies.iter().zip(configs) {
            println!("  {}", tally.line(config_name));
        }
    }
    Ok(())
}

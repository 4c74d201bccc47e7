//! `patch_mapper footholds plan`: a coarse route over footholds (CNN IV, [`patchwalk_route`]) for
//! one depth frame of a dataset. The holds come from a JSON file (any source: CNN predictions, …)
//! or from the patch pipeline's valid patches — of the frame alone (`map`'s single-frame mapper) or
//! of a fused sequence ending at the frame (`--fuse N`, the node's pipeline: TSDF + ICP +
//! birds-eye mapping). The terrain is the frame's depth on CNN's 60 × 80 grid.
//!
//! Everything is expressed in the frame's **heading frame**: origin at the camera, z up (against
//! gravity), x the viewing direction made horizontal, y to the left (REP-103 axes). `--goal 1.0,0`
//! is one metre straight ahead of the camera, on whatever height the terrain has there.
//!
//! Writes `route.json` (the stances with left/right sole positions, Flex and cost, the body path,
//! the clustered holds, timings), `holds.json` (the input holds, in the `--holds` format) and
//! `route.png` (the depth image with the holds, the body path and the stances).

use std::path::PathBuf;
use std::time::Instant;

use anyhow::{bail, Context, Result};
use nalgebra::{Isometry3, Matrix3, Point3, Rotation3, Translation3, Unit, UnitQuaternion, Vector2, Vector3};
use patchwalk_fusion::camera::{DepthImage, Intrinsics};
use patchwalk_fusion::dataset::Dataset;
use patchwalk_mapping::acquire::{gravity_from_accelerometer, gravity_from_dominant_plane, gravity_from_vector, organized_cloud};
use patchwalk_mapping::mapper::{default_volume_from_map, single_frame_volume_from_camera, FrameInput, Mapper, MapperConfig};
use patchwalk_mapping::pipeline::Pipeline;
use patchwalk_mapping::render::Rgb;
use patchwalk_route::grid::{CNN_COLS, CNN_ROWS};
use patchwalk_route::{Hold, Pinhole, Planner, PlannerConfig, Route, RouteError, Target, TerrainGrid};
use serde::Serialize;

/// Arguments of `patch_mapper footholds plan`.
#[derive(clap::Args, Debug)]
pub struct PlanArgs {
    /// TUM directory (depth.txt [+ accelerometer.txt]), directory of depth PNGs with an intrinsics
    /// JSON, or one depth PNG.
    pub dataset: PathBuf,
    /// Goal `x,y[,z]` in the heading frame (m): x ahead, y left, z up from the camera. Without z the
    /// nearest terrain point is found in the horizontal plane.
    #[arg(long, value_parser = parse_target, allow_hyphen_values = true)]
    pub goal: Target,
    /// Start `x,y[,z]` (default: the body position with a stance nearest the bottom centre of the
    /// image, as CNN IV starts).
    #[arg(long, value_parser = parse_target, allow_hyphen_values = true)]
    pub start: Option<Target>,
    /// Output directory for route.json, holds.json and route.png.
    #[arg(long, default_value = "plan_out")]
    pub out: PathBuf,
    /// The frame to plan on (index into the dataset; default the last one).
    #[arg(long)]
    pub frame: Option<usize>,
    /// Holds from the node's patch pipeline fused over this many frames ending at --frame (1: the
    /// frame's own patches from the single-frame mapper of `map`).
    #[arg(long, default_value_t = 10)]
    pub fuse: usize,
    /// Keep the mapper's DtFP region of interest (the seeds around the fixation point in front of
    /// the feet, J 3.1); by default the whole view is seeded, as a route needs holds all over it.
    #[arg(long)]
    pub dtfp: bool,
    /// Holds from a JSON file instead of the patch pipeline: `[{"position": [x, y, z], "score": s}]`
    /// in the heading frame.
    #[arg(long)]
    pub holds: Option<PathBuf>,
    /// Patch holds steeper than this (normal from vertical, degrees) are not footholds.
    #[arg(long, default_value_t = 30.0)]
    pub max_slope_deg: f64,
    /// YAML configuring the patch pipeline (`mapper:`, and for --fuse `pipeline:`/`tracker:`), as in
    /// config/patch_mapper.yaml.
    #[arg(long)]
    pub config: Option<PathBuf>,
    /// YAML of planner parameters (clusters, seed, min_score, height_samples, yaw_samples,
    /// thinning_m, keep_flex_ratio, snap_m, max_edge_m); missing keys take the defaults.
    #[arg(long)]
    pub planner: Option<PathBuf>,
    /// Gravity (down) in the camera frame, e.g. `0,0.79,0.62`; else the IMU (through
    /// mapper.acquire.camera_from_imu) when configured, else the dominant plane.
    #[arg(long, value_parser = super::parse_vec3, allow_hyphen_values = true)]
    pub gravity: Option<Vector3<f64>>,
    /// k of k-means over the holds (CNN IV: 30).
    #[arg(long)]
    pub clusters: Option<usize>,
}

/// A `x,y` or `x,y,z` target of finite numbers.
fn parse_target(s: &str) -> Result<Target, String> {
    let values: Result<Vec<f64>, _> = s.split(',').map(|p| p.trim().parse::<f64>()).collect();
    match values.as_deref() {
        Ok([x, y]) if x.is_finite() && y.is_finite() => Ok(Target { x: *x, y: *y, z: None }),
        Ok([x, y, z]) if [x, y, z].iter().all(|v| v.is_finite()) => Ok(Target { x: *x, y: *y, z: Some(*z) }),
        _ => Err(format!("expected x,y or x,y,z of finite numbers, got '{s}'")),
    }
}

/// route.json.
#[derive(Serialize)]
struct RouteFile<'a> {
    dataset: String,
    frame: usize,
    timestamp: f64,
    /// How the fixed frame is defined.
    frame_id: &'static str,
    /// Where the holds came from.
    holds_source: String,
    /// Gravity (down) in the camera frame.
    gravity_in_camera: [f64; 3],
    /// `heading_from_camera` as a row-major 4 × 4 matrix.
    heading_from_camera: [[f64; 4]; 4],
    planner: &'a PlannerConfig,
    #[serde(flatten)]
    route: &'a Route,
}

const FRAME_ID: &str = "heading: origin at the camera, z up, x the viewing direction made horizontal, y left";

pub fn run(args: PlanArgs) -> Result<()> {
    if args.fuse == 0 {
        bail!("--fuse must be at least 1");
    }
    if !(args.max_slope_deg.is_finite() && args.max_slope_deg > 0.0) {
        bail!("--max-slope-deg must be a positive angle, got {}", args.max_slope_deg);
    }
    let mut planner_config: PlannerConfig = match &args.planner {
        Some(path) => patchwalk_ros::params::load_config(Some(path), &[])
            .with_context(|| format!("{}: invalid planner parameters", path.display()))?,
        None => PlannerConfig::default(),
    };
    if let Some(k) = args.clusters {
        planner_config.clusters = k;
    }
    let planner = Planner::new(patchwalk_route::BipedModel::rpbp()?, planner_config)?;
    let dataset = Dataset::open(&args.dataset).with_context(|| format!("opening {}", args.dataset.display()))?;
    if dataset.frames.is_empty() {
        bail!("{}: no frames", args.dataset.display());
    }
    let frame = args.frame.unwrap_or(dataset.frames.len() - 1);
    if frame >= dataset.frames.len() {
        bail!("--frame {frame} is past the dataset's {} frames", dataset.frames.len());
    }
    let mut mapper_config = match &args.config {
        Some(path) => super::map::load_config(path)?,
        None => MapperConfig::default(),
    };
    if !args.dtfp {
        mapper_config.saliency.fixation_radius_m = f64::INFINITY;
    }
    // Offline: no per-frame time limit, so the holds do not depend on the host's load.
    mapper_config.time_limit_ms = f64::INFINITY;
    let depth = dataset.load_depth(frame)?;
    let t_holds = Instant::now();
    let view = if args.fuse == 1 || args.holds.is_some() {
        single_frame_view(&args, frame, &dataset, &depth, &mapper_config)?
    } else {
        fused_view(&args, frame, &dataset)?
    };
    let holds_ms = t_holds.elapsed().as_secs_f64() * 1e3;
    let (holds, holds_source) = match &args.holds {
        Some(path) => {
            let text = std::fs::read_to_string(path).with_context(|| format!("reading {}", path.display()))?;
            let holds: Vec<Hold> = serde_json::from_str(&text).with_context(|| format!("{}: not a list of holds", path.display()))?;
            (holds, format!("file {}", path.display()))
        }
        None => (view.patch_holds.clone(), view.source.clone()),
    };
    std::fs::create_dir_all(&args.out).with_context(|| format!("creating {}", args.out.display()))?;
    std::fs::write(args.out.join("holds.json"), serde_json::to_string_pretty(&holds)?)?;

    let k = &dataset.intrinsics;
    let pinhole = Pinhole { fx: k.fx, fy: k.fy, cx: k.cx, cy: k.cy };
    let grid = TerrainGrid::from_depth(depth.width, depth.height, &depth.depth_m, &pinhole, &view.heading_from_camera, CNN_ROWS, CNN_COLS)?;
    let t_plan = Instant::now();
    let planned = planner.plan(&grid, &holds, args.start, args.goal);
    let plan_ms = t_plan.elapsed().as_secs_f64() * 1e3;

    let picture = render(&depth, k, &view.heading_from_camera, &holds, planned.as_ref().ok(), &grid);
    let png = args.out.join("route.png");
    picture.save_png(&png)?;
    println!(
        "footholds plan: {} frame {} — {} holds ({}), {} terrain vertices; holds {holds_ms:.0} ms",
        args.dataset.display(),
        frame,
        holds.len(),
        holds_source,
        grid.valid()
    );
    let route = match planned {
        Ok(route) => route,
        Err(err) => {
            println!("picture (holds only): {}", png.display());
            return Err(plan_error(err, plan_ms));
        }
    };
    let gravity = view.gravity_in_camera;
    let json = RouteFile {
        dataset: args.dataset.display().to_string(),
        frame,
        timestamp: dataset.frames[frame].timestamp,
        frame_id: FRAME_ID,
        holds_source,
        gravity_in_camera: [gravity.x, gravity.y, gravity.z],
        heading_from_camera: matrix_rows(&view.heading_from_camera),
        planner: &planner.config,
        route: &route,
    };
    let json_path = args.out.join("route.json");
    std::fs::write(&json_path, serde_json::to_string_pretty(&json)?).with_context(|| format!("writing {}", json_path.display()))?;
    let s = &route.stats;
    println!(
        "route: {} stances over {:.2} m of body path ({} vertices), cost {:.3}; {} clusters, {} of {} vertices with a stance",
        route.stances.len(),
        route.length_m,
        route.body_path.len(),
        route.cost,
        s.clusters,
        s.vertices_with_stance,
        s.vertices
    );
    println!(
        "plan time {plan_ms:.0} ms (k-means {:.1}, stances {:.0}, search {:.1}); wrote {} and {}",
        s.cluster_ms,
        s.stance_ms,
        s.search_ms,
        json_path.display(),
        png.display()
    );
    Ok(())
}

fn plan_error(err: RouteError, plan_ms: f64) -> anyhow::Error {
    anyhow::anyhow!("planning failed after {plan_ms:.0} ms: {err}")
}

/// The frame's geometry and its patch holds in the heading frame.
struct View {
    heading_from_camera: Isometry3<f64>,
    gravity_in_camera: Unit<Vector3<f64>>,
    patch_holds: Vec<Hold>,
    source: String,
}

/// heading_from_camera for gravity (down) in the camera frame: rows forward, left, up.
pub fn heading_from_camera(gravity_in_camera: &Unit<Vector3<f64>>) -> Result<Isometry3<f64>> {
    let up = -gravity_in_camera.into_inner();
    let view = Vector3::z();
    let forward = view - up * view.dot(&up);
    if forward.norm() < 1e-6 {
        bail!("the camera looks straight down or up: no viewing direction to make horizontal");
    }
    let forward = forward.normalize();
    let left = up.cross(&forward);
    let rows = Matrix3::from_rows(&[forward.transpose(), left.transpose(), up.transpose()]);
    let rotation = UnitQuaternion::from_rotation_matrix(&Rotation3::from_matrix_unchecked(rows));
    Ok(Isometry3::from_parts(Translation3::identity(), rotation))
}

/// A validated patch as a hold when it is no steeper than the limit (normal `n` against `up`).
fn patch_hold(center: &Vector3<f64>, normal: &Vector3<f64>, up: &Vector3<f64>, max_slope_deg: f64) -> Option<Hold> {
    let cos = normal.normalize().dot(up).abs();
    (cos >= max_slope_deg.to_radians().cos()).then(|| Hold::new(*center, 1.0))
}

fn single_frame_view(args: &PlanArgs, frame: usize, dataset: &Dataset, depth: &DepthImage, config: &MapperConfig) -> Result<View> {
    let gravity = frame_gravity(args, frame, dataset, depth, config)?;
    let heading_from_camera = heading_from_camera(&gravity)?;
    if args.holds.is_some() {
        return Ok(View { heading_from_camera, gravity_in_camera: gravity, patch_holds: Vec::new(), source: String::new() });
    }
    let mut mapper = Mapper::new(config.clone(), "camera_optical", default_volume_from_map())?;
    let result = mapper.process(&FrameInput {
        depth,
        intrinsics: &dataset.intrinsics,
        volume_from_camera: single_frame_volume_from_camera(&gravity, config.volume_edge_m),
        timestamp: dataset.frames[frame].timestamp,
    })?;
    let up = Vector3::z();
    let patch_holds: Vec<Hold> = result
        .outcomes
        .iter()
        .filter(|o| o.verdict.is_valid())
        .filter_map(|o| o.patch_in_camera.as_ref())
        .filter_map(|p| {
            let center = heading_from_camera * Point3::from(p.center);
            let normal = heading_from_camera.rotation * p.normal();
            patch_hold(&center.coords, &normal, &up, args.max_slope_deg)
        })
        .collect();
    let valid = result.outcomes.iter().filter(|o| o.verdict.is_valid()).count();
    let source = format!("{valid} valid patches of the frame, {} no steeper than {}°", patch_holds.len(), args.max_slope_deg);
    Ok(View { heading_from_camera, gravity_in_camera: gravity, patch_holds, source })
}

fn fused_view(args: &PlanArgs, frame: usize, dataset: &Dataset) -> Result<View> {
    let mut config: crate::ros::PatchMapperConfig = patchwalk_ros::params::load_config(args.config.as_deref(), &[])?;
    if !args.dtfp {
        config.mapper.saliency.fixation_radius_m = f64::INFINITY;
    }
    config.mapper.time_limit_ms = f64::INFINITY;
    let mut pipeline = Pipeline::new(config.pipeline.clone(), config.tracker.clone(), config.mapper.clone(), dataset.intrinsics)?;
    let first = (frame + 1).saturating_sub(args.fuse);
    let half_window = config.mapper.acquire.accel_half_window_s;
    let mut next_imu = 0;
    let mut last = None;
    for index in first..=frame {
        let timestamp = dataset.frames[index].timestamp;
        while let Some(sample) = dataset.accelerometer.get(next_imu).filter(|s| s.timestamp <= timestamp + half_window) {
            if sample.timestamp >= dataset.frames[first].timestamp - 1.0 {
                pipeline.push_imu(sample.timestamp, sample.acceleration_in_imu)?;
            }
            next_imu += 1;
        }
        let depth = dataset.load_depth(index)?;
        match pipeline.process(&depth, timestamp) {
            Ok(output) => last = Some(output.map_from_camera),
            Err(err) => eprintln!("frame {index} skipped: {err}"),
        }
    }
    let Some(map_from_camera) = last else { bail!("no frame of {first}..={frame} could be fused") };
    let gravity = Unit::new_normalize(map_from_camera.inverse_transform_vector(&-Vector3::z()));
    let heading_from_camera = heading_from_camera(&gravity)?;
    let heading_from_map = heading_from_camera * map_from_camera.inverse();
    let up = Vector3::z();
    let map = pipeline.map();
    let patch_holds: Vec<Hold> = map
        .patches()
        .iter()
        .filter_map(|m| {
            let center = heading_from_map * Point3::from(m.patch.center);
            let normal = heading_from_map.rotation * m.patch.normal();
            patch_hold(&center.coords, &normal, &up, args.max_slope_deg)
        })
        .collect();
    let source = format!(
        "patch map fused over frames {first}..={frame} ({} patches, {} no steeper than {}°)",
        map.len(),
        patch_holds.len(),
        args.max_slope_deg
    );
    Ok(View { heading_from_camera, gravity_in_camera: gravity, patch_holds, source })
}

fn frame_gravity(
    args: &PlanArgs,
    frame: usize,
    dataset: &Dataset,
    depth: &DepthImage,
    config: &MapperConfig,
) -> Result<Unit<Vector3<f64>>> {
    if let Some(g) = args.gravity {
        return Ok(gravity_from_vector(g)?);
    }
    let camera_from_imu = config.acquire.camera_from_imu()?;
    if camera_from_imu.matrix() != &Matrix3::identity() && !dataset.accelerometer.is_empty() {
        let timestamp = dataset.frames[frame].timestamp;
        let acceleration = dataset
            .acceleration_near(timestamp, config.acquire.accel_half_window_s)
            .with_context(|| format!("no accelerometer samples near frame {frame} (t = {timestamp:.3})"))?;
        return Ok(gravity_from_accelerometer(&acceleration, &camera_from_imu)?);
    }
    let cloud = organized_cloud(depth, &dataset.intrinsics)?;
    gravity_from_dominant_plane(&cloud, 0.02, frame as u64).with_context(|| format!("frame {frame}: no gravity (try --gravity x,y,z)"))
}

fn matrix_rows(iso: &Isometry3<f64>) -> [[f64; 4]; 4] {
    let m = iso.to_homogeneous();
    std::array::from_fn(|r| std::array::from_fn(|c| m[(r, c)]))
}

const RAW_HOLD: [u8; 3] = [250, 200, 0];
const CLUSTER: [u8; 3] = [255, 120, 0];
const PATH: [u8; 3] = [40, 140, 255];
const LEFT: [u8; 3] = [30, 220, 60];
const RIGHT: [u8; 3] = [230, 30, 30];

/// The depth image (grey) with the input holds (small yellow squares), the clustered holds (orange
/// outlines), the body path (blue) and the stances (left sole green, right sole red, joined).
fn render(
    depth: &DepthImage,
    k: &Intrinsics,
    heading_from_camera: &Isometry3<f64>,
    holds: &[Hold],
    route: Option<&Route>,
    grid: &TerrainGrid,
) -> Rgb {
    let mut picture = Rgb::from_depth(depth);
    let pinhole = Pinhole { fx: k.fx, fy: k.fy, cx: k.cx, cy: k.cy };
    let camera_from_heading = heading_from_camera.inverse();
    let pixel =
        |p: &[f64; 3]| pinhole.project(&(camera_from_heading * Point3::new(p[0], p[1], p[2])).coords).map(|(u, v)| Vector2::new(u, v));
    let square =
        |c: Vector2<f64>, r: f64| vec![c + Vector2::new(-r, -r), c + Vector2::new(r, -r), c + Vector2::new(r, r), c + Vector2::new(-r, r)];
    for hold in holds.iter().filter(|h| h.position.iter().all(|v| v.is_finite())) {
        if let Some(c) = pixel(&hold.position) {
            picture.fill_polygon(&square(c, 1.5), RAW_HOLD, 0.8);
        }
    }
    let Some(route) = route else { return picture };
    for hold in &route.holds {
        if let Some(c) = pixel(&hold.position) {
            picture.outline(&square(c, 6.0), CLUSTER);
        }
    }
    let path: Vec<Vector2<f64>> = route
        .body_vertices
        .iter()
        .map(|[r, c]| {
            let (u, v) = grid.pixels[r * grid.cols + c];
            Vector2::new(u, v)
        })
        .collect();
    for pair in path.windows(2) {
        for offset in [Vector2::zeros(), Vector2::new(1.0, 0.0), Vector2::new(0.0, 1.0)] {
            // An open polyline segment drawn as a degenerate closed one, 2 px wide.
            picture.outline(&[pair[0] + offset, pair[1] + offset], PATH);
        }
    }
    for stance in &route.stances {
        if let (Some(l), Some(r)) = (pixel(&stance.left), pixel(&stance.right)) {
            picture.outline(&[l, r], [255, 255, 255]);
            picture.fill_polygon(&square(l, 4.0), LEFT, 1.0);
            picture.fill_polygon(&square(r, 4.0), RIGHT, 1.0);
        }
    }
    picture
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn targets_parse_and_bad_ones_are_rejected() {
        assert_eq!(parse_target("1.0,-0.2").unwrap(), Target { x: 1.0, y: -0.2, z: None });
        assert_eq!(parse_target("1,2,3").unwrap(), Target { x: 1.0, y: 2.0, z: Some(3.0) });
        for bad in ["1", "1,2,3,4", "a,b", "NaN,1", "1,inf"] {
            assert!(parse_target(bad).is_err(), "{bad}");
        }
    }

    #[test]
    fn the_heading_frame_is_level_and_looks_ahead() {
        // Camera pitched 49° down: gravity in the optical frame (y down, z forward).
        let pitch = 0.85f64;
        let gravity = Unit::new_normalize(Vector3::new(0.0, pitch.cos(), pitch.sin()));
        let h = heading_from_camera(&gravity).unwrap();
        // Gravity maps to −z, the optical axis to forward and down, image right (optical x) to −y.
        assert!((h.rotation * gravity.into_inner() - Vector3::new(0.0, 0.0, -1.0)).norm() < 1e-12);
        let view = h.rotation * Vector3::z();
        assert!(view.y.abs() < 1e-12 && view.x > 0.0 && view.z < 0.0, "{view:?}");
        assert!((h.rotation * Vector3::x() - Vector3::new(0.0, -1.0, 0.0)).norm() < 1e-12);
        let straight_down = Unit::new_normalize(Vector3::z());
        assert!(heading_from_camera(&straight_down).is_err());
    }

    #[test]
    fn steep_patches_are_not_holds() {
        let up = Vector3::z();
        assert!(patch_hold(&Vector3::zeros(), &Vector3::new(0.0, 0.3, 1.0), &up, 30.0).is_some());
        assert!(patch_hold(&Vector3::zeros(), &Vector3::new(0.0, 1.0, 1.0), &up, 30.0).is_none());
        // A normal pointing down (the fit's sign) counts as its flip.
        assert!(patch_hold(&Vector3::zeros(), &Vector3::new(0.0, 0.0, -1.0), &up, 30.0).is_some());
    }
}

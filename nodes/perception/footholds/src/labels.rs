//! Labels without a human (in place of CNN III-C's painted footholds): the patch pipeline, fused
//! over a whole sequence at full quality, says where the footholds are.
//!
//! 1. [`fuse_sequence`] runs [`patchwalk_mapping::pipeline::Pipeline`] (TSDF fusion + ICP, birds-eye
//!    raycast, hiking saliency, seeds, SPL fit, validation) over every frame, with the seeds spread
//!    over the whole volume instead of the node's small fixation ball and a generous time limit
//!    ([`labelling_mapper_config`]). The footholds are the final map's patches that are valid (the
//!    validator kept them), foot-sized (the boundary's smaller half-extent at least
//!    [`LabelConfig::min_half_extent_m`]) and walkable (normal within [`LabelConfig::max_slope_deg`] of
//!    up, in the gravity-aligned map frame). The moving volume adapts to the recording as
//!    `patch_mapper replay` does ([`labelling_configs`]): when more than half of the first frame's
//!    valid depth lies outside the configured cube, the cube is fitted to the first frames' depth
//!    (e.g. a desk 1–2 m in front of a hand-held camera), with the seed cells kept at 4 cm.
//!    The places the pipeline tried and found no foothold are kept too: the seed points whose fit the
//!    validation rejected for the terrain's shape (residual, curvature, tilt, edge; not coverage or
//!    too few points, which say the data there was incomplete, e.g. at the birds-eye view's border)
//!    and the map's patches that are not footholds (too steep or too small).
//! 2. [`label_frame`] projects them into each single frame. A point counts in a frame when it is
//!    visible there (the frame's depth at its pixel agrees with its depth within
//!    [`LabelConfig::visibility_tolerance_m`]). A region is positive when a visible foothold centre
//!    lies in its central 80 % (CNN III-C ignores holds at the border); negative when none does but a
//!    visible tried-and-rejected point does; unknown (left out of training and scoring) when the pipeline
//!    tried nothing there (e.g. flat ground without salient points: no evidence either way), when
//!    the sequence's map holds no foothold at all (on the simulated scenes a failed labelling run —
//!    the map's patches all too small or steep — rather than a scene without any walkable place), or when
//!    part of the region's central 80 % lies outside the area the map covered (the final volume's
//!    footprint) or outside the volume's height range.
//! 3. A positive region's (x, y) is where the walkable area lies in it, as CNN III-C's (x, y) is the
//!    position of a painted foothold area. The footholds come from seeds placed one per
//!    [`SEED_CELL_M`] cell, so each stands for about a cell of walkable ground: each visible foothold
//!    is painted as the disc of radius [`LabelConfig::paint_radius_m`] (half a seed cell) on the
//!    surface around its centre, a disc of `f · r / depth` pixels in the image ([`Disc`]); (x, y) is
//!    the centroid of the painted part of the region's central 80 %, counted on a [`PAINT_SAMPLES`]²
//!    grid of points there ([`painted_centroid`]). On flat ground painted throughout that is the
//!    region centre, whichever seed landed nearest it; next to a step edge it lies inside the
//!    walkable part.

use nalgebra::{Isometry3, Point3, UnitQuaternion, Vector3};
use patchwalk_fusion::camera::{DepthImage, Intrinsics};
use patchwalk_fusion::dataset::Dataset;
use patchwalk_fusion::tracking::TrackerConfig;
use patchwalk_fusion::volume::{depth_points, initial_volume_from_camera, share_inside, size_volume_to_depth, VolumeSizing};
use patchwalk_mapping::acquire::gravity_from_accelerometer;
use patchwalk_mapping::mapper::{MapperConfig, Verdict};
use patchwalk_mapping::patch_map::VolumeGrid;
use patchwalk_mapping::pipeline::{default_mapper_config, Pipeline, PipelineConfig};
use patchwalk_spl::patch::{BoundaryType, Patch};

use crate::error::FootholdError;
use crate::regions::{propose, Region, RegionConfig};
use crate::tilt::Tilt;

/// What makes a patch a foothold and a region positive.
#[derive(Debug, Clone, PartialEq, serde::Serialize, serde::Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct LabelConfig {
    /// Central fraction of a region a foothold centre must lie in (CNN III-C: 80 %).
    pub centre_fraction: f64,
    /// Walkable: the patch normal within this angle of up (degrees).
    pub max_slope_deg: f64,
    /// Foot-sized: the smaller boundary half-extent at least this (m): 0.9 of the RPBP's foot radius
    /// (0.05 m), so the patch carries nearly the whole sole.
    pub min_half_extent_m: f64,
    /// A foothold is visible in a frame when the frame's depth at its pixel is within this of its depth (m).
    pub visibility_tolerance_m: f64,
    /// Regions with a point of their central part closer than this to the covered area's edge are
    /// unknown (m): the map holds no foothold centre nearer its edge than a foot radius, whose seed
    /// cell ([`SEED_CELL_M`]) is painted to within about this of the edge.
    pub coverage_margin_m: f64,
    /// Radius of the disc painted around each visible foothold centre (m, on the surface): half a
    /// seed cell ([`SEED_CELL_M`]), the area one foothold stands for. 0 paints nothing: a positive
    /// region's (x, y) is then the foothold centre nearest the region centre.
    pub paint_radius_m: f64,
}

impl Default for LabelConfig {
    fn default() -> Self {
        Self {
            centre_fraction: 0.8,
            max_slope_deg: 30.0,
            min_half_extent_m: 0.045,
            visibility_tolerance_m: 0.03,
            coverage_margin_m: 0.04,
            paint_radius_m: SEED_CELL_M / 2.0,
        }
    }
}

/// The label of one region.
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize, serde::Deserialize)]
pub enum Label {
    /// Outside the mapped area: neither trained on nor scored.
    Unknown,
    Negative,
    /// A foothold at (x, y) ∈ [0, 1]² of the region.
    Positive {
        x: f64,
        y: f64,
    },
}

impl Label {
    pub fn is_known(&self) -> bool {
        !matches!(self, Label::Unknown)
    }
}

/// The mapper of the labelling run: the node's configuration (the RPBP foot, the birds-eye input)
/// with seeds over the whole volume (no fixation ball, 4 cm cells, up to 1,024 seeds per frame), a
/// time limit that does not cut the fit short, and the foot window's plane test alone (no
/// quadric), as when the shipped weights' labels were made.
pub fn labelling_mapper_config() -> MapperConfig {
    let mut config = default_mapper_config();
    config.saliency.fixation_radius_m = f64::INFINITY;
    config.saliency.window_quadric_rms_max_m = 0.0;
    config.seeds.cells_per_side = 32;
    config.seeds.per_cell = 1;
    config.seeds.max_seeds = 1024;
    config.time_limit_ms = 5000.0;
    config.coverage_fraction = 1.0;
    config
}

/// The camera's place in the labelling run's moving volume (fractions of the edge along x, y down,
/// z forward): J's middle of the cube, where the shipped weights' labels were made (a fitted volume
/// places the camera itself).
pub const LABELLING_NOMINAL_POSITION_FRACTION: [f64; 3] = [0.5, 0.5, 0.5];
/// Birds-eye resolution of the labelling run (px): 5 mm pixels over the 1.28 m volume, the voxel
/// size, finer than the node's 200 px; the shipped weights were trained on its labels.
pub const LABELLING_BIRDS_EYE_PX: usize = 240;
/// Side of a seed cell of the labelling run (m): 32 cells over the 1.28 m volume.
pub const SEED_CELL_M: f64 = 0.04;
/// Points per side of the grid a region's central part is sampled on for the painted centroid.
pub const PAINT_SAMPLES: usize = 24;
/// Points per side of the grid on which a region's central part must lie in the covered area.
pub const COVERAGE_SAMPLES: usize = 5;
/// Frames whose depth a fitted volume is sized from (as `patch_mapper replay`).
pub const FIT_FRAMES: usize = 5;
/// Seeds per frame of the labelling run at most, whatever the volume.
pub const MAX_SEEDS: usize = 4096;

/// The tracker and mapper of a dataset's labelling run and the volume edge fitted to it, if any.
#[derive(Debug, Clone)]
pub struct LabellingConfigs {
    pub tracker: TrackerConfig,
    pub mapper: MapperConfig,
    /// The fitted cube edge (m) when the configured one missed most of the first frame's depth.
    pub fitted_edge_m: Option<f64>,
}

/// The labelling run's configurations for `dataset`: [`labelling_mapper_config`] and the node's
/// tracker, with the moving volume fitted to the first [`FIT_FRAMES`] frames' depth (95 % of the
/// valid depth per axis, 1.28–4 m, `patchwalk_fusion::volume::size_volume_to_depth`) when more than
/// half of the first frame's valid depth lies outside the configured cube; the seed grid then keeps
/// [`SEED_CELL_M`] cells and scales its seed budget with the area (at most [`MAX_SEEDS`]).
pub fn labelling_configs(dataset: &Dataset, camera_from_imu: &UnitQuaternion<f64>) -> Result<LabellingConfigs, FootholdError> {
    let mut tracker = TrackerConfig::default();
    tracker.moving_volume.nominal_position_fraction = LABELLING_NOMINAL_POSITION_FRACTION;
    tracker.birds_eye.resolution_px = LABELLING_BIRDS_EYE_PX;
    let mut mapper = labelling_mapper_config();
    let mut fitted_edge_m = None;
    let Some(first) = dataset.frames.first() else {
        return Ok(LabellingConfigs { tracker, mapper, fitted_edge_m });
    };
    let depth = dataset.load_depth(0)?;
    let rotation = camera_from_imu.to_rotation_matrix();
    let gravity = dataset
        .acceleration_near(first.timestamp, mapper.acquire.accel_half_window_s)
        .and_then(|a| gravity_from_accelerometer(&a, &rotation).ok())
        .map(nalgebra::Unit::into_inner);
    let (min_depth, max_depth) = (f64::from(tracker.tsdf.min_depth_m), f64::from(tracker.tsdf.max_depth_m));
    let mut points = depth_points(&depth, &dataset.intrinsics, min_depth, max_depth, 8);
    let edge = f64::from(tracker.tsdf.size_m);
    let outside = 1.0 - share_inside(&points, &initial_volume_from_camera(gravity, edge, &tracker.moving_volume), edge);
    if outside > 0.5 {
        for index in 1..FIT_FRAMES.min(dataset.frames.len()) {
            points.extend(depth_points(&dataset.load_depth(index)?, &dataset.intrinsics, min_depth, max_depth, 8));
        }
        let block = f64::from(tracker.tsdf.voxel_size_m) * 8.0;
        if let Some(fit) = size_volume_to_depth(&points, gravity, block, &VolumeSizing::default()) {
            tracker.tsdf.size_m = fit.edge_m as f32;
            tracker.moving_volume.nominal_position_fraction = fit.nominal_position_fraction;
            mapper.volume_edge_m = fit.edge_m;
            let cells = (fit.edge_m / SEED_CELL_M).round().max(1.0) as usize;
            let base = mapper.seeds.cells_per_side;
            mapper.seeds.max_seeds = (mapper.seeds.max_seeds * cells * cells / (base * base).max(1)).clamp(1, MAX_SEEDS);
            mapper.seeds.cells_per_side = cells;
            fitted_edge_m = Some(fit.edge_m);
        }
    }
    Ok(LabellingConfigs { tracker, mapper, fitted_edge_m })
}

/// Where the camera was and which way was down in one frame of a fused sequence.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct FramePose {
    /// Index into the dataset's frames.
    pub index: usize,
    pub timestamp: f64,
    pub map_from_camera: Isometry3<f64>,
    pub tilt: Tilt,
}

/// A fused sequence: the footholds of its final map and each frame's pose.
#[derive(Debug, Clone)]
pub struct FusedSequence {
    /// Foothold centres in the map frame (gravity aligned, z up).
    pub footholds_in_map: Vec<Vector3<f64>>,
    /// Places tried without a foothold (map frame): rejected seed points and non-foothold patches.
    pub rejected_in_map: Vec<Vector3<f64>>,
    /// All patches of the final map (valid ones), for counts.
    pub map_patches: usize,
    pub frames: Vec<FramePose>,
    /// The final volume's grid: the covered area.
    pub grid: VolumeGrid,
    /// Wall time of the pipeline per frame (ms).
    pub pipeline_ms: Vec<f64>,
    /// The fitted cube edge (m), when the volume adapted to the recording.
    pub fitted_edge_m: Option<f64>,
}

/// Whether a map patch is a foothold: foot-sized and walkable (it is in the map, so it is valid).
pub fn is_foothold(patch: &Patch, config: &LabelConfig) -> bool {
    let normal = patch.normal();
    let up = normal.z.abs() / normal.norm().max(1e-12);
    let walkable = up >= config.max_slope_deg.to_radians().cos();
    let half_extent = match patch.boundary {
        BoundaryType::Circle => patch.boundary_params.first().copied(),
        BoundaryType::Ellipse | BoundaryType::Rectangle => patch.boundary_params.iter().take(2).copied().reduce(f64::min),
        // d_1..d_4: distances of the quadrilateral's corners; the shorter diagonal half.
        BoundaryType::Quadrilateral => {
            let d = &patch.boundary_params;
            (d.len() >= 4).then(|| ((d[0] + d[2]) / 2.0).min((d[1] + d[3]) / 2.0))
        }
    };
    walkable && half_extent.is_some_and(|h| h >= config.min_half_extent_m)
}

/// Whether a seed's verdict says the surface's shape there is no foothold (not: skipped, a failed
/// fit, or too little data under the foot, which says nothing about the terrain).
pub fn is_rejection(verdict: &Verdict) -> bool {
    matches!(verdict, Verdict::Residual | Verdict::Curvature | Verdict::Tilt | Verdict::Edge)
}

/// The IMU mount of a dataset written by `terrain_sim record` (`intrinsics.json`'s
/// `camera_from_imu_xyzw`), if it has one.
pub fn dataset_camera_from_imu(dataset: &Dataset) -> Result<Option<UnitQuaternion<f64>>, FootholdError> {
    let path = dataset.root.join("intrinsics.json");
    if !path.is_file() {
        return Ok(None);
    }
    let text = std::fs::read_to_string(&path).map_err(crate::error::io_error(&path))?;
    let value: serde_json::Value =
        serde_json::from_str(&text).map_err(|e| FootholdError::Format { path: path.clone(), reason: e.to_string() })?;
    let Some(q) = value.get("camera_from_imu_xyzw").and_then(|q| q.as_array()) else {
        return Ok(None);
    };
    let q: Vec<f64> = q.iter().filter_map(serde_json::Value::as_f64).collect();
    match q.as_slice() {
        [x, y, z, w] => Ok(Some(UnitQuaternion::from_quaternion(nalgebra::Quaternion::new(*w, *x, *y, *z)))),
        _ => Err(FootholdError::Format { path, reason: "camera_from_imu_xyzw must be four numbers".into() }),
    }
}

/// A pipeline for `intrinsics` with the given tracker, mapper and IMU mount.
pub fn pipeline(
    intrinsics: Intrinsics,
    configs: &LabellingConfigs,
    camera_from_imu: &UnitQuaternion<f64>,
) -> Result<Pipeline, FootholdError> {
    let mut pipeline = Pipeline::new(
        PipelineConfig { allow_missing_imu: false, ..PipelineConfig::default() },
        configs.tracker.clone(),
        configs.mapper.clone(),
        intrinsics,
    )?;
    pipeline.set_camera_from_imu(&camera_from_imu.to_rotation_matrix());
    Ok(pipeline)
}

/// Feeds the IMU samples up to `until` (s) into the pipeline, from `next` on; returns the new `next`.
fn feed_imu(pipeline: &mut Pipeline, dataset: &Dataset, mut next: usize, until: f64) -> usize {
    while let Some(sample) = dataset.accelerometer.get(next).filter(|s| s.timestamp <= until) {
        // Out-of-order or non-finite samples are skipped, as the node does.
        let _ = pipeline.push_imu(sample.timestamp, sample.acceleration_in_imu);
        next += 1;
    }
    next
}

/// Runs the pipeline (`configs`, e.g. from [`labelling_configs`]) over the frames `frames` of `dataset`
/// (all when `None`) and returns its footholds.
pub fn fuse_sequence(
    dataset: &Dataset,
    camera_from_imu: &UnitQuaternion<f64>,
    configs: &LabellingConfigs,
    frames: Option<&[usize]>,
    label: &LabelConfig,
) -> Result<FusedSequence, FootholdError> {
    let half_window = configs.mapper.acquire.accel_half_window_s;
    let mut pipeline = pipeline(dataset.intrinsics, configs, camera_from_imu)?;
    let all: Vec<usize> = (0..dataset.frames.len()).collect();
    let frames = frames.unwrap_or(&all);
    let mut next_imu = 0;
    let mut poses = Vec::new();
    let mut pipeline_ms = Vec::new();
    let mut rejected = Vec::new();
    for &index in frames {
        let timestamp =
            dataset.frames.get(index).map(|f| f.timestamp).ok_or_else(|| FootholdError::Config(format!("frame {index} out of range")))?;
        next_imu = feed_imu(&mut pipeline, dataset, next_imu, timestamp + half_window);
        let depth = dataset.load_depth(index)?;
        // Frames the pipeline refuses (no IMU near the stamp, too little depth) are not labelled.
        let Ok(output) = pipeline.process(&depth, timestamp) else {
            continue;
        };
        pipeline_ms.push(output.timings.total_ms);
        let Some(gravity) = output.gravity_in_camera else {
            continue;
        };
        let tilt = Tilt::from_gravity_in_camera(&gravity.into_inner())?;
        if matches!(output.tracking, patchwalk_fusion::tracking::TrackingStatus::Lost(_)) {
            // The map was reset: the poses and points before do not share its frame.
            poses.clear();
            rejected.clear();
        }
        rejected.extend(
            output
                .seeds
                .iter()
                .filter(|o| is_rejection(&o.verdict))
                .map(|o| (output.map_from_birds_eye * Point3::from(o.seed.point_in_camera)).coords),
        );
        poses.push(FramePose { index, timestamp, map_from_camera: output.map_from_camera, tilt });
    }
    let map = pipeline.map();
    let footholds_in_map = map.patches().iter().filter(|m| is_foothold(&m.patch, label)).map(|m| m.patch.center).collect();
    rejected.extend(map.patches().iter().filter(|m| !is_foothold(&m.patch, label)).map(|m| m.patch.center));
    Ok(FusedSequence {
        footholds_in_map,
        rejected_in_map: rejected,
        map_patches: map.len(),
        frames: poses,
        grid: *map.grid(),
        pipeline_ms,
        fitted_edge_m: configs.fitted_edge_m,
    })
}

/// The regions of one frame with their labels and inputs.
#[derive(Debug, Clone)]
pub struct LabelledFrame {
    pub tilt: Tilt,
    pub regions: Vec<Region>,
    /// `config.input_len()` values per region.
    pub inputs: Vec<f32>,
    pub labels: Vec<Label>,
}

/// Depth of the image near a pixel: the median of the valid values of its 5 × 5 neighbourhood.
fn depth_near(depth: &DepthImage, u: f64, v: f64) -> Option<f64> {
    let (u, v) = (u.round() as i64, v.round() as i64);
    let mut values: Vec<f32> = Vec::with_capacity(25);
    for dv in -2..=2 {
        for du in -2..=2 {
            let (x, y) = (u + du, v + dv);
            if x >= 0 && y >= 0 {
                if let Some(d) = depth.get(x as usize, y as usize) {
                    values.push(d);
                }
            }
        }
    }
    values.sort_by(f32::total_cmp);
    values.get(values.len() / 2).map(|d| f64::from(*d))
}

/// A point of the map visible in a frame: its pixel and its depth (m).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct SeenPoint {
    pub u: f64,
    pub v: f64,
    pub depth_m: f64,
}

/// Points of the map (footholds or rejected places) visible in a frame.
pub fn visible_points(
    depth: &DepthImage,
    intrinsics: &Intrinsics,
    map_from_camera: &Isometry3<f64>,
    points_in_map: &[Vector3<f64>],
    config: &LabelConfig,
) -> Vec<SeenPoint> {
    let camera_from_map = map_from_camera.inverse();
    points_in_map
        .iter()
        .filter_map(|c| {
            let p = camera_from_map * Point3::from(*c);
            let (u, v) = intrinsics.project(&p.coords)?;
            if u < 0.0 || v < 0.0 || u >= intrinsics.width as f64 || v >= intrinsics.height as f64 {
                return None;
            }
            let measured = depth_near(depth, u, v)?;
            ((measured - p.z).abs() <= config.visibility_tolerance_m).then_some(SeenPoint { u, v, depth_m: p.z })
        })
        .collect()
}

/// A painted foothold: the disc its seed cell stands for, in image pixels.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Disc {
    /// Centre pixel: the foothold centre.
    pub u: f64,
    pub v: f64,
    pub radius_px: f64,
}

impl Disc {
    /// The disc of `radius_m` on the surface around a visible point: `f · r / depth` pixels, with f
    /// the mean of the focal lengths.
    pub fn around(point: &SeenPoint, intrinsics: &Intrinsics, radius_m: f64) -> Self {
        let focal = 0.5 * (intrinsics.fx + intrinsics.fy);
        Self { u: point.u, v: point.v, radius_px: focal * radius_m / point.depth_m.max(1e-6) }
    }

    pub fn contains(&self, u: f64, v: f64) -> bool {
        (u - self.u).powi(2) + (v - self.v).powi(2) <= self.radius_px * self.radius_px
    }
}

/// The painted discs of the footholds visible in a frame.
pub fn painted_footholds(
    depth: &DepthImage,
    intrinsics: &Intrinsics,
    map_from_camera: &Isometry3<f64>,
    footholds_in_map: &[Vector3<f64>],
    config: &LabelConfig,
) -> Vec<Disc> {
    visible_points(depth, intrinsics, map_from_camera, footholds_in_map, config)
        .iter()
        .map(|p| Disc::around(p, intrinsics, config.paint_radius_m))
        .collect()
}

/// The centroid (region coordinates) of the painted part of the region's central fraction, sampled
/// on a [`PAINT_SAMPLES`]² grid of cell centres there; `None` when no sample is painted (or every
/// disc has radius 0).
pub fn painted_centroid(region: &Region, discs: &[Disc], centre_fraction: f64) -> Option<(f64, f64)> {
    let size = region.size_px as f64;
    let (u0, v0) = region.origin();
    let low = 0.5 - centre_fraction / 2.0;
    let step = centre_fraction / PAINT_SAMPLES as f64;
    let (u_min, u_max) = (u0 + low * size, u0 + (low + centre_fraction) * size);
    let (v_min, v_max) = (v0 + low * size, v0 + (low + centre_fraction) * size);
    let near: Vec<&Disc> = discs
        .iter()
        .filter(|d| d.radius_px > 0.0)
        .filter(|d| d.u + d.radius_px >= u_min && d.u - d.radius_px <= u_max && d.v + d.radius_px >= v_min && d.v - d.radius_px <= v_max)
        .collect();
    if near.is_empty() {
        return None;
    }
    let (mut sum_x, mut sum_y, mut count) = (0.0, 0.0, 0usize);
    for j in 0..PAINT_SAMPLES {
        let y = low + (j as f64 + 0.5) * step;
        let v = v0 + y * size;
        for i in 0..PAINT_SAMPLES {
            let x = low + (i as f64 + 0.5) * step;
            if near.iter().any(|d| d.contains(u0 + x * size, v)) {
                sum_x += x;
                sum_y += y;
                count += 1;
            }
        }
    }
    (count > 0).then(|| (sum_x / count as f64, sum_y / count as f64))
}

/// The label of a region from the painted footholds of its frame: positive when a foothold centre
/// lies in the central fraction, at the [`painted_centroid`] there (the nearest such centre to the
/// region centre if the discs are too small to cover a sample).
pub fn region_label(region: &Region, discs: &[Disc], centre_fraction: f64) -> Label {
    let nearest = discs
        .iter()
        .map(|d| region.to_region(d.u, d.v))
        .filter(|&(x, y)| Region::in_centre(x, y, centre_fraction))
        .min_by(|a, b| ((a.0 - 0.5).powi(2) + (a.1 - 0.5).powi(2)).total_cmp(&((b.0 - 0.5).powi(2) + (b.1 - 0.5).powi(2))));
    match nearest {
        None => Label::Negative,
        Some(centre) => {
            let (x, y) = painted_centroid(region, discs, centre_fraction).unwrap_or(centre);
            Label::Positive { x, y }
        }
    }
}

/// Whether one of the visible points lies in the region's central fraction.
pub fn tried(region: &Region, points: &[SeenPoint], centre_fraction: f64) -> bool {
    points.iter().any(|p| {
        let (x, y) = region.to_region(p.u, p.v);
        Region::in_centre(x, y, centre_fraction)
    })
}

/// Whether the region's central part lies in the covered area: every point of a
/// [`COVERAGE_SAMPLES`]² grid over it (corners and centre included), back-projected at the frame's
/// depth there (at the region's depth where the frame has none), lies at least `margin` inside the
/// final volume. Where part of a region lies outside the map, that part has neither footholds nor
/// rejected places, so its (x, y) would lean away from the volume's edge for a reason the image
/// does not show.
fn covered(
    region: &Region,
    depth: &DepthImage,
    intrinsics: &Intrinsics,
    map_from_camera: &Isometry3<f64>,
    grid: &VolumeGrid,
    config: &LabelConfig,
) -> bool {
    let low = 0.5 - config.centre_fraction / 2.0;
    let step = config.centre_fraction / (COVERAGE_SAMPLES - 1) as f64;
    let e = grid.edge_m;
    let margin = config.coverage_margin_m;
    (0..COVERAGE_SAMPLES * COVERAGE_SAMPLES).all(|k| {
        let (x, y) = (low + (k % COVERAGE_SAMPLES) as f64 * step, low + (k / COVERAGE_SAMPLES) as f64 * step);
        let (u, v) = region.to_image(x, y);
        let z = depth_near(depth, u, v).unwrap_or(region.depth_m);
        let p = intrinsics.back_project(u, v, z);
        let in_volume = grid.volume_from_map * (map_from_camera * Point3::from(p));
        [in_volume.x, in_volume.y, in_volume.z].iter().all(|c| *c >= margin && *c <= e - margin)
    })
}

/// Proposes and labels the regions of one frame.
#[allow(clippy::too_many_arguments)]
pub fn label_frame(
    depth: &DepthImage,
    intrinsics: &Intrinsics,
    pose: &FramePose,
    footholds_in_map: &[Vector3<f64>],
    rejected_in_map: &[Vector3<f64>],
    grid: &VolumeGrid,
    regions_config: &RegionConfig,
    config: &LabelConfig,
) -> Result<LabelledFrame, FootholdError> {
    let mut inputs = Vec::new();
    let regions = propose(depth, intrinsics, regions_config, &mut inputs)?;
    let footholds_px = painted_footholds(depth, intrinsics, &pose.map_from_camera, footholds_in_map, config);
    let rejected = visible_points(depth, intrinsics, &pose.map_from_camera, rejected_in_map, config);
    let labels = regions
        .iter()
        .map(|r| {
            if footholds_in_map.is_empty() || !covered(r, depth, intrinsics, &pose.map_from_camera, grid, config) {
                return Label::Unknown;
            }
            match region_label(r, &footholds_px, config.centre_fraction) {
                Label::Negative if !tried(r, &rejected, config.centre_fraction) => Label::Unknown,
                label => label,
            }
        })
        .collect();
    Ok(LabelledFrame { tilt: pose.tilt, regions, inputs, labels })
}

#[cfg(test)]
mod tests {
    use super::*;
    use nalgebra::Vector2;
    use patchwalk_spl::patch::SurfaceType;

    fn region() -> Region {
        Region { row: 0, col: 0, u: 100.0, v: 100.0, depth_m: 0.5, size_px: 100 }
    }

    fn disc(u: f64, v: f64, radius_px: f64) -> Disc {
        Disc { u, v, radius_px }
    }

    fn assert_positive_at(label: Label, x: f64, y: f64) {
        match label {
            Label::Positive { x: lx, y: ly } => assert!((lx - x).abs() < 1e-9 && (ly - y).abs() < 1e-9, "({lx}, {ly}) != ({x}, {y})"),
            other => panic!("{other:?} is not positive"),
        }
    }

    #[test]
    fn a_central_foothold_centre_makes_the_region_positive() {
        let r = region();
        // Region spans [50, 150)²; central 80 %: [60, 140].
        assert_eq!(region_label(&r, &[], 0.8), Label::Negative);
        assert_eq!(region_label(&r, &[disc(55.0, 100.0, 4.0)], 0.8), Label::Negative);
        // A disc reaching into the centre without its centre there leaves the region negative.
        assert_eq!(region_label(&r, &[disc(55.0, 100.0, 30.0)], 0.8), Label::Negative);
        // Samples every 80 / 24 px from 61.67 px; the one disc inside is sampled symmetrically about
        // its centre (120 and 90 px lie halfway between samples): its centre.
        assert_positive_at(region_label(&r, &[disc(55.0, 100.0, 4.0), disc(120.0, 90.0, 4.0)], 0.8), 0.7, 0.4);
        // Two discs of radius 4 px: 4 samples of the one at (120, 90) (offsets ±1.67 px), 6 of the one
        // at (105, 100) (u offsets 0, ±3.33 px, v offsets ±1.67 px): centroid (111, 96) px.
        assert_positive_at(region_label(&r, &[disc(55.0, 100.0, 4.0), disc(120.0, 90.0, 4.0), disc(105.0, 100.0, 4.0)], 0.8), 0.61, 0.46);
    }

    #[test]
    fn painted_area_sets_the_position() {
        let r = region();
        // Fully painted: the region centre, wherever the foothold centre is.
        assert_positive_at(region_label(&r, &[disc(70.0, 130.0, 1000.0)], 0.8), 0.5, 0.5);
        // The left half painted (a huge disc whose edge is the line u = 100, plus a small one whose
        // centre lies in the central 80 %): the 12 sample columns left of it, centroid x = 0.1 + 6 / 30.
        let half = [disc(100.0 - 1e6, 100.0, 1e6), disc(80.0, 100.0, 5.0)];
        assert_positive_at(region_label(&r, &half, 0.8), 0.3, 0.5);
        assert_eq!(painted_centroid(&r, &[disc(10.0, 10.0, 5.0)], 0.8), None);
        // Radius 0: the foothold centre nearest the region centre.
        assert_positive_at(region_label(&r, &[disc(120.0, 90.0, 0.0), disc(105.0, 100.0, 0.0)], 0.8), 0.55, 0.5);
    }

    #[test]
    fn discs_span_the_seed_cell_area_at_the_points_depth() {
        let k = Intrinsics::new(64, 48, 50.0, 50.0, 32.0, 24.0).unwrap();
        let config = LabelConfig::default();
        let near = Disc::around(&SeenPoint { u: 10.0, v: 20.0, depth_m: 0.5 }, &k, config.paint_radius_m);
        assert_eq!((near.u, near.v), (10.0, 20.0));
        // 50 px · 0.02 m / 0.5 m.
        assert!((near.radius_px - 2.0).abs() < 1e-12);
        let far = Disc::around(&SeenPoint { u: 10.0, v: 20.0, depth_m: 2.0 }, &k, config.paint_radius_m);
        assert!((far.radius_px - 0.5).abs() < 1e-12);
        assert!(near.contains(11.9, 20.0) && !near.contains(12.1, 20.0));
    }

    #[test]
    fn negatives_need_a_rejected_point_in_the_centre() {
        let r = region();
        let at = |u, v| SeenPoint { u, v, depth_m: 0.5 };
        assert!(tried(&r, &[at(70.0, 130.0)], 0.8));
        assert!(!tried(&r, &[at(55.0, 100.0)], 0.8));
        assert!(is_rejection(&Verdict::Edge) && is_rejection(&Verdict::Tilt));
        assert!(!is_rejection(&Verdict::Skipped) && !is_rejection(&Verdict::Valid { id: 1 }));
        assert!(!is_rejection(&Verdict::FitFailed("x".into())) && !is_rejection(&Verdict::Coverage));
    }

    #[test]
    fn footholds_are_walkable_and_foot_sized() {
        let config = LabelConfig::default();
        // Rotation vector about y by the slope: the normal tilts away from up by that angle.
        let plane = |rotation: Vector3<f64>, r: f64| {
            Patch::new(SurfaceType::Plane, BoundaryType::Circle, vec![r], Vector2::zeros(), rotation, Vector3::zeros()).unwrap()
        };
        let up = |deg: f64| Vector3::new(0.0, deg.to_radians(), 0.0);
        assert!(is_foothold(&plane(up(0.0), 0.05), &config));
        assert!(is_foothold(&plane(up(25.0), 0.05), &config));
        assert!(!is_foothold(&plane(up(40.0), 0.05), &config));
        assert!(!is_foothold(&plane(up(0.0), 0.03), &config));
    }

    #[test]
    fn visibility_uses_the_frames_depth() {
        let k = Intrinsics::new(64, 48, 50.0, 50.0, 32.0, 24.0).unwrap();
        let depth = DepthImage::new(64, 48, vec![1.0; 64 * 48]).unwrap();
        let pose = Isometry3::identity();
        let config = LabelConfig::default();
        let seen = visible_points(
            &depth,
            &k,
            &pose,
            &[Vector3::new(0.0, 0.0, 1.0), Vector3::new(0.0, 0.0, 0.5), Vector3::new(5.0, 0.0, 1.0)],
            &config,
        );
        assert_eq!(seen.iter().map(|p| (p.u, p.v)).collect::<Vec<_>>(), vec![(32.0, 24.0)]);
        let painted = painted_footholds(&depth, &k, &pose, &[Vector3::new(0.0, 0.0, 1.0), Vector3::new(0.0, 0.0, 0.5)], &config);
        assert_eq!(painted, vec![Disc { u: 32.0, v: 24.0, radius_px: 1.0 }]);
    }

    #[test]
    fn the_whole_central_part_must_lie_in_the_covered_area() {
        // A wall 1 m in front of the camera (map frame = camera frame); a 20 px region at the image
        // centre spans 0.4 m of it, its central 80 % x ∈ [-0.16, 0.16] m.
        let k = Intrinsics::new(64, 48, 50.0, 50.0, 32.0, 24.0).unwrap();
        let depth = DepthImage::new(64, 48, vec![1.0; 64 * 48]).unwrap();
        let region = Region { row: 0, col: 0, u: 32.0, v: 24.0, depth_m: 1.0, size_px: 20 };
        let config = LabelConfig::default();
        let grid = |x: f64| VolumeGrid { volume_from_map: Isometry3::translation(x, 0.5, -0.5), edge_m: 1.0, cells_per_side: 25 };
        let pose = Isometry3::identity();
        // Centred in the 1 m cube: covered.
        assert!(covered(&region, &depth, &k, &pose, &grid(0.5), &config));
        // The region centre 0.15 m inside the cube's edge, its central part's left side 0.01 m
        // outside: not covered.
        assert!(!covered(&region, &depth, &k, &pose, &grid(0.15), &config));
        // Within the margin of the edge counts as outside too (0.03 m inside).
        assert!(!covered(&region, &depth, &k, &pose, &grid(0.19), &config));
        assert!(covered(&region, &depth, &k, &pose, &grid(0.21), &config));
        // Where the frame has no depth the region's depth is used: the same answers.
        let holes = DepthImage::new(64, 48, vec![0.0; 64 * 48]).unwrap();
        assert!(covered(&region, &holes, &k, &pose, &grid(0.5), &config));
        assert!(!covered(&region, &holes, &k, &pose, &grid(0.15), &config));
    }
}

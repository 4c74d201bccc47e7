//! The single-frame patch mapper (J 4, stages i–v, steps 1–16) as one straight pipeline with one
//! config, adding patches to a [`PatchMap`].
//!
//! Input is a depth image with its pinhole intrinsics and the camera pose in the gravity-aligned
//! volume frame, so the same code runs on a real camera frame or on the fusion's birds-eye raycast
//! (a virtual pinhole camera; set `preprocess.median_downsample = false` there, J step 5).
//! Patches are fitted in the camera frame (the sensor error model lives there) and stored in the
//! map's frame through `map_from_camera = map_from_volume · volume_from_camera`.

use std::sync::atomic::{AtomicBool, AtomicUsize, Ordering};
use std::sync::Mutex;
use std::time::Instant;

use nalgebra::{Isometry3, Point3, Unit, Vector3};
use rand::{rngs::StdRng, SeedableRng};
use rayon::prelude::*;

use crate::acquire::{organized_cloud, AcquireConfig, AcquireError, OrganizedCloud};
use crate::foot_column::{foot_column, DEFAULT_MAX_PIXELS};
use crate::neighbourhood::{ball_neighbourhood, gather, uniform_subset, NeighbourhoodConfig};
use crate::patch_fusion::{reobserve, revisits, FusionConfig, FusionCounts, Reobserved};
use crate::patch_map::{PatchMap, VolumeGrid};
use crate::preprocess::{preprocess, PreprocessConfig, PreprocessError, Preprocessed};
use crate::saliency::{fixation_point, hiking_saliency_reusing, Saliency, SaliencyConfig, SaliencyTables};
use crate::seeds::{select_seeds, AuxiliaryImage, Seed, SeedConfig, SeedPrior};
use patchwalk_fusion::camera::{DepthImage, Intrinsics};
use patchwalk_spl::fit::neighbourhood::{fit_neighbourhood, NeighbourhoodFit};
use patchwalk_spl::fit::FitConfig;
use patchwalk_spl::patch::Patch;
use patchwalk_spl::sensor::ErrorModel;
use patchwalk_spl::transform::transform_patch;
use patchwalk_spl::validate::visibility::out_of_view_fraction;
use patchwalk_spl::validate::{validate_foothold, DiscView, Foothold, SampledBall, ValidateConfig, Validation};

/// Configuration of the whole mapper; every default is J's value (see each stage's struct).
#[derive(Debug, Clone, PartialEq, serde::Serialize, serde::Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct MapperConfig {
    /// r: neighbourhood radius = foot size (J 4.4; 0.05 m for RPBP's foot, 0.1 m in the human-data
    /// experiments of J 6.1.1).
    pub foot_radius_m: f64,
    /// Vs: edge of the cubic volume whose xz-plane carries the seed grid (m). Same default as the
    /// fusion's TSDF volume (1.28 m); J gives no number.
    pub volume_edge_m: f64,
    /// tm: time limit for stages iii–v per frame (ms). J 6.1.2: "we additionally limit the total
    /// time spent per frame to e.g. 100 ms".
    pub time_limit_ms: f64,
    /// ν: stop once the valid patches reach ν·S/(πr²) (J eq 19), S the salient surface area.
    /// J 6.1.1 mapped until patches covered 90 % of the surface.
    pub coverage_fraction: f64,
    pub acquire: AcquireConfig,
    pub preprocess: PreprocessConfig,
    pub saliency: SaliencyConfig,
    pub seeds: SeedConfig,
    pub neighbourhood: NeighbourhoodConfig,
    pub fit: FitConfig,
    pub validate: ValidateConfig,
    /// Point covariances for the fit (J eq 2, Murray–Little with the Kinect values).
    pub sensor: ErrorModel,
    /// Γ: boundary containment probability (J 3.2.1 step 4 / IROS IV: 0.95).
    pub containment: f64,
    /// Size plane boundaries like every other type with J 3.2.1 step 5, `d_e = λ[√v_x √v_y]`,
    /// `λ = √2 erf⁻¹(Γ)` (0.98 r for the uniform disc an r-ball cuts from a plane). The patch core
    /// follows IROS eq 30 for planes, `d = √(−2 ln(1 − Γ) v)` (1.22 r), which leaves a third of
    /// the ellipse without data and fails the coverage test (J eq 16) on every r-ball; true
    /// rescales the plane's d (and its covariance) by `λ / √(−2 ln(1 − Γ))`.
    pub plane_boundary_j_step5: bool,
    /// Re-observation of mapped patches and their fusion with Σ (see [`crate::patch_fusion`]).
    pub fusion: FusionConfig,
    /// Most patches the map holds; beyond it the least recently seen are dropped. J bounds the map
    /// by its grid (ng per cell, 64 cells); with the robot's 1 cm cells (16,384) that bound is no
    /// bound when saliency runs without DtFP over a whole view: the map would grow by about 20
    /// patches a frame to thousands, each published at 30 Hz. 512 holds a patch per 1 cm cell of the
    /// 0.12 m fixation ball (452 cells) with room for the ones the robot walks past.
    pub max_patches: usize,
}

impl Default for MapperConfig {
    fn default() -> Self {
        Self {
            foot_radius_m: 0.05,
            volume_edge_m: 1.28,
            time_limit_ms: 100.0,
            coverage_fraction: 0.9,
            acquire: AcquireConfig::default(),
            preprocess: PreprocessConfig::default(),
            saliency: SaliencyConfig::default(),
            seeds: SeedConfig::default(),
            neighbourhood: NeighbourhoodConfig::default(),
            fit: FitConfig::default(),
            validate: ValidateConfig::default(),
            sensor: ErrorModel::default(),
            containment: 0.95,
            plane_boundary_j_step5: true,
            fusion: FusionConfig::default(),
            max_patches: 512,
        }
    }
}

/// Errors of the mapper.
#[derive(Debug, thiserror::Error, PartialEq)]
pub enum MapperError {
    #[error(transparent)]
    Preprocess(#[from] PreprocessError),
    #[error(transparent)]
    Acquire(#[from] AcquireError),
    #[error("invalid mapper config: {0}")]
    Config(String),
}

/// One frame to map.
#[derive(Debug, Clone, Copy)]
pub struct FrameInput<'a> {
    /// Depth in metres (NaN invalid): a real frame or a birds-eye raycast.
    pub depth: &'a DepthImage,
    /// Its pinhole intrinsics.
    pub intrinsics: &'a Intrinsics,
    /// Camera pose in the volume frame (J eq 18, `C_t`): volume y along gravity.
    pub volume_from_camera: Isometry3<f64>,
    /// Timestamp (s) recorded as first/last seen.
    pub timestamp: f64,
}

/// What happened to one seed (J steps 13–16).
#[derive(Debug, Clone, PartialEq)]
pub enum Verdict {
    /// Passed every validation and went into the map with this id.
    Valid { id: u64 },
    /// Step 14: residual above dmax.
    Residual,
    /// Step 15: coverage.
    Coverage,
    /// Step 16: curvature out of [κmin, κmax].
    Curvature,
    /// The normal tilts from gravity's up by more than `validate.tilt_max_deg`.
    Tilt,
    /// The terrain inside the foot disc lies off the surface (an edge or fold under the foot).
    Edge,
    /// The foot disc was not seen to carry the foot: more of it than `validate.out_of_view_max_fraction`
    /// lies outside the image; or (tests off by default) with `validate.open_rim_max_fraction` set,
    /// too many of its pixels see through it or into a hole at an edge; with
    /// `validate.unseen_max_fraction` set, too many did not measure it at all (no depth, or free
    /// space or an occluder where the surface should be).
    Unseen,
    /// Fewer neighbourhood points than `neighbourhood.min_points`.
    TooFewPoints,
    /// The fit failed (message of the patch core's error).
    FitFailed(String),
    /// Not processed: time limit or coverage target reached first.
    Skipped,
}

impl Verdict {
    /// Short name for reports and JSON (`valid`, `residual`, `coverage`, `curvature`, `tilt`,
    /// `edge`, `unseen`, `too_few_points`, `fit_failed`, `skipped`).
    pub fn name(&self) -> &'static str {
        match self {
            Verdict::Valid { .. } => "valid",
            Verdict::Residual => "residual",
            Verdict::Coverage => "coverage",
            Verdict::Curvature => "curvature",
            Verdict::Tilt => "tilt",
            Verdict::Edge => "edge",
            Verdict::Unseen => "unseen",
            Verdict::TooFewPoints => "too_few_points",
            Verdict::FitFailed(_) => "fit_failed",
            Verdict::Skipped => "skipped",
        }
    }

    /// The verdict of a validated patch: the first failed test in J's order (steps 14–16), then
    /// the foothold tests (tilt, edge, unseen), or valid (with the placeholder id `u64::MAX` until the patch
    /// map assigns one).
    pub fn from_validation(validation: &Validation) -> Self {
        if !validation.residual.passed {
            Verdict::Residual
        } else if !validation.coverage.passed {
            Verdict::Coverage
        } else if !validation.curvature_ok() {
            Verdict::Curvature
        } else if !validation.tilt_ok() {
            Verdict::Tilt
        } else if !validation.edge_ok() {
            Verdict::Edge
        } else if !validation.unseen_ok() || !validation.open_rim_ok() || !validation.in_view_ok() {
            Verdict::Unseen
        } else {
            Verdict::Valid { id: u64::MAX }
        }
    }

    /// Whether the patch passed validation.
    pub fn is_valid(&self) -> bool {
        matches!(self, Verdict::Valid { .. })
    }
}

/// Result for one seed.
#[derive(Debug, Clone)]
pub struct SeedOutcome {
    pub seed: Seed,
    /// Points in the r-ball (before the nf subsample).
    pub neighbourhood_size: usize,
    /// The fitted patch in the camera frame (also for rejected patches).
    pub patch_in_camera: Option<Patch>,
    pub validation: Option<Validation>,
    pub verdict: Verdict,
}

/// A mapped patch re-fitted this frame: the seed at its centre, and what fusion did with a valid re-fit.
#[derive(Debug, Clone)]
pub struct Revisited {
    /// The id the patch had before this frame.
    pub id: u64,
    pub outcome: SeedOutcome,
    /// `None` when the re-fit failed validation (the patch is left as it was).
    pub fused: Option<Reobserved>,
}

/// Why stage v stopped.
#[derive(Debug, Clone, Copy, PartialEq, Eq, serde::Serialize)]
pub enum StopReason {
    /// Every seed was processed (ns or the seeds ran out).
    SeedsExhausted,
    /// tm reached.
    TimeLimit,
    /// ν·S/(πr²) valid patches reached (J eq 19).
    CoverageReached,
}

/// Wall-clock times of the stages (ms). Neighbourhood and fit times are summed over the threads.
#[derive(Debug, Clone, Copy, Default, PartialEq, serde::Serialize)]
pub struct StageTimings {
    pub preprocess_ms: f64,
    pub saliency_ms: f64,
    pub seeds_ms: f64,
    pub neighbourhood_cpu_ms: f64,
    pub fit_validate_cpu_ms: f64,
    /// The validation part of `fit_validate_cpu_ms` (J 3.3 on the full neighbourhood).
    pub validate_cpu_ms: f64,
    /// Wall time of stages iv–v together (new seeds and re-observations).
    pub fit_stage_ms: f64,
    /// Wall time of the re-observations: the re-fits of mapped patches and their fusion.
    pub reobserve_ms: f64,
    /// The fusion part of `reobserve_ms` (gate, update, map bookkeeping).
    pub fusion_ms: f64,
    pub total_ms: f64,
}

/// Everything the mapper produced for one frame (kept for pictures and statistics).
#[derive(Debug, Clone)]
pub struct FrameResult {
    pub outcomes: Vec<SeedOutcome>,
    /// The mapped patches re-fitted this frame ([`crate::patch_fusion`]).
    pub revisited: Vec<Revisited>,
    pub preprocessed: Preprocessed,
    pub saliency: Saliency,
    /// Unit gravity in the camera frame (from `volume_from_camera`).
    pub gravity_in_camera: Unit<Vector3<f64>>,
    /// Patch count of J eq 19 for this frame.
    pub target_patches: usize,
    pub stop: StopReason,
    /// Patches dropped from the map this frame to keep it within `max_patches`.
    pub evicted: usize,
    pub timings: StageTimings,
}

impl FrameResult {
    /// Counts like J Table 2.
    pub fn summary(&self) -> FrameSummary {
        let mut s = FrameSummary::default();
        for outcome in &self.outcomes {
            match &outcome.verdict {
                Verdict::Valid { .. } => {
                    s.valid += 1;
                    s.residual_sum_m += outcome.patch_in_camera.as_ref().map_or(0.0, |p| p.residual);
                    s.area_m2 += outcome.patch_in_camera.as_ref().map_or(0.0, |p| p.boundary_area());
                }
                Verdict::Residual => s.residual += 1,
                Verdict::Coverage => s.coverage += 1,
                Verdict::Curvature => s.curvature += 1,
                Verdict::Tilt => s.tilt += 1,
                Verdict::Edge => s.edge += 1,
                Verdict::Unseen => s.unseen += 1,
                Verdict::TooFewPoints | Verdict::FitFailed(_) => s.failed += 1,
                Verdict::Skipped => s.skipped += 1,
            }
        }
        s.seeds = self.outcomes.len();
        s.fitted = s.valid + s.residual + s.coverage + s.curvature + s.tilt + s.edge + s.unseen;
        s.fusion.revisited = self.revisited.len();
        for fused in self.revisited.iter().filter_map(|r| r.fused.as_ref()) {
            s.fusion.count(fused);
        }
        s
    }
}

/// J Table 2 columns for one or more frames.
#[derive(Debug, Clone, Copy, Default, PartialEq, serde::Serialize)]
pub struct FrameSummary {
    pub seeds: usize,
    /// Patches fitted (valid + dropped).
    pub fitted: usize,
    pub valid: usize,
    pub residual: usize,
    pub coverage: usize,
    pub curvature: usize,
    /// Normal too far from up (`validate.tilt_max_deg`).
    pub tilt: usize,
    /// An edge or fold under the foot disc (`validate.edge_max_offset_m`).
    pub edge: usize,
    /// The foot disc not seen to carry the foot (`validate.open_rim_max_fraction`,
    /// `validate.unseen_max_fraction`).
    pub unseen: usize,
    /// Fit errors and too-small neighbourhoods.
    pub failed: usize,
    pub skipped: usize,
    /// Σ residual of the valid patches (m), for the mean.
    pub residual_sum_m: f64,
    /// Σ boundary area of the valid patches (m²).
    pub area_m2: f64,
    /// Re-observations of mapped patches and what fusion made of them.
    pub fusion: FusionCounts,
}

impl FrameSummary {
    /// Adds another frame's counts.
    pub fn add(&mut self, other: &FrameSummary) {
        self.seeds += other.seeds;
        self.fitted += other.fitted;
        self.valid += other.valid;
        self.residual += other.residual;
        self.coverage += other.coverage;
        self.curvature += other.curvature;
        self.tilt += other.tilt;
        self.edge += other.edge;
        self.unseen += other.unseen;
        self.failed += other.failed;
        self.skipped += other.skipped;
        self.residual_sum_m += other.residual_sum_m;
        self.area_m2 += other.area_m2;
        self.fusion.add(&other.fusion);
    }

    /// Mean residual of the valid patches (m).
    pub fn mean_residual_m(&self) -> f64 {
        if self.valid == 0 {
            0.0
        } else {
            self.residual_sum_m / self.valid as f64
        }
    }
}

/// The mapper: config, the patch map it fills and a frame counter.
#[derive(Debug, Clone)]
pub struct Mapper {
    pub config: MapperConfig,
    pub map: PatchMap,
    frames: u64,
    /// Predicted footholds in the map frame (point, score) for the learned seed orders.
    seed_priors_in_map: Vec<(Vector3<f64>, f64)>,
    /// The saliency's summed-area tables, rebuilt in place every frame.
    saliency_tables: SaliencyTables,
}

/// The single-frame volume: y along gravity, z along the camera's horizontal forward direction,
/// camera at the middle of the top edge of the back face (`[Vs/2, 0, 0]`), so the whole cube lies
/// ahead of and below the camera. (J 5.2 puts the camera in the middle of the volume when fusing;
/// for a single frame that would waste the half of the grid behind the camera.)
pub fn single_frame_volume_from_camera(gravity_in_camera: &Unit<Vector3<f64>>, edge_m: f64) -> Isometry3<f64> {
    let config = patchwalk_fusion::volume::MovingVolumeConfig { nominal_position_fraction: [0.5, 0.0, 0.0], ..Default::default() };
    patchwalk_fusion::volume::initial_volume_from_camera(Some(gravity_in_camera.into_inner()), edge_m, &config)
}

/// `volume_from_map` for the map frame of the fusion (`map` z up, axes from
/// [`patchwalk_fusion::volume::map_from_volume_rotation`], same origin as the volume).
pub fn default_volume_from_map() -> Isometry3<f64> {
    Isometry3::from_parts(nalgebra::Translation3::identity(), patchwalk_fusion::volume::map_from_volume_rotation().inverse())
}

impl Mapper {
    /// A mapper with an empty map in frame `frame_id`, gridded with `volume_from_map`.
    pub fn new(config: MapperConfig, frame_id: &str, volume_from_map: Isometry3<f64>) -> Result<Self, MapperError> {
        check_config(&config)?;
        let grid = VolumeGrid { volume_from_map, edge_m: config.volume_edge_m, cells_per_side: config.seeds.cells_per_side };
        Ok(Self {
            map: PatchMap::new(frame_id, grid),
            config,
            frames: 0,
            seed_priors_in_map: Vec::new(),
            saliency_tables: SaliencyTables::default(),
        })
    }

    /// Predicted footholds (points in the map frame, scores in [0, 1]) for the learned seed orders
    /// (`seeds.order`), used from the next frame on until replaced; an empty list clears them.
    pub fn set_seed_priors(&mut self, priors_in_map: Vec<(Vector3<f64>, f64)>) {
        self.seed_priors_in_map = priors_in_map;
    }

    /// The predicted footholds the learned seed orders use (map frame).
    pub fn seed_priors(&self) -> &[(Vector3<f64>, f64)] {
        &self.seed_priors_in_map
    }

    /// The pixels of a view (`intrinsics`, at `volume_from_view`, looking along gravity as the
    /// birds-eye camera does) that the next [`Mapper::process`] reads: the DtFP ball (step 6.2), the
    /// patches it will re-fit ([`revisits`]: those whose anchor the view sees, found by
    /// `anchor_depth`, the view's depth at the marked anchor pixels), and the predicted footholds of
    /// the learned seed orders, each [`REGION_MARGIN_RADII`] foot radii wider. `None` (all of them)
    /// without a DtFP ball.
    pub fn read_region(
        &self,
        intrinsics: &Intrinsics,
        volume_from_view: &Isometry3<f64>,
        anchor_depth: impl FnOnce(&[bool]) -> DepthImage,
    ) -> Option<Vec<bool>> {
        let config = &self.config;
        let saliency = seed_saliency_config(config);
        if !saliency.fixation_radius_m.is_finite() {
            return None;
        }
        let margin = REGION_MARGIN_RADII * config.foot_radius_m;
        let mut region = vec![false; intrinsics.width * intrinsics.height];
        // The view looks along gravity, its z axis.
        let fixation = fixation_point(&Vector3::z_axis(), saliency.fixation_down_m, saliency.fixation_forward_m);
        mark_ball(&mut region, intrinsics, &fixation, saliency.fixation_radius_m + margin);
        let view_from_map = volume_from_view.inverse() * self.map.grid().volume_from_map;
        let mut anchor_pixels = vec![false; region.len()];
        for patch in self.map.patches() {
            if let Some((u, v)) = intrinsics.pixel_of(&(view_from_map * Point3::from(patch.anchor)).coords) {
                if let Some(pixel) = anchor_pixels.get_mut(v * intrinsics.width + u) {
                    *pixel = true;
                }
            }
        }
        let anchors = anchor_depth(&anchor_pixels);
        for revisit in revisits(&self.map, &view_from_map, &anchors, intrinsics, config.foot_radius_m, &config.fusion) {
            mark_ball(&mut region, intrinsics, &revisit.anchor_in_camera, margin);
        }
        // Predicted footholds seed where they are, in or out of the ball (the learned seed orders).
        for (point, _) in &self.seed_priors_in_map {
            mark_ball(&mut region, intrinsics, &(view_from_map * Point3::from(*point)).coords, margin);
        }
        Some(region)
    }

    /// New parameters from the next frame on (a node's parameter set). The map's grid (volume edge,
    /// seed cells per side) is fixed for the mapper's life; a change of it is refused.
    pub fn set_config(&mut self, config: MapperConfig) -> Result<(), MapperError> {
        check_config(&config)?;
        if config.volume_edge_m != self.config.volume_edge_m || config.seeds.cells_per_side != self.config.seeds.cells_per_side {
            return Err(MapperError::Config("volume_edge_m and seeds.cells_per_side are fixed while the mapper runs".into()));
        }
        self.config = config;
        Ok(())
    }

    /// Stages i–v on one frame; valid patches are added to the map.
    pub fn process(&mut self, input: &FrameInput) -> Result<FrameResult, MapperError> {
        let config = &self.config;
        let start = Instant::now();
        let gravity_in_camera = Unit::new_normalize(input.volume_from_camera.inverse().rotation * Vector3::y());
        // Stage ii, steps 3–5.
        let preprocessed = preprocess(input.depth, input.intrinsics, &config.preprocess)?;
        let cloud = organized_cloud(&preprocessed.filtered, input.intrinsics)?;
        let t_pre = Instant::now();
        // Stage ii, step 6.
        let saliency = hiking_saliency_reusing(
            &preprocessed.auxiliary,
            &preprocessed.auxiliary_intrinsics,
            &gravity_in_camera,
            config.foot_radius_m,
            &seed_saliency_config(config),
            &mut self.saliency_tables,
        );
        let t_sal = Instant::now();
        // Stage iii.
        let volume_from_map = self.map.grid().volume_from_map;
        let priors: Vec<SeedPrior> = self
            .seed_priors_in_map
            .iter()
            .map(|(point, score)| SeedPrior { point_in_volume: (volume_from_map * nalgebra::Point3::from(*point)).coords, score: *score })
            .collect();
        let seeds = select_seeds(
            &saliency,
            AuxiliaryImage { depth: &preprocessed.auxiliary, intrinsics: &preprocessed.auxiliary_intrinsics },
            self.map.grid(),
            &input.volume_from_camera,
            &self.map.cell_counts(),
            &priors,
            &config.seeds,
            self.frames,
        );
        let t_seeds = Instant::now();
        // Re-observations first (at most `fusion.reobserve_per_frame` fits), within the same tm.
        let deadline =
            std::time::Duration::try_from_secs_f64(config.time_limit_ms.max(0.0) / 1000.0).ok().and_then(|limit| start.checked_add(limit));
        let map_from_camera = self.map.grid().volume_from_map.inverse() * input.volume_from_camera;
        self.map.set_frame(self.frames);
        let revisit =
            revisits(&self.map, &map_from_camera.inverse(), &preprocessed.filtered, input.intrinsics, config.foot_radius_m, &config.fusion);
        let revisit_seeds: Vec<Seed> = revisit
            .iter()
            .filter_map(|r| Some(Seed { pixel: r.pixel, point_in_camera: r.anchor_in_camera, cell: self.map.get(r.id)?.cell? }))
            .collect();
        let up_in_camera = -gravity_in_camera.into_inner();
        let (revisit_outcomes, _, _) = fit_seeds(
            &revisit_seeds,
            &cloud,
            input.intrinsics,
            &up_in_camera,
            config,
            usize::MAX,
            deadline,
            self.frames ^ REVISIT_RNG_SALT,
        );
        let t_revisit = Instant::now();
        // Stages iv–v until tm, ns or ν (J eq 19).
        let target_patches =
            (config.coverage_fraction * saliency.salient_area_m2 / (std::f64::consts::PI * config.foot_radius_m.powi(2))).ceil() as usize;
        let (mut outcomes, stop, [neighbourhood_cpu_ms, fit_validate_cpu_ms, validate_cpu_ms]) =
            fit_seeds(&seeds, &cloud, input.intrinsics, &up_in_camera, config, target_patches, deadline, self.frames);
        let t_fit = Instant::now();
        // Into the map, in seed order.
        for outcome in &mut outcomes {
            if let (Verdict::Valid { id }, Some(patch)) = (&mut outcome.verdict, &outcome.patch_in_camera) {
                match transform_patch(patch, &map_from_camera) {
                    Some(patch_in_map) => {
                        let anchor = (map_from_camera * nalgebra::Point3::from(outcome.seed.point_in_camera)).coords;
                        *id = self.map.insert_anchored(patch_in_map, Some(outcome.seed.cell), anchor, input.timestamp);
                    }
                    None => outcome.verdict = Verdict::FitFailed("patch could not be moved to the map frame".into()),
                }
            }
        }
        // Re-observations fused into their patches.
        let t_fuse = Instant::now();
        let mut revisited = Vec::with_capacity(revisit_outcomes.len());
        for (r, outcome) in revisit.iter().zip(revisit_outcomes) {
            let fused = match (&outcome.verdict, &outcome.patch_in_camera) {
                (Verdict::Valid { .. }, Some(patch)) => transform_patch(patch, &map_from_camera)
                    .map(|in_map| reobserve(&mut self.map, r.id, in_map, input.timestamp, &config.fusion)),
                _ => None,
            };
            revisited.push(Revisited { id: r.id, outcome, fused });
        }
        let evicted = self.map.keep_most_recent(config.max_patches);
        let t_done = Instant::now();
        self.frames += 1;
        let ms = |a: Instant, b: Instant| (b - a).as_secs_f64() * 1e3;
        let timings = StageTimings {
            preprocess_ms: ms(start, t_pre),
            saliency_ms: ms(t_pre, t_sal),
            seeds_ms: ms(t_sal, t_seeds),
            neighbourhood_cpu_ms,
            fit_validate_cpu_ms,
            validate_cpu_ms,
            fit_stage_ms: ms(t_seeds, t_fit),
            reobserve_ms: ms(t_seeds, t_revisit) + ms(t_fuse, t_done),
            fusion_ms: ms(t_fuse, t_done),
            total_ms: ms(start, Instant::now()),
        };
        Ok(FrameResult { outcomes, revisited, preprocessed, saliency, gravity_in_camera, target_patches, stop, evicted, timings })
    }
}

impl MapperConfig {
    /// The part of the configuration that step 13 (the fit of one neighbourhood) uses.
    pub fn neighbourhood_fit(&self) -> NeighbourhoodFit {
        NeighbourhoodFit {
            sensor: self.sensor,
            fit: self.fit,
            containment: self.containment,
            plane_boundary_j_step5: self.plane_boundary_j_step5,
        }
    }
}

/// The saliency configuration step 6 runs with: φ_g (step 6.5) is capped by the foothold tilt limit
/// `validate.tilt_max_deg` when that test is on, since a seed whose surface normal is steeper than the
/// limit can only fit a patch the tilt test rejects (fitting it costs time and takes the place of a
/// seed that could stand). With the tilt test off (`ValidateConfig::j33`) φ_g is J's as configured.
/// Likewise a window's quadric keeps a bump only within the validator's `curvature_max`.
pub fn seed_saliency_config(config: &MapperConfig) -> SaliencyConfig {
    SaliencyConfig {
        dong_max_deg: config.saliency.dong_max_deg.min(config.validate.tilt_max_deg),
        window_curvature_max: config.saliency.window_curvature_max.min(config.validate.curvature_max),
        ..config.saliency.clone()
    }
}

/// How far (foot radii r) [`Mapper::read_region`] reaches past the DtFP ball and past the anchors
/// of the patches re-fitted: a seed's foot window and neighbourhood (r), and the foot disc of the
/// patch fitted there, whose centre may lie another r out.
pub const REGION_MARGIN_RADII: f64 = 2.0;

/// Marks the pixels of the rectangle that holds the image of the ball of `radius` around `centre`
/// (camera frame), all of them when the ball reaches the camera's plane.
fn mark_ball(region: &mut [bool], intrinsics: &Intrinsics, centre: &Vector3<f64>, radius: f64) {
    let near = centre.z - radius;
    if !(near > 1e-3 && radius.is_finite() && centre.x.is_finite() && centre.y.is_finite()) {
        region.fill(true);
        return;
    }
    // Over the ball's bounding box (z > 0), x/z and y/z are monotonic in each coordinate: its
    // corners bound the image.
    let span = |along: f64, focal: f64, principal: f64, size: usize| {
        let (mut lo, mut hi) = (f64::INFINITY, f64::NEG_INFINITY);
        for a in [along - radius, along + radius] {
            for depth in [near, centre.z + radius] {
                let pixel = focal * a / depth + principal;
                lo = lo.min(pixel);
                hi = hi.max(pixel);
            }
        }
        let first = lo.floor().clamp(0.0, size as f64) as usize;
        let end = (hi.ceil() + 1.0).clamp(0.0, size as f64) as usize;
        first..end.max(first)
    };
    let columns = span(centre.x, intrinsics.fx, intrinsics.cx, intrinsics.width);
    for v in span(centre.y, intrinsics.fy, intrinsics.cy, intrinsics.height) {
        let row = v * intrinsics.width;
        if let Some(pixels) = region.get_mut(row + columns.start..row + columns.end) {
            pixels.fill(true);
        }
    }
}

/// The checks [`Mapper::new`] makes on a configuration.
pub fn check_config(config: &MapperConfig) -> Result<(), MapperError> {
    let bad = |what: &str| Err(MapperError::Config(what.to_string()));
    if !(config.foot_radius_m.is_finite() && config.foot_radius_m > 0.0) {
        return bad("foot_radius_m must be positive");
    }
    if !(config.volume_edge_m.is_finite() && config.volume_edge_m > 0.0) {
        return bad("volume_edge_m must be positive");
    }
    if config.seeds.cells_per_side == 0 || config.seeds.cells_per_side > 1024 {
        return bad("seeds.cells_per_side must be in 1..=1024");
    }
    if config.neighbourhood.fit_points == 0 {
        return bad("neighbourhood.fit_points must be positive");
    }
    if !(config.containment > 0.0 && config.containment < 1.0) {
        return bad("containment must be in (0, 1)");
    }
    if config.max_patches == 0 {
        return bad("max_patches must be positive");
    }
    if config.time_limit_ms.is_nan() || config.coverage_fraction.is_nan() {
        return bad("time_limit_ms and coverage_fraction must be numbers");
    }
    config.acquire.camera_from_imu()?;
    config.validate.check().map_err(MapperError::Config)?;
    config.fusion.validate().map_err(MapperError::Config)?;
    Ok(())
}

/// Mixed into the frame counter for the re-observations' neighbourhood subsets, so they do not
/// draw the same random subsets as the new seeds of the same index.
const REVISIT_RNG_SALT: u64 = 0x5EED_F05E_0000;

/// Stages iv–v over the seeds in parallel. Workers pull seeds in order (nearest cells first), so a
/// time limit drops the farthest seeds. Returns outcomes in seed order, the stop reason and the
/// CPU times of stage iv and v.
#[allow(clippy::too_many_arguments)]
fn fit_seeds(
    seeds: &[Seed],
    cloud: &OrganizedCloud,
    intrinsics: &Intrinsics,
    up_in_camera: &Vector3<f64>,
    config: &MapperConfig,
    target_patches: usize,
    deadline: Option<Instant>,
    frame: u64,
) -> (Vec<SeedOutcome>, StopReason, [f64; 3]) {
    let next = AtomicUsize::new(0);
    let valid = AtomicUsize::new(0);
    let timed_out = AtomicBool::new(false);
    let covered = AtomicBool::new(false);
    let times = Mutex::new([0.0f64; 3]);
    let workers = rayon::current_num_threads().clamp(1, seeds.len().max(1));
    let mut done: Vec<(usize, SeedOutcome)> = (0..workers)
        .into_par_iter()
        .flat_map_iter(|_| {
            let mut local = Vec::new();
            let mut scratch = Vec::new();
            let mut column = Vec::new();
            let mut cpu = [0.0f64; 3];
            loop {
                let index = next.fetch_add(1, Ordering::Relaxed);
                let Some(seed) = seeds.get(index) else { break };
                if deadline.is_some_and(|d| Instant::now() >= d) {
                    timed_out.store(true, Ordering::Relaxed);
                    break;
                }
                if valid.load(Ordering::Relaxed) >= target_patches {
                    covered.store(true, Ordering::Relaxed);
                    break;
                }
                let scratch = SeedScratch { indices: &mut scratch, column: &mut column };
                let outcome = process_seed(seed, cloud, intrinsics, up_in_camera, config, frame, index, scratch, &mut cpu);
                if matches!(outcome.verdict, Verdict::Valid { .. }) {
                    valid.fetch_add(1, Ordering::Relaxed);
                }
                local.push((index, outcome));
            }
            if let Ok(mut total) = times.lock() {
                for (t, c) in total.iter_mut().zip(cpu) {
                    *t += c;
                }
            }
            local
        })
        .collect();
    done.sort_by_key(|(index, _)| *index);
    let mut outcomes: Vec<SeedOutcome> = Vec::with_capacity(seeds.len());
    let mut iter = done.into_iter().peekable();
    for (index, seed) in seeds.iter().enumerate() {
        match iter.peek() {
            Some((i, _)) if *i == index => {
                if let Some((_, outcome)) = iter.next() {
                    outcomes.push(outcome);
                }
            }
            _ => outcomes.push(SeedOutcome {
                seed: *seed,
                neighbourhood_size: 0,
                patch_in_camera: None,
                validation: None,
                verdict: Verdict::Skipped,
            }),
        }
    }
    let stop = if covered.load(Ordering::Relaxed) {
        StopReason::CoverageReached
    } else if timed_out.load(Ordering::Relaxed) {
        StopReason::TimeLimit
    } else {
        StopReason::SeedsExhausted
    };
    let cpu = times.lock().map(|t| *t).unwrap_or([0.0; 3]);
    (outcomes, stop, cpu)
}

/// Buffers a worker reuses across its seeds.
struct SeedScratch<'a> {
    indices: &'a mut Vec<u32>,
    column: &'a mut Vec<Vector3<f64>>,
}

/// Steps 11–16 for one seed, and the foothold tests (tilt against `up_in_camera`, the edge test on
/// the foot disc's column of the whole cloud).
#[allow(clippy::too_many_arguments)]
fn process_seed(
    seed: &Seed,
    cloud: &OrganizedCloud,
    intrinsics: &Intrinsics,
    up_in_camera: &Vector3<f64>,
    config: &MapperConfig,
    frame: u64,
    index: usize,
    scratch: SeedScratch,
    cpu_ms: &mut [f64; 3],
) -> SeedOutcome {
    let SeedScratch { indices: scratch, column } = scratch;
    let t0 = Instant::now();
    // Step 11.
    ball_neighbourhood(cloud, intrinsics, &seed.point_in_camera, config.foot_radius_m, scratch);
    let neighbourhood_size = scratch.len();
    let mut rng = StdRng::seed_from_u64(config.seeds.rng_seed ^ (frame << 32) ^ index as u64);
    // Step 12.
    let fit_points = gather(cloud, &uniform_subset(&mut rng, scratch, config.neighbourhood.fit_points));
    let validation_points = gather(cloud, &uniform_subset(&mut rng, scratch, config.neighbourhood.validation_points));
    let t1 = Instant::now();
    cpu_ms[0] += (t1 - t0).as_secs_f64() * 1e3;
    let mut outcome =
        SeedOutcome { seed: *seed, neighbourhood_size, patch_in_camera: None, validation: None, verdict: Verdict::TooFewPoints };
    if neighbourhood_size < config.neighbourhood.min_points.max(1) {
        return outcome;
    }
    // Step 13.
    match fit_neighbourhood(&fit_points, &validation_points, &config.neighbourhood_fit()) {
        Ok(patch) => {
            // Steps 14–16, reported in J's order.
            let t2 = Instant::now();
            let half_height = config.validate.edge_column_height_m;
            let visibility = config.validate.unseen_max_fraction.min(config.validate.open_rim_max_fraction) < f64::INFINITY;
            let mut view = visibility.then(|| DiscView::new(&patch, config.validate.edge_max_offset_m));
            if view.is_some() || config.validate.edge_max_offset_m < f64::INFINITY {
                foot_column(cloud, intrinsics, &patch, up_in_camera, half_height, DEFAULT_MAX_PIXELS, column, view.as_mut());
            }
            let sampled = SampledBall { centre: seed.point_in_camera, radius: config.foot_radius_m };
            let out_of_view = (config.validate.out_of_view_max_fraction < f64::INFINITY)
                .then(|| out_of_view_fraction(&patch, |p| intrinsics.pixel_of(p).is_some()));
            let foothold = Foothold { up: Some(*up_in_camera), column: Some(column.as_slice()), sampled: Some(sampled), view, out_of_view };
            let validation = validate_foothold(&patch, &validation_points, &foothold, &config.validate);
            outcome.verdict = Verdict::from_validation(&validation);
            outcome.patch_in_camera = Some(patch);
            outcome.validation = Some(validation);
            cpu_ms[2] += t2.elapsed().as_secs_f64() * 1e3;
        }
        Err(e) => outcome.verdict = Verdict::FitFailed(e.to_string()),
    }
    cpu_ms[1] += t1.elapsed().as_secs_f64() * 1e3;
    outcome
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::acquire::{gravity_from_dominant_plane, gravity_from_vector};
    use crate::saliency::tests::render;
    use patchwalk_fusion::dataset::{test_data_dir, Dataset};
    use patchwalk_spl::patch::{BoundaryType, SurfaceType};

    /// No tm / ν / DtFP limits. The coverage test is switched off (T_p = N_p): with J's
    /// thresholds it tolerates only ~±2 % error in the boundary size of a perfectly sampled disc
    /// (see `coverage_test_is_strict_about_the_boundary_size`), which the nf = 50 moment boundary
    /// does not reach; these tests check geometry and bookkeeping.
    fn no_limits() -> MapperConfig {
        let mut config = MapperConfig { time_limit_ms: f64::INFINITY, coverage_fraction: f64::INFINITY, ..Default::default() };
        config.saliency.fixation_radius_m = f64::INFINITY;
        config.validate.bad_cell_fraction = 1.0;
        config
    }

    #[test]
    fn coverage_test_is_strict_about_the_boundary_size() {
        // A disc of radius r = 0.05 m sampled on a 2 mm grid (a Kinect at ~1 m).
        let mut points = Vec::new();
        for i in -30..=30 {
            for j in -30..=30 {
                let (x, y) = (f64::from(i) * 0.002 + 0.0003, f64::from(j) * 0.002 + 0.0007);
                if x.hypot(y) <= 0.05 {
                    points.push(Vector3::new(x, y, 1.0));
                }
            }
        }
        let coverage_passes = |d: f64| {
            let patch = Patch::new(
                SurfaceType::Plane,
                BoundaryType::Ellipse,
                vec![d, d],
                nalgebra::Vector2::zeros(),
                Vector3::zeros(),
                Vector3::z(),
            )
            .unwrap();
            patchwalk_spl::validate::validate_patch(&patch, &points, &ValidateConfig::default()).coverage.passed
        };
        assert!(coverage_passes(0.05) && coverage_passes(0.051));
        assert!(!coverage_passes(0.045) && !coverage_passes(0.055));
        // J 3.2.1 step 5 for planes: λ√v = 0.98 r here, IROS eq 30: 1.22 r.
        assert!((patchwalk_spl::fit::neighbourhood::plane_boundary_factor(0.95) - 1.96 / 2.4477).abs() < 1e-3);
    }

    #[test]
    fn seed_dong_is_capped_by_the_tilt_limit_only_when_the_tilt_test_is_on() {
        let config = MapperConfig::default();
        assert!(config.validate.tilt_max_deg < config.saliency.dong_max_deg);
        assert_eq!(seed_saliency_config(&config).dong_max_deg, config.validate.tilt_max_deg);
        let j33 = MapperConfig { validate: ValidateConfig::j33(), ..MapperConfig::default() };
        assert_eq!(seed_saliency_config(&j33), j33.saliency);
        let loose =
            MapperConfig { validate: ValidateConfig { tilt_max_deg: 60.0, ..ValidateConfig::default() }, ..MapperConfig::default() };
        assert_eq!(seed_saliency_config(&loose).dong_max_deg, loose.saliency.dong_max_deg);
    }

    /// Camera 0.5 m above a floor, pitched down by 40°, a spherical rock (radius 0.15 m) ahead.
    fn rock_scene() -> (DepthImage, Intrinsics, Isometry3<f64>, Vector3<f64>, f64) {
        let intrinsics = Intrinsics::primesense_default();
        let pitch = 40f64.to_radians();
        let g = gravity_from_vector(Vector3::new(0.0, pitch.cos(), pitch.sin())).unwrap();
        let up = -g.into_inner();
        let height = 0.5;
        let forward = Vector3::x().cross(&g).normalize();
        let rock = -up * (height - 0.05) + forward * 0.9;
        let depth = render(&intrinsics, |p| (p.dot(&up) + height).min((p - rock).norm() - 0.15));
        let volume_from_camera = single_frame_volume_from_camera(&g, 1.28);
        (depth, intrinsics, volume_from_camera, rock, height)
    }

    #[test]
    fn synthetic_rock_scene_gives_accurate_floor_patches() {
        let (depth, intrinsics, volume_from_camera, _rock, height) = rock_scene();
        let mut mapper = Mapper::new(no_limits(), "map", default_volume_from_map()).unwrap();
        let result = mapper.process(&FrameInput { depth: &depth, intrinsics: &intrinsics, volume_from_camera, timestamp: 1.0 }).unwrap();
        let summary = result.summary();
        assert!(summary.valid >= 15, "{summary:?}");
        assert_eq!(summary.fitted + summary.failed + summary.skipped, summary.seeds);
        // Noise-free synthetic data: sub-millimetre residuals.
        assert!(summary.mean_residual_m() < 1e-3, "{summary:?}");
        // Patches are in the map frame (z up): floor patches lie at z = camera z − height with an
        // upward normal; the map frame origin is the volume corner, the camera is at volume y = 0.
        let camera_in_map = mapper.map.grid().volume_from_map.inverse() * volume_from_camera * nalgebra::Point3::origin();
        let mut floor = 0;
        for mapped in mapper.map.patches() {
            let normal = mapped.patch.normal();
            if (mapped.patch.center.z - (camera_in_map.z - height)).abs() < 0.005 {
                assert!(normal.z > 0.999, "floor normal {normal:?}");
                floor += 1;
            }
            assert!(mapped.cell.is_some());
            assert_eq!(mapped.first_seen, 1.0);
        }
        assert!(floor >= 10, "{floor} floor patches");
        // ng = 1: one patch per cell; the second frame adds none to the full cells.
        let counts = mapper.map.cell_counts();
        assert!(counts.iter().all(|&c| c <= 1));
        let second = mapper.process(&FrameInput { depth: &depth, intrinsics: &intrinsics, volume_from_camera, timestamp: 2.0 }).unwrap();
        assert!(second.outcomes.iter().all(|o| counts[mapper.map.grid().flat(o.seed.cell)] == 0));
        let stats = mapper.map.stats();
        assert_eq!(stats.patches, mapper.map.len());
        assert!(stats.occupied_cells == stats.patches);
    }

    #[test]
    fn the_map_holds_at_most_max_patches_the_newest_kept() {
        let (depth, intrinsics, volume_from_camera, _, _) = rock_scene();
        let mut config = no_limits();
        config.max_patches = 6;
        let mut mapper = Mapper::new(config, "map", default_volume_from_map()).unwrap();
        let first = mapper.process(&FrameInput { depth: &depth, intrinsics: &intrinsics, volume_from_camera, timestamp: 1.0 }).unwrap();
        assert!(first.summary().valid > 6, "{:?}", first.summary());
        assert_eq!(first.evicted, first.summary().valid - 6);
        assert_eq!(mapper.map.len(), 6);
        // Cells freed by the eviction take seeds again; the patches of the newer frame are kept.
        let second = mapper.process(&FrameInput { depth: &depth, intrinsics: &intrinsics, volume_from_camera, timestamp: 2.0 }).unwrap();
        assert!(second.summary().valid >= 6 && second.evicted > 0, "{:?}", second.summary());
        assert_eq!(mapper.map.len(), 6);
        assert!(mapper.map.patches().iter().all(|p| p.last_seen == 2.0));
        config = no_limits();
        config.max_patches = 0;
        assert!(matches!(Mapper::new(config, "map", default_volume_from_map()), Err(MapperError::Config(_))));
    }

    #[test]
    fn limits_stop_stage_v() {
        let (depth, intrinsics, volume_from_camera, _, _) = rock_scene();
        let mut config = no_limits();
        config.coverage_fraction = 1e-4;
        let mut mapper = Mapper::new(config, "map", default_volume_from_map()).unwrap();
        let result = mapper.process(&FrameInput { depth: &depth, intrinsics: &intrinsics, volume_from_camera, timestamp: 0.0 }).unwrap();
        assert_eq!(result.target_patches, 1);
        assert_eq!(result.stop, StopReason::CoverageReached);
        assert!(result.summary().valid <= rayon::current_num_threads());
        assert!(result.summary().skipped > 0);
        let mut config = no_limits();
        config.time_limit_ms = 0.0;
        let mut mapper = Mapper::new(config, "map", default_volume_from_map()).unwrap();
        let result = mapper.process(&FrameInput { depth: &depth, intrinsics: &intrinsics, volume_from_camera, timestamp: 0.0 }).unwrap();
        assert_eq!(result.stop, StopReason::TimeLimit);
        assert_eq!(result.summary().skipped, result.outcomes.len());
        assert!(mapper.map.is_empty());
        assert!(Mapper::new(MapperConfig { foot_radius_m: -1.0, ..Default::default() }, "map", default_volume_from_map()).is_err());
    }

    #[test]
    fn real_frames_give_table_2_like_statistics() {
        for name in ["tum_fr1_xyz", "open3d_rgbd", "cape_tunnel/depth_0.png"] {
            let dataset = Dataset::open(&test_data_dir().join(name)).unwrap();
            let depth = dataset.load_depth(0).unwrap();
            let cloud = organized_cloud(&depth, &dataset.intrinsics).unwrap();
            let g = gravity_from_dominant_plane(&cloud, 0.02, 1).unwrap();
            let mut config = no_limits();
            config.seeds.per_cell = 4;
            config.volume_edge_m = 3.0;
            let mut mapper = Mapper::new(config, "map", default_volume_from_map()).unwrap();
            let volume_from_camera = single_frame_volume_from_camera(&g, 3.0);
            let input = FrameInput { depth: &depth, intrinsics: &dataset.intrinsics, volume_from_camera, timestamp: 0.0 };
            let result = mapper.process(&input).unwrap();
            let s = result.summary();
            assert!(s.fitted >= 10, "{name}: {s:?}");
            assert!(s.valid * 2 >= s.fitted, "{name}: most salient patches are valid: {s:?}");
            assert!(s.mean_residual_m() < 0.005, "{name}: {s:?}");
            assert_eq!(mapper.map.len(), s.valid);
        }
    }

    #[test]
    fn the_marked_rectangle_holds_the_image_of_the_ball() {
        let intrinsics = Intrinsics::primesense_default().scaled(0.5);
        for (centre, radius) in
            [(Vector3::new(0.1, -0.2, 0.9), 0.15), (Vector3::new(-0.5, 0.3, 1.2), 0.1), (Vector3::new(2.0, 0.0, 1.0), 0.2)]
        {
            let mut region = vec![false; intrinsics.width * intrinsics.height];
            mark_ball(&mut region, &intrinsics, &centre, radius);
            let mut inside = 0;
            for i in 0..2000 {
                // Points spread over the ball (a deterministic spiral of directions and radii).
                let (a, b, r) = (i as f64 * 2.399, (i as f64 / 2000.0 * 2.0 - 1.0).acos(), radius * ((i % 7) as f64 / 6.0));
                let point = centre + Vector3::new(b.sin() * a.cos(), b.sin() * a.sin(), b.cos()) * r;
                if let Some((u, v)) = intrinsics.pixel_of(&point) {
                    assert!(region[v * intrinsics.width + u], "{point:?} at ({u}, {v}) not marked");
                    inside += 1;
                }
            }
            assert!(inside > 0 || centre.x > 1.0);
            let marked = region.iter().filter(|m| **m).count();
            assert!(marked < region.len() / 2, "{marked}");
        }
        // A ball reaching the camera's plane marks everything.
        let mut region = vec![false; 12];
        mark_ball(&mut region, &Intrinsics::new(4, 3, 2.0, 2.0, 1.5, 1.0).unwrap(), &Vector3::new(0.0, 0.0, 0.1), 0.2);
        assert!(region.iter().all(|m| *m));
    }
}

//! `patch_mapper map`: the single-frame patch mapper (J 4, stages i–v) run offline over a TUM
//! directory, a directory of depth PNGs with an intrinsics JSON, or one PNG. Writes the patches as
//! JSON lines, a picture per frame (patches coloured as J Fig. 6) and the saliency mask, and prints
//! a summary like J Table 2.
//!
//! Gravity (in the camera frame) comes from, in order: `--gravity x,y,z`; the dataset's
//! accelerometer, through `mapper.acquire.camera_from_imu` when that rotation is configured (not the
//! identity), else through a rotation calibrated on the dataset (J 2.2); otherwise the ground plane
//! of the frame: of its dominant planes, the largest consistent with the camera's nominal down
//! (`mapper.acquire.plane_prior`), never a wall.
//!
//! The fixation point and the seed area follow the rig: the camera height above the ground plane
//! (the plane perpendicular to gravity) and the camera pitch give the fixation point two steps ahead
//! on the ground ([`patchwalk_mapping::rig`]), and the single-frame volume is centred on it.
//! `--camera-height` gives the height instead; `--fixed-fixation` keeps the configured
//! `mapper.saliency.fixation_*_m` and the volume at the camera.

use std::io::Write;
use std::path::{Path, PathBuf};

use anyhow::{bail, Context, Result};
use nalgebra::{Unit, Vector3};
use patchwalk_fusion::dataset::Dataset;
use patchwalk_mapping::acquire::{
    gravity_from_accelerometer, gravity_from_ground_plane, gravity_from_vector, ground_plane, organized_cloud,
};
use patchwalk_mapping::mapper::{
    default_volume_from_map, single_frame_volume_from_camera, FrameInput, FrameResult, FrameSummary, Mapper, MapperConfig, StageTimings,
    Verdict,
};
use patchwalk_mapping::record::PatchRecord;
use patchwalk_mapping::render::{render_patches, render_saliency};
use patchwalk_mapping::rig::{volume_from_camera_at_fixation, RigEstimate};
use serde::Serialize;

/// Arguments of `patch_mapper map`.
#[derive(clap::Args, Debug)]
pub struct MapArgs {
    /// TUM directory (depth.txt [+ accelerometer.txt]), directory of depth PNGs with an intrinsics
    /// JSON, or one depth PNG (with a JSON or calib_params.xml beside it).
    pub input: PathBuf,
    /// YAML whose `mapper:` section configures the mapper (as in config/patch_mapper.yaml); missing
    /// keys take J's defaults.
    #[arg(long)]
    pub config: Option<PathBuf>,
    /// Output directory for patches.jsonl and the pictures.
    #[arg(long, default_value = "map_out")]
    pub out: PathBuf,
    /// Gravity (down) in the camera frame, e.g. `0,0.79,0.62`; overrides every other source.
    #[arg(long, value_parser = super::parse_vec3, allow_hyphen_values = true)]
    pub gravity: Option<Vector3<f64>>,
    /// Where gravity comes from without --gravity: auto (the accelerometer when the data has one,
    /// else the ground plane), imu (accelerometer through mapper.acquire.camera_from_imu, or a
    /// rotation calibrated on the data when that is the identity) or plane (the dominant plane
    /// consistent with mapper.acquire.plane_prior).
    #[arg(long, default_value = "auto")]
    pub gravity_source: String,
    /// Neighbourhood radius r (m), overriding the config (J: 0.05 RPBP foot, 0.1 human data).
    #[arg(long)]
    pub radius: Option<f64>,
    /// Disable the DtFP region of interest (keep the DoN/DoNG filters).
    #[arg(long)]
    pub no_dtfp: bool,
    /// Camera height above the ground (m) for the fixation point and seed area, instead of the
    /// distance to the frame's ground plane.
    #[arg(long)]
    pub camera_height: Option<f64>,
    /// Keep the configured fixation point (mapper.saliency.fixation_down_m / fixation_forward_m)
    /// and the single-frame volume at the camera instead of following the rig.
    #[arg(long)]
    pub fixed_fixation: bool,
    /// Process at most this many frames.
    #[arg(long)]
    pub max_frames: Option<usize>,
    /// Process every n-th frame.
    #[arg(long, default_value_t = 1)]
    pub step: usize,
    /// Skip writing pictures.
    #[arg(long)]
    pub no_pictures: bool,
}

/// The part of a configuration file `map` reads: its `mapper:` section (other sections, such as the
/// node's `ros:`, are ignored).
#[derive(serde::Deserialize, Default)]
#[serde(default)]
struct MapFile {
    mapper: MapperConfig,
}

/// Loads a MapperConfig from the `mapper:` section of a YAML file, laid over J's defaults, with the
/// nodes' loader (unknown keys are errors naming the key).
pub fn load_config(path: &Path) -> Result<MapperConfig> {
    let file: MapFile =
        patchwalk_ros::params::load_config(Some(path), &[]).with_context(|| format!("{}: invalid mapper configuration", path.display()))?;
    Ok(file.mapper)
}

/// One JSON line of patches.jsonl: a fitted patch (valid or rejected by J 3.3, Fig. 6) and where
/// it came from.
#[derive(Serialize)]
struct PatchLine<'a> {
    frame: usize,
    timestamp: f64,
    /// Map id of valid patches.
    id: Option<u64>,
    /// Seed cell `[ix, iz]` on the volume grid.
    cell: [usize; 2],
    /// The patch pose is in this frame.
    frame_id: &'a str,
    neighbourhood_points: usize,
    #[serde(flatten)]
    record: PatchRecord,
}

pub fn run(args: MapArgs) -> Result<()> {
    let mut config = match &args.config {
        Some(path) => load_config(path)?,
        None => MapperConfig::default(),
    };
    if let Some(r) = args.radius {
        if !(r.is_finite() && r > 0.0) {
            bail!("--radius must be positive, got {r}");
        }
        config.foot_radius_m = r;
    }
    if args.no_dtfp {
        config.saliency.fixation_radius_m = f64::INFINITY;
    }
    if args.step == 0 {
        bail!("--step must be at least 1");
    }
    let dataset = Dataset::open(&args.input).with_context(|| format!("opening {}", args.input.display()))?;
    let frames: Vec<usize> = (0..dataset.frames.len()).step_by(args.step).take(args.max_frames.unwrap_or(usize::MAX)).collect();
    if frames.is_empty() {
        bail!("{}: no frames", args.input.display());
    }
    std::fs::create_dir_all(&args.out).with_context(|| format!("creating {}", args.out.display()))?;
    let jsonl_path = args.out.join("patches.jsonl");
    let mut jsonl =
        std::io::BufWriter::new(std::fs::File::create(&jsonl_path).with_context(|| format!("creating {}", jsonl_path.display()))?);
    if let Some(h) = args.camera_height {
        if !(h.is_finite() && h > 0.0) {
            bail!("--camera-height must be positive, got {h}");
        }
    }
    config.acquire.plane_prior.validate()?;
    let configured_camera_from_imu = config.acquire.camera_from_imu()?;
    let source = match (args.gravity.is_some(), args.gravity_source.as_str()) {
        (true, _) => "--gravity".to_string(),
        (false, "imu" | "auto") if !dataset.accelerometer.is_empty() => "imu".to_string(),
        (false, "imu") => bail!("--gravity-source imu: {} has no accelerometer", args.input.display()),
        (false, "auto" | "plane") => "plane".to_string(),
        (false, other) => bail!("--gravity-source must be auto, imu or plane, got '{other}'"),
    };
    let (camera_from_imu, source) = if source == "imu" {
        match super::dataset_camera_from_imu(&dataset, &configured_camera_from_imu) {
            (Some(rotation), how) => (rotation, format!("the accelerometer ({how})")),
            (None, why) if args.gravity_source == "auto" => {
                eprintln!("warning: {why}; gravity from the ground plane instead");
                (configured_camera_from_imu, "plane".to_string())
            }
            (None, why) => bail!("--gravity-source imu: {why}"),
        }
    } else {
        (configured_camera_from_imu, source)
    };
    let source = if source == "plane" { "the ground plane".to_string() } else { source };
    let mut warnings = Warnings::default();
    let progress = (frames.len() > 1).then(|| {
        let bar = indicatif::ProgressBar::new(frames.len() as u64);
        bar.set_style(
            indicatif::ProgressStyle::with_template("{bar:40} {pos}/{len} frames {elapsed_precise} eta {eta} {msg}")
                .unwrap_or_else(|_| indicatif::ProgressStyle::default_bar()),
        );
        bar
    });
    let mut rows = Vec::new();
    for &index in &frames {
        let frame = &dataset.frames[index];
        let depth = dataset.load_depth(index)?;
        let gravity = match frame_gravity(&args, &source, &dataset, index, &depth, &camera_from_imu, &config) {
            Ok(gravity) => gravity,
            Err(err) => {
                // A frame without gravity (e.g. no floor in view) is skipped; the others map.
                warnings.once("gravity", format!("frame {index}: {err:#}; frame skipped"));
                warnings.skipped += 1;
                if let Some(bar) = &progress {
                    bar.inc(1);
                }
                continue;
            }
        };
        let mut frame_config = config.clone();
        let rig = if args.fixed_fixation { None } else { frame_rig(&args, &dataset, index, &depth, &gravity, &mut warnings) };
        let volume_from_camera = match rig {
            Some(rig) => {
                let (down, forward) = rig.fixation_distances(&dataset.intrinsics);
                frame_config.saliency.fixation_down_m = down;
                frame_config.saliency.fixation_forward_m = forward;
                volume_from_camera_at_fixation(&gravity, config.volume_edge_m, down, forward)
            }
            None => single_frame_volume_from_camera(&gravity, config.volume_edge_m),
        };
        let mut mapper = Mapper::new(frame_config, "camera_optical", default_volume_from_map())?;
        let result = mapper.process(&FrameInput {
            depth: &depth,
            intrinsics: &dataset.intrinsics,
            volume_from_camera,
            timestamp: frame.timestamp,
        })?;
        write_patches(&mut jsonl, index, frame.timestamp, &result)?;
        if !args.no_pictures {
            render_patches(&depth, &dataset.intrinsics, &result.outcomes)
                .save_png(&args.out.join(format!("frame_{index:05}_patches.png")))?;
            render_saliency(&result.saliency).save_png(&args.out.join(format!("frame_{index:05}_saliency.png")))?;
        }
        let summary = result.summary();
        if let Some(reason) = &result.saliency.dtfp_fallback {
            warnings.once("dtfp", format!("frame {index}: {reason}"));
        }
        if result.outcomes.is_empty() {
            let salient = result.saliency.count(patchwalk_mapping::saliency::SaliencyLabel::Salient);
            let why = if salient == 0 {
                "no salient point (every valid point is steep or irregular)".to_string()
            } else {
                format!("none of the {salient} salient points lies in the {} m seed volume", config.volume_edge_m)
            };
            warnings.once("seeds", format!("frame {index}: no seeds: {why}"));
        }
        if let Some(bar) = &progress {
            bar.set_message(format!("{} valid", summary.valid));
            bar.inc(1);
        }
        rows.push((index, summary, result.timings, gravity, rig));
    }
    if let Some(bar) = progress {
        bar.finish_and_clear();
    }
    jsonl.flush()?;
    print_table(&args, &source, &rows);
    warnings.print_counts();
    println!(
        "patches: {}   pictures: {}",
        jsonl_path.display(),
        if args.no_pictures { "none".to_string() } else { args.out.display().to_string() }
    );
    Ok(())
}

fn frame_gravity(
    args: &MapArgs,
    source: &str,
    dataset: &Dataset,
    index: usize,
    depth: &patchwalk_fusion::camera::DepthImage,
    camera_from_imu: &nalgebra::Rotation3<f64>,
    config: &MapperConfig,
) -> Result<Unit<Vector3<f64>>> {
    if let Some(g) = args.gravity {
        return Ok(gravity_from_vector(g)?);
    }
    if source.starts_with("the accelerometer") {
        let timestamp = dataset.frames[index].timestamp;
        let acceleration = dataset
            .acceleration_near(timestamp, 0.05)
            .with_context(|| format!("no accelerometer samples near frame {index} (t = {timestamp:.3})"))?;
        return Ok(gravity_from_accelerometer(&acceleration, camera_from_imu)?);
    }
    let cloud = organized_cloud(depth, &dataset.intrinsics)?;
    Ok(gravity_from_ground_plane(&cloud, 0.02, &config.acquire.plane_prior, index as u64)?)
}

/// Largest angle (degrees) between gravity and the normal of the plane taken as the ground for the
/// camera height.
const GROUND_TOLERANCE_DEG: f64 = 15.0;

/// The rig of one frame: `--camera-height` or the distance to the ground plane perpendicular to
/// gravity, with the pitch from gravity. `None` (and a warning) when the frame shows no such plane.
fn frame_rig(
    args: &MapArgs,
    dataset: &Dataset,
    index: usize,
    depth: &patchwalk_fusion::camera::DepthImage,
    gravity: &Unit<Vector3<f64>>,
    warnings: &mut Warnings,
) -> Option<RigEstimate> {
    let height = match args.camera_height {
        Some(h) => Ok(h),
        None => organized_cloud(depth, &dataset.intrinsics)
            .map_err(anyhow::Error::from)
            .and_then(|cloud| Ok(ground_plane(&cloud, 0.02, gravity, GROUND_TOLERANCE_DEG, index as u64)?.distance_m)),
    };
    match height.and_then(|h| Ok(RigEstimate::new(h, gravity)?)) {
        Ok(rig) => Some(rig),
        Err(err) => {
            warnings.once(
                "rig",
                format!("frame {index}: no camera height ({err:#}); the configured fixation point is used (give --camera-height)"),
            );
            None
        }
    }
}

/// Warnings printed once per kind (the first occurrence, naming the frame), counted for the end.
#[derive(Default)]
struct Warnings {
    counts: std::collections::BTreeMap<&'static str, usize>,
    skipped: usize,
}

impl Warnings {
    fn once(&mut self, kind: &'static str, message: String) {
        let count = self.counts.entry(kind).or_default();
        if *count == 0 {
            eprintln!("warning: {message}");
        }
        *count += 1;
    }

    fn print_counts(&self) {
        for (kind, count) in self.counts.iter().filter(|(_, &n)| n > 1) {
            eprintln!("warning: the '{kind}' warning above applied to {count} frames");
        }
        if self.skipped > 0 {
            eprintln!("warning: {} frames skipped (no gravity)", self.skipped);
        }
    }
}

fn write_patches(out: &mut impl Write, frame: usize, timestamp: f64, result: &FrameResult) -> Result<()> {
    for outcome in &result.outcomes {
        let Some(patch) = &outcome.patch_in_camera else { continue };
        let id = match &outcome.verdict {
            Verdict::Valid { id } => Some(*id),
            Verdict::Residual | Verdict::Coverage | Verdict::Curvature | Verdict::Tilt | Verdict::Edge | Verdict::Unseen => None,
            _ => continue,
        };
        let line = PatchLine {
            frame,
            timestamp,
            id,
            cell: [outcome.seed.cell.0, outcome.seed.cell.1],
            frame_id: "camera_optical",
            neighbourhood_points: outcome.neighbourhood_size,
            record: PatchRecord::with_verdict(patch.clone(), &outcome.verdict, outcome.validation.as_ref()),
        };
        serde_json::to_writer(&mut *out, &line)?;
        out.write_all(b"\n")?;
    }
    Ok(())
}

/// J Table 2-like table: one row per frame and the total.
/// One frame's row of the table: index, counts, times, gravity and the rig estimate.
type FrameRow = (usize, FrameSummary, StageTimings, Unit<Vector3<f64>>, Option<RigEstimate>);

fn print_table(args: &MapArgs, source: &str, rows: &[FrameRow]) {
    println!("patch mapping of {} ({} frames, gravity from {source})", args.input.display(), rows.len());
    let rigs: Vec<&RigEstimate> = rows.iter().filter_map(|row| row.4.as_ref()).collect();
    if let (Some(first), false) = (rigs.first(), rigs.is_empty()) {
        let n = rigs.len() as f64;
        let height = rigs.iter().map(|r| r.camera_height_m).sum::<f64>() / n;
        let pitch = rigs.iter().map(|r| r.pitch_deg).sum::<f64>() / n;
        println!(
            "rig: camera {height:.2} m above the ground, pitched {pitch:.0}° down (mean of {} frames; first frame {:.2} m, {:.0}°)",
            rigs.len(),
            first.camera_height_m,
            first.pitch_deg
        );
    }
    println!(
        "{:>6} {:>6} {:>6} {:>6} {:>8} {:>8} {:>9} {:>9} {:>9} {:>11} {:>6} {:>8} {:>9} {:>7} {:>7} {:>8}",
        "frame",
        "seeds",
        "total",
        "valid",
        "drop:res",
        "drop:cov",
        "drop:curv",
        "drop:tilt",
        "drop:edge",
        "drop:unseen",
        "failed",
        "avg res",
        "area",
        "pre ms",
        "sal ms",
        "fit ms"
    );
    let mut total = FrameSummary::default();
    let mut times = StageTimings::default();
    for (index, s, t, _, _) in rows {
        total.add(s);
        times.preprocess_ms += t.preprocess_ms;
        times.saliency_ms += t.saliency_ms;
        times.fit_stage_ms += t.fit_stage_ms;
        if rows.len() <= 40 {
            println!(
                "{:>6} {:>6} {:>6} {:>6} {:>8} {:>8} {:>9} {:>9} {:>9} {:>11} {:>6} {:>6.2}mm {:>7.4}m² {:>7.1} {:>7.1} {:>8.1}",
                index,
                s.seeds,
                s.fitted,
                s.valid,
                s.residual,
                s.coverage,
                s.curvature,
                s.tilt,
                s.edge,
                s.unseen,
                s.failed,
                s.mean_residual_m() * 1e3,
                s.area_m2,
                t.preprocess_ms,
                t.saliency_ms,
                t.fit_stage_ms
            );
        }
    }
    let n = rows.len().max(1) as f64;
    println!(
        "{:>6} {:>6} {:>6} {:>6} {:>8} {:>8} {:>9} {:>9} {:>9} {:>11} {:>6} {:>6.2}mm {:>7.4}m² {:>7.1} {:>7.1} {:>8.1}",
        "total",
        total.seeds,
        total.fitted,
        total.valid,
        total.residual,
        total.coverage,
        total.curvature,
        total.tilt,
        total.edge,
        total.unseen,
        total.failed,
        total.mean_residual_m() * 1e3,
        total.area_m2,
        times.preprocess_ms / n,
        times.saliency_ms / n,
        times.fit_stage_ms / n
    );
    if total.fitted > 0 {
        println!(
            "valid {:.0} %; dropped by residual {:.0} %, coverage {:.0} %, curvature {:.0} %, tilt {:.0} %, edge {:.0} %, unseen {:.0} % (times: per-frame means)",
            100.0 * total.valid as f64 / total.fitted as f64,
            100.0 * total.residual as f64 / total.fitted as f64,
            100.0 * total.coverage as f64 / total.fitted as f64,
            100.0 * total.curvature as f64 / total.fitted as f64,
            100.0 * total.tilt as f64 / total.fitted as f64,
            100.0 * total.edge as f64 / total.fitted as f64,
            100.0 * total.unseen as f64 / total.fitted as f64
        );
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use nalgebra::Vector2;
    use patchwalk_spl::patch::{BoundaryType, Patch, SurfaceType};

    #[test]
    fn patch_lines_parse_into_the_patch_record() {
        let patch = Patch::new(
            SurfaceType::Plane,
            BoundaryType::Circle,
            vec![0.05],
            Vector2::zeros(),
            Vector3::zeros(),
            Vector3::new(0.0, 0.0, 1.0),
        )
        .unwrap();
        for verdict in [Verdict::Valid { id: 3 }, Verdict::Coverage, Verdict::FitFailed("degenerate".into())] {
            let line = PatchLine {
                frame: 1,
                timestamp: 0.5,
                id: None,
                cell: [2, 3],
                frame_id: "camera_optical",
                neighbourhood_points: 40,
                record: PatchRecord::with_verdict(patch.clone(), &verdict, None),
            };
            let text = serde_json::to_string(&line).unwrap();
            let record: PatchRecord = serde_json::from_str(&text).unwrap();
            assert_eq!((record.valid, record.verdict.as_str()), (verdict.is_valid(), verdict.name()), "{text}");
            assert_eq!(record.patch, patch);
        }
    }

    #[test]
    fn config_files_are_laid_over_the_defaults_and_reject_unknown_keys() {
        let dir = tempfile::tempdir().unwrap();
        let empty = dir.path().join("empty.yaml");
        std::fs::write(&empty, "# only comments\n").unwrap();
        assert_eq!(load_config(&empty).unwrap(), MapperConfig::default());
        let section = dir.path().join("section.yaml");
        std::fs::write(&section, "mapper:\n  time_limit_ms: 50.0\n").unwrap();
        assert_eq!(load_config(&section).unwrap(), MapperConfig { time_limit_ms: 50.0, ..MapperConfig::default() });
        let bad = dir.path().join("bad.yaml");
        std::fs::write(&bad, "mapper:\n  seeds:\n    cells: 4\n").unwrap();
        let message = format!("{:#}", load_config(&bad).unwrap_err());
        assert!(message.contains("cells"), "{message}");
    }

    /// `patch_mapper map` with default flags on a shared dataset: the number of valid patches written.
    fn valid_patches_with_default_flags(input: &str) -> usize {
        let out = tempfile::tempdir().unwrap();
        let args = MapArgs {
            input: patchwalk_fusion::dataset::test_data_dir().join(input),
            config: None,
            out: out.path().to_path_buf(),
            gravity: None,
            gravity_source: "auto".into(),
            radius: None,
            no_dtfp: false,
            camera_height: None,
            fixed_fixation: false,
            max_frames: Some(4),
            step: 9,
            no_pictures: true,
        };
        run(args).unwrap();
        let text = std::fs::read_to_string(out.path().join("patches.jsonl")).unwrap();
        text.lines().map(|line| serde_json::from_str::<PatchRecord>(line).unwrap()).filter(|r| r.valid).count()
    }

    #[test]
    fn default_flags_map_every_shared_dataset() {
        // Real frames from a desk-height Kinect (TUM, with an accelerometer), a hand-held PrimeSense
        // (Open3D) and a tunnel (CAPE): none gives 0 valid patches with the default flags.
        for input in ["tum_fr1_xyz", "open3d_rgbd", "cape_tunnel/depth_0.png"] {
            let valid = valid_patches_with_default_flags(input);
            assert!(valid > 0, "{input}: {valid} valid patches");
        }
    }
}

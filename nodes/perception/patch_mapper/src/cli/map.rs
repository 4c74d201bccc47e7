//! `patch_mapper map`: the single-frame patch mapper (J 4, stages i–v) run offline over a TUM
//! directory, a directory of depth PNGs with an intrinsics JSON, or one PNG. Writes the patches as
//! JSON lines, a picture per frame (patches coloured as J Fig. 6) and the saliency mask, and prints
//! a summary like J Table 2.
//!
//! Gravity (in the camera frame) comes from, in order: `--gravity x,y,z`; the dataset's
//! accelerometer through `mapper.acquire.camera_from_imu` when that rotation is configured (not the
//! identity) or `--gravity-source imu` is given; otherwise the normal of the frame's dominant plane
//! (valid when a horizontal floor or table dominates the view, J 2.2's calibration assumption).

use std::io::Write;
use std::path::{Path, PathBuf};

use anyhow::{bail, Context, Result};
use nalgebra::{Matrix3, Unit, Vector3};
use patchwalk_fusion::dataset::Dataset;
use patchwalk_mapping::acquire::{gravity_from_accelerometer, gravity_from_dominant_plane, gravity_from_vector, organized_cloud};
use patchwalk_mapping::mapper::{
    default_volume_from_map, single_frame_volume_from_camera, FrameInput, FrameResult, FrameSummary, Mapper, MapperConfig, StageTimings,
    Verdict,
};
use patchwalk_mapping::record::PatchRecord;
use patchwalk_mapping::render::{render_patches, render_saliency};
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
    /// Where gravity comes from without --gravity: auto, imu (accelerometer through
    /// mapper.acquire.camera_from_imu) or plane (dominant plane normal).
    #[arg(long, default_value = "auto")]
    pub gravity_source: String,
    /// Neighbourhood radius r (m), overriding the config (J: 0.05 RPBP foot, 0.1 human data).
    #[arg(long)]
    pub radius: Option<f64>,
    /// Disable the DtFP region of interest (keep the DoN/DoNG filters).
    #[arg(long)]
    pub no_dtfp: bool,
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
    let camera_from_imu = config.acquire.camera_from_imu()?;
    let imu_configured = camera_from_imu.matrix() != &Matrix3::identity();
    let source = match (args.gravity.is_some(), args.gravity_source.as_str()) {
        (true, _) => "--gravity",
        (false, "imu") => "imu",
        (false, "plane") => "plane",
        (false, "auto") if imu_configured && !dataset.accelerometer.is_empty() => "imu",
        (false, "auto") => "plane",
        (false, other) => bail!("--gravity-source must be auto, imu or plane, got '{other}'"),
    };
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
        let gravity = frame_gravity(&args, source, &dataset, index, &depth, &camera_from_imu)?;
        let volume_from_camera = single_frame_volume_from_camera(&gravity, config.volume_edge_m);
        let mut mapper = Mapper::new(config.clone(), "camera_optical", default_volume_from_map())?;
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
        if let Some(bar) = &progress {
            bar.set_message(format!("{} valid", summary.valid));
            bar.inc(1);
        }
        rows.push((index, summary, result.timings, gravity));
    }
    if let Some(bar) = progress {
        bar.finish_and_clear();
    }
    jsonl.flush()?;
    print_table(&args, source, &rows);
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
) -> Result<Unit<Vector3<f64>>> {
    if let Some(g) = args.gravity {
        return Ok(gravity_from_vector(g)?);
    }
    if source == "imu" {
        let timestamp = dataset.frames[index].timestamp;
        let acceleration = dataset
            .mean_acceleration_near(timestamp, 0.05)
            .with_context(|| format!("no accelerometer samples near frame {index} (t = {timestamp:.3})"))?;
        return Ok(gravity_from_accelerometer(&acceleration, camera_from_imu)?);
    }
    let cloud = organized_cloud(depth, &dataset.intrinsics)?;
    gravity_from_dominant_plane(&cloud, 0.02, index as u64).with_context(|| format!("frame {index}: no gravity (try --gravity x,y,z)"))
}

fn write_patches(out: &mut impl Write, frame: usize, timestamp: f64, result: &FrameResult) -> Result<()> {
    for outcome in &result.outcomes {
        let Some(patch) = &outcome.patch_in_camera else { continue };
        let id = match &outcome.verdict {
            Verdict::Valid { id } => Some(*id),
            Verdict::Residual | Verdict::Coverage | Verdict::Curvature | Verdict::Tilt | Verdict::Edge => None,
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
fn print_table(args: &MapArgs, source: &str, rows: &[(usize, FrameSummary, StageTimings, Unit<Vector3<f64>>)]) {
    println!("patch mapping of {} ({} frames, gravity from {source})", args.input.display(), rows.len());
    println!(
        "{:>6} {:>6} {:>6} {:>6} {:>8} {:>8} {:>9} {:>9} {:>9} {:>6} {:>8} {:>9} {:>7} {:>7} {:>8}",
        "frame",
        "seeds",
        "total",
        "valid",
        "drop:res",
        "drop:cov",
        "drop:curv",
        "drop:tilt",
        "drop:edge",
        "failed",
        "avg res",
        "area",
        "pre ms",
        "sal ms",
        "fit ms"
    );
    let mut total = FrameSummary::default();
    let mut times = StageTimings::default();
    for (index, s, t, _) in rows {
        total.add(s);
        times.preprocess_ms += t.preprocess_ms;
        times.saliency_ms += t.saliency_ms;
        times.fit_stage_ms += t.fit_stage_ms;
        if rows.len() <= 40 {
            println!(
                "{:>6} {:>6} {:>6} {:>6} {:>8} {:>8} {:>9} {:>9} {:>9} {:>6} {:>6.2}mm {:>7.4}m² {:>7.1} {:>7.1} {:>8.1}",
                index,
                s.seeds,
                s.fitted,
                s.valid,
                s.residual,
                s.coverage,
                s.curvature,
                s.tilt,
                s.edge,
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
        "{:>6} {:>6} {:>6} {:>6} {:>8} {:>8} {:>9} {:>9} {:>9} {:>6} {:>6.2}mm {:>7.4}m² {:>7.1} {:>7.1} {:>8.1}",
        "total",
        total.seeds,
        total.fitted,
        total.valid,
        total.residual,
        total.coverage,
        total.curvature,
        total.tilt,
        total.edge,
        total.failed,
        total.mean_residual_m() * 1e3,
        total.area_m2,
        times.preprocess_ms / n,
        times.saliency_ms / n,
        times.fit_stage_ms / n
    );
    if total.fitted > 0 {
        println!(
            "valid {:.0} %; dropped by residual {:.0} %, coverage {:.0} %, curvature {:.0} %, tilt {:.0} %, edge {:.0} % (times: per-frame means)",
            100.0 * total.valid as f64 / total.fitted as f64,
            100.0 * total.residual as f64 / total.fitted as f64,
            100.0 * total.coverage as f64 / total.fitted as f64,
            100.0 * total.curvature as f64 / total.fitted as f64,
            100.0 * total.tilt as f64 / total.fitted as f64,
            100.0 * total.edge as f64 / total.fitted as f64
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
}

//! `patch_mapper replay <dataset>`: the node's whole per-frame pipeline (gravity from the IMU, TSDF
//! fusion + ICP, moving volume, birds-eye raycast, patch mapping and tracking) run offline over a
//! recorded dataset, with the node's configuration (`config/patch_mapper.yaml` + `--param`).
//! What the node would publish, without ROS: the final patch map as JSON lines, every seed's
//! verdict per frame, the trajectory, and birds-eye pictures with the frame's patches (J Fig. 6
//! colours). With ground truth (`groundtruth.txt`, e.g. from `terrain_sim record`) the patches are
//! also given in the dataset's world frame, to compare with the scene's footholds.

use std::io::Write;
use std::path::PathBuf;

use anyhow::{Context, Result};
use indicatif::{ProgressBar, ProgressStyle};
use nalgebra::Isometry3;
use patchwalk_fusion::dataset::{write_tum_poses, Dataset, StampedPose};
use patchwalk_mapping::mapper::FrameSummary;
use patchwalk_mapping::pipeline::{birds_eye_points_in_map, Pipeline};
use patchwalk_mapping::record::PatchRecord;
use patchwalk_mapping::render::render_patches;
use patchwalk_spl::transform::transform_patch;
use serde::Serialize;

use crate::ros::PatchMapperConfig;

/// Arguments of `patch_mapper replay`.
#[derive(clap::Args, Debug)]
pub struct ReplayArgs {
    /// Dataset: TUM directory (depth.txt + accelerometer.txt [+ groundtruth.txt]).
    pub dataset: PathBuf,
    /// The node's YAML configuration (config/patch_mapper.yaml); embedded defaults when omitted.
    #[arg(long)]
    pub config: Option<PathBuf>,
    /// Override `dotted.key=value` (YAML value), as for `patch_mapper run`.
    #[arg(short = 'p', long = "param", value_name = "KEY=VALUE")]
    pub params: Vec<String>,
    /// Output directory for patches.jsonl, seeds.jsonl, trajectory.txt and pictures.
    #[arg(long, default_value = "replay_out")]
    pub out: PathBuf,
    /// Write a birds-eye picture every n frames (0: only the last frame).
    #[arg(long, default_value_t = 10)]
    pub picture_every: usize,
    /// Process at most this many frames.
    #[arg(long)]
    pub max_frames: Option<usize>,
}

/// One line of seeds.jsonl: a seed's patch (map frame) and what validation said.
#[derive(Serialize)]
struct SeedLine {
    frame: usize,
    neighbourhood_points: usize,
    /// Seed point in the map frame.
    seed_in_map: [f64; 3],
    /// Patch centre in the dataset's world frame (with ground truth).
    center_in_world: Option<[f64; 3]>,
    #[serde(flatten)]
    record: PatchRecord,
}

/// One line of patches.jsonl: a patch of the final map.
#[derive(Serialize)]
struct MapLine {
    id: u64,
    first_seen: f64,
    last_seen: f64,
    center_in_world: Option<[f64; 3]>,
    normal_in_world: Option<[f64; 3]>,
    #[serde(flatten)]
    record: PatchRecord,
}

pub fn run(args: ReplayArgs) -> Result<()> {
    let config: PatchMapperConfig = patchwalk_ros::params::load_config(args.config.as_deref(), &args.params)?;
    let dataset = Dataset::open(&args.dataset).with_context(|| format!("opening {}", args.dataset.display()))?;
    let mut pipeline = Pipeline::new(config.pipeline.clone(), config.tracker.clone(), config.mapper.clone(), dataset.intrinsics)?;
    std::fs::create_dir_all(&args.out).with_context(|| format!("creating {}", args.out.display()))?;
    let seeds_path = args.out.join("seeds.jsonl");
    let mut seeds_out =
        std::io::BufWriter::new(std::fs::File::create(&seeds_path).with_context(|| format!("creating {}", seeds_path.display()))?);
    let count = dataset.frames.len().min(args.max_frames.unwrap_or(usize::MAX));
    let bar = ProgressBar::new(count as u64);
    bar.set_style(
        ProgressStyle::with_template("{bar:40} {pos}/{len} frames {elapsed_precise} {msg}")
            .unwrap_or_else(|_| ProgressStyle::default_bar()),
    );
    let mut next_imu = 0;
    let mut world_from_map: Option<Isometry3<f64>> = None;
    let mut trajectory = Vec::new();
    let mut summary = FrameSummary::default();
    let (mut skipped, mut total_ms) = (0usize, Vec::new());
    for index in 0..count {
        let frame = &dataset.frames[index];
        // The IMU samples up to the frame stamp (+ the averaging half window), in stamp order, as a driver delivers them.
        let until = frame.timestamp + config.mapper.acquire.accel_half_window_s;
        while let Some(sample) = dataset.accelerometer.get(next_imu).filter(|s| s.timestamp <= until) {
            if let Err(err) = pipeline.push_imu(sample.timestamp, sample.acceleration_in_imu) {
                bar.println(format!("IMU sample {next_imu} skipped: {err}"));
            }
            next_imu += 1;
        }
        let depth = dataset.load_depth(index)?;
        let output = match pipeline.process(&depth, frame.timestamp) {
            Ok(output) => output,
            Err(err) => {
                bar.println(format!("frame {index} skipped: {err}"));
                skipped += 1;
                bar.inc(1);
                continue;
            }
        };
        if world_from_map.is_none() {
            world_from_map =
                dataset.groundtruth_near(frame.timestamp, 0.02).map(|gt| gt.world_from_camera * output.map_from_camera.inverse());
        }
        trajectory.push(StampedPose { timestamp: frame.timestamp, world_from_camera: output.map_from_camera });
        summary.add(&output.mapped);
        total_ms.push(output.timings.total_ms);
        for outcome in &output.seeds {
            let Some(patch) = outcome.patch_in_camera.as_ref().and_then(|p| transform_patch(p, &output.map_from_birds_eye)) else {
                continue;
            };
            let center_in_world = world_from_map.map(|w| (w * nalgebra::Point3::from(patch.center)).coords.into());
            let line = SeedLine {
                frame: index,
                neighbourhood_points: outcome.neighbourhood_size,
                seed_in_map: (output.map_from_birds_eye * nalgebra::Point3::from(outcome.seed.point_in_camera)).coords.into(),
                center_in_world,
                record: PatchRecord::with_verdict(patch, &outcome.verdict, outcome.validation.as_ref()),
            };
            serde_json::to_writer(&mut seeds_out, &line)?;
            seeds_out.write_all(b"\n")?;
        }
        let last = index + 1 == count;
        if last || (args.picture_every > 0 && index % args.picture_every == 0) {
            let path = args.out.join(format!("birds_eye_{index:05}.png"));
            render_patches(&output.birds_eye.depth, &output.birds_eye.intrinsics, &output.seeds).save_png(&path)?;
        }
        if last {
            // The last birds-eye cloud in the map frame, as CSV (x,y,z), readable by `patch_mapper fit`.
            let cloud = birds_eye_points_in_map(&output.birds_eye, &output.map_from_birds_eye);
            let text: String = cloud.iter().map(|p| format!("{},{},{}\n", p.x, p.y, p.z)).collect();
            let path = args.out.join("birds_eye_last_in_map.csv");
            std::fs::write(&path, text).with_context(|| format!("writing {}", path.display()))?;
        }
        bar.set_message(format!("{} patches in the map", pipeline.map().len()));
        bar.inc(1);
    }
    bar.finish_and_clear();
    seeds_out.flush()?;
    write_tum_poses(&args.out.join("trajectory.txt"), &trajectory)?;
    let map_path = args.out.join("patches.jsonl");
    let mut map_out =
        std::io::BufWriter::new(std::fs::File::create(&map_path).with_context(|| format!("creating {}", map_path.display()))?);
    for mapped in pipeline.map().patches() {
        let line = MapLine {
            id: mapped.id,
            first_seen: mapped.first_seen,
            last_seen: mapped.last_seen,
            center_in_world: world_from_map.map(|w| (w * nalgebra::Point3::from(mapped.patch.center)).coords.into()),
            normal_in_world: world_from_map.map(|w| (w.rotation * mapped.patch.normal()).into()),
            record: PatchRecord::mapped(mapped.patch.clone()),
        };
        serde_json::to_writer(&mut map_out, &line)?;
        map_out.write_all(b"\n")?;
    }
    map_out.flush()?;
    total_ms.sort_by(f64::total_cmp);
    let median = total_ms.get(total_ms.len() / 2).copied().unwrap_or(f64::NAN);
    println!(
        "{count} frames ({skipped} skipped), pipeline median {median:.1} ms/frame; seeds {} fitted {} valid {} | dropped: residual {} coverage {} curvature {} | failed {} skipped {}",
        summary.seeds, summary.fitted, summary.valid, summary.residual, summary.coverage, summary.curvature, summary.failed, summary.skipped
    );
    println!("final map: {} patches -> {}; seeds -> {}", pipeline.map().len(), map_path.display(), seeds_path.display());
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;
    use nalgebra::{Vector2, Vector3};
    use patchwalk_mapping::mapper::Verdict;
    use patchwalk_spl::patch::{BoundaryType, Patch, SurfaceType};

    #[test]
    fn seed_and_map_lines_parse_into_the_patch_record() {
        let patch = Patch::new(
            SurfaceType::Plane,
            BoundaryType::Circle,
            vec![0.05],
            Vector2::zeros(),
            Vector3::zeros(),
            Vector3::new(0.0, 0.0, 1.0),
        )
        .unwrap();
        let seed = SeedLine {
            frame: 0,
            neighbourhood_points: 40,
            seed_in_map: [0.0; 3],
            center_in_world: None,
            record: PatchRecord::with_verdict(patch.clone(), &Verdict::Residual, None),
        };
        let map = MapLine {
            id: 7,
            first_seen: 0.0,
            last_seen: 1.0,
            center_in_world: None,
            normal_in_world: None,
            record: PatchRecord::mapped(patch.clone()),
        };
        for (text, valid, verdict) in
            [(serde_json::to_string(&seed).unwrap(), false, "residual"), (serde_json::to_string(&map).unwrap(), true, "valid")]
        {
            let record: PatchRecord = serde_json::from_str(&text).unwrap();
            assert_eq!((record.valid, record.verdict.as_str(), &record.patch), (valid, verdict, &patch), "{text}");
        }
    }
}

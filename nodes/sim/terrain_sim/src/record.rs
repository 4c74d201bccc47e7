//! Writes the simulated stream as a TUM RGB-D-style dataset that `patchwalk_fusion::dataset` reads:
//! `depth/<t>.png` (16-bit, 1/5000 m), `depth.txt`, `accelerometer.txt` (IMU frame, m/s²),
//! `groundtruth.txt` (`world_from_camera`, world z up), `intrinsics.json` (with `depth_scale` and
//! the `camera_from_imu` mounting), and `scene.json` (rocks with their ground-truth footholds). A
//! terrain scene also gets its ground truth: `terrain.json` + `terrain_heights.f32`
//! (`scene::ground_truth`), the exact surface the depth was rendered from.

use std::path::{Path, PathBuf};

use patchwalk_fusion::dataset::{save_depth_png, write_tum_poses, DatasetError, StampedPose};
use serde_json::json;

use crate::scene::ground_truth::{write_ground_truth, GroundTruthError};
use crate::sim::Simulator;

/// TUM depth PNG units per metre.
pub const TUM_UNITS_PER_METRE: f64 = 5000.0;

#[derive(Debug, thiserror::Error)]
pub enum RecordError {
    #[error("{path}: {source}")]
    Io { path: PathBuf, source: std::io::Error },
    #[error(transparent)]
    Dataset(#[from] DatasetError),
    #[error("nothing to record: frames must be ≥ 1")]
    NoFrames,
    #[error(transparent)]
    GroundTruth(#[from] GroundTruthError),
}

/// What was written.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct RecordSummary {
    pub frames: usize,
    pub imu_samples: usize,
    pub duration_s: f64,
}

/// Records `frames` depth frames (and the IMU samples over the same time span) into `out_dir`,
/// calling `progress(i)` after each frame.
pub fn record(sim: &Simulator, out_dir: &Path, frames: usize, mut progress: impl FnMut(usize)) -> Result<RecordSummary, RecordError> {
    if frames == 0 {
        return Err(RecordError::NoFrames);
    }
    let io = |path: &Path| {
        let path = path.to_path_buf();
        move |source| RecordError::Io { path, source }
    };
    let depth_dir = out_dir.join("depth");
    std::fs::create_dir_all(&depth_dir).map_err(io(&depth_dir))?;
    let mut depth_list = String::from("# depth maps (terrain_sim)\n# timestamp filename\n");
    let mut poses = Vec::with_capacity(frames);
    for index in 0..frames {
        let frame = sim.depth_frame(index as u64);
        let name = format!("depth/{:.6}.png", frame.timestamp);
        save_depth_png(&out_dir.join(&name), &frame.depth, 1.0 / TUM_UNITS_PER_METRE)?;
        depth_list.push_str(&format!("{:.6} {name}\n", frame.timestamp));
        poses.push(StampedPose { timestamp: frame.timestamp, world_from_camera: frame.world_from_camera });
        progress(index);
    }
    write(out_dir.join("depth.txt"), &depth_list)?;
    write_tum_poses(&out_dir.join("groundtruth.txt"), &poses)?;

    let duration_s = (frames - 1) as f64 / sim.config.camera.rate_hz;
    let imu_samples = (duration_s * sim.config.imu.rate_hz).floor() as usize + 1;
    let mut accelerometer = String::from("# accelerometer data (terrain_sim, imu frame)\n# timestamp ax ay az\n");
    for index in 0..imu_samples {
        let sample = sim.imu_sample(index as u64);
        let a = sample.linear_acceleration_in_imu;
        accelerometer.push_str(&format!("{:.6} {:.6} {:.6} {:.6}\n", sample.timestamp, a.x, a.y, a.z));
    }
    write(out_dir.join("accelerometer.txt"), &accelerometer)?;

    let k = &sim.camera.intrinsics;
    let q = sim.imu.camera_from_imu.quaternion();
    let intrinsics = json!({
        "width": k.width, "height": k.height, "fx": k.fx, "fy": k.fy, "cx": k.cx, "cy": k.cy,
        "depth_scale": TUM_UNITS_PER_METRE,
        "camera_from_imu_xyzw": [q.i, q.j, q.k, q.w],
        "baseline_m": sim.config.camera.baseline_m,
        "sigma_pointing_px": sim.config.camera.noise.sigma_pointing_px,
        "sigma_disparity_px": sim.config.camera.noise.sigma_disparity_px,
    });
    write(out_dir.join("intrinsics.json"), &pretty(&intrinsics))?;
    write(out_dir.join("scene.json"), &pretty(&scene_json(sim)))?;
    write_terrain_ground_truth(sim, out_dir)?;
    Ok(RecordSummary { frames, imu_samples, duration_s })
}

/// Writes a terrain scene's ground truth (`terrain.json`, `terrain_heights.f32`) into `dir`;
/// nothing for the rock scene (its ground truth is analytic, in `scene.json`). Returns whether it wrote.
pub fn write_terrain_ground_truth(sim: &Simulator, dir: &Path) -> Result<bool, GroundTruthError> {
    match &sim.scene.terrain {
        Some(terrain) => {
            write_ground_truth(terrain, dir, &sim.config.scene.terrain.describe())?;
            Ok(true)
        }
        None => Ok(false),
    }
}

/// Rocks, their ground-truth footholds and stations, and the robot's `base_from_camera`; for a
/// terrain scene the terrain's grid and the camera path instead of rocks.
pub fn scene_json(sim: &Simulator) -> serde_json::Value {
    let vector = |v: &nalgebra::Vector3<f64>| json!([v.x, v.y, v.z]);
    let pose = |p: &nalgebra::Isometry3<f64>| {
        let q = p.rotation.quaternion();
        json!({ "translation": vector(&p.translation.vector), "rotation_xyzw": [q.i, q.j, q.k, q.w] })
    };
    let rocks: Vec<serde_json::Value> = sim
        .scene
        .rocks
        .iter()
        .map(|rock| {
            let foothold = rock.foothold();
            // The foothold relative to the robot standing at this rock's station (J 6.3 stores
            // patches relative to the robot): base_link at the lookdown height above the station.
            let world_from_base = rock.world_from_station * nalgebra::Isometry3::translation(0.0, 0.0, sim.config.motion.base_height_m);
            let top_in_base = world_from_base.inverse_transform_point(&foothold.top_in_world.into()).coords;
            let normal_in_base = world_from_base.inverse_transform_vector(&foothold.normal_in_world);
            json!({
                "name": rock.name,
                "trained": rock.trained,
                "shape": rock.shape,
                "world_from_rock": pose(&rock.world_from_rock),
                "world_from_station": pose(&rock.world_from_station),
                "foothold": {
                    "surface_type": foothold.surface_type,
                    "top_in_world": vector(&foothold.top_in_world),
                    "normal_in_world": vector(&foothold.normal_in_world),
                    "direction_x_in_world": vector(&foothold.direction_x_in_world),
                    "curvatures_per_m": foothold.curvatures_per_m,
                    "top_radius_m": foothold.top_radius_m,
                    "top_in_base": vector(&top_in_base),
                    "normal_in_base": vector(&normal_in_base),
                },
            })
        })
        .collect();
    let terrain = sim.scene.terrain.as_ref().map(|t| {
        json!({
            "source": sim.config.scene.terrain.describe(),
            "ground_truth": crate::scene::ground_truth::DESCRIPTOR_FILE,
            "columns": t.columns(), "rows": t.rows(), "resolution_m": t.resolution_m(), "origin_m": t.origin_m(),
            "extent_m": t.extent_m(), "z_range_m": t.z_range_m(),
        })
    });
    let path = sim.path.as_ref().map(|p| {
        json!({
            "config": p.config, "speed_mps": p.speed_mps(),
            "walker_from_camera": pose(&p.walker_from_camera()),
        })
    });
    json!({
        "seed": sim.config.seed,
        "terrain": terrain,
        "camera_path": path,
        "world_from_station": pose(&sim.world_from_station),
        "base_from_camera": pose(&sim.base_from_camera),
        "rocks": rocks,
    })
}

fn pretty(value: &serde_json::Value) -> String {
    serde_json::to_string_pretty(value).unwrap_or_else(|_| value.to_string())
}

fn write(path: PathBuf, text: &str) -> Result<(), RecordError> {
    std::fs::write(&path, text).map_err(|source| RecordError::Io { path, source })
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::config::SimConfig;
    use patchwalk_fusion::dataset::Dataset;

    #[test]
    fn recorded_dataset_opens_with_patch_mapper() {
        let dir = tempfile::tempdir().unwrap();
        let mut config = SimConfig::default();
        config.motion.sway.enabled = true;
        let sim = Simulator::new(config).unwrap();
        let summary = record(&sim, dir.path(), 4, |_| {}).unwrap();
        assert_eq!(summary.frames, 4);
        assert_eq!(summary.imu_samples, 11);
        let dataset = Dataset::open(dir.path()).unwrap();
        assert_eq!(dataset.frames.len(), 4);
        assert_eq!(dataset.intrinsics, sim.camera.intrinsics);
        assert!((dataset.metres_per_unit - 1.0 / 5000.0).abs() < 1e-15);
        assert_eq!(dataset.accelerometer.len(), 11);
        assert_eq!(dataset.groundtruth.len(), 4);
        // Depth survives the PNG round trip to the millimetre.
        let loaded = dataset.load_depth(2).unwrap();
        let rendered = sim.depth_frame(2).depth;
        assert_eq!(loaded.valid_count(), rendered.valid_count());
        let max_error =
            loaded.depth_m.iter().zip(&rendered.depth_m).filter(|(a, _)| a.is_finite()).map(|(a, b)| (a - b).abs()).fold(0.0f32, f32::max);
        assert!(max_error < 1e-4, "{max_error}");
        // Ground truth and accelerometer match the simulator.
        let pose = dataset.groundtruth_near(dataset.frames[1].timestamp, 1e-3).unwrap();
        assert!((pose.world_from_camera.translation.vector - sim.depth_frame(1).world_from_camera.translation.vector).norm() < 1e-5);
        let a = dataset.acceleration_near(0.05, 0.06).unwrap();
        assert!((a.norm() - 9.81).abs() < 0.3, "{}", a.norm());
        let scene: serde_json::Value = serde_json::from_str(&std::fs::read_to_string(dir.path().join("scene.json")).unwrap()).unwrap();
        assert_eq!(scene["rocks"].as_array().map(Vec::len), Some(sim.scene.rocks.len()));
        assert_eq!(scene["rocks"][0]["foothold"]["surface_type"], "elliptic_paraboloid");
        // Rock 1's top: standoff ahead of base_link, its height minus the base height.
        let top_in_base = &scene["rocks"][0]["foothold"]["top_in_base"];
        let expected = [sim.config.scene.standoff_m, 0.0, 0.05 - sim.config.motion.base_height_m];
        for (axis, value) in expected.iter().enumerate() {
            assert!((top_in_base[axis].as_f64().unwrap() - value).abs() < 1e-9, "{top_in_base}");
        }
        assert!(matches!(record(&sim, dir.path(), 0, |_| {}), Err(RecordError::NoFrames)));
    }
}

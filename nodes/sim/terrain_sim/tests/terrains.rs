//! Bring-your-own terrains end to end: analytic terrains written as heightmaps, the two real
//! elevation-map terrains (`tests/data/heightmaps`), rendered along a camera path; the rendered
//! depth back-projected through the ground-truth poses must lie on the ground-truth surface (to
//! f32 precision without noise, to the Murray–Little noise level with it), and grazing surfaces
//! must be missing. Prints the error figures.

use std::path::{Path, PathBuf};

use nalgebra::{Isometry3, Vector3};
use patchwalk_fusion::camera::DepthImage;
use patchwalk_fusion::dataset::test_data_dir;
use terrain_sim::config::SimConfig;
use terrain_sim::scene::ground_truth::read_ground_truth;
use terrain_sim::scene::heightmap_png::encode_png;
use terrain_sim::scene::{Ray, Scene};
use terrain_sim::sim::Simulator;

/// Back-projects every valid pixel and measures its distance to the ground-truth surface along the
/// normal (vertical offset × n_z, first order). Returns (errors sorted, valid pixel count).
fn surface_errors(sim: &Simulator, depth: &DepthImage, pose: &Isometry3<f64>) -> Vec<f64> {
    let k = &sim.camera.intrinsics;
    let mut errors = Vec::new();
    for v in 0..depth.height {
        for u in 0..depth.width {
            let Some(z) = depth.get(u, v) else { continue };
            let z = f64::from(z);
            let in_camera = Vector3::new((u as f64 - k.cx) / k.fx * z, (v as f64 - k.cy) / k.fy * z, z);
            let p = pose * nalgebra::Point3::from(in_camera);
            let (Some(h), Some(n)) = (sim.scene.height_at(p.x, p.y), sim.scene.normal_at(p.x, p.y)) else { continue };
            errors.push(((p.z - h) * n.z).abs());
        }
    }
    errors.sort_by(f64::total_cmp);
    errors
}

fn percentile(sorted: &[f64], p: f64) -> f64 {
    sorted.get(((sorted.len().max(1) - 1) as f64 * p).round() as usize).copied().unwrap_or(f64::NAN)
}

fn config_for(path: &Path, metres_per_pixel: f64, height_max_m: f64) -> SimConfig {
    let mut config = SimConfig::default();
    config.scene.terrain.path = path.to_path_buf();
    config.scene.terrain.metres_per_pixel = metres_per_pixel;
    config.scene.terrain.height_max_m = height_max_m;
    config
}

fn noiseless(config: &mut SimConfig) {
    config.camera.noise.enabled = false;
    config.camera.noise.depth_step_m = 0.0;
}

/// A 16-bit heightmap PNG from a function of the pixel (column, grid row from the bottom).
fn write_png16(dir: &Path, name: &str, width: u32, height: u32, level: impl Fn(u32, u32) -> u16) -> PathBuf {
    let data: Vec<u8> =
        (0..height).rev().flat_map(|row| (0..width).map(move |c| (c, row))).flat_map(|(c, r)| level(c, r).to_be_bytes()).collect();
    let path = dir.join(name);
    std::fs::write(&path, encode_png(width, height, png::ColorType::Grayscale, png::BitDepth::Sixteen, &data).unwrap()).unwrap();
    path
}

#[test]
fn analytic_plane_and_step_are_exact() {
    let dir = tempfile::tempdir().unwrap();
    // Plane of levels 20 i + 10 j at 1e-4 m per level and 1 cm/px: z = 0.2 x + 0.1 y (integer levels
    // are exact in 16 bits, and bilinear interpolation reproduces a plane exactly).
    let plane = write_png16(dir.path(), "plane.png", 300, 200, |c, r| (20 * c + 10 * r) as u16);
    let mut config = config_for(&plane, 0.01, 6.5535);
    noiseless(&mut config);
    config.path.start_m = Some([0.6, 1.0]);
    config.path.pitch_deg = 50.0;
    let sim = Simulator::new(config).unwrap();
    let expected_normal = Vector3::new(-0.2, -0.1, 1.0).normalize();
    for (x, y) in [(0.5, 0.5), (1.234, 0.987), (2.99, 1.99)] {
        assert!((sim.scene.height_at(x, y).unwrap() - (0.2 * x + 0.1 * y)).abs() < 1e-5);
        assert!((sim.scene.normal_at(x, y).unwrap() - expected_normal).norm() < 1e-5);
    }
    let frame = sim.depth_frame(3);
    let errors = surface_errors(&sim, &frame.depth, &frame.world_from_camera);
    assert!(errors.len() > 100_000, "valid pixels {}", errors.len());
    println!("plane: {} pixels, max error {:.2e} m", errors.len(), percentile(&errors, 1.0));
    assert!(percentile(&errors, 1.0) < 1e-5);
    // Also against the analytic plane directly: the ray–plane intersection.
    let k = &sim.camera.intrinsics;
    let pose = frame.world_from_camera;
    let (u, v) = (320, 300);
    let direction = pose.rotation * Vector3::new((u as f64 - k.cx) / k.fx, (v as f64 - k.cy) / k.fy, 1.0);
    let o = pose.translation.vector;
    // o.z + t d.z = 0.2 (o.x + t d.x) + 0.1 (o.y + t d.y)
    let t = (0.2 * o.x + 0.1 * o.y - o.z) / (direction.z - 0.2 * direction.x - 0.1 * direction.y);
    assert!((f64::from(frame.depth.get(u, v).unwrap()) - t).abs() < 1e-5);

    // A 0.1 m step across x = 1.0 m (levels 0 | 1000 at 1e-4 m per level), 1 cm/px: flat on both
    // sides, a 1 cm ramp between samples 100 and 101.
    let step = write_png16(dir.path(), "step.png", 200, 100, |c, _| if c <= 100 { 0 } else { 1000 });
    let mut config = config_for(&step, 0.01, 6.5535);
    noiseless(&mut config);
    config.path.start_m = Some([0.3, 0.5]);
    let sim = Simulator::new(config).unwrap();
    assert!((sim.scene.height_at(0.7, 0.5).unwrap()).abs() < 1e-9);
    assert!((sim.scene.height_at(1.5, 0.2).unwrap() - 0.1).abs() < 1e-6);
    assert!((sim.scene.height_at(1.005, 0.2).unwrap() - 0.05).abs() < 1e-6);
    let frame = sim.depth_frame(0);
    let errors = surface_errors(&sim, &frame.depth, &frame.world_from_camera);
    println!("step: {} pixels, max error {:.2e} m", errors.len(), percentile(&errors, 1.0));
    assert!(percentile(&errors, 1.0) < 1e-5);
    // The riser is seen: a horizontal ray at 5 cm hits it at x = 1.005.
    let hit = sim.scene.ray_hit(&Ray { origin: Vector3::new(0.2, 0.5, 0.05), direction: Vector3::x() }).unwrap();
    assert!((hit.t - 0.805).abs() < 1e-9);
}

#[test]
fn real_terrains_render_on_their_ground_truth() {
    let heightmaps = test_data_dir().join("heightmaps");
    // (file, m/px, height of level 255, walk start, heading)
    let cases = [
        ("terrain.png", 0.04, 1.0, Some([2.0, 10.0]), 0.0),
        ("terrain.png", 0.01, 0.25, Some([0.5, 2.5]), 0.0),
        // The stairs descend along +x from a 0.94 m landing (x ≈ 0.6 m) to 0.18 m: walk up them.
        ("real_stairs_125cm.png", 0.04, 1.25, Some([4.6, 1.4]), 180.0),
    ];
    for (file, metres_per_pixel, height_max, start, heading) in cases {
        let mut config = config_for(&heightmaps.join(file), metres_per_pixel, height_max);
        config.path.start_m = start;
        config.path.heading_deg = heading;
        let sim = Simulator::new(config.clone()).unwrap();
        let terrain = sim.scene.terrain.clone().unwrap();
        assert!(terrain.z_range_m()[1] <= height_max + 1e-6);
        // Noisy frames: the back-projection error is the camera's noise.
        let (mut all, mut depths) = (Vec::new(), Vec::new());
        for index in [0u64, 15, 30] {
            let frame = sim.depth_frame(index);
            depths.extend(frame.depth.depth_m.iter().filter(|z| z.is_finite()).map(|&z| f64::from(z)));
            all.extend(surface_errors(&sim, &frame.depth, &frame.world_from_camera));
        }
        all.sort_by(f64::total_cmp);
        depths.sort_by(f64::total_cmp);
        let median_depth = percentile(&depths, 0.5);
        // J eq. 2 depth σ at the median depth; |N(0, σ)| has median 0.674 σ (the normal distance is
        // at most the depth error, so ≤ that on slanted views).
        let sigma = sim.config.camera.depth_sigma(median_depth);
        let (median, p90) = (percentile(&all, 0.5), percentile(&all, 0.9));
        println!(
            "{file} at {metres_per_pixel} m/px: {} points in 3 frames, median depth {median_depth:.3} m, surface error median {:.2} mm p90 {:.2} mm (σz {:.2} mm → 0.674σ = {:.2} mm)",
            all.len(),
            median * 1e3,
            p90 * 1e3,
            sigma * 1e3,
            0.674 * sigma * 1e3
        );
        assert!(all.len() > 300_000, "{file}: {} valid points", all.len());
        assert!(median < 1.5 * 0.674 * sigma + 5e-4, "{file}: median {median} vs σ {sigma}");
        assert!(median > 0.1 * sigma, "{file}: noise must be present ({median})");
        // Noiseless: on the surface to f32 precision.
        let mut exact = config.clone();
        noiseless(&mut exact);
        let sim_exact = Simulator::new(exact).unwrap();
        let frame = sim_exact.depth_frame(15);
        let errors = surface_errors(&sim_exact, &frame.depth, &frame.world_from_camera);
        println!("{file} at {metres_per_pixel} m/px noiseless: max surface error {:.2e} m", percentile(&errors, 1.0));
        assert!(percentile(&errors, 1.0) < 2e-5, "{file}");
        // Grazing angles: no valid pixel sees the surface beyond the camera's max incidence, and some are dropped for it.
        let (mut grazing_dropped, mut checked) = (0, 0);
        let k = &sim_exact.camera.intrinsics;
        let cos_max = sim_exact.config.camera.missing.max_incidence_deg.to_radians().cos();
        for v in (0..k.height).step_by(4) {
            for u in (0..k.width).step_by(4) {
                let direction = frame.world_from_camera.rotation * Vector3::new((u as f64 - k.cx) / k.fx, (v as f64 - k.cy) / k.fy, 1.0);
                let Some(hit) = sim_exact.scene.ray_hit(&Ray { origin: frame.world_from_camera.translation.vector, direction }) else {
                    continue;
                };
                if hit.t > sim_exact.config.camera.max_depth_m {
                    continue;
                }
                let cos_incidence = -direction.normalize().dot(&hit.normal);
                checked += 1;
                if cos_incidence < cos_max - 1e-6 {
                    assert!(frame.depth.get(u, v).is_none(), "{file}: grazing pixel ({u}, {v}) has depth");
                    grazing_dropped += 1;
                }
            }
        }
        println!("{file} at {metres_per_pixel} m/px: {grazing_dropped} of {checked} sampled pixels dropped as grazing");
    }
}

#[test]
fn stairs_edges_and_shadows_are_missing() {
    // Looking up the stairs from their foot: depth edges at the step noses and the projector's
    // shadows (it sits 7.5 cm to the right) leave pixels without data where the terrain is in view.
    let mut config = config_for(&test_data_dir().join("heightmaps/real_stairs_125cm.png"), 0.04, 1.25);
    config.path.start_m = Some([4.6, 1.4]);
    config.path.heading_deg = 180.0;
    config.camera.noise.enabled = false;
    let sim = Simulator::new(config.clone()).unwrap();
    let frame = sim.depth_frame(0);
    let k = &sim.camera.intrinsics;
    let (mut in_view, mut missing) = (0, 0);
    for v in 0..k.height {
        for u in 0..k.width {
            let direction = frame.world_from_camera.rotation * Vector3::new((u as f64 - k.cx) / k.fx, (v as f64 - k.cy) / k.fy, 1.0);
            let hit = sim.scene.ray_hit(&Ray { origin: frame.world_from_camera.translation.vector, direction });
            if hit.is_some_and(|h| (config.camera.min_depth_m..=config.camera.max_depth_m).contains(&h.t)) {
                in_view += 1;
                missing += usize::from(frame.depth.get(u, v).is_none());
            }
        }
    }
    println!("stairs: {} valid pixels, {missing} of {in_view} pixels seeing the terrain in range have no data", frame.depth.valid_count());
    assert!(frame.depth.valid_count() > 150_000);
    assert!(missing > 100 && missing < in_view / 4, "{missing} of {in_view}");
    // Without the projector shadow fewer are missing.
    config.camera.missing.projector_shadow = false;
    let unshadowed = Simulator::new(config).unwrap().depth_frame(0).depth.valid_count();
    println!("stairs: {unshadowed} valid pixels without projector shadows");
    assert!(unshadowed > frame.depth.valid_count());
}

#[test]
fn recorded_terrain_ground_truth_reloads() {
    let dir = tempfile::tempdir().unwrap();
    let mut config = config_for(&test_data_dir().join("heightmaps/real_stairs_125cm.png"), 0.04, 1.25);
    config.camera.width = 160;
    config.camera.height = 120;
    config.camera.fx = 142.6;
    config.camera.fy = 142.6;
    config.camera.cx = 79.5;
    config.camera.cy = 59.5;
    let sim = Simulator::new(config).unwrap();
    let summary = terrain_sim::record::record(&sim, dir.path(), 3, |_| {}).unwrap();
    assert_eq!(summary.frames, 3);
    for file in ["depth.txt", "accelerometer.txt", "groundtruth.txt", "terrain.json", "terrain_heights.f32", "scene.json"] {
        assert!(dir.path().join(file).exists(), "{file}");
    }
    let truth = read_ground_truth(dir.path()).unwrap();
    let original = sim.scene.terrain.as_deref().unwrap();
    assert_eq!(&truth, original);
    let reloaded = Scene::from_terrain(truth);
    for (x, y) in [(1.0, 1.0), (2.3, 0.7), (4.0, 2.6)] {
        assert_eq!(reloaded.height_at(x, y), sim.scene.height_at(x, y));
        assert_eq!(reloaded.normal_at(x, y), sim.scene.normal_at(x, y));
    }
    let dataset = patchwalk_fusion::dataset::Dataset::open(dir.path()).unwrap();
    assert_eq!(dataset.frames.len(), 3);
    let scene: serde_json::Value = serde_json::from_str(&std::fs::read_to_string(dir.path().join("scene.json")).unwrap()).unwrap();
    assert_eq!(scene["terrain"]["columns"], 122);
    assert!(scene["camera_path"]["speed_mps"].as_f64().is_some());
}

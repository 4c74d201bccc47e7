//! Tests of the runtime on the mock bus and without one.

use super::*;
use patchwalk_dynamixel::servo_bus::mock::MockBus;
use patchwalk_spl::patch::SurfaceType;
use std::time::{Duration, Instant};

fn config(dir: &std::path::Path) -> StepExecutorConfig {
    let root = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("../../..");
    let mut config: StepExecutorConfig = patchwalk_ros::params::load_config(Some(&root.join("config/step_executor.yaml")), &[]).unwrap();
    config.urdf_path = root.join("urdf/rpbp.urdf");
    config.library_path = dir.join("motions.yaml");
    config
}

fn wait(runtime: &mut Runtime, what: &str, mut done: impl FnMut(&Runtime) -> bool) {
    let deadline = Instant::now() + Duration::from_secs(5);
    while !done(runtime) {
        assert!(Instant::now() < deadline, "timed out waiting for {what}");
        runtime.poll();
        std::thread::sleep(Duration::from_millis(5));
    }
}

/// J 6.3 training by fitting: a round bump (κ = −10 m⁻¹) in the mapper's cloud, fitted at a
/// point given in base_link, comes back as a circular paraboloid at the bump's apex.
#[test]
fn select_fit_fits_the_cloud_around_a_point_in_base_link() {
    let dir = tempfile::tempdir().unwrap();
    let (mut runtime, _) = Runtime::with_bus(config(dir.path()), || Err("no bus".into())).unwrap();
    assert!(runtime.select_fit(&[], [0.28, 0.0, -0.25], 0.05).unwrap_err().to_string().contains("no patch map"));
    // Any map frame: here the map is 1 m to the side and turned 30° about its up axis.
    let map_from_camera = Isometry3::new(Vector3::new(1.0, 0.5, 0.0), Vector3::z() * 0.5) * runtime.base_from_camera().unwrap().inverse();
    runtime.on_patch_map(&[], &map_from_camera).unwrap();
    assert!(runtime.select_fit(&[], [0.28, 0.0, -0.25], 0.05).unwrap_err().to_string().contains("no birds-eye cloud"));
    let base_from_map = runtime.base_from_camera().unwrap() * map_from_camera.inverse();
    let apex_in_base = Vector3::new(0.28, 0.0, -0.25);
    let kappa = 10.0;
    let mut cloud_in_map = Vec::new();
    for i in -16..=16 {
        for j in -16..=16 {
            let (x, y) = (f64::from(i) * 0.005, f64::from(j) * 0.005);
            let point_in_base = apex_in_base + Vector3::new(x, y, -0.5 * kappa * (x * x + y * y));
            cloud_in_map.push((base_from_map.inverse() * Point3::from(point_in_base)).coords);
        }
    }
    cloud_in_map.push(Vector3::new(f64::NAN, 0.0, 0.0));
    let patch = runtime.select_fit(&cloud_in_map, [0.28, 0.0, -0.25], 0.05).unwrap();
    assert_eq!(patch.surface, SurfaceType::CircularParaboloid, "{patch:?}");
    assert!((patch.curvatures.x + kappa).abs() < 0.5, "{patch:?}");
    assert!((patch.center - apex_in_base).norm() < 0.003, "{patch:?}");
    assert!(patch.normal().z > 0.99, "{patch:?}");
    // Nothing there, or a nonsense radius: errors, and the target is kept.
    assert!(runtime.select_fit(&cloud_in_map, [2.0, 0.0, -0.25], 0.05).unwrap_err().to_string().contains("only 0 cloud points"));
    assert!(runtime.select_fit(&cloud_in_map, [0.28, 0.0, -0.25], 0.0).is_err());
    assert!(runtime.select_fit(&cloud_in_map, [f64::NAN, 0.0, -0.25], 0.05).is_err());
    assert_eq!(runtime.target.as_ref(), Some(&patch));
}

#[test]
fn commands_are_refused_with_typed_errors_naming_the_field() {
    let dir = tempfile::tempdir().unwrap();
    let (mut runtime, _) = Runtime::with_bus(config(dir.path()), || Err("no such port".into())).unwrap();
    // A non-finite point is refused before anything is looked at, also with a map to pick from.
    let patch = Patch::level_disc(0.03, Vector3::new(0.0, 0.1, 0.4)).unwrap();
    assert!(matches!(runtime.select_nearest([0.0; 3]), Err(CommandError::NoPatches)));
    runtime.on_patch_map(&[patch], &Isometry3::identity()).unwrap();
    for bad in [f64::NAN, f64::INFINITY, f64::NEG_INFINITY] {
        let err = runtime.select_nearest([0.2, bad, 0.0]).unwrap_err();
        assert!(matches!(err, CommandError::InvalidArgument { field: "point", .. }), "{err:?}");
        assert!(err.to_string().contains("finite"), "{err}");
        assert!(matches!(runtime.fit_job([bad, 0.0, 0.0], 0.05), Err(CommandError::InvalidArgument { field: "point", .. })));
    }
    assert!(runtime.target.is_none(), "no target stored at a non-finite point");
    assert!(runtime.select_nearest([0.0; 3]).is_ok());
    assert!(matches!(runtime.fit_job([0.0; 3], 0.6), Err(CommandError::InvalidArgument { field: "radius", .. })));
    for (duration, pause, field) in [(f64::NAN, 0.0, "duration"), (-1.0, 0.0, "duration"), (1.0, f64::INFINITY, "pause")] {
        let err = runtime.record_keyframe(duration, pause).unwrap_err();
        assert!(matches!(err, CommandError::InvalidArgument { field: f, .. } if f == field), "{err:?}");
    }
    // Names: the rule is named, before the state (no target, no bus) is looked at.
    for name in ["", "a\u{202E}b", "a\nb"] {
        assert!(matches!(runtime.prepare_save(name), Err(CommandError::InvalidName(_))), "{name:?}");
        assert!(matches!(runtime.prepare_delete(name), Err(CommandError::InvalidName(_))), "{name:?}");
        assert!(matches!(runtime.play_motion(name), Err(CommandError::InvalidName(_))), "{name:?}");
    }
    assert!(matches!(runtime.prepare_save("ok"), Err(CommandError::NoKeyframes)));
    runtime.target = None;
    assert!(matches!(runtime.prepare_save("ok"), Err(CommandError::NoTarget)));
    assert!(matches!(runtime.prepare_delete("ok"), Err(CommandError::Library(LibraryError::NotFound(_)))));
    assert!(matches!(runtime.play_motion("ok"), Err(CommandError::BusUnavailable(reason)) if reason == "no such port"));
    runtime.stop();
    assert!(matches!(runtime.arm(true), Err(CommandError::EStopped)));
    assert!(runtime.arm(false).is_ok());
}

#[test]
fn stale_temp_files_beside_the_library_are_removed_at_start() {
    let dir = tempfile::tempdir().unwrap();
    let stale = dir.path().join(".motions.yaml.tmp-4194999");
    let other = dir.path().join(".other.yaml.tmp-4194999");
    std::fs::write(&stale, "garbage: [").unwrap();
    std::fs::write(&other, "garbage: [").unwrap();
    let (_runtime, warnings) = Runtime::with_bus(config(dir.path()), || Err("no bus".into())).unwrap();
    assert!(!stale.exists() && other.exists());
    assert!(warnings.iter().any(|w| w.contains(".motions.yaml.tmp-4194999") && w.contains("interrupted save")), "{warnings:?}");
}

#[test]
fn missing_urdf_file_falls_back_to_the_built_in_model() {
    let dir = tempfile::tempdir().unwrap();
    let mut config = config(dir.path());
    config.urdf_path = dir.path().join("nowhere.urdf");
    let (runtime, warnings) = Runtime::with_bus(config, || Err("no bus".into())).unwrap();
    assert!(warnings.iter().any(|w| w.contains("built-in")));
    assert!(runtime.base_from_camera().is_ok());
}

#[test]
fn without_a_bus_the_node_still_starts_and_explains() {
    let dir = tempfile::tempdir().unwrap();
    let (mut runtime, warnings) = Runtime::with_bus(config(dir.path()), || Err("no such port".into())).unwrap();
    assert!(warnings.iter().any(|w| w.contains("servo bus not available")));
    assert!(runtime.play_motion("x").unwrap_err().to_string().contains("not available"));
    assert!(runtime.record_keyframe(1.0, 0.0).unwrap_err().to_string().contains("not available"));
    assert!(runtime.status().last_fault.contains("not available"));
}

/// The runtime on a mock chain of 12 servos, with "rock1" trained on a plane 0.4 m ahead of the
/// camera (two keyframes: right knee bent, then straight), the map's camera at the map's origin.
fn trained_on_mock_bus(dir: &std::path::Path) -> (Runtime, MockBus, Patch) {
    let bus = MockBus::new(&(1..=12).collect::<Vec<_>>());
    bus.state().max_step_ticks = 40;
    let handle = bus.clone();
    let (mut runtime, _) = Runtime::with_bus(config(dir), move || Ok(Box::new(handle) as Box<dyn ServoBus>)).unwrap();
    wait(&mut runtime, "positions", |r| r.positions().iter().all(Option::is_some));

    // A patch map: one plane 0.4 m ahead of the camera.
    let map_from_camera = Isometry3::identity();
    let camera_patch = Patch::level_disc(0.03, Vector3::new(0.0, 0.1, 0.4)).unwrap();
    runtime.on_patch_map(std::slice::from_ref(&camera_patch), &map_from_camera).unwrap();
    let base_from_camera = runtime.base_from_camera().unwrap();
    let expected_c = base_from_camera * Point3::from(camera_patch.center);
    let target = runtime.select_nearest(expected_c.coords.into()).unwrap();
    assert!((Point3::from(target.center) - expected_c).norm() < 1e-9);

    // Train: torque off, "move" the servos by hand, record two keyframes, save.
    runtime.set_torque(false).unwrap();
    for (id, ticks) in [(7u8, 2300), (8, 2300)] {
        bus.state().servos.get_mut(&id).unwrap().present = ticks;
    }
    std::thread::sleep(Duration::from_millis(30));
    let (index, positions) = runtime.record_keyframe(0.2, 0.0).unwrap();
    assert_eq!(index, 0);
    assert!(positions[6] > 0.3);
    bus.state().servos.get_mut(&7).unwrap().present = 2048;
    std::thread::sleep(Duration::from_millis(30));
    runtime.record_keyframe(0.2, 0.0).unwrap();
    assert!(runtime.save_motion("rock1").unwrap().contains("2 keyframes"));
    assert_eq!(runtime.list_motions()[0].keyframe_count, 2);
    let reloaded = MotionLibrary::load(&dir.join("motions.yaml"), runtime.joint_names()).unwrap();
    assert_eq!(reloaded.names(), vec!["rock1"]);
    (runtime, bus, camera_patch)
}

/// A match plays the motion while the bus thread's cycles from before it are still queued (nobody
/// polled for a while): they say idle, and reading them must not turn the step back to idle (the
/// deadman ends its watch and `hold` does nothing when the motion looks idle).
#[test]
fn a_motion_started_with_idle_cycles_queued_reads_as_playing() {
    let dir = tempfile::tempdir().unwrap();
    let (mut runtime, _bus, camera_patch) = trained_on_mock_bus(dir.path());
    for attempt in 0..20 {
        runtime.arm(true).unwrap();
        runtime.poll();
        std::thread::sleep(Duration::from_millis(30));
        assert!(runtime.on_patch_map(std::slice::from_ref(&camera_patch), &Isometry3::identity()).unwrap().best.is_some());
        assert_eq!(runtime.status().state, RunState::Playing);
        runtime.poll();
        assert_eq!(runtime.status().state, RunState::Playing, "attempt {attempt}: idle cycles from before the start were taken as current");
        assert_eq!(runtime.status().current_motion, "rock1");
        assert!(runtime.hold(), "a playing motion is held");
        wait(&mut runtime, "the hold", |r| r.status().state == RunState::Idle);
    }
}

#[test]
fn train_match_and_play_on_the_mock_bus() {
    let dir = tempfile::tempdir().unwrap();
    let (mut runtime, bus, camera_patch) = trained_on_mock_bus(dir.path());
    let map_from_camera = Isometry3::identity();

    // Non-matching map: nothing moves even when armed.
    runtime.arm(true).unwrap();
    let writes = bus.state().goal_writes.len();
    let far = Patch { center: Vector3::new(0.3, 0.1, 0.4), ..camera_patch.clone() };
    let report = runtime.on_patch_map(&[far], &map_from_camera).unwrap();
    assert!(report.best.is_none());
    assert!(matches!(report.near_misses[0].reason, crate::matcher::Rejection::Position { .. }));
    std::thread::sleep(Duration::from_millis(30));
    runtime.poll();
    assert_eq!(bus.state().goal_writes.len(), writes);

    // Matching map while armed: plays rock1 to the end.
    let report = runtime.on_patch_map(&[camera_patch], &map_from_camera).unwrap();
    assert!(report.best.is_some());
    assert_eq!(runtime.status().last_match, "rock1");
    assert!(!runtime.status().armed, "automatic execution is one-shot");
    wait(&mut runtime, "playback", |r| r.status().state == RunState::Playing);
    wait(&mut runtime, "finish", |r| r.status().state == RunState::Idle);
    assert!(bus.state().goal_writes.len() > writes + 40);

    // E-stop latches: play and arming are refused until reset_estop, which does not arm.
    runtime.stop();
    assert_eq!(runtime.status().state, RunState::EStopped);
    assert!(runtime.play_motion("rock1").unwrap_err().to_string().contains("reset_estop"));
    assert!(runtime.arm(true).unwrap_err().to_string().contains("reset_estop"));
    assert_eq!(runtime.status().state, RunState::EStopped);
    runtime.reset_estop();
    assert_eq!(runtime.status().state, RunState::Idle);
    assert!(!runtime.status().armed);
    runtime.arm(true).unwrap();
    assert!(runtime.delete_motion("rock1").is_ok());
    assert_eq!(runtime.status().library_size, 0);
}

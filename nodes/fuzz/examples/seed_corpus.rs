//! Writes the seed inputs of every fuzz target into `tests/data/fuzz/<target>/seed-*`: well-formed
//! messages, requests, frames, bags and files the nodes accept, made with the same encoders the
//! nodes use (depth frames also cut from the recorded TUM fr1/xyz excerpt in `tests/data`), so the
//! fuzzer starts from inputs that reach deep into each parser. Run from the repository root:
//! `cargo run --manifest-path nodes/fuzz/Cargo.toml --example seed_corpus`.

use std::path::Path;

use anyhow::{ensure, Context, Result};
use nalgebra::{Vector2, Vector3};
use patchwalk_bag::messages as bag;
use patchwalk_bag::metadata::Qos;
use patchwalk_bag::{BagWriter, Compression};
use patchwalk_dynamixel::protocol::{encode, encode_status, instruction, BROADCAST_ID};
use patchwalk_fusion::dataset::{test_data_dir, Dataset};
use patchwalk_msgs::builtin_interfaces::msg::Time;
use patchwalk_msgs::geometry_msgs::msg::Point;
use patchwalk_msgs::msg::{Patch, PatchArray};
use patchwalk_msgs::sensor_msgs::msg::{CameraInfo, Image, Imu};
use patchwalk_msgs::srv;
use patchwalk_ros::wire::encode as cdr;
use patchwalk_spl::patch::{BoundaryType, Patch as SplPatch, SurfaceType};
use step_executor::action_file::{keyframes_to_page, page_name, Page};
use step_executor::library::{Keyframe, Motion, MotionLibrary};

fn write(target: &str, name: &str, bytes: &[u8]) -> Result<()> {
    let dir = Path::new("tests/data/fuzz").join(target);
    std::fs::create_dir_all(&dir).with_context(|| format!("creating {}", dir.display()))?;
    let path = dir.join(format!("seed-{name}"));
    std::fs::write(&path, bytes).with_context(|| format!("writing {}", path.display()))
}

fn selected(selector: u8, payload: Vec<u8>) -> Vec<u8> {
    let mut bytes = vec![selector];
    bytes.extend(payload);
    bytes
}

fn stamp() -> Time {
    Time { sec: 1_000_000_000, nanosec: 0 }
}

/// A 64×48 camera looking at a floor 0.8 m away, tilted.
fn camera_info() -> CameraInfo {
    let mut info = CameraInfo { width: 64, height: 48, ..Default::default() };
    info.header.stamp = stamp();
    info.k = [52.5, 0.0, 31.5, 0.0, 52.5, 23.5, 0.0, 0.0, 1.0];
    info
}

fn imu() -> Imu {
    let mut imu = Imu::default();
    imu.header.stamp = Time { sec: 999_999_999, nanosec: 990_000_000 };
    imu.linear_acceleration.y = 9.81;
    imu
}

fn depth_mm() -> Image {
    let (w, h) = (64u32, 48u32);
    let data = (0..h).flat_map(|v| (0..w).map(move |_| 700 + 4 * v as u16)).flat_map(u16::to_le_bytes).collect();
    let mut image = Image { width: w, height: h, encoding: "16UC1".into(), step: 2 * w, data, ..Default::default() };
    image.header.stamp = stamp();
    image
}

fn depth_m() -> Image {
    let (w, h) = (8u32, 4u32);
    let data = (0..w * h).map(|i| 0.5 + 0.01 * i as f32).flat_map(f32::to_le_bytes).collect();
    let mut image = Image { width: w, height: h, encoding: "32FC1".into(), step: 4 * w, data, is_bigendian: 0, ..Default::default() };
    image.header.stamp = stamp();
    image
}

/// Frame `index` of the TUM fr1/xyz excerpt, every `stride`-th pixel (millimetres), its intrinsics
/// scaled alike and the accelerometer sample nearest it; restamped at 1e9 s (the replay clock).
fn tum_frame(index: usize, stride: usize) -> Result<(CameraInfo, Imu, Image)> {
    let dataset = Dataset::open(&test_data_dir().join("tum_fr1_xyz"))?;
    let depth = dataset.load_depth(index)?;
    let (w, h) = (depth.width / stride, depth.height / stride);
    let data = (0..h)
        .flat_map(|v| (0..w).map(move |u| (u, v)))
        .map(|(u, v)| depth.depth_m[v * stride * depth.width + u * stride])
        .map(|d| if d.is_finite() { (f64::from(d) * 1000.0).round().clamp(0.0, 65535.0) as u16 } else { 0 })
        .flat_map(u16::to_le_bytes)
        .collect();
    let t = dataset.frames[index].timestamp;
    let sample = dataset
        .accelerometer
        .iter()
        .min_by(|a, b| (a.timestamp - t).abs().total_cmp(&(b.timestamp - t).abs()))
        .context("the excerpt has no accelerometer samples")?;
    let k = &dataset.intrinsics;
    let scale = stride as f64;
    let mut info = CameraInfo { width: w as u32, height: h as u32, ..Default::default() };
    info.header.stamp = stamp();
    info.k = [k.fx / scale, 0.0, k.cx / scale, 0.0, k.fy / scale, k.cy / scale, 0.0, 0.0, 1.0];
    let mut imu = Imu::default();
    imu.header.stamp = Time { sec: 999_999_999, nanosec: 990_000_000 };
    let a = sample.acceleration_in_imu;
    (imu.linear_acceleration.x, imu.linear_acceleration.y, imu.linear_acceleration.z) = (a.x, a.y, a.z);
    let mut image = Image { width: w as u32, height: h as u32, encoding: "16UC1".into(), step: 2 * w as u32, data, ..Default::default() };
    image.header.stamp = stamp();
    Ok((info, imu, image))
}

/// A bag of `frames` TUM frames (every 20th pixel: 32×24) on the replay topics, with IMU samples and
/// ground-truth poses (PoseStamped, or TFMessage with the camera frame as child), as file bytes.
fn tum_bag(frames: usize, compression: Compression, tf_groundtruth: bool) -> Result<Vec<u8>> {
    let dataset = Dataset::open(&test_data_dir().join("tum_fr1_xyz"))?;
    let dir = std::env::temp_dir().join(format!("patchwalk-seed-bag-{}", std::process::id()));
    std::fs::create_dir_all(&dir)?;
    let path = dir.join("seed.mcap");
    let _ = std::fs::remove_file(&path);
    let mut writer = BagWriter::create(&path, compression)?;
    let topics = patch_mapper::inputs::replay_bag_topics();
    let info_topic = writer.add_topic::<bag::CameraInfo>(&topics.camera_info, Qos::SensorData)?;
    let imu_topic = writer.add_topic::<bag::Imu>(&topics.imu, Qos::SensorData)?;
    let depth_topic = writer.add_topic::<bag::Image>(&topics.depth, Qos::SensorData)?;
    let frame_id = "camera_depth_optical_frame";
    for index in 0..frames {
        let (info, imu, image) = tum_frame(index, 20)?;
        let t = dataset.frames[index].timestamp;
        let stamp = bag::Time::from_seconds(t);
        let log_time = (t * 1e9) as u64;
        let header = bag::Header::new(stamp, frame_id);
        let mut bag_info = bag::CameraInfo {
            header: header.clone(),
            width: info.width,
            height: info.height,
            distortion_model: "plumb_bob".into(),
            ..Default::default()
        };
        bag_info.k = info.k;
        writer.write(info_topic, log_time, &bag_info)?;
        let a = &imu.linear_acceleration;
        let bag_imu = bag::Imu { header: header.clone(), linear_acceleration: bag::Vector3::new(a.x, a.y, a.z), ..Default::default() };
        writer.write(imu_topic, log_time, &bag_imu)?;
        let bag_image = bag::Image {
            header: header.clone(),
            width: image.width,
            height: image.height,
            encoding: image.encoding.clone(),
            is_bigendian: 0,
            step: image.step,
            data: image.data.clone(),
        };
        writer.write(depth_topic, log_time, &bag_image)?;
    }
    let nearest = |t: f64| dataset.groundtruth.iter().min_by(|a, b| (a.timestamp - t).abs().total_cmp(&(b.timestamp - t).abs()));
    if tf_groundtruth {
        let gt_topic = writer.add_topic::<bag::TfMessage>(&topics.groundtruth, Qos::Reliable(10))?;
        for index in 0..frames {
            let t = dataset.frames[index].timestamp;
            let pose = nearest(t).context("no ground truth")?;
            let (p, q) = (pose.world_from_camera.translation.vector, pose.world_from_camera.rotation);
            let transform = bag::TransformStamped {
                header: bag::Header::new(bag::Time::from_seconds(t), "world"),
                child_frame_id: frame_id.into(),
                translation: bag::Vector3::new(p.x, p.y, p.z),
                rotation: bag::Quaternion { x: q.i, y: q.j, z: q.k, w: q.w },
            };
            writer.write(gt_topic, (t * 1e9) as u64, &bag::TfMessage { transforms: vec![transform] })?;
        }
    } else {
        let gt_topic = writer.add_topic::<bag::PoseStamped>(&topics.groundtruth, Qos::Reliable(10))?;
        for index in 0..frames {
            let t = dataset.frames[index].timestamp;
            let pose = nearest(t).context("no ground truth")?;
            let (p, q) = (pose.world_from_camera.translation.vector, pose.world_from_camera.rotation);
            let message = bag::PoseStamped {
                header: bag::Header::new(bag::Time::from_seconds(t), "world"),
                position: bag::Vector3::new(p.x, p.y, p.z),
                orientation: bag::Quaternion { x: q.i, y: q.j, z: q.k, w: q.w },
            };
            writer.write(gt_topic, (t * 1e9) as u64, &message)?;
        }
    }
    writer.finish()?;
    let bytes = std::fs::read(&path)?;
    std::fs::remove_dir_all(&dir)?;
    Ok(bytes)
}

/// A page written by the exporter over an empty page: `steps` keyframes bending both knees.
fn exported_page(steps: u32, move_s: f64, pause_s: f64) -> Result<Vec<u8>> {
    let (map, limits) = step_executor::inputs::import_tables()?;
    let keyframes: Vec<Keyframe> = (0..steps)
        .map(|i| {
            let mut positions = vec![0.05; 12];
            positions[6] = 0.3 + 0.15 * f64::from(i);
            positions[7] = 0.3 + 0.15 * f64::from(i);
            Keyframe { positions, move_s, pause_s }
        })
        .collect();
    let page = keyframes_to_page(&keyframes, &map, &limits, &Page::empty(), page_name("knee bend")?)?.page;
    Ok([&[0u8][..], &page.to_bytes()].concat())
}

fn patch_msg(surface: u8, boundary: u8, curvatures: Vec<f64>, boundary_params: Vec<f64>) -> Patch {
    Patch {
        id: 1,
        surface,
        boundary,
        curvatures,
        boundary_params,
        rotation: [0.1, 0.2, 0.3],
        center: [0.1, 0.05, 0.9],
        ..Default::default()
    }
}

fn main() -> Result<()> {
    let t = "cdr_sensor_messages";
    write(t, "image_16uc1", &selected(0, cdr(&depth_mm())?))?;
    write(t, "image_32fc1", &selected(0, cdr(&depth_m())?))?;
    write(t, "camera_info", &selected(1, cdr(&camera_info())?))?;
    write(t, "imu", &selected(2, cdr(&imu())?))?;

    let (tum_info, tum_imu, tum_image) = tum_frame(0, 10)?;
    write(t, "tum_fr1_xyz_image_64x48", &selected(0, cdr(&tum_image)?))?;
    write(t, "tum_fr1_xyz_camera_info", &selected(1, cdr(&tum_info)?))?;
    write(t, "tum_fr1_xyz_imu", &selected(2, cdr(&tum_imu)?))?;

    let t = "pipeline_frame";
    write(t, "floor_16uc1", &patch_mapper::inputs::encode_pipeline_frame(&camera_info(), &imu(), &depth_mm())?)?;
    let tum = patch_mapper::inputs::encode_pipeline_frame(&tum_info, &tum_imu, &tum_image)?;
    ensure!(patch_mapper::inputs::pipeline_frame(&tum).is_ok(), "the TUM frame must run through the pipeline");
    write(t, "tum_fr1_xyz_64x48", &tum)?;

    let t = "mcap_bag";
    for (name, frames, compression, tf) in [
        ("tum_fr1_xyz_zstd", 3, Compression::Zstd, false),
        ("tum_fr1_xyz_lz4_tf", 2, Compression::Lz4, true),
        ("tum_fr1_xyz_uncompressed", 2, Compression::None, false),
    ] {
        let bytes = tum_bag(frames, compression, tf)?;
        let summary = patch_mapper::inputs::bag(&bytes)?;
        ensure!(summary.frames == frames && summary.skipped == 0, "{name}: {summary:?}");
        write(t, name, &bytes)?;
    }

    let t = "action_page";
    for (name, steps, move_s, pause_s) in [("knee_bend_3", 3, 0.4, 0.1), ("knee_bend_7_slow", 7, 1.2, 0.5), ("one_step", 1, 0.2, 0.0)] {
        let bytes = exported_page(steps, move_s, pause_s)?;
        ensure!(step_executor::inputs::action_page(&bytes)?.keyframes == steps as usize, "{name}");
        write(t, name, &bytes)?;
    }
    let mut empty = Page::empty().to_bytes().to_vec();
    empty.insert(0, 1);
    write(t, "empty_page", &empty)?;

    let t = "cdr_patch_array";
    let mut map = PatchArray::default();
    map.header.stamp = stamp();
    map.camera_pose.orientation.w = 1.0;
    let mut plane = patch_msg(Patch::PLANE, Patch::CIRCLE, vec![], vec![0.03]);
    plane.covariance = (0..36).map(|i| if i % 7 == 0 { 1e-4 } else { 0.0 }).collect();
    map.patches = vec![
        plane,
        patch_msg(Patch::ELLIPTIC_PARABOLOID, Patch::ELLIPSE, vec![4.0, 2.0], vec![0.03, 0.02]),
        patch_msg(Patch::CYLINDRIC_PARABOLOID, Patch::RECTANGLE, vec![-10.0], vec![0.04, 0.02]),
        patch_msg(Patch::PLANE, Patch::QUADRILATERAL, vec![], vec![0.03, 0.02, 0.03, 0.02, 1.0]),
    ];
    write(t, "four_patches", &cdr(&map)?)?;
    write(t, "empty", &cdr(&PatchArray { camera_pose: map.camera_pose.clone(), ..Default::default() })?)?;

    let t = "cdr_service_requests";
    write(t, "record_keyframe", &selected(0, cdr(&srv::RecordKeyframeRequest { duration: 0.5, pause: 0.1 })?))?;
    let point = Point { x: 0.12, y: 0.04, z: -0.3 };
    write(t, "select_nearest", &selected(1, cdr(&srv::SelectTargetRequest { mode: 0, point: point.clone(), radius: 0.0 })?))?;
    write(t, "select_fit", &selected(1, cdr(&srv::SelectTargetRequest { mode: 1, point, radius: 0.05 })?))?;
    write(t, "save_motion", &selected(2, cdr(&srv::SaveMotionRequest { name: "rock 1".into() })?))?;
    write(t, "list_motions", &selected(3, cdr(&srv::ListMotionsRequest::default())?))?;
    write(t, "delete_motion", &selected(4, cdr(&srv::DeleteMotionRequest { name: "replay_step".into() })?))?;
    write(t, "play_motion", &selected(5, cdr(&srv::PlayMotionRequest { name: "replay_step".into() })?))?;

    let t = "dynamixel_status_frames";
    let mut stream = vec![7u8];
    stream.extend(encode_status(1, 0, &[0x06, 0x04, 0x26]));
    stream.extend(encode_status(2, 0x80, &[0x00, 0x08, 0x00, 0x00]));
    stream.extend(encode(3, instruction::READ, &[132, 0, 4, 0]));
    stream.extend([0xFF, 0xFF, 0xFD, 0x00, 0x05, 0x02, 0x00]);
    write(t, "statuses_echo_noise", &stream)?;
    write(t, "stuffed", &[&[0u8][..], &encode_status(4, 0, &[0xFF, 0xFF, 0xFD, 0x01])].concat())?;

    let t = "dynamixel_sim_chain";
    let mut chain = encode(BROADCAST_ID, instruction::PING, &[]);
    chain.extend(encode(1, instruction::WRITE, &[64, 0, 1]));
    chain.extend(encode(1, instruction::WRITE, &[116, 0, 0x00, 0x09, 0x00, 0x00]));
    chain.extend(encode(BROADCAST_ID, instruction::SYNC_READ, &[132, 0, 4, 0, 1, 2, 3]));
    chain.extend(encode(BROADCAST_ID, instruction::SYNC_WRITE, &[116, 0, 4, 0, 2, 0, 8, 0, 0, 3, 0, 8, 0, 0]));
    chain.extend(encode(2, instruction::READ, &[0, 0, 146, 0]));
    chain.extend(encode(2, instruction::REBOOT, &[]));
    write(t, "ping_write_sync", &chain)?;

    let t = "motion_library";
    let joints = step_executor::config::StepExecutorConfig::default().joint_names();
    let mut library = MotionLibrary::new(Path::new("motions.yaml"), joints.clone());
    for (name, surface, boundary, d, k) in [
        ("flat rock", SurfaceType::Plane, BoundaryType::Circle, vec![0.03], Vector2::zeros()),
        ("log", SurfaceType::CylindricParaboloid, BoundaryType::Rectangle, vec![0.04, 0.02], Vector2::new(0.0, -11.0)),
        ("bump", SurfaceType::EllipticParaboloid, BoundaryType::Ellipse, vec![0.03, 0.02], Vector2::new(-8.0, -5.0)),
    ] {
        let patch = SplPatch::new(surface, boundary, d, k, Vector3::new(0.1, -0.2, 0.05), Vector3::new(0.12, 0.04, -0.3))?;
        let keyframes = (0..3).map(|i| Keyframe { positions: vec![0.1 * f64::from(i); joints.len()], move_s: 0.5, pause_s: 0.1 }).collect();
        library.insert(Motion { name: name.into(), patch, keyframes })?;
    }
    let text = library.to_yaml()?;
    write(t, "three_motions", text.as_bytes())?;
    write(t, "three_motions_bom", format!("\u{FEFF}{text}").as_bytes())?;

    let t = "params_yaml";
    for name in ["step_executor", "terrain_sim"] {
        let text = std::fs::read(format!("config/{name}.yaml")).with_context(|| format!("config/{name}.yaml"))?;
        write(t, name, &text)?;
    }
    write(t, "overrides", b"player:\n  cycle_ms: 8\n\0matcher.diagnostics=3\0ros.status_rate_hz:=10")?;
    Ok(())
}

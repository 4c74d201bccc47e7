//! The entry points on well-formed inputs, and every stored fuzz input (seeds, minimised corpus,
//! inputs that once crashed) replayed through them: each must give a result or a typed error.

use super::*;

use patchwalk_test_support::stored_fuzz_inputs as stored_inputs;

fn camera_info(width: u32, height: u32) -> CameraInfo {
    let mut info = CameraInfo { width, height, ..Default::default() };
    info.k = [52.5, 0.0, 31.5, 0.0, 52.5, 23.5, 0.0, 0.0, 1.0];
    info
}

fn floor_image(width: u32, height: u32) -> Image {
    let data = (0..height).flat_map(|v| (0..width).map(move |_| 700 + 4 * v as u16)).flat_map(u16::to_le_bytes).collect();
    let mut image = Image { width, height, encoding: "16UC1".into(), step: 2 * width, data, ..Default::default() };
    image.header.stamp = Time { sec: 1_000_000_000, nanosec: 0 };
    image
}

fn gravity() -> Imu {
    let mut imu = Imu::default();
    imu.header.stamp = Time { sec: 999_999_999, nanosec: 990_000_000 };
    imu.linear_acceleration.y = 9.81;
    imu
}

fn selected(selector: u8, payload: Vec<u8>) -> Vec<u8> {
    [vec![selector], payload].concat()
}

#[test]
fn sensor_messages_decode_and_convert() {
    match sensor_message(&selected(0, wire::encode(&floor_image(4, 2)).unwrap())).unwrap() {
        SensorOutput::Depth { width, height, valid } => assert_eq!((width, height, valid), (4, 2, 8)),
        other => panic!("{other:?}"),
    }
    assert!(
        matches!(sensor_message(&selected(1, wire::encode(&camera_info(64, 48)).unwrap())), Ok(SensorOutput::Intrinsics(i)) if i.width == 64)
    );
    assert!(matches!(sensor_message(&selected(2, wire::encode(&gravity()).unwrap())), Ok(SensorOutput::Acceleration(a)) if a[1] == 9.81));
    assert!(matches!(sensor_message(&[]), Err(InputError::Empty)));
    assert!(matches!(sensor_message(&[9, 0, 1, 0, 0]), Err(InputError::Selector(9))));
    assert!(matches!(sensor_message(&[0, 0, 1, 0, 0, 1]), Err(InputError::Wire(_))));
    let mut future = gravity();
    future.header.stamp.sec = 2_000_000_000;
    let err = sensor_message(&selected(2, wire::encode(&future).unwrap())).unwrap_err().to_string();
    assert!(err.contains("ahead of the node clock"), "{err}");
}

#[test]
fn a_frame_runs_through_the_pipeline_and_bad_frames_are_named() {
    let frame = encode_pipeline_frame(&camera_info(64, 48), &gravity(), &floor_image(64, 48)).unwrap();
    let summary = pipeline_frame(&frame).unwrap();
    assert!(summary.seeds <= 256, "{summary:?}");
    let mismatch = encode_pipeline_frame(&camera_info(64, 48), &gravity(), &floor_image(32, 48)).unwrap();
    assert!(matches!(pipeline_frame(&mismatch), Err(InputError::SizeMismatch { .. })));
    let big = encode_pipeline_frame(&camera_info(128, 96), &gravity(), &floor_image(128, 96)).unwrap();
    assert!(matches!(pipeline_frame(&big), Err(InputError::Budget { pixels: 12288 })));
    assert!(matches!(pipeline_frame(&[200, 0, 1]), Err(InputError::Length { length: 200, left: 1 })));
}

#[test]
fn stored_sensor_message_inputs_are_handled() {
    for (path, bytes) in stored_inputs("cdr_sensor_messages") {
        if let Err(e) = sensor_message(&bytes) {
            assert!(!e.to_string().is_empty(), "{}", path.display());
        }
    }
}

#[test]
fn stored_pipeline_frame_inputs_are_handled() {
    let mut accepted = 0;
    for (path, bytes) in stored_inputs("pipeline_frame") {
        match pipeline_frame(&bytes) {
            Ok(_) => accepted += 1,
            Err(e) => assert!(!e.to_string().is_empty(), "{}", path.display()),
        }
    }
    assert!(accepted > 0, "the seed frame must run through the pipeline");
}

/// A two-frame bag on the replay topics (CameraInfo, IMU, depth, ground truth), as an MCAP file's bytes.
fn tiny_bag(compression: patchwalk_bag::Compression) -> Vec<u8> {
    use patchwalk_bag::messages as bag;
    use patchwalk_bag::metadata::Qos;
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("tiny.mcap");
    let mut writer = patchwalk_bag::BagWriter::create(&path, compression).unwrap();
    let topics = replay_bag_topics();
    let info_topic = writer.add_topic::<bag::CameraInfo>(&topics.camera_info, Qos::SensorData).unwrap();
    let imu_topic = writer.add_topic::<bag::Imu>(&topics.imu, Qos::SensorData).unwrap();
    let depth_topic = writer.add_topic::<bag::Image>(&topics.depth, Qos::SensorData).unwrap();
    let pose_topic = writer.add_topic::<bag::PoseStamped>(&topics.groundtruth, Qos::Reliable(10)).unwrap();
    let (width, height) = (8u32, 6u32);
    for frame in 0..2u32 {
        let stamp = bag::Time { sec: 100, nanosec: frame * 33_000_000 };
        let t = stamp.nanos() as u64;
        let header = bag::Header::new(stamp, "camera_depth_optical_frame");
        let mut info = bag::CameraInfo { header: header.clone(), width, height, ..Default::default() };
        info.k = [7.0, 0.0, 3.5, 0.0, 7.0, 2.5, 0.0, 0.0, 1.0];
        writer.write(info_topic, t, &info).unwrap();
        let imu = bag::Imu { header: header.clone(), linear_acceleration: bag::Vector3::new(0.0, 9.81, 0.0), ..Default::default() };
        writer.write(imu_topic, t, &imu).unwrap();
        let data = (0..width * height).flat_map(|i| (800 + i as u16).to_le_bytes()).collect();
        let image = bag::Image { header: header.clone(), width, height, encoding: "16UC1".into(), is_bigendian: 0, step: 2 * width, data };
        writer.write(depth_topic, t, &image).unwrap();
        writer.write(pose_topic, t, &bag::PoseStamped { header, ..Default::default() }).unwrap();
    }
    writer.finish().unwrap();
    std::fs::read(&path).unwrap()
}

#[test]
fn a_bag_in_memory_reads_as_replay_reads_it() {
    for compression in [patchwalk_bag::Compression::Zstd, patchwalk_bag::Compression::None] {
        let bytes = tiny_bag(compression);
        let summary = bag(&bytes).unwrap();
        assert_eq!(
            (summary.frames, summary.imu_samples, summary.groundtruth_poses, summary.skipped, summary.broken),
            (2, 2, 2, 0, false),
            "{compression:?}"
        );
        // Cut in its data section: nothing usable before the cut, or the frames before it, and the
        // bag reported broken (its summary and footer are gone).
        match bag(&bytes[..bytes.len() / 2]) {
            Ok(summary) => assert!(summary.broken && summary.frames <= 2, "{summary:?}"),
            Err(e) => assert!(e.to_string().contains("input.mcap"), "{e}"),
        }
    }
    let err = bag(b"not an mcap file").unwrap_err().to_string();
    assert!(err.contains("input.mcap: not a readable MCAP file"), "{err}");
}

#[test]
fn stored_bag_inputs_are_handled() {
    let mut accepted = 0;
    for (path, bytes) in stored_inputs("mcap_bag") {
        match bag(&bytes) {
            Ok(_) => accepted += 1,
            Err(e) => assert!(!e.to_string().is_empty(), "{}", path.display()),
        }
    }
    assert!(accepted > 0, "the seed bags must be read");
}

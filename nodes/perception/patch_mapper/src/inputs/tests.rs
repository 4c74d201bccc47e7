//! The entry points on well-formed inputs, and every stored fuzz input (seeds, minimised corpus,
//! inputs that once crashed) replayed through them: each must give a result or a typed error.

use super::*;
use std::path::{Path, PathBuf};

/// Every file of `tests/data/fuzz/<target>/` (a missing directory is a failure: the corpus is part
/// of the repository).
fn stored_inputs(target: &str) -> Vec<(PathBuf, Vec<u8>)> {
    let dir = Path::new(env!("CARGO_MANIFEST_DIR")).join("../../../tests/data/fuzz").join(target);
    let mut inputs: Vec<(PathBuf, Vec<u8>)> = std::fs::read_dir(&dir)
        .unwrap_or_else(|e| panic!("{}: {e}", dir.display()))
        .map(|entry| entry.unwrap().path())
        .map(|path| {
            let bytes = std::fs::read(&path).unwrap();
            (path, bytes)
        })
        .collect();
    inputs.sort();
    assert!(!inputs.is_empty(), "no stored inputs in {}", dir.display());
    inputs
}

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

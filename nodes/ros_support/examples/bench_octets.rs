//! Encode and decode time of a 640×480 16UC1 depth image and a 57,600-point PointCloud2 (the
//! birds-eye cloud's largest), as the nodes' DDS readers and writers do it (`patchwalk_ros::wire`):
//! `patchwalk_msgs`' `Image` and `PointCloud2` (byte arrays in one block) side by side with the
//! upstream types (one serde call per byte). Prints the median of 200 rounds per type.
//!
//! Usage: `cargo run --release -p patchwalk_ros --example bench_octets`

use std::time::Instant;

use patchwalk_msgs::sensor_msgs::msg::{Image, PointCloud2, PointField};
use patchwalk_ros::wire::{decode, encode};
use ros2_interfaces_jazzy_serde::sensor_msgs::msg as upstream;
use serde::de::DeserializeOwned;
use serde::Serialize;

const ROUNDS: usize = 200;

/// Median (ms) of `ROUNDS` runs of `f`.
fn median_ms(mut f: impl FnMut()) -> f64 {
    let mut times: Vec<f64> = (0..ROUNDS)
        .map(|_| {
            let start = Instant::now();
            f();
            start.elapsed().as_secs_f64() * 1e3
        })
        .collect();
    times.sort_by(f64::total_cmp);
    times.get(ROUNDS / 2).copied().unwrap_or(f64::NAN)
}

fn row<T: Serialize + DeserializeOwned>(name: &str, value: &T) {
    let payload = match encode(value) {
        Ok(payload) => payload,
        Err(e) => return eprintln!("  {name}: {e}"),
    };
    let encode_ms = median_ms(|| {
        std::hint::black_box(encode(value).ok());
    });
    let decode_ms = median_ms(|| {
        std::hint::black_box(decode::<T>(&payload).ok());
    });
    println!("  {name:<32} {:>9} bytes   encode {encode_ms:7.3} ms   decode {decode_ms:7.3} ms", payload.len());
}

fn main() {
    let data: Vec<u8> = (0..640 * 480 * 2).map(|i| (i % 251) as u8).collect();
    let image = Image { height: 480, width: 640, encoding: "16UC1".into(), step: 1280, data: data.clone(), ..Default::default() };
    let upstream_image = upstream::Image {
        header: image.header.clone(),
        height: 480,
        width: 640,
        encoding: "16UC1".into(),
        is_bigendian: 0,
        step: 1280,
        data,
    };
    let field = |name: &str, offset: u32| PointField { name: name.into(), offset, datatype: PointField::FLOAT32, count: 1 };
    let points: Vec<u8> = (0..57_600 * 3).flat_map(|i| (i as f32 * 1e-3).to_le_bytes()).collect();
    let cloud = PointCloud2 {
        height: 1,
        width: 57_600,
        fields: vec![field("x", 0), field("y", 4), field("z", 8)],
        point_step: 12,
        row_step: 57_600 * 12,
        data: points.clone(),
        is_dense: true,
        ..Default::default()
    };
    let upstream_cloud = upstream::PointCloud2 {
        header: cloud.header.clone(),
        height: 1,
        width: 57_600,
        fields: cloud.fields.clone(),
        is_bigendian: false,
        point_step: 12,
        row_step: 57_600 * 12,
        data: points,
        is_dense: true,
    };
    println!("bench_octets: CDR (little endian) through rustdds' serializer and reader adapter, median of {ROUNDS}");
    row("Image 640x480 16UC1 (ours)", &image);
    row("Image 640x480 16UC1 (upstream)", &upstream_image);
    row("PointCloud2 57,600 xyz (ours)", &cloud);
    row("PointCloud2 57,600 xyz (upstream)", &upstream_cloud);
}

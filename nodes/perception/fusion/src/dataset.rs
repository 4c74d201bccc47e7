//! Readers for recorded data: TUM RGB-D directories, directories of depth PNGs with an intrinsics
//! JSON (Open3D layout), single PNGs, TUM pose files and Open3D trajectory logs.
//!
//! `Dataset::open` detects the layout:
//! - TUM: a directory with `depth.txt` (+ optional `accelerometer.txt`, `groundtruth.txt`);
//!   depth in units of 1/5000 m; intrinsics from an `intrinsics.json` in the directory, else
//!   TUM's freiburg1 calibration.
//! - PNG directory: `depth/*.png` (or `*.png` directly) + a `*.json` with intrinsics (Open3D's
//!   `{"width","height","intrinsic_matrix":[column-major 3×3]}` or `{"width","height","fx","fy","cx","cy"}`,
//!   optional `"depth_scale"` in units per metre, default 1000); optional `trajectory.log`.
//! - One PNG: intrinsics from a JSON beside it, or an OpenCV `calib_params.xml` (IR intrinsics).

use std::path::{Path, PathBuf};

use nalgebra::{Isometry3, Matrix3, Matrix4, Quaternion, Rotation3, Translation3, UnitQuaternion, Vector3};

use crate::camera::{CameraError, DepthImage, Intrinsics};

/// Errors from reading recorded data; each names the file (and line) at fault.
#[derive(Debug, thiserror::Error)]
pub enum DatasetError {
    #[error("{path}: {source}")]
    Io { path: PathBuf, source: std::io::Error },
    #[error("{path}: not a 16-bit grayscale PNG depth image: {reason}")]
    Png { path: PathBuf, reason: String },
    #[error("{path}:{line}: {reason}")]
    Parse { path: PathBuf, line: usize, reason: String },
    #[error("{path}: {reason}")]
    Layout { path: PathBuf, reason: String },
    #[error("{path}: {source}")]
    Camera { path: PathBuf, source: CameraError },
}

/// One depth frame of a dataset: its timestamp (s) and PNG file.
#[derive(Debug, Clone, PartialEq)]
pub struct DepthFrame {
    pub timestamp: f64,
    pub path: PathBuf,
}

/// A timestamped accelerometer sample (m/s², in the IMU frame).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct AccelSample {
    pub timestamp: f64,
    pub acceleration_in_imu: Vector3<f64>,
}

/// A timestamped camera pose (`world_from_camera`).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct StampedPose {
    pub timestamp: f64,
    pub world_from_camera: Isometry3<f64>,
}

/// A recorded depth sequence with whatever side data it came with.
#[derive(Debug, Clone)]
pub struct Dataset {
    pub root: PathBuf,
    pub intrinsics: Intrinsics,
    /// Metres per raw 16-bit unit (TUM 1/5000, millimetre PNGs 1/1000).
    pub metres_per_unit: f64,
    pub frames: Vec<DepthFrame>,
    /// Accelerometer samples sorted by time (TUM only).
    pub accelerometer: Vec<AccelSample>,
    /// Ground-truth camera poses sorted by time (TUM `groundtruth.txt`, or Open3D `trajectory.log`
    /// with frame index as timestamp).
    pub groundtruth: Vec<StampedPose>,
}

impl Dataset {
    /// Opens a TUM directory, a PNG directory with intrinsics, or a single PNG (see module docs).
    pub fn open(path: &Path) -> Result<Self, DatasetError> {
        if path.is_file() {
            return open_single_png(path);
        }
        if path.join("depth.txt").is_file() {
            return open_tum(path);
        }
        if path.is_dir() {
            return open_png_dir(path);
        }
        Err(DatasetError::Layout { path: path.to_path_buf(), reason: "no such file or directory".into() })
    }

    /// Loads frame `index` as a metric depth image.
    pub fn load_depth(&self, index: usize) -> Result<DepthImage, DatasetError> {
        let frame = self.frames.get(index).ok_or_else(|| DatasetError::Layout {
            path: self.root.clone(),
            reason: format!("frame {index} out of range ({} frames)", self.frames.len()),
        })?;
        let image = load_depth_png(&frame.path, self.metres_per_unit)?;
        if image.width != self.intrinsics.width || image.height != self.intrinsics.height {
            return Err(DatasetError::Layout {
                path: frame.path.clone(),
                reason: format!(
                    "image is {}x{} but the intrinsics are for {}x{}",
                    image.width, image.height, self.intrinsics.width, self.intrinsics.height
                ),
            });
        }
        Ok(image)
    }

    /// Ground-truth pose nearest in time to `timestamp`, if one lies within `max_gap` seconds.
    pub fn groundtruth_near(&self, timestamp: f64, max_gap: f64) -> Option<StampedPose> {
        nearest_by_time(&self.groundtruth, timestamp, |pose| pose.timestamp)
            .filter(|pose| (pose.timestamp - timestamp).abs() <= max_gap)
            .copied()
    }

    /// The accelerometer reading (m/s², IMU frame) within `half_window` seconds of `timestamp`: the
    /// per-axis median of the samples there ([`median_per_axis`]).
    pub fn acceleration_near(&self, timestamp: f64, half_window: f64) -> Option<Vector3<f64>> {
        let start = self.accelerometer.partition_point(|s| s.timestamp < timestamp - half_window);
        let readings: Vec<Vector3<f64>> = self.accelerometer[start..]
            .iter()
            .take_while(|s| s.timestamp <= timestamp + half_window)
            .map(|s| s.acceleration_in_imu)
            .collect();
        median_per_axis(&readings)
    }
}

/// Element of a time-sorted slice nearest to `timestamp`.
pub fn nearest_by_time<T>(sorted: &[T], timestamp: f64, time_of: impl Fn(&T) -> f64) -> Option<&T> {
    let index = sorted.partition_point(|item| time_of(item) < timestamp);
    let after = sorted.get(index);
    let before = index.checked_sub(1).and_then(|i| sorted.get(i));
    match (before, after) {
        (Some(b), Some(a)) => Some(if timestamp - time_of(b) <= time_of(a) - timestamp { b } else { a }),
        (b, a) => b.or(a),
    }
}

/// Reads a 16-bit grayscale PNG into metres (0 = no data → NaN).
pub fn load_depth_png(path: &Path, metres_per_unit: f64) -> Result<DepthImage, DatasetError> {
    let png_error = |reason: String| DatasetError::Png { path: path.to_path_buf(), reason };
    let file = std::fs::File::open(path).map_err(|source| DatasetError::Io { path: path.to_path_buf(), source })?;
    let decoder = png::Decoder::new(std::io::BufReader::new(file));
    let mut reader = decoder.read_info().map_err(|e| png_error(e.to_string()))?;
    let info = reader.info();
    let (width, height) = (info.width as usize, info.height as usize);
    if info.color_type != png::ColorType::Grayscale || info.bit_depth != png::BitDepth::Sixteen {
        return Err(png_error(format!("colour type {:?}, bit depth {:?}", info.color_type, info.bit_depth)));
    }
    let mut buffer = vec![0u8; width * height * 2];
    reader.next_frame(&mut buffer).map_err(|e| png_error(e.to_string()))?;
    let raw: Vec<u16> = buffer.chunks_exact(2).map(|b| u16::from_be_bytes([b[0], b[1]])).collect();
    DepthImage::from_u16(width, height, &raw, metres_per_unit).map_err(|source| DatasetError::Camera { path: path.to_path_buf(), source })
}

/// Writes metric depth as a 16-bit PNG (`metres_per_unit` per count; NaN → 0).
pub fn save_depth_png(path: &Path, image: &DepthImage, metres_per_unit: f64) -> Result<(), DatasetError> {
    let io = |source| DatasetError::Io { path: path.to_path_buf(), source };
    let file = std::fs::File::create(path).map_err(io)?;
    let mut encoder = png::Encoder::new(std::io::BufWriter::new(file), image.width as u32, image.height as u32);
    encoder.set_color(png::ColorType::Grayscale);
    encoder.set_depth(png::BitDepth::Sixteen);
    let png_error = |e: png::EncodingError| DatasetError::Png { path: path.to_path_buf(), reason: e.to_string() };
    let mut writer = encoder.write_header().map_err(png_error)?;
    let bytes: Vec<u8> = image
        .depth_m
        .iter()
        .flat_map(|&d| {
            let units = if d.is_finite() { (f64::from(d) / metres_per_unit).round().clamp(0.0, 65535.0) as u16 } else { 0 };
            units.to_be_bytes()
        })
        .collect();
    writer.write_image_data(&bytes).map_err(png_error)?;
    writer.finish().map_err(png_error)
}

/// Reads TUM pose lines `timestamp tx ty tz qx qy qz qw` (camera pose in the world).
pub fn read_tum_poses(path: &Path) -> Result<Vec<StampedPose>, DatasetError> {
    let mut poses = Vec::new();
    for (line_number, values) in numeric_lines(path)? {
        let [t, tx, ty, tz, qx, qy, qz, qw] = fixed::<8>(path, line_number, &values)?;
        let rotation = UnitQuaternion::from_quaternion(Quaternion::new(qw, qx, qy, qz));
        poses.push(StampedPose { timestamp: t, world_from_camera: Isometry3::from_parts(Translation3::new(tx, ty, tz), rotation) });
    }
    poses.sort_by(|a, b| a.timestamp.total_cmp(&b.timestamp));
    Ok(poses)
}

/// Writes poses in TUM format (`timestamp tx ty tz qx qy qz qw`).
pub fn write_tum_poses(path: &Path, poses: &[StampedPose]) -> Result<(), DatasetError> {
    let mut text = String::from("# timestamp tx ty tz qx qy qz qw\n");
    for pose in poses {
        let t = pose.world_from_camera.translation.vector;
        let q = pose.world_from_camera.rotation;
        text.push_str(&format!("{:.6} {:.6} {:.6} {:.6} {:.6} {:.6} {:.6} {:.6}\n", pose.timestamp, t.x, t.y, t.z, q.i, q.j, q.k, q.w));
    }
    std::fs::write(path, text).map_err(|source| DatasetError::Io { path: path.to_path_buf(), source })
}

/// Reads an Open3D `.log` trajectory: per frame a header line then 4 rows of a 4×4
/// `world_from_camera` matrix. The frame index becomes the timestamp.
pub fn read_open3d_log(path: &Path) -> Result<Vec<StampedPose>, DatasetError> {
    let lines = numeric_lines(path)?;
    let mut poses = Vec::new();
    for chunk in lines.chunks(5) {
        let [(header_line, header), rows @ ..] = chunk else { continue };
        if rows.len() != 4 {
            return Err(DatasetError::Parse { path: path.to_path_buf(), line: *header_line, reason: "incomplete 4x4 block".into() });
        }
        let mut matrix = Matrix4::zeros();
        for (r, (line_number, values)) in rows.iter().enumerate() {
            let row = fixed::<4>(path, *line_number, values)?;
            for (c, value) in row.iter().enumerate() {
                matrix[(r, c)] = *value;
            }
        }
        let frame_index = header.first().copied().unwrap_or(poses.len() as f64);
        poses.push(StampedPose { timestamp: frame_index, world_from_camera: isometry_from_matrix(&matrix) });
    }
    Ok(poses)
}

/// Rigid transform from a homogeneous matrix (rotation re-orthonormalised).
pub fn isometry_from_matrix(matrix: &Matrix4<f64>) -> Isometry3<f64> {
    let rotation_matrix: Matrix3<f64> = matrix.fixed_view::<3, 3>(0, 0).into_owned();
    let rotation = UnitQuaternion::from_rotation_matrix(&Rotation3::from_matrix(&rotation_matrix));
    Isometry3::from_parts(Translation3::new(matrix[(0, 3)], matrix[(1, 3)], matrix[(2, 3)]), rotation)
}

/// Reads intrinsics JSON (Open3D layout or explicit fx/fy/cx/cy). Returns intrinsics and, if
/// present, the depth scale in raw units per metre.
pub fn read_intrinsics_json(path: &Path) -> Result<(Intrinsics, Option<f64>), DatasetError> {
    let text = std::fs::read_to_string(path).map_err(|source| DatasetError::Io { path: path.to_path_buf(), source })?;
    let parse = |reason: String| DatasetError::Parse { path: path.to_path_buf(), line: 0, reason };
    let value: serde_json::Value = serde_json::from_str(&text).map_err(|e| parse(e.to_string()))?;
    let number = |key: &str| value.get(key).and_then(serde_json::Value::as_f64);
    let (width, height) = match (number("width"), number("height")) {
        (Some(w), Some(h)) if w >= 1.0 && h >= 1.0 => (w as usize, h as usize),
        _ => return Err(parse("missing or invalid \"width\"/\"height\"".into())),
    };
    let (fx, fy, cx, cy) = if let Some(matrix) = value.get("intrinsic_matrix").and_then(serde_json::Value::as_array) {
        let m: Vec<f64> = matrix.iter().filter_map(serde_json::Value::as_f64).collect();
        if m.len() != 9 {
            return Err(parse(format!("\"intrinsic_matrix\" has {} numbers, expected 9", m.len())));
        }
        // Column-major 3×3 (Open3D): [fx 0 0 0 fy 0 cx cy 1].
        (m[0], m[4], m[6], m[7])
    } else {
        match (number("fx"), number("fy"), number("cx"), number("cy")) {
            (Some(fx), Some(fy), Some(cx), Some(cy)) => (fx, fy, cx, cy),
            _ => return Err(parse("needs \"intrinsic_matrix\" or \"fx\",\"fy\",\"cx\",\"cy\"".into())),
        }
    };
    let intrinsics =
        Intrinsics::new(width, height, fx, fy, cx, cy).map_err(|source| DatasetError::Camera { path: path.to_path_buf(), source })?;
    Ok((intrinsics, number("depth_scale")))
}

/// Reads the IR camera intrinsics (`IR_intrinsic_params`) of an OpenCV storage XML (CAPE layout).
pub fn read_opencv_ir_intrinsics(path: &Path, width: usize, height: usize) -> Result<Intrinsics, DatasetError> {
    let text = std::fs::read_to_string(path).map_err(|source| DatasetError::Io { path: path.to_path_buf(), source })?;
    let parse = |reason: &str| DatasetError::Parse { path: path.to_path_buf(), line: 0, reason: reason.into() };
    let section = text.split("<IR_intrinsic_params").nth(1).ok_or_else(|| parse("no <IR_intrinsic_params> element"))?;
    let data = section
        .split("<data>")
        .nth(1)
        .and_then(|rest| rest.split("</data>").next())
        .ok_or_else(|| parse("<IR_intrinsic_params> has no <data>"))?;
    let values: Vec<f64> = data.split_whitespace().filter_map(|s| s.parse().ok()).collect();
    if values.len() != 9 {
        return Err(parse("<IR_intrinsic_params> needs 9 numbers"));
    }
    // Row-major 3×3: [fx 0 cx; 0 fy cy; 0 0 1].
    Intrinsics::new(width, height, values[0], values[4], values[2], values[5])
        .map_err(|source| DatasetError::Camera { path: path.to_path_buf(), source })
}

fn open_tum(root: &Path) -> Result<Dataset, DatasetError> {
    let depth_list = root.join("depth.txt");
    let text = read_text(&depth_list)?;
    let mut frames = Vec::new();
    for (index, line) in text.lines().enumerate() {
        let line = line.trim();
        if line.is_empty() || line.starts_with('#') {
            continue;
        }
        let mut fields = line.split_whitespace();
        let (Some(stamp), Some(file)) = (fields.next(), fields.next()) else {
            return Err(DatasetError::Parse { path: depth_list.clone(), line: index + 1, reason: "expected `timestamp filename`".into() });
        };
        let timestamp: f64 = stamp.parse().map_err(|_| DatasetError::Parse {
            path: depth_list.clone(),
            line: index + 1,
            reason: format!("bad timestamp {stamp:?}"),
        })?;
        frames.push(DepthFrame { timestamp, path: root.join(file) });
    }
    frames.sort_by(|a, b| a.timestamp.total_cmp(&b.timestamp));
    let accelerometer_path = root.join("accelerometer.txt");
    let mut accelerometer = Vec::new();
    if accelerometer_path.is_file() {
        for (line_number, values) in numeric_lines(&accelerometer_path)? {
            let [t, ax, ay, az] = fixed::<4>(&accelerometer_path, line_number, &values)?;
            accelerometer.push(AccelSample { timestamp: t, acceleration_in_imu: Vector3::new(ax, ay, az) });
        }
        accelerometer.sort_by(|a, b| a.timestamp.total_cmp(&b.timestamp));
    }
    let groundtruth_path = root.join("groundtruth.txt");
    let groundtruth = if groundtruth_path.is_file() { read_tum_poses(&groundtruth_path)? } else { Vec::new() };
    let intrinsics_path = root.join("intrinsics.json");
    let (intrinsics, units_per_metre) =
        if intrinsics_path.is_file() { read_intrinsics_json(&intrinsics_path)? } else { (Intrinsics::tum_freiburg1(), None) };
    Ok(Dataset {
        root: root.to_path_buf(),
        intrinsics,
        metres_per_unit: 1.0 / units_per_metre.unwrap_or(5000.0),
        frames,
        accelerometer,
        groundtruth,
    })
}

fn open_png_dir(root: &Path) -> Result<Dataset, DatasetError> {
    let depth_dir = if root.join("depth").is_dir() { root.join("depth") } else { root.to_path_buf() };
    let mut pngs = list_with_extension(&depth_dir, "png")?;
    pngs.sort();
    if pngs.is_empty() {
        return Err(DatasetError::Layout { path: root.to_path_buf(), reason: "no depth.txt and no PNG files".into() });
    }
    let json = list_with_extension(root, "json")?.into_iter().min().ok_or_else(|| DatasetError::Layout {
        path: root.to_path_buf(),
        reason: "a directory of depth PNGs needs an intrinsics JSON beside them".into(),
    })?;
    let (intrinsics, units_per_metre) = read_intrinsics_json(&json)?;
    let frames = pngs.into_iter().enumerate().map(|(i, path)| DepthFrame { timestamp: i as f64, path }).collect();
    let log = root.join("trajectory.log");
    let groundtruth = if log.is_file() { read_open3d_log(&log)? } else { Vec::new() };
    Ok(Dataset {
        root: root.to_path_buf(),
        intrinsics,
        metres_per_unit: 1.0 / units_per_metre.unwrap_or(1000.0),
        frames,
        accelerometer: Vec::new(),
        groundtruth,
    })
}

fn open_single_png(path: &Path) -> Result<Dataset, DatasetError> {
    let dir = path.parent().unwrap_or(Path::new("."));
    let (intrinsics, metres_per_unit) = if let Some(json) = list_with_extension(dir, "json")?.into_iter().min() {
        let (intrinsics, units_per_metre) = read_intrinsics_json(&json)?;
        (intrinsics, 1.0 / units_per_metre.unwrap_or(1000.0))
    } else if dir.join("calib_params.xml").is_file() {
        let image = load_depth_png(path, 0.001)?;
        (read_opencv_ir_intrinsics(&dir.join("calib_params.xml"), image.width, image.height)?, 0.001)
    } else {
        return Err(DatasetError::Layout {
            path: path.to_path_buf(),
            reason: "a single PNG needs an intrinsics JSON or calib_params.xml beside it".into(),
        });
    };
    Ok(Dataset {
        root: dir.to_path_buf(),
        intrinsics,
        metres_per_unit,
        frames: vec![DepthFrame { timestamp: 0.0, path: path.to_path_buf() }],
        accelerometer: Vec::new(),
        groundtruth: Vec::new(),
    })
}

fn read_text(path: &Path) -> Result<String, DatasetError> {
    std::fs::read_to_string(path).map_err(|source| DatasetError::Io { path: path.to_path_buf(), source })
}

fn list_with_extension(dir: &Path, extension: &str) -> Result<Vec<PathBuf>, DatasetError> {
    let entries = std::fs::read_dir(dir).map_err(|source| DatasetError::Io { path: dir.to_path_buf(), source })?;
    Ok(entries
        .filter_map(Result::ok)
        .map(|entry| entry.path())
        .filter(|p| p.is_file() && p.extension().is_some_and(|e| e.eq_ignore_ascii_case(extension)))
        .collect())
}

/// Non-comment, non-empty lines parsed as whitespace-separated numbers, with 1-based line numbers.
fn numeric_lines(path: &Path) -> Result<Vec<(usize, Vec<f64>)>, DatasetError> {
    let text = read_text(path)?;
    let mut lines = Vec::new();
    for (index, line) in text.lines().enumerate() {
        let line = line.trim();
        if line.is_empty() || line.starts_with('#') {
            continue;
        }
        let values = line
            .split_whitespace()
            .map(|field| field.parse::<f64>())
            .collect::<Result<Vec<_>, _>>()
            .map_err(|e| DatasetError::Parse { path: path.to_path_buf(), line: index + 1, reason: e.to_string() })?;
        lines.push((index + 1, values));
    }
    Ok(lines)
}

fn fixed<const N: usize>(path: &Path, line: usize, values: &[f64]) -> Result<[f64; N], DatasetError> {
    <[f64; N]>::try_from(values).map_err(|_| DatasetError::Parse {
        path: path.to_path_buf(),
        line,
        reason: format!("expected {N} numbers, found {}", values.len()),
    })
}

/// Directory of the vendored recorded data (`tests/data`, a copy of `shared/data`), overridable
/// with `PATCHWALK_DATA`. For tests, benches and examples.
pub fn test_data_dir() -> PathBuf {
    if let Some(dir) = std::env::var_os("PATCHWALK_DATA") {
        return PathBuf::from(dir);
    }
    Path::new(env!("CARGO_MANIFEST_DIR")).join("../../../tests/data")
}

/// The per-axis median of accelerometer readings (`None` when there are none). J 2.2 averages the
/// readings around a frame; the median gives the same on a smooth motion and leaves out a short
/// spike (a foot's impact, a glitch) that would tilt the mean's gravity by tens of degrees.
pub fn median_per_axis(readings: &[Vector3<f64>]) -> Option<Vector3<f64>> {
    if readings.is_empty() {
        return None;
    }
    let median = |axis: usize| {
        let mut values: Vec<f64> = readings.iter().map(|r| r[axis]).collect();
        values.sort_by(f64::total_cmp);
        let middle = values.len() / 2;
        if values.len() % 2 == 1 {
            values[middle]
        } else {
            0.5 * (values[middle - 1] + values[middle])
        }
    };
    Some(Vector3::new(median(0), median(1), median(2)))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn opens_tum_excerpt_with_side_data() {
        let dataset = Dataset::open(&test_data_dir().join("tum_fr1_xyz")).unwrap();
        assert_eq!(dataset.frames.len(), 37);
        assert!(dataset.accelerometer.len() > 1000);
        assert!(dataset.groundtruth.len() > 100);
        let depth = dataset.load_depth(0).unwrap();
        assert_eq!((depth.width, depth.height), (640, 480));
        // A desk scene at arm's length: most valid depths between 0.4 and 3 m.
        let valid: Vec<f32> = depth.depth_m.iter().copied().filter(|d| d.is_finite()).collect();
        assert!(valid.len() > 200_000);
        let in_range = valid.iter().filter(|d| (0.4..3.0).contains(*d)).count();
        assert!(in_range as f64 > 0.95 * valid.len() as f64);
        // Accelerometer magnitude ≈ g near the first frame.
        let a = dataset.acceleration_near(dataset.frames[0].timestamp, 0.05).unwrap();
        assert!((a.norm() - 9.81).abs() < 0.5, "{}", a.norm());
        let pose = dataset.groundtruth_near(dataset.frames[0].timestamp, 0.02).unwrap();
        assert!((pose.timestamp - dataset.frames[0].timestamp).abs() < 0.02);
    }

    #[test]
    fn opens_open3d_png_dir_with_trajectory() {
        let dataset = Dataset::open(&test_data_dir().join("open3d_rgbd")).unwrap();
        assert_eq!(dataset.frames.len(), 5);
        assert_eq!(dataset.intrinsics, Intrinsics::primesense_default());
        assert_eq!(dataset.groundtruth.len(), 5);
        let first = dataset.groundtruth[0].world_from_camera;
        assert!((first.translation.vector - Vector3::new(-0.31057997, 0.57301224, 2.12648002)).norm() < 1e-6);
        assert!((dataset.metres_per_unit - 0.001).abs() < 1e-12);
        dataset.load_depth(4).unwrap();
    }

    #[test]
    fn opens_single_cape_png_with_opencv_calibration() {
        let dataset = Dataset::open(&test_data_dir().join("cape_tunnel/depth_0.png")).unwrap();
        assert!((dataset.intrinsics.fx - 575.9268).abs() < 1e-3);
        assert!((dataset.intrinsics.cy - 230.5858).abs() < 1e-3);
        let depth = dataset.load_depth(0).unwrap();
        let valid: Vec<f32> = depth.depth_m.iter().copied().filter(|d| d.is_finite()).collect();
        let min = valid.iter().copied().fold(f32::INFINITY, f32::min);
        assert!(min > 0.8, "{min}");
    }

    #[test]
    fn png_round_trip_keeps_millimetres() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("d.png");
        let image = DepthImage::new(3, 2, vec![1.0, f32::NAN, 0.5, 2.25, 0.001, 7.0]).unwrap();
        save_depth_png(&path, &image, 0.001).unwrap();
        let back = load_depth_png(&path, 0.001).unwrap();
        assert_eq!(back.get(0, 0), Some(1.0));
        assert!(back.get(1, 0).is_none());
        assert!((back.get(0, 1).unwrap() - 2.25).abs() < 1e-6);
    }

    #[test]
    fn malformed_files_name_the_line() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("gt.txt");
        std::fs::write(&path, "# header\n1 2 3 4 5 6 7 1\n1 2 x\n").unwrap();
        match read_tum_poses(&path) {
            Err(DatasetError::Parse { line, .. }) => assert_eq!(line, 3),
            other => panic!("expected a parse error, got {other:?}"),
        }
        let not_png = dir.path().join("bad.png");
        std::fs::write(&not_png, b"not a png").unwrap();
        assert!(matches!(load_depth_png(&not_png, 0.001), Err(DatasetError::Png { .. })));
        assert!(Dataset::open(&dir.path().join("missing")).is_err());
    }

    #[test]
    fn nearest_by_time_picks_closest() {
        let times = [1.0, 2.0, 4.0];
        assert_eq!(nearest_by_time(&times, 2.9, |t| *t), Some(&2.0));
        assert_eq!(nearest_by_time(&times, 3.1, |t| *t), Some(&4.0));
        assert_eq!(nearest_by_time(&times, -5.0, |t| *t), Some(&1.0));
        assert_eq!(nearest_by_time(&times, 9.0, |t| *t), Some(&4.0));
        assert!(nearest_by_time(&[] as &[f64], 1.0, |t| *t).is_none());
    }
}

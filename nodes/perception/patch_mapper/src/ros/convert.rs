//! Message conversion of the patch_mapper node: `sensor_msgs/Image` (16UC1/mono16 mm, 32FC1 m) ->
//! [`DepthImage`] in metres, `sensor_msgs/CameraInfo` -> [`Intrinsics`], `sensor_msgs/Imu` -> the
//! accelerometer reading. Every malformed input gives a typed error naming what is wrong; nothing here
//! can panic on input.

use nalgebra::Vector3;
use patchwalk_fusion::camera::{CameraError, DepthImage, Intrinsics};
use patchwalk_msgs::sensor_msgs::msg::{CameraInfo, Image, Imu};

/// Largest accepted image side; larger headers are corrupt, not cameras.
const MAX_SIDE: u32 = 16_384;

/// Why a depth image was rejected.
#[derive(Debug, thiserror::Error, PartialEq)]
pub enum ImageError {
    #[error("unsupported depth encoding {0:?} (expected 16UC1 or mono16 in mm, or 32FC1 in m)")]
    Encoding(String),
    #[error("bad image size {width}x{height}")]
    Size { width: u32, height: u32 },
    #[error("row step {step} is smaller than width {width} x {bytes_per_pixel} bytes")]
    Step { step: u32, width: u32, bytes_per_pixel: u32 },
    #[error("image data holds {len} bytes but {height} rows of step {step} need {needed}")]
    Data { len: usize, height: u32, step: u32, needed: usize },
    #[error(transparent)]
    Camera(#[from] CameraError),
}

/// Why a CameraInfo was rejected.
#[derive(Debug, thiserror::Error, PartialEq)]
pub enum CameraInfoError {
    #[error("bad CameraInfo size {width}x{height}")]
    Size { width: u32, height: u32 },
    #[error(transparent)]
    Camera(#[from] CameraError),
}

/// Why an IMU sample was rejected.
#[derive(Debug, thiserror::Error, PartialEq)]
pub enum ImuError {
    #[error("non-finite acceleration {0:?}")]
    NotFinite([f64; 3]),
}

/// Depth encodings of REP-118.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum DepthEncoding {
    /// Unsigned 16-bit millimetres, 0 = no data (`16UC1`, also published as `mono16`).
    MillimetresU16,
    /// 32-bit float metres, NaN/0 = no data (`32FC1`).
    MetresF32,
}

impl DepthEncoding {
    fn parse(encoding: &str) -> Result<DepthEncoding, ImageError> {
        match encoding {
            "16UC1" | "mono16" => Ok(DepthEncoding::MillimetresU16),
            "32FC1" => Ok(DepthEncoding::MetresF32),
            other => Err(ImageError::Encoding(other.to_string())),
        }
    }

    fn bytes_per_pixel(self) -> u32 {
        match self {
            DepthEncoding::MillimetresU16 => 2,
            DepthEncoding::MetresF32 => 4,
        }
    }
}

/// `sensor_msgs/Image` depth -> metric [`DepthImage`] (row padding and either byte order handled).
pub fn depth_image(msg: &Image) -> Result<DepthImage, ImageError> {
    let encoding = DepthEncoding::parse(&msg.encoding)?;
    let (width, height) = (msg.width, msg.height);
    if width == 0 || height == 0 || width > MAX_SIDE || height > MAX_SIDE {
        return Err(ImageError::Size { width, height });
    }
    let bytes_per_pixel = encoding.bytes_per_pixel();
    let row_bytes = width * bytes_per_pixel; // <= 16384 * 4, no overflow
    if msg.step < row_bytes {
        return Err(ImageError::Step { step: msg.step, width, bytes_per_pixel });
    }
    // The last row needs only its pixels, not the padding.
    let needed = msg.step as usize * (height as usize - 1) + row_bytes as usize;
    if msg.data.len() < needed {
        return Err(ImageError::Data { len: msg.data.len(), height, step: msg.step, needed });
    }
    let big_endian = msg.is_bigendian != 0;
    let rows = (0..height as usize).map(|v| {
        let start = v * msg.step as usize;
        msg.data.get(start..start + row_bytes as usize).unwrap_or_default()
    });
    let (w, h) = (width as usize, height as usize);
    match encoding {
        DepthEncoding::MillimetresU16 => {
            // Filled row by row into the final size (a flattened iterator does not know its length).
            let mut raw: Vec<u16> = Vec::with_capacity(w * h);
            for row in rows {
                raw.extend(row.chunks_exact(2).map(|b| {
                    let bytes = [b[0], b[1]];
                    if big_endian {
                        u16::from_be_bytes(bytes)
                    } else {
                        u16::from_le_bytes(bytes)
                    }
                }));
            }
            Ok(DepthImage::from_u16(w, h, &raw, 0.001)?)
        }
        DepthEncoding::MetresF32 => {
            let mut depth_m: Vec<f32> = Vec::with_capacity(w * h);
            for row in rows {
                depth_m.extend(row.chunks_exact(4).map(|b| {
                    let bytes = [b[0], b[1], b[2], b[3]];
                    if big_endian {
                        f32::from_be_bytes(bytes)
                    } else {
                        f32::from_le_bytes(bytes)
                    }
                }));
            }
            Ok(DepthImage::new(w, h, depth_m)?)
        }
    }
}

/// `sensor_msgs/CameraInfo` -> pinhole [`Intrinsics`] from K = [fx 0 cx; 0 fy cy; 0 0 1] (row-major).
/// Distortion is ignored: depth images of RGB-D cameras are published rectified.
pub fn intrinsics(msg: &CameraInfo) -> Result<Intrinsics, CameraInfoError> {
    let (width, height) = (msg.width, msg.height);
    if width == 0 || height == 0 || width > MAX_SIDE || height > MAX_SIDE {
        return Err(CameraInfoError::Size { width, height });
    }
    let k = &msg.k;
    Ok(Intrinsics::new(width as usize, height as usize, k[0], k[4], k[2], k[5])?)
}

/// `sensor_msgs/Imu` -> linear acceleration (m/s², IMU frame); every component must be finite.
pub fn imu_acceleration(msg: &Imu) -> Result<Vector3<f64>, ImuError> {
    let a = &msg.linear_acceleration;
    let acceleration = Vector3::new(a.x, a.y, a.z);
    if acceleration.iter().all(|v| v.is_finite()) {
        Ok(acceleration)
    } else {
        Err(ImuError::NotFinite([a.x, a.y, a.z]))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn image(encoding: &str, width: u32, height: u32, step: u32, data: Vec<u8>) -> Image {
        Image { encoding: encoding.into(), width, height, step, data, ..Default::default() }
    }

    #[test]
    fn millimetres_become_metres_and_zero_is_invalid() {
        let data: Vec<u8> = [1000u16, 0, 2500, 65535].iter().flat_map(|v| v.to_le_bytes()).collect();
        let depth = depth_image(&image("16UC1", 2, 2, 4, data)).unwrap();
        assert_eq!(depth.get(0, 0), Some(1.0));
        assert_eq!(depth.get(1, 0), None);
        assert!((depth.get(0, 1).unwrap() - 2.5).abs() < 1e-6);
        assert_eq!(depth.valid_count(), 3);
    }

    #[test]
    fn big_endian_and_row_padding_are_honoured() {
        // 1x2 image, 4-byte step (2 bytes of padding per row), big-endian.
        let data = vec![0x03, 0xE8, 0xAA, 0xAA, 0x07, 0xD0];
        let mut msg = image("mono16", 1, 2, 4, data);
        msg.is_bigendian = 1;
        let depth = depth_image(&msg).unwrap();
        assert_eq!(depth.get(0, 0), Some(1.0));
        assert_eq!(depth.get(0, 1), Some(2.0));
    }

    #[test]
    fn float_metres_with_nan_and_negative_become_invalid() {
        let data: Vec<u8> = [1.5f32, f32::NAN, -1.0, 0.75].iter().flat_map(|v| v.to_le_bytes()).collect();
        let depth = depth_image(&image("32FC1", 4, 1, 16, data)).unwrap();
        assert_eq!(depth.get(0, 0), Some(1.5));
        assert_eq!(depth.get(3, 0), Some(0.75));
        assert_eq!(depth.valid_count(), 2);
    }

    #[test]
    fn malformed_images_are_typed_errors() {
        assert!(matches!(depth_image(&image("rgb8", 2, 2, 6, vec![0; 12])), Err(ImageError::Encoding(_))));
        assert!(matches!(depth_image(&image("16UC1", 0, 2, 0, vec![])), Err(ImageError::Size { .. })));
        assert!(matches!(depth_image(&image("16UC1", 99_999, 1, 199_998, vec![])), Err(ImageError::Size { .. })));
        assert!(matches!(depth_image(&image("16UC1", 4, 2, 6, vec![0; 16])), Err(ImageError::Step { .. })));
        assert!(matches!(depth_image(&image("16UC1", 4, 2, 8, vec![0; 15])), Err(ImageError::Data { .. })));
        assert!(matches!(depth_image(&image("32FC1", 4, 2, 16, vec![0; 16])), Err(ImageError::Data { .. })));
    }

    #[test]
    fn camera_info_gives_intrinsics_and_rejects_garbage() {
        let mut info = CameraInfo { width: 640, height: 480, ..Default::default() };
        info.k = [525.0, 0.0, 319.5, 0.0, 526.0, 239.5, 0.0, 0.0, 1.0];
        let intr = intrinsics(&info).unwrap();
        assert_eq!((intr.width, intr.height, intr.fx, intr.fy, intr.cx, intr.cy), (640, 480, 525.0, 526.0, 319.5, 239.5));
        info.k = [0.0; 9];
        assert!(intrinsics(&info).is_err());
        info.width = 0;
        assert!(matches!(intrinsics(&info), Err(CameraInfoError::Size { .. })));
    }

    #[test]
    fn imu_acceleration_must_be_finite() {
        let mut imu = Imu::default();
        imu.linear_acceleration.y = -9.81;
        assert_eq!(imu_acceleration(&imu), Ok(Vector3::new(0.0, -9.81, 0.0)));
        imu.linear_acceleration.z = f64::NAN;
        assert!(imu_acceleration(&imu).unwrap_err().to_string().contains("non-finite"));
    }
}

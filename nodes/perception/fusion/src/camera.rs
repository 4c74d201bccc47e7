//! Pinhole camera intrinsics and depth images (metres, NaN where invalid); back-projection to
//! organized clouds.
//!
//! Frame convention: `camera_optical` (REP-103 optical frame: x right, y down, z forward). Pixel
//! `(u, v)` is column `u`, row `v`; pixel centres are at integer coordinates (OpenCV convention).

use nalgebra::Vector3;

/// Errors from building camera models and depth images.
#[derive(Debug, thiserror::Error, PartialEq)]
pub enum CameraError {
    #[error("invalid intrinsics: {0}")]
    InvalidIntrinsics(String),
    #[error("depth image is {width}x{height} but holds {len} values (expected {expected})")]
    SizeMismatch { width: usize, height: usize, len: usize, expected: usize },
    #[error("depth image is empty ({width}x{height})")]
    Empty { width: usize, height: usize },
}

/// Pinhole intrinsics (no distortion) of a `width` × `height` image.
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct Intrinsics {
    pub width: usize,
    pub height: usize,
    pub fx: f64,
    pub fy: f64,
    pub cx: f64,
    pub cy: f64,
}

impl Intrinsics {
    /// Checked constructor: positive finite focal lengths and a non-empty image.
    pub fn new(width: usize, height: usize, fx: f64, fy: f64, cx: f64, cy: f64) -> Result<Self, CameraError> {
        let intrinsics = Self { width, height, fx, fy, cx, cy };
        intrinsics.validate()?;
        Ok(intrinsics)
    }

    /// TUM RGB-D freiburg1 depth/RGB intrinsics (TUM's published calibration, distortion ignored).
    pub fn tum_freiburg1() -> Self {
        Self { width: 640, height: 480, fx: 517.3, fy: 516.5, cx: 318.6, cy: 255.3 }
    }

    /// PrimeSense / Kinect default intrinsics used by TUM's tools and Open3D (fx = fy = 525).
    pub fn primesense_default() -> Self {
        Self { width: 640, height: 480, fx: 525.0, fy: 525.0, cx: 319.5, cy: 239.5 }
    }

    /// Rejects zero-sized images and non-positive or non-finite parameters.
    pub fn validate(&self) -> Result<(), CameraError> {
        if self.width == 0 || self.height == 0 {
            return Err(CameraError::InvalidIntrinsics(format!("image size {}x{}", self.width, self.height)));
        }
        for (name, value) in [("fx", self.fx), ("fy", self.fy)] {
            if !(value.is_finite() && value > 0.0) {
                return Err(CameraError::InvalidIntrinsics(format!("{name} = {value} must be positive and finite")));
            }
        }
        for (name, value) in [("cx", self.cx), ("cy", self.cy)] {
            if !value.is_finite() {
                return Err(CameraError::InvalidIntrinsics(format!("{name} = {value} must be finite")));
            }
        }
        Ok(())
    }

    /// Intrinsics of the image scaled by `factor` (e.g. 0.5 for a 2×2 downsample). Pixel centres
    /// stay consistent: `c' = (c + 0.5)·factor − 0.5`.
    pub fn scaled(&self, factor: f64) -> Self {
        Self {
            width: ((self.width as f64) * factor).round().max(1.0) as usize,
            height: ((self.height as f64) * factor).round().max(1.0) as usize,
            fx: self.fx * factor,
            fy: self.fy * factor,
            cx: (self.cx + 0.5) * factor - 0.5,
            cy: (self.cy + 0.5) * factor - 0.5,
        }
    }

    /// Point in the camera frame seen at pixel `(u, v)` with depth `z` (metres along the optical axis).
    #[inline]
    pub fn back_project(&self, u: f64, v: f64, z: f64) -> Vector3<f64> {
        Vector3::new((u - self.cx) * z / self.fx, (v - self.cy) * z / self.fy, z)
    }

    /// Pixel coordinates `(u, v)` of a point in the camera frame; `None` behind the camera.
    #[inline]
    pub fn project(&self, point_in_camera: &Vector3<f64>) -> Option<(f64, f64)> {
        if point_in_camera.z <= 0.0 || !point_in_camera.z.is_finite() {
            return None;
        }
        Some((self.fx * point_in_camera.x / point_in_camera.z + self.cx, self.fy * point_in_camera.y / point_in_camera.z + self.cy))
    }

    /// Nearest pixel `(column, row)` inside the image for a projected point, if any.
    #[inline]
    pub fn pixel_of(&self, point_in_camera: &Vector3<f64>) -> Option<(usize, usize)> {
        let (u, v) = self.project(point_in_camera)?;
        let (col, row) = (u.round(), v.round());
        if col < 0.0 || row < 0.0 || col >= self.width as f64 || row >= self.height as f64 {
            return None;
        }
        Some((col as usize, row as usize))
    }
}

/// A depth image in metres, row-major, `NaN` where there is no valid measurement.
#[derive(Debug, Clone, PartialEq)]
pub struct DepthImage {
    pub width: usize,
    pub height: usize,
    /// `width * height` depths in metres (z along the optical axis); NaN = invalid.
    pub depth_m: Vec<f32>,
}

impl DepthImage {
    /// Wraps metric depths; non-finite and non-positive values become NaN.
    pub fn new(width: usize, height: usize, mut depth_m: Vec<f32>) -> Result<Self, CameraError> {
        check_size(width, height, depth_m.len())?;
        for d in &mut depth_m {
            if !(d.is_finite() && *d > 0.0) {
                *d = f32::NAN;
            }
        }
        Ok(Self { width, height, depth_m })
    }

    /// Converts raw 16-bit depth (e.g. `16UC1` millimetres with `metres_per_unit = 0.001`, or TUM's
    /// `1/5000`); 0 means no data.
    pub fn from_u16(width: usize, height: usize, raw: &[u16], metres_per_unit: f64) -> Result<Self, CameraError> {
        check_size(width, height, raw.len())?;
        if !(metres_per_unit.is_finite() && metres_per_unit > 0.0) {
            return Err(CameraError::InvalidIntrinsics(format!("depth scale {metres_per_unit} must be positive")));
        }
        let depth_m = raw.iter().map(|&value| if value == 0 { f32::NAN } else { (f64::from(value) * metres_per_unit) as f32 }).collect();
        Ok(Self { width, height, depth_m })
    }

    /// Depth at column `u`, row `v`, if inside the image and valid.
    #[inline]
    pub fn get(&self, u: usize, v: usize) -> Option<f32> {
        if u >= self.width || v >= self.height {
            return None;
        }
        self.depth_m.get(v * self.width + u).copied().filter(|d| d.is_finite())
    }

    /// Number of valid (finite) depths.
    pub fn valid_count(&self) -> usize {
        self.depth_m.iter().filter(|d| d.is_finite()).count()
    }

    /// Organized cloud in the camera frame (row-major, `NaN` points where the depth is invalid).
    pub fn to_points_in_camera(&self, intrinsics: &Intrinsics) -> Vec<Vector3<f64>> {
        let mut points = Vec::with_capacity(self.width * self.height);
        for v in 0..self.height {
            for u in 0..self.width {
                let z = self.depth_m[v * self.width + u];
                points.push(if z.is_finite() {
                    intrinsics.back_project(u as f64, v as f64, f64::from(z))
                } else {
                    Vector3::repeat(f64::NAN)
                });
            }
        }
        points
    }
}

fn check_size(width: usize, height: usize, len: usize) -> Result<(), CameraError> {
    if width == 0 || height == 0 {
        return Err(CameraError::Empty { width, height });
    }
    let expected = width.saturating_mul(height);
    if len != expected {
        return Err(CameraError::SizeMismatch { width, height, len, expected });
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn project_inverts_back_project() {
        let intrinsics = Intrinsics::tum_freiburg1();
        let point_in_camera = intrinsics.back_project(100.25, 400.5, 1.7);
        let (u, v) = intrinsics.project(&point_in_camera).unwrap();
        assert!((u - 100.25).abs() < 1e-9 && (v - 400.5).abs() < 1e-9);
        assert!(intrinsics.project(&Vector3::new(0.0, 0.0, -1.0)).is_none());
    }

    #[test]
    fn scaled_intrinsics_keep_rays() {
        let full = Intrinsics::primesense_default();
        let half = full.scaled(0.5);
        assert_eq!((half.width, half.height), (320, 240));
        // Pixel (1,1) of the half image covers full pixels 2..4: centre 2.5.
        let ray_half = half.back_project(1.0, 1.0, 1.0);
        let ray_full = full.back_project(2.5, 2.5, 1.0);
        assert!((ray_half - ray_full).norm() < 1e-12);
    }

    #[test]
    fn depth_from_u16_marks_zero_invalid() {
        let image = DepthImage::from_u16(2, 1, &[0, 5000], 1.0 / 5000.0).unwrap();
        assert!(image.get(0, 0).is_none());
        assert_eq!(image.get(1, 0), Some(1.0));
        assert_eq!(image.valid_count(), 1);
        assert!(image.get(2, 0).is_none());
    }

    #[test]
    fn bad_sizes_and_intrinsics_are_errors() {
        assert!(matches!(DepthImage::new(2, 2, vec![1.0; 3]), Err(CameraError::SizeMismatch { .. })));
        assert!(matches!(DepthImage::new(0, 2, vec![]), Err(CameraError::Empty { .. })));
        assert!(Intrinsics::new(640, 480, 0.0, 1.0, 0.0, 0.0).is_err());
        assert!(Intrinsics::new(640, 480, 1.0, f64::NAN, 0.0, 0.0).is_err());
    }

    #[test]
    fn non_finite_depths_become_nan() {
        let image = DepthImage::new(3, 1, vec![f32::INFINITY, -1.0, 2.0]).unwrap();
        assert_eq!(image.valid_count(), 1);
        let cloud = image.to_points_in_camera(&Intrinsics::new(3, 1, 1.0, 1.0, 1.0, 0.0).unwrap());
        assert!(cloud[0].x.is_nan());
        assert_eq!(cloud[2], Vector3::new(2.0, 0.0, 2.0));
    }
}

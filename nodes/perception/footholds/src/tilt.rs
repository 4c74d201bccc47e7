//! The camera tilt side channels of CNN III-B: `(cos θ, sin θ, θ / 90°)`.
//!
//! θ is the angle of the camera's viewing direction (the optical z axis) below the horizontal plane,
//! from the IMU's gravity in the camera frame: `sin θ = ĝ · ẑ` for the unit "down" vector ĝ, so a
//! camera looking straight down has θ = 90°, a level one 0°, one looking up a negative θ. The last
//! channel is in [−1, 1] as in the paper.

use nalgebra::Vector3;

use crate::error::FootholdError;

/// Camera tilt θ (degrees, positive looking down) and its three side channels.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Tilt {
    pub degrees: f64,
}

impl Tilt {
    /// A tilt in degrees; refuses non-finite values and values outside [−90°, 90°].
    pub fn from_degrees(degrees: f64) -> Result<Self, FootholdError> {
        if degrees.is_finite() && (-90.0..=90.0).contains(&degrees) {
            Ok(Self { degrees })
        } else {
            Err(FootholdError::BadTilt(degrees))
        }
    }

    /// θ from gravity (pointing down, any length) in the camera's optical frame (x right, y down,
    /// z forward).
    pub fn from_gravity_in_camera(gravity: &Vector3<f64>) -> Result<Self, FootholdError> {
        let norm = gravity.norm();
        if !(norm.is_finite() && norm > 1e-9) {
            return Err(FootholdError::BadGravity([gravity.x, gravity.y, gravity.z]));
        }
        let sin = (gravity.z / norm).clamp(-1.0, 1.0);
        Self::from_degrees(sin.asin().to_degrees())
    }

    /// The side channels `(cos θ, sin θ, θ / 90°)` (CNN III-B).
    pub fn channels(&self) -> [f32; 3] {
        let rad = self.degrees.to_radians();
        [rad.cos() as f32, rad.sin() as f32, (self.degrees / 90.0) as f32]
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn tilt_from_gravity() {
        // Looking 49° down: gravity has the component sin 49° along the optical axis.
        let t = 49f64.to_radians();
        let tilt = Tilt::from_gravity_in_camera(&(Vector3::new(0.0, t.cos(), t.sin()) * 9.81)).unwrap();
        assert!((tilt.degrees - 49.0).abs() < 1e-9);
        let [c, s, r] = tilt.channels();
        assert!((c - t.cos() as f32).abs() < 1e-6 && (s - t.sin() as f32).abs() < 1e-6 && (r - 49.0 / 90.0).abs() < 1e-6);
        let level = Tilt::from_gravity_in_camera(&Vector3::new(0.0, 1.0, 0.0)).unwrap();
        assert_eq!(level.degrees, 0.0);
        let up = Tilt::from_gravity_in_camera(&Vector3::new(0.0, 0.0, -2.0)).unwrap();
        assert_eq!(up.channels()[2], -1.0);
    }

    #[test]
    fn zero_nan_and_out_of_range_tilts_are_refused() {
        assert!(matches!(Tilt::from_gravity_in_camera(&Vector3::zeros()), Err(FootholdError::BadGravity(_))));
        let err = Tilt::from_gravity_in_camera(&Vector3::new(f64::NAN, 1.0, 0.0)).unwrap_err();
        assert!(err.to_string().contains("zero or not finite"), "{err}");
        assert!(matches!(Tilt::from_degrees(f64::NAN), Err(FootholdError::BadTilt(_))));
        assert!(matches!(Tilt::from_degrees(91.0), Err(FootholdError::BadTilt(_))));
    }
}

//! The initial pose of ICP: a constant-velocity prediction of the camera (MonoSLAM's motion model,
//! Davison et al. 2007, sec. 3.2, here without the noise terms) with its tilt taken from the IMU.
//!
//! From the last two tracked poses `T₁` (at t₁) and `T₂` (at t₂, both `map_from_camera`), the pose at
//! t is predicted by repeating the last camera-frame increment Δ = T₁⁻¹ T₂ scaled to the time step:
//!
//! ```text
//! T̂(t) = T₂ · (exp(s · log R_Δ), s · t_Δ),   s = (t − t₂) / (t₂ − t₁)   (clamped to [0, max_extrapolation])
//! ```
//!
//! (rotation and translation scaled separately; exact at s = 1). With the gravity of the frame
//! (unit `ĝ_c`, camera frame, from the accelerometer) the prediction's roll and pitch are replaced by
//! the IMU's: the smallest rotation Q with Q R̂ ĝ_c = ĝ_m (gravity in the gravity-aligned map, −z)
//! is applied about the camera centre, `R' = Q R̂` (J 5.1: "the gravity vector ... to constrain
//! rotation"). The position stays that of the prediction; Q turns about a horizontal axis, so the
//! heading of a pitched camera moves by at most the size of the correction.

use nalgebra::{Isometry3, Translation3, UnitQuaternion, Vector3};

/// A tracked pose and when it was taken.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct StampedPose {
    pub time: f64,
    pub map_from_camera: Isometry3<f64>,
}

/// The last two tracked poses, for the constant-velocity prediction.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct MotionModel {
    previous: Option<StampedPose>,
    last: Option<StampedPose>,
}

impl MotionModel {
    /// Records a tracked pose (times must increase; an older or equal one replaces the history).
    pub fn push(&mut self, time: f64, map_from_camera: Isometry3<f64>) {
        let pose = StampedPose { time, map_from_camera };
        match self.last {
            Some(last) if time > last.time => self.previous = Some(last),
            _ => self.previous = None,
        }
        self.last = Some(pose);
    }

    /// Forgets the history (tracking reset).
    pub fn clear(&mut self) {
        *self = Self::default();
    }

    /// The last tracked pose.
    pub fn last(&self) -> Option<StampedPose> {
        self.last
    }

    /// T̂(t): the last pose moved on by the last increment scaled to `time`, or the last pose itself
    /// when there is only one (or no time has passed). `max_extrapolation` bounds s (a long gap does
    /// not fling the prediction away).
    pub fn predict(&self, time: f64, max_extrapolation: f64) -> Option<Isometry3<f64>> {
        let last = self.last?;
        let Some(previous) = self.previous else { return Some(last.map_from_camera) };
        let step = last.time - previous.time;
        if !(step > 0.0 && time.is_finite()) {
            return Some(last.map_from_camera);
        }
        let s = ((time - last.time) / step).clamp(0.0, max_extrapolation.max(0.0));
        let increment = previous.map_from_camera.inverse() * last.map_from_camera;
        Some(last.map_from_camera * scale_increment(&increment, s))
    }
}

/// (exp(s · log R), s · t) of an increment (SO(3) × R³ scaling).
pub fn scale_increment(increment: &Isometry3<f64>, s: f64) -> Isometry3<f64> {
    let rotation = UnitQuaternion::from_scaled_axis(increment.rotation.scaled_axis() * s);
    Isometry3::from_parts(Translation3::from(increment.translation.vector * s), rotation)
}

/// The pose with its tilt taken from the IMU: `R' = Q R` with Q the smallest rotation that takes the
/// predicted gravity `R ĝ_c` onto `gravity_in_reference` (both unit). The position is kept.
pub fn tilt_corrected(
    reference_from_camera: &Isometry3<f64>,
    gravity_in_camera: &Vector3<f64>,
    gravity_in_reference: &Vector3<f64>,
) -> Isometry3<f64> {
    let predicted = reference_from_camera.rotation * gravity_in_camera;
    match UnitQuaternion::rotation_between(&predicted, gravity_in_reference) {
        Some(q) => Isometry3::from_parts(reference_from_camera.translation, q * reference_from_camera.rotation),
        // Opposite vectors (a pose upside down relative to the IMU): no unique smallest rotation.
        None => *reference_from_camera,
    }
}

/// Angle (deg) between the gravity the pose implies (`R ĝ_c`) and the reference's gravity.
pub fn tilt_error_deg(
    reference_from_camera: &Isometry3<f64>,
    gravity_in_camera: &Vector3<f64>,
    gravity_in_reference: &Vector3<f64>,
) -> f64 {
    (reference_from_camera.rotation * gravity_in_camera).angle(gravity_in_reference).to_degrees()
}

#[cfg(test)]
mod tests {
    use super::*;

    fn pose(x: f64, y: f64, yaw_deg: f64) -> Isometry3<f64> {
        Isometry3::from_parts(Translation3::new(x, y, 0.5), UnitQuaternion::from_euler_angles(0.0, 0.0, yaw_deg.to_radians()))
    }

    fn close(a: &Isometry3<f64>, b: &Isometry3<f64>) -> bool {
        (a.translation.vector - b.translation.vector).norm() < 1e-9 && a.rotation.angle_to(&b.rotation) < 1e-9
    }

    #[test]
    fn constant_velocity_repeats_the_last_increment_scaled_to_the_time_step() {
        let mut model = MotionModel::default();
        assert_eq!(model.predict(1.0, 3.0), None);
        model.push(0.0, pose(0.0, 0.0, 0.0));
        // One pose: no velocity yet, the prediction is the pose.
        assert!(close(&model.predict(0.1, 3.0).unwrap(), &pose(0.0, 0.0, 0.0)));
        model.push(0.1, pose(0.1, 0.0, 10.0));
        // One step later: 0.1 m along the camera's x turned by 10°, and another 10°.
        let expected = pose(0.1, 0.0, 10.0) * pose(0.1, 0.0, 10.0) * Isometry3::translation(0.0, 0.0, -0.5);
        let next = model.predict(0.2, 3.0).unwrap();
        assert!(close(&next, &expected), "{next} vs {expected}");
        // A skipped frame: twice the increment.
        let two = model.predict(0.3, 3.0).unwrap();
        let doubled =
            Isometry3::from_parts(Translation3::new(0.2, 0.0, 0.0), UnitQuaternion::from_euler_angles(0.0, 0.0, 20f64.to_radians()));
        assert!(close(&two, &(pose(0.1, 0.0, 10.0) * doubled)), "{two}");
        assert!(close(&scale_increment(&(pose(0.0, 0.0, 0.0).inverse() * pose(0.1, 0.0, 10.0)), 2.0), &doubled));
        // Half a step: half the rotation and translation.
        let half = model.predict(0.15, 3.0).unwrap();
        assert!((half.rotation.angle().to_degrees() - 15.0).abs() < 1e-9);
        // A long gap is clamped to max_extrapolation steps; a time before the last pose gives it.
        let far = model.predict(10.0, 3.0).unwrap();
        assert!((far.rotation.angle().to_degrees() - 40.0).abs() < 1e-9, "{}", far.rotation.angle().to_degrees());
        assert!(close(&model.predict(0.05, 3.0).unwrap(), &pose(0.1, 0.0, 10.0)));
        // A pose older than the last one starts the history over.
        model.push(0.05, pose(1.0, 0.0, 0.0));
        assert!(close(&model.predict(0.5, 3.0).unwrap(), &pose(1.0, 0.0, 0.0)));
        model.clear();
        assert_eq!(model.last(), None);
    }

    #[test]
    fn tilt_correction_takes_roll_and_pitch_from_gravity() {
        let down = -Vector3::z();
        // An optical camera frame (z forward, y down) pitched 50° down and yawed 30° (heading).
        let optical = UnitQuaternion::from_euler_angles(-std::f64::consts::FRAC_PI_2, 0.0, -std::f64::consts::FRAC_PI_2);
        let camera = |roll: f64, pitch: f64, yaw: f64| {
            UnitQuaternion::from_axis_angle(&Vector3::z_axis(), yaw)
                * UnitQuaternion::from_axis_angle(&Vector3::y_axis(), pitch)
                * UnitQuaternion::from_axis_angle(&Vector3::x_axis(), roll)
                * optical
        };
        let truth = Isometry3::from_parts(Translation3::new(0.2, 0.1, 0.45), camera(0.0, 0.87, 0.52));
        let gravity_in_camera = truth.rotation.inverse() * down;
        // A prediction 8° off in roll and 5° in pitch, heading right.
        let predicted = Isometry3::from_parts(truth.translation, camera(0.14, 0.87 + 0.087, 0.52));
        assert!(tilt_error_deg(&predicted, &gravity_in_camera, &down) > 5.0);
        let corrected = tilt_corrected(&predicted, &gravity_in_camera, &down);
        assert!(tilt_error_deg(&corrected, &gravity_in_camera, &down) < 1e-9);
        assert_eq!(corrected.translation, predicted.translation);
        // Q is about a horizontal axis: the heading (forward axis made horizontal) of the 50°-pitched
        // camera moves by less than the 9.4° correction (6.4° here).
        let heading = |p: &Isometry3<f64>| {
            let f = p.rotation * Vector3::z();
            f.y.atan2(f.x).to_degrees()
        };
        let correction = corrected.rotation.angle_to(&predicted.rotation).to_degrees();
        assert!((heading(&corrected) - heading(&predicted)).abs() < correction, "{} vs {}", heading(&corrected), heading(&predicted));
        assert!(corrected.rotation.angle_to(&truth.rotation) < predicted.rotation.angle_to(&truth.rotation));
    }
}

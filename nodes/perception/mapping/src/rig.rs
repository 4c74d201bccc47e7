//! The camera rig as the mapper sees it: the camera's height above the ground and its pitch, and
//! what follows from them, the DtFP fixation point (J 4.2.1 step 6.1) and the single-frame seed area
//! (the volume whose xz-plane carries the J 4.3 grid).
//!
//! J 4.2.1 defines the fixation point in the camera frame as `f = l_d·ĝ + l_f·(x̂ × ĝ)/|x̂ × ĝ|`,
//! with `l_d`, `l_f` the distances down and forward from the camera to the point humans fixate,
//! "approximately two steps ahead" (J \[75\]). J gives no numbers for `l_d`, `l_f`; the mapper's
//! defaults (1.2 m down, 1.5 m ahead) are a chest-height hand-held rig. A robot head at 0.45 m sees
//! nothing of a ball around such a point, so here the fixation point is put on the ground
//! (`l_d` = camera height) two steps ahead, steps scaled with the camera height (the default rig's
//! 0.75 m step at 1.2 m), and pulled back into the camera's vertical field of view when the camera
//! looks too far down to see that far.
//!
//! The rig comes from the robot (URDF/TF: camera height above the feet) when there is one, or from
//! gravity and the ground plane of a frame ([`RigEstimate::from_ground_plane`]) in the offline tools.

use nalgebra::{Isometry3, Unit, Vector3};

use crate::acquire::Plane;
use patchwalk_fusion::camera::Intrinsics;
use patchwalk_fusion::volume::{initial_volume_from_camera, MovingVolumeConfig};

/// Step length per metre of camera height: the default fixation point's two 0.75 m steps from a
/// 1.2 m high camera.
pub const STEP_PER_HEIGHT: f64 = 0.75 / 1.2;

/// Share of the camera's vertical half field of view the fixation direction may use (keeps the
/// R-ball's centre inside the image, away from its border).
const FOV_MARGIN: f64 = 0.8;

/// Camera height above the ground and pitch of the optical axis.
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize)]
pub struct RigEstimate {
    /// Height of the camera centre above the ground, along gravity (m).
    pub camera_height_m: f64,
    /// Angle of the optical axis below the horizontal (degrees; negative: looking up).
    pub pitch_deg: f64,
}

/// Errors of the rig estimate.
#[derive(Debug, thiserror::Error, PartialEq)]
pub enum RigError {
    #[error("camera height {0} m is not a positive finite number")]
    BadHeight(f64),
    #[error("gravity {0:?} is not a finite unit vector")]
    BadGravity([f64; 3]),
}

impl RigEstimate {
    /// A rig from a measured camera height and the gravity (down) in the camera frame.
    pub fn new(camera_height_m: f64, gravity_in_camera: &Unit<Vector3<f64>>) -> Result<Self, RigError> {
        if !(camera_height_m.is_finite() && camera_height_m > 0.0) {
            return Err(RigError::BadHeight(camera_height_m));
        }
        let g = gravity_in_camera.into_inner();
        if !(g.iter().all(|c| c.is_finite()) && (g.norm() - 1.0).abs() < 1e-6) {
            return Err(RigError::BadGravity(g.into()));
        }
        // The optical axis ẑ makes an angle asin(ẑ·ĝ) with the horizontal, positive downwards.
        Ok(Self { camera_height_m, pitch_deg: g.z.clamp(-1.0, 1.0).asin().to_degrees() })
    }

    /// A rig from gravity and the ground plane (its distance from the camera is the camera height).
    pub fn from_ground_plane(gravity_in_camera: &Unit<Vector3<f64>>, ground: &Plane) -> Result<Self, RigError> {
        Self::new(ground.distance_m, gravity_in_camera)
    }

    /// `(l_d, l_f)` of J step 6.1 for this rig seen through `intrinsics`: the ground point two steps
    /// ahead (`l_f = 2·STEP_PER_HEIGHT·h`), moved along the ground into the vertical field of view
    /// (within 80 % of its half angle around the optical axis) when it is outside.
    pub fn fixation_distances(&self, intrinsics: &Intrinsics) -> (f64, f64) {
        let h = self.camera_height_m;
        let two_steps = 2.0 * STEP_PER_HEIGHT * h;
        let half_fov = (0.5 * intrinsics.height as f64 / intrinsics.fy).atan().to_degrees() * FOV_MARGIN;
        let pitch = self.pitch_deg;
        // Angle below the horizontal of the ray to the ground point two steps ahead.
        let depression = h.atan2(two_steps).to_degrees();
        let clamped = depression.clamp(pitch - half_fov, pitch + half_fov).clamp(1.0, 90.0);
        let forward = if (clamped - depression).abs() < 1e-9 { two_steps } else { h / clamped.to_radians().tan() };
        (h, forward.max(0.0))
    }

    /// `(l_d, l_f)` for a virtual camera `offset_m` above the real one looking straight down (the
    /// fusion's birds-eye view, J 5.1): the same ground point, `offset_m` further down.
    pub fn birds_eye_fixation_distances(&self, intrinsics: &Intrinsics, offset_m: f64) -> (f64, f64) {
        let (down, forward) = self.fixation_distances(intrinsics);
        (down + offset_m, forward)
    }
}

/// The single-frame volume (the seed area) placed around the rig's fixation point: volume y along
/// gravity, z along the camera's horizontal forward direction, the camera above the middle of the
/// volume's x range, the volume's xz-centre at the fixation point `forward_m` ahead, and the ground
/// (`down_m` below the camera) three quarters down the cube (or the camera on the top face if the
/// ground is lower). A fixation point at the camera gives the mapper's default single-frame volume
/// (camera at the middle of the back face's top edge).
pub fn volume_from_camera_at_fixation(gravity_in_camera: &Unit<Vector3<f64>>, edge_m: f64, down_m: f64, forward_m: f64) -> Isometry3<f64> {
    // Camera position in the volume: the cube's xz-centre at the fixation point; when that is nearer
    // than half the edge the camera stays on the back face, so the seeds start at its feet.
    let z = (0.5 * edge_m - forward_m).min(0.0);
    let y = (0.75 * edge_m - down_m).max(0.0);
    let config = MovingVolumeConfig { nominal_position_fraction: [0.5, y / edge_m, z / edge_m], ..MovingVolumeConfig::default() };
    initial_volume_from_camera(Some(gravity_in_camera.into_inner()), edge_m, &config)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::saliency::fixation_point;

    fn kinect() -> Intrinsics {
        Intrinsics::new(640, 480, 525.0, 525.0, 319.5, 239.5).unwrap()
    }

    fn pitched(pitch_deg: f64) -> Unit<Vector3<f64>> {
        let p = pitch_deg.to_radians();
        Unit::new_normalize(Vector3::new(0.0, p.cos(), p.sin()))
    }

    #[test]
    fn pitch_and_height_come_from_gravity_and_the_ground() {
        let rig = RigEstimate::new(0.45, &pitched(50.0)).unwrap();
        assert!((rig.pitch_deg - 50.0).abs() < 1e-9);
        let ground = Plane { normal_away: pitched(20.0), distance_m: 1.1, share: 0.5 };
        let rig = RigEstimate::from_ground_plane(&pitched(20.0), &ground).unwrap();
        assert_eq!(rig.camera_height_m, 1.1);
        assert!((rig.pitch_deg - 20.0).abs() < 1e-9);
        assert_eq!(RigEstimate::new(0.0, &pitched(0.0)), Err(RigError::BadHeight(0.0)));
        assert!(matches!(RigEstimate::new(f64::NAN, &pitched(0.0)), Err(RigError::BadHeight(_))));
    }

    #[test]
    fn a_chest_height_rig_keeps_j_defaults_two_steps_ahead() {
        // 1.2 m high, 40° down: two 0.75 m steps ahead (the mapper's default l_f = 1.5 m) are in view.
        let rig = RigEstimate::new(1.2, &pitched(40.0)).unwrap();
        let (down, forward) = rig.fixation_distances(&kinect());
        assert_eq!(down, 1.2);
        assert!((forward - 1.5).abs() < 1e-9, "{forward}");
    }

    #[test]
    fn a_low_pitched_down_head_fixates_on_the_ground_it_sees() {
        // 0.45 m high, 50° down (a biped's head): the fixation point is on the ground, in the image.
        let intrinsics = kinect();
        let g = pitched(50.0);
        let rig = RigEstimate::new(0.45, &g).unwrap();
        let (down, forward) = rig.fixation_distances(&intrinsics);
        assert_eq!(down, 0.45);
        assert!(forward > 0.2 && forward < 0.7, "{forward}");
        let f = fixation_point(&g, down, forward);
        // In front of the camera and projecting inside the image.
        assert!(f.z > 0.0);
        let v = intrinsics.fy * f.y / f.z + intrinsics.cy;
        assert!((0.0..480.0).contains(&v), "row {v}");
        // Looking almost straight down, the point moves under the camera's view, not behind it.
        let steep = RigEstimate::new(0.45, &pitched(85.0)).unwrap();
        let (_, forward) = steep.fixation_distances(&intrinsics);
        assert!(forward > 0.0 && forward < 0.25, "{forward}");
        let level = RigEstimate::new(0.45, &pitched(0.0)).unwrap();
        let (_, forward) = level.fixation_distances(&intrinsics);
        // Level camera: the ground two steps ahead is below the field of view; pulled out to where the
        // lower image edge meets the ground.
        let lowest = (0.5 * 480.0 / 525.0f64).atan() * FOV_MARGIN;
        assert!((forward - 0.45 / lowest.tan()).abs() < 1e-6, "{forward}");
    }

    #[test]
    fn birds_eye_fixation_is_the_same_ground_point_seen_from_above() {
        let rig = RigEstimate::new(0.45, &pitched(50.0)).unwrap();
        let (d, f) = rig.fixation_distances(&kinect());
        assert_eq!(rig.birds_eye_fixation_distances(&kinect(), 0.5), (d + 0.5, f));
    }

    #[test]
    fn the_seed_volume_is_centred_on_the_fixation_point() {
        let g = pitched(40.0);
        let edge = 1.28;
        let volume_from_camera = volume_from_camera_at_fixation(&g, edge, 1.2, 1.5);
        let f = fixation_point(&g, 1.2, 1.5);
        let f_in_volume = volume_from_camera * nalgebra::Point3::from(f);
        assert!((f_in_volume.x - 0.64).abs() < 1e-9 && (f_in_volume.z - 0.64).abs() < 1e-9, "{f_in_volume:?}");
        // The volume's y axis is gravity.
        assert!((volume_from_camera.rotation * g.into_inner() - Vector3::y()).norm() < 1e-12);
        // A near fixation point keeps the camera on the back face (seeds from the feet on).
        let near = volume_from_camera_at_fixation(&g, edge, 0.45, 0.4);
        assert_eq!(near.translation.vector.z, 0.0);
        assert!((near.translation.vector.y - (0.96 - 0.45)).abs() < 1e-12);
    }
}

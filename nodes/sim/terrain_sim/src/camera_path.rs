//! Camera path over a terrain, as a small biped walking across it would see it: the camera at
//! `camera_height_m` above the ground under it, pitched `pitch_deg` down, heading along the path,
//! advancing `step_per_frame_m` per camera frame (default 5 mm: 0.15 m/s at 30 Hz, a small
//! biped's walking speed).
//!
//! The path is a polyline of waypoints, or a straight walk from `start_m` along `heading_deg` when
//! no waypoints are given. Corners are rounded: the walker's position is the midpoint and its heading
//! the direction of the chord between the path points `turn_smoothing_m` behind and ahead of it, so
//! position and heading change continuously (the IMU differentiates them). The ground height is the
//! mean of the terrain's heights on a disc of radius `ground_smoothing_m` around the walker (its
//! centre and eight points on the rim), so the camera rides smoothly over bumps and climbs stairs as a
//! ramp. At the last waypoint the walker stops. The motion's sway (`motion.sway`) applies on top.

use std::f64::consts::FRAC_PI_2;

use nalgebra::{Isometry3, Translation3, UnitQuaternion, Vector2};
use serde::{Deserialize, Serialize};

use crate::motion::link_from_optical;
use crate::scene::Scene;

/// The camera path (`path` in the config).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct CameraPathConfig {
    /// Follow this path in the rock scene too (terrain scenes always follow it; the rock scene
    /// otherwise stands at a rock's station).
    pub enabled: bool,
    /// Waypoints `(x, y)` in the world (m); empty = a straight walk from `start_m` along `heading_deg`.
    pub waypoints_m: Vec<[f64; 2]>,
    /// Start of the straight walk (m); `None` = 0.5 m inside the terrain's −x edge, halfway along y.
    pub start_m: Option<[f64; 2]>,
    /// Heading of the straight walk (deg, 0 = +x, counter-clockwise).
    pub heading_deg: f64,
    /// Distance walked per camera frame (m).
    pub step_per_frame_m: f64,
    /// Height of the camera above the (smoothed) ground (m).
    pub camera_height_m: f64,
    /// Camera pitch below the horizon (deg).
    pub pitch_deg: f64,
    /// Radius of the disc the ground height is averaged over (m); 0 = the height under the walker.
    pub ground_smoothing_m: f64,
    /// Half-length of the chord that rounds corners (m).
    pub turn_smoothing_m: f64,
}

impl Default for CameraPathConfig {
    fn default() -> Self {
        Self {
            enabled: false,
            waypoints_m: Vec::new(),
            start_m: None,
            heading_deg: 0.0,
            step_per_frame_m: 0.005,
            camera_height_m: 0.45,
            pitch_deg: 45.0,
            ground_smoothing_m: 0.1,
            turn_smoothing_m: 0.1,
        }
    }
}

/// Why a path is unusable.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum CameraPathError {
    #[error("invalid camera path: {0}")]
    Invalid(String),
}

/// A resolved path: polyline, speed and camera mount.
#[derive(Debug, Clone)]
pub struct CameraPath {
    pub config: CameraPathConfig,
    points: Vec<Vector2<f64>>,
    /// Arc length at each point.
    lengths: Vec<f64>,
    /// Walking speed (m/s).
    speed_mps: f64,
    /// Height used where the terrain has no surface under the walker.
    fallback_ground_m: f64,
}

/// Length of the straight walk's polyline (m): longer than any recording.
const WALK_LENGTH_M: f64 = 1.0e4;

impl CameraPath {
    /// Resolves `config` over `scene` (default start from the terrain's extent) for a camera at
    /// `camera_rate_hz`.
    pub fn new(config: &CameraPathConfig, scene: &Scene, camera_rate_hz: f64) -> Result<Self, CameraPathError> {
        let invalid = |m: String| Err(CameraPathError::Invalid(m));
        if !(config.step_per_frame_m.is_finite() && config.step_per_frame_m >= 0.0) {
            return invalid(format!("step_per_frame_m = {} must be ≥ 0", config.step_per_frame_m));
        }
        if !(config.camera_height_m.is_finite() && config.camera_height_m > 0.0) {
            return invalid(format!("camera_height_m = {} must be positive", config.camera_height_m));
        }
        if !(config.pitch_deg.is_finite() && (-90.0..=90.0).contains(&config.pitch_deg)) {
            return invalid(format!("pitch_deg = {} must be in −90..=90", config.pitch_deg));
        }
        if !(config.ground_smoothing_m >= 0.0 && config.turn_smoothing_m >= 0.0 && config.heading_deg.is_finite()) {
            return invalid("ground_smoothing_m and turn_smoothing_m must be ≥ 0, heading_deg finite".into());
        }
        if !(camera_rate_hz.is_finite() && camera_rate_hz > 0.0) {
            return invalid(format!("camera rate {camera_rate_hz} Hz must be positive"));
        }
        let points: Vec<Vector2<f64>> = if config.waypoints_m.is_empty() {
            let start = config.start_m.unwrap_or_else(|| match &scene.terrain {
                Some(terrain) => {
                    let [[x0, _], _] = terrain.extent_m();
                    [x0 + 0.5, terrain.centre_m()[1]]
                }
                None => [0.2, scene.table_y_m.iter().sum::<f64>() / 2.0],
            });
            let heading = config.heading_deg.to_radians();
            let start = Vector2::new(start[0], start[1]);
            vec![start, start + Vector2::new(heading.cos(), heading.sin()) * WALK_LENGTH_M]
        } else {
            config.waypoints_m.iter().map(|p| Vector2::new(p[0], p[1])).collect()
        };
        if let Some(bad) = points.iter().find(|p| !(p.x.is_finite() && p.y.is_finite())) {
            return invalid(format!("waypoint ({}, {}) is not finite", bad.x, bad.y));
        }
        let mut lengths = vec![0.0];
        for pair in points.windows(2) {
            let last = lengths.last().copied().unwrap_or(0.0);
            lengths.push(last + (pair[1] - pair[0]).norm());
        }
        let fallback_ground_m = scene.terrain.as_ref().map_or(0.0, |t| t.z_range_m()[0]);
        Ok(Self { config: config.clone(), points, lengths, speed_mps: config.step_per_frame_m * camera_rate_hz, fallback_ground_m })
    }

    /// Walking speed (m/s).
    pub fn speed_mps(&self) -> f64 {
        self.speed_mps
    }

    /// Length of the polyline (m).
    pub fn length_m(&self) -> f64 {
        self.lengths.last().copied().unwrap_or(0.0)
    }

    /// Point at arc length `s` (clamped to the polyline).
    fn point_at(&self, s: f64) -> Vector2<f64> {
        let first = self.points.first().copied().unwrap_or_else(Vector2::zeros);
        if self.points.len() < 2 || s <= 0.0 {
            return first;
        }
        let segment = self.lengths.partition_point(|&l| l <= s).clamp(1, self.points.len() - 1);
        let (a, b) = (self.points.get(segment - 1).copied().unwrap_or(first), self.points.get(segment).copied().unwrap_or(first));
        let (la, lb) = (self.lengths.get(segment - 1).copied().unwrap_or(0.0), self.lengths.get(segment).copied().unwrap_or(0.0));
        if lb <= la {
            return b;
        }
        a + (b - a) * ((s - la) / (lb - la)).clamp(0.0, 1.0)
    }

    /// Walker position and heading (rad) at arc length `s`.
    fn walker_at(&self, s: f64) -> (Vector2<f64>, f64) {
        let w = self.config.turn_smoothing_m.max(1e-3);
        let total = self.length_m();
        let s = s.clamp(0.0, total);
        let (behind, ahead) = (self.point_at(s - w), self.point_at(s + w));
        let chord = ahead - behind;
        let heading = if chord.norm() > 1e-9 {
            chord.y.atan2(chord.x)
        } else {
            // A degenerate path (single waypoint): the configured heading.
            self.config.heading_deg.to_radians()
        };
        // Near the ends the chord is one-sided; the midpoint rule would stop short, so use the point itself there.
        let position = if s < w || s > total - w { self.point_at(s) } else { (behind + ahead) / 2.0 };
        (position, heading)
    }

    /// Mean terrain height on the smoothing disc around `p`.
    pub fn ground_height(&self, scene: &Scene, p: &Vector2<f64>) -> f64 {
        let r = self.config.ground_smoothing_m;
        let mut samples = vec![scene.height_at(p.x, p.y)];
        if r > 0.0 {
            for k in 0..8 {
                let angle = k as f64 * std::f64::consts::FRAC_PI_4;
                samples.push(scene.height_at(p.x + r * angle.cos(), p.y + r * angle.sin()));
            }
        }
        let valid: Vec<f64> = samples.into_iter().flatten().collect();
        if valid.is_empty() {
            self.fallback_ground_m
        } else {
            valid.iter().sum::<f64>() / valid.len() as f64
        }
    }

    /// `world_from_walker` at time `t`: on the ground under the walker plus the camera height, x
    /// along the heading, z up (the camera's `base`, to which sway and the pitched camera attach).
    pub fn world_from_walker(&self, scene: &Scene, t: f64) -> Isometry3<f64> {
        let (p, heading) = self.walker_at(self.speed_mps * t.max(0.0));
        let z = self.ground_height(scene, &p) + self.config.camera_height_m;
        Isometry3::from_parts(Translation3::new(p.x, p.y, z), UnitQuaternion::from_euler_angles(0.0, 0.0, heading))
    }

    /// `walker_from_camera` (optical): pitched down by `pitch_deg`.
    pub fn walker_from_camera(&self) -> Isometry3<f64> {
        let pitch = self.config.pitch_deg.to_radians().clamp(-FRAC_PI_2, FRAC_PI_2);
        Isometry3::from_parts(Translation3::identity(), UnitQuaternion::from_euler_angles(0.0, pitch, 0.0) * link_from_optical())
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::scene::heightfield::tests::tilted_plane;
    use nalgebra::Vector3;

    #[test]
    fn walk_keeps_height_above_the_ground_and_pitch() {
        let scene = Scene::from_terrain(tilted_plane());
        let config = CameraPathConfig { ground_smoothing_m: 0.0, pitch_deg: 40.0, ..CameraPathConfig::default() };
        let path = CameraPath::new(&config, &scene, 30.0).unwrap();
        assert!((path.speed_mps() - 0.15).abs() < 1e-12);
        let camera = path.walker_from_camera();
        for frame in [0, 10, 60] {
            let t = frame as f64 / 30.0;
            let pose = path.world_from_walker(&scene, t) * camera;
            let p = pose.translation.vector;
            // Default start: 0.5 m inside the −x edge (x = −0.5), middle of y; 5 mm per frame.
            assert!((p.x - (0.0 + 0.005 * frame as f64)).abs() < 1e-9 && p.y.abs() < 1e-9, "{p:?}");
            assert!((p.z - scene.height_at(p.x, p.y).unwrap() - 0.45).abs() < 1e-6);
            let axis = pose.rotation * Vector3::z();
            assert!(((-axis.z).asin() - 40f64.to_radians()).abs() < 1e-9 && axis.x > 0.0);
        }
    }

    #[test]
    fn waypoints_turn_smoothly_and_stop_at_the_end() {
        let scene = Scene::from_terrain(tilted_plane());
        let config = CameraPathConfig { waypoints_m: vec![[-0.4, 0.0], [0.0, 0.0], [0.0, 0.2]], ..CameraPathConfig::default() };
        let path = CameraPath::new(&config, &scene, 30.0).unwrap();
        assert!((path.length_m() - 0.6).abs() < 1e-12);
        let mut previous: Option<Isometry3<f64>> = None;
        for i in 0..200 {
            let pose = path.world_from_walker(&scene, i as f64 / 30.0);
            if let Some(before) = previous {
                // ≤ 5 mm and < 3.5° per frame: no jumps at the corner.
                let moved = (pose.translation.vector.xy() - before.translation.vector.xy()).norm();
                assert!(moved < 0.0051, "frame {i}: {moved}");
                assert!(pose.rotation.angle_to(&before.rotation) < 3.5f64.to_radians(), "frame {i}");
            }
            previous = Some(pose);
        }
        let end = previous.unwrap();
        assert!((end.translation.vector.xy() - Vector2::new(0.0, 0.2)).norm() < 1e-9);
        assert!((end.rotation.euler_angles().2 - FRAC_PI_2).abs() < 1e-9);
        let bad = CameraPathConfig { waypoints_m: vec![[f64::NAN, 0.0]], ..CameraPathConfig::default() };
        assert!(CameraPath::new(&bad, &scene, 30.0).is_err());
        let bad = CameraPathConfig { camera_height_m: 0.0, ..CameraPathConfig::default() };
        assert!(CameraPath::new(&bad, &scene, 30.0).unwrap_err().to_string().contains("camera_height_m"));
    }
}

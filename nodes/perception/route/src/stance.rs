//! Stances and their movement flexibility (CNN IV). A stance σ = (h_l, h_r) assigns a left and a
//! right foothold (the biped's two limbs; CNN's RoboSimian has four). At a body position v it is
//! valid when both holds are at least the minimum separation apart and both reachable;
//! Flex(v, σ) ∈ [0, 1] is "the fraction of the robot's height and yaw workspace in which" the holds
//! are reachable, sampled on a grid of body heights and yaws, each sample solved with the leg IK.
//!
//! The nominal pose (CNN: "about the terrain plane estimated by MSAC") is here the plane through the
//! stance's holds, which the gravity-aligned frame makes horizontal: base_link at v's (x, y), at a
//! sampled height above the holds' mean height, upright, yawed by a sampled angle relative to the
//! stance heading (the feet face the direction with the left hold on their left). A sample also
//! needs the hips above the terrain at v, so the body does not pass through a rock between the feet.

use nalgebra::Vector3;

use crate::biped::BipedModel;

/// A stance: cluster indices of the left and right holds and its Flex at the body position.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Stance {
    pub left: usize,
    pub right: usize,
    pub flex: f64,
}

/// The sampling grid of the body's height and yaw workspace.
#[derive(Debug, Clone, PartialEq)]
pub struct WorkspaceSamples {
    /// base_link heights above the holds' mean height (m).
    pub heights_m: Vec<f64>,
    /// Body yaws relative to the stance heading (rad).
    pub yaws_rad: Vec<f64>,
}

impl WorkspaceSamples {
    /// `heights` × `yaws` samples spread evenly over the biped's workspace, ends included.
    pub fn new(biped: &BipedModel, heights: usize, yaws: usize) -> Self {
        let spread = |(lo, hi): (f64, f64), n: usize| -> Vec<f64> {
            if n <= 1 {
                vec![0.5 * (lo + hi)]
            } else {
                (0..n).map(|i| lo + (hi - lo) * i as f64 / (n - 1) as f64).collect()
            }
        };
        Self { heights_m: spread(biped.height_range_m, heights), yaws_rad: spread(biped.yaw_range_rad, yaws) }
    }

    /// Number of samples.
    pub fn len(&self) -> usize {
        self.heights_m.len() * self.yaws_rad.len()
    }

    /// True when there is no sample.
    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }
}

/// The heading of a stance (rad, about z): the direction the feet face with `left` on their left.
pub fn stance_heading(left: &Vector3<f64>, right: &Vector3<f64>) -> f64 {
    let d = left - right;
    // forward = (l − r) turned by −90° about z
    (-d.x).atan2(d.y)
}

/// Flex(v, σ): the fraction of workspace samples in which both holds are reachable with the body at
/// `v` (the terrain point under the body; its height bounds the hips from below).
pub fn flex(biped: &BipedModel, samples: &WorkspaceSamples, v: &Vector3<f64>, left: &Vector3<f64>, right: &Vector3<f64>) -> f64 {
    flex_above(biped, samples, v, left, right, 0.0).unwrap_or(0.0)
}

/// Flex(v, σ) when it exceeds `to_beat`, else `None`; stops sampling as soon as so many samples
/// failed that `to_beat` cannot be exceeded (the search for σ*(v) only needs the best stance).
pub fn flex_above(
    biped: &BipedModel,
    samples: &WorkspaceSamples,
    v: &Vector3<f64>,
    left: &Vector3<f64>,
    right: &Vector3<f64>,
    to_beat: f64,
) -> Option<f64> {
    if samples.is_empty() || (left - right).norm() < biped.min_separation_m {
        return None;
    }
    let total = samples.len();
    // More failures than this and Flex ≤ to_beat.
    let allowed_failures = total as f64 * (1.0 - to_beat);
    let heading = stance_heading(left, right);
    let reference = 0.5 * (left.z + right.z);
    let hip_below_base = -biped.left.hip_in_base.z.max(biped.right.hip_in_base.z);
    let mut failures = 0usize;
    for &h in &samples.heights_m {
        let base = Vector3::new(v.x, v.y, reference + h);
        if base.z - hip_below_base < v.z {
            failures += samples.yaws_rad.len();
        } else {
            for &yaw in &samples.yaws_rad {
                if !biped.stance_reachable(&base, heading + yaw, heading, left, right) {
                    failures += 1;
                }
            }
        }
        if failures as f64 >= allowed_failures {
            return None;
        }
    }
    let f = (total - failures) as f64 / total as f64;
    (f > to_beat).then_some(f)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn heading_faces_forward_with_left_on_the_left() {
        let h = stance_heading(&Vector3::new(0.0, 0.04, 0.0), &Vector3::new(0.0, -0.04, 0.0));
        assert!(h.abs() < 1e-12);
        let h = stance_heading(&Vector3::new(-0.04, 0.0, 0.0), &Vector3::new(0.04, 0.0, 0.0));
        assert!((h - std::f64::consts::FRAC_PI_2).abs() < 1e-12);
    }

    #[test]
    fn flex_is_high_under_the_hips_and_falls_off() {
        let biped = BipedModel::rpbp().unwrap();
        let samples = WorkspaceSamples::new(&biped, 5, 7);
        assert_eq!(samples.len(), 35);
        let v = Vector3::new(0.0, 0.0, 0.0);
        let natural = flex(&biped, &samples, &v, &Vector3::new(0.0, 0.037, 0.0), &Vector3::new(0.0, -0.037, 0.0));
        let wide = flex(&biped, &samples, &v, &Vector3::new(0.0, 0.12, 0.0), &Vector3::new(0.0, -0.12, 0.0));
        let stride = flex(&biped, &samples, &v, &Vector3::new(0.10, 0.037, 0.0), &Vector3::new(-0.10, -0.037, 0.0));
        let too_far = flex(&biped, &samples, &v, &Vector3::new(0.3, 0.037, 0.0), &Vector3::new(-0.3, -0.037, 0.0));
        assert!(natural > 0.3 && natural <= 1.0, "{natural}");
        assert!(wide < natural && stride < natural, "{wide} {stride} {natural}");
        assert_eq!(too_far, 0.0);
        // Closer than the sole width: no stance.
        assert_eq!(flex(&biped, &samples, &v, &Vector3::new(0.0, 0.02, 0.0), &Vector3::new(0.0, -0.02, 0.0)), 0.0);
        // A rock 0.3 m high under the body between the feet: the hips would be inside it.
        assert_eq!(
            flex(&biped, &samples, &Vector3::new(0.0, 0.0, 0.3), &Vector3::new(0.0, 0.037, 0.0), &Vector3::new(0.0, -0.037, 0.0)),
            0.0
        );
    }
}

//! Stage iv (J 4.4, steps 11–12): r-ball neighbourhoods in the organized cloud C by image
//! back-projection, then nf uniformly spread points for fitting.
//!
//! The r-sphere around a seed `s` projects into the image inside the rectangle centred at the seed's
//! pixel with half sides `f_x·r·√(s_x² + s_z²) / (s_z (s_z − r))` and `f_y·r·√(s_y² + s_z²) / (s_z (s_z − r))`
//! (for `p = s + d`, `|d| ≤ r`: `x/z − s_x/s_z = (s_z d_x − s_x d_z) / (s_z (s_z + d_z))`, whose
//! numerator is at most `r·√(s_x² + s_z²)`; on the optical axis this is the `f·r/(s_z − r)` of the
//! projected circle, off-axis the circle becomes an ellipse that the rectangle still bounds).
//! Every pixel of the rectangle is tested with the 3D distance (J: "the Euclidean distance of the
//! corresponding 3D points to the seed point is checked"). O(r²) per seed, no extra data structure.

use nalgebra::Vector3;
use rand::Rng;

use crate::acquire::OrganizedCloud;
use patchwalk_fusion::camera::Intrinsics;

/// Configuration of stage iv (J 4.4, J 6.1.2).
#[derive(Debug, Clone, PartialEq, serde::Serialize, serde::Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct NeighbourhoodConfig {
    /// nf: points kept per neighbourhood for fitting (J 6.1.2: nf = 50).
    pub fit_points: usize,
    /// Points kept for validation. The coverage test (J eq 16–17) needs the dense neighbourhood:
    /// with N points on N_p ≈ 100 cells of w_c = 0.01 m, a cell is bad when it holds fewer than
    /// 0.8·N/N_p points, which happens by chance to ~40 % of the cells at N = 400 but to ~15 % at
    /// the ~2000 points of a Kinect r = 0.05 m ball at 1 m. Default: all points (J validates
    /// against the neighbourhood data); lower it to trade coverage accuracy for speed.
    pub validation_points: usize,
    /// Neighbourhoods with fewer points than this are skipped (no fit).
    pub min_points: usize,
}

impl Default for NeighbourhoodConfig {
    fn default() -> Self {
        Self { fit_points: 50, validation_points: usize::MAX, min_points: 20 }
    }
}

/// The bounding rectangle `(u0, v0, u1, v1)` (inclusive, clipped) of the r-ball around `seed` in the
/// image, or `None` if it does not reach the image. A ball that contains the camera centre covers
/// the whole image.
pub fn bounding_square(intrinsics: &Intrinsics, seed_in_camera: &Vector3<f64>, radius_m: f64) -> Option<(usize, usize, usize, usize)> {
    let (w, h) = (intrinsics.width as f64, intrinsics.height as f64);
    if !(seed_in_camera.iter().all(|c| c.is_finite()) && radius_m.is_finite() && radius_m > 0.0) {
        return None;
    }
    if seed_in_camera.z <= radius_m {
        // The ball reaches the camera plane: search everywhere (rare, and still correct).
        return Some((0, 0, intrinsics.width - 1, intrinsics.height - 1));
    }
    let (u, v) = intrinsics.project(seed_in_camera)?;
    let s = seed_in_camera;
    let denominator = s.z * (s.z - radius_m);
    let half_u = intrinsics.fx * radius_m * s.x.hypot(s.z) / denominator;
    let half_v = intrinsics.fy * radius_m * s.y.hypot(s.z) / denominator;
    let (u0, u1) = ((u - half_u).floor().max(0.0), (u + half_u).ceil().min(w - 1.0));
    let (v0, v1) = ((v - half_v).floor().max(0.0), (v + half_v).ceil().min(h - 1.0));
    if u0 > u1 || v0 > v1 {
        return None;
    }
    Some((u0 as usize, v0 as usize, u1 as usize, v1 as usize))
}

/// Step 11: row-major indices into C of every valid point within `radius_m` of the seed,
/// appended to `out` (cleared first; reuse it across seeds to avoid allocations).
pub fn ball_neighbourhood(
    cloud: &OrganizedCloud,
    intrinsics: &Intrinsics,
    seed_in_camera: &Vector3<f64>,
    radius_m: f64,
    out: &mut Vec<u32>,
) {
    out.clear();
    let Some((u0, v0, u1, v1)) = bounding_square(intrinsics, seed_in_camera, radius_m) else { return };
    let seed = seed_in_camera.cast::<f32>();
    let r2 = (radius_m * radius_m) as f32;
    for v in v0..=v1.min(cloud.height.saturating_sub(1)) {
        let row_start = v * cloud.width;
        let Some(row) = cloud.points_in_camera.get(row_start + u0..=row_start + u1.min(cloud.width.saturating_sub(1))) else { continue };
        for (du, p) in row.iter().enumerate() {
            // NaN points fail the comparison.
            if (p - seed).norm_squared() <= r2 {
                out.push((row_start + u0 + du) as u32);
            }
        }
    }
}

/// Step 12: `count` indices spread uniformly over the neighbourhood: a uniform random subset
/// without replacement (all of them when fewer), in image order.
pub fn uniform_subset<R: Rng + ?Sized>(rng: &mut R, indices: &[u32], count: usize) -> Vec<u32> {
    if indices.len() <= count {
        return indices.to_vec();
    }
    let mut picked: Vec<u32> =
        rand::seq::index::sample(rng, indices.len(), count).into_iter().filter_map(|i| indices.get(i).copied()).collect();
    picked.sort_unstable();
    picked
}

/// Points of C at `indices`, as f64 vectors in the camera frame.
pub fn gather(cloud: &OrganizedCloud, indices: &[u32]) -> Vec<Vector3<f64>> {
    indices.iter().filter_map(|&i| cloud.points_in_camera.get(i as usize)).map(|p| p.cast::<f64>()).collect()
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::acquire::organized_cloud;
    use patchwalk_fusion::dataset::{test_data_dir, Dataset};
    use rand::SeedableRng;

    fn brute_force(cloud: &OrganizedCloud, seed: &Vector3<f64>, r: f64) -> Vec<u32> {
        let s = seed.cast::<f32>();
        (0..cloud.points_in_camera.len() as u32)
            .filter(|&i| (cloud.points_in_camera[i as usize] - s).norm_squared() <= (r * r) as f32)
            .collect()
    }

    #[test]
    fn neighbourhoods_match_brute_force_on_real_frames() {
        for (name, radius) in [("tum_fr1_xyz", 0.05), ("cape_tunnel/depth_0.png", 0.1), ("open3d_rgbd", 0.05)] {
            let dataset = Dataset::open(&test_data_dir().join(name)).unwrap();
            let cloud = organized_cloud(&dataset.load_depth(0).unwrap(), &dataset.intrinsics).unwrap();
            let mut rng = rand::rngs::StdRng::seed_from_u64(5);
            let mut out = Vec::new();
            let mut checked = 0;
            while checked < 8 {
                let i = rng.random_range(0..cloud.points_in_camera.len());
                let seed = cloud.points_in_camera[i];
                if !seed.z.is_finite() {
                    continue;
                }
                // Seeds off the surface too (a D point need not lie in C).
                let seed = seed.cast::<f64>() + Vector3::new(0.0, 0.0, 0.004);
                ball_neighbourhood(&cloud, &dataset.intrinsics, &seed, radius, &mut out);
                assert_eq!(out, brute_force(&cloud, &seed, radius), "{name} seed {seed:?}");
                checked += 1;
            }
        }
    }

    #[test]
    fn ball_around_the_camera_and_outside_the_view() {
        let intrinsics = Intrinsics::new(8, 6, 4.0, 4.0, 3.5, 2.5).unwrap();
        let depth = patchwalk_fusion::camera::DepthImage::new(8, 6, vec![0.1; 48]).unwrap();
        let cloud = organized_cloud(&depth, &intrinsics).unwrap();
        let mut out = Vec::new();
        // Ball containing the camera: everything in range is found.
        ball_neighbourhood(&cloud, &intrinsics, &Vector3::zeros(), 1.0, &mut out);
        assert_eq!(out.len(), 48);
        // Behind the camera: nothing, no panic.
        ball_neighbourhood(&cloud, &intrinsics, &Vector3::new(0.0, 0.0, -5.0), 0.5, &mut out);
        assert!(out.is_empty());
        ball_neighbourhood(&cloud, &intrinsics, &Vector3::new(f64::NAN, 0.0, 1.0), 0.5, &mut out);
        assert!(out.is_empty());
    }

    #[test]
    fn uniform_subset_is_a_subset_of_the_requested_size() {
        let indices: Vec<u32> = (0..1000).map(|i| i * 3).collect();
        let mut rng = rand::rngs::StdRng::seed_from_u64(1);
        let subset = uniform_subset(&mut rng, &indices, 50);
        assert_eq!(subset.len(), 50);
        assert!(subset.windows(2).all(|w| w[0] < w[1]));
        assert!(subset.iter().all(|i| indices.contains(i)));
        // Spread: both halves of the neighbourhood are sampled.
        assert!(subset.iter().any(|&i| i < 1500) && subset.iter().any(|&i| i >= 1500));
        assert_eq!(uniform_subset(&mut rng, &indices[..10], 50).len(), 10);
    }
}

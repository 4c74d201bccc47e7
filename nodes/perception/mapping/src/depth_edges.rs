//! Depth discontinuities of the auxiliary image D and every pixel's distance to the nearest one.
//!
//! J's normals come from integral images (J \[76\], Holzer et al.), whose method shrinks the
//! smoothing window where the depth jumps, so that a box never averages an occluding surface with
//! the one behind it. A foot needs more: the whole foot disc on one surface. A pixel whose foot
//! window (half size `r·f/Z`) holds a depth jump sees either the near side of an occluding edge (the
//! disc hangs over it) or the far side (part of the disc is hidden in its shadow); neither is a
//! foothold the frame can confirm, and its box normals mix two surfaces. [`EdgeDistance`] gives
//! the saliency filter that distance.

use patchwalk_fusion::camera::DepthImage;
use rayon::prelude::*;

/// Chessboard distance (pixels) from every pixel of D to the nearest pixel beside a depth jump.
#[derive(Debug, Clone)]
pub struct EdgeDistance {
    width: usize,
    distance_px: Vec<u32>,
}

impl EdgeDistance {
    /// Marks both pixels of every 4-neighbour pair with valid depths `z₁ < z₂` and
    /// `z₂ − z₁ > relative_jump · z₁`, then a two-pass chamfer transform. A non-finite or
    /// non-positive `relative_jump` marks nothing (every distance is `u32::MAX`).
    pub fn new(depth: &DepthImage, relative_jump: f64) -> Self {
        let (width, height) = (depth.width, depth.height);
        let mut distance_px = vec![u32::MAX; width * height];
        if !(relative_jump.is_finite() && relative_jump > 0.0) || depth.depth_m.len() != width * height {
            return Self { width, distance_px };
        }
        let jump = relative_jump as f32;
        // NaN (no depth) compares false, so holes mark nothing.
        let is_jump = |a: f32, b: f32| (a - b).abs() > jump * a.min(b);
        let z = &depth.depth_m;
        distance_px.par_chunks_mut(width.max(1)).enumerate().for_each(|(v, out)| {
            let row = &z[v * width..(v + 1) * width];
            let above = (v > 0).then(|| &z[(v - 1) * width..v * width]);
            let below = (v + 1 < height).then(|| &z[(v + 1) * width..(v + 2) * width]);
            for (u, d) in out.iter_mut().enumerate() {
                let c = row[u];
                let marked = (u > 0 && is_jump(c, row[u - 1]))
                    || (u + 1 < width && is_jump(c, row[u + 1]))
                    || above.is_some_and(|a| is_jump(c, a[u]))
                    || below.is_some_and(|b| is_jump(c, b[u]));
                if marked {
                    *d = 0;
                }
            }
        });
        chamfer_chessboard(&mut distance_px, width, height);
        Self { width, distance_px }
    }

    /// Distance of pixel `(u, v)` to the nearest depth jump (`u32::MAX`: none in the image, or
    /// outside it).
    pub fn at(&self, u: usize, v: usize) -> u32 {
        if u >= self.width {
            return u32::MAX;
        }
        self.distance_px.get(v * self.width + u).copied().unwrap_or(u32::MAX)
    }
}

/// In-place chessboard distance transform: forward pass over the upper-left neighbours, backward
/// pass over the lower-right ones (`u32::MAX` = no source yet; saturating so it stays so).
fn chamfer_chessboard(d: &mut [u32], width: usize, height: usize) {
    if width == 0 || d.len() < width * height {
        return;
    }
    let d = &mut d[..width * height];
    // Forward: left neighbour in the row, then the three above.
    for v in 0..height {
        let (done, rest) = d.split_at_mut(v * width);
        let row = &mut rest[..width];
        if v > 0 {
            let above = &done[(v - 1) * width..];
            for u in 0..width {
                let lo = u.saturating_sub(1);
                let hi = (u + 1).min(width - 1);
                let best = above[lo].min(above[u]).min(above[hi]).saturating_add(1);
                row[u] = row[u].min(best);
            }
        }
        for u in 1..width {
            row[u] = row[u].min(row[u - 1].saturating_add(1));
        }
    }
    // Backward: right neighbour in the row, then the three below.
    for v in (0..height).rev() {
        let (head, below) = d.split_at_mut((v + 1) * width);
        let row = &mut head[v * width..];
        if v + 1 < height {
            for u in 0..width {
                let lo = u.saturating_sub(1);
                let hi = (u + 1).min(width - 1);
                let best = below[lo].min(below[u]).min(below[hi]).saturating_add(1);
                row[u] = row[u].min(best);
            }
        }
        for u in (0..width - 1).rev() {
            row[u] = row[u].min(row[u + 1].saturating_add(1));
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn image(width: usize, height: usize, depth: impl Fn(usize, usize) -> f32) -> DepthImage {
        let depth_m = (0..width * height).map(|i| depth(i % width, i / width)).collect();
        DepthImage { width, height, depth_m }
    }

    #[test]
    fn a_step_is_marked_on_both_sides_and_distances_grow_away_from_it() {
        // A box 1.0 m away in front of a wall at 1.5 m, from column 20 on.
        let depth = image(40, 30, |u, _| if u < 20 { 1.5 } else { 1.0 });
        let edges = EdgeDistance::new(&depth, 0.05);
        for v in 0..30 {
            assert_eq!((edges.at(19, v), edges.at(20, v)), (0, 0));
            assert_eq!(edges.at(10, v), 9);
            assert_eq!(edges.at(35, v), 15);
        }
        assert_eq!(edges.at(40, 0), u32::MAX);
    }

    #[test]
    fn a_slanted_plane_and_holes_are_not_jumps() {
        // A floor seen at a grazing angle: depth grows 2 % per row; holes of missing depth.
        let depth = image(30, 30, |u, v| if (u * 7 + v * 3) % 11 == 0 { f32::NAN } else { 1.0 * 1.02f32.powi(v as i32) });
        let edges = EdgeDistance::new(&depth, 0.05);
        assert!((0..30).all(|v| (0..30).all(|u| edges.at(u, v) == u32::MAX)));
        // Off: nothing is marked even across a real step.
        let step = image(10, 10, |u, _| if u < 5 { 2.0 } else { 1.0 });
        assert_eq!(EdgeDistance::new(&step, 0.0).at(4, 4), u32::MAX);
        assert_eq!(EdgeDistance::new(&step, f64::NAN).at(4, 4), u32::MAX);
    }

    #[test]
    fn chessboard_distance_from_one_point() {
        let mut d = vec![u32::MAX; 7 * 5];
        d[2 * 7 + 3] = 0;
        chamfer_chessboard(&mut d, 7, 5);
        for v in 0..5i64 {
            for u in 0..7i64 {
                assert_eq!(d[(v * 7 + u) as usize] as i64, (u - 3).abs().max((v - 2).abs()));
            }
        }
    }
}

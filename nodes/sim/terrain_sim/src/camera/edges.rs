//! Depth discontinuities of a rendered image: the pixels at depth edges, which a structured-light
//! sensor does not measure, and the image gradients of depth used to re-render at a reused pose.

use rayon::prelude::*;

/// Whether pixel `(u, v)` of depth `z` lies at a depth discontinuity: a valid 4-neighbour differs
/// by more than `ratio · z`.
#[inline]
pub(super) fn at_depth_edge(depth: &[f32], width: usize, height: usize, u: usize, v: usize, z: f32, ratio: f32) -> bool {
    let neighbours = [
        (u > 0).then(|| v * width + u - 1),
        (u + 1 < width).then(|| v * width + u + 1),
        (v > 0).then(|| (v - 1) * width + u),
        (v + 1 < height).then(|| (v + 1) * width + u),
    ];
    neighbours.into_iter().flatten().filter_map(|i| depth.get(i).copied()).any(|n| n.is_finite() && (n - z).abs() > ratio * z)
}

/// Image gradients (m/px) of a depth image: central differences, one-sided next to invalid pixels
/// or depth edges (jumps above `ratio · z`), 0 where neither neighbour is usable.
pub(super) fn depth_gradients(depth: &[f32], width: usize, height: usize, ratio: f32) -> (Vec<f32>, Vec<f32>) {
    let at = |u: usize, v: usize| depth.get(v * width + u).copied().filter(|z| z.is_finite());
    let derivative = |z: f32, before: Option<f32>, after: Option<f32>| {
        let near = |n: Option<f32>| n.filter(|n| (n - z).abs() <= ratio * z);
        match (near(before), near(after)) {
            (Some(b), Some(a)) => 0.5 * (a - b),
            (Some(b), None) => z - b,
            (None, Some(a)) => a - z,
            (None, None) => 0.0,
        }
    };
    let mut gradient_u = vec![0.0f32; width * height];
    let mut gradient_v = vec![0.0f32; width * height];
    gradient_u.par_chunks_mut(width).zip(gradient_v.par_chunks_mut(width)).enumerate().for_each(|(v, (row_u, row_v))| {
        for u in 0..width {
            let Some(z) = at(u, v) else { continue };
            let (left, right) = (u.checked_sub(1).and_then(|l| at(l, v)), (u + 1 < width).then(|| at(u + 1, v)).flatten());
            let (up, down) = (v.checked_sub(1).and_then(|w| at(u, w)), (v + 1 < height).then(|| at(u, v + 1)).flatten());
            if let (Some(gu), Some(gv)) = (row_u.get_mut(u), row_v.get_mut(u)) {
                *gu = derivative(z, left, right);
                *gv = derivative(z, up, down);
            }
        }
    });
    (gradient_u, gradient_v)
}

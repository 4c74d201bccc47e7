//! Stage ii, steps 3–5 (J 4.2): background removal by a depth threshold, a discontinuity-preserving
//! bilateral filter, and a 2×2 median downsample that makes the auxiliary image D.
//!
//! Everything works on depth images (metres along the optical axis, NaN invalid): the organized
//! cloud of a pinhole camera is `back_project(u, v, z)`, so filtering z filters the cloud along the
//! pixel rays and keeps it organized (J: "we replace them with NaN values to maintain their
//! organization"). The returned C (full resolution) is used for neighbourhoods, D for saliency and
//! seeds (J step 5/6).

use rayon::prelude::*;

use crate::acquire::{check_size, AcquireError};
use patchwalk_fusion::camera::{DepthImage, Intrinsics};

/// Configuration of steps 3–5.
#[derive(Debug, Clone, PartialEq, serde::Serialize, serde::Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct PreprocessConfig {
    /// Step 3: depths below this are removed (m). J gives no number; the near limit of a
    /// Kinect/PrimeSense is about 0.4 m, raycast birds-eye views can be closer.
    pub z_min_m: f64,
    /// Step 3: "background" threshold on the camera-frame z (m). J gives no number; 4 m is the
    /// usable Kinect range (beyond it the disparity noise of J eq 2 exceeds a foot-size patch's dmax).
    pub z_max_m: f64,
    /// Step 4: half size of the bilateral window in pixels (window 2·radius + 1).
    pub bilateral_radius_px: usize,
    /// Step 4: spatial standard deviation of the bilateral filter (pixels).
    pub bilateral_sigma_px: f64,
    /// Step 4: range standard deviation at 1 m depth (m); it grows with z² like the disparity
    /// error of J eq 2 (σ_z = z²·σ_m/(f·b)). 0.01 m ≈ 3σ of a Kinect at 1 m, so real steps of a
    /// few centimetres are preserved.
    pub bilateral_sigma_depth_at_1m: f64,
    /// Step 5: make D by a 2×2 median downsample (J: for a 640×480 physical camera; a 200×200
    /// birds-eye raycast uses D = C, set this to false).
    pub median_downsample: bool,
}

impl Default for PreprocessConfig {
    fn default() -> Self {
        Self {
            z_min_m: 0.3,
            z_max_m: 4.0,
            bilateral_radius_px: 2,
            bilateral_sigma_px: 1.5,
            bilateral_sigma_depth_at_1m: 0.01,
            median_downsample: true,
        }
    }
}

/// Errors of steps 3–5.
#[derive(Debug, thiserror::Error, PartialEq)]
pub enum PreprocessError {
    #[error(transparent)]
    Acquire(#[from] AcquireError),
    #[error("invalid preprocessing config: {0}")]
    Config(String),
}

/// Output of steps 3–5.
#[derive(Debug, Clone)]
pub struct Preprocessed {
    /// C: background-removed, bilateral-filtered depth at full resolution.
    pub filtered: DepthImage,
    /// D: the auxiliary image for saliency and seeds (2×2 median of C, or C itself).
    pub auxiliary: DepthImage,
    /// Intrinsics of D.
    pub auxiliary_intrinsics: Intrinsics,
}

impl PreprocessConfig {
    fn check(&self) -> Result<(), PreprocessError> {
        let ok = self.z_min_m.is_finite()
            && self.z_max_m > self.z_min_m
            && self.bilateral_sigma_px > 0.0
            && self.bilateral_sigma_depth_at_1m > 0.0
            && self.bilateral_radius_px <= 16;
        if ok {
            Ok(())
        } else {
            Err(PreprocessError::Config(format!("{self:?}")))
        }
    }
}

/// Steps 3–5 in order. Step 3 is folded into step 4 (the background test is applied while the
/// bilateral filter pads its input), so the full-resolution image is read once.
pub fn preprocess(depth: &DepthImage, intrinsics: &Intrinsics, config: &PreprocessConfig) -> Result<Preprocessed, PreprocessError> {
    config.check()?;
    check_size(depth, intrinsics)?;
    let filtered = bilateral_filter_in_range(
        depth,
        (config.z_min_m as f32, config.z_max_m as f32),
        config.bilateral_radius_px,
        config.bilateral_sigma_px,
        config.bilateral_sigma_depth_at_1m,
    );
    let (auxiliary, auxiliary_intrinsics) = if config.median_downsample && depth.width >= 2 && depth.height >= 2 {
        (median_downsample_2x2(&filtered), intrinsics.scaled(0.5))
    } else {
        (filtered.clone(), *intrinsics)
    };
    Ok(Preprocessed { filtered, auxiliary, auxiliary_intrinsics })
}

/// Step 3: depths outside `[z_min, z_max]` become NaN.
pub fn remove_background(depth: &DepthImage, z_min_m: f64, z_max_m: f64) -> DepthImage {
    let (lo, hi) = (z_min_m as f32, z_max_m as f32);
    let depth_m = depth.depth_m.iter().map(|&z| if z >= lo && z <= hi { z } else { f32::NAN }).collect();
    DepthImage { width: depth.width, height: depth.height, depth_m }
}

/// Step 4: discontinuity-preserving bilateral filter (J \[72\]). Each valid pixel becomes the
/// weighted mean of the valid pixels in its window, with weight
/// `exp(−Δp²/2σ_s²) · k(Δz²/2σ_r(z)²)`, `σ_r(z) = σ_1m·z²`; invalid pixels stay NaN. The range
/// kernel is the biweight `k(t) = (1 − t/4)₊²` (≈ e^{−t/2}·… near 0, exactly 0 beyond
/// |Δz| = 2√2 σ_r), so neighbours across a depth discontinuity get no weight at all and the inner
/// loop is branch- and division-free (vectorised). Rows run in parallel.
pub fn bilateral_filter(depth: &DepthImage, radius: usize, sigma_px: f64, sigma_depth_at_1m: f64) -> DepthImage {
    bilateral_filter_in_range(depth, (f32::NEG_INFINITY, f32::INFINITY), radius, sigma_px, sigma_depth_at_1m)
}

/// Steps 3 + 4: [`bilateral_filter`] of [`remove_background`]`(depth, z_min, z_max)`, bit for bit,
/// without the intermediate image. Depths outside `[z_min, z_max]` (and non-finite or non-positive
/// ones) are invalid: they get no weight and stay NaN.
///
/// Invalid taps are stored as 0. For a centre depth z the biweight of a 0 tap is
/// `(1 − z²/(8σ_1m²z⁴))₊²`, exactly 0 whenever z < 1/(2√2 σ_1m) (35 m for the default σ_1m), so
/// a row whose valid centres all satisfy that (checked in the same f32 arithmetic) needs no
/// validity mask in its inner loop; other rows multiply each weight by the tap's validity.
fn bilateral_filter_in_range(depth: &DepthImage, (lo, hi): (f32, f32), radius: usize, sigma_px: f64, sigma_depth_at_1m: f64) -> DepthImage {
    let (width, height) = (depth.width, depth.height);
    let padded_width = width + 2 * radius;
    // Zero-padded copy, 0 = invalid (step 3 applied here), so the inner loop needs no bounds or
    // NaN branches.
    let mut padded = vec![0.0f32; padded_width * height];
    padded.par_chunks_mut(padded_width.max(1)).zip(depth.depth_m.par_chunks(width.max(1))).for_each(|(dst, src)| {
        for (d, &z) in dst[radius..radius + width].iter_mut().zip(src) {
            *d = if z >= lo && z <= hi && z > 0.0 { z } else { 0.0 };
        }
    });
    let diameter = 2 * radius + 1;
    let spatial: Vec<f32> = (0..diameter)
        .flat_map(|dv| (0..diameter).map(move |du| (dv, du)))
        .map(|(dv, du)| {
            let (dy, dx) = (dv as f64 - radius as f64, du as f64 - radius as f64);
            (-(dx * dx + dy * dy) / (2.0 * sigma_px * sigma_px)).exp() as f32
        })
        .collect();
    let inv_two_sigma_sq_1m = (1.0 / (2.0 * sigma_depth_at_1m * sigma_depth_at_1m)) as f32;
    let mut out = vec![f32::NAN; width * height];
    out.par_chunks_mut(width.max(1)).enumerate().for_each_init(
        || (vec![0.0f32; width], vec![0.0f32; width], vec![0.0f32; width]),
        |(sum_w, sum_wz, quarter_inv), (v, out_row)| {
            let centre = &padded[v * padded_width + radius..v * padded_width + radius + width];
            for (q, &z) in quarter_inv.iter_mut().zip(centre) {
                // 1 / (8 σ_r(z)²) with σ_r = σ_1m z², i.e. t/4 = Δz²·q (0 for an invalid centre,
                // whose output is NaN). Scaling by 1/4 is exact, so (Δz²·inv)/4 = Δz²·(inv/4).
                let z2 = z * z;
                *q = if z > 0.0 { 0.25 * (inv_two_sigma_sq_1m / (z2 * z2)) } else { 0.0 };
            }
            // Does a 0 (invalid) tap get weight exactly 0 from every valid centre of the row?
            let zero_tap_ignored =
                centre.iter().zip(quarter_inv.iter()).all(|(&z, &q)| z.is_nan() || z <= 0.0 || biweight(0.0 - z, q) == 0.0);
            sum_w.fill(0.0);
            sum_wz.fill(0.0);
            // Window rows inside the image (rows outside it contribute nothing).
            for dv in radius.saturating_sub(v)..=(height - 1 + radius - v).min(2 * radius) {
                let src_v = v + dv - radius;
                let src_row = &padded[src_v * padded_width..(src_v + 1) * padded_width];
                let weights = &spatial[dv * diameter..(dv + 1) * diameter];
                // The default 5×5 window: all taps of a window row in one pass (sums stay in
                // registers; same per-pixel summation order as the generic loop below).
                if let Ok(weights) = <&[f32; 5]>::try_from(weights) {
                    if zero_tap_ignored {
                        window_row::<5, false>(src_row, weights, centre, quarter_inv, sum_w, sum_wz);
                    } else {
                        window_row::<5, true>(src_row, weights, centre, quarter_inv, sum_w, sum_wz);
                    }
                    continue;
                }
                for (du, &ws) in weights.iter().enumerate() {
                    let (Some(taps), Some(centre), Some(quarter_inv)) =
                        (src_row.get(du..du + width), centre.get(..width), quarter_inv.get(..width))
                    else {
                        continue;
                    };
                    let (sum_w, sum_wz) = (&mut sum_w[..width], &mut sum_wz[..width]);
                    if zero_tap_ignored {
                        tap_row::<false>(taps, ws, centre, quarter_inv, sum_w, sum_wz);
                    } else {
                        tap_row::<true>(taps, ws, centre, quarter_inv, sum_w, sum_wz);
                    }
                }
            }
            for (((o, &zc), &sw), &swz) in out_row.iter_mut().zip(centre).zip(sum_w.iter()).zip(sum_wz.iter()) {
                *o = if zc > 0.0 && sw > 0.0 { swz / sw } else { f32::NAN };
            }
        },
    );
    DepthImage { width, height, depth_m: out }
}

/// Step 4 sums of one tap (spatial weight `ws`) for every pixel of an output row; `MASK` multiplies
/// each weight by the tap's validity (see [`bilateral_filter_in_range`]). Equal-length slices, no
/// division, no branch: the loop vectorises.
#[inline(always)]
fn tap_row<const MASK: bool>(taps: &[f32], ws: f32, centre: &[f32], quarter_inv: &[f32], sum_w: &mut [f32], sum_wz: &mut [f32]) {
    let n = sum_w.len().min(sum_wz.len()).min(taps.len()).min(centre.len()).min(quarter_inv.len());
    let (taps, centre, quarter_inv) = (&taps[..n], &centre[..n], &quarter_inv[..n]);
    let (sum_w, sum_wz) = (&mut sum_w[..n], &mut sum_wz[..n]);
    for i in 0..n {
        let zs = taps[i];
        let a = biweight(zs - centre[i], quarter_inv[i]);
        let w = if MASK { ws * a * a * if zs > 0.0 { 1.0 } else { 0.0 } } else { ws * a * a };
        sum_w[i] += w;
        sum_wz[i] += w * zs;
    }
}

/// Step 4 sums of one window row with `D` taps (`weights`, the spatial weights of the row) into
/// `sum_w`, `sum_wz` for every pixel of an output row: each pixel adds its taps left to right
/// with the same arithmetic as the generic loop of [`bilateral_filter_in_range`], but reads and
/// writes its sums once per window row instead of once per tap. `MASK` multiplies each weight by
/// the tap's validity.
#[inline(always)]
fn window_row<const D: usize, const MASK: bool>(
    src_row: &[f32],
    weights: &[f32; D],
    centre: &[f32],
    quarter_inv: &[f32],
    sum_w: &mut [f32],
    sum_wz: &mut [f32],
) {
    let n = centre.len().min(quarter_inv.len()).min(sum_w.len()).min(sum_wz.len()).min((src_row.len() + 1).saturating_sub(D));
    let taps: [&[f32]; D] = std::array::from_fn(|du| &src_row[du..du + n]);
    let (centre, quarter_inv, sum_w, sum_wz) = (&centre[..n], &quarter_inv[..n], &mut sum_w[..n], &mut sum_wz[..n]);
    for i in 0..n {
        let (zc, q) = (centre[i], quarter_inv[i]);
        let (mut sw, mut swz) = (sum_w[i], sum_wz[i]);
        for du in 0..D {
            let zs = taps[du][i];
            let a = biweight(zs - zc, q);
            let mut w = weights[du] * a * a;
            if MASK {
                w *= if zs > 0.0 { 1.0 } else { 0.0 };
            }
            sw += w;
            swz += w * zs;
        }
        sum_w[i] = sw;
        sum_wz[i] = swz;
    }
}

/// Step 4 range kernel `(1 − t/4)₊` of a tap at depth difference `dz` (its square is the weight),
/// with `t/4 = dz²·quarter_inv`, `quarter_inv` = 1/(8σ_r²); a NaN gives 0.
#[inline(always)]
fn biweight(dz: f32, quarter_inv: f32) -> f32 {
    (1.0 - dz * dz * quarter_inv).max(0.0)
}

/// Step 5 median of one 2×2 block: the lower middle of its valid depths (NaN if none). Invalid
/// depths become +∞ so a 5-comparator network finds the two smallest values.
#[inline(always)]
fn median_of_4(block: [f32; 4]) -> f32 {
    let valid = block.iter().filter(|z| z.is_finite()).count();
    let [a, b, c, d] = block.map(|z| if z.is_finite() { z } else { f32::INFINITY });
    let (lo1, hi1) = if a < b { (a, b) } else { (b, a) };
    let (lo2, hi2) = if c < d { (c, d) } else { (d, c) };
    let smallest = if lo1 < lo2 { lo1 } else { lo2 };
    let (mid_lo, mid_hi) = (if lo1 < lo2 { lo2 } else { lo1 }, if hi1 < hi2 { hi1 } else { hi2 });
    let second = if mid_lo < mid_hi { mid_lo } else { mid_hi };
    match valid {
        0 => f32::NAN,
        1 | 2 => smallest,
        _ => second,
    }
}

/// Step 5: 2×2 median downsample. Each output pixel is the median of the valid depths of its
/// 2×2 block; with an even count the *lower* (nearer) middle value is taken, so the result is
/// always one of the measured depths and never a blend across a discontinuity. A block with no
/// valid depth gives NaN. An odd last row/column is dropped.
pub fn median_downsample_2x2(depth: &DepthImage) -> DepthImage {
    let (width, height) = (depth.width / 2, depth.height / 2);
    let mut out = vec![f32::NAN; width * height];
    out.par_chunks_mut(width.max(1)).enumerate().for_each(|(v, out_row)| {
        let row0 = &depth.depth_m[2 * v * depth.width..(2 * v + 1) * depth.width];
        let row1 = &depth.depth_m[(2 * v + 1) * depth.width..(2 * v + 2) * depth.width];
        for ((o, top), bottom) in out_row.iter_mut().zip(row0.chunks_exact(2)).zip(row1.chunks_exact(2)) {
            *o = median_of_4([top[0], top[1], bottom[0], bottom[1]]);
        }
    });
    DepthImage { width, height, depth_m: out }
}

#[cfg(test)]
mod tests {
    use super::*;
    use patchwalk_fusion::dataset::{test_data_dir, Dataset};
    use rand::{Rng, SeedableRng};
    use rand_distr::{Distribution, Normal};

    /// Left half at 1 m, right half at 1.5 m, with Gaussian noise of 3 mm.
    fn noisy_step(width: usize, height: usize) -> (DepthImage, Vec<f32>) {
        let mut rng = rand::rngs::StdRng::seed_from_u64(3);
        let noise = Normal::new(0.0, 0.003).unwrap();
        let truth: Vec<f32> = (0..width * height).map(|i| if i % width < width / 2 { 1.0 } else { 1.5 }).collect();
        let noisy = truth.iter().map(|&z| z + noise.sample(&mut rng) as f32).collect();
        (DepthImage::new(width, height, noisy).unwrap(), truth)
    }

    #[test]
    fn bilateral_smooths_noise_but_keeps_the_step() {
        let (image, truth) = noisy_step(64, 32);
        let filtered = bilateral_filter(&image, 2, 1.5, 0.01);
        let rms = |a: &[f32]| (a.iter().zip(&truth).map(|(x, t)| (x - t).powi(2)).sum::<f32>() / a.len() as f32).sqrt();
        assert!(rms(&filtered.depth_m) < 0.6 * rms(&image.depth_m));
        // Next to the step every pixel stays on its own side (no blending across 0.5 m).
        for v in 0..32 {
            for u in [30, 31, 32, 33] {
                let i = v * 64 + u;
                assert!((filtered.depth_m[i] - truth[i]).abs() < 0.02, "pixel ({u},{v}) {}", filtered.depth_m[i]);
            }
        }
    }

    #[test]
    fn bilateral_keeps_holes_and_ignores_them() {
        let mut depth = vec![2.0f32; 25];
        depth[12] = f32::NAN;
        depth[0] = f32::NAN;
        let filtered = bilateral_filter(&DepthImage::new(5, 5, depth).unwrap(), 2, 1.5, 0.01);
        assert!(filtered.depth_m[12].is_nan() && filtered.depth_m[0].is_nan());
        assert!(filtered.depth_m.iter().filter(|z| z.is_finite()).all(|&z| (z - 2.0).abs() < 1e-6));
    }

    #[test]
    fn median_picks_measured_depths_and_never_blends() {
        let depth = DepthImage::new(4, 2, vec![1.0, 2.0, f32::NAN, f32::NAN, 1.0, 2.0, 3.0, f32::NAN]).unwrap();
        let down = median_downsample_2x2(&depth);
        assert_eq!((down.width, down.height), (2, 1));
        // Block {1,2,1,2}: lower middle = 1 (not the blend 1.5). Block {NaN,NaN,3,NaN}: 3.
        assert_eq!(down.depth_m, vec![1.0, 3.0]);
        let empty = median_downsample_2x2(&DepthImage::new(2, 2, vec![f32::NAN; 4]).unwrap());
        assert!(empty.depth_m[0].is_nan());
        // Salt noise: one outlier in a block of 4 is removed.
        let salt = median_downsample_2x2(&DepthImage::new(2, 2, vec![1.0, 1.01, 9.0, 1.02]).unwrap());
        assert_eq!(salt.depth_m[0], 1.01);
    }

    #[test]
    fn median_at_a_discontinuity_returns_only_input_values() {
        let mut rng = rand::rngs::StdRng::seed_from_u64(11);
        let values: Vec<f32> = (0..16 * 16).map(|_| if rng.random_bool(0.5) { 1.0 } else { 3.0 }).collect();
        let down = median_downsample_2x2(&DepthImage::new(16, 16, values).unwrap());
        assert!(down.depth_m.iter().all(|&z| z == 1.0 || z == 3.0));
    }

    #[test]
    fn background_and_pipeline_on_a_real_frame() {
        let dataset = Dataset::open(&test_data_dir().join("open3d_rgbd")).unwrap();
        let depth = dataset.load_depth(0).unwrap();
        let config = PreprocessConfig { z_max_m: 2.0, ..Default::default() };
        let out = preprocess(&depth, &dataset.intrinsics, &config).unwrap();
        assert_eq!((out.auxiliary.width, out.auxiliary.height), (320, 240));
        assert_eq!(out.auxiliary_intrinsics.width, 320);
        assert!(out.filtered.depth_m.iter().filter(|z| z.is_finite()).all(|&z| (0.3..=2.0).contains(&z)));
        // Filtering never creates data where there was none.
        let kept = out.filtered.valid_count();
        let foreground = remove_background(&depth, 0.3, 2.0).valid_count();
        assert_eq!(kept, foreground);
        assert!(kept > 50_000);
        let bad = PreprocessConfig { z_max_m: 0.1, ..Default::default() };
        assert!(matches!(preprocess(&depth, &dataset.intrinsics, &bad), Err(PreprocessError::Config(_))));
    }
}

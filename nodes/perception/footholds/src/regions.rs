//! Region proposal and perspective correction (CNN III-A).
//!
//! An m × n grid of vertices is laid over the depth image (CNN: 14 × 19 with 32 px spacing on a
//! 640 × 480 image; the spacing scales with the image). At each vertex p_i the depth d_i is the mean
//! of the valid pixels of a 50 × 50 window (scaled alike) centred on it, and a square region of side
//! `s_i = round(s_far · d_far / d_i)` is cut around p_i and resampled to 60 × 60.
//!
//! What `s_far · d_far` means: s_far is the region's side in pixels at the farthest usable depth
//! d_far, so `s_i · d_i` is constant and every region spans the same metric width
//! `W = s_far · d_far / f` (f the focal length in pixels). The paper's numbers (s_far = 10 px,
//! d_far = 8 m, the Astra's far limit, f ≈ 570 px) give W ≈ 0.14 m. We keep that metric width,
//! [`RegionConfig::region_width_m`] = 0.14 m, and compute `s_i = round(f · W / d_i)`; for our
//! 640 × 480 cameras (f ≈ 525 px) that is s_far = 10 px at d_far = 7.35 m, 147 px at 0.5 m. A foot of
//! the RPBP (radius 0.05 m) fits in the central 80 % of a region.
//!
//! Each resampled cell is the mean of the valid pixels under it (integral images, so the cost does
//! not grow with s_i). Depth is divided by the absolute range [`RegionConfig::depth_range_m`], the
//! region's mean is subtracted, and the result is multiplied by a constant gain (so that a 5 cm rock
//! gives values ≈ 0.25 rather than 0.025; a constant scale the first convolution would otherwise
//! have to learn). Cells without any valid pixel are 0 (the mean). Optionally two more channels
//! carry the surface normal's x and y in the camera frame, from central differences of the
//! resampled depth at the region's metric cell spacing.

use patchwalk_fusion::camera::{DepthImage, Intrinsics};

use crate::error::FootholdError;

/// Parameters of the region proposal.
#[derive(Debug, Clone, PartialEq, serde::Serialize, serde::Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct RegionConfig {
    /// m: grid rows (CNN: 14).
    pub rows: usize,
    /// n: grid columns (CNN: 19).
    pub cols: usize,
    /// Side of the depth-averaging window at 640 px image width (CNN: 50 px), scaled with the width.
    pub window_px: usize,
    /// W = s_far · d_far / f: the metric width every region spans (m).
    pub region_width_m: f64,
    /// Side of the resampled region (CNN: 60 px).
    pub out_px: usize,
    /// Vertices whose window depth lies outside [min_depth_m, max_depth_m] give no region.
    pub min_depth_m: f64,
    pub max_depth_m: f64,
    /// The absolute depth range the depth channel is divided by (m).
    pub depth_range_m: f64,
    /// Constant gain after the mean subtraction.
    pub depth_gain: f32,
    /// Regions with fewer valid resampled cells than this fraction are not proposed.
    pub min_valid_fraction: f64,
    /// Add the two surface-normal channels (nx, ny in the camera frame).
    pub normals: bool,
}

impl Default for RegionConfig {
    fn default() -> Self {
        Self {
            rows: 14,
            cols: 19,
            window_px: 50,
            region_width_m: 0.14,
            out_px: 60,
            min_depth_m: 0.2,
            max_depth_m: 3.0,
            depth_range_m: 2.0,
            depth_gain: 10.0,
            min_valid_fraction: 0.6,
            normals: false,
        }
    }
}

impl RegionConfig {
    /// Input channels of the network: depth, plus nx, ny with normals.
    pub fn channels(&self) -> usize {
        if self.normals {
            3
        } else {
            1
        }
    }

    /// Values per region input (`channels · out_px²`).
    pub fn input_len(&self) -> usize {
        self.channels() * self.out_px * self.out_px
    }

    /// Checks the ranges.
    pub fn validate(&self) -> Result<(), FootholdError> {
        let ok = self.rows > 0
            && self.cols > 0
            && self.window_px > 0
            && self.out_px >= 8
            && self.region_width_m.is_finite()
            && self.region_width_m > 0.0
            && self.min_depth_m.is_finite()
            && self.min_depth_m > 0.0
            && self.max_depth_m > self.min_depth_m
            && self.depth_range_m.is_finite()
            && self.depth_range_m > 0.0
            && self.depth_gain.is_finite()
            && (0.0..=1.0).contains(&self.min_valid_fraction);
        if ok {
            Ok(())
        } else {
            Err(FootholdError::Config(format!("region parameters out of range: {self:?}")))
        }
    }

    /// Pixel positions (u, v) of the grid vertices for an image of `width × height`: evenly spaced
    /// with the spacing as margin, `u_j = (j + 1) · width / (n + 1)` (32 px on 640 × 480 with 19 × 14).
    pub fn vertices(&self, width: usize, height: usize) -> Vec<(usize, usize, f64, f64)> {
        let mut out = Vec::with_capacity(self.rows * self.cols);
        for row in 0..self.rows {
            for col in 0..self.cols {
                let u = (col + 1) as f64 * width as f64 / (self.cols + 1) as f64;
                let v = (row + 1) as f64 * height as f64 / (self.rows + 1) as f64;
                out.push((row, col, u, v));
            }
        }
        out
    }

    /// s_i = round(f · W / d_i) (pixels), at least 2.
    pub fn region_size_px(&self, focal_px: f64, depth_m: f64) -> usize {
        ((focal_px * self.region_width_m / depth_m).round() as usize).max(2)
    }

    /// The averaging window side for an image of `width` pixels (50 at 640).
    pub fn window_for_width(&self, width: usize) -> usize {
        ((self.window_px as f64 * width as f64 / 640.0).round() as usize).max(1)
    }
}

/// One proposed region: where it is in the image and its network input.
#[derive(Debug, Clone, PartialEq)]
pub struct Region {
    pub row: usize,
    pub col: usize,
    /// Centre pixel p_i.
    pub u: f64,
    pub v: f64,
    /// d_i: mean valid depth of the window (m).
    pub depth_m: f64,
    /// s_i: side of the square region in image pixels.
    pub size_px: usize,
}

impl Region {
    /// Top-left corner (u, v) of the region in the image.
    pub fn origin(&self) -> (f64, f64) {
        (self.u - self.size_px as f64 / 2.0, self.v - self.size_px as f64 / 2.0)
    }

    /// Image pixel of region coordinates (x, y) ∈ [0, 1]².
    pub fn to_image(&self, x: f64, y: f64) -> (f64, f64) {
        let (u0, v0) = self.origin();
        (u0 + x * self.size_px as f64, v0 + y * self.size_px as f64)
    }

    /// Region coordinates (x, y) of an image pixel (outside [0, 1]² when the pixel is outside).
    pub fn to_region(&self, u: f64, v: f64) -> (f64, f64) {
        let (u0, v0) = self.origin();
        ((u - u0) / self.size_px as f64, (v - v0) / self.size_px as f64)
    }

    /// Whether region coordinates lie in the central `fraction` of the region (CNN III-C: 80 %).
    pub fn in_centre(x: f64, y: f64, fraction: f64) -> bool {
        let half = fraction / 2.0;
        (x - 0.5).abs() <= half && (y - 0.5).abs() <= half
    }
}

/// Integral images of depth and of the valid-pixel count, `(w + 1) × (h + 1)`.
pub struct Integral {
    width: usize,
    height: usize,
    sum: Vec<f64>,
    count: Vec<u32>,
}

impl Integral {
    /// Builds both integral images of a depth image.
    pub fn new(depth: &DepthImage) -> Self {
        let (w, h) = (depth.width, depth.height);
        let stride = w + 1;
        let mut sum = vec![0.0; stride * (h + 1)];
        let mut count = vec![0u32; stride * (h + 1)];
        for v in 0..h {
            let (mut row_sum, mut row_count) = (0.0, 0u32);
            for u in 0..w {
                let d = depth.depth_m[v * w + u];
                if d.is_finite() {
                    row_sum += f64::from(d);
                    row_count += 1;
                }
                sum[(v + 1) * stride + u + 1] = sum[v * stride + u + 1] + row_sum;
                count[(v + 1) * stride + u + 1] = count[v * stride + u + 1] + row_count;
            }
        }
        Self { width: w, height: h, sum, count }
    }

    /// Sum and count of the valid pixels in `[u0, u1) × [v0, v1)` (clamped to the image).
    pub fn box_sum(&self, u0: i64, v0: i64, u1: i64, v1: i64) -> (f64, u32) {
        let clamp_u = |u: i64| u.clamp(0, self.width as i64) as usize;
        let clamp_v = |v: i64| v.clamp(0, self.height as i64) as usize;
        let (a, b, c, d) = (clamp_u(u0), clamp_v(v0), clamp_u(u1), clamp_v(v1));
        if c <= a || d <= b {
            return (0.0, 0);
        }
        let s = self.width + 1;
        let sum = self.sum[d * s + c] - self.sum[b * s + c] - self.sum[d * s + a] + self.sum[b * s + a];
        let count = self.count[d * s + c] + self.count[b * s + a] - self.count[b * s + c] - self.count[d * s + a];
        (sum, count)
    }

    /// Mean valid depth of the box, `None` without valid pixels.
    pub fn box_mean(&self, u0: i64, v0: i64, u1: i64, v1: i64) -> Option<f64> {
        let (sum, count) = self.box_sum(u0, v0, u1, v1);
        (count > 0).then(|| sum / f64::from(count))
    }
}

/// Checks a depth image against the intrinsics and the region grid.
pub fn check_image(depth: &DepthImage, intrinsics: &Intrinsics, config: &RegionConfig) -> Result<(), FootholdError> {
    let (width, height) = (depth.width, depth.height);
    let image_error = |reason: String| FootholdError::Image { width, height, reason };
    if depth.depth_m.len() != width * height {
        return Err(image_error(format!("{} depth values for {} pixels", depth.depth_m.len(), width * height)));
    }
    if (intrinsics.width, intrinsics.height) != (width, height) {
        return Err(image_error(format!("the intrinsics are for {}x{}", intrinsics.width, intrinsics.height)));
    }
    let window = config.window_for_width(width);
    if width < window.max(config.cols + 1) || height < window.max(config.rows + 1) {
        return Err(image_error(format!("too small for a {}x{} region grid with {window} px depth windows", config.rows, config.cols)));
    }
    if depth.depth_m.iter().any(|d| d.is_infinite() || (d.is_finite() && *d <= 0.0)) {
        return Err(image_error("has infinite, zero or negative depth values (invalid pixels must be NaN)".into()));
    }
    if depth.valid_count() == 0 {
        return Err(FootholdError::NoValidDepth { width, height });
    }
    Ok(())
}

/// Proposes the regions of a depth image and writes their inputs, one `config.input_len()` block per
/// region in the returned order, into `inputs` (cleared first). NaN marks invalid pixels.
pub fn propose(
    depth: &DepthImage,
    intrinsics: &Intrinsics,
    config: &RegionConfig,
    inputs: &mut Vec<f32>,
) -> Result<Vec<Region>, FootholdError> {
    config.validate()?;
    check_image(depth, intrinsics, config)?;
    let integral = Integral::new(depth);
    let window = config.window_for_width(depth.width) as i64;
    let focal = (intrinsics.fx + intrinsics.fy) / 2.0;
    let mut candidates = Vec::new();
    for (row, col, u, v) in config.vertices(depth.width, depth.height) {
        let (u0, v0) = (u.round() as i64 - window / 2, v.round() as i64 - window / 2);
        let Some(depth_m) = integral.box_mean(u0, v0, u0 + window, v0 + window) else {
            continue;
        };
        if !(config.min_depth_m..=config.max_depth_m).contains(&depth_m) {
            continue;
        }
        candidates.push(Region { row, col, u, v, depth_m, size_px: config.region_size_px(focal, depth_m) });
    }
    let len = config.input_len();
    // Every candidate's input in place, in parallel; then the regions with too few valid cells are
    // squeezed out.
    inputs.clear();
    inputs.resize(candidates.len() * len, 0.0);
    let valid: Vec<bool> = {
        use rayon::prelude::*;
        inputs
            .par_chunks_mut(len)
            .zip(&candidates)
            .map_init(Vec::new, |metres, (out, region)| region_input(&integral, region, focal, config, out, metres))
            .collect()
    };
    let mut regions = Vec::with_capacity(candidates.len());
    for (i, (region, valid)) in candidates.into_iter().zip(valid).enumerate() {
        if valid {
            let to = regions.len() * len;
            if to != i * len {
                inputs.copy_within(i * len..(i + 1) * len, to);
            }
            regions.push(region);
        }
    }
    inputs.truncate(regions.len() * len);
    Ok(regions)
}

/// The pixel span `[start, end)` of each of the `n` cells along one axis of a region starting at
/// `origin` with cells `step` pixels wide (at least one pixel), clamped to `[0, limit]`.
fn cell_spans(origin: f64, step: f64, n: usize, limit: usize) -> impl Iterator<Item = (usize, usize)> {
    let clamp = move |p: i64| p.clamp(0, limit as i64) as usize;
    (0..n).map(move |a| {
        let p0 = (origin + a as f64 * step).floor() as i64;
        let p1 = ((origin + (a + 1) as f64 * step).floor() as i64).max(p0 + 1);
        (clamp(p0), clamp(p1))
    })
}

/// Writes the resampled, normalised input of one region into `out` (`config.input_len()` values);
/// false when too few cells are valid. `metres` is a work buffer.
fn region_input(integral: &Integral, region: &Region, focal: f64, config: &RegionConfig, out: &mut [f32], metres: &mut Vec<f64>) -> bool {
    let n = config.out_px;
    let s = region.size_px as f64;
    let (u0, v0) = region.origin();
    let step = s / n as f64;
    let columns: Vec<(usize, usize)> = cell_spans(u0, step, n, integral.width).collect();
    metres.clear();
    metres.resize(n * n, f64::NAN);
    let mut valid = 0usize;
    let stride = integral.width + 1;
    for ((y0, y1), row) in cell_spans(v0, step, n, integral.height).zip(metres.chunks_exact_mut(n)) {
        if y1 <= y0 {
            continue;
        }
        let (top, bottom) = (y0 * stride, y1 * stride);
        for (&(x0, x1), cell) in columns.iter().zip(row) {
            if x1 <= x0 {
                continue;
            }
            // The box's valid count and depth sum from the integral images (Integral::box_sum).
            let count = integral.count[bottom + x1] + integral.count[top + x0] - integral.count[top + x1] - integral.count[bottom + x0];
            if count > 0 {
                let sum = integral.sum[bottom + x1] - integral.sum[top + x1] - integral.sum[bottom + x0] + integral.sum[top + x0];
                *cell = sum / f64::from(count);
                valid += 1;
            }
        }
    }
    if (valid as f64) < config.min_valid_fraction * (n * n) as f64 || valid == 0 {
        return false;
    }
    let mean = metres.iter().filter(|d| d.is_finite()).sum::<f64>() / valid as f64;
    out.fill(0.0);
    for (o, d) in out.iter_mut().zip(metres.iter()) {
        if d.is_finite() {
            *o = (((d - mean) / config.depth_range_m) * f64::from(config.depth_gain)) as f32;
        }
    }
    if config.normals {
        // Metric spacing of the resampled cells: the region spans s·d/f metres.
        let h = s * region.depth_m / focal / n as f64;
        let at = |a: usize, b: usize| metres[b * n + a];
        for b in 0..n {
            for a in 0..n {
                let (al, ar) = (a.saturating_sub(1), (a + 1).min(n - 1));
                let (bu, bd) = (b.saturating_sub(1), (b + 1).min(n - 1));
                let (dl, dr, du, dd) = (at(al, b), at(ar, b), at(a, bu), at(a, bd));
                if !(dl.is_finite() && dr.is_finite() && du.is_finite() && dd.is_finite()) {
                    continue;
                }
                let gx = (dr - dl) / (h * (ar - al).max(1) as f64);
                let gy = (dd - du) / (h * (bd - bu).max(1) as f64);
                let norm = (1.0 + gx * gx + gy * gy).sqrt();
                out[n * n + b * n + a] = (-gx / norm) as f32;
                out[2 * n * n + b * n + a] = (-gy / norm) as f32;
            }
        }
    }
    true
}

/// Mirrors one region input horizontally (CNN III-C augmentation); the normal's x flips sign.
pub fn mirror_input(input: &mut [f32], channels: usize, side: usize) {
    for c in 0..channels {
        let plane = &mut input[c * side * side..(c + 1) * side * side];
        for row in plane.chunks_mut(side) {
            row.reverse();
        }
        if c == 1 {
            plane.iter_mut().for_each(|v| *v = -*v);
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn flat(width: usize, height: usize, d: f32) -> (DepthImage, Intrinsics) {
        let depth = DepthImage::new(width, height, vec![d; width * height]).unwrap();
        let k = Intrinsics::new(
            width,
            height,
            525.0 * width as f64 / 640.0,
            525.0 * width as f64 / 640.0,
            width as f64 / 2.0,
            height as f64 / 2.0,
        )
        .unwrap();
        (depth, k)
    }

    #[test]
    fn grid_is_the_papers_14_by_19_with_32_px_spacing() {
        let config = RegionConfig::default();
        let v = config.vertices(640, 480);
        assert_eq!(v.len(), 266);
        assert_eq!((v[0].2, v[0].3), (32.0, 32.0));
        assert_eq!((v[1].2 - v[0].2, v[19].3 - v[0].3), (32.0, 32.0));
        assert_eq!((v[265].2, v[265].3), (608.0, 448.0));
        // Scaled image: spacing halves with the width.
        let half = config.vertices(320, 240);
        assert_eq!((half[1].2 - half[0].2, half[0].3), (16.0, 16.0));
        assert_eq!(config.window_for_width(640), 50);
        assert_eq!(config.window_for_width(320), 25);
    }

    #[test]
    fn region_sizes_follow_s_far_d_far_over_d() {
        let config = RegionConfig::default();
        // f·W = 525 · 0.14 = 73.5 px·m: s = round(73.5 / d).
        assert_eq!(config.region_size_px(525.0, 0.5), 147);
        assert_eq!(config.region_size_px(525.0, 1.0), 74); // 73.5 rounds half away from zero
        assert_eq!(config.region_size_px(525.0, 7.35), 10); // the paper's s_far = 10 px at d_far
        assert_eq!(config.region_size_px(570.0, 8.0), 10); // the paper's Astra numbers
        let (depth, k) = flat(640, 480, 0.7);
        let mut inputs = Vec::new();
        let regions = propose(&depth, &k, &config, &mut inputs).unwrap();
        assert_eq!(regions.len(), 266);
        assert_eq!(inputs.len(), 266 * 3600);
        assert!(regions.iter().all(|r| r.size_px == 105 && (r.depth_m - 0.7).abs() < 1e-6));
        // A flat plane at constant depth normalises to zeros.
        assert!(inputs.iter().all(|v| v.abs() < 1e-5));
    }

    #[test]
    fn a_step_is_resampled_and_normalised() {
        let (mut depth, k) = flat(640, 480, 1.0);
        // Left half of the image 0.1 m closer.
        for v in 0..480 {
            for u in 0..320 {
                depth.depth_m[v * 640 + u] = 0.9;
            }
        }
        let config = RegionConfig::default();
        let mut inputs = Vec::new();
        let regions = propose(&depth, &k, &config, &mut inputs).unwrap();
        // The vertex at u = 320 (col 9) straddles the step: mean 0.95 m, s = round(73.5/0.95) = 77.
        let (i, r) = regions.iter().enumerate().find(|(_, r)| r.col == 9 && r.row == 7).unwrap();
        assert!((r.depth_m - 0.95).abs() < 1e-6, "{}", r.depth_m);
        assert_eq!(r.size_px, 77);
        let input = &inputs[i * 3600..(i + 1) * 3600];
        // Left cells are 0.05 m below the mean: (-0.05 / 2.0) · 10 = -0.25; right +0.25.
        let (left, right) = (input[30 * 60 + 2], input[30 * 60 + 57]);
        assert!((left + 0.25).abs() < 0.02 && (right - 0.25).abs() < 0.02, "{left} {right}");
    }

    /// Each cell is the mean of the valid pixels under it (Integral::box_mean), normalised, for
    /// regions larger and smaller than 60 px, with holes and partly outside the image.
    #[test]
    fn cells_are_the_means_of_the_valid_pixels_under_them() {
        let (mut depth, k) = flat(640, 480, 1.0);
        for v in 0..480 {
            for u in 0..640 {
                depth.depth_m[v * 640 + u] =
                    if (u * 7 + v * 13) % 11 == 0 { f32::NAN } else { 0.5 + 0.002 * u as f32 + 0.1 * (v as f32 * 0.05).sin() };
            }
        }
        let config = RegionConfig::default();
        let mut inputs = Vec::new();
        let regions = propose(&depth, &k, &config, &mut inputs).unwrap();
        let n = config.out_px;
        assert!(regions.iter().any(|r| r.size_px < n) && regions.iter().any(|r| r.size_px > n));
        assert!(regions.len() > 200 && inputs.len() == regions.len() * config.input_len());
        let integral = Integral::new(&depth);
        let mut outside = 0;
        for (region, input) in regions.iter().zip(inputs.chunks_exact(config.input_len())) {
            let (u0, v0) = region.origin();
            let step = region.size_px as f64 / n as f64;
            let span = |origin: f64, a: usize| {
                let p0 = (origin + a as f64 * step).floor() as i64;
                (p0, ((origin + (a + 1) as f64 * step).floor() as i64).max(p0 + 1))
            };
            let means: Vec<Option<f64>> = (0..n * n)
                .map(|i| {
                    let ((x0, x1), (y0, y1)) = (span(u0, i % n), span(v0, i / n));
                    integral.box_mean(x0, y0, x1, y1)
                })
                .collect();
            let valid: Vec<f64> = means.iter().flatten().copied().collect();
            outside += usize::from(valid.len() < n * n);
            let mean = valid.iter().sum::<f64>() / valid.len() as f64;
            for (value, cell) in input.iter().zip(&means) {
                assert_eq!(*value, cell.map_or(0.0, |d| (((d - mean) / 2.0) * 10.0) as f32));
            }
        }
        assert!(outside > 0);
    }

    #[test]
    fn normal_channels_of_a_tilted_plane() {
        // Depth growing along u: dz/du per pixel = 0.001 m at 1 m depth, f = 525 → dz/dx = 0.525.
        let (mut depth, k) = flat(640, 480, 1.0);
        for v in 0..480 {
            for u in 0..640 {
                depth.depth_m[v * 640 + u] = 1.0 + 0.001 * (u as f32 - 320.0);
            }
        }
        let config = RegionConfig { normals: true, ..RegionConfig::default() };
        let mut inputs = Vec::new();
        let regions = propose(&depth, &k, &config, &mut inputs).unwrap();
        let (i, r) = regions.iter().enumerate().find(|(_, r)| r.col == 9 && r.row == 7).unwrap();
        let input = &inputs[i * 3 * 3600..(i + 1) * 3 * 3600];
        let gx = 0.001 * 525.0 / r.depth_m;
        let expected = -gx / (1.0 + gx * gx).sqrt();
        let nx = f64::from(input[3600 + 30 * 60 + 30]);
        let ny = f64::from(input[2 * 3600 + 30 * 60 + 30]);
        assert!((nx - expected).abs() < 0.03 && ny.abs() < 1e-3, "{nx} vs {expected}, {ny}");
    }

    #[test]
    fn bad_images_are_refused_with_a_reason() {
        let config = RegionConfig::default();
        let (depth, k) = flat(16, 12, 1.0);
        let err = propose(&depth, &k, &config, &mut Vec::new()).unwrap_err();
        assert!(err.to_string().contains("too small"), "{err}");
        let nan = DepthImage { width: 640, height: 480, depth_m: vec![f32::NAN; 640 * 480] };
        let (_, k) = flat(640, 480, 1.0);
        let err = propose(&nan, &k, &config, &mut Vec::new()).unwrap_err();
        assert!(matches!(err, FootholdError::NoValidDepth { .. }), "{err}");
        let (depth, _) = flat(640, 480, 1.0);
        let (_, other) = flat(320, 240, 1.0);
        let err = propose(&depth, &other, &config, &mut Vec::new()).unwrap_err();
        assert!(err.to_string().contains("intrinsics are for 320x240"), "{err}");
        let inf = DepthImage { width: 640, height: 480, depth_m: vec![f32::INFINITY; 640 * 480] };
        assert!(propose(&inf, &k, &config, &mut Vec::new()).unwrap_err().to_string().contains("infinite"));
    }

    #[test]
    fn mirroring_twice_is_the_identity_and_flips_nx() {
        let mut input: Vec<f32> = (0..3 * 16).map(|i| i as f32).collect();
        let original = input.clone();
        mirror_input(&mut input, 3, 4);
        assert_eq!(input[0], 3.0);
        assert_eq!(input[16], -19.0);
        mirror_input(&mut input, 3, 4);
        assert_eq!(input, original);
    }
}

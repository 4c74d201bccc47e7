//! Stage ii, step 6 (J 4.2.1): the hiking saliency filter on the auxiliary image D.
//!
//! - 6.1 DtFP: fixation point `f = l_d·ĝ + l_f·(x̂ × ĝ)/|x̂ × ĝ|` in the camera frame,
//! - 6.2 H ← points of D within the R-ball around f,
//! - 6.3 normals N (window 2rf/Z) and N_s (half window) by integral images (J \[76\], the
//!   "average 3D gradient" variant: smoothed horizontal and vertical 3D gradients from box means),
//! - 6.4 DoN: drop i when `N(i)ᵀN_s(i) < cos φ_d`,
//! - 6.5 DoNG: drop i when `−N(i)ᵀĝ < cos φ_g`;
//!
//! and, before the normals, drop i when a depth discontinuity lies inside its foot window
//! ([`crate::depth_edges`]): the foot disc would span two surfaces and the box normals mix them;
//! when the window reaches past the image border (the foothold is not seen whole); and after them
//! when the window's points spread off their plane ([`crate::window_flatness`]: a step or a bump).
//!
//! The output is a per-pixel label image of D (so the cloud stays organized), the coarse normals,
//! and the sampled surface area S of the salient set (used by the ν termination of J eq 19).

use nalgebra::{Unit, Vector3};
use rayon::prelude::*;

use patchwalk_fusion::camera::{DepthImage, Intrinsics};

use crate::depth_edges::EdgeDistance;
use crate::window_flatness::{summed_area_table, WindowMoments};

/// Configuration of step 6. Defaults from J 6.1.2 / Table 3 ("auto" = human mean + 3σ).
#[derive(Debug, Clone, PartialEq, serde::Serialize, serde::Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct SaliencyConfig {
    /// Step 6.1: l_d, distance of the fixation point below the camera (m). Not given numerically
    /// in J; 1.2 m is a chest-height hand-held rig like J's human recordings.
    pub fixation_down_m: f64,
    /// Step 6.1: l_f, horizontal distance of the fixation point ahead of the camera (m): "about two
    /// steps ahead" (J 4.2.1, \[75\]); 2 × 0.75 m human steps.
    pub fixation_forward_m: f64,
    /// Step 6.2: R, radius of the region of interest around f (m). J 6.1.2: "no patches fitted
    /// further than 0.7 m from the fixation point". Non-finite (`.inf` in YAML) disables DtFP.
    pub fixation_radius_m: f64,
    /// Step 6.4: φ_d, DoN threshold (degrees). J Table 3 "auto" max DoN = 15.31° (= 4.95 + 3·3.45).
    pub don_max_deg: f64,
    /// Step 6.5: φ_g, DoNG threshold (degrees). J Table 3 "auto" max DoNG = 34.96° (= 12.34 + 3·7.54).
    pub dong_max_deg: f64,
    /// Smallest half window (pixels) for the fine normals; below it the box means get noisy.
    pub min_half_window_px: usize,
    /// Minimum fraction of valid pixels in each half-window box for a normal to be computed.
    pub min_support_fraction: f64,
    /// Relative depth jump between neighbouring pixels of D that marks a depth discontinuity
    /// ([`crate::depth_edges`]; 0.04: 4 cm at 1 m, above a Kinect-class camera's quantisation step
    /// there and below the side of a 5 cm step seen from 1 m).
    pub depth_edge_jump: f64,
    /// Share of the foot window (half size `r·f/Z`) that must be free of depth discontinuities and
    /// inside the image, so that the foothold is seen whole (1: the whole window; 0 turns both
    /// checks off, J's step 6 as written).
    pub depth_edge_clearance: f64,
    /// Largest RMS distance (m) of the foot window's points from the plane through their mean
    /// along the coarse normal N ([`crate::window_flatness`]): a window spread further holds a step
    /// or a bump a foot disc cannot stand on. The window is a square of half side r (on a surface
    /// facing the camera): N tilts towards a step through its middle, so that seen from 1 m steps
    /// of 2 cm and more are caught (1.5 cm not); a paraboloid of curvature κ centred in it spreads
    /// `κ r² √(2/45)` (5 mm at κ = 9.5 m⁻¹ and r = 5 cm, below J's κ_max = 19.7 m⁻¹, which is what
    /// `window_quadric_rms_max_m` is for). Infinite turns the check off, J's step 6 as written.
    pub window_rms_max_m: f64,
    /// A window spread further than `window_rms_max_m` is kept when the quadric that fits it best
    /// leaves no more than this RMS (m) and curves no more than `window_curvature_max`: a smooth
    /// bump (a rock's top), which the plane test cannot tell from a step. A step of height h
    /// through the window's middle leaves h/4 (5 mm for the 2 cm steps the plane test catches), so
    /// steps stay out. 0 turns the quadric off (the plane test alone).
    pub window_quadric_rms_max_m: f64,
    /// Largest principal curvature (m⁻¹) of a window's quadric for `window_quadric_rms_max_m` to
    /// keep it. J 3.3.3's κ_max = 19.7; the mapper uses the lower of this and the validator's
    /// `curvature_max`.
    pub window_curvature_max: f64,
}

impl Default for SaliencyConfig {
    fn default() -> Self {
        Self {
            fixation_down_m: 1.2,
            fixation_forward_m: 1.5,
            fixation_radius_m: 0.7,
            don_max_deg: 15.3,
            dong_max_deg: 35.0,
            min_half_window_px: 2,
            min_support_fraction: 0.25,
            depth_edge_jump: 0.04,
            depth_edge_clearance: 1.0,
            window_rms_max_m: 0.005,
            window_quadric_rms_max_m: 0.002,
            window_curvature_max: 19.7,
        }
    }
}

/// Why a pixel of D is or is not in the salient set H.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, serde::Serialize)]
#[repr(u8)]
pub enum SaliencyLabel {
    /// No depth.
    Invalid = 0,
    /// Outside the R-ball around the fixation point (step 6.2).
    Distant = 1,
    /// Too few valid neighbours for a normal (window at a hole or the image border).
    NoNormal = 2,
    /// Dropped by DoN (step 6.4): irregular surface.
    Irregular = 3,
    /// Dropped by DoNG (step 6.5): too steep.
    Steep = 4,
    /// In H.
    Salient = 5,
    /// A depth discontinuity inside the foot window ([`crate::depth_edges`]).
    DepthEdge = 6,
    /// The foot window reaches past the image border: the foothold cannot be seen whole.
    ImageBorder = 7,
    /// The foot window's points spread too far off their plane (`window_rms_max_m`): a step or a
    /// bump under the foot.
    Uneven = 8,
}

/// Result of step 6 on D.
#[derive(Debug, Clone)]
pub struct Saliency {
    pub width: usize,
    pub height: usize,
    /// One label per pixel of D, row-major.
    pub labels: Vec<SaliencyLabel>,
    /// Coarse normals N (unit, towards the camera) per pixel of D; NaN where not computed.
    pub normals_in_camera: Vec<Vector3<f32>>,
    /// Fixation point f in the camera frame (step 6.1).
    pub fixation_in_camera: Vector3<f64>,
    /// Sampled surface area S of H (m²): Σ z²/(f_x f_y) / |n·ray| over the salient pixels.
    pub salient_area_m2: f64,
    /// Set when the DtFP ball around the fixation point held no salient point and the labels are
    /// those of the DoN/DoNG filters alone (no region of interest): why, in words.
    pub dtfp_fallback: Option<String>,
}

impl Saliency {
    /// Number of pixels with `label`.
    pub fn count(&self, label: SaliencyLabel) -> usize {
        self.labels.iter().filter(|&&l| l == label).count()
    }

    /// Pixel indices of H (row-major into D).
    pub fn salient_indices(&self) -> impl Iterator<Item = usize> + '_ {
        self.labels.iter().enumerate().filter(|(_, &l)| l == SaliencyLabel::Salient).map(|(i, _)| i)
    }
}

/// Step 6.1: fixation point `f = l_d ĝ + l_f (x̂ × ĝ)/|x̂ × ĝ|` in the camera frame.
pub fn fixation_point(gravity_in_camera: &Unit<Vector3<f64>>, down_m: f64, forward_m: f64) -> Vector3<f64> {
    let forward = Vector3::x().cross(gravity_in_camera);
    let forward = if forward.norm() > 1e-9 { forward.normalize() } else { Vector3::z() };
    gravity_in_camera.into_inner() * down_m + forward * forward_m
}

/// Integral image (summed-area table) of x, y, z and the valid count of an organized cloud.
#[derive(Debug, Clone, Default)]
pub struct IntegralCloud {
    width: usize,
    height: usize,
    /// `(width + 1) × (height + 1)` prefix sums [Σx, Σy, Σz, n].
    sums: Vec<[f64; 4]>,
}

impl IntegralCloud {
    /// Builds the sums from D and its intrinsics (points back-projected on the fly).
    pub fn new(depth: &DepthImage, intrinsics: &Intrinsics) -> Self {
        let mut integral = Self::default();
        integral.rebuild(depth, intrinsics);
        integral
    }

    /// [`IntegralCloud::new`] of another frame, in the memory of this one's table.
    pub fn rebuild(&mut self, depth: &DepthImage, intrinsics: &Intrinsics) {
        (self.width, self.height) = (depth.width, depth.height);
        summed_area_table(depth, intrinsics, |p| [p.x, p.y, p.z, 1.0], &mut self.sums);
    }

    /// The four half-window box sums of [`IntegralCloud::normal`] at `(u, v)`: `[right, left,
    /// below, above]` (boxes clipped to the image), from 12 table reads (the boxes share corners)
    /// instead of 16.
    #[inline]
    fn half_window_sums(&self, u: usize, v: usize, half: usize) -> [[f64; 4]; 4] {
        let (u, v, h) = (u as isize, v as isize, half as isize);
        let [c0, c1, c2, c3] = [u - h, u, u + 1, u + h + 1].map(|x| x.clamp(0, self.width as isize) as usize);
        let [r0, r1, r2, r3] = [v - h, v, v + 1, v + h + 1].map(|x| x.clamp(0, self.height as isize) as usize);
        let stride = self.width + 1;
        let row = |r: usize| self.sums.get(r * stride..(r + 1) * stride).unwrap_or(&[]);
        let at = |row: &[[f64; 4]], c: usize| row.get(c).copied().unwrap_or([0.0; 4]);
        let (top, upper, lower, bottom) = (row(r0), row(r1), row(r2), row(r3));
        let (t0, t1, t2, t3) = (at(top, c0), at(top, c1), at(top, c2), at(top, c3));
        let (b0, b1, b2, b3) = (at(bottom, c0), at(bottom, c1), at(bottom, c2), at(bottom, c3));
        let (m0, m3, l0, l3) = (at(upper, c0), at(upper, c3), at(lower, c0), at(lower, c3));
        // Box sum a − b − c + d from the summed-area table, a = (u1, v1), b = (u0, v1), c = (u1, v0),
        // d = (u0, v0).
        let sum = |a: [f64; 4], b: [f64; 4], c: [f64; 4], d: [f64; 4]| std::array::from_fn(|i| a[i] - b[i] - c[i] + d[i]);
        [sum(b3, b2, t3, t2), sum(b1, b0, t1, t0), sum(b3, b0, l3, l0), sum(m3, m0, t3, t0)]
    }

    /// Normal at pixel `(u, v)` from half window `half` (J \[76\], average 3D gradient): the
    /// horizontal gradient is mean(right box) − mean(left box), the vertical one mean(lower box) −
    /// mean(upper box), each box `half × (2·half + 1)` pixels; `n = ∂h × ∂v` turned towards the camera.
    pub fn normal(&self, u: usize, v: usize, half: usize, point: &Vector3<f64>, min_support: f64) -> Option<Vector3<f64>> {
        let h = half as isize;
        let min_count = (min_support * (h * (2 * h + 1)) as f64).max(1.0);
        let [right, left, below, above] = self.half_window_sums(u, v, half);
        let mean = |s: [f64; 4]| (s[3] >= min_count).then(|| Vector3::new(s[0], s[1], s[2]) / s[3]);
        let normal = (mean(right)? - mean(left)?).cross(&(mean(below)? - mean(above)?));
        let norm = normal.norm();
        if norm.is_nan() || norm <= 1e-12 {
            return None;
        }
        let normal = normal / norm;
        Some(if normal.dot(point) > 0.0 { -normal } else { normal })
    }
}

/// Step 6 on D: labels, normals and the salient area. `foot_radius_m` is r (J 4: foot size).
///
/// When the R-ball around the fixation point holds no salient point (the fixation point does not
/// match the camera rig, or the view there is all steep or irregular) while the image has valid
/// depth elsewhere, the labels are recomputed without DtFP and [`Saliency::dtfp_fallback`] says why,
/// so a mis-set fixation point never silently yields no seeds.
pub fn hiking_saliency(
    depth: &DepthImage,
    intrinsics: &Intrinsics,
    gravity_in_camera: &Unit<Vector3<f64>>,
    foot_radius_m: f64,
    config: &SaliencyConfig,
) -> Saliency {
    hiking_saliency_reusing(depth, intrinsics, gravity_in_camera, foot_radius_m, config, &mut SaliencyTables::default())
}

/// The summed-area tables [`hiking_saliency_reusing`] builds from D (about 8 MB for J's 200 px
/// birds-eye view), kept between frames so that each frame writes them into the same memory instead
/// of allocating and zeroing them anew.
#[derive(Debug, Clone, Default)]
pub struct SaliencyTables {
    integral: IntegralCloud,
    moments: WindowMoments,
}

/// [`hiking_saliency`] with its tables built in `tables` (the result does not depend on what they
/// held before).
pub fn hiking_saliency_reusing(
    depth: &DepthImage,
    intrinsics: &Intrinsics,
    gravity_in_camera: &Unit<Vector3<f64>>,
    foot_radius_m: f64,
    config: &SaliencyConfig,
    tables: &mut SaliencyTables,
) -> Saliency {
    let fixation = fixation_point(gravity_in_camera, config.fixation_down_m, config.fixation_forward_m);
    // Both are serial scans of D: side by side.
    let jump = if config.depth_edge_clearance > 0.0 { config.depth_edge_jump } else { 0.0 };
    let SaliencyTables { integral, moments } = tables;
    let with_moments = config.window_rms_max_m.is_finite();
    let (edges, ()) = rayon::join(
        || rayon::join(|| integral.rebuild(depth, intrinsics), || EdgeDistance::new(depth, jump)).1,
        || {
            if with_moments {
                moments.rebuild(depth, intrinsics, config.window_quadric_rms_max_m > 0.0);
            }
        },
    );
    let frame = LabelInput {
        depth,
        intrinsics,
        integral,
        edges: &edges,
        moments: with_moments.then_some(&*moments),
        gravity_in_camera,
        fixation: &fixation,
        foot_radius_m,
    };
    let pass = |radius_m: f64| label_pixels(&frame, radius_m, config);
    let first = pass(config.fixation_radius_m);
    if !config.fixation_radius_m.is_finite() || first.count(SaliencyLabel::Salient) > 0 || first.count(SaliencyLabel::Distant) == 0 {
        return first;
    }
    let valid = first.labels.len() - first.count(SaliencyLabel::Invalid);
    let in_ball = valid - first.count(SaliencyLabel::Distant);
    let reason = format!(
        "no salient point within R = {:.2} m of the fixation point ({:.2} m down, {:.2} m ahead): {in_ball} of {valid} valid points in the ball \
         ({} steep, {} irregular, {} uneven, {} beside a depth edge, {} at the image border, {} without a normal); saliency ran without DtFP",
        config.fixation_radius_m,
        config.fixation_down_m,
        config.fixation_forward_m,
        first.count(SaliencyLabel::Steep),
        first.count(SaliencyLabel::Irregular),
        first.count(SaliencyLabel::Uneven),
        first.count(SaliencyLabel::DepthEdge),
        first.count(SaliencyLabel::ImageBorder),
        first.count(SaliencyLabel::NoNormal),
    );
    let mut fallback = pass(f64::INFINITY);
    fallback.dtfp_fallback = Some(reason);
    fallback
}

/// What [`label_pixels`] reads of the frame: D, its integral cloud and depth-jump distances,
/// gravity, the fixation point and the foot radius r.
struct LabelInput<'a> {
    depth: &'a DepthImage,
    intrinsics: &'a Intrinsics,
    integral: &'a IntegralCloud,
    edges: &'a EdgeDistance,
    moments: Option<&'a WindowMoments>,
    gravity_in_camera: &'a Unit<Vector3<f64>>,
    fixation: &'a Vector3<f64>,
    foot_radius_m: f64,
}

/// Steps 6.2–6.5 with DtFP radius `radius_m` (non-finite: no region of interest), the foot
/// window's depth-discontinuity and image-border checks before the normals and its flatness check
/// after them.
fn label_pixels(frame: &LabelInput, radius_m: f64, config: &SaliencyConfig) -> Saliency {
    let LabelInput { depth, intrinsics, integral, edges, moments, gravity_in_camera, fixation, foot_radius_m } = *frame;
    let (width, height) = (depth.width, depth.height);
    let radius_sq = if radius_m.is_finite() { radius_m.powi(2) } else { f64::INFINITY };
    let cos_don = config.don_max_deg.to_radians().cos();
    let cos_dong = config.dong_max_deg.to_radians().cos();
    let focal = 0.5 * (intrinsics.fx + intrinsics.fy);
    let pixel_area_per_z2 = 1.0 / (intrinsics.fx * intrinsics.fy);
    let g = gravity_in_camera.into_inner();
    let mut labels = vec![SaliencyLabel::Invalid; width * height];
    let mut normals_in_camera = vec![Vector3::repeat(f32::NAN); width * height];
    let salient_area_m2: f64 = labels
        .par_chunks_mut(width)
        .zip(normals_in_camera.par_chunks_mut(width))
        .enumerate()
        .map(|(v, (label_row, normal_row))| {
            let mut area = 0.0;
            for (u, (label, normal_out)) in label_row.iter_mut().zip(normal_row.iter_mut()).enumerate() {
                let z = f64::from(depth.depth_m[v * width + u]);
                if !z.is_finite() {
                    continue;
                }
                let point = intrinsics.back_project(u as f64, v as f64, z);
                // 6.2 DtFP.
                if (point - fixation).norm_squared() > radius_sq {
                    *label = SaliencyLabel::Distant;
                    continue;
                }
                // 6.3 normals: window 2rf/Z, i.e. half window rf/Z, and half of that.
                let half = (foot_radius_m * focal / z).round().max(2.0 * config.min_half_window_px as f64) as usize;
                if f64::from(edges.at(u, v)) < config.depth_edge_clearance * half as f64 {
                    *label = SaliencyLabel::DepthEdge;
                    continue;
                }
                let to_border = u.min(v).min(width - 1 - u).min(height - 1 - v);
                if (to_border as f64) < config.depth_edge_clearance * half as f64 {
                    *label = SaliencyLabel::ImageBorder;
                    continue;
                }
                let half_fine = (half / 2).max(config.min_half_window_px);
                let (Some(n), Some(n_fine)) = (
                    integral.normal(u, v, half, &point, config.min_support_fraction),
                    integral.normal(u, v, half_fine, &point, config.min_support_fraction),
                ) else {
                    *label = SaliencyLabel::NoNormal;
                    continue;
                };
                *normal_out = n.cast::<f32>();
                *label = if n.dot(&n_fine) < cos_don {
                    SaliencyLabel::Irregular // 6.4 DoN
                } else if -n.dot(&g) < cos_dong {
                    SaliencyLabel::Steep // 6.5 DoNG
                } else if moments.is_some_and(|m| uneven(m, u, v, half, &n, config)) {
                    SaliencyLabel::Uneven
                } else {
                    let cos_view = (n.dot(&point) / point.norm()).abs().max(0.1);
                    area += z * z * pixel_area_per_z2 / cos_view;
                    SaliencyLabel::Salient
                };
            }
            area
        })
        .sum();
    Saliency { width, height, labels, normals_in_camera, fixation_in_camera: *fixation, salient_area_m2, dtfp_fallback: None }
}

/// Whether the foot window of half size `half` at `(u, v)` spreads off its plane along the coarse
/// normal `n` (a step or a bump) and is not a smooth bump a quadric explains either (`moments`
/// without quadric tables have no quadric).
fn uneven(moments: &WindowMoments, u: usize, v: usize, half: usize, n: &Vector3<f64>, config: &SaliencyConfig) -> bool {
    let min_points = config.min_support_fraction * ((2 * half + 1) as f64).powi(2);
    let spread = moments.rms_off_plane(u, v, half, n, min_points).is_some_and(|rms| rms > config.window_rms_max_m);
    spread
        && !moments
            .quadric(u, v, half, min_points)
            .is_some_and(|q| q.rms_m <= config.window_quadric_rms_max_m && q.curvature_max <= config.window_curvature_max)
}

#[cfg(test)]
pub(crate) mod tests {
    use super::*;
    use crate::acquire::gravity_from_vector;

    /// Renders a depth image of an analytic surface by ray marching: `surface(p)` is a signed
    /// height-like function that changes sign when the ray crosses the surface.
    pub(crate) fn render(intrinsics: &Intrinsics, surface: impl Fn(&Vector3<f64>) -> f64 + Sync) -> DepthImage {
        let mut depth = vec![f32::NAN; intrinsics.width * intrinsics.height];
        depth.par_iter_mut().enumerate().for_each(|(i, d)| {
            let (u, v) = ((i % intrinsics.width) as f64, (i / intrinsics.width) as f64);
            let ray = intrinsics.back_project(u, v, 1.0);
            let (mut t0, mut t1) = (0.2, 0.2);
            let mut s0 = surface(&(ray * t0));
            while t1 < 6.0 {
                t1 = t0 + 0.01;
                let s1 = surface(&(ray * t1));
                if s0.signum() != s1.signum() {
                    // Bisection to 1e-7 m.
                    let (mut a, mut b) = (t0, t1);
                    for _ in 0..40 {
                        let m = 0.5 * (a + b);
                        if surface(&(ray * m)).signum() == s0.signum() {
                            a = m;
                        } else {
                            b = m;
                        }
                    }
                    *d = (0.5 * (a + b)) as f32;
                    return;
                }
                t0 = t1;
                s0 = s1;
            }
        });
        DepthImage::new(intrinsics.width, intrinsics.height, depth).unwrap_or_else(|_| unreachable!())
    }

    pub(crate) fn small_camera() -> Intrinsics {
        Intrinsics::new(160, 120, 131.25, 131.25, 79.5, 59.5).unwrap()
    }

    /// Camera looking straight ahead (gravity +y) at 0.4 m above a floor, a wall 2 m ahead.
    pub(crate) fn floor_and_wall(intrinsics: &Intrinsics) -> DepthImage {
        render(intrinsics, |p| (0.4 - p.y).min(2.0 - p.z))
    }

    /// Tables reused across frames of other sizes, contents and configurations give what fresh
    /// ones give: nothing of an earlier frame is left in them.
    #[test]
    fn reused_tables_give_the_fresh_tables_saliency() {
        let wide = small_camera();
        let tall = Intrinsics::new(120, 160, 131.25, 131.25, 59.5, 79.5).unwrap();
        let centre = Vector3::new(0.0, 0.1, 1.2);
        let mut holed = floor_and_wall(&wide);
        for (i, d) in holed.depth_m.iter_mut().enumerate() {
            if (i / 7) % 11 == 0 {
                *d = f32::NAN;
            }
        }
        let plane_only = SaliencyConfig { window_quadric_rms_max_m: 0.0, ..SaliencyConfig::default() };
        let no_moments = SaliencyConfig { window_rms_max_m: f64::INFINITY, ..SaliencyConfig::default() };
        let frames = [
            (floor_and_wall(&wide), wide, SaliencyConfig::default()),
            (render(&tall, |p| (p - centre).norm() - 0.5), tall, SaliencyConfig::default()),
            (holed, wide, plane_only),
            (floor_and_wall(&wide), wide, no_moments),
            (render(&tall, |p| 0.3 - p.y), tall, SaliencyConfig::default()),
        ];
        let g = Unit::new_normalize(Vector3::new(0.0, 1.0, 0.2));
        let mut tables = SaliencyTables::default();
        for (index, (depth, intrinsics, config)) in frames.iter().enumerate() {
            let reused = hiking_saliency_reusing(depth, intrinsics, &g, 0.05, config, &mut tables);
            let fresh = hiking_saliency(depth, intrinsics, &g, 0.05, config);
            assert_eq!((reused.width, reused.height), (fresh.width, fresh.height));
            assert!(reused.labels == fresh.labels, "frame {index}: labels differ");
            let bits = |s: &Saliency| s.normals_in_camera.iter().flat_map(|n| n.iter().map(|c| c.to_bits())).collect::<Vec<_>>();
            assert!(bits(&reused) == bits(&fresh), "frame {index}: normals differ");
            assert_eq!(reused.salient_area_m2.to_bits(), fresh.salient_area_m2.to_bits(), "frame {index}");
            assert!(fresh.count(SaliencyLabel::Salient) > 0, "frame {index} has salient points to compare");
        }
    }

    #[test]
    fn integral_normals_match_analytic_plane_normals() {
        let intrinsics = small_camera();
        // Tilted plane n·p = 1.5 with n = normalize(0.2, -0.9, -0.4) (facing the camera).
        let n_true = Vector3::new(0.2, -0.9, -0.4).normalize();
        let depth = render(&intrinsics, |p| -1.5 - n_true.dot(p));
        let integral = IntegralCloud::new(&depth, &intrinsics);
        let mut checked = 0;
        for v in (10..110).step_by(7) {
            for u in (10..150).step_by(7) {
                let Some(z) = depth.get(u, v) else { continue };
                let p = intrinsics.back_project(u as f64, v as f64, f64::from(z));
                // Only where the whole window sees the plane (it leaves the image at the horizon).
                let Some(n) = integral.normal(u, v, 4, &p, 1.0) else { continue };
                assert!(n.dot(&n_true) > (0.5f64).to_radians().cos(), "normal {n:?} at ({u},{v})");
                checked += 1;
            }
        }
        assert!(checked > 100);
    }

    #[test]
    fn integral_normals_on_a_sphere_match_the_radial_direction() {
        let intrinsics = small_camera();
        let centre = Vector3::new(0.0, 0.0, 1.5);
        let depth = render(&intrinsics, |p| (p - centre).norm() - 0.5);
        let integral = IntegralCloud::new(&depth, &intrinsics);
        for (u, v) in [(80, 60), (70, 50), (95, 66)] {
            let z = depth.get(u, v).unwrap();
            let p = intrinsics.back_project(u as f64, v as f64, f64::from(z));
            let n_true = (p - centre).normalize();
            let n = integral.normal(u, v, 2, &p, 0.5).unwrap();
            assert!(n.dot(&n_true) > (3.0f64).to_radians().cos(), "({u},{v}): {n:?} vs {n_true:?}");
        }
    }

    #[test]
    fn saliency_keeps_ground_and_drops_the_wall() {
        let intrinsics = small_camera();
        let depth = floor_and_wall(&intrinsics);
        let g = gravity_from_vector(Vector3::y()).unwrap();
        let config = SaliencyConfig { fixation_radius_m: f64::INFINITY, ..Default::default() };
        let saliency = hiking_saliency(&depth, &intrinsics, &g, 0.05, &config);
        let mut floor = (0, 0);
        let mut wall = (0, 0);
        for (i, label) in saliency.labels.iter().enumerate() {
            let Some(z) = depth.get(i % 160, i / 160) else { continue };
            let p = intrinsics.back_project((i % 160) as f64, (i / 160) as f64, f64::from(z));
            let salient = *label == SaliencyLabel::Salient;
            // Well away from the crease (y = 0.4, z = 2) and the image border (normal windows).
            let inside = (15..145).contains(&(i % 160)) && i / 160 < 105;
            if inside && (p.y - 0.4).abs() < 1e-3 && p.z < 1.8 {
                floor = (floor.0 + usize::from(salient), floor.1 + 1);
            } else if (p.z - 2.0).abs() < 1e-3 && p.y < 0.2 {
                wall = (wall.0 + usize::from(salient), wall.1 + 1);
                assert_ne!(*label, SaliencyLabel::Salient, "wall pixel {i} salient");
            }
        }
        assert!(floor.1 > 1000 && wall.1 > 1000);
        assert!(
            floor.0 as f64 > 0.95 * floor.1 as f64,
            "floor salient {floor:?} labels {:?}",
            [0u8, 1, 2, 3, 4, 5, 6].map(|l| saliency.labels.iter().filter(|x| **x as u8 == l).count())
        );
        assert_eq!(wall.0, 0);
        assert!(saliency.count(SaliencyLabel::Steep) > 1000);
        // The crease itself is irregular (DoN) for some pixels.
        assert!(saliency.count(SaliencyLabel::Irregular) > 0);
        // Salient area ≈ visible floor area up to the crease region.
        assert!(saliency.salient_area_m2 > 0.5, "area {}", saliency.salient_area_m2);
    }

    #[test]
    fn foot_windows_across_a_depth_edge_are_not_salient() {
        // Looking straight down at a floor 1 m away with a 15 cm block (0.2 m square) on it.
        let intrinsics = small_camera();
        let inside_block = |p: &Vector3<f64>| p.x.abs() < 0.1 && p.y.abs() < 0.1;
        let depth = render(&intrinsics, |p| if inside_block(p) { 0.85 - p.z } else { 1.0 - p.z });
        let g = gravity_from_vector(Vector3::z()).unwrap();
        let r = 0.05;
        let config = SaliencyConfig { fixation_radius_m: f64::INFINITY, ..Default::default() };
        let saliency = hiking_saliency(&depth, &intrinsics, &g, r, &config);
        let (mut near, mut clear) = ((0, 0), (0, 0));
        for (i, label) in saliency.labels.iter().enumerate() {
            let (u, v) = (i % 160, i / 160);
            let Some(z) = depth.get(u, v) else { continue };
            let p = intrinsics.back_project(u as f64, v as f64, f64::from(z));
            // Distance in the image plane's xy to the block's outline.
            let to_edge = if inside_block(&p) { (0.1 - p.x.abs()).min(0.1 - p.y.abs()) } else { (p.x.abs() - 0.1).max(p.y.abs() - 0.1) };
            let off_border = (12..148).contains(&u) && (12..108).contains(&v);
            if to_edge < 0.6 * r {
                near = (near.0 + usize::from(*label == SaliencyLabel::DepthEdge), near.1 + 1);
            } else if to_edge > 1.3 * r && off_border {
                clear = (clear.0 + usize::from(*label == SaliencyLabel::Salient), clear.1 + 1);
            }
        }
        assert!(near.1 > 500 && clear.1 > 500, "{near:?} {clear:?}");
        assert_eq!(near.0, near.1, "pixels by the edge not marked: {near:?}");
        assert!(clear.0 as f64 > 0.98 * clear.1 as f64, "clear pixels salient: {clear:?}");
        // The block's top, 2.5 r across, keeps salient pixels at its centre.
        let centre = saliency.labels.get(60 * 160 + 80).copied();
        assert_eq!(centre, Some(SaliencyLabel::Salient));
        // Off (J's step 6 as written): nothing is a depth edge.
        let off = hiking_saliency(&depth, &intrinsics, &g, r, &SaliencyConfig { depth_edge_clearance: 0.0, ..config });
        assert_eq!(off.count(SaliencyLabel::DepthEdge) + off.count(SaliencyLabel::ImageBorder), 0);
        // There J's DoN and DoNG drop most windows across the step, but not all: the rest are seeds
        // whose disc hangs over the edge or past the image border.
        let extra: Vec<_> = (0..off.labels.len())
            .filter(|&i| off.labels[i] == SaliencyLabel::Salient && saliency.labels[i] != SaliencyLabel::Salient)
            .collect();
        assert!(extra.len() > 50, "{}", extra.len());
        assert!(extra.iter().all(|&i| matches!(saliency.labels[i], SaliencyLabel::DepthEdge | SaliencyLabel::ImageBorder)));
    }

    #[test]
    fn foot_windows_past_the_image_border_are_not_salient() {
        // A floor 1 m below a camera looking straight down: the foot window's half size is
        // r·f/Z = 0.05 · 131.25 ≈ 7 pixels.
        let intrinsics = small_camera();
        let depth = render(&intrinsics, |p| 1.0 - p.z);
        let g = gravity_from_vector(Vector3::z()).unwrap();
        let config = SaliencyConfig { fixation_radius_m: f64::INFINITY, ..Default::default() };
        let saliency = hiking_saliency(&depth, &intrinsics, &g, 0.05, &config);
        let half = 7;
        for (i, &label) in saliency.labels.iter().enumerate() {
            let (u, v) = (i % 160, i / 160);
            let to_border = u.min(v).min(159 - u).min(119 - v);
            let expected = if to_border < half { SaliencyLabel::ImageBorder } else { SaliencyLabel::Salient };
            assert_eq!(label, expected, "pixel ({u}, {v})");
        }
        let off = hiking_saliency(&depth, &intrinsics, &g, 0.05, &SaliencyConfig { depth_edge_clearance: 0.0, ..config });
        assert_eq!(off.count(SaliencyLabel::ImageBorder), 0);
        assert!(off.count(SaliencyLabel::Salient) > saliency.count(SaliencyLabel::Salient));
    }

    #[test]
    fn dtfp_keeps_only_the_ball_around_the_fixation_point() {
        let intrinsics = small_camera();
        let depth = floor_and_wall(&intrinsics);
        let g = gravity_from_vector(Vector3::y()).unwrap();
        let config = SaliencyConfig { fixation_down_m: 0.4, fixation_forward_m: 1.3, fixation_radius_m: 0.25, ..Default::default() };
        let saliency = hiking_saliency(&depth, &intrinsics, &g, 0.05, &config);
        assert!((saliency.fixation_in_camera - Vector3::new(0.0, 0.4, 1.3)).norm() < 1e-12);
        let mut salient = 0;
        for i in saliency.salient_indices() {
            let z = depth.depth_m[i];
            let p = intrinsics.back_project((i % 160) as f64, (i / 160) as f64, f64::from(z));
            assert!((p - saliency.fixation_in_camera).norm() <= 0.25 + 1e-9);
            salient += 1;
        }
        assert!(salient > 200);
        assert!(saliency.count(SaliencyLabel::Distant) > saliency.count(SaliencyLabel::Salient));
    }

    #[test]
    fn a_fixation_point_off_the_rig_falls_back_to_no_dtfp_and_says_why() {
        // The floor is 0.4 m below the camera; a chest-height fixation point 1.2 m down has no
        // surface within its ball.
        let intrinsics = small_camera();
        let depth = floor_and_wall(&intrinsics);
        let g = gravity_from_vector(Vector3::y()).unwrap();
        let config = SaliencyConfig { fixation_down_m: 1.2, fixation_forward_m: 1.5, fixation_radius_m: 0.5, ..Default::default() };
        let saliency = hiking_saliency(&depth, &intrinsics, &g, 0.05, &config);
        let reason = saliency.dtfp_fallback.as_deref().unwrap();
        assert!(reason.contains("no salient point within R = 0.50 m") && reason.contains("1.20 m down"), "{reason}");
        let no_dtfp = SaliencyConfig { fixation_radius_m: f64::INFINITY, ..config.clone() };
        let expected = hiking_saliency(&depth, &intrinsics, &g, 0.05, &no_dtfp);
        assert_eq!(saliency.labels, expected.labels);
        assert!(saliency.count(SaliencyLabel::Salient) > 200);
        assert!(expected.dtfp_fallback.is_none());
        // A fixation point on the rig's floor needs no fallback.
        let on_rig = SaliencyConfig { fixation_down_m: 0.4, fixation_forward_m: 1.0, ..config };
        assert!(hiking_saliency(&depth, &intrinsics, &g, 0.05, &on_rig).dtfp_fallback.is_none());
    }

    #[test]
    fn the_top_of_a_smooth_bump_is_salient_and_a_step_is_not() {
        // Looking straight down from 1 m (foot window half size 7 px): a κ = 12 m⁻¹ bump spreads
        // 6.3 mm off the plane at its top, more than window_rms_max_m, but its quadric explains it;
        // a 2 cm step (below the depth-edge jump) does not get in that way, nor does a bump
        // rounder than window_curvature_max.
        let intrinsics = small_camera();
        let g = gravity_from_vector(Vector3::z()).unwrap();
        let config = SaliencyConfig { fixation_radius_m: f64::INFINITY, ..Default::default() };
        let bump = |kappa: f64| render(&intrinsics, move |p| 1.0 - kappa / 2.0 * (p.x * p.x + p.y * p.y) - p.z);
        let top = 60 * 160 + 80;
        let label_at_top = |kappa: f64, config: &SaliencyConfig| hiking_saliency(&bump(kappa), &intrinsics, &g, 0.05, config).labels[top];
        assert_eq!(label_at_top(12.0, &config), SaliencyLabel::Salient);
        let plane_only = SaliencyConfig { window_quadric_rms_max_m: 0.0, ..config.clone() };
        assert_eq!(label_at_top(12.0, &plane_only), SaliencyLabel::Uneven);
        assert_eq!(label_at_top(25.0, &config), SaliencyLabel::Uneven);
        // The step along x = 0: the pixels whose window it crosses near the middle stay uneven.
        let step = render(&intrinsics, |p| if p.x < 0.0 { 0.98 - p.z } else { 1.0 - p.z });
        let with_quadric = hiking_saliency(&step, &intrinsics, &g, 0.05, &config);
        let without = hiking_saliency(&step, &intrinsics, &g, 0.05, &plane_only);
        let uneven = without.count(SaliencyLabel::Uneven);
        assert!(uneven > 100, "{uneven}");
        assert_eq!(with_quadric.count(SaliencyLabel::Uneven), uneven);
    }
}

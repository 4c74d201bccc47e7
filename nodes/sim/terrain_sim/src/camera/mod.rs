//! Virtual depth camera like the PrimeSense Carmine 1.09 of the RPBP (J 2.1, 6.2): 640×480 at 30 Hz,
//! rendered by ray casting the analytic scene, with the Murray–Little stereo error model (J eq. 2),
//! missing data at grazing angles, depth edges and projector shadows, and 16UC1-millimetre output.
//!
//! Noise (J eq. 2, Murray & Little): each pixel's measurement ray is perturbed by the pointing error
//! σp (pixels, in u and v), and its disparity `d = f·b/z` by the matching error σm (pixels); the
//! depth is `z = f·b/d`, so to first order σz = z²·σm/(f·b). Disparity is then quantised to the
//! sensor's sub-pixel step and depth to millimetres. The simulation samples the disparity itself
//! (exact, not linearised); a test checks its σz against `patchwalk_spl::sensor::murray_little`, the
//! covariance model perception uses (`CameraConfig::stereo_error_params` gives matching parameters).
//!
//! Rendering is parallel over rows (rayon); per frame each rock's bounding box is projected into the
//! camera and the projector images so that per pixel only the rocks that can be hit are tested. A
//! terrain scene casts every ray against the terrain's heightfield (exact bilinear surface), with the
//! same grazing-angle, depth-edge and projector-shadow rules (a terrain shadows itself).
//!
//! [`config`] holds the camera's parameters, `noise` the random draws of the error model and
//! `edges` the depth discontinuities where data go missing.

pub mod config;
mod edges;
mod noise;

use nalgebra::{Isometry3, Point3, Vector3};
use patchwalk_fusion::camera::{CameraError, DepthImage, Intrinsics};
use rayon::prelude::*;

pub use config::{CameraConfig, MissingDataConfig, NoiseConfig};
use edges::{at_depth_edge, depth_gradients};
use noise::row_rng;
pub use noise::{mix, FastNormal};

use crate::scene::{Ray, Scene};

/// Errors from building the camera.
#[derive(Debug, thiserror::Error, PartialEq)]
pub enum DepthCameraError {
    #[error(transparent)]
    Camera(#[from] CameraError),
    #[error("invalid camera config: {0}")]
    Invalid(String),
}

/// The virtual depth camera.
#[derive(Debug, Clone)]
pub struct DepthCamera {
    pub config: CameraConfig,
    pub intrinsics: Intrinsics,
}

/// Conservative pixel rectangle `[u_min, u_max, v_min, v_max]` (inclusive, f64).
type PixelRect = [f64; 4];

/// Pixel-centre depths and their image gradients at one camera pose (see
/// [`DepthCamera::render_reusing`]).
#[derive(Debug, Clone)]
pub struct RenderCache {
    world_from_camera: Isometry3<f64>,
    centre: Vec<f32>,
    gradient_u: Vec<f32>,
    gradient_v: Vec<f32>,
}

/// Per-frame constants of `DepthCamera::render`.
struct FrameSetup {
    world_from_camera_rotation: nalgebra::Matrix3<f64>,
    camera_in_world: Vector3<f64>,
    projector_in_world: Vector3<f64>,
    cos_max_incidence: f64,
    /// Rocks (index, rectangle) that may appear in the camera / projector image.
    camera_rects: Vec<(usize, PixelRect)>,
    projector_rects: Vec<(usize, PixelRect)>,
}

/// Largest pointing jitter applied (px); Gaussian draws are clamped here so culling stays exact.
const MAX_JITTER_PX: f64 = 1.5;

impl DepthCamera {
    pub fn new(config: CameraConfig) -> Result<Self, DepthCameraError> {
        let intrinsics = config.intrinsics()?;
        let n = &config.noise;
        let checks = [
            (config.rate_hz > 0.0, "rate_hz must be positive"),
            (config.baseline_m > 0.0, "baseline_m must be positive"),
            (config.min_depth_m >= 0.0 && config.max_depth_m > config.min_depth_m, "need 0 ≤ min_depth_m < max_depth_m"),
            (n.sigma_pointing_px >= 0.0 && n.sigma_disparity_px >= 0.0, "noise sigmas must be ≥ 0"),
            (n.disparity_step_px >= 0.0 && n.depth_step_m >= 0.0, "quantisation steps must be ≥ 0"),
            ((0.0..=90.0).contains(&config.missing.max_incidence_deg), "max_incidence_deg must be in 0..=90"),
            (config.missing.edge_jump_ratio > 0.0, "edge_jump_ratio must be positive"),
        ];
        if let Some((_, message)) = checks.iter().find(|(ok, _)| !ok) {
            return Err(DepthCameraError::Invalid((*message).to_string()));
        }
        Ok(Self { config, intrinsics })
    }

    /// Renders one depth frame (metres, NaN = no data) seen from `world_from_camera`
    /// (`camera_optical`). `noise_seed` makes the noise reproducible (use a per-frame seed).
    pub fn render(&self, scene: &Scene, world_from_camera: &Isometry3<f64>, noise_seed: u64) -> DepthImage {
        let jitter_seed = self.config.noise.enabled.then_some(noise_seed);
        let ideal = self.cast_all(scene, world_from_camera, jitter_seed);
        self.finish(&ideal, noise_seed)
    }

    /// Like [`render`](Self::render), but while the camera stays exactly at the pose cached in
    /// `cache` the ray casting is reused: the pointing error is applied to the cached pixel-centre
    /// depths to first order (`z + ∂z/∂u·δu + ∂z/∂v·δv`), which costs a fraction of a full cast.
    /// A static robot in the lookdown pose renders ≈ 3× faster this way.
    pub fn render_reusing(
        &self,
        scene: &Scene,
        world_from_camera: &Isometry3<f64>,
        noise_seed: u64,
        cache: &mut Option<RenderCache>,
    ) -> DepthImage {
        if !self.config.noise.enabled {
            return self.render(scene, world_from_camera, noise_seed);
        }
        let (width, height) = (self.intrinsics.width, self.intrinsics.height);
        let ratio = self.config.missing.edge_jump_ratio as f32;
        let cached = match cache.take() {
            Some(cached) if cached.world_from_camera == *world_from_camera => cached,
            _ => {
                let centre = self.cast_all(scene, world_from_camera, None);
                let (gradient_u, gradient_v) = depth_gradients(&centre, width, height, ratio);
                RenderCache { world_from_camera: *world_from_camera, centre, gradient_u, gradient_v }
            }
        };
        let mut jittered = vec![f32::NAN; width * height];
        jittered.par_chunks_mut(width).enumerate().for_each(|(v, row)| {
            let mut rng = row_rng(noise_seed, 0, v);
            for (u, out) in row.iter_mut().enumerate() {
                let (ju, jv) = self.pointing_jitter(&mut rng);
                let i = v * width + u;
                let (Some(z), Some(gu), Some(gv)) = (cached.centre.get(i), cached.gradient_u.get(i), cached.gradient_v.get(i)) else {
                    continue;
                };
                *out = z + gu * ju as f32 + gv * jv as f32;
            }
        });
        let image = self.finish(&jittered, noise_seed);
        *cache = Some(cached);
        image
    }

    /// Casts every pixel's ray (jittered by the pointing error when `jitter_seed` is given).
    fn cast_all(&self, scene: &Scene, world_from_camera: &Isometry3<f64>, jitter_seed: Option<u64>) -> Vec<f32> {
        let (width, height) = (self.intrinsics.width, self.intrinsics.height);
        let setup = self.frame_setup(scene, world_from_camera);
        let mut ideal = vec![f32::NAN; width * height];
        ideal.par_chunks_mut(width).enumerate().for_each(|(v, row)| {
            let mut rng = row_rng(jitter_seed.unwrap_or(0), 0, v);
            // Rocks whose projected bounds reach this row (jitter stays within the margin).
            let camera_rocks = rocks_on_row(&setup.camera_rects, v as f64);
            // The projector is displaced along x only, so a point keeps its row in its image.
            let projector_rocks = rocks_on_row(&setup.projector_rects, v as f64);
            for (u, out) in row.iter_mut().enumerate() {
                let (ju, jv) = if jitter_seed.is_some() { self.pointing_jitter(&mut rng) } else { (0.0, 0.0) };
                let (pu, pv) = (u as f64 + ju, v as f64 + jv);
                let candidates = camera_rocks.iter().filter(|(_, r)| rect_contains(r, pu, pv)).map(|(i, _)| *i);
                *out = self.cast(scene, &setup, candidates, &projector_rocks, pu, pv);
            }
        });
        ideal
    }

    /// One pass over the cast depths: drop depth edges, then disparity noise and quantisation.
    fn finish(&self, ideal: &[f32], noise_seed: u64) -> DepthImage {
        let (width, height) = (self.intrinsics.width, self.intrinsics.height);
        let ratio = self.config.missing.edge_jump_ratio as f32;
        let mut depth = vec![f32::NAN; width * height];
        depth.par_chunks_mut(width).enumerate().for_each(|(v, row)| {
            let mut rng = row_rng(noise_seed, 1, v);
            for (u, out) in row.iter_mut().enumerate() {
                let z = ideal.get(v * width + u).copied().unwrap_or(f32::NAN);
                if !z.is_finite() || at_depth_edge(ideal, width, height, u, v, z, ratio) {
                    continue;
                }
                *out = if self.config.noise.enabled {
                    self.disparity_noise(f64::from(z), &mut rng)
                } else {
                    quantise(f64::from(z), self.config.noise.depth_step_m) as f32
                };
            }
        });
        DepthImage { width, height, depth_m: depth }
    }

    /// Per-frame constants: pose as a matrix, projector position, culling rectangles.
    fn frame_setup(&self, scene: &Scene, world_from_camera: &Isometry3<f64>) -> FrameSetup {
        let projector_in_camera = Vector3::new(self.config.baseline_m, 0.0, 0.0);
        // The projector's image is unbounded: points the camera sees may project outside it.
        let visible = |viewpoint: &Vector3<f64>, clip: bool| -> Vec<(usize, PixelRect)> {
            scene
                .rocks
                .iter()
                .enumerate()
                .filter_map(|(i, rock)| Some((i, self.project_bounds(rock, world_from_camera, viewpoint, clip)?)))
                .collect()
        };
        FrameSetup {
            world_from_camera_rotation: world_from_camera.rotation.to_rotation_matrix().into_inner(),
            camera_in_world: world_from_camera.translation.vector,
            projector_in_world: (world_from_camera * Point3::from(projector_in_camera)).coords,
            cos_max_incidence: self.config.missing.max_incidence_deg.to_radians().cos(),
            camera_rects: visible(&Vector3::zeros(), true),
            projector_rects: visible(&projector_in_camera, false),
        }
    }

    /// Depth along the ray through pixel `(u, v)` (possibly sub-pixel), or NaN; `candidates` are
    /// the rocks the ray may hit.
    #[inline]
    fn cast(
        &self,
        scene: &Scene,
        setup: &FrameSetup,
        candidates: impl Iterator<Item = usize>,
        projector_rocks: &[(usize, PixelRect)],
        u: f64,
        v: f64,
    ) -> f32 {
        let k = &self.intrinsics;
        let direction_in_camera = Vector3::new((u - k.cx) / k.fx, (v - k.cy) / k.fy, 1.0);
        let ray = Ray { origin: setup.camera_in_world, direction: setup.world_from_camera_rotation * direction_in_camera };
        let Some((hit, _)) = scene.intersect_among(&ray, candidates) else {
            return f32::NAN;
        };
        // With a unit-z ray in the camera frame the ray parameter is the depth.
        let z = hit.t;
        if !(self.config.min_depth_m..=self.config.max_depth_m).contains(&z) {
            return f32::NAN;
        }
        if -ray.direction.dot(&hit.normal) < setup.cos_max_incidence * ray.direction.norm() {
            return f32::NAN;
        }
        if self.config.missing.projector_shadow && !projector_rocks.is_empty() {
            let from_projector = direction_in_camera * z - Vector3::new(self.config.baseline_m, 0.0, 0.0);
            let (pu, pv) = (k.fx * from_projector.x / from_projector.z + k.cx, k.fy * from_projector.y / from_projector.z + k.cy);
            let mut blockers = projector_rocks.iter().filter(|(_, r)| rect_contains(r, pu, pv)).peekable();
            if blockers.peek().is_some() {
                let point_in_world = ray.at(z) + hit.normal * 1e-6;
                let to_projector = Ray { origin: point_in_world, direction: setup.projector_in_world - point_in_world };
                let shadowed = blockers
                    .any(|(i, _)| scene.rocks.get(*i).is_some_and(|rock| rock.intersect_world(&to_projector).is_some_and(|h| h.t < 1.0)));
                if shadowed {
                    return f32::NAN;
                }
            }
        }
        if self.config.missing.projector_shadow {
            if let Some(terrain) = &scene.terrain {
                // A terrain occludes itself (risers, walls): the projector must see the point too.
                let point_in_world = ray.at(z) + hit.normal * 1e-5;
                let to_projector = Ray { origin: point_in_world, direction: setup.projector_in_world - point_in_world };
                if terrain.intersect(&to_projector).is_some_and(|h| h.t < 1.0) {
                    return f32::NAN;
                }
            }
        }
        z as f32
    }

    /// Pointing error (J eq. 2, σp) in pixels, clamped to ±`MAX_JITTER_PX`.
    #[inline]
    fn pointing_jitter(&self, rng: &mut FastNormal) -> (f64, f64) {
        let sigma = self.config.noise.sigma_pointing_px;
        let (du, dv) = (rng.sample(), rng.sample());
        ((du * sigma).clamp(-MAX_JITTER_PX, MAX_JITTER_PX), (dv * sigma).clamp(-MAX_JITTER_PX, MAX_JITTER_PX))
    }

    /// Disparity-domain noise (J eq. 2, σm), disparity and depth quantisation; NaN if out of range.
    #[inline]
    fn disparity_noise(&self, z: f64, rng: &mut FastNormal) -> f32 {
        let noise = &self.config.noise;
        let fb = self.intrinsics.fx * self.config.baseline_m;
        let e = rng.sample();
        let mut disparity = fb / z + noise.sigma_disparity_px * e;
        if noise.disparity_step_px > 0.0 {
            disparity = quantise(disparity, noise.disparity_step_px);
        }
        if disparity <= 0.0 {
            return f32::NAN;
        }
        let z = quantise(fb / disparity, noise.depth_step_m);
        if (self.config.min_depth_m..=self.config.max_depth_m).contains(&z) {
            z as f32
        } else {
            f32::NAN
        }
    }

    /// Pixel rectangle covering a rock's bounding box as seen from a viewpoint at
    /// `viewpoint_in_camera` (the camera itself or the projector) with the camera's intrinsics and
    /// orientation; `None` if it is entirely behind (or, with `clip`, outside the image); the whole
    /// plane if it straddles the image plane.
    fn project_bounds(
        &self,
        rock: &crate::scene::Rock,
        world_from_camera: &Isometry3<f64>,
        viewpoint_in_camera: &Vector3<f64>,
        clip: bool,
    ) -> Option<PixelRect> {
        let [min, max] = rock.bounds_in_rock;
        let camera_from_rock = world_from_camera.inverse() * rock.world_from_rock;
        let k = &self.intrinsics;
        let margin = MAX_JITTER_PX + 1.0;
        let mut rect = [f64::INFINITY, f64::NEG_INFINITY, f64::INFINITY, f64::NEG_INFINITY];
        let mut behind = 0;
        for corner in 0..8 {
            let local = Point3::new(
                if corner & 1 == 0 { min.x } else { max.x },
                if corner & 2 == 0 { min.y } else { max.y },
                if corner & 4 == 0 { min.z } else { max.z },
            );
            let p = (camera_from_rock * local).coords - viewpoint_in_camera;
            if p.z <= 1e-3 {
                behind += 1;
                continue;
            }
            let (u, v) = (k.fx * p.x / p.z + k.cx, k.fy * p.y / p.z + k.cy);
            rect = [rect[0].min(u), rect[1].max(u), rect[2].min(v), rect[3].max(v)];
        }
        let rect = match behind {
            8 => return None,
            0 => [rect[0] - margin, rect[1] + margin, rect[2] - margin, rect[3] + margin],
            _ => [f64::NEG_INFINITY, f64::INFINITY, f64::NEG_INFINITY, f64::INFINITY],
        };
        if !clip {
            return Some(rect);
        }
        // Clip to the image (± margin); nothing left = not visible.
        let (w, h) = (k.width as f64 - 1.0 + margin, k.height as f64 - 1.0 + margin);
        let clipped = [rect[0].max(-margin), rect[1].min(w), rect[2].max(-margin), rect[3].min(h)];
        (clipped[0] <= clipped[1] && clipped[2] <= clipped[3]).then_some(clipped)
    }
}

#[inline]
fn rect_contains(r: &PixelRect, u: f64, v: f64) -> bool {
    u >= r[0] && u <= r[1] && v >= r[2] && v <= r[3]
}

/// The rectangles that reach row `v` (± the jitter margin, already in the rectangles).
fn rocks_on_row(rects: &[(usize, PixelRect)], v: f64) -> Vec<(usize, PixelRect)> {
    rects.iter().filter(|(_, r)| v + MAX_JITTER_PX >= r[2] && v - MAX_JITTER_PX <= r[3]).copied().collect()
}

/// Rounds a non-negative `value` to a multiple of `step` (0 = unchanged). Multiplying by the
/// reciprocal and truncating to i64 (one instruction each on baseline x86-64, unlike `f64::round`
/// and f64→u64) matters here: it runs twice per pixel.
#[inline]
fn quantise(value: f64, step: f64) -> f64 {
    if step > 0.0 && (0.0..9.0e15 * step).contains(&value) {
        ((value * (1.0 / step) + 0.5) as i64) as f64 * step
    } else {
        value
    }
}

/// Depth in 16-bit millimetres (0 = no data), the `16UC1` encoding of `sensor_msgs/Image`.
pub fn to_millimetres(image: &DepthImage) -> Vec<u16> {
    image.depth_m.iter().map(|&d| if d.is_finite() { (f64::from(d) * 1000.0).round().clamp(0.0, 65535.0) as u16 } else { 0 }).collect()
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::scene::{RockShape, SceneConfig, TableConfig};
    use nalgebra::{Rotation3, UnitQuaternion};

    fn empty_scene() -> Scene {
        let table = TableConfig { length_x_m: 3.0, margin_y_m: 3.0, ..TableConfig::default() };
        Scene::new(&SceneConfig { table, training_rocks: Some(vec![]), untrained_rocks: 0, ..SceneConfig::default() }, 0).unwrap()
    }

    /// Camera at height `h` above (1.5, 0.3) looking straight down (optical z = −world z).
    fn looking_down(h: f64) -> Isometry3<f64> {
        let rotation = Rotation3::from_matrix_unchecked(nalgebra::Matrix3::new(1.0, 0.0, 0.0, 0.0, -1.0, 0.0, 0.0, 0.0, -1.0));
        Isometry3::from_parts(nalgebra::Translation3::new(1.5, 0.3, h), UnitQuaternion::from_rotation_matrix(&rotation))
    }

    fn noiseless() -> CameraConfig {
        CameraConfig { noise: NoiseConfig { enabled: false, depth_step_m: 0.0, ..NoiseConfig::default() }, ..CameraConfig::default() }
    }

    #[test]
    fn plane_at_known_distance_renders_exactly() {
        let camera = DepthCamera::new(noiseless()).unwrap();
        let image = camera.render(&empty_scene(), &looking_down(0.8), 0);
        assert_eq!((image.width, image.height), (640, 480));
        assert_eq!(image.valid_count(), 640 * 480);
        assert!(image.depth_m.iter().all(|&z| (z - 0.8).abs() < 1e-6));
        // Tilted 30° about the camera x axis: analytic depth z(v) = h / (cos θ + sin θ·(v − cy)/fy)
        // for the table plane (ray (0, y, 1) rotated).
        let theta = 30f64.to_radians();
        let pose = looking_down(0.8) * UnitQuaternion::from_euler_angles(theta, 0.0, 0.0);
        let image = camera.render(&empty_scene(), &pose, 0);
        for v in [0usize, 100, 239, 400, 479] {
            let y = (v as f64 - camera.intrinsics.cy) / camera.intrinsics.fy;
            let expected = 0.8 / (theta.cos() + theta.sin() * y);
            let got = f64::from(image.get(320, v).unwrap());
            assert!((got - expected).abs() < 1e-5, "row {v}: {got} vs {expected}");
        }
    }

    #[test]
    fn sphere_silhouette_matches_projection() {
        // A full sphere (ellipsoid a = b = c = r standing on the table) seen from above.
        let r = 0.08;
        let shape = RockShape::EllipsoidCap { semi_axes_m: [r, r, r], centre_z_m: r };
        let config = SceneConfig {
            training_rocks: Some(vec![shape]),
            untrained_rocks: 0,
            rock_x_m: 0.7,
            station_spacing_m: 0.6,
            table: TableConfig::default(),
            ..SceneConfig::default()
        };
        let scene = Scene::new(&config, 0).unwrap();
        let centre = scene.rocks[0].world_from_rock.translation.vector + Vector3::new(0.0, 0.0, r);
        let h = 0.9;
        let pose = Isometry3::from_parts(nalgebra::Translation3::new(centre.x, centre.y, h), looking_down(h).rotation);
        let camera = DepthCamera::new(noiseless()).unwrap();
        let image = camera.render(&scene, &pose, 0);
        // Centre pixel: top of the sphere.
        let top = f64::from(image.get(320, 240).unwrap_or(f32::NAN));
        let expected_top = h - centre.z - r;
        assert!((top - expected_top).abs() < 1e-3, "{top} vs {expected_top}");
        // Silhouette radius in pixels: the tangent cone half-angle α = asin(r / D).
        let distance = h - centre.z;
        let radius_px = camera.intrinsics.fx * (r / distance).asin().tan();
        let near_sphere = |u: usize| image.get(u, 240).is_some_and(|z| f64::from(z) < distance);
        // Pixels well inside see the sphere; well outside see the table (further than the centre).
        for offset in [0.0, 0.5 * radius_px, radius_px - 4.0] {
            assert!(near_sphere((320.0 + offset) as usize), "inside at {offset}");
        }
        for offset in [radius_px + 2.0, radius_px + 20.0] {
            assert!(!near_sphere((320.0 + offset) as usize), "outside at {offset}");
        }
    }

    #[test]
    fn noise_matches_murray_little_model() {
        let mut config = CameraConfig::default();
        config.noise.disparity_step_px = 0.0;
        config.noise.depth_step_m = 0.0;
        let camera = DepthCamera::new(config).unwrap();
        for h in [0.6, 1.2] {
            let image = camera.render(&empty_scene(), &looking_down(h), 42);
            let values: Vec<f64> = image.depth_m.iter().filter(|z| z.is_finite()).map(|&z| f64::from(z)).collect();
            let n = values.len() as f64;
            let mean = values.iter().sum::<f64>() / n;
            let std = (values.iter().map(|z| (z - mean).powi(2)).sum::<f64>() / n).sqrt();
            let model = config.depth_sigma(h);
            // Same σz as the mapper's covariance model (J eq. 2) at the image centre.
            let covariance = patchwalk_spl::sensor::murray_little(&Vector3::new(0.0, 0.0, h), &config.stereo_error_params()).unwrap();
            assert!((covariance[(2, 2)].sqrt() - model).abs() < 1e-12 * model.max(1.0));
            assert!((mean - h).abs() < 0.1 * model, "mean {mean} at {h}");
            assert!((std / model - 1.0).abs() < 0.1, "std {std} vs model {model} at {h}");
        }
    }

    #[test]
    fn quantised_output_is_millimetres() {
        let camera = DepthCamera::new(CameraConfig::default()).unwrap();
        let image = camera.render(&empty_scene(), &looking_down(0.7), 3);
        assert!(image
            .depth_m
            .iter()
            .filter(|z| z.is_finite())
            .all(|&z| ((f64::from(z) * 1000.0).round() - f64::from(z) * 1000.0).abs() < 1e-3));
        let mm = to_millimetres(&image);
        assert!(mm.iter().all(|&d| d == 0 || (680..=720).contains(&d)));
    }

    #[test]
    fn grazing_rays_and_depth_edges_are_missing() {
        // Looking almost along the table: far rows hit it at grazing angles → no data there.
        let camera = DepthCamera::new(noiseless()).unwrap();
        let pose = looking_down(0.3) * UnitQuaternion::from_euler_angles(75f64.to_radians(), 0.0, 0.0);
        let image = camera.render(&empty_scene(), &pose, 0);
        assert!(image.get(320, 479).is_some());
        let v_top = (0..480).find(|&v| image.get(320, v).is_some()).unwrap();
        // Incidence at row v is 75° − atan((v − cy)/fy): 78° at v = cy − fy·tan 3°; rows above are dropped.
        let expected = camera.intrinsics.cy - camera.intrinsics.fy * (3f64.to_radians()).tan();
        assert!((v_top as f64 - expected).abs() <= 2.0, "{v_top} vs {expected}");
        // A box edge over the table produces a band of missing pixels around its silhouette.
        let shape = RockShape::FlatBoulder { radius_m: 0.06, height_m: 0.15, top_slope: [0.0, 0.0] };
        let table = TableConfig { length_x_m: 3.0, ..TableConfig::default() };
        let config = SceneConfig { table, training_rocks: Some(vec![shape]), untrained_rocks: 0, rock_x_m: 1.5, ..SceneConfig::default() };
        let scene = Scene::new(&config, 0).unwrap();
        let image = camera.render(&scene, &looking_down(0.8), 0);
        let row: Vec<bool> = (0..640).map(|u| image.get(u, 240).is_some()).collect();
        let gaps = row.windows(2).filter(|w| w[0] != w[1]).count();
        assert!(gaps >= 4, "expected missing bands on both sides of the boulder, row validity changes {gaps} times");
    }

    #[test]
    fn rendering_is_deterministic_from_the_seed() {
        let scene = Scene::new(&SceneConfig::default(), 5).unwrap();
        let camera = DepthCamera::new(CameraConfig::default()).unwrap();
        let pose = looking_down(0.6);
        let a = camera.render(&scene, &pose, 11);
        let b = camera.render(&scene, &pose, 11);
        let c = camera.render(&scene, &pose, 12);
        assert_eq!(to_millimetres(&a), to_millimetres(&b));
        assert_ne!(to_millimetres(&a), to_millimetres(&c));
    }

    #[test]
    fn reused_render_matches_full_render_statistics() {
        // A slanted table (depth varies across rows) with a rock: the first-order pointing error
        // of the cached path must give the same noise as casting jittered rays.
        let scene = Scene::new(&SceneConfig::default(), 5).unwrap();
        let sim_pose = crate::motion::HeadMotion::new(crate::motion::MotionConfig::default(), 0).world_from_camera(
            &scene.station(0).unwrap(),
            &crate::motion::base_from_camera_lookdown(&crate::motion::MotionConfig::default()),
            0.0,
        );
        let mut config = CameraConfig::default();
        config.noise.disparity_step_px = 0.0;
        config.noise.depth_step_m = 0.0;
        let camera = DepthCamera::new(config).unwrap();
        let truth = DepthCamera::new(noiseless()).unwrap().render(&scene, &sim_pose, 0);
        let mut cache = None;
        let stats = |image: &DepthImage| {
            let residuals: Vec<f64> = image
                .depth_m
                .iter()
                .zip(&truth.depth_m)
                .filter(|(a, b)| a.is_finite() && b.is_finite())
                .map(|(a, b)| f64::from(a - b))
                .collect();
            let n = residuals.len() as f64;
            let mean = residuals.iter().sum::<f64>() / n;
            (residuals.len(), mean, (residuals.iter().map(|r| (r - mean).powi(2)).sum::<f64>() / n).sqrt())
        };
        let full = stats(&camera.render(&scene, &sim_pose, 9));
        let first = camera.render_reusing(&scene, &sim_pose, 9, &mut cache);
        assert!(cache.is_some());
        let second = camera.render_reusing(&scene, &sim_pose, 10, &mut cache);
        assert_ne!(to_millimetres(&first), to_millimetres(&second));
        let reused = stats(&second);
        assert!((reused.0 as f64 / full.0 as f64 - 1.0).abs() < 0.01, "valid {} vs {}", reused.0, full.0);
        assert!((reused.2 / full.2 - 1.0).abs() < 0.05, "std {} vs {}", reused.2, full.2);
        assert!((reused.1 - full.1).abs() < 0.1 * full.2, "mean {} vs {}", reused.1, full.1);
        // Same seed, same cache → same image.
        assert_eq!(to_millimetres(&camera.render_reusing(&scene, &sim_pose, 10, &mut cache)), to_millimetres(&second));
    }

    #[test]
    fn bad_config_is_an_error() {
        assert!(DepthCamera::new(CameraConfig { fx: 0.0, ..CameraConfig::default() }).is_err());
        assert!(DepthCamera::new(CameraConfig { min_depth_m: 4.0, ..CameraConfig::default() }).is_err());
    }
}

//! Raycasting the TSDF (J 5.1): from the real camera (points + normals in the volume frame, the model
//! for ICP) and from the birds-eye virtual camera (J 5.1 "Adaptations": axis-aligned with the volume,
//! looking down along volume +y, `bo` above the real camera, `br × br` pixels) whose organized depth
//! image feeds the patch mapper unchanged.
//!
//! Marching: rays are clipped to the bounds of the allocated blocks; empty superblocks (4³ blocks) and
//! unallocated blocks are skipped whole (empty-space leaping); inside blocks the step shrinks with the
//! nearest-voxel TSDF (step = max(voxel, 0.8·|tsdf|·μ)); at a sign change from positive to negative
//! the crossing is found by secant steps on trilinear TSDF values and the normal is the normalized
//! trilinear gradient. The model raycast for ICP is guided by the frame just integrated: a ray with a
//! depth d there marches only the band [d − 2μ, d + 2μ] around the surface that frame just fused
//! (a model crossing farther behind it would be occluded by that surface); where the downsampled
//! frame has a hole, the depth range of the full-resolution pixels under the ray gives the band.
//! Rays of a row are marched a few at a time, one step each in turn, so that their (independent)
//! voxel cache misses overlap.

use nalgebra::{Isometry3, Matrix3, Point3, Rotation3, Translation3, UnitQuaternion, Vector3};
use rayon::prelude::*;

use crate::camera::{DepthImage, Intrinsics};
use crate::fusion::{floor_i, Block, TsdfVolume, BLOCK_EDGE, SUPERBLOCK_EDGE};

/// Raycast parameters.
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize, serde::Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct RaycastConfig {
    /// Nearest range considered along a ray (m).
    pub min_range_m: f32,
    /// Farthest range considered along a ray (m).
    pub max_range_m: f32,
    /// Step factor on the TSDF distance inside blocks (KinectFusion uses < 1 to not skip the crossing).
    pub step_factor: f32,
}

impl Default for RaycastConfig {
    fn default() -> Self {
        Self { min_range_m: 0.1, max_range_m: 4.0, step_factor: 0.8 }
    }
}

/// Birds-eye virtual camera (J 5.1 "Adaptations to moving volume KinectFusion").
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize, serde::Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct BirdsEyeConfig {
    /// bo: offset of the centre of projection above the real camera (m). J gives no value.
    pub offset_above_camera_m: f64,
    /// br: image width and height in pixels (J: "e.g. br = 200px").
    pub resolution_px: usize,
    /// Full field of view of the pinhole virtual camera (deg); J does not fix it.
    pub field_of_view_deg: f64,
}

impl Default for BirdsEyeConfig {
    /// For RPBP (camera ≈ 0.47 m above the ground): bo = 0.5 m and 64° put the ground ≈ 0.97 m
    /// below the virtual camera with a 1.2 m wide view (about the 1.28 m volume); J's br = 200 px
    /// gives 6 mm pixels, so a foot-size (r = 0.05 m) neighbourhood holds ≈ 210 points. 240 px (5 mm,
    /// the voxel size, ≈ 300 points) fits patches no better and costs 45 % more raycast. (A 90° view
    /// at 200 px gives 9.6 mm pixels: ≈ 85 points per neighbourhood and rock tops 10 px wide.)
    fn default() -> Self {
        Self { offset_above_camera_m: 0.5, resolution_px: 200, field_of_view_deg: 64.0 }
    }
}

/// Organized raycast of the model: per pixel a surface point and normal in the volume frame (NaN
/// where the ray hit nothing) and the depth along the virtual/real camera's optical axis.
#[derive(Debug, Clone)]
pub struct ModelRaycast {
    pub intrinsics: Intrinsics,
    pub volume_from_camera: Isometry3<f64>,
    pub points_in_volume: Vec<Point3<f32>>,
    pub normals_in_volume: Vec<Vector3<f32>>,
    pub depth: DepthImage,
}

impl ModelRaycast {
    /// Number of pixels with a surface hit.
    pub fn hit_count(&self) -> usize {
        self.depth.valid_count()
    }
}

/// The birds-eye raycast handed to the mapper: an organized depth image of a pinhole camera and its pose.
#[derive(Debug, Clone)]
pub struct BirdsEyeView {
    pub depth: DepthImage,
    pub intrinsics: Intrinsics,
    pub volume_from_birds_eye: Isometry3<f64>,
    /// Surface normals in the volume frame (NaN where no hit), for rendering.
    pub normals_in_volume: Vec<Vector3<f32>>,
}

/// Pose and intrinsics of the birds-eye camera for a real camera at `volume_from_camera`: axes aligned
/// with the volume (z = volume +y, down; x = volume x; y = −volume z), centre `bo` above the camera.
pub fn birds_eye_camera(config: &BirdsEyeConfig, volume_from_camera: &Isometry3<f64>) -> (Intrinsics, Isometry3<f64>) {
    let rotation = Rotation3::from_matrix_unchecked(Matrix3::from_columns(&[Vector3::x(), -Vector3::z(), Vector3::y()]));
    let camera_position = volume_from_camera.translation.vector;
    let position = camera_position - Vector3::y() * config.offset_above_camera_m;
    let pose = Isometry3::from_parts(Translation3::from(position), UnitQuaternion::from_rotation_matrix(&rotation));
    let br = config.resolution_px.max(1);
    let half_fov = (config.field_of_view_deg.clamp(1.0, 170.0) / 2.0).to_radians();
    let focal = (br as f64 / 2.0) / half_fov.tan();
    let centre = (br as f64 - 1.0) / 2.0;
    let intrinsics = Intrinsics { width: br, height: br, fx: focal, fy: focal, cx: centre, cy: centre };
    (intrinsics, pose)
}

/// Raycasts the birds-eye view for the real camera at `volume_from_camera`.
pub fn raycast_birds_eye(
    volume: &TsdfVolume,
    config: &RaycastConfig,
    birds_eye: &BirdsEyeConfig,
    volume_from_camera: &Isometry3<f64>,
) -> BirdsEyeView {
    raycast_birds_eye_within(volume, config, birds_eye, volume_from_camera, None)
}

/// [`raycast_birds_eye`] of only the pixels `within` marks (row-major, one per pixel of the view;
/// the others are left without a hit), or of all of them.
pub fn raycast_birds_eye_within(
    volume: &TsdfVolume,
    config: &RaycastConfig,
    birds_eye: &BirdsEyeConfig,
    volume_from_camera: &Isometry3<f64>,
    within: Option<&[bool]>,
) -> BirdsEyeView {
    let (intrinsics, volume_from_birds_eye) = birds_eye_camera(birds_eye, volume_from_camera);
    let model = raycast_pixels(volume, config, &intrinsics, &volume_from_birds_eye, None, within);
    BirdsEyeView { depth: model.depth, intrinsics, volume_from_birds_eye, normals_in_volume: model.normals_in_volume }
}

/// Raycasts the volume from a pinhole camera at `volume_from_camera` (J 5.1).
pub fn raycast(volume: &TsdfVolume, config: &RaycastConfig, intrinsics: &Intrinsics, volume_from_camera: &Isometry3<f64>) -> ModelRaycast {
    raycast_guided(volume, config, intrinsics, volume_from_camera, None)
}

/// Where the frame just integrated at the raycast pose saw surfaces, to bound each ray's march.
#[derive(Debug, Clone, Copy)]
pub struct RayHint<'a> {
    /// Depth at the raycast resolution: a ray with depth d there marches [d − 2μ, d + 2μ].
    pub depth: &'a DepthImage,
    /// The same frame at an integer multiple f of the raycast resolution (e.g. the full-resolution
    /// input): where `depth` has no value (holes of the averaged image, mostly depth edges), the ray
    /// marches [min − 2μ, max + 2μ] of the valid depths in its f × f pixel patch here. Rays whose
    /// patch has no valid depth either are marched in full.
    pub fine: Option<&'a DepthImage>,
}

/// Depth range (m along the optical axis) of the valid depths of `fine` in the `factor × factor`
/// patch of pixel `(u, v)` of the coarse image.
fn patch_depth_range(fine: &DepthImage, factor: usize, u: usize, v: usize) -> Option<(f32, f32)> {
    let (mut near, mut far) = (f32::INFINITY, f32::NEG_INFINITY);
    for row in (v * factor..(v + 1) * factor).take_while(|row| *row < fine.height) {
        let start = row * fine.width + u * factor;
        let end = start + factor.min(fine.width.saturating_sub(u * factor));
        for &d in fine.depth_m.get(start..end).unwrap_or(&[]) {
            if d.is_finite() {
                near = near.min(d);
                far = far.max(d);
            }
        }
    }
    (near <= far).then_some((near, far))
}

/// Raycast guided by a depth hint (e.g. the frame just integrated at this pose): a ray with hint
/// depth d marches only [d − 2μ, d + 2μ] (along the optical axis), the band around the expected
/// surface; rays that do not find a crossing there stop at its end instead of marching the occluded
/// volume behind it. Pixels without a hint at the raycast resolution take the depth range of the
/// finer image's patch (`RayHint::fine`); pixels without any hint are marched in full.
pub fn raycast_guided(
    volume: &TsdfVolume,
    config: &RaycastConfig,
    intrinsics: &Intrinsics,
    volume_from_camera: &Isometry3<f64>,
    hint: Option<RayHint<'_>>,
) -> ModelRaycast {
    raycast_pixels(volume, config, intrinsics, volume_from_camera, hint, None)
}

/// [`raycast_guided`] of the pixels `within` marks (all of them when it does not match the image).
fn raycast_pixels(
    volume: &TsdfVolume,
    config: &RaycastConfig,
    intrinsics: &Intrinsics,
    volume_from_camera: &Isometry3<f64>,
    hint: Option<RayHint<'_>>,
    within: Option<&[bool]>,
) -> ModelRaycast {
    let within = within.filter(|w| w.len() == intrinsics.width * intrinsics.height);
    let hint = hint.filter(|h| h.depth.width == intrinsics.width && h.depth.height == intrinsics.height);
    // The finer image must be an integer multiple of the raycast resolution.
    let fine = hint.and_then(|h| h.fine).and_then(|fine| {
        let factor = fine.width / intrinsics.width.max(1);
        (factor >= 1 && fine.width == factor * intrinsics.width && fine.height == factor * intrinsics.height).then_some((fine, factor))
    });
    let mu = volume.truncation();
    let inv_voxel = 1.0 / volume.voxel_size();
    let bounds = volume.allocated_bounds().map(|(lo, hi)| (lo, hi - Vector3::repeat(1e-4)));
    let (width, height) = (intrinsics.width, intrinsics.height);
    let pose = volume_from_camera.cast::<f32>();
    let rotation = pose.rotation.to_rotation_matrix();
    let origin = pose.translation.vector;
    let (fx, fy, cx, cy) = (intrinsics.fx as f32, intrinsics.fy as f32, intrinsics.cx as f32, intrinsics.cy as f32);
    let mut points_in_volume = vec![Point3::new(f32::NAN, f32::NAN, f32::NAN); width * height];
    let mut normals_in_volume = vec![Vector3::repeat(f32::NAN); width * height];
    let mut depth_m = vec![f32::NAN; width * height];
    points_in_volume
        .par_chunks_mut(width.max(1))
        .zip(normals_in_volume.par_chunks_mut(width.max(1)))
        .zip(depth_m.par_chunks_mut(width.max(1)))
        .enumerate()
        .for_each(|(v, ((points, normals), depths))| {
            let Some(bounds) = bounds else {
                return;
            };
            let start_ray = |u: usize| {
                if within.is_some_and(|w| !w.get(v * width + u).copied().unwrap_or(false)) {
                    return None;
                }
                let ray_in_camera = Vector3::new((u as f32 - cx) / fx, (v as f32 - cy) / fy, 1.0);
                let ray_length = ray_in_camera.norm();
                let direction = rotation * (ray_in_camera / ray_length);
                let band = hint
                    .and_then(|h| h.depth.depth_m.get(v * width + u))
                    .filter(|d| d.is_finite())
                    .map(|&d| (d, d))
                    .or_else(|| fine.and_then(|(fine, factor)| patch_depth_range(fine, factor, u, v)))
                    .map(|(near, far)| ((near - 2.0 * mu) * ray_length, (far + 2.0 * mu) * ray_length));
                RayMarch::start(config, inv_voxel, &bounds, &origin, &direction, band).map(|march| (u, ray_length, march))
            };
            // RAY_LANES rays of the row are marched in turn, one step each: their voxel loads do not
            // depend on each other, so the processor overlaps their cache misses (a single ray's
            // next position depends on the TSDF just loaded).
            let mut lanes: [Option<(usize, f32, RayMarch<'_>)>; RAY_LANES] = std::array::from_fn(|_| None);
            let mut next_u = 0;
            loop {
                let mut active = false;
                for lane in lanes.iter_mut() {
                    while lane.is_none() && next_u < width {
                        *lane = start_ray(next_u);
                        next_u += 1;
                    }
                    let Some((u, ray_length, march)) = lane else { continue };
                    active = true;
                    let outcome = match march.step(volume, config, inv_voxel) {
                        MarchStep::Continue => continue,
                        MarchStep::Done => None,
                        MarchStep::Bracketed { t_positive, t_negative } => {
                            refine_crossing(volume, &origin, &march.direction, t_positive, t_negative, inv_voxel)
                        }
                    };
                    if let Some((t, normal)) = outcome {
                        if let (Some(point), Some(n), Some(depth)) = (points.get_mut(*u), normals.get_mut(*u), depths.get_mut(*u)) {
                            *point = Point3::from(origin + march.direction * t);
                            *n = normal;
                            *depth = t / *ray_length;
                        }
                    }
                    *lane = None;
                }
                if !active && next_u >= width {
                    break;
                }
            }
        });
    let depth = DepthImage { width, height, depth_m };
    ModelRaycast { intrinsics: *intrinsics, volume_from_camera: *volume_from_camera, points_in_volume, normals_in_volume, depth }
}

/// Entry and exit ray parameters of the box [lo, hi] (slab method), from the ray's origin and the
/// per-axis inverse of its direction (infinite along axes it does not move on).
fn clip_to_box(origin: &Vector3<f32>, inverse_direction: &Vector3<f32>, lo: &Vector3<f32>, hi: &Vector3<f32>) -> Option<(f32, f32)> {
    let mut t_near = f32::NEG_INFINITY;
    let mut t_far = f32::INFINITY;
    for axis in 0..3 {
        let (o, inv) = (origin[axis], inverse_direction[axis]);
        if !inv.is_finite() {
            if o < lo[axis] || o > hi[axis] {
                return None;
            }
            continue;
        }
        let (a, b) = ((lo[axis] - o) * inv, (hi[axis] - o) * inv);
        t_near = t_near.max(a.min(b));
        t_far = t_far.min(a.max(b));
    }
    (t_near <= t_far).then_some((t_near, t_far))
}

/// Rays marched interleaved per row (see `raycast_guided`).
const RAY_LANES: usize = 4;

/// Outcome of one marching step.
enum MarchStep {
    /// Still marching.
    Continue,
    /// Left the band, the cube or the range without a crossing: no hit.
    Done,
    /// A positive TSDF sample followed by a non-positive one: the crossing lies between.
    Bracketed { t_positive: f32, t_negative: f32 },
}

/// One ray being marched within `band` (ray parameters) if given, toward its first front-facing zero
/// crossing. The ray is clipped to `bounds` (of the allocated blocks, computed once per raycast);
/// empty superblocks and unallocated blocks are leapt over whole; inside blocks the step shrinks
/// with the TSDF (the surface is at least |tsdf|·μ away).
struct RayMarch<'v> {
    direction: Vector3<f32>,
    origin_voxel: Vector3<f32>,
    inverse_direction: Vector3<f32>,
    t: f32,
    t_end: f32,
    /// The last observed sample (t, tsdf), if the step before was in observed data.
    previous: Option<(f32, f32)>,
    /// The allocated block the previous step was in: consecutive steps inside it skip both lookups.
    current: Option<([i32; 3], &'v Block)>,
    steps: usize,
}

impl<'v> RayMarch<'v> {
    /// Starts a ray from `origin` along unit `direction` (volume frame, m; `inv_voxel` the inverse
    /// voxel edge, 1/m); `None` if it misses `bounds`.
    fn start(
        config: &RaycastConfig,
        inv_voxel: f32,
        bounds: &(Vector3<f32>, Vector3<f32>),
        origin: &Vector3<f32>,
        direction: &Vector3<f32>,
        band: Option<(f32, f32)>,
    ) -> Option<Self> {
        let inverse_direction = direction.map(|d| if d.abs() < 1e-9 { f32::INFINITY } else { 1.0 / d });
        let (t_enter, t_exit) = clip_to_box(origin, &inverse_direction, &bounds.0, &bounds.1)?;
        let t = t_enter.max(config.min_range_m).max(band.map_or(0.0, |(start, _)| start));
        let t_end = t_exit.min(config.max_range_m).min(band.map_or(f32::INFINITY, |(_, end)| end));
        Some(Self {
            direction: *direction,
            origin_voxel: origin * inv_voxel,
            inverse_direction,
            t,
            t_end,
            previous: None,
            current: None,
            steps: 0,
        })
    }

    /// One step of the march; `inv_voxel` is the inverse voxel edge (1/m).
    #[inline]
    fn step(&mut self, volume: &'v TsdfVolume, config: &RaycastConfig, inv_voxel: f32) -> MarchStep {
        if !(self.t < self.t_end && self.steps < 100_000) {
            return MarchStep::Done;
        }
        self.steps += 1;
        let voxel = volume.voxel_size();
        let mu = volume.truncation();
        let p = self.origin_voxel + self.direction * (self.t * inv_voxel);
        let (i, j, k) = (floor_i(p.x), floor_i(p.y), floor_i(p.z));
        let block_coords = [i >> 3, j >> 3, k >> 3];
        let block = match self.current {
            Some((coords, block)) if coords == block_coords => block,
            _ => {
                if !volume.superblock_occupied(i, j, k) {
                    self.previous = None;
                    let superblock_voxels = (BLOCK_EDGE * SUPERBLOCK_EDGE) as f32;
                    self.t += cell_exit(&p, &self.inverse_direction, superblock_voxels) * voxel + 0.01 * voxel;
                    return MarchStep::Continue;
                }
                let Some(block) = volume.block_of_voxel(i, j, k) else {
                    // Empty-space leaping: jump to where the ray leaves this block.
                    self.previous = None;
                    self.t += cell_exit(&p, &self.inverse_direction, BLOCK_EDGE as f32) * voxel + 0.01 * voxel;
                    return MarchStep::Continue;
                };
                self.current = Some((block_coords, block));
                block
            }
        };
        let local = ((i & 7) + 8 * ((j & 7) + 8 * (k & 7))) as usize;
        let Some(tsdf) = block.voxels.get(local).filter(|v| v.weight > 0.0).map(|v| v.tsdf) else {
            // Unobserved voxel (behind a surface): no crossing can be bracketed here.
            self.previous = None;
            self.t += (0.5 * mu).max(voxel);
            return MarchStep::Continue;
        };
        if let Some((t_previous, tsdf_previous)) = self.previous {
            if tsdf_previous > 0.0 && tsdf <= 0.0 {
                return MarchStep::Bracketed { t_positive: t_previous, t_negative: self.t };
            }
        }
        self.previous = Some((self.t, tsdf));
        // The surface is at least |tsdf|·μ away (on either side of it).
        self.t += (config.step_factor * tsdf.abs() * mu).max(voxel);
        MarchStep::Continue
    }
}

/// Distance (voxel units along the ray) from `p` (voxel units) to the exit of its cubic cell of edge `size`.
#[inline]
fn cell_exit(p: &Vector3<f32>, inverse_direction: &Vector3<f32>, size: f32) -> f32 {
    let mut exit = f32::INFINITY;
    for axis in 0..3 {
        let inv = inverse_direction[axis];
        if !inv.is_finite() {
            continue;
        }
        let cell = floor_i(p[axis] / size) as f32;
        let boundary = if inv > 0.0 { (cell + 1.0) * size } else { cell * size };
        exit = exit.min((boundary - p[axis]) * inv);
    }
    exit.max(0.0)
}

/// Zero crossing between `t_a` (TSDF > 0) and `t_b` (≤ 0) by secant steps on trilinear values.
fn refine_crossing(
    volume: &TsdfVolume,
    origin: &Vector3<f32>,
    direction: &Vector3<f32>,
    mut t_a: f32,
    mut t_b: f32,
    inv_voxel: f32,
) -> Option<(f32, Vector3<f32>)> {
    let trilinear = |t: f32| volume.trilinear(&((origin + direction * t) * inv_voxel));
    let trilinear_tsdf = |t: f32| volume.trilinear_tsdf(&((origin + direction * t) * inv_voxel));
    // Both brackets must be fully observed, else the crossing is at the edge of the data: no hit.
    let (mut f_a, mut f_b) = (trilinear_tsdf(t_a)?, trilinear_tsdf(t_b)?);
    // The march brackets on nearest-voxel values; within a voxel of the surface the trilinear value
    // can still have the other sign. Widen the bracket by up to two voxels on that side.
    let voxel = 1.0 / inv_voxel;
    for _ in 0..2 {
        if f_b > 0.0 {
            t_b += voxel;
            f_b = trilinear_tsdf(t_b)?;
        }
        if f_a <= 0.0 {
            t_a -= voxel;
            f_a = trilinear_tsdf(t_a)?;
        }
    }
    if !(f_a > 0.0 && f_b <= 0.0) {
        return None;
    }
    let secant = |t_a: f32, t_b: f32, f_a: f32, f_b: f32| {
        if f_a - f_b > 1e-6 {
            t_a + (t_b - t_a) * f_a / (f_a - f_b)
        } else {
            0.5 * (t_a + t_b)
        }
    };
    let mut t = secant(t_a, t_b, f_a, f_b);
    let mut at = trilinear(t)?;
    if at.tsdf.abs() > 0.02 {
        // One more secant step on the side that still brackets the crossing.
        if at.tsdf > 0.0 {
            (t_a, f_a) = (t, at.tsdf);
        } else {
            (t_b, f_b) = (t, at.tsdf);
        }
        t = secant(t_a, t_b, f_a, f_b);
        at = trilinear(t)?;
    }
    let norm = at.gradient.norm();
    if norm.is_nan() || norm <= 1e-6 {
        return None;
    }
    Some((t, at.gradient / norm))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::fusion::tests::{looking_down_pose, render_plane};
    use crate::fusion::TsdfConfig;

    #[test]
    fn raycast_recovers_an_integrated_plane() {
        let config = TsdfConfig { voxel_size_m: 0.01, size_m: 1.28, ..TsdfConfig::default() };
        let mut volume = TsdfVolume::new(config).unwrap();
        let intrinsics = Intrinsics::primesense_default().scaled(0.5);
        // A tilted plane through (0.64, 0.9, 0.64).
        let normal = Vector3::new(0.2, -1.0, 0.1).normalize();
        let offset = normal.dot(&Vector3::new(0.64, 0.9, 0.64));
        let pose = looking_down_pose(Vector3::new(0.64, 0.3, 0.64));
        let depth = render_plane(&intrinsics, &pose, normal, offset);
        volume.integrate(&depth, &intrinsics, &pose).unwrap();
        // Cast from a slightly moved camera.
        let cast_pose = Isometry3::translation(0.02, 0.0, -0.01) * pose;
        let model = raycast(&volume, &RaycastConfig::default(), &intrinsics, &cast_pose);
        assert!(model.hit_count() > intrinsics.width * intrinsics.height / 3, "{}", model.hit_count());
        let expected_depth = render_plane(&intrinsics, &cast_pose, normal, offset);
        let mut errors = Vec::new();
        for (i, p) in model.points_in_volume.iter().enumerate() {
            if p.x.is_nan() {
                continue;
            }
            let distance = (normal.cast::<f32>().dot(&p.coords) - offset as f32).abs();
            assert!(distance < 0.002, "point {i} is {distance} m off the plane");
            let n = model.normals_in_volume[i];
            // Normal faces the camera: opposite to the plane normal n (which points down, +y... here −y).
            assert!(n.dot(&normal.cast::<f32>()).abs() > 0.99, "normal {n}");
            if let Some(d) = expected_depth.depth_m.get(i).filter(|d| d.is_finite()) {
                errors.push((model.depth.depth_m[i] - d).abs());
            }
        }
        let mean = errors.iter().sum::<f32>() / errors.len() as f32;
        assert!(mean < 0.001, "mean depth error {mean}");
    }

    /// A 1.28 m volume holding the floor at y = 1.0 as a forward-looking camera tilted 45° down at
    /// (0.64, 0.5, 0.3) sees it; the volume and that camera's pose.
    fn floor_seen_from_a_tilted_camera() -> (TsdfVolume, Isometry3<f64>) {
        let config = TsdfConfig { voxel_size_m: 0.01, size_m: 1.28, ..TsdfConfig::default() };
        let mut volume = TsdfVolume::new(config).unwrap();
        let intrinsics = Intrinsics::primesense_default().scaled(0.5);
        let tilt = UnitQuaternion::from_axis_angle(&Vector3::x_axis(), -std::f64::consts::FRAC_PI_4);
        let pose = Isometry3::from_parts(Translation3::new(0.64, 0.5, 0.3), tilt);
        volume.integrate(&render_plane(&intrinsics, &pose, Vector3::y(), 1.0), &intrinsics, &pose).unwrap();
        (volume, pose)
    }

    #[test]
    fn birds_eye_looks_down_from_above_the_camera() {
        let (volume, pose) = floor_seen_from_a_tilted_camera();
        let birds_eye = BirdsEyeConfig::default();
        let view = raycast_birds_eye(&volume, &RaycastConfig::default(), &birds_eye, &pose);
        let br = birds_eye.resolution_px;
        assert_eq!((view.depth.width, view.depth.height), (br, br));
        // Birds-eye centre 0.5 m above the camera at y = 0.0: the floor is 1.0 m away along its z.
        let d = view.depth.valid_count();
        assert!(d > 1000, "{d}");
        for value in view.depth.depth_m.iter().filter(|d| d.is_finite()) {
            assert!((value - 1.0).abs() < 0.003, "{value}");
        }
        // The camera z axis is volume +y.
        let z_axis = view.volume_from_birds_eye.rotation * Vector3::z();
        assert!((z_axis - Vector3::y()).norm() < 1e-12);
    }

    #[test]
    fn birds_eye_rays_over_an_observed_floor_all_hit_it() {
        // Nearest-voxel brackets whose trilinear value has not yet changed sign must still yield the
        // crossing: every birds-eye ray over floor the camera saw (away from the image and cube
        // borders) hits it, at any sub-voxel offset of the floor.
        for (index, floor_y) in [1.0, 1.0013, 1.0027, 1.0041].into_iter().enumerate() {
            let config = TsdfConfig { voxel_size_m: 0.005, size_m: 1.28, ..TsdfConfig::default() };
            let mut volume = TsdfVolume::new(config).unwrap();
            let intrinsics = Intrinsics::primesense_default().scaled(0.5);
            let tilt = UnitQuaternion::from_axis_angle(&Vector3::x_axis(), -std::f64::consts::FRAC_PI_4);
            let pose = Isometry3::from_parts(Translation3::new(0.64, 0.55, 0.25), tilt);
            volume.integrate(&render_plane(&intrinsics, &pose, Vector3::y(), floor_y), &intrinsics, &pose).unwrap();
            let birds_eye = BirdsEyeConfig::default();
            let view = raycast_birds_eye(&volume, &RaycastConfig::default(), &birds_eye, &pose);
            let camera_from_volume = pose.inverse();
            let (mut observed, mut hit) = (0, 0);
            for v in 0..view.depth.height {
                for u in 0..view.depth.width {
                    // Where this ray meets the floor, and whether the camera saw that point well inside.
                    let ray = view.intrinsics.back_project(u as f64, v as f64, 1.0);
                    let ray_in_volume = view.volume_from_birds_eye.rotation * ray;
                    let origin = view.volume_from_birds_eye.translation.vector;
                    let floor = origin + ray_in_volume * ((floor_y - origin.y) / ray_in_volume.y);
                    let inside_cube = floor.iter().all(|c| *c > 0.05 && *c < 1.23);
                    let seen = intrinsics.project(&(camera_from_volume * Point3::from(floor)).coords).is_some_and(|(x, y)| {
                        x > 8.0 && y > 8.0 && x < intrinsics.width as f64 - 8.0 && y < intrinsics.height as f64 - 8.0
                    });
                    if inside_cube && seen {
                        observed += 1;
                        hit += usize::from(view.depth.depth_m[v * view.depth.width + u].is_finite());
                    }
                }
            }
            assert!(observed > 5000, "{observed}");
            assert!(hit as f64 >= 0.995 * observed as f64, "offset {index}: {hit} of {observed} observed floor rays hit");
        }
    }

    #[test]
    fn patch_depth_range_spans_the_valid_fine_depths() {
        // 4×2 fine image, factor 2: coarse pixel (0, 0) covers columns 0–1, (1, 0) columns 2–3.
        let nan = f32::NAN;
        let fine = DepthImage { width: 4, height: 2, depth_m: vec![1.0, nan, nan, nan, 1.5, 1.2, nan, nan] };
        assert_eq!(patch_depth_range(&fine, 2, 0, 0), Some((1.0, 1.5)));
        assert_eq!(patch_depth_range(&fine, 2, 1, 0), None);
        assert_eq!(patch_depth_range(&fine, 2, 2, 0), None);
    }

    #[test]
    fn empty_volume_yields_no_hits() {
        let volume = TsdfVolume::new(TsdfConfig::default()).unwrap();
        let intrinsics = Intrinsics::primesense_default().scaled(0.25);
        let model = raycast(&volume, &RaycastConfig::default(), &intrinsics, &Isometry3::translation(0.6, 0.6, 0.1));
        assert_eq!(model.hit_count(), 0);
        // A camera outside the cube looking away hits nothing either.
        let model = raycast(&volume, &RaycastConfig::default(), &intrinsics, &Isometry3::translation(-5.0, 0.0, 0.0));
        assert_eq!(model.hit_count(), 0);
    }

    #[test]
    fn a_birds_eye_view_within_a_region_is_the_whole_view_there() {
        let (volume, pose) = floor_seen_from_a_tilted_camera();
        let birds_eye = BirdsEyeConfig::default();
        let whole = raycast_birds_eye(&volume, &RaycastConfig::default(), &birds_eye, &pose);
        let br = birds_eye.resolution_px;
        let within: Vec<bool> = (0..br * br).map(|i| (i % br) % 3 == 0 && (i / br) % 2 == 0).collect();
        let part = raycast_birds_eye_within(&volume, &RaycastConfig::default(), &birds_eye, &pose, Some(&within));
        let mut hits = 0;
        for (i, (a, b)) in whole.depth.depth_m.iter().zip(&part.depth.depth_m).enumerate() {
            if within[i] {
                assert!(a.to_bits() == b.to_bits(), "pixel {i}: {a} vs {b}");
                hits += usize::from(b.is_finite());
            } else {
                assert!(b.is_nan(), "pixel {i} outside the region has depth {b}");
            }
        }
        assert!(hits > 1000, "{hits}");
    }
}

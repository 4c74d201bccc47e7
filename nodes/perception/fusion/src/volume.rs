//! Moving-volume policy (J 4, 5.1–5.2): the `volume` frame (corner origin, y along gravity, z along the
//! camera's horizontal forward direction), its initialisation with the camera at a nominal position,
//! and remaps (translation + rotation about the vertical) whenever the camera leaves its nominal pose by
//! more than a distance cd or an angle ca. The y axis stays vertical through every remap.
//!
//! Translation-only remaps are quantised to whole blocks so the TSDF moves by re-indexing blocks
//! (lossless, O(blocks)); remaps with a rotation resample the TSDF trilinearly.

use nalgebra::{Isometry3, Matrix3, Point3, Rotation3, Translation3, UnitQuaternion, Vector3};
use rayon::prelude::*;

use crate::camera::{DepthImage, Intrinsics};
use crate::fusion::{floor_i, Block, TsdfVolume, Voxel, BLOCK_EDGE, BLOCK_VOXELS};

/// Moving-volume parameters (J 4 "moving policies", J 5.2).
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize, serde::Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct MovingVolumeConfig {
    /// cd: remap when the camera is farther than this from its nominal position (m). J gives no
    /// value; a quarter of the default 1.28 m cube keeps the seen area inside.
    pub distance_threshold_m: f64,
    /// ca: remap when the camera's heading (rotation about the vertical) differs from the volume's z
    /// axis by more than this (deg). J gives no value.
    pub angle_threshold_deg: f64,
    /// Nominal camera position as fractions of the cube edge along x, y (down), z (forward). J 5.2
    /// puts it "in the middle of the volume"; a camera looking down from a robot's head never sees
    /// above itself, so the default puts it a quarter of the edge below the top face: 0.96 m of the
    /// 1.28 m cube lie below the camera, 0.49 m below the feet of a 0.47 m high head, and the
    /// ground stays inside when the robot looks down off a ledge or walks down a slope (in the
    /// middle, with 0.17 m below its feet, tracking lost the ground walking down the simulated
    /// course).
    pub nominal_position_fraction: [f64; 3],
    /// Whether remaps happen at all (a fixed volume otherwise, e.g. for benchmarks against Open3D).
    pub enabled: bool,
}

impl Default for MovingVolumeConfig {
    fn default() -> Self {
        Self { distance_threshold_m: 0.3, angle_threshold_deg: 30.0, nominal_position_fraction: [0.5, 0.25, 0.5], enabled: true }
    }
}

impl MovingVolumeConfig {
    /// Nominal camera position in a cube of edge `edge_m`.
    pub fn nominal_position(&self, edge_m: f64) -> Vector3<f64> {
        Vector3::from(self.nominal_position_fraction) * edge_m
    }
}

/// Rotation taking volume axes to the gravity-aligned `map` frame (z up): map x = volume x,
/// map y = volume z, map z = −volume y (volume y points down along gravity).
pub fn map_from_volume_rotation() -> UnitQuaternion<f64> {
    let rotation = Rotation3::from_matrix_unchecked(Matrix3::new(1.0, 0.0, 0.0, 0.0, 0.0, 1.0, 0.0, -1.0, 0.0));
    UnitQuaternion::from_rotation_matrix(&rotation)
}

/// Initial `volume_from_camera` (J 5.2): volume y along gravity, z along the camera's forward
/// direction made horizontal, camera at the nominal position. Without gravity the camera's own y
/// axis is taken as down.
pub fn initial_volume_from_camera(gravity_in_camera: Option<Vector3<f64>>, edge_m: f64, config: &MovingVolumeConfig) -> Isometry3<f64> {
    let down = gravity_in_camera.and_then(|g| g.try_normalize(1e-9)).unwrap_or_else(Vector3::y);
    let forward = Vector3::z();
    let horizontal = (forward - down * down.dot(&forward))
        .try_normalize(1e-6)
        // Looking straight down: use the camera's "up in image" (−y) made horizontal instead.
        .or_else(|| {
            let up_image = -Vector3::y();
            (up_image - down * down.dot(&up_image)).try_normalize(1e-6)
        })
        .unwrap_or_else(|| down.cross(&Vector3::x()).normalize());
    let x = down.cross(&horizontal);
    // Columns: volume axes in the camera frame → camera_from_volume rotation.
    let camera_from_volume = Rotation3::from_matrix_unchecked(Matrix3::from_columns(&[x, down, horizontal]));
    let rotation = UnitQuaternion::from_rotation_matrix(&camera_from_volume.inverse());
    Isometry3::from_parts(Translation3::from(config.nominal_position(edge_m)), rotation)
}

/// Sizing and placing the moving volume from the depth the camera sees (J 5.1 keeps the volume
/// around the data the camera observes; J 5.2 starts it around the camera). A robot-scale 1.28 m
/// cube holds little of a desk 1–2 m away; this fits the cube to the first frames instead.
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize, serde::Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct VolumeSizing {
    /// Share of the valid depth points (within the fusion's depth range) the cube should hold along
    /// each axis; the rest (far background, outliers) is trimmed equally from both ends.
    pub coverage: f64,
    /// Smallest edge (m).
    pub min_edge_m: f64,
    /// Largest edge (m): bounds memory and the raycast's work.
    pub max_edge_m: f64,
    /// Free space kept around the data and the camera inside the cube (m).
    pub margin_m: f64,
    /// The camera's nominal position stays at least this fraction of the edge inside every face, so
    /// the cube keeps some of what is behind and above the camera when it moves or turns (J 5.2
    /// starts with the camera in the middle). On TUM fr1/xyz a camera at the back face tracked
    /// worse than a centred one.
    pub min_camera_fraction: f64,
}

impl Default for VolumeSizing {
    fn default() -> Self {
        Self { coverage: 0.95, min_edge_m: 1.28, max_edge_m: 4.0, margin_m: 0.1, min_camera_fraction: 0.25 }
    }
}

/// The cube fitted to the depth of the first frames by [`size_volume_to_depth`].
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize)]
pub struct VolumeFit {
    /// Edge Vs (m), a whole number of blocks.
    pub edge_m: f64,
    /// Where the camera sits in the cube, as fractions of the edge (the moving volume's nominal
    /// position, [`MovingVolumeConfig::nominal_position_fraction`]).
    pub nominal_position_fraction: [f64; 3],
    /// Share of the valid depth points inside the fitted cube.
    pub inside_share: f64,
}

/// The valid points of a depth image in the camera frame, limited to `[min_depth_m, max_depth_m]`
/// (the depth range the fusion integrates), every `stride`-th pixel.
pub fn depth_points(depth: &DepthImage, intrinsics: &Intrinsics, min_depth_m: f64, max_depth_m: f64, stride: usize) -> Vec<Vector3<f64>> {
    depth
        .depth_m
        .iter()
        .enumerate()
        .step_by(stride.max(1))
        .filter_map(|(i, &z)| {
            let z = f64::from(z);
            (z.is_finite() && z >= min_depth_m && z <= max_depth_m)
                .then(|| intrinsics.back_project((i % depth.width) as f64, (i / depth.width) as f64, z))
        })
        .collect()
}

/// Share of `points_in_camera` inside the cube `[0, edge_m)³` posed by `volume_from_camera`
/// (1 for no points).
pub fn share_inside(points_in_camera: &[Vector3<f64>], volume_from_camera: &Isometry3<f64>, edge_m: f64) -> f64 {
    if points_in_camera.is_empty() {
        return 1.0;
    }
    let inside = points_in_camera
        .par_iter()
        .filter(|p| {
            let q = volume_from_camera * Point3::from(**p);
            q.iter().all(|c| (0.0..edge_m).contains(c))
        })
        .count();
    inside as f64 / points_in_camera.len() as f64
}

/// Fits the cube to the points (camera frame) of the first frames: gravity-aligned axes as in
/// [`initial_volume_from_camera`], per axis the central `coverage` share of the points together with
/// the camera (it must stay inside the cube for tracking and the birds-eye view), plus `margin_m`;
/// the edge is the largest extent rounded up to whole blocks of `block_m` and clamped to
/// `[min_edge_m, max_edge_m]`; the data's bounding box is centred in the cube, the camera kept at
/// least `min_camera_fraction` of the edge inside. `None` without points.
pub fn size_volume_to_depth(
    points_in_camera: &[Vector3<f64>],
    gravity_in_camera: Option<Vector3<f64>>,
    block_m: f64,
    sizing: &VolumeSizing,
) -> Option<VolumeFit> {
    if points_in_camera.is_empty() || block_m.is_nan() || block_m <= 0.0 {
        return None;
    }
    let rotation = initial_volume_from_camera(gravity_in_camera, 1.0, &MovingVolumeConfig::default()).rotation;
    let rotated: Vec<Vector3<f64>> = points_in_camera.par_iter().map(|p| rotation * p).collect();
    let trim = (0.5 * (1.0 - sizing.coverage.clamp(0.0, 1.0)) * rotated.len() as f64) as usize;
    let mut lo = Vector3::zeros();
    let mut hi = Vector3::zeros();
    for axis in 0..3 {
        let mut values: Vec<f64> = rotated.iter().map(|p| p[axis]).collect();
        values.sort_by(f64::total_cmp);
        let last = values.len() - 1;
        let (a, b) = (values[trim.min(last)], values[last.saturating_sub(trim)]);
        // The camera (the origin) is part of the box.
        lo[axis] = a.min(0.0) - sizing.margin_m;
        hi[axis] = b.max(0.0) + sizing.margin_m;
    }
    let extent = (hi - lo).max();
    let edge = ((extent / block_m).ceil() * block_m).clamp(sizing.min_edge_m, sizing.max_edge_m.max(sizing.min_edge_m));
    let centre = 0.5 * (lo + hi);
    // Camera position in the cube: the box centred, the camera at least the margin inside.
    let inner = sizing.margin_m.max(sizing.min_camera_fraction * edge).min(0.5 * edge);
    let camera = (Vector3::repeat(0.5 * edge) - centre).map(|c| c.clamp(inner, edge - inner));
    let nominal_position_fraction = [camera.x / edge, camera.y / edge, camera.z / edge];
    let volume_from_camera = Isometry3::from_parts(Translation3::from(camera), rotation);
    let inside_share = share_inside(points_in_camera, &volume_from_camera, edge);
    Some(VolumeFit { edge_m: edge, nominal_position_fraction, inside_share })
}

/// Heading of the camera about the volume's vertical (rad): angle of its forward axis, made
/// horizontal, from volume z toward volume x.
pub fn camera_heading(volume_from_camera: &Isometry3<f64>) -> f64 {
    let forward = volume_from_camera.rotation * Vector3::z();
    forward.x.atan2(forward.z)
}

/// The remap the policy asks for, as `new_volume_from_old_volume`, or `None` while the camera stays
/// within cd and ca of its nominal pose (J 5.2 step 5). Translation-only remaps are multiples of
/// `block_m` on each axis.
pub fn plan_remap(config: &MovingVolumeConfig, volume_from_camera: &Isometry3<f64>, edge_m: f64, block_m: f64) -> Option<Isometry3<f64>> {
    if !config.enabled {
        return None;
    }
    let nominal = config.nominal_position(edge_m);
    let position = volume_from_camera.translation.vector;
    let heading = camera_heading(volume_from_camera);
    let forward = volume_from_camera.rotation * Vector3::z();
    let heading_defined = forward.x.hypot(forward.z) > 0.2;
    let rotate = heading_defined && heading.abs() > config.angle_threshold_deg.to_radians();
    let translate = (position - nominal).norm() > config.distance_threshold_m;
    if !(rotate || translate) {
        return None;
    }
    if rotate {
        // Rotation about the vertical (volume y) that brings the heading back to 0, then the
        // translation that brings the camera to the nominal position.
        let rotation = UnitQuaternion::from_axis_angle(&Vector3::y_axis(), -heading);
        let translation = nominal - rotation * position;
        return Some(Isometry3::from_parts(Translation3::from(translation), rotation));
    }
    let shift = (nominal - position).map(|c| (c / block_m).round() * block_m);
    (shift.norm() > 0.0).then(|| Isometry3::translation(shift.x, shift.y, shift.z))
}

/// Applies `new_from_old` to the TSDF content: block re-indexing for whole-block translations,
/// trilinear resampling otherwise. Content leaving the cube is dropped.
pub fn remap_tsdf(volume: &mut TsdfVolume, new_from_old: &Isometry3<f64>) {
    let block_m = f64::from(volume.block_size());
    let shift_blocks = new_from_old.translation.vector / block_m;
    let whole_blocks = shift_blocks.iter().all(|c| (c - c.round()).abs() < 1e-6);
    if new_from_old.rotation.angle() < 1e-9 && whole_blocks {
        let shift = shift_blocks.map(|c| c.round() as i32);
        let blocks = volume
            .take_blocks()
            .into_iter()
            .map(|(c, block)| ([c[0] as i32 + shift.x, c[1] as i32 + shift.y, c[2] as i32 + shift.z], block))
            .collect();
        volume.rebuild(blocks);
        return;
    }
    resample(volume, new_from_old);
}

/// Trilinear resampling of the TSDF into the remapped frame.
fn resample(volume: &mut TsdfVolume, new_from_old: &Isometry3<f64>) {
    let block_m = volume.block_size();
    let n = volume.blocks_per_edge() as i32;
    let pose = new_from_old.cast::<f32>();
    // New blocks overlapped by the transformed bounding boxes of old blocks.
    let mut targets: Vec<[i32; 3]> = Vec::new();
    for (c, _) in volume.blocks() {
        let mut lo = Vector3::repeat(f32::INFINITY);
        let mut hi = Vector3::repeat(f32::NEG_INFINITY);
        for corner in 0..8 {
            let offset = Vector3::new((corner & 1) as f32, ((corner >> 1) & 1) as f32, ((corner >> 2) & 1) as f32);
            let p = pose * Point3::from((Vector3::new(c[0] as f32, c[1] as f32, c[2] as f32) + offset) * block_m);
            lo = lo.inf(&p.coords);
            hi = hi.sup(&p.coords);
        }
        let lo = (lo / block_m).map(|v| (v.floor() as i32).max(0));
        let hi = (hi / block_m).map(|v| (v.floor() as i32).min(n - 1));
        for z in lo.z..=hi.z {
            for y in lo.y..=hi.y {
                for x in lo.x..=hi.x {
                    targets.push([x, y, z]);
                }
            }
        }
    }
    targets.sort_unstable();
    targets.dedup();
    let old_from_new = pose.inverse();
    let voxel = volume.voxel_size();
    let fresh: Vec<Box<Block>> = targets.iter().map(|_| volume.empty_block()).collect();
    let old = &*volume;
    let filled: Vec<([i32; 3], Box<Block>, bool)> = targets
        .par_iter()
        .zip(fresh)
        .map(|(c, mut block)| {
            let mut any = false;
            for index in 0..BLOCK_VOXELS {
                let (x, y, z) = (index % BLOCK_EDGE, (index / BLOCK_EDGE) % BLOCK_EDGE, index / (BLOCK_EDGE * BLOCK_EDGE));
                let voxel_new = Vector3::new(
                    (c[0] as usize * BLOCK_EDGE + x) as f32 + 0.5,
                    (c[1] as usize * BLOCK_EDGE + y) as f32 + 0.5,
                    (c[2] as usize * BLOCK_EDGE + z) as f32 + 0.5,
                );
                let voxel_old = (old_from_new * Point3::from(voxel_new * voxel)).coords / voxel;
                let Some((_, weight)) = old.voxel(floor_i(voxel_old.x), floor_i(voxel_old.y), floor_i(voxel_old.z)) else {
                    continue;
                };
                if weight <= 0.0 {
                    continue;
                }
                let tsdf = match old.trilinear_tsdf(&voxel_old) {
                    Some(tsdf) => tsdf,
                    None => old.nearest(&voxel_old).unwrap_or(1.0),
                };
                if let Some(voxel) = block.voxels.get_mut(index) {
                    *voxel = Voxel { tsdf, weight };
                    any = true;
                }
            }
            (*c, block, any)
        })
        .collect();
    let (kept, unused): (Vec<_>, Vec<_>) = filled.into_iter().partition(|(_, _, any)| *any);
    volume.rebuild(kept.into_iter().map(|(c, block, _)| (c, block)).collect());
    volume.give_back(unused.into_iter().map(|(_, block, _)| block));
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::camera::Intrinsics;
    use crate::fusion::tests::render_plane;
    use crate::fusion::TsdfConfig;

    #[test]
    fn initial_volume_has_y_down_and_z_forward() {
        // Camera pitched 30° down: gravity in the camera has a +z component.
        let pitch = 30f64.to_radians();
        let gravity_in_camera = Vector3::new(0.0, pitch.cos(), pitch.sin());
        let config = MovingVolumeConfig::default();
        let pose = initial_volume_from_camera(Some(gravity_in_camera), 1.28, &config);
        assert!((pose.rotation * gravity_in_camera - Vector3::y()).norm() < 1e-12);
        let forward = pose.rotation * Vector3::z();
        assert!(forward.x.abs() < 1e-12 && forward.z > 0.8, "{forward}");
        // A quarter of the edge below the top face, in the middle across and along.
        assert!((pose.translation.vector - Vector3::new(0.64, 0.32, 0.64)).norm() < 1e-12);
        assert!(camera_heading(&pose).abs() < 1e-12);
        // Right-handed map rotation: volume y (down) is map −z.
        assert!((map_from_volume_rotation() * Vector3::y() + Vector3::z()).norm() < 1e-12);
    }

    #[test]
    fn ground_that_falls_away_below_a_robot_head_stays_inside_the_cube() {
        // RPBP's head camera 0.47 m above its feet, pitched 45° down, in the default 1.28 m cube.
        let pitch = 45f64.to_radians();
        let gravity_in_camera = Vector3::new(0.0, pitch.cos(), pitch.sin());
        let inside = |config: &MovingVolumeConfig, drop_m: f64, ahead_m: f64| {
            let camera = initial_volume_from_camera(Some(gravity_in_camera), 1.28, config).translation.vector;
            // Volume y is down, z forward.
            let ground = camera + Vector3::new(0.0, 0.47 + drop_m, ahead_m);
            ground.iter().all(|c| (0.0..1.28).contains(c))
        };
        let default = MovingVolumeConfig::default();
        // Looking down off a 0.4 m ledge, 0.5 m ahead.
        assert!(inside(&default, 0.4, 0.5));
        // With the camera in the middle of the cube (J 5.2), 0.17 m of it lie below the feet.
        let middle = MovingVolumeConfig { nominal_position_fraction: [0.5; 3], ..default };
        assert!(inside(&middle, 0.15, 0.5) && !inside(&middle, 0.4, 0.5));
    }

    #[test]
    fn remaps_follow_distance_and_heading_thresholds() {
        let config = MovingVolumeConfig { distance_threshold_m: 0.1, angle_threshold_deg: 20.0, ..MovingVolumeConfig::default() };
        let start = initial_volume_from_camera(None, 1.28, &config);
        assert!(plan_remap(&config, &start, 1.28, 0.04).is_none());
        // Moved 0.25 m along x: block-quantised translation back toward the middle.
        let moved = Isometry3::translation(0.25, 0.0, 0.0) * start;
        let remap = plan_remap(&config, &moved, 1.28, 0.04).unwrap();
        assert!(remap.rotation.angle() < 1e-12);
        assert!((remap.translation.x + 0.24).abs() < 1e-9, "{}", remap.translation.x);
        let nominal = config.nominal_position(1.28);
        let after = remap * moved;
        assert!((after.translation.vector - nominal).norm() < 0.021);
        // Turned 40° about the vertical: rotation about y only, heading back to 0, y stays vertical.
        let turned = Isometry3::from_parts(
            start.translation,
            UnitQuaternion::from_axis_angle(&Vector3::y_axis(), 40f64.to_radians()) * start.rotation,
        );
        let remap = plan_remap(&config, &turned, 1.28, 0.04).unwrap();
        let after = remap * turned;
        assert!(camera_heading(&after).abs() < 1e-9);
        assert!((remap.rotation * Vector3::y() - Vector3::y()).norm() < 1e-12);
        assert!((after.translation.vector - nominal).norm() < 1e-9);
        let disabled = MovingVolumeConfig { enabled: false, ..config };
        assert!(plan_remap(&disabled, &turned, 1.28, 0.04).is_none());
    }

    fn plane_volume() -> (TsdfVolume, Isometry3<f64>) {
        let config = TsdfConfig { voxel_size_m: 0.01, size_m: 1.28, ..TsdfConfig::default() };
        let mut volume = TsdfVolume::new(config).unwrap();
        let intrinsics = Intrinsics::primesense_default().scaled(0.5);
        let pose = crate::fusion::tests::looking_down_pose(Vector3::new(0.64, 0.3, 0.64));
        let depth = render_plane(&intrinsics, &pose, Vector3::y(), 0.9);
        volume.integrate(&depth, &intrinsics, &pose).unwrap();
        (volume, pose)
    }

    #[test]
    fn block_translation_is_lossless() {
        let (mut volume, _) = plane_volume();
        let before = volume.voxel(64, 89, 64).unwrap();
        let remap = Isometry3::translation(0.08, -0.16, 0.0);
        remap_tsdf(&mut volume, &remap);
        assert_eq!(volume.voxel(72, 73, 64).unwrap(), before);
    }

    #[test]
    fn rotation_resampling_keeps_the_surface() {
        let (mut volume, _) = plane_volume();
        let rotation = UnitQuaternion::from_axis_angle(&Vector3::y_axis(), 0.5);
        let centre = Vector3::repeat(0.64);
        let remap = Isometry3::from_parts(Translation3::from(centre - rotation * centre), rotation);
        remap_tsdf(&mut volume, &remap);
        assert!(volume.block_count() > 20);
        // A horizontal plane stays at y = 0.9 under rotation about the vertical through the centre.
        let surface = volume.surface_voxels(0.2);
        assert!(surface.len() > 100);
        assert!(surface.iter().all(|p| (p.y - 0.9).abs() < 0.01), "surface moved");
    }

    #[test]
    fn the_volume_is_sized_and_placed_around_a_desk_ahead() {
        // A level camera, a 1.6 m wide desk top 0.5 m below from 0.8 m to 2.4 m ahead, and a wall behind it.
        let mut points = Vec::new();
        for i in 0..80 {
            for j in 0..80 {
                points.push(Vector3::new(-0.8 + 0.02 * f64::from(i), 0.5, 0.8 + 0.02 * f64::from(j)));
            }
        }
        let sizing = VolumeSizing::default();
        let fit = size_volume_to_depth(&points, Some(Vector3::y()), 0.04, &sizing).unwrap();
        // Extent: 1.6 m + 2 × 0.1 m margin along z (the camera at z = 0 included), 1.6 + 0.2 along x.
        assert!((fit.edge_m - 2.6).abs() < 0.041, "{fit:?}");
        assert!((fit.edge_m / 0.04 - (fit.edge_m / 0.04).round()).abs() < 1e-9);
        // The camera sits a quarter of the edge from the back face (no closer), centred across,
        // above the desk: most of the desk is inside.
        let [fx, fy, fz] = fit.nominal_position_fraction;
        assert!((fx - 0.5).abs() < 0.01 && (fz - 0.25).abs() < 1e-9 && fy < 0.5, "{fit:?}");
        assert!(fit.inside_share > 0.65, "{fit:?}");
        let at_back =
            size_volume_to_depth(&points, Some(Vector3::y()), 0.04, &VolumeSizing { min_camera_fraction: 0.0, ..sizing }).unwrap();
        assert!(at_back.inside_share > 0.95 && at_back.nominal_position_fraction[2] < 0.1, "{at_back:?}");
        // The default robot cube around the camera holds much less of it.
        let robot = initial_volume_from_camera(Some(Vector3::y()), 1.28, &MovingVolumeConfig::default());
        assert!(share_inside(&points, &robot, 1.28) < 0.2);
        // Far outliers (1.5 %) do not inflate the cube; nothing to fit gives None.
        let mut with_outliers = points.clone();
        with_outliers.extend((0..100).map(|k| Vector3::new(0.0, 0.0, 8.0 + f64::from(k) * 0.01)));
        let trimmed = size_volume_to_depth(&with_outliers, Some(Vector3::y()), 0.04, &sizing).unwrap();
        assert!(trimmed.edge_m <= fit.edge_m + 0.2, "{trimmed:?}");
        assert!(size_volume_to_depth(&[], None, 0.04, &sizing).is_none());
    }

    #[test]
    fn a_robot_view_keeps_the_minimum_cube_and_clamps_huge_scenes() {
        // Ground 0.45 m below, 0.2–0.8 m ahead: fits in the 1.28 m minimum.
        let points: Vec<_> = (0..100).map(|k| Vector3::new(0.0, 0.45, 0.2 + 0.006 * f64::from(k))).collect();
        let sizing = VolumeSizing::default();
        let fit = size_volume_to_depth(&points, Some(Vector3::y()), 0.04, &sizing).unwrap();
        assert_eq!(fit.edge_m, 1.28);
        assert_eq!(fit.inside_share, 1.0);
        // A hall 10 m deep: the edge stops at max_edge_m and the camera stays inside the cube.
        let far: Vec<_> = (0..100).map(|k| Vector3::new(0.0, 1.0, 0.1 * f64::from(k))).collect();
        let fit = size_volume_to_depth(&far, Some(Vector3::y()), 0.04, &sizing).unwrap();
        assert_eq!(fit.edge_m, 4.0);
        assert!(fit.nominal_position_fraction.iter().all(|f| (0.0..=1.0).contains(f)), "{fit:?}");
        assert!(fit.inside_share < 0.5);
    }

    #[test]
    fn depth_points_respect_the_depth_range() {
        let intrinsics = Intrinsics::new(4, 1, 2.0, 2.0, 1.5, 0.0).unwrap();
        let depth = DepthImage::new(4, 1, vec![0.1, 1.0, f32::NAN, 5.0]).unwrap();
        let points = depth_points(&depth, &intrinsics, 0.2, 3.0, 1);
        assert_eq!(points.len(), 1);
        assert!((points[0] - intrinsics.back_project(1.0, 0.0, 1.0)).norm() < 1e-12);
    }
}

//! Patch tracking (J 5.2 step 6): keeps the patch map consistent with the moving volume. Patches are
//! stored in the fixed `map` frame, so a volume remap moves them by exactly the remap's rigid
//! transform relative to the volume; what changes is the volume-frame grid they are gridded on. On a
//! remap the grid is replaced (new `volume_from_map`), patches that left the cube are dropped
//! (optionally also those more than dcp behind the camera) and cells are re-associated. After a
//! tracking loss the whole map is reset (J 5.2, end of the section).

use nalgebra::{Point3, Vector3};

use crate::patch_map::{PatchMap, VolumeGrid};
use patchwalk_fusion::tracking::{FrameReport, Tracker, TrackingStatus};

/// Patch-tracking parameters (J 4.3, J 5.2).
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize, serde::Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct PatchTrackingConfig {
    /// Vg: grid cells per side on the volume xz-plane (J 4.3: "we typically use Vg = 8").
    pub cells_per_side: usize,
    /// dcp: drop patches farther than this behind the camera, horizontally (m). J 5.2 makes it
    /// optional and gives no value; `None` keeps everything inside the volume.
    pub drop_behind_camera_m: Option<f64>,
}

impl Default for PatchTrackingConfig {
    fn default() -> Self {
        Self { cells_per_side: 8, drop_behind_camera_m: None }
    }
}

/// What patch tracking did in one frame.
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub struct PatchTrackingUpdate {
    /// The map was cleared (tracking loss).
    pub reset: bool,
    /// The grid moved with a volume remap (or re-initialisation).
    pub regridded: bool,
    pub dropped_outside_volume: usize,
    pub dropped_behind_camera: usize,
}

/// The grid of the tracker's current volume (map → volume from the tracker's pose bookkeeping).
pub fn volume_grid(tracker: &Tracker, cells_per_side: usize) -> VolumeGrid {
    VolumeGrid {
        volume_from_map: tracker.map_from_volume().inverse(),
        edge_m: f64::from(tracker.volume().edge_m()),
        cells_per_side: cells_per_side.max(1),
    }
}

/// J 5.2 step 6 for one processed frame: reset on loss; on a remap, re-grid, drop patches outside
/// the volume (and optionally more than dcp behind the camera).
pub fn track_patches(map: &mut PatchMap, report: &FrameReport, tracker: &Tracker, config: &PatchTrackingConfig) -> PatchTrackingUpdate {
    let mut update = PatchTrackingUpdate::default();
    let lost = matches!(report.status, TrackingStatus::Lost(_));
    if lost {
        map.retain(|_| false);
        update.reset = true;
    }
    let moved = lost || report.remap.is_some() || report.status == TrackingStatus::Initialized;
    if moved {
        map.set_grid(volume_grid(tracker, config.cells_per_side));
        update.regridded = true;
        update.dropped_outside_volume = map.drop_outside_volume();
    }
    if let Some(dcp) = config.drop_behind_camera_m {
        let map_from_camera = report.map_from_camera;
        let camera = map_from_camera.translation.vector;
        // Horizontal forward direction in the map (z up).
        let forward = map_from_camera.rotation * Vector3::z();
        if let Some(forward) = Vector3::new(forward.x, forward.y, 0.0).try_normalize(1e-6) {
            update.dropped_behind_camera = map.retain(|p| (p.patch.center - camera).dot(&forward) >= -dcp);
        }
    }
    update
}

/// Where the surface seen by a birds-eye view lies under a point given in the map frame: the
/// raycast surface point (map frame) at the pixel the point projects to, if any.
pub fn birds_eye_surface_under(
    tracker: &Tracker,
    view: &patchwalk_fusion::raycast::BirdsEyeView,
    point_in_map: &Vector3<f64>,
) -> Option<Vector3<f64>> {
    let map_from_birds_eye = tracker.map_from_birds_eye(view);
    let point_in_birds_eye = map_from_birds_eye.inverse() * Point3::from(*point_in_map);
    let (u, v) = view.intrinsics.pixel_of(&point_in_birds_eye.coords)?;
    let depth = f64::from(view.depth.get(u, v)?);
    let surface_in_birds_eye = view.intrinsics.back_project(u as f64, v as f64, depth);
    Some((map_from_birds_eye * Point3::from(surface_in_birds_eye)).coords)
}

#[cfg(test)]
mod tests {
    use super::*;
    use nalgebra::{Isometry3, Matrix3, Rotation3, Translation3, UnitQuaternion, Vector2};
    use patchwalk_fusion::camera::{DepthImage, Intrinsics};
    use patchwalk_fusion::fusion::TsdfConfig;
    use patchwalk_fusion::tracking::{Frame, TrackerConfig};
    use patchwalk_fusion::volume::MovingVolumeConfig;
    use patchwalk_spl::patch::{BoundaryType, Patch, SurfaceType};
    use patchwalk_spl::transform::transform_patch;

    /// Rocky terrain height (world z up): Gaussian bumps on a 0.3 m lattice with pseudo-random
    /// amplitudes, plus gentle ridges (so ICP is constrained in every direction).
    fn height(x: f64, y: f64) -> f64 {
        let spacing = 0.3;
        let (ci, cj) = ((x / spacing).round() as i64, (y / spacing).round() as i64);
        let mut h = 0.01 * (4.0 * x).sin() * (3.0 * y).cos();
        for i in ci - 1..=ci + 1 {
            for j in cj - 1..=cj + 1 {
                let (cx, cy, a) = bump(i, j, spacing);
                h += a * (-((x - cx).powi(2) + (y - cy).powi(2)) / (2.0 * 0.07f64.powi(2))).exp();
            }
        }
        h
    }

    fn bump(i: i64, j: i64, spacing: f64) -> (f64, f64, f64) {
        let hash = ((i as f64) * 12.9898 + (j as f64) * 78.233).sin() * 43758.5453;
        (i as f64 * spacing, j as f64 * spacing, 0.03 + 0.05 * (hash - hash.floor()))
    }

    /// Ray-marched depth image of the terrain (camera z forward; depth = z in the camera).
    fn render(intrinsics: &Intrinsics, world_from_camera: &Isometry3<f64>) -> DepthImage {
        let origin = world_from_camera.translation.vector;
        let mut depth = vec![f32::NAN; intrinsics.width * intrinsics.height];
        for v in 0..intrinsics.height {
            for u in 0..intrinsics.width {
                let ray = world_from_camera.rotation * intrinsics.back_project(u as f64, v as f64, 1.0);
                let gap = |t: f64| {
                    let p = origin + ray * t;
                    p.z - height(p.x, p.y)
                };
                let (mut t0, mut t) = (0.1, 0.1);
                while t < 4.0 && gap(t) > 0.0 {
                    t0 = t;
                    t += (0.5 * gap(t)).max(0.002);
                }
                if t >= 4.0 {
                    continue;
                }
                let mut t1 = t;
                for _ in 0..20 {
                    let mid = 0.5 * (t0 + t1);
                    if gap(mid) > 0.0 {
                        t0 = mid;
                    } else {
                        t1 = mid;
                    }
                }
                depth[v * intrinsics.width + u] = (0.5 * (t0 + t1)) as f32;
            }
        }
        DepthImage::new(intrinsics.width, intrinsics.height, depth).unwrap()
    }

    /// Camera pose on the path: walking along world +y at 0.7 m, pitched 50° down, heading swaying.
    fn camera_pose(k: usize) -> Isometry3<f64> {
        let s = k as f64;
        let heading = 0.35 * (s / 5.0).sin();
        let pitch = 50f64.to_radians();
        let forward = Vector3::new(-heading.sin(), heading.cos(), 0.0);
        let z = forward * pitch.cos() - Vector3::z() * pitch.sin();
        let x = forward.cross(&Vector3::z());
        let y = z.cross(&x);
        let rotation = Rotation3::from_matrix_unchecked(Matrix3::from_columns(&[x, y, z]));
        let position = Vector3::new(0.08 * (s / 4.0).sin(), 0.03 * s, 0.7);
        Isometry3::from_parts(Translation3::from(position), UnitQuaternion::from_rotation_matrix(&rotation))
    }

    #[test]
    fn patches_keep_their_world_pose_through_remaps() {
        let intrinsics = Intrinsics::primesense_default().scaled(0.25);
        let mut config = TrackerConfig {
            tsdf: TsdfConfig { voxel_size_m: 0.01, size_m: 1.28, ..TsdfConfig::default() },
            moving_volume: MovingVolumeConfig {
                distance_threshold_m: 0.12,
                angle_threshold_deg: 10.0,
                nominal_position_fraction: [0.5, 0.25, 0.5],
                enabled: true,
            },
            model_scale: 0.5,
            ..TrackerConfig::default()
        };
        config.icp.iterations = [10, 8, 4];
        config.icp.min_inliers = 200;
        let mut tracker = Tracker::new(config, intrinsics).unwrap();
        let patch_config = PatchTrackingConfig::default();
        let mut map = PatchMap::new("map", volume_grid(&tracker, patch_config.cells_per_side));
        let mut map_from_world = Isometry3::identity();
        let (mut translations, mut rotations, mut dropped) = (0, 0, 0);
        let mut patches_in_world = Vec::new();
        for k in 0..30 {
            let world_from_camera = camera_pose(k);
            let depth = render(&intrinsics, &world_from_camera);
            let gravity_in_camera = world_from_camera.rotation.inverse() * -Vector3::z();
            let report = tracker
                .process(Frame {
                    depth: &depth,
                    gravity_in_camera: Some(gravity_in_camera),
                    external_map_from_camera: None,
                    timestamp: None,
                })
                .unwrap();
            assert!(matches!(report.status, TrackingStatus::Initialized | TrackingStatus::Tracked), "frame {k}: {:?}", report.status);
            if k == 0 {
                map_from_world = report.map_from_camera * world_from_camera.inverse();
            }
            if let Some(remap) = report.remap {
                if remap.rotation.angle() > 1e-9 {
                    rotations += 1;
                } else {
                    translations += 1;
                }
            }
            let update = track_patches(&mut map, &report, &tracker, &patch_config);
            assert!(!update.reset);
            dropped += update.dropped_outside_volume;
            if k == 2 {
                // Patches on the rock tops ahead of the camera, posed in the world, stored in the map.
                for i in -1..=1 {
                    for j in 1..=4 {
                        let (cx, cy, _) = bump(i, j, 0.3);
                        let centre = Vector3::new(cx, cy, height(cx, cy));
                        let patch =
                            Patch::new(SurfaceType::Plane, BoundaryType::Circle, vec![0.04], Vector2::zeros(), Vector3::zeros(), centre)
                                .unwrap();
                        let in_map = transform_patch(&patch, &map_from_world).unwrap();
                        let id = map.insert(in_map, k as f64);
                        patches_in_world.push((id, centre));
                    }
                }
            }
        }
        assert!(translations >= 2 && rotations >= 1, "remaps: {translations} translations, {rotations} rotations");
        // Tracking drift over the path is small (ground truth known).
        let world_from_map = map_from_world.inverse();
        let final_error = ((world_from_map * tracker.map_from_camera()).translation.vector - camera_pose(29).translation.vector).norm();
        assert!(final_error < 0.005, "camera drift {final_error}");
        // Every remaining patch sits on the fused surface seen from the birds-eye camera after all
        // the remaps, and maps back to its world pose.
        let view = tracker.birds_eye();
        let mut checked = 0;
        for mapped in map.patches() {
            let Some((_, centre_in_world)) = patches_in_world.iter().find(|(id, _)| *id == mapped.id) else { continue };
            let back_in_world = world_from_map * Point3::from(mapped.patch.center);
            assert!((back_in_world.coords - centre_in_world).norm() < 1e-9);
            let Some(surface) = birds_eye_surface_under(&tracker, &view, &mapped.patch.center) else { continue };
            let offset = surface.z - mapped.patch.center.z;
            assert!(offset.abs() < 0.002, "patch {} is {offset} m off the fused surface", mapped.id);
            checked += 1;
        }
        eprintln!("remaps {translations}+{rotations}, dropped {dropped}, checked {checked} of {} patches, drift {final_error}", map.len());
        assert!(checked >= 4, "only {checked} patches checked");
    }

    #[test]
    fn loss_resets_and_dcp_drops_patches_behind() {
        let intrinsics = Intrinsics::primesense_default().scaled(0.25);
        // Every failed frame a real loss (no short losses), as J 5.2 describes it.
        let mut config = TrackerConfig::default();
        config.relocalisation.max_lost_frames = 0;
        let mut tracker = Tracker::new(config, intrinsics).unwrap();
        let depth = render(&intrinsics, &camera_pose(0));
        let empty = DepthImage::new(intrinsics.width, intrinsics.height, vec![f32::NAN; intrinsics.width * intrinsics.height]).unwrap();
        let report =
            tracker.process(Frame { depth: &depth, gravity_in_camera: None, external_map_from_camera: None, timestamp: None }).unwrap();
        let mut map = PatchMap::new("map", volume_grid(&tracker, 8));
        let camera = report.map_from_camera.translation.vector;
        let forward = report.map_from_camera.rotation * Vector3::z();
        let forward = Vector3::new(forward.x, forward.y, 0.0).normalize();
        for offset in [-0.5, -0.1, 0.3] {
            let centre = camera + forward * offset - Vector3::z() * 0.2;
            map.insert(
                Patch::new(SurfaceType::Plane, BoundaryType::Circle, vec![0.03], Vector2::zeros(), Vector3::zeros(), centre).unwrap(),
                0.0,
            );
        }
        let config = PatchTrackingConfig { drop_behind_camera_m: Some(0.3), ..PatchTrackingConfig::default() };
        let update = track_patches(&mut map, &report, &tracker, &config);
        assert_eq!(update.dropped_behind_camera, 1);
        assert_eq!(map.len(), 2);
        let report =
            tracker.process(Frame { depth: &empty, gravity_in_camera: None, external_map_from_camera: None, timestamp: None }).unwrap();
        assert!(matches!(report.status, TrackingStatus::Lost(_)));
        let update = track_patches(&mut map, &report, &tracker, &config);
        assert!(update.reset && map.is_empty());
    }
}

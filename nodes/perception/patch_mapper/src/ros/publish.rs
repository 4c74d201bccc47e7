//! Output messages of the patch_mapper node built from the pipeline's state: `PatchArray` (every patch
//! by its minimal parameters with covariance), `MarkerArray` (patch surfaces and outlines for RViz,
//! coloured by surface type) and the birds-eye `PointCloud2`, all in the gravity-aligned `map` frame.

use nalgebra::{Isometry3, Point3, Vector2};

use patchwalk_mapping::patch_map::PatchMap;
use patchwalk_msgs::builtin_interfaces::msg::Time;
use patchwalk_msgs::geometry_msgs::msg::{Point, Pose, Quaternion, Vector3};
use patchwalk_msgs::msg;
use patchwalk_msgs::sensor_msgs::msg::{PointCloud2, PointField};
use patchwalk_msgs::std_msgs::msg::{ColorRGBA, Header};
use patchwalk_msgs::visualization_msgs::msg::{Marker, MarkerArray};
use patchwalk_ros::patch_msg::{self, pose_from_isometry};
use patchwalk_spl::patch::Patch;

/// Seconds since the epoch -> `builtin_interfaces/Time` (saturating; non-finite -> 0).
pub fn time_from_seconds(seconds: f64) -> Time {
    if !(seconds.is_finite() && seconds > 0.0) {
        return Time::default();
    }
    let sec = seconds.floor().min(f64::from(i32::MAX));
    let nanosec = ((seconds - sec) * 1e9).round().clamp(0.0, 999_999_999.0);
    Time { sec: sec as i32, nanosec: nanosec as u32 }
}

/// `builtin_interfaces/Time` -> seconds.
pub fn seconds_from_time(time: &Time) -> f64 {
    f64::from(time.sec) + f64::from(time.nanosec) * 1e-9
}

/// One patch of the map -> `patchwalk_msgs/Patch` (covariance row-major p × p over [d, k, r, c]).
pub fn patch_msg(id: u64, patch: &Patch, first_seen: f64, last_seen: f64) -> msg::Patch {
    patch_msg::msg_from_patch(u32::try_from(id).unwrap_or(u32::MAX), patch, time_from_seconds(first_seen), time_from_seconds(last_seen))
}

/// The whole map with the camera pose; `stamp` is the depth frame's stamp.
pub fn patch_array(map: &PatchMap, map_from_camera: &Isometry3<f64>, stamp: &Time) -> msg::PatchArray {
    msg::PatchArray {
        header: Header { stamp: stamp.clone(), frame_id: map.frame_id.clone() },
        camera_pose: pose_from_isometry(map_from_camera),
        patches: map.patches().iter().map(|m| patch_msg(m.id, &m.patch, m.first_seen, m.last_seen)).collect(),
    }
}

/// Colour per surface type (index = Patch.msg constant).
const TYPE_COLOURS: [[f32; 3]; 7] = [
    [0.90, 0.30, 0.20], // elliptic paraboloid
    [0.60, 0.20, 0.80], // hyperbolic paraboloid
    [0.95, 0.65, 0.10], // cylindric paraboloid
    [0.95, 0.90, 0.20], // circular paraboloid
    [0.20, 0.70, 0.30], // plane
    [0.20, 0.50, 0.95], // sphere
    [0.10, 0.85, 0.85], // circular cylinder
];

fn colour(patch: &Patch, alpha: f32) -> ColorRGBA {
    let [r, g, b] = TYPE_COLOURS.get(patch.surface as usize).copied().unwrap_or([0.7, 0.7, 0.7]);
    ColorRGBA { r, g, b, a: alpha }
}

fn point(v: &nalgebra::Vector3<f64>) -> Point {
    Point { x: v.x, y: v.y, z: v.z }
}

/// Boundary outline in (u, v): per direction the largest radius still inside (bisection), so it
/// works for every boundary type alike.
fn outline_uv(patch: &Patch, directions: usize) -> Vec<Vector2<f64>> {
    let reach = patch.boundary_half_extents().norm() * 1.5 + 1e-6;
    (0..=directions)
        .map(|i| {
            let angle = std::f64::consts::TAU * i as f64 / directions as f64;
            let dir = Vector2::new(angle.cos(), angle.sin());
            let (mut inside, mut outside) = (0.0, reach);
            for _ in 0..20 {
                let mid = 0.5 * (inside + outside);
                if patch.contains_uv(&(dir * mid)) {
                    inside = mid;
                } else {
                    outside = mid;
                }
            }
            dir * inside
        })
        .collect()
}

/// RViz markers: a DELETEALL, then per patch a triangle fan of its surface and its outline.
pub fn markers(map: &PatchMap, stamp: &Time) -> MarkerArray {
    let header = Header { stamp: stamp.clone(), frame_id: map.frame_id.clone() };
    let mut markers = vec![Marker { header: header.clone(), action: Marker::DELETEALL, ..Default::default() }];
    let identity = Pose { orientation: Quaternion { x: 0.0, y: 0.0, z: 0.0, w: 1.0 }, ..Default::default() };
    for mapped in map.patches() {
        let patch = &mapped.patch;
        let outline: Vec<nalgebra::Vector3<f64>> = outline_uv(patch, 24).iter().filter_map(|uv| patch.explicit_world(uv)).collect();
        let Some(centre) = patch.explicit_world(&Vector2::zeros()) else { continue };
        let id = i32::try_from(mapped.id % (i32::MAX as u64 / 2)).unwrap_or(0) * 2;
        let mut surface = Vec::with_capacity(outline.len() * 3);
        for pair in outline.windows(2) {
            surface.extend([point(&centre), point(&pair[0]), point(&pair[1])]);
        }
        markers.push(Marker {
            header: header.clone(),
            ns: "patch_surfaces".into(),
            id,
            type_: Marker::TRIANGLE_LIST,
            pose: identity.clone(),
            scale: Vector3 { x: 1.0, y: 1.0, z: 1.0 },
            color: colour(patch, 0.7),
            points: surface,
            ..Default::default()
        });
        markers.push(Marker {
            header: header.clone(),
            ns: "patch_outlines".into(),
            id: id + 1,
            type_: Marker::LINE_STRIP,
            pose: identity.clone(),
            scale: Vector3 { x: 0.003, y: 0.0, z: 0.0 },
            color: colour(patch, 1.0),
            points: outline.iter().map(point).collect(),
            ..Default::default()
        });
    }
    MarkerArray { markers }
}

/// Unorganized xyz float32 cloud in `frame_id`.
pub fn point_cloud(points: &[Point3<f32>], stamp: &Time, frame_id: &str) -> PointCloud2 {
    let field = |name: &str, offset: u32| PointField { name: name.into(), offset, datatype: PointField::FLOAT32, count: 1 };
    let data: Vec<u8> = points.iter().flat_map(|p| [p.x, p.y, p.z]).flat_map(f32::to_le_bytes).collect();
    let width = u32::try_from(points.len()).unwrap_or(u32::MAX);
    PointCloud2 {
        header: Header { stamp: stamp.clone(), frame_id: frame_id.into() },
        height: 1,
        width,
        fields: vec![field("x", 0), field("y", 4), field("z", 8)],
        is_bigendian: false,
        point_step: 12,
        row_step: width.saturating_mul(12),
        data,
        is_dense: true,
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use nalgebra::{DMatrix, Vector3 as V3};
    use patchwalk_mapping::patch_map::VolumeGrid;
    use patchwalk_spl::patch::{BoundaryType, SurfaceType};

    fn plane_patch() -> Patch {
        let mut patch = Patch::from_params(SurfaceType::Plane, BoundaryType::Circle, &[0.05, 0.0, 0.0, 1.0, 2.0, 3.0]).unwrap();
        let p = patch.dof();
        patch.covariance = DMatrix::from_fn(p, p, |r, c| (r * 10 + c) as f64);
        patch
    }

    #[test]
    fn patches_markers_and_clouds_carry_the_map() {
        let grid = VolumeGrid { volume_from_map: Isometry3::identity(), edge_m: 10.0, cells_per_side: 8 };
        let mut map = PatchMap::new("map", grid);
        map.insert(plane_patch(), 12.5);
        let stamp = time_from_seconds(12.5);
        assert_eq!((stamp.sec, stamp.nanosec), (12, 500_000_000));
        assert_eq!(seconds_from_time(&stamp), 12.5);
        let array = patch_array(&map, &Isometry3::translation(0.0, 0.0, 1.0), &stamp);
        assert_eq!(array.header.frame_id, "map");
        assert_eq!(array.camera_pose.position.z, 1.0);
        let patch = &array.patches[0];
        assert_eq!((patch.surface, patch.boundary), (msg::Patch::PLANE, msg::Patch::CIRCLE));
        assert_eq!(patch.center, [1.0, 2.0, 3.0]);
        let p = 6;
        assert_eq!(patch.covariance.len(), p * p);
        // Row-major: element (0, 1) is 1, (1, 0) is 10.
        assert_eq!((patch.covariance[1], patch.covariance[p]), (1.0, 10.0));
        assert!(patch.curvatures.is_empty());
        let markers = markers(&map, &stamp);
        assert_eq!(markers.markers.len(), 3);
        assert_eq!(markers.markers[0].action, Marker::DELETEALL);
        // The outline of a 5 cm circle lies 5 cm from the centre.
        for q in &markers.markers[2].points {
            let r = V3::new(q.x - 1.0, q.y - 2.0, q.z - 3.0).norm();
            assert!((r - 0.05).abs() < 1e-4, "{r}");
        }
        assert_eq!(markers.markers[1].points.len() % 3, 0);
        let cloud = point_cloud(&[Point3::new(1.0, 2.0, 3.0)], &stamp, "map");
        assert_eq!((cloud.width, cloud.data.len()), (1, 12));
        assert_eq!(f32::from_le_bytes([cloud.data[8], cloud.data[9], cloud.data[10], cloud.data[11]]), 3.0);
    }
}

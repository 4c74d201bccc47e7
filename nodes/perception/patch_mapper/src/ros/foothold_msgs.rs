//! Output messages of the foothold stage, all in the fixed frame: the predicted footholds as
//! `geometry_msgs/PoseArray` (orientation: z along the surface normal), as RViz markers coloured by
//! score, and as an unorganized `sensor_msgs/PointCloud2` with a `score` field (so the scores travel
//! in a standard type); the coarse route as `nav_msgs/Path` (the body path, heading along it) and its
//! markers (body path, left and right soles).

use nalgebra::{Isometry3, Translation3, UnitQuaternion, Vector3};
use patchwalk_msgs::builtin_interfaces::msg::Time;
use patchwalk_msgs::geometry_msgs::msg::{Point, Pose, PoseArray, PoseStamped, Vector3 as Vector3Msg};
use patchwalk_msgs::nav_msgs::msg::Path;
use patchwalk_msgs::sensor_msgs::msg::{PointCloud2, PointField};
use patchwalk_msgs::std_msgs::msg::{ColorRGBA, Header};
use patchwalk_msgs::visualization_msgs::msg::{Marker, MarkerArray};
use patchwalk_ros::patch_msg::pose_from_isometry;
use patchwalk_route::Route;

use patch_mapper::foothold_points::ScoredHold;

fn header(stamp: &Time, frame_id: &str) -> Header {
    Header { stamp: stamp.clone(), frame_id: frame_id.to_string() }
}

fn point(v: &Vector3<f64>) -> Point {
    Point { x: v.x, y: v.y, z: v.z }
}

fn point_of(p: &[f64; 3]) -> Point {
    Point { x: p[0], y: p[1], z: p[2] }
}

/// The pose of a hold: at its position, z along its normal (the shortest rotation from up).
pub fn hold_pose(hold: &ScoredHold) -> Pose {
    let rotation = UnitQuaternion::rotation_between(&Vector3::z(), &hold.normal).unwrap_or_else(UnitQuaternion::identity);
    pose_from_isometry(&Isometry3::from_parts(Translation3::from(hold.position), rotation))
}

/// `~/footholds`: one pose per hold.
pub fn pose_array(holds: &[ScoredHold], stamp: &Time, frame_id: &str) -> PoseArray {
    PoseArray { header: header(stamp, frame_id), poses: holds.iter().map(hold_pose).collect() }
}

/// Score colour: red at 0, yellow at 0.5, green at 1.
pub fn score_colour(score: f64) -> ColorRGBA {
    let s = score.clamp(0.0, 1.0) as f32;
    ColorRGBA { r: (2.0 * (1.0 - s)).min(1.0), g: (2.0 * s).min(1.0), b: 0.1, a: 0.9 }
}

/// Sphere diameter of a hold marker (m): a foot's width.
const HOLD_MARKER_M: f64 = 0.03;
/// Length of a normal's line (m).
const NORMAL_LINE_M: f64 = 0.05;

/// `~/footholds/markers`: DELETEALL, the holds as one sphere list coloured by score, their normals.
pub fn hold_markers(holds: &[ScoredHold], stamp: &Time, frame_id: &str) -> MarkerArray {
    let header = header(stamp, frame_id);
    let identity = pose_from_isometry(&Isometry3::identity());
    let mut markers = vec![Marker { header: header.clone(), action: Marker::DELETEALL, ..Default::default() }];
    if holds.is_empty() {
        return MarkerArray { markers };
    }
    markers.push(Marker {
        header: header.clone(),
        ns: "footholds".into(),
        id: 0,
        type_: Marker::SPHERE_LIST,
        pose: identity.clone(),
        scale: Vector3Msg { x: HOLD_MARKER_M, y: HOLD_MARKER_M, z: HOLD_MARKER_M },
        color: score_colour(1.0),
        points: holds.iter().map(|h| point(&h.position)).collect(),
        colors: holds.iter().map(|h| score_colour(h.score)).collect(),
        ..Default::default()
    });
    markers.push(Marker {
        header,
        ns: "foothold_normals".into(),
        id: 1,
        type_: Marker::LINE_LIST,
        pose: identity,
        scale: Vector3Msg { x: 0.003, y: 0.0, z: 0.0 },
        color: ColorRGBA { r: 0.9, g: 0.9, b: 0.9, a: 1.0 },
        points: holds.iter().flat_map(|h| [point(&h.position), point(&(h.position + h.normal * NORMAL_LINE_M))]).collect(),
        ..Default::default()
    });
    MarkerArray { markers }
}

/// `~/footholds/scored`: x, y, z, score as float32, one point per hold.
pub fn scored_cloud(holds: &[ScoredHold], stamp: &Time, frame_id: &str) -> PointCloud2 {
    let field = |name: &str, offset: u32| PointField { name: name.into(), offset, datatype: PointField::FLOAT32, count: 1 };
    let data: Vec<u8> = holds
        .iter()
        .flat_map(|h| [h.position.x as f32, h.position.y as f32, h.position.z as f32, h.score as f32])
        .flat_map(f32::to_le_bytes)
        .collect();
    let width = u32::try_from(holds.len()).unwrap_or(u32::MAX);
    PointCloud2 {
        header: header(stamp, frame_id),
        height: 1,
        width,
        fields: vec![field("x", 0), field("y", 4), field("z", 8), field("score", 12)],
        is_bigendian: false,
        point_step: 16,
        row_step: width.saturating_mul(16),
        data,
        is_dense: true,
    }
}

/// `~/route`: the body path, each pose heading towards the next vertex (the last keeps the
/// previous heading), z up.
pub fn route_path(route: &Route, stamp: &Time, frame_id: &str) -> Path {
    let header = header(stamp, frame_id);
    let points: Vec<Vector3<f64>> = route.body_path.iter().map(|p| Vector3::new(p[0], p[1], p[2])).collect();
    let mut yaw = 0.0;
    let poses = points
        .iter()
        .enumerate()
        .map(|(i, p)| {
            if let Some(next) = points.get(i + 1) {
                let d = next - p;
                if d.x.hypot(d.y) > 1e-9 {
                    yaw = d.y.atan2(d.x);
                }
            }
            let pose = Isometry3::from_parts(Translation3::from(*p), UnitQuaternion::from_axis_angle(&Vector3::z_axis(), yaw));
            PoseStamped { header: header.clone(), pose: pose_from_isometry(&pose) }
        })
        .collect();
    Path { header, poses }
}

const PATH_COLOUR: ColorRGBA = ColorRGBA { r: 0.16, g: 0.55, b: 1.0, a: 1.0 };
const LEFT_COLOUR: ColorRGBA = ColorRGBA { r: 0.12, g: 0.86, b: 0.24, a: 1.0 };
const RIGHT_COLOUR: ColorRGBA = ColorRGBA { r: 0.9, g: 0.12, b: 0.12, a: 1.0 };

/// `~/route/markers`: DELETEALL, the body path (blue line), the left (green) and right (red) soles
/// of each stance and a line joining them.
pub fn route_markers(route: &Route, stamp: &Time, frame_id: &str) -> MarkerArray {
    let header = header(stamp, frame_id);
    let identity = pose_from_isometry(&Isometry3::identity());
    let marker = |ns: &str, id: i32, type_: i32, scale: f64, color: ColorRGBA, points: Vec<Point>| Marker {
        header: header.clone(),
        ns: ns.into(),
        id,
        type_,
        pose: identity.clone(),
        scale: Vector3Msg { x: scale, y: scale, z: scale },
        color,
        points,
        ..Default::default()
    };
    let mut markers = vec![Marker { header: header.clone(), action: Marker::DELETEALL, ..Default::default() }];
    markers.push(marker("route_body", 0, Marker::LINE_STRIP, 0.006, PATH_COLOUR, route.body_path.iter().map(point_of).collect()));
    markers.push(marker(
        "route_left",
        1,
        Marker::SPHERE_LIST,
        0.03,
        LEFT_COLOUR,
        route.stances.iter().map(|s| point_of(&s.left)).collect(),
    ));
    markers.push(marker(
        "route_right",
        2,
        Marker::SPHERE_LIST,
        0.03,
        RIGHT_COLOUR,
        route.stances.iter().map(|s| point_of(&s.right)).collect(),
    ));
    let pairs = route.stances.iter().flat_map(|s| [point_of(&s.left), point_of(&s.right)]).collect();
    markers.push(marker("route_stances", 3, Marker::LINE_LIST, 0.003, ColorRGBA { r: 1.0, g: 1.0, b: 1.0, a: 1.0 }, pairs));
    MarkerArray { markers }
}

#[cfg(test)]
mod tests {
    use super::*;
    use patchwalk_route::{synthetic, Planner, Target};

    fn holds() -> Vec<ScoredHold> {
        let tilted = Vector3::new(0.0, 0.5, 1.0).normalize();
        vec![
            ScoredHold { position: Vector3::new(0.3, 0.1, 0.02), normal: Vector3::z(), from_surface: false, score: 0.9 },
            ScoredHold { position: Vector3::new(0.4, -0.1, 0.05), normal: tilted, from_surface: true, score: 0.5 },
        ]
    }

    #[test]
    fn poses_clouds_and_markers_carry_positions_normals_and_scores() {
        let stamp = Time { sec: 3, nanosec: 5 };
        let holds = holds();
        let array = pose_array(&holds, &stamp, "odom");
        assert_eq!((array.header.frame_id.as_str(), array.header.stamp.sec, array.poses.len()), ("odom", 3, 2));
        assert_eq!((array.poses[1].position.x, array.poses[1].position.z), (0.4, 0.05));
        // The pose's z axis is the normal.
        for (pose, hold) in array.poses.iter().zip(&holds) {
            let q = &pose.orientation;
            let rotation = UnitQuaternion::from_quaternion(nalgebra::Quaternion::new(q.w, q.x, q.y, q.z));
            assert!((rotation * Vector3::z() - hold.normal).norm() < 1e-9);
        }
        let cloud = scored_cloud(&holds, &stamp, "odom");
        assert_eq!((cloud.width, cloud.point_step, cloud.data.len()), (2, 16, 32));
        assert_eq!(cloud.fields[3].name, "score");
        let f = |i: usize| f32::from_le_bytes([cloud.data[i], cloud.data[i + 1], cloud.data[i + 2], cloud.data[i + 3]]);
        assert_eq!((f(0), f(12), f(28)), (0.3, 0.9, 0.5));
        let markers = hold_markers(&holds, &stamp, "odom");
        assert_eq!(markers.markers[0].action, Marker::DELETEALL);
        let spheres = &markers.markers[1];
        assert_eq!((spheres.points.len(), spheres.colors.len()), (2, 2));
        // Colour = score: the better hold is greener.
        assert!(spheres.colors[0].g > spheres.colors[0].r && spheres.colors[1].r == 1.0 && spheres.colors[1].g == 1.0);
        assert_eq!(markers.markers[2].points.len(), 4);
        assert_eq!(hold_markers(&[], &stamp, "odom").markers.len(), 1);
    }

    #[test]
    fn a_route_becomes_a_path_heading_along_it_and_its_markers() {
        let terrain = synthetic::Terrain::trench(Some(0.15));
        let route = Planner::rpbp()
            .unwrap()
            .plan(
                &terrain.grid(),
                &terrain.holds(0.03, 1),
                Some(Target { x: 0.15, y: -0.2, z: None }),
                Target { x: 1.05, y: -0.2, z: None },
            )
            .unwrap();
        let stamp = Time { sec: 1, nanosec: 0 };
        let path = route_path(&route, &stamp, "odom");
        assert_eq!(path.header.frame_id, "odom");
        assert_eq!(path.poses.len(), route.body_path.len());
        assert!(path.poses.iter().all(|p| p.header.frame_id == "odom"));
        let first = &path.poses[0].pose;
        let last = path.poses.last().unwrap();
        assert_eq!((first.position.x, first.position.y), (route.body_path[0][0], route.body_path[0][1]));
        assert!(last.pose.position.x > first.position.x + 0.5, "from the start to the goal");
        // Each pose heads toward the next vertex, z up.
        for (pose, pair) in path.poses.iter().zip(route.body_path.windows(2)) {
            let q = &pose.pose.orientation;
            let yaw = (2.0 * (q.w * q.z + q.x * q.y)).atan2(1.0 - 2.0 * (q.y * q.y + q.z * q.z));
            let (dx, dy) = (pair[1][0] - pair[0][0], pair[1][1] - pair[0][1]);
            if dx.hypot(dy) > 1e-9 {
                let off = (yaw - dy.atan2(dx) + std::f64::consts::PI).rem_euclid(std::f64::consts::TAU) - std::f64::consts::PI;
                assert!(off.abs() < 1e-9, "{yaw} vs {}", dy.atan2(dx));
            }
            assert!(q.x.abs() < 1e-12 && q.y.abs() < 1e-12, "z up");
        }
        let markers = route_markers(&route, &stamp, "odom");
        assert_eq!(markers.markers.len(), 5);
        assert_eq!(markers.markers[1].points.len(), route.body_path.len());
        assert_eq!((markers.markers[2].points.len(), markers.markers[3].points.len()), (route.stances.len(), route.stances.len()));
    }
}

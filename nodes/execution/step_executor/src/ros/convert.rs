//! Conversions between patchwalk_msgs / geometry_msgs and the step_executor library types
//! (patches by their minimal parameters; poses as `target_from_source` isometries).

use nalgebra::{Isometry3, Quaternion, Translation3, UnitQuaternion, Vector3};

use patchwalk_msgs::geometry_msgs::msg::{Point, Pose, Quaternion as QuaternionMsg};
use patchwalk_msgs::msg::Patch;
use patchwalk_msgs::sensor_msgs::msg::{PointCloud2, PointField};
use step_executor::patch::{BoundaryType, PatchGeometry, SurfaceType};

/// geometry_msgs/Pose → isometry (a zero quaternion is rejected).
pub fn isometry_from_pose(pose: &Pose) -> Result<Isometry3<f64>, String> {
    let q = &pose.orientation;
    let quaternion = Quaternion::new(q.w, q.x, q.y, q.z);
    let norm = quaternion.norm();
    if !(norm.is_finite() && norm > 1e-9) {
        return Err(format!("pose orientation {q:?} is not a rotation"));
    }
    let p = &pose.position;
    Ok(Isometry3::from_parts(Translation3::new(p.x, p.y, p.z), UnitQuaternion::from_quaternion(quaternion)))
}

/// Isometry → geometry_msgs/Pose.
pub fn pose_from_isometry(iso: &Isometry3<f64>) -> Pose {
    let q = iso.rotation.quaternion();
    Pose {
        position: Point { x: iso.translation.x, y: iso.translation.y, z: iso.translation.z },
        orientation: QuaternionMsg { x: q.i, y: q.j, z: q.k, w: q.w },
    }
}

/// Patch message → library patch (validated).
pub fn patch_from_msg(msg: &Patch) -> Result<PatchGeometry, String> {
    let surface = SurfaceType::from_u8(msg.surface).ok_or_else(|| format!("patch {}: unknown surface type {}", msg.id, msg.surface))?;
    let boundary =
        BoundaryType::from_u8(msg.boundary).ok_or_else(|| format!("patch {}: unknown boundary type {}", msg.id, msg.boundary))?;
    let patch =
        PatchGeometry { surface, boundary, d: msg.boundary_params.clone(), k: msg.curvatures.clone(), r: msg.rotation, c: msg.center };
    patch.validate().map_err(|e| format!("patch {}: {e}", msg.id))?;
    Ok(patch)
}

/// x, y, z of a `sensor_msgs/PointCloud2` with FLOAT32 x/y/z fields (little-endian), as the mapper
/// publishes its birds-eye cloud. A malformed cloud is an error naming what is wrong.
pub fn points_from_cloud(cloud: &PointCloud2) -> Result<Vec<Vector3<f64>>, String> {
    if cloud.is_bigendian {
        return Err("big-endian clouds are not supported".into());
    }
    let offset = |name: &str| -> Result<usize, String> {
        let field = cloud.fields.iter().find(|f| f.name == name).ok_or_else(|| format!("no field {name:?}"))?;
        if field.datatype != PointField::FLOAT32 {
            return Err(format!("field {name:?} has datatype {}, expected FLOAT32 (7)", field.datatype));
        }
        Ok(field.offset as usize)
    };
    let offsets = [offset("x")?, offset("y")?, offset("z")?];
    let step = cloud.point_step as usize;
    let count = (cloud.width as usize).saturating_mul(cloud.height as usize);
    if offsets.iter().any(|o| o + 4 > step) {
        return Err(format!("point_step {step} is smaller than the x/y/z fields"));
    }
    if cloud.data.len() < count.saturating_mul(step) {
        return Err(format!("{} data bytes for {count} points of {step} bytes", cloud.data.len()));
    }
    let read = |at: usize| cloud.data.get(at..at + 4).and_then(|b| b.try_into().ok()).map(|b: [u8; 4]| f64::from(f32::from_le_bytes(b)));
    Ok((0..count)
        .filter_map(|i| {
            let base = i * step;
            Some(Vector3::new(read(base + offsets[0])?, read(base + offsets[1])?, read(base + offsets[2])?))
        })
        .collect())
}

/// Library patch → Patch message (pose derived from r, c).
pub fn msg_from_patch(patch: &PatchGeometry) -> Patch {
    Patch {
        surface: patch.surface as u8,
        boundary: patch.boundary as u8,
        curvatures: patch.k.clone(),
        boundary_params: patch.d.clone(),
        rotation: patch.r,
        center: patch.c,
        pose: pose_from_isometry(&patch.pose()),
        ..Default::default()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A cloud laid out as patch_mapper publishes it (x, y, z FLOAT32, 12-byte points), plus
    /// malformed ones.
    #[test]
    fn clouds_decode_and_malformed_ones_are_errors() {
        let field = |name: &str, offset: u32| PointField { name: name.into(), offset, datatype: PointField::FLOAT32, count: 1 };
        let points = [[0.5f32, -1.0, 2.0], [0.25, 0.0, -3.5]];
        let cloud = PointCloud2 {
            height: 1,
            width: 2,
            fields: vec![field("x", 0), field("y", 4), field("z", 8)],
            point_step: 12,
            row_step: 24,
            data: points.iter().flatten().flat_map(|v| v.to_le_bytes()).collect(),
            is_dense: true,
            ..Default::default()
        };
        let decoded = points_from_cloud(&cloud).unwrap();
        assert_eq!(decoded, vec![Vector3::new(0.5, -1.0, 2.0), Vector3::new(0.25, 0.0, -3.5)]);
        let short = PointCloud2 { data: cloud.data[..20].to_vec(), ..cloud.clone() };
        assert!(points_from_cloud(&short).unwrap_err().contains("data bytes"));
        let no_z = PointCloud2 { fields: cloud.fields[..2].to_vec(), ..cloud.clone() };
        assert!(points_from_cloud(&no_z).unwrap_err().contains("\"z\""));
        let mut doubles = cloud.clone();
        doubles.fields[1].datatype = PointField::FLOAT64;
        assert!(points_from_cloud(&doubles).unwrap_err().contains("FLOAT32"));
        let narrow = PointCloud2 { point_step: 8, ..cloud.clone() };
        assert!(points_from_cloud(&narrow).unwrap_err().contains("point_step"));
        assert!(points_from_cloud(&PointCloud2 { is_bigendian: true, ..cloud }).is_err());
    }

    #[test]
    fn patch_and_pose_round_trip() {
        let patch = PatchGeometry {
            surface: SurfaceType::CylindricParaboloid,
            boundary: BoundaryType::Rectangle,
            d: vec![0.03, 0.02],
            k: vec![7.0],
            r: [0.1, -0.2, 0.3],
            c: [0.2, 0.0, -0.3],
        };
        let msg = msg_from_patch(&patch);
        assert_eq!(patch_from_msg(&msg).unwrap(), patch);
        let iso = isometry_from_pose(&msg.pose).unwrap();
        assert!((iso.translation.vector - nalgebra::Vector3::from(patch.c)).norm() < 1e-12);
        assert!((iso.rotation.scaled_axis() - nalgebra::Vector3::from(patch.r)).norm() < 1e-12);
        let bad = Patch { surface: 9, ..msg.clone() };
        assert!(patch_from_msg(&bad).unwrap_err().contains("surface"));
        let mut zero = msg.pose.clone();
        zero.orientation = QuaternionMsg { x: 0.0, y: 0.0, z: 0.0, w: 0.0 };
        assert!(isometry_from_pose(&zero).is_err());
    }
}

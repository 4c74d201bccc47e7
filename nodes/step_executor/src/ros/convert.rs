//! Conversions between patchwalk_msgs / geometry_msgs and the step_executor library types
//! (patches by their minimal parameters; poses as `target_from_source` isometries).

use nalgebra::{Isometry3, Quaternion, Translation3, UnitQuaternion};

use patchwalk_msgs::geometry_msgs::msg::{Point, Pose, Quaternion as QuaternionMsg};
use patchwalk_msgs::msg::Patch;
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
    let boundary = BoundaryType::from_u8(msg.boundary).ok_or_else(|| format!("patch {}: unknown boundary type {}", msg.id, msg.boundary))?;
    let patch = PatchGeometry {
        surface,
        boundary,
        d: msg.boundary_params.clone(),
        k: msg.curvatures.clone(),
        r: msg.rotation,
        c: msg.center,
    };
    patch.validate().map_err(|e| format!("patch {}: {e}", msg.id))?;
    Ok(patch)
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

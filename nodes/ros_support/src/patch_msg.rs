//! The Surface Patch Library's [`Patch`] on the wire: conversion to and from
//! `patchwalk_msgs/Patch`, and between `geometry_msgs/Pose` and isometries. Incoming patches are
//! validated where they enter (type constants, parameter counts, finiteness, covariance size), with
//! an error naming the field.

use nalgebra::{DMatrix, Isometry3, Quaternion, Translation3, UnitQuaternion, Vector2, Vector3};
use patchwalk_msgs::builtin_interfaces::msg::Time;
use patchwalk_msgs::geometry_msgs::msg::{Point, Pose, Quaternion as QuaternionMsg};
use patchwalk_msgs::msg;
use patchwalk_spl::patch::{BoundaryType, Patch, PatchError, SurfaceType};

/// Why a `patchwalk_msgs/Patch` or a pose cannot be used.
#[derive(Debug, PartialEq, thiserror::Error)]
pub enum PatchMsgError {
    #[error("patch {id}: unknown surface type {value}")]
    Surface { id: u32, value: u8 },
    #[error("patch {id}: unknown boundary type {value}")]
    Boundary { id: u32, value: u8 },
    #[error("patch {id}: curvatures: {surface:?} has {expected} curvature parameters, got {got}")]
    Curvatures { id: u32, surface: SurfaceType, expected: usize, got: usize },
    #[error("patch {id}: covariance: expected 0 or {expected} values ({p}×{p}), got {got}")]
    Covariance { id: u32, p: usize, expected: usize, got: usize },
    #[error("patch {id}: {field} is not finite")]
    NotFinite { id: u32, field: &'static str },
    #[error("patch {id}: {source}")]
    Patch { id: u32, source: PatchError },
    #[error("pose orientation {0:?} is not a rotation (zero or non-finite quaternion)")]
    Orientation([f64; 4]),
    #[error("pose position {0:?} is not finite")]
    Position([f64; 3]),
}

/// Surface type of a `Patch.msg` constant.
pub fn surface_from_u8(value: u8) -> Option<SurfaceType> {
    SurfaceType::ALL.iter().copied().find(|s| *s as u8 == value)
}

/// Boundary type of a `Patch.msg` constant.
pub fn boundary_from_u8(value: u8) -> Option<BoundaryType> {
    BoundaryType::ALL.into_iter().find(|b| *b as u8 == value)
}

/// `geometry_msgs/Pose` → isometry (the quaternion normalised; zero or non-finite is an error).
pub fn isometry_from_pose(pose: &Pose) -> Result<Isometry3<f64>, PatchMsgError> {
    let q = &pose.orientation;
    let quaternion = Quaternion::new(q.w, q.x, q.y, q.z);
    let norm = quaternion.norm();
    if !(norm.is_finite() && norm > 1e-9) {
        return Err(PatchMsgError::Orientation([q.x, q.y, q.z, q.w]));
    }
    let p = &pose.position;
    if !(p.x.is_finite() && p.y.is_finite() && p.z.is_finite()) {
        return Err(PatchMsgError::Position([p.x, p.y, p.z]));
    }
    Ok(Isometry3::from_parts(Translation3::new(p.x, p.y, p.z), UnitQuaternion::from_quaternion(quaternion)))
}

/// Isometry → `geometry_msgs/Pose`.
pub fn pose_from_isometry(iso: &Isometry3<f64>) -> Pose {
    let q = iso.rotation.quaternion();
    Pose {
        position: Point { x: iso.translation.x, y: iso.translation.y, z: iso.translation.z },
        orientation: QuaternionMsg { x: q.i, y: q.j, z: q.k, w: q.w },
    }
}

/// A patch as `patchwalk_msgs/Patch`: the minimal parameters, the same pose as
/// `geometry_msgs/Pose`, the covariance row-major over the minimal parameter vector.
pub fn msg_from_patch(id: u32, patch: &Patch, first_seen: Time, last_seen: Time) -> msg::Patch {
    let p = patch.covariance.nrows();
    let covariance = (0..p).flat_map(|r| (0..p).map(move |c| (r, c))).map(|(r, c)| patch.covariance[(r, c)]).collect();
    msg::Patch {
        id,
        surface: patch.surface as u8,
        boundary: patch.boundary as u8,
        curvatures: patch.curvature_params(),
        boundary_params: patch.boundary_params.clone(),
        rotation: patch.rotation.into(),
        center: patch.center.into(),
        pose: pose_from_isometry(&patch.world_from_patch()),
        covariance,
        residual: patch.residual,
        num_points: patch.num_points.try_into().unwrap_or(u32::MAX),
        first_seen,
        last_seen,
    }
}

/// `patchwalk_msgs/Patch` → patch, validated (the pose is rebuilt from `rotation` and `center`).
pub fn patch_from_msg(m: &msg::Patch) -> Result<Patch, PatchMsgError> {
    let id = m.id;
    let surface = surface_from_u8(m.surface).ok_or(PatchMsgError::Surface { id, value: m.surface })?;
    let boundary = boundary_from_u8(m.boundary).ok_or(PatchMsgError::Boundary { id, value: m.boundary })?;
    let curvatures = match (surface.num_curvatures(), m.curvatures.as_slice()) {
        (0, []) => Vector2::zeros(),
        (1, [kappa]) => Vector2::new(*kappa, *kappa),
        (2, [kx, ky]) => Vector2::new(*kx, *ky),
        (expected, got) => return Err(PatchMsgError::Curvatures { id, surface, expected, got: got.len() }),
    };
    let mut patch =
        Patch::new(surface, boundary, m.boundary_params.clone(), curvatures, Vector3::from(m.rotation), Vector3::from(m.center))
            .map_err(|source| PatchMsgError::Patch { id, source })?;
    let p = patch.dof();
    match m.covariance.len() {
        0 => {}
        n if n == p * p => {
            if m.covariance.iter().any(|v| !v.is_finite()) {
                return Err(PatchMsgError::NotFinite { id, field: "covariance" });
            }
            patch.covariance = DMatrix::from_row_slice(p, p, &m.covariance);
        }
        got => return Err(PatchMsgError::Covariance { id, p, expected: p * p, got }),
    }
    if !m.residual.is_finite() {
        return Err(PatchMsgError::NotFinite { id, field: "residual" });
    }
    patch.residual = m.residual;
    patch.num_points = m.num_points as usize;
    Ok(patch)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn cylinder() -> Patch {
        let mut patch = Patch::new(
            SurfaceType::CylindricParaboloid,
            BoundaryType::Rectangle,
            vec![0.04, 0.02],
            Vector2::new(0.0, -12.0),
            Vector3::new(0.3, -0.2, 1.1),
            Vector3::new(0.1, 0.0, -0.28),
        )
        .unwrap();
        let p = patch.dof();
        patch.covariance = DMatrix::from_fn(p, p, |r, c| if r == c { 1e-4 * (r + 1) as f64 } else { 1e-6 });
        patch.residual = 0.002;
        patch.num_points = 321;
        patch
    }

    #[test]
    fn every_type_round_trips_through_the_message() {
        for surface in SurfaceType::ALL {
            for boundary in BoundaryType::ALL {
                let d = match boundary {
                    BoundaryType::Circle => vec![0.03],
                    BoundaryType::Quadrilateral => vec![0.03, 0.02, 0.03, 0.02, 1.0],
                    _ => vec![0.03, 0.02],
                };
                let Ok(patch) =
                    Patch::new(surface, boundary, d, Vector2::new(5.0, -3.0), Vector3::new(0.1, 0.2, 0.3), Vector3::new(1.0, 2.0, 3.0))
                else {
                    continue; // not one of the 10 types
                };
                let back = patch_from_msg(&msg_from_patch(7, &patch, Time::default(), Time::default())).unwrap();
                assert_eq!(back, patch, "{surface:?}/{boundary:?}");
            }
        }
        let patch = cylinder();
        let m = msg_from_patch(3, &patch, Time::default(), Time::default());
        assert_eq!(m.curvatures, vec![-12.0]);
        assert_eq!(patch_from_msg(&m).unwrap(), patch);
        let pose = isometry_from_pose(&m.pose).unwrap();
        assert!((pose.translation.vector - patch.center).norm() < 1e-12);
    }

    #[test]
    fn malformed_messages_name_the_field() {
        let good = msg_from_patch(9, &cylinder(), Time::default(), Time::default());
        let mut m = good.clone();
        m.surface = 42;
        assert!(matches!(patch_from_msg(&m), Err(PatchMsgError::Surface { id: 9, value: 42 })));
        let mut m = good.clone();
        m.boundary = 7;
        assert!(matches!(patch_from_msg(&m), Err(PatchMsgError::Boundary { .. })));
        let mut m = good.clone();
        m.curvatures = vec![1.0, 2.0];
        assert!(patch_from_msg(&m).unwrap_err().to_string().contains("curvatures"));
        let mut m = good.clone();
        m.covariance.pop();
        assert!(patch_from_msg(&m).unwrap_err().to_string().contains("covariance"));
        let mut m = good.clone();
        m.center[1] = f64::NAN;
        assert!(matches!(patch_from_msg(&m), Err(PatchMsgError::Patch { .. })));
        let mut m = good.clone();
        m.covariance[0] = f64::INFINITY;
        assert!(patch_from_msg(&m).unwrap_err().to_string().contains("covariance is not finite"));
        let mut m = good;
        m.boundary_params = vec![0.03];
        assert!(patch_from_msg(&m).unwrap_err().to_string().contains("boundary_params"));
        let mut pose = Pose::default();
        pose.orientation.w = 0.0;
        assert!(isometry_from_pose(&pose).is_err());
        pose.orientation.w = 1.0;
        pose.position.x = f64::NAN;
        assert!(isometry_from_pose(&pose).is_err());
    }
}

//! Trajectory evaluation against ground truth (TUM RGB-D benchmark metrics, as J 5 reports them):
//! the rigid alignment of an estimated trajectory to the reference (Horn/Kabsch), the absolute
//! trajectory error (RMSE of the aligned positions) and the relative pose errors between consecutive
//! poses.

use nalgebra::{Isometry3, Matrix3, Point3, Translation3, UnitQuaternion, Vector3};

/// Rigid transform `reference_from_estimate` minimising Σ‖R e + t − r‖² (Horn / Kabsch via SVD).
pub fn align_rigid(estimate: &[Vector3<f64>], reference: &[Vector3<f64>]) -> Option<Isometry3<f64>> {
    if estimate.len() != reference.len() || estimate.len() < 3 {
        return None;
    }
    let n = estimate.len() as f64;
    let mean_e: Vector3<f64> = estimate.iter().sum::<Vector3<f64>>() / n;
    let mean_r: Vector3<f64> = reference.iter().sum::<Vector3<f64>>() / n;
    let mut covariance = Matrix3::zeros();
    for (e, r) in estimate.iter().zip(reference) {
        covariance += (r - mean_r) * (e - mean_e).transpose();
    }
    let rotation = patchwalk_spl::geometry::nearest_rotation(&covariance)?;
    let translation = mean_r - rotation * mean_e;
    Some(Isometry3::from_parts(Translation3::from(translation), UnitQuaternion::from_rotation_matrix(&rotation)))
}

/// Absolute trajectory error (RMSE of positions after rigid alignment) of matched pose pairs.
pub fn absolute_trajectory_rmse(estimate: &[Isometry3<f64>], reference: &[Isometry3<f64>]) -> Option<f64> {
    let e: Vec<Vector3<f64>> = estimate.iter().map(|p| p.translation.vector).collect();
    let r: Vec<Vector3<f64>> = reference.iter().map(|p| p.translation.vector).collect();
    let alignment = align_rigid(&e, &r)?;
    let sum: f64 = e.iter().zip(&r).map(|(e, r)| (alignment * Point3::from(*e) - Point3::from(*r)).norm_squared()).sum();
    Some((sum / e.len() as f64).sqrt())
}

/// Relative pose errors between consecutive matched poses: (translation m, rotation deg) per pair.
pub fn relative_pose_errors(estimate: &[Isometry3<f64>], reference: &[Isometry3<f64>]) -> Vec<(f64, f64)> {
    estimate
        .windows(2)
        .zip(reference.windows(2))
        .filter_map(|(e, r)| {
            let (e0, e1, r0, r1) = (e.first()?, e.get(1)?, r.first()?, r.get(1)?);
            let error = (r0.inverse() * r1).inverse() * (e0.inverse() * e1);
            Some((error.translation.vector.norm(), error.rotation.angle().to_degrees()))
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn alignment_recovers_a_known_transform() {
        let truth = Isometry3::new(Vector3::new(0.3, -1.0, 2.0), Vector3::new(0.1, -0.4, 0.9));
        let points: Vec<Vector3<f64>> = (0..10).map(|i| Vector3::new(i as f64, (i * i) as f64 * 0.1, (i as f64).sin())).collect();
        let moved: Vec<Vector3<f64>> = points.iter().map(|p| (truth * Point3::from(*p)).coords).collect();
        let found = align_rigid(&points, &moved).unwrap();
        assert!((found.to_homogeneous() - truth.to_homogeneous()).norm() < 1e-9);
        assert!(align_rigid(&points[..2], &moved[..2]).is_none());
        let poses: Vec<Isometry3<f64>> = points.iter().map(|p| Isometry3::translation(p.x, p.y, p.z)).collect();
        let moved_poses: Vec<Isometry3<f64>> = poses.iter().map(|p| truth * p).collect();
        assert!(absolute_trajectory_rmse(&poses, &moved_poses).unwrap() < 1e-9);
    }
}

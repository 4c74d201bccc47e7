//! Moving a patch with its uncertainty: a rigid transform of the pose and first-order propagation
//! of the covariance over the minimal parameter vector (IROS III: Σ travels with the patch).

use nalgebra::{DMatrix, Isometry3, Vector3};

use crate::geometry::{log_map, r_xy_from_normal};
use crate::patch::Patch;

/// A patch moved by the rigid transform `target_from_source`: centre `c' = T c`, rotation
/// `R' = R_T R(r)` (for 5-DoF types only the normal is kept, `r_z = 0`), and the covariance
/// propagated to first order, `Σ' = J Σ Jᵀ`, with `J = ∂p'/∂p` by central differences over the
/// minimal parameter vector. `None` if the patch cannot be rebuilt (non-finite input).
pub fn transform_patch(patch: &Patch, target_from_source: &Isometry3<f64>) -> Option<Patch> {
    let moved = move_params(patch, &patch.params().iter().copied().collect::<Vec<_>>(), target_from_source)?;
    let p = patch.dof();
    if patch.covariance.nrows() != p || patch.covariance.iter().all(|&v| v == 0.0) {
        return Some(Patch { covariance: DMatrix::zeros(p, p), ..moved });
    }
    let base: Vec<f64> = patch.params().iter().copied().collect();
    let moved_params = moved.params();
    let mut jacobian = DMatrix::zeros(moved_params.len(), p);
    for j in 0..p {
        let step = 1e-6 * base[j].abs().max(1e-3);
        let mut plus = base.clone();
        let mut minus = base.clone();
        plus[j] += step;
        minus[j] -= step;
        let (Some(a), Some(b)) = (move_params(patch, &plus, target_from_source), move_params(patch, &minus, target_from_source)) else {
            return Some(Patch { covariance: DMatrix::zeros(p, p), ..moved });
        };
        let column = (a.params() - b.params()) / (2.0 * step);
        jacobian.set_column(j, &column);
    }
    let covariance = &jacobian * &patch.covariance * jacobian.transpose();
    Some(Patch { covariance, ..moved })
}

/// The patch of the same type built from parameters `params`, moved by `target_from_source`.
fn move_params(patch: &Patch, params: &[f64], target_from_source: &Isometry3<f64>) -> Option<Patch> {
    let source = Patch::from_params(patch.surface, patch.boundary, params).ok()?;
    let rotation = target_from_source.rotation.to_rotation_matrix().into_inner() * source.rotation_matrix();
    let r = if source.is_5dof() {
        let n = rotation.column(2).into_owned();
        let xy = r_xy_from_normal(&n);
        Vector3::new(xy.x, xy.y, 0.0)
    } else {
        log_map(&rotation)
    };
    let center = (target_from_source * nalgebra::Point3::from(source.center)).coords;
    let mut moved = Patch::new(source.surface, source.boundary, source.boundary_params, source.curvatures, r, center).ok()?;
    moved.residual = patch.residual;
    moved.num_points = patch.num_points;
    Some(moved)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::patch::{BoundaryType, SurfaceType};
    use nalgebra::{Translation3, UnitQuaternion, Vector2};

    fn plane_at(center: Vector3<f64>) -> Patch {
        Patch::new(SurfaceType::Plane, BoundaryType::Ellipse, vec![0.05, 0.03], Vector2::zeros(), Vector3::new(0.1, -0.2, 0.3), center)
            .unwrap()
    }

    #[test]
    fn transform_moves_poses_and_propagates_covariance() {
        let mut patch = plane_at(Vector3::new(0.3, 0.2, 1.0));
        let p = patch.dof();
        patch.covariance = DMatrix::from_fn(p, p, |r, c| if r == c { 1e-4 * (r + 1) as f64 } else { 0.0 });
        let t = Isometry3::from_parts(Translation3::new(0.5, -1.0, 2.0), UnitQuaternion::from_euler_angles(0.3, -0.5, 1.2));
        let moved = transform_patch(&patch, &t).unwrap();
        // Every point of the patch moves rigidly.
        for u in [Vector2::new(0.0, 0.0), Vector2::new(0.03, -0.01)] {
            let before = patch.explicit_world(&u).unwrap();
            let after = moved.explicit_world(&u).unwrap();
            assert!(((t * nalgebra::Point3::from(before)).coords - after).norm() < 1e-9);
        }
        // Covariance: same size, symmetric, PSD, centre block rotated (trace preserved).
        assert_eq!(moved.covariance.shape(), (p, p));
        let centre = |c: &DMatrix<f64>| c.view((p - 3, p - 3), (3, 3)).trace();
        assert!((centre(&moved.covariance) - centre(&patch.covariance)).abs() < 1e-9);
        assert!((moved.covariance.clone() - moved.covariance.transpose()).norm() < 1e-12);
        // Round trip.
        let back = transform_patch(&moved, &t.inverse()).unwrap();
        assert!((back.center - patch.center).norm() < 1e-9);
        assert!((back.covariance - &patch.covariance).norm() < 1e-8);
    }
}

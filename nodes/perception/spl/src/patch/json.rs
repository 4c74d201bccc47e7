//! The JSON form of a [`Patch`]: the serde proxy through which `Patch` is serialized (names of the
//! types, curvatures, boundary parameters, rotation, centre, the derived minimal parameter vector,
//! covariance rows, residual, point count) and checked when read back.

use super::{BoundaryType, Patch, PatchError, SurfaceType};
use nalgebra::{DMatrix, Vector2, Vector3};
use serde::{Deserialize, Serialize};

/// JSON form of a patch (the patch fields of every CLI's patch record).
#[derive(Clone, Debug, Serialize, Deserialize)]
pub(super) struct PatchJson {
    /// Surface type name.
    pub surface: SurfaceType,
    /// Boundary type name.
    pub boundary: BoundaryType,
    /// `[κx, κy]`.
    pub curvatures: [f64; 2],
    /// Boundary parameters `d`.
    pub boundary_params: Vec<f64>,
    /// Orientation vector `[rx, ry, rz]`.
    pub rotation: [f64; 3],
    /// Centre `[x, y, z]`.
    pub center: [f64; 3],
    /// Minimal parameter vector (derived; ignored when reading).
    #[serde(default)]
    pub params: Vec<f64>,
    /// Covariance rows (p × p over `params`); empty means zero.
    #[serde(default)]
    pub covariance: Vec<Vec<f64>>,
    /// RMS residual of the fit points (m).
    #[serde(default)]
    pub residual: f64,
    /// Number of fit points.
    #[serde(default)]
    pub num_points: usize,
}

impl From<Patch> for PatchJson {
    fn from(p: Patch) -> Self {
        let rows = p.covariance.nrows();
        PatchJson {
            surface: p.surface,
            boundary: p.boundary,
            curvatures: [p.curvatures.x, p.curvatures.y],
            params: p.params().iter().copied().collect(),
            boundary_params: p.boundary_params,
            rotation: [p.rotation.x, p.rotation.y, p.rotation.z],
            center: [p.center.x, p.center.y, p.center.z],
            covariance: (0..rows).map(|i| p.covariance.row(i).iter().copied().collect()).collect(),
            residual: p.residual,
            num_points: p.num_points,
        }
    }
}

impl TryFrom<PatchJson> for Patch {
    type Error = PatchError;

    fn try_from(j: PatchJson) -> Result<Self, Self::Error> {
        let mut patch = Patch::new(
            j.surface,
            j.boundary,
            j.boundary_params,
            Vector2::new(j.curvatures[0], j.curvatures[1]),
            Vector3::from(j.rotation),
            Vector3::from(j.center),
        )?;
        let p = patch.dof();
        if !j.covariance.is_empty() {
            if j.covariance.len() != p || j.covariance.iter().any(|row| row.len() != p) {
                return Err(PatchError::WrongLength { what: "covariance rows", expected: p, got: j.covariance.len() });
            }
            patch.covariance = DMatrix::from_fn(p, p, |r, c| j.covariance.get(r).and_then(|row| row.get(c)).copied().unwrap_or(0.0));
        }
        patch.residual = j.residual;
        patch.num_points = j.num_points;
        Ok(patch)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::patch::tests::example;

    #[test]
    fn json_round_trip() {
        let mut p = example(SurfaceType::CircularCylinder, BoundaryType::Rectangle);
        p.covariance = DMatrix::identity(9, 9) * 1e-4;
        let s = serde_json::to_string(&p).unwrap();
        assert!(s.contains("\"surface\":\"circular_cylinder\"") && s.contains("\"boundary\":\"rect\""));
        let back: Patch = serde_json::from_str(&s).unwrap();
        assert_eq!(back, p);
        let bad = s.replace("\"rect\"", "\"circle\"");
        assert!(serde_json::from_str::<Patch>(&bad).is_err());
    }
}
